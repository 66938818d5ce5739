//! Turntable: the [`Turntable`] trait the station drives, serial drivers for GRBL 1.1 and Zaber ASCII, a
//! manual (operator) driver, a fixed rig, an in-memory fake and protocol simulators.
//!
//! # Design
//! The station needs four things from a turntable: [`home`](Turntable::home) it,
//! [`move_to`](Turntable::move_to) an absolute angle *and only return once the stage reports it has
//! settled*, read its [`position`](Turntable::position) and [`stop`](Turntable::stop) it. The trait has
//! exactly those, plus [`describe`](Turntable::describe) (what are we talking to, for logs and
//! `cubecal turntable probe`) and [`resolution`](Turntable::resolution) (the smallest step the stage can
//! report, which is also the tolerance used when a settled position is checked against the command).
//! Angles cross this boundary as [`Degrees`]; nothing else does.
//!
//! Each protocol is split in two layers:
//! - **pure encode/decode** ([`grbl`] and [`zaber`] module functions: `encode_*`, `decode_*`), no I/O,
//!   table-tested and fuzzed with proptest;
//! - **a driver** ([`grbl::GrblTurntable`], [`zaber::ZaberTurntable`]) generic over a [`serial::Link`], a
//!   two-method byte stream with a timeout on every read. `Link` is implemented for
//!   `Box<dyn serialport::SerialPort>` and [`serialport::TTYPort`], so the same driver code runs against
//!   a USB adapter and against a simulator on the other end of a pseudo-terminal.
//!
//! [`sim`] holds one simulator per protocol. Each serves the master end of a pty pair
//! (`TTYPort::pair`) from a thread, moves with an acceleration-limited trapezoidal profile
//! ([`sim::Trapezoid`]), and can inject faults ([`sim::Fault`]): no reply, garbage, an alarm/stall
//! mid-move, lost steps, the port closing. [`fake::FakeTurntable`] is an instant in-memory
//! implementation with scripted failures. [`manual::ManualTurntable`] asks an operator through an
//! injectable [`manual::Operator`]; [`manual::FixedRig`] is the "no turntable" case. One contract test
//! suite (`tests/turntable_contract.rs`) runs the same functions against the fake and against both
//! drivers talking to their simulators.
//!
//! A second axis: [`stage::TiltStage`] puts a rotation stage on a tilting cradle driven by a second
//! driver (its own serial link: a second GRBL controller's axis, a second Zaber device), with limits
//! and homing per axis; the trait's [`tilt_limits`](Turntable::tilt_limits) and
//! [`tilt_to`](Turntable::tilt_to) default to "no tilt axis", so one-axis stages are unchanged.
//!
//! # Protocols
//! **GRBL 1.1** (G-code over serial, 115200 8N1). Line commands end in `\n` and are answered by `ok`,
//! `error:N` or, asynchronously, `ALARM:N`; [`grbl::error_meaning`] and [`grbl::alarm_meaning`] carry
//! the GRBL 1.1 tables so an error says what the code means. Homing is `$H` when the machine has homing
//! switches configured (`GrblConfig::homing`), otherwise `$X` (unlock) and a move to 0. Moves are
//! `G90 G53 G0 <axis><units>` on a configurable axis (`X`…`C`) with a degrees-per-unit factor: absolute,
//! in *machine* coordinates, so angles are read straight from `MPos` (GRBL's default report) and a
//! work offset left behind by someone's `G92` cannot shift them. 0° is therefore the machine origin;
//! after `$H` GRBL puts the axis at −pull-off (`$27`), which [`Turntable::home`] reports as it is. `ok` only
//! means "planned", so the driver then polls the real-time `?` (one byte, no newline; the answer is one
//! `<State|MPos:…|…>` line and no `ok`) until the state is `Idle` *and* the reported position is within
//! the resolution of the target. [`Turntable::stop`] sends feed hold `!`, waits for the hold to
//! complete, then soft reset `0x18` (which leaves GRBL in `ALARM:3` if it was moving: home again).
//!
//! **Zaber ASCII** (115200 8N1). Commands `/<device> <axis> <command>\n`; replies
//! `@<device> <axis> <OK|RJ> <IDLE|BUSY> <warning flag or --> <data>`. The driver uses `home`,
//! `move abs <microsteps>`, the empty command (status) and `get pos`, polls status until `IDLE`, converts
//! microsteps ↔ degrees with `ZaberConfig::microsteps_per_degree`, turns `RJ` into
//! [`TurntableError::ZaberRejected`] with a typed [`zaber::Rejection`], and surfaces warning flags as
//! typed [`zaber::Flag`]s: fault flags (`F…`) end the operation with [`TurntableError::ZaberFault`],
//! other flags are logged with `tracing::warn!`.
//!
//! # Timeouts and retries (every wait has a deadline)
//! - Every exchange waits at most `exchange_timeout` for its reply (default 500 ms).
//! - Zaber commands are all idempotent (absolute moves, queries, home, stop) and every attempt carries
//!   its own message id (`/1 1 17 get pos` → `@01 1 17 …`), so a late reply to an earlier attempt is
//!   recognised and skipped. A command without a reply (or with a garbled one) is re-sent up to
//!   `retries` more times (default 2). Bound per exchange: `exchange_timeout × (retries + 1)`, 1.5 s
//!   by default.
//! - GRBL line commands are **not** re-sent: GRBL answers every line with exactly one `ok`/`error`, and
//!   re-sending a line whose `ok` was merely late would shift every later reply by one. A missing reply
//!   fails after one `exchange_timeout`. Only the real-time `?`, which has no such counting, is retried
//!   up to `status_retries` times (same bound as a Zaber exchange). GRBL replies carry no ids, so
//!   before each exchange the driver consumes lines that arrived late (an `ALARM:N` among them is still
//!   an error), and when several status reports are waiting the newest wins.
//! - Opening an Arduino's USB port resets it (DTR) and GRBL ignores input for 1–2 s while it boots, so
//!   before its first exchange the GRBL driver polls `?` for up to `startup_wait` (default 3 s).
//! - On top of that each operation has an overall deadline: `move_timeout` for a move (command, motion,
//!   polling, read-back; default 60 s), `home_timeout` for homing (default 120 s). No wait inside an
//!   operation extends past it, so a move settles or fails with a typed error within `move_timeout`.
//! - A settled position is accepted when it is within [`Turntable::resolution`] of the target; GRBL
//!   must additionally report `Idle` away from the target [`grbl::SETTLE_CONFIRMATIONS`] times in a
//!   row before that is called [`TurntableError::PositionMismatch`] (its `ok` precedes the motion).
//!
//! What a fault becomes: silence → [`TurntableError::Timeout`] (with any partial bytes, escaped);
//! bytes that are not the protocol → [`TurntableError::UnexpectedReply`] (escaped); a closed or
//! unplugged port → [`TurntableError::Disconnected`]; `ALARM:N` → [`TurntableError::GrblAlarm`] with
//! the table's meaning; a Zaber `F…` flag → [`TurntableError::ZaberFault`]; settling in the wrong place
//! → [`TurntableError::PositionMismatch`]; never settling → [`TurntableError::MoveTimeout`].
//! `tests/turntable_contract.rs` injects each fault through the simulators and checks the variant and
//! the time taken against these bounds (with 100 ms exchanges and 2 retries there).
//!
//! The constants [`DEFAULT_EXCHANGE_TIMEOUT`], [`DEFAULT_RETRIES`], [`DEFAULT_MOVE_TIMEOUT`],
//! [`DEFAULT_HOME_TIMEOUT`] and [`DEFAULT_POLL_INTERVAL`] are the defaults for real hardware; tests use
//! much shorter ones.
//!
//! # Why hand-written
//! There is no maintained Rust crate for either protocol: the GRBL crates on crates.io are G-code
//! *parsers* or senders for CNC jobs (streaming files, no status-polled absolute positioning), and Zaber
//! publishes its Motion Library for Python/C#/C++/Java but nothing for Rust. Both protocols are small,
//! line-based ASCII; the part worth owning is the timeout/retry/settle logic, which is station-specific.
//!
//! # Testing against hardware
//! `CUBECAL_TURNTABLE_PORT=/dev/ttyUSB0 CUBECAL_TURNTABLE_PROTOCOL=grbl|zaber cargo test --test
//! turntable_contract -- --ignored` runs the contract against a real stage. For bring-up,
//! `cubecal turntable simulate --protocol grbl` serves a simulator on a pty and prints its path;
//! `udev/99-cubecal.rules` gives the `dialout` group access to common USB-serial adapters.

use std::fmt;
use std::io;
use std::time::Duration;

pub mod fake;
pub mod grbl;
pub mod manual;
pub mod serial;
pub mod sim;
pub mod stage;
pub mod zaber;

/// Default wait for one reply from the stage.
pub const DEFAULT_EXCHANGE_TIMEOUT: Duration = Duration::from_millis(500);
/// Default number of re-sends after a missing or garbled reply (for commands that may be re-sent).
pub const DEFAULT_RETRIES: u32 = 2;
/// Default limit for one move, from sending the command to the settled read-back.
pub const DEFAULT_MOVE_TIMEOUT: Duration = Duration::from_secs(60);
/// Default limit for homing (a homing search can take a full revolution at low speed).
pub const DEFAULT_HOME_TIMEOUT: Duration = Duration::from_secs(120);
/// Default interval between status polls while a move is under way.
pub const DEFAULT_POLL_INTERVAL: Duration = Duration::from_millis(50);

/// An angle in degrees: the unit of every angle at the turntable boundary.
#[derive(
    Debug, Clone, Copy, PartialEq, PartialOrd, Default, serde::Serialize, serde::Deserialize,
)]
pub struct Degrees(pub f64);

impl Degrees {
    /// Validate an angle coming from a user or a config: finite, and within ±`MAX_ABS_DEGREES`.
    pub fn checked(value: f64) -> Result<Degrees, TurntableError> {
        if !value.is_finite() {
            return Err(TurntableError::InvalidAngle {
                value,
                reason: "not a finite number",
            });
        }
        if value.abs() > MAX_ABS_DEGREES {
            return Err(TurntableError::InvalidAngle {
                value,
                reason: "beyond ±3600° (ten turns)",
            });
        }
        Ok(Degrees(value))
    }

    /// Is `self` within `tolerance` of `other`?
    pub fn within(self, other: Degrees, tolerance: Degrees) -> bool {
        (self.0 - other.0).abs() <= tolerance.0
    }
}

/// Largest absolute angle accepted by [`Degrees::checked`]: ten turns, far beyond any station pose.
pub const MAX_ABS_DEGREES: f64 = 3600.0;

impl fmt::Display for Degrees {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match f.precision() {
            Some(p) => write!(f, "{:.*}°", p, self.0),
            None => {
                // Micro-degree precision without trailing zeros: 90.125°, 0.000234°, 30.0°.
                let s = format!("{:.6}", self.0);
                let s = s.trim_end_matches('0');
                let s = if s.ends_with('.') {
                    format!("{s}0")
                } else {
                    s.to_string()
                };
                write!(f, "{s}°")
            }
        }
    }
}

/// What the station needs from a turntable. Implementations: [`grbl::GrblTurntable`],
/// [`zaber::ZaberTurntable`], [`manual::ManualTurntable`], [`manual::FixedRig`], [`fake::FakeTurntable`].
pub trait Turntable: Send {
    /// Identify the device (firmware, protocol) for logs and bring-up.
    fn describe(&mut self) -> Result<String, TurntableError>;
    /// Find the reference position and return the settled position afterwards: 0°, except for GRBL
    /// with homing switches, which reports where its homing cycle left the axis (−pull-off).
    fn home(&mut self) -> Result<Degrees, TurntableError>;
    /// Move to an absolute angle; return only once the stage reports it has settled, with the settled
    /// position (within [`resolution`](Turntable::resolution) of `target`, otherwise an error).
    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError>;
    /// The current position as reported by the stage.
    fn position(&mut self) -> Result<Degrees, TurntableError>;
    /// Stop any motion now.
    fn stop(&mut self) -> Result<(), TurntableError>;
    /// The smallest position step the stage reports; the tolerance of a settled read-back.
    fn resolution(&self) -> Degrees;
    /// The tilt axis's limits, when the stage has one ([`stage::TiltStage`]); `None` for a
    /// one-axis turntable (the default).
    fn tilt_limits(&self) -> Option<(Degrees, Degrees)> {
        None
    }
    /// Tilt to an absolute angle within [`tilt_limits`](Turntable::tilt_limits) and return the
    /// settled tilt, as [`move_to`](Turntable::move_to) does for the rotation.
    fn tilt_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        Err(TurntableError::NoTiltAxis { requested: target })
    }
    /// Whether a person moves this stage ([`manual::ManualTurntable`]): the station then words each
    /// pose as one instruction and hands it to [`by_hand`](Turntable::by_hand).
    fn is_manual(&self) -> bool {
        false
    }
    /// A stage moved by a person: have the whole pose carried out from `instruction` (which names
    /// the rotation and tilt marks) and return the (rotation, tilt) confirmed. Motorised stages are
    /// moved axis by axis instead: the default moves the tilt, then the rotation.
    fn by_hand(
        &mut self,
        _instruction: &str,
        rotation: Degrees,
        tilt: Option<Degrees>,
    ) -> Result<(Degrees, Option<Degrees>), TurntableError> {
        let t = tilt.map(|t| self.tilt_to(t)).transpose()?;
        Ok((self.move_to(rotation)?, t))
    }
}

impl<T: Turntable + ?Sized> Turntable for Box<T> {
    fn describe(&mut self) -> Result<String, TurntableError> {
        (**self).describe()
    }
    fn home(&mut self) -> Result<Degrees, TurntableError> {
        (**self).home()
    }
    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        (**self).move_to(target)
    }
    fn position(&mut self) -> Result<Degrees, TurntableError> {
        (**self).position()
    }
    fn stop(&mut self) -> Result<(), TurntableError> {
        (**self).stop()
    }
    fn resolution(&self) -> Degrees {
        (**self).resolution()
    }
    fn tilt_limits(&self) -> Option<(Degrees, Degrees)> {
        (**self).tilt_limits()
    }
    fn tilt_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        (**self).tilt_to(target)
    }
    fn is_manual(&self) -> bool {
        (**self).is_manual()
    }
    fn by_hand(
        &mut self,
        instruction: &str,
        rotation: Degrees,
        tilt: Option<Degrees>,
    ) -> Result<(Degrees, Option<Degrees>), TurntableError> {
        (**self).by_hand(instruction, rotation, tilt)
    }
}

/// Errors from turntable drivers. Every variant says what happened; causes are chained, not repeated.
#[derive(Debug, thiserror::Error)]
pub enum TurntableError {
    /// The serial port does not exist (unplugged, wrong path).
    #[error("turntable port {path} does not exist")]
    PortNotFound {
        path: String,
        #[source]
        source: serialport::Error,
    },
    /// Another process holds the port.
    #[error("turntable port {path} is busy (another program has it open)")]
    PortBusy {
        path: String,
        #[source]
        source: serialport::Error,
    },
    /// The user may not open the port.
    #[error("permission denied opening turntable port {path}")]
    PermissionDenied {
        path: String,
        #[source]
        source: serialport::Error,
    },
    /// The serial port could not be opened for another reason.
    #[error("cannot open turntable port {path}")]
    Open {
        path: String,
        #[source]
        source: serialport::Error,
    },
    /// The port went away (device unplugged, other end closed) during an exchange.
    #[error("turntable port closed or disconnected while {during}")]
    Disconnected {
        during: String,
        #[source]
        source: io::Error,
    },
    /// Any other serial I/O failure.
    #[error("serial I/O error while {during}")]
    Io {
        during: String,
        #[source]
        source: io::Error,
    },
    /// No (complete) reply within the exchange timeout, after every allowed attempt.
    #[error(
        "no reply to {command} within {timeout:?} ({attempts} attempt(s)){}",
        received_suffix(received)
    )]
    Timeout {
        command: String,
        timeout: Duration,
        attempts: u32,
        /// Bytes received without a line ending, escaped (empty when nothing came back).
        received: String,
    },
    /// Replies kept coming but the stage did not settle at the target before the move deadline.
    #[error("turntable did not settle at {target} within {limit:?} (last reported: {last_state})")]
    MoveTimeout {
        target: Degrees,
        limit: Duration,
        last_state: String,
    },
    /// A reply that does not fit the protocol; the bytes are shown escaped.
    #[error("unexpected reply to {command}: \"{reply}\" (expected {expected})")]
    UnexpectedReply {
        command: String,
        expected: &'static str,
        reply: String,
    },
    /// GRBL answered `error:N`.
    #[error("GRBL rejected {command}: error:{code} ({meaning})")]
    GrblError {
        command: String,
        code: u16,
        meaning: &'static str,
    },
    /// GRBL raised `ALARM:N`.
    #[error("GRBL alarm {code}: {meaning}")]
    GrblAlarm { code: u16, meaning: &'static str },
    /// GRBL printed its start-up banner in the middle of an operation: it was reset (power or USB
    /// glitch, someone pressed reset), so its position can no longer be trusted.
    #[error("GRBL restarted unexpectedly (power, USB or reset button?): home it again")]
    GrblRestarted,
    /// GRBL reports the Alarm state without a fresh `ALARM:N` line (e.g. after a reset or at power-up).
    #[error(
        "GRBL is in the Alarm state (position not trusted): home it ($H) or unlock it ($X) first"
    )]
    GrblLocked,
    /// A Zaber device answered `RJ`.
    #[error("Zaber device rejected {command}: {reason}")]
    ZaberRejected {
        command: String,
        reason: zaber::Rejection,
    },
    /// A Zaber device raised a fault flag (`F…`).
    #[error("Zaber device reports fault {flag} during {command}")]
    ZaberFault { command: String, flag: zaber::Flag },
    /// The stage settled somewhere other than where it was sent (lost steps, stall, obstruction).
    #[error(
        "turntable settled at {reported} after a move to {commanded} (tolerance {tolerance}): lost steps or an obstruction"
    )]
    PositionMismatch {
        commanded: Degrees,
        reported: Degrees,
        tolerance: Degrees,
    },
    /// An angle that cannot be commanded.
    #[error("invalid angle {value}: {reason}")]
    InvalidAngle { value: f64, reason: &'static str },
    /// A configuration value that cannot work.
    #[error("invalid turntable configuration: {field}: {reason}")]
    InvalidConfig { field: &'static str, reason: String },
    /// The operator of a manual turntable declined a request.
    #[error("the operator did not confirm: {instruction}")]
    OperatorDeclined { instruction: String },
    /// The operator could not be asked (terminal closed).
    #[error("cannot ask the operator")]
    Operator {
        #[source]
        source: io::Error,
    },
    /// A tilt was asked of a stage without a tilt axis.
    #[error("the stage has no tilt axis: cannot tilt to {requested}")]
    NoTiltAxis { requested: Degrees },
    /// A move beyond an axis's configured limits.
    #[error("{axis} {requested} is beyond the axis's limits [{min}, {max}]")]
    BeyondLimit {
        axis: &'static str,
        requested: Degrees,
        min: Degrees,
        max: Degrees,
    },
    /// A fixed rig (no turntable) was asked to move.
    #[error("the rig is fixed (no turntable): cannot move to {requested}")]
    FixedRig { requested: Degrees },
    /// A simulator could not be set up (pseudo-terminal allocation failed).
    #[error("cannot start the turntable simulator: {during}")]
    Simulator {
        during: &'static str,
        #[source]
        source: serialport::Error,
    },
}

fn received_suffix(received: &str) -> String {
    if received.is_empty() {
        String::new()
    } else {
        format!("; received only \"{received}\"")
    }
}

impl TurntableError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        use crate::exit;
        match self {
            TurntableError::PortNotFound { .. }
            | TurntableError::PortBusy { .. }
            | TurntableError::PermissionDenied { .. }
            | TurntableError::Open { .. }
            | TurntableError::Disconnected { .. }
            | TurntableError::Io { .. }
            | TurntableError::Timeout { .. }
            | TurntableError::MoveTimeout { .. }
            | TurntableError::UnexpectedReply { .. }
            | TurntableError::GrblError { .. }
            | TurntableError::GrblAlarm { .. }
            | TurntableError::GrblLocked
            | TurntableError::GrblRestarted
            | TurntableError::ZaberRejected { .. }
            | TurntableError::ZaberFault { .. }
            | TurntableError::PositionMismatch { .. }
            | TurntableError::OperatorDeclined { .. }
            | TurntableError::Operator { .. } => exit::DEVICE,
            TurntableError::InvalidAngle { .. }
            | TurntableError::InvalidConfig { .. }
            | TurntableError::FixedRig { .. }
            | TurntableError::NoTiltAxis { .. }
            | TurntableError::BeyondLimit { .. } => exit::BAD_INPUT,
            TurntableError::Simulator { .. } => exit::INTERNAL,
        }
    }
}

/// Escape bytes for an error message: printable ASCII as is, everything else as `\xNN`, `\r`, `\n`.
pub fn escape_bytes(bytes: &[u8]) -> String {
    bytes.escape_ascii().to_string()
}

/// A poll that failed because the move's own deadline cut it short is a [`TurntableError::MoveTimeout`]
/// (the stage was answering but had not settled), not a reply timeout. Any other error passes through.
pub(crate) fn out_of_time(
    e: TurntableError,
    deadline: std::time::Instant,
    target: Degrees,
    limit: Duration,
    last_state: Option<String>,
) -> TurntableError {
    match e {
        TurntableError::Timeout { attempts, .. }
            if std::time::Instant::now() >= deadline && (last_state.is_some() || attempts == 0) =>
        {
            TurntableError::MoveTimeout {
                target,
                limit,
                last_state: last_state.unwrap_or_else(|| "no status yet".into()),
            }
        }
        e => e,
    }
}

/// Check a timing configuration value is usable (non-zero).
pub(crate) fn nonzero(field: &'static str, d: Duration) -> Result<(), TurntableError> {
    if d.is_zero() {
        Err(TurntableError::InvalidConfig {
            field,
            reason: "must be greater than zero".into(),
        })
    } else {
        Ok(())
    }
}

/// Whether `position` (the tilt a stage would reach for `requested`) lies within the tilt axis's
/// `[min, max]`; else [`TurntableError::BeyondLimit`] naming the request.
pub(crate) fn check_tilt(
    position: Degrees,
    requested: Degrees,
    (min, max): (Degrees, Degrees),
) -> Result<(), TurntableError> {
    if position.0 < min.0 || position.0 > max.0 {
        return Err(TurntableError::BeyondLimit {
            axis: "tilt",
            requested,
            min,
            max,
        });
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    #[test]
    fn degrees_checked_rejects_non_finite_and_huge() {
        assert!(Degrees::checked(f64::NAN).is_err());
        assert!(Degrees::checked(f64::INFINITY).is_err());
        assert!(Degrees::checked(3600.1).is_err());
        assert_eq!(Degrees::checked(-90.0).ok(), Some(Degrees(-90.0)));
    }

    #[test]
    fn degrees_display_keeps_small_steps_visible() {
        assert_eq!(Degrees(90.0).to_string(), "90.0°");
        assert_eq!(Degrees(90.125).to_string(), "90.125°");
        assert_eq!(Degrees(0.000_234_375).to_string(), "0.000234°");
        assert_eq!(format!("{:.1}", Degrees(29.96)), "30.0°");
    }

    #[test]
    fn escape_shows_control_bytes() {
        assert_eq!(escape_bytes(b"ok\r\n\x18\xff"), "ok\\r\\n\\x18\\xff");
    }
}
