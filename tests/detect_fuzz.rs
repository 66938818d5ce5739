//! The detector fed random and adversarial frames that contain no rig face: uniform frames, noise,
//! stripes, fine checkerboards, checkerboards of sizes no face has (several scales and rotations),
//! salt and pepper, tiny and huge frames, and a proptest over random sizes and content. Every frame
//! goes through `detect` with the cube rig and with the flat 9×6 board. Nothing may panic, frames
//! under `MIN_SIDE` must fail with `TooSmall`, and every call must end within a generous bound.
//!
//! The rule on labels: **never a label that changes the intrinsics or a 3D rig's geometry.** So no
//! face may be reported on the cube rig (a face of a 3D rig placed on the wrong face, or shifted
//! against the others, changes its geometry), and none on the flat board either, with one exception
//! that changes nothing: a complete grid of the board's size whose extent is unproven only because
//! the frame border cuts the next line or the next line is an incomplete line of corner-like
//! junctions (the paper's edge on a two-tone desk), or whose orientation a 180°-symmetric board
//! leaves open (`FaceDetection::ambiguous_pose`). If the pattern in the
//! frame is a bigger checkerboard, its labels are shifted within its plane, which moves that view's
//! pose and nothing else: a planar view constrains the camera through its homography up to a
//! similarity of the plane. Such a face must be the whole board (every corner, one lattice) and its
//! pose is flagged; mirror labellings are impossible (handedness), broken lattices fail the rule. Each call's time is printed (`cargo test --test detect_fuzz -- --nocapture`).
//! Every random generator is seeded. Grids a frame leaves out and a known camera settles
//! (`detect::settle`) need a proven face in the frame, which none of these frames has; the same
//! rule holds them, scored against ground truth on the cube cut by the frame border and the
//! wrapped sheet (tests/detect_settle.rs).
//!
//! What this fuzzing found, each kept as a test with its recipe: frames (fine stripes, dense
//! checkerboards) that took seconds, and boards cut by the frame border to a face's size, labelled as
//! that face until the labeller checked that the board ends where the grid does
//! ([`boards_cut_by_the_border_are_not_labelled_as_faces`]; the proptest now cuts boards too).

#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::print_stderr
)]

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;
use std::time::{Duration, Instant};

use cubecal::detect::{CornerFinder, DetectError, FrameDetection, MIN_SIDE, detect};
use cubecal::rig::Rig;
use image::{GrayImage, Luma};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Time allowed for one `detect` call (test profile, shared 2-core machine).
const BOUND: Duration = Duration::from_secs(2);
/// Time allowed for one `detect` call on the huge frame.
const HUGE_BOUND: Duration = Duration::from_secs(5);

const RIGS: [&str; 2] = ["cube_outside.toml", "opencv_board_9x6.toml"];
/// Inner corners (cols, rows) of the faces of [`RIGS`] (checked against the files by
/// [`checkerboards_of_the_wrong_size`]).
const FACE_SIZES: [(u32, u32); 4] = [(9, 8), (8, 7), (7, 6), (9, 6)];

fn rigs() -> Vec<Rig> {
    RIGS.iter()
        .map(|name| {
            let p = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("fixtures/rigs")
                .join(name);
            Rig::load(&p).unwrap().0
        })
        .collect()
}

/// Runs frames through the detector with every rig; collects failures instead of stopping at the
/// first, so that one run reports every bad case.
struct Fuzz {
    rigs: Vec<Rig>,
    finder: CornerFinder,
    failures: Vec<String>,
}

impl Fuzz {
    fn new() -> Fuzz {
        Fuzz {
            rigs: rigs(),
            finder: CornerFinder::new().unwrap(),
            failures: Vec::new(),
        }
    }

    /// Detect in `img` with every rig; a frame under `MIN_SIDE` must be `TooSmall`, any other must
    /// give no face. Returns the detections (for callers that look at the rejections).
    fn check(&mut self, case: &str, img: &GrayImage, bound: Duration) -> Vec<FrameDetection> {
        let mut found = Vec::new();
        for k in 0..self.rigs.len() {
            let rig = &self.rigs[k];
            let started = Instant::now();
            let result = catch_unwind(AssertUnwindSafe(|| detect(&mut self.finder, img, rig)));
            let t = started.elapsed();
            let (w, h) = img.dimensions();
            let label = format!("{case} {w}×{h} rig '{}'", rig.name);
            let mut fail = |why: String| self.failures.push(format!("{label}: {why}"));
            match result {
                Err(panic) => {
                    let msg = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    fail(format!("panicked: {msg}"));
                    // The finder's scratch state is unknown after a panic.
                    self.finder = CornerFinder::new().unwrap();
                }
                Ok(Err(DetectError::TooSmall { width, height })) => {
                    eprintln!("{label}: TooSmall in {:.1} ms", t.as_secs_f64() * 1e3);
                    if (width, height) != (w, h) || (w >= MIN_SIDE && h >= MIN_SIDE) {
                        fail(format!("unexpected TooSmall {{ {width}, {height} }}"));
                    }
                }
                Ok(Err(e)) => fail(format!("error: {e}")),
                Ok(Ok(det)) => {
                    eprintln!(
                        "{label}: {} faces, {} rejections in {:.1} ms",
                        det.faces.len(),
                        det.rejected.len(),
                        t.as_secs_f64() * 1e3
                    );
                    if w < MIN_SIDE || h < MIN_SIDE {
                        fail("a frame under MIN_SIDE was accepted".into());
                    }
                    // The one harmless label (module doc): a one-face rig's whole board, extent
                    // unproven only at the frame border, pose flagged.
                    let harmless = |f: &cubecal::detect::label::FaceDetection| {
                        let face = &rig.faces[f.face];
                        rig.faces.len() == 1
                            && f.ambiguous_pose.is_some()
                            && f.corners.len() == face.rows * face.cols
                    };
                    for f in det.faces.iter().filter(|f| harmless(f)) {
                        eprintln!(
                            "{label}: flat board labelled with its pose flagged: {:?}",
                            f.ambiguous_pose
                        );
                    }
                    if det.faces.iter().any(|f| !harmless(f)) {
                        let names: Vec<String> = det
                            .faces
                            .iter()
                            .map(|f| {
                                format!(
                                    "'{}' ({} corners, (0,0) at {:.1?})",
                                    rig.faces[f.face].name,
                                    f.corners.len(),
                                    f.corners[0].uv
                                )
                            })
                            .collect();
                        fail(format!("reported faces {}", names.join(", ")));
                    }
                    if (det.width, det.height) != (w, h) {
                        fail(format!("size reported as {}×{}", det.width, det.height));
                    }
                    found.push(det);
                }
            }
            if t > bound {
                self.failures.push(format!(
                    "{label}: took {:.0} ms (bound {:.0} ms)",
                    t.as_secs_f64() * 1e3,
                    bound.as_secs_f64() * 1e3
                ));
            }
        }
        found
    }

    fn finish(self) {
        assert!(
            self.failures.is_empty(),
            "{} failures:\n{}",
            self.failures.len(),
            self.failures.join("\n")
        );
    }
}

fn uniform_noise(w: u32, h: u32, seed: u64) -> GrayImage {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    GrayImage::from_fn(w, h, |_, _| Luma([rng.random()]))
}

fn gaussian_noise(w: u32, h: u32, mean: f64, sigma: f64, seed: u64) -> GrayImage {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(mean, sigma).unwrap();
    GrayImage::from_fn(w, h, |_, _| {
        Luma([normal.sample(&mut rng).round().clamp(0.0, 255.0) as u8])
    })
}

fn salt_and_pepper(w: u32, h: u32, fraction: f64, seed: u64) -> GrayImage {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    GrayImage::from_fn(w, h, |_, _| {
        let v = if rng.random_bool(fraction) {
            if rng.random_bool(0.5) { 0 } else { 255 }
        } else {
            128
        };
        Luma([v])
    })
}

/// Black and white stripes of `period` px (one black and one white band), across direction
/// `angle_deg` (0: vertical stripes, 90: horizontal).
fn stripes(w: u32, h: u32, period: f64, angle_deg: f64) -> GrayImage {
    let (s, c) = angle_deg.to_radians().sin_cos();
    GrayImage::from_fn(w, h, |x, y| {
        let t = (f64::from(x) * c + f64::from(y) * s) / period;
        Luma([if t.rem_euclid(1.0) < 0.5 { 20 } else { 235 }])
    })
}

/// A checkerboard filling the frame, squares of `square` px.
fn fine_checkerboard(w: u32, h: u32, square: u32) -> GrayImage {
    GrayImage::from_fn(w, h, |x, y| {
        Luma([if (x / square + y / square).is_multiple_of(2) {
            20
        } else {
            235
        }])
    })
}

/// A printed board with `cols × rows` inner corners, squares of `square` px and a one-square white
/// margin, turned by `angle_deg` about the frame centre, on a mid-grey background; 3×3 supersampled.
/// Panics unless the whole board (margin included) is inside the frame.
fn board(w: u32, h: u32, cols: u32, rows: u32, square: f64, angle_deg: f64) -> GrayImage {
    let (ew, eh) = board_extent(cols, rows, square, angle_deg);
    assert!(
        ew + 4.0 < f64::from(w) && eh + 4.0 < f64::from(h),
        "{cols}×{rows} board of {square} px squares at {angle_deg}° does not fit {w}×{h}"
    );
    let centre = ((f64::from(w) - 1.0) / 2.0, (f64::from(h) - 1.0) / 2.0);
    board_at(w, h, cols, rows, square, angle_deg, centre)
}

/// Size (px) of the axis-aligned box around a `cols × rows` board (margin included) turned by
/// `angle_deg`.
fn board_extent(cols: u32, rows: u32, square: f64, angle_deg: f64) -> (f64, f64) {
    let (bw, bh) = (f64::from(cols + 3) * square, f64::from(rows + 3) * square);
    let (s, c) = angle_deg.to_radians().sin_cos();
    (bw * c.abs() + bh * s.abs(), bw * s.abs() + bh * c.abs())
}

/// As [`board`], centred on `centre` (pixel coordinates), and wherever that puts it: parts outside
/// the frame are cut off. Inner corner `(r, c)` of an unturned board is at
/// `centre + ((c + 2 − (cols + 3)/2)·square, (r + 2 − (rows + 3)/2)·square)`.
fn board_at(
    w: u32,
    h: u32,
    cols: u32,
    rows: u32,
    square: f64,
    angle_deg: f64,
    centre: (f64, f64),
) -> GrayImage {
    let (bw, bh) = (f64::from(cols + 3) * square, f64::from(rows + 3) * square);
    let (s, c) = angle_deg.to_radians().sin_cos();
    const N: u32 = 3;
    GrayImage::from_fn(w, h, |x, y| {
        let mut sum = 0.0;
        for sy in 0..N {
            for sx in 0..N {
                // Sample points inside the pixel (pixel centres at integer coordinates).
                let px = f64::from(x) - 0.5 + (f64::from(sx) + 0.5) / f64::from(N) - centre.0;
                let py = f64::from(y) - 0.5 + (f64::from(sy) + 0.5) / f64::from(N) - centre.1;
                // Board coordinates: rotate back, origin at the board's top-left outer edge.
                let bx = c * px + s * py + bw / 2.0;
                let by = -s * px + c * py + bh / 2.0;
                let v = if bx < 0.0 || by < 0.0 || bx >= bw || by >= bh {
                    120.0
                } else {
                    let (i, j) = ((bx / square).floor() as i64, (by / square).floor() as i64);
                    let in_pattern =
                        i >= 1 && j >= 1 && i <= i64::from(cols) + 1 && j <= i64::from(rows) + 1;
                    if in_pattern && (i + j) % 2 == 0 {
                        20.0
                    } else {
                        235.0
                    }
                };
                sum += v;
            }
        }
        Luma([(sum / f64::from(N * N)).round() as u8])
    })
}

#[test]
fn uniform_frames() {
    let mut fuzz = Fuzz::new();
    for (name, v) in [("black", 0), ("white", 255), ("mid grey", 128)] {
        let dets = fuzz.check(name, &GrayImage::from_pixel(640, 480, Luma([v])), BOUND);
        for d in dets {
            assert!(
                d.rejected
                    .iter()
                    .any(|r| r.reason.contains("no checkerboard grid")),
                "{name}: {:?}",
                d.rejected
            );
        }
    }
    fuzz.finish();
}

#[test]
fn noise_frames() {
    let mut fuzz = Fuzz::new();
    for seed in 0..3 {
        fuzz.check(
            &format!("uniform noise seed {seed}"),
            &uniform_noise(640, 480, seed),
            BOUND,
        );
        for sigma in [10.0, 40.0, 90.0] {
            fuzz.check(
                &format!("gaussian noise σ {sigma} seed {seed}"),
                &gaussian_noise(640, 480, 128.0, sigma, seed),
                BOUND,
            );
        }
        for fraction in [0.02, 0.1, 0.3] {
            fuzz.check(
                &format!("salt and pepper {fraction} seed {seed}"),
                &salt_and_pepper(640, 480, fraction, seed),
                BOUND,
            );
        }
    }
    fuzz.finish();
}

/// Stripe frames that take the detector far longer than [`BOUND`] (see
/// [`fine_stripes_are_searched_within_the_time_bound`]); left out of [`stripe_frames`].
const SLOW_STRIPES: [(f64, f64); 8] = [
    (2.0, 30.0),
    (2.0, 45.0),
    (2.0, 135.0),
    (3.0, 30.0),
    (3.0, 45.0),
    (3.0, 135.0),
    (4.0, 0.0),
    (4.0, 90.0),
];

#[test]
fn stripe_frames() {
    let mut fuzz = Fuzz::new();
    for period in [2.0, 3.0, 4.0, 7.0, 16.0, 41.0] {
        for angle in [0.0, 90.0, 45.0, 30.0, 135.0] {
            if SLOW_STRIPES.contains(&(period, angle)) {
                continue;
            }
            fuzz.check(
                &format!("stripes period {period} px at {angle}°"),
                &stripes(640, 480, period, angle),
                BOUND,
            );
        }
    }
    fuzz.finish();
}

/// Fine stripes were slow in both stages of the detector with the `chess-corners` front end (2.8–3.9 s
/// per 640×480 frame in the front end, then 1000–2700 corners and 0.3–9 s of grid assembly); the
/// current front end finds no corner on them (stripes have no saddle points).
#[test]
fn fine_stripes_are_searched_within_the_time_bound() {
    let mut fuzz = Fuzz::new();
    for (period, angle) in SLOW_STRIPES {
        fuzz.check(
            &format!("stripes period {period} px at {angle}°"),
            &stripes(640, 480, period, angle),
            BOUND,
        );
    }
    fuzz.finish();
}

/// Dense checkerboards filling the frame: thousands of corners in one lattice, no face's size. Grid
/// assembly was super-linear (1215 corners 2.1 s; 3640 corners 6.5 s); it now only retries cells near
/// the corners added in the previous pass. The 4 and 6 px squares are below what the front end
/// resolves (no corners); 9–12 px squares give up to ~3600 corners.
#[test]
fn dense_checkerboards_are_searched_within_the_time_bound() {
    let mut fuzz = Fuzz::new();
    fuzz.check(
        "checkerboard of 4 px squares",
        &fine_checkerboard(128, 199, 4),
        BOUND,
    );
    fuzz.check(
        "checkerboard of 6 px squares",
        &fine_checkerboard(300, 300, 6),
        BOUND,
    );
    for square in [9, 10, 12] {
        fuzz.check(
            &format!("640×480 checkerboard of {square} px squares"),
            &fine_checkerboard(640, 480, square),
            BOUND,
        );
    }
    fuzz.check(
        "1280×960 checkerboard of 10 px squares",
        &fine_checkerboard(1280, 960, 10),
        HUGE_BOUND,
    );
    fuzz.finish();
}

/// A checkerboard larger than a face, cut by the frame's border so that exactly a face's number of
/// inner corners is visible, was labelled as that face: the labeller checked the inner squares'
/// colours but not that the board ends where the grid does. On a real rig this mislabels, for
/// example, a partly visible bigger board (or a larger face cut down to a smaller face's size) with
/// wrong 3D points. The labeller now drops a grid unless, one lattice step beyond each of its sides,
/// the image shows no corner (`label`'s module doc) — except, on a rig of one face, a grid cut only by
/// the frame border, labelled with its pose flagged (the module doc's rule: such a shift changes the
/// view's pose, never the intrinsics). The cube rig must still drop every one of these frames.
#[test]
fn boards_cut_by_the_border_are_not_labelled_as_faces() {
    let mut fuzz = Fuzz::new();
    let mut cases: Vec<(&str, GrayImage)> = vec![
        // Found by the proptest (w 185, h 154, kind 3, seed 15697626356347620307 in the frame-filling
        // checkerboard generator it had then): 18 px squares filling the frame show 9×8 inner corners.
        (
            "checkerboard of 18 px squares filling the frame",
            fine_checkerboard(185, 154, 18),
        ),
        // A 10×9 board, 30 px squares, whose last column and row of inner corners are outside the
        // frame: 9×8 visible, the size of the cube's 'top'.
        (
            "10×9 board, last column and row cut off",
            board_at(640, 480, 10, 9, 30.0, 0.0, (513.0, 368.0)),
        ),
        // A 10×7 board cut to 9×6, the OpenCV board's size.
        (
            "10×7 board, last column and row cut off",
            board_at(640, 480, 10, 7, 30.0, 0.0, (513.0, 398.0)),
        ),
        // A 10×9 board cut by the left and top borders instead.
        (
            "10×9 board, first column and row cut off",
            board_at(640, 480, 10, 9, 30.0, 0.0, (127.0, 112.0)),
        ),
    ];
    cases.extend(cut_cube_faces().1);
    for (case, img) in &cases {
        let dets = fuzz.check(case, img, BOUND);
        // Each frame must reach the rule with the rig that has a face of the visible grid's size (not
        // fail earlier, e.g. for lack of a complete grid).
        let reasons: Vec<&str> = dets
            .iter()
            .flat_map(|d| d.rejected.iter().map(|r| r.reason.as_str()))
            .collect();
        eprintln!("{case}: {reasons:?}");
        // Reaching the rule: rejected for its extent, or (the flat board only) labelled with its pose
        // flagged for it, which `check` has held to the module doc's exception.
        let flagged = dets
            .iter()
            .any(|d| d.faces.iter().any(|f| f.ambiguous_pose.is_some()));
        if !flagged && !reasons.iter().any(|r| r.contains("grid may continue")) {
            fuzz.failures
                .push(format!("{case}: not rejected for its extent: {reasons:?}"));
        }
    }
    fuzz.finish();
}

/// The cube rig's 'top' (9×8 inner corners) rendered from above, tilted by 35° (perspective) with
/// k1 −0.3, and cut by the frame border to the size of another face: one row and one column cut
/// (8×7, 'side-x' of the cube: the last column and the far, foreshortened row 0) and the two near
/// rows (9×6, the OpenCV board). The camera sees 'side-y' too (at 76°).
/// The uncut frame must give 'top' (so the cut frames fail for the cut alone); it is returned first.
fn cut_cube_faces() -> (GrayImage, Vec<(&'static str, GrayImage)>) {
    use cubecal::camera::{Camera, DistortionModel, Pose};
    use cubecal::detect::score::EvalSet;
    use cubecal::render::{ground_truth, render};
    use nalgebra::{Rotation3, Vector3};

    let rig = &rigs()[0];
    let camera = Camera::pinhole([1280, 960], 900.0, 900.0, 639.5, 479.5)
        .with_distortion(DistortionModel::Brown5, &[-0.3]);
    let settings = EvalSet::Realistic.settings();
    // Camera axes in the rig frame: x along +x, y along −y, looking down −z; then tilted about its x
    // axis so that it sees the top at 35° from the +y side.
    let frontal = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
        1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0,
    ));
    let rotation = Rotation3::from_axis_angle(&Vector3::x_axis(), 35f64.to_radians()) * frontal;
    let centre = Vector3::new(100.0, 100.0, 200.0);
    let eye = centre - rotation.inverse() * Vector3::z() * 330.0;
    let pose = Pose {
        rotation,
        translation: -(rotation * eye),
    };
    let img = render(rig, &camera, &pose, &settings, 0).unwrap();
    let truth = ground_truth(rig, &camera, &pose, &settings, 0);
    let top: Vec<_> = truth.corners.iter().filter(|c| c.face_index == 0).collect();
    assert!(top.iter().all(|c| c.visible), "top not fully visible");
    let mut finder = CornerFinder::new().unwrap();
    let det = detect(&mut finder, &img, rig).unwrap();
    assert!(
        det.faces
            .iter()
            .any(|f| f.face == 0 && f.corners.len() == 72),
        "uncut top not found: {:?}",
        det.rejected
    );
    let scores = cubecal::detect::score::score(rig, &truth, &det);
    assert!(scores.iter().all(|s| s.mislabelled == 0), "{scores:?}");
    // Image extent of one row or column of 'top'.
    let span = |row: Option<usize>, col: Option<usize>, x: bool| {
        let v: Vec<f64> = top
            .iter()
            .filter(|c| row.is_none_or(|r| c.row == r) && col.is_none_or(|k| c.col == k))
            .map(|c| c.uv.unwrap()[usize::from(!x)])
            .collect();
        (
            v.iter().copied().fold(f64::INFINITY, f64::min),
            v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        )
    };
    // Rows run along image x (cols increase rightwards), rows increase upwards (y along −y).
    let (x_last, _) = span(None, Some(8), true);
    let (_, x_before) = span(None, Some(7), true);
    assert!(x_before < x_last);
    let crop_w = (x_before + 0.9 * (x_last - x_before)).round() as u32;
    // Row 0 is the bottom line in the image (the farthest, rows 30 px apart there); cut it: the crop
    // ends above it.
    let (_, y_row1_max) = (0.0, span(Some(1), None, false).1);
    let (y_row0_min, _) = span(Some(0), None, false);
    assert!(y_row1_max < y_row0_min);
    let crop_h = (y_row1_max + 0.9 * (y_row0_min - y_row1_max)).round() as u32;
    let one_each = image::imageops::crop_imm(&img, 0, 0, crop_w, crop_h).to_image();
    // The near rows 6 and 7 (top of the image, rows 42 px apart): cut them, keep the rest.
    let (_, y_row7_max) = span(Some(7), None, false);
    let (y_row6_min, y_row6_max) = span(Some(6), None, false);
    let (y_row5_min, _) = span(Some(5), None, false);
    assert!(y_row7_max < y_row6_min && y_row6_max < y_row5_min);
    let y0 = (y_row6_max + 0.2 * (y_row5_min - y_row6_max)).round() as u32;
    let two_near =
        image::imageops::crop_imm(&img, 0, y0, img.width(), img.height() - y0).to_image();
    let cut = vec![
        (
            "cube 'top' at 35°, k1 −0.3, cut to 8×7 ('side-x')",
            one_each,
        ),
        (
            "cube 'top' at 35°, k1 −0.3, cut to 9×6 (OpenCV board)",
            two_near,
        ),
    ];
    (img, cut)
}

/// `grid::assemble` grew lattices by iterating a `HashMap` (std's randomly seeded hasher), so where
/// corners were ambiguous the grids, and the time, differed from call to call (49–61 grids on 2 px
/// stripes at 45° with the `chess-corners` front end). Replaying a recorded session must give the
/// same detections every time; grids and completion now use ordered maps. The present front end
/// finds no corner on those stripes, so the frames here are ones where it finds many (frame-filling
/// checkerboards, boards cut anywhere, the cube renders): every stage's output — corners, grids,
/// detection — must be identical over repeated calls with one finder and with a fresh one (it held
/// when written, with the present front end and the extent rule of the labeller).
#[test]
fn the_same_frame_gives_the_same_detection() {
    use cubecal::detect::grid;
    let rig = &rigs()[0];
    let mut frames: Vec<(String, GrayImage)> = vec![
        ("stripes 2 px at 45°".into(), stripes(640, 480, 2.0, 45.0)),
        (
            "checkerboard of 5 px squares".into(),
            fine_checkerboard(160, 120, 5),
        ),
        (
            "checkerboard of 9 px squares".into(),
            fine_checkerboard(240, 180, 9),
        ),
    ];
    for seed in 0..12 {
        frames.push((
            format!("random cut board seed {seed}"),
            random_frame(300, 300, 6, seed),
        ));
    }
    let (top, cut) = cut_cube_faces();
    frames.push(("cube 'top' at 35°, k1 −0.3".into(), top));
    frames.extend(cut.into_iter().map(|(n, img)| (n.to_string(), img)));
    let mut finder = CornerFinder::new().unwrap();
    let (mut total_grids, mut total_faces) = (0, 0);
    for (name, img) in &frames {
        let t = Instant::now();
        let corners = finder.find(img).unwrap();
        let t_front = t.elapsed();
        let grids = grid::assemble(&corners);
        let t_grid = t.elapsed() - t_front;
        let t = Instant::now();
        let first = detect(&mut finder, img, rig).unwrap();
        eprintln!(
            "{name}: {} corners ({:.1} ms), {} grids ({:.1} ms), {} faces, {} rejections, detect {:.1} ms",
            corners.len(),
            t_front.as_secs_f64() * 1e3,
            grids.len(),
            t_grid.as_secs_f64() * 1e3,
            first.faces.len(),
            first.rejected.len(),
            t.elapsed().as_secs_f64() * 1e3
        );
        total_grids += grids.len();
        total_faces += first.faces.len();
        for run in 1..4 {
            // Runs 1 and 2 reuse the finder (its scratch buffers), run 3 starts afresh.
            if run == 3 {
                finder = CornerFinder::new().unwrap();
            }
            let again_corners = finder.find(img).unwrap();
            assert_eq!(again_corners, corners, "{name} run {run}: corners differ");
            assert_eq!(
                grid::assemble(&again_corners),
                grids,
                "{name} run {run}: grids differ"
            );
            let again = detect(&mut finder, img, rig).unwrap();
            assert_eq!(
                (&again.faces, &again.rejected),
                (&first.faces, &first.rejected),
                "{name} run {run}: detections differ"
            );
        }
    }
    eprintln!(
        "{total_grids} grids, {total_faces} faces in {} frames",
        frames.len()
    );
    // The frames must exercise grid assembly and labelling, or the test proves nothing (16 grids and
    // two faces when written).
    assert!(
        total_grids >= 12 && total_faces >= 1,
        "only {total_grids} grids and {total_faces} faces in all frames"
    );
}

#[test]
fn fine_checkerboards() {
    let mut fuzz = Fuzz::new();
    for square in 1..=3 {
        fuzz.check(
            &format!("checkerboard of {square} px squares"),
            &fine_checkerboard(640, 480, square),
            BOUND,
        );
    }
    fuzz.finish();
}

/// Whole boards with inner-corner counts that no face of either rig has, including near misses that
/// contain a face's grid (10×9 ⊃ 9×8, 9×7 ⊃ 9×6).
#[test]
fn checkerboards_of_the_wrong_size() {
    let sizes = [(5, 4), (4, 3), (8, 6), (10, 6), (9, 5), (9, 7), (10, 9)];
    let mut faces: Vec<(u32, u32)> = rigs()
        .iter()
        .flat_map(|rig| rig.faces.iter().map(|f| (f.cols as u32, f.rows as u32)))
        .collect();
    faces.sort_unstable();
    let mut expected = FACE_SIZES.to_vec();
    expected.sort_unstable();
    assert_eq!(faces, expected, "FACE_SIZES is out of date");
    for (cols, rows) in sizes {
        assert!(
            !FACE_SIZES.contains(&(cols, rows)) && !FACE_SIZES.contains(&(rows, cols)),
            "{cols}×{rows} is a face size"
        );
    }
    let mut fuzz = Fuzz::new();
    let (mut cases, mut seen) = (0, 0);
    for (cols, rows) in sizes {
        for square in [14.0, 20.0, 28.0] {
            for angle in [0.0, 17.0, 45.0, 98.0] {
                let img = board(800, 600, cols, rows, square, angle);
                let dets = fuzz.check(
                    &format!("{cols}×{rows} board, {square} px squares at {angle}°"),
                    &img,
                    BOUND,
                );
                // The frame must really reach the labeller: its grid is rejected by size.
                for d in &dets {
                    cases += 1;
                    if d.rejected
                        .iter()
                        .any(|r| r.reason.contains("matches no face"))
                    {
                        seen += 1;
                    } else {
                        eprintln!(
                            "  {cols}×{rows} board, {square} px at {angle}°: {:?}",
                            d.rejected
                        );
                    }
                }
            }
        }
    }
    eprintln!("wrong-size boards rejected by size in {seen} of {cases} detections");
    // All of them when written (squares of 10 px were not found at all, hence 14 px and up).
    assert!(seen * 10 >= cases * 9, "{seen} of {cases}");
    fuzz.finish();
}

#[test]
fn tiny_frames() {
    let mut fuzz = Fuzz::new();
    for (w, h) in [
        (1, 1),
        (1, 1000),
        (1000, 1),
        (2, 2),
        (31, 31),
        (31, 1000),
        (1000, 31),
        (32, 31),
        (32, 32),
        (33, 40),
        (40, 33),
        (64, 32),
    ] {
        fuzz.check("noise", &uniform_noise(w, h, u64::from(w * h)), BOUND);
        fuzz.check("grey", &GrayImage::from_pixel(w, h, Luma([128])), BOUND);
        fuzz.check("2 px checkerboard", &fine_checkerboard(w, h, 2), BOUND);
        fuzz.check("7 px checkerboard", &fine_checkerboard(w, h, 7), BOUND);
    }
    fuzz.finish();
}

#[test]
fn huge_noisy_frame() {
    let mut fuzz = Fuzz::new();
    fuzz.check(
        "mid grey with gaussian noise σ 12",
        &gaussian_noise(6000, 4000, 128.0, 12.0, 7),
        HUGE_BOUND,
    );
    fuzz.finish();
}

/// Random content for the proptest: picked by `kind` from `seed`.
fn random_frame(w: u32, h: u32, kind: u8, seed: u64) -> GrayImage {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    match kind {
        0 => uniform_noise(w, h, seed),
        1 => GrayImage::from_pixel(w, h, Luma([rng.random()])),
        // Stripes of 5 px or more: finer ones are slow (see
        // `fine_stripes_are_searched_within_the_time_bound`).
        2 => stripes(
            w,
            h,
            rng.random_range(5.0..40.0),
            rng.random_range(0.0..180.0),
        ),
        // A whole board of a size no face has, at a random scale, angle and place, entirely inside
        // the frame (squares under 4 px are not found).
        3 => {
            let (cols, rows) = loop {
                let (c, r) = (rng.random_range(2..=12), rng.random_range(2..=12));
                if !FACE_SIZES.contains(&(c, r)) && !FACE_SIZES.contains(&(r, c)) {
                    break (c, r);
                }
            };
            let angle = rng.random_range(0.0..180.0);
            let (ew, eh) = board_extent(cols, rows, 1.0, angle);
            let largest = ((f64::from(w) - 4.0) / ew).min((f64::from(h) - 4.0) / eh);
            if largest < 4.0 {
                return uniform_noise(w, h, seed);
            }
            let square = rng.random_range(4.0..=largest.min(30.0));
            let (ew, eh) = (ew * square, eh * square);
            let cx = rng.random_range(ew / 2.0..=f64::from(w) - 1.0 - ew / 2.0);
            let cy = rng.random_range(eh / 2.0..=f64::from(h) - 1.0 - eh / 2.0);
            board_at(w, h, cols, rows, square, angle, (cx, cy))
        }
        // A board of a size no face has, at a random scale and angle, centred anywhere in the frame:
        // often cut by the border, sometimes to a face's size (see
        // `boards_cut_by_the_border_are_not_labelled_as_faces`).
        6 => {
            let (cols, rows) = loop {
                let (c, r) = (rng.random_range(2..=14), rng.random_range(2..=14));
                if !FACE_SIZES.contains(&(c, r)) && !FACE_SIZES.contains(&(r, c)) {
                    break (c, r);
                }
            };
            let square = rng.random_range(4.0..=30.0);
            let angle = rng.random_range(0.0..180.0);
            let cx = rng.random_range(0.0..f64::from(w));
            let cy = rng.random_range(0.0..f64::from(h));
            board_at(w, h, cols, rows, square, angle, (cx, cy))
        }
        // A checkerboard filling the frame with squares too small to be found (1 or 2 px).
        5 => fine_checkerboard(w, h, rng.random_range(1..=2)),
        // Random axis-aligned blocks of random grey: many T- and L-junctions, few X-corners.
        _ => {
            let mut img = GrayImage::from_pixel(w, h, Luma([rng.random()]));
            for _ in 0..rng.random_range(1..40) {
                let (x0, y0) = (rng.random_range(0..w), rng.random_range(0..h));
                let (bw, bh) = (rng.random_range(1..=w), rng.random_range(1..=h));
                let v = Luma([rng.random()]);
                for y in y0..(y0 + bh).min(h) {
                    for x in x0..(x0 + bw).min(w) {
                        img.put_pixel(x, y, v);
                    }
                }
            }
            img
        }
    }
}

proptest! {
    // Seeded so a run is reproducible (6000 unseeded cases also passed when this was written).
    #![proptest_config(ProptestConfig {
        cases: 300,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0xdec7_f022),
        ..ProptestConfig::default()
    })]

    #[test]
    fn random_sizes_and_content(w in 1u32..300, h in 1u32..300, kind in 0u8..7, seed in any::<u64>()) {
        let img = random_frame(w, h, kind, seed);
        let mut fuzz = Fuzz::new();
        fuzz.check(&format!("random kind {kind} seed {seed}"), &img, BOUND);
        prop_assert!(fuzz.failures.is_empty(), "{}", fuzz.failures.join("\n"));
    }
}
