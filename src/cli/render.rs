//! `cubecal render`: synthetic frames of a rig with exact ground truth.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use cubecal::camera::{Camera, DistortionModel};
use cubecal::render::{
    Palette, RenderSettings, SyntheticError, default_view, ground_truth, random_poses, render,
    turntable_poses, write_frame,
};
use cubecal::rig::Rig;

use super::solve::count;
use super::{Output, OutputError};

/// Which views to render.
#[derive(Debug, Clone, PartialEq)]
pub enum PoseSpec {
    /// The rig's default view only.
    Single,
    /// The rig turned about its `up` axis in `n` equal steps over `sweep_deg`, camera fixed.
    Turntable { n: usize, sweep_deg: f64 },
    /// `n` seeded random views around the default view.
    Random { n: usize },
}

impl FromStr for PoseSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let parts: Vec<&str> = s.split(':').collect();
        let count = |p: &str| -> Result<usize, String> {
            match p.parse::<usize>() {
                Ok(n) if n >= 1 => Ok(n),
                _ => Err(format!("'{p}' is not a frame count ≥ 1")),
            }
        };
        match parts.as_slice() {
            ["single"] => Ok(PoseSpec::Single),
            ["turntable", n] => Ok(PoseSpec::Turntable {
                n: count(n)?,
                sweep_deg: 60.0,
            }),
            ["turntable", n, sweep] => {
                let sweep_deg = sweep
                    .parse::<f64>()
                    .ok()
                    .filter(|d| d.is_finite() && *d >= 0.0 && *d <= 360.0)
                    .ok_or_else(|| format!("'{sweep}' is not a sweep in degrees (0..=360)"))?;
                Ok(PoseSpec::Turntable {
                    n: count(n)?,
                    sweep_deg,
                })
            }
            ["random", n] => Ok(PoseSpec::Random { n: count(n)? }),
            _ => Err("expected single, turntable:N[:SWEEP_DEG] or random:N".into()),
        }
    }
}

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// Rig description (TOML).
    pub rig: PathBuf,
    /// Output directory (created if needed); frames are written as frame_000.png + frame_000.json.
    /// Frames of an earlier, longer render into the same directory are removed, so that the directory
    /// holds exactly this render.
    #[arg(long)]
    pub out: PathBuf,
    /// Views: `single`, `turntable:N[:SWEEP_DEG]` (rig turned about its up axis in N equal steps over
    /// SWEEP_DEG, default 60, centred on the default view; 360 = full turn) or `random:N`.
    #[arg(long, default_value = "single")]
    pub poses: PoseSpec,
    /// Image width, px.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1280, value_parser = clap::value_parser!(u32).range(1..=20_000))]
    pub width: u32,
    /// Image height, px.
    #[arg(long, allow_negative_numbers = true, default_value_t = 960, value_parser = clap::value_parser!(u32).range(1..=20_000))]
    pub height: u32,
    /// Focal length in x, px.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000.0, value_parser = positive)]
    pub fx: f64,
    /// Focal length in y, px.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000.0, value_parser = positive)]
    pub fy: f64,
    /// Principal point x, px (default: image centre, (width − 1)/2).
    #[arg(long, allow_negative_numbers = true)]
    pub cx: Option<f64>,
    /// Principal point y, px (default: image centre, (height − 1)/2).
    #[arg(long, allow_negative_numbers = true)]
    pub cy: Option<f64>,
    /// Lens model: brown5 (OpenCV's k1, k2, p1, p2, k3) or kb4 (the fisheye, cv::fisheye's k1..k4
    /// of θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸); e.g. `--model kb4 --fx 350 --fy 350 --k1 0.02`
    /// sees 210° across 1280 px).
    #[arg(long, default_value = "brown5", value_parser = ["brown5", "kb4"])]
    pub model: String,
    /// Radial distortion k1 (OpenCV Brown–Conrady; with --model kb4 the fisheye's k1).
    #[arg(long, default_value_t = -0.1, allow_negative_numbers = true)]
    pub k1: f64,
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub k2: f64,
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub p1: f64,
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub p2: f64,
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub k3: f64,
    /// The fisheye's k4 (--model kb4 only).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub k4: f64,
    /// Gaussian blur σ, px.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = non_negative)]
    pub blur: f64,
    /// Gaussian noise σ, grey levels.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = non_negative)]
    pub noise: f64,
    /// Gamma (output = linear^(1/G)).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0, value_parser = positive)]
    pub gamma: f64,
    /// Vignetting: brightness loss at the farthest image corner (0..1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = fraction)]
    pub vignetting: f64,
    /// Reflectance of the black squares (linear, 0..1; must be below --white). Raise it and lower
    /// --white for a low-contrast print, e.g. `--black 0.3 --white 0.55`.
    #[arg(long, allow_negative_numbers = true, default_value_t = Palette::default().black, value_parser = fraction)]
    pub black: f64,
    /// Reflectance of the white squares and the board margin (linear, 0..1; must be above --black).
    #[arg(long, allow_negative_numbers = true, default_value_t = Palette::default().white, value_parser = fraction)]
    pub white: f64,
    /// Seed for noise and random poses.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub seed: u64,
    /// Sub-samples per axis for pixels near edges.
    #[arg(long, allow_negative_numbers = true, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub supersample: u32,
}

fn number(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("'{s}' is not a finite number"))
}

fn positive(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| {
        if v > 0.0 {
            Ok(v)
        } else {
            Err(format!("{v} must be positive"))
        }
    })
}

fn non_negative(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| {
        if v >= 0.0 {
            Ok(v)
        } else {
            Err(format!("{v} must be ≥ 0"))
        }
    })
}

fn fraction(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| {
        if (0.0..=1.0).contains(&v) {
            Ok(v)
        } else {
            Err(format!("{v} must be in 0..=1"))
        }
    })
}

/// One written frame, for the summary.
#[derive(Debug, serde::Serialize)]
struct FrameSummary {
    index: u64,
    image: PathBuf,
    ground_truth: PathBuf,
    visible_corners: usize,
    visible_per_face: Vec<usize>,
}

pub fn run(args: RenderArgs, out: Output) -> anyhow::Result<u8> {
    let (rig, warnings) = Rig::load(&args.rig)?;
    let camera = Camera::pinhole(
        [args.width, args.height],
        args.fx,
        args.fy,
        args.cx.unwrap_or((f64::from(args.width) - 1.0) / 2.0),
        args.cy.unwrap_or((f64::from(args.height) - 1.0) / 2.0),
    )
    .with_distortion(
        DistortionModel::Brown5,
        &[args.k1, args.k2, args.p1, args.p2, args.k3],
    );
    let camera = if args.model == "kb4" {
        if args.p1 != 0.0 || args.p2 != 0.0 {
            return Err(SyntheticError::Setting {
                name: "p1, p2",
                value: format!("{}, {}", args.p1, args.p2),
                expected: "0 with --model kb4 (tangential terms are Brown–Conrady's)",
            }
            .into());
        }
        camera.with_distortion(DistortionModel::Kb4, &[args.k1, args.k2, args.k3, args.k4])
    } else if args.k4 != 0.0 {
        return Err(SyntheticError::Setting {
            name: "k4",
            value: args.k4.to_string(),
            expected: "0 with --model brown5 (k4 is the fisheye's: --model kb4)",
        }
        .into());
    } else {
        camera
    };
    camera.validate().map_err(SyntheticError::Camera)?;
    let settings = RenderSettings {
        supersample: args.supersample,
        blur_sigma_px: args.blur,
        noise_sigma: args.noise,
        gamma: args.gamma,
        vignetting: args.vignetting,
        seed: args.seed,
        palette: Palette {
            black: args.black,
            white: args.white,
            ..Palette::default()
        },
        ..RenderSettings::default()
    };
    settings.validate()?;
    let poses = match args.poses {
        PoseSpec::Single => vec![default_view(&rig, &camera)],
        PoseSpec::Turntable { n, sweep_deg } => turntable_poses(&rig, &camera, n, sweep_deg),
        PoseSpec::Random { n } => random_poses(&rig, &camera, n, args.seed),
    };
    std::fs::create_dir_all(&args.out).map_err(|source| OutputError {
        path: args.out.clone(),
        source,
    })?;
    remove_stale_frames(&args.out, poses.len())?;
    let mut frames = Vec::new();
    for (k, pose) in poses.iter().enumerate() {
        let index = k as u64;
        let started = std::time::Instant::now();
        let image = render(&rig, &camera, pose, &settings, index)?;
        let truth = ground_truth(&rig, &camera, pose, &settings, index);
        let (png, json) = write_frame(&args.out, &image, &truth)?;
        let mut per_face = vec![0; rig.faces.len()];
        for c in truth.visible() {
            per_face[c.face_index] += 1;
        }
        tracing::info!(
            frame = index,
            of = poses.len(),
            ms = started.elapsed().as_millis() as u64,
            visible = truth.visible().count(),
            "rendered {}",
            png.display()
        );
        frames.push(FrameSummary {
            index,
            image: png,
            ground_truth: json,
            visible_corners: truth.visible().count(),
            visible_per_face: per_face,
        });
    }
    print_summary(&rig, &warnings, &frames, out)?;
    Ok(cubecal::exit::SUCCESS)
}

/// Remove `frame_NNN.png` / `frame_NNN.json` with `NNN ≥ n` from `dir`: what an earlier, longer render
/// left there, which would otherwise pass for frames of this one.
fn remove_stale_frames(dir: &Path, n: usize) -> anyhow::Result<()> {
    let entries = std::fs::read_dir(dir).map_err(|source| OutputError {
        path: dir.to_path_buf(),
        source,
    })?;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let Some(stem) = name
            .strip_suffix(".png")
            .or_else(|| name.strip_suffix(".json"))
            .and_then(|s| s.strip_prefix("frame_"))
        else {
            continue;
        };
        let stale = stem.len() >= 3
            && stem.bytes().all(|b| b.is_ascii_digit())
            && stem.parse::<usize>().is_ok_and(|k| k >= n);
        if stale {
            let path = entry.path();
            std::fs::remove_file(&path).map_err(|source| OutputError {
                path: path.clone(),
                source,
            })?;
            tracing::info!("removed {} (left by an earlier render)", path.display());
        }
    }
    Ok(())
}

fn print_summary(
    rig: &Rig,
    warnings: &[cubecal::rig::RigWarning],
    frames: &[FrameSummary],
    out: Output,
) -> anyhow::Result<()> {
    if out.json {
        let v = serde_json::json!({
            "rig": rig.name,
            "faces": rig.faces.iter().map(|f| &f.name).collect::<Vec<_>>(),
            "warnings": warnings.iter().map(|w| w.to_string()).collect::<Vec<_>>(),
            "frames": frames,
        });
        outln!("{v}")?;
        return Ok(());
    }
    // The rig's warnings were logged on stderr when it was loaded (`Rig::load`): not twice.
    let names: Vec<&str> = rig.faces.iter().map(|f| f.name.as_str()).collect();
    outln!(
        "rig '{}': {} ({}), {}",
        rig.name,
        count(rig.faces.len(), "face"),
        names.join(", "),
        count(rig.n_corners(), "corner")
    )?;
    for f in frames {
        let per: Vec<String> = names
            .iter()
            .zip(&f.visible_per_face)
            .map(|(n, c)| format!("{n} {c}"))
            .collect();
        outln!(
            "{}  {} visible ({})  + {}",
            f.image.display(),
            count(f.visible_corners, "corner"),
            per.join(", "),
            f.ground_truth.display()
        )?;
    }
    Ok(())
}
