//! `cubecal turntable ...` (being built under issue 6).

use clap::Subcommand;

use super::Output;

#[derive(Debug, Subcommand)]
pub enum TurntableCommand {
    /// Print the state of a turntable.
    Status {
        /// Serial port path, e.g. /dev/ttyUSB0.
        #[arg(long)]
        port: String,
    },
}

pub fn run(cmd: TurntableCommand, _out: Output) -> anyhow::Result<u8> {
    match cmd {
        TurntableCommand::Status { port } => Err(cubecal::turntable::TurntableError::Open {
            path: port,
            source: std::io::Error::other("not implemented yet"),
        }
        .into()),
    }
}
