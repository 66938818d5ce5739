//! Run reports: one self-contained HTML file a calibration engineer can judge a run from by looking,
//! plus the same plots as PNG files beside it. Reports of stored profiles and their history are in
//! [`profile`]; both share the tables, the lens plots ([`lens_plots`]) and the file writing here.
//!
//! The report shows the verdict table and the device; the coverage of the image by accepted corners
//! (coloured by face, on the coverage grid); the residuals as a magnified vector field and as a
//! histogram against the estimated noise σ; the RMS of each view with the held-out view and outlier
//! views marked; the lens distortion (displacement magnitude in bands, and a straight grid as the
//! lens draws it); the projection uncertainty over the image from the intrinsics' covariance; and a
//! thumbnail of every pose with its detection overlay and a legend of the faces in their colours.
//!
//! ## Design
//! - [`analysis`] computes every number shown (pure functions, tested against ground truth);
//!   [`plots`] draws them with `plotters` on any backend: inline SVG in the HTML (text rendered by the
//!   browser, no JavaScript), a bitmap for the PNG files. Text in bitmaps is drawn with the DejaVu
//!   Sans font embedded in the binary (`dejavu` crate, through plotters' `ab_glyph` feature), so no
//!   system font library or installed font is needed on a bare Debian.
//! - Thumbnails are PNG embedded as `data:` URIs, so the HTML needs nothing beside it to be read.
//! - Residuals are recomputed from the calibrated camera, the view poses (fitted views from the
//!   calibration, held-out views from `held_out`) and the observations.
//! - Files are written atomically (temporary file, then rename).

pub mod analysis;
pub mod plots;
pub mod profile;
pub mod run;
pub mod thumbs;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use base64::Engine as _;

use analysis::{COVERAGE_GRID, CoverageGrid, OUTLIER_VIEW_FACTOR};
use plots::{
    CoverageFigure, Figure, Geometry, HeatmapFigure, HistogramFigure, PlotError, PointKind,
    ResidualFigure, ViewRmsFigure,
};
pub use run::{HeldOutPose, RunData, RunResult, ViewOutcome};

/// Errors making a report.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(
        "{path} is not a run directory (a folder with result.json, observations.json, rig.toml)"
    )]
    NotARunDir { path: PathBuf },
    /// `cubecal report TARGET` names nothing a report can be made of.
    #[error(
        "'{}' is not a run directory (with result.json), a profile document, a camera folder of a profile store (with current.json), nor a camera in the profile store {}",
        .target.escape_debug(), .store.display()
    )]
    NothingToReport { target: String, store: PathBuf },
    /// Reading a stored profile failed.
    #[error(transparent)]
    Profile(#[from] crate::profile::ProfileError),
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not in the expected format")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("cannot load the run's rig")]
    Rig(#[from] crate::rig::RigError),
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("the calibration in {path} is not a usable camera")]
    Camera {
        path: PathBuf,
        #[source]
        source: crate::camera::CameraError,
    },
    #[error("cannot draw the {plot} plot")]
    Plot {
        plot: &'static str,
        #[source]
        source: PlotError,
    },
    #[error("cannot encode {path} as PNG")]
    Encode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl ReportError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            ReportError::NotARunDir { .. }
            | ReportError::NothingToReport { .. }
            | ReportError::Read { .. }
            | ReportError::Json { .. }
            | ReportError::Invalid { .. }
            | ReportError::Camera { .. } => crate::exit::BAD_INPUT,
            ReportError::Rig(e) => e.exit_code(),
            ReportError::Profile(e) => e.exit_code(),
            ReportError::Plot { .. } | ReportError::Encode { .. } | ReportError::Write { .. } => {
                crate::exit::INTERNAL
            }
        }
    }
}

/// One drawn plot: SVG for the HTML, PNG for the file beside it.
#[derive(Debug, Clone)]
pub struct Plot {
    pub name: &'static str,
    pub svg: String,
    pub png: Vec<u8>,
    pub geometry: Geometry,
    /// What the plot shows and how to read it.
    pub note: String,
}

/// A pose's thumbnail.
#[derive(Debug, Clone)]
pub struct Thumb {
    pub name: String,
    pub frame: Option<String>,
    pub accepted: bool,
    pub held_out: bool,
    pub reason: Option<String>,
    pub angle_deg: Option<f64>,
    /// PNG bytes, or why there is no image.
    pub png: Result<Vec<u8>, String>,
}

/// A rendered run report.
#[derive(Debug, Clone)]
pub struct RunReport {
    pub html: String,
    pub plots: Vec<Plot>,
    pub thumbs: Vec<Thumb>,
    pub coverage: CoverageGrid,
    /// Time spent in each stage (for the benchmark and `-vv` logs).
    pub timings: Vec<(&'static str, std::time::Duration)>,
}

/// PNG with fast compression: plots and thumbnails are flat colours and a downscaled frame, where
/// stronger compression costs several times the time for a few per cent of size. Every row is
/// Paeth-filtered: the adaptive choice among the five filters took twice the time for the same size
/// (a photo run's 13 thumbnails and 6 plots: 19.0 ms adaptive, 10.2 ms Paeth; thumbnails 1.598 MB
/// either way, plots 346 kB adaptive, 366 kB Paeth; Sub and Up 9 ms, 17 % and 53 % larger).
fn encode_png(img: &image::RgbImage, what: &Path) -> Result<Vec<u8>, ReportError> {
    use image::ImageEncoder as _;
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let mut bytes = Vec::new();
    PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Paeth)
        .write_image(
            img.as_raw(),
            img.width(),
            img.height(),
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|source| ReportError::Encode {
            path: what.to_path_buf(),
            source,
        })?;
    Ok(bytes)
}

fn plot(fig: &impl Figure, note: String) -> Result<Plot, ReportError> {
    let err = |source| ReportError::Plot {
        plot: fig.name(),
        source,
    };
    let (svg, geometry) = plots::to_svg(fig).map_err(err)?;
    let rgb = plots::to_rgb(fig).map_err(err)?;
    let png = encode_png(&rgb, Path::new(fig.name()))?;
    Ok(Plot {
        name: fig.name(),
        svg,
        png,
        geometry,
        note,
    })
}

/// Escape text for HTML.
pub fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '&' => o.push_str("&amp;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

/// Render the report of a loaded run. `png_dir` is the relative folder the PNG links point to. The
/// thumbnails (their frames decoded, scaled, drawn and encoded on threads of their own) are built
/// beside the plots, not after them.
pub fn render_run(data: &RunData, png_dir: &str) -> Result<RunReport, ReportError> {
    std::thread::scope(|scope| {
        let thumbs = scope.spawn(|| {
            let start = std::time::Instant::now();
            thumbnails(data).map(|t| (t, start.elapsed()))
        });
        render_run_beside(data, png_dir, || match thumbs.join() {
            Ok(r) => r,
            Err(panic) => std::panic::resume_unwind(panic),
        })
    })
}

/// [`render_run`] with the thumbnails from `thumbs` (built meanwhile; with the time they took).
fn render_run_beside(
    data: &RunData,
    png_dir: &str,
    thumbs: impl FnOnce() -> Result<(Vec<Thumb>, std::time::Duration), ReportError>,
) -> Result<RunReport, ReportError> {
    let mut timings = Vec::new();
    let mut clock = std::time::Instant::now();
    let mut lap = |name: &'static str, timings: &mut Vec<(&'static str, std::time::Duration)>| {
        timings.push((name, clock.elapsed()));
        clock = std::time::Instant::now();
    };
    let result = &data.result;
    let Some(cal) = &result.calibration else {
        // No calibration (nothing accepted, the solver failed): what is left to judge the run by
        // are the views, each with its overlay and the reason it was rejected.
        let thumbs = thumbnails(data)?;
        lap("thumbnails", &mut timings);
        let grid = CoverageGrid::count(
            std::iter::empty(),
            data.observations.image_size,
            COVERAGE_GRID,
        );
        let html = html(data, &[], &thumbs, &[], &grid, &[], png_dir);
        return Ok(RunReport {
            html,
            plots: Vec::new(),
            thumbs,
            coverage: grid,
            timings,
        });
    };
    let cam = analysis::camera_from_report(cal).map_err(|source| ReportError::Camera {
        path: data.dir.join(run::RESULT),
        source,
    })?;
    std::thread::scope(|scope| {
        let image_size = cal.image_size;
        // The two lens plots (a dense field each) on a thread of their own, beside the other four.
        let cam_ref = &cam;
        let lens = scope.spawn(move || {
            let start = std::time::Instant::now();
            lens_plots(cal, cam_ref).map(|r| (r, start.elapsed()))
        });
        let (residuals, stats, no_pose) =
            analysis::residuals(&cam, &data.observations, cal, &result.held_out);

        // Coverage: every accepted corner (fitted and held out).
        lap("residuals", &mut timings);
        let face_names: Vec<String> = data.rig.faces.iter().map(|f| f.name.clone()).collect();
        let points: Vec<((f64, f64), Option<usize>)> = data
            .observations
            .views
            .iter()
            .flat_map(|v| v.points.iter())
            .map(|p| {
                let face = p
                    .face
                    .as_deref()
                    .and_then(|n| face_names.iter().position(|f| f == n));
                ((p.uv[0], p.uv[1]), face)
            })
            .collect();
        let grid = CoverageGrid::count(
            points
                .iter()
                .map(|&((u, v), _)| nalgebra::Vector2::new(u, v)),
            image_size,
            COVERAGE_GRID,
        );
        let mut plots = Vec::new();
        plots.push(plot(
            &CoverageFigure {
                image_size,
                points,
                face_names: face_names.clone(),
                grid: grid.clone(),
            },
            format!(
                "Every accepted corner over the image, coloured by face, on the {}×{} coverage grid \
                 (green: cell holds corners).",
                COVERAGE_GRID.0, COVERAGE_GRID.1
            ),
        )?);

        lap("coverage plot", &mut timings);
        let norms: Vec<f64> = residuals.iter().map(|r| r.r.norm()).collect();
        let (scale, bar_px) = ResidualFigure::choose_scale(image_size, &norms);
        let arrows = residuals
            .iter()
            .map(|r| {
                let kind = if r.held_out {
                    PointKind::HeldOut
                } else if r.outlier {
                    PointKind::Outlier
                } else {
                    PointKind::Fitted
                };
                ((r.uv.x, r.uv.y), (r.r.x, r.r.y), kind)
            })
            .collect();
        plots.push(plot(
            &ResidualFigure {
                image_size,
                arrows,
                scale,
                bar_px,
            },
            format!(
                "Residual of every corner drawn from the corner, magnified {scale}×; the bar is a \
                 {bar_px} px residual at that scale. A pattern (swirl, radial flow) means a model error; \
                 noise looks random."
            ),
        )?);

        lap("residual plot", &mut timings);
        let sigma = if cal.sigma_px > 0.0 && cal.sigma_px.is_finite() {
            cal.sigma_px
        } else {
            1.0
        };
        let components = residuals
            .iter()
            .filter(|r| !r.held_out && !r.outlier)
            .flat_map(|r| [r.r.x, r.r.y]);
        plots.push(plot(
            &HistogramFigure {
                hist: analysis::histogram(components, sigma),
                sigma_px: sigma,
            },
            "Residual components of the fitted inliers in bins of σ/4, with the normal density \
             expected for corner noise σ (red). Heavy tails or a skew mean outliers or a model error."
                .to_string(),
        )?);

        lap("histogram plot", &mut timings);
        let median = analysis::median_fitted_rms(&stats);
        plots.push(plot(
            &ViewRmsFigure {
                stats: stats.clone(),
                sigma_px: cal.sigma_px,
                outlier_above: median.map(|m| m * OUTLIER_VIEW_FACTOR),
            },
            format!(
                "RMS of each view's residual components (outlier points excluded). Dashed: σ (grey) and \
                 {OUTLIER_VIEW_FACTOR}× the median fitted view (red): a view above it is an outlier view."
            ),
        )?);

        lap("per-view plot", &mut timings);
        let mut notes = Vec::new();
        if !no_pose.is_empty() {
            notes.push(format!(
                "{} observed view(s) have no pose in result.json and are not in the residual plots: {}",
                no_pose.len(),
                no_pose.join(", ")
            ));
        }
        let ((lens, lens_notes), took) = match lens.join() {
            Ok(r) => r?,
            Err(panic) => std::panic::resume_unwind(panic),
        };
        plots.extend(lens);
        notes.extend(lens_notes);
        lap("waiting for the lens plots", &mut timings);
        timings.push(("distortion and uncertainty plots (beside)", took));
        let (thumbs, took) = thumbs()?;
        lap("waiting for the thumbnails", &mut timings);
        timings.push(("thumbnails (beside the plots)", took));
        let html = html(data, &plots, &thumbs, &stats, &grid, &notes, png_dir);
        lap("html", &mut timings);
        for (stage, t) in &timings {
            tracing::debug!(stage, ms = t.as_secs_f64() * 1e3, "report stage");
        }
        Ok(RunReport {
            html,
            plots,
            thumbs,
            coverage: grid,
            timings,
        })
    })
}

/// The lens plots of a calibration: the distortion (displacement bands with the distorted straight
/// grid) and the projection uncertainty from the intrinsics' covariance, one colour-band figure each.
/// The second value says why a plot is missing (no covariance in the calibration).
pub fn lens_plots(
    cal: &crate::calib::report::CalibrationReport,
    cam: &crate::camera::Camera,
) -> Result<(Vec<Plot>, Vec<String>), ReportError> {
    let image_size = cal.image_size;
    let mut plots = vec![plot(
        &HeatmapFigure {
            name: "distortion",
            caption: format!(
                "Lens distortion ({}): displacement from the ideal {} image",
                cal.distortion.model,
                if cam.model == crate::camera::DistortionModel::Kb4 {
                    "equidistant (r = f·θ)"
                } else {
                    "pinhole"
                }
            ),
            unit: "px".into(),
            image_size,
            field: analysis::displacement_field(cam, 64, 48),
            lines: analysis::distorted_grid(cam, 10),
        },
        "Colour bands: how far the lens moves each pixel from where an ideal pinhole camera with \
         the same K would image it (a fisheye: an ideal equidistant one). Black: a straight grid of \
         the pinhole image as this lens draws it."
            .to_string(),
    )?];
    let mut notes = Vec::new();
    match analysis::full_covariance(cal) {
        Ok(cov) => {
            let d = analysis::working_distance_mm(cal).unwrap_or(1000.0);
            plots.push(plot(
                &HeatmapFigure {
                    name: "uncertainty",
                    caption: format!(
                        "Projection uncertainty σ (px) at {d:.0} mm, from the intrinsics' covariance"
                    ),
                    unit: "σ px".into(),
                    image_size,
                    field: analysis::uncertainty_field(cam, &cov, d, 32, 24),
                    lines: Vec::new(),
                },
                format!(
                    "1σ error of projecting a point at {d:.0} mm ({}) along each pixel's ray, from \
                     the covariance of the {} estimated intrinsics (larger axis of the error \
                     ellipse). For intrinsics alone it is the same at every distance along the ray; \
                     pose uncertainty is not included.",
                    if cal.views.is_empty() {
                        "no poses stored: a nominal distance"
                    } else {
                        "the median camera–rig distance"
                    },
                    cal.free_params.len()
                ),
            )?);
        }
        Err(e) => notes.push(format!("No projection uncertainty plot: {e}.")),
    }
    Ok((plots, notes))
}

fn thumbnails(data: &RunData) -> Result<Vec<Thumb>, ReportError> {
    let obs_by_name: std::collections::HashMap<&str, &crate::calib::observations::RawView> = data
        .observations
        .views
        .iter()
        .filter_map(|v| Some((v.name.as_deref()?, v)))
        .collect();
    let held: std::collections::HashSet<&str> = data
        .observations
        .views
        .iter()
        .filter(|v| v.held_out)
        .filter_map(|v| v.name.as_deref())
        .chain(data.result.held_out.iter().map(|h| h.name.as_str()))
        .collect();
    // Views listed in result.json, else the observed views.
    let outcomes: Vec<ViewOutcome> = if data.result.views.is_empty() {
        data.observations
            .views
            .iter()
            .enumerate()
            .map(|(i, v)| ViewOutcome {
                name: v.name.clone().unwrap_or_else(|| format!("view{i}")),
                frame: v.frame.clone(),
                accepted: true,
                reason: None,
            })
            .collect()
    } else {
        data.result.views.clone()
    };
    let previews: std::collections::HashMap<&str, &crate::run::preview::FramePreview> = data
        .previews
        .iter()
        .map(|p| (p.frame.as_str(), p))
        .collect();
    // One thumbnail per pose, on up to four threads (decoding, scaling and encoding dominate; a
    // preview from the station saves the first two).
    let one = |o: &ViewOutcome| -> Result<Thumb, ReportError> {
        let obs = obs_by_name.get(o.name.as_str()).copied();
        let frame = o
            .frame
            .clone()
            .or_else(|| obs.and_then(|v| v.frame.clone()));
        let preview = frame
            .as_deref()
            .and_then(|f| previews.get(f).copied())
            .and_then(|p| {
                let (w, h) = p.full_size;
                let det = match obs {
                    Some(v) => thumbs::detection_from_view(v, &data.rig, w, h),
                    None => p.detection.clone()?,
                };
                Some((p, det))
            });
        let png = match (&frame, preview) {
            (None, _) => Err("no frame recorded for this view".to_string()),
            (Some(f), Some((p, det))) => {
                let path = data.dir.join(run::SESSION).join(f);
                let rgb = thumbs::thumbnail_of_preview(&p.image, p.factor, &det, &data.rig)
                    .map_err(|source| ReportError::Plot {
                        plot: "thumbnail",
                        source,
                    })?;
                Ok(encode_png(&rgb, &path)?)
            }
            (Some(f), None) => {
                let path = data.dir.join(run::SESSION).join(f);
                match thumbs::load_frame(&path) {
                    Err(e) => Err(format!("frame {f} cannot be read: {e}")),
                    Ok(img) => {
                        let det = match obs {
                            Some(v) => Some(thumbs::detection_from_view(
                                v,
                                &data.rig,
                                img.width(),
                                img.height(),
                            )),
                            None => thumbs::detect_frame(&img, &data.rig),
                        };
                        let det = det.unwrap_or(crate::detect::FrameDetection {
                            width: img.width(),
                            height: img.height(),
                            faces: Vec::new(),
                            rejected: Vec::new(),
                        });
                        let rgb = thumbs::thumbnail(&img, &det, &data.rig).map_err(|source| {
                            ReportError::Plot {
                                plot: "thumbnail",
                                source,
                            }
                        })?;
                        Ok(encode_png(&rgb, &path)?)
                    }
                }
            }
        };
        Ok(Thumb {
            held_out: held.contains(o.name.as_str()),
            angle_deg: frame.as_deref().and_then(|f| data.angle_deg(f)),
            name: o.name.clone(),
            frame,
            accepted: o.accepted,
            reason: o.reason.clone(),
            png,
        })
    };
    let from_previews = outcomes
        .iter()
        .filter(|o| {
            let obs = obs_by_name.get(o.name.as_str());
            (o.frame.as_deref().or(obs.and_then(|v| v.frame.as_deref())))
                .and_then(|f| previews.get(f))
                .is_some_and(|p| obs.is_some() || p.detection.is_some())
        })
        .count();
    tracing::debug!(
        from_previews,
        decoded = outcomes.len() - from_previews,
        "thumbnails"
    );
    crate::render::parallel_map(outcomes.len(), |i| one(&outcomes[i]))
        .into_iter()
        .collect()
}

const CSS: &str = "body{font-family:sans-serif;margin:24px;color:#222;max-width:1500px}\
h1{margin-bottom:4px}h2{margin-top:32px;border-bottom:1px solid #ccc}\
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}\
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}\
.pass{color:#1a7f37;font-weight:bold}.fail{color:#c62828;font-weight:bold}\
.banner{display:inline-block;padding:6px 16px;font-size:22px;color:#fff;border-radius:4px}\
.banner.pass{background:#1a7f37;color:#fff}.banner.fail{background:#c62828;color:#fff}\
figure{display:inline-block;vertical-align:top;margin:8px 16px 16px 0;max-width:860px}\
figure svg{max-width:100%;height:auto;border:1px solid #eee}\
figcaption{font-size:13px;color:#444;max-width:820px}\
.thumbs{display:flex;flex-wrap:wrap;gap:12px}.thumb{width:400px;font-size:13px}\
.thumb img{width:400px;border:1px solid #ccc}.note{color:#8a5a00}\
table.hist td,table.hist th{white-space:nowrap}table.hist small{color:#555}";

fn fmt_num(x: f64) -> String {
    if !x.is_finite() {
        format!("{x}")
    } else if x != 0.0 && (x.abs() < 1e-3 || x.abs() >= 1e6) {
        format!("{x:.3e}")
    } else {
        format!("{x:.4}")
    }
}

/// Table rows `<th>key</th><td>value</td>` of a JSON object's fields (strings unquoted); nothing for
/// anything else.
fn kv_rows(value: &serde_json::Value) -> String {
    let mut h = String::new();
    if let serde_json::Value::Object(m) = value {
        for (k, v) in m {
            let v = match v {
                serde_json::Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            let _ = write!(h, "<tr><th>{}</th><td>{}</td></tr>", esc(k), esc(&v));
        }
    }
    h
}

/// The start of a report page: doctype, style and the `<h1>` title.
fn page_start(title: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{t}</title><style>{CSS}</style></head><body>\n<h1>{t}</h1>\n",
        t = esc(title)
    )
}

/// The PASS/FAIL banner of a verdict.
fn banner(pass: bool) -> String {
    if pass {
        "<div class=\"banner pass\">PASS: calibration accepted</div>\n".to_string()
    } else {
        "<div class=\"banner fail\">FAIL: calibration rejected</div>\n".to_string()
    }
}

/// The verdict section: each check with its value, threshold, result and hint.
fn verdict_table(verdict: &crate::run::Verdict) -> String {
    let mut h = String::from(
        "<h2>Verdict</h2>\n<table><tr><th>check</th><th>value</th><th>threshold</th>\
         <th>result</th><th>what to do</th></tr>\n",
    );
    for c in &verdict.checks {
        let (cls, word) = if c.pass {
            ("pass", "pass")
        } else {
            ("fail", "FAIL")
        };
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>\
             <td class=\"{cls}\">{word}</td><td>{}</td></tr>",
            esc(&c.name),
            fmt_num(c.value),
            fmt_num(c.threshold),
            esc(c.hint.as_deref().unwrap_or(""))
        );
    }
    h.push_str("</table>\n");
    h
}

/// Intrinsic parameter names in the order tables show them (`K`, then OpenCV's coefficient order).
const PARAM_ORDER: [&str; 13] = [
    "fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
];

/// One line on a fit: model, points, views, RMS (and OpenCV's figure), noise σ.
fn fit_summary(cal: &crate::calib::report::CalibrationReport) -> String {
    format!(
        "model {}; {} points in {} views; RMS {} px (OpenCV's figure {} px); noise σ {} px",
        esc(&cal.distortion.model),
        cal.n_points,
        cal.views.len(),
        fmt_num(cal.rms_px),
        fmt_num(cal.rms_reprojection_px),
        fmt_num(cal.sigma_px),
    )
}

/// The calibration section's table: each intrinsic with its value and σ (`fixed` when not estimated).
fn parameter_table(cal: &crate::calib::report::CalibrationReport) -> String {
    let values = crate::profile::intrinsic_values(cal);
    let mut h = String::from(
        "<h2>Calibration</h2>\n<table><tr><th>parameter</th><th>value</th><th>σ</th></tr>",
    );
    for name in PARAM_ORDER {
        let Some(v) = values.get(name) else { continue };
        let sd = cal
            .std_dev
            .get(name)
            .map_or(String::from("fixed"), |s| format!("± {}", fmt_num(*s)));
        let _ = write!(
            h,
            "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{sd}</td></tr>",
            esc(name),
            fmt_num(*v),
        );
    }
    h.push_str("</table>\n");
    h
}

/// The plots, each inline as SVG with its note and a link to its PNG.
fn plots_section(plots: &[Plot], png_dir: &str) -> String {
    let mut h = String::from("<h2>Plots</h2>\n");
    for p in plots {
        // plotters writes a standalone SVG document; inline it as an element of the page.
        let svg = p
            .svg
            .trim_start_matches("<?xml version=\"1.0\" encoding=\"UTF-8\"?>");
        let _ = writeln!(
            h,
            "<figure id=\"{name}\">{svg}<figcaption>{} <a href=\"{}/{name}.png\">PNG</a></figcaption></figure>",
            esc(&p.note),
            esc(png_dir),
            name = p.name,
        );
    }
    h
}

fn html(
    data: &RunData,
    plots: &[Plot],
    thumbs: &[Thumb],
    stats: &[analysis::ViewStat],
    grid: &CoverageGrid,
    notes: &[String],
    png_dir: &str,
) -> String {
    let r = &data.result;
    let mut h = page_start("cubecal run report");
    let _ = writeln!(
        h,
        "<p>Run directory <code>{}</code>; rig <b>{}</b>.</p>",
        esc(&data.dir.display().to_string()),
        esc(&data.rig.name),
    );
    h.push_str(&banner(r.verdict.pass));
    // Device.
    h.push_str("<h2>Device</h2>\n<table>");
    match &r.device {
        serde_json::Value::Object(m) if !m.is_empty() => h.push_str(&kv_rows(&r.device)),
        _ => h.push_str("<tr><td>no device recorded (replayed or synthetic run)</td></tr>"),
    }
    h.push_str("</table>\n");
    h.push_str(&verdict_table(&r.verdict));
    match &r.calibration {
        Some(cal) => {
            h.push_str(&parameter_table(cal));
            let _ = writeln!(
                h,
                "<p>Fitted views: {}; coverage {} of {} cells; {} ({} iterations).</p>",
                fit_summary(cal),
                grid.covered(),
                grid.counts.len(),
                esc(&cal.termination),
                cal.iterations
            );
        }
        None => {
            let accepted = thumbs.iter().filter(|t| t.accepted).count();
            let _ = writeln!(
                h,
                "<p class=\"fail\">No calibration: {}. Each view below shows what the detector \
                 found and why the view was rejected.</p>",
                esc(&match &r.solve_error {
                    Some(e) => format!("the solver failed ({e})"),
                    None => format!("{accepted} of {} views accepted", thumbs.len()),
                })
            );
        }
    }
    if !r.held_out.is_empty() {
        h.push_str("<table><tr><th>held-out view</th><th>RMS (px)</th></tr>");
        for ho in &r.held_out {
            let _ = write!(
                h,
                "<tr><td>{}</td><td class=\"num\">{}</td></tr>",
                esc(&ho.name),
                fmt_num(ho.rms_px)
            );
        }
        h.push_str("</table>\n");
    }
    // The station's notes (k3 fixed and why, a jump against the stored profile), then the report's.
    for n in r.notes.iter().chain(notes) {
        let _ = writeln!(h, "<p class=\"note\">{}</p>", esc(n));
    }
    h.push_str(&plots_section(plots, png_dir));
    // Views.
    h.push_str(
        "<h2>Poses</h2>\n<table><tr><th>view</th><th>frame</th><th>angle (°)</th><th>status</th>\
         <th>RMS (px)</th><th>points</th><th>reason</th></tr>\n",
    );
    for t in thumbs {
        let st = stats.iter().find(|s| s.name == t.name);
        let status = if !t.accepted {
            "<span class=\"fail\">rejected</span>"
        } else if t.held_out {
            "held out"
        } else {
            "fitted"
        };
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td>{status}</td>\
             <td class=\"num\">{}</td><td class=\"num\">{}</td><td>{}</td></tr>",
            esc(&t.name),
            esc(t.frame.as_deref().unwrap_or("")),
            t.angle_deg.map_or(String::new(), |a| format!("{a:.1}")),
            st.map_or(String::new(), |s| fmt_num(s.rms_px)),
            st.map_or(String::new(), |s| s.n_points.to_string()),
            esc(t.reason.as_deref().unwrap_or(""))
        );
    }
    h.push_str("</table>\n<div class=\"thumbs\">\n");
    for t in thumbs {
        let _ = write!(h, "<div class=\"thumb\">");
        match &t.png {
            Ok(png) => {
                let _ = write!(
                    h,
                    "<img alt=\"{} with detection overlay\" src=\"data:image/png;base64,{}\">",
                    esc(&t.name),
                    base64::engine::general_purpose::STANDARD.encode(png)
                );
            }
            Err(why) => {
                let _ = write!(h, "<p class=\"note\">{}</p>", esc(why));
            }
        }
        let _ = writeln!(
            h,
            "<div><b>{}</b> {}</div></div>",
            esc(&t.name),
            if !t.accepted {
                format!("rejected: {}", esc(t.reason.as_deref().unwrap_or("")))
            } else if t.held_out {
                "held out".to_string()
            } else {
                String::new()
            }
        );
    }
    h.push_str("</div>\n</body></html>\n");
    h
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    crate::rig::svg::write_atomic(path, bytes).map_err(|source| ReportError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// The folder beside `out` the PNG plots go into: `<out stem>_plots`.
pub fn png_dir_name(out: &Path) -> String {
    let stem = out.file_stem().map_or_else(
        || "report".to_string(),
        |s| s.to_string_lossy().into_owned(),
    );
    format!("{stem}_plots")
}

/// Write `html` to `out` and each plot as PNG into `png_dir_name` beside it.
fn write_outputs(
    out: &Path,
    html: &str,
    plots: &[Plot],
    png_dir_name: &str,
) -> Result<(), ReportError> {
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let png_dir = parent.join(png_dir_name);
    std::fs::create_dir_all(&png_dir).map_err(|source| ReportError::Write {
        path: png_dir.clone(),
        source,
    })?;
    // Each file is written atomically (temporary file, fsync, rename): all at once, so that their
    // fsyncs overlap (one after another they were most of a photo run's report on a busy disk).
    let files: Vec<(PathBuf, &[u8])> = (plots.iter())
        .map(|p| (png_dir.join(format!("{}.png", p.name)), p.png.as_slice()))
        .chain([(out.to_path_buf(), html.as_bytes())])
        .collect();
    std::thread::scope(|scope| {
        let writes: Vec<_> = (files.iter())
            .map(|(path, bytes)| scope.spawn(move || write_file(path, bytes)))
            .collect();
        (writes.into_iter()).try_for_each(|w| match w.join() {
            Ok(r) => r,
            Err(panic) => std::panic::resume_unwind(panic),
        })
    })
}

/// Write the report of `run_dir` to `out` (HTML) and its plots as PNG into `<out stem>_plots/`
/// beside it. Returns the HTML path.
pub fn write_report(run_dir: &Path, out: &Path) -> Result<PathBuf, ReportError> {
    let data = RunData::load(run_dir)?;
    let png_dir_name = png_dir_name(out);
    let report = render_run(&data, &png_dir_name)?;
    write_outputs(out, &report.html, &report.plots, &png_dir_name)?;
    tracing::info!(path = %out.display(), plots = report.plots.len(), thumbnails = report.thumbs.len(), "wrote run report");
    Ok(out.to_path_buf())
}

/// Write `RUN_DIR/report.html` and `RUN_DIR/report_plots/*.png`, decoding the session's frames for the
/// thumbnails.
pub fn write_run_report(run_dir: &Path) -> Result<PathBuf, ReportError> {
    write_run_report_with(run_dir, Vec::new())
}

/// [`write_run_report`] with the thumbnails drawn on `previews` (the run's
/// [`crate::run::RunResult::previews`], as the station made them; a view without one is decoded from
/// the session): a front end's entry point right after the run.
pub fn write_run_report_with(
    run_dir: &Path,
    previews: Vec<crate::run::preview::FramePreview>,
) -> Result<PathBuf, ReportError> {
    let out = run_dir.join("report.html");
    let mut data = RunData::load(run_dir)?;
    data.previews = previews;
    let png_dir_name = png_dir_name(&out);
    let report = render_run(&data, &png_dir_name)?;
    write_outputs(&out, &report.html, &report.plots, &png_dir_name)?;
    tracing::info!(path = %out.display(), plots = report.plots.len(), thumbnails = report.thumbs.len(), "wrote run report");
    Ok(out)
}
