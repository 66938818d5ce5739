//! `cubecal detect --rig RIG.toml IMAGE...` (or `--board COLSxROWS --square MM`): find and label the rig's faces in image files.
//!
//! Loading, timing and printing only; detection is [`cubecal::detect::detect`] and drawing is
//! [`cubecal::detect::overlay`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use cubecal::detect::label::{GridCorner, LabelledCorner};
use cubecal::detect::{self, CornerFinder, FrameDetection, overlay};
use cubecal::exit;
use cubecal::rig::Rig;
use image::GrayImage;
use nalgebra::{Matrix2, Vector2, Vector3};
use serde::Serialize;

use super::solve::count;
use super::{Output, UsageError};

#[derive(Debug, clap::Args)]
#[command(
    after_help = "Images are processed in argument order; the first one that cannot be read \
    or decoded, or is smaller than 32×32 px, stops the run with exit code 3 (overlays of earlier \
    images are already written). A frame in which no face is found is not an error: its rejection \
    reasons say why."
)]
pub struct DetectArgs {
    /// Rig description (TOML; see README "Rig files"). Or --board and --square.
    #[arg(long, required_unless_present = "board")]
    pub rig: Option<PathBuf>,
    #[command(flatten)]
    pub board: super::BoardArgs,
    /// Frames to search (PNG or JPEG, any colour type; converted to 8-bit grey).
    #[arg(required = true, value_name = "IMAGE")]
    pub images: Vec<PathBuf>,
    /// Also draw what was found: with one IMAGE, OUT is the overlay PNG (or an existing directory to
    /// write it into); with several, OUT is a directory (created if missing) that receives
    /// `<image file stem>_overlay.png` per image.
    #[arg(long, value_name = "OUT")]
    pub overlay: Option<PathBuf>,
    /// A profile of this camera (a run's profile.json, or a store's current.json): grids a frame
    /// alone leaves out are settled by it, as a calibration run settles them with the camera of its
    /// other views — each labelling scored in the pose of the frame's proven faces, admitted within
    /// 3σ and by a log-likelihood ratio of 50 over every other; each decision is printed.
    #[arg(long, value_name = "PROFILE")]
    pub profile: Option<PathBuf>,
}

/// Errors of `cubecal detect` that are not library errors.
#[derive(Debug, thiserror::Error)]
pub enum DetectCliError {
    #[error("cannot read image {path}")]
    ReadImage {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot decode image {path}")]
    DecodeImage {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot create overlay directory {path}")]
    CreateOverlayDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "images {first} and {second} would both write the overlay {overlay}: rename one, or run them separately"
    )]
    OverlayClash {
        first: PathBuf,
        second: PathBuf,
        overlay: PathBuf,
    },
}

impl DetectCliError {
    /// The process exit code for this error (see [`cubecal::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            DetectCliError::ReadImage { .. } | DetectCliError::DecodeImage { .. } => {
                exit::BAD_INPUT
            }
            DetectCliError::OverlayClash { .. } => exit::USAGE,
            // As for every other result file cubecal fails to write (README: exit codes).
            DetectCliError::CreateOverlayDir { .. } => exit::IO,
        }
    }
}

/// One corner in the `--json` output: a field-for-field mirror of [`LabelledCorner`] (serde's remote
/// derive), so a detector field is published by adding its line here.
#[derive(Serialize)]
#[serde(remote = "LabelledCorner")]
struct CornerJson {
    row: usize,
    col: usize,
    #[serde(serialize_with = "xyz_array")]
    xyz: Vector3<f64>,
    #[serde(serialize_with = "uv_array")]
    uv: Vector2<f64>,
    /// Estimated standard deviation of each coordinate of `uv` (px), from the corner's fit.
    sigma_px: f64,
    /// Covariance of `uv` from the corner's fit, `[var_u, cov_uv, var_v]` (px²).
    #[serde(serialize_with = "cov_array")]
    cov: Matrix2<f64>,
}

fn cov_array<S: serde::Serializer>(c: &Matrix2<f64>, s: S) -> Result<S::Ok, S::Error> {
    cubecal::calib::observations::cov_to_array(c).serialize(s)
}

fn xyz_array<S: serde::Serializer>(v: &Vector3<f64>, s: S) -> Result<S::Ok, S::Error> {
    [v.x, v.y, v.z].serialize(s)
}

fn uv_array<S: serde::Serializer>(v: &Vector2<f64>, s: S) -> Result<S::Ok, S::Error> {
    [v.x, v.y].serialize(s)
}

#[derive(Serialize)]
struct CornerRef<'a>(#[serde(with = "CornerJson")] &'a LabelledCorner);

#[derive(Serialize)]
struct FaceJson<'a> {
    face: &'a str,
    corners: Vec<CornerRef<'a>>,
    /// Labels certain only up to a shift or turn within the plane (one-face rig: cut only by the frame
    /// border, or a lone 180°-symmetric board): the view's pose is not trusted, its corners are.
    #[serde(skip_serializing_if = "Option::is_none")]
    ambiguous_pose: Option<&'a str>,
    /// How the face's identity was decided when its size and colours left a choice: the rig
    /// geometry's margin over the closest alternative, or the symmetry that leaves it open.
    #[serde(skip_serializing_if = "Option::is_none")]
    identity: Option<&'a str>,
}

#[derive(Serialize)]
#[serde(remote = "GridCorner")]
struct GridCornerJson {
    row: usize,
    col: usize,
    #[serde(serialize_with = "uv_array")]
    uv: Vector2<f64>,
}

#[derive(Serialize)]
struct GridCornerRef<'a>(#[serde(with = "GridCornerJson")] &'a GridCorner);

/// A rejected grid: the reason, and its corners by their index in the grid (not a face's) and image
/// position (empty for a rejection of the whole frame).
#[derive(Serialize)]
struct RejectionJson<'a> {
    reason: &'a str,
    corners: Vec<GridCornerRef<'a>>,
}

/// One image in the `--json` array.
#[derive(Serialize)]
struct ImageJson<'a> {
    image: String,
    width: u32,
    height: u32,
    faces: Vec<FaceJson<'a>>,
    rejected: Vec<RejectionJson<'a>>,
    time_ms: f64,
}

impl<'a> ImageJson<'a> {
    fn new(image: &Path, det: &'a FrameDetection, rig: &'a Rig, time_ms: f64) -> Self {
        ImageJson {
            image: image.display().to_string(),
            width: det.width,
            height: det.height,
            faces: det
                .faces
                .iter()
                .map(|f| FaceJson {
                    face: face_name(rig, f.face),
                    corners: f.corners.iter().map(CornerRef).collect(),
                    ambiguous_pose: f.ambiguous_pose.as_deref(),
                    identity: f.identity.as_deref(),
                })
                .collect(),
            rejected: det
                .rejected
                .iter()
                .map(|r| RejectionJson {
                    reason: &r.reason,
                    corners: r.corners.iter().map(GridCornerRef).collect(),
                })
                .collect(),
            time_ms,
        }
    }
}

fn face_name(rig: &Rig, face: usize) -> &str {
    rig.faces.get(face).map_or("?", |f| f.name.as_str())
}

/// One processed image.
struct Processed {
    image: PathBuf,
    detection: FrameDetection,
    time_ms: f64,
    overlay: Option<PathBuf>,
}

pub fn run(args: DetectArgs, out: Output) -> anyhow::Result<u8> {
    // Rig warnings are logged by `Rig::load`; the JSON output has no place for them.
    let (rig, _warnings) = match (&args.rig, args.board.board()) {
        (Some(path), _) => Rig::load(path)?,
        (None, Some((size, square_mm))) => {
            let (rig, warnings) = Rig::from_toml_str(
                &cubecal::rig::board_toml(size, square_mm),
                &format!("--board {size} --square {square_mm}"),
            )?;
            rig.log_warnings(&warnings);
            (rig, warnings)
        }
        (None, None) => {
            return Err(super::UsageError(
                "give --rig RIG.toml or --board COLSxROWS --square MM".into(),
            )
            .into());
        }
    };
    let overlays = match &args.overlay {
        Some(target) => Some(overlay_paths(target, &args.images)?),
        None => None,
    };
    let camera = match &args.profile {
        Some(path) => {
            let profile = cubecal::profile::read_document(path)?;
            let camera = cubecal::report::analysis::camera_from_report(&profile.calibration)
                .with_context(|| format!("the camera of profile {}", path.display()))?;
            Some((path, camera))
        }
        None => None,
    };
    let mut finder = CornerFinder::new()?;
    let mut done = Vec::with_capacity(args.images.len());
    for (k, path) in args.images.iter().enumerate() {
        let img = load_grey(path)?;
        let started = Instant::now();
        let mut detection = detect::detect(&mut finder, &img, &rig)
            .with_context(|| format!("detecting corners in {}", path.display()))?;
        if let Some((profile, camera)) = &camera {
            if camera.image_size != [img.width(), img.height()] {
                return Err(UsageError(format!(
                    "{} is {}×{}, the camera of profile {} is for {}×{} images",
                    path.display(),
                    img.width(),
                    img.height(),
                    profile.display(),
                    camera.image_size[0],
                    camera.image_size[1]
                ))
                .into());
            }
            let name = path.display().to_string();
            cubecal::detect::settle::settle(&rig, camera, &mut detection, &name);
        }
        let time_ms = started.elapsed().as_secs_f64() * 1e3;
        let overlay = match &overlays {
            Some(paths) => {
                let o = &paths[k];
                overlay::write_png(&overlay::draw_annotated(&img, &detection, &rig)?, o)?;
                Some(o.clone())
            }
            None => None,
        };
        let p = Processed {
            image: path.clone(),
            detection,
            time_ms,
            overlay,
        };
        if !out.json {
            print_human(&p, &rig)?;
        }
        done.push(p);
    }
    if out.json {
        print_json(&done, &rig)?;
    }
    Ok(exit::SUCCESS)
}

/// Read and decode an image file (format from its content, not its name) as 8-bit grey.
pub(crate) fn load_grey(path: &Path) -> Result<GrayImage, DetectCliError> {
    let bytes = std::fs::read(path).map_err(|source| DetectCliError::ReadImage {
        path: path.to_path_buf(),
        source,
    })?;
    let img = image::load_from_memory(&bytes).map_err(|source| DetectCliError::DecodeImage {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(img.into_luma8())
}

/// Where each image's overlay goes (see [`DetectArgs::overlay`]); creates the directory if needed.
fn overlay_paths(target: &Path, images: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    if images.len() == 1 && !target.is_dir() {
        // Overlays are PNG: a name promising another format would hold the wrong bytes.
        if let Some(ext) = target.extension()
            && !ext.eq_ignore_ascii_case("png")
        {
            return Err(UsageError(format!(
                "--overlay {}: overlays are written as PNG; name the file .png",
                target.display()
            ))
            .into());
        }
        return Ok(vec![target.to_path_buf()]);
    }
    let mut paths = Vec::with_capacity(images.len());
    let mut owner: HashMap<PathBuf, &PathBuf> = HashMap::new();
    for image in images {
        let stem = image
            .file_stem()
            .map_or_else(|| "image".into(), |s| s.to_string_lossy());
        let path = target.join(format!("{stem}_overlay.png"));
        if let Some(first) = owner.get(&path)
            && *first != image
        {
            return Err(DetectCliError::OverlayClash {
                first: (*first).clone(),
                second: image.clone(),
                overlay: path,
            }
            .into());
        }
        owner.insert(path.clone(), image);
        paths.push(path);
    }
    std::fs::create_dir_all(target).map_err(|source| DetectCliError::CreateOverlayDir {
        path: target.to_path_buf(),
        source,
    })?;
    Ok(paths)
}

fn print_human(p: &Processed, rig: &Rig) -> anyhow::Result<()> {
    let det = &p.detection;
    let n_corners: usize = det.faces.iter().map(|f| f.corners.len()).sum();
    outln!(
        "{}: {}, {} in {:.1} ms",
        p.image.display(),
        count(det.faces.len(), "face"),
        count(n_corners, "corner"),
        p.time_ms
    )?;
    for f in &det.faces {
        outln!(
            "  face '{}': {}",
            face_name(rig, f.face),
            count(f.corners.len(), "corner")
        )?;
        if let Some(why) = &f.ambiguous_pose {
            outln!(
                "    pose not trusted (labels certain up to a motion that moves the pose only): {why}"
            )?;
        }
        if let Some(how) = &f.identity {
            outln!("    identity {how}")?;
        }
    }
    for r in &det.rejected {
        outln!("  rejected: {}", r.reason)?;
    }
    if let Some(o) = &p.overlay {
        outln!("  overlay: {}", o.display())?;
    }
    Ok(())
}

fn print_json(done: &[Processed], rig: &Rig) -> anyhow::Result<()> {
    let images: Vec<ImageJson<'_>> = done
        .iter()
        .map(|p| ImageJson::new(&p.image, &p.detection, rig, p.time_ms))
        .collect();
    outln!("{}", serde_json::to_string(&images)?)?;
    Ok(())
}
