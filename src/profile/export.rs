//! Exports of a profile's intrinsics in the formats other tools read.
//!
//! | format | file | pinhole / brown5 / brown8 | kb4 (Kannala–Brandt, `cv::fisheye`) | pixel convention |
//! |---|---|---|---|---|
//! | OpenCV `FileStorage` YAML ([`opencv_yaml`]) | as OpenCV's calibration samples write it: `image_width`, `image_height`, `camera_matrix` and `distortion_coefficients` as `!!opencv-matrix` | 5 or 8 coefficients (`cv::projectPoints`) | 4 coefficients and `fisheye_model: 1`, the key OpenCV's own calibration tutorial writes for its fisheye flag (`cv::fisheye::projectPoints`) | pixel centres at integers (ours) |
//! | ROS `camera_info` YAML ([`ros_camera_info_yaml`]) | `camera_calibration_parsers`' layout | `plumb_bob` (5), `rational_polynomial` (8) | `equidistant`, D = (k1, k2, k3, k4) as `image_geometry` hands it to `cv::fisheye` | same as OpenCV |
//! | mrcal `.cameramodel` ([`mrcal_cameramodel`]) | Python-literal dict, identity extrinsics | `LENSMODEL_PINHOLE`/`OPENCV5`/`OPENCV8` | refused, unless k3 = k4 = 0: see below | same as OpenCV |
//! | COLMAP `cameras.txt` ([`colmap_cameras_txt`]) | one camera line | `PINHOLE`/`OPENCV`/`FULL_OPENCV` | `OPENCV_FISHEYE` (fx, fy, cx, cy, k1..k4) | centre of the top-left pixel at (0.5, 0.5): `cx`, `cy` shifted by +0.5 |
//! | Kalibr camchain YAML ([`kalibr_camchain_yaml`]) | one camera, `cam0`, `camera_model: pinhole`, `intrinsics: [fu, fv, pu, pv]`, `resolution` | `none` (pinhole); `radtan` (k1, k2, p1, p2) when every coefficient past p2 is 0, else refused | `equidistant` (k1..k4) | same as OpenCV |
//!
//! None of these formats has a skew term (OpenCV's `projectPoints` ignores `K[0][1]`), so a profile
//! with a non-zero skew is refused with [`ExportError::Unsupported`] rather than exported wrongly; so
//! is any model a format cannot express exactly. Numbers are written with the shortest representation
//! that reads back to the same `f64`, in a form every one of these parsers (and YAML 1.1) takes as a
//! float (`1.5`, `-2.0e-7`).
//!
//! **kb4 in mrcal.** mrcal (its lens-model list and docs up to its master of 2026-06-30) has no
//! Kannala–Brandt model: its to-do list says ROS's `equidistant` "mrcal does not support this today",
//! and its reader refuses an `equidistant` camera_info. Its `OPENCV*` models are polynomials in
//! `tan θ`, `STEREOGRAPHIC`, `LONLAT` and `LATLON` have no coefficients, and the splined model is a
//! fit. The one exact match is partial: `LENSMODEL_CAHVORE` with linearity 0, its axis on `z`
//! (α = β = 0) and `E = 0` (central) projects to `θ (1 + r0 + r1 θ² + r2 θ⁴)`, which is kb4 with
//! `r0 = 0, r1 = k1, r2 = k2` when `k3 = k4 = 0`. Such a profile is exported so; any other kb4 profile
//! is refused, naming the terms mrcal lacks. (`tests/profile.rs` checks both against `mrcal.project`,
//! which projects that CAHVORE past 90° although mrcal's metadata says it does not project behind the
//! camera; mrcal cannot solve for CAHVORE, having no gradients for it.)
//!
//! **Kalibr.** The camchain holds only what a camera calibration knows: `T_cam_imu` is left out (it is
//! what `kalibr_calibrate_imu_camera` computes and writes into its own camchain-imucam file, which is
//! where Kalibr's exporters read it; an identity here would claim the IMU's axes are the camera's), and
//! `rostopic`, which Kalibr's IMU–camera calibration and validator read, is the placeholder
//! `/cam0/image_raw` with a comment to set it. Kalibr's projection divides by `z`, so it sees the
//! fisheye to 90° off the axis, as `cv::fisheye` does.
//!
//! The identity is not written into the OpenCV, mrcal, COLMAP or Kalibr files, and only as a sanitised
//! `camera_name` into the ROS file: USB serial strings are untrusted, and none of these parsers needs it.

use super::{Profile, intrinsic_values};
use crate::camera::DistortionModel;

/// Errors from exports.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExportError {
    /// The profile's model cannot be expressed in the format.
    #[error("cannot export to {format}: {reason}")]
    Unsupported {
        format: &'static str,
        reason: String,
    },
}

impl ExportError {
    pub fn exit_code(&self) -> u8 {
        crate::exit::BAD_INPUT
    }
}

/// The profile's software version reduced to `[A-Za-z0-9.+-]`, for a comment line of a file another
/// tool parses (the version string comes from a file that may have been edited).
fn comment_safe_version(profile: &Profile) -> String {
    (profile.software_version.chars())
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '+'))
        .collect()
}

/// The export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Opencv,
    Ros,
    Mrcal,
    Colmap,
    Kalibr,
}

impl Format {
    pub const ALL: [Format; 5] = [
        Format::Opencv,
        Format::Ros,
        Format::Mrcal,
        Format::Colmap,
        Format::Kalibr,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Format::Opencv => "opencv",
            Format::Ros => "ros",
            Format::Mrcal => "mrcal",
            Format::Colmap => "colmap",
            Format::Kalibr => "kalibr",
        }
    }

    /// The usual file name extension.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Opencv | Format::Ros | Format::Kalibr => "yaml",
            Format::Mrcal => "cameramodel",
            Format::Colmap => "txt",
        }
    }

    /// Render `profile` in this format.
    pub fn render(self, profile: &Profile) -> Result<String, ExportError> {
        match self {
            Format::Opencv => opencv_yaml(profile),
            Format::Ros => ros_camera_info_yaml(profile),
            Format::Mrcal => mrcal_cameramodel(profile),
            Format::Colmap => colmap_cameras_txt(profile),
            Format::Kalibr => kalibr_camchain_yaml(profile),
        }
    }
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Format::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| {
                format!("unknown export format '{s}' (opencv, ros, mrcal, colmap, kalibr)")
            })
    }
}

/// Shortest round-tripping representation, always with a `.` and a signed exponent when there is
/// one (`1280.0`, `-3.5e-7`, `1.0e+20`).
pub fn fmt_f64(v: f64) -> String {
    let s = format!("{v:?}");
    match s.split_once('e') {
        None => s,
        Some((mantissa, exp)) => {
            let mantissa = if mantissa.contains('.') {
                mantissa.to_string()
            } else {
                format!("{mantissa}.0")
            };
            let exp = if exp.starts_with('-') {
                exp.to_string()
            } else {
                format!("+{exp}")
            };
            format!("{mantissa}e{exp}")
        }
    }
}

fn list(values: &[f64]) -> String {
    values
        .iter()
        .map(|&v| fmt_f64(v))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The parts every format needs, checked: `fx, fy, cx, cy`, the distortion model and its
/// coefficients, the image size.
struct Intrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    model: DistortionModel,
    /// As stored, in the model's order: as many as the model has (0, 5, 8 or 4).
    coefficients: Vec<f64>,
    width: u32,
    height: u32,
}

fn intrinsics(profile: &Profile, format: &'static str) -> Result<Intrinsics, ExportError> {
    let c = &profile.calibration;
    let unsupported = |reason: String| ExportError::Unsupported { format, reason };
    let k = &c.camera_matrix;
    if k[0][1] != 0.0 {
        return Err(unsupported(format!(
            "the camera matrix has skew {} and the format has no skew term (calibrate without --estimate-skew)",
            k[0][1]
        )));
    }
    if k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        return Err(unsupported(format!(
            "the camera matrix {k:?} is not upper triangular with K[2] = (0, 0, 1)"
        )));
    }
    let values = intrinsic_values(c);
    if let Some((name, v)) = values.iter().find(|(_, v)| !v.is_finite()) {
        return Err(unsupported(format!("{name} is not finite ({v})")));
    }
    let model: DistortionModel = c
        .distortion
        .model
        .parse()
        .map_err(|e: crate::camera::CameraError| unsupported(e.to_string()))?;
    let n = c.distortion.coefficients.len();
    if n != model.n_coefficients() {
        return Err(unsupported(format!(
            "{n} distortion coefficients for the {} model, which has {}",
            model.name(),
            model.n_coefficients()
        )));
    }
    Ok(Intrinsics {
        fx: k[0][0],
        fy: k[1][1],
        cx: k[0][2],
        cy: k[1][2],
        model,
        coefficients: c.distortion.coefficients.clone(),
        width: c.image_size[0],
        height: c.image_size[1],
    })
}

impl Intrinsics {
    /// Coefficients for formats that carry at least OpenCV's 5 for a Brown–Conrady or pinhole lens
    /// (zeros for a pinhole), and kb4's 4 as they are.
    fn at_least_five(&self) -> Vec<f64> {
        let mut d = self.coefficients.clone();
        if self.model != DistortionModel::Kb4 && d.len() < 5 {
            d.resize(5, 0.0);
        }
        d
    }
}

fn opencv_matrix(name: &str, rows: usize, cols: usize, data: &[f64]) -> String {
    format!(
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
        list(data)
    )
}

/// OpenCV `FileStorage` YAML, as OpenCV's camera calibration samples write it. A kb4 profile carries
/// its 4 coefficients for `cv::fisheye` and `fisheye_model: 1`, the flag OpenCV's calibration tutorial
/// (`camera_calibration.cpp`) writes beside them; a reader that does not know the key never looks it
/// up, and an absent key reads as 0 in that tutorial's reader.
pub fn opencv_yaml(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "OpenCV YAML")?;
    let d = i.at_least_five();
    let mut s = String::from("%YAML:1.0\n---\n");
    // `created` was validated as RFC 3339 (digits, '-', ':', 'T', '.', 'Z'): safe inside quotes.
    s += &format!(
        "calibration_time: \"{}\"\n",
        profile.created.escape_default()
    );
    s += &format!("image_width: {}\nimage_height: {}\n", i.width, i.height);
    if i.model == DistortionModel::Kb4 {
        s += "fisheye_model: 1\n";
    }
    s += &opencv_matrix(
        "camera_matrix",
        3,
        3,
        &[i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0],
    );
    s += &opencv_matrix("distortion_coefficients", d.len(), 1, &d);
    s += &format!(
        "avg_reprojection_error: {}\n",
        fmt_f64(profile.calibration.rms_reprojection_px)
    );
    Ok(s)
}

/// A ROS camera name from an identity: `[A-Za-z0-9_]` only, starting with a letter.
fn ros_camera_name(identity: &str) -> String {
    let name: String = identity
        .chars()
        .take(64)
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if name.starts_with(|c: char| c.is_ascii_alphabetic()) {
        name
    } else {
        format!("camera_{name}")
    }
}

fn ros_matrix(name: &str, rows: usize, cols: usize, data: &[f64]) -> String {
    format!(
        "{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{}]\n",
        list(data)
    )
}

/// ROS `camera_info` YAML (`camera_calibration_parsers`' layout); the projection matrix is `K` with a
/// zero fourth column and the rectification the identity (a monocular camera). kb4 is ROS's
/// `equidistant` with `D = (k1, k2, k3, k4)`, which `image_geometry` passes to `cv::fisheye`.
pub fn ros_camera_info_yaml(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "ROS camera_info")?;
    let d = i.at_least_five();
    let model = match i.model {
        DistortionModel::Kb4 => "equidistant",
        DistortionModel::Brown8 => "rational_polynomial",
        DistortionModel::Pinhole | DistortionModel::Brown5 => "plumb_bob",
    };
    let mut s = format!(
        "image_width: {}\nimage_height: {}\ncamera_name: {}\n",
        i.width,
        i.height,
        ros_camera_name(&profile.identity.id)
    );
    s += &ros_matrix(
        "camera_matrix",
        3,
        3,
        &[i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0],
    );
    s += &format!("distortion_model: {model}\n");
    s += &ros_matrix("distortion_coefficients", 1, d.len(), &d);
    s += &ros_matrix(
        "rectification_matrix",
        3,
        3,
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    );
    s += &ros_matrix(
        "projection_matrix",
        3,
        4,
        &[
            i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
    );
    Ok(s)
}

/// mrcal `.cameramodel` with identity extrinsics (`rt_cam_ref` = 0). A kb4 profile is exported only
/// when `k3 = k4 = 0`, as the `LENSMODEL_CAHVORE` that projects exactly like it (see the module docs),
/// and refused otherwise.
pub fn mrcal_cameramodel(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "mrcal")?;
    let (model, mut params) = match i.model {
        DistortionModel::Pinhole => ("LENSMODEL_PINHOLE", vec![]),
        DistortionModel::Brown5 => ("LENSMODEL_OPENCV5", i.coefficients.clone()),
        DistortionModel::Brown8 => ("LENSMODEL_OPENCV8", i.coefficients.clone()),
        DistortionModel::Kb4 => match i.coefficients[..] {
            // α, β (axis on z); R = (r0, r1, r2); E = 0 (central)
            [k1, k2, k3, k4] if k3 == 0.0 && k4 == 0.0 => (
                "LENSMODEL_CAHVORE_linearity=0.00",
                vec![0.0, 0.0, 0.0, k1, k2, 0.0, 0.0, 0.0],
            ),
            _ => {
                return Err(ExportError::Unsupported {
                    format: "mrcal",
                    // one line under the CLI's 240 characters: the figures to 3 digits
                    reason: format!(
                        "the kb4 lens (Kannala–Brandt, cv::fisheye) has k3 = {:.2e}, k4 = {:.2e}; \
                         mrcal has no model with θ⁷, θ⁹ terms (CAHVORE stops at θ⁵), and no \
                         approximation is written: use opencv, ros, colmap or kalibr",
                        i.coefficients.get(2).copied().unwrap_or(f64::NAN),
                        i.coefficients.get(3).copied().unwrap_or(f64::NAN),
                    ),
                });
            }
        },
    };
    params.splice(0..0, [i.fx, i.fy, i.cx, i.cy]);
    Ok(format!(
        "# generated by cubecal {} on {}\n{{\n    'lensmodel': '{model}',\n    'intrinsics': [ {} ],\n    'extrinsics': [ 0.0, 0.0, 0.0, 0.0, 0.0, 0.0 ],\n    'imagersize': [ {}, {} ],\n}}\n",
        comment_safe_version(profile),
        profile.created.escape_default(),
        list(&params),
        i.width,
        i.height
    ))
}

/// A COLMAP `cameras.txt` with camera id 1: `PINHOLE`, `OPENCV` (`k3` = 0), `FULL_OPENCV` or, for
/// kb4, `OPENCV_FISHEYE` (`fx, fy, cx, cy, k1, k2, k3, k4`), with the principal point moved to
/// COLMAP's convention (+0.5 px).
pub fn colmap_cameras_txt(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "COLMAP")?;
    let (cx, cy) = (i.cx + 0.5, i.cy + 0.5);
    let d = &i.coefficients;
    let (model, mut params) = match i.model {
        DistortionModel::Pinhole => ("PINHOLE", vec![]),
        DistortionModel::Kb4 => ("OPENCV_FISHEYE", d.clone()),
        DistortionModel::Brown5 if d.get(4) == Some(&0.0) => ("OPENCV", d[..4].to_vec()),
        DistortionModel::Brown5 | DistortionModel::Brown8 => {
            let mut full = d.clone();
            full.resize(8, 0.0);
            ("FULL_OPENCV", full)
        }
    };
    params.splice(0..0, [i.fx, i.fy, cx, cy]);
    let params: Vec<String> = params.iter().map(|&v| fmt_f64(v)).collect();
    Ok(format!(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n1 {model} {} {} {}\n",
        i.width,
        i.height,
        params.join(" ")
    ))
}

/// A Kalibr camera chain (`camchain.yaml`) of one camera, `cam0`, as Kalibr's `ConfigReader` reads it:
/// `camera_model: pinhole`, `intrinsics: [fu, fv, pu, pv]`, `distortion_model` with its
/// `distortion_coeffs` (`equidistant` for kb4; `radtan` = k1, k2, p1, p2 for a Brown–Conrady lens
/// whose further coefficients are all 0; `none` for a pinhole), `resolution: [w, h]`, and `rostopic`
/// as a placeholder (see the module docs for what is left out and why).
pub fn kalibr_camchain_yaml(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "Kalibr")?;
    let unsupported = |reason: String| ExportError::Unsupported {
        format: "Kalibr",
        reason,
    };
    let (model, coeffs) = match i.model {
        DistortionModel::Pinhole => ("none", vec![]),
        DistortionModel::Kb4 => ("equidistant", i.coefficients.clone()),
        DistortionModel::Brown5 | DistortionModel::Brown8 => {
            let beyond: Vec<String> = i
                .model
                .coefficient_names()
                .zip(&i.coefficients)
                .skip(4)
                .filter(|(_, v)| **v != 0.0)
                .map(|(name, v)| format!("{name} = {v:.2e}"))
                .collect();
            if !beyond.is_empty() {
                // one line under the CLI's 240 characters: the figures to 3 digits
                return Err(unsupported(format!(
                    "the {} lens has {}; Kalibr's radtan has only k1, k2, p1, p2, and no \
                     approximation is written (for Kalibr: --model brown5 --fix k3)",
                    i.model.name(),
                    beyond.join(", ")
                )));
            }
            ("radtan", i.coefficients[..4].to_vec())
        }
    };
    if i.cx < 0.0 || i.cy < 0.0 {
        return Err(unsupported(format!(
            "Kalibr refuses a principal point below 0 (pu {}, pv {})",
            fmt_f64(i.cx),
            fmt_f64(i.cy)
        )));
    }
    Ok(format!(
        "# Kalibr camera chain (camchain.yaml) written by cubecal {} from the profile of {}\n\
         # rostopic is a placeholder: set it to the topic of this camera's images\n\
         cam0:\n  camera_model: pinhole\n  intrinsics: [{}]\n  distortion_model: {model}\n  \
         distortion_coeffs: [{}]\n  resolution: [{}, {}]\n  rostopic: /cam0/image_raw\n",
        comment_safe_version(profile),
        profile.created.escape_default(),
        list(&[i.fx, i.fy, i.cx, i.cy]),
        list(&coeffs),
        i.width,
        i.height
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floats_read_back_exactly_and_look_like_floats() {
        for v in [
            0.0,
            -0.0,
            1280.0,
            0.1,
            -3.5e-7,
            1e20,
            1.0 / 3.0,
            f64::MIN_POSITIVE,
            123456.789e-300,
        ] {
            let s = fmt_f64(v);
            assert!(s.contains('.'), "{s}");
            if let Some((_, e)) = s.split_once('e') {
                assert!(e.starts_with(['+', '-']), "{s}");
            }
            let back: f64 = s.parse().unwrap_or(f64::NAN);
            assert_eq!(back.to_bits(), v.to_bits(), "{s}");
        }
    }

    #[test]
    fn ros_names_are_plain() {
        assert_eq!(ros_camera_name("usb:046d:0825:AB"), "usb_046d_0825_AB");
        assert_eq!(ros_camera_name("../\n"), "camera_____");
        assert_eq!(ros_camera_name(""), "camera_");
    }
}
