//! Issue 17, items 1–5: the solver's outlier rejection, input checks and undetermined parameters,
//! against exact synthetic ground truth (`cubecal::synthetic`) and the real detections of
//! `../shared/datasets/opencv_stereo_left_right` (the 13 left images, 9×6 board).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use cubecal::calib::observations::Observations;
use cubecal::calib::{self, CalibError, Calibration, Fix, SolveOptions, View};
use cubecal::camera::{Camera, DistortionModel, idx};
use cubecal::render::correspondences::{add_noise, cube_scenario, reference_camera};
use nalgebra::Vector2;

/// Move point `j` of view `i` by `dist_px` in a direction that varies with the point.
fn displace(views: &mut [View], i: usize, j: usize, dist_px: f64) {
    let angle = 0.7 * (i * 31 + j) as f64;
    views[i].points[j].uv += Vector2::new(angle.cos(), angle.sin()) * dist_px;
}

/// The rejected points as (view index, point index).
fn dropped(cal: &Calibration) -> BTreeSet<(usize, usize)> {
    cal.views
        .iter()
        .enumerate()
        .flat_map(|(i, v)| v.outliers.iter().map(move |&j| (i, j)))
        .collect()
}

fn with_k(k: f64) -> SolveOptions {
    SolveOptions {
        outlier_sigma: Some(k),
        ..SolveOptions::default()
    }
}

/// Item 1: outliers of several sizes and counts per view are dropped, and nothing else (at k = 5 a
/// clean point is dropped with probability exp(−12.5) = 4e-6, so none of the ~1500 is).
#[test]
fn outlier_rejection_drops_exactly_the_injected_points() {
    let truth = reference_camera();
    let sc = cube_scenario(&truth, 200.0, 10, 17);
    let sigma = 0.3;
    let mut views = add_noise(&sc.views, sigma, 99);
    // (view, point, size px): one gross outlier in a view, one medium, three of mixed sizes in one
    // view, five small ones (27σ) in one view, and a 4 px one (13σ).
    let injected: Vec<(usize, usize, f64)> = vec![
        (0, 10, 40.0),
        (1, 50, 25.0),
        (2, 3, 60.0),
        (2, 40, 20.0),
        (2, 90, 10.0),
        (3, 5, 8.0),
        (3, 25, 8.0),
        (3, 45, 8.0),
        (3, 65, 8.0),
        (3, 85, 8.0),
        (4, 70, 4.0),
    ];
    for &(i, j, d) in &injected {
        displace(&mut views, i, j, d);
    }
    let expected: BTreeSet<(usize, usize)> = injected.iter().map(|&(i, j, _)| (i, j)).collect();
    let cal = calib::solve(&views, truth.image_size, &with_k(5.0)).unwrap();
    assert_eq!(dropped(&cal), expected);
    // With the outliers gone the result is that of clean data: within 3σ of the truth.
    for k in [idx::FX, idx::FY, idx::CX, idx::CY, idx::K1] {
        let err = (cal.camera.params[k] - truth.params[k]).abs();
        assert!(
            err < 3.0 * cal.std_dev[k],
            "param {k}: error {err} vs σ {}",
            cal.std_dev[k]
        );
    }
    assert!((cal.sigma_px - sigma).abs() < 0.03, "σ̂ {}", cal.sigma_px);

    // At k = 3 every injected point goes, plus clean ones at the expected rate (1.1 %, about 17 of
    // the ~1500 here; allow up to 35).
    let cal3 = calib::solve(&views, truth.image_size, &with_k(3.0)).unwrap();
    let d3 = dropped(&cal3);
    assert!(expected.is_subset(&d3), "{expected:?} not all in {d3:?}");
    let extra = d3.len() - expected.len();
    eprintln!("k = 3: {extra} clean points dropped besides the injected ones");
    assert!(extra <= 35, "{extra} clean points dropped");
    // No view loses more than a handful of points (the old procedure emptied views with an outlier).
    for v in &cal3.views {
        assert!(v.outliers.len() <= 8, "{}: {:?}", v.name, v.outliers);
    }
}

/// Item 1: the false-rejection rate on clean data at k = 3 matches `exp(−k²/2) = 1.11 %`, the
/// probability that a 2D Gaussian residual's norm exceeds kσ (module docs of `calib::lm`).
#[test]
fn false_rejection_rate_on_clean_data_matches_the_sigma_estimate() {
    let truth = reference_camera();
    let k: f64 = 3.0;
    let p = (-k * k / 2.0).exp();
    let (mut n, mut rejected) = (0usize, 0usize);
    for seed in [1u64, 2, 3] {
        let sc = cube_scenario(&truth, 200.0, 20, 100 + seed);
        let views = add_noise(&sc.views, 0.3, seed);
        let cal = calib::solve(&views, truth.image_size, &with_k(k)).unwrap();
        let d = dropped(&cal).len();
        n += cal.n_points + d;
        rejected += d;
    }
    let expected = p * n as f64;
    let sd = (n as f64 * p * (1.0 - p)).sqrt();
    eprintln!(
        "k = {k}: {rejected} of {n} clean points rejected ({:.2} %), expected {expected:.1} ± {sd:.1} ({:.2} %)",
        100.0 * rejected as f64 / n as f64,
        100.0 * p
    );
    assert!(
        (rejected as f64 - expected).abs() < 4.0 * sd,
        "{rejected} rejected, expected {expected:.1} ± {sd:.1}"
    );
}

fn cubecal(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run cubecal")
}

/// The 13 left images of the OpenCV sample set, detected by `cubecal detect` and read back as
/// observations (which also checks that `solve` input accepts detect's output, item 11).
fn opencv_left_observations(dir: &Path) -> Observations {
    let images = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/datasets/opencv_stereo_left_right/images");
    let mut left: Vec<PathBuf> = std::fs::read_dir(&images)
        .unwrap_or_else(|e| panic!("dataset missing at {}: {e}", images.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_string_lossy().starts_with("left"))
        .collect();
    left.sort();
    assert_eq!(left.len(), 13);
    let mut args = vec![
        "detect".to_string(),
        "--json".into(),
        "--rig".into(),
        "fixtures/rigs/opencv_board_9x6.toml".into(),
    ];
    args.extend(left.iter().map(|p| p.display().to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = cubecal(&args);
    assert_eq!(out.status.code(), Some(0));
    let path = dir.join("detections.json");
    std::fs::write(&path, &out.stdout).unwrap();
    let obs = Observations::load(&path).unwrap();
    assert_eq!(obs.image_size, [640, 480]);
    assert_eq!(obs.views.len(), 13);
    assert!(obs.views.iter().all(|v| v.points.len() == 54));
    obs
}

/// Item 1 on real detections, as the issue reproduced it: one corner of one view moved by 40 px and
/// one of another by 25 px. The rejection drops those two on top of what it drops on the clean
/// data, and nothing else.
#[test]
fn real_detections_lose_only_the_injected_outliers() {
    let dir = tempfile::tempdir().unwrap();
    let obs = opencv_left_observations(dir.path());
    // The ordinary (equal-weight) solve the issue reproduced this with: every corner alike (the
    // covariances detect's output carries are left out). Weighted by the corners' own covariances,
    // and with the station's equal weights (alike but for corners whose σ is over twice the
    // median's), the two injected points are dropped too; which borderline clean points join them
    // then shifts (checked below).
    let equal = SolveOptions {
        weighting: calib::Weighting::Equal,
        ..with_k(3.0)
    };
    let plain = |views: &[calib::View]| -> Vec<calib::View> {
        (views.iter().cloned())
            .map(|mut v| {
                v.points.iter_mut().for_each(|p| p.cov = None);
                v
            })
            .collect()
    };
    let clean = calib::solve(&plain(&obs.views), obs.image_size, &equal).unwrap();
    let mut views = obs.views.clone();
    displace(&mut views, 2, 10, 40.0);
    displace(&mut views, 5, 30, 25.0);
    for opts in [with_k(3.0), equal.clone()] {
        let weighted = calib::solve(&views, obs.image_size, &opts).unwrap();
        let w = dropped(&weighted);
        assert!(
            w.contains(&(2, 10)) && w.contains(&(5, 30)),
            "{:?} solve kept an injected outlier: {w:?}",
            opts.weighting
        );
    }
    let cal = calib::solve(&plain(&views), obs.image_size, &equal).unwrap();
    let mut expected = dropped(&clean);
    expected.insert((2, 10));
    expected.insert((5, 30));
    let n = obs.views.len() * 54;
    eprintln!(
        "clean: {} of {n} dropped ({:.1} %): {:?}",
        dropped(&clean).len(),
        100.0 * dropped(&clean).len() as f64 / n as f64,
        dropped(&clean)
    );
    assert_eq!(dropped(&cal), expected);
}

/// Item 2: points outside the stated image are bad input naming the view and point; a solved
/// principal point outside the image is a failed calibration, not a result.
#[test]
fn image_size_is_checked_against_points_and_principal_point() {
    let truth = reference_camera();
    let sc = cube_scenario(&truth, 200.0, 6, 7);
    let e = calib::solve(&sc.views, [640, 480], &SolveOptions::default()).unwrap_err();
    assert!(
        matches!(
            e,
            CalibError::PointOutsideImage {
                width: 640,
                height: 480,
                ..
            }
        ),
        "{e}"
    );
    assert_eq!(e.exit_code(), 3);
    assert!(e.to_string().contains("view 'view00': point"), "{e}");

    // Crop the images to their right part, x ≥ 700: the principal point (645.2 − 700 = −54.8) is
    // then left of the 580 px wide image. The data still determine it there, and the solver refuses
    // to return it.
    let cropped: Vec<View> = sc
        .views
        .iter()
        .map(|v| View {
            name: v.name.clone(),
            points: v
                .points
                .iter()
                .map(|c| calib::Correspondence {
                    xyz: c.xyz,
                    uv: c.uv - Vector2::new(700.0, 0.0),
                    cov: c.cov,
                })
                .filter(|c| c.uv.x >= 0.0 && c.uv.x <= 579.0)
                .collect(),
        })
        .collect();
    assert!(cropped.iter().all(|v| v.points.len() >= 20));
    let e = calib::solve(&cropped, [580, 960], &SolveOptions::default()).unwrap_err();
    match &e {
        CalibError::PrincipalPointOutside { cx, .. } => assert!((cx + 54.8).abs() < 1e-3, "{cx}"),
        other => panic!("{other}"),
    }
    assert_eq!(e.exit_code(), 5);
}

/// Item 3: absurd magnitudes are bad input (exit 3) with a message naming the view and point.
#[test]
fn absurd_magnitudes_are_bad_input_naming_view_and_point() {
    let truth = reference_camera();
    let sc = cube_scenario(&truth, 200.0, 6, 7);
    let mut views = sc.views.clone();
    views[3].points[7].uv.x = 1e300;
    let e = calib::solve(&views, truth.image_size, &SolveOptions::default()).unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    assert!(e.to_string().contains("view 'view03': point 7"), "{e}");
    assert!(!e.to_string().contains("coincide"), "{e}");
    let mut views = sc.views.clone();
    views[2].points[4].xyz.y = 1e300;
    let e = calib::solve(&views, truth.image_size, &SolveOptions::default()).unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    assert!(e.to_string().contains("view 'view02': point 4"), "{e}");
}

/// Item 4: with the rational model on data without distortion, k4..k6 cannot be told apart from
/// k1..k3 (at zero distortion ∂/∂k4 = −∂/∂k1, and so on): the error names them, and fixing k4, k5,
/// k6 makes the problem solvable.
#[test]
fn brown8_names_the_undetermined_parameters_and_they_can_be_fixed() {
    let truth = Camera::pinhole([1280, 960], 1002.5, 998.0, 645.2, 476.8);
    let sc = cube_scenario(&truth, 200.0, 8, 5);
    let brown8 = SolveOptions {
        model: DistortionModel::Brown8,
        ..SolveOptions::default()
    };
    let e = calib::solve(&sc.views, truth.image_size, &brown8).unwrap_err();
    match &e {
        CalibError::Undetermined { params } => {
            for p in ["k1", "k4"] {
                assert!(params.iter().any(|q| q == p), "{p} not in {params:?}");
            }
            assert!(!params.iter().any(|q| q == "fx" || q == "cx"), "{params:?}");
        }
        other => panic!("{other}"),
    }
    assert!(e.to_string().contains("k4"), "{e}");
    assert_eq!(e.exit_code(), 5);
    let fixed = SolveOptions {
        fix: Fix {
            k4: true,
            k5: true,
            k6: true,
            ..Fix::default()
        },
        ..brown8
    };
    let cal = calib::solve(&sc.views, truth.image_size, &fixed).unwrap();
    let c = cal.camera.distortion_coefficients();
    assert_eq!(&c[5..], &[0.0, 0.0, 0.0]);
    assert!((cal.camera.fx() - 1002.5).abs() < 1e-6);
    assert!(!cal.free_params.contains(&"k4"));
}

/// Item 5: a parameter whose σ far exceeds its value is named by `undetermined_parameters`; the
/// well-determined ones are not.
#[test]
fn undetermined_parameters_names_k3_on_the_cube_fixture() {
    let obs = Observations::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/observations/cube_synthetic.json"
    )))
    .unwrap();
    let cal = calib::solve(&obs.views, obs.image_size, &SolveOptions::default()).unwrap();
    let u = calib::undetermined_parameters(&cal);
    let names: Vec<&str> = u.iter().map(|p| p.name).collect();
    eprintln!("{u:?}");
    assert!(names.contains(&"k3"), "{names:?}");
    for p in &u {
        assert!(p.std_dev > p.value.abs());
        assert!(p.effect_px > calib::UNDETERMINED_EFFECT_PX);
    }
    for good in ["fx", "fy", "cx", "cy", "k1", "p1", "p2"] {
        assert!(!names.contains(&good), "{good} flagged: {u:?}");
    }
    // 20 views with the same noise pin every parameter down: nothing is flagged.
    let truth = reference_camera();
    let sc = cube_scenario(&truth, 200.0, 20, 11);
    let views = add_noise(&sc.views, 0.1, 5);
    let cal = calib::solve(&views, truth.image_size, &SolveOptions::default()).unwrap();
    let u = calib::undetermined_parameters(&cal);
    assert!(u.is_empty(), "{u:?}");
}

/// The station's k3 rule (`insignificant_at_border`): a k3 within 2σ of zero that moves the image border
/// by more than a pixel per σ is flagged even when σ < |k3| (the k3 = 2.1 ± 2.0 that a turntable run with
/// corners in the middle third of the image produced); at 2.5σ it is kept; with 20 views nothing is.
#[test]
fn insignificant_k3_is_flagged_up_to_two_sigma() {
    let obs = Observations::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/observations/cube_synthetic.json"
    )))
    .unwrap();
    let mut cal = calib::solve(&obs.views, obs.image_size, &SolveOptions::default()).unwrap();
    let sd = cal.std_dev[idx::K3];
    assert!(calib::insignificant_at_border(&cal, idx::K3).is_some());
    cal.camera.params[idx::K3] = 1.5 * sd;
    let flagged = calib::insignificant_at_border(&cal, idx::K3).expect("1.5σ flagged");
    assert!(flagged.effect_px > calib::UNDETERMINED_EFFECT_PX);
    let names: Vec<&str> = calib::undetermined_parameters(&cal)
        .iter()
        .map(|p| p.name)
        .collect();
    assert!(!names.contains(&"k3"), "σ < |k3|: not undetermined");
    cal.camera.params[idx::K3] = -2.5 * sd;
    assert!(calib::insignificant_at_border(&cal, idx::K3).is_none());
    let truth = reference_camera();
    let sc = cube_scenario(&truth, 200.0, 20, 11);
    let views = add_noise(&sc.views, 0.1, 5);
    let cal = calib::solve(&views, truth.image_size, &SolveOptions::default()).unwrap();
    let k3 = calib::insignificant_at_border(&cal, idx::K3);
    assert!(k3.is_none(), "{k3:?}");
}

// ---- Items 6–12: the command line. ----

fn stderr(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn stdout(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Item 6: a closed stdout (`| head -1`) stops the command quietly with exit 0, no panic.
#[test]
fn closed_pipe_stops_quietly() {
    use std::process::Stdio;
    for json in [false, true] {
        let mut args = vec!["solve", "fixtures/observations/cube_synthetic.json"];
        if json {
            args.push("--json");
        }
        let mut child = Command::new(env!("CARGO_BIN_EXE_cubecal"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Close the reading end before the solve (≈ 0.1 s) has printed anything.
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        assert_eq!(out.status.code(), Some(0), "json {json}: {}", stderr(&out));
        assert!(!stderr(&out).contains("panicked"), "{}", stderr(&out));
    }
}

/// Item 7: usage errors exit 2 before any device is opened, and are JSON with --json.
#[test]
fn usage_errors_exit_2_before_devices_and_as_json() {
    let cases: &[&[&str]] = &[
        &[
            "record",
            "--device",
            "/dev/nonexistent-video",
            "--out",
            "/tmp/x",
            "--format",
            "FOO",
        ],
        &[
            "record",
            "--device",
            "/dev/nonexistent-video",
            "--out",
            "/tmp/x",
            "--frames",
            "0",
        ],
        &[
            "record",
            "--device",
            "/dev/nonexistent-video",
            "--out",
            "/tmp/x",
            "--width",
            "0",
        ],
        &["turntable", "status", "--protocol", "grbl"],
        &["turntable", "status", "--protocol", "zaber"],
        &[
            "solve",
            "fixtures/observations/cube_synthetic.json",
            "--reject-outliers",
            "0",
        ],
        &[
            "solve",
            "fixtures/observations/cube_synthetic.json",
            "--reject-outliers",
            "-3",
        ],
    ];
    for args in cases {
        let out = cubecal(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", stderr(&out));
        let mut with_json = args.to_vec();
        with_json.push("--json");
        let out = cubecal(&with_json);
        assert_eq!(out.status.code(), Some(2), "{with_json:?}");
        let v: serde_json::Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{with_json:?}: not JSON ({e}): {}", stdout(&out)));
        assert_eq!(v["exit_code"], 2);
        assert!(v["error"].as_str().is_some_and(|s| !s.is_empty()), "{v}");
    }
}

/// Item 8: failing to write an output file is exit 7 (`exit::IO`) with the user's path, not the
/// temporary's.
#[test]
fn unwritable_output_is_exit_7_naming_the_users_path() {
    // (tempfile's own directories are called .tmpXXXX too: use another name.)
    let dir = tempfile::Builder::new()
        .prefix("cubecal-")
        .tempdir()
        .unwrap();
    let target = dir.path().join("missing/overlay.png");
    let out = cubecal(&[
        "detect",
        "--rig",
        "fixtures/rigs/cube_outside.toml",
        "fixtures/render/cube_outside/frame_000.png",
        "--overlay",
        target.to_str().unwrap(),
    ]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(7), "{err}");
    assert!(err.contains(target.to_str().unwrap()), "{err}");
    assert!(!err.contains(".tmp"), "{err}");
}

/// Item 9: negative numbers are accepted without `=`.
#[test]
fn negative_numbers_need_no_equals_sign() {
    let dir = tempfile::tempdir().unwrap();
    let out = cubecal(&[
        "render",
        "fixtures/rigs/cube_outside.toml",
        "--out",
        dir.path().to_str().unwrap(),
        "--width",
        "80",
        "--height",
        "60",
        "--fx",
        "60",
        "--fy",
        "60",
        "--cx",
        "-5",
        "--cy",
        "-2.5",
        "--supersample",
        "1",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("frame_000.json")).unwrap()).unwrap();
    let text = truth.to_string();
    assert!(text.contains("-5.0") && text.contains("-2.5"), "{text}");
}

/// Item 10: no ANSI colour codes in logs when stderr is not a terminal.
#[test]
fn logs_are_plain_when_stderr_is_not_a_terminal() {
    let out = cubecal(&["-vv", "solve", "fixtures/observations/cube_synthetic.json"]);
    assert_eq!(out.status.code(), Some(0));
    let err = stderr(&out);
    assert!(err.contains("INFO"), "no logs: {err}");
    assert!(!err.contains('\u{1b}'), "ANSI escape in {err:?}");
}

/// Item 11: `solve` reads `detect --json` output; a parse error on a huge one-line file is cut.
#[test]
fn solve_reads_detect_output_and_long_errors_are_cut() {
    let dir = tempfile::tempdir().unwrap();
    let obs = opencv_left_observations(dir.path());
    let out = cubecal(&[
        "solve",
        dir.path().join("detections.json").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(
        stdout(&out).contains("13 views, 702 points, image 640×480"),
        "{}",
        stdout(&out)
    );
    assert_eq!(obs.views[0].name, "left01");

    let long = dir.path().join("long.toml");
    std::fs::write(&long, format!("name = \"x\" {}\n", "a".repeat(100_000))).unwrap();
    let out = cubecal(&[
        "rig",
        "print",
        long.to_str().unwrap(),
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(3));
    let err = stderr(&out);
    assert!(err.len() < 2000, "{} bytes of error", err.len());
    assert!(err.contains("more characters"), "{err}");
}

/// Item 12: plurals and words instead of internal names; overlay names that promise another format;
/// stale frames; duplicate view names; unknown keys; contradictory skew options.
#[test]
fn small_cli_defects() {
    let dir = tempfile::tempdir().unwrap();
    // One view of the cube fixture: "1 view", no Rust names in the output.
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/observations/cube_synthetic.json"),
    )
    .unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let views = v["views"].as_array_mut().unwrap();
    views.truncate(1);
    let one = dir.path().join("one.json");
    std::fs::write(&one, v.to_string()).unwrap();
    let out = cubecal(&["solve", one.to_str().unwrap(), "--model", "pinhole"]);
    let text = stdout(&out);
    assert!(text.contains(": 1 view, "), "{text}");
    for internal in ["Dlt", "small_predicted_decrease", "1 views", "1 outliers"] {
        assert!(!text.contains(internal), "{internal} in {text}");
    }

    let out = cubecal(&[
        "detect",
        "--rig",
        "fixtures/rigs/cube_outside.toml",
        "fixtures/render/cube_outside/frame_000.png",
        "--overlay",
        dir.path().join("o.jpg").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(!dir.path().join("o.jpg").exists());

    // A shorter render into a used directory leaves no frames of the longer one.
    let frames = dir.path().join("frames");
    let render = |n: &str| {
        cubecal(&[
            "render",
            "fixtures/rigs/cube_outside.toml",
            "--out",
            frames.to_str().unwrap(),
            "--poses",
            n,
            "--width",
            "64",
            "--height",
            "48",
            "--fx",
            "50",
            "--fy",
            "50",
            "--supersample",
            "1",
        ])
    };
    assert_eq!(render("turntable:3").status.code(), Some(0));
    std::fs::write(frames.join("notes.txt"), "mine").unwrap();
    assert_eq!(render("turntable:1").status.code(), Some(0));
    let mut left: Vec<String> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["frame_000.json", "frame_000.png", "notes.txt"]);

    let dup = dir.path().join("dup.json");
    std::fs::write(
        &dup,
        r#"{"image_size": [640, 480], "views": [
            {"name": "a", "points": [{"xyz": [0, 0, 0], "uv": [1, 1]}]},
            {"name": "a", "points": [{"xyz": [0, 0, 0], "uv": [1, 1]}]}]}"#,
    )
    .unwrap();
    let out = cubecal(&["solve", dup.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(3));
    assert!(
        stderr(&out).contains("name 'a' is already used"),
        "{}",
        stderr(&out)
    );

    let unknown = dir.path().join("unknown.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&one).unwrap()).unwrap();
    v["views"][0]["nmae"] = "typo".into();
    std::fs::write(&unknown, v.to_string()).unwrap();
    let out = cubecal(&["solve", unknown.to_str().unwrap(), "--model", "pinhole"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stderr(&out).contains("views[0].nmae"), "{}", stderr(&out));

    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--estimate-skew",
        "--fix",
        "skew",
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
}

/// Items 4 and 5 at the command line: `--fix k4,k5,k6` exists, and an undetermined parameter is
/// named in a warning (human) and in `undetermined` (JSON).
#[test]
fn solve_warns_about_undetermined_parameters_and_fixes_k4_to_k6() {
    let out = cubecal(&["solve", "fixtures/observations/cube_synthetic.json"]);
    assert_eq!(out.status.code(), Some(0));
    assert!(stdout(&out).contains("warning: k3 = "), "{}", stdout(&out));
    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let names: Vec<&str> = v["undetermined"]
        .as_array()
        .unwrap()
        .iter()
        .map(|u| u["name"].as_str().unwrap())
        .collect();
    assert!(names.contains(&"k3"), "{names:?}");
    let out = cubecal(&[
        "solve",
        "fixtures/observations/cube_synthetic.json",
        "--model",
        "brown8",
        "--fix",
        "k4,k5,k6",
        "--json",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["distortion"]["coefficients"][5], 0.0);
    assert!(v["std_dev"].get("k4").is_none());
}
