//! Issue 19's grid cases on renders with exact ground truth (sets described in `tests/cases/mod.rs`;
//! the full figures come from `cargo run --release --example detect_cases -- 6`): every fully visible
//! face found, no corner labelled wrong, corners accurate against the truth.
//!
//! RMS bars: 0.02 px where the grid decisions are the whole story (the wrapped cube too, since its
//! faces are fitted again on their own lattices: 0.0096 px over 6 views). The board filling the
//! frame (k1 −0.1: 0.0285 px over 6 views; k1 −0.4: 0.0264 px) is held to what the corner
//! refinement reaches on 4×4 supersampled renders (see tests/detect_accuracy.rs).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

mod cases;

use std::path::PathBuf;

use cubecal::detect::score::{FaceScore, Summary, score};
use cubecal::detect::{CornerFinder, detect};

/// `frames` of the set `name`, scored.
fn run(name: &str, frames: std::ops::Range<usize>) -> Vec<Vec<FaceScore>> {
    let case = cases::cases(6)
        .into_iter()
        .find(|c| c.name == name)
        .unwrap();
    let cache = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("detect_cases");
    let mut finder = CornerFinder::new().unwrap();
    frames
        .map(|k| {
            let (img, truth) = cases::frame(&case, k, &cache);
            let det = detect(&mut finder, &img, &case.rig).unwrap();
            let s = score(&case.rig, &truth, &det);
            for f in &s {
                if f.fully_visible && !f.found {
                    eprintln!(
                        "{name} frame {k}: face {} missed: {:?}",
                        f.face, det.rejected
                    );
                }
            }
            s
        })
        .collect()
}

fn check(name: &str, frames: std::ops::Range<usize>, max_rms_px: f64) -> Summary {
    let all: Vec<FaceScore> = run(name, frames).into_iter().flatten().collect();
    let s = Summary::of(&all, 0.0, 90.1);
    eprintln!("{name}: {s}");
    assert!(s.faces > 0, "{name}: no fully visible face");
    assert_eq!(s.found, s.faces, "{name}: {s}");
    assert_eq!(s.mislabelled, 0, "{name}: {s}");
    assert!(s.rms_px <= max_rms_px, "{name}: {s}");
    s
}

#[test]
fn a_board_without_margin_over_a_dark_background() {
    check("nomargin", 0..2, 0.02);
}

#[test]
fn a_board_printed_to_the_paper_edge_on_a_two_tone_desk_is_labelled_with_its_pose_flagged() {
    // Issue 28's classic planar set: where the desk's dark/bright line meets the paper's edge, one
    // corner-like junction sits one step beyond the board's last column. It is an incomplete line,
    // not a continuing board: the board is labelled (every view, no wrong label) with its pose
    // flagged, since a shift by that line would move the view's pose and not the intrinsics.
    let s = check("paper-edge", 0..6, 0.03);
    assert_eq!(s.faces, 6, "{s}");
    let case = cases::cases(6)
        .into_iter()
        .find(|c| c.name == "paper-edge")
        .unwrap();
    let cache = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("detect_cases");
    let (img, _) = cases::frame(&case, 0, &cache);
    let det = detect(&mut CornerFinder::new().unwrap(), &img, &case.rig).unwrap();
    let why = det.faces[0].ambiguous_pose.as_deref().unwrap_or_default();
    assert!(why.contains("an incomplete line"), "{why:?}");
}

#[test]
fn a_board_filling_the_frame() {
    check("fill", 0..2, 0.05);
    check("fill-k04", 0..2, 0.05);
}

#[test]
fn an_inside_corner_with_two_walls_of_equal_size_meeting_at_seams() {
    let s = check("inside-corner", 0..2, 0.02);
    assert_eq!(s.faces, 6, "three faces per view");
}

#[test]
fn a_sheet_wrapped_around_an_edge_is_cut_at_the_fold() {
    // All six views, the right face up to 69° from frontal included: in views 4 and 5 the assembly
    // runs across the fold and skips foreshortened lines beyond it, and the joined lattice takes the
    // grid beyond the fold for those lines (fold::join).
    let s = check("wrapped-cube", 0..6, 0.02);
    assert_eq!(s.faces, 12, "two faces per view");
}

#[test]
fn a_lone_board_cut_by_the_border_is_never_mislabelled() {
    // Not placed yet (0 of 6 views): placing a lone cut board by its visible ends, colours and the
    // border labelled random content and another board cut by the border in fuzzing, so it is not
    // done. What holds: no wrong label.
    let all: Vec<FaceScore> = run("cut", 0..3).into_iter().flatten().collect();
    assert!(
        all.iter()
            .all(|f| !f.fully_visible && f.visible_corners > 0)
    );
    assert_eq!(all.iter().map(|f| f.mislabelled).sum::<usize>(), 0);
}

#[test]
fn a_larger_board_of_the_same_squares_is_never_taken_for_the_rig() {
    // The rig's 13×12 board beside a 15×14 board with the same squares (rendered from a scene file,
    // detected with the rig's): views of both, and views turned so that only the larger board, cut by
    // the border, is left — where a part of it with the board's size and colours tempts placement.
    let all: Vec<FaceScore> = run("two-boards", 0..6).into_iter().flatten().collect();
    let s = Summary::of(&all, 0.0, 90.1);
    eprintln!("two-boards: {s}");
    assert_eq!(s.mislabelled, 0, "{s}");
    assert_eq!(s.found, s.faces, "{s}");
}

#[test]
fn a_replica_of_the_photographed_inside_corner_is_labelled_by_its_fold_and_pattern_ends() {
    // Two walls, the pattern continuous across the fold, k1 −0.25 at a wide angle: wall-z ends inside
    // the frame, wall-x runs off it (the photos of tests/detect_photo.rs). wall-x is never fully
    // visible: it must be placed by its fold and pattern ends in every view, nothing mislabelled.
    let frames = run("photo-corner", 0..3);
    let all: Vec<&FaceScore> = frames.iter().flatten().collect();
    for (k, s) in frames.iter().enumerate() {
        for f in s {
            assert!(f.found, "photo-corner frame {k}: face {} not found", f.face);
            assert_eq!(f.mislabelled, 0, "photo-corner frame {k}: face {}", f.face);
        }
        assert!(
            !s[1].fully_visible,
            "frame {k}: wall-x should run off the frame"
        );
    }
    let errors: Vec<f64> = all.iter().flat_map(|f| f.errors.iter().copied()).collect();
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    eprintln!("photo-corner: {} corners, RMS {rms:.4} px", errors.len());
    assert!(
        errors.len() > 500 && rms <= 0.1,
        "{} corners, RMS {rms}",
        errors.len()
    );
}
