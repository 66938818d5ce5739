//! Every real chessboard set in `../shared/datasets` through `cubecal calibrate --images`, held to
//! OpenCV: no view that OpenCV's findChessboardCornersSB or findChessboardCorners labels may be lost
//! (issue 28, line 1). Which views OpenCV labels is recorded in `fixtures/peers/opencv_views.json`
//! by `tests/peers/opencv_views.py` (OpenCV's SB detector takes minutes on these photos, too long
//! for the test run; rerun the script to refresh the record). Zero wrong labels: each run's
//! calibration must fit every accepted view (RMS and largest residual of the verdict's checks),
//! which a broken lattice or a mixed-up corner cannot.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// One `calibrate --images` run; returns its result.json.
fn calibrate(images: &[PathBuf], rig: &str, out: &Path) -> Value {
    let output = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .arg("calibrate")
        .arg("--json")
        .arg("--rig")
        .arg(root().join(rig))
        .arg("--out")
        .arg(out)
        .arg("--images")
        .args(images)
        .output()
        .unwrap();
    let result = out.join("result.json");
    assert!(
        result.exists(),
        "{}: no result.json; stderr: {}",
        out.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(result).unwrap()).unwrap()
}

#[test]
fn no_view_opencv_labels_is_lost_on_the_real_sets() {
    let record: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("fixtures/peers/opencv_views.json")).unwrap(),
    )
    .unwrap();
    let data = root().join("../shared/datasets");
    let tmp = tempfile::tempdir().unwrap();
    let mut lost = Vec::new();
    let mut total = (0, 0);
    for (k, set) in record["sets"].as_array().unwrap().iter().enumerate() {
        let name = set["set"].as_str().unwrap();
        let rig = match name {
            "opencv_stereo_left_right" => "fixtures/rigs/opencv_board_9x6.toml",
            "pose2sim_board_4x7" => "fixtures/rigs/pose2sim_board_4x7.toml",
            "pycalib_chessboard_10x7" => "fixtures/rigs/pycalib_board_10x7.toml",
            other => panic!("no rig for set {other}"),
        };
        let labelled: Vec<String> = set["views"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|v| v["sb"].as_bool().unwrap() || v["classic"].as_bool().unwrap())
            .map(|v| v["image"].as_str().unwrap().to_string())
            .collect();
        // One camera per run: pose2sim's images are four cameras (camNN_...).
        let mut groups: Vec<(String, Vec<String>)> = Vec::new();
        for img in &labelled {
            let camera = if name == "pose2sim_board_4x7" {
                let file = img.rsplit('/').next().unwrap();
                file.split('_').next().unwrap().to_string()
            } else {
                String::new()
            };
            match groups.iter_mut().find(|g| g.0 == camera) {
                Some(g) => g.1.push(img.clone()),
                None => groups.push((camera, vec![img.clone()])),
            }
        }
        for (g, (camera, imgs)) in groups.iter().enumerate() {
            let paths: Vec<PathBuf> = imgs.iter().map(|i| data.join(name).join(i)).collect();
            let result = calibrate(&paths, rig, &tmp.path().join(format!("run{k}_{g}")));
            let views = result["views"].as_array().unwrap();
            let accepted: Vec<&str> = views
                .iter()
                .filter(|v| v["accepted"].as_bool() == Some(true))
                .map(|v| v["name"].as_str().unwrap())
                .collect();
            for v in views
                .iter()
                .filter(|v| v["accepted"].as_bool() != Some(true))
            {
                lost.push(format!("{name} {camera} {}: {}", v["name"], v["reason"]));
            }
            let checks = result["verdict"]["checks"].as_array().unwrap();
            for check in ["rms_px", "max_residual_px", "converged"] {
                let c = checks.iter().find(|c| c["name"] == check).unwrap();
                assert_eq!(
                    c["pass"].as_bool(),
                    Some(true),
                    "{name} {camera}: check {c} fails: a wrong label?"
                );
            }
            eprintln!(
                "{name} {camera}: OpenCV labels {}, cubecal keeps {}, rms {:.3} px",
                imgs.len(),
                accepted.len(),
                result["calibration"]["rms_px"].as_f64().unwrap_or(f64::NAN)
            );
            total.0 += imgs.len();
            total.1 += accepted.len();
        }
    }
    eprintln!(
        "all sets: OpenCV labels {}, cubecal keeps {}",
        total.0, total.1
    );
    assert!(
        lost.is_empty(),
        "views OpenCV labels, lost by cubecal: {lost:#?}"
    );
}
