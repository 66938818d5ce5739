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
    /// The detection fit's edge width `s` (px, [`super::refine::Refined::edge_width`]): the blur
    /// the grazing bias grows with ([`grazing_bias_px`]); 0 where no fit gave one.
    pub edge_px: f64,
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

/// Noise-free corner error (px RMS per coordinate) the detector leaves where a face is so
/// foreshortened that its blurred edges crowd each other: `x` is the corner's edge width over the
/// face's shorter image step there (both px: [`LabelledCorner::edge_px`], and the smaller singular
/// value of the image steps of one square along the row and the column). A window then sees its
/// neighbouring lines' blur, on the short side of the step more than on the long one.
///
/// Measured on noise-free renders at 16×16 sub-samples, corners refitted through the true lens,
/// 12 views of each set at blur σ 1.0 and 1.5 px (`NOISE=0 BLUR=σ cargo run --release --example
/// receding_bias -- SET 12`): by `x` = 0.09 / 0.11 / 0.14 / 0.175 / 0.225 / 0.275 / 0.325 the
/// error is 2.0–6.2 / 2.6–7.1 / 5.1–8.3 / 5.1–10.8 / 12.5–18 / 13–46 / 74–84 mpx (the lower figures
/// the realistic set's, the upper the hard set's, k1 −0.3 and low contrast), modelled as
/// [`GRAZING_LINEAR_PX`]·x + [`GRAZING_STEEP_PX`]·exp((x − 0.3)/[`GRAZING_STEEP_WIDTH`]): 5.0 / 6.8 /
/// 9.7 / 17 / 32 / 67 mpx from 0.11 on, between the two sets up to 0.2 and near the hard set's
/// beyond. The face's angle alone (the model before) put the realistic set's corners at 75–80° at
/// 11.5 mpx (measured 5) and the hard set's beyond 80° at 27 (measured 40–80): blur decides as much
/// as the angle. (With the hard set's upper envelope, 0.045·x, the realistic set's σ came out 12 %
/// above its scatter and a lean camera's planned run no longer reached its σ targets.)
pub fn grazing_bias_px(x: f64) -> f64 {
    // Beyond 0.6 the edges have merged (no corner fit holds there); the bound keeps the term finite.
    let x = x.clamp(0.0, 0.6);
    GRAZING_LINEAR_PX * x + GRAZING_STEEP_PX * ((x - 0.3) / GRAZING_STEEP_WIDTH).exp()
}

/// See [`grazing_bias_px`] (px per unit of edge width over step).
pub const GRAZING_LINEAR_PX: f64 = 0.035;
/// See [`grazing_bias_px`] (px).
pub const GRAZING_STEEP_PX: f64 = 0.035;
/// See [`grazing_bias_px`].
pub const GRAZING_STEEP_WIDTH: f64 = 0.055;
/// Corners whose edge width over short step exceeds this carry a bias term in their covariance
/// ([`add_grazing_bias`]): where [`grazing_bias_px`] reaches 0.008 px, the level the model by angle
/// started at (75°, on the realistic set). Below it the noise-free error is under the corner noise
/// of any real camera and does not grow with it.
pub const GRAZING_FROM: f64 = 0.155;
/// The edge width assumed for a face none of whose corners carries one (px): a sharp camera's,
/// blur σ 1 px (the fits measure 1.25–1.35 px there).
pub const DEFAULT_EDGE_PX: f64 = 1.3;

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

/// The shorter image step of one square of `face` at its corner `k` (px): the smaller singular
/// value of the steps to its labelled neighbours along its row and its column (central differences
/// where both sides are there).
fn short_step(face: &FaceDetection, at: &CornerIndex, k: usize) -> Option<f64> {
    let c = &face.corners[k];
    let step = |dr: isize, dc: isize| -> Option<Vector2<f64>> {
        let get = |s: isize| {
            let r = c.row.checked_add_signed(s * dr)?;
            let col = c.col.checked_add_signed(s * dc)?;
            at.get(r, col).map(|i| &face.corners[i])
        };
        let (a, b, n) = match (get(1), get(-1)) {
            (Some(p), Some(m)) => (p, m, 2.0),
            (Some(p), None) => (p, c, 1.0),
            (None, Some(m)) => (c, m, 1.0),
            (None, None) => return None,
        };
        Some((a.uv - b.uv) / n)
    };
    let (u, v) = (step(0, 1)?, step(1, 0)?);
    // The singular values of the 2×2 map [u v] in closed form: q ± r.
    let (e, f) = ((u.x + v.y) / 2.0, (u.x - v.y) / 2.0);
    let (g, h) = ((u.y + v.x) / 2.0, (u.y - v.x) / 2.0);
    let (q, r) = (e.hypot(h), f.hypot(g));
    let lo = (q - r).abs();
    lo.is_finite().then_some(lo)
}

/// Each corner of a face whose edges crowd each other carries its noise-free bias in its
/// covariance and σ: the variance `N · (b(x)² − b(x₀)²)` added isotropically, with `b` =
/// [`grazing_bias_px`] at the corner's own edge width over short step `x` (its edge width, else the
/// face's median, else [`DEFAULT_EDGE_PX`]), `x₀` = [`GRAZING_FROM`] and `N` the face's number of
/// corners.
///
/// Why `N ·`: the bias of a grazing face is coherent (an offset of the whole face, growing towards
/// its most foreshortened column), so it does not average out over the face's corners as noise does;
/// a correlated error of variance b² shared by N corners weighs on the solve like independent errors
/// of variance N·b² on each (the face's mean then has variance b², as it should). Why the excess over
/// b(x₀): the term starts at 0 (no jump between a face just below and one just above), and below it
/// the bias is small against the noise. So a biased grazing face enters the solve with the weight
/// its bias allows and cannot move the principal point (issue 29, acceptance line 4;
/// `examples/second_look_eval.rs`).
pub fn add_grazing_bias(faces: &mut [FaceDetection]) {
    for face in faces {
        add_grazing_bias_where(face, |_| true);
    }
}

/// [`add_grazing_bias`] to the corners of `face` that `to` holds for (by index): the lens refit
/// ([`super::refine_with_camera`]) gives the corners it fits again their new fit's covariance, and
/// the face's bias is added to that, not to the corners it kept.
pub(super) fn add_grazing_bias_where(face: &mut FaceDetection, to: impl Fn(usize) -> bool) {
    let b0 = grazing_bias_px(GRAZING_FROM);
    let at = CornerIndex::of(face);
    let n = face.corners.len() as f64;
    let mut edges: Vec<f64> = (face.corners.iter())
        .map(|c| c.edge_px)
        .filter(|e| e.is_finite() && *e > 0.0)
        .collect();
    edges.sort_by(f64::total_cmp);
    let typical = edges
        .get(edges.len() / 2)
        .copied()
        .unwrap_or(DEFAULT_EDGE_PX);
    let extra: Vec<f64> = (0..face.corners.len())
        .map(|k| {
            if !to(k) {
                return 0.0;
            }
            let edge = Some(face.corners[k].edge_px)
                .filter(|e| e.is_finite() && *e > 0.0)
                .unwrap_or(typical);
            short_step(face, &at, k)
                .filter(|s| *s > 0.0)
                .map_or(0.0, |s| {
                    n * (grazing_bias_px(edge / s).powi(2) - b0 * b0).max(0.0)
                })
        })
        .collect();
    for (c, v) in face.corners.iter_mut().zip(extra) {
        if v > 0.0 {
            c.cov += Matrix2::from_diagonal_element(v);
            c.sigma_px = (c.cov.trace() / 2.0).sqrt();
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
                    edge_px: 1.3,
                })
                .collect(),
            colour_contrast: 50.0,
            ambiguous_pose: None,
            identity: None,
        }
    }

    /// A face whose short step is 5.2 px with 1.3 px edges (x = 0.25): every corner's covariance
    /// grows by N·(b(0.25)² − b(0.155)²) = 72·(0.022851² − 0.007932²) = 0.03307 px² (σ 0.18 px);
    /// at x = 0.1 and on a frontal face nothing changes; with 0.85 px edges (x = 0.163) a little;
    /// without edge widths the default's.
    #[test]
    fn a_grazing_face_carries_its_bias_and_a_frontal_one_does_not() {
        assert!((grazing_bias_px(0.25) - 0.022_851).abs() < 1e-6);
        assert!((grazing_bias_px(GRAZING_FROM) - 0.007_932).abs() < 1e-6);
        let mut faces = vec![face(1.0), face(0.65)];
        let before = faces.clone();
        add_grazing_bias(&mut faces);
        assert_eq!(faces, before);
        let added = |mut face: FaceDetection| {
            let cov = face.corners[0].cov;
            add_grazing_bias(std::slice::from_mut(&mut face));
            for c in &face.corners {
                let d = c.cov - cov;
                assert!((d[(1, 1)] - d[(0, 0)]).abs() < 1e-12 && d[(0, 1)] == 0.0);
                assert!((c.sigma_px - (c.cov.trace() / 2.0).sqrt()).abs() < 1e-15);
            }
            face.corners
                .iter()
                .map(|c| c.cov[(0, 0)] - cov[(0, 0)])
                .collect::<Vec<_>>()
        };
        for d in added(face(0.26)) {
            assert!((d - 0.033_07).abs() < 1e-4, "{d}");
        }
        let mut sharp = face(0.26);
        sharp.corners.iter_mut().for_each(|c| c.edge_px = 0.85);
        for d in added(sharp) {
            assert!((d - 0.000_851).abs() < 1e-5, "{d}");
        }
        let mut unknown = face(0.26);
        unknown.corners.iter_mut().for_each(|c| c.edge_px = 0.0);
        for d in added(unknown) {
            assert!((d - 0.033_07).abs() < 1e-4, "{d}");
        }
    }
}
