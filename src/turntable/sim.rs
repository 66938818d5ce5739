//! Protocol simulators: a GRBL 1.1 controller and a Zaber ASCII device, each served from a thread on
//! the master end of a pseudo-terminal so that the real drivers (or `cubecal turntable` pointed at the
//! slave's path) talk to them exactly as to hardware.
//!
//! Motion follows an acceleration-limited trapezoidal profile ([`Trapezoid`]) with configurable speed
//! and acceleration (in the protocol's native units: GRBL axis units, Zaber microsteps), so tests can
//! run moves in milliseconds and bring-up can run them at a realistic pace. Faults ([`Fault`]) are
//! injected on the first *move* command (`G0`/`G1` for GRBL, `move abs` for Zaber; homing is not a
//! move), so a test can home, then see the fault. Simplifications: one axis moves; a new move while
//! moving replans from the current position at rest; feed hold stops at once.
//!
//! A simulator stops when its [`SimHandle`] is dropped (or [`SimHandle::stop`]ped): a stop flag is
//! checked every [`SIM_TICK`].
//!
//! A GRBL simulator can also be *seen* ([`grbl_pair_seen`]): it publishes its position to a
//! [`StageView`] at every tick, and a move (or homing cycle) is reported finished only once the
//! view says a picture of the table at its final position is on screen. A real camera sees the table
//! the moment it stops; a feeder that renders the scene (the capture module's `feed`) needs time, and
//! without this gate the station would grab the previous pose's picture after "settled".

use std::fmt::Write as _;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use super::TurntableError;
use super::grbl::{Axis, CYCLE_START, FEED_HOLD, SOFT_RESET, STATUS_QUERY};

/// Longest a simulator waits for input before updating its motion and checking its stop flag.
pub const SIM_TICK: Duration = Duration::from_millis(2);

/// Bytes a simulator sends instead of a reply under [`Fault::Garbage`]: no valid line in either protocol.
pub const GARBAGE: &[u8] = b"\xff\x00\x13#~garbage\x7f\r\n";

/// An acceleration-limited move from rest to rest: accelerate at `accel` up to `speed`, cruise,
/// decelerate. Short moves never reach `speed` (a triangular profile).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trapezoid {
    pub start: f64,
    pub target: f64,
    t_accel: f64,
    t_cruise: f64,
    v_peak: f64,
    accel: f64,
}

impl Trapezoid {
    /// Plan a move; `speed` and `accel` must be positive (non-positive values are treated as instant).
    pub fn new(start: f64, target: f64, speed: f64, accel: f64) -> Self {
        let d = (target - start).abs();
        if !(speed > 0.0 && accel > 0.0) || d == 0.0 {
            return Trapezoid {
                start,
                target,
                t_accel: 0.0,
                t_cruise: 0.0,
                v_peak: 0.0,
                accel: 0.0,
            };
        }
        // Full trapezoid when the distance covers accelerating to `speed` and back: d ≥ v²/a.
        let (v_peak, t_cruise) = if d >= speed * speed / accel {
            (speed, (d - speed * speed / accel) / speed)
        } else {
            ((d * accel).sqrt(), 0.0)
        };
        Trapezoid {
            start,
            target,
            t_accel: v_peak / accel,
            t_cruise,
            v_peak,
            accel,
        }
    }

    /// Total time of the move.
    pub fn duration(&self) -> Duration {
        Duration::from_secs_f64(2.0 * self.t_accel + self.t_cruise)
    }

    /// Position `t` after the start.
    pub fn position_at(&self, t: Duration) -> f64 {
        let t = t.as_secs_f64();
        let total = 2.0 * self.t_accel + self.t_cruise;
        if t >= total || total == 0.0 {
            return self.target;
        }
        let a = self.accel;
        let s = if t < self.t_accel {
            0.5 * a * t * t
        } else if t < self.t_accel + self.t_cruise {
            0.5 * a * self.t_accel * self.t_accel + self.v_peak * (t - self.t_accel)
        } else {
            let d = (self.target - self.start).abs();
            let r = total - t;
            d - 0.5 * a * r * r
        };
        self.start + s * (self.target - self.start).signum()
    }
}

/// A fault to inject. All but [`Fault::LostSteps`] fire once, on the first move command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    /// From the first move command on, answer nothing (the command itself gets no reply).
    NoReply,
    /// From the first move command on, answer every command with [`GARBAGE`].
    Garbage,
    /// Halfway through the first move, stop: GRBL raises `ALARM:1` (hard limit), Zaber stalls (`FS`).
    AlarmMidMove,
    /// Every move ends `offset` native units away from its target (as if steps were lost).
    LostSteps { offset: f64 },
    /// On the first move command, close the port.
    PortClosed,
}

/// Motion and fault settings shared by both simulators.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimConfig {
    /// Cruise speed in native units per second.
    pub speed: f64,
    /// Acceleration in native units per second².
    pub accel: f64,
    /// The fault to inject, if any.
    pub fault: Option<Fault>,
}

/// Handle to a running simulator; dropping it stops the simulator thread and waits for it.
#[derive(Debug)]
pub struct SimHandle {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl SimHandle {
    /// Stop the simulator and wait for its thread.
    pub fn stop(mut self) {
        self.shutdown();
    }

    /// Whether the simulator thread is still serving (false after [`Fault::PortClosed`] fired).
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("turntable simulator thread panicked");
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// What a camera sees of a simulated stage (see the module doc): the position the simulator publishes
/// every tick (native units), and the position whose picture a feeder has on screen. Cloning shares it.
#[derive(Debug, Clone, Default)]
pub struct StageView(Arc<Mutex<ViewState>>);

#[derive(Debug, Default)]
struct ViewState {
    position: f64,
    moving: bool,
    shown: Option<f64>,
}

impl StageView {
    fn lock(&self) -> std::sync::MutexGuard<'_, ViewState> {
        // The state is two numbers: a panicked holder cannot leave it inconsistent.
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The stage's position now (native units: GRBL axis units).
    pub fn position(&self) -> f64 {
        self.lock().position
    }

    /// The stage's position now and whether it is moving (a move or homing cycle under way).
    pub fn position_and_motion(&self) -> (f64, bool) {
        let s = self.lock();
        (s.position, s.moving)
    }

    /// A picture of the stage at `position` (a value read from [`StageView::position`]) is on screen.
    pub fn set_shown(&self, position: f64) {
        self.lock().shown = Some(position);
    }

    /// The position whose picture is on screen, if any.
    pub fn shown(&self) -> Option<f64> {
        self.lock().shown
    }

    fn publish(&self, position: f64, moving: bool) {
        let mut s = self.lock();
        s.position = position;
        s.moving = moving;
    }

    fn shows(&self, position: f64) -> bool {
        self.lock().shown == Some(position)
    }
}

/// What a protocol machine does with bytes and time.
trait Machine: Send + 'static {
    /// Handle one received byte, appending any reply to `out`.
    fn on_byte(&mut self, b: u8, now: Instant, out: &mut Vec<u8>);
    /// Advance motion to `now`, appending any unprompted output to `out`.
    fn tick(&mut self, now: Instant, out: &mut Vec<u8>);
    /// Whether the machine wants the port closed ([`Fault::PortClosed`]).
    fn hung_up(&self) -> bool;
}

fn spawn(
    mut port: TTYPort,
    mut machine: impl Machine,
    name: &'static str,
) -> Result<SimHandle, TurntableError> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    let thread = std::thread::Builder::new()
        .name(format!("{name}-sim"))
        .spawn(move || {
            let mut buf = [0u8; 256];
            let mut out = Vec::new();
            if port.set_timeout(SIM_TICK).is_err() {
                tracing::error!("simulator cannot set its port timeout");
                return;
            }
            while !flag.load(Ordering::Relaxed) {
                let now = Instant::now();
                machine.tick(now, &mut out);
                match port.read(&mut buf) {
                    Ok(n) => {
                        for &b in &buf[..n] {
                            machine.on_byte(b, now, &mut out);
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                    // No slave end open (EIO) or similar: wait for a client.
                    Err(_) => std::thread::sleep(SIM_TICK * 5),
                }
                if machine.hung_up() {
                    tracing::info!("{name} simulator closing its port (injected fault)");
                    return; // drops `port`
                }
                if !out.is_empty() {
                    if let Err(e) = port.write_all(&out) {
                        tracing::debug!(error = %e, "{name} simulator write failed");
                    }
                    out.clear();
                }
            }
        });
    match thread {
        Ok(t) => Ok(SimHandle {
            stop,
            thread: Some(t),
        }),
        Err(e) => Err(TurntableError::Simulator {
            during: "spawning the simulator thread",
            source: e.into(),
        }),
    }
}

/// Create a pty pair and serve a GRBL simulator on its master end; returns the slave end (for a driver,
/// or to keep open while an external client uses its path) and the handle.
pub fn grbl_pair(config: SimConfig, grbl: GrblSim) -> Result<(TTYPort, SimHandle), TurntableError> {
    let (master, slave) = pty_pair()?;
    Ok((
        slave,
        spawn(master, GrblMachine::new(config, grbl), "grbl")?,
    ))
}

/// [`grbl_pair`] for a simulator that a camera sees through `view`: moves finish only once the view
/// shows the final position (see the module doc).
pub fn grbl_pair_seen(
    config: SimConfig,
    grbl: GrblSim,
    view: StageView,
) -> Result<(TTYPort, SimHandle), TurntableError> {
    let (master, slave) = pty_pair()?;
    let mut machine = GrblMachine::new(config, grbl);
    machine.view = Some(view);
    Ok((slave, spawn(master, machine, "grbl")?))
}

/// Create a pty pair and serve a Zaber ASCII simulator on its master end (see [`grbl_pair`]).
pub fn zaber_pair(
    config: SimConfig,
    zaber: ZaberSim,
) -> Result<(TTYPort, SimHandle), TurntableError> {
    let (master, slave) = pty_pair()?;
    Ok((
        slave,
        spawn(master, ZaberMachine::new(config, zaber), "zaber")?,
    ))
}

fn pty_pair() -> Result<(TTYPort, TTYPort), TurntableError> {
    TTYPort::pair().map_err(|source| TurntableError::Simulator {
        during: "allocating a pseudo-terminal pair",
        source,
    })
}

/// Per-move state shared by both machines.
#[derive(Debug)]
struct Motion {
    traj: Trapezoid,
    t0: Instant,
    /// When the injected mid-move alarm/stall fires.
    fault_at: Option<Instant>,
}

/// Fault bookkeeping shared by both machines.
#[derive(Debug)]
struct FaultState {
    fault: Option<Fault>,
    fired: bool,
    silent: bool,
    garbage: bool,
    hung_up: bool,
}

impl FaultState {
    fn new(fault: Option<Fault>) -> Self {
        FaultState {
            fault,
            fired: false,
            silent: false,
            garbage: false,
            hung_up: false,
        }
    }

    /// Called on each move command; returns the mid-move fault time if one is due.
    fn on_move(&mut self, traj: &Trapezoid, now: Instant) -> Option<Instant> {
        if self.fired {
            return None;
        }
        let fault = self.fault?;
        if matches!(fault, Fault::LostSteps { .. }) {
            return None;
        }
        self.fired = true;
        tracing::info!(?fault, "simulator injecting fault");
        match fault {
            Fault::NoReply => self.silent = true,
            Fault::Garbage => self.garbage = true,
            Fault::PortClosed => self.hung_up = true,
            Fault::AlarmMidMove => return Some(now + traj.duration() / 2),
            Fault::LostSteps { .. } => {}
        }
        None
    }

    fn offset(&self) -> f64 {
        match self.fault {
            Some(Fault::LostSteps { offset }) => offset,
            _ => 0.0,
        }
    }
}

// ------------------------------------------------------------------------------------------------
// GRBL

/// GRBL-specific simulator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GrblSim {
    /// The axis the table is on (the report has 3 axes, or as many as needed to include it).
    pub axis: Axis,
    /// Homing switches configured (`$22=1`): start in Alarm, `$H` works and ends at machine 0 (as GRBL
    /// built with `HOMING_FORCE_SET_ORIGIN`). Otherwise `$H` is `error:5`.
    pub homing: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GState {
    Idle,
    Run,
    Home,
    Hold,
    Alarm,
}

/// GRBL's line buffer size; longer lines get `error:11`.
const GRBL_LINE_MAX: usize = 80;

struct GrblMachine {
    cfg: SimConfig,
    grbl: GrblSim,
    axes: usize,
    pos: f64,
    relative: bool,
    state: GState,
    motion: Option<Motion>,
    line: Vec<u8>,
    overflow: bool,
    reports: u32,
    faults: FaultState,
    /// The camera's view of the stage, when a feeder renders it ([`grbl_pair_seen`]).
    view: Option<StageView>,
    /// Motion ended at `pos`; the state stays Run (or Home) until the view shows `pos`.
    awaiting_view: bool,
}

impl GrblMachine {
    fn new(cfg: SimConfig, grbl: GrblSim) -> Self {
        GrblMachine {
            cfg,
            grbl,
            axes: (grbl.axis.index() + 1).max(3),
            pos: 0.0,
            relative: false,
            state: if grbl.homing {
                GState::Alarm
            } else {
                GState::Idle
            },
            motion: None,
            line: Vec::new(),
            overflow: false,
            reports: 0,
            faults: FaultState::new(cfg.fault),
            view: None,
            awaiting_view: false,
        }
    }

    fn current(&self, now: Instant) -> f64 {
        match &self.motion {
            Some(m) => m.traj.position_at(now.saturating_duration_since(m.t0)),
            None => self.pos,
        }
    }

    /// End a move or homing cycle at `pos`: `ok` for homing, then Idle.
    fn finish_motion(&mut self, out: &mut Vec<u8>) {
        self.awaiting_view = false;
        if self.state == GState::Home {
            self.reply(b"ok\r\n", out);
        }
        self.state = GState::Idle;
    }

    fn status(&mut self, now: Instant, out: &mut Vec<u8>) {
        let state = match self.state {
            GState::Idle => "Idle",
            GState::Run => "Run",
            GState::Home => "Home",
            GState::Hold => "Hold:0",
            GState::Alarm => "Alarm",
        };
        let p = self.current(now);
        let mut s = format!("<{state}|MPos:");
        for i in 0..self.axes {
            let v = if i == self.grbl.axis.index() { p } else { 0.0 };
            let sep = if i + 1 == self.axes { "" } else { "," };
            let _ = write!(s, "{v:.3}{sep}");
        }
        s.push_str("|FS:0,0");
        if self.reports.is_multiple_of(10) {
            s.push_str("|WCO:");
            s.push_str(&vec!["0.000"; self.axes].join(","));
        }
        s.push_str(">\r\n");
        self.reports += 1;
        out.extend_from_slice(s.as_bytes());
    }

    fn start_move(&mut self, target: f64, now: Instant) {
        let from = self.current(now);
        let traj = Trapezoid::new(from, target, self.cfg.speed, self.cfg.accel);
        self.pos = from;
        self.awaiting_view = false;
        let fault_at = self.faults.on_move(&traj, now);
        self.motion = Some(Motion {
            traj,
            t0: now,
            fault_at,
        });
    }

    fn line(&mut self, now: Instant, out: &mut Vec<u8>) {
        let raw = std::mem::take(&mut self.line);
        if std::mem::take(&mut self.overflow) {
            out.extend_from_slice(b"error:11\r\n");
            return;
        }
        let text: String = String::from_utf8_lossy(&raw)
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect::<String>()
            .to_ascii_uppercase();
        let reply: &[u8] = match text.as_str() {
            "" => b"ok\r\n",
            "$X" => {
                if self.state == GState::Alarm {
                    self.state = GState::Idle;
                    b"[MSG:Caution: Unlocked]\r\nok\r\n"
                } else {
                    b"ok\r\n"
                }
            }
            "$H" if !self.grbl.homing => b"error:5\r\n",
            "$H" => {
                if matches!(self.state, GState::Run | GState::Home) {
                    b"error:8\r\n"
                } else {
                    // `ok` comes when the cycle ends (in tick).
                    let from = self.current(now);
                    let traj = Trapezoid::new(from, 0.0, self.cfg.speed, self.cfg.accel);
                    self.awaiting_view = false;
                    self.motion = Some(Motion {
                        traj,
                        t0: now,
                        fault_at: None,
                    });
                    self.state = GState::Home;
                    b""
                }
            }
            "$I" => b"[VER:1.1h.20190825:cubecal-sim]\r\n[OPT:V,15,128]\r\nok\r\n",
            t if t.starts_with('$') => b"error:3\r\n",
            _ => return self.gcode(&text, now, out),
        };
        self.reply(reply, out);
    }

    fn reply(&self, bytes: &[u8], out: &mut Vec<u8>) {
        if self.faults.silent {
            return;
        }
        if self.faults.garbage {
            out.extend_from_slice(super::sim::GARBAGE);
            return;
        }
        out.extend_from_slice(bytes);
    }

    fn gcode(&mut self, text: &str, now: Instant, out: &mut Vec<u8>) {
        if self.state == GState::Alarm {
            return self.reply(b"error:9\r\n", out);
        }
        let mut words = Vec::new();
        let mut chars = text.chars().peekable();
        while let Some(letter) = chars.next() {
            if !letter.is_ascii_alphabetic() {
                return self.reply(b"error:1\r\n", out);
            }
            let mut num = String::new();
            while let Some(&c) = chars.peek() {
                if c.is_ascii_digit() || c == '.' || c == '-' || c == '+' {
                    num.push(c);
                    chars.next();
                } else {
                    break;
                }
            }
            match num.parse::<f64>() {
                Ok(v) if v.is_finite() => words.push((letter, v)),
                _ => return self.reply(b"error:2\r\n", out),
            }
        }
        let mut target = None;
        let mut motion = false;
        for (letter, v) in words {
            match (letter, v) {
                ('G', 90.0) => self.relative = false,
                ('G', 91.0) => self.relative = true,
                ('G', 0.0 | 1.0) => motion = true,
                ('G', 53.0) => {} // machine coordinates: the simulator has no work offsets
                ('F' | 'N', _) => {}
                (l, v) if Axis::from_letter(l).is_some_and(|a| a.index() < self.axes) => {
                    if Axis::from_letter(l) == Some(self.grbl.axis) {
                        target = Some(v);
                    }
                }
                _ => return self.reply(b"error:20\r\n", out),
            }
        }
        if let (true, Some(v)) = (motion, target) {
            let base = if self.relative {
                self.current(now)
            } else {
                0.0
            };
            self.start_move(base + v + self.faults.offset(), now);
            self.state = GState::Run;
            if self.faults.hung_up {
                return;
            }
        }
        self.reply(b"ok\r\n", out);
    }
}

impl Machine for GrblMachine {
    fn on_byte(&mut self, b: u8, now: Instant, out: &mut Vec<u8>) {
        match b {
            STATUS_QUERY => {
                if self.faults.silent {
                } else if self.faults.garbage {
                    out.extend_from_slice(GARBAGE);
                } else {
                    self.status(now, out);
                }
            }
            FEED_HOLD => {
                if self.state == GState::Run {
                    self.pos = self.current(now);
                    self.motion = None;
                    self.awaiting_view = false;
                    self.state = GState::Hold;
                }
            }
            CYCLE_START => {
                if self.state == GState::Hold {
                    self.state = GState::Idle;
                }
            }
            SOFT_RESET => {
                self.line.clear();
                self.pos = self.current(now);
                self.awaiting_view = false;
                if matches!(self.state, GState::Run | GState::Home) {
                    self.motion = None;
                    self.state = GState::Alarm;
                    self.reply(b"ALARM:3\r\n", out);
                } else if self.state == GState::Hold {
                    self.state = GState::Idle;
                }
                self.reply(b"\r\nGrbl 1.1h ['$' for help]\r\n", out);
                if self.state == GState::Alarm {
                    self.reply(b"[MSG:'$H'|'$X' to unlock]\r\n", out);
                }
            }
            b'\n' => self.line(now, out),
            b'\r' => {}
            _ => {
                if self.line.len() >= GRBL_LINE_MAX {
                    self.overflow = true;
                } else {
                    self.line.push(b);
                }
            }
        }
    }

    fn tick(&mut self, now: Instant, out: &mut Vec<u8>) {
        if let Some(view) = &self.view {
            view.publish(self.current(now), self.motion.is_some());
        }
        if self.awaiting_view {
            if self.view.as_ref().is_none_or(|v| v.shows(self.pos)) {
                self.finish_motion(out);
            }
            return;
        }
        let Some(m) = &self.motion else { return };
        if m.fault_at.is_some_and(|t| now >= t) {
            self.pos = self.current(now);
            self.motion = None;
            self.state = GState::Alarm;
            self.reply(b"ALARM:1\r\n[MSG:Reset to continue]\r\n", out);
            return;
        }
        if now.saturating_duration_since(m.t0) >= m.traj.duration() {
            self.pos = m.traj.target;
            self.motion = None;
            match &self.view {
                Some(view) if !view.shows(self.pos) => {
                    view.publish(self.pos, false);
                    self.awaiting_view = true;
                }
                _ => self.finish_motion(out),
            }
        }
    }

    fn hung_up(&self) -> bool {
        self.faults.hung_up
    }
}

// ------------------------------------------------------------------------------------------------
// Zaber

/// Zaber-specific simulator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZaberSim {
    /// Device address (replies only to this address and to 0 = all).
    pub device: u8,
    /// Travel limit, ± microsteps (`move abs` beyond it is `RJ … BADDATA`).
    pub limit_microsteps: i64,
}

struct ZaberMachine {
    cfg: SimConfig,
    zaber: ZaberSim,
    pos: f64,
    homed: bool,
    stalled: bool,
    motion: Option<Motion>,
    line: Vec<u8>,
    faults: FaultState,
}

impl ZaberMachine {
    fn new(cfg: SimConfig, zaber: ZaberSim) -> Self {
        ZaberMachine {
            cfg,
            zaber,
            pos: 0.0,
            homed: false,
            stalled: false,
            motion: None,
            line: Vec::new(),
            faults: FaultState::new(cfg.fault),
        }
    }

    fn current(&self, now: Instant) -> f64 {
        match &self.motion {
            Some(m) => m.traj.position_at(now.saturating_duration_since(m.t0)),
            None => self.pos,
        }
    }

    fn flag(&self) -> &'static str {
        if self.stalled {
            "FS"
        } else if !self.homed {
            "WR"
        } else {
            "--"
        }
    }

    fn line(&mut self, now: Instant, out: &mut Vec<u8>) {
        let raw = std::mem::take(&mut self.line);
        let text = String::from_utf8_lossy(&raw);
        let Some(body) = text.trim().strip_prefix('/') else {
            return; // not a command: a real device ignores it
        };
        let mut words = body.split_whitespace().peekable();
        let num = |words: &mut std::iter::Peekable<std::str::SplitWhitespace<'_>>| match words
            .peek()
            .and_then(|w| w.parse::<u8>().ok())
        {
            Some(n) => {
                words.next();
                Some(n)
            }
            None => None,
        };
        let device = num(&mut words).unwrap_or(0);
        let axis = num(&mut words).unwrap_or(0);
        let id = num(&mut words);
        let command: Vec<&str> = words.collect();
        if device != 0 && device != self.zaber.device {
            return;
        }
        if self.faults.silent {
            return;
        }
        let rj = |reason: &str| (false, reason.to_string());
        let (ok, data) = if axis > 1 {
            rj("BADAXIS")
        } else {
            match command.as_slice() {
                [] => (true, "0".to_string()),
                ["home"] => {
                    let from = self.current(now);
                    self.stalled = false;
                    self.homed = true;
                    self.pos = from;
                    self.motion = Some(Motion {
                        traj: Trapezoid::new(from, 0.0, self.cfg.speed, self.cfg.accel),
                        t0: now,
                        fault_at: None,
                    });
                    (true, "0".to_string())
                }
                ["move", "abs", n] => match n.parse::<i64>() {
                    Ok(n) if n.abs() <= self.zaber.limit_microsteps => {
                        let from = self.current(now);
                        self.stalled = false;
                        self.pos = from;
                        let target = n as f64 + self.faults.offset();
                        let traj = Trapezoid::new(from, target, self.cfg.speed, self.cfg.accel);
                        let fault_at = self.faults.on_move(&traj, now);
                        self.motion = Some(Motion {
                            traj,
                            t0: now,
                            fault_at,
                        });
                        (true, "0".to_string())
                    }
                    _ => rj("BADDATA"),
                },
                ["move", ..] => rj("BADDATA"),
                ["get", "pos"] => (true, format!("{}", self.current(now).round() as i64)),
                ["get", "version"] => (true, "7.38".to_string()),
                ["stop"] => {
                    self.pos = self.current(now);
                    self.motion = None;
                    (true, "0".to_string())
                }
                ["warnings", "clear"] => {
                    let f = self.flag();
                    self.stalled = false;
                    (true, f.to_string())
                }
                _ => rj("BADCOMMAND"),
            }
        };
        if self.faults.silent || self.faults.hung_up {
            return;
        }
        if self.faults.garbage {
            out.extend_from_slice(GARBAGE);
            return;
        }
        let busy = if self.motion.is_some() {
            "BUSY"
        } else {
            "IDLE"
        };
        let id = id.map(|i| format!(" {i:02}")).unwrap_or_default();
        let reply = format!(
            "@{:02} {axis}{id} {} {busy} {} {data}\r\n",
            self.zaber.device,
            if ok { "OK" } else { "RJ" },
            self.flag()
        );
        out.extend_from_slice(reply.as_bytes());
    }
}

impl Machine for ZaberMachine {
    fn on_byte(&mut self, b: u8, now: Instant, out: &mut Vec<u8>) {
        match b {
            b'\n' => self.line(now, out),
            b'\r' => {}
            _ if self.line.len() < 256 => self.line.push(b),
            _ => {}
        }
    }

    fn tick(&mut self, now: Instant, _out: &mut Vec<u8>) {
        let Some(m) = &self.motion else { return };
        if m.fault_at.is_some_and(|t| now >= t) {
            self.pos = self.current(now);
            self.motion = None;
            self.stalled = true;
            return;
        }
        if now.saturating_duration_since(m.t0) >= m.traj.duration() {
            self.pos = m.traj.target;
            self.motion = None;
        }
    }

    fn hung_up(&self) -> bool {
        self.faults.hung_up
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    #[test]
    fn trapezoid_reaches_target_monotonically_within_limits() {
        for (start, target, v, a) in [
            (0.0, 100.0, 10.0, 5.0),
            (50.0, -20.0, 10.0, 100.0),
            (0.0, 1.0, 10.0, 5.0),
        ] {
            let t = Trapezoid::new(start, target, v, a);
            let total = t.duration();
            assert_eq!(t.position_at(total), target);
            assert_eq!(t.position_at(Duration::ZERO), start);
            let n = 200;
            let dt = total.as_secs_f64() / n as f64;
            let mut prev = start;
            for i in 1..=n {
                let p = t.position_at(Duration::from_secs_f64(dt * i as f64));
                let speed = (p - prev).abs() / dt;
                assert!(speed <= v * 1.001 + 1e-9, "speed {speed} > {v}");
                assert!((p - prev) * (target - start) >= -1e-9, "not monotonic");
                prev = p;
            }
        }
        // 100 units at 10/s with 5/s²: 2 s accelerating, 8 s cruising, 2 s braking.
        let t = Trapezoid::new(0.0, 100.0, 10.0, 5.0);
        assert!((t.duration().as_secs_f64() - 12.0).abs() < 1e-9);
    }
}
