//! The Cramér–Rao bounds of `detect::crlb` against what they must be: the closed form of an
//! axis-aligned blurred X-junction, and the scatter of the detector's own corner fit on fresh noise
//! (an efficient unbiased fit cannot beat the bound, and ours should come close to it). The figures
//! on the evaluation sets come from `cargo run --release --example crlb -- hard 24 target/detect_eval`.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/normal.rs"]
mod normal;

use cubecal::camera::{Camera, Pose};
use cubecal::detect::crlb::{
    Crop, LOCAL_PARAMS, Param, View, efficient_position_covariance, expected_image, noise_variance,
};
use cubecal::detect::refine::{refine_near_border, refine_near_border_with_window};
use cubecal::render::correspondences::look_at;
use cubecal::render::{Palette, RenderSettings};
use cubecal::rig::Rig;
use nalgebra::{Vector2, Vector3};
use normal::{normal_cdf, normal_pdf};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// One board of 5×4 inner corners, 16 mm squares, in the plane z = 0 facing +z.
fn board() -> Rig {
    let toml = r#"
        name = "board"
        units = "mm"
        up = [0, 1, 0]
        [[faces]]
        name = "board"
        cols = 5
        rows = 4
        square_mm = 16.0
        margin_mm = 10.0
        origin = [0, 0, 0]
        col_dir = [1, 0, 0]
        row_dir = [0, 1, 0]
    "#;
    Rig::from_toml_str(toml, "board.toml").unwrap().0
}

/// A frontal, axis-aligned, high-contrast corner: the bound on its position over a square block of
/// pixels is the closed form of a blurred step edge. The renderer blurs the scene (a Gaussian of σ_b)
/// before the pixels integrate it, so with the image `m + h·P(x)·P(y)` (grey levels), pixel `j` of an
/// edge at `e` holds `P(j) = ∫ over [j−½, j+½] of (2Φ((x − e)/σ_b) − 1) dx = 2σ_b[Ψ(t₊) − Ψ(t₋)] − 1`
/// (`Ψ(t) = tΦ(t) + φ(t)`, `t± = (j ± ½ − e)/σ_b`), and moving the corner by `δx` changes pixel `(i, j)`
/// by `−2h·K(j − e)·P(y_i)·δx` with `K` the box ⊛ Gaussian kernel, `K(d) = Φ((d + ½)/σ_b) −
/// Φ((d − ½)/σ_b)`. So `I_xx = (2h/σ)² Σ_j K(j − e)² Σ_i P(y_i)²`, and for a long block `Σ K² ≈
/// 1/(2√π s)`, `Σ P² ≈ n − 4s/√π` (`n` rows, `s² = σ_b² + 1/12`).
#[test]
fn frontal_corner_bound_is_the_step_edge_closed_form() {
    let rig = board();
    let corner = rig.faces[0].corner_xyz(1, 2);
    // Looking straight at the corner from 400 mm: 40 px squares, the corner at (cx, cy).
    let pose: Pose = look_at(
        &(corner + Vector3::new(0.0, 0.0, 400.0)),
        &corner,
        &Vector3::new(0.0, 1.0, 0.0),
    );
    let (xc, yc) = (100.2, 80.3);
    let camera = Camera::pinhole([200, 160], 1000.0, 1000.0, xc, yc);
    let (black, white, blur, noise) = (0.1, 0.9, 1.2, 2.0);
    let settings = RenderSettings {
        supersample: 16,
        blur_sigma_px: blur,
        noise_sigma: noise,
        gamma: 1.0,
        vignetting: 0.0,
        shading: false,
        palette: Palette {
            black,
            white,
            ..Palette::default()
        },
        ..RenderSettings::default()
    };
    let view = View {
        rig: &rig,
        camera: camera.clone(),
        cam_from_rig: pose,
        settings,
        pivot: pose.transform(&corner),
        // 2 × 0.125 px = 4 of the 16 sub-samples per pixel: the difference is exact.
        step_px: 0.125,
    };
    let half = 12u32;
    let crop = Crop {
        x0: 100 - half,
        y0: 80 - half,
        width: 2 * half + 1,
        height: 2 * half + 1,
    };
    let dx = view.derivative(Param::Cx, crop, &[corner]).unwrap();
    let dy = view.derivative(Param::Cy, crop, &[corner]).unwrap();
    assert!((dx.motion[0] - Vector2::new(1.0, 0.0)).norm() < 1e-9);
    let all: Vec<usize> = (0..crop.len()).collect();
    let var = noise_variance(&settings);
    let cov = efficient_position_covariance([&dx.image, &dy.image], &[], &all, var).unwrap();

    // The closed form on the pixel grid.
    let h = 255.0 * (white - black) / 2.0;
    let psi = |t: f64| t * normal_cdf(t) + normal_pdf(t);
    let profile = |p: i64, edge: f64| -> f64 {
        let t = |d: f64| (p as f64 + d - edge) / blur;
        2.0 * blur * (psi(t(0.5)) - psi(t(-0.5))) - 1.0
    };
    let slope = |p: i64, edge: f64| -> f64 {
        let t = |d: f64| (p as f64 + d - edge) / blur;
        2.0 * (normal_cdf(t(0.5)) - normal_cdf(t(-0.5)))
    };
    let range = |c: i64| (c - i64::from(half))..=(c + i64::from(half));
    let (sk2x, sp2y): (f64, f64) = (
        range(100).map(|j| slope(j, xc).powi(2)).sum(),
        range(80).map(|i| profile(i, yc).powi(2)).sum(),
    );
    let (sk2y, sp2x): (f64, f64) = (
        range(80).map(|i| slope(i, yc).powi(2)).sum(),
        range(100).map(|j| profile(j, xc).powi(2)).sum(),
    );
    let ixy: f64 = range(100)
        .map(|j| slope(j, xc) * profile(j, xc))
        .sum::<f64>()
        * range(80)
            .map(|i| slope(i, yc) * profile(i, yc))
            .sum::<f64>();
    let info = nalgebra::Matrix2::new(sk2x * sp2y, ixy, ixy, sk2y * sp2x) * (h * h / var);
    let closed = info.try_inverse().unwrap();
    for (a, b) in cov.iter().zip(closed.iter()) {
        assert!(
            (a - b).abs() < 2e-3 * closed[(0, 0)],
            "render-based bound {cov} vs closed form {closed}"
        );
    }
    // The continuous approximation, to within the pixel grid's effect on the sums.
    let s = (blur * blur + 1.0 / 12.0).sqrt();
    let n = f64::from(2 * half + 1);
    let pi_sqrt = std::f64::consts::PI.sqrt();
    let continuous = var / ((2.0 * h).powi(2) / (2.0 * pi_sqrt * s) * (n - 4.0 * s / pi_sqrt));
    let rel = cov[(0, 0)] / continuous - 1.0;
    assert!(
        rel.abs() < 0.03,
        "σx² {} vs continuous {continuous} ({:+.1} %)",
        cov[(0, 0)],
        100.0 * rel
    );
    eprintln!(
        "frontal corner: bound σx {:.5} px, σy {:.5} px, closed form σx {:.5} px, continuous {:.5} px",
        cov[(0, 0)].sqrt(),
        cov[(1, 1)].sqrt(),
        closed[(0, 0)].sqrt(),
        continuous.sqrt()
    );
}

/// The detector's corner fit on fresh noise over a hard-set-like oblique corner (low contrast, blur
/// σ 1.5, noise σ 5, gamma 2.2): its scatter is at least the bound with the local model's unknowns
/// (allowing for the sampling error of the scatter) and close to it — the bound is the right one for
/// that fit, which leaves little to gain inside its window.
#[test]
fn the_corner_fit_scatters_at_its_window_bound() {
    let rig = board();
    let face = &rig.faces[0];
    let corner = face.corner_xyz(1, 2);
    // 55° from the board's normal, turned about both board axes: oblique lattice lines.
    let dir = Vector3::new(0.45, 0.55, 0.0).normalize() * 55f64.to_radians().sin()
        + Vector3::new(0.0, 0.0, 55f64.to_radians().cos());
    let pose = look_at(
        &(corner + dir * 300.0),
        &corner,
        &Vector3::new(0.0, 1.0, 0.0),
    );
    let camera = Camera::pinhole([160, 120], 600.0, 600.0, 80.3, 60.1);
    let settings = RenderSettings {
        supersample: 16,
        blur_sigma_px: 1.5,
        noise_sigma: 5.0,
        gamma: 2.2,
        palette: Palette {
            black: 0.3,
            white: 0.55,
            ..Palette::default()
        },
        ..RenderSettings::default()
    };
    let truth = camera.project(&pose, &corner).unwrap();
    let at = |r: usize, c: usize| camera.project(&pose, &face.corner_xyz(r, c)).unwrap();
    let (a, b) = ((at(1, 3) - at(1, 1)) / 2.0, (at(2, 2) - at(0, 2)) / 2.0);
    let crop = Crop::around([truth], 30.0, camera.image_size).unwrap();
    let mu = expected_image(&rig, &camera, &pose, &settings, crop).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(19);
    let noise = Normal::new(0.0, settings.noise_sigma).unwrap();
    let mut img = image::GrayImage::new(160, 120);
    let mut draw = |img: &mut image::GrayImage| {
        for (k, m) in mu.iter().enumerate() {
            let [x, y] = crop.pixel(k);
            let v = (m + noise.sample(&mut rng)).round().clamp(0.0, 255.0);
            img.put_pixel(x, y, image::Luma([v as u8]));
        }
    };
    draw(&mut img);
    let (_, window) = refine_near_border_with_window(&img, truth, a, b).unwrap();
    let pixels: Vec<usize> = window.iter().filter_map(|&p| crop.index(p)).collect();
    assert_eq!(pixels.len(), window.len(), "the window lies in the crop");

    let view = View {
        rig: &rig,
        camera: camera.clone(),
        cam_from_rig: pose,
        settings,
        pivot: pose.transform(&corner),
        step_px: 0.1,
    };
    let d = |p: Param| view.derivative(p, crop, &[corner]).unwrap();
    let (dx, dy) = (d(Param::Cx), d(Param::Cy));
    let nuisance: Vec<_> = LOCAL_PARAMS.map(d).into_iter().collect();
    let local: Vec<(&[f64], Vector2<f64>)> = nuisance
        .iter()
        .map(|n| (n.image.as_slice(), n.motion[0]))
        .collect();
    let var = noise_variance(&settings);
    let position = efficient_position_covariance([&dx.image, &dy.image], &[], &pixels, var)
        .unwrap()
        .trace();
    let bound = efficient_position_covariance([&dx.image, &dy.image], &local, &pixels, var)
        .unwrap()
        .trace();
    // The finite differences have converged: a finer sub-sample grid and a smaller step agree.
    let fine = View {
        settings: RenderSettings {
            supersample: 32,
            ..settings
        },
        step_px: 0.05,
        ..view.clone()
    };
    let fd = |p: Param| fine.derivative(p, crop, &[corner]).unwrap().image;
    let finer = efficient_position_covariance([&fd(Param::Cx), &fd(Param::Cy)], &[], &pixels, var)
        .unwrap()
        .trace();
    assert!(
        (finer / position - 1.0).abs() < 0.02,
        "16×16 samples, 0.1 px steps: {position}; 32×32, 0.05 px: {finer}"
    );
    assert!(
        bound >= position * (1.0 - 1e-9),
        "unknowns cannot add information: {bound} < {position}"
    );

    let draws = 300;
    let mut fits = Vec::new();
    for _ in 0..draws {
        draw(&mut img);
        fits.push(refine_near_border(&img, truth, a, b).unwrap().uv);
    }
    let n = fits.len() as f64;
    let mean = fits.iter().sum::<Vector2<f64>>() / n;
    let scatter = fits.iter().map(|p| (p - mean).norm_squared()).sum::<f64>() / (n - 1.0);
    // The trace of a sample covariance of n draws scatters by about 1/√n of itself.
    let sampling = 1.0 / n.sqrt();
    let ratio = scatter / bound;
    eprintln!(
        "oblique corner: fit scatter RMS {:.4} px over {draws} draws, bound RMS {:.4} px (position only {:.4}), ratio of variances {ratio:.3} ± {sampling:.3}; bias {:.4} px",
        scatter.sqrt(),
        bound.sqrt(),
        position.sqrt(),
        (mean - truth).norm()
    );
    assert!(
        ratio > 1.0 - 4.0 * sampling,
        "the fit beats the bound: {ratio}"
    );
    assert!(ratio < 1.5, "the fit is far from efficient: {ratio}");
}
