//! A rig with a symmetry of its own: the two equal, 180°-symmetric walls of an inside corner without
//! its floor (`fixtures/rigs/inside_corner_walls.toml`). A half turn about their diagonal exchanges
//! them, so every frame fits two labellings alike, for any camera; they are one similarity apart and
//! give the same intrinsics. The detector labels such frames with one of them, pose flagged (it used
//! to drop every frame: "two assignments fit one camera alike"), and the calibration from them
//! recovers the rendered camera. Renders of the hard set's wide lens (k1 = −0.3), exact ground truth.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/truth.rs"]
mod truth;

use std::path::Path;

use cubecal::calib::pose::solve_pose;
use cubecal::detect::score::EvalSet;
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::{random_poses, render};
use cubecal::rig::Rig;

#[test]
fn a_symmetric_rig_is_labelled_up_to_its_symmetry_and_calibrates_the_rendered_camera() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/rigs/inside_corner_walls.toml");
    let (rig, _) = Rig::load(&path).unwrap();
    let set = EvalSet::Hard;
    let camera = set.camera();
    let settings = cubecal::render::RenderSettings {
        supersample: 2,
        ..set.settings()
    };
    let mut finder = CornerFinder::new().unwrap();
    let mut views = Vec::new();
    let n = 6;
    for (k, pose) in random_poses(&rig, &camera, n, 5).iter().enumerate() {
        let img = render(&rig, &camera, pose, &settings, k as u64).unwrap();
        let det = detect(&mut finder, &img, &rig).unwrap();
        let reasons: Vec<&str> = det.rejected.iter().map(|r| r.reason.as_str()).collect();
        if det.faces.len() != 2 {
            eprintln!("view {k}: {} faces: {reasons:?}", det.faces.len());
            continue;
        }
        for f in &det.faces {
            let why = f.ambiguous_pose.as_deref().unwrap_or_default();
            assert!(
                why.contains("symmetry of the rig"),
                "view {k}: face '{}' not flagged: {why:?}",
                rig.faces[f.face].name
            );
            assert_eq!(f.identity.as_deref(), Some(why), "view {k}");
        }
        let view = det.to_view(&format!("v{k:02}"));
        // Whichever labelling was taken, it fits the true camera as well as the truth does: a
        // labelling that is not one similarity from the truth misses by many pixels.
        let fit = solve_pose(&camera, &view).unwrap();
        eprintln!(
            "view {k}: 2 faces, pose fit in the true camera {:.3} px RMS",
            fit.rms_px
        );
        assert!(
            fit.rms_px < 0.3,
            "view {k}: {} px in the true camera",
            fit.rms_px
        );
        // A symmetry of the nominal rig is not one of the real rig: the rig survey leaves them out.
        assert!(det.to_rig_view("v").points.is_empty(), "view {k}");
        views.push(view);
    }
    eprintln!("{} of {n} views labelled", views.len());
    assert!(
        views.len() >= n - 1,
        "{} of {n} views labelled",
        views.len()
    );
    truth::assert_calibrates_to(&views, &camera, 0.3);
}
