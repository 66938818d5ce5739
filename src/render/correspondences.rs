//! Synthetic correspondences with exact ground truth, for tests and benchmarks: the inner corners of a
//! three-face outside cube, views from around the cube's visible corner, exact projection through a
//! known camera, and seeded Gaussian corner noise.
//!
//! (Rendered *images* of rigs are the job of the parent module, [`crate::render`]; this module stops at
//! correspondences.)

use nalgebra::{Rotation3, Unit, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::calib::{Correspondence, View};
use crate::camera::{Camera, DistortionModel, Pose};

/// One planar grid of inner corners: origin, column and row directions (unit), counts and pitch (mm).
#[derive(Debug, Clone)]
pub struct Grid {
    pub origin: Vector3<f64>,
    pub col_dir: Vector3<f64>,
    pub row_dir: Vector3<f64>,
    pub cols: usize,
    pub rows: usize,
    pub square_mm: f64,
}

impl Grid {
    pub fn points(&self) -> impl Iterator<Item = Vector3<f64>> + '_ {
        (0..self.rows).flat_map(move |r| {
            (0..self.cols).map(move |c| {
                self.origin
                    + self.col_dir * (c as f64 * self.square_mm)
                    + self.row_dir * (r as f64 * self.square_mm)
            })
        })
    }
}

/// A cube of side `side_mm` occupying `[0, side]³`, with distinct grids on its three faces that are
/// visible from the `(+, +, +)` corner: `x = side`, `y = side`, `z = side`. About 150 corners.
pub fn three_face_cube(side_mm: f64) -> Vec<Grid> {
    let sq = side_mm / 10.0;
    let m = 1.5 * sq; // margin from the cube edges to the first inner corner
    vec![
        Grid {
            origin: Vector3::new(side_mm, m, m),
            col_dir: Vector3::y(),
            row_dir: Vector3::z(),
            cols: 8,
            rows: 8,
            square_mm: sq,
        },
        Grid {
            origin: Vector3::new(m, side_mm, m),
            col_dir: Vector3::x(),
            row_dir: Vector3::z(),
            cols: 8,
            rows: 6,
            square_mm: sq,
        },
        Grid {
            origin: Vector3::new(m, m, side_mm),
            col_dir: Vector3::x(),
            row_dir: Vector3::y(),
            cols: 7,
            rows: 6,
            square_mm: sq,
        },
    ]
}

/// Every inner corner of [`three_face_cube`], face by face.
pub fn three_face_cube_points(side_mm: f64) -> Vec<Vector3<f64>> {
    three_face_cube(side_mm)
        .iter()
        .flat_map(|g| g.points().collect::<Vec<_>>())
        .collect()
}

/// `cam_from_rig` for a camera at `eye` looking at `target`, with the image "up" near `up`
/// (camera frame: x right, y down, z forward).
pub fn look_at(eye: &Vector3<f64>, target: &Vector3<f64>, up: &Vector3<f64>) -> Pose {
    let z = (target - eye).normalize();
    let x = z.cross(up).normalize(); // right = forward × up (with y down)
    let y = z.cross(&x);
    let r = nalgebra::Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let rotation = Rotation3::from_matrix_unchecked(r);
    Pose {
        rotation,
        translation: -(rotation * eye),
    }
}

/// The camera used throughout the acceptance tests: 1280×960, fx ≈ 1000, Brown–Conrady 5.
pub fn reference_camera() -> Camera {
    Camera::pinhole([1280, 960], 1002.5, 998.0, 645.2, 476.8).with_distortion(
        DistortionModel::Brown5,
        &[-0.21, 0.09, 0.0009, -0.0006, -0.018],
    )
}

/// A synthetic calibration problem with its ground truth.
#[derive(Debug, Clone)]
pub struct Scenario {
    pub camera: Camera,
    pub poses: Vec<Pose>,
    /// Noise-free observations.
    pub views: Vec<View>,
}

/// Views of the three-face cube from around its `(+, +, +)` corner: directions perturbed up to ~25°,
/// random roll, distance chosen so that the cube fills much of the image. Only corners that project
/// inside the image (with a 2 px border) are kept; every view keeps at least 100 of them.
pub fn cube_scenario(camera: &Camera, side_mm: f64, n_views: usize, seed: u64) -> Scenario {
    let pts = three_face_cube_points(side_mm);
    let centre = Vector3::repeat(side_mm / 2.0);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let [w, h] = camera.image_size;
    let mut poses = Vec::new();
    let mut views = Vec::new();
    let mut attempts = 0;
    while views.len() < n_views && attempts < 10_000 {
        attempts += 1;
        let dir = Vector3::new(
            1.0 + rng.random_range(-0.45..0.45),
            1.0 + rng.random_range(-0.45..0.45),
            1.0 + rng.random_range(-0.45..0.45),
        )
        .normalize();
        let dist = side_mm * rng.random_range(2.6..3.6);
        let eye = centre + dir * dist;
        let aim = centre
            + Vector3::new(
                rng.random_range(-0.15..0.15),
                rng.random_range(-0.15..0.15),
                rng.random_range(-0.15..0.15),
            ) * side_mm;
        let up0 = Vector3::z();
        let roll = rng.random_range(-0.6..0.6);
        let axis = Unit::new_normalize(aim - eye);
        let up = Rotation3::from_axis_angle(&axis, roll) * up0;
        let pose = look_at(&eye, &aim, &up);
        let mut corr = Vec::new();
        for p in &pts {
            // Visible face: the camera must be on the outer side of the face plane.
            let pc = pose.transform(p);
            if pc.z <= 0.0 {
                continue;
            }
            if let Ok(uv) = camera.project(&pose, p)
                && uv.x > 1.5
                && uv.y > 1.5
                && uv.x < f64::from(w) - 2.5
                && uv.y < f64::from(h) - 2.5
            {
                corr.push(Correspondence::new(*p, uv));
            }
        }
        // Keep only poses seeing nearly all of the cube (the three faces are all visible by design).
        if corr.len() < 100 {
            continue;
        }
        views.push(View {
            name: format!("view{:02}", views.len()),
            points: corr,
        });
        poses.push(pose);
    }
    Scenario {
        camera: camera.clone(),
        poses,
        views,
    }
}

/// Add seeded isotropic Gaussian noise of `sigma_px` to every image point.
pub fn add_noise(views: &[View], sigma_px: f64, seed: u64) -> Vec<View> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // σ is clamped to a finite non-negative value, for which `Normal::new` cannot fail.
    let sigma = if sigma_px.is_finite() {
        sigma_px.max(0.0)
    } else {
        0.0
    };
    let Ok(normal) = Normal::new(0.0, sigma) else {
        return views.to_vec();
    };
    views
        .iter()
        .map(|v| View {
            name: v.name.clone(),
            points: v
                .points
                .iter()
                .map(|c| Correspondence {
                    xyz: c.xyz,
                    uv: c.uv + Vector2::new(normal.sample(&mut rng), normal.sample(&mut rng)),
                    cov: None,
                })
                .collect(),
        })
        .collect()
}
