//! Planning-time benchmark (issue 30 line 2: planning a pose ≤ 50 ms): `cargo bench --bench plan`.
//! Times one choice of the two-axis planner (every candidate of the default 7 × 7 grid predicted and
//! scored against the poses already taken) on the acceptance camera (1920×1080, k3 ≠ 0), after 0, 5
//! and 15 accepted poses; prints wall and this thread's CPU time per choice and the 50 ms bar.
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::time::Instant;

use cubecal::calib::Fix;
use cubecal::camera::{Camera, DistortionModel};
use cubecal::render::{StageGeometry, default_view};
use cubecal::rig::Rig;
use cubecal::station::plan::{Planner, StagePose, grid};

#[path = "support/cpu.rs"]
mod cpu;
use cpu::cpu_ns;

fn main() {
    let rig = Rig::from_toml_str(
        include_str!("../fixtures/rigs/cube_outside.toml"),
        "cube_outside.toml",
    )
    .unwrap()
    .0;
    let camera = Camera::pinhole([1920, 1080], 1400.0, 1400.0, 962.3, 537.8)
        .with_distortion(DistortionModel::Brown5, &[-0.2, 0.05, 0.0, 0.0, 0.05]);
    let base = default_view(&rig, &camera);
    let planner = Planner {
        rig,
        geometry: StageGeometry {
            rig_offset_mm: 300.0,
            tilt_pivot_mm: 300.0,
        },
        candidates: grid(60.0, Some((-30.0, 30.0)), 10.0),
        model: DistortionModel::Brown5,
        fix: Fix::default(),
        target_sigma_f_rel: 5e-5,
        target_sigma_c_px: 0.065,
        min_corners: 20,
    };
    println!(
        "{} candidates; one choice = predict + score every untried candidate",
        planner.candidates.len()
    );
    for n_taken in [0usize, 5, 15] {
        let mut taken: Vec<StagePose> = Vec::new();
        while taken.len() < n_taken {
            let c = planner.next(&camera, &base, &taken, &[], 0.1).unwrap();
            taken.push(c.pose);
        }
        let reps = 5;
        let (t, cpu) = (Instant::now(), cpu_ns());
        for _ in 0..reps {
            std::hint::black_box(planner.next(&camera, &base, &taken, &[], 0.1));
        }
        let wall = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let cpu = match (cpu, cpu_ns()) {
            (Some(a), Some(b)) => format!("{:.1} ms CPU", (b - a) as f64 / 1e6 / reps as f64),
            _ => "CPU n/a".into(),
        };
        println!(
            "after {n_taken:2} poses: {wall:.1} ms wall, {cpu} per choice (bar 50 ms: {})",
            if wall <= 50.0 { "met" } else { "NOT met" }
        );
    }
}
