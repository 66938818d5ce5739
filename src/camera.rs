//! The camera model: intrinsics `K`, lens distortion, projection with analytic Jacobians, and
//! unprojection by bounded iterative undistortion.
//!
//! ## Model
//! A rig point `X` is moved into the camera frame by `cam_from_rig` (`X_c = R·X + t`), divided by its
//! depth (`x = X_c/Z_c`, `y = Y_c/Z_c`), distorted, then mapped to pixels by `K`:
//!
//! ```text
//! r² = x² + y²
//! radial = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
//! x'' = x·radial + 2 p1 x y + p2 (r² + 2x²)
//! y'' = y·radial + p1 (r² + 2y²) + 2 p2 x y
//! u = fx x'' + skew y'' + cx
//! v = fy y'' + cy
//! ```
//!
//! This is OpenCV's model and coefficient order `(k1, k2, p1, p2, k3, k4, k5, k6)`, so that a profile's
//! numbers mean the same thing in `cv::projectPoints`. With integer pixel coordinates at pixel centres
//! (see the crate docs) `cx, cy` are directly comparable with OpenCV's.
//!
//! The full intrinsic parameter vector used by the solvers is
//! `[fx, fy, cx, cy, skew, k1, k2, p1, p2, k3, k4, k5, k6]` ([`PARAM_NAMES`]); a [`DistortionModel`]
//! says which of the distortion entries are in use (the rest are held at zero).

use nalgebra::{Matrix2, Matrix3, Rotation3, SMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Number of entries in the full intrinsic parameter vector.
pub const N_INTRINSIC: usize = 13;

/// Names of the full intrinsic parameter vector, in order.
pub const PARAM_NAMES: [&str; N_INTRINSIC] = [
    "fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
];

/// Index of each parameter in the full intrinsic vector.
pub mod idx {
    pub const FX: usize = 0;
    pub const FY: usize = 1;
    pub const CX: usize = 2;
    pub const CY: usize = 3;
    pub const SKEW: usize = 4;
    pub const K1: usize = 5;
    pub const K2: usize = 6;
    pub const P1: usize = 7;
    pub const P2: usize = 8;
    pub const K3: usize = 9;
    pub const K4: usize = 10;
    pub const K5: usize = 11;
    pub const K6: usize = 12;
}

/// Errors from the camera model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// Iterative undistortion did not converge (typically: a pixel outside the region where the
    /// distortion polynomial is invertible, far beyond the calibrated field of view).
    #[error(
        "undistortion of pixel ({u:.3}, {v:.3}) did not converge after {iterations} iterations (residual {residual:.3e})"
    )]
    UndistortNotConverged {
        u: f64,
        v: f64,
        iterations: usize,
        residual: f64,
    },
    /// The point is behind the camera or on its centre plane and has no image.
    #[error("point is not in front of the camera (depth {depth:.6})")]
    BehindCamera { depth: f64 },
    /// An intrinsic value is unusable.
    #[error("invalid intrinsics: {reason}")]
    InvalidIntrinsics { reason: String },
    /// A distortion model name was not recognised.
    #[error("unknown distortion model '{0}' (expected pinhole, brown5 or brown8)")]
    UnknownModel(String),
}

/// Which lens-distortion terms are in use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DistortionModel {
    /// No distortion: a pure pinhole.
    Pinhole,
    /// Brown–Conrady with OpenCV's 5 coefficients `k1, k2, p1, p2, k3`.
    #[default]
    Brown5,
    /// Brown–Conrady rational model with OpenCV's 8 coefficients `k1, k2, p1, p2, k3, k4, k5, k6`.
    Brown8,
}

impl DistortionModel {
    /// Number of OpenCV coefficients this model writes out.
    pub fn n_coefficients(self) -> usize {
        match self {
            DistortionModel::Pinhole => 0,
            DistortionModel::Brown5 => 5,
            DistortionModel::Brown8 => 8,
        }
    }

    /// The model's name as used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            DistortionModel::Pinhole => "pinhole",
            DistortionModel::Brown5 => "brown5",
            DistortionModel::Brown8 => "brown8",
        }
    }
}

impl std::str::FromStr for DistortionModel {
    type Err = CameraError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "pinhole" | "none" => Ok(DistortionModel::Pinhole),
            "brown5" => Ok(DistortionModel::Brown5),
            "brown8" | "rational" => Ok(DistortionModel::Brown8),
            other => Err(CameraError::UnknownModel(other.to_string())),
        }
    }
}

/// A rigid transform `b_from_a`: `X_b = R·X_a + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
}

impl Pose {
    pub fn identity() -> Self {
        Pose {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Build from an axis-angle vector (radians, OpenCV's `rvec`) and a translation.
    pub fn from_axis_angle(rvec: Vector3<f64>, translation: Vector3<f64>) -> Self {
        Pose {
            rotation: Rotation3::new(rvec),
            translation,
        }
    }

    /// Apply the transform to a point.
    pub fn transform(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// The inverse transform (`a_from_b`).
    pub fn inverse(&self) -> Pose {
        let r = self.rotation.inverse();
        Pose {
            rotation: r,
            translation: -(r * self.translation),
        }
    }

    /// Compose: `self ∘ other` (apply `other` first).
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose {
            rotation: self.rotation * other.rotation,
            translation: self.rotation * other.translation + self.translation,
        }
    }

    /// Axis-angle vector (OpenCV `rvec`).
    pub fn rvec(&self) -> Vector3<f64> {
        self.rotation.scaled_axis()
    }

    /// Camera centre in the `a` frame when this is `cam_from_a`: `C = −Rᵀ t`.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }
}

/// A camera: image size, intrinsics and distortion, as one parameter vector (see [`PARAM_NAMES`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Image width and height in pixels.
    pub image_size: [u32; 2],
    /// Which distortion terms are in use.
    pub model: DistortionModel,
    /// `[fx, fy, cx, cy, skew, k1, k2, p1, p2, k3, k4, k5, k6]`.
    pub params: [f64; N_INTRINSIC],
}

/// Jacobian of one projected pixel with respect to the full intrinsic vector.
pub type IntrinsicJacobian = SMatrix<f64, 2, N_INTRINSIC>;
/// Jacobian of one projected pixel with respect to a point in the camera frame.
pub type PointJacobian = SMatrix<f64, 2, 3>;

/// Maximum Newton iterations in [`Camera::undistort`].
pub const UNDISTORT_MAX_ITERATIONS: usize = 50;
/// Convergence tolerance of [`Camera::undistort`], in normalised image units (≈ 1e-12 px·f).
pub const UNDISTORT_TOLERANCE: f64 = 1e-14;

impl Camera {
    /// A pinhole camera with square pixels, no skew and no distortion.
    pub fn pinhole(image_size: [u32; 2], fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        let mut params = [0.0; N_INTRINSIC];
        params[idx::FX] = fx;
        params[idx::FY] = fy;
        params[idx::CX] = cx;
        params[idx::CY] = cy;
        Camera {
            image_size,
            model: DistortionModel::Pinhole,
            params,
        }
    }

    /// Set the distortion model and its OpenCV-ordered coefficients (missing ones are zero).
    pub fn with_distortion(mut self, model: DistortionModel, coefficients: &[f64]) -> Self {
        self.model = model;
        let slots = [
            idx::K1,
            idx::K2,
            idx::P1,
            idx::P2,
            idx::K3,
            idx::K4,
            idx::K5,
            idx::K6,
        ];
        for (i, &slot) in slots.iter().enumerate() {
            self.params[slot] = if i < model.n_coefficients() {
                coefficients.get(i).copied().unwrap_or(0.0)
            } else {
                0.0
            };
        }
        self
    }

    pub fn fx(&self) -> f64 {
        self.params[idx::FX]
    }
    pub fn fy(&self) -> f64 {
        self.params[idx::FY]
    }
    pub fn cx(&self) -> f64 {
        self.params[idx::CX]
    }
    pub fn cy(&self) -> f64 {
        self.params[idx::CY]
    }
    pub fn skew(&self) -> f64 {
        self.params[idx::SKEW]
    }

    /// The camera matrix `K`.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.fx(),
            self.skew(),
            self.cx(),
            0.0,
            self.fy(),
            self.cy(),
            0.0,
            0.0,
            1.0,
        )
    }

    /// Distortion coefficients in OpenCV order, as many as the model uses.
    pub fn distortion_coefficients(&self) -> Vec<f64> {
        let all = [
            self.params[idx::K1],
            self.params[idx::K2],
            self.params[idx::P1],
            self.params[idx::P2],
            self.params[idx::K3],
            self.params[idx::K4],
            self.params[idx::K5],
            self.params[idx::K6],
        ];
        all[..self.model.n_coefficients()].to_vec()
    }

    /// Check that the intrinsics are finite and the focal lengths positive.
    pub fn validate(&self) -> Result<(), CameraError> {
        if let Some((i, v)) = self.params.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(CameraError::InvalidIntrinsics {
                reason: format!("{} is not finite ({v})", PARAM_NAMES[i]),
            });
        }
        if self.fx() <= 0.0 || self.fy() <= 0.0 {
            return Err(CameraError::InvalidIntrinsics {
                reason: format!(
                    "focal lengths must be positive (fx {}, fy {})",
                    self.fx(),
                    self.fy()
                ),
            });
        }
        Ok(())
    }

    /// Distort normalised coordinates: `(x, y) → (x'', y'')`.
    pub fn distort(&self, x: f64, y: f64) -> Vector2<f64> {
        let p = &self.params;
        let r2 = x * x + y * y;
        let r4 = r2 * r2;
        let r6 = r4 * r2;
        let radial = (1.0 + p[idx::K1] * r2 + p[idx::K2] * r4 + p[idx::K3] * r6)
            / (1.0 + p[idx::K4] * r2 + p[idx::K5] * r4 + p[idx::K6] * r6);
        let (p1, p2) = (p[idx::P1], p[idx::P2]);
        Vector2::new(
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Distort, returning also `∂(x'', y'')/∂(x, y)`: the same numbers as the first two of
    /// [`Camera::distort_with_jacobians`] without the coefficients' Jacobian (undistortion's Newton
    /// steps need only this, and the lens refit takes several per window pixel).
    pub fn distort_with_point_jacobian(&self, x: f64, y: f64) -> (Vector2<f64>, Matrix2<f64>) {
        let t = self.distortion_terms(x, y);
        (t.distorted, t.j_xy)
    }

    /// The distorted point, its point Jacobian, and the radial terms the coefficients' Jacobian
    /// is built from (shared by both `distort_with_*` functions).
    fn distortion_terms(&self, x: f64, y: f64) -> DistortionTerms {
        let p = &self.params;
        let (k1, k2, p1, p2, k3) = (p[idx::K1], p[idx::K2], p[idx::P1], p[idx::P2], p[idx::K3]);
        let (k4, k5, k6) = (p[idx::K4], p[idx::K5], p[idx::K6]);
        let r2 = x * x + y * y;
        let r4 = r2 * r2;
        let r6 = r4 * r2;
        let a = 1.0 + k1 * r2 + k2 * r4 + k3 * r6;
        let b = 1.0 + k4 * r2 + k5 * r4 + k6 * r6;
        let radial = a / b;
        let da = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4;
        let db = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4;
        let d_radial = (da * b - a * db) / (b * b); // ∂radial/∂r²
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let j_xy = Matrix2::new(
            radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x,
            2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y,
            2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y,
            radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x,
        );
        DistortionTerms {
            distorted: Vector2::new(xd, yd),
            j_xy,
            r2,
            r4,
            r6,
            a,
            b,
        }
    }

    /// Distort, returning also `∂(x'', y'')/∂(x, y)` and `∂(x'', y'')/∂(k1, k2, p1, p2, k3, k4, k5, k6)`.
    pub fn distort_with_jacobians(
        &self,
        x: f64,
        y: f64,
    ) -> (Vector2<f64>, Matrix2<f64>, SMatrix<f64, 2, 8>) {
        let DistortionTerms {
            distorted,
            j_xy,
            r2,
            r4,
            r6,
            a,
            b,
        } = self.distortion_terms(x, y);
        // ∂radial/∂k: numerator terms over b, denominator terms −a·r^n / b².
        let inv_b = 1.0 / b;
        let na = -a * inv_b * inv_b;
        let d_rad_dk = [
            r2 * inv_b,
            r4 * inv_b,
            r6 * inv_b,
            r2 * na,
            r4 * na,
            r6 * na,
        ];
        let mut j_k = SMatrix::<f64, 2, 8>::zeros();
        // Column order: k1, k2, p1, p2, k3, k4, k5, k6.
        let radial_cols = [0usize, 1, 4, 5, 6, 7];
        for (c, &col) in radial_cols.iter().enumerate() {
            j_k[(0, col)] = x * d_rad_dk[c];
            j_k[(1, col)] = y * d_rad_dk[c];
        }
        j_k[(0, 2)] = 2.0 * x * y;
        j_k[(1, 2)] = r2 + 2.0 * y * y;
        j_k[(0, 3)] = r2 + 2.0 * x * x;
        j_k[(1, 3)] = 2.0 * x * y;
        (distorted, j_xy, j_k)
    }

    /// Map distorted normalised coordinates to pixels.
    pub fn to_pixel(&self, d: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(
            self.fx() * d.x + self.skew() * d.y + self.cx(),
            self.fy() * d.y + self.cy(),
        )
    }

    /// Project a point given in the camera frame to a pixel.
    pub fn project_cam(&self, p: &Vector3<f64>) -> Result<Vector2<f64>, CameraError> {
        if p.z <= 0.0 || !p.z.is_finite() {
            return Err(CameraError::BehindCamera { depth: p.z });
        }
        let d = self.distort(p.x / p.z, p.y / p.z);
        Ok(self.to_pixel(&d))
    }

    /// Project a rig point seen from `cam_from_rig` to a pixel.
    pub fn project(
        &self,
        cam_from_rig: &Pose,
        x_rig: &Vector3<f64>,
    ) -> Result<Vector2<f64>, CameraError> {
        self.project_cam(&cam_from_rig.transform(x_rig))
    }

    /// Project a point in the camera frame, returning the pixel, `∂uv/∂(full intrinsic vector)` and
    /// `∂uv/∂X_cam`. The solvers chain `∂X_cam/∂pose` onto the latter.
    pub fn project_cam_with_jacobians(
        &self,
        p: &Vector3<f64>,
    ) -> Result<(Vector2<f64>, IntrinsicJacobian, PointJacobian), CameraError> {
        if p.z <= 0.0 || !p.z.is_finite() {
            return Err(CameraError::BehindCamera { depth: p.z });
        }
        let iz = 1.0 / p.z;
        let x = p.x * iz;
        let y = p.y * iz;
        let (d, j_xy, j_k) = self.distort_with_jacobians(x, y);
        let (fx, fy, s) = (self.fx(), self.fy(), self.skew());
        let uv = self.to_pixel(&d);
        // ∂uv/∂(x'', y'')
        let j_pix = Matrix2::new(fx, s, 0.0, fy);
        let mut j_int = IntrinsicJacobian::zeros();
        j_int[(0, idx::FX)] = d.x;
        j_int[(1, idx::FY)] = d.y;
        j_int[(0, idx::CX)] = 1.0;
        j_int[(1, idx::CY)] = 1.0;
        j_int[(0, idx::SKEW)] = d.y;
        let j_dist = j_pix * j_k;
        for c in 0..8 {
            j_int[(0, idx::K1 + c)] = j_dist[(0, c)];
            j_int[(1, idx::K1 + c)] = j_dist[(1, c)];
        }
        // ∂(x, y)/∂X_cam
        let j_norm = SMatrix::<f64, 2, 3>::new(iz, 0.0, -x * iz, 0.0, iz, -y * iz);
        let j_point = j_pix * j_xy * j_norm;
        Ok((uv, j_int, j_point))
    }

    /// Invert the distortion: distorted normalised `(x'', y'')` → undistorted `(x, y)`, by Newton's
    /// method from `(x'', y'')` with at most [`UNDISTORT_MAX_ITERATIONS`] steps. Reports
    /// non-convergence (and a fold in the distortion, where the inverse is not unique) as an error.
    pub fn undistort(&self, xd: f64, yd: f64) -> Result<Vector2<f64>, CameraError> {
        let start = Vector2::new(xd, yd);
        self.undistort_from(xd, yd, start).map(|(p, _)| p)
    }

    /// [`undistort`](Camera::undistort) with Newton's method started from `start` instead of
    /// `(x'', y'')`, returning also the Jacobian `∂(x'', y'')/∂(x, y)` at the solution. From the
    /// solution of a nearby point moved by that Jacobian's inverse (as when undistorting every
    /// pixel of a window in turn), it converges in one or two steps instead of four to eight.
    pub fn undistort_from(
        &self,
        xd: f64,
        yd: f64,
        start: Vector2<f64>,
    ) -> Result<(Vector2<f64>, Matrix2<f64>), CameraError> {
        let target = Vector2::new(xd, yd);
        let not_converged = |iterations: usize, residual: f64| {
            let px = self.to_pixel(&target);
            CameraError::UndistortNotConverged {
                u: px.x,
                v: px.y,
                iterations,
                residual,
            }
        };
        if !xd.is_finite() || !yd.is_finite() {
            return Err(not_converged(0, f64::NAN));
        }
        if self.model == DistortionModel::Pinhole {
            return Ok((target, Matrix2::identity()));
        }
        let mut p = if start.x.is_finite() && start.y.is_finite() {
            start
        } else {
            target
        };
        let mut residual = f64::INFINITY;
        for it in 0..UNDISTORT_MAX_ITERATIONS {
            let (d, j) = self.distort_with_point_jacobian(p.x, p.y);
            let r = d - target;
            residual = r.norm();
            if residual <= UNDISTORT_TOLERANCE * (1.0 + target.norm()) {
                // A solution past the fold (Jacobian not positive definite in orientation) is not
                // the physical inverse.
                if j.determinant() <= 0.0 {
                    return Err(not_converged(it, residual));
                }
                return Ok((p, j));
            }
            let step = match j.try_inverse() {
                Some(inv) => inv * r,
                None => return Err(not_converged(it, residual)),
            };
            // Limit the step so that the iteration cannot leap across the fold.
            let max_step = 0.5 * (1.0 + p.norm());
            let step = if step.norm() > max_step {
                step * (max_step / step.norm())
            } else {
                step
            };
            p -= step;
            if !p.x.is_finite() || !p.y.is_finite() {
                return Err(not_converged(it, residual));
            }
        }
        Err(not_converged(UNDISTORT_MAX_ITERATIONS, residual))
    }

    /// Unproject a pixel to a unit-length ray in the camera frame (z > 0).
    pub fn unproject(&self, u: f64, v: f64) -> Result<Vector3<f64>, CameraError> {
        let yd = (v - self.cy()) / self.fy();
        let xd = (u - self.cx() - self.skew() * yd) / self.fx();
        let p = self.undistort(xd, yd)?;
        Ok(Vector3::new(p.x, p.y, 1.0).normalize())
    }
}

/// What [`Camera::distort_with_point_jacobian`] and [`Camera::distort_with_jacobians`] share: the
/// distorted point, `∂(x'', y'')/∂(x, y)`, the powers of r² and the rational model's numerator `a`
/// and denominator `b`.
struct DistortionTerms {
    distorted: Vector2<f64>,
    j_xy: Matrix2<f64>,
    r2: f64,
    r4: f64,
    r6: f64,
    a: f64,
    b: f64,
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn test_camera() -> Camera {
        let mut c = Camera::pinhole([1280, 960], 910.0, 905.0, 641.3, 478.9).with_distortion(
            DistortionModel::Brown8,
            &[-0.21, 0.08, 0.0012, -0.0007, -0.015, 0.02, -0.01, 0.005],
        );
        c.params[idx::SKEW] = 0.7;
        c
    }

    #[test]
    fn intrinsic_jacobian_matches_central_differences() {
        let cam = test_camera();
        let p = Vector3::new(0.31, -0.22, 1.4);
        let (_, j_int, j_pt) = cam.project_cam_with_jacobians(&p).unwrap();
        for k in 0..N_INTRINSIC {
            let h = 1e-6 * (1.0 + cam.params[k].abs());
            let mut cp = cam.clone();
            cp.params[k] += h;
            let mut cm = cam.clone();
            cm.params[k] -= h;
            let num = (cp.project_cam(&p).unwrap() - cm.project_cam(&p).unwrap()) / (2.0 * h);
            for r in 0..2 {
                let err = (num[r] - j_int[(r, k)]).abs();
                assert!(
                    err < 1e-5 * (1.0 + num[r].abs()),
                    "param {} row {r}: analytic {} numeric {}",
                    PARAM_NAMES[k],
                    j_int[(r, k)],
                    num[r]
                );
            }
        }
        for k in 0..3 {
            let mut dp = Vector3::zeros();
            dp[k] = 1e-6;
            let num =
                (cam.project_cam(&(p + dp)).unwrap() - cam.project_cam(&(p - dp)).unwrap()) / 2e-6;
            for r in 0..2 {
                assert!((num[r] - j_pt[(r, k)]).abs() < 1e-4 * (1.0 + num[r].abs()));
            }
        }
    }

    #[test]
    fn fast_distort_agrees_with_the_jacobian_version() {
        let cam = test_camera();
        for (x, y) in [(0.1, -0.2), (0.5, 0.4), (-0.7, 0.05)] {
            assert!((cam.distort(x, y) - cam.distort_with_jacobians(x, y).0).norm() < 1e-15);
            let (d, j, _) = cam.distort_with_jacobians(x, y);
            assert_eq!(cam.distort_with_point_jacobian(x, y), (d, j));
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let cam = test_camera();
        for i in 0..=20 {
            for j in 0..=20 {
                let u = -0.5 + 1280.0 * i as f64 / 20.0;
                let v = -0.5 + 960.0 * j as f64 / 20.0;
                let ray = cam.unproject(u, v).unwrap();
                let back = cam.project_cam(&ray).unwrap();
                assert!(
                    (back - Vector2::new(u, v)).norm() < 1e-9,
                    "({u},{v}) -> {back}"
                );
            }
        }
    }

    #[test]
    fn undistort_reports_non_convergence_beyond_the_fold() {
        // Strong barrel distortion folds back: x'' = x (1 - 0.5 r²) peaks at r = 0.816 with
        // x'' = 0.544. A distorted radius of 0.8 has no inverse.
        let cam = Camera::pinhole([640, 480], 500.0, 500.0, 320.0, 240.0)
            .with_distortion(DistortionModel::Brown5, &[-0.5]);
        assert!(matches!(
            cam.undistort(0.8, 0.0),
            Err(CameraError::UndistortNotConverged { .. })
        ));
        assert!(cam.undistort(0.3, 0.1).is_ok());
    }

    #[test]
    fn behind_camera_is_an_error() {
        let cam = test_camera();
        assert!(matches!(
            cam.project_cam(&Vector3::new(0.0, 0.0, -1.0)),
            Err(CameraError::BehindCamera { .. })
        ));
    }

    #[test]
    fn matches_opencv_reference_projection() {
        // OpenCV's documented projectPoints formula evaluated by hand for
        // K = [[800, 0, 320], [0, 810, 240], [0, 0, 1]], dist = [-0.3, 0.1, 0.001, -0.002, 0.05],
        // rvec = 0, tvec = 0, X = (0.2, -0.1, 1.0):
        // r² = 0.05, radial = 1 - 0.015 + 0.00025 + 0.00000625 = 0.98525625
        // x'' = 0.19705125 + 2·0.001·(−0.02) + (−0.002)(0.05 + 0.08) = 0.19675125
        // y'' = −0.098525625 + 0.001·(0.05 + 0.02) + 2·(−0.002)·(−0.02) = −0.098375625
        let cam = Camera::pinhole([640, 480], 800.0, 810.0, 320.0, 240.0)
            .with_distortion(DistortionModel::Brown5, &[-0.3, 0.1, 0.001, -0.002, 0.05]);
        let uv = cam.project_cam(&Vector3::new(0.2, -0.1, 1.0)).unwrap();
        assert!((uv.x - (320.0 + 800.0 * 0.19675125)).abs() < 1e-9);
        assert!((uv.y - (240.0 - 810.0 * 0.098375625)).abs() < 1e-9);
    }
}
