//! One view's pose with the camera held fixed (perspective-n-point): what the station uses to check a
//! held-out view against a calibration, and to place a view in a known camera.
//!
//! Initialisation works on undistorted normalised coordinates (the camera's distortion inverted), so
//! `K = I`: a normalised DLT and [`pose_from_projection`] for a view whose points span 3D, a
//! homography in the plane's own frame and [`pose_from_homography`] for a planar view. The pose is
//! then refined by Levenberg–Marquardt on the pixel residuals with the analytic point Jacobian of
//! [`Camera::project_cam_with_jacobians`] chained onto a left-multiplied rotation increment.

use nalgebra::{Matrix3, Matrix6, Rotation3, Vector2, Vector3, Vector6};

use super::linear::{
    COPLANAR_TOLERANCE, dlt, homography, plane_frame, pose_from_homography, pose_from_projection,
    relative_thickness,
};
use super::{CalibError, View};
use crate::camera::{Camera, Pose};

/// A view's pose in a fixed camera and how well it fits.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseFit {
    pub cam_from_rig: Pose,
    /// RMS of the residual components `√(Σr²/2n)` (px), as [`super::Calibration::rms_px`].
    pub rms_px: f64,
    /// Largest residual norm (px).
    pub max_px: f64,
    /// Residual vector (observed − projected) of each point, px.
    pub residuals: Vec<Vector2<f64>>,
    pub iterations: usize,
}

/// Fewest points a pose is solved from.
pub const MIN_POINTS: usize = 4;

/// Rays farther than this from the optical axis are left out of the linear initial pose (they are in
/// the refinement).
const MAX_INIT_ANGLE_DEG: f64 = 80.0;

/// Solve `cam_from_rig` of `view` with `camera` fixed.
pub fn solve_pose(camera: &Camera, view: &View) -> Result<PoseFit, CalibError> {
    super::validate_views(std::slice::from_ref(view))?;
    let n = view.points.len();
    if n < MIN_POINTS {
        return Err(CalibError::TooFewPoints {
            got: n,
            need: MIN_POINTS,
        }
        .in_view(&view.name));
    }
    let rays: Vec<Vector3<f64>> = view
        .points
        .iter()
        .map(|c| {
            camera.unproject(c.uv.x, c.uv.y).map_err(|e| {
                CalibError::Degenerate {
                    reason: format!("cannot undistort an image point: {e}"),
                }
                .in_view(&view.name)
            })
        })
        .collect::<Result<_, _>>()?;
    // A fisheye sees rays at and beyond 90°, which have no place on the normalised plane the linear
    // initialisation works in: it uses the rays within 80° of the axis when enough are.
    let central = |r: &Vector3<f64>| r.z > MAX_INIT_ANGLE_DEG.to_radians().cos();
    let use_all = rays.iter().filter(|r| central(r)).count() < MIN_POINTS;
    let (xyz, rays): (Vec<Vector3<f64>>, Vec<Vector2<f64>>) = view
        .points
        .iter()
        .zip(&rays)
        .filter(|(_, r)| use_all || central(r))
        .map(|(c, r)| (c.xyz, Vector2::new(r.x / r.z, r.y / r.z)))
        .unzip();
    let init = initial_pose(&xyz, &rays).map_err(|e| e.in_view(&view.name))?;
    refine(camera, view, init).map_err(|e| e.in_view(&view.name))
}

fn initial_pose(xyz: &[Vector3<f64>], rays: &[Vector2<f64>]) -> Result<Pose, CalibError> {
    let eye = Matrix3::identity();
    if xyz.len() >= 6 && relative_thickness(xyz) >= COPLANAR_TOLERANCE.sqrt() {
        let p = dlt(xyz, rays)?;
        let pose = pose_from_projection(&p, &eye)?;
        // The DLT's sign makes det(P[:, :3]) > 0; the points must also lie in front of the camera.
        let in_front = xyz.iter().filter(|x| pose.transform(x).z > 0.0).count();
        if 2 * in_front >= xyz.len() {
            return Ok(pose);
        }
    }
    // Planar (or nearly): a homography in the plane's own frame.
    let plane_from_rig = plane_frame(xyz);
    let plane: Vec<Vector2<f64>> = xyz
        .iter()
        .map(|x| {
            let p = plane_from_rig.transform(x);
            Vector2::new(p.x, p.y)
        })
        .collect();
    let h = homography(&plane, rays)?;
    let cam_from_plane = pose_from_homography(&h, &eye)?;
    Ok(cam_from_plane.compose(&plane_from_rig))
}

fn residuals(camera: &Camera, view: &View, pose: &Pose) -> Option<Vec<Vector2<f64>>> {
    view.points
        .iter()
        .map(|c| camera.project(pose, &c.xyz).ok().map(|p| c.uv - p))
        .collect()
}

fn cost(r: &[Vector2<f64>]) -> f64 {
    r.iter().map(|v| v.norm_squared()).sum()
}

fn refine(camera: &Camera, view: &View, init: Pose) -> Result<PoseFit, CalibError> {
    const MAX_ITERATIONS: usize = 100;
    let mut pose = init;
    let mut r = residuals(camera, view, &pose).ok_or_else(|| CalibError::Degenerate {
        reason: "initial pose puts points behind the camera".into(),
    })?;
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    while iterations < MAX_ITERATIONS {
        iterations += 1;
        // Normal equations in (δω, δt): X_cam = exp(δω)·(R X) + t + δt.
        let mut jtj = Matrix6::<f64>::zeros();
        let mut jtr = Vector6::<f64>::zeros();
        for (pt, ri) in view.points.iter().zip(&r) {
            let xc = pose.transform(&pt.xyz);
            let rx = pose.rotation * pt.xyz;
            let Ok((_, _, dp)) = camera.project_cam_with_jacobians(&xc) else {
                continue;
            };
            // ∂X_cam/∂δω = −[R X]×, ∂X_cam/∂δt = I.
            let skew = Matrix3::new(0.0, -rx.z, rx.y, rx.z, 0.0, -rx.x, -rx.y, rx.x, 0.0);
            let d_omega = dp * (-skew);
            let mut j = nalgebra::Matrix2x6::<f64>::zeros();
            j.fixed_view_mut::<2, 3>(0, 0).copy_from(&d_omega);
            j.fixed_view_mut::<2, 3>(0, 3).copy_from(&dp);
            jtj += j.transpose() * j;
            jtr += j.transpose() * ri;
        }
        let mut improved = false;
        while lambda < 1e12 {
            let mut a = jtj;
            for i in 0..6 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|ch| ch.solve(&jtr)) else {
                lambda *= 10.0;
                continue;
            };
            let omega = Vector3::new(step[0], step[1], step[2]);
            let candidate = Pose {
                rotation: Rotation3::new(omega) * pose.rotation,
                translation: pose.translation + Vector3::new(step[3], step[4], step[5]),
            };
            if let Some(rn) = residuals(camera, view, &candidate) {
                let cn = cost(&rn);
                if cn <= c {
                    let small = c - cn <= 1e-12 * c.max(1e-300) || step.norm() < 1e-12;
                    pose = candidate;
                    r = rn;
                    c = cn;
                    lambda = (lambda / 10.0).max(1e-12);
                    improved = !small;
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let n = r.len() as f64;
    Ok(PoseFit {
        cam_from_rig: pose,
        rms_px: (c / (2.0 * n)).sqrt(),
        max_px: r.iter().map(|v| v.norm()).fold(0.0, f64::max),
        residuals: r,
        iterations,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::calib::Correspondence;
    use crate::camera::DistortionModel;

    fn camera() -> Camera {
        Camera::pinhole([1280, 960], 1100.0, 1098.0, 642.0, 477.0).with_distortion(
            DistortionModel::Brown5,
            &[-0.25, 0.1, 0.001, -0.0005, -0.02],
        )
    }

    fn view(points: &[Vector3<f64>], pose: &Pose, cam: &Camera) -> View {
        View {
            name: "v".into(),
            points: points
                .iter()
                .map(|x| Correspondence {
                    xyz: *x,
                    uv: cam.project(pose, x).unwrap(),
                    cov: None,
                })
                .collect(),
        }
    }

    fn truth() -> Pose {
        Pose::from_axis_angle(
            Vector3::new(0.3, -0.5, 0.1),
            Vector3::new(-40.0, 25.0, 600.0),
        )
    }

    fn check(points: &[Vector3<f64>]) {
        let cam = camera();
        let fit = solve_pose(&cam, &view(points, &truth(), &cam)).unwrap();
        let dr = (fit.cam_from_rig.rotation.matrix() - truth().rotation.matrix()).norm();
        let dt = (fit.cam_from_rig.translation - truth().translation).norm();
        assert!(dr < 1e-9 && dt < 1e-7, "dr {dr} dt {dt}");
        assert!(fit.rms_px < 1e-8, "{}", fit.rms_px);
    }

    #[test]
    fn recovers_the_pose_of_a_3d_view() {
        let mut pts = Vec::new();
        for i in 0..5 {
            for j in 0..4 {
                pts.push(Vector3::new(i as f64 * 30.0, j as f64 * 30.0, 0.0));
                pts.push(Vector3::new(
                    0.0,
                    j as f64 * 30.0 + 10.0,
                    i as f64 * 30.0 + 15.0,
                ));
            }
        }
        check(&pts);
    }

    #[test]
    fn recovers_the_pose_of_a_planar_view() {
        let mut pts = Vec::new();
        for i in 0..6 {
            for j in 0..5 {
                pts.push(Vector3::new(i as f64 * 25.0, j as f64 * 25.0, 0.0));
            }
        }
        check(&pts);
    }

    #[test]
    fn residuals_grow_when_the_camera_is_wrong() {
        let cam = camera();
        let mut pts = Vec::new();
        for i in 0..6 {
            for j in 0..5 {
                pts.push(Vector3::new(i as f64 * 25.0, j as f64 * 25.0, 0.0));
                pts.push(Vector3::new(0.0, i as f64 * 25.0, j as f64 * 25.0 + 10.0));
            }
        }
        let v = view(&pts, &truth(), &cam);
        let mut wrong = cam.clone();
        wrong.params[crate::camera::idx::K1] = -0.35;
        let fit = solve_pose(&wrong, &v).unwrap();
        assert!(fit.rms_px > 0.05, "{}", fit.rms_px);
    }
}
