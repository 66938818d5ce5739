//! The station's events rendered for systemd (`Type=notify` services, see `sd_notify(3)`): the
//! [`SystemdNotifier`] sink sends, through the `sd-notify` crate,
//!
//! - `READY=1` when the camera and turntable are open ([`Event::Opened`]): the unit is "active" from
//!   then on, and `TimeoutStartSec=` bounds how long opening the hardware may take;
//! - `STATUS=…` for every station event except [`Event::Alive`] (what `systemctl status` shows: the
//!   pose being worked on, why a view was rejected, the coverage, the verdict with every check);
//! - `WATCHDOG=1` when the service manager asked for pings (`WATCHDOG_USEC`, set by `WatchdogSec=`),
//!   driven **only** by the station's own events. No free-running timer pings on the station's behalf:
//!   if the camera or the turntable stalls the loop, the events stop, the pings stop, and systemd kills
//!   and restarts the unit. [`Event::Alive`] exists so that the loop can keep pinging while it
//!   legitimately waits: on hardware between frames, and during the steps that take long without an
//!   event (a turntable move or homing, the solve, drawing the report), which the station runs through
//!   [`alive_during`]: the step runs on a worker thread while the station's thread emits `Alive` —
//!   for at most the step's own bound, so a step that hangs past it still stops the pings;
//! - `STOPPING=1` from [`SystemdNotifier::stopping`] when the service shuts down (SIGTERM or the end
//!   of a run).
//!
//! # Watchdog pacing
//! With a watchdog interval `W`, a ping is sent with the first event at least `W/4` after the previous
//! ping ([`WatchdogPacer`]). Events arrive all the time during a run (several per pose, `Alive` while
//! waiting), so this keeps the datagrams few while the gap between two pings stays at most
//! `W/4 + (largest gap between events)`: at most `W/2`, as `sd_watchdog_enabled(3)` recommends, as
//! long as the station emits an event at least every `W/4` (7.5 s with the unit's `WatchdogSec=30`;
//! [`alive_during`] emits one every [`ALIVE_EVERY`]).
//! The first event always pings.
//!
//! # Outside systemd
//! Without `NOTIFY_SOCKET` `sd_notify::notify` sends nothing and succeeds, so the sink can stay in place
//! when `cubecal serve` runs from a terminal. A failing send (socket gone, permission) is logged once
//! with `tracing::warn!` and counted ([`SystemdNotifier::send_failures`]); it never stops a run.

use std::sync::mpsc;
use std::time::{Duration, Instant};

use sd_notify::NotifyState;

use super::event::{Event, EventSink};
use crate::run::Verdict;

/// How often [`alive_during`] emits [`Event::Alive`] while its step runs.
pub const ALIVE_EVERY: Duration = Duration::from_secs(1);

/// Run `work` (a long step without events of its own: a move, a solve) on a worker thread while this
/// thread emits [`Event::Alive`] to `sink` every [`ALIVE_EVERY`] — for at most `limit`: a step still
/// running after its bound is stuck, and the silence lets the watchdog say so. Returns `work`'s result
/// (a panic in `work` is resumed here).
pub fn alive_during<T: Send>(
    sink: &mut dyn EventSink,
    limit: Duration,
    work: impl FnOnce() -> T + Send,
) -> T {
    let start = Instant::now();
    std::thread::scope(|scope| {
        let (done_tx, done_rx) = mpsc::channel::<()>();
        let worker = scope.spawn(move || {
            let result = work();
            // The receiver lives until the worker is joined below.
            let _ = done_tx.send(());
            result
        });
        while let Err(mpsc::RecvTimeoutError::Timeout) = done_rx.recv_timeout(ALIVE_EVERY) {
            if start.elapsed() < limit {
                sink.event(&Event::Alive);
            }
        }
        match worker.join() {
            Ok(result) => result,
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
}

/// Decides when a watchdog ping is due: at the first event, then at the first event at least
/// `interval / 4` after the previous ping.
#[derive(Debug, Clone)]
pub struct WatchdogPacer {
    min_gap: Duration,
    last: Option<Instant>,
}

impl WatchdogPacer {
    /// Pacing for the service manager's watchdog interval (`WATCHDOG_USEC`).
    pub fn new(watchdog_interval: Duration) -> WatchdogPacer {
        WatchdogPacer {
            min_gap: watchdog_interval / 4,
            last: None,
        }
    }

    /// The shortest gap between two pings (a quarter of the watchdog interval).
    pub fn min_gap(&self) -> Duration {
        self.min_gap
    }

    /// Whether an event at `now` should carry a ping; if so, `now` becomes the last ping.
    pub fn due(&mut self, now: Instant) -> bool {
        let due = match self.last {
            None => true,
            Some(last) => now.saturating_duration_since(last) >= self.min_gap,
        };
        if due {
            self.last = Some(now);
        }
        due
    }
}

/// An [`EventSink`] that tells systemd what the station is doing (see the module doc).
#[derive(Debug)]
pub struct SystemdNotifier {
    watchdog: Option<WatchdogPacer>,
    /// Number of planned poses, from the latest [`Event::PosePlanned`] (for "pose 3/12").
    total: Option<usize>,
    sent: u64,
    send_failures: u64,
}

impl SystemdNotifier {
    /// A notifier for this process: pings the watchdog when the service manager enabled it for us
    /// (`WATCHDOG_USEC`, and `WATCHDOG_PID` naming this process when set).
    pub fn from_env() -> SystemdNotifier {
        SystemdNotifier::with_watchdog(sd_notify::watchdog_enabled())
    }

    /// A notifier with an explicit watchdog interval (`None`: never ping).
    pub fn with_watchdog(watchdog_interval: Option<Duration>) -> SystemdNotifier {
        SystemdNotifier {
            watchdog: watchdog_interval
                .filter(|w| !w.is_zero())
                .map(WatchdogPacer::new),
            total: None,
            sent: 0,
            send_failures: 0,
        }
    }

    /// The watchdog pacing in use, if the watchdog is enabled.
    pub fn watchdog(&self) -> Option<&WatchdogPacer> {
        self.watchdog.as_ref()
    }

    /// Notifications sent successfully so far (counted also when no `NOTIFY_SOCKET` is set).
    pub fn sent(&self) -> u64 {
        self.sent
    }

    /// Notifications that could not be sent.
    pub fn send_failures(&self) -> u64 {
        self.send_failures
    }

    /// Set a free-form `STATUS=` line (the service's own messages: waiting for the camera, an error).
    pub fn status(&mut self, text: &str) {
        let line = one_line(text);
        self.send(&[NotifyState::Status(&line)]);
    }

    /// Tell systemd the service is shutting down (`STOPPING=1`), with the reason as its status.
    pub fn stopping(&mut self, reason: &str) {
        let line = stopping_line(reason);
        self.send(&[NotifyState::Stopping, NotifyState::Status(&line)]);
    }

    /// Notify systemd of an event (as [`EventSink::event`]) and return the `STATUS=` text sent, so a
    /// front-end can print the same line.
    pub fn notify_event(&mut self, event: &Event) -> Option<String> {
        self.event_at(event, Instant::now())
    }

    /// [`SystemdNotifier::notify_event`] at a given time (the pacing's clock), for tests of the pacing.
    pub fn event_at(&mut self, event: &Event, now: Instant) -> Option<String> {
        let status = self.status_line(event);
        let ping = match self.watchdog.as_mut() {
            Some(pacer) => pacer.due(now),
            None => false,
        };
        let mut states = Vec::with_capacity(3);
        if matches!(event, Event::Opened { .. }) {
            states.push(NotifyState::Ready);
        }
        if let Some(line) = status.as_deref() {
            states.push(NotifyState::Status(line));
        }
        if ping {
            states.push(NotifyState::Watchdog);
        }
        if !states.is_empty() {
            self.send(&states);
        }
        status
    }

    /// The `STATUS=` text for an event (`None` for [`Event::Alive`]). Remembers the number of planned
    /// poses so that later events can say "pose 3/12".
    pub fn status_line(&mut self, event: &Event) -> Option<String> {
        let line = match event {
            Event::Opened {
                source,
                width,
                height,
                turntable,
            } => format!("ready: camera {source} {width}x{height}, turntable {turntable}"),
            Event::PosePlanned {
                index,
                total,
                angle_deg,
                instruction,
            } => {
                self.total = Some(*total);
                let pose = self.pose(*index);
                match (instruction, angle_deg) {
                    (Some(text), _) => format!("{pose}: {text}"),
                    (None, Some(angle)) => format!("{pose}: planned at {angle:.1}°"),
                    (None, None) => format!("{pose}: planned"),
                }
            }
            Event::Homing { instruction } => match instruction {
                Some(text) => format!("homing: {text}"),
                None => "homing the turntable".to_string(),
            },
            Event::PoseChosen {
                index,
                rotation_deg,
                tilt_deg,
                corners,
                ..
            } => format!(
                "{}: chose rotation {rotation_deg:.1}°, tilt {tilt_deg:.1}° ({corners} corners predicted)",
                self.pose(*index)
            ),
            Event::Tilting { index, tilt_deg } => {
                format!("{}: tilting to {tilt_deg:.1}°", self.pose(*index))
            }
            Event::Moving { index, angle_deg } => {
                format!("{}: turning to {angle_deg:.1}°", self.pose(*index))
            }
            Event::Settled { index, angle_deg } => {
                format!("{}: settled at {angle_deg:.1}°", self.pose(*index))
            }
            Event::FrameGrabbed {
                index,
                sequence,
                flushed,
            } => format!(
                "{}: frame {sequence} grabbed ({flushed} stale dropped), detecting",
                self.pose(*index)
            ),
            Event::ViewAccepted {
                index,
                name,
                faces,
                corners,
            } => format!(
                "{}: view {name} accepted, {faces} face(s), {corners} corners",
                self.pose(*index)
            ),
            Event::ViewRejected {
                index,
                name,
                reason,
            } => format!("{}: view {name} rejected: {reason}", self.pose(*index)),
            Event::Coverage {
                views,
                fraction,
                cells_covered,
                cells_total,
                ..
            } => format!(
                "{views} view(s), coverage {:.0}% ({cells_covered}/{cells_total} cells)",
                fraction * 100.0
            ),
            Event::Solving { views, points } => {
                format!("solving: {views} view(s), {points} points")
            }
            Event::Verdict { verdict } => verdict_line(verdict),
            Event::ProfileSpooled {
                path,
                store,
                waiting,
                ..
            } => format!(
                "profile store {store} unreachable: profile waits in {} (spool: {waiting} waiting)",
                path.display()
            ),
            Event::SpoolDrained {
                store,
                committed,
                already_stored,
                failed,
                waiting,
            } => format!(
                "spool: {} committed to {store}, {failed} refused, {waiting} waiting",
                committed + already_stored
            ),
            Event::Alive | Event::Frame { .. } | Event::Detected { .. } => return None,
        };
        Some(one_line(&line))
    }

    fn pose(&self, index: usize) -> String {
        match self.total {
            Some(total) => format!("pose {}/{total}", index + 1),
            None => format!("pose {}", index + 1),
        }
    }

    fn send(&mut self, states: &[NotifyState<'_>]) {
        match sd_notify::notify(states) {
            Ok(()) => self.sent += 1,
            Err(error) => {
                self.send_failures += 1;
                if self.send_failures == 1 {
                    tracing::warn!(
                        %error,
                        socket = ?std::env::var_os("NOTIFY_SOCKET"),
                        "cannot notify the service manager (further failures are logged at debug level)"
                    );
                } else {
                    tracing::debug!(%error, "cannot notify the service manager");
                }
            }
        }
    }
}

impl EventSink for SystemdNotifier {
    fn event(&mut self, event: &Event) {
        self.notify_event(event);
    }
}

/// Send `STOPPING=1` with the reason as status, from anywhere (a signal-handling thread, while the
/// station loop owns the [`SystemdNotifier`]). A failure is logged, not returned: stopping goes on.
pub fn notify_stopping(reason: &str) {
    let line = stopping_line(reason);
    if let Err(error) = sd_notify::notify(&[NotifyState::Stopping, NotifyState::Status(&line)]) {
        tracing::warn!(%error, "cannot tell the service manager that we are stopping");
    }
}

fn stopping_line(reason: &str) -> String {
    format!("stopping: {}", one_line(reason))
}

/// `verdict PASS: rms_px=0.1234 (limit 0.5), …` or `verdict FAIL: coverage=0.34 (limit 0.6) — hint; …`
/// (failing checks first, each with its hint).
pub fn verdict_line(verdict: &Verdict) -> String {
    let mut parts: Vec<String> = Vec::with_capacity(verdict.checks.len());
    for check in verdict.failures() {
        let mut part = format!(
            "{}={} (limit {})",
            check.name,
            number(check.value),
            number(check.threshold)
        );
        if let Some(hint) = &check.hint {
            part.push_str(" — ");
            part.push_str(hint);
        }
        parts.push(part);
    }
    for check in verdict.checks.iter().filter(|c| c.pass) {
        parts.push(format!(
            "{}={} (limit {})",
            check.name,
            number(check.value),
            number(check.threshold)
        ));
    }
    let word = if verdict.pass { "PASS" } else { "FAIL" };
    if parts.is_empty() {
        format!("verdict {word}: no checks")
    } else {
        format!("verdict {word}: {}", parts.join("; "))
    }
}

/// Four decimals in the everyday range, scientific notation for tiny or huge values.
fn number(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 || (1e-3..1e6).contains(&a) || !v.is_finite() {
        format!("{v:.4}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_string()
    } else {
        format!("{v:.3e}")
    }
}

/// A `STATUS=` value must be one line: the notify message is newline-separated `KEY=value` pairs.
fn one_line(text: &str) -> String {
    text.split(['\n', '\r'])
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect::<Vec<_>>()
        .join(" / ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Check;

    #[test]
    fn pacer_pings_first_event_then_at_quarter_interval() {
        let t0 = Instant::now();
        let mut p = WatchdogPacer::new(Duration::from_millis(1000));
        assert_eq!(p.min_gap(), Duration::from_millis(250));
        // Events every 10 ms for 2 s: pings at 0, 250, 500, ... exactly (the grid divides evenly).
        let mut pings = Vec::new();
        for k in 0..=200u64 {
            let now = t0 + Duration::from_millis(10 * k);
            if p.due(now) {
                pings.push(10 * k);
            }
        }
        assert_eq!(pings, vec![0, 250, 500, 750, 1000, 1250, 1500, 1750, 2000]);
        // Events every 300 ms: each one pings (gap above the minimum).
        let mut p = WatchdogPacer::new(Duration::from_millis(1000));
        let due: Vec<bool> = (0..4u64)
            .map(|k| p.due(t0 + Duration::from_millis(300 * k)))
            .collect();
        assert_eq!(due, vec![true; 4]);
    }

    #[test]
    fn status_lines_name_the_pose_and_stay_one_line() {
        let mut n = SystemdNotifier::with_watchdog(None);
        assert_eq!(n.status_line(&Event::Alive), None);
        let planned = Event::PosePlanned {
            index: 2,
            total: 12,
            angle_deg: Some(60.0),
            instruction: None,
        };
        assert_eq!(
            n.status_line(&planned).as_deref(),
            Some("pose 3/12: planned at 60.0°")
        );
        let rejected = Event::ViewRejected {
            index: 2,
            name: "pose_02".into(),
            reason: "blurred\nmove the cube closer".into(),
        };
        assert_eq!(
            n.status_line(&rejected).as_deref(),
            Some("pose 3/12: view pose_02 rejected: blurred / move the cube closer")
        );
    }

    #[test]
    fn verdict_line_lists_failures_first_with_hints() {
        let v = Verdict::from_checks(vec![
            Check::at_most("rms_px", 0.12345, 0.5, unreachable_hint),
            Check::at_least("coverage", 0.34, 0.6, || {
                "add poses near the corners".into()
            }),
            Check::at_most("sigma_fx_rel", 2.5e-5, 1e-3, unreachable_hint),
        ]);
        assert_eq!(
            verdict_line(&v),
            "verdict FAIL: coverage=0.34 (limit 0.6) — add poses near the corners; \
             rms_px=0.1235 (limit 0.5); sigma_fx_rel=2.500e-5 (limit 0.001)"
        );
        let ok = Verdict::from_checks(vec![Check::at_most("rms_px", 0.2, 0.5, unreachable_hint)]);
        assert_eq!(verdict_line(&ok), "verdict PASS: rms_px=0.2 (limit 0.5)");
    }

    fn unreachable_hint() -> String {
        "a passing check has no hint".into()
    }
}
