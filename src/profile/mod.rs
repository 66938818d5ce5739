//! Per-device profiles: what a passing calibration run leaves behind for one physical camera, stores
//! of them keyed by the camera's identity behind one trait ([`ProfileStore`], [`backend`]) — the
//! crash-safe versioned file store ([`Store`], [`store`]) for one station and PostgreSQL
//! ([`postgres::PgStore`]) for a fleet — and exports that OpenCV, ROS, mrcal and COLMAP load
//! ([`export`]).
//!
//! ## The document
//! A profile is one JSON document: `{"format_version": 1, ...}` followed by the fields of [`Profile`]
//! (the calibration with σ per parameter and the intrinsics' covariance, the device identity, locked
//! controls and capture format, the rig and its content hash, the session and its manifest hash, the QA
//! verdict with every check, the software version, the creation time, and — filled in by the store —
//! how far it moved from the profile it replaced). [`parse_document`] reads the version first: a
//! document from a newer cubecal is refused with [`ProfileError::NewerVersion`], never half-read.
//!
//! ## Identities
//! The identity is the store's key (`usb:046d:0825:SERIAL`, `v4l2:driver:bus:card`, or the name a user
//! gives with `--device-id`). USB serial strings are written by whoever made the camera, so the store
//! treats them as hostile: the folder name is a sanitised prefix plus a hash of the full identity
//! ([`store::folder_name`]), and the raw identity lives only inside the profile. Raw bytes that are not
//! UTF-8 are turned into an identity with [`identity_from_bytes`], which is injective (unlike
//! `from_utf8_lossy`, under which two different serials could collide).
//!
//! ## Change from the previous profile
//! On each commit the store compares the new calibration with the one it replaces ([`compare`]): for
//! every intrinsic estimated in both, `Δ/σ` with `σ = √(σ_prev² + σ_new²)` (the standard deviation of
//! the difference of two independent estimates). Beyond `k·σ` ([`CommitOptions::jump_sigma`]) the change
//! is flagged as a jump: a bumped lens, or the wrong camera on the station. A changed image size or
//! distortion model is also a jump (the numbers are not comparable).

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::calib::report::CalibrationReport;
use crate::capture::v4l2::{ControlSetting, DeviceInfo, Negotiated};
use crate::run::Verdict;

pub mod backend;
pub mod export;
pub mod postgres;
pub mod spool;
pub mod store;

pub use backend::{
    Committed, ProfileStore, Provenance, RolledBack, StoreLocation, open_existing_store, open_store,
};
pub use store::{CommitOptions, CommitOutcome, ListEntry, RollbackOutcome, Store};

/// The document format this cubecal writes and the newest it reads.
pub const FORMAT_VERSION: u32 = 1;

/// Where an identity came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IdentityOrigin {
    /// Read from the device (USB vendor:product:serial, or driver/bus/card).
    Device,
    /// The identity a replayed session recorded.
    Session,
    /// Given by the user (`--device-id`) for image or synthetic runs.
    User,
}

/// Which physical camera a profile belongs to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Identity {
    /// The store key, kept verbatim (it may hold any character; see the module docs).
    pub id: String,
    pub origin: IdentityOrigin,
    /// Driver, card, bus, USB ids and formats when the device was seen.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<DeviceInfo>,
}

/// The rig a calibration was computed with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RigRef {
    pub name: String,
    /// Lower-case hex SHA-256 of the rig description file's bytes.
    pub sha256: String,
}

/// The recorded session a calibration came from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionRef {
    /// The session directory, absolute (the station writes it so; profiles of earlier versions may
    /// hold a path relative to the directory the station ran in).
    pub path: PathBuf,
    /// Lower-case hex SHA-256 of the session's `manifest.json`.
    pub manifest_sha256: String,
}

/// One camera's calibration with everything needed to trust and reproduce it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub identity: Identity,
    pub calibration: CalibrationReport,
    pub verdict: Verdict,
    /// Camera controls locked for the run, as the driver accepted them.
    #[serde(default)]
    pub controls: Vec<ControlSetting>,
    /// The capture format the driver agreed to (absent for image and synthetic runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub format: Option<Negotiated>,
    pub rig: RigRef,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<SessionRef>,
    /// `cubecal` version that wrote the profile.
    pub software_version: String,
    /// Creation time, RFC 3339 in UTC (`2026-11-25T15:04:05Z`, optional fraction of a second).
    pub created: String,
    /// How far this profile moved from the one it replaced; set by [`Store::commit`] (whatever the
    /// caller put here is replaced).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub change: Option<Change>,
}

/// The change of one intrinsic parameter between two profiles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamChange {
    pub name: String,
    pub previous: f64,
    pub current: f64,
    /// `current − previous`.
    pub delta: f64,
    /// `√(σ_prev² + σ_new²)`.
    pub sigma: f64,
    /// `delta / sigma`.
    pub delta_sigma: f64,
    /// The side on which the parameter was fixed, not estimated (`"previous"` or `"current"`): σ is
    /// then the other side's alone, and the row does not count toward a jump (a changed model choice,
    /// such as k3 fixed by the station, is not a moved camera).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fixed: Option<String>,
}

/// How far a profile moved from the previous one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Change {
    /// `created` of the previous profile.
    pub previous_created: String,
    /// SHA-256 of the previous profile document's bytes (lower-case hex).
    pub previous_sha256: String,
    /// Parameters estimated (σ > 0) in at least one profile, in [`crate::camera::PARAM_NAMES`] order
    /// (one fixed on a side is marked [`ParamChange::fixed`]).
    pub params: Vec<ParamChange>,
    /// Largest `|Δ/σ|` over `params` (0 when there are none).
    pub max_abs_delta_sigma: f64,
    /// The threshold `k` the change was judged with.
    pub jump_sigma: f64,
    /// Whether any `|Δ/σ|` exceeded `k`, or the image size or distortion model changed.
    pub jump: bool,
    /// Why parts could not be compared (image size or model changed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

/// Errors from profiles and the profile store.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    /// The run's verdict failed: a failing calibration never replaces a profile. Nothing was written.
    #[error("profile for '{}' not stored: the calibration was rejected by quality checks ({})", .identity.escape_debug(), .failures.join(", "))]
    Rejected {
        identity: String,
        failures: Vec<String>,
    },
    /// Another process holds the device's lock (another station is writing this camera).
    #[error("profile store for '{}' is busy: another process holds {}; retry when it has finished", .identity.escape_debug(), .lock.display())]
    Busy { identity: String, lock: PathBuf },
    /// Reading a file or directory failed.
    #[error("cannot read {}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Writing, syncing or renaming failed (disk full, read-only, I/O error). The previous profile is
    /// intact.
    #[error("cannot write {}; the previous profile is unchanged", .path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A profile document is not valid JSON of the expected shape.
    #[error("{}: not a valid profile document", .path.display())]
    Parse {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    /// A document written by a newer cubecal.
    #[error("{}: profile format version {found} is newer than this cubecal reads ({supported}); upgrade cubecal", .path.display())]
    NewerVersion {
        path: PathBuf,
        found: u64,
        supported: u32,
    },
    /// The profile to store is not usable (empty identity, non-finite numbers, bad time …).
    #[error("invalid profile: {field}: {reason}")]
    Invalid { field: String, reason: String },
    /// A device folder holds a profile of a different identity (a hash collision or a tampered store).
    #[error("{}: holds the profile of '{}', not of '{}'; refusing to mix two cameras", .folder.display(), .stored.escape_debug(), .requested.escape_debug())]
    Collision {
        folder: PathBuf,
        stored: String,
        requested: String,
    },
    /// No profile for this device in the store.
    #[error("no profile for '{}' in {}", .device.escape_debug(), .store.display())]
    NotFound { device: String, store: PathBuf },
    /// The store directory does not exist (a typo, or no run has stored a profile there yet).
    #[error("no profile store at {}: the directory does not exist (`cubecal calibrate --store {}` creates it with the first passing run)", .store.display(), .store.display())]
    NoStore { store: PathBuf },
    /// Rollback asked for, but there is no earlier profile.
    #[error("no earlier profile of '{}' to roll back to", .identity.escape_debug())]
    NoHistory { identity: String },
    /// The database cannot be reached, or refused or failed a statement. Nothing was committed.
    #[error("profile store {store}: {action} failed")]
    Database {
        store: String,
        action: String,
        #[source]
        source: ::postgres::Error,
    },
    /// The store cannot be used as given: a password in its URL, a schema not yet migrated or newer
    /// than this cubecal knows.
    #[error("profile store {store}: {reason}")]
    Unusable { store: String, reason: String },
}

impl ProfileError {
    /// Whether the store could not be reached (the connection refused, reset, closed or timed out; the
    /// server shutting down, crashed or still recovering): the profile may wait in the
    /// [`spool`] and be committed later. A refusal by a reachable store (a role without the right,
    /// a schema to migrate, an invalid profile) is not.
    pub fn is_unreachable(&self) -> bool {
        let ProfileError::Database { source, .. } = self else {
            return false;
        };
        if let Some(code) = source.code() {
            let c = code.code();
            // class 08: connection exception; 57P01–57P03: admin/crash shutdown, cannot connect now
            return c.starts_with("08") || matches!(c, "57P01" | "57P02" | "57P03");
        }
        if source.is_closed() || source.to_string() == "timeout waiting for server" {
            return true;
        }
        let mut cause = std::error::Error::source(source);
        while let Some(e) = cause {
            if e.is::<std::io::Error>() {
                return true;
            }
            cause = e.source();
        }
        false
    }

    /// The documented exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            ProfileError::Rejected { .. } => crate::exit::QA_REJECTED,
            ProfileError::Busy { .. } => crate::exit::DEVICE,
            ProfileError::Write { .. } => crate::exit::INTERNAL,
            ProfileError::Database { .. } => crate::exit::IO,
            ProfileError::Unusable { .. } => crate::exit::BAD_INPUT,
            ProfileError::Read { .. }
            | ProfileError::Parse { .. }
            | ProfileError::NewerVersion { .. }
            | ProfileError::Invalid { .. }
            | ProfileError::Collision { .. }
            | ProfileError::NotFound { .. }
            | ProfileError::NoStore { .. }
            | ProfileError::NoHistory { .. } => crate::exit::BAD_INPUT,
        }
    }
}

/// `e` and its causes in one line (`a: b: c`), for messages kept in files and notes.
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut parts = vec![e.to_string()];
    let mut cause = e.source();
    while let Some(c) = cause {
        parts.push(c.to_string());
        cause = c.source();
    }
    parts.join(": ")
}

#[derive(Serialize)]
struct DocumentOut<'a> {
    format_version: u32,
    #[serde(flatten)]
    profile: &'a Profile,
}

#[derive(Deserialize)]
struct DocumentIn {
    #[allow(dead_code)]
    format_version: u32,
    #[serde(flatten)]
    profile: Profile,
}

/// The document's bytes: pretty JSON with `format_version` first and a final newline.
pub fn to_document(profile: &Profile) -> Vec<u8> {
    let doc = DocumentOut {
        format_version: FORMAT_VERSION,
        profile,
    };
    // Serialising plain data with string keys cannot fail; an error would be a bug in our types.
    let mut bytes = serde_json::to_vec_pretty(&doc).unwrap_or_default();
    bytes.push(b'\n');
    bytes
}

/// Parse a profile document; `path` names it in errors. A newer `format_version` is refused before
/// anything else is read.
pub fn parse_document(path: &std::path::Path, bytes: &[u8]) -> Result<Profile, ProfileError> {
    let parse = |source| ProfileError::Parse {
        path: path.to_path_buf(),
        source,
    };
    let value: serde_json::Value = serde_json::from_slice(bytes).map_err(parse)?;
    if let Some(found) = value.get("format_version").and_then(|v| v.as_u64())
        && found > u64::from(FORMAT_VERSION)
    {
        return Err(ProfileError::NewerVersion {
            path: path.to_path_buf(),
            found,
            supported: FORMAT_VERSION,
        });
    }
    let doc: DocumentIn = serde_json::from_value(value).map_err(parse)?;
    Ok(doc.profile)
}

/// Read and parse a profile document file.
pub fn read_document(path: &std::path::Path) -> Result<Profile, ProfileError> {
    let bytes = std::fs::read(path).map_err(|source| ProfileError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_document(path, &bytes)
}

/// An identity string from raw bytes (e.g. a USB serial read from sysfs): valid UTF-8 is kept, every
/// byte of an invalid sequence becomes `\xNN`, and `\` becomes `\\`, so that distinct byte strings give
/// distinct identities.
pub fn identity_from_bytes(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len());
    for chunk in bytes.utf8_chunks() {
        for c in chunk.valid().chars() {
            if c == '\\' {
                out.push_str("\\\\");
            } else {
                out.push(c);
            }
        }
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    out
}

/// An identity as it is safe to show on a terminal: control characters, quotes and backslashes
/// escaped (Rust's `escape_debug`).
pub fn display_identity(id: &str) -> String {
    id.escape_debug().to_string()
}

/// Current UTC time as RFC 3339 with seconds (`2026-11-25T15:04:05Z`).
///
/// Hand-written (days → civil date, H. Hinnant's algorithm) rather than pulling a date-time crate in
/// for one formatting call.
pub fn now_rfc3339() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    rfc3339_from_unix(secs)
}

/// `secs` since the Unix epoch as RFC 3339 UTC.
pub fn rfc3339_from_unix(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// Whether `s` has the shape `YYYY-MM-DDTHH:MM:SS[.fraction]Z` with fields in range.
pub fn is_rfc3339_utc(s: &str) -> bool {
    let b = s.as_bytes();
    let digits = |r: std::ops::Range<usize>| {
        b.get(r.clone())
            .filter(|d| d.iter().all(u8::is_ascii_digit))
            .map(|d| {
                d.iter()
                    .fold(0u32, |acc, &c| acc * 10 + u32::from(c - b'0'))
            })
    };
    let sep = |i: usize, c: u8| b.get(i) == Some(&c);
    let (Some(_year), Some(mon), Some(day), Some(h), Some(m), Some(sec)) = (
        digits(0..4),
        digits(5..7),
        digits(8..10),
        digits(11..13),
        digits(14..16),
        digits(17..19),
    ) else {
        return false;
    };
    if !(sep(4, b'-') && sep(7, b'-') && sep(10, b'T') && sep(13, b':') && sep(16, b':')) {
        return false;
    }
    let tail = &b[19..];
    let tail_ok = match tail {
        [b'Z'] => true,
        [b'.', rest @ .., b'Z'] => !rest.is_empty() && rest.iter().all(u8::is_ascii_digit),
        _ => false,
    };
    tail_ok && (1..=12).contains(&mon) && (1..=31).contains(&day) && h < 24 && m < 60 && sec < 61
}

/// Distortion coefficient names in OpenCV order.
const DISTORTION_NAMES: [&str; 8] = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"];

/// The names of a stored model's coefficients, in the order the document lists them: the model's own
/// ([`crate::camera::DistortionModel::coefficient_names`]: kb4's are `k1, k2, k3, k4`, the names its σ
/// is stored under), or OpenCV's order for a model this cubecal does not know.
pub fn coefficient_names(model: &str) -> Vec<&'static str> {
    match model.parse::<crate::camera::DistortionModel>() {
        Ok(m) => m.coefficient_names().collect(),
        Err(_) => DISTORTION_NAMES.to_vec(),
    }
}

/// The intrinsic values of a calibration by name (`fx, fy, cx, cy, skew` and the model's coefficients).
pub fn intrinsic_values(c: &CalibrationReport) -> BTreeMap<&'static str, f64> {
    let k = &c.camera_matrix;
    let mut out = BTreeMap::from([
        ("fx", k[0][0]),
        ("fy", k[1][1]),
        ("cx", k[0][2]),
        ("cy", k[1][2]),
        ("skew", k[0][1]),
    ]);
    for (name, v) in coefficient_names(&c.distortion.model)
        .into_iter()
        .zip(&c.distortion.coefficients)
    {
        out.insert(name, *v);
    }
    out
}

/// Compare `current` with `previous` (see the module docs); `previous_sha256` names the previous
/// document.
pub fn compare(
    previous: &Profile,
    previous_sha256: &str,
    current: &Profile,
    jump_sigma: f64,
) -> Change {
    let (a, b) = (&previous.calibration, &current.calibration);
    let mut notes = Vec::new();
    if a.image_size != b.image_size {
        notes.push(format!(
            "image size changed from {}x{} to {}x{}",
            a.image_size[0], a.image_size[1], b.image_size[0], b.image_size[1]
        ));
    }
    if a.distortion.model != b.distortion.model {
        notes.push(format!(
            "distortion model changed from {} to {}",
            a.distortion.model, b.distortion.model
        ));
    }
    let (va, vb) = (intrinsic_values(a), intrinsic_values(b));
    let params: Vec<ParamChange> = crate::camera::PARAM_NAMES
        .iter()
        .filter_map(|&name| {
            let (prev, cur) = (*va.get(name)?, *vb.get(name)?);
            // A parameter without σ (or σ = 0) was fixed on that side; estimated on neither, it is
            // not compared.
            let estimated = |c: &CalibrationReport| {
                c.std_dev
                    .get(name)
                    .copied()
                    .filter(|s| *s > 0.0 && s.is_finite())
            };
            let (sa, sb) = (estimated(a), estimated(b));
            let fixed = match (sa, sb) {
                (None, None) => return None,
                (None, Some(_)) => Some("previous".to_string()),
                (Some(_), None) => Some("current".to_string()),
                (Some(_), Some(_)) => None,
            };
            let (sa, sb) = (sa.unwrap_or(0.0), sb.unwrap_or(0.0));
            let sigma = (sa * sa + sb * sb).sqrt();
            Some(ParamChange {
                name: name.to_string(),
                previous: prev,
                current: cur,
                delta: cur - prev,
                sigma,
                delta_sigma: (cur - prev) / sigma,
                fixed,
            })
        })
        .collect();
    let max_abs_delta_sigma = params
        .iter()
        .filter(|p| p.fixed.is_none())
        .map(|p| p.delta_sigma.abs())
        .fold(0.0, f64::max);
    Change {
        previous_created: previous.created.clone(),
        previous_sha256: previous_sha256.to_string(),
        jump: !notes.is_empty() || !(max_abs_delta_sigma <= jump_sigma),
        params,
        max_abs_delta_sigma,
        jump_sigma,
        notes,
    }
}

/// Refuse a failing run before any store is touched: a failed run never replaces a passing profile.
pub fn check_passing(profile: &Profile) -> Result<(), ProfileError> {
    if profile.verdict.pass {
        return Ok(());
    }
    let failures: Vec<String> = profile.verdict.failures().map(|c| c.name.clone()).collect();
    Err(ProfileError::Rejected {
        identity: profile.identity.id.clone(),
        failures: if failures.is_empty() {
            vec!["no checks".to_string()]
        } else {
            failures
        },
    })
}

/// The document a store commits: `profile` with its [`Change`] from `previous` (its document bytes and
/// parsed profile), and the document's bytes. Refused as [`ProfileError::Invalid`] when the document
/// does not survive a JSON round trip; `path` names it in that check's parse errors. Every store
/// commits through this, so the stored bytes are the same whichever store holds them.
pub fn prepare_document(
    path: &std::path::Path,
    profile: &Profile,
    previous: Option<(&[u8], &Profile)>,
    options: &CommitOptions,
) -> Result<(Profile, Vec<u8>), ProfileError> {
    let mut doc = profile.clone();
    doc.change = previous
        .map(|(bytes, prev)| compare(prev, &store::sha256_hex(bytes), profile, options.jump_sigma));
    let bytes = to_document(&doc);
    if parse_document(path, &bytes).ok().as_ref() != Some(&doc) {
        return Err(ProfileError::Invalid {
            field: "profile".into(),
            reason: "does not survive a JSON round trip (a NaN or infinite σ or covariance?)"
                .into(),
        });
    }
    Ok((doc, bytes))
}

/// Check what the store relies on: a non-empty identity, finite intrinsics, a positive image size, a
/// known distortion model with its number of coefficients, an RFC 3339 UTC time.
pub fn validate(profile: &Profile) -> Result<(), ProfileError> {
    let invalid = |field: &str, reason: String| {
        Err(ProfileError::Invalid {
            field: field.to_string(),
            reason,
        })
    };
    if profile.identity.id.is_empty() {
        return invalid("identity.id", "empty".into());
    }
    let c = &profile.calibration;
    if c.image_size[0] == 0 || c.image_size[1] == 0 {
        return invalid(
            "calibration.image_size",
            format!("{}x{}", c.image_size[0], c.image_size[1]),
        );
    }
    if let Some(v) = c.camera_matrix.iter().flatten().find(|v| !v.is_finite()) {
        return invalid("calibration.camera_matrix", format!("not finite ({v})"));
    }
    if let Some(v) = c.distortion.coefficients.iter().find(|v| !v.is_finite()) {
        return invalid("calibration.distortion", format!("not finite ({v})"));
    }
    match c.distortion.model.parse::<crate::camera::DistortionModel>() {
        Ok(m) if m.n_coefficients() == c.distortion.coefficients.len() => {}
        Ok(m) => {
            return invalid(
                "calibration.distortion",
                format!(
                    "{} has {} coefficients, not {}",
                    m.name(),
                    m.n_coefficients(),
                    c.distortion.coefficients.len()
                ),
            );
        }
        Err(e) => return invalid("calibration.distortion.model", e.to_string()),
    }
    if !is_rfc3339_utc(&profile.created) {
        return invalid(
            "created",
            format!(
                "'{}' is not RFC 3339 UTC (e.g. 2026-11-25T15:04:05Z)",
                profile.created.escape_debug()
            ),
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc3339_matches_known_dates() {
        assert_eq!(rfc3339_from_unix(0), "1970-01-01T00:00:00Z");
        // 2000-02-29 (a leap day) 12:34:56 UTC
        assert_eq!(rfc3339_from_unix(951_827_696), "2000-02-29T12:34:56Z");
        // 2026-11-25T15:04:05Z
        assert_eq!(rfc3339_from_unix(1_795_619_045), "2026-11-25T15:04:05Z");
        assert!(is_rfc3339_utc(&now_rfc3339()));
        assert!(is_rfc3339_utc("2026-11-25T15:04:05.123Z"));
        for bad in [
            "",
            "2026-11-25 15:04:05Z",
            "2026-11-25T15:04:05",
            "2026-11-25T15:04:05+01:00",
            "2026-13-25T15:04:05Z",
            "2026-11-25T15:04:05.Z",
            "2026-11-25T15:04:05Zjunk",
        ] {
            assert!(!is_rfc3339_utc(bad), "{bad}");
        }
    }

    #[test]
    fn identity_from_bytes_is_injective_on_tricky_inputs() {
        let inputs: [&[u8]; 6] = [
            b"abc",
            b"a\\xffb",
            b"a\xffb",
            b"a\\\xffb",
            b"\xc3\xa9",
            b"\xc3",
        ];
        let ids: Vec<String> = inputs.iter().map(|b| identity_from_bytes(b)).collect();
        assert_eq!(ids[0], "abc");
        assert_eq!(ids[2], "a\\xffb");
        assert_eq!(ids[4], "é");
        let unique: std::collections::BTreeSet<&String> = ids.iter().collect();
        assert_eq!(unique.len(), ids.len(), "{ids:?}");
    }
}
