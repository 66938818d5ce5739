//! Poses chosen by what they teach: for every candidate stage pose (rotation, tilt) the planner
//! predicts the corners the camera would see there and the covariance the solve would reach with
//! them, and takes next the pose that most reduces the uncertainty of the parameters the verdict
//! asks for.
//!
//! ## Prediction
//! A candidate's corners are the rig's corners projected through the current camera estimate at
//! `base ∘ stage_motion(rotation, tilt)` ([`crate::render::stage_pose`]), keeping the faces whose
//! every corner is visible (in the image, front-facing, not hidden by the rig) and seen within
//! [`MAX_OBLIQUITY_DEG`] of their normal — what the detector labels reliably. The covariance is the
//! solver's own: [`crate::calib::view_information`] gives each view's reduced normal matrix `S_i`
//! (its pose eliminated), the covariance of a set of views is `σ² (P + Σ S_i)⁻¹`, where `P` is a
//! weak prior (σ of f: half of it, of the principal point: a quarter of the image, of each distortion
//! coefficient: 1) that only keeps the first poses' sums invertible.
//!
//! ## Score
//! `Σ_k (σ_k / t_k)²` over fx, fy, cx, cy, k1, k2, k3 (those estimated): `t` is
//! `plan.target_sigma_fx_rel · f` for the focal lengths, `plan.target_sigma_cx_px` for the principal
//! point and, for a distortion coefficient, the change that moves the image border by
//! [`crate::calib::UNDETERMINED_EFFECT_PX`] ([`crate::calib::determined::border_gain_of`]). The next
//! pose is the candidate not yet taken with the lowest score after adding it (greedy A-optimal design
//! in target units). The score's scale (σ² of the corners) does not change the choice.
//!
//! ## Estimates
//! The camera is a nominal pinhole (focal length 0.75 × the image width, centred) until three views
//! are accepted, then the latest solve; `base` (`cam_from_rig` at (0°, 0°)) is the nominal
//! [`crate::render::default_view`] until the first view is accepted, then recovered from the latest
//! accepted view's pose.

use nalgebra::{DMatrix, Vector3};
use serde::Serialize;

use crate::calib::{Correspondence, Fix, View};
use crate::camera::{Camera, DistortionModel, PARAM_NAMES, Pose, idx};
use crate::render::{RenderSettings, StageGeometry, ground_truth, stage_motion};
use crate::rig::Rig;

use super::coverage::Coverage;

/// Faces seen more obliquely than this (angle between their normal and the line of sight) are not
/// counted on: the detector's labelling gets unreliable toward grazing views.
pub const MAX_OBLIQUITY_DEG: f64 = 70.0;

/// A pose of the two-axis stage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StagePose {
    pub rotation_deg: f64,
    pub tilt_deg: f64,
}

/// A parameter's predicted standard deviation after the next pose.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PredictedSigma {
    pub name: &'static str,
    pub sigma: f64,
    /// The σ the plan aims for.
    pub target: f64,
}

/// The planner's choice for the next pose.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Choice {
    pub pose: StagePose,
    /// Corners predicted at that pose.
    pub corners: usize,
    /// Predicted σ of the verdict's parameters once that view is added (corner noise `sigma_px`).
    pub sigma: Vec<PredictedSigma>,
    /// The score after adding it (lower is better; see the module docs).
    pub score: f64,
    /// The predicted corners' image positions.
    #[serde(skip)]
    pub points: Vec<nalgebra::Vector2<f64>>,
}

/// The planner: a rig on a stage, the candidate poses and the σ targets.
#[derive(Debug, Clone)]
pub struct Planner {
    pub rig: Rig,
    pub geometry: StageGeometry,
    pub candidates: Vec<StagePose>,
    pub model: DistortionModel,
    pub fix: Fix,
    pub target_sigma_f_rel: f64,
    pub target_sigma_c_px: f64,
    pub min_corners: usize,
}

/// Candidate poses: rotations over `sweep_deg` (centred on 0°) and tilts over `[tilt_min, tilt_max]`,
/// each in steps of at most `step_deg`.
pub fn grid(sweep_deg: f64, tilt: Option<(f64, f64)>, step_deg: f64) -> Vec<StagePose> {
    let steps = |lo: f64, hi: f64| -> Vec<f64> {
        let n = (((hi - lo) / step_deg.max(1e-3)).ceil() as usize).max(1);
        (0..=n)
            .map(|k| lo + (hi - lo) * k as f64 / n as f64)
            .collect()
    };
    let rotations = steps(-sweep_deg / 2.0, sweep_deg / 2.0);
    let tilts = match tilt {
        Some((lo, hi)) => steps(lo, hi),
        None => vec![0.0],
    };
    let mut out = Vec::with_capacity(rotations.len() * tilts.len());
    for &t in &tilts {
        for &r in &rotations {
            out.push(StagePose {
                rotation_deg: r,
                tilt_deg: t,
            });
        }
    }
    out
}

/// The nominal camera the planner starts from: a pinhole with focal length 0.75 × the image width.
pub fn nominal_camera(image_size: [u32; 2]) -> Camera {
    let [w, h] = image_size;
    let f = 0.75 * f64::from(w);
    Camera::pinhole(
        image_size,
        f,
        f,
        (f64::from(w) - 1.0) / 2.0,
        (f64::from(h) - 1.0) / 2.0,
    )
}

impl Planner {
    /// The planner of a station configured by `cfg`, its stage tilting within `tilt_limits` (none:
    /// rotation only).
    pub fn for_station(
        cfg: &super::StationConfig,
        rig: &Rig,
        tilt_limits: Option<(f64, f64)>,
    ) -> Planner {
        let (model, fix) = cfg.solve_options("station config").map_or_else(
            |_| (DistortionModel::Brown5, Fix::default()),
            |o| (o.model, planning_fix(&o.fix)),
        );
        Planner {
            rig: rig.clone(),
            geometry: cfg.turntable.geometry(),
            candidates: grid(cfg.plan.sweep_deg, tilt_limits, cfg.plan.step_deg),
            model,
            fix,
            target_sigma_f_rel: cfg.plan.target_sigma_fx_rel,
            target_sigma_c_px: cfg.plan.target_sigma_cx_px,
            min_corners: cfg.qa.min_corners,
        }
    }

    /// `cam_from_rig` at `pose` for a stage whose (0°, 0°) view is `base`.
    pub fn cam_from_rig(&self, base: &Pose, pose: StagePose) -> Pose {
        let view = base.rotation.inverse() * Vector3::z();
        base.compose(&stage_motion(
            &self.rig,
            &view,
            &self.geometry,
            pose.rotation_deg,
            pose.tilt_deg,
        ))
    }

    /// `base` recovered from the `cam_from_rig` observed at `pose` (the line of sight taken from
    /// `guess`, the previous base).
    pub fn base_from(&self, observed: &Pose, pose: StagePose, guess: &Pose) -> Pose {
        let view = guess.rotation.inverse() * Vector3::z();
        let m = stage_motion(
            &self.rig,
            &view,
            &self.geometry,
            pose.rotation_deg,
            pose.tilt_deg,
        );
        observed.compose(&m.inverse())
    }

    /// The corners the camera would label at `cam_from_rig` (see the module docs); `None` when fewer
    /// than `min_corners`.
    pub fn predict_view(&self, camera: &Camera, cam_from_rig: &Pose) -> Option<View> {
        let gt = ground_truth(
            &self.rig,
            camera,
            cam_from_rig,
            &RenderSettings::default(),
            0,
        );
        let cos_max = MAX_OBLIQUITY_DEG.to_radians().cos();
        let mut points = Vec::new();
        for (fi, face) in self.rig.faces.iter().enumerate() {
            let corners: Vec<_> = gt.corners.iter().filter(|c| c.face_index == fi).collect();
            if corners.is_empty() || !corners.iter().all(|c| c.visible) {
                continue;
            }
            let mid = cam_from_rig.transform(&face.corner_xyz(face.rows / 2, face.cols / 2));
            let normal = cam_from_rig.rotation * face.normal();
            if -normal.dot(&mid.normalize()) < cos_max {
                continue;
            }
            for c in corners {
                let Some(uv) = c.uv else { continue };
                points.push(Correspondence {
                    xyz: Vector3::from(c.xyz),
                    uv: uv.into(),
                    cov: None,
                });
            }
        }
        (points.len() >= self.min_corners.max(6)).then(|| View {
            name: "predicted".into(),
            points,
        })
    }

    /// Reduced information of the view predicted at `pose`, if any corners are predicted there.
    fn information(
        &self,
        camera: &Camera,
        base: &Pose,
        pose: StagePose,
    ) -> Option<(Vec<&'static str>, DMatrix<f64>, View)> {
        let p = self.cam_from_rig(base, pose);
        let view = self.predict_view(camera, &p)?;
        let (names, mut infos) = crate::calib::view_information(
            camera,
            &[p],
            std::slice::from_ref(&view),
            self.model,
            &self.fix,
        )
        .ok()?;
        Some((names, infos.pop()?, view))
    }

    /// Target σ of each free parameter (∞ for those the verdict does not ask about), and the prior.
    fn targets(&self, camera: &Camera, names: &[&'static str]) -> (Vec<f64>, Vec<f64>) {
        let gain = crate::calib::determined::border_gain_of(camera);
        let [w, _] = camera.image_size;
        let f = camera.fx();
        names
            .iter()
            .map(|name| {
                let k = PARAM_NAMES.iter().position(|n| n == name);
                let distortion_target = |k: usize| {
                    gain.map(|g| crate::calib::UNDETERMINED_EFFECT_PX / g[k].max(1e-12))
                        .unwrap_or(f64::INFINITY)
                };
                match k {
                    Some(idx::FX) | Some(idx::FY) => (self.target_sigma_f_rel * f, 0.5 * f),
                    Some(idx::CX) | Some(idx::CY) => (self.target_sigma_c_px, 0.25 * f64::from(w)),
                    Some(k @ (idx::K1 | idx::K2 | idx::K3)) => (distortion_target(k), 1.0),
                    // aspect-tied focal length "f", tangential terms, skew and the rest
                    _ if *name == "f" => (self.target_sigma_f_rel * f, 0.5 * f),
                    _ => (f64::INFINITY, 1.0),
                }
            })
            .unzip()
    }

    /// The next pose: the candidate not in `taken` whose predicted view most lowers the score of
    /// `taken` plus it (see the module docs); `None` when no candidate shows enough corners.
    /// `sigma_px` is the corner noise per coordinate the σ are predicted for.
    pub fn next(
        &self,
        camera: &Camera,
        base: &Pose,
        taken: &[StagePose],
        tried: &[StagePose],
        sigma_px: f64,
    ) -> Option<Choice> {
        let mut sum: Option<DMatrix<f64>> = None;
        for &p in taken {
            if let Some((_, s, _)) = self.information(camera, base, p) {
                sum = Some(match sum {
                    Some(acc) => acc + s,
                    None => s,
                });
            }
        }
        let mut best: Option<Choice> = None;
        for &cand in &self.candidates {
            if taken.iter().chain(tried).any(|t| t == &cand) {
                continue;
            }
            let Some((n, s, view)) = self.information(camera, base, cand) else {
                continue;
            };
            let (targets, prior) = self.targets(camera, &n);
            let mut total = match &sum {
                Some(acc) => acc + &s,
                None => s,
            };
            for (k, p) in prior.iter().enumerate() {
                total[(k, k)] += (sigma_px / p).powi(2);
            }
            let Some(cov) = total.cholesky().map(|c| c.inverse() * sigma_px.powi(2)) else {
                continue;
            };
            let mut score = 0.0;
            let mut sigma = Vec::new();
            for (k, name) in n.iter().enumerate() {
                let sd = cov[(k, k)].max(0.0).sqrt();
                if targets[k].is_finite() {
                    score += (sd / targets[k]).powi(2);
                    sigma.push(PredictedSigma {
                        name,
                        sigma: sd,
                        target: targets[k],
                    });
                }
            }
            if best.as_ref().is_none_or(|b| score < b.score) {
                best = Some(Choice {
                    pose: cand,
                    corners: view.points.len(),
                    sigma,
                    score,
                    points: view.points.iter().map(|p| p.uv).collect(),
                });
            }
        }
        best
    }
}

/// A stage pose the run did not reach that would put corners into empty coverage cells.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Placement {
    pub pose: StagePose,
    /// Where the rig would appear (3×3 division of the image, [`Coverage::region_of`]).
    pub region: &'static str,
    /// How many cells still empty before it it would cover.
    pub cells: usize,
}

impl Planner {
    /// The placements missing from `coverage`: greedily, up to `max` candidates that each cover the
    /// most cells still empty (after the ones before them), at least one cell each. What a station
    /// without a tilt axis tells the operator it lacks.
    pub fn missing_placements(
        &self,
        camera: &Camera,
        base: &Pose,
        coverage: &Coverage,
        max: usize,
    ) -> Vec<Placement> {
        let predicted: Vec<(StagePose, Vec<nalgebra::Vector2<f64>>)> = (self.candidates.iter())
            .filter_map(|&pose| {
                let view = self.predict_view(camera, &self.cam_from_rig(base, pose))?;
                Some((pose, view.points.iter().map(|p| p.uv).collect()))
            })
            .collect();
        let mut coverage = coverage.clone();
        let mut out = Vec::new();
        while out.len() < max {
            let best = (predicted.iter())
                .map(|(pose, pts)| (pose, pts, coverage.newly_covered(pts)))
                .filter(|c| c.2 > 0)
                // most cells; among equals the smaller motion (the first candidate closest to rest)
                .max_by(|a, b| {
                    let rest = |p: &StagePose| -(p.rotation_deg.abs() + p.tilt_deg.abs());
                    (a.2, rest(a.0))
                        .partial_cmp(&(b.2, rest(b.0)))
                        .unwrap_or(std::cmp::Ordering::Equal)
                });
            let Some((pose, pts, cells)) = best else {
                break;
            };
            let n = pts.len().max(1) as f64;
            let mean = pts.iter().sum::<nalgebra::Vector2<f64>>() / n;
            out.push(Placement {
                pose: *pose,
                region: coverage.region_of(&mean),
                cells,
            });
            for p in pts {
                coverage.add(p);
            }
        }
        out
    }
}

/// What a station without a tilt axis says it is missing: the empty cells, and the placements (on a
/// cradle tilted within `tilt_limits`, the rig `geometry` as configured) that would fill them, in
/// words. `views` are the accepted views' `cam_from_rig` with the turntable angle each was taken at;
/// `None` when nothing is missing or no view is at hand.
pub fn missing_without_tilt(
    planner: &Planner,
    camera: &Camera,
    views: &[(Pose, f64)],
    coverage: &Coverage,
) -> Option<String> {
    if coverage.covered() == coverage.total() {
        return None;
    }
    // The view nearest 0° gives the stage's rest pose: there the motion is the identity whatever the
    // geometry.
    let (observed, angle) = (views.iter()).min_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    let at = StagePose {
        rotation_deg: *angle,
        tilt_deg: 0.0,
    };
    let base = planner.base_from(observed, at, observed);
    let placements = planner.missing_placements(camera, &base, coverage, 4);
    let empty = coverage.total() - coverage.covered();
    let mut s = format!(
        "without a tilt axis the rig reached {} of the {} coverage cells ({empty} empty{})",
        coverage.covered(),
        coverage.total(),
        match coverage.empty_regions() {
            e if e.is_empty() => String::new(),
            e => format!(": {}", e.join(", ")),
        }
    );
    if placements.is_empty() {
        s.push_str("; no tilted placement of this rig within the cradle limits would fill them: move the camera or the rig closer");
        return Some(s);
    }
    s.push_str("; the placements missing, on a cradle tilting the table (turntable.tilt) or the cube propped by hand: ");
    let words: Vec<String> = placements
        .iter()
        .map(|p| {
            let t = p.pose.tilt_deg.round();
            let tilt = if t.abs() < 0.5 {
                "level".to_string()
            } else {
                format!(
                    "its top tilted {} by about {:.0}°",
                    if t < 0.0 {
                        "toward the camera"
                    } else {
                        "away from the camera"
                    },
                    t.abs()
                )
            };
            format!(
                "turned to {:+.0}° with {tilt} ({}, {} empty cell(s))",
                p.pose.rotation_deg.round(),
                p.region,
                p.cells
            )
        })
        .collect();
    s.push_str(&words.join("; "));
    Some(s)
}

/// The model and fixes the planner predicts for: the solve's, with k3 estimated (the plan aims to
/// determine it).
pub fn planning_fix(fix: &Fix) -> Fix {
    Fix {
        k3: false,
        ..fix.clone()
    }
}

/// A run's planning state: the planner, the current estimates of the camera and of `base`, and
/// the poses tried and accepted so far (see the module docs).
#[derive(Debug)]
pub struct Planning {
    planner: Planner,
    image_size: [u32; 2],
    camera: Camera,
    base: Pose,
    opts: Option<crate::calib::SolveOptions>,
    sigma_px: f64,
    tried: Vec<StagePose>,
    taken: Vec<(StagePose, View)>,
}

/// Corner noise assumed before a solve measures it (px per coordinate).
pub const DEFAULT_SIGMA_PX: f64 = 0.1;

impl Planning {
    /// Planning for a run of `spec` on a stage with `turntable`'s tilt limits.
    pub fn new(
        spec: &super::RunSpec<'_>,
        info: &crate::capture::SourceInfo,
        turntable: &dyn crate::turntable::Turntable,
    ) -> Planning {
        let cfg = spec.config;
        let image_size = [info.width, info.height];
        let opts = cfg.solve_options("station config").ok().map(|mut o| {
            o.fix = planning_fix(&o.fix);
            o
        });
        let limits = turntable.tilt_limits().map(|(a, b)| (a.0, b.0));
        let planner = Planner::for_station(cfg, spec.rig, limits);
        let camera = nominal_camera(image_size);
        let base = crate::render::default_view(spec.rig, &camera);
        Planning {
            planner,
            image_size,
            camera,
            base,
            opts,
            sigma_px: DEFAULT_SIGMA_PX,
            tried: Vec::new(),
            taken: Vec::new(),
        }
    }

    /// The next pose to try (remembered as tried), or `None` when no untried candidate shows the rig.
    pub fn choose(&mut self) -> Option<Choice> {
        let taken: Vec<StagePose> = self.taken.iter().map(|t| t.0).collect();
        let choice =
            self.planner
                .next(&self.camera, &self.base, &taken, &self.tried, self.sigma_px)?;
        self.tried.push(choice.pose);
        Some(choice)
    }

    /// A view was accepted at `pose`: update the estimates of the camera (a solve once three views
    /// are in) and of `base`.
    pub fn accepted(&mut self, pose: StagePose, view: &View) {
        self.taken.push((pose, view.clone()));
        if self.taken.len() >= 3
            && let Some(opts) = &self.opts
        {
            let views: Vec<View> = self.taken.iter().map(|t| t.1.clone()).collect();
            match crate::calib::solve(&views, self.image_size, opts) {
                Ok(cal) => {
                    self.camera = cal.camera.clone();
                    self.sigma_px = cal.sigma_px.max(0.01);
                    if let Some(v) = cal.views.last() {
                        self.base = self.planner.base_from(&v.cam_from_rig, pose, &self.base);
                    }
                    return;
                }
                Err(e) => {
                    tracing::debug!(error = %e, "planning solve failed; keeping the estimates")
                }
            }
        }
        match crate::calib::pose::solve_pose(&self.camera, view) {
            Ok(fit) => self.base = self.planner.base_from(&fit.cam_from_rig, pose, &self.base),
            Err(e) => {
                tracing::debug!(error = %e, "planning pose failed; keeping the base estimate")
            }
        }
    }
}

/// How far (degrees, on either axis) a hand-placed stage may be from its prompt before the station
/// asks again.
pub const PROMPT_TOLERANCE_DEG: f64 = 5.0;

/// The stage pose an operator actually reached, as far as a view tells, when it is not the prompted
/// one.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Misplaced {
    /// The pose (within ±20° of the prompt on each axis, 5° steps) that best explains the view.
    pub looks_like: StagePose,
    /// Mean distance (px) between the view's corners and where the prompted pose puts them.
    pub off_px: f64,
    /// Where the rig appears, and where the prompt wanted it (3×3 division of the image).
    pub appears: &'static str,
    pub wanted: &'static str,
}

impl Planning {
    /// Whether `view`, taken after the operator confirmed `pose`, shows the rig where that pose puts
    /// it: `Some` when a pose more than [`PROMPT_TOLERANCE_DEG`] away on an axis explains its
    /// corners better. Nothing is judged before a view has placed the stage (the first pose).
    pub fn misplaced(
        &self,
        pose: StagePose,
        view: &View,
        coverage: &Coverage,
    ) -> Option<Misplaced> {
        if self.taken.is_empty() || view.points.is_empty() {
            return None;
        }
        let off = |p: StagePose| -> Option<f64> {
            let cam_from_rig = self.planner.cam_from_rig(&self.base, p);
            let mut sum = 0.0;
            for c in &view.points {
                let uv = self
                    .camera
                    .project_cam(&cam_from_rig.transform(&c.xyz))
                    .ok()?;
                sum += (uv - c.uv).norm();
            }
            Some(sum / view.points.len() as f64)
        };
        let at_prompt = off(pose)?;
        let mut best = (pose, at_prompt);
        // ±40° on each axis in 5° steps: wide enough for a forgotten tilt (the planner asks for
        // up to ±30°, and the cradle left level must be among the poses tried).
        let steps: Vec<f64> = (-8..=8).map(|k| 5.0 * f64::from(k)).collect();
        for &dr in &steps {
            for &dt in &steps {
                let p = StagePose {
                    rotation_deg: pose.rotation_deg + dr,
                    tilt_deg: pose.tilt_deg + dt,
                };
                if let Some(d) = off(p)
                    && d < best.1
                {
                    best = (p, d);
                }
            }
        }
        let (looks_like, _) = best;
        if (looks_like.rotation_deg - pose.rotation_deg).abs() <= PROMPT_TOLERANCE_DEG
            && (looks_like.tilt_deg - pose.tilt_deg).abs() <= PROMPT_TOLERANCE_DEG
        {
            return None;
        }
        let mean = |pts: &mut dyn Iterator<Item = nalgebra::Vector2<f64>>| {
            let (s, n) = pts.fold((nalgebra::Vector2::zeros(), 0usize), |(s, n), p| {
                (s + p, n + 1)
            });
            s / n.max(1) as f64
        };
        let seen = mean(&mut view.points.iter().map(|c| c.uv));
        let cam_from_rig = self.planner.cam_from_rig(&self.base, pose);
        let wanted = mean(&mut (view.points.iter()).filter_map(|c| {
            self.camera
                .project_cam(&cam_from_rig.transform(&c.xyz))
                .ok()
        }));
        Some(Misplaced {
            looks_like,
            off_px: at_prompt,
            appears: coverage.region_of(&seen),
            wanted: coverage.region_of(&wanted),
        })
    }
}

impl Misplaced {
    /// In words, for the operator's next prompt and the rejected view's reason.
    pub fn words(&self, tilt: bool) -> String {
        let mut s = format!(
            "the rig is not where the prompt puts it (its corners are {:.0} px off; it looks turned to about {:+.0}°",
            self.off_px,
            self.looks_like.rotation_deg.round()
        );
        if tilt {
            s.push_str(&format!(
                " with the cradle at about {:+.0}°",
                self.looks_like.tilt_deg.round()
            ));
        }
        s.push(')');
        if self.appears != self.wanted {
            s.push_str(&format!(
                ": it appears in the {} of the image, the pose wants it in the {}",
                self.appears, self.wanted
            ));
        }
        s
    }
}

/// A pose in plain words for the person moving a manual stage: the rotation mark, the tilt as a
/// motion ("tilt the top of the cube toward the camera by about 20°") and, when the planner
/// predicted where the rig will appear, that image region and how many empty coverage cells it
/// fills. A positive tilt turns the top of the rig away from the camera ([`crate::render::stage_pose`]).
pub fn instruction(pose: StagePose, tilt: bool, target: Option<(&str, usize)>) -> String {
    // Marks are whole degrees (manual::MANUAL_RESOLUTION), rounded as the stage rounds them.
    let mut s = format!(
        "turn the turntable to the {:+.0}° mark",
        pose.rotation_deg.round()
    );
    if tilt {
        let t = pose.tilt_deg.round();
        if t.abs() < 0.5 {
            s.push_str(" and level the cradle (0°)");
        } else {
            s.push_str(&format!(
                " and tilt the top of the cube {} by about {:.0}° (cradle mark {:+.0}°)",
                if t < 0.0 {
                    "toward the camera"
                } else {
                    "away from the camera"
                },
                t.abs(),
                t
            ));
        }
    }
    if let Some((region, cells)) = target {
        s.push_str(&format!(
            ": this moves the rig toward the {region} of the image{}",
            if cells > 0 {
                format!(", where {cells} coverage cell(s) are still empty")
            } else {
                String::new()
            }
        ));
    }
    s.push_str("; hold it still, then confirm");
    s
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    #[test]
    fn grid_spans_both_axes_in_even_steps() {
        let g = grid(60.0, Some((-30.0, 30.0)), 10.0);
        assert_eq!(g.len(), 49);
        assert_eq!(
            g[0],
            StagePose {
                rotation_deg: -30.0,
                tilt_deg: -30.0
            }
        );
        assert_eq!(
            g[48],
            StagePose {
                rotation_deg: 30.0,
                tilt_deg: 30.0
            }
        );
        assert_eq!(grid(60.0, None, 10.0).len(), 7);
    }

    #[test]
    fn instructions_name_the_motion_and_the_image_region() {
        let p = StagePose {
            rotation_deg: 22.5,
            tilt_deg: -20.0,
        };
        assert_eq!(
            instruction(p, true, Some(("top-left", 3))),
            "turn the turntable to the +23° mark and tilt the top of the cube toward the camera by about 20° (cradle mark -20°): this moves the rig toward the top-left of the image, where 3 coverage cell(s) are still empty; hold it still, then confirm"
        );
        assert_eq!(
            instruction(p, false, None),
            "turn the turntable to the +23° mark; hold it still, then confirm"
        );
    }

    /// A one-axis sweep leaves cells empty; the placements named as missing are tilted and, rendered
    /// with the true camera (ground truth), put corners into cells the sweep left empty.
    #[test]
    fn missing_placements_are_tilted_and_fill_the_empty_cells() {
        let rig = Rig::from_toml_str(
            include_str!("../../fixtures/rigs/cube_outside.toml"),
            "cube_outside.toml",
        )
        .unwrap()
        .0;
        let truth = Camera::pinhole([1280, 960], 1100.0, 1100.0, 641.0, 478.0)
            .with_distortion(DistortionModel::Brown5, &[-0.2, 0.05, 0.0, 0.0, 0.0]);
        let base = crate::render::default_view(&rig, &truth);
        let planner = Planner {
            rig: rig.clone(),
            geometry: StageGeometry {
                rig_offset_mm: 300.0,
                tilt_pivot_mm: 300.0,
            },
            candidates: grid(60.0, Some((-30.0, 30.0)), 10.0),
            model: DistortionModel::Brown5,
            fix: Fix::default(),
            target_sigma_f_rel: 2e-4,
            target_sigma_c_px: 0.5,
            min_corners: 20,
        };
        let corners_at = |pose: StagePose| -> Vec<nalgebra::Vector2<f64>> {
            let p = planner.cam_from_rig(&base, pose);
            let gt = ground_truth(&rig, &truth, &p, &RenderSettings::default(), 0);
            gt.visible().filter_map(|c| c.uv.map(Into::into)).collect()
        };
        let mut coverage = Coverage::new(1280, 960, [8, 6]);
        for r in [-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0] {
            for uv in corners_at(StagePose {
                rotation_deg: r,
                tilt_deg: 0.0,
            }) {
                coverage.add(&uv);
            }
        }
        let before = coverage.covered();
        assert!(
            before < coverage.total(),
            "the level sweep left no cell empty"
        );
        let missing = planner.missing_placements(&truth, &base, &coverage, 4);
        assert!(!missing.is_empty());
        assert!(
            missing.iter().all(|m| m.pose.tilt_deg != 0.0),
            "{missing:?}"
        );
        let mut after = coverage.clone();
        for m in &missing {
            for uv in corners_at(m.pose) {
                after.add(&uv);
            }
        }
        let claimed: usize = missing.iter().map(|m| m.cells).sum();
        let filled = after.covered() - before;
        assert!(
            filled + 2 >= claimed && filled >= 4,
            "{missing:?}: claimed {claimed} cells, ground truth fills {filled}"
        );
        let text = missing_without_tilt(
            &planner,
            &truth,
            &[(
                planner.cam_from_rig(
                    &base,
                    StagePose {
                        rotation_deg: 0.0,
                        tilt_deg: 0.0,
                    },
                ),
                0.0,
            )],
            &coverage,
        )
        .unwrap();
        assert!(
            text.starts_with(&format!(
                "without a tilt axis the rig reached {before} of the 48"
            )) && text.contains("its top tilted"),
            "{text}"
        );
    }

    #[test]
    fn a_stage_at_rest_is_the_one_axis_turntable() {
        let rig = Rig::from_toml_str(
            include_str!("../../fixtures/rigs/cube_outside.toml"),
            "cube_outside.toml",
        )
        .unwrap()
        .0;
        let camera = nominal_camera([1280, 960]);
        let base = crate::render::default_view(&rig, &camera);
        let a = crate::render::stage_pose(&rig, &base, &StageGeometry::default(), 25.0, 0.0);
        let b = crate::render::turned(&rig, &base, 25.0);
        assert!((a.rotation.matrix() - b.rotation.matrix()).norm() < 1e-12);
        assert!((a.translation - b.translation).norm() < 1e-9);
        // with an offset, turning moves the rig sideways in the image; tilting moves it vertically
        let g = StageGeometry {
            rig_offset_mm: 300.0,
            tilt_pivot_mm: 300.0,
        };
        let c = rig.centre();
        let at = |r, t| {
            let p = crate::render::stage_pose(&rig, &base, &g, r, t).transform(&c);
            camera.project_cam(&p).unwrap()
        };
        let (o, turned, tilted) = (at(0.0, 0.0), at(20.0, 0.0), at(0.0, 20.0));
        assert!((turned.x - o.x).abs() > 100.0 && (turned.y - o.y).abs() < (turned.x - o.x).abs());
        assert!(
            (tilted.y - o.y).abs() > 50.0 && (tilted.x - o.x).abs() < (tilted.y - o.y).abs(),
            "centre at {o:?}, turned 20°: {turned:?}, tilted 20°: {tilted:?}"
        );
    }
}
