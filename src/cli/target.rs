//! `cubecal target ...` (being built under issue 3).

use clap::Subcommand;

use super::Output;

#[derive(Debug, Subcommand)]
pub enum TargetCommand {
    /// Write one printable SVG per face of a rig, at exact physical scale.
    Print {
        /// Rig description (TOML).
        rig: std::path::PathBuf,
        /// Output directory.
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

pub fn run(cmd: TargetCommand, _out: Output) -> anyhow::Result<u8> {
    match cmd {
        TargetCommand::Print { rig, .. } => Err(cubecal::target::TargetError::Read {
            path: rig.display().to_string(),
            source: std::io::Error::other("not implemented yet"),
        }
        .into()),
    }
}
