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
//! Either way the decision is printed with its margin. A frame whose only labelled face is known
//! only up to a symmetry of the rig (`identity` labelled it with its pose flagged: a lone grid of a
//! shape two faces share, a lone 180°-symmetric face) has no pose to predict from; there each of
//! that face's labellings that fits the camera gives one, and the rejected grids choose between
//! them by the same log-likelihood margin: the frame's two faces are then labelled jointly and the
//! flag lifted (a sheet wrapped around a box's edge seen with one face at 70°, whose extent the
//! frame cannot prove). A frame with no labelled face is left as it is. The admitted
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
/// rejections removed), and every grid tried gets a decision. The pose comes from the frame's
/// proven faces; a frame whose one face is labelled only up to a symmetry of the rig (its pose
/// flagged) is settled jointly: each of that face's labellings gives a pose, and the one under which
/// the rejected grids fit — by the same margin — labels both, the flag lifted. Nothing happens
/// without rejected grids or without a face to take the pose from.
pub fn settle(rig: &Rig, camera: &Camera, det: &mut FrameDetection, name: &str) -> Vec<Decision> {
    let tried: Vec<usize> = (0..det.rejected.len())
        .filter(|&i| det.rejected[i].corners.len() >= MIN_CORNERS)
        .collect();
    if tried.is_empty() {
        return Vec::new();
    }
    let proven: Vec<&FaceDetection> = det
        .faces
        .iter()
        .filter(|f| f.ambiguous_pose.is_none())
        .collect();
    let corner_sigma = median_sigma(&det.faces);
    if !proven.is_empty() {
        let points: Vec<_> = proven
            .iter()
            .flat_map(|f| f.corners.iter())
            .map(|c| (c.xyz, c.uv))
            .collect();
        let Some((pose, rms)) = pose_of(camera, &points, name) else {
            return Vec::new();
        };
        let sigma = rms.max(MIN_SIGMA_PX);
        let taken: Vec<usize> = det.faces.iter().map(|f| f.face).collect();
        return settle_in(rig, camera, &pose, sigma, corner_sigma, det, &tried, &taken);
    }
    if det.faces.len() != 1 {
        return Vec::new();
    }
    settle_flagged(rig, camera, det, name, &tried, corner_sigma)
}

/// The median σ of the frame's labelled corners (0.1 px without one).
fn median_sigma(faces: &[FaceDetection]) -> f64 {
    let mut sigmas: Vec<f64> = faces
        .iter()
        .flat_map(|f| f.corners.iter().map(|c| c.sigma_px))
        .filter(|s| s.is_finite())
        .collect();
    sigmas.sort_by(f64::total_cmp);
    sigmas.get(sigmas.len() / 2).copied().unwrap_or(0.1)
}

/// The pose of 2D–3D pairs in `camera`, and its RMS (px).
fn pose_of(
    camera: &Camera,
    points: &[(nalgebra::Vector3<f64>, Vector2<f64>)],
    name: &str,
) -> Option<(Pose, f64)> {
    let view = crate::calib::View {
        name: name.to_string(),
        points: points
            .iter()
            .map(|&(xyz, uv)| crate::calib::Correspondence { xyz, uv, cov: None })
            .collect(),
    };
    solve_pose(camera, &view)
        .ok()
        .map(|p| (p.cam_from_rig, p.rms_px))
}

/// One labelling of a flagged face: the labelling, its pose, its RMS (px), the rejected grids'
/// summed best SSR under that pose, and those best fits.
type Alternative = (Fit, Pose, f64, f64, Vec<Option<Fit>>);

/// The frame's one face, labelled only up to a symmetry, and its rejected grids: every labelling of
/// that face that fits the camera gives a pose; the rejected grids' best fits under each pose are
/// summed, and the labelling whose sum beats every other's by [`MIN_LOG_LR`] is taken — if under it
/// at least one grid is admitted by [`settle_in`]'s rule. Then the face is relabelled and its flag
/// lifted; otherwise nothing changes.
fn settle_flagged(
    rig: &Rig,
    camera: &Camera,
    det: &mut FrameDetection,
    name: &str,
    tried: &[usize],
    corner_sigma: f64,
) -> Vec<Decision> {
    let face = det.faces[0].clone();
    let grid: Vec<GridCorner> = face
        .corners
        .iter()
        .map(|c| GridCorner {
            row: c.row,
            col: c.col,
            uv: c.uv,
        })
        .collect();
    let (rows, cols) = dims(&grid);
    // Each labelling of the face's grid, with its pose, its RMS, the rejected grids' summed best
    // fit under it, and those best fits.
    let mut alts: Vec<Alternative> = Vec::new();
    for l in labellings(rig, rows, cols, &[]) {
        let points: Vec<_> = grid
            .iter()
            .map(|g| {
                let (r, c) = l.at(rows, cols, g);
                (rig.faces[l.face].corner_xyz(r, c), g.uv)
            })
            .collect();
        let Some((pose, rms)) = pose_of(camera, &points, name) else {
            continue;
        };
        let bests: Vec<Option<Fit>> = tried
            .iter()
            .map(|&i| {
                fits(rig, camera, &pose, &det.rejected[i].corners, &[l.face])
                    .into_iter()
                    .min_by(|a, b| a.ssr.total_cmp(&b.ssr))
            })
            .collect();
        let sum: f64 = bests
            .iter()
            .map(|b| b.map_or(f64::INFINITY, |b| b.ssr))
            .sum();
        alts.push((l, pose, rms, sum, bests));
    }
    // Labellings the face alone does not fit (mirrors, shifts off the lattice) are no alternatives.
    let best_rms = alts.iter().map(|a| a.2).fold(f64::INFINITY, f64::min);
    alts.retain(|a| a.2 <= ADMIT_SIGMAS * best_rms.max(MIN_SIGMA_PX) && a.3.is_finite());
    alts.sort_by(|a, b| a.3.total_cmp(&b.3));
    let Some((best, pose, rms, sum, _)) = alts.first().cloned() else {
        return Vec::new();
    };
    let sigma = rms.max(MIN_SIGMA_PX);
    let lr = |a: &Alternative| (a.3 - sum) / (2.0 * sigma * sigma);
    // Rivals within the margin that are the best joint labelling moved by a similarity (a symmetry
    // of the rig, e.g. the half turn exchanging a wrapped sheet's two faces) teach the camera the
    // same: the joint labelling is taken, its pose flagged. Any other rival leaves the frame as is.
    let joint = |a: &Alternative| -> Option<Vec<nalgebra::Vector3<f64>>> {
        let mut xyz: Vec<_> = grid
            .iter()
            .map(|g| {
                let (r, c) = a.0.at(rows, cols, g);
                rig.faces[a.0.face].corner_xyz(r, c)
            })
            .collect();
        for (&i, b) in tried.iter().zip(&a.4) {
            let b = (*b)?;
            let corners = &det.rejected[i].corners;
            let (gr, gc) = dims(corners);
            xyz.extend(corners.iter().map(|g| {
                let (r, c) = b.at(gr, gc, g);
                rig.faces[b.face].corner_xyz(r, c)
            }));
        }
        Some(xyz)
    };
    let rivals: Vec<_> = alts[1..].iter().filter(|a| lr(a) < MIN_LOG_LR).collect();
    let symmetric = !rivals.is_empty()
        && joint(&alts[0]).is_some_and(|b| {
            rivals
                .iter()
                .all(|a| joint(a).is_some_and(|x| super::identity::similar(&b, &x)))
        });
    let log_lr = alts[1..]
        .iter()
        .filter(|a| !(symmetric && rivals.iter().any(|r| std::ptr::eq(*r, *a))))
        .map(lr)
        .fold(f64::INFINITY, f64::min);
    let mut trial = det.clone();
    let relabelled: Vec<LabelledCorner> = face
        .corners
        .iter()
        .zip(&grid)
        .map(|(c, g)| {
            let (r, col) = best.at(rows, cols, g);
            LabelledCorner {
                row: r,
                col,
                xyz: rig.faces[best.face].corner_xyz(r, col),
                ..*c
            }
        })
        .collect();
    let face_text = format!(
        "face '{}' labelled jointly with the frame's other grids by the camera of the other views: log-likelihood ratio {} over the face's next labelling that is not a symmetry of the rig ({MIN_LOG_LR} needed)",
        rig.faces[best.face].name,
        if log_lr.is_finite() {
            format!("{log_lr:.0}")
        } else {
            "∞".into()
        }
    );
    let flag = symmetric.then(|| {
        format!(
            "labelled jointly with the frame's other grids up to a symmetry of the rig ({} joint labellings fit the camera alike, each one similarity from the others)",
            rivals.len() + 1
        )
    });
    trial.faces[0] = FaceDetection {
        face: best.face,
        corners: relabelled,
        ambiguous_pose: flag.clone(),
        identity: Some(face_text.clone()),
        ..face
    };
    let mut decisions = settle_in(
        rig,
        camera,
        &pose,
        sigma,
        corner_sigma,
        &mut trial,
        tried,
        &[best.face],
    );
    if log_lr >= MIN_LOG_LR && decisions.iter().any(|d| d.admitted.is_some()) {
        if flag.is_some() {
            for f in &mut trial.faces[1..] {
                f.ambiguous_pose = flag.clone();
            }
        }
        *det = trial;
        for d in &mut decisions {
            d.text = format!("{} ({face_text})", d.text);
        }
        return decisions;
    }
    let out: Vec<Decision> = tried
        .iter()
        .map(|&i| Decision {
            rejection: i,
            admitted: None,
            text: format!(
                "left out: the frame's one face is labelled only up to a symmetry and the camera does not settle it with this grid ({face_text}; {})",
                decisions
                    .iter()
                    .find(|d| d.rejection == i)
                    .map_or("", |d| d.text.as_str())
            ),
        })
        .collect();
    for d in &out {
        let r = &mut det.rejected[d.rejection];
        r.reason = format!("{}; {}", r.reason, d.text);
    }
    out
}

/// Settle the grids `tried` of `det` in `pose` (see the module doc); faces in `taken` are not
/// candidates.
#[allow(clippy::too_many_arguments)]
fn settle_in(
    rig: &Rig,
    camera: &Camera,
    pose: &Pose,
    sigma: f64,
    corner_sigma: f64,
    det: &mut FrameDetection,
    tried: &[usize],
    taken: &[usize],
) -> Vec<Decision> {
    let mut decisions = Vec::new();
    let mut admitted: Vec<(usize, FaceDetection)> = Vec::new();
    for &i in tried {
        let corners = &det.rejected[i].corners;
        let mut fits = fits(rig, camera, pose, corners, taken);
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
    // Each grid left out says why in its rejection too (detect's output, the overlay, the report).
    for d in decisions.iter().filter(|d| d.admitted.is_none()) {
        let r = &mut det.rejected[d.rejection];
        r.reason = format!("{}; {}", r.reason, d.text);
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

/// The size of a grid given by its corners' indices.
fn dims(corners: &[GridCorner]) -> (usize, usize) {
    let rows = corners.iter().map(|g| g.row).max().map_or(0, |m| m + 1);
    let cols = corners.iter().map(|g| g.col).max().map_or(0, |m| m + 1);
    (rows, cols)
}

impl Fit {
    /// The face indices of grid corner `g` under this labelling (grid of `rows × cols`).
    fn at(&self, rows: usize, cols: usize, g: &GridCorner) -> (usize, usize) {
        let ((r, c), _) = turned(self.sym, rows, cols, g.row, g.col);
        (r + self.offset.0, c + self.offset.1)
    }
}

/// Every labelling of a `rows × cols` grid on a checkerboard face not in `taken`: face, symmetry
/// and offset keeping the grid inside the face (`ssr` 0).
fn labellings(rig: &Rig, rows: usize, cols: usize, taken: &[usize]) -> Vec<Fit> {
    let mut out = Vec::new();
    for (fi, face) in rig.faces.iter().enumerate() {
        if taken.contains(&fi) || face.charuco.is_some() {
            continue;
        }
        for sym in 0..8u8 {
            let (_, (tr, tc)) = turned(sym, rows, cols, 0, 0);
            if tr > face.rows || tc > face.cols {
                continue;
            }
            for or in 0..=face.rows - tr {
                for oc in 0..=face.cols - tc {
                    out.push(Fit {
                        face: fi,
                        sym,
                        offset: (or, oc),
                        ssr: 0.0,
                    });
                }
            }
        }
    }
    out
}

/// Every labelling of `corners` on a face not in `taken` that faces the camera, with its residuals.
fn fits(
    rig: &Rig,
    camera: &Camera,
    pose: &Pose,
    corners: &[GridCorner],
    taken: &[usize],
) -> Vec<Fit> {
    let (rows, cols) = dims(corners);
    let mut predicted: Vec<Option<Vec<Option<Vector2<f64>>>>> = vec![None; rig.faces.len()];
    let mut out = Vec::new();
    for mut l in labellings(rig, rows, cols, taken) {
        let face = &rig.faces[l.face];
        let slot = &mut predicted[l.face];
        if slot.is_none() {
            // The face's printed side must face the camera; then the predicted image position of
            // each of its corners (None: not projectable).
            let centre = face.corner_xyz(face.rows / 2, face.cols / 2);
            let facing = face.normal().dot(&(pose.centre() - centre)) > 0.0;
            *slot = Some(if facing {
                (0..face.rows)
                    .flat_map(|r| (0..face.cols).map(move |c| (r, c)))
                    .map(|(r, c)| camera.project(pose, &face.corner_xyz(r, c)).ok())
                    .collect()
            } else {
                Vec::new()
            });
        }
        let Some(pred) = slot.as_ref().filter(|p| !p.is_empty()) else {
            continue;
        };
        let mut ssr = 0.0;
        let mut ok = true;
        for g in corners {
            let (r, c) = l.at(rows, cols, g);
            match pred[r * face.cols + c] {
                Some(p) => ssr += (g.uv - p).norm_squared(),
                None => {
                    ok = false;
                    break;
                }
            }
        }
        if ok {
            l.ssr = ssr;
            out.push(l);
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
    let (rows, cols) = dims(corners);
    let corners = corners
        .iter()
        .map(|g| {
            let (r, c) = fit.at(rows, cols, g);
            LabelledCorner {
                row: r,
                col: c,
                xyz: face.corner_xyz(r, c),
                uv: g.uv,
                sigma_px,
                cov: Matrix2::from_diagonal_element(sigma_px * sigma_px),
                edge_px: 0.0,
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
