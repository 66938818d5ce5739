//! X-corner front end: candidate checkerboard corners with their two edge directions, fast.
//!
//! ## Method
//! 1. The frame is averaged 2×2 to half resolution and smoothed with the binomial `[1 2 1]/4` kernel
//!    in each direction (together about σ ≈ 1.5 full-resolution pixels).
//! 2. At every half-resolution pixel the Hessian `H` of the smoothed image gives the saddle response
//!    `R = I_xy² − I_xx·I_yy = −det H`. At an X-junction, where the image is locally
//!    `I ≈ k·d₁·d₂` (dᵢ the distances to the two edge lines), `R = k²·sin²(angle between the lines)`;
//!    along a straight edge `H` has rank one and `R = 0`; on a blob `R < 0`. So `R` peaks at corners and
//!    nowhere else, at any rotation and (up to the sin² factor) any foreshortening.
//! 3. Local maxima of `R` above [`RESPONSE_THRESHOLD`] in a 5×5 neighbourhood are kept if the image has
//!    a saddle point next to them: one Newton step `δ = −H⁻¹∇I` from the peak (or a second one from
//!    where the first leads) must stay within [`MAX_SADDLE_OFFSET`]. This keeps X-junctions (point-symmetric: zero gradient at the centre) and
//!    drops L-junctions, the corners of the outer squares against the board's margin, which have a
//!    strong `R` too. The corner is placed at the saddle point. Its two edge directions come from the
//!    ring of radius [`RING_RADII`] around it: four crossings of the mid level, opposite ones π apart
//!    (which rejects most candidates that noise or clutter produce).
//!
//! 4. Before any peak is looked at, the frame must look like it could hold a checkerboard: the
//!    response exceeds the floor only near corners — under 1 % of the hard synthetic renders, at
//!    most 15 % of the 140 real photos and fixtures (the OpenCV 640×480 set, whose board fills the
//!    frame) — while in noise or fine texture it does so nearly everywhere (43 % of a frame of
//!    uniform noise, 30 % of noise blurred by σ 1.5 px). Above [`MAX_BUSY_FRACTION`] no
//!    corner is looked for: the count is one vectorised pass over the response, so such a frame
//!    costs little more than the filter, where the peaks, ring tests and grid assembly of its
//!    thousands of false candidates cost four times a cube frame (`cargo bench --bench detect`).
//!
//! Positions are only starting points (a few tenths of a pixel): [`super::complete`] fits every corner
//! of an assembled grid at full resolution. What the front end must be is fast and complete.
//!
//! ## Why not `chess-corners`
//! The `chess-corners` crate (MIT; ChESS response, two-level pyramid, saddle-point refinement) was the
//! first front end and met the recall figures, but on stable Rust (its SIMD path needs nightly) it
//! costs 11 ms on a blank 1280×960 frame and 16–20 ms on a cube frame, against a budget of 3 ms to
//! reject a frame with no target and 10 ms for the whole detection of a three-face frame. This front end
//! does one pass of a few arithmetic operations per half-resolution pixel, in loops the compiler
//! vectorises: see `cargo bench --bench detect` for its time (the "front end" stage).
//!
//! Pixel convention: integer coordinates are pixel centres. Half-resolution pixel `(i, j)` averages
//! full-resolution pixels `2i, 2i+1` × `2j, 2j+1`, so its centre is at `(2i + 0.5, 2j + 0.5)`.

use image::GrayImage;
use nalgebra::Vector2;

use super::{DetectError, MIN_SIDE, XCorner};

/// Saddle response floor, in (grey levels per half-resolution pixel²)². Measured on the hard synthetic
/// set (contrast 46 grey levels, blur σ 1.5 px, noise σ 5): a floor of 30 found 22 of the 38 faces
/// seen at < 75°, 10 finds 32, 5 no more than 10; false candidates are removed by the saddle and ring
/// tests and by grid assembly.
pub const RESPONSE_THRESHOLD: f32 = 10.0;
/// Non-maximum suppression radius (half-resolution pixels).
pub const NMS_RADIUS: usize = 2;
/// Largest distance (half-resolution pixels) from a response peak, or from the pixel one Newton step
/// leads to, to the image's saddle point for the peak to count as an X-corner (see `corner_at`).
pub const MAX_SADDLE_OFFSET: f64 = 1.0;
/// Radii (full-resolution pixels) of the rings that give a corner's edge directions, tried in turn:
/// the largest is the least biased by blur (see `ring_axes`), the smaller ones fit between the
/// corners of squares foreshortened to a few pixels. On the hard synthetic set (blur σ 1.5 px, faces
/// up to 90° from frontal), rings of 6, 4, 3 px gave 360 of the 2489 corners found axes more than
/// 0.2 rad off (the grid's tolerance) and 8, 6, 4, 3 px give 82 of 2522; 10 px first gains nothing.
pub const RING_RADII: [f64; 4] = [8.0, 6.0, 4.0, 3.0];
/// Samples on that ring.
pub const RING_SAMPLES: usize = 32;
/// Largest departure from π between opposite crossings of the ring (radians).
pub const MAX_RING_ASYMMETRY: f64 = 0.35;
/// Peaks are looked for this far (half-resolution pixels) inside the frame, so that the
/// neighbourhoods of `is_peak` and `corner_at` stay inside.
const BORDER: usize = NMS_RADIUS + 1;
/// Most candidates returned (strongest first): bounds the time spent on cluttered or noisy frames.
pub const MAX_CANDIDATES: usize = 4000;
/// Largest fraction of the half-resolution frame whose saddle response may exceed the floor for
/// corners to be looked for (step 4 of the module doc).
pub const MAX_BUSY_FRACTION: f32 = 0.25;

/// The X-corner front end, reusable across frames (it keeps its buffers).
#[derive(Debug, Default)]
pub struct CornerFinder {
    threshold: f32,
    /// Fraction of the last frame's half-resolution pixels whose response exceeded the floor.
    busy: f32,
    /// One row of the 2×2-summed frame.
    half: Vec<u16>,
    /// Three rows of it smoothed horizontally (a ring, see `filter`).
    rows: Vec<u16>,
    /// The smoothed half-resolution frame.
    smooth: Vec<f32>,
    /// Its saddle response.
    resp: Vec<f32>,
    /// The rectangle of a second look, enlarged 2× (see [`CornerFinder::find_full_res`]).
    zoomed: Vec<u8>,
    /// Whether [`super::grid::find_and_assemble`] takes the full-resolution second look where the
    /// first pass left unlinked corners (on unless [`CornerFinder::set_second_look`] says otherwise).
    second_look: bool,
}

impl CornerFinder {
    pub fn new() -> Result<CornerFinder, DetectError> {
        Ok(Self::with_threshold(RESPONSE_THRESHOLD))
    }

    /// A front end with another response floor (see [`RESPONSE_THRESHOLD`] for its unit).
    pub fn with_threshold(threshold: f32) -> CornerFinder {
        CornerFinder {
            threshold,
            second_look: true,
            ..CornerFinder::default()
        }
    }

    /// Turn the full-resolution second look at grazing faces on or off (on by default; the station's
    /// `detect.second_look`).
    pub fn set_second_look(&mut self, on: bool) {
        self.second_look = on;
    }

    /// Whether the full-resolution second look is taken (see [`CornerFinder::set_second_look`]).
    pub fn second_look(&self) -> bool {
        self.second_look
    }

    /// All X-corners of a frame, strongest first.
    pub fn find(&mut self, img: &GrayImage) -> Result<Vec<XCorner>, DetectError> {
        let (width, height) = img.dimensions();
        if width < MIN_SIDE || height < MIN_SIDE {
            return Err(DetectError::TooSmall { width, height });
        }
        let (w, h) = ((width / 2) as usize, (height / 2) as usize);
        self.filter(img, w, h);
        let above: u32 = (self.resp.iter())
            .map(|&v| u32::from(v > self.threshold))
            .sum();
        self.busy = above as f32 / (w * h) as f32;
        tracing::trace!(
            busy = self.busy,
            "share of the frame above the response floor"
        );
        if self.busy > MAX_BUSY_FRACTION {
            return Ok(Vec::new());
        }
        Ok(self.sorted_peaks(img, w, h))
    }

    /// The peaks of the response last filtered (frame `img`, `w`×`h` at half resolution), strongest
    /// first, at most [`MAX_CANDIDATES`].
    fn sorted_peaks(&self, img: &GrayImage, w: usize, h: usize) -> Vec<XCorner> {
        let mut out = self.peaks(img, w, h);
        // Strongest first; two peaks whose Newton steps lead to the same pixel give the same corner.
        out.sort_by(|a, b| {
            b.response
                .total_cmp(&a.response)
                .then(a.uv.x.total_cmp(&b.uv.x))
                .then(a.uv.y.total_cmp(&b.uv.y))
        });
        out.dedup_by(|a, b| a == b);
        out.truncate(MAX_CANDIDATES);
        out
    }

    /// The fraction of the last frame's half-resolution pixels whose saddle response exceeded the
    /// floor; above [`MAX_BUSY_FRACTION`] [`find`](CornerFinder::find) looked for no corner.
    pub fn busy_fraction(&self) -> f32 {
        self.busy
    }

    /// X-corners of the rectangle `[x0, x1) × [y0, y1)` of `img` found at full resolution, with their
    /// positions in the frame: the method of [`CornerFinder::find`] applied to the rectangle
    /// enlarged 2× by pixel replication, whose 2×2 average is the frame itself, and whose rings
    /// ([`RING_RADII`]) are half as wide in the frame. A face seen at 75°+ from frontal, or a small one
    /// at an image corner under strong barrel distortion, has squares 3–5 px across in one direction:
    /// the half-resolution pass smooths them away, this pass sees them (at about 4× the cost per
    /// frame pixel, so it is only run where [`super::grid`] asks for it). Responses are scaled to
    /// the half-resolution pass's unit (a second difference over half-resolution pixels is 4× one
    /// over full-resolution pixels, the response its square), so that both rank together as seeds.
    pub fn find_full_res(
        &mut self,
        img: &GrayImage,
        [x0, y0, x1, y1]: [u32; 4],
    ) -> Result<Vec<XCorner>, DetectError> {
        let (x1, y1) = (x1.min(img.width()), y1.min(img.height()));
        let (w, h) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        if 2 * w < MIN_SIDE || 2 * h < MIN_SIDE {
            return Ok(Vec::new());
        }
        let mut zoomed = std::mem::take(&mut self.zoomed);
        zoomed.clear();
        let src = img.as_raw();
        let stride = img.width() as usize;
        for y in y0..y1 {
            let row = &src[y as usize * stride..][x0 as usize..x1 as usize];
            let start = zoomed.len();
            zoomed.extend(row.iter().flat_map(|&v| [v, v]));
            zoomed.extend_from_within(start..);
        }
        let Some(up) = GrayImage::from_raw(2 * w, 2 * h, zoomed) else {
            return Ok(Vec::new());
        };
        // No busy-frame test here (step 4 of the module doc): the region holds a face's tiny
        // squares, whose response can exceed the floor over much of it, and the frame's busy
        // fraction, measured by the first pass, stays what `busy_fraction` reports.
        let (hw, hh) = (w as usize, h as usize);
        self.filter(&up, hw, hh);
        let found = self.sorted_peaks(&up, hw, hh);
        self.zoomed = up.into_raw();
        let origin = Vector2::new(f64::from(x0), f64::from(y0));
        Ok(found
            .into_iter()
            .map(|c| XCorner {
                uv: origin + (c.uv - Vector2::new(0.5, 0.5)) / 2.0,
                response: 16.0 * c.response,
                ..c
            })
            .collect())
    }

    /// The smoothed half-resolution frame into `smooth` and its saddle response into `resp` (zero
    /// on the one-pixel border), in one pass over the rows: each half-resolution row is averaged 2×2
    /// and smoothed horizontally into a ring of three rows (`rows`, which stays in the cache), smoothed
    /// vertically from there, and the response of the row above it computed at once. Only `smooth`
    /// and `resp` are whole frames, and nothing is cleared first (every element is written): on a
    /// blank 1280×960 frame the separate passes, with their seven cleared whole-frame buffers, wrote
    /// ~17 MB per frame and were most of the 1.9 ms the front end took.
    fn filter(&mut self, img: &GrayImage, w: usize, h: usize) {
        let src = img.as_raw();
        let stride = img.width() as usize;
        for buf in [&mut self.smooth, &mut self.resp] {
            buf.resize(w * h, 0.0);
        }
        self.half.resize(w, 0);
        self.rows.resize(3 * w, 0);
        for k in 0..h {
            // 2×2 sum of full-resolution rows 2k, 2k + 1 (4 × the mean). Integer sums of byte pairs
            // read as u16, which the compiler vectorises; the smoothing below is exact in integers
            // too (at most 16 × 4 × 255), so `smooth` holds the same values as a float pipeline.
            let a = &src[2 * k * stride..2 * k * stride + 2 * w];
            let b = &src[(2 * k + 1) * stride..(2 * k + 1) * stride + 2 * w];
            let half = &mut self.half[..w];
            let (pa, _) = a.as_chunks::<2>();
            let (pb, _) = b.as_chunks::<2>();
            for ((out, &pa), &pb) in half.iter_mut().zip(pa).zip(pb) {
                let (va, vb) = (u16::from_le_bytes(pa), u16::from_le_bytes(pb));
                *out = (va & 0xff) + (va >> 8) + (vb & 0xff) + (vb >> 8);
            }
            // Horizontal [1 2 1] (edges clamped), into ring slot k mod 3: 16 × the smoothed mean.
            let dst = &mut self.rows[(k % 3) * w..][..w];
            dst[0] = 3 * half[0] + half[1];
            dst[w - 1] = 3 * half[w - 1] + half[w - 2];
            for (d, s) in dst[1..w - 1].iter_mut().zip(half.windows(3)) {
                *d = s[0] + 2 * s[1] + s[2];
            }
            // Vertical [1 2 1]/4 of row k − 1 (rows k − 2 and k around it, clamped at the top).
            if k >= 1 {
                self.vertical(k - 1, k.saturating_sub(2), k, w);
            }
            if k >= 3 {
                self.response(k - 2, w);
            }
        }
        // The last row (clamped at the bottom) and its neighbour's response.
        self.vertical(h - 1, h.saturating_sub(2), h - 1, w);
        self.response(h - 2, w);
        // The border of the response: rows 0 and h − 1 (columns are set by `response`).
        self.resp[..w].fill(0.0);
        self.resp[(h - 1) * w..].fill(0.0);
    }

    /// Row `y` of `smooth` from the ring's rows `up`, `y` and `down` (half-resolution row indices):
    /// their vertical [1 2 1], scaled from 64 × the mean to grey levels.
    fn vertical(&mut self, y: usize, up: usize, down: usize, w: usize) {
        let up = &self.rows[(up % 3) * w..][..w];
        let mid = &self.rows[(y % 3) * w..][..w];
        let down = &self.rows[(down % 3) * w..][..w];
        let dst = &mut self.smooth[y * w..][..w];
        for (((d, &a), &b), &c) in dst.iter_mut().zip(up).zip(mid).zip(down) {
            *d = f32::from(a + 2 * b + c) * (1.0 / 64.0);
        }
    }

    /// Row `y` (0 < y < h − 1) of the saddle response `R = I_xy² − I_xx·I_yy` of `smooth`, zero in
    /// its first and last columns.
    fn response(&mut self, y: usize, w: usize) {
        let s = &self.smooth;
        let up = &s[(y - 1) * w..][..w];
        let mid = &s[y * w..][..w];
        let down = &s[(y + 1) * w..][..w];
        let resp = &mut self.resp[y * w..][..w];
        resp[0] = 0.0;
        resp[w - 1] = 0.0;
        for (x, r) in resp[1..w - 1].iter_mut().enumerate() {
            let (xx, yy, xy) = second_differences(up, mid, down, x + 1);
            *r = xy * xy - xx * yy;
        }
    }

    /// Local maxima of the response above the threshold, as corners at full resolution.
    fn peaks(&self, img: &GrayImage, w: usize, h: usize) -> Vec<XCorner> {
        let mut out = Vec::new();
        if w <= 2 * BORDER || h <= 2 * BORDER {
            return out;
        }
        let resp = &self.resp;
        let thr = self.threshold;
        // Blocks of 16 with nothing above the floor (most of a frame) are passed over with one
        // branch: the count is a SIMD compare and add.
        const BLOCK: usize = 16;
        for y in BORDER..h - BORDER {
            let row = &resp[y * w..][..w - BORDER];
            let mut x0 = BORDER;
            while x0 < row.len() {
                let block = &row[x0..(x0 + BLOCK).min(row.len())];
                if block.iter().map(|&v| u32::from(v > thr)).sum::<u32>() > 0 {
                    for (x, &v) in (x0..).zip(block) {
                        if v > thr && self.is_peak(x, y, w, v) {
                            out.extend(self.corner_at(img, x, y, w));
                        }
                    }
                }
                x0 += BLOCK;
            }
        }
        out
    }

    /// Whether `(x, y)` with response `v` is the maximum of its neighbourhood (ties go to the first
    /// pixel in raster order, so a plateau gives one corner).
    fn is_peak(&self, x: usize, y: usize, w: usize, v: f32) -> bool {
        let r = NMS_RADIUS;
        for yy in y - r..=y + r {
            for xx in x - r..=x + r {
                let u = self.resp[yy * w + xx];
                let before = (yy, xx) < (y, x);
                if u > v || (before && u == v) {
                    return false;
                }
            }
        }
        true
    }

    /// The corner at peak `(x, y)`: the saddle point of the smoothed image by Newton steps
    /// `δ = −H⁻¹∇I` (see `newton`), or `None` when there is no saddle point near the peak. An
    /// X-junction is point-symmetric, so its gradient vanishes where `R` peaks; an L-junction (a
    /// square's corner against the board margin) also has a strong `R` but a gradient of half its
    /// contrast there, which puts the "saddle point" ~2σ away, and no saddle point is there.
    ///
    /// When the first step leaves [`MAX_SADDLE_OFFSET`], a second one is taken from the pixel it
    /// leads to, and the corner is kept if that one converges (within [`MAX_SADDLE_OFFSET`]): on faces
    /// seen at 65°+ the squares are a few pixels wide in one direction, the responses of neighbouring
    /// corners overlap, and their peaks sit 1–1.5 half-resolution pixels from the saddle point. On the
    /// hard synthetic set this finds 2913 of 3798 visible corners instead of 2522 (3315 candidates
    /// instead of 2697). Two peaks may lead to the same pixel: the copy is dropped by `find`.
    fn corner_at(&self, img: &GrayImage, x: usize, y: usize, w: usize) -> Option<XCorner> {
        let (mut dx, mut dy) = self.newton(x, y, w)?;
        let (mut x, mut y) = (x, y);
        if dx.hypot(dy) > MAX_SADDLE_OFFSET {
            let (nx, ny) = ((x as f64 + dx).round(), (y as f64 + dy).round());
            let h = self.resp.len() / w;
            // The 3×3 sums of `newton` read one more pixel around: stay inside the border.
            if nx < 2.0 || ny < 2.0 || nx > (w - 3) as f64 || ny > (h - 3) as f64 {
                return None;
            }
            (x, y) = (nx as usize, ny as usize);
            (dx, dy) = self.newton(x, y, w)?;
            // The saddle point must be a corner in its own right, not a weak structure that the
            // first step reached.
            if dx.hypot(dy) > MAX_SADDLE_OFFSET || self.resp[y * w + x] <= self.threshold {
                return None;
            }
        }
        let uv = Vector2::new(2.0 * (x as f64 + dx) + 0.5, 2.0 * (y as f64 + dy) + 0.5);
        let (axes, dark) = RING_RADII
            .iter()
            .find_map(|&radius| Self::ring_axes(img, uv, radius))?;
        Some(XCorner {
            uv,
            axes,
            dark,
            response: f64::from(self.resp[y * w + x]),
        })
    }

    /// One Newton step `δ = −H⁻¹∇I` towards the saddle point of the smoothed image from half-resolution
    /// pixel `(x, y)` (gradient and Hessian summed over 3×3), or `None` where `H` is not a saddle's.
    fn newton(&self, x: usize, y: usize, w: usize) -> Option<(f64, f64)> {
        let (mut hxx, mut hyy, mut hxy, mut gx, mut gy) = (0.0_f64, 0.0_f64, 0.0_f64, 0.0, 0.0);
        let s = &self.smooth;
        for yy in y - 1..=y + 1 {
            for xx in x - 1..=x + 1 {
                let i = yy * w + xx;
                // The second differences `response` took (the 3×3 block is inside its border).
                let (ixx, iyy, ixy) =
                    second_differences(&s[i - w - xx..], &s[i - xx..], &s[i + w - xx..], xx);
                hxx += f64::from(ixx);
                hyy += f64::from(iyy);
                hxy += f64::from(ixy);
                gx += 0.5 * f64::from(s[i + 1] - s[i - 1]);
                gy += 0.5 * f64::from(s[i + w] - s[i - w]);
            }
        }
        let det = hxx * hyy - hxy * hxy;
        if det >= 0.0 {
            return None;
        }
        // δ = −H⁻¹ g with H⁻¹ = [[h_yy, −h_xy], [−h_xy, h_xx]] / det.
        Some((-(hyy * gx - hxy * gy) / det, -(-hxy * gx + hxx * gy) / det))
    }

    /// The two edge directions of the X-junction at `c` (full-resolution pixels) from the ring of
    /// radius [`RING_RADII`] around it in the frame itself, and the direction of the bisector of its
    /// dark quadrants ([`XCorner::dark`]), or `None` if the ring is not an X-junction's or leaves the
    /// frame.
    ///
    /// Around an X-junction the ring crosses the mid level `(min + max)/2` exactly four times, at the
    /// two lines, and point symmetry puts opposite crossings π apart; each line's direction is the
    /// mean of its two crossings. The ring is read at full resolution, unsmoothed, and several blur
    /// widths out: near its centre a blurred X-junction's mid-level contour bends towards a right
    /// angle, whatever the angle between the lines. (For the same reason the Hessian cannot give these
    /// directions: at the centre it is traceless, so its zero directions are always 90° apart.) Noise
    /// and clutter rarely give four point-symmetric crossings.
    fn ring_axes(img: &GrayImage, c: Vector2<f64>, radius: f64) -> Option<([f64; 2], f64)> {
        let (w, h) = (f64::from(img.width()), f64::from(img.height()));
        if c.x < radius + 1.0
            || c.y < radius + 1.0
            || c.x > w - radius - 2.0
            || c.y > h - radius - 2.0
        {
            return None;
        }
        let mut ring = [0.0_f64; RING_SAMPLES];
        for (v, u) in ring.iter_mut().zip(unit_ring()) {
            *v = bilinear(img, c + u * radius);
        }
        let (lo, hi) = ring
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let mid = 0.5 * (lo + hi);
        let mut crossings = [0.0_f64; 4];
        let mut n = 0;
        for k in 0..RING_SAMPLES {
            let (a, b) = (ring[k] - mid, ring[(k + 1) % RING_SAMPLES] - mid);
            if (a < 0.0) != (b < 0.0) {
                if n == 4 {
                    return None;
                }
                let t = a / (a - b);
                crossings[n] = std::f64::consts::TAU * (k as f64 + t) / RING_SAMPLES as f64;
                n += 1;
            }
        }
        if n != 4 {
            return None;
        }
        let pi = std::f64::consts::PI;
        let mut axes = [0.0; 2];
        for (i, axis) in axes.iter_mut().enumerate() {
            let (a, b) = (crossings[i], crossings[i + 2] - pi);
            // Opposite crossings must be (nearly) π apart.
            if (a - b).abs() > MAX_RING_ASYMMETRY {
                return None;
            }
            *axis = (0.5 * (a + b)).rem_euclid(pi);
        }
        // Polarity: the mean level of the quadrants between crossings 0–1 and 2–3 against the other
        // two (crossings are in increasing angle, so these are opposite quadrants).
        let (mut first, mut second) = ((0.0, 0.0_f64), (0.0, 0.0_f64));
        for (k, v) in ring.iter().enumerate() {
            let theta = std::f64::consts::TAU * k as f64 / RING_SAMPLES as f64;
            let in_01 = theta > crossings[0] && theta < crossings[1];
            let in_23 = theta > crossings[2] && theta < crossings[3];
            let acc = if in_01 || in_23 {
                &mut first
            } else {
                &mut second
            };
            acc.0 += v;
            acc.1 += 1.0;
        }
        let dark = if first.0 * second.1 < second.0 * first.1 {
            0.5 * (crossings[0] + crossings[1])
        } else {
            0.5 * (crossings[1] + crossings[2])
        };
        Some((axes, dark.rem_euclid(pi)))
    }
}

/// The second differences `(I_xx, I_yy, I_xy)` of the smoothed frame at column `x` of row `mid`,
/// with `up` and `down` the rows above and below (`0 < x < w − 1`).
#[inline(always)]
fn second_differences(up: &[f32], mid: &[f32], down: &[f32], x: usize) -> (f32, f32, f32) {
    let xx = mid[x - 1] - 2.0 * mid[x] + mid[x + 1];
    let yy = up[x] - 2.0 * mid[x] + down[x];
    let xy = 0.25 * (down[x + 1] - down[x - 1] - up[x + 1] + up[x - 1]);
    (xx, yy, xy)
}

/// The [`RING_SAMPLES`] unit vectors of the ring, computed once.
fn unit_ring() -> &'static [Vector2<f64>; RING_SAMPLES] {
    static RING: std::sync::OnceLock<[Vector2<f64>; RING_SAMPLES]> = std::sync::OnceLock::new();
    RING.get_or_init(|| {
        std::array::from_fn(|k| {
            let theta = std::f64::consts::TAU * k as f64 / RING_SAMPLES as f64;
            Vector2::new(theta.cos(), theta.sin())
        })
    })
}

/// The frame at a sub-pixel point, bilinear (the point must be ≥ 1 px inside).
///
/// The point's coordinates are positive, so `⌊·⌋` is a truncating conversion (through `i32`, which
/// holds any frame's coordinates): `f64::floor` is a library call on the x86-64 baseline (no
/// SSE4.1), and on a frame of pure noise, where every response peak gets its four rings tested, those
/// calls were a third of the detector's instructions.
fn bilinear(img: &GrayImage, p: Vector2<f64>) -> f64 {
    let (ix, iy) = (p.x as i32, p.y as i32);
    let (tx, ty) = (p.x - f64::from(ix), p.y - f64::from(iy));
    let w = img.width() as usize;
    let i = iy as usize * w + ix as usize;
    let raw = img.as_raw();
    let at = |k: usize| f64::from(raw[k]);
    let top = at(i) * (1.0 - tx) + at(i + 1) * tx;
    let bottom = at(i + w) * (1.0 - tx) + at(i + w + 1) * tx;
    top * (1.0 - ty) + bottom * ty
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn line_diff(a: f64, b: f64) -> f64 {
        let d = (a - b).rem_euclid(std::f64::consts::PI);
        d.min(std::f64::consts::PI - d)
    }

    /// A blurred checkerboard rotated by `angle`, squares of `size` px, corner lattice through
    /// `origin`.
    fn board(w: u32, h: u32, size: f64, angle: f64, origin: Vector2<f64>) -> GrayImage {
        let (s, c) = angle.sin_cos();
        let img = GrayImage::from_fn(w, h, |x, y| {
            let mut acc = 0.0;
            for i in 0..4 {
                for j in 0..4 {
                    let px = f64::from(x) - 0.5 + (f64::from(i) + 0.5) / 4.0 - origin.x;
                    let py = f64::from(y) - 0.5 + (f64::from(j) + 0.5) / 4.0 - origin.y;
                    let bu = (c * px + s * py) / size;
                    let bv = (-s * px + c * py) / size;
                    let dark = (bu.floor() as i64 + bv.floor() as i64).rem_euclid(2) == 0;
                    acc += if dark { 40.0 } else { 210.0 };
                }
            }
            image::Luma([(acc / 16.0) as u8])
        });
        image::imageops::blur(&img, 1.0)
    }

    /// Inner corner `(i, j)` of the board drawn by [`board`].
    fn lattice_point(origin: Vector2<f64>, size: f64, angle: f64, i: i32, j: i32) -> Vector2<f64> {
        let (s, c) = angle.sin_cos();
        origin
            + Vector2::new(c, s) * (f64::from(i) * size)
            + Vector2::new(-s, c) * (f64::from(j) * size)
    }

    #[test]
    fn finds_every_corner_of_a_rotated_board_with_its_axes() {
        let origin = Vector2::new(100.3, 90.7);
        let (size, angle) = (17.0, 0.4_f64);
        let img = board(240, 200, size, angle, origin);
        let corners = CornerFinder::new().unwrap().find(&img).unwrap();
        let (s, c) = angle.sin_cos();
        let (mut found, mut inside) = (0, 0);
        for i in -4..=4 {
            for j in -4..=4 {
                let p = lattice_point(origin, size, angle, i, j);
                // Half a square from the frame's edge: the four squares around it are in the frame.
                if p.x < size / 2.0
                    || p.y < size / 2.0
                    || p.x > 240.0 - size / 2.0
                    || p.y > 200.0 - size / 2.0
                {
                    continue;
                }
                inside += 1;
                let Some(k) = corners.iter().find(|k| (k.uv - p).norm() < 1.0) else {
                    continue;
                };
                found += 1;
                assert!(
                    k.axes.iter().any(|&a| line_diff(a, angle) < 0.1)
                        && k.axes
                            .iter()
                            .any(|&a| line_diff(a, angle + std::f64::consts::FRAC_PI_2) < 0.1),
                    "{k:?}"
                );
            }
        }
        assert!(inside >= 70, "{inside}");
        assert_eq!(found, inside, "{} candidates", corners.len());
        // Nothing else: corners are only at lattice points (the board fills the frame).
        let stray = corners
            .iter()
            .filter(|k| {
                let d = k.uv - origin;
                let (bu, bv) = ((c * d.x + s * d.y) / size, (-s * d.x + c * d.y) / size);
                (bu - bu.round()).abs() * size > 1.0 || (bv - bv.round()).abs() * size > 1.0
            })
            .count();
        assert_eq!(stray, 0);
    }

    /// The full-resolution look sees squares the half-resolution pass smooths away, and places the
    /// corners in the frame's coordinates.
    #[test]
    fn the_full_resolution_look_finds_small_squares_in_frame_coordinates() {
        let origin = Vector2::new(150.3, 120.6);
        let (size, angle) = (5.0, 0.3_f64);
        let img = board(300, 240, size, angle, origin);
        let mut finder = CornerFinder::new().unwrap();
        let rect = [100, 70, 200, 170];
        let half = finder.find(&img).unwrap();
        let full = finder.find_full_res(&img, rect).unwrap();
        let (mut inside, mut by_half, mut by_full) = (0, 0, 0);
        for i in -12..=12 {
            for j in -12..=12 {
                let p = lattice_point(origin, size, angle, i, j);
                // Corners well inside the rectangle (its rings must fit).
                if p.x < 110.0 || p.y < 80.0 || p.x > 190.0 || p.y > 160.0 {
                    continue;
                }
                inside += 1;
                by_half += usize::from(half.iter().any(|k| (k.uv - p).norm() < 1.0));
                by_full += usize::from(full.iter().any(|k| (k.uv - p).norm() < 0.5));
            }
        }
        assert!(inside >= 150, "{inside}");
        assert!(
            by_half * 4 < inside,
            "half resolution: {by_half} of {inside}"
        );
        assert!(
            by_full * 10 >= 9 * inside,
            "full resolution: {by_full} of {inside}"
        );
        // Only in the rectangle; an empty or tiny rectangle gives nothing.
        assert!(
            full.iter()
                .all(|k| k.uv.x > 99.0 && k.uv.x < 200.0 && k.uv.y > 69.0 && k.uv.y < 170.0)
        );
        assert!(
            finder
                .find_full_res(&img, [10, 10, 20, 20])
                .unwrap()
                .is_empty()
        );
        assert!(
            finder
                .find_full_res(&img, [290, 10, 400, 100])
                .unwrap()
                .is_empty()
        );
    }

    /// Neighbours along a row or column have opposite polarity: their dark-quadrant bisectors are
    /// ~90° apart; diagonal neighbours have the same.
    #[test]
    fn polarity_alternates_along_rows_and_columns() {
        let origin = Vector2::new(100.3, 90.7);
        let (size, angle) = (17.0, 0.4_f64);
        let img = board(240, 200, size, angle, origin);
        let corners = CornerFinder::new().unwrap().find(&img).unwrap();
        let at = |i: i32, j: i32| {
            let p = lattice_point(origin, size, angle, i, j);
            corners
                .iter()
                .find(|k| (k.uv - p).norm() < 1.0)
                .map(|k| k.dark)
        };
        let mut pairs = 0;
        for i in -3..=3 {
            for j in -3..=3 {
                let Some(d) = at(i, j) else { continue };
                for (di, dj, flips) in [(1, 0, true), (0, 1, true), (1, 1, false), (1, -1, false)] {
                    if let Some(e) = at(i + di, j + dj) {
                        let diff = line_diff(d, e);
                        if flips {
                            assert!(diff > 1.2, "({i}, {j}) +({di}, {dj}): {diff}");
                        } else {
                            assert!(diff < 0.35, "({i}, {j}) +({di}, {dj}): {diff}");
                        }
                        pairs += 1;
                    }
                }
            }
        }
        assert!(pairs > 100, "{pairs}");
    }

    #[test]
    fn blank_frame_has_no_corners() {
        let img = GrayImage::from_pixel(320, 240, image::Luma([128]));
        assert!(CornerFinder::new().unwrap().find(&img).unwrap().is_empty());
    }

    #[test]
    fn odd_sizes_and_the_minimum_size_work() {
        for (w, h) in [(MIN_SIDE, MIN_SIDE), (33, 47), (101, 32)] {
            let img = GrayImage::from_pixel(w, h, image::Luma([10]));
            assert!(CornerFinder::new().unwrap().find(&img).is_ok());
        }
        let tiny = GrayImage::new(MIN_SIDE - 1, 100);
        assert!(matches!(
            CornerFinder::new().unwrap().find(&tiny),
            Err(DetectError::TooSmall { .. })
        ));
    }
}
