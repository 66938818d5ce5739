//! Exports of a profile's intrinsics in the formats other tools read.
//!
//! | format | file | model names | pixel convention |
//! |---|---|---|---|
//! | OpenCV `FileStorage` YAML ([`opencv_yaml`]) | as OpenCV's `calibration.cpp` sample writes it: `image_width`, `image_height`, `camera_matrix` and `distortion_coefficients` as `!!opencv-matrix` | 5 or 8 coefficients | pixel centres at integers (ours) |
//! | ROS `camera_info` YAML ([`ros_camera_info_yaml`]) | `camera_calibration_parsers`' layout | `plumb_bob` (5), `rational_polynomial` (8) | same as OpenCV |
//! | mrcal `.cameramodel` ([`mrcal_cameramodel`]) | Python-literal dict, identity extrinsics | `LENSMODEL_OPENCV5`/`OPENCV8`/`PINHOLE` | same as OpenCV |
//! | COLMAP `cameras.txt` ([`colmap_cameras_txt`]) | one camera line | `PINHOLE`/`OPENCV`/`FULL_OPENCV` | centre of the top-left pixel at (0.5, 0.5): `cx`, `cy` shifted by +0.5 |
//!
//! None of these formats has a skew term (OpenCV's `projectPoints` ignores `K[0][1]`), so a profile
//! with a non-zero skew is refused with [`ExportError::Unsupported`] rather than exported wrongly.
//! Numbers are written with the shortest representation that reads back to the same `f64`, in a form
//! every one of these parsers (and YAML 1.1) takes as a float (`1.5`, `-2.0e-7`).
//!
//! The identity is not written into the OpenCV, mrcal or COLMAP files, and only as a sanitised
//! `camera_name` into the ROS file: USB serial strings are untrusted, and none of these parsers needs it.

use super::{Profile, intrinsic_values};

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

/// The export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Opencv,
    Ros,
    Mrcal,
    Colmap,
}

impl Format {
    pub const ALL: [Format; 4] = [Format::Opencv, Format::Ros, Format::Mrcal, Format::Colmap];

    pub fn name(self) -> &'static str {
        match self {
            Format::Opencv => "opencv",
            Format::Ros => "ros",
            Format::Mrcal => "mrcal",
            Format::Colmap => "colmap",
        }
    }

    /// The usual file name extension.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Opencv | Format::Ros => "yaml",
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
        }
    }
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Format::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| format!("unknown export format '{s}' (opencv, ros, mrcal, colmap)"))
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

/// The parts every format needs, checked: `fx, fy, cx, cy`, the coefficients (5 zeros for a pinhole
/// camera in the formats without a pinhole model) and the model's coefficient count.
struct Intrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    /// As stored: 0, 5 or 8 coefficients.
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
    let n = c.distortion.coefficients.len();
    if ![0, 5, 8].contains(&n) {
        return Err(unsupported(format!(
            "{n} distortion coefficients (expected 0, 5 or 8)"
        )));
    }
    Ok(Intrinsics {
        fx: k[0][0],
        fy: k[1][1],
        cx: k[0][2],
        cy: k[1][2],
        coefficients: c.distortion.coefficients.clone(),
        width: c.image_size[0],
        height: c.image_size[1],
    })
}

impl Intrinsics {
    /// Coefficients for formats that always carry at least OpenCV's 5.
    fn at_least_five(&self) -> Vec<f64> {
        let mut d = self.coefficients.clone();
        if d.len() < 5 {
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

/// OpenCV `FileStorage` YAML, as OpenCV's camera calibration sample writes it.
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
/// zero fourth column and the rectification the identity (a monocular camera).
pub fn ros_camera_info_yaml(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "ROS camera_info")?;
    let d = i.at_least_five();
    let model = if d.len() == 8 {
        "rational_polynomial"
    } else {
        "plumb_bob"
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

/// mrcal `.cameramodel` with identity extrinsics (`rt_cam_ref` = 0).
pub fn mrcal_cameramodel(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "mrcal")?;
    let (model, mut params) = match i.coefficients.len() {
        0 => ("LENSMODEL_PINHOLE", vec![]),
        5 => ("LENSMODEL_OPENCV5", i.coefficients.clone()),
        _ => ("LENSMODEL_OPENCV8", i.coefficients.clone()),
    };
    params.splice(0..0, [i.fx, i.fy, i.cx, i.cy]);
    Ok(format!(
        "# generated by cubecal {} on {}\n{{\n    'lensmodel': '{model}',\n    'intrinsics': [ {} ],\n    'extrinsics': [ 0.0, 0.0, 0.0, 0.0, 0.0, 0.0 ],\n    'imagersize': [ {}, {} ],\n}}\n",
        profile
            .software_version
            .chars()
            .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '+'))
            .collect::<String>(),
        profile.created.escape_default(),
        list(&params),
        i.width,
        i.height
    ))
}

/// A COLMAP `cameras.txt` with camera id 1: `PINHOLE`, `OPENCV` (`k3` = 0) or `FULL_OPENCV`, with the
/// principal point moved to COLMAP's convention (+0.5 px).
pub fn colmap_cameras_txt(profile: &Profile) -> Result<String, ExportError> {
    let i = intrinsics(profile, "COLMAP")?;
    let (cx, cy) = (i.cx + 0.5, i.cy + 0.5);
    let d = &i.coefficients;
    let (model, mut params) = match d.len() {
        0 => ("PINHOLE", vec![]),
        5 if d[4] == 0.0 => ("OPENCV", d[..4].to_vec()),
        _ => {
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
