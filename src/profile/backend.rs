//! The [`ProfileStore`] trait: what the station, `serve` and `cubecal profile` need of a profile store,
//! implemented by the file store ([`super::store::Store`], the embedded default for one station) and
//! by PostgreSQL ([`super::postgres::PgStore`], for a fleet of stations), and [`open_store`], which
//! picks one from the `--store` argument or `output.store` of the station config.
//!
//! The trait is called `ProfileStore` rather than `Store` because `profile::Store` is the file store's
//! type, which existing callers (and `tests/profile.rs`) name.
//!
//! ## Choosing the store
//! A `store` value that starts with `postgres://` or `postgresql://` is a PostgreSQL URL; anything else
//! is the file store's directory. The URL must not hold a password (it would end up in shell history,
//! `ps` and logs): the password comes from a file (`--store-password-file`, `output.store_password_file`)
//! or else from the `PGPASSWORD` environment variable, as libpq's clients take it.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::store::{CommitOptions, ListEntry};
use super::{Change, Profile, ProfileError};

/// Where a run's profile came from, kept with it in the store's history (the file store keeps what
/// the profile document itself holds — rig, software version, verdict — and ignores the rest).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize)]
pub struct Provenance {
    /// Unique per run and stable when the same run is committed again (the station uses the SHA-256 of
    /// the run's own `profile.json`): a second commit of the same run id stores nothing new.
    pub run_id: String,
    /// The station (host) that ran the calibration.
    pub station: String,
    /// The run's report (`report.html`) or run directory, as the station saw it.
    pub report: Option<String>,
}

/// What a commit through [`ProfileStore`] did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Committed {
    /// File store: the new `current.json`; PostgreSQL: `URL#version-ID`.
    pub location: PathBuf,
    /// The change from the replaced profile (as stored in the new one).
    pub change: Option<Change>,
    /// Whether the change is a jump (see [`Change::jump`]); false for a first profile.
    pub jump: bool,
    /// The run id was already stored: nothing was written (PostgreSQL only).
    pub already_stored: bool,
}

/// What a rollback through [`ProfileStore`] did. Its JSON has the file store's
/// [`super::store::RollbackOutcome`] fields.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RolledBack {
    /// The camera's folder (file store) or folder name (PostgreSQL).
    pub folder: String,
    /// `created` of the profile now current again.
    pub restored_created: String,
    /// `created` of the profile taken out of use.
    pub replaced_created: String,
    /// Where the replaced profile was kept.
    pub set_aside: String,
}

/// A profile store: versioned profiles per camera identity, one writer per camera at a time.
///
/// Every implementation keeps the same guarantees: a failing verdict is refused with
/// [`ProfileError::Rejected`] before the store is touched; a second writer of the same camera gets
/// [`ProfileError::Busy`] at once; a replaced profile stays in the history; identities are data, never
/// names of files or SQL.
pub trait ProfileStore: std::fmt::Debug {
    /// The store as it may be shown in messages and logs (never a password).
    fn describe(&self) -> String;

    /// Store a passing profile as its camera's current one, keeping the previous one in history.
    fn commit_run(
        &self,
        profile: &Profile,
        options: &CommitOptions,
        provenance: &Provenance,
    ) -> Result<Committed, ProfileError>;

    /// The current profile of `device` (identity, or folder name as `list` prints it) and its
    /// document bytes.
    fn current_profile(&self, device: &str) -> Result<(Profile, Vec<u8>), ProfileError>;

    /// Every camera with a current profile, by folder name.
    fn list_cameras(&self) -> Result<Vec<ListEntry>, ProfileError>;

    /// Make the newest earlier profile of `device` current again.
    fn roll_back(&self, device: &str) -> Result<RolledBack, ProfileError>;

    /// The earlier profiles of `device`, oldest first, each with where it is stored (a history file,
    /// or the database row) and its document, or why the document cannot be read (the profile
    /// report lists those rather than failing).
    fn earlier_profiles(&self, device: &str) -> Result<Vec<EarlierProfile>, ProfileError>;
}

/// An earlier profile: where it is stored, and its document or why it cannot be read.
pub type EarlierProfile = (String, Result<Profile, ProfileError>);

impl ProfileStore for super::store::Store {
    fn describe(&self) -> String {
        self.root().display().to_string()
    }

    fn commit_run(
        &self,
        profile: &Profile,
        options: &CommitOptions,
        _provenance: &Provenance,
    ) -> Result<Committed, ProfileError> {
        let o = self.commit(profile, options)?;
        Ok(Committed {
            location: o.current,
            change: o.change,
            jump: o.jump,
            already_stored: false,
        })
    }

    fn current_profile(&self, device: &str) -> Result<(Profile, Vec<u8>), ProfileError> {
        self.current(device)
    }

    fn list_cameras(&self) -> Result<Vec<ListEntry>, ProfileError> {
        self.list()
    }

    fn earlier_profiles(&self, device: &str) -> Result<Vec<EarlierProfile>, ProfileError> {
        Ok(self
            .history(device)?
            .into_iter()
            .map(|path| {
                let doc = std::fs::read(&path)
                    .map_err(|source| ProfileError::Read {
                        path: path.clone(),
                        source,
                    })
                    .and_then(|bytes| super::parse_document(&path, &bytes));
                (path.display().to_string(), doc)
            })
            .collect())
    }

    fn roll_back(&self, device: &str) -> Result<RolledBack, ProfileError> {
        let r = self.rollback(device)?;
        Ok(RolledBack {
            folder: r.folder.display().to_string(),
            restored_created: r.restored_created,
            replaced_created: r.replaced_created,
            set_aside: r.set_aside.display().to_string(),
        })
    }
}

/// Which store a `store` value names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StoreLocation {
    /// The file store's directory.
    Dir(PathBuf),
    /// A PostgreSQL URL (without a password).
    Postgres(String),
}

impl StoreLocation {
    /// `postgres://…` / `postgresql://…` is PostgreSQL, anything else a directory.
    pub fn parse(value: &Path) -> StoreLocation {
        match value.to_str() {
            Some(s) if s.starts_with("postgres://") || s.starts_with("postgresql://") => {
                StoreLocation::Postgres(s.to_string())
            }
            _ => StoreLocation::Dir(value.to_path_buf()),
        }
    }
}

/// The store `value` names as it may be shown (a directory, or the URL without password or options),
/// the same text as the opened store's [`ProfileStore::describe`].
pub fn describe_location(value: &Path) -> String {
    match StoreLocation::parse(value) {
        StoreLocation::Dir(dir) => dir.display().to_string(),
        StoreLocation::Postgres(url) => super::postgres::redact(&url),
    }
}

/// The PostgreSQL password: the first line of `password_file` when given, else `PGPASSWORD`, else none
/// (peer or trust authentication, or a `.pgpass`-less set-up that needs none).
pub fn read_password(password_file: Option<&Path>) -> Result<Option<String>, ProfileError> {
    if let Some(path) = password_file {
        let text = std::fs::read_to_string(path).map_err(|source| ProfileError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let line = text.lines().next().unwrap_or_default().to_string();
        return Ok(Some(line));
    }
    Ok(std::env::var("PGPASSWORD").ok().filter(|p| !p.is_empty()))
}

/// Open the store `value` names (see the module docs), connecting to PostgreSQL when it is a URL. A
/// store directory is created when missing (the station's first passing run).
pub fn open_store(
    value: &Path,
    password_file: Option<&Path>,
) -> Result<Box<dyn ProfileStore>, ProfileError> {
    open(value, password_file, super::store::Store::open)
}

/// [`open_store`] for commands that only read or manage what is stored: a missing store directory is
/// [`ProfileError::NoStore`], never created.
pub fn open_existing_store(
    value: &Path,
    password_file: Option<&Path>,
) -> Result<Box<dyn ProfileStore>, ProfileError> {
    open(value, password_file, super::store::Store::open_existing)
}

fn open(
    value: &Path,
    password_file: Option<&Path>,
    open_dir: fn(&Path) -> Result<super::store::Store, ProfileError>,
) -> Result<Box<dyn ProfileStore>, ProfileError> {
    match StoreLocation::parse(value) {
        StoreLocation::Dir(dir) => Ok(Box::new(open_dir(&dir)?)),
        StoreLocation::Postgres(url) => {
            let password = read_password(password_file)?;
            Ok(Box::new(super::postgres::PgStore::connect(&url, password)?))
        }
    }
}
