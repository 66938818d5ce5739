//! `cubecal report RUN_DIR|PROFILE [--out FILE.html] [--store DIR]`: the self-contained HTML report of
//! a station run or of a camera's stored profile (with its history).

use std::path::{Path, PathBuf};

use cubecal::station::{self, EventSink};

use cubecal::report::profile::ProfileData;

use super::Output;
use super::profile::DEFAULT_STORE;

#[derive(Debug, clap::Args)]
#[command(
    after_help = "RUN_DIR|PROFILE is, in this order (the first that exists): a station run directory (result.json, observations.json, \
rig.toml, session/); a profile document file (a run's profile.json; a store's .../current.json \
stands for its camera folder, history included); a camera folder of a profile store (holding \
current.json and history/); or a camera identity or folder name in the store given by --store, as \
`cubecal profile show` takes it. A profile report shows the identity, the current parameters with \
σ, the stored verdict, the distortion and projection uncertainty, and how every parameter moved \
across the stored versions in σ units, (p_v − p_current) / √(σ_v² + σ_current²) as `cubecal \
profile diff` prints it (plot and table)."
)]
pub struct ReportArgs {
    /// A station run directory, or a profile: a profile file, a store's camera folder, or a camera
    /// identity or folder name in the store.
    #[arg(value_name = "RUN_DIR|PROFILE")]
    pub run: String,
    /// The HTML file to write (default RUN_DIR/report.html for a run,
    /// ./report-<camera folder>.html for a profile); the plots are also written as PNG into
    /// `<file stem>_plots/` beside it.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Profile store a camera identity is looked up in (not created when missing): a directory, or
    /// postgres://USER@HOST/DB (password from PGPASSWORD) for a fleet's store.
    #[arg(long, default_value = DEFAULT_STORE)]
    pub store: PathBuf,
}

pub fn run(args: ReportArgs, out: Output) -> anyhow::Result<u8> {
    let target = Path::new(&args.run);
    let path = if target.join(cubecal::report::run::RESULT).is_file() {
        let html = args
            .out
            .clone()
            .unwrap_or_else(|| target.join("report.html"));
        cubecal::report::write_report(target, &html)?
    } else if matches!(
        cubecal::profile::backend::StoreLocation::parse(&args.store),
        cubecal::profile::backend::StoreLocation::Postgres(_)
    ) {
        // A fleet's store: the camera's profile and history from the database (password from
        // PGPASSWORD, never the URL).
        let store = cubecal::profile::open_existing_store(&args.store, None)?;
        let data = ProfileData::from_backend(store.as_ref(), &args.run)?;
        let html = args.out.clone().unwrap_or_else(|| data.default_out());
        cubecal::report::profile::write_profile_report(&data, &html)?
    } else {
        let data = ProfileData::locate(&args.run, &args.store)?;
        let html = args.out.clone().unwrap_or_else(|| data.default_out());
        cubecal::report::profile::write_profile_report(&data, &html)?
    };
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

/// The run's `report.html`, drawn once the station's run has returned (the station emits its results;
/// front ends decide what to render), its thumbnails on the station's `previews` of the frames. The watchdog keeps being pinged through `sink` meanwhile. The
/// report is for people: a run whose report cannot be drawn is still a run, so a failure is logged.
pub(super) fn write_for_run(
    run_dir: &Path,
    previews: Vec<cubecal::run::preview::FramePreview>,
    sink: &mut dyn EventSink,
) {
    if let Err(e) = station::notify::alive_during(sink, station::SOLVE_LIMIT, || {
        cubecal::report::write_run_report_with(run_dir, previews)
    }) {
        tracing::warn!(error = %e, "could not write the run's report.html");
    }
}
