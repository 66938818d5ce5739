//! The render sets of issue 19's grid cases, with exact ground truth: shared by
//! `examples/detect_cases.rs` (the figures) and `tests/detect_cases.rs` (the assertions).
//!
//! Every set renders realistic frames (blur σ 1 px, noise σ 2, gamma 2.2, vignetting 0.3) over a dark
//! background (reflectance 0.03, the black squares' 0.06), so that a board without margin merges with
//! it:
//! - `nomargin`: a 13×12 board printed without margin (random views, k1 −0.1);
//! - `fill`: a 13×12 board with a 10 mm margin filling the frame, its outer squares 10–20 px from the
//!   nearest image border (k1 −0.1); `fill-k04`: the same with a wide-angle lens (k1 −0.4);
//! - `inside-corner`: a floor and two walls meeting at seams, no margins, the walls of equal 8×6 grid
//!   size, 1600×1200;
//! - `wrapped-cube`: one sheet of squares wrapped around a vertical edge of a box (two faces of 6×10,
//!   30 mm squares; the fold on a line of the sheet's corners), strong barrel distortion (k1 −0.3);
//! - `cut`: the 13×12 board with margin, cut by the frame border (no complete face in the frame);
//! - `cube-cut`: the three-face cube pushed against the frame's borders (k1 −0.3), faces cut;
//! - `paper-edge`: the 13×12 board printed to the paper's edge, on a desk dark on one side of a line
//!   and bright on the other, 640×480, k1 −0.25 (issue 28's classic planar set);
//! - `photo-corner`: a replica of the real inside corner of `bailus_tsai_cube_stereo` (two walls, the
//!   pattern continuous across the fold, one wall running off the frame, k1 −0.3 at a wide angle).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use cubecal::camera::{Camera, DistortionModel, Pose};
use cubecal::render::correspondences::look_at;
use cubecal::render::{
    GroundTruth, Palette, RenderSettings, cached_frame, default_view, random_poses,
};
use cubecal::rig::Rig;
use image::GrayImage;
use nalgebra::{Rotation3, Unit, Vector3};

/// One render set.
#[derive(Debug, Clone)]
pub struct Case {
    pub name: &'static str,
    /// The rig the frames are detected (and scored) with.
    pub rig: Rig,
    /// What is rendered: the rig itself, or a scene whose first faces are the rig's.
    pub scene: Rig,
    pub camera: Camera,
    pub settings: RenderSettings,
    pub poses: Vec<Pose>,
}

pub fn rig(file: &str) -> Rig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/rigs")
        .join(file);
    Rig::load(&path).expect("bundled rig loads").0
}

fn settings(seed: u64) -> RenderSettings {
    RenderSettings {
        blur_sigma_px: 1.0,
        noise_sigma: 2.0,
        gamma: 2.2,
        vignetting: 0.3,
        seed,
        palette: Palette {
            background: std::env::var("BG")
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(0.03),
            ..Palette::default()
        },
        ..RenderSettings::default()
    }
}

fn camera(w: u32, h: u32, f: f64, k1: f64) -> Camera {
    Camera::pinhole(
        [w, h],
        f,
        f,
        f64::from(w) / 2.0 - 0.5,
        f64::from(h) / 2.0 - 0.5,
    )
    .with_distortion(DistortionModel::Brown5, &[k1])
}

/// Smallest distance (px) from the projection of face 0's pattern outline to the image border
/// (negative when part of it is outside).
fn clearance(rig: &Rig, camera: &Camera, pose: &Pose) -> f64 {
    let face = &rig.faces[0];
    let ([a0, a1], [b0, b1]) = face.pattern_extent();
    let [w, h] = camera.image_size;
    let (w, h) = (f64::from(w), f64::from(h));
    let mut m = f64::INFINITY;
    for k in 0..=200 {
        let t = f64::from(k) / 200.0;
        for (a, b) in [
            (a0 + t * (a1 - a0), b0),
            (a0 + t * (a1 - a0), b1),
            (a0, b0 + t * (b1 - b0)),
            (a1, b0 + t * (b1 - b0)),
        ] {
            let p = face.origin + face.col_dir * a + face.row_dir * b;
            match camera.project(pose, &p) {
                Ok(uv) => {
                    m = m.min(
                        (uv.x + 0.5)
                            .min(uv.y + 0.5)
                            .min(w - 0.5 - uv.x)
                            .min(h - 0.5 - uv.y),
                    )
                }
                Err(_) => return f64::NEG_INFINITY,
            }
        }
    }
    m
}

/// A view of a single-board rig from direction `dir` (tilted from the normal) and `roll`, at the
/// distance where the pattern's outline comes `margin_px` from the nearest image border.
fn filling(
    rig: &Rig,
    camera: &Camera,
    tilt_deg: f64,
    tilt_axis: Vector3<f64>,
    roll_deg: f64,
    margin_px: f64,
) -> Pose {
    let face = &rig.faces[0];
    let ([a0, a1], [b0, b1]) = face.pattern_extent();
    let centre = face.origin + face.col_dir * ((a0 + a1) / 2.0) + face.row_dir * ((b0 + b1) / 2.0);
    let dir = Rotation3::from_axis_angle(&Unit::new_normalize(tilt_axis), tilt_deg.to_radians())
        * face.normal();
    let up = Rotation3::from_axis_angle(&Unit::new_normalize(dir), roll_deg.to_radians())
        * (-face.row_dir);
    let pose_at = |d: f64| look_at(&(centre + dir * d), &centre, &up);
    let (mut lo, mut hi) = (50.0, 5000.0);
    for _ in 0..60 {
        let mid = (lo + hi) / 2.0;
        if clearance(rig, camera, &pose_at(mid)) < margin_px {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    pose_at(hi)
}

/// `pose` with the camera turned by `deg` about its own axis `axis` (camera frame).
fn panned(pose: &Pose, axis: Vector3<f64>, deg: f64) -> Pose {
    Pose::from_axis_angle(axis.normalize() * deg.to_radians(), Vector3::zeros()).compose(pose)
}

/// The first `n` of `base` turned by each camera turn (axis in the camera frame, degrees).
fn panned_views(base: &Pose, pans: &[([f64; 3], f64)], n: usize) -> Vec<Pose> {
    pans.iter()
        .take(n)
        .map(|&(a, d)| panned(base, Vector3::from(a), d))
        .collect()
}

/// The sets, with `n` views each (`n` ≤ 6 for `fill`, `fill-k04` and `cut`, whose views are chosen).
pub fn cases(n: usize) -> Vec<Case> {
    let mut out = Vec::new();
    {
        let rig = rig("board_13x12_nomargin.toml");
        let camera = camera(1280, 960, 1100.0, -0.1);
        let poses = random_poses(&rig, &camera, n, 11);
        out.push(Case {
            name: "nomargin",
            scene: rig.clone(),
            rig,
            camera,
            settings: settings(11),
            poses,
        });
    }
    // Tilt (deg, axis in the rig frame), roll (deg), clearance (px).
    let fills: [(f64, [f64; 3], f64, f64); 6] = [
        (4.0, [1.0, 0.0, 0.0], 0.5, 15.0),
        (8.0, [0.0, 1.0, 0.0], -1.0, 12.0),
        (6.0, [1.0, 1.0, 0.0], 1.0, 18.0),
        (12.0, [0.0, 1.0, 0.0], 0.0, 10.0),
        (2.0, [0.0, 1.0, 0.0], -0.5, 20.0),
        (15.0, [1.0, 0.0, 0.0], 1.5, 14.0),
    ];
    for (name, cam) in [
        ("fill", camera(1280, 960, 1100.0, -0.1)),
        ("fill-k04", camera(1280, 960, 1500.0, -0.4)),
    ] {
        let rig = rig("board_13x12.toml");
        let poses = fills
            .iter()
            .take(n)
            .map(|&(t, a, r, m)| filling(&rig, &cam, t, Vector3::from(a), r, m))
            .collect();
        out.push(Case {
            name,
            scene: rig.clone(),
            rig,
            camera: cam,
            settings: settings(12),
            poses,
        });
    }
    {
        let rig = rig("inside_corner_seams.toml");
        let camera = camera(1600, 1200, 1300.0, -0.1);
        let poses = random_poses(&rig, &camera, n, 13);
        out.push(Case {
            name: "inside-corner",
            scene: rig.clone(),
            rig,
            camera,
            settings: settings(13),
            poses,
        });
    }
    {
        let rig = rig("wrapped_cube.toml");
        let camera = camera(1500, 1125, 1500.0, -0.3);
        let poses = random_poses(&rig, &camera, n, 14);
        out.push(Case {
            name: "wrapped-cube",
            scene: rig.clone(),
            rig,
            camera,
            settings: settings(14),
            poses,
        });
    }
    {
        let rig = rig("board_13x12.toml");
        let camera = camera(1280, 960, 1100.0, -0.1);
        let base = default_view(&rig, &camera);
        // Camera turns (axis in the camera frame, deg) that push a part of the board out of the frame.
        let poses = panned_views(
            &base,
            &[
                ([0.05, 1.0, 0.1], 22.0),
                ([0.05, 1.0, -0.1], -25.0),
                ([1.0, 0.05, 0.1], 19.0),
                ([1.0, 0.05, -0.1], -21.0),
                ([1.0, 1.0, 0.1], 24.0),
                ([1.0, -1.0, -0.1], -26.0),
            ],
            n,
        );
        out.push(Case {
            name: "cut",
            scene: rig.clone(),
            rig,
            camera,
            settings: settings(15),
            poses,
        });
    }
    {
        // The rig's board beside a larger board of the same squares: random views of both, and views
        // turned toward the larger board so that the rig's board leaves the frame.
        let scene = rig("two_boards_scene.toml");
        let rig = rig("board_13x12.toml");
        let camera = camera(1280, 960, 1100.0, -0.1);
        let mut poses = random_poses(&scene, &camera, n.div_ceil(2), 16);
        let base = default_view(&scene, &camera);
        for (k, deg) in [-24.0, -38.0, -43.0].into_iter().enumerate().take(n / 2) {
            poses.push(panned(
                &base,
                Vector3::new(0.02 * k as f64, -1.0, 0.05),
                deg,
            ));
        }
        out.push(Case {
            name: "two-boards",
            rig,
            scene,
            camera,
            settings: settings(16),
            poses,
        });
    }
    {
        // The three-face cube pushed toward the frame's borders and corners by turning the camera
        // (wide lens, k1 −0.3): one or two faces cut by the border beside proven ones.
        let rig = rig("cube_outside.toml");
        let camera = camera(1280, 960, 900.0, -0.3);
        let base = default_view(&rig, &camera);
        let poses = panned_views(
            &base,
            &[
                ([0.05, 1.0, 0.1], 24.0),
                ([0.05, 1.0, -0.1], -26.0),
                ([1.0, 0.05, 0.1], 20.0),
                ([1.0, 0.05, -0.1], -21.0),
                ([1.0, 1.0, 0.1], 24.0),
                ([1.0, -1.0, -0.1], -25.0),
            ],
            n,
        );
        out.push(Case {
            name: "cube-cut",
            scene: rig.clone(),
            rig,
            camera,
            settings: settings(19),
            poses,
        });
    }
    {
        // Issue 28's classic planar set: a 13×12 board printed to the paper's edge, 640×480 with
        // barrel distortion, the paper on a desk dark on one side of a line and bright on the other
        // (fixtures/rigs/board_on_desk_scene.toml): one corner-like junction one column beyond the
        // board, where the line meets the paper's edge.
        let scene = rig("board_on_desk_scene.toml");
        let rig = rig("board_13x12_nomargin.toml");
        let camera = camera(640, 480, 660.0, -0.25);
        let poses = random_poses(&rig, &camera, n, 18);
        out.push(Case {
            name: "paper-edge",
            rig,
            scene,
            camera,
            settings: settings(18),
            poses,
        });
    }
    {
        // A replica of the inside corner of bailus_tsai_cube_stereo (fixtures/rigs/bailus_inside_corner.toml):
        // the camera close to the corner with a wide, strongly distorted lens, the pattern continuous
        // across the fold; wall-z ends inside the frame on every side, wall-x (longer in the scene than
        // the rig describes, as its open side says) runs off the frame on its side away from the fold.
        // The camera stands further back than in the photos, so wall-x shows more columns than the
        // photos' 9: the rig describes 20 of them (its open side), the scene prints 40.
        let mut rig = rig("bailus_inside_corner.toml");
        rig.faces[1].rows = 20;
        let mut scene = rig.clone();
        scene.faces[1].rows = 40;
        scene.faces[1].open_sides.clear();
        let camera = camera(1500, 1125, 1300.0, -0.25);
        let up = Vector3::new(0.0, -1.0, 0.0);
        // Eye and target (rig frame, mm).
        let views: [([f64; 3], [f64; 3]); 6] = [
            ([330.0, 40.0, 330.0], [30.0, 50.0, 120.0]),
            ([360.0, 60.0, 300.0], [40.0, 50.0, 110.0]),
            ([300.0, 20.0, 360.0], [20.0, 60.0, 130.0]),
            ([340.0, 80.0, 330.0], [35.0, 40.0, 115.0]),
            ([380.0, 50.0, 360.0], [50.0, 50.0, 130.0]),
            ([320.0, 30.0, 310.0], [25.0, 55.0, 110.0]),
        ];
        let poses = views
            .iter()
            .take(n)
            .map(|(e, t)| look_at(&Vector3::from(*e), &Vector3::from(*t), &up))
            .collect();
        out.push(Case {
            name: "photo-corner",
            rig,
            scene,
            camera,
            settings: settings(17),
            poses,
        });
    }
    out
}

/// Frame `k` of `case` and its ground truth, rendered once into `cache/<case>/`.
pub fn frame(case: &Case, k: usize, cache: &Path) -> (GrayImage, GroundTruth) {
    cached_frame(
        &cache.join(case.name),
        &case.scene,
        &case.camera,
        &case.poses[k],
        &case.settings,
        k as u64,
    )
    .expect("render the frame into the cache")
}
