//! The data a station run produces and its readers consume: the verdict and its checks, the run's
//! result (`RUN_DIR/result.json`, also what `calibrate --json` prints last) and the layout of a run
//! directory. It sits below the station that writes it and the profile store, report and front ends
//! that read it, so none of them needs another to know what a run is.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::calib::report::CalibrationReport;
use crate::capture::SourceInfo;

pub mod preview;
pub mod verdict;

pub use verdict::{Check, FixedParameter, Verdict};

/// `RUN_DIR/result.json`: the verdict, calibration, held-out poses, per-view outcomes, device.
pub const RESULT: &str = "result.json";
/// `RUN_DIR/observations.json`: the accepted views (`cubecal solve` format with face/frame/held_out).
pub const OBSERVATIONS: &str = "observations.json";
/// `RUN_DIR/rig.toml`: the rig the run used.
pub const RIG: &str = "rig.toml";
/// `RUN_DIR/session/`: the recorded session (manifest and frames).
pub const SESSION: &str = "session";

/// Why a view was accepted or not (result.json `views`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewRecord {
    pub name: String,
    /// Session frame file the view was detected in.
    pub frame: Option<String>,
    pub angle_deg: Option<f64>,
    /// The stage's tilt (two-axis stages).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_deg: Option<f64>,
    pub accepted: bool,
    pub reason: Option<String>,
    pub faces: usize,
    pub corners: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blur_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion: Option<f64>,
}

/// A held-out view checked against the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOut {
    pub name: String,
    pub rms_px: f64,
    pub max_px: f64,
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

/// The result of a run: what `--json` prints last and `RUN_DIR/result.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    pub verdict: Verdict,
    /// The calibration, when the solver produced one (also for a failing verdict).
    pub calibration: Option<CalibrationReport>,
    pub held_out: Vec<HeldOut>,
    pub views: Vec<ViewRecord>,
    /// Where the profile went (null when none was written).
    pub profile: Option<PathBuf>,
    /// The profile store that could not be reached: `profile` is then the profile's entry in the
    /// local spool, committed when the store returns (see `crate::profile::spool`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile_waits_for: Option<String>,
    pub run_dir: PathBuf,
    pub device: SourceInfo,
    /// What the station decided beyond the config (e.g. "k3 fixed: not determined by the data").
    #[serde(default)]
    pub notes: Vec<String>,
    /// The solver's error when it could not calibrate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub solve_error: Option<String>,
    /// Each view's frame at thumbnail size, from the station (never in result.json: a report drawn
    /// from the run directory decodes the session's frames instead).
    #[serde(skip)]
    pub previews: Vec<preview::FramePreview>,
}

impl RunResult {
    /// The process exit code of this result: 0 pass, 5 no calibration (too few views accepted, or
    /// the solver failed), 6 calibrated but rejected by QA.
    pub fn exit_code(&self) -> u8 {
        if self.verdict.pass {
            crate::exit::SUCCESS
        } else if self.calibration.is_none() {
            crate::exit::CALIBRATION_FAILED
        } else {
            crate::exit::QA_REJECTED
        }
    }
}
