//! What the lens refit ([`refine_with_camera`]) changes, on photos or on renders with ground truth:
//!
//! ```sh
//! cargo run --release --example lens_refit_eval -- photos fixtures/rigs/opencv_board_9x6.toml \
//!     ../shared/datasets/opencv_stereo_left_right/images/left*.jpg
//! cargo run --release --example lens_refit_eval -- render periphery-0.3 12
//! K1=-0.001 cargo run --release --example lens_refit_eval -- render realistic 8
//! ```
//!
//! Detects the corners, solves (k3 held at 0 when the views do not determine it, as a run does),
//! measures the lens's bend over each corner's window with the solved camera ([`lens_bends`]),
//! refits every corner in undistorted coordinates, solves again, and prints: the bend, the corner σ
//! and their ratio (median, 95th percentile, largest), how far the refit moved the corners, and both
//! calibrations with their difference in units of their σ. On renders also each calibration's error
//! against the true camera and the corners' RMS error against the ground truth.
#![allow(clippy::print_stdout)]

use anyhow::Context;
use cubecal::calib::{Calibration, SolveOptions, View};
use cubecal::camera::{Camera, idx};
use cubecal::detect::score::{EvalSet, Summary, score};
use cubecal::detect::undistorted::{lens_bends, refine_with_camera_exactly};
use cubecal::detect::{CornerFinder, FrameDetection, detect, refine_with_camera};
use cubecal::render::{GroundTruth, ground_truth, render};
use cubecal::rig::Rig;

struct Frame {
    img: image::GrayImage,
    det: FrameDetection,
    truth: Option<GroundTruth>,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (rig, frames, truth_camera) = match args.first().map(String::as_str) {
        Some("photos") => {
            let rig_path = args.get(1).context("photos RIG FILE...")?;
            let (rig, _) = Rig::load(std::path::Path::new(rig_path))?;
            let mut finder = CornerFinder::new()?;
            let mut frames = Vec::new();
            for p in &args[2..] {
                let img = image::open(p).with_context(|| p.clone())?.to_luma8();
                let det = detect(&mut finder, &img, &rig)?;
                if !det.faces.is_empty() {
                    frames.push(Frame {
                        img,
                        det,
                        truth: None,
                    });
                }
            }
            (rig, frames, None)
        }
        Some("render") => {
            let name = args.get(1).context("render SET N")?;
            let set = EvalSet::from_name(name).context("unknown set")?;
            let n: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(12);
            let rig_path = concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/fixtures/rigs/cube_outside.toml"
            );
            let (rig, _) = Rig::load(std::path::Path::new(rig_path))?;
            let (mut camera, settings) = (set.camera(), set.settings());
            // K1=value: the set's camera with that k1 instead (K1=-0.001: a lens that barely bends).
            if let Some(k1) = std::env::var("K1")
                .ok()
                .map(|v| v.parse::<f64>())
                .transpose()?
            {
                let model = camera.model;
                camera = camera.with_distortion(model, &[k1]);
            }
            let mut finder = CornerFinder::new()?;
            let mut frames = Vec::new();
            for (k, pose) in set.poses(&rig, n).iter().enumerate() {
                let img = render(&rig, &camera, pose, &settings, k as u64)?;
                let truth = ground_truth(&rig, &camera, pose, &settings, k as u64);
                let det = detect(&mut finder, &img, &rig)?;
                if !det.faces.is_empty() {
                    frames.push(Frame {
                        img,
                        det,
                        truth: Some(truth),
                    });
                }
            }
            (rig, frames, Some(camera))
        }
        _ => anyhow::bail!("usage: lens_refit_eval photos RIG FILE... | render SET N"),
    };
    let size = [frames[0].img.width(), frames[0].img.height()];
    let views = |dets: &[&FrameDetection]| -> Vec<View> {
        (dets.iter().enumerate())
            .map(|(k, d)| d.to_view(&format!("view {k}")))
            .collect()
    };
    let plain: Vec<&FrameDetection> = frames.iter().map(|f| &f.det).collect();
    let (cal, opts) = solve(&views(&plain), size)?;
    // The bend over each window against the corner's σ.
    let (mut bend, mut sigma, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
    for f in &frames {
        let corners = f.det.faces.iter().flat_map(|x| x.corners.iter());
        for (c, b) in corners.zip(lens_bends(&f.det, &cal.camera)) {
            if let Some(b) = b {
                bend.push(b);
                sigma.push(c.sigma_px);
                ratio.push(b / c.sigma_px);
            }
        }
    }
    println!(
        "{} views, {} corners with a window",
        frames.len(),
        bend.len()
    );
    println!("  lens bend over the window, px: {}", stats(&mut bend));
    println!("  corner σ, px:                  {}", stats(&mut sigma));
    println!("  bend / σ:                      {}", stats(&mut ratio));
    let t = std::time::Instant::now();
    let mut polynomial = 0;
    let refit: Vec<FrameDetection> = (frames.iter())
        .map(|f| {
            let mut d = f.det.clone();
            refine_with_camera(&f.img, &mut d, &cal.camera).map(|r| {
                polynomial += r.local;
                d
            })
        })
        .collect::<Result<_, _>>()?;
    let fast = t.elapsed();
    let t = std::time::Instant::now();
    let exact: Vec<FrameDetection> = (frames.iter())
        .map(|f| {
            let mut d = f.det.clone();
            refine_with_camera_exactly(&f.img, &mut d, &cal.camera).map(|_| d)
        })
        .collect::<Result<_, _>>()?;
    let slow = t.elapsed();
    let mut apart = Vec::new();
    for (a, b) in refit.iter().zip(&exact) {
        let a = a.faces.iter().flat_map(|x| x.corners.iter());
        let b = b.faces.iter().flat_map(|x| x.corners.iter());
        apart.extend(a.zip(b).map(|(a, b)| (a.uv - b.uv).norm()));
    }
    println!(
        "  refit: {polynomial} of {} windows through the polynomial map, {:.1} ms (exactly: {:.1} ms, single thread)",
        apart.len(),
        fast.as_secs_f64() * 1e3,
        slow.as_secs_f64() * 1e3
    );
    apart.sort_by(f64::total_cmp);
    println!(
        "  refit corners, polynomial − exact map, px: median {:.1e}, max {:.1e}",
        apart[apart.len() / 2],
        apart[apart.len() - 1]
    );
    let (mut moved, mut moved_sigma) = (Vec::new(), Vec::new());
    for (f, d) in frames.iter().zip(&refit) {
        let a = f.det.faces.iter().flat_map(|x| x.corners.iter());
        let b = d.faces.iter().flat_map(|x| x.corners.iter());
        for (a, b) in a.zip(b) {
            moved.push((a.uv - b.uv).norm());
            moved_sigma.push((a.uv - b.uv).norm() / a.sigma_px);
        }
    }
    println!("  refit moved the corners, px:   {}", stats(&mut moved));
    println!(
        "  … in units of their σ:         {}",
        stats(&mut moved_sigma)
    );
    let refit_refs: Vec<&FrameDetection> = refit.iter().collect();
    let again = cubecal::calib::solve(&views(&refit_refs), size, &opts)?;
    print_calibration("without the refit", &cal, truth_camera.as_ref());
    print_calibration("with the refit   ", &again, truth_camera.as_ref());
    let names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];
    let ks = [
        idx::FX,
        idx::FY,
        idx::CX,
        idx::CY,
        idx::K1,
        idx::K2,
        idx::P1,
        idx::P2,
        idx::K3,
    ];
    let diff: Vec<String> = (names.iter().zip(ks))
        .filter(|(_, k)| cal.std_dev[*k] > 0.0)
        .map(|(n, k)| {
            let d = again.camera.params[k] - cal.camera.params[k];
            format!("{n} {:+.3}σ", d / cal.std_dev[k])
        })
        .collect();
    println!("  with − without, in σ: {}", diff.join(", "));
    if frames.iter().all(|f| f.truth.is_some()) {
        for (label, dets) in [("without", &plain), ("with", &refit_refs)] {
            let scores: Vec<_> = (frames.iter().zip(dets.iter()))
                .filter_map(|(f, d)| Some(score(&rig, f.truth.as_ref()?, d)))
                .flatten()
                .collect();
            println!(
                "  corners {label} the refit, faces < 75°: {}",
                Summary::of(&scores, 0.0, 75.0)
            );
        }
    }
    Ok(())
}

/// Solve as a run does: Brown5, k3 held at 0 when these views do not determine it.
fn solve(views: &[View], size: [u32; 2]) -> anyhow::Result<(Calibration, SolveOptions)> {
    let mut opts = SolveOptions::default();
    let cal = cubecal::calib::solve(views, size, &opts)?;
    if cubecal::calib::insignificant_at_border(&cal, idx::K3).is_some() {
        opts.fix.k3 = true;
        return Ok((cubecal::calib::solve(views, size, &opts)?, opts));
    }
    Ok((cal, opts))
}

fn print_calibration(label: &str, cal: &Calibration, truth: Option<&Camera>) {
    let c = &cal.camera;
    print!(
        "  {label}: fx {:.3} fy {:.3} cx {:.3} cy {:.3} k1 {:+.5} k2 {:+.5} k3 {:+.5}, RMS {:.4} px",
        c.fx(),
        c.fy(),
        c.cx(),
        c.cy(),
        c.params[idx::K1],
        c.params[idx::K2],
        c.params[idx::K3],
        cal.rms_px
    );
    if let Some(t) = truth {
        print!(
            "; error fx {:+.4} fy {:+.4} cx {:+.4} cy {:+.4} k1 {:+.5} (σ fx {:.4} cx {:.4} k1 {:.5})",
            c.fx() - t.fx(),
            c.fy() - t.fy(),
            c.cx() - t.cx(),
            c.cy() - t.cy(),
            c.params[idx::K1] - t.params[idx::K1],
            cal.std_dev[idx::FX],
            cal.std_dev[idx::CX],
            cal.std_dev[idx::K1],
        );
    }
    println!();
}

/// Median, 95th percentile and largest.
fn stats(v: &mut [f64]) -> String {
    if v.is_empty() {
        return "none".into();
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    format!(
        "median {:.4}, p95 {:.4}, max {:.4}",
        at(0.5),
        at(0.95),
        at(1.0)
    )
}
