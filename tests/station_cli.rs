//! `cubecal calibrate` as a user runs it: the bundled demo, exit codes, signals, help.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::BufRead;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn cubecal() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cubecal"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn demo() -> &'static Path {
    Path::new("fixtures/sessions/demo")
}

#[test]
fn the_bundled_demo_replays_to_a_passing_profile_with_the_documented_json() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str| {
        let out = cubecal()
            .args(["calibrate", "--json", "--replay"])
            .arg(demo())
            .arg("--out")
            .arg(dir.path().join(name))
            .output()
            .unwrap();
        assert_eq!(
            out.status.code(),
            Some(0),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8(out.stdout).unwrap();
        let last = text.lines().last().unwrap().to_string();
        let events = text.lines().count() - 1;
        (
            serde_json::from_str::<serde_json::Value>(&last).unwrap(),
            events,
        )
    };
    let (a, events) = run("a");
    assert!(events >= 12 * 4, "one JSON line per event: {events}");
    for key in ["verdict", "calibration", "views", "profile", "run_dir"] {
        assert!(a.get(key).is_some(), "missing {key}");
    }
    assert_eq!(a["verdict"]["pass"], serde_json::json!(true));
    for c in a["verdict"]["checks"].as_array().unwrap() {
        for key in ["name", "value", "threshold", "pass"] {
            assert!(c.get(key).is_some(), "check without {key}: {c}");
        }
    }
    assert_eq!(a["views"].as_array().unwrap().len(), 12);
    let profile = a["profile"].as_str().unwrap();
    assert!(Path::new(profile).exists());
    // The demo's camera (fixtures/README.md): fx = fy = 560, principal point at the centre.
    let k = &a["calibration"]["camera_matrix"];
    let fx = k[0][0].as_f64().unwrap();
    assert!((fx - 560.0).abs() / 560.0 < 5e-4, "fx {fx}");
    // Replayed twice: the same calibration to the last bit.
    let (b, _) = run("b");
    assert_eq!(a["calibration"].to_string(), b["calibration"].to_string());
}

#[test]
fn no_camera_exits_4_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let out = cubecal()
        .args([
            "calibrate",
            "--device",
            "/dev/video-cubecal-missing",
            "--turntable",
            "none",
            "--out",
        ])
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(4), "{err}");
    assert!(err.contains("/dev/video-cubecal-missing"), "{err}");
}

#[test]
fn a_bad_config_names_the_key_and_exits_3() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("station.toml");
    std::fs::write(&cfg, "[plan]\nposes = 12\n[qa]\nmax_rms_pixels = 0.3\n").unwrap();
    let out = cubecal()
        .args(["calibrate", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(
        err.contains("max_rms_pixels") && err.contains("station.toml"),
        "{err}"
    );
    let out = cubecal()
        .args(["calibrate", "--set", "plan.sweep_deg=400"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(err.contains("plan.sweep_deg"), "{err}");
}

#[test]
fn help_documents_every_option() {
    let out = cubecal().args(["calibrate", "--help"]).output().unwrap();
    let help = String::from_utf8(out.stdout).unwrap();
    for flag in [
        "--config",
        "--device",
        "--replay",
        "--images",
        "--synthetic",
        "--turntable",
        "--rig",
        "--store",
        "--out",
        "--poses",
        "--sweep-deg",
        "--device-id",
        "--set",
        "--json",
    ] {
        assert!(help.contains(flag), "--help lacks {flag}:\n{help}");
    }
}

#[test]
fn sigterm_mid_run_exits_130_with_the_session_marked_incomplete() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut child = cubecal()
        .args([
            "calibrate",
            "--synthetic",
            "--turntable",
            "sim-grbl",
            "--set",
            "synthetic.width=640",
            "--set",
            "synthetic.height=480",
            "--set",
            "synthetic.fx=560.0",
            "--set",
            "synthetic.fy=560.0",
            "--out",
        ])
        .arg(&run)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let mut lines = std::io::BufReader::new(stderr).lines();
    // Wait for the second pose, then SIGTERM.
    loop {
        let line = lines.next().expect("cubecal ended before pose01").unwrap();
        if line.starts_with("pose01") {
            break;
        }
    }
    let t = Instant::now();
    let pid = child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap()
            .success()
    );
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = child.wait().unwrap();
    let took = t.elapsed();
    assert_eq!(status.code(), Some(130), "{rest:?}");
    assert!(took < Duration::from_secs(5), "took {took:?}");
    assert!(rest.iter().any(|l| l.contains("interrupted")), "{rest:?}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("session/manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["complete"], serde_json::json!(false));
    assert!(!run.join("profile.json").exists());
}

#[test]
fn a_passing_replay_goes_into_the_profile_store_and_a_failing_one_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let ok = cubecal()
        .args(["calibrate", "--json", "--replay"])
        .arg(demo())
        .arg("--out")
        .arg(dir.path().join("a"))
        .arg("--store")
        .arg(&store)
        .output()
        .unwrap();
    assert_eq!(
        ok.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let last: serde_json::Value = serde_json::from_str(
        String::from_utf8(ok.stdout)
            .unwrap()
            .lines()
            .last()
            .unwrap(),
    )
    .unwrap();
    let current = std::path::PathBuf::from(last["profile"].as_str().unwrap());
    assert!(
        current.starts_with(&store) && current.ends_with("current.json"),
        "{current:?}"
    );
    assert!(dir.path().join("a/report.html").exists());
    let before = std::fs::read(&current).unwrap();
    // The same session judged by a stricter verdict: rejected (6), the stored profile untouched.
    let bad = cubecal()
        .args(["calibrate", "--replay"])
        .arg(demo())
        .arg("--out")
        .arg(dir.path().join("b"))
        .arg("--store")
        .arg(&store)
        .args(["--set", "qa.min_coverage=0.9"])
        .output()
        .unwrap();
    assert_eq!(
        bad.status.code(),
        Some(6),
        "{}",
        String::from_utf8_lossy(&bad.stderr)
    );
    assert_eq!(std::fs::read(&current).unwrap(), before);
    let list = cubecal()
        .args(["profile", "list", "--store"])
        .arg(&store)
        .output()
        .unwrap();
    assert!(
        String::from_utf8_lossy(&list.stdout).contains("demo-camera"),
        "{}",
        String::from_utf8_lossy(&list.stdout)
    );
}

#[test]
fn storing_a_synthetic_run_needs_a_device_id() {
    let dir = tempfile::tempdir().unwrap();
    let out = cubecal()
        .args(["calibrate", "--synthetic", "--store"])
        .arg(dir.path().join("store"))
        .arg("--out")
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--device-id"), "{err}");
}
