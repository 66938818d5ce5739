//! The profile store: one folder per camera, `current.json` plus `history/`, crash-safe writes and a
//! lock per camera.
//!
//! ```text
//! STORE/
//!   usb_046d_0825_A1B2-3f9c…/          folder_name(identity): sanitised prefix + hash of the identity
//!     lock                             flock(2)-locked by the one writer of this camera
//!     current.json                     the profile in use
//!     history/000001-20261125T150405Z-9a0b1c2d3e4f.json    profiles it replaced, oldest first
//!     rolled-back/…                    profiles a rollback took out of use
//! ```
//!
//! ## Why a commit cannot tear or lose a profile
//! Every file is written as a temporary file in its final directory, `fsync`ed, renamed over its name
//! and the directory `fsync`ed (rename is atomic on POSIX file systems). A commit first *copies* the old
//! `current.json` into `history/` and only then renames the new one over it, so at every instant
//! `current.json` is one complete version, old or new; a crash between the two steps leaves a history
//! copy of the still-current profile, which the next commit recognises and does not duplicate. A failed
//! write removes its temporary file and reports [`ProfileError::Write`]; `current.json` is untouched.
//! Temporary files a killed writer left behind are deleted by the next writer (which holds the lock).
//!
//! ## Locking
//! `lock` is locked with `flock(2)` through [`std::fs::File::try_lock`]: the lock is released by the
//! kernel when its holder dies, so a killed station never leaves a stale lock, and a second writer gets
//! [`ProfileError::Busy`] at once instead of waiting or interleaving.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::Serialize;
use sha2::{Digest, Sha256};

use super::{
    Change, Profile, ProfileError, check_passing, parse_document, prepare_document, validate,
};

/// The current profile's file name.
pub const CURRENT: &str = "current.json";
/// The folder of replaced profiles.
pub const HISTORY: &str = "history";
/// The folder of profiles a rollback took out of use.
pub const ROLLED_BACK: &str = "rolled-back";
/// The lock file's name.
pub const LOCK: &str = "lock";
/// Prefix of temporary files (never a valid profile name).
const TMP_PREFIX: &str = ".tmp-";
/// Longest readable prefix of a folder name (the hash follows).
const READABLE_MAX: usize = 48;

/// How a commit judges the change from the previous profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommitOptions {
    /// A parameter moving more than this many σ (of the difference) flags a jump.
    pub jump_sigma: f64,
}

impl Default for CommitOptions {
    fn default() -> Self {
        CommitOptions { jump_sigma: 5.0 }
    }
}

/// What a commit did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CommitOutcome {
    /// The camera's folder.
    pub folder: PathBuf,
    /// The new `current.json`.
    pub current: PathBuf,
    /// Where the replaced profile now lives (`None` for a camera's first profile).
    pub archived: Option<PathBuf>,
    /// The change from the replaced profile (as stored in the new one).
    pub change: Option<Change>,
    /// Whether the change is a jump (see [`Change::jump`]); false for a first profile.
    pub jump: bool,
}

/// What a rollback did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RollbackOutcome {
    pub folder: PathBuf,
    /// `created` of the profile now current again.
    pub restored_created: String,
    /// `created` of the profile taken out of use.
    pub replaced_created: String,
    /// Where the replaced profile was kept.
    pub set_aside: PathBuf,
}

/// A summary of one camera in the store.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// The raw identity (escape it before printing: [`super::display_identity`]).
    pub identity: String,
    pub created: String,
    pub model: String,
    pub rms_px: f64,
    /// Number of earlier profiles in `history/`.
    pub history: usize,
    /// Whether the current profile jumped from its predecessor.
    pub jump: bool,
}

/// One folder of the store.
#[derive(Debug)]
pub struct ListEntry {
    /// The folder's name inside the store.
    pub folder: String,
    pub summary: Result<Summary, ProfileError>,
}

/// A held device lock; dropping it releases the lock.
#[derive(Debug)]
pub struct DeviceLock {
    _file: std::fs::File,
    path: PathBuf,
}

impl DeviceLock {
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// A profile store rooted at one directory.
#[derive(Debug)]
pub struct Store {
    root: PathBuf,
    /// Bytes that may still be written before writes fail with "no space left" (fault injection for
    /// tests; `u64::MAX` means no limit).
    write_budget: AtomicU64,
}

/// Lower-case hex SHA-256.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The folder name of an identity: up to 48 characters of it with everything outside
/// `[A-Za-z0-9._-]` replaced by `_` (and no leading `.`), then `-` and 32 hex digits of its SHA-256.
/// The hash makes names of distinct identities distinct (up to a 2⁻¹²⁸ collision, which the store
/// still detects: see [`ProfileError::Collision`]); the prefix only helps people find a camera.
pub fn folder_name(identity: &str) -> String {
    let mut readable: String = identity
        .chars()
        .take(READABLE_MAX)
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if readable.starts_with('.') {
        readable.replace_range(0..1, "_");
    }
    let hash = sha256_hex(identity.as_bytes());
    format!("{readable}-{}", &hash[..32])
}

pub(super) fn write_err(path: &Path) -> impl FnOnce(std::io::Error) -> ProfileError + '_ {
    move |source| ProfileError::Write {
        path: path.to_path_buf(),
        source,
    }
}

pub(super) fn read_err(path: &Path) -> impl FnOnce(std::io::Error) -> ProfileError + '_ {
    move |source| ProfileError::Read {
        path: path.to_path_buf(),
        source,
    }
}

fn sync_dir(dir: &Path) -> Result<(), ProfileError> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(write_err(dir))
}

/// `2026-11-25T15:04:05.5Z` → `20261125T150405.5Z` (file-name friendly, still sortable).
fn compact_time(created: &str) -> String {
    created
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || *c == '.')
        .take(32)
        .collect()
}

/// The sequence number a history file name starts with.
fn history_seq(name: &str) -> Option<u64> {
    let (seq, rest) = name.split_once('-')?;
    (rest.ends_with(".json") && !seq.is_empty() && seq.bytes().all(|b| b.is_ascii_digit()))
        .then(|| seq.parse().ok())
        .flatten()
}

impl Store {
    /// Open (and create if missing) the store at `dir`.
    pub fn open(dir: &Path) -> Result<Store, ProfileError> {
        std::fs::create_dir_all(dir).map_err(write_err(dir))?;
        Ok(Store {
            root: dir.to_path_buf(),
            write_budget: AtomicU64::new(u64::MAX),
        })
    }

    /// Open a store that must already exist (for reading and managing it): a missing directory is
    /// [`ProfileError::NoStore`] naming it, never silently an empty store.
    pub fn open_existing(dir: &Path) -> Result<Store, ProfileError> {
        if !dir.is_dir() {
            return Err(ProfileError::NoStore {
                store: dir.to_path_buf(),
            });
        }
        Store::open(dir)
    }

    /// The store's directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Fault injection for tests: after `bytes` more bytes, every write fails as on a full disk
    /// (`io::ErrorKind::StorageFull`), part-way through a file.
    #[doc(hidden)]
    pub fn fail_writes_after(self, bytes: u64) -> Store {
        self.write_budget.store(bytes, Ordering::SeqCst);
        self
    }

    /// The folder of an identity (whether or not it exists).
    pub fn device_dir(&self, identity: &str) -> PathBuf {
        self.root.join(folder_name(identity))
    }

    /// Take the lock of `identity`'s folder (created if missing): [`ProfileError::Busy`] if another
    /// process (or another open of the store in this one) holds it.
    pub fn lock(&self, identity: &str) -> Result<DeviceLock, ProfileError> {
        let folder = self.device_dir(identity);
        std::fs::create_dir_all(&folder).map_err(write_err(&folder))?;
        self.lock_folder(&folder, identity)
    }

    fn lock_folder(&self, folder: &Path, identity: &str) -> Result<DeviceLock, ProfileError> {
        let path = folder.join(LOCK);
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(write_err(&path))?;
        match file.try_lock() {
            Ok(()) => Ok(DeviceLock { _file: file, path }),
            Err(std::fs::TryLockError::WouldBlock) => Err(ProfileError::Busy {
                identity: identity.to_string(),
                lock: path,
            }),
            Err(std::fs::TryLockError::Error(source)) => Err(ProfileError::Write { path, source }),
        }
    }

    /// Write `bytes` to `dir/name` atomically (temporary file, fsync, rename, fsync of `dir`).
    fn atomic_write(&self, dir: &Path, name: &str, bytes: &[u8]) -> Result<PathBuf, ProfileError> {
        let target = dir.join(name);
        let mut tmp = tempfile::Builder::new()
            .prefix(TMP_PREFIX)
            .tempfile_in(dir)
            .map_err(write_err(dir))?;
        let tmp_path = tmp.path().to_path_buf();
        self.write_limited(tmp.as_file_mut(), bytes)
            .and_then(|()| tmp.as_file().sync_all())
            .map_err(write_err(&tmp_path))?;
        tmp.persist(&target)
            .map_err(|e| write_err(&target)(e.error))?;
        sync_dir(dir)?;
        Ok(target)
    }

    fn write_limited(&self, file: &mut std::fs::File, bytes: &[u8]) -> std::io::Result<()> {
        let len = bytes.len() as u64;
        let budget = self
            .write_budget
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |b| {
                Some(if b == u64::MAX {
                    b
                } else {
                    b.saturating_sub(len)
                })
            })
            .unwrap_or(u64::MAX);
        if budget >= len {
            return file.write_all(bytes);
        }
        // usize::try_from cannot fail: budget < len = bytes.len()
        let part = usize::try_from(budget).unwrap_or(0);
        file.write_all(&bytes[..part])?;
        Err(std::io::Error::new(
            std::io::ErrorKind::StorageFull,
            "no space left on device (injected)",
        ))
    }

    /// Delete temporary files a killed writer left in `dir` (caller holds the lock).
    fn remove_stale_temps(dir: &Path) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            if e.file_name().to_string_lossy().starts_with(TMP_PREFIX) {
                match std::fs::remove_file(e.path()) {
                    Ok(()) => {
                        tracing::debug!(path = %e.path().display(), "removed stale temporary file")
                    }
                    Err(err) => {
                        tracing::warn!(path = %e.path().display(), %err, "cannot remove stale temporary file")
                    }
                }
            }
        }
    }

    /// Read `folder/current.json` if it exists and check it belongs to `identity`.
    fn read_current(
        folder: &Path,
        identity: &str,
    ) -> Result<Option<(Vec<u8>, Profile)>, ProfileError> {
        let path = folder.join(CURRENT);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(read_err(&path)(e)),
        };
        let profile = parse_document(&path, &bytes)?;
        if profile.identity.id != identity {
            return Err(ProfileError::Collision {
                folder: folder.to_path_buf(),
                stored: profile.identity.id,
                requested: identity.to_string(),
            });
        }
        Ok(Some((bytes, profile)))
    }

    /// History files of a folder, oldest first: (sequence number, path).
    fn history_files(folder: &Path) -> Result<Vec<(u64, PathBuf)>, ProfileError> {
        let dir = folder.join(HISTORY);
        let entries = match std::fs::read_dir(&dir) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(read_err(&dir)(e)),
        };
        let mut out = Vec::new();
        for e in entries {
            let e = e.map_err(read_err(&dir))?;
            if let Some(seq) = e.file_name().to_str().and_then(history_seq) {
                out.push((seq, e.path()));
            }
        }
        out.sort();
        Ok(out)
    }

    /// Copy the replaced profile into `history/` (unless the newest entry already is that profile,
    /// left by a commit that crashed before replacing `current.json`).
    fn archive(&self, folder: &Path, bytes: &[u8], created: &str) -> Result<PathBuf, ProfileError> {
        let history = Self::history_files(folder)?;
        if let Some((_, newest)) = history.last()
            && std::fs::read(newest).map_err(read_err(newest))? == bytes
        {
            return Ok(newest.clone());
        }
        let seq = history.last().map_or(1, |(s, _)| s + 1);
        let name = format!(
            "{seq:06}-{}-{}.json",
            compact_time(created),
            &sha256_hex(bytes)[..12]
        );
        self.atomic_write(&folder.join(HISTORY), &name, bytes)
    }

    /// Store a passing profile as its camera's `current.json`, keeping the previous one in history.
    ///
    /// A failing verdict is refused with [`ProfileError::Rejected`] before anything is touched; a camera
    /// another process is writing gives [`ProfileError::Busy`]. The stored profile's `change` is the
    /// comparison with the profile it replaces.
    pub fn commit(
        &self,
        profile: &Profile,
        options: &CommitOptions,
    ) -> Result<CommitOutcome, ProfileError> {
        let identity = profile.identity.id.as_str();
        check_passing(profile)?;
        validate(profile)?;
        let folder = self.device_dir(identity);
        let history = folder.join(HISTORY);
        std::fs::create_dir_all(&history).map_err(write_err(&history))?;
        let _lock = self.lock_folder(&folder, identity)?;
        Self::remove_stale_temps(&folder);
        Self::remove_stale_temps(&history);

        let current = folder.join(CURRENT);
        let previous = Self::read_current(&folder, identity)?;
        let (doc, bytes) = prepare_document(
            &current,
            profile,
            previous.as_ref().map(|(b, p)| (b.as_slice(), p)),
            options,
        )?;
        let archived = match &previous {
            Some((pbytes, prev)) => Some(self.archive(&folder, pbytes, &prev.created)?),
            None => None,
        };
        self.atomic_write(&folder, CURRENT, &bytes)?;
        tracing::info!(folder = %folder.display(), "profile committed");
        let jump = doc.change.as_ref().is_some_and(|c| c.jump);
        Ok(CommitOutcome {
            folder,
            current,
            archived,
            change: doc.change,
            jump,
        })
    }

    /// The folder a user's `DEVICE` argument names: an identity, or else a folder name in the store.
    /// The identity is tried first, so an identity crafted to look like another camera's folder name
    /// cannot stand for that camera when its own profile exists.
    pub fn resolve(&self, device: &str) -> Result<PathBuf, ProfileError> {
        let by_identity = self.device_dir(device);
        if by_identity.join(CURRENT).is_file() {
            return Ok(by_identity);
        }
        let is_plain_name =
            !device.is_empty() && device != "." && device != ".." && !device.contains(['/', '\0']);
        if is_plain_name {
            let direct = self.root.join(device);
            if direct.join(CURRENT).is_file() {
                return Ok(direct);
            }
        }
        Err(ProfileError::NotFound {
            device: device.to_string(),
            store: self.root.clone(),
        })
    }

    /// Read a folder's current profile and check that it belongs there.
    fn load_folder(folder: &Path) -> Result<(Vec<u8>, Profile), ProfileError> {
        let path = folder.join(CURRENT);
        let bytes = std::fs::read(&path).map_err(read_err(&path))?;
        let profile = parse_document(&path, &bytes)?;
        let expected = folder_name(&profile.identity.id);
        if folder.file_name().and_then(|n| n.to_str()) != Some(expected.as_str()) {
            return Err(ProfileError::Collision {
                folder: folder.to_path_buf(),
                stored: profile.identity.id,
                requested: folder
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            });
        }
        Ok((bytes, profile))
    }

    /// The current profile of `device` (folder name or identity) and its document bytes.
    pub fn current(&self, device: &str) -> Result<(Profile, Vec<u8>), ProfileError> {
        let (bytes, profile) = Self::load_folder(&self.resolve(device)?)?;
        Ok((profile, bytes))
    }

    /// Earlier profiles of `device`, oldest first.
    pub fn history(&self, device: &str) -> Result<Vec<PathBuf>, ProfileError> {
        let folder = self.resolve(device)?;
        Ok(Self::history_files(&folder)?
            .into_iter()
            .map(|(_, p)| p)
            .collect())
    }

    /// Every camera folder with a current profile, by folder name.
    pub fn list(&self) -> Result<Vec<ListEntry>, ProfileError> {
        let entries = std::fs::read_dir(&self.root).map_err(read_err(&self.root))?;
        let mut out = Vec::new();
        for e in entries {
            let e = e.map_err(read_err(&self.root))?;
            let path = e.path();
            if !path.join(CURRENT).is_file() {
                continue;
            }
            let summary = Self::load_folder(&path).and_then(|(_, p)| {
                Ok(Summary {
                    history: Self::history_files(&path)?.len(),
                    identity: p.identity.id,
                    created: p.created,
                    model: p.calibration.distortion.model,
                    rms_px: p.calibration.rms_px,
                    jump: p.change.is_some_and(|c| c.jump),
                })
            });
            out.push(ListEntry {
                folder: e.file_name().to_string_lossy().into_owned(),
                summary,
            });
        }
        out.sort_by(|a, b| a.folder.cmp(&b.folder));
        Ok(out)
    }

    /// Make the newest earlier profile of `device` current again; the replaced one is kept in
    /// `rolled-back/` (and is not a rollback candidate itself, so rolling back twice goes two steps
    /// back).
    pub fn rollback(&self, device: &str) -> Result<RollbackOutcome, ProfileError> {
        let folder = self.resolve(device)?;
        let (cur_bytes, cur) = Self::load_folder(&folder)?;
        let identity = cur.identity.id.clone();
        let _lock = self.lock_folder(&folder, &identity)?;
        // re-read under the lock: a commit may have finished in between
        let (cur_bytes, cur) = match Self::read_current(&folder, &identity)? {
            Some(c) => c,
            None => (cur_bytes, cur),
        };
        let history_dir = folder.join(HISTORY);
        let (restore_path, restore_bytes) = loop {
            let Some((_, newest)) = Self::history_files(&folder)?.pop() else {
                return Err(ProfileError::NoHistory { identity });
            };
            let bytes = std::fs::read(&newest).map_err(read_err(&newest))?;
            if bytes != cur_bytes {
                break (newest, bytes);
            }
            // a copy of the current profile left by an interrupted commit: not an earlier version
            std::fs::remove_file(&newest).map_err(write_err(&newest))?;
            sync_dir(&history_dir)?;
        };
        let restored = parse_document(&restore_path, &restore_bytes)?;
        if restored.identity.id != identity {
            return Err(ProfileError::Collision {
                folder: folder.clone(),
                stored: restored.identity.id,
                requested: identity,
            });
        }
        let aside_dir = folder.join(ROLLED_BACK);
        std::fs::create_dir_all(&aside_dir).map_err(write_err(&aside_dir))?;
        Self::remove_stale_temps(&aside_dir);
        let aside_name = format!(
            "{}-{}.json",
            compact_time(&cur.created),
            &sha256_hex(&cur_bytes)[..12]
        );
        let set_aside = self.atomic_write(&aside_dir, &aside_name, &cur_bytes)?;
        self.atomic_write(&folder, CURRENT, &restore_bytes)?;
        std::fs::remove_file(&restore_path).map_err(write_err(&restore_path))?;
        sync_dir(&history_dir)?;
        Ok(RollbackOutcome {
            folder,
            restored_created: restored.created,
            replaced_created: cur.created,
            set_aside,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folder_names_are_plain_and_bounded() {
        for id in ["", ".", "..", "../../etc", "a/b", "\0", &"x".repeat(4096)] {
            let name = folder_name(id);
            assert!(!name.starts_with('.'), "{name}");
            assert!(
                name.chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.')),
                "{name}"
            );
            assert!(name.len() <= READABLE_MAX + 33, "{}", name.len());
        }
        assert_ne!(folder_name("a/b"), folder_name("a_b"));
    }

    #[test]
    fn history_names_parse() {
        assert_eq!(history_seq("000012-20261125T150405Z-abc.json"), Some(12));
        assert_eq!(history_seq(".tmp-abc"), None);
        assert_eq!(history_seq("x-1.json"), None);
        assert_eq!(compact_time("2026-11-25T15:04:05.5Z"), "20261125T150405.5Z");
    }
}
