//! Thumbnails of each pose with its detection overlay ([`crate::detect::overlay::draw`]) and a legend
//! strip naming the faces in their overlay colours.
//!
//! Accepted views are drawn from the run's observations (exactly the corners the fit used; rows and
//! columns recovered from the rig geometry), which costs no detection. Rejected views have no
//! observations: their frame is searched again with [`crate::detect::detect`] so that the thumbnail
//! shows what the detector found and the reason says why it was not enough. The overlay is drawn
//! on the downscaled frame with the corners mapped to it, so lines stay one pixel wide.
//!
//! Downscaling is a hand-written integer box filter ([`downscale`]; [`crate::run::preview`] says why).
//! A run's report draws on the previews the station reduced while it held the frames
//! ([`thumbnail_of_preview`]); a report drawn later from the run directory decodes the session's frames.

use std::path::Path;

use image::{GrayImage, RgbImage};
use nalgebra::{Vector2, Vector3};
use plotters::prelude::*;

use crate::calib::observations::RawView;
use crate::detect::label::{FaceDetection, LabelledCorner};
use crate::detect::{CornerFinder, FrameDetection, overlay};
use crate::rig::Rig;

use super::plots::{PlotError, face_rgb};

pub use crate::run::preview::{THUMB_WIDTH, downscale};
/// Height of the legend strip under a thumbnail (px).
pub const LEGEND_HEIGHT: u32 = 22;

/// The corners of an observed view as a detection of `rig`'s faces. Points whose face is unknown or
/// that do not lie on a corner of their face (beyond 1 % of a square) are left out.
pub fn detection_from_view(view: &RawView, rig: &Rig, width: u32, height: u32) -> FrameDetection {
    let mut faces: Vec<FaceDetection> = Vec::new();
    for p in &view.points {
        let Some(fi) = p
            .face
            .as_deref()
            .and_then(|name| rig.faces.iter().position(|f| f.name == name))
        else {
            continue;
        };
        let face = &rig.faces[fi];
        let (a, b) = face.local(&Vector3::from(p.xyz));
        let (col, row) = (a / face.square_mm, b / face.square_mm);
        let (c, r) = (col.round(), row.round());
        if (col - c).abs() > 0.01 || (row - r).abs() > 0.01 || c < 0.0 || r < 0.0 {
            continue;
        }
        let corner = LabelledCorner {
            row: r as usize,
            col: c as usize,
            xyz: Vector3::from(p.xyz),
            uv: Vector2::from(p.uv),
            sigma_px: 0.0,
            cov: nalgebra::Matrix2::zeros(),
            edge_px: 0.0,
        };
        match faces.iter_mut().find(|f| f.face == fi) {
            Some(f) => f.corners.push(corner),
            None => faces.push(FaceDetection {
                face: fi,
                corners: vec![corner],
                colour_contrast: 0.0,
                ambiguous_pose: None,
                identity: None,
            }),
        }
    }
    FrameDetection {
        width,
        height,
        faces,
        rejected: Vec::new(),
    }
}

/// Detect `rig` in a full-size frame (for views without observations).
pub fn detect_frame(img: &GrayImage, rig: &Rig) -> Option<FrameDetection> {
    let mut finder = CornerFinder::new().ok()?;
    crate::detect::detect(&mut finder, img, rig).ok()
}

/// `det` with every corner mapped into an image scaled by `s` (pixel centres map to pixel centres:
/// `u' = (u + ½)·s − ½`).
fn scaled(det: &FrameDetection, s: f64, width: u32, height: u32) -> FrameDetection {
    let map = |uv: Vector2<f64>| uv.map(|x| (x + 0.5) * s - 0.5);
    FrameDetection {
        width,
        height,
        faces: det
            .faces
            .iter()
            .map(|f| FaceDetection {
                face: f.face,
                corners: f
                    .corners
                    .iter()
                    .map(|c| LabelledCorner {
                        uv: map(c.uv),
                        ..*c
                    })
                    .collect(),
                colour_contrast: f.colour_contrast,
                ambiguous_pose: None,
                identity: None,
            })
            .collect(),
        rejected: det.rejected.clone(),
    }
}

/// The thumbnail of `frame` with `det` drawn on it and a legend strip of the faces found
/// (name and corner count in the face's colour).
pub fn thumbnail(
    frame: &GrayImage,
    det: &FrameDetection,
    rig: &Rig,
) -> Result<RgbImage, PlotError> {
    // The legend is text: the font must be there even when no plot was drawn before (a run
    // without a calibration has thumbnails only).
    let k = crate::run::preview::factor(frame.width());
    thumbnail_of_preview(&downscale(frame, k), k, det, rig)
}

/// [`thumbnail`] of a frame already reduced by `k` with [`downscale`] (`det` is in full-frame
/// pixels).
pub fn thumbnail_of_preview(
    small: &GrayImage,
    k: u32,
    det: &FrameDetection,
    rig: &Rig,
) -> Result<RgbImage, PlotError> {
    super::plots::register_font()?;
    let (tw, th) = small.dimensions();
    let s = 1.0 / f64::from(k);
    let drawn = overlay::draw(small, &scaled(det, s, tw, th), rig);
    // The drawn frame with a white strip under it (rows of the same width: its bytes, then white).
    let (ow, oh) = (tw, th + LEGEND_HEIGHT);
    let mut buf = drawn.into_raw();
    buf.resize(ow as usize * oh as usize * 3, 255);
    {
        let root = BitMapBackend::with_buffer(&mut buf, (ow, oh)).into_drawing_area();
        let (_, strip) = root.split_vertically(th);
        let mut x = 4i32;
        if det.faces.is_empty() {
            strip
                .draw(&Text::new("no face found", (x, 4), ("sans-serif", 13)))
                .map_err(|e| -> PlotError { Box::new(e) })?;
        }
        let mut faces: Vec<&FaceDetection> = det.faces.iter().collect();
        faces.sort_by_key(|f| f.face);
        for f in faces {
            let name = rig
                .faces
                .get(f.face)
                .map_or_else(|| format!("face {}", f.face), |r| r.name.clone());
            let label = format!("{name} ({})", f.corners.len());
            let style = ("sans-serif", 13).into_font().color(&face_rgb(f.face));
            strip
                .draw(&Rectangle::new(
                    [(x, 6), (x + 10, 16)],
                    face_rgb(f.face).filled(),
                ))
                .map_err(|e| -> PlotError { Box::new(e) })?;
            strip
                .draw(&Text::new(label.clone(), (x + 14, 4), style.clone()))
                .map_err(|e| -> PlotError { Box::new(e) })?;
            let (lw, _) = strip
                .estimate_text_size(&label, &style)
                .map_err(|e| -> PlotError { Box::new(e) })?;
            x += 14 + lw as i32 + 12;
        }
        root.present().map_err(|e| -> PlotError { Box::new(e) })?;
    }
    RgbImage::from_raw(ow, oh, buf).ok_or_else(|| "thumbnail buffer size mismatch".into())
}

/// Load a frame as 8-bit grey.
pub fn load_frame(path: &Path) -> Result<GrayImage, image::ImageError> {
    Ok(image::open(path)?.to_luma8())
}
