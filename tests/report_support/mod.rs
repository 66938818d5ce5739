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

use cubecal::calib::report::CalibrationReport;
use cubecal::calib::{self, Correspondence, SolveOptions, View};
use cubecal::camera::{Camera, DistortionModel, Pose};
use cubecal::capture::session::{SessionHeader, SessionWriter};
use cubecal::capture::synthetic::{self, RenderSettings};
use cubecal::capture::{Frame, SourceInfo};
use cubecal::detect::CornerFinder;
use cubecal::observations::{RawObservations, RawPoint, RawView};
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
            let mut p: Vec<Pose> = synthetic::random_poses(&rig, &cam, n, 7)
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
            let p: Vec<Pose> = synthetic::turntable_poses(&rig, &cam, n, 40.0)
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
        let img = synthetic::render(&rig, &cam, pose, &settings, i as u64).unwrap();
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
