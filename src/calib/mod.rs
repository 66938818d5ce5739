//! The solvers: normalised DLT, RQ decomposition, planar homographies and Zhang's closed form
//! ([`linear`]), initialisation of a multi-view problem ([`init`]), and Levenberg–Marquardt refinement
//! with parameter uncertainty ([`solve()`], and with the rig's geometry: [`solve_rig`]). Both refinements
//! run on one Levenberg–Marquardt machinery (`lm_core.rs`: a shared parameter block plus a pose block per
//! view, solved by the Schur complement), which depends on nothing else in `calib` but [`CalibError`].
//! The correspondence file format read by `cubecal solve` is [`observations`].
//!
//! Hand-written rather than taken from a crate: the refinement needs the block (Schur complement)
//! structure of a calibration problem, the exact OpenCV distortion model with analytic Jacobians, parameter
//! tying (aspect ratio) and the marginal covariance of the intrinsics; generic least-squares crates
//! (`levenberg-marquardt`, `argmin`) offer dense normal equations over an opaque parameter vector only.

use nalgebra::{Matrix2, Vector2, Vector3};
use serde::Serialize;

pub mod determined;
pub mod init;
pub mod linear;
mod lm;
mod lm_core;
pub mod neighbours;
pub mod observations;
pub mod pose;
pub mod report;
pub mod rigrefine;

pub use determined::{
    SIGNIFICANCE_SIGMAS, UNDETERMINED_EFFECT_PX, UndeterminedParam, insignificant_at_border,
    undetermined_parameters,
};
pub use lm::{
    Calibration, Fix, SolveOptions, ViewResult, Weighting, predicted_covariance, solve, solve_from,
    view_information,
};
pub use lm_core::{Loss, Termination};
pub use rigrefine::{
    FaceCorrection, NoiseCorrelation, RigCalibration, RigPoint, RigRefineOptions, RigView,
    inflate_for_neighbour_correlation, solve_rig,
};

/// One 2D–3D correspondence: a rig point (mm) and where it was seen (pixels, centre convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    pub xyz: Vector3<f64>,
    pub uv: Vector2<f64>,
    /// Covariance of `uv` (px²), when the detector gives one: the solve then weights the point by
    /// its inverse (see [`Weighting`]).
    pub cov: Option<Matrix2<f64>>,
}

impl Correspondence {
    /// A correspondence with no covariance of its own (equal weights).
    pub fn new(xyz: Vector3<f64>, uv: Vector2<f64>) -> Correspondence {
        Correspondence { xyz, uv, cov: None }
    }
}

/// Whether a covariance is usable as a point's weight: finite, symmetric, positive definite.
pub fn valid_covariance(c: &Matrix2<f64>) -> bool {
    c.iter().all(|x| x.is_finite())
        && (c[(0, 1)] - c[(1, 0)]).abs() <= 1e-9 * (c[(0, 0)] + c[(1, 1)]).abs()
        && c[(0, 0)] > 0.0
        && c[(0, 0)] * c[(1, 1)] - c[(0, 1)] * c[(1, 0)] > 0.0
}

/// All correspondences seen in one image.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub name: String,
    pub points: Vec<Correspondence>,
}

impl View {
    /// The same view (same name) with each point mapped by `f`, those it returns `None` for left out.
    pub fn filter_map_points(
        &self,
        f: impl FnMut(&Correspondence) -> Option<Correspondence>,
    ) -> View {
        View {
            name: self.name.clone(),
            points: self.points.iter().filter_map(f).collect(),
        }
    }
}

/// Errors from the solvers. Each says what was wrong and, where there is one, what to do about it.
#[derive(Debug, Clone, PartialEq, thiserror::Error, Serialize)]
pub enum CalibError {
    #[error("too few points: {got} given, at least {need} needed")]
    TooFewPoints { got: usize, need: usize },
    #[error("too few views: {got} given, at least {need} needed")]
    TooFewViews { got: usize, need: usize },
    #[error("{what} {index} is not finite (NaN or infinite)")]
    NonFinite { what: String, index: usize },
    #[error(
        "all 3D points are coplanar (relative thickness {thickness:.2e}): the 3D DLT cannot solve this; use the planar (homography) path"
    )]
    Coplanar { thickness: f64 },
    #[error(
        "the linear system is rank-deficient (singular value ratio {ratio:.2e}): the points do not determine a unique solution"
    )]
    RankDeficient { ratio: f64 },
    #[error("SVD did not converge within {iterations} iterations")]
    SvdNotConverged { iterations: usize },
    #[error("degenerate problem: {reason}")]
    Degenerate { reason: String },
    #[error("view '{view}': {source}")]
    InView {
        view: String,
        #[source]
        source: Box<CalibError>,
    },
    #[error("view '{view}': point {index} duplicates point {first} (same 3D position)")]
    DuplicatePoint {
        view: String,
        index: usize,
        first: usize,
    },
    #[error("view '{view}' has no points")]
    EmptyView { view: String },
    #[error("no views given")]
    NoViews,
    #[error(
        "the rig coordinates are left-handed (a mirror image of any real camera view): negate one axis of the 3D points"
    )]
    LeftHandedRig,
    #[error(
        "parameters are not determined by these views ({reason}): add views at other orientations or fix parameters"
    )]
    Unobservable { reason: String },
    #[error("invalid option: {reason}")]
    InvalidOption { reason: String },
    #[error(
        "{} not determined by these views (the data cannot tell {} apart from the other parameters): add views at other orientations or hold {} fixed",
        list_params(params), if params.len() == 1 { "it" } else { "them" }, if params.len() == 1 { "it" } else { "them" }
    )]
    Undetermined { params: Vec<String> },
    #[error(
        "view '{view}': point {index}: image point ({u:?}, {v:?}) lies outside the {width}×{height} image (image_size in the input is wrong, or the point is)"
    )]
    PointOutsideImage {
        view: String,
        index: usize,
        u: f64,
        v: f64,
        width: u32,
        height: u32,
    },
    #[error(
        "view '{view}': point {index}: 3D point ({x:?}, {y:?}, {z:?}) is absurdly far from the rig origin (more than {limit_mm} mm): wrong units?"
    )]
    OutOfRange {
        view: String,
        index: usize,
        x: f64,
        y: f64,
        z: f64,
        limit_mm: f64,
    },
    #[error(
        "the solved principal point ({cx:.1}, {cy:.1}) lies outside the {width}×{height} image: the data do not determine it (or image_size is wrong); hold it fixed or add views"
    )]
    PrincipalPointOutside {
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
    },
    #[error("two views are named '{name}' (views {first} and {second}): names must be unique")]
    DuplicateViewName {
        name: String,
        first: usize,
        second: usize,
    },
    #[error("the rig file does not match the printed rig: face '{face}': {reason}")]
    RigMismatch { face: String, reason: String },
}

/// `k4, k5 and k6 are` / `k3 is`.
fn list_params(params: &[String]) -> String {
    match params {
        [] => "some parameters are".into(),
        [one] => format!("parameter {one} is"),
        [init @ .., last] => format!("parameters {} and {last} are", init.join(", ")),
    }
}

/// Rig coordinates (mm) beyond this distance from the origin (10 km) are refused as absurd.
pub const MAX_RIG_COORDINATE_MM: f64 = 1e7;

impl CalibError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        use crate::exit;
        match self {
            CalibError::TooFewPoints { .. }
            | CalibError::TooFewViews { .. }
            | CalibError::NonFinite { .. }
            | CalibError::Coplanar { .. }
            | CalibError::DuplicatePoint { .. }
            | CalibError::EmptyView { .. }
            | CalibError::NoViews
            | CalibError::LeftHandedRig
            | CalibError::InvalidOption { .. }
            | CalibError::PointOutsideImage { .. }
            | CalibError::OutOfRange { .. }
            | CalibError::DuplicateViewName { .. }
            | CalibError::RigMismatch { .. } => exit::BAD_INPUT,
            CalibError::RankDeficient { .. }
            | CalibError::SvdNotConverged { .. }
            | CalibError::Degenerate { .. }
            | CalibError::Unobservable { .. }
            | CalibError::Undetermined { .. }
            | CalibError::PrincipalPointOutside { .. } => exit::CALIBRATION_FAILED,
            CalibError::InView { source, .. } => source.exit_code(),
        }
    }

    pub(crate) fn in_view(self, view: &str) -> CalibError {
        match self {
            e @ (CalibError::InView { .. }
            | CalibError::DuplicatePoint { .. }
            | CalibError::EmptyView { .. }
            | CalibError::PointOutsideImage { .. }
            | CalibError::OutOfRange { .. }) => e,
            e => CalibError::InView {
                view: view.to_string(),
                source: Box::new(e),
            },
        }
    }
}

/// Check views for the problems every solver must refuse: no views, empty views, non-finite values,
/// absurd rig coordinates (beyond [`MAX_RIG_COORDINATE_MM`]), duplicated view names and duplicated 3D
/// points within a view.
pub fn validate_views(views: &[View]) -> Result<(), CalibError> {
    if views.is_empty() {
        return Err(CalibError::NoViews);
    }
    let mut names: Vec<(&str, usize)> = views
        .iter()
        .enumerate()
        .map(|(i, v)| (v.name.as_str(), i))
        .collect();
    names.sort();
    for w in names.windows(2) {
        if w[0].0 == w[1].0 {
            return Err(CalibError::DuplicateViewName {
                name: w[0].0.to_string(),
                first: w[0].1,
                second: w[1].1,
            });
        }
    }
    for v in views {
        if v.points.is_empty() {
            return Err(CalibError::EmptyView {
                view: v.name.clone(),
            });
        }
        for (i, c) in v.points.iter().enumerate() {
            if !c.xyz.iter().all(|x| x.is_finite()) {
                return Err(CalibError::NonFinite {
                    what: "3D point".into(),
                    index: i,
                }
                .in_view(&v.name));
            }
            if !c.uv.iter().all(|x| x.is_finite()) {
                return Err(CalibError::NonFinite {
                    what: "image point".into(),
                    index: i,
                }
                .in_view(&v.name));
            }
            if let Some(cov) = &c.cov
                && !valid_covariance(cov)
            {
                return Err(CalibError::InvalidOption {
                    reason: format!(
                        "point {i}: covariance [[{}, {}], [{}, {}]] px² is not symmetric positive definite",
                        cov[(0, 0)],
                        cov[(0, 1)],
                        cov[(1, 0)],
                        cov[(1, 1)]
                    ),
                }
                .in_view(&v.name));
            }
            if c.xyz.norm() > MAX_RIG_COORDINATE_MM {
                return Err(CalibError::OutOfRange {
                    view: v.name.clone(),
                    index: i,
                    x: c.xyz.x,
                    y: c.xyz.y,
                    z: c.xyz.z,
                    limit_mm: MAX_RIG_COORDINATE_MM,
                });
            }
        }
        let mut order: Vec<usize> = (0..v.points.len()).collect();
        let key = |i: usize| {
            let p = v.points[i].xyz;
            (p.x, p.y, p.z)
        };
        order.sort_by(|&a, &b| {
            let (ka, kb) = (key(a), key(b));
            ka.0.total_cmp(&kb.0)
                .then(ka.1.total_cmp(&kb.1))
                .then(ka.2.total_cmp(&kb.2))
                .then(a.cmp(&b))
        });
        for w in order.windows(2) {
            if key(w[0]) == key(w[1]) {
                return Err(CalibError::DuplicatePoint {
                    view: v.name.clone(),
                    index: w[1],
                    first: w[0],
                });
            }
        }
    }
    Ok(())
}

/// Check that every image point lies inside a `width×height` image, whose pixels cover
/// `[−0.5, width − 0.5) × [−0.5, height − 0.5)` (pixel-centre convention).
pub fn validate_image_points(views: &[View], image_size: [u32; 2]) -> Result<(), CalibError> {
    let [w, h] = image_size;
    let inside = |x: f64, n: u32| x >= -0.5 && x <= f64::from(n) - 0.5;
    for v in views {
        for (i, c) in v.points.iter().enumerate() {
            if !(inside(c.uv.x, w) && inside(c.uv.y, h)) {
                return Err(CalibError::PointOutsideImage {
                    view: v.name.clone(),
                    index: i,
                    u: c.uv.x,
                    v: c.uv.y,
                    width: w,
                    height: h,
                });
            }
        }
    }
    Ok(())
}
