//! Command-line front end: clap subcommands, output rendering (human or `--json`), and the mapping from
//! library errors to the documented exit codes in [`cubecal::exit`]. No calibration logic lives here.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use cubecal::exit;

mod calibrate;
mod capture;
mod detect;
mod profile;
mod render;
mod report;
mod rig;
mod serve;
mod solve;
mod turntable;

/// cubecal — camera calibration station.
#[derive(Debug, Parser)]
#[command(name = "cubecal", version, about, long_about = None)]
struct Cli {
    /// Print machine-readable JSON instead of human-readable text.
    #[arg(long, global = true)]
    json: bool,
    /// More log output on stderr (-v info, -vv debug, -vvv trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Calibrate a camera: plan poses, drive the turntable, capture, detect, solve, judge, write a
    /// profile (the station).
    Calibrate(calibrate::CalibrateArgs),
    /// Solve a calibration from a file of 2D–3D correspondences and print it.
    Solve(solve::SolveArgs),
    /// Render synthetic frames of a rig with exact ground truth.
    Render(render::RenderArgs),
    /// Find and label the rig's checkerboard faces in image files (optionally drawing overlays).
    Detect(detect::DetectArgs),
    /// Work with rig descriptions (print the faces as targets). `target` is an alias.
    #[command(subcommand, alias = "target")]
    Rig(rig::RigCommand),
    /// List the V4L2 capture devices on this machine.
    Devices(capture::DevicesArgs),
    /// Record a session of frames from a camera.
    Record(capture::RecordArgs),
    /// Bring up, drive or simulate a serial turntable.
    #[command(subcommand)]
    Turntable(turntable::TurntableCommand),
    /// List, show, export, compare and roll back per-camera profiles in the profile store.
    #[command(subcommand)]
    Profile(profile::ProfileCommand),
    /// Write the self-contained HTML report (plots, thumbnails) of a station run directory.
    Report(report::ReportArgs),
    /// Run the station as a systemd service on one camera (what cubecal@.service runs): one
    /// calibration with READY/STATUS/watchdog notifications, SIGTERM stops it cleanly.
    Serve(serve::ServeArgs),
}

/// Global output options every subcommand receives.
#[derive(Debug, Clone, Copy)]
pub struct Output {
    pub json: bool,
}

pub fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            // clap prints help/version to stdout and usage errors to stderr, with its own exit code
            // (0 for --help/--version, 2 for usage errors).
            let _ = e.print();
            return ExitCode::from(if e.use_stderr() {
                exit::USAGE
            } else {
                exit::SUCCESS
            });
        }
    };
    init_logging(cli.verbose);
    let out = Output { json: cli.json };
    let result = match cli.command {
        Command::Calibrate(args) => calibrate::run(args, out),
        Command::Solve(args) => solve::run(args, out),
        Command::Render(args) => render::run(args, out),
        Command::Detect(args) => detect::run(args, out),
        Command::Rig(cmd) => rig::run(cmd, out),
        Command::Devices(args) => capture::run_devices(args, out),
        Command::Record(args) => capture::run_record(args, out),
        Command::Turntable(cmd) => turntable::run(cmd, out),
        Command::Profile(cmd) => profile::run(cmd, out),
        Command::Report(args) => report::run(args, out),
        Command::Serve(args) => serve::run(args, out),
    };
    match result {
        Ok(code) => ExitCode::from(code),
        Err(err) => {
            let code = exit_code_for(&err);
            report_error(&err, out);
            ExitCode::from(code)
        }
    }
}

fn init_logging(verbose: u8) {
    use tracing_subscriber::EnvFilter;
    let default = match verbose {
        0 => "warn",
        1 => "info",
        2 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// Map an error to its exit code: the first library error found in the chain decides.
fn exit_code_for(err: &anyhow::Error) -> u8 {
    for cause in err.chain() {
        if let Some(e) = cause.downcast_ref::<cubecal::calib::CalibError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::observations::ObservationsError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::rig::RigError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::capture::CaptureError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::capture::synthetic::SyntheticError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::detect::DetectError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::detect::overlay::OverlayError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::turntable::TurntableError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::station::StationError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::station::config::ConfigError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::capture::session::SessionError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::report::ReportError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<detect::DetectCliError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::profile::ProfileError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::profile::export::ExportError>() {
            return e.exit_code();
        }
        if cause.downcast_ref::<profile::UsageError>().is_some() {
            return exit::USAGE;
        }
    }
    exit::INTERNAL
}

/// Print an error once, with its chain of causes, to stderr (and as JSON on stdout with `--json`).
#[allow(clippy::print_stderr, clippy::print_stdout)]
fn report_error(err: &anyhow::Error, out: Output) {
    let chain: Vec<String> = err.chain().map(|c| c.to_string()).collect();
    if out.json {
        let v = serde_json::json!({ "error": chain.first(), "causes": &chain[1..], "exit_code": exit_code_for(err) });
        println!("{v}");
    }
    eprintln!("error: {}", chain.join("\n  caused by: "));
}
