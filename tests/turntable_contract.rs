//! The turntable contract: the same test functions run against every implementation — the in-memory
//! fake, the GRBL driver talking to the GRBL simulator over a pseudo-terminal (with and without homing
//! switches), and the Zaber driver talking to the Zaber simulator. Then every injected simulator fault
//! must end in the right typed error within a stated bound.
//!
//! Real hardware: `CUBECAL_TURNTABLE_PORT=/dev/ttyUSB0 CUBECAL_TURNTABLE_PROTOCOL=grbl|zaber
//! cargo test --test turntable_contract -- --ignored` runs the contract against a real stage (with the
//! hardware defaults: GRBL axis X at 1 °/unit, homing off; Zaber device 1 axis 1, X-RSW60A microsteps).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
// The fault tests print their measured time-to-error (see them with `-- --nocapture`).
#![allow(clippy::print_stderr)]

use std::time::{Duration, Instant};

use cubecal::turntable::fake::FakeTurntable;
use cubecal::turntable::grbl::{Axis, GrblConfig, GrblTurntable};
use cubecal::turntable::sim::{self, Fault, GrblSim, SimConfig, SimHandle, ZaberSim};
use cubecal::turntable::zaber::{
    Flag, Rejection, X_RSW60A_MICROSTEPS_PER_DEGREE, ZaberConfig, ZaberTurntable,
};
use cubecal::turntable::{Degrees, Turntable, TurntableError};

/// Reply timeout per exchange in the fault tests (short, so the faults fail fast).
const EXCHANGE: Duration = Duration::from_millis(100);
/// Reply timeout per exchange in the healthy contract tests: generous, because a loaded machine can
/// delay the simulator thread by a few hundred milliseconds; it costs nothing when replies come.
const HEALTHY_EXCHANGE: Duration = Duration::from_secs(1);
/// Re-sends per exchange in these tests.
const RETRIES: u32 = 2;
/// Overall limit per move in these tests.
const MOVE_LIMIT: Duration = Duration::from_secs(2);
/// Slack for thread scheduling: the suite must pass while other builds load the 2-core machine.
/// Unloaded, the overshoot past the theoretical bound is a few milliseconds (run with `--nocapture`
/// to see the measured times); with three CPU hogs on two cores it reached 1.4 s once in ten runs.
const SLACK: Duration = Duration::from_millis(1000);
/// The bound for a fault that silences or garbles a retried exchange: every attempt, plus slack.
const EXCHANGE_BOUND: Duration = Duration::from_millis(100 * (RETRIES as u64 + 1) + 1000);

/// GRBL in these tests: 2 units per degree (0.5 °/unit), so the resolution is 0.001 × 0.5 = 0.0005°.
const GRBL_DEG_PER_UNIT: f64 = 0.5;

/// A turntable under test plus whatever keeps it alive (the simulator thread).
struct Rig {
    table: Box<dyn Turntable>,
    _sim: Option<SimHandle>,
}

fn grbl_config(homing: bool) -> GrblConfig {
    GrblConfig {
        homing,
        exchange_timeout: HEALTHY_EXCHANGE,
        status_retries: RETRIES,
        poll_interval: Duration::from_millis(3),
        move_timeout: MOVE_LIMIT,
        home_timeout: MOVE_LIMIT,
        ..GrblConfig::new(Axis::A, GRBL_DEG_PER_UNIT)
    }
}

/// The healthy config, with the short fault-test exchange timeout when a fault is injected.
fn grbl_fault_config(homing: bool, fault: Option<Fault>) -> GrblConfig {
    GrblConfig {
        exchange_timeout: if fault.is_some() {
            EXCHANGE
        } else {
            HEALTHY_EXCHANGE
        },
        ..grbl_config(homing)
    }
}

fn zaber_fault_config(fault: Option<Fault>) -> ZaberConfig {
    ZaberConfig {
        exchange_timeout: if fault.is_some() {
            EXCHANGE
        } else {
            HEALTHY_EXCHANGE
        },
        ..zaber_config()
    }
}

fn zaber_config() -> ZaberConfig {
    ZaberConfig {
        exchange_timeout: HEALTHY_EXCHANGE,
        retries: RETRIES,
        poll_interval: Duration::from_millis(3),
        move_timeout: MOVE_LIMIT,
        home_timeout: MOVE_LIMIT,
        ..ZaberConfig::new(X_RSW60A_MICROSTEPS_PER_DEGREE)
    }
}

/// Fast motion: GRBL units (2/°) — 30° poses take ~50 ms.
fn grbl_sim_config(fault: Option<Fault>) -> SimConfig {
    SimConfig {
        speed: 20_000.0,
        accel: 100_000.0,
        fault,
    }
}

/// Fast motion: Zaber microsteps (4267/°) — 30° poses take ~70 ms.
fn zaber_sim_config(fault: Option<Fault>) -> SimConfig {
    SimConfig {
        speed: 1.0e7,
        accel: 1.0e8,
        fault,
    }
}

fn fake() -> Rig {
    Rig {
        table: Box::new(FakeTurntable::new()),
        _sim: None,
    }
}

fn grbl_with(homing: bool, fault: Option<Fault>) -> Rig {
    let (port, sim) = sim::grbl_pair(
        grbl_sim_config(fault),
        GrblSim {
            axis: Axis::A,
            homing,
        },
    )
    .unwrap();
    Rig {
        table: Box::new(GrblTurntable::new(port, grbl_fault_config(homing, fault)).unwrap()),
        _sim: Some(sim),
    }
}

fn grbl_homing() -> Rig {
    grbl_with(true, None)
}

fn grbl_no_homing() -> Rig {
    grbl_with(false, None)
}

fn zaber_with(fault: Option<Fault>) -> Rig {
    let (port, sim) = sim::zaber_pair(
        zaber_sim_config(fault),
        ZaberSim {
            device: 1,
            limit_microsteps: 10_000_000,
        },
    )
    .unwrap();
    Rig {
        table: Box::new(ZaberTurntable::new(port, zaber_fault_config(fault)).unwrap()),
        _sim: Some(sim),
    }
}

fn zaber() -> Rig {
    zaber_with(None)
}

/// A real stage, when the environment says one is attached.
fn hardware() -> Rig {
    let port = std::env::var("CUBECAL_TURNTABLE_PORT")
        .expect("set CUBECAL_TURNTABLE_PORT (and CUBECAL_TURNTABLE_PROTOCOL) to test hardware");
    let link = cubecal::turntable::serial::open_port(&port, 115_200).unwrap();
    let table: Box<dyn Turntable> = match std::env::var("CUBECAL_TURNTABLE_PROTOCOL").as_deref() {
        Ok("zaber") => Box::new(
            ZaberTurntable::new(link, ZaberConfig::new(X_RSW60A_MICROSTEPS_PER_DEGREE)).unwrap(),
        ),
        _ => Box::new(GrblTurntable::new(link, GrblConfig::new(Axis::X, 1.0)).unwrap()),
    };
    Rig { table, _sim: None }
}

// ------------------------------------------------------------------------------------------------
// The contract

/// Read-back tolerance: one resolution step, plus float noise.
fn tol(t: &dyn Turntable) -> Degrees {
    Degrees(t.resolution().0 * 1.000_001 + 1e-12)
}

fn homes_to_zero(rig: Rig) {
    let mut t = rig.table;
    assert!(t.resolution().0 > 0.0);
    let p = t.home().unwrap();
    assert!(p.within(Degrees(0.0), tol(&*t)), "home settled at {p}");
    t.move_to(Degrees(45.0)).unwrap();
    let p = t.home().unwrap();
    assert!(p.within(Degrees(0.0), tol(&*t)), "re-home settled at {p}");
    let p = t.position().unwrap();
    assert!(p.within(Degrees(0.0), tol(&*t)), "position after home {p}");
}

fn twelve_pose_sequence(rig: Rig) {
    let mut t = rig.table;
    t.home().unwrap();
    for i in 0..12 {
        let target = Degrees(30.0 * f64::from(i));
        let settled = t.move_to(target).unwrap();
        assert!(
            settled.within(target, tol(&*t)),
            "pose {i}: settled at {settled}, wanted {target} ± {}",
            t.resolution()
        );
    }
}

fn position_reads_back_within_resolution(rig: Rig) {
    let mut t = rig.table;
    t.home().unwrap();
    // Angles that are not multiples of the resolution: read-back must round, not drift.
    for target in [12.345_678, -7.25, 359.999_9, 0.000_1] {
        let settled = t.move_to(Degrees(target)).unwrap();
        let read = t.position().unwrap();
        assert!(read.within(Degrees(target), tol(&*t)), "{read} vs {target}");
        assert!(
            read.within(settled, tol(&*t)),
            "{read} vs settled {settled}"
        );
    }
}

fn rejects_invalid_angles(rig: Rig) {
    let mut t = rig.table;
    t.home().unwrap();
    for bad in [f64::NAN, f64::INFINITY, 1.0e6] {
        match t.move_to(Degrees(bad)) {
            Err(e @ TurntableError::InvalidAngle { .. }) => {
                assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
            }
            other => panic!("move_to({bad}) gave {other:?}"),
        }
    }
    // Still usable afterwards.
    t.move_to(Degrees(10.0)).unwrap();
}

fn stop_when_idle_keeps_it_usable(rig: Rig) {
    let mut t = rig.table;
    t.home().unwrap();
    t.move_to(Degrees(20.0)).unwrap();
    t.stop().unwrap();
    let p = t.position().unwrap();
    assert!(p.within(Degrees(20.0), tol(&*t)), "{p}");
    t.move_to(Degrees(40.0)).unwrap();
}

fn describes_itself(rig: Rig) {
    let mut t = rig.table;
    let d = t.describe().unwrap();
    assert!(!d.is_empty());
}

macro_rules! contract {
    ($($imp:ident),* $(,)?) => {$(
        mod $imp {
            #[test]
            fn homes_to_zero() { super::homes_to_zero(super::$imp()) }
            #[test]
            fn twelve_pose_sequence() { super::twelve_pose_sequence(super::$imp()) }
            #[test]
            fn position_reads_back_within_resolution() {
                super::position_reads_back_within_resolution(super::$imp())
            }
            #[test]
            fn rejects_invalid_angles() { super::rejects_invalid_angles(super::$imp()) }
            #[test]
            fn stop_when_idle_keeps_it_usable() { super::stop_when_idle_keeps_it_usable(super::$imp()) }
            #[test]
            fn describes_itself() { super::describes_itself(super::$imp()) }
        }
    )*};
}

contract!(fake, grbl_homing, grbl_no_homing, zaber);

mod hardware {
    #[test]
    #[ignore = "needs a real turntable: set CUBECAL_TURNTABLE_PORT and CUBECAL_TURNTABLE_PROTOCOL"]
    fn twelve_pose_sequence() {
        super::twelve_pose_sequence(super::hardware())
    }
    #[test]
    #[ignore = "needs a real turntable: set CUBECAL_TURNTABLE_PORT and CUBECAL_TURNTABLE_PROTOCOL"]
    fn position_reads_back_within_resolution() {
        super::position_reads_back_within_resolution(super::hardware())
    }
}

#[test]
fn resolutions_are_what_the_docs_say() {
    assert_eq!(FakeTurntable::new().resolution(), Degrees(0.001));
    assert!((grbl_config(false).resolution().0 - 0.0005).abs() < 1e-15);
    assert!((zaber_config().resolution().0 - 0.000_234_375).abs() < 1e-15);
}

// ------------------------------------------------------------------------------------------------
// Faults: each ends in a typed error, within a bound, and says what happened.

/// Home, then move to 90° with the fault armed; return the error and how long the move took.
fn fault_run(rig: Rig) -> (TurntableError, Duration) {
    let mut t = rig.table;
    t.home().unwrap();
    let start = Instant::now();
    let err = t
        .move_to(Degrees(90.0))
        .expect_err("the fault must surface as an error");
    (err, start.elapsed())
}

fn assert_within(elapsed: Duration, bound: Duration, err: &TurntableError) {
    assert!(
        elapsed < bound,
        "took {elapsed:?} (bound {bound:?}) to fail with: {err}"
    );
    eprintln!("{elapsed:>10.1?} < {bound:?}: {err}");
}

#[test]
fn grbl_no_reply_times_out() {
    let (err, elapsed) = fault_run(grbl_with(true, Some(Fault::NoReply)));
    // The G0 line is not re-sent (see the module docs): one exchange timeout.
    assert!(
        matches!(err, TurntableError::Timeout { attempts: 1, .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("G90 G53 G0 A180.000"), "{err}");
    assert_within(elapsed, EXCHANGE + SLACK, &err);
}

#[test]
fn grbl_garbage_is_an_unexpected_reply_with_escaped_bytes() {
    let (err, elapsed) = fault_run(grbl_with(true, Some(Fault::Garbage)));
    assert!(
        matches!(err, TurntableError::UnexpectedReply { .. }),
        "{err:?}"
    );
    assert!(
        err.to_string().contains(r"\xff\x00\x13#~garbage\x7f"),
        "{err}"
    );
    assert_within(elapsed, EXCHANGE + SLACK, &err);
}

#[test]
fn grbl_alarm_mid_move_names_the_alarm() {
    let (err, elapsed) = fault_run(grbl_with(true, Some(Fault::AlarmMidMove)));
    assert!(
        matches!(err, TurntableError::GrblAlarm { code: 1, .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("Hard limit triggered"), "{err}");
    assert_within(elapsed, MOVE_LIMIT + SLACK, &err);
}

#[test]
fn grbl_lost_steps_is_a_position_mismatch() {
    let (err, elapsed) = fault_run(grbl_with(true, Some(Fault::LostSteps { offset: 0.25 })));
    match err {
        TurntableError::PositionMismatch {
            commanded,
            reported,
            ..
        } => {
            assert_eq!(commanded, Degrees(90.0));
            assert!((reported.0 - 90.125).abs() < 1e-9, "{reported}");
        }
        ref other => panic!("{other:?}"),
    }
    assert_within(elapsed, MOVE_LIMIT + SLACK, &err);
}

#[test]
fn grbl_port_closed_is_a_disconnect() {
    let (err, elapsed) = fault_run(grbl_with(true, Some(Fault::PortClosed)));
    assert!(
        matches!(err, TurntableError::Disconnected { .. }),
        "{err:?}"
    );
    assert_within(elapsed, EXCHANGE + SLACK, &err);
}

#[test]
fn grbl_simulator_gone_is_an_error_not_a_hang() {
    // Stopping the simulator closes the pty master: the next status query must fail promptly.
    let (port, sim) = sim::grbl_pair(
        grbl_sim_config(None),
        GrblSim {
            axis: Axis::A,
            homing: true,
        },
    )
    .unwrap();
    let mut t = GrblTurntable::new(port, grbl_fault_config(true, Some(Fault::PortClosed))).unwrap();
    t.home().unwrap();
    drop(sim);
    let start = Instant::now();
    let err = t.position().expect_err("no simulator");
    assert!(
        matches!(
            err,
            TurntableError::Disconnected { .. } | TurntableError::Timeout { .. }
        ),
        "{err:?}"
    );
    assert_within(start.elapsed(), EXCHANGE_BOUND, &err);
}

#[test]
fn grbl_move_before_homing_is_locked_out_with_meaning() {
    let rig = grbl_homing();
    let mut t = rig.table;
    let err = t.move_to(Degrees(30.0)).expect_err("GRBL starts in Alarm");
    assert!(
        matches!(err, TurntableError::GrblError { code: 9, .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("G-code lock"), "{err}");
}

#[test]
fn zaber_no_reply_times_out_after_every_retry() {
    let (err, elapsed) = fault_run(zaber_with(Some(Fault::NoReply)));
    assert!(
        matches!(err, TurntableError::Timeout { attempts, .. } if attempts == RETRIES + 1),
        "{err:?}"
    );
    assert!(err.to_string().contains("/1 1 move abs 384000"), "{err}");
    assert_within(elapsed, EXCHANGE_BOUND, &err);
}

#[test]
fn zaber_garbage_is_an_unexpected_reply_with_escaped_bytes() {
    let (err, elapsed) = fault_run(zaber_with(Some(Fault::Garbage)));
    assert!(
        matches!(err, TurntableError::UnexpectedReply { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains(r"\xff\x00\x13"), "{err}");
    assert_within(elapsed, EXCHANGE_BOUND, &err);
}

#[test]
fn zaber_stall_mid_move_is_a_typed_fault() {
    let (err, elapsed) = fault_run(zaber_with(Some(Fault::AlarmMidMove)));
    assert!(
        matches!(
            err,
            TurntableError::ZaberFault {
                flag: Flag::StalledAndStopped,
                ..
            }
        ),
        "{err:?}"
    );
    assert!(
        err.to_string().contains("FS (stalled and stopped)"),
        "{err}"
    );
    assert_within(elapsed, MOVE_LIMIT + SLACK, &err);
}

#[test]
fn zaber_lost_steps_is_a_position_mismatch() {
    let (err, elapsed) = fault_run(zaber_with(Some(Fault::LostSteps { offset: -500.0 })));
    assert!(
        matches!(err, TurntableError::PositionMismatch { .. }),
        "{err:?}"
    );
    assert_within(elapsed, MOVE_LIMIT + SLACK, &err);
}

#[test]
fn zaber_port_closed_is_a_disconnect() {
    let (err, elapsed) = fault_run(zaber_with(Some(Fault::PortClosed)));
    assert!(
        matches!(err, TurntableError::Disconnected { .. }),
        "{err:?}"
    );
    assert_within(elapsed, EXCHANGE_BOUND, &err);
}

#[test]
fn zaber_out_of_range_is_a_typed_rejection() {
    let (port, _sim) = sim::zaber_pair(
        zaber_sim_config(None),
        ZaberSim {
            device: 1,
            limit_microsteps: 100_000, // ~23°
        },
    )
    .unwrap();
    let mut t = ZaberTurntable::new(port, zaber_config()).unwrap();
    t.home().unwrap();
    let err = t.move_to(Degrees(90.0)).expect_err("beyond travel");
    assert!(
        matches!(
            err,
            TurntableError::ZaberRejected {
                reason: Rejection::BadData,
                ..
            }
        ),
        "{err:?}"
    );
}

#[test]
fn zaber_wrong_device_address_times_out() {
    let (port, _sim) = sim::zaber_pair(
        zaber_sim_config(None),
        ZaberSim {
            device: 2,
            limit_microsteps: 10_000_000,
        },
    )
    .unwrap();
    // Nobody answers at address 1, which looks like a silent device: use the short fault timeout.
    let mut t = ZaberTurntable::new(port, zaber_fault_config(Some(Fault::NoReply))).unwrap();
    let start = Instant::now();
    let err = t.position().expect_err("nobody at address 1");
    assert!(matches!(err, TurntableError::Timeout { .. }), "{err:?}");
    assert_within(start.elapsed(), EXCHANGE_BOUND, &err);
}

#[test]
fn every_fault_error_maps_to_the_device_exit_code() {
    let (err, _) = fault_run(zaber_with(Some(Fault::NoReply)));
    assert_eq!(err.exit_code(), cubecal::exit::DEVICE);
}

/// A slow stage (a 90° move takes seconds) with a short move limit: the move must fail with
/// `MoveTimeout` within the limit, and `stop` must then halt the table where it is.
fn move_timeout_then_stop(mut t: Box<dyn Turntable>) {
    t.home().unwrap();
    let start = Instant::now();
    let err = t
        .move_to(Degrees(90.0))
        .expect_err("too slow for the limit");
    assert!(matches!(err, TurntableError::MoveTimeout { .. }), "{err:?}");
    assert_within(start.elapsed(), SHORT_MOVE_LIMIT + SLACK, &err);
    t.stop().unwrap();
    let p1 = t.position().unwrap();
    std::thread::sleep(Duration::from_millis(60));
    let p2 = t.position().unwrap();
    assert_eq!(p1, p2, "still moving after stop");
    assert!(p1.0 > 0.0 && p1.0 < 90.0, "{p1}");
    // Not locked out: feed hold before the reset means GRBL keeps its position (no ALARM:3).
    // A zero-length move, so it fits the short limit even on a loaded machine.
    let p3 = t.move_to(p1).unwrap();
    assert!(p3.within(p1, tol(&*t)), "{p3}");
}

const SHORT_MOVE_LIMIT: Duration = Duration::from_millis(200);

#[test]
fn grbl_move_timeout_then_stop() {
    let (port, _sim) = sim::grbl_pair(
        SimConfig {
            speed: 100.0, // units/s: 90° = 180 units ≈ 1.9 s
            accel: 1_000.0,
            fault: None,
        },
        GrblSim {
            axis: Axis::A,
            homing: false,
        },
    )
    .unwrap();
    let config = GrblConfig {
        move_timeout: SHORT_MOVE_LIMIT,
        ..grbl_config(false)
    };
    move_timeout_then_stop(Box::new(GrblTurntable::new(port, config).unwrap()));
}

#[test]
fn zaber_move_timeout_then_stop() {
    let (port, _sim) = sim::zaber_pair(
        SimConfig {
            speed: 200_000.0, // microsteps/s: 90° = 384 000 µsteps ≈ 2 s
            accel: 2_000_000.0,
            fault: None,
        },
        ZaberSim {
            device: 1,
            limit_microsteps: 10_000_000,
        },
    )
    .unwrap();
    let config = ZaberConfig {
        move_timeout: SHORT_MOVE_LIMIT,
        ..zaber_config()
    };
    move_timeout_then_stop(Box::new(ZaberTurntable::new(port, config).unwrap()));
}
