//! GRBL 1.1: pure encode/decode of the serial protocol, the GRBL 1.1 error and alarm tables, and
//! [`GrblTurntable`], a driver generic over a [`Link`].
//!
//! Only what a turntable needs: `$X`, `$H`, `$I`, `G90 G53 G0 <axis><value>`, the real-time bytes `?`, `!`,
//! `~` and soft reset `0x18`. See the [module docs](super) for the timeout and retry rules.

use std::time::{Duration, Instant};

use super::serial::{self, LineError, LineIo, Link};
use super::{Degrees, Turntable, TurntableError, escape_bytes};

/// Real-time status query (no newline; answered by one `<…>` line and no `ok`).
pub const STATUS_QUERY: u8 = b'?';
/// Real-time feed hold: decelerate to a stop and hold.
pub const FEED_HOLD: u8 = b'!';
/// Real-time cycle start / resume.
pub const CYCLE_START: u8 = b'~';
/// Real-time soft reset (Ctrl-X). Resetting while moving raises `ALARM:3`.
pub const SOFT_RESET: u8 = 0x18;

/// Decimal places GRBL reports positions with (in millimetre mode, the default `$13=0`).
pub const REPORT_DECIMALS: i32 = 3;

/// How long to wait for GRBL to answer its first status query. Opening the USB port of an Arduino
/// resets it (DTR), and GRBL needs about 1–2 s to boot before it answers anything.
pub const DEFAULT_STARTUP_WAIT: Duration = Duration::from_secs(3);

/// How many consecutive `Idle` reports away from the target are needed before a move is declared to
/// have settled in the wrong place (a single early `Idle` can precede the start of motion).
pub const SETTLE_CONFIRMATIONS: u32 = 3;

/// A GRBL axis letter. Standard GRBL has X, Y, Z; forks (grblHAL, 4/6-axis builds) add A, B, C, which
/// is where a rotary table usually lives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Axis {
    X,
    Y,
    Z,
    A,
    B,
    C,
}

impl Axis {
    /// All axes in report order.
    pub const ALL: [Axis; 6] = [Axis::X, Axis::Y, Axis::Z, Axis::A, Axis::B, Axis::C];

    /// The G-code letter.
    pub fn letter(self) -> char {
        match self {
            Axis::X => 'X',
            Axis::Y => 'Y',
            Axis::Z => 'Z',
            Axis::A => 'A',
            Axis::B => 'B',
            Axis::C => 'C',
        }
    }

    /// Index of this axis in a status report's comma-separated position list.
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
            Axis::A => 3,
            Axis::B => 4,
            Axis::C => 5,
        }
    }

    /// Parse a letter (either case).
    pub fn from_letter(c: char) -> Option<Axis> {
        Axis::ALL
            .into_iter()
            .find(|a| a.letter() == c.to_ascii_uppercase())
    }
}

/// `$X`: unlock after an alarm (without homing).
pub fn encode_unlock() -> &'static [u8] {
    b"$X\n"
}

/// `$H`: run the homing cycle (needs `$22=1`).
pub fn encode_home() -> &'static [u8] {
    b"$H\n"
}

/// `$I`: build info (`[VER:…]`, `[OPT:…]`, `ok`).
pub fn encode_build_info() -> &'static [u8] {
    b"$I\n"
}

/// An absolute rapid move of one axis in *machine* coordinates (`G53`, so work offsets an operator may
/// have set with `G10`/`G92` do not shift the table's angles), with GRBL's reporting precision.
pub fn encode_move(axis: Axis, units: f64) -> String {
    format!(
        "G90 G53 G0 {}{:.*}\n",
        axis.letter(),
        REPORT_DECIMALS as usize,
        units
    )
}

/// The machine state at the head of a status report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum State {
    Idle,
    Run,
    /// Feed hold; sub-state 0 = hold complete, 1 = decelerating.
    Hold,
    Jog,
    Alarm,
    Door,
    Check,
    Home,
    Sleep,
}

impl State {
    fn parse(s: &str) -> Option<State> {
        Some(match s {
            "Idle" => State::Idle,
            "Run" => State::Run,
            "Hold" => State::Hold,
            "Jog" => State::Jog,
            "Alarm" => State::Alarm,
            "Door" => State::Door,
            "Check" => State::Check,
            "Home" => State::Home,
            "Sleep" => State::Sleep,
            _ => return None,
        })
    }
}

/// A decoded `<State|MPos:…|…>` report. Positions are in machine units, one entry per axis.
#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    pub state: State,
    pub substate: Option<u8>,
    /// Machine position (`MPos`), when reported (`$10` bit 0 = 1, the default).
    pub mpos: Option<Vec<f64>>,
    /// Work position (`WPos`), when reported instead.
    pub wpos: Option<Vec<f64>>,
    /// Work coordinate offset (`WCO`), reported every 10–30 status reports.
    pub wco: Option<Vec<f64>>,
}

impl Status {
    /// Machine position of `axis` (what `G53` moves address): `MPos` (reported by default, `$10=1`),
    /// or `WPos + WCO` when the controller reports work positions (`$10=0`) and an offset is known.
    pub fn machine_position(&self, axis: Axis, wco: &[f64]) -> Option<f64> {
        let i = axis.index();
        if let Some(m) = &self.mpos {
            return m.get(i).copied();
        }
        let w = self.wpos.as_ref()?.get(i).copied()?;
        Some(w + wco.get(i).copied().unwrap_or(0.0))
    }
}

/// One decoded line from GRBL.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// `ok`: the line was accepted (for motion: planned, not finished).
    Ok,
    /// `error:N`.
    Error(u16),
    /// `ALARM:N`.
    Alarm(u16),
    /// `<…>` status report.
    Status(Status),
    /// `Grbl 1.1h ['$' for help]`, printed at power-up and after a soft reset.
    Welcome { version: String },
    /// `[…]` feedback message (`MSG:`, `VER:`, `OPT:`, `GC:`, …), contents without brackets.
    Feedback(String),
    /// `$N=value` setting line (answer to `$$`).
    Setting(String),
}

/// Why a line could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{reason}: \"{line}\"")]
pub struct DecodeError {
    pub reason: &'static str,
    /// The line, escaped.
    pub line: String,
}

fn bad(reason: &'static str, line: &[u8]) -> DecodeError {
    DecodeError {
        reason,
        line: escape_bytes(line),
    }
}

/// Decode one line (without its line ending).
pub fn decode_line(line: &[u8]) -> Result<Reply, DecodeError> {
    let text = std::str::from_utf8(line).map_err(|_| bad("not ASCII", line))?;
    let text = text.trim();
    if text == "ok" {
        return Ok(Reply::Ok);
    }
    if let Some(code) = text.strip_prefix("error:") {
        return code
            .parse()
            .map(Reply::Error)
            .map_err(|_| bad("bad error code", line));
    }
    if let Some(code) = text.strip_prefix("ALARM:") {
        return code
            .parse()
            .map(Reply::Alarm)
            .map_err(|_| bad("bad alarm code", line));
    }
    if let Some(inner) = text.strip_prefix('<') {
        let inner = inner
            .strip_suffix('>')
            .ok_or_else(|| bad("status report without '>'", line))?;
        return decode_status(inner)
            .map(Reply::Status)
            .ok_or_else(|| bad("malformed status report", line));
    }
    if let Some(inner) = text.strip_prefix('[') {
        let inner = inner
            .strip_suffix(']')
            .ok_or_else(|| bad("feedback message without ']'", line))?;
        return Ok(Reply::Feedback(inner.to_string()));
    }
    if let Some(rest) = text.strip_prefix("Grbl ") {
        let version = rest.split_whitespace().next().unwrap_or_default();
        return Ok(Reply::Welcome {
            version: version.to_string(),
        });
    }
    if text.starts_with('$') && text.contains('=') {
        return Ok(Reply::Setting(text.to_string()));
    }
    Err(bad("not a GRBL reply", line))
}

fn decode_numbers(s: &str) -> Option<Vec<f64>> {
    let v: Vec<f64> = s
        .split(',')
        .map(|n| n.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()?;
    (!v.is_empty() && v.len() <= Axis::ALL.len()).then_some(v)
}

/// Decode the inside of `<…>`.
pub fn decode_status(inner: &str) -> Option<Status> {
    let mut fields = inner.split('|');
    let head = fields.next()?;
    let (state, substate) = match head.split_once(':') {
        Some((s, sub)) => (State::parse(s)?, Some(sub.parse().ok()?)),
        None => (State::parse(head)?, None),
    };
    let mut status = Status {
        state,
        substate,
        mpos: None,
        wpos: None,
        wco: None,
    };
    for field in fields {
        let (key, value) = field.split_once(':')?;
        match key {
            "MPos" => status.mpos = Some(decode_numbers(value)?),
            "WPos" => status.wpos = Some(decode_numbers(value)?),
            "WCO" => status.wco = Some(decode_numbers(value)?),
            _ => {} // Bf, Ln, F, FS, Pn, Ov, A: not needed here.
        }
    }
    if status.mpos.is_none() && status.wpos.is_none() {
        return None;
    }
    Some(status)
}

/// Meaning of `error:N` (GRBL 1.1 `error_codes_en_US.csv`).
pub fn error_meaning(code: u16) -> &'static str {
    match code {
        1 => {
            "Expected command letter: G-code words consist of a letter and a value. Letter was not found."
        }
        2 => {
            "Bad number format: Missing the expected G-code word value or numeric value format is not valid."
        }
        3 => "Invalid statement: Grbl '$' system command was not recognized or supported.",
        4 => "Value < 0: Negative value received for an expected positive value.",
        5 => "Setting disabled: Homing cycle failure. Homing is not enabled via settings.",
        6 => "Value < 3 usec: Minimum step pulse time must be greater than 3usec.",
        7 => {
            "EEPROM read fail. Using defaults: An EEPROM read failed. Auto-restoring affected EEPROM to default values."
        }
        8 => {
            "Not idle: Grbl '$' command cannot be used unless Grbl is IDLE. Ensures smooth operation during a job."
        }
        9 => "G-code lock: G-code commands are locked out during alarm or jog state.",
        10 => "Homing not enabled: Soft limits cannot be enabled without homing also enabled.",
        11 => {
            "Line overflow: Max characters per line exceeded. Received command line was not executed."
        }
        12 => {
            "Step rate > 30kHz: Grbl '$' setting value cause the step rate to exceed the maximum supported."
        }
        13 => "Check Door: Safety door detected as opened and door state initiated.",
        14 => {
            "Line length exceeded: Build info or startup line exceeded EEPROM line length limit. Line not stored."
        }
        15 => "Travel exceeded: Jog target exceeds machine travel. Jog command has been ignored.",
        16 => "Invalid jog command: Jog command has no '=' or contains prohibited g-code.",
        17 => "Setting disabled: Laser mode requires PWM output.",
        20 => "Unsupported command: Unsupported or invalid g-code command found in block.",
        21 => {
            "Modal group violation: More than one g-code command from same modal group found in block."
        }
        22 => "Undefined feed rate: Feed rate has not yet been set or is undefined.",
        23 => "Invalid gcode ID:23: G-code command in block requires an integer value.",
        24 => {
            "Invalid gcode ID:24: More than one g-code command that requires axis words found in block."
        }
        25 => "Invalid gcode ID:25: Repeated g-code word found in block.",
        26 => {
            "Invalid gcode ID:26: No axis words found in block for g-code command or current modal state which requires them."
        }
        27 => "Invalid gcode ID:27: Line number value is invalid.",
        28 => "Invalid gcode ID:28: G-code command is missing a required value word.",
        29 => "Invalid gcode ID:29: G59.x work coordinate systems are not supported.",
        30 => "Invalid gcode ID:30: G53 only allowed with G0 and G1 motion modes.",
        31 => {
            "Invalid gcode ID:31: Axis words found in block when no command or current modal state uses them."
        }
        32 => "Invalid gcode ID:32: G2 and G3 arcs require at least one in-plane axis word.",
        33 => "Invalid gcode ID:33: Motion command target is invalid.",
        34 => "Invalid gcode ID:34: Arc radius value is invalid.",
        35 => "Invalid gcode ID:35: G2 and G3 arcs require at least one in-plane offset word.",
        36 => "Invalid gcode ID:36: Unused value words found in block.",
        37 => {
            "Invalid gcode ID:37: G43.1 dynamic tool length offset is not assigned to configured tool length axis."
        }
        38 => "Invalid gcode ID:38: Tool number greater than max supported value.",
        _ => "unknown error code (not in the GRBL 1.1 table)",
    }
}

/// Meaning of `ALARM:N` (GRBL 1.1 `alarm_codes_en_US.csv`).
pub fn alarm_meaning(code: u16) -> &'static str {
    match code {
        1 => {
            "Hard limit triggered. Machine position is likely lost due to sudden and immediate halt. Re-homing is highly recommended."
        }
        2 => {
            "G-code motion target exceeds machine travel. Machine position safely retained. Alarm may be unlocked."
        }
        3 => {
            "Reset while in motion. Grbl cannot guarantee position. Lost steps are likely. Re-homing is highly recommended."
        }
        4 => {
            "Probe fail. The probe is not in the expected initial state before starting probe cycle."
        }
        5 => {
            "Probe fail. Probe did not contact the workpiece within the programmed travel for G38.2 and G38.4."
        }
        6 => "Homing fail. Reset during active homing cycle.",
        7 => "Homing fail. Safety door was opened during active homing cycle.",
        8 => {
            "Homing fail. Cycle failed to clear limit switch when pulling off. Try increasing pull-off setting or check wiring."
        }
        9 => "Homing fail. Could not find limit switch within search distance.",
        _ => "unknown alarm code (not in the GRBL 1.1 table)",
    }
}

/// Settings of a [`GrblTurntable`].
#[derive(Debug, Clone, PartialEq)]
pub struct GrblConfig {
    /// The axis the turntable is wired to.
    pub axis: Axis,
    /// Degrees of table rotation per GRBL unit on that axis (1.0 when `$10x` steps/unit is set in
    /// steps per degree).
    pub degrees_per_unit: f64,
    /// Home with `$H` (the machine has homing switches, `$22=1`); otherwise `$X` and a move to 0.
    pub homing: bool,
    /// Wait for one reply.
    pub exchange_timeout: Duration,
    /// Re-sends of the status query `?` after a missing or garbled report.
    pub status_retries: u32,
    /// Interval between status polls during a move.
    pub poll_interval: Duration,
    /// Overall limit for one move.
    pub move_timeout: Duration,
    /// Overall limit for homing.
    pub home_timeout: Duration,
    /// Limit for the first answer after connecting (board boot after the DTR reset).
    pub startup_wait: Duration,
}

impl GrblConfig {
    /// Hardware defaults (see the `DEFAULT_*` constants in [`super`]).
    pub fn new(axis: Axis, degrees_per_unit: f64) -> Self {
        GrblConfig {
            axis,
            degrees_per_unit,
            homing: false,
            exchange_timeout: super::DEFAULT_EXCHANGE_TIMEOUT,
            status_retries: super::DEFAULT_RETRIES,
            poll_interval: super::DEFAULT_POLL_INTERVAL,
            move_timeout: super::DEFAULT_MOVE_TIMEOUT,
            home_timeout: super::DEFAULT_HOME_TIMEOUT,
            startup_wait: DEFAULT_STARTUP_WAIT,
        }
    }

    fn validate(&self) -> Result<(), TurntableError> {
        if !self.degrees_per_unit.is_finite() || self.degrees_per_unit == 0.0 {
            return Err(TurntableError::InvalidConfig {
                field: "degrees_per_unit",
                reason: format!("must be finite and non-zero, got {}", self.degrees_per_unit),
            });
        }
        super::nonzero("exchange_timeout", self.exchange_timeout)?;
        super::nonzero("poll_interval", self.poll_interval)?;
        super::nonzero("move_timeout", self.move_timeout)?;
        super::nonzero("home_timeout", self.home_timeout)?;
        super::nonzero("startup_wait", self.startup_wait)
    }

    /// The position resolution in degrees: one unit of the last reported decimal.
    pub fn resolution(&self) -> Degrees {
        Degrees(10f64.powi(-REPORT_DECIMALS) * self.degrees_per_unit.abs())
    }
}

/// A GRBL 1.1 controller driving a turntable on one axis.
#[derive(Debug)]
pub struct GrblTurntable<L> {
    io: LineIo<L>,
    config: GrblConfig,
    /// Last work coordinate offset seen in a status report (only needed when GRBL reports `WPos`).
    wco: Vec<f64>,
    /// GRBL has answered since we connected.
    awake: bool,
}

impl<L: Link> GrblTurntable<L> {
    /// Wrap a link to a GRBL controller. No bytes are exchanged yet.
    pub fn new(link: L, config: GrblConfig) -> Result<Self, TurntableError> {
        config.validate()?;
        Ok(GrblTurntable {
            io: LineIo::new(link),
            config,
            wco: Vec::new(),
            awake: false,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &GrblConfig {
        &self.config
    }

    /// Before the first exchange: poll `?` until GRBL answers (it may be booting after the DTR reset
    /// that opening an Arduino's port causes), at most `startup_wait`.
    fn ensure_awake(&mut self) -> Result<(), TurntableError> {
        if self.awake {
            return Ok(());
        }
        let start = Instant::now();
        let deadline = start + self.config.startup_wait;
        let mut attempts = 0;
        let mut last = None;
        while Instant::now() < deadline {
            attempts += 1;
            self.io
                .send(&[STATUS_QUERY])
                .map_err(|e| serial::io_error("sending the status query ?", e))?;
            let attempt_deadline = deadline.min(Instant::now() + self.config.exchange_timeout);
            match self.read_status(attempt_deadline) {
                Ok(s) => {
                    tracing::debug!(state = ?s.state, waited = ?start.elapsed(), "grbl is up");
                    self.awake = true;
                    return Ok(());
                }
                // A stale ALARM line from before we connected: GRBL is up; the state says the rest.
                Err(StatusFailure::Fatal(TurntableError::GrblAlarm { code, meaning })) => {
                    tracing::warn!(code, meaning, "grbl reported an alarm on connect");
                }
                // The boot banner after the DTR reset: expected here; the next `?` will be answered.
                Err(StatusFailure::Fatal(TurntableError::GrblRestarted)) => {
                    tracing::debug!("grbl booted");
                }
                Err(StatusFailure::Fatal(e)) => return Err(e),
                Err(StatusFailure::Retry(e)) => last = Some(e),
            }
        }
        Err(TurntableError::Timeout {
            command: "status query ? (is GRBL running at this baud rate?)".into(),
            timeout: self.config.startup_wait,
            attempts,
            received: match last {
                Some(TurntableError::Timeout { received, .. }) => received,
                Some(TurntableError::UnexpectedReply { reply, .. }) => reply,
                _ => String::new(),
            },
        })
    }

    /// Consume lines that arrived since the last exchange (a late `ok`, a status report answering a
    /// `?` that had already timed out) so they are not taken for the next reply. An `ALARM:N` or a
    /// start-up banner among them is still an error.
    fn flush_stale(&mut self) -> Result<(), TurntableError> {
        while let Some(line) = self
            .io
            .try_line()
            .map_err(|e| serial::io_error("reading stale input", e))?
        {
            match decode_line(&line) {
                Ok(Reply::Alarm(code)) => return Err(alarm(code)),
                Ok(Reply::Welcome { .. }) => return Err(TurntableError::GrblRestarted),
                Ok(Reply::Status(s)) => self.note_wco(&s),
                _ => tracing::debug!(line = %escape_bytes(&line), "grbl: dropping a stale line"),
            }
        }
        Ok(())
    }

    /// Send a line command and wait for its `ok` (feedback lines are collected and returned).
    fn command(&mut self, cmd: &[u8], deadline: Instant) -> Result<Vec<String>, TurntableError> {
        self.flush_stale()?;
        let shown = escape_bytes(cmd.strip_suffix(b"\n").unwrap_or(cmd));
        tracing::debug!(command = %shown, "grbl send");
        // The wait this reply gets, rounded up to whole milliseconds for the error message.
        let waited = deadline.saturating_duration_since(Instant::now());
        let waited = Duration::from_millis(waited.as_micros().div_ceil(1000) as u64);
        self.io
            .send(cmd)
            .map_err(|e| serial::io_error(format!("sending {shown}"), e))?;
        let mut feedback = Vec::new();
        loop {
            let line = self
                .io
                .read_line(deadline)
                .map_err(|e| serial::line_error(&shown, e, waited, 1))?;
            tracing::trace!(line = %escape_bytes(&line), "grbl recv");
            match decode_line(&line) {
                Ok(Reply::Ok) => return Ok(feedback),
                Ok(Reply::Error(code)) => {
                    return Err(TurntableError::GrblError {
                        command: shown,
                        code,
                        meaning: error_meaning(code),
                    });
                }
                Ok(Reply::Alarm(code)) => return Err(alarm(code)),
                Ok(Reply::Feedback(f)) => feedback.push(f),
                Ok(Reply::Status(s)) => self.note_wco(&s),
                Ok(Reply::Welcome { .. }) => return Err(TurntableError::GrblRestarted),
                Ok(Reply::Setting(_)) => {}
                Err(e) => {
                    return Err(TurntableError::UnexpectedReply {
                        command: shown,
                        expected: "ok, error:N or ALARM:N",
                        reply: e.line,
                    });
                }
            }
        }
    }

    fn note_wco(&mut self, s: &Status) {
        if let Some(w) = &s.wco {
            self.wco.clone_from(w);
        }
    }

    /// One status query, re-sent up to `status_retries` times, never past `deadline`.
    pub fn status(&mut self) -> Result<Status, TurntableError> {
        self.ensure_awake()?;
        let deadline = Instant::now() + self.exchange_bound();
        self.status_before(deadline)
    }

    /// The longest a single retried exchange can take: `exchange_timeout × (status_retries + 1)`.
    pub fn exchange_bound(&self) -> Duration {
        self.config.exchange_timeout * (self.config.status_retries + 1)
    }

    fn status_before(&mut self, deadline: Instant) -> Result<Status, TurntableError> {
        self.flush_stale()?;
        let mut last_failure = None;
        let mut attempts = 0;
        while attempts <= self.config.status_retries && Instant::now() < deadline {
            attempts += 1;
            if attempts > 1 {
                // Drop the tail of a garbled report before asking again.
                self.flush_stale()?;
                self.io.drop_partial();
            }
            self.io
                .send(&[STATUS_QUERY])
                .map_err(|e| serial::io_error("sending the status query ?", e))?;
            let attempt_deadline = deadline.min(Instant::now() + self.config.exchange_timeout);
            match self.read_status(attempt_deadline) {
                Ok(s) => return Ok(s),
                Err(StatusFailure::Fatal(e)) => return Err(e),
                Err(StatusFailure::Retry(e)) => {
                    tracing::debug!(attempt = attempts, error = %e, "grbl status query failed");
                    last_failure = Some(e);
                }
            }
        }
        Err(match last_failure {
            Some(TurntableError::Timeout { received, .. }) => TurntableError::Timeout {
                command: "status query ?".into(),
                timeout: self.config.exchange_timeout,
                attempts,
                received,
            },
            Some(e) => e,
            None => TurntableError::Timeout {
                command: "status query ?".into(),
                timeout: self.config.exchange_timeout,
                attempts,
                received: String::new(),
            },
        })
    }

    fn read_status(&mut self, deadline: Instant) -> Result<Status, StatusFailure> {
        loop {
            let line = match self.io.read_line(deadline) {
                Ok(line) => line,
                Err(e @ LineError::TimedOut { .. }) => {
                    return Err(StatusFailure::Retry(serial::line_error(
                        "status query ?",
                        e,
                        self.config.exchange_timeout,
                        1,
                    )));
                }
                Err(e) => {
                    return Err(StatusFailure::Fatal(serial::line_error(
                        "status query ?",
                        e,
                        self.config.exchange_timeout,
                        1,
                    )));
                }
            };
            tracing::trace!(line = %escape_bytes(&line), "grbl recv");
            match decode_line(&line) {
                Ok(Reply::Status(s)) => {
                    self.note_wco(&s);
                    return self.newest(s);
                }
                Ok(Reply::Alarm(code)) => return Err(StatusFailure::Fatal(alarm(code))),
                Ok(Reply::Welcome { .. }) => {
                    return Err(StatusFailure::Fatal(TurntableError::GrblRestarted));
                }
                // A late ok/error or a message: not ours, keep reading.
                Ok(_) => {}
                Err(e) => {
                    return Err(StatusFailure::Retry(TurntableError::UnexpectedReply {
                        command: "status query ?".into(),
                        expected: "a <State|MPos:...> status report",
                        reply: e.line,
                    }));
                }
            }
        }
    }

    /// `?` carries no id, so a report that answered an earlier, timed-out query can arrive first:
    /// if newer reports are already waiting, the newest one wins.
    fn newest(&mut self, mut s: Status) -> Result<Status, StatusFailure> {
        loop {
            let line = match self.io.try_line() {
                Ok(Some(line)) => line,
                Ok(None) => return Ok(s),
                Err(e) => {
                    return Err(StatusFailure::Fatal(serial::io_error(
                        "reading status reports",
                        e,
                    )));
                }
            };
            match decode_line(&line) {
                Ok(Reply::Status(newer)) => {
                    self.note_wco(&newer);
                    s = newer;
                }
                Ok(Reply::Alarm(code)) => return Err(StatusFailure::Fatal(alarm(code))),
                Ok(Reply::Welcome { .. }) => {
                    return Err(StatusFailure::Fatal(TurntableError::GrblRestarted));
                }
                _ => {}
            }
        }
    }

    fn degrees_of(&self, s: &Status) -> Result<Degrees, TurntableError> {
        s.machine_position(self.config.axis, &self.wco)
            .map(|u| Degrees(u * self.config.degrees_per_unit))
            .ok_or_else(|| TurntableError::UnexpectedReply {
                command: "status query ?".into(),
                expected: "a position for the configured axis",
                reply: format!("{s:?}"),
            })
    }

    /// Poll until Idle at `target` (within the resolution), or fail by `deadline`.
    fn wait_settled(
        &mut self,
        target: Degrees,
        deadline: Instant,
        limit: Duration,
    ) -> Result<Degrees, TurntableError> {
        let tolerance = Degrees(self.config.resolution().0 * 1.000_001);
        let mut idle_elsewhere = 0;
        let mut last_state = None;
        loop {
            let s = match self.status_before(deadline) {
                Ok(s) => s,
                Err(e) => return Err(super::out_of_time(e, deadline, target, limit, last_state)),
            };
            let pos = self.degrees_of(&s)?;
            last_state = Some(format!("{:?} at {pos}", s.state));
            match s.state {
                State::Alarm => return Err(TurntableError::GrblLocked),
                State::Idle if pos.within(target, tolerance) => return Ok(pos),
                State::Idle => {
                    idle_elsewhere += 1;
                    if idle_elsewhere >= SETTLE_CONFIRMATIONS {
                        return Err(TurntableError::PositionMismatch {
                            commanded: target,
                            reported: pos,
                            tolerance,
                        });
                    }
                }
                _ => idle_elsewhere = 0,
            }
            let now = Instant::now();
            if now + self.config.poll_interval >= deadline {
                break;
            }
            std::thread::sleep(self.config.poll_interval);
        }
        Err(TurntableError::MoveTimeout {
            target,
            limit,
            last_state: last_state.unwrap_or_default(),
        })
    }

    fn move_before(&mut self, target: Degrees, limit: Duration) -> Result<Degrees, TurntableError> {
        let target = Degrees::checked(target.0)?;
        self.ensure_awake()?;
        let start = Instant::now();
        let deadline = start + limit;
        let units = target.0 / self.config.degrees_per_unit;
        let cmd = encode_move(self.config.axis, units);
        let reply_deadline = deadline.min(start + self.config.exchange_timeout);
        self.command(cmd.as_bytes(), reply_deadline)?;
        let pos = self.wait_settled(target, deadline, limit)?;
        tracing::info!(%target, %pos, elapsed = ?start.elapsed(), "grbl move settled");
        Ok(pos)
    }

    /// Soft reset (0x18) and wait for the `Grbl …` banner. Leaves GRBL in `ALARM:3` if it was moving.
    pub fn soft_reset(&mut self) -> Result<(), TurntableError> {
        self.ensure_awake()?;
        self.io
            .send(&[SOFT_RESET])
            .map_err(|e| serial::io_error("sending soft reset", e))?;
        let deadline = Instant::now() + self.config.exchange_timeout;
        loop {
            let line = self.io.read_line(deadline).map_err(|e| {
                serial::line_error("soft reset (0x18)", e, self.config.exchange_timeout, 1)
            })?;
            match decode_line(&line) {
                Ok(Reply::Welcome { version }) => {
                    tracing::info!(%version, "grbl reset");
                    return Ok(());
                }
                Ok(Reply::Alarm(code)) => {
                    tracing::warn!(code, meaning = alarm_meaning(code), "grbl alarm on reset");
                }
                _ => {}
            }
        }
    }
}

enum StatusFailure {
    /// Worth asking again (timeout, garbled report).
    Retry(TurntableError),
    /// Not worth asking again (alarm, port gone).
    Fatal(TurntableError),
}

fn alarm(code: u16) -> TurntableError {
    TurntableError::GrblAlarm {
        code,
        meaning: alarm_meaning(code),
    }
}

impl<L: Link> Turntable for GrblTurntable<L> {
    fn describe(&mut self) -> Result<String, TurntableError> {
        self.ensure_awake()?;
        let deadline = Instant::now() + self.config.exchange_timeout;
        let feedback = self.command(encode_build_info(), deadline)?;
        let version = feedback
            .iter()
            .find_map(|f| f.strip_prefix("VER:"))
            .unwrap_or("unknown version");
        Ok(format!(
            "GRBL {version} (axis {}, {} °/unit)",
            self.config.axis.letter(),
            self.config.degrees_per_unit
        ))
    }

    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.ensure_awake()?;
        let limit = self.config.home_timeout;
        if self.config.homing {
            let start = Instant::now();
            let deadline = start + limit;
            self.command(encode_home(), deadline)?;
            let s = self.status_before(deadline)?;
            if s.state == State::Alarm {
                return Err(TurntableError::GrblLocked);
            }
            self.degrees_of(&s)
        } else {
            let deadline = Instant::now() + self.config.exchange_timeout;
            self.command(encode_unlock(), deadline)?;
            self.move_before(Degrees(0.0), limit)
        }
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        self.move_before(target, self.config.move_timeout)
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        let s = self.status()?;
        self.degrees_of(&s)
    }

    fn stop(&mut self) -> Result<(), TurntableError> {
        self.ensure_awake()?;
        self.io
            .send(&[FEED_HOLD])
            .map_err(|e| serial::io_error("sending feed hold !", e))?;
        // Wait for the hold to complete (Hold:0) or the machine to be idle, then reset.
        let deadline = Instant::now() + self.exchange_bound();
        loop {
            let s = self.status_before(deadline)?;
            let held = matches!(
                (s.state, s.substate),
                (State::Hold, Some(0)) | (State::Idle, _) | (State::Alarm, _)
            );
            if held || Instant::now() + self.config.poll_interval >= deadline {
                break;
            }
            std::thread::sleep(self.config.poll_interval);
        }
        self.soft_reset()
    }

    fn resolution(&self) -> Degrees {
        self.config.resolution()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    #[test]
    fn encodes() {
        assert_eq!(encode_move(Axis::X, 12.3456), "G90 G53 G0 X12.346\n");
        assert_eq!(encode_move(Axis::A, -0.0004), "G90 G53 G0 A-0.000\n");
        assert_eq!(encode_unlock(), b"$X\n");
        assert_eq!(encode_home(), b"$H\n");
    }

    #[test]
    fn decodes_table() {
        let cases: &[(&[u8], Reply)] = &[
            (b"ok", Reply::Ok),
            (b"error:9", Reply::Error(9)),
            (b"ALARM:1", Reply::Alarm(1)),
            (
                b"Grbl 1.1h ['$' for help]",
                Reply::Welcome {
                    version: "1.1h".into(),
                },
            ),
            (
                b"[MSG:Caution: Unlocked]",
                Reply::Feedback("MSG:Caution: Unlocked".into()),
            ),
            (b"$100=250.000", Reply::Setting("$100=250.000".into())),
            (
                b"<Idle|MPos:1.000,2.500,-3.000|FS:0,0>",
                Reply::Status(Status {
                    state: State::Idle,
                    substate: None,
                    mpos: Some(vec![1.0, 2.5, -3.0]),
                    wpos: None,
                    wco: None,
                }),
            ),
            (
                b"<Hold:1|WPos:0.000,0.000,0.000,90.000|Bf:15,128|WCO:0.000,0.000,0.000,0.000>",
                Reply::Status(Status {
                    state: State::Hold,
                    substate: Some(1),
                    mpos: None,
                    wpos: Some(vec![0.0, 0.0, 0.0, 90.0]),
                    wco: Some(vec![0.0; 4]),
                }),
            ),
        ];
        for (line, want) in cases {
            assert_eq!(
                decode_line(line).as_ref(),
                Ok(want),
                "{}",
                escape_bytes(line)
            );
        }
    }

    #[test]
    fn rejects_table() {
        let cases: &[&[u8]] = &[
            b"",
            b"okay",
            b"error:x",
            b"ALARM:",
            b"<Idle|MPos:1,2,3",
            b"<Bogus|MPos:1,2,3>",
            b"<Idle|MPos:1,nan,3>",
            b"<Idle|FS:0,0>",
            b"[MSG:unterminated",
            b"\xff\xfe",
        ];
        for line in cases {
            assert!(decode_line(line).is_err(), "{}", escape_bytes(line));
        }
    }

    #[test]
    fn machine_position_adds_offset_to_work_position() {
        let s = Status {
            state: State::Idle,
            substate: None,
            mpos: None,
            wpos: Some(vec![8.0, 0.0, 0.0]),
            wco: None,
        };
        assert_eq!(s.machine_position(Axis::X, &[2.0, 0.0, 0.0]), Some(10.0));
        assert_eq!(s.machine_position(Axis::A, &[]), None);
        let m = Status {
            mpos: Some(vec![10.0, 0.0, 0.0]),
            wpos: None,
            ..s
        };
        assert_eq!(m.machine_position(Axis::X, &[2.0, 0.0, 0.0]), Some(10.0));
    }

    #[test]
    fn meanings_cover_the_tables() {
        for code in (1..=17).chain(20..=38) {
            assert!(!error_meaning(code).starts_with("unknown"), "error {code}");
        }
        for code in 1..=9 {
            assert!(!alarm_meaning(code).starts_with("unknown"), "alarm {code}");
        }
        assert!(error_meaning(99).starts_with("unknown"));
    }
}
