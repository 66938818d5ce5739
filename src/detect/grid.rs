//! Grid assembly: link X-corners into checkerboard lattices.
//!
//! A seed corner is linked to its nearest neighbours along its two edge directions (each neighbour's own
//! axes must agree with the link, and its polarity must be the opposite, see [`XCorner::dark`]), which
//! fixes the lattice's column (+axis 0) and row (+axis 1) directions. The nearest corner along an edge
//! direction is taken or nothing: when it has the seed's polarity the true neighbour was missed by
//! the front end, and the nearest of opposite polarity would be three steps away, a step that the
//! whole grid would then follow (on the realistic set, frame 4's face at 74° was split into
//! fragments of every other or every third column this way).
//!
//! The lattice then grows cell by cell: the next position along a row or column is predicted by
//! extrapolation from the two or three previous corners (or by the parallel step of a line beside it,
//! up to two lines away), and the nearest unused corner within [`CAPTURE_RADIUS`] steps of the
//! prediction, with compatible axes and the polarity opposite to the corner it is reached from, is
//! taken (so the corner one step across the line, which a foreshortened board can put within the
//! radius, is never taken for it: frame 0 of the hard set lost its top face at 72° that way).
//! Extrapolation over one step tolerates perspective and strong lens distortion, which
//! a global homography would not. Seeds are tried in order of decreasing response; every corner belongs
//! to at most one grid, so several boards (faces) in one frame give several grids.
//!
//! Grid indices are local: which face a grid is, and where its (0, 0) corner lies, is decided later
//! against the rig.

// Ordered maps: the growth order, and so the result, must not depend on hashing (replayed sessions
// must give the same detections).
use std::collections::BTreeMap;

use image::GrayImage;
use nalgebra::Vector2;

use super::front::CornerFinder;
use super::{DetectError, XCorner};

/// Largest number of corners considered (strongest first); bounds the time on cluttered frames.
pub const MAX_CORNERS: usize = 2000;
/// Tolerance on the angle between a link and a corner's edge direction (radians).
pub const AXIS_TOLERANCE: f64 = 0.2;
/// A predicted position captures a corner within this fraction of the local step.
pub const CAPTURE_RADIUS: f64 = 0.3;
/// A predicted position captures a corner at most this fraction of the step across the line from it.
pub const MAX_ACROSS: f64 = 0.5;
/// Largest ratio between a seed's two steps: a face seen at 78° from frontal foreshortens one
/// direction by cos 78° ≈ 1/5.
pub const MAX_STEP_RATIO: f64 = 5.0;
/// Smallest grid kept: at least this many rows and columns.
pub const MIN_LINES: usize = 3;

/// A lattice of corners with local indices.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    pub rows: usize,
    pub cols: usize,
    /// Row-major `rows × cols`: index into the corner list given to [`assemble`], or `None`.
    pub cells: Vec<Option<usize>>,
}

impl Grid {
    pub fn get(&self, row: usize, col: usize) -> Option<usize> {
        if row < self.rows && col < self.cols {
            self.cells[row * self.cols + col]
        } else {
            None
        }
    }

    /// Number of corners in the grid.
    pub fn count(&self) -> usize {
        self.cells.iter().filter(|c| c.is_some()).count()
    }
}

/// Angle between two line directions, modulo π, in `[0, π/2]`.
fn line_angle_diff(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::PI);
    d.min(std::f64::consts::PI - d)
}

fn direction(d: &Vector2<f64>) -> f64 {
    d.y.atan2(d.x).rem_euclid(std::f64::consts::PI)
}

/// Whether `a` and `b` have opposite polarity (see [`XCorner::dark`]): true for neighbours along a row
/// or column, false for diagonal neighbours and corners two steps apart.
fn opposite(a: &XCorner, b: &XCorner) -> bool {
    line_angle_diff(a.dark, b.dark) > std::f64::consts::FRAC_PI_4
}

/// Whether corner `c` has an edge line along `theta` (mod π).
fn has_axis(c: &XCorner, theta: f64) -> bool {
    c.axes
        .iter()
        .any(|&a| line_angle_diff(a, theta) < AXIS_TOLERANCE)
}

struct Builder<'a> {
    corners: &'a [XCorner],
    used: Vec<bool>,
}

impl Builder<'_> {
    /// Nearest unused corner to `p` within `radius` whose axes include the direction `theta` and whose
    /// polarity is opposite to `from`'s (`flip`) or the same.
    fn nearest(
        &self,
        p: &Vector2<f64>,
        radius: f64,
        theta: f64,
        (from, flip): (&XCorner, bool),
        exclude: &dyn Fn(usize) -> bool,
    ) -> Option<usize> {
        let mut best: Option<(usize, f64)> = None;
        for (i, c) in self.corners.iter().enumerate() {
            if self.used[i] || exclude(i) {
                continue;
            }
            let d = (c.uv - p).norm();
            if d < radius
                && has_axis(c, theta)
                && opposite(from, c) == flip
                && best.is_none_or(|(_, bd)| d < bd)
            {
                best = Some((i, d));
            }
        }
        best.map(|(i, _)| i)
    }

    /// Nearest unused corner to `from` in the direction `e` (a unit vector) within
    /// [`AXIS_TOLERANCE`] of it, with an edge line along the link; any polarity.
    fn nearest_along(&self, from: usize, e: Vector2<f64>) -> Option<usize> {
        let p = self.corners[from].uv;
        let axis = direction(&e);
        let mut best: Option<(usize, f64)> = None;
        for (i, c) in self.corners.iter().enumerate() {
            if i == from || self.used[i] {
                continue;
            }

            let d = c.uv - p;
            let dist = d.norm();
            if dist < 2.0 || d.dot(&e) <= 0.0 || best.is_some_and(|(_, bd)| dist >= bd) {
                continue;
            }
            let theta = direction(&d);
            if line_angle_diff(theta, axis) < AXIS_TOLERANCE && has_axis(c, theta) {
                best = Some((i, dist));
            }
        }
        best.map(|(i, _)| i)
    }

    /// The neighbour of `seed` along the edge direction `axis` on the side `sign`: the nearest
    /// corner there, if it has the opposite polarity (else it is two steps away, across a corner the
    /// front end missed). Taking the nearest of opposite polarity instead would link across two or
    /// more missed corners (three steps), and the whole grid would grow on that wrong step.
    fn axis_neighbour(&self, seed: usize, axis: f64, sign: f64) -> Option<usize> {
        let e = Vector2::new(axis.cos(), axis.sin()) * sign;
        let n = self.nearest_along(seed, e)?;
        opposite(&self.corners[seed], &self.corners[n]).then_some(n)
    }

    /// Nearest neighbour along an edge direction, on whichever side is nearer, with the side's sign.
    fn nearer_side(&self, seed: usize, axis: f64) -> Option<(usize, f64)> {
        let p = self.corners[seed].uv;
        let plus = self.axis_neighbour(seed, axis, 1.0);
        let minus = self.axis_neighbour(seed, axis, -1.0);
        let dist = |i: usize| (self.corners[i].uv - p).norm();
        match (plus, minus) {
            (Some(a), Some(b)) if dist(b) < dist(a) => Some((b, -1.0)),
            (Some(a), _) => Some((a, 1.0)),
            (None, Some(b)) => Some((b, -1.0)),
            (None, None) => None,
        }
    }

    fn grow(&mut self, seed: usize) -> Option<BTreeMap<(i32, i32), usize>> {
        let s = self.corners[seed];
        let (right, sr) = self.nearer_side(seed, s.axes[0])?;
        let (down, sd) = self.nearer_side(seed, s.axes[1])?;
        let l0 = (self.corners[right].uv - s.uv).norm();
        let l1 = (self.corners[down].uv - s.uv).norm();
        if !(l0 / l1 > 1.0 / MAX_STEP_RATIO && l0 / l1 < MAX_STEP_RATIO) {
            return None;
        }
        // The seed cell must close: the fourth corner of the square sits where the parallelogram puts it.
        let diagonal = self.corners[right].uv + self.corners[down].uv - s.uv;
        let closing = self.nearest(
            &diagonal,
            CAPTURE_RADIUS * l0.min(l1),
            direction(&(self.corners[right].uv - s.uv)),
            (&s, false),
            &|i| i == seed || i == right || i == down,
        )?;
        let (cr, rd) = (sr as i32, sd as i32);
        tracing::trace!(seed = ?s.uv, right = ?self.corners[right].uv, down = ?self.corners[down].uv, "grid seed");
        let mut cells: BTreeMap<(i32, i32), usize> = BTreeMap::new();
        cells.insert((0, 0), seed);
        cells.insert((0, cr), right);
        cells.insert((rd, 0), down);
        cells.insert((rd, cr), closing);
        let mut member = vec![false; self.corners.len()];
        for i in [seed, right, down, closing] {
            member[i] = true;
        }
        let dirs = [(0, 1), (0, -1), (1, 0), (-1, 0)];
        // Cells whose attempts may succeed in this pass: those within two lines of a corner added in
        // the last one (an attempt reads only the cells that near), so each pass costs what it adds,
        // not the whole grid again (the result is that of retrying every cell).
        let mut dirty: Vec<(i32, i32)> = cells.keys().copied().collect();
        loop {
            let mut added = Vec::new();
            let mut near: std::collections::BTreeSet<(i32, i32)> = Default::default();
            for &(r, c) in &dirty {
                for dr in -2..=2 {
                    for dc in -2..=2 {
                        near.insert((r + dr, c + dc));
                    }
                }
            }
            let filled: Vec<((i32, i32), usize)> = near
                .iter()
                .filter_map(|k| cells.get(k).map(|&v| (*k, v)))
                .collect();
            for ((r, c), idx) in filled {
                for (dr, dc) in dirs {
                    let target = (r + dr, c + dc);
                    if cells.contains_key(&target) {
                        continue;
                    }
                    let p = self.corners[idx].uv;
                    let back1 = cells.get(&(r - dr, c - dc)).map(|&i| self.corners[i].uv);
                    let back2 = cells
                        .get(&(r - 2 * dr, c - 2 * dc))
                        .map(|&i| self.corners[i].uv);
                    let step = if let (Some(p1), Some(p2)) = (back1, back2) {
                        // Quadratic extrapolation follows perspective foreshortening and lens curvature.
                        Some(2.0 * p - 3.0 * p1 + p2)
                    } else if let Some(p1) = back1 {
                        Some(p - p1)
                    } else {
                        // Parallel step of the nearest line beside it (up to two lines away).
                        [(dc, dr), (-dc, -dr), (2 * dc, 2 * dr), (-2 * dc, -2 * dr)]
                            .iter()
                            .find_map(|&(or, oc)| {
                                let a = cells.get(&(r + or, c + oc))?;
                                let b = cells.get(&(r + or + dr, c + oc + dc))?;
                                Some(self.corners[*b].uv - self.corners[*a].uv)
                            })
                    };
                    let Some(step) = step else { continue };
                    let len = step.norm();
                    if len < 2.0 {
                        continue;
                    }
                    let pred = p + step;
                    // The step across the line here: a candidate must be within half of it of the
                    // prediction across, so that on a foreshortened face (steps across a quarter of
                    // the steps along) a diagonal neighbour of the predicted corner, which has its
                    // polarity, is not taken for it.
                    let across = [(dc, dr), (-dc, -dr)]
                        .iter()
                        .find_map(|&(or, oc)| cells.get(&(r + or, c + oc)))
                        .map(|&i| self.corners[i].uv - p)
                        .and_then(|a| nalgebra::Matrix2::from_columns(&[step, a]).try_inverse());
                    let off_line = |i: usize| {
                        across.is_some_and(|inv| {
                            (inv * (self.corners[i].uv - pred)).y.abs() > MAX_ACROSS
                        })
                    };
                    if let Some(j) = self.nearest(
                        &pred,
                        CAPTURE_RADIUS * len,
                        direction(&step),
                        (&self.corners[idx], true),
                        &|i| member[i] || off_line(i),
                    ) {
                        cells.insert(target, j);
                        member[j] = true;
                        added.push(target);
                    }
                }
            }
            if added.is_empty() {
                break;
            }
            dirty = added;
        }
        Some(cells)
    }
}

/// Drops the corner of a boundary row or column that has only that one corner while the line next to
/// it has [`MIN_LINES`] or more, until none is left: one corner beyond the edge of a lattice is more
/// often a structure next to the board (its outer corner against the background is an X-junction
/// too, with a compatible polarity: 4 of the 26 OpenCV sample images) than a line of the board whose
/// other corners the front end all missed; completion recovers the corners of such a line anyway.
fn prune_lone_lines(cells: &mut BTreeMap<(i32, i32), usize>) {
    loop {
        let count = |f: &dyn Fn(&(i32, i32)) -> bool| cells.keys().filter(|k| f(k)).count();
        let (rmin, rmax, cmin, cmax) = cells.keys().fold(
            (i32::MAX, i32::MIN, i32::MAX, i32::MIN),
            |(a, b, c, d), &(r, cc)| (a.min(r), b.max(r), c.min(cc), d.max(cc)),
        );
        let lone = [(rmin, 1), (rmax, -1)]
            .iter()
            .find(|&&(r, d)| count(&|k| k.0 == r) == 1 && count(&|k| k.0 == r + d) >= MIN_LINES)
            .and_then(|&(r, _)| cells.keys().find(|k| k.0 == r).copied())
            .or_else(|| {
                [(cmin, 1), (cmax, -1)]
                    .iter()
                    .find(|&&(c, d)| {
                        count(&|k| k.1 == c) == 1 && count(&|k| k.1 == c + d) >= MIN_LINES
                    })
                    .and_then(|&(c, _)| cells.keys().find(|k| k.1 == c).copied())
            });
        match lone {
            Some(k) => {
                cells.remove(&k);
            }
            None => return,
        }
    }
}

/// Link corners into grids, largest first.
pub fn assemble(corners: &[XCorner]) -> Vec<Grid> {
    let mut order: Vec<usize> = (0..corners.len()).collect();
    order.sort_by(|&a, &b| corners[b].response.total_cmp(&corners[a].response));
    order.truncate(MAX_CORNERS);
    let kept: Vec<XCorner> = order.iter().map(|&i| corners[i]).collect();
    let mut b = Builder {
        corners: &kept,
        used: vec![false; kept.len()],
    };
    let mut grids = Vec::new();
    for seed in 0..kept.len() {
        if b.used[seed] {
            continue;
        }
        let Some(mut cells) = b.grow(seed) else {
            continue;
        };
        prune_lone_lines(&mut cells);
        let (rmin, rmax, cmin, cmax) = cells.keys().fold(
            (i32::MAX, i32::MIN, i32::MAX, i32::MIN),
            |(a, b, c, d), &(r, cc)| (a.min(r), b.max(r), c.min(cc), d.max(cc)),
        );
        let rows = (rmax - rmin + 1) as usize;
        let cols = (cmax - cmin + 1) as usize;
        if rows < MIN_LINES || cols < MIN_LINES || cells.len() < MIN_LINES * MIN_LINES {
            continue;
        }
        let mut grid_cells = vec![None; rows * cols];
        for (&(r, c), &i) in &cells {
            b.used[i] = true;
            grid_cells[(r - rmin) as usize * cols + (c - cmin) as usize] = Some(order[i]);
        }
        grids.push(Grid {
            rows,
            cols,
            cells: grid_cells,
        });
    }
    grids.sort_by_key(|g| std::cmp::Reverse(g.count()));
    grids
}

/// Side of the tiles (px) in which unlinked corners are counted for a second look.
pub const SECOND_LOOK_TILE_PX: u32 = 32;
/// A tile takes part in a second look from this many unlinked corners on.
pub const SECOND_LOOK_TILE_CORNERS: usize = 2;
/// A region gets a second look from this many unlinked corners on.
pub const SECOND_LOOK_MIN_CORNERS: usize = 8;
/// The second look covers at most this fraction of the frame (bounds the time on cluttered frames:
/// the full-resolution pass costs about 4× the first pass per pixel covered).
pub const SECOND_LOOK_MAX_AREA: f64 = 0.2;

/// Regions `[x0, y0, x1, y1]` (px, end exclusive) where the front end found corners that no grid
/// took: tiles of [`SECOND_LOOK_TILE_PX`] with at least [`SECOND_LOOK_TILE_CORNERS`] of them, more
/// than corners of a grid, grown
/// by one tile and joined where they touch, kept when they hold [`SECOND_LOOK_MIN_CORNERS`]; the most
/// populated first, up to [`SECOND_LOOK_MAX_AREA`] of the frame.
///
/// Such scattered corners are what the half-resolution front end leaves of a face whose squares are
/// 3–5 px wide in one direction (at 75–80° from frontal, or small in an image corner under strong
/// distortion): it finds some of them, too few to link.
pub fn unlinked_regions(
    corners: &[XCorner],
    grids: &[Grid],
    width: u32,
    height: u32,
) -> Vec<[u32; 4]> {
    let t = SECOND_LOOK_TILE_PX;
    let (tw, th) = (width.div_ceil(t) as usize, height.div_ceil(t) as usize);
    let mut linked = vec![false; corners.len()];
    for i in grids.iter().flat_map(|g| g.cells.iter().flatten()) {
        linked[*i] = true;
    }
    let tile_of = |c: &XCorner| {
        let (x, y) = (
            c.uv.x.max(0.0) as usize / t as usize,
            c.uv.y.max(0.0) as usize / t as usize,
        );
        (x < tw && y < th).then_some(y * tw + x)
    };
    let mut count = vec![0usize; tw * th];
    let mut linked_count = vec![0usize; tw * th];
    for (c, &l) in corners.iter().zip(&linked) {
        if let Some(k) = tile_of(c) {
            if l {
                linked_count[k] += 1;
            } else {
                count[k] += 1;
            }
        }
    }
    // Tiles with enough unlinked corners, more than linked ones (among a grid's corners, unlinked
    // ones are its rejects, not a face the first pass could not resolve), grown by one tile.
    let mut marked = vec![false; tw * th];
    for (k, _) in count
        .iter()
        .enumerate()
        .filter(|&(k, n)| *n >= SECOND_LOOK_TILE_CORNERS && *n > linked_count[k])
    {
        let (x, y) = (k % tw, k / tw);
        for yy in y.saturating_sub(1)..(y + 2).min(th) {
            for xx in x.saturating_sub(1)..(x + 2).min(tw) {
                marked[yy * tw + xx] = true;
            }
        }
    }
    // Connected regions of marked tiles (4-neighbours), with their corner counts.
    let mut seen = vec![false; tw * th];
    let mut regions: Vec<(usize, [u32; 4])> = Vec::new();
    for start in 0..tw * th {
        if !marked[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let (mut n, mut bx) = (0, [usize::MAX, usize::MAX, 0, 0]);
        while let Some(k) = stack.pop() {
            let (x, y) = (k % tw, k / tw);
            n += count[k];
            bx = [
                bx[0].min(x),
                bx[1].min(y),
                bx[2].max(x + 1),
                bx[3].max(y + 1),
            ];
            let neighbours = [
                (x > 0).then(|| k - 1),
                (x + 1 < tw).then(|| k + 1),
                (y > 0).then(|| k - tw),
                (y + 1 < th).then(|| k + tw),
            ];
            for j in neighbours.into_iter().flatten() {
                if marked[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        if n >= SECOND_LOOK_MIN_CORNERS {
            let px = |v: usize, limit: u32| (v as u32 * t).min(limit);
            regions.push((
                n,
                [
                    px(bx[0], width),
                    px(bx[1], height),
                    px(bx[2], width),
                    px(bx[3], height),
                ],
            ));
        }
    }
    regions.sort_by_key(|(n, r)| (std::cmp::Reverse(*n), *r));
    let budget = SECOND_LOOK_MAX_AREA * f64::from(width) * f64::from(height);
    let mut area = 0.0;
    regions
        .into_iter()
        .filter_map(|(_, r)| {
            let a = f64::from(r[2] - r[0]) * f64::from(r[3] - r[1]);
            (area + a <= budget).then(|| {
                area += a;
                r
            })
        })
        .collect()
}

/// The front end's corners and their grids, with a second, full-resolution look
/// ([`CornerFinder::find_full_res`]) at the [`unlinked_regions`]: the full-resolution corners found
/// there (those near a linked corner left out) are assembled into grids of their own, added to the
/// first pass's, which stay as they were (a face the first pass found is never lost to the second).
pub fn find_and_assemble(
    finder: &mut CornerFinder,
    img: &GrayImage,
) -> Result<(Vec<XCorner>, Vec<Grid>), DetectError> {
    let mut corners = finder.find(img)?;
    let mut grids = assemble(&corners);
    if !finder.second_look() {
        return Ok((corners, grids));
    }
    let regions = unlinked_regions(&corners, &grids, img.width(), img.height());
    if regions.is_empty() {
        return Ok((corners, grids));
    }
    let linked: Vec<Vector2<f64>> = grids
        .iter()
        .flat_map(|g| g.cells.iter().flatten())
        .map(|&i| corners[i].uv)
        .collect();
    let mut second = Vec::new();
    for r in &regions {
        second.extend(finder.find_full_res(img, *r)?.into_iter().filter(|c| {
            linked
                .iter()
                .all(|p| (p - c.uv).norm() > SECOND_LOOK_SAME_PX)
        }));
    }
    let offset = corners.len();
    for mut g in assemble(&second) {
        for i in g.cells.iter_mut().flatten() {
            *i += offset;
        }
        grids.push(g);
    }
    corners.extend(second);
    Ok((corners, grids))
}

/// A full-resolution corner this close (px) to a linked corner is that corner again.
pub const SECOND_LOOK_SAME_PX: f64 = 2.0;

#[cfg(test)]
mod tests {
    use super::*;

    /// Corners of a `cols × rows` checkerboard lattice from `origin` with steps `step` (x, y), with the
    /// polarity that alternates along rows and columns; `keep` selects which (column, row) are found,
    /// `response` gives each its front-end response (which orders the seeds).
    fn lattice_of(
        (cols, rows): (i32, i32),
        origin: Vector2<f64>,
        step: Vector2<f64>,
        keep: impl Fn(i32, i32) -> bool,
        response: impl Fn(i32, i32) -> f64,
    ) -> Vec<XCorner> {
        let mut out = Vec::new();
        for j in 0..rows {
            for i in 0..cols {
                if !keep(i, j) {
                    continue;
                }
                let dark = if (i + j) % 2 == 0 {
                    0.3
                } else {
                    0.3 + std::f64::consts::FRAC_PI_2
                };
                out.push(XCorner {
                    uv: origin + Vector2::new(step.x * f64::from(i), step.y * f64::from(j)),
                    axes: [0.0, std::f64::consts::FRAC_PI_2],
                    dark,
                    response: response(i, j),
                });
            }
        }
        out
    }

    /// A 9 × 7 lattice with a 12 × 8 px step (a foreshortened board).
    fn lattice(keep: impl Fn(i32, i32) -> bool) -> Vec<XCorner> {
        lattice_of(
            (9, 7),
            Vector2::new(100.0, 80.0),
            Vector2::new(12.0, 8.0),
            keep,
            |i, j| 100.0 + f64::from(i + 9 * j),
        )
    }

    #[test]
    fn a_full_lattice_is_one_grid() {
        let corners = lattice(|_, _| true);
        let grids = assemble(&corners);
        assert_eq!(grids.len(), 1);
        assert_eq!((grids[0].count(), grids[0].rows * grids[0].cols), (63, 63));
    }

    /// A dense lattice at the corner cap is one grid, fast: growth retries only the cells near the
    /// corners added in the last pass (before, every cell every pass: 1936 corners took 6.1 s, now
    /// 14 ms in a release build).
    #[test]
    fn a_dense_lattice_is_one_grid() {
        let corners = lattice_of(
            (44, 44),
            Vector2::new(10.0, 10.0),
            Vector2::new(6.0, 6.0),
            |_, _| true,
            |i, j| 100.0 + f64::from((i * 7 + j * 13) % 17),
        );
        let grids = assemble(&corners);
        assert_eq!(grids.len(), 1);
        assert_eq!(
            (grids[0].rows, grids[0].cols, grids[0].count()),
            (44, 44, 1936)
        );
    }

    /// With every other column missed by the front end, the remaining corners still form a lattice
    /// (cells two squares wide), but neighbours along its rows have the same polarity: no grid.
    #[test]
    fn corners_two_steps_apart_are_never_linked() {
        let corners = lattice(|i, _| i % 2 == 0);
        assert!(assemble(&corners).is_empty());
    }

    /// Nor across the two corners the front end missed on either side of the strongest corner: the
    /// nearest corners along its row have its polarity, so it is no seed (the nearest corners of
    /// opposite polarity are three steps away), and the grid grows from another with the true step.
    #[test]
    fn missed_neighbours_do_not_set_the_step() {
        let mut corners = lattice(|i, j| j != 3 || (i != 3 && i != 5));
        for c in &mut corners {
            if (c.uv - Vector2::new(148.0, 104.0)).norm() < 0.1 {
                c.response = 1e4;
            }
        }
        let grids = assemble(&corners);
        for g in &grids {
            for r in 0..g.rows {
                for c in 0..g.cols {
                    for (dr, dc) in [(0, 1), (1, 0)] {
                        if let (Some(a), Some(b)) = (g.get(r, c), g.get(r + dr, c + dc)) {
                            let d = (corners[a].uv - corners[b].uv).norm();
                            assert!(d < 13.0, "link of {d} px");
                        }
                    }
                }
            }
        }
    }
}
