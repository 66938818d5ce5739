//! ChArUco detection on synthetic renders of the 3-face ChArUco cube (`fixtures/rigs/charuco_cube.toml`)
//! with exact ground truth:
//!
//! ```sh
//! cargo run --release --example charuco_eval -- realistic 24 target/charuco_eval
//! PAN_DEG=25 cargo run --release --example charuco_eval -- hard 24 target/charuco_eval
//! ```
//! Arguments: set (`realistic` | `hard`, see [`EvalSet`]), number of random poses, cache directory
//! (frames and their ground truth are rendered once and kept there, for the OpenCV peer
//! `tests/peers/charuco_opencv.py` too). `PAN_DEG=θ` turns the camera by ±θ so that faces are cut by
//! the frame. Prints per frame the markers decoded and corners labelled, then the corners labelled,
//! the wrong labels and the corner RMS against the ground truth, and the detection time.
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use cubecal::camera::Pose;
use cubecal::detect::score::{EvalSet, score};
use cubecal::detect::{CornerFinder, charuco, detect};
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
            .unwrap_or("target/charuco_eval"),
    );
    let pan_deg: f64 = std::env::var("PAN_DEG")
        .ok()
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(0.0);
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let rig_path = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/charuco_cube.toml"
    ));
    let (rig, _) = Rig::load(&rig_path)?;
    let Some(eval_set) = EvalSet::from_name(set) else {
        anyhow::bail!("unknown set {set:?} (realistic | hard)");
    };
    let (camera, settings) = (eval_set.camera(), eval_set.settings());
    let dir = cache.join(format!("{set}-pan{pan_deg}"));
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
    let (mut labelled, mut wrong, mut visible, mut sq, mut count) = (0, 0, 0, 0.0, 0);
    let mut times = Vec::new();
    for (k, pose) in poses.iter().enumerate() {
        let (img, truth) = cached_frame(&dir, &rig, &camera, pose, &settings, k as u64)?;
        let t = Instant::now();
        let det = detect(&mut finder, &img, &rig)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        let markers = charuco::find_markers(
            &img,
            &[cubecal::rig::charuco::Dictionary::from_name("DICT_5X5_250")
                .context("dictionary")?],
        );
        let scores = score(&rig, &truth, &det);
        let frame_corners: usize = scores.iter().map(|s| s.corners).sum();
        let frame_wrong: usize = scores.iter().map(|s| s.mislabelled).sum();
        let frame_visible: usize = scores.iter().map(|s| s.visible_corners).sum();
        println!(
            "frame {k:3}: {} markers, {frame_corners} corners of {frame_visible} visible, {frame_wrong} wrong, faces at {}",
            markers.len(),
            scores
                .iter()
                .map(|s| format!("{:.0}°", s.angle_deg))
                .collect::<Vec<_>>()
                .join(" ")
        );
        for s in &scores {
            labelled += s.corners;
            wrong += s.mislabelled;
            visible += s.visible_corners;
            sq += s.errors.iter().map(|e| e * e).sum::<f64>();
            count += s.errors.len();
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "set {set} pan ±{pan_deg}°: {n} frames, {labelled} corners labelled of {visible} visible, {wrong} wrong labels, RMS {:.4} px",
        (sq / count.max(1) as f64).sqrt()
    );
    println!(
        "  detect time per frame (this build): median {:.1} ms, max {:.1} ms",
        times[times.len() / 2],
        times[times.len() - 1]
    );
    Ok(())
}
