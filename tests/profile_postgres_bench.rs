//! The PostgreSQL store's concurrency benchmark (issue 34, acceptance 2): 8 station processes × 200
//! passing runs over 50 cameras against one durable PostgreSQL (fsync on; tests/support/pg.rs). A
//! station that gets Busy retries, as an operator would. Afterwards: every run in history exactly
//! once, one current profile per camera that reads back whole, and the commit latency's p50/p99
//! (successful commits, from the call to its return) printed.
//!
//! Ignored by default (it is a measurement, ~10 s): run it with
//! `cargo test --test profile_postgres_bench -- --ignored --nocapture`.

#![allow(clippy::print_stdout, clippy::print_stderr)]

#[path = "support/pg.rs"]
mod pg;
#[path = "support/sample_profile.rs"]
mod sample_profile;

use std::collections::BTreeSet;
use std::process::Command;
use std::time::{Duration, Instant};

use cubecal::profile::postgres::PgStore;
use cubecal::profile::{CommitOptions, ProfileError, ProfileStore, Provenance};
use rand::{Rng, SeedableRng};

const STATIONS: usize = 8;
const RUNS: usize = 200;
const CAMERAS: usize = 50;
const NAME: &str = "eight_stations_two_hundred_runs_over_fifty_cameras";
const URL_VAR: &str = "CUBECAL_BENCH_URL";
const STATION_VAR: &str = "CUBECAL_BENCH_STATION";

fn camera(c: usize) -> String {
    format!("usb:046d:0825:BENCH{c:02}")
}

/// One station process: 200 runs, each committed (retried on Busy); prints `RESULT busy lat_us…`.
fn station(url: &str, s: usize) {
    let store = PgStore::connect(url, Some(pg::PASSWORD.into())).unwrap_or_else(|e| panic!("{e}"));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(s as u64);
    let (mut busy, mut lat) = (0usize, Vec::with_capacity(RUNS));
    for r in 0..RUNS {
        let c = rng.random_range(0..CAMERAS);
        let profile = sample_profile::profile(&camera(c), (s * RUNS + r) as u64, true);
        let provenance = Provenance {
            run_id: format!("s{s}-r{r}"),
            station: format!("station-{s}"),
            report: None,
        };
        loop {
            let t0 = Instant::now();
            match store.commit_run(&profile, &CommitOptions::default(), &provenance) {
                Ok(_) => {
                    lat.push(t0.elapsed().as_micros());
                    break;
                }
                Err(ProfileError::Busy { .. }) => {
                    busy += 1;
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(e) => panic!("station {s} run {r}: {e}"),
            }
        }
    }
    let lat: Vec<String> = lat.iter().map(u128::to_string).collect();
    println!("RESULT {busy} {}", lat.join(" "));
}

fn percentile(sorted: &[u128], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i] as f64 / 1000.0
}

#[test]
#[ignore = "benchmark: cargo test --test profile_postgres_bench -- --ignored --nocapture"]
fn eight_stations_two_hundred_runs_over_fifty_cameras() {
    if let (Ok(url), Some(s)) = (
        std::env::var(URL_VAR),
        std::env::var(STATION_VAR).ok().and_then(|v| v.parse().ok()),
    ) {
        station(&url, s);
        return;
    }
    let Some(cluster) = pg::cluster_with(true) else {
        return;
    };
    let url = cluster.database("bench");
    PgStore::connect_unchecked(&url, Some(pg::PASSWORD.into()))
        .and_then(|s| s.migrate())
        .unwrap_or_else(|e| panic!("{e}"));
    let exe = std::env::current_exe().unwrap_or_else(|e| panic!("{e}"));
    let t0 = Instant::now();
    let children: Vec<_> = (0..STATIONS)
        .map(|s| {
            Command::new(&exe)
                .args([
                    NAME,
                    "--exact",
                    "--ignored",
                    "--nocapture",
                    "--test-threads=1",
                ])
                .env(URL_VAR, &url)
                .env(STATION_VAR, s.to_string())
                .stdout(std::process::Stdio::piped())
                .spawn()
                .unwrap_or_else(|e| panic!("station {s}: {e}"))
        })
        .collect();
    let (mut busy, mut lat) = (0usize, Vec::new());
    for (s, child) in children.into_iter().enumerate() {
        let out = child
            .wait_with_output()
            .unwrap_or_else(|e| panic!("station {s}: {e}"));
        assert!(out.status.success(), "station {s} failed");
        let text = String::from_utf8_lossy(&out.stdout);
        let line = text
            .lines()
            // libtest prints "test NAME ... " before the test runs, on the same line
            .find_map(|l| l.split_once("RESULT ").map(|(_, r)| r.trim()))
            .unwrap_or_else(|| panic!("station {s}: no result in {text}"));
        let mut fields = line.split(' ');
        busy += fields
            .next()
            .and_then(|b| b.parse::<usize>().ok())
            .unwrap_or_else(|| panic!("station {s}: {line}"));
        lat.extend(fields.map(|f| f.parse::<u128>().unwrap_or_else(|e| panic!("{f}: {e}"))));
    }
    let wall = t0.elapsed();
    assert_eq!(lat.len(), STATIONS * RUNS, "every run committed");
    lat.sort_unstable();

    // every passing run in history exactly once; one whole current profile per camera
    let store = PgStore::connect(&url, Some(pg::PASSWORD.into())).unwrap_or_else(|e| panic!("{e}"));
    let mut stored = Vec::new();
    let mut cameras = 0;
    for c in 0..CAMERAS {
        let Ok(history) = store.history(&camera(c)) else {
            continue;
        };
        cameras += 1;
        assert_eq!(
            history.iter().filter(|v| v.state == "current").count(),
            1,
            "{}",
            camera(c)
        );
        let (p, _) = store
            .current_profile(&camera(c))
            .unwrap_or_else(|e| panic!("{}: {e}", camera(c)));
        assert_eq!(p.identity.id, camera(c));
        stored.extend(history.into_iter().map(|v| v.run_id));
    }
    let unique: BTreeSet<&String> = stored.iter().collect();
    assert_eq!(stored.len(), STATIONS * RUNS, "no run lost or duplicated");
    assert_eq!(unique.len(), stored.len(), "no run twice");
    println!(
        "{STATIONS} stations x {RUNS} runs over {cameras} cameras: {} commits in {:.1} s, {busy} Busy retries; commit latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        lat.len(),
        wall.as_secs_f64(),
        percentile(&lat, 0.50),
        percentile(&lat, 0.99),
        percentile(&lat, 1.0),
    );
}
