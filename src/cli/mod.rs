//! Command-line front end: clap subcommands, output rendering (human or `--json`), and the mapping from
//! library errors to the documented exit codes in [`cubecal::exit`]. No calibration logic lives here.
//!
//! Output goes through [`outln!`], which returns write errors instead of panicking: when stdout is a
//! closed pipe (`cubecal solve big.json | head -1`) the command stops quietly with exit 0, as ripgrep
//! does. Logs on stderr are coloured only on a terminal, and never when `NO_COLOR` is set.

use std::io::IsTerminal;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use cubecal::exit;

/// `println!` that returns the write's `io::Result` instead of panicking (a closed pipe must not
/// panic); use with `?` in a command that returns `anyhow::Result`.
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)
    }};
}

mod calibrate;
mod capture;
mod detect;
mod live;
mod operator;
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
    /// Write the self-contained HTML report of a station run directory or of a stored profile.
    Report(report::ReportArgs),
    /// Run the station as a systemd service on one camera (what cubecal@.service runs): one
    /// calibration with READY/STATUS/watchdog notifications, SIGTERM stops it cleanly.
    Serve(serve::ServeArgs),
}

/// A check's value or threshold for people: a count as a count (`11`, not `11.000000`), other values
/// with up to six decimals and no trailing zeros (`0.3`, `0.000123`).
pub fn fmt_value(x: f64) -> String {
    if !x.is_finite() {
        return x.to_string();
    }
    if x.fract() == 0.0 && x.abs() < 1e15 {
        return format!("{x:.0}");
    }
    let s = format!("{x:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "0" || s == "-0" {
        // Smaller than six decimals show: keep its significant digits.
        format!("{x:.3e}")
    } else {
        s.to_string()
    }
}

/// Distortion coefficients named as their model names them (OpenCV's order for Brown–Conrady,
/// `k1..k4` for kb4), each to six significant decimals, with σ where the calibration has one:
/// `k1 -0.281234 ± 0.001234, k2 …`.
pub fn fmt_distortion(
    distortion: &cubecal::calib::report::DistortionReport,
    std_dev: &std::collections::BTreeMap<String, f64>,
) -> String {
    distortion
        .coefficients
        .iter()
        .zip(cubecal::profile::coefficient_names(&distortion.model))
        .map(|(v, name)| match std_dev.get(name) {
            Some(sd) => format!("{name} {v:.6} ± {sd:.6}"),
            None => format!("{name} {v:.6} (fixed)"),
        })
        .collect::<Vec<_>>()
        .join(", ")
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
            // (0 for --help/--version, 2 for usage errors). With --json a usage error is also one
            // JSON object on stdout, like every other error.
            let _ = e.print();
            if !e.use_stderr() {
                return ExitCode::from(exit::SUCCESS);
            }
            if std::env::args_os().skip(1).any(|a| a == "--json") {
                let message = e.render().to_string();
                let first = message
                    .lines()
                    .next()
                    .unwrap_or_default()
                    .trim_start_matches("error: ")
                    .to_string();
                let v =
                    serde_json::json!({ "error": first, "causes": [], "exit_code": exit::USAGE });
                let _ = outln!("{v}");
            }
            return ExitCode::from(exit::USAGE);
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
        // The reader went away (`| head`): nothing left to say, and nobody to say it to.
        Err(err) if is_broken_pipe(&err) => ExitCode::from(exit::SUCCESS),
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
    let colour = std::io::stderr().is_terminal()
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .try_init();
}

/// Whether the error is a write to a closed pipe.
fn is_broken_pipe(err: &anyhow::Error) -> bool {
    err.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// A command-line usage error found after parsing (options that contradict each other, an output
/// name the command cannot honour): exit 2, like clap's own.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

/// `--board COLSxROWS --square MM`: a plain chessboard instead of a rig file (`calibrate`, `detect`;
/// each of them has a `--rig` this conflicts with).
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct BoardArgs {
    /// A plain chessboard instead of a rig file: inner corners COLSxROWS, as OpenCV counts them
    /// (9x6 for a board of 10 × 7 squares). Needs --square.
    #[arg(
        long,
        value_name = "COLSxROWS",
        conflicts_with = "rig",
        requires = "square"
    )]
    pub board: Option<cubecal::rig::BoardSize>,
    /// The --board's square size in millimetres.
    #[arg(long, value_name = "MM", requires = "board")]
    pub square: Option<f64>,
}

impl BoardArgs {
    /// The board and its square size, when given (clap requires both together).
    pub fn board(&self) -> Option<(cubecal::rig::BoardSize, f64)> {
        self.board.zip(self.square)
    }
}

/// A result location the command could not create or write (exit 7, `exit::IO`).
#[derive(Debug, thiserror::Error)]
#[error("cannot write {path}")]
pub struct OutputError {
    pub path: std::path::PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// Failing to write a result file the user asked for (an overlay, a rendered frame, a target SVG):
/// the user's path is named, and the code is `exit::IO` (7), as the README documents. (The library's
/// own `exit_code()` of these write errors still says 1; this takes precedence.)
fn output_write_failure(cause: &(dyn std::error::Error + 'static)) -> bool {
    use cubecal::detect::overlay::OverlayError;
    use cubecal::render::SyntheticError;
    use cubecal::rig::RigError;
    cause.downcast_ref::<OutputError>().is_some()
        || matches!(
            cause.downcast_ref::<RigError>(),
            Some(RigError::Write { .. })
        )
        || matches!(
            cause.downcast_ref::<SyntheticError>(),
            Some(SyntheticError::Write { .. })
        )
        || matches!(
            cause.downcast_ref::<OverlayError>(),
            Some(OverlayError::Write { .. })
        )
        || matches!(
            cause.downcast_ref::<detect::DetectCliError>(),
            Some(detect::DetectCliError::CreateOverlayDir { .. })
        )
}

/// Map an error to its exit code: the first library error found in the chain decides.
pub(crate) fn exit_code_for(err: &anyhow::Error) -> u8 {
    for cause in err.chain() {
        if cause.downcast_ref::<UsageError>().is_some() {
            return exit::USAGE;
        }
        if output_write_failure(cause) {
            return exit::IO;
        }
        if let Some(e) = cause.downcast_ref::<cubecal::calib::CalibError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::calib::observations::ObservationsError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::rig::RigError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::capture::CaptureError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::render::SyntheticError>() {
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
        if let Some(e) = cause.downcast_ref::<cubecal::capture::feed::FeedError>() {
            return e.exit_code();
        }
        if let Some(e) = cause.downcast_ref::<cubecal::station::setup::SetupError>() {
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
        if let Some(e) = cause.downcast_ref::<cubecal::live::LiveError>() {
            return e.exit_code();
        }
        if cause.downcast_ref::<profile::UsageError>().is_some() {
            return exit::USAGE;
        }
    }
    exit::INTERNAL
}

/// Print an error once, with its chain of causes, to stderr (and as JSON on stdout with `--json`).
#[allow(clippy::print_stderr)]
fn report_error(err: &anyhow::Error, out: Output) {
    let chain: Vec<String> = err.chain().map(cause_text).collect();
    if out.json {
        let v = serde_json::json!({ "error": chain.first(), "causes": &chain[1..], "exit_code": exit_code_for(err) });
        let _ = outln!("{v}");
    }
    eprintln!("error: {}", chain.join("\n  caused by: "));
}

/// Longest line of an error message printed whole; longer ones (a parser quoting a 100 KB one-line
/// file) are cut.
const MAX_ERROR_LINE_CHARS: usize = 240;

/// One cause as printed: an I/O error behind a write names the OS reason only (the user's path is in
/// the message above it; the temporary file's is of no use), and over-long lines are cut.
fn cause_text(cause: &(dyn std::error::Error + 'static)) -> String {
    let mut text = cause.to_string();
    // tempfile reports a failed temporary file as `<OS error> at path "<dir>/.tmpXXXX"` and hides the
    // OS error itself (its `source()` skips it), so the temporary path is cut from the text.
    if cause.downcast_ref::<std::io::Error>().is_some()
        && let Some(at) = text.find(" at path \"")
        && text[at..].contains("/.tmp")
    {
        text.truncate(at);
    }
    text.lines()
        .map(|line| {
            let n = line.chars().count();
            if n > MAX_ERROR_LINE_CHARS {
                let cut: String = line.chars().take(MAX_ERROR_LINE_CHARS - 40).collect();
                format!(
                    "{cut}… ({} more characters)",
                    n - (MAX_ERROR_LINE_CHARS - 40)
                )
            } else {
                line.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}
