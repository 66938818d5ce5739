//! The detector's corner front end and grid assembly on real images: the 26 OpenCV sample images of a
//! 9×6 board (`../shared/datasets/opencv_stereo_left_right`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

use cubecal::detect::{CornerFinder, grid};

fn dataset_images() -> Vec<std::path::PathBuf> {
    let dir = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/datasets/opencv_stereo_left_right/images"
    );
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("dataset missing: {dir}: {e}"))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
        .collect();
    v.sort();
    assert_eq!(v.len(), 26, "expected 26 images in {dir}");
    v
}

#[test]
fn every_sample_image_yields_a_complete_9x6_grid() {
    let mut finder = CornerFinder::new().unwrap();
    let mut complete = 0;
    for path in dataset_images() {
        let img = image::open(&path).unwrap().to_luma8();
        let corners = finder.find(&img).unwrap();
        let grids = grid::assemble(&corners);
        let best = grids.first();
        let ok = best.is_some_and(|g| {
            g.count() == 54 && ((g.rows, g.cols) == (6, 9) || (g.rows, g.cols) == (9, 6))
        });
        eprintln!(
            "{}: {} corners, {} grids, largest {}",
            path.file_name().unwrap().to_string_lossy(),
            corners.len(),
            grids.len(),
            best.map(|g| format!("{}×{} with {}", g.rows, g.cols, g.count()))
                .unwrap_or_else(|| "none".into())
        );
        if ok {
            complete += 1;
        }
    }
    assert_eq!(complete, 26);
}

#[test]
fn tiny_and_flat_frames_are_handled() {
    let mut finder = CornerFinder::new().unwrap();
    assert!(finder.find(&image::GrayImage::new(3, 3)).is_err());
    for v in [0u8, 255] {
        let img = image::GrayImage::from_pixel(640, 480, image::Luma([v]));
        let c = finder.find(&img).unwrap();
        assert!(grid::assemble(&c).is_empty());
    }
}

/// Detect with the 9×6 rig in all 26 images, then calibrate from the 13 left images and compare with
/// the reference (Bouguet's toolbox: left K = [533.00371 0 341.58612; 0 533.15260 234.25940]).
#[test]
fn sample_board_is_labelled_in_every_image_and_calibrates_to_the_reference() {
    let rig_path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/opencv_board_9x6.toml"
    );
    let (rig, _) = cubecal::rig::Rig::load(std::path::Path::new(rig_path)).unwrap();
    let mut finder = CornerFinder::new().unwrap();
    let mut left_views = Vec::new();
    for path in dataset_images() {
        let img = image::open(&path).unwrap().to_luma8();
        let det = cubecal::detect::detect(&mut finder, &img, &rig).unwrap();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        assert_eq!(det.faces.len(), 1, "{name}: {:?}", det.rejected);
        assert_eq!(det.faces[0].corners.len(), 54);
        if name.starts_with("left") {
            left_views.push(det.to_view(&name));
        }
    }
    assert_eq!(left_views.len(), 13);
    let cal = cubecal::calib::solve(
        &left_views,
        [640, 480],
        &cubecal::calib::SolveOptions::default(),
    )
    .unwrap();
    let fx = cal.camera.fx();
    let rel = (fx - 533.00371).abs() / 533.00371;
    eprintln!(
        "left: fx {fx:.2} ± {:.2} (reference 533.00, {:.3}%), fy {:.2}, cx {:.2}, cy {:.2}, k1 {:.4}, rms {:.3} px ({:.3} OpenCV-style)",
        cal.std_dev[0],
        100.0 * rel,
        cal.camera.fy(),
        cal.camera.cx(),
        cal.camera.cy(),
        cal.camera.params[cubecal::camera::idx::K1],
        cal.rms_px,
        cal.rms_reprojection_px
    );
    assert!(rel < 0.005);
}
