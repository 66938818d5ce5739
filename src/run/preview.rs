//! Previews: each view's frame reduced to thumbnail size by the station while it holds the decoded
//! frame, handed to front ends with the run's result ([`super::RunResult::previews`]) so that the
//! report's thumbnails need not decode the session's frames again (issue 36: re-decoding the photos
//! was the largest single cost of a photo run's report).
//!
//! The reduction is [`downscale`], a hand-written integer box filter: output pixel `i` covers input
//! pixels `k·i .. k·i + k`, so pixel centres map by `u' = (u + ½)/k − ½`, the mapping the report's
//! overlay moves the corners by. Written here rather than calling `image::imageops::thumbnail` (any
//! ratio) for that exact mapping and for speed outside release builds: per 1280×960 frame, measured
//! by `cargo bench --bench report`, image's version takes 31 ms in the test profile (4.3 ms in
//! release) against 3–5 ms for this loop with the overlay and legend.
//!
//! A preview is the same image the report would compute from the session's copy of the frame (the
//! session decodes through the same function, bit for bit), so a report drawn from previews and one
//! drawn later from the run directory are identical (`tests/photo_run.rs`).

use image::GrayImage;

use crate::detect::FrameDetection;

/// Target width of a thumbnail (px); the frame is reduced by the nearest integer factor.
pub const THUMB_WIDTH: u32 = 400;

/// The integer reduction factor for a frame `width` px wide (nearest to `width / THUMB_WIDTH`, ≥ 1).
pub fn factor(width: u32) -> u32 {
    (f64::from(width) / f64::from(THUMB_WIDTH)).round().max(1.0) as u32
}

/// One view's frame at thumbnail size.
#[derive(Clone, PartialEq)]
pub struct FramePreview {
    /// The session frame file it was reduced from (the view record's `frame`).
    pub frame: String,
    /// The reduction factor ([`factor`] of the full frame's width).
    pub factor: u32,
    /// Width and height of the full frame.
    pub full_size: (u32, u32),
    /// The frame reduced by `factor` with [`downscale`].
    pub image: GrayImage,
    /// What the detector found in the full frame, for a view without observations (a rejected
    /// view); `None` for accepted views, whose observations say it.
    pub detection: Option<FrameDetection>,
}

impl std::fmt::Debug for FramePreview {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FramePreview")
            .field("frame", &self.frame)
            .field("factor", &self.factor)
            .field("full_size", &self.full_size)
            .field("image", &self.image.dimensions())
            .field("detection", &self.detection.is_some())
            .finish()
    }
}

impl FramePreview {
    /// The preview of the full frame `img` recorded as session file `frame`.
    pub fn of(frame: String, img: &GrayImage, detection: Option<FrameDetection>) -> FramePreview {
        let k = factor(img.width());
        FramePreview {
            frame,
            factor: k,
            full_size: img.dimensions(),
            image: downscale(img, k),
            detection,
        }
    }
}

/// Average `k × k` blocks (a box filter with an integer factor; the last partial row and column
/// are dropped); see the module docs.
pub fn downscale(img: &GrayImage, k: u32) -> GrayImage {
    let k = k.max(1);
    let (w, h) = img.dimensions();
    let (ow, oh) = ((w / k).max(1), (h / k).max(1));
    let (kw, kh) = (k.min(w) as usize, k.min(h) as usize);
    let src = img.as_raw();
    let stride = w as usize;
    let mut out = vec![0u8; ow as usize * oh as usize];
    let mut sums = vec![0u32; ow as usize];
    for oy in 0..oh as usize {
        sums.iter_mut().for_each(|s| *s = 0);
        for y in oy * kh..oy * kh + kh {
            let row = &src[y * stride..y * stride + ow as usize * kw];
            match kw {
                2 => add_blocks::<2>(&mut sums, row),
                3 => add_blocks::<3>(&mut sums, row),
                _ => {
                    for (s, block) in sums.iter_mut().zip(row.chunks_exact(kw)) {
                        *s += block.iter().map(|&p| u32::from(p)).sum::<u32>();
                    }
                }
            }
        }
        let n = (kw * kh) as u32;
        for (o, s) in out[oy * ow as usize..(oy + 1) * ow as usize]
            .iter_mut()
            .zip(&sums)
        {
            *o = ((s + n / 2) / n) as u8;
        }
    }
    GrayImage::from_raw(ow, oh, out).unwrap_or_else(|| GrayImage::new(ow, oh))
}

/// Add each block of `K` pixels of `row` to its sum: the common factors (640 and 1280 px wide frames)
/// with the block size known to the compiler, which then sums whole rows in SIMD registers (the
/// reduction was 3.5 % of a photo run's instructions, 13 px a pixel, with the size unknown).
fn add_blocks<const K: usize>(sums: &mut [u32], row: &[u8]) {
    for (s, block) in sums.iter_mut().zip(row.chunks_exact(K)) {
        *s += block.iter().map(|&p| u32::from(p)).sum::<u32>();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscale_averages_blocks() {
        let img = GrayImage::from_fn(7, 5, |x, y| image::Luma([(10 * x + y) as u8]));
        let s = downscale(&img, 2);
        assert_eq!(s.dimensions(), (3, 2));
        // Block (1, 1): x 2..4, y 2..4 → values 22, 23, 32, 33 → mean 27.5 → 28.
        assert_eq!(s.get_pixel(1, 1).0[0], 28);
        assert_eq!(s.get_pixel(0, 0).0[0], 6); // 0, 1, 10, 11 → 5.5 → 6
        assert_eq!(downscale(&img, 1), img);
    }

    #[test]
    fn factor_is_the_nearest_integer_ratio() {
        assert_eq!(factor(640), 2);
        assert_eq!(factor(1280), 3);
        assert_eq!(factor(1920), 5);
        assert_eq!(factor(200), 1);
    }
}
