//! `cubecal serve`: the station as a systemd service (deploy/systemd/cubecal@.service, started by udev
//! when a camera appears). One calibration run on `--device` with the station config, like
//! `cubecal calibrate --config … --device …`, with its events rendered for the service manager by
//! [`SystemdNotifier`] (`READY=1`, `STATUS=`, watchdog pings from the station loop) and as one line per
//! event on stdout for the journal.
//!
//! SIGTERM (systemd stopping the unit, the camera unplugged) or SIGINT: a thread sends `STOPPING=1` at
//! once and sets the station's stop flag; the station stops the turntable, closes the session marked
//! incomplete and writes no profile, and `serve` exits with 130 (the unit lists it in
//! `SuccessExitStatus=`, so a requested stop is not a failure).
//!
//! Relative paths of the config (run directory, profile store) are relative to the working directory:
//! `/var/lib/cubecal` under the unit (`WorkingDirectory=`, the unit's `StateDirectory=`).

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use cubecal::station::notify::{SystemdNotifier, notify_stopping};
use cubecal::station::{self, Event, EventSink, RunSpec};
use signal_hook::consts::{SIGINT, SIGTERM};

use super::Output;
use cubecal::station::setup::{self, RunRequest};

#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    /// The camera: a V4L2 capture device (the unit passes /dev/%I).
    #[arg(long)]
    pub device: PathBuf,
    /// Station config (TOML; see fixtures/station.toml).
    #[arg(long, default_value = "/etc/cubecal/station.toml")]
    pub config: PathBuf,
    #[command(flatten)]
    pub http: super::live::HttpArgs,
    /// Set any config key: --set qa.max_rms_px=0.2 (repeatable; applied after the config and --device).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

/// The service's sink: systemd notifications, and the same status text (or JSON lines) on stdout.
struct ServiceSink {
    notifier: SystemdNotifier,
    json: bool,
}

impl EventSink for ServiceSink {
    fn event(&mut self, event: &Event) {
        let status = self.notifier.notify_event(event);
        let line = if self.json {
            (!matches!(event, Event::Alive))
                .then(|| serde_json::to_string(event).ok())
                .flatten()
        } else {
            status
        };
        if let Some(line) = line {
            let mut out = std::io::stdout().lock();
            let _ = writeln!(out, "{line}");
        }
    }
}

pub fn run(args: ServeArgs, out: Output) -> anyhow::Result<u8> {
    let stop = Arc::new(AtomicBool::new(false));
    let quit = Arc::new(AtomicBool::new(false));
    watch_signals(Arc::clone(&stop), Arc::clone(&quit))
        .context("installing the SIGTERM/SIGINT handler")?;
    let mut sink = ServiceSink {
        notifier: SystemdNotifier::from_env(),
        json: out.json,
    };
    sink.notifier
        .status(&format!("opening {}", args.device.display()));
    let result = serve(&args, &mut sink, &stop, &quit);
    match &result {
        Ok(code) => tracing::info!(code, "station run finished"),
        Err(e) => {
            // The error itself is printed by the CLI; systemctl status shows it too.
            let text = e
                .chain()
                .map(|c| c.to_string())
                .collect::<Vec<_>>()
                .join(": ");
            sink.notifier.status(&format!("error: {text}"));
        }
    }
    result
}

fn serve(
    args: &ServeArgs,
    sink: &mut ServiceSink,
    stop: &Arc<AtomicBool>,
    quit: &AtomicBool,
) -> anyhow::Result<u8> {
    let mut request = RunRequest::from_config(
        args.config.clone(),
        Some(args.device.clone()),
        args.set.clone(),
    );
    request.http = args.http.http.clone();
    request.http_token_file = args.http.http_token_file.clone();
    let prepared = setup::prepare(&request)?;
    let Some(page) = super::live::open(&prepared.cfg, Arc::clone(stop))? else {
        return serve_once(prepared, sink, stop, None);
    };
    // With the page: as `calibrate --http`, the page stays up after the run (until SIGTERM, or
    // http.linger_s) and its Start runs the station again in a new run directory. The run's loop
    // no longer pings the watchdog during the wait: the tick does (paced by the notifier).
    page.runs(
        prepared,
        request,
        stop,
        quit,
        sink,
        |sink, prepared, live| serve_once(prepared, sink, stop, Some(live)),
        |sink| {
            sink.notifier.notify_event(&Event::Alive);
        },
    )
}

/// One station run for the service (and the live page, when open).
fn serve_once(
    prepared: setup::Prepared,
    sink: &mut ServiceSink,
    stop: &AtomicBool,
    live: Option<&cubecal::live::Live>,
) -> anyhow::Result<u8> {
    let setup::Prepared {
        cfg,
        rig_toml,
        rig_path,
        rig,
        run_dir,
    } = prepared;
    if let Some(line) = spool_line(&cfg, sink, "before the run") {
        sink.notifier.status(&line);
    }
    // No operator: a service cannot answer a manual turntable's prompts (the station says so).
    let hw = station::hardware::open(&cfg, &rig, None)?;
    if stop.load(Ordering::SeqCst) {
        return Ok(cubecal::exit::INTERRUPTED);
    }
    let spec = RunSpec {
        config: &cfg,
        rig: &rig,
        rig_toml: &rig_toml,
        rig_path,
        run_dir: &run_dir,
    };
    let mut result = super::live::with_page(live, sink, |s| station::run(&spec, hw, s, stop))?;
    // The last status an operator sees in `systemctl status` starts with the verdict; the spool's
    // depth follows it.
    let verdict = cubecal::station::notify::verdict_line(&result.verdict);
    match spool_line(&cfg, sink, "after the run") {
        Some(line) => sink.notifier.status(&format!("{verdict} | {line}")),
        None => sink.notifier.status(&verdict),
    }
    let previews = std::mem::take(&mut result.previews);
    super::report::write_for_run(&run_dir, previews, sink);
    let mut o = std::io::stdout().lock();
    if sink.json {
        let _ = writeln!(o, "{}", serde_json::to_string(&result)?);
    } else {
        match &result.profile {
            Some(p) => {
                let _ = writeln!(o, "profile: {}", p.display());
            }
            None => {
                let _ = writeln!(o, "profile: none written");
            }
        }
        let _ = writeln!(o, "run directory: {}", result.run_dir.display());
    }
    Ok(result.exit_code())
}

/// The spool's depth (`spool: N profile(s) waiting for STORE in DIR`), printed on stdout and returned
/// for the service status, when the station has a store: profiles that passed while the store was
/// unreachable and wait to be committed (by this run's commit, or `cubecal profile sync`).
fn spool_line(cfg: &station::StationConfig, sink: &ServiceSink, when: &str) -> Option<String> {
    let Some(store) = &cfg.output.store else {
        return None;
    };
    let dir = cfg.output.spool_dir();
    let store = cubecal::profile::backend::describe_location(store);
    let line = match cubecal::profile::spool::Spool::new(&dir).depth() {
        Ok(n) => format!(
            "spool: {n} profile(s) waiting for {store} in {} ({when})",
            dir.display()
        ),
        Err(e) => format!("spool: cannot read {} ({when}): {e}", dir.display()),
    };
    let mut o = std::io::stdout().lock();
    let _ = if sink.json {
        writeln!(
            o,
            "{}",
            serde_json::json!({ "event": "spool", "status": line })
        )
    } else {
        writeln!(o, "{line}")
    };
    Some(line)
}

/// On the first SIGTERM or SIGINT: tell systemd we are stopping, and set the station's stop flag
/// and `quit` (which ends the live page's wait after a run).
fn watch_signals(stop: Arc<AtomicBool>, quit: Arc<AtomicBool>) -> std::io::Result<()> {
    let mut signals = signal_hook::iterator::Signals::new([SIGTERM, SIGINT])?;
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            if let Some(sig) = signals.forever().next() {
                let name = if sig == SIGTERM { "SIGTERM" } else { "SIGINT" };
                stop.store(true, Ordering::SeqCst);
                quit.store(true, Ordering::SeqCst);
                notify_stopping(&format!(
                    "{name}: stopping the turntable and closing the session"
                ));
                tracing::info!("{name}: stopping");
            }
        })?;
    Ok(())
}
