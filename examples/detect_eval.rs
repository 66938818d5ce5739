//! Detector evaluation on synthetic renders with exact ground truth, the sets of issue 4:
//!
//! ```sh
//! cargo run --release --example detect_eval -- realistic 24 target/detect_eval
//! cargo run --release --example detect_eval -- hard 24 target/detect_eval
//! ```
//! Arguments: set (`realistic`: cube rig, 1920×1080, fx 1400, k1 −0.1, blur σ 1, noise σ 2, gamma 2.2,
//! vignetting 0.3; `hard`: 1280×960, fx 700, k1 −0.3, blur σ 1.5, noise σ 5, low contrast (reflectances
//! 0.3 / 0.55), gamma 2.2, vignetting 0.3; `periphery-0.3`, `periphery-0.4`: strong barrel distortion
//! with the rig near the image corners, see [`EvalSet`]), number of random poses, cache directory (frames are
//! rendered once and reused). Prints every face (angle from frontal, found or why not) and the
//! summary by angle bucket, plus the detection time per frame. `VERBOSE=1` prints every face and
//! rejection; `FRONT=1` also prints the front end's recall per frame (true corners with a candidate
//! within 1 px) and its number of candidates. `REREFINE=1` also fits the corners again in
//! undistorted coordinates, with the true camera and with calibrations solved from the corners
//! (see `rerefine_report`), and prints the calibration's errors before and after. `NOISE=σ`
//! renders with pixel noise σ instead of the set's (`NOISE=0`: the noise-free bias); `SS=n` with
//! n×n supersampling; `VIG`, `GAMMA`, `BLUR` with that vignetting, gamma, blur σ; `SECOND_LOOK=0`
//! without the full-resolution second look at grazing faces.
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use cubecal::calib::SolveOptions;
use cubecal::camera::Pose;
use cubecal::camera::{Camera, idx};
use cubecal::detect::score::{
    Bias, EvalSet, Summary, imaged_radius, in_border_band, relative_radius, score,
};
use cubecal::detect::{CornerFinder, detect, refine_with_camera};
use cubecal::render::cached_frame;
use cubecal::rig::Rig;
use nalgebra::Vector3;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let set = args.first().map(String::as_str).unwrap_or("realistic");
    let n: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(24);
    let cache = PathBuf::from(
        args.get(2)
            .map(String::as_str)
            .unwrap_or("target/detect_eval"),
    );
    let verbose = std::env::var_os("VERBOSE").is_some();
    let front = std::env::var_os("FRONT").is_some();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let rig_path = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    ));
    let (rig, _) = Rig::load(&rig_path)?;
    let Some(eval_set) = EvalSet::from_name(set) else {
        anyhow::bail!("unknown set {set:?} (realistic | hard | periphery-0.3 | periphery-0.4)");
    };
    let (camera, mut settings) = (eval_set.camera(), eval_set.settings());
    // NOISE=σ overrides the set's pixel noise (NOISE=0: the detector's noise-free bias).
    let noise: Option<f64> = std::env::var("NOISE").ok().map(|s| s.parse()).transpose()?;
    // SS=n overrides the renderer's supersampling (n×n samples per edge pixel; default 4).
    let ss: Option<u32> = std::env::var("SS").ok().map(|s| s.parse()).transpose()?;
    if let Some(n) = ss {
        settings.supersample = n;
    }
    if let Some(sigma) = noise {
        settings.noise_sigma = sigma;
    }
    // VIG, GAMMA, BLUR override the set's vignetting, gamma and blur σ (to tell which part of the
    // image model a noise-free bias comes from).
    let knob = |name: &str| -> anyhow::Result<Option<f64>> {
        Ok(std::env::var(name).ok().map(|s| s.parse()).transpose()?)
    };
    let (vig, gamma, blur) = (knob("VIG")?, knob("GAMMA")?, knob("BLUR")?);
    if let Some(v) = vig {
        settings.vignetting = v;
    }
    if let Some(g) = gamma {
        settings.gamma = g;
    }
    if let Some(b) = blur {
        settings.blur_sigma_px = b;
    }
    // PAN_DEG=θ turns the camera about its vertical axis by ±θ (alternating) so that the rig is
    // cut by the image border: partially visible faces.
    let pan_deg: f64 = std::env::var("PAN_DEG")
        .ok()
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(0.0);
    let mut dir_name = set.to_string();
    if pan_deg != 0.0 {
        dir_name += &format!("-pan{pan_deg}");
    }
    if let Some(n) = ss {
        dir_name += &format!("-ss{n}");
    }
    if let Some(sigma) = noise {
        dir_name += &format!("-noise{sigma}");
    }
    for (tag, v) in [("vig", vig), ("gamma", gamma), ("blur", blur)] {
        if let Some(v) = v {
            dir_name += &format!("-{tag}{v}");
        }
    }
    let dir = cache.join(dir_name);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let poses: Vec<_> = eval_set
        .poses(&rig, n)
        .into_iter()
        .enumerate()
        .map(|(k, p)| {
            let deg = if k % 2 == 0 { pan_deg } else { -pan_deg };
            let pan =
                Pose::from_axis_angle(Vector3::new(0.0, deg.to_radians(), 0.0), Vector3::zeros());
            pan.compose(&p)
        })
        .collect();
    let mut finder = CornerFinder::new()?;
    // SECOND_LOOK=0: without the full-resolution second look at grazing faces.
    finder.set_second_look(std::env::var("SECOND_LOOK").map_or(true, |v| v != "0"));
    let rerefine = std::env::var_os("REREFINE").is_some();
    let mut kept = Vec::new();
    let mut all = Vec::new();
    let mut times = Vec::new();
    // Mean error along each face's far direction (+ away from the camera, in the image) and across
    // it, per angle band: [sum along, sum across, count] (`FAR=1`).
    let far = std::env::var_os("FAR").is_some();
    let mut far_sums = [[0.0_f64; 3]; 5];
    let mut scale_sums = [[0.0_f64; 4]; 5];
    let mut border_sums = [[0.0_f64; 5]; 5];
    for (k, pose) in poses.iter().enumerate() {
        let (img, truth) = cached_frame(&dir, &rig, &camera, pose, &settings, k as u64)?;
        let t = Instant::now();
        let det = detect(&mut finder, &img, &rig)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        let scores = score(&rig, &truth, &det);
        if front {
            front_end_recall(&mut finder, &img, &truth, k)?;
        }
        for s in &scores {
            if !(s.fully_visible || s.found || verbose && s.visible_corners > 0) {
                continue;
            }
            let rms =
                (s.errors.iter().map(|e| e * e).sum::<f64>() / s.errors.len().max(1) as f64).sqrt();
            let max = s.errors.iter().copied().fold(0.0, f64::max);
            if verbose || !s.found || s.mislabelled > 0 || max > 0.15 {
                println!(
                    "frame {k:3} face {:6} {:5.1}° visible {}/{}: {} ({} corners, rms {rms:.3}, max {max:.3}, mislabelled {})",
                    rig.faces[s.face].name,
                    s.angle_deg,
                    s.visible_corners,
                    rig.faces[s.face].n_corners(),
                    if s.found { "found" } else { "MISSED" },
                    s.corners,
                    s.mislabelled
                );
            }
        }
        if verbose || scores.iter().any(|s| s.fully_visible && !s.found) {
            for r in &det.rejected {
                println!("frame {k:3}   rejected: {}", r.reason);
            }
        }
        if far {
            for s in scores.iter().filter(|s| s.found) {
                let Some(d) = far_direction(&rig, &camera, pose, s.face) else {
                    continue;
                };
                let band = BANDS
                    .iter()
                    .position(|&(a, b)| (a..b).contains(&s.angle_deg))
                    .unwrap_or(BANDS.len() - 1);
                let f = &rig.faces[s.face];
                let border = |&(r, c): &(usize, usize)| {
                    r == 0 || c == 0 || r + 1 == f.rows || c + 1 == f.cols
                };
                for ((o, t), l) in s.offsets.iter().zip(&s.truth_uv).zip(&s.labels) {
                    // Border corners: the mean error towards the face's middle.
                    if border(l) {
                        let inward = (s.truth_uv.iter().sum::<nalgebra::Vector2<f64>>()
                            / s.truth_uv.len() as f64
                            - t)
                            .normalize();
                        border_sums[band][0] += o.dot(&inward);
                        border_sums[band][1] += o.norm_squared();
                        border_sums[band][2] += 1.0;
                    } else {
                        border_sums[band][3] += o.norm_squared();
                        border_sums[band][4] += 1.0;
                    }
                }
                for o in &s.offsets {
                    far_sums[band][0] += o.dot(&d);
                    far_sums[band][1] += o.x * -d.y + o.y * d.x;
                    far_sums[band][2] += 1.0;
                }
                // The face's scale error: least-squares s in offset ≈ s·(uv − centre), split
                // into the far direction and across it.
                let c = s.truth_uv.iter().sum::<nalgebra::Vector2<f64>>()
                    / s.truth_uv.len().max(1) as f64;
                let e = nalgebra::Vector2::new(-d.y, d.x);
                for (o, t) in s.offsets.iter().zip(&s.truth_uv) {
                    let r = t - c;
                    scale_sums[band][0] += o.dot(&d) * r.dot(&d);
                    scale_sums[band][1] += r.dot(&d).powi(2);
                    scale_sums[band][2] += o.dot(&e) * r.dot(&e);
                    scale_sums[band][3] += r.dot(&e).powi(2);
                }
            }
        }
        all.extend(scores);
        if rerefine {
            kept.push((img, det, truth));
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "set {set}: {n} frames, {}×{}",
        camera.image_size[0], camera.image_size[1]
    );
    println!(
        "  all fully visible faces: {}",
        Summary::of(&all, 0.0, 90.1)
    );
    println!(
        "  faces < 75°:             {}",
        Summary::of(&all, 0.0, 75.0)
    );
    for (a, b) in BANDS {
        println!("  {a:2}–{b:2}°: {}", Summary::of(&all, a, b));
    }
    if far {
        for (((a, b), [along, across, n]), [sa, ra, sc, rc]) in
            BANDS.iter().zip(far_sums).zip(scale_sums)
        {
            println!(
                "  {a:2}–{b:2}°: mean error along the far direction {:+.4} px, across {:+.4} px ({n} corners); scale error along {:+.2e}, across {:+.2e}",
                along / n.max(1.0),
                across / n.max(1.0),
                sa / ra.max(1e-12),
                sc / rc.max(1e-12)
            );
        }
        for ((a, b), [inward, sq_b, n_b, sq_i, n_i]) in BANDS.iter().zip(border_sums) {
            println!(
                "  {a:2}–{b:2}°: border corners mean error inwards {:+.4} px, RMS {:.4} px ({n_b}); inner corners RMS {:.4} px ({n_i})",
                inward / n_b.max(1.0),
                (sq_b / n_b.max(1.0)).sqrt(),
                (sq_i / n_i.max(1.0)).sqrt()
            );
        }
    }
    print_bias(&all, &camera);
    let partial: Vec<_> = all.iter().filter(|s| !s.fully_visible).collect();
    let placed: Vec<_> = partial.iter().filter(|s| s.found).collect();
    let errors: Vec<f64> = placed
        .iter()
        .flat_map(|s| s.errors.iter().copied())
        .collect();
    println!(
        "  partially visible faces (≥ 1 corner visible): {}, placed {} with {} corners (of {} visible), {} mislabelled, RMS {:.4} px",
        partial.iter().filter(|s| s.visible_corners > 0).count(),
        placed.len(),
        placed.iter().map(|s| s.corners).sum::<usize>(),
        placed.iter().map(|s| s.visible_corners).sum::<usize>(),
        placed.iter().map(|s| s.mislabelled).sum::<usize>(),
        (errors.iter().map(|e| e * e).sum::<f64>() / errors.len().max(1) as f64).sqrt() + 0.0
    );
    println!(
        "  detect time per frame (this build): median {:.1} ms, max {:.1} ms",
        times[times.len() / 2],
        times[times.len() - 1]
    );
    if rerefine {
        rerefine_report(&rig, &camera, &kept)?;
    }
    Ok(())
}

/// The angle bands of the summary (degrees from frontal).
const BANDS: [(f64, f64); 5] = [
    (0.0, 45.0),
    (45.0, 60.0),
    (60.0, 75.0),
    (75.0, 80.0),
    (80.0, 90.1),
];

/// The image direction (unit) in which face `face` recedes from the camera at its centre: the
/// projection of the in-plane direction along which the depth grows fastest.
fn far_direction(
    rig: &Rig,
    camera: &Camera,
    pose: &Pose,
    face: usize,
) -> Option<nalgebra::Vector2<f64>> {
    let f = &rig.faces[face];
    let mid = (f.corner_xyz(0, 0) + f.corner_xyz(f.rows - 1, f.cols - 1)) / 2.0;
    let n = pose.rotation * f.normal();
    let x = pose.transform(&mid);
    let v = x.normalize();
    let t = (v - n * v.dot(&n)).try_normalize(1e-9)?;
    let eps = 0.01 * f.square_mm;
    let a = camera.project_cam(&(x - t * eps)).ok()?;
    let b = camera.project_cam(&(x + t * eps)).ok()?;
    (b - a).try_normalize(1e-12)
}

type Kept = (
    image::GrayImage,
    cubecal::detect::FrameDetection,
    cubecal::render::GroundTruth,
);

/// `REREFINE=1`: the corners fitted again in undistorted coordinates ([`refine_with_camera`]),
/// first with the true camera (the bound), then as a user gets it: calibrate from the detected
/// corners, fit again with the solved camera, calibrate again (two rounds); the calibration's errors
/// against the true camera after each round.
fn rerefine_report(rig: &Rig, truth_camera: &Camera, kept: &[Kept]) -> anyhow::Result<()> {
    let size = truth_camera.image_size;
    let summarise = |label: &str, dets: &[cubecal::detect::FrameDetection]| {
        let scores: Vec<_> = kept
            .iter()
            .zip(dets)
            .flat_map(|((_, _, truth), d)| score(rig, truth, d))
            .collect();
        println!("{label}:");
        println!("  faces < 75°: {}", Summary::of(&scores, 0.0, 75.0));
        println!("  75–80°:      {}", Summary::of(&scores, 75.0, 80.0));
        print_bias(&scores, truth_camera);
    };
    let refit = |camera: &Camera| -> anyhow::Result<Vec<cubecal::detect::FrameDetection>> {
        let t = Instant::now();
        let mut out = Vec::new();
        let (mut n, mut refitted) = (0, 0);
        for (img, det, _) in kept {
            let mut d = det.clone();
            let r = refine_with_camera(img, &mut d, camera)?;
            n += r.corners;
            refitted += r.refitted;
            out.push(d);
        }
        println!(
            "  refitted {refitted} of {n} corners in {:.1} ms per frame",
            t.elapsed().as_secs_f64() * 1e3 / kept.len().max(1) as f64
        );
        Ok(out)
    };
    let calibrate = |label: &str,
                     dets: &[cubecal::detect::FrameDetection]|
     -> anyhow::Result<Camera> {
        let views: Vec<_> = dets
            .iter()
            .enumerate()
            .filter(|(_, d)| !d.faces.is_empty())
            .map(|(k, d)| d.to_view(&format!("frame_{k:03}")))
            .collect();
        let cal = cubecal::calib::solve(&views, size, &SolveOptions::default())?;
        let (c, t) = (&cal.camera, truth_camera);
        println!(
            "  calibration {label}: fx {:+.4} px ({:+.4} %), fy {:+.4}, cx {:+.4}, cy {:+.4}, k1 {:+.5} (σ fx {:.4}, cx {:.4}, k1 {:.5}), RMS {:.4} px",
            c.fx() - t.fx(),
            100.0 * (c.fx() / t.fx() - 1.0),
            c.fy() - t.fy(),
            c.cx() - t.cx(),
            c.cy() - t.cy(),
            c.params[idx::K1] - t.params[idx::K1],
            cal.std_dev[idx::FX],
            cal.std_dev[idx::CX],
            cal.std_dev[idx::K1],
            cal.rms_px
        );
        Ok(cal.camera)
    };
    let plain: Vec<_> = kept.iter().map(|(_, d, _)| d.clone()).collect();
    println!("--- re-refinement in undistorted coordinates");
    let with_truth = refit(truth_camera)?;
    summarise("with the true camera", &with_truth);
    println!("as a user calibrates (calibration errors vs the true camera):");
    let mut camera = calibrate("from the detector's corners", &plain)?;
    let mut dets = plain;
    for round in 1..=2 {
        dets = refit(&camera)?;
        camera = calibrate(&format!("after re-refinement round {round}"), &dets)?;
    }
    summarise("with the solved camera (2 rounds)", &dets);
    Ok(())
}

/// Corner errors by position in the image (fully visible faces < 75°): the outer 10 % border band
/// and rings of relative radius (fraction of the largest radius imaged: the farthest image corner or
/// the distortion's fold, whichever is nearer; [`imaged_radius`]).
fn print_bias(all: &[cubecal::detect::score::FaceScore], camera: &Camera) {
    let size = camera.image_size;
    println!(
        "  outer 10 % (within 10 % of the width / height of the border): {}",
        Bias::of(all, size, 75.0, |t| in_border_band(t, size, 0.1))
    );
    for (a, b) in [(0.0, 0.5), (0.5, 0.7), (0.7, 0.8), (0.8, 0.9), (0.9, 1.01)] {
        println!(
            "  radius {a:.1}–{b:.1} of {:.0} px: {}",
            imaged_radius(camera),
            Bias::of(all, size, 75.0, |t| (a..b)
                .contains(&relative_radius(t, camera)))
        );
    }
}

/// The front end alone against the ground truth: how many visible corners have a candidate within
/// 1 px, and how many candidates there are.
fn front_end_recall(
    finder: &mut CornerFinder,
    img: &image::GrayImage,
    truth: &cubecal::render::GroundTruth,
    frame: usize,
) -> anyhow::Result<()> {
    let candidates = finder.find(img)?;
    let mut per_face: std::collections::BTreeMap<usize, (usize, usize)> = Default::default();
    for c in truth.visible() {
        let Some(uv) = c.uv else { continue };
        let uv = nalgebra::Vector2::new(uv[0], uv[1]);
        let near = candidates
            .iter()
            .map(|k| (k.uv - uv).norm())
            .fold(f64::INFINITY, f64::min);
        let hit = near < 1.0;
        let e = per_face.entry(c.face_index).or_default();
        e.0 += usize::from(hit);
        e.1 += 1;
    }
    let faces: Vec<String> = per_face
        .iter()
        .map(|(f, (hit, n))| format!("face {f}: {hit}/{n}"))
        .collect();
    println!(
        "frame {frame:3} front end: {} candidates; {}",
        candidates.len(),
        faces.join(", ")
    );
    Ok(())
}
