//! Station configuration: a TOML file (`--config station.toml`) whose every key can also be given on
//! the command line (the CLI's named flags, or `--set section.key=VALUE` for any key). Parsed into
//! plain structs (unknown keys are errors naming the key), then validated into [`StationConfig`]
//! with units in the names. `fixtures/station.toml` is the commented example.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::calib::{Fix, Loss, SolveOptions};
use crate::camera::{Camera, DistortionModel};
use crate::render::{Palette, RenderSettings};

/// A configuration problem, naming the key (`qa.max_rms_px`) or the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read station config {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{origin}: {message}")]
    Syntax { origin: String, message: String },
    #[error("{origin}: {key}: {message}")]
    Invalid {
        origin: String,
        key: String,
        message: String,
    },
}

impl ConfigError {
    pub fn exit_code(&self) -> u8 {
        crate::exit::BAD_INPUT
    }
}

/// Where frames come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SourceKind {
    /// The built-in renderer: a known camera in front of the turntable (the default; no hardware).
    Synthetic,
    /// A V4L2 camera (`camera.device`).
    Device,
    /// A recorded session (`camera.replay`).
    Replay,
    /// Photos a user already took (`camera.images`).
    Images,
}

/// What turns the rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TurntableKind {
    Grbl,
    Zaber,
    SimGrbl,
    SimZaber,
    Manual,
    None,
}

/// `[camera]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraSection {
    pub source: SourceKind,
    pub device: Option<PathBuf>,
    pub replay: Option<PathBuf>,
    pub images: Vec<PathBuf>,
    /// Requested capture size and FourCC for a V4L2 device.
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub fourcc: Option<String>,
    /// The identity profiles are stored under for synthetic and image runs (a V4L2 camera's comes
    /// from the device: USB vendor:product:serial).
    pub device_id: Option<String>,
    /// Frames grabbed per pose (≥ 2 enables the motion check: consecutive frames must agree).
    pub frames_per_pose: u32,
    pub grab_timeout_ms: u64,
}

impl Default for CameraSection {
    fn default() -> Self {
        CameraSection {
            source: SourceKind::Synthetic,
            device: None,
            replay: None,
            images: Vec::new(),
            width: None,
            height: None,
            fourcc: None,
            device_id: None,
            frames_per_pose: 2,
            grab_timeout_ms: 3000,
        }
    }
}

/// `[turntable]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TurntableSection {
    pub kind: TurntableKind,
    pub port: Option<String>,
    /// Time to wait after the stage reports it has settled (vibration), before flushing frames.
    pub settle_ms: u64,
    /// GRBL: degrees per unit; Zaber: microsteps per degree.
    pub degrees_per_unit: f64,
    pub microsteps_per_degree: f64,
    pub move_timeout_s: u64,
    /// Longest wait for one reply of a serial turntable (raise it for slow links or emulation).
    pub reply_timeout_ms: u64,
    /// The stage has a tilt axis (a cradle under the table): the simulators then run a second
    /// simulator for it; real hardware needs `tilt_port`. Unset: the simulators have one (they
    /// show the whole station), hardware has one when `tilt_port` is set, a manual table has none
    /// ([`TurntableSection::has_tilt`]).
    pub tilt: Option<bool>,
    /// Serial port of the tilt axis's driver (a second GRBL board or Zaber device, same protocol as
    /// `kind`).
    pub tilt_port: Option<String>,
    /// Tilt limits (degrees); homing leaves the cradle at 0°.
    pub tilt_min_deg: f64,
    pub tilt_max_deg: f64,
    /// Horizontal distance (mm) of the rig's centre in front of the rotation axis (toward the
    /// camera at 0°); turning swings it across the image ([`crate::render::StageGeometry`]).
    pub rig_offset_mm: f64,
    /// Height (mm) of the rig's centre above the tilt axis; tilting swings it up and down the image.
    pub tilt_pivot_mm: f64,
}

impl Default for TurntableSection {
    fn default() -> Self {
        TurntableSection {
            kind: TurntableKind::SimGrbl,
            port: None,
            settle_ms: 0,
            degrees_per_unit: 0.5,
            microsteps_per_degree: crate::turntable::zaber::X_RSW60A_MICROSTEPS_PER_DEGREE,
            move_timeout_s: 60,
            reply_timeout_ms: crate::turntable::DEFAULT_EXCHANGE_TIMEOUT.as_millis() as u64,
            tilt: None,
            tilt_port: None,
            tilt_min_deg: -30.0,
            tilt_max_deg: 30.0,
            rig_offset_mm: 300.0,
            tilt_pivot_mm: 300.0,
        }
    }
}

impl TurntableSection {
    /// Whether the stage has a tilt axis: `tilt` when set, else the simulators do, hardware does
    /// when `tilt_port` names the tilt driver, and a manual table does not.
    pub fn has_tilt(&self) -> bool {
        self.tilt.unwrap_or(match self.kind {
            TurntableKind::SimGrbl | TurntableKind::SimZaber => true,
            TurntableKind::Grbl | TurntableKind::Zaber => self.tilt_port.is_some(),
            TurntableKind::Manual | TurntableKind::None => false,
        })
    }

    /// Where the rig sits on the stage's axes.
    pub fn geometry(&self) -> crate::render::StageGeometry {
        crate::render::StageGeometry {
            rig_offset_mm: self.rig_offset_mm,
            tilt_pivot_mm: self.tilt_pivot_mm,
        }
    }
}

/// `[plan]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlanSection {
    /// Number of poses (turntable, manual and synthetic runs).
    pub poses: usize,
    /// Turntable sweep centred on 0° (degrees).
    pub sweep_deg: f64,
    /// Views kept out of the fit and checked against it (the last accepted views).
    pub held_out: usize,
    /// Stop before the plan is exhausted once coverage and the σ targets are met.
    pub stop_when_sufficient: bool,
    /// The σ targets of `stop_when_sufficient` and of the planner.
    pub target_sigma_fx_rel: f64,
    pub target_sigma_cx_px: f64,
    /// How a moving stage's poses are chosen: `predicted` (each next pose the one whose predicted
    /// covariance best meets the σ targets, [`crate::station::plan`]) or `sweep` (a uniform grid
    /// over rotation × tilt, row by row).
    pub planner: PlannerKind,
    /// Spacing of the candidate grid (degrees).
    pub step_deg: f64,
}

/// `plan.planner`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PlannerKind {
    Predicted,
    Sweep,
}

impl Default for PlanSection {
    fn default() -> Self {
        PlanSection {
            poses: 12,
            sweep_deg: 60.0,
            held_out: 1,
            stop_when_sufficient: false,
            target_sigma_fx_rel: 2e-4,
            target_sigma_cx_px: 0.5,
            planner: PlannerKind::Predicted,
            step_deg: 10.0,
        }
    }
}

/// `[synthetic]`: the known camera and render effects of the synthetic source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyntheticSection {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
    pub blur: f64,
    pub noise: f64,
    pub gamma: f64,
    pub vignetting: f64,
    pub black: f64,
    pub white: f64,
    pub seed: u64,
    pub supersample: u32,
}

impl Default for SyntheticSection {
    fn default() -> Self {
        SyntheticSection {
            width: 1280,
            height: 960,
            fx: 1100.0,
            fy: 1100.0,
            cx: None,
            cy: None,
            k1: -0.2,
            k2: 0.05,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
            blur: 1.0,
            noise: 2.0,
            gamma: 1.0,
            vignetting: 0.0,
            black: 0.06,
            white: 0.88,
            seed: 1,
            supersample: 4,
        }
    }
}

impl SyntheticSection {
    pub fn camera(&self) -> Camera {
        let cx = self.cx.unwrap_or((f64::from(self.width) - 1.0) / 2.0);
        let cy = self.cy.unwrap_or((f64::from(self.height) - 1.0) / 2.0);
        Camera::pinhole([self.width, self.height], self.fx, self.fy, cx, cy).with_distortion(
            DistortionModel::Brown5,
            &[self.k1, self.k2, self.p1, self.p2, self.k3],
        )
    }

    pub fn settings(&self) -> RenderSettings {
        RenderSettings {
            supersample: self.supersample,
            blur_sigma_px: self.blur,
            noise_sigma: self.noise,
            gamma: self.gamma,
            vignetting: self.vignetting,
            seed: self.seed,
            shading: true,
            palette: Palette {
                black: self.black,
                white: self.white,
                ..Palette::default()
            },
        }
    }
}

/// `[solve]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolveSection {
    /// `pinhole`, `brown5`, `brown8` or `kb4`.
    pub model: String,
    /// Parameters held fixed: `aspect`, `principal-point`, `tangential`, `k3`.
    pub fix: Vec<String>,
    /// Robust loss `huber:C` / `cauchy:C` (px), or `none`.
    pub loss: String,
    /// Fix k3 (the fisheye's k4: the highest radial term) at 0 (and say so) when the data leave it
    /// undetermined: within 2σ of 0 while 1σ moves the image border by over a pixel
    /// ([`crate::calib::insignificant_at_border`]).
    pub fix_undetermined_k3: bool,
    /// `equal` (every corner alike, but for the few the detector rates much worse than the median,
    /// such as a grazing face's: [`crate::calib::Weighting::Equal`]) or `covariance` (each corner by
    /// the inverse of its own fit's covariance, [`crate::calib::Weighting`]). `equal` by default while the detector's noise-free
    /// bias is as large as its noise: on the synthetic station the covariance-weighted σ are then
    /// smaller but miss that bias (χ² of fx, fy, cx, cy against the truth 34 / 16 / 24 against
    /// 17 / 7.5 / 10 equally weighted, seeds 1–3, `examples/station_chi2.rs`; issue 29).
    pub weighting: String,
    /// Refine the rig's faces jointly with the camera ([`crate::calib::solve_rig`]): a hand-built
    /// cube's boards sit a millimetre off and tilted a fraction of a degree, which the plain solve
    /// takes for lens and pose. The refined faces are noted in the result; when the views cannot
    /// place a face the run keeps the rig file's faces and says why.
    pub refine_rig: bool,
}

impl Default for SolveSection {
    fn default() -> Self {
        SolveSection {
            model: "brown5".into(),
            fix: Vec::new(),
            loss: "huber:1".into(),
            fix_undetermined_k3: true,
            weighting: "equal".into(),
            refine_rig: false,
        }
    }
}

/// `[qa]`: the verdict's thresholds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QaSection {
    pub min_views: usize,
    pub max_rms_px: f64,
    pub max_residual_px: f64,
    /// Fraction of the image's coverage grid cells holding accepted corners.
    pub min_coverage: f64,
    pub coverage_grid: [usize; 2],
    pub max_sigma_fx_rel: f64,
    pub max_sigma_cx_px: f64,
    /// Held-out RMS may be at most this many times the fit's RMS (plus `held_out_floor_px`).
    pub max_held_out_ratio: f64,
    pub held_out_floor_px: f64,
    /// A view whose estimated blur σ exceeds this is rejected (px).
    pub max_blur_px: f64,
    /// A view whose consecutive frames differ in more than this fraction of blocks is rejected.
    pub max_motion: f64,
    /// Fewest labelled corners for a view to be used.
    pub min_corners: usize,
    /// A new profile that moves a parameter by more than this many σ from the camera's previous
    /// profile is noted (a bumped lens, a wrong camera on the station).
    pub max_jump_sigma: f64,
}

impl Default for QaSection {
    fn default() -> Self {
        QaSection {
            min_views: 6,
            max_rms_px: 0.3,
            max_residual_px: 2.0,
            min_coverage: 0.25,
            coverage_grid: [8, 6],
            max_sigma_fx_rel: 1e-3,
            max_sigma_cx_px: 2.0,
            max_held_out_ratio: 2.0,
            held_out_floor_px: 0.02,
            max_blur_px: 3.0,
            max_motion: 0.01,
            min_corners: 20,
            max_jump_sigma: 5.0,
        }
    }
}

/// `[output]`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputSection {
    /// Run directory (created; must not already hold a run).
    pub out: Option<PathBuf>,
    /// Profile store: a directory, or a PostgreSQL URL `postgres://USER@HOST[:PORT]/DB` without a
    /// password (see [`crate::profile::backend`]).
    pub store: Option<PathBuf>,
    /// File whose first line is the PostgreSQL password (else `PGPASSWORD` is used).
    pub store_password_file: Option<PathBuf>,
    /// Where a passing run's profile waits while the store cannot be reached, until a later run,
    /// `serve` or `cubecal profile sync` commits it (see [`crate::profile::spool`]). Default
    /// [`DEFAULT_SPOOL`], relative to the working directory like the run directories.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spool: Option<PathBuf>,
}

/// The spool directory when `output.spool` is not set.
pub const DEFAULT_SPOOL: &str = "cubecal-spool";

impl OutputSection {
    /// `output.spool`, or [`DEFAULT_SPOOL`].
    pub fn spool_dir(&self) -> PathBuf {
        self.spool
            .clone()
            .unwrap_or_else(|| PathBuf::from(DEFAULT_SPOOL))
    }
}

/// `[http]`: the live page ([`crate::live`]). Never recorded in a run's session (a replay must not
/// open a server), so the field is skipped when the config is written.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HttpSection {
    /// Where to serve the page: `PORT`, `HOST:PORT` or `IP:PORT` (a bare port binds 127.0.0.1).
    /// Off when not set.
    pub listen: Option<String>,
    /// File whose first line is the operator token that enables the page's Start/Stop buttons
    /// (without it the page is read-only).
    pub token_file: Option<PathBuf>,
    /// Seconds the page stays up after a run (waiting for Start); not set: until the process is
    /// stopped (SIGINT/SIGTERM).
    pub linger_s: Option<u64>,
}

/// `[rig]`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RigSection {
    pub path: Option<PathBuf>,
}

/// `[detect]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectSection {
    /// Look again at full resolution where the half-resolution front end left corners it could not
    /// link (faces seen at 75°+ from frontal, squares 3–5 px across one way;
    /// [`crate::detect::grid::find_and_assemble`]). Those corners carry their foreshortening bias
    /// in their covariance ([`crate::detect::face::grazing_bias_px`]).
    pub second_look: bool,
}

impl Default for DetectSection {
    fn default() -> Self {
        DetectSection { second_look: true }
    }
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StationConfig {
    pub camera: CameraSection,
    pub turntable: TurntableSection,
    pub rig: RigSection,
    pub plan: PlanSection,
    pub synthetic: SyntheticSection,
    pub detect: DetectSection,
    pub solve: SolveSection,
    pub qa: QaSection,
    pub output: OutputSection,
    #[serde(skip_serializing)]
    pub http: HttpSection,
}

/// Set `key` (dotted path, e.g. `qa.max_rms_px`) in a TOML table to `value`, parsed as a TOML value
/// when it is one (`0.5`, `true`, `[1, 2]`, `"x"`) and as a string otherwise.
pub fn set_key(table: &mut toml::Table, key: &str, value: &str) -> Result<(), ConfigError> {
    let invalid = |message: String| ConfigError::Invalid {
        origin: "command line".into(),
        key: key.to_string(),
        message,
    };
    let parsed: toml::Value = match format!("v = {value}").parse::<toml::Table>() {
        Ok(mut t) => t.remove("v").unwrap_or(toml::Value::String(value.into())),
        Err(_) => toml::Value::String(value.to_string()),
    };
    let parts: Vec<&str> = key.split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        return Err(invalid("expected section.key".into()));
    }
    let mut cur = table;
    for p in &parts[..parts.len() - 1] {
        let entry = cur
            .entry(p.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        cur = entry
            .as_table_mut()
            .ok_or_else(|| invalid(format!("'{p}' is not a section")))?;
    }
    if let Some(last) = parts.last() {
        cur.insert(last.to_string(), parsed);
    }
    Ok(())
}

/// Cut a long text for an error message.
fn excerpt(s: &str) -> String {
    const MAX: usize = 300;
    if s.len() <= MAX {
        return s.to_string();
    }
    let mut end = MAX;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", &s[..end])
}

/// The dotted paths of a table's values that are not tables (`qa.max_rms_px`), in order; an empty
/// table is a leaf too (an unknown section without keys).
fn leaf_keys(table: &toml::Table, prefix: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (k, v) in table {
        let path = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(t) if !t.is_empty() => out.extend(leaf_keys(t, &path)),
            _ => out.push(path),
        }
    }
    out
}

/// Remove the value at a dotted path.
fn remove_key(table: &mut toml::Table, key: &str) {
    match key.split_once('.') {
        Some((head, rest)) => {
            if let Some(toml::Value::Table(t)) = table.get_mut(head) {
                remove_key(t, rest);
            }
        }
        None => {
            table.remove(key);
        }
    }
}

/// serde's "unknown field `x`, expected one of `a`, `b`, …" as "unknown key; the keys of [section]
/// are:" followed by every valid key, a few per line (long lines are cut when printed).
fn unknown_field_message(key: &str, serde_message: &str) -> Option<String> {
    let rest = serde_message.strip_prefix("unknown field `")?;
    let (_, expected) = rest.split_once('`')?;
    let names: Vec<&str> = expected
        .split('`')
        .skip(1)
        .step_by(2)
        .filter(|n| !n.is_empty())
        .collect();
    let section = match key.rsplit_once('.') {
        Some((section, _)) => format!("[{section}]"),
        None => "the config (sections)".to_string(),
    };
    let mut lines = vec![format!("unknown key; the keys of {section} are:")];
    for chunk in names.chunks(6) {
        lines.push(format!("    {}", chunk.join(", ")));
    }
    Some(lines.join("\n"))
}

impl StationConfig {
    /// Read a config file into a TOML table (not yet validated).
    pub fn read_table(path: &Path) -> Result<toml::Table, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        text.parse::<toml::Table>()
            .map_err(|e| ConfigError::Syntax {
                origin: path.display().to_string(),
                message: excerpt(&e.to_string()),
            })
    }

    /// Parse a table (file plus overrides) and validate it. `origin` names it in messages.
    pub fn from_table(table: toml::Table, origin: &str) -> Result<StationConfig, ConfigError> {
        let parse = |t: &toml::Table| -> Result<StationConfig, toml::de::Error> {
            toml::Value::Table(t.clone()).try_into()
        };
        let cfg = match parse(&table) {
            Ok(cfg) => cfg,
            Err(e) => {
                let message = e.message().to_string();
                // serde names neither the key of a wrong type nor (from a table, not text) its line:
                // the key is the one whose removal changes the error.
                let key = leaf_keys(&table, "").into_iter().find(|key| {
                    let mut t = table.clone();
                    remove_key(&mut t, key);
                    parse(&t).err().is_none_or(|e2| e2.message() != message)
                });
                return Err(match key {
                    Some(key) => ConfigError::Invalid {
                        origin: origin.to_string(),
                        message: unknown_field_message(&key, &message)
                            .unwrap_or_else(|| excerpt(&message)),
                        key,
                    },
                    None => ConfigError::Syntax {
                        origin: origin.to_string(),
                        message: excerpt(&message),
                    },
                });
            }
        };
        cfg.validate(origin)?;
        Ok(cfg)
    }

    fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let bad = |key: &str, message: String| ConfigError::Invalid {
            origin: origin.to_string(),
            key: key.to_string(),
            message,
        };
        let positive = |key: &str, v: f64| -> Result<(), ConfigError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(bad(key, format!("must be a positive number, got {v}")))
            }
        };
        let c = &self.camera;
        match c.source {
            SourceKind::Device if c.device.is_none() => {
                return Err(bad(
                    "camera.device",
                    "required when camera.source = \"device\"".into(),
                ));
            }
            SourceKind::Replay if c.replay.is_none() => {
                return Err(bad(
                    "camera.replay",
                    "required when camera.source = \"replay\"".into(),
                ));
            }
            SourceKind::Images if c.images.is_empty() => {
                return Err(bad(
                    "camera.images",
                    "required when camera.source = \"images\"".into(),
                ));
            }
            _ => {}
        }
        if c.frames_per_pose == 0 || c.frames_per_pose > 10 {
            return Err(bad(
                "camera.frames_per_pose",
                format!("must be 1..=10, got {}", c.frames_per_pose),
            ));
        }
        if c.grab_timeout_ms == 0 {
            return Err(bad("camera.grab_timeout_ms", "must be positive".into()));
        }
        if let Some(id) = &c.device_id
            && id.trim().is_empty()
        {
            return Err(bad("camera.device_id", "must not be empty".into()));
        }
        let t = &self.turntable;
        if matches!(t.kind, TurntableKind::Grbl | TurntableKind::Zaber) && t.port.is_none() {
            return Err(bad(
                "turntable.port",
                "required for a serial turntable (grbl, zaber)".into(),
            ));
        }
        if !(t.degrees_per_unit.is_finite() && t.degrees_per_unit != 0.0) {
            return Err(bad(
                "turntable.degrees_per_unit",
                format!("must be non-zero, got {}", t.degrees_per_unit),
            ));
        }
        positive("turntable.microsteps_per_degree", t.microsteps_per_degree)?;
        if t.move_timeout_s == 0 {
            return Err(bad("turntable.move_timeout_s", "must be positive".into()));
        }
        if t.reply_timeout_ms == 0 {
            return Err(bad("turntable.reply_timeout_ms", "must be positive".into()));
        }
        if !(t.tilt_min_deg.is_finite()
            && t.tilt_max_deg.is_finite()
            && t.tilt_min_deg <= 0.0
            && t.tilt_max_deg >= 0.0
            && t.tilt_min_deg < t.tilt_max_deg
            && t.tilt_max_deg - t.tilt_min_deg <= 180.0)
        {
            return Err(bad(
                "turntable.tilt_min_deg",
                format!(
                    "tilt limits must hold 0° and span at most 180°, got [{}, {}]",
                    t.tilt_min_deg, t.tilt_max_deg
                ),
            ));
        }
        for (key, v) in [
            ("turntable.rig_offset_mm", t.rig_offset_mm),
            ("turntable.tilt_pivot_mm", t.tilt_pivot_mm),
        ] {
            if !(v.is_finite() && v.abs() <= 10_000.0) {
                return Err(bad(
                    key,
                    format!("must be a distance within ±10 m, got {v}"),
                ));
            }
        }
        let p = &self.plan;
        if p.poses == 0 || p.poses > 1000 {
            return Err(bad(
                "plan.poses",
                format!("must be 1..=1000, got {}", p.poses),
            ));
        }
        if !(p.sweep_deg.is_finite() && (0.0..=360.0).contains(&p.sweep_deg)) {
            return Err(bad(
                "plan.sweep_deg",
                format!("must be 0..=360, got {}", p.sweep_deg),
            ));
        }
        if p.held_out > 3 {
            return Err(bad(
                "plan.held_out",
                format!("must be 0..=3, got {}", p.held_out),
            ));
        }
        positive("plan.target_sigma_fx_rel", p.target_sigma_fx_rel)?;
        positive("plan.target_sigma_cx_px", p.target_sigma_cx_px)?;
        if !(p.step_deg.is_finite() && (0.5..=90.0).contains(&p.step_deg)) {
            return Err(bad(
                "plan.step_deg",
                format!("must be 0.5..=90, got {}", p.step_deg),
            ));
        }
        let s = &self.synthetic;
        if s.width < crate::detect::MIN_SIDE
            || s.height < crate::detect::MIN_SIDE
            || s.width > 16384
            || s.height > 16384
        {
            return Err(bad(
                "synthetic.width",
                format!(
                    "image {}×{} must be 32..=16384 px per side",
                    s.width, s.height
                ),
            ));
        }
        positive("synthetic.fx", s.fx)?;
        positive("synthetic.fy", s.fy)?;
        s.camera()
            .validate()
            .map_err(|e| bad("synthetic", e.to_string()))?;
        s.settings()
            .validate()
            .map_err(|e| bad("synthetic", e.to_string()))?;
        self.solve_options(origin)?;
        let q = &self.qa;
        positive("qa.max_rms_px", q.max_rms_px)?;
        positive("qa.max_residual_px", q.max_residual_px)?;
        if !(q.min_coverage.is_finite() && (0.0..=1.0).contains(&q.min_coverage)) {
            return Err(bad(
                "qa.min_coverage",
                format!("must be 0..=1, got {}", q.min_coverage),
            ));
        }
        if q.coverage_grid[0] == 0
            || q.coverage_grid[1] == 0
            || q.coverage_grid[0] > 100
            || q.coverage_grid[1] > 100
        {
            return Err(bad(
                "qa.coverage_grid",
                format!("must be [1..=100, 1..=100], got {:?}", q.coverage_grid),
            ));
        }
        positive("qa.max_sigma_fx_rel", q.max_sigma_fx_rel)?;
        positive("qa.max_sigma_cx_px", q.max_sigma_cx_px)?;
        positive("qa.max_held_out_ratio", q.max_held_out_ratio)?;
        if !(q.held_out_floor_px.is_finite() && q.held_out_floor_px >= 0.0) {
            return Err(bad("qa.held_out_floor_px", "must be ≥ 0".into()));
        }
        positive("qa.max_blur_px", q.max_blur_px)?;
        positive("qa.max_motion", q.max_motion)?;
        positive("qa.max_jump_sigma", q.max_jump_sigma)?;
        if q.min_views < 2 {
            return Err(bad(
                "qa.min_views",
                format!("must be at least 2, got {}", q.min_views),
            ));
        }
        Ok(())
    }

    /// The lens models the station solves with: `solve.model`'s, or for `"auto"` Brown–Conrady 5 and
    /// the Kannala–Brandt fisheye, of which the run keeps the one its held-out views prefer.
    pub fn model_candidates(&self, origin: &str) -> Result<Vec<DistortionModel>, ConfigError> {
        Ok(if self.solve.model == "auto" {
            vec![DistortionModel::Brown5, DistortionModel::Kb4]
        } else {
            vec![self.solve_options(origin)?.model]
        })
    }

    /// The solver options `[solve]` describes.
    pub fn solve_options(&self, origin: &str) -> Result<SolveOptions, ConfigError> {
        let bad = |key: &str, message: String| ConfigError::Invalid {
            origin: origin.to_string(),
            key: key.to_string(),
            message,
        };
        let s = &self.solve;
        let model = match s.model.as_str() {
            "pinhole" => DistortionModel::Pinhole,
            "brown5" => DistortionModel::Brown5,
            "brown8" => DistortionModel::Brown8,
            "kb4" => DistortionModel::Kb4,
            // The first of `model_candidates`; the station solves with each.
            "auto" => DistortionModel::Brown5,
            other => {
                return Err(bad(
                    "solve.model",
                    format!("'{other}' is not pinhole, brown5, brown8, kb4 or auto"),
                ));
            }
        };
        let mut fix = Fix::default();
        for f in &s.fix {
            match f.as_str() {
                "aspect" => fix.aspect_ratio = Some(1.0),
                "principal-point" => fix.principal_point = true,
                "tangential" => fix.tangential = true,
                "k3" => fix.k3 = true,
                other => {
                    return Err(bad(
                        "solve.fix",
                        format!("'{other}' is not aspect, principal-point, tangential or k3"),
                    ));
                }
            }
        }
        let loss = match s.loss.split_once(':') {
            None if s.loss == "none" => Loss::default(),
            Some((kind, c)) => {
                let c: f64 = c
                    .parse()
                    .ok()
                    .filter(|c: &f64| c.is_finite() && *c > 0.0)
                    .ok_or_else(|| {
                        bad(
                            "solve.loss",
                            format!("scale '{c}' is not a positive number"),
                        )
                    })?;
                match kind {
                    "huber" => Loss::Huber(c),
                    "cauchy" => Loss::Cauchy(c),
                    other => {
                        return Err(bad(
                            "solve.loss",
                            format!("'{other}' is not huber or cauchy"),
                        ));
                    }
                }
            }
            None => {
                return Err(bad(
                    "solve.loss",
                    format!("'{}' is not none, huber:C or cauchy:C", s.loss),
                ));
            }
        };
        Ok(SolveOptions {
            model,
            fix,
            loss,
            outlier_sigma: None,
            max_iterations: 200,
            weighting: match s.weighting.as_str() {
                "equal" => crate::calib::Weighting::Equal,
                "covariance" => crate::calib::Weighting::Covariance,
                other => {
                    return Err(bad(
                        "solve.weighting",
                        format!("'{other}' is not equal or covariance"),
                    ));
                }
            },
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_example_config_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/station.toml");
        let t = StationConfig::read_table(&path).unwrap();
        StationConfig::from_table(t, "station.toml").unwrap();
    }

    #[test]
    fn errors_name_the_key() {
        let mut t = toml::Table::new();
        set_key(&mut t, "qa.max_rms_px", "-1").unwrap();
        let e = StationConfig::from_table(t, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("qa.max_rms_px"), "{e}");
        let t: toml::Table = "[qa]\nmax_rsm_px = 1.0\n".parse().unwrap();
        let e = StationConfig::from_table(t, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("max_rsm_px"), "{e}");
        let t: toml::Table = "[camera]\nsource = \"device\"\n".parse().unwrap();
        let e = StationConfig::from_table(t, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("camera.device"), "{e}");
        let t: toml::Table = "[solve]\nloss = \"huber:x\"\n".parse().unwrap();
        let e = StationConfig::from_table(t, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("solve.loss"), "{e}");
        let t: toml::Table = "[solve]\nweighting = \"inverse\"\n".parse().unwrap();
        let e = StationConfig::from_table(t, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("solve.weighting"), "{e}");
        let t: toml::Table = "[solve]\nweighting = \"covariance\"\n".parse().unwrap();
        let cfg = StationConfig::from_table(t, "x.toml").unwrap();
        assert_eq!(
            cfg.solve_options("x.toml").unwrap().weighting,
            crate::calib::Weighting::Covariance
        );
        let cfg = StationConfig::from_table(toml::Table::new(), "x.toml").unwrap();
        assert_eq!(
            cfg.solve_options("x.toml").unwrap().weighting,
            crate::calib::Weighting::Equal
        );
    }

    #[test]
    fn set_key_parses_values() {
        let mut t = toml::Table::new();
        set_key(&mut t, "plan.poses", "7").unwrap();
        set_key(&mut t, "camera.device", "/dev/video3").unwrap();
        set_key(&mut t, "qa.coverage_grid", "[4, 3]").unwrap();
        let c = StationConfig::from_table(t, "cli").unwrap();
        assert_eq!(c.plan.poses, 7);
        assert_eq!(c.camera.device.as_deref(), Some(Path::new("/dev/video3")));
        assert_eq!(c.qa.coverage_grid, [4, 3]);
    }
}
