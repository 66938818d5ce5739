//! Identity: which face a complete grid is, and which of its corners is the face's `(0, 0)`.
//!
//! A grid (handedness-corrected, so no mirror images) has up to eight candidate mappings onto the
//! rig's faces: every face of its size, directly or turned by 90°, in two orientations 180° apart.
//! They are narrowed by evidence, in this order:
//! 1. **Size.** The grid's rows × cols must equal the face's (after the turn).
//! 2. **Colours.** The mean intensity of the squares the mapping predicts white must exceed that of
//!    the squares it predicts black by [`MIN_COLOUR_CONTRAST`] grey levels. For a face that is not
//!    180°-symmetric the two orientations predict opposite colours, so at most one survives; for a
//!    symmetric face both survive, and faces of equal size all survive.
//! 3. **Geometry.** One camera must see all faces of the frame: every joint assignment of the
//!    surviving candidates (distinct faces) is fitted with the normalised DLT on all its corners, and
//!    the best must fit [`GEOMETRY_MARGIN`] times better than every other assignment — and than the
//!    best with any one face reversed, whatever its colours say — and within
//!    [`MAX_GEOMETRY_RMS_STEPS`] of the grids' step. This tells apart faces of equal size (the two
//!    walls of an inside corner) and orients 180°-symmetric faces, whenever the frame's grids are not
//!    all coplanar.
//!
//! When the geometry cannot decide (one grid, or coplanar grids, or no clear winner), a grid is
//! labelled only if its size and colours leave exactly one candidate; the others are rejected with
//! the reason — except a lone 180°-symmetric face on a rig of one face: its candidates differ by a
//! turn within its plane, which moves the view's pose and never the intrinsics, so it is labelled
//! with (0, 0) nearest the image's top-left and its pose flagged ([`FaceDetection::ambiguous_pose`]).

use image::GrayImage;
use nalgebra::{Matrix3x4, Vector2, Vector3};

use super::dense::Dense;
use super::face::{FaceDetection, LabelledCorner, MIN_COLOUR_CONTRAST, Rejection};
use crate::calib::linear::{COPLANAR_TOLERANCE, dlt, relative_thickness};
use crate::rig::{Rig, SquareColour};

/// With several faces, the chosen labelling's DLT RMS must be this many times smaller than any
/// alternative's.
pub const GEOMETRY_MARGIN: f64 = 3.0;
/// When the geometry decides between candidates, the best assignment's DLT RMS may be at most this
/// fraction of the grids' median step (a wrong grid among right ones fits no assignment).
pub const MAX_GEOMETRY_RMS_STEPS: f64 = 0.25;
/// Most joint assignments tried when the geometry decides (beyond: not told apart).
pub const MAX_ASSIGNMENTS: usize = 4096;

/// A grid with local indices mapped to a face: `cell(row, col)` of the face is the grid's
/// `index(row, col)`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Mapping {
    pub(super) face: usize,
    /// 0..4: number of quarter turns applied to the handedness-corrected grid.
    pub(super) turns: u8,
}

pub(super) fn mean_square_intensity(img: &GrayImage, quad: [Vector2<f64>; 4]) -> Option<f64> {
    let c = (quad[0] + quad[1] + quad[2] + quad[3]) / 4.0;
    // Average a small neighbourhood a third of the way to each corner.
    let mut sum = 0.0;
    let mut n = 0.0;
    for q in &quad {
        let p = c + (q - c) * 0.3;
        let (x, y) = (p.x.round(), p.y.round());
        if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
            return None;
        }
        sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
        n += 1.0;
    }
    let (x, y) = (c.x.round(), c.y.round());
    if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
        return None;
    }
    sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
    Some(sum / (n + 1.0))
}

/// The face indices that occur more than once.
pub(super) fn repeated(faces: impl Iterator<Item = usize>) -> Vec<usize> {
    let mut faces: Vec<usize> = faces.collect();
    faces.sort_unstable();
    let mut dup: Vec<usize> = faces
        .windows(2)
        .filter(|w| w[0] == w[1])
        .map(|w| w[0])
        .collect();
    dup.dedup();
    dup
}

/// Mean intensities of the squares predicted white and black by a labelling.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct ColourSums {
    white: f64,
    n_white: usize,
    black: f64,
    n_black: usize,
}

impl ColourSums {
    pub(super) fn add(&mut self, colour: SquareColour, intensity: f64) {
        match colour {
            SquareColour::White => {
                self.white += intensity;
                self.n_white += 1;
            }
            SquareColour::Black => {
                self.black += intensity;
                self.n_black += 1;
            }
        }
    }

    /// White-minus-black mean intensity (`None` unless both colours were seen).
    pub(super) fn contrast(&self) -> Option<f64> {
        (self.n_white > 0 && self.n_black > 0)
            .then(|| self.white / self.n_white as f64 - self.black / self.n_black as f64)
    }
}

/// The normalised DLT projection of 2D–3D pairs (`None` when the 3D points are coplanar).
pub(super) fn dlt_fit(points: &[(Vector3<f64>, Vector2<f64>)]) -> Option<Matrix3x4<f64>> {
    let x3: Vec<Vector3<f64>> = points.iter().map(|p| p.0).collect();
    if relative_thickness(&x3) < COPLANAR_TOLERANCE {
        return None;
    }
    let x2: Vec<Vector2<f64>> = points.iter().map(|p| p.1).collect();
    dlt(&x3, &x2).ok()
}

/// RMS image distance (px) between the pairs' 2D points and their 3D points projected by `p`.
pub(super) fn reprojection_rms(
    p: &Matrix3x4<f64>,
    points: &[(Vector3<f64>, Vector2<f64>)],
) -> Option<f64> {
    let mut ssr = 0.0;
    for (x, u) in points {
        let h = p * x.push(1.0);
        if h.z.abs() < 1e-300 {
            return None;
        }
        ssr += (Vector2::new(h.x / h.z, h.y / h.z) - u).norm_squared();
    }
    Some((ssr / points.len().max(1) as f64).sqrt())
}

fn dlt_rms(points: &[(Vector3<f64>, Vector2<f64>)]) -> Option<f64> {
    reprojection_rms(&dlt_fit(points)?, points)
}

/// The labelled faces must fit one camera clearly better than with any face's orientation reversed.
pub(super) fn check_geometry(
    rig: &Rig,
    found: &[(FaceDetection, Dense, Mapping)],
) -> Result<(), String> {
    let assemble = |flip: Option<usize>| -> Vec<(Vector3<f64>, Vector2<f64>)> {
        let mut pts = Vec::new();
        for (k, (f, d, _)) in found.iter().enumerate() {
            let face = &rig.faces[f.face];
            let dd = if flip == Some(k) {
                d.turned(2)
            } else {
                d.clone()
            };
            for r in 0..dd.rows {
                for c in 0..dd.cols {
                    pts.push((face.corner_xyz(r, c), dd.at(r, c)));
                }
            }
        }
        pts
    };
    let Some(chosen) = dlt_rms(&assemble(None)) else {
        return Err(
            "labelled faces are coplanar or degenerate: the rig geometry cannot confirm them"
                .into(),
        );
    };
    for k in 0..found.len() {
        if let Some(alt) = dlt_rms(&assemble(Some(k)))
            && alt < GEOMETRY_MARGIN * chosen
        {
            return Err(format!(
                "labelling not confirmed by the rig geometry: DLT RMS {chosen:.2} px vs {alt:.2} px with face '{}' reversed",
                rig.faces[found[k].0.face].name
            ));
        }
    }
    Ok(())
}

/// A grid of a face's size whose extent is proven, with the mappings its size and colours allow.
#[derive(Debug, Clone)]
pub(super) struct Whole {
    pub(super) dense: Dense,
    /// Mappings (face, quarter turns) with the white-minus-black contrast they read.
    pub(super) candidates: Vec<(Mapping, f64)>,
    /// Why the grid's extent is not proven, when it is labelled all the same (see
    /// [`FaceDetection::ambiguous_pose`]).
    pub(super) ambiguous_pose: Option<String>,
}

/// The mappings whose face has the grid's size (directly or turned by 90°).
pub(super) fn by_size(rig: &Rig, d: &Dense) -> Vec<Mapping> {
    let mut out = Vec::new();
    // A face with open sides has no size to match: the board runs on beyond the corners described.
    for (fi, f) in rig
        .faces
        .iter()
        .enumerate()
        .filter(|f| f.1.open_sides.is_empty())
    {
        for turns in 0..4u8 {
            let (r, c) = if turns % 2 == 0 {
                (d.rows, d.cols)
            } else {
                (d.cols, d.rows)
            };
            if (r, c) == (f.rows, f.cols) {
                out.push(Mapping { face: fi, turns });
            }
        }
    }
    out
}

/// White-minus-black mean intensity of the squares of `d` as labelled by `face` (`None` when a
/// square cannot be read).
fn colour_contrast(img: &GrayImage, face: &crate::rig::Face, d: &Dense) -> Option<f64> {
    let mut sums = ColourSums::default();
    for r in 0..d.rows - 1 {
        for c in 0..d.cols - 1 {
            let quad = [
                d.at(r, c),
                d.at(r, c + 1),
                d.at(r + 1, c),
                d.at(r + 1, c + 1),
            ];
            sums.add(
                face.square_colour(r + 1, c + 1),
                mean_square_intensity(img, quad)?,
            );
        }
    }
    sums.contrast()
}

/// The mappings whose predicted square colours the image shows, or why none is.
pub(super) fn by_colours(
    img: &GrayImage,
    rig: &Rig,
    d: &Dense,
    by_size: &[Mapping],
) -> Result<Vec<(Mapping, f64)>, String> {
    let mut read = Vec::new();
    for m in by_size {
        match colour_contrast(img, &rig.faces[m.face], &d.turned(m.turns)) {
            Some(c) => read.push((*m, c)),
            None => {
                return Err("grid touches the image border: square colours cannot be read".into());
            }
        }
    }
    let best = read.iter().map(|r| r.1).fold(f64::NEG_INFINITY, f64::max);
    let kept: Vec<(Mapping, f64)> = read
        .into_iter()
        .filter(|r| r.1 >= MIN_COLOUR_CONTRAST)
        .collect();
    if kept.is_empty() {
        let faces = names(rig, by_size.iter().map(|m| m.face));
        return Err(format!(
            "face '{faces}': square colours do not decide the orientation (white − black = {best:.1} grey levels)"
        ));
    }
    Ok(kept)
}

/// The distinct face names of `faces`, joined.
fn names(rig: &Rig, faces: impl Iterator<Item = usize>) -> String {
    let mut v: Vec<usize> = faces.collect();
    v.sort_unstable();
    v.dedup();
    v.iter()
        .map(|&f| rig.faces[f].name.as_str())
        .collect::<Vec<_>>()
        .join("', '")
}

fn detection(rig: &Rig, w: &Whole, m: Mapping, contrast: f64) -> (FaceDetection, Dense, Mapping) {
    let face = &rig.faces[m.face];
    let d = w.dense.turned(m.turns);
    let corners = (0..d.rows)
        .flat_map(|r| (0..d.cols).map(move |c| (r, c)))
        .map(|(r, c)| LabelledCorner {
            row: r,
            col: c,
            xyz: face.corner_xyz(r, c),
            uv: d.at(r, c),
            sigma_px: d.sigma[r * d.cols + c],
            cov: d.cov[r * d.cols + c],
        })
        // Positions held for the extent only (no window fits there) are no observations.
        .filter(|c| c.sigma_px.is_finite())
        .collect();
    (
        FaceDetection {
            face: m.face,
            corners,
            colour_contrast: contrast,
            ambiguous_pose: w.ambiguous_pose.clone(),
        },
        d,
        m,
    )
}

/// The 2D–3D pairs of the grids under one joint assignment.
fn pairs(rig: &Rig, wholes: &[&Whole], pick: &[Mapping]) -> Vec<(Vector3<f64>, Vector2<f64>)> {
    let mut pts = Vec::new();
    for (w, m) in wholes.iter().zip(pick) {
        let face = &rig.faces[m.face];
        let d = w.dense.turned(m.turns);
        for r in 0..d.rows {
            for c in 0..d.cols {
                pts.push((face.corner_xyz(r, c), d.at(r, c)));
            }
        }
    }
    pts
}

/// Median distance between neighbouring corners of the grids.
fn median_step(wholes: &[&Whole]) -> f64 {
    let mut d = Vec::new();
    for w in wholes {
        let g = &w.dense;
        for r in 0..g.rows {
            for c in 0..g.cols {
                if c + 1 < g.cols {
                    d.push((g.at(r, c + 1) - g.at(r, c)).norm());
                }
                if r + 1 < g.rows {
                    d.push((g.at(r + 1, c) - g.at(r, c)).norm());
                }
            }
        }
    }
    super::complete::median(&mut d).unwrap_or(0.0)
}

/// The joint assignment of every grid to a distinct face that fits one camera clearly best, or why
/// the geometry does not decide.
fn by_geometry(rig: &Rig, wholes: &[&Whole]) -> Result<Vec<(Mapping, f64)>, String> {
    let total: usize = wholes
        .iter()
        .map(|w| w.candidates.len())
        .try_fold(1usize, |a, n| a.checked_mul(n))
        .unwrap_or(usize::MAX);
    if total > MAX_ASSIGNMENTS {
        return Err(format!("{total} assignments to try"));
    }
    let mut scored: Vec<(f64, Vec<usize>)> = Vec::new();
    let mut pick = vec![0usize; wholes.len()];
    'all: loop {
        let maps: Vec<Mapping> = pick
            .iter()
            .zip(wholes)
            .map(|(&k, w)| w.candidates[k].0)
            .collect();
        if repeated(maps.iter().map(|m| m.face)).is_empty()
            && let Some(rms) = dlt_rms(&pairs(rig, wholes, &maps))
        {
            scored.push((rms, pick.clone()));
        }
        for (i, w) in wholes.iter().enumerate() {
            pick[i] += 1;
            if pick[i] < w.candidates.len() {
                continue 'all;
            }
            pick[i] = 0;
        }
        break;
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let Some((best, chosen)) = scored.first().cloned() else {
        return Err("no assignment of distinct faces gives a projection (the grids are coplanar, or claim the same face)".into());
    };
    if let Some((second, _)) = scored.get(1)
        && *second < GEOMETRY_MARGIN * best
    {
        return Err(format!(
            "two assignments fit one camera alike (DLT RMS {best:.2} px and {second:.2} px)"
        ));
    }
    let maps: Vec<Mapping> = chosen
        .iter()
        .zip(wholes)
        .map(|(&k, w)| w.candidates[k].0)
        .collect();
    // Any one face reversed, whatever its colours say.
    for i in 0..maps.len() {
        let mut alt = maps.clone();
        alt[i].turns = (alt[i].turns + 2) % 4;
        if let Some(rms) = dlt_rms(&pairs(rig, wholes, &alt))
            && rms < GEOMETRY_MARGIN * best
        {
            return Err(format!(
                "DLT RMS {best:.2} px vs {rms:.2} px with face '{}' reversed",
                rig.faces[alt[i].face].name
            ));
        }
    }
    let step = median_step(wholes);
    if best > MAX_GEOMETRY_RMS_STEPS * step {
        return Err(format!(
            "the best assignment fits one camera with DLT RMS {best:.2} px, more than {MAX_GEOMETRY_RMS_STEPS} of the grids' step {step:.1} px"
        ));
    }
    Ok(chosen
        .iter()
        .zip(wholes)
        .map(|(&k, w)| w.candidates[k])
        .collect())
}

/// Decide which face each whole grid is (see the module docs).
pub(super) fn identify(rig: &Rig, wholes: Vec<Whole>) -> (Vec<FaceDetection>, Vec<Rejection>) {
    let mut rejected = Vec::new();
    let mut found: Vec<(FaceDetection, Dense, Mapping)> = Vec::new();
    let open = wholes.iter().any(|w| w.candidates.len() > 1);
    let refs: Vec<&Whole> = wholes.iter().collect();
    let geometric = if open && wholes.len() >= 2 {
        Some(by_geometry(rig, &refs))
    } else {
        None
    };
    match geometric {
        Some(Ok(chosen)) => {
            for (w, (m, contrast)) in wholes.iter().zip(chosen) {
                found.push(detection(rig, w, m, contrast));
            }
            return (found.into_iter().map(|f| f.0).collect(), rejected);
        }
        Some(Err(why)) => {
            for w in wholes.iter().filter(|w| w.candidates.len() > 1) {
                rejected.push(Rejection {
                    reason: format!(
                        "{}×{} grid matches several labellings (faces '{}'), not told apart by the rig geometry: {why}",
                        w.dense.rows,
                        w.dense.cols,
                        names(rig, w.candidates.iter().map(|c| c.0.face))
                    ),
                    corners: w.dense.grid_corners(),
                });
            }
        }
        None => {
            for w in wholes.iter().filter(|w| w.candidates.len() > 1) {
                let faces = names(rig, w.candidates.iter().map(|c| c.0.face));
                let one_face = w
                    .candidates
                    .iter()
                    .all(|c| c.0.face == w.candidates[0].0.face);
                if one_face && rig.faces.len() == 1 {
                    // A lone board whose orientation its colours cannot tell: every candidate is
                    // the same lattice turned within the board's plane (handedness is fixed, so
                    // never mirrored), which moves this view's pose and never the intrinsics. The
                    // turn that puts (0, 0) nearest the image's top-left is taken, pose flagged.
                    let Some(&(m, contrast)) = w.candidates.iter().min_by(|a, b| {
                        let at = |m: Mapping| {
                            let d = w.dense.turned(m.turns);
                            let uv = d.at(0, 0);
                            uv.x + uv.y
                        };
                        at(a.0).total_cmp(&at(b.0))
                    }) else {
                        continue;
                    };
                    let mut f = detection(rig, w, m, contrast);
                    let why = format!(
                        "face '{faces}' is 180°-symmetric and alone: its orientation is not decided, the turn putting (0, 0) nearest the image's top-left is taken"
                    );
                    f.0.ambiguous_pose = Some(match f.0.ambiguous_pose.take() {
                        Some(other) => format!("{why}; {other}"),
                        None => why,
                    });
                    found.push(f);
                    continue;
                }
                let reason = if one_face {
                    format!(
                        "face '{faces}' is 180°-symmetric: its orientation cannot be decided from one face"
                    )
                } else {
                    format!(
                        "{}×{} grid matches several faces ('{faces}') and no other grid of the frame fixes the rig geometry",
                        w.dense.rows, w.dense.cols
                    )
                };
                rejected.push(Rejection {
                    reason,
                    corners: w.dense.grid_corners(),
                });
            }
        }
    }
    for w in wholes.iter().filter(|w| w.candidates.len() == 1) {
        let (m, contrast) = w.candidates[0];
        found.push(detection(rig, w, m, contrast));
    }
    // A face found twice is a contradiction: drop both.
    let dup = repeated(found.iter().map(|(f, _, _)| f.face));
    found.retain(|(f, d, _)| {
        let keep = !dup.contains(&f.face);
        if !keep {
            rejected.push(Rejection {
                reason: format!("face '{}' matched by two grids", rig.faces[f.face].name),
                corners: d.grid_corners(),
            });
        }
        keep
    });
    if found.len() >= 2
        && let Err(reason) = check_geometry(rig, &found)
    {
        // Every grid of the contradicted labelling is shown with the reason.
        rejected.extend(found.iter().map(|(_, d, _)| Rejection {
            reason: reason.clone(),
            corners: d.grid_corners(),
        }));
        return (Vec::new(), rejected);
    }
    (found.into_iter().map(|f| f.0).collect(), rejected)
}
