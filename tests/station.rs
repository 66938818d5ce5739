//! The station end to end (`cubecal calibrate`, issue 16): accuracy against the synthetic camera's
//! ground truth through the real turntable protocols on a pseudo-terminal, photos, replay, the
//! verdict's failures and the faults. Library-level, except where the exit code is the point.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/scripted.rs"]
mod scripted;
use scripted::Scripted;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use cubecal::capture::synthetic::{AngleCell, TurntableScene};
use cubecal::capture::{CaptureError, Frame, FrameSource, SourceInfo};
use cubecal::render::default_view;
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, set_key};
use cubecal::station::hardware::{self, Hardware, Poses, plan_angles};
use cubecal::station::{Event, RunResult, RunSpec, StationError};
use cubecal::turntable::manual::Operator;
use cubecal::turntable::{Degrees, Turntable, TurntableError};

const CUBE: &str = include_str!("../fixtures/rigs/cube_outside.toml");

/// The station config of `keys`, on a one-axis turntable unless they say otherwise: this file is the
/// turntable-only station (the simulators' default tilt axis is `tests/station_plan.rs`'s).
fn config(keys: &[(&str, &str)]) -> StationConfig {
    let mut t = toml::Table::new();
    for (k, v) in [("turntable.tilt", "false")].iter().chain(keys) {
        set_key(&mut t, k, v).unwrap();
    }
    StationConfig::from_table(t, "test").unwrap()
}

fn rig() -> Rig {
    Rig::from_toml_str(CUBE, "cube_outside.toml").unwrap().0
}

/// Run the station on `hw`; returns the result (or error) and the run directory.
fn run_hw(
    cfg: &StationConfig,
    rig: &Rig,
    rig_toml: &str,
    hw: Hardware,
    stop: &AtomicBool,
    sink: &mut dyn cubecal::station::EventSink,
) -> (Result<RunResult, StationError>, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let spec = RunSpec {
        config: cfg,
        rig,
        rig_toml,
        rig_path: None,
        run_dir: &run_dir,
    };
    (cubecal::station::run(&spec, hw, sink, stop), dir)
}

fn run_cfg(
    cfg: &StationConfig,
    operator: Option<Box<dyn Operator>>,
) -> (RunResult, tempfile::TempDir) {
    let rig = rig();
    let hw = hardware::open(cfg, &rig, operator).unwrap();
    let (r, dir) = run_hw(
        cfg,
        &rig,
        CUBE,
        hw,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
    );
    (r.unwrap(), dir)
}

/// |estimate − truth| of fx, fy, cx, cy and each in units of its reported σ.
fn errors(r: &RunResult, truth: &cubecal::camera::Camera) -> [(f64, f64); 4] {
    let c = r.calibration.as_ref().expect("a calibration");
    let k = c.camera_matrix;
    let est = [k[0][0], k[1][1], k[0][2], k[1][2]];
    let tru = [truth.fx(), truth.fy(), truth.cx(), truth.cy()];
    let names = ["fx", "fy", "cx", "cy"];
    let mut out = [(0.0, 0.0); 4];
    for i in 0..4 {
        let e = (est[i] - tru[i]).abs();
        out[i] = (e, e / c.std_dev[names[i]]);
    }
    out
}

fn assert_accurate(r: &RunResult, cfg: &StationConfig, f_rel: f64, c_px: f64, what: &str) {
    assert!(r.verdict.pass, "{what}: verdict {:#?}", r.verdict);
    let truth = cfg.synthetic.camera();
    let e = errors(r, &truth);
    eprintln!(
        "{what}: fx {:.4} % ({:.1}σ), fy {:.4} % ({:.1}σ), cx {:.3} px ({:.1}σ), cy {:.3} px ({:.1}σ)",
        100.0 * e[0].0 / truth.fx(),
        e[0].1,
        100.0 * e[1].0 / truth.fy(),
        e[1].1,
        e[2].0,
        e[2].1,
        e[3].0,
        e[3].1
    );
    assert!(
        e[0].0 / truth.fx() <= f_rel && e[1].0 / truth.fy() <= f_rel,
        "{what}: {e:?}"
    );
    // The principal point: the bar (`c_px`) is 1.3–1.7 of the σ this geometry gives (a cube on
    // a turntable in front of a fixed camera: σ(cx) ≈ 0.12 px at 1920×1080), so a fixed bar would
    // fail by chance about one run in five; it is asserted where the reported σ makes it a 2.5σ
    // statement, and 3σ always (below).
    let c = r
        .calibration
        .as_ref()
        .map(|c| c.std_dev["cx"].max(c.std_dev["cy"]))
        .unwrap_or(0.0);
    let bar = c_px.max(2.5 * c);
    if bar > c_px {
        eprintln!("{what}: principal-point bar {c_px} px is below 2.5σ; asserting {bar:.3} px");
    }
    assert!(e[2].0 <= bar && e[3].0 <= bar, "{what}: {e:?}");
    for (i, (_, k)) in e.iter().enumerate() {
        assert!(*k <= 3.0, "{what}: parameter {i} is {k:.1} σ off");
    }
}

const REALISTIC: &[(&str, &str)] = &[
    ("synthetic.width", "1920"),
    ("synthetic.height", "1080"),
    ("synthetic.fx", "1400.0"),
    ("synthetic.fy", "1400.0"),
    ("synthetic.cx", "962.3"),
    ("synthetic.cy", "537.8"),
    ("synthetic.k1", "-0.2"),
    ("synthetic.k2", "0.05"),
    ("synthetic.blur", "1.0"),
    ("synthetic.noise", "2.0"),
    ("synthetic.gamma", "2.2"),
    ("synthetic.vignetting", "0.3"),
    // 2×2 sub-samples locate an edge to 1/8 px (vertical) and 1/4 px (horizontal): on a level
    // turntable the vertical edges' error is coherent and moved this run's cx by 0.36 px (3.4σ);
    // 0.12 px (1.9σ) at 4×4.
    ("synthetic.supersample", "4"),
];

fn with(
    base: &[(&'static str, &'static str)],
    more: &[(&'static str, &'static str)],
) -> StationConfig {
    let mut v: Vec<(&str, &str)> = base.to_vec();
    v.extend_from_slice(more);
    config(&v)
}

#[test]
fn grbl_simulator_realistic_camera_is_recovered() {
    let cfg = with(REALISTIC, &[("turntable.kind", "\"sim-grbl\"")]);
    let (r, _d) = run_cfg(&cfg, None);
    assert_accurate(&r, &cfg, 2e-4, 0.2, "realistic, GRBL simulator");
    assert!(r.profile.is_some());
}

#[test]
fn grbl_simulator_hard_camera_is_recovered() {
    let cfg = config(&[
        ("synthetic.width", "1920"),
        ("synthetic.height", "1080"),
        ("synthetic.fx", "700.0"),
        ("synthetic.fy", "700.0"),
        ("synthetic.k1", "-0.3"),
        ("synthetic.k2", "0.08"),
        ("synthetic.blur", "1.5"),
        ("synthetic.noise", "5.0"),
        ("synthetic.black", "0.3"),
        ("synthetic.white", "0.55"),
        ("synthetic.supersample", "2"),
        ("turntable.kind", "\"sim-grbl\""),
    ]);
    let (r, _d) = run_cfg(&cfg, None);
    assert_accurate(&r, &cfg, 5e-4, 0.5, "hard, GRBL simulator");
}

#[test]
fn zaber_simulator_realistic_camera_is_recovered() {
    let cfg = with(REALISTIC, &[("turntable.kind", "\"sim-zaber\"")]);
    let (r, _d) = run_cfg(&cfg, None);
    assert_accurate(&r, &cfg, 2e-4, 0.2, "realistic, Zaber simulator");
}

#[test]
fn manual_turntable_with_a_scripted_operator() {
    let cfg = with(REALISTIC, &[("turntable.kind", "\"manual\"")]);
    let op = Scripted::default();
    let (r, _d) = run_cfg(&cfg, Some(Box::new(op.clone())));
    assert_accurate(&r, &cfg, 2e-4, 0.2, "realistic, manual turntable");
    let prompts = op.0.lock().unwrap();
    assert_eq!(prompts.len(), 13, "home + 12 poses: {prompts:?}");
    assert!(prompts[1].contains("turn the turntable"), "{}", prompts[1]);
}

const SMALL: &[(&str, &str)] = &[
    ("synthetic.width", "640"),
    ("synthetic.height", "480"),
    ("synthetic.fx", "560.0"),
    ("synthetic.fy", "560.0"),
    ("synthetic.supersample", "2"),
];

#[test]
fn replay_reproduces_the_calibration_bit_for_bit() {
    let cfg = config(SMALL);
    let (first, dir) = run_cfg(&cfg, None);
    assert!(first.verdict.pass);
    let session = dir.path().join("run/session");
    let quoted = format!("{:?}", session.display().to_string());
    let mut keys: Vec<(&str, &str)> = SMALL.to_vec();
    keys.extend([
        ("camera.source", "\"replay\""),
        ("camera.replay", quoted.as_str()),
        ("turntable.kind", "\"none\""),
    ]);
    let replay = config(&keys);
    let (second, _d2) = run_cfg(&replay, None);
    let a = serde_json::to_string(&first.calibration).unwrap();
    let b = serde_json::to_string(&second.calibration).unwrap();
    assert_eq!(a, b, "replayed calibration differs");
    assert_eq!(
        serde_json::to_string(&first.verdict).unwrap(),
        serde_json::to_string(&second.verdict).unwrap()
    );
    // The files the run wrote describe the same data.
    let obs = std::fs::read_to_string(dir.path().join("run/observations.json")).unwrap();
    assert!(obs.contains("\"held_out\": true") && obs.contains("\"face\": \"top\""));
}

fn hint_of<'a>(r: &'a RunResult, check: &str) -> &'a str {
    let c = r
        .verdict
        .checks
        .iter()
        .find(|c| c.name.starts_with(check))
        .unwrap_or_else(|| panic!("no check {check}: {:#?}", r.verdict));
    assert!(!c.pass, "{check} passed: {c:?}");
    c.hint.as_deref().unwrap_or("")
}

#[test]
fn verdict_fails_on_poor_coverage_and_says_where_to_put_the_rig() {
    let cfg = with(SMALL, &[("qa.min_coverage", "0.6")]);
    let (r, dir) = run_cfg(&cfg, None);
    assert!(!r.verdict.pass);
    assert_eq!(r.exit_code(), cubecal::exit::QA_REJECTED);
    let hint = hint_of(&r, "coverage");
    assert!(
        hint.contains("corners cover") && hint.contains("near the image corners"),
        "{hint}"
    );
    // a turntable alone: the hint names the tilted placements it lacks
    assert!(
        hint.contains("without a tilt axis") && hint.contains("its top tilted"),
        "{hint}"
    );
    assert!(r.profile.is_none() && !dir.path().join("run/profile.json").exists());
    assert!(dir.path().join("run/result.json").exists());
}

#[test]
fn verdict_fails_with_too_few_poses() {
    let cfg = with(SMALL, &[("plan.poses", "4")]);
    let (r, _dir) = run_cfg(&cfg, None);
    let hint = hint_of(&r, "views");
    assert!(hint.contains("usable view"), "{hint}");
}

#[test]
fn verdict_fails_for_a_blurred_camera() {
    let cfg = with(SMALL, &[("synthetic.blur", "4.5"), ("plan.poses", "8")]);
    let (r, _dir) = run_cfg(&cfg, None);
    assert!(!r.verdict.pass);
    let blurred = r
        .views
        .iter()
        .filter(|v| v.reason.as_deref().unwrap_or("").contains("blurred"))
        .count();
    assert!(blurred >= 6, "{:#?}", r.views);
    assert!(hint_of(&r, "views").contains("blurred"));
}

#[test]
fn verdict_fails_when_the_rig_file_does_not_match_the_printed_rig() {
    // Render the real cube, detect with a rig file whose grids are one column wider.
    let cfg = with(SMALL, &[("plan.poses", "6")]);
    let printed = rig();
    let wrong_toml = CUBE
        .replace("cols = 9", "cols = 10")
        .replace("cols = 8", "cols = 11")
        .replace("cols = 7", "cols = 12");
    let wrong = Rig::from_toml_str(&wrong_toml, "wrong.toml").unwrap().0;
    let hw = hardware::open(&cfg, &printed, None).unwrap();
    let (r, _d) = run_hw(
        &cfg,
        &wrong,
        &wrong_toml,
        hw,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
    );
    let r = r.unwrap();
    assert!(!r.verdict.pass);
    assert!(r.views.iter().all(|v| !v.accepted));
    let hint = hint_of(&r, "views");
    assert!(hint.contains("rig file matches the printed rig"), "{hint}");
}

/// The fit RMS (px) the station stays under on the `SMALL` camera (measured: 0.025–0.027 px over
/// noise seeds 1–8, with and without the detector's full-resolution second look). It bounds the
/// held-out check's limit, `qa.max_held_out_ratio` × fit RMS + `qa.held_out_floor_px`, from above.
const SMALL_FIT_RMS_CEILING_PX: f64 = 0.035;

/// The held-out RMS (px) a change of the focal length by the factor `scale` gives on the pose
/// `cam_from_rig`, noise-free: the visible corners of the faces seen within 75° of frontal (those the
/// detector labels) projected through the changed camera and posed through the unchanged one, as
/// the held-out check does with an exact detector.
fn held_out_rms_of_focus_change(
    rig: &Rig,
    camera: &cubecal::camera::Camera,
    cam_from_rig: &cubecal::camera::Pose,
    scale: f64,
) -> f64 {
    use cubecal::camera::idx;
    let mut changed = camera.clone();
    changed.params[idx::FX] *= scale;
    changed.params[idx::FY] *= scale;
    let settings = cubecal::render::RenderSettings::default();
    let truth = cubecal::render::ground_truth(rig, &changed, cam_from_rig, &settings, 0);
    let eye = cam_from_rig.centre();
    let points = truth
        .visible()
        .filter(|c| {
            let face = &rig.faces[c.face_index];
            let mid = (face.corner_xyz(0, 0) + face.corner_xyz(face.rows - 1, face.cols - 1)) / 2.0;
            face.normal().angle(&(eye - mid)).to_degrees() < 75.0
        })
        .map(|c| cubecal::calib::Correspondence {
            xyz: c.xyz.into(),
            uv: c.uv.unwrap().into(),
            cov: None,
        })
        .collect();
    let view = cubecal::calib::View {
        name: "held out".into(),
        points,
    };
    cubecal::calib::pose::solve_pose(camera, &view)
        .unwrap()
        .rms_px
}

/// A focus change the held-out check must catch, sized from the check's own limit: the smallest
/// change (in steps of 0.25 %) whose noise-free held-out RMS is 1.25× the largest limit the fit's RMS
/// allows
/// ([`SMALL_FIT_RMS_CEILING_PX`], asserted). A change sized at the limit itself (1.5 %: noise-free
/// 0.070 px against limits of 0.070–0.074 px) is caught or not by the corner noise of the run.
#[test]
fn verdict_fails_when_the_focus_changed_before_the_held_out_pose() {
    let cfg = config(SMALL);
    let rig = rig();
    let camera = cfg.synthetic.camera();
    let base = default_view(&rig, &camera);
    let angles = plan_angles(12, 60.0);
    let held_pose = cubecal::render::turned(&rig, &base, angles[11]);
    let most = cfg.qa.max_held_out_ratio * SMALL_FIT_RMS_CEILING_PX + cfg.qa.held_out_floor_px;
    let (scale, expected) = (1..=40)
        .map(|k| 1.0 + 0.0025 * f64::from(k))
        .map(|s| {
            (
                s,
                held_out_rms_of_focus_change(&rig, &camera, &held_pose, s),
            )
        })
        .find(|(_, rms)| *rms >= 1.25 * most)
        .unwrap();
    eprintln!(
        "focus change {:.2} %: noise-free held-out RMS {expected:.4} px, limit at most {most:.4} px",
        100.0 * (scale - 1.0)
    );
    let mut refocused = camera.clone();
    refocused.params[cubecal::camera::idx::FX] *= scale;
    refocused.params[cubecal::camera::idx::FY] *= scale;
    let angle = AngleCell::default();
    let scene = TurntableScene::new(
        rig.clone(),
        camera.clone(),
        base,
        cfg.synthetic.settings(),
        angle.clone(),
    )
    .unwrap()
    .with_camera_change(22, refocused) // frames 22, 23: the 12th (held-out) pose
    .unwrap();
    let (turntable, sim, name) = hardware::open_turntable(&cfg, None).unwrap();
    let hw = Hardware {
        source: Box::new(scene),
        turntable,
        turntable_name: name,
        poses: Poses::Angles(angles),
        angle: Some(angle),
        tilt: None,
        simulator: sim,
        device: None,
        capture: None,
        controls: vec![],
        identity: Some("focus-test".into()),
        replayed: None,
    };
    let (r, _d) = run_hw(
        &cfg,
        &rig,
        CUBE,
        hw,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
    );
    let r = r.unwrap();
    let fit_rms = r.calibration.as_ref().unwrap().rms_px;
    eprintln!(
        "fit RMS {fit_rms:.4} px, held-out {:?}",
        r.held_out.first().map(|h| h.rms_px)
    );
    assert!(fit_rms <= SMALL_FIT_RMS_CEILING_PX, "{fit_rms}");
    let hint = hint_of(&r, "held_out_rms_px");
    assert!(hint.contains("camera changed during the run"), "{hint}");
    assert!(r.profile.is_none());
}

/// A frame source that fails after `ok` frames.
struct Failing {
    inner: Box<dyn FrameSource>,
    ok: usize,
    error: fn() -> CaptureError,
}

impl FrameSource for Failing {
    fn describe(&self) -> SourceInfo {
        self.inner.describe()
    }
    fn grab(&mut self, timeout: Duration) -> Result<Frame, CaptureError> {
        if self.ok == 0 {
            return Err((self.error)());
        }
        self.ok -= 1;
        self.inner.grab(timeout)
    }
    fn flush(&mut self) -> Result<usize, CaptureError> {
        self.inner.flush()
    }
}

/// A turntable that records whether it was stopped.
struct Spy {
    inner: Box<dyn Turntable>,
    stopped: Arc<AtomicBool>,
}

impl Turntable for Spy {
    fn describe(&mut self) -> Result<String, TurntableError> {
        self.inner.describe()
    }
    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.inner.home()
    }
    fn move_to(&mut self, t: Degrees) -> Result<Degrees, TurntableError> {
        self.inner.move_to(t)
    }
    fn position(&mut self) -> Result<Degrees, TurntableError> {
        self.inner.position()
    }
    fn stop(&mut self) -> Result<(), TurntableError> {
        self.stopped.store(true, Ordering::SeqCst);
        self.inner.stop()
    }
    fn resolution(&self) -> Degrees {
        self.inner.resolution()
    }
}

/// Check a run that ended by a fault: typed error with its exit code, turntable stopped, session
/// closed and marked incomplete, no profile, within `bound`.
fn assert_fault(
    hw: Hardware,
    cfg: &StationConfig,
    stop: &AtomicBool,
    sink: &mut dyn cubecal::station::EventSink,
    code: u8,
    bound: Duration,
) -> StationError {
    let stopped = Arc::new(AtomicBool::new(false));
    let hw = Hardware {
        turntable: Box::new(Spy {
            inner: hw.turntable,
            stopped: stopped.clone(),
        }),
        ..hw
    };
    let t = Instant::now();
    let (r, dir) = run_hw(cfg, &rig(), CUBE, hw, stop, sink);
    let took = t.elapsed();
    let e = r.expect_err("the run must fail");
    assert_eq!(e.exit_code(), code, "{e}");
    assert!(took <= bound, "took {took:?} (bound {bound:?}) for {e}");
    assert!(
        stopped.load(Ordering::SeqCst),
        "turntable not stopped after {e}"
    );
    let run = dir.path().join("run");
    assert!(!run.join("profile.json").exists());
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("session/manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["complete"], serde_json::json!(false));
    assert!(manifest["ended_by"].as_str().unwrap().len() > 5);
    e
}

fn small_hw(cfg: &StationConfig) -> Hardware {
    hardware::open(cfg, &rig(), None).unwrap()
}

#[test]
fn camera_unplugged_mid_run_ends_with_a_device_error() {
    let cfg = config(SMALL);
    let hw = small_hw(&cfg);
    let hw = Hardware {
        source: Box::new(Failing {
            inner: hw.source,
            ok: 7,
            error: || CaptureError::Unplugged {
                device: "/dev/video0".into(),
                context: "dequeuing a buffer".into(),
                source: std::io::Error::from_raw_os_error(19),
            },
        }),
        ..hw
    };
    let e = assert_fault(
        hw,
        &cfg,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
        4,
        Duration::from_secs(30),
    );
    assert!(e.to_string().contains("disconnected"), "{e}");
}

#[test]
fn camera_stalled_mid_run_ends_with_a_device_error() {
    let cfg = config(SMALL);
    let hw = small_hw(&cfg);
    let hw = Hardware {
        source: Box::new(Failing {
            inner: hw.source,
            ok: 4,
            error: || CaptureError::Timeout {
                source_name: "/dev/video0".into(),
                timeout: Duration::from_millis(3000),
            },
        }),
        ..hw
    };
    assert_fault(
        hw,
        &cfg,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
        4,
        Duration::from_secs(30),
    );
}

fn grbl_with_fault(
    fault: cubecal::turntable::sim::Fault,
) -> (Box<dyn Turntable>, cubecal::turntable::sim::SimHandle) {
    use cubecal::turntable::grbl::{Axis, GrblConfig, GrblTurntable};
    use cubecal::turntable::sim::{self, GrblSim, SimConfig};
    let (port, handle) = sim::grbl_pair(
        SimConfig {
            speed: 2000.0,
            accel: 20000.0,
            fault: Some(fault),
        },
        GrblSim {
            axis: Axis::A,
            homing: false,
        },
    )
    .unwrap();
    let config = GrblConfig {
        exchange_timeout: Duration::from_millis(200),
        move_timeout: Duration::from_secs(3),
        ..GrblConfig::new(Axis::A, 0.5)
    };
    (Box::new(GrblTurntable::new(port, config).unwrap()), handle)
}

#[test]
fn turntable_faults_mid_run_end_with_a_device_error() {
    use cubecal::turntable::sim::Fault;
    let cfg = config(SMALL);
    for fault in [Fault::AlarmMidMove, Fault::NoReply, Fault::Garbage] {
        let hw = small_hw(&cfg);
        let (turntable, handle) = grbl_with_fault(fault);
        let hw = Hardware {
            turntable,
            simulator: vec![handle],
            ..hw
        };
        let e = assert_fault(
            hw,
            &cfg,
            &AtomicBool::new(false),
            &mut cubecal::station::event::NullSink,
            4,
            Duration::from_secs(10),
        );
        eprintln!("{fault:?}: {e}");
    }
}

#[test]
fn stop_flag_mid_run_closes_the_session_incomplete() {
    let cfg = config(SMALL);
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let mut sink = move |e: &Event| {
        if let Event::ViewAccepted { index: 3, .. } = e {
            flag.store(true, Ordering::SeqCst);
        }
    };
    let e = assert_fault(
        small_hw(&cfg),
        &cfg,
        &stop,
        &mut sink,
        cubecal::exit::INTERRUPTED,
        Duration::from_secs(30),
    );
    assert!(
        matches!(e, StationError::Interrupted { pose: 4, .. }),
        "{e}"
    );
}

#[test]
fn a_run_directory_on_a_full_disk_is_a_typed_error() {
    // /dev/full accepts opens and fails every write with ENOSPC.
    if !Path::new("/dev/full").exists() {
        panic!("/dev/full is missing");
    }
    let cfg = config(SMALL);
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    std::fs::create_dir_all(run_dir.join("session")).unwrap();
    // The frames go to /dev/full: the session's first frame file is a symlink to it.
    std::os::unix::fs::symlink("/dev/full", run_dir.join("session/frame_000003.png")).unwrap();
    let rig = rig();
    let spec = RunSpec {
        config: &cfg,
        rig: &rig,
        rig_toml: CUBE,
        rig_path: None,
        run_dir: &run_dir,
    };
    let stopped = Arc::new(AtomicBool::new(false));
    let hw = small_hw(&cfg);
    let hw = Hardware {
        turntable: Box::new(Spy {
            inner: hw.turntable,
            stopped: stopped.clone(),
        }),
        ..hw
    };
    let e = cubecal::station::run(
        &spec,
        hw,
        &mut cubecal::station::event::NullSink,
        &AtomicBool::new(false),
    )
    .expect_err("writing to a full disk must fail");
    assert!(e.to_string().contains("frame_000003.png"), "{e}");
    assert!(stopped.load(Ordering::SeqCst));
    assert!(!run_dir.join("profile.json").exists());
}

#[test]
fn photos_of_a_board_give_the_reference_focal_length() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/datasets/opencv_stereo_left_right/images");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_string_lossy().starts_with("left"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 13);
    let board_toml = include_str!("../fixtures/rigs/opencv_board_9x6.toml");
    let board = Rig::from_toml_str(board_toml, "opencv_board_9x6.toml")
        .unwrap()
        .0;
    let list: Vec<String> = files
        .iter()
        .map(|f| format!("{:?}", f.display().to_string()))
        .collect();
    let list = format!("[{}]", list.join(", "));
    let cfg = config(&[
        ("camera.source", "\"images\""),
        ("camera.images", list.as_str()),
        ("camera.frames_per_pose", "1"),
        ("turntable.kind", "\"none\""),
        // These 13 photos (640×480) determine fx to σ 0.12 % with the neighbours' correlation
        // counted (issue 29), beyond the default verdict's 0.1 %; the published calibrations of
        // them spread as much (SOURCE.md: fx 532.3–533.5).
        ("qa.max_sigma_fx_rel", "0.002"),
    ]);
    let hw = hardware::open(&cfg, &board, None).unwrap();
    let (r, _d) = run_hw(
        &cfg,
        &board,
        board_toml,
        hw,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
    );
    let r = r.unwrap();
    assert!(r.verdict.pass, "{:#?}", r.verdict);
    let k = r.calibration.unwrap().camera_matrix;
    // SOURCE.md: Bouguet's left camera fx = 533.00371, fy = 533.15260.
    let (dfx, dfy) = (
        (k[0][0] - 533.00371) / 533.00371,
        (k[1][1] - 533.15260) / 533.15260,
    );
    eprintln!(
        "opencv left: fx {:.3} ({:+.3} %), fy {:.3} ({:+.3} %)",
        k[0][0],
        100.0 * dfx,
        k[1][1],
        100.0 * dfy
    );
    assert!(dfx.abs() < 0.005 && dfy.abs() < 0.005);
}

#[test]
fn a_folder_of_renders_gives_the_rendered_camera() {
    use cubecal::render::{random_poses, render};
    let cfg = with(REALISTIC, &[]);
    let rig = rig();
    let camera = cfg.synthetic.camera();
    let dir = tempfile::tempdir().unwrap();
    let settings = cfg.synthetic.settings();
    for (i, pose) in random_poses(&rig, &camera, 12, 7).iter().enumerate() {
        let img = render(&rig, &camera, pose, &settings, i as u64).unwrap();
        // TIFF, as the classic public sets are.
        img.save(dir.path().join(format!("view_{i:02}.tif")))
            .unwrap();
    }
    let folder = format!("[{:?}]", dir.path().display().to_string());
    let mut keys: Vec<(&str, &str)> = REALISTIC.to_vec();
    keys.extend([
        ("camera.source", "\"images\""),
        ("camera.images", folder.as_str()),
        ("camera.frames_per_pose", "1"),
        ("turntable.kind", "\"none\""),
    ]);
    let run = config(&keys);
    let hw = hardware::open(&run, &rig, None).unwrap();
    let (r, _d) = run_hw(
        &run,
        &rig,
        CUBE,
        hw,
        &AtomicBool::new(false),
        &mut cubecal::station::event::NullSink,
    );
    assert_accurate(&r.unwrap(), &cfg, 2e-4, 0.2, "folder of TIFF renders");
}

/// Issue 29, acceptance line 4: the faces the full-resolution second look adds (one face at ~79.5°
/// per run on the `SMALL` camera; none on `REALISTIC`, whose grazing faces the first pass finds)
/// enter the solve with their bias in their covariance and move the station's cx, cy by at most
/// 0.3σ on average over noise seeds 1, 5, 7, 8 (σ of the run without them). Without that (the bias
/// term and equal weighting's ceiling, `detect::face::add_grazing_bias`,
/// `calib::lm::EQUAL_WEIGHT_CEILING`) the mean was 0.86σ. Ignored: 8 station runs, ~40 s in release
/// (`cargo test --release --test station -- --ignored second_look`); the table is
/// `cargo run --release --example second_look_eval -- small 1 5 7 8`.
#[test]
#[ignore = "8 station runs (~40 s in release); examples/second_look_eval.rs prints the table"]
fn second_look_faces_do_not_move_the_principal_point() {
    let mut shifts = Vec::new();
    let mut added = 0;
    for seed in ["1", "5", "7", "8"] {
        let mut c = [[0.0; 4]; 2];
        let mut corners = [0; 2];
        for (slot, on) in ["false", "true"].into_iter().enumerate() {
            let cfg = with(
                SMALL,
                &[
                    ("synthetic.supersample", "4"),
                    ("synthetic.seed", seed),
                    ("detect.second_look", on),
                ],
            );
            let (r, _d) = run_cfg(&cfg, None);
            let cal = r.calibration.as_ref().expect("a calibration");
            let k = cal.camera_matrix;
            c[slot] = [k[0][2], cal.std_dev["cx"], k[1][2], cal.std_dev["cy"]];
            corners[slot] = r
                .views
                .iter()
                .filter(|v| v.accepted)
                .map(|v| v.corners)
                .sum();
        }
        added += corners[1] - corners[0].min(corners[1]);
        let (dx, dy) = ((c[1][0] - c[0][0]) / c[0][1], (c[1][2] - c[0][2]) / c[0][3]);
        eprintln!(
            "seed {seed}: corners {} → {}, cx shift {dx:+.2}σ, cy shift {dy:+.2}σ",
            corners[0], corners[1]
        );
        shifts.extend([dx.abs(), dy.abs()]);
    }
    let mean = shifts.iter().sum::<f64>() / shifts.len() as f64;
    eprintln!("mean |shift|/σ {mean:.3}, {added} corners added by the second look");
    // The premise: the second look does add grazing faces on this camera.
    assert!(added >= 4 * 20, "{added}");
    assert!(mean <= 0.3, "{mean}");
}
