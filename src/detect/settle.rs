//! Settle: a grid the frame alone could not label, labelled by a camera known from the other views.
//!
//! The detector labels a grid only on its own frame's evidence (`label`); a grid cut by the frame
//! border on a rig of several faces, a partial grid `place` could not place through the frame's
//! DLT, a grid whose identity the frame's geometry left open — each comes out as a rejection with
//! its corners in its own row/column indices. Once a calibration exists, a frame that also holds
//! proven faces has a pose in that camera: the proven faces' corners fix it ([`solve_pose`], the
//! intrinsics and the lens held). Every labelling of the rejected grid — each face of the rig not
//! already in the frame and facing the camera, each of the grid's eight symmetries (four turns,
//! mirrored or not: a mirror is just another labelling that will not fit), each offset that keeps
//! the grid inside the face — then predicts where its corners must be, and is scored against
//! where they are:
//!
//! * the best labelling must fit within [`ADMIT_SIGMAS`] σ, where σ is the prediction's scale: the
//!   larger of the proven faces' own RMS in that pose and [`MIN_SIGMA_PX`] (a pose extrapolated to
//!   another face errs by more than its own residuals);
//! * every other labelling must be refuted by a log-likelihood ratio of at least [`MIN_LOG_LR`]
//!   under Gaussian residuals of that σ: `(SSR_other − SSR_best) / (2σ²) ≥ 50`, i.e. the best is
//!   e⁵⁰ times likelier. Labellings one line apart differ by a lattice step on every corner, tens
//!   of σ each, so the margin is wide where the test decides and the rule only bites when the
//!   prediction is poor (a badly known lens far out in the image) or the grid tiny.
//!
//! Either way the decision is printed with its margin. Labellings one similarity apart of a frame
//! without proven faces are not this module's (`identity` labels them with the pose flagged); a
//! frame with no proven face has no pose to predict from and is left as it is. The admitted
//! corners carry the median σ of the frame's labelled corners (their own fit's σ is not kept in a
//! rejection); the station's second look (`undistorted`) fits them again with the lens.

use nalgebra::{Matrix2, Vector2};

use super::FrameDetection;
use super::face::{FaceDetection, GridCorner, LabelledCorner};
use crate::calib::pose::solve_pose;
use crate::camera::{Camera, Pose};
use crate::rig::Rig;

/// The best labelling must fit within this many σ (RMS over its corners).
pub const ADMIT_SIGMAS: f64 = 3.0;
/// Floor of the prediction σ (px).
pub const MIN_SIGMA_PX: f64 = 0.3;
/// Least log-likelihood ratio of the best labelling over every other.
pub const MIN_LOG_LR: f64 = 50.0;
/// Fewest corners a rejected grid must hold to be settled.
pub const MIN_CORNERS: usize = 4;

/// What settling one rejected grid decided.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// Index of the rejection in the frame's `rejected`.
    pub rejection: usize,
    /// The face the grid was admitted as (`None`: left out).
    pub admitted: Option<usize>,
    /// The decision in words, with its margin.
    pub text: String,
}

/// One labelling's fit: face, symmetry and offset, and the sum of squared residuals (px²).
#[derive(Debug, Clone, Copy)]
struct Fit {
    face: usize,
    sym: u8,
    offset: (usize, usize),
    ssr: f64,
}

/// Settle the rejected grids of `det` with `camera`: admitted grids become faces of `det` (their
/// rejections removed), and every grid tried gets a decision. Nothing happens without a proven face
/// in the frame (no pose) or without rejected grids.
pub fn settle(rig: &Rig, camera: &Camera, det: &mut FrameDetection, name: &str) -> Vec<Decision> {
    let proven: Vec<&FaceDetection> = det
        .faces
        .iter()
        .filter(|f| f.ambiguous_pose.is_none())
        .collect();
    let tried: Vec<usize> = (0..det.rejected.len())
        .filter(|&i| det.rejected[i].corners.len() >= MIN_CORNERS)
        .collect();
    if proven.is_empty() || tried.is_empty() {
        return Vec::new();
    }
    let view = crate::calib::View {
        name: name.to_string(),
        points: proven
            .iter()
            .flat_map(|f| f.corners.iter())
            .map(|c| crate::calib::Correspondence {
                xyz: c.xyz,
                uv: c.uv,
                cov: None,
            })
            .collect(),
    };
    let Ok(pose) = solve_pose(camera, &view) else {
        return Vec::new();
    };
    let sigma = pose.rms_px.max(MIN_SIGMA_PX);
    let mut sigmas: Vec<f64> = proven
        .iter()
        .flat_map(|f| f.corners.iter().map(|c| c.sigma_px))
        .filter(|s| s.is_finite())
        .collect();
    sigmas.sort_by(f64::total_cmp);
    let corner_sigma = sigmas.get(sigmas.len() / 2).copied().unwrap_or(0.1);
    let taken: Vec<usize> = det.faces.iter().map(|f| f.face).collect();
    let mut decisions = Vec::new();
    let mut admitted: Vec<(usize, FaceDetection)> = Vec::new();
    for i in tried {
        let corners = &det.rejected[i].corners;
        let mut fits = fits(rig, camera, &pose.cam_from_rig, corners, &taken);
        fits.sort_by(|a, b| a.ssr.total_cmp(&b.ssr));
        let n = corners.len() as f64;
        let Some(best) = fits.first().copied() else {
            decisions.push(Decision {
                rejection: i,
                admitted: None,
                text: "no face of the rig can hold the grid facing the camera".into(),
            });
            continue;
        };
        let rms = (best.ssr / (2.0 * n)).sqrt();
        let log_lr = fits.get(1).map_or(f64::INFINITY, |s| {
            (s.ssr - best.ssr) / (2.0 * sigma * sigma)
        });
        let face_name = &rig.faces[best.face].name;
        let margin = if log_lr.is_finite() {
            format!(
                "log-likelihood ratio {log_lr:.0} over the next labelling ({MIN_LOG_LR} needed)"
            )
        } else {
            "no other labelling".into()
        };
        let fits_camera = rms <= ADMIT_SIGMAS * sigma;
        let text = format!(
            "{} corners settled by the camera of the other views: face '{face_name}' fits at {rms:.2} px RMS (σ {sigma:.2} px, {ADMIT_SIGMAS}σ allowed), {margin}",
            corners.len()
        );
        if fits_camera && log_lr >= MIN_LOG_LR {
            let face = labelled(rig, best, corners, corner_sigma, &text);
            admitted.push((i, face));
            decisions.push(Decision {
                rejection: i,
                admitted: Some(best.face),
                text: format!("admitted: {text}"),
            });
        } else {
            decisions.push(Decision {
                rejection: i,
                admitted: None,
                text: format!("left out: {text}"),
            });
        }
    }
    // A face admitted twice in one frame (two grids claiming it) is admitted for neither.
    let mut twice: Vec<usize> = admitted.iter().map(|a| a.1.face).collect();
    twice.sort_unstable();
    let dup: Vec<usize> = twice
        .windows(2)
        .filter(|w| w[0] == w[1])
        .map(|w| w[0])
        .collect();
    for d in &mut decisions {
        if d.admitted.is_some_and(|f| dup.contains(&f)) {
            d.admitted = None;
            d.text = format!(
                "left out: another grid of the frame fits the same face ({})",
                d.text
            );
        }
    }
    let mut removed: Vec<usize> = Vec::new();
    for (i, face) in admitted {
        if !dup.contains(&face.face) {
            removed.push(i);
            det.faces.push(face);
        }
    }
    removed.sort_unstable();
    for i in removed.into_iter().rev() {
        det.rejected.remove(i);
    }
    decisions
}

/// Grid indices `(r, c)` of a `rows × cols` grid under symmetry `sym` (bit 2: transpose first;
/// bits 0–1: quarter turns), and the turned grid's size.
fn turned(
    sym: u8,
    rows: usize,
    cols: usize,
    r: usize,
    c: usize,
) -> ((usize, usize), (usize, usize)) {
    let (r, c, rows, cols) = if sym & 4 != 0 {
        (c, r, cols, rows)
    } else {
        (r, c, rows, cols)
    };
    match sym & 3 {
        0 => ((r, c), (rows, cols)),
        1 => ((c, rows - 1 - r), (cols, rows)),
        2 => ((rows - 1 - r, cols - 1 - c), (rows, cols)),
        _ => ((cols - 1 - c, r), (cols, rows)),
    }
}

/// Every labelling of `corners` on a face not in `taken` that faces the camera, with its residuals.
fn fits(
    rig: &Rig,
    camera: &Camera,
    pose: &Pose,
    corners: &[GridCorner],
    taken: &[usize],
) -> Vec<Fit> {
    let rows = corners.iter().map(|g| g.row).max().map_or(0, |m| m + 1);
    let cols = corners.iter().map(|g| g.col).max().map_or(0, |m| m + 1);
    let mut out = Vec::new();
    for (fi, face) in rig.faces.iter().enumerate() {
        if taken.contains(&fi) || face.charuco.is_some() {
            continue;
        }
        // The face's printed side must face the camera.
        let centre = face.corner_xyz(face.rows / 2, face.cols / 2);
        let to_camera = pose.centre() - centre;
        if face.normal().dot(&to_camera) <= 0.0 {
            continue;
        }
        // Predicted image positions of every corner of the face (None: not projectable).
        let predicted: Vec<Option<Vector2<f64>>> = (0..face.rows)
            .flat_map(|r| (0..face.cols).map(move |c| (r, c)))
            .map(|(r, c)| camera.project(pose, &face.corner_xyz(r, c)).ok())
            .collect();
        for sym in 0..8u8 {
            let (_, (tr, tc)) = turned(sym, rows, cols, 0, 0);
            if tr > face.rows || tc > face.cols {
                continue;
            }
            for or in 0..=face.rows - tr {
                'offset: for oc in 0..=face.cols - tc {
                    let mut ssr = 0.0;
                    for g in corners {
                        let ((r, c), _) = turned(sym, rows, cols, g.row, g.col);
                        let Some(p) = predicted[(r + or) * face.cols + (c + oc)] else {
                            continue 'offset;
                        };
                        ssr += (g.uv - p).norm_squared();
                    }
                    out.push(Fit {
                        face: fi,
                        sym,
                        offset: (or, oc),
                        ssr,
                    });
                }
            }
        }
    }
    out
}

/// The grid's corners labelled by `fit`.
fn labelled(
    rig: &Rig,
    fit: Fit,
    corners: &[GridCorner],
    sigma_px: f64,
    decision: &str,
) -> FaceDetection {
    let face = &rig.faces[fit.face];
    let rows = corners.iter().map(|g| g.row).max().map_or(0, |m| m + 1);
    let cols = corners.iter().map(|g| g.col).max().map_or(0, |m| m + 1);
    let corners = corners
        .iter()
        .map(|g| {
            let ((r, c), _) = turned(fit.sym, rows, cols, g.row, g.col);
            let (r, c) = (r + fit.offset.0, c + fit.offset.1);
            LabelledCorner {
                row: r,
                col: c,
                xyz: face.corner_xyz(r, c),
                uv: g.uv,
                sigma_px,
                cov: Matrix2::from_diagonal_element(sigma_px * sigma_px),
            }
        })
        .collect();
    FaceDetection {
        face: fit.face,
        corners,
        colour_contrast: 0.0,
        ambiguous_pose: None,
        identity: Some(decision.to_string()),
    }
}
