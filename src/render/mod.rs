//! The exact synthetic renderer: images of rigs with exact ground truth, the reference every accuracy
//! test and benchmark is measured against. Not a capture device: the synthetic cameras that grab
//! frames from it are frame sources of the capture module. [`correspondences`] stops short of images:
//! exact 2D–3D correspondences through a known camera, for the solver's tests and benchmarks.
//!
//! ## How a frame is made
//! 1. **Radiance** ([`render_radiance`]): every sample position `(u, v)` (pixel convention of the crate:
//!    pixel `(i, j)` covers `u ∈ [j−½, j+½)`, `v ∈ [i−½, i+½)`) is unprojected through the exact inverse
//!    distortion ([`Camera::unproject`]) to a ray, moved into the rig frame, and intersected with every
//!    face plane and the optional body box; the nearest hit wins, so faces occlude each other and the
//!    body. The printed pattern is evaluated analytically ([`crate::rig::Face::region_at`]); surfaces are shaded by
//!    a fixed light (Lambert) so faces differ in brightness as in a photo. Samples that cannot be
//!    unprojected (beyond the distortion fold) see the background.
//!    A pixel's value is the mean over `N × N` sub-pixel samples (box filter = area coverage), `N`
//!    rows each shifted by `1/N²` in x ([`sub_sample`]: a vertical edge is located to `1/2N²` px,
//!    not `1/2N`). Adaptive: the `(W+1) × (H+1)` pixel-corner samples are traced first; a pixel whose
//!    3 × 3 neighbourhood of corners all hit the same surface region, and that contains no projected
//!    feature point (inner corner, board or body vertex), is uniform and takes that value; only the
//!    others are supersampled. (A feature thinner than the corner spacing that touches none of those
//!    samples, such as a board seen exactly edge-on, can be missed; it has no measurable corners.)
//! 2. **Lens blur** (in [`render_radiance`], optional, σ px): a lens blurs the scene before the pixels
//!    integrate it, so a pixel is the scene convolved with box ⊛ Gaussian, evaluated on the sub-samples
//!    (point samples weighted by that smooth kernel; pixels beyond the frame are traced too, so a crop
//!    renders as the frame does). Blurring the finished pixels instead (as this renderer did until
//!    render version 2) makes an edge's profile depend on its phase within the pixel: up to 0.0075 px
//!    of corner bias on a frontal junction whose lines run along the pixel axes, which the detector's
//!    noise-free error measured, not the detector's own.
//! 3. **Sensor effects** ([`finish`]): vignetting
//!    (`1 − V·r²/r_max²` about the principal point), gamma (`value^(1/γ)`), Gaussian noise (σ grey
//!    levels, seeded ChaCha8 with one stream per frame) and 8-bit quantisation.
//!
//! The ground truth ([`ground_truth`]) projects every inner corner with [`Camera::project`] and says
//! why it is or is not visible.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError, DistortionModel, Pose};
use crate::rig::{BoardRegion, Rig, SquareColour};
use image::GrayImage;

pub mod correspondences;

use correspondences::look_at;

/// Errors from rendering and writing synthetic frames.
#[derive(Debug, thiserror::Error)]
pub enum SyntheticError {
    #[error("invalid camera for rendering")]
    Camera(#[source] CameraError),
    #[error("invalid render setting {name} = {value}: expected {expected}")]
    Setting {
        name: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot encode {path}")]
    Encode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot serialise ground truth for {path}")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
}

impl SyntheticError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            SyntheticError::Camera(_) | SyntheticError::Setting { .. } => crate::exit::BAD_INPUT,
            SyntheticError::Write { .. }
            | SyntheticError::Encode { .. }
            | SyntheticError::Json { .. } => crate::exit::INTERNAL,
        }
    }
}

/// Surface reflectances (linear, 0..1) used by the renderer.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Palette {
    pub black: f64,
    pub white: f64,
    /// The rig body and the back of boards.
    pub body: f64,
    pub background: f64,
}

impl Default for Palette {
    fn default() -> Self {
        Palette {
            black: 0.06,
            white: 0.88,
            body: 0.45,
            background: 0.2,
        }
    }
}

/// Rendering options. The defaults give a clean, sharp, noise-free, linear image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    /// Sub-samples per axis for pixels near edges (≥ 1).
    pub supersample: u32,
    /// Gaussian blur σ in pixels (0 = none).
    pub blur_sigma_px: f64,
    /// Gaussian noise σ in grey levels (0 = none).
    pub noise_sigma: f64,
    /// Output value = linear^(1/gamma) (1 = linear).
    pub gamma: f64,
    /// Fractional brightness loss at the image corner farthest from the principal point (0..1).
    pub vignetting: f64,
    /// Seed of the noise generator (frame `k` uses stream `k`).
    pub seed: u64,
    /// Whether faces are shaded by a fixed light (off: pure reflectances).
    pub shading: bool,
    pub palette: Palette,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            supersample: 4,
            blur_sigma_px: 0.0,
            noise_sigma: 0.0,
            gamma: 1.0,
            vignetting: 0.0,
            seed: 0,
            shading: true,
            palette: Palette::default(),
        }
    }
}

impl RenderSettings {
    /// Check every setting is usable.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        let bad = |name, value: f64, expected| {
            Err(SyntheticError::Setting {
                name,
                value: value.to_string(),
                expected,
            })
        };
        if self.supersample == 0 || self.supersample > 64 {
            return Err(SyntheticError::Setting {
                name: "supersample",
                value: self.supersample.to_string(),
                expected: "1..=64",
            });
        }
        if !(self.blur_sigma_px >= 0.0 && self.blur_sigma_px <= 50.0) {
            return bad("blur", self.blur_sigma_px, "a σ in pixels in 0..=50");
        }
        if !(self.noise_sigma >= 0.0 && self.noise_sigma.is_finite()) {
            return bad("noise", self.noise_sigma, "a finite σ ≥ 0 in grey levels");
        }
        if !(self.gamma > 0.0 && self.gamma.is_finite()) {
            return bad("gamma", self.gamma, "a positive number");
        }
        if !(0.0..=1.0).contains(&self.vignetting) {
            return bad("vignetting", self.vignetting, "a fraction in 0..=1");
        }
        self.palette.validate()
    }
}

impl Palette {
    /// Check every reflectance is in `0..=1` and the black squares are darker than the white ones
    /// (otherwise the printed pattern would be blank or inverted, and a detector would rightly see a
    /// different board from the one the ground truth describes).
    pub fn validate(&self) -> Result<(), SyntheticError> {
        for (name, value) in [
            ("black", self.black),
            ("white", self.white),
            ("body", self.body),
            ("background", self.background),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(SyntheticError::Setting {
                    name,
                    value: value.to_string(),
                    expected: "a linear reflectance in 0..=1",
                });
            }
        }
        if !(self.black < self.white) {
            return Err(SyntheticError::Setting {
                name: "black",
                value: format!("{} (white = {})", self.black, self.white),
                expected: "a reflectance below white's (0 ≤ black < white ≤ 1)",
            });
        }
        Ok(())
    }
}

/// A linear (radiance) image, row-major, values nominally in `0..1`.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f64>,
}

impl LinearImage {
    /// Value of pixel `(row, col)`.
    pub fn get(&self, row: usize, col: usize) -> f64 {
        self.data[row * self.width as usize + col]
    }
}

/// What a ray hits; equal labels mean equal radiance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Label {
    Background,
    /// Body box, hit through its side `0..6` (−x, +x, −y, +y, −z, +z).
    Body(u8),
    Board {
        face: u16,
        back: bool,
        region: BoardRegion,
    },
}

/// One face prepared for ray casting (rig frame).
#[derive(Debug)]
struct FacePlane {
    normal: Vector3<f64>,
    offset: f64,
}

/// A rig seen by a camera from one pose, ready for ray casting.
#[derive(Debug)]
struct Scene<'a> {
    rig: &'a Rig,
    camera: &'a Camera,
    rig_from_cam: Rotation3<f64>,
    centre: Vector3<f64>,
    planes: Vec<FacePlane>,
    /// Light direction (toward the light), rig frame.
    light: Vector3<f64>,
    settings: RenderSettings,
}

const BODY_NORMALS: [[f64; 3]; 6] = [
    [-1.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, -1.0],
    [0.0, 0.0, 1.0],
];

impl<'a> Scene<'a> {
    fn new(
        rig: &'a Rig,
        camera: &'a Camera,
        cam_from_rig: &Pose,
        settings: RenderSettings,
    ) -> Self {
        let rig_from_cam = cam_from_rig.rotation.inverse();
        // Light above-left of the camera, fixed to the camera.
        let light = rig_from_cam * Vector3::new(-0.35, -0.6, -1.0).normalize();
        Scene {
            rig,
            camera,
            rig_from_cam,
            centre: cam_from_rig.centre(),
            planes: rig
                .faces
                .iter()
                .map(|f| FacePlane {
                    normal: f.normal(),
                    offset: f.normal().dot(&f.origin),
                })
                .collect(),
            light,
            settings,
        }
    }

    /// Nearest board hit along a rig-frame ray: `(t, face index, back side, region)`.
    fn board_hit(
        &self,
        d: &Vector3<f64>,
        skip: Option<usize>,
    ) -> Option<(f64, usize, bool, BoardRegion, SquareColour)> {
        let mut best: Option<(f64, usize, bool, BoardRegion, SquareColour)> = None;
        for (k, (face, plane)) in self.rig.faces.iter().zip(&self.planes).enumerate() {
            if Some(k) == skip {
                continue;
            }
            let denom = plane.normal.dot(d);
            if denom.abs() < 1e-15 {
                continue;
            }
            let t = (plane.offset - plane.normal.dot(&self.centre)) / denom;
            if !(t > 0.0) || best.is_some_and(|b| b.0 <= t) {
                continue;
            }
            let (a, b) = face.local(&(self.centre + d * t));
            let region = face.region_at(a, b);
            if region != BoardRegion::Outside {
                let ink = face.ink_at(a, b).unwrap_or(SquareColour::White);
                best = Some((t, k, denom > 0.0, region, ink));
            }
        }
        best
    }

    /// Entry into the body box along a rig-frame ray: `(t, side)`; `t = 0` if the camera is inside.
    fn body_hit(&self, d: &Vector3<f64>) -> Option<(f64, u8)> {
        let body = self.rig.body.as_ref()?;
        let (mut t0, mut t1) = (0.0_f64, f64::INFINITY);
        let mut side = 255u8;
        for k in 0..3 {
            if d[k].abs() < 1e-300 {
                if self.centre[k] < body.min[k] || self.centre[k] > body.max[k] {
                    return None;
                }
                continue;
            }
            let ta = (body.min[k] - self.centre[k]) / d[k];
            let tb = (body.max[k] - self.centre[k]) / d[k];
            let (near, far, near_side) = if ta < tb {
                (ta, tb, 2 * k as u8)
            } else {
                (tb, ta, 2 * k as u8 + 1)
            };
            if near > t0 {
                t0 = near;
                side = near_side;
            }
            t1 = t1.min(far);
        }
        (t0 <= t1 && side != 255).then_some((t0, side))
    }

    fn shade(&self, normal: &Vector3<f64>) -> f64 {
        if self.settings.shading {
            0.4 + 0.6 * normal.dot(&self.light).max(0.0)
        } else {
            1.0
        }
    }

    /// Trace a camera-frame ray: what it hits and the radiance there.
    fn trace(&self, ray_cam: &Vector3<f64>) -> (Label, f64) {
        let p = &self.settings.palette;
        let d = self.rig_from_cam * ray_cam;
        let board = self.board_hit(&d, None);
        let body = self.body_hit(&d);
        // A board lying on the body surface wins over the body (1 µm tolerance).
        let use_board = match (board, body) {
            (Some((tb, ..)), Some((tbody, _))) => tb <= tbody + 1e-3,
            (Some(_), None) => true,
            _ => false,
        };
        if use_board && let Some((_, face, back, region, ink)) = board {
            let n = self.planes[face].normal;
            let label = Label::Board {
                face: face as u16,
                back,
                region,
            };
            if back {
                return (label, p.body * self.shade(&-n));
            }
            let reflectance = match ink {
                SquareColour::Black => p.black,
                SquareColour::White => p.white,
            };
            return (label, reflectance * self.shade(&n));
        }
        if let Some((_, side)) = body {
            let n = Vector3::from(BODY_NORMALS[side as usize]);
            return (Label::Body(side), p.body * self.shade(&n));
        }
        (Label::Background, p.background)
    }

    fn sample(&self, u: f64, v: f64) -> (Label, f64) {
        match self.camera.unproject(u, v) {
            Ok(ray) => self.trace(&ray),
            Err(_) => (Label::Background, self.settings.palette.background),
        }
    }
}

/// Render the linear image the pixels of `camera` integrate when it sees `rig` from `cam_from_rig`:
/// the scene's radiance blurred by the lens (`blur_sigma_px`) before each pixel's area integrates it
/// (see the module docs; `supersample`, `blur_sigma_px`, `shading` and `palette` of `settings` matter
/// here).
pub fn render_radiance(
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    settings: &RenderSettings,
) -> Result<LinearImage, SyntheticError> {
    camera.validate().map_err(SyntheticError::Camera)?;
    settings.validate()?;
    let scene = Scene::new(rig, camera, cam_from_rig, *settings);
    let [w, h] = camera.image_size;
    let (w, h) = (w as usize, h as usize);
    let n = settings.supersample as usize;
    let sigma = settings.blur_sigma_px;
    if !(sigma > 0.0) {
        let grid = Grid::new(0, 0, w, h, false);
        let pixels = grid.pixels(&scene, rig, camera, cam_from_rig);
        let rows = parallel_rows(h, |i| {
            (0..w)
                .map(|j| pixels.value(&scene, i, j, n))
                .collect::<Vec<f64>>()
        });
        return Ok(LinearImage {
            width: w as u32,
            height: h as u32,
            data: rows.into_iter().flatten().collect(),
        });
    }

    // The lens blurs the scene before the pixels integrate it: pixel (i, j) is the scene convolved
    // with K = box ⊛ Gaussian(σ), K(x, y) = k(x)·k(y), k(x) = Φ((x+½)/σ) − Φ((x−½)/σ), evaluated at
    // the pixel centre. The scene is point-sampled on the supersampling grid (uniform pixels are one
    // value), so the sum is a Riemann sum of a smooth kernel, separable: rows of sub-samples first,
    // then columns. Pixels beyond the frame are traced as well (the scene goes on past the border).
    let pad = (4.0 * sigma + 0.5).ceil() as usize;
    let taps = blur_taps(sigma, pad, n);
    let (pw, ph) = (w + 2 * pad, h + 2 * pad);
    let grid = Grid::new(-(pad as isize), -(pad as isize), pw, ph, true);
    let pixels = grid.pixels(&scene, rig, camera, cam_from_rig);
    let width = 2 * pad + 1;
    // Per padded pixel row: its n sub-sample rows filtered along x at the w output columns.
    let along_x: Vec<Vec<f32>> = parallel_rows(ph, |pi| {
        let row: Vec<Option<f64>> = (0..pw).map(|pj| pixels.uniform(pi, pj)).collect();
        let subs: Vec<Vec<f64>> = (0..pw)
            .map(|pj| match row[pj] {
                Some(_) => Vec::new(),
                None => pixels.samples(&scene, pi, pj, n),
            })
            .collect();
        let mut out = vec![0.0_f32; n * w];
        let mut acc = vec![0.0_f64; n];
        for j in 0..w {
            acc.iter_mut().for_each(|a| *a = 0.0);
            for d in 0..width {
                let pj = j + d;
                match row[pj] {
                    Some(v) => {
                        for (si, a) in acc.iter_mut().enumerate() {
                            *a += taps.whole[si * width + d] * v;
                        }
                    }
                    None => {
                        let s = &subs[pj];
                        for (si, a) in acc.iter_mut().enumerate() {
                            let k = &taps.x[(si * width + d) * n..(si * width + d + 1) * n];
                            *a += s[si * n..(si + 1) * n]
                                .iter()
                                .zip(k)
                                .map(|(x, y)| x * y)
                                .sum::<f64>();
                        }
                    }
                }
            }
            for (si, a) in acc.iter().enumerate() {
                out[si * w + j] = *a as f32;
            }
        }
        out
    });
    let rows = parallel_rows(h, |i| {
        let mut out = vec![0.0_f64; w];
        for d in 0..width {
            let x = &along_x[i + d];
            for si in 0..n {
                let k = taps.y[d * n + si];
                for (o, v) in out.iter_mut().zip(&x[si * w..(si + 1) * w]) {
                    *o += k * f64::from(*v);
                }
            }
        }
        out
    });
    Ok(LinearImage {
        width: w as u32,
        height: h as u32,
        data: rows.into_iter().flatten().collect(),
    })
}

/// Where sub-sample (`si`, `sj`) of an `n × n` pixel lies, from the pixel's top-left corner (px):
/// rows of `n` samples, each row shifted by `1/n²` in x against the one above, so that the `n²`
/// samples take `n²` distinct x positions. On a regular `n × n` grid a vertical edge is seen at the
/// nearest of only `n` positions in every row it crosses, an error of up to `1/2n` px that no row
/// averages away: the vertical edges of a rig on a level turntable, where it moved the station's
/// noise-free cx by −0.07 px (equal weights; −0.28 px weighted) at `n` = 4 against +0.002 px with
/// the shift (`examples/station_chi2`, `ORACLE=1`, `synthetic.noise=0`). The rows stay at common
/// heights so that the blur stays separable and exact; horizontal edges are located to `1/2n` as
/// before (shearing the rows as well, with the blur's y weights taken at each row's mean height,
/// made the corners of the realistic set's faces at 60–75° worse: 0.0042 → 0.0044 px RMS).
fn sub_sample(si: usize, sj: usize, n: usize) -> (f64, f64) {
    let nf = n as f64;
    (
        (sj as f64 + (si as f64 + 0.5) / nf) / nf,
        (si as f64 + 0.5) / nf,
    )
}

/// The blur's weights on the sub-samples ([`sub_sample`]), separable: along x per sub-row
/// (`x[(si·W + d)·n + sj]` for sub-sample `sj` of the pixel `d − pad` away, `W = 2·pad + 1`;
/// `whole[si·W + d]` their sum over the pixel) and along y per sub-row (`y[d·n + si]`). Each set
/// normalised to a total of 1 so that a uniform region keeps its value.
struct BlurTaps {
    x: Vec<f64>,
    whole: Vec<f64>,
    y: Vec<f64>,
}

fn blur_taps(sigma: f64, pad: usize, n: usize) -> BlurTaps {
    // k(x) = ∫ over [x−½, x+½] of the unit Gaussian of σ: Simpson's rule (the integrand is smooth;
    // 64 intervals leave < 1e-12).
    let k = |x: f64| {
        let m = 64;
        let step = 1.0 / m as f64;
        let g = |t: f64| (-(t * t) / (2.0 * sigma * sigma)).exp();
        let mut s = g(x - 0.5) + g(x + 0.5);
        for q in 1..m {
            let t = x - 0.5 + q as f64 * step;
            s += if q % 2 == 1 { 4.0 } else { 2.0 } * g(t);
        }
        s * step / 3.0
    };
    let width = 2 * pad + 1;
    let normalise = |v: &mut [f64]| {
        let total: f64 = v.iter().sum();
        v.iter_mut().for_each(|t| *t /= total);
    };
    let mut x = Vec::with_capacity(n * width * n);
    for si in 0..n {
        let start = x.len();
        for d in 0..width {
            for sj in 0..n {
                let (ox, _) = sub_sample(si, sj, n);
                x.push(k(d as f64 - pad as f64 - 0.5 + ox));
            }
        }
        normalise(&mut x[start..]);
    }
    let whole = x.chunks(n).map(|c| c.iter().sum()).collect();
    let mut y: Vec<f64> = (0..width)
        .flat_map(|d| {
            (0..n).map(move |si| d as f64 - pad as f64 - 0.5 + (si as f64 + 0.5) / n as f64)
        })
        .map(k)
        .collect();
    normalise(&mut y);
    BlurTaps { x, whole, y }
}

/// A block of pixels (`x0, y0`: the frame coordinates of its first pixel) and their pixel-corner
/// samples, from which each pixel is classified as uniform or in need of supersampling.
struct Grid {
    x0: isize,
    y0: isize,
    w: usize,
    h: usize,
    /// Trace the corners one pixel beyond the block, so that every pixel of the block is classified
    /// from its whole 3 × 3 neighbourhood (a block inside a larger image classifies its pixels as the
    /// larger image does); without it the neighbourhood is cut at the block's edge.
    margin: bool,
}

/// The pixel-corner samples of a [`Grid`] and the pixels that hold a feature point.
struct GridPixels<'g> {
    grid: &'g Grid,
    /// Corner rows/columns traced beyond the block on each side (0 or 1).
    m: usize,
    cw: usize,
    ch: usize,
    corners: Vec<(Label, f64)>,
    feature: Vec<bool>,
}

impl Grid {
    fn new(x0: isize, y0: isize, w: usize, h: usize, margin: bool) -> Self {
        Grid {
            x0,
            y0,
            w,
            h,
            margin,
        }
    }

    fn pixels<'g>(
        &'g self,
        scene: &Scene<'_>,
        rig: &Rig,
        camera: &Camera,
        cam_from_rig: &Pose,
    ) -> GridPixels<'g> {
        let m = usize::from(self.margin);
        let (w, h) = (self.w, self.h);
        // Corner (r, c) of the block is at (u, v) = (x0 + c − m − ½, y0 + r − m − ½).
        let (cw, ch) = (w + 1 + 2 * m, h + 1 + 2 * m);
        let (ux, vy) = (
            self.x0 as f64 - m as f64 - 0.5,
            self.y0 as f64 - m as f64 - 0.5,
        );
        let corner_rows = parallel_rows(ch, |r| {
            (0..cw)
                .map(|c| scene.sample(ux + c as f64, vy + r as f64))
                .collect::<Vec<_>>()
        });
        let corners: Vec<(Label, f64)> = corner_rows.into_iter().flatten().collect();

        // Pixels containing a feature point are always supersampled.
        let mut feature = vec![false; w * h];
        let mut mark = |p: Vector3<f64>| {
            if let Ok(uv) = camera.project(cam_from_rig, &p) {
                let (j, i) = (
                    (uv.x + 0.5).floor() - self.x0 as f64,
                    (uv.y + 0.5).floor() - self.y0 as f64,
                );
                for di in -1..=1 {
                    for dj in -1..=1 {
                        let (ii, jj) = (i + f64::from(di), j + f64::from(dj));
                        if ii >= 0.0 && jj >= 0.0 && (ii as usize) < h && (jj as usize) < w {
                            feature[ii as usize * w + jj as usize] = true;
                        }
                    }
                }
            }
        };
        for f in &rig.faces {
            for r in 0..f.rows {
                for c in 0..f.cols {
                    mark(f.corner_xyz(r, c));
                }
            }
            f.outline().into_iter().for_each(&mut mark);
        }
        if let Some(b) = &rig.body {
            for k in 0..8 {
                mark(Vector3::new(
                    if k & 1 == 0 { b.min.x } else { b.max.x },
                    if k & 2 == 0 { b.min.y } else { b.max.y },
                    if k & 4 == 0 { b.min.z } else { b.max.z },
                ));
            }
        }
        GridPixels {
            grid: self,
            m,
            cw,
            ch,
            corners,
            feature,
        }
    }
}

impl GridPixels<'_> {
    /// The value of block pixel (`i`, `j`) when it is uniform (no feature point, and its 3 × 3
    /// neighbourhood of pixel corners all on one surface region).
    fn uniform(&self, i: usize, j: usize) -> Option<f64> {
        if self.feature[i * self.grid.w + j] {
            return None;
        }
        // corner (i, j) of the pixel in the traced corner array
        let (ci, cj) = (i + self.m, j + self.m);
        let first = self.corners[ci * self.cw + cj];
        let (r0, r1) = (ci.saturating_sub(1), (ci + 2).min(self.ch - 1));
        let (c0, c1) = (cj.saturating_sub(1), (cj + 2).min(self.cw - 1));
        for r in r0..=r1 {
            for c in c0..=c1 {
                if self.corners[r * self.cw + c].0 != first.0 {
                    return None;
                }
            }
        }
        Some(first.1)
    }

    /// The `n × n` point samples of block pixel (`i`, `j`), row-major.
    fn samples(&self, scene: &Scene<'_>, i: usize, j: usize, n: usize) -> Vec<f64> {
        let (x, y) = (
            (self.grid.x0 + j as isize) as f64,
            (self.grid.y0 + i as isize) as f64,
        );
        let mut out = Vec::with_capacity(n * n);
        for si in 0..n {
            for sj in 0..n {
                let (ox, oy) = sub_sample(si, sj, n);
                out.push(scene.sample(x - 0.5 + ox, y - 0.5 + oy).1);
            }
        }
        out
    }

    /// The box-filtered value of block pixel (`i`, `j`): uniform, or the mean of its samples.
    fn value(&self, scene: &Scene<'_>, i: usize, j: usize, n: usize) -> f64 {
        self.uniform(i, j)
            .unwrap_or_else(|| self.samples(scene, i, j, n).iter().sum::<f64>() / (n * n) as f64)
    }
}

/// Compute `f(row)` for `0..n` rows on the available cores (at most 4), in order.
fn parallel_rows<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    if n < 16 {
        return (0..n).map(&f).collect();
    }
    parallel_map(n, f)
}

/// Compute `f(i)` for `i` in `0..n` on the available cores (at most 4, each a contiguous share),
/// in order. Used beyond the renderer for any per-item work (views refitted, report thumbnails).
pub fn parallel_map<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let threads = std::thread::available_parallelism()
        .map(|t| t.get())
        .unwrap_or(1)
        .clamp(1, 4);
    if threads == 1 || n < 2 {
        return (0..n).map(&f).collect();
    }
    let chunk = n.div_ceil(threads);
    let f = &f;
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|t| {
                s.spawn(move || {
                    (t * chunk..((t + 1) * chunk).min(n))
                        .map(f)
                        .collect::<Vec<T>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| match h.join() {
                Ok(v) => v,
                Err(panic) => std::panic::resume_unwind(panic),
            })
            .collect()
    })
}

/// Separable Gaussian blur with standard deviation `sigma_px` (kernel radius ⌈4σ⌉, edges clamped).
pub fn gaussian_blur(img: &LinearImage, sigma_px: f64) -> LinearImage {
    if !(sigma_px > 0.0) {
        return img.clone();
    }
    let radius = (4.0 * sigma_px).ceil() as isize;
    let mut kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k as f64).powi(2) / (2.0 * sigma_px * sigma_px)).exp())
        .collect();
    let total: f64 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    let (w, h) = (img.width as isize, img.height as isize);
    let mut tmp = vec![0.0; img.data.len()];
    for i in 0..h {
        for j in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let jj = (j + k as isize - radius).clamp(0, w - 1);
                s += kv * img.data[(i * w + jj) as usize];
            }
            tmp[(i * w + j) as usize] = s;
        }
    }
    let mut out = vec![0.0; img.data.len()];
    for i in 0..h {
        for j in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let ii = (i + k as isize - radius).clamp(0, h - 1);
                s += kv * tmp[(ii * w + j) as usize];
            }
            out[(i * w + j) as usize] = s;
        }
    }
    LinearImage {
        width: img.width,
        height: img.height,
        data: out,
    }
}

/// The camera's response of `settings` in a `w`×`h` frame with principal point (`cx`, `cy`): the
/// grey level (before noise and rounding) of blurred radiance `v` at pixel (`j`, `i`), vignetting and
/// gamma applied. [`finish`] and the Cramér–Rao bounds' noise-free image (the detector's
/// `crlb::expected_image`) share it.
pub fn response(
    settings: &RenderSettings,
    w: u32,
    h: u32,
    cx: f64,
    cy: f64,
) -> impl Fn(f64, f64, f64) -> f64 + '_ {
    let r_max2 = [
        (0.0, 0.0),
        (f64::from(w) - 1.0, 0.0),
        (0.0, f64::from(h) - 1.0),
        (f64::from(w) - 1.0, f64::from(h) - 1.0),
    ]
    .iter()
    .map(|(u, v)| (u - cx).powi(2) + (v - cy).powi(2))
    .fold(1.0_f64, f64::max);
    move |mut v, j, i| {
        if settings.vignetting > 0.0 {
            v *= 1.0 - settings.vignetting * ((j - cx).powi(2) + (i - cy).powi(2)) / r_max2;
        }
        v.max(0.0).powf(1.0 / settings.gamma) * 255.0
    }
}

/// Apply the sensor's effects of `settings` (vignetting, gamma, noise) to the image the pixels
/// integrated ([`render_radiance`], the lens's blur included) and quantise to 8 bits. `frame` selects
/// the noise stream.
pub fn finish(
    radiance: &LinearImage,
    camera: &Camera,
    settings: &RenderSettings,
    frame: u64,
) -> GrayImage {
    let img = radiance;
    let (w, h) = (img.width, img.height);
    let respond = response(settings, w, h, camera.cx(), camera.cy());
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    rng.set_stream(frame);
    let noise = Normal::new(0.0, settings.noise_sigma).ok();
    let mut out = GrayImage::new(w, h);
    for (k, px) in out.pixels_mut().enumerate() {
        let (j, i) = ((k as u32 % w.max(1)) as f64, (k as u32 / w.max(1)) as f64);
        let mut v = respond(img.data[k], j, i);
        if settings.noise_sigma > 0.0
            && let Some(nd) = &noise
        {
            v += nd.sample(&mut rng);
        }
        px.0[0] = v.round().clamp(0.0, 255.0) as u8;
    }
    out
}

/// Render one finished 8-bit frame.
pub fn render(
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    settings: &RenderSettings,
    frame: u64,
) -> Result<GrayImage, SyntheticError> {
    let radiance = render_radiance(rig, camera, cam_from_rig, settings)?;
    Ok(finish(&radiance, camera, settings, frame))
}

/// The camera as written in ground-truth files.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRecord {
    pub image_size: [u32; 2],
    /// `K`, row-major.
    pub camera_matrix: [[f64; 3]; 3],
    pub distortion_model: DistortionModel,
    /// OpenCV order `k1, k2, p1, p2, k3[, k4, k5, k6]`.
    pub distortion_coefficients: Vec<f64>,
}

impl CameraRecord {
    pub fn from_camera(camera: &Camera) -> Self {
        let k = camera.k_matrix();
        CameraRecord {
            image_size: camera.image_size,
            camera_matrix: rows3(&k),
            distortion_model: camera.model,
            distortion_coefficients: camera.distortion_coefficients(),
        }
    }

    /// Back to a [`Camera`].
    pub fn to_camera(&self) -> Camera {
        let k = &self.camera_matrix;
        let mut cam = Camera::pinhole(self.image_size, k[0][0], k[1][1], k[0][2], k[1][2])
            .with_distortion(self.distortion_model, &self.distortion_coefficients);
        cam.params[crate::camera::idx::SKEW] = k[0][1];
        cam
    }
}

fn rows3(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|r| [m[(r, 0)], m[(r, 1)], m[(r, 2)]])
}

/// A pose as written in ground-truth files: `cam_from_rig`, `X_cam = R·X_rig + t`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseRecord {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

impl PoseRecord {
    pub fn from_pose(pose: &Pose) -> Self {
        PoseRecord {
            rotation: rows3(pose.rotation.matrix()),
            translation: [pose.translation.x, pose.translation.y, pose.translation.z],
        }
    }

    /// Back to a [`Pose`] (the rotation is re-orthonormalised).
    pub fn to_pose(&self) -> Pose {
        let r = Matrix3::from_fn(|i, j| self.rotation[i][j]);
        Pose {
            rotation: Rotation3::from_matrix(&r),
            translation: Vector3::from(self.translation),
        }
    }
}

/// Ground truth of one inner corner.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CornerTruth {
    /// Face name and index in the rig.
    pub face: String,
    pub face_index: usize,
    pub row: usize,
    pub col: usize,
    /// Rig-frame position, mm.
    pub xyz: [f64; 3],
    /// Exact distorted pixel position ([`Camera::project`]); `None` behind the camera.
    pub uv: Option<[f64; 2]>,
    /// In front of the camera (`z > 0`).
    pub in_front: bool,
    /// The camera is on the printed side of the face.
    pub front_facing: bool,
    /// Projects inside the image (`[−½, W−½) × [−½, H−½)`) and within the invertible part of the
    /// distortion (unprojecting `uv` gives back the corner's ray).
    pub in_image: bool,
    /// Another face or the body is in front of it.
    pub occluded: bool,
    /// `in_front && front_facing && in_image && !occluded`.
    pub visible: bool,
}

/// The renderer's version, recorded in every [`GroundTruth`]: 2 since the lens blur is applied
/// before the pixels integrate the scene (1 blurred the finished pixels).
pub const RENDERER_VERSION: u32 = 2;

fn first_renderer() -> u32 {
    1
}

/// Ground truth of one rendered frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroundTruth {
    /// The renderer's version ([`RENDERER_VERSION`]; 1 when absent: frames written before it was
    /// recorded): a frame cache keyed by the truth renders again when the renderer changed.
    #[serde(default = "first_renderer")]
    pub renderer: u32,
    pub rig: String,
    pub frame: u64,
    pub camera: CameraRecord,
    pub cam_from_rig: PoseRecord,
    pub render: RenderSettings,
    pub corners: Vec<CornerTruth>,
}

impl GroundTruth {
    /// The visible corners.
    pub fn visible(&self) -> impl Iterator<Item = &CornerTruth> {
        self.corners.iter().filter(|c| c.visible)
    }
}

/// Exact ground truth for every inner corner of `rig` seen by `camera` from `cam_from_rig`.
pub fn ground_truth(
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    settings: &RenderSettings,
    frame: u64,
) -> GroundTruth {
    let scene = Scene::new(rig, camera, cam_from_rig, *settings);
    let [w, h] = camera.image_size;
    let corners = rig
        .corners()
        .map(|id| {
            let face = &rig.faces[id.face];
            let p = face.corner_xyz(id.row, id.col);
            let pc = cam_from_rig.transform(&p);
            let in_front = pc.z > 0.0;
            let front_facing = face.normal().dot(&(scene.centre - p)) > 0.0;
            let uv = camera.project_cam(&pc).ok();
            let in_image = uv.is_some_and(|uv| {
                uv.x >= -0.5
                    && uv.y >= -0.5
                    && uv.x < f64::from(w) - 0.5
                    && uv.y < f64::from(h) - 0.5
                    && camera
                        .unproject(uv.x, uv.y)
                        .is_ok_and(|ray| (ray - pc.normalize()).norm() < 1e-6)
            });
            let to_p = p - scene.centre;
            let dist = to_p.norm();
            let d = to_p / dist;
            let eps = 1e-6 * (1.0 + dist);
            let by_board = scene
                .board_hit(&d, Some(id.face))
                .is_some_and(|(t, ..)| t < dist - eps);
            let by_body = scene.body_hit(&d).is_some_and(|(t, _)| t < dist - eps);
            let occluded = by_board || by_body;
            CornerTruth {
                face: face.name.clone(),
                face_index: id.face,
                row: id.row,
                col: id.col,
                xyz: [p.x, p.y, p.z],
                uv: uv.map(|uv| [uv.x, uv.y]),
                in_front,
                front_facing,
                in_image,
                occluded,
                visible: in_front && front_facing && in_image && !occluded,
            }
        })
        .collect();
    GroundTruth {
        renderer: RENDERER_VERSION,
        rig: rig.name.clone(),
        frame,
        camera: CameraRecord::from_camera(camera),
        cam_from_rig: PoseRecord::from_pose(cam_from_rig),
        render: *settings,
        corners,
    }
}

/// `cam_from_rig` looking at the rig's centre along [`Rig::viewing_direction`], with the rig's `up`
/// pointing up in the image, from a distance at which the rig's bounding sphere fills about 90 % of
/// the smaller field of view.
pub fn default_view(rig: &Rig, camera: &Camera) -> Pose {
    let centre = rig.centre();
    let dir = rig.viewing_direction();
    let dist = viewing_distance(rig, camera);
    let up = if rig.up.cross(&dir).norm() > 1e-6 {
        rig.up
    } else {
        dir.cross(&Vector3::x())
            .try_normalize(1e-9)
            .unwrap_or_else(Vector3::y)
    };
    look_at(&(centre + dir * dist), &centre, &up)
}

fn viewing_distance(rig: &Rig, camera: &Camera) -> f64 {
    let [w, h] = camera.image_size;
    let half_u = (f64::from(w) / 2.0) / camera.fx();
    let half_v = (f64::from(h) / 2.0) / camera.fy();
    let half = half_u.min(half_v).atan();
    rig.radius() / (0.9 * half).sin()
}

/// `cam_from_rig` of a turntable: the rig turned about its `up` axis through its centre, in `n` equal
/// steps of `sweep_deg / n` centred on [`default_view`]; the camera stays fixed. `sweep_deg = 360`
/// is a full turn.
pub fn turntable_poses(rig: &Rig, camera: &Camera, n: usize, sweep_deg: f64) -> Vec<Pose> {
    let base = default_view(rig, camera);
    let step = sweep_deg / n.max(1) as f64;
    (0..n)
        .map(|k| turned(rig, &base, (k as f64 - (n as f64 - 1.0) / 2.0) * step))
        .collect()
}

/// `n` seeded random views around [`default_view`]: viewing direction tilted up to 30°, distance
/// × 0.75..1.1, aim point within 10 % of the rig's radius, roll ±15°.
pub fn random_poses(rig: &Rig, camera: &Camera, n: usize, seed: u64) -> Vec<Pose> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let centre = rig.centre();
    let dir0 = rig.viewing_direction();
    let dist0 = viewing_distance(rig, camera);
    let radius = rig.radius();
    (0..n)
        .map(|_| {
            let perp = dir0
                .cross(&Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ))
                .try_normalize(1e-9)
                .unwrap_or_else(|| {
                    dir0.cross(&Vector3::x())
                        .try_normalize(1e-9)
                        .unwrap_or_else(Vector3::y)
                });
            let tilt = rng.random_range(0.0..30.0_f64).to_radians();
            let dir = Rotation3::from_axis_angle(&Unit::new_normalize(perp), tilt) * dir0;
            let dist = dist0 * rng.random_range(0.75..1.1);
            let aim = centre
                + Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ) * (0.1 * radius);
            let eye = centre + dir * dist;
            let up0 = if rig.up.cross(&dir).norm() > 1e-3 {
                rig.up
            } else {
                perp
            };
            let roll = rng.random_range(-15.0..15.0_f64).to_radians();
            let up = Rotation3::from_axis_angle(&Unit::new_normalize(aim - eye), roll) * up0;
            look_at(&eye, &aim, &up)
        })
        .collect()
}

/// Paths of frame `index` in `dir`: `frame_000.png`, `frame_000.json`.
pub fn frame_paths(dir: &Path, index: u64) -> (PathBuf, PathBuf) {
    (
        dir.join(format!("frame_{index:03}.png")),
        dir.join(format!("frame_{index:03}.json")),
    )
}

/// Frame `frame` of `rig` seen by `camera` from `cam_from_rig`, rendered once into `dir` (created if
/// missing) and read back on later calls while its ground truth — pose, camera, settings — is the
/// same: the frame cache of the tests and examples that score the detector against the truth.
pub fn cached_frame(
    dir: &Path,
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    settings: &RenderSettings,
    frame: u64,
) -> Result<(GrayImage, GroundTruth), SyntheticError> {
    let truth = ground_truth(rig, camera, cam_from_rig, settings, frame);
    let (png, json) = frame_paths(dir, frame);
    let same = std::fs::read_to_string(&json)
        .ok()
        .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
        .is_some_and(|v| serde_json::to_value(&truth).ok() == Some(v));
    if same && let Ok(img) = image::open(&png) {
        return Ok((img.to_luma8(), truth));
    }
    std::fs::create_dir_all(dir).map_err(|source| SyntheticError::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let img = render(rig, camera, cam_from_rig, settings, frame)?;
    write_frame(dir, &img, &truth)?;
    Ok((img, truth))
}

/// Write a frame's PNG and ground-truth JSON atomically into `dir`; returns their paths.
pub fn write_frame(
    dir: &Path,
    image: &GrayImage,
    truth: &GroundTruth,
) -> Result<(PathBuf, PathBuf), SyntheticError> {
    let (png, json) = frame_paths(dir, truth.frame);
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|source| SyntheticError::Encode {
            path: png.clone(),
            source,
        })?;
    crate::rig::write_atomic(&png, &bytes).map_err(|source| SyntheticError::Write {
        path: png.clone(),
        source,
    })?;
    let text = serde_json::to_string_pretty(truth).map_err(|source| SyntheticError::Json {
        path: json.clone(),
        source,
    })?;
    crate::rig::write_atomic(&json, text.as_bytes()).map_err(|source| SyntheticError::Write {
        path: json.clone(),
        source,
    })?;
    Ok((png, json))
}

/// `cam_from_rig` of a fixed camera looking at a rig turned by `angle_deg` about its `up` axis through
/// its centre, from `base` (the pose at 0°): what a camera in front of a turntable sees.
pub fn turned(rig: &Rig, base: &Pose, angle_deg: f64) -> Pose {
    let c = rig.centre();
    let axis = Unit::new_normalize(rig.up);
    let r = Rotation3::from_axis_angle(&axis, angle_deg.to_radians());
    base.compose(&Pose {
        rotation: r,
        translation: c - r * c,
    })
}

/// Where the rig sits on a two-axis stage (rotation on a tilting cradle) relative to its axes, in mm.
/// With both zero and no tilt, [`stage_pose`] is [`turned`].
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct StageGeometry {
    /// Horizontal distance from the rotation axis to the rig's centre, the rig standing in front of
    /// the axis (toward the camera at 0°): turning the table then swings the rig across the image.
    pub rig_offset_mm: f64,
    /// Height of the rig's centre above the tilt axis: tilting then swings the rig up and down
    /// the image.
    pub tilt_pivot_mm: f64,
}

/// `cam_from_rig` of a rig on a two-axis stage seen by a fixed camera: `base` is `cam_from_rig` at
/// (0°, 0°). The table turns by `rotation_deg` about the rig's `up` through a point `rig_offset_mm`
/// behind the rig's centre (away from the camera, horizontally); the table sits on a cradle that
/// tilts by `tilt_deg` about the horizontal axis `up × (line of sight at 0°)` through the point
/// `tilt_pivot_mm` below the rig's centre.
pub fn stage_pose(
    rig: &Rig,
    base: &Pose,
    geometry: &StageGeometry,
    rotation_deg: f64,
    tilt_deg: f64,
) -> Pose {
    let view = base.rotation.inverse() * Vector3::z();
    base.compose(&stage_motion(rig, &view, geometry, rotation_deg, tilt_deg))
}

/// The stage's motion of the rig in its own frame at (0°, 0°) (so `cam_from_rig = base ∘ motion`),
/// `line_of_sight` being the camera's optical axis at (0°, 0°) in that frame; see [`stage_pose`].
pub fn stage_motion(
    rig: &Rig,
    line_of_sight: &Vector3<f64>,
    geometry: &StageGeometry,
    rotation_deg: f64,
    tilt_deg: f64,
) -> Pose {
    let c = rig.centre();
    let up = rig.up.try_normalize(1e-12).unwrap_or_else(Vector3::z);
    let view = line_of_sight;
    let away = (view - up * up.dot(view))
        .try_normalize(1e-9)
        .or_else(|| up.cross(&Vector3::x()).try_normalize(1e-9))
        .unwrap_or_else(Vector3::y);
    let tilt_axis = up.cross(&away);
    let axis_point = c + away * geometry.rig_offset_mm;
    let r = Rotation3::from_axis_angle(&Unit::new_normalize(up), rotation_deg.to_radians());
    let turn = Pose {
        rotation: r,
        translation: axis_point - r * axis_point,
    };
    let pivot = c - up * geometry.tilt_pivot_mm;
    let t = Rotation3::from_axis_angle(&Unit::new_normalize(tilt_axis), tilt_deg.to_radians());
    let tilt = Pose {
        rotation: t,
        translation: pivot - t * pivot,
    };
    tilt.compose(&turn)
}
