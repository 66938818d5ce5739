//! The local spool: where a passing run's profile waits while its store (a PostgreSQL database) cannot
//! be reached, and from which it is committed, exactly once, when the store returns.
//!
//! ## Why a spool, and why exactly once
//! A station that loses its database must keep calibrating: the camera on the bench does not wait for
//! the network. When a commit cannot reach the store ([`ProfileError::is_unreachable`]: the connection
//! refused, reset, closed or timed out, the server shutting down or recovering), the station writes the
//! profile, the commit options and the run's [`Provenance`] into one file of the spool directory
//! (`<run id>.json`, written atomically: temporary file, fsync, rename, fsync of the directory) and the
//! run says where it waits. [`Spool::drain`] — run by the station before its own commit, by `serve`,
//! and by `cubecal profile sync` — commits each entry, oldest profile first, and removes the file only
//! once the store has answered. A crash or a lost connection between the store's commit and the
//! removal leaves the file behind; its next commit finds the run id already stored
//! ([`Committed::already_stored`]) and writes nothing: the run id, the SHA-256 of the run's own
//! `profile.json`, makes the commit idempotent, so a spooled run lands in the history once.
//!
//! Entries the store refuses for good (an invalid profile, a run id stored for another camera, a role
//! without the right to commit) are moved to `failed/` with the reason beside them, never dropped; a
//! camera that another station is committing at that moment ([`ProfileError::Busy`]) stays for the
//! next drain. An entry recorded for another store than the one draining stays where it is.
//!
//! A spooled profile is committed when the store returns, after any profile another station committed
//! for the same camera meanwhile: it then becomes that camera's current profile (the store orders
//! profiles by commit, as for any late commit).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::backend::{Committed, ProfileStore, Provenance};
use super::store::{CommitOptions, read_err, write_err};
use super::{ProfileError, parse_document, to_document};

/// The spool's file format.
pub const SPOOL_FORMAT: u32 = 1;

/// The folder (inside the spool) of entries the store refused for good.
pub const FAILED: &str = "failed";

/// One waiting profile, as written in the spool.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Entry {
    spool_format: u32,
    /// The store it is meant for, as [`ProfileStore::describe`] shows it (no password).
    store: String,
    run_id: String,
    station: String,
    report: Option<String>,
    jump_sigma: f64,
    /// Why it was spooled (the store's error).
    reason: String,
    /// The profile document, exactly as the run's `profile.json` holds it.
    document: String,
    /// When it was spooled, nanoseconds since the Unix epoch: orders the profiles of one second
    /// (`created` has whole seconds), so that runs drain in the order they ran. 0 in entries
    /// written before it existed.
    #[serde(default)]
    spooled_ns: u64,
}

/// A spool directory (created on the first entry).
#[derive(Debug, Clone)]
pub struct Spool {
    dir: PathBuf,
}

/// What a drain did.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Drained {
    /// Run ids committed now, with where each went.
    pub committed: Vec<(String, PathBuf)>,
    /// Run ids the store already held (a drain cut short after the store's commit): removed.
    pub already_stored: Vec<String>,
    /// Entries moved to `failed/`, with the reason.
    pub failed: Vec<(PathBuf, String)>,
    /// Entries still waiting (store unreachable again, camera busy, or meant for another store).
    pub waiting: usize,
    /// Why the drain stopped early (the store unreachable again), if it did.
    pub stopped: Option<String>,
}

/// `bytes` into `dir/name`: temporary file, fsync, rename, fsync of `dir`.
fn write_durable(dir: &Path, name: &str, bytes: &[u8]) -> Result<PathBuf, ProfileError> {
    use std::io::Write;
    let path = dir.join(name);
    let mut tmp = tempfile::Builder::new()
        .prefix(".spool-")
        .tempfile_in(dir)
        .map_err(write_err(dir))?;
    tmp.write_all(bytes)
        .and_then(|()| tmp.as_file().sync_all())
        .map_err(write_err(&path))?;
    tmp.persist(&path).map_err(|e| write_err(&path)(e.error))?;
    sync_dir(dir)?;
    Ok(path)
}

fn sync_dir(dir: &Path) -> Result<(), ProfileError> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(write_err(dir))
}

impl Spool {
    pub fn new(dir: impl Into<PathBuf>) -> Spool {
        Spool { dir: dir.into() }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Put a passing profile in the spool for `store` (its [`ProfileStore::describe`]); `reason` is
    /// why it could not be committed. Returns the entry's path. The same run spooled twice is one
    /// entry (its file name is the run id).
    pub fn put(
        &self,
        store: &str,
        profile: &super::Profile,
        options: &CommitOptions,
        provenance: &Provenance,
        reason: &str,
    ) -> Result<PathBuf, ProfileError> {
        super::check_passing(profile)?;
        let run_id = &provenance.run_id;
        if run_id.is_empty()
            || !run_id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-')
        {
            return Err(ProfileError::Invalid {
                field: "run_id".into(),
                reason: format!(
                    "'{}' cannot name a spool file (letters, digits and '-' only)",
                    run_id.escape_debug()
                ),
            });
        }
        std::fs::create_dir_all(&self.dir).map_err(write_err(&self.dir))?;
        let document =
            String::from_utf8(to_document(profile)).map_err(|e| ProfileError::Invalid {
                field: "document".into(),
                reason: e.to_string(),
            })?;
        let entry = Entry {
            spool_format: SPOOL_FORMAT,
            store: store.to_string(),
            run_id: run_id.clone(),
            station: provenance.station.clone(),
            report: provenance.report.clone(),
            jump_sigma: options.jump_sigma,
            reason: reason.to_string(),
            document,
            spooled_ns: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)),
        };
        let mut bytes = serde_json::to_vec_pretty(&entry).map_err(|e| ProfileError::Invalid {
            field: "spool entry".into(),
            reason: e.to_string(),
        })?;
        bytes.push(b'\n');
        let path = write_durable(&self.dir, &format!("{run_id}.json"), &bytes)?;
        tracing::info!(path = %path.display(), %store, "profile spooled until the store returns");
        Ok(path)
    }

    /// The entries waiting (files `*.json` directly in the spool; none when it does not exist).
    pub fn entries(&self) -> Result<Vec<PathBuf>, ProfileError> {
        let rd = match std::fs::read_dir(&self.dir) {
            Ok(rd) => rd,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(read_err(&self.dir)(e)),
        };
        let mut out = Vec::new();
        for e in rd {
            let e = e.map_err(read_err(&self.dir))?;
            let path = e.path();
            let name = e.file_name();
            let name = name.to_string_lossy();
            if name.ends_with(".json") && !name.starts_with('.') && path.is_file() {
                out.push(path);
            }
        }
        out.sort();
        Ok(out)
    }

    /// How many profiles wait.
    pub fn depth(&self) -> Result<usize, ProfileError> {
        Ok(self.entries()?.len())
    }

    /// Commit every waiting entry meant for `store`, oldest profile first (see the module docs).
    /// Stops at the first entry that finds the store unreachable. An entry that cannot be read is
    /// moved to `failed/` like one the store refuses.
    pub fn drain(&self, store: &dyn ProfileStore) -> Result<Drained, ProfileError> {
        let mut out = Drained::default();
        let name = store.describe();
        let mut loaded = Vec::new();
        for path in self.entries()? {
            match read_entry(&path) {
                Ok((entry, profile)) => loaded.push((path, entry, profile)),
                Err(e) => {
                    let reason = e.to_string();
                    self.set_aside(&path, &reason)?;
                    out.failed.push((path, reason));
                }
            }
        }
        loaded.sort_by(|a, b| {
            (&a.2.created, a.1.spooled_ns, &a.1.run_id).cmp(&(
                &b.2.created,
                b.1.spooled_ns,
                &b.1.run_id,
            ))
        });
        let total = loaded.len();
        for (i, (path, entry, profile)) in loaded.into_iter().enumerate() {
            if entry.store != name {
                out.waiting += 1;
                continue;
            }
            let provenance = Provenance {
                run_id: entry.run_id.clone(),
                station: entry.station.clone(),
                report: entry.report.clone(),
            };
            let options = CommitOptions {
                jump_sigma: entry.jump_sigma,
            };
            match store.commit_run(&profile, &options, &provenance) {
                Ok(Committed {
                    already_stored,
                    location,
                    ..
                }) => {
                    remove(&path)?;
                    if already_stored {
                        out.already_stored.push(entry.run_id);
                    } else {
                        out.committed.push((entry.run_id, location));
                    }
                }
                Err(e) if e.is_unreachable() => {
                    out.waiting += total - i;
                    out.stopped = Some(e.to_string());
                    break;
                }
                Err(ProfileError::Busy { .. }) => out.waiting += 1,
                Err(e) => {
                    let reason = e.to_string();
                    self.set_aside(&path, &reason)?;
                    out.failed.push((path, reason));
                }
            }
        }
        if !out.committed.is_empty() || !out.already_stored.is_empty() {
            sync_dir(&self.dir)?;
        }
        tracing::info!(
            committed = out.committed.len(),
            already_stored = out.already_stored.len(),
            failed = out.failed.len(),
            waiting = out.waiting,
            spool = %self.dir.display(),
            "spool drained"
        );
        Ok(out)
    }

    /// Move `path` into `failed/` with `<name>.reason` beside it.
    fn set_aside(&self, path: &Path, reason: &str) -> Result<(), ProfileError> {
        let failed = self.dir.join(FAILED);
        std::fs::create_dir_all(&failed).map_err(write_err(&failed))?;
        let file = path.file_name().unwrap_or_default().to_string_lossy();
        write_durable(
            &failed,
            &format!("{file}.reason"),
            format!("{reason}\n").as_bytes(),
        )?;
        let to = failed.join(&*file);
        std::fs::rename(path, &to).map_err(write_err(&to))?;
        tracing::warn!(entry = %to.display(), reason, "spooled profile refused by the store; set aside");
        Ok(())
    }
}

fn remove(path: &Path) -> Result<(), ProfileError> {
    match std::fs::remove_file(path) {
        // another drain (a second process on this station) removed it first
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(write_err(path)(e)),
        _ => Ok(()),
    }
}

fn read_entry(path: &Path) -> Result<(Entry, super::Profile), ProfileError> {
    let bytes = std::fs::read(path).map_err(read_err(path))?;
    let entry: Entry = serde_json::from_slice(&bytes).map_err(|source| ProfileError::Parse {
        path: path.to_path_buf(),
        source,
    })?;
    if entry.spool_format > SPOOL_FORMAT {
        return Err(ProfileError::NewerVersion {
            path: path.to_path_buf(),
            found: u64::from(entry.spool_format),
            supported: SPOOL_FORMAT,
        });
    }
    let profile = parse_document(path, entry.document.as_bytes())?;
    Ok((entry, profile))
}
