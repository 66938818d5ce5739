//! Per-view image checks before a view is trusted: **motion** (two consecutive frames of a pose must
//! agree: a rig or camera still moving, or a frame from before the move, differs) and **blur** (the
//! width of the checkerboard's edges where the detector found them).
//!
//! Motion compares 8×8 block means of two frames (every other row: 32 pixels, cutting sensor noise by
//! 5.7), so a block differing by more than [`MOTION_LEVEL`] grey levels is a change of the scene, not
//! noise (noise σ 5 gives block-difference σ ≈ 1.2). The result is the fraction of blocks that changed.
//!
//! Blur is measured on the edges between adjacent labelled corners: across the midpoint of each
//! edge the intensity profile is a blurred step; for a Gaussian blur σ its 10–90 % rise is 2.563 σ.
//! The median over a view's edges is its blur estimate (px, including the pixel's own box filter,
//! σ ≈ 0.29 for a sharp image).

use image::GrayImage;
use nalgebra::Vector2;

use crate::detect::label::FaceDetection;

/// Grey-level change of an 8×8 block mean that counts as motion.
pub const MOTION_LEVEL: f64 = 8.0;
const BLOCK: u32 = 8;

/// Fraction of 8×8 blocks whose mean changed by more than [`MOTION_LEVEL`] between two frames of the
/// same size (1.0 when the sizes differ).
pub fn motion_fraction(a: &GrayImage, b: &GrayImage) -> f64 {
    if a.dimensions() != b.dimensions() {
        return 1.0;
    }
    let (w, h) = a.dimensions();
    let (bw, bh) = (w / BLOCK, h / BLOCK);
    if bw == 0 || bh == 0 {
        return 0.0;
    }
    let (ra, rb) = (a.as_raw(), b.as_raw());
    let mut changed = 0usize;
    for by in 0..bh {
        for bx in 0..bw {
            // Every other row of the block: 32 samples cut the noise by 5.7, plenty against
            // MOTION_LEVEL, at half the cost.
            let mut d: i32 = 0;
            for y in (by * BLOCK..(by + 1) * BLOCK).step_by(2) {
                let row = (y * w + bx * BLOCK) as usize;
                let (a, b) = (
                    &ra[row..row + BLOCK as usize],
                    &rb[row..row + BLOCK as usize],
                );
                d += a
                    .iter()
                    .zip(b)
                    .map(|(&p, &q)| i32::from(p) - i32::from(q))
                    .sum::<i32>();
            }
            if (f64::from(d) / f64::from(BLOCK * BLOCK / 2)).abs() > MOTION_LEVEL {
                changed += 1;
            }
        }
    }
    changed as f64 / f64::from(bw * bh)
}

fn bilinear(img: &GrayImage, p: Vector2<f64>) -> Option<f64> {
    let (w, h) = img.dimensions();
    let (x0, y0) = (p.x.floor(), p.y.floor());
    if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= f64::from(w) || y0 + 1.0 >= f64::from(h) {
        return None;
    }
    let (fx, fy) = (p.x - x0, p.y - y0);
    let (x, y) = (x0 as u32, y0 as u32);
    let g = |x: u32, y: u32| f64::from(img.get_pixel(x, y).0[0]);
    Some(
        g(x, y) * (1.0 - fx) * (1.0 - fy)
            + g(x + 1, y) * fx * (1.0 - fy)
            + g(x, y + 1) * (1.0 - fx) * fy
            + g(x + 1, y + 1) * fx * fy,
    )
}

/// Blur σ (px) of one edge from its profile across the midpoint of `a`–`b`.
fn edge_blur(img: &GrayImage, a: Vector2<f64>, b: Vector2<f64>) -> Option<f64> {
    let d = b - a;
    let len = d.norm();
    if len < 8.0 {
        return None;
    }
    let n = Vector2::new(-d.y, d.x) / len;
    let m = (a + b) / 2.0;
    let half = (0.35 * len).min(12.0);
    let step = 0.25;
    let k = (half / step) as i32;
    let prof: Vec<f64> = (-k..=k)
        .map(|i| bilinear(img, m + n * (f64::from(i) * step)))
        .collect::<Option<_>>()?;
    let q = prof.len() / 5;
    let lo_side: f64 = prof[..q].iter().sum::<f64>() / q as f64;
    let hi_side: f64 = prof[prof.len() - q..].iter().sum::<f64>() / q as f64;
    let (lo, hi, rising) = if hi_side >= lo_side {
        (lo_side, hi_side, true)
    } else {
        (hi_side, lo_side, false)
    };
    if hi - lo < 20.0 {
        return None;
    }
    let level = |f: f64| lo + f * (hi - lo);
    // Positions where the profile crosses 10 % and 90 % (linear interpolation, outermost crossing
    // towards the centre).
    let cross = |target: f64| -> Option<f64> {
        let vals: Vec<f64> = if rising {
            prof.clone()
        } else {
            prof.iter().map(|v| lo + hi - v).collect()
        };
        let mid = vals.len() / 2;
        // Search outward from the centre for the crossing of `target`.
        if vals[mid] >= target {
            (0..mid).rev().find(|&i| vals[i] < target).map(|i| {
                let t = (target - vals[i]) / (vals[i + 1] - vals[i]);
                i as f64 + t
            })
        } else {
            (mid..vals.len() - 1)
                .find(|&i| vals[i + 1] >= target)
                .map(|i| {
                    let t = (target - vals[i]) / (vals[i + 1] - vals[i]);
                    i as f64 + t
                })
        }
    };
    let x10 = cross(level(0.1))?;
    let x90 = cross(level(0.9))?;
    Some(((x90 - x10) * step / 2.563).abs())
}

/// Median blur σ (px) over the edges between adjacent labelled corners, or `None` when no edge could
/// be measured.
pub fn blur_px(img: &GrayImage, faces: &[FaceDetection]) -> Option<f64> {
    let mut widths = Vec::new();
    for f in faces {
        let at: std::collections::HashMap<(usize, usize), Vector2<f64>> =
            f.corners.iter().map(|c| ((c.row, c.col), c.uv)).collect();
        for c in &f.corners {
            for (dr, dc) in [(0, 1), (1, 0)] {
                if let Some(b) = at.get(&(c.row + dr, c.col + dc))
                    && let Some(w) = edge_blur(img, c.uv, *b)
                {
                    widths.push(w);
                }
            }
        }
    }
    if widths.is_empty() {
        return None;
    }
    widths.sort_by(f64::total_cmp);
    Some(widths[widths.len() / 2])
}

/// Blur σ (px) of a whole frame, for frames where nothing could be detected: the contrast between
/// the 2nd and 98th intensity percentiles over the 99.7th percentile of the gradient magnitude,
/// `σ = C / (|∇I|max · √(2π))` for a Gaussian-blurred step of contrast `C`. Coarse (noise raises
/// the gradient, small features lower the contrast), but it tells a defocused camera from a sharp
/// one whose rig is not in view. `None` for a featureless frame.
pub fn frame_blur_px(img: &GrayImage) -> Option<f64> {
    let (w, h) = img.dimensions();
    if w < 3 || h < 3 {
        return None;
    }
    let raw = img.as_raw();
    let mut hist = [0usize; 256];
    for &v in raw {
        hist[usize::from(v)] += 1;
    }
    let pct = |p: f64| -> f64 {
        let target = (p * raw.len() as f64) as usize;
        let mut acc = 0;
        for (v, n) in hist.iter().enumerate() {
            acc += n;
            if acc > target {
                return v as f64;
            }
        }
        255.0
    };
    let contrast = pct(0.98) - pct(0.02);
    if contrast < 20.0 {
        return None;
    }
    // Gradient magnitudes in half-level bins (at most 255·√2/2... < 181 levels per pixel).
    let mut ghist = vec![0usize; 512];
    let (wu, hu) = (w as usize, h as usize);
    let mut n = 0usize;
    for y in 1..hu - 1 {
        for x in 1..wu - 1 {
            let i = y * wu + x;
            let gx = (f64::from(raw[i + 1]) - f64::from(raw[i - 1])) / 2.0;
            let gy = (f64::from(raw[i + wu]) - f64::from(raw[i - wu])) / 2.0;
            let g = (gx * gx + gy * gy).sqrt();
            ghist[((g * 2.0) as usize).min(511)] += 1;
            n += 1;
        }
    }
    let target = (0.997 * n as f64) as usize;
    let mut acc = 0;
    let mut g = 0.0;
    for (b, k) in ghist.iter().enumerate() {
        acc += k;
        if acc > target {
            g = (b as f64 + 0.5) / 2.0;
            break;
        }
    }
    (g > 0.0).then(|| contrast / (g * (2.0 * std::f64::consts::PI).sqrt()))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::detect::label::LabelledCorner;
    use nalgebra::Vector3;

    fn board(blur: f32) -> (GrayImage, Vec<FaceDetection>) {
        let sq = 40.0;
        let mut img = GrayImage::from_fn(400, 400, |x, y| {
            let (i, j) = (
                ((x as f64 + 0.5) / sq) as i32,
                ((y as f64 + 0.5) / sq) as i32,
            );
            image::Luma([if (i + j) % 2 == 0 { 30 } else { 220 }])
        });
        if blur > 0.0 {
            img = image::imageops::blur(&img, blur);
        }
        let mut corners = Vec::new();
        for r in 0..8 {
            for c in 0..8 {
                corners.push(LabelledCorner {
                    row: r,
                    col: c,
                    xyz: Vector3::zeros(),
                    uv: Vector2::new(sq * (c + 1) as f64 - 0.5, sq * (r + 1) as f64 - 0.5),
                    sigma_px: 0.01,
                    cov: nalgebra::Matrix2::from_diagonal_element(1e-4),
                    edge_px: 1.0,
                });
            }
        }
        (
            img,
            vec![FaceDetection {
                face: 0,
                corners,
                colour_contrast: 190.0,
                ambiguous_pose: None,
                identity: None,
            }],
        )
    }

    #[test]
    fn blur_estimate_follows_the_blur() {
        let sharp = blur_px(&board(0.0).0, &board(0.0).1).unwrap();
        let (img2, f2) = board(2.0);
        let b2 = blur_px(&img2, &f2).unwrap();
        let (img4, f4) = board(4.0);
        let b4 = blur_px(&img4, &f4).unwrap();
        assert!(sharp < 0.6, "sharp {sharp}");
        assert!((b2 - 2.0).abs() < 0.4, "σ 2 → {b2}");
        assert!((b4 - 4.0).abs() < 0.6, "σ 4 → {b4}");
    }

    #[test]
    fn frame_blur_tells_defocus_from_sharp() {
        let sharp = frame_blur_px(&board(0.5).0).unwrap();
        let b4 = frame_blur_px(&board(4.0).0).unwrap();
        assert!(sharp < 1.5, "sharp {sharp}");
        assert!(b4 > 3.0 && b4 < 6.0, "σ 4 → {b4}");
    }

    #[test]
    fn motion_sees_a_shift_not_noise() {
        let (a, _) = board(1.0);
        let shifted = GrayImage::from_fn(400, 400, |x, y| *a.get_pixel((x + 6).min(399), y));
        let noisy = GrayImage::from_fn(400, 400, |x, y| {
            let v = a.get_pixel(x, y).0[0] as i32 + if (x * 7 + y * 13) % 3 == 0 { 5 } else { -4 };
            image::Luma([v.clamp(0, 255) as u8])
        });
        assert!(motion_fraction(&a, &shifted) > 0.1);
        assert!(motion_fraction(&a, &noisy) < 1e-9);
    }
}
