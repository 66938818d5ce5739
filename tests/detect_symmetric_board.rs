//! A lone 180°-symmetric board (both inner-corner counts even, 8×6): its square colours read the same
//! either way round, so one frame cannot tell its orientation. On a rig of one face this does not
//! matter for the camera: the two labellings differ by a half turn within the board's plane, which
//! moves the view's pose and never the intrinsics. Such a board is labelled (pose flagged) and the
//! calibration from renders of it recovers the rendered camera. Renders with exact ground truth.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/truth.rs"]
mod truth;

use cubecal::detect::score::EvalSet;
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::{random_poses, render};
use cubecal::rig::Rig;

const BOARD_8X6: &str = r#"
name = "board-8x6"
units = "mm"

[[faces]]
name = "board"
cols = 8
rows = 6
square_mm = 25.0
margin_mm = 25.0
origin = [0, 0, 0]
col_dir = [1, 0, 0]
row_dir = [0, 1, 0]
"#;

#[test]
fn a_lone_symmetric_board_is_labelled_and_calibrates_the_rendered_camera() {
    let (rig, _) = Rig::from_toml_str(BOARD_8X6, "board-8x6").unwrap();
    let set = EvalSet::Realistic;
    let camera = set.camera();
    // The realistic set's camera effects; 2×2 supersampling keeps the renders quick.
    let settings = cubecal::render::RenderSettings {
        supersample: 2,
        ..set.settings()
    };
    let mut finder = CornerFinder::new().unwrap();
    let mut views = Vec::new();
    for (k, pose) in random_poses(&rig, &camera, 8, 3).iter().enumerate() {
        let img = render(&rig, &camera, pose, &settings, k as u64).unwrap();
        let det = detect(&mut finder, &img, &rig).unwrap();
        let reasons: Vec<&str> = det.rejected.iter().map(|r| r.reason.as_str()).collect();
        assert!(
            !reasons.iter().any(|r| r.contains("180°-symmetric")),
            "view {k}: a lone symmetric board was refused: {reasons:?}"
        );
        let Some(face) = det.faces.first() else {
            eprintln!("view {k}: not labelled: {reasons:?}");
            continue;
        };
        assert_eq!(face.corners.len(), 48, "view {k}");
        let why = face.ambiguous_pose.as_deref().unwrap_or_default();
        assert!(
            why.contains("180°-symmetric"),
            "view {k}: pose not flagged: {why:?}"
        );
        views.push(det.to_view(&format!("v{k:02}")));
    }
    eprintln!("{} of 8 views labelled", views.len());
    assert!(views.len() >= 7, "{} of 8 views labelled", views.len());
    truth::assert_calibrates_to(&views, &camera, 0.2);
}
