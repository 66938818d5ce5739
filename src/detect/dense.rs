//! A complete grid as a dense array of image points, and the relabellings that keep its handedness.

use nalgebra::{Matrix2, Vector2};

/// A complete grid as a dense `rows × cols` array of image points (with their σ), handedness-corrected.
#[derive(Debug, Clone)]
pub(super) struct Dense {
    pub(super) rows: usize,
    pub(super) cols: usize,
    pub(super) uv: Vec<Vector2<f64>>,
    pub(super) sigma: Vec<f64>,
    /// Each point's covariance (px²).
    pub(super) cov: Vec<Matrix2<f64>>,
    /// Each point's fitted edge width (px; 0 where unknown).
    pub(super) edge: Vec<f64>,
}

impl Dense {
    pub(super) fn at(&self, r: usize, c: usize) -> Vector2<f64> {
        self.uv[r * self.cols + c]
    }

    /// A `rows × cols` grid whose cell (r, c) is this grid's `source(r, c)`.
    pub(super) fn remapped(
        &self,
        rows: usize,
        cols: usize,
        source: impl Fn(usize, usize) -> (usize, usize),
    ) -> Dense {
        let mut uv = Vec::with_capacity(self.uv.len());
        let mut sigma = Vec::with_capacity(self.uv.len());
        let mut cov = Vec::with_capacity(self.uv.len());
        let mut edge = Vec::with_capacity(self.uv.len());
        for r in 0..rows {
            for c in 0..cols {
                let (r0, c0) = source(r, c);
                uv.push(self.uv[r0 * self.cols + c0]);
                sigma.push(self.sigma[r0 * self.cols + c0]);
                cov.push(self.cov[r0 * self.cols + c0]);
                edge.push(self.edge[r0 * self.cols + c0]);
            }
        }
        Dense {
            rows,
            cols,
            uv,
            sigma,
            cov,
            edge,
        }
    }

    pub(super) fn transposed(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (c, r))
    }

    /// Rotate the labelling by a quarter turn (keeps handedness): new (r, c) = old (rows − 1 − c, r).
    pub(super) fn quarter_turn(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (self.rows - 1 - c, r))
    }

    pub(super) fn turned(&self, turns: u8) -> Dense {
        let mut d = self.clone();
        for _ in 0..turns {
            d = d.quarter_turn();
        }
        d
    }

    /// Mean 2D cross product of column and row steps (negative for the rig's handedness).
    pub(super) fn handedness(&self) -> f64 {
        let mut s = 0.0;
        for r in 0..self.rows - 1 {
            for c in 0..self.cols - 1 {
                let p = self.at(r, c);
                let a = self.at(r, c + 1) - p;
                let b = self.at(r + 1, c) - p;
                s += a.x * b.y - a.y * b.x;
            }
        }
        s
    }
}
