//! Labelling: which rig face a detected grid is, and which of its corners is `(0, 0)`.
//!
//! Never guessed — a grid is dropped with a reason unless every step is clear:
//! 1. **Handedness.** A face seen from its printed side shows `col_dir` and `row_dir` with a fixed
//!    orientation in the image (`col × row` points toward the camera, so in image coordinates with y
//!    down the 2D cross product of the column and row steps is negative). A grid with the other
//!    orientation is transposed; mirror-image labellings are thereby impossible.
//! 2. **Size.** The (complete) grid's rows × cols must equal a face's, directly or rotated by 90°.
//! 3. **Extent** (`extent`): the size only means something if the board ends where the
//!    grid does. On a rig of one face, a grid of the face's size whose only missing proof is the
//!    frame border, or an incomplete line of corner-like junctions one step beyond a side (the
//!    paper's edge on a two-tone desk), is labelled all the same, its pose flagged
//!    ([`FaceDetection::ambiguous_pose`]): a shift of a planar view's labels within its plane
//!    changes that view's pose, never the intrinsics. A grid that grew over such a line — one line
//!    larger than a face, that line incomplete — is first trimmed to the face (`trim`).
//! 4. **Identity** (`identity`): the face and its orientation, by square colours and,
//!    when they leave a choice (faces of equal size, 180°-symmetric faces), by the rig geometry of
//!    all grids of the frame; with two or more faces the labelling must fit one camera clearly
//!    better than with any face reversed, or the frame's labelling is dropped — unless the
//!    alternatives are one similarity apart (a symmetry of the rig, a lone grid of a shape several
//!    faces share, a lone 180°-symmetric board): those differ in the view's pose only, never in the
//!    intrinsics, so the grid is labelled and its pose flagged ([`FaceDetection::ambiguous_pose`]).
//!
//! Grids that fail the size or extent steps (partially visible faces, incomplete grids) are not
//! labelled by their own evidence: [`super::place`] tries to place them through the rig geometry of
//! the complete faces found here, and reports the ones it cannot place as rejected.

use super::complete::Completed;
use super::dense::Dense;
use super::extent::extent;
use super::fold::{self, Piece};
use super::grid::MIN_LINES;
use super::identity::{self, Whole};
use super::place::{Partial, place, place_by_edges};
use super::trim;
use crate::rig::Rig;
use image::GrayImage;

pub use super::extent::{CONTINUED_CONTRAST, END_UNIFORMITY, MIN_EMPTY_BEYOND};
pub use super::face::{FaceDetection, GridCorner, LabelledCorner, MIN_COLOUR_CONTRAST, Rejection};
pub use super::identity::GEOMETRY_MARGIN;

/// Label the grids of one frame against the rig.
pub fn label(
    img: &GrayImage,
    rig: &Rig,
    grids: &[Completed],
) -> (Vec<FaceDetection>, Vec<Rejection>) {
    let mut rejected = Vec::new();
    let mut whole: Vec<Whole> = Vec::new();
    let mut partials = Vec::new();
    let pieces: Vec<Piece> = fold::join(grids).iter().flat_map(fold::split).collect();
    for Piece { grid: g, folds } in &pieces {
        let mut grid_folds = *folds;
        if g.count() == 0 {
            rejected.push(Rejection::frame(
                "a lattice of X-corners was found but none of its corners fits a checkerboard corner"
                    .into(),
            ));
            continue;
        }
        let mut trimmed: Option<String> = None;
        let trimmed_grid;
        let mut g = g;
        if g.count() != g.rows * g.cols || g.rows < MIN_LINES || g.cols < MIN_LINES {
            let reason = format!(
                "incomplete grid ({} of {}×{} corners)",
                g.count(),
                g.rows,
                g.cols
            );
            let t = (g.rows >= MIN_LINES && g.cols >= MIN_LINES)
                .then(|| trim::trim(g, rig, [img.width(), img.height()]))
                .flatten();
            let Some(t) = t else {
                partials.push(Partial::new(g, grid_folds, reason));
                continue;
            };
            // The trimmed side is a new side of the grid: no fold there.
            grid_folds = t.side.clear(grid_folds);
            if rig.faces.len() > 1 {
                // A shift by one line would move the face against the others: placed through the
                // frame's proven faces only.
                partials.push(Partial::new(
                    &t.grid,
                    grid_folds,
                    format!("{reason}; {}", t.reason),
                ));
                continue;
            }
            trimmed = Some(t.reason);
            trimmed_grid = t.grid;
            g = &trimmed_grid;
            // The trimmed side's proof is the extra line's emptiness (see `trim`).
            let mut ends = grid_folds;
            t.side.set(&mut ends);
            grid_folds = ends;
        }
        let mut folds = grid_folds;
        let mut dense = Dense {
            rows: g.rows,
            cols: g.cols,
            uv: g.cells.iter().flatten().map(|f| f.uv).collect(),
            sigma: g.cells.iter().flatten().map(|f| f.sigma_px).collect(),
            cov: g.cells.iter().flatten().map(|f| f.cov).collect(),
            edge: g.cells.iter().flatten().map(|f| f.edge_px).collect(),
        };
        if dense.handedness() > 0.0 {
            dense = dense.transposed();
            folds = folds.transposed();
        }
        let by_size = identity::by_size(rig, &dense);
        if by_size.is_empty() {
            let reason = format!(
                "{}×{} grid matches no face of rig '{}'",
                dense.rows, dense.cols, rig.name
            );
            partials.push(Partial::new(g, grid_folds, reason));
            continue;
        }
        let ambiguous_pose = match extent(img, &dense, folds) {
            // One face: a shift of the labels by the trimmed line moves this view's pose only.
            Ok(()) if trimmed.is_some() => trimmed.take(),
            Ok(()) => None,
            // One face: a grid of its size cut only by the frame border (or ending at an incomplete
            // line of corner-like junctions) is the whole board or, if the rig file understates the
            // board, a part of it whose labels are shifted within the plane, which moves this
            // view's pose and not the intrinsics. Labelled, pose flagged.
            Err(f) if f.only_border && rig.faces.len() == 1 => Some(match trimmed.take() {
                Some(t) => format!("{t}; {}", f.reason),
                None => f.reason,
            }),
            Err(f) => {
                let reason = match &trimmed {
                    Some(t) => format!("{t}; {}", f.reason),
                    None => f.reason,
                };
                partials.push(Partial::new(g, grid_folds, reason));
                continue;
            }
        };
        match identity::by_colours(img, rig, &dense, &by_size) {
            Ok(candidates) => whole.push(Whole {
                dense,
                candidates,
                ambiguous_pose,
            }),
            Err(reason) => rejected.push(Rejection {
                reason,
                corners: dense.grid_corners(),
            }),
        }
    }
    let (faces, mut not_identified) = identity::identify(rig, whole);
    rejected.append(&mut not_identified);
    // On a rig of several faces, a face labelled only up to a symmetry is no anchor: a partial grid
    // placed against it would inherit the ambiguity without the symmetry that makes it harmless.
    if rig.faces.len() > 1 && faces.iter().any(|f| f.ambiguous_pose.is_some()) {
        rejected.extend(partials.into_iter().map(|p| Rejection {
            reason: format!(
                "{}; not placed on the rig: the frame's complete grids are labelled only up to a symmetry of the rig",
                p.reason
            ),
            corners: p.grid_corners(),
        }));
        return (faces, rejected);
    }
    let (placed, mut contradicted, not_placed) = place(img, rig, &faces, partials);
    let mut faces = faces;
    faces.extend(placed);
    rejected.append(&mut contradicted);
    let (by_edges, mut not_placed) = place_by_edges(img, rig, &faces, not_placed);
    faces.extend(by_edges);
    rejected.append(&mut not_placed);
    (faces, rejected)
}
