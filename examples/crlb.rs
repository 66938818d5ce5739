//! The Cramér–Rao lower bound of the detector's corners on the synthetic evaluation sets, against
//! their measured errors (issue 19, line 1's "RMS ≤ 0.1 px at 75–80°" on the hard set):
//!
//! ```sh
//! cargo run --release --example crlb -- hard 24 target/detect_eval
//! cargo run --release --example crlb -- realistic 24 target/detect_eval
//! ```
//! Arguments as `detect_eval` (set, number of poses, cache directory; the frames cached there are
//! reused). Every correctly labelled corner of a fully visible face found at 45–80° gets the four
//! bounds of [`cubecal::detect::crlb`] — over its fit window (position only; with the local model's
//! unknowns) and over its face (position only; a joint fit of the face's pose, levels and blur) —
//! from the renderer's noise-free image model at `SS`×`SS` supersampling (default 16) and its noise.
//! Printed per angle bucket: the measured RMS error, and each bound's RMS `sqrt(mean trace(cov))`;
//! for 75–80° also per face, and by the corner's place in its grid. `BUCKETS=45-60,75-80` picks the
//! buckets, `FRAMES=2,4,7` the frames, `STEP_PX` the finite-difference step (image motion, default
//! 0.1 px), `MC=k` also fits a few corners of each face on `k` fresh noise draws over the model (the
//! fit's scatter against its window bound).
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::collections::HashMap;
use std::path::PathBuf;

use anyhow::Context;
use cubecal::detect::crlb::{
    CornerBound, Crop, View, corner_bounds, derivatives, expected_image, face_pixels,
    noise_variance,
};
use cubecal::detect::refine::{refine_near_border, refine_near_border_with_window};
use cubecal::detect::score::{EvalSet, MISLABEL_PX, score};
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::cached_frame;
use cubecal::rig::Rig;
use nalgebra::{Matrix2, Vector2};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// With `MC=k`: this many corners of each face are fitted on `k` fresh noise draws.
const MC_CORNERS_PER_FACE: usize = 6;

/// A corner fitted on fresh noise draws (`MC`).
struct Draws {
    frame: usize,
    face: usize,
    /// Scatter of the fits: trace of their covariance, px².
    variance: f64,
    /// Mean fit minus the truth.
    bias: Vector2<f64>,
    /// The detected corner the fits started from (identifies the corner).
    start: Vector2<f64>,
}

/// One correctly labelled corner with its bounds.
struct Record {
    frame: usize,
    face: usize,
    angle_deg: f64,
    /// Lattice distance to the nearest side of the grid (0: the outer ring).
    ring: usize,
    /// Angle between the corner's two lattice lines in the image, degrees (0–90).
    line_angle_deg: f64,
    error: Vector2<f64>,
    /// Error of the window's fit alone (before the lattice's curvature correction).
    fit_error: Vector2<f64>,
    truth: Vector2<f64>,
    sigma_px: f64,
    bound: CornerBound,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let set_name = args.first().map(String::as_str).unwrap_or("hard");
    let n: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(24);
    let cache = PathBuf::from(args.get(2).map_or("target/detect_eval", String::as_str));
    let env = |name: &str| std::env::var(name).ok();
    let ss: u32 = env("SS").map(|s| s.parse()).transpose()?.unwrap_or(16);
    let step_px: f64 = env("STEP_PX")
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(0.1);
    let buckets: Vec<(f64, f64)> = env("BUCKETS")
        .unwrap_or_else(|| "45-60,60-75,75-80".into())
        .split(',')
        .map(|b| {
            let (a, z) = b
                .split_once('-')
                .context("a bucket is LOW-HIGH (degrees)")?;
            Ok((a.parse()?, z.parse()?))
        })
        .collect::<anyhow::Result<_>>()?;
    let rig_path = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/rigs/cube_outside.toml"
    ));
    let (rig, _) = Rig::load(&rig_path)?;
    let Some(set) = EvalSet::from_name(set_name) else {
        anyhow::bail!(
            "unknown set {set_name:?} (realistic | hard | periphery-0.3 | periphery-0.4)"
        );
    };
    let (camera, settings) = (set.camera(), set.settings());
    let dir = cache.join(set_name);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let var = noise_variance(&settings);
    println!(
        "set {set_name}: noise σ {} grey levels (+ rounding: √var {:.3}), blur σ {} px, palette {}/{}, model at {ss}×{ss} supersampling, steps {step_px} px",
        settings.noise_sigma,
        var.sqrt(),
        settings.blur_sigma_px,
        settings.palette.black,
        settings.palette.white
    );
    let mut finder = CornerFinder::new()?;
    let mut records = Vec::new();
    let mc: usize = env("MC").map(|s| s.parse()).transpose()?.unwrap_or(0);
    let mut monte_carlo: Vec<Draws> = Vec::new();
    // FRAMES=2,4,7 restricts the run to those frames.
    let frames: Option<Vec<usize>> = env("FRAMES")
        .map(|f| f.split(',').map(str::parse).collect())
        .transpose()?;
    for (k, pose) in set.poses(&rig, n).iter().enumerate() {
        if frames.as_ref().is_some_and(|f| !f.contains(&k)) {
            continue;
        }
        let (img, truth) = cached_frame(&dir, &rig, &camera, pose, &settings, k as u64)?;
        let det = detect(&mut finder, &img, &rig)?;
        let gt: HashMap<(usize, usize, usize), Vector2<f64>> = truth
            .visible()
            .filter_map(|c| Some(((c.face_index, c.row, c.col), Vector2::from(c.uv?))))
            .collect();
        for s in score(&rig, &truth, &det) {
            let in_bucket = buckets.iter().any(|&(a, b)| (a..b).contains(&s.angle_deg));
            if !(s.fully_visible && s.found && in_bucket) {
                continue;
            }
            let face = &rig.faces[s.face];
            let at = |r: i64, c: i64| -> Option<Vector2<f64>> {
                gt.get(&(s.face, usize::try_from(r).ok()?, usize::try_from(c).ok()?))
                    .copied()
            };
            // The step along (dr, dc) at (r, c), from the truth (central where it can be).
            let step = |r: i64, c: i64, dr: i64, dc: i64| -> Option<Vector2<f64>> {
                match (at(r - dr, c - dc), at(r + dr, c + dc)) {
                    (Some(a), Some(b)) => Some((b - a) / 2.0),
                    (None, Some(b)) => Some(b - at(r, c)?),
                    (Some(a), None) => Some(at(r, c)? - a),
                    (None, None) => None,
                }
            };
            let mut corners = Vec::new();
            for d in det.faces.iter().filter(|d| d.face == s.face) {
                for c in &d.corners {
                    let Some(t) = gt.get(&(s.face, c.row, c.col)) else {
                        continue;
                    };
                    if (c.uv - t).norm() > MISLABEL_PX {
                        continue;
                    }
                    let (r, cc) = (c.row as i64, c.col as i64);
                    let (Some(a), Some(b)) = (step(r, cc, 0, 1), step(r, cc, 1, 0)) else {
                        continue;
                    };
                    let Ok((fit, window)) = refine_near_border_with_window(&img, c.uv, a, b) else {
                        eprintln!(
                            "frame {k} face {} ({}, {}): no fit window at the detected corner",
                            face.name, c.row, c.col
                        );
                        continue;
                    };
                    let angle = a.angle(&b).to_degrees();
                    corners.push((c, *t, angle.min(180.0 - angle), window, a, b, fit.uv - t));
                }
            }
            // The crop: the board's outline (its edges sampled, distortion bends them) and the
            // windows.
            let outline = face.outline();
            let mut points: Vec<Vector2<f64>> = (0..4)
                .flat_map(|e| {
                    let (p, q) = (outline[e], outline[(e + 1) % 4]);
                    (0..32).map(move |i| p + (q - p) * (f64::from(i) / 32.0))
                })
                .filter_map(|x| camera.project(pose, &x).ok())
                .collect();
            points.extend(corners.iter().flat_map(|(_, _, _, w, ..)| {
                w.iter()
                    .map(|p| Vector2::new(f64::from(p[0]), f64::from(p[1])))
            }));
            let Some(crop) = Crop::around(points, 3.0, camera.image_size) else {
                continue;
            };
            let centre =
                (face.corner_xyz(0, 0) + face.corner_xyz(face.rows - 1, face.cols - 1)) / 2.0;
            let view = View {
                rig: &rig,
                camera: camera.clone(),
                cam_from_rig: *pose,
                settings: cubecal::render::RenderSettings {
                    supersample: ss,
                    ..settings
                },
                pivot: pose.transform(&centre),
                step_px,
            };
            let probes: Vec<_> = corners
                .iter()
                .map(|(c, ..)| face.corner_xyz(c.row, c.col))
                .collect();
            let started = std::time::Instant::now();
            let derivs = derivatives(&view, crop, &probes)?;
            let face_px = face_pixels(&rig, &camera, pose, s.face, crop);
            if mc > 0 {
                // The fit itself on fresh noise over the noise-free model (a few corners per face).
                let mu = expected_image(&rig, &camera, pose, &view.settings, crop)?;
                let noise = Normal::new(0.0, settings.noise_sigma)?;
                let mut rng = ChaCha8Rng::seed_from_u64(1000 * k as u64 + s.face as u64);
                let stride = corners.len().div_ceil(MC_CORNERS_PER_FACE).max(1);
                let picked: Vec<usize> = (0..corners.len()).step_by(stride).collect();
                let mut fits = vec![Vec::new(); picked.len()];
                let mut noisy = img.clone();
                for _ in 0..mc {
                    for (i, m) in mu.iter().enumerate() {
                        let [x, y] = crop.pixel(i);
                        let v = (m + noise.sample(&mut rng)).round().clamp(0.0, 255.0);
                        noisy.put_pixel(x, y, image::Luma([v as u8]));
                    }
                    for (f, &i) in fits.iter_mut().zip(&picked) {
                        let (c, _, _, _, a, b, _) = &corners[i];
                        if let Ok(r) = refine_near_border(&noisy, c.uv, *a, *b) {
                            f.push(r.uv);
                        }
                    }
                }
                for (f, &i) in fits.iter().zip(&picked) {
                    if f.len() < 2 {
                        continue;
                    }
                    let n = f.len() as f64;
                    let mean = f.iter().sum::<Vector2<f64>>() / n;
                    let var = f.iter().map(|p| (p - mean).norm_squared()).sum::<f64>() / (n - 1.0);
                    monte_carlo.push(Draws {
                        frame: k,
                        face: s.face,
                        variance: var,
                        bias: mean - corners[i].1,
                        start: corners[i].0.uv,
                    });
                }
            }
            for (i, (c, t, line_angle, window, _, _, fit_error)) in corners.iter().enumerate() {
                let win: Vec<usize> = window.iter().filter_map(|&p| crop.index(p)).collect();
                if win.len() < window.len() {
                    eprintln!("frame {k}: window outside the crop");
                }
                let Some(bound) = corner_bounds(&derivs, i, &win, &face_px, var) else {
                    eprintln!(
                        "frame {k} face {} ({}, {}): no bound",
                        face.name, c.row, c.col
                    );
                    continue;
                };
                let ring = c
                    .row
                    .min(c.col)
                    .min(face.rows - 1 - c.row)
                    .min(face.cols - 1 - c.col);
                records.push(Record {
                    frame: k,
                    face: s.face,
                    angle_deg: s.angle_deg,
                    ring,
                    line_angle_deg: *line_angle,
                    error: c.uv - t,
                    fit_error: *fit_error,
                    truth: *t,
                    sigma_px: c.sigma_px,
                    bound,
                });
            }
            let done: Vec<&Record> = records
                .iter()
                .filter(|r| r.frame == k && r.face == s.face)
                .collect();
            eprintln!(
                "frame {k:3} {:6} {:4.1}° ({:.0} s): {}",
                face.name,
                s.angle_deg,
                started.elapsed().as_secs_f64(),
                Line::of(&done)
            );
        }
    }
    if mc > 0 {
        // Pair each Monte-Carlo corner with its record to compare with its bound.
        let (mut var, mut bias2, mut local, mut position, mut count) = (0.0, 0.0, 0.0, 0.0, 0);
        for d in &monte_carlo {
            let Some(r) = records.iter().find(|r| {
                r.frame == d.frame
                    && r.face == d.face
                    && (r.error + r.truth - d.start).norm() < 1e-9
            }) else {
                continue;
            };
            var += d.variance;
            bias2 += d.bias.norm_squared();
            local += r.bound.window_local.trace();
            position += r.bound.window_position.trace();
            count += 1;
        }
        let n = f64::from(count.max(1));
        println!(
            "the fit on {mc} fresh noise draws over the model, {count} corners: scatter RMS {:.4} px, bias RMS {:.4} px; bound RMS window {:.4} (position only) / {:.4} (local model); scatter / local bound {:.2}",
            (var / n).sqrt(),
            (bias2 / n).sqrt(),
            (position / n).sqrt(),
            (local / n).sqrt(),
            (var / local).sqrt()
        );
    }
    for &(a, b) in &buckets {
        let sel: Vec<&Record> = records
            .iter()
            .filter(|r| (a..b).contains(&r.angle_deg))
            .collect();
        println!("{a}–{b}°: {}", Line::of(&sel));
    }
    // The last bucket in detail (by default 75–80°).
    let Some(&(a, b)) = buckets.last() else {
        return Ok(());
    };
    let last: Vec<&Record> = records
        .iter()
        .filter(|r| (a..b).contains(&r.angle_deg))
        .collect();
    println!("{a}–{b}° by face:");
    let mut faces: Vec<(usize, usize)> = last.iter().map(|r| (r.frame, r.face)).collect();
    faces.dedup();
    for (frame, face) in faces {
        let sel: Vec<&Record> = last
            .iter()
            .copied()
            .filter(|r| r.frame == frame && r.face == face)
            .collect();
        println!(
            "  frame {frame:3} {:6} {:4.1}°: {}",
            rig.faces[face].name,
            sel[0].angle_deg,
            Line::of(&sel)
        );
    }
    println!("{a}–{b}° by ring (0 = the grid's outer ring):");
    for ring in 0..3 {
        let sel: Vec<&Record> = last
            .iter()
            .copied()
            .filter(|r| r.ring.min(2) == ring)
            .collect();
        println!(
            "  ring {ring}{}: {}",
            if ring == 2 { "+" } else { "" },
            Line::of(&sel)
        );
    }
    println!("{a}–{b}° by the angle between the corner's lattice lines in the image:");
    for (lo, hi) in [(0.0, 30.0), (30.0, 45.0), (45.0, 60.0), (60.0, 90.1)] {
        let sel: Vec<&Record> = last
            .iter()
            .copied()
            .filter(|r| (lo..hi).contains(&r.line_angle_deg))
            .collect();
        if !sel.is_empty() {
            println!("  {lo:2}–{hi:2}°: {}", Line::of(&sel));
        }
    }
    Ok(())
}

/// A summary of some corners: measured RMS and each bound's RMS.
struct Line {
    corners: usize,
    measured: f64,
    fit_alone: f64,
    sigma: f64,
    bounds: [f64; 5],
}

impl Line {
    fn of(sel: &[&Record]) -> Line {
        let n = sel.len().max(1) as f64;
        let rms = |f: &dyn Fn(&Record) -> f64| (sel.iter().map(|r| f(r)).sum::<f64>() / n).sqrt();
        let tr = |m: &Matrix2<f64>| m.trace();
        Line {
            corners: sel.len(),
            measured: rms(&|r| r.error.norm_squared()),
            fit_alone: rms(&|r| r.fit_error.norm_squared()),
            sigma: rms(&|r| 2.0 * r.sigma_px.powi(2)),
            bounds: [
                rms(&|r| tr(&r.bound.window_position)),
                rms(&|r| tr(&r.bound.window_local)),
                rms(&|r| tr(&r.bound.face_position)),
                rms(&|r| tr(&r.bound.face_joint)),
                rms(&|r| tr(&r.bound.face_joint_k1)),
            ],
        }
    }
}

impl std::fmt::Display for Line {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The RMS of n corners' errors scatters by about 1/(2√n) of itself (2-D Gaussian errors).
        let spread = 1.0 / (2.0 * (self.corners.max(1) as f64).sqrt());
        let [wp, wl, fp, fj, fk] = self.bounds;
        write!(
            f,
            "{} corners, measured RMS {:.4} px (±{:.0} %; √2·σ {:.4}; the window's fit alone {:.4}); bound RMS: window {:.4} (position only) / {:.4} (local model), face {:.4} (position only) / {:.4} (joint) / {:.4} (joint, k1 unknown); measured / window-local bound {:.2}",
            self.corners,
            self.measured,
            100.0 * spread,
            self.sigma,
            self.fit_alone,
            wp,
            wl,
            fp,
            fj,
            fk,
            self.measured / wl
        )
    }
}
