//! Zaber ASCII protocol: pure encode/decode, typed warning flags and rejection reasons, and
//! [`ZaberTurntable`], a driver generic over a [`Link`].
//!
//! Command: `/<device> <axis> [command]\n`. Reply: `@<device> <axis> <OK|RJ> <IDLE|BUSY> <flag|--> <data>`
//! (device zero-padded to two digits, an optional message id after the axis, an optional `:XX`
//! checksum at the end). Info lines start with `#`, alerts with `!`.

use std::fmt;
use std::time::{Duration, Instant};

use super::serial::{self, LineIo, Link};
use super::{Degrees, Turntable, TurntableError, escape_bytes};

/// Encode a command for `device` / `axis` (axis 0 addresses the whole device).
pub fn encode(device: u8, axis: u8, command: &str) -> String {
    if command.is_empty() {
        format!("/{device} {axis}\n")
    } else {
        format!("/{device} {axis} {command}\n")
    }
}

/// Encode a command carrying a message id (0–99), which the device echoes in its reply.
pub fn encode_with_id(device: u8, axis: u8, id: u8, command: &str) -> String {
    if command.is_empty() {
        format!("/{device} {axis} {id}\n")
    } else {
        format!("/{device} {axis} {id} {command}\n")
    }
}

/// Message ids run 0..=99 and wrap.
pub const MAX_MESSAGE_ID: u8 = 99;

/// `home`: find the home sensor; position becomes 0.
pub fn encode_home(device: u8, axis: u8) -> String {
    encode(device, axis, "home")
}

/// `move abs N`: absolute move to `microsteps`.
pub fn encode_move_abs(device: u8, axis: u8, microsteps: i64) -> String {
    encode(device, axis, &format!("move abs {microsteps}"))
}

/// `get pos`: the position in microsteps (and, in the reply header, BUSY/IDLE).
pub fn encode_get_pos(device: u8, axis: u8) -> String {
    encode(device, axis, "get pos")
}

/// `stop`: decelerate to a stop.
pub fn encode_stop(device: u8, axis: u8) -> String {
    encode(device, axis, "stop")
}

/// Empty command: status only.
pub fn encode_status(device: u8, axis: u8) -> String {
    encode(device, axis, "")
}

/// Whether the device accepted the command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplyFlag {
    Ok,
    Rejected,
}

/// Whether the axis is moving.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum DeviceStatus {
    Idle,
    Busy,
}

/// A warning flag from the reply header. `F…` are faults, `W…` warnings, `N…` notices (Zaber ASCII
/// protocol manual, "Warning Flags"). Only the highest-priority flag is shown in a reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flag {
    /// FD: driver disabled (over-temperature, over-voltage or hardware fault).
    DriverDisabled,
    /// FQ: encoder error.
    EncoderError,
    /// FS: stalled and stopped (the motor could not follow: obstruction, excessive load).
    StalledAndStopped,
    /// FT: excessive twist.
    ExcessiveTwist,
    /// FB: stream bounds error.
    StreamBoundsError,
    /// FP: interpolated path deviation.
    PathDeviation,
    /// FE: limit error.
    LimitError,
    /// FZ: peripheral inactive.
    PeripheralInactive,
    /// WH: device not homed.
    NotHomed,
    /// WL: unexpected limit trigger.
    UnexpectedLimit,
    /// WR: no reference position (home first).
    NoReference,
    /// WV: voltage out of range.
    VoltageOutOfRange,
    /// WT: controller temperature high.
    TemperatureHigh,
    /// WM: displaced when stationary.
    Displaced,
    /// NC: manual control.
    ManualControl,
    /// NI: command interrupted.
    CommandInterrupted,
    /// NU: setting update pending.
    UpdatePending,
    /// Any other two-letter flag.
    Other([u8; 2]),
}

impl Flag {
    /// Parse a two-letter flag; `--` is "no flag" (`None`).
    pub fn parse(s: &str) -> Option<Option<Flag>> {
        let b = s.as_bytes();
        if s == "--" {
            return Some(None);
        }
        if b.len() != 2 || !b.iter().all(u8::is_ascii_uppercase) {
            return None;
        }
        Some(Some(match s {
            "FD" => Flag::DriverDisabled,
            "FQ" => Flag::EncoderError,
            "FS" => Flag::StalledAndStopped,
            "FT" => Flag::ExcessiveTwist,
            "FB" => Flag::StreamBoundsError,
            "FP" => Flag::PathDeviation,
            "FE" => Flag::LimitError,
            "FZ" => Flag::PeripheralInactive,
            "WH" => Flag::NotHomed,
            "WL" => Flag::UnexpectedLimit,
            "WR" => Flag::NoReference,
            "WV" => Flag::VoltageOutOfRange,
            "WT" => Flag::TemperatureHigh,
            "WM" => Flag::Displaced,
            "NC" => Flag::ManualControl,
            "NI" => Flag::CommandInterrupted,
            "NU" => Flag::UpdatePending,
            _ => Flag::Other([b[0], b[1]]),
        }))
    }

    /// The two-letter code.
    pub fn code(self) -> String {
        let s: &str = match self {
            Flag::DriverDisabled => "FD",
            Flag::EncoderError => "FQ",
            Flag::StalledAndStopped => "FS",
            Flag::ExcessiveTwist => "FT",
            Flag::StreamBoundsError => "FB",
            Flag::PathDeviation => "FP",
            Flag::LimitError => "FE",
            Flag::PeripheralInactive => "FZ",
            Flag::NotHomed => "WH",
            Flag::UnexpectedLimit => "WL",
            Flag::NoReference => "WR",
            Flag::VoltageOutOfRange => "WV",
            Flag::TemperatureHigh => "WT",
            Flag::Displaced => "WM",
            Flag::ManualControl => "NC",
            Flag::CommandInterrupted => "NI",
            Flag::UpdatePending => "NU",
            Flag::Other(b) => return String::from_utf8_lossy(&b).into_owned(),
        };
        s.to_string()
    }

    /// What the flag means.
    pub fn meaning(self) -> &'static str {
        match self {
            Flag::DriverDisabled => "driver disabled",
            Flag::EncoderError => "encoder error",
            Flag::StalledAndStopped => "stalled and stopped",
            Flag::ExcessiveTwist => "excessive twist",
            Flag::StreamBoundsError => "stream bounds error",
            Flag::PathDeviation => "interpolated path deviation",
            Flag::LimitError => "limit error",
            Flag::PeripheralInactive => "peripheral inactive",
            Flag::NotHomed => "device not homed",
            Flag::UnexpectedLimit => "unexpected limit trigger",
            Flag::NoReference => "no reference position",
            Flag::VoltageOutOfRange => "voltage out of range",
            Flag::TemperatureHigh => "controller temperature high",
            Flag::Displaced => "displaced when stationary",
            Flag::ManualControl => "manual control",
            Flag::CommandInterrupted => "command interrupted",
            Flag::UpdatePending => "setting update pending",
            Flag::Other(_) => "unknown flag",
        }
    }

    /// Faults (`F…`) stop motion; the operation cannot succeed.
    pub fn is_fault(self) -> bool {
        self.code().starts_with('F')
    }
}

impl fmt::Display for Flag {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.code(), self.meaning())
    }
}

/// Why a command was rejected (`RJ` reply data).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Rejection {
    /// AGAIN: the device is busy; try again.
    Again,
    /// BADAXIS: no such axis.
    BadAxis,
    /// BADCOMMAND: unknown command.
    BadCommand,
    /// BADDATA: the value is out of range or malformed.
    BadData,
    /// BADMESSAGEID: message id out of range.
    BadMessageId,
    /// DEVICEONLY: the command needs axis 0.
    DeviceOnly,
    /// FULL: buffer full.
    Full,
    /// LOCKSTEP: the axis is in lockstep.
    Lockstep,
    /// NOACCESS: access level too low.
    NoAccess,
    /// PARKED: the axis is parked.
    Parked,
    /// STATUSBUSY: the command needs the axis idle.
    StatusBusy,
    /// Anything else, as sent.
    Other(String),
}

impl Rejection {
    /// Parse the reason word of an `RJ` reply.
    pub fn parse(data: &str) -> Rejection {
        match data.trim() {
            "AGAIN" => Rejection::Again,
            "BADAXIS" => Rejection::BadAxis,
            "BADCOMMAND" => Rejection::BadCommand,
            "BADDATA" => Rejection::BadData,
            "BADMESSAGEID" => Rejection::BadMessageId,
            "DEVICEONLY" => Rejection::DeviceOnly,
            "FULL" => Rejection::Full,
            "LOCKSTEP" => Rejection::Lockstep,
            "NOACCESS" => Rejection::NoAccess,
            "PARKED" => Rejection::Parked,
            "STATUSBUSY" => Rejection::StatusBusy,
            other => Rejection::Other(other.to_string()),
        }
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self {
            Rejection::Again => "AGAIN (device busy, try again)",
            Rejection::BadAxis => "BADAXIS (no such axis)",
            Rejection::BadCommand => "BADCOMMAND (unknown command)",
            Rejection::BadData => "BADDATA (value out of range or malformed)",
            Rejection::BadMessageId => "BADMESSAGEID",
            Rejection::DeviceOnly => "DEVICEONLY (command needs axis 0)",
            Rejection::Full => "FULL (buffer full)",
            Rejection::Lockstep => "LOCKSTEP (axis is in lockstep)",
            Rejection::NoAccess => "NOACCESS (access level too low)",
            Rejection::Parked => "PARKED (axis is parked)",
            Rejection::StatusBusy => "STATUSBUSY (axis must be idle)",
            Rejection::Other(s) => return write!(f, "{s}"),
        };
        f.write_str(s)
    }
}

/// A decoded reply (`@…`).
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    pub device: u8,
    pub axis: u8,
    pub message_id: Option<u8>,
    pub flag: ReplyFlag,
    pub status: DeviceStatus,
    pub warning: Option<Flag>,
    /// Everything after the warning flag (may be empty or contain spaces).
    pub data: String,
}

/// One decoded line from a Zaber device.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    /// `@…` reply to a command.
    Reply(Reply),
    /// `#…` info line (e.g. help text), contents after the `#`.
    Info(String),
    /// `!…` alert (sent unprompted, e.g. when a move finishes with `comm.alert` on).
    Alert {
        device: u8,
        axis: u8,
        status: DeviceStatus,
        warning: Option<Flag>,
    },
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

fn strip_checksum(s: &str) -> &str {
    let b = s.as_bytes();
    if b.len() >= 3 && b[b.len() - 3] == b':' && b[b.len() - 2..].iter().all(u8::is_ascii_hexdigit)
    {
        &s[..s.len() - 3]
    } else {
        s
    }
}

fn parse_status(s: &str) -> Option<DeviceStatus> {
    match s {
        "IDLE" => Some(DeviceStatus::Idle),
        "BUSY" => Some(DeviceStatus::Busy),
        _ => None,
    }
}

/// Decode one line (without its line ending).
pub fn decode_line(line: &[u8]) -> Result<Message, DecodeError> {
    let text = std::str::from_utf8(line).map_err(|_| bad("not ASCII", line))?;
    let text = strip_checksum(text.trim());
    let Some(kind) = text.chars().next() else {
        return Err(bad("empty line", line));
    };
    let body = &text[kind.len_utf8()..];
    match kind {
        '#' => return Ok(Message::Info(body.trim().to_string())),
        '@' | '!' => {}
        _ => return Err(bad("not a Zaber reply, alert or info line", line)),
    }
    let mut words = body.split(' ').filter(|w| !w.is_empty());
    let device: u8 = words
        .next()
        .and_then(|w| w.parse().ok())
        .ok_or_else(|| bad("bad device address", line))?;
    let axis: u8 = words
        .next()
        .and_then(|w| w.parse().ok())
        .ok_or_else(|| bad("bad axis number", line))?;
    if kind == '!' {
        let status = words
            .next()
            .and_then(parse_status)
            .ok_or_else(|| bad("bad status in alert", line))?;
        let warning = words
            .next()
            .and_then(Flag::parse)
            .ok_or_else(|| bad("bad warning flag in alert", line))?;
        return Ok(Message::Alert {
            device,
            axis,
            status,
            warning,
        });
    }
    let mut next = words.next().ok_or_else(|| bad("reply too short", line))?;
    let mut message_id = None;
    if let Ok(id) = next.parse::<u8>() {
        message_id = Some(id);
        next = words.next().ok_or_else(|| bad("reply too short", line))?;
    }
    let flag = match next {
        "OK" => ReplyFlag::Ok,
        "RJ" => ReplyFlag::Rejected,
        _ => return Err(bad("reply flag is neither OK nor RJ", line)),
    };
    let status = words
        .next()
        .and_then(parse_status)
        .ok_or_else(|| bad("status is neither IDLE nor BUSY", line))?;
    let warning = words
        .next()
        .and_then(Flag::parse)
        .ok_or_else(|| bad("bad warning flag", line))?;
    let data = words.collect::<Vec<_>>().join(" ");
    if data.is_empty() {
        return Err(bad("reply without data", line));
    }
    Ok(Message::Reply(Reply {
        device,
        axis,
        message_id,
        flag,
        status,
        warning,
        data,
    }))
}

/// Settings of a [`ZaberTurntable`].
#[derive(Debug, Clone, PartialEq)]
pub struct ZaberConfig {
    /// Device address on the daisy chain (1 = nearest the computer).
    pub device: u8,
    /// Axis number on the device (1 for a stand-alone stage).
    pub axis: u8,
    /// Microsteps per degree of rotation (the stage's datasheet: 1 / microstep size in degrees).
    pub microsteps_per_degree: f64,
    /// Wait for one reply.
    pub exchange_timeout: Duration,
    /// Re-sends after a missing or garbled reply.
    pub retries: u32,
    /// Interval between position polls during a move.
    pub poll_interval: Duration,
    /// Overall limit for one move.
    pub move_timeout: Duration,
    /// Overall limit for homing.
    pub home_timeout: Duration,
}

/// Microsteps per degree of an X-RSW60A rotary stage (microstep 0.000234375°): the CLI default.
pub const X_RSW60A_MICROSTEPS_PER_DEGREE: f64 = 1.0 / 0.000_234_375;

impl ZaberConfig {
    /// Hardware defaults for device 1, axis 1.
    pub fn new(microsteps_per_degree: f64) -> Self {
        ZaberConfig {
            device: 1,
            axis: 1,
            microsteps_per_degree,
            exchange_timeout: super::DEFAULT_EXCHANGE_TIMEOUT,
            retries: super::DEFAULT_RETRIES,
            poll_interval: super::DEFAULT_POLL_INTERVAL,
            move_timeout: super::DEFAULT_MOVE_TIMEOUT,
            home_timeout: super::DEFAULT_HOME_TIMEOUT,
        }
    }

    fn validate(&self) -> Result<(), TurntableError> {
        if !self.microsteps_per_degree.is_finite() || self.microsteps_per_degree <= 0.0 {
            return Err(TurntableError::InvalidConfig {
                field: "microsteps_per_degree",
                reason: format!(
                    "must be finite and positive, got {}",
                    self.microsteps_per_degree
                ),
            });
        }
        if self.device == 0 || self.device > 99 {
            return Err(TurntableError::InvalidConfig {
                field: "device",
                reason: format!("must be 1..=99, got {}", self.device),
            });
        }
        super::nonzero("exchange_timeout", self.exchange_timeout)?;
        super::nonzero("poll_interval", self.poll_interval)?;
        super::nonzero("move_timeout", self.move_timeout)?;
        super::nonzero("home_timeout", self.home_timeout)
    }

    /// One microstep in degrees.
    pub fn resolution(&self) -> Degrees {
        Degrees(1.0 / self.microsteps_per_degree)
    }

    /// Degrees → nearest microstep.
    pub fn to_microsteps(&self, angle: Degrees) -> i64 {
        (angle.0 * self.microsteps_per_degree).round() as i64
    }

    /// Microsteps → degrees.
    pub fn to_degrees(&self, microsteps: i64) -> Degrees {
        Degrees(microsteps as f64 / self.microsteps_per_degree)
    }
}

/// A Zaber stage speaking the ASCII protocol.
#[derive(Debug)]
pub struct ZaberTurntable<L> {
    io: LineIo<L>,
    config: ZaberConfig,
    last_warning: Option<Flag>,
    next_id: u8,
}

impl<L: Link> ZaberTurntable<L> {
    /// Wrap a link to a Zaber device. No bytes are exchanged yet.
    pub fn new(link: L, config: ZaberConfig) -> Result<Self, TurntableError> {
        config.validate()?;
        Ok(ZaberTurntable {
            io: LineIo::new(link),
            config,
            last_warning: None,
            next_id: 0,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &ZaberConfig {
        &self.config
    }

    /// The last non-fault warning flag seen (faults are errors).
    pub fn last_warning(&self) -> Option<Flag> {
        self.last_warning
    }

    /// The longest a single exchange can take: `exchange_timeout × (retries + 1)`.
    pub fn exchange_bound(&self) -> Duration {
        self.config.exchange_timeout * (self.config.retries + 1)
    }

    /// Send `command` to `axis` and return the matching reply, re-sending on timeout or garbage.
    /// `RJ` becomes [`TurntableError::ZaberRejected`]; a fault flag becomes
    /// [`TurntableError::ZaberFault`] unless `motion` (a movement command clears faults, so the flag
    /// in its own reply is stale).
    fn exchange(
        &mut self,
        axis: u8,
        command: &str,
        motion: bool,
        deadline: Instant,
    ) -> Result<Reply, TurntableError> {
        let shown = encode(self.config.device, axis, command)
            .trim_end()
            .to_string();
        let mut attempts = 0;
        let mut last_failure = None;
        while attempts <= self.config.retries && Instant::now() < deadline {
            attempts += 1;
            // Every attempt gets its own id, so a late reply to an earlier attempt (or command) is
            // recognised and skipped instead of being taken for this one.
            let id = self.next_id;
            self.next_id = if id >= MAX_MESSAGE_ID { 0 } else { id + 1 };
            let text = encode_with_id(self.config.device, axis, id, command);
            tracing::debug!(command = %text.trim_end(), attempt = attempts, "zaber send");
            self.io
                .send(text.as_bytes())
                .map_err(|e| serial::io_error(format!("sending {shown}"), e))?;
            let attempt_deadline = deadline.min(Instant::now() + self.config.exchange_timeout);
            match self.read_reply(&shown, axis, id, attempt_deadline) {
                Ok(reply) => return self.check(reply, &shown, motion),
                Err(Failure::Fatal(e)) => return Err(e),
                Err(Failure::Retry(e)) => {
                    tracing::debug!(attempt = attempts, error = %e, "zaber exchange failed");
                    last_failure = Some(e);
                }
            }
        }
        Err(match last_failure {
            Some(TurntableError::Timeout { received, .. }) => TurntableError::Timeout {
                command: shown,
                timeout: self.config.exchange_timeout,
                attempts,
                received,
            },
            Some(e) => e,
            None => TurntableError::Timeout {
                command: shown,
                timeout: self.config.exchange_timeout,
                attempts,
                received: String::new(),
            },
        })
    }

    fn read_reply(
        &mut self,
        shown: &str,
        axis: u8,
        id: u8,
        deadline: Instant,
    ) -> Result<Reply, Failure> {
        loop {
            let line = self.io.read_line(deadline).map_err(|e| {
                let timed_out = matches!(e, serial::LineError::TimedOut { .. });
                let err = serial::line_error(shown, e, self.config.exchange_timeout, 1);
                if timed_out {
                    Failure::Retry(err)
                } else {
                    Failure::Fatal(err)
                }
            })?;
            tracing::trace!(line = %escape_bytes(&line), "zaber recv");
            match decode_line(&line) {
                Ok(Message::Reply(r))
                    if r.device == self.config.device
                        && r.axis == axis
                        && r.message_id == Some(id) =>
                {
                    return Ok(r);
                }
                // Stale replies (other ids), other devices' replies, alerts and info lines.
                Ok(_) => {}
                Err(e) => {
                    return Err(Failure::Retry(TurntableError::UnexpectedReply {
                        command: shown.to_string(),
                        expected: "@<device> <axis> OK|RJ IDLE|BUSY <flag> <data>",
                        reply: e.line,
                    }));
                }
            }
        }
    }

    fn check(&mut self, reply: Reply, shown: &str, motion: bool) -> Result<Reply, TurntableError> {
        if reply.flag == ReplyFlag::Rejected {
            return Err(TurntableError::ZaberRejected {
                command: shown.to_string(),
                reason: Rejection::parse(&reply.data),
            });
        }
        if let Some(flag) = reply.warning {
            if flag.is_fault() && !motion {
                return Err(TurntableError::ZaberFault {
                    command: shown.to_string(),
                    flag,
                });
            }
            if !flag.is_fault() && self.last_warning != Some(flag) {
                tracing::warn!(flag = %flag, "zaber warning");
            }
            if !flag.is_fault() {
                self.last_warning = Some(flag);
            }
        } else {
            self.last_warning = None;
        }
        Ok(reply)
    }

    fn microsteps(&self, reply: &Reply, shown: &str) -> Result<i64, TurntableError> {
        reply
            .data
            .split(' ')
            .next()
            .and_then(|w| w.parse::<i64>().ok())
            .ok_or_else(|| TurntableError::UnexpectedReply {
                command: shown.to_string(),
                expected: "a position in microsteps",
                reply: escape_bytes(reply.data.as_bytes()),
            })
    }

    /// One `get pos`: (status, position).
    fn poll(&mut self, deadline: Instant) -> Result<(DeviceStatus, Degrees), TurntableError> {
        let axis = self.config.axis;
        let reply = self.exchange(axis, "get pos", false, deadline)?;
        let steps = self.microsteps(&reply, "get pos")?;
        Ok((reply.status, self.config.to_degrees(steps)))
    }

    /// Send a movement command, then poll until IDLE at `target` or fail by the deadline.
    fn run_motion(
        &mut self,
        command: &str,
        target: Degrees,
        limit: Duration,
    ) -> Result<Degrees, TurntableError> {
        let start = Instant::now();
        let deadline = start + limit;
        let axis = self.config.axis;
        self.exchange(axis, command, true, deadline)?;
        let tolerance = Degrees(self.config.resolution().0 * 1.000_001);
        let mut last_state = None;
        loop {
            let (status, pos) = match self.poll(deadline) {
                Ok(p) => p,
                Err(e) => return Err(super::out_of_time(e, deadline, target, limit, last_state)),
            };
            last_state = Some(format!("{status:?} at {pos}"));
            if status == DeviceStatus::Idle {
                if pos.within(target, tolerance) {
                    tracing::info!(%target, %pos, elapsed = ?start.elapsed(), "zaber move settled");
                    return Ok(pos);
                }
                return Err(TurntableError::PositionMismatch {
                    commanded: target,
                    reported: pos,
                    tolerance,
                });
            }
            if Instant::now() + self.config.poll_interval >= deadline {
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
}

enum Failure {
    Retry(TurntableError),
    Fatal(TurntableError),
}

impl<L: Link> Turntable for ZaberTurntable<L> {
    fn describe(&mut self) -> Result<String, TurntableError> {
        let deadline = Instant::now() + self.exchange_bound();
        let version = self.exchange(0, "get version", false, deadline)?;
        Ok(format!(
            "Zaber ASCII device {} axis {}, firmware {} ({} microsteps/°)",
            self.config.device, self.config.axis, version.data, self.config.microsteps_per_degree
        ))
    }

    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.run_motion("home", Degrees(0.0), self.config.home_timeout)
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        let target = Degrees::checked(target.0)?;
        let steps = self.config.to_microsteps(target);
        self.run_motion(
            &format!("move abs {steps}"),
            self.config.to_degrees(steps),
            self.config.move_timeout,
        )
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        let deadline = Instant::now() + self.exchange_bound();
        self.poll(deadline).map(|(_, pos)| pos)
    }

    fn stop(&mut self) -> Result<(), TurntableError> {
        let deadline = Instant::now() + self.exchange_bound();
        let axis = self.config.axis;
        self.exchange(axis, "stop", true, deadline)?;
        // A Zaber stage decelerates after `stop`: return once it reports IDLE.
        loop {
            let (status, _) = self.poll(deadline)?;
            if status == DeviceStatus::Idle {
                return Ok(());
            }
            if Instant::now() + self.config.poll_interval >= deadline {
                return Err(TurntableError::Timeout {
                    command: "stop (waiting for IDLE)".into(),
                    timeout: self.exchange_bound(),
                    attempts: 1,
                    received: String::new(),
                });
            }
            std::thread::sleep(self.config.poll_interval);
        }
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
        assert_eq!(encode_home(1, 1), "/1 1 home\n");
        assert_eq!(encode_move_abs(1, 1, -4267), "/1 1 move abs -4267\n");
        assert_eq!(encode_status(2, 1), "/2 1\n");
        assert_eq!(encode_get_pos(1, 1), "/1 1 get pos\n");
        assert_eq!(encode_stop(1, 1), "/1 1 stop\n");
        assert_eq!(encode_with_id(1, 1, 7, "get pos"), "/1 1 7 get pos\n");
        assert_eq!(encode_with_id(3, 0, 99, ""), "/3 0 99\n");
    }

    fn reply(flag: ReplyFlag, status: DeviceStatus, warning: Option<Flag>, data: &str) -> Message {
        Message::Reply(Reply {
            device: 1,
            axis: 1,
            message_id: None,
            flag,
            status,
            warning,
            data: data.into(),
        })
    }

    #[test]
    fn decodes_table() {
        use DeviceStatus::*;
        use ReplyFlag::*;
        let cases: Vec<(&[u8], Message)> = vec![
            (b"@01 1 OK IDLE -- 0", reply(Ok, Idle, None, "0")),
            (b"@01 1 OK BUSY -- 12345", reply(Ok, Busy, None, "12345")),
            (
                b"@01 1 OK IDLE WR 0",
                reply(Ok, Idle, Some(Flag::NoReference), "0"),
            ),
            (
                b"@01 1 OK IDLE FS -17",
                reply(Ok, Idle, Some(Flag::StalledAndStopped), "-17"),
            ),
            (
                b"@01 1 RJ IDLE -- BADDATA",
                reply(Rejected, Idle, None, "BADDATA"),
            ),
            (
                b"@01 1 OK IDLE XY 0:4F",
                reply(Ok, Idle, Some(Flag::Other(*b"XY")), "0"),
            ),
            (b"#01 1 help text", Message::Info("01 1 help text".into())),
            (
                b"!01 1 IDLE --",
                Message::Alert {
                    device: 1,
                    axis: 1,
                    status: Idle,
                    warning: None,
                },
            ),
        ];
        for (line, want) in cases {
            assert_eq!(
                decode_line(line),
                Result::Ok(want),
                "{}",
                escape_bytes(line)
            );
        }
        let with_id = decode_line(b"@01 1 07 OK IDLE -- 5");
        assert!(matches!(
            with_id,
            Result::Ok(Message::Reply(Reply {
                message_id: Some(7),
                ..
            }))
        ));
    }

    #[test]
    fn rejects_table() {
        let cases: &[&[u8]] = &[
            b"",
            b"01 1 OK IDLE -- 0",
            b"@xx 1 OK IDLE -- 0",
            b"@01 1 MAYBE IDLE -- 0",
            b"@01 1 OK SLEEPY -- 0",
            b"@01 1 OK IDLE w 0",
            b"@01 1 OK IDLE --",
            b"@01",
            b"\xff",
        ];
        for line in cases {
            assert!(decode_line(line).is_err(), "{}", escape_bytes(line));
        }
    }

    #[test]
    fn rejection_and_flags() {
        assert_eq!(Rejection::parse("BADCOMMAND"), Rejection::BadCommand);
        assert_eq!(Rejection::parse("WHAT"), Rejection::Other("WHAT".into()));
        assert!(Flag::StalledAndStopped.is_fault());
        assert!(!Flag::NoReference.is_fault());
        assert_eq!(Flag::parse("FZ"), Some(Some(Flag::PeripheralInactive)));
        assert_eq!(
            Flag::PeripheralInactive.to_string(),
            "FZ (peripheral inactive)"
        );
    }

    #[test]
    fn microstep_conversion_round_trips() {
        let c = ZaberConfig::new(X_RSW60A_MICROSTEPS_PER_DEGREE);
        for deg in [0.0, 30.0, 330.0, -45.5, 0.000_117] {
            let steps = c.to_microsteps(Degrees(deg));
            assert!((c.to_degrees(steps).0 - deg).abs() <= c.resolution().0 / 2.0 + 1e-12);
        }
        assert_eq!(c.to_microsteps(Degrees(30.0)), 128_000);
    }
}
