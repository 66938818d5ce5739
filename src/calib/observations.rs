//! The correspondence file read by `cubecal solve` (and written by the detector):
//!
//! ```json
//! {"image_size": [w, h],
//!  "views": [{"name": "...", "points": [{"xyz": [x, y, z], "uv": [u, v]}, ...]}]}
//! ```
//!
//! `xyz` are rig coordinates in millimetres, `uv` pixel coordinates with integer values at pixel centres.
//! Field names are fixed so that other tools can feed cubecal. Unknown fields are ignored (other tools
//! may add their own) but each is named in a warning, so that a misspelt optional field (`nmae`) does
//! not pass unnoticed; missing or mistyped fields are errors naming the file, line and column. View
//! names must be unique.
//!
//! The output of `cubecal detect --json` (a JSON *array* with one object per image) is read too: each
//! image in which faces were labelled becomes a view named after the image, its corners the points
//! (with their face); all images must have the same size, which becomes `image_size`.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::calib::{Correspondence, View};

/// Errors reading an observations file.
#[derive(Debug, thiserror::Error)]
pub enum ObservationsError {
    #[error("cannot read observations file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
}

impl ObservationsError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            ObservationsError::Read { .. }
            | ObservationsError::Parse { .. }
            | ObservationsError::Invalid { .. } => crate::exit::BAD_INPUT,
        }
    }
}

/// One correspondence as stored in the file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RawPoint {
    pub xyz: [f64; 3],
    pub uv: [f64; 2],
    /// The rig face the point lies on (written by the station; optional on input).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face: Option<String>,
    /// Covariance of `uv`, `[var_u, cov_uv, var_v]` (px²), from the detector's fit (written by the
    /// station and `detect --json`; optional on input, files without it load as before). When every
    /// point has one, the solve weights each point by its inverse.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cov: Option<[f64; 3]>,
}

/// A 2×2 covariance as the files store it: `[var_u, cov_uv, var_v]`.
pub fn cov_to_array(c: &Matrix2<f64>) -> [f64; 3] {
    [c[(0, 0)], 0.5 * (c[(0, 1)] + c[(1, 0)]), c[(1, 1)]]
}

/// The 2×2 covariance of a file's `[var_u, cov_uv, var_v]`.
pub fn cov_from_array(c: [f64; 3]) -> Matrix2<f64> {
    Matrix2::new(c[0], c[1], c[1], c[2])
}

/// One view as stored in the file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RawView {
    #[serde(default)]
    pub name: Option<String>,
    pub points: Vec<RawPoint>,
    /// The frame the view was detected in (a file name inside the run's session; station output).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    /// The view was kept out of the fit and checked against it (station output).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub held_out: bool,
}

/// The file as stored.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RawObservations {
    pub image_size: [u32; 2],
    pub views: Vec<RawView>,
}

/// Validated observations.
#[derive(Debug, Clone)]
pub struct Observations {
    pub image_size: [u32; 2],
    pub views: Vec<View>,
}

impl Observations {
    /// Parse and validate from JSON text; `path` is used in messages only.
    pub fn from_json(text: &str, path: &Path) -> Result<Observations, ObservationsError> {
        let parse_error = |e: serde_json::Error| ObservationsError::Parse {
            path: path.to_path_buf(),
            line: e.line(),
            column: e.column(),
            message: e.to_string(),
        };
        let raw: RawObservations = if text.trim_start().starts_with('[') {
            let images: Vec<DetectedImage> = serde_json::from_str(text).map_err(|e| {
                let mut err = parse_error(e);
                if let ObservationsError::Parse { message, .. } = &mut err {
                    message.push_str(
                        " (a JSON array is read as the output of `cubecal detect --json`)",
                    );
                }
                err
            })?;
            from_detections(images, path)?
        } else {
            let raw = serde_json::from_str(text).map_err(parse_error)?;
            if let Ok(value) = serde_json::from_str::<serde_json::Value>(text) {
                warn_unknown_keys(&value, path);
            }
            raw
        };
        Observations::validate(raw, path)
    }

    /// Read, parse and validate a file.
    pub fn load(path: &Path) -> Result<Observations, ObservationsError> {
        let text = std::fs::read_to_string(path).map_err(|source| ObservationsError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Observations::from_json(&text, path)
    }

    fn validate(raw: RawObservations, path: &Path) -> Result<Observations, ObservationsError> {
        let mut seen = std::collections::HashMap::new();
        for (i, v) in raw.views.iter().enumerate() {
            if let Some(name) = &v.name
                && let Some(first) = seen.insert(name.clone(), i)
            {
                return Err(ObservationsError::Invalid {
                    path: path.to_path_buf(),
                    reason: format!(
                        "views[{i}]: name '{name}' is already used by views[{first}]: view names must be unique"
                    ),
                });
            }
        }
        let invalid = |reason: String| ObservationsError::Invalid {
            path: path.to_path_buf(),
            reason,
        };
        if raw.image_size[0] == 0 || raw.image_size[1] == 0 {
            return Err(invalid(format!(
                "image_size: must be positive, got [{}, {}]",
                raw.image_size[0], raw.image_size[1]
            )));
        }
        if raw.views.is_empty() {
            return Err(invalid("views: no views given".into()));
        }
        let mut views = Vec::with_capacity(raw.views.len());
        for (i, v) in raw.views.into_iter().enumerate() {
            let name = v.name.unwrap_or_else(|| format!("view{i}"));
            if v.points.is_empty() {
                return Err(invalid(format!("views[{i}] ('{name}').points: empty")));
            }
            let mut points = Vec::with_capacity(v.points.len());
            for (j, p) in v.points.into_iter().enumerate() {
                if !p.xyz.iter().chain(&p.uv).all(|x| x.is_finite()) {
                    return Err(invalid(format!(
                        "views[{i}] ('{name}').points[{j}]: value is not finite"
                    )));
                }
                let cov = p.cov.map(cov_from_array);
                if let Some(c) = &cov
                    && !super::valid_covariance(c)
                {
                    return Err(invalid(format!(
                        "views[{i}] ('{name}').points[{j}].cov: {:?} is not a covariance [var_u, cov_uv, var_v] (finite, var_u > 0, var_u·var_v > cov_uv²)",
                        p.cov.unwrap_or_default()
                    )));
                }
                points.push(Correspondence {
                    xyz: Vector3::from(p.xyz),
                    uv: Vector2::from(p.uv),
                    cov,
                });
            }
            views.push(View { name, points });
        }
        Ok(Observations {
            image_size: raw.image_size,
            views,
        })
    }

    /// The stored form, for writing.
    pub fn to_raw(&self) -> RawObservations {
        RawObservations {
            image_size: self.image_size,
            views: self
                .views
                .iter()
                .map(|v| RawView {
                    name: Some(v.name.clone()),
                    points: v
                        .points
                        .iter()
                        .map(|c| RawPoint {
                            xyz: c.xyz.into(),
                            uv: c.uv.into(),
                            face: None,
                            cov: c.cov.as_ref().map(cov_to_array),
                        })
                        .collect(),
                    frame: None,
                    held_out: false,
                })
                .collect(),
        }
    }
}

/// One image of `cubecal detect --json` (only the fields read here).
#[derive(Debug, Deserialize)]
struct DetectedImage {
    image: String,
    width: u32,
    height: u32,
    faces: Vec<DetectedFace>,
}

#[derive(Debug, Deserialize)]
struct DetectedFace {
    face: String,
    corners: Vec<DetectedCorner>,
}

#[derive(Debug, Deserialize)]
struct DetectedCorner {
    xyz: [f64; 3],
    uv: [f64; 2],
    #[serde(default)]
    cov: Option<[f64; 3]>,
}

/// Views from detections: one per image with labelled faces, named by the image's file stem (its
/// whole path when two stems clash).
fn from_detections(
    images: Vec<DetectedImage>,
    path: &Path,
) -> Result<RawObservations, ObservationsError> {
    let invalid = |reason: String| ObservationsError::Invalid {
        path: path.to_path_buf(),
        reason,
    };
    let Some(first) = images.first() else {
        return Err(invalid("detections: no images".into()));
    };
    let image_size = [first.width, first.height];
    let stem = |image: &str| {
        Path::new(image)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| image.to_string())
    };
    let mut stems: Vec<String> = images.iter().map(|im| stem(&im.image)).collect();
    stems.sort();
    let clash = stems.windows(2).any(|w| w[0] == w[1]);
    let mut views = Vec::new();
    for (i, im) in images.into_iter().enumerate() {
        if [im.width, im.height] != image_size {
            return Err(invalid(format!(
                "[{i}] ({}): {}×{} image, but the first is {}×{}: one camera's images only",
                im.image, im.width, im.height, image_size[0], image_size[1]
            )));
        }
        let points: Vec<RawPoint> = im
            .faces
            .iter()
            .flat_map(|f| {
                f.corners.iter().map(|c| RawPoint {
                    xyz: c.xyz,
                    uv: c.uv,
                    face: Some(f.face.clone()),
                    cov: c.cov,
                })
            })
            .collect();
        if points.is_empty() {
            tracing::info!(image = %im.image, "no faces detected: not a view");
            continue;
        }
        let name = if clash {
            im.image.clone()
        } else {
            stem(&im.image)
        };
        views.push(RawView {
            name: Some(name),
            points,
            frame: Some(im.image),
            held_out: false,
        });
    }
    Ok(RawObservations { image_size, views })
}

/// Warn about keys the observation format does not define (they are ignored).
fn warn_unknown_keys(value: &serde_json::Value, path: &Path) {
    const TOP: &[&str] = &["image_size", "views"];
    const VIEW: &[&str] = &["name", "points", "frame", "held_out"];
    const POINT: &[&str] = &["xyz", "uv", "face", "cov"];
    let mut unknown = Vec::new();
    let mut check = |v: &serde_json::Value, known: &[&str], at: &dyn Fn(&str) -> String| {
        if let Some(map) = v.as_object() {
            for k in map.keys().filter(|k| !known.contains(&k.as_str())) {
                unknown.push(at(k));
            }
        }
    };
    check(value, TOP, &|k| k.to_string());
    let views = value.get("views").and_then(|v| v.as_array());
    for (i, view) in views.into_iter().flatten().enumerate() {
        check(view, VIEW, &|k| format!("views[{i}].{k}"));
        let points = view.get("points").and_then(|p| p.as_array());
        for (j, p) in points.into_iter().flatten().enumerate() {
            check(p, POINT, &|k| format!("views[{i}].points[{j}].{k}"));
        }
    }
    if !unknown.is_empty() {
        let shown: Vec<&str> = unknown.iter().take(5).map(String::as_str).collect();
        tracing::warn!(
            "{}: ignoring {} unknown key{} ({}{})",
            path.display(),
            unknown.len(),
            if unknown.len() == 1 { "" } else { "s" },
            shown.join(", "),
            if unknown.len() > shown.len() {
                ", …"
            } else {
                ""
            }
        );
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Observations, ObservationsError> {
        Observations::from_json(text, Path::new("obs.json"))
    }

    #[test]
    fn round_trip() {
        let text = r#"{"image_size": [640, 480], "extra": 1, "views": [{"name": "a", "points": [{"xyz": [1, 2, 3], "uv": [4.5, 5.5]}]}]}"#;
        let o = parse(text).unwrap();
        assert_eq!(o.views[0].points[0].uv, Vector2::new(4.5, 5.5));
        let back = serde_json::to_string(&o.to_raw()).unwrap();
        let o2 = parse(&back).unwrap();
        assert_eq!(o2.views, o.views);
        assert_eq!(o.views[0].points[0].cov, None);
    }

    #[test]
    fn covariances_round_trip_and_bad_ones_are_named() {
        let text = r#"{"image_size": [640, 480], "views": [{"name": "a", "points": [{"xyz": [1, 2, 3], "uv": [4.5, 5.5], "cov": [0.0004, -0.0001, 0.0009]}, {"xyz": [1, 2, 4], "uv": [4.5, 6.5]}]}]}"#;
        let o = parse(text).unwrap();
        assert_eq!(
            o.views[0].points[0].cov,
            Some(Matrix2::new(0.0004, -0.0001, -0.0001, 0.0009))
        );
        assert_eq!(o.views[0].points[1].cov, None);
        let back = serde_json::to_string(&o.to_raw()).unwrap();
        assert!(back.contains("\"cov\":[0.0004,-0.0001,0.0009]"), "{back}");
        assert_eq!(parse(&back).unwrap().views, o.views);
        // `detect --json` output carries it too.
        let det = r#"[{"image": "f.png", "width": 640, "height": 480, "faces": [{"face": "top", "corners": [{"row": 0, "col": 0, "xyz": [1, 2, 3], "uv": [4.5, 5.5], "sigma_px": 0.02, "cov": [0.0004, 0.0, 0.0004]}]}]}]"#;
        let o = parse(det).unwrap();
        assert_eq!(
            o.views[0].points[0].cov,
            Some(Matrix2::from_diagonal_element(0.0004))
        );
        // Not positive definite (|cov_uv| too large), negative.
        for bad in ["[0.0004, 0.001, 0.0009]", "[-1, 0, 1]"] {
            let text = format!(
                r#"{{"image_size": [640, 480], "views": [{{"name": "a", "points": [{{"xyz": [1, 2, 3], "uv": [4.5, 5.5], "cov": {bad}}}]}}]}}"#
            );
            let e = parse(&text).unwrap_err().to_string();
            assert!(e.contains("views[0] ('a').points[0].cov"), "{bad}: {e}");
        }
    }

    #[test]
    fn errors_name_the_problem() {
        let e = parse(
            r#"{"image_size": [640, 480], "views": [{"points": [{"xyz": [1, 2], "uv": [4, 5]}]}]}"#,
        )
        .unwrap_err();
        assert!(matches!(e, ObservationsError::Parse { line: 1, .. }), "{e}");
        let e = parse(r#"{"image_size": [0, 480], "views": []}"#).unwrap_err();
        assert!(e.to_string().contains("image_size"), "{e}");
        let e = parse(r#"{"image_size": [10, 10], "views": [{"name": "v", "points": []}]}"#)
            .unwrap_err();
        assert!(
            e.to_string().contains("views[0] ('v').points: empty"),
            "{e}"
        );
        let e = parse("{not json").unwrap_err();
        assert!(e.to_string().starts_with("obs.json:1:"), "{e}");
        let e = parse(r#"{"image_size": [10, 10], "views": [{"points": [{"xyz": [1e400, 2, 3], "uv": [4, 5]}]}]}"#).unwrap_err();
        assert!(matches!(e, ObservationsError::Parse { .. }), "{e}");
    }
}
