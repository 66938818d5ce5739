//! Print the ArUco markers cubecal decodes in images, as JSON lines `{path, id, bits, corners,
//! corrected_bits}` (for comparing with OpenCV's, `tests/peers/charuco_opencv.py`):
//! `cargo run --release --example charuco_markers -- DICT_5X5_250 IMAGE...`
//!
//! With `--candidates` first, every dark region examined as a marker instead, as JSON lines
//! `{path, bbox, pixels, quad, outcome}` (`outcome`: `size`, `frame-border`, `not-quad`, `not-decoded` or
//! the decoded marker's id), to see why a marker OpenCV finds is missed.
#![allow(clippy::print_stdout)]

use anyhow::Context;
use cubecal::detect::charuco::{CandidateOutcome, find_markers, marker_candidates};
use cubecal::rig::charuco::Dictionary;

fn main() -> anyhow::Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let candidates = args.first().is_some_and(|a| a == "--candidates");
    if candidates {
        args.remove(0);
    }
    let dict = Dictionary::from_name(args.first().context("dictionary name")?)
        .context("unknown dictionary")?;
    for path in &args[1..] {
        let img = image::open(path)
            .with_context(|| format!("cannot read {path}"))?
            .to_luma8();
        if candidates {
            for c in marker_candidates(&img, &[dict]) {
                let outcome = match c.outcome {
                    CandidateOutcome::Size => serde_json::json!("size"),
                    CandidateOutcome::FrameBorder => serde_json::json!("frame-border"),
                    CandidateOutcome::NotQuad => serde_json::json!("not-quad"),
                    CandidateOutcome::NotDecoded(why) => {
                        serde_json::json!(format!("not-decoded {why:?}"))
                    }
                    CandidateOutcome::Decoded(m) => serde_json::json!(m.id),
                };
                println!(
                    "{}",
                    serde_json::json!({"path": path, "bbox": c.bbox, "pixels": c.pixels,
                        "quad": c.quad.map(|q| q.map(|p| [p.x, p.y])), "outcome": outcome})
                );
            }
            continue;
        }
        for m in find_markers(&img, &[dict]) {
            let corners: Vec<[f64; 2]> = m.corners.iter().map(|c| [c.x, c.y]).collect();
            println!(
                "{}",
                serde_json::json!({"path": path, "id": m.id, "bits": m.bits, "corners": corners,
                    "corrected_bits": m.corrected_bits})
            );
        }
    }
    Ok(())
}
