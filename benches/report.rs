//! Report generation time for a 12-pose station run at 1280×960 (issue 22: ≤ 1 s), and for a stored
//! profile with ten versions.
//!
//! Builds the run directory first (rendering, detection and solving are not timed), then times
//! `report::write_run_report` end to end (load, residuals, six plots as SVG and PNG, 13 thumbnails
//! with overlays, HTML, writing) several times and prints each time, the minimum and the median.
//! The profile report is timed the same way from `ProfileData::locate` (reading the store: current
//! and nine history documents) to the written HTML and PNGs (distortion, uncertainty, history).
//!
//! `cargo bench --bench report`
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout)]

#[path = "../tests/report_support/mod.rs"]
mod report_support;

use std::time::Instant;

fn main() {
    let tmp = tempfile::tempdir().unwrap();
    let t = Instant::now();
    let run = report_support::build_run(
        &tmp.path().join("run"),
        report_support::Kind::Good { n: 12 },
        1280,
        960,
    );
    println!(
        "built a 12-pose run (13 frames, 1280×960) in {:.1} s (not part of the figure)",
        t.elapsed().as_secs_f64()
    );
    let mut times = Vec::new();
    for i in 0..7 {
        let t = Instant::now();
        let path = cubecal::report::write_run_report(&run).unwrap();
        let dt = t.elapsed().as_secs_f64();
        if i == 0 {
            let size = std::fs::metadata(&path).unwrap().len();
            println!("report.html: {:.0} kB", size as f64 / 1024.0);
        }
        println!("run {i}: {:.1} ms", dt * 1e3);
        times.push(dt);
    }
    // Where the time goes (one more run, by stage, without writing).
    let t = Instant::now();
    let data = cubecal::report::RunData::load(&run).unwrap();
    println!("stage load: {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    let report = cubecal::report::render_run(&data, "report_plots").unwrap();
    for (stage, d) in &report.timings {
        println!("stage {stage}: {:.1} ms", d.as_secs_f64() * 1e3);
    }
    // One thumbnail, by step: frame decoding, detection (rejected frames only), drawing.
    let frame = run.join("session/frame_000000.png");
    let t = Instant::now();
    let img = cubecal::report::thumbs::load_frame(&frame).unwrap();
    println!(
        "thumbnail step decode 1280×960 PNG: {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let det = cubecal::report::thumbs::detect_frame(&img, &data.rig).unwrap();
    println!(
        "thumbnail step detect (rejected frames only): {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let best = |f: &mut dyn FnMut()| {
        (0..5)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .fold(f64::MAX, f64::min)
    };
    let small = image::imageops::thumbnail(&img, 400, 300);
    println!(
        "(for comparison, not used: image::imageops::thumbnail to 400×300: {:.1} ms)",
        best(&mut || {
            let _ = image::imageops::thumbnail(&img, 400, 300);
        })
    );
    println!(
        "thumbnail step overlay: {:.1} ms",
        best(&mut || {
            let _ = cubecal::detect::overlay::draw(&small, &det, &data.rig);
        })
    );
    println!(
        "thumbnail step scale + overlay + legend: {:.1} ms",
        best(&mut || {
            let _ = cubecal::report::thumbs::thumbnail(&img, &det, &data.rig).unwrap();
        })
    );
    times.sort_by(f64::total_cmp);
    println!(
        "report generation, 12 poses: min {:.1} ms, median {:.1} ms (7 runs)",
        times[0] * 1e3,
        times[times.len() / 2] * 1e3
    );

    // A profile with ten stored versions.
    let store = tmp.path().join("store");
    let versions: Vec<_> = (0..10).map(report_support::drifting_camera).collect();
    report_support::build_history(&store, "usb:046d:0825:BENCH", &versions);
    let out = tmp.path().join("profile.html");
    let mut times = Vec::new();
    for i in 0..7 {
        let t = Instant::now();
        let data =
            cubecal::report::profile::ProfileData::locate("usb:046d:0825:BENCH", &store).unwrap();
        cubecal::report::profile::write_profile_report(&data, &out).unwrap();
        let dt = t.elapsed().as_secs_f64();
        if i == 0 {
            let size = std::fs::metadata(&out).unwrap().len();
            println!(
                "profile report ({} versions): {:.0} kB",
                data.versions().len(),
                size as f64 / 1024.0
            );
        }
        println!("profile run {i}: {:.1} ms", dt * 1e3);
        times.push(dt);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "report generation, profile with 10 versions: min {:.1} ms, median {:.1} ms (7 runs)",
        times[0] * 1e3,
        times[times.len() / 2] * 1e3
    );
}
