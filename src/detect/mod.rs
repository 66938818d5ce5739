//! Corner detection: grayscale frame → X-corners → checkerboard grids → fitted, completed grids →
//! labelled rig correspondences with a per-corner σ.
//!
//! ## Front end (ours)
//! [`front`] finds X-corner candidates and their edge directions from the saddle response of the
//! Hessian at half resolution. The `chess-corners` crate was the first front end and is not used any
//! more: on stable Rust it alone took longer than the whole detection budget (reasons and figures in
//! [`front`]'s module doc).
//!
//! ## Grid assembly, fitting and completion (ours)
//! [`grid`] links corners into a lattice by growing from seeds along their local axes. [`complete`]
//! fits every lattice corner with the X-junction model of [`refine`] (window shaped by the lattice,
//! per-corner σ from the fit) and recovers the corners the front end missed where the lattice
//! predicts them. [`label`] decides which face each grid is, never guessing, in one order with each
//! rule in its own module: [`fold`] cuts lattices that bend from one plane to another, `extent` proves
//! where a grid ends, `identity` names the face by size, colours and the geometry of all grids of the
//! frame, and [`place`] places partial grids through the faces found; [`own_lattice`] fits the
//! corners of a face cut from a larger lattice (at a fold) again on the face's own lattice; [`score`] measures all of
//! this against the ground truth of synthetic renders. Once a calibration exists,
//! [`refine_with_camera`] ([`undistorted`]) fits the labelled corners again in undistorted
//! coordinates, where lens distortion no longer bends their edges.

use image::GrayImage;
use nalgebra::Vector2;

use crate::calib::rigrefine::{RigPoint, RigView};
use crate::rig::CornerId;

pub use front::CornerFinder;

pub mod charuco;
pub mod complete;
pub mod crlb;
mod dense;
mod extent;
pub mod face;
pub mod fold;
pub mod front;
pub mod grid;
mod identity;
pub mod label;
pub mod overlay;
pub mod own_lattice;
pub mod place;
pub mod refine;
pub mod score;
pub mod settle;
mod trim;
pub mod undistorted;

pub use undistorted::refine_with_camera;

/// Smallest frame side the detector accepts.
pub const MIN_SIDE: u32 = 32;

/// Errors from the detector.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DetectError {
    #[error("frame {width}×{height} is too small (minimum {MIN_SIDE}×{MIN_SIDE})")]
    TooSmall { width: u32, height: u32 },
    #[error("the camera is for {}×{} images, the frame is {}×{}", camera[0], camera[1], frame[0], frame[1])]
    CameraSize { camera: [u32; 2], frame: [u32; 2] },
}

impl DetectError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            DetectError::TooSmall { .. } | DetectError::CameraSize { .. } => crate::exit::BAD_INPUT,
        }
    }
}

/// An X-corner: sub-pixel position, the directions of its two edge lines (radians, modulo π), the
/// direction of the bisector of its two dark quadrants (radians, modulo π) and the front end's
/// response.
///
/// `dark` is the corner's polarity: the bisectors of the two pairs of opposite quadrants are always
/// 90° apart, and neighbours along a row or column of a checkerboard swap dark and bright quadrants,
/// so their `dark` directions are ~90° apart, while corners two steps apart or diagonal neighbours
/// have the same polarity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct XCorner {
    pub uv: Vector2<f64>,
    pub axes: [f64; 2],
    pub dark: f64,
    pub response: f64,
}

/// Everything found in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameDetection {
    pub width: u32,
    pub height: u32,
    pub faces: Vec<label::FaceDetection>,
    pub rejected: Vec<label::Rejection>,
}

impl FrameDetection {
    /// The labelled corners as one calibration view.
    pub fn to_view(&self, name: &str) -> crate::calib::View {
        crate::calib::View {
            name: name.to_string(),
            points: self
                .faces
                .iter()
                .flat_map(|f| f.corners.iter())
                .map(|c| crate::calib::Correspondence {
                    xyz: c.xyz,
                    uv: c.uv,
                    cov: c.covariance(),
                })
                .collect(),
        }
    }

    /// The labelled corners with their rig labels, for refining the rig itself
    /// ([`crate::calib::rigrefine`]). Faces labelled only up to a symmetry
    /// ([`label::FaceDetection::ambiguous_pose`]) are left out when the frame holds several: a
    /// symmetry of the nominal rig is not one of the real rig, whose geometry is what is refined (a
    /// lone face constrains no relative geometry and stays).
    pub fn to_rig_view(&self, name: &str) -> RigView {
        let several = self.faces.len() > 1;
        RigView {
            name: name.to_string(),
            points: self
                .faces
                .iter()
                .filter(|f| !(several && f.ambiguous_pose.is_some()))
                .flat_map(|f| {
                    f.corners.iter().map(move |c| RigPoint {
                        corner: CornerId {
                            face: f.face,
                            row: c.row,
                            col: c.col,
                        },
                        uv: c.uv,
                        sigma_px: c.sigma_px.is_finite().then_some(c.sigma_px),
                        cov: c.covariance(),
                    })
                })
                .collect(),
        }
    }
}

/// Corners → grids → labelled faces for one frame. A rig's ChArUco faces are found by their
/// markers ([`charuco`]), its checkerboard faces by their grids; in a mixed rig a checkerboard
/// labelling that falls on a decoded ChArUco face is dropped with a reason.
pub fn detect(
    finder: &mut CornerFinder,
    img: &GrayImage,
    rig: &crate::rig::Rig,
) -> Result<FrameDetection, DetectError> {
    let (width, height) = img.dimensions();
    if width < MIN_SIDE || height < MIN_SIDE {
        return Err(DetectError::TooSmall { width, height });
    }
    let n_charuco = rig.faces.iter().filter(|f| f.charuco.is_some()).count();
    if n_charuco == 0 {
        return detect_checkerboards(finder, img, rig);
    }
    let found = charuco::detect(img, rig);
    let mut faces = found.faces;
    let mut rejected = found.rejected;
    if found.markers.is_empty() {
        rejected.push(label::Rejection::frame(
            "no ArUco marker of the rig's ChArUco faces decoded".into(),
        ));
    }
    if n_charuco < rig.faces.len() {
        // The checkerboard faces alone, their indices mapped back to the rig's.
        let index: Vec<usize> = (0..rig.faces.len())
            .filter(|&k| rig.faces[k].charuco.is_none())
            .collect();
        let boards = crate::rig::Rig {
            faces: index.iter().map(|&k| rig.faces[k].clone()).collect(),
            ..rig.clone()
        };
        let checker = detect_checkerboards(finder, img, &boards)?;
        rejected.extend(checker.rejected);
        for mut f in checker.faces {
            f.face = index[f.face];
            let on_markers = f.corners.iter().any(|c| {
                found.markers.iter().any(|m| {
                    let centre = m.corners.iter().sum::<Vector2<f64>>() / 4.0;
                    let side = (m.corners[0] - m.corners[2]).norm();
                    (c.uv - centre).norm() < side
                })
            });
            if on_markers {
                rejected.push(label::Rejection {
                    reason: format!(
                        "grid labelled as checkerboard face '{}' lies on decoded ArUco markers",
                        rig.faces[f.face].name
                    ),
                    corners: f
                        .corners
                        .iter()
                        .map(|c| label::GridCorner {
                            row: c.row,
                            col: c.col,
                            uv: c.uv,
                        })
                        .collect(),
                });
            } else {
                faces.push(f);
            }
        }
    }
    faces.sort_by_key(|f| f.face);
    Ok(FrameDetection {
        width,
        height,
        faces,
        rejected,
    })
}

/// [`detect`] for a rig of checkerboard faces only.
fn detect_checkerboards(
    finder: &mut CornerFinder,
    img: &GrayImage,
    rig: &crate::rig::Rig,
) -> Result<FrameDetection, DetectError> {
    let (corners, grids) = grid::find_and_assemble(finder, img)?;
    let max_lines = rig
        .faces
        .iter()
        .map(|f| f.rows.max(f.cols))
        .max()
        .unwrap_or(0);
    let completed: Vec<complete::Completed> = grids
        .iter()
        .map(|g| complete::complete(img, &corners, g, max_lines))
        .collect();
    let (mut faces, mut rejected) = label::label(img, rig, &completed);
    own_lattice::refit_on_own_lattice(img, &completed, &mut faces);
    face::add_grazing_bias(&mut faces);
    if grids.is_empty() {
        let busy = finder.busy_fraction();
        rejected.push(label::Rejection::frame(if busy > front::MAX_BUSY_FRACTION {
            format!(
                "no checkerboard: the corner response is above its floor over {:.0} % of the frame (at most {:.0} % for a checkerboard's corners): noise or fine texture",
                100.0 * busy,
                100.0 * front::MAX_BUSY_FRACTION
            )
        } else {
            format!(
                "no checkerboard grid found ({} isolated corners)",
                corners.len()
            )
        }));
    }
    Ok(FrameDetection {
        width: img.width(),
        height: img.height(),
        faces,
        rejected,
    })
}
