//! `cubecal devices` and `cubecal record` (being built under issue 5).

use super::Output;

#[derive(Debug, clap::Args)]
pub struct DevicesArgs {}

#[derive(Debug, clap::Args)]
pub struct RecordArgs {
    /// V4L2 device node, e.g. /dev/video0.
    #[arg(long)]
    pub device: std::path::PathBuf,
    /// Output session directory.
    #[arg(long)]
    pub out: std::path::PathBuf,
}

pub fn run_devices(_args: DevicesArgs, _out: Output) -> anyhow::Result<u8> {
    Err(cubecal::capture::CaptureError::Io {
        source_name: "v4l2".into(),
        context: "device discovery".into(),
        source: std::io::Error::other("not implemented yet"),
    }
    .into())
}

pub fn run_record(args: RecordArgs, _out: Output) -> anyhow::Result<u8> {
    Err(cubecal::capture::CaptureError::Io {
        source_name: args.device.display().to_string(),
        context: "recording".into(),
        source: std::io::Error::other("not implemented yet"),
    }
    .into())
}
