//! The PostgreSQL profile store: every station of a plant commits into one database, and any machine
//! with read access finds a camera's profile by its identity.
//!
//! ## Why the synchronous `postgres` crate
//! cubecal is synchronous throughout: the station loop blocks on the camera and the turntable, `serve`
//! is one run per process, the CLI is one command per process, and a commit is a handful of statements
//! in one transaction. `tokio-postgres` would bring an async runtime into the station's API for no
//! concurrency we could use; the `postgres` crate is the same protocol implementation (it drives
//! `tokio-postgres` on a private current-thread runtime) behind a blocking API that fits the
//! [`ProfileStore`] trait as it is.
//!
//! ## Schema and migrations
//! The schema is versioned in the repository (`migrations/postgres/NNNN_name.sql`, embedded in the
//! binary in [`MIGRATIONS`]) and applied by `cubecal profile migrate` ([`PgStore::migrate`]): each
//! migration not yet recorded in `cubecal_migrations` runs in one transaction with its record, under a
//! transaction-level advisory lock so two migrating machines cannot interleave. [`PgStore::connect`]
//! refuses a database that is not migrated or is migrated further than this cubecal knows.
//!
//! ## The file store's guarantees
//! - A failing verdict is refused before the database is touched ([`super::check_passing`]); the
//!   table's `CHECK (verdict_pass)` refuses one from any other client.
//! - One writer per camera: a commit (and a rollback) first takes `pg_try_advisory_xact_lock` on a
//!   64-bit key hashed from the identity. A second station committing the same camera at that moment
//!   gets [`ProfileError::Busy`] at once, not a wait; the lock ends with the transaction (or with the
//!   connection of a station that died). Two cameras whose keys collide (2⁻⁶⁴) only see a spurious
//!   Busy. A partial unique index keeps at most one current profile per camera regardless.
//! - A commit is one transaction: the previous version becomes `history` and the new one `current`, or
//!   neither (a killed station or database leaves the previous profile current, never a torn one).
//! - History keeps every version's document bytes with the run's provenance (station, rig, software
//!   version, verdict, report) — see [`PgStore::history`].
//! - Identities are data: every statement is a constant with `$n` parameters, and the identity is
//!   stored as bytes (a hostile serial may hold NUL, which PostgreSQL's `text` refuses).
//!
//! The connection is not encrypted (no TLS client is built in): use it on a trusted network or a local
//! socket, or tunnel it.

use std::path::PathBuf;
use std::sync::Mutex;

use postgres::error::SqlState;
use postgres::{Client, NoTls, Row, Statement, ToStatement};
use serde::Serialize;

use super::backend::{Committed, ProfileStore, Provenance, RolledBack};
use super::store::{CommitOptions, ListEntry, Summary, folder_name, sha256_hex};
use super::{Profile, ProfileError, check_passing, parse_document, prepare_document, validate};

/// The schema migrations in order: (version, name, SQL). Version `n` is the `n`-th entry.
pub const MIGRATIONS: &[(i32, &str, &str)] = &[(
    1,
    "profiles",
    include_str!("../../migrations/postgres/0001_profiles.sql"),
)];

/// Advisory-lock key of `cubecal profile migrate` (any constant outside the cameras' hash space use).
const MIGRATE_LOCK: i64 = 0x6375_6265_6361_6c00; // "cubecal\0"

/// A connection to a PostgreSQL profile store.
pub struct PgStore {
    client: Mutex<Client>,
    /// The commit's statements, prepared on `client` at the first commit (halves its round trips).
    commit_statements: Mutex<Option<CommitStatements>>,
    describe: String,
}

/// The statements of a commit, prepared once per connection.
#[derive(Clone)]
struct CommitStatements {
    lock: Statement,
    by_run: Statement,
    current: Statement,
    archive: Statement,
    insert: Statement,
}

const LOCK_SQL: &str = "SELECT pg_try_advisory_xact_lock($1) AS locked";
const CURRENT_SQL: &str =
    "SELECT id, document FROM cubecal_profile WHERE identity = $1 AND state = 'current'";

impl std::fmt::Debug for PgStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PgStore")
            .field("store", &self.describe)
            .finish_non_exhaustive()
    }
}

/// One stored version of a camera's profile with its provenance, oldest first in
/// [`PgStore::history`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Version {
    pub id: i64,
    /// `current`, `history` or `rolled_back`.
    pub state: String,
    pub run_id: String,
    pub station: String,
    pub rig_name: String,
    pub rig_sha256: String,
    pub software_version: String,
    pub verdict_pass: bool,
    pub report: Option<String>,
    pub created: String,
    /// The profile document's SHA-256.
    pub sha256: String,
}

/// The URL as it may be shown: scheme, user, hosts, ports and database, never a password or options.
pub fn redact(url: &str) -> String {
    let (scheme, rest) = url.split_once("://").unwrap_or(("postgres", url));
    let rest = rest.split(['?', '#']).next().unwrap_or_default();
    let rest = match rest.rsplit_once('@') {
        Some((userinfo, host)) => {
            let user = userinfo.split(':').next().unwrap_or_default();
            format!("{user}@{host}")
        }
        None => rest.to_string(),
    };
    format!("{scheme}://{rest}")
}

/// The advisory-lock key of a camera: the first 8 bytes of SHA-256 of the identity (big-endian). An
/// operator finds a station holding a camera in `pg_locks` (`locktype = 'advisory'`) by it.
pub fn camera_key(identity: &str) -> i64 {
    use sha2::{Digest, Sha256};
    let d = Sha256::digest(identity.as_bytes());
    let mut b = [0u8; 8];
    b.copy_from_slice(&d[..8]);
    i64::from_be_bytes(b)
}

/// A provenance or rig string as a `text` column: refused when it holds NUL.
fn text_field<'a>(field: &str, value: &'a str) -> Result<&'a str, ProfileError> {
    if value.contains('\0') {
        return Err(ProfileError::Invalid {
            field: field.to_string(),
            reason: "holds a NUL character".into(),
        });
    }
    Ok(value)
}

impl PgStore {
    /// Connect to the store at `url` (no password in it: see [`super::backend`]) and check its schema
    /// is the one this cubecal knows.
    pub fn connect(url: &str, password: Option<String>) -> Result<PgStore, ProfileError> {
        let store = PgStore::connect_unchecked(url, password)?;
        let applied = store.schema_version()?;
        let known = MIGRATIONS.len() as i32;
        if applied < known {
            return Err(ProfileError::Unusable {
                store: store.describe,
                reason: format!(
                    "database schema is at version {applied}, this cubecal needs {known}: run `cubecal profile migrate --store URL` with a role that may create tables"
                ),
            });
        }
        if applied > known {
            return Err(ProfileError::Unusable {
                store: store.describe,
                reason: format!(
                    "database schema version {applied} is newer than this cubecal knows ({known}); upgrade cubecal"
                ),
            });
        }
        Ok(store)
    }

    /// Connect without checking the schema (what `migrate` needs).
    pub fn connect_unchecked(url: &str, password: Option<String>) -> Result<PgStore, ProfileError> {
        let describe = redact(url);
        let unusable = |reason: String| ProfileError::Unusable {
            store: describe.clone(),
            reason,
        };
        let mut config: postgres::Config = url
            .parse()
            .map_err(|e: postgres::Error| unusable(format!("not a PostgreSQL URL: {e}")))?;
        if config.get_password().is_some() {
            return Err(unusable(
                "the URL holds a password; give it in a file (--store-password-file, output.store_password_file) or PGPASSWORD instead".into(),
            ));
        }
        if let Some(p) = password {
            config.password(p);
        }
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(std::time::Duration::from_secs(5));
        }
        config.application_name("cubecal");
        let client = config
            .connect(NoTls)
            .map_err(|source| ProfileError::Database {
                store: describe.clone(),
                action: "connecting".into(),
                source,
            })?;
        tracing::debug!(store = %describe, "connected to the profile database");
        Ok(PgStore {
            client: Mutex::new(client),
            commit_statements: Mutex::new(None),
            describe,
        })
    }

    fn db_err(&self, action: &str) -> impl FnOnce(postgres::Error) -> ProfileError + '_ {
        let action = action.to_string();
        move |source| ProfileError::Database {
            store: self.describe.clone(),
            action,
            source,
        }
    }

    /// The commit's prepared statements (prepared on `client` the first time).
    fn commit_statements(&self, client: &mut Client) -> Result<CommitStatements, ProfileError> {
        let mut cached = self
            .commit_statements
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some(s) = cached.as_ref() {
            return Ok(s.clone());
        }
        let mut prepare = |sql: &str| {
            client
                .prepare(sql)
                .map_err(self.db_err("preparing the commit"))
        };
        let s = CommitStatements {
            lock: prepare(LOCK_SQL)?,
            by_run: prepare("SELECT id, document FROM cubecal_profile WHERE run_id = $1")?,
            current: prepare(CURRENT_SQL)?,
            archive: prepare("UPDATE cubecal_profile SET state = 'history' WHERE id = $1")?,
            insert: prepare(
                "INSERT INTO cubecal_profile (identity, folder, state, run_id, document, sha256,
                     created, station, rig_name, rig_sha256, software_version, verdict_pass, report)
                 VALUES ($1, $2, 'current', $3, $4, $5, $6, $7, $8, $9, $10, $11, $12)
                 RETURNING id",
            )?,
        };
        *cached = Some(s.clone());
        Ok(s)
    }

    fn client(&self) -> std::sync::MutexGuard<'_, Client> {
        // A panic while holding the lock cannot leave the client half-used in a way that matters:
        // an open transaction is rolled back when it is dropped.
        self.client.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn get<'r, T: postgres::types::FromSql<'r>>(
        &self,
        row: &'r Row,
        column: &str,
    ) -> Result<T, ProfileError> {
        row.try_get(column)
            .map_err(self.db_err(&format!("reading column {column}")))
    }

    /// The highest migration applied (0 for an empty database).
    pub fn schema_version(&self) -> Result<i32, ProfileError> {
        let mut client = self.client();
        match client.query_one("SELECT max(version) AS v FROM cubecal_migrations", &[]) {
            Ok(row) => Ok(self.get::<Option<i32>>(&row, "v")?.unwrap_or(0)),
            Err(e) if e.code() == Some(&SqlState::UNDEFINED_TABLE) => Ok(0),
            Err(e) => Err(self.db_err("reading the schema version")(e)),
        }
    }

    /// Apply the migrations the database lacks; returns the versions applied (empty when it was up
    /// to date).
    pub fn migrate(&self) -> Result<Vec<i32>, ProfileError> {
        let mut client = self.client();
        let mut tx = client
            .transaction()
            .map_err(self.db_err("starting the migration"))?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATE_LOCK])
            .map_err(self.db_err("locking the migration"))?;
        tx.batch_execute(
            "CREATE TABLE IF NOT EXISTS cubecal_migrations (
                version integer PRIMARY KEY,
                name text NOT NULL,
                applied_at timestamptz NOT NULL DEFAULT now())",
        )
        .map_err(self.db_err("creating cubecal_migrations"))?;
        let row = tx
            .query_one("SELECT max(version) AS v FROM cubecal_migrations", &[])
            .map_err(self.db_err("reading the schema version"))?;
        let applied = self.get::<Option<i32>>(&row, "v")?.unwrap_or(0);
        if applied > MIGRATIONS.len() as i32 {
            return Err(ProfileError::Unusable {
                store: self.describe.clone(),
                reason: format!(
                    "database schema version {applied} is newer than this cubecal knows ({}); upgrade cubecal",
                    MIGRATIONS.len()
                ),
            });
        }
        let mut done = Vec::new();
        for &(version, name, sql) in MIGRATIONS.iter().filter(|m| m.0 > applied) {
            // The migration's SQL is the repository's own text, never data.
            tx.batch_execute(sql)
                .map_err(self.db_err(&format!("applying migration {version} ({name})")))?;
            tx.execute(
                "INSERT INTO cubecal_migrations (version, name) VALUES ($1, $2)",
                &[&version, &name],
            )
            .map_err(self.db_err("recording the migration"))?;
            done.push(version);
        }
        tx.commit()
            .map_err(self.db_err("committing the migration"))?;
        tracing::info!(store = %self.describe, applied = ?done, "profile database migrated");
        Ok(done)
    }

    fn busy(&self, identity: &str) -> ProfileError {
        ProfileError::Busy {
            identity: identity.to_string(),
            lock: PathBuf::from(format!("the lock of this camera in {}", self.describe)),
        }
    }

    /// The document path used in parse errors: `URL#folder`.
    fn doc_path(&self, folder: &str) -> PathBuf {
        PathBuf::from(format!("{}#{folder}", self.describe))
    }

    /// The identity `device` names: an identity with a current profile, else a folder name.
    fn resolve(
        &self,
        client: &mut impl postgres::GenericClient,
        device: &str,
    ) -> Result<String, ProfileError> {
        // the identity first, so that an identity crafted to look like another camera's folder name
        // cannot stand for that camera when its own profile exists
        let mut rows = client
            .query(
                "SELECT identity FROM cubecal_profile WHERE state = 'current' AND identity = $1",
                &[&device.as_bytes()],
            )
            .map_err(self.db_err("finding the camera"))?;
        // a folder name is plain ASCII; anything holding NUL (which text cannot carry) is not one
        if rows.is_empty() && !device.contains('\0') {
            rows = client
                .query(
                    "SELECT identity FROM cubecal_profile WHERE state = 'current' AND folder = $1",
                    &[&device],
                )
                .map_err(self.db_err("finding the camera"))?;
        }
        let Some(row) = rows.first() else {
            return Err(ProfileError::NotFound {
                device: device.to_string(),
                store: PathBuf::from(&self.describe),
            });
        };
        let bytes: Vec<u8> = self.get(row, "identity")?;
        String::from_utf8(bytes).map_err(|_| ProfileError::Invalid {
            field: "identity".into(),
            reason: format!("not UTF-8 in {}", self.describe),
        })
    }

    /// The current (document bytes, profile) of `identity`, checked to belong to it.
    fn current_of<Q: ?Sized + ToStatement>(
        &self,
        client: &mut impl postgres::GenericClient,
        query: &Q,
        identity: &str,
    ) -> Result<Option<(i64, Vec<u8>, Profile)>, ProfileError> {
        let row = client
            .query_opt(query, &[&identity.as_bytes()])
            .map_err(self.db_err("reading the current profile"))?;
        let Some(row) = row else {
            return Ok(None);
        };
        let id: i64 = self.get(&row, "id")?;
        let bytes: Vec<u8> = self.get(&row, "document")?;
        let profile = parse_document(&self.doc_path(&folder_name(identity)), &bytes)?;
        if profile.identity.id != identity {
            return Err(ProfileError::Collision {
                folder: self.doc_path(&folder_name(identity)),
                stored: profile.identity.id,
                requested: identity.to_string(),
            });
        }
        Ok(Some((id, bytes, profile)))
    }

    /// Every stored version of `device`'s profile with its provenance, oldest first.
    pub fn history(&self, device: &str) -> Result<Vec<Version>, ProfileError> {
        let mut client = self.client();
        let identity = self.resolve(&mut *client, device)?;
        let rows = client
            .query(
                "SELECT id, state, run_id, station, rig_name, rig_sha256, software_version,
                        verdict_pass, report, created, sha256
                 FROM cubecal_profile WHERE identity = $1 ORDER BY id",
                &[&identity.as_bytes()],
            )
            .map_err(self.db_err("reading the history"))?;
        rows.iter()
            .map(|r| {
                Ok(Version {
                    id: self.get(r, "id")?,
                    state: self.get(r, "state")?,
                    run_id: self.get(r, "run_id")?,
                    station: self.get(r, "station")?,
                    rig_name: self.get(r, "rig_name")?,
                    rig_sha256: self.get(r, "rig_sha256")?,
                    software_version: self.get(r, "software_version")?,
                    verdict_pass: self.get(r, "verdict_pass")?,
                    report: self.get(r, "report")?,
                    created: self.get(r, "created")?,
                    sha256: self.get(r, "sha256")?,
                })
            })
            .collect()
    }
}

impl ProfileStore for PgStore {
    fn describe(&self) -> String {
        self.describe.clone()
    }

    fn earlier_profiles(
        &self,
        device: &str,
    ) -> Result<Vec<super::backend::EarlierProfile>, ProfileError> {
        let mut client = self.client();
        let identity = self.resolve(&mut *client, device)?;
        let rows = client
            .query(
                "SELECT id, folder, document FROM cubecal_profile
                 WHERE identity = $1 AND state = 'history' ORDER BY id",
                &[&identity.as_bytes()],
            )
            .map_err(self.db_err("reading the history"))?;
        rows.iter()
            .map(|r| {
                let id: i64 = self.get(r, "id")?;
                let folder: String = self.get(r, "folder")?;
                let bytes: Vec<u8> = self.get(r, "document")?;
                let doc = parse_document(&self.doc_path(&folder), &bytes);
                Ok((format!("{} (row {id})", self.describe), doc))
            })
            .collect()
    }

    fn commit_run(
        &self,
        profile: &Profile,
        options: &CommitOptions,
        provenance: &Provenance,
    ) -> Result<Committed, ProfileError> {
        check_passing(profile)?;
        validate(profile)?;
        let identity = profile.identity.id.as_str();
        let station = text_field("station", &provenance.station)?;
        let run_id = text_field("run_id", &provenance.run_id)?;
        let report = provenance
            .report
            .as_deref()
            .map(|r| text_field("report", r))
            .transpose()?;
        let rig_name = text_field("rig.name", &profile.rig.name)?;
        let rig_sha256 = text_field("rig.sha256", &profile.rig.sha256)?;
        let software = text_field("software_version", &profile.software_version)?;
        let created = text_field("created", &profile.created)?;
        if run_id.is_empty() {
            return Err(ProfileError::Invalid {
                field: "run_id".into(),
                reason: "empty".into(),
            });
        }
        let folder = folder_name(identity);

        let mut client = self.client();
        let st = self.commit_statements(&mut client)?;
        let mut tx = client
            .transaction()
            .map_err(self.db_err("starting the commit"))?;
        let row = tx
            .query_one(&st.lock, &[&camera_key(identity)])
            .map_err(self.db_err("locking the camera"))?;
        if !self.get::<bool>(&row, "locked")? {
            return Err(self.busy(identity));
        }
        let done = tx
            .query_opt(&st.by_run, &[&run_id])
            .map_err(self.db_err("looking the run up"))?;
        if let Some(row) = done {
            let id: i64 = self.get(&row, "id")?;
            let bytes: Vec<u8> = self.get(&row, "document")?;
            let stored = parse_document(&self.doc_path(&folder), &bytes)?;
            if stored.identity.id != identity {
                return Err(ProfileError::Invalid {
                    field: "run_id".into(),
                    reason: format!(
                        "already stored for another camera ('{}')",
                        stored.identity.id.escape_debug()
                    ),
                });
            }
            tracing::info!(store = %self.describe, %folder, id, "run already stored; nothing written");
            let jump = stored.change.as_ref().is_some_and(|c| c.jump);
            return Ok(Committed {
                location: PathBuf::from(format!("{}#version-{id}", self.describe)),
                change: stored.change,
                jump,
                already_stored: true,
            });
        }
        let previous = self.current_of(&mut tx, &st.current, identity)?;
        let (doc, bytes) = prepare_document(
            &self.doc_path(&folder),
            profile,
            previous.as_ref().map(|(_, b, p)| (b.as_slice(), p)),
            options,
        )?;
        if let Some((prev_id, _, _)) = &previous {
            tx.execute(&st.archive, &[prev_id])
                .map_err(self.db_err("archiving the previous profile"))?;
        }
        let row = tx
            .query_one(
                &st.insert,
                &[
                    &identity.as_bytes(),
                    &folder,
                    &run_id,
                    &bytes,
                    &sha256_hex(&bytes),
                    &created,
                    &station,
                    &rig_name,
                    &rig_sha256,
                    &software,
                    &profile.verdict.pass,
                    &report,
                ],
            )
            .map_err(self.db_err("storing the profile"))?;
        let id: i64 = self.get(&row, "id")?;
        tx.commit().map_err(self.db_err("committing the profile"))?;
        tracing::info!(store = %self.describe, %folder, id, "profile committed");
        let jump = doc.change.as_ref().is_some_and(|c| c.jump);
        Ok(Committed {
            location: PathBuf::from(format!("{}#version-{id}", self.describe)),
            change: doc.change,
            jump,
            already_stored: false,
        })
    }

    fn current_profile(&self, device: &str) -> Result<(Profile, Vec<u8>), ProfileError> {
        let mut client = self.client();
        let identity = self.resolve(&mut *client, device)?;
        match self.current_of(&mut *client, CURRENT_SQL, &identity)? {
            Some((_, bytes, profile)) => Ok((profile, bytes)),
            None => Err(ProfileError::NotFound {
                device: device.to_string(),
                store: PathBuf::from(&self.describe),
            }),
        }
    }

    fn list_cameras(&self) -> Result<Vec<ListEntry>, ProfileError> {
        let mut client = self.client();
        let rows = client
            .query(
                "SELECT c.folder, c.document,
                        (SELECT count(*) FROM cubecal_profile h
                         WHERE h.identity = c.identity AND h.state = 'history') AS history
                 FROM cubecal_profile c WHERE c.state = 'current' ORDER BY c.folder",
                &[],
            )
            .map_err(self.db_err("listing the cameras"))?;
        rows.iter()
            .map(|r| {
                let folder: String = self.get(r, "folder")?;
                let bytes: Vec<u8> = self.get(r, "document")?;
                let history: i64 = self.get(r, "history")?;
                let summary = parse_document(&self.doc_path(&folder), &bytes).map(|p| Summary {
                    history: usize::try_from(history).unwrap_or(0),
                    identity: p.identity.id,
                    created: p.created,
                    model: p.calibration.distortion.model,
                    rms_px: p.calibration.rms_px,
                    jump: p.change.is_some_and(|c| c.jump),
                });
                Ok(ListEntry { folder, summary })
            })
            .collect()
    }

    fn roll_back(&self, device: &str) -> Result<RolledBack, ProfileError> {
        let mut client = self.client();
        let mut tx = client
            .transaction()
            .map_err(self.db_err("starting the rollback"))?;
        let identity = self.resolve(&mut tx, device)?;
        let row = tx
            .query_one(LOCK_SQL, &[&camera_key(&identity)])
            .map_err(self.db_err("locking the camera"))?;
        if !self.get::<bool>(&row, "locked")? {
            return Err(self.busy(&identity));
        }
        // re-read under the lock: a commit may have finished in between
        let Some((cur_id, _, cur)) = self.current_of(&mut tx, CURRENT_SQL, &identity)? else {
            return Err(ProfileError::NotFound {
                device: device.to_string(),
                store: PathBuf::from(&self.describe),
            });
        };
        let folder = folder_name(&identity);
        let row = tx
            .query_opt(
                "SELECT id, document FROM cubecal_profile
                 WHERE identity = $1 AND state = 'history' ORDER BY id DESC LIMIT 1",
                &[&identity.as_bytes()],
            )
            .map_err(self.db_err("reading the history"))?;
        let Some(row) = row else {
            return Err(ProfileError::NoHistory { identity });
        };
        let restore_id: i64 = self.get(&row, "id")?;
        let restore_bytes: Vec<u8> = self.get(&row, "document")?;
        let restored = parse_document(&self.doc_path(&folder), &restore_bytes)?;
        if restored.identity.id != identity {
            return Err(ProfileError::Collision {
                folder: self.doc_path(&folder),
                stored: restored.identity.id,
                requested: identity,
            });
        }
        tx.execute(
            "UPDATE cubecal_profile SET state = 'rolled_back' WHERE id = $1",
            &[&cur_id],
        )
        .map_err(self.db_err("setting the current profile aside"))?;
        tx.execute(
            "UPDATE cubecal_profile SET state = 'current' WHERE id = $1",
            &[&restore_id],
        )
        .map_err(self.db_err("restoring the earlier profile"))?;
        tx.commit()
            .map_err(self.db_err("committing the rollback"))?;
        tracing::info!(store = %self.describe, %folder, restore_id, "profile rolled back");
        Ok(RolledBack {
            folder,
            restored_created: restored.created,
            replaced_created: cur.created,
            set_aside: format!("{}#version-{cur_id}", self.describe),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn redaction_drops_passwords_and_options() {
        assert_eq!(
            redact("postgres://bob:secret@db.example:5433/fleet?password=x"),
            "postgres://bob@db.example:5433/fleet"
        );
        assert_eq!(redact("postgresql://db/fleet"), "postgresql://db/fleet");
    }

    #[test]
    fn migrations_are_numbered_in_order() {
        for (i, m) in MIGRATIONS.iter().enumerate() {
            assert_eq!(m.0, i as i32 + 1);
        }
    }
}
