//! Reading a station run directory:
//!
//! ```text
//! RUN_DIR/session/           recorded session (manifest.json + PNG frames)
//! RUN_DIR/rig.toml           the rig
//! RUN_DIR/observations.json  accepted views (`cubecal solve` format with face/frame/held_out)
//! RUN_DIR/result.json        verdict, calibration, held-out poses, per-view outcomes, device
//! ```
//!
//! `result.json`, `observations.json` and `rig.toml` are required. The session is optional: without it
//! (or without a frame) the report says so instead of showing that thumbnail.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::calib::observations::RawObservations;
use crate::calib::report::CalibrationReport;
use crate::capture::session::Manifest;
use crate::rig::Rig;
use crate::run::Verdict;

use super::ReportError;

/// The pose of a view kept out of the fit and checked against it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutPose {
    pub name: String,
    pub rms_px: f64,
    /// `cam_from_rig` rotation, row-major.
    pub rotation: [[f64; 3]; 3],
    /// `cam_from_rig` translation (mm).
    pub translation: [f64; 3],
}

/// What became of one captured view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewOutcome {
    pub name: String,
    /// Frame file name inside `session/`.
    #[serde(default)]
    pub frame: Option<String>,
    pub accepted: bool,
    /// Why it was rejected (or a remark on an accepted view).
    #[serde(default)]
    pub reason: Option<String>,
}

/// `RUN_DIR/result.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    pub verdict: Verdict,
    /// Null when the run obtained no calibration (no view accepted, the solver failed): the report
    /// then shows the verdict and every view with its overlay and reason.
    #[serde(default)]
    pub calibration: Option<CalibrationReport>,
    #[serde(default)]
    pub held_out: Vec<HeldOutPose>,
    #[serde(default)]
    pub views: Vec<ViewOutcome>,
    #[serde(default)]
    pub profile: Option<PathBuf>,
    #[serde(default)]
    pub run_dir: Option<PathBuf>,
    /// Device identity (`identity`, `name`, …) as the station wrote it.
    #[serde(default)]
    pub device: serde_json::Value,
    /// What the station decided or noticed (k3 fixed and why, a jump against the stored profile).
    #[serde(default)]
    pub notes: Vec<String>,
    /// The solver's error when it could not calibrate.
    #[serde(default)]
    pub solve_error: Option<String>,
}

/// Everything a run report is made from.
#[derive(Debug, Clone)]
pub struct RunData {
    pub dir: PathBuf,
    pub rig: Rig,
    pub observations: RawObservations,
    pub result: RunResult,
    /// The session's manifest, when the session is there.
    pub manifest: Option<Manifest>,
    /// The frames at thumbnail size as the station held them (empty when the run is read from its
    /// directory: the thumbnails then decode the session's frames).
    pub previews: Vec<crate::run::preview::FramePreview>,
}

pub use crate::run::{OBSERVATIONS, RESULT, RIG, SESSION};

fn read(path: &Path) -> Result<Vec<u8>, ReportError> {
    std::fs::read(path).map_err(|source| ReportError::Read {
        path: path.to_path_buf(),
        source,
    })
}

fn json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, ReportError> {
    serde_json::from_slice(&read(path)?).map_err(|source| ReportError::Json {
        path: path.to_path_buf(),
        source,
    })
}

impl RunData {
    /// Load a run directory (see the module docs).
    pub fn load(dir: &Path) -> Result<RunData, ReportError> {
        if !dir.is_dir() || !dir.join(RESULT).is_file() {
            return Err(ReportError::NotARunDir {
                path: dir.to_path_buf(),
            });
        }
        let result: RunResult = json(&dir.join(RESULT))?;
        let observations: RawObservations = json(&dir.join(OBSERVATIONS))?;
        // The run told the rig's warnings when it used the rig; the report does not repeat them.
        let (rig, _warnings) = Rig::read_quiet(&dir.join(RIG))?;
        let manifest_path = dir.join(SESSION).join("manifest.json");
        let manifest = if manifest_path.exists() {
            Some(json::<Manifest>(&manifest_path)?)
        } else {
            None
        };
        let data = RunData {
            dir: dir.to_path_buf(),
            rig,
            observations,
            result,
            manifest,
            previews: Vec::new(),
        };
        data.check()?;
        Ok(data)
    }

    /// Consistency the plots rely on: the image sizes agree and are positive.
    pub fn check(&self) -> Result<(), ReportError> {
        let a = self.observations.image_size;
        let b = self.result.calibration.as_ref().map_or(a, |c| c.image_size);
        if a != b || a[0] == 0 || a[1] == 0 {
            return Err(ReportError::Invalid {
                path: self.dir.clone(),
                reason: format!(
                    "image size of observations.json ({}×{}) and result.json ({}×{}) disagree or are empty",
                    a[0], a[1], b[0], b[1]
                ),
            });
        }
        Ok(())
    }

    /// The turntable angle recorded with a frame, if any.
    pub fn angle_deg(&self, frame: &str) -> Option<f64> {
        self.manifest
            .as_ref()?
            .frames
            .iter()
            .find(|f| f.file == frame)?
            .angle_deg
    }
}
