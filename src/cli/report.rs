//! `cubecal report RUN_DIR [--out FILE.html]`: the self-contained HTML report of a station run.

use std::path::PathBuf;

use super::Output;

#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// A station run directory (result.json, observations.json, rig.toml and session/).
    pub run: PathBuf,
    /// The HTML file to write (default RUN_DIR/report.html); the plots are also written as PNG into
    /// `<file stem>_plots/` beside it.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: ReportArgs, out: Output) -> anyhow::Result<u8> {
    let html = args
        .out
        .clone()
        .unwrap_or_else(|| args.run.join("report.html"));
    let path = cubecal::report::write_report(&args.run, &html)?;
    print_written(&path, out);
    Ok(cubecal::exit::SUCCESS)
}

#[allow(clippy::print_stdout)]
fn print_written(path: &std::path::Path, out: Output) {
    if out.json {
        println!("{}", serde_json::json!({ "report": path }));
    } else {
        println!("wrote {}", path.display());
    }
}
