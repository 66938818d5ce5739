//! Which estimated parameters the data leave undetermined: the check behind `cubecal solve`'s warning
//! and the station's verdict.
//!
//! A parameter is *undetermined* when its standard deviation exceeds its own magnitude (the data cannot
//! even tell its sign) **and** one standard deviation of it moves the projection of some point of the
//! image border by more than [`UNDETERMINED_EFFECT_PX`]. The second condition keeps parameters whose
//! true value is near zero (`p1`, `p2`, `skew`, a small `k3`) and that the data pin down to well below a
//! pixel's effect from being flagged just because `σ > |value|`: there the calibration is fine.
//!
//! The effect of parameter `k` is `σ_k · max ‖∂π/∂θ_k‖` over the four image corners and the four edge
//! midpoints, each taken on the ray through that pixel under the undistorted pinhole `K` (the profile
//! is used over the whole image, so the border is where an undetermined term does harm).

use nalgebra::Vector3;
use serde::Serialize;

use super::Calibration;
use crate::camera::{N_INTRINSIC, PARAM_NAMES};

/// Effect (px at the image border, for one standard deviation) above which a parameter whose σ
/// exceeds its value is reported as undetermined.
pub const UNDETERMINED_EFFECT_PX: f64 = 1.0;

/// An estimated intrinsic parameter the data do not determine.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct UndeterminedParam {
    /// The parameter's name ([`PARAM_NAMES`]: `fx` … `k6`).
    pub name: &'static str,
    pub value: f64,
    pub std_dev: f64,
    /// How far one standard deviation moves the projection of the image border, at most (px).
    pub effect_px: f64,
}

/// The estimated parameters of `cal` whose standard deviation exceeds their magnitude and moves the
/// image border by more than [`UNDETERMINED_EFFECT_PX`] (see the module docs), in parameter order.
pub fn undetermined_parameters(cal: &Calibration) -> Vec<UndeterminedParam> {
    (0..N_INTRINSIC)
        .filter_map(|k| unresolved(cal, k, 1.0))
        .collect()
}

/// How many standard deviations from zero a higher-order distortion term must lie for the station to
/// keep it (see [`insignificant_at_border`]).
pub const SIGNIFICANCE_SIGMAS: f64 = 2.0;

/// Parameter `k` of `cal` when it is estimated, its value lies within [`SIGNIFICANCE_SIGMAS`] standard
/// deviations of zero (the data cannot tell it from zero) **and** one standard deviation moves the image
/// border by more than [`UNDETERMINED_EFFECT_PX`]. Such a term only adds noise where the profile is used
/// beyond the observed corners: the station fixes `k3` at 0 when this holds. It is wider than
/// [`undetermined_parameters`] (σ > |value|): a k3 of 2.1 ± 2.0 fitted to corners in the middle third of
/// the image moves the image corners by hundreds of pixels per σ and is not evidence of a k3.
pub fn insignificant_at_border(cal: &Calibration, k: usize) -> Option<UndeterminedParam> {
    unresolved(cal, k, SIGNIFICANCE_SIGMAS)
}

/// Parameter `k` when estimated, within `sigmas` σ of zero and costing more than
/// [`UNDETERMINED_EFFECT_PX`] at the image border per σ.
fn unresolved(cal: &Calibration, k: usize, sigmas: f64) -> Option<UndeterminedParam> {
    if k >= N_INTRINSIC || !cal.estimated[k] {
        return None;
    }
    let value = cal.camera.params[k];
    let std_dev = cal.std_dev[k];
    let effect_px = std_dev * border_gain(cal)?[k];
    (sigmas * std_dev > value.abs() && effect_px > UNDETERMINED_EFFECT_PX).then_some(
        UndeterminedParam {
            name: PARAM_NAMES[k],
            value,
            std_dev,
            effect_px,
        },
    )
}

/// `max ‖∂π/∂θ_k‖` over the image corners and edge midpoints (see the module docs), per parameter;
/// `None` when K is singular.
fn border_gain(cal: &Calibration) -> Option<[f64; N_INTRINSIC]> {
    border_gain_of(&cal.camera)
}

/// How far (px) a unit change of each intrinsic parameter of `cam` moves the projection of the image
/// border at most (the image corners and edge midpoints, as in the module docs); `None` when K is
/// singular. The station's planner weighs distortion terms by it.
pub fn border_gain_of(cam: &crate::camera::Camera) -> Option<[f64; N_INTRINSIC]> {
    let [w, h] = cam.image_size;
    let (xmax, ymax) = (f64::from(w) - 0.5, f64::from(h) - 0.5);
    let (xmid, ymid) = (0.5 * (xmax - 0.5), 0.5 * (ymax - 0.5));
    let border = [
        (-0.5, -0.5),
        (xmax, -0.5),
        (-0.5, ymax),
        (xmax, ymax),
        (xmid, -0.5),
        (xmid, ymax),
        (-0.5, ymid),
        (xmax, ymid),
    ];
    let k_inv = cam.k_matrix().try_inverse()?;
    let mut gain = [0.0f64; N_INTRINSIC];
    for (u, v) in border {
        // A fisheye's border lies far beyond the pinhole ray of its pixel (θ, not tan θ): its own.
        let ray = match cam.model {
            crate::camera::DistortionModel::Kb4 => cam.unproject(u, v).ok(),
            _ => None,
        }
        .unwrap_or_else(|| k_inv * Vector3::new(u, v, 1.0));
        if let Ok((_, j, _)) = cam.project_cam_with_jacobians(&ray) {
            for (k, g) in gain.iter_mut().enumerate() {
                *g = g.max(j.column(k).norm());
            }
        }
    }
    Some(gain)
}
