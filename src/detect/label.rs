//! Labelling: which rig face a detected grid is, and which of its corners is `(0, 0)`.
//!
//! Never guessed — a grid is dropped with a reason unless every step is clear:
//! 1. **Handedness.** A face seen from its printed side shows `col_dir` and `row_dir` with a fixed
//!    orientation in the image (`col × row` points toward the camera, so in image coordinates with y
//!    down the 2D cross product of the column and row steps is negative). A grid with the other
//!    orientation is transposed; mirror-image labellings are thereby impossible.
//! 2. **Size.** The (complete) grid's rows × cols must equal a face's, directly or rotated by 90°.
//! 3. **Extent.** The size only means something if the board ends where the grid does: a bigger board
//!    (or a bigger face) cut by the frame border, or a fragment of a bigger lattice, can show exactly a
//!    face's number of corners. So on each of the grid's four sides, at the position one lattice step
//!    beyond each corner of the outermost line — extrapolated along its row or column from the three
//!    outermost corners (quadratic: it follows perspective and lens curvature, as in
//!    [`super::complete`]) — the image must show that there is no corner:
//!    * a position is **empty** when the two squares half a step further out differ by at most
//!      [`END_UNIFORMITY`] of the two half a step back (the board's outer squares, which must differ by
//!      [`MIN_COLOUR_CONTRAST`]): a continuing board would show two squares of opposite colours there,
//!      a board's end shows its uniform margin. Otherwise the X-junction fit of [`super::refine`] is
//!      run there, and no fit, or a fit unlike the grid's corners (residual and contrast against the
//!      medians of the next line inward, with the thresholds [`super::complete`] uses to accept a
//!      recovered corner), makes the position empty too — unless the squares beyond look checkered
//!      (opposite difference, at least [`CONTINUED_CONTRAST`] of the inner one): a fit that fails
//!      there may have missed a real corner (the grid stopped growing precisely because fits failed,
//!      e.g. at a foreshortened far end), so the position proves nothing;
//!    * a fit like the grid's corners at any position drops the grid (it may continue);
//!    * positions outside the image, or whose fit window the border clips (the fit refuses it),
//!      prove nothing;
//!    * each side needs [`MIN_EMPTY_BEYOND`] empty positions, else the grid is dropped: "grid may
//!      continue beyond the frame border" (or "beyond its side"). A board is a rectangle, so a line
//!      of corners either continues along the whole side or not at all, and two positions seen empty
//!      prove the side without needing the whole next line inside the frame (fully visible boards
//!      often have it partly outside).
//!
//!    The position beyond a cube face's outermost line is on the face's own margin (12 mm margin,
//!    16 mm squares: 0.75 step), never on the neighbouring face, so faces meeting at the cube's
//!    edges keep their proof. Measured: on the realistic and hard synthetic sets (24 frames each,
//!    k1 −0.1 / −0.3, faces up to 90°) every position beyond every face found is empty by the
//!    colour test alone and no face is lost (realistic 52/53 faces < 75°, hard 32/38, as before);
//!    on the 26 OpenCV sample images every board is kept, but the printed board's white margin is
//!    narrower than half a square, so the samples beyond fall on its dark rim or the background and
//!    320 positions reach the fit: 18 clipped, 111 fits all unlike the grid's corners (residual at
//!    least 2.4 times the threshold), 191 failed fits; 83 of the positions are undecided (the
//!    background looks checkered as often as not). The fewest empty positions on a side is 2
//!    (left03.jpg, whose next line is partly outside the image), 3 on four more sides, and the next
//!    line is partly outside the image or too close to its border in 11 images. The check costs
//!    0.2–0.4 ms per frame.
//! 4. **Orientation.** For a board that is not 180°-symmetric, the two remaining labellings predict
//!    opposite colours for every square: the mean intensity of the squares predicted white must exceed
//!    that of the squares predicted black by a clear margin, or the grid is dropped.
//! 5. **Rigid geometry.** With two or more faces, a wrong labelling does not fit one camera: the
//!    normalised DLT on all labelled corners must fit clearly better than with any single face's
//!    orientation reversed ([`GEOMETRY_MARGIN`]), or the frame's labelling is dropped.
//!
//! Grids that fail the size or extent steps (partially visible faces, incomplete grids) are not
//! labelled by their own evidence: [`super::place`] tries to place them through the rig geometry of
//! the complete faces found here, and reports the ones it cannot place as rejected.

use image::GrayImage;
use nalgebra::{Matrix3x4, Vector2, Vector3};

use super::complete::{Completed, like_grid, median};
use super::grid::MIN_LINES;
use super::place::{Partial, place};
use super::refine::{self, RefineFailure};
use crate::calib::linear::{COPLANAR_TOLERANCE, dlt, relative_thickness};
use crate::rig::{Rig, SquareColour};

/// Mean white-minus-black square intensity (grey levels) needed for an orientation to count as decided.
pub const MIN_COLOUR_CONTRAST: f64 = 10.0;
/// With several faces, the chosen labelling's DLT RMS must be this many times smaller than any
/// alternative's.
pub const GEOMETRY_MARGIN: f64 = 3.0;
/// Fewest positions one step beyond each side of a grid that must show no corner (inside the image,
/// fit window unclipped) for the grid's extent to count as proven.
pub const MIN_EMPTY_BEYOND: usize = 2;
/// One step beyond a grid's side, the two squares half a step further out may differ by at most this
/// fraction of the two inside for the board's end to be clear without a corner fit.
pub const END_UNIFORMITY: f64 = 0.3;
/// Squares beyond a grid's side whose difference has the opposite sign of the outer squares' and at
/// least this fraction of it look like a continuing board.
pub const CONTINUED_CONTRAST: f64 = 0.5;

/// One labelled corner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LabelledCorner {
    pub row: usize,
    pub col: usize,
    pub xyz: Vector3<f64>,
    pub uv: Vector2<f64>,
    /// Estimated standard deviation of each coordinate of `uv` (px), from the refinement fit.
    pub sigma_px: f64,
}

/// A face found in the frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceDetection {
    pub face: usize,
    pub corners: Vec<LabelledCorner>,
    /// White-minus-black mean intensity that decided the orientation (grey levels).
    pub colour_contrast: f64,
}

/// Why a grid (or the frame) was not used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rejection {
    pub reason: String,
}

/// A grid with local indices mapped to a face: `cell(row, col)` of the face is the grid's
/// `index(row, col)`.
#[derive(Debug, Clone, Copy)]
struct Mapping {
    face: usize,
    /// 0..4: number of quarter turns applied to the handedness-corrected grid.
    turns: u8,
}

pub(super) fn mean_square_intensity(img: &GrayImage, quad: [Vector2<f64>; 4]) -> Option<f64> {
    let c = (quad[0] + quad[1] + quad[2] + quad[3]) / 4.0;
    // Average a small neighbourhood a third of the way to each corner.
    let mut sum = 0.0;
    let mut n = 0.0;
    for q in &quad {
        let p = c + (q - c) * 0.3;
        let (x, y) = (p.x.round(), p.y.round());
        if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
            return None;
        }
        sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
        n += 1.0;
    }
    let (x, y) = (c.x.round(), c.y.round());
    if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
        return None;
    }
    sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
    Some(sum / (n + 1.0))
}

/// The face indices that occur more than once.
pub(super) fn repeated(faces: impl Iterator<Item = usize>) -> Vec<usize> {
    let mut faces: Vec<usize> = faces.collect();
    faces.sort_unstable();
    let mut dup: Vec<usize> = faces
        .windows(2)
        .filter(|w| w[0] == w[1])
        .map(|w| w[0])
        .collect();
    dup.dedup();
    dup
}

/// Mean intensities of the squares predicted white and black by a labelling.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct ColourSums {
    white: f64,
    n_white: usize,
    black: f64,
    n_black: usize,
}

impl ColourSums {
    pub(super) fn add(&mut self, colour: SquareColour, intensity: f64) {
        match colour {
            SquareColour::White => {
                self.white += intensity;
                self.n_white += 1;
            }
            SquareColour::Black => {
                self.black += intensity;
                self.n_black += 1;
            }
        }
    }

    /// White-minus-black mean intensity (`None` unless both colours were seen).
    pub(super) fn contrast(&self) -> Option<f64> {
        (self.n_white > 0 && self.n_black > 0)
            .then(|| self.white / self.n_white as f64 - self.black / self.n_black as f64)
    }
}

/// A complete grid as a dense `rows × cols` array of image points (with their σ), handedness-corrected.
#[derive(Debug, Clone)]
struct Dense {
    rows: usize,
    cols: usize,
    uv: Vec<Vector2<f64>>,
    sigma: Vec<f64>,
}

impl Dense {
    fn at(&self, r: usize, c: usize) -> Vector2<f64> {
        self.uv[r * self.cols + c]
    }

    /// A `rows × cols` grid whose cell (r, c) is this grid's `source(r, c)`.
    fn remapped(
        &self,
        rows: usize,
        cols: usize,
        source: impl Fn(usize, usize) -> (usize, usize),
    ) -> Dense {
        let mut uv = Vec::with_capacity(self.uv.len());
        let mut sigma = Vec::with_capacity(self.uv.len());
        for r in 0..rows {
            for c in 0..cols {
                let (r0, c0) = source(r, c);
                uv.push(self.uv[r0 * self.cols + c0]);
                sigma.push(self.sigma[r0 * self.cols + c0]);
            }
        }
        Dense {
            rows,
            cols,
            uv,
            sigma,
        }
    }

    fn transposed(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (c, r))
    }

    /// Rotate the labelling by a quarter turn (keeps handedness): new (r, c) = old (rows − 1 − c, r).
    fn quarter_turn(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (self.rows - 1 - c, r))
    }

    fn turned(&self, turns: u8) -> Dense {
        let mut d = self.clone();
        for _ in 0..turns {
            d = d.quarter_turn();
        }
        d
    }

    /// Mean 2D cross product of column and row steps (negative for the rig's handedness).
    fn handedness(&self) -> f64 {
        let mut s = 0.0;
        for r in 0..self.rows - 1 {
            for c in 0..self.cols - 1 {
                let p = self.at(r, c);
                let a = self.at(r, c + 1) - p;
                let b = self.at(r + 1, c) - p;
                s += a.x * b.y - a.y * b.x;
            }
        }
        s
    }
}

/// Label the grids of one frame against the rig.
pub fn label(
    img: &GrayImage,
    rig: &Rig,
    grids: &[Completed],
) -> (Vec<FaceDetection>, Vec<Rejection>) {
    let mut rejected = Vec::new();
    let mut found: Vec<(FaceDetection, Dense, Mapping)> = Vec::new();
    let mut partials = Vec::new();
    for g in grids {
        if g.count() == 0 {
            rejected.push(Rejection {
                reason: "a lattice of X-corners was found but none of its corners fits a checkerboard corner"
                    .into(),
            });
            continue;
        }
        if g.count() != g.rows * g.cols || g.rows < MIN_LINES || g.cols < MIN_LINES {
            let reason = format!(
                "incomplete grid ({} of {}×{} corners)",
                g.count(),
                g.rows,
                g.cols
            );
            partials.push(Partial::new(g, reason));
            continue;
        }
        let mut dense = Dense {
            rows: g.rows,
            cols: g.cols,
            uv: g.cells.iter().flatten().map(|f| f.uv).collect(),
            sigma: g.cells.iter().flatten().map(|f| f.sigma_px).collect(),
        };
        if dense.handedness() > 0.0 {
            dense = dense.transposed();
        }
        // Candidate (face, turns) by size.
        let mut candidates = Vec::new();
        for (fi, f) in rig.faces.iter().enumerate() {
            for turns in 0..4u8 {
                let (r, c) = if turns % 2 == 0 {
                    (dense.rows, dense.cols)
                } else {
                    (dense.cols, dense.rows)
                };
                if (r, c) == (f.rows, f.cols) {
                    candidates.push(Mapping { face: fi, turns });
                }
            }
        }
        if candidates.is_empty() {
            let reason = format!(
                "{}×{} grid matches no face of rig '{}'",
                dense.rows, dense.cols, rig.name
            );
            partials.push(Partial::new(g, reason));
            continue;
        }
        if let Err(reason) = check_extent(img, &dense) {
            partials.push(Partial::new(g, reason));
            continue;
        }
        // Orientation by square colours, per candidate face.
        let mut best: Option<(Mapping, f64, Dense)> = None;
        let mut ambiguous = false;
        let mut faces_seen: Vec<usize> = candidates.iter().map(|m| m.face).collect();
        faces_seen.dedup();
        if faces_seen.len() > 1 {
            rejected.push(Rejection {
                reason: format!(
                    "{}×{} grid matches several faces ({}): faces of equal size are not told apart yet",
                    dense.rows,
                    dense.cols,
                    faces_seen
                        .iter()
                        .map(|&f| rig.faces[f].name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            });
            continue;
        }
        for m in &candidates {
            let face = &rig.faces[m.face];
            let d = dense.turned(m.turns);
            let mut sums = ColourSums::default();
            let mut ok = true;
            for r in 0..d.rows - 1 {
                for c in 0..d.cols - 1 {
                    let quad = [
                        d.at(r, c),
                        d.at(r, c + 1),
                        d.at(r + 1, c),
                        d.at(r + 1, c + 1),
                    ];
                    let Some(v) = mean_square_intensity(img, quad) else {
                        ok = false;
                        continue;
                    };
                    sums.add(face.square_colour(r + 1, c + 1), v);
                }
            }
            let Some(contrast) = sums.contrast().filter(|_| ok) else {
                continue;
            };
            if face.is_point_symmetric() && best.is_some() {
                ambiguous = true;
            }
            if best.as_ref().is_none_or(|(_, b, _)| contrast > *b) {
                best = Some((*m, contrast, d));
            }
        }
        let Some((mapping, contrast, d)) = best else {
            rejected.push(Rejection {
                reason: "grid touches the image border: square colours cannot be read".into(),
            });
            continue;
        };
        let face = &rig.faces[mapping.face];
        if ambiguous {
            rejected.push(Rejection {
                reason: format!(
                    "face '{}' is 180°-symmetric: its orientation cannot be decided from one face",
                    face.name
                ),
            });
            continue;
        }
        if contrast < MIN_COLOUR_CONTRAST {
            rejected.push(Rejection {
                reason: format!(
                    "face '{}': square colours do not decide the orientation (white − black = {contrast:.1} grey levels)",
                    face.name
                ),
            });
            continue;
        }
        let corners = (0..d.rows)
            .flat_map(|r| (0..d.cols).map(move |c| (r, c)))
            .map(|(r, c)| LabelledCorner {
                row: r,
                col: c,
                xyz: face.corner_xyz(r, c),
                uv: d.at(r, c),
                sigma_px: d.sigma[r * d.cols + c],
            })
            .collect();
        let det = FaceDetection {
            face: mapping.face,
            corners,
            colour_contrast: contrast,
        };
        found.push((det, d, mapping));
    }
    // A face found twice is a contradiction: drop both.
    let dup = repeated(found.iter().map(|(f, _, _)| f.face));
    if !dup.is_empty() {
        found.retain(|(f, _, _)| {
            let keep = !dup.contains(&f.face);
            if !keep {
                rejected.push(Rejection {
                    reason: format!("face '{}' matched by two grids", rig.faces[f.face].name),
                });
            }
            keep
        });
    }
    if found.len() >= 2
        && let Err(reason) = check_geometry(rig, &found)
    {
        rejected.push(Rejection { reason });
        rejected.extend(partials.into_iter().map(|p| Rejection { reason: p.reason }));
        return (Vec::new(), rejected);
    }
    let mut faces: Vec<FaceDetection> = found.into_iter().map(|(f, _, _)| f).collect();
    let (placed, not_placed) = place(img, rig, &faces, partials);
    faces.extend(placed);
    rejected.extend(not_placed);
    (faces, rejected)
}

/// One side of a grid: its outermost line of corners and the lines inside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Side {
    FirstRow,
    LastRow,
    FirstCol,
    LastCol,
}

impl Side {
    const ALL: [Side; 4] = [Side::FirstRow, Side::LastRow, Side::FirstCol, Side::LastCol];

    /// Number of corners along the side.
    fn len(self, d: &Dense) -> usize {
        match self {
            Side::FirstRow | Side::LastRow => d.cols,
            Side::FirstCol | Side::LastCol => d.rows,
        }
    }

    /// Number of lines parallel to the side.
    fn depth(self, d: &Dense) -> usize {
        match self {
            Side::FirstRow | Side::LastRow => d.rows,
            Side::FirstCol | Side::LastCol => d.cols,
        }
    }

    /// Corner `i` along the side on the `k`-th line inward (0: the outermost).
    fn at(self, d: &Dense, k: usize, i: usize) -> Vector2<f64> {
        match self {
            Side::FirstRow => d.at(k, i),
            Side::LastRow => d.at(d.rows - 1 - k, i),
            Side::FirstCol => d.at(i, k),
            Side::LastCol => d.at(i, d.cols - 1 - k),
        }
    }
}

/// Image side (`left`, `right`, `top`, `bottom`) that the outward direction `v` points to most.
fn image_side(v: Vector2<f64>) -> &'static str {
    if v.x.abs() >= v.y.abs() {
        if v.x >= 0.0 { "right" } else { "left" }
    } else if v.y >= 0.0 {
        "bottom"
    } else {
        "top"
    }
}

/// Where the lattice continues one step beyond `side`: for each corner of the outermost line, the
/// position one step further along its lattice line, extrapolated from the outermost three corners of
/// the line (quadratic, so it follows perspective and lens curvature; linear with two).
fn beyond(d: &Dense, side: Side) -> Vec<Vector2<f64>> {
    (0..side.len(d))
        .map(|i| {
            let p0 = side.at(d, 0, i);
            let p1 = side.at(d, 1, i);
            if side.depth(d) >= 3 {
                3.0 * p0 - 3.0 * p1 + side.at(d, 2, i)
            } else {
                2.0 * p0 - p1
            }
        })
        .collect()
}

/// What one step beyond a side of a grid shows.
#[derive(Debug, Clone)]
struct SideBeyond {
    /// Outward direction of the side (mean step from the outermost line to the positions beyond).
    outward: Vector2<f64>,
    /// Positions beyond that are outside the image.
    outside: usize,
    /// Positions beyond inside the image but whose corner fit window is clipped by the border.
    clipped: usize,
    /// Positions beyond with an unclipped window where the fit finds no corner like the grid's.
    empty: usize,
    /// Positions beyond with squares of opposite colours (as on a continuing board) where the fit
    /// finds no corner like the grid's: neither proof nor veto.
    undecided: usize,
    /// Positions beyond where the corner fit found a corner like the grid's.
    corners: Vec<Vector2<f64>>,
    /// Positions beyond (the side's number of corners).
    n: usize,
}

/// Step along a line of points at index `i` (central difference inside, one-sided at the ends).
fn step_at(ps: &[Vector2<f64>], i: usize) -> Vector2<f64> {
    match (i.checked_sub(1).and_then(|j| ps.get(j)), ps.get(i + 1)) {
        (Some(prev), Some(next)) => (next - prev) / 2.0,
        (None, Some(next)) => next - ps[i],
        (Some(prev), None) => ps[i] - prev,
        (None, None) => Vector2::zeros(),
    }
}

/// Mean intensity of the 3×3 pixels around `p`, if they are all inside the image.
fn mean_3x3(img: &GrayImage, p: Vector2<f64>) -> Option<f64> {
    let (x, y) = (p.x.round(), p.y.round());
    if !(x >= 1.0
        && y >= 1.0
        && x + 1.0 < f64::from(img.width())
        && y + 1.0 < f64::from(img.height()))
    {
        return None;
    }
    let (x, y) = (x as u32, y as u32);
    let mut sum = 0.0;
    for yy in y - 1..=y + 1 {
        for xx in x - 1..=x + 1 {
            sum += f64::from(img.get_pixel(xx, yy).0[0]);
        }
    }
    Some(sum / 9.0)
}

/// The squares around `p`, one step beyond a grid's outermost corner (steps `along` the side and
/// `outward`): the intensity difference along the side between the two squares half a step back (the
/// board's outer squares) and between the two half a step beyond. `None` when a sample is outside the
/// image.
fn square_pattern(
    img: &GrayImage,
    p: Vector2<f64>,
    along: Vector2<f64>,
    outward: Vector2<f64>,
) -> Option<(f64, f64)> {
    let at = |s: f64, t: f64| mean_3x3(img, p + along * s + outward * t);
    Some((
        at(0.5, -0.5)? - at(-0.5, -0.5)?,
        at(0.5, 0.5)? - at(-0.5, 0.5)?,
    ))
}

fn look_beyond(img: &GrayImage, d: &Dense, side: Side) -> SideBeyond {
    let ps = beyond(d, side);
    let n = ps.len();
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    let line: Vec<Vector2<f64>> = (0..n).map(|i| side.at(d, 0, i)).collect();
    // What a corner of this lattice looks like here (median contrast and residual): the corners of the
    // line next to the outermost, fitted as complete.rs fits them (their windows stay on the board,
    // where the outermost corners' windows may reach its edge). Only needed when a fit beyond succeeds.
    let mut medians: Option<Option<(f64, f64)>> = None;
    let mut reference = || {
        *medians.get_or_insert_with(|| {
            let inner: Vec<Vector2<f64>> = (0..n).map(|i| side.at(d, 1, i)).collect();
            let (mut contrasts, mut residuals) = (Vec::new(), Vec::new());
            for (i, &p) in inner.iter().enumerate() {
                let across = if side.depth(d) >= 3 {
                    (side.at(d, 2, i) - line[i]) / 2.0
                } else {
                    p - line[i]
                };
                if let Ok(f) = refine::refine(img, p, step_at(&inner, i), across) {
                    contrasts.push(f.contrast);
                    residuals.push(f.residual);
                }
            }
            median(&mut contrasts).zip(median(&mut residuals))
        })
    };
    let mut out = SideBeyond {
        outward: Vector2::zeros(),
        outside: 0,
        clipped: 0,
        empty: 0,
        undecided: 0,
        corners: Vec::new(),
        n,
    };
    for (i, &p) in ps.iter().enumerate() {
        let along = step_at(&ps, i);
        let outward = p - line[i];
        out.outward += outward / n as f64;
        if !(p.x >= 0.0 && p.y >= 0.0 && p.x <= w - 1.0 && p.y <= h - 1.0) {
            out.outside += 1;
            continue;
        }
        let pattern = square_pattern(img, p, along, outward);
        let contrasted = pattern.is_some_and(|(d_in, _)| d_in.abs() >= MIN_COLOUR_CONTRAST);
        // The board's uniform margin beyond its outer squares.
        if contrasted
            && pattern.is_some_and(|(d_in, d_out)| d_out.abs() <= END_UNIFORMITY * d_in.abs())
        {
            out.empty += 1;
            continue;
        }
        // Squares of opposite colours beyond, as a continuing board has.
        let checkered = contrasted
            && pattern.is_some_and(|(d_in, d_out)| {
                d_in * d_out < 0.0 && d_out.abs() >= CONTINUED_CONTRAST * d_in.abs()
            });
        tracing::debug!(?side, i, ?pattern, checkered, "squares beyond the grid");
        match refine::refine(img, p, along, outward) {
            Ok(f) => {
                let medians = reference();
                let like_grid = medians.is_none_or(|(c, r)| like_grid(&f, c, r));
                tracing::debug!(?side, i, uv = ?f.uv, contrast = f.contrast, residual = f.residual, ?medians, like_grid, "corner fit beyond the grid");
                if like_grid {
                    out.corners.push(f.uv);
                } else if checkered {
                    out.undecided += 1;
                } else {
                    out.empty += 1;
                }
            }
            // The window is clipped by the border (or has too few pixels): nothing is proven.
            Err(RefineFailure::Window) => out.clipped += 1,
            // A failed fit where the squares look checkered is no proof: the fit may have missed
            // a real corner (a poor prediction, blur, foreshortening).
            Err(why) => {
                tracing::debug!(?side, i, ?p, ?why, "no corner fit beyond the grid");
                if checkered {
                    out.undecided += 1;
                } else {
                    out.empty += 1;
                }
            }
        }
    }
    out
}

/// The grid's extent is proven: on each of its four sides, one lattice step beyond the outermost
/// line (where a bigger board would have its next line of corners), the corner fit window lies
/// inside the image and the fit finds no X-corner. Else the reason the grid is dropped.
fn check_extent(img: &GrayImage, d: &Dense) -> Result<(), String> {
    for side in Side::ALL {
        let b = look_beyond(img, d, side);
        tracing::debug!(
            ?side,
            outside = b.outside,
            clipped = b.clipped,
            empty = b.empty,
            undecided = b.undecided,
            corners = b.corners.len(),
            n = b.n,
            "one step beyond the grid"
        );
        let towards = image_side(b.outward);
        if let Some(c) = b.corners.first() {
            return Err(format!(
                "grid may continue: an X-corner like the grid's at ({:.1}, {:.1}), one step beyond its side towards the image {towards}",
                c.x, c.y
            ));
        }
        if b.empty < MIN_EMPTY_BEYOND.min(b.n) {
            let wher = if b.outside + b.clipped > 0 {
                format!("beyond the frame border (side towards the image {towards})")
            } else {
                format!("beyond its side towards the image {towards}")
            };
            return Err(format!(
                "grid may continue {wher}: of the {} positions one step beyond it, {} are outside the image, {} too close to the border for a corner fit, {} undecided (checkered squares, no corner fit), {} show no corner ({} needed)",
                b.n,
                b.outside,
                b.clipped,
                b.undecided,
                b.empty,
                MIN_EMPTY_BEYOND.min(b.n)
            ));
        }
    }
    Ok(())
}

/// The normalised DLT projection of 2D–3D pairs (`None` when the 3D points are coplanar).
pub(super) fn dlt_fit(points: &[(Vector3<f64>, Vector2<f64>)]) -> Option<Matrix3x4<f64>> {
    let x3: Vec<Vector3<f64>> = points.iter().map(|p| p.0).collect();
    if relative_thickness(&x3) < COPLANAR_TOLERANCE {
        return None;
    }
    let x2: Vec<Vector2<f64>> = points.iter().map(|p| p.1).collect();
    dlt(&x3, &x2).ok()
}

/// RMS image distance (px) between the pairs' 2D points and their 3D points projected by `p`.
pub(super) fn reprojection_rms(
    p: &Matrix3x4<f64>,
    points: &[(Vector3<f64>, Vector2<f64>)],
) -> Option<f64> {
    let mut ssr = 0.0;
    for (x, u) in points {
        let h = p * x.push(1.0);
        if h.z.abs() < 1e-300 {
            return None;
        }
        ssr += (Vector2::new(h.x / h.z, h.y / h.z) - u).norm_squared();
    }
    Some((ssr / points.len().max(1) as f64).sqrt())
}

fn dlt_rms(points: &[(Vector3<f64>, Vector2<f64>)]) -> Option<f64> {
    reprojection_rms(&dlt_fit(points)?, points)
}

/// The labelled faces must fit one camera clearly better than with any face's orientation reversed.
fn check_geometry(rig: &Rig, found: &[(FaceDetection, Dense, Mapping)]) -> Result<(), String> {
    let assemble = |flip: Option<usize>| -> Vec<(Vector3<f64>, Vector2<f64>)> {
        let mut pts = Vec::new();
        for (k, (f, d, _)) in found.iter().enumerate() {
            let face = &rig.faces[f.face];
            let dd = if flip == Some(k) {
                d.turned(2)
            } else {
                d.clone()
            };
            for r in 0..dd.rows {
                for c in 0..dd.cols {
                    pts.push((face.corner_xyz(r, c), dd.at(r, c)));
                }
            }
        }
        pts
    };
    let Some(chosen) = dlt_rms(&assemble(None)) else {
        return Err(
            "labelled faces are coplanar or degenerate: the rig geometry cannot confirm them"
                .into(),
        );
    };
    for k in 0..found.len() {
        if let Some(alt) = dlt_rms(&assemble(Some(k)))
            && alt < GEOMETRY_MARGIN * chosen
        {
            return Err(format!(
                "labelling not confirmed by the rig geometry: DLT RMS {chosen:.2} px vs {alt:.2} px with face '{}' reversed",
                rig.faces[found[k].0.face].name
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use image::Luma;

    /// A board of `cols × rows` inner corners with squares of `s` px, its first inner corner at pixel
    /// boundary `(x0, y0)` (pixel-centre coordinates `x0 − ½, y0 − ½`), a white margin of one square
    /// and a grey background, lightly blurred.
    fn board(w: u32, h: u32, cols: i64, rows: i64, s: i64, x0: i64, y0: i64) -> GrayImage {
        let img = GrayImage::from_fn(w, h, |x, y| {
            // Square indices: inner corner (r, c) joins squares r − 1..=r × c − 1..=c; squares −1 and
            // `cols − 1`/`rows − 1` are the outer ones, −2 and `cols`/`rows` the margin.
            let i = (i64::from(x) - x0).div_euclid(s);
            let j = (i64::from(y) - y0).div_euclid(s);
            let v = if i < -2 || j < -2 || i > cols || j > rows {
                120
            } else if i < -1 || j < -1 || i >= cols || j >= rows || (i + j).rem_euclid(2) == 1 {
                230
            } else {
                25
            };
            Luma([v])
        });
        image::imageops::blur(&img, 1.0)
    }

    /// The dense grid of inner corners `(r, c)` for `r` in `rows`, `c` in `cols` of [`board`].
    fn grid(
        rows: std::ops::Range<i64>,
        cols: std::ops::Range<i64>,
        s: i64,
        x0: i64,
        y0: i64,
    ) -> Dense {
        let mut uv = Vec::new();
        for r in rows.clone() {
            for c in cols.clone() {
                uv.push(Vector2::new(
                    (x0 + c * s) as f64 - 0.5,
                    (y0 + r * s) as f64 - 0.5,
                ));
            }
        }
        Dense {
            rows: rows.count(),
            cols: cols.count(),
            sigma: vec![0.05; uv.len()],
            uv,
        }
    }

    #[test]
    fn the_extent_of_a_grid_is_proven_only_where_the_board_visibly_ends() {
        // A whole 9×8 board with its margin inside the frame.
        let img = board(400, 360, 9, 8, 24, 80, 80);
        assert_eq!(check_extent(&img, &grid(0..8, 0..9, 24, 80, 80)), Ok(()));
        // A 9×7 part of it: one step beyond its last row are the corners of the board's last row.
        let part = check_extent(&img, &grid(0..7, 0..9, 24, 80, 80)).unwrap_err();
        assert!(part.contains("an X-corner like the grid's"), "{part}");
        assert!(part.contains("towards the image bottom"), "{part}");
        // The same board cut by the right border just after its last column: the outer squares and
        // the positions one step beyond are outside the frame.
        let cut = board(80 + 8 * 24 + 10, 360, 9, 8, 24, 80, 80);
        let reason = check_extent(&cut, &grid(0..8, 0..9, 24, 80, 80)).unwrap_err();
        assert!(reason.contains("beyond the frame border"), "{reason}");
        assert!(reason.contains("towards the image right"), "{reason}");
        assert!(reason.contains("8 are outside the image"), "{reason}");
        // Cut so that the positions one step beyond are inside, but too close to the border for a
        // corner fit window (4 px beyond them: the window reaches 0.65 step = 15.6 px).
        let close = board(80 + 9 * 24 + 4, 360, 9, 8, 24, 80, 80);
        let reason = check_extent(&close, &grid(0..8, 0..9, 24, 80, 80)).unwrap_err();
        assert!(
            reason.contains("0 are outside the image, 8 too close"),
            "{reason}"
        );
    }

    #[test]
    fn checkered_squares_beyond_a_grid_are_no_proof_of_its_end() {
        // The 9×8 board, with its bottom margin replaced by a band of squares that continues the
        // checkerboard's colours but is shifted by 0.3 square along the side: one step beyond the last
        // row there is no X-corner to fit, yet the squares beyond are checkered, as on a board whose
        // next row the fit misses.
        let (s, x0, y0) = (24, 80, 80);
        let mut img = board(400, 360, 9, 8, s, x0, y0);
        let shift = 0.3 * s as f64;
        for y in (y0 + 8 * s) as u32..(y0 + 9 * s) as u32 {
            for x in (x0 - s) as u32..(x0 + 9 * s) as u32 {
                let k = ((f64::from(x) - x0 as f64 - shift) / s as f64).floor() as i64;
                let v = if (k + 8).rem_euclid(2) == 1 { 230 } else { 25 };
                img.put_pixel(x, y, Luma([v]));
            }
        }
        let reason = check_extent(&img, &grid(0..8, 0..9, s, x0, y0)).unwrap_err();
        assert!(
            reason.contains("beyond its side towards the image bottom"),
            "{reason}"
        );
        assert!(reason.contains("0 show no corner"), "{reason}");
    }
}
