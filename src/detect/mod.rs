//! Corner detection: grayscale frame → X-corners → checkerboard grids → fitted, completed grids →
//! labelled rig correspondences with a per-corner σ.
//!
//! ## Front end: `chess-corners`
//! X-corners come from the `chess-corners` crate (two-level ChESS pyramid, saddle-point sub-pixel
//! refinement with radius 3). It was measured before adoption (see the issue notes): on exactly
//! area-sampled synthetic boards 100 % recall, 0.022 px RMS, 3 false detections over 36 images; on the
//! 26 OpenCV sample images every true corner found; ~9 ms per 1280×960 frame. Its positions use the
//! pixel-centre convention of this crate (measured offset < 0.001 px). Two caveats handled here: its
//! single-scale path panics on tiny images (frames under [`MIN_SIDE`] pixels are rejected first) and
//! the default refiner radius 2 drops real corners on JPEG images.
//!
//! ## Grid assembly, fitting and completion (ours)
//! [`grid`] links corners into a lattice by growing from seeds along their local axes. [`complete`]
//! fits every lattice corner with the X-junction model of [`refine`] (window shaped by the lattice,
//! per-corner σ from the fit) and recovers the corners the front end missed where the lattice
//! predicts them. [`label`] decides which face each grid is, never guessing; [`score`] measures all of
//! this against the ground truth of synthetic renders.

use image::GrayImage;
use nalgebra::Vector2;

pub mod complete;
pub mod grid;
pub mod label;
pub mod overlay;
pub mod refine;
pub mod score;

/// ChESS response floor. The crate's default (30) loses most corners of foreshortened, low-contrast
/// faces (squares of ~15–25 px seen at 60°+); false corners this lets through are removed by grid
/// assembly, which needs a consistent lattice.
pub const RESPONSE_THRESHOLD: f32 = 30.0;

/// Pyramid levels of the ChESS front end. The crate's default of 3 finds only 66 of the 170 corners of
/// a cube frame whose side faces are seen at 60°+ (squares ~8 px across in one direction); 2 levels
/// find 169 at about 3× the time of 3 levels (measured on a 1280×960 render).
pub const PYRAMID_LEVELS: u8 = 2;
/// Smallest pyramid level side (px).
pub const PYRAMID_MIN_SIZE: usize = 128;
/// Search radius (px) when refining a coarse seed at the next finer level.
pub const PYRAMID_REFINEMENT_RADIUS: u32 = 3;

/// Smallest frame side the detector accepts.
pub const MIN_SIDE: u32 = 32;

/// Errors from the detector.
#[derive(Debug, thiserror::Error)]
pub enum DetectError {
    #[error("frame {width}×{height} is too small (minimum {MIN_SIDE}×{MIN_SIDE})")]
    TooSmall { width: u32, height: u32 },
    #[error("corner front end failed: {0}")]
    FrontEnd(String),
}

impl DetectError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            DetectError::TooSmall { .. } => crate::exit::BAD_INPUT,
            DetectError::FrontEnd(_) => crate::exit::INTERNAL,
        }
    }
}

/// An X-corner: sub-pixel position, the directions of its two edge lines (radians, modulo π), and the
/// front end's response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct XCorner {
    pub uv: Vector2<f64>,
    pub axes: [f64; 2],
    pub response: f64,
}

/// The X-corner front end, reusable across frames (it keeps its scratch buffers).
pub struct CornerFinder {
    detector: chess_corners::Detector,
}

impl std::fmt::Debug for CornerFinder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CornerFinder").finish_non_exhaustive()
    }
}

impl CornerFinder {
    pub fn new() -> Result<CornerFinder, DetectError> {
        Self::with_threshold(RESPONSE_THRESHOLD)
    }

    /// A front end with a given ChESS response floor (raw 8-bit response units).
    pub fn with_threshold(threshold: f32) -> Result<CornerFinder, DetectError> {
        let mut saddle = chess_corners::SaddlePointConfig::default();
        saddle.radius = 3;
        let mut cfg = chess_corners::DetectorConfig::chess()
            .with_multiscale(chess_corners::MultiscaleConfig::pyramid(
                PYRAMID_LEVELS,
                PYRAMID_MIN_SIZE,
                PYRAMID_REFINEMENT_RADIUS,
            ))
            .with_refiner(chess_corners::ImageRefiner::SaddlePoint(saddle))
            .with_threshold(threshold);
        // A corner the saddle refiner rejects is kept at its ChESS position rather than lost: on JPEG
        // images the refiner rejects a few real corners near the board's border.
        if let chess_corners::DetectionStrategy::Chess(chess) = &mut cfg.strategy {
            chess.on_refiner_reject = chess_corners::OnRefinerReject::KeepCenterOfMass;
        }
        let detector = chess_corners::Detector::new(cfg)
            .map_err(|e| DetectError::FrontEnd(format!("{e:?}")))?;
        Ok(CornerFinder { detector })
    }

    /// All X-corners of a frame.
    pub fn find(&mut self, img: &GrayImage) -> Result<Vec<XCorner>, DetectError> {
        let (width, height) = img.dimensions();
        if width < MIN_SIDE || height < MIN_SIDE {
            return Err(DetectError::TooSmall { width, height });
        }
        let corners = self
            .detector
            .detect_u8(img.as_raw(), width, height)
            .map_err(|e| DetectError::FrontEnd(format!("{e:?}")))?;
        Ok(corners
            .into_iter()
            .filter_map(|c| {
                let axes = c.axes?;
                let uv = Vector2::new(f64::from(c.x), f64::from(c.y));
                uv.iter().all(|v| v.is_finite()).then_some(XCorner {
                    uv,
                    axes: [
                        f64::from(axes[0].angle).rem_euclid(std::f64::consts::PI),
                        f64::from(axes[1].angle).rem_euclid(std::f64::consts::PI),
                    ],
                    response: f64::from(c.response),
                })
            })
            .collect())
    }
}

/// Everything found in one frame.
#[derive(Debug, Clone)]
pub struct FrameDetection {
    pub width: u32,
    pub height: u32,
    pub faces: Vec<label::FaceDetection>,
    pub rejected: Vec<label::Rejection>,
}

impl FrameDetection {
    /// The labelled corners as one calibration view.
    pub fn to_view(&self, name: &str) -> crate::calib::View {
        crate::calib::View {
            name: name.to_string(),
            points: self
                .faces
                .iter()
                .flat_map(|f| f.corners.iter())
                .map(|c| crate::calib::Correspondence {
                    xyz: c.xyz,
                    uv: c.uv,
                })
                .collect(),
        }
    }
}

/// Corners → grids → labelled faces for one frame.
pub fn detect(
    finder: &mut CornerFinder,
    img: &GrayImage,
    rig: &crate::target::Rig,
) -> Result<FrameDetection, DetectError> {
    let corners = finder.find(img)?;
    let grids = grid::assemble(&corners);
    let max_lines = rig
        .faces
        .iter()
        .map(|f| f.rows.max(f.cols))
        .max()
        .unwrap_or(0);
    let completed: Vec<complete::Completed> = grids
        .iter()
        .map(|g| complete::complete(img, &corners, g, max_lines))
        .collect();
    let (faces, mut rejected) = label::label(img, rig, &completed);
    if grids.is_empty() {
        rejected.push(label::Rejection {
            reason: format!(
                "no checkerboard grid found ({} isolated corners)",
                corners.len()
            ),
        });
    }
    Ok(FrameDetection {
        width: img.width(),
        height: img.height(),
        faces,
        rejected,
    })
}
