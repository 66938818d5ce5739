//! Initialisation of a calibration problem, before refinement:
//! - a view whose rig points span 3D (≥ 6 points) → normalised DLT + RQ gives a `K` and a pose;
//! - a planar view (a flat board, or one face of a cube) → a homography;
//! - shared `K`: the per-component median over the 3D views; with planar views only, Zhang's closed
//!   form (≥ 2 views), falling back to a focal length from each homography with the principal point at
//!   the image centre (one view, or views too alike for Zhang);
//! - poses are then re-estimated with the shared `K` (from `P` or from the homography).
//!
//! Distortion starts at zero: the refinement estimates it.
//!
//! **Fisheye** ([`DistortionModel::Kb4`], [`initialise_fisheye`]): the pinhole initialisations above
//! fail on a fisheye (its image of a straight line is a curve, and rays beyond 90° have no pinhole
//! image). A fisheye is close to equidistant (`r = f θ`, all k = 0), so each of a ladder of focal
//! lengths (the whole image diagonal spanning 60° to 360°, steps of 2^¼) unprojects the points
//! through that equidistant lens about the image centre, re-images the rays within 75° of the axis
//! through a pinhole of the same focal length, and runs the initialisation above on them; the candidate
//! whose camera and poses reproject all points best (median error, as a fisheye) is kept. This is the
//! guess `cv::fisheye::calibrate` starts from (f = max(w, h)/π), searched instead of assumed, so a
//! 100° lens starts as well as a 200° one; a generic central-camera linear method (Scaramuzza's)
//! would need the principal point first and a polynomial the refinement replaces anyway.

use nalgebra::{Matrix3, Matrix3x4, Vector2, Vector3};
use tracing::debug;

use super::linear::{
    COPLANAR_TOLERANCE, decompose_projection, dlt, focal_from_homography, homography, plane_frame,
    pose_from_homography, pose_from_projection, relative_thickness, zhang_intrinsics,
};
use super::{CalibError, Correspondence, View};
use crate::camera::{Camera, DistortionModel, Pose};

/// How the initial intrinsics were obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InitMethod {
    /// DLT + RQ on views of a 3D rig, K shared by median.
    Dlt,
    /// Zhang's closed form on planar homographies.
    Zhang,
    /// One focal length per homography, principal point at the image centre.
    PlanarFocal,
    /// A fisheye: the points unprojected through an equidistant lens (`r = f θ`) for each of a ladder
    /// of focal lengths, each set initialised as a pinhole, the one that reprojects best kept.
    Equidistant,
}

impl InitMethod {
    /// How the initial values were found, in words.
    pub fn describe(self) -> &'static str {
        match self {
            InitMethod::Dlt => "the direct linear transform of each 3D view",
            InitMethod::Zhang => "Zhang's closed form on the planar views",
            InitMethod::PlanarFocal => {
                "a focal length per planar view, principal point at the image centre"
            }
            InitMethod::Equidistant => {
                "a pinhole initialisation of the points unprojected through the best of a ladder of equidistant lenses"
            }
        }
    }
}

/// Initial camera and poses for the refinement.
#[derive(Debug, Clone)]
pub struct Initial {
    pub camera: Camera,
    pub poses: Vec<Pose>,
    pub method: InitMethod,
}

enum ViewInit {
    Projective(Matrix3x4<f64>),
    Planar {
        h: Matrix3<f64>,
        plane_from_rig: Pose,
    },
}

/// The image centre in the pixel-centre convention: `((w − 1)/2, (h − 1)/2)`.
pub fn image_centre(image_size: [u32; 2]) -> Vector2<f64> {
    Vector2::new(
        0.5 * (f64::from(image_size[0]) - 1.0),
        0.5 * (f64::from(image_size[1]) - 1.0),
    )
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Fewest points off a view's main plane for the view to be initialised as 3D (by the DLT). With
/// fewer, the DLT is ill-posed — its off-plane information rests on a few points, and a stray
/// corner labelled on a second face beside a whole first one (22 + 1 on a ChArUco cube photo)
/// made it return a projection whose pose the refinement could not recover — and the view is
/// initialised from the homography of its main plane instead (the strays still enter the
/// refinement). Six is the DLT's own minimum.
pub const MIN_POINTS_OFF_PLANE: usize = 6;

/// When all but fewer than [`MIN_POINTS_OFF_PLANE`] of `x3` lie on one plane: the indices of those
/// on it. Found by trimming: the point farthest from the least-squares plane of those left is
/// dropped until the rest are coplanar ([`COPLANAR_TOLERANCE`]). A few strays pull the
/// least-squares plane less than they lie off it, so they go first; a view spread over two faces
/// needs many drops and is reported as 3D (`None`).
fn plane_with_strays(x3: &[Vector3<f64>]) -> Option<Vec<usize>> {
    let mut kept: Vec<usize> = (0..x3.len()).collect();
    for _ in 0..MIN_POINTS_OFF_PLANE {
        let pts: Vec<Vector3<f64>> = kept.iter().map(|&i| x3[i]).collect();
        if relative_thickness(&pts) < COPLANAR_TOLERANCE {
            return (kept.len() >= 4).then_some(kept);
        }
        let frame = plane_frame(&pts);
        let farthest = (0..kept.len()).max_by(|&a, &b| {
            let da = frame.transform(&pts[a]).z.abs();
            let db = frame.transform(&pts[b]).z.abs();
            da.total_cmp(&db)
        })?;
        kept.remove(farthest);
    }
    None
}

/// Rays farther than this from the axis are left out of the fisheye's pinhole initialisation.
const FISHEYE_INIT_MAX_ANGLE_DEG: f64 = 75.0;

/// Initial intrinsics (distortion zero, model as given) and per-view `cam_from_rig`.
pub fn initialise(
    views: &[View],
    image_size: [u32; 2],
    model: DistortionModel,
) -> Result<Initial, CalibError> {
    if model == DistortionModel::Kb4 {
        return initialise_fisheye(views, image_size);
    }
    initialise_pinhole(views, image_size, model)
}

/// The fisheye's initialisation (module docs): an equidistant lens of the focal length, among a
/// ladder, whose pinhole initialisation reprojects best.
pub fn initialise_fisheye(views: &[View], image_size: [u32; 2]) -> Result<Initial, CalibError> {
    let centre = image_centre(image_size);
    let diagonal = f64::from(image_size[0]).hypot(f64::from(image_size[1]));
    let cos_max = FISHEYE_INIT_MAX_ANGLE_DEG.to_radians().cos();
    let mut best: Option<(f64, Initial)> = None;
    let mut last_error = None;
    // f such that the diagonal spans 360°·2^(−k/4): k = 0 … 8 covers 360° down to 90°, 9, 10 to 60°.
    for k in 0..=10 {
        let f = diagonal / (2.0 * std::f64::consts::PI) * 2f64.powf(f64::from(k) / 4.0);
        let guess = Camera::pinhole(image_size, f, f, centre.x, centre.y)
            .with_distortion(DistortionModel::Kb4, &[]);
        let central: Vec<View> = views
            .iter()
            .map(|v| {
                v.filter_map_points(|c| {
                    let ray = guess.unproject(c.uv.x, c.uv.y).ok()?;
                    (ray.z > cos_max).then(|| Correspondence {
                        uv: Vector2::new(
                            centre.x + f * ray.x / ray.z,
                            centre.y + f * ray.y / ray.z,
                        ),
                        ..*c
                    })
                })
            })
            .collect();
        let init = match initialise_pinhole(&central, image_size, DistortionModel::Kb4) {
            Ok(init) => init,
            Err(e) => {
                last_error = Some(e);
                continue;
            }
        };
        let mut errors: Vec<f64> = views
            .iter()
            .zip(&init.poses)
            .flat_map(|(v, pose)| {
                v.points.iter().map(|c| {
                    init.camera
                        .project(pose, &c.xyz)
                        .map_or(f64::INFINITY, |uv| (uv - c.uv).norm())
                })
            })
            .collect();
        errors.sort_by(f64::total_cmp);
        let score = errors
            .get(errors.len() / 2)
            .copied()
            .unwrap_or(f64::INFINITY);
        debug!(f, score, "fisheye initialisation candidate");
        if score.is_finite() && best.as_ref().is_none_or(|(s, _)| score < *s) {
            best = Some((score, init));
        }
    }
    match best {
        Some((_, mut init)) => {
            init.method = InitMethod::Equidistant;
            Ok(init)
        }
        None => Err(last_error.unwrap_or_else(|| CalibError::Degenerate {
            reason: "no equidistant focal length initialises the fisheye".into(),
        })),
    }
}

fn initialise_pinhole(
    views: &[View],
    image_size: [u32; 2],
    model: DistortionModel,
) -> Result<Initial, CalibError> {
    let mut inits = Vec::with_capacity(views.len());
    let mut ks = Vec::new();
    for v in views {
        let x3: Vec<Vector3<f64>> = v.points.iter().map(|c| c.xyz).collect();
        let x2: Vec<Vector2<f64>> = v.points.iter().map(|c| c.uv).collect();
        let planar = if relative_thickness(&x3) >= COPLANAR_TOLERANCE {
            plane_with_strays(&x3)
        } else {
            Some((0..x3.len()).collect())
        };
        let init = if let Some(on_plane) = planar {
            let x3: Vec<Vector3<f64>> = on_plane.iter().map(|&i| x3[i]).collect();
            let x2: Vec<Vector2<f64>> = on_plane.iter().map(|&i| x2[i]).collect();
            let plane_from_rig = plane_frame(&x3);
            let plane: Vec<Vector2<f64>> = x3
                .iter()
                .map(|p| {
                    let q = plane_from_rig.transform(p);
                    Vector2::new(q.x, q.y)
                })
                .collect();
            let h = homography(&plane, &x2).map_err(|e| e.in_view(&v.name))?;
            ViewInit::Planar { h, plane_from_rig }
        } else {
            let p = dlt(&x3, &x2).map_err(|e| e.in_view(&v.name))?;
            let (k, _) = decompose_projection(&p).map_err(|e| e.in_view(&v.name))?;
            ks.push(k);
            ViewInit::Projective(p)
        };
        inits.push(init);
    }

    let centre = image_centre(image_size);
    let (k, method) = if !ks.is_empty() {
        let k = Matrix3::new(
            median(ks.iter().map(|k| k[(0, 0)]).collect()),
            0.0,
            median(ks.iter().map(|k| k[(0, 2)]).collect()),
            0.0,
            median(ks.iter().map(|k| k[(1, 1)]).collect()),
            median(ks.iter().map(|k| k[(1, 2)]).collect()),
            0.0,
            0.0,
            1.0,
        );
        (k, InitMethod::Dlt)
    } else {
        let hs: Vec<Matrix3<f64>> = inits
            .iter()
            .filter_map(|i| match i {
                ViewInit::Planar { h, .. } => Some(*h),
                ViewInit::Projective(_) => None,
            })
            .collect();
        let zhang = if hs.len() >= 2 {
            zhang_intrinsics(&hs, image_size).ok().filter(|k| {
                // Reject closed-form answers far outside the image (a sign of near-degenerate views).
                let w = f64::from(image_size[0]);
                let h = f64::from(image_size[1]);
                k[(0, 2)] > -0.25 * w
                    && k[(0, 2)] < 1.25 * w
                    && k[(1, 2)] > -0.25 * h
                    && k[(1, 2)] < 1.25 * h
            })
        } else {
            None
        };
        match zhang {
            Some(k) => (k, InitMethod::Zhang),
            None => {
                let fs: Vec<f64> = hs
                    .iter()
                    .filter_map(|h| focal_from_homography(h, centre.x, centre.y))
                    .collect();
                if fs.is_empty() {
                    return Err(CalibError::Degenerate {
                        reason: "no focal length can be estimated: every planar view is fronto-parallel; tilt the board"
                            .into(),
                    });
                }
                let f = median(fs);
                (
                    Matrix3::new(f, 0.0, centre.x, 0.0, f, centre.y, 0.0, 0.0, 1.0),
                    InitMethod::PlanarFocal,
                )
            }
        }
    };
    if !(k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0 && k.iter().all(|x| x.is_finite())) {
        return Err(CalibError::Degenerate {
            reason: format!("initial camera matrix is invalid: {k}"),
        });
    }
    debug!(
        ?method,
        fx = k[(0, 0)],
        fy = k[(1, 1)],
        cx = k[(0, 2)],
        cy = k[(1, 2)],
        "initial intrinsics"
    );

    let mut poses = Vec::with_capacity(views.len());
    for (v, init) in views.iter().zip(&inits) {
        let pose = match init {
            ViewInit::Projective(p) => pose_from_projection(p, &k),
            ViewInit::Planar { h, plane_from_rig } => pose_from_homography(h, &k)
                .map(|cam_from_plane| cam_from_plane.compose(plane_from_rig)),
        }
        .map_err(|e| e.in_view(&v.name))?;
        let behind = v
            .points
            .iter()
            .filter(|c| pose.transform(&c.xyz).z <= 0.0)
            .count();
        if behind == v.points.len() && matches!(init, ViewInit::Projective(_)) {
            // det(M) > 0 and every point behind the camera: only a mirrored (left-handed) rig frame
            // projects like this.
            return Err(CalibError::LeftHandedRig.in_view(&v.name));
        }
        if let Some(i) = v
            .points
            .iter()
            .position(|c| pose.transform(&c.xyz).z <= 0.0)
        {
            return Err(CalibError::Degenerate {
                reason: format!("initial pose puts point {i} behind the camera"),
            }
            .in_view(&v.name));
        }
        poses.push(pose);
    }
    let camera = Camera::pinhole(image_size, k[(0, 0)], k[(1, 1)], k[(0, 2)], k[(1, 2)])
        .with_distortion(model, &[]);
    Ok(Initial {
        camera,
        poses,
        method,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::calib::Correspondence;
    use nalgebra::Rotation3;

    /// A 3×3-face corner of a cube (three faces of 5 × 4 points, 30 mm apart, from 20 mm).
    fn cube_points() -> Vec<Vector3<f64>> {
        let mut pts = Vec::new();
        for i in 0..5 {
            for j in 0..4 {
                let (a, b) = (20.0 + 30.0 * f64::from(i), 20.0 + 30.0 * f64::from(j));
                pts.push(Vector3::new(a, b, 0.0));
                pts.push(Vector3::new(0.0, a, b));
                pts.push(Vector3::new(b, 0.0, a));
            }
        }
        pts
    }

    fn view(name: &str, camera: &Camera, pose: &Pose, xyz: &[Vector3<f64>]) -> View {
        View {
            name: name.into(),
            points: xyz
                .iter()
                .map(|x| Correspondence {
                    xyz: *x,
                    uv: camera.project(pose, x).unwrap_or_default(),
                    cov: None,
                })
                .collect(),
        }
    }

    /// A view whose corners are a whole face and one stray corner of another face (as a ChArUco cube
    /// photo gave: 22 + 1) is initialised from its face's homography, not by a DLT that its one
    /// off-plane point cannot constrain: its initial pose is the true one (noise-free points).
    #[test]
    fn a_face_with_one_stray_corner_is_initialised_as_a_plane() {
        let camera = Camera::pinhole([1280, 960], 900.0, 900.0, 640.0, 480.0);
        let pose = |rx: f64, ry: f64, rz: f64| {
            let rotation = Rotation3::from_euler_angles(rx, ry, rz);
            let centre = rotation.inverse() * Vector3::new(0.0, 0.0, -700.0);
            Pose {
                rotation,
                translation: -(rotation * (centre - Vector3::new(60.0, 60.0, 60.0))),
            }
        };
        let cube = cube_points();
        let poses = [
            pose(2.5, 0.4, 0.3),
            pose(2.3, -0.5, -0.2),
            pose(2.6, 0.2, 0.9),
        ];
        // Third view: the face z = 0 (20 points) and the first point of the face x = 0.
        let mut face: Vec<Vector3<f64>> = cube.iter().filter(|p| p.z == 0.0).copied().collect();
        face.push(cube[1]);
        let views = [
            view("a", &camera, &poses[0], &cube),
            view("b", &camera, &poses[1], &cube),
            view("face and stray", &camera, &poses[2], &face),
        ];
        for (v, p) in views.iter().zip(&poses) {
            assert!(
                v.points.iter().all(|c| p.transform(&c.xyz).z > 0.0),
                "test geometry: {} sees its points",
                v.name
            );
        }
        let init = initialise(&views, camera.image_size, DistortionModel::Pinhole).unwrap();
        assert_eq!(init.method, InitMethod::Dlt);
        let got = &init.poses[2];
        let angle = (got.rotation.matrix().transpose() * poses[2].rotation.matrix()
            - Matrix3::identity())
        .norm();
        let shift = (got.centre() - poses[2].centre()).norm();
        assert!(
            angle < 1e-6 && shift < 1e-3,
            "stray view's initial pose off by {angle} rad, {shift} mm"
        );
    }
}
