//! `cubecal detect` end to end: the JSON shape, accuracy against rendered ground truth, overlays, and
//! the documented exit codes for bad images.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

const RIG: &str = "fixtures/rigs/cube_outside.toml";
const FRAME: &str = "fixtures/render/cube_outside/frame_000.png";
const TRUTH: &str = "fixtures/render/cube_outside/frame_000.json";
/// Largest distance (px) between a detected corner and its ground-truth position.
const TOLERANCE_PX: f64 = 0.2;

fn cubecal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run cubecal")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn json(out: &Output) -> Value {
    assert_eq!(out.status.code(), Some(0), "{}", stderr(out));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", stdout(out)))
}

fn keys(v: &Value) -> BTreeSet<&str> {
    v.as_object()
        .unwrap_or_else(|| panic!("not an object: {v}"))
        .keys()
        .map(String::as_str)
        .collect()
}

fn set<'a>(k: &[&'a str]) -> BTreeSet<&'a str> {
    k.iter().copied().collect()
}

fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Ground truth of a rendered frame: (face name, row, col) → (xyz, uv) of every visible corner.
type Truth = HashMap<(String, u64, u64), ([f64; 3], [f64; 2])>;

fn ground_truth(path: &Path) -> Truth {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let v: Value = serde_json::from_str(&text).unwrap();
    let corners = v["corners"].as_array().unwrap();
    assert!(!corners.is_empty(), "{}: no corners", path.display());
    let num = |v: &Value| v.as_f64().unwrap();
    corners
        .iter()
        .filter(|c| c["visible"].as_bool().unwrap())
        .map(|c| {
            let key = (
                c["face"].as_str().unwrap().to_string(),
                c["row"].as_u64().unwrap(),
                c["col"].as_u64().unwrap(),
            );
            let (x, u) = (&c["xyz"], &c["uv"]);
            (
                key,
                (
                    [num(&x[0]), num(&x[1]), num(&x[2])],
                    [num(&u[0]), num(&u[1])],
                ),
            )
        })
        .collect()
}

/// Check one image object of the `--json` array: the exact keys, and every corner against the truth.
/// Returns the names of the faces found.
fn check_image(img: &Value, name: &str, size: [u64; 2], truth: &Truth) -> Vec<String> {
    assert_eq!(
        keys(img),
        set(&["image", "width", "height", "faces", "rejected", "time_ms"])
    );
    assert_eq!(img["image"], name);
    assert_eq!(
        [img["width"].as_u64(), img["height"].as_u64()],
        size.map(Some)
    );
    let t = img["time_ms"].as_f64().unwrap();
    assert!(t > 0.0 && t < 60_000.0, "time_ms {t}");
    for r in img["rejected"].as_array().unwrap() {
        assert_eq!(keys(r), set(&["reason"]));
        assert!(!r["reason"].as_str().unwrap().is_empty());
    }
    let mut names = Vec::new();
    for face in img["faces"].as_array().unwrap() {
        assert_eq!(keys(face), set(&["face", "corners"]));
        let fname = face["face"].as_str().unwrap().to_string();
        let corners = face["corners"].as_array().unwrap();
        assert!(!corners.is_empty(), "face {fname} without corners");
        for c in corners {
            assert_eq!(
                keys(c),
                set(&["row", "col", "xyz", "uv", "sigma_px", "cov"])
            );
            let sigma = c["sigma_px"].as_f64().unwrap();
            assert!(sigma > 0.0);
            // The corner's own covariance [var_u, cov_uv, var_v]: positive definite, and σ is the
            // root of its mean variance.
            let cov: Vec<f64> = c["cov"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            assert!(cov[0] > 0.0 && cov[0] * cov[2] > cov[1] * cov[1], "{cov:?}");
            assert!((((cov[0] + cov[2]) / 2.0).sqrt() - sigma).abs() < 1e-9 * sigma.max(1.0));
            let (row, col) = (c["row"].as_u64().unwrap(), c["col"].as_u64().unwrap());
            let xyz: Vec<f64> = c["xyz"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let uv: Vec<f64> = c["uv"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            assert_eq!((xyz.len(), uv.len()), (3, 2));
            let (txyz, tuv) = truth
                .get(&(fname.clone(), row, col))
                .unwrap_or_else(|| panic!("{fname} ({row}, {col}) is not a visible corner"));
            for k in 0..3 {
                assert!(
                    (xyz[k] - txyz[k]).abs() < 1e-9,
                    "{fname} ({row}, {col}) xyz"
                );
            }
            let e = (uv[0] - tuv[0]).hypot(uv[1] - tuv[1]);
            assert!(
                e < TOLERANCE_PX,
                "{fname} ({row}, {col}): {e:.3} px from ground truth"
            );
        }
        names.push(fname);
    }
    names
}

/// Render a frame of the cube rig with a little blur (the detector finds every face of it) into
/// `dir`; returns its PNG and ground-truth paths.
fn render_blurred(dir: &Path) -> (PathBuf, PathBuf) {
    let out = cubecal(&[
        "render",
        RIG,
        "--out",
        path_str(dir),
        "--poses",
        "turntable:1",
        "--blur",
        "0.8",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    (dir.join("frame_000.png"), dir.join("frame_000.json"))
}

#[test]
fn json_has_the_documented_shape_and_corners_match_ground_truth() {
    let v = json(&cubecal(&["detect", "--rig", RIG, FRAME, "--json"]));
    let images = v.as_array().unwrap();
    assert_eq!(images.len(), 1);
    let names = check_image(
        &images[0],
        FRAME,
        [1280, 960],
        &ground_truth(Path::new(TRUTH)),
    );
    assert!(
        !names.is_empty(),
        "no face found: {}",
        images[0]["rejected"]
    );
}

#[test]
fn json_on_the_fixture_frame_finds_all_three_faces() {
    let v = json(&cubecal(&["detect", "--rig", RIG, FRAME, "--json"]));
    let names = check_image(&v[0], FRAME, [1280, 960], &ground_truth(Path::new(TRUTH)));
    assert_eq!(
        set(&names.iter().map(String::as_str).collect::<Vec<_>>()),
        set(&["top", "side-x", "side-y"])
    );
}

#[test]
fn all_three_faces_of_a_blurred_render_match_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let (png, truth) = render_blurred(dir.path());
    let v = json(&cubecal(&[
        "detect",
        "--rig",
        RIG,
        path_str(&png),
        "--json",
    ]));
    let mut names = check_image(&v[0], path_str(&png), [1280, 960], &ground_truth(&truth));
    names.sort();
    assert_eq!(names, ["side-x", "side-y", "top"]);
    let n: usize = v[0]["faces"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["corners"].as_array().unwrap().len())
        .sum();
    assert_eq!(n, 72 + 56 + 42);
}

#[test]
fn two_images_give_an_array_of_two_in_argument_order() {
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("copy.png");
    std::fs::copy(FRAME, &copy).unwrap();
    let v = json(&cubecal(&[
        "detect",
        "--rig",
        RIG,
        path_str(&copy),
        FRAME,
        "--json",
    ]));
    let images = v.as_array().unwrap();
    assert_eq!(images.len(), 2);
    let truth = ground_truth(Path::new(TRUTH));
    let a = check_image(&images[0], path_str(&copy), [1280, 960], &truth);
    let b = check_image(&images[1], FRAME, [1280, 960], &truth);
    assert_eq!(a, b);
    assert_eq!(images[0]["faces"], images[1]["faces"]);
}

fn coloured_pixels(path: &Path) -> (image::RgbImage, usize) {
    let img = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_rgb8();
    let n = img
        .pixels()
        .filter(|p| p.0[0] != p.0[1] || p.0[1] != p.0[2])
        .count();
    (img, n)
}

#[test]
fn overlay_is_a_png_of_the_frame_size_with_coloured_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let out_png = dir.path().join("overlay.png");
    let out = cubecal(&[
        "detect",
        "--rig",
        RIG,
        FRAME,
        "--overlay",
        path_str(&out_png),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert_eq!(
        image::ImageFormat::from_path(&out_png).unwrap(),
        image::ImageFormat::Png
    );
    let bytes = std::fs::read(&out_png).unwrap();
    assert_eq!(
        image::guess_format(&bytes).unwrap(),
        image::ImageFormat::Png
    );
    let (img, coloured) = coloured_pixels(&out_png);
    assert_eq!(img.dimensions(), (1280, 960));
    // 42 corners of one face at least: lines, crosses and the origin marker.
    assert!(coloured > 500, "{coloured} coloured pixels");
    // Away from the overlay (and from its legend in the top left corner) the grey frame is unchanged.
    let frame = image::open(FRAME).unwrap().into_luma8();
    let g = frame.get_pixel(1275, 955).0[0];
    assert_eq!(img.get_pixel(1275, 955).0, [g, g, g]);
}

#[test]
fn overlays_of_several_images_go_into_a_directory() {
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("second.png");
    std::fs::copy(FRAME, &copy).unwrap();
    let out_dir = dir.path().join("overlays/nested");
    let out = cubecal(&[
        "detect",
        "--rig",
        RIG,
        FRAME,
        path_str(&copy),
        "--overlay",
        path_str(&out_dir),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    for name in ["frame_000_overlay.png", "second_overlay.png"] {
        let (img, coloured) = coloured_pixels(&out_dir.join(name));
        assert_eq!(img.dimensions(), (1280, 960));
        assert!(coloured > 500, "{name}: {coloured} coloured pixels");
    }
    // Two images with the same file stem would overwrite each other's overlay: refused up front.
    let sub = dir.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    std::fs::copy(FRAME, sub.join("second.png")).unwrap();
    let clash_dir = dir.path().join("clash");
    let out = cubecal(&[
        "detect",
        "--rig",
        RIG,
        path_str(&copy),
        path_str(&sub.join("second.png")),
        "--overlay",
        path_str(&clash_dir),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("second_overlay.png"),
        "{}",
        stderr(&out)
    );
    assert!(!clash_dir.exists());
}

#[test]
fn missing_image_exits_3_naming_the_path() {
    let out = cubecal(&["detect", "--rig", RIG, "/nonexistent/frame.png"]);
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("/nonexistent/frame.png"),
        "{}",
        stderr(&out)
    );
    assert!(!stderr(&out).contains("panicked"));
    // With --json the error is also reported as JSON on stdout.
    let out = cubecal(&["detect", "--rig", RIG, "/nonexistent/frame.png", "--json"]);
    assert_eq!(out.status.code(), Some(3));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["exit_code"], 3);
    assert!(
        v["error"]
            .as_str()
            .unwrap()
            .contains("/nonexistent/frame.png")
    );
}

#[test]
fn non_image_and_truncated_files_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("notes.png");
    std::fs::write(&text, "not an image\n").unwrap();
    let truncated = dir.path().join("truncated.png");
    let bytes = std::fs::read(FRAME).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    for p in [text, truncated, PathBuf::from("Cargo.toml")] {
        let out = cubecal(&["detect", "--rig", RIG, path_str(&p)]);
        assert_eq!(
            out.status.code(),
            Some(3),
            "{}: {}",
            p.display(),
            stderr(&out)
        );
        assert!(stderr(&out).contains(path_str(&p)), "{}", stderr(&out));
        assert!(!stderr(&out).contains("panicked"), "{}", stderr(&out));
    }
}

#[test]
fn processing_stops_at_the_first_bad_image() {
    let out = cubecal(&["detect", "--rig", RIG, FRAME, "/nonexistent/b.png", FRAME]);
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    let text = stdout(&out);
    assert_eq!(text.matches(FRAME).count(), 1, "{text}");
    assert!(stderr(&out).contains("/nonexistent/b.png"));
}

#[test]
fn too_small_image_exits_3_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("tiny.png");
    image::GrayImage::from_pixel(20, 40, image::Luma([128]))
        .save(&p)
        .unwrap();
    let out = cubecal(&["detect", "--rig", RIG, path_str(&p)]);
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(stderr(&out).contains(path_str(&p)), "{}", stderr(&out));
    assert!(stderr(&out).contains("too small"), "{}", stderr(&out));
}

#[test]
fn bad_rig_exits_3() {
    let out = cubecal(&["detect", "--rig", "/nonexistent/rig.toml", FRAME]);
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(stderr(&out).contains("/nonexistent/rig.toml"));
}

#[test]
fn blank_frame_is_not_an_error_and_says_why_nothing_was_found() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("blank.png");
    image::GrayImage::from_pixel(200, 200, image::Luma([128]))
        .save(&p)
        .unwrap();
    let v = json(&cubecal(&["detect", "--rig", RIG, path_str(&p), "--json"]));
    let img = &v[0];
    assert_eq!(img["faces"].as_array().unwrap().len(), 0);
    let rejected = img["rejected"].as_array().unwrap();
    assert!(!rejected.is_empty());
    assert!(
        rejected[0]["reason"]
            .as_str()
            .unwrap()
            .contains("no checkerboard grid"),
        "{rejected:?}"
    );
    let out = cubecal(&["detect", "--rig", RIG, path_str(&p)]);
    assert_eq!(out.status.code(), Some(0));
    assert!(
        stdout(&out).contains("0 faces, 0 corners"),
        "{}",
        stdout(&out)
    );
    assert!(stdout(&out).contains("rejected: no checkerboard grid"));
}

#[test]
fn human_output_names_the_faces() {
    let dir = tempfile::tempdir().unwrap();
    let (png, _) = render_blurred(dir.path());
    let out = cubecal(&["detect", "--rig", RIG, path_str(&png)]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = stdout(&out);
    let first = text.lines().next().unwrap();
    assert!(
        first.starts_with(&format!("{}: 3 faces, 170 corners in ", png.display())),
        "{text}"
    );
    assert!(first.ends_with(" ms"), "{text}");
    for line in [
        "  face 'top': 72 corners",
        "  face 'side-x': 56 corners",
        "  face 'side-y': 42 corners",
    ] {
        assert!(
            text.lines().any(|l| l == line),
            "missing {line:?} in\n{text}"
        );
    }
    // The shipped fixture: whatever is found is named, and what is not is explained.
    let out = cubecal(&["detect", "--rig", RIG, FRAME]);
    assert_eq!(out.status.code(), Some(0));
    let text = stdout(&out);
    assert!(text.contains("face 'side-y'"), "{text}");
}
