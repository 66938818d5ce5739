//! Issue 30's acceptance figures for the two-axis station (rotation + tilt on the GRBL simulator,
//! synthetic 1920×1080 camera with k3 ≠ 0), printed as tables:
//!
//! ```sh
//! cargo run --example plan_eval -- table 20     # line 1: coverage, k3, fx/fy, σ(cx, cy), cx/cy per seed
//! cargo run --example plan_eval -- compare 10   # line 2: poses to reach the σ targets, planned vs sweep
//! cargo run --example plan_eval -- manual 20    # line 3: line 1's table, a scripted operator moving a manual stage
//! ```
//! (The manual table's operator does what each prompt says; `tests/station_plan.rs` has one that
//! forgets tilts and is asked again.)
//! Every run is a real station run (render, detect, solve, judge) through the GRBL simulator on a
//! pseudo-terminal; seeds change the render noise. Each table row says which bars it meets.
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::sync::atomic::AtomicBool;

use anyhow::Result;
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, TurntableKind, set_key};
use cubecal::station::{RunResult, RunSpec, hardware};
use cubecal::turntable::manual::Operator;

const CUBE: &str = include_str!("../fixtures/rigs/cube_outside.toml");

/// Issue 30 line 1's camera and stage: realistic 1920×1080, k3 ≠ 0, two-axis GRBL simulator.
pub const ACCEPTANCE: &[(&str, &str)] = &[
    ("synthetic.width", "1920"),
    ("synthetic.height", "1080"),
    ("synthetic.fx", "1400.0"),
    ("synthetic.fy", "1400.0"),
    ("synthetic.cx", "962.3"),
    ("synthetic.cy", "537.8"),
    ("synthetic.k1", "-0.2"),
    ("synthetic.k2", "0.05"),
    ("synthetic.k3", "0.05"),
    ("synthetic.blur", "1.0"),
    ("synthetic.noise", "2.0"),
    ("synthetic.gamma", "2.2"),
    ("synthetic.vignetting", "0.3"),
    // 4×4 sub-samples: 2×2 locate an edge only to 1/4 px and bias cx by ~0.3 px (tests/station.rs)
    ("synthetic.supersample", "4"),
    ("turntable.kind", "\"sim-grbl\""),
    ("turntable.tilt", "true"),
    ("plan.poses", "40"),
    ("plan.stop_when_sufficient", "true"),
    ("plan.target_sigma_fx_rel", "5e-5"),
    ("plan.target_sigma_cx_px", "0.065"),
    ("qa.min_coverage", "0.7"),
    ("qa.max_sigma_cx_px", "0.07"),
    // generous serial replies: these runs share the machine with other builds
    ("turntable.reply_timeout_ms", "5000"),
];

fn config(extra: &[(&str, String)]) -> Result<StationConfig> {
    let mut t = toml::Table::new();
    for (k, v) in ACCEPTANCE {
        set_key(&mut t, k, v)?;
    }
    for (k, v) in extra {
        set_key(&mut t, k, v)?;
    }
    Ok(StationConfig::from_table(t, "plan_eval")?)
}

/// An operator who does what every prompt says and confirms.
struct Follows;

impl Operator for Follows {
    fn confirm(&mut self, _instruction: &str) -> std::io::Result<bool> {
        Ok(true)
    }
}

fn run(cfg: &StationConfig) -> Result<(RunResult, f64)> {
    let rig = Rig::from_toml_str(CUBE, "cube_outside.toml")?.0;
    let operator: Option<Box<dyn Operator>> = (cfg.turntable.kind == TurntableKind::Manual)
        .then(|| Box::new(Follows) as Box<dyn Operator>);
    let hw = hardware::open(cfg, &rig, operator)?;
    let dir = tempfile::tempdir()?;
    let run_dir = dir.path().join("run");
    let spec = RunSpec {
        config: cfg,
        rig: &rig,
        rig_toml: CUBE,
        rig_path: None,
        run_dir: &run_dir,
    };
    let t = std::time::Instant::now();
    let r = cubecal::station::run(
        &spec,
        hw,
        &mut cubecal::station::event::NullSink,
        &AtomicBool::new(false),
    )?;
    Ok((r, t.elapsed().as_secs_f64()))
}

/// The coverage check's value in a result.
fn coverage(r: &RunResult) -> f64 {
    (r.verdict.checks.iter())
        .find(|c| c.name == "coverage")
        .map_or(f64::NAN, |c| c.value)
}

fn table(seeds: u64, manual: bool) -> Result<()> {
    println!(
        "seed poses cover   k3 (est ± σ, truth 0.05)   fx err %  fy err %  σcx    σcy    cx err  cy err  verdict  line1  time"
    );
    let mut met = 0;
    for seed in 1..=seeds {
        let mut keys = vec![("synthetic.seed", seed.to_string())];
        if manual {
            keys.push(("turntable.kind", "\"manual\"".into()));
        }
        let cfg = config(&keys)?;
        let truth = cfg.synthetic.camera();
        let (r, secs) = match run(&cfg) {
            Ok(x) => x,
            Err(e) => {
                println!("{seed:4} run failed: {e:#}");
                continue;
            }
        };
        let Some(c) = r.calibration.as_ref() else {
            println!("{seed:4} no calibration: {:?}", r.solve_error);
            continue;
        };
        let k = c.camera_matrix;
        let sd = |n: &str| c.std_dev.get(n).copied().unwrap_or(f64::NAN);
        let k3 = c
            .distortion
            .coefficients
            .get(4)
            .copied()
            .unwrap_or(f64::NAN);
        let k3_estimated = r.verdict.fixed.iter().all(|f| f.name != "k3");
        let fx_e = 100.0 * (k[0][0] - truth.fx()) / truth.fx();
        let fy_e = 100.0 * (k[1][1] - truth.fy()) / truth.fy();
        let (cx_e, cy_e) = (k[0][2] - truth.cx(), k[1][2] - truth.cy());
        let cov = coverage(&r);
        let ok = cov >= 0.7
            && k3_estimated
            && (k3 - 0.05).abs() <= 3.0 * sd("k3")
            && fx_e.abs() <= 0.02
            && fy_e.abs() <= 0.02
            && sd("cx") <= 0.07
            && sd("cy") <= 0.07
            && cx_e.abs() <= 0.2
            && cy_e.abs() <= 0.2;
        met += usize::from(ok);
        println!(
            "{seed:4} {:5} {:4.0}%  {:>9} ± {:.4} {:>8}  {fx_e:+8.4} {fy_e:+8.4}  {:.4} {:.4} {cx_e:+.3}  {cy_e:+.3}  {:7}  {:5}  {secs:.0}s",
            r.views.len(),
            100.0 * cov,
            format!("{k3:+.4}"),
            sd("k3"),
            if k3_estimated { "" } else { "(fixed)" },
            sd("cx"),
            sd("cy"),
            if r.verdict.pass { "pass" } else { "FAIL" },
            if ok { "met" } else { "NOT" },
        );
    }
    println!("line 1 met in {met} of {seeds} seeds (bar: 19 of 20)");
    Ok(())
}

fn compare(seeds: u64) -> Result<()> {
    println!("seed  planned: poses reached  sweep: poses reached");
    let (mut sum_p, mut sum_s, mut fewer) = (0usize, 0usize, 0usize);
    for seed in 1..=seeds {
        let mut row = Vec::new();
        for planner in ["predicted", "sweep"] {
            let cfg = config(&[
                ("synthetic.seed", seed.to_string()),
                ("plan.planner", format!("\"{planner}\"")),
                ("plan.poses", "49".into()),
            ])?;
            match run(&cfg) {
                Ok((r, _)) => row.push((r.views.len(), r.verdict.pass)),
                Err(e) => {
                    println!("{seed:4} {planner} run failed: {e:#}");
                    row.push((usize::MAX, false));
                }
            }
        }
        let (p, s) = (row[0], row[1]);
        sum_p += p.0;
        sum_s += s.0;
        fewer += usize::from(p.1 && (!s.1 || p.0 < s.0));
        println!("{seed:4}  {:5} {:7}  {:5} {:7}", p.0, p.1, s.0, s.1);
    }
    println!(
        "mean poses: planned {:.1}, sweep {:.1}; planned needed fewer (and passed) in {fewer} of {seeds} seeds",
        sum_p as f64 / seeds as f64,
        sum_s as f64 / seeds as f64
    );
    Ok(())
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n = |d: u64| args.get(1).and_then(|s| s.parse().ok()).unwrap_or(d);
    match args.first().map(String::as_str) {
        Some("table") => table(n(20), false),
        Some("manual") => table(n(20), true),
        Some("compare") => compare(n(10)),
        _ => anyhow::bail!("usage: plan_eval table [SEEDS] | compare [SEEDS] | manual [SEEDS]"),
    }
}
