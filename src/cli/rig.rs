//! `cubecal rig ...` (alias `target`): work with rig descriptions.

use clap::Subcommand;
use cubecal::rig::{Rig, svg};

use super::Output;

#[derive(Debug, Subcommand)]
pub enum RigCommand {
    /// Write one printable SVG per face of a rig, at exact physical scale (print at 100 %, then check
    /// the 100 mm scale bar with a ruler).
    Print {
        /// Rig description (TOML).
        rig: std::path::PathBuf,
        /// Output directory (created if needed).
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

pub fn run(cmd: RigCommand, out: Output) -> anyhow::Result<u8> {
    match cmd {
        RigCommand::Print { rig, out: dir } => {
            let (rig, warnings) = Rig::load(&rig)?;
            let paths = svg::write_face_svgs(&rig, &dir)?;
            print_written(&rig, &warnings, &paths, out)?;
            Ok(cubecal::exit::SUCCESS)
        }
    }
}

fn print_written(
    rig: &Rig,
    warnings: &[cubecal::rig::RigWarning],
    paths: &[std::path::PathBuf],
    out: Output,
) -> anyhow::Result<()> {
    if out.json {
        let faces: Vec<_> = rig
            .faces
            .iter()
            .zip(paths)
            .map(|(f, p)| {
                let lay = svg::PageLayout::for_face(f);
                serde_json::json!({
                    "face": f.name, "svg": p, "cols": f.cols, "rows": f.rows, "square_mm": f.square_mm,
                    "page_mm": [lay.page_width_mm, lay.page_height_mm],
                })
            })
            .collect();
        let v = serde_json::json!({
            "rig": rig.name,
            "warnings": warnings.iter().map(|w| w.to_string()).collect::<Vec<_>>(),
            "faces": faces,
        });
        outln!("{v}")?;
        return Ok(());
    }
    for w in warnings {
        outln!("warning: {w}")?;
    }
    for (f, p) in rig.faces.iter().zip(paths) {
        let lay = svg::PageLayout::for_face(f);
        outln!(
            "{}: face '{}', {}×{} inner corners, {} mm squares, page {:.1} × {:.1} mm",
            p.display(),
            f.name,
            f.cols,
            f.rows,
            f.square_mm,
            lay.page_width_mm,
            lay.page_height_mm
        )?;
    }
    Ok(())
}
