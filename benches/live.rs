//! Live page benchmark: `cargo bench --bench live`. Release build; needs Debian's chromium.
//! A synthetic station run at 1280×960 (the GRBL simulator, 12 poses, 2 frames each) with the live
//! page open in headless Chromium, driven over the DevTools protocol. Prints the grab-to-page
//! latency of every frame the page received — from the moment the station's grab returned
//! (`Event::Frame`'s `grabbed_unix_ms`) to the page's script receiving that frame's JPEG event
//! (`Date.now()` in its handler; the same clock, one machine) — as mean, median, p95 and max, the
//! frames the page skipped because the encoder was busy, and the station's wall time for the same
//! run without the page and with it (in process; the whole-process ratio is measured separately, see
//! README "The live page").
#![allow(
    clippy::print_stdout,
    clippy::print_stderr,
    clippy::unwrap_used,
    clippy::expect_used
)]

#[path = "../tests/support/chromium.rs"]
mod chromium;

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use cubecal::live::{Live, Tee};
use cubecal::rig::Rig;
use cubecal::station::config::{StationConfig, set_key};
use cubecal::station::event::NullSink;

const SETTINGS: &[(&str, &str)] = &[
    ("camera.source", "\"synthetic\""),
    ("synthetic.width", "1280"),
    ("synthetic.height", "960"),
    ("synthetic.fx", "1100.0"),
    ("synthetic.fy", "1100.0"),
    ("turntable.kind", "\"sim-grbl\""),
    ("plan.poses", "12"),
];

fn run(
    cfg: &StationConfig,
    rig: &Rig,
    rig_toml: &str,
    dir: &std::path::Path,
    live: Option<&Live>,
) -> Duration {
    let spec = cubecal::station::RunSpec {
        config: cfg,
        rig,
        rig_toml,
        rig_path: None,
        run_dir: dir,
    };
    let hw = cubecal::station::hardware::open(cfg, rig, None).unwrap();
    let stop = AtomicBool::new(false);
    let t0 = Instant::now();
    let r = match live {
        Some(live) => {
            live.run_started(dir);
            let mut page = live.sink();
            let mut both = Tee {
                first: &mut NullSink,
                second: &mut page,
            };
            cubecal::station::run(&spec, hw, &mut both, &stop)
        }
        None => cubecal::station::run(&spec, hw, &mut NullSink, &stop),
    };
    let wall = t0.elapsed();
    r.unwrap();
    wall
}

fn main() {
    let Some(chromium) = chromium::find() else {
        eprintln!("live bench: no chromium (apt-get install chromium); nothing measured");
        return;
    };
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let rig_toml = std::fs::read_to_string(root.join("fixtures/rigs/cube_outside.toml")).unwrap();
    let rig = Rig::from_toml_str(&rig_toml, "cube_outside.toml")
        .unwrap()
        .0;
    let mut table = toml::Table::new();
    for (k, v) in SETTINGS {
        set_key(&mut table, k, v).unwrap();
    }
    let cfg = StationConfig::from_table(table, "bench").unwrap();
    let dir = tempfile::tempdir().unwrap();

    let without = run(&cfg, &rig, &rig_toml, &dir.path().join("without"), None);

    let live = Live::start("127.0.0.1:0", None, Arc::new(AtomicBool::new(false))).unwrap();
    let mut browser = chromium::Browser::start(&chromium);
    browser.goto(&live.url());
    browser.wait_for("the page connected", Duration::from_secs(30), |d| {
        d["state"] == "waiting"
    });
    let with = run(&cfg, &rig, &rig_toml, &dir.path().join("with"), Some(&live));
    // The last frame's message may still be on its way.
    std::thread::sleep(Duration::from_millis(300));
    let latencies = browser.eval("JSON.stringify(window.cubecalLatencies || [])");
    let mut ms: Vec<f64> = serde_json::from_str(latencies.as_str().unwrap_or("[]")).unwrap();
    assert!(!ms.is_empty(), "the page received no frame");
    ms.sort_by(f64::total_cmp);
    let at = |q: f64| ms[((q * ms.len() as f64) as usize).min(ms.len() - 1)];
    let mean = ms.iter().sum::<f64>() / ms.len() as f64;
    let console = browser.console.lock().unwrap().clone();
    println!(
        "live page, 1280×960 frames sent at {} px wide as JPEG q{}: grab-to-page latency over {} frames: mean {mean:.1} ms, median {:.1} ms, p95 {:.1} ms, max {:.1} ms; frames skipped by the encoder: {}; console messages: {}",
        cubecal::live::FRAME_WIDTH,
        cubecal::live::JPEG_QUALITY,
        ms.len(),
        at(0.5),
        at(0.95),
        ms[ms.len() - 1],
        live.frames_dropped(),
        console.len()
    );
    println!(
        "station wall time in process, 12 poses at 1280×960 on the GRBL simulator: without the page {:.2} s, with it open {:.2} s (ratio {:.3})",
        without.as_secs_f64(),
        with.as_secs_f64(),
        with.as_secs_f64() / without.as_secs_f64()
    );
}
