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
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

use cubecal::station::notify::SystemdNotifier;
use cubecal::station::{Check, Event, EventSink, Verdict};

/// The child's scenario is named in this variable; without it the `child` test refuses to run.
const SCENARIO: &str = "CUBECAL_NOTIFY_SCENARIO";

/// Watchdog interval of the pacing scenario (1 s: pings every 250–500 ms).
const WATCHDOG_USEC: u64 = 1_000_000;
/// How long the pacing scenario emits events, and how long it then stays silent.
const BUSY: Duration = Duration::from_millis(3000);
const QUIET: Duration = Duration::from_millis(1500);

/// One datagram as received: arrival time and its `KEY=value` lines.
#[derive(Debug)]
struct Message {
    at: Instant,
    lines: Vec<String>,
}

/// Run the `child` test of this binary with `scenario`, the notify socket and the watchdog variable;
/// return every datagram it sent and the child's run time.
fn run_child(scenario: &str, watchdog_usec: Option<u64>) -> (Vec<Message>, Duration) {
    let dir = tempfile::tempdir().unwrap();
    let socket_path = dir.path().join("notify");
    let socket = UnixDatagram::bind(&socket_path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_millis(50)))
        .unwrap();

    let (done_tx, done_rx) = mpsc::channel::<()>();
    let reader = thread::spawn(move || {
        let mut messages = Vec::new();
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            match socket.recv(&mut buf) {
                Ok(n) => {
                    let text = String::from_utf8(buf[..n].to_vec()).unwrap();
                    messages.push(Message {
                        at: Instant::now(),
                        lines: text.lines().map(str::to_string).collect(),
                    });
                }
                Err(e)
                    if e.kind() == std::io::ErrorKind::WouldBlock
                        || e.kind() == std::io::ErrorKind::TimedOut =>
                {
                    if done_rx.try_recv().is_ok() {
                        return messages;
                    }
                }
                Err(e) => panic!("recv on the notify socket: {e}"),
            }
        }
    });

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
    .env("NOTIFY_SOCKET", &socket_path)
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
    // The datagrams are queued in the socket before the child exits; let the reader drain them.
    thread::sleep(Duration::from_millis(200));
    done_tx.send(()).unwrap();
    let messages = reader.join().unwrap();
    (messages, elapsed)
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
        .filter(|m| m.lines.iter().any(|l| l == "WATCHDOG=1"))
        .map(|m| m.at)
        .collect();
    let quiet_at = messages
        .iter()
        .find(|m| m.lines.iter().any(|l| l == "STATUS=quiet"))
        .expect("the quiet marker")
        .at;
    let stopping_at = messages
        .iter()
        .find(|m| m.lines.iter().any(|l| l == "STOPPING=1"))
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
