//! `cubecal solve` (being built under issue 2).

use super::Output;

#[derive(Debug, clap::Args)]
pub struct SolveArgs {
    /// Observations JSON file.
    pub observations: std::path::PathBuf,
}

pub fn run(args: SolveArgs, _out: Output) -> anyhow::Result<u8> {
    Err(cubecal::observations::ObservationsError::Read {
        path: args.observations.display().to_string(),
        source: std::io::Error::other("not implemented yet"),
    }
    .into())
}
