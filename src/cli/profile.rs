//! `cubecal profile list | show | export (get) | diff | rollback | migrate | sync`: read and manage the
//! per-device profile store (`cubecal::profile`): a directory, or a PostgreSQL database named by
//! `--store postgres://USER@HOST/DB` (password from `--store-password-file` or `PGPASSWORD`, never the
//! URL). `migrate` applies the database schema's migrations; `sync` commits the profiles that wait in a
//! station's spool (runs that passed while the store was unreachable, [`cubecal::profile::spool`]).
//!
//! `DEVICE` is a camera identity (`usb:046d:0825:SERIAL`) or its folder name in the store (as `list`
//! prints it); `show`, `export` and `diff` also take a profile file (a run's `profile.json`), read
//! without a store. A store directory that does not exist is an error naming it (exit 3). Identities are printed escaped (`\n`, `\u{1b}`, …): USB serial strings are untrusted
//! and must not reach the terminal raw. `--json` prints the same data as JSON (`show --json` prints
//! the stored document itself).
//!
//! Exit codes: 0 ok; 3 missing store, unknown device, unreadable or newer-format profile, nothing to
//! roll back, a model an export format cannot express, a password in the store URL, a database schema
//! not migrated or newer than this cubecal; 4 the camera's profile is being written by another
//! process (or station); 7 the database cannot be reached or fails a statement.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use cubecal::profile::export::Format;
use cubecal::profile::postgres::PgStore;
use cubecal::profile::store::sha256_hex;
use cubecal::profile::{self, Change, Profile, ProfileStore, StoreLocation, display_identity};

use super::Output;

/// The default store of the systemd service (`StateDirectory=cubecal`).
pub const DEFAULT_STORE: &str = "/var/lib/cubecal/profiles";

#[derive(Debug, clap::Args)]
pub struct StoreArg {
    /// Profile store: a directory, which must exist (`calibrate --store DIR` creates it with the
    /// first passing run), or a PostgreSQL URL postgres://USER@HOST[:PORT]/DB (no password).
    #[arg(long, default_value = DEFAULT_STORE)]
    pub store: PathBuf,
    /// File whose first line is the PostgreSQL password (default: the PGPASSWORD variable).
    #[arg(long)]
    pub store_password_file: Option<PathBuf>,
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
    /// Export a camera's current profile, or a profile file (a run's profile.json), for another tool
    /// (`get` is the same command).
    #[command(visible_alias = "get")]
    Export {
        /// Camera identity or folder name, or a profile file.
        device: String,
        /// opencv (FileStorage YAML), ros (camera_info YAML), mrcal (.cameramodel), colmap
        /// (cameras.txt), kalibr (camchain YAML). A lens the format cannot express exactly is refused.
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
    /// Create or upgrade a PostgreSQL store's tables (the migrations in migrations/postgres/).
    Migrate(StoreArg),
    /// Commit the profiles waiting in the spool (runs that passed while the store was unreachable),
    /// each exactly once; exit 7 when the store is still unreachable (they keep waiting).
    Sync {
        /// The station's spool directory (output.spool).
        #[arg(long, default_value = cubecal::station::config::DEFAULT_SPOOL)]
        spool: PathBuf,
        #[command(flatten)]
        store: StoreArg,
    },
}

pub fn run(cmd: ProfileCommand, out: Output) -> anyhow::Result<u8> {
    match cmd {
        ProfileCommand::List(s) => list(&*open(&s)?, out),
        ProfileCommand::Show { device, store } => show(&store, &device, out),
        ProfileCommand::Export {
            device,
            format,
            out: file,
            store,
        } => export(&store, &device, format, file.as_deref()),
        ProfileCommand::Diff {
            a,
            b,
            jump_sigma,
            store,
        } => diff(&store, &a, &b, jump_sigma, out),
        ProfileCommand::Rollback { device, store } => rollback(&*open(&store)?, &device, out),
        ProfileCommand::Migrate(store) => migrate(&store, out),
        ProfileCommand::Sync { spool, store } => sync(&store, &spool, out),
    }
}

/// `profile sync`: drain the spool into the store.
#[allow(clippy::print_stdout)]
fn sync(s: &StoreArg, spool_dir: &Path, out: Output) -> anyhow::Result<u8> {
    let spool = profile::spool::Spool::new(spool_dir);
    let store = profile::open_store(&s.store, s.store_password_file.as_deref())
        .with_context(|| format!("opening the profile store {}", describe(&s.store)))?;
    let drained = spool
        .drain(&*store)
        .with_context(|| format!("draining the spool {}", spool_dir.display()))?;
    if out.json {
        println!(
            "{}",
            serde_json::json!({ "store": store.describe(), "spool": spool_dir, "drained": drained })
        );
    } else {
        for (run, location) in &drained.committed {
            println!("committed {run}: {}", location.display());
        }
        for run in &drained.already_stored {
            println!("already stored {run}: removed from the spool");
        }
        for (entry, reason) in &drained.failed {
            println!("refused {}: {reason}", entry.display());
        }
        println!(
            "{}: {} committed, {} already stored, {} refused (in {}), {} waiting",
            store.describe(),
            drained.committed.len(),
            drained.already_stored.len(),
            drained.failed.len(),
            spool_dir.join(profile::spool::FAILED).display(),
            drained.waiting
        );
        if let Some(why) = &drained.stopped {
            println!("stopped: {why}");
        }
    }
    Ok(if drained.stopped.is_some() {
        cubecal::exit::IO
    } else {
        cubecal::exit::SUCCESS
    })
}

fn open(s: &StoreArg) -> anyhow::Result<Box<dyn ProfileStore>> {
    // Reading commands never create a store: a missing directory is named as such.
    profile::open_existing_store(&s.store, s.store_password_file.as_deref())
        .with_context(|| format!("opening the profile store {}", describe(&s.store)))
}

/// The store as it may be shown (a URL without password or options; the URL is refused when it holds
/// a password, but its text must not reach the terminal either).
fn describe(store: &Path) -> String {
    match StoreLocation::parse(store) {
        StoreLocation::Dir(d) => d.display().to_string(),
        StoreLocation::Postgres(url) => profile::postgres::redact(&url),
    }
}

#[allow(clippy::print_stdout)]
fn migrate(s: &StoreArg, out: Output) -> anyhow::Result<u8> {
    let StoreLocation::Postgres(url) = StoreLocation::parse(&s.store) else {
        anyhow::bail!(UsageError(format!(
            "{} is a file store, which has no schema to migrate; give --store postgres://…",
            s.store.display()
        )));
    };
    let password = profile::backend::read_password(s.store_password_file.as_deref())?;
    let store = PgStore::connect_unchecked(&url, password)?;
    let applied = store.migrate()?;
    let version = store.schema_version()?;
    if out.json {
        println!(
            "{}",
            serde_json::json!({ "store": store.describe(), "applied": applied, "schema_version": version })
        );
    } else if applied.is_empty() {
        println!(
            "{}: schema at version {version}, up to date",
            store.describe()
        );
    } else {
        println!(
            "{}: applied migrations {applied:?}; schema at version {version}",
            store.describe()
        );
    }
    Ok(cubecal::exit::SUCCESS)
}

#[allow(clippy::print_stdout)]
fn list(store: &dyn ProfileStore, out: Output) -> anyhow::Result<u8> {
    let entries = store.list_cameras()?;
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
fn show(store: &StoreArg, device: &str, out: Output) -> anyhow::Result<u8> {
    let (p, bytes) = load(store, device)?;
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
        super::fmt_distortion(&c.distortion, &c.std_dev)
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
    store: &StoreArg,
    device: &str,
    format: Format,
    file: Option<&Path>,
) -> anyhow::Result<u8> {
    let (p, _) = load(store, device)?;
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
fn load(store: &StoreArg, what: &str) -> anyhow::Result<(Profile, Vec<u8>)> {
    let path = Path::new(what);
    if path.is_file() {
        let bytes = std::fs::read(path).map_err(|source| profile::ProfileError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let p = profile::parse_document(path, &bytes)?;
        return Ok((p, bytes));
    }
    Ok(open(store)?.current_profile(what)?)
}

#[allow(clippy::print_stdout)]
fn diff(store: &StoreArg, a: &str, b: &str, jump_sigma: f64, out: Output) -> anyhow::Result<u8> {
    anyhow::ensure!(
        jump_sigma.is_finite() && jump_sigma > 0.0,
        UsageError(format!(
            "--jump-sigma must be a positive number, not {jump_sigma}"
        ))
    );
    let (pa, bytes_a) = load(store, a)?;
    let (pb, _) = load(store, b)?;
    let change = profile::compare(&pa, &sha256_hex(&bytes_a), &pb, jump_sigma);
    if out.json {
        println!("{}", serde_json::to_string(&change)?);
    } else {
        print!("{}", fmt_change(&change));
    }
    Ok(cubecal::exit::SUCCESS)
}

#[allow(clippy::print_stdout)]
fn rollback(store: &dyn ProfileStore, device: &str, out: Output) -> anyhow::Result<u8> {
    let r = store.roll_back(device)?;
    if out.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        println!(
            "{}: restored the profile of {} (the profile of {} is kept in {})",
            r.folder,
            display_identity(&r.restored_created),
            display_identity(&r.replaced_created),
            r.set_aside
        );
    }
    Ok(cubecal::exit::SUCCESS)
}

/// A bad combination of arguments clap cannot check (exit 2).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);
