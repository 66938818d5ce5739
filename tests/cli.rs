//! The `cubecal` binary end to end: output formats and documented exit codes.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;
use std::process::{Command, Output};

fn cubecal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run cubecal")
}

fn write_temp(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
    let p = dir.path().join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn solve_prints_json_with_the_documented_fields() {
    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--json",
    ]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "image_size",
        "camera_matrix",
        "distortion",
        "std_dev",
        "rms_px",
        "views",
        "iterations",
        "termination",
    ] {
        assert!(v.get(key).is_some(), "missing {key}");
    }
    assert_eq!(v["distortion"]["model"], "brown5");
    assert_eq!(v["distortion"]["coefficients"].as_array().unwrap().len(), 5);
    let fx = v["camera_matrix"][0][0].as_f64().unwrap();
    let sd = v["std_dev"]["fx"].as_f64().unwrap();
    // Ground truth of the fixture: fx = 1002.5 (see fixtures/README.md).
    assert!((fx - 1002.5).abs() < 3.0 * sd, "fx {fx} ± {sd}");
    let view = &v["views"][0];
    for key in ["name", "rotation", "translation", "rms_px", "outliers"] {
        assert!(view.get(key).is_some(), "view missing {key}");
    }
}

#[test]
fn solve_human_output_and_fix_options() {
    let out = cubecal(&[
        "solve",
        "fixtures/observations/bailus_left.json",
        "--fix",
        "tangential,k3",
    ]);
    assert_eq!(out.status.code(), Some(0));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("p1 = 0.000000 (fixed)"), "{text}");
    assert!(text.contains("converged"), "{text}");

    // kb4's coefficients are k1..k4 with their own σ (not OpenCV's k1, k2, p1, p2)
    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--model",
        "kb4",
        "--fix",
        "k4",
    ]);
    assert_eq!(out.status.code(), Some(0));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("  k3 = ") && text.contains(" ± "), "{text}");
    assert!(text.contains("  k4 = 0.000000 (fixed)"), "{text}");
    assert!(!text.contains("p1 = ") && !text.contains("p2 = "), "{text}");
}

#[test]
fn bad_input_exits_3_with_a_message_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "malformed.json",
            "{\"image_size\": [640, 480], \"views\": [",
            "malformed.json:1:",
        ),
        (
            "empty_views.json",
            "{\"image_size\": [640, 480], \"views\": []}",
            "no views",
        ),
        (
            "empty_view.json",
            "{\"image_size\": [640, 480], \"views\": [{\"name\": \"a\", \"points\": []}]}",
            "points: empty",
        ),
        (
            "few.json",
            "{\"image_size\": [640, 480], \"views\": [{\"name\": \"a\", \"points\": [
              {\"xyz\": [0,0,0], \"uv\": [1,1]}, {\"xyz\": [1,0,0], \"uv\": [2,1]},
              {\"xyz\": [0,1,0], \"uv\": [1,2]}, {\"xyz\": [0,0,1], \"uv\": [3,3]},
              {\"xyz\": [1,1,1], \"uv\": [4,4]}]}]}",
            "at least 6",
        ),
        (
            "dup.json",
            "{\"image_size\": [640, 480], \"views\": [{\"name\": \"a\", \"points\": [
              {\"xyz\": [0,0,0], \"uv\": [1,1]}, {\"xyz\": [0,0,0], \"uv\": [2,1]}]}]}",
            "duplicates",
        ),
    ];
    for (name, text, needle) in cases {
        let p = write_temp(&dir, name, text);
        let out = cubecal(&["solve", p.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(3), "{name}: {err}");
        assert!(err.contains(needle), "{name}: {err}");
        assert!(!err.contains("panicked"), "{name}: {err}");
    }
    let out = cubecal(&["solve", "/nonexistent/obs.json"]);
    assert_eq!(out.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/obs.json"));
    // JSON error report on stdout with --json.
    let p = write_temp(&dir, "m2.json", "[");
    let out = cubecal(&["solve", p.to_str().unwrap(), "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["exit_code"], 3);
}

#[test]
fn non_convergence_exits_5_and_says_so() {
    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--max-iterations",
        "1",
    ]);
    assert_eq!(out.status.code(), Some(5));
    assert!(String::from_utf8_lossy(&out.stdout).contains("NOT CONVERGED"));
}

#[test]
fn usage_errors_exit_2() {
    let out = cubecal(&["solve"]);
    assert_eq!(out.status.code(), Some(2));
    let out = cubecal(&["solve", "x.json", "--model", "tsai"]);
    assert_eq!(out.status.code(), Some(2));
    let out = cubecal(&["--help"]);
    assert_eq!(out.status.code(), Some(0));
}

/// `render --model kb4` renders through the fisheye (its ground truth names the model and the four
/// coefficients); a Brown–Conrady render with a k4, or a fisheye with tangential terms, is refused.
#[test]
fn render_takes_the_fisheye_model() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("fe");
    let rig = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    );
    let o = cubecal(&[
        "render",
        rig,
        "--out",
        out.to_str().unwrap(),
        "--width",
        "320",
        "--height",
        "240",
        "--fx",
        "90",
        "--fy",
        "90",
        "--model",
        "kb4",
        "--k1",
        "0.02",
        "--k4",
        "-0.0001",
    ]);
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("frame_000.json")).unwrap()).unwrap();
    let cam = &truth["camera"];
    assert_eq!(cam["distortion_model"], "kb4", "{cam}");
    assert_eq!(
        cam["distortion_coefficients"],
        serde_json::json!([0.02, 0.0, 0.0, -0.0001])
    );
    let o = cubecal(&["render", rig, "--out", out.to_str().unwrap(), "--k4", "0.1"]);
    assert_eq!(o.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&o.stderr).contains("k4"));
    let o = cubecal(&[
        "render",
        rig,
        "--out",
        out.to_str().unwrap(),
        "--model",
        "kb4",
        "--p1",
        "0.001",
    ]);
    assert_eq!(o.status.code(), Some(3));
}
