//! The numbers behind the plots, as pure functions of the run's data: residuals per point and view,
//! the coverage grid, the lens displacement field and the projection uncertainty. The plots only draw
//! what these return, so the tests check these values and then that the plots show them.

use std::collections::HashMap;
use std::str::FromStr;

use nalgebra::{DMatrix, Matrix3, Rotation3, SMatrix, Vector2, Vector3};

use crate::calib::observations::RawObservations;
use crate::calib::report::CalibrationReport;
use crate::camera::{Camera, CameraError, DistortionModel, N_INTRINSIC, PARAM_NAMES, Pose, idx};

use super::run::HeldOutPose;

/// Image grid used for the coverage plot: columns × rows of equal cells over the frame.
pub const COVERAGE_GRID: (usize, usize) = (8, 6);

/// A view whose RMS exceeds this multiple of the median RMS of the fitted views is marked as an
/// outlier view in the per-view plot.
pub const OUTLIER_VIEW_FACTOR: f64 = 2.0;

/// The calibrated camera of a report (`K`, distortion model and coefficients).
pub fn camera_from_report(c: &CalibrationReport) -> Result<Camera, CameraError> {
    let k = c.camera_matrix;
    let model = DistortionModel::from_str(&c.distortion.model)?;
    let mut cam = Camera::pinhole(c.image_size, k[0][0], k[1][1], k[0][2], k[1][2])
        .with_distortion(model, &c.distortion.coefficients);
    cam.params[idx::SKEW] = k[0][1];
    cam.validate()?;
    Ok(cam)
}

/// `cam_from_rig` from a row-major rotation and a translation (as stored in reports).
pub fn pose_from_rows(rotation: &[[f64; 3]; 3], translation: &[f64; 3]) -> Pose {
    let r = Matrix3::from_fn(|i, j| rotation[i][j]);
    Pose {
        rotation: Rotation3::from_matrix_unchecked(r),
        translation: Vector3::from(*translation),
    }
}

/// One observed corner and its reprojection residual.
#[derive(Debug, Clone, PartialEq)]
pub struct Residual {
    /// Index of the view in the observations file.
    pub view: usize,
    /// Observed position (px).
    pub uv: Vector2<f64>,
    /// Observed minus projected (px).
    pub r: Vector2<f64>,
    /// Face name, when the observations carry it.
    pub face: Option<String>,
    /// The solver rejected this point as an outlier.
    pub outlier: bool,
    /// The point belongs to a held-out view (not in the fit).
    pub held_out: bool,
}

/// Residual summary of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewStat {
    pub name: String,
    /// RMS of the residual components of the inliers, `√(Σr²/2n)` (the convention of `rms_px`).
    pub rms_px: f64,
    pub n_points: usize,
    pub n_outliers: usize,
    pub held_out: bool,
}

/// Residuals of every observed point of every view that has a pose (fitted views from the
/// calibration, held-out views from `held_out`), and the per-view summary, in observation order.
/// Views without a pose are skipped and named in the third value.
pub fn residuals(
    cam: &Camera,
    obs: &RawObservations,
    cal: &CalibrationReport,
    held_out: &[HeldOutPose],
) -> (Vec<Residual>, Vec<ViewStat>, Vec<String>) {
    let fitted: HashMap<&str, &crate::calib::report::ViewReport> =
        cal.views.iter().map(|v| (v.name.as_str(), v)).collect();
    let held: HashMap<&str, &HeldOutPose> = held_out.iter().map(|h| (h.name.as_str(), h)).collect();
    let mut out = Vec::new();
    let mut stats = Vec::new();
    let mut skipped = Vec::new();
    for (i, view) in obs.views.iter().enumerate() {
        let name = view.name.clone().unwrap_or_else(|| format!("view{i}"));
        let (pose, outliers, is_held) = if let Some(v) = fitted.get(name.as_str()) {
            (
                pose_from_rows(&v.rotation, &v.translation),
                v.outliers.clone(),
                false,
            )
        } else if let Some(h) = held.get(name.as_str()) {
            (
                pose_from_rows(&h.rotation, &h.translation),
                Vec::new(),
                true,
            )
        } else {
            skipped.push(name);
            continue;
        };
        let (mut ss, mut n) = (0.0, 0usize);
        let mut n_out = 0;
        for (j, p) in view.points.iter().enumerate() {
            let Ok(proj) = cam.project(&pose, &Vector3::from(p.xyz)) else {
                continue;
            };
            let uv = Vector2::from(p.uv);
            let r = uv - proj;
            let outlier = outliers.contains(&j);
            if outlier {
                n_out += 1;
            } else {
                ss += r.norm_squared();
                n += 1;
            }
            out.push(Residual {
                view: i,
                uv,
                r,
                face: p.face.clone(),
                outlier,
                held_out: is_held,
            });
        }
        stats.push(ViewStat {
            name,
            rms_px: if n > 0 {
                (ss / (2 * n) as f64).sqrt()
            } else {
                f64::NAN
            },
            n_points: view.points.len(),
            n_outliers: n_out,
            held_out: is_held,
        });
    }
    (out, stats, skipped)
}

/// Median RMS of the fitted (not held-out) views; views above [`OUTLIER_VIEW_FACTOR`] times this are
/// outlier views.
pub fn median_fitted_rms(stats: &[ViewStat]) -> Option<f64> {
    let mut v: Vec<f64> = stats
        .iter()
        .filter(|s| !s.held_out && s.rms_px.is_finite())
        .map(|s| s.rms_px)
        .collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    Some(if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    })
}

/// Corner counts per cell of a `cols × rows` grid over the image (row-major, row 0 at the top).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CoverageGrid {
    pub cols: usize,
    pub rows: usize,
    pub counts: Vec<usize>,
}

impl CoverageGrid {
    /// Count `points` (px, pixel-centre convention) into the grid; points outside the image are
    /// ignored. The image spans `[-½, w − ½) × [-½, h − ½)`.
    pub fn count(
        points: impl IntoIterator<Item = Vector2<f64>>,
        image_size: [u32; 2],
        (cols, rows): (usize, usize),
    ) -> CoverageGrid {
        let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
        let mut counts = vec![0; cols * rows];
        for p in points {
            let (a, b) = ((p.x + 0.5) / w, (p.y + 0.5) / h);
            if !(0.0..1.0).contains(&a) || !(0.0..1.0).contains(&b) {
                continue;
            }
            let c = ((a * cols as f64) as usize).min(cols - 1);
            let r = ((b * rows as f64) as usize).min(rows - 1);
            counts[r * cols + c] += 1;
        }
        CoverageGrid { cols, rows, counts }
    }

    pub fn covered(&self) -> usize {
        self.counts.iter().filter(|&&c| c > 0).count()
    }

    /// Fraction of cells holding at least one corner.
    pub fn fraction(&self) -> f64 {
        if self.counts.is_empty() {
            0.0
        } else {
            self.covered() as f64 / self.counts.len() as f64
        }
    }
}

/// A histogram of residual components in units of pixels, with bins of equal width centred on 0.
#[derive(Debug, Clone, PartialEq)]
pub struct Histogram {
    /// Left edge of the first bin (px).
    pub start: f64,
    /// Bin width (px).
    pub width: f64,
    pub counts: Vec<usize>,
    /// Values beyond either end.
    pub outside: usize,
}

/// Histogram of `values` over `±4σ` in bins of `σ/4` (32 bins). `sigma` must be positive.
pub fn histogram(values: impl IntoIterator<Item = f64>, sigma: f64) -> Histogram {
    const BINS: usize = 32;
    let width = 8.0 * sigma / BINS as f64;
    let start = -4.0 * sigma;
    let mut counts = vec![0; BINS];
    let mut outside = 0;
    for v in values {
        let k = ((v - start) / width).floor();
        if k >= 0.0 && k < BINS as f64 {
            counts[k as usize] += 1;
        } else {
            outside += 1;
        }
    }
    Histogram {
        start,
        width,
        counts,
        outside,
    }
}

/// Samples of a scalar field over the image: `values[j * nx + i]` at the centre of cell `(i, j)` of
/// an `nx × ny` grid; NaN where it could not be computed.
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub nx: usize,
    pub ny: usize,
    pub values: Vec<f64>,
}

impl Field {
    fn sample(image_size: [u32; 2], nx: usize, ny: usize, f: impl Fn(f64, f64) -> f64) -> Field {
        let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
        let mut values = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                let (u, v) = cell_centre(w, h, nx, ny, i, j);
                values.push(f(u, v));
            }
        }
        Field { nx, ny, values }
    }

    /// Smallest finite value (0 when there is none).
    pub fn min(&self) -> f64 {
        let m = self
            .values
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(f64::INFINITY, f64::min);
        if m.is_finite() { m } else { 0.0 }
    }

    /// Largest finite value (0 when there is none).
    pub fn max(&self) -> f64 {
        self.values
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }
}

/// Pixel position of the centre of cell `(i, j)` of an `nx × ny` grid over a `w × h` image.
pub fn cell_centre(w: f64, h: f64, nx: usize, ny: usize, i: usize, j: usize) -> (f64, f64) {
    (
        (i as f64 + 0.5) * w / nx as f64 - 0.5,
        (j as f64 + 0.5) * h / ny as f64 - 0.5,
    )
}

/// How far the lens moves each pixel: at an observed (distorted) pixel, the distance in pixels to
/// where an ideal pinhole camera with the same `K` would have imaged the same ray — for a fisheye
/// ([`DistortionModel::Kb4`]) an ideal equidistant one (`r = f·θ`, all k zero: its k measure the
/// departure from that, and a pinhole's image of 90° is at infinity). NaN where the undistortion
/// does not converge (far outside the calibrated field).
pub fn displacement_field(cam: &Camera, nx: usize, ny: usize) -> Field {
    if cam.model == DistortionModel::Kb4 {
        return Field::sample(cam.image_size, nx, ny, |u, v| match cam.unproject(u, v) {
            Ok(ray) => {
                let theta = ray.xy().norm().atan2(ray.z);
                let yd = (v - cam.cy()) / cam.fy();
                let xd = (u - cam.cx() - cam.skew() * yd) / cam.fx();
                let rd = xd.hypot(yd);
                if rd == 0.0 {
                    return 0.0;
                }
                let ideal = Vector2::new(xd, yd) * (theta / rd);
                (cam.to_pixel(&ideal) - Vector2::new(u, v)).norm()
            }
            Err(_) => f64::NAN,
        });
    }
    Field::sample(cam.image_size, nx, ny, |u, v| {
        let yd = (v - cam.cy()) / cam.fy();
        let xd = (u - cam.cx() - cam.skew() * yd) / cam.fx();
        match cam.undistort(xd, yd) {
            Ok(p) => (cam.to_pixel(&p) - Vector2::new(u, v)).norm(),
            Err(_) => f64::NAN,
        }
    })
}

/// Straight lines of the ideal (undistorted) image, as the lens draws them: a `lines × lines` grid
/// of lines spanning the image in ideal pixel coordinates, each sampled at 40 points and mapped
/// through the distortion. Points more than half an image outside the frame are dropped.
pub fn distorted_grid(cam: &Camera, lines: usize) -> Vec<Vec<(f64, f64)>> {
    let (w, h) = (f64::from(cam.image_size[0]), f64::from(cam.image_size[1]));
    let map = |u: f64, v: f64| -> Option<(f64, f64)> {
        let y = (v - cam.cy()) / cam.fy();
        let x = (u - cam.cx() - cam.skew() * y) / cam.fx();
        let p = cam.to_pixel(&cam.distort(x, y));
        let inside = p.x > -0.5 * w && p.x < 1.5 * w && p.y > -0.5 * h && p.y < 1.5 * h;
        (p.x.is_finite() && p.y.is_finite() && inside).then_some((p.x, p.y))
    };
    let steps = 40;
    let mut out = Vec::new();
    for k in 0..=lines {
        let t = k as f64 / lines as f64;
        let vertical: Vec<_> = (0..=steps)
            .filter_map(|s| map(t * (w - 1.0), s as f64 / steps as f64 * (h - 1.0)))
            .collect();
        let horizontal: Vec<_> = (0..=steps)
            .filter_map(|s| map(s as f64 / steps as f64 * (w - 1.0), t * (h - 1.0)))
            .collect();
        out.push(vertical);
        out.push(horizontal);
    }
    out
}

/// Why the projection uncertainty cannot be computed from a report.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum UncertaintyError {
    #[error("the calibration has no covariance")]
    NoCovariance,
    #[error("covariance is {rows}×{cols} but {n} free parameters are named")]
    Shape { rows: usize, cols: usize, n: usize },
    #[error("unknown free parameter '{0}'")]
    UnknownParam(String),
}

/// The covariance of the full 13-parameter intrinsic vector implied by a report's covariance of its
/// free parameters: `Σ₁₃ = M Σ Mᵀ` where `M` maps free parameters to the full vector (`f` is the tied
/// focal length of a fixed aspect ratio: `fx = a·f`, `fy = f`).
pub fn full_covariance(
    cal: &CalibrationReport,
) -> Result<SMatrix<f64, N_INTRINSIC, N_INTRINSIC>, UncertaintyError> {
    let n = cal.free_params.len();
    if n == 0 || cal.covariance.is_empty() {
        return Err(UncertaintyError::NoCovariance);
    }
    if cal.covariance.len() != n || cal.covariance.iter().any(|r| r.len() != n) {
        return Err(UncertaintyError::Shape {
            rows: cal.covariance.len(),
            cols: cal.covariance.first().map_or(0, Vec::len),
            n,
        });
    }
    let k = cal.camera_matrix;
    let aspect = k[0][0] / k[1][1];
    let mut m = DMatrix::<f64>::zeros(N_INTRINSIC, n);
    for (j, name) in cal.free_params.iter().enumerate() {
        if name == "f" {
            m[(idx::FX, j)] = aspect;
            m[(idx::FY, j)] = 1.0;
        } else if let Some(i) = PARAM_NAMES.iter().position(|p| p == name) {
            m[(i, j)] = 1.0;
        } else {
            return Err(UncertaintyError::UnknownParam(name.clone()));
        }
    }
    let s = DMatrix::from_fn(n, n, |i, j| cal.covariance[i][j]);
    let full = &m * s * m.transpose();
    Ok(SMatrix::from_fn(|i, j| full[(i, j)]))
}

/// Standard deviation (px) of the projection of the point seen at pixel `(u, v)` at `distance_mm`
/// along its ray, from the intrinsics' covariance: the larger semi-axis of the 1σ ellipse of
/// `J Σ Jᵀ`, `J = ∂uv/∂intrinsics`. For a point fixed in the camera frame the projection depends
/// only on its direction, so the value is the same at every distance; the distance is an argument
/// so that the statement "at D mm" is explicit where it is shown. NaN where the pixel's ray cannot
/// be found (undistortion fails).
pub fn projection_sigma(
    cam: &Camera,
    cov: &SMatrix<f64, N_INTRINSIC, N_INTRINSIC>,
    u: f64,
    v: f64,
    distance_mm: f64,
) -> f64 {
    let yd = (v - cam.cy()) / cam.fy();
    let xd = (u - cam.cx() - cam.skew() * yd) / cam.fx();
    let Ok(p) = cam.undistort(xd, yd) else {
        return f64::NAN;
    };
    let ray = Vector3::new(p.x, p.y, 1.0).normalize() * distance_mm;
    let Ok((_, j, _)) = cam.project_cam_with_jacobians(&ray) else {
        return f64::NAN;
    };
    let s = j * cov * j.transpose();
    // Largest eigenvalue of the symmetric 2×2 matrix.
    let (a, b, c) = (s[(0, 0)], s[(0, 1)], s[(1, 1)]);
    let mean = 0.5 * (a + c);
    let dev = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    (mean + dev).max(0.0).sqrt()
}

/// [`projection_sigma`] over an `nx × ny` grid of the image.
pub fn uncertainty_field(
    cam: &Camera,
    cov: &SMatrix<f64, N_INTRINSIC, N_INTRINSIC>,
    distance_mm: f64,
    nx: usize,
    ny: usize,
) -> Field {
    Field::sample(cam.image_size, nx, ny, |u, v| {
        projection_sigma(cam, cov, u, v, distance_mm)
    })
}

/// Median distance (mm) from the camera to the rig origin over the fitted views: the working
/// distance at which the uncertainty map is stated.
pub fn working_distance_mm(cal: &CalibrationReport) -> Option<f64> {
    let mut d: Vec<f64> = cal
        .views
        .iter()
        .map(|v| Vector3::from(v.translation).norm())
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn coverage_counts_cells_with_the_pixel_centre_convention() {
        // 80×60 image, 8×6 grid: 10×10 px cells. Pixel 9 is the last of cell 0 (covers [8.5, 9.5)).
        let pts = [
            Vector2::new(9.0, 0.0),
            Vector2::new(9.6, 0.0),
            Vector2::new(-0.5, -0.5),
            Vector2::new(79.4, 59.4),
            Vector2::new(79.6, 0.0),
        ];
        let g = CoverageGrid::count(pts, [80, 60], (8, 6));
        assert_eq!(g.counts[0], 2);
        assert_eq!(g.counts[1], 1);
        assert_eq!(g.counts[5 * 8 + 7], 1);
        assert_eq!(g.covered(), 3);
        assert!((g.fraction() - 3.0 / 48.0).abs() < 1e-12);
    }

    #[test]
    fn histogram_bins_are_sigma_quarters() {
        let h = histogram([0.0, 0.1, -0.1, 0.26, 5.0, -5.0], 1.0);
        assert_eq!(h.counts.len(), 32);
        assert_eq!(h.counts[16], 2); // [0, 0.25)
        assert_eq!(h.counts[15], 1); // [-0.25, 0)
        assert_eq!(h.counts[17], 1); // [0.25, 0.5)
        assert_eq!(h.outside, 2);
    }

    #[test]
    fn uncertainty_of_the_principal_point_alone_is_its_sigma_everywhere() {
        let cam = Camera::pinhole([640, 480], 500.0, 500.0, 320.0, 240.0);
        let mut cov = SMatrix::<f64, N_INTRINSIC, N_INTRINSIC>::zeros();
        cov[(idx::CX, idx::CX)] = 0.25; // σ 0.5 px
        cov[(idx::CY, idx::CY)] = 0.04; // σ 0.2 px
        for (u, v) in [(0.0, 0.0), (320.0, 240.0), (639.0, 100.0)] {
            for d in [100.0, 1000.0] {
                let s = projection_sigma(&cam, &cov, u, v, d);
                assert!((s - 0.5).abs() < 1e-9, "{s}");
            }
        }
        // σ_fx = 1 px: the u error grows with |x| = |u − cx| / fx.
        let mut cov = SMatrix::<f64, N_INTRINSIC, N_INTRINSIC>::zeros();
        cov[(idx::FX, idx::FX)] = 1.0;
        let s = projection_sigma(&cam, &cov, 320.0 + 250.0, 240.0, 500.0);
        assert!((s - 0.5).abs() < 1e-9, "{s}");
        assert!(projection_sigma(&cam, &cov, 320.0, 240.0, 500.0) < 1e-9);
    }

    #[test]
    fn a_fisheye_is_measured_from_the_equidistant_image() {
        // θ_d = θ(1 + k1 θ²): the lens moves a pixel by f·(θ_d − θ) = f·k1·θ³ radially, θ from θ_d.
        let eq = Camera::pinhole([1280, 960], 350.0, 350.0, 639.5, 479.5)
            .with_distortion(DistortionModel::Kb4, &[]);
        let cam = eq.clone().with_distortion(DistortionModel::Kb4, &[0.03]);
        assert!(
            displacement_field(&eq, 8, 6)
                .values
                .iter()
                .all(|v| v.abs() < 1e-9)
        );
        let f = displacement_field(&cam, 8, 6);
        for j in 0..6 {
            for i in 0..8 {
                let (u, v) = cell_centre(1280.0, 960.0, 8, 6, i, j);
                let td = (u - 639.5).hypot(v - 479.5) / 350.0;
                let mut t = td;
                for _ in 0..200 {
                    t = td / (1.0 + 0.03 * t * t);
                }
                let want = 350.0 * (td - t);
                let got = f.values[j * 8 + i];
                assert!((got - want).abs() < 1e-6, "{got} vs {want}");
            }
        }
    }

    #[test]
    fn displacement_of_radial_distortion_matches_the_model() {
        let cam = Camera::pinhole([640, 480], 500.0, 500.0, 319.5, 239.5)
            .with_distortion(DistortionModel::Brown5, &[-0.2, 0.0, 0.0, 0.0, 0.0]);
        let f = displacement_field(&cam, 4, 2);
        // Undistorted radius r solves r(1 − 0.2 r²) = rd; displacement = 500·(r − rd).
        for j in 0..2 {
            for i in 0..4 {
                let (u, v) = cell_centre(640.0, 480.0, 4, 2, i, j);
                let rd = ((u - 319.5).powi(2) + (v - 239.5).powi(2)).sqrt() / 500.0;
                let mut r = rd;
                for _ in 0..100 {
                    r = rd / (1.0 - 0.2 * r * r);
                }
                let want = 500.0 * (r - rd);
                let got = f.values[j * 4 + i];
                assert!((got - want).abs() < 1e-6, "{got} vs {want}");
            }
        }
    }
}
