//! The report's figures, drawn with `plotters` on any backend: SVG for the HTML, a bitmap for the PNG
//! files beside it. Each figure is a plain struct holding exactly the data it shows (computed in
//! [`super::analysis`]) and draws itself through [`Figure::draw`], which returns where the image
//! area landed in pixels so that tests can map data to the drawn coordinates.
//!
//! Image-shaped plots (coverage, residual field, displacement, uncertainty) use image coordinates:
//! `u` to the right, `v` down, the frame spanning `[-½, w − ½] × [-½, h − ½]` (pixel centres at
//! integers), and keep the image's aspect ratio.

use std::error::Error;

use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

use super::analysis::{CoverageGrid, Field, Histogram, ViewStat};
use crate::detect::overlay::PALETTE;

/// Result of drawing on backend `DB`.
pub type DrawResult<T, DB> = Result<T, DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

/// Where a figure's data area landed: pixel rectangle and the data range it shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    /// Pixels the data edges map to: x (left, right) and y (top, bottom), both inclusive (plotters
    /// maps a range onto the first to the last pixel of the plotting area).
    pub px_x: (i32, i32),
    pub px_y: (i32, i32),
    /// Data values at the left/right and top/bottom edges.
    pub data_x: (f64, f64),
    pub data_y: (f64, f64),
}

impl Geometry {
    /// The pixel a data point maps to (plotters rounds down to whole pixels).
    pub fn to_px(&self, x: f64, y: f64) -> (f64, f64) {
        let fx = (x - self.data_x.0) / (self.data_x.1 - self.data_x.0);
        let fy = (y - self.data_y.0) / (self.data_y.1 - self.data_y.0);
        (
            f64::from(self.px_x.0) + fx * f64::from(self.px_x.1 - self.px_x.0),
            f64::from(self.px_y.0) + fy * f64::from(self.px_y.1 - self.px_y.0),
        )
    }
}

/// A figure that can be drawn on any plotters backend.
pub trait Figure {
    /// Short file-name-safe identifier (`coverage`, `residuals`, …).
    fn name(&self) -> &'static str;
    /// Size in pixels.
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB>;
}

/// A plotters failure, kept as the error it was (the backend's error type differs per backend).
pub type PlotError = Box<dyn Error + Send + Sync>;

fn boxed<E: Error + Send + Sync + 'static>(e: DrawingAreaErrorKind<E>) -> PlotError {
    Box::new(e)
}

/// Register the embedded DejaVu Sans as plotters' `sans-serif` (once per process): the bitmap
/// backend draws text with it, and both backends measure text with it.
pub(crate) fn register_font() -> Result<(), PlotError> {
    static DONE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular())
            .is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err("the embedded DejaVu Sans font could not be parsed".into())
    }
}

/// Draw `fig` as an SVG document.
pub fn to_svg(fig: &impl Figure) -> Result<(String, Geometry), PlotError> {
    register_font()?;
    let mut svg = String::new();
    let geometry = {
        let root = SVGBackend::with_string(&mut svg, fig.size()).into_drawing_area();
        let g = fig.draw(&root).map_err(boxed)?;
        root.present().map_err(boxed)?;
        g
    };
    Ok((svg, geometry))
}

/// Draw `fig` into an RGB bitmap (row-major, 3 bytes per pixel).
pub fn to_rgb(fig: &impl Figure) -> Result<image::RgbImage, PlotError> {
    register_font()?;
    let (w, h) = fig.size();
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        fig.draw(&root).map_err(boxed)?;
        root.present().map_err(boxed)?;
    }
    image::RgbImage::from_raw(w, h, buf).ok_or_else(|| "bitmap buffer size mismatch".into())
}

/// Colour of rig face `i` (the detector overlay's palette).
pub fn face_rgb(i: usize) -> RGBColor {
    let [r, g, b] = PALETTE[i % PALETTE.len()];
    RGBColor(r, g, b)
}

/// Fitted points and views.
pub const FITTED: RGBColor = RGBColor(0, 114, 178);
/// Held-out points and views.
pub const HELD_OUT: RGBColor = RGBColor(230, 159, 0);
/// Outliers.
pub const OUTLIER: RGBColor = RGBColor(213, 40, 40);
const GREY: RGBColor = RGBColor(150, 150, 150);
const FONT: &str = "sans-serif";

/// The smallest of 1, 2, 5 × 10^k not below `x` (`x > 0`).
pub fn nice(x: f64) -> f64 {
    if !(x > 0.0 && x.is_finite()) {
        return 1.0;
    }
    let p = 10f64.powf(x.log10().floor());
    for m in [1.0, 2.0, 5.0, 10.0] {
        if m * p >= x * (1.0 - 1e-12) {
            return m * p;
        }
    }
    10.0 * p
}

/// Viridis, by linear interpolation between five anchors; `t ∈ [0, 1]`.
pub fn viridis(t: f64) -> RGBColor {
    const A: [[f64; 3]; 5] = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f64;
    let c = |k: usize| (A[i][k] + f * (A[i + 1][k] - A[i][k])).round() as u8;
    RGBColor(c(0), c(1), c(2))
}

/// Layout of an image-shaped chart: plot width, and the figure size that keeps the image's aspect.
const IMG_PLOT_W: u32 = 640;
const LEFT: u32 = 60;
const BOTTOM: u32 = 40;
const MARGIN: u32 = 12;
const CAPTION: u32 = 34;

fn image_figure_size(image_size: [u32; 2], right: u32, strip: u32) -> (u32, u32) {
    let plot_h = (f64::from(IMG_PLOT_W) * f64::from(image_size[1]) / f64::from(image_size[0]))
        .round() as u32;
    (
        IMG_PLOT_W + LEFT + 2 * MARGIN + right,
        plot_h + BOTTOM + CAPTION + 2 * MARGIN + strip,
    )
}

type ImageChart<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

fn image_chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    caption: &str,
    image_size: [u32; 2],
) -> DrawResult<(ImageChart<'a, DB>, Geometry), DB> {
    let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
    let (x0, x1, y0, y1) = (-0.5, w - 0.5, -0.5, h - 0.5);
    // The caption in a strip of fixed height (not plotters' caption, whose height depends on the
    // font), so that the plotting area has exactly the image's aspect ratio.
    area.draw(&Text::new(
        caption.to_string(),
        ((LEFT + MARGIN) as i32, (MARGIN + 4) as i32),
        (FONT, 15),
    ))?;
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .margin_top(MARGIN + CAPTION)
        .x_label_area_size(BOTTOM)
        .y_label_area_size(LEFT)
        .build_cartesian_2d(x0..x1, y1..y0)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("u (px)")
        .y_desc("v (px)")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .label_style((FONT, 12))
        .draw()?;
    let (px, py) = chart.plotting_area().get_pixel_range();
    let geometry = Geometry {
        px_x: (px.start, px.end - 1),
        px_y: (py.start, py.end - 1),
        data_x: (x0, x1),
        data_y: (y0, y1),
    };
    Ok((chart, geometry))
}

/// A row of legend entries (colour swatch + label) in a strip.
fn legend<DB: DrawingBackend>(
    strip: &DrawingArea<DB, Shift>,
    entries: &[(RGBColor, String)],
) -> DrawResult<(), DB> {
    let mut x = (LEFT + MARGIN) as i32;
    for (colour, label) in entries {
        strip.draw(&Rectangle::new([(x, 6), (x + 12, 18)], colour.filled()))?;
        strip.draw(&Text::new(label.clone(), (x + 16, 5), (FONT, 13)))?;
        let (tw, _) = strip.estimate_text_size(label, &TextStyle::from((FONT, 13)))?;
        x += 16 + tw as i32 + 18;
    }
    Ok(())
}

/// The cells of a `cols × rows` grid over an image of `image_size`, row by row: each cell's index
/// (`row · cols + col`) and its corners in image coordinates (the coverage grid and the colour bands).
fn image_cells(
    image_size: [u32; 2],
    cols: usize,
    rows: usize,
) -> impl Iterator<Item = (usize, [(f64, f64); 2])> {
    let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
    let x = move |c: usize| c as f64 * w / cols as f64 - 0.5;
    let y = move |r: usize| r as f64 * h / rows as f64 - 0.5;
    (0..rows).flat_map(move |r| {
        (0..cols).map(move |c| (r * cols + c, [(x(c), y(r)), (x(c + 1), y(r + 1))]))
    })
}

/// All accepted corners over the frame, coloured by face, on the coverage grid.
#[derive(Debug, Clone)]
pub struct CoverageFigure {
    pub image_size: [u32; 2],
    /// Corner positions (px) with the index of their face in `face_names` (None: face unknown).
    pub points: Vec<((f64, f64), Option<usize>)>,
    pub face_names: Vec<String>,
    pub grid: CoverageGrid,
}

impl Figure for CoverageFigure {
    fn name(&self) -> &'static str {
        "coverage"
    }
    fn size(&self) -> (u32, u32) {
        image_figure_size(self.image_size, 0, 26)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let (_, h) = self.size();
        let (main, strip) = root.split_vertically(h - 26);
        let caption = format!(
            "Coverage: {} corners; {} of {} grid cells hold corners ({:.0} %)",
            self.points.len(),
            self.grid.covered(),
            self.grid.counts.len(),
            100.0 * self.grid.fraction()
        );
        let (mut chart, geometry) = image_chart(&main, &caption, self.image_size)?;
        let cells = || image_cells(self.image_size, self.grid.cols, self.grid.rows);
        let covered = RGBColor(200, 235, 200);
        let empty = RGBColor(250, 225, 225);
        chart.draw_series(cells().map(|(k, cell)| {
            let fill = if self.grid.counts[k] > 0 {
                covered
            } else {
                empty
            };
            Rectangle::new(cell, fill.filled())
        }))?;
        chart.draw_series(cells().map(|(_, cell)| Rectangle::new(cell, GREY.stroke_width(1))))?;
        chart.draw_series(self.points.iter().map(|&((u, v), face)| {
            let colour = face.map_or(GREY, face_rgb);
            Circle::new((u, v), 2, colour.filled())
        }))?;
        let mut entries: Vec<(RGBColor, String)> = self
            .face_names
            .iter()
            .enumerate()
            .map(|(i, n)| (face_rgb(i), n.clone()))
            .collect();
        entries.push((covered, "cell with corners".into()));
        entries.push((empty, "empty cell".into()));
        legend(&strip, &entries)?;
        Ok(geometry)
    }
}

/// Kind of a residual arrow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PointKind {
    Fitted,
    HeldOut,
    Outlier,
}

impl PointKind {
    pub fn colour(self) -> RGBColor {
        match self {
            PointKind::Fitted => FITTED,
            PointKind::HeldOut => HELD_OUT,
            PointKind::Outlier => OUTLIER,
        }
    }
}

/// One residual arrow: corner (px), residual (px), kind.
pub type Arrow = ((f64, f64), (f64, f64), PointKind);

/// Residual vectors drawn at their corners, magnified by `scale`.
#[derive(Debug, Clone)]
pub struct ResidualFigure {
    pub image_size: [u32; 2],
    /// Corner (px), residual (px), kind.
    pub arrows: Vec<Arrow>,
    /// Magnification of the arrows.
    pub scale: f64,
    /// Length of the scale bar, as a residual in px.
    pub bar_px: f64,
}

impl ResidualFigure {
    /// A scale making the 95th percentile residual about 4 % of the image width, rounded to 1-2-5,
    /// and a scale bar of a round residual near that percentile.
    pub fn choose_scale(image_size: [u32; 2], norms: &[f64]) -> (f64, f64) {
        let mut n: Vec<f64> = norms.iter().copied().filter(|x| x.is_finite()).collect();
        n.sort_by(f64::total_cmp);
        let p95 = n
            .get(((n.len() as f64 * 0.95) as usize).min(n.len().saturating_sub(1)))
            .copied()
            .filter(|x| *x > 0.0)
            .unwrap_or(1.0);
        let scale = nice(0.04 * f64::from(image_size[0]) / p95 / 2.0);
        (scale, nice(p95 / 2.0))
    }
}

impl Figure for ResidualFigure {
    fn name(&self) -> &'static str {
        "residuals"
    }
    fn size(&self) -> (u32, u32) {
        image_figure_size(self.image_size, 0, 26)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let (_, h) = self.size();
        let (main, strip) = root.split_vertically(h - 26);
        let caption = format!(
            "Residuals (observed − projected) at their corners, arrows magnified ×{}",
            self.scale
        );
        let (mut chart, geometry) = image_chart(&main, &caption, self.image_size)?;
        chart.draw_series(self.arrows.iter().map(|&((u, v), (ru, rv), kind)| {
            PathElement::new(
                vec![(u, v), (u + self.scale * ru, v + self.scale * rv)],
                kind.colour().stroke_width(1),
            )
        }))?;
        let count = |k: PointKind| self.arrows.iter().filter(|a| a.2 == k).count();
        legend(
            &strip,
            &[
                (FITTED, format!("fitted ({})", count(PointKind::Fitted))),
                (
                    HELD_OUT,
                    format!("held out ({})", count(PointKind::HeldOut)),
                ),
                (OUTLIER, format!("outliers ({})", count(PointKind::Outlier))),
            ],
        )?;
        // Scale bar at the right of the strip: `bar_px` of residual drawn at the arrows' scale.
        let px_per_u =
            f64::from(geometry.px_x.1 - geometry.px_x.0) / (geometry.data_x.1 - geometry.data_x.0);
        let len = (self.bar_px * self.scale * px_per_u).round() as i32;
        let label = format!("{} px residual", self.bar_px);
        let (tw, _) = strip.estimate_text_size(&label, &TextStyle::from((FONT, 13)))?;
        let x1 = geometry.px_x.1;
        let x0 = x1 - len;
        strip.draw(&PathElement::new(
            vec![(x0, 12), (x1, 12)],
            BLACK.stroke_width(2),
        ))?;
        strip.draw(&Text::new(label, (x0 - tw as i32 - 8, 5), (FONT, 13)))?;
        Ok(geometry)
    }
}

/// Histogram of residual components with the normal density of the estimated noise.
#[derive(Debug, Clone)]
pub struct HistogramFigure {
    pub hist: Histogram,
    pub sigma_px: f64,
}

impl Figure for HistogramFigure {
    fn name(&self) -> &'static str {
        "histogram"
    }
    fn size(&self) -> (u32, u32) {
        (720, 420)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let h = &self.hist;
        let n: usize = h.counts.iter().sum::<usize>() + h.outside;
        let x0 = h.start;
        let x1 = h.start + h.width * h.counts.len() as f64;
        let sigma = self.sigma_px;
        let density = |x: f64| {
            n as f64 * h.width * (-0.5 * (x / sigma).powi(2)).exp()
                / (sigma * (2.0 * std::f64::consts::PI).sqrt())
        };
        let ymax = h
            .counts
            .iter()
            .map(|&c| c as f64)
            .fold(density(0.0), f64::max)
            .max(1.0)
            * 1.1;
        let caption = format!(
            "Residual components (x and y) vs N(0, σ²), σ = {:.3} px; {} beyond ±4σ",
            sigma, h.outside
        );
        let mut chart = ChartBuilder::on(root)
            .caption(caption, (FONT, 15))
            .margin(MARGIN)
            .x_label_area_size(BOTTOM)
            .y_label_area_size(LEFT)
            .build_cartesian_2d(x0..x1, 0.0..ymax)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .light_line_style(WHITE)
            .bold_line_style(RGBColor(225, 225, 225))
            .x_desc("residual component (px)")
            .y_desc("count")
            .label_style((FONT, 12))
            .draw()?;
        chart.draw_series(h.counts.iter().enumerate().filter(|(_, c)| **c > 0).map(
            |(k, &c)| {
                let a = h.start + k as f64 * h.width;
                Rectangle::new(
                    [(a, 0.0), (a + h.width, c as f64)],
                    FITTED.mix(0.7).filled(),
                )
            },
        ))?;
        chart.draw_series(LineSeries::new(
            (0..=200).map(|i| {
                let x = x0 + (x1 - x0) * f64::from(i) / 200.0;
                (x, density(x))
            }),
            OUTLIER.stroke_width(2),
        ))?;
        let (px, py) = chart.plotting_area().get_pixel_range();
        Ok(Geometry {
            px_x: (px.start, px.end - 1),
            px_y: (py.start, py.end - 1),
            data_x: (x0, x1),
            data_y: (ymax, 0.0),
        })
    }
}

/// RMS per view as horizontal bars: fitted, held out, and outlier views marked.
#[derive(Debug, Clone)]
pub struct ViewRmsFigure {
    pub stats: Vec<ViewStat>,
    pub sigma_px: f64,
    /// Views above this RMS are outlier views.
    pub outlier_above: Option<f64>,
}

impl Figure for ViewRmsFigure {
    fn name(&self) -> &'static str {
        "views"
    }
    fn size(&self) -> (u32, u32) {
        (720, 110 + 24 * self.stats.len().max(1) as u32)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let n = self.stats.len().max(1) as f64;
        let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
        let xmax = self
            .stats
            .iter()
            .map(|s| finite(s.rms_px))
            .fold(finite(self.sigma_px), f64::max)
            .max(self.outlier_above.map_or(0.0, finite))
            .max(1e-3)
            * 1.6;
        let mut chart = ChartBuilder::on(root)
            .caption(
                "RMS per view (px): blue fitted, orange held out, red outlier view",
                (FONT, 15),
            )
            .margin(MARGIN)
            .x_label_area_size(BOTTOM)
            .y_label_area_size(10)
            .build_cartesian_2d(0.0..xmax, n..0.0)?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .light_line_style(WHITE)
            .bold_line_style(RGBColor(225, 225, 225))
            .y_labels(0)
            .x_desc("RMS of residual components (px)")
            .label_style((FONT, 12))
            .draw()?;
        let kind = |s: &ViewStat| {
            if s.held_out {
                HELD_OUT
            } else if self.outlier_above.is_some_and(|t| s.rms_px > t) {
                OUTLIER
            } else {
                FITTED
            }
        };
        chart.draw_series(self.stats.iter().enumerate().map(|(i, s)| {
            let y = i as f64;
            Rectangle::new(
                [(0.0, y + 0.15), (finite(s.rms_px), y + 0.85)],
                kind(s).filled(),
            )
        }))?;
        chart.draw_series(self.stats.iter().enumerate().map(|(i, s)| {
            let mut label = format!("{}  {:.3} px, {} pts", s.name, s.rms_px, s.n_points);
            if s.n_outliers > 0 {
                label.push_str(&format!(", {} outliers", s.n_outliers));
            }
            if s.held_out {
                label.push_str(", held out");
            }
            Text::new(
                label,
                (finite(s.rms_px) + xmax * 0.01, i as f64 + 0.2),
                (FONT, 12),
            )
        }))?;
        let mut lines = vec![(self.sigma_px, GREY, "σ")];
        if let Some(t) = self.outlier_above {
            lines.push((t, OUTLIER, "outlier view"));
        }
        for (x, colour, _) in &lines {
            if x.is_finite() {
                chart.draw_series(DashedLineSeries::new(
                    vec![(*x, 0.0), (*x, n)],
                    5,
                    4,
                    colour.stroke_width(1),
                ))?;
            }
        }
        let (px, py) = chart.plotting_area().get_pixel_range();
        Ok(Geometry {
            px_x: (px.start, px.end - 1),
            px_y: (py.start, py.end - 1),
            data_x: (0.0, xmax),
            data_y: (0.0, n),
        })
    }
}

/// A scalar field over the image in colour bands, with a colour bar and optional polylines on top.
#[derive(Debug, Clone)]
pub struct HeatmapFigure {
    pub name: &'static str,
    pub caption: String,
    /// Unit shown on the colour bar.
    pub unit: String,
    pub image_size: [u32; 2],
    pub field: Field,
    /// Polylines in image coordinates (px), drawn in black.
    pub lines: Vec<Vec<(f64, f64)>>,
}

impl HeatmapFigure {
    /// Colour bands: a round step and the lower edge of the first band (a multiple of the step),
    /// giving at most about 10 bands from the field's minimum to its maximum.
    pub fn bands(&self) -> (f64, f64, usize) {
        let (lo, hi) = (self.field.min(), self.field.max());
        let span = hi - lo;
        let step = if span > 1e-12 * hi.abs().max(1e-300) {
            nice(span / 10.0)
        } else {
            nice(hi.abs().max(1e-12) / 10.0)
        };
        let start = (lo / step).floor() * step;
        let n = (((hi - start) / step).floor() as usize + 1).clamp(1, 64);
        (step, start, n)
    }
}

/// Decimals needed to print multiples of `step`.
fn decimals(step: f64) -> usize {
    if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()).clamp(0.0, 9.0) as usize
    }
}

const COLOUR_BAR: u32 = 110;

impl Figure for HeatmapFigure {
    fn name(&self) -> &'static str {
        self.name
    }
    fn size(&self) -> (u32, u32) {
        image_figure_size(self.image_size, COLOUR_BAR, 0)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let (w, _) = self.size();
        let (main, bar) = root.split_horizontally(w - COLOUR_BAR);
        let (mut chart, geometry) = image_chart(&main, &self.caption, self.image_size)?;
        let (step, start, bands) = self.bands();
        let band = |k: usize| viridis(k as f64 / (bands.max(2) - 1) as f64);
        let colour = |v: f64| {
            if !v.is_finite() {
                return GREY;
            }
            band((((v - start) / step).floor().max(0.0) as usize).min(bands - 1))
        };
        chart.draw_series(
            image_cells(self.image_size, self.field.nx, self.field.ny)
                .map(|(k, cell)| Rectangle::new(cell, colour(self.field.values[k]).filled())),
        )?;
        for line in &self.lines {
            chart.draw_series(std::iter::once(PathElement::new(
                line.clone(),
                BLACK.mix(0.8).stroke_width(1),
            )))?;
        }
        // Colour bar: one swatch per band with its lower edge, top band first.
        let top = (MARGIN + CAPTION) as i32;
        let sw = 18;
        let per = ((geometry.px_y.1 - geometry.px_y.0) / bands.max(1) as i32).clamp(10, 28);
        bar.draw(&Text::new(self.unit.clone(), (4, top - 20), (FONT, 13)))?;
        for k in 0..bands {
            let y = top + (bands - 1 - k) as i32 * per;
            bar.draw(&Rectangle::new(
                [(4, y), (4 + sw, y + per)],
                band(k).filled(),
            ))?;
            bar.draw(&Text::new(
                format!("{:.*}", decimals(step), start + k as f64 * step),
                (4 + sw + 6, y + per - 12),
                (FONT, 12),
            ))?;
        }
        Ok(geometry)
    }
}

/// Colours of parameter series (Tableau 10: distinguishable lines on white).
pub const SERIES: [RGBColor; 10] = [
    RGBColor(78, 121, 167),
    RGBColor(242, 142, 43),
    RGBColor(225, 87, 89),
    RGBColor(118, 183, 178),
    RGBColor(89, 161, 79),
    RGBColor(237, 201, 72),
    RGBColor(176, 122, 161),
    RGBColor(255, 157, 167),
    RGBColor(156, 117, 95),
    RGBColor(186, 176, 172),
];

/// One parameter's history: its name and, per version (oldest first), its offset in σ units, or
/// `None` where the version cannot be compared (parameter fixed or absent in that version).
pub type Series = (String, Vec<Option<f64>>);

/// How each intrinsic parameter moved across a camera's profile versions, in σ units: per version a
/// point per parameter at `Δ/σ`, joined by lines (broken where a version has no value), dashed lines
/// at `±jump_sigma`, and the versions' dates under the x axis.
#[derive(Debug, Clone)]
pub struct HistoryFigure {
    pub caption: String,
    /// Label of each version (its date), oldest first; the x axis places version `i` at `i`.
    pub versions: Vec<String>,
    pub series: Vec<Series>,
    /// The store's jump threshold, drawn as dashed lines at `±jump_sigma`.
    pub jump_sigma: f64,
}

impl HistoryFigure {
    /// The y range shown: symmetric, covering every point and the jump threshold with 15 % headroom.
    pub fn y_max(&self) -> f64 {
        let finite = |x: &f64| x.is_finite();
        self.series
            .iter()
            .flat_map(|(_, v)| v.iter().flatten().filter(|x| finite(x)).map(|x| x.abs()))
            .fold(
                if self.jump_sigma.is_finite() {
                    self.jump_sigma
                } else {
                    1.0
                },
                f64::max,
            )
            .max(1.0)
            * 1.15
    }

    /// The colour of series `i`.
    pub fn colour(i: usize) -> RGBColor {
        SERIES[i % SERIES.len()]
    }
}

const DATE_AREA: u32 = 54;

impl Figure for HistoryFigure {
    fn name(&self) -> &'static str {
        "history"
    }
    fn size(&self) -> (u32, u32) {
        (900, 480)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<Geometry, DB> {
        root.fill(&WHITE)?;
        let (_, h) = self.size();
        let (main, strip) = root.split_vertically(h - 26);
        let n = self.versions.len().max(1);
        let (x0, x1) = (-0.5, n as f64 - 0.5);
        let ymax = self.y_max();
        let mut chart = ChartBuilder::on(&main)
            .caption(self.caption.clone(), (FONT, 15))
            .margin(MARGIN)
            .margin_right(3 * MARGIN)
            .x_label_area_size(DATE_AREA)
            .y_label_area_size(LEFT)
            .build_cartesian_2d(x0..x1, -ymax..ymax)?;
        // The x axis is labelled by hand (dates under each version); plotters labels only y.
        chart
            .configure_mesh()
            .disable_x_mesh()
            .light_line_style(WHITE)
            .bold_line_style(RGBColor(225, 225, 225))
            .x_labels(0)
            .y_desc("Δ/σ")
            .label_style((FONT, 12))
            .draw()?;
        chart.draw_series(std::iter::once(PathElement::new(
            vec![(x0, 0.0), (x1, 0.0)],
            GREY.stroke_width(1),
        )))?;
        if self.jump_sigma.is_finite() {
            for s in [-self.jump_sigma, self.jump_sigma] {
                chart.draw_series(DashedLineSeries::new(
                    vec![(x0, s), (x1, s)],
                    6,
                    4,
                    OUTLIER.stroke_width(1),
                ))?;
            }
        }
        for (k, (_, values)) in self.series.iter().enumerate() {
            let colour = Self::colour(k);
            // Lines between consecutive versions that both have a value.
            chart.draw_series(values.windows(2).enumerate().filter_map(|(i, w)| {
                let (a, b) = (w[0]?, w[1]?);
                (a.is_finite() && b.is_finite()).then(|| {
                    PathElement::new(
                        vec![(i as f64, a), ((i + 1) as f64, b)],
                        colour.stroke_width(2),
                    )
                })
            }))?;
            chart.draw_series(values.iter().enumerate().filter_map(|(i, v)| {
                let v = (*v)?;
                v.is_finite()
                    .then(|| Circle::new((i as f64, v), 4, colour.filled()))
            }))?;
        }
        let (px, py) = chart.plotting_area().get_pixel_range();
        let geometry = Geometry {
            px_x: (px.start, px.end - 1),
            px_y: (py.start, py.end - 1),
            data_x: (x0, x1),
            data_y: (ymax, -ymax),
        };
        // Version labels: "vN" and the date, centred under each version (every k-th when crowded).
        let every = n.div_ceil(12).max(1);
        let centred = TextStyle::from((FONT, 12)).pos(plotters::style::text_anchor::Pos::new(
            plotters::style::text_anchor::HPos::Center,
            plotters::style::text_anchor::VPos::Top,
        ));
        for (i, label) in self.versions.iter().enumerate() {
            if i % every != 0 && i + 1 != n {
                continue;
            }
            let (x, _) = geometry.to_px(i as f64, 0.0);
            let y = geometry.px_y.1 + 6;
            main.draw(&Text::new(
                format!("v{}", i + 1),
                (x.round() as i32, y),
                centred.clone(),
            ))?;
            main.draw(&Text::new(
                label.clone(),
                (x.round() as i32, y + 16),
                centred.clone(),
            ))?;
        }
        let mut entries: Vec<(RGBColor, String)> = self
            .series
            .iter()
            .enumerate()
            .map(|(k, (name, _))| (Self::colour(k), name.clone()))
            .collect();
        entries.push((OUTLIER, format!("±{} σ (jump)", self.jump_sigma)));
        legend(&strip, &entries)?;
        Ok(geometry)
    }
}
