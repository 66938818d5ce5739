//! `cubecal render --black/--white`: printed reflectances for low-contrast targets, and their
//! validation.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::process::{Command, Output};

use cubecal::render::{GroundTruth, Palette};

/// Render the default view of the cube at 160×120 (no noise, linear output) with `extra` options.
fn render(out_dir: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["render", "fixtures/rigs/cube_outside.toml", "--out"])
        .arg(out_dir)
        .args([
            "--width", "160", "--height", "120", "--fx", "125", "--fy", "125",
        ])
        .args(extra)
        .output()
        .expect("run cubecal")
}

/// Grey levels at the 1st and 99th percentiles of a frame.
fn spread(dir: &Path) -> (u8, u8) {
    let img = image::open(dir.join("frame_000.png"))
        .expect("rendered frame")
        .to_luma8();
    let mut v: Vec<u8> = img.pixels().map(|p| p.0[0]).collect();
    v.sort_unstable();
    (v[v.len() / 100], v[v.len() * 99 / 100])
}

#[test]
fn low_contrast_palette_narrows_the_dynamic_range() {
    let (default_dir, low_dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    for (dir, extra) in [
        (&default_dir, &[][..]),
        (&low_dir, &["--black", "0.3", "--white", "0.55"][..]),
    ] {
        let out = render(dir.path(), extra);
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let (d_lo, d_hi) = spread(default_dir.path());
    let (l_lo, l_hi) = spread(low_dir.path());
    let (d_range, l_range) = (d_hi - d_lo, l_hi - l_lo);
    // Default: black 0.06, white 0.88; low: 0.3 and 0.55, a third of the reflectance span. Shading,
    // the body and the background keep the image range from shrinking by exactly that factor.
    assert!(
        f64::from(l_range) < 0.6 * f64::from(d_range),
        "low-contrast 1–99 % range {l_lo}..{l_hi} vs default {d_lo}..{d_hi}"
    );
    // Nothing in the scene is brighter than the white squares fully lit (shading ≤ 1, gamma 1).
    assert!(l_hi <= 141, "low-contrast 99th percentile {l_hi}");
    // The ground truth records the palette the frame was rendered with.
    let gt: GroundTruth = serde_json::from_str(
        &std::fs::read_to_string(low_dir.path().join("frame_000.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        gt.render.palette,
        Palette {
            black: 0.3,
            white: 0.55,
            ..Palette::default()
        }
    );
}

#[test]
fn black_not_below_white_is_bad_input_and_out_of_range_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    for bad in [
        ["--black", "0.6", "--white", "0.55"],
        ["--black", "0.5", "--white", "0.5"],
    ] {
        let out = render(dir.path(), &bad);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(
            out.status.code(),
            Some(i32::from(cubecal::exit::BAD_INPUT)),
            "{bad:?}: {err}"
        );
        assert!(
            err.contains("black") && err.contains("white"),
            "{bad:?}: {err}"
        );
        assert!(
            std::fs::read_dir(dir.path()).unwrap().next().is_none(),
            "{bad:?}: nothing may be rendered"
        );
    }
    for bad in [
        ["--black=-0.1", "--seed=0"],
        ["--white", "1.5"],
        ["--white", "nan"],
    ] {
        let out = render(dir.path(), &bad);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(
            out.status.code(),
            Some(i32::from(cubecal::exit::USAGE)),
            "{bad:?}: {err}"
        );
        assert!(
            err.contains(bad[0].split('=').next().unwrap()),
            "{bad:?}: {err}"
        );
    }
}
