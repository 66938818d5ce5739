//! Scoring a detection against the exact ground truth of a synthetic render: which faces were fully
//! visible, at what angle from frontal, which were found, the corner errors, and mislabelled corners.
//!
//! One scorer serves the accuracy tests, the evaluation example and anyone measuring the detector on
//! their own renders, so every figure reported for the detector is computed the same way.

use std::collections::HashMap;

use nalgebra::Vector3;

use super::FrameDetection;
use crate::camera::{Camera, DistortionModel, Pose};
use crate::capture::synthetic::{GroundTruth, Palette, RenderSettings, random_poses};
use crate::rig::Rig;

/// The two image sets the detector is measured on (issue 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EvalSet {
    /// 1920×1080, fx 1400, k1 −0.1, blur σ 1, noise σ 2, gamma 2.2, vignetting 0.3.
    Realistic,
    /// 1280×960, fx 700, k1 −0.3, blur σ 1.5, noise σ 5, gamma 2.2, vignetting 0.3, low contrast
    /// (reflectances 0.3 / 0.55 instead of 0.06 / 0.88).
    Hard,
}

impl EvalSet {
    pub fn camera(self) -> Camera {
        match self {
            EvalSet::Realistic => Camera::pinhole([1920, 1080], 1400.0, 1400.0, 959.5, 539.5)
                .with_distortion(DistortionModel::Brown5, &[-0.1]),
            EvalSet::Hard => Camera::pinhole([1280, 960], 700.0, 700.0, 639.5, 479.5)
                .with_distortion(DistortionModel::Brown5, &[-0.3]),
        }
    }

    pub fn settings(self) -> RenderSettings {
        let base = RenderSettings {
            gamma: 2.2,
            vignetting: 0.3,
            ..RenderSettings::default()
        };
        match self {
            EvalSet::Realistic => RenderSettings {
                blur_sigma_px: 1.0,
                noise_sigma: 2.0,
                seed: 1,
                ..base
            },
            EvalSet::Hard => RenderSettings {
                blur_sigma_px: 1.5,
                noise_sigma: 5.0,
                seed: 2,
                palette: Palette {
                    black: 0.3,
                    white: 0.55,
                    ..Palette::default()
                },
                ..base
            },
        }
    }

    /// `n` seeded random views of `rig` ([`random_poses`]); the first `k` of `n` do not depend on `n`.
    pub fn poses(self, rig: &Rig, n: usize) -> Vec<Pose> {
        random_poses(rig, &self.camera(), n, self.settings().seed)
    }
}

/// A detected corner farther than this from its ground-truth position (px) counts as mislabelled.
pub const MISLABEL_PX: f64 = 1.0;

/// One face of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceScore {
    pub face: usize,
    /// Angle between the face normal and the ray from the camera centre to the face centre (degrees;
    /// 0 = frontal).
    pub angle_deg: f64,
    /// Every inner corner of the face is visible in the frame.
    pub fully_visible: bool,
    /// Visible corners of the face.
    pub visible_corners: usize,
    /// The detector reported this face.
    pub found: bool,
    /// Corners reported for this face.
    pub corners: usize,
    /// Reported corners that are not visible in the ground truth or lie more than [`MISLABEL_PX`]
    /// from the ground truth of their (row, col).
    pub mislabelled: usize,
    /// Position errors (px) of the correctly labelled corners.
    pub errors: Vec<f64>,
    /// The detector's σ (px, per coordinate) of the same corners.
    pub sigmas: Vec<f64>,
}

/// Score one frame's detection.
pub fn score(rig: &Rig, truth: &GroundTruth, det: &FrameDetection) -> Vec<FaceScore> {
    let gt: HashMap<(usize, usize, usize), [f64; 2]> = truth
        .visible()
        .filter_map(|c| Some(((c.face_index, c.row, c.col), c.uv?)))
        .collect();
    let pose = truth.cam_from_rig.to_pose();
    let camera_centre = -(pose.rotation.inverse() * pose.translation);
    rig.faces
        .iter()
        .enumerate()
        .map(|(fi, f)| {
            let visible_corners = truth
                .corners
                .iter()
                .filter(|c| c.face_index == fi && c.visible)
                .count();
            let centre: Vector3<f64> =
                (f.corner_xyz(0, 0) + f.corner_xyz(f.rows - 1, f.cols - 1)) / 2.0;
            let angle_deg = f.normal().angle(&(camera_centre - centre)).to_degrees();
            let mut s = FaceScore {
                face: fi,
                angle_deg,
                fully_visible: visible_corners == f.n_corners(),
                visible_corners,
                found: false,
                corners: 0,
                mislabelled: 0,
                errors: Vec::new(),
                sigmas: Vec::new(),
            };
            for d in det.faces.iter().filter(|d| d.face == fi) {
                s.found = true;
                for c in &d.corners {
                    s.corners += 1;
                    match gt.get(&(fi, c.row, c.col)) {
                        Some(t) => {
                            let e = ((c.uv.x - t[0]).powi(2) + (c.uv.y - t[1]).powi(2)).sqrt();
                            if e > MISLABEL_PX {
                                s.mislabelled += 1;
                            } else {
                                s.errors.push(e);
                                s.sigmas.push(c.sigma_px);
                            }
                        }
                        None => s.mislabelled += 1,
                    }
                }
            }
            s
        })
        .collect()
}

/// Totals over many frames, restricted to fully visible faces seen at less than `max_angle_deg`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Summary {
    pub faces: usize,
    pub found: usize,
    pub corners: usize,
    pub mislabelled: usize,
    pub rms_px: f64,
    pub max_px: f64,
    /// RMS of the detector's per-corner σ (px per coordinate); an honest σ makes
    /// `rms_px ≈ √2 · rms_sigma_px`.
    pub rms_sigma_px: f64,
}

impl Summary {
    /// Found / fully visible faces, in 0..1 (1 when there are none).
    pub fn rate(&self) -> f64 {
        if self.faces == 0 {
            1.0
        } else {
            self.found as f64 / self.faces as f64
        }
    }

    /// Summarise the faces seen at an angle in `[min_angle_deg, max_angle_deg)`; mislabelled corners
    /// are counted over every face, whatever its angle or visibility.
    pub fn of(scores: &[FaceScore], min_angle_deg: f64, max_angle_deg: f64) -> Summary {
        let mut s = Summary::default();
        let mut sq = 0.0;
        let mut sq_sigma = 0.0;
        for f in scores {
            s.mislabelled += f.mislabelled;
            if !f.fully_visible || f.angle_deg < min_angle_deg || f.angle_deg >= max_angle_deg {
                continue;
            }
            s.faces += 1;
            if f.found {
                s.found += 1;
            }
            s.corners += f.errors.len();
            for e in &f.errors {
                sq += e * e;
                s.max_px = s.max_px.max(*e);
            }
            sq_sigma += f.sigmas.iter().map(|v| v * v).sum::<f64>();
        }
        if s.corners > 0 {
            s.rms_px = (sq / s.corners as f64).sqrt();
            s.rms_sigma_px = (sq_sigma / s.corners as f64).sqrt();
        }
        s
    }
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}/{} faces ({:.1} %), {} corners, RMS {:.4} px, max {:.4} px, {} mislabelled, σ {:.4} px",
            self.found,
            self.faces,
            100.0 * self.rate(),
            self.corners,
            self.rms_px,
            self.max_px,
            self.mislabelled,
            self.rms_sigma_px
        )
    }
}
