//! ChArUco faces: ArUco markers found and decoded, each ChArUco corner labelled from the two markers
//! beside it and fitted by the checkerboard corners' sub-pixel refinement ([`super::refine`]).
//!
//! ## Method
//! 1. **Dark regions.** A pixel is dark when the mean of the 3 × 3 pixels around it is
//!    [`THRESHOLD_OFFSET`] grey levels below the mean of the [`BOX_PX`]-wide box around it (OpenCV's
//!    adaptive threshold compares the pixel itself, with several boxes; the 3 × 3 mean keeps a
//!    noisy frame's one-cell marker borders whole with one small box). One pass down the frame in
//!    integers: per column, the sum over the box's rows is kept running (the entering row added,
//!    the leaving one taken off) and the sum over the 3 rows around the pixel taken afresh; along
//!    the row, window sums of those (differences of running sums; three neighbours added), and
//!    where neither window is clipped by the frame the comparison is made in u16 — whole rows of
//!    additions the compiler vectorises. Each row leaves as runs of dark pixels, and the runs are
//!    labelled into 4-connected regions (runs on neighbouring rows sharing a column joined by
//!    union–find); a marker's black border is one region, whatever its bits.
//! 2. **Quadrilaterals.** Each region of plausible size (judged on its bounding box and pixel
//!    count first) is reduced to the convex hull of its pixels (their outer pixel edges: per line
//!    between two rows only the leftmost and rightmost edge, already in order, so the monotone
//!    chain needs no sort) and the hull to the largest quadrilateral on its vertices; a region
//!    whose hull the quadrilateral does not fill to [`MIN_QUAD_FILL`] is no marker.
//! 3. **Bits.** The quadrilateral's sides are first fitted to sub-pixel (the outline as thresholded
//!    can miss a blurred corner by a good part of a cell). Through the homography of the
//!    quadrilateral, every cell of an `(n + 2)²` grid is sampled (the mean of 3 × 3 bilinear
//!    samples in its middle half) for each marker size `n` the rig uses; the cells split into dark and light by two-means. The border cells must be dark (at
//!    most [`MAX_BORDER_ERROR_RATE`] of them light, OpenCV's default); the data bits, in each of the
//!    four rotations, are matched against every marker of the dictionary by Hamming distance (the
//!    read rotated, four times, rather than each code of the dictionary), and a
//!    marker is decoded when the nearest is within the dictionary's `maxCorrectionBits` (the bits
//!    corrected are reported per marker, [`Marker::corrected_bits`]). A marker whose id is not on any
//!    face, or whose id is decoded twice in the frame, is dropped.
//! 4. **Markers the regions missed** (`predicted_markers`). A marker whose outline is no
//!    quadrilateral of its own (at a grazing angle, two-and-a-half pixels a cell, the fine threshold
//!    splits it in two; where the face runs into a dark band its outline is cut short) or whose
//!    fitted outline misreads by a few bits (one side's edge found at few of its lines) is read
//!    where its face's decoded markers put it: per square of a face whose marker is not decoded,
//!    beside a decoded diagonal neighbour and with at least [`MIN_PREDICTING_MARKERS`] decoded
//!    markers within [`NEIGHBOUR_REACH`] squares (the square with the most first), the homography
//!    fitted to all their corners (least squares) gives its outline, read as in step 3 (the sides
//!    fitted first, through the prediction itself if that misreads). The read is taken only when
//!    it decodes, against the whole dictionary as any region's, to that square's id in that
//!    square's orientation, each corner within [`MAX_PREDICTED_MARKER_SHIFT`] cells of the
//!    prediction. A marker so found lends its corners to the squares around it in turn.
//!    Measured: the pyCamSet cube photos 2179 → 2186 of OpenCV 4.6's 2186 corners labelled (2421 →
//!    2558 in all, none differently; `CUBECAL_REQUIRE_TOOLS=1 cargo test --release --test
//!    detect_charuco_real -- --nocapture`); `cargo run --release --example charuco_eval --
//!    realistic 24` (and `hard 24`): 2249 → 2342 corners (509 → 826), no wrong label, every corner
//!    labelled before at the same place to the last digit; RMS over all 0.0189 → 0.0208 px
//!    (0.0862 → 0.1051 px), the corners added, on markers the regions cannot read, 0.047 px (0.130 px).
//! 5. **Corners.** Every inner corner of a ChArUco board touches two white squares, each holding a
//!    marker. A corner is labelled only when both are decoded and the homographies of both put the
//!    corner at the same place (within [`MAX_PREDICTION_DISAGREEMENT`] of a square): one wrongly
//!    decoded marker cannot label a corner. (OpenCV's `CharucoDetector` also needs two markers by
//!    default, `minMarkers = 2`.) The corner is then fitted by the checkerboard corners' fit, its
//!    window reaching along the edges as far as theirs (the image steps of the two markers'
//!    homographies), but on the pixels of the white gaps beside its two lines only
//!    ([`refine::refine_near_border_in_bands`], `fit_in_gaps`): the markers fill the middle of the
//!    white squares, the fit must not see them. Where that fails (gaps under a pixel wide and the
//!    like), the fit is tried again with the whole window shrunk into the gap around the corner
//!    ([`refine::refine_near_border`] with the steps scaled); a prediction a pixel off (markers
//!    drawn or printed a pixel from their place) brings a marker's edge into that window: a fit that
//!    finds no X-junction there, or is pulled away, is started again a pixel away (`fit_corner`); a
//!    corner whose fits fail is not labelled.
//!
//! Everything runs on the full-resolution frame; no part of a face needs any other part to be seen,
//! but for the markers of step 4, read only beside markers already decoded.
//!
//! ## Speed
//! Issue 33 asks for 10 ms per 1280 × 960 frame. `cargo bench --bench charuco` (the ChArUco cube in
//! the hard evaluation set's three poses, hard and realistic looks), 27 Nov 2026 on the shared
//! 2-core build machine (load average 2.9), median `detect` per frame: 4.33 ms hard, 6.25 ms
//! realistic look; the same bench built from 067cf73 (before the changes below), right after it:
//! 8.05 ms and 13.03 ms. Timed as whole processes side by side (10 pairs, the bench's frames read
//! from PNG, 10 runs of each frame), the new build takes 0.527 of the old one's time (median of
//! the pairs' ratios). callgrind, instructions per frame (mean of the six frames): finding and
//! decoding markers 126.4 M → 51.8 M, `detect` 129.3 M → 55.8 M. The changes to finding markers
//! reorder no arithmetic that reaches a result: every marker, and every corner labelled before,
//! is the same to the last digit the bench prints (`CUBECAL_BENCH_DUMP` of both builds compared;
//! the realistic look gains 17 corners from the fit's restart, step 5). What made the difference:
//! the threshold's sums vectorised (per-column running sums, a u16 comparison), run-length
//! labelling instead of a per-pixel flood fill, the hull without a sort, the dictionary matched
//! against four rotations of the read instead of every code rotated four times, and bilinear
//! sampling on the raw buffer. What is left, per frame: decoding (two reads of 7 × 7 cells of 9
//! bilinear samples each, the outline's sub-pixel fit) about 45 %, the threshold about 23 %.
//!
//! The second threshold pass with the finer box (46d24fa: markers at grazing angles whose white
//! gap to the squares is 2–3 px) costs 1.41× (whole process, paired, 5 pairs): 6.13 ms hard and
//! 8.55 ms realistic per frame (`cargo bench --bench charuco`, 27 Nov 2026); it labels 43 more of
//! OpenCV's corners on the real cube photos. Cheaper next: one rectangle per face instead of one
//! per frame, or both thresholds from the one set of 3 × 3 sums.
//!
//! The corner fit in the white gaps (`fit_in_gaps`, windows as long as a checkerboard corner's)
//! costs 4 %: median `detect` per frame 6.45 ms hard and 9.35 ms realistic against 6.22 and
//! 8.97 ms for the build before it (27 Nov 2026, two runs of each alternately, the same frames
//! read from PNG); it fits 65 and 161 corners of the bench's frames where that build fitted 35 and
//! 134.
//!
//! Reading the markers the regions miss (step 4) costs 1.055–1.09× on the realistic look and
//! 1.24–1.37× on the hard one (medians of three sessions of four runs alternating with the bench
//! built from 74ce6fe, `cargo bench --bench charuco`, the same frames read from PNG,
//! `CUBECAL_BENCH_FRAMES`, 27 Nov 2026, load average 3–6): median `detect` per frame 9.06–9.95 ms
//! realistic and 7.46–8.57 ms hard against 8.6–9.13 and 6.1–6.45 ms; it labels 118 and 173 corners
//! of the bench's frames where that build labels 65 and 161, every corner that build labels at the
//! same place to the last digit. Per frame up to about 30 squares are read on the hard look and 15
//! on the realistic one, each a read through the prediction, the outline's fit and a read through
//! it ([`PREDICTED_EDGE_SAMPLES`] lines a side; with the regions' 40 the reads took 1.3–1.45× as
//! long), and the corners the new markers add are fitted. Its module grown, the compiler stopped
//! inlining the pixel-by-pixel copy of the second pass's rectangle (`crop_imm(…).to_image()`, some
//! 120 million instructions over the bench's frames); it is copied row by row now, finding markers
//! as fast as before.
//!
//! Written here because no well-kept crate detects OpenCV's ArUco markers (see [`crate::rig::charuco`]).

use image::GrayImage;
use nalgebra::{Matrix3, SMatrix, SVector, Vector2, Vector3};

use super::face::{FaceDetection, LabelledCorner, Rejection};
use super::refine;
use crate::calib::linear::{homography_h33, normalize_2d};
use crate::rig::charuco::{Charuco, Dictionary, rotate_code};
use crate::rig::{Face, Rig};

/// How far the 3 × 3 mean around a pixel must be below the mean of the [`BOX_PX`] box around it
/// for the pixel to be dark (grey levels). OpenCV compares the pixel itself with 7; the 3 × 3 mean
/// has a third of the pixel's noise, so 4 asks more of the noise (2.4 σ of it instead of 1.4 σ)
/// while seeing low-contrast markers that 7 misses.
pub const THRESHOLD_OFFSET: i32 = 4;
/// Side of the adaptive threshold's box, px: about two cells of the smallest markers read
/// ([`MIN_CELL_PX`] × 7 cells = 10 px), so that a marker's one-cell black border stays darker
/// than the mean around it even where light bits touch it. Larger markers keep a dark outline
/// along their border's outer edge, which is all the outline needs.
pub const BOX_PX: usize = 15;
/// Side of the second pass's box (see [`marker_candidates`]), px. Where a face is seen at a grazing
/// angle, the white gap between a marker and the black squares beside it (two-thirds of a cell
/// each side on the ArUco boards OpenCV draws, a sixth of a square) narrows to 2–3 px: in a
/// [`BOX_PX`] box the mean is pulled down so far by the black squares around that the gap falls
/// below it too, and the marker's border joins the squares into one region that is no
/// quadrilateral. A box of 9 px keeps gaps of 2 px apart (the pyCamSet cube photos: 22 of the 24
/// markers OpenCV 4.6 decodes and cubecal did not come out as regions of their own); it is not the
/// only pass because at 9 px the border of a large marker is hollow, its outline broken by noise.
pub const FINE_BOX_PX: usize = 9;
/// Smallest side of a marker's quadrilateral, px per cell of the `(n + 2)²` grid.
pub const MIN_CELL_PX: f64 = 1.5;
/// Smallest ratio of the quadrilateral's area to its region's hull.
pub const MIN_QUAD_FILL: f64 = 0.8;
/// Largest share of a marker's border cells read light (OpenCV's `maxErroneousBitsInBorderRate`).
pub const MAX_BORDER_ERROR_RATE: f64 = 0.35;
/// Smallest difference between the light and dark cells' mean (grey levels).
pub const MIN_MARKER_CONTRAST: f64 = 10.0;
/// Largest distance between the two markers' predictions of a corner, in squares. A marker
/// decoded with another id of the face sits at least one square diagonal (√2 squares) from where
/// that id belongs, so its prediction misses by about that much; a quarter of a square leaves
/// room for a lens that bends a square's sides (the pycalib wide-angle photos, ~106°: the two
/// predictions differ by 0.10–0.15 of a square at the frame's edges).
pub const MAX_PREDICTION_DISAGREEMENT: f64 = 0.25;

/// A decoded marker.
#[derive(Debug, Clone, PartialEq)]
pub struct Marker {
    /// Marker size (data bits per side).
    pub bits: usize,
    pub id: u32,
    /// Image corners in the marker's own order as printed: top left, top right, bottom right,
    /// bottom left (OpenCV's order).
    pub corners: [Vector2<f64>; 4],
    /// Data bits read wrong and corrected.
    pub corrected_bits: u32,
    /// Light-minus-dark mean of its cells (grey levels).
    pub contrast: f64,
}

/// What the ChArUco detector found in one frame.
#[derive(Debug, Clone, Default)]
pub struct CharucoDetection {
    pub faces: Vec<FaceDetection>,
    pub rejected: Vec<Rejection>,
    /// Every marker decoded whose id is on a face of the rig.
    pub markers: Vec<Marker>,
}

/// Sums over windows of `2r + 1` values of `v` (clipped by its ends), into `out`: differences of
/// running sums (`pre`, scratch); three neighbours added directly. The differences and additions
/// run over whole rows, which the compiler vectorises (in u16: callers keep the sums below 2¹⁶).
fn window_sums(v: &[u16], r: usize, out: &mut [u16], pre: &mut [u32]) {
    let w = v.len().min(out.len());
    if r == 1 && w >= 3 {
        let (l, m, rt) = (&v[..w - 2], &v[1..w - 1], &v[2..w]);
        for (o, ((&a, &b), &c)) in out[1..w - 1].iter_mut().zip(l.iter().zip(m).zip(rt)) {
            *o = a + b + c;
        }
        out[0] = v[0] + v[1];
        out[w - 1] = v[w - 2] + v[w - 1];
        return;
    }
    let pre = &mut pre[..w + 1];
    pre[0] = 0;
    for x in 0..w {
        pre[x + 1] = pre[x] + u32::from(v[x]);
    }
    let clipped = |x: usize| (pre[(x + r + 1).min(w)] - pre[x.saturating_sub(r)]) as u16;
    if w > 2 * r + 1 {
        for x in (0..r).chain(w - r..w) {
            out[x] = clipped(x);
        }
        let n = w - 2 * r;
        let (hi, lo) = (&pre[2 * r + 1..2 * r + 1 + n], &pre[..n]);
        for (o, (&p, &q)) in out[r..r + n].iter_mut().zip(hi.iter().zip(lo)) {
            *o = (p - q) as u16;
        }
    } else {
        for x in 0..w {
            out[x] = clipped(x);
        }
    }
}

// The fast path of [`threshold`] compares in u16: the box's sum and the 3 × 3 sum scaled to it
// must stay below 2¹⁶, and the box's pixel count must be a multiple of the 3 × 3 window's.
const _: () = assert!(BOX_PX * BOX_PX * (255 + THRESHOLD_OFFSET as usize) <= u16::MAX as usize);
const _: () = assert!(BOX_PX.is_multiple_of(3) && !BOX_PX.is_multiple_of(2));
const _: () = assert!(FINE_BOX_PX.is_multiple_of(3) && !FINE_BOX_PX.is_multiple_of(2));
const _: () = assert!(FINE_BOX_PX < BOX_PX);

/// The dark pixels of the adaptive threshold, row by row (`row_out(y, row)`, one byte per pixel,
/// 1 = dark): the 3 × 3 mean around a pixel at least [`THRESHOLD_OFFSET`] below the mean of the
/// `BOX` box around it ([`BOX_PX`] or [`FINE_BOX_PX`]) (both windows clipped by the frame). Separable sums in integers: per
/// column, the sums over the box's rows (kept running: the entering row added, the leaving one
/// taken off) and over the 3 rows around the pixel, then over the windows along the row
/// ([`window_sums`]).
fn threshold<const BOX: usize>(img: &GrayImage, mut row_out: impl FnMut(usize, &[u8])) {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let src = img.as_raw();
    let r = BOX / 2;
    let side = 2 * r + 1;
    // Pixels per window column span.
    let n3x: Vec<i32> = (0..w)
        .map(|x| ((x + 2).min(w) - x.saturating_sub(1)) as i32)
        .collect();
    let nbx: Vec<i32> = (0..w)
        .map(|x| ((x + r + 1).min(w) - x.saturating_sub(r)) as i32)
        .collect();
    let mut out = vec![0u8; w];
    // Column sums over the box's rows [lo, hi) and over the 3 rows around y; their window sums.
    let mut vbox = vec![0u16; w];
    let mut v3 = vec![0u16; w];
    let mut sbox = vec![0u16; w];
    let mut s3 = vec![0u16; w];
    let mut pre = vec![0u32; w + 1];
    let (mut lo, mut hi) = (0usize, 0usize);
    let row = |y: usize| &src[y * w..(y + 1) * w];
    // The fast path's comparison: t / 9 < c / nb − offset ⇔ k·t + offset·nb < c, k = nb / 9.
    let nb_full = side * side;
    let k = (nb_full / 9) as u16;
    let bias = (THRESHOLD_OFFSET as usize * nb_full) as u16;
    for y in 0..h {
        let (want_lo, want_hi) = (y.saturating_sub(r), (y + r + 1).min(h));
        while lo < want_lo {
            for (c, &v) in vbox.iter_mut().zip(row(lo)) {
                *c -= u16::from(v);
            }
            lo += 1;
        }
        while hi < want_hi {
            for (c, &v) in vbox.iter_mut().zip(row(hi)) {
                *c += u16::from(v);
            }
            hi += 1;
        }
        let (a, b) = (y.saturating_sub(1), (y + 2).min(h));
        if b - a == 3 {
            let (p, q, u) = (row(a), row(a + 1), row(a + 2));
            for (c, ((&x, &y), &z)) in v3.iter_mut().zip(p.iter().zip(q).zip(u)) {
                *c = u16::from(x) + u16::from(y) + u16::from(z);
            }
        } else {
            v3.fill(0);
            for yy in a..b {
                for (c, &v) in v3.iter_mut().zip(row(yy)) {
                    *c += u16::from(v);
                }
            }
        }
        window_sums(&vbox, r, &mut sbox, &mut pre);
        window_sums(&v3, 1, &mut s3, &mut pre);
        let nby = (hi - lo) as i32;
        let n3y = (b - a) as i32;
        let dark = |x: usize| {
            let (n3, nb) = (n3x[x] * n3y, nbx[x] * nby);
            // t / n3 < c / nb − offset, in integers.
            u8::from(i32::from(s3[x]) * nb < n3 * (i32::from(sbox[x]) - THRESHOLD_OFFSET * nb))
        };
        if n3y == 3 && nby == side as i32 && w > 2 * r {
            // Away from the frame's border neither window is clipped: constant pixel counts.
            for x in (0..r).chain(w - r..w) {
                out[x] = dark(x);
            }
            for ((o, &t), &c) in out[r..w - r]
                .iter_mut()
                .zip(&s3[r..w - r])
                .zip(&sbox[r..w - r])
            {
                *o = u8::from(k * t + bias < c);
            }
        } else {
            for x in 0..w {
                out[x] = dark(x);
            }
        }
        row_out(y, &out);
    }
}

/// One 4-connected dark region: per image row, its leftmost and rightmost pixel.
struct Region {
    rows: Vec<(u32, u32, u32)>,
    pixels: usize,
    /// `[x0, y0, x1, y1]`, inclusive.
    bbox: [u32; 4],
}

/// A horizontal run of dark pixels: row, first and last pixel.
#[derive(Clone, Copy)]
struct Run {
    y: u32,
    x0: u32,
    x1: u32,
}

/// The runs of dark pixels of the adaptive threshold, in raster order, and where each row's
/// runs start (`h + 1` entries).
fn dark_runs<const BOX: usize>(img: &GrayImage) -> (Vec<Run>, Vec<usize>) {
    let mut runs = Vec::new();
    let mut row_start = Vec::with_capacity(img.height() as usize + 1);
    threshold::<BOX>(img, |y, row| {
        row_start.push(runs.len());
        let mut x = 0;
        while let Some(k) = row[x..].iter().position(|&d| d != 0) {
            let x0 = x + k;
            let len = row[x0..]
                .iter()
                .position(|&d| d == 0)
                .unwrap_or(row.len() - x0);
            runs.push(Run {
                y: y as u32,
                x0: x0 as u32,
                x1: (x0 + len - 1) as u32,
            });
            x = x0 + len;
        }
    });
    row_start.push(runs.len());
    (runs, row_start)
}

/// The root of run `k`'s set, halving the path on the way.
fn find(parent: &mut [u32], mut k: u32) -> u32 {
    while parent[k as usize] != k {
        let up = parent[parent[k as usize] as usize];
        parent[k as usize] = up;
        k = up;
    }
    k
}

/// The 4-connected dark regions at least `min_side` px wide or high, in the raster order of their
/// first pixel. Run-length labelling: runs on neighbouring rows that share a column are joined
/// (union–find, the earliest run the root), then each region's runs give its rows, pixel count and
/// bounding box.
fn regions<const BOX: usize>(img: &GrayImage, min_side: f64) -> Vec<Region> {
    let (runs, row_start) = dark_runs::<BOX>(img);
    let mut parent: Vec<u32> = (0..runs.len() as u32).collect();
    for y in 1..row_start.len().saturating_sub(1) {
        let (mut i, mut j) = (row_start[y - 1], row_start[y]);
        let (i_end, j_end) = (row_start[y], row_start[y + 1]);
        while i < i_end && j < j_end {
            let (a, b) = (runs[i], runs[j]);
            if a.x0 <= b.x1 && b.x0 <= a.x1 {
                let (ra, rb) = (find(&mut parent, i as u32), find(&mut parent, j as u32));
                if ra != rb {
                    let (lo, hi) = (ra.min(rb), ra.max(rb));
                    parent[hi as usize] = lo;
                }
            }
            if a.x1 < b.x1 {
                i += 1;
            } else {
                j += 1;
            }
        }
    }
    // Per root: pixels and bounding box; a run's root comes no later than the run.
    let mut stats = vec![(0usize, [u32::MAX, u32::MAX, 0u32, 0u32]); runs.len()];
    let mut root = vec![0u32; runs.len()];
    for k in 0..runs.len() {
        let rt = find(&mut parent, k as u32);
        root[k] = rt;
        let run = runs[k];
        let (pixels, b) = &mut stats[rt as usize];
        *pixels += (run.x1 - run.x0 + 1) as usize;
        *b = [
            b[0].min(run.x0),
            b[1].min(run.y),
            b[2].max(run.x1),
            b[3].max(run.y),
        ];
    }
    let mut slot = vec![u32::MAX; runs.len()];
    let mut out: Vec<Region> = Vec::new();
    for k in 0..runs.len() {
        if root[k] != k as u32 {
            continue;
        }
        let (pixels, bbox) = stats[k];
        let [x0, y0, x1, y1] = bbox;
        if (f64::from((x1 - x0 + 1).max(y1 - y0 + 1))) < min_side {
            continue;
        }
        slot[k] = out.len() as u32;
        out.push(Region {
            rows: (y0..=y1).map(|y| (y, u32::MAX, 0)).collect(),
            pixels,
            bbox,
        });
    }
    for (run, &rt) in runs.iter().zip(&root) {
        let s = slot[rt as usize];
        if s == u32::MAX {
            continue;
        }
        let region = &mut out[s as usize];
        let row = &mut region.rows[(run.y - region.bbox[1]) as usize];
        row.1 = row.1.min(run.x0);
        row.2 = row.2.max(run.x1);
    }
    for region in &mut out {
        region.rows.retain(|r| r.1 != u32::MAX);
    }
    out
}

fn cross(o: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> f64 {
    (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
}

/// Convex hull (monotone chain), counter-clockwise in a y-up frame — clockwise as seen in the image.
fn hull(mut pts: Vec<Vector2<f64>>) -> Vec<Vector2<f64>> {
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    monotone_chain(&pts)
}

/// The outer pixel-edge corners of each row run `(y, x0, x1)`: the points whose [`hull`] is the
/// region's.
fn row_edge_points(rows: &[(u32, u32, u32)]) -> Vec<Vector2<f64>> {
    let mut pts = Vec::with_capacity(rows.len() * 4);
    for &(y, x0, x1) in rows {
        let (y, x0, x1) = (f64::from(y), f64::from(x0), f64::from(x1));
        pts.extend([
            Vector2::new(x0 - 0.5, y - 0.5),
            Vector2::new(x0 - 0.5, y + 0.5),
            Vector2::new(x1 + 0.5, y - 0.5),
            Vector2::new(x1 + 0.5, y + 0.5),
        ]);
    }
    pts
}

/// Convex hull of a region's pixels (their outer pixel edges), as [`hull`] gives it: the same
/// vertices in the same order. Its rows are consecutive (the region is connected), so the
/// candidates are, on each horizontal line between two rows, the leftmost and rightmost pixel edge
/// of the two rows: already ordered by (y, x), and the monotone chain needs no sort.
fn region_hull(rows: &[(u32, u32, u32)]) -> Vec<Vector2<f64>> {
    let consecutive = rows.windows(2).all(|p| p[1].0 == p[0].0 + 1);
    if rows.is_empty() || !consecutive {
        return hull(row_edge_points(rows));
    }
    let n = rows.len();
    let mut pts = Vec::with_capacity(2 * (n + 1));
    for k in 0..=n {
        let (y, l, r) = match (k.checked_sub(1).map(|i| rows[i]), rows.get(k)) {
            (Some(a), Some(b)) => (f64::from(b.0) - 0.5, a.1.min(b.1), a.2.max(b.2)),
            (None, Some(b)) => (f64::from(b.0) - 0.5, b.1, b.2),
            (Some(a), None) => (f64::from(a.0) + 0.5, a.1, a.2),
            (None, None) => continue,
        };
        pts.push(Vector2::new(f64::from(l) - 0.5, y));
        pts.push(Vector2::new(f64::from(r) + 0.5, y));
    }
    let mut out = monotone_chain(&pts);
    // Ordered by (y, x), the chain runs the other way round: turn it to [`hull`]'s orientation
    // and start, the least (x, y).
    if polygon_area(&out) < 0.0 {
        out.reverse();
    }
    if let Some(first) = (0..out.len()).min_by(|&a, &b| {
        let (p, q) = (out[a], out[b]);
        p.x.total_cmp(&q.x).then(p.y.total_cmp(&q.y))
    }) {
        out.rotate_left(first);
    }
    out
}

/// Andrew's monotone chain on points sorted lexicographically (in either coordinate order), no
/// two equal; collinear points dropped.
fn monotone_chain(pts: &[Vector2<f64>]) -> Vec<Vector2<f64>> {
    if pts.len() < 3 {
        return pts.to_vec();
    }
    let mut lower: Vec<Vector2<f64>> = Vec::with_capacity(pts.len());
    for &p in pts {
        while lower.len() >= 2 && cross(lower[lower.len() - 2], lower[lower.len() - 1], p) <= 0.0 {
            lower.pop();
        }
        lower.push(p);
    }
    let mut upper: Vec<Vector2<f64>> = Vec::with_capacity(pts.len());
    for &p in pts.iter().rev() {
        while upper.len() >= 2 && cross(upper[upper.len() - 2], upper[upper.len() - 1], p) <= 0.0 {
            upper.pop();
        }
        upper.push(p);
    }
    lower.pop();
    upper.pop();
    lower.extend(upper);
    lower
}

/// Drop the vertices of a closed polygon closer than `eps` px to the line through their
/// neighbours, the least significant first, until every vertex stands out (the hull of a blurred
/// quadrilateral keeps its four corners and a few vertices of each rounded one).
fn simplify(mut p: Vec<Vector2<f64>>, eps: f64) -> Vec<Vector2<f64>> {
    while p.len() > 4 {
        let n = p.len();
        let (mut best, mut at) = (f64::INFINITY, 0);
        for i in 0..n {
            let (a, b, c) = (p[(i + n - 1) % n], p[i], p[(i + 1) % n]);
            let len = (c - a).norm();
            let d = if len > 0.0 {
                cross(a, c, b).abs() / len
            } else {
                0.0
            };
            if d < best {
                (best, at) = (d, i);
            }
        }
        if best >= eps {
            break;
        }
        p.remove(at);
    }
    p
}

fn polygon_area(p: &[Vector2<f64>]) -> f64 {
    let n = p.len();
    (0..n)
        .map(|i| p[i].x * p[(i + 1) % n].y - p[(i + 1) % n].x * p[i].y)
        .sum::<f64>()
        / 2.0
}

/// The largest-area quadrilateral on the hull's vertices, in hull order.
fn largest_quad(h: &[Vector2<f64>]) -> Option<[Vector2<f64>; 4]> {
    let n = h.len();
    if n < 4 {
        return None;
    }
    let tri = |a: usize, b: usize, c: usize| cross(h[a], h[b], h[c]).abs() / 2.0;
    let mut best = (0.0, [0usize; 4]);
    // Diagonal (i, k); the best vertex on each side, found by scanning (hulls have few vertices).
    for i in 0..n {
        for k in i + 2..n {
            let (mut b1, mut j1) = (0.0, usize::MAX);
            for j in i + 1..k {
                let t = tri(i, j, k);
                if t > b1 {
                    (b1, j1) = (t, j);
                }
            }
            let (mut b2, mut l2) = (0.0, usize::MAX);
            for l in (k + 1..n).chain(0..i) {
                let t = tri(k, l, i);
                if t > b2 {
                    (b2, l2) = (t, l);
                }
            }
            if j1 != usize::MAX && l2 != usize::MAX && b1 + b2 > best.0 {
                best = (b1 + b2, [i, j1, k, l2]);
            }
        }
    }
    if best.0 <= 0.0 {
        return None;
    }
    let mut idx = best.1;
    idx.sort_unstable();
    Some(idx.map(|i| h[i]))
}

/// Homography taking `from[i]` to `to[i]` (four points, DLT with h₃₃ = 1).
pub fn homography(from: &[Vector2<f64>; 4], to: &[Vector2<f64>; 4]) -> Option<Matrix3<f64>> {
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut rhs = SVector::<f64, 8>::zeros();
    for k in 0..4 {
        let (x, y) = (from[k].x, from[k].y);
        let (u, v) = (to[k].x, to[k].y);
        a.set_row(
            2 * k,
            &SMatrix::<f64, 1, 8>::from_row_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]),
        );
        a.set_row(
            2 * k + 1,
            &SMatrix::<f64, 1, 8>::from_row_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]),
        );
        rhs[2 * k] = u;
        rhs[2 * k + 1] = v;
    }
    let h = a.lu().solve(&rhs)?;
    Some(Matrix3::new(
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0,
    ))
}

/// Apply a homography; `None` behind the plane's horizon.
pub fn apply(h: &Matrix3<f64>, p: Vector2<f64>) -> Option<Vector2<f64>> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    (q.z.abs() > 1e-12).then(|| Vector2::new(q.x / q.z, q.y / q.z))
}

#[inline]
fn bilinear(img: &GrayImage, p: Vector2<f64>) -> Option<f64> {
    let (wu, hu) = (img.width() as usize, img.height() as usize);
    if !(p.x >= 0.0 && p.y >= 0.0 && p.x <= (wu - 1) as f64 && p.y <= (hu - 1) as f64) {
        return None;
    }
    // Non-negative and within the frame: truncation is the floor (through u32, a cheaper
    // conversion than to usize).
    let (x0, y0) = (p.x as u32 as usize, p.y as u32 as usize);
    let (fx, fy) = (p.x - x0 as f64, p.y - y0 as f64);
    // The next pixel right and down, or the same one on the last column and row.
    let dx = usize::from(x0 + 1 < wu);
    let dy = if y0 + 1 < hu { wu } else { 0 };
    let i = y0 * wu + x0;
    let g = img.as_raw().get(i..=i + dy + dx)?;
    Some(
        f64::from(g[0]) * (1.0 - fx) * (1.0 - fy)
            + f64::from(g[dx]) * fx * (1.0 - fy)
            + f64::from(g[dy]) * (1.0 - fx) * fy
            + f64::from(g[dy + dx]) * fx * fy,
    )
}

/// Why a quadrilateral decoded to no marker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodeMiss {
    /// Its cells reach outside the frame or its homography is degenerate.
    Geometry,
    /// Light and dark cells too alike ([`MIN_MARKER_CONTRAST`]).
    Contrast,
    /// This many border cells read light (more than [`MAX_BORDER_ERROR_RATE`] allows).
    Border(usize),
    /// The nearest code of the dictionary is this many bits away (more than it corrects).
    Distance(u32),
}

/// A marker's cells as read: the mean grey level of each cell of the `(n + 2)²` grid (row-major),
/// and their two-means split (threshold `t`, the dark and light cells' means).
struct Cells {
    values: Vec<f64>,
    t: f64,
    m_dark: f64,
    m_light: f64,
}

/// Read the `cells × cells` grid of a quadrilateral: each cell the mean of 3 × 3 bilinear samples
/// in its middle half; the cells split into dark and light by two-means.
fn read_cells(
    img: &GrayImage,
    quad: &[Vector2<f64>; 4],
    cells: usize,
) -> Result<Cells, DecodeMiss> {
    let unit = [
        Vector2::new(0.0, 0.0),
        Vector2::new(1.0, 0.0),
        Vector2::new(1.0, 1.0),
        Vector2::new(0.0, 1.0),
    ];
    let h = homography(&unit, quad).ok_or(DecodeMiss::Geometry)?;
    let mut values = vec![0.0; cells * cells];
    for r in 0..cells {
        for c in 0..cells {
            let mut sum = 0.0;
            for dy in [-0.25, 0.0, 0.25] {
                for dx in [-0.25, 0.0, 0.25] {
                    let u = (c as f64 + 0.5 + dx) / cells as f64;
                    let v = (r as f64 + 0.5 + dy) / cells as f64;
                    sum += apply(&h, Vector2::new(u, v))
                        .and_then(|p| bilinear(img, p))
                        .ok_or(DecodeMiss::Geometry)?;
                }
            }
            values[r * cells + c] = sum / 9.0;
        }
    }
    let (lo, hi) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let mut t = (lo + hi) / 2.0;
    let (mut m_dark, mut m_light) = (lo, hi);
    for _ in 0..10 {
        let (mut sd, mut nd, mut sl, mut nl) = (0.0, 0, 0.0, 0);
        for &v in &values {
            if v < t {
                sd += v;
                nd += 1;
            } else {
                sl += v;
                nl += 1;
            }
        }
        if nd == 0 || nl == 0 {
            return Err(DecodeMiss::Contrast);
        }
        (m_dark, m_light) = (sd / nd as f64, sl / nl as f64);
        t = (m_dark + m_light) / 2.0;
    }
    if m_light - m_dark < MIN_MARKER_CONTRAST {
        return Err(DecodeMiss::Contrast);
    }
    Ok(Cells {
        values,
        t,
        m_dark,
        m_light,
    })
}

/// Read and decode a quadrilateral (image corners clockwise as seen) as a marker of `dict`; its
/// corners are refined to sub-pixel ([`Marker::corners`]).
pub fn decode(
    img: &GrayImage,
    quad: &[Vector2<f64>; 4],
    dict: Dictionary,
) -> Result<Marker, DecodeMiss> {
    let cells = dict.bits + 2;
    // The outline as thresholded can be off by a good part of a cell at a blurred, noisy corner:
    // its sides are fitted to sub-pixel first, with the level between the cells' two means as
    // first read, and the cells read again through the fitted outline.
    let first = read_cells(img, quad, cells)?;
    let (quad, read) =
        fit_outline::<MAX_EDGE_SAMPLES>(img, quad, &first, cells).unwrap_or((*quad, first));
    match_cells(read, &quad, dict)
}

/// The outline `quad` fitted to sub-pixel ([`refine_quad`], at the level between the dark and light
/// cells of `first`, its read) and the cells read through it; `None` when either fails.
/// `SAMPLES`: the most lines across a side ([`refine_quad`]).
#[inline]
fn fit_outline<const SAMPLES: usize>(
    img: &GrayImage,
    quad: &[Vector2<f64>; 4],
    first: &Cells,
    cells: usize,
) -> Option<([Vector2<f64>; 4], Cells)> {
    let cell_px = (0..4)
        .map(|k| (quad[(k + 1) % 4] - quad[k]).norm())
        .fold(f64::INFINITY, f64::min)
        / cells as f64;
    let level = (first.m_dark + first.m_light) / 2.0;
    let q = refine_quad::<SAMPLES>(img, quad, level, cell_px)?;
    let read = read_cells(img, &q, cells).ok()?;
    Some((q, read))
}

/// Decode cells read through `quad` as a marker of `dict`: the border dark, the data bits the
/// nearest code within the dictionary's correction bits, in any rotation.
#[inline]
fn match_cells(
    read: Cells,
    quad: &[Vector2<f64>; 4],
    dict: Dictionary,
) -> Result<Marker, DecodeMiss> {
    let n = dict.bits;
    let cells = n + 2;
    let Cells {
        values,
        t,
        m_dark,
        m_light,
    } = read;
    let light = |r: usize, c: usize| values[r * cells + c] >= t;
    let border_light = (0..cells)
        .flat_map(|r| (0..cells).map(move |c| (r, c)))
        .filter(|&(r, c)| r == 0 || c == 0 || r == cells - 1 || c == cells - 1)
        .filter(|&(r, c)| light(r, c))
        .count();
    if border_light as f64 > MAX_BORDER_ERROR_RATE * (4 * (cells - 1)) as f64 {
        return Err(DecodeMiss::Border(border_light));
    }
    let mut read = 0u64;
    for r in 0..n {
        for c in 0..n {
            read = (read << 1) | u64::from(light(r + 1, c + 1));
        }
    }
    let max = dict.max_correction_bits();
    // A rotation permutes the bits, so a code rotated `rot` times is as far from the read as the
    // code from the read rotated back (`4 − rot` times): the read is rotated, not every code.
    let mut back = [read; 4];
    for rot in [3, 2, 1] {
        back[rot] = rotate_code(back[(rot + 1) % 4], n);
    }
    let mut best: Option<(u32, u32, usize)> = None; // (distance, id, rotation)
    let mut nearest = u32::MAX;
    for (id, &code) in dict.codes().iter().enumerate() {
        for (rot, &r) in back.iter().enumerate() {
            let d = (code ^ r).count_ones();
            nearest = nearest.min(d);
            if d <= max && best.is_none_or(|b| d < b.0) {
                best = Some((d, id as u32, rot));
            }
        }
    }
    let Some((distance, id, rot)) = best else {
        return Err(DecodeMiss::Distance(nearest));
    };
    Ok(Marker {
        bits: n,
        id,
        corners: [0, 1, 2, 3].map(|k| quad[(k + rot) % 4]),
        corrected_bits: distance,
        contrast: m_light - m_dark,
    })
}

/// The marker's outline to sub-pixel precision: along each side, where the grey level crosses
/// `level` (between the marker's dark and light cells) on lines across the side, searched within
/// 0.8 of a cell of the thresholded outline; a straight line fitted to those points per side; the
/// corners where neighbouring lines meet. `None` (keep the outline as found) when a side has too
/// few crossings.
fn refine_quad<const MAX_SAMPLES: usize>(
    img: &GrayImage,
    quad: &[Vector2<f64>; 4],
    level: f64,
    cell_px: f64,
) -> Option<[Vector2<f64>; 4]> {
    let centre = quad.iter().sum::<Vector2<f64>>() / 4.0;
    let reach = (0.8 * cell_px).clamp(1.0, 4.0);
    let mut lines = [(Vector2::zeros(), Vector2::zeros()); 4]; // (point, unit direction)
    for k in 0..4 {
        let (p, q) = (quad[k], quad[(k + 1) % 4]);
        let len = (q - p).norm();
        let dir = (q - p) / len;
        let mut normal = Vector2::new(-dir.y, dir.x);
        if normal.dot(&((p + q) / 2.0 - centre)) < 0.0 {
            normal = -normal;
        }
        let samples = (len as usize).clamp(4, MAX_SAMPLES.max(4));
        let mut pts: Vec<Vector2<f64>> = Vec::with_capacity(samples);
        for i in 0..samples {
            let t = 0.15 + 0.7 * (i as f64 + 0.5) / samples as f64;
            let base = p + (q - p) * t;
            // From outside (light) inward: the first crossing below the level.
            let step = 0.25;
            let mut prev: Option<(f64, f64)> = None;
            let mut o = reach;
            while o >= -reach {
                let Some(v) = bilinear(img, base + normal * o) else {
                    break;
                };
                if let Some((po, pv)) = prev
                    && pv >= level
                    && v < level
                {
                    let f = (pv - level) / (pv - v);
                    pts.push(base + normal * (po - f * step));
                    break;
                }
                prev = Some((o, v));
                o -= step;
            }
        }
        if pts.len() < 3 {
            return None;
        }
        // Total least squares line through the points.
        let m = pts.iter().sum::<Vector2<f64>>() / pts.len() as f64;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for q in &pts {
            let d = q - m;
            sxx += d.x * d.x;
            sxy += d.x * d.y;
            syy += d.y * d.y;
        }
        let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let mut u = Vector2::new(angle.cos(), angle.sin());
        if u.dot(&dir) < 0.0 {
            u = -u;
        }
        if u.dot(&dir) < 0.9 {
            return None;
        }
        lines[k] = (m, u);
    }
    let mut out = [Vector2::zeros(); 4];
    for k in 0..4 {
        // Corner k is where side k − 1 (ending at it) meets side k (starting from it).
        let (p1, u1) = lines[(k + 3) % 4];
        let (p2, u2) = lines[k];
        let det = u1.x * (-u2.y) - u1.y * (-u2.x);
        if det.abs() < 1e-6 {
            return None;
        }
        let r = p2 - p1;
        let t = (r.x * (-u2.y) - r.y * (-u2.x)) / det;
        out[k] = p1 + u1 * t;
        if (out[k] - quad[k]).norm() > 2.0 * reach {
            return None;
        }
    }
    Some(out)
}

/// Most lines across a side on which `refine_quad` looks for the outline's edge (one per pixel of
/// the side up to this many).
pub const MAX_EDGE_SAMPLES: usize = 40;

/// [`MAX_EDGE_SAMPLES`] for the outlines `predicted_markers` reads: their sides are fitted only
/// to read the cells (a misread is retried through the prediction itself), and a fit that finds no
/// edge, where no marker is, scans every line to its end.
pub const PREDICTED_EDGE_SAMPLES: usize = 12;

/// What became of one dark region examined as a marker candidate ([`marker_candidates`]).
#[derive(Debug, Clone, PartialEq)]
pub enum CandidateOutcome {
    /// Smaller or larger than a marker can be.
    Size,
    /// Touching the frame's border.
    FrameBorder,
    /// Its outline is no quadrilateral (the quadrilateral fills too little of its hull).
    NotQuad,
    /// A quadrilateral whose bits decode to no marker of the dictionaries (why, for the last
    /// dictionary tried).
    NotDecoded(DecodeMiss),
    Decoded(Marker),
}

/// One dark region examined as a marker: its bounding box `[x0, y0, x1, y1]` (pixels, inclusive),
/// pixel count and outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// The threshold's box it was found with ([`BOX_PX`] or [`FINE_BOX_PX`]).
    pub box_px: usize,
    pub bbox: [u32; 4],
    /// The quadrilateral read, when its outline is one.
    pub quad: Option<[Vector2<f64>; 4]>,
    pub pixels: usize,
    pub outcome: CandidateOutcome,
}

/// Find and decode the markers of every size in `dicts` (one dictionary per marker size).
pub fn find_markers(img: &GrayImage, dicts: &[Dictionary]) -> Vec<Marker> {
    marker_candidates(img, dicts)
        .into_iter()
        .filter_map(|c| match c.outcome {
            CandidateOutcome::Decoded(m) => Some(m),
            _ => None,
        })
        .collect()
}

/// Every dark region of at least a marker's minimum size and what became of it (for measuring
/// which markers are missed and why; [`find_markers`] keeps the decoded ones). Two passes: the
/// regions of the [`BOX_PX`] threshold, then those of the [`FINE_BOX_PX`] one that do not lie on a
/// marker the first pass decoded (their middle outside its quadrilateral): markers whose border
/// the first joined to the black squares around (see [`FINE_BOX_PX`]). A marker of the second
/// pass whose middle lies in a quadrilateral of the first is that marker again and dropped.
pub fn marker_candidates(img: &GrayImage, dicts: &[Dictionary]) -> Vec<Candidate> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let Some(min_bits) = dicts.iter().map(|d| d.bits).min() else {
        return Vec::new();
    };
    let min_side = (min_bits + 2) as f64 * MIN_CELL_PX;
    let max_side = w.min(h) as f64 / 2.0;
    let mut out = Vec::new();
    for region in regions::<BOX_PX>(img, min_side) {
        let (quad, outcome) = examine(img, &region, dicts, (w, h), min_side, max_side);
        out.push(Candidate {
            box_px: BOX_PX,
            bbox: region.bbox,
            quad,
            pixels: region.pixels,
            outcome,
        });
    }
    // The first pass's markers, with their bounding boxes for a quick test.
    let first: Vec<([Vector2<f64>; 4], [f64; 4])> = out
        .iter()
        .filter_map(|c| match &c.outcome {
            CandidateOutcome::Decoded(m) => Some((m.corners, bounds(&m.corners))),
            _ => None,
        })
        .collect();
    let on_first = |p: Vector2<f64>| {
        first.iter().any(|(q, b)| {
            p.x >= b[0] && p.y >= b[1] && p.x <= b[2] && p.y <= b[3] && inside_convex(q, p)
        })
    };
    // Where the second pass looks: around the first pass's markers, [`ROI_REACH`] times a marker's
    // extent on each side — a marker the first pass joined to the squares around is the neighbour of
    // one it decoded (or no corner beside it has two markers) — one rectangle for the frame.
    let Some(roi) = first
        .iter()
        .map(|(_, b)| {
            let (rx, ry) = (ROI_REACH * (b[2] - b[0]), ROI_REACH * (b[3] - b[1]));
            [b[0] - rx, b[1] - ry, b[2] + rx, b[3] + ry]
        })
        .reduce(|a, b| {
            [
                a[0].min(b[0]),
                a[1].min(b[1]),
                a[2].max(b[2]),
                a[3].max(b[3]),
            ]
        })
    else {
        return out;
    };
    let rx0 = roi[0].floor().max(0.0) as u32;
    let ry0 = roi[1].floor().max(0.0) as u32;
    let rx1 = (roi[2].ceil().max(0.0) as u32).min(img.width());
    let ry1 = (roi[3].ceil().max(0.0) as u32).min(img.height());
    if rx1 <= rx0 || ry1 <= ry0 {
        return out;
    }
    // The first pass's regions by their left edge: a region of the second whose bounding box is
    // one of them to [`SAME_REGION_PX`] is the same outline again, examined once already.
    let mut seen: Vec<[u32; 4]> = out.iter().map(|c| c.bbox).collect();
    seen.sort_unstable();
    let tol = SAME_REGION_PX;
    let seen_before = |b: [u32; 4]| {
        let from = seen.partition_point(|s| s[0] + tol < b[0]);
        seen[from..]
            .iter()
            .take_while(|s| s[0] <= b[0] + tol)
            .any(|s| (1..4).all(|k| s[k].abs_diff(b[k]) <= tol))
    };
    // The rectangle copied row by row (`crop_imm(…).to_image()` copies pixel by pixel, and where
    // the compiler does not inline it, costs as much as the threshold of the rectangle).
    let row_px = img.width() as usize;
    let (cx0, cx1) = (rx0 as usize, rx1 as usize);
    let mut pixels = Vec::with_capacity((cx1 - cx0) * (ry1 - ry0) as usize);
    for y in ry0 as usize..ry1 as usize {
        pixels.extend_from_slice(&img.as_raw()[y * row_px + cx0..y * row_px + cx1]);
    }
    let Some(crop) = GrayImage::from_raw(rx1 - rx0, ry1 - ry0, pixels) else {
        return out;
    };
    let (cw, ch) = (crop.width(), crop.height());
    for mut region in regions::<FINE_BOX_PX>(&crop, min_side) {
        let [x0, y0, x1, y1] = region.bbox;
        // Cut by the rectangle (where it is not the frame's border): not a whole outline.
        if (x0 == 0 && rx0 > 0)
            || (y0 == 0 && ry0 > 0)
            || (x1 + 1 == cw && rx1 < img.width())
            || (y1 + 1 == ch && ry1 < img.height())
        {
            continue;
        }
        region.bbox = [x0 + rx0, y0 + ry0, x1 + rx0, y1 + ry0];
        for row in &mut region.rows {
            *row = (row.0 + ry0, row.1 + rx0, row.2 + rx0);
        }
        let [x0, y0, x1, y1] = region.bbox;
        let middle = Vector2::new(f64::from(x0 + x1) / 2.0, f64::from(y0 + y1) / 2.0);
        if on_first(middle) || seen_before(region.bbox) {
            continue;
        }
        let (quad, outcome) = examine(img, &region, dicts, (w, h), min_side, max_side);
        if let CandidateOutcome::Decoded(m) = &outcome
            && on_first(m.corners.iter().sum::<Vector2<f64>>() / 4.0)
        {
            continue;
        }
        out.push(Candidate {
            box_px: FINE_BOX_PX,
            bbox: region.bbox,
            quad,
            pixels: region.pixels,
            outcome,
        });
    }
    out
}

/// How far around the first pass's markers the second pass of [`marker_candidates`] looks, in
/// multiples of a marker's extent (its bounding box's width and height): a marker beside it (two
/// squares' diagonal away, at most about 2 of its extents on a board OpenCV draws) and its whole
/// outline.
pub const ROI_REACH: f64 = 2.5;
/// Largest difference, px, of each side of two regions' bounding boxes for the second pass of
/// [`marker_candidates`] to take them for the same outline.
pub const SAME_REGION_PX: u32 = 2;

/// `[x0, y0, x1, y1]` of a quadrilateral.
fn bounds(q: &[Vector2<f64>; 4]) -> [f64; 4] {
    q.iter().fold(
        [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ],
        |b, p| [b[0].min(p.x), b[1].min(p.y), b[2].max(p.x), b[3].max(p.y)],
    )
}

/// Whether `p` lies inside the convex quadrilateral `q` (either orientation).
fn inside_convex(q: &[Vector2<f64>; 4], p: Vector2<f64>) -> bool {
    let s: [f64; 4] = std::array::from_fn(|k| cross(q[k], q[(k + 1) % 4], p));
    s.iter().all(|&v| v >= 0.0) || s.iter().all(|&v| v <= 0.0)
}

fn examine(
    img: &GrayImage,
    region: &Region,
    dicts: &[Dictionary],
    (w, h): (usize, usize),
    min_side: f64,
    max_side: f64,
) -> (Option<[Vector2<f64>; 4]>, CandidateOutcome) {
    let [x0, y0, x1, y1] = region.bbox;
    let (bw, bh) = (f64::from(x1 - x0 + 1), f64::from(y1 - y0 + 1));
    if bw.max(bh) < min_side || bw.max(bh) > max_side || (region.pixels as f64) < min_side * 2.0 {
        return (None, CandidateOutcome::Size);
    }
    // Touching the frame border: a marker cut by the frame cannot be read.
    if x0 == 0 || y0 == 0 || x1 as usize + 1 == w || y1 as usize + 1 == h {
        return (None, CandidateOutcome::FrameBorder);
    }
    let hl = simplify(region_hull(&region.rows), 0.7);
    let Some(quad) = largest_quad(&hl) else {
        return (None, CandidateOutcome::NotQuad);
    };
    let (ha, qa) = (polygon_area(&hl).abs(), polygon_area(&quad).abs());
    if qa < MIN_QUAD_FILL * ha || (region.pixels as f64) < 0.3 * qa {
        return (None, CandidateOutcome::NotQuad);
    }
    let sides = (0..4).map(|k| (quad[(k + 1) % 4] - quad[k]).norm());
    if sides.fold(f64::INFINITY, f64::min) < min_side {
        return (Some(quad), CandidateOutcome::Size);
    }
    // Hull order is counter-clockwise in a y-up frame: clockwise as seen in the image (y down).
    // Any start works; decoding finds the rotation.
    let mut miss = DecodeMiss::Geometry;
    for &dict in dicts {
        match decode(img, &quad, dict) {
            Ok(m) => return (Some(m.corners), CandidateOutcome::Decoded(m)),
            Err(e) => miss = e,
        }
    }
    (Some(quad), CandidateOutcome::NotDecoded(miss))
}

/// OpenCV board coordinates (mm, x right, y down from the board's top-left square corner) of a
/// marker's four corners (top left, top right, bottom right, bottom left).
fn marker_board_corners(face: &Face, ch: &Charuco, sq: (usize, usize)) -> [Vector2<f64>; 4] {
    let s = face.square_mm;
    let d = (s - ch.marker_mm) / 2.0;
    let (x, y) = (sq.0 as f64 * s + d, sq.1 as f64 * s + d);
    let m = ch.marker_mm;
    [
        Vector2::new(x, y),
        Vector2::new(x + m, y),
        Vector2::new(x + m, y + m),
        Vector2::new(x, y + m),
    ]
}

/// How far the bands of [`fit_in_gaps`] stay from the markers' edges as the markers predict them,
/// px: room for the prediction's error and the edges' blur. Measured (`charuco_eval`, 24 poses,
/// realistic / hard): 0.5 px 2300 / 511 corners, RMS 0.0205 / 0.0859 px; 1 px 2249 / 509, 0.0189 /
/// 0.0862; 1.5 px 2135 / 501, 0.0162 / 0.0846; no wrong label in any.
pub const GAP_MARGIN_PX: f64 = 1.0;

/// Fit the corner predicted at `p0` (`a`, `b` the image steps of a whole square) with the window of
/// a checkerboard corner, reaching [`refine::WINDOW`] of the way to the next corners along its
/// edges, but only the pixels within the white gaps beside its two lines
/// ([`refine::refine_near_border_in_bands`]): the gap is `gap` of a square wide (between a marker
/// and its square's sides), the bands reach [`GAP_MARGIN_PX`] less far from each line. Within
/// them the four squares are an X-junction along the whole of the edges; the markers' edges beyond
/// them, left out, do not bias the fit anyway, as they are point-symmetric about the corner (the
/// two markers diagonal to each other). `None` when the bands would be under a pixel wide or the fit
/// fails ([`fit_corner`], the window shrunk into the gap, is tried then).
///
/// Before (the shrunk window only), at grazing angles the gap is 2–4 px wide, the window as
/// narrow, and the blur takes all of it: the fit found no X-junction where two markers predict the
/// corner within 0.02–0.09 of a square (the pyCamSet cube photos). Measured against it: the cube
/// photos 2173 → 2179 of OpenCV 4.6's 2186 corners labelled (2411 → 2421 in all), the calibration
/// on them RMS 0.404 → 0.393 px; `charuco_eval` (24 poses) realistic 2070 → 2249 corners, RMS
/// 0.0322 → 0.0189 px, hard 260 → 509 corners, RMS 0.1688 → 0.0862 px, no wrong label.
fn fit_in_gaps(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
    gap: f64,
) -> Option<refine::Refined> {
    // A line's distance from the marker edge beside it, px: along the other step, `gap` of it,
    // measured across the line.
    let area = (a.x * b.y - a.y * b.x).abs();
    let band = [area / a.norm(), area / b.norm()].map(|h| gap * h - GAP_MARGIN_PX);
    if band.iter().any(|&w| !(w >= 1.0)) {
        return None;
    }
    refine::refine_near_border_in_bands(img, p0, a, b, band).ok()
}

/// Share of the fit window's half-extent by which [`fit_corner`] moves its start when the fit
/// from the markers' prediction finds no X-junction.
pub const RESTART_SHIFT: f64 = 0.3;

/// Fit the corner predicted at `p0` (steps `a`, `b` scaled to the white gap around it). The window
/// reaches within a pixel or so of the markers, so a prediction a pixel off — markers printed or
/// drawn a pixel away from where the board puts them, as OpenCV 4.6's `CharucoBoard.draw` does
/// at 32 px a square — brings a marker's edge into it and the fit finds no X-junction
/// ([`refine::RefineFailure::NotX`]) or is pulled away (`Moved`). The fit is then started again
/// from the eight points [`RESTART_SHIFT`] of the window's half-extent away along the steps (1 px
/// at 32 px a square with markers of 0.75 of a square), and the first that succeeds is taken: a fit
/// moves its corner at most [`refine::MAX_SHIFT`] of the steps from its start, so whatever it finds
/// lies within half a step (a twelfth of a square with such markers) of the prediction, where no
/// other corner is. Measured: OpenCV 4.6's 10 × 10 board 72 → 81 of 81 corners (at most 0.001 px
/// off); `charuco_eval` (24 poses) realistic 1881 → 1996 corners, RMS 0.0308 → 0.0315 px, hard
/// 251 → 257, 0.1703 → 0.1704 px, no wrong label; the pyCamSet cube photos 2230 → 2278 corners
/// and the pycalib wide-angle photos 1210 → 1211, of those OpenCV labels none labelled otherwise.
fn fit_corner(
    img: &GrayImage,
    p0: Vector2<f64>,
    a: Vector2<f64>,
    b: Vector2<f64>,
) -> Option<refine::Refined> {
    use refine::RefineFailure::{Moved, NotX};
    match refine::refine_near_border(img, p0, a, b) {
        Ok(fit) => return Some(fit),
        Err(NotX | Moved) => {}
        Err(_) => return None,
    }
    let (da, db) = (
        a * RESTART_SHIFT * refine::WINDOW,
        b * RESTART_SHIFT * refine::WINDOW,
    );
    [da + db, da - db, -da + db, -da - db, da, -da, db, -db]
        .into_iter()
        .find_map(|d| refine::refine_near_border(img, p0 + d, a, b).ok())
}

/// Detect the ChArUco faces of `rig` in a frame.
pub fn detect(img: &GrayImage, rig: &Rig) -> CharucoDetection {
    let mut dicts: Vec<Dictionary> = Vec::new();
    for f in &rig.faces {
        if let Some(ch) = &f.charuco
            && !dicts.iter().any(|d| d.bits == ch.dictionary.bits)
        {
            dicts.push(ch.dictionary);
        }
    }
    // One dictionary per marker size: the largest of that size in the rig (the smaller ones are
    // its first ids; a face's ids are checked against its own dictionary at validation).
    for d in &mut dicts {
        for f in &rig.faces {
            if let Some(ch) = &f.charuco
                && ch.dictionary.bits == d.bits
                && ch.dictionary.count > d.count
            {
                *d = ch.dictionary;
            }
        }
    }
    let mut out = CharucoDetection::default();
    if dicts.is_empty() {
        return out;
    }
    let found = find_markers(img, &dicts);
    // Ids on the rig: (bits, id) → (face, marker index); ids decoded twice are dropped.
    let mut markers: Vec<Marker> = Vec::new();
    let mut twice: Vec<(usize, u32)> = Vec::new();
    for m in found {
        if markers.iter().any(|o| o.bits == m.bits && o.id == m.id) {
            twice.push((m.bits, m.id));
        }
        markers.push(m);
    }
    markers.retain(|m| !twice.contains(&(m.bits, m.id)));
    for &(bits, id) in &twice {
        out.rejected.push(Rejection::frame(format!(
            "marker {id} ({bits}×{bits}) decoded twice in the frame; neither used"
        )));
    }
    markers.retain(|m| {
        rig.faces.iter().any(|f| {
            f.charuco
                .as_ref()
                .is_some_and(|c| c.dictionary.bits == m.bits && c.ids.contains(&m.id))
        })
    });
    for face in &rig.faces {
        let Some(ch) = &face.charuco else { continue };
        let Some(&dict) = dicts.iter().find(|d| d.bits == ch.dictionary.bits) else {
            continue;
        };
        markers.extend(predicted_markers(img, face, ch, dict, &markers, &twice));
    }
    for (fi, face) in rig.faces.iter().enumerate() {
        let Some(ch) = &face.charuco else { continue };
        if let Some(fd) = detect_face(img, face, fi, ch, &markers) {
            out.faces.push(fd);
        }
    }
    out.markers = markers;
    out
}

/// Largest distance, in cells of the `(n + 2)²` grid, of a marker `predicted_markers` decodes
/// from where its decoded neighbours predict each of its corners. A marker of the face in another
/// square lies a square (`(n + 2)` cells and the white gap) away; the prediction from a neighbour
/// two squares away is off by a fraction of a cell where a lens bends the face.
pub const MAX_PREDICTED_MARKER_SHIFT: f64 = 2.0;

/// The markers of `face` that the dark regions missed, read where the face's decoded markers put
/// them (OpenCV's `refineDetectedMarkers` does the like for boards). Per square of the face whose
/// marker is not decoded, beside a decoded diagonal neighbour (a marker labels corners only with
/// those) and with at least [`MIN_PREDICTING_MARKERS`] decoded markers within [`NEIGHBOUR_REACH`]
/// squares (the square with the most of them first): the homography fitted to
/// all their corners (least squares, [`homography_lsq`]) gives the square's outline; it is read as
/// [`decode`] reads a region's (its sides fitted to sub-pixel first, [`PREDICTED_EDGE_SAMPLES`]
/// lines a side), and if that misreads, through the predicted outline itself. A read is taken only
/// when it decodes, against the whole dictionary as any region's read, to that square's id in the
/// square's orientation, every corner within [`MAX_PREDICTED_MARKER_SHIFT`] cells of the
/// prediction: the bits any marker must have, at the one place the face allows them. A marker so
/// found lends its corners to the predictions of the squares around it; a square is read again
/// when more markers around it are decoded. `barred` holds ids decoded twice in the frame (not
/// used).
///
/// The regions miss markers whose outline does not come out as one quadrilateral: at a grazing
/// angle, two-and-a-half pixels a cell, the finer threshold splits a marker into two regions, and
/// where a face runs into a dark band beyond the board its outline is cut short; the fit of a
/// region's outline can also pull two corners a good part of a cell away (one side's edge found at
/// few of its lines), and the read then misses by a few bits (the pyCamSet cube photos: all seven
/// of OpenCV 4.6's corners that cubecal did not label).
fn predicted_markers(
    img: &GrayImage,
    face: &Face,
    ch: &Charuco,
    dict: Dictionary,
    markers: &[Marker],
    barred: &[(usize, u32)],
) -> Vec<Marker> {
    let (sx, sy) = (face.cols + 1, face.rows + 1);
    let n = dict.bits;
    let min_side = (n + 2) as f64 * MIN_CELL_PX;
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    let mut corners: Vec<Option<[Vector2<f64>; 4]>> = vec![None; sx * sy];
    let mut ids: Vec<Option<u32>> = vec![None; sx * sy];
    let mut any = false;
    for y in 0..sy {
        for x in 0..sx {
            let Some(&id) = Charuco::marker_index(face.cols, x, y).and_then(|k| ch.ids.get(k))
            else {
                continue;
            };
            ids[y * sx + x] = Some(id);
            if let Some(m) = markers.iter().find(|m| m.bits == n && m.id == id) {
                corners[y * sx + x] = Some(m.corners);
                any = true;
            }
        }
    }
    let mut out: Vec<Marker> = Vec::new();
    if !any {
        return out;
    }
    // The squares to read: markers not decoded, not barred.
    let open: Vec<usize> = (0..sx * sy)
        .filter(|&at| ids[at].is_some_and(|id| corners[at].is_none() && !barred.contains(&(n, id))))
        .collect();
    // The decoded markers within [`NEIGHBOUR_REACH`] of a square.
    fn near(
        corners: &[Option<[Vector2<f64>; 4]>],
        (sx, sy): (usize, usize),
        at: usize,
    ) -> impl Iterator<Item = (usize, usize)> + '_ {
        let (x, y) = (at % sx, at / sx);
        let r = NEIGHBOUR_REACH;
        (y.saturating_sub(r)..(y + r + 1).min(sy))
            .flat_map(move |v| (x.saturating_sub(r)..(x + r + 1).min(sx)).map(move |u| (u, v)))
            .filter(move |&(u, v)| corners[v * sx + u].is_some())
    }
    // Whether a marker diagonal to the square is decoded: the two share a corner, which the
    // square's marker, read, labels (a square without one waits until one is read).
    fn diagonal_decoded(
        corners: &[Option<[Vector2<f64>; 4]>],
        (sx, sy): (usize, usize),
        at: usize,
    ) -> bool {
        let (x, y) = (at % sx, at / sx);
        [(-1, -1), (1, -1), (-1, 1), (1, 1)]
            .iter()
            .any(
                |&(dx, dy)| match (x.checked_add_signed(dx), y.checked_add_signed(dy)) {
                    (Some(u), Some(v)) if u < sx && v < sy => corners[v * sx + u].is_some(),
                    _ => false,
                },
            )
    }
    // Per square, how many neighbours predicted it when it was last read (read again only when
    // more do).
    let mut tried = vec![0usize; sx * sy];
    loop {
        // The open square with the most decoded neighbours (the best prediction) first.
        let best = open
            .iter()
            .filter(|&&at| corners[at].is_none() && diagonal_decoded(&corners, (sx, sy), at))
            .map(|&at| (near(&corners, (sx, sy), at).count(), at))
            .filter(|&(count, at)| count >= MIN_PREDICTING_MARKERS && count > tried[at])
            .max_by_key(|&(count, at)| (count, std::cmp::Reverse(at)));
        let Some((count, at)) = best else {
            return out;
        };
        tried[at] = count;
        let (x, y) = (at % sx, at / sx);
        let Some(id) = ids[at] else { continue };
        let pairs: Vec<(Vector2<f64>, Vector2<f64>)> = near(&corners, (sx, sy), at)
            .flat_map(|(u, v)| {
                let c = corners[v * sx + u].into_iter().flatten();
                marker_board_corners(face, ch, (u, v)).into_iter().zip(c)
            })
            .collect();
        let board = marker_board_corners(face, ch, (x, y));
        let Some(hom) = homography_lsq(&pairs) else {
            continue;
        };
        let Some(pred) = board
            .iter()
            .map(|&b| apply(&hom, b))
            .collect::<Option<Vec<_>>>()
            .and_then(|v| <[Vector2<f64>; 4]>::try_from(v).ok())
        else {
            continue;
        };
        let sides = (0..4).map(|k| (pred[(k + 1) % 4] - pred[k]).norm());
        let side = sides.fold(f64::INFINITY, f64::min);
        if !(side >= min_side)
            || pred
                .iter()
                .any(|p| !(p.x >= 1.0 && p.y >= 1.0 && p.x <= w - 2.0 && p.y <= h - 2.0))
        {
            continue;
        }
        let centre = pred.iter().sum::<Vector2<f64>>() / 4.0;
        if markers
            .iter()
            .chain(&out)
            .any(|m| inside_convex(&m.corners, centre))
        {
            continue;
        }
        let tol = MAX_PREDICTED_MARKER_SHIFT * side / (n + 2) as f64;
        let expected =
            |m: &Marker| m.id == id && (0..4).all(|k| (m.corners[k] - pred[k]).norm() <= tol);
        // Through the fitted outline, as a region's; if that misreads, through the prediction
        // itself (its cells read already, for the fit's level).
        let cells = n + 2;
        let Ok(first) = read_cells(img, &pred, cells) else {
            continue;
        };
        let fitted = fit_outline::<PREDICTED_EDGE_SAMPLES>(img, &pred, &first, cells)
            .and_then(|(q, read)| match_cells(read, &q, dict).ok())
            .filter(expected);
        let found = fitted.or_else(|| match_cells(first, &pred, dict).ok().filter(expected));
        if let Some(m) = found {
            tracing::debug!(id, "marker read where its neighbours predict it");
            corners[at] = Some(m.corners);
            out.push(m);
        }
    }
}

/// How far, in squares along a row or column, the decoded markers reach whose corners give
/// `predicted_markers` a marker's outline: two, the markers diagonal to it and the next along its
/// row and column, and those beyond them.
pub const NEIGHBOUR_REACH: usize = 2;

/// Fewest decoded markers within [`NEIGHBOUR_REACH`] for `predicted_markers` to read a square: one
/// marker's homography, carried a square or two beyond it, misses by a cell or more at a grazing
/// angle (the pyCamSet cube photos: 4 px at 2.7 px a cell), and a corner needs two markers anyway.
pub const MIN_PREDICTING_MARKERS: usize = 2;

/// The homography taking each pair's first point to its second, least squares
/// ([`homography_h33`] on points moved to their centroid and scaled to a mean distance of √2);
/// `None` for fewer than four pairs or a degenerate fit.
fn homography_lsq(pairs: &[(Vector2<f64>, Vector2<f64>)]) -> Option<Matrix3<f64>> {
    if pairs.len() < 4 {
        return None;
    }
    let side = |k: usize| -> Vec<Vector2<f64>> {
        pairs
            .iter()
            .map(|p| if k == 0 { p.0 } else { p.1 })
            .collect()
    };
    let ta = normalize_2d(&side(0)).ok()?;
    let tb = normalize_2d(&side(1)).ok()?;
    let hn = homography_h33(
        pairs
            .iter()
            .map(|&(a, b)| Some((apply(&ta, a)?, apply(&tb, b)?)))
            .collect::<Option<Vec<_>>>()?,
    )?;
    let h = tb.try_inverse()? * hn * ta;
    (h[(2, 2)].abs() > 1e-12).then(|| h / h[(2, 2)])
}

fn detect_face(
    img: &GrayImage,
    face: &Face,
    fi: usize,
    ch: &Charuco,
    markers: &[Marker],
) -> Option<FaceDetection> {
    let (sx, sy) = (face.cols + 1, face.rows + 1);
    // Per OpenCV square: the decoded marker's homography from board mm to image px.
    let mut homs: Vec<Option<Matrix3<f64>>> = vec![None; sx * sy];
    let mut contrast = Vec::new();
    for y in 0..sy {
        for x in 0..sx {
            let Some(id) = Charuco::marker_index(face.cols, x, y).and_then(|k| ch.ids.get(k))
            else {
                continue;
            };
            let Some(m) = markers
                .iter()
                .find(|m| m.bits == ch.dictionary.bits && m.id == *id)
            else {
                continue;
            };
            homs[y * sx + x] = homography(&marker_board_corners(face, ch, (x, y)), &m.corners);
            contrast.push(m.contrast);
        }
    }
    let s = face.square_mm;
    // The white gap between a marker and its square's sides, in squares.
    let gap_frac = (s - ch.marker_mm) / 2.0 / s;
    // The fallback fit's window (half-extent refine::WINDOW of the steps given) must stay within
    // that gap around the corner: scale the steps to it, less a fiftieth of a square for the blur.
    let gap = (gap_frac - 0.02).max(0.02);
    let scale = gap / refine::WINDOW;
    let mut corners = Vec::new();
    for cy in 0..face.rows {
        for cx in 0..face.cols {
            let p = Vector2::new((cx + 1) as f64 * s, (cy + 1) as f64 * s);
            let mut preds: Vec<(Vector2<f64>, Vector2<f64>, Vector2<f64>)> = Vec::new();
            for (x, y) in [(cx, cy), (cx + 1, cy), (cx, cy + 1), (cx + 1, cy + 1)] {
                if let Some(h) = homs[y * sx + x] {
                    let (Some(c), Some(ax), Some(ay)) = (
                        apply(&h, p),
                        apply(&h, p + Vector2::new(s, 0.0)),
                        apply(&h, p + Vector2::new(0.0, s)),
                    ) else {
                        continue;
                    };
                    preds.push((c, ax - c, ay - c));
                }
            }
            if preds.len() < 2 {
                continue;
            }
            let (c0, c1) = (preds[0].0, preds[1].0);
            let a = (preds[0].1 + preds[1].1) / 2.0;
            // cubecal's rows run up the face: its row step is OpenCV's −y.
            let b = -(preds[0].2 + preds[1].2) / 2.0;
            let square_px = a.norm().min(b.norm());
            if (c0 - c1).norm() > MAX_PREDICTION_DISAGREEMENT * square_px {
                continue;
            }
            let p0 = (c0 + c1) / 2.0;
            let Some(fit) = fit_in_gaps(img, p0, a, b, gap_frac)
                .or_else(|| fit_corner(img, p0, a * scale, b * scale))
            else {
                continue;
            };
            let (row, col) = (face.rows - 1 - cy, cx);
            corners.push(LabelledCorner {
                row,
                col,
                xyz: face.corner_xyz(row, col),
                uv: fit.uv,
                sigma_px: fit.sigma_px,
                cov: fit.cov,
                edge_px: fit.edge_width,
            });
        }
    }
    if corners.is_empty() {
        return None;
    }
    corners.sort_by_key(|c| (c.row, c.col));
    Some(FaceDetection {
        face: fi,
        corners,
        colour_contrast: contrast.iter().sum::<f64>() / contrast.len().max(1) as f64,
        ambiguous_pose: None,
        identity: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A frame of blobs (dark discs and rings on light, some touching the border) with noise, of
    /// odd sides so that no window fits it evenly.
    fn blobs(w: u32, h: u32, seed: u64) -> GrayImage {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let discs: Vec<(f64, f64, f64, f64)> = (0..40)
            .map(|_| {
                (
                    rng.random_range(-5.0..f64::from(w) + 5.0),
                    rng.random_range(-5.0..f64::from(h) + 5.0),
                    rng.random_range(2.0..14.0),
                    rng.random_range(0.0..0.7),
                )
            })
            .collect();
        GrayImage::from_fn(w, h, |x, y| {
            let (x, y) = (f64::from(x), f64::from(y));
            let dark = discs.iter().any(|&(cx, cy, r, hole)| {
                let d = ((x - cx).powi(2) + (y - cy).powi(2)).sqrt();
                d < r && d >= hole * r
            });
            let v = if dark { 60.0 } else { 200.0 } + rng.random_range(-12.0..12.0);
            image::Luma([v as u8])
        })
    }

    /// The threshold by its definition: the clipped windows' sums taken pixel by pixel.
    fn threshold_direct(img: &GrayImage, box_px: usize) -> Vec<u8> {
        let (w, h) = (img.width() as i64, img.height() as i64);
        let r = (box_px / 2) as i64;
        let at = |x: i64, y: i64| i64::from(img.get_pixel(x as u32, y as u32).0[0]);
        let sum = |x: i64, y: i64, r: i64| {
            let (mut s, mut n) = (0, 0);
            for yy in (y - r).max(0)..(y + r + 1).min(h) {
                for xx in (x - r).max(0)..(x + r + 1).min(w) {
                    s += at(xx, yy);
                    n += 1;
                }
            }
            (s, n)
        };
        let off = i64::from(THRESHOLD_OFFSET);
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let ((t, n3), (c, nb)) = (sum(x, y, 1), sum(x, y, r));
                out.push(u8::from(t * nb < n3 * (c - off * nb)));
            }
        }
        out
    }

    #[test]
    fn threshold_matches_its_definition_to_the_pixel() {
        for (w, h, seed) in [(97, 61, 1), (40, 33, 2), (16, 9, 3), (7, 5, 4)] {
            let img = blobs(w, h, seed);
            let mut fast = Vec::new();
            threshold::<BOX_PX>(&img, |_, row| fast.extend_from_slice(row));
            let mut fine = Vec::new();
            threshold::<FINE_BOX_PX>(&img, |_, row| fine.extend_from_slice(row));
            for (fast, box_px) in [(fast, BOX_PX), (fine, FINE_BOX_PX)] {
                let direct = threshold_direct(&img, box_px);
                let differ = fast.iter().zip(&direct).filter(|(a, b)| a != b).count();
                let dark = direct.iter().filter(|&&d| d == 1).count();
                assert!(dark > 0, "{w}×{h}, box {box_px}: no dark pixel to compare");
                assert_eq!(differ, 0, "{w}×{h}, box {box_px}: {differ} pixels differ");
            }
        }
    }

    /// A region as the flood fill finds it: pixel count, bounding box, per row (y, first, last).
    type RegionRef = (usize, [u32; 4], Vec<(u32, u32, u32)>);

    #[test]
    fn run_labelling_and_row_hull_match_flood_fill_and_sorted_hull() {
        let img = blobs(181, 127, 5);
        let (w, h) = (img.width() as usize, img.height() as usize);
        let mut dark = Vec::new();
        threshold::<BOX_PX>(&img, |_, row| dark.extend_from_slice(row));
        // Reference: 4-connected flood fill from each unvisited dark pixel in raster order.
        let mut seen = vec![false; w * h];
        let mut reference: Vec<RegionRef> = Vec::new();
        for start in 0..w * h {
            if dark[start] == 0 || seen[start] {
                continue;
            }
            seen[start] = true;
            let mut stack = vec![start];
            let mut pixels = Vec::new();
            while let Some(p) = stack.pop() {
                pixels.push(p);
                let (x, y) = (p % w, p / w);
                let mut near = Vec::new();
                if x > 0 {
                    near.push(p - 1);
                }
                if x + 1 < w {
                    near.push(p + 1);
                }
                if y > 0 {
                    near.push(p - w);
                }
                if y + 1 < h {
                    near.push(p + w);
                }
                for q in near {
                    if dark[q] == 1 && !seen[q] {
                        seen[q] = true;
                        stack.push(q);
                    }
                }
            }
            let xs = pixels.iter().map(|p| (p % w) as u32);
            let ys = pixels.iter().map(|p| (p / w) as u32);
            let bbox = [
                xs.clone().min().unwrap_or(0),
                ys.clone().min().unwrap_or(0),
                xs.max().unwrap_or(0),
                ys.max().unwrap_or(0),
            ];
            let rows = (bbox[1]..=bbox[3])
                .map(|y| {
                    let on: Vec<u32> = pixels
                        .iter()
                        .filter(|&&p| (p / w) as u32 == y)
                        .map(|&p| (p % w) as u32)
                        .collect();
                    (
                        y,
                        on.iter().copied().min().unwrap_or(0),
                        on.iter().copied().max().unwrap_or(0),
                    )
                })
                .collect();
            reference.push((pixels.len(), bbox, rows));
        }
        let found = regions::<BOX_PX>(&img, 0.0);
        assert!(found.len() > 20, "only {} regions", found.len());
        assert_eq!(found.len(), reference.len(), "regions");
        for (r, (pixels, bbox, rows)) in found.iter().zip(&reference) {
            assert_eq!((r.pixels, r.bbox, &r.rows), (*pixels, *bbox, rows));
            // The hull from the rows: the same vertices in the same order as from every pixel
            // edge, sorted.
            assert_eq!(
                region_hull(&r.rows),
                hull(row_edge_points(rows)),
                "region at {bbox:?}"
            );
        }
    }
}
