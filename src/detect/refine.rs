//! Sub-pixel corner refinement by fitting an X-junction model in a window shaped by the grid.
//!
//! Once a corner's grid neighbours are known, the image steps to them (`a` along the columns, `b`
//! along the rows) give the local affine frame of the board. The window is the parallelogram
//! `|s|, |t| ≤ w` in that frame (`q = p₀ + s·a + t·b`) with `w` = [`WINDOW`] below 1, so it covers only
//! the four squares around the corner and stays clear of the neighbouring corners (and so of the board
//! margin and other faces) by `1 − w` squares — however foreshortened the face is. Of that
//! parallelogram only the bands within [`BAND_PX`] of the two initial edge lines are used: the pixels
//! deep inside a square carry no information on the corner, and leaving them out keeps the cost
//! proportional to the window's extent rather than its area. In it the image is fitted by least
//! squares (Levenberg–Marquardt) with
//!
//! ```text
//! I(q) = m + h · tanh(d₁(q)/s) · tanh(d₂(q)/s),   dᵢ(q) = nᵢ(φᵢ) · (q − c)
//! ```
//!
//! seven parameters: the corner `c`, the two edge-line angles `φ₁, φ₂` (free: perspective makes them
//! non-perpendicular), the edge width `s` (blur), the mean level `m` and the half-contrast `h`. The
//! profile `tanh` stands for the blurred step; its exact shape does not bias `c`, because both the true
//! X-junction and the model are point-symmetric about the corner. Every pixel of the window contributes
//! (a saddle fit in a fixed 7×7 window uses 49), which is what makes the fit hold up under noise and
//! blur. The corner's variance falls with the edge length in the window, hence a window reaching 0.65
//! of the way to the next corner and a half-extent cap of 24 px (on the hard synthetic set, with the
//! curvature correction below, the corner RMS went from 0.134 px at 0.42 / 9 px to 0.097 px). With
//! `w > ½` the windows of neighbouring corners share the middle of their common edge, so their errors
//! are mildly correlated. The fit's covariance `σ̂²(JᵀJ)⁻¹` is the per-corner quality figure
//! ([`Refined::sigma_px`]): the standard deviation of the corner position implied by the residuals,
//! valid for independent pixel noise (sensor noise; JPEG or demosaicing correlate neighbouring pixels
//! and make it optimistic).
//!
//! The model's edges are straight, but lens distortion bends them, and a straight-line fit to a bent
//! edge is biased towards its concave side by about `κL²/6` (curvature `κ`, half-length `L`): on the
//! hard set (k1 −0.3) that is 0.05 px RMS of the corner in noise-free renders with this window. Fitting
//! the curvatures as two more parameters removes the bias but costs far more in variance (σ 0.072 →
//! 0.118 px: the curvature is confounded with the line's offset). Instead the fit reports the
//! first-order shift of the corner per unit curvature of each line ([`Refined::curvature_shift`], from
//! the same normal equations) and [`super::complete`] applies it with curvatures measured on the
//! lattice, where many corners determine them well (noise-free bias 0.047 → 0.026 px).
//!
//! Written here because no crate fits X-junction models: `chess-corners` refines with a saddle point
//! in a fixed window, OpenCV's `cornerSubPix` is a gradient-orthogonality iteration in a fixed square.

use image::GrayImage;
use nalgebra::{Matrix2, SMatrix, SVector, Vector2};

/// Half-size of the window in board units (the neighbouring corner is at 1).
pub const WINDOW: f64 = 0.65;
/// Largest window half-extent along a board axis, px. It bounds the cost on large squares; on the
/// hard set 16 / 20 / 24 / 30 px gave a corner RMS of 0.108 / 0.101 / 0.097 / 0.097 px.
pub const MAX_HALF_PX: f64 = 24.0;
/// Half-width of the bands around the two initial edge lines that make up the window, px: pixels
/// farther than this from both lines (deep inside a square) are left out. A blurred edge is flat
/// beyond about 3 edge widths (~5 px at blur σ 1.5); the rest is the initial lines' error (start
/// position and angle). 6 px lost 3 of 36 faces on the hard set.
pub const BAND_PX: f64 = 8.0;
/// Smallest window half-extent along a board axis, px.
pub const MIN_HALF_PX: f64 = 1.5;
/// Fewest pixels a fit may use.
pub const MIN_PIXELS: usize = 16;
/// Fewest pixels in each quadrant for the alternation test.
pub const MIN_QUADRANT_PIXELS: usize = 2;
/// See [`quadrants_alternate`].
pub const MIN_QUADRANT_SEPARATION: f64 = 0.35;
/// Iteration cap of the fit.
pub const MAX_ITERATIONS: usize = 20;
/// The fit stops when the corner moves less than this in one step (px).
pub const CONVERGED_PX: f64 = 1e-3;
/// The fitted corner may move at most this far from its start, in board units.
pub const MAX_SHIFT: f64 = 0.3;
/// Smallest half-contrast `|h|` over its own standard deviation for a fit to count (a corner, not
/// noise).
pub const MIN_SNR: f64 = 10.0;
/// Smallest angle between the two fitted edge lines (radians).
pub const MIN_LINE_ANGLE: f64 = 0.25;

/// A refined corner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refined {
    pub uv: Vector2<f64>,
    /// Estimated standard deviation of each coordinate of `uv`, px (√ of the mean of the two
    /// variances of the fit's covariance).
    pub sigma_px: f64,
    /// Fitted half-contrast |h| (grey levels).
    pub contrast: f64,
    /// Residual RMS of the fit (grey levels).
    pub residual: f64,
    /// Fitted edge width `s` (px).
    pub edge_width: f64,
    /// First-order shift of `uv` per unit curvature (1/px) of the two edge lines, column 0 for the
    /// line along `a`, column 1 for the line along `b`: the corner had the lines been fitted with
    /// curvatures `κ` is `uv + curvature_shift·κ`. Line `i` runs along `uᵢ` (`a` or `b`) with left
    /// normal `nᵢ = (−uᵢ.y, uᵢ.x)`; `κᵢ > 0` bends it towards `nᵢ`: `q = c + t·uᵢ + κᵢ·t²/2·nᵢ`.
    pub curvature_shift: Matrix2<f64>,
}

/// Why a fit was not accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RefineFailure {
    /// Too few pixels in the window (too small or outside the image).
    Window,
    /// The normal equations became singular or values non-finite.
    Degenerate,
    /// The corner moved too far from its start.
    Moved,
    /// Contrast too low for the residual noise.
    Weak,
    /// The two fitted edge lines are nearly parallel.
    Parallel,
    /// The four quadrants do not alternate dark / bright (an edge, a T- or L-junction, not a corner).
    NotX,
}

type P = SVector<f64, 7>;

struct Window {
    /// Pixel centre coordinates relative to `p0` and values.
    px: Vec<(f64, f64, f64)>,
}

fn window(img: &GrayImage, p0: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> Option<Window> {
    let la = a.norm();
    let lb = b.norm();
    if !(la.is_finite() && lb.is_finite()) || la < 1e-6 || lb < 1e-6 {
        return None;
    }
    let ws = (WINDOW * la).clamp(MIN_HALF_PX, MAX_HALF_PX) / la;
    let wt = (WINDOW * lb).clamp(MIN_HALF_PX, MAX_HALF_PX) / lb;
    let inv = Matrix2::from_columns(&[a, b]).try_inverse()?;
    // Unit normals of the initial edge lines through `p0`.
    let na = Vector2::new(-a.y, a.x) / la;
    let nb = Vector2::new(-b.y, b.x) / lb;
    // Bounding box of the parallelogram.
    let ext = a.abs() * ws + b.abs() * wt;
    let x0 = (p0.x - ext.x).floor() as i64;
    let x1 = (p0.x + ext.x).ceil() as i64;
    let y0 = (p0.y - ext.y).floor() as i64;
    let y1 = (p0.y + ext.y).ceil() as i64;
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    let mut px = Vec::new();
    let mut clipped = 0usize;
    for y in y0..=y1 {
        for x in x0..=x1 {
            let q = Vector2::new(x as f64 - p0.x, y as f64 - p0.y);
            let st = inv * q;
            if st.x.abs() > ws
                || st.y.abs() > wt
                || na.dot(&q).abs().min(nb.dot(&q).abs()) > BAND_PX
            {
                continue;
            }
            if x < 0 || y < 0 || x >= w || y >= h {
                clipped += 1;
                continue;
            }
            let v = f64::from(img.get_pixel(x as u32, y as u32).0[0]);
            px.push((q.x, q.y, v));
        }
    }
    // The window must lie (almost) entirely inside the image: a clipped window is asymmetric.
    (px.len() >= MIN_PIXELS && clipped as f64 <= 0.15 * (px.len() + clipped) as f64)
        .then_some(Window { px })
}

/// `tanh` to within 1e-4 (Lambert's continued fraction to the 7th order, held at its value at ±4.97, 1 − 6·10⁻⁷, beyond):
/// a fit evaluates it twice per pixel per iteration, and `f64::tanh` made it 70 % of the fit's time.
/// The profile's exact shape does not bias the corner (see the module doc).
#[inline]
fn tanh(x: f64) -> f64 {
    // Clamped rather than branched: half the pixels of a window saturate, unpredictably.
    let x = x.clamp(-4.97, 4.97);
    let x2 = x * x;
    x * (135_135.0 + x2 * (17_325.0 + x2 * (378.0 + x2)))
        / (135_135.0 + x2 * (62_370.0 + x2 * (3_150.0 + 28.0 * x2)))
}

/// Residuals and Jacobian rows of the model at `p` (coordinates relative to `p0`).
fn accumulate(win: &Window, p: &P) -> (SMatrix<f64, 7, 7>, P, f64) {
    let (cx, cy, f1, f2, s, m, h) = (p[0], p[1], p[2], p[3], p[4], p[5], p[6]);
    let (s1, c1) = f1.sin_cos();
    let (s2, c2) = f2.sin_cos();
    let inv_s = 1.0 / s;
    // Upper triangle of JᵀJ, row by row, as a flat array: the compiler keeps it in registers.
    let mut upper = [0.0_f64; 28];
    let mut jtr = [0.0_f64; 7];
    let mut ssr = 0.0;
    for &(x, y, v) in &win.px {
        let (dx, dy) = (x - cx, y - cy);
        // Normals of the lines along (cos φ, sin φ): (−sin φ, cos φ).
        let d1 = -s1 * dx + c1 * dy;
        let d2 = -s2 * dx + c2 * dy;
        let g1 = tanh(d1 * inv_s);
        let g2 = tanh(d2 * inv_s);
        let e1 = 1.0 - g1 * g1;
        let e2 = 1.0 - g2 * g2;
        let r = m + h * g1 * g2 - v;
        // ∂dᵢ/∂c = −nᵢ; ∂dᵢ/∂φᵢ = −(cos φᵢ, sin φᵢ)·(q − c).
        let dg1 = h * g2 * e1 * inv_s;
        let dg2 = h * g1 * e2 * inv_s;
        let j = [
            dg1 * s1 + dg2 * s2,
            -dg1 * c1 - dg2 * c2,
            dg1 * -(c1 * dx + s1 * dy),
            dg2 * -(c2 * dx + s2 * dy),
            -(dg1 * d1 + dg2 * d2) * inv_s,
            1.0,
            g1 * g2,
        ];
        let mut k = 0;
        for a in 0..7 {
            for b in a..7 {
                upper[k] += j[a] * j[b];
                k += 1;
            }
            jtr[a] += j[a] * r;
        }
        ssr += r * r;
    }
    let mut jtj = SMatrix::<f64, 7, 7>::zeros();
    let mut k = 0;
    for a in 0..7 {
        for b in a..7 {
            jtj[(a, b)] = upper[k];
            jtj[(b, a)] = upper[k];
            k += 1;
        }
    }
    (jtj, P::from(jtr), ssr)
}

/// The first-order shift of the corner per unit curvature of each line ([`Refined::curvature_shift`]) at
/// the converged straight-line fit `p` with normal matrix `jtj`: with the curvatures held at `κ`
/// instead of 0, the normal equations move the seven parameters by `−(JᵀJ)⁻¹·Jᵀ J_κ·κ`, where
/// `J_κ` are the residuals' derivatives in `κ` (`∂dᵢ/∂κᵢ = −tᵢ²/2`).
fn curvature_shift(win: &Window, p: &P, jtj: &SMatrix<f64, 7, 7>) -> Option<Matrix2<f64>> {
    let (cx, cy, f1, f2, s, _, h) = (p[0], p[1], p[2], p[3], p[4], p[5], p[6]);
    let (s1, c1) = f1.sin_cos();
    let (s2, c2) = f2.sin_cos();
    let inv_s = 1.0 / s;
    let mut cross = SMatrix::<f64, 7, 2>::zeros();
    for &(x, y, _) in &win.px {
        let (dx, dy) = (x - cx, y - cy);
        let d1 = -s1 * dx + c1 * dy;
        let d2 = -s2 * dx + c2 * dy;
        let (t1, t2) = (c1 * dx + s1 * dy, c2 * dx + s2 * dy);
        let g1 = tanh(d1 * inv_s);
        let g2 = tanh(d2 * inv_s);
        let dg1 = h * g2 * (1.0 - g1 * g1) * inv_s;
        let dg2 = h * g1 * (1.0 - g2 * g2) * inv_s;
        let j = SVector::<f64, 7>::from([
            dg1 * s1 + dg2 * s2,
            -dg1 * c1 - dg2 * c2,
            -dg1 * t1,
            -dg2 * t2,
            -(dg1 * d1 + dg2 * d2) * inv_s,
            1.0,
            g1 * g2,
        ]);
        let jk = [-0.5 * dg1 * t1 * t1, -0.5 * dg2 * t2 * t2];
        for (k, jk) in jk.iter().enumerate() {
            cross.column_mut(k).axpy(*jk, &j, 1.0);
        }
    }
    let shift = -(jtj.cholesky()?.solve(&cross));
    Some(shift.fixed_view::<2, 2>(0, 0).into_owned())
}

/// Whether the fitted junction's quadrants (pixels beyond one edge width of both lines) alternate:
/// the darker of the two bright quadrants must exceed the brighter of the two dark ones by at least
/// [`MIN_QUADRANT_SEPARATION`] × the fitted contrast `2|h|`.
fn quadrants_alternate(win: &Window, p: &P) -> bool {
    let (cx, cy, f1, f2, s, _, h) = (p[0], p[1], p[2], p[3], p[4], p[5], p[6]);
    let (s1, c1) = f1.sin_cos();
    let (s2, c2) = f2.sin_cos();
    let mut sum = [0.0; 4];
    let mut n = [0usize; 4];
    for &(x, y, v) in &win.px {
        let (dx, dy) = (x - cx, y - cy);
        let d1 = -s1 * dx + c1 * dy;
        let d2 = -s2 * dx + c2 * dy;
        if d1.abs() < s || d2.abs() < s {
            continue;
        }
        let k = usize::from(d1 > 0.0) * 2 + usize::from(d2 > 0.0);
        sum[k] += v;
        n[k] += 1;
    }
    if n.iter().any(|&k| k < MIN_QUADRANT_PIXELS) {
        return false;
    }
    let mean = |k: usize| sum[k] / n[k] as f64;
    // Quadrants 0 (−,−) and 3 (+,+) have d₁·d₂ > 0: bright when h > 0.
    let (pos, neg) = (mean(0).min(mean(3)), mean(1).max(mean(2)));
    let (pos_hi, neg_lo) = (mean(0).max(mean(3)), mean(1).min(mean(2)));
    let separation = if h > 0.0 { pos - neg } else { neg_lo - pos_hi };
    separation >= MIN_QUADRANT_SEPARATION * 2.0 * h.abs()
}

/// Refine the corner near `p0` given the image steps `a` (to the next column) and `b` (to the next
/// row) of its grid.
pub fn refine(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Result<Refined, RefineFailure> {
    let win = window(img, p0, a, b).ok_or(RefineFailure::Window)?;
    let n = win.px.len() as f64;
    let mean = win.px.iter().map(|p| p.2).sum::<f64>() / n;
    let f1 = a.y.atan2(a.x);
    let f2 = b.y.atan2(b.x);
    let s0 = (0.15 * a.norm().min(b.norm())).clamp(0.7, 3.0);
    // Initial half-contrast: least-squares h for the initial geometry.
    let mut p = P::from([0.0, 0.0, f1, f2, s0, mean, 0.0]);
    {
        let (mut num, mut den) = (0.0, 0.0);
        let (s1, c1) = f1.sin_cos();
        let (s2, c2) = f2.sin_cos();
        for &(x, y, v) in &win.px {
            let g = tanh((-s1 * x + c1 * y) / s0) * tanh((-s2 * x + c2 * y) / s0);
            num += g * (v - mean);
            den += g * g;
        }
        if den <= 0.0 {
            return Err(RefineFailure::Degenerate);
        }
        p[6] = num / den;
    }
    let (mut jtj, mut jtr, mut ssr) = accumulate(&win, &p);
    let mut lambda = 1e-3;
    let to_board = Matrix2::from_columns(&[a, b])
        .try_inverse()
        .ok_or(RefineFailure::Degenerate)?;
    for _ in 0..MAX_ITERATIONS {
        let mut a_mat = jtj;
        for i in 0..7 {
            a_mat[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
        }
        let Some(chol) = a_mat.cholesky() else {
            lambda *= 10.0;
            if lambda > 1e8 {
                return Err(RefineFailure::Degenerate);
            }
            continue;
        };
        let step = chol.solve(&(-jtr));
        let mut cand = p + step;
        cand[4] = cand[4].abs().max(0.2);
        let (j2, r2, s2) = accumulate(&win, &cand);
        if s2.is_finite() && s2 < ssr {
            p = cand;
            // A fit running away from its start will be rejected: stop paying for it.
            let st = to_board * Vector2::new(p[0], p[1]);
            if st.x.abs() > 2.0 * MAX_SHIFT || st.y.abs() > 2.0 * MAX_SHIFT {
                return Err(RefineFailure::Moved);
            }
            jtj = j2;
            jtr = r2;
            let done = step[0].hypot(step[1]) < CONVERGED_PX;
            ssr = s2;
            lambda = (lambda * 0.3).max(1e-9);
            if done {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    let c = Vector2::new(p[0], p[1]);
    if !c.iter().all(|v| v.is_finite()) {
        return Err(RefineFailure::Degenerate);
    }
    // Shift in board units.
    let st = to_board * c;
    if st.x.abs() > MAX_SHIFT || st.y.abs() > MAX_SHIFT {
        return Err(RefineFailure::Moved);
    }
    let dof = (n - 7.0).max(1.0);
    let var = ssr / dof;
    let residual = var.sqrt();
    let contrast = p[6].abs();
    let cov = jtj.try_inverse().ok_or(RefineFailure::Degenerate)? * var;
    if contrast < MIN_SNR * cov[(6, 6)].max(0.0).sqrt() {
        return Err(RefineFailure::Weak);
    }
    let dphi = (p[2] - p[3]).rem_euclid(std::f64::consts::PI);
    if dphi.min(std::f64::consts::PI - dphi) < MIN_LINE_ANGLE {
        return Err(RefineFailure::Parallel);
    }
    if !quadrants_alternate(&win, &p) {
        return Err(RefineFailure::NotX);
    }
    let sigma_px = ((cov[(0, 0)] + cov[(1, 1)]) / 2.0).max(0.0).sqrt();
    let curvature_shift = curvature_shift(&win, &p, &jtj).ok_or(RefineFailure::Degenerate)?;
    Ok(Refined {
        uv: p0 + c,
        sigma_px,
        contrast,
        residual,
        edge_width: p[4],
        curvature_shift,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// An exactly area-sampled X-junction: lines through `c` along `u` and `v`, 8×8 supersampling.
    fn xjunction(size: u32, c: Vector2<f64>, u: f64, v: f64) -> GrayImage {
        let (su, cu) = u.sin_cos();
        let (sv, cv) = v.sin_cos();
        GrayImage::from_fn(size, size, |x, y| {
            let mut acc = 0.0_f64;
            for i in 0..8 {
                for j in 0..8 {
                    let qx = f64::from(x) - 0.5 + (f64::from(i) + 0.5) / 8.0 - c.x;
                    let qy = f64::from(y) - 0.5 + (f64::from(j) + 0.5) / 8.0 - c.y;
                    let d1 = -su * qx + cu * qy;
                    let d2 = -sv * qx + cv * qy;
                    acc += if d1 * d2 > 0.0 { 220.0 } else { 30.0 };
                }
            }
            image::Luma([(acc / 64.0).round() as u8])
        })
    }

    #[test]
    fn finds_an_oblique_junction_to_a_hundredth_of_a_pixel() {
        let c = Vector2::new(20.37, 19.81);
        let (u, v) = (0.3_f64, 1.3_f64);
        let img = xjunction(41, c, u, v);
        let a = Vector2::new(u.cos(), u.sin()) * 14.0;
        let b = Vector2::new(v.cos(), v.sin()) * 9.0;
        // Sharp (area-sampled only): the worst case for the tanh profile.
        let r = refine(&img, Vector2::new(20.0, 20.0), a, b).unwrap();
        assert!((r.uv - c).norm() < 0.02, "{:?} vs {c:?}", r.uv);
        assert!(r.sigma_px < 0.05, "{r:?}");
        // Blurred as a lens does.
        let blurred = image::imageops::blur(&img, 1.0);
        let r = refine(&blurred, Vector2::new(20.0, 20.0), a, b).unwrap();
        assert!((r.uv - c).norm() < 0.01, "{:?} vs {c:?}", r.uv);
    }

    #[test]
    fn curvature_shift_corrects_a_bent_edge() {
        // Two lines through c: along x (bent towards +y: y = κ·x²/2) and straight along y. Its left
        // normal is +y, so κ > 0; the straight fit is pulled towards the concave side (+y).
        let c = Vector2::new(30.0, 30.0);
        let kappa = 0.01;
        let img = GrayImage::from_fn(61, 61, |x, y| {
            let mut acc = 0.0_f64;
            for i in 0..8 {
                for j in 0..8 {
                    let qx = f64::from(x) - 0.5 + (f64::from(i) + 0.5) / 8.0 - c.x;
                    let qy = f64::from(y) - 0.5 + (f64::from(j) + 0.5) / 8.0 - c.y;
                    let d1 = qy - 0.5 * kappa * qx * qx;
                    acc += if d1 * qx > 0.0 { 220.0 } else { 30.0 };
                }
            }
            image::Luma([(acc / 64.0).round() as u8])
        });
        let img = image::imageops::blur(&img, 1.0);
        let a = Vector2::new(30.0, 0.0);
        let b = Vector2::new(0.0, 30.0);
        let r = refine(&img, c, a, b).unwrap();
        let straight = r.uv - c;
        let curved = r.uv + r.curvature_shift * Vector2::new(kappa, 0.0) - c;
        assert!(straight.y > 0.1, "{straight:?}");
        assert!(
            curved.norm() < 0.25 * straight.norm(),
            "{curved:?} vs {straight:?}"
        );
    }

    #[test]
    fn an_l_junction_is_not_a_corner() {
        // One dark quadrant, three bright: the corner of a board's outer square against its margin.
        let img = GrayImage::from_fn(40, 40, |x, y| {
            image::Luma([if x < 20 && y < 20 { 30 } else { 220 }])
        });
        let a = Vector2::new(12.0, 0.0);
        let b = Vector2::new(0.0, 12.0);
        assert!(refine(&img, Vector2::new(19.5, 19.5), a, b).is_err());
    }

    #[test]
    fn flat_window_is_rejected() {
        let img = GrayImage::from_pixel(40, 40, image::Luma([128]));
        let a = Vector2::new(10.0, 0.0);
        let b = Vector2::new(0.0, 10.0);
        assert!(refine(&img, Vector2::new(20.0, 20.0), a, b).is_err());
    }

    #[test]
    fn window_outside_the_image_is_rejected() {
        let img = xjunction(30, Vector2::new(15.0, 15.0), 0.0, 1.5);
        let a = Vector2::new(10.0, 0.0);
        let b = Vector2::new(0.0, 10.0);
        assert_eq!(
            refine(&img, Vector2::new(1.0, 1.0), a, b),
            Err(RefineFailure::Window)
        );
    }
}
