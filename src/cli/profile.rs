//! `cubecal profile list | show | export | diff | rollback`: read and manage the per-device profile
//! store (`cubecal::profile`).
//!
//! `DEVICE` is a camera identity (`usb:046d:0825:SERIAL`) or its folder name in the store (as `list`
//! prints it); `show`, `export` and `diff` also take a profile file (a run's `profile.json`), read
//! without a store. A store directory that does not exist is an error naming it (exit 3). Identities are printed escaped (`\n`, `\u{1b}`, …): USB serial strings are untrusted
//! and must not reach the terminal raw. `--json` prints the same data as JSON (`show --json` prints
//! the stored document itself).
//!
//! Exit codes: 0 ok; 3 missing store, unknown device, unreadable or newer-format profile, nothing to roll back, a
//! model an export format cannot express; 4 the camera's profile is being written by another process.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use cubecal::profile::export::Format;
use cubecal::profile::store::sha256_hex;
use cubecal::profile::{self, Change, Profile, Store, display_identity};

use super::Output;

/// The default store of the systemd service (`StateDirectory=cubecal`).
pub const DEFAULT_STORE: &str = "/var/lib/cubecal/profiles";

#[derive(Debug, clap::Args)]
pub struct StoreArg {
    /// Profile store directory; it must exist (`calibrate --store DIR` creates it with the first
    /// passing run).
    #[arg(long, default_value = DEFAULT_STORE)]
    pub store: PathBuf,
}

#[derive(Debug, clap::Subcommand)]
pub enum ProfileCommand {
    /// List the cameras in the store with their current profile.
    List(StoreArg),
    /// Show a camera's current profile, or a profile file (a run's profile.json).
    Show {
        /// Camera identity or folder name, or a profile file.
        device: String,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Export a camera's current profile, or a profile file (a run's profile.json), for another tool.
    Export {
        /// Camera identity or folder name, or a profile file.
        device: String,
        /// opencv (FileStorage YAML), ros (camera_info YAML), mrcal (.cameramodel), colmap (cameras.txt).
        #[arg(long)]
        format: Format,
        /// Write to this file instead of standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Compare two profiles (each a profile file or a camera in the store): Δ per parameter in σ.
    Diff {
        a: String,
        b: String,
        /// Flag a jump beyond this many σ.
        #[arg(long, default_value_t = 5.0)]
        jump_sigma: f64,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Make a camera's previous profile current again (the replaced one is kept in rolled-back/).
    Rollback {
        /// Camera identity or folder name.
        device: String,
        #[command(flatten)]
        store: StoreArg,
    },
}

pub fn run(cmd: ProfileCommand, out: Output) -> anyhow::Result<u8> {
    match cmd {
        ProfileCommand::List(s) => list(&open(&s.store)?, out),
        ProfileCommand::Show { device, store } => show(&store.store, &device, out),
        ProfileCommand::Export {
            device,
            format,
            out: file,
            store,
        } => export(&store.store, &device, format, file.as_deref()),
        ProfileCommand::Diff {
            a,
            b,
            jump_sigma,
            store,
        } => diff(&store.store, &a, &b, jump_sigma, out),
        ProfileCommand::Rollback { device, store } => rollback(&open(&store.store)?, &device, out),
    }
}

fn open(dir: &Path) -> anyhow::Result<Store> {
    Store::open_existing(dir)
        .with_context(|| format!("opening the profile store {}", dir.display()))
}

#[allow(clippy::print_stdout)]
fn list(store: &Store, out: Output) -> anyhow::Result<u8> {
    let entries = store.list()?;
    if out.json {
        let rows: Vec<serde_json::Value> = entries
            .iter()
            .map(|e| match &e.summary {
                Ok(s) => serde_json::json!({ "folder": e.folder, "summary": s }),
                Err(err) => serde_json::json!({ "folder": e.folder, "error": err.to_string() }),
            })
            .collect();
        println!("{}", serde_json::Value::Array(rows));
        return Ok(cubecal::exit::SUCCESS);
    }
    println!("FOLDER\tIDENTITY\tCREATED\tMODEL\tRMS_PX\tHISTORY\tJUMP");
    for e in &entries {
        match &e.summary {
            Ok(s) => println!(
                "{}\t{}\t{}\t{}\t{:.3}\t{}\t{}",
                e.folder,
                display_identity(&s.identity),
                display_identity(&s.created),
                display_identity(&s.model),
                s.rms_px,
                s.history,
                if s.jump { "yes" } else { "no" }
            ),
            Err(err) => println!(
                "{}\terror: {}",
                e.folder,
                display_identity(&err.to_string())
            ),
        }
    }
    Ok(cubecal::exit::SUCCESS)
}

fn fmt_change(c: &Change) -> String {
    let mut s = format!(
        "change from {} (max |Δ/σ| {:.2}, threshold {}): {}\n",
        display_identity(&c.previous_created),
        c.max_abs_delta_sigma,
        c.jump_sigma,
        if c.jump { "JUMP" } else { "within threshold" }
    );
    for note in &c.notes {
        s += &format!("  note: {note}\n");
    }
    for p in &c.params {
        s += &format!(
            "  {:<5} {:>14.6} -> {:>14.6}  Δ {:>+12.6}  σ {:>10.6}  Δ/σ {:>+8.2}{}\n",
            p.name,
            p.previous,
            p.current,
            p.delta,
            p.sigma,
            p.delta_sigma,
            match p.fixed.as_deref() {
                Some(side) => format!("  (fixed in the {side} profile; not counted as a jump)"),
                None => String::new(),
            }
        );
    }
    s
}

#[allow(clippy::print_stdout)]
fn show(store_dir: &Path, device: &str, out: Output) -> anyhow::Result<u8> {
    let (p, bytes) = load(store_dir, device)?;
    if out.json {
        std::io::stdout()
            .write_all(&bytes)
            .context("writing to standard output")?;
        return Ok(cubecal::exit::SUCCESS);
    }
    let c = &p.calibration;
    let k = &c.camera_matrix;
    println!("identity:   {}", display_identity(&p.identity.id));
    println!("created:    {}", display_identity(&p.created));
    println!(
        "software:   cubecal {}",
        display_identity(&p.software_version)
    );
    println!(
        "rig:        {} (sha256 {})",
        display_identity(&p.rig.name),
        display_identity(&p.rig.sha256)
    );
    if let Some(s) = &p.session {
        println!(
            "session:    {} (manifest sha256 {})",
            display_identity(&s.path.to_string_lossy()),
            display_identity(&s.manifest_sha256)
        );
    }
    println!("image:      {}x{}", c.image_size[0], c.image_size[1]);
    println!(
        "K:          fx {:.4}  fy {:.4}  cx {:.4}  cy {:.4}  skew {:.4}",
        k[0][0], k[1][1], k[0][2], k[1][2], k[0][1]
    );
    println!(
        "distortion: {} {}",
        display_identity(&c.distortion.model),
        super::fmt_distortion(&c.distortion.coefficients, &c.std_dev)
    );
    for (name, sd) in &c.std_dev {
        println!("  σ {:<5} {sd:.6}", display_identity(name));
    }
    println!(
        "rms:        {:.4} px (reprojection {:.4} px), {} points",
        c.rms_px, c.rms_reprojection_px, c.n_points
    );
    println!(
        "verdict:    {}",
        if p.verdict.pass { "pass" } else { "FAIL" }
    );
    for ch in &p.verdict.checks {
        println!(
            "  {} {:<20} {} (threshold {})",
            if ch.pass { "ok  " } else { "FAIL" },
            display_identity(&ch.name),
            super::fmt_value(ch.value),
            super::fmt_value(ch.threshold)
        );
    }
    if let Some(ch) = &p.change {
        print!("{}", fmt_change(ch));
    }
    Ok(cubecal::exit::SUCCESS)
}

fn export(
    store_dir: &Path,
    device: &str,
    format: Format,
    file: Option<&Path>,
) -> anyhow::Result<u8> {
    let (p, _) = load(store_dir, device)?;
    let text = format.render(&p)?;
    match file {
        Some(path) => {
            std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?
        }
        None => std::io::stdout()
            .write_all(text.as_bytes())
            .context("writing to standard output")?,
    }
    Ok(cubecal::exit::SUCCESS)
}

/// A profile named by a file path (a run's `profile.json`, a history file) or by a camera in the
/// store, with the document's bytes.
fn load(store_dir: &Path, what: &str) -> anyhow::Result<(Profile, Vec<u8>)> {
    let path = Path::new(what);
    if path.is_file() {
        let bytes = std::fs::read(path).map_err(|source| profile::ProfileError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let p = profile::parse_document(path, &bytes)?;
        return Ok((p, bytes));
    }
    Ok(open(store_dir)?.current(what)?)
}

#[allow(clippy::print_stdout)]
fn diff(store_dir: &Path, a: &str, b: &str, jump_sigma: f64, out: Output) -> anyhow::Result<u8> {
    anyhow::ensure!(
        jump_sigma.is_finite() && jump_sigma > 0.0,
        UsageError(format!(
            "--jump-sigma must be a positive number, not {jump_sigma}"
        ))
    );
    let (pa, bytes_a) = load(store_dir, a)?;
    let (pb, _) = load(store_dir, b)?;
    let change = profile::compare(&pa, &sha256_hex(&bytes_a), &pb, jump_sigma);
    if out.json {
        println!("{}", serde_json::to_string(&change)?);
    } else {
        print!("{}", fmt_change(&change));
    }
    Ok(cubecal::exit::SUCCESS)
}

#[allow(clippy::print_stdout)]
fn rollback(store: &Store, device: &str, out: Output) -> anyhow::Result<u8> {
    let r = store.rollback(device)?;
    if out.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        println!(
            "{}: restored the profile of {} (the profile of {} is kept in {})",
            r.folder.display(),
            display_identity(&r.restored_created),
            display_identity(&r.replaced_created),
            r.set_aside.display()
        );
    }
    Ok(cubecal::exit::SUCCESS)
}

/// A bad combination of arguments clap cannot check (exit 2).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);
