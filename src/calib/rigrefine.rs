//! Rig refinement: estimate the as-built rig (each face's pose relative to a reference face) jointly
//! with the camera, and refuse a rig file that does not describe the printed rig.
//!
//! ## Model
//! A hand-built cube has its boards glued a millimetre off and tilted a fraction of a degree. Each
//! non-reference face `f` carries a rigid correction about its nominal centre `c_f` (the centre of its
//! inner-corner grid in the rig file):
//!
//! `X' = c_f + R_f (X − c_f) + t_f`
//!
//! where `X` is the corner's position in the rig file. The reference face keeps `R = I, t = 0`: with the
//! per-view poses this fixes the gauge (six rigid degrees of freedom), and the square sizes fix the scale.
//! The projection is `u = π(θ, R_i X' + t_i)` with the intrinsics `θ` of [`super::solve`].
//!
//! ## Jacobians
//! Rotations are updated on the left (`R ← exp([δ]ₓ) R`) for both the views and the faces, translations
//! additively. With `a = R_f (X − c_f)`, `∂X'/∂δω_f = −[a]ₓ`, `∂X'/∂δt_f = I`, and
//! `∂u/∂(δω_f, δt_f) = J_pt R_i [−[a]ₓ | I]`, with `J_pt = ∂u/∂X_cam` from the camera model.
//! `tests` checks every block against central differences.
//!
//! ## Normal equations
//! The *shared* block is the free intrinsics plus six parameters per refined face (≤ 13 + 6·(F − 1);
//! 25 for a three-face cube); it plays the role the intrinsics play in [`super::solve`]. The normal matrix
//! keeps its arrow shape, so the problem hands its blocks to the Levenberg–Marquardt machinery that
//! [`super::solve`] uses too (`lm_core.rs`: Schur complement, damping loop, covariance). A point touches
//! only the intrinsics and its own face's block, so the accumulation updates only those sub-blocks.
//!
//! ## When the data do not determine the rig
//! A face's pose relative to the reference is seen only in views that show it together with an already
//! placed face. [`solve_rig`] refuses ([`CalibError::Unobservable`], naming the face) when a face is not
//! connected to the reference through such views, when it is seen with another face in fewer than
//! [`RigRefineOptions::min_views_per_face`] views, and when the covariance at the optimum leaves its
//! offset or tilt more uncertain than the options allow. Faces with no observations at all are kept as
//! in the rig file and reported as not refined.
//!
//! ## A rig file that is wrong, not just imprecise
//! A correction larger than [`RigRefineOptions::max_offset_mm`] / [`RigRefineOptions::max_tilt_deg`]
//! (a board glued a quarter turn off, a wrong face position), or a face whose residual RMS after
//! refinement stays above [`RigRefineOptions::max_face_rms_ratio`] times that of the other faces (a wrong
//! square size, a board that is not flat: no rigid motion explains it) is refused with
//! [`CalibError::RigMismatch`], naming the face.

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};
use tracing::{debug, info};

use super::init::{InitMethod, initialise};
use super::lm::{ParamMap, apply_fixes};
#[cfg(test)]
use super::lm_core::Vec6;
use super::lm_core::{
    BlockProblem, Mat2x6, Normal, Step, levenberg_marquardt, rigid_jacobian, update_poses,
    update_rigid,
};
use super::{
    CalibError, Calibration, Correspondence, Loss, SolveOptions, Termination, View, ViewResult,
    validate_views,
};
use crate::camera::{Camera, N_INTRINSIC, Pose};
use crate::rig::{CornerId, Face, Rig};

/// One observed rig corner: which corner, and where it was seen (px, centre convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigPoint {
    pub corner: CornerId,
    pub uv: Vector2<f64>,
    /// The detector's own standard deviation of each coordinate (px), when it gives one: the yardstick
    /// for whether the refined rig explains the corners (see [`RigRefineOptions::max_sigma_ratio`]).
    pub sigma_px: Option<f64>,
    /// The detector's covariance of `uv` (px²), when it gives one; carried to [`RigView::to_view`].
    pub cov: Option<nalgebra::Matrix2<f64>>,
}

/// The labelled corners of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct RigView {
    pub name: String,
    pub points: Vec<RigPoint>,
}

impl RigView {
    /// Recover the corner labels of an ordinary view made against `rig` (e.g. an observations file the
    /// station wrote): each point's `xyz` must be one of the rig's corners (within 1e-6 mm).
    pub fn from_view(view: &View, rig: &Rig) -> Result<RigView, CalibError> {
        let mut index: Vec<(CornerId, Vector3<f64>)> = rig
            .corners()
            .filter_map(|c| rig.corner_xyz(c.face, c.row, c.col).map(|x| (c, x)))
            .collect();
        index.sort_by(|a, b| a.1.x.total_cmp(&b.1.x));
        let points = view
            .points
            .iter()
            .enumerate()
            .map(|(j, p)| {
                let lo = index.partition_point(|(_, x)| x.x < p.xyz.x - 1e-6);
                index[lo..]
                    .iter()
                    .take_while(|(_, x)| x.x <= p.xyz.x + 1e-6)
                    .find(|(_, x)| (x - p.xyz).norm() <= 1e-6)
                    .map(|&(corner, _)| RigPoint {
                        corner,
                        uv: p.uv,
                        sigma_px: p.cov.map(|c| (c.trace() / 2.0).sqrt()),
                        cov: p.cov,
                    })
                    .ok_or_else(|| {
                        CalibError::InvalidOption {
                            reason: format!(
                                "point {j} at [{}, {}, {}] mm is not a corner of rig '{}'",
                                p.xyz.x, p.xyz.y, p.xyz.z, rig.name
                            ),
                        }
                        .in_view(&view.name)
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(RigView {
            name: view.name.clone(),
            points,
        })
    }

    /// The view with the corners at their positions in `rig` (for the ordinary solver).
    pub fn to_view(&self, rig: &Rig) -> Result<View, CalibError> {
        let points = self
            .points
            .iter()
            .enumerate()
            .map(|(j, p)| {
                rig.corner_xyz(p.corner.face, p.corner.row, p.corner.col)
                    .map(|xyz| Correspondence {
                        xyz,
                        uv: p.uv,
                        cov: p.cov,
                    })
                    .ok_or_else(|| {
                        CalibError::InvalidOption {
                            reason: format!(
                                "point {j}: corner (face {}, row {}, col {}) is not on rig '{}'",
                                p.corner.face, p.corner.row, p.corner.col, rig.name
                            ),
                        }
                        .in_view(&self.name)
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(View {
            name: self.name.clone(),
            points,
        })
    }
}

/// Options for [`solve_rig`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigRefineOptions {
    /// Camera model, fixes and loss, as for [`super::solve`]. Outlier rejection is not supported here.
    pub solve: SolveOptions,
    /// The face that fixes the gauge (index into the rig's faces). `None`: the face with the most
    /// observations.
    pub reference_face: Option<usize>,
    /// A refined face must be seen together with another face in at least this many views.
    pub min_views_per_face: usize,
    /// A face counts as seen in a view with at least this many corners.
    pub min_points_per_face: usize,
    /// A correction moving a face's centre farther than this (mm) means the rig file is wrong.
    pub max_offset_mm: f64,
    /// A correction rotating a face by more than this (degrees) means the rig file is wrong.
    pub max_tilt_deg: f64,
    /// A face whose residual RMS exceeds this multiple of the other faces' RMS does not fit any rigid
    /// correction (wrong square size, warped board).
    pub max_face_rms_ratio: f64,
    /// When the detector gives per-corner σ: a fit whose noise estimate exceeds this multiple of the
    /// detector's median σ does not explain the corners; the face without which it would is named.
    pub max_sigma_ratio: f64,
    /// Refuse when the data leave a face's offset this uncertain (σ, mm, any axis).
    pub max_offset_std_mm: f64,
    /// Refuse when the data leave a face's rotation this uncertain (σ, degrees, any axis).
    pub max_tilt_std_deg: f64,
}

impl Default for RigRefineOptions {
    fn default() -> Self {
        RigRefineOptions {
            solve: SolveOptions::default(),
            reference_face: None,
            min_views_per_face: 3,
            min_points_per_face: 6,
            max_offset_mm: 5.0,
            max_tilt_deg: 3.0,
            max_face_rms_ratio: 2.0,
            max_sigma_ratio: 3.0,
            max_offset_std_mm: 0.5,
            max_tilt_std_deg: 0.25,
        }
    }
}

/// The estimated as-built pose of one face relative to the rig file.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceCorrection {
    pub face: usize,
    pub name: String,
    /// Whether the face was estimated (false for the reference face and for unobserved faces).
    pub refined: bool,
    /// Nominal centre of the face's inner-corner grid (rig frame, mm): the correction rotates about it.
    pub centre: Vector3<f64>,
    /// `R_f` of the module docs.
    pub rotation: Rotation3<f64>,
    /// `t_f` of the module docs (rig frame, mm): the displacement of the face centre.
    pub translation_mm: Vector3<f64>,
    /// The displacement in the face's own axes: along its rows (`col_dir`), along its columns
    /// (`row_dir`), out of its plane (normal), mm.
    pub offset_mm: [f64; 3],
    pub offset_std_mm: [f64; 3],
    /// The rotation vector in the face's axes (about `col_dir`, `row_dir`, normal), degrees.
    pub rotation_deg: [f64; 3],
    pub rotation_std_deg: [f64; 3],
    /// Residual RMS over this face's points (components, px), and their number.
    pub rms_px: f64,
    pub n_points: usize,
}

impl FaceCorrection {
    /// Out-of-plane tilt (degrees): the rotation about the face's in-plane axes.
    pub fn tilt_deg(&self) -> f64 {
        self.rotation_deg[0].hypot(self.rotation_deg[1])
    }

    /// Total rotation angle (degrees).
    pub fn angle_deg(&self) -> f64 {
        self.rotation.angle().to_degrees()
    }

    /// The `[faces.survey]` record of a surveyed rig file.
    pub fn to_survey(&self) -> crate::rig::survey::FaceSurvey {
        crate::rig::survey::FaceSurvey {
            refined: self.refined,
            offset_mm: self.offset_mm,
            offset_std_mm: self.offset_std_mm,
            rotation_deg: self.rotation_deg,
            rotation_std_deg: self.rotation_std_deg,
            rms_px: if self.rms_px.is_finite() {
                self.rms_px
            } else {
                0.0
            },
            n_points: self.n_points,
        }
    }

    /// "side-x: 0.62 mm along its rows, 0.98 mm along its columns, 0.10 mm out of its plane, tilted
    /// 0.04°, turned 0.01° in its plane".
    pub fn describe(&self) -> String {
        if !self.refined {
            return format!("{}: as in the rig file (not refined)", self.name);
        }
        let [a, b, n] = self.offset_mm;
        format!(
            "{}: {a:+.3} mm along its rows, {b:+.3} mm along its columns, {n:+.3} mm out of its plane, \
             tilted {:.3}°, turned {:+.3}° in its plane",
            self.name,
            self.tilt_deg(),
            self.rotation_deg[2]
        )
    }
}

/// A calibration with the rig refined.
#[derive(Debug, Clone)]
pub struct RigCalibration {
    /// The camera, views and uncertainty; `covariance` and `std_dev` are marginal over the rig.
    pub calibration: Calibration,
    pub reference_face: usize,
    /// One entry per rig face, in the rig's order.
    pub faces: Vec<FaceCorrection>,
    /// The rig as built: the input rig with every refined face moved by its correction.
    pub rig: Rig,
    /// Neighbour correlation of the residuals and the variance inflation applied to the covariance
    /// (see [`inflate_for_neighbour_correlation`]).
    pub noise_correlation: NoiseCorrelation,
}

/// Correlation of the residuals of neighbouring corners, and the variance inflation it implies.
///
/// ## Why
/// The detector fits each corner in a window that overlaps its neighbours' windows, so the same image
/// noise moves neighbouring corners together: measured over 50 re-noised hard renders, the corner noise
/// correlates +0.30 with the neighbour along a row and +0.06 along a column (`examples/sigma_coverage`).
/// Least squares that assumes independent corners then reports σ too small.
///
/// ## Derivation
/// With corner noise covariance `σ² (I + ρ_r A_r + ρ_c A_c)` (`A` the neighbour adjacency), the
/// least-squares covariance is the sandwich `σ² (JᵀJ)⁻¹ Jᵀ(I + ρ_r A_r + ρ_c A_c)J (JᵀJ)⁻¹`. For the
/// intrinsics, whose Jacobian rows change slowly from a corner to its neighbour, `Jᵀ A J ≈ (2m/n) JᵀJ`
/// with `m` neighbour pairs among `n` corners, so the covariance is `σ² (JᵀJ)⁻¹` times
/// `1 + 2 (ρ_r m_r + ρ_c m_c) / n`. `ρ` is estimated from the fit's own residuals (their correlation
/// underestimates the noise's by about p/n, a few per cent here). The factor is held at ≥ 1: a negative
/// estimate is not trusted to shrink σ.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NoiseCorrelation {
    /// Residual correlation between neighbours along a row (same row, adjacent columns).
    pub along_rows: f64,
    /// Residual correlation between neighbours along a column.
    pub along_columns: f64,
    /// The factor applied to the covariance (σ grows by its square root).
    pub variance_factor: f64,
}

/// Measure the neighbour correlation of `cal`'s residuals (views in the order of `views`, corner
/// positions from `rig`) and scale `cal`'s covariance and standard deviations by the variance factor
/// of [`NoiseCorrelation`].
pub fn inflate_for_neighbour_correlation(
    cal: &mut Calibration,
    views: &[RigView],
    rig: &Rig,
) -> NoiseCorrelation {
    use std::collections::HashMap;
    let (mut srow, mut aarow, mut bbrow, mut nrow) = (0.0, 0.0, 0.0, 0usize);
    let (mut scol, mut aacol, mut bbcol, mut ncol) = (0.0, 0.0, 0.0, 0usize);
    let mut n = 0usize;
    for (v, vr) in views.iter().zip(&cal.views) {
        let res: HashMap<CornerId, Vector2<f64>> = v
            .points
            .iter()
            .filter_map(|p| {
                let x = rig.corner_xyz(p.corner.face, p.corner.row, p.corner.col)?;
                let uv = cal.camera.project(&vr.cam_from_rig, &x).ok()?;
                Some((p.corner, uv - p.uv))
            })
            .collect();
        n += res.len();
        for (c, a) in &res {
            let right = CornerId {
                col: c.col + 1,
                ..*c
            };
            if let Some(b) = res.get(&right) {
                srow += a.dot(b);
                aarow += a.norm_squared();
                bbrow += b.norm_squared();
                nrow += 1;
            }
            let below = CornerId {
                row: c.row + 1,
                ..*c
            };
            if let Some(b) = res.get(&below) {
                scol += a.dot(b);
                aacol += a.norm_squared();
                bbcol += b.norm_squared();
                ncol += 1;
            }
        }
    }
    let corr = |s: f64, a: f64, b: f64| {
        let d = (a * b).sqrt();
        if d > 0.0 { s / d } else { 0.0 }
    };
    let along_rows = corr(srow, aarow, bbrow);
    let along_columns = corr(scol, aacol, bbcol);
    let variance_factor = if n > 0 {
        (1.0 + 2.0 * (along_rows * nrow as f64 + along_columns * ncol as f64) / n as f64).max(1.0)
    } else {
        1.0
    };
    let k = variance_factor.sqrt();
    cal.covariance *= variance_factor;
    cal.std_dev.iter_mut().for_each(|s| *s *= k);
    for v in &mut cal.views {
        v.rotation_std_rad.iter_mut().for_each(|s| *s *= k);
        v.translation_std.iter_mut().for_each(|s| *s *= k);
    }
    NoiseCorrelation {
        along_rows,
        along_columns,
        variance_factor,
    }
}

/// Per-face correction state: `X' = c + R (X − c) + t`.
#[derive(Debug, Clone, Copy)]
struct FaceState {
    rotation: Rotation3<f64>,
    translation: Vector3<f64>,
}

impl FaceState {
    fn identity() -> FaceState {
        FaceState {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }
}

/// Centre of a face's inner-corner grid.
fn face_centre(f: &Face) -> Vector3<f64> {
    f.origin
        + f.col_dir * (0.5 * (f.cols as f64 - 1.0) * f.square_mm)
        + f.row_dir * (0.5 * (f.rows as f64 - 1.0) * f.square_mm)
}

/// Residual of one point with its Jacobians: full intrinsics (2×13), view pose (2×6, left update),
/// face correction (2×6, left rotation update about the face centre, additive translation).
fn point_jacobians(
    camera: &Camera,
    pose: &Pose,
    face: &FaceState,
    centre: &Vector3<f64>,
    xnom: &Vector3<f64>,
    uv: &Vector2<f64>,
) -> Result<
    (
        Vector2<f64>,
        crate::camera::IntrinsicJacobian,
        Mat2x6,
        Mat2x6,
    ),
    crate::camera::CameraError,
> {
    let arm = face.rotation * (xnom - centre);
    let xf = centre + arm + face.translation;
    let xr = pose.rotation * xf;
    let xc = xr + pose.translation;
    let (proj, j_int, j_pt) = camera.project_cam_with_jacobians(&xc)?;
    let j_pose = rigid_jacobian(&j_pt, &xr);
    let j_face = rigid_jacobian(&(j_pt * pose.rotation.matrix()), &arm);
    Ok((proj - uv, j_int, j_pose, j_face))
}

/// One observation, resolved against the rig.
#[derive(Debug, Clone, Copy)]
struct Obs {
    face: usize,
    xnom: Vector3<f64>,
    uv: Vector2<f64>,
}

struct Problem<'a> {
    rig: &'a Rig,
    names: Vec<String>,
    obs: Vec<Vec<Obs>>,
    centres: Vec<Vector3<f64>>,
    /// `slot[f]`: offset of face f's six parameters in the shared vector, if refined.
    slot: Vec<Option<usize>>,
    /// The free intrinsics.
    map: ParamMap,
    /// Free intrinsics: column k of the map as `(row, coefficient)` entries.
    map_cols: Vec<Vec<(usize, f64)>>,
    /// Size of the shared block (free intrinsics + 6 per refined face).
    q: usize,
    loss: Loss,
}

#[derive(Debug, Clone)]
struct State {
    camera: Camera,
    poses: Vec<Pose>,
    faces: Vec<FaceState>,
}

impl Problem<'_> {
    fn p(&self) -> usize {
        self.map_cols.len()
    }

    fn n_points(&self) -> usize {
        self.obs.iter().map(Vec::len).sum()
    }

    fn residual(&self, s: &State, i: usize, o: &Obs) -> Option<Vector2<f64>> {
        let fs = &s.faces[o.face];
        let c = &self.centres[o.face];
        let x = c + fs.rotation * (o.xnom - c) + fs.translation;
        s.camera.project(&s.poses[i], &x).ok().map(|p| p - o.uv)
    }
}

/// Add one residual row's shared part `ar` (at the shared indices `idx`; pose part `b`, weight `wgt`,
/// residual `r`) to the lower triangle of `U`, to `W_i` and to `g_c`. A function of its own so that the
/// compiler knows the three blocks do not alias (the hot loop of the rig refinement).
#[allow(clippy::too_many_arguments)]
fn add_shared_row(
    u: &mut DMatrix<f64>,
    w: &mut DMatrix<f64>,
    g_c: &mut DVector<f64>,
    idx: &[usize],
    ar: &[f64],
    b: &Vector6<f64>,
    wgt: f64,
    r: f64,
) {
    for (x, &gx) in idx.iter().enumerate() {
        let wa = wgt * ar[x];
        for (y, &gy) in idx.iter().enumerate().take(x + 1) {
            u[(gx, gy)] += wa * ar[y];
        }
        for k in 0..6 {
            w[(gx, k)] += wa * b[k];
        }
        g_c[gx] += wa * r;
    }
}

/// The rig problem: the shared block is the free intrinsics followed by six parameters per refined face.
impl BlockProblem for Problem<'_> {
    type State = State;
    const SINGULAR: &'static str = "the normal equations of the rig refinement are singular";

    fn n_residuals(&self) -> usize {
        2 * self.n_points()
    }

    fn cost(&self, s: &State) -> Option<f64> {
        let mut cost = 0.0;
        for (i, obs) in self.obs.iter().enumerate() {
            for o in obs {
                cost += self.loss.rho(self.residual(s, i, o)?.norm());
            }
        }
        cost.is_finite().then_some(cost)
    }

    /// A point touches only the intrinsics and its own face's block, so only those sub-blocks of the
    /// shared rows are accumulated.
    fn linearise(&self, s: &State) -> Result<Normal, CalibError> {
        let (p, q, nv) = (self.p(), self.q, self.obs.len());
        let mut n = Normal::zeros(q, nv);
        // Compact shared Jacobian row: the p free intrinsics, then (if refined) the face's six.
        let mut idx: Vec<usize> = Vec::with_capacity(p + 6);
        let mut a = [[0.0; N_INTRINSIC + 6]; 2];
        for (i, obs) in self.obs.iter().enumerate() {
            let pose = &s.poses[i];
            for (j, o) in obs.iter().enumerate() {
                let (r, j_int, j_pose, j_face) = point_jacobians(
                    &s.camera,
                    pose,
                    &s.faces[o.face],
                    &self.centres[o.face],
                    &o.xnom,
                    &o.uv,
                )
                .map_err(|_| {
                    CalibError::Degenerate {
                        reason: format!("point {j} moved behind the camera during refinement"),
                    }
                    .in_view(&self.names[i])
                })?;
                idx.clear();
                idx.extend(0..p);
                for (k, col) in self.map_cols.iter().enumerate() {
                    for row in 0..2 {
                        a[row][k] = col.iter().map(|&(e, c)| j_int[(row, e)] * c).sum();
                    }
                }
                if let Some(sl) = self.slot[o.face] {
                    idx.extend(sl..sl + 6);
                    for row in 0..2 {
                        for k in 0..6 {
                            a[row][p + k] = j_face[(row, k)];
                        }
                    }
                }
                let wgt = n.add_cost(self.loss, r.norm());
                for row in 0..2 {
                    let b = j_pose.row(row).transpose();
                    add_shared_row(
                        &mut n.u,
                        &mut n.w[i],
                        &mut n.g_c,
                        &idx,
                        &a[row][..idx.len()],
                        &b,
                        wgt,
                        r[row],
                    );
                    n.add_pose_row(i, wgt, &b, r[row]);
                }
            }
        }
        n.fill_upper_triangles();
        Ok(n)
    }

    fn apply(&self, s: &State, step: &Step) -> State {
        let d_c = step.d_c.as_slice();
        let faces = s
            .faces
            .iter()
            .zip(&self.slot)
            .map(|(f, sl)| match sl {
                Some(sl) => {
                    let (rotation, translation) =
                        update_rigid(&f.rotation, &f.translation, &d_c[*sl..*sl + 6]);
                    FaceState {
                        rotation,
                        translation,
                    }
                }
                None => *f,
            })
            .collect();
        State {
            camera: self.map.step(&s.camera, d_c),
            poses: update_poses(&s.poses, &step.d_p),
            faces,
        }
    }
}

fn check_options(opts: &RigRefineOptions, rig: &Rig) -> Result<(), CalibError> {
    let bad = |reason: String| Err(CalibError::InvalidOption { reason });
    if opts.solve.outlier_sigma.is_some() {
        return bad("outlier rejection is not available with rig refinement".into());
    }
    if let Some(a) = opts.solve.fix.aspect_ratio
        && !(a > 0.0 && a.is_finite())
    {
        return bad(format!("aspect ratio must be positive, got {a}"));
    }
    if let Loss::Huber(c) | Loss::Cauchy(c) = opts.solve.loss
        && !(c > 0.0 && c.is_finite())
    {
        return bad(format!("robust loss scale must be positive, got {c}"));
    }
    if let Some(r) = opts.reference_face
        && r >= rig.faces.len()
    {
        return bad(format!(
            "reference face {r} is not on rig '{}' ({} faces)",
            rig.name,
            rig.faces.len()
        ));
    }
    for (name, v) in [
        ("max_offset_mm", opts.max_offset_mm),
        ("max_tilt_deg", opts.max_tilt_deg),
        ("max_face_rms_ratio", opts.max_face_rms_ratio),
        ("max_sigma_ratio", opts.max_sigma_ratio),
        ("max_offset_std_mm", opts.max_offset_std_mm),
        ("max_tilt_std_deg", opts.max_tilt_std_deg),
    ] {
        if !(v > 0.0 && v.is_finite()) {
            return bad(format!("{name} must be a positive number, got {v}"));
        }
    }
    if opts.min_views_per_face == 0 || opts.min_points_per_face < 3 {
        return bad("min_views_per_face must be ≥ 1 and min_points_per_face ≥ 3".into());
    }
    Ok(())
}

/// Which faces can be refined: the reference, and the faces to refine. Refuses a face that is observed
/// but not tied to the reference by enough views.
fn plan_faces(
    rig: &Rig,
    views: &[RigView],
    opts: &RigRefineOptions,
) -> Result<(usize, Vec<bool>), CalibError> {
    let nf = rig.faces.len();
    let mut seen = vec![vec![false; nf]; views.len()];
    let mut total = vec![0usize; nf];
    for (i, v) in views.iter().enumerate() {
        let mut count = vec![0usize; nf];
        for p in &v.points {
            count[p.corner.face] += 1;
            total[p.corner.face] += 1;
        }
        for f in 0..nf {
            seen[i][f] = count[f] >= opts.min_points_per_face;
        }
    }
    let reference = match opts.reference_face {
        Some(r) => r,
        None => (0..nf).max_by_key(|&f| (total[f], nf - f)).unwrap_or(0),
    };
    let ref_name = &rig.faces[reference].name;
    if total[reference] == 0 {
        return Err(CalibError::Unobservable {
            reason: format!("the reference face '{ref_name}' is never seen"),
        });
    }
    // Views that show f together with another face, and connectivity to the reference.
    let mut shared = vec![0usize; nf];
    let mut linked = vec![vec![false; nf]; nf];
    for s in &seen {
        let faces: Vec<usize> = (0..nf).filter(|&f| s[f]).collect();
        if faces.len() < 2 {
            continue;
        }
        for &a in &faces {
            shared[a] += 1;
            for &b in &faces {
                linked[a][b] = true;
            }
        }
    }
    let mut reached = vec![false; nf];
    reached[reference] = true;
    let mut stack = vec![reference];
    while let Some(a) = stack.pop() {
        for b in 0..nf {
            if linked[a][b] && !reached[b] {
                reached[b] = true;
                stack.push(b);
            }
        }
    }
    let mut refine = vec![false; nf];
    for f in 0..nf {
        if f == reference || total[f] == 0 {
            continue;
        }
        let name = &rig.faces[f].name;
        if !reached[f] {
            return Err(CalibError::Unobservable {
                reason: format!(
                    "face '{name}' is never seen in a view together with the reference face \
                     '{ref_name}' or a face tied to it, so its position on the rig cannot be measured"
                ),
            });
        }
        if shared[f] < opts.min_views_per_face {
            return Err(CalibError::Unobservable {
                reason: format!(
                    "face '{name}' is seen together with another face in {} view(s); refining the rig \
                     needs at least {}",
                    shared[f], opts.min_views_per_face
                ),
            });
        }
        refine[f] = true;
    }
    Ok((reference, refine))
}

/// Calibrate the camera and refine the rig: see the module docs.
///
/// When the points carry the detector's σ and the refined fit's noise estimate is more than
/// [`RigRefineOptions::max_sigma_ratio`] times the detector's median σ, no rigid placement of the faces
/// explains the corners: each face is left out in turn, and the face without which the fit becomes
/// consistent is named in [`CalibError::RigMismatch`].
pub fn solve_rig(
    rig: &Rig,
    views: &[RigView],
    image_size: [u32; 2],
    opts: &RigRefineOptions,
) -> Result<RigCalibration, CalibError> {
    let mut sigmas: Vec<f64> = views
        .iter()
        .flat_map(|v| v.points.iter().filter_map(|p| p.sigma_px))
        .filter(|s| s.is_finite() && *s > 0.0)
        .collect();
    sigmas.sort_by(f64::total_cmp);
    let detector = sigmas.get(sigmas.len() / 2).copied();
    let result = solve_rig_unchecked(rig, views, image_size, opts);
    // A wrong face shows either as a fit far worse than the detector's corners, or as a failure of the
    // initialisation that a rig-consistent set of corners would not cause.
    let (fit, original) = match (result, detector) {
        (r, None) => return r,
        (Ok(r), Some(d)) if r.calibration.sigma_px <= opts.max_sigma_ratio * d => return Ok(r),
        (Ok(r), Some(_)) => (Some(r.calibration.sigma_px), None),
        (
            Err(
                e @ (CalibError::LeftHandedRig
                | CalibError::Degenerate { .. }
                | CalibError::RankDeficient { .. }
                | CalibError::SvdNotConverged { .. }
                | CalibError::InView { .. }),
            ),
            Some(_),
        ) => (None, Some(e)),
        (Err(e), Some(_)) => return Err(e),
    };
    let detector = detector.unwrap_or(f64::NAN);
    // Leave each observed face out in turn.
    let mut best: Option<(usize, f64)> = None;
    for f in 0..rig.faces.len() {
        if !views
            .iter()
            .any(|v| v.points.iter().any(|p| p.corner.face == f))
        {
            continue;
        }
        let without: Vec<RigView> = views
            .iter()
            .map(|v| RigView {
                name: v.name.clone(),
                points: v
                    .points
                    .iter()
                    .filter(|p| p.corner.face != f)
                    .copied()
                    .collect(),
            })
            .filter(|v| !v.points.is_empty())
            .collect();
        let mut sub = opts.clone();
        if sub.reference_face == Some(f) {
            sub.reference_face = None;
        }
        let sigma = match solve_rig_unchecked(rig, &without, image_size, &sub) {
            Ok(r) => r.calibration.sigma_px,
            Err(e) => {
                debug!(face = %rig.faces[f].name, error = %e, "fit without the face failed");
                continue;
            }
        };
        debug!(face = %rig.faces[f].name, sigma, "fit without the face");
        if best.is_none_or(|(_, s)| sigma < s) {
            best = Some((f, sigma));
        }
    }
    let mismatch = |face: usize, reason: String| CalibError::RigMismatch {
        face: rig.faces[face].name.clone(),
        reason,
    };
    let with = match (fit, &original) {
        (Some(fit), _) => format!("with it the corners fit to σ {fit:.3} px"),
        (None, Some(e)) => format!("with it the calibration fails ({e})"),
        (None, None) => String::new(),
    };
    match (best, original) {
        (Some((f, s)), _) if s <= opts.max_sigma_ratio * detector => Err(mismatch(
            f,
            format!(
                "no rigid placement of it explains its corners: {with}, without it they fit to σ {s:.3} px, \
                 and the detector measured them to {detector:.3} px (a wrong square size, a board \
                 turned on its face, a board that is not flat?)"
            ),
        )),
        (_, Some(e)) => Err(e),
        (Some((f, s)), None) => Err(mismatch(
            f,
            format!(
                "{with}, but the detector measured them to {detector:.3} px; \
                 leaving out this face helps most (σ {s:.3} px) but does not explain it: more than one \
                 face, or the camera model, may be wrong"
            ),
        )),
        (None, None) => Err(CalibError::Degenerate {
            reason: format!(
                "neither the rig nor the camera model explains the corners: {with}, but the detector \
                 measured them to {detector:.3} px, and no face can be left out to find the cause"
            ),
        }),
    }
}

fn solve_rig_unchecked(
    rig: &Rig,
    views: &[RigView],
    image_size: [u32; 2],
    opts: &RigRefineOptions,
) -> Result<RigCalibration, CalibError> {
    check_options(opts, rig)?;
    if image_size[0] == 0 || image_size[1] == 0 {
        return Err(CalibError::InvalidOption {
            reason: format!("image size {}×{} is empty", image_size[0], image_size[1]),
        });
    }
    let nominal: Vec<View> = views
        .iter()
        .map(|v| v.to_view(rig))
        .collect::<Result<_, _>>()?;
    validate_views(&nominal)?;
    let (reference, refine) = plan_faces(rig, views, opts)?;
    let init = initialise(&nominal, image_size, opts.solve.model)?;
    let map = ParamMap::new(opts.solve.model, &opts.solve.fix);
    let map_cols: Vec<Vec<(usize, f64)>> = (0..map.len())
        .map(|k| {
            (0..N_INTRINSIC)
                .filter(|&e| map.m[(e, k)] != 0.0)
                .map(|e| (e, map.m[(e, k)]))
                .collect()
        })
        .collect();
    let p = map.len();
    let mut slot = vec![None; rig.faces.len()];
    let mut q = p;
    for (f, &r) in refine.iter().enumerate() {
        if r {
            slot[f] = Some(q);
            q += 6;
        }
    }
    let problem = Problem {
        rig,
        names: views.iter().map(|v| v.name.clone()).collect(),
        obs: views
            .iter()
            .zip(&nominal)
            .map(|(v, nv)| {
                v.points
                    .iter()
                    .zip(&nv.points)
                    .map(|(rp, c)| Obs {
                        face: rp.corner.face,
                        xnom: c.xyz,
                        uv: c.uv,
                    })
                    .collect()
            })
            .collect(),
        centres: rig.faces.iter().map(face_centre).collect(),
        slot,
        map,
        map_cols,
        q,
        loss: opts.solve.loss,
    };
    let mut camera = init
        .camera
        .clone()
        .with_distortion(opts.solve.model, &init.camera.distortion_coefficients());
    apply_fixes(&mut camera, &opts.solve.fix);
    let state = State {
        camera,
        poses: init.poses.clone(),
        faces: vec![FaceState::identity(); rig.faces.len()],
    };
    let (state, iterations, termination) =
        levenberg_marquardt(&problem, state, opts.solve.max_iterations)?;
    info!(
        iterations,
        termination = termination.as_str(),
        refined_faces = refine.iter().filter(|&&r| r).count(),
        "rig refinement finished"
    );
    finish(
        &problem,
        state,
        iterations,
        termination,
        init.method,
        reference,
        opts,
        views,
    )
}

#[allow(clippy::too_many_arguments)]
fn finish(
    problem: &Problem<'_>,
    state: State,
    iterations: usize,
    termination: Termination,
    init_method: InitMethod,
    reference: usize,
    opts: &RigRefineOptions,
    views: &[RigView],
) -> Result<RigCalibration, CalibError> {
    let rig = problem.rig;
    let map = &problem.map;
    let n = problem.linearise(&state)?;
    let n_points = problem.n_points();
    let m_res = 2 * n_points;
    let nv = problem.obs.len();
    let marginal = n.marginal(
        m_res,
        |i| problem.names[i].clone(),
        |_| CalibError::Unobservable {
            reason: format!(
                "the intrinsics ({}) and the rig's face poses are not all constrained by these views",
                map.names.join(", ")
            ),
        },
    )?;
    let cov_shared = &marginal.covariance;
    let covariance = cov_shared
        .view((0, 0), (problem.p(), problem.p()))
        .into_owned();
    let (std_dev, estimated) = map.std_dev(&covariance);

    // Per-view results and per-face residuals.
    let nf = rig.faces.len();
    let mut face_ssr = vec![0.0; nf];
    let mut face_n = vec![0usize; nf];
    let mut view_results = Vec::with_capacity(nv);
    for (i, obs) in problem.obs.iter().enumerate() {
        let mut ssr = 0.0;
        for o in obs {
            if let Some(r) = problem.residual(&state, i, o) {
                ssr += r.norm_squared();
                face_ssr[o.face] += r.norm_squared();
                face_n[o.face] += 1;
            }
        }
        let (rotation_std_rad, translation_std) = marginal.pose_std(&n, i);
        view_results.push(ViewResult {
            name: problem.names[i].clone(),
            cam_from_rig: state.poses[i],
            rms_px: (ssr / (2 * obs.len()).max(1) as f64).sqrt(),
            n_points: obs.len(),
            outliers: Vec::new(),
            rotation_std_rad,
            translation_std,
        });
    }

    let mut faces = Vec::with_capacity(nf);
    let mut built = rig.clone();
    for (f, face) in rig.faces.iter().enumerate() {
        let fs = state.faces[f];
        let axes = Matrix3::from_rows(&[
            face.col_dir.transpose(),
            face.row_dir.transpose(),
            face.normal().transpose(),
        ]);
        let offset = axes * fs.translation;
        let rot = axes * fs.rotation.scaled_axis();
        let (mut offset_std, mut rot_std) = ([0.0; 3], [0.0; 3]);
        if let Some(sl) = problem.slot[f] {
            let c = cov_shared.view((sl, sl), (6, 6));
            let c_rot = axes * c.view((0, 0), (3, 3)) * axes.transpose();
            let c_t = axes * c.view((3, 3), (3, 3)) * axes.transpose();
            for k in 0..3 {
                rot_std[k] = c_rot[(k, k)].max(0.0).sqrt().to_degrees();
                offset_std[k] = c_t[(k, k)].max(0.0).sqrt();
            }
        }
        let centre = problem.centres[f];
        let bf = &mut built.faces[f];
        bf.origin = centre + fs.rotation * (face.origin - centre) + fs.translation;
        bf.col_dir = fs.rotation * face.col_dir;
        bf.row_dir = fs.rotation * face.row_dir;
        faces.push(FaceCorrection {
            face: f,
            name: face.name.clone(),
            refined: problem.slot[f].is_some(),
            centre,
            rotation: fs.rotation,
            translation_mm: fs.translation,
            offset_mm: [offset.x, offset.y, offset.z],
            offset_std_mm: offset_std,
            rotation_deg: [rot.x.to_degrees(), rot.y.to_degrees(), rot.z.to_degrees()],
            rotation_std_deg: rot_std,
            rms_px: if face_n[f] > 0 {
                (face_ssr[f] / (2 * face_n[f]) as f64).sqrt()
            } else {
                f64::NAN
            },
            n_points: face_n[f],
        });
    }
    let mut calibration = Calibration {
        camera: state.camera,
        views: view_results,
        rms_px: (n.ssr / m_res as f64).sqrt(),
        rms_reprojection_px: (n.ssr / n_points as f64).sqrt(),
        sigma_px: marginal.sigma2.sqrt(),
        noise_scale: None,
        free_params: map.names.clone(),
        covariance,
        std_dev,
        estimated,
        n_points,
        n_params: n.n_params(),
        iterations,
        termination,
        init_method,
    };
    let noise_correlation = inflate_for_neighbour_correlation(&mut calibration, views, &built);
    let k = noise_correlation.variance_factor.sqrt();
    for f in &mut faces {
        f.offset_std_mm.iter_mut().for_each(|s| *s *= k);
        f.rotation_std_deg.iter_mut().for_each(|s| *s *= k);
    }
    check_consistency(&faces, opts)?;
    Ok(RigCalibration {
        calibration,
        reference_face: reference,
        faces,
        rig: built,
        noise_correlation,
    })
}

/// Refuse corrections that are not a hand-built rig's imprecision, faces that no rigid correction fits,
/// and faces the data leave undetermined.
fn check_consistency(faces: &[FaceCorrection], opts: &RigRefineOptions) -> Result<(), CalibError> {
    // Corrections too large for an imprecisely built rig. Which face is "wrong" depends on the gauge:
    // with the reference face itself misplaced every other face would seem to move. So judge the faces
    // relative to each observed face in turn and take the reference that leaves the fewest faces moved.
    let seen: Vec<&FaceCorrection> = faces.iter().filter(|f| f.n_points > 0).collect();
    // Each correction as an affine map X ↦ R X + d.
    let affine = |f: &FaceCorrection| {
        (
            f.rotation,
            f.centre + f.translation_mm - f.rotation * f.centre,
        )
    };
    let moved_relative_to = |r: &FaceCorrection| -> Vec<(&FaceCorrection, f64, f64)> {
        let (rr, dr) = affine(r);
        seen.iter()
            .map(|f| {
                let (rf, df) = affine(f);
                let rot = rr.inverse() * rf;
                let d = rr.inverse() * (df - dr);
                let moved = (rot * f.centre + d - f.centre).norm();
                (*f, moved, rot.angle().to_degrees())
            })
            .filter(|&(_, moved, angle)| moved > opts.max_offset_mm || angle > opts.max_tilt_deg)
            .collect()
    };
    if let Some(worst) = seen
        .iter()
        .map(|r| moved_relative_to(r))
        .min_by_key(Vec::len)
        && let Some(&(f, moved, angle)) = worst.first()
    {
        return Err(CalibError::RigMismatch {
            face: f.name.clone(),
            reason: format!(
                "relative to the other faces it would have to move {moved:.2} mm and turn {angle:.2}° \
                 from where the rig file puts it (limits {} mm, {}°): a board mounted elsewhere or \
                 turned (a quarter turn?)",
                opts.max_offset_mm, opts.max_tilt_deg
            ),
        });
    }
    let total_ssr: f64 = faces
        .iter()
        .filter(|f| f.n_points > 0)
        .map(|f| f.rms_px * f.rms_px * (2 * f.n_points) as f64)
        .sum();
    let total_n: usize = faces.iter().map(|f| f.n_points).sum();
    for f in faces {
        if f.n_points > 0 && total_n > f.n_points {
            let own = f.rms_px * f.rms_px * (2 * f.n_points) as f64;
            let others = ((total_ssr - own) / (2 * (total_n - f.n_points)) as f64).sqrt();
            if f.rms_px > opts.max_face_rms_ratio * others {
                return Err(CalibError::RigMismatch {
                    face: f.name.clone(),
                    reason: format!(
                        "its corners fit no rigid placement: residual RMS {:.3} px against {:.3} px on \
                         the other faces (a wrong square size or grid, or a board that is not flat?)",
                        f.rms_px, others
                    ),
                });
            }
        }
        if !f.refined {
            continue;
        }
        let worst_t = f.offset_std_mm.iter().cloned().fold(0.0, f64::max);
        let worst_r = f.rotation_std_deg.iter().cloned().fold(0.0, f64::max);
        if worst_t > opts.max_offset_std_mm || worst_r > opts.max_tilt_std_deg {
            return Err(CalibError::Unobservable {
                reason: format!(
                    "the views determine face '{}' only to σ {worst_t:.2} mm / {worst_r:.2}° (limits {} mm, \
                     {}°): add views that show it at other angles together with the other faces",
                    f.name, opts.max_offset_std_mm, opts.max_tilt_std_deg
                ),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn views_made_against_a_rig_get_their_corner_labels_back() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/fixtures/rigs/cube_outside.toml"
        );
        let (rig, _) = Rig::load(std::path::Path::new(path)).unwrap();
        let rv = RigView {
            name: "v".into(),
            points: rig
                .corners()
                .enumerate()
                .map(|(k, corner)| RigPoint {
                    corner,
                    uv: Vector2::new(k as f64, 0.5),
                    sigma_px: None,
                    cov: None,
                })
                .collect(),
        };
        let back = RigView::from_view(&rv.to_view(&rig).unwrap(), &rig).unwrap();
        assert_eq!(back, rv);
        let mut off = rv.to_view(&rig).unwrap();
        off.points[3].xyz.x += 0.01;
        assert!(matches!(
            RigView::from_view(&off, &rig),
            Err(CalibError::InView { .. })
        ));
    }

    #[test]
    fn face_and_pose_jacobians_match_central_differences() {
        let cam = crate::render::correspondences::reference_camera().with_distortion(
            crate::camera::DistortionModel::Brown5,
            &[-0.2, 0.05, 1e-3, -2e-3, 0.01],
        );
        let pose = Pose::from_axis_angle(
            Vector3::new(0.3, -0.5, 0.2),
            Vector3::new(-40.0, 25.0, 600.0),
        );
        let face = FaceState {
            rotation: Rotation3::new(Vector3::new(0.01, -0.02, 0.005)),
            translation: Vector3::new(0.4, -0.7, 0.2),
        };
        let centre = Vector3::new(100.0, 90.0, 200.0);
        let x = Vector3::new(120.0, -80.0, 35.0);
        let uv = Vector2::new(600.0, 400.0);
        let (_, _, j_pose, j_face) = point_jacobians(&cam, &pose, &face, &centre, &x, &uv).unwrap();
        for k in 0..12 {
            let h = if k % 6 < 3 { 1e-7 } else { 1e-5 };
            let eval = |sign: f64| {
                let mut d = Vec6::zeros();
                d[k % 6] = sign * h;
                let rot = Rotation3::new(Vector3::new(d[0], d[1], d[2]));
                let t = Vector3::new(d[3], d[4], d[5]);
                let (p, f) = if k < 6 {
                    let p = Pose {
                        rotation: rot * pose.rotation,
                        translation: pose.translation + t,
                    };
                    (p, face)
                } else {
                    let f = FaceState {
                        rotation: rot * face.rotation,
                        translation: face.translation + t,
                    };
                    (pose, f)
                };
                point_jacobians(&cam, &p, &f, &centre, &x, &uv).unwrap().0
            };
            let num = (eval(1.0) - eval(-1.0)) / (2.0 * h);
            let ana = if k < 6 { j_pose } else { j_face };
            for r in 0..2 {
                let a = ana[(r, k % 6)];
                assert!(
                    (num[r] - a).abs() < 1e-5 * (1.0 + num[r].abs()),
                    "{} param {} row {r}: analytic {a} numeric {}",
                    if k < 6 { "pose" } else { "face" },
                    k % 6,
                    num[r]
                );
            }
        }
    }
}
