//! Print the ArUco markers cubecal decodes in images, as JSON lines `{path, id, bits, corners,
//! corrected_bits}` (for comparing with OpenCV's, `tests/peers/charuco_opencv.py`):
//! `cargo run --release --example charuco_markers -- DICT_5X5_250 IMAGE...`
#![allow(clippy::print_stdout)]

use anyhow::Context;
use cubecal::detect::charuco::find_markers;
use cubecal::rig::charuco::Dictionary;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dict = Dictionary::from_name(args.first().context("dictionary name")?)
        .context("unknown dictionary")?;
    for path in &args[1..] {
        let img = image::open(path)
            .with_context(|| format!("cannot read {path}"))?
            .to_luma8();
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
