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
//! **Fisheye** ([`DistortionModel::Kb4`]): Kannala–Brandt in OpenCV's `cv::fisheye` convention, a
//! polynomial in the angle θ between the ray and the optical axis rather than in `r`, so that it holds
//! to fields of view of 180° and beyond, where `X/Z` does not exist:
//!
//! ```text
//! θ = atan2(√(X² + Y²), Z)
//! θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)
//! (x'', y'') = θ_d · (X, Y) / √(X² + Y²)
//! ```
//!
//! then `K` as above. Projection is evaluated on the 3D point (valid while `θ_d` increases with θ,
//! [`CameraError::BeyondFieldOfView`] past that); unprojection solves `θ_d(θ) = |(x'', y'')|` by
//! Newton's method bounded to `[0, π)`. Its coefficients occupy the `k1, k2, k3, k4` slots below.
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
    /// The point lies beyond the lens model's field of view: past the angle where a fisheye's
    /// θ_d(θ) stops increasing (the image folds back), or straight behind the camera.
    #[error(
        "point at {theta_deg:.2}° off the optical axis is beyond the lens model's field of view"
    )]
    BeyondFieldOfView { theta_deg: f64 },
    /// A distortion model name was not recognised.
    #[error("unknown distortion model '{0}' (expected pinhole, brown5, brown8 or kb4)")]
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
    /// Kannala–Brandt fisheye with OpenCV's `cv::fisheye` convention and order `k1, k2, k3, k4`:
    /// `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)` (ROS `equidistant`, Kalibr `pinhole-equi`).
    Kb4,
}

impl DistortionModel {
    /// Number of OpenCV coefficients this model writes out.
    pub fn n_coefficients(self) -> usize {
        match self {
            DistortionModel::Pinhole => 0,
            DistortionModel::Brown5 => 5,
            DistortionModel::Brown8 => 8,
            DistortionModel::Kb4 => 4,
        }
    }

    /// Where the model's coefficients live in the full intrinsic vector, in the model's own order.
    pub fn coefficient_slots(self) -> &'static [usize] {
        const BROWN: [usize; 8] = [
            idx::K1,
            idx::K2,
            idx::P1,
            idx::P2,
            idx::K3,
            idx::K4,
            idx::K5,
            idx::K6,
        ];
        const KB4: [usize; 4] = [idx::K1, idx::K2, idx::K3, idx::K4];
        match self {
            DistortionModel::Pinhole => &[],
            DistortionModel::Brown5 => &BROWN[..5],
            DistortionModel::Brown8 => &BROWN,
            DistortionModel::Kb4 => &KB4,
        }
    }

    /// The names of the model's coefficients in its own order, as in [`PARAM_NAMES`]: OpenCV's
    /// `k1, k2, p1, p2, k3, …` for Brown–Conrady, `k1, k2, k3, k4` for kb4.
    pub fn coefficient_names(self) -> impl Iterator<Item = &'static str> {
        self.coefficient_slots()
            .iter()
            .map(|&slot| PARAM_NAMES[slot])
    }

    /// The model's name as used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            DistortionModel::Pinhole => "pinhole",
            DistortionModel::Brown5 => "brown5",
            DistortionModel::Brown8 => "brown8",
            DistortionModel::Kb4 => "kb4",
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
            "kb4" | "fisheye" | "equidistant" => Ok(DistortionModel::Kb4),
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
        for slot in idx::K1..N_INTRINSIC {
            self.params[slot] = 0.0;
        }
        for (i, &slot) in model.coefficient_slots().iter().enumerate() {
            self.params[slot] = coefficients.get(i).copied().unwrap_or(0.0);
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
        self.model
            .coefficient_slots()
            .iter()
            .map(|&slot| self.params[slot])
            .collect()
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
        if self.model == DistortionModel::Kb4 {
            return self.kb4_distort(x, y).0;
        }
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
        if self.model == DistortionModel::Kb4 {
            let (d, j, _) = self.kb4_distort(x, y);
            return (d, j);
        }
        let t = self.distortion_terms(x, y);
        (t.distorted, t.j_xy)
    }

    /// The distorted point, its point Jacobian, and the radial terms the coefficients' Jacobian
    /// is built from (shared by both `distort_with_*` functions).
    #[inline]
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
        if self.model == DistortionModel::Kb4 {
            let (d, j_xy, j_k4) = self.kb4_distort(x, y);
            return (d, j_xy, kb4_columns(&j_k4));
        }
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
        if self.model == DistortionModel::Kb4 {
            return self.kb4_project_cam(p);
        }
        if p.z <= 0.0 || !p.z.is_finite() {
            return Err(CameraError::BehindCamera { depth: p.z });
        }
        let d = self.distort(p.x / p.z, p.y / p.z);
        Ok(self.to_pixel(&d))
    }

    /// [`project_cam`](Camera::project_cam) for the fisheye, out of line: inlined, it made the
    /// Brown–Conrady projection that the solver's cost runs on every corner 17 % dearer.
    #[inline(never)]
    fn kb4_project_cam(&self, p: &Vector3<f64>) -> Result<Vector2<f64>, CameraError> {
        Ok(self.to_pixel(&self.kb4_project(p)?.0))
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
        if self.model == DistortionModel::Kb4 {
            return self.kb4_project_cam_with_jacobians(p);
        }
        if p.z <= 0.0 || !p.z.is_finite() {
            return Err(CameraError::BehindCamera { depth: p.z });
        }
        let iz = 1.0 / p.z;
        let x = p.x * iz;
        let y = p.y * iz;
        let (d, j_xy, j_k) = self.distort_with_jacobians(x, y);
        let (uv, j_int, j_pix) = self.pixel_jacobians(&d, &j_k);
        // ∂(x, y)/∂X_cam
        let j_norm = SMatrix::<f64, 2, 3>::new(iz, 0.0, -x * iz, 0.0, iz, -y * iz);
        Ok((uv, j_int, j_pix * j_xy * j_norm))
    }

    /// [`project_cam_with_jacobians`](Camera::project_cam_with_jacobians) for the fisheye (kept out
    /// of the Brown–Conrady path, which the solver runs for every corner at every iteration).
    fn kb4_project_cam_with_jacobians(
        &self,
        p: &Vector3<f64>,
    ) -> Result<(Vector2<f64>, IntrinsicJacobian, PointJacobian), CameraError> {
        let (d, j_point, j_k4) = self.kb4_project(p)?;
        let (uv, j_int, j_pix) = self.pixel_jacobians(&d, &kb4_columns(&j_k4));
        Ok((uv, j_int, j_pix * j_point))
    }

    /// The pixel of distorted normalised `d`, the Jacobian of the pixel in the full intrinsic vector
    /// given `j_k` (∂d/∂ the eight distortion slots), and `∂uv/∂d`.
    #[inline(always)]
    fn pixel_jacobians(
        &self,
        d: &Vector2<f64>,
        j_k: &SMatrix<f64, 2, 8>,
    ) -> (Vector2<f64>, IntrinsicJacobian, Matrix2<f64>) {
        let (fx, fy, s) = (self.fx(), self.fy(), self.skew());
        let uv = self.to_pixel(d);
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
        (uv, j_int, j_pix)
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
        if self.model == DistortionModel::Kb4 {
            // Radial: one bounded Newton solve in θ, exact to the tolerance, whatever the start.
            let (theta, iterations) = self
                .kb4_theta(target.norm())
                .map_err(|(it, res)| not_converged(it, res))?;
            if theta >= 0.5 * std::f64::consts::PI {
                // On or behind the centre plane: a ray, but no point of the normalised plane.
                return Err(not_converged(iterations, f64::NAN));
            }
            let rd = target.norm();
            let p = if rd > 0.0 {
                target * (theta.tan() / rd)
            } else {
                target
            };
            let (_, j) = self.distort_with_point_jacobian(p.x, p.y);
            return Ok((p, j));
        }
        let mut p = if start.x.is_finite() && start.y.is_finite() {
            start
        } else {
            target
        };
        let mut residual = f64::INFINITY;
        for it in 0..UNDISTORT_MAX_ITERATIONS {
            // Brown–Conrady here (the fisheye returned above): its terms directly, inlined into
            // this loop, which the renderer runs for every sample.
            let t = self.distortion_terms(p.x, p.y);
            let (d, j) = (t.distorted, t.j_xy);
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
        if self.model == DistortionModel::Kb4 {
            let rd = xd.hypot(yd);
            let (theta, _) = self.kb4_theta(rd).map_err(|(iterations, residual)| {
                CameraError::UndistortNotConverged {
                    u,
                    v,
                    iterations,
                    residual,
                }
            })?;
            let (sin, cos) = theta.sin_cos();
            return Ok(if rd > 0.0 {
                Vector3::new(sin * xd / rd, sin * yd / rd, cos)
            } else {
                Vector3::z()
            });
        }
        let p = self.undistort(xd, yd)?;
        Ok(Vector3::new(p.x, p.y, 1.0).normalize())
    }
}

/// Kannala–Brandt (`cv::fisheye`) terms. The model is a function of the angle θ between a ray and
/// the optical axis, so it is evaluated on the 3D point, not on `X/Z`: a fisheye sees points at and
/// beyond 90° (`Z ≤ 0`), which have no place on the normalised plane.
impl Camera {
    /// `θ_d(θ)` and `dθ_d/dθ`.
    fn kb4_theta_d(&self, theta: f64) -> (f64, f64) {
        let p = &self.params;
        let (k1, k2, k3, k4) = (p[idx::K1], p[idx::K2], p[idx::K3], p[idx::K4]);
        let t2 = theta * theta;
        let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
        let dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
        (theta * poly, dpoly)
    }

    /// `∂θ_d/∂(k1, k2, k3, k4)`: `θ³, θ⁵, θ⁷, θ⁹`.
    fn kb4_theta_d_coefficients(theta: f64) -> [f64; 4] {
        let t2 = theta * theta;
        let t3 = theta * t2;
        [t3, t3 * t2, t3 * t2 * t2, t3 * t2 * t2 * t2]
    }

    /// Distort on the normalised plane (`Z > 0`): `(x'', y'') = θ_d/r · (x, y)`, `θ = atan r`, with
    /// `∂/∂(x, y)` and `∂/∂(k1..k4)`.
    fn kb4_distort(&self, x: f64, y: f64) -> (Vector2<f64>, Matrix2<f64>, SMatrix<f64, 2, 4>) {
        let r2 = x * x + y * y;
        let r = r2.sqrt();
        let theta = r.atan();
        let (td, dtd) = self.kb4_theta_d(theta);
        let c = Self::kb4_theta_d_coefficients(theta);
        // s = θ_d/r and (ds/dr)/r; below 1e-6 their series s = 1 + (k1 − ⅓) r², (ds/dr)/r = 2(k1 − ⅓).
        let (s, ds_over_r, theta_over_r) = if r < 1e-6 {
            let a = self.params[idx::K1] - 1.0 / 3.0;
            (1.0 + a * r2, 2.0 * a, 1.0 - r2 / 3.0)
        } else {
            let ds = (dtd * r / (1.0 + r2) - td) / r2;
            (td / r, ds / r, theta / r)
        };
        let d = Vector2::new(s * x, s * y);
        let j_xy = Matrix2::new(
            s + ds_over_r * x * x,
            ds_over_r * x * y,
            ds_over_r * x * y,
            s + ds_over_r * y * y,
        );
        let mut j_k = SMatrix::<f64, 2, 4>::zeros();
        for (i, ci) in c.iter().enumerate() {
            // x · θ^(2i+3) / r, written with θ/r so that it stays exact as r → 0.
            let per_r = ci / theta.max(f64::MIN_POSITIVE) * theta_over_r;
            j_k[(0, i)] = x * per_r;
            j_k[(1, i)] = y * per_r;
        }
        (d, j_xy, j_k)
    }

    /// Project a camera-frame point to distorted normalised coordinates with `∂/∂X` and
    /// `∂/∂(k1..k4)`: valid at any angle up to where `θ_d(θ)` stops increasing.
    fn kb4_project(
        &self,
        p: &Vector3<f64>,
    ) -> Result<(Vector2<f64>, PointJacobian, SMatrix<f64, 2, 4>), CameraError> {
        let (a, b, c) = (p.x, p.y, p.z);
        let rho2 = a * a + b * b;
        let rho = rho2.sqrt();
        let n2 = rho2 + c * c;
        if !n2.is_finite() || n2 == 0.0 {
            return Err(CameraError::BehindCamera { depth: c });
        }
        let theta = rho.atan2(c);
        let (td, dtd) = self.kb4_theta_d(theta);
        if dtd <= 0.0 || theta >= std::f64::consts::PI {
            return Err(CameraError::BeyondFieldOfView {
                theta_deg: theta.to_degrees(),
            });
        }
        if rho <= 1e-9 * c.abs() {
            // On the axis (in front): the normalised-plane form is exact and has no 0/0.
            let (d, j_xy, j_k) = self.kb4_distort(a / c, b / c);
            let iz = 1.0 / c;
            let j_norm = SMatrix::<f64, 2, 3>::new(iz, 0.0, -a * iz * iz, 0.0, iz, -b * iz * iz);
            return Ok((d, j_xy * j_norm, j_k));
        }
        let (ua, ub) = (a / rho, b / rho);
        let d = Vector2::new(td * ua, td * ub);
        // ∂θ/∂(a, b, c) = (c a / (ρ n²), c b / (ρ n²), −ρ / n²); ∂(a/ρ)/∂a = b²/ρ³ etc.
        let dth = Vector3::new(c * ua / n2, c * ub / n2, -rho / n2);
        let rho3 = rho2 * rho;
        let du = Vector3::new(b * b / rho3, -a * b / rho3, 0.0);
        let dv = Vector3::new(-a * b / rho3, a * a / rho3, 0.0);
        let row_x = dth * (dtd * ua) + du * td;
        let row_y = dth * (dtd * ub) + dv * td;
        let j_point = PointJacobian::new(row_x.x, row_x.y, row_x.z, row_y.x, row_y.y, row_y.z);
        let coeffs = Self::kb4_theta_d_coefficients(theta);
        let mut j_k = SMatrix::<f64, 2, 4>::zeros();
        for (i, ci) in coeffs.iter().enumerate() {
            j_k[(0, i)] = ci * ua;
            j_k[(1, i)] = ci * ub;
        }
        Ok((d, j_point, j_k))
    }

    /// Invert `θ_d(θ) = rd` by Newton's method bounded to `[0, π)`: the angle and the iterations
    /// taken, or (iterations, residual) when it does not converge or lands where `θ_d` folds.
    fn kb4_theta(&self, rd: f64) -> Result<(f64, usize), (usize, f64)> {
        if !rd.is_finite() {
            return Err((0, f64::NAN));
        }
        if rd == 0.0 {
            return Ok((0.0, 0));
        }
        let pi = std::f64::consts::PI;
        let mut theta = rd.min(0.5 * pi);
        let mut residual = f64::INFINITY;
        for it in 0..UNDISTORT_MAX_ITERATIONS {
            let (td, dtd) = self.kb4_theta_d(theta);
            residual = td - rd;
            if residual.abs() <= UNDISTORT_TOLERANCE * (1.0 + rd) {
                return if dtd > 0.0 {
                    Ok((theta, it))
                } else {
                    Err((it, residual))
                };
            }
            if dtd <= 0.0 {
                return Err((it, residual));
            }
            // A step at most half-way to either end of [0, π): the iteration cannot leave it.
            let step = residual / dtd;
            let limit = 0.5 * if step > 0.0 { theta } else { pi - theta };
            theta -= step.clamp(-limit, limit);
        }
        Err((UNDISTORT_MAX_ITERATIONS, residual))
    }
}

/// Place `∂/∂(k1..k4)` of the KB4 model into the 8 Brown columns `(k1, k2, p1, p2, k3, k4, k5, k6)`
/// by the coefficients' slots (k1, k2, k3, k4 → columns 0, 1, 4, 5).
fn kb4_columns(j: &SMatrix<f64, 2, 4>) -> SMatrix<f64, 2, 8> {
    let mut out = SMatrix::<f64, 2, 8>::zeros();
    for (i, col) in [0usize, 1, 4, 5].into_iter().enumerate() {
        out.set_column(col, &j.column(i));
    }
    out
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
        assert_jacobians_match(&cam, &Vector3::new(0.31, -0.22, 1.4), 0..N_INTRINSIC);
    }

    /// `project_cam_with_jacobians` at `p` against central differences: `∂/∂params[k]` for each `k`
    /// of `params`, and `∂/∂X`.
    fn assert_jacobians_match(cam: &Camera, p: &Vector3<f64>, params: impl Iterator<Item = usize>) {
        let (_, j_int, j_pt) = cam.project_cam_with_jacobians(p).unwrap();
        for k in params {
            let h = 1e-6 * (1.0 + cam.params[k].abs());
            let (mut cp, mut cm) = (cam.clone(), cam.clone());
            cp.params[k] += h;
            cm.params[k] -= h;
            let num = (cp.project_cam(p).unwrap() - cm.project_cam(p).unwrap()) / (2.0 * h);
            for r in 0..2 {
                assert!(
                    (num[r] - j_int[(r, k)]).abs() < 1e-5 * (1.0 + num[r].abs()),
                    "X {p:?} {} row {r}: analytic {} numeric {}",
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
                assert!(
                    (num[r] - j_pt[(r, k)]).abs() < 1e-4 * (1.0 + num[r].abs()),
                    "X {p:?} X{k} row {r}: analytic {} numeric {}",
                    j_pt[(r, k)],
                    num[r]
                );
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

    /// A 1280×960 fisheye whose image circle reaches past 100° off the axis at the corners.
    fn fisheye() -> Camera {
        Camera::pinhole([1280, 960], 352.0, 351.0, 641.7, 478.2)
            .with_distortion(DistortionModel::Kb4, &[0.021, -0.006, 0.0011, -0.00012])
    }

    /// A camera-frame point at angle `theta` off the axis, azimuth `phi`, distance `d`.
    fn at_angle(theta: f64, phi: f64, d: f64) -> Vector3<f64> {
        Vector3::new(
            d * theta.sin() * phi.cos(),
            d * theta.sin() * phi.sin(),
            d * theta.cos(),
        )
    }

    #[test]
    fn kb4_coefficients_round_trip_in_opencv_order() {
        let c = fisheye();
        assert_eq!(
            c.distortion_coefficients(),
            vec![0.021, -0.006, 0.0011, -0.00012]
        );
        assert_eq!(c.params[idx::K3], 0.0011);
        assert_eq!(c.params[idx::K4], -0.00012);
        assert_eq!(c.params[idx::P1], 0.0);
        assert_eq!(
            "fisheye".parse::<DistortionModel>(),
            Ok(DistortionModel::Kb4)
        );
    }

    #[test]
    fn kb4_matches_opencv_fisheye_formula() {
        // cv::fisheye::projectPoints, evaluated by hand: X = (0.3, -0.4, 0.5), a = 0.3, b = -0.4,
        // r = 0.5/0.5 = 1 → θ = atan 1 = π/4, θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸),
        // x' = θ_d/r · a/z, u = fx x' + cx.
        let c = Camera::pinhole([640, 480], 300.0, 310.0, 320.0, 240.0)
            .with_distortion(DistortionModel::Kb4, &[0.1, -0.02, 0.003, -0.0004]);
        let th = std::f64::consts::FRAC_PI_4;
        let t2 = th * th;
        let td = th * (1.0 + 0.1 * t2 - 0.02 * t2 * t2 + 0.003 * t2.powi(3) - 0.0004 * t2.powi(4));
        let uv = c.project_cam(&Vector3::new(0.3, -0.4, 0.5)).unwrap();
        assert!((uv.x - (320.0 + 300.0 * td * 0.6)).abs() < 1e-12);
        assert!((uv.y - (240.0 - 310.0 * td * 0.8)).abs() < 1e-12);
    }

    #[test]
    fn kb4_jacobians_match_central_differences_to_beyond_90_degrees() {
        let mut cam = fisheye();
        cam.params[idx::SKEW] = 0.4;
        for (theta_deg, phi) in [
            (0.5, 0.3),
            (20.0, 1.1),
            (60.0, -2.0),
            (89.0, 2.5),
            (95.0, 0.7),
            (110.0, -0.4),
        ] {
            let p = at_angle(f64::to_radians(theta_deg), phi, 1.7);
            let slots = cam.model.coefficient_slots().to_vec();
            assert_jacobians_match(&cam, &p, slots.into_iter().chain(0..5));
            // The normalised-plane form (Z > 0) agrees with the 3D form, Jacobians included.
            if p.z > 0.0 {
                let (x, y) = (p.x / p.z, p.y / p.z);
                let (d, j_xy, j_k) = cam.distort_with_jacobians(x, y);
                let (d3, _, j_k3) = cam.kb4_project(&p).unwrap();
                assert!((d - d3).norm() < 1e-13);
                for (col, i) in [(0, 0), (1, 1), (4, 2), (5, 3)] {
                    assert!((j_k.column(col) - j_k3.column(i)).norm() < 1e-12);
                }
                let h = 1e-7;
                let num_x = (cam.distort(x + h, y) - cam.distort(x - h, y)) / (2.0 * h);
                assert!((num_x - j_xy.column(0)).norm() < 1e-6 * (1.0 + num_x.norm()));
            }
        }
    }

    #[test]
    fn kb4_behind_the_fold_is_beyond_the_field_of_view() {
        // θ_d = θ(1 − 0.2 θ²) stops increasing at θ = 1/√0.6 ≈ 74°.
        let c = Camera::pinhole([640, 480], 300.0, 300.0, 320.0, 240.0)
            .with_distortion(DistortionModel::Kb4, &[-0.2]);
        assert!(c.project_cam(&at_angle(1.0, 0.2, 1.0)).is_ok());
        assert!(matches!(
            c.project_cam(&at_angle(1.4, 0.2, 1.0)),
            Err(CameraError::BeyondFieldOfView { .. })
        ));
        // θ_d peaks at 0.861: a larger distorted radius has no ray.
        assert!(matches!(
            c.unproject(320.0 + 300.0 * 0.9, 240.0),
            Err(CameraError::UndistortNotConverged { .. })
        ));
        assert!(matches!(
            fisheye().project_cam(&Vector3::new(0.0, 0.0, -1.0)),
            Err(CameraError::BeyondFieldOfView { .. })
        ));
    }

    proptest::proptest! {
        /// Project then unproject returns the ray to 1e-9 over the whole field of view (θ up to
        /// 110°, every azimuth), and unproject then project returns the pixel to 1e-9 px.
        #[test]
        fn kb4_round_trip_over_the_field_of_view(theta in 0.0f64..1.92, phi in -3.15f64..3.15, d in 0.05f64..20.0) {
            let cam = fisheye();
            let p = at_angle(theta, phi, d);
            let uv = cam.project_cam(&p).unwrap();
            let ray = cam.unproject(uv.x, uv.y).unwrap();
            proptest::prop_assert!((ray - p.normalize()).norm() < 1e-9, "θ {theta}: {ray} vs {}", p.normalize());
            let back = cam.project_cam(&ray).unwrap();
            proptest::prop_assert!((back - uv).norm() < 1e-9);
            if theta < 1.5 {
                let yd = (uv.y - cam.cy()) / cam.fy();
                let xd = (uv.x - cam.cx() - cam.skew() * yd) / cam.fx();
                let n = cam.undistort(xd, yd).unwrap();
                proptest::prop_assert!((n - Vector2::new(p.x / p.z, p.y / p.z)).norm() < 1e-9 * (1.0 + n.norm()));
            }
        }
    }
}
