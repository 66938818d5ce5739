//! The PostgreSQL profile store (issue 34) against a real, throw-away PostgreSQL (tests/support/pg.rs):
//! migrations, the file store's guarantees kept (a failed run never replaces a passing profile, one of
//! two concurrent committers wins and the other gets Busy, history with provenance, hostile identities
//! and SQL injection are data), and `cubecal profile get/list/migrate` on a database.
//!
//! Each test has its own database in the one cluster of this binary. Without PostgreSQL the tests skip,
//! and fail under `CUBECAL_REQUIRE_TOOLS=1`.

#![allow(clippy::print_stdout, clippy::print_stderr)]

#[path = "support/pg.rs"]
mod pg;
#[path = "support/sample_profile.rs"]
mod sample_profile;

use std::process::Command;
use std::sync::{Arc, Barrier};

use cubecal::profile::export::Format;
use cubecal::profile::postgres::{PgStore, camera_key};
use cubecal::profile::store::folder_name;
use cubecal::profile::{
    CommitOptions, ProfileError, ProfileStore, Provenance, Store, identity_from_bytes,
};
use sample_profile::profile;

fn provenance(run: &str) -> Provenance {
    Provenance {
        run_id: run.to_string(),
        station: "bench-3".into(),
        report: Some(format!("/var/lib/cubecal/runs/{run}/report.html")),
    }
}

fn opts() -> CommitOptions {
    CommitOptions { jump_sigma: 5.0 }
}

/// `count` passing profiles of camera `id` committed to `store`, runs `<run>0`, `<run>1`, ….
fn commit_passing(store: &impl ProfileStore, id: &str, count: u64, run: &str) {
    for n in 0..count {
        store
            .commit_run(
                &profile(id, n, true),
                &opts(),
                &provenance(&format!("{run}{n}")),
            )
            .unwrap_or_else(|e| panic!("{e}"));
    }
}

/// A migrated database `name` and a store connected to it, or `None` when PostgreSQL is absent.
fn store(name: &str) -> Option<(PgStore, String)> {
    let cluster = pg::cluster()?;
    let url = cluster.database(name);
    let store = PgStore::connect_unchecked(&url, Some(pg::PASSWORD.into()))
        .unwrap_or_else(|e| panic!("{e}"));
    store.migrate().unwrap_or_else(|e| panic!("{e}"));
    let store = PgStore::connect(&url, Some(pg::PASSWORD.into())).unwrap_or_else(|e| panic!("{e}"));
    Some((store, url))
}

fn cubecal(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .env_remove("PGPASSWORD")
        .output()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"))
}

/// `cubecal profile ARGS --store URL --store-password-file PW`.
fn on_store(args: &[&str], url: &str, pw: &str) -> std::process::Output {
    let mut all = vec!["profile"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--store", url, "--store-password-file", pw]);
    cubecal(&all)
}

/// `cubecal profile migrate` on `url`, whose stdout must contain `expect`.
fn migrate(url: &str, pw: &str, expect: &str) {
    let out = on_store(&["migrate"], url, pw);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains(expect), "{}", text(&out.stdout));
}

/// The stored versions of `id` are `expected` (run id, state), oldest first; returns them.
fn assert_runs(
    store: &PgStore,
    id: &str,
    expected: &[(&str, &str)],
) -> Vec<cubecal::profile::postgres::Version> {
    let history = store.history(id).unwrap_or_else(|e| panic!("{e}"));
    let runs: Vec<(&str, &str)> = history
        .iter()
        .map(|v| (v.run_id.as_str(), v.state.as_str()))
        .collect();
    assert_eq!(runs, expected);
    history
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn migrate_applies_each_version_once_and_an_unmigrated_database_is_refused() {
    let Some(cluster) = pg::cluster() else { return };
    let url = cluster.database("t_migrate");
    let pw = cluster.password_file.to_string_lossy().into_owned();

    // not migrated: refused with the command that fixes it
    match PgStore::connect(&url, Some(pg::PASSWORD.into())) {
        Err(e @ ProfileError::Unusable { .. }) => {
            assert!(e.to_string().contains("cubecal profile migrate"), "{e}");
            assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
        }
        other => panic!("expected Unusable, got {other:?}"),
    }
    let out = on_store(&["list"], &url, &pw);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out.stderr));

    migrate(&url, &pw, "applied migrations [1]");
    migrate(&url, &pw, "up to date");

    // PGPASSWORD works as libpq's clients take it
    let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["profile", "list", "--store", &url])
        .env("PGPASSWORD", pg::PASSWORD)
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(out.status.success(), "{}", text(&out.stderr));

    // a migration applied by another cubecal later than ours: refused, never half-read
    cluster
        .admin("t_migrate")
        .execute(
            "INSERT INTO cubecal_migrations (version, name) VALUES ($1, $2)",
            &[&99i32, &"from the future"],
        )
        .unwrap_or_else(|e| panic!("{e}"));
    let out = on_store(&["list"], &url, &pw);
    assert_eq!(out.status.code(), Some(3));
    assert!(text(&out.stderr).contains("newer"), "{}", text(&out.stderr));
}

#[test]
fn a_password_in_the_url_is_refused_and_never_printed() {
    let Some(cluster) = pg::cluster() else { return };
    let secret = "hunter2-do-not-print";
    let url = format!(
        "postgres://{}:{secret}@127.0.0.1:{}/postgres",
        pg::ADMIN,
        cluster.port
    );
    let out = cubecal(&["profile", "list", "--store", &url]);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out.stderr));
    let all = text(&out.stdout) + &text(&out.stderr);
    assert!(!all.contains(secret), "{all}");
    assert!(all.contains("password"), "{all}");
    // a wrong password: a database error that names the store, not the password
    let bad = cluster.dir.join("wrong-password");
    std::fs::write(&bad, "wrong\n").unwrap_or_else(|e| panic!("{e}"));
    let out = cubecal(&[
        "profile",
        "list",
        "--store",
        &cluster.url("postgres"),
        "--store-password-file",
        &bad.to_string_lossy(),
    ]);
    assert_eq!(out.status.code(), Some(7), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("127.0.0.1"),
        "{}",
        text(&out.stderr)
    );
    assert!(!text(&out.stderr).contains("wrong\n"));
}

#[test]
fn history_keeps_provenance_a_failed_run_changes_nothing_and_a_run_is_stored_once() {
    let Some((store, url)) = store("t_history") else {
        return;
    };
    let id = "usb:046d:0825:A1B2C3";
    let first = store
        .commit_run(&profile(id, 0, true), &opts(), &provenance("run-0"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(first.change.is_none() && !first.jump);
    let second = store
        .commit_run(&profile(id, 1, true), &opts(), &provenance("run-1"))
        .unwrap_or_else(|e| panic!("{e}"));
    let change = second.change.unwrap_or_else(|| panic!("no change"));
    assert!(!change.jump && change.max_abs_delta_sigma < 0.01);
    let (_, v1_bytes) = store.current_profile(id).unwrap_or_else(|e| panic!("{e}"));

    // a failing run: refused before the database is touched, the passing profile byte-identical
    match store.commit_run(&profile(id, 2, false), &opts(), &provenance("run-2")) {
        Err(e @ ProfileError::Rejected { .. }) => {
            assert_eq!(e.exit_code(), cubecal::exit::QA_REJECTED)
        }
        other => panic!("expected Rejected, got {other:?}"),
    }
    // the same run committed again (a retry, a spool re-sent): nothing new
    let again = store
        .commit_run(&profile(id, 1, true), &opts(), &provenance("run-1"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(again.already_stored);
    let (current, bytes) = store.current_profile(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(bytes, v1_bytes);
    assert_eq!(current.calibration.camera_matrix[0][0], 1000.001);

    let history = assert_runs(&store, id, &[("run-0", "history"), ("run-1", "current")]);
    for v in &history {
        assert_eq!(v.station, "bench-3");
        assert_eq!(v.rig_name, "cube_outside");
        assert_eq!(v.software_version, env!("CARGO_PKG_VERSION"));
        assert!(v.verdict_pass);
        assert!(v.report.as_deref().is_some_and(|r| r.contains(&v.run_id)));
    }

    // by folder name too, as `list` prints it
    let (by_folder, _) = store
        .current_profile(&folder_name(id))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(by_folder.identity.id, id);

    // rollback: v0 current again, v1 set aside (not a rollback candidate), then nothing left
    let back = store.roll_back(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back.restored_created, profile(id, 0, true).created);
    let (current, _) = store.current_profile(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(current.calibration.camera_matrix[0][0], 1000.0);
    assert!(matches!(
        store.roll_back(id),
        Err(ProfileError::NoHistory { .. })
    ));

    // `profile get SERIAL --format F` from the database prints what the export gives for the profile
    let pw = pg::cluster()
        .map(|c| c.password_file.to_string_lossy().into_owned())
        .unwrap_or_default();
    for format in Format::ALL {
        let name = format.name();
        let out = on_store(&["get", id, "--format", name], &url, &pw);
        match format.render(&current) {
            Ok(expected) => {
                assert!(out.status.success(), "{name}: {}", text(&out.stderr));
                assert_eq!(text(&out.stdout), expected, "{name}");
            }
            // the sample's brown5 has k3 ≠ 0, which Kalibr's radtan cannot hold: refused alike
            Err(e) => {
                assert_eq!(out.status.code(), Some(3), "{name}: {}", text(&out.stderr));
                assert_eq!(text(&out.stderr), format!("error: {e}\n"), "{name}");
            }
        }
    }
    let out = on_store(&["list"], &url, &pw);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains(&folder_name(id)));
    let out = on_store(&["get", "usb:none", "--format", "ros"], &url, &pw);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out.stderr));
}

#[test]
fn the_file_store_and_the_database_store_the_same_document() {
    let Some((db, _)) = store("t_same_bytes") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let files = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:1234:5678:SAME";
    for n in 0..2 {
        let s: &dyn ProfileStore = &files;
        s.commit_run(
            &profile(id, n, true),
            &opts(),
            &provenance(&format!("f{n}")),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        db.commit_run(
            &profile(id, n, true),
            &opts(),
            &provenance(&format!("d{n}")),
        )
        .unwrap_or_else(|e| panic!("{e}"));
    }
    let (_, a) = files.current_profile(id).unwrap_or_else(|e| panic!("{e}"));
    let (_, b) = db.current_profile(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a, b);
}

#[test]
fn two_stations_committing_one_camera_one_wins_and_the_other_is_busy() {
    let Some((store, url)) = store("t_busy") else {
        return;
    };
    let id = "usb:046d:0825:BUSY";
    // another station holds the camera's lock (mid-commit): ours is refused at once with Busy
    let mut other = pg::cluster()
        .map(|c| c.admin("t_busy"))
        .unwrap_or_else(|| panic!("cluster"));
    let mut tx = other.transaction().unwrap_or_else(|e| panic!("{e}"));
    tx.execute("SELECT pg_advisory_xact_lock($1)", &[&camera_key(id)])
        .unwrap_or_else(|e| panic!("{e}"));
    let t0 = std::time::Instant::now();
    match store.commit_run(&profile(id, 0, true), &opts(), &provenance("b0")) {
        Err(e @ ProfileError::Busy { .. }) => {
            assert_eq!(e.exit_code(), cubecal::exit::DEVICE);
            assert!(e.to_string().contains("127.0.0.1"), "{e}");
        }
        other => panic!("expected Busy, got {other:?}"),
    }
    assert!(t0.elapsed().as_secs_f64() < 2.0, "Busy without waiting");
    tx.rollback().unwrap_or_else(|e| panic!("{e}"));

    // eight stations race on one camera, many rounds: every attempt commits or is Busy, each
    // commit is in history exactly once, and one profile is current
    let stations = 8;
    let rounds = 10;
    let barrier = Arc::new(Barrier::new(stations));
    let handles: Vec<_> = (0..stations)
        .map(|s| {
            let barrier = Arc::clone(&barrier);
            let url = url.clone();
            std::thread::spawn(move || {
                let store = PgStore::connect(&url, Some(pg::PASSWORD.into()))
                    .unwrap_or_else(|e| panic!("{e}"));
                let (mut ok, mut busy) = (Vec::new(), 0);
                for r in 0..rounds {
                    barrier.wait();
                    let n = (s * rounds + r) as u64;
                    let run = format!("s{s}-r{r}");
                    match store.commit_run(&profile(id, n, true), &opts(), &provenance(&run)) {
                        Ok(_) => ok.push(run),
                        Err(ProfileError::Busy { .. }) => busy += 1,
                        Err(e) => panic!("{e}"),
                    }
                }
                (ok, busy)
            })
        })
        .collect();
    let mut committed = Vec::new();
    let mut busy = 0;
    for h in handles {
        let (ok, b) = h
            .join()
            .unwrap_or_else(|_| panic!("station thread panicked"));
        committed.extend(ok);
        busy += b;
    }
    println!(
        "{} commits, {busy} Busy of {} attempts",
        committed.len(),
        stations * rounds
    );
    assert_eq!(committed.len() + busy, stations * rounds);
    assert!(committed.len() >= rounds, "at least one winner per round");
    let history = store.history(id).unwrap_or_else(|e| panic!("{e}"));
    let mut stored: Vec<String> = history.iter().map(|v| v.run_id.clone()).collect();
    stored.sort();
    committed.sort();
    assert_eq!(stored, committed, "every commit in history exactly once");
    assert_eq!(history.iter().filter(|v| v.state == "current").count(), 1);
    let current = history.last().map(|v| v.run_id.clone());
    assert_eq!(
        history
            .iter()
            .find(|v| v.state == "current")
            .map(|v| v.run_id.clone()),
        current,
        "the newest commit is current"
    );
}

/// The file store's hostile identities, and SQL injection.
fn hostile_identities() -> Vec<String> {
    let mut ids: Vec<String> = [
        "'; DROP TABLE cubecal_profile; --",
        "x' OR '1'='1",
        "\\'; SELECT pg_sleep(10); --",
        "$1",
        "E'\\x00'",
        "Robert'); DELETE FROM cubecal_migrations;--",
        "../../../../etc/passwd",
        "a/b",
        "a_b",
        "nul\0inside",
        "nul_inside",
        "newline\nand\rcarriage\x1b[31mred",
        "usb:046d:0825:\u{202e}reversed",
        "unicode-é-漢字",
        "-rf",
    ]
    .into_iter()
    .map(String::from)
    .collect();
    ids.push("x".repeat(4096));
    ids.push(format!("{}y", "x".repeat(4095)));
    ids.push(identity_from_bytes(b"bad\xff\xfeutf8"));
    // looks like the folder of "a/b": must still name its own camera
    ids.push(folder_name("a/b"));
    ids
}

#[test]
fn hostile_identities_and_sql_injection_are_data() {
    let Some((store, _)) = store("t_hostile") else {
        return;
    };
    let ids = hostile_identities();
    for (n, id) in ids.iter().enumerate() {
        store
            .commit_run(
                &profile(id, n as u64, true),
                &opts(),
                &provenance(&format!("hostile-{n}")),
            )
            .unwrap_or_else(|e| panic!("{}: {e}", id.escape_debug()));
    }
    // an empty identity is refused, as by the file store
    assert!(matches!(
        store.commit_run(&profile("", 0, true), &opts(), &provenance("empty")),
        Err(ProfileError::Invalid { .. })
    ));
    // provenance strings are data too; NUL, which text columns cannot hold, is refused by name
    let evil = Provenance {
        run_id: "r'); DROP TABLE cubecal_profile; --".into(),
        station: "'; TRUNCATE cubecal_profile; --".into(),
        report: Some("$$; DROP SCHEMA public CASCADE; $$".into()),
    };
    store
        .commit_run(&profile("usb:evil:provenance", 0, true), &opts(), &evil)
        .unwrap_or_else(|e| panic!("{e}"));
    let nul = Provenance {
        station: "st\0ation".into(),
        ..provenance("nul-station")
    };
    match store.commit_run(&profile("usb:nul:station", 0, true), &opts(), &nul) {
        Err(ProfileError::Invalid { field, .. }) => assert_eq!(field, "station"),
        other => panic!("expected Invalid, got {other:?}"),
    }

    // every camera reads back as itself, by identity; the tables are intact
    for (n, id) in ids.iter().enumerate() {
        let (p, _) = store
            .current_profile(id)
            .unwrap_or_else(|e| panic!("{}: {e}", id.escape_debug()));
        assert_eq!(&p.identity.id, id);
        assert_eq!(
            p.calibration.camera_matrix[0][0],
            1000.0 + n as f64 / 1000.0,
            "{}",
            id.escape_debug()
        );
    }
    let list = store.list_cameras().unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(list.len(), ids.len() + 1);
    for e in &list {
        assert!(
            e.folder
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.')),
            "{}",
            e.folder
        );
    }
    let h = store
        .history("usb:evil:provenance")
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(h.len(), 1);
    assert_eq!(h[0].station, evil.station);
    assert_eq!(h[0].report, evil.report);
    assert!(matches!(
        store.current_profile("' OR '1'='1"),
        Err(ProfileError::NotFound { .. })
    ));
}

/// The README's role set-up: a station role that may commit, a reader that may only read.
const ROLES_SQL: &[&str] = &[
    "CREATE ROLE cubecal_station LOGIN PASSWORD 'station-pw'",
    "CREATE ROLE cubecal_reader LOGIN PASSWORD 'reader-pw'",
    "GRANT SELECT ON cubecal_migrations TO cubecal_station, cubecal_reader",
    "GRANT SELECT ON cubecal_profile TO cubecal_reader",
    "GRANT SELECT, INSERT, UPDATE ON cubecal_profile TO cubecal_station",
    "GRANT USAGE ON SEQUENCE cubecal_profile_id_seq TO cubecal_station",
];

#[test]
fn a_read_only_role_can_get_profiles_but_not_commit() {
    let Some((admin_store, url)) = store("t_roles") else {
        return;
    };
    let Some(cluster) = pg::cluster() else { return };
    let mut admin = cluster.admin("t_roles");
    for sql in [
        "DROP ROLE IF EXISTS cubecal_station",
        "DROP ROLE IF EXISTS cubecal_reader",
    ] {
        admin
            .batch_execute(sql)
            .unwrap_or_else(|e| panic!("{sql}: {e:?}"));
    }
    for sql in ROLES_SQL {
        admin
            .batch_execute(sql)
            .unwrap_or_else(|e| panic!("{sql}: {e:?}"));
    }
    drop(admin_store);
    let as_role = |role: &str| url.replacen(pg::ADMIN, role, 1);
    let id = "usb:046d:0825:ROLES";

    // the station commits
    let station = PgStore::connect(&as_role("cubecal_station"), Some("station-pw".into()))
        .unwrap_or_else(|e| panic!("{e}"));
    commit_passing(&station, id, 2, "roles-");

    // the reader gets the profile, from the command line too
    let reader = PgStore::connect(&as_role("cubecal_reader"), Some("reader-pw".into()))
        .unwrap_or_else(|e| panic!("{e}"));
    let (p, _) = reader.current_profile(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(p.identity.id, id);
    let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["profile", "get", id, "--format", "ros", "--store"])
        .arg(as_role("cubecal_reader"))
        .env("PGPASSWORD", "reader-pw")
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(out.status.success(), "{}", text(&out.stderr));

    // and cannot commit or roll back: refused by the database, nothing changed
    for attempt in [
        reader
            .commit_run(&profile(id, 2, true), &opts(), &provenance("roles-2"))
            .map(|_| ()),
        reader.roll_back(id).map(|_| ()),
    ] {
        match attempt {
            Err(e @ ProfileError::Database { .. }) => {
                let chain = format!("{e}: {:?}", std::error::Error::source(&e));
                assert!(chain.contains("permission denied"), "{chain}");
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }
    assert_runs(
        &station,
        id,
        &[("roles-0", "history"), ("roles-1", "current")],
    );
}

/// `cubecal calibrate --replay fixtures/sessions/demo --out DIR/RUN --store URL` (password from
/// `PGPASSWORD`) with `extra` arguments.
fn calibrate_into(
    url: &str,
    dir: &std::path::Path,
    run: &str,
    extra: &[&str],
) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args([
            "calibrate",
            "--json",
            "--replay",
            "fixtures/sessions/demo",
            "--out",
        ])
        .arg(dir.join(run))
        .args(["--store", url])
        .args(extra)
        .env("PGPASSWORD", pg::PASSWORD)
        .output()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"))
}

#[test]
fn the_station_commits_a_passing_run_with_its_provenance_and_a_failing_one_not_at_all() {
    let Some((store, url)) = store("t_station") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let ok = calibrate_into(&url, dir.path(), "a", &[]);
    assert_eq!(ok.status.code(), Some(0), "{}", text(&ok.stderr));
    let last: serde_json::Value = text(&ok.stdout)
        .lines()
        .last()
        .and_then(|l| serde_json::from_str(l).ok())
        .unwrap_or_else(|| panic!("no result line"));
    let location = last["profile"].as_str().unwrap_or_default();
    assert!(
        location.starts_with(&url) && location.contains("#version-"),
        "{location}"
    );
    assert!(!text(&ok.stdout).contains(pg::PASSWORD));

    let list = store.list_cameras().unwrap_or_else(|e| panic!("{e}"));
    let [camera] = list.as_slice() else {
        panic!("expected one camera, got {list:?}")
    };
    let history = store
        .history(&camera.folder)
        .unwrap_or_else(|e| panic!("{e}"));
    let [v] = history.as_slice() else {
        panic!("expected one version, got {history:?}")
    };
    assert_eq!(v.state, "current");
    assert_eq!(
        v.report.as_deref(),
        Some(dir.path().join("a").to_string_lossy().as_ref())
    );
    assert!(
        !v.station.is_empty() && v.rig_name == "cube-outside",
        "{v:?}"
    );
    let run_profile =
        std::fs::read(dir.path().join("a/profile.json")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(v.run_id, cubecal::profile::store::sha256_hex(&run_profile));

    // rejected by a stricter verdict: exit 6 and nothing reaches the database
    let bad = calibrate_into(&url, dir.path(), "b", &["--set", "qa.min_coverage=0.9"]);
    assert_eq!(bad.status.code(), Some(6), "{}", text(&bad.stderr));
    assert_eq!(store.history(&camera.folder).map(|h| h.len()).ok(), Some(1));

    // the database unreachable at the start: the run passes, its profile waits in the spool, and
    // the run says where (the store named, not a password)
    let closed = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or_else(|e| panic!("{e}"));
    let nowhere = format!("postgres://{}@127.0.0.1:{closed}/t_station", pg::ADMIN);
    let spool = dir.path().join("spool");
    let spool_arg = format!("output.spool={}", spool.display());
    let down = calibrate_into(&nowhere, dir.path(), "c", &["--set", &spool_arg]);
    assert_eq!(down.status.code(), Some(0), "{}", text(&down.stderr));
    let last = result_line(&down);
    assert_eq!(last["profile_waits_for"], nowhere.as_str());
    let waiting = spool.join(format!("{}.json", run_id(&dir.path().join("c"))));
    assert_eq!(last["profile"], waiting.to_string_lossy().as_ref());
    assert!(waiting.is_file(), "{}", waiting.display());
    assert!(
        dir.path().join("c/profile.json").is_file(),
        "the run keeps its profile.json"
    );
    let human = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["calibrate", "--replay", "fixtures/sessions/demo", "--out"])
        .arg(dir.path().join("d"))
        .args(["--store", &nowhere, "--set", &spool_arg])
        .env("PGPASSWORD", pg::PASSWORD)
        .output()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"));
    assert_eq!(human.status.code(), Some(0), "{}", text(&human.stderr));
    let out = text(&human.stdout);
    assert!(
        out.contains("waiting in the spool") && out.contains(&spool.display().to_string()),
        "{out}"
    );
    assert!(!out.contains(pg::PASSWORD) && !text(&human.stderr).contains(pg::PASSWORD));
}

/// The last line of a `--json` run: its result.
fn result_line(out: &std::process::Output) -> serde_json::Value {
    text(&out.stdout)
        .lines()
        .last()
        .and_then(|l| serde_json::from_str(l).ok())
        .unwrap_or_else(|| panic!("no result line in {}", text(&out.stdout)))
}

/// The run id of the run in `run_dir`: the SHA-256 of its profile.json.
fn run_id(run_dir: &std::path::Path) -> String {
    let bytes = std::fs::read(run_dir.join("profile.json")).unwrap_or_else(|e| panic!("{e}"));
    cubecal::profile::store::sha256_hex(&bytes)
}

/// Issue 34 line 3: the database killed (SIGKILL, every server process) while a station runs, and
/// unreachable when the next one starts; both runs pass with their profiles in the spool. Restarted,
/// the next run drains the spool before its own commit, and a spool entry whose commit already landed
/// (a drain cut short between the store's commit and the file's removal) is recognised by its run id:
/// every run is in the history exactly once, none is lost, the spool ends empty.
#[test]
fn the_database_killed_mid_run_spools_and_the_spool_drains_exactly_once() {
    let Some(cluster) = pg::Cluster::own() else {
        return;
    };
    let url = cluster.database("t_spool");
    let pw = cluster.password_file.to_string_lossy().into_owned();
    migrate(&url, &pw, "applied migrations [1]");
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let spool = dir.path().join("spool");
    let spool_arg = format!("output.spool={}", spool.display());
    let spooled = |out: &std::process::Output, run: &str| {
        assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
        let last = result_line(out);
        assert_eq!(last["profile_waits_for"], url.as_str(), "{last}");
        let entry = spool.join(format!("{}.json", run_id(&dir.path().join(run))));
        assert_eq!(last["profile"], entry.to_string_lossy().as_ref());
        assert!(entry.is_file());
        entry
    };

    // a: the database up, committed
    let a = calibrate_into(&url, dir.path(), "a", &["--set", &spool_arg]);
    assert_eq!(a.status.code(), Some(0), "{}", text(&a.stderr));
    assert!(result_line(&a)["profile_waits_for"].is_null());

    // b: the database killed while the station runs (after its first view is accepted)
    let mut b = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args([
            "calibrate",
            "--json",
            "--replay",
            "fixtures/sessions/demo",
            "--out",
        ])
        .arg(dir.path().join("b"))
        .args(["--store", &url, "--set", &spool_arg])
        .env("PGPASSWORD", pg::PASSWORD)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"));
    let mut stdout = std::io::BufReader::new(b.stdout.take().unwrap_or_else(|| panic!("stdout")));
    let mut lines = Vec::new();
    loop {
        let mut line = String::new();
        let n = std::io::BufRead::read_line(&mut stdout, &mut line).unwrap_or(0);
        assert!(n > 0, "run b ended before its first view: {lines:?}");
        let accepted = line.contains("\"view_accepted\"");
        lines.push(line);
        if accepted {
            break;
        }
    }
    let killed = cluster.kill();
    assert!(killed.len() >= 2, "postmaster and its children: {killed:?}");
    let mut b_all = lines.concat();
    std::io::Read::read_to_string(&mut stdout, &mut b_all).unwrap_or_else(|e| panic!("{e}"));
    let b_out = b.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
    let b_out = std::process::Output {
        stdout: b_all.into_bytes(),
        ..b_out
    };
    let b_entry = spooled(&b_out, "b");
    assert!(text(&b_out.stdout).contains("\"event\":\"profile_spooled\""));

    // c: the database still down when the station starts
    let c = calibrate_into(&url, dir.path(), "c", &["--set", &spool_arg]);
    spooled(&c, "c");
    let status = cubecal(&[
        "profile",
        "sync",
        "--store",
        &url,
        "--store-password-file",
        &pw,
        "--spool",
        &spool.to_string_lossy(),
    ]);
    assert_eq!(
        status.status.code(),
        Some(7),
        "sync with the database down: {}",
        text(&status.stderr)
    );
    assert_eq!(std::fs::read_dir(&spool).map(|d| d.count()).ok(), Some(2));

    // the database back (crash recovery); b's entry kept aside to be synced a second time
    cluster.restart();
    let b_copy = std::fs::read(&b_entry).unwrap_or_else(|e| panic!("{e}"));
    // d: drains b and c, in run order, before its own commit
    let d = calibrate_into(&url, dir.path(), "d", &["--set", &spool_arg]);
    assert_eq!(d.status.code(), Some(0), "{}", text(&d.stderr));
    assert!(result_line(&d)["profile_waits_for"].is_null());
    let drained: Vec<serde_json::Value> = text(&d.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .filter(|v: &serde_json::Value| v["event"] == "spool_drained")
        .collect();
    assert_eq!(drained.len(), 1, "{}", text(&d.stdout));
    assert_eq!(drained[0]["committed"], 2);
    assert_eq!(drained[0]["waiting"], 0);
    assert_eq!(std::fs::read_dir(&spool).map(|d| d.count()).ok(), Some(0));

    // b's entry again (its first drain had committed it): recognised, nothing written twice
    std::fs::write(&b_entry, &b_copy).unwrap_or_else(|e| panic!("{e}"));
    let again = cubecal(&[
        "profile",
        "sync",
        "--json",
        "--store",
        &url,
        "--store-password-file",
        &pw,
        "--spool",
        &spool.to_string_lossy(),
    ]);
    assert_eq!(again.status.code(), Some(0), "{}", text(&again.stderr));
    let v: serde_json::Value =
        serde_json::from_slice(&again.stdout).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        v["drained"]["already_stored"].as_array().map(Vec::len),
        Some(1),
        "{v}"
    );
    assert_eq!(
        v["drained"]["committed"].as_array().map(Vec::len),
        Some(0),
        "{v}"
    );
    assert_eq!(std::fs::read_dir(&spool).map(|d| d.count()).ok(), Some(0));

    // the history: a, b, c, d — each once, d current
    let store = PgStore::connect(&url, Some(pg::PASSWORD.into())).unwrap_or_else(|e| panic!("{e}"));
    let list = store.list_cameras().unwrap_or_else(|e| panic!("{e}"));
    let [camera] = list.as_slice() else {
        panic!("expected one camera, got {list:?}")
    };
    let ids: Vec<String> = ["a", "b", "c", "d"]
        .iter()
        .map(|r| run_id(&dir.path().join(r)))
        .collect();
    let expected: Vec<(&str, &str)> = ids
        .iter()
        .zip(["history", "history", "history", "current"])
        .map(|(id, state)| (id.as_str(), state))
        .collect();
    assert_runs(&store, &camera.folder, &expected);
}

#[test]
fn the_profile_report_is_drawn_from_the_database_with_its_history() {
    let Some((store, url)) = store("t_report") else {
        return;
    };
    let id = "usb:046d:0825:REPORT";
    commit_passing(&store, id, 3, "r");
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let html = tmp.path().join("report.html");
    let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["report", id, "--store", &url, "--out"])
        .arg(&html)
        .env("PGPASSWORD", pg::PASSWORD)
        .output()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"));
    assert!(out.status.success(), "{}", text(&out.stderr));
    let page = std::fs::read_to_string(&html).unwrap_or_else(|e| panic!("{e}"));
    // The two earlier versions, named by their rows, and the camera.
    let rows: Vec<i64> = store
        .history(id)
        .unwrap_or_else(|e| panic!("{e}"))
        .iter()
        .filter(|v| v.state == "history")
        .map(|v| v.id)
        .collect();
    assert_eq!(rows.len(), 2);
    for row in rows {
        assert!(
            page.contains(&format!("(row {row})")),
            "row {row} not in the report"
        );
    }
    assert!(page.contains("REPORT"), "camera not named");
    // The password never reaches the page or the output.
    assert!(!page.contains(pg::PASSWORD) && !text(&out.stdout).contains(pg::PASSWORD));
    // An unknown camera is an error that names it, not an empty report.
    let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["report", "usb:none", "--store", &url, "--out"])
        .arg(tmp.path().join("none.html"))
        .env("PGPASSWORD", pg::PASSWORD)
        .output()
        .unwrap_or_else(|e| panic!("running cubecal: {e}"));
    assert!(!out.status.success());
    assert!(
        text(&out.stderr).contains("usb:none"),
        "{}",
        text(&out.stderr)
    );
}
