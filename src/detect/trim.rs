//! Trim: a grid one line larger than a face, whose extra line is mostly empty, is the face.
//!
//! A board printed to the paper's edge, lying on a desk that is bright on one side and dark on the
//! other, shows corner-like junctions along the paper's edge one step beyond the board's last line:
//! the grid grows over a few of them and comes out one line larger than the face, with that line
//! nearly empty ("incomplete grid (157 of 12×14 corners)"). Such a grid is trimmed to the face when
//!
//! * its size is a face's with one line more (rows or columns, either way round),
//! * exactly one face-sized sub-grid of it is complete — over every face of the rig — so which
//!   line is the extra one is not a choice,
//! * the extra line holds at most [`MAX_EXTRA_FRACTION`] of a line's corners, and every position of
//!   it that holds no corner lies inside the image by at least half a lattice step (a line cut by
//!   the frame border proves nothing: the board may continue there).
//!
//! A real board continuing beyond the face would show that line whole. The trimmed side is then
//! taken as the grid's end (its proof is the extra line's emptiness), the other sides still need
//! theirs (`extent`). What a wrong trim could damage: on a planar view, a shift of the labels by
//! one line is a motion of the plane, which changes the view's pose and never the intrinsics; so on
//! a rig of one face the trimmed grid is labelled with its pose flagged
//! ([`super::face::FaceDetection::ambiguous_pose`]). On a rig of several faces the shift would move
//! the face against the others: the trimmed grid is only placed through the frame's proven faces
//! (`place`), as a partial grid is.

use nalgebra::Vector2;

use super::complete::Completed;
use super::fold::FoldSides;
use crate::rig::Rig;

/// The extra line may hold at most this fraction of a line's corners (a continuing board shows it
/// whole, minus the odd failed fit).
pub const MAX_EXTRA_FRACTION: f64 = 0.5;

/// The side of a grid a trim removed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Trimmed {
    FirstRow,
    LastRow,
    FirstCol,
    LastCol,
}

impl Trimmed {
    /// `folds` with this side marked.
    pub(super) fn set(self, folds: &mut FoldSides) {
        match self {
            Trimmed::FirstRow => folds.first_row = true,
            Trimmed::LastRow => folds.last_row = true,
            Trimmed::FirstCol => folds.first_col = true,
            Trimmed::LastCol => folds.last_col = true,
        }
    }

    /// `folds` with this side unmarked.
    pub(super) fn clear(self, mut folds: FoldSides) -> FoldSides {
        match self {
            Trimmed::FirstRow => folds.first_row = false,
            Trimmed::LastRow => folds.last_row = false,
            Trimmed::FirstCol => folds.first_col = false,
            Trimmed::LastCol => folds.last_col = false,
        }
        folds
    }
}

/// A grid trimmed to a face's size: the sub-grid, the side removed and why.
#[derive(Debug, Clone)]
pub(super) struct Trim {
    pub(super) grid: Completed,
    pub(super) side: Trimmed,
    pub(super) reason: String,
}

/// `g` trimmed to the one complete face-sized sub-grid, when the rules above allow (`None` else).
pub(super) fn trim(g: &Completed, rig: &Rig, image_size: [u32; 2]) -> Option<Trim> {
    let sizes: Vec<(usize, usize)> = rig
        .faces
        .iter()
        .filter(|f| f.open_sides.is_empty())
        .flat_map(|f| [(f.rows, f.cols), (f.cols, f.rows)])
        .collect();
    let mut complete: Vec<(Completed, Trimmed)> = Vec::new();
    for side in [
        Trimmed::FirstRow,
        Trimmed::LastRow,
        Trimmed::FirstCol,
        Trimmed::LastCol,
    ] {
        let rows_cut = matches!(side, Trimmed::FirstRow | Trimmed::LastRow);
        let (r, c) = if rows_cut {
            (g.rows.checked_sub(1)?, g.cols)
        } else {
            (g.rows, g.cols.checked_sub(1)?)
        };
        if !sizes.contains(&(r, c)) {
            continue;
        }
        let sub = sub_grid(g, side);
        if sub.count() == sub.rows * sub.cols {
            complete.push((sub, side));
        }
    }
    if complete.len() != 1 {
        return None;
    }
    let (grid, side) = complete.pop()?;
    let line = extra_line(g, side);
    let held = line.iter().filter(|p| p.is_some()).count();
    if held as f64 > MAX_EXTRA_FRACTION * line.len() as f64 {
        return None;
    }
    // Each empty position of the extra line, predicted from the two lines inside it, must lie well
    // inside the image: a line the border cuts may hold a continuing board's corners out of sight.
    let inner = |k: usize, depth: usize| -> Option<Vector2<f64>> {
        let (r, c) = position(g, side, k, depth);
        g.get(r, c).map(|f| f.uv)
    };
    let [w, h] = image_size;
    let (w, h) = (f64::from(w), f64::from(h));
    for (k, p) in line.iter().enumerate() {
        if p.is_some() {
            continue;
        }
        let (a, b) = (inner(k, 1)?, inner(k, 2)?);
        let step = (a - b).norm();
        let at = a + (a - b);
        let margin = 0.5 * step;
        if !(at.x >= margin - 0.5
            && at.y >= margin - 0.5
            && at.x <= w - 0.5 - margin
            && at.y <= h - 0.5 - margin)
        {
            return None;
        }
    }
    let which = match side {
        Trimmed::FirstRow => "first row",
        Trimmed::LastRow => "last row",
        Trimmed::FirstCol => "first column",
        Trimmed::LastCol => "last column",
    };
    let reason = format!(
        "trimmed from {}×{}: its {which} held {held} of {} corners, inside the image (the paper's \
         edge or clutter beyond the board), and exactly one {}×{} sub-grid is complete",
        g.rows,
        g.cols,
        line.len(),
        grid.rows,
        grid.cols
    );
    Some(Trim { grid, side, reason })
}

/// The grid without the line on `side`.
fn sub_grid(g: &Completed, side: Trimmed) -> Completed {
    let (r0, r1, c0, c1) = match side {
        Trimmed::FirstRow => (1, g.rows, 0, g.cols),
        Trimmed::LastRow => (0, g.rows - 1, 0, g.cols),
        Trimmed::FirstCol => (0, g.rows, 1, g.cols),
        Trimmed::LastCol => (0, g.rows, 0, g.cols - 1),
    };
    let mut cells = Vec::with_capacity((r1 - r0) * (c1 - c0));
    for r in r0..r1 {
        for c in c0..c1 {
            cells.push(g.get(r, c));
        }
    }
    Completed {
        rows: r1 - r0,
        cols: c1 - c0,
        cells,
        dropped: 0,
        recovered: 0,
    }
}

/// Grid indices of the `k`-th position of the line `depth` lines inside the line on `side` (depth
/// 0 is that line).
fn position(g: &Completed, side: Trimmed, k: usize, depth: usize) -> (usize, usize) {
    match side {
        Trimmed::FirstRow => (depth, k),
        Trimmed::LastRow => (g.rows - 1 - depth, k),
        Trimmed::FirstCol => (k, depth),
        Trimmed::LastCol => (k, g.cols - 1 - depth),
    }
}

/// The positions (found or not) of the line on `side`.
fn extra_line(g: &Completed, side: Trimmed) -> Vec<Option<Vector2<f64>>> {
    let n = match side {
        Trimmed::FirstRow | Trimmed::LastRow => g.cols,
        Trimmed::FirstCol | Trimmed::LastCol => g.rows,
    };
    (0..n)
        .map(|k| {
            let (r, c) = position(g, side, k, 0);
            g.get(r, c).map(|f| f.uv)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::detect::complete::Fitted;

    fn rig(rows: usize, cols: usize) -> Rig {
        let text = format!(
            "name = \"b\"\nunits = \"mm\"\n[[faces]]\nname = \"board\"\ncols = {cols}\nrows = {rows}\n\
             square_mm = 20.0\nmargin_mm = 0.0\norigin = [0, 0, 0]\ncol_dir = [1, 0, 0]\n\
             row_dir = [0, 1, 0]\n"
        );
        Rig::from_toml_str(&text, "test.toml").unwrap().0
    }

    /// A `rows × cols` grid with 30 px steps from (100, 100), holding the cells `keep` allows.
    fn grid(rows: usize, cols: usize, keep: impl Fn(usize, usize) -> bool) -> Completed {
        let mut cells = Vec::new();
        for r in 0..rows {
            for c in 0..cols {
                let uv = Vector2::new(100.0 + 30.0 * c as f64, 100.0 + 30.0 * r as f64);
                cells.push(keep(r, c).then(|| Fitted::isotropic(uv, 0.02)));
            }
        }
        Completed {
            rows,
            cols,
            cells,
            dropped: 0,
            recovered: 0,
        }
    }

    #[test]
    fn an_extra_column_with_one_corner_is_trimmed_to_the_face() {
        // 5 × 7 corners (rows × cols) on a 5 × 6 face: the last column holds one corner.
        let g = grid(5, 7, |r, c| c < 6 || r == 2);
        let t = trim(&g, &rig(5, 6), [640, 480]).unwrap();
        assert_eq!((t.grid.rows, t.grid.cols, t.side), (5, 6, Trimmed::LastCol));
        assert_eq!(t.grid.count(), 30);
        assert_eq!(t.grid.get(0, 0).unwrap().uv, Vector2::new(100.0, 100.0));
        assert!(t.reason.contains("held 1 of 5"), "{}", t.reason);
        // An extra first row on a grid whose every sub-grid of 5 × 6 or 6 × 5 but one includes it.
        let g = grid(6, 6, |r, c| r > 0 || c == 4);
        let t = trim(&g, &rig(5, 6), [640, 480]).unwrap();
        assert_eq!(
            (t.grid.rows, t.grid.cols, t.side),
            (5, 6, Trimmed::FirstRow)
        );
        assert_eq!(t.grid.get(0, 0).unwrap().uv, Vector2::new(100.0, 130.0));
    }

    #[test]
    fn a_line_that_may_be_a_continuing_board_is_not_trimmed() {
        let face = rig(5, 6);
        // Three of five corners: more than half the line.
        let g = grid(5, 7, |r, c| c < 6 || r < 3);
        assert!(trim(&g, &face, [640, 480]).is_none());
        // One corner, but the line's empty positions lie at the image border (x = 280 in a frame 290
        // wide, less than half a step inside): the border may hide the rest of a bigger board.
        let g = grid(5, 7, |r, c| c < 6 || r == 2);
        assert!(trim(&g, &face, [290, 480]).is_none());
        assert!(trim(&g, &face, [310, 480]).is_some());
        // A hole inside the face: no face-sized sub-grid is complete.
        let g = grid(5, 7, |r, c| (c < 6 || r == 2) && (r, c) != (2, 3));
        assert!(trim(&g, &face, [640, 480]).is_none());
        // No face of that size plus one line.
        let g = grid(5, 7, |r, c| c < 6 || r == 2);
        assert!(trim(&g, &rig(4, 6), [640, 480]).is_none());
    }
}
