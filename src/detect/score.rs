//! Scoring a detection against the exact ground truth of a synthetic render: which faces were fully
//! visible, at what angle from frontal, which were found, the corner errors, and mislabelled corners.
//!
//! One scorer serves the accuracy tests, the evaluation example and anyone measuring the detector on
//! their own renders, so every figure reported for the detector is computed the same way.

use std::collections::HashMap;

use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::FrameDetection;
use crate::camera::{Camera, DistortionModel, Pose};
use crate::render::{GroundTruth, Palette, RenderSettings, random_poses};
use crate::rig::Rig;

/// The two image sets the detector is measured on (issue 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EvalSet {
    /// 1920×1080, fx 1400, k1 −0.1, blur σ 1, noise σ 2, gamma 2.2, vignetting 0.3.
    Realistic,
    /// 1280×960, fx 700, k1 −0.3, blur σ 1.5, noise σ 5, gamma 2.2, vignetting 0.3, low contrast
    /// (reflectances 0.3 / 0.55 instead of 0.06 / 0.88).
    Hard,
    /// Strong barrel distortion with the rig near the image corners (issue 19): 1280×960, k1 −0.3,
    /// fx 1250 (the distortion's fold, where the radial magnification `1 + 3·k1·r²` reaches 0, lies
    /// at 1.1 × the half-diagonal, so the whole frame is imaged and the magnification in the image
    /// corners is down to ~0.4), the realistic set's blur, noise, gamma and vignetting; the cube at
    /// about twice the realistic distance, its centre turned towards one of the four image corners
    /// in turn ([`periphery_poses`]).
    PeripheryK1m03,
    /// As [`EvalSet::PeripheryK1m03`] with k1 −0.4 and fx 1450 (fold at 1.1 × the half-diagonal).
    PeripheryK1m04,
    /// A 180° fisheye (issue 32): 1280×960, Kannala–Brandt fx 350 (the image's width spans 210°, its
    /// corners 131° off the axis), the realistic set's blur, noise, gamma and vignetting; the cube's
    /// centre turned to a seeded angle of 0–70° off the axis ([`fisheye_poses`]).
    Fisheye,
}

impl EvalSet {
    pub fn camera(self) -> Camera {
        match self {
            EvalSet::Realistic => Camera::pinhole([1920, 1080], 1400.0, 1400.0, 959.5, 539.5)
                .with_distortion(DistortionModel::Brown5, &[-0.1]),
            EvalSet::Hard => Camera::pinhole([1280, 960], 700.0, 700.0, 639.5, 479.5)
                .with_distortion(DistortionModel::Brown5, &[-0.3]),
            EvalSet::PeripheryK1m03 => Camera::pinhole([1280, 960], 1250.0, 1250.0, 639.5, 479.5)
                .with_distortion(DistortionModel::Brown5, &[-0.3]),
            EvalSet::PeripheryK1m04 => Camera::pinhole([1280, 960], 1450.0, 1450.0, 639.5, 479.5)
                .with_distortion(DistortionModel::Brown5, &[-0.4]),
            EvalSet::Fisheye => Camera::pinhole([1280, 960], 350.0, 350.0, 641.2, 478.6)
                .with_distortion(DistortionModel::Kb4, &[0.021, -0.0043, 0.00052, -0.000047]),
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
            EvalSet::PeripheryK1m03 | EvalSet::PeripheryK1m04 => RenderSettings {
                blur_sigma_px: 1.0,
                noise_sigma: 2.0,
                seed: 3,
                ..base
            },
            EvalSet::Fisheye => RenderSettings {
                blur_sigma_px: 1.0,
                noise_sigma: 2.0,
                seed: 4,
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
        match self {
            EvalSet::Realistic | EvalSet::Hard => {
                random_poses(rig, &self.camera(), n, self.settings().seed)
            }
            EvalSet::PeripheryK1m03 | EvalSet::PeripheryK1m04 => {
                periphery_poses(rig, &self.camera(), n, self.settings().seed)
            }
            EvalSet::Fisheye => fisheye_poses(rig, &self.camera(), n, self.settings().seed),
        }
    }

    /// The set's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            EvalSet::Realistic => "realistic",
            EvalSet::Hard => "hard",
            EvalSet::PeripheryK1m03 => "periphery-0.3",
            EvalSet::PeripheryK1m04 => "periphery-0.4",
            EvalSet::Fisheye => "fisheye",
        }
    }

    /// The set named `name` ([`EvalSet::name`]).
    pub fn from_name(name: &str) -> Option<EvalSet> {
        [
            EvalSet::Realistic,
            EvalSet::Hard,
            EvalSet::PeripheryK1m03,
            EvalSet::PeripheryK1m04,
            EvalSet::Fisheye,
        ]
        .into_iter()
        .find(|s| s.name() == name)
    }
}

/// `n` seeded views with the rig near the image corners: [`random_poses`] moved back to
/// [`PERIPHERY_DISTANCE`] × their distance, then the camera turned so that the rig's centre is seen
/// at [`PERIPHERY_OFFSET`] of the way from the image centre to corner `k mod 4`.
pub fn periphery_poses(rig: &Rig, camera: &Camera, n: usize, seed: u64) -> Vec<Pose> {
    let centre = rig.centre();
    let (w, h) = (
        f64::from(camera.image_size[0]),
        f64::from(camera.image_size[1]),
    );
    random_poses(rig, camera, n, seed)
        .into_iter()
        .enumerate()
        .map(|(k, p)| {
            let (sx, sy) = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)][k % 4];
            let target = Vector2::new(
                camera.cx() + sx * PERIPHERY_OFFSET * w / 2.0,
                camera.cy() + sy * PERIPHERY_OFFSET * h / 2.0,
            );
            back_and_turned(
                p,
                &centre,
                PERIPHERY_DISTANCE,
                camera.unproject(target.x, target.y).ok(),
            )
        })
        .collect()
}

/// `p` moved back along its optical axis to `distance` × the depth of `centre`, then turned about the
/// camera centre so that `centre` is seen along the ray `to` (only moved back without one).
fn back_and_turned(
    p: Pose,
    centre: &Vector3<f64>,
    distance: f64,
    to: Option<Vector3<f64>>,
) -> Pose {
    let depth = p.transform(centre).z;
    let back = Pose::from_axis_angle(
        Vector3::zeros(),
        Vector3::new(0.0, 0.0, (distance - 1.0) * depth),
    );
    let p = back.compose(&p);
    let Some(to) = to else {
        return p;
    };
    let from = p.transform(centre).normalize();
    let axis = from.cross(&to);
    let angle = axis.norm().atan2(from.dot(&to));
    let turn = match axis.try_normalize(1e-12) {
        Some(a) => Pose::from_axis_angle(a * angle, Vector3::zeros()),
        None => Pose::identity(),
    };
    turn.compose(&p)
}

/// `n` seeded views for a fisheye: [`random_poses`] moved back to [`FISHEYE_DISTANCE`] × their
/// distance, then the camera turned about its centre so that the rig's centre is seen at a seeded
/// angle of 0 to [`FISHEYE_MAX_OFF_AXIS_DEG`] off the optical axis, in a seeded direction.
pub fn fisheye_poses(rig: &Rig, camera: &Camera, n: usize, seed: u64) -> Vec<Pose> {
    let centre = rig.centre();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_f15e);
    random_poses(rig, camera, n, seed)
        .into_iter()
        .map(|p| {
            let off = rng.random_range(0.0..FISHEYE_MAX_OFF_AXIS_DEG).to_radians();
            let azimuth = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let to = Vector3::new(
                off.sin() * azimuth.cos(),
                off.sin() * azimuth.sin(),
                off.cos(),
            );
            back_and_turned(p, &centre, FISHEYE_DISTANCE, Some(to))
        })
        .collect()
}

/// Distance of [`fisheye_poses`]' views relative to [`random_poses`]' (which fill a pinhole's frame
/// of the same focal length: a fisheye's frame holds far more than that).
pub const FISHEYE_DISTANCE: f64 = 1.4;

/// Largest angle off the axis at which [`fisheye_poses`] puts the rig's centre.
pub const FISHEYE_MAX_OFF_AXIS_DEG: f64 = 70.0;

/// Distance of [`periphery_poses`]' views relative to [`random_poses`]'.
pub const PERIPHERY_DISTANCE: f64 = 1.9;
/// Where [`periphery_poses`] puts the rig's centre: this fraction of the way from the image centre
/// to an image corner.
pub const PERIPHERY_OFFSET: f64 = 0.8;

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
    /// Error vectors (detected − true, px) of the same corners.
    pub offsets: Vec<Vector2<f64>>,
    /// True positions of the same corners.
    pub truth_uv: Vec<Vector2<f64>>,
    /// (row, col) of the same corners.
    pub labels: Vec<(usize, usize)>,
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
                offsets: Vec::new(),
                truth_uv: Vec::new(),
                labels: Vec::new(),
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
                                let t = Vector2::new(t[0], t[1]);
                                s.offsets.push(c.uv - t);
                                s.truth_uv.push(t);
                                s.labels.push((c.row, c.col));
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

/// Whether `uv` lies in the outer `fraction` of an image of `size`: within `fraction` of the width of
/// the left or right border, or within `fraction` of the height of the top or bottom border.
pub fn in_border_band(uv: &Vector2<f64>, size: [u32; 2], fraction: f64) -> bool {
    let (w, h) = (f64::from(size[0]), f64::from(size[1]));
    // Pixel centres run from 0 to w − 1: the image spans [−½, w − ½).
    let (x, y) = (uv.x + 0.5, uv.y + 0.5);
    x < fraction * w || x > (1.0 - fraction) * w || y < fraction * h || y > (1.0 - fraction) * h
}

/// The systematic part of the corner errors in a region of the image: the mean error vector in the
/// local radial frame about the image centre (radial component positive outwards; a lens-model bias
/// is radial and changes sign across the image, so a mean of raw vectors would cancel), and the RMS.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Bias {
    pub corners: usize,
    /// Mean radial component of the error (px, + outwards).
    pub radial_px: f64,
    /// Mean tangential component (px, + counter-clockwise in image coordinates).
    pub tangential_px: f64,
    /// RMS of the error (px).
    pub rms_px: f64,
}

impl Bias {
    /// Over the correctly labelled corners of the faces (fully or partly visible) seen at less than
    /// `max_angle_deg` whose true position satisfies `keep`.
    pub fn of(
        scores: &[FaceScore],
        size: [u32; 2],
        max_angle_deg: f64,
        keep: impl Fn(&Vector2<f64>) -> bool,
    ) -> Bias {
        let centre = Vector2::new(
            (f64::from(size[0]) - 1.0) / 2.0,
            (f64::from(size[1]) - 1.0) / 2.0,
        );
        let mut b = Bias::default();
        let mut sq = 0.0;
        for f in scores.iter().filter(|f| f.angle_deg < max_angle_deg) {
            for (e, t) in f.offsets.iter().zip(&f.truth_uv) {
                if !keep(t) {
                    continue;
                }
                let Some(r) = (t - centre).try_normalize(1e-9) else {
                    continue;
                };
                b.corners += 1;
                b.radial_px += e.dot(&r);
                b.tangential_px += e.x * -r.y + e.y * r.x;
                sq += e.norm_squared();
            }
        }
        if b.corners > 0 {
            let n = b.corners as f64;
            b.radial_px /= n;
            b.tangential_px /= n;
            b.rms_px = (sq / n).sqrt();
        }
        b
    }

    /// Length of the mean error vector (radial, tangential), px.
    pub fn mean_px(&self) -> f64 {
        self.radial_px.hypot(self.tangential_px)
    }
}

impl std::fmt::Display for Bias {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} corners, mean error (radial {:+.4}, tangential {:+.4}) px, |mean| {:.4} px, RMS {:.4} px",
            self.corners,
            self.radial_px,
            self.tangential_px,
            self.mean_px(),
            self.rms_px
        )
    }
}

/// Distance of `uv` from the principal point of `camera`, as a fraction of [`imaged_radius`].
pub fn relative_radius(uv: &Vector2<f64>, camera: &Camera) -> f64 {
    (uv - Vector2::new(camera.cx(), camera.cy())).norm() / imaged_radius(camera)
}

/// The largest distance from the principal point (px) at which `camera` images anything: the
/// farthest image corner, or the distortion's fold (where the radial magnification reaches 0 and
/// the renderer sees nothing beyond) if that is nearer. Radial distortion only, along the x axis.
pub fn imaged_radius(camera: &Camera) -> f64 {
    let [w, h] = camera.image_size.map(f64::from);
    let (cx, cy) = (camera.cx(), camera.cy());
    let corner = [
        (-0.5, -0.5),
        (w - 0.5, -0.5),
        (-0.5, h - 0.5),
        (w - 0.5, h - 0.5),
    ]
    .iter()
    .map(|&(x, y)| (x - cx).hypot(y - cy))
    .fold(0.0, f64::max);
    let mut previous = 0.0;
    for k in 1..=3000 {
        let r = f64::from(k) * 1e-3;
        let d = camera.distort(r, 0.0).x;
        if d <= previous {
            return corner.min(previous * camera.fx());
        }
        previous = d;
    }
    corner
}
