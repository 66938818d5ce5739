//! The synthetic renderer: accuracy of rendered corners against the ground truth (saddle-point fit),
//! visibility and occlusion in the ground truth, camera effects, the `SyntheticSource` frame source
//! and the `cubecal render` command.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/normal.rs"]
mod normal;

use std::path::Path;
use std::time::Duration;

use cubecal::camera::{Camera, DistortionModel, Pose};
use cubecal::capture::CaptureError;
use cubecal::capture::FrameSource;
use cubecal::capture::synthetic::SyntheticSource;
use cubecal::render::{
    GroundTruth, LinearImage, RenderSettings, default_view, gaussian_blur, ground_truth,
    random_poses, render, render_radiance, turntable_poses,
};
use cubecal::rig::Rig;
use nalgebra::{Matrix6, Vector2, Vector3, Vector6};
use normal::normal_cdf;

fn fixture_rig(name: &str) -> Rig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/rigs")
        .join(name);
    Rig::load(&path)
        .unwrap_or_else(|e| panic!("fixture {} must load: {e}", path.display()))
        .0
}

/// A small camera with clearly non-trivial distortion (so that the test exercises `unproject`).
fn small_camera() -> Camera {
    Camera::pinhole([360, 270], 330.0, 328.0, 181.3, 133.6).with_distortion(
        DistortionModel::Brown5,
        &[-0.12, 0.03, 0.0008, -0.0005, 0.0],
    )
}

/// Saddle point of the intensity near `start`: an iteratively re-centred, Gaussian-weighted
/// (σ = `sigma_w` px) least-squares fit of `f = a0 + a1 x + a2 y + a3 x² + a4 xy + a5 y²` in
/// coordinates relative to the current centre; the centre moves to the quadratic's stationary point
/// until the step is below 1e-9 px. With a Gaussian weight centred on the estimate, the discrete sums
/// approximate the continuous moments closely, and an ideal (straight-edged) corner image is
/// point-symmetric about the corner, so the fit has no systematic offset at convergence.
fn saddle_point(img: &LinearImage, start: Vector2<f64>, sigma_w: f64) -> Option<Vector2<f64>> {
    let radius = (4.0 * sigma_w).ceil() as i64;
    let mut c = start;
    for _ in 0..50 {
        let (ci, cj) = (c.y.round() as i64, c.x.round() as i64);
        let mut ata = Matrix6::<f64>::zeros();
        let mut atb = Vector6::<f64>::zeros();
        for i in ci - radius..=ci + radius {
            for j in cj - radius..=cj + radius {
                if i < 0 || j < 0 || i >= i64::from(img.height) || j >= i64::from(img.width) {
                    return None;
                }
                let (x, y) = (j as f64 - c.x, i as f64 - c.y);
                let w = (-(x * x + y * y) / (2.0 * sigma_w * sigma_w)).exp();
                let row = Vector6::new(1.0, x, y, x * x, x * y, y * y);
                ata += row * row.transpose() * w;
                atb += row * (w * img.get(i as usize, j as usize));
            }
        }
        let a = ata.lu().solve(&atb)?;
        let h = nalgebra::Matrix2::new(2.0 * a[3], a[4], a[4], 2.0 * a[5]);
        if h.determinant() >= 0.0 {
            return None; // not a saddle
        }
        let step = -(h.try_inverse()? * Vector2::new(a[1], a[2]));
        if step.norm() > 3.0 {
            return None;
        }
        c += step;
        if step.norm() < 1e-9 {
            return Some(c);
        }
    }
    None
}

/// Visible corners whose neighbouring corners are at least `min_px` away in the image, so that the
/// fit window sees a single X-junction.
fn isolated_visible(gt: &GroundTruth, min_px: f64, border: f64) -> Vec<(usize, Vector2<f64>)> {
    let [w, h] = gt.camera.image_size;
    let uv = |c: &cubecal::render::CornerTruth| c.uv.map(|[u, v]| Vector2::new(u, v));
    gt.corners
        .iter()
        .enumerate()
        .filter(|(_, c)| c.visible)
        .filter_map(|(k, c)| {
            let p = uv(c)?;
            if p.x < border
                || p.y < border
                || p.x > f64::from(w) - border
                || p.y > f64::from(h) - border
            {
                return None;
            }
            let nearest = gt
                .corners
                .iter()
                .filter(|o| o.face_index == c.face_index && (o.row != c.row || o.col != c.col))
                .filter_map(&uv)
                .map(|q| (q - p).norm())
                .fold(f64::INFINITY, f64::min);
            (nearest >= min_px).then_some((k, p))
        })
        .collect()
}

/// The same camera with `k`× the resolution: low-resolution pixel `(u, v)` is high-resolution
/// `(k·u + (k−1)/2, k·v + (k−1)/2)`, so high-resolution pixels `k·j .. k·j+k−1` tile pixel `j`.
fn scaled(camera: &Camera, k: u32) -> Camera {
    let mut c = camera.clone();
    let kf = f64::from(k);
    c.image_size = [camera.image_size[0] * k, camera.image_size[1] * k];
    for p in [0, 1, 4] {
        c.params[p] *= kf; // fx, fy, skew
    }
    c.params[2] = camera.cx() * kf + (kf - 1.0) / 2.0;
    c.params[3] = camera.cy() * kf + (kf - 1.0) / 2.0;
    c
}

/// A band-limited image of the rig: rendered exactly at 5× resolution (box-filtered, 8×8 samples per
/// high-resolution edge pixel, i.e. 1600 per output pixel), blurred by a Gaussian of σ = `blur_px`
/// output pixels, then sampled at the output pixel centres. Sampling a box-filtered (not band-limited)
/// image directly makes any sub-pixel corner estimator "pixel-lock" by a few hundredths of a pixel
/// (measured here: 0.02–0.04 px for blur 0.7–1.5 px applied after sampling, independent of the
/// supersampling rate, so a property of the estimator, not of the renderer); blurring before
/// sampling removes that aliasing.
fn band_limited(rig: &Rig, camera: &Camera, pose: &Pose, blur_px: f64) -> LinearImage {
    const K: u32 = 5;
    let hi_cam = scaled(camera, K);
    let settings = RenderSettings {
        supersample: 8,
        ..RenderSettings::default()
    };
    let hi = gaussian_blur(
        &render_radiance(rig, &hi_cam, pose, &settings).unwrap(),
        blur_px * f64::from(K),
    );
    let [w, h] = camera.image_size;
    let mut data = Vec::with_capacity((w * h) as usize);
    for i in 0..h as usize {
        for j in 0..w as usize {
            data.push(hi.get(K as usize * i + 2, K as usize * j + 2));
        }
    }
    LinearImage {
        width: w,
        height: h,
        data,
    }
}

/// Max and RMS distance between saddle fits on a clean, sharp, heavily supersampled render and the
/// ground truth.
fn corner_errors(rig: &Rig, camera: &Camera, pose: &Pose) -> (f64, f64, usize) {
    let smooth = band_limited(rig, camera, pose, 1.0);
    let gt = ground_truth(rig, camera, pose, &RenderSettings::default(), 0);
    let corners = isolated_visible(&gt, 12.0, 12.0);
    assert!(corners.len() >= 20, "only {} usable corners", corners.len());
    let mut max: f64 = 0.0;
    let mut sum2 = 0.0;
    for (k, truth) in &corners {
        let start = truth + Vector2::new(0.3, -0.2);
        let est = saddle_point(&smooth, start, 1.5)
            .unwrap_or_else(|| panic!("no saddle at corner {:?}", gt.corners[*k]));
        let e = (est - truth).norm();
        max = max.max(e);
        sum2 += e * e;
    }
    (max, (sum2 / corners.len() as f64).sqrt(), corners.len())
}

/// The renderer's accuracy: saddle fits on band-limited renders land on the ground truth.
/// Measured (renderer version 2): flat board 54 corners, max 0.0009 px, RMS 0.0005 px; cube (2× crop)
/// 117 corners, max 0.0045 px, RMS 0.0009 px. The residual is mostly the sampling of the 5× render:
/// at 4×4 the cube's max is 0.0050 px (its horizontal edges are located to 1/8 of a 5× pixel).
#[test]
fn rendered_corners_match_ground_truth_within_5_millipixels() {
    let camera = small_camera();
    let flat = fixture_rig("opencv_board_9x6.toml");
    let cube = fixture_rig("cube_outside.toml");
    let flat_pose = random_poses(&flat, &camera, 1, 3)[0];
    let cube_pose = turntable_poses(&cube, &camera, 3, 30.0)[1];
    // The cube seen through a longer lens from the same place: a 2× crop around its near vertex, so
    // that its foreshortened squares are large enough for isolated fit windows.
    let mut zoom = camera.clone();
    zoom.params[0] *= 2.1;
    zoom.params[1] *= 2.1;
    let mut report = Vec::new();
    for (name, rig, cam, pose) in [
        ("flat", &flat, &camera, flat_pose),
        ("cube", &cube, &zoom, cube_pose),
    ] {
        let (max, rms, n) = corner_errors(rig, cam, &pose);
        eprintln!("{name}: {n} corners, saddle-fit error max {max:.5} px, rms {rms:.5} px");
        report.push((name, max));
    }
    for (name, max) in report {
        assert!(max < 0.005, "{name}: max corner error {max} px");
    }
}

#[test]
fn ground_truth_projects_with_the_camera_and_round_trips_through_json() {
    let camera = small_camera();
    let rig = fixture_rig("cube_outside.toml");
    let pose = default_view(&rig, &camera);
    let gt = ground_truth(&rig, &camera, &pose, &RenderSettings::default(), 4);
    assert_eq!(gt.corners.len(), rig.n_corners());
    assert_eq!(
        gt.visible().count(),
        rig.n_corners(),
        "the default cube view shows every corner"
    );
    for c in &gt.corners {
        let p = Vector3::from(c.xyz);
        assert_eq!(p, rig.corner_xyz(c.face_index, c.row, c.col).unwrap());
        let uv = camera.project(&pose, &p).unwrap();
        assert_eq!(c.uv, Some([uv.x, uv.y]));
    }
    let text = serde_json::to_string(&gt).unwrap();
    let back: GroundTruth = serde_json::from_str(&text).unwrap();
    assert_eq!(back.corners.len(), gt.corners.len());
    for (a, b) in back.corners.iter().zip(&gt.corners) {
        let (ua, ub) = (a.uv.unwrap(), b.uv.unwrap());
        assert!((ua[0] - ub[0]).abs() < 1e-9 && (ua[1] - ub[1]).abs() < 1e-9);
        assert_eq!(
            (a.visible, a.row, a.col, &a.face),
            (b.visible, b.row, b.col, &b.face)
        );
    }
    assert_eq!(back.camera.to_camera(), camera);
    let p2 = back.cam_from_rig.to_pose();
    assert!((p2.rotation.matrix() - pose.rotation.matrix()).norm() < 1e-12);
    assert!((p2.translation - pose.translation).norm() < 1e-9);
    assert_eq!(back.camera.camera_matrix[0][2], camera.cx());
    assert_eq!(back.camera.distortion_coefficients.len(), 5);
}

#[test]
fn faces_turned_away_are_not_visible() {
    let camera = small_camera();
    let rig = fixture_rig("cube_outside.toml");
    // Full turn in 8 steps: some side faces necessarily face away.
    let poses = turntable_poses(&rig, &camera, 8, 360.0);
    let mut hidden_faces = 0;
    for pose in &poses {
        let gt = ground_truth(&rig, &camera, pose, &RenderSettings::default(), 0);
        for c in &gt.corners {
            assert_eq!(
                c.visible,
                c.in_front && c.front_facing && c.in_image && !c.occluded
            );
            if !c.front_facing {
                assert!(!c.visible);
                hidden_faces += 1;
            }
        }
    }
    assert!(hidden_faces > 0);
    // The default turntable keeps all three faces in view in most frames.
    let poses = turntable_poses(&rig, &camera, 8, 60.0);
    let all_three = poses
        .iter()
        .filter(|p| {
            let gt = ground_truth(&rig, &camera, p, &RenderSettings::default(), 0);
            (0..3).all(|f| gt.visible().any(|c| c.face_index == f))
        })
        .count();
    assert!(
        all_three >= 6,
        "{all_three} of 8 frames show all three faces"
    );
}

/// Two parallel boards: a small one 100 mm in front of a big one hides part of it.
const OCCLUSION_RIG: &str = r#"
name = "occlusion"
units = "mm"
[[faces]]
name = "back"
cols = 9
rows = 6
square_mm = 20.0
origin = [0, 0, 0]
col_dir = [1, 0, 0]
row_dir = [0, 1, 0]
[[faces]]
name = "front"
cols = 3
rows = 2
square_mm = 20.0
margin_mm = 5.0
origin = [60, 40, 100]
col_dir = [1, 0, 0]
row_dir = [0, 1, 0]
"#;

#[test]
fn nearer_faces_occlude_corners_and_pixels() {
    let (rig, _) = Rig::from_toml_str(OCCLUSION_RIG, "occlusion.toml").unwrap();
    let camera = Camera::pinhole([320, 240], 300.0, 300.0, 159.5, 119.5);
    // Looking straight down −z at the back board from 600 mm.
    let eye = Vector3::new(80.0, 50.0, 600.0);
    let pose = cubecal::render::correspondences::look_at(
        &eye,
        &Vector3::new(80.0, 50.0, 0.0),
        &Vector3::new(0.0, -1.0, 0.0),
    );
    let gt = ground_truth(&rig, &camera, &pose, &RenderSettings::default(), 0);
    let occluded: Vec<_> = gt.corners.iter().filter(|c| c.occluded).collect();
    assert!(!occluded.is_empty());
    assert!(occluded.iter().all(|c| c.face == "back" && !c.visible));
    assert!(
        gt.corners
            .iter()
            .filter(|c| c.face == "front")
            .all(|c| c.visible)
    );
    // Back corner (row 2, col 4) at (80, 40, 0) lies behind the front board's square area.
    let hidden = gt
        .corners
        .iter()
        .find(|c| c.face == "back" && c.row == 2 && c.col == 4)
        .unwrap();
    assert!(hidden.occluded);
    // Pixels: around the hidden corner the image is exactly that of the front board alone.
    let settings = RenderSettings::default();
    let both = render_radiance(&rig, &camera, &pose, &settings).unwrap();
    let front_only_toml = OCCLUSION_RIG
        .replacen("name = \"back\"", "name = \"back\"\nmargin_mm = 0.0", 1)
        .replacen("origin = [0, 0, 0]", "origin = [0, 0, -100000]", 1);
    let (front_only, _) = Rig::from_toml_str(&front_only_toml, "front-only.toml").unwrap();
    let alone = render_radiance(&front_only, &camera, &pose, &settings).unwrap();
    let [u, v] = hidden.uv.unwrap();
    let (i, j) = (v.round() as usize, u.round() as usize);
    for r in i - 3..=i + 3 {
        for c in j - 3..=j + 3 {
            let (a, b) = (both.get(r, c), alone.get(r, c));
            assert!((a - b).abs() < 1e-12, "pixel ({r}, {c}): {a} vs {b}");
        }
    }
    // Elsewhere the back board shows: the image differs somewhere.
    assert_ne!(both, alone);
}

#[test]
fn pixels_beyond_the_distortion_fold_are_background() {
    let rig = fixture_rig("opencv_board_9x6.toml");
    // Strong barrel distortion: the image corners lie beyond the fold.
    let camera = Camera::pinhole([200, 150], 80.0, 80.0, 99.5, 74.5)
        .with_distortion(DistortionModel::Brown5, &[-0.6, 0.0, 0.0, 0.0, 0.0]);
    assert!(camera.unproject(0.0, 0.0).is_err());
    let pose = default_view(&rig, &camera);
    let settings = RenderSettings::default();
    let img = render_radiance(&rig, &camera, &pose, &settings).unwrap();
    assert!((img.get(0, 0) - settings.palette.background).abs() < 1e-12);
}

#[test]
fn camera_effects_are_seeded_and_change_the_image() {
    let rig = fixture_rig("opencv_board_9x6.toml");
    let camera = Camera::pinhole([160, 120], 150.0, 150.0, 79.5, 59.5);
    let pose = default_view(&rig, &camera);
    let clean = RenderSettings::default();
    let noisy = RenderSettings {
        noise_sigma: 3.0,
        blur_sigma_px: 0.8,
        gamma: 2.2,
        vignetting: 0.4,
        seed: 11,
        ..clean
    };
    let a = render(&rig, &camera, &pose, &noisy, 0).unwrap();
    let b = render(&rig, &camera, &pose, &noisy, 0).unwrap();
    assert_eq!(a, b, "same seed and frame, same image");
    let c = render(&rig, &camera, &pose, &noisy, 1).unwrap();
    assert_ne!(a, c, "another frame draws other noise");
    let d = render(
        &rig,
        &camera,
        &pose,
        &RenderSettings { seed: 12, ..noisy },
        0,
    )
    .unwrap();
    assert_ne!(a, d, "another seed draws other noise");
    let e = render(&rig, &camera, &pose, &clean, 0).unwrap();
    assert_ne!(a, e);
    // Vignetting darkens the corners of the background relative to a render without it.
    let no_vig = render(
        &rig,
        &camera,
        &pose,
        &RenderSettings {
            vignetting: 0.0,
            noise_sigma: 0.0,
            ..noisy
        },
        0,
    )
    .unwrap();
    let vig = render(
        &rig,
        &camera,
        &pose,
        &RenderSettings {
            noise_sigma: 0.0,
            ..noisy
        },
        0,
    )
    .unwrap();
    assert!(vig.get_pixel(0, 0).0[0] < no_vig.get_pixel(0, 0).0[0]);
    // Bad settings are rejected with the setting's name.
    let err = render(
        &rig,
        &camera,
        &pose,
        &RenderSettings {
            gamma: 0.0,
            ..clean
        },
        0,
    )
    .unwrap_err();
    assert!(err.to_string().contains("gamma"), "{err}");
}

#[test]
fn adaptive_supersampling_matches_full_supersampling() {
    // Uniform pixels are taken from corner samples; check against a brute-force box filter on a crop.
    let rig = fixture_rig("cube_outside.toml");
    let camera = Camera::pinhole([120, 90], 90.0, 90.0, 59.5, 44.5)
        .with_distortion(DistortionModel::Brown5, &[-0.1, 0.0, 0.0, 0.0, 0.0]);
    let pose = default_view(&rig, &camera);
    let settings = RenderSettings {
        supersample: 6,
        ..RenderSettings::default()
    };
    let adaptive = render_radiance(&rig, &camera, &pose, &settings).unwrap();
    // Brute force: render at 6× resolution with 1 sample per pixel, then box-average 6×6 blocks.
    // The supersampling grid's sub-row `a` is shifted by (a − 2.5)/36 px in x (render's
    // `sub_sample`), i.e. (a − 2.5)/6 px of the 6× image: row `a` of each block is taken from a
    // render whose principal point is moved by that much (distortion acts in normalised
    // coordinates, so the whole image shifts alike).
    let n = 6.0;
    let hi: Vec<_> = (0..6)
        .map(|a| {
            let mut big = camera.clone();
            big.image_size = [120 * 6, 90 * 6];
            big.params[0] *= n;
            big.params[1] *= n;
            big.params[2] = (camera.cx() + 0.5) * n - 0.5 - (a as f64 - 2.5) / n;
            big.params[3] = (camera.cy() + 0.5) * n - 0.5;
            render_radiance(
                &rig,
                &big,
                &pose,
                &RenderSettings {
                    supersample: 1,
                    ..settings
                },
            )
            .unwrap()
        })
        .collect();
    let mut worst: f64 = 0.0;
    for i in 0..90 {
        for j in 0..120 {
            let mut s = 0.0;
            for a in 0..6 {
                for b in 0..6 {
                    s += hi[a].get(i * 6 + a, j * 6 + b);
                }
            }
            worst = worst.max((s / 36.0 - adaptive.get(i, j)).abs());
        }
    }
    assert!(
        worst < 1e-9,
        "adaptive and full supersampling differ by {worst}"
    );
}

#[test]
fn synthetic_source_renders_each_pose_once_with_sequence_and_time() {
    let rig = fixture_rig("inside_corner.toml");
    let camera = Camera::pinhole([96, 72], 80.0, 80.0, 47.5, 35.5);
    let poses = turntable_poses(&rig, &camera, 3, 30.0);
    let mut src = SyntheticSource::new(
        rig.clone(),
        camera.clone(),
        poses.clone(),
        RenderSettings::default(),
    )
    .unwrap()
    .with_frame_interval(Duration::from_millis(40));
    let info = src.describe();
    assert_eq!((info.width, info.height), (96, 72));
    assert_eq!(info.identity, "synthetic:inside-corner");
    assert_eq!(src.len(), 3);
    for k in 0..3u64 {
        assert_eq!(src.flush().unwrap(), 0);
        let f = src.grab(Duration::from_millis(10)).unwrap();
        assert_eq!(f.sequence, k);
        assert_eq!(f.timestamp, Duration::from_millis(40 * k));
        assert_eq!(
            f.image,
            render(
                &rig,
                &camera,
                &poses[k as usize],
                &RenderSettings::default(),
                k
            )
            .unwrap()
        );
        assert_eq!(src.ground_truth(k).unwrap().frame, k);
    }
    assert!(matches!(
        src.grab(Duration::from_millis(10)),
        Err(CaptureError::EndOfStream { .. })
    ));
    let bad = Camera::pinhole([96, 72], -1.0, 80.0, 47.5, 35.5);
    assert!(SyntheticSource::new(rig, bad, poses, RenderSettings::default()).is_err());
}

#[test]
fn cli_render_writes_frames_and_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/rigs/cube_outside.toml");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["--json", "render"])
        .arg(&rig)
        .arg("--out")
        .arg(dir.path())
        .args([
            "--poses",
            "turntable:2",
            "--width",
            "160",
            "--height",
            "120",
            "--fx",
            "125",
            "--fy",
            "125",
        ])
        .args(["--k1", "-0.05", "--noise", "1.5", "--seed", "3"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["frames"].as_array().unwrap().len(), 2);
    for k in 0..2 {
        let img = image::open(dir.path().join(format!("frame_{k:03}.png")))
            .unwrap()
            .to_luma8();
        assert_eq!(img.dimensions(), (160, 120));
        let gt: GroundTruth = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join(format!("frame_{k:03}.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(gt.frame, k);
        assert_eq!(gt.camera.image_size, [160, 120]);
        assert_eq!(
            gt.camera.distortion_coefficients,
            vec![-0.05, 0.0, 0.0, 0.0, 0.0]
        );
        assert!(gt.visible().count() > 100);
    }
    // A bad pose spec is a usage error.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .arg("render")
        .arg(&rig)
        .arg("--out")
        .arg(dir.path())
        .args(["--poses", "spiral:3"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(i32::from(cubecal::exit::USAGE)));
    // So are out-of-range camera and effect settings.
    for bad in [
        ["--gamma", "0"],
        ["--vignetting", "1.5"],
        ["--fx=-3", "--seed=1"],
        ["--supersample", "0"],
        ["--noise", "nan"],
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
            .arg("render")
            .arg(&rig)
            .arg("--out")
            .arg(dir.path())
            .args(bad)
            .output()
            .unwrap();
        assert_eq!(
            out.status.code(),
            Some(i32::from(cubecal::exit::USAGE)),
            "{bad:?}"
        );
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(bad[0].split('=').next().unwrap()),
            "{bad:?}"
        );
    }
}

/// The committed renders in `fixtures/render/` are what the commands in `fixtures/README.md` produce.
#[test]
fn shipped_renders_are_reproduced() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let cases: [(&str, &str, &[&str]); 2] = [
        (
            "cube_outside",
            "fixtures/rigs/cube_outside.toml",
            &["--poses", "turntable:1"],
        ),
        (
            "opencv_board_9x6",
            "fixtures/rigs/opencv_board_9x6.toml",
            &[
                "--poses",
                "random:1",
                "--seed",
                "5",
                "--blur",
                "0.8",
                "--gamma",
                "1.8",
                "--vignetting",
                "0.35",
                "--k1",
                "-0.25",
                "--k2",
                "0.08",
            ],
        ),
    ];
    for (name, rig, args) in cases {
        let dir = tempfile::tempdir().unwrap();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
            .current_dir(root)
            .args(["render", rig, "--out"])
            .arg(dir.path())
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let shipped = root.join("fixtures/render").join(name);
        let a = image::open(shipped.join("frame_000.png"))
            .expect("fixture image")
            .to_luma8();
        let b = image::open(dir.path().join("frame_000.png"))
            .unwrap()
            .to_luma8();
        assert_eq!(a.dimensions(), b.dimensions());
        let worst = a
            .pixels()
            .zip(b.pixels())
            .map(|(p, q)| p.0[0].abs_diff(q.0[0]))
            .max()
            .unwrap();
        assert!(
            worst <= 1,
            "{name}: pixels differ by up to {worst} grey levels"
        );
        let read = |p: &Path| -> GroundTruth {
            serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
        };
        let (ga, gb) = (
            read(&shipped.join("frame_000.json")),
            read(&dir.path().join("frame_000.json")),
        );
        assert_eq!(ga.camera, gb.camera);
        assert_eq!(ga.corners.len(), gb.corners.len());
        for (x, y) in ga.corners.iter().zip(&gb.corners) {
            assert_eq!((x.visible, x.row, x.col), (y.visible, y.row, y.col));
            let (u, v) = (x.uv.unwrap(), y.uv.unwrap());
            assert!(
                (u[0] - v[0]).abs() < 1e-9 && (u[1] - v[1]).abs() < 1e-9,
                "{name}: {x:?} vs {y:?}"
            );
        }
    }
}

/// The lens blurs the scene before the pixels integrate it: across a straight edge at `x = e`
/// between levels `a` and `b`, pixel `j` is `a + (b − a)·∫ over [j−½, j+½] of Φ((x − e)/σ) dx`
/// (box ⊛ Gaussian), whatever the edge's phase within the pixel. Edges along a pixel axis are the
/// worst case of sampling (no row averages the samples' positions): a vertical edge is resolved to
/// `1/2n²` px by the shifted sub-sample rows, a horizontal one to `1/2n` (the rows' heights), as
/// measured here. Blurring the finished pixels instead (the renderer before version 2) gives a
/// profile that depends on the phase; the test measures that too, so that it fails if the order
/// comes back.
#[test]
fn the_blur_acts_before_the_pixels_integrate_an_edge() {
    let rig = fixture_rig("opencv_board_9x6.toml");
    let sigma = 1.0;
    let settings = RenderSettings {
        supersample: 16,
        blur_sigma_px: sigma,
        ..RenderSettings::default()
    };
    let sharp = RenderSettings {
        blur_sigma_px: 0.0,
        ..settings
    };
    // ∫Φ(t)dt = tΦ(t) + φ(t).
    let big_phi =
        |t: f64| t * normal_cdf(t) + (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
    let (mut worst_new, mut worst_old) = ([0.0_f64; 2], 0.0_f64);
    for vertical in [true, false] {
        for phase in [0.0, 0.17, 0.25, 0.5, 0.71] {
            let (dx, dy) = if vertical { (phase, 0.0) } else { (0.0, phase) };
            let camera = Camera::pinhole([240, 180], 260.0, 260.0, 119.5 + dx, 89.5 + dy);
            let pose = default_view(&rig, &camera);
            // A square edge between two corners of one lattice column (vertical) or row.
            let p = |r, c| {
                camera
                    .project(&pose, &rig.corner_xyz(0, r, c).unwrap())
                    .unwrap()
            };
            let (p0, p1) = if vertical {
                (p(2, 4), p(3, 4))
            } else {
                (p(2, 4), p(2, 5))
            };
            let (along, across) = if vertical { (1, 0) } else { (0, 1) };
            assert!(
                (p0[across] - p1[across]).abs() < 1e-6,
                "a frontal view images the line along a pixel axis: {p0:?} {p1:?}"
            );
            let e = p0[across];
            let line = ((p0[along] + p1[along]) / 2.0).round() as usize;
            let img = render_radiance(&rig, &camera, &pose, &settings).unwrap();
            let old = gaussian_blur(
                &render_radiance(&rig, &camera, &pose, &sharp).unwrap(),
                sigma,
            );
            let at = |im: &LinearImage, k: usize| {
                if vertical {
                    im.get(line, k)
                } else {
                    im.get(k, line)
                }
            };
            let k0 = e.round() as usize;
            // The two squares' levels, read far from the edge (the squares are 14 px wide here).
            let (a, b) = (at(&img, k0 - 6), at(&img, k0 + 6));
            assert!((b - a).abs() > 0.5, "the edge has contrast: {a} {b}");
            for k in k0 - 4..=k0 + 4 {
                let x = k as f64;
                let f = sigma * (big_phi((x + 0.5 - e) / sigma) - big_phi((x - 0.5 - e) / sigma));
                let expected = a + (b - a) * f;
                let slot = usize::from(!vertical);
                worst_new[slot] =
                    worst_new[slot].max((at(&img, k) - expected).abs() / (b - a).abs());
                if vertical {
                    worst_old = worst_old.max((at(&old, k) - expected).abs() / (b - a).abs());
                }
            }
        }
    }
    eprintln!(
        "largest deviation from box ⊛ Gaussian, of the contrast: vertical edges {:.5}, horizontal \
         {:.5} (vertical, blur after integration: {worst_old:.5})",
        worst_new[0], worst_new[1]
    );
    assert!(worst_new[0] < 1e-3, "{worst_new:?}");
    // A sub-row's height quantises a horizontal edge by up to 1/2n = 1/32 px: at the edge the
    // profile's slope is at most k(0) ≈ 0.38 of the contrast per px.
    assert!(worst_new[1] < 0.38 / 32.0, "{worst_new:?}");
    assert!(
        worst_old > 5.0 * worst_new[0],
        "{worst_old} vs {worst_new:?}"
    );
}
