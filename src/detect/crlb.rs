//! Cramér–Rao lower bounds on the position of a corner in a synthetic render, from the renderer's
//! own image model: how precisely *any* unbiased estimator could locate a corner, given the pixels it
//! uses and the pixel noise of the render.
//!
//! A render ([`crate::render::render`]) is a noise-free image `μ(θ)` — radiance
//! blurred by the lens before the pixels integrate it ([`render_radiance`]), vignetting, gamma, scaled to grey levels ([`expected_image`]) — plus
//! independent Gaussian noise of σ grey levels and rounding to 8 bits (uniform, variance 1/12,
//! counted as noise: [`noise_variance`]). For parameters `θ` of the image model, the Fisher
//! information of a set of pixels is `I = (1/σ²) Σ ∂μ/∂θ ∂μ/∂θᵀ`, and the covariance of any unbiased
//! estimate of the corner position `p(θ)` is at least `J I⁻¹ Jᵀ`, `J = ∂p/∂θ`.
//!
//! The derivatives are central differences of renders with one parameter of the scene moved
//! ([`Param`]; steps of about [`View::step_px`] of image motion): the principal point (`Cx`, `Cy`)
//! shifts the whole image — and so the corner — exactly, since the renderer unprojects every sample
//! through the camera and centres the vignetting on the principal point; the focal lengths, skew and a
//! roll about the optical axis add an affine change of the image, the rig pose moves the face, the
//! palette and the blur change the image's levels and edge width. Renders are of a crop of the frame
//! ([`Crop`]: a camera with the crop's size and a principal point moved by its origin; the renderer
//! traces the scene beyond the crop as far as the lens blur reaches), equal to the frame's pixels there.
//!
//! The renderer samples each edge pixel on an `N × N` grid, so its image is a step function of the
//! scene's position on the scale of `1/N` px; the differences must span several sub-samples. On an
//! oblique hard-set-like corner, 8×8 samples with 0.1 px steps gave 40 % too little information
//! along x (the sub-sample grid aliases with the edges); 16×16 with 0.1 px and 32×32 with 0.05 px
//! agree within 1 % (asserted in tests/crlb.rs). The bound is that of the continuous scene: the
//! evaluation sets' own 4×4 renders add their quantisation to the measured errors.
//!
//! Four bounds per corner ([`CornerBound`]):
//! - **window, position only**: the pixels the detector's fit uses
//!   ([`super::refine::refine_near_border_with_window`]), everything but the corner's position known
//!   (`θ = (Cx, Cy)`: the local image translated). The lowest bound for that window.
//! - **window, local model**: the same pixels, with the unknowns a local corner model must also fit:
//!   the image's local affine frame (`Fx`, `Fy`, `Skew`, `Roll` with `Cx`, `Cy`: any affine map of the
//!   image about the corner), the square reflectances and the blur. Directions that leave the
//!   window's image unchanged (a stretch along an edge) carry no information and move no corner:
//!   they drop out of the Schur complement ([`efficient_position_covariance`]).
//! - **face, position only**: the whole face's pixels, the face translated rigidly in the image —
//!   the bound had every other property of the face been known.
//! - **face, joint**: the whole face's pixels, with the rig pose (6), the reflectances and the blur
//!   unknown and the camera known: a perfect estimator of the face as a whole (a model fit of the
//!   entire board), the corner as a function of its pose; and the same with the lens's `k1` unknown
//!   too (the lines' curvature then has to be measured on the face).
//!
//! **Measured** (`MC=30 BUCKETS=75-80 cargo run --release --example crlb -- hard 24
//! target/detect_eval`: the 13 faces found at 75–80°, 753 corners; 1.5–5 min a face): measured RMS
//! 0.160 px; window bound 0.164 px with the local model's unknowns, 0.149 px with only the position
//! unknown; face bound 0.028 px (joint; 0.029 with `k1` unknown too). So 0.1 px is out of reach of
//! any unbiased estimator of one corner from its fit window — the fit sits at its bound — but not of
//! one that fits the face as a whole. Checks of the method: hard set 45–60° (frames 0, 2: 98
//! corners) 0.080 px measured against a bound of 0.086; realistic set 75–80° (frames 2, 4, 7: 156
//! corners) 0.0203 px against 0.0163; the fit on fresh noise over the model scatters at 0.96–1.01 of
//! its window bound on both sets.
//!
//! Written here because this is a measurement of our own renderer, not a generic estimation tool.

use nalgebra::{DMatrix, DVector, Matrix2, Rotation3, Vector2, Vector3};

use crate::camera::{Camera, Pose, idx};
use crate::render::{RenderSettings, SyntheticError, render_radiance, response};
use crate::rig::{BoardRegion, Rig};

/// A rectangle of the frame: columns `x0..x0 + width`, rows `y0..y0 + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Crop {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl Crop {
    /// The bounding box of `points` (pixel coordinates) grown by `pad` px and clipped to an image of
    /// `size`; `None` if nothing of it is inside.
    pub fn around(
        points: impl IntoIterator<Item = Vector2<f64>>,
        pad: f64,
        size: [u32; 2],
    ) -> Option<Crop> {
        let (mut lo, mut hi) = (
            Vector2::repeat(f64::INFINITY),
            Vector2::repeat(f64::NEG_INFINITY),
        );
        for p in points {
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let x0 = (lo.x - pad).floor().max(0.0);
        let y0 = (lo.y - pad).floor().max(0.0);
        let x1 = (hi.x + pad).ceil().min(f64::from(size[0]) - 1.0);
        let y1 = (hi.y + pad).ceil().min(f64::from(size[1]) - 1.0);
        (x1 >= x0 && y1 >= y0).then(|| Crop {
            x0: x0 as u32,
            y0: y0 as u32,
            width: (x1 - x0) as u32 + 1,
            height: (y1 - y0) as u32 + 1,
        })
    }

    /// Index into the crop's row-major pixels of frame pixel `[column, row]`, if inside.
    pub fn index(&self, px: [u32; 2]) -> Option<usize> {
        let (x, y) = (px[0].checked_sub(self.x0)?, px[1].checked_sub(self.y0)?);
        (x < self.width && y < self.height).then(|| y as usize * self.width as usize + x as usize)
    }

    /// Frame pixel `[column, row]` of crop index `k`.
    pub fn pixel(&self, k: usize) -> [u32; 2] {
        let w = self.width as usize;
        [self.x0 + (k % w) as u32, self.y0 + (k / w) as u32]
    }

    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The noise variance (grey levels²) of a render's pixels: the set's noise plus the 8-bit rounding's
/// `1/12`.
pub fn noise_variance(settings: &RenderSettings) -> f64 {
    settings.noise_sigma.powi(2) + 1.0 / 12.0
}

/// The expected grey levels (before noise and rounding) of the pixels of `crop` in the frame
/// [`crate::render::render`] makes of `rig` seen by `camera` from `cam_from_rig`: row-major
/// over the crop. The same arithmetic as [`crate::render::finish`], whose output is
/// this rounded when the noise is 0.
pub fn expected_image(
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    settings: &RenderSettings,
    crop: Crop,
) -> Result<Vec<f64>, SyntheticError> {
    let [w, h] = camera.image_size;
    // The renderer traces the scene beyond the crop as far as the lens blur reaches; one pixel of
    // padding gives the crop's edge pixels the neighbours the renderer classifies them by (where the
    // padded crop meets the frame's border, both stop alike), so the crop's pixels are the frame's.
    let (px0, py0) = (crop.x0.saturating_sub(1), crop.y0.saturating_sub(1));
    let px1 = (crop.x0 + crop.width + 1).min(w);
    let py1 = (crop.y0 + crop.height + 1).min(h);
    let mut cam = camera.clone();
    cam.image_size = [px1 - px0, py1 - py0];
    cam.params[idx::CX] -= f64::from(px0);
    cam.params[idx::CY] -= f64::from(py0);
    let img = render_radiance(rig, &cam, cam_from_rig, settings)?;
    let respond = response(settings, w, h, camera.cx(), camera.cy());
    let pw = (px1 - px0) as usize;
    let mut out = Vec::with_capacity(crop.len());
    for i in crop.y0..crop.y0 + crop.height {
        for j in crop.x0..crop.x0 + crop.width {
            let v = img.data[(i - py0) as usize * pw + (j - px0) as usize];
            out.push(respond(v, f64::from(j), f64::from(i)));
        }
    }
    Ok(out)
}

/// A parameter of the render the image is differentiated by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Param {
    /// The principal point (px): moves the whole image, every corner by as much.
    Cx,
    Cy,
    /// Focal lengths and skew (px): with `Cx`, `Cy` and `Roll`, any affine change of the image.
    Fx,
    Fy,
    Skew,
    /// The camera turned about its optical axis (radians).
    Roll,
    /// The rig turned about [`View::pivot`] about camera axis `k` (radians).
    Turn(usize),
    /// The rig moved along camera axis `k` (mm).
    Shift(usize),
    /// Reflectance of the black squares.
    Black,
    /// Reflectance of the white squares (and margin).
    White,
    /// Blur σ (px).
    Blur,
    /// The lens's first radial distortion coefficient.
    K1,
}

/// Steps of the reflectances and of the blur σ for the central differences.
const REFLECTANCE_STEP: f64 = 0.005;
const BLUR_STEP_PX: f64 = 0.05;

/// One rendered view and how to differentiate it.
#[derive(Debug, Clone)]
pub struct View<'a> {
    pub rig: &'a Rig,
    pub camera: Camera,
    pub cam_from_rig: Pose,
    pub settings: RenderSettings,
    /// Camera-frame point the rig turns about for [`Param::Turn`] (e.g. the face's centre).
    pub pivot: Vector3<f64>,
    /// Image motion (px) of a geometric parameter's finite-difference step, at the farthest of the
    /// probe points given to [`View::derivative`].
    pub step_px: f64,
}

/// A parameter's derivative image over a crop and the motion of probe points per unit parameter.
#[derive(Debug, Clone)]
pub struct Derivative {
    pub param: Param,
    /// `∂μ/∂θ` per crop pixel (grey levels per unit of the parameter).
    pub image: Vec<f64>,
    /// `∂uv/∂θ` of each probe point (px per unit).
    pub motion: Vec<Vector2<f64>>,
}

impl View<'_> {
    /// The scene with `param` moved by `d`.
    fn moved(&self, param: Param, d: f64) -> (Camera, Pose, RenderSettings) {
        let (mut camera, mut pose, mut settings) =
            (self.camera.clone(), self.cam_from_rig, self.settings);
        let axis = |k: usize| Vector3::from_fn(|i, _| if i == k { 1.0 } else { 0.0 });
        match param {
            Param::Cx => camera.params[idx::CX] += d,
            Param::Cy => camera.params[idx::CY] += d,
            Param::Fx => camera.params[idx::FX] += d,
            Param::Fy => camera.params[idx::FY] += d,
            Param::Skew => camera.params[idx::SKEW] += d,
            Param::Roll => {
                pose = Pose::from_axis_angle(axis(2) * d, Vector3::zeros()).compose(&pose);
            }
            Param::Turn(k) => {
                // X' = R (X − c) + c.
                let r = Rotation3::new(axis(k) * d);
                let turn = Pose {
                    rotation: r,
                    translation: self.pivot - r * self.pivot,
                };
                pose = turn.compose(&pose);
            }
            Param::Shift(k) => pose.translation += axis(k) * d,
            Param::Black => settings.palette.black += d,
            Param::White => settings.palette.white += d,
            Param::Blur => settings.blur_sigma_px += d,
            Param::K1 => camera.params[idx::K1] += d,
        }
        (camera, pose, settings)
    }

    /// Image positions of rig points `probes` with `param` moved by `d` (`None` for one that does
    /// not project).
    fn project(&self, param: Param, d: f64, probes: &[Vector3<f64>]) -> Vec<Option<Vector2<f64>>> {
        let (camera, pose, _) = self.moved(param, d);
        probes
            .iter()
            .map(|x| camera.project(&pose, x).ok())
            .collect()
    }

    /// The finite-difference step of `param`: [`View::step_px`] of image motion at the farthest
    /// moving probe for a geometric parameter, fixed steps for the reflectances and the blur.
    fn step(&self, param: Param, probes: &[Vector3<f64>]) -> f64 {
        match param {
            Param::Black | Param::White => return REFLECTANCE_STEP,
            Param::Blur => return BLUR_STEP_PX,
            _ => {}
        }
        let unit = match param {
            Param::Cx | Param::Cy => return self.step_px,
            Param::Fx | Param::Fy | Param::Skew => 1e-3 * self.camera.fx(),
            Param::K1 => 1e-4,
            Param::Roll | Param::Turn(_) => 1e-6,
            _ => 1e-3,
        };
        let (a, b) = (
            self.project(param, unit, probes),
            self.project(param, -unit, probes),
        );
        let fastest = a
            .iter()
            .zip(&b)
            .filter_map(|(a, b)| Some((a.as_ref()? - b.as_ref()?).norm() / (2.0 * unit)))
            .fold(0.0, f64::max);
        if fastest > 0.0 {
            self.step_px / fastest
        } else {
            unit
        }
    }

    /// `∂μ/∂param` over `crop` by central differences of [`expected_image`], and `∂uv/∂param` of
    /// the rig points `probes` (zero for the reflectances and the blur; a probe that does not
    /// project gets NaN).
    pub fn derivative(
        &self,
        param: Param,
        crop: Crop,
        probes: &[Vector3<f64>],
    ) -> Result<Derivative, SyntheticError> {
        let d = self.step(param, probes);
        let image_at = |d: f64| {
            let (camera, pose, settings) = self.moved(param, d);
            expected_image(self.rig, &camera, &pose, &settings, crop)
        };
        let (plus, minus) = (image_at(d)?, image_at(-d)?);
        let image = plus
            .iter()
            .zip(&minus)
            .map(|(p, m)| (p - m) / (2.0 * d))
            .collect();
        let motion = self
            .project(param, d, probes)
            .iter()
            .zip(&self.project(param, -d, probes))
            .map(|(a, b)| match (a, b) {
                (Some(a), Some(b)) => (a - b) / (2.0 * d),
                _ => Vector2::repeat(f64::NAN),
            })
            .collect();
        Ok(Derivative {
            param,
            image,
            motion,
        })
    }
}

/// The Fisher information `(1/var) Σ_pixels ∂μ/∂θ ∂μ/∂θᵀ` of the crop indices `pixels` for the
/// derivative images `derivs`.
pub fn fisher(derivs: &[&[f64]], pixels: &[usize], var: f64) -> DMatrix<f64> {
    let n = derivs.len();
    let mut info = DMatrix::zeros(n, n);
    let mut row = DVector::zeros(n);
    for &k in pixels {
        for (r, d) in row.iter_mut().zip(derivs) {
            *r = d[k];
        }
        info.ger(1.0 / var, &row, &row, 1.0);
    }
    info
}

/// The covariance bound of a position whose derivative images are `position` (its two coordinates:
/// images moving the position by one pixel along x and y, everything else fixed) with the nuisance
/// parameters `nuisance` unknown, each with the position's motion per unit of it: `(I_pp − I_pν
/// I_νν⁺ I_νp)⁻¹` after re-expressing each nuisance so that it does not move the position. Nuisance
/// directions the pixels carry no information on are dropped by the pseudo-inverse (`I_νν`'s
/// eigenvalues below 1e-9 of its largest); they cannot lower the information on the position.
/// `None` if the position is not determined.
pub fn efficient_position_covariance(
    position: [&[f64]; 2],
    nuisance: &[(&[f64], Vector2<f64>)],
    pixels: &[usize],
    var: f64,
) -> Option<Matrix2<f64>> {
    let fixed: Vec<Vec<f64>> = nuisance
        .iter()
        .map(|(d, m)| {
            d.iter()
                .zip(position[0].iter().zip(position[1]))
                .map(|(v, (px, py))| v - m.x * px - m.y * py)
                .collect()
        })
        .collect();
    let mut all: Vec<&[f64]> = vec![position[0], position[1]];
    all.extend(fixed.iter().map(Vec::as_slice));
    let info = fisher(&all, pixels, var);
    let ipp = info.fixed_view::<2, 2>(0, 0).into_owned();
    let n = nuisance.len();
    let efficient = if n == 0 {
        ipp
    } else {
        let inn = info.view((2, 2), (n, n)).into_owned();
        let ipn = info.view((0, 2), (2, n)).into_owned();
        let pinv = pseudo_inverse(inn)?;
        let schur = &ipn * pinv * ipn.transpose();
        ipp - Matrix2::from_fn(|r, c| schur[(r, c)])
    };
    efficient.try_inverse()
}

/// The covariance bound `J I⁻¹ Jᵀ` of a position moving by `motions` (px per unit) with the
/// parameters whose derivative images are `derivs`, all unknown. `None` if the information is
/// singular.
pub fn position_covariance_through(
    derivs: &[&[f64]],
    motions: &[Vector2<f64>],
    pixels: &[usize],
    var: f64,
) -> Option<Matrix2<f64>> {
    let info = fisher(derivs, pixels, var);
    let cov = info.try_inverse()?;
    let j = DMatrix::from_fn(2, motions.len(), |r, c| motions[c][r]);
    let out = &j * cov * j.transpose();
    Some(Matrix2::from_fn(|r, c| out[(r, c)]))
}

/// Moore–Penrose inverse of a symmetric positive semi-definite matrix, eigenvalues below 1e-9 of the
/// largest treated as 0.
fn pseudo_inverse(m: DMatrix<f64>) -> Option<DMatrix<f64>> {
    let eig = m.symmetric_eigen();
    let top = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    if !top.is_finite() {
        return None;
    }
    let inv = eig
        .eigenvalues
        .map(|e| if e > 1e-9 * top { 1.0 / e } else { 0.0 });
    Some(&eig.eigenvectors * DMatrix::from_diagonal(&inv) * eig.eigenvectors.transpose())
}

/// The crop indices of the pixels whose centre sees face `face`'s board (squares or margin) from the
/// front. Occlusion by other faces is not checked (none occludes another on a convex rig).
pub fn face_pixels(
    rig: &Rig,
    camera: &Camera,
    cam_from_rig: &Pose,
    face: usize,
    crop: Crop,
) -> Vec<usize> {
    let f = &rig.faces[face];
    let rig_from_cam = cam_from_rig.inverse();
    let centre = rig_from_cam.translation;
    let (n, offset) = (f.normal(), f.normal().dot(&f.origin));
    (0..crop.len())
        .filter(|&k| {
            let [x, y] = crop.pixel(k);
            let Ok(ray) = camera.unproject(f64::from(x), f64::from(y)) else {
                return false;
            };
            let d = rig_from_cam.rotation * ray;
            let denom = n.dot(&d);
            if denom >= 0.0 {
                return false;
            }
            let t = (offset - n.dot(&centre)) / denom;
            let (a, b) = f.local(&(centre + d * t));
            t > 0.0 && f.region_at(a, b) != BoardRegion::Outside
        })
        .collect()
}

/// The four bounds of one corner (covariance matrices, px²; see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CornerBound {
    pub window_position: Matrix2<f64>,
    pub window_local: Matrix2<f64>,
    pub face_position: Matrix2<f64>,
    pub face_joint: Matrix2<f64>,
    /// [`CornerBound::face_joint`] with the lens's `k1` unknown too.
    pub face_joint_k1: Matrix2<f64>,
}

/// The local corner model's nuisances besides the position: any affine change of the image
/// (with the position), the two reflectances and the blur.
pub const LOCAL_PARAMS: [Param; 7] = [
    Param::Fx,
    Param::Fy,
    Param::Skew,
    Param::Roll,
    Param::Black,
    Param::White,
    Param::Blur,
];

/// A whole-face joint fit's unknowns with the camera known: the face's pose (6), and the levels and
/// blur shared with the local model.
pub const FACE_PARAMS: [Param; 9] = [
    Param::Turn(0),
    Param::Turn(1),
    Param::Turn(2),
    Param::Shift(0),
    Param::Shift(1),
    Param::Shift(2),
    Param::Black,
    Param::White,
    Param::Blur,
];

/// The parameters [`corner_bounds`] needs derivatives of: the position (2), [`LOCAL_PARAMS`], the
/// face's pose (the rest of [`FACE_PARAMS`]) and `k1`.
pub const PARAMS: [Param; 16] = [
    Param::Cx,
    Param::Cy,
    Param::Fx,
    Param::Fy,
    Param::Skew,
    Param::Roll,
    Param::Black,
    Param::White,
    Param::Blur,
    Param::Turn(0),
    Param::Turn(1),
    Param::Turn(2),
    Param::Shift(0),
    Param::Shift(1),
    Param::Shift(2),
    Param::K1,
];

/// The derivatives of every parameter of [`PARAMS`] over `crop`, with probes `probes`.
pub fn derivatives(
    view: &View<'_>,
    crop: Crop,
    probes: &[Vector3<f64>],
) -> Result<Vec<Derivative>, SyntheticError> {
    PARAMS
        .iter()
        .map(|&p| view.derivative(p, crop, probes))
        .collect()
}

/// The bounds of probe `probe` (an index into the probes `derivs` were computed with) over its fit
/// window `window` and its face's pixels `face` (crop indices), with noise variance `var`. `None` if
/// a bound is undetermined (no information).
pub fn corner_bounds(
    derivs: &[Derivative],
    probe: usize,
    window: &[usize],
    face: &[usize],
    var: f64,
) -> Option<CornerBound> {
    let get = |p: Param| derivs.iter().find(|d| d.param == p);
    let pos = [
        get(Param::Cx)?.image.as_slice(),
        get(Param::Cy)?.image.as_slice(),
    ];
    let local: Vec<(&[f64], Vector2<f64>)> = LOCAL_PARAMS
        .iter()
        .map(|&p| get(p).map(|d| (d.image.as_slice(), d.motion[probe])))
        .collect::<Option<_>>()?;
    let joint: Vec<&Derivative> = FACE_PARAMS.iter().map(|&p| get(p)).collect::<Option<_>>()?;
    let mut joint_images: Vec<&[f64]> = joint.iter().map(|d| d.image.as_slice()).collect();
    let mut joint_motion: Vec<Vector2<f64>> = joint.iter().map(|d| d.motion[probe]).collect();
    let face_joint = position_covariance_through(&joint_images, &joint_motion, face, var)?;
    let k1 = get(Param::K1)?;
    joint_images.push(&k1.image);
    joint_motion.push(k1.motion[probe]);
    Some(CornerBound {
        window_position: efficient_position_covariance(pos, &[], window, var)?,
        window_local: efficient_position_covariance(pos, &local, window, var)?,
        face_position: efficient_position_covariance(pos, &[], face, var)?,
        face_joint,
        face_joint_k1: position_covariance_through(&joint_images, &joint_motion, face, var)?,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::detect::score::EvalSet;
    use crate::render::{finish, render_radiance};

    /// The crop's expected image is the frame's, and rounds to the noise-free render.
    #[test]
    fn expected_image_is_the_render_before_noise() {
        let (rig, _) = Rig::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/fixtures/rigs/cube_outside.toml"
        )))
        .unwrap();
        let set = EvalSet::Hard;
        let mut camera = set.camera();
        camera.image_size = [320, 240];
        camera.params[idx::CX] = 159.5;
        camera.params[idx::CY] = 119.5;
        camera.params[idx::FX] = 175.0;
        camera.params[idx::FY] = 175.0;
        let pose = set.poses(&rig, 1)[0];
        let settings = RenderSettings {
            noise_sigma: 0.0,
            ..set.settings()
        };
        let frame = finish(
            &render_radiance(&rig, &camera, &pose, &settings).unwrap(),
            &camera,
            &settings,
            0,
        );
        let full = Crop {
            x0: 0,
            y0: 0,
            width: 320,
            height: 240,
        };
        let mu = expected_image(&rig, &camera, &pose, &settings, full).unwrap();
        let mut edges = 0;
        for (k, m) in mu.iter().enumerate() {
            let [x, y] = full.pixel(k);
            assert_eq!(
                frame.get_pixel(x, y).0[0],
                m.round().clamp(0.0, 255.0) as u8
            );
            edges += usize::from((m - mu[0]).abs() > 1.0);
        }
        assert!(
            edges > 1000,
            "the view shows the rig ({edges} pixels differ)"
        );
        let crop = Crop {
            x0: 100,
            y0: 60,
            width: 90,
            height: 70,
        };
        let part = expected_image(&rig, &camera, &pose, &settings, crop).unwrap();
        for (k, p) in part.iter().enumerate() {
            let f = mu[full.index(crop.pixel(k)).unwrap()];
            assert!((p - f).abs() < 1e-9, "{p} vs {f}");
        }
    }
}
