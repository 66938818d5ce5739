//! Neighbouring corners of a view, found from their rig coordinates alone (the solver's views carry
//! no labels).
//!
//! The detector fits each corner in a window that overlaps its neighbours' windows, so the same
//! image noise moves neighbouring corners together (issue 29: +0.08 to +0.17 between grid
//! neighbours on the realistic and hard render sets, `examples/sigma_coverage`), and a lens or
//! board the model does not fit moves a face's neighbouring corners alike. A covariance that takes
//! the corners as independent is then too small; the solver's sandwich covariance (`lm.rs`, both
//! weightings) adds the neighbours' residual cross-products to it.
//!
//! Written here rather than with a k-d tree crate (`kiddo`, `rstar`): a view holds a few hundred
//! points, which a sorted sweep pairs in about 65 ns each (0.10 ms for the solve bench's 1540), and
//! the rule (each point's own nearest distance, both ends agreeing) is a few lines on top of it.

use nalgebra::Vector3;

/// Two points are neighbours when they are at most this factor beyond the nearest point of each
/// (a grid's step; its diagonal, √2 steps, is not a neighbour).
const NEIGHBOUR_SLACK: f64 = 1.05;

/// The axes the search sweeps along and screens with: oblique to every axis plane and to the
/// diagonals, so that the corners of a face, which rig files put in axis planes (all at one `x`,
/// say), spread along them.
const SWEEP: [f64; 3] = [0.8017, 0.5345, 0.2673];
const SCREEN: [f64; 3] = [-0.4082, 0.8165, -0.4082];

/// The pairs `(i, j)`, `i < j`, in no particular order, of points that are grid neighbours: no
/// farther apart than [`NEIGHBOUR_SLACK`] times the distance from each of them to its own nearest
/// point. On a checkerboard's corners these are the row and column neighbours; points that coincide
/// pair with nothing. Found by sweeping the points sorted along [`SWEEP`]: a point's search stops
/// where the gap along that axis alone exceeds the distance sought, and skips candidates whose gap
/// along [`SCREEN`] does.
pub fn grid_neighbours(xyz: &[Vector3<f64>]) -> Vec<(usize, usize)> {
    let (axis, screen) = (
        Vector3::from(SWEEP).normalize(),
        Vector3::from(SCREEN).normalize(),
    );
    let mut order: Vec<usize> = (0..xyz.len()).collect();
    let along: Vec<f64> = xyz.iter().map(|p| p.dot(&axis)).collect();
    order.sort_unstable_by(|&a, &b| along[a].total_cmp(&along[b]));
    // Sorted, structure of arrays: position along the sweep, along the screen, the point.
    let t: Vec<f64> = order.iter().map(|&i| along[i]).collect();
    let w: Vec<f64> = order.iter().map(|&i| xyz[i].dot(&screen)).collect();
    let p: Vec<Vector3<f64>> = order.iter().map(|&i| xyz[i]).collect();
    let n = p.len();
    // Nearest-point distance² of each sorted point: out both ways until the gap along the sweep
    // alone exceeds the best distance found.
    let mut nearest = vec![f64::INFINITY; n];
    for k in 0..n {
        let mut best = f64::INFINITY;
        let mut look = |l: usize| -> bool {
            let dt = t[l] - t[k];
            if dt * dt >= best {
                return false;
            }
            let dw = w[l] - w[k];
            if dw * dw < best {
                let d = (p[l] - p[k]).norm_squared();
                if d > 0.0 && d < best {
                    best = d;
                }
            }
            true
        };
        for l in k + 1..n {
            if !look(l) {
                break;
            }
        }
        for l in (0..k).rev() {
            if !look(l) {
                break;
            }
        }
        nearest[k] = best;
    }
    let slack2 = NEIGHBOUR_SLACK * NEIGHBOUR_SLACK;
    let mut pairs = Vec::new();
    for k in 0..n {
        if !nearest[k].is_finite() {
            continue;
        }
        let reach2 = slack2 * nearest[k];
        for l in k + 1..n {
            let dt = t[l] - t[k];
            if dt * dt > reach2 {
                break;
            }
            let dw = w[l] - w[k];
            if dw * dw > reach2 {
                continue;
            }
            let d = (p[l] - p[k]).norm_squared();
            if d > 0.0 && d <= slack2 * nearest[k].min(nearest[l]) {
                let (i, j) = (order[k], order[l]);
                pairs.push((i.min(j), i.max(j)));
            }
        }
    }
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(cols: usize, rows: usize, step: f64, z: f64) -> Vec<Vector3<f64>> {
        (0..rows)
            .flat_map(|r| (0..cols).map(move |c| Vector3::new(c as f64 * step, r as f64 * step, z)))
            .collect()
    }

    #[test]
    fn a_grid_pairs_its_rows_and_columns_only() {
        let p = grid(5, 4, 30.0, 0.0);
        let pairs = grid_neighbours(&p);
        // 4 per row × 4 rows + 3 per column × 5 columns.
        assert_eq!(pairs.len(), 4 * 4 + 3 * 5);
        for (i, j) in pairs {
            assert!(((p[i] - p[j]).norm() - 30.0).abs() < 1e-9, "{i} {j}");
        }
    }

    #[test]
    fn faces_with_different_steps_and_missing_corners() {
        // A face at z = 0 with 30 mm squares and one at z = 500 with 20 mm squares, one corner of
        // each missing; a lone point far away pairs with nothing.
        let mut p = grid(4, 3, 30.0, 0.0);
        p.remove(5);
        let mut q = grid(3, 3, 20.0, 500.0);
        q.remove(4);
        let n0 = p.len();
        p.extend(q);
        p.push(Vector3::new(1e4, 0.0, 0.0));
        let pairs = grid_neighbours(&p);
        // First face: 3 × 3 + 2 × 4 = 17 edges, less the 4 at the missing interior corner (5 is
        // row 1, col 1). Second: 2 × 3 + 2 × 3 = 12, less the 4 at the centre.
        assert_eq!(pairs.len(), 13 + 8);
        assert!(pairs.iter().all(|&(i, j)| (i < n0) == (j < n0)));
        assert!(pairs.iter().all(|&(_, j)| j != p.len() - 1));
    }
}
