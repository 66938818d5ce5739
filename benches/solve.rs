//! Solve-time benchmark: `cargo bench --bench solve`. Prints the median and spread of the full solve
//! (initialisation + Levenberg–Marquardt + covariance) on synthetic cube data, single-threaded. The
//! points of `solve` carry their covariance (as detected corners do), so it times the weighted solve.
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::time::{Duration, Instant};

use cubecal::calib::{self, SolveOptions};
use cubecal::render::correspondences::{add_noise, cube_scenario, reference_camera};

#[path = "support/cpu.rs"]
mod cpu;
use cpu::cpu_ns;

fn cpu_ms_per_run(start: Option<u64>, runs: usize) -> String {
    match (start, cpu_ns()) {
        (Some(a), Some(b)) => format!("{:.2} ms CPU per run", (b - a) as f64 / 1e6 / runs as f64),
        _ => "CPU time unavailable".into(),
    }
}

/// How the bench's points are weighted.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    /// No covariances: the plain equally weighted solve.
    Plain,
    /// Every point carries its covariance and the solve whitens by it (issue 29).
    Weighted,
    /// The station's default: every point carries its covariance (one in ten three times the
    /// others' σ, as a grazing face's), weighted equally with the ceiling, σ from the sandwich.
    EqualWithCovariance,
}

/// The modes are run side by side, so their ratios are measured in one run.
fn bench(label: &str, n_views: usize, reps: usize, mode: Mode) -> f64 {
    let camera = reference_camera();
    let sc = cube_scenario(&camera, 200.0, n_views, 42);
    let mut views = add_noise(&sc.views, 0.3, 43);
    // Each point with its covariance, as the detector's corners come.
    if mode != Mode::Plain {
        for v in &mut views {
            for (k, p) in v.points.iter_mut().enumerate() {
                let scale = if mode == Mode::EqualWithCovariance && k % 10 == 0 {
                    9.0
                } else {
                    1.0
                };
                p.cov = Some(nalgebra::Matrix2::new(0.09, 0.01, 0.01, 0.08) * scale);
            }
        }
    }
    let n_points: usize = views.iter().map(|v| v.points.len()).sum();
    let opts = SolveOptions {
        weighting: if mode == Mode::Weighted {
            calib::Weighting::Covariance
        } else {
            calib::Weighting::Equal
        },
        ..SolveOptions::default()
    };
    // Warm-up.
    let cal = calib::solve(&views, camera.image_size, &opts).unwrap();
    let cpu0 = cpu_ns();
    let mut times: Vec<Duration> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            let c = calib::solve(&views, camera.image_size, &opts).unwrap();
            std::hint::black_box(c);
            t.elapsed()
        })
        .collect();
    let cpu_per_run = cpu0
        .zip(cpu_ns())
        .map(|(a, b)| (b - a) as f64 / 1e6 / reps as f64);
    let cpu = cpu_ms_per_run(cpu0, reps);
    times.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "{label} ({}): {n_views} views, {n_points} points, brown5: {cpu}; wall median {:.2} ms (min {:.2}, p90 {:.2}) over {reps} runs; {} LM iterations, rms {:.3} px",
        match mode {
            Mode::Plain => "equal weights",
            Mode::Weighted => "weighted",
            Mode::EqualWithCovariance => "equal weights, covariances: the station's default",
        },
        ms(times[reps / 2]),
        ms(times[0]),
        ms(times[reps * 9 / 10]),
        cal.iterations,
        cal.rms_px
    );
    // This thread's CPU time per LM iteration (wall time on a loaded machine is mostly other
    // processes'; the weighting may change the number of iterations, not only their cost).
    cpu_per_run.unwrap_or(ms(times[reps / 2])) / cal.iterations.max(1) as f64
}

/// 12 views × 3 faces of `fixtures/rigs/cube_outside.toml` (side boards moved by ~1 mm and 0.5°),
/// exact projections plus 0.03 px noise, solved with the rig refined (issue 20: ≤ 20 ms).
fn bench_rig_refinement(reps: usize) {
    use cubecal::calib::{RigPoint, RigRefineOptions, RigView, solve_rig};
    use cubecal::render::random_poses;
    use cubecal::rig::Rig;
    use nalgebra::{Rotation3, Vector2, Vector3};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    );
    let (rig, _) = Rig::load(std::path::Path::new(path)).unwrap();
    let mut built = rig.clone();
    for (f, t, r) in [
        (
            1,
            Vector3::new(0.6, -0.4, 0.9),
            Vector3::new(0.004, -0.006, 0.003),
        ),
        (
            2,
            Vector3::new(-0.8, 0.5, 0.3),
            Vector3::new(-0.007, 0.004, 0.005),
        ),
    ] {
        let face = &mut built.faces[f];
        let rot = Rotation3::new(r);
        face.origin = rot * face.origin + t;
        face.col_dir = rot * face.col_dir;
        face.row_dir = rot * face.row_dir;
    }
    let camera = cubecal::camera::Camera::pinhole([1920, 1080], 1400.0, 1400.0, 959.5, 539.5)
        .with_distortion(cubecal::camera::DistortionModel::Brown5, &[-0.1]);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, 0.03).unwrap();
    let views: Vec<RigView> = random_poses(&rig, &camera, 12, 1)
        .iter()
        .enumerate()
        .map(|(k, pose)| RigView {
            name: format!("view{k:02}"),
            points: built
                .corners()
                .filter_map(|c| {
                    let face = &built.faces[c.face];
                    let x = face.corner_xyz(c.row, c.col);
                    let xc = pose.transform(&x);
                    if (pose.rotation * face.normal()).dot(&xc) > -0.26 * xc.norm() {
                        return None;
                    }
                    let uv = camera.project(pose, &x).ok()?;
                    let n = Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
                    Some(RigPoint {
                        corner: c,
                        uv: uv + n,
                        sigma_px: Some(0.03),
                        cov: None,
                    })
                })
                .collect(),
        })
        .collect();
    let n_points: usize = views.iter().map(|v| v.points.len()).sum();
    let opts = RigRefineOptions::default();
    let r = solve_rig(&rig, &views, camera.image_size, &opts).unwrap();
    let cpu0 = cpu_ns();
    let mut times: Vec<Duration> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            let c = solve_rig(&rig, &views, camera.image_size, &opts).unwrap();
            std::hint::black_box(c);
            t.elapsed()
        })
        .collect();
    let cpu = cpu_ms_per_run(cpu0, reps);
    times.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "solve_rig: 12 views × 3 faces, {n_points} points, brown5, 2 faces refined: {cpu}; wall median {:.2} ms (min {:.2}, p90 {:.2}) over {reps} runs; {} LM iterations, rms {:.3} px",
        ms(times[reps / 2]),
        ms(times[0]),
        ms(times[reps * 9 / 10]),
        r.calibration.iterations,
        r.calibration.rms_px
    );
}

fn main() {
    // `cargo test --benches` runs this with `--bench` absent: keep that quick.
    let quick = !std::env::args().any(|a| a == "--bench");
    // CUBECAL_BENCH_REPS shortens a run where each solve is slow (under qemu: tests/aarch64.sh).
    let env_reps = std::env::var("CUBECAL_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n >= 1);
    let reps = env_reps.unwrap_or(if quick { 3 } else { 101 });
    for (n_views, reps) in [
        (10, reps),
        (50, env_reps.unwrap_or(if quick { 1 } else { 21 })),
    ] {
        let equal = bench("solve", n_views, reps, Mode::Plain);
        let weighted = bench("solve", n_views, reps, Mode::Weighted);
        bench("solve", n_views, reps, Mode::EqualWithCovariance);
        println!(
            "solve, {n_views} views: weighted / equal weights, CPU time per LM iteration: {:.3}",
            weighted / equal
        );
    }
    bench_rig_refinement(reps);
}
