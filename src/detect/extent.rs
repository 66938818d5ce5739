//! Extent: where a grid ends, from the evidence one step beyond each of its sides.
//!
//! The size of a grid only means something if the board ends where the grid does: a bigger board
//! (or a bigger face) cut by the frame border, or a fragment of a bigger lattice, can show exactly a
//! face's number of corners. So on each of the grid's four sides, at the position one lattice step
//! beyond each corner of the outermost line — extrapolated along its row or column from the three
//! outermost corners (quadratic: it follows perspective and lens curvature, as in
//! [`super::complete`]) — the image must show that there is no corner:
//! * a position is **empty** when the two squares half a step further out differ by at most
//!   [`END_UNIFORMITY`] of the two half a step back (the board's outer squares, which must differ by
//!   [`MIN_COLOUR_CONTRAST`]): a continuing board would show two squares of opposite colours there,
//!   a board's end shows its uniform margin. Otherwise the X-junction fit of [`super::refine`] is
//!   run there, and no fit, or a fit unlike the grid's corners (residual and contrast against the
//!   medians of the next line inward, with the thresholds [`super::complete`] uses to accept a
//!   recovered corner), makes the position empty too — unless the squares beyond look checkered
//!   (opposite difference, at least [`CONTINUED_CONTRAST`] of the inner one): a fit that fails
//!   there may have missed a real corner (the grid stopped growing precisely because fits failed,
//!   e.g. at a foreshortened far end), so the position proves nothing;
//! * a fit like the grid's corners at any position drops the grid (it may continue) — unless the
//!   side shows an incomplete line: corners at no more than [`MAX_EXTRA_FRACTION`] of its
//!   positions, every other position empty (the paper's edge on a desk bright on one side and dark
//!   on the other makes one or two such junctions; a continuing board shows the line whole). Such
//!   a side is not proven either, but like the border it cannot hide a continuing board, so a rig
//!   of one face labels the grid with its pose flagged (see `label`);
//! * positions outside the image, or whose fit window the border clips (the fit refuses it),
//!   prove nothing;
//! * each side needs [`MIN_EMPTY_BEYOND`] empty positions, else the grid is dropped: "grid may
//!   continue beyond the frame border" (or "beyond its side"). A board is a rectangle, so a line
//!   of corners either continues along the whole side or not at all, and two positions seen empty
//!   prove the side without needing the whole next line inside the frame (fully visible boards
//!   often have it partly outside).
//!
//! The position beyond a cube face's outermost line is on the face's own margin (12 mm margin,
//! 16 mm squares: 0.75 step), never on the neighbouring face, so faces meeting at the cube's
//! edges keep their proof. Measured: on the realistic and hard synthetic sets (24 frames each,
//! k1 −0.1 / −0.3, faces up to 90°) every position beyond every face found is empty by the
//! colour test alone and no face is lost (realistic 52/53 faces < 75°, hard 32/38, as before);
//! on the 26 OpenCV sample images every board is kept, but the printed board's white margin is
//! narrower than half a square, so the samples beyond fall on its dark rim or the background and
//! 320 positions reach the fit: 18 clipped, 111 fits all unlike the grid's corners (residual at
//! least 2.4 times the threshold), 191 failed fits; 83 of the positions are undecided (the
//! background looks checkered as often as not). The fewest empty positions on a side is 2
//! (left03.jpg, whose next line is partly outside the image), 3 on four more sides, and the next
//! line is partly outside the image or too close to its border in 11 images. The check costs
//! 0.2–0.4 ms per frame.

use image::GrayImage;
use nalgebra::Vector2;

use super::complete::{like_grid, median};
use super::dense::Dense;
use super::face::MIN_COLOUR_CONTRAST;
use super::fold::FoldSides;
use super::refine::{self, RefineFailure};
use super::trim::MAX_EXTRA_FRACTION;

/// fit window unclipped) for the grid's extent to count as proven.
pub const MIN_EMPTY_BEYOND: usize = 2;
/// One step beyond a grid's side, the two squares half a step further out may differ by at most this
/// fraction of the two inside for the board's end to be clear without a corner fit.
pub const END_UNIFORMITY: f64 = 0.3;
/// Squares beyond a grid's side whose difference has the opposite sign of the outer squares' and at
/// least this fraction of it look like a continuing board.
pub const CONTINUED_CONTRAST: f64 = 0.5;

/// One side of a grid: its outermost line of corners and the lines inside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Side {
    FirstRow,
    LastRow,
    FirstCol,
    LastCol,
}

impl Side {
    fn at_fold(self, f: FoldSides) -> bool {
        match self {
            Side::FirstRow => f.first_row,
            Side::LastRow => f.last_row,
            Side::FirstCol => f.first_col,
            Side::LastCol => f.last_col,
        }
    }

    pub(super) const ALL: [Side; 4] =
        [Side::FirstRow, Side::LastRow, Side::FirstCol, Side::LastCol];

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
pub(super) struct SideBeyond {
    /// Outward direction of the side (mean step from the outermost line to the positions beyond).
    pub(super) outward: Vector2<f64>,
    /// Positions beyond that are outside the image.
    pub(super) outside: usize,
    /// Positions beyond inside the image but whose corner fit window is clipped by the border.
    pub(super) clipped: usize,
    /// Positions beyond with an unclipped window where the fit finds no corner like the grid's.
    pub(super) empty: usize,
    /// Positions beyond with squares of opposite colours (as on a continuing board) where the fit
    /// finds no corner like the grid's: neither proof nor veto.
    pub(super) undecided: usize,
    /// Positions beyond where the corner fit found a corner like the grid's.
    pub(super) corners: Vec<Vector2<f64>>,
    /// Positions beyond (the side's number of corners).
    pub(super) n: usize,
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

pub(super) fn look_beyond(img: &GrayImage, d: &Dense, side: Side) -> SideBeyond {
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

/// [`extent`]'s verdict with the reason alone (the unit tests').
#[cfg(test)]
pub(super) fn check_extent(img: &GrayImage, d: &Dense, folds: FoldSides) -> Result<(), String> {
    extent(img, d, folds).map_err(|f| f.reason)
}

/// Why a grid's extent is not proven.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct ExtentFailure {
    /// The first failing side's reason (and each side that shows an incomplete line).
    pub reason: String,
    /// Nothing shows a continuing board: every side without its empty positions has positions
    /// outside the image or too close to its border, and a side with corners like the grid's one
    /// step beyond it shows an incomplete line of them (at most [`MAX_EXTRA_FRACTION`] of its
    /// positions, every other one empty: the paper's edge on a two-tone desk, clutter). The grid may
    /// be the whole board or a part of a bigger one cut by the border or shifted by that line.
    pub only_border: bool,
}

/// The grid's extent is proven: on each of its four sides, one lattice step beyond the outermost
/// line (where a bigger board would have its next line of corners), the corner fit window lies
/// inside the image and the fit finds no X-corner. Else the reason the grid is dropped.
/// The failure tells a grid whose only missing proof is the frame border from one that may really
/// continue (a corner beyond it, or undecided positions inside the image).
pub(super) fn extent(img: &GrayImage, d: &Dense, folds: FoldSides) -> Result<(), ExtentFailure> {
    let mut first: Option<String> = None;
    let mut only_border = true;
    let mut lines: Vec<String> = Vec::new();
    for side in Side::ALL {
        // A side at a fold ends there: the next line of corners is the fold, on another plane.
        if side.at_fold(folds) {
            continue;
        }
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
        // An incomplete line beyond the side: a few corners, every other position seen empty. A
        // continuing board shows the line whole (a failed fit or two aside).
        let k = b.corners.len();
        if k > 0 && k as f64 <= MAX_EXTRA_FRACTION * b.n as f64 && b.empty + k == b.n {
            lines.push(format!(
                "one step beyond its side towards the image {towards}, {k} of {} positions show an X-corner like the grid's and the others none: an incomplete line (the paper's edge, clutter), not a continuing board",
                b.n
            ));
            continue;
        }
        if let Some(c) = b.corners.first() {
            return Err(ExtentFailure {
                reason: first.unwrap_or_else(|| format!(
                    "grid may continue: an X-corner like the grid's at ({:.1}, {:.1}), one step beyond its side towards the image {towards}",
                    c.x, c.y
                )),
                only_border: false,
            });
        }
        if b.empty < MIN_EMPTY_BEYOND.min(b.n) {
            let at_border = b.outside + b.clipped > 0;
            only_border &= at_border;
            let wher = if at_border {
                format!("beyond the frame border (side towards the image {towards})")
            } else {
                format!("beyond its side towards the image {towards}")
            };
            if first.is_none() {
                first = Some(format!(
                    "grid may continue {wher}: of the {} positions one step beyond it, {} are outside the image, {} too close to the border for a corner fit, {} undecided (checkered squares, no corner fit), {} show no corner ({} needed)",
                    b.n,
                    b.outside,
                    b.clipped,
                    b.undecided,
                    b.empty,
                    MIN_EMPTY_BEYOND.min(b.n)
                ));
            }
            // A side unproven away from the border settles it: no need to look at the others.
            if !only_border {
                break;
            }
        }
    }
    match first {
        None if lines.is_empty() => Ok(()),
        None => Err(ExtentFailure {
            reason: lines.join("; "),
            only_border,
        }),
        Some(reason) => Err(ExtentFailure {
            reason: std::iter::once(reason)
                .chain(lines)
                .collect::<Vec<_>>()
                .join("; "),
            only_border,
        }),
    }
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
            cov: vec![nalgebra::Matrix2::from_diagonal_element(0.0025); uv.len()],
            edge: vec![1.0; uv.len()],
            uv,
        }
    }

    #[test]
    fn the_extent_of_a_grid_is_proven_only_where_the_board_visibly_ends() {
        // A whole 9×8 board with its margin inside the frame.
        let img = board(400, 360, 9, 8, 24, 80, 80);
        assert_eq!(
            check_extent(&img, &grid(0..8, 0..9, 24, 80, 80), FoldSides::default()),
            Ok(())
        );
        // A 9×7 part of it: one step beyond its last row are the corners of the board's last row.
        let part =
            check_extent(&img, &grid(0..7, 0..9, 24, 80, 80), FoldSides::default()).unwrap_err();
        assert!(part.contains("an X-corner like the grid's"), "{part}");
        assert!(part.contains("towards the image bottom"), "{part}");
        // The same board cut by the right border just after its last column: the outer squares and
        // the positions one step beyond are outside the frame.
        let cut = board(80 + 8 * 24 + 10, 360, 9, 8, 24, 80, 80);
        let reason =
            check_extent(&cut, &grid(0..8, 0..9, 24, 80, 80), FoldSides::default()).unwrap_err();
        assert!(reason.contains("beyond the frame border"), "{reason}");
        assert!(reason.contains("towards the image right"), "{reason}");
        assert!(reason.contains("8 are outside the image"), "{reason}");
        // Cut so that the positions one step beyond are inside, but too close to the border for a
        // corner fit window (4 px beyond them: the window reaches 0.65 step = 15.6 px).
        let close = board(80 + 9 * 24 + 4, 360, 9, 8, 24, 80, 80);
        let reason =
            check_extent(&close, &grid(0..8, 0..9, 24, 80, 80), FoldSides::default()).unwrap_err();
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
        let reason =
            check_extent(&img, &grid(0..8, 0..9, s, x0, y0), FoldSides::default()).unwrap_err();
        assert!(
            reason.contains("beyond its side towards the image bottom"),
            "{reason}"
        );
        assert!(reason.contains("0 show no corner"), "{reason}");
    }
}
