//! Where do the detector's noise-free corner errors point on foreshortened faces? Renders a set's
//! views without noise (16×16 supersampling), detects, fits the corners again through the true lens
//! (as a calibration run's refit does) and splits each corner's error along its face's receding
//! direction (where the face is foreshortened, signed toward its vanishing point) and across it
//! (signed outward from the face's centre), by angle from frontal and border/interior:
//!
//! ```sh
//! cargo run --release --example receding_bias -- [realistic|hard] [VIEWS]
//! ```
//! `VIG`, `GAMMA`, `BLUR` override the set's vignetting, gamma and blur σ (to tell the image
//! model's photometry from the geometry), `SS` the supersampling (16), `NODIST=1` drops the lens
//! distortion, `BLOCK=k` takes the views `k·VIEWS … (k+1)·VIEWS − 1` of the set's sequence instead
//! of the first. Also prints the errors by the angle between each corner's two lines, and the
//! errors of fx, fy, cx, cy, k1 solved from these noise-free corners (both weightings): what the
//! corners' noise-free error alone does to a calibration from these views.
//!
//! Issue 29: on the realistic set the errors lay across the receding direction, with an outward
//! mean that grew with the angle (the face looked wider) and biased fx by −0.015 px on the first 12
//! views (SS=32). Most of it was the shading correction's gradient, measured on the junction
//! model's level and contrast (see `detect::complete::shading_gradient`); with the squares' flat
//! levels fx −0.0032 px.
#![allow(clippy::print_stdout, clippy::unwrap_used, clippy::expect_used)]

use cubecal::detect::score::EvalSet;
use cubecal::detect::{CornerFinder, detect, refine_with_camera};
use cubecal::render::{finish, render_radiance};
use cubecal::rig::Rig;
use nalgebra::{Matrix2, Vector2, Vector3};

/// One corner's error: sine of the angle between its two lines in the image, angle of its face
/// from frontal (°), toward the vanishing point (px), across the receding direction outward (px), on
/// the grid's border.
struct Split {
    sin: f64,
    angle: f64,
    toward: f64,
    outward: f64,
    border: bool,
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let set = EvalSet::from_name(args.get(1).map_or("realistic", String::as_str))
        .expect("set: realistic or hard");
    let views: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(12);
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    );
    let (rig, _) = Rig::load(std::path::Path::new(path)).unwrap();
    let (mut camera, mut settings) = (set.camera(), set.settings());
    if std::env::var("NODIST").is_ok() {
        for v in camera.params.iter_mut().skip(5) {
            *v = 0.0;
        }
    }
    settings.noise_sigma = 0.0;
    let knob = |name: &str| std::env::var(name).ok().map(|v| v.parse::<f64>().unwrap());
    settings.supersample = knob("SS").map_or(16, |v| v as u32);
    if let Some(v) = knob("VIG") {
        settings.vignetting = v;
    }
    if let Some(v) = knob("GAMMA") {
        settings.gamma = v;
    }
    if let Some(v) = knob("BLUR") {
        settings.blur_sigma_px = v;
    }
    let mut finder = CornerFinder::new().unwrap();
    let mut all = Vec::new();
    let block = knob("BLOCK").map_or(0, |v| v as usize);
    let poses = set.poses(&rig, views * (block + 1));
    let mut solve_views = Vec::new();
    for pose in &poses[views * block..] {
        let radiance = render_radiance(&rig, &camera, pose, &settings).unwrap();
        let img = finish(&radiance, &camera, &settings, 1);
        let mut det = detect(&mut finder, &img, &rig).unwrap();
        refine_with_camera(&img, &mut det, &camera).unwrap();
        solve_views.push(det.to_view(&format!("v{}", solve_views.len())));
        for p in &det.to_rig_view("v").points {
            let c = p.corner;
            let f = &rig.faces[c.face];
            let x0 = rig.corner_xyz(c.face, c.row, c.col).unwrap();
            let truth = camera.project(pose, &x0).unwrap();
            // The local map from the face plane (mm) to the image, at a point of the face.
            let jacobian = |x: &Vector3<f64>| {
                let at = |dc: f64, dr: f64| {
                    camera
                        .project(pose, &(x + f.col_dir * dc + f.row_dir * dr))
                        .unwrap()
                };
                Matrix2::from_columns(&[at(0.5, 0.0) - at(-0.5, 0.0), at(0.0, 0.5) - at(0.0, -0.5)])
            };
            let svd = jacobian(&x0).svd(true, true);
            let k = if svd.singular_values[0] < svd.singular_values[1] {
                0
            } else {
                1
            };
            // The receding direction: the image direction of least scale, turned toward where the
            // face's scale shrinks.
            let mut receding: Vector2<f64> = svd.u.unwrap().column(k).into_owned();
            let v = svd.v_t.unwrap().row(k).transpose();
            let plane = f.col_dir * v[0] + f.row_dir * v[1];
            let scale = |t: f64| jacobian(&(x0 + plane * t)).determinant().abs();
            let step = camera.project(pose, &(x0 + plane)).unwrap() - truth;
            if (step.dot(&receding) < 0.0) != (scale(5.0) > scale(-5.0)) {
                receding = -receding;
            }
            let across = Vector2::new(-receding.y, receding.x);
            let centre = f.origin
                + f.col_dir * (0.5 * (f.cols as f64 - 1.0) * f.square_mm)
                + f.row_dir * (0.5 * (f.rows as f64 - 1.0) * f.square_mm);
            let out = (truth - camera.project(pose, &centre).unwrap())
                .dot(&across)
                .signum();
            let normal = pose.rotation * f.col_dir.cross(&f.row_dir);
            let xc = pose.transform(&x0);
            let err = p.uv - truth;
            let sa = camera
                .project(pose, &(x0 + f.col_dir * f.square_mm))
                .unwrap()
                - truth;
            let sb = camera
                .project(pose, &(x0 + f.row_dir * f.square_mm))
                .unwrap()
                - truth;
            let sin = (sa.perp(&sb) / (sa.norm() * sb.norm())).abs();
            all.push(Split {
                sin,
                angle: (normal.dot(&xc).abs() / xc.norm()).acos().to_degrees(),
                toward: err.dot(&receding),
                outward: err.dot(&across) * out,
                border: c.row == 0 || c.col == 0 || c.row + 1 == f.rows || c.col + 1 == f.cols,
            });
        }
    }
    for (name, w) in [
        ("equal", cubecal::calib::Weighting::Equal),
        ("covariance", cubecal::calib::Weighting::Covariance),
    ] {
        let opts = cubecal::calib::SolveOptions {
            weighting: w,
            ..Default::default()
        };
        let cal = cubecal::calib::solve(&solve_views, camera.image_size, &opts).unwrap();
        let e: Vec<String> = [0usize, 1, 2, 3, 5]
            .iter()
            .map(|&i| format!("{:+.4}", cal.camera.params[i] - camera.params[i]))
            .collect();
        println!(
            "noise-free solve ({name}): fx fy cx cy k1 error {}",
            e.join(" ")
        );
    }
    for (lo, hi) in [
        (0.0, 0.3),
        (0.3, 0.5),
        (0.5, 0.7),
        (0.7, 0.85),
        (0.85, 1.01),
    ] {
        let s: Vec<&Split> = all.iter().filter(|r| r.sin >= lo && r.sin < hi).collect();
        let n = s.len().max(1) as f64;
        let m = 1e3 * s.iter().map(|r| r.outward).sum::<f64>() / n;
        let rms = 1e3 * (s.iter().map(|r| r.outward.powi(2)).sum::<f64>() / n).sqrt();
        let mt = 1e3 * s.iter().map(|r| r.toward).sum::<f64>() / n;
        println!(
            "sin θ {lo:.2}–{hi:.2}: {} corners, outward mean {m:+.2} RMS {rms:.2}, toward mean {mt:+.2}",
            s.len()
        );
    }
    println!("{set:?}, {views} views, noise-free, refitted through the true lens (mpx):");
    for (lo, hi) in [(0.0, 60.0), (60.0, 75.0), (75.0, 80.0), (80.0, 90.0)] {
        for border in [false, true] {
            let s: Vec<&Split> = (all.iter())
                .filter(|r| r.angle >= lo && r.angle < hi && r.border == border)
                .collect();
            let n = s.len().max(1) as f64;
            let mean = |g: fn(&Split) -> f64| 1e3 * s.iter().map(|r| g(r)).sum::<f64>() / n;
            let rms = |g: fn(&Split) -> f64| {
                1e3 * (s.iter().map(|r| g(r).powi(2)).sum::<f64>() / n).sqrt()
            };
            println!(
                "{lo:>2}–{hi:<2}° {:8} {:4} corners: toward the vanishing point mean {:+.2} RMS {:.2}; across, outward, mean {:+.2} RMS {:.2}",
                if border { "border" } else { "interior" },
                s.len(),
                mean(|r| r.toward),
                rms(|r| r.toward),
                mean(|r| r.outward),
                rms(|r| r.outward)
            );
        }
    }
}
