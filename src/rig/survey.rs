//! Surveyed rig files: the as-built rig measured by `cubecal rig survey` (see
//! the calibration solver's `solve_rig`), written as an ordinary rig TOML that any cubecal command loads.
//!
//! The faces carry their measured poses (`origin`, `col_dir`, `row_dir`); an informational
//! `[faces.survey]` table per face records the deviation from the nominal file and its σ, and a top-level
//! `[survey]` table records what the survey was made from (the nominal file's SHA-256, views, RMS).
//! Neither table changes what the file means: loading ignores them.
//!
//! ```toml
//! [[faces]]
//! name = "side-x"
//! origin = [200.41, 44.61, 52.73]
//! ...
//! [faces.survey]
//! offset_mm = [0.62, 0.98, -0.40]       # along its rows, along its columns, out of its plane
//! offset_std_mm = [0.0013, 0.0012, 0.0013]
//! rotation_deg = [0.30, -0.35, 0.20]    # about col_dir, row_dir, the normal
//! rotation_std_deg = [0.0008, 0.0006, 0.0006]
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::{RawBody, RawCharuco, RawFace, RawRig, Rig, RigError};

/// `[survey]`: what the surveyed rig was measured from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigSurvey {
    /// SHA-256 (hex) of the nominal rig file's bytes.
    pub nominal_sha256: String,
    /// The face the others were measured against (it keeps its nominal pose).
    pub reference_face: String,
    pub views: usize,
    pub points: usize,
    /// RMS of the residual components of the survey fit (px).
    pub rms_px: f64,
}

/// `[faces.survey]`: one face's measured deviation from the nominal file, relative to the reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaceSurvey {
    /// Whether the face was measured (false: the reference face, or a face never seen).
    pub refined: bool,
    /// Displacement of the face's grid centre: along its rows, along its columns, out of its plane (mm).
    pub offset_mm: [f64; 3],
    pub offset_std_mm: [f64; 3],
    /// Rotation about its centre as a rotation vector about `col_dir`, `row_dir`, normal (degrees).
    pub rotation_deg: [f64; 3],
    pub rotation_std_deg: [f64; 3],
    /// Residual RMS over the face's corners (px) and their number.
    pub rms_px: f64,
    pub n_points: usize,
}

/// SHA-256 (hex) of a rig file's bytes: the identity a profile records for the rig it used.
pub fn content_sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl Rig {
    /// The rig as TOML structures (what [`Rig::from_toml_str`] reads back to an equal rig).
    pub fn to_raw(&self) -> RawRig {
        RawRig {
            name: Some(self.name.clone()),
            units: Some("mm".into()),
            up: Some(self.up.into()),
            survey: None,
            body: self.body.map(|b| RawBody {
                min: Some(b.min.into()),
                max: Some(b.max.into()),
            }),
            faces: Some(
                self.faces
                    .iter()
                    .map(|f| RawFace {
                        name: Some(f.name.clone()),
                        cols: i64::try_from(f.cols).ok(),
                        rows: i64::try_from(f.rows).ok(),
                        square_mm: Some(f.square_mm),
                        origin: Some(f.origin.into()),
                        col_dir: Some(f.col_dir.into()),
                        row_dir: Some(f.row_dir.into()),
                        margin_mm: Some(f.margin_mm),
                        first_square: Some(f.first_square),
                        open_sides: (!f.open_sides.is_empty()).then(|| {
                            f.open_sides
                                .iter()
                                .map(|s| s.as_str().to_string())
                                .collect()
                        }),
                        survey: None,
                        charuco: f.charuco.as_ref().map(|c| RawCharuco {
                            dictionary: Some(c.dictionary.name()),
                            marker_mm: Some(c.marker_mm),
                            first_id: None,
                            ids: Some(c.ids.iter().map(|&i| i64::from(i)).collect()),
                        }),
                    })
                    .collect(),
            ),
        }
    }
}

/// The surveyed rig as TOML text: `comment` lines first (each prefixed with `# `), then the rig with
/// its `[survey]` and per-face `[faces.survey]` tables (`faces[k]` for face k).
pub fn surveyed_toml(
    built: &Rig,
    survey: RigSurvey,
    faces: Vec<FaceSurvey>,
    comment: &[String],
) -> Result<String, toml::ser::Error> {
    let mut raw = built.to_raw();
    raw.survey = Some(survey);
    if let Some(rf) = raw.faces.as_mut() {
        for (r, s) in rf.iter_mut().zip(faces) {
            r.survey = Some(s);
        }
    }
    let body = toml::to_string(&raw)?;
    let mut text: String = comment.iter().map(|l| format!("# {l}\n")).collect();
    text.push_str(&body);
    Ok(text)
}

/// Write a surveyed rig atomically (a crash never leaves a truncated rig file).
pub fn write_surveyed(path: &Path, text: &str) -> Result<(), RigError> {
    super::write_atomic(path, text.as_bytes()).map_err(|source| RigError::Write {
        path: path.display().to_string(),
        source,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_rig_round_trips_through_toml_with_its_survey() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/fixtures/rigs/cube_outside.toml"
        );
        let (mut rig, _) = Rig::load(Path::new(path)).unwrap();
        // A face turned by an awkward angle: directions with full f64 digits.
        let r = nalgebra::Rotation3::new(nalgebra::Vector3::new(0.0031, -0.0047, 0.0029));
        rig.faces[1].col_dir = r * rig.faces[1].col_dir;
        rig.faces[1].row_dir = r * rig.faces[1].row_dir;
        rig.faces[1].origin += nalgebra::Vector3::new(0.123456789, -0.5, 0.25);
        let survey = RigSurvey {
            nominal_sha256: content_sha256(b"x"),
            reference_face: "top".into(),
            views: 12,
            points: 1926,
            rms_px: 0.0139,
        };
        let face = FaceSurvey {
            refined: true,
            offset_mm: [0.62, 0.98, -0.4],
            offset_std_mm: [0.001; 3],
            rotation_deg: [0.3, -0.35, 0.2],
            rotation_std_deg: [0.001; 3],
            rms_px: 0.014,
            n_points: 600,
        };
        let text = surveyed_toml(&rig, survey, vec![face; 3], &["surveyed".into()]).unwrap();
        assert!(text.starts_with("# surveyed\n"));
        let (back, _) = Rig::from_toml_str(&text, "surveyed.toml").unwrap();
        assert_eq!(back.faces.len(), rig.faces.len());
        for (a, b) in back.faces.iter().zip(&rig.faces) {
            assert_eq!(a.name, b.name);
            assert!((a.origin - b.origin).norm() < 1e-12);
            assert!((a.col_dir - b.col_dir).norm() < 1e-12);
            assert!((a.row_dir - b.row_dir).norm() < 1e-12);
        }
        let raw: RawRig = toml::from_str(&text).unwrap();
        assert_eq!(raw.survey.unwrap().views, 12);
        assert_eq!(
            content_sha256(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }
}
