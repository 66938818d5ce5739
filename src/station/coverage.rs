//! Coverage of the image by accepted corners: a `cols × rows` grid of cells over the frame; a cell is
//! covered when at least one accepted corner lies in it. Corners near the image edges and corners are
//! what determine the distortion, so the verdict asks for a covered fraction, and the hint names the
//! image regions that are still empty.

use nalgebra::Vector2;

/// The coverage grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    pub cols: usize,
    pub rows: usize,
    pub width: u32,
    pub height: u32,
    /// Corner count per cell, row-major.
    pub counts: Vec<usize>,
}

impl Coverage {
    pub fn new(width: u32, height: u32, grid: [usize; 2]) -> Coverage {
        let (cols, rows) = (grid[0].max(1), grid[1].max(1));
        Coverage {
            cols,
            rows,
            width,
            height,
            counts: vec![0; cols * rows],
        }
    }

    /// The cell of a pixel (centre convention: the frame spans `[-0.5, w - 0.5)`).
    pub fn cell(&self, uv: &Vector2<f64>) -> Option<usize> {
        let fx = (uv.x + 0.5) / f64::from(self.width);
        let fy = (uv.y + 0.5) / f64::from(self.height);
        if !(0.0..1.0).contains(&fx) || !(0.0..1.0).contains(&fy) {
            return None;
        }
        let c = ((fx * self.cols as f64) as usize).min(self.cols - 1);
        let r = ((fy * self.rows as f64) as usize).min(self.rows - 1);
        Some(r * self.cols + c)
    }

    pub fn add(&mut self, uv: &Vector2<f64>) {
        if let Some(i) = self.cell(uv) {
            self.counts[i] += 1;
        }
    }

    pub fn covered(&self) -> usize {
        self.counts.iter().filter(|&&n| n > 0).count()
    }

    pub fn total(&self) -> usize {
        self.counts.len()
    }

    pub fn fraction(&self) -> f64 {
        self.covered() as f64 / self.total() as f64
    }

    /// The image region of a pixel in words, on a 3×3 division: `top-left`, `top`, …, `centre`.
    pub fn region_of(&self, uv: &Vector2<f64>) -> &'static str {
        let third =
            |x: f64, n: u32| ((3.0 * (x + 0.5) / f64::from(n)).floor().clamp(0.0, 2.0)) as usize;
        const NAMES: [[&str; 3]; 3] = [
            ["top-left", "top", "top-right"],
            ["left", "centre", "right"],
            ["bottom-left", "bottom", "bottom-right"],
        ];
        NAMES[third(uv.y, self.height)][third(uv.x, self.width)]
    }

    /// How many cells now empty the points would cover.
    pub fn newly_covered<'a>(&self, points: impl IntoIterator<Item = &'a Vector2<f64>>) -> usize {
        let mut cells: Vec<usize> = points
            .into_iter()
            .filter_map(|p| self.cell(p))
            .filter(|&c| self.counts[c] == 0)
            .collect();
        cells.sort_unstable();
        cells.dedup();
        cells.len()
    }

    /// Which of the image's four corner regions (the outer cells) hold no corner, in words.
    pub fn empty_regions(&self) -> Vec<&'static str> {
        let at = |r: usize, c: usize| self.counts[r * self.cols + c] > 0;
        let (r1, c1) = (self.rows - 1, self.cols - 1);
        let mut out = Vec::new();
        for (name, r, c) in [
            ("top-left", 0, 0),
            ("top-right", 0, c1),
            ("bottom-left", r1, 0),
            ("bottom-right", r1, c1),
        ] {
            if !at(r, c) {
                out.push(name);
            }
        }
        if (0..self.cols).all(|c| !at(0, c)) {
            out.push("top edge");
        }
        if (0..self.cols).all(|c| !at(r1, c)) {
            out.push("bottom edge");
        }
        if (0..self.rows).all(|r| !at(r, 0)) {
            out.push("left edge");
        }
        if (0..self.rows).all(|r| !at(r, c1)) {
            out.push("right edge");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_cells_and_names_empty_corners() {
        let mut c = Coverage::new(800, 600, [4, 3]);
        c.add(&Vector2::new(0.0, 0.0));
        c.add(&Vector2::new(399.0, 299.0));
        c.add(&Vector2::new(-0.6, 0.0)); // outside
        c.add(&Vector2::new(799.4, 599.4));
        assert_eq!(c.covered(), 3);
        assert!((c.fraction() - 0.25).abs() < 1e-12);
        let empty = c.empty_regions();
        assert!(empty.contains(&"top-right") && empty.contains(&"bottom-left"));
        assert!(!empty.contains(&"top-left") && !empty.contains(&"bottom-right"));
    }
}
