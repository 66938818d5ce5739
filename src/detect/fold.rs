//! Folds: one lattice of corners that bends from one plane to another — a sheet wrapped around a
//! cube's edge, boards meeting at a seam — is cut into per-plane grids before anything is decided
//! about them.
//!
//! Along a line of corners on one plane, perspective and lens distortion bend the spacing and the
//! direction smoothly, so the quadratic through three consecutive corners of a row predicts the
//! next one (`3·p₀ − 3·p₁ + p₂`). Across a fold it does not: the next corner lies on another plane
//! and the row kinks. For each inner line `k` of a grid (each direction), every row's corners at
//! `k, k − 1, k − 2` predict its corner at `k + 1`, and those at `k, k + 1, k + 2` its corner at
//! `k − 1`. Only at a fold do both predictions miss — the fold line itself lies on both planes, so on
//! either side of it one of the two windows stays on one plane — and line `k` is a fold when the
//! smaller mean miss of the two exceeds [`FOLD_STEPS`] of the grid's step and [`FOLD_CONTRAST`] times
//! the median over the grid's other lines. The grid is cut there: the lines before and after it
//! become two grids, each with its side at the fold marked (a face printed up to the fold ends there;
//! there is no margin to prove it), and the corners on the fold line belong to no face. The strongest
//! fold is cut first and each part is examined again.
//!
//! The predictor was a homography fitted to the three lines; it follows perspective exactly but not
//! lens curvature, which bends every line of a strongly distorted grid. Measured (miss in steps, fold
//! vs the grid's median): wrapped cube renders (k1 −0.3, `cargo run --release --example detect_cases
//! -- 6`), homography 0.26–0.36 vs 0.02–0.03 (13–16×), quadratic 0.20–0.25 vs 0.005–0.008 (26–48×);
//! the real inside corner of `bailus_tsai_cube_stereo` (k1 ≈ −0.24 Tsai over a 3000 px frame),
//! homography 0.28 vs 0.11 (2.5×, not cut), quadratic 0.19–0.21 vs 0.006–0.008 (24–32×); lines of
//! unfolded grids (inside-corner renders, the photos' per-wall grids) at most 0.026 with the
//! quadratic; the shallowest fold seen, 0.086 against 0.0024 (a replica of the photos seen almost
//! symmetrically, `photo-corner` frame 4), sets [`FOLD_STEPS`] at 0.05. With the quadratic, 8 of
//! the 12 wrapped-cube faces were found as before, none mislabelled; every case of `detect_cases`
//! kept its figures (the other 4: see [`join`] below).
//!
//! The assembly may also stop at a fold and build the plane beyond it as a second grid (in the right
//! photo the fold line and one line beyond it are in one grid, the rest of the wall in another):
//! [`join`] first joins two grids when the positions one step beyond a side of one (the same
//! quadratic extrapolation) are the corners of a side line of the other, [`MIN_JOINED`] or more of
//! them, all on one lattice line and each within [`JOIN_STEPS`] of the local step on each lattice
//! axis; where the two overlap they must have found the same corners — except on the first grid's
//! lines beyond the matched line, where the second grid's corners replace the first's.
//!
//! That exception and the per-axis tolerance are what the wrapped cube's views 4–5 (the right face
//! at 65–69°) needed. Measured there: the assembly grows the front face across the fold, takes the
//! fold line, and then links a corner three lines further on. The grazing face is so foreshortened
//! that three of its steps match one step of the front face. So the fold is the grid's
//! second-outermost line, where [`split`] cannot test it (one line beyond). In view 5 it then cut
//! nothing; in view 4 it cut the line before the fold instead, because the fold corners are fitted
//! up to 7 px off along the fold (a straight-edge model where the edges bend), which makes the line
//! before them look bent (0.051 step). The grazing face was a grid of its own, and its side at the
//! fold stayed undecided (checkered squares beyond, no corner like its own). Joining it to the
//! other grid failed twice over. The fold corners' 7 px miss was 0.18 of the grazing face's
//! foreshortened row step but only 0.10 of the step along the fold. And the wrongly linked line
//! conflicted with the grazing face's first line. With the join, the fold lies inside the lattice,
//! [`split`] cuts it there (both faces found in all 6 views, `cargo run --release --example
//! detect_cases -- 6`: 8/12 → 12/12, none mislabelled, RMS 0.0096 px).

use nalgebra::Vector2;

use super::complete::{Completed, Fitted, median};

/// Lines on each side of a candidate fold used for the prediction (the fold line included).
pub const WINDOW: usize = 3;
/// Mean prediction miss (fraction of the grid's step) beyond which a line is a fold.
pub const FOLD_STEPS: f64 = 0.05;
/// A fold's miss must also be this many times the median miss of the grid's other lines: lens
/// distortion bends every line a little, a fold one line a lot.
pub const FOLD_CONTRAST: f64 = 5.0;

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

/// Mean miss (px) of column `target` extrapolated along each row from the three columns `from`
/// (nearest to `target` first): quadratic, so it follows a row's perspective and lens curvature.
fn miss_along_rows(g: &Completed, from: [usize; 3], target: usize) -> Option<f64> {
    let (mut sum, mut n) = (0.0, 0usize);
    for r in 0..g.rows {
        if let (Some(p0), Some(p1), Some(p2), Some(t)) = (
            g.get(r, from[0]),
            g.get(r, from[1]),
            g.get(r, from[2]),
            g.get(r, target),
        ) {
            let pred = 3.0 * p0.uv - 3.0 * p1.uv + p2.uv;
            sum += (pred - t.uv).norm();
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
            miss_along_rows(g, [k, k - 1, k - 2], k + 1),
            miss_along_rows(g, [k, k + 1, k + 2], k - 1),
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
    tracing::debug!(
        k,
        best,
        typical,
        rows = g.rows,
        cols = g.cols,
        "strongest bend"
    );
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

/// Largest distance (fraction of the local step) between the position one step beyond a grid's
/// side and a corner of another grid for the two to count as one lattice.
pub const JOIN_STEPS: f64 = 0.15;
/// Fewest corners beyond a grid's side that must coincide with another grid's corners to join them.
pub const MIN_JOINED: usize = 3;

/// Whether `miss` is within [`JOIN_STEPS`] of the lattice's local steps on each axis (`outward`, along
/// a row, and `along` the side): measured in lattice units, since a step across a foreshortened plane
/// can be a fraction of the step along it, and the corners of a fold line, fitted with a model of
/// straight edges where the edges bend, lie off by up to 0.1 step along the fold (measured on the
/// wrapped-cube renders at 65–69°: 7 px of a 70 px step) but not across it.
fn within_lattice_steps(miss: Vector2<f64>, outward: Vector2<f64>, along: Vector2<f64>) -> bool {
    let basis = nalgebra::Matrix2::from_columns(&[outward, along]);
    basis
        .try_inverse()
        .map(|inv| inv * miss)
        .is_some_and(|l| l.x.abs() <= JOIN_STEPS && l.y.abs() <= JOIN_STEPS)
}

/// `g` with its cell `(r, c)` taken from `source(r, c)` of `g` (a relabelling of rows and columns).
fn relabelled(
    g: &Completed,
    rows: usize,
    cols: usize,
    source: impl Fn(usize, usize) -> (usize, usize),
) -> Completed {
    let mut cells = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            let (r0, c0) = source(r, c);
            cells.push(g.get(r0, c0));
        }
    }
    Completed {
        rows,
        cols,
        cells,
        dropped: g.dropped,
        recovered: g.recovered,
    }
}

/// The four relabellings of `g` that bring each of its sides to the last column.
fn sides_last(g: &Completed) -> [Completed; 4] {
    let t = transposed(g);
    let flip = |g: &Completed| relabelled(g, g.rows, g.cols, |r, c| (r, g.cols - 1 - c));
    let (ft, fg) = (flip(&t), flip(g));
    [g.clone(), fg, t, ft]
}

/// Index and position of the corner of `a` nearest to `p`.
fn nearest(a: &Completed, p: Vector2<f64>) -> Option<((i64, i64), Vector2<f64>)> {
    (0..a.rows)
        .flat_map(|r| (0..a.cols).map(move |c| (r, c)))
        .filter_map(|(r, c)| a.get(r, c).map(|f| ((r as i64, c as i64), f.uv)))
        .min_by(|x, y| (x.1 - p).norm().total_cmp(&(y.1 - p).norm()))
}

/// Grid `b` joined to grid `a` when the positions one step beyond one of `b`'s sides (extrapolated
/// along its rows, as in the fold test) are corners of `a` along one lattice line: a lattice that the
/// assembly split into two grids at a fold (the fold line in one grid, the rest of the plane beyond
/// it in the other). On `a`'s lines beyond that line, toward `b`, `b`'s corners replace `a`'s where
/// they differ (`a` went on across the fold by its own prediction and may have skipped
/// foreshortened lines). `None` when they are not one lattice, or when joining would put two
/// different corners in one cell elsewhere.
fn joined(a: &Completed, b: &Completed) -> Option<Completed> {
    'sides: for bv in sides_last(b) {
        if bv.cols < WINDOW {
            continue;
        }
        let k = bv.cols - 1;
        let mut matches: Vec<(usize, (i64, i64))> = Vec::new();
        let mut misses = 0usize;
        for r in 0..bv.rows {
            let (Some(p0), Some(p1), Some(p2)) = (bv.get(r, k), bv.get(r, k - 1), bv.get(r, k - 2))
            else {
                continue;
            };
            let pred = 3.0 * p0.uv - 3.0 * p1.uv + p2.uv;
            // The lattice's two steps here: outward (along the row) and along the side.
            let outward = pred - p0.uv;
            let along = match (
                r.checked_sub(1).and_then(|q| bv.get(q, k)),
                bv.get(r + 1, k),
            ) {
                (Some(q0), Some(q1)) => (q1.uv - q0.uv) / 2.0,
                (None, Some(q1)) => q1.uv - p0.uv,
                (Some(q0), None) => p0.uv - q0.uv,
                (None, None) => Vector2::new(-outward.y, outward.x),
            };
            match nearest(a, pred) {
                Some((idx, uv)) if within_lattice_steps(uv - pred, outward, along) => {
                    matches.push((r, idx))
                }
                other => {
                    tracing::trace!(
                        ?pred,
                        ?outward,
                        ?along,
                        ?other,
                        "no corner of the other grid beyond"
                    );
                    misses += 1
                }
            }
        }
        tracing::trace!(a = ?(a.rows, a.cols), b = ?(b.rows, b.cols), matched = matches.len(), misses, first = ?matches.first(), "join side");
        if matches.len() < MIN_JOINED {
            continue;
        }
        // The matches must lie on one lattice line of `a`, one index per row of `b`.
        let (r0, i0) = matches[0];
        let (r1, i1) = matches[1];
        let dr = r1 as i64 - r0 as i64;
        let d = ((i1.0 - i0.0) / dr, (i1.1 - i0.1) / dr);
        let unit = matches!(d, (0, 1) | (0, -1) | (1, 0) | (-1, 0));
        let on_line = |&(r, i): &(usize, (i64, i64))| {
            let k = r as i64 - r0 as i64;
            i == (i0.0 + k * d.0, i0.1 + k * d.1)
        };
        if !unit || !matches.iter().all(on_line) || misses > matches.len() {
            tracing::debug!(
                matched = matches.len(),
                misses,
                "grids touch but do not join"
            );
            continue;
        }
        // The direction in `a` from the matched line toward `b`'s outermost line: `a`'s next line
        // that way is `b`'s outermost, or `a`'s line before lies on the other side.
        let p0 = bv.get(r0, k)?.uv;
        let m = a.get(i0.0 as usize, i0.1 as usize)?.uv;
        let tol = JOIN_STEPS * (p0 - m).norm();
        let get = |r: i64, c: i64| {
            (r >= 0 && c >= 0)
                .then(|| a.get(r as usize, c as usize))
                .flatten()
        };
        let toward: Vec<(i64, i64)> = [(0i64, 1i64), (0, -1), (1, 0), (-1, 0)]
            .into_iter()
            .filter(|e| e.0 * d.0 + e.1 * d.1 == 0)
            .filter(|e| {
                let next_is_b =
                    get(i0.0 + e.0, i0.1 + e.1).is_some_and(|q| (q.uv - p0).norm() <= tol);
                // The line before lies on the other side (a next line of `a` that is not `b`'s went
                // on across the fold wrongly: `b`'s corners replace it below).
                let behind =
                    get(i0.0 - e.0, i0.1 - e.1).is_some_and(|q| (m - q.uv).dot(&(p0 - m)) > 0.0);
                next_is_b || behind
            })
            .collect();
        let [e] = toward[..] else {
            tracing::debug!(?toward, "grids touch but the side of the join is unclear");
            continue;
        };
        // `b`'s (r, c) goes to `a`'s i0 + (r − r0)·d + (k + 1 − c)·e.
        let map = |r: usize, c: usize| {
            let (s, t) = (r as i64 - r0 as i64, (k + 1 - c) as i64);
            (i0.0 + s * d.0 + t * e.0, i0.1 + s * d.1 + t * e.1)
        };
        let mut cells: Vec<((i64, i64), Fitted)> = Vec::new();
        for r in 0..a.rows {
            for c in 0..a.cols {
                if let Some(f) = a.get(r, c) {
                    cells.push(((r as i64, c as i64), f));
                }
            }
        }
        let from_a = cells.len();
        for r in 0..bv.rows {
            for c in 0..bv.cols {
                if let Some(f) = bv.get(r, c) {
                    cells.push((map(r, c), f));
                }
            }
        }
        let (rmin, rmax) = cells
            .iter()
            .map(|x| x.0.0)
            .fold((i64::MAX, i64::MIN), |m, v| (m.0.min(v), m.1.max(v)));
        let (cmin, cmax) = cells
            .iter()
            .map(|x| x.0.1)
            .fold((i64::MAX, i64::MIN), |m, v| (m.0.min(v), m.1.max(v)));
        let (rows, cols) = ((rmax - rmin + 1) as usize, (cmax - cmin + 1) as usize);
        let mut out: Vec<Option<Fitted>> = vec![None; rows * cols];
        let mut replaced = 0usize;
        for (n, ((r, c), f)) in cells.into_iter().enumerate() {
            let slot = &mut out[(r - rmin) as usize * cols + (c - cmin) as usize];
            // Lines of `a` from the matched line toward `b` (1: the first of `b`'s lines).
            let beyond = (r - i0.0) * e.0 + (c - i0.1) * e.1;
            match slot {
                // Beyond the matched line, `a`'s assembly went on across the fold by its own
                // prediction (on a foreshortened plane it can skip lines: `a` found the fold line
                // and then a corner two lines further on); `b`'s corners there are its own lattice,
                // continuous with the matched line.
                Some(g) if n >= from_a && beyond >= 1 && (g.uv - f.uv).norm() > tol => {
                    *slot = Some(f);
                    replaced += 1;
                }
                // Elsewhere, where the grids overlap, both must have found the same corner.
                Some(g) if (g.uv - f.uv).norm() > tol => {
                    tracing::debug!(?d, ?e, "two grids overlap with different corners");
                    continue 'sides;
                }
                Some(_) => {}
                None => *slot = Some(f),
            }
        }
        tracing::debug!(
            matched = matches.len(),
            rows,
            cols,
            replaced,
            "two grids joined across a fold"
        );
        return Some(Completed {
            rows,
            cols,
            cells: out,
            dropped: a.dropped + b.dropped,
            recovered: a.recovered + b.recovered,
        });
    }
    None
}

/// The grids of a frame with every pair that is one lattice split at a fold joined (see [`joined`]).
pub fn join(grids: &[Completed]) -> Vec<Completed> {
    let mut out: Vec<Completed> = grids.to_vec();
    'again: loop {
        for i in 0..out.len() {
            for j in 0..out.len() {
                if i == j || out[i].count() == 0 || out[j].count() == 0 {
                    continue;
                }
                if let Some(g) = joined(&out[i], &out[j]) {
                    out[i] = g;
                    out.remove(j);
                    continue 'again;
                }
            }
        }
        return out;
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A lattice of `rows` rows and columns `cols` of a sheet folded along column 5: the rows run
    /// along (30, 0) px per column up to the fold and along (20, 8) beyond it, bent a little by a
    /// quadratic "lens" term that every line shares.
    fn sheet(rows: usize, cols: std::ops::Range<usize>) -> Completed {
        let at = |r: usize, c: usize| {
            let (r, c) = (r as f64, c as f64);
            let base = if c <= 5.0 {
                Vector2::new(100.0 + 30.0 * c, 100.0 + 30.0 * r)
            } else {
                Vector2::new(250.0 + 20.0 * (c - 5.0), 100.0 + 30.0 * r + 8.0 * (c - 5.0))
            };
            base + Vector2::new(0.0, 0.002 * (base.x - 300.0).powi(2))
        };
        let n = cols.len();
        let cells = (0..rows)
            .flat_map(|r| cols.clone().map(move |c| (r, c)))
            .map(|(r, c)| Some(Fitted::isotropic(at(r, c), 0.05)))
            .collect();
        Completed {
            rows,
            cols: n,
            cells,
            dropped: 0,
            recovered: 0,
        }
    }

    #[test]
    fn a_fold_under_curvature_is_cut_and_its_sides_marked() {
        let pieces = split(&sheet(6, 0..12));
        let mut sizes: Vec<(usize, usize, FoldSides)> = pieces
            .iter()
            .map(|p| (p.grid.rows, p.grid.cols, p.folds))
            .collect();
        sizes.sort_by_key(|s| s.1);
        assert_eq!(sizes.len(), 2, "{sizes:?}");
        // Columns 0..5 and 6..12; the fold column 5 belongs to neither.
        assert_eq!((sizes[0].0, sizes[0].1), (6, 5));
        assert_eq!((sizes[1].0, sizes[1].1), (6, 6));
        assert!(pieces.iter().all(|p| p.folds.first_col != p.folds.last_col));
        // The same curvature without a fold is not cut.
        assert_eq!(split(&sheet(6, 0..6)).len(), 1);
    }

    #[test]
    fn grids_assembled_on_either_side_of_a_fold_are_joined() {
        // The fold line and one line beyond it in one grid, the rest of the plane in another.
        let joined = join(&[sheet(6, 0..7), sheet(6, 7..12)]);
        assert_eq!(joined.len(), 1);
        assert_eq!((joined[0].rows, joined[0].cols), (6, 12));
        assert_eq!(joined[0], sheet(6, 0..12));
        // Two grids of one plane that do not touch stay apart.
        assert_eq!(join(&[sheet(6, 0..3), sheet(6, 9..12)]).len(), 2);
    }

    #[test]
    fn a_grid_that_ran_on_across_a_fold_yields_to_the_grid_beyond_it() {
        // One grid has the plane up to the fold line (column 5) and then, where the assembly skipped
        // two lines of the other plane, column 8; the other grid is that plane (columns 6..12).
        let whole = sheet(6, 0..12);
        let ran_on = relabelled(&whole, 6, 7, |r, c| (r, if c < 6 { c } else { 8 }));
        let joined = join(&[ran_on, sheet(6, 6..12)]);
        assert_eq!(joined.len(), 1);
        assert_eq!(joined[0], whole);
        // The fold is then inside the lattice and cut there.
        let pieces = split(&joined[0]);
        let mut cols: Vec<usize> = pieces.iter().map(|p| p.grid.cols).collect();
        cols.sort_unstable();
        assert_eq!(cols, [5, 6]);
    }
}
