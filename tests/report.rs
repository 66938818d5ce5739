//! Run and profile reports: the plots show the data they are given (element counts and positions in
//! the SVG, against data with known values), residuals recomputed from a calibration equal the
//! offsets put into the observations, a profile history with known parameter moves is plotted at
//! the right distances in σ, and whole reports of a good and a poor-coverage run and of stored
//! profiles are written (HTML with every plot inline and every thumbnail embedded, PNGs beside it
//! that decode), also through the CLI.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod report_support;

use std::collections::HashMap;
use std::path::Path;

use cubecal::calib::init::InitMethod;
use cubecal::calib::observations::{RawObservations, RawPoint, RawView};
use cubecal::calib::report::{CalibrationReport, DistortionReport, ViewReport};
use cubecal::camera::{Camera, DistortionModel, Pose};
use cubecal::report::analysis::{self, CoverageGrid};
use cubecal::report::plots::{
    self, CoverageFigure, HistogramFigure, PointKind, ResidualFigure, ViewRmsFigure,
};
use cubecal::report::{HeldOutPose, RunData};
use nalgebra::{Vector2, Vector3};
use report_support::{Kind, Param, build_history, build_run, drifting_camera};

/// Attributes of every `<tag ...>` element of an SVG document.
fn elements(svg: &str, tag: &str) -> Vec<HashMap<String, String>> {
    let open = format!("<{tag} ");
    let mut out = Vec::new();
    let mut rest = svg;
    while let Some(i) = rest.find(&open) {
        rest = &rest[i + open.len()..];
        let end = rest.find('>').unwrap();
        let body = &rest[..end];
        let mut attrs = HashMap::new();
        let mut s = body;
        while let Some(eq) = s.find("=\"") {
            let key = s[..eq].trim().to_string();
            let after = &s[eq + 2..];
            let close = after.find('"').unwrap();
            attrs.insert(key, after[..close].to_string());
            s = &after[close + 1..];
        }
        out.push(attrs);
    }
    out
}

fn num(a: &HashMap<String, String>, k: &str) -> f64 {
    a[k].parse().unwrap()
}

#[test]
fn coverage_plot_draws_every_corner_where_it_is() {
    let size = [1280, 960];
    // A 7×5 lattice spanning the whole frame, corners included, in two faces.
    let mut pts = Vec::new();
    for j in 0..5u32 {
        for i in 0..7u32 {
            let u = -0.5 + 1280.0 * f64::from(i) / 6.0;
            let v = -0.5 + 960.0 * f64::from(j) / 4.0;
            pts.push(((u.min(1279.4), v.min(959.4)), Some(((i + j) % 2) as usize)));
        }
    }
    let grid = CoverageGrid::count(
        pts.iter().map(|&((u, v), _)| Vector2::new(u, v)),
        size,
        (8, 6),
    );
    let fig = CoverageFigure {
        image_size: size,
        points: pts.clone(),
        face_names: vec!["top".into(), "side-x".into()],
        grid: grid.clone(),
    };
    let (svg, g) = plots::to_svg(&fig).unwrap();
    let circles = elements(&svg, "circle");
    assert_eq!(circles.len(), pts.len());
    // Face colours: 18 of face 0 (red), 17 of face 1 (green).
    let red = circles.iter().filter(|c| c["fill"] == "#E6194B").count();
    assert_eq!(red, 18);
    // Extent: the circles span the image area of the chart, and every one is where its point maps.
    for (c, &((u, v), _)) in circles.iter().zip(&pts) {
        let (x, y) = g.to_px(u, v);
        assert!((num(c, "cx") - x).abs() <= 1.0, "cx {} vs {x}", c["cx"]);
        assert!((num(c, "cy") - y).abs() <= 1.0, "cy {} vs {y}", c["cy"]);
    }
    let min_x = circles
        .iter()
        .map(|c| num(c, "cx"))
        .fold(f64::MAX, f64::min);
    let max_y = circles
        .iter()
        .map(|c| num(c, "cy"))
        .fold(f64::MIN, f64::max);
    assert!((min_x - f64::from(g.px_x.0)).abs() <= 1.0);
    assert!((max_y - f64::from(g.px_y.1)).abs() <= 1.5);
    // The image keeps its aspect ratio: 1280×960 → 4:3 plotting area.
    let aspect = f64::from(g.px_x.1 - g.px_x.0) / f64::from(g.px_y.1 - g.px_y.0);
    assert!((aspect - 4.0 / 3.0).abs() < 0.01, "{aspect}");
    // Covered cells are drawn green: the 7 lattice columns fall in grid columns 0, 1, 2, 4, 5, 6, 7
    // and the 5 rows in grid rows 0, 1, 3, 4, 5 (pixel-centre convention): 35 cells.
    assert_eq!(grid.covered(), 35);
    let green = elements(&svg, "rect")
        .into_iter()
        .filter(|r| r["fill"] == "#C8EBC8" && num(r, "y") < f64::from(g.px_y.1))
        .count();
    assert_eq!(
        green, 35,
        "green cells in the plotting area (the legend swatch is below it)"
    );
}

#[test]
fn residual_arrows_have_the_residuals_length_and_direction() {
    let size = [1000, 800];
    let arrows: Vec<_> = (0..40)
        .map(|k| {
            let a = f64::from(k) * 0.3;
            let r = 0.1 + 0.02 * f64::from(k);
            let kind = match k % 3 {
                0 => PointKind::Fitted,
                1 => PointKind::HeldOut,
                _ => PointKind::Outlier,
            };
            (
                (100.0 + 20.0 * f64::from(k), 400.0),
                (r * a.cos(), r * a.sin()),
                kind,
            )
        })
        .collect();
    let norms: Vec<f64> = arrows
        .iter()
        .map(|(_, (x, y), _)| f64::hypot(*x, *y))
        .collect();
    let (scale, bar) = ResidualFigure::choose_scale(size, &norms);
    assert!(scale > 0.0 && bar > 0.0);
    let fig = ResidualFigure {
        image_size: size,
        arrows: arrows.clone(),
        scale,
        bar_px: bar,
    };
    let (svg, g) = plots::to_svg(&fig).unwrap();
    // One polyline per arrow in its kind's colour (axes and the black scale bar are the others).
    let colours = ["#0072B2", "#E69F00", "#D52828"];
    let lines: Vec<_> = elements(&svg, "polyline")
        .into_iter()
        .filter(|l| {
            l.get("stroke")
                .is_some_and(|s| colours.contains(&s.as_str()))
        })
        .collect();
    assert_eq!(lines.len(), arrows.len());
    let px_per_u = f64::from(g.px_x.1 - g.px_x.0) / 1000.0;
    for (l, ((u, v), (ru, rv), kind)) in lines.iter().zip(&arrows) {
        let p: Vec<f64> = l["points"]
            .split([' ', ','])
            .filter(|s| !s.is_empty())
            .map(|s| s.parse().unwrap())
            .collect();
        let (x0, y0) = g.to_px(*u, *v);
        assert!((p[0] - x0).abs() <= 1.0 && (p[1] - y0).abs() <= 1.0);
        let (dx, dy) = (p[2] - p[0], p[3] - p[1]);
        let want = (ru * scale * px_per_u, rv * scale * px_per_u);
        assert!((dx - want.0).abs() <= 1.5, "{dx} vs {}", want.0);
        assert!((dy - want.1).abs() <= 1.5, "{dy} vs {}", want.1);
        let colour = match kind {
            PointKind::Fitted => "#0072B2",
            PointKind::HeldOut => "#E69F00",
            PointKind::Outlier => "#D52828",
        };
        assert_eq!(l["stroke"], colour);
    }
}

#[test]
fn histogram_bars_have_the_counts() {
    // 1000 deterministic values with known bins: value k·0.01 − 2 for k in 0..400 (σ = 1).
    let values: Vec<f64> = (0..400).map(|k| f64::from(k) * 0.01 - 2.0).collect();
    let hist = analysis::histogram(values.iter().copied(), 1.0);
    assert_eq!(hist.outside, 0);
    // Bins of 0.25 from −2 to 2: 16 bins of 25 values each.
    assert_eq!(hist.counts.iter().filter(|&&c| c == 25).count(), 16);
    let fig = HistogramFigure {
        hist: hist.clone(),
        sigma_px: 1.0,
    };
    let (svg, g) = plots::to_svg(&fig).unwrap();
    let bars: Vec<_> = elements(&svg, "rect")
        .into_iter()
        .filter(|r| r["fill"] == "#0072B2")
        .collect();
    assert_eq!(bars.len(), 16);
    let px_per_count = f64::from(g.px_y.1 - g.px_y.0) / (g.data_y.0 - g.data_y.1);
    for b in &bars {
        assert!(
            (num(b, "height") - 25.0 * px_per_count).abs() <= 1.5,
            "{}",
            b["height"]
        );
        // Bars sit between x = −2 and 2.
        let (l, _) = g.to_px(-2.0, 0.0);
        let (r, _) = g.to_px(2.0, 0.0);
        assert!(num(b, "x") >= l - 1.0 && num(b, "x") + num(b, "width") <= r + 1.0);
    }
}

fn camera_report(cam: &Camera, views: Vec<ViewReport>) -> CalibrationReport {
    let k = cam.k_matrix();
    CalibrationReport {
        image_size: cam.image_size,
        camera_matrix: [
            [k[(0, 0)], k[(0, 1)], k[(0, 2)]],
            [k[(1, 0)], k[(1, 1)], k[(1, 2)]],
            [0.0, 0.0, 1.0],
        ],
        distortion: DistortionReport {
            model: cam.model.name().to_string(),
            coefficients: cam.distortion_coefficients(),
        },
        std_dev: Default::default(),
        free_params: vec!["fx".into(), "cx".into()],
        covariance: vec![vec![4.0, 0.0], vec![0.0, 0.25]],
        rms_px: 0.0,
        rms_reprojection_px: 0.0,
        sigma_px: 0.3,
        noise_scale: None,
        n_points: 0,
        n_params: 0,
        views,
        iterations: 1,
        termination: "test".into(),
        converged: true,
        init_method: InitMethod::Dlt,
    }
}

fn rows(p: &Pose) -> [[f64; 3]; 3] {
    let m = p.rotation.matrix();
    [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ]
}

#[test]
fn residuals_are_the_offsets_put_into_the_observations() {
    let cam = Camera::pinhole([800, 600], 700.0, 700.0, 400.0, 300.0)
        .with_distortion(DistortionModel::Brown5, &[-0.1, 0.01, 0.0, 0.0, 0.0]);
    let fitted = Pose::from_axis_angle(
        Vector3::new(0.1, -0.2, 0.05),
        Vector3::new(-50.0, -40.0, 600.0),
    );
    let held = Pose::from_axis_angle(
        Vector3::new(-0.2, 0.1, 0.0),
        Vector3::new(-30.0, -60.0, 650.0),
    );
    let mut views = Vec::new();
    let mut offsets = Vec::new();
    for (vi, pose) in [fitted, held].iter().enumerate() {
        let mut points = Vec::new();
        for k in 0..30 {
            let xyz = Vector3::new(
                f64::from(k % 6) * 20.0,
                f64::from(k / 6) * 20.0,
                f64::from(k % 3) * 10.0,
            );
            let off = Vector2::new(0.1 * f64::from(k % 5) - 0.2, 0.05 * f64::from(k % 7) - 0.15);
            let uv = cam.project(pose, &xyz).unwrap() + off;
            offsets.push((vi, off));
            points.push(RawPoint {
                xyz: xyz.into(),
                uv: uv.into(),
                face: Some("top".into()),
                cov: None,
            });
        }
        views.push(RawView {
            name: Some(format!("v{vi}")),
            points,
            frame: None,
            held_out: vi == 1,
        });
    }
    let obs = RawObservations {
        image_size: [800, 600],
        views,
    };
    let cal = camera_report(
        &cam,
        vec![ViewReport {
            name: "v0".into(),
            rotation: rows(&fitted),
            translation: fitted.translation.into(),
            rvec: fitted.rvec().into(),
            rms_px: 0.0,
            n_points: 30,
            outliers: vec![3, 7],
            rotation_std_deg: [0.0; 3],
            translation_std: [0.0; 3],
        }],
    );
    let held_out = vec![HeldOutPose {
        name: "v1".into(),
        rms_px: 0.0,
        rotation: rows(&held),
        translation: held.translation.into(),
    }];
    let cam2 = analysis::camera_from_report(&cal).unwrap();
    let (res, stats, skipped) = analysis::residuals(&cam2, &obs, &cal, &held_out);
    assert!(skipped.is_empty());
    assert_eq!(res.len(), 60);
    for (r, (vi, off)) in res.iter().zip(&offsets) {
        assert_eq!(r.view, *vi);
        assert!((r.r - off).norm() < 1e-9, "{} vs {off}", r.r);
        assert_eq!(r.held_out, *vi == 1);
    }
    assert_eq!(res.iter().filter(|r| r.outlier).count(), 2);
    // Per-view RMS over the inliers: √(Σr² / 2n).
    let want = |vi: usize, skip: &[usize]| {
        let v: Vec<_> = offsets
            .iter()
            .filter(|(i, _)| *i == vi)
            .enumerate()
            .filter(|(j, _)| !skip.contains(j))
            .map(|(_, (_, o))| o.norm_squared())
            .collect();
        (v.iter().sum::<f64>() / (2 * v.len()) as f64).sqrt()
    };
    assert!((stats[0].rms_px - want(0, &[3, 7])).abs() < 1e-9);
    assert!((stats[1].rms_px - want(1, &[])).abs() < 1e-9);
    assert!(stats[1].held_out && stats[0].n_outliers == 2);
    // The per-view plot draws one bar per view in its colour.
    let fig = ViewRmsFigure {
        stats: stats.clone(),
        sigma_px: 0.3,
        outlier_above: Some(10.0),
    };
    let (svg, _) = plots::to_svg(&fig).unwrap();
    let rects = elements(&svg, "rect");
    assert_eq!(rects.iter().filter(|r| r["fill"] == "#0072B2").count(), 1);
    assert_eq!(rects.iter().filter(|r| r["fill"] == "#E69F00").count(), 1);
    // Uncertainty from σ_cx = 0.5 px and σ_fx = 2 px: at the principal point only cx counts.
    let cov = analysis::full_covariance(&cal).unwrap();
    let s = analysis::projection_sigma(&cam2, &cov, 400.0, 300.0, 600.0);
    assert!((s - 0.5).abs() < 1e-9, "{s}");
}

#[test]
fn reports_of_a_good_and_a_poor_coverage_run() {
    let tmp = tempfile::tempdir().unwrap();
    let good = build_run(&tmp.path().join("good"), Kind::Good { n: 5 }, 640, 480);
    let html_path = cubecal::report::write_run_report(&good).unwrap();
    let html = std::fs::read_to_string(&html_path).unwrap();
    let data = RunData::load(&good).unwrap();
    assert!(data.result.verdict.pass, "{:?}", data.result.verdict);
    assert!(html.contains("PASS: calibration accepted"));
    // Six plots inline, one thumbnail per captured frame (5 accepted + 1 rejected).
    assert_eq!(html.matches("<svg ").count(), 6);
    assert_eq!(html.matches("src=\"data:image/png;base64,").count(), 6);
    assert!(html.contains("rejected: "));
    for name in [
        "coverage",
        "residuals",
        "histogram",
        "views",
        "distortion",
        "uncertainty",
    ] {
        let png = good.join("report_plots").join(format!("{name}.png"));
        let img = image::open(&png).unwrap();
        assert!(img.width() >= 700 && img.height() >= 200, "{name}");
        assert!(html.contains(&format!("href=\"report_plots/{name}.png\"")));
    }
    // The coverage plot holds every accepted corner.
    let corners: usize = data.observations.views.iter().map(|v| v.points.len()).sum();
    let report = cubecal::report::render_run(&data, "x").unwrap();
    let coverage = &report.plots[0];
    assert_eq!(coverage.name, "coverage");
    assert_eq!(elements(&coverage.svg, "circle").len(), corners);

    let poor = build_run(&tmp.path().join("poor"), Kind::PoorCoverage, 640, 480);
    let data = RunData::load(&poor).unwrap();
    assert!(!data.result.verdict.pass);
    let cov = data
        .result
        .verdict
        .checks
        .iter()
        .find(|c| c.name == "coverage")
        .unwrap();
    assert!(!cov.pass && cov.value < 0.4, "{cov:?}");
    let out = tmp.path().join("elsewhere/poor.html");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args([
            "report",
            poor.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(0));
    let html = std::fs::read_to_string(&out).unwrap();
    assert!(html.contains("FAIL: calibration rejected"));
    assert!(html.contains("add poses that bring the rig near the image corners"));
    assert!(
        tmp.path()
            .join("elsewhere/poor_plots/coverage.png")
            .exists()
    );
    // A folder that is not a run: bad input, exit 3.
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["report", tmp.path().to_str().unwrap()])
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(3));
}

/// Writes the demo run used by `tests/report_chromium.sh` (12 poses at 1280×960, report through the
/// CLI), a poor-coverage run with their reports, and a profile store with a five-version camera and
/// its report (`profile/report.html`) into `$CUBECAL_REPORT_DEMO_DIR`. Ignored by
/// default; the CI script runs it.
#[test]
#[ignore]
fn write_demo_runs() {
    let dir = std::env::var_os("CUBECAL_REPORT_DEMO_DIR").expect("set CUBECAL_REPORT_DEMO_DIR");
    let dir = Path::new(&dir);
    let demo = build_run(&dir.join("demo"), Kind::Good { n: 12 }, 1280, 960);
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["report", demo.to_str().unwrap()])
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(0));
    let poor = build_run(&dir.join("poor_coverage"), Kind::PoorCoverage, 1280, 960);
    cubecal::report::write_run_report(&poor).unwrap();
    // A camera with five stored versions (drift in f, a jump in cx), reported through the CLI.
    let versions: Vec<_> = (0..5).map(drifting_camera).collect();
    let store = dir.join("profile_store");
    build_history(&store, "usb:046d:0825:DEMO-1", &versions);
    let out = dir.join("profile/report.html");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args([
            "report",
            "usb:046d:0825:DEMO-1",
            "--store",
            store.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(0));
}

/// A camera's four versions with known moves: fx and cx move (cx jumps by 3.5 px, 6 σ, at v3), the
/// focal length's σ doubles at v2, k3 is fixed at v1 and estimated later, the rest stays.
fn known_moves() -> Vec<Vec<Param>> {
    let v = |fx: f64, sfx: f64, cx: f64, k1: f64, k3: (f64, f64)| {
        vec![
            ("fx", fx, sfx),
            ("fy", 1000.0, 0.5),
            ("cx", cx, 0.4),
            ("cy", 480.0, 0.4),
            ("k1", k1, 0.002),
            ("k2", 0.1, 0.004),
            ("p1", 0.001, 0.0001),
            ("p2", -0.001, 0.0001),
            ("k3", k3.0, k3.1),
        ]
    };
    vec![
        v(1000.0, 0.5, 640.0, -0.300, (0.0, 0.0)),
        v(1001.0, 1.0, 640.0, -0.301, (0.01, 0.01)),
        v(999.5, 0.5, 644.0, -0.300, (0.02, 0.01)),
        v(1000.3, 0.5, 640.5, -0.305, (0.015, 0.01)),
    ]
}

fn hex(c: plotters::style::RGBColor) -> String {
    format!("#{:02X}{:02X}{:02X}", c.0, c.1, c.2)
}

#[test]
fn profile_history_is_plotted_at_each_versions_distance_in_sigma() {
    let tmp = tempfile::tempdir().unwrap();
    let versions = known_moves();
    build_history(&tmp.path().join("store"), "usb:1d6b:0104:CAM-7", &versions);
    let data = cubecal::report::profile::ProfileData::locate(
        "usb:1d6b:0104:CAM-7",
        &tmp.path().join("store"),
    )
    .unwrap();
    assert_eq!(data.versions().len(), 4);
    let report = cubecal::report::profile::render_profile(&data, "p").unwrap();
    let names: Vec<&str> = report.plots.iter().map(|p| p.name).collect();
    assert_eq!(names, ["distortion", "uncertainty", "history"]);
    let history = &report.plots[2];

    // Ground truth, from the parameter lists: (p_v − p_cur) / √(σ_v² + σ_cur²), none where either
    // version holds the parameter fixed.
    let cur = &versions[3];
    let order = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];
    let want: Vec<Vec<Option<f64>>> = order
        .iter()
        .map(|name| {
            let (_, pc, sc) = *cur.iter().find(|p| p.0 == *name).unwrap();
            versions
                .iter()
                .map(|v| {
                    let (_, pv, sv) = *v.iter().find(|p| p.0 == *name).unwrap();
                    (sv > 0.0 && sc > 0.0).then(|| (pv - pc) / f64::hypot(sv, sc))
                })
                .collect()
        })
        .collect();
    // Spot checks of the arithmetic itself: fx at v2 is 0.7 / √1.25, cx at v3 is 3.5 / √0.32.
    assert!((want[0][1].unwrap() - 0.7 / 1.25f64.sqrt()).abs() < 1e-12);
    assert!((want[2][2].unwrap() - 6.187184335382291).abs() < 1e-9);
    assert_eq!(want[8][0], None);
    let got_names: Vec<&str> = report.series.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(got_names, order);
    for ((name, got), want) in report.series.iter().zip(&want) {
        for (g, w) in got.iter().zip(want) {
            match (g, w) {
                (Some(g), Some(w)) => assert!((g - w).abs() < 1e-9, "{name}: {g} vs {w}"),
                _ => assert_eq!(g, w, "{name}"),
            }
        }
    }

    // The SVG: one marker per (parameter, version) with a value — 9 × 4 minus k3 at v1 — in the
    // parameter's colour, at x = version (offset by the parameter's dodge, so that equal values sit
    // side by side) and y = its Δ/σ.
    let g = history.geometry;
    let figure = plots::HistoryFigure {
        caption: String::new(),
        versions: Vec::new(),
        series: report.series.clone(),
        jump_sigma: 5.0,
    };
    let circles = elements(&history.svg, "circle");
    assert_eq!(circles.len(), 35);
    for (k, w) in want.iter().enumerate() {
        let colour = hex(plots::HistoryFigure::colour(k));
        let mine: Vec<_> = circles.iter().filter(|c| c["fill"] == colour).collect();
        let expected: Vec<(usize, f64)> = w
            .iter()
            .enumerate()
            .filter_map(|(i, z)| Some((i, (*z)?)))
            .collect();
        assert_eq!(mine.len(), expected.len(), "{}", order[k]);
        for (c, (i, z)) in mine.iter().zip(&expected) {
            let (x, y) = g.to_px(*i as f64 + figure.dodge(k), *z);
            assert!((num(c, "cx") - x).abs() <= 1.0, "{} v{i} x", order[k]);
            assert!(
                (num(c, "cy") - y).abs() <= 1.0,
                "{} v{i}: cy {} vs {y} (Δ/σ {z})",
                order[k],
                c["cy"]
            );
        }
        // Lines join consecutive versions that both have a value: 3, and 2 for k3.
        let segments = elements(&history.svg, "polyline")
            .into_iter()
            .filter(|l| l.get("stroke").is_some_and(|s| *s == colour))
            .count();
        assert_eq!(
            segments,
            if order[k] == "k3" { 2 } else { 3 },
            "{}",
            order[k]
        );
    }
    // The jump lines are at ±5 σ (the store's default threshold) and the range holds cx's 6.19 σ.
    let (_, y5) = g.to_px(0.0, 5.0);
    let (_, ym5) = g.to_px(0.0, -5.0);
    let dashed: Vec<f64> = elements(&history.svg, "polyline")
        .into_iter()
        .filter(|l| l.get("stroke").is_some_and(|s| *s == hex(plots::JUMP)))
        .map(|l| {
            let p: Vec<f64> = l["points"]
                .split([' ', ','])
                .filter(|s| !s.is_empty())
                .map(|s| s.parse().unwrap())
                .collect();
            p[1]
        })
        .collect();
    assert!(
        dashed.iter().any(|y| (y - y5).abs() <= 1.0),
        "{dashed:?} vs {y5}"
    );
    assert!(
        dashed.iter().any(|y| (y - ym5).abs() <= 1.0),
        "{dashed:?} vs {ym5}"
    );
    assert!(g.data_y.0 > 6.19 && g.data_y.1 < -6.19);
    // Version dates under the axis, a week apart.
    for d in [
        "2026-11-01 00:00:00",
        "2026-11-08 00:00:00",
        "2026-11-15 00:00:00",
        "2026-11-22 00:00:00",
    ] {
        assert!(history.svg.contains(d), "{d}");
    }

    // The table prints the same numbers, and the step the store recorded (cx's 4 px jump at v3 is
    // 4 / √0.32 = 7.07 σ, flagged).
    let html = &report.html;
    assert!(html.contains("+6.19 σ"), "cx at v3");
    assert!(html.contains(&format!("{:+.2} σ", want[0][1].unwrap())));
    assert!(
        html.contains("7.0711 <span class=\"fail\">JUMP</span>"),
        "stored step of v3"
    );
    assert_eq!(html.matches("<tr><td title=").count(), 4);
    // The current version's parameters with σ, and the stored verdict.
    assert!(html.contains(
        "<tr><td>fx</td><td class=\"num\">1000.3000</td><td class=\"num\">± 0.5000</td></tr>"
    ));
    assert!(html.contains(
        "<tr><td>skew</td><td class=\"num\">0.0000</td><td class=\"num\">fixed</td></tr>"
    ));
    assert!(html.contains("PASS: calibration accepted") && html.contains("<td>coverage</td>"));
    assert!(html.contains("usb:1d6b:0104:CAM-7"));
}

fn cubecal_in(dir: &Path, args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .current_dir(dir)
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn profile_reports_through_the_cli_for_every_way_of_naming_a_profile() {
    let tmp = tempfile::tempdir().unwrap();
    let store = tmp.path().join("store");
    let s = store.to_str().unwrap();
    let id = "usb:1d6b:0104:CAM-7";
    let folder = build_history(&store, id, &known_moves());
    let folder_name = folder.file_name().unwrap().to_str().unwrap().to_string();
    let versions_of = |html: &str| html.matches("<tr><td title=").count();

    // By identity, default output in the current directory.
    let out = cubecal_in(tmp.path(), &["report", id, "--store", s]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let html_path = tmp.path().join(format!("report-{folder_name}.html"));
    let html = std::fs::read_to_string(&html_path).unwrap();
    assert_eq!(versions_of(&html), 4);
    assert_eq!(html.matches("<svg ").count(), 3);
    for name in ["distortion", "uncertainty", "history"] {
        let png = tmp
            .path()
            .join(format!("report-{folder_name}_plots/{name}.png"));
        let img = image::open(&png).unwrap();
        assert!(img.width() >= 700, "{name}");
    }
    // By folder name in the store, by the folder's path, by its current.json: the same history.
    let by_folder = tmp.path().join("a.html");
    let by_path = tmp.path().join("b.html");
    let by_current = tmp.path().join("c.html");
    for (target, out_file) in [
        (folder_name.clone(), &by_folder),
        (folder.to_str().unwrap().to_string(), &by_path),
        (
            folder.join("current.json").to_str().unwrap().to_string(),
            &by_current,
        ),
    ] {
        let out = cubecal_in(
            tmp.path(),
            &[
                "report",
                &target,
                "--store",
                s,
                "--out",
                out_file.to_str().unwrap(),
                "--json",
            ],
        );
        assert_eq!(
            out.status.code(),
            Some(0),
            "{target}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let line: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(line["report"], out_file.to_str().unwrap());
        assert_eq!(
            versions_of(&std::fs::read_to_string(out_file).unwrap()),
            4,
            "{target}"
        );
    }
    // One history file alone: that version, no history plot.
    let oldest = std::fs::read_dir(folder.join("history"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    let single = tmp.path().join("single.html");
    let out = cubecal_in(
        tmp.path(),
        &[
            "report",
            oldest.to_str().unwrap(),
            "--out",
            single.to_str().unwrap(),
        ],
    );
    assert_eq!(out.status.code(), Some(0));
    let html = std::fs::read_to_string(&single).unwrap();
    assert_eq!(html.matches("<svg ").count(), 2);
    assert!(html.contains("No earlier version") && html.contains("1000.0000"));
    // Nothing of that name, and a store that does not exist (not created): bad input, exit 3.
    let out = cubecal_in(tmp.path(), &["report", "usb:dead:beef:NONE", "--store", s]);
    assert_eq!(out.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&out.stderr).contains("nor a camera in the profile store"));
    let missing = tmp.path().join("no-store");
    let out = cubecal_in(
        tmp.path(),
        &["report", id, "--store", missing.to_str().unwrap()],
    );
    assert_eq!(out.status.code(), Some(3));
    assert!(!missing.exists());
    // A newer-format current profile: refused, exit 3.
    let cur = folder.join("current.json");
    let text = std::fs::read_to_string(&cur).unwrap();
    std::fs::write(
        &cur,
        text.replacen("\"format_version\": 1", "\"format_version\": 99", 1),
    )
    .unwrap();
    let out = cubecal_in(tmp.path(), &["report", id, "--store", s]);
    assert_eq!(out.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&out.stderr).contains("newer"));
}

#[test]
fn a_replayed_station_runs_profile_json_and_store_entry_are_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let demo = report_support::repo().join("fixtures/sessions/demo");
    let (run, store) = (tmp.path().join("run"), tmp.path().join("store"));
    let out = cubecal_in(
        tmp.path(),
        &[
            "calibrate",
            "--replay",
            demo.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--store",
            store.to_str().unwrap(),
        ],
    );
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The run's profile.json is a profile document like the store's.
    let single = tmp.path().join("single.html");
    let out = cubecal_in(
        tmp.path(),
        &[
            "report",
            run.join("profile.json").to_str().unwrap(),
            "--out",
            single.to_str().unwrap(),
        ],
    );
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let html = std::fs::read_to_string(&single).unwrap();
    assert!(html.contains("demo-camera") && html.contains("No earlier version"));
    assert_eq!(html.matches("<svg ").count(), 2);
    let stored = cubecal::profile::read_document(&run.join("profile.json")).unwrap();
    let (current, _) = cubecal::profile::Store::open(&store)
        .unwrap()
        .current("demo-camera")
        .unwrap();
    assert_eq!(stored.calibration, current.calibration);
}
