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
//! ([`Refined::sigma_px`]): the standard deviation of the corner position implied by the residuals
//! (`σ̂²` from the first stage's wide bands, see below, where the model's mismatch at the edges
//! weighs less), valid for independent pixel noise (sensor noise; JPEG or demosaicing correlate neighbouring pixels
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
//! With a calibrated lens, [`refine_mapped`] fits the same model at the pixels' undistorted positions
//! (see [`super::undistorted`]): there the edges are straight and no correction is needed. On
//! noise-free renders with k1 −0.3 and the rig near the image corners the mean error of the corners
//! in the outer 10 % of the image went from 0.0023 to 0.0005 px, and at 0.9–1.0 of the
//! half-diagonal from 0.0081 to 0.0024 px (`NOISE=0 REREFINE=1 detect_eval periphery-0.3 24`).
//!
//! **Longer windows** (measured on the hard set, where the fit is at its noise limit: RMS 0.098 px,
//! RMS/(√2 σ) 0.94). Widening the parallelogram alone does not help (`WINDOW` 0.75 / 0.85 / 0.95:
//! 0.0955 / 0.0993 / 0.118 px): the neighbouring corners' blurred edges enter it. A model that
//! stays valid past the neighbours (the X-junction times fixed `tanh` factors of the four
//! neighbouring lattice lines, pixels near them masked, symmetric windows up to 1.5 squares / 48 px,
//! a quadratic profile term for gamma) reached 0.087 px (realistic 0.0118) but tripled the fit's
//! instructions and doubled the correlation of adjacent corners' errors (0.11 → 0.25); the corners
//! on a board's border, 45 % of them, cannot be extended that way. It is kept on the branch
//! `hard-rms`, not here. A second try (branch `edges`) kept this fit and measured each of the
//! corner's two lines again *outside* its window, along the edges to and past its neighbours (the
//! edge modulated by `tanh` factors of the crossing lattice lines, a level and contrast per side, the
//! lattice curvature, one Gauss–Newton step), combined with the fit by inverse covariance: hard
//! 0.098 → 0.089 px (σ 0.074 → 0.062, honest), realistic unchanged, but twice the detection time
//! before any optimisation; following the lines further (two, three neighbours) lowered σ to
//! 0.054 px without lowering the error (the lattice curvature, itself from the noisy corners, and the
//! neighbours' positions then dominate), and adding the strips' slopes to the fit's angles made the
//! realistic set worse (0.0138 → 0.0169 px). What limits the hard set is the foreshortened line of
//! faces at 60–75°: its squares are 10–17 px long, so every stretch of it lies within a few edge
//! widths of a crossing.
//!
//! **Cost.** The fit runs in two stages. The first starts from the grid's estimate (the front end's
//! position, the lattice's directions) on a quarter of the window's pixels (even rows and columns)
//! and only has to converge to ~0.1 px; the second fits every pixel within `2.5 s + 0.5` px of the
//! lines the first found (the blurred edge's slope is down to 3 % there), starting so close that one
//! or two evaluations finish it, the last step taken without another (see `FINE`). Before either, a
//! loose version of the quadrant test below ([`MIN_START_SEPARATION`]) drops the windows with no
//! X-junction at all: completion tries every cell around a grid, and those fits, which ran to the
//! iteration cap, were 63 % of the time. The per-pixel work is single precision in groups of
//! `LANES` pixels, structure-of-arrays, written so that it compiles to SIMD instructions (the
//! sums of squares are of a few hundred terms of similar size: single precision keeps them to
//! ~10⁻⁵, far below the noise). On the benchmark frame (`cargo bench --bench detect`, 1280×960,
//! three faces, 170 corners) these took the fit from 80 ms to under 10 ms, with the corner errors
//! on the synthetic sets unchanged (realistic RMS 0.0137 px, hard 0.0956 px, same faces found).
//! The windows' arrays are reused from fit to fit (`Window`) and the sums are kept in four lanes
//! (see `accumulate`): together 37 → 29 M instructions per bench frame, results unchanged.
//!
//! Written here because no crate fits X-junction models: `chess-corners` refines with a saddle point
//! in a fixed window, OpenCV's `cornerSubPix` is a gradient-orthogonality iteration in a fixed square.

use std::cell::Cell;

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
/// Smallest window half-extent (px, along each board axis) a corner near the image border is fitted
/// with: its window shrinks to fit inside the image rather than being clipped (a clipped window is
/// asymmetric and biases the fit). Corners 5–10 px from the border of a board that fills the frame,
/// or of a face near an image corner, were dropped before, and their grid with them.
pub const MIN_BORDER_HALF_PX: f64 = 3.0;
/// Fewest pixels a fit may use.
pub const MIN_PIXELS: usize = 16;
/// Fewest pixels in each quadrant for the alternation test.
pub const MIN_QUADRANT_PIXELS: usize = 2;
/// See [`quadrants_alternate`].
pub const MIN_QUADRANT_SEPARATION: f64 = 0.35;
/// The same test, loose, on the starting geometry: a window that fails it is not fitted.
pub const MIN_START_SEPARATION: f64 = 0.1;
/// Iteration cap of the fit.
pub const MAX_ITERATIONS: usize = 20;
/// When the first stage (a quarter of the pixels, see [`refine`]) stops: it only has to bring the
/// second within its linear range.
const COARSE: Tolerance = Tolerance {
    position_px: 0.1,
    angle: 0.05,
    width: 0.3,
    decrease: 1.0,
};
/// When the second stage stops. Its last step is taken without evaluating the model again: from a
/// point this close, one Gauss–Newton step lands within about its square of the optimum. On the
/// synthetic sets, stopping at a step of 0.05 px instead of 0.001 px changed the corner RMS by less
/// than 0.0001 px (realistic 0.0137, hard 0.0956) and lost no face, with 1.3 instead of 2.4
/// evaluations of the full window per corner. Without the angle, width and decrease conditions (the
/// position alone) two faces were lost: recovered corners whose residual, taken before a large
/// change of the edge width, looked unlike the grid's.
const FINE: Tolerance = Tolerance {
    position_px: 0.05,
    angle: 0.01,
    width: 0.05,
    decrease: 0.2,
};
/// Windows of at least this area (px², parallelogram before banding) start on a quarter of their
/// pixels.
pub const COARSE_MIN_AREA_PX: f64 = 400.0;
/// The second stage's bands: this many fitted edge widths `s` plus [`FINE_BAND_MARGIN_PX`] on each
/// side of the lines, at least [`MIN_FINE_BAND_PX`], at most [`BAND_PX`]. At `2.5 s` the blurred
/// edge's slope (`sech²`) is down to 3 % of its peak, so the pixels beyond carry ~0.1 % of the
/// information on the corner.
pub const FINE_BAND_WIDTHS: f64 = 2.5;
pub const FINE_BAND_MARGIN_PX: f64 = 0.5;
pub const MIN_FINE_BAND_PX: f64 = 2.5;
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
    /// Covariance of `uv` (px²): the fit's `(JᵀJ)⁻¹` position block scaled by the window's residual
    /// noise (see the module docs). `sigma_px` is `√(trace/2)` of it.
    pub cov: Matrix2<f64>,
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
    /// The squares' mean level and half-contrast (grey levels), measured on their flat parts (see
    /// [`SQUARE_WIDTHS`]), `None` where either colour has too few such pixels in the window. Unlike
    /// the fitted level `m` and `contrast`, these do not take up the model's mismatch with the blurred junction,
    /// which changes with the window's shape (across a receding face, from corner to corner): the
    /// brightness gradient [`Self::shading_shift`] is applied with is measured on them.
    pub squares: Option<[f64; 2]>,
    /// First-order shift of `uv` per unit relative gradient of the brightness across the window
    /// (1/px, image axes): the corner had the model carried the shading `γ` (`(m + h·G)·(1 + γ·(q −
    /// c))` instead of constant levels) is `uv + shading_shift·γ`. Vignetting and uneven light scale
    /// the scene's radiance, and a power-law response keeps a scale a scale, so both the level and
    /// the contrast vary across a window by the same factor; the model's constant levels then pull
    /// the corner toward the brighter side (see the module docs). In image units also for a mapped
    /// fit.
    pub shading_shift: Matrix2<f64>,
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

/// Pixels are processed in groups of this many, one array per quantity, so that the per-pixel work
/// (the model, its Jacobian row and the normal-equation products) compiles to SIMD instructions.
const LANES: usize = 8;
type Lane = [f32; LANES];

/// The window's pixels, structure-of-arrays, padded to a whole number of groups of [`LANES`] with
/// pixels of weight 0. The arrays are kept from one fit to the next (see [`refine`]) and only grow:
/// a run of a window's row, 9 pixels on average, is then a few stores per pixel, where filling new
/// vectors (`extend` per run, with its reservation and remainder loops) took a sixth of the fit's
/// instructions.
#[derive(Default)]
struct Window {
    /// Pixel-centre coordinates relative to `p0`.
    x: Vec<f32>,
    y: Vec<f32>,
    /// Grey values.
    v: Vec<f32>,
    /// 1 for a pixel, 0 for padding.
    w: Vec<f32>,
    /// Number of (real) pixels.
    n: usize,
    /// Number of pixels with the padding (a multiple of [`LANES`]).
    len: usize,
}

/// One group of pixels.
struct Group<'a> {
    x: &'a Lane,
    y: &'a Lane,
    v: &'a Lane,
    w: &'a Lane,
}

impl Window {
    /// Empties the window, with room for `n` pixels.
    fn reset(&mut self, n: usize) {
        let n = n + LANES;
        if self.x.len() < n {
            for q in [&mut self.x, &mut self.y, &mut self.v, &mut self.w] {
                q.resize(n, 0.0);
            }
        }
        self.n = 0;
        self.len = 0;
    }

    /// Appends a run of pixels of one row: every `step`-th of `pixels`, with `dx0`, `dy` the first
    /// one's offset from `p0`.
    fn push_run(&mut self, dx0: f32, dy: f32, pixels: &[u8], step: usize) {
        let k = pixels.len().div_ceil(step);
        let (base, end) = (self.n, self.n + k);
        if end + LANES > self.x.len() {
            // More than `reset` was told (it is given an upper bound).
            for q in [&mut self.x, &mut self.y, &mut self.v, &mut self.w] {
                q.resize(end + LANES, 0.0);
            }
        }
        // (Through i32: converting a usize to f32 is a slow sequence on x86-64.)
        let step_f = step as i32;
        let xs = self.x[base..end].iter_mut();
        let ys = self.y[base..end].iter_mut();
        let vs = self.v[base..end].iter_mut();
        for (i, ((x, y), v)) in (0i32..).zip(xs.zip(ys).zip(vs)) {
            *x = dx0 + (i * step_f) as f32;
            *y = dy;
            *v = f32::from(pixels[(i * step_f) as usize]);
        }
        self.n = end;
    }

    /// Pads the pixels to whole groups and sets the weights.
    fn finish(&mut self) {
        let (n, len) = (self.n, self.n.div_ceil(LANES) * LANES);
        self.w[..n].fill(1.0);
        for q in [&mut self.x, &mut self.y, &mut self.v, &mut self.w] {
            q[n..len].fill(0.0);
        }
        self.len = len;
    }

    fn groups(&self) -> impl Iterator<Item = Group<'_>> {
        let (x, _) = self.x[..self.len].as_chunks::<LANES>();
        let (y, _) = self.y[..self.len].as_chunks::<LANES>();
        let (v, _) = self.v[..self.len].as_chunks::<LANES>();
        let (w, _) = self.w[..self.len].as_chunks::<LANES>();
        x.iter()
            .zip(y)
            .zip(v)
            .zip(w)
            .map(|(((x, y), v), w)| Group { x, y, v, w })
    }
}

/// `⌊x⌋` for the window's coordinates (finite, far inside `i64`). Written out because without SSE4.1
/// (the x86-64 baseline) `f64::floor` is a library call, made four times per window row.
#[inline]
fn floor(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// `⌈x⌉`, as [`floor`].
#[inline]
fn ceil(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) < x {
        t.saturating_add(1)
    } else {
        t
    }
}

/// The `dx` interval (closed) where `|nx·dx + c| ≤ half`; `None` if empty.
fn slab(nx: f64, c: f64, half: f64) -> Option<(f64, f64)> {
    if nx.abs() < 1e-12 {
        return (c.abs() <= half).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let (lo, hi) = ((-half - c) / nx, (half - c) / nx);
    Some(if lo <= hi { (lo, hi) } else { (hi, lo) })
}

/// The lines' geometry a window's bands follow: their crossing (relative to `p0`) and unit normals.
#[derive(Clone, Copy)]
struct Bands {
    centre: Vector2<f64>,
    normals: [Vector2<f64>; 2],
    /// Half-width of the band around each line (px).
    half_width: [f64; 2],
}

/// The pixels of the parallelogram `|s| ≤ ws, |t| ≤ wt` around `p0` (steps `a`, `b`) that lie in one
/// of the two `bands`; with `coarse`, only the pixels of even row and column (a quarter).
fn window(
    win: &mut Window,
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    bands: Option<Bands>,
    coarse: bool,
    shrink: bool,
) -> Option<()> {
    let la = a.norm();
    let lb = b.norm();
    if !(la.is_finite() && lb.is_finite()) || la < 1e-6 || lb < 1e-6 {
        return None;
    }
    let ws = (WINDOW * la).clamp(MIN_HALF_PX, MAX_HALF_PX) / la;
    let wt = (WINDOW * lb).clamp(MIN_HALF_PX, MAX_HALF_PX) / lb;
    // Near the image border the parallelogram shrinks about `p0` until it fits (it stays symmetric,
    // so the fit stays unbiased), down to half-extents of [`MIN_BORDER_HALF_PX`].
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    let ext = |u: f64, v: f64| u.abs() * ws + v.abs() * wt;
    let room = [
        (p0.x + 0.5) / ext(a.x, b.x),
        (w - 0.5 - p0.x) / ext(a.x, b.x),
        (p0.y + 0.5) / ext(a.y, b.y),
        (h - 0.5 - p0.y) / ext(a.y, b.y),
    ]
    .into_iter()
    .fold(1.0_f64, f64::min);
    let shrink =
        if shrink && room < 1.0 && (room * ws * la).min(room * wt * lb) >= MIN_BORDER_HALF_PX {
            room
        } else {
            1.0
        };
    let (ws, wt) = (ws * shrink, wt * shrink);
    let inv = Matrix2::from_columns(&[a, b]).try_inverse()?;
    // By default the bands follow the initial edge lines through `p0`.
    let bands = bands.unwrap_or(Bands {
        centre: Vector2::zeros(),
        normals: [Vector2::new(-a.y, a.x) / la, Vector2::new(-b.y, b.x) / lb],
        half_width: [BAND_PX; 2],
    });
    let [na, nb] = bands.normals;
    let nc = [na.dot(&bands.centre), nb.dot(&bands.centre)];
    // Row range of the parallelogram; in each row, the pixels are the intersection of the two slabs
    // |s| ≤ ws, |t| ≤ wt with the union of the two bands |nᵢ·q| ≤ BAND_PX.
    let ext_y = a.y.abs() * ws + b.y.abs() * wt;
    let y0 = (p0.y - ext_y).floor() as i64;
    let y1 = (p0.y + ext_y).ceil() as i64;
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    let raw = img.as_raw();
    // Room for the whole parallelogram (an upper bound on the bands' pixels).
    let bound = 4.0 * ws * wt * (a.x * b.y - a.y * b.x).abs()
        + 4.0 * (ext_y + a.x.abs() * ws + b.x.abs() * wt)
        + 16.0;
    win.reset(bound as usize / if coarse { 4 } else { 1 });
    // In-band positions outside and inside the image (every column of the rows visited).
    let mut clipped = 0usize;
    let mut inside = 0usize;
    for y in y0..=y1 {
        if coarse && y.rem_euclid(2) == 1 {
            continue;
        }
        let dy = y as f64 - p0.y;
        let (Some(sa), Some(sb)) = (
            slab(inv[(0, 0)], inv[(0, 1)] * dy, ws),
            slab(inv[(1, 0)], inv[(1, 1)] * dy, wt),
        ) else {
            continue;
        };
        let lo = if sa.0 > sb.0 { sa.0 } else { sb.0 };
        let hi = if sa.1 < sb.1 { sa.1 } else { sb.1 };
        if lo > hi {
            continue;
        }
        // The two bands' spans within the parallelogram's, the one starting first first (an empty
        // span has its start past its end).
        let clip = |band: Option<(f64, f64)>| match band {
            Some((l, u)) => (if l > lo { l } else { lo }, if u < hi { u } else { hi }),
            None => (f64::INFINITY, f64::NEG_INFINITY),
        };
        let mut spans = [
            clip(slab(na.x, na.y * dy - nc[0], bands.half_width[0])),
            clip(slab(nb.x, nb.y * dy - nc[1], bands.half_width[1])),
        ];
        if spans[1].0 < spans[0].0 {
            spans.swap(0, 1);
        }
        // Pixel columns of the bands, each taken once.
        let mut next = i64::MIN;
        for (l, u) in spans {
            if l > u {
                continue;
            }
            let x0 = ceil(p0.x + l).max(next);
            let x1 = floor(p0.x + u);
            if x1 < x0 {
                continue;
            }
            next = x1 + 1;
            if y < 0 || y >= h {
                clipped += (x1 - x0 + 1) as usize;
                continue;
            }
            let (xa, xb) = (x0.max(0), x1.min(w - 1));
            clipped += (x1 - x0 + 1 - (xb - xa + 1).max(0)) as usize;
            if xb < xa {
                continue;
            }
            inside += (xb - xa + 1) as usize;
            let row = (y * w) as usize;
            let Some(pixels) = raw.get(row + xa as usize..=row + xb as usize) else {
                continue;
            };
            if coarse {
                let skip = usize::from(xa % 2 == 1);
                let first = xa + skip as i64;
                let run = pixels.get(skip..).unwrap_or_default();
                win.push_run((first as f64 - p0.x) as f32, dy as f32, run, 2);
            } else {
                win.push_run((xa as f64 - p0.x) as f32, dy as f32, pixels, 1);
            }
        }
    }
    // The window must lie (almost) entirely inside the image: a clipped window is asymmetric.
    let min_pixels = if coarse { MIN_PIXELS / 4 } else { MIN_PIXELS };
    (win.n >= min_pixels && clipped as f64 <= 0.15 * (inside + clipped) as f64)
        .then(|| win.finish())
}

/// `tanh` to within 1e-4 (Lambert's continued fraction to the 7th order, held at its value at ±4.97,
/// 1 − 6·10⁻⁷, beyond): a fit evaluates it twice per pixel per iteration, and `f64::tanh` made it
/// 70 % of the fit's time. The profile's exact shape does not bias the corner (see the module doc).
#[inline(always)]
fn tanh(x: f32) -> f32 {
    // Clamped rather than branched: half the pixels of a window saturate, unpredictably.
    let x = x.clamp(-4.97, 4.97);
    let x2 = x * x;
    x * (135_135.0 + x2 * (17_325.0 + x2 * (378.0 + x2)))
        / (135_135.0 + x2 * (62_370.0 + x2 * (3_150.0 + 28.0 * x2)))
}

/// The model's parameters in the form the per-pixel loops use.
#[derive(Clone, Copy)]
struct Model {
    cx: f32,
    cy: f32,
    s1: f32,
    c1: f32,
    s2: f32,
    c2: f32,
    inv_s: f32,
    m: f32,
    h: f32,
}

impl Model {
    /// The signed distances `(d₁, d₂)` of the window point `(x, y)` from the two lines.
    #[inline(always)]
    fn distances(&self, x: f32, y: f32) -> (f32, f32) {
        let (dx, dy) = (x - self.cx, y - self.cy);
        (-self.s1 * dx + self.c1 * dy, -self.s2 * dx + self.c2 * dy)
    }

    fn new(p: &P) -> Model {
        let (s1, c1) = p[2].sin_cos();
        let (s2, c2) = p[3].sin_cos();
        Model {
            cx: p[0] as f32,
            cy: p[1] as f32,
            s1: s1 as f32,
            c1: c1 as f32,
            s2: s2 as f32,
            c2: c2 as f32,
            inv_s: (1.0 / p[4]) as f32,
            m: p[5] as f32,
            h: p[6] as f32,
        }
    }
}

/// The model at one group of pixels: residuals, Jacobian rows (both zero for padding) and the
/// quantities the curvature terms need.
struct Eval {
    /// ∂I/∂(cx, cy, φ₁, φ₂, s, m, h), one lane per pixel.
    j: [Lane; 7],
    /// Model minus image.
    r: Lane,
    /// Positions along the two lines.
    t1: Lane,
    t2: Lane,
    /// ∂I/∂dᵢ.
    dg1: Lane,
    dg2: Lane,
    /// Offsets from the corner, the model's value `m + h·G` and the junction's profile `G =
    /// tanh·tanh`, for the shading and response terms.
    dx: Lane,
    dy: Lane,
    model: Lane,
    g: Lane,
}

#[inline(always)]
fn eval(grp: &Group<'_>, md: &Model) -> Eval {
    let mut e = Eval {
        j: [[0.0; LANES]; 7],
        r: [0.0; LANES],
        t1: [0.0; LANES],
        t2: [0.0; LANES],
        dg1: [0.0; LANES],
        dg2: [0.0; LANES],
        dx: [0.0; LANES],
        dy: [0.0; LANES],
        model: [0.0; LANES],
        g: [0.0; LANES],
    };
    let (xs, ys, vs, ws) = (grp.x, grp.y, grp.v, grp.w);
    for i in 0..LANES {
        let (dx, dy) = (xs[i] - md.cx, ys[i] - md.cy);
        // Normals of the lines along (cos φ, sin φ): (−sin φ, cos φ).
        let d1 = -md.s1 * dx + md.c1 * dy;
        let d2 = -md.s2 * dx + md.c2 * dy;
        let t1 = md.c1 * dx + md.s1 * dy;
        let t2 = md.c2 * dx + md.s2 * dy;
        let g1 = tanh(d1 * md.inv_s);
        let g2 = tanh(d2 * md.inv_s);
        let w = ws[i];
        // ∂dᵢ/∂c = −nᵢ; ∂dᵢ/∂φᵢ = −tᵢ.
        let dg1 = w * md.h * g2 * (1.0 - g1 * g1) * md.inv_s;
        let dg2 = w * md.h * g1 * (1.0 - g2 * g2) * md.inv_s;
        e.j[0][i] = dg1 * md.s1 + dg2 * md.s2;
        e.j[1][i] = -dg1 * md.c1 - dg2 * md.c2;
        e.j[2][i] = -dg1 * t1;
        e.j[3][i] = -dg2 * t2;
        e.j[4][i] = -(dg1 * d1 + dg2 * d2) * md.inv_s;
        e.j[5][i] = w;
        e.j[6][i] = w * g1 * g2;
        let model = md.m + md.h * g1 * g2;
        e.r[i] = w * (model - vs[i]);
        e.t1[i] = t1;
        e.t2[i] = t2;
        e.dg1[i] = dg1;
        e.dg2[i] = dg2;
        e.dx[i] = dx;
        e.dy[i] = dy;
        e.model[i] = model;
        e.g[i] = w * g1 * g2;
    }
    e
}

/// Sum of the lanes of `acc`, in f64.
fn lane_sum(acc: &[f32]) -> f64 {
    acc.iter().map(|&v| f64::from(v)).sum()
}

/// The normal equations of the model at `p` (coordinates relative to `p0`): `JᵀJ`, `Jᵀr` and the sum
/// of squared residuals; with `CURVATURE`, also `Jᵀ J_κ`, the cross products with the residuals'
/// derivatives in the two lines' curvatures `κ` (`∂dᵢ/∂κᵢ = −tᵢ²/2`, see
/// [`Refined::curvature_shift`]), in the relative shading gradient (`(m + h·G)·(q − c)`, see
/// [`Refined::shading_shift`]) and in the response's curvature (`G²`, see [`response_shift`]) with
/// that column's own products, zero otherwise.
#[inline(never)]
fn accumulate<const CURVATURE: bool>(win: &Window, p: &P) -> Normal {
    const HALF: usize = LANES / 2;
    let md = Model::new(p);
    // Upper triangle of [J r]ᵀ[J r], row by row, one lane per pixel of a group.
    let mut acc = [[0.0_f32; HALF]; 36];
    let mut cross = [[[0.0_f32; HALF]; 7]; EXTRA];
    let (mut qq, mut qr) = ([0.0_f32; HALF], [0.0_f32; HALF]);
    for grp in win.groups() {
        let e = eval(&grp, &md);
        let rows = [e.j[0], e.j[1], e.j[2], e.j[3], e.j[4], e.j[5], e.j[6], e.r];
        // Written out (not two nested loops over a triangle, whose bounds the compiler does not
        // unroll): every product is then a pair of SIMD multiply-adds at fixed addresses. (Tried: a
        // second pass over stored rows in sweeps of eight sums, to keep the sums in registers; the
        // compiler shuffled lanes instead and it took 30 % more instructions.)
        macro_rules! products {
            ($($k:literal: $a:literal $b:literal),*) => {
                $(for i in 0..HALF {
                    acc[$k][i] += rows[$a][i] * rows[$b][i] + rows[$a][i + HALF] * rows[$b][i + HALF];
                })*
            };
        }
        products!(0: 0 0, 1: 0 1, 2: 0 2, 3: 0 3, 4: 0 4, 6: 0 6, 7: 0 7, 8: 1 1, 9: 1 2,
            10: 1 3, 11: 1 4, 13: 1 6, 14: 1 7, 15: 2 2, 16: 2 3, 17: 2 4, 19: 2 6,
            20: 2 7, 21: 3 3, 22: 3 4, 24: 3 6, 25: 3 7, 26: 4 4, 28: 4 6, 29: 4 7,
            33: 6 6, 34: 6 7, 35: 7 7);
        // Row 5 (∂/∂m) is the weight, 0 or 1, and every row carries it as a factor: its products
        // are plain sums of the other rows.
        macro_rules! sums {
            ($($k:literal: $a:literal),*) => {
                $(for i in 0..HALF {
                    acc[$k][i] += rows[$a][i] + rows[$a][i + HALF];
                })*
            };
        }
        sums!(5: 0, 12: 1, 18: 2, 23: 3, 27: 4, 30: 5, 31: 6, 32: 7);
        if CURVATURE {
            // (Padding pixels have Jacobian rows of 0, so their extra columns need no weight.)
            let jk = |i: usize| {
                [
                    -0.5 * e.dg1[i] * e.t1[i] * e.t1[i],
                    -0.5 * e.dg2[i] * e.t2[i] * e.t2[i],
                    e.model[i] * e.dx[i],
                    e.model[i] * e.dy[i],
                    e.g[i] * e.g[i],
                ]
            };
            for i in 0..HALF {
                let (lo, hi) = (jk(i), jk(i + HALF));
                for k in 0..EXTRA {
                    for a in 0..7 {
                        cross[k][a][i] += e.j[a][i] * lo[k] + e.j[a][i + HALF] * hi[k];
                    }
                }
                qq[i] += lo[4] * lo[4] + hi[4] * hi[4];
                qr[i] += lo[4] * e.r[i] + hi[4] * e.r[i + HALF];
            }
        }
    }
    let mut out = Normal {
        jtj: SMatrix::zeros(),
        jtr: P::zeros(),
        ssr: 0.0,
        cross: SMatrix::zeros(),
        qq: 0.0,
        qr: 0.0,
    };
    let mut k = 0;
    for a in 0..8 {
        for b in a..8 {
            let v = lane_sum(&acc[k]);
            match (a, b) {
                (7, 7) => out.ssr = v,
                (_, 7) => out.jtr[a] = v,
                _ => {
                    out.jtj[(a, b)] = v;
                    out.jtj[(b, a)] = v;
                }
            }
            k += 1;
        }
    }
    if CURVATURE {
        for k in 0..EXTRA {
            for a in 0..7 {
                out.cross[(a, k)] = lane_sum(&cross[k][a]);
            }
        }
        out.qq = lane_sum(&qq);
        out.qr = lane_sum(&qr);
    }
    out
}

/// Terms beside the model's seven parameters whose first-order effect on the corner a converged fit
/// reports: the two lines' curvatures, the two components of the relative shading gradient and the
/// response's curvature.
const EXTRA: usize = 5;

/// The normal equations at one point (see [`accumulate`]).
struct Normal {
    jtj: SMatrix<f64, 7, 7>,
    jtr: P,
    ssr: f64,
    cross: SMatrix<f64, 7, EXTRA>,
    /// `Σ (G²)²` and `Σ G²·r`: the response column's own products (see [`response_shift`]).
    qq: f64,
    qr: f64,
}

/// A fit's curvature shift, shading shift and response correction ([`extra_shifts`]).
type ExtraShifts = (Matrix2<f64>, Matrix2<f64>, Vector2<f64>);

/// The first-order shift of the corner per unit curvature of each line ([`Refined::curvature_shift`])
/// and per unit shading gradient ([`Refined::shading_shift`]) at a converged fit with normal
/// equations `n` (accumulated with the extra terms): with a term held at `κ` instead of 0, the
/// normal equations move the seven parameters by `−(JᵀJ)⁻¹·Jᵀ J_κ·κ`.
fn extra_shifts(n: &Normal) -> Option<ExtraShifts> {
    let chol = n.jtj.cholesky()?;
    let shift = -chol.solve(&n.cross);
    Some((
        shift.fixed_view::<2, 2>(0, 0).into_owned(),
        shift.fixed_view::<2, 2>(0, 2).into_owned(),
        response_shift(n, &chol.solve(&(-n.jtr)), &shift.column(4).into_owned()),
    ))
}

/// The corner's correction for the camera's response curve: the fitted model is linear in the
/// junction's profile `G`, a camera's response (gamma) is not, and to second order it adds `q·G²`
/// to the image. That term is even about the corner, so in a window symmetric about it it would not
/// move the fit; the windows are not quite symmetric (they are placed from the start position, and
/// bands and borders cut them), and it did: on noise-free renders of the realistic set (gamma 2.2)
/// the corners below 75° were 0.0037 px RMS from the truth, against 0.0025 px with gamma 1. Here `q`
/// is solved jointly with the seven parameters in one Gauss–Newton step from the point of the
/// normal equations `n` (the second stage's first point, see [`solve`]; Schur complement:
/// `q = −(Σ G²r + bᵀδ)/(Σ G⁴ − bᵀ(JᵀJ)⁻¹b)` with `b = Jᵀ G²` and `δ` the seven-parameter step),
/// and the corner moves by `−(JᵀJ)⁻¹b·q`. `delta` is that step, `sb` is `−(JᵀJ)⁻¹b`.
fn response_shift(n: &Normal, delta: &P, sb: &P) -> Vector2<f64> {
    let b = n.cross.column(4);
    let denom = n.qq + b.dot(sb);
    if !(denom > 1e-9 * n.qq.max(1e-300)) {
        return Vector2::zeros();
    }
    let q = -(n.qr + b.dot(delta)) / denom;
    let shift = Vector2::new(sb[0], sb[1]) * q;
    if shift.iter().all(|v| v.is_finite()) {
        shift
    } else {
        Vector2::zeros()
    }
}

/// Whether the junction `p`'s quadrants (pixels beyond one edge width `s` of both lines) alternate:
/// the darker of the two bright quadrants must exceed the brighter of the two dark ones by at least
/// `min_separation` × the contrast `2|h|`.
fn quadrants_alternate(win: &Window, p: &P, min_separation: f64) -> bool {
    let md = Model::new(p);
    let s = p[4] as f32;
    // Sum and count per quadrant, one lane per pixel of a group.
    let mut sum = [[0.0_f32; LANES]; 4];
    let mut n = [[0.0_f32; LANES]; 4];
    for grp in win.groups() {
        let (xs, ys, vs, ws) = (grp.x, grp.y, grp.v, grp.w);
        for i in 0..LANES {
            let (d1, d2) = md.distances(xs[i], ys[i]);
            let far1 = if d1.abs() < s { 0.0 } else { 1.0 };
            let far2 = if d2.abs() < s { 0.0 } else { 1.0 };
            let inside = ws[i] * far1 * far2;
            let p1 = if d1 > 0.0 { inside } else { 0.0 };
            let p2 = if d2 > 0.0 { 1.0 } else { 0.0 };
            let n1 = inside - p1;
            // Quadrant k = 2·[d₁ > 0] + [d₂ > 0].
            let q = [n1 * (1.0 - p2), n1 * p2, p1 * (1.0 - p2), p1 * p2];
            for k in 0..4 {
                sum[k][i] += q[k] * vs[i];
                n[k][i] += q[k];
            }
        }
    }
    let count: Vec<f64> = n.iter().map(|k| lane_sum(k)).collect();
    if count.iter().any(|&k| k < MIN_QUADRANT_PIXELS as f64) {
        return false;
    }
    let mean = |k: usize| lane_sum(&sum[k]) / count[k];
    // Quadrants 0 (−,−) and 3 (+,+) have d₁·d₂ > 0: bright when h > 0.
    let (pos, neg) = (mean(0).min(mean(3)), mean(1).max(mean(2)));
    let (pos_hi, neg_lo) = (mean(0).max(mean(3)), mean(1).min(mean(2)));
    let h = p[6];
    let separation = if h > 0.0 { pos - neg } else { neg_lo - pos_hi };
    separation >= min_separation * 2.0 * h.abs()
}

/// How far from both lines (in edge widths `s`) a pixel of a square counts for
/// [`Refined::squares`]: there the model's `tanh` is within 1.3 % of its plateau and a Gaussian
/// blur's edge (`s` ≈ 1.2 σ) within 0.3 %; what is left lowers the bright squares and raises the
/// dark ones alike, which their mean, the level, does not see.
pub const SQUARE_WIDTHS: f64 = 2.5;
/// Fewest pixels of each colour for [`Refined::squares`].
pub const MIN_SQUARE_PIXELS: f64 = 4.0;

/// The squares' mean level and half-contrast around the junction `p` ([`Refined::squares`]): from
/// the window's pixels farther than [`SQUARE_WIDTHS`] edge widths from both lines, the mean of the
/// bright squares' pixels and the mean of the dark squares' (`d₁·d₂` of either sign), the level
/// half their sum, the half-contrast half their difference (in absolute value). The window is
/// symmetric about the corner, so the two squares of a colour weigh alike and a brightness slope
/// across the window cancels in each mean. `None` when either colour has fewer than
/// [`MIN_SQUARE_PIXELS`] such pixels.
fn square_levels(win: &Window, p: &P) -> Option<[f64; 2]> {
    let md = Model::new(p);
    let flat = (SQUARE_WIDTHS * p[4].abs()) as f32;
    // Σ v, Σ 1, Σ ±v, Σ ±1 over the flat pixels (+ where d₁·d₂ > 0), one lane per pixel.
    let mut acc = [[0.0_f32; LANES]; 4];
    for grp in win.groups() {
        let (xs, ys, vs, ws) = (grp.x, grp.y, grp.v, grp.w);
        for i in 0..LANES {
            let (d1, d2) = md.distances(xs[i], ys[i]);
            // Selects, not branches: the loop stays vectorised.
            let far1 = if d1.abs() < flat { 0.0 } else { 1.0 };
            let far2 = if d2.abs() < flat { 0.0 } else { 1.0 };
            let sign = if d1 * d2 > 0.0 { 1.0 } else { -1.0 };
            let far = ws[i] * far1 * far2;
            let signed = far * sign;
            acc[0][i] += far * vs[i];
            acc[1][i] += far;
            acc[2][i] += signed * vs[i];
            acc[3][i] += signed;
        }
    }
    let [sum, n, signed_sum, signed_n] = acc.map(|a| lane_sum(&a));
    let (plus, minus) = ((n + signed_n) / 2.0, (n - signed_n) / 2.0);
    if plus.min(minus) < MIN_SQUARE_PIXELS {
        return None;
    }
    let (plus_mean, minus_mean) = (
        (sum + signed_sum) / (2.0 * plus),
        (sum - signed_sum) / (2.0 * minus),
    );
    Some([
        (plus_mean + minus_mean) / 2.0,
        ((plus_mean - minus_mean) / 2.0).abs(),
    ])
}

/// The least-squares half-contrast `h` of the model at `p` (with `p`'s level `m`), if defined.
fn initial_contrast(win: &Window, p: &P) -> Option<f64> {
    let md = Model::new(p);
    let mut num = [0.0_f32; LANES];
    let mut den = [0.0_f32; LANES];
    for grp in win.groups() {
        let (xs, ys, vs, ws) = (grp.x, grp.y, grp.v, grp.w);
        for i in 0..LANES {
            let (d1, d2) = md.distances(xs[i], ys[i]);
            let (g1, g2) = (tanh(d1 * md.inv_s), tanh(d2 * md.inv_s));
            let gg = ws[i] * g1 * g2;
            num[i] += gg * (vs[i] - md.m);
            den[i] += gg * gg;
        }
    }
    let den = lane_sum(&den);
    (den > 0.0).then(|| lane_sum(&num) / den)
}

/// Refine the corner near `p0` given the image steps `a` (to the next column) and `b` (to the next
/// row) of its grid.
pub fn refine(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Result<Refined, RefineFailure> {
    refine_reusing(img, p0, a, b, None, false, NO_BAND_CAP)
}

/// [`refine`], with the window shrunk about `p0` to fit inside the image where the image border
/// would clip it (down to half-extents of [`MIN_BORDER_HALF_PX`]) instead of failing with
/// [`RefineFailure::Window`]. For fitting corners known to belong to a grid; a test for the absence
/// of a corner (as `label`'s extent check) wants [`refine`]'s full window or nothing.
pub fn refine_near_border(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Result<Refined, RefineFailure> {
    refine_reusing(img, p0, a, b, None, true, NO_BAND_CAP)
}

/// No cap on the bands' half-widths beyond [`BAND_PX`].
const NO_BAND_CAP: [f64; 2] = [f64::INFINITY; 2];

/// [`refine_near_border`] for a junction that is an X only close to its two lines: the bands around
/// the line along `a` and the one along `b` are at most `band_px[0]` and `band_px[1]` px wide on each
/// side, in both stages. A ChArUco corner is one: its light squares hold markers, so the four squares'
/// X-junction holds along the whole of its edges but only within the white gap between a marker and
/// the lines. Bands that stay in that gap let the window reach along the edges as far as a
/// checkerboard corner's (`a`, `b` the steps of a whole square) instead of shrinking the whole window
/// into the gap, which at grazing angles leaves fewer pixels than the blur's width.
pub fn refine_near_border_in_bands(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    band_px: [f64; 2],
) -> Result<Refined, RefineFailure> {
    refine_reusing(img, p0, a, b, None, true, band_px)
}

/// [`refine_near_border`] (the fit grid corners get), also returning the pixels its final stage
/// fitted, `[column, row]`: the window a bound on the corner's precision must be computed over (see
/// [`super::crlb`]).
pub fn refine_near_border_with_window(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Result<(Refined, Vec<[u32; 2]>), RefineFailure> {
    thread_local! {
        static WINDOWS: Cell<[Window; 2]> = Cell::default();
    }
    WINDOWS.with(|cell| {
        let mut windows = cell.take();
        let result = refine_in(&mut windows, img, p0, a, b, None, true, NO_BAND_CAP).map(|fit| {
            let fine = &windows[1];
            // The window keeps offsets from `p0` (whole pixels minus `p0`, in f32): round back.
            let pixels = fine.x[..fine.n]
                .iter()
                .zip(&fine.y[..fine.n])
                .map(|(&x, &y)| {
                    let q = p0 + Vector2::new(f64::from(x), f64::from(y));
                    [q.x.round() as u32, q.y.round() as u32]
                })
                .collect();
            (fit, pixels)
        });
        cell.set(windows);
        result
    })
}

/// A smooth, locally invertible map from image pixels to a plane where the board's edges are
/// straight lines (for a calibrated lens: the undistorted pinhole image, see
/// [`super::undistorted`]).
pub trait PlaneMap {
    /// The plane point of image point `uv`, `None` where the map is not defined.
    fn to_plane(&self, uv: Vector2<f64>) -> Option<Vector2<f64>>;
    /// The image point of plane point `q` and the Jacobian `∂uv/∂q` there.
    fn to_image(&self, q: Vector2<f64>) -> Option<(Vector2<f64>, Matrix2<f64>)>;
}

/// [`refine`] with the X-junction model fitted in the plane of `map` instead of the image: each
/// pixel of the window (chosen in the image as by [`refine`]) takes part at its mapped position, the
/// fitted corner is mapped back and its covariance carried through the map's Jacobian. Where the
/// map straightens the edges that lens distortion bends, the fit has no curvature bias to correct
/// ([`Refined::curvature_shift`] is then in the plane's units and not meant to be applied). Near the
/// image border the window shrinks as in [`refine_near_border`].
pub fn refine_mapped(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    map: &dyn PlaneMap,
) -> Result<Refined, RefineFailure> {
    refine_reusing(img, p0, a, b, Some(map), true, NO_BAND_CAP)
}

/// [`refine_in`] with this thread's two stage windows, kept from one fit to the next (see [`Window`]),
/// shared by every public entry point.
fn refine_reusing(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    map: Option<&dyn PlaneMap>,
    shrink_at_border: bool,
    band_cap: [f64; 2],
) -> Result<Refined, RefineFailure> {
    thread_local! {
        static WINDOWS: Cell<[Window; 2]> = Cell::default();
    }
    WINDOWS.with(|cell| {
        let mut windows = cell.take();
        let result = refine_in(&mut windows, img, p0, a, b, map, shrink_at_border, band_cap);
        cell.set(windows);
        result
    })
}

/// Moves the window's pixels to `map`'s plane, relative to `q0` (the image of `p0`); with `keep`,
/// keeps only the pixels within its half-width of either of its lines there. `None` if a pixel
/// cannot be mapped or too few remain.
fn map_window(
    win: &mut Window,
    p0: Vector2<f64>,
    q0: Vector2<f64>,
    map: &dyn PlaneMap,
    keep: Option<Bands>,
) -> Option<()> {
    let mut k = 0;
    for i in 0..win.n {
        let uv = p0 + Vector2::new(f64::from(win.x[i]), f64::from(win.y[i]));
        let q = map.to_plane(uv)? - q0;
        if let Some(bands) = keep {
            let d = q - bands.centre;
            if bands
                .normals
                .iter()
                .zip(bands.half_width)
                .all(|(n, hw)| n.dot(&d).abs() > hw)
            {
                continue;
            }
        }
        win.x[k] = q.x as f32;
        win.y[k] = q.y as f32;
        win.v[k] = win.v[i];
        k += 1;
    }
    win.n = k;
    (k >= MIN_PIXELS).then(|| win.finish())
}

/// [`refine`] with the windows of the first stage (`coarse_win`) and the second (`fine_win`) to fill.
fn refine_in(
    [coarse_win, fine_win]: &mut [Window; 2],
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    map: Option<&dyn PlaneMap>,
    shrink: bool,
    band_cap: [f64; 2],
) -> Result<Refined, RefineFailure> {
    let (image_a, image_b) = (a, b);
    let la = a.norm();
    let lb = b.norm();
    // Stage 1 on a quarter of the pixels of large windows: it converges from the start as well as
    // the full window does, at a quarter of the cost.
    let area = 4.0
        * (WINDOW * la).clamp(MIN_HALF_PX, MAX_HALF_PX)
        * (WINDOW * lb).clamp(MIN_HALF_PX, MAX_HALF_PX);
    let coarse = area >= COARSE_MIN_AREA_PX;
    let first_bands = Bands {
        centre: Vector2::zeros(),
        normals: [Vector2::new(-a.y, a.x) / la, Vector2::new(-b.y, b.x) / lb],
        half_width: band_cap.map(|cap| cap.min(BAND_PX)),
    };
    window(coarse_win, img, p0, a, b, Some(first_bands), coarse, shrink)
        .ok_or(RefineFailure::Window)?;
    // In a mapped fit, the plane position of p0 and the steps there (to first order).
    let (q0, a, b) = match map {
        None => (p0, a, b),
        Some(m) => {
            let q0 = m.to_plane(p0).ok_or(RefineFailure::Window)?;
            let (_, jac) = m.to_image(q0).ok_or(RefineFailure::Window)?;
            let inv = jac.try_inverse().ok_or(RefineFailure::Degenerate)?;
            map_window(coarse_win, p0, q0, m, None).ok_or(RefineFailure::Window)?;
            (q0, inv * a, inv * b)
        }
    };
    let win = &*coarse_win;
    let f1 = a.y.atan2(a.x);
    let f2 = b.y.atan2(b.x);
    // Starting edge width: a sharp lens's (s ≈ 1.2 × the blur σ). Capped at 3 px it took 16 % more
    // instructions on the bench frame (large squares), at 1 px 8 % more; same corners either way.
    let s0 = (0.15 * la.min(lb)).clamp(0.7, 1.5);
    // Initial level and half-contrast: least squares for the initial geometry.
    let mut p = P::from([0.0, 0.0, f1, f2, s0, 0.0, 1.0]);
    p[5] = win.v[..win.n].iter().map(|&v| f64::from(v)).sum::<f64>() / win.n as f64;
    p[6] = initial_contrast(win, &p).ok_or(RefineFailure::Degenerate)?;
    // A window whose quadrants do not alternate even roughly (the extrapolated positions around a
    // grid fall on its margin: L- and T-junctions) is not worth the fit.
    if !quadrants_alternate(win, &p, MIN_START_SEPARATION) {
        return Err(RefineFailure::NotX);
    }
    let to_board = Matrix2::from_columns(&[a, b])
        .try_inverse()
        .ok_or(RefineFailure::Degenerate)?;
    let mut lambda = 1e-3;
    let start = solve::<false>(win, p, &mut lambda, &COARSE, &to_board)?;
    // The pixel noise, as the first stage's residuals show it: its wide bands are mostly the squares'
    // flat insides, where the residual is the noise; the second stage's narrow bands are mostly the
    // edges, where the model's mismatch with the real blurred edge (which does not move the corner:
    // both are point-symmetric) adds to it.
    let noise_var = start.normal.ssr / (win.n as f64 - 7.0).max(1.0);
    // Stage 2 on every pixel within a few edge widths of the lines found.
    let bands = Bands {
        centre: Vector2::new(start.p[0], start.p[1]),
        normals: [2, 3].map(|i| Vector2::new(-start.p[i].sin(), start.p[i].cos())),
        half_width: band_cap.map(|cap| {
            (FINE_BAND_WIDTHS * start.p[4].abs() + FINE_BAND_MARGIN_PX)
                .clamp(MIN_FINE_BAND_PX, BAND_PX)
                .min(cap)
        }),
    };
    match map {
        None => window(fine_win, img, p0, a, b, Some(bands), false, shrink),
        // The bands are straight in the plane, not in the image: the image window is the first
        // stage's at full resolution, narrowed to the bands once mapped.
        Some(m) => window(fine_win, img, p0, image_a, image_b, None, false, shrink)
            .and_then(|()| map_window(fine_win, p0, q0, m, Some(bands))),
    }
    .ok_or(RefineFailure::Window)?;
    let win = &*fine_win;
    let Fit { p, normal, extras } = solve::<true>(win, start.p, &mut lambda, &FINE, &to_board)?;
    let (jtj, ssr) = (normal.jtj, normal.ssr);
    let (curvature_shift, mut shading_shift, response) = extras.ok_or(RefineFailure::Degenerate)?;
    let c = Vector2::new(p[0], p[1]) + response;
    if !c.iter().all(|v| v.is_finite()) {
        return Err(RefineFailure::Degenerate);
    }
    // Shift in board units.
    let st = to_board * c;
    if st.x.abs() > MAX_SHIFT || st.y.abs() > MAX_SHIFT {
        return Err(RefineFailure::Moved);
    }
    let dof = (win.n as f64 - 7.0).max(1.0);
    let var = ssr / dof;
    let residual = var.sqrt();
    let contrast = p[6].abs();
    let unit_cov = jtj.try_inverse().ok_or(RefineFailure::Degenerate)?;
    let cov = unit_cov * var;
    if contrast < MIN_SNR * cov[(6, 6)].max(0.0).sqrt() {
        return Err(RefineFailure::Weak);
    }
    let dphi = (p[2] - p[3]).rem_euclid(std::f64::consts::PI);
    if dphi.min(std::f64::consts::PI - dphi) < MIN_LINE_ANGLE {
        return Err(RefineFailure::Parallel);
    }
    // On the first stage's window: its wide bands reach into the squares, where the quadrants are
    // told apart, and it has half the pixels of the second's (on the synthetic sets one more face
    // beyond 75° found, nothing else changed).
    if !quadrants_alternate(coarse_win, &p, MIN_QUADRANT_SEPARATION) {
        return Err(RefineFailure::NotX);
    }
    // The corner's σ from the second stage's normal equations and the first stage's noise level: on
    // the realistic synthetic set RMS / (√2 σ) went from 0.55 to 0.66 (σ still on the safe side),
    // on the hard set (noise-dominated) 0.93 to 0.94.
    let mut cov_c = unit_cov.fixed_view::<2, 2>(0, 0).into_owned() * noise_var;
    let uv = match map {
        None => p0 + c,
        Some(m) => {
            let (uv, jac) = m.to_image(q0 + c).ok_or(RefineFailure::Degenerate)?;
            cov_c = jac * cov_c * jac.transpose();
            // The shift in the plane to the image (`jac`), and image gradients to the plane's
            // (`∇_q = jacᵀ ∇_uv`).
            shading_shift = jac * shading_shift * jac.transpose();
            uv
        }
    };
    let sigma_px = (cov_c.trace() / 2.0).max(0.0).sqrt();
    Ok(Refined {
        uv,
        sigma_px,
        cov: cov_c,
        contrast,
        residual,
        edge_width: p[4],
        curvature_shift,
        squares: square_levels(coarse_win, &p),
        shading_shift,
    })
}

/// When a step is the last one, taken without evaluating the model again (see [`solve`]).
struct Tolerance {
    /// Largest corner move, px.
    position_px: f64,
    /// Largest turn of either line, radians.
    angle: f64,
    /// Largest change of the edge width, as a fraction of it.
    width: f64,
    /// Largest predicted decrease of the sum of squares, as a fraction of it.
    decrease: f64,
}

/// A converged fit: parameters, and the normal equations at `p` or at a point within the last,
/// negligible, step of it (the sum of squares then as predicted for `p`).
struct Fit {
    p: P,
    normal: Normal,
    /// With `CURVATURE`: [`extra_shifts`] at the first point evaluated (see [`solve`]).
    extras: Option<ExtraShifts>,
}

/// Levenberg–Marquardt from `p` on `win` until a step is within `tol`. That last step is taken
/// without evaluating the model again: from that close, one Gauss–Newton step lands within about
/// its square of the optimum, and the normal matrix there is the same to that order. `to_board` maps
/// image offsets to board units (to stop fits that run away). With `CURVATURE`, the normal equations
/// carry the curvature terms.
fn solve<const CURVATURE: bool>(
    win: &Window,
    mut p: P,
    lambda: &mut f64,
    tol: &Tolerance,
    to_board: &Matrix2<f64>,
) -> Result<Fit, RefineFailure> {
    let mut normal = accumulate::<CURVATURE>(win, &p);
    // The extra terms' shifts are taken at the first point only: the second stage starts within
    // about 0.1 px of the optimum, where they are the same to first order (they are themselves
    // corrections of a few thousandths of a pixel), and its further evaluations (0.3 a corner)
    // skip their five columns. On the callgrind frames (four `cubecal render --poses turntable:4`
    // frames of the cube, realistic look) `detect` 200.9 → 195.5 M instructions, same corners to
    // the printed digit; noise-free realistic SS=16 RMS below 75° 0.0029 px either way, 75–80°
    // 0.0083 → 0.0085 px. (`accumulate` is kept out of line: inlined into `solve` beside its other
    // instance, it lost its vectorisation, +25 M.)
    let extras = if CURVATURE {
        extra_shifts(&normal)
    } else {
        None
    };
    for _ in 0..MAX_ITERATIONS {
        let (jtj, jtr, ssr) = (&normal.jtj, &normal.jtr, normal.ssr);
        let mut a_mat = *jtj;
        for i in 0..7 {
            a_mat[(i, i)] += *lambda * jtj[(i, i)].max(1e-12);
        }
        let Some(chol) = a_mat.cholesky() else {
            *lambda *= 10.0;
            if *lambda > 1e8 {
                return Err(RefineFailure::Degenerate);
            }
            continue;
        };
        let step = chol.solve(&(-jtr));
        let mut cand = p + step;
        cand[4] = cand[4].abs().max(0.2);
        // The sum of squares after the step, as the linearised model predicts it (exact in the
        // linear parameters m and h, second-order in the others).
        let predicted = ssr + 2.0 * step.dot(jtr) + step.dot(&(jtj * step));
        if step[0].hypot(step[1]) < tol.position_px
            && step[2].abs().max(step[3].abs()) < tol.angle
            && step[4].abs() < tol.width * p[4]
            && ssr - predicted < tol.decrease * ssr
        {
            normal.ssr = predicted.clamp(0.0, ssr);
            return Ok(Fit {
                p: cand,
                normal,
                extras,
            });
        }
        let next = accumulate::<false>(win, &cand);
        if next.ssr.is_finite() && next.ssr < ssr {
            p = cand;
            // A fit running away from its start will be rejected: stop paying for it.
            let st = to_board * Vector2::new(p[0], p[1]);
            if st.x.abs() > 2.0 * MAX_SHIFT || st.y.abs() > 2.0 * MAX_SHIFT {
                return Err(RefineFailure::Moved);
            }
            normal = next;
            *lambda = (*lambda * 0.3).max(1e-9);
        } else {
            *lambda *= 10.0;
            if *lambda > 1e8 {
                break;
            }
        }
    }
    Ok(Fit { p, normal, extras })
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

    /// [`xjunction`] blurred as a lens does: before the pixels integrate the scene (the scene at 8×
    /// resolution blurred by `sigma` output pixels, then averaged over each pixel's 8×8 block).
    fn lens_xjunction(size: u32, c: Vector2<f64>, u: f64, v: f64, sigma: f32) -> GrayImage {
        let fine = xjunction(size * 8, c * 8.0 + Vector2::new(3.5, 3.5), u, v);
        let fine = image::imageops::blur(&fine, 8.0 * sigma);
        GrayImage::from_fn(size, size, |x, y| {
            let mut acc = 0u32;
            for i in 0..8 {
                for j in 0..8 {
                    acc += u32::from(fine.get_pixel(8 * x + i, 8 * y + j).0[0]);
                }
            }
            image::Luma([((f64::from(acc) / 64.0).round()) as u8])
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
        let blurred = lens_xjunction(41, c, u, v, 1.0);
        let r = refine(&blurred, Vector2::new(20.0, 20.0), a, b).unwrap();
        assert!((r.uv - c).norm() < 0.01, "{:?} vs {c:?}", r.uv);
    }

    /// The squares' levels are read where the blurred edges are flat: the true levels (220 and 30:
    /// mean 125, half-contrast 95) to a quarter of a grey level, on an oblique junction and on a
    /// narrow one (31°), blurred as a lens does (σ 1.5 px), where the fitted model's level and
    /// contrast take up its mismatch with the blurred junction by 1–4 grey levels, differently at
    /// each angle.
    #[test]
    fn squares_read_the_true_levels() {
        let c = Vector2::new(40.37, 39.81);
        for (u, v) in [(0.3_f64, 1.3_f64), (0.2, 0.75)] {
            let img = lens_xjunction(81, c, u, v, 1.5);
            let a = Vector2::new(u.cos(), u.sin()) * 30.0;
            let b = Vector2::new(v.cos(), v.sin()) * 30.0;
            let r = refine(&img, Vector2::new(40.0, 40.0), a, b).unwrap();
            let [level, contrast] = r.squares.unwrap();
            // (The model's own: level 126.4 and 128.9, half-contrast 97.1 and 96.5.)
            assert!((level - 125.0).abs() < 0.25, "{level}");
            assert!((contrast - 95.0).abs() < 0.25, "{contrast}");
        }
    }

    #[test]
    fn sigma_matches_the_scatter_under_pixel_noise() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        // A blurred oblique junction with 40 grey levels of half-contrast and noise σ 5: the spread
        // of the fitted corner over noise draws must match the σ the fit reports.
        let c = Vector2::new(30.3, 29.8);
        let (u, v) = (0.2_f64, 1.4_f64);
        let clean = image::imageops::blur(&xjunction(61, c, u, v), 1.5);
        let a = Vector2::new(u.cos(), u.sin()) * 30.0;
        let b = Vector2::new(v.cos(), v.sin()) * 24.0;
        let noise = Normal::new(0.0, 5.0).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (mut sq, mut sigma, mut n) = (0.0, 0.0, 0.0);
        // And the 2×2 covariance, not only its trace: eᵀ Σ⁻¹ e averages 2 when Σ is the scatter's.
        let mut mahalanobis = 0.0;
        for _ in 0..60 {
            let img = GrayImage::from_fn(61, 61, |x, y| {
                let v = f64::from(clean.get_pixel(x, y).0[0]) * 0.27 + 90.0;
                image::Luma([(v + noise.sample(&mut rng)).round().clamp(0.0, 255.0) as u8])
            });
            let r = refine(&img, Vector2::new(30.0, 30.0), a, b).unwrap();
            sq += (r.uv - c).norm_squared();
            sigma += r.sigma_px;
            assert!((r.cov.trace() / 2.0).sqrt() - r.sigma_px < 1e-12);
            let e = r.uv - c;
            mahalanobis += e.dot(&(r.cov.try_inverse().unwrap() * e));
            n += 1.0;
        }
        // RMS of the 2-D error against √2 × the mean per-coordinate σ.
        let ratio = (sq / n).sqrt() / (std::f64::consts::SQRT_2 * sigma / n);
        assert!((0.75..1.3).contains(&ratio), "RMS / (√2 σ) = {ratio}");
        // The mean of 60 χ²₂ draws has a standard deviation of 0.26; σ itself is ~10 % loose.
        let m = mahalanobis / n;
        assert!((1.2..3.0).contains(&m), "mean eᵀΣ⁻¹e = {m}");
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
