//! Corner refinement with a lens estimate: the X-junction model fitted in undistorted coordinates.
//!
//! The fit of [`super::refine`] takes the two edge lines through a corner as straight. Lens
//! distortion bends them, and near the border of a strongly distorted image (k1 −0.3 … −0.4, where
//! the radial magnification falls to 0.4) the bend is not the gentle parabola that
//! [`super::complete`]'s curvature correction assumes: the corners there carried a bias of up to a
//! pixel, radial, the same in every view, which the calibration then absorbs into its distortion and
//! principal point. Once a calibration exists, the bend is known: each pixel of the window is moved
//! to its undistorted position (`K·undistort(K⁻¹·uv)`, the pinhole image of the same camera), where
//! the board's edges are straight lines again, the model is fitted there, and the corner is mapped
//! back through the distortion with its covariance. The window itself is chosen in the image, as
//! before (the blur and the pixel grid are the image's).
//!
//! The caller iterates: detect → solve → [`refine_with_camera`] with the solved camera → solve
//! again. The lens estimate need not be exact: what matters is the bend of a line across one window,
//! and an error of a few percent in k1 leaves a few percent of the bias.

use image::GrayImage;
use nalgebra::{Matrix2, Vector2};

use super::refine::{PlaneMap, refine_mapped};
use super::{DetectError, FrameDetection};
use crate::camera::Camera;

/// The undistorted pinhole image of `camera`: the same intrinsics, no distortion.
///
/// The fit maps every pixel of a window in turn, each a pixel or so from the one before: each is
/// undistorted by one Newton step from the previous solution moved by the inverse Jacobian there,
/// where [`Camera::undistort`] from the distorted point takes four to eight to its 1e-14 tolerance
/// (this map was half of a photo run's time); the first pixel, and any whose warm start is not close
/// enough, are undistorted in full.
struct Undistorted<'a> {
    camera: &'a Camera,
    /// The last point undistorted: distorted and undistorted normalised position, and the
    /// inverse of the distortion's Jacobian there.
    last: std::cell::Cell<Option<Solved>>,
}

/// Largest residual (normalised coordinates) from which [`Undistorted`] takes one Newton step as
/// the solution.
const WARM_RESIDUAL: f64 = 1e-5;

/// A distorted point, its undistorted position and the inverse distortion Jacobian there.
type Solved = (Vector2<f64>, Vector2<f64>, Matrix2<f64>);

impl Undistorted<'_> {
    /// `∂pixel/∂(normalised)` of the intrinsics (focal lengths and skew).
    fn scale(&self) -> Matrix2<f64> {
        let c = self.camera;
        Matrix2::new(c.fx(), c.skew(), 0.0, c.fy())
    }

    fn normalised(&self, q: Vector2<f64>) -> Vector2<f64> {
        let c = self.camera;
        let y = (q.y - c.cy()) / c.fy();
        Vector2::new((q.x - c.cx() - c.skew() * y) / c.fx(), y)
    }
}

impl PlaneMap for Undistorted<'_> {
    fn to_plane(&self, uv: Vector2<f64>) -> Option<Vector2<f64>> {
        let d = self.normalised(uv);
        // Warm: one Newton step from the neighbour's solution moved by its inverse Jacobian. From
        // a residual below WARM_RESIDUAL its error is of the order of the residual squared (1e-10,
        // 1e-7 px), and the Jacobian's sign there says the point is on the physical side of a fold.
        if let Some((d0, p0, inv0)) = self.last.get() {
            let start = p0 + inv0 * (d - d0);
            let (at, j) = self.camera.distort_with_point_jacobian(start.x, start.y);
            let r = at - d;
            if r.norm() <= WARM_RESIDUAL
                && j.determinant() > 0.0
                && let Some(inv) = j.try_inverse()
            {
                let p = start - inv * r;
                self.last.set(Some((d, p, inv)));
                return Some(self.camera.to_pixel(&p));
            }
        }
        let (p, j) = self.camera.undistort_from(d.x, d.y, d).ok()?;
        self.last.set(j.try_inverse().map(|inv| (d, p, inv)));
        Some(self.camera.to_pixel(&p))
    }

    fn to_image(&self, q: Vector2<f64>) -> Option<(Vector2<f64>, Matrix2<f64>)> {
        let p = self.normalised(q);
        let (d, j_xy) = self.camera.distort_with_point_jacobian(p.x, p.y);
        let k = self.scale();
        let jac = k * j_xy * k.try_inverse()?;
        let uv = self.camera.to_pixel(&d);
        (uv.iter().chain(jac.iter()).all(|v| v.is_finite())).then_some((uv, jac))
    }
}

/// What [`refine_with_camera`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rerefined {
    /// Labelled corners in the frame.
    pub corners: usize,
    /// Corners fitted again in undistorted coordinates (the others keep their image fit: no
    /// neighbour along a row or column to shape the window, or the fit failed).
    pub refitted: usize,
}

/// Fit every labelled corner of `det` again in the undistorted coordinates of `camera` (see the
/// module doc); `img` is the frame `det` was detected in. Corners that cannot be fitted again keep
/// their position. `camera` must be of the frame's size.
pub fn refine_with_camera(
    img: &GrayImage,
    det: &mut FrameDetection,
    camera: &Camera,
) -> Result<Rerefined, DetectError> {
    let size = [img.width(), img.height()];
    if camera.image_size != size || [det.width, det.height] != size {
        return Err(DetectError::CameraSize {
            camera: camera.image_size,
            frame: size,
        });
    }
    let map = Undistorted {
        camera,
        last: std::cell::Cell::new(None),
    };
    let mut out = Rerefined::default();
    for face in &mut det.faces {
        let at: std::collections::HashMap<(usize, usize), Vector2<f64>> = face
            .corners
            .iter()
            .map(|c| ((c.row, c.col), c.uv))
            .collect();
        // The image step to the next corner along (dr, dc), from whichever neighbour exists.
        let step = |r: usize, c: usize, dr: usize, dc: usize| -> Option<Vector2<f64>> {
            let here = at.get(&(r, c))?;
            if let Some(next) = at.get(&(r + dr, c + dc)) {
                return Some(next - here);
            }
            let prev = at.get(&(r.checked_sub(dr)?, c.checked_sub(dc)?))?;
            Some(here - prev)
        };
        for corner in &mut face.corners {
            out.corners += 1;
            let (Some(a), Some(b)) = (
                step(corner.row, corner.col, 0, 1),
                step(corner.row, corner.col, 1, 0),
            ) else {
                continue;
            };
            match refine_mapped(img, corner.uv, a, b, &map) {
                Ok(f) => {
                    corner.uv = f.uv;
                    corner.sigma_px = f.sigma_px;
                    corner.cov = f.cov;
                    out.refitted += 1;
                }
                Err(why) => {
                    tracing::debug!(
                        row = corner.row,
                        col = corner.col,
                        ?why,
                        "undistorted refit failed; corner kept"
                    );
                }
            }
        }
    }
    Ok(out)
}

/// One recorded view for [`refit_recorded`]: the frame it was detected in and the detection.
#[derive(Debug, Clone)]
pub struct Recorded<'a> {
    pub name: &'a str,
    pub frame: &'a GrayImage,
    pub detection: &'a FrameDetection,
}

/// The calibration views of `recorded` with every corner fitted again in the undistorted coordinates
/// of `camera` ([`refine_with_camera`]), in the same order, each view's points in the order of
/// [`FrameDetection::to_view`]; the views are shared among up to four threads. `None` (with a warning
/// logged) when a frame is not the size of the camera: the caller keeps the corners it has.
pub fn refit_recorded(
    recorded: &[Recorded<'_>],
    camera: &Camera,
) -> Option<Vec<crate::calib::View>> {
    let one = |r: &Recorded<'_>| {
        let mut det = r.detection.clone();
        if let Err(e) = refine_with_camera(r.frame, &mut det, camera) {
            tracing::warn!(view = r.name, error = %e, "cannot refit the frame's corners");
            return None;
        }
        Some(det.to_view(r.name))
    };
    crate::render::parallel_map(recorded.len(), |i| one(&recorded[i]))
        .into_iter()
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::camera::DistortionModel;

    fn camera() -> Camera {
        Camera::pinhole([1280, 960], 1250.0, 1240.0, 641.0, 478.0)
            .with_distortion(DistortionModel::Brown5, &[-0.3, 0.05, 0.001, -0.0005])
    }

    #[test]
    fn the_map_and_its_inverse_agree_with_their_jacobian() {
        let camera = camera();
        let map = Undistorted {
            camera: &camera,
            last: std::cell::Cell::new(None),
        };
        for uv in [
            Vector2::new(640.0, 480.0),
            Vector2::new(20.0, 30.0),
            Vector2::new(1250.0, 900.0),
        ] {
            let q = map.to_plane(uv).unwrap();
            let (back, jac) = map.to_image(q).unwrap();
            assert!((back - uv).norm() < 1e-6, "{uv:?} → {q:?} → {back:?}");
            let h = 1e-3;
            for k in 0..2 {
                let mut dq = Vector2::zeros();
                dq[k] = h;
                let (p, _) = map.to_image(q + dq).unwrap();
                let (m, _) = map.to_image(q - dq).unwrap();
                let numeric = (p - m) / (2.0 * h);
                assert!(
                    (numeric - jac.column(k)).norm() < 1e-5,
                    "{numeric:?} vs {jac:?}"
                );
            }
        }
        // Barrel distortion: the undistorted image is larger than the image.
        let q = map.to_plane(Vector2::new(20.0, 30.0)).unwrap();
        assert!(q.x < 20.0 && q.y < 30.0, "{q:?}");
    }

    #[test]
    fn a_camera_of_another_size_is_refused() {
        let img = GrayImage::new(640, 480);
        let mut det = FrameDetection {
            width: 640,
            height: 480,
            faces: Vec::new(),
            rejected: Vec::new(),
        };
        let err = refine_with_camera(&img, &mut det, &camera()).unwrap_err();
        assert!(matches!(err, DetectError::CameraSize { .. }), "{err}");
    }
}
