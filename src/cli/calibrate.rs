//! `cubecal calibrate`: run the station (src/station) and render its events — a progress bar and one
//! line per pose on a terminal, one JSON object per line with `--json` (the last is the result).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, set_key};
use cubecal::station::{self, Event, EventSink, RunResult, RunSpec};
use cubecal::turntable::manual::Operator;

use super::Output;

/// The rig used when neither `--rig` nor `rig.path` names one (the bundled 200 mm cube).
pub const DEFAULT_RIG: &str = include_str!("../../fixtures/rigs/cube_outside.toml");

#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    /// Station config (TOML; see fixtures/station.toml). Every key can also be set with a flag below
    /// or with --set.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Camera: a V4L2 device (sets camera.source = "device").
    #[arg(long, group = "source")]
    pub device: Option<PathBuf>,
    /// Camera: re-run a recorded session (a run's `session/` folder). Without --config, the recorded
    /// station config and rig are used, so the run is reproduced bit for bit.
    #[arg(long, group = "source")]
    pub replay: Option<PathBuf>,
    /// Camera: photos already taken (files or folders of PNG, JPEG, TIFF); no turntable.
    #[arg(long, group = "source", num_args = 1..)]
    pub images: Vec<PathBuf>,
    /// Camera: the built-in synthetic camera (the default when the config names none).
    #[arg(long, group = "source")]
    pub synthetic: bool,
    /// Turntable: grbl:PORT, zaber:PORT, sim-grbl, sim-zaber, manual or none.
    #[arg(long, value_name = "KIND[:PORT]")]
    pub turntable: Option<String>,
    /// Rig description (TOML). Default: the config's rig.path, else the bundled cube.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Profile store directory (output.store).
    #[arg(long)]
    pub store: Option<PathBuf>,
    /// Run directory to create (output.out). Default: cubecal-runs/<UTC time>.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Number of poses (plan.poses).
    #[arg(long)]
    pub poses: Option<usize>,
    /// Turntable sweep in degrees, centred on 0° (plan.sweep_deg).
    #[arg(long, allow_negative_numbers = true)]
    pub sweep_deg: Option<f64>,
    /// Identity to store the profile under for synthetic and image runs (camera.device_id).
    #[arg(long)]
    pub device_id: Option<String>,
    /// Set any config key: --set qa.max_rms_px=0.2 (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

impl CalibrateArgs {
    /// The arguments of a run from `config` alone (plus `--set` overrides): what `serve` and the
    /// turntable feeder pass to [`prepare`].
    pub fn from_config(config: PathBuf, device: Option<PathBuf>, set: Vec<String>) -> Self {
        CalibrateArgs {
            config: Some(config),
            device,
            replay: None,
            images: Vec::new(),
            synthetic: false,
            turntable: None,
            rig: None,
            store: None,
            out: None,
            poses: None,
            sweep_deg: None,
            device_id: None,
            set,
        }
    }
}

/// Build the validated config: the file (or, for a replay without --config, the recorded one), then
/// the flags. Returns the config and the rig's TOML text and path.
pub fn build_config(
    args: &CalibrateArgs,
) -> anyhow::Result<(StationConfig, String, Option<PathBuf>)> {
    let mut origin = "command line".to_string();
    let mut recorded_rig: Option<String> = None;
    let mut table = match (&args.config, &args.replay) {
        (Some(path), _) => {
            origin = path.display().to_string();
            StationConfig::read_table(path)?
        }
        (None, Some(dir)) => {
            let session = cubecal::capture::session::Session::open(dir)?;
            let cfg = &session.manifest.header.config;
            recorded_rig = cfg
                .get("rig_toml")
                .and_then(|v| v.as_str())
                .map(str::to_string);
            origin = format!("{} (recorded config)", dir.display());
            match cfg.get("station") {
                Some(v) => {
                    let recorded: StationConfig =
                        serde_json::from_value(v.clone()).with_context(|| {
                            format!("{}: the recorded station config", dir.display())
                        })?;
                    toml::Table::try_from(&recorded).with_context(|| {
                        format!("{}: the recorded station config", dir.display())
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
    for kv in &args.set {
        let (k, v) = kv
            .split_once('=')
            .with_context(|| format!("--set {kv}: expected KEY=VALUE"))?;
        set(k.trim(), v.trim())?;
    }
    if args.replay.is_some() && args.out.is_none() {
        // The recorded run's output folder is not reused.
        if let Some(out) = table.get_mut("output").and_then(|o| o.as_table_mut()) {
            out.remove("out");
        }
    }
    let cfg = StationConfig::from_table(table, &origin)?;
    let (rig_toml, rig_path) = match (&args.rig, &recorded_rig, &cfg.rig.path) {
        (Some(p), _, _) => (read_rig(p)?, Some(p.clone())),
        (None, Some(text), _) => (text.clone(), cfg.rig.path.clone()),
        (None, None, Some(p)) => (read_rig(p)?, Some(p.clone())),
        (None, None, None) => (DEFAULT_RIG.to_string(), None),
    };
    Ok((cfg, rig_toml, rig_path))
}

fn read_rig(p: &Path) -> anyhow::Result<String> {
    std::fs::read_to_string(p).map_err(|source| {
        anyhow::Error::new(cubecal::rig::RigError::Read {
            path: p.display().to_string(),
            source,
        })
    })
}

/// A default run directory: `cubecal-runs/<UTC time>`.
fn default_run_dir() -> PathBuf {
    PathBuf::from("cubecal-runs").join(cubecal::station::utc_stamp(std::time::SystemTime::now()))
}

/// Renders events for a person: a progress bar (on a terminal) and one line per pose.
struct Human {
    bar: Option<indicatif::ProgressBar>,
}

impl Human {
    fn line(&self, s: String) {
        match &self.bar {
            Some(b) => b.println(s),
            None => {
                let mut err = std::io::stderr().lock();
                let _ = writeln!(err, "{s}");
            }
        }
    }
}

impl EventSink for Human {
    fn event(&mut self, e: &Event) {
        match e {
            Event::Opened {
                source,
                width,
                height,
                turntable,
            } => {
                self.line(format!(
                    "camera: {source} ({width}×{height}); turntable: {turntable}"
                ));
            }
            Event::PosePlanned {
                index,
                total,
                angle_deg,
                ..
            } => {
                if self.bar.is_none() && std::io::stderr().is_terminal() {
                    let b = indicatif::ProgressBar::new(*total as u64);
                    b.set_style(
                        indicatif::ProgressStyle::with_template(
                            "{bar:30} {pos}/{len} poses  {msg}",
                        )
                        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                    );
                    self.bar = Some(b);
                }
                if let Some(b) = &self.bar {
                    b.set_position(*index as u64);
                    b.set_message(match angle_deg {
                        Some(a) => format!("pose {index:02} at {a:+.1}°"),
                        None => format!("pose {index:02}"),
                    });
                }
            }
            Event::ViewAccepted {
                name,
                faces,
                corners,
                ..
            } => {
                self.line(format!(
                    "{name}: accepted, {faces} face(s), {corners} corners"
                ));
            }
            Event::ViewRejected { name, reason, .. } => {
                self.line(format!("{name}: rejected: {reason}"));
            }
            Event::Solving { views, points } => {
                if let Some(b) = self.bar.take() {
                    b.finish_and_clear();
                }
                self.line(format!("solving from {views} view(s), {points} corners"));
            }
            _ => {}
        }
    }
}

/// Renders events as JSON lines on stdout.
struct JsonLines;

impl EventSink for JsonLines {
    fn event(&mut self, e: &Event) {
        if matches!(e, Event::Alive) {
            return;
        }
        if let Ok(s) = serde_json::to_string(e) {
            let mut out = std::io::stdout().lock();
            let _ = writeln!(out, "{s}");
        }
    }
}

/// A validated run: config, rig (text, path, parsed) and run directory.
pub struct Prepared {
    pub cfg: StationConfig,
    pub rig_toml: String,
    pub rig_path: Option<PathBuf>,
    pub rig: Rig,
    pub run_dir: PathBuf,
}

/// Build the config, parse the rig (warnings logged) and choose the run directory: shared by
/// `calibrate` and `serve`.
pub fn prepare(args: &CalibrateArgs) -> anyhow::Result<Prepared> {
    let (cfg, rig_toml, rig_path) = build_config(args)?;
    let origin = rig_path
        .as_ref()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| "the bundled rig".into());
    let (rig, warnings) = Rig::from_toml_str(&rig_toml, &origin)?;
    for w in &warnings {
        tracing::warn!("{w}");
    }
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

pub fn run(args: CalibrateArgs, out: Output) -> anyhow::Result<u8> {
    let Prepared {
        cfg,
        rig_toml,
        rig_path,
        rig,
        run_dir,
    } = prepare(&args)?;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, Arc::clone(&stop))
            .context("installing the signal handler")?;
    }
    let operator: Option<Box<dyn Operator>> = Some(Box::new(super::turntable::TerminalOperator));
    let hw = station::hardware::open(&cfg, &rig, operator)?;
    let spec = RunSpec {
        config: &cfg,
        rig: &rig,
        rig_toml: &rig_toml,
        rig_path,
        run_dir: &run_dir,
    };
    let result = if out.json {
        station::run(&spec, hw, &mut JsonLines, &stop)?
    } else {
        let mut human = Human { bar: None };
        let r = station::run(&spec, hw, &mut human, &stop);
        if let Some(b) = human.bar.take() {
            b.finish_and_clear();
        }
        r?
    };
    if out.json {
        print_json(&result)?;
    } else {
        print_human(&result);
    }
    Ok(result.exit_code())
}

fn print_json(r: &RunResult) -> anyhow::Result<()> {
    let s = serde_json::to_string(r)?;
    let mut o = std::io::stdout().lock();
    let _ = writeln!(o, "{s}");
    Ok(())
}

fn print_human(r: &RunResult) {
    let mut o = std::io::stdout().lock();
    let mut w = |s: String| {
        let _ = writeln!(o, "{s}");
    };
    if let Some(c) = &r.calibration {
        let k = c.camera_matrix;
        let sd = |n: &str| {
            c.std_dev
                .get(n)
                .map(|s| format!(" ± {s:.3}"))
                .unwrap_or_default()
        };
        w(format!(
            "calibration ({} views, {} corners, RMS {:.3} px):",
            c.views.len(),
            c.n_points,
            c.rms_px
        ));
        w(format!(
            "  fx = {:.3}{}   fy = {:.3}{}",
            k[0][0],
            sd("fx"),
            k[1][1],
            sd("fy")
        ));
        w(format!(
            "  cx = {:.3}{}   cy = {:.3}{}",
            k[0][2],
            sd("cx"),
            k[1][2],
            sd("cy")
        ));
        w(format!(
            "  distortion ({}): {:?}",
            c.distortion.model, c.distortion.coefficients
        ));
    }
    for n in &r.notes {
        w(format!("note: {n}"));
    }
    w(format!(
        "verdict: {}",
        if r.verdict.pass { "PASS" } else { "FAIL" }
    ));
    for c in &r.verdict.checks {
        w(format!(
            "  [{}] {:<28} {:>12.6}  (limit {:.6})",
            if c.pass { "ok" } else { "FAIL" },
            c.name,
            c.value,
            c.threshold
        ));
        if let Some(h) = &c.hint {
            w(format!("        {h}"));
        }
    }
    match &r.profile {
        Some(p) => w(format!("profile: {}", p.display())),
        None => w("profile: none written".into()),
    }
    w(format!("run directory: {}", r.run_dir.display()));
}
