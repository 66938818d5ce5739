//! Labelling: which rig face a detected grid is, and which of its corners is `(0, 0)`.
//!
//! Never guessed — a grid is dropped with a reason unless every step is clear:
//! 1. **Handedness.** A face seen from its printed side shows `col_dir` and `row_dir` with a fixed
//!    orientation in the image (`col × row` points toward the camera, so in image coordinates with y
//!    down the 2D cross product of the column and row steps is negative). A grid with the other
//!    orientation is transposed; mirror-image labellings are thereby impossible.
//! 2. **Size.** The (complete) grid's rows × cols must equal a face's, directly or rotated by 90°.
//! 3. **Orientation.** For a board that is not 180°-symmetric, the two remaining labellings predict
//!    opposite colours for every square: the mean intensity of the squares predicted white must exceed
//!    that of the squares predicted black by a clear margin, or the grid is dropped.
//! 4. **Rigid geometry.** With two or more faces, a wrong labelling does not fit one camera: the
//!    normalised DLT on all labelled corners must fit clearly better than with any single face's
//!    orientation reversed ([`GEOMETRY_MARGIN`]), or the frame's labelling is dropped.
//!
//! Partially visible faces (incomplete grids) are not labelled yet: they are reported as rejected.

use image::GrayImage;
use nalgebra::{Vector2, Vector3};

use super::complete::Completed;
use super::grid::MIN_LINES;
use crate::calib::linear::{COPLANAR_TOLERANCE, dlt, relative_thickness};
use crate::target::{Rig, SquareColour};

/// Mean white-minus-black square intensity (grey levels) needed for an orientation to count as decided.
pub const MIN_COLOUR_CONTRAST: f64 = 10.0;
/// With several faces, the chosen labelling's DLT RMS must be this many times smaller than any
/// alternative's.
pub const GEOMETRY_MARGIN: f64 = 3.0;

/// One labelled corner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LabelledCorner {
    pub row: usize,
    pub col: usize,
    pub xyz: Vector3<f64>,
    pub uv: Vector2<f64>,
    /// Estimated standard deviation of each coordinate of `uv` (px), from the refinement fit.
    pub sigma_px: f64,
}

/// A face found in the frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceDetection {
    pub face: usize,
    pub corners: Vec<LabelledCorner>,
    /// White-minus-black mean intensity that decided the orientation (grey levels).
    pub colour_contrast: f64,
}

/// Why a grid (or the frame) was not used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rejection {
    pub reason: String,
}

/// A grid with local indices mapped to a face: `cell(row, col)` of the face is the grid's
/// `index(row, col)`.
#[derive(Debug, Clone, Copy)]
struct Mapping {
    face: usize,
    /// 0..4: number of quarter turns applied to the handedness-corrected grid.
    turns: u8,
}

fn mean_square_intensity(img: &GrayImage, quad: [Vector2<f64>; 4]) -> Option<f64> {
    let c = (quad[0] + quad[1] + quad[2] + quad[3]) / 4.0;
    // Average a small neighbourhood a third of the way to each corner.
    let mut sum = 0.0;
    let mut n = 0.0;
    for q in &quad {
        let p = c + (q - c) * 0.3;
        let (x, y) = (p.x.round(), p.y.round());
        if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
            return None;
        }
        sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
        n += 1.0;
    }
    let (x, y) = (c.x.round(), c.y.round());
    if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
        return None;
    }
    sum += f64::from(img.get_pixel(x as u32, y as u32).0[0]);
    Some(sum / (n + 1.0))
}

/// A complete grid as a dense `rows × cols` array of image points (with their σ), handedness-corrected.
#[derive(Debug, Clone)]
struct Dense {
    rows: usize,
    cols: usize,
    uv: Vec<Vector2<f64>>,
    sigma: Vec<f64>,
}

impl Dense {
    fn at(&self, r: usize, c: usize) -> Vector2<f64> {
        self.uv[r * self.cols + c]
    }

    /// A `rows × cols` grid whose cell (r, c) is this grid's `source(r, c)`.
    fn remapped(
        &self,
        rows: usize,
        cols: usize,
        source: impl Fn(usize, usize) -> (usize, usize),
    ) -> Dense {
        let mut uv = Vec::with_capacity(self.uv.len());
        let mut sigma = Vec::with_capacity(self.uv.len());
        for r in 0..rows {
            for c in 0..cols {
                let (r0, c0) = source(r, c);
                uv.push(self.uv[r0 * self.cols + c0]);
                sigma.push(self.sigma[r0 * self.cols + c0]);
            }
        }
        Dense {
            rows,
            cols,
            uv,
            sigma,
        }
    }

    fn transposed(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (c, r))
    }

    /// Rotate the labelling by a quarter turn (keeps handedness): new (r, c) = old (rows − 1 − c, r).
    fn quarter_turn(&self) -> Dense {
        self.remapped(self.cols, self.rows, |r, c| (self.rows - 1 - c, r))
    }

    fn turned(&self, turns: u8) -> Dense {
        let mut d = self.clone();
        for _ in 0..turns {
            d = d.quarter_turn();
        }
        d
    }

    /// Mean 2D cross product of column and row steps (negative for the rig's handedness).
    fn handedness(&self) -> f64 {
        let mut s = 0.0;
        for r in 0..self.rows - 1 {
            for c in 0..self.cols - 1 {
                let p = self.at(r, c);
                let a = self.at(r, c + 1) - p;
                let b = self.at(r + 1, c) - p;
                s += a.x * b.y - a.y * b.x;
            }
        }
        s
    }
}

/// Label the grids of one frame against the rig.
pub fn label(
    img: &GrayImage,
    rig: &Rig,
    grids: &[Completed],
) -> (Vec<FaceDetection>, Vec<Rejection>) {
    let mut rejected = Vec::new();
    let mut found: Vec<(FaceDetection, Dense, Mapping)> = Vec::new();
    for g in grids {
        if g.count() == 0 {
            rejected.push(Rejection {
                reason: "a lattice of X-corners was found but none of its corners fits a checkerboard corner"
                    .into(),
            });
            continue;
        }
        if g.count() != g.rows * g.cols || g.rows < MIN_LINES || g.cols < MIN_LINES {
            rejected.push(Rejection {
                reason: format!(
                    "incomplete grid ({} of {}×{} corners): partially visible faces are not labelled",
                    g.count(),
                    g.rows,
                    g.cols
                ),
            });
            continue;
        }
        let mut dense = Dense {
            rows: g.rows,
            cols: g.cols,
            uv: g.cells.iter().flatten().map(|f| f.uv).collect(),
            sigma: g.cells.iter().flatten().map(|f| f.sigma_px).collect(),
        };
        if dense.handedness() > 0.0 {
            dense = dense.transposed();
        }
        // Candidate (face, turns) by size.
        let mut candidates = Vec::new();
        for (fi, f) in rig.faces.iter().enumerate() {
            for turns in 0..4u8 {
                let (r, c) = if turns % 2 == 0 {
                    (dense.rows, dense.cols)
                } else {
                    (dense.cols, dense.rows)
                };
                if (r, c) == (f.rows, f.cols) {
                    candidates.push(Mapping { face: fi, turns });
                }
            }
        }
        if candidates.is_empty() {
            rejected.push(Rejection {
                reason: format!(
                    "{}×{} grid matches no face of rig '{}'",
                    dense.rows, dense.cols, rig.name
                ),
            });
            continue;
        }
        // Orientation by square colours, per candidate face.
        let mut best: Option<(Mapping, f64, Dense)> = None;
        let mut ambiguous = false;
        let mut faces_seen: Vec<usize> = candidates.iter().map(|m| m.face).collect();
        faces_seen.dedup();
        if faces_seen.len() > 1 {
            rejected.push(Rejection {
                reason: format!(
                    "{}×{} grid matches several faces ({}): faces of equal size are not told apart yet",
                    dense.rows,
                    dense.cols,
                    faces_seen
                        .iter()
                        .map(|&f| rig.faces[f].name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            });
            continue;
        }
        for m in &candidates {
            let face = &rig.faces[m.face];
            let d = dense.turned(m.turns);
            let (mut white, mut nw, mut black, mut nb) = (0.0, 0.0, 0.0, 0.0);
            let mut ok = true;
            for r in 0..d.rows - 1 {
                for c in 0..d.cols - 1 {
                    let quad = [
                        d.at(r, c),
                        d.at(r, c + 1),
                        d.at(r + 1, c),
                        d.at(r + 1, c + 1),
                    ];
                    let Some(v) = mean_square_intensity(img, quad) else {
                        ok = false;
                        continue;
                    };
                    match face.square_colour(r + 1, c + 1) {
                        SquareColour::White => {
                            white += v;
                            nw += 1.0;
                        }
                        SquareColour::Black => {
                            black += v;
                            nb += 1.0;
                        }
                    }
                }
            }
            if !ok || nw == 0.0 || nb == 0.0 {
                continue;
            }
            let contrast = white / nw - black / nb;
            if face.is_point_symmetric() && best.is_some() {
                ambiguous = true;
            }
            if best.as_ref().is_none_or(|(_, b, _)| contrast > *b) {
                best = Some((*m, contrast, d));
            }
        }
        let Some((mapping, contrast, d)) = best else {
            rejected.push(Rejection {
                reason: "grid touches the image border: square colours cannot be read".into(),
            });
            continue;
        };
        let face = &rig.faces[mapping.face];
        if ambiguous {
            rejected.push(Rejection {
                reason: format!(
                    "face '{}' is 180°-symmetric: its orientation cannot be decided from one face",
                    face.name
                ),
            });
            continue;
        }
        if contrast < MIN_COLOUR_CONTRAST {
            rejected.push(Rejection {
                reason: format!(
                    "face '{}': square colours do not decide the orientation (white − black = {contrast:.1} grey levels)",
                    face.name
                ),
            });
            continue;
        }
        let corners = (0..d.rows)
            .flat_map(|r| (0..d.cols).map(move |c| (r, c)))
            .map(|(r, c)| LabelledCorner {
                row: r,
                col: c,
                xyz: face.corner_xyz(r, c),
                uv: d.at(r, c),
                sigma_px: d.sigma[r * d.cols + c],
            })
            .collect();
        let det = FaceDetection {
            face: mapping.face,
            corners,
            colour_contrast: contrast,
        };
        found.push((det, d, mapping));
    }
    // A face found twice is a contradiction: drop both.
    let mut faces: Vec<usize> = found.iter().map(|(f, _, _)| f.face).collect();
    faces.sort_unstable();
    let dup: Vec<usize> = faces
        .windows(2)
        .filter(|w| w[0] == w[1])
        .map(|w| w[0])
        .collect();
    if !dup.is_empty() {
        found.retain(|(f, _, _)| {
            let keep = !dup.contains(&f.face);
            if !keep {
                rejected.push(Rejection {
                    reason: format!("face '{}' matched by two grids", rig.faces[f.face].name),
                });
            }
            keep
        });
    }
    if found.len() >= 2
        && let Err(reason) = check_geometry(rig, &found)
    {
        rejected.push(Rejection { reason });
        return (Vec::new(), rejected);
    }
    (found.into_iter().map(|(f, _, _)| f).collect(), rejected)
}

fn dlt_rms(points: &[(Vector3<f64>, Vector2<f64>)]) -> Option<f64> {
    let x3: Vec<Vector3<f64>> = points.iter().map(|p| p.0).collect();
    let x2: Vec<Vector2<f64>> = points.iter().map(|p| p.1).collect();
    if relative_thickness(&x3) < COPLANAR_TOLERANCE {
        return None;
    }
    let p = dlt(&x3, &x2).ok()?;
    let mut ssr = 0.0;
    for (x, u) in x3.iter().zip(&x2) {
        let h = p * x.push(1.0);
        if h.z.abs() < 1e-300 {
            return None;
        }
        ssr += (Vector2::new(h.x / h.z, h.y / h.z) - u).norm_squared();
    }
    Some((ssr / x3.len() as f64).sqrt())
}

/// The labelled faces must fit one camera clearly better than with any face's orientation reversed.
fn check_geometry(rig: &Rig, found: &[(FaceDetection, Dense, Mapping)]) -> Result<(), String> {
    let assemble = |flip: Option<usize>| -> Vec<(Vector3<f64>, Vector2<f64>)> {
        let mut pts = Vec::new();
        for (k, (f, d, _)) in found.iter().enumerate() {
            let face = &rig.faces[f.face];
            let dd = if flip == Some(k) {
                d.turned(2)
            } else {
                d.clone()
            };
            for r in 0..dd.rows {
                for c in 0..dd.cols {
                    pts.push((face.corner_xyz(r, c), dd.at(r, c)));
                }
            }
        }
        pts
    };
    let Some(chosen) = dlt_rms(&assemble(None)) else {
        return Err(
            "labelled faces are coplanar or degenerate: the rig geometry cannot confirm them"
                .into(),
        );
    };
    for k in 0..found.len() {
        if let Some(alt) = dlt_rms(&assemble(Some(k)))
            && alt < GEOMETRY_MARGIN * chosen
        {
            return Err(format!(
                "labelling not confirmed by the rig geometry: DLT RMS {chosen:.2} px vs {alt:.2} px with face '{}' reversed",
                rig.faces[found[k].0.face].name
            ));
        }
    }
    Ok(())
}
