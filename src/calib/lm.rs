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
//! With `J = [J_c | J_1 … J_m]` the normal matrix has an arrow shape:
//! `U = Σ J_cᵀJ_c` (p×p), `V_i = J_iᵀJ_i` (6×6 per view), `W_i = J_cᵀJ_i`. Each step solves the reduced
//! system `(U − Σ W_i V_i⁻¹ W_iᵀ) δ_c = −g_c + Σ W_i V_i⁻¹ g_i`, then `δ_i = V_i⁻¹(−g_i − W_iᵀ δ_c)`:
//! cost linear in the number of views, and a p×p (p ≤ 13) dense solve. Damping is Marquardt's
//! (`λ·diag`), updated with Nielsen's rule from the gain ratio.
//!
//! ## Uncertainty
//! At the optimum `σ̂² = Σ r² / (2n − p_total)` and the covariance of the intrinsics is the
//! corresponding block of `σ̂² (JᵀJ)⁻¹`, which is exactly `σ̂² S⁻¹` with `S` the undamped Schur
//! complement. Per-view pose covariance is `σ̂² (V_i⁻¹ + V_i⁻¹ W_iᵀ S⁻¹ W_i V_i⁻¹)`. These assume
//! independent, equal-variance corner noise and a correct model; `tests/calibration.rs` checks the
//! claimed ±2σ coverage over seeded trials.
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

use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, SVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use tracing::{debug, info};

use super::init::{InitMethod, Initial, image_centre, initialise};
use super::{CalibError, View, validate_image_points, validate_views};
use crate::camera::{Camera, DistortionModel, N_INTRINSIC, PARAM_NAMES, Pose, idx};

type Mat13 = SMatrix<f64, N_INTRINSIC, N_INTRINSIC>;
type Mat13x6 = SMatrix<f64, N_INTRINSIC, 6>;
type Mat6 = SMatrix<f64, 6, 6>;
type Vec13 = SVector<f64, N_INTRINSIC>;
type Vec6 = SVector<f64, 6>;

/// Robust loss applied to each point's residual norm `s` (pixels).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Loss {
    /// Ordinary least squares, `ρ(s) = s²/2`.
    #[default]
    Squared,
    /// Huber with threshold `c` px: quadratic below `c`, linear above.
    Huber(f64),
    /// Cauchy (Lorentzian) with scale `c` px: `ρ(s) = c²/2 · ln(1 + s²/c²)`.
    Cauchy(f64),
}

impl Loss {
    pub(super) fn rho(self, s: f64) -> f64 {
        match self {
            Loss::Squared => 0.5 * s * s,
            Loss::Huber(c) => {
                if s <= c {
                    0.5 * s * s
                } else {
                    c * s - 0.5 * c * c
                }
            }
            Loss::Cauchy(c) => 0.5 * c * c * (s * s / (c * c)).ln_1p(),
        }
    }

    /// IRLS weight `ρ'(s)/s`.
    pub(super) fn weight(self, s: f64) -> f64 {
        match self {
            Loss::Squared => 1.0,
            Loss::Huber(c) => {
                if s <= c {
                    1.0
                } else {
                    c / s
                }
            }
            Loss::Cauchy(c) => 1.0 / (1.0 + s * s / (c * c)),
        }
    }
}

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
    /// Hold `k4 = 0`, `k5 = 0`, `k6 = 0` (rational model only), each on its own.
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
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            model: DistortionModel::Brown5,
            fix: Fix::default(),
            loss: Loss::Squared,
            outlier_sigma: None,
            max_iterations: 200,
        }
    }
}

/// Why the refinement stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Termination {
    /// The quadratic model predicts a relative cost decrease below 1e-12: at the optimum.
    SmallPredictedDecrease,
    /// The residuals are zero to machine precision.
    ZeroResidual,
    /// No step decreases the cost any further (damping exhausted) after the cost had stopped changing.
    NoFurtherDecrease,
    /// The iteration limit was reached before convergence: the result is not trustworthy.
    MaxIterations,
    /// Damping exhausted while the cost was still decreasing noticeably: the result is not trustworthy.
    Stalled,
}

impl Termination {
    /// Whether the refinement reached an optimum.
    pub fn is_converged(self) -> bool {
        matches!(
            self,
            Termination::SmallPredictedDecrease
                | Termination::ZeroResidual
                | Termination::NoFurtherDecrease
        )
    }

    /// The reason in words, for people.
    pub fn describe(self) -> &'static str {
        match self {
            Termination::SmallPredictedDecrease => "no step could reduce the error noticeably",
            Termination::ZeroResidual => "the data are fitted exactly",
            Termination::NoFurtherDecrease => "the error stopped decreasing",
            Termination::MaxIterations => "the iteration limit was reached",
            Termination::Stalled => "no step reduced the error although it was still falling",
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Termination::SmallPredictedDecrease => "small_predicted_decrease",
            Termination::ZeroResidual => "zero_residual",
            Termination::NoFurtherDecrease => "no_further_decrease",
            Termination::MaxIterations => "max_iterations",
            Termination::Stalled => "stalled",
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
        if model != DistortionModel::Pinhole {
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

/// Normal equations accumulated at one linearisation point.
struct Normal {
    u: Mat13,
    g_c: Vec13,
    v: Vec<Mat6>,
    w: Vec<Mat13x6>,
    g_p: Vec<Vec6>,
    /// Robust cost `Σ ρ(‖r‖)`.
    cost: f64,
    /// Weighted squared residuals `Σ w ‖r‖²` and plain `Σ ‖r‖²`.
    wssr: f64,
    ssr: f64,
}

struct Problem<'a> {
    views: &'a [View],
    /// `active[i][j]`: point j of view i is used.
    active: Vec<Vec<bool>>,
    loss: Loss,
}

pub(super) fn skew_matrix(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Residual `π(cam_from_rig · X) − u` of one correspondence with its Jacobians with respect to the full
/// intrinsic vector and to the pose increment `(δ_rotation, δ_translation)` applied on the left.
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
    let mut j_pose = SMatrix::<f64, 2, 6>::zeros();
    j_pose
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(-(j_pt * skew_matrix(&xr))));
    j_pose.fixed_view_mut::<2, 3>(0, 3).copy_from(&j_pt);
    Ok((uv - c.uv, j_int, j_pose))
}

impl Problem<'_> {
    fn n_active(&self) -> usize {
        self.active
            .iter()
            .map(|a| a.iter().filter(|&&x| x).count())
            .sum()
    }

    /// Robust cost only, or `None` if a point falls behind the camera.
    fn cost(&self, camera: &Camera, poses: &[Pose]) -> Option<f64> {
        let mut cost = 0.0;
        for (i, v) in self.views.iter().enumerate() {
            for (j, c) in v.points.iter().enumerate() {
                if !self.active[i][j] {
                    continue;
                }
                let uv = camera.project(&poses[i], &c.xyz).ok()?;
                cost += self.loss.rho((uv - c.uv).norm());
            }
        }
        cost.is_finite().then_some(cost)
    }

    fn linearise(&self, camera: &Camera, poses: &[Pose]) -> Result<Normal, CalibError> {
        let nv = self.views.len();
        let mut n = Normal {
            u: Mat13::zeros(),
            g_c: Vec13::zeros(),
            v: vec![Mat6::zeros(); nv],
            w: vec![Mat13x6::zeros(); nv],
            g_p: vec![Vec6::zeros(); nv],
            cost: 0.0,
            wssr: 0.0,
            ssr: 0.0,
        };
        for (i, view) in self.views.iter().enumerate() {
            let pose = &poses[i];
            for (j, c) in view.points.iter().enumerate() {
                if !self.active[i][j] {
                    continue;
                }
                let (r, j_int, j_pose) = residual_jacobians(camera, pose, c).map_err(|_| {
                    CalibError::Degenerate {
                        reason: format!("point {j} moved behind the camera during refinement"),
                    }
                    .in_view(&view.name)
                })?;
                let s = r.norm();
                let wgt = self.loss.weight(s);
                n.cost += self.loss.rho(s);
                n.ssr += s * s;
                n.wssr += wgt * s * s;
                // Rank-2 updates of the lower triangles (symmetrised once at the end).
                for row in 0..2 {
                    let a = j_int.row(row).transpose();
                    let b = j_pose.row(row).transpose();
                    n.u.syger(wgt, &a, &a, 1.0);
                    n.v[i].syger(wgt, &b, &b, 1.0);
                    n.w[i].ger(wgt, &a, &b, 1.0);
                    n.g_c.axpy(wgt * r[row], &a, 1.0);
                    n.g_p[i].axpy(wgt * r[row], &b, 1.0);
                }
            }
        }
        n.u.fill_upper_triangle_with_lower_triangle();
        for v in &mut n.v {
            v.fill_upper_triangle_with_lower_triangle();
        }
        Ok(n)
    }
}

/// Result of solving the (damped) reduced system.
struct Step {
    d_c: DVector<f64>,
    d_p: Vec<Vec6>,
}

/// Solve `(A + λ D) δ = −g` by the Schur complement on the intrinsic block.
fn solve_step(n: &Normal, map: &ParamMap, lambda: f64) -> Option<Step> {
    let m = &map.m;
    let u =
        m.transpose() * DMatrix::from_column_slice(N_INTRINSIC, N_INTRINSIC, n.u.as_slice()) * m;
    let g_c = m.transpose() * DVector::from_column_slice(n.g_c.as_slice());
    let p = map.len();
    let mut s = u.clone();
    for k in 0..p {
        s[(k, k)] += lambda * u[(k, k)].max(1e-12);
    }
    let mut rhs = -g_c;
    let mut vinv = Vec::with_capacity(n.v.len());
    let mut ws = Vec::with_capacity(n.v.len());
    for i in 0..n.v.len() {
        let mut vi = n.v[i];
        for k in 0..6 {
            vi[(k, k)] += lambda * n.v[i][(k, k)].max(1e-12);
        }
        let vi_inv = vi.cholesky()?.inverse();
        let wi = m.transpose() * DMatrix::from_column_slice(N_INTRINSIC, 6, n.w[i].as_slice());
        let wv = &wi * DMatrix::from_column_slice(6, 6, vi_inv.as_slice());
        s -= &wv * wi.transpose();
        rhs += &wv * DVector::from_column_slice(n.g_p[i].as_slice());
        vinv.push(vi_inv);
        ws.push(wi);
    }
    let d_c = s.cholesky()?.solve(&rhs);
    let mut d_p = Vec::with_capacity(n.v.len());
    for i in 0..n.v.len() {
        let wt_dc = ws[i].transpose() * &d_c;
        let b = -n.g_p[i] - Vec6::from_column_slice(wt_dc.as_slice());
        d_p.push(vinv[i] * b);
    }
    Some(Step { d_c, d_p })
}

fn apply_step(camera: &Camera, poses: &[Pose], map: &ParamMap, step: &Step) -> (Camera, Vec<Pose>) {
    let dx = &map.m * &step.d_c;
    let mut cam = camera.clone();
    for k in 0..N_INTRINSIC {
        cam.params[k] += dx[k];
    }
    let new_poses = poses
        .iter()
        .zip(&step.d_p)
        .map(|(p, d)| Pose {
            rotation: nalgebra::Rotation3::new(Vector3::new(d[0], d[1], d[2])) * p.rotation,
            translation: p.translation + Vector3::new(d[3], d[4], d[5]),
        })
        .collect();
    (cam, new_poses)
}

/// Run LM from the given state; returns the refined state, iterations and termination.
fn levenberg_marquardt(
    problem: &Problem<'_>,
    map: &ParamMap,
    mut camera: Camera,
    mut poses: Vec<Pose>,
    max_iterations: usize,
) -> Result<(Camera, Vec<Pose>, usize, Termination), CalibError> {
    let mut lambda = 1e-3;
    let mut nu = 2.0;
    let mut normal = problem.linearise(&camera, &poses)?;
    let m_res = 2 * problem.n_active();
    let zero_cost = 1e-26 * m_res as f64;
    let mut last_rel_decrease = f64::INFINITY;
    for iteration in 1..=max_iterations {
        if normal.cost <= zero_cost {
            return Ok((camera, poses, iteration - 1, Termination::ZeroResidual));
        }
        let Some(step) = solve_step(&normal, map, lambda) else {
            lambda *= nu;
            nu *= 2.0;
            if lambda > 1e20 {
                return Err(CalibError::Unobservable {
                    reason: "the normal equations are singular".into(),
                });
            }
            continue;
        };
        // Predicted decrease of the quadratic model: ½ (λ δᵀDδ − gᵀδ), in free coordinates.
        let pred = predicted_decrease(&normal, map, &step, lambda);
        if pred <= 1e-12 * normal.cost {
            return Ok((
                camera,
                poses,
                iteration,
                Termination::SmallPredictedDecrease,
            ));
        }
        let (cam_new, poses_new) = apply_step(&camera, &poses, map, &step);
        let new_cost = problem.cost(&cam_new, &poses_new);
        match new_cost {
            Some(c) if c < normal.cost => {
                let rho = (normal.cost - c) / pred;
                last_rel_decrease = (normal.cost - c) / normal.cost;
                lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                camera = cam_new;
                poses = poses_new;
                normal = problem.linearise(&camera, &poses)?;
                debug!(iteration, cost = normal.cost, lambda, "LM step accepted");
            }
            _ => {
                lambda *= nu;
                nu *= 2.0;
                if lambda > 1e16 {
                    let t = if last_rel_decrease < 1e-6 {
                        Termination::NoFurtherDecrease
                    } else {
                        Termination::Stalled
                    };
                    return Ok((camera, poses, iteration, t));
                }
            }
        }
    }
    Ok((camera, poses, max_iterations, Termination::MaxIterations))
}

fn predicted_decrease(n: &Normal, map: &ParamMap, step: &Step, lambda: f64) -> f64 {
    let m = &map.m;
    let u =
        m.transpose() * DMatrix::from_column_slice(N_INTRINSIC, N_INTRINSIC, n.u.as_slice()) * m;
    let g_c = m.transpose() * DVector::from_column_slice(n.g_c.as_slice());
    let mut dd = 0.0;
    let mut gd = g_c.dot(&step.d_c);
    for k in 0..map.len() {
        dd += u[(k, k)].max(1e-12) * step.d_c[k] * step.d_c[k];
    }
    for i in 0..n.v.len() {
        for k in 0..6 {
            dd += n.v[i][(k, k)].max(1e-12) * step.d_p[i][k] * step.d_p[i][k];
        }
        gd += n.g_p[i].dot(&step.d_p[i]);
    }
    0.5 * (lambda * dd - gd)
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
    let map = ParamMap::new(opts.model, &opts.fix);
    let mut problem = Problem {
        views,
        active: views.iter().map(|v| vec![true; v.points.len()]).collect(),
        loss: opts.loss,
    };
    let mut poses = init.poses.clone();
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
        let (c, p, it, term) =
            levenberg_marquardt(&problem, &map, camera, poses, opts.max_iterations)?;
        camera = c;
        poses = p;
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
        if outlier_round(&mut problem, &mut readmitted, &camera, &poses, k)? == 0 {
            break;
        }
    }
    let cal = finish(
        &problem,
        &map,
        camera,
        poses,
        total_iterations,
        termination,
        init.method,
    )?;
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
    camera: &Camera,
    poses: &[Pose],
    k: f64,
) -> Result<usize, CalibError> {
    let mut comps = Vec::new();
    let mut norms: Vec<Vec<Option<f64>>> = Vec::with_capacity(problem.views.len());
    for (i, v) in problem.views.iter().enumerate() {
        let mut row = Vec::with_capacity(v.points.len());
        for (j, c) in v.points.iter().enumerate() {
            let r = match camera.project(&poses[i], &c.xyz) {
                Ok(uv) => uv - c.uv,
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
    map: &ParamMap,
    camera: Camera,
    poses: Vec<Pose>,
    iterations: usize,
    termination: Termination,
    init_method: InitMethod,
) -> Result<Calibration, CalibError> {
    let n = problem.linearise(&camera, &poses)?;
    let n_points = problem.n_active();
    let m_res = 2 * n_points;
    let p_total = map.len() + 6 * problem.views.len();
    if m_res <= p_total {
        return Err(CalibError::Unobservable {
            reason: format!("{m_res} residuals for {p_total} parameters"),
        });
    }
    let sigma2 = n.wssr / (m_res - p_total) as f64;
    // Undamped Schur complement and its inverse: the marginal information of the intrinsics.
    let m = &map.m;
    let mut s =
        m.transpose() * DMatrix::from_column_slice(N_INTRINSIC, N_INTRINSIC, n.u.as_slice()) * m;
    let mut vinv = Vec::with_capacity(n.v.len());
    let mut ws = Vec::with_capacity(n.v.len());
    for i in 0..n.v.len() {
        let vi_inv =
            n.v[i]
                .cholesky()
                .map(|c| c.inverse())
                .ok_or_else(|| CalibError::Unobservable {
                    reason: format!(
                        "the pose of view '{}' is not determined",
                        problem.views[i].name
                    ),
                })?;
        let wi = m.transpose() * DMatrix::from_column_slice(N_INTRINSIC, 6, n.w[i].as_slice());
        s -= &wi * DMatrix::from_column_slice(6, 6, vi_inv.as_slice()) * wi.transpose();
        vinv.push(vi_inv);
        ws.push(wi);
    }
    let s_inv =
        s.clone()
            .cholesky()
            .map(|c| c.inverse())
            .ok_or_else(|| CalibError::Undetermined {
                params: weakest_parameters(&s, &map.names)
                    .iter()
                    .map(|n| n.to_string())
                    .collect(),
            })?;
    let covariance = &s_inv * sigma2;
    let full_cov = m * &covariance * m.transpose();
    let mut std_dev = [0.0; N_INTRINSIC];
    let mut estimated = [false; N_INTRINSIC];
    for k in 0..N_INTRINSIC {
        estimated[k] = m.row(k).iter().any(|&x| x != 0.0);
        std_dev[k] = full_cov[(k, k)].max(0.0).sqrt();
    }

    let mut views = Vec::with_capacity(problem.views.len());
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
        let vi = DMatrix::from_column_slice(6, 6, vinv[i].as_slice());
        // Cov_i = σ² (V⁻¹ + V⁻¹ Wᵀ S⁻¹ W V⁻¹)
        let wv = &ws[i] * &vi; // p×6
        let cov_pose = (&vi + wv.transpose() * &s_inv * &wv) * sigma2;
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
            rotation_std_rad: [
                cov_pose[(0, 0)].max(0.0).sqrt(),
                cov_pose[(1, 1)].max(0.0).sqrt(),
                cov_pose[(2, 2)].max(0.0).sqrt(),
            ],
            translation_std: [
                cov_pose[(3, 3)].max(0.0).sqrt(),
                cov_pose[(4, 4)].max(0.0).sqrt(),
                cov_pose[(5, 5)].max(0.0).sqrt(),
            ],
        });
    }
    Ok(Calibration {
        camera,
        views,
        rms_px: (n.ssr / m_res as f64).sqrt(),
        rms_reprojection_px: (n.ssr / n_points as f64).sqrt(),
        sigma_px: sigma2.sqrt(),
        free_params: map.names.clone(),
        covariance,
        std_dev,
        estimated,
        n_points,
        n_params: p_total,
        iterations,
        termination,
        init_method,
    })
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
