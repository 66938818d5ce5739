//! Corner accuracy of issue 19's case renders against their exact ground truth (acceptance line 1:
//! RMS ≤ 0.02 px), where the corners meet a fold, their face's pattern edge or the frame border.
//! The figures per corner (by lattice distance to the pattern edge and to the fold, by distance to
//! the image border, by image radius, by how close the lattice lines are to the pixel axes) come from
//! `cargo run --release --example detect_accuracy -- 6 target/detect_accuracy`.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

mod cases;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use cubecal::detect::score::{Summary, score};
use cubecal::detect::{CornerFinder, detect};
use nalgebra::Vector2;

/// One correctly labelled corner: face, row, column, error vector (px), and how far (deg) the nearer
/// of its two lattice lines is from a pixel axis.
struct Corner {
    face: usize,
    col: usize,
    error: Vector2<f64>,
    off_axis_deg: f64,
}

/// Detect `frames` of `case` (rendered into `cache`): the summary over the fully visible faces and
/// every correctly labelled corner.
fn run(case: &cases::Case, frames: std::ops::Range<usize>, cache: &Path) -> (Summary, Vec<Corner>) {
    let mut finder = CornerFinder::new().unwrap();
    let mut scores = Vec::new();
    let mut corners = Vec::new();
    for k in frames {
        let (img, truth) = cases::frame(case, k, cache);
        let det = detect(&mut finder, &img, &case.rig).unwrap();
        scores.extend(score(&case.rig, &truth, &det));
        let gt: HashMap<(usize, usize, usize), Vector2<f64>> = truth
            .visible()
            .filter_map(|c| Some(((c.face_index, c.row, c.col), Vector2::from(c.uv?))))
            .collect();
        let off_axis = |v: Vector2<f64>| {
            let a = v.y.atan2(v.x).to_degrees().rem_euclid(90.0);
            a.min(90.0 - a)
        };
        for f in &det.faces {
            for c in &f.corners {
                let Some(t) = gt.get(&(f.face, c.row, c.col)) else {
                    continue;
                };
                if (c.uv - t).norm() > 1.0 {
                    continue;
                }
                // The lines' directions from the truth of a neighbour on each (either side).
                let along = |dr: i64, dc: i64| {
                    [1, -1].iter().find_map(|&s| {
                        let (r, cc) = (c.row as i64 + s * dr, c.col as i64 + s * dc);
                        let n =
                            gt.get(&(f.face, usize::try_from(r).ok()?, usize::try_from(cc).ok()?))?;
                        Some(off_axis(n - t))
                    })
                };
                corners.push(Corner {
                    face: f.face,
                    col: c.col,
                    error: c.uv - t,
                    off_axis_deg: along(0, 1).unwrap_or(90.0).min(along(1, 0).unwrap_or(90.0)),
                });
            }
        }
    }
    (Summary::of(&scores, 0.0, 90.1), corners)
}

fn rms<'a>(errors: impl Iterator<Item = &'a Corner>) -> (f64, usize) {
    let (sq, n) = errors.fold((0.0, 0), |(s, n), c| (s + c.error.norm_squared(), n + 1));
    ((sq / n.max(1) as f64).sqrt(), n)
}

fn case(name: &str) -> cases::Case {
    cases::cases(6)
        .into_iter()
        .find(|c| c.name == name)
        .unwrap()
}

fn cache(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

/// One sheet wrapped around a cube's edge (k1 −0.3): the lattice runs across the fold, and the
/// curvature correction measured on it used to bend the corners next to the fold by up to 0.43 px
/// (RMS 0.16 px on that column, 0.076 px over all). Fitted again on their own face's lattice, every
/// column is at the accuracy of the face's middle.
#[test]
fn corners_next_to_a_fold_are_as_accurate_as_the_rest() {
    let case = case("wrapped-cube");
    // Views 4 and 5 are not found yet (the right face at 65–69°; see tests/detect_cases.rs).
    let (s, corners) = run(&case, 0..4, &cache("detect_cases"));
    eprintln!("wrapped-cube: {s}");
    assert_eq!((s.faces, s.found, s.mislabelled), (8, 8, 0), "{s}");
    assert!(s.rms_px <= 0.02, "{s}");
    // The fold is at the last column of "front" (face 0) and the first of "right".
    let cols = case.rig.faces[0].cols;
    for steps in 0..3 {
        let (r, n) = rms(corners
            .iter()
            .filter(|c| (if c.face == 0 { cols - 1 - c.col } else { c.col }) == steps));
        eprintln!("{steps} steps from the fold: {n} corners, RMS {r:.4} px");
        assert_eq!(n, 80);
        assert!(r <= 0.02, "{steps} steps from the fold: RMS {r:.4} px");
    }
    let max = corners.iter().map(|c| c.error.norm()).fold(0.0, f64::max);
    assert!(max <= 0.08, "largest error {max:.4} px");
}

/// A board filling the frame (k1 −0.1, squares of 60–70 px, its lines within a few degrees of the
/// pixel axes): the case set's renders (4 × 4 sub-samples per edge pixel) put an edge parallel to a
/// pixel axis on a quarter-pixel grid, an error of the render itself that no fit of the image can
/// remove; the same views rendered with 16 × 16 sub-samples show what the detector reaches.
#[test]
fn a_board_filling_the_frame_is_within_0_02_px_of_an_exact_render() {
    let coarse = case("fill");
    let mut fine = coarse.clone();
    fine.settings.supersample = 16;
    let (s4, c4) = run(&coarse, 0..2, &cache("detect_cases"));
    let (s16, c16) = run(&fine, 0..2, &cache("detect_accuracy_ss16"));
    eprintln!("fill, 4×4 sub-samples: {s4}\nfill, 16×16 sub-samples: {s16}");
    for s in [s4, s16] {
        assert_eq!((s.faces, s.found, s.mislabelled), (2, 2, 0), "{s}");
    }
    assert!(s16.rms_px <= 0.02, "{s16}");
    // The render's share: the error sits on the corners whose lines run along the pixel axes, and
    // goes with finer sub-sampling.
    let near = |c: &&Corner| c.off_axis_deg < 0.5;
    let (r4, n4) = rms(c4.iter().filter(near));
    let (r16, n16) = rms(c16.iter().filter(near));
    let (far4, _) = rms(c4.iter().filter(|c| !near(c)));
    eprintln!(
        "lines < 0.5° off the pixel axes: {n4} corners, RMS {r4:.4} px (4×4), {r16:.4} px (16×16); the others {far4:.4} px (4×4)"
    );
    assert!(n4 >= 50 && n4 == n16);
    assert!(
        r4 > 0.025 && r4 > 2.0 * far4 && r16 <= 0.02,
        "{r4} {far4} {r16}"
    );
}
