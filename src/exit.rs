//! Process exit codes. These are an API: scripts and the systemd unit depend on them, and the README
//! carries the same table. Every library error maps to exactly one of these in `cli`.

/// Everything worked.
pub const SUCCESS: u8 = 0;
/// A bug or an unexpected condition inside cubecal (please report it).
pub const INTERNAL: u8 = 1;
/// Command-line usage error (unknown flag, missing argument). clap uses this code too.
pub const USAGE: u8 = 2;
/// Bad input or configuration: unreadable/malformed file, invalid values, degenerate data.
pub const BAD_INPUT: u8 = 3;
/// A device (camera, turntable port) is missing, busy, not permitted, or failed mid-run.
pub const DEVICE: u8 = 4;
/// The solver could not produce a calibration (no convergence, numerically degenerate problem).
pub const CALIBRATION_FAILED: u8 = 5;
/// A calibration was computed but rejected by quality checks; no profile was written.
pub const QA_REJECTED: u8 = 6;
/// An output file (run directory, profile, overlay, report) could not be written: disk full, no
/// permission, missing directory. Nothing that was there before was replaced.
pub const IO: u8 = 7;
/// Interrupted by SIGINT or SIGTERM: the turntable was stopped, the session closed and marked
/// incomplete, no profile written (128 + SIGINT, as shells report it).
pub const INTERRUPTED: u8 = 130;
