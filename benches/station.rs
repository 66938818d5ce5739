//! Station benchmark: `cargo bench --bench station`. Release build. Prints
//! 1. the compute per pose beyond waiting for the hardware at 1280×960 — queuing the frames to the
//!    session's writer thread (which encodes the PNGs while the turntable moves), the motion check,
//!    detection, the blur check — over 12 turntable poses, 2 frames each;
//! 2. the final solve for 12 poses × 3 faces (+ the held-out pose);
//! 3. a whole replay of the bundled session (`fixtures/sessions/demo`) through `station::run`, wall time,
//!    and the process's peak RSS afterwards (VmHWM).
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use cubecal::calib::{Correspondence, View};
use cubecal::camera::{Camera, DistortionModel};
use cubecal::capture::FrameSource;
use cubecal::capture::session::{SessionHeader, SessionWriter};
use cubecal::capture::synthetic::{AngleCell, TurntableScene};
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::{RenderSettings, default_view};
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, set_key};
use cubecal::station::hardware::plan_angles;
use cubecal::station::sharpness;

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn peak_rss_mb() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let rig_toml = std::fs::read_to_string(root.join("fixtures/rigs/cube_outside.toml")).unwrap();
    let rig = Rig::from_toml_str(&rig_toml, "cube_outside.toml")
        .unwrap()
        .0;
    let camera = Camera::pinhole([1280, 960], 1100.0, 1100.0, 639.5, 479.5)
        .with_distortion(DistortionModel::Brown5, &[-0.2, 0.05]);
    let settings = RenderSettings {
        blur_sigma_px: 1.0,
        noise_sigma: 2.0,
        seed: 3,
        ..RenderSettings::default()
    };
    let angle = AngleCell::default();
    let mut scene = TurntableScene::new(
        rig.clone(),
        camera.clone(),
        default_view(&rig, &camera),
        settings,
        angle.clone(),
    )
    .unwrap();
    let mut frames = Vec::new();
    for a in plan_angles(12, 60.0) {
        angle.set(a);
        let f1 = scene.grab(Duration::from_secs(1)).unwrap();
        let f2 = scene.grab(Duration::from_secs(1)).unwrap();
        frames.push((f1, f2, a));
    }
    // 1. Per-pose compute.
    let dir = tempfile::tempdir().unwrap();
    let mut finder = CornerFinder::new().unwrap();
    let mut per_pose = Vec::new();
    let mut parts = [Duration::ZERO; 4];
    let mut views = Vec::new();
    for rep in 0..3 {
        let header = SessionHeader {
            source: scene.describe(),
            device: None,
            capture: None,
            controls: vec![],
            rig: None,
            config: serde_json::Value::Null,
        };
        let mut w =
            SessionWriter::create_background(&dir.path().join(format!("s{rep}")), header).unwrap();
        for (i, (f1, f2, a)) in frames.iter().enumerate() {
            let t0 = Instant::now();
            w.add_frame(f1, Some(*a)).unwrap();
            w.add_frame(f2, Some(*a)).unwrap();
            let t1 = Instant::now();
            let m = sharpness::motion_fraction(&f1.image, &f2.image);
            let t2 = Instant::now();
            let det = detect(&mut finder, &f2.image, &rig).unwrap();
            let t3 = Instant::now();
            let b = sharpness::blur_px(&f2.image, &det.faces);
            let t4 = Instant::now();
            assert!(m < 0.01 && b.is_some());
            per_pose.push(t4 - t0);
            parts[0] += t1 - t0;
            parts[1] += t2 - t1;
            parts[2] += t3 - t2;
            parts[3] += t4 - t3;
            if rep == 0 {
                views.push(View {
                    name: format!("pose{i:02}"),
                    points: det
                        .faces
                        .iter()
                        .flat_map(|f| f.corners.iter())
                        .map(|c| Correspondence {
                            xyz: c.xyz,
                            uv: c.uv,
                            cov: c.covariance(),
                        })
                        .collect(),
                });
            }
        }
        w.finish().unwrap();
    }
    let n = per_pose.len() as u32;
    println!(
        "station per pose (1280×960, 2 frames, 3 faces): median {:.1} ms — session writes queued {:.1} ms, motion {:.2} ms, detect {:.1} ms, blur {:.2} ms (means)",
        median(per_pose).as_secs_f64() * 1e3,
        (parts[0] / n).as_secs_f64() * 1e3,
        (parts[1] / n).as_secs_f64() * 1e3,
        (parts[2] / n).as_secs_f64() * 1e3,
        (parts[3] / n).as_secs_f64() * 1e3,
    );
    // 2. Final solve: 11 fitted views + the held-out pose, as the station does.
    let opts = StationConfig::default().solve_options("bench").unwrap();
    let points: usize = views.iter().map(|v| v.points.len()).sum();
    let mut times = Vec::new();
    for _ in 0..20 {
        let t0 = Instant::now();
        let cal = cubecal::calib::solve(&views[..11], [1280, 960], &opts).unwrap();
        cubecal::calib::pose::solve_pose(&cal.camera, &views[11]).unwrap();
        times.push(t0.elapsed());
    }
    println!(
        "final solve, 12 poses × 3 faces ({points} corners, 11 fitted + 1 held out): median {:.1} ms",
        median(times).as_secs_f64() * 1e3
    );
    // 3. Replay of the bundled session.
    let mut table = toml::Table::new();
    set_key(&mut table, "camera.source", "\"replay\"").unwrap();
    let demo = root.join("fixtures/sessions/demo");
    set_key(
        &mut table,
        "camera.replay",
        &format!("{:?}", demo.display().to_string()),
    )
    .unwrap();
    set_key(&mut table, "turntable.kind", "\"none\"").unwrap();
    set_key(&mut table, "camera.frames_per_pose", "1").unwrap();
    let cfg = StationConfig::from_table(table, "bench").unwrap();
    let mut walls = Vec::new();
    for rep in 0..3 {
        let run_dir = dir.path().join(format!("replay{rep}"));
        let spec = cubecal::station::RunSpec {
            config: &cfg,
            rig: &rig,
            rig_toml: &rig_toml,
            rig_path: None,
            run_dir: &run_dir,
        };
        let t0 = Instant::now();
        let hw = cubecal::station::hardware::open(&cfg, &rig, None).unwrap();
        let r = cubecal::station::run(
            &spec,
            hw,
            &mut cubecal::station::event::NullSink,
            &AtomicBool::new(false),
        )
        .unwrap();
        walls.push(t0.elapsed());
        assert!(r.verdict.pass);
    }
    println!(
        "replay of fixtures/sessions/demo (12 poses, 640×480): median wall {:.0} ms; peak RSS {:.0} MB",
        median(walls).as_secs_f64() * 1e3,
        peak_rss_mb().unwrap_or(f64::NAN)
    );
}
