//! # cubecal — camera calibration station
//!
//! cubecal points a camera at a calibration rig (checkerboards on orthogonal faces of a cube, an inside
//! corner, or a flat board), finds the corners, solves the camera's intrinsics, extrinsics and lens
//! distortion, judges the result and writes a profile for that exact camera.
//!
//! ## Conventions (stated once, used everywhere)
//! - **Pixels**: integer pixel coordinates are pixel *centres*, as in OpenCV. The top-left pixel covers
//!   `[-0.5, 0.5) × [-0.5, 0.5)`; `u` grows to the right (column), `v` grows down (row).
//! - **Camera frame**: x right, y down, z forward (along the optical axis). A point is in front of the
//!   camera when `z > 0`.
//! - **Units**: rig and 3D coordinates in millimetres; pixels for image quantities; angles in radians
//!   inside the maths and degrees at user-facing boundaries (turntable, CLI), with the unit in the name.
//! - **Transforms** are named `b_from_a`: `cam_from_rig` maps a rig point into the camera frame,
//!   `X_cam = R · X_rig + t`. This is OpenCV's `rvec/tvec` and the seed's `[R | t]`.
//! - **Projection**: `u = fx·x'' + skew·y'' + cx`, `v = fy·y'' + cy`, where `(x'', y'')` are the
//!   distorted normalised coordinates of the Brown–Conrady model in OpenCV's coefficient order
//!   `(k1, k2, p1, p2, k3, k4, k5, k6)`. A profile therefore means the same thing in OpenCV.
//!
//! ## Modules
//! In layers: each imports only modules above it in this list, so the imports form no circle
//! ([`exit`] is used by all). The station stores profiles but renders nothing; the report reads runs
//! and profiles and never calls the station.
//! - [`camera`]: camera model — K, distortion models, project/unproject.
//! - [`rig`]: rig descriptions (faces, grids, square size, 3D layout) loaded from TOML.
//! - [`calib`]: solvers — normalized DLT, RQ, homographies, Zhang, one Levenberg–Marquardt with
//!   uncertainty, rig refinement; the correspondence file format read by `cubecal solve`.
//! - [`render`]: the exact synthetic renderer (ground truth for every test) and exact synthetic
//!   correspondences; not a capture device.
//! - [`detect`]: corners in a grayscale frame → checkerboard grids → labelled correspondences.
//! - [`turntable`]: the `Turntable` trait, serial drivers and simulators.
//! - [`capture`]: the `FrameSource` trait; V4L2, replay of recorded sessions, photos, synthetic
//!   cameras (which call [`render`]).
//! - [`run`]: the data of a run — verdict and checks, `result.json`, the run directory's layout —
//!   written by the station, read by the profile store, the report and the front ends.
//! - [`profile`]: per-device profiles — the crash-safe versioned store and the OpenCV/ROS/mrcal exports.
//! - [`station`]: the run — set-up, plan, move, capture, detect, solve, judge, write; it emits events
//!   and results and calls none of their renderers.
//! - [`report`]: self-contained HTML reports with plots (and the same plots as PNG) of station runs
//!   and of stored profiles with their history: a renderer of run data, like the CLI and the service.
//! - [`live`]: the operator's screen — a web page served by the station's process that renders the
//!   station's events live (frame with detections, coverage, σ, prompts, verdict, report): a renderer
//!   of the event stream, like the CLI and the service, which the station never calls.
//! - [`exit`]: the process exit codes (an API).

pub mod calib;
pub mod camera;
pub mod capture;
pub mod detect;
pub mod exit;
pub mod live;
pub mod profile;
pub mod render;
pub mod report;
pub mod rig;
pub mod run;
pub mod station;
pub mod turntable;
