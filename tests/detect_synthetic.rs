//! The detector on renders with exact ground truth: the three-face cube on a turntable at realistic
//! settings (blur, noise, gamma, vignetting). Measures the share of fully visible faces found, the corner
//! error against ground truth, and counts mislabelled corners (which must be zero).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use std::collections::HashMap;

use cubecal::camera::{Camera, DistortionModel};
use cubecal::capture::synthetic::{RenderSettings, ground_truth, render, turntable_poses};
use cubecal::detect::{CornerFinder, detect};
use cubecal::target::Rig;

#[test]
fn cube_turntable_faces_found_exactly_labelled_and_accurate() {
    let rig_path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    );
    let (rig, _) = Rig::load(std::path::Path::new(rig_path)).unwrap();
    let camera = Camera::pinhole([1280, 960], 1000.0, 1000.0, 639.5, 479.5)
        .with_distortion(DistortionModel::Brown5, &[-0.1, 0.02]);
    let settings = RenderSettings {
        blur_sigma_px: 1.0,
        noise_sigma: 2.0,
        gamma: 1.8,
        vignetting: 0.3,
        seed: 11,
        ..RenderSettings::default()
    };
    let poses = turntable_poses(&rig, &camera, 4, 60.0);
    let mut finder = CornerFinder::new().unwrap();
    let (mut faces_visible, mut faces_found, mut mislabelled) = (0, 0, 0);
    let (mut sq, mut n, mut max) = (0.0, 0usize, 0.0f64);
    for (k, pose) in poses.iter().enumerate() {
        let img = render(&rig, &camera, pose, &settings, k as u64).unwrap();
        let gt = ground_truth(&rig, &camera, pose, &settings, k as u64);
        let truth: HashMap<(usize, usize, usize), [f64; 2]> = gt
            .visible()
            .map(|c| ((c.face_index, c.row, c.col), c.uv.unwrap()))
            .collect();
        let det = detect(&mut finder, &img, &rig).unwrap();
        for (fi, f) in rig.faces.iter().enumerate() {
            let visible = gt
                .corners
                .iter()
                .filter(|c| c.face_index == fi && c.visible)
                .count();
            if visible == f.n_corners() {
                faces_visible += 1;
                // Angle between the face normal and the ray to the face centre.
                let centre = f.corner_xyz(f.rows / 2, f.cols / 2);
                let to_cam = -(pose.rotation.inverse() * pose.translation) - centre;
                let angle = f.normal().angle(&to_cam).to_degrees();
                let found = det.faces.iter().any(|d| d.face == fi);
                eprintln!(
                    "frame {k}: face '{}' seen at {angle:.0}° from frontal: {}",
                    f.name,
                    if found { "found" } else { "MISSED" }
                );
            }
        }
        for face in &det.faces {
            if gt
                .corners
                .iter()
                .filter(|c| c.face_index == face.face && c.visible)
                .count()
                == rig.faces[face.face].n_corners()
            {
                faces_found += 1;
            }
            for c in &face.corners {
                match truth.get(&(face.face, c.row, c.col)) {
                    Some(t) => {
                        let e = ((c.uv.x - t[0]).powi(2) + (c.uv.y - t[1]).powi(2)).sqrt();
                        if e > 1.0 {
                            mislabelled += 1;
                        }
                        sq += e * e;
                        n += 1;
                        max = max.max(e);
                    }
                    None => mislabelled += 1,
                }
            }
        }
        eprintln!(
            "frame {k}: {} faces, rejected {:?}",
            det.faces.len(),
            det.rejected
        );
    }
    let rms = (sq / n.max(1) as f64).sqrt();
    eprintln!(
        "faces found {faces_found}/{faces_visible} fully visible; {n} corners, RMS {rms:.4} px, max {max:.4} px, mislabelled {mislabelled}"
    );
    assert_eq!(mislabelled, 0);
    assert!(faces_visible > 0);
    // Regression guard at today's level (9 of 12 faces: the misses are faces seen at 70°+ whose corners
    // the front end does not find, and one face with a corner lost in grid growth); issue 4's bar is
    // ≥ 99 %, not met yet.
    assert!(
        faces_found * 4 >= faces_visible * 3,
        "{faces_found}/{faces_visible}"
    );
    assert!(rms < 0.05, "rms {rms}");
    assert!(max < 0.25, "max {max}");
}
