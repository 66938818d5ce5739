//! The detector on renders with exact ground truth: the three-face cube from seeded random views in the
//! two sets of issue 4 ([`EvalSet`]), scored by [`cubecal::detect::score`]. Mislabelled corners must be
//! zero; the other figures are guards at the level measured when the test was written (the full
//! 24-frame figures come from `cargo run --release --example detect_eval -- SET 24 DIR`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use cubecal::camera::Pose;
use cubecal::detect::score::{EvalSet, FaceScore, Summary, score};
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::{ground_truth, render};
use cubecal::rig::Rig;
use nalgebra::Vector3;

fn run(set: EvalSet, n: usize) -> Vec<FaceScore> {
    run_panned(set, n, 0.0)
}

/// The views of `set` with the camera turned about its vertical axis by ±`pan_deg` (alternating).
fn run_panned(set: EvalSet, n: usize, pan_deg: f64) -> Vec<FaceScore> {
    let rig_path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    );
    let (rig, _) = Rig::load(std::path::Path::new(rig_path)).unwrap();
    let (camera, settings) = (set.camera(), set.settings());
    let mut finder = CornerFinder::new().unwrap();
    let mut all = Vec::new();
    for (k, pose) in set.poses(&rig, n).iter().enumerate() {
        let deg = if k % 2 == 0 { pan_deg } else { -pan_deg };
        let pan = Pose::from_axis_angle(Vector3::new(0.0, deg.to_radians(), 0.0), Vector3::zeros());
        let pose = &pan.compose(pose);
        let img = render(&rig, &camera, pose, &settings, k as u64).unwrap();
        let truth = ground_truth(&rig, &camera, pose, &settings, k as u64);
        let det = detect(&mut finder, &img, &rig).unwrap();
        let scores = score(&rig, &truth, &det);
        for s in scores.iter().filter(|s| s.fully_visible) {
            eprintln!(
                "{set:?} frame {k}: face '{}' at {:.0}° from frontal: {}",
                rig.faces[s.face].name,
                s.angle_deg,
                if s.found { "found" } else { "missed" }
            );
        }
        all.extend(scores);
    }
    all
}

#[test]
fn realistic_views_every_face_below_75_degrees_found_accurately() {
    let scores = run(EvalSet::Realistic, 6);
    let below = Summary::of(&scores, 0.0, 75.0);
    eprintln!("realistic, faces < 75°: {below}");
    eprintln!(
        "realistic, all faces:   {}",
        Summary::of(&scores, 0.0, 90.1)
    );
    assert_eq!(below.mislabelled, 0);
    assert!(below.faces >= 10, "{below}");
    // Every face: frame 4's side-x at 74.1° was missed until grid assembly required alternating
    // polarity (it was split into fragments of every other column). Over the 24-frame set the
    // detector finds 53 of 53 faces under 75°.
    assert_eq!(below.found, below.faces, "{below}");
    assert!(below.rms_px <= 0.03, "{below}");
    assert!(below.max_px <= 0.15, "{below}");
    // The per-corner σ bounds the error: radial RMS error ≈ √2 σ when noise dominates (hard set); at
    // low noise σ stays conservative (ratio 0.65 on these frames, 0.66 over the 24-frame set).
    let ratio = below.rms_px / (2f64.sqrt() * below.rms_sigma_px);
    assert!((0.4..1.5).contains(&ratio), "error / σ ratio {ratio}");
}

#[test]
fn hard_views_are_never_mislabelled_and_sigma_is_honest() {
    let scores = run(EvalSet::Hard, 6);
    let below = Summary::of(&scores, 0.0, 75.0);
    eprintln!("hard, faces < 75°: {below}");
    assert_eq!(Summary::of(&scores, 0.0, 90.1).mislabelled, 0);
    // Issue 4's bar on the share of faces found, 90 %, is met (11 of these 11; 38 of 38 over the
    // 24-frame set); its RMS bar (≤ 0.08 px) is not met yet (0.099 here, 0.098 over the 24-frame
    // set): guard just above today's level.
    assert!(below.found * 10 >= below.faces * 9, "{below}");
    assert!(below.rms_px <= 0.11, "{below}");
    let ratio = below.rms_px / (2f64.sqrt() * below.rms_sigma_px);
    assert!((0.7..1.5).contains(&ratio), "error / σ ratio {ratio}");
}

/// Faces cut by the image border are placed on the rig through the completely visible faces of the
/// same frame (`detect::place`): never mislabelled, as accurate as whole faces at that distance from
/// the image centre. (Over 24 frames, `PAN_DEG=30 detect_eval realistic 24`: 41 partially visible
/// faces, 23 placed with 1176 of their 1222 visible corners, 0 mislabelled, RMS 0.036 px; the others
/// have no complete face beside them.)
#[test]
fn partially_visible_faces_are_placed_and_never_mislabelled() {
    let scores = run_panned(EvalSet::Realistic, 8, 30.0);
    let partial: Vec<&FaceScore> = scores.iter().filter(|s| !s.fully_visible).collect();
    let placed: Vec<&&FaceScore> = partial.iter().filter(|s| s.found).collect();
    let errors: Vec<f64> = placed
        .iter()
        .flat_map(|s| s.errors.iter().copied())
        .collect();
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len().max(1) as f64).sqrt();
    eprintln!(
        "panned realistic: {} partially visible faces, {} placed, {} corners, RMS {rms:.4} px",
        partial.iter().filter(|s| s.visible_corners > 0).count(),
        placed.len(),
        errors.len()
    );
    assert_eq!(scores.iter().map(|s| s.mislabelled).sum::<usize>(), 0);
    assert!(placed.len() >= 3, "{} placed", placed.len());
    assert!(rms <= 0.06, "RMS {rms}");
}
