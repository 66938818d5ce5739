//! Are the station's σ honest? Runs the synthetic station (its default known camera, the simulated
//! GRBL turntable) with `N` render seeds and prints, per run, the errors of fx, fy, cx, cy against the
//! truth in units of the reported σ and `χ² = eᵀ C⁻¹ e` with the reported 4×4 covariance `C`
//! (issue 29, acceptance line 3): honest σ give χ² distributed with 4 degrees of freedom (mean 4,
//! 95th percentile 9.49).
//!
//! ```sh
//! cargo run --release --example station_chi2 -- 20
//! ```
//! Each run's fit views are also re-solved with the corners weighted alike (the station before issue
//! 29), side by side.
#![allow(clippy::print_stdout, clippy::unwrap_used, clippy::expect_used)]

use std::sync::atomic::AtomicBool;

use cubecal::calib::observations::{Observations, RawObservations};
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, set_key};
use cubecal::station::{RunSpec, hardware};
use nalgebra::{DMatrix, DVector};

const CUBE: &str = include_str!("../fixtures/rigs/cube_outside.toml");
const NAMES: [&str; 4] = ["fx", "fy", "cx", "cy"];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(20);
    let rig = Rig::from_toml_str(CUBE, "cube_outside.toml").unwrap().0;
    println!(
        "synthetic station: per seed, (estimate − truth)/σ of fx fy cx cy and χ², as the station solved \
         (corners weighted by their covariances) | re-solved from its observations.json with equal weights"
    );
    let mut chi2s: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    for seed in 1..=n {
        let mut t = toml::Table::new();
        set_key(&mut t, "synthetic.seed", &seed.to_string()).unwrap();
        // The station weighting each corner by its covariance; re-solved below with equal weights.
        set_key(&mut t, "solve.weighting", "covariance").unwrap();
        // A loaded machine delays the simulated turntable's replies beyond the default wait.
        set_key(&mut t, "turntable.reply_timeout_ms", "20000").unwrap();
        let cfg = StationConfig::from_table(t, "station_chi2").unwrap();
        let truth = cfg.synthetic.camera();
        let hw = hardware::open(&cfg, &rig, None).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let run_dir = dir.path().join("run");
        let spec = RunSpec {
            config: &cfg,
            rig: &rig,
            rig_toml: CUBE,
            rig_path: None,
            run_dir: &run_dir,
        };
        let r = cubecal::station::run(
            &spec,
            hw,
            &mut cubecal::station::event::NullSink,
            &AtomicBool::new(false),
        )
        .unwrap();
        let Some(rep) = r.calibration else {
            println!("  seed {seed:2}: no calibration");
            continue;
        };
        // The station's own intrinsics and covariance, and the same fit views re-solved with the
        // corners weighted alike (the station's options otherwise).
        let k = rep.camera_matrix;
        let mut p = vec![0.0; 13];
        (p[0], p[1], p[2], p[3]) = (k[0][0], k[1][1], k[0][2], k[1][2]);
        let q = rep.free_params.len();
        let cov = DMatrix::from_fn(q, q, |i, j| rep.covariance[i][j]);
        let station = (p, rep.free_params.clone(), cov, rep.noise_scale);
        let text = std::fs::read_to_string(run_dir.join("observations.json")).unwrap();
        let raw: RawObservations = serde_json::from_str(&text).unwrap();
        let obs = Observations::from_json(&text, &run_dir).unwrap();
        let fit: Vec<_> = obs
            .views
            .into_iter()
            .zip(&raw.views)
            .filter(|(_, rv)| !rv.held_out)
            .map(|(v, _)| v)
            .collect();
        let mut opts = cfg.solve_options("station_chi2").unwrap();
        opts.weighting = cubecal::calib::Weighting::Equal;
        if !rep.std_dev.contains_key("k3") {
            opts.fix.k3 = true;
        }
        let c = cubecal::calib::solve(&fit, obs.image_size, &opts).unwrap();
        let equal = (
            c.camera.params.to_vec(),
            c.free_params
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>(),
            c.covariance.clone(),
            c.noise_scale,
        );
        let mut line = format!("  seed {seed:2}:");
        for (slot, (params, free, cov, scale)) in [station, equal].into_iter().enumerate() {
            let pos: Vec<usize> = NAMES
                .iter()
                .map(|n| free.iter().position(|f| f == n).unwrap())
                .collect();
            let c = DMatrix::from_fn(4, 4, |i, j| cov[(pos[i], pos[j])]);
            let e = DVector::from_iterator(4, (0..4).map(|k| params[k] - truth.params[k]));
            let chi2 = e.dot(&c.clone().cholesky().unwrap().solve(&e));
            chi2s[slot].push(chi2);
            let z: Vec<String> = (0..4)
                .map(|k| format!("{:+6.2}", e[k] / c[(k, k)].sqrt()))
                .collect();
            line += &format!(
                "  {} χ² {chi2:6.2}{}  |",
                z.join(" "),
                scale.map_or(String::new(), |s| format!(" (noise scale {s:.2})"))
            );
        }
        println!("{line}");
    }
    for (slot, label) in ["station (weighted)", "equal weights"].iter().enumerate() {
        let chi2s = &chi2s[slot];
        let m = chi2s.len() as f64;
        let mean = chi2s.iter().sum::<f64>() / m;
        let over = chi2s.iter().filter(|&&c| c > 9.488).count();
        println!(
            "{label}, {} runs: mean χ² {mean:.2} (4 ± {:.2} expected for honest σ: 2·√(8/{})), {over} above the 95th percentile 9.49 ({:.1} expected)",
            chi2s.len(),
            2.0 * (8.0 / m).sqrt(),
            chi2s.len(),
            0.05 * m
        );
    }
}
