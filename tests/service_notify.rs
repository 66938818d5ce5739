//! The systemd notify protocol over a real `AF_UNIX` datagram socket.
//!
//! Each test binds a datagram socket in a temporary directory, then runs this same test binary again
//! as a child process (the `child` test below, `#[ignore]`d so it only runs when asked for) with
//! `NOTIFY_SOCKET` (and `WATCHDOG_USEC`) in the child's environment, exactly as systemd starts a
//! `Type=notify` service. The child feeds a scripted stream of station events into
//! [`SystemdNotifier::from_env`]; the parent reads every datagram with its arrival time and checks the
//! messages: their sequence for a whole run, the watchdog pings' spacing while events flow, and that
//! the pings stop when the events do.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
#![allow(clippy::print_stderr)]

use std::os::unix::net::UnixDatagram;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

use cubecal::station::notify::{ALIVE_EVERY, SystemdNotifier, alive_during};
use cubecal::station::{Check, Event, EventSink, Verdict};

/// The child's scenario is named in this variable; without it the `child` test refuses to run.
const SCENARIO: &str = "CUBECAL_NOTIFY_SCENARIO";

/// Watchdog interval of the pacing scenario (1 s: pings every 250–500 ms).
const WATCHDOG_USEC: u64 = 1_000_000;
/// How long the pacing scenario emits events, and how long it then stays silent.
const BUSY: Duration = Duration::from_millis(3000);
const QUIET: Duration = Duration::from_millis(1500);

/// The long step of the `long_step` scenario, and the bound it overruns.
const STEP: Duration = Duration::from_millis(4500);
const STEP_LIMIT: Duration = Duration::from_millis(3000);

/// One datagram as received: arrival time and its `KEY=value` lines.
#[derive(Debug)]
struct Message {
    at: Instant,
    lines: Vec<String>,
}

impl Message {
    fn has(&self, line: &str) -> bool {
        self.lines.iter().any(|l| l == line)
    }
    fn status(&self) -> Option<&str> {
        self.lines.iter().find_map(|l| l.strip_prefix("STATUS="))
    }
}

/// A bound notify socket; a thread forwards every datagram, with its arrival time, to `rx`.
struct Listener {
    _dir: tempfile::TempDir,
    path: PathBuf,
    rx: mpsc::Receiver<Message>,
}

impl Listener {
    fn new() -> Listener {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notify");
        let socket = UnixDatagram::bind(&path).unwrap();
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            let mut buf = vec![0u8; 64 * 1024];
            loop {
                let n = socket.recv(&mut buf).expect("recv on the notify socket");
                let text = String::from_utf8(buf[..n].to_vec()).unwrap();
                let message = Message {
                    at: Instant::now(),
                    lines: text.lines().map(str::to_string).collect(),
                };
                if tx.send(message).is_err() {
                    return;
                }
            }
        });
        Listener {
            _dir: dir,
            path,
            rx,
        }
    }

    /// Every message that arrived so far, waiting `settle` for late ones.
    fn drain(&self, settle: Duration) -> Vec<Message> {
        let mut out = Vec::new();
        while let Ok(m) = self.rx.recv_timeout(settle) {
            out.push(m);
        }
        out
    }
}

/// Run the `child` test of this binary with `scenario`, the notify socket and the watchdog variable;
/// return every datagram it sent and the child's run time.
fn run_child(scenario: &str, watchdog_usec: Option<u64>) -> (Vec<Message>, Duration) {
    let listener = Listener::new();
    let start = Instant::now();
    let mut cmd = Command::new(std::env::current_exe().unwrap());
    cmd.args([
        "child",
        "--exact",
        "--ignored",
        "--nocapture",
        "--test-threads=1",
    ])
    .env(SCENARIO, scenario)
    .env("NOTIFY_SOCKET", &listener.path)
    .env_remove("WATCHDOG_USEC")
    .env_remove("WATCHDOG_PID")
    .stdout(Stdio::piped())
    .stderr(Stdio::piped());
    if let Some(usec) = watchdog_usec {
        cmd.env("WATCHDOG_USEC", usec.to_string());
    }
    let out = cmd.output().unwrap();
    let elapsed = start.elapsed();
    assert!(
        out.status.success(),
        "child scenario {scenario} failed: {}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // The datagrams are queued in the socket before the child exits.
    (listener.drain(Duration::from_millis(300)), elapsed)
}

/// The scripted run: two poses (one rejected), coverage, solve and a failing verdict.
fn scripted_run() -> Vec<Event> {
    vec![
        Event::Opened {
            source: "/dev/video0".into(),
            width: 1280,
            height: 720,
            turntable: "GRBL 1.1h".into(),
        },
        Event::PosePlanned {
            index: 0,
            total: 2,
            angle_deg: Some(0.0),
            instruction: None,
        },
        Event::Moving {
            index: 0,
            angle_deg: 0.0,
        },
        Event::Alive,
        Event::Settled {
            index: 0,
            angle_deg: 0.0,
        },
        Event::FrameGrabbed {
            index: 0,
            sequence: 17,
            flushed: 3,
        },
        Event::ViewAccepted {
            index: 0,
            name: "pose_00".into(),
            faces: 3,
            corners: 170,
        },
        Event::Coverage {
            views: 1,
            fraction: 0.25,
            cells_covered: 12,
            cells_total: 48,
            grid: [8, 6],
            counts: vec![1; 48],
        },
        Event::PosePlanned {
            index: 1,
            total: 2,
            angle_deg: Some(45.0),
            instruction: None,
        },
        Event::Moving {
            index: 1,
            angle_deg: 45.0,
        },
        Event::Settled {
            index: 1,
            angle_deg: 45.0,
        },
        Event::FrameGrabbed {
            index: 1,
            sequence: 31,
            flushed: 2,
        },
        Event::ViewRejected {
            index: 1,
            name: "pose_01".into(),
            reason: "no face found".into(),
        },
        Event::Solving {
            views: 1,
            points: 170,
        },
        Event::Verdict {
            verdict: Verdict::from_checks(vec![
                Check::at_most("rms_px", 0.21, 0.5, || "unused".into()),
                Check::at_least("coverage", 0.25, 0.6, || "add poses".into()),
            ]),
        },
    ]
}

/// Runs only as the child of the tests below (with `CUBECAL_NOTIFY_SCENARIO` set).
#[test]
#[ignore = "helper: the other tests in this file run it in a child process with NOTIFY_SOCKET set"]
fn child() {
    let scenario = std::env::var(SCENARIO)
        .expect("the child test runs only from the other tests of tests/service_notify.rs");
    let mut sink = SystemdNotifier::from_env();
    match scenario.as_str() {
        "run" => {
            for event in scripted_run() {
                sink.event(&event);
            }
            sink.stopping("run finished");
        }
        "pacing" => {
            sink.event(&Event::Opened {
                source: "/dev/video0".into(),
                width: 640,
                height: 480,
                turntable: "none".into(),
            });
            let start = Instant::now();
            while start.elapsed() < BUSY {
                sink.event(&Event::Alive);
                thread::sleep(Duration::from_millis(10));
            }
            sink.status("quiet");
            thread::sleep(QUIET);
            sink.stopping("done");
        }
        "long_step" => {
            sink.event(&Event::Opened {
                source: "/dev/video0".into(),
                width: 640,
                height: 480,
                turntable: "none".into(),
            });
            // A step without events of its own (a solve, a move waiting for its turntable) that
            // overruns its bound: pings while within the bound, silence after it.
            let value = alive_during(&mut sink, STEP_LIMIT, || {
                thread::sleep(STEP);
                42
            });
            assert_eq!(value, 42, "the step's result comes back");
            sink.status("step done");
            sink.stopping("done");
        }
        other => panic!("unknown scenario {other}"),
    }
    assert_eq!(sink.send_failures(), 0, "every notification was delivered");
}

#[test]
fn a_scripted_run_sends_ready_statuses_verdict_and_stopping_in_order() {
    let (messages, _) = run_child("run", None);
    let got: Vec<String> = messages.iter().map(|m| m.lines.join("|")).collect();
    let want = [
        "READY=1|STATUS=ready: camera /dev/video0 1280x720, turntable GRBL 1.1h",
        "STATUS=pose 1/2: planned at 0.0°",
        "STATUS=pose 1/2: turning to 0.0°",
        "STATUS=pose 1/2: settled at 0.0°",
        "STATUS=pose 1/2: frame 17 grabbed (3 stale dropped), detecting",
        "STATUS=pose 1/2: view pose_00 accepted, 3 face(s), 170 corners",
        "STATUS=1 view(s), coverage 25% (12/48 cells)",
        "STATUS=pose 2/2: planned at 45.0°",
        "STATUS=pose 2/2: turning to 45.0°",
        "STATUS=pose 2/2: settled at 45.0°",
        "STATUS=pose 2/2: frame 31 grabbed (2 stale dropped), detecting",
        "STATUS=pose 2/2: view pose_01 rejected: no face found",
        "STATUS=solving: 1 view(s), 170 points",
        "STATUS=verdict FAIL: coverage=0.25 (limit 0.6) — add poses; rms_px=0.21 (limit 0.5)",
        "STOPPING=1|STATUS=stopping: run finished",
    ];
    assert_eq!(
        got, want,
        "without WATCHDOG_USEC: no pings, Alive sends nothing"
    );
}

#[test]
fn watchdog_pings_follow_events_at_most_half_the_interval_apart_and_stop_with_them() {
    let (messages, elapsed) = run_child("pacing", Some(WATCHDOG_USEC));
    let watchdog = Duration::from_micros(WATCHDOG_USEC);
    let pings: Vec<Instant> = messages
        .iter()
        .filter(|m| m.has("WATCHDOG=1"))
        .map(|m| m.at)
        .collect();
    let quiet_at = messages
        .iter()
        .find(|m| m.has("STATUS=quiet"))
        .expect("the quiet marker")
        .at;
    let stopping_at = messages
        .iter()
        .find(|m| m.has("STOPPING=1"))
        .expect("STOPPING=1")
        .at;
    assert!(
        messages[0].lines.iter().any(|l| l == "READY=1")
            && messages[0].lines.iter().any(|l| l == "WATCHDOG=1"),
        "the first event readies and pings: {:?}",
        messages[0]
    );
    let gaps: Vec<Duration> = pings.windows(2).map(|w| w[1] - w[0]).collect();
    let gaps_ms: Vec<u128> = gaps.iter().map(Duration::as_millis).collect();
    eprintln!(
        "{} pings in {BUSY:?} of events (child ran {elapsed:?}), gaps ms: {gaps_ms:?}",
        pings.len()
    );
    // Rate-limited: not one ping per event (300 Alive events), about one per W/4.
    let expected = (BUSY.as_secs_f64() / (watchdog.as_secs_f64() / 4.0)) as usize;
    assert!(
        (expected - 2..=expected + 2).contains(&pings.len()),
        "{} pings, expected about {expected}",
        pings.len()
    );
    // Never more than half the interval apart while events flow. Arrival times carry scheduling
    // jitter on a loaded machine, so the lower bound gets 60 ms of slack (send-side pacing is exact,
    // see the unit test of WatchdogPacer).
    for gap in &gaps {
        assert!(
            *gap <= watchdog / 2,
            "gap {gap:?} above W/2 = {:?}",
            watchdog / 2
        );
        assert!(
            *gap + Duration::from_millis(60) >= watchdog / 4,
            "gap {gap:?} below W/4 = {:?}",
            watchdog / 4
        );
    }
    // Pings stop with the events: none after the quiet marker, which came QUIET before STOPPING.
    assert!(
        pings.iter().all(|p| *p < quiet_at),
        "a ping arrived after the events stopped"
    );
    assert!(
        stopping_at - quiet_at >= QUIET - Duration::from_millis(50),
        "the silence lasted {:?}",
        stopping_at - quiet_at
    );
}

/// A long step run through `alive_during` (as the station runs its solves, moves and report) keeps
/// the watchdog fed — pings at most W/2 apart although the step itself emits nothing — until its
/// bound; after the bound the pings stop while the step still runs, so a hung step is still caught.
#[test]
fn pings_continue_during_a_long_step_until_its_bound() {
    let (messages, _) = run_child("long_step", Some(WATCHDOG_USEC));
    let watchdog = Duration::from_micros(WATCHDOG_USEC);
    let start = messages
        .iter()
        .find(|m| m.has("READY=1"))
        .expect("READY=1")
        .at;
    let done = messages
        .iter()
        .find(|m| m.has("STATUS=step done"))
        .expect("the end-of-step marker")
        .at;
    let pings: Vec<Duration> = messages
        .iter()
        .filter(|m| m.has("WATCHDOG=1"))
        .map(|m| m.at - start)
        .collect();
    let ms: Vec<u128> = pings.iter().map(Duration::as_millis).collect();
    eprintln!(
        "pings at ms {ms:?} after READY; step {STEP:?}, bound {STEP_LIMIT:?}, Alive every {ALIVE_EVERY:?}"
    );
    // Both times are arrival times of datagrams: READY may arrive a little after the step began
    // (scheduling on a loaded machine), so the step is measured with 50 ms of slack.
    assert!(
        done - start + Duration::from_millis(50) >= STEP,
        "the step ran {:?}",
        done - start
    );
    // Within the bound: a ping at READY, then one per Alive event, ALIVE_EVERY apart (here W/4 <
    // ALIVE_EVERY, so the pacer passes every one; with the unit's W = 30 s, ALIVE_EVERY ≤ W/4 keeps
    // the gaps under W/2).
    let within: Vec<Duration> = pings.iter().copied().filter(|p| *p <= STEP_LIMIT).collect();
    assert!(
        within.len() >= (STEP_LIMIT.as_millis() / ALIVE_EVERY.as_millis()) as usize,
        "pings within the bound: {ms:?}"
    );
    let mut previous = Duration::ZERO;
    for p in &within {
        assert!(
            *p - previous <= ALIVE_EVERY + Duration::from_millis(150),
            "gap {:?} before the ping at {p:?} (pings {ms:?})",
            *p - previous
        );
        previous = *p;
    }
    // Past the bound: silence until the step ends.
    assert!(
        pings
            .iter()
            .all(|p| *p <= STEP_LIMIT + Duration::from_millis(150)),
        "a ping after the step's bound: {ms:?}"
    );
    assert!(
        STEP - STEP_LIMIT > watchdog,
        "the silence after the bound is longer than the watchdog interval, so systemd would act"
    );
}

/// Every file under `dir` with its bytes (sorted by path).
fn tree(dir: &std::path::Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let bytes = std::fs::read(&p).unwrap();
                out.push((p, bytes));
            }
        }
    }
    out.sort();
    out
}

/// The real `cubecal serve` (synthetic camera in front of the GRBL simulator on a pty), stopped by
/// SIGTERM mid-run as systemd stops a unit: READY=1 came first, watchdog pings came from the run,
/// STOPPING=1 comes at once, the process exits with 130 within 5 s, the session is closed and marked
/// incomplete, no profile is written and the profile store — holding a previous, passing profile of
/// the same camera from a real run — is left byte-identical.
#[test]
fn sigterm_mid_run_stops_within_5_s_without_touching_profiles() {
    let listener = Listener::new();
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let store = dir.path().join("store");
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/station.toml");
    let quoted = |p: &std::path::Path| format!("\"{}\"", p.display());
    // A previous, passing profile of this camera in the store, made by a real (short) run of the
    // service itself: its last status starts with the verdict (what `systemctl status` shows after
    // the run), the spool's depth after it.
    let first_listener = Listener::new();
    let first = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["serve", "--device", "/dev/null", "--config", config])
        .args(["--set", "camera.source=\"synthetic\""])
        .args(["--set", "camera.device_id=\"demo-camera\""])
        .args(["--set", "plan.poses=6", "--set", "qa.min_views=4"])
        .arg("--set")
        .arg(format!("output.out={}", quoted(&dir.path().join("first"))))
        .arg("--set")
        .arg(format!("output.store={}", quoted(&store)))
        .env("NOTIFY_SOCKET", &first_listener.path)
        .env_remove("WATCHDOG_USEC")
        .output()
        .unwrap();
    assert!(
        first.status.success(),
        "the first run passes: {}",
        String::from_utf8_lossy(&first.stdout)
    );
    let statuses: Vec<String> = first_listener
        .drain(Duration::from_millis(300))
        .iter()
        .filter_map(|m| m.status().map(str::to_string))
        .collect();
    let last = statuses
        .iter()
        .rfind(|s| !s.starts_with("stopping"))
        .expect("statuses from the first run");
    assert!(
        last.starts_with("verdict PASS: ") && last.contains(" | spool: 0 profile(s) waiting for "),
        "the last status names the verdict, then the spool: {last:?}"
    );
    let before = tree(&store);
    assert!(
        before.iter().any(
            |(p, _)| p.ends_with("current.json") && p.to_string_lossy().contains("demo-camera")
        ),
        "the store holds demo-camera's current profile: {:?}",
        before.iter().map(|(p, _)| p).collect::<Vec<_>>()
    );
    let mut child = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["serve", "--device", "/dev/null", "--config", config])
        .args(["--set", "camera.source=\"synthetic\""])
        .args(["--set", "camera.device_id=\"demo-camera\""])
        .arg("--set")
        .arg(format!("output.out={}", quoted(&run_dir)))
        .arg("--set")
        .arg(format!("output.store={}", quoted(&store)))
        .env("NOTIFY_SOCKET", &listener.path)
        .env("WATCHDOG_USEC", "2000000")
        .env_remove("WATCHDOG_PID")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();

    // Wait for the third pose to be under way (READY=1 long before), then SIGTERM.
    let mut seen = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let m = listener
            .rx
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            .expect("serve reached pose 3 within 120 s");
        let third = m.status().is_some_and(|s| s.starts_with("pose 3/"));
        seen.push(m);
        if third {
            break;
        }
    }
    let term_at = Instant::now();
    let kill = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(
            term_at.elapsed() < Duration::from_secs(10),
            "serve still running 10 s after SIGTERM"
        );
        thread::sleep(Duration::from_millis(20));
    };
    let exit_after = term_at.elapsed();
    let out = child.wait_with_output().unwrap();
    let after: Vec<Message> = listener.drain(Duration::from_millis(300));
    let stopping = after
        .iter()
        .find(|m| m.has("STOPPING=1"))
        .expect("STOPPING=1 after SIGTERM");
    eprintln!(
        "STOPPING=1 {:?} after SIGTERM, exit {:?} after SIGTERM with {status}",
        stopping.at - term_at,
        exit_after
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        status.code(),
        Some(130),
        "exit code 130 (interrupted); stderr: {stderr}"
    );
    assert!(
        exit_after <= Duration::from_secs(5),
        "exited {exit_after:?} after SIGTERM"
    );
    assert!(stopping.at - term_at < Duration::from_secs(1));
    let ready = seen.iter().position(|m| m.has("READY=1")).expect("READY=1");
    let first_pose = seen
        .iter()
        .position(|m| m.status().is_some_and(|s| s.starts_with("pose ")))
        .unwrap();
    assert!(ready < first_pose, "READY=1 before the first pose");
    assert!(
        seen.iter().any(|m| m.has("WATCHDOG=1")),
        "watchdog pings during the run"
    );
    // No profile, the session closed and marked incomplete, the store untouched.
    assert!(!run_dir.join("profile.json").exists());
    let manifest: serde_json::Value = serde_json::from_slice(
        &std::fs::read(run_dir.join("session").join("manifest.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["complete"], serde_json::json!(false));
    assert!(
        manifest["ended_by"]
            .as_str()
            .is_some_and(|s| s.contains("interrupted")),
        "{}",
        manifest["config"]
    );
    assert_eq!(tree(&store), before, "the profile store changed");
}
