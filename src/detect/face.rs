//! What labelling produces, shared by the decision ([`super::label`]) and its tests
//! (`extent`, `identity`, [`super::place`]): labelled faces and corners, rejections
//! with the grid they concern, and the colour contrast every orientation test holds squares to.

use nalgebra::{Matrix2, Vector2, Vector3};

use super::dense::Dense;

/// Mean white-minus-black square intensity (grey levels) needed for an orientation to count as decided.
pub const MIN_COLOUR_CONTRAST: f64 = 10.0;

/// One labelled corner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LabelledCorner {
    pub row: usize,
    pub col: usize,
    pub xyz: Vector3<f64>,
    pub uv: Vector2<f64>,
    /// Estimated standard deviation of each coordinate of `uv` (px), from the refinement fit:
    /// `√(trace/2)` of `cov`.
    pub sigma_px: f64,
    /// Covariance of `uv` (px²) from the refinement fit: the fit's own estimator covariance, scaled
    /// by the residual noise of its window ([`super::refine::Refined::cov`]).
    pub cov: Matrix2<f64>,
}

impl LabelledCorner {
    /// `cov` when it is usable as the corner's weight (finite, positive definite): what
    /// [`crate::calib::Correspondence::cov`] takes.
    pub fn covariance(&self) -> Option<Matrix2<f64>> {
        crate::calib::valid_covariance(&self.cov).then_some(self.cov)
    }
}

/// A face found in the frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceDetection {
    pub face: usize,
    pub corners: Vec<LabelledCorner>,
    /// White-minus-black mean intensity that decided the orientation (grey levels).
    pub colour_contrast: f64,
    /// Set, with the reason, when the face's labels are certain only up to a motion that changes
    /// this view's pose and never the intrinsics: on a rig of one face, a grid of exactly the face's
    /// size whose only missing proof of extent is the frame border (were it part of a bigger board,
    /// its labels would be shifted within the plane); on any rig, labellings one similarity apart
    /// that nothing in the frame tells apart (a lone 180°-symmetric board, a lone grid of a shape
    /// several faces share, a rig with a symmetry of its own; see `identity`). A planar view
    /// constrains the camera through its homography up to a similarity of the plane, and a
    /// similarity of the whole rig is taken up by the pose; so the pose is flagged, not trusted.
    pub ambiguous_pose: Option<String>,
    /// How the face's identity was decided when its size and colours left a choice (the rig
    /// geometry's margin over the closest alternative, or the symmetry that leaves it open).
    pub identity: Option<String>,
}

/// Why a grid (or the frame) was not used.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    pub reason: String,
    /// The rejected grid's corners in its own row/column indices (empty for a rejection of the whole
    /// frame, such as "no checkerboard grid found").
    pub corners: Vec<GridCorner>,
}

/// A corner of a rejected grid: its index in the grid (not a face's) and its image position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridCorner {
    pub row: usize,
    pub col: usize,
    pub uv: Vector2<f64>,
}

impl Rejection {
    /// A rejection of the frame as a whole (no grid to show).
    pub fn frame(reason: String) -> Rejection {
        Rejection {
            reason,
            corners: Vec::new(),
        }
    }
}

impl Dense {
    /// The grid's corners for a rejection.
    pub(super) fn grid_corners(&self) -> Vec<GridCorner> {
        (0..self.rows)
            .flat_map(|r| (0..self.cols).map(move |c| (r, c)))
            .map(|(row, col)| GridCorner {
                row,
                col,
                uv: self.at(row, col),
            })
            .collect()
    }
}

/// Noise-free corner error (px RMS) the detector leaves on a face foreshortened to `c` = cos of its
/// angle from frontal (the ratio of the image's shorter to longer scale of the face plane): measured
/// on noise-free renders at 16×16 sub-samples (`NOISE=0 SS=16 detect_eval realistic 12`: 0.0014 px
/// at 45–60°, 0.0033 px at 60–75°, 0.0083 px at 75–80°, 0.020 px beyond) and modelled as
/// [`GRAZING_BIAS_PX`] · (cos 75° / c)², which gives 0.0011 / 0.0021 / 0.008 / 0.018 px at the
/// middle of those buckets.
pub fn grazing_bias_px(c: f64) -> f64 {
    let c = c.clamp(0.02, 1.0);
    GRAZING_BIAS_PX * (GRAZING_FROM_DEG.to_radians().cos() / c).powi(2)
}

/// [`grazing_bias_px`] at [`GRAZING_FROM_DEG`] (px).
pub const GRAZING_BIAS_PX: f64 = 0.008;
/// Faces seen further from frontal than this (degrees) carry a bias term in their corners'
/// covariance ([`add_grazing_bias`]); below it the noise-free error (≤ 0.003 px) is under the corner
/// noise of any real camera and does not grow with it.
pub const GRAZING_FROM_DEG: f64 = 75.0;

/// Where each (row, col) of a face is in its corner list: a dense table over the face's extent.
struct CornerIndex {
    cols: usize,
    slot: Vec<Option<usize>>,
}

impl CornerIndex {
    fn of(face: &FaceDetection) -> CornerIndex {
        let rows = face.corners.iter().map(|c| c.row + 1).max().unwrap_or(0);
        let cols = face.corners.iter().map(|c| c.col + 1).max().unwrap_or(0);
        let mut slot = vec![None; rows * cols];
        for (k, c) in face.corners.iter().enumerate() {
            slot[c.row * cols + c.col] = Some(k);
        }
        CornerIndex { cols, slot }
    }

    fn get(&self, row: usize, col: usize) -> Option<usize> {
        if col >= self.cols {
            return None;
        }
        self.slot.get(row * self.cols + col).copied().flatten()
    }
}

/// The foreshortening of `face` at its corner `k`: cos of the angle from frontal, the ratio of the
/// singular values of the local map from the face plane (mm) to the image (px), from the corner's
/// labelled neighbours along its row and column (central differences where both sides are there).
fn foreshortening(face: &FaceDetection, at: &CornerIndex, k: usize) -> Option<f64> {
    let c = &face.corners[k];
    let step = |dr: isize, dc: isize| -> Option<(Vector2<f64>, f64)> {
        let get = |s: isize| {
            let r = c.row.checked_add_signed(s * dr)?;
            let col = c.col.checked_add_signed(s * dc)?;
            at.get(r, col).map(|i| &face.corners[i])
        };
        let (p, m) = (get(1), get(-1));
        let (a, b, n) = match (p, m) {
            (Some(p), Some(m)) => (p, m, 2.0),
            (Some(p), None) => (p, c, 1.0),
            (None, Some(m)) => (c, m, 1.0),
            (None, None) => return None,
        };
        let mm = (a.xyz - b.xyz).norm() / n;
        (mm > 0.0).then(|| ((a.uv - b.uv) / n / mm, mm))
    };
    let (u, _) = step(0, 1)?;
    let (v, _) = step(1, 0)?;
    // The singular values of the 2×2 map [u v] in closed form: q ± r.
    let (e, f) = ((u.x + v.y) / 2.0, (u.x - v.y) / 2.0);
    let (g, h) = ((u.y + v.x) / 2.0, (u.y - v.x) / 2.0);
    let (q, r) = (e.hypot(h), f.hypot(g));
    let (hi, lo) = (q + r, (q - r).abs());
    (hi > 0.0 && lo.is_finite()).then(|| lo / hi)
}

/// Each corner of a face seen beyond [`GRAZING_FROM_DEG`] gets its noise-free bias in its covariance
/// and σ: the variance `N · (b(c)² − b(cos 75°)²)` added isotropically, with `b` =
/// [`grazing_bias_px`] at the corner's own foreshortening `c` and `N` the face's number of corners.
///
/// Why `N ·`: the bias of a grazing face is coherent (an offset of the whole face, growing towards
/// its most foreshortened column), so it does not average out over the face's corners as noise does;
/// a correlated error of variance b² shared by N corners weighs on the solve like independent errors
/// of variance N·b² on each (the face's mean then has variance b², as it should). Why the excess over
/// b(cos 75°): the term starts at 0 at 75° (no jump between a face at 74.9° and one at 75.1°), and
/// below 75° the bias is small against the noise. So a biased grazing face enters the solve with the
/// weight its bias allows and cannot move the principal point (issue 29, acceptance line 4;
/// `examples/second_look_eval.rs`).
pub fn add_grazing_bias(faces: &mut [FaceDetection]) {
    let b0 = grazing_bias_px(GRAZING_FROM_DEG.to_radians().cos());
    for face in faces {
        let at = CornerIndex::of(face);
        let n = face.corners.len() as f64;
        let extra: Vec<f64> = (0..face.corners.len())
            .map(|k| {
                foreshortening(face, &at, k)
                    .map_or(0.0, |c| n * (grazing_bias_px(c).powi(2) - b0 * b0).max(0.0))
            })
            .collect();
        for (c, v) in face.corners.iter_mut().zip(extra) {
            if v > 0.0 {
                c.cov += Matrix2::from_diagonal_element(v);
                c.sigma_px = (c.cov.trace() / 2.0).sqrt();
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A 9×8 face of 20 mm squares imaged at 1 px/mm along its columns and `c` px/mm along its rows.
    fn face(c: f64) -> FaceDetection {
        let cov: Matrix2<f64> = Matrix2::new(4e-4, 1e-5, 1e-5, 9e-4);
        FaceDetection {
            face: 0,
            corners: (0..8)
                .flat_map(|row| (0..9).map(move |col| (row, col)))
                .map(|(row, col)| LabelledCorner {
                    row,
                    col,
                    xyz: Vector3::new(20.0 * col as f64, 20.0 * row as f64, 0.0),
                    uv: Vector2::new(100.0 + 20.0 * col as f64, 50.0 + 20.0 * c * row as f64),
                    sigma_px: (cov.trace() / 2.0).sqrt(),
                    cov,
                })
                .collect(),
            colour_contrast: 50.0,
            ambiguous_pose: None,
            identity: None,
        }
    }

    /// A face at 80° from frontal: every corner's covariance grows by N·(b(c)² − b(cos 75°)²) =
    /// 72·(0.01778² − 0.008²) = 0.01815 px² (σ 0.135 px); at 75° and frontal nothing changes.
    #[test]
    fn a_grazing_face_carries_its_bias_and_a_frontal_one_does_not() {
        assert!((grazing_bias_px(75f64.to_radians().cos()) - 0.008).abs() < 1e-12);
        assert!((grazing_bias_px(80f64.to_radians().cos()) - 0.017_778).abs() < 1e-5);
        let mut faces = vec![face(1.0), face(74.9f64.to_radians().cos())];
        let before = faces.clone();
        add_grazing_bias(&mut faces);
        assert_eq!(faces, before);
        let mut faces = vec![face(80f64.to_radians().cos())];
        let cov = faces[0].corners[0].cov;
        add_grazing_bias(&mut faces);
        for c in &faces[0].corners {
            let added = c.cov - cov;
            assert!((added[(0, 0)] - 0.018_15).abs() < 2e-4, "{added}");
            assert!((added[(1, 1)] - added[(0, 0)]).abs() < 1e-12 && added[(0, 1)] == 0.0);
            assert!((c.sigma_px - (c.cov.trace() / 2.0).sqrt()).abs() < 1e-15);
        }
    }
}
