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
