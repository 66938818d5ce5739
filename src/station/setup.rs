//! Setting a run up: the station config built from a file (or a recorded session's) and the front
//! end's overrides, the rig read and parsed, and the run directory chosen. Shared by every front end
//! that starts a run (`calibrate`, `serve`, the turntable feeder), so they agree on what a request
//! means; the front ends only turn their own arguments into a [`RunRequest`].

use std::path::{Path, PathBuf};

use super::config::{ConfigError, StationConfig, set_key};
use crate::capture::session::SessionError;
use crate::rig::{Rig, RigError};

/// The rig used when neither the request nor `rig.path` names one (the bundled 200 mm cube).
pub const DEFAULT_RIG: &str = include_str!("../../fixtures/rigs/cube_outside.toml");

/// What a front end asks of a run: a config file and overrides of its keys. Every field but `set`
/// stands for one config key (see `cubecal calibrate --help`); `set` holds `KEY=VALUE` overrides.
#[derive(Debug, Clone, Default)]
pub struct RunRequest {
    /// Station config file (TOML).
    pub config: Option<PathBuf>,
    /// A V4L2 device (camera.source = "device").
    pub device: Option<PathBuf>,
    /// A recorded session to re-run: without `config`, its recorded config and rig are used.
    pub replay: Option<PathBuf>,
    /// Photos already taken (files or folders); no turntable.
    pub images: Vec<PathBuf>,
    /// The built-in synthetic camera.
    pub synthetic: bool,
    /// `KIND[:PORT]` of the turntable.
    pub turntable: Option<String>,
    pub rig: Option<PathBuf>,
    /// A plain chessboard instead of a rig file: inner corners and square size (mm).
    pub board: Option<(crate::rig::BoardSize, f64)>,
    pub store: Option<PathBuf>,
    pub out: Option<PathBuf>,
    pub poses: Option<usize>,
    pub sweep_deg: Option<f64>,
    pub device_id: Option<String>,
    /// Serve the live page here (http.listen).
    pub http: Option<String>,
    /// The live page's operator token file (http.token_file).
    pub http_token_file: Option<PathBuf>,
    /// `KEY=VALUE` overrides, applied last.
    pub set: Vec<String>,
}

impl RunRequest {
    /// A run from `config` alone (plus `KEY=VALUE` overrides): what `serve` and the turntable feeder
    /// ask for.
    pub fn from_config(config: PathBuf, device: Option<PathBuf>, set: Vec<String>) -> Self {
        RunRequest {
            config: Some(config),
            device,
            set,
            ..RunRequest::default()
        }
    }
}

/// Why a run could not be set up. The config, session and rig errors are passed through as they are
/// (same message and causes, same exit code).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SetupError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error(transparent)]
    Rig(#[from] RigError),
    #[error("{}: the recorded station config", dir.display())]
    Recorded {
        dir: PathBuf,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    #[error("--set {0}: expected KEY=VALUE")]
    Set(String),
    /// Photos without a rig: the bundled cube is a turntable rig, never the right guess for them.
    #[error(
        "photos need the rig they show: give --rig RIG.toml, or --board COLSxROWS --square MM for a plain chessboard (inner corners, as OpenCV counts them: 9x6 for a board of 10 × 7 squares)"
    )]
    ImagesNeedRig,
}

impl SetupError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            SetupError::Config(e) => e.exit_code(),
            SetupError::Session(e) => e.exit_code(),
            SetupError::Rig(e) => e.exit_code(),
            SetupError::Recorded { .. } => crate::exit::BAD_INPUT,
            SetupError::Set(_) | SetupError::ImagesNeedRig => crate::exit::USAGE,
        }
    }
}

/// Build the validated config: the file (or, for a replay without --config, the recorded one), then
/// the flags. Returns the config and the rig's TOML text and path.
pub fn build_config(
    args: &RunRequest,
) -> Result<(StationConfig, String, Option<PathBuf>), SetupError> {
    let mut origin = "command line".to_string();
    let mut recorded_rig: Option<String> = None;
    let mut table = match (&args.config, &args.replay) {
        (Some(path), _) => {
            origin = path.display().to_string();
            StationConfig::read_table(path)?
        }
        (None, Some(dir)) => {
            let session = crate::capture::session::Session::open(dir)?;
            let cfg = &session.manifest.header.config;
            recorded_rig = cfg
                .get("rig_toml")
                .and_then(|v| v.as_str())
                .map(str::to_string);
            origin = format!("{} (recorded config)", dir.display());
            match cfg.get("station") {
                Some(v) => {
                    let recorded: StationConfig =
                        serde_json::from_value(v.clone()).map_err(|source| {
                            SetupError::Recorded {
                                dir: dir.clone(),
                                source: Box::new(source),
                            }
                        })?;
                    toml::Table::try_from(&recorded).map_err(|source| SetupError::Recorded {
                        dir: dir.clone(),
                        source: Box::new(source),
                    })?
                }
                None => toml::Table::new(),
            }
        }
        (None, None) => toml::Table::new(),
    };
    let mut set = |k: &str, v: &str| set_key(&mut table, k, v);
    let quote = |p: &Path| toml::Value::String(p.display().to_string()).to_string();
    if let Some(d) = &args.device {
        set("camera.source", "\"device\"")?;
        set("camera.device", &quote(d))?;
    }
    if let Some(r) = &args.replay {
        set("camera.source", "\"replay\"")?;
        set("camera.replay", &quote(r))?;
        set("turntable.kind", "\"none\"")?;
        set("output.out", "\"\"")?;
    }
    if !args.images.is_empty() {
        set("camera.source", "\"images\"")?;
        let list: Vec<String> = args.images.iter().map(|p| quote(p)).collect();
        set("camera.images", &format!("[{}]", list.join(", ")))?;
        set("turntable.kind", "\"none\"")?;
        set("camera.frames_per_pose", "1")?;
    }
    if args.synthetic {
        set("camera.source", "\"synthetic\"")?;
    }
    if let Some(t) = &args.turntable {
        let (kind, port) = match t.split_once(':') {
            Some((k, p)) => (k, Some(p)),
            None => (t.as_str(), None),
        };
        set(
            "turntable.kind",
            &toml::Value::String(kind.into()).to_string(),
        )?;
        if let Some(p) = port {
            set("turntable.port", &toml::Value::String(p.into()).to_string())?;
        }
    }
    if let Some(r) = &args.rig {
        set("rig.path", &quote(r))?;
    }
    if let Some(s) = &args.store {
        set("output.store", &quote(s))?;
    }
    if let Some(o) = &args.out {
        set("output.out", &quote(o))?;
    }
    if let Some(n) = args.poses {
        set("plan.poses", &n.to_string())?;
    }
    if let Some(s) = args.sweep_deg {
        set("plan.sweep_deg", &format!("{s:?}"))?;
    }
    if let Some(id) = &args.device_id {
        set(
            "camera.device_id",
            &toml::Value::String(id.clone()).to_string(),
        )?;
    }
    if let Some(h) = &args.http {
        set("http.listen", &toml::Value::String(h.clone()).to_string())?;
    }
    if let Some(f) = &args.http_token_file {
        set("http.token_file", &quote(f))?;
    }
    for kv in &args.set {
        let (k, v) = kv
            .split_once('=')
            .ok_or_else(|| SetupError::Set(kv.clone()))?;
        set(k.trim(), v.trim())?;
    }
    if args.replay.is_some() && args.out.is_none() {
        // The recorded run's output folder is not reused.
        if let Some(out) = table.get_mut("output").and_then(|o| o.as_table_mut()) {
            out.remove("out");
        }
    }
    let cfg = StationConfig::from_table(table, &origin)?;
    if cfg.camera.source == super::config::SourceKind::Images
        && args.rig.is_none()
        && args.board.is_none()
        && cfg.rig.path.is_none()
    {
        return Err(SetupError::ImagesNeedRig);
    }
    if let Some((size, square_mm)) = args.board {
        return Ok((cfg, crate::rig::board_toml(size, square_mm), None));
    }
    let (rig_toml, rig_path) = match (&args.rig, &recorded_rig, &cfg.rig.path) {
        (Some(p), _, _) => (read_rig(p)?, Some(p.clone())),
        (None, Some(text), _) => (text.clone(), cfg.rig.path.clone()),
        (None, None, Some(p)) => (read_rig(p)?, Some(p.clone())),
        (None, None, None) => (DEFAULT_RIG.to_string(), None),
    };
    Ok((cfg, rig_toml, rig_path))
}

fn read_rig(p: &Path) -> Result<String, RigError> {
    std::fs::read_to_string(p).map_err(|source| RigError::Read {
        path: p.display().to_string(),
        source,
    })
}

/// A default run directory: `cubecal-runs/<UTC time>`.
fn default_run_dir() -> PathBuf {
    PathBuf::from("cubecal-runs").join(super::utc_stamp(std::time::SystemTime::now()))
}

/// A validated run: config, rig (text, path, parsed) and run directory.
#[derive(Debug)]
pub struct Prepared {
    pub cfg: StationConfig,
    pub rig_toml: String,
    pub rig_path: Option<PathBuf>,
    pub rig: Rig,
    pub run_dir: PathBuf,
}

/// Build the config, parse the rig (warnings logged) and choose the run directory: shared by
/// `calibrate`, `serve` and the turntable feeder.
pub fn prepare(args: &RunRequest) -> Result<Prepared, SetupError> {
    let (cfg, rig_toml, rig_path) = build_config(args)?;
    let origin = match (&rig_path, args.board) {
        (Some(p), _) => p.display().to_string(),
        (None, Some((size, square_mm))) => format!("--board {size} --square {square_mm}"),
        (None, None) => "the bundled rig".into(),
    };
    let (rig, warnings) = Rig::from_toml_str(&rig_toml, &origin)?;
    rig.log_warnings(&warnings);
    let run_dir = cfg
        .output
        .out
        .clone()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or_else(default_run_dir);
    Ok(Prepared {
        cfg,
        rig_toml,
        rig_path,
        rig,
        run_dir,
    })
}
