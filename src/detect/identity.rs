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
//! the reason — except where the candidates cannot differ in what they teach the camera:
//!
//! **Labellings one similarity apart.** Two labellings of the same image corners whose 3D points
//! are related by a proper similarity (rotation, translation, uniform scale: [`similar`]) project
//! identically for every camera, the pose taking up the motion; no camera, however well known, can
//! tell them apart, and either gives the same intrinsics. That is the case of a lone 180°-symmetric
//! board (its two turns), of a lone grid that fits several faces of equal size (a planar view
//! constrains the camera through its homography up to a similarity of its plane, even the square
//! size drops out), and of a rig that has a symmetry of its own — the two equal, 180°-symmetric
//! walls of an inside corner without its floor, exchanged by a half turn about their diagonal. Such
//! a grid (or the frame's joint assignment) is labelled with one of the alternatives, chosen by a
//! fixed rule, and its pose is flagged ([`FaceDetection::ambiguous_pose`]); any alternative that is
//! not one similarity apart (a shifted lattice, a face reversed against the others, faces of
//! different shapes) still rejects the grid. A flagged face of a rig of several faces is no anchor
//! for placing the frame's partial grids (`place`): their placement would inherit the ambiguity
//! without the symmetry that makes it harmless.

use image::GrayImage;
use std::collections::HashMap;

use nalgebra::{Matrix3, Matrix3x4, Vector2, Vector3};

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
/// Two point sets are one similarity apart when the best similarity maps one onto the other to
/// this fraction of the sets' RMS spread (rig coordinates are exact, so true symmetries reach
/// rounding error, ~1e-15; a shift by one square of a 10-square face is ~0.1).
pub const SIMILARITY_TOLERANCE: f64 = 1e-6;

/// Whether `b` is `a` moved by a proper similarity `b ≈ s·R·a + t` (R a rotation, s > 0), point for
/// point (Umeyama's closed form; `false` for mismatched or degenerate sets).
pub fn similar(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> bool {
    let n = a.len();
    if n != b.len() || n < 3 {
        return false;
    }
    let nf = n as f64;
    let ma = a.iter().sum::<Vector3<f64>>() / nf;
    let mb = b.iter().sum::<Vector3<f64>>() / nf;
    let var_a = a.iter().map(|p| (p - ma).norm_squared()).sum::<f64>() / nf;
    let var_b = b.iter().map(|p| (p - mb).norm_squared()).sum::<f64>() / nf;
    if !(var_a > 0.0 && var_b > 0.0) {
        return false;
    }
    let cov = a
        .iter()
        .zip(b)
        .map(|(p, q)| (q - mb) * (p - ma).transpose())
        .sum::<Matrix3<f64>>()
        / nf;
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return false;
    };
    let mut sign = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        sign[(2, 2)] = -1.0;
    }
    let r = u * sign * v_t;
    let scale = (Matrix3::from_diagonal(&svd.singular_values) * sign).trace() / var_a;
    if scale <= 0.0 {
        return false;
    }
    let t = mb - scale * r * ma;
    let ss = a
        .iter()
        .zip(b)
        .map(|(p, q)| (q - (scale * r * p + t)).norm_squared())
        .sum::<f64>()
        / nf;
    ss.sqrt() <= SIMILARITY_TOLERANCE * var_b.sqrt()
}

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
            edge_px: d.edge[r * d.cols + c],
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
            identity: None,
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

/// The 3D point each grid corner gets under a joint assignment, in the grids' own corner order (so
/// that two assignments' points correspond corner for corner); `None` if a turned grid's corner
/// cannot be matched back.
fn xyz_in_grid_order(rig: &Rig, wholes: &[&Whole], pick: &[Mapping]) -> Option<Vec<Vector3<f64>>> {
    let key = |uv: Vector2<f64>| (uv.x.to_bits(), uv.y.to_bits());
    let mut out = Vec::new();
    for (w, m) in wholes.iter().zip(pick) {
        let face = &rig.faces[m.face];
        let d = w.dense.turned(m.turns);
        let mut by_uv = HashMap::with_capacity(d.rows * d.cols);
        for r in 0..d.rows {
            for c in 0..d.cols {
                by_uv.insert(key(d.at(r, c)), face.corner_xyz(r, c));
            }
        }
        for uv in &w.dense.uv {
            out.push(*by_uv.get(&key(*uv))?);
        }
    }
    Some(out)
}

/// Whether every rival assignment labels the grids one similarity away from `chosen`.
fn all_similar(rig: &Rig, wholes: &[&Whole], chosen: &[Mapping], rivals: &[Vec<Mapping>]) -> bool {
    let Some(base) = xyz_in_grid_order(rig, wholes, chosen) else {
        return false;
    };
    rivals
        .iter()
        .all(|alt| xyz_in_grid_order(rig, wholes, alt).is_some_and(|pts| similar(&base, &pts)))
}

/// How a joint assignment was decided, printed with the face.
struct Decision {
    /// The margin, or the alternatives it could not refute.
    text: String,
    /// The alternatives fit alike but are one similarity apart: pose flagged.
    up_to_similarity: bool,
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
/// the geometry does not decide. Alternatives that fit alike but label the grids one similarity
/// apart (module docs) do not block the decision; they flag it.
fn by_geometry(rig: &Rig, wholes: &[&Whole]) -> Result<(Vec<(Mapping, f64)>, Decision), String> {
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
    let to_maps = |pick: &[usize]| -> Vec<Mapping> {
        pick.iter()
            .zip(wholes)
            .map(|(&k, w)| w.candidates[k].0)
            .collect()
    };
    let maps = to_maps(&chosen);
    // Rivals: other assignments that fit alike, and the chosen one with any one face reversed
    // (whatever its colours say), with the RMS of the closest.
    let mut rivals: Vec<Vec<Mapping>> = Vec::new();
    let mut closest: Option<(f64, String)> = None;
    let note = |rms: f64, what: String, closest: &mut Option<(f64, String)>| {
        if closest.as_ref().is_none_or(|c| rms < c.0) {
            *closest = Some((rms, what));
        }
    };
    for (rms, pick) in scored.iter().skip(1) {
        note(*rms, "the next assignment".into(), &mut closest);
        if *rms < GEOMETRY_MARGIN * best {
            rivals.push(to_maps(pick));
        }
    }
    let mut reversed_rival: Option<(f64, String)> = None;
    for i in 0..maps.len() {
        let mut alt = maps.clone();
        alt[i].turns = (alt[i].turns + 2) % 4;
        if let Some(rms) = dlt_rms(&pairs(rig, wholes, &alt)) {
            let what = format!("face '{}' reversed", rig.faces[alt[i].face].name);
            note(rms, what.clone(), &mut closest);
            if rms < GEOMETRY_MARGIN * best {
                reversed_rival.get_or_insert((rms, what));
                rivals.push(alt);
            }
        }
    }
    let symmetric = !rivals.is_empty() && all_similar(rig, wholes, &maps, &rivals);
    if !rivals.is_empty() && !symmetric {
        if let Some((second, _)) = scored.get(1)
            && *second < GEOMETRY_MARGIN * best
        {
            return Err(format!(
                "two assignments fit one camera alike (DLT RMS {best:.2} px and {second:.2} px)"
            ));
        }
        if let Some((rms, what)) = reversed_rival {
            return Err(format!("DLT RMS {best:.2} px vs {rms:.2} px with {what}"));
        }
    }
    let step = median_step(wholes);
    if best > MAX_GEOMETRY_RMS_STEPS * step {
        return Err(format!(
            "the best assignment fits one camera with DLT RMS {best:.2} px, more than {MAX_GEOMETRY_RMS_STEPS} of the grids' step {step:.1} px"
        ));
    }
    let decision = if symmetric {
        Decision {
            text: format!(
                "labelled up to a symmetry of the rig: {} other labelling(s) fit one camera alike (DLT RMS {best:.2} px) and are one similarity apart, so they differ in this view's pose only, never in the intrinsics",
                rivals.len()
            ),
            up_to_similarity: true,
        }
    } else {
        Decision {
            text: match closest {
                Some((rms, what)) => format!(
                    "decided by the rig geometry: DLT RMS {best:.2} px against {rms:.2} px for {what} ({:.1}× apart, {GEOMETRY_MARGIN}× needed)",
                    rms / best.max(f64::MIN_POSITIVE)
                ),
                None => format!(
                    "decided by the rig geometry: the only assignment that fits one camera (DLT RMS {best:.2} px)"
                ),
            },
            up_to_similarity: false,
        }
    };
    Ok((
        chosen
            .iter()
            .zip(wholes)
            .map(|(&k, w)| w.candidates[k])
            .collect(),
        decision,
    ))
}

/// Flag a face's pose as not trusted, keeping an earlier reason.
fn flag(f: &mut FaceDetection, why: String) {
    f.ambiguous_pose = Some(match f.ambiguous_pose.take() {
        Some(other) => format!("{why}; {other}"),
        None => why,
    });
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
        Some(Ok((chosen, decision))) => {
            for (w, (m, contrast)) in wholes.iter().zip(chosen) {
                let mut f = detection(rig, w, m, contrast);
                f.0.identity = Some(decision.text.clone());
                if decision.up_to_similarity {
                    flag(&mut f.0, decision.text.clone());
                }
                found.push(f);
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
                // A lone grid whose candidates are one similarity apart (module docs): a board
                // whose orientation its colours cannot tell, or a grid that fits several faces of
                // equal shape. Every candidate is the same lattice moved (handedness is fixed, so
                // never mirrored), which moves this view's pose and never the intrinsics. The
                // candidate that puts (0, 0) nearest the image's top-left is taken, pose flagged.
                let alike = wholes.len() == 1 && {
                    let first = [w.candidates[0].0];
                    let rivals: Vec<Vec<Mapping>> =
                        w.candidates[1..].iter().map(|c| vec![c.0]).collect();
                    all_similar(rig, &[w], &first, &rivals)
                };
                if alike {
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
                    let why = if one_face && rig.faces.len() == 1 {
                        format!(
                            "face '{faces}' is 180°-symmetric and alone: its orientation is not decided, the turn putting (0, 0) nearest the image's top-left is taken"
                        )
                    } else {
                        format!(
                            "{}×{} grid is alone in the frame and fits {} labellings (faces '{faces}') one similarity apart: labelled as '{}' with (0, 0) nearest the image's top-left; the others differ in this view's pose only, never in the intrinsics",
                            w.dense.rows,
                            w.dense.cols,
                            w.candidates.len(),
                            rig.faces[m.face].name
                        )
                    };
                    f.0.identity = Some(why.clone());
                    flag(&mut f.0, why);
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn lattice(rows: usize, cols: usize, step: f64) -> Vec<Vector3<f64>> {
        (0..rows)
            .flat_map(|r| {
                (0..cols).map(move |c| Vector3::new(c as f64 * step, r as f64 * step, 0.0))
            })
            .collect()
    }

    #[test]
    fn similar_accepts_a_moved_scaled_copy_and_refuses_shifts_and_mirrors() {
        let a = lattice(6, 8, 28.0);
        let rot = Rotation3::from_euler_angles(0.3, -1.1, 2.0);
        let t = Vector3::new(10.0, -4.0, 300.0);
        let moved: Vec<_> = a.iter().map(|p| 1.7 * (rot * p) + t).collect();
        assert!(similar(&a, &moved));
        // Turned by 180° within the plane (the two labellings of a symmetric board): similar.
        let turned: Vec<_> = a.iter().rev().copied().collect();
        assert!(similar(&a, &turned));
        // The same corners labelled one column further along: not a similarity.
        let shifted: Vec<_> = a
            .iter()
            .map(|p| {
                let c = (p.x / 28.0).round();
                Vector3::new(((c + 1.0) % 8.0) * 28.0, p.y, 0.0)
            })
            .collect();
        assert!(!similar(&a, &shifted));
        // A mirror of a 3D set is not a proper motion.
        let mut solid = a.clone();
        solid.extend(
            lattice(6, 8, 28.0)
                .iter()
                .map(|p| Vector3::new(0.0, p.y, p.x + 28.0)),
        );
        let mirrored: Vec<_> = solid.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        assert!(similar(&solid, &solid));
        assert!(!similar(&solid, &mirrored));
        // Mismatched or degenerate sets.
        assert!(!similar(&a, &a[1..]));
        assert!(!similar(&[Vector3::zeros(); 4], &[Vector3::zeros(); 4]));
    }
}
