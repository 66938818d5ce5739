//! Overlays: draw what the detector found on top of the frame, for a person to check at a glance.
//!
//! Each detected face gets its own colour ([`face_colour`], by the face's index in the rig, so a face
//! has the same colour in every overlay of that rig). For each face the overlay shows
//! - lines joining neighbouring corners along rows and columns (the lattice as labelled),
//! - a small diagonal cross at every corner,
//! - a filled square at the face's corner `(0, 0)` and a thick arrow from it toward `(0, 1)`, so that a
//!   wrong orientation or a transposed labelling is visible.
//!
//! Drawing is by sampled segments in pixel-centre coordinates (integer coordinates are pixel centres,
//! see the crate docs): a point `(u, v)` colours pixel `(⌊u + ½⌋, ⌊v + ½⌋)`. Segments are clipped to
//! the image before sampling, so corners far outside the frame (or non-finite ones, which are skipped)
//! cost nothing and never panic.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use image::{GrayImage, Rgb, RgbImage};
use nalgebra::Vector2;

use super::FrameDetection;
use crate::rig::Rig;

/// Face colours, in rig face order (wrapping around): saturated hues that stand out from a grey frame
/// and from each other.
pub const PALETTE: [[u8; 3]; 8] = [
    [230, 25, 75],  // red
    [60, 180, 75],  // green
    [0, 130, 200],  // blue
    [245, 130, 48], // orange
    [145, 30, 180], // purple
    [70, 240, 240], // cyan
    [240, 50, 230], // magenta
    [210, 245, 60], // lime
];

/// Half the arm length of the cross drawn at every corner (px).
pub const CROSS_HALF_PX: f64 = 3.0;
/// Half the side of the filled square marking corner `(0, 0)` (px).
pub const ORIGIN_HALF_PX: i64 = 4;
/// The orientation arrow reaches this fraction of the way from corner `(0, 0)` toward `(0, 1)`.
pub const ARROW_FRACTION: f64 = 0.7;

/// Colour of rejected grids (dashed) and their reasons.
pub const REJECTED: [u8; 3] = [255, 255, 255];
/// Length of a dash (and of the gap after it) of a rejected grid's lines (px).
pub const DASH_PX: f64 = 6.0;
/// Longest reason written beside a rejected grid (characters; the full reason is in the text and
/// JSON output).
pub const SHORT_REASON_CHARS: usize = 48;
/// Text height of the legend and of the reasons (px).
pub const TEXT_PX: u32 = 14;

/// Errors writing an overlay file.
#[derive(Debug, thiserror::Error)]
pub enum OverlayError {
    #[error("cannot encode overlay {path} as PNG")]
    Encode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot draw the overlay's text: {reason}")]
    Text { reason: String },
    #[error("cannot write overlay {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl OverlayError {
    /// The process exit code for this error (see [`crate::exit`]). Like every other failure to write
    /// a result file in cubecal, this is [`crate::exit::INTERNAL`].
    pub fn exit_code(&self) -> u8 {
        match self {
            OverlayError::Encode { .. }
            | OverlayError::Write { .. }
            | OverlayError::Text { .. } => crate::exit::INTERNAL,
        }
    }
}

/// The colour of rig face `face` in overlays.
pub fn face_colour(face: usize) -> Rgb<u8> {
    Rgb(PALETTE[face % PALETTE.len()])
}

/// An RGB copy of `img` with the faces of `det` drawn on it (see the module docs).
pub fn draw(img: &GrayImage, det: &FrameDetection, rig: &Rig) -> RgbImage {
    // The frame in grey, converted in one pass over its bytes (pixel by pixel, with a bounds check
    // each, it was a third of a thumbnail's drawing).
    let (w, h) = img.dimensions();
    let grey: Vec<u8> = (img.as_raw().iter())
        .take(w as usize * h as usize)
        .flat_map(|&g| [g, g, g])
        .collect();
    let mut out = RgbImage::from_raw(w, h, grey).unwrap_or_else(|| RgbImage::new(w, h));
    for face in &det.faces {
        let colour = face_colour(face.face);
        let at: HashMap<(usize, usize), Vector2<f64>> = face
            .corners
            .iter()
            .map(|c| ((c.row, c.col), c.uv))
            .collect();
        // The face's grid size comes from the rig; fall back to the corners' own extent for a face
        // index the rig does not have (a detection from another rig).
        let (rows, cols) = match rig.faces.get(face.face) {
            Some(f) => (f.rows, f.cols),
            None => at
                .keys()
                .fold((0, 0), |(r, c), &(rr, cc)| (r.max(rr + 1), c.max(cc + 1))),
        };
        for r in 0..rows {
            for c in 0..cols {
                let Some(&p) = at.get(&(r, c)) else {
                    continue;
                };
                for next in [(r, c + 1), (r + 1, c)] {
                    if let Some(&q) = at.get(&next) {
                        segment(&mut out, p, q, 0, colour);
                    }
                }
            }
        }
        for &p in at.values() {
            let (a, b) = (
                Vector2::new(CROSS_HALF_PX, CROSS_HALF_PX),
                Vector2::new(CROSS_HALF_PX, -CROSS_HALF_PX),
            );
            segment(&mut out, p - a, p + a, 0, colour);
            segment(&mut out, p - b, p + b, 0, colour);
        }
        if let Some(&origin) = at.get(&(0, 0)) {
            stamp(&mut out, origin, ORIGIN_HALF_PX, colour);
            if let Some(&next) = at.get(&(0, 1)) {
                arrow(
                    &mut out,
                    origin,
                    origin + (next - origin) * ARROW_FRACTION,
                    colour,
                );
            }
        }
    }
    out
}

/// The first clause of a rejection's reason, at most [`SHORT_REASON_CHARS`] characters.
pub fn short_reason(reason: &str) -> String {
    let first = reason
        .split(['(', ';', ':'])
        .next()
        .unwrap_or(reason)
        .trim();
    if first.chars().count() <= SHORT_REASON_CHARS {
        first.to_string()
    } else {
        let cut: String = first.chars().take(SHORT_REASON_CHARS - 1).collect();
        format!("{cut}…")
    }
}

/// [`draw`], plus every rejected grid of `det` drawn dashed in [`REJECTED`] with its number and
/// short reason beside it, and a legend in the top left corner: every face of the rig in its colour
/// (with its corner count when found) and the numbered reasons of the rejected grids.
pub fn draw_annotated(
    img: &GrayImage,
    det: &FrameDetection,
    rig: &Rig,
) -> Result<RgbImage, OverlayError> {
    use plotters::prelude::*;

    let mut out = draw(img, det, rig);
    let white = Rgb(REJECTED);
    let mut labels: Vec<(Vector2<f64>, String)> = Vec::new();
    for (k, r) in det.rejected.iter().enumerate() {
        if r.corners.is_empty() {
            continue;
        }
        let at: HashMap<(usize, usize), Vector2<f64>> =
            r.corners.iter().map(|c| ((c.row, c.col), c.uv)).collect();
        for (&(row, col), &p) in &at {
            for next in [(row, col + 1), (row + 1, col)] {
                if let Some(&q) = at.get(&next) {
                    dashed(&mut out, p, q, white);
                }
            }
            stamp(&mut out, p, 1, white);
        }
        // The reason's number goes next to the grid's top-left-most corner.
        let anchor = r
            .corners
            .iter()
            .map(|c| c.uv)
            .filter(|p| p.x.is_finite() && p.y.is_finite())
            .min_by(|a, b| (a.x + a.y).total_cmp(&(b.x + b.y)));
        if let Some(p) = anchor {
            labels.push((p, format!("#{}", k + 1)));
        }
    }
    register_font()?;
    let (w, h) = out.dimensions();
    let mut buf = out.into_raw();
    {
        let text_err = |e: &dyn std::fmt::Display| OverlayError::Text {
            reason: e.to_string(),
        };
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let size = TEXT_PX as i32;
        let font = |c: [u8; 3]| {
            ("sans-serif", size)
                .into_font()
                .color(&RGBColor(c[0], c[1], c[2]))
        };
        for (p, text) in &labels {
            let (x, y) = (p.x.round() as i32 - 2 * size, p.y.round() as i32 - size);
            root.draw(&Text::new(text.clone(), (x, y), font(REJECTED)))
                .map_err(|e| text_err(&e))?;
        }
        // Legend: faces, then the numbered reasons, on a dark band for contrast.
        let mut lines: Vec<([u8; 3], String)> = rig
            .faces
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let n: usize = det
                    .faces
                    .iter()
                    .filter(|d| d.face == i)
                    .map(|d| d.corners.len())
                    .sum();
                let text = if n > 0 {
                    format!("■ {} ({n} corners)", f.name)
                } else {
                    format!("■ {} (not found)", f.name)
                };
                (face_colour(i).0, text)
            })
            .collect();
        for (k, r) in det.rejected.iter().enumerate() {
            lines.push((
                REJECTED,
                format!("#{} rejected: {}", k + 1, short_reason(&r.reason)),
            ));
        }
        let line_h = size + 4;
        let width = lines
            .iter()
            .map(|l| l.1.chars().count() as i32 * size * 6 / 10)
            .max()
            .unwrap_or(0)
            + 8;
        root.draw(&Rectangle::new(
            [(0, 0), (width, line_h * lines.len() as i32 + 10)],
            RGBColor(0, 0, 0).mix(0.6).filled(),
        ))
        .map_err(|e| text_err(&e))?;
        for (i, (c, text)) in lines.iter().enumerate() {
            root.draw(&Text::new(
                text.clone(),
                (4, 5 + line_h * i as i32),
                font(*c),
            ))
            .map_err(|e| text_err(&e))?;
        }
        root.present().map_err(|e| text_err(&e))?;
    }
    RgbImage::from_raw(w, h, buf).ok_or_else(|| OverlayError::Text {
        reason: "the drawing buffer changed size".into(),
    })
}

/// Register the embedded DejaVu Sans as plotters' `sans-serif` (once per process; the report's
/// plots register the same font under the same name).
fn register_font() -> Result<(), OverlayError> {
    static DONE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font(
            "sans-serif",
            plotters::style::FontStyle::Normal,
            dejavu::sans::regular(),
        )
        .is_ok()
    });
    ok.then_some(()).ok_or_else(|| OverlayError::Text {
        reason: "the embedded DejaVu Sans font could not be parsed".into(),
    })
}

/// A dashed 1 px segment `a → b` ([`DASH_PX`] on, [`DASH_PX`] off), clipped to the image.
fn dashed(img: &mut RgbImage, a: Vector2<f64>, b: Vector2<f64>, colour: Rgb<u8>) {
    let lo = Vector2::new(-1.0, -1.0);
    let hi = Vector2::new(f64::from(img.width()) + 1.0, f64::from(img.height()) + 1.0);
    let Some((a, b)) = clip(a, b, lo, hi) else {
        return;
    };
    let len = (b - a).norm();
    let n = (len * 2.0).ceil().max(1.0) as usize;
    for i in 0..=n {
        let t = i as f64 / n as f64;
        if (t * len).rem_euclid(2.0 * DASH_PX) < DASH_PX {
            stamp(img, a + (b - a) * t, 0, colour);
        }
    }
}

/// Encode `overlay` as PNG and write it to `path` atomically (temporary file, then rename).
pub fn write_png(overlay: &RgbImage, path: &Path) -> Result<(), OverlayError> {
    let mut bytes = Vec::new();
    overlay
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|source| OverlayError::Encode {
            path: path.to_path_buf(),
            source,
        })?;
    crate::rig::write_atomic(path, &bytes).map_err(|source| OverlayError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// The pixel whose area contains `p` (pixel-centre convention). `p` must be finite and, after
/// clipping, within a few pixels of the image, so the conversion cannot overflow.
fn pixel_of(p: Vector2<f64>) -> (i64, i64) {
    ((p.x + 0.5).floor() as i64, (p.y + 0.5).floor() as i64)
}

/// Colour the `(2·half + 1)²` pixels centred on the pixel containing `p`, where they are in the image.
fn stamp(img: &mut RgbImage, p: Vector2<f64>, half: i64, colour: Rgb<u8>) {
    if !(p.x.is_finite() && p.y.is_finite()) {
        return;
    }
    let margin = half as f64 + 1.0;
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    if p.x < -margin || p.y < -margin || p.x > w + margin || p.y > h + margin {
        return;
    }
    let (x0, y0) = pixel_of(p);
    for y in y0 - half..=y0 + half {
        for x in x0 - half..=x0 + half {
            if x >= 0 && y >= 0 && x < i64::from(img.width()) && y < i64::from(img.height()) {
                img.put_pixel(x as u32, y as u32, colour);
            }
        }
    }
}

/// Clip the segment `a → b` to the axis-aligned box `[lo, hi]²` (Liang–Barsky); `None` if it misses.
fn clip(
    a: Vector2<f64>,
    b: Vector2<f64>,
    lo: Vector2<f64>,
    hi: Vector2<f64>,
) -> Option<(Vector2<f64>, Vector2<f64>)> {
    if !(a.iter().chain(b.iter()).all(|v| v.is_finite())) {
        return None;
    }
    let d = b - a;
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-d.x, a.x - lo.x),
        (d.x, hi.x - a.x),
        (-d.y, a.y - lo.y),
        (d.y, hi.y - a.y),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    // Far-away endpoints lose precision in `a + d·t`: clamp, so that the result is in the box.
    let inside = |p: Vector2<f64>| Vector2::new(p.x.clamp(lo.x, hi.x), p.y.clamp(lo.y, hi.y));
    (t0 <= t1).then(|| (inside(a + d * t0), inside(a + d * t1)))
}

/// A segment `a → b` of width `2·half + 1` px, sampled every half pixel after clipping to the image.
fn segment(img: &mut RgbImage, a: Vector2<f64>, b: Vector2<f64>, half: i64, colour: Rgb<u8>) {
    let margin = half as f64 + 1.0;
    let lo = Vector2::new(-margin, -margin);
    let hi = Vector2::new(
        f64::from(img.width()) + margin,
        f64::from(img.height()) + margin,
    );
    let Some((a, b)) = clip(a, b, lo, hi) else {
        return;
    };
    let n = ((b - a).norm() * 2.0).ceil().max(1.0) as usize;
    for i in 0..=n {
        stamp(img, a + (b - a) * (i as f64 / n as f64), half, colour);
    }
}

/// A 3 px wide arrow from `from` to `tip` with a two-stroke head.
fn arrow(img: &mut RgbImage, from: Vector2<f64>, tip: Vector2<f64>, colour: Rgb<u8>) {
    let d = tip - from;
    let len = d.norm();
    if !(len > 0.0 && len.is_finite()) {
        return;
    }
    segment(img, from, tip, 1, colour);
    let back = -d / len * (len * 0.35).clamp(4.0, 12.0);
    for angle in [0.5f64, -0.5] {
        let (s, c) = angle.sin_cos();
        let side = Vector2::new(c * back.x - s * back.y, s * back.x + c * back.y);
        segment(img, tip, tip + side, 1, colour);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::detect::label::{FaceDetection, LabelledCorner};

    const RIG: &str = r#"
        name = "two-faces"
        units = "mm"
        [[faces]]
        name = "a"
        cols = 3
        rows = 2
        square_mm = 10.0
        origin = [0, 0, 0]
        col_dir = [1, 0, 0]
        row_dir = [0, 1, 0]
        [[faces]]
        name = "b"
        cols = 3
        rows = 2
        square_mm = 10.0
        origin = [0, 0, 100]
        col_dir = [1, 0, 0]
        row_dir = [0, 1, 0]
    "#;

    fn rig() -> Rig {
        Rig::from_toml_str(RIG, "test.toml").unwrap().0
    }

    /// A `rows × cols` face whose corner `(r, c)` is at `origin + (c·step, r·step)`.
    fn face(face: usize, origin: [f64; 2], step: f64) -> FaceDetection {
        let corners = (0..2)
            .flat_map(|r| (0..3).map(move |c| (r, c)))
            .map(|(r, c)| LabelledCorner {
                row: r,
                col: c,
                xyz: nalgebra::Vector3::zeros(),
                uv: Vector2::new(origin[0] + c as f64 * step, origin[1] + r as f64 * step),
                sigma_px: 0.01,
                cov: nalgebra::Matrix2::from_diagonal_element(1e-4),
                edge_px: 1.0,
            })
            .collect();
        FaceDetection {
            face,
            corners,
            colour_contrast: 100.0,
            ambiguous_pose: None,
            identity: None,
        }
    }

    fn frame(w: u32, h: u32, faces: Vec<FaceDetection>) -> (GrayImage, FrameDetection) {
        let img = GrayImage::from_pixel(w, h, image::Luma([128]));
        let det = FrameDetection {
            width: w,
            height: h,
            faces,
            rejected: Vec::new(),
        };
        (img, det)
    }

    #[test]
    fn rejected_grids_are_dashed_with_their_number_and_the_legend_names_the_faces() {
        use crate::detect::label::{GridCorner, Rejection};
        let (img, mut det) = frame(400, 300, vec![face(1, [300.0, 200.0], 20.0)]);
        // A 2×3 rejected grid, rows 40 px apart, from (100, 150).
        det.rejected.push(Rejection {
            reason: "incomplete grid (5 of 2×3 corners); not placed on the rig: because".into(),
            corners: (0..2)
                .flat_map(|r| (0..3).map(move |c| (r, c)))
                .map(|(row, col)| GridCorner {
                    row,
                    col,
                    uv: Vector2::new(100.0 + 40.0 * col as f64, 150.0 + 40.0 * row as f64),
                })
                .collect(),
        });
        let out = draw_annotated(&img, &det, &rig()).unwrap();
        let white = |x: u32, y: u32| out.get_pixel(x, y).0 == REJECTED;
        // Along the first row (y = 150) from x = 100: dashes of DASH_PX on and off.
        let on: Vec<bool> = (100..180).map(|x| white(x, 150)).collect();
        let lit = on.iter().filter(|&&b| b).count();
        assert!((30..=56).contains(&lit), "{lit} of 80 px lit");
        assert!(on[2] && !on[9] && on[14], "{on:?}");
        // The found face keeps its colour; the legend (top left) has both face colours in it.
        assert_eq!(*out.get_pixel(300, 200), face_colour(1));
        let legend = |c: Rgb<u8>| {
            (0..60).any(|y| {
                (0..200).any(|x| {
                    let p = out.get_pixel(x, y).0;
                    p.iter()
                        .zip(c.0)
                        .all(|(a, b)| (i32::from(*a) - i32::from(b)).abs() < 40)
                })
            })
        };
        assert!(legend(face_colour(0)) && legend(face_colour(1)));
        assert_eq!(short_reason(&det.rejected[0].reason), "incomplete grid");
    }

    #[test]
    fn grey_frame_without_faces_is_copied_unchanged() {
        let (img, det) = frame(40, 30, Vec::new());
        let out = draw(&img, &det, &rig());
        assert_eq!(out.dimensions(), (40, 30));
        assert!(out.pixels().all(|p| p.0 == [128, 128, 128]));
    }

    #[test]
    fn segments_markers_and_crosses_have_the_face_colour() {
        let (img, det) = frame(
            200,
            120,
            vec![face(0, [20.0, 20.0], 30.0), face(1, [20.0, 80.0], 30.0)],
        );
        let out = draw(&img, &det, &rig());
        let (a, b) = (face_colour(0), face_colour(1));
        assert_ne!(a, b);
        // Along row 0 of face 0, between corners (0, 1) and (0, 2): pixel centres on the line y = 20.
        for x in 55..=75 {
            assert_eq!(*out.get_pixel(x, 20), a, "x = {x}");
        }
        // Along column 2 of face 0, x = 80, between rows 0 and 1 (y 20 → 50).
        for y in 25..=45 {
            assert_eq!(*out.get_pixel(80, y), a, "y = {y}");
        }
        // Face 1's row 1 (y = 110) in its own colour.
        assert_eq!(*out.get_pixel(65, 110), b);
        // Filled square at (0, 0) of face 0: the whole 9×9 block around (20, 20).
        for y in 16..=24 {
            for x in 16..=24 {
                assert_eq!(*out.get_pixel(x, y), a, "({x}, {y})");
            }
        }
        // Diagonal cross arm at corner (1, 1) of face 0, (50, 50): pixel (52, 52) is on it and on no
        // grid line.
        assert_eq!(*out.get_pixel(52, 52), a);
        // The orientation arrow is 3 px wide along row 0: a pixel one row below the grid line, near
        // the origin, is coloured; the same offset near corner (0, 2) is not.
        assert_eq!(*out.get_pixel(33, 21), a);
        assert_eq!(*out.get_pixel(70, 21), Rgb([128, 128, 128]));
        // Far from everything, the grey frame shows through.
        assert_eq!(*out.get_pixel(150, 60), Rgb([128, 128, 128]));
    }

    #[test]
    fn corners_outside_the_image_or_not_finite_do_not_panic() {
        for (origin, step) in [
            ([-50.0, -50.0], 40.0),
            ([190.0, 110.0], 25.0),
            ([1e12, -1e12], 1e11),
            ([-1e300, 1e300], 1e299),
            ([f64::NAN, 5.0], 10.0),
            ([5.0, f64::INFINITY], 10.0),
            ([0.0, 0.0], 0.0),
        ] {
            let (img, det) = frame(100, 60, vec![face(0, origin, step)]);
            let out = draw(&img, &det, &rig());
            assert_eq!(out.dimensions(), (100, 60));
        }
        // A 1×1 frame with a face around it.
        let (img, det) = frame(1, 1, vec![face(1, [-1.0, -1.0], 1.0)]);
        let out = draw(&img, &det, &rig());
        assert_eq!(out.dimensions(), (1, 1));
    }

    #[test]
    fn a_segment_crossing_the_image_is_drawn_only_where_it_is_inside() {
        let mut img = RgbImage::from_pixel(10, 10, Rgb([0, 0, 0]));
        let red = Rgb([255, 0, 0]);
        segment(
            &mut img,
            Vector2::new(-1e9, 4.0),
            Vector2::new(1e9, 4.0),
            0,
            red,
        );
        for x in 0..10 {
            assert_eq!(*img.get_pixel(x, 4), red);
            assert_eq!(*img.get_pixel(x, 3), Rgb([0, 0, 0]));
            assert_eq!(*img.get_pixel(x, 5), Rgb([0, 0, 0]));
        }
        // The main diagonal from far-away endpoints.
        let mut img = RgbImage::from_pixel(10, 10, Rgb([0, 0, 0]));
        segment(
            &mut img,
            Vector2::new(-1e12, -1e12),
            Vector2::new(1e12, 1e12),
            0,
            red,
        );
        for k in 0..10 {
            assert_eq!(*img.get_pixel(k, k), red);
        }
        // So far away that `a + d·t` loses all precision: whatever is drawn, it ends (the clipped
        // endpoints are clamped into the image) and does not panic.
        segment(
            &mut img,
            Vector2::new(-1e300, -3e299),
            Vector2::new(1e300, 2e300),
            0,
            red,
        );
    }

    #[test]
    fn pixel_centre_convention() {
        // (2.49, 2.5) lies in pixel (2, 3): pixel 2 covers [1.5, 2.5).
        assert_eq!(pixel_of(Vector2::new(2.49, 2.5)), (2, 3));
        assert_eq!(pixel_of(Vector2::new(-0.5, -0.51)), (0, -1));
    }

    #[test]
    fn write_png_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("o.png");
        let img = RgbImage::from_fn(7, 5, |x, y| Rgb([x as u8, y as u8, 9]));
        write_png(&img, &path).unwrap();
        let back = image::open(&path).unwrap().into_rgb8();
        assert_eq!(back, img);
        let err = write_png(&img, &dir.path().join("missing/o.png")).unwrap_err();
        assert!(matches!(err, OverlayError::Write { .. }), "{err:?}");
        assert!(err.to_string().contains("missing/o.png"), "{err}");
    }
}
