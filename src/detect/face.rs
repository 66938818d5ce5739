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
