//! Placing a lone partial face: a board cut by the frame border with no complete face beside it (a
//! single board held close to the camera, a cube face running off the frame), placed by its own
//! evidence — the sides where the pattern visibly ends, the square colours, and the frame border
//! that hides the rest — never by its size alone.
//!
//! The grid is trimmed to a complete rectangle (lines along the border whose corners could not all
//! be fitted are dropped) and each of its four sides is examined one step beyond, as
//! [`super::extent`] does for whole faces:
//! * **ends**: the pattern visibly ends there (at least [`MIN_EMPTY_BEYOND`] positions empty, no
//!   corner like the grid's);
//! * **cut**: at least half the positions beyond are outside the image or too close to its border
//!   for a corner fit, and none shows a corner;
//! * **continues**: the trimming dropped a line there (the lattice has corners beyond);
//! * anything else (a corner like the grid's beyond, checkered squares without a fit) rejects the
//!   grid: it may continue where the image shows more pattern.
//!
//! Every placement on every face — quarter turn (after the handedness correction, so no mirror
//! images) and offset that keeps the grid on the face — must put each side that **ends** on the
//! face's outermost line, and each side that **continues** or is **cut** inside the face (a face that
//! would end exactly at the border could as well be a larger board: not placed), show the face's square colours (white minus black at least
//! [`MIN_COLOUR_CONTRAST`]), and, through the homography of the grid, put every corner of the face
//! the grid lacks outside the frame or within one step of its border. Exactly one placement must
//! remain, else the grid is rejected with the count ("ambiguous").

use image::GrayImage;
use nalgebra::{Vector2, Vector3};

use super::complete::median;
use super::dense::Dense;
use super::extent::{MIN_EMPTY_BEYOND, Side, look_beyond};
use super::identity::{ColourSums, MIN_COLOUR_CONTRAST, mean_square_intensity};
use super::label::{FaceDetection, LabelledCorner};
use crate::calib::linear::homography;
use crate::rig::Rig;

/// What one step beyond a side of a lone grid shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum End {
    /// The pattern visibly ends.
    Ends,
    /// The frame border hides what is beyond.
    Cut,
    /// The lattice has corners beyond (a line dropped for the corners the border cut off): the
    /// face continues.
    Continues,
}

/// The sides' states in [`Side::ALL`] order (first row, last row, first column, last column).
fn ends(img: &GrayImage, d: &Dense, lost: [bool; 4]) -> Result<[End; 4], String> {
    let mut out = [End::Cut; 4];
    for (k, side) in Side::ALL.into_iter().enumerate() {
        if lost[k] {
            out[k] = End::Continues;
            continue;
        }
        let b = look_beyond(img, d, side);
        if !b.corners.is_empty() {
            return Err(format!(
                "an X-corner like the grid's one step beyond its {side:?} side: the board continues"
            ));
        }
        out[k] = if b.empty >= MIN_EMPTY_BEYOND.min(b.n) && b.undecided == 0 {
            End::Ends
        } else if 2 * (b.outside + b.clipped) >= b.n {
            End::Cut
        } else {
            return Err(format!(
                "its {side:?} side is neither at the frame border nor at the end of the pattern ({} of {} positions beyond undecided)",
                b.undecided, b.n
            ));
        };
    }
    Ok(out)
}

/// Side states after one quarter turn of the grid ([`Dense::quarter_turn`]: new (r, c) = old
/// (rows − 1 − c, r)): new first row = old first column, new last row = old last column, new first
/// column = old last row, new last column = old first row.
fn turn_ends(e: [End; 4]) -> [End; 4] {
    [e[2], e[3], e[1], e[0]]
}

/// Place `d` (a complete, handedness-corrected grid that matches no whole face) on the rig by its
/// own evidence (see the module docs).
pub(super) fn place_alone(
    img: &GrayImage,
    rig: &Rig,
    d: &Dense,
    lost: [bool; 4],
) -> Result<FaceDetection, String> {
    let e0 = ends(img, d, lost)?;
    let mut steps = Vec::new();
    for r in 0..d.rows {
        for c in 0..d.cols {
            if c + 1 < d.cols {
                steps.push((d.at(r, c + 1) - d.at(r, c)).norm());
            }
            if r + 1 < d.rows {
                steps.push((d.at(r + 1, c) - d.at(r, c)).norm());
            }
        }
    }
    let step = median(&mut steps).ok_or("no two neighbouring corners")?;
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    let mut found: Vec<(usize, u8, (usize, usize), f64)> = Vec::new();
    let mut e = e0;
    for turns in 0..4u8 {
        if turns > 0 {
            e = turn_ends(e);
        }
        let t = d.turned(turns);
        for (fi, face) in rig.faces.iter().enumerate() {
            if t.rows > face.rows || t.cols > face.cols {
                continue;
            }
            for dr in 0..=face.rows - t.rows {
                for dc in 0..=face.cols - t.cols {
                    let outer = [
                        dr == 0,
                        dr + t.rows == face.rows,
                        dc == 0,
                        dc + t.cols == face.cols,
                    ];
                    if (0..4).any(|k| {
                        (e[k] == End::Ends && !outer[k]) || (e[k] != End::Ends && outer[k])
                    }) {
                        continue;
                    }
                    let mut sums = ColourSums::default();
                    for r in 0..t.rows - 1 {
                        for c in 0..t.cols - 1 {
                            let quad = [
                                t.at(r, c),
                                t.at(r, c + 1),
                                t.at(r + 1, c),
                                t.at(r + 1, c + 1),
                            ];
                            if let Some(v) = mean_square_intensity(img, quad) {
                                sums.add(face.square_colour(r + dr + 1, c + dc + 1), v);
                            }
                        }
                    }
                    let Some(contrast) = sums.contrast().filter(|&c| c >= MIN_COLOUR_CONTRAST)
                    else {
                        continue;
                    };
                    // The face's other corners must be hidden by the frame border.
                    let (mut plane, mut image) = (Vec::new(), Vec::new());
                    for r in 0..t.rows {
                        for c in 0..t.cols {
                            plane.push(Vector2::new((c + dc) as f64, (r + dr) as f64));
                            image.push(t.at(r, c));
                        }
                    }
                    let Ok(hm) = homography(&plane, &image) else {
                        continue;
                    };
                    let hidden = (0..face.rows).all(|r| {
                        (0..face.cols).all(|c| {
                            if (dr..dr + t.rows).contains(&r) && (dc..dc + t.cols).contains(&c) {
                                return true;
                            }
                            let x = hm * Vector3::new(c as f64, r as f64, 1.0);
                            if x.z.abs() < 1e-12 {
                                return true;
                            }
                            let (u, v) = (x.x / x.z, x.y / x.z);
                            !(u > step && v > step && u < w - 1.0 - step && v < h - 1.0 - step)
                        })
                    });
                    if hidden {
                        found.push((fi, turns, (dr, dc), contrast));
                    }
                }
            }
        }
    }
    match found.as_slice() {
        [] => Err("no face, turn and offset of the rig agrees with its visible ends, square colours and the frame border".into()),
        [(fi, turns, (dr, dc), contrast)] => {
            let face = &rig.faces[*fi];
            let t = d.turned(*turns);
            let corners = (0..t.rows)
                .flat_map(|r| (0..t.cols).map(move |c| (r, c)))
                .map(|(r, c)| LabelledCorner {
                    row: r + dr,
                    col: c + dc,
                    xyz: face.corner_xyz(r + dr, c + dc),
                    uv: t.at(r, c),
                    sigma_px: t.sigma[r * t.cols + c],
                })
                .collect();
            Ok(FaceDetection {
                face: *fi,
                corners,
                colour_contrast: *contrast,
            })
        }
        many => Err(format!(
            "ambiguous: {} placements agree with its visible ends, square colours and the frame border",
            many.len()
        )),
    }
}
