//! Labelled faces cut from a larger lattice are fitted again on their own lattice.
//!
//! [`super::complete`] fits every corner of an assembled lattice and then corrects it for the
//! curvature of its two lattice lines, measured by a parabola through up to three fitted corners on
//! each side. That rests on the lattice being one plane seen through a lens: perspective keeps its
//! lines straight and only distortion bends them, slowly. A lattice that runs over a fold (one sheet
//! wrapped around a cube's edge, boards meeting at a seam) or past the end of a face (the black
//! squares of a board without margin against a dark background) is not: at the fold its lines kink,
//! and the parabola through the kink reads as a strong curvature that the correction then applies to
//! the corners next to it. [`super::label`] cuts such a lattice into its faces afterwards, but the
//! corners keep the correction computed across the cut.
//!
//! Measured on the wrapped-cube renders of issue 19 (`tests/cases`, k1 −0.3, two 6×10 faces of one
//! sheet; `cargo run --release --example detect_accuracy`, `CASE=wrapped-cube`): the corners on the
//! column next to the fold had an RMS error of 0.160 px (max 0.43 px, along the fold: the kinked rows
//! bend the corner normal to them), the next column 0.095 px, the columns three or more steps away
//! 0.010 px, the same with noise-free renders, so a model error, not noise. Fitted again in
//! undistorted coordinates with the true camera (no curvature correction at all) every column was at
//! 0.009 px: the windows themselves stay on their face (they reach 0.65 of the way to the next
//! corner, and the fold is a whole square away from the last corner of a face), only the correction
//! reached across.
//!
//! So, once a face is labelled, the rig has said where its pattern ends: when the face's corners are
//! a strict part of the lattice they were fitted in, every corner of the face is fitted again with
//! steps taken from the face's own corners, and the curvature of each of its lines is measured on the
//! face's own corners only (the same estimate and first-order correction as completion). A face whose
//! lattice was the face (the common case: a board with margins, a cube face) is left as it is, at no
//! cost. A corner whose fit fails keeps its position and σ.

use std::collections::{BTreeMap, HashMap, HashSet};

use image::GrayImage;
use nalgebra::{Matrix2, Vector2};

use super::complete::{Completed, Fitted, Shade, lattice_curvature, shading_correction};
use super::label::FaceDetection;
use super::refine;

/// What [`refit_on_own_lattice`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OwnLattice {
    /// Faces whose corners were part of a larger lattice.
    pub faces: usize,
    /// Corners fitted again (the others of those faces kept their position).
    pub refitted: usize,
}

/// The key of an image position, exact: labelling copies the completed corners' positions.
fn key(uv: &Vector2<f64>) -> [u64; 2] {
    [uv.x.to_bits(), uv.y.to_bits()]
}

/// Whether `face`'s corners are a strict part of one of the `grids` they were labelled from: all of
/// them are corners of that grid, and the grid has fitted corners that are not the face's.
fn cut_from_larger(face: &FaceDetection, grids: &[Completed]) -> bool {
    !face.corners.is_empty()
        && grids.iter().any(|g| {
            let own: HashSet<[u64; 2]> = g.cells.iter().flatten().map(|f| key(&f.uv)).collect();
            own.len() > face.corners.len() && face.corners.iter().all(|c| own.contains(&key(&c.uv)))
        })
}

/// Fit every corner of the faces in `faces` that were cut from a larger lattice of `grids` again on
/// the face's own lattice (see the module doc); `img` is the frame they were detected in.
pub fn refit_on_own_lattice(
    img: &GrayImage,
    grids: &[Completed],
    faces: &mut [FaceDetection],
) -> OwnLattice {
    let mut out = OwnLattice::default();
    for face in faces.iter_mut() {
        if !cut_from_larger(face, grids) {
            continue;
        }
        out.faces += 1;
        let at: HashMap<(i32, i32), Vector2<f64>> = face
            .corners
            .iter()
            .map(|c| ((c.row as i32, c.col as i32), c.uv))
            .collect();
        // The image step from (r, c) to the next corner along (dr, dc), on the face: the central
        // difference where both neighbours are the face's, else the one-sided step.
        let step = |r: i32, c: i32, dr: i32, dc: i32| -> Option<Vector2<f64>> {
            let next = at.get(&(r + dr, c + dc));
            let prev = at.get(&(r - dr, c - dc));
            match (prev, next) {
                (Some(p), Some(n)) => Some((n - p) / 2.0),
                (None, Some(n)) => Some(n - at.get(&(r, c))?),
                (Some(p), None) => Some(at.get(&(r, c))? - p),
                (None, None) => None,
            }
        };
        // Straight-edge fits and their sensitivity to the lines' curvature.
        let mut fits: BTreeMap<(i32, i32), Fitted> = BTreeMap::new();
        let mut shifts: HashMap<(i32, i32), Matrix2<f64>> = HashMap::new();
        let mut shades: BTreeMap<(i32, i32), Shade> = BTreeMap::new();
        for c in &face.corners {
            let (r, cc) = (c.row as i32, c.col as i32);
            let (Some(a), Some(b)) = (step(r, cc, 0, 1), step(r, cc, 1, 0)) else {
                continue;
            };
            match refine::refine_near_border(img, c.uv, a, b) {
                Ok(f) => {
                    fits.insert((r, cc), Fitted::from_refined(&f));
                    shifts.insert((r, cc), f.curvature_shift);
                    shades.insert((r, cc), Shade::of(&f));
                }
                Err(why) => {
                    tracing::debug!(
                        row = c.row,
                        col = c.col,
                        ?why,
                        "own-lattice refit failed; corner kept"
                    );
                }
            }
        }
        for c in &mut face.corners {
            let k = (c.row as i32, c.col as i32);
            let (Some(f), Some(shift)) = (fits.get(&k), shifts.get(&k)) else {
                continue;
            };
            let kappa = Vector2::new(
                lattice_curvature(&fits, k.0, k.1, 0, 1).unwrap_or(0.0),
                lattice_curvature(&fits, k.0, k.1, 1, 0).unwrap_or(0.0),
            );
            c.uv = f.uv + shift * kappa + shading_correction(&shades, k.0, k.1);
            c.sigma_px = f.sigma_px;
            c.cov = f.cov;
            out.refitted += 1;
        }
    }
    if out.faces > 0 {
        tracing::debug!(
            faces = out.faces,
            refitted = out.refitted,
            "faces cut from a larger lattice fitted again on their own"
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::label::LabelledCorner;
    use nalgebra::Vector3;

    /// A `rows × cols` lattice of 10 px steps.
    fn lattice(rows: usize, cols: usize) -> Completed {
        Completed {
            rows,
            cols,
            cells: (0..rows * cols)
                .map(|i| {
                    Some(Fitted::isotropic(
                        Vector2::new(10.0 * (i % cols) as f64, 10.0 * (i / cols) as f64),
                        0.01,
                    ))
                })
                .collect(),
            dropped: 0,
            recovered: 0,
        }
    }

    /// The face made of the lattice's first `cols` columns.
    fn face(grid: &Completed, cols: usize) -> FaceDetection {
        FaceDetection {
            face: 0,
            corners: (0..grid.rows)
                .flat_map(|r| (0..cols).map(move |c| (r, c)))
                .map(|(row, col)| LabelledCorner {
                    row,
                    col,
                    xyz: Vector3::zeros(),
                    uv: grid.get(row, col).map(|f| f.uv).unwrap_or_default(),
                    sigma_px: 0.01,
                    cov: nalgebra::Matrix2::from_diagonal_element(1e-4),
                    edge_px: 1.0,
                })
                .collect(),
            colour_contrast: 100.0,
            ambiguous_pose: None,
            identity: None,
        }
    }

    #[test]
    fn only_a_face_that_is_a_strict_part_of_its_lattice_is_fitted_again() {
        let whole = lattice(4, 5);
        assert!(!cut_from_larger(
            &face(&whole, 5),
            std::slice::from_ref(&whole)
        ));
        assert!(cut_from_larger(
            &face(&whole, 3),
            std::slice::from_ref(&whole)
        ));
        // Corners of no lattice (or of two) are left alone.
        let mut moved = face(&whole, 3);
        moved.corners[4].uv.x += 0.5;
        assert!(!cut_from_larger(&moved, std::slice::from_ref(&whole)));
        assert!(!cut_from_larger(&face(&whole, 3), &[]));
        // With nothing to fit in a blank frame, no corner moves.
        let img = GrayImage::new(64, 64);
        let mut faces = vec![face(&whole, 3)];
        let before = faces.clone();
        let done = refit_on_own_lattice(&img, std::slice::from_ref(&whole), &mut faces);
        assert_eq!(
            done,
            OwnLattice {
                faces: 1,
                refitted: 0
            }
        );
        assert_eq!(faces, before);
    }
}
