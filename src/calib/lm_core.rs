//! The Levenberg–Marquardt machinery shared by the camera solve ([`super::solve`]) and the rig
//! refinement ([`super::solve_rig`]): robust losses, the arrow-shaped normal equations, their Schur
//! complement, the damping loop and the marginal covariance of the shared block.
//!
//! ## Parameter blocks
//! A problem ([`BlockProblem`]) has a *shared* block of `q` parameters that every residual may touch
//! (the free intrinsics; for the rig also six per refined face) and one six-parameter pose block per
//! view that only that view's residuals touch. It supplies the normal equations at a state
//! ([`Normal`], already in its free coordinates), the robust cost of a trial state, and how a step moves
//! the state. Everything else — the reduced system, Nielsen's damping, the stopping rules, σ̂² and the
//! covariances — is here, once.
//!
//! ## Normal equations and the Schur complement
//! With `J = [J_c | J_1 … J_m]` the normal matrix has an arrow shape:
//! `U = Σ J_cᵀJ_c` (q×q), `V_i = J_iᵀJ_i` (6×6 per view), `W_i = J_cᵀJ_i`. Each step solves the reduced
//! system `(U − Σ W_i V_i⁻¹ W_iᵀ) δ_c = −g_c + Σ W_i V_i⁻¹ g_i`, then `δ_i = V_i⁻¹(−g_i − W_iᵀ δ_c)`:
//! cost linear in the number of views, and a q×q dense solve. Damping is Marquardt's (`λ·diag`),
//! updated with Nielsen's rule from the gain ratio.
//!
//! ## Uncertainty
//! At the optimum `σ̂² = Σ w r² / (m − p_total)` and the covariance of the shared block is the
//! corresponding block of `σ̂² (JᵀJ)⁻¹`, which is exactly `σ̂² S⁻¹` with `S` the undamped Schur
//! complement. Per-view pose covariance is `σ̂² (V_i⁻¹ + V_i⁻¹ W_iᵀ S⁻¹ W_i V_i⁻¹)`.
//!
//! This file depends on nothing in `calib` but the error type: `lm.rs` and `rigrefine.rs` build on it.

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SMatrix, SVector, Vector3};
use serde::{Deserialize, Serialize};
use tracing::debug;

use super::CalibError;
use crate::camera::{PointJacobian, Pose};

pub(super) type Mat6 = SMatrix<f64, 6, 6>;
pub(super) type Vec6 = SVector<f64, 6>;
pub(super) type Mat2x6 = SMatrix<f64, 2, 6>;

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
    #[inline]
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
    #[inline]
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

#[inline]
pub(super) fn skew_matrix(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Jacobian of an image point with respect to a rigid increment `(δω, δt)` applied on the left to the
/// motion that carries it (`R ← exp([δω]ₓ) R`, `t ← t + δt`): `j · [−[a]ₓ | I]`, with `j` the image
/// point's Jacobian with respect to the moved point and `a` the rotated arm (`R X`, or for a face
/// `R (X − c)`).
#[inline]
pub(super) fn rigid_jacobian(j: &PointJacobian, arm: &Vector3<f64>) -> Mat2x6 {
    let mut out = Mat2x6::zeros();
    out.fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(-(j * skew_matrix(arm))));
    out.fixed_view_mut::<2, 3>(0, 3).copy_from(j);
    out
}

/// The rigid motion `(R, t)` moved by the increment `d = (δω, δt)`: `R ← exp([δω]ₓ) R`, `t ← t + δt`.
pub(super) fn update_rigid(
    rotation: &Rotation3<f64>,
    translation: &Vector3<f64>,
    d: &[f64],
) -> (Rotation3<f64>, Vector3<f64>) {
    (
        Rotation3::new(Vector3::new(d[0], d[1], d[2])) * rotation,
        translation + Vector3::new(d[3], d[4], d[5]),
    )
}

/// The per-view poses moved by a step's pose increments.
pub(super) fn update_poses(poses: &[Pose], d_p: &[Vec6]) -> Vec<Pose> {
    poses
        .iter()
        .zip(d_p)
        .map(|(p, d)| {
            let (rotation, translation) = update_rigid(&p.rotation, &p.translation, d.as_slice());
            Pose {
                rotation,
                translation,
            }
        })
        .collect()
}

/// Normal equations accumulated at one linearisation point, in the problem's free coordinates.
pub(super) struct Normal {
    /// Shared block `U` (q×q).
    pub(super) u: DMatrix<f64>,
    pub(super) g_c: DVector<f64>,
    /// Per-view pose blocks `V_i`.
    pub(super) v: Vec<Mat6>,
    /// Shared × view blocks `W_i` (q×6).
    pub(super) w: Vec<DMatrix<f64>>,
    pub(super) g_p: Vec<Vec6>,
    /// Robust cost `Σ ρ(‖r‖)`.
    pub(super) cost: f64,
    /// Weighted squared residuals `Σ w ‖r‖²` and plain `Σ ‖r‖²`.
    pub(super) wssr: f64,
    pub(super) ssr: f64,
}

impl Normal {
    /// All zero, for a shared block of `q` parameters and `n_views` views.
    pub(super) fn zeros(q: usize, n_views: usize) -> Normal {
        Normal {
            u: DMatrix::zeros(q, q),
            g_c: DVector::zeros(q),
            v: vec![Mat6::zeros(); n_views],
            w: vec![DMatrix::zeros(q, 6); n_views],
            g_p: vec![Vec6::zeros(); n_views],
            cost: 0.0,
            wssr: 0.0,
            ssr: 0.0,
        }
    }

    /// Count one point with residual norm `s` into the costs; returns its IRLS weight.
    #[inline]
    pub(super) fn add_cost(&mut self, loss: Loss, s: f64) -> f64 {
        let wgt = loss.weight(s);
        self.cost += loss.rho(s);
        self.ssr += s * s;
        self.wssr += wgt * s * s;
        wgt
    }

    /// Add one residual row's pose part `b` (weight `wgt`, residual `r`) to view `i`'s blocks (the
    /// lower triangle of `V_i`: see [`Normal::fill_upper_triangles`]).
    #[inline]
    pub(super) fn add_pose_row(&mut self, i: usize, wgt: f64, b: &Vec6, r: f64) {
        self.v[i].syger(wgt, b, b, 1.0);
        self.g_p[i].axpy(wgt * r, b, 1.0);
    }

    /// Symmetrise `U` and the `V_i` from their accumulated lower triangles.
    pub(super) fn fill_upper_triangles(&mut self) {
        self.u.fill_upper_triangle_with_lower_triangle();
        for v in &mut self.v {
            v.fill_upper_triangle_with_lower_triangle();
        }
    }

    /// Number of parameters: the shared block plus six per view.
    pub(super) fn n_params(&self) -> usize {
        self.u.nrows() + 6 * self.v.len()
    }

    /// Solve `(A + λ D) δ = −g` by the Schur complement on the shared block; `None` when a damped
    /// block is not positive definite.
    fn solve_step(&self, lambda: f64) -> Option<Step> {
        let q = self.u.nrows();
        let mut s = self.u.clone();
        for k in 0..q {
            s[(k, k)] += lambda * self.u[(k, k)].max(1e-12);
        }
        let mut rhs = -&self.g_c;
        let mut vinv = Vec::with_capacity(self.v.len());
        for i in 0..self.v.len() {
            let mut vi = self.v[i];
            for k in 0..6 {
                vi[(k, k)] += lambda * self.v[i][(k, k)].max(1e-12);
            }
            let vi_inv = vi.cholesky()?.inverse();
            let wv = &self.w[i] * vi_inv;
            s -= &wv * self.w[i].transpose();
            rhs += &wv * self.g_p[i];
            vinv.push(vi_inv);
        }
        let d_c = s.cholesky()?.solve(&rhs);
        let d_p = (0..self.v.len())
            .map(|i| {
                let wt_dc: Vec6 = self.w[i].tr_mul(&d_c).fixed_rows::<6>(0).into_owned();
                vinv[i] * (-self.g_p[i] - wt_dc)
            })
            .collect();
        Some(Step { d_c, d_p })
    }

    /// Decrease of the quadratic model for `step`: `½ (λ δᵀDδ − gᵀδ)`.
    fn predicted_decrease(&self, step: &Step, lambda: f64) -> f64 {
        let mut dd = 0.0;
        let mut gd = self.g_c.dot(&step.d_c);
        for k in 0..self.u.nrows() {
            dd += self.u[(k, k)].max(1e-12) * step.d_c[k] * step.d_c[k];
        }
        for i in 0..self.v.len() {
            for k in 0..6 {
                dd += self.v[i][(k, k)].max(1e-12) * step.d_p[i][k] * step.d_p[i][k];
            }
            gd += self.g_p[i].dot(&step.d_p[i]);
        }
        0.5 * (lambda * dd - gd)
    }

    /// The covariance at the optimum from these (undamped) normal equations over `n_residuals`
    /// residual components. `view_name(i)` names a view whose pose is not determined;
    /// `undetermined(S)` makes the error for a singular Schur complement `S`.
    pub(super) fn marginal(
        &self,
        n_residuals: usize,
        view_name: impl Fn(usize) -> String,
        undetermined: impl FnOnce(&DMatrix<f64>) -> CalibError,
    ) -> Result<Marginal, CalibError> {
        let p_total = self.n_params();
        if n_residuals <= p_total {
            return Err(CalibError::Unobservable {
                reason: format!("{n_residuals} residuals for {p_total} parameters"),
            });
        }
        let sigma2 = self.wssr / (n_residuals - p_total) as f64;
        let mut s = self.u.clone();
        let mut vinv = Vec::with_capacity(self.v.len());
        for i in 0..self.v.len() {
            let vi_inv = self.v[i].cholesky().map(|c| c.inverse()).ok_or_else(|| {
                CalibError::Unobservable {
                    reason: format!("the pose of view '{}' is not determined", view_name(i)),
                }
            })?;
            s -= &self.w[i] * vi_inv * self.w[i].transpose();
            vinv.push(vi_inv);
        }
        let s_inv = match s.clone().cholesky() {
            Some(c) => c.inverse(),
            None => return Err(undetermined(&s)),
        };
        Ok(Marginal {
            sigma2,
            covariance: &s_inv * sigma2,
            s_inv,
            vinv,
        })
    }
}

/// Uncertainty at the optimum: see the module docs.
pub(super) struct Marginal {
    /// `σ̂²`, the estimated variance of a residual component.
    pub(super) sigma2: f64,
    /// Covariance of the shared block, `σ̂² S⁻¹`.
    pub(super) covariance: DMatrix<f64>,
    /// `S⁻¹`.
    pub(super) s_inv: DMatrix<f64>,
    vinv: Vec<Mat6>,
}

impl Marginal {
    /// `W_i V_i⁻¹` (q×6) of view `i`, `n` the normal equations this was computed from: how the
    /// view's pose moves with the shared block.
    pub(super) fn w_vinv(&self, n: &Normal, i: usize) -> DMatrix<f64> {
        &n.w[i] * DMatrix::from_column_slice(6, 6, self.vinv[i].as_slice())
    }

    /// Standard deviations of view `i`'s rotation (radians) and translation, from
    /// `σ̂² (V⁻¹ + V⁻¹ Wᵀ S⁻¹ W V⁻¹)`; `n` the normal equations this was computed from.
    pub(super) fn pose_std(&self, n: &Normal, i: usize) -> ([f64; 3], [f64; 3]) {
        let vi = DMatrix::from_column_slice(6, 6, self.vinv[i].as_slice());
        let wv = self.w_vinv(n, i);
        let cov = (&vi + wv.transpose() * &self.s_inv * &wv) * self.sigma2;
        let sd = |k: usize| cov[(k, k)].max(0.0).sqrt();
        ([sd(0), sd(1), sd(2)], [sd(3), sd(4), sd(5)])
    }
}

/// A damped step: the shared block's increment and each view's pose increment.
pub(super) struct Step {
    pub(super) d_c: DVector<f64>,
    pub(super) d_p: Vec<Vec6>,
}

/// A least-squares problem with a shared parameter block and one pose block per view.
pub(super) trait BlockProblem {
    type State;
    /// The reason given when the normal equations stay singular at any damping.
    const SINGULAR: &'static str;
    /// Number of residual components (twice the points used).
    fn n_residuals(&self) -> usize;
    /// Normal equations at `state`.
    fn linearise(&self, state: &Self::State) -> Result<Normal, CalibError>;
    /// Robust cost at `state`, or `None` if it cannot be evaluated (a point behind the camera).
    fn cost(&self, state: &Self::State) -> Option<f64>;
    /// `state` moved by `step`.
    fn apply(&self, state: &Self::State, step: &Step) -> Self::State;
}

/// Levenberg–Marquardt with Nielsen's damping update from `state`; returns the refined state, the
/// iterations (accepted plus rejected steps) and why it stopped.
pub(super) fn levenberg_marquardt<P: BlockProblem>(
    problem: &P,
    mut state: P::State,
    max_iterations: usize,
) -> Result<(P::State, usize, Termination), CalibError> {
    let mut lambda = 1e-3;
    let mut nu = 2.0;
    let mut normal = problem.linearise(&state)?;
    let zero_cost = 1e-26 * problem.n_residuals() as f64;
    let mut last_rel_decrease = f64::INFINITY;
    for iteration in 1..=max_iterations {
        if normal.cost <= zero_cost {
            return Ok((state, iteration - 1, Termination::ZeroResidual));
        }
        let Some(step) = normal.solve_step(lambda) else {
            lambda *= nu;
            nu *= 2.0;
            if lambda > 1e20 {
                return Err(CalibError::Unobservable {
                    reason: P::SINGULAR.into(),
                });
            }
            continue;
        };
        let pred = normal.predicted_decrease(&step, lambda);
        if pred <= 1e-12 * normal.cost {
            return Ok((state, iteration, Termination::SmallPredictedDecrease));
        }
        let trial = problem.apply(&state, &step);
        match problem.cost(&trial) {
            Some(c) if c < normal.cost => {
                let rho = (normal.cost - c) / pred;
                last_rel_decrease = (normal.cost - c) / normal.cost;
                lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                state = trial;
                normal = problem.linearise(&state)?;
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
                    return Ok((state, iteration, t));
                }
            }
        }
    }
    Ok((state, max_iterations, Termination::MaxIterations))
}
