//! The grid cases of issue 19 on renders with exact ground truth (the sets are described in
//! `tests/cases/mod.rs`):
//!
//! ```sh
//! cargo run --release --example detect_cases -- 6 target/detect_cases
//! ```
//! Arguments: views per set (≤ 6), cache directory (frames are rendered once and reused while their
//! ground truth is unchanged). Prints, per set: the fully visible faces and how many were found, the
//! wrongly labelled corners, the RMS error of the correctly labelled corners against the truth, the
//! partially visible faces placed, and for every frame with a missed face the rejections (why).
//! `VERBOSE=1` prints every face of every frame.
#![allow(clippy::print_stdout, clippy::print_stderr)]

#[path = "../tests/cases/mod.rs"]
mod cases;

use std::path::PathBuf;
use std::time::Instant;

use cubecal::detect::score::{Summary, score};
use cubecal::detect::{CornerFinder, detect};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n: usize = args.first().map(|s| s.parse()).transpose()?.unwrap_or(6);
    let cache = PathBuf::from(
        args.get(1)
            .map(String::as_str)
            .unwrap_or("target/detect_cases"),
    );
    let only = std::env::var("CASE").ok();
    let verbose = std::env::var_os("VERBOSE").is_some();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let mut finder = CornerFinder::new()?;
    for case in cases::cases(n) {
        if only.as_deref().is_some_and(|o| o != case.name) {
            continue;
        }
        let mut all = Vec::new();
        let mut times = Vec::new();
        for k in 0..case.poses.len() {
            let (img, truth) = cases::frame(&case, k, &cache);
            let t = Instant::now();
            let det = detect(&mut finder, &img, &case.rig)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            let scores = score(&case.rig, &truth, &det);
            for s in &scores {
                if s.visible_corners == 0 {
                    continue;
                }
                let rms = (s.errors.iter().map(|e| e * e).sum::<f64>()
                    / s.errors.len().max(1) as f64)
                    .sqrt();
                if verbose || (s.fully_visible && !s.found) || s.mislabelled > 0 {
                    println!(
                        "{} frame {k}: face {} {:.1}° visible {}/{}: {} ({} corners, rms {rms:.4}, mislabelled {})",
                        case.name,
                        case.rig.faces[s.face].name,
                        s.angle_deg,
                        s.visible_corners,
                        case.rig.faces[s.face].n_corners(),
                        if s.found { "found" } else { "MISSED" },
                        s.corners,
                        s.mislabelled
                    );
                }
            }
            if verbose || scores.iter().any(|s| s.visible_corners > 0 && !s.found) {
                for r in &det.rejected {
                    println!("{} frame {k}:   rejected: {}", case.name, r.reason);
                }
            }
            all.extend(scores);
        }
        let partial: Vec<_> = all
            .iter()
            .filter(|s| !s.fully_visible && s.visible_corners > 0)
            .collect();
        let placed: Vec<_> = partial.iter().filter(|s| s.found).collect();
        let placed_sq: Vec<f64> = placed
            .iter()
            .flat_map(|s| s.errors.iter().map(|e| e * e))
            .collect();
        times.sort_by(f64::total_cmp);
        println!(
            "CASE {:14} {} frames {}×{}: fully visible {}",
            case.name,
            case.poses.len(),
            case.camera.image_size[0],
            case.camera.image_size[1],
            Summary::of(&all, 0.0, 90.1)
        );
        println!(
            "     {:14} partially visible faces {}, placed {} ({} corners, RMS {:.4} px); median detect {:.1} ms",
            "",
            partial.len(),
            placed.len(),
            placed_sq.len(),
            (placed_sq.iter().sum::<f64>() / placed_sq.len().max(1) as f64).sqrt(),
            times.get(times.len() / 2).copied().unwrap_or(0.0)
        );
    }
    Ok(())
}
