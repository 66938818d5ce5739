//! `cubecal solve OBSERVATIONS.json`: calibrate from a file of 2D–3D correspondences and print the result.

use std::path::PathBuf;

use anyhow::Context;
use clap::ValueEnum;
use cubecal::calib::report::CalibrationReport;
use cubecal::calib::{self, Fix, Loss, SolveOptions};
use cubecal::camera::DistortionModel;
use cubecal::exit;
use cubecal::observations::Observations;

use super::Output;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModelArg {
    /// No distortion.
    Pinhole,
    /// OpenCV k1, k2, p1, p2, k3.
    Brown5,
    /// OpenCV rational model k1, k2, p1, p2, k3, k4, k5, k6.
    Brown8,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FixArg {
    /// Square pixels: fx = fy.
    Aspect,
    /// Principal point at the image centre.
    PrincipalPoint,
    /// No tangential distortion (p1 = p2 = 0).
    Tangential,
    /// k3 = 0.
    K3,
    /// Zero skew (the default; use --estimate-skew to free it).
    Skew,
}

#[derive(Debug, clap::Args)]
pub struct SolveArgs {
    /// Observations JSON: {"image_size": [w, h], "views": [{"name", "points": [{"xyz", "uv"}]}]}.
    pub observations: PathBuf,
    /// Distortion model.
    #[arg(long, value_enum, default_value = "brown5")]
    pub model: ModelArg,
    /// Hold parameters fixed (repeat or comma-separate).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub fix: Vec<FixArg>,
    /// Estimate the skew term (held at zero by default).
    #[arg(long)]
    pub estimate_skew: bool,
    /// Robust loss: `huber:C` or `cauchy:C` with scale C in pixels.
    #[arg(long, value_parser = parse_loss)]
    pub loss: Option<Loss>,
    /// Reject points whose residual exceeds K robust standard deviations, and re-solve.
    #[arg(long, value_name = "K")]
    pub reject_outliers: Option<f64>,
    /// Iteration limit of the refinement.
    #[arg(long, default_value_t = 200)]
    pub max_iterations: usize,
}

fn parse_loss(s: &str) -> Result<Loss, String> {
    let (kind, scale) = s
        .split_once(':')
        .ok_or_else(|| format!("expected huber:C or cauchy:C, got '{s}'"))?;
    let c: f64 = scale
        .parse()
        .map_err(|_| format!("loss scale '{scale}' is not a number"))?;
    if !(c > 0.0 && c.is_finite()) {
        return Err(format!("loss scale must be positive, got {c}"));
    }
    match kind {
        "huber" => Ok(Loss::Huber(c)),
        "cauchy" => Ok(Loss::Cauchy(c)),
        other => Err(format!("unknown loss '{other}' (huber or cauchy)")),
    }
}

impl SolveArgs {
    fn options(&self) -> SolveOptions {
        let model = match self.model {
            ModelArg::Pinhole => DistortionModel::Pinhole,
            ModelArg::Brown5 => DistortionModel::Brown5,
            ModelArg::Brown8 => DistortionModel::Brown8,
        };
        let has = |f: FixArg| self.fix.contains(&f);
        SolveOptions {
            model,
            fix: Fix {
                aspect_ratio: has(FixArg::Aspect).then_some(1.0),
                principal_point: has(FixArg::PrincipalPoint),
                tangential: has(FixArg::Tangential),
                k3: has(FixArg::K3),
                skew: !self.estimate_skew || has(FixArg::Skew),
            },
            loss: self.loss.unwrap_or_default(),
            outlier_sigma: self.reject_outliers,
            max_iterations: self.max_iterations,
        }
    }
}

pub fn run(args: SolveArgs, out: Output) -> anyhow::Result<u8> {
    let obs = Observations::load(&args.observations)?;
    let opts = args.options();
    let cal = calib::solve(&obs.views, obs.image_size, &opts)
        .with_context(|| format!("calibrating from {}", args.observations.display()))?;
    let report = CalibrationReport::from(&cal);
    if out.json {
        print_json(&report)?;
    } else {
        print_human(&report, &args);
    }
    Ok(if report.converged {
        exit::SUCCESS
    } else {
        exit::CALIBRATION_FAILED
    })
}

#[allow(clippy::print_stdout)]
fn print_json(report: &CalibrationReport) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string_pretty(report)?);
    Ok(())
}

#[allow(clippy::print_stdout)]
fn print_human(r: &CalibrationReport, args: &SolveArgs) {
    let k = &r.camera_matrix;
    let sd = |name: &str| {
        r.std_dev
            .get(name)
            .map(|s| format!(" ± {s:.3}"))
            .unwrap_or_else(|| " (fixed)".into())
    };
    println!(
        "{}: {} views, {} points, image {}×{}, model {}",
        args.observations.display(),
        r.views.len(),
        r.n_points,
        r.image_size[0],
        r.image_size[1],
        r.distortion.model
    );
    println!("  fx = {:.3}{} px", k[0][0], sd("fx"));
    println!("  fy = {:.3}{} px", k[1][1], sd("fy"));
    println!("  cx = {:.3}{} px", k[0][2], sd("cx"));
    println!("  cy = {:.3}{} px", k[1][2], sd("cy"));
    if r.std_dev.contains_key("skew") {
        println!("  skew = {:.4}{}", k[0][1], sd("skew"));
    }
    let names = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"];
    for (name, v) in names.iter().zip(&r.distortion.coefficients) {
        let s = r
            .std_dev
            .get(*name)
            .map(|s| format!(" ± {s:.6}"))
            .unwrap_or_else(|| " (fixed)".into());
        println!("  {name} = {v:.6}{s}");
    }
    println!(
        "  RMS {:.4} px per coordinate ({:.4} px per point, OpenCV's figure); noise estimate σ = {:.4} px",
        r.rms_px, r.rms_reprojection_px, r.sigma_px
    );
    println!(
        "  {} after {} iterations ({}), initialised by {:?}",
        if r.converged {
            "converged"
        } else {
            "NOT CONVERGED"
        },
        r.iterations,
        r.termination,
        r.init_method
    );
    println!("  views:");
    for v in &r.views {
        let t = v.translation;
        println!(
            "    {:<16} rms {:.3} px  {:>4} points  {} outliers  t = [{:.1}, {:.1}, {:.1}] mm",
            v.name,
            v.rms_px,
            v.n_points,
            v.outliers.len(),
            t[0],
            t[1],
            t[2]
        );
    }
}
