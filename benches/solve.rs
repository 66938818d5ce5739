//! Solve-time benchmark: `cargo bench --bench solve`. Prints the median and spread of the full solve
//! (initialisation + Levenberg–Marquardt + covariance) on synthetic cube data, single-threaded.
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::time::{Duration, Instant};

use cubecal::calib::{self, SolveOptions};
use cubecal::synthetic::{add_noise, cube_scenario, reference_camera};

fn bench(label: &str, n_views: usize, reps: usize) {
    let camera = reference_camera();
    let sc = cube_scenario(&camera, 200.0, n_views, 42);
    let views = add_noise(&sc.views, 0.3, 43);
    let n_points: usize = views.iter().map(|v| v.points.len()).sum();
    let opts = SolveOptions::default();
    // Warm-up.
    let cal = calib::solve(&views, camera.image_size, &opts).unwrap();
    let mut times: Vec<Duration> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            let c = calib::solve(&views, camera.image_size, &opts).unwrap();
            std::hint::black_box(c);
            t.elapsed()
        })
        .collect();
    times.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "{label}: {n_views} views, {n_points} points, brown5: median {:.2} ms (min {:.2}, p90 {:.2}) over {reps} runs; {} LM iterations, rms {:.3} px",
        ms(times[reps / 2]),
        ms(times[0]),
        ms(times[reps * 9 / 10]),
        cal.iterations,
        cal.rms_px
    );
}

fn main() {
    // `cargo test --benches` runs this with `--bench` absent: keep that quick.
    let quick = !std::env::args().any(|a| a == "--bench");
    let reps = if quick { 3 } else { 101 };
    bench("solve", 10, reps);
    bench("solve", 50, if quick { 1 } else { 21 });
}
