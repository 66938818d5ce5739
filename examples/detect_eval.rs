//! Detector evaluation on synthetic renders with exact ground truth, the sets of issue 4:
//!
//! ```sh
//! cargo run --release --example detect_eval -- realistic 24 target/detect_eval
//! cargo run --release --example detect_eval -- hard 24 target/detect_eval
//! ```
//! Arguments: set (`realistic`: cube rig, 1920×1080, fx 1400, k1 −0.1, blur σ 1, noise σ 2, gamma 2.2,
//! vignetting 0.3; `hard`: 1280×960, fx 700, k1 −0.3, blur σ 1.5, noise σ 5, low contrast (reflectances
//! 0.3 / 0.55), gamma 2.2, vignetting 0.3), number of random poses, cache directory (frames are
//! rendered once and reused). Prints every face (angle from frontal, found or why not) and the
//! summary by angle bucket, plus the detection time per frame. `VERBOSE=1` prints every face and
//! rejection; `FRONT=1` also prints the front end's recall per frame (true corners with a candidate
//! within 1 px) and its number of candidates.
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use cubecal::camera::Pose;
use cubecal::capture::synthetic::{frame_paths, ground_truth, render, write_frame};
use cubecal::detect::score::{EvalSet, Summary, score};
use cubecal::detect::{CornerFinder, detect};
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
    let eval_set = match set {
        "realistic" => EvalSet::Realistic,
        "hard" => EvalSet::Hard,
        other => anyhow::bail!("unknown set {other:?} (realistic | hard)"),
    };
    let (camera, settings) = (eval_set.camera(), eval_set.settings());
    // PAN_DEG=θ turns the camera about its vertical axis by ±θ (alternating) so that the rig is
    // cut by the image border: partially visible faces.
    let pan_deg: f64 = std::env::var("PAN_DEG")
        .ok()
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(0.0);
    let dir = if pan_deg == 0.0 {
        cache.join(set)
    } else {
        cache.join(format!("{set}-pan{pan_deg}"))
    };
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
    let mut all = Vec::new();
    let mut times = Vec::new();
    for (k, pose) in poses.iter().enumerate() {
        let (png, _) = frame_paths(&dir, k as u64);
        let truth = ground_truth(&rig, &camera, pose, &settings, k as u64);
        let img = if png.exists() {
            image::open(&png)?.to_luma8()
        } else {
            let img = render(&rig, &camera, pose, &settings, k as u64)?;
            write_frame(&dir, &img, &truth)?;
            img
        };
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
        all.extend(scores);
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
    for (a, b) in [(0.0, 45.0), (45.0, 60.0), (60.0, 75.0), (75.0, 90.1)] {
        println!("  {a:2}–{b:2}°: {}", Summary::of(&all, a, b));
    }
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
    Ok(())
}

/// The front end alone against the ground truth: how many visible corners have a candidate within
/// 1 px, and how many candidates there are.
fn front_end_recall(
    finder: &mut CornerFinder,
    img: &image::GrayImage,
    truth: &cubecal::capture::synthetic::GroundTruth,
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
