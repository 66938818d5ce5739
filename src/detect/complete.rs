//! Grid completion: every corner of an assembled grid is fitted at full resolution, and corners the
//! front end missed are recovered where the lattice predicts them.
//!
//! The X-corner front end misses corners on faces seen at 60°+ (squares a few pixels wide in one
//! direction), in low contrast or in heavy noise; grid assembly then stops with holes or short rows. The
//! lattice still knows where each missing corner must be: the next position along a row or column is
//! extrapolated from the two or three before it (quadratic, so it follows perspective and lens
//! curvature), and the X-junction fit of [`super::refine`] decides whether a corner is there. A fit is
//! accepted only when it converges near the prediction and its four quadrants alternate dark / bright
//! (so the board's outer edge, a margin or the neighbouring face never pass for a corner); the lattice
//! cannot grow beyond the largest face of the rig in either direction.
//! A corner the assembled grid captured from a neighbouring junction (a face at 75°+ in low
//! contrast and noise) lies a step off the homography of the cells around it: it is dropped and
//! recovered afresh from the lattice's prediction (`drop_off_lattice`).
//!
//! Last, each corner is corrected for the curvature of its two lattice lines (lens distortion), which
//! the straight-edge fit does not model: the curvature is measured by a parabola through the fitted
//! corners along each line and applied with the fit's own first-order sensitivity
//! ([`Refined::curvature_shift`]), and for the shading across its window (vignetting, uneven light):
//! the gradients of the fitted level and contrast over the neighbouring corners, applied with the
//! fit's sensitivity to them ([`Refined::shading_shift`], see [`shading_gradient`]).

// Ordered: recovery order must not depend on hashing (same frame, same result).
use std::collections::BTreeMap;

use image::GrayImage;
use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

use super::XCorner;
use super::grid::Grid;
use super::refine::{self, Refined};

/// A fitted corner, or (σ infinite) a lattice position too close to the image border for any corner
/// window: see [`Fitted::is_measured`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fitted {
    pub uv: Vector2<f64>,
    pub sigma_px: f64,
    /// Covariance of `uv` (px²), from the fit ([`Refined::cov`]); `sigma_px` is `√(trace/2)` of it.
    pub cov: Matrix2<f64>,
    /// The fit's edge width `s` (px, [`Refined::edge_width`]); 0 for a position no fit measured.
    pub edge_px: f64,
}

impl Fitted {
    /// A position with the same σ along both axes, uncorrelated (`σ` NaN or infinite for a position
    /// that was not measured).
    pub fn isotropic(uv: Vector2<f64>, sigma_px: f64) -> Fitted {
        Fitted {
            uv,
            sigma_px,
            cov: Matrix2::from_diagonal_element(sigma_px * sigma_px),
            edge_px: 0.0,
        }
    }

    /// The fitted corner of a window fit.
    pub fn from_refined(r: &Refined) -> Fitted {
        Fitted {
            uv: r.uv,
            sigma_px: r.sigma_px,
            cov: r.cov,
            edge_px: r.edge_width,
        }
    }

    /// Whether the position was measured by a corner fit. A grid's lattice position that lies inside
    /// the image but so near its border that not even the smallest corner window fits
    /// ([`refine::MIN_BORDER_HALF_PX`]) is kept at its predicted position with an infinite σ: it
    /// completes the grid's extent — a face is identified by where its pattern ends, not by having
    /// every corner fitted — but it is no observation and never becomes a labelled corner.
    pub fn is_measured(&self) -> bool {
        self.sigma_px.is_finite()
    }
}

/// A completed grid: `rows × cols`, row-major, with the corners that could be fitted.
#[derive(Debug, Clone, PartialEq)]
pub struct Completed {
    pub rows: usize,
    pub cols: usize,
    pub cells: Vec<Option<Fitted>>,
    /// Corners of the assembled grid whose fit failed (dropped).
    pub dropped: usize,
    /// Corners recovered by prediction and fit.
    pub recovered: usize,
}

impl Completed {
    /// A grid none of whose corners could be fitted.
    fn empty(dropped: usize, recovered: usize) -> Completed {
        Completed {
            rows: 0,
            cols: 0,
            cells: Vec::new(),
            dropped,
            recovered,
        }
    }

    pub fn get(&self, r: usize, c: usize) -> Option<Fitted> {
        if r < self.rows && c < self.cols {
            self.cells[r * self.cols + c]
        } else {
            None
        }
    }

    pub fn count(&self) -> usize {
        self.cells.iter().filter(|c| c.is_some()).count()
    }
}

type Cells = BTreeMap<(i32, i32), Fitted>;

/// The image step from `(r, c)` to the next cell along `(dr, dc)`: the central difference when both
/// neighbours are known, else the nearest pair of consecutive filled cells on that line (up to three
/// cells away), else the same step on a parallel line next to it.
fn step_along(cells: &Cells, r: i32, c: i32, dr: i32, dc: i32) -> Option<Vector2<f64>> {
    step_along_in(&|r, c| cells.get(&(r, c)).map(|f| f.uv), r, c, dr, dc, true)
}

/// [`step_along`] on the lattice `get`, with the cell `(r, c)` itself taken as empty unless `own`.
fn step_along_in(
    get: &impl Fn(i32, i32) -> Option<Vector2<f64>>,
    r: i32,
    c: i32,
    dr: i32,
    dc: i32,
    own: bool,
) -> Option<Vector2<f64>> {
    let at = |k: i32| {
        if k == 0 && !own {
            return None;
        }
        get(r + k * dr, c + k * dc)
    };
    if let (Some(a), Some(b)) = (at(-1), at(1)) {
        return Some((b - a) / 2.0);
    }
    for k in [0, -1, 1, -2, 2, -3] {
        if let (Some(a), Some(b)) = (at(k), at(k + 1)) {
            return Some(b - a);
        }
    }
    [(dc, dr), (-dc, -dr)].iter().find_map(|&(or, oc)| {
        let a = get(r + or, c + oc)?;
        let b = get(r + or + dr, c + oc + dc)?;
        Some(b - a)
    })
}

/// A recovered corner's fit residual may be at most this multiple of the grid's median (+1 grey level).
pub const RECOVER_RESIDUAL: f64 = 1.5;
/// A recovered corner's contrast must be at least this fraction of the grid's median.
pub const RECOVER_CONTRAST: f64 = 0.4;

/// Whether the fit `f` looks like a corner of a grid whose corners have these median contrast and
/// residual: residual at most [`RECOVER_RESIDUAL`] × the median (+1 grey level), contrast at least
/// [`RECOVER_CONTRAST`] × the median.
pub(super) fn like_grid(f: &Refined, median_contrast: f64, median_residual: f64) -> bool {
    f.residual <= RECOVER_RESIDUAL * median_residual + 1.0
        && f.contrast >= RECOVER_CONTRAST * median_contrast
}

/// Cells within this many lines of a target feed its local homography.
pub const LOCAL_RADIUS: i32 = 3;

/// Predicted position of an empty cell: a homography fitted to the filled cells around it (within
/// [`LOCAL_RADIUS`] lines: locally, perspective is exact and lens distortion small), else extrapolation
/// along rows and columns.
fn predict(cells: &Cells, r: i32, c: i32) -> Option<Vector2<f64>> {
    local_homography(&|r, c| cells.get(&(r, c)).map(|f| f.uv), r, c, 6)
        .or_else(|| extrapolate(cells, r, c))
}

/// The image of cell `(r, c)` under a homography fitted to at least `min_cells` filled cells of the
/// lattice `get` around it (within [`LOCAL_RADIUS`] lines, on two rows and two columns at least;
/// the cell itself left out).
fn local_homography(
    get: &impl Fn(i32, i32) -> Option<Vector2<f64>>,
    r: i32,
    c: i32,
    min_cells: usize,
) -> Option<Vector2<f64>> {
    let mut plane = Vec::new();
    let mut image = Vec::new();
    let (mut rows, mut cols) = (Vec::new(), Vec::new());
    for dr in -LOCAL_RADIUS..=LOCAL_RADIUS {
        for dc in -LOCAL_RADIUS..=LOCAL_RADIUS {
            if (dr, dc) == (0, 0) {
                continue;
            }
            if let Some(uv) = get(r + dr, c + dc) {
                plane.push(Vector2::new(f64::from(dc), f64::from(dr)));
                image.push(uv);
                if !rows.contains(&dr) {
                    rows.push(dr);
                }
                if !cols.contains(&dc) {
                    cols.push(dc);
                }
            }
        }
    }
    if plane.len() >= min_cells && rows.len() >= 2 && cols.len() >= 2 {
        image_of_origin(&plane, &image)
    } else {
        None
    }
}

/// An assembled corner farther than this from where the cells around it put it, in lattice steps
/// along either axis of the grid, is not that cell's corner (see [`drop_off_lattice`]).
pub const MAX_LATTICE_DEVIATION: f64 = 0.4;
/// A corner within this many steps of its extrapolation along its lattice lines is not judged
/// further by [`drop_off_lattice`].
pub const LATTICE_SCREEN: f64 = 0.2;
/// Fewest filled cells around a corner for [`drop_off_lattice`] to judge it.
pub const LATTICE_CHECK_MIN_CELLS: usize = 8;

/// How far `uv` lies from `p`, a prediction of the lattice position `(r, c)`, in lattice steps of
/// `get` along the grid's two axes (the larger of the two; the steps taken without `(r, c)`'s own
/// cell); `None` where no steps can be taken.
fn lattice_deviation(
    get: &impl Fn(i32, i32) -> Option<Vector2<f64>>,
    r: i32,
    c: i32,
    uv: Vector2<f64>,
    p: Vector2<f64>,
) -> Option<f64> {
    let steps = Matrix2::from_columns(&[
        step_along_in(get, r, c, 0, 1, false)?,
        step_along_in(get, r, c, 1, 0, false)?,
    ]);
    let st = steps.try_inverse()? * (uv - p);
    st.iter().all(|v| v.is_finite()).then(|| st.abs().max())
}

/// Removes from `cells`, worst first, the corners more than [`MAX_LATTICE_DEVIATION`] steps from
/// where the cells around them put them, and returns their cells. Grid assembly captures each
/// corner from the front end's detections near a predicted position; on a face seen at 75°+ in
/// low contrast and noise, the junction a step or a diagonal step away can be the one found, and
/// the window fit then refines that junction under the wrong label (the hard set, 30 noise streams
/// of its first 12 views: 3 of 44 780 corners, 9–13 px from the truth, which alone biased fx by
/// +0.05 px, a third of its σ in a 12-view solve: `examples/receding_bias`). A right corner lies
/// within its noise and the lens's bending of the lattice over a few cells of the local
/// homography, hundredths of a step; a neighbour's junction a whole step off along some axis.
/// Worst first, because one wrong corner also shifts its neighbours' predictions (by a fraction
/// of its own error).
fn drop_off_lattice(cells: &mut Cells) -> Vec<(i32, i32)> {
    let mut gone = Vec::new();
    loop {
        let Some((r0, r1, c0, c1)) = bounds(cells) else {
            return gone;
        };
        // The lattice as a dense array for the screen's lookups (a tree's, per corner, cost more
        // than the screen's arithmetic).
        let cols = (c1 - c0 + 1) as usize;
        let mut dense = vec![None; (r1 - r0 + 1) as usize * cols];
        for (&(r, c), f) in cells.iter() {
            dense[(r - r0) as usize * cols + (c - c0) as usize] = Some(f.uv);
        }
        let get = |r: i32, c: i32| {
            if r < r0 || r > r1 || c < c0 || c > c1 {
                return None;
            }
            dense[(r - r0) as usize * cols + (c - c0) as usize]
        };
        let mut worst: Option<(f64, (i32, i32))> = None;
        for (&(r, c), f) in cells.iter() {
            // Screened by the lines through it (a few extrapolations), judged by the homography
            // of the cells around it only when the screen fails: the homography for every corner
            // cost 7 % of the detector's instructions, screened 0.5 % (`cargo bench --bench
            // detect` under callgrind).
            let screened = extrapolate_in(&get, r, c)
                .and_then(|p| lattice_deviation(&get, r, c, f.uv, p))
                .is_some_and(|d| d <= LATTICE_SCREEN);
            if !screened
                && let Some(p) = local_homography(&get, r, c, LATTICE_CHECK_MIN_CELLS)
                && let Some(d) = lattice_deviation(&get, r, c, f.uv, p)
                && d > MAX_LATTICE_DEVIATION
                && worst.is_none_or(|(w, _)| d > w)
            {
                worst = Some((d, (r, c)));
            }
        }
        let Some((_, key)) = worst else {
            return gone;
        };
        cells.remove(&key);
        gone.push(key);
    }
}

/// The image of the plane's origin under the homography fitted (DLT) to `plane` → `image`.
///
/// The origin is the cell being predicted, so it is never mapped to infinity and the homography can
/// be normalised by `H₃₃ = 1`: eight unknowns from the normal equations, with the image points
/// centred and scaled (Hartley) — a fraction of the cost of the general SVD solution
/// ([`crate::calib::linear::homography`]), which this is called too often for (every empty cell
/// around every grid).
fn image_of_origin(plane: &[Vector2<f64>], image: &[Vector2<f64>]) -> Option<Vector2<f64>> {
    let n = image.len() as f64;
    let centre = image.iter().sum::<Vector2<f64>>() / n;
    let scale = (image
        .iter()
        .map(|p| (p - centre).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt();
    if !(scale.is_finite() && scale > 1e-9) {
        return None;
    }
    let h = crate::calib::linear::homography_h33(
        plane
            .iter()
            .zip(image)
            .map(|(q, p)| (*q, (p - centre) / scale)),
    )?;
    let uv = centre + Vector2::new(h[(0, 2)], h[(1, 2)]) * scale;
    uv.iter().all(|v| v.is_finite()).then_some(uv)
}

/// Predicted position of an empty cell from the filled cells before it along rows and columns.
fn extrapolate(cells: &Cells, r: i32, c: i32) -> Option<Vector2<f64>> {
    extrapolate_in(&|r, c| cells.get(&(r, c)).map(|f| f.uv), r, c)
}

/// [`extrapolate`] on the lattice `get` (the cell `(r, c)` itself is never read).
fn extrapolate_in(
    get: &impl Fn(i32, i32) -> Option<Vector2<f64>>,
    r: i32,
    c: i32,
) -> Option<Vector2<f64>> {
    let mut sum = Vector2::zeros();
    let mut n = 0.0;
    for (dr, dc) in [(0, 1), (0, -1), (1, 0), (-1, 0)] {
        let at = |k: i32| get(r - k * dr, c - k * dc);
        let p = match (at(1), at(2), at(3)) {
            (Some(p1), Some(p2), Some(p3)) => 3.0 * p1 - 3.0 * p2 + p3,
            (Some(p1), Some(p2), None) => 2.0 * p1 - p2,
            _ => continue,
        };
        sum += p;
        n += 1.0;
    }
    // Interior holes: the mean of both neighbours along a line.
    for (dr, dc) in [(0, 1), (1, 0)] {
        if let (Some(a), Some(b)) = (get(r - dr, c - dc), get(r + dr, c + dc)) {
            sum += (a + b) / 2.0;
            n += 1.0;
        }
    }
    (n > 0.0).then(|| sum / n)
}

/// What a corner fit says of the shading at its corner: level, contrast and the corner's sensitivity
/// to their gradients ([`Refined::shading_shift`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Shade {
    pub uv: Vector2<f64>,
    /// The squares' level and half-contrast ([`Refined::squares`]).
    pub squares: Option<[f64; 2]>,
    pub shift: Matrix2<f64>,
}

impl Shade {
    pub fn of(r: &Refined) -> Shade {
        Shade {
            uv: r.uv,
            squares: r.squares,
            shift: r.shading_shift,
        }
    }
}

/// Lattice steps on each side of a corner whose fits feed its shading gradient.
pub const SHADING_RADIUS: i32 = 2;
/// Fewest fitted corners (the corner's own included) for a shading gradient.
pub const SHADING_MIN_POINTS: usize = 5;

/// The relative gradient (1/px, image axes) of the brightness at fitted corner `(r, c)`: planes
/// fitted by least squares to the squares' levels `m` and half-contrasts `|h|` around the corners
/// within [`SHADING_RADIUS`] lattice steps ([`Refined::squares`]), and the one scale `γ` that best
/// explains both slopes (`∇m ≈ m·γ`, `∇|h| ≈ |h|·γ`, see [`super::refine::Refined::shading_shift`]).
/// Vignetting and the light vary slowly across a board; a corner window sees the slope, which its
/// constant-level model does not (measured on renders with vignetting 0.3 at 1920×1080,
/// noise-free: corner RMS below 75° 0.0044 px against 0.0021 px without vignetting). `None` with
/// too few fits or a degenerate layout.
///
/// The levels are the squares' flat parts, not the junction model's fitted `m` and `h`: those take
/// up the model's mismatch with the blurred junction, which changes with the window's shape, and so
/// from corner to corner across a receding face. On renders without any shading (the realistic
/// set with vignetting 0 and gamma 1, noise-free, 32×32 supersampling, its first 12 views) that
/// made a gradient where there is none: the correction moved the interior corners of faces at
/// 60–75° outward across the receding direction by 0.16 mpx on average (−0.03 mpx with the
/// squares' levels, −0.02 mpx with no correction at all), and over a thousand corners that biased
/// fx by −0.0146 px (−0.0073 px with the squares' levels). With the set's own shading, −0.0153 →
/// −0.0032 px (`examples/receding_bias`, issue 29).
pub(super) fn shading_gradient(
    shades: &BTreeMap<(i32, i32), Shade>,
    r: i32,
    c: i32,
) -> Option<Vector2<f64>> {
    let centre = shades.get(&(r, c))?.uv;
    let mut ata = Matrix3::zeros();
    let mut atm = Vector3::zeros();
    let mut ath = Vector3::zeros();
    let mut n = 0;
    for dr in -SHADING_RADIUS..=SHADING_RADIUS {
        for dc in -SHADING_RADIUS..=SHADING_RADIUS {
            let Some((s, [level, contrast])) = shades
                .get(&(r + dr, c + dc))
                .and_then(|s| Some((s, s.squares?)))
            else {
                continue;
            };
            let d = s.uv - centre;
            let row = Vector3::new(1.0, d.x, d.y);
            ata += row * row.transpose();
            atm += row * level;
            ath += row * contrast;
            n += 1;
        }
    }
    if n < SHADING_MIN_POINTS {
        return None;
    }
    let chol = ata.cholesky()?;
    let (m, h) = (chol.solve(&atm), chol.solve(&ath));
    let scale = m.x * m.x + h.x * h.x;
    if !(scale > 0.0) {
        return None;
    }
    let g = (Vector2::new(m.y, m.z) * m.x + Vector2::new(h.y, h.z) * h.x) / scale;
    g.iter().all(|v| v.is_finite()).then_some(g)
}

/// The shading correction of fitted corner `(r, c)`: `shading_shift·γ` ([`shading_gradient`]),
/// zero where no gradient can be measured.
pub(super) fn shading_correction(
    shades: &BTreeMap<(i32, i32), Shade>,
    r: i32,
    c: i32,
) -> Vector2<f64> {
    match (shades.get(&(r, c)), shading_gradient(shades, r, c)) {
        (Some(s), Some(g)) => s.shift * g,
        _ => Vector2::zeros(),
    }
}

/// Corners on each side of a cell along a lattice line that feed its curvature estimate.
pub const CURVATURE_RADIUS: i32 = 3;
/// Fewest fitted corners (the cell's own included) on a lattice line for a curvature estimate.
pub const CURVATURE_MIN_POINTS: usize = 4;

/// Curvature (1/px, positive towards the left normal of the direction of increasing `(dr, dc)`) of
/// the lattice line through the fitted cell `(r, c)` along `(dr, dc)`: a parabola fitted to the
/// offsets of the fitted corners within [`CURVATURE_RADIUS`] from their chord. Perspective keeps
/// lines straight; what bends them is lens distortion, which varies slowly across the image.
pub(super) fn lattice_curvature(cells: &Cells, r: i32, c: i32, dr: i32, dc: i32) -> Option<f64> {
    let centre = cells.get(&(r, c))?.uv;
    let pts: Vec<Vector2<f64>> = (-CURVATURE_RADIUS..=CURVATURE_RADIUS)
        .filter_map(|k| cells.get(&(r + k * dr, c + k * dc)).map(|f| f.uv - centre))
        .collect();
    let (first, last) = (pts.first()?, pts.last()?);
    if pts.len() < CURVATURE_MIN_POINTS {
        return None;
    }
    let u = (last - first).try_normalize(1e-9)?;
    let n = Vector2::new(-u.y, u.x);
    // Least squares y = α + β·t + γ·t² through (t, y) = (u·p, n·p).
    let mut ata = Matrix3::zeros();
    let mut aty = Vector3::zeros();
    for p in &pts {
        let t = u.dot(p);
        let row = Vector3::new(1.0, t, t * t);
        ata += row * row.transpose();
        aty += row * n.dot(p);
    }
    let sol = ata.cholesky()?.solve(&aty);
    let kappa = 2.0 * sol.z;
    kappa.is_finite().then_some(kappa)
}

/// The fitted corners of a grid being completed, with what each fit said of its lattice lines'
/// curvature and its shading, and which empty cells were tried with how many neighbours.
struct Lattice {
    cells: Cells,
    shifts: BTreeMap<(i32, i32), Matrix2<f64>>,
    shades: BTreeMap<(i32, i32), Shade>,
    tried: BTreeMap<(i32, i32), usize>,
}

impl Lattice {
    /// Recovers missing corners, ring by ring, until nothing changes; returns how many. A recovered
    /// corner must look like the grid's own ([`like_grid`] with `grid` = its median contrast and
    /// residual); the lattice may span at most `max_lines` rows and columns.
    fn recover(&mut self, img: &GrayImage, grid: (f64, f64), max_lines: usize) -> usize {
        let Lattice {
            cells,
            shifts,
            shades,
            tried,
        } = self;
        let mut recovered = 0;
        while let Some(bounds) = bounds(cells) {
            let mut candidates: Vec<(i32, i32)> = Vec::new();
            for &(r, c) in cells.keys() {
                for (dr, dc) in [(0, 1), (0, -1), (1, 0), (-1, 0)] {
                    let t = (r + dr, c + dc);
                    if cells.contains_key(&t) || candidates.contains(&t) {
                        continue;
                    }
                    let (r0, r1, c0, c1) = bounds;
                    let span_r = (r1.max(t.0) - r0.min(t.0) + 1) as usize;
                    let span_c = (c1.max(t.1) - c0.min(t.1) + 1) as usize;
                    if span_r > max_lines || span_c > max_lines {
                        continue;
                    }
                    candidates.push(t);
                }
            }
            let mut added = false;
            for (r, c) in candidates {
                let n_neighbours = [(0, 1), (0, -1), (1, 0), (-1, 0)]
                    .iter()
                    .filter(|(dr, dc)| cells.contains_key(&(r + dr, c + dc)))
                    .count();
                // Each cell is tried again only when it has gained neighbours since its last try.
                if tried.get(&(r, c)).is_some_and(|&n| n >= n_neighbours) {
                    continue;
                }
                tried.insert((r, c), n_neighbours);
                let Some(p) = predict(cells, r, c) else {
                    continue;
                };
                let (Some(a), Some(b)) =
                    (step_along(cells, r, c, 0, 1), step_along(cells, r, c, 1, 0))
                else {
                    continue;
                };
                let fitted = fit(img, p, a, b);
                let like_grid = |f: &Refined| like_grid(f, grid.0, grid.1);
                if let Some(f) = fitted.filter(|f| !like_grid(f)) {
                    tracing::trace!(r, c, ?p, uv = ?f.uv, contrast = f.contrast, residual = f.residual, median_contrast = grid.0, median_residual = grid.1, "recovered corner unlike the grid's");
                }
                if let Some(f) = fitted.filter(like_grid) {
                    shifts.insert((r, c), f.curvature_shift);
                    shades.insert((r, c), Shade::of(&f));
                    cells.insert((r, c), Fitted::from_refined(&f));
                    tracing::trace!(r, c, ?p, uv = ?f.uv, contrast = f.contrast, residual = f.residual, width = f.edge_width, "corner recovered");
                    recovered += 1;
                    added = true;
                }
            }
            if !added {
                break;
            }
        }
        recovered
    }
}

fn fit(img: &GrayImage, p: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> Option<Refined> {
    match refine::refine_near_border(img, p, a, b) {
        Ok(f) => Some(f),
        Err(why) => {
            tracing::trace!(?p, ?a, ?b, ?why, "corner fit failed");
            None
        }
    }
}

/// Fit every corner of `grid` and recover the missing ones; the lattice may span at most
/// `max_lines` rows and columns.
pub fn complete(img: &GrayImage, corners: &[XCorner], grid: &Grid, max_lines: usize) -> Completed {
    let mut raw: Cells = BTreeMap::new();
    for r in 0..grid.rows {
        for c in 0..grid.cols {
            if let Some(i) = grid.get(r, c) {
                raw.insert(
                    (r as i32, c as i32),
                    Fitted::isotropic(corners[i].uv, f64::NAN),
                );
            }
        }
    }
    // Fit the assembled corners with steps from the front-end lattice.
    let mut cells: Cells = BTreeMap::new();
    let mut shifts: BTreeMap<(i32, i32), Matrix2<f64>> = BTreeMap::new();
    let mut shades: BTreeMap<(i32, i32), Shade> = BTreeMap::new();
    let mut dropped = 0;
    let mut residuals = Vec::new();
    let mut contrasts = Vec::new();
    for (&(r, c), f) in &raw {
        let (Some(a), Some(b)) = (step_along(&raw, r, c, 0, 1), step_along(&raw, r, c, 1, 0))
        else {
            dropped += 1;
            continue;
        };
        match fit(img, f.uv, a, b) {
            Some(fit) => {
                residuals.push(fit.residual);
                contrasts.push(fit.contrast);
                shifts.insert((r, c), fit.curvature_shift);
                shades.insert((r, c), Shade::of(&fit));
                cells.insert((r, c), Fitted::from_refined(&fit));
            }
            None => dropped += 1,
        }
    }
    // A recovered corner must look like the grid's own: residual and contrast near their medians.
    let (Some(median_residual), Some(median_contrast)) =
        (median(&mut residuals), median(&mut contrasts))
    else {
        return Completed::empty(dropped, 0);
    };
    // Recover missing corners, ring by ring, until nothing changes; then drop the corners the
    // lattice around them puts elsewhere (captured from a neighbouring junction, see
    // `drop_off_lattice`) and recover those afresh from its prediction.
    let mut lattice = Lattice {
        cells,
        shifts,
        shades,
        tried: BTreeMap::new(),
    };
    let grid_levels = (median_contrast, median_residual);
    let mut recovered = lattice.recover(img, grid_levels, max_lines);
    let off = drop_off_lattice(&mut lattice.cells);
    if !off.is_empty() {
        for key in off {
            tracing::debug!(r = key.0, c = key.1, "corner off its lattice: fitted again");
            lattice.shifts.remove(&key);
            lattice.shades.remove(&key);
            lattice.tried.remove(&key);
            dropped += 1;
        }
        recovered += lattice.recover(img, grid_levels, max_lines);
    }
    let Lattice {
        mut cells,
        shifts,
        shades,
        ..
    } = lattice;
    // The fits take the edge lines as straight and the levels as constant; correct each corner for
    // the curvature of its lattice lines (estimated from the straight-line fits: the bias they carry
    // varies slowly along a line) and for the shading across its window.
    let corrected: Vec<((i32, i32), Vector2<f64>)> = cells
        .iter()
        .filter_map(|(&(r, c), f)| {
            let shift = shifts.get(&(r, c))?;
            let kappa = Vector2::new(
                lattice_curvature(&cells, r, c, 0, 1).unwrap_or(0.0),
                lattice_curvature(&cells, r, c, 1, 0).unwrap_or(0.0),
            );
            Some((
                (r, c),
                f.uv + shift * kappa + shading_correction(&shades, r, c),
            ))
        })
        .collect();
    for (key, uv) in corrected {
        if let Some(f) = cells.get_mut(&key) {
            f.uv = uv;
        }
    }
    let Some((r0, r1, c0, c1)) = bounds(&cells) else {
        return Completed::empty(dropped, recovered);
    };
    // Positions of the lattice that no window can fit at, held for the grid's extent.
    let mut at_border = Vec::new();
    for r in r0..=r1 {
        for c in c0..=c1 {
            if cells.contains_key(&(r, c)) {
                continue;
            }
            if let (Some(p), Some(a), Some(b)) = (
                predict(&cells, r, c),
                step_along(&cells, r, c, 0, 1),
                step_along(&cells, r, c, 1, 0),
            ) && beyond_any_window(img, p, a, b)
            {
                at_border.push(((r, c), p));
            }
        }
    }
    for (key, uv) in at_border {
        cells.insert(key, Fitted::isotropic(uv, f64::INFINITY));
    }
    let rows = (r1 - r0 + 1) as usize;
    let cols = (c1 - c0 + 1) as usize;
    let mut out = vec![None; rows * cols];
    for (&(r, c), f) in &cells {
        out[(r - r0) as usize * cols + (c - c0) as usize] = Some(*f);
    }
    Completed {
        rows,
        cols,
        cells: out,
        dropped,
        recovered,
    }
}

/// Whether `p` lies inside the image but too close to its border for any corner window: the window
/// of [`refine::refine_near_border`] (half-extents [`refine::WINDOW`] of the lattice steps `a`, `b`)
/// shrunk about `p` until it fits would be smaller than [`refine::MIN_BORDER_HALF_PX`] along a step.
fn beyond_any_window(img: &GrayImage, p: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> bool {
    let (w, h) = (f64::from(img.width()) - 0.5, f64::from(img.height()) - 0.5);
    if !(p.x >= -0.5 && p.x < w && p.y >= -0.5 && p.y < h) {
        return false;
    }
    let (la, lb) = (a.norm(), b.norm());
    if !(la > 1e-6 && lb > 1e-6) {
        return false;
    }
    let half = |l: f64| (refine::WINDOW * l).clamp(refine::MIN_HALF_PX, refine::MAX_HALF_PX);
    let (ha, hb) = (half(la), half(lb));
    let ext_x = a.x.abs() / la * ha + b.x.abs() / lb * hb;
    let ext_y = a.y.abs() / la * ha + b.y.abs() / lb * hb;
    let room = ((p.x + 0.5).min(w - p.x) / ext_x).min((p.y + 0.5).min(h - p.y) / ext_y);
    room < 1.0 && room * ha.min(hb) < refine::MIN_BORDER_HALF_PX
}

/// The median of `v` (the upper one for an even count), `None` if empty.
pub(super) fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

fn bounds(cells: &Cells) -> Option<(i32, i32, i32, i32)> {
    if cells.is_empty() {
        return None;
    }
    Some(cells.keys().fold(
        (i32::MAX, i32::MIN, i32::MAX, i32::MIN),
        |(a, b, c, d), &(r, cc)| (a.min(r), b.max(r), c.min(cc), d.max(cc)),
    ))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn cells_on(f: impl Fn(i32, i32) -> Vector2<f64>) -> Cells {
        let mut cells = BTreeMap::new();
        for r in 0..7 {
            for c in 0..7 {
                let uv = f(r, c);
                cells.insert((r, c), Fitted::isotropic(uv, 0.1));
            }
        }
        cells
    }

    #[test]
    fn the_origin_is_predicted_exactly_under_a_strong_perspective() {
        // A lattice seen obliquely: cells on one side of the target only (extrapolation).
        let h = Matrix3::new(30.0, 4.0, 640.0, -3.0, 22.0, 480.0, 2e-2, -1.5e-2, 1.0);
        let project = |x: f64, y: f64| {
            let p = h * Vector3::new(x, y, 1.0);
            Vector2::new(p.x / p.z, p.y / p.z)
        };
        let (mut plane, mut image) = (Vec::new(), Vec::new());
        for dr in -3..=0 {
            for dc in 1..=3 {
                let q = Vector2::new(f64::from(dc), f64::from(dr));
                plane.push(q);
                image.push(project(q.x, q.y));
            }
        }
        let uv = image_of_origin(&plane, &image).unwrap();
        assert!((uv - project(0.0, 0.0)).norm() < 1e-6, "{uv:?}");
        // All cells at one point: no scale, no prediction.
        let same = vec![Vector2::new(5.0, 5.0); 6];
        assert_eq!(image_of_origin(&plane[..6], &same), None);
    }

    #[test]
    fn a_corner_captured_from_a_neighbouring_junction_is_dropped_and_only_it() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        // A face near 80° (steps 31 px and 30 px, 0.34 rad apart, as on the hard set where this
        // was found) under strong barrel distortion, with 0.3 px of corner noise: 8 × 10 cells.
        let h = Matrix3::new(28.4, -29.7, 500.0, 13.7, -2.9, 300.0, 1e-3, 2e-3, 1.0);
        let lattice = |r: f64, c: f64| {
            let p = h * Vector3::new(c, r, 1.0);
            let d = Vector2::new(p.x / p.z - 640.0, p.y / p.z - 480.0) / 700.0;
            Vector2::new(640.0, 480.0) + d * 700.0 * (1.0 - 0.3 * d.norm_squared())
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.3).unwrap();
        for seed in 0..20 {
            let mut cells = BTreeMap::new();
            for r in 0..8 {
                for c in 0..10 {
                    let e = Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
                    let uv = lattice(f64::from(r), f64::from(c)) + e;
                    cells.insert((r, c), Fitted::isotropic(uv, 0.3));
                }
            }
            let clean = cells.clone();
            assert_eq!(drop_off_lattice(&mut cells), vec![], "seed {seed}");
            assert_eq!(cells, clean);
            // The border corner (0, 1) fitted on the junction a diagonal step outside the grid,
            // and an interior one on its neighbour along the foreshortened axis.
            cells.get_mut(&(0, 1)).unwrap().uv = lattice(-1.0, 0.0);
            cells.get_mut(&(4, 5)).unwrap().uv = lattice(4.0, 6.0);
            let mut gone = drop_off_lattice(&mut cells);
            gone.sort_unstable();
            assert_eq!(gone, vec![(0, 1), (4, 5)], "seed {seed}");
        }
    }

    #[test]
    fn positions_beyond_any_window_lie_inside_the_frame_within_a_few_px_of_its_border() {
        let img = GrayImage::new(200, 100);
        // Square steps of 20 px: the window's half-extent is 13 px, shrinkable to 3 px.
        let (a, b) = (Vector2::new(20.0, 0.0), Vector2::new(0.0, 20.0));
        let at = |x: f64, y: f64| beyond_any_window(&img, Vector2::new(x, y), a, b);
        assert!(at(1.0, 50.0) && at(198.8, 50.0) && at(100.0, 1.9) && at(100.0, 97.6));
        assert!(!at(2.6, 50.0) && !at(100.0, 50.0) && !at(196.4, 50.0) && !at(100.0, 2.6));
        // Outside the frame: not held (a corner there is not visible).
        assert!(!at(-0.6, 50.0) && !at(199.6, 50.0) && !at(100.0, -1.0));
        // Diagonal steps: the window's corners reach farther along x.
        let (a, b) = (Vector2::new(14.0, 14.0), Vector2::new(-14.0, 14.0));
        assert!(beyond_any_window(&img, Vector2::new(3.5, 50.0), a, b));
        assert!(!beyond_any_window(&img, Vector2::new(5.0, 50.0), a, b));
    }

    #[test]
    fn lattice_curvature_of_parabolic_rows_and_straight_columns() {
        // Rows y = 10·r + κ·x²/2 (x from the middle column), bent towards +y, the left normal of +x.
        let kappa = 2e-3;
        let cells = cells_on(|r, c| {
            let x = 12.0 * f64::from(c - 3);
            Vector2::new(100.0 + x, 50.0 + 10.0 * f64::from(r) + 0.5 * kappa * x * x)
        });
        for c in 0..7 {
            let k = lattice_curvature(&cells, 2, c, 0, 1).unwrap();
            // Exact at the vertex, first order elsewhere (the chord tilts away from the tangent).
            assert!((k - kappa).abs() < 0.1 * kappa, "column {c}: {k}");
        }
        // The columns are straight (the rows' bend is along them).
        let k = lattice_curvature(&cells, 3, 3, 1, 0).unwrap();
        assert!(k.abs() < 1e-9, "{k}");
        // Three points make no estimate.
        let mut few = cells.clone();
        few.retain(|&(r, c), _| r != 4 || c < 3);
        assert_eq!(lattice_curvature(&few, 4, 0, 0, 1), None);
    }
}
