//! Where the corner error of issue 19's case renders sits: per labelled corner, its error against the
//! ground truth, binned by its lattice distance to its face's pattern edge (and, on the wrapped cube,
//! to the fold), by its distance to the image border and by its image radius, with the error's
//! component towards the nearest pattern edge (+ outwards) and along the image radius (+ outwards).
//!
//! ```sh
//! cargo run --release --example detect_accuracy -- 6 target/detect_accuracy
//! CASE=fill NOISE=0 VIG=0 cargo run --release --example detect_accuracy -- 6 target/detect_accuracy
//! ```
//! Arguments: views per set (≤ 6), cache directory. Environment: `CASE` (one set), `NOISE`, `VIG`,
//! `BLUR`, `GAMMA`, `SS` (supersampling) (override the render settings; each variant is cached apart), `REREFINE=1` (fit
//! again in undistorted coordinates with the true camera), `WORST=N` (list the N worst corners).
#![allow(clippy::print_stdout, clippy::print_stderr)]

#[path = "../tests/cases/mod.rs"]
mod cases;

use std::collections::HashMap;
use std::path::PathBuf;

use cubecal::detect::{CornerFinder, detect, refine_with_camera};
use nalgebra::Vector2;

#[derive(Default)]
struct Bin {
    n: usize,
    sq: f64,
    max: f64,
    out: f64,
    radial: f64,
}

impl Bin {
    fn add(&mut self, e: Vector2<f64>, outward: Vector2<f64>, radial: Vector2<f64>) {
        self.n += 1;
        self.sq += e.norm_squared();
        self.max = self.max.max(e.norm());
        self.out += e.dot(&outward);
        self.radial += e.dot(&radial);
    }

    fn line(&self, label: &str) -> String {
        let n = self.n.max(1) as f64;
        format!(
            "  {label:>22}: {:5} corners, RMS {:.4}, max {:.4}, mean toward pattern edge {:+.4}, mean radial {:+.4} px",
            self.n,
            (self.sq / n).sqrt(),
            self.max,
            self.out / n,
            self.radial / n
        )
    }
}

fn env_f64(name: &str) -> Option<f64> {
    std::env::var(name).ok().and_then(|s| s.parse().ok())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n: usize = args.first().map(|s| s.parse()).transpose()?.unwrap_or(6);
    let cache = PathBuf::from(
        args.get(1)
            .map(String::as_str)
            .unwrap_or("target/detect_accuracy"),
    );
    let only = std::env::var("CASE").ok();
    let rerefine = std::env::var_os("REREFINE").is_some();
    let worst: usize = env_f64("WORST").map_or(0, |v| v as usize);
    let mut finder = CornerFinder::new()?;
    for mut case in cases::cases(n) {
        if only.as_deref().is_some_and(|o| o != case.name) {
            continue;
        }
        let mut variant = String::new();
        for (var, field) in [
            ("NOISE", &mut case.settings.noise_sigma),
            ("VIG", &mut case.settings.vignetting),
            ("BLUR", &mut case.settings.blur_sigma_px),
            ("GAMMA", &mut case.settings.gamma),
        ] {
            if let Some(v) = env_f64(var) {
                *field = v;
                variant.push_str(&format!("{var}={v} "));
            }
        }
        if let Some(v) = env_f64("SS") {
            case.settings.supersample = v as u32;
            variant.push_str(&format!("SS={v} "));
        }
        let dir = cache.join(variant.trim().replace([' ', '='], "_"));
        let cam = case.camera.clone();
        let centre = Vector2::new(cam.cx(), cam.cy());
        let [w, h] = cam.image_size.map(f64::from);
        let mut by_ring: Vec<Bin> = (0..4).map(|_| Bin::default()).collect();
        let mut by_fold: Vec<Bin> = (0..4).map(|_| Bin::default()).collect();
        let mut by_border: Vec<Bin> = (0..5).map(|_| Bin::default()).collect();
        let mut by_radius: Vec<Bin> = (0..5).map(|_| Bin::default()).collect();
        let mut by_window: Vec<Bin> = (0..3).map(|_| Bin::default()).collect();
        let mut by_axis: Vec<Bin> = (0..4).map(|_| Bin::default()).collect();
        let mut all = Bin::default();
        let mut rows = Vec::new();
        for k in 0..case.poses.len() {
            let (img, truth) = cases::frame(&case, k, &dir);
            let mut det = detect(&mut finder, &img, &case.rig)?;
            if rerefine {
                refine_with_camera(&img, &mut det, &cam)?;
            }
            let gt: HashMap<(usize, usize, usize), Vector2<f64>> = truth
                .visible()
                .filter_map(|c| Some(((c.face_index, c.row, c.col), c.uv.map(Vector2::from)?)))
                .collect();
            for d in &det.faces {
                let face = &case.rig.faces[d.face];
                for c in &d.corners {
                    let Some(t) = gt.get(&(d.face, c.row, c.col)).copied() else {
                        continue;
                    };
                    let e = c.uv - t;
                    if e.norm() > 1.0 {
                        continue;
                    }
                    // The image step to each lattice neighbour, from the truth (or mirrored).
                    let step = |dr: i64, dc: i64| -> Vector2<f64> {
                        let (r, cc) = (c.row as i64 + dr, c.col as i64 + dc);
                        let back = (c.row as i64 - dr, c.col as i64 - dc);
                        let get = |r: i64, cc: i64| {
                            (r >= 0 && cc >= 0)
                                .then(|| gt.get(&(d.face, r as usize, cc as usize)).copied())
                                .flatten()
                        };
                        get(r, cc)
                            .map(|n| n - t)
                            .or_else(|| get(back.0, back.1).map(|n| t - n))
                            .unwrap_or_else(Vector2::zeros)
                    };
                    // Lattice distance to the face's pattern edge and the outward direction there.
                    let sides = [
                        (c.col, (0, -1)),
                        (face.cols - 1 - c.col, (0, 1)),
                        (c.row, (-1, 0)),
                        (face.rows - 1 - c.row, (1, 0)),
                    ];
                    let (ring, (dr, dc)) =
                        sides.into_iter().min_by_key(|s| s.0).unwrap_or_default();
                    let outward = step(dr, dc).try_normalize(1e-9).unwrap_or_default();
                    let radial = (t - centre).try_normalize(1e-9).unwrap_or_default();
                    let border = (t.x + 0.5)
                        .min(t.y + 0.5)
                        .min(w - 0.5 - t.x)
                        .min(h - 0.5 - t.y);
                    let half = 0.65 * step(0, 1).norm().min(step(1, 0).norm());
                    let rel_r = (t - centre).norm() / (w / 2.0).hypot(h / 2.0);
                    all.add(e, outward, radial);
                    by_ring[ring.min(3)].add(e, outward, radial);
                    if case.name == "wrapped-cube" {
                        // The fold is at the last column of "front" and the first of "right".
                        let f = if d.face == 0 {
                            face.cols - 1 - c.col
                        } else {
                            c.col
                        };
                        by_fold[f.min(3)].add(e, outward, radial);
                    }
                    let bi = [20.0, 50.0, 100.0, 200.0]
                        .iter()
                        .position(|&b| border < b)
                        .unwrap_or(4);
                    by_border[bi].add(e, outward, radial);
                    by_radius[((rel_r * 5.0) as usize).min(4)].add(e, outward, radial);
                    by_window[if half < 12.0 {
                        0
                    } else if half < 24.0 {
                        1
                    } else {
                        2
                    }]
                    .add(e, outward, radial);
                    // How far the corner's two lattice lines are from the pixel axes (deg): the
                    // render's box-filter supersampling quantises an edge parallel to an axis.
                    let off_axis = |v: Vector2<f64>| {
                        let a = v.y.atan2(v.x).to_degrees().rem_euclid(90.0);
                        a.min(90.0 - a)
                    };
                    let tilt = off_axis(step(0, 1)).min(off_axis(step(1, 0)));
                    by_axis[[0.5, 2.0, 5.0].iter().position(|&b| tilt < b).unwrap_or(3)]
                        .add(e, outward, radial);
                    rows.push((
                        e.norm(),
                        format!(
                            "frame {k} face {} ({:2},{:2}) ring {ring} border {border:6.1} px r {rel_r:.2} step {:5.1} px err ({:+.3},{:+.3}) toward edge {:+.3} radial {:+.3} σ {:.3}",
                            face.name,
                            c.row,
                            c.col,
                            step(0, 1).norm().min(step(1, 0).norm()),
                            e.x,
                            e.y,
                            e.dot(&outward),
                            e.dot(&radial),
                            c.sigma_px
                        ),
                    ));
                }
            }
        }
        println!(
            "CASE {} {}{}",
            case.name,
            variant,
            if rerefine { "REREFINE" } else { "" }
        );
        println!("{}", all.line("all"));
        for (i, b) in by_ring.iter().enumerate() {
            println!(
                "{}",
                b.line(&format!("ring {i}{}", if i == 3 { "+" } else { "" }))
            );
        }
        if case.name == "wrapped-cube" {
            for (i, b) in by_fold.iter().enumerate() {
                println!(
                    "{}",
                    b.line(&format!(
                        "{i}{} steps from fold",
                        if i == 3 { "+" } else { "" }
                    ))
                );
            }
        }
        for (b, l) in by_border
            .iter()
            .zip(["border <20", "20–50", "50–100", "100–200", "≥200"])
        {
            println!("{}", b.line(l));
        }
        for (i, b) in by_radius.iter().enumerate() {
            println!(
                "{}",
                b.line(&format!(
                    "r {:.1}–{:.1}",
                    i as f64 / 5.0,
                    (i + 1) as f64 / 5.0
                ))
            );
        }
        for (b, l) in by_window
            .iter()
            .zip(["window <12 px", "window 12–24", "window capped 24"])
        {
            println!("{}", b.line(l));
        }
        for (b, l) in by_axis
            .iter()
            .zip(["lines <0.5° off axis", "0.5–2°", "2–5°", "≥5°"])
        {
            println!("{}", b.line(l));
        }
        rows.sort_by(|a, b| b.0.total_cmp(&a.0));
        for (_, r) in rows.iter().take(worst) {
            println!("    {r}");
        }
    }
    Ok(())
}
