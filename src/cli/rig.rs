//! `cubecal rig ...` (alias `target`): work with rig descriptions.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Subcommand;
use cubecal::calib::{self, RigCalibration, RigRefineOptions};
use cubecal::camera::DistortionModel;
use cubecal::detect::{self, CornerFinder};
use cubecal::rig::survey::{self, RigSurvey};
use cubecal::rig::{Rig, svg};

use super::Output;
use super::detect::{DetectCliError, load_grey};
use super::solve::ModelArg;

#[derive(Debug, Subcommand)]
pub enum RigCommand {
    /// Write one printable SVG per face of a rig, at exact physical scale (print at 100 %, then check
    /// the 100 mm scale bar with a ruler).
    Print {
        /// Rig description (TOML).
        rig: std::path::PathBuf,
        /// Output directory (created if needed).
        #[arg(long)]
        out: std::path::PathBuf,
    },
    /// Measure the as-built rig from frames of it: each face's pose relative to a reference face,
    /// estimated jointly with the camera, written as a rig TOML with the measured poses, their σ and
    /// the deviation from RIG.toml. Frames with no labelled face are skipped; a face that no rigid
    /// placement explains (wrong square size, board turned) is named and nothing is written (exit 3).
    Survey(SurveyArgs),
}

#[derive(Debug, clap::Args)]
pub struct SurveyArgs {
    /// The nominal rig description (TOML) the cube was built from.
    pub rig: PathBuf,
    /// Frames (PNG or JPEG) or directories of frames (a recorded session): every `.png`/`.jpg` in a
    /// directory, in name order.
    #[arg(required = true, value_name = "FRAMES")]
    pub frames: Vec<PathBuf>,
    /// Where to write the surveyed rig (TOML).
    #[arg(long)]
    pub out: PathBuf,
    /// Distortion model of the camera calibrated alongside.
    #[arg(long, value_enum, default_value = "brown5")]
    pub model: ModelArg,
    /// The face the others are measured against (default: the face with the most corners).
    #[arg(long, value_name = "FACE")]
    pub reference: Option<String>,
}

pub fn run(cmd: RigCommand, out: Output) -> anyhow::Result<u8> {
    match cmd {
        RigCommand::Print { rig, out: dir } => {
            let (rig, warnings) = Rig::load(&rig)?;
            let paths = svg::write_face_svgs(&rig, &dir)?;
            print_written(&rig, &warnings, &paths, out)?;
            Ok(cubecal::exit::SUCCESS)
        }
        RigCommand::Survey(args) => run_survey(args, out),
    }
}

/// The frames named on the command line, directories expanded.
fn expand_frames(inputs: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut frames = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|source| DetectCliError::ReadImage {
                    path: p.clone(),
                    source,
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.extension().and_then(|x| x.to_str()).is_some_and(|x| {
                        matches!(x.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg")
                    })
                })
                .collect();
            found.sort();
            frames.extend(found);
        } else {
            frames.push(p.clone());
        }
    }
    Ok(frames)
}

fn run_survey(args: SurveyArgs, out: Output) -> anyhow::Result<u8> {
    let nominal_bytes =
        std::fs::read(&args.rig).map_err(|source| cubecal::rig::RigError::Read {
            path: args.rig.display().to_string(),
            source,
        })?;
    let (rig, _) = Rig::load(&args.rig)?;
    let frames = expand_frames(&args.frames)?;
    let mut finder = CornerFinder::new()?;
    let mut views = Vec::new();
    let mut size: Option<[u32; 2]> = None;
    for path in &frames {
        let img = load_grey(path)?;
        let this = [img.width(), img.height()];
        if let Some(s) = size
            && s != this
        {
            anyhow::bail!(calib::CalibError::InvalidOption {
                reason: format!(
                    "{} is {}×{} but the first frame is {}×{}: one camera mode per survey",
                    path.display(),
                    this[0],
                    this[1],
                    s[0],
                    s[1]
                ),
            });
        }
        size = Some(this);
        let det = detect::detect(&mut finder, &img, &rig)?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| path.display().to_string());
        let view = det.to_rig_view(&name);
        tracing::info!(frame = %name, corners = view.points.len(), "detected");
        if !view.points.is_empty() {
            views.push(view);
        }
    }
    let Some(size) = size else {
        anyhow::bail!(calib::CalibError::NoViews);
    };
    let reference_face =
        match &args.reference {
            None => None,
            Some(name) => Some(rig.faces.iter().position(|f| &f.name == name).ok_or_else(
                || calib::CalibError::InvalidOption {
                    reason: format!(
                    "--reference {name}: rig '{}' has no such face (faces: {})",
                    rig.name,
                    rig.faces.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(", ")
                ),
                },
            )?),
        };
    let mut opts = RigRefineOptions {
        reference_face,
        ..RigRefineOptions::default()
    };
    opts.solve.model = match args.model {
        ModelArg::Pinhole => DistortionModel::Pinhole,
        ModelArg::Brown5 => DistortionModel::Brown5,
        ModelArg::Brown8 => DistortionModel::Brown8,
        ModelArg::Kb4 => DistortionModel::Kb4,
    };
    let result = calib::solve_rig(&rig, &views, size, &opts)
        .with_context(|| format!("surveying rig '{}' from {} frame(s)", rig.name, views.len()))?;
    if !result.calibration.termination.is_converged() {
        anyhow::bail!(calib::CalibError::Degenerate {
            reason: format!(
                "the survey fit did not converge ({}); nothing written",
                result.calibration.termination.as_str()
            ),
        });
    }
    let comment = comment_lines(&args.rig, &result, views.len());
    let text = survey::surveyed_toml(
        &result.rig,
        RigSurvey {
            nominal_sha256: survey::content_sha256(&nominal_bytes),
            reference_face: rig.faces[result.reference_face].name.clone(),
            views: views.len(),
            points: result.calibration.n_points,
            rms_px: result.calibration.rms_px,
        },
        result.faces.iter().map(|f| f.to_survey()).collect(),
        &comment,
    )
    .context("cannot express the surveyed rig as TOML")?;
    survey::write_surveyed(&args.out, &text)?;
    print_survey(&args.out, &result, views.len(), frames.len(), &text, out);
    Ok(cubecal::exit::SUCCESS)
}

fn comment_lines(nominal: &Path, r: &RigCalibration, n_views: usize) -> Vec<String> {
    let mut lines = vec![
        format!(
            "Surveyed by cubecal rig survey from {} and {n_views} frame(s): residual RMS {:.4} px.",
            nominal.display(),
            r.calibration.rms_px
        ),
        format!(
            "Face poses relative to '{}' (kept as in the nominal file); deviations with their σ in [faces.survey].",
            r.faces[r.reference_face].name
        ),
    ];
    lines.extend(r.faces.iter().map(|f| f.describe()));
    lines
}

#[allow(clippy::print_stdout)]
fn print_survey(
    path: &Path,
    r: &RigCalibration,
    n_views: usize,
    n_frames: usize,
    text: &str,
    out: Output,
) {
    let cam = &r.calibration.camera;
    if out.json {
        let faces: Vec<_> = r
            .faces
            .iter()
            .map(|f| {
                serde_json::json!({
                    "face": f.name, "refined": f.refined, "reference": f.face == r.reference_face,
                    "offset_mm": f.offset_mm, "offset_std_mm": f.offset_std_mm,
                    "rotation_deg": f.rotation_deg, "rotation_std_deg": f.rotation_std_deg,
                    "tilt_deg": f.tilt_deg(), "rms_px": f.rms_px, "n_points": f.n_points,
                })
            })
            .collect();
        let v = serde_json::json!({
            "out": path, "rig_sha256": survey::content_sha256(text.as_bytes()),
            "frames": n_frames, "views": n_views, "rms_px": r.calibration.rms_px,
            "camera_matrix": [[cam.fx(), cam.skew(), cam.cx()], [0.0, cam.fy(), cam.cy()], [0.0, 0.0, 1.0]],
            "faces": faces,
        });
        println!("{v}");
        return;
    }
    println!(
        "{}: surveyed from {n_views} of {n_frames} frame(s), {} corners, residual RMS {:.4} px",
        path.display(),
        r.calibration.n_points,
        r.calibration.rms_px
    );
    for f in &r.faces {
        if f.refined {
            println!(
                "  {} (σ {:.3}/{:.3}/{:.3} mm, {:.3}/{:.3}/{:.3}°)",
                f.describe(),
                f.offset_std_mm[0],
                f.offset_std_mm[1],
                f.offset_std_mm[2],
                f.rotation_std_deg[0],
                f.rotation_std_deg[1],
                f.rotation_std_deg[2]
            );
        } else if f.face == r.reference_face {
            println!("  {}: reference face, as in the rig file", f.name);
        } else {
            println!("  {}", f.describe());
        }
    }
}

fn print_written(
    rig: &Rig,
    warnings: &[cubecal::rig::RigWarning],
    paths: &[std::path::PathBuf],
    out: Output,
) -> anyhow::Result<()> {
    if out.json {
        let faces: Vec<_> = rig
            .faces
            .iter()
            .zip(paths)
            .map(|(f, p)| {
                let lay = svg::PageLayout::for_face(f);
                serde_json::json!({
                    "face": f.name, "svg": p, "cols": f.cols, "rows": f.rows, "square_mm": f.square_mm,
                    "page_mm": [lay.page_width_mm, lay.page_height_mm],
                })
            })
            .collect();
        let v = serde_json::json!({
            "rig": rig.name,
            "warnings": warnings.iter().map(|w| w.to_string()).collect::<Vec<_>>(),
            "faces": faces,
        });
        outln!("{v}")?;
        return Ok(());
    }
    // The rig's warnings were logged on stderr when it was loaded (`Rig::load`): not twice.
    for (f, p) in rig.faces.iter().zip(paths) {
        let lay = svg::PageLayout::for_face(f);
        outln!(
            "{}: face '{}', {}×{} inner corners, {} mm squares, page {:.1} × {:.1} mm",
            p.display(),
            f.name,
            f.cols,
            f.rows,
            f.square_mm,
            lay.page_width_mm,
            lay.page_height_mm
        )?;
    }
    Ok(())
}
