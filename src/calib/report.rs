//! The serialisable form of a [`Calibration`]: what `cubecal solve --json` prints and profiles store.
//! Field names follow OpenCV's vocabulary (`camera_matrix`, `distortion` coefficients in OpenCV order).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::Calibration;
use super::init::InitMethod;

/// Distortion model and OpenCV-ordered coefficients.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DistortionReport {
    pub model: String,
    pub coefficients: Vec<f64>,
}

/// Per-view result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewReport {
    pub name: String,
    /// `cam_from_rig` rotation, 3×3 row-major.
    pub rotation: [[f64; 3]; 3],
    /// `cam_from_rig` translation (mm).
    pub translation: [f64; 3],
    /// OpenCV `rvec` (axis-angle, radians).
    pub rvec: [f64; 3],
    pub rms_px: f64,
    pub n_points: usize,
    /// Indices of the view's points rejected as outliers.
    pub outliers: Vec<usize>,
    /// Standard deviation of the rotation about the camera axes (degrees).
    pub rotation_std_deg: [f64; 3],
    /// Standard deviation of the translation (mm).
    pub translation_std: [f64; 3],
}

/// The full result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    pub image_size: [u32; 2],
    /// `K`, 3×3 row-major.
    pub camera_matrix: [[f64; 3]; 3],
    pub distortion: DistortionReport,
    /// Standard deviation of each estimated intrinsic parameter, by name.
    pub std_dev: BTreeMap<String, f64>,
    /// Names of the estimated intrinsic parameters, in the order of `covariance`.
    #[serde(default)]
    pub free_params: Vec<String>,
    /// Covariance of the estimated intrinsic parameters (row-major, `free_params` order), scaled by
    /// `sigma_px²` (by `noise_scale²` when the corners are weighted by their covariances).
    #[serde(default)]
    pub covariance: Vec<Vec<f64>>,
    /// RMS of residual components `√(Σr²/2n)` (px).
    pub rms_px: f64,
    /// OpenCV's reprojection error `√(Σ‖r‖²/n)` (px).
    pub rms_reprojection_px: f64,
    /// Estimated corner noise per coordinate `√(Σr²/(2n − p))` (px).
    pub sigma_px: f64,
    /// With the corners weighted by their own covariances: the whitened residuals' `σ̂`, the corners'
    /// scatter over what their covariances claim (≈ 1 when the detector is honest).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_scale: Option<f64>,
    pub n_points: usize,
    pub n_params: usize,
    pub views: Vec<ViewReport>,
    pub iterations: usize,
    pub termination: String,
    pub converged: bool,
    pub init_method: InitMethod,
}

impl From<&Calibration> for CalibrationReport {
    fn from(c: &Calibration) -> Self {
        let k = c.camera.k_matrix();
        let rows = |m: &nalgebra::Matrix3<f64>| {
            [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ]
        };
        CalibrationReport {
            image_size: c.camera.image_size,
            camera_matrix: rows(&k),
            distortion: DistortionReport {
                model: c.camera.model.name().to_string(),
                coefficients: c.camera.distortion_coefficients(),
            },
            std_dev: c
                .std_dev_by_name()
                .into_iter()
                .map(|(k, v)| (k.to_string(), v))
                .collect(),
            free_params: c.free_params.iter().map(|s| s.to_string()).collect(),
            covariance: (0..c.covariance.nrows())
                .map(|i| c.covariance.row(i).iter().copied().collect())
                .collect(),
            rms_px: c.rms_px,
            rms_reprojection_px: c.rms_reprojection_px,
            sigma_px: c.sigma_px,
            noise_scale: c.noise_scale,
            n_points: c.n_points,
            n_params: c.n_params,
            views: c
                .views
                .iter()
                .map(|v| ViewReport {
                    name: v.name.clone(),
                    rotation: rows(v.cam_from_rig.rotation.matrix()),
                    translation: v.cam_from_rig.translation.into(),
                    rvec: v.cam_from_rig.rvec().into(),
                    rms_px: v.rms_px,
                    n_points: v.n_points,
                    outliers: v.outliers.clone(),
                    rotation_std_deg: v.rotation_std_rad.map(f64::to_degrees),
                    translation_std: v.translation_std,
                })
                .collect(),
            iterations: c.iterations,
            termination: c.termination.as_str().to_string(),
            converged: c.termination.is_converged(),
            init_method: c.init_method,
        }
    }
}
