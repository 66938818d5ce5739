//! Issue 31 ("defects found tried as a new user would, round 2"): the path from photos or a recorded
//! session to a profile another tool loads, each item as the user met it, through the binary.
//! The photos are `../shared/datasets/opencv_stereo_left_right` (OpenCV's left*.jpg, 9×6 board,
//! 30 mm squares); tests that need them say so and skip when the dataset is absent.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn cubecal() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cubecal"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

/// Run cubecal (in the crate's directory) with `args` to its end.
fn run<S: AsRef<OsStr>>(args: impl IntoIterator<Item = S>) -> Output {
    cubecal().args(args).output().unwrap()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The last line of stdout as JSON (with `--json`: the result, or the error object).
fn last_json(o: &Output) -> serde_json::Value {
    serde_json::from_str(stdout(o).lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("last line not JSON ({e}): {}", stdout(o)))
}

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The left photos of the OpenCV sample, or `None` (with a message) when the dataset is absent.
fn left_photos() -> Option<Vec<PathBuf>> {
    let dir = manifest_dir().join("../shared/datasets/opencv_stereo_left_right/images");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| Some(e.ok()?.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("left") && n.ends_with(".jpg"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        eprintln!("skipped: no photos in {}", dir.display());
        return None;
    }
    Some(files)
}

/// One replay of the bundled demo session, run from a temporary working directory with a relative
/// `--out run` and no `--store`: (working directory, human stdout, stderr, exit code).
struct DemoRun {
    cwd: tempfile::TempDir,
    stdout: String,
    code: Option<i32>,
}

fn demo_run() -> &'static DemoRun {
    static RUN: OnceLock<DemoRun> = OnceLock::new();
    RUN.get_or_init(|| {
        let cwd = tempfile::tempdir().unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
            .current_dir(cwd.path())
            .args(["calibrate", "--replay"])
            .arg(manifest_dir().join("fixtures/sessions/demo"))
            .args(["--out", "run"])
            .output()
            .unwrap();
        eprintln!("{}", stderr(&out));
        DemoRun {
            stdout: stdout(&out),
            code: out.status.code(),
            cwd,
        }
    })
}

impl DemoRun {
    fn dir(&self) -> PathBuf {
        self.cwd.path().join("run")
    }
}

/// Item 1: without `--store` the station says the profile is not stored and how to store or export
/// it; a store that does not exist is an error naming it (exit 3), not an empty list, and is not
/// created by looking at it.
#[test]
fn item1_the_station_says_where_the_profile_went_and_a_missing_store_is_an_error() {
    let demo = demo_run();
    assert_eq!(demo.code, Some(0), "{}", demo.stdout);
    let profile_line = demo
        .stdout
        .lines()
        .find(|l| l.starts_with("profile: "))
        .unwrap_or_else(|| panic!("no profile line: {}", demo.stdout));
    assert!(
        profile_line.contains("run/profile.json") && profile_line.contains("not stored"),
        "{profile_line}"
    );
    assert!(
        demo.stdout.contains("--store DIR")
            && demo
                .stdout
                .contains("cubecal profile export run/profile.json --format opencv"),
        "{}",
        demo.stdout
    );

    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nosuchstore");
    for args in [
        vec!["profile", "list"],
        vec!["profile", "show", "cam"],
        vec!["profile", "rollback", "cam"],
    ] {
        let out = run(args
            .iter()
            .map(OsStr::new)
            .chain([OsStr::new("--store"), missing.as_os_str()]));
        assert_eq!(out.status.code(), Some(3), "{args:?}: {}", stderr(&out));
        let err = stderr(&out);
        assert!(
            err.contains(&missing.display().to_string()) && err.contains("does not exist"),
            "{args:?}: {err}"
        );
        assert!(stdout(&out).is_empty(), "{args:?}: {}", stdout(&out));
        assert!(!missing.exists(), "{args:?} created the store");
    }
    // JSON carries the code too.
    let out = cubecal()
        .args(["profile", "list", "--json", "--store"])
        .arg(&missing)
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["exit_code"], 3, "{v}");
}

/// Item 2: `profile show` and `profile export` take a run's own `profile.json` (no store needed), as
/// `diff` and `report` do; the OpenCV YAML carries the run's camera matrix.
#[test]
fn item2_show_and_export_read_a_runs_profile_json() {
    let run = demo_run();
    let profile = run.dir().join("profile.json");
    assert!(profile.is_file(), "{}", run.stdout);
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&profile).unwrap()).unwrap();
    let fx = doc["calibration"]["camera_matrix"][0][0].as_f64().unwrap();

    let tmp = tempfile::tempdir().unwrap();
    let yaml = tmp.path().join("camera.yml");
    let out = cubecal()
        .args(["profile", "export"])
        .arg(&profile)
        .args(["--format", "opencv", "--out"])
        .arg(&yaml)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = std::fs::read_to_string(&yaml).unwrap();
    assert!(text.starts_with("%YAML:1.0"), "{text}");
    assert!(text.contains("camera_matrix"), "{text}");
    // fx is the first element of the camera matrix's data, to the digits the YAML prints.
    let data = text.split("data: [").nth(1).unwrap();
    let first: f64 = data
        .split([',', ']'])
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!((first - fx).abs() < 1e-6 * fx, "{first} vs {fx}");

    let out = cubecal()
        .args(["profile", "show"])
        .arg(&profile)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stdout(&out).contains("identity:"), "{}", stdout(&out));
    let out = cubecal()
        .args(["profile", "show", "--json"])
        .arg(&profile)
        .output()
        .unwrap();
    assert_eq!(out.stdout, std::fs::read(&profile).unwrap());
}

/// Item 3: a malformed `--set` is a usage error (2, also in JSON); a bad value names its key, from
/// `--set` and from a config file; the unknown-key message lists every valid key, uncut.
#[test]
fn item3_set_errors_are_usage_errors_and_name_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("run");
    let out = cubecal()
        .args([
            "calibrate",
            "--synthetic",
            "--set",
            "foo",
            "--json",
            "--out",
        ])
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert_eq!(last_json(&out)["exit_code"], 2);
    assert!(stderr(&out).contains("--set foo"), "{}", stderr(&out));
    assert!(!out_dir.exists());

    let out = cubecal()
        .args([
            "calibrate",
            "--synthetic",
            "--set",
            "qa.max_rms_px=abc",
            "--out",
        ])
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("command line: qa.max_rms_px: invalid type"),
        "{}",
        stderr(&out)
    );

    let cfg = tmp.path().join("station.toml");
    std::fs::write(&cfg, "[qa]\nmax_rms_px = \"abc\"\n").unwrap();
    let out = cubecal()
        .args(["calibrate", "--synthetic", "--config"])
        .arg(&cfg)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(
        stderr(&out).contains(&format!("{}: qa.max_rms_px: invalid type", cfg.display())),
        "{}",
        stderr(&out)
    );

    // Every key of [qa] in the commented example config is listed for an unknown one.
    let example = std::fs::read_to_string(manifest_dir().join("fixtures/station.toml")).unwrap();
    let qa_keys: Vec<String> = example
        .split("[qa]")
        .nth(1)
        .unwrap()
        .split("\n[")
        .next()
        .unwrap()
        .lines()
        .filter_map(|l| {
            let l = l.trim_start_matches('#').trim();
            let (k, _) = l.split_once(" = ")?;
            (!k.is_empty() && k.chars().all(|c| c.is_ascii_lowercase() || c == '_'))
                .then(|| k.to_string())
        })
        .collect();
    assert!(qa_keys.len() >= 8, "{qa_keys:?}");
    let out = cubecal()
        .args([
            "calibrate",
            "--synthetic",
            "--set",
            "qa.no_such_key=1",
            "--out",
        ])
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(err.contains("qa.no_such_key: unknown key"), "{err}");
    assert!(!err.contains("more characters"), "{err}");
    for k in &qa_keys {
        assert!(err.contains(k.as_str()), "{k} not listed: {err}");
    }
}

/// Items 4 and 5: photos without a rig are refused before anything is written, saying what to give
/// (exit 2); photos of the wrong rig accept no view, exit 5 as README says ("no calibration was
/// obtained"), and still get a report showing every view with its overlay and rejection reason.
#[test]
fn item4_5_photos_need_a_rig_and_a_failed_run_still_gets_its_report() {
    let Some(photos) = left_photos() else { return };
    let photos = &photos[..3];
    let tmp = tempfile::tempdir().unwrap();
    let out = cubecal()
        .arg("calibrate")
        .arg("--images")
        .args(photos)
        .arg("--out")
        .arg(tmp.path().join("norig"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(
        err.contains("--rig") && err.contains("--board COLSxROWS --square MM"),
        "{err}"
    );
    assert!(!tmp.path().join("norig").exists());

    let run_dir = tmp.path().join("wrong");
    let wrong_rig = manifest_dir().join("fixtures/rigs/cube_outside.toml");
    let mut args: Vec<&OsStr> = ["calibrate", "--json", "--rig"].map(OsStr::new).to_vec();
    args.extend([wrong_rig.as_os_str(), OsStr::new("--images")]);
    args.extend(photos.iter().map(|p| p.as_os_str()));
    args.extend([OsStr::new("--out"), run_dir.as_os_str()]);
    let out = run(args);
    assert_eq!(out.status.code(), Some(5), "{}", stderr(&out));
    let last = last_json(&out);
    assert_eq!(last["calibration"], serde_json::Value::Null, "{last}");
    let html = std::fs::read_to_string(run_dir.join("report.html"))
        .unwrap_or_else(|e| panic!("no report.html ({e}): {}", stderr(&out)));
    assert!(html.contains("No calibration"), "{html}");
    assert_eq!(
        html.matches("with detection overlay\" src=\"data:image/png;base64,")
            .count(),
        3
    );
    assert_eq!(html.matches("rejected: no rig face labelled").count(), 3);
}

/// Item 7: `--board COLSxROWS --square MM` is the plain board's rig: `detect` finds the same corners
/// as with `fixtures/rigs/opencv_board_9x6.toml`, and `calibrate --images` calibrates the photos
/// with it (OpenCV's sample camera: fx ≈ 536 px).
#[test]
fn item7_board_and_square_stand_for_a_plain_board_rig() {
    let Some(photos) = left_photos() else { return };
    let detect = |rig_args: &[&str]| {
        let out = cubecal()
            .args(["detect", "--json"])
            .args(rig_args)
            .arg(&photos[0])
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
        let mut v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        v[0]["time_ms"] = serde_json::Value::Null;
        v
    };
    let by_board = detect(&["--board", "9x6", "--square", "30"]);
    let by_file = detect(&["--rig", "fixtures/rigs/opencv_board_9x6.toml"]);
    assert_eq!(by_board, by_file);
    assert_eq!(
        by_board[0]["faces"][0]["corners"].as_array().unwrap().len(),
        54
    );

    // A malformed size or a board without its square is a usage error.
    for bad in [
        vec!["--board", "9by6", "--square", "30"],
        vec!["--board", "9x6"],
        vec!["--board", "1x6", "--square", "30"],
    ] {
        let out = cubecal()
            .arg("detect")
            .args(&bad)
            .arg(&photos[0])
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{bad:?}: {}", stderr(&out));
    }

    let tmp = tempfile::tempdir().unwrap();
    let out = cubecal()
        .args(["calibrate", "--json", "--board", "9x6", "--square", "30"])
        .arg("--images")
        .args(&photos)
        .arg("--out")
        .arg(tmp.path().join("run"))
        .output()
        .unwrap();
    let last = last_json(&out);
    let fx = last["calibration"]["camera_matrix"][0][0]
        .as_f64()
        .unwrap_or_else(|| panic!("no calibration: {last}\n{}", stderr(&out)));
    assert!((fx - 536.0).abs() < 15.0, "fx {fx}");
    let rig = std::fs::read_to_string(tmp.path().join("run/rig.toml")).unwrap();
    assert!(
        rig.contains("cols = 9") && rig.contains("rows = 6"),
        "{rig}"
    );
}

/// Item 9: the run report shows the station's notes (k3 fixed and why, a profile jump).
#[test]
fn item9_the_run_report_shows_the_runs_notes() {
    let run = demo_run();
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("run");
    copy_dir(&run.dir(), &copy);
    let result_path = copy.join("result.json");
    let mut result: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&result_path).unwrap()).unwrap();
    let note =
        "the profile moved by more than 5σ from the previous one of this camera (a test note)";
    result["notes"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!(note));
    let notes: Vec<String> = result["notes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap().to_string())
        .collect();
    std::fs::write(&result_path, serde_json::to_vec(&result).unwrap()).unwrap();
    let html_path = tmp.path().join("r.html");
    let out = cubecal()
        .arg("report")
        .arg(&copy)
        .arg("--out")
        .arg(&html_path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let html = std::fs::read_to_string(&html_path).unwrap();
    for n in &notes {
        let escaped = n
            .replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;");
        assert!(html.contains(&escaped), "note {n:?} missing");
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap();
        }
    }
}

/// Item 10: the profile names its session by an absolute path, also when `--out` was relative.
#[test]
fn item10_the_profile_records_the_session_path_absolute() {
    let run = demo_run();
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.dir().join("profile.json")).unwrap()).unwrap();
    let session = PathBuf::from(doc["session"]["path"].as_str().unwrap());
    assert!(session.is_absolute(), "{session:?}");
    assert!(session.join("manifest.json").is_file(), "{session:?}");
    assert_eq!(
        session.canonicalize().unwrap(),
        run.dir().join("session").canonicalize().unwrap()
    );
}

/// Item 11: the README's "Reading the verdict" commands run as written (no usage error), with a
/// store and a camera name for the placeholders.
#[test]
fn item11_readme_reading_the_verdict_commands_are_complete() {
    let readme = std::fs::read_to_string(manifest_dir().join("README.md")).unwrap();
    let block = readme
        .split("Reading the verdict:")
        .nth(1)
        .unwrap()
        .split("```")
        .nth(1)
        .unwrap();
    let store = tempfile::tempdir().unwrap();
    let commands: Vec<Vec<String>> = block
        .lines()
        .filter(|l| l.starts_with("cubecal "))
        .map(|l| {
            l.split('#')
                .next()
                .unwrap()
                .split_whitespace()
                .skip(1)
                .map(str::to_string)
                .collect()
        })
        .collect();
    assert!(!commands.is_empty(), "{block}");
    for args in commands {
        let out = cubecal()
            .args(&args)
            .arg("--store")
            .arg(store.path())
            .output()
            .unwrap();
        assert_ne!(out.status.code(), Some(2), "{args:?}: {}", stderr(&out));
        assert!(
            matches!(out.status.code(), Some(0) | Some(3)),
            "{args:?}: {}",
            stderr(&out)
        );
    }
}

/// Item 12: `profile diff` keeps a parameter fixed on one side (k3 the station fixed), marked, with
/// the other side's σ, and not counted toward the jump.
#[test]
fn item12_diff_shows_a_parameter_fixed_on_one_side() {
    let run = demo_run();
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.dir().join("profile.json")).unwrap()).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let mut estimated = doc.clone();
    estimated["calibration"]["std_dev"]["k3"] = serde_json::json!(0.02);
    estimated["calibration"]["distortion"]["coefficients"][4] = serde_json::json!(0.01);
    let mut fixed = doc.clone();
    fixed["calibration"]["std_dev"]
        .as_object_mut()
        .unwrap()
        .remove("k3");
    fixed["calibration"]["distortion"]["coefficients"][4] = serde_json::json!(0.0);
    let (a, b) = (tmp.path().join("a.json"), tmp.path().join("b.json"));
    std::fs::write(&a, serde_json::to_vec(&estimated).unwrap()).unwrap();
    std::fs::write(&b, serde_json::to_vec(&fixed).unwrap()).unwrap();
    let out = cubecal()
        .args(["profile", "diff"])
        .args([&a, &b])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = stdout(&out);
    let k3 = text
        .lines()
        .find(|l| l.trim_start().starts_with("k3 "))
        .unwrap_or_else(|| panic!("no k3 row: {text}"));
    assert!(k3.contains("fixed in the current profile"), "{k3}");
    let out = cubecal()
        .args(["profile", "diff", "--json"])
        .args([&a, &b])
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let row = v["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "k3")
        .unwrap();
    assert_eq!(row["fixed"], "current");
    assert!(
        (row["sigma"].as_f64().unwrap() - 0.02).abs() < 1e-12,
        "{row}"
    );
    assert!(
        (row["delta_sigma"].as_f64().unwrap() + 0.5).abs() < 1e-9,
        "{row}"
    );
    // Δ/σ of k3 is -0.5; nothing else moved, so the largest counted |Δ/σ| is 0.
    assert_eq!(v["max_abs_delta_sigma"], 0.0, "{v}");
}

/// Item 13: the manifest is an ordinary file like the frames beside it, and `complete` / `ended_by`
/// sit at its top level as the README says.
#[test]
fn item13_manifest_mode_and_top_level_complete() {
    use std::os::unix::fs::PermissionsExt;
    let run = demo_run();
    let session = run.dir().join("session");
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    let frame = std::fs::read_dir(&session)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "png"))
        .unwrap();
    assert_eq!(mode(&session.join("manifest.json")), mode(&frame));
    assert_ne!(mode(&frame) & 0o044, 0, "frames are readable by others");
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(session.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["complete"], true, "{}", m["complete"]);
    assert!(m.get("ended_by").is_none());
    assert!(m["config"].get("complete").is_none(), "{}", m["config"]);
}

/// Item 14, printed output: counts as counts, distortion to six decimals with names, a rig warning
/// once, and a warning when replaying a session that was recorded incomplete.
#[test]
fn item14_printed_output_is_tidy() {
    let demo = demo_run();
    let views = demo
        .stdout
        .lines()
        .find(|l| l.contains("] views "))
        .unwrap_or_else(|| panic!("no views check: {}", demo.stdout));
    assert!(!views.contains(".000000"), "{views}");
    let dist = demo
        .stdout
        .lines()
        .find(|l| l.trim_start().starts_with("distortion"))
        .unwrap();
    assert!(dist.contains("k1 ") && dist.contains(" ± "), "{dist}");
    for number in dist
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter(|t| t.contains('.'))
    {
        let decimals = number.split('.').nth(1).unwrap().len();
        assert!(decimals <= 6, "{number} in {dist}");
    }

    // A 180°-symmetric board (8 + 6 even) warns once, not twice.
    let tmp = tempfile::tempdir().unwrap();
    let out = cubecal()
        .args(["calibrate", "--board", "8x6", "--square", "30", "--images"])
        .arg("fixtures/render/cube_outside/frame_000.png")
        .arg("--out")
        .arg(tmp.path().join("sym"))
        .output()
        .unwrap();
    assert_eq!(
        stderr(&out)
            .matches("looks the same rotated by 180°")
            .count(),
        1,
        "{}",
        stderr(&out)
    );

    // A session recorded incomplete: replaying it warns.
    let session = tmp.path().join("cut");
    copy_dir(&manifest_dir().join("fixtures/sessions/demo"), &session);
    let path = session.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    m["frames"].as_array_mut().unwrap().truncate(2);
    m["complete"] = serde_json::json!(false);
    m["ended_by"] = serde_json::json!("camera unplugged at pose 2");
    std::fs::write(&path, serde_json::to_vec(&m).unwrap()).unwrap();
    let replayed = tmp.path().join("replayed");
    let out = run([
        OsStr::new("calibrate"),
        OsStr::new("--replay"),
        session.as_os_str(),
        OsStr::new("--out"),
        replayed.as_os_str(),
    ]);
    let err = stderr(&out);
    assert!(
        err.contains("recorded incomplete") && err.contains("camera unplugged at pose 2"),
        "{err}"
    );
}

/// Item 14, plots: the history plot's jump lines have a colour of their own, every parameter has its
/// own colour and equal values sit side by side; residual arrows have heads.
#[test]
fn item14_plots_tell_series_apart_and_arrows_have_heads() {
    use cubecal::report::plots::{HistoryFigure, JUMP, SERIES, arrow_path};
    assert!(SERIES.len() >= 13);
    for (i, a) in SERIES.iter().enumerate() {
        assert_ne!(*a, JUMP);
        for b in &SERIES[i + 1..] {
            assert_ne!(a, b);
        }
    }
    let fig = HistoryFigure {
        caption: String::new(),
        versions: vec!["a".into(), "b".into()],
        series: ["k2", "p1", "p2"]
            .iter()
            .map(|n| (n.to_string(), vec![Some(0.0), Some(0.0)]))
            .collect(),
        jump_sigma: 5.0,
    };
    let xs: Vec<f64> = (0..3).map(|k| fig.dodge(k)).collect();
    assert!(xs[0] < xs[1] && xs[1] < xs[2], "{xs:?}");
    assert!(xs.iter().all(|x| x.abs() < 0.5), "{xs:?}");

    let path = arrow_path((100.0, 100.0), (40.0, 0.0));
    assert_eq!(path.len(), 5, "{path:?}");
    assert_eq!(path[1], (140.0, 100.0));
    // The barbs point back from the tip, one on each side of the shaft.
    let (b1, b2) = (path[2], path[4]);
    assert!(b1.0 < 140.0 && b2.0 < 140.0, "{path:?}");
    assert!((b1.1 - 100.0) * (b2.1 - 100.0) < 0.0, "{path:?}");
}
