//! The GRBL simulator seen by a camera (`sim::grbl_pair_seen`, what `cubecal turntable simulate
//! --feed` runs): the real GRBL driver over the pseudo-terminal waits for the picture of the final
//! position before it reports a move settled, and the view publishes where the stage is.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::time::{Duration, Instant};

use cubecal::turntable::grbl::{Axis, GrblConfig, GrblTurntable};
use cubecal::turntable::sim::{self, GrblSim, SimConfig, StageView};
use cubecal::turntable::{Degrees, Turntable};

/// Degrees per GRBL unit, as in the station config of tests/vm/service.sh.
const DEG_PER_UNIT: f64 = 0.5;

fn seen_table(view: &StageView) -> (GrblTurntable<serialport::TTYPort>, sim::SimHandle) {
    let (port, handle) = sim::grbl_pair_seen(
        SimConfig {
            speed: 2000.0,
            accel: 20000.0,
            fault: None,
        },
        GrblSim {
            axis: Axis::A,
            homing: false,
        },
        view.clone(),
    )
    .unwrap();
    let config = GrblConfig {
        exchange_timeout: Duration::from_millis(200),
        move_timeout: Duration::from_secs(10),
        ..GrblConfig::new(Axis::A, DEG_PER_UNIT)
    };
    (GrblTurntable::new(port, config).unwrap(), handle)
}

/// A stand-in for the feeder: once the stage rests somewhere not yet shown, "render" for `delay`
/// and show it. Returns when `until` passes.
fn fake_feeder(view: StageView, delay: Duration, until: Instant) -> Vec<f64> {
    let mut shown = Vec::new();
    while Instant::now() < until {
        let (p, moving) = view.position_and_motion();
        if !moving && view.shown() != Some(p) {
            std::thread::sleep(delay);
            view.set_shown(p);
            shown.push(p);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    shown
}

#[test]
fn a_move_settles_only_after_the_picture_of_its_target_is_shown() {
    let view = StageView::default();
    let (mut table, _sim) = seen_table(&view);
    let delay = Duration::from_millis(700);
    let feeder = {
        let view = view.clone();
        std::thread::spawn(move || {
            fake_feeder(view, delay, Instant::now() + Duration::from_secs(6))
        })
    };
    let home = table.home().unwrap();
    assert_eq!(home.0, 0.0);
    for target in [-20.0, 15.0] {
        let start = Instant::now();
        let settled = table.move_to(Degrees::checked(target).unwrap()).unwrap();
        let took = start.elapsed();
        // The motion itself takes ~20 ms; the rest is the wait for the picture.
        assert!(
            took >= delay,
            "settled at {settled} after {took:?}, before the picture ({delay:?})"
        );
        assert!((settled.0 - target).abs() < 1e-9, "settled at {settled}");
        assert_eq!(
            view.shown(),
            Some(target / DEG_PER_UNIT),
            "the picture shows the target (native units)"
        );
        assert_eq!(view.position_and_motion(), (target / DEG_PER_UNIT, false));
    }
    let shown = feeder.join().unwrap();
    // Home (0), then the two targets: one picture per resting position, none mid-move.
    assert_eq!(shown, vec![0.0, -40.0, 30.0]);
}

#[test]
fn without_a_picture_the_move_never_settles() {
    let view = StageView::default();
    let (port, _sim) = sim::grbl_pair_seen(
        SimConfig {
            speed: 2000.0,
            accel: 20000.0,
            fault: None,
        },
        GrblSim {
            axis: Axis::A,
            homing: false,
        },
        view.clone(),
    )
    .unwrap();
    let config = GrblConfig {
        exchange_timeout: Duration::from_millis(200),
        move_timeout: Duration::from_millis(1500),
        ..GrblConfig::new(Axis::A, DEG_PER_UNIT)
    };
    let mut table = GrblTurntable::new(port, config).unwrap();
    let err = table.move_to(Degrees::checked(10.0).unwrap()).unwrap_err();
    assert!(
        err.to_string().contains("move") || err.to_string().contains("settle"),
        "{err}"
    );
    assert_eq!(view.position_and_motion(), (20.0, false));
}
