//! `cubecal calibrate`: run the station (src/station) and render its events — a progress bar and one
//! line per pose on a terminal, one JSON object per line with `--json` (the last is the result).

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use cubecal::station::setup::RunRequest;
use cubecal::station::{self, Event, EventSink, RunResult, RunSpec};
use cubecal::turntable::manual::Operator;

use super::Output;

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
    /// Rig description (TOML; see README "Rig files"). Default: the config's rig.path, else the
    /// bundled cube (turntable and synthetic runs; photos need --rig or --board).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    #[command(flatten)]
    pub board: super::BoardArgs,
    /// Profile store (output.store): a directory or postgres://USER@HOST/DB (password from
    /// output.store_password_file or PGPASSWORD, never the URL). A passing run's profile is
    /// committed there; without it the profile is only RUN_DIR/profile.json (printed with how to
    /// store or export it).
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
    /// Refine the rig's faces jointly with the camera (solve.refine_rig): for a hand-built rig whose
    /// boards sit slightly off the rig file.
    #[arg(long)]
    pub refine_rig: bool,
    /// Lens model (solve.model): pinhole, brown5, brown8, kb4 (the fisheye: OpenCV's cv::fisheye),
    /// or auto (Brown–Conrady and the fisheye both solved; the held-out views decide).
    #[arg(long, value_parser = ["pinhole", "brown5", "brown8", "kb4", "auto"])]
    pub model: Option<String>,
    #[command(flatten)]
    pub http: super::live::HttpArgs,
    /// Set any config key: --set qa.max_rms_px=0.2 (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

impl From<&CalibrateArgs> for RunRequest {
    fn from(a: &CalibrateArgs) -> RunRequest {
        RunRequest {
            config: a.config.clone(),
            device: a.device.clone(),
            replay: a.replay.clone(),
            images: a.images.clone(),
            synthetic: a.synthetic,
            turntable: a.turntable.clone(),
            rig: a.rig.clone(),
            board: a.board.board(),
            store: a.store.clone(),
            out: a.out.clone(),
            poses: a.poses,
            sweep_deg: a.sweep_deg,
            device_id: a.device_id.clone(),
            http: a.http.http.clone(),
            http_token_file: a.http.http_token_file.clone(),
            set: (a.set.iter().cloned())
                .chain(a.refine_rig.then(|| "solve.refine_rig=true".to_string()))
                .chain(a.model.as_ref().map(|m| format!("solve.model={m}")))
                .collect(),
        }
    }
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
            Event::PoseChosen {
                index,
                rotation_deg,
                tilt_deg,
                corners,
                predicted,
            } => {
                let sigma: Vec<String> = (predicted.iter())
                    .filter(|p| matches!(p.name, "cx" | "cy"))
                    .map(|p| format!("σ({}) → {:.3} px", p.name, p.sigma))
                    .collect();
                self.line(format!(
                    "pose {index:02}: planned at rotation {rotation_deg:+.0}°, tilt {tilt_deg:+.0}° ({corners} corners predicted{})",
                    if sigma.is_empty() {
                        String::new()
                    } else {
                        format!("; {}", sigma.join(", "))
                    }
                ));
            }
            Event::Coverage {
                cells_covered,
                cells_total,
                fraction,
                ..
            } => {
                self.line(format!(
                    "coverage: {cells_covered} of {cells_total} cells ({:.0} %)",
                    100.0 * fraction
                ));
            }
            Event::SpoolDrained {
                store,
                committed,
                already_stored,
                failed,
                waiting,
            } => {
                self.line(format!(
                    "spool: {} waiting profile(s) committed to {store}, {failed} refused (set aside), {waiting} still waiting",
                    committed + already_stored
                ));
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

pub fn run(args: CalibrateArgs, out: Output) -> anyhow::Result<u8> {
    let request = RunRequest::from(&args);
    let prepared = station::setup::prepare(&request)?;
    // `stop` is the station's stop flag (signals and the page's Stop set it); `quit` only signals.
    let stop = Arc::new(AtomicBool::new(false));
    let quit = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        for flag in [&stop, &quit] {
            signal_hook::flag::register(sig, Arc::clone(flag))
                .context("installing the signal handler")?;
        }
    }
    let Some(page) = super::live::open(&prepared.cfg, Arc::clone(&stop))? else {
        return run_once(prepared, out, &stop, None);
    };
    // With the page: run, show the outcome, and run again when the operator asks (a new run
    // directory each time) until the linger time passes or a signal comes.
    page.runs(
        prepared,
        request,
        &stop,
        &quit,
        &mut (),
        |(), prepared, live| run_once(prepared, out, &stop, Some(live)),
        |()| {},
    )
}

/// One station run with its events rendered on the terminal (and on the live page, when open).
fn run_once(
    prepared: station::setup::Prepared,
    out: Output,
    stop: &AtomicBool,
    live: Option<&cubecal::live::Live>,
) -> anyhow::Result<u8> {
    let mut laps = station::Laps::start();
    let station::setup::Prepared {
        cfg,
        rig_toml,
        rig_path,
        rig,
        run_dir,
    } = prepared;
    let operator: Option<Box<dyn Operator>> = Some(Box::new(super::operator::TerminalOperator));
    let hw = station::hardware::open(&cfg, &rig, operator)?;
    laps.lap("open");
    let spec = RunSpec {
        config: &cfg,
        rig: &rig,
        rig_toml: &rig_toml,
        rig_path,
        run_dir: &run_dir,
    };
    let run = |sink: &mut dyn EventSink| {
        super::live::with_page(live, sink, |s| station::run(&spec, hw, s, stop))
    };
    let mut result = if out.json {
        run(&mut JsonLines)?
    } else {
        let mut human = Human { bar: None };
        let r = run(&mut human);
        if let Some(b) = human.bar.take() {
            b.finish_and_clear();
        }
        r?
    };
    laps.lap("station run");
    let previews = std::mem::take(&mut result.previews);
    super::report::write_for_run(&run_dir, previews, &mut station::event::NullSink);
    laps.lap("report");
    if out.json {
        print_json(&result)?;
    } else {
        print_human(&result, cfg.output.store.as_deref());
    }
    laps.lap("print");
    Ok(result.exit_code())
}

fn print_json(r: &RunResult) -> anyhow::Result<()> {
    let s = serde_json::to_string(r)?;
    let mut o = std::io::stdout().lock();
    let _ = writeln!(o, "{s}");
    Ok(())
}

/// The run in words. `store` is the profile store the run committed to, if any: without one the
/// profile is only the run's `profile.json`, and the user is told how to store or export it.
fn print_human(r: &RunResult, store: Option<&std::path::Path>) {
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
            "  distortion ({}): {}",
            c.distortion.model,
            super::fmt_distortion(&c.distortion, &c.std_dev)
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
            "  [{}] {:<28} {:>12}  (limit {})",
            if c.pass { "ok" } else { "FAIL" },
            c.name,
            super::fmt_value(c.value),
            super::fmt_value(c.threshold)
        ));
        if let Some(h) = &c.hint {
            w(format!("        {h}"));
        }
    }
    for f in &r.verdict.fixed {
        w(format!(
            "  fixed: {} = {} ({})",
            f.name,
            super::fmt_value(f.value),
            f.reason
        ));
    }
    match (&r.profile, store) {
        (Some(p), Some(_)) if let Some(waits) = &r.profile_waits_for => w(format!(
            "profile: {} (waiting in the spool: {waits} unreachable; committed when it returns)",
            p.display()
        )),
        (Some(p), Some(s)) => w(format!(
            "profile: {} (stored in {})",
            p.display(),
            s.display()
        )),
        (Some(p), None) => {
            w(format!(
                "profile: {} (not stored: no --store given)",
                p.display()
            ));
            w(format!(
                "  to store it per camera, run with --store DIR (and --device-id NAME for photos); to use it elsewhere: cubecal profile export {} --format opencv",
                p.display()
            ));
        }
        (None, _) => w("profile: none written".into()),
    }
    w(format!("run directory: {}", r.run_dir.display()));
}
