//! Folds: one lattice of corners that bends from one plane to another — a sheet wrapped around a
//! cube's edge, boards meeting at a seam — is cut into per-plane grids before anything is decided
//! about them.
//!
//! On a plane, a lattice is the image of a square grid under a homography (up to the lens's
//! distortion, small over a few squares), so the homography fitted to a few lines of corners
//! predicts the next line. Across a fold it does not: the next line lies on another plane. For each
//! inner line `k` of a grid (each direction), a homography is fitted to the [`WINDOW`] lines ending
//! at `k` and predicts line `k + 1`, and one fitted to the lines starting at `k` predicts line
//! `k − 1`. Only at a fold do both predictions miss — the fold line itself lies on both planes, so
//! on either side of it one of the two windows stays on one plane — and line `k` is a fold when the
//! smaller mean miss of the two exceeds [`FOLD_STEPS`] of the grid's step and [`FOLD_CONTRAST`]
//! times the median over the grid's other lines (strong lens distortion bends every line a little). The grid is cut there: the lines
//! before and after it become two grids, each with its side at the fold marked (a face printed up to
//! the fold ends there; there is no margin to prove it), and the corners on the fold line belong to
//! no face. The strongest fold is cut first and each part is examined again.
//!
//! Measured with `cargo run --release --example detect_cases -- 6` (wrapped cube: one sheet of 30 mm
//! squares around a box edge, k1 −0.3): true folds score 0.26–0.58 of a step against a median of
//! 0.01–0.03 on the same grid; 8 of the 12 faces are found, none mislabelled. On the realistic and
//! hard cube sets no grid is cut (the figures of `detect_eval` are unchanged). Not seen yet: a fold
//! with only one line of corners beyond it (the windows need [`WINDOW`] lines on each side), and two
//! grids assembled separately on either side of a fold (the side at the fold then fails its extent
//! check). On the real inside corner of `bailus_tsai_cube_stereo` (k1 ≈ −0.24 over a 3000 px frame)
//! the fold scores 0.28 against a median of 0.11 and is not cut.

use nalgebra::Vector2;

use super::complete::{Completed, median};
use crate::calib::linear::homography;

/// Lines on each side of a candidate fold used to fit the homography (the fold line included).
pub const WINDOW: usize = 3;
/// Mean prediction miss (fraction of the grid's step) beyond which a line is a fold.
pub const FOLD_STEPS: f64 = 0.2;
/// A fold's miss must also be this many times the median miss of the grid's other lines: lens
/// distortion bends every line a little, a fold one line a lot.
pub const FOLD_CONTRAST: f64 = 3.0;
/// Fewest corners a window needs for its homography.
const MIN_WINDOW_CORNERS: usize = 6;

/// The sides of a grid (in its own row/column indices) that end at a fold.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FoldSides {
    pub first_row: bool,
    pub last_row: bool,
    pub first_col: bool,
    pub last_col: bool,
}

impl FoldSides {
    /// The same sides after transposing the grid.
    pub fn transposed(self) -> FoldSides {
        FoldSides {
            first_row: self.first_col,
            last_row: self.last_col,
            first_col: self.first_row,
            last_col: self.last_row,
        }
    }

    pub fn any(self) -> bool {
        self.first_row || self.last_row || self.first_col || self.last_col
    }
}

/// A grid cut out of a lattice, with its sides at folds.
#[derive(Debug, Clone)]
pub struct Piece {
    pub grid: Completed,
    pub folds: FoldSides,
}

fn transposed(g: &Completed) -> Completed {
    let mut cells = Vec::with_capacity(g.cells.len());
    for c in 0..g.cols {
        for r in 0..g.rows {
            cells.push(g.get(r, c));
        }
    }
    Completed {
        rows: g.cols,
        cols: g.rows,
        cells,
        dropped: g.dropped,
        recovered: g.recovered,
    }
}

/// Columns `range` of `g`.
fn columns(g: &Completed, range: std::ops::Range<usize>) -> Completed {
    let mut cells = Vec::new();
    for r in 0..g.rows {
        for c in range.clone() {
            cells.push(g.get(r, c));
        }
    }
    Completed {
        rows: g.rows,
        cols: range.len(),
        cells,
        dropped: 0,
        recovered: 0,
    }
}

fn step(g: &Completed) -> Option<f64> {
    let mut d = Vec::new();
    for r in 0..g.rows {
        for c in 0..g.cols {
            if let Some(p) = g.get(r, c) {
                for q in [g.get(r, c + 1), g.get(r + 1, c)].into_iter().flatten() {
                    d.push((q.uv - p.uv).norm());
                }
            }
        }
    }
    median(&mut d)
}

/// Mean miss (px) of column `target` predicted by the homography of columns `window`.
fn miss(g: &Completed, window: std::ops::RangeInclusive<usize>, target: usize) -> Option<f64> {
    let (mut plane, mut image) = (Vec::new(), Vec::new());
    for r in 0..g.rows {
        for c in window.clone() {
            if let Some(p) = g.get(r, c) {
                plane.push(Vector2::new(c as f64, r as f64));
                image.push(p.uv);
            }
        }
    }
    if plane.len() < MIN_WINDOW_CORNERS {
        return None;
    }
    let h = homography(&plane, &image).ok()?;
    let (mut sum, mut n) = (0.0, 0usize);
    for r in 0..g.rows {
        if let Some(p) = g.get(r, target) {
            let x = h * nalgebra::Vector3::new(target as f64, r as f64, 1.0);
            if x.z.abs() < 1e-12 {
                return None;
            }
            sum += (Vector2::new(x.x / x.z, x.y / x.z) - p.uv).norm();
            n += 1;
        }
    }
    (n >= 2).then(|| sum / n as f64)
}

/// The strongest fold column of `g` and its score (fraction of the step), if any line is a fold.
fn fold_column(g: &Completed) -> Option<(usize, f64)> {
    let step = step(g)?;
    let mut scores = Vec::new();
    for k in WINDOW - 1..g.cols.saturating_sub(WINDOW - 1) {
        let (Some(a), Some(b)) = (
            miss(g, k + 1 - WINDOW..=k, k + 1),
            miss(g, k..=k + WINDOW - 1, k - 1),
        ) else {
            continue;
        };
        let score = a.min(b) / step;
        tracing::trace!(k, a, b, step, score, "fold score");
        scores.push((k, score));
    }
    let &(k, best) = scores.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let mut others: Vec<f64> = scores.iter().filter(|s| s.0 != k).map(|s| s.1).collect();
    let typical = median(&mut others).unwrap_or(0.0);
    tracing::debug!(k, best, typical, "strongest bend");
    (best > FOLD_STEPS && best > FOLD_CONTRAST * typical).then_some((k, best))
}

/// Cut `g` at its folds (see the module docs). A grid without folds comes back whole.
pub fn split(g: &Completed) -> Vec<Piece> {
    let mut out = Vec::new();
    let mut todo = vec![Piece {
        grid: g.clone(),
        folds: FoldSides::default(),
    }];
    while let Some(p) = todo.pop() {
        // Columns first, then rows (as the columns of the transposed grid).
        if let Some((k, score)) = fold_column(&p.grid) {
            tracing::debug!(k, score, "fold along a column");
            let (g, f) = (&p.grid, p.folds);
            todo.push(Piece {
                grid: columns(g, 0..k),
                folds: FoldSides {
                    last_col: true,
                    ..f
                },
            });
            todo.push(Piece {
                grid: columns(g, k + 1..g.cols),
                folds: FoldSides {
                    first_col: true,
                    ..f
                },
            });
            continue;
        }
        let t = transposed(&p.grid);
        if let Some((k, score)) = fold_column(&t) {
            tracing::debug!(k, score, "fold along a row");
            let f = p.folds.transposed();
            for (range, folds) in [
                (
                    0..k,
                    FoldSides {
                        last_col: true,
                        ..f
                    },
                ),
                (
                    k + 1..t.cols,
                    FoldSides {
                        first_col: true,
                        ..f
                    },
                ),
            ] {
                todo.push(Piece {
                    grid: transposed(&columns(&t, range)),
                    folds: folds.transposed(),
                });
            }
            continue;
        }
        out.push(p);
    }
    out
}
