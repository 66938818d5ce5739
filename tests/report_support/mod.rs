//! Builds station run directories for the report tests, the report benchmark and the CI's
//! headless-browser check, the way the station lays them out (see `cubecal::report::run`): frames
//! rendered from the bundled cube rig with a known camera, recorded as a session, detected, solved,
//! judged with a simple verdict.
//!
//! The held-out view's pose comes from a solve that includes it (the station fits it with the
//! intrinsics fixed; for a report fixture the difference does not matter).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::time::Duration;

use cubecal::calib::observations::{RawObservations, RawPoint, RawView};
use cubecal::calib::report::CalibrationReport;
use cubecal::calib::{self, Correspondence, SolveOptions, View};
use cubecal::camera::{Camera, DistortionModel, Pose};
use cubecal::capture::session::{SessionHeader, SessionWriter};
use cubecal::capture::{Frame, SourceInfo};
use cubecal::detect::CornerFinder;
use cubecal::render::{self, RenderSettings};
use cubecal::report::analysis::{COVERAGE_GRID, CoverageGrid};
use cubecal::rig::Rig;
use cubecal::station::{Check, Verdict};
use nalgebra::{Rotation3, Vector3};

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn rig_path() -> PathBuf {
    repo().join("fixtures/rigs/cube_outside.toml")
}

/// Which run to build.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `n` seeded random views around the rig plus one frame that misses the rig (rejected).
    Good { n: usize },
    /// Six turntable views over 40° from twice the distance: the corners fill the image centre
    /// only, and the verdict fails on coverage.
    PoorCoverage,
}

/// The camera every fixture run is rendered with.
pub fn camera(width: u32, height: u32) -> Camera {
    let f = 0.86 * f64::from(width);
    Camera::pinhole(
        [width, height],
        f,
        f,
        (f64::from(width) - 1.0) / 2.0 + 6.0,
        (f64::from(height) - 1.0) / 2.0 - 4.0,
    )
    .with_distortion(
        DistortionModel::Brown5,
        &[-0.18, 0.06, 0.0004, -0.0003, 0.0],
    )
}

/// Build a run directory in `dir` (created) and return it.
pub fn build_run(dir: &Path, kind: Kind, width: u32, height: u32) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let (rig, _) = Rig::load(&rig_path()).unwrap();
    std::fs::copy(rig_path(), dir.join("rig.toml")).unwrap();
    let cam = camera(width, height);
    let (poses, angles): (Vec<Pose>, Vec<Option<f64>>) = match kind {
        Kind::Good { n } => {
            // Random views from 1.5× the distance, the camera panned so that the rig lands in turn
            // near each corner and edge of the frame and in its centre.
            let fov_x = (0.27 * f64::from(width) / cam.fx()).atan();
            let fov_y = (0.27 * f64::from(height) / cam.fy()).atan();
            let pans = [
                (-1.0, -1.0),
                (1.0, 1.0),
                (1.0, -1.0),
                (-1.0, 1.0),
                (0.0, 0.0),
                (-1.0, 0.0),
                (1.0, 0.0),
                (0.0, -1.0),
                (0.0, 1.0),
            ];
            let mut p: Vec<Pose> = render::random_poses(&rig, &cam, n, 7)
                .into_iter()
                .enumerate()
                .map(|(k, mut pose)| {
                    pose.translation *= 1.5;
                    let (a, b) = pans[k % pans.len()];
                    // Turning the camera by −θ about its y axis moves the image of the rig right.
                    let turn = Rotation3::from_euler_angles(b * fov_y, -a * fov_x, 0.0);
                    Pose {
                        rotation: turn * pose.rotation,
                        translation: turn * pose.translation,
                    }
                })
                .collect();
            // A frame that misses the rig: moved far to the side.
            let mut away = p[0];
            away.translation += Vector3::new(4000.0, 0.0, 0.0);
            p.push(away);
            let a = vec![None; p.len()];
            (p, a)
        }
        Kind::PoorCoverage => {
            let n = 6;
            let p: Vec<Pose> = render::turntable_poses(&rig, &cam, n, 40.0)
                .into_iter()
                .map(|mut p| {
                    p.translation *= 2.0;
                    p
                })
                .collect();
            let a = (0..n)
                .map(|k| Some((k as f64 - (n as f64 - 1.0) / 2.0) * 40.0 / n as f64))
                .collect();
            (p, a)
        }
    };
    let settings = RenderSettings {
        supersample: 2,
        blur_sigma_px: 0.7,
        noise_sigma: 1.5,
        seed: 3,
        ..RenderSettings::default()
    };
    let header = SessionHeader {
        source: SourceInfo {
            identity: "synthetic:cube-outside".into(),
            name: "report test fixture".into(),
            width,
            height,
            format: "GREY".into(),
        },
        device: None,
        capture: None,
        controls: vec![],
        rig: None,
        config: serde_json::Value::Null,
    };
    let session_dir = dir.join("session");
    let mut writer = SessionWriter::create(&session_dir, header).unwrap();
    let mut finder = CornerFinder::new().unwrap();
    let mut raw_views = Vec::new();
    let mut outcomes = Vec::new();
    for (i, (pose, angle)) in poses.iter().zip(&angles).enumerate() {
        let img = render::render(&rig, &cam, pose, &settings, i as u64).unwrap();
        let det = cubecal::detect::detect(&mut finder, &img, &rig).unwrap();
        writer
            .add_frame(
                &Frame {
                    sequence: i as u64,
                    timestamp: Duration::from_millis(33 * i as u64),
                    image: img,
                },
                *angle,
            )
            .unwrap();
        let frame = format!("frame_{i:06}.png");
        let name = format!("pose{i:02}");
        let points: Vec<RawPoint> = det
            .faces
            .iter()
            .flat_map(|f| {
                let face = rig.faces[f.face].name.clone();
                f.corners.iter().map(move |c| RawPoint {
                    xyz: c.xyz.into(),
                    uv: c.uv.into(),
                    face: Some(face.clone()),
                    cov: None,
                })
            })
            .collect();
        if points.len() < 20 {
            let reason = det
                .rejected
                .first()
                .map_or("no face found".to_string(), |r| r.reason.clone());
            outcomes.push(serde_json::json!({"name": name, "frame": frame, "accepted": false, "reason": reason}));
            continue;
        }
        outcomes.push(
            serde_json::json!({"name": name, "frame": frame, "accepted": true, "reason": null}),
        );
        raw_views.push(RawView {
            name: Some(name),
            points,
            frame: Some(frame),
            held_out: false,
        });
    }
    writer.finish().unwrap();
    // The last accepted view is held out.
    let last = raw_views.len() - 1;
    raw_views[last].held_out = true;
    let to_view = |v: &RawView| View {
        name: v.name.clone().unwrap(),
        points: v
            .points
            .iter()
            .map(|p| Correspondence {
                xyz: p.xyz.into(),
                uv: p.uv.into(),
                cov: None,
            })
            .collect(),
    };
    let fitted: Vec<View> = raw_views
        .iter()
        .filter(|v| !v.held_out)
        .map(to_view)
        .collect();
    let all: Vec<View> = raw_views.iter().map(to_view).collect();
    let opts = SolveOptions::default();
    let cal = calib::solve(&fitted, [width, height], &opts).unwrap();
    let with_held = calib::solve(&all, [width, height], &opts).unwrap();
    let held = &with_held.views[last];
    let report = CalibrationReport::from(&cal);
    let obs = RawObservations {
        image_size: [width, height],
        views: raw_views,
    };
    let grid = CoverageGrid::count(
        obs.views
            .iter()
            .flat_map(|v| v.points.iter())
            .map(|p| nalgebra::Vector2::from(p.uv)),
        [width, height],
        COVERAGE_GRID,
    );
    let verdict = Verdict::from_checks(vec![
        Check::at_most("rms_px", report.rms_px, 0.5, || {
            "check focus and lighting".into()
        }),
        Check::at_least("coverage", grid.fraction(), 0.6, || {
            "add poses that bring the rig near the image corners and edges".into()
        }),
        Check::at_most("held_out_rms_px", held.rms_px, 0.5, || {
            "the calibration does not predict a view it was not fitted to: add poses".into()
        }),
    ]);
    let r = held.cam_from_rig.rotation.matrix();
    let rotation: Vec<[f64; 3]> = (0..3).map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]).collect();
    let result = serde_json::json!({
        "verdict": verdict,
        "calibration": report,
        "held_out": [{
            "name": held.name,
            "rms_px": held.rms_px,
            "rotation": rotation,
            "translation": [held.cam_from_rig.translation.x, held.cam_from_rig.translation.y, held.cam_from_rig.translation.z],
        }],
        "views": outcomes,
        "profile": null,
        "run_dir": dir,
        "device": {"identity": "synthetic:cube-outside", "name": "report test fixture"},
    });
    std::fs::write(
        dir.join("observations.json"),
        serde_json::to_string_pretty(&obs).unwrap(),
    )
    .unwrap();
    std::fs::write(
        dir.join("result.json"),
        serde_json::to_string_pretty(&result).unwrap(),
    )
    .unwrap();
    dir.to_path_buf()
}

// ---------------------------------------------------------------------------------------------------
// profiles with history

/// One intrinsic of a profile version: name, value, σ (0: fixed, not estimated).
pub type Param = (&'static str, f64, f64);

/// A calibration of a 1280×960 Brown5 camera with exactly these parameters (absent ones are 0 and
/// fixed), a diagonal covariance of the estimated ones, and three views 600 mm away.
pub fn calibration_with(params: &[Param]) -> CalibrationReport {
    let get = |n: &str| params.iter().find(|p| p.0 == n).map_or(0.0, |p| p.1);
    let free: Vec<&Param> = params.iter().filter(|p| p.2 > 0.0).collect();
    let view = |k: u32| cubecal::calib::report::ViewReport {
        name: format!("v{k}"),
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [f64::from(k) * 10.0, 0.0, 600.0],
        rvec: [0.0; 3],
        rms_px: 0.1,
        n_points: 100,
        outliers: vec![],
        rotation_std_deg: [0.01; 3],
        translation_std: [0.1; 3],
    };
    CalibrationReport {
        image_size: [1280, 960],
        camera_matrix: [
            [get("fx"), get("skew"), get("cx")],
            [0.0, get("fy"), get("cy")],
            [0.0, 0.0, 1.0],
        ],
        distortion: cubecal::calib::report::DistortionReport {
            model: "brown5".into(),
            coefficients: ["k1", "k2", "p1", "p2", "k3"]
                .iter()
                .map(|n| get(n))
                .collect(),
        },
        std_dev: free.iter().map(|p| (p.0.to_string(), p.2)).collect(),
        free_params: free.iter().map(|p| p.0.to_string()).collect(),
        covariance: (0..free.len())
            .map(|i| {
                (0..free.len())
                    .map(|j| if i == j { free[i].2 * free[i].2 } else { 0.0 })
                    .collect()
            })
            .collect(),
        rms_px: 0.1,
        rms_reprojection_px: 0.1 * 2f64.sqrt(),
        sigma_px: 0.1,
        noise_scale: None,
        n_points: 300,
        n_params: free.len() + 18,
        views: (0..3).map(view).collect(),
        iterations: 6,
        termination: "converged".into(),
        converged: true,
        init_method: cubecal::calib::init::InitMethod::Dlt,
    }
}

/// A passing profile of `identity` with calibration `cal`, created `secs` after 2026-11-01 00:00 UTC.
pub fn profile_of(identity: &str, cal: CalibrationReport, secs: u64) -> cubecal::profile::Profile {
    cubecal::profile::Profile {
        identity: cubecal::profile::Identity {
            id: identity.to_string(),
            origin: cubecal::profile::IdentityOrigin::User,
            device: None,
        },
        calibration: cal,
        verdict: Verdict::from_checks(vec![
            Check::at_most("rms_px", 0.1, 0.5, || "refocus".into()),
            Check::at_least("coverage", 0.8, 0.6, || "more corners".into()),
        ]),
        controls: vec![],
        format: None,
        rig: cubecal::profile::RigRef {
            name: "cube_outside".into(),
            sha256: "0".repeat(64),
        },
        session: None,
        software_version: env!("CARGO_PKG_VERSION").into(),
        created: cubecal::profile::rfc3339_from_unix(1_793_491_200 + secs),
        change: None,
    }
}

/// Commit one profile per entry of `versions` (oldest first, a week apart) for `identity` into the
/// store at `store_dir`; returns the camera's folder.
pub fn build_history(store_dir: &Path, identity: &str, versions: &[Vec<Param>]) -> PathBuf {
    let store = cubecal::profile::Store::open(store_dir).unwrap();
    let mut folder = None;
    for (i, params) in versions.iter().enumerate() {
        let p = profile_of(identity, calibration_with(params), i as u64 * 7 * 86_400);
        folder = Some(store.commit(&p, &Default::default()).unwrap().folder);
    }
    folder.expect("at least one version")
}

/// The parameters of version `v` of a camera whose focal length drifts by +0.4 px (fx) and +0.25 px
/// (fy) a version (σ 0.3),
/// whose principal point jumps by 3 px in x at version 3 (σ 0.25) and whose k1 wanders.
pub fn drifting_camera(v: usize) -> Vec<Param> {
    let t = v as f64;
    vec![
        ("fx", 1100.0 + 0.4 * t, 0.3),
        ("fy", 1100.2 + 0.25 * t, 0.3),
        ("cx", 645.0 + if v >= 2 { 3.0 } else { 0.0 }, 0.25),
        ("cy", 476.0 + 0.05 * t, 0.25),
        ("k1", -0.180 + 0.0015 * (t * 1.7).sin(), 0.001),
        ("k2", 0.060, 0.004),
        ("p1", 0.0004, 0.0001),
        ("p2", -0.0003, 0.0001),
    ]
}
