//! `cubecal solve OBSERVATIONS.json`: calibrate from a file of 2D–3D correspondences and print the result.

use std::path::PathBuf;

use anyhow::Context;
use clap::ValueEnum;

use cubecal::calib::observations::Observations;
use cubecal::calib::report::CalibrationReport;
use cubecal::calib::{self, Fix, Loss, SolveOptions, Termination, UndeterminedParam, Weighting};
use cubecal::camera::DistortionModel;
use cubecal::exit;

use super::{Output, UsageError};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModelArg {
    /// No distortion.
    Pinhole,
    /// OpenCV k1, k2, p1, p2, k3.
    Brown5,
    /// OpenCV rational model k1, k2, p1, p2, k3, k4, k5, k6.
    Brown8,
    /// Kannala–Brandt fisheye, OpenCV's cv::fisheye k1, k2, k3, k4 (ROS equidistant).
    #[value(alias = "fisheye")]
    Kb4,
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
    /// k4 = 0 (brown8).
    K4,
    /// k5 = 0 (brown8).
    K5,
    /// k6 = 0 (brown8).
    K6,
    /// Zero skew (the default; use --estimate-skew to free it).
    Skew,
}

#[derive(Debug, clap::Args)]
pub struct SolveArgs {
    /// Observations JSON: {"image_size": [w, h], "views": [{"name", "points": [{"xyz", "uv"}]}]}, or
    /// the output of `cubecal detect --json` (one view per image with faces).
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
    /// Reject outliers: per view, drop the worst point while its residual exceeds K robust standard
    /// deviations, re-solving after each round (K = 3 drops 1.1 % of clean Gaussian points).
    #[arg(long, value_name = "K", value_parser = parse_positive)]
    pub reject_outliers: Option<f64>,
    /// Iteration limit of the refinement.
    #[arg(long, default_value_t = 200)]
    pub max_iterations: usize,
    /// Weight every point alike but for those whose `cov` gives a σ over twice the median point's,
    /// which count by that σ (a grazing face's corners carry its bias there); by default, when
    /// every point has a covariance, each is weighted by its inverse.
    #[arg(long)]
    pub unweighted: bool,
}

fn parse_positive(s: &str) -> Result<f64, String> {
    let k: f64 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if k > 0.0 && k.is_finite() {
        Ok(k)
    } else {
        Err(format!("must be a positive number, got {s}"))
    }
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
            ModelArg::Kb4 => DistortionModel::Kb4,
        };
        let has = |f: FixArg| self.fix.contains(&f);
        SolveOptions {
            model,
            fix: Fix {
                aspect_ratio: has(FixArg::Aspect).then_some(1.0),
                principal_point: has(FixArg::PrincipalPoint),
                tangential: has(FixArg::Tangential),
                k3: has(FixArg::K3),
                k4: has(FixArg::K4),
                k5: has(FixArg::K5),
                k6: has(FixArg::K6),
                skew: !self.estimate_skew || has(FixArg::Skew),
            },
            loss: self.loss.unwrap_or_default(),
            outlier_sigma: self.reject_outliers,
            max_iterations: self.max_iterations,
            weighting: if self.unweighted {
                Weighting::Equal
            } else {
                Weighting::Covariance
            },
        }
    }
}

pub fn run(args: SolveArgs, out: Output) -> anyhow::Result<u8> {
    if args.estimate_skew && args.fix.contains(&FixArg::Skew) {
        return Err(
            UsageError("--estimate-skew and --fix skew contradict each other".into()).into(),
        );
    }
    let model_has = |f: FixArg| match f {
        FixArg::K4 => matches!(args.model, ModelArg::Brown8 | ModelArg::Kb4),
        FixArg::K5 | FixArg::K6 => args.model == ModelArg::Brown8,
        FixArg::Tangential => matches!(args.model, ModelArg::Brown5 | ModelArg::Brown8),
        FixArg::K3 => args.model != ModelArg::Pinhole,
        _ => true,
    };
    if let Some(f) = args.fix.iter().find(|&&f| !model_has(f)) {
        let name = f.to_possible_value().map(|v| v.get_name().to_string());
        return Err(UsageError(format!(
            "--fix {}: model {} has no such parameter",
            name.unwrap_or_default(),
            args.model
                .to_possible_value()
                .map(|v| v.get_name().to_string())
                .unwrap_or_default()
        ))
        .into());
    }
    let obs = Observations::load(&args.observations)?;
    let opts = args.options();
    let cal = calib::solve(&obs.views, obs.image_size, &opts)
        .with_context(|| format!("calibrating from {}", args.observations.display()))?;
    let undetermined = calib::undetermined_parameters(&cal);
    let report = CalibrationReport::from(&cal);
    if out.json {
        print_json(&report, &undetermined)?;
    } else {
        print_human(&report, &args, &undetermined, cal.termination)?;
    }
    Ok(if report.converged {
        exit::SUCCESS
    } else {
        exit::CALIBRATION_FAILED
    })
}

/// The report, plus `undetermined`: the parameters [`calib::undetermined_parameters`] flags.
fn print_json(
    report: &CalibrationReport,
    undetermined: &[UndeterminedParam],
) -> anyhow::Result<()> {
    let mut v = serde_json::to_value(report)?;
    if let Some(map) = v.as_object_mut() {
        map.insert("undetermined".into(), serde_json::to_value(undetermined)?);
    }
    outln!("{}", serde_json::to_string_pretty(&v)?)?;
    Ok(())
}

/// `1 view`, `2 views`.
pub(crate) fn count(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

fn print_human(
    r: &CalibrationReport,
    args: &SolveArgs,
    undetermined: &[UndeterminedParam],
    termination: Termination,
) -> anyhow::Result<()> {
    let k = &r.camera_matrix;
    let sd = |name: &str| {
        r.std_dev
            .get(name)
            .map(|s| format!(" ± {s:.3}"))
            .unwrap_or_else(|| " (fixed)".into())
    };
    outln!(
        "{}: {}, {}, image {}×{}, model {}",
        args.observations.display(),
        count(r.views.len(), "view"),
        count(r.n_points, "point"),
        r.image_size[0],
        r.image_size[1],
        r.distortion.model
    )?;
    outln!("  fx = {:.3}{} px", k[0][0], sd("fx"))?;
    outln!("  fy = {:.3}{} px", k[1][1], sd("fy"))?;
    outln!("  cx = {:.3}{} px", k[0][2], sd("cx"))?;
    outln!("  cy = {:.3}{} px", k[1][2], sd("cy"))?;
    if r.std_dev.contains_key("skew") {
        outln!("  skew = {:.4}{}", k[0][1], sd("skew"))?;
    }
    let names = cubecal::profile::coefficient_names(&r.distortion.model);
    for (name, v) in names.iter().zip(&r.distortion.coefficients) {
        let s = r
            .std_dev
            .get(*name)
            .map(|s| format!(" ± {s:.6}"))
            .unwrap_or_else(|| " (fixed)".into());
        outln!("  {name} = {v:.6}{s}")?;
    }
    outln!(
        "  RMS {:.4} px per coordinate ({:.4} px per point, OpenCV's figure); noise estimate σ = {:.4} px",
        r.rms_px,
        r.rms_reprojection_px,
        r.sigma_px
    )?;
    for u in undetermined {
        outln!(
            "  warning: {} = {:.6} ± {:.6} is not determined by these views (σ exceeds its value; one σ moves the image border by {:.1} px): add views at other orientations or hold it fixed",
            u.name,
            u.value,
            u.std_dev,
            u.effect_px
        )?;
    }
    outln!(
        "  {} after {} ({}); initial values from {}",
        if r.converged {
            "converged"
        } else {
            "NOT CONVERGED"
        },
        count(r.iterations, "iteration"),
        termination.describe(),
        r.init_method.describe()
    )?;
    outln!("  views:")?;
    for v in &r.views {
        let t = v.translation;
        outln!(
            "    {:<16} rms {:.3} px  {:>10}  {:>11}  t = [{:.1}, {:.1}, {:.1}] mm",
            v.name,
            v.rms_px,
            count(v.n_points, "point"),
            count(v.outliers.len(), "outlier"),
            t[0],
            t[1],
            t[2]
        )?;
    }
    Ok(())
}
