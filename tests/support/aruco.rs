//! OpenCV's python module (with aruco) for the tests that compare with it: the python that has it,
//! and the peer scripts of `tests/peers/` run with it.

use std::ffi::OsStr;
use std::path::Path;
use std::process::{Command, Stdio};

/// A python with `cv2.aruco` (`CUBECAL_PYTHON`, then the system's); `None` (the test skips) without
/// one, unless `CUBECAL_REQUIRE_TOOLS=1`, which makes it a failure.
pub fn python_with_aruco() -> Option<String> {
    let found = [
        std::env::var("CUBECAL_PYTHON").ok(),
        Some("/usr/bin/python3".to_string()),
        Some("python3".to_string()),
    ]
    .into_iter()
    .flatten()
    .find(|py| {
        Command::new(py)
            .args(["-c", "import cv2; cv2.aruco.getPredefinedDictionary"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    });
    if found.is_none() {
        assert!(
            std::env::var("CUBECAL_REQUIRE_TOOLS").map_or(true, |v| v != "1"),
            "CUBECAL_REQUIRE_TOOLS=1 but no python3 with cv2.aruco"
        );
        eprintln!("skipped: no python3 with cv2.aruco (run deploy/install-test-tools.sh)");
    }
    found
}

/// Runs the OpenCV peer script with `args`; its standard output (it must succeed).
#[allow(dead_code)] // not every test file that includes this module runs this script
pub fn run_peer<S: AsRef<OsStr>>(py: &str, args: &[S]) -> Vec<u8> {
    run_script(py, "charuco_opencv.py", args)
}

/// Runs `tests/peers/<script>` with `args`; its standard output (it must succeed).
pub fn run_script<S: AsRef<OsStr>>(py: &str, script: &str, args: &[S]) -> Vec<u8> {
    let peer = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(script);
    let out = Command::new(py)
        .arg(&peer)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("{py}: {e}"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}
