//! Where does outlier rejection drop points on real photos? Detects a plain board in every image of
//! a folder, solves (brown5) with `--reject-outliers K` as `cubecal solve` does, once with every corner
//! weighted by its own covariance and once with equal weights, and prints how the dropped points
//! spread over the board's rows and columns: per row and per column the number dropped against its
//! share (dropped × the row's or column's fraction of all points). Issue 29, acceptance line 5: no
//! row or column should hold more than twice its share.
//!
//! ```sh
//! cargo run --release --example outlier_spread -- DIR COLSxROWS SQUARE_MM [K]
//! cargo run --release --example outlier_spread -- ../shared/datasets/pycalib_chessboard_10x7/images 10x7 160
//! ```
#![allow(clippy::print_stdout, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::path::PathBuf;

use cubecal::calib::{self, SolveOptions, View, Weighting};
use cubecal::detect::{CornerFinder, detect};
use cubecal::rig::{BoardSize, Rig, board_toml};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = PathBuf::from(&args[1]);
    let size: BoardSize = args[2].parse().unwrap();
    let square: f64 = args[3].parse().unwrap();
    let k: f64 = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(3.0);
    let rig = Rig::from_toml_str(&board_toml(size, square), "board")
        .unwrap()
        .0;
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .is_some_and(|e| ["jpg", "jpeg", "png"].contains(&e.to_string_lossy().as_ref()))
        })
        .collect();
    files.sort();
    let mut finder = CornerFinder::new().unwrap();
    let mut views: Vec<View> = Vec::new();
    // (row, col) of every point, per view.
    let mut labels: Vec<Vec<(usize, usize)>> = Vec::new();
    let mut image_size = [0, 0];
    for f in &files {
        let img = image::open(f).unwrap().to_luma8();
        image_size = [img.width(), img.height()];
        let det = detect(&mut finder, &img, &rig).unwrap();
        if det.faces.is_empty() {
            continue;
        }
        labels.push(
            det.faces
                .iter()
                .flat_map(|fc| fc.corners.iter().map(|c| (c.row, c.col)))
                .collect(),
        );
        views.push(det.to_view(&f.file_name().unwrap().to_string_lossy()));
    }
    let n_points: usize = views.iter().map(|v| v.points.len()).sum();
    println!(
        "{}: {} of {} images with the board, {n_points} corners; outlier rejection at k = {k}",
        dir.display(),
        views.len(),
        files.len()
    );
    for (label, weighting) in [
        (
            "weighted by each corner's covariance",
            Weighting::Covariance,
        ),
        ("equal weights", Weighting::Equal),
    ] {
        let opts = SolveOptions {
            outlier_sigma: Some(k),
            weighting,
            ..SolveOptions::default()
        };
        let cal = match calib::solve(&views, image_size, &opts) {
            Ok(c) => c,
            Err(e) => {
                println!("  {label}: {e}");
                continue;
            }
        };
        let mut all_rows: BTreeMap<usize, usize> = BTreeMap::new();
        let mut all_cols: BTreeMap<usize, usize> = BTreeMap::new();
        let mut rows: BTreeMap<usize, usize> = BTreeMap::new();
        let mut cols: BTreeMap<usize, usize> = BTreeMap::new();
        let mut dropped = 0;
        for (v, lab) in cal.views.iter().zip(&labels) {
            for &(r, c) in lab {
                *all_rows.entry(r).or_default() += 1;
                *all_cols.entry(c).or_default() += 1;
            }
            for &j in &v.outliers {
                let (r, c) = lab[j];
                *rows.entry(r).or_default() += 1;
                *cols.entry(c).or_default() += 1;
                dropped += 1;
            }
        }
        let worst = |all: &BTreeMap<usize, usize>, got: &BTreeMap<usize, usize>| {
            let mut worst = (0, 0.0_f64);
            let line: Vec<String> = all
                .iter()
                .map(|(&i, &n)| {
                    let share = dropped as f64 * n as f64 / n_points as f64;
                    let g = got.get(&i).copied().unwrap_or(0);
                    if share > 0.0 && g as f64 / share > worst.1 {
                        worst = (i, g as f64 / share);
                    }
                    format!("{i}:{g}/{share:.1}")
                })
                .collect();
            (line.join(" "), worst)
        };
        let (rl, rw) = worst(&all_rows, &rows);
        let (cl, cw) = worst(&all_cols, &cols);
        println!(
            "  {label}: dropped {dropped} of {n_points} ({:.1} %), rms {:.3} px, fx {:.2} cx {:.2} cy {:.2}{}",
            100.0 * dropped as f64 / n_points as f64,
            cal.rms_px,
            cal.camera.fx(),
            cal.camera.cx(),
            cal.camera.cy(),
            cal.noise_scale
                .map_or(String::new(), |s| format!(", noise scale {s:.2}"))
        );
        println!("    per row (dropped/share): {rl}");
        println!("    per column (dropped/share): {cl}");
        println!(
            "    most over its share: row {} at {:.2}×, column {} at {:.2}×",
            rw.0, rw.1, cw.0, cw.1
        );
    }
}
