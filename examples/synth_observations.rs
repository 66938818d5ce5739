//! Writes a synthetic observations file (three-face cube, reference camera, seeded noise) for
//! `cubecal solve`. Used to make `fixtures/observations/cube_synthetic.json`:
//!
//! ```sh
//! cargo run --example synth_observations -- 10 0.3 42 > fixtures/observations/cube_synthetic.json
//! ```
//! Arguments: number of views, noise σ (px), seed.
#![allow(clippy::print_stdout, clippy::print_stderr)]

use cubecal::calib::observations::Observations;
use cubecal::render::correspondences::{add_noise, cube_scenario, reference_camera};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n_views: usize = args.first().map(|s| s.parse()).transpose()?.unwrap_or(10);
    let sigma: f64 = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(0.3);
    let seed: u64 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(42);
    let camera = reference_camera();
    let sc = cube_scenario(&camera, 200.0, n_views, seed);
    let views = add_noise(&sc.views, sigma, seed.wrapping_add(1));
    let obs = Observations {
        image_size: camera.image_size,
        views,
    };
    eprintln!(
        "truth: fx {} fy {} cx {} cy {} dist {:?}",
        camera.fx(),
        camera.fy(),
        camera.cx(),
        camera.cy(),
        camera.distortion_coefficients()
    );
    println!("{}", serde_json::to_string(&obs.to_raw())?);
    Ok(())
}
