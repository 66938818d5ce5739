//! Levenberg–Marquardt refinement of shared intrinsics + distortion and per-view extrinsics, with the
//! marginal covariance of the result.
//!
//! ## Problem
//! Minimise `Σ_views Σ_points ρ(‖π(θ, cam_from_rig_i · X_ij) − u_ij‖)` over the free intrinsic
//! parameters `θ` (a linear image of the 13-vector of [`crate::camera::PARAM_NAMES`]: fixed entries
//! drop out, a fixed aspect ratio ties `fx = a·fy`) and six pose parameters per view. Rotations are
//! updated on the left, `R ← exp([δ]ₓ) R`, so that `∂X_c/∂δ = −[R X]ₓ` exactly at the linearisation
//! point; translations additively.
//!
//! ## Normal equations and the Schur complement
//! The free intrinsics (p ≤ 13) are the shared block of the Levenberg–Marquardt machinery in
//! `lm_core.rs`, the view poses its per-view blocks: each step is a p×p dense solve plus 6×6 blocks per
//! view, with Marquardt's damping updated by Nielsen's rule. The intrinsic blocks are accumulated over
//! the full 13-vector in fixed-size matrices and mapped to the free parameters once per linearisation.
//!
//! ## Each corner's own covariance (generalised least squares)
//! When every point carries a covariance `Σ_ij` ([`super::Correspondence::cov`], the detector's fit
//! gives one per corner) and [`SolveOptions::weighting`] is [`Weighting::Covariance`] (the default),
//! residuals and Jacobians are whitened: with the Cholesky factor `Σ = L Lᵀ`, the solve sees
//! `r̃ = L⁻¹ r` and `J̃ = L⁻¹ J`, so it minimises `Σ ρ(‖r̃‖)` = `Σ ρ(√(rᵀ Σ⁻¹ r))`. A corner of a
//! foreshortened face (long, thin fit window, large σ across its short axis) then counts for what its
//! fit is worth. Everything below (robust loss, outlier rejection, σ̂) works on the whitened
//! residuals; the robust loss's scale, given in pixels, is divided by the median corner σ
//! (`√(trace Σ / 2)`), so that it means the same for a typical corner as in the unweighted solve.
//! A set where only some points carry a covariance is solved unweighted: the two kinds of point
//! have no common unit.
//!
//! ## Uncertainty
//! At the optimum `σ̂² = Σ r̃² / (2n − p_total)` and the covariance of the intrinsics is the
//! corresponding block of `σ̂² (J̃ᵀJ̃)⁻¹`, which is exactly `σ̂² S⁻¹` with `S` the undamped Schur
//! complement (`lm_core.rs`). Unweighted (`r̃ = r`), these assume independent, equal-variance corner
//! noise; weighted, `σ̂` is the ratio of the corners' actual scatter to the scatter the detector
//! claims ([`Calibration::noise_scale`], 1 when the detector's covariances are right), and scaling by
//! it keeps the σ honest when they are right only up to a common factor. `tests/calibration.rs`
//! checks the claimed ±2σ coverage over seeded trials.
//!
//! Equal weights ([`Weighting::Equal`]) with every point's covariance known: `σ̂² S⁻¹` is the
//! estimator's covariance only when every corner's noise is the same, and a station's corners are
//! not (grazing, blurred and far faces are noisier, and equal weights give them the same say). The
//! covariance is then the sandwich `S⁻¹ (Σᵢ J̃ᵢᵀ Σᵢ J̃ᵢ) S⁻¹` marginalised over the poses
//! (`sandwich_covariance`), scaled by the residuals' `χ²/dof` against the `Σᵢ` (as the weighted
//! solve scales by `σ̂²`: the detector's covariances are taken as right in their proportions only).
//! Measured on 20 seeds of the synthetic station (`cargo run --release --example station_chi2 --
//! 20`): χ² of (fx, fy, cx, cy) against the truth averages 5.00 with it (1 run of 20 above the 95th
//! percentile), 6.35 with the scatter's σ alone (3 runs); 4 ± 1.26 expected.
//!
//! Neighbouring corners are not independent either: their fit windows overlap and they share their
//! face's model error. Both weightings add the grid neighbours' residual cross-products to the
//! sandwich where they are significant (`neighbours_part`; neighbours found from the rig
//! coordinates, [`super::neighbours`]): the station's mean χ² 5.00 → 4.24, and on the pycalib photo
//! set, disjoint quarters disagree by 1.3σ RMS instead of 2.1σ (issue 29).
//!
//! ## Robustness and outliers
//! An optional robust loss (Huber, Cauchy) is applied by iteratively reweighted least squares.
//!
//! Optional outlier rejection (`outlier_sigma = k`) works one point per view at a time: after each
//! solve, `σ̂ = 1.4826 · median |r_c|` over the residual components of *all* points (rejected ones
//! included, so that the estimate does not shrink as the tails are cut), and in every view the single
//! point with the largest residual norm is dropped if that norm exceeds `k·σ̂`; then the problem is
//! re-solved from the current state, until no view has such a point. A dropped point whose residual is
//! back within `k·σ̂` in a later fit (it was dropped while another outlier still distorted the fit) is
//! re-admitted, once. So at the end every used point is within `k·σ̂` of the final fit and (but for
//! the rare point re-admitted and dropped again) every dropped one beyond it. Dropping only the worst point is
//! what keeps inliers: a gross outlier pulls its view's pose, so that *every* point of the view looks
//! bad until the outlier is gone and the pose re-solved (dropping all of them at once threw away most of
//! the view). Views are independent enough (they share only the intrinsics) to be cleaned in parallel.
//!
//! False rejections: for isotropic Gaussian corner noise the residual norm satisfies
//! `‖r‖²/σ² ~ χ²₂`, so a clean point is dropped with probability `P(‖r‖ > kσ) = exp(−k²/2)`: 1.11 % at
//! `k = 3` (0.6 of a 54-point view), 0.034 % at `k = 4`. The residuals' own spread is
//! `σ√(1 − p/2n)`, and σ̂ estimates exactly that spread, so the rate holds for the residuals tested
//! (`tests/defects.rs` checks it on seeded synthetic data).

use nalgebra::{DMatrix, DVector, Matrix2, SMatrix, SVector, Vector2};
use serde::{Deserialize, Serialize};
use tracing::{debug, info};

use super::init::{InitMethod, Initial, image_centre, initialise};
use super::lm_core::{
    BlockProblem, Loss, Normal, Step, Termination, levenberg_marquardt, rigid_jacobian,
    update_poses,
};
use super::neighbours::grid_neighbours;
use super::{CalibError, View, validate_image_points, validate_views};
use crate::camera::{Camera, DistortionModel, N_INTRINSIC, PARAM_NAMES, Pose, idx};

type Mat13 = SMatrix<f64, N_INTRINSIC, N_INTRINSIC>;
type Mat13x6 = SMatrix<f64, N_INTRINSIC, 6>;
type Vec13 = SVector<f64, N_INTRINSIC>;
#[cfg(test)]
use {super::lm_core::Vec6, nalgebra::Vector3};

/// Parameters held fixed during refinement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Fix {
    /// Hold `fx / fy` at this value (1.0 for square pixels).
    pub aspect_ratio: Option<f64>,
    /// Hold the principal point at the image centre `((w − 1)/2, (h − 1)/2)`.
    pub principal_point: bool,
    /// Hold `p1 = p2 = 0`.
    pub tangential: bool,
    /// Hold `k3 = 0`.
    pub k3: bool,
    /// Hold `k4 = 0`, `k5 = 0`, `k6 = 0` (rational model; `k4` also the fisheye's), each on its own.
    pub k4: bool,
    pub k5: bool,
    pub k6: bool,
    /// Hold `skew = 0` (the default: modern sensors have none).
    pub skew: bool,
}

impl Default for Fix {
    fn default() -> Self {
        Fix {
            aspect_ratio: None,
            principal_point: false,
            tangential: false,
            k3: false,
            k4: false,
            k5: false,
            k6: false,
            skew: true,
        }
    }
}

/// Options for [`solve`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SolveOptions {
    pub model: DistortionModel,
    pub fix: Fix,
    pub loss: Loss,
    /// Reject points whose residual norm exceeds this many robust (MAD) standard deviations.
    pub outlier_sigma: Option<f64>,
    /// Limit on LM iterations (accepted plus rejected steps) per solve.
    pub max_iterations: usize,
    /// How the points are weighted (see the module docs).
    #[serde(default)]
    pub weighting: Weighting,
}

/// How [`solve`] weights the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Weighting {
    /// By the inverse of each point's own covariance when every point has one (generalised least
    /// squares); equally otherwise.
    #[default]
    Covariance,
    /// Equally (ordinary least squares), except that a corner whose own σ exceeds
    /// [`EQUAL_WEIGHT_CEILING`] × the median corner's counts by that σ (a grazing face's corners,
    /// whose covariance holds the face's bias: [`crate::detect::face::add_grazing_bias`]). Without
    /// covariances, or with none that large, plain equal weights.
    Equal,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            model: DistortionModel::Brown5,
            fix: Fix::default(),
            loss: Loss::Squared,
            outlier_sigma: None,
            max_iterations: 200,
            weighting: Weighting::default(),
        }
    }
}

/// The refined result for one view.
#[derive(Debug, Clone)]
pub struct ViewResult {
    pub name: String,
    pub cam_from_rig: Pose,
    /// RMS of the residual components (px) over this view's inliers.
    pub rms_px: f64,
    /// Number of points used.
    pub n_points: usize,
    /// Indices (into the view's points) rejected as outliers.
    pub outliers: Vec<usize>,
    /// Standard deviation of the rotation (radians, about the camera axes).
    pub rotation_std_rad: [f64; 3],
    /// Standard deviation of the translation (mm).
    pub translation_std: [f64; 3],
}

/// A refined calibration with its uncertainty.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub camera: Camera,
    pub views: Vec<ViewResult>,
    /// RMS of the residual components, `√(Σ r² / 2n)` px. (OpenCV reports `√(Σ‖r‖² / n)`, which is
    /// √2 times this: see `rms_reprojection_px`.)
    pub rms_px: f64,
    /// OpenCV's figure: RMS of the per-point residual norms, `√(Σ‖r‖² / n)` px.
    pub rms_reprojection_px: f64,
    /// Estimated corner noise per coordinate, `√(Σ r² / (2n − p))` px.
    pub sigma_px: f64,
    /// With the corners weighted by their own covariances: `σ̂` of the whitened residuals,
    /// `√(Σ rᵀΣ⁻¹r / (2n − p))`, the corners' actual scatter over the scatter their covariances
    /// claim (≈ 1 when the detector is honest). The reported σ are scaled by it. `None` unweighted.
    pub noise_scale: Option<f64>,
    /// Names of the free intrinsic parameters, in the order of `covariance`.
    pub free_params: Vec<&'static str>,
    /// Covariance of the free intrinsic parameters.
    pub covariance: DMatrix<f64>,
    /// Standard deviation of each of the 13 intrinsic parameters (0 for fixed ones).
    pub std_dev: [f64; N_INTRINSIC],
    /// Whether each of the 13 intrinsic parameters was estimated (not held fixed).
    pub estimated: [bool; N_INTRINSIC],
    pub n_points: usize,
    /// Total number of estimated parameters (intrinsics + 6 per view).
    pub n_params: usize,
    pub iterations: usize,
    pub termination: Termination,
    pub init_method: InitMethod,
}

impl Calibration {
    /// `χ² = eᵀ C⁻¹ e` of the named free parameters' errors `e` = estimate − `truth` (the 13-vector),
    /// with `C` their reported covariance: χ²-distributed with as many degrees of freedom as names
    /// when the reported covariance is honest. `None` if a name is not free or `C` is singular.
    pub fn chi2_against(&self, truth: &[f64; N_INTRINSIC], names: &[&str]) -> Option<f64> {
        let pos: Vec<usize> = names
            .iter()
            .map(|n| self.free_params.iter().position(|f| f == n))
            .collect::<Option<_>>()?;
        let full: Vec<usize> = names
            .iter()
            .map(|n| PARAM_NAMES.iter().position(|f| f == n))
            .collect::<Option<_>>()?;
        let c = DMatrix::from_fn(pos.len(), pos.len(), |r, k| {
            self.covariance[(pos[r], pos[k])]
        });
        let e = DVector::from_iterator(
            full.len(),
            full.iter().map(|&k| self.camera.params[k] - truth[k]),
        );
        let x = c.cholesky()?.solve(&e);
        Some(e.dot(&x))
    }

    /// Standard deviations of the estimated intrinsic parameters, by name.
    pub fn std_dev_by_name(&self) -> Vec<(&'static str, f64)> {
        (0..N_INTRINSIC)
            .filter(|&k| self.estimated[k])
            .map(|k| (PARAM_NAMES[k], self.std_dev[k]))
            .collect()
    }
}

/// The linear map from free parameters to the full 13-vector: `δx = M δθ`.
pub(super) struct ParamMap {
    pub(super) m: DMatrix<f64>,
    pub(super) names: Vec<&'static str>,
}

impl ParamMap {
    pub(super) fn new(model: DistortionModel, fix: &Fix) -> ParamMap {
        let mut cols: Vec<(Vec<(usize, f64)>, &'static str)> = Vec::new();
        match fix.aspect_ratio {
            Some(a) => cols.push((vec![(idx::FX, a), (idx::FY, 1.0)], "f")),
            None => {
                cols.push((vec![(idx::FX, 1.0)], "fx"));
                cols.push((vec![(idx::FY, 1.0)], "fy"));
            }
        }
        if !fix.principal_point {
            cols.push((vec![(idx::CX, 1.0)], "cx"));
            cols.push((vec![(idx::CY, 1.0)], "cy"));
        }
        if !fix.skew {
            cols.push((vec![(idx::SKEW, 1.0)], "skew"));
        }
        if model == DistortionModel::Kb4 {
            cols.push((vec![(idx::K1, 1.0)], "k1"));
            cols.push((vec![(idx::K2, 1.0)], "k2"));
            for (fixed, k, name) in [(fix.k3, idx::K3, "k3"), (fix.k4, idx::K4, "k4")] {
                if !fixed {
                    cols.push((vec![(k, 1.0)], name));
                }
            }
        } else if model != DistortionModel::Pinhole {
            cols.push((vec![(idx::K1, 1.0)], "k1"));
            cols.push((vec![(idx::K2, 1.0)], "k2"));
            if !fix.tangential {
                cols.push((vec![(idx::P1, 1.0)], "p1"));
                cols.push((vec![(idx::P2, 1.0)], "p2"));
            }
            if !fix.k3 {
                cols.push((vec![(idx::K3, 1.0)], "k3"));
            }
        }
        if model == DistortionModel::Brown8 {
            for (fixed, k, name) in [
                (fix.k4, idx::K4, "k4"),
                (fix.k5, idx::K5, "k5"),
                (fix.k6, idx::K6, "k6"),
            ] {
                if !fixed {
                    cols.push((vec![(k, 1.0)], name));
                }
            }
        }
        let mut m = DMatrix::zeros(N_INTRINSIC, cols.len());
        let mut names = Vec::with_capacity(cols.len());
        for (j, (entries, name)) in cols.into_iter().enumerate() {
            for (row, coef) in entries {
                m[(row, j)] = coef;
            }
            names.push(name);
        }
        ParamMap { m, names }
    }

    pub(super) fn len(&self) -> usize {
        self.names.len()
    }

    /// `camera` with its full parameter vector moved by `M δθ`; `d` holds at least the free
    /// parameters' increments `δθ` (the first [`ParamMap::len`] entries are used).
    pub(super) fn step(&self, camera: &Camera, d: &[f64]) -> Camera {
        let dx = &self.m * DVector::from_column_slice(&d[..self.len()]);
        let mut cam = camera.clone();
        for k in 0..N_INTRINSIC {
            cam.params[k] += dx[k];
        }
        cam
    }

    /// From the covariance of the free parameters: the standard deviation of each of the 13 intrinsic
    /// parameters (0 for fixed ones), and which of them are estimated.
    pub(super) fn std_dev(
        &self,
        covariance: &DMatrix<f64>,
    ) -> ([f64; N_INTRINSIC], [bool; N_INTRINSIC]) {
        let m = &self.m;
        let full_cov = m * covariance * m.transpose();
        let mut std_dev = [0.0; N_INTRINSIC];
        let mut estimated = [false; N_INTRINSIC];
        for k in 0..N_INTRINSIC {
            estimated[k] = m.row(k).iter().any(|&x| x != 0.0);
            std_dev[k] = full_cov[(k, k)].max(0.0).sqrt();
        }
        (std_dev, estimated)
    }
}

/// Apply the fixes to an initial camera so that fixed parameters hold their fixed values.
pub(super) fn apply_fixes(camera: &mut Camera, fix: &Fix) {
    let p = &mut camera.params;
    if fix.skew {
        p[idx::SKEW] = 0.0;
    }
    if let Some(a) = fix.aspect_ratio {
        let f = 0.5 * (p[idx::FX] / a + p[idx::FY]);
        p[idx::FY] = f;
        p[idx::FX] = a * f;
    }
    if fix.principal_point {
        let c = image_centre(camera.image_size);
        p[idx::CX] = c.x;
        p[idx::CY] = c.y;
    }
    if fix.tangential {
        p[idx::P1] = 0.0;
        p[idx::P2] = 0.0;
    }
    if fix.k3 {
        p[idx::K3] = 0.0;
    }
    for (fixed, k) in [(fix.k4, idx::K4), (fix.k5, idx::K5), (fix.k6, idx::K6)] {
        if fixed {
            p[k] = 0.0;
        }
    }
}

/// The camera problem: the free intrinsics are the shared block of [`BlockProblem`].
struct Problem<'a> {
    views: &'a [View],
    /// `active[i][j]`: point j of view i is used.
    active: Vec<Vec<bool>>,
    /// In whitened units when `whiten` is set.
    loss: Loss,
    map: ParamMap,
    /// `whiten[i][j] = L⁻¹` with `Σ_ij = L Lᵀ`, when the points are weighted by their covariances.
    whiten: Option<Vec<Vec<Matrix2<f64>>>>,
    /// `whiten` holds [`Weighting::Equal`]'s weights (no claimed scatter to compare with), whose
    /// unit is `unit_px` px. They are isotropic, `s·I` ([`equal_whitening`]): `linearise` folds
    /// them into each residual's weight.
    equal: bool,
    unit_px: f64,
}

/// `L⁻¹` for the Cholesky factor `L` of a symmetric positive definite 2×2 matrix (`None` otherwise).
fn inverse_cholesky(c: &Matrix2<f64>) -> Option<Matrix2<f64>> {
    let a = c[(0, 0)].sqrt();
    let b = c[(1, 0)] / a;
    let d = (c[(1, 1)] - b * b).sqrt();
    let w = Matrix2::new(1.0 / a, 0.0, -b / (a * d), 1.0 / d);
    (a > 0.0 && d > 0.0 && w.iter().all(|x| x.is_finite())).then_some(w)
}

/// With [`Weighting::Equal`], a corner whose own σ (`√(trace Σ / 2)`) is more than this many times
/// the median corner's counts by it: its weight is `(EQUAL_WEIGHT_CEILING · median / σ)²`; every
/// other corner weighs the same.
pub const EQUAL_WEIGHT_CEILING: f64 = 2.0;

/// The whitening matrices of every point and the corner σ (px) the solve's unit stands for, when
/// `weighting` asks for them and every point has a covariance. With [`Weighting::Equal`]: `None`
/// unless some corner's σ exceeds [`EQUAL_WEIGHT_CEILING`] × the median (then the plain equal solve
/// is the same), and otherwise isotropic weights `1 / max(ceiling, σ)` — equal for the corners the
/// detector rates ordinary, less for the few it says are much worse (a grazing face's, whose
/// covariance holds its bias: [`crate::detect::face::add_grazing_bias`]).
fn whitening(views: &[View], weighting: Weighting) -> Option<(Vec<Vec<Matrix2<f64>>>, f64)> {
    if weighting == Weighting::Equal {
        return equal_whitening(views);
    }
    let mut sigmas = Vec::new();
    let whiten = views
        .iter()
        .map(|v| {
            v.points
                .iter()
                .map(|c| {
                    let cov = c.cov?;
                    sigmas.push((cov.trace() / 2.0).sqrt());
                    inverse_cholesky(&cov)
                })
                .collect::<Option<Vec<_>>>()
        })
        .collect::<Option<Vec<_>>>()?;
    sigmas.sort_by(f64::total_cmp);
    let median = *sigmas.get(sigmas.len() / 2)?;
    (median > 0.0 && median.is_finite()).then_some((whiten, median))
}

/// [`whitening`] for [`Weighting::Equal`].
fn equal_whitening(views: &[View]) -> Option<(Vec<Vec<Matrix2<f64>>>, f64)> {
    let sigmas: Vec<Vec<f64>> = views
        .iter()
        .map(|v| {
            (v.points.iter())
                .map(|c| c.cov.map(|cov| (cov.trace() / 2.0).sqrt()))
                .collect::<Option<Vec<_>>>()
        })
        .collect::<Option<Vec<_>>>()?;
    let mut all: Vec<f64> = sigmas.iter().flatten().copied().collect();
    all.sort_by(f64::total_cmp);
    let median = *all.get(all.len() / 2)?;
    let ceiling = EQUAL_WEIGHT_CEILING * median;
    let largest = *all.last()?;
    if !(ceiling > 0.0 && largest.is_finite() && largest > ceiling) {
        return None;
    }
    let whiten = (sigmas.iter())
        .map(|v| {
            v.iter()
                .map(|&s| Matrix2::from_diagonal_element(1.0 / s.max(ceiling)))
                .collect()
        })
        .collect();
    Some((whiten, ceiling))
}

/// A loss whose scale (px) is expressed in units of `sigma` px.
fn loss_in_units(loss: Loss, sigma: f64) -> Loss {
    match loss {
        Loss::Squared => Loss::Squared,
        Loss::Huber(c) => Loss::Huber(c / sigma),
        Loss::Cauchy(c) => Loss::Cauchy(c / sigma),
    }
}

/// The camera and the per-view poses.
struct State {
    camera: Camera,
    poses: Vec<Pose>,
}

/// Residual `π(cam_from_rig · X) − u` of one correspondence with its Jacobians with respect to the full
/// intrinsic vector and to the pose increment `(δ_rotation, δ_translation)` applied on the left.
/// (Inlined: called out of line, its 40-number result went through memory, 9 % of `linearise`.)
#[inline(always)]
fn residual_jacobians(
    camera: &Camera,
    pose: &Pose,
    c: &super::Correspondence,
) -> Result<
    (
        Vector2<f64>,
        crate::camera::IntrinsicJacobian,
        SMatrix<f64, 2, 6>,
    ),
    crate::camera::CameraError,
> {
    let xr = pose.rotation * c.xyz;
    let xc = xr + pose.translation;
    let (uv, j_int, j_pt) = camera.project_cam_with_jacobians(&xc)?;
    Ok((uv - c.uv, j_int, rigid_jacobian(&j_pt, &xr)))
}

impl Problem<'_> {
    /// Point `j` of view `i`'s residual in the solve's units (whitened when weighted).
    #[inline]
    fn white(&self, i: usize, j: usize, r: Vector2<f64>) -> Vector2<f64> {
        match &self.whiten {
            Some(w) => w[i][j] * r,
            None => r,
        }
    }

    fn n_active(&self) -> usize {
        self.active
            .iter()
            .map(|a| a.iter().filter(|&&x| x).count())
            .sum()
    }
}

impl BlockProblem for Problem<'_> {
    type State = State;
    const SINGULAR: &'static str = "the normal equations are singular";

    fn n_residuals(&self) -> usize {
        2 * self.n_active()
    }

    /// Robust cost only, or `None` if a point falls behind the camera.
    fn cost(&self, s: &State) -> Option<f64> {
        let mut cost = 0.0;
        for (i, v) in self.views.iter().enumerate() {
            for (j, c) in v.points.iter().enumerate() {
                if !self.active[i][j] {
                    continue;
                }
                let uv = s.camera.project(&s.poses[i], &c.xyz).ok()?;
                cost += self.loss.rho(self.white(i, j, uv - c.uv).norm());
            }
        }
        cost.is_finite().then_some(cost)
    }

    /// Accumulates the intrinsic blocks over the full 13-vector in fixed-size matrices (the hot path),
    /// then maps them to the free parameters once.
    fn linearise(&self, s: &State) -> Result<Normal, CalibError> {
        let nv = self.views.len();
        let m = &self.map.m;
        let mt = m.transpose();
        let mut n = Normal::zeros(self.map.len(), nv);
        let mut u = Mat13::zeros();
        let mut g_c = Vec13::zeros();
        for (i, view) in self.views.iter().enumerate() {
            let pose = &s.poses[i];
            let mut w = Mat13x6::zeros();
            for (j, c) in view.points.iter().enumerate() {
                if !self.active[i][j] {
                    continue;
                }
                let (mut r, mut j_int, mut j_pose) = residual_jacobians(&s.camera, pose, c)
                    .map_err(|_| {
                        CalibError::Degenerate {
                            reason: format!("point {j} moved behind the camera during refinement"),
                        }
                        .in_view(&view.name)
                    })?;
                // The weight of each squared residual: the loss's, times the whitening's when it is a
                // scale (equal weights with their ceiling are `s·I`: folded in, not multiplied out).
                let wgt = match &self.whiten {
                    Some(wh) if self.equal => {
                        let sc = wh[i][j][(0, 0)];
                        n.add_cost(self.loss, sc * r.norm()) * sc * sc
                    }
                    Some(wh) => {
                        let l = &wh[i][j];
                        r = l * r;
                        j_int = l * j_int;
                        j_pose = l * j_pose;
                        n.add_cost(self.loss, r.norm())
                    }
                    None => n.add_cost(self.loss, r.norm()),
                };
                // Rank-2 updates of the lower triangles (symmetrised once at the end).
                for row in 0..2 {
                    let a = j_int.row(row).transpose();
                    let b = j_pose.row(row).transpose();
                    u.syger(wgt, &a, &a, 1.0);
                    w.ger(wgt, &a, &b, 1.0);
                    g_c.axpy(wgt * r[row], &a, 1.0);
                    n.add_pose_row(i, wgt, &b, r[row]);
                }
            }
            n.w[i] = &mt * DMatrix::from_column_slice(N_INTRINSIC, 6, w.as_slice());
        }
        // The V_i (and the still empty free block): the mapped U is symmetric as it stands.
        n.fill_upper_triangles();
        u.fill_upper_triangle_with_lower_triangle();
        n.u = &mt * DMatrix::from_column_slice(N_INTRINSIC, N_INTRINSIC, u.as_slice()) * m;
        n.g_c = &mt * DVector::from_column_slice(g_c.as_slice());
        Ok(n)
    }

    fn apply(&self, s: &State, step: &Step) -> State {
        State {
            camera: self.map.step(&s.camera, step.d_c.as_slice()),
            poses: update_poses(&s.poses, &step.d_p),
        }
    }
}

/// Validate, initialise and refine. See the module docs for the method.
pub fn solve(
    views: &[View],
    image_size: [u32; 2],
    opts: &SolveOptions,
) -> Result<Calibration, CalibError> {
    validate_views(views)?;
    if image_size[0] == 0 || image_size[1] == 0 {
        return Err(CalibError::InvalidOption {
            reason: format!("image size {}×{} is empty", image_size[0], image_size[1]),
        });
    }
    validate_image_points(views, image_size)?;
    let init = initialise(views, image_size, opts.model)?;
    solve_from(views, init, opts)
}

/// Refine from a given initial state (e.g. a previous profile).
pub fn solve_from(
    views: &[View],
    init: Initial,
    opts: &SolveOptions,
) -> Result<Calibration, CalibError> {
    validate_views(views)?;
    validate_image_points(views, init.camera.image_size)?;
    if init.poses.len() != views.len() {
        return Err(CalibError::InvalidOption {
            reason: format!(
                "{} initial poses for {} views",
                init.poses.len(),
                views.len()
            ),
        });
    }
    if let Some(a) = opts.fix.aspect_ratio
        && !(a > 0.0 && a.is_finite())
    {
        return Err(CalibError::InvalidOption {
            reason: format!("aspect ratio must be positive, got {a}"),
        });
    }
    if let Some(k) = opts.outlier_sigma
        && !(k > 0.0 && k.is_finite())
    {
        return Err(CalibError::InvalidOption {
            reason: format!("outlier threshold must be a positive number of sigmas, got {k}"),
        });
    }
    match opts.loss {
        Loss::Huber(c) | Loss::Cauchy(c) if !(c > 0.0 && c.is_finite()) => {
            return Err(CalibError::InvalidOption {
                reason: format!("robust loss scale must be positive, got {c}"),
            });
        }
        _ => {}
    }
    let mut camera = init
        .camera
        .clone()
        .with_distortion(opts.model, &init.camera.distortion_coefficients());
    apply_fixes(&mut camera, &opts.fix);
    let (whiten, loss, unit_px) = match whitening(views, opts.weighting) {
        Some((w, sigma)) => {
            info!(
                corner_sigma_px = sigma,
                weighting = ?opts.weighting,
                "points weighted by their own covariances"
            );
            (Some(w), loss_in_units(opts.loss, sigma), sigma)
        }
        None => (None, opts.loss, 1.0),
    };
    let mut problem = Problem {
        views,
        active: views.iter().map(|v| vec![true; v.points.len()]).collect(),
        loss,
        map: ParamMap::new(opts.model, &opts.fix),
        whiten,
        equal: opts.weighting == Weighting::Equal,
        unit_px,
    };
    let mut state = State {
        camera,
        poses: init.poses.clone(),
    };
    let mut total_iterations = 0;
    let mut termination;
    // Each round moves at least one point: a point is dropped at most twice and re-admitted at most
    // once, so the rounds are bounded by three times the number of points.
    let max_rounds = 1 + 3 * views.iter().map(|v| v.points.len()).sum::<usize>();
    let mut readmitted: Vec<Vec<bool>> =
        views.iter().map(|v| vec![false; v.points.len()]).collect();
    let mut round = 0;
    loop {
        round += 1;
        let (s, it, term) = levenberg_marquardt(&problem, state, opts.max_iterations)?;
        state = s;
        total_iterations += it;
        termination = term;
        info!(
            round,
            iterations = it,
            termination = term.as_str(),
            "refinement finished"
        );
        let Some(k) = opts.outlier_sigma else { break };
        if round >= max_rounds || !termination.is_converged() {
            break;
        }
        if outlier_round(&mut problem, &mut readmitted, &state, k)? == 0 {
            break;
        }
    }
    let cal = finish(&problem, state, total_iterations, termination, init.method)?;
    let [w, h] = cal.camera.image_size;
    let (cx, cy) = (cal.camera.cx(), cal.camera.cy());
    let inside = |x: f64, n: u32| x >= -0.5 && x <= f64::from(n) - 0.5;
    if !(inside(cx, w) && inside(cy, h)) {
        return Err(CalibError::PrincipalPointOutside {
            cx,
            cy,
            width: w,
            height: h,
        });
    }
    Ok(cal)
}

/// One round of outlier rejection against the current fit: re-admit rejected points whose residual
/// norm is now within `k·σ̂` (each point at most once, so that the rounds end), then in every view drop
/// the active point with the largest residual norm if it exceeds `k·σ̂` (σ̂ from the MAD of the
/// residual components of all points, rejected ones included). Returns how many points changed side.
fn outlier_round(
    problem: &mut Problem<'_>,
    readmitted: &mut [Vec<bool>],
    state: &State,
    k: f64,
) -> Result<usize, CalibError> {
    let State { camera, poses } = state;
    let mut comps = Vec::new();
    let mut norms: Vec<Vec<Option<f64>>> = Vec::with_capacity(problem.views.len());
    for (i, v) in problem.views.iter().enumerate() {
        let mut row = Vec::with_capacity(v.points.len());
        for (j, c) in v.points.iter().enumerate() {
            let r = match camera.project(&poses[i], &c.xyz) {
                Ok(uv) => problem.white(i, j, uv - c.uv),
                // A rejected point may lie anywhere; an active one must be in front of the camera.
                Err(_) if !problem.active[i][j] => {
                    row.push(None);
                    continue;
                }
                Err(_) => {
                    return Err(CalibError::Degenerate {
                        reason: format!("point {j} is behind the camera"),
                    }
                    .in_view(&v.name));
                }
            };
            comps.push(r.x.abs());
            comps.push(r.y.abs());
            row.push(Some(r.norm()));
        }
        norms.push(row);
    }
    comps.sort_by(f64::total_cmp);
    let sigma = 1.4826 * comps.get(comps.len() / 2).copied().unwrap_or(0.0);
    let threshold = k * sigma;
    let (mut dropped, mut returned) = (0, 0);
    for (i, row) in norms.iter().enumerate() {
        let mut worst: Option<(usize, f64)> = None;
        for (j, s) in row.iter().enumerate() {
            let Some(s) = *s else { continue };
            if !problem.active[i][j] {
                if s <= threshold && !readmitted[i][j] {
                    problem.active[i][j] = true;
                    readmitted[i][j] = true;
                    returned += 1;
                }
            } else if worst.is_none_or(|(_, w)| s > w) {
                worst = Some((j, s));
            }
        }
        if let Some((j, s)) = worst
            && s > threshold
            && s > 1e-9
        {
            problem.active[i][j] = false;
            dropped += 1;
            debug!(view = %problem.views[i].name, point = j, residual_px = s, threshold_px = threshold, "outlier rejected");
        }
    }
    if dropped + returned > 0 {
        info!(dropped, returned, threshold_px = threshold, "outlier round");
    }
    for (i, v) in problem.views.iter().enumerate() {
        let left = problem.active[i].iter().filter(|&&a| a).count();
        if left < 4 {
            return Err(CalibError::TooFewPoints { got: left, need: 4 }.in_view(&v.name));
        }
    }
    Ok(dropped + returned)
}

fn finish(
    problem: &Problem<'_>,
    state: State,
    iterations: usize,
    termination: Termination,
    init_method: InitMethod,
) -> Result<Calibration, CalibError> {
    let n = problem.linearise(&state)?;
    let State { camera, poses } = state;
    let map = &problem.map;
    let n_points = problem.n_active();
    let m_res = 2 * n_points;
    // Undamped Schur complement and its inverse: the marginal information of the intrinsics.
    let mut marginal = n.marginal(
        m_res,
        |i| problem.views[i].name.clone(),
        |s| CalibError::Undetermined {
            params: weakest_parameters(s, &map.names)
                .iter()
                .map(|n| n.to_string())
                .collect(),
        },
    )?;
    if problem.equal && problem.whiten.is_some() {
        // Equal weights with a ceiling: the residuals' scatter is measured in pixels over every
        // corner, as the plain equal solve measures it (the few corners that count by their own σ
        // keep their share of it), and the poses' σ are never smaller than that scatter gives
        // (the intrinsics' covariance is the sandwich below).
        let mut ssr = 0.0;
        for (i, v) in problem.views.iter().enumerate() {
            for (j, c) in v.points.iter().enumerate() {
                if let (true, Ok(uv)) = (problem.active[i][j], camera.project(&poses[i], &c.xyz)) {
                    ssr += (uv - c.uv).norm_squared();
                }
            }
        }
        let dof = m_res.saturating_sub(n.n_params()).max(1) as f64;
        let s2 = ssr / dof / (problem.unit_px * problem.unit_px);
        if s2.is_finite() && s2 > marginal.sigma2 && marginal.sigma2 > 0.0 {
            marginal.covariance *= s2 / marginal.sigma2;
            marginal.sigma2 = s2;
        }
    }
    // Equal weights: the intrinsics' covariance from each corner's own (the scatter's is right only
    // for equal noise).
    if (problem.equal || problem.whiten.is_some())
        && let Some(c) = sandwich_covariance(problem, &camera, &poses, &n, &marginal)
    {
        marginal.covariance = c;
    }
    let (std_dev, estimated) = map.std_dev(&marginal.covariance);

    let mut views = Vec::with_capacity(problem.views.len());
    // Σ r² in pixels (the normal equations' are whitened when weighted).
    let mut ssr_px = 0.0;
    for (i, v) in problem.views.iter().enumerate() {
        let mut ssr = 0.0;
        let mut count = 0;
        let mut outliers = Vec::new();
        for (j, c) in v.points.iter().enumerate() {
            if !problem.active[i][j] {
                outliers.push(j);
                continue;
            }
            if let Ok(uv) = camera.project(&poses[i], &c.xyz) {
                ssr += (uv - c.uv).norm_squared();
                count += 1;
            }
        }
        ssr_px += ssr;
        let (rotation_std_rad, translation_std) = marginal.pose_std(&n, i);
        views.push(ViewResult {
            name: v.name.clone(),
            cam_from_rig: poses[i],
            rms_px: if count > 0 {
                (ssr / (2 * count) as f64).sqrt()
            } else {
                f64::NAN
            },
            n_points: count,
            outliers,
            rotation_std_rad,
            translation_std,
        });
    }
    let (ssr, sigma_px, noise_scale) = match problem.whiten {
        None => (n.ssr, marginal.sigma2.sqrt(), None),
        Some(_) => (
            ssr_px,
            (ssr_px / (m_res - n.n_params()) as f64).sqrt(),
            // Equal weights claim no scatter of their own to compare with.
            (!problem.equal).then(|| marginal.sigma2.sqrt()),
        ),
    };
    Ok(Calibration {
        camera,
        views,
        rms_px: (ssr / m_res as f64).sqrt(),
        rms_reprojection_px: (ssr / n_points as f64).sqrt(),
        sigma_px,
        noise_scale,
        free_params: map.names.clone(),
        covariance: marginal.covariance,
        std_dev,
        estimated,
        n_points,
        n_params: n.n_params(),
        iterations,
        termination,
        init_method,
    })
}

/// The covariance of the free intrinsics as a sandwich `S⁻¹ (M + N) S⁻¹`, marginalised over each
/// view's pose (`Eᵢ = J̃ᵢ,cᵀ − W_v V_v⁻¹ J̃ᵢ,poseᵀ`, `Wᵢ` the corner's weight in the solve).
///
/// `M`, the corners' own part:
/// - equal weights (`Wᵢ` with its ceiling): `Σᵢ Eᵢ Wᵢ Σᵢ Wᵢᵀ Eᵢᵀ` with `Σᵢ` each corner's own
///   covariance, scaled by `χ²/dof` of the residuals against the `Σᵢ` (the detector's covariances
///   are right in their proportions, not necessarily in their scale). `σ̂² S⁻¹` from the residuals'
///   scatter is this covariance only when every corner's noise is the same: equal weights give
///   grazing, blurred and far faces' corners the same say as the rest, and their larger noise then
///   moves the estimate by more than the scatter admits. Needs every active corner's covariance.
/// - weighted by the corners' covariances (`Wᵢ = Σᵢ⁻¹`): `σ̂² S`, so that without `N` this is the
///   usual `σ̂² S⁻¹`.
///
/// `N` is the neighbours' part: `Σ (Eₐ Wₐ rₐ rᵦᵀ Wᵦ Eᵦᵀ + its transpose)` over the pairs of grid
/// neighbours of each view ([`grid_neighbours`]), with the residuals `r` standing in for the noise
/// (the cross-products of a heteroscedasticity-and-autocorrelation-consistent sandwich, with the
/// grid's adjacency as the kernel), added where it is significant ([`neighbours_part`]). Why:
/// neighbouring corners share the image noise of their overlapping fit windows and the model error
/// of their face (a lens or board the model does not fit), so they move together. Measured (issue
/// 29): residual correlation across the line joining neighbours ≈ 0.2 on the hard render set, 0.1
/// on the realistic one, 0.3–0.5 on real photos. `N` is used as estimated, negative directions
/// included: holding its eigenvalues at ≥ 0 made σ too large (hard set, 200 realisations: χ² of
/// fx, fy, cx, cy against the truth 3.37 against 3.80). Should `N` make the total indefinite, the
/// corners are taken as independent. `None` when a needed covariance is missing.
fn sandwich_covariance(
    problem: &Problem<'_>,
    camera: &Camera,
    poses: &[Pose],
    n: &Normal,
    marginal: &super::lm_core::Marginal,
) -> Option<DMatrix<f64>> {
    let m = &problem.map.m;
    let q = m.ncols();
    let mut own = DMatrix::<f64>::zeros(q, q);
    let (mut chi2, mut count) = (0.0, 0usize);
    // `Eᵢ = [mᵀ | −W_v V_v⁻¹] cᵢ` with `cᵢ` the corner's Jacobians stacked (STACKED×2, the full
    // intrinsic vector and the pose): per view, `Σᵢ cᵢ Qᵢ cᵢᵀ` in fixed size, then mapped once.
    type Stacked = SMatrix<f64, STACKED, STACKED>;
    let mut t = DMatrix::<f64>::zeros(q, STACKED);
    t.view_mut((0, 0), (q, N_INTRINSIC))
        .copy_from(&m.transpose());
    // Per view: each active corner's `yᵢ = Eᵢ Wᵢ rᵢ` (columns) and its neighbour pairs.
    let mut mapped: Vec<MappedView> = Vec::new();
    let mut weighted = Vec::new();
    let mut xyz = Vec::new();
    for (i, view) in problem.views.iter().enumerate() {
        let mut acc = Stacked::zeros();
        weighted.clear();
        xyz.clear();
        for (j, c) in view.points.iter().enumerate() {
            if !problem.active[i][j] {
                continue;
            }
            let (r, j_int, j_pose) = residual_jacobians(camera, &poses[i], c).ok()?;
            let ci = stacked(&j_int, &j_pose);
            // The corner's weight `Wᵢ = wᵀw` (`w` its whitening: `sc·I` for equal weights with
            // their ceiling, `L⁻¹` for its covariance; the identity when no corner is whitened).
            let w = problem
                .whiten
                .as_ref()
                .map_or(Matrix2::identity(), |w| w[i][j]);
            let wt_w = w.transpose() * w;
            if problem.equal {
                let cov = c.cov?;
                chi2 += r.dot(&(cov.try_inverse()? * r));
                count += 2;
                // `cᵢ Wᵢ Σᵢ Wᵢᵀ cᵢᵀ = (cᵢ R)(cᵢ R)ᵀ` with `R = Wᵢ chol(Σᵢ)`: two symmetric rank-1
                // updates of the lower triangle.
                let d = ci * (wt_w * cov.cholesky()?.l());
                for k in 0..2 {
                    acc.syger(1.0, &d.column(k), &d.column(k), 1.0);
                }
            }
            weighted.extend((ci * (wt_w * r)).iter());
            xyz.push(c.xyz);
        }
        t.view_mut((0, N_INTRINSIC), (q, 6))
            .copy_from(&(-marginal.w_vinv(n, i)));
        if problem.equal {
            acc.fill_upper_triangle_with_lower_triangle();
            own +=
                &t * DMatrix::from_column_slice(STACKED, STACKED, acc.as_slice()) * t.transpose();
        }
        let pairs = grid_neighbours(&xyz);
        if !pairs.is_empty() {
            let x = DMatrix::from_column_slice(STACKED, xyz.len(), &weighted);
            mapped.push((&t * x, pairs));
        }
    }
    // The covariance with the corners taken as independent, `S⁻¹ M S⁻¹`, and `M⁻¹` for the test of
    // the neighbours' part.
    let (independent, own_inv) = if problem.equal {
        // The corners' own part, at the scale of their covariances the residuals say.
        let dof = count.saturating_sub(n.n_params()).max(1) as f64;
        let own = own * (chi2 / dof);
        let own_inv = own.clone().cholesky()?.inverse();
        (&marginal.s_inv * own * &marginal.s_inv, own_inv)
    } else {
        // `M = σ̂² S`: the covariance as solved, and `M⁻¹ = S⁻¹ / σ̂²` without inverting twice.
        (
            marginal.covariance.clone(),
            &marginal.s_inv / marginal.sigma2,
        )
    };
    let out = match neighbours_part(&own_inv, &mapped) {
        Some(pairs_part) => {
            let with_pairs = &independent + &marginal.s_inv * pairs_part * &marginal.s_inv;
            // An indefinite total (`M + N`, as `S⁻¹` is definite) falls back to the corners taken
            // as independent.
            if with_pairs.clone().cholesky().is_some() {
                with_pairs
            } else {
                independent
            }
        }
        None if !problem.equal => return None,
        None => independent,
    };
    out.iter().all(|x| x.is_finite()).then_some(out)
}

/// The full intrinsic vector and the pose, stacked: the size of a corner's Jacobian `cᵢ` (its
/// transpose, STACKED×2) in the sandwich.
const STACKED: usize = N_INTRINSIC + 6;

/// A corner's Jacobians stacked as `cᵢ` (STACKED×2).
fn stacked(
    j_int: &crate::camera::IntrinsicJacobian,
    j_pose: &SMatrix<f64, 2, 6>,
) -> SMatrix<f64, STACKED, 2> {
    let mut ci = SMatrix::<f64, STACKED, 2>::zeros();
    ci.fixed_view_mut::<N_INTRINSIC, 2>(0, 0)
        .copy_from(&j_int.transpose());
    ci.fixed_view_mut::<6, 2>(N_INTRINSIC, 0)
        .copy_from(&j_pose.transpose());
    ci
}

/// One view's corners for [`neighbours_part`]: their mapped, weighted residuals `yᵢ = Eᵢ Wᵢ rᵢ`
/// (columns) and the pairs of grid neighbours among them.
type MappedView = (DMatrix<f64>, Vec<(usize, usize)>);

/// The neighbours' part `N = Σ_pairs (yₐ yᵦᵀ + yᵦ yₐᵀ)` of the sandwich's middle (`y` the corners'
/// mapped, weighted residuals, a view's in the columns of its matrix, with its neighbour pairs),
/// when it is significant against the corners' own part `own` (given as `own⁻¹`); `None` when it
/// is not. Where neighbours are independent `N` is noise about 0, which would shrink σ as often as
/// grow it (and, σ entering χ² inversely, make them too small on average: an equal-weight solve of
/// independent corners, 1/3 of them 5× noisier, went from χ² 4.98 to 5.40 against the truth). The test: `T = tr(own⁻¹ N) = Σ 2 yₐᵀ own⁻¹ yᵦ`, the
/// variance `N` adds relative to the corners' own, counts when it exceeds twice its standard error
/// under independence, `√(Σ (2 yₐᵀ own⁻¹ yᵦ)²)`.
fn neighbours_part(own_inv: &DMatrix<f64>, mapped: &[MappedView]) -> Option<DMatrix<f64>> {
    let q = own_inv.nrows();
    let (mut total, mut var) = (0.0, 0.0);
    let mut part = DMatrix::<f64>::zeros(q, q);
    for (y, pairs) in mapped {
        let u = own_inv * y;
        let mut sums = DMatrix::<f64>::zeros(q, y.ncols());
        for &(a, b) in pairs {
            let p = 2.0 * u.column(a).dot(&y.column(b));
            total += p;
            var += p * p;
            for k in 0..q {
                sums[(k, a)] += y[(k, b)];
                sums[(k, b)] += y[(k, a)];
            }
        }
        part += y * sums.transpose();
    }
    debug!(
        variance_added = total / q as f64,
        z = total / var.sqrt(),
        "neighbour correlation of the residuals"
    );
    (total > 2.0 * var.sqrt()).then(|| (&part + part.transpose()) * 0.5)
}

/// The free parameters that take part in the weakest direction of the information matrix `s` (the
/// eigenvector of its smallest eigenvalue after scaling to unit diagonal): the ones the data cannot
/// tell apart. A parameter with no information at all (zero diagonal) is named on its own.
fn weakest_parameters(s: &DMatrix<f64>, names: &[&'static str]) -> Vec<&'static str> {
    let p = s.nrows();
    let dead: Vec<&'static str> = (0..p)
        .filter(|&k| !(s[(k, k)] > 0.0 && s[(k, k)].is_finite()))
        .map(|k| names[k])
        .collect();
    if !dead.is_empty() {
        return dead;
    }
    let d: Vec<f64> = (0..p).map(|k| 1.0 / s[(k, k)].sqrt()).collect();
    let scaled = DMatrix::from_fn(p, p, |r, c| s[(r, c)] * d[r] * d[c]);
    if !scaled.iter().all(|x| x.is_finite()) {
        return names.to_vec();
    }
    let eig = scaled.symmetric_eigen();
    let Some(min) = (0..p).min_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]))
    else {
        return Vec::new();
    };
    let v = eig.eigenvectors.column(min);
    let largest = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    (0..p)
        .filter(|&k| v[k].abs() >= 0.3 * largest)
        .map(|k| names[k])
        .collect()
}

/// The information each view would give about the free intrinsics: for every view, its reduced
/// normal matrix `S_i = U_i − W_i V_i⁻¹ W_iᵀ` (the view's own pose eliminated), built by the solver's
/// own linearisation ([`BlockProblem::linearise`]) at `camera` and `poses` with unit corner noise.
/// The Schur complement of a set of views is the sum of theirs, so the covariance a solve would reach
/// on any subset is `σ² (Σ S_i)⁻¹` ([`predicted_covariance`]): this is how the station's planner
/// predicts what a pose would teach before taking it. The views' points are taken as observed
/// exactly (zero residuals), which is what the normal matrix of an unbiased fit converges to.
pub fn view_information(
    camera: &Camera,
    poses: &[Pose],
    views: &[View],
    model: DistortionModel,
    fix: &Fix,
) -> Result<(Vec<&'static str>, Vec<DMatrix<f64>>), CalibError> {
    if poses.len() != views.len() {
        return Err(CalibError::InvalidOption {
            reason: format!("{} poses for {} views", poses.len(), views.len()),
        });
    }
    let mut camera = camera
        .clone()
        .with_distortion(model, &camera.distortion_coefficients());
    apply_fixes(&mut camera, fix);
    let map = ParamMap::new(model, fix);
    let q = map.len();
    let mut out = Vec::with_capacity(views.len());
    for i in 0..views.len() {
        // U_i: the view's own share of U, rebuilt from its rows (U is a sum over views).
        let one = Problem {
            views: &views[i..=i],
            active: vec![vec![true; views[i].points.len()]],
            loss: Loss::Squared,
            map: ParamMap::new(model, fix),
            // Predicted corners carry no covariance of their own: equal weights.
            whiten: None,
            equal: true,
            unit_px: 1.0,
        };
        let ni = one.linearise(&State {
            camera: camera.clone(),
            poses: vec![poses[i]],
        })?;
        let vi = ni.v[0];
        let Some(vi_inv) = vi.cholesky().map(|c| c.inverse()) else {
            out.push(DMatrix::zeros(q, q));
            continue;
        };
        let vi_inv = DMatrix::from_column_slice(6, 6, vi_inv.as_slice());
        out.push(&ni.u - &ni.w[0] * vi_inv * ni.w[0].transpose());
    }
    Ok((map.names, out))
}

/// The covariance of the free intrinsics (names as [`view_information`] gives them) that a solve of
/// views with reduced information `infos` would reach with corner noise `sigma_px` per coordinate;
/// `None` when the sum is singular (some parameter undetermined by these views).
pub fn predicted_covariance(infos: &[&DMatrix<f64>], sigma_px: f64) -> Option<DMatrix<f64>> {
    let first = infos.first()?;
    let mut s = DMatrix::zeros(first.nrows(), first.ncols());
    for i in infos {
        s += *i;
    }
    s.cholesky().map(|c| c.inverse() * (sigma_px * sigma_px))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::calib::Correspondence;

    #[test]
    fn pose_jacobian_matches_central_differences() {
        let cam = crate::render::correspondences::reference_camera();
        let pose = Pose::from_axis_angle(
            Vector3::new(0.3, -0.5, 0.2),
            Vector3::new(-40.0, 25.0, 600.0),
        );
        let c = Correspondence {
            xyz: Vector3::new(120.0, -80.0, 35.0),
            uv: Vector2::new(600.0, 400.0),
            cov: None,
        };
        let (_, _, j_pose) = residual_jacobians(&cam, &pose, &c).unwrap();
        for k in 0..6 {
            let h = if k < 3 { 1e-7 } else { 1e-5 };
            let perturbed = |sign: f64| {
                let mut d = Vec6::zeros();
                d[k] = sign * h;
                let p = Pose {
                    rotation: nalgebra::Rotation3::new(Vector3::new(d[0], d[1], d[2]))
                        * pose.rotation,
                    translation: pose.translation + Vector3::new(d[3], d[4], d[5]),
                };
                residual_jacobians(&cam, &p, &c).unwrap().0
            };
            let num = (perturbed(1.0) - perturbed(-1.0)) / (2.0 * h);
            for r in 0..2 {
                let err = (num[r] - j_pose[(r, k)]).abs();
                assert!(
                    err < 1e-5 * (1.0 + num[r].abs()),
                    "pose param {k} row {r}: analytic {} numeric {}",
                    j_pose[(r, k)],
                    num[r]
                );
            }
        }
    }

    /// Equal weighting: no whitening while every corner's σ is within the ceiling (the plain equal
    /// solve, bit for bit); a corner whose σ is over twice the median counts by it, all others alike.
    #[test]
    fn equal_weights_have_a_ceiling_at_twice_the_median_sigma() {
        let point = |s: f64| Correspondence {
            xyz: Vector3::zeros(),
            uv: Vector2::zeros(),
            cov: Some(Matrix2::from_diagonal_element(s * s)),
        };
        let view = |sigmas: &[f64]| View {
            name: "v".into(),
            points: sigmas.iter().map(|&s| point(s)).collect(),
        };
        assert!(whitening(&[view(&[0.01, 0.012, 0.015, 0.019])], Weighting::Equal).is_none());
        let (w, unit) = whitening(&[view(&[0.01, 0.012, 0.015, 0.1])], Weighting::Equal).unwrap();
        // Median 0.015 (the upper of the two middle ones), ceiling 0.03 px.
        assert!((unit - 0.03).abs() < 1e-12, "{unit}");
        for (j, want) in [1.0 / 0.03, 1.0 / 0.03, 1.0 / 0.03, 10.0]
            .into_iter()
            .enumerate()
        {
            assert!((w[0][j][(0, 0)] - want).abs() < 1e-9, "{j}: {}", w[0][j]);
            assert!((w[0][j][(1, 1)] - want).abs() < 1e-9 && w[0][j][(0, 1)] == 0.0);
        }
        // A point without a covariance: plain equal weights.
        let mut v = view(&[0.01, 0.1]);
        v.points[0].cov = None;
        assert!(whitening(&[v], Weighting::Equal).is_none());
    }

    #[test]
    fn robust_losses_are_consistent() {
        for loss in [Loss::Squared, Loss::Huber(1.5), Loss::Cauchy(2.0)] {
            for s in [0.1, 1.0, 3.0, 10.0] {
                let h = 1e-6;
                let drho = (loss.rho(s + h) - loss.rho(s - h)) / (2.0 * h);
                assert!((drho / s - loss.weight(s)).abs() < 1e-6, "{loss:?} at {s}");
            }
        }
    }
}
