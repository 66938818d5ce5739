//! Placing partially visible faces: a grid that is not a whole face (cut by the frame border, or
//! with corners the completion could not fit) is labelled through the rig's rigid geometry, never
//! by its own size.
//!
//! A partial grid's size says nothing about which face it is or where on the face it lies, so it is
//! placed only when the frame also shows completely visible faces, labelled by [`super::label`]
//! with their own proofs (size, extent, colours, geometry). Every candidate placement — each face
//! not already found, each quarter turn (after the handedness correction, so no mirror images), each
//! offset that keeps the grid on the face — is tested:
//! 1. **Colours.** The squares between four found corners must show the candidate's colours (white
//!    minus black at least [`MIN_COLOUR_CONTRAST`]): half of the offsets fail this.
//! 2. **Geometry.** The candidate's 3D corners must fit one camera with the complete faces: with two
//!    or more complete faces (not coplanar) their DLT projection is fixed and the candidate's corners
//!    are reprojected through it; with one, the DLT is fitted to both faces together. The best
//!    candidate's RMS must be [`PLACEMENT_MARGIN`] times smaller than every other's (a wrong offset
//!    moves the whole grid by a square; the DLT ignores lens distortion, which costs every candidate
//!    alike), and below [`MAX_PLACEMENT_RMS_STEPS`] of the grid's step.
//! 3. **Extent.** Through the projection fitted to all faces with the chosen placement, every corner
//!    of the face that the grid lacks, outside the grid's own index range, must fall outside the
//!    image or within one grid step of its border: a face that would show corners well inside the
//!    frame that were not found is not what the grid is (or the frame hides part of it for a reason
//!    the detector cannot see). Holes inside the grid's range are corners whose fit failed.
//!
//! A face placed by two grids is a contradiction: both are dropped.
//!
//! Grids cut at a fold that this cannot place (no complete face in the frame) are placed by their
//! visible pattern ends
//! in [`place_by_edges`]: a side at a fold of the lattice goes to a fold side of a face (computed from
//! the rig: the line one step beyond it is also one step beyond another face's side), a side beyond
//! which the squares give way to a uniform surface goes to a side of a face that is neither open nor at
//! a fold, and those ends must fix the grid's offset on both axes; the colours, one camera for all
//! such grids of the frame (clear winner) and the extent through that camera must agree as above. A
//! single cut board stays unplaced: one plane cannot confirm it. Measured on the real inside corner
//! of `bailus_tsai_cube_stereo` (`cargo test --release --test detect_photo -- --nocapture`): both walls
//! in both photos, DLT RMS 32–33 px against a step of 164–169 px (the lens's barrel distortion; the
//! only assignment its pattern ends allow); every hand-labelled point matched at its rig position.
//!
//! Measured with `PAN_DEG=θ cargo run --release --example detect_eval -- SET 24 DIR` (the set's views
//! with the camera turned by ±θ, so that the cube is cut by the border): realistic, θ = 30°: 41
//! partially visible faces, 23 placed with 1176 of their 1222 visible corners, none mislabelled,
//! RMS 0.036 px; 13 of the others had no complete face beside them. Hard (k1 −0.3), θ = 38°: 28
//! partially visible faces, 3 placed, 20 with no complete face; one corner of a placed face (77.6°
//! from frontal, near the image's left border) is 1.1 px from the truth with σ 0.11 px — a
//! refinement bias at the periphery of that lens (its neighbours are labelled right, several
//! corners of whole faces there are 0.5–0.9 px off), not a placement error. Without the pan, the
//! incomplete grids of whole faces that completion could not finish are placed too (realistic 63 →
//! 64 of 70 whole faces, hard 49 → 51 of 66).

use image::GrayImage;
use nalgebra::{Matrix3x4, Vector2, Vector3};

use super::complete::{Completed, median};
use super::dense::Dense;
use super::extent::{MIN_EMPTY_BEYOND, Side, look_beyond};
use super::face::{self, FaceDetection, LabelledCorner, MIN_COLOUR_CONTRAST, Rejection};
use super::fold::FoldSides;
use super::identity::{ColourSums, dlt_fit, mean_square_intensity, repeated, reprojection_rms};
use crate::rig::{Face, FaceSide, Rig};

/// The best placement's geometric RMS must be this many times smaller than any other's.
pub const PLACEMENT_MARGIN: f64 = 3.0;
/// The best placement's geometric RMS may be at most this fraction of the grid's median step.
pub const MAX_PLACEMENT_RMS_STEPS: f64 = 0.25;
/// Fewest corners a partial grid needs to be placed.
pub const MIN_PARTIAL_CORNERS: usize = 6;

/// One found corner of a partial grid, by its grid index.
#[derive(Debug, Clone, Copy)]
struct GridCorner {
    r: usize,
    c: usize,
    uv: Vector2<f64>,
    sigma_px: f64,
    cov: nalgebra::Matrix2<f64>,
    edge_px: f64,
}

/// A grid that could not be labelled as a whole face, with the reason it was not.
#[derive(Debug, Clone)]
pub(super) struct Partial {
    rows: usize,
    cols: usize,
    corners: Vec<GridCorner>,
    /// The grid's sides at a fold (in its own indices).
    folds: FoldSides,
    pub(super) reason: String,
}

impl Partial {
    pub(super) fn new(g: &Completed, folds: FoldSides, reason: String) -> Partial {
        let corners = (0..g.rows)
            .flat_map(|r| (0..g.cols).map(move |c| (r, c)))
            .filter_map(|(r, c)| {
                // Positions held for the extent only (no window fits there) are no observations.
                g.get(r, c).filter(|f| f.is_measured()).map(|f| GridCorner {
                    r,
                    c,
                    uv: f.uv,
                    sigma_px: f.sigma_px,
                    cov: f.cov,
                    edge_px: f.edge_px,
                })
            })
            .collect();
        Partial {
            rows: g.rows,
            cols: g.cols,
            corners,
            folds,
            reason,
        }
    }

    pub(super) fn grid_corners(&self) -> Vec<face::GridCorner> {
        self.corners
            .iter()
            .map(|g| face::GridCorner {
                row: g.r,
                col: g.c,
                uv: g.uv,
            })
            .collect()
    }

    fn index(&self) -> Vec<Option<usize>> {
        let mut idx = vec![None; self.rows * self.cols];
        for (k, p) in self.corners.iter().enumerate() {
            idx[p.r * self.cols + p.c] = Some(k);
        }
        idx
    }

    /// Mean 2D cross product of column and row steps (negative for the rig's handedness).
    fn handedness(&self) -> f64 {
        let idx = self.index();
        let at = |r: usize, c: usize| idx[r * self.cols + c].map(|k| self.corners[k].uv);
        let mut s = 0.0;
        for r in 0..self.rows.saturating_sub(1) {
            for c in 0..self.cols.saturating_sub(1) {
                if let (Some(p), Some(a), Some(b)) = (at(r, c), at(r, c + 1), at(r + 1, c)) {
                    let (a, b) = (a - p, b - p);
                    s += a.x * b.y - a.y * b.x;
                }
            }
        }
        s
    }

    fn transposed(&self) -> Partial {
        Partial {
            rows: self.cols,
            cols: self.rows,
            corners: self
                .corners
                .iter()
                .map(|p| GridCorner {
                    r: p.c,
                    c: p.r,
                    ..*p
                })
                .collect(),
            folds: self.folds.transposed(),
            reason: self.reason.clone(),
        }
    }

    /// Median distance between grid neighbours, px (`None` when no two found corners are neighbours).
    fn step(&self) -> Option<f64> {
        let idx = self.index();
        let mut d = Vec::new();
        for p in &self.corners {
            for (dr, dc) in [(0, 1), (1, 0)] {
                let (r, c) = (p.r + dr, p.c + dc);
                if r < self.rows
                    && c < self.cols
                    && let Some(k) = idx[r * self.cols + c]
                {
                    d.push((self.corners[k].uv - p.uv).norm());
                }
            }
        }
        median(&mut d)
    }
}

/// One candidate placement: grid index `(r, c)` goes to face corner `turn(r, c) + offset`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Placement {
    face: usize,
    turns: u8,
    offset: (usize, usize),
}

/// Grid index `(r, c)` of a `rows × cols` grid after `turns` quarter turns, and the turned size.
fn turn(r: usize, c: usize, rows: usize, cols: usize, turns: u8) -> (usize, usize) {
    let (mut r, mut c, mut rows, mut cols) = (r, c, rows, cols);
    for _ in 0..turns {
        (r, c) = (c, rows - 1 - r);
        std::mem::swap(&mut rows, &mut cols);
    }
    (r, c)
}

fn turned_size(rows: usize, cols: usize, turns: u8) -> (usize, usize) {
    if turns.is_multiple_of(2) {
        (rows, cols)
    } else {
        (cols, rows)
    }
}

impl Placement {
    fn map(&self, p: &Partial, r: usize, c: usize) -> (usize, usize) {
        let (r, c) = turn(r, c, p.rows, p.cols, self.turns);
        (r + self.offset.0, c + self.offset.1)
    }
}

/// Place the partial grids of one frame on the faces not found complete. Returns the placed faces,
/// the rejections of contradicting placements, and the grids that could not be placed with the
/// reason why (for [`place_by_edges`]).
pub(super) fn place(
    img: &GrayImage,
    rig: &Rig,
    complete: &[FaceDetection],
    partials: Vec<Partial>,
) -> (Vec<FaceDetection>, Vec<Rejection>, Vec<(Partial, String)>) {
    let mut placed: Vec<FaceDetection> = Vec::new();
    let mut rejected = Vec::new();
    let mut not_placed = Vec::new();
    for p in partials {
        match place_one(img, rig, complete, &p) {
            Ok(f) => placed.push(f),
            Err(why) => not_placed.push((p, why)),
        }
    }
    let dup = repeated(placed.iter().map(|f| f.face));
    placed.retain(|f| {
        let keep = !dup.contains(&f.face);
        if !keep {
            rejected.push(Rejection {
                reason: format!(
                    "face '{}' placed by two partial grids",
                    rig.faces[f.face].name
                ),
                corners: f
                    .corners
                    .iter()
                    .map(|c| face::GridCorner {
                        row: c.row,
                        col: c.col,
                        uv: c.uv,
                    })
                    .collect(),
            });
        }
        keep
    });
    (placed, rejected, not_placed)
}

fn place_one(
    img: &GrayImage,
    rig: &Rig,
    complete: &[FaceDetection],
    p: &Partial,
) -> Result<FaceDetection, String> {
    if complete.is_empty() {
        // A lone partial grid is not placed by its own evidence: fuzzing found random content and
        // another board cut by the border that a face's visible end, square colours and the border
        // would place (see the report of issue 19).
        return Err("no completely visible face in the frame to place it against".into());
    }
    if p.corners.len() < MIN_PARTIAL_CORNERS || p.rows < 2 || p.cols < 2 {
        return Err(format!(
            "{} corners in {}×{}: too few to place",
            p.corners.len(),
            p.rows,
            p.cols
        ));
    }
    let p = if p.handedness() > 0.0 {
        p.transposed()
    } else {
        p.clone()
    };
    let Some(step) = p.step() else {
        return Err("no two of its corners are neighbours".into());
    };
    // The squares between four found corners, by their first corner's grid index.
    let idx = p.index();
    let at = |r: usize, c: usize| idx[r * p.cols + c].map(|k| p.corners[k].uv);
    let mut squares = Vec::new();
    for r in 0..p.rows - 1 {
        for c in 0..p.cols - 1 {
            if let (Some(a), Some(b), Some(d), Some(e)) =
                (at(r, c), at(r, c + 1), at(r + 1, c), at(r + 1, c + 1))
                && let Some(v) = mean_square_intensity(img, [a, b, d, e])
            {
                squares.push((r, c, v));
            }
        }
    }
    if squares.is_empty() {
        return Err("no whole square between its corners: colours cannot be read".into());
    }
    let known: Vec<(Vector3<f64>, Vector2<f64>)> = complete
        .iter()
        .flat_map(|f| f.corners.iter().map(|c| (c.xyz, c.uv)))
        .collect();
    let fixed = dlt_fit(&known);
    let taken: Vec<usize> = complete.iter().map(|f| f.face).collect();
    let mut scored: Vec<(f64, Placement, f64)> = Vec::new();
    let mut pts = known.clone();
    for (fi, face) in rig.faces.iter().enumerate() {
        if taken.contains(&fi) {
            continue;
        }
        for turns in 0..4u8 {
            let (tr, tc) = turned_size(p.rows, p.cols, turns);
            if tr > face.rows || tc > face.cols {
                continue;
            }
            for dr in 0..=face.rows - tr {
                for dc in 0..=face.cols - tc {
                    let pl = Placement {
                        face: fi,
                        turns,
                        offset: (dr, dc),
                    };
                    let mut sums = ColourSums::default();
                    for &(r, c, v) in &squares {
                        // The square's corner nearest the face's (0, 0) after the turn.
                        let (r0, c0) = [(r, c), (r, c + 1), (r + 1, c), (r + 1, c + 1)]
                            .iter()
                            .map(|&(a, b)| pl.map(&p, a, b))
                            .fold((usize::MAX, usize::MAX), |m, x| {
                                (m.0.min(x.0), m.1.min(x.1))
                            });
                        sums.add(face.square_colour(r0 + 1, c0 + 1), v);
                    }
                    let Some(contrast) = sums.contrast() else {
                        continue;
                    };
                    if contrast < MIN_COLOUR_CONTRAST {
                        continue;
                    }
                    let cand = p.corners.iter().map(|g| {
                        let (r, c) = pl.map(&p, g.r, g.c);
                        (face.corner_xyz(r, c), g.uv)
                    });
                    let rms = match &fixed {
                        Some(pm) => reprojection_rms(pm, &cand.collect::<Vec<_>>()),
                        None => {
                            pts.truncate(known.len());
                            pts.extend(cand);
                            dlt_fit(&pts).and_then(|pm| reprojection_rms(&pm, &pts))
                        }
                    };
                    if let Some(rms) = rms {
                        scored.push((rms, pl, contrast));
                    }
                }
            }
        }
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let Some(&(best, pl, contrast)) = scored.first() else {
        return Err("no face and offset of the rig shows its square colours".into());
    };
    let face = &rig.faces[pl.face];
    if let Some(&(second, other, _)) = scored.get(1)
        && second < PLACEMENT_MARGIN * best
    {
        return Err(format!(
            "ambiguous: on face '{}' at offset {:?} it fits the camera with RMS {best:.2} px, on face '{}' at offset {:?} with {second:.2} px",
            face.name, pl.offset, rig.faces[other.face].name, other.offset
        ));
    }
    if best > MAX_PLACEMENT_RMS_STEPS * step {
        return Err(format!(
            "its best placement (face '{}') fits the camera with RMS {best:.2} px, more than {MAX_PLACEMENT_RMS_STEPS} of its step {step:.1} px",
            face.name
        ));
    }
    let corners = placed_corners(rig, &p, &pl);
    // Extent: the face's other corners must lie outside the frame (or hug its border).
    let mut all = known;
    all.extend(corners.iter().map(|c| (c.xyz, c.uv)));
    let pm = dlt_fit(&all).ok_or("the faces are coplanar: the rig geometry cannot place it")?;
    if let Some((r, c, u, v)) = lacked_corner_in_frame(&pm, face, &corners, step, img) {
        return Err(format!(
            "as face '{}' it would show corner ({r}, {c}) inside the frame at ({u:.0}, {v:.0}), which it lacks",
            face.name
        ));
    }
    Ok(FaceDetection {
        face: pl.face,
        corners,
        colour_contrast: contrast,
        ambiguous_pose: None,
        identity: None,
    })
}

/// What a partial grid shows beyond one of its sides.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SideEvidence {
    /// The lattice bends onto another plane there (a fold found by [`super::fold`]).
    Fold,
    /// The pattern visibly ends there: one step beyond, the squares give way to a uniform surface.
    End,
    /// Nothing proven (the frame border, or squares that may continue).
    Open,
}

/// The grid side that a face side `side` of the turned grid comes from, and back: one quarter turn
/// takes (r, c) to (c, rows − 1 − r) (see [`turn`]).
fn turned_side(side: FaceSide, turns: u8) -> FaceSide {
    let mut s = side;
    for _ in 0..turns {
        s = match s {
            FaceSide::FirstRow => FaceSide::LastCol,
            FaceSide::LastRow => FaceSide::FirstCol,
            FaceSide::FirstCol => FaceSide::FirstRow,
            FaceSide::LastCol => FaceSide::LastRow,
        };
    }
    s
}

/// The face sides that lie on a fold of the rig: the lattice line one step beyond the side is also
/// the line one step beyond a side of another face, on another plane (the two faces are one pattern
/// bent along that line, or two boards meeting there).
pub(super) fn fold_sides(rig: &Rig, fi: usize) -> Vec<FaceSide> {
    let beyond = |f: &crate::rig::Face, side: FaceSide| -> [Vector3<f64>; 2] {
        let (r, c) = (f.rows as f64, f.cols as f64);
        match side {
            FaceSide::FirstRow => [f.lattice_xyz(-1.0, 0.0), f.lattice_xyz(-1.0, 1.0)],
            FaceSide::LastRow => [f.lattice_xyz(r, 0.0), f.lattice_xyz(r, 1.0)],
            FaceSide::FirstCol => [f.lattice_xyz(0.0, -1.0), f.lattice_xyz(1.0, -1.0)],
            FaceSide::LastCol => [f.lattice_xyz(0.0, c), f.lattice_xyz(1.0, c)],
        }
    };
    let face = &rig.faces[fi];
    let tol = 1e-3 * face.square_mm;
    FaceSide::ALL
        .into_iter()
        .filter(|&side| {
            let [a0, a1] = beyond(face, side);
            rig.faces.iter().enumerate().any(|(gi, g)| {
                gi != fi
                    && face.normal().dot(&g.normal()).abs() < 0.99
                    && FaceSide::ALL.into_iter().any(|gs| {
                        let [b0, b1] = beyond(g, gs);
                        let dir = (b1 - b0).normalize();
                        let off = |p: Vector3<f64>| {
                            let d = p - b0;
                            (d - dir * d.dot(&dir)).norm()
                        };
                        off(a0) < tol && off(a1) < tol
                    })
            })
        })
        .collect()
}

impl Partial {
    /// The grid's corners at `(r, c)` if found.
    fn at(&self, idx: &[Option<usize>], r: usize, c: usize) -> Option<Vector2<f64>> {
        idx[r * self.cols + c].map(|k| self.corners[k].uv)
    }

    /// What the image shows one step beyond `side` (the grid's own indices): the longest run of the
    /// outermost line's corners with two corners inward is examined as [`super::extent`] examines a
    /// whole grid's side.
    fn evidence(&self, img: &GrayImage, side: FaceSide) -> SideEvidence {
        let folded = match side {
            FaceSide::FirstRow => self.folds.first_row,
            FaceSide::LastRow => self.folds.last_row,
            FaceSide::FirstCol => self.folds.first_col,
            FaceSide::LastCol => self.folds.last_col,
        };
        if folded {
            return SideEvidence::Fold;
        }
        let idx = self.index();
        let (len, depth) = match side {
            FaceSide::FirstRow | FaceSide::LastRow => (self.cols, self.rows),
            FaceSide::FirstCol | FaceSide::LastCol => (self.rows, self.cols),
        };
        if depth < 3 {
            return SideEvidence::Open;
        }
        let point = |k: usize, i: usize| match side {
            FaceSide::FirstRow => self.at(&idx, k, i),
            FaceSide::LastRow => self.at(&idx, self.rows - 1 - k, i),
            FaceSide::FirstCol => self.at(&idx, i, k),
            FaceSide::LastCol => self.at(&idx, i, self.cols - 1 - k),
        };
        // The longest run of positions along the side with three corners inward.
        let (mut best, mut run) = ((0, 0), (0, 0));
        for i in 0..len {
            if (0..3).all(|k| point(k, i).is_some()) {
                run = if run.1 == 0 {
                    (i, 1)
                } else {
                    (run.0, run.1 + 1)
                };
                if run.1 > best.1 {
                    best = run;
                }
            } else {
                run = (0, 0);
            }
        }
        if best.1 < MIN_EMPTY_BEYOND {
            return SideEvidence::Open;
        }
        let mut uv = Vec::with_capacity(3 * best.1);
        for k in 0..3 {
            uv.extend((best.0..best.0 + best.1).filter_map(|i| point(k, i)));
        }
        let lines = Dense {
            rows: 3,
            cols: best.1,
            sigma: vec![0.0; uv.len()],
            cov: vec![nalgebra::Matrix2::zeros(); uv.len()],
            edge: vec![0.0; uv.len()],
            uv,
        };
        let b = look_beyond(img, &lines, Side::FirstRow);
        let inside = b.n - b.outside;
        let end = b.corners.is_empty()
            && b.undecided == 0
            && b.empty >= MIN_EMPTY_BEYOND
            && 2 * b.empty >= inside;
        tracing::debug!(
            ?side,
            n = b.n,
            outside = b.outside,
            clipped = b.clipped,
            empty = b.empty,
            undecided = b.undecided,
            corners = b.corners.len(),
            end,
            "beyond a partial grid's side"
        );
        if end {
            SideEvidence::End
        } else {
            SideEvidence::Open
        }
    }

    /// The squares between four found corners, by their first corner's grid index, with their mean
    /// intensity.
    fn squares(&self, img: &GrayImage) -> Vec<(usize, usize, f64)> {
        let idx = self.index();
        let mut squares = Vec::new();
        for r in 0..self.rows.saturating_sub(1) {
            for c in 0..self.cols.saturating_sub(1) {
                if let (Some(a), Some(b), Some(d), Some(e)) = (
                    self.at(&idx, r, c),
                    self.at(&idx, r, c + 1),
                    self.at(&idx, r + 1, c),
                    self.at(&idx, r + 1, c + 1),
                ) && let Some(v) = mean_square_intensity(img, [a, b, d, e])
                {
                    squares.push((r, c, v));
                }
            }
        }
        squares
    }
}

/// White-minus-black contrast of the squares of `p` as placed by `pl` (`None` unless both colours
/// are seen).
fn placed_contrast(
    rig: &Rig,
    p: &Partial,
    squares: &[(usize, usize, f64)],
    pl: &Placement,
) -> Option<f64> {
    let face = &rig.faces[pl.face];
    let mut sums = ColourSums::default();
    for &(r, c, v) in squares {
        let (r0, c0) = [(r, c), (r, c + 1), (r + 1, c), (r + 1, c + 1)]
            .iter()
            .map(|&(a, b)| pl.map(p, a, b))
            .fold((usize::MAX, usize::MAX), |m, x| {
                (m.0.min(x.0), m.1.min(x.1))
            });
        sums.add(face.square_colour(r0 + 1, c0 + 1), v);
    }
    sums.contrast()
}

/// The placements of `p` (handedness-corrected) whose offset its visible pattern ends fix: each of
/// its sides at a fold goes to a fold side of the face, each side where the pattern visibly ends to a
/// side of the face that is neither open nor at a fold, and on each axis at least one side fixes
/// where the grid lies on the face. Each must show the face's square colours.
fn edge_placements(
    img: &GrayImage,
    rig: &Rig,
    taken: &[usize],
    p: &Partial,
) -> Result<Vec<(Placement, f64)>, String> {
    let evidence: Vec<(FaceSide, SideEvidence)> = FaceSide::ALL
        .into_iter()
        .map(|s| (s, p.evidence(img, s)))
        .collect();
    // Only a grid cut from a folded lattice: the fold ties it to the plane beyond (fuzzing found a
    // board cut by the border beside a grazing face placed by their margins alone, which no truth
    // confirms).
    if !evidence.iter().any(|e| e.1 == SideEvidence::Fold) {
        return Err(
            "no side at a fold (only grids cut at a fold are placed by their pattern ends)".into(),
        );
    }
    let squares = p.squares(img);
    let mut out = Vec::new();
    for (fi, face) in rig.faces.iter().enumerate() {
        if taken.contains(&fi) {
            continue;
        }
        let folds = fold_sides(rig, fi);
        'turns: for turns in 0..4u8 {
            let (tr, tc) = turned_size(p.rows, p.cols, turns);
            if tr > face.rows || tc > face.cols {
                continue;
            }
            let (mut off_r, mut off_c): (Option<usize>, Option<usize>) = (None, None);
            for &(side, ev) in &evidence {
                if ev == SideEvidence::Open {
                    continue;
                }
                let fs = turned_side(side, turns);
                let fits = match ev {
                    SideEvidence::Fold => folds.contains(&fs),
                    _ => !folds.contains(&fs) && !face.is_open(fs),
                };
                if !fits {
                    continue 'turns;
                }
                let (slot, value) = match fs {
                    FaceSide::FirstRow => (&mut off_r, 0),
                    FaceSide::LastRow => (&mut off_r, face.rows - tr),
                    FaceSide::FirstCol => (&mut off_c, 0),
                    FaceSide::LastCol => (&mut off_c, face.cols - tc),
                };
                if slot.is_some_and(|v| v != value) {
                    continue 'turns;
                }
                *slot = Some(value);
            }
            let (Some(dr), Some(dc)) = (off_r, off_c) else {
                continue;
            };
            let pl = Placement {
                face: fi,
                turns,
                offset: (dr, dc),
            };
            if let Some(contrast) = placed_contrast(rig, p, &squares, &pl)
                && contrast >= MIN_COLOUR_CONTRAST
            {
                out.push((pl, contrast));
            }
        }
    }
    if out.is_empty() {
        let shown: Vec<String> = evidence
            .iter()
            .filter(|e| e.1 != SideEvidence::Open)
            .map(|e| format!("{} {:?}", e.0.as_str(), e.1).to_lowercase())
            .collect();
        return Err(format!(
            "no face of the rig has its pattern ends where the grid's are ({}) with its square colours",
            shown.join(", ")
        ));
    }
    Ok(out)
}

/// A partial grid (handedness-corrected), why [`place`] did not place it, and its placements by
/// its pattern ends with their colour contrast.
type EdgePlaced = (Partial, String, Vec<(Placement, f64)>);

/// The labelled corners of `p` placed by `pl`.
fn placed_corners(rig: &Rig, p: &Partial, pl: &Placement) -> Vec<LabelledCorner> {
    let face = &rig.faces[pl.face];
    p.corners
        .iter()
        .map(|g| {
            let (r, c) = pl.map(p, g.r, g.c);
            LabelledCorner {
                row: r,
                col: c,
                xyz: face.corner_xyz(r, c),
                uv: g.uv,
                sigma_px: g.sigma_px,
                cov: g.cov,
                edge_px: g.edge_px,
            }
        })
        .collect()
}

/// Partial grids cut at a fold, placed by where their pattern visibly ends — at the fold, or where the
/// squares give way to a uniform surface — when the frame shows no complete face to place them
/// against (or [`place`] could not): faces cut by the frame border, such as the walls of an inside
/// corner that run off the picture everywhere but at the fold, the floor and the ceiling. A grid with
/// no side at a fold is not placed this way (fuzzing: a board cut by the border beside a grazing face
/// was placed by their margins alone).
///
/// Each grid's pattern ends fix its offset on a face (see [`edge_placements`]), and its square
/// colours must agree; the faces of all such grids of the frame (with the faces already found) must
/// then fit one camera: every joint assignment of distinct faces is fitted with the normalised DLT,
/// and the best must fit [`PLACEMENT_MARGIN`] times better than any other and within
/// [`MAX_PLACEMENT_RMS_STEPS`] of the grids' step. A grid on one plane alone cannot be confirmed by
/// the geometry and is not placed (a lone board cut by the border: fuzzing found random content and
/// other boards that a visible end and colours would place). Through the fitted camera, every corner
/// of each face that its grid lacks must lie outside the frame or within one step of its border.
pub(super) fn place_by_edges(
    img: &GrayImage,
    rig: &Rig,
    found: &[FaceDetection],
    partials: Vec<(Partial, String)>,
) -> (Vec<FaceDetection>, Vec<Rejection>) {
    let taken: Vec<usize> = found.iter().map(|f| f.face).collect();
    let mut rejected = Vec::new();
    let mut open: Vec<EdgePlaced> = Vec::new();
    for (p, why) in partials {
        let reject = |p: &Partial, more: String| Rejection {
            reason: format!("{}; not placed on the rig: {why}; {more}", p.reason),
            corners: p.grid_corners(),
        };
        if p.corners.len() < MIN_PARTIAL_CORNERS || p.rows < 3 || p.cols < 3 {
            rejected.push(reject(&p, "too small to place by its edges".into()));
            continue;
        }
        let q = if p.handedness() > 0.0 {
            p.transposed()
        } else {
            p.clone()
        };
        match edge_placements(img, rig, &taken, &q) {
            Ok(c) => open.push((q, why, c)),
            Err(more) => rejected.push(reject(&p, more)),
        }
    }
    if open.is_empty() {
        return (Vec::new(), rejected);
    }
    let reject_all = |open: &[EdgePlaced], more: &str| {
        open.iter()
            .map(|(p, why, _)| Rejection {
                reason: format!(
                    "{}; not placed on the rig: {why}; placed by its edges: {more}",
                    p.reason
                ),
                corners: p.grid_corners(),
            })
            .collect::<Vec<_>>()
    };
    let known: Vec<(Vector3<f64>, Vector2<f64>)> = found
        .iter()
        .flat_map(|f| f.corners.iter().map(|c| (c.xyz, c.uv)))
        .collect();
    let total = open
        .iter()
        .map(|o| o.2.len())
        .try_fold(1usize, |a, n| a.checked_mul(n))
        .unwrap_or(usize::MAX);
    if total > super::identity::MAX_ASSIGNMENTS {
        rejected.extend(reject_all(&open, &format!("{total} assignments to try")));
        return (Vec::new(), rejected);
    }
    let mut scored: Vec<(f64, Vec<usize>)> = Vec::new();
    let mut pick = vec![0usize; open.len()];
    'all: loop {
        let faces: Vec<usize> = pick
            .iter()
            .zip(&open)
            .map(|(&k, o)| o.2[k].0.face)
            .collect();
        if repeated(faces.into_iter()).is_empty() {
            let mut pts = known.clone();
            for (&k, (p, _, c)) in pick.iter().zip(&open) {
                pts.extend(
                    placed_corners(rig, p, &c[k].0)
                        .iter()
                        .map(|c| (c.xyz, c.uv)),
                );
            }
            if let Some(rms) = dlt_fit(&pts).and_then(|pm| reprojection_rms(&pm, &pts)) {
                scored.push((rms, pick.clone()));
            }
        }
        for (i, o) in open.iter().enumerate() {
            pick[i] += 1;
            if pick[i] < o.2.len() {
                continue 'all;
            }
            pick[i] = 0;
        }
        break;
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let Some((best, chosen)) = scored.first().cloned() else {
        rejected.extend(reject_all(
            &open,
            "no assignment of distinct faces fits a camera (the grids are coplanar, or a lone grid: one plane does not confirm the placement)",
        ));
        return (Vec::new(), rejected);
    };
    if let Some((second, _)) = scored.get(1)
        && *second < PLACEMENT_MARGIN * best
    {
        rejected.extend(reject_all(
            &open,
            &format!(
                "two assignments fit one camera alike (DLT RMS {best:.2} px and {second:.2} px)"
            ),
        ));
        return (Vec::new(), rejected);
    }
    let mut steps: Vec<f64> = open.iter().filter_map(|o| o.0.step()).collect();
    let step = median(&mut steps).unwrap_or(0.0);
    if best > MAX_PLACEMENT_RMS_STEPS * step {
        rejected.extend(reject_all(
            &open,
            &format!("the best assignment fits one camera with DLT RMS {best:.2} px, more than {MAX_PLACEMENT_RMS_STEPS} of the step {step:.1} px"),
        ));
        return (Vec::new(), rejected);
    }
    let placed: Vec<FaceDetection> = chosen
        .iter()
        .zip(&open)
        .map(|(&k, (p, _, c))| FaceDetection {
            face: c[k].0.face,
            corners: placed_corners(rig, p, &c[k].0),
            colour_contrast: c[k].1,
            ambiguous_pose: None,
            identity: None,
        })
        .collect();
    // Extent: each face's corners that its grid lacks lie outside the frame (or hug its border).
    let mut all = known;
    all.extend(
        placed
            .iter()
            .flat_map(|f| f.corners.iter().map(|c| (c.xyz, c.uv))),
    );
    let Some(pm) = dlt_fit(&all) else {
        rejected.extend(reject_all(&open, "the faces are coplanar"));
        return (Vec::new(), rejected);
    };
    for f in &placed {
        let face = &rig.faces[f.face];
        if let Some((r, c, u, v)) = lacked_corner_in_frame(&pm, face, &f.corners, step, img) {
            rejected.extend(reject_all(
                &open,
                &format!("as face '{}' its grid would show corner ({r}, {c}) inside the frame at ({u:.0}, {v:.0}), which it lacks", face.name),
            ));
            return (Vec::new(), rejected);
        }
    }
    tracing::debug!(
        best,
        step,
        faces = placed.len(),
        "partial grids placed by their pattern ends"
    );
    (placed, rejected)
}

/// The first corner of `face` outside the rig-position box of `corners` that the camera `pm`
/// projects in front of it and inside the frame, more than `step` from its border: a corner the
/// grid would show but lacks, so the placement's extent is wrong. `(row, col, u, v)`.
fn lacked_corner_in_frame(
    pm: &Matrix3x4<f64>,
    face: &Face,
    corners: &[LabelledCorner],
    step: f64,
    img: &GrayImage,
) -> Option<(usize, usize, f64, f64)> {
    let (rmin, rmax) = corners
        .iter()
        .fold((usize::MAX, 0), |m, c| (m.0.min(c.row), m.1.max(c.row)));
    let (cmin, cmax) = corners
        .iter()
        .fold((usize::MAX, 0), |m, c| (m.0.min(c.col), m.1.max(c.col)));
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    (0..face.rows)
        .flat_map(|r| (0..face.cols).map(move |c| (r, c)))
        .filter(|(r, c)| !((rmin..=rmax).contains(r) && (cmin..=cmax).contains(c)))
        .find_map(|(r, c)| {
            let x = pm * face.corner_xyz(r, c).push(1.0);
            let (u, v) = (x.x / x.z, x.y / x.z);
            (x.z > 0.0 && u > step && v > step && u < w - 1.0 - step && v < h - 1.0 - step)
                .then_some((r, c, u, v))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turns_match_the_quarter_turn_of_a_grid() {
        // A 2×3 grid turned once is 3×2; its (0, 0) goes to (0, rows − 1) = (0, 1).
        assert_eq!(turn(0, 0, 2, 3, 1), (0, 1));
        assert_eq!(turn(1, 2, 2, 3, 1), (2, 0));
        // Four turns are the identity.
        for r in 0..2 {
            for c in 0..3 {
                assert_eq!(turn(r, c, 2, 3, 4), (r, c));
            }
        }
        assert_eq!(turned_size(2, 3, 1), (3, 2));
    }
}
