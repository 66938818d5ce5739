//! `cubecal render` (being built under issue 3).

use super::Output;

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// Rig description (TOML).
    pub rig: std::path::PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: std::path::PathBuf,
}

pub fn run(args: RenderArgs, _out: Output) -> anyhow::Result<u8> {
    Err(cubecal::target::TargetError::Read {
        path: args.rig.display().to_string(),
        source: std::io::Error::other("not implemented yet"),
    }
    .into())
}
