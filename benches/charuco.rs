//! ChArUco detection benchmark (issue 33, acceptance line 1: ≤ 10 ms per 1280×960 frame):
//! `cargo bench --bench charuco`. Release build, one thread. The ChArUco cube
//! (`fixtures/rigs/charuco_cube.toml`) rendered at 1280×960 in the hard evaluation set's poses and
//! camera (`detect::score::EvalSet::Hard`: f 700 px, k1 −0.3), with the hard set's look and with the
//! realistic set's look (blur σ 1, noise σ 2, full contrast). Prints, per look, the median, min and
//! p90 of `detect::detect` per frame over every run of every frame, the median of finding and
//! decoding the markers alone (`charuco::find_markers`), and the corners and markers found (the
//! same figures before and after a change say its results did not move).
//!
//! `CUBECAL_BENCH_REPS` sets the runs per frame (default 31; 2 without `--bench`, as under
//! `cargo test --benches`). `CUBECAL_BENCH_DUMP=FILE` writes every labelled corner (look, frame,
//! face, row, col, u, v) and marker (look, frame, id, corners) to FILE, to compare two builds'
//! results exactly. `CUBECAL_BENCH_FRAMES=DIR` keeps the rendered frames in DIR as PNG and reads
//! them from there when present (rendering costs several times the detection: a process timed
//! from outside, or run under a profiler, then spends its time detecting).
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::fmt::Write as _;
use std::time::Instant;

use cubecal::camera::{Camera, Pose};
use cubecal::detect::score::EvalSet;
use cubecal::detect::{CornerFinder, charuco, detect};
use cubecal::render::{RenderSettings, render};
use cubecal::rig::Rig;
use image::GrayImage;

fn main() {
    let quick = !std::env::args().any(|a| a == "--bench");
    let reps = std::env::var("CUBECAL_BENCH_REPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&n: &usize| n >= 1)
        .unwrap_or(if quick { 2 } else { 31 });
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/charuco_cube.toml"
    );
    let (rig, _) = Rig::load(std::path::Path::new(path)).unwrap();
    let camera = EvalSet::Hard.camera();
    let dict = rig.faces[0].charuco.as_ref().unwrap().dictionary;
    let mut dump = String::new();
    for (label, settings) in [
        ("hard", EvalSet::Hard.settings()),
        ("realistic look", EvalSet::Realistic.settings()),
    ] {
        let poses = EvalSet::Hard.poses(&rig, 3);
        let mut all = Vec::new();
        let mut markers_ms = Vec::new();
        let (mut corners, mut markers) = (0, 0);
        // Regions examined, by outcome (charuco::CandidateOutcome).
        let mut outcomes = [0usize; 8];
        for (k, pose) in poses.iter().enumerate() {
            let img = frame(&rig, &camera, pose, &settings, (label, k));
            let mut finder = CornerFinder::new().unwrap();
            let det = detect(&mut finder, &img, &rig).unwrap();
            let found = charuco::find_markers(&img, &[dict]);
            for c in charuco::marker_candidates(&img, &[dict]) {
                use charuco::CandidateOutcome as O;
                let slot = match c.outcome {
                    O::Size => 0,
                    O::FrameBorder => 1,
                    O::NotQuad => 2,
                    O::NotDecoded(charuco::DecodeMiss::Geometry) => 3,
                    O::NotDecoded(charuco::DecodeMiss::Contrast) => 4,
                    O::NotDecoded(charuco::DecodeMiss::Border(_)) => 5,
                    O::NotDecoded(charuco::DecodeMiss::Distance(_)) => 6,
                    O::Decoded(_) => 7,
                };
                outcomes[slot] += 1;
            }
            corners += det.faces.iter().map(|f| f.corners.len()).sum::<usize>();
            markers += found.len();
            for f in &det.faces {
                for c in &f.corners {
                    let _ = writeln!(
                        dump,
                        "{label}\t{k}\tface {}\t{} {}\t{:.6} {:.6}",
                        f.face, c.row, c.col, c.uv.x, c.uv.y
                    );
                }
            }
            for m in &found {
                let _ = writeln!(
                    dump,
                    "{label}\t{k}\tmarker {}\t{:?}",
                    m.id,
                    m.corners.map(|p| format!("{:.6} {:.6}", p.x, p.y))
                );
            }
            for _ in 0..reps {
                let t = Instant::now();
                std::hint::black_box(detect(&mut finder, &img, &rig).unwrap());
                all.push(t.elapsed().as_secs_f64() * 1e3);
                let t = Instant::now();
                std::hint::black_box(charuco::find_markers(&img, &[dict]));
                markers_ms.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        all.sort_by(f64::total_cmp);
        markers_ms.sort_by(f64::total_cmp);
        println!(
            "charuco cube, {label} (1280×960): median {:.2} ms per frame (min {:.2}, p90 {:.2}) over {} runs of {} frames; markers alone median {:.2} ms; {corners} corners, {markers} markers",
            all[all.len() / 2],
            all[0],
            all[all.len() * 9 / 10],
            reps,
            poses.len(),
            markers_ms[markers_ms.len() / 2]
        );
        println!(
            "    regions examined in the {} frames: {} too small or large, {} on the frame's border, {} no quadrilateral, {} not decoded (geometry {}, contrast {}, border {}, distance {}), {} decoded",
            poses.len(),
            outcomes[0],
            outcomes[1],
            outcomes[2],
            outcomes[3..7].iter().sum::<usize>(),
            outcomes[3],
            outcomes[4],
            outcomes[5],
            outcomes[6],
            outcomes[7]
        );
    }
    if let Ok(file) = std::env::var("CUBECAL_BENCH_DUMP") {
        std::fs::write(file, dump).unwrap();
    }
}

/// Frame `k` of a look, rendered, or read from `CUBECAL_BENCH_FRAMES` when it holds it.
fn frame(
    rig: &Rig,
    camera: &Camera,
    pose: &Pose,
    settings: &RenderSettings,
    (look, k): (&str, usize),
) -> GrayImage {
    let dir = std::env::var_os("CUBECAL_BENCH_FRAMES").map(std::path::PathBuf::from);
    let path = dir.map(|d| d.join(format!("{}-{k}.png", look.replace(' ', "-"))));
    if let Some(p) = &path
        && let Ok(img) = image::open(p)
    {
        return img.to_luma8();
    }
    let img = render(rig, camera, pose, settings, k as u64).unwrap();
    if let Some(p) = &path {
        img.save(p).unwrap();
    }
    img
}
