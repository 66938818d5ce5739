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
//!
//! **Cost.** Mapping every pixel of a window (about a thousand, each one Newton step from its
//! neighbour) was most of the refit. Over one window the map is smooth, so [`refine_with_camera`]
//! interpolates it (`Local`: degree 4 in each window coordinate, 25 exact points at Chebyshev nodes)
//! and uses the polynomial only where it matches the exact map within [`LOCAL_TOLERANCE_PX`]
//! (1e-4 px) at 36 other points over the window, edges and corners included; elsewhere, and beyond
//! the window, the exact map answers. On the 13 OpenCV left photos (640×480, k1 −0.29) 693 of 702
//! windows take the polynomial, the refitted corners are those of the exact map to 1.2e-6 px
//! (median 6e-8), and the photo run's instructions fell from 1540 M to 1462 M (the refit's from
//! 461 M to 381 M; callgrind, `cubecal calibrate --images`); on the k1 −0.3 periphery renders the
//! corners agree to 1e-5 px (`tests/detect_periphery.rs`). Elsewhere (`examples/lens_refit_eval.rs`):
//! OpenCV right photos, pose2sim cam01, the periphery −0.3 and hard renders to ≤ 1.2e-6 px; pycalib
//! 10×7 to 5.2e-4 px at most (median 1.6e-8), at corners whose refit moves them by many σ (an
//! ill-conditioned fit amplifies the map's 1e-4 px), its calibration changed by ≤ 0.003 σ.
//! [`refine_with_camera_exactly`] keeps the pixel-by-pixel map as the reference.
//!
//! **Not skipped.** Skipping the refit where the lens bends a window by less than a tenth of the
//! corner's σ ([`lens_bend_px`]) was measured and rejected (`examples/lens_refit_eval.rs`): the
//! bend is never that small on the photo sets (bend / σ median 40 on the OpenCV left photos, 49 on
//! the right, 0.6 on pose2sim cam01, 0.4 on pycalib 10×7; 11 and 4.7 on the periphery −0.3 and hard
//! renders), and where it is (renders with k1 −0.001 or 0: bend / σ ≤ 0.08) the refit still changes
//! the calibration by up to 0.6 σ and for the better: it is a second fit from the converged corner,
//! without the lattice's noisy curvature correction (realistic set with k1 −0.001: fx error
//! +0.017 → +0.0006 px, cy −0.031 → −0.010 px; hard set with k1 0: corner RMS against the ground
//! truth 0.0939 → 0.0927 px). Skipping it would not be harmless.

use image::GrayImage;
use nalgebra::{Matrix2, SMatrix, Vector2};

use super::complete::{Shade, shading_correction};
use super::face::{FaceDetection, add_grazing_bias_where};
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
        let mut from = d;
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
            // Too far for one step (a jump across a window, as [`Local`] makes between its
            // nodes): Newton's method in full, from the prediction rather than from `d`.
            if start.iter().all(|v| v.is_finite()) {
                from = start;
            }
        }
        let (p, j) = self.camera.undistort_from(d.x, d.y, from).ok()?;
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

/// Degree (in each of the two window coordinates) of [`Local`]'s polynomial.
const LOCAL_DEGREE: usize = 4;
/// Nodes per coordinate of [`Local`]'s interpolation.
const LOCAL_NODES: usize = LOCAL_DEGREE + 1;
/// How far [`Local`] holds, in units of the window's half-extents (every pixel of a window lies
/// within 1; beyond this bound a point is mapped exactly).
const LOCAL_REACH: f64 = 1.05;
/// Largest error, in image px, of [`Local`]'s polynomial against the exact map at its check points
/// for it to be used; a corner whose window bends more is mapped exactly, pixel by pixel.
pub const LOCAL_TOLERANCE_PX: f64 = 1e-4;

/// The undistorted map of one corner's window as a polynomial of degree [`LOCAL_DEGREE`] in each of
/// the window's coordinates `(s, t)` (image offset `s·a + t·b` from the corner, `a`, `b` the
/// window's half-extent steps), interpolating the exact map at Chebyshev nodes: 25 exact points a
/// window instead of one per pixel (a window has about a thousand). It is used only where it agrees
/// with the exact map within [`LOCAL_TOLERANCE_PX`] at 36 other points spread over the window
/// (its edges and corners included); [`PlaneMap::to_image`] (the corner's way back) is the exact map.
struct Local<'m, 'c> {
    exact: &'m Undistorted<'c>,
    p0: Vector2<f64>,
    /// Image offset from `p0` → `(s, t)`.
    to_st: Matrix2<f64>,
    /// The plane position at `p0`; the polynomial gives the offset from it.
    q0: Vector2<f64>,
    /// `coef[i][j][k]`: coefficient of `sⁱ tʲ` in plane coordinate `k` (the two coordinates side
    /// by side, evaluated together).
    coef: [[[f64; 2]; LOCAL_NODES]; LOCAL_NODES],
}

/// The Chebyshev nodes in `[−LOCAL_REACH, LOCAL_REACH]` and the inverse of their Vandermonde matrix
/// (`A[(a, i)] = xₐⁱ`), computed once.
fn local_nodes() -> &'static ([f64; LOCAL_NODES], SMatrix<f64, LOCAL_NODES, LOCAL_NODES>) {
    static NODES: std::sync::OnceLock<(
        [f64; LOCAL_NODES],
        SMatrix<f64, LOCAL_NODES, LOCAL_NODES>,
    )> = std::sync::OnceLock::new();
    NODES.get_or_init(|| {
        let n = LOCAL_NODES as f64;
        let x: [f64; LOCAL_NODES] = std::array::from_fn(|a| {
            LOCAL_REACH * ((2.0 * a as f64 + 1.0) * std::f64::consts::PI / (2.0 * n)).cos()
        });
        let vandermonde =
            SMatrix::<f64, LOCAL_NODES, LOCAL_NODES>::from_fn(|a, i| x[a].powi(i as i32));
        // Distinct nodes: the Vandermonde matrix is invertible (and well conditioned at degree 4).
        let inverse = vandermonde
            .try_inverse()
            .unwrap_or_else(SMatrix::<f64, LOCAL_NODES, LOCAL_NODES>::identity);
        (x, inverse)
    })
}

impl<'m, 'c> Local<'m, 'c> {
    /// The polynomial map of the window at `p0` with steps `a`, `b` to the neighbours (shaped as
    /// [`super::refine`] shapes it), or `None` where it does not hold within
    /// [`LOCAL_TOLERANCE_PX`] (or the exact map fails at one of its points).
    fn new(
        exact: &'m Undistorted<'c>,
        p0: Vector2<f64>,
        a: Vector2<f64>,
        b: Vector2<f64>,
    ) -> Option<Local<'m, 'c>> {
        let (a, b) = (window_half_step(a)?, window_half_step(b)?);
        let frame = Matrix2::from_columns(&[a, b]);
        let to_st = frame.try_inverse()?;
        let q0 = exact.to_plane(p0)?;
        let (x, inverse) = local_nodes();
        let mut values = [SMatrix::<f64, LOCAL_NODES, LOCAL_NODES>::zeros(); 2];
        for (i, &s) in x.iter().enumerate() {
            for (j, &t) in x.iter().enumerate() {
                let q = exact.to_plane(p0 + frame * Vector2::new(s, t))? - q0;
                values[0][(i, j)] = q.x;
                values[1][(i, j)] = q.y;
            }
        }
        let [c0, c1] = values.map(|v| inverse * v * inverse.transpose());
        let coef = std::array::from_fn(|i| std::array::from_fn(|j| [c0[(i, j)], c1[(i, j)]]));
        let local = Local {
            exact,
            p0,
            to_st,
            q0,
            coef,
        };
        // Plane px → image px: the map's Jacobian at the corner bounds how far an error moves.
        let (_, jac) = exact.to_image(q0)?;
        let scale = jac.norm();
        const CHECKS: usize = LOCAL_NODES + 1;
        for i in 0..CHECKS {
            for j in 0..CHECKS {
                let at = |k: usize| LOCAL_REACH * (2.0 * k as f64 / (CHECKS - 1) as f64 - 1.0);
                let uv = p0 + frame * Vector2::new(at(i), at(j));
                let error =
                    (local.polynomial(Vector2::new(at(i), at(j))) - exact.to_plane(uv)?).norm();
                if !(error * scale <= LOCAL_TOLERANCE_PX) {
                    return None;
                }
            }
        }
        Some(local)
    }

    /// Horner's scheme in `t` for each power of `s`, then in `s` (written out: through nalgebra's
    /// generic products it took twice the instructions), both coordinates in step: the same
    /// operations in the same order for each as one at a time, as pairs the compiler packs into one
    /// SIMD register (a photo run's refit: 381 M instructions one coordinate at a time, 348 M in step;
    /// callgrind, `cubecal calibrate --images` on the 13 OpenCV left photos, the same corners).
    fn polynomial(&self, st: Vector2<f64>) -> Vector2<f64> {
        let (s, t) = (st.x, st.y);
        let mut acc = [0.0; 2];
        for c in self.coef.iter().rev() {
            let mut row = [0.0; 2];
            for cij in c.iter().rev() {
                row = [row[0] * t + cij[0], row[1] * t + cij[1]];
            }
            acc = [acc[0] * s + row[0], acc[1] * s + row[1]];
        }
        self.q0 + Vector2::new(acc[0], acc[1])
    }
}

impl PlaneMap for Local<'_, '_> {
    fn to_plane(&self, uv: Vector2<f64>) -> Option<Vector2<f64>> {
        let st = self.to_st * (uv - self.p0);
        if st.x.abs() <= LOCAL_REACH && st.y.abs() <= LOCAL_REACH {
            Some(self.polynomial(st))
        } else {
            self.exact.to_plane(uv)
        }
    }

    fn to_image(&self, q: Vector2<f64>) -> Option<(Vector2<f64>, Matrix2<f64>)> {
        self.exact.to_image(q)
    }
}

/// The step `v` to a neighbouring corner scaled to the window's half-extent along it, as
/// [`super::refine`] sizes its window ([`refine::WINDOW`] of the step, within
/// [`refine::MIN_HALF_PX`] … [`refine::MAX_HALF_PX`]).
fn window_half_step(v: Vector2<f64>) -> Option<Vector2<f64>> {
    use super::refine::{MAX_HALF_PX, MIN_HALF_PX, WINDOW};
    let l = v.norm();
    (l > 0.0).then(|| v * ((WINDOW * l).clamp(MIN_HALF_PX, MAX_HALF_PX) / l))
}

/// Each corner's image steps to its next neighbours along the columns and along the rows (from
/// whichever neighbour exists), in the order of `face.corners`: the frame its window is shaped by.
/// `None` for a corner with no neighbour along a row or a column.
fn corner_steps(face: &FaceDetection) -> Vec<Option<(Vector2<f64>, Vector2<f64>)>> {
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
    (face.corners.iter())
        .map(|c| Some((step(c.row, c.col, 0, 1)?, step(c.row, c.col, 1, 0)?)))
        .collect()
}

/// How far `camera`'s lens bends the window a corner at `uv` is fitted in (the steps `a`, `b` to its
/// neighbours, as in [`refine_with_camera`]): the largest distance, px, between where the lens images
/// a point of the window and where its affine approximation at the corner (the first-order Taylor
/// expansion of the undistorted → image map) puts it, over a 5 × 5 grid of the window's parallelogram
/// (half-extents [`refine::WINDOW`] of the steps, within [`refine::MIN_HALF_PX`] …
/// [`refine::MAX_HALF_PX`]). A straight edge through the window is imaged within this distance of a
/// straight line; the straight-edge fit's bias is a fraction of it (`κL²/6` of a sagitta `κL²/2`).
/// `None` where the lens cannot be inverted at `uv`.
pub fn lens_bend_px(
    camera: &Camera,
    uv: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Option<f64> {
    let map = Undistorted {
        camera,
        last: std::cell::Cell::new(None),
    };
    let (a, b) = (window_half_step(a)?, window_half_step(b)?);
    let q0 = map.to_plane(uv)?;
    let (at, jac) = map.to_image(q0)?;
    let inv = jac.try_inverse()?;
    let mut worst: f64 = 0.0;
    for i in -2..=2 {
        for j in -2..=2 {
            let d = a * (f64::from(i) / 2.0) + b * (f64::from(j) / 2.0);
            let (p, _) = map.to_image(q0 + inv * d)?;
            worst = worst.max((p - (at + d)).norm());
        }
    }
    Some(worst)
}

/// [`lens_bend_px`] of every labelled corner of `det`, in the order of [`FrameDetection::to_view`]
/// (`None` for a corner [`refine_with_camera`] would not fit again: no neighbour along a row or a
/// column, or the lens not invertible there).
pub fn lens_bends(det: &FrameDetection, camera: &Camera) -> Vec<Option<f64>> {
    (det.faces.iter())
        .flat_map(|face| {
            (face.corners.iter().zip(corner_steps(face)))
                .map(|(c, step)| step.and_then(|(a, b)| lens_bend_px(camera, c.uv, a, b)))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// What [`refine_with_camera`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rerefined {
    /// Labelled corners in the frame.
    pub corners: usize,
    /// Corners fitted again in undistorted coordinates (the others keep their image fit: no
    /// neighbour along a row or column to shape the window, or the fit failed).
    pub refitted: usize,
    /// Corners whose window was mapped through its polynomial ([`LOCAL_TOLERANCE_PX`]) rather
    /// than pixel by pixel.
    pub local: usize,
}

/// Fit every labelled corner of `det` again in the undistorted coordinates of `camera` (see the
/// module doc); `img` is the frame `det` was detected in. Corners that cannot be fitted again keep
/// their position. `camera` must be of the frame's size.
pub fn refine_with_camera(
    img: &GrayImage,
    det: &mut FrameDetection,
    camera: &Camera,
) -> Result<Rerefined, DetectError> {
    refit(img, det, camera, true)
}

/// [`refine_with_camera`] with every window mapped exactly, pixel by pixel (no polynomial map):
/// the reference the polynomial is measured against (`examples/lens_refit_eval.rs`, tests).
pub fn refine_with_camera_exactly(
    img: &GrayImage,
    det: &mut FrameDetection,
    camera: &Camera,
) -> Result<Rerefined, DetectError> {
    refit(img, det, camera, false)
}

fn refit(
    img: &GrayImage,
    det: &mut FrameDetection,
    camera: &Camera,
    polynomial: bool,
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
        let steps = corner_steps(face);
        // Each refitted corner's shading, for the correction applied once the face is done.
        let mut shades = std::collections::BTreeMap::new();
        let mut refitted = vec![false; face.corners.len()];
        for ((corner, step), refitted) in face.corners.iter_mut().zip(steps).zip(&mut refitted) {
            out.corners += 1;
            let Some((a, b)) = step else {
                continue;
            };
            let local = polynomial
                .then(|| Local::new(&map, corner.uv, a, b))
                .flatten();
            let fit = match local {
                Some(local) => {
                    out.local += 1;
                    refine_mapped(img, corner.uv, a, b, &local)
                }
                None => refine_mapped(img, corner.uv, a, b, &map),
            };
            match fit {
                Ok(f) => {
                    corner.uv = f.uv;
                    corner.sigma_px = f.sigma_px;
                    corner.cov = f.cov;
                    shades.insert((corner.row as i32, corner.col as i32), Shade::of(&f));
                    out.refitted += 1;
                    *refitted = true;
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
        // The shading across each window, from the refitted neighbours' levels (as in detection).
        for corner in &mut face.corners {
            let key = (corner.row as i32, corner.col as i32);
            if shades.contains_key(&key) {
                corner.uv += shading_correction(&shades, key.0, key.1);
            }
        }
        // A grazing face's bias outlives the refit (noise-free, the realistic set's corners at
        // 75–80° err by 0.0076 px after it, 0.0080 px before): its term goes back into the new
        // fits' covariances, as detection put it into the first ones'.
        add_grazing_bias_where(face, |k| refitted[k]);
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
    fn the_polynomial_map_holds_over_the_whole_window() {
        let camera = camera();
        let map = Undistorted {
            camera: &camera,
            last: std::cell::Cell::new(None),
        };
        let (mut used, mut checked) = (0, 0);
        // Corners from the centre to the image corner, 30 px squares (windows of 19.5 px) and the
        // largest windows (squares of 40 px and more: 24 px), the steps turned and foreshortened.
        for (uv, a, b) in [
            ((640.0, 480.0), (30.0, 0.0), (0.0, 30.0)),
            ((900.0, 700.0), (28.0, 6.0), (-5.0, 22.0)),
            ((1200.0, 900.0), (40.0, 3.0), (2.0, 45.0)),
            ((60.0, 50.0), (38.0, -9.0), (12.0, 30.0)),
        ] {
            let (uv, a, b) = (
                Vector2::new(uv.0, uv.1),
                Vector2::new(a.0, a.1),
                Vector2::new(b.0, b.1),
            );
            let Some(local) = Local::new(&map, uv, a, b) else {
                continue;
            };
            used += 1;
            let (ha, hb) = (window_half_step(a).unwrap(), window_half_step(b).unwrap());
            let (_, jac) = map.to_image(map.to_plane(uv).unwrap()).unwrap();
            for i in 0..=40 {
                for j in 0..=40 {
                    let (s, t) = (f64::from(i) / 20.0 - 1.0, f64::from(j) / 20.0 - 1.0);
                    let p = uv + ha * s + hb * t;
                    let err =
                        jac.norm() * (local.to_plane(p).unwrap() - map.to_plane(p).unwrap()).norm();
                    assert!(
                        err <= 2.0 * LOCAL_TOLERANCE_PX,
                        "{uv:?} at ({s}, {t}): {err:e} px"
                    );
                    checked += 1;
                }
            }
            // Beyond its reach the exact map answers (to its warm start's 1e-7 px).
            let far = uv + ha * 1.5;
            assert!((local.to_plane(far).unwrap() - map.to_plane(far).unwrap()).norm() < 1e-6);
        }
        assert!(used >= 3, "{used} of 4 windows took the polynomial");
        assert!(checked > 0);
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
