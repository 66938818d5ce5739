//! The station: plan poses, move the turntable, capture, detect, judge coverage, solve, give a verdict
//! and write a profile — `cubecal calibrate`.
//!
//! ## A run
//! 1. [`hardware::open`] opens the camera (V4L2, a replayed session, photos, or the synthetic camera in
//!    front of the turntable) and the turntable (serial GRBL/Zaber, their simulators on a pty, a
//!    manual operator, or none).
//! 2. Per pose ([`run`]): move and wait until settled, drop the frames queued before the move, grab
//!    `frames_per_pose` frames, check that consecutive frames agree (motion), detect, check the edges'
//!    blur, accept the view or reject it with a reason, update the coverage grid. Every frame goes into
//!    the run's recorded session (`RUN_DIR/session`), whose manifest records the station config and
//!    rig, so `--replay RUN_DIR/session` re-runs the same data bit for bit. Frames taken before the
//!    run (photos, a replayed session) are grabbed a few poses at a time and detected at once, one
//!    pose a core ([`FrameSource::recorded`](crate::capture::FrameSource::recorded)): the same views,
//!    session and events in the same order as one pose at a time.
//! 3. Solve (robust loss), with the last `plan.held_out` accepted views kept out; each held-out view's
//!    pose is then solved with the intrinsics fixed ([`crate::calib::pose`]) and its RMS compared with
//!    the fit's. k3 is fixed (and the verdict says so) when the data cannot tell it from zero (within 2σ) while one
//!    σ of it moves the image border by over a pixel ([`crate::calib::insignificant_at_border`]) —
//!    turntable sequences keep the rig near the image centre and determine high-order distortion poorly.
//! 4. [`judge`] turns the result into a [`Verdict`] of named checks with thresholds and hints.
//! 5. A passing run writes its profile; a failing one writes none. The run directory holds
//!    `session/`, `rig.toml`, `observations.json` (accepted views, with faces and held-out marks),
//!    `result.json` (the `--json` result), `report.html` (with its plots in `report_plots/`) and, on a
//!    pass, `profile.json`; with `output.store` set the profile is also committed to the per-device
//!    store ([`crate::profile::Store`]), and a run without a camera identity is refused up front.
//!
//! The library never prints: everything a person sees comes from [`Event`]s given to an
//! [`EventSink`]. A stop flag (set by the CLI's SIGINT/SIGTERM handler) is checked between steps: the
//! turntable is stopped, the session closed and marked incomplete, and no profile is written.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use serde::Serialize;

pub mod config;
pub mod coverage;
pub mod event;
pub mod hardware;
pub mod judge;
pub mod notify;
pub mod plan;
pub mod setup;
pub mod sharpness;

pub use crate::run::{Check, HeldOut, RunResult, Verdict, ViewRecord};
pub use config::StationConfig;
use event::Recorder;
pub use event::{Event, EventSink};

use crate::calib::observations::{RawObservations, RawPoint, RawView};
use crate::calib::report::CalibrationReport;
use crate::calib::{Correspondence, View};
use crate::capture::session::{RigRef, SessionError, SessionHeader, SessionWriter};
use crate::capture::{CaptureError, SourceInfo};
use crate::detect::CornerFinder;
use crate::rig::{Rig, RigError};
use crate::turntable::{Degrees, Turntable, TurntableError};
use coverage::Coverage;
use hardware::{Hardware, Poses};

/// Errors that end a run. Each keeps its cause; [`StationError::exit_code`] maps it to the documented
/// exit codes.
#[derive(Debug, thiserror::Error)]
pub enum StationError {
    #[error(transparent)]
    Config(#[from] config::ConfigError),
    #[error(transparent)]
    Rig(#[from] RigError),
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Turntable(#[from] TurntableError),
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error(transparent)]
    Synthetic(#[from] crate::render::SyntheticError),
    #[error("detector: {0}")]
    Detect(String),
    #[error("a manual turntable needs an operator to answer its prompts (run interactively)")]
    NoOperator,
    #[error(transparent)]
    Profile(#[from] crate::profile::ProfileError),
    #[error(
        "no camera identity to store the profile under: give --device-id NAME (camera.device_id) for synthetic and photo runs, or no --store"
    )]
    NoIdentity,
    #[error("run directory {path} already holds a run; choose another --out")]
    RunDirExists { path: PathBuf },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "interrupted at pose {pose} of {total}; the session in {session} is closed and marked incomplete, no profile was written"
    )]
    Interrupted {
        pose: usize,
        total: usize,
        session: PathBuf,
    },
}

impl StationError {
    pub fn exit_code(&self) -> u8 {
        use crate::exit;
        match self {
            StationError::Config(e) => e.exit_code(),
            StationError::Rig(e) => e.exit_code(),
            StationError::Capture(e) => e.exit_code(),
            StationError::Turntable(e) => e.exit_code(),
            StationError::Session(e) => e.exit_code(),
            StationError::Synthetic(e) => e.exit_code(),
            StationError::NoOperator => exit::USAGE,
            StationError::Detect(_) => exit::INTERNAL,
            StationError::RunDirExists { .. } => exit::BAD_INPUT,
            StationError::Profile(e) => e.exit_code(),
            StationError::NoIdentity => exit::USAGE,
            StationError::Write { .. } => exit::IO,
            StationError::Interrupted { .. } => exit::INTERRUPTED,
        }
    }
}

/// Longest a solve (or a front end's work after the run, such as its report) may take before the
/// watchdog pings stop for it.
pub const SOLVE_LIMIT: Duration = Duration::from_secs(600);

/// Inputs of a run besides the hardware.
#[derive(Debug)]
pub struct RunSpec<'a> {
    pub config: &'a StationConfig,
    pub rig: &'a Rig,
    /// The rig file's text (recorded in the session and copied into the run directory).
    pub rig_toml: &'a str,
    pub rig_path: Option<PathBuf>,
    pub run_dir: &'a Path,
}

/// The wall time of each stage of a run, logged at debug level (`RUST_LOG=cubecal::station=debug`)
/// as it ends: where a run's time goes, without a profiler.
#[derive(Debug)]
pub struct Laps(std::time::Instant);

impl Laps {
    pub fn start() -> Laps {
        Laps(std::time::Instant::now())
    }

    /// Log the time since the previous lap (or the start) as `stage`'s.
    pub fn lap(&mut self, stage: &'static str) {
        let now = std::time::Instant::now();
        tracing::debug!(
            stage,
            ms = (now - self.0).as_secs_f64() * 1e3,
            "station stage"
        );
        self.0 = now;
    }
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), StationError> {
    crate::rig::svg::write_atomic(path, bytes).map_err(|source| StationError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), StationError> {
    write_file(path, &json_bytes(path, value)?)
}

/// `value` as the pretty JSON of the file `path`.
fn json_bytes<T: Serialize>(path: &Path, value: &T) -> Result<Vec<u8>, StationError> {
    serde_json::to_vec_pretty(value).map_err(|e| StationError::Write {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    })
}

/// The session frames of one pose, and its view.
struct PoseData {
    record: ViewRecord,
    view: Option<(View, Vec<String>)>,
    /// The detection behind `view` and its frame, to fit its corners again once a lens is known.
    detection: Option<crate::detect::FrameDetection>,
    image: Option<crate::capture::GrayImage>,
    /// The pose's photo could not be used (missing, empty, not an image, another size).
    unusable: bool,
    /// The frame at thumbnail size (with the detection of a rejected view), for the run's report.
    preview: Option<crate::run::preview::FramePreview>,
}

/// Run a station: see the module docs. Returns the result (with its verdict) or the error that ended
/// the run; in both cases the run directory holds what was done.
pub fn run(
    spec: &RunSpec<'_>,
    mut hw: Hardware,
    sink: &mut dyn EventSink,
    stop: &AtomicBool,
) -> Result<RunResult, StationError> {
    let cfg = spec.config;
    let run_dir = spec.run_dir;
    let mut laps = Laps::start();
    if run_dir.join(crate::run::RESULT).exists()
        || run_dir
            .join(crate::run::SESSION)
            .join(crate::capture::session::MANIFEST)
            .exists()
    {
        return Err(StationError::RunDirExists {
            path: run_dir.to_path_buf(),
        });
    }
    if cfg.output.store.is_some() && hw.identity.is_none() {
        return Err(StationError::NoIdentity);
    }
    std::fs::create_dir_all(run_dir).map_err(|source| StationError::Write {
        path: run_dir.to_path_buf(),
        source,
    })?;
    let mut info = hw.source.describe();
    if let Some(id) = &hw.identity {
        info.identity = id.clone();
    }
    let session_dir = run_dir.join(crate::run::SESSION);
    let header = SessionHeader {
        source: info.clone(),
        device: hw.device.clone(),
        capture: hw.capture,
        controls: hw.controls.clone(),
        rig: Some(RigRef {
            path: spec.rig_path.clone(),
            name: Some(spec.rig.name.clone()),
        }),
        config: serde_json::json!({
            "station": cfg,
            "rig_toml": spec.rig_toml,
        }),
    };
    let mut session = SessionWriter::create_background(&session_dir, header)?;
    sink.event(&Event::Opened {
        source: info.name.clone(),
        width: info.width,
        height: info.height,
        turntable: hw.turntable_name.clone(),
    });
    laps.lap("open the session");
    // rig.toml is written (fsync included) beside the capture; a failure ends the run like one of
    // the capture's.
    let mut outcome = std::thread::scope(|scope| {
        let rig =
            scope.spawn(|| write_file(&run_dir.join(crate::run::RIG), spec.rig_toml.as_bytes()));
        let poses = capture_poses(spec, &mut hw, &mut session, sink, stop);
        let written = finish_write(&mut Some(rig));
        poses.and_then(|poses| written.map(|()| poses))
    });
    laps.lap("capture and detect");
    // A signal can also cut a wait short (EINTR on the serial port or the camera): the run was
    // interrupted, whatever the interrupted call reported.
    if stop.load(Ordering::SeqCst)
        && let Err(e) = &outcome
        && !matches!(e, StationError::Interrupted { .. })
    {
        tracing::info!(error = %e, "stopped by a signal");
        let fpp = spec.config.camera.frames_per_pose.max(1) as usize;
        let total = hw.poses.len();
        outcome = Err(StationError::Interrupted {
            pose: session.frame_count() / fpp,
            total,
            session: session_dir.clone(),
        });
    }
    // Whatever happened, close the session: complete, or marked with what ended it (the manifest's
    // top-level `complete` and `ended_by`).
    let mut ended_by = None;
    if let Err(e) = &outcome {
        tracing::warn!(error = %e, "run ended early; stopping the turntable");
        if let Err(te) = hw.turntable.stop() {
            tracing::warn!(error = %te, "could not stop the turntable");
        }
        ended_by = Some(e.to_string());
    }
    session.set_outcome(outcome.is_ok(), ended_by);
    let finished = session.finish();
    laps.lap("close the session");
    let poses = outcome?;
    finished?;
    // Photos of which not one could be used: bad input, as for `cubecal detect`.
    if !poses.is_empty() && poses.iter().all(|p| p.unusable) {
        let names: Vec<String> = poses.iter().map(|p| p.record.name.clone()).collect();
        let first = (poses.first())
            .and_then(|p| p.record.reason.clone())
            .unwrap_or_default();
        return Err(StationError::Capture(CaptureError::Image {
            path: info.name.clone(),
            reason: crate::capture::images::unusable(&names, &first),
        }));
    }

    let mut poses = poses;
    let previews: Vec<_> = poses.iter_mut().filter_map(|p| p.preview.take()).collect();
    let result = solve_and_judge(spec, &info, poses, sink, &mut laps);
    let mut result = result?;
    result.previews = previews;
    // Files: observations and result; a passing run writes its profile.
    // A passing verdict always comes with a calibration (the checks run only after a solve).
    if let (true, Some(calibration)) = (result.verdict.pass, result.calibration.clone()) {
        let path = write_profile(spec, &hw, &mut result, calibration, sink)?;
        result.profile = Some(path);
        laps.lap("profile");
    }
    write_json(&run_dir.join(crate::run::RESULT), &result)?;
    laps.lap("result.json");
    sink.event(&Event::Verdict {
        verdict: result.verdict.clone(),
    });
    Ok(result)
}

/// The most poses whose frames are detected at once (one a core, on a machine with more).
const MAX_DETECT_AT_ONCE: usize = 4;

/// One pose's frames, grabbed and recorded in the session, before detection.
struct Acquired {
    frames: Vec<crate::capture::Frame>,
    name: String,
    grabbed: Grabbed,
    angle: Option<f64>,
    planned: Option<f64>,
    tilt: Option<f64>,
    /// The planner's choice behind a planned pose, and how many prompts it has had (manual stages).
    choice: Option<(plan::Choice, usize)>,
    /// The events of its grab, held back while the poses grabbed with it are detected (none when
    /// poses are taken one at a time: their events go out as they happen).
    events: Vec<Event>,
}

/// Where a pose's events go while it is grabbed: to the run's sink, or held back with the pose.
enum PoseEvents<'s> {
    Live(&'s mut dyn EventSink),
    /// Held, and whether the sink they are for wants frames.
    Held(Recorder, bool),
}

impl EventSink for PoseEvents<'_> {
    fn event(&mut self, event: &Event) {
        match self {
            PoseEvents::Live(sink) => sink.event(event),
            PoseEvents::Held(held, _) => held.event(event),
        }
    }

    fn wants_frames(&self) -> bool {
        match self {
            PoseEvents::Live(sink) => sink.wants_frames(),
            PoseEvents::Held(_, frames) => *frames,
        }
    }
}

impl PoseEvents<'_> {
    fn held(self) -> Vec<Event> {
        match self {
            PoseEvents::Live(_) => Vec::new(),
            PoseEvents::Held(held, _) => held.events,
        }
    }
}

fn capture_poses(
    spec: &RunSpec<'_>,
    hw: &mut Hardware,
    session: &mut SessionWriter,
    sink: &mut dyn EventSink,
    stop: &AtomicBool,
) -> Result<Vec<PoseData>, StationError> {
    let cfg = spec.config;
    let info = hw.source.describe();
    let total = hw.poses.len();
    let mut coverage = Coverage::new(info.width, info.height, cfg.qa.coverage_grid);
    let mut out = Vec::with_capacity(total);
    let moving = matches!(hw.poses, Poses::Angles(_) | Poses::Stage { .. });
    let mut planning = match &hw.poses {
        Poses::Stage { sweep: None, .. } => Some(plan::Planning::new(spec, &info, &*hw.turntable)),
        _ => None,
    };
    // Frames taken before the run (photos, a replayed session) are the same whenever they are
    // grabbed: a few poses are grabbed and recorded, then detected at once, one a core, and their
    // events go out in the order of a pose-by-pose run. A moving turntable, the planner and an early
    // stop decide each pose on the ones before it, and a live camera's frames depend on when they
    // are grabbed: those runs take one pose at a time.
    let at_once = if hw.source.recorded()
        && !moving
        && planning.is_none()
        && !cfg.plan.stop_when_sufficient
    {
        std::thread::available_parallelism()
            .map_or(1, std::num::NonZero::get)
            .clamp(1, MAX_DETECT_AT_ONCE)
    } else {
        1
    };
    let mut finders = (0..at_once)
        .map(|_| CornerFinder::new())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| StationError::Detect(e.to_string()))?;
    for f in &mut finders {
        f.set_second_look(cfg.detect.second_look);
    }
    // Homing gets twice the move timeout (hardware::open_turntable); past that, let the watchdog see.
    let move_limit =
        Duration::from_secs(cfg.turntable.move_timeout_s) * 2 + Duration::from_secs(10);
    if moving {
        sink.event(&Event::Homing {
            instruction: hw
                .turntable
                .is_manual()
                .then(|| crate::turntable::manual::HOME_INSTRUCTION.to_string()),
        });
        let home = notify::alive_during(sink, move_limit, || hw.turntable.home())?;
        if let Some(cell) = &hw.angle {
            cell.set(home.0);
        }
        if let Some(cell) = &hw.tilt {
            cell.set(0.0);
        }
    }
    let mut index = 0;
    let mut planned_out = false;
    // A planned pose the operator of a manual stage did not reach: asked for again, with why.
    let mut again: Option<Again> = None;
    while index < total && !planned_out {
        let mut batch = Vec::with_capacity(at_once);
        // An error that ends the run once the poses grabbed before it are accounted for, with the
        // events of the grab that failed.
        let mut ended = None;
        while batch.len() < at_once && index < total {
            let mut events = if at_once == 1 {
                PoseEvents::Live(&mut *sink)
            } else {
                PoseEvents::Held(Recorder::default(), sink.wants_frames())
            };
            let acquired = acquire(
                spec,
                hw,
                session,
                &mut events,
                stop,
                index,
                &mut planning,
                &coverage,
                move_limit,
                again.take(),
            );
            let events = events.held();
            match acquired {
                Ok(Some(mut a)) => {
                    a.events = events;
                    batch.push(a);
                    index += 1;
                }
                Ok(None) => {
                    planned_out = true;
                    break;
                }
                Err(e) => {
                    ended = Some((e, events));
                    break;
                }
            }
        }
        let examined = examine_batch(spec, &mut finders, &mut batch);
        for (a, pose) in batch.iter_mut().zip(examined) {
            let index = out.len();
            for e in a.events.drain(..) {
                sink.event(&e);
            }
            let mut pose = pose?;
            // A hand-placed pose is judged against its prompt: after a view that is not still, not
            // usable or not where the prompt puts the rig, the pose is asked for again. A usable
            // view elsewhere still calibrates (its corners are as good), but its stage pose is not
            // the prompted one, so the planner does not learn from it.
            let mut misplaced = false;
            if hw.turntable.is_manual()
                && let (Some(p), Some((choice, prompts))) = (planning.as_ref(), a.choice.take())
            {
                let unmet = match &pose.view {
                    Some((view, _)) => p
                        .misplaced(choice.pose, view, &coverage)
                        .map(|m| m.words(matches!(hw.poses, Poses::Stage { .. }))),
                    None => pose.record.reason.clone(),
                };
                if let Some(why) = unmet {
                    if prompts < MAX_PROMPTS {
                        tracing::info!(%why, prompts, "pose not as prompted; asking again");
                        again = Some(Again {
                            choice,
                            prompts: prompts + 1,
                            why: why.clone(),
                        });
                    }
                    if pose.view.is_some() {
                        misplaced = true;
                        pose.record.reason = Some(format!(
                            "not as prompted (kept for the calibration, not for the plan): {why}"
                        ));
                    }
                }
            }
            if sink.wants_frames() {
                let last = a.frames.last().map(|f| f.sequence).unwrap_or_default();
                sink.event(&detected_event(index, last, &info, &pose, spec.rig));
            }
            match &pose.view {
                Some((view, _)) => {
                    if let (Some(p), Some(r), Some(t), false) =
                        (planning.as_mut(), a.planned, a.tilt, misplaced)
                    {
                        p.accepted(
                            plan::StagePose {
                                rotation_deg: r,
                                tilt_deg: t,
                            },
                            view,
                        );
                    }
                    for p in &view.points {
                        coverage.add(&p.uv);
                    }
                    sink.event(&Event::ViewAccepted {
                        index,
                        name: pose.record.name.clone(),
                        faces: pose.record.faces,
                        corners: pose.record.corners,
                    });
                }
                None => sink.event(&Event::ViewRejected {
                    index,
                    name: pose.record.name.clone(),
                    reason: pose.record.reason.clone().unwrap_or_default(),
                }),
            }
            out.push(pose);
            sink.event(&Event::Coverage {
                views: out.iter().filter(|p| p.view.is_some()).count(),
                fraction: coverage.fraction(),
                cells_covered: coverage.covered(),
                cells_total: coverage.total(),
                grid: [coverage.cols, coverage.rows],
                counts: coverage.counts.clone(),
            });
            if cfg.plan.stop_when_sufficient
                && sufficient(spec, &out, &coverage, info.width, info.height)
            {
                tracing::info!(
                    poses = out.len(),
                    "data sufficient; stopping the plan early"
                );
                return Ok(out);
            }
        }
        if let Some((e, events)) = ended {
            for event in &events {
                sink.event(event);
            }
            return Err(e);
        }
    }
    Ok(out)
}

/// How many times a manual stage's operator is prompted for one planned pose before the plan moves on.
const MAX_PROMPTS: usize = 3;

/// A planned pose to prompt for again: the operator's view did not satisfy the last prompt.
struct Again {
    choice: plan::Choice,
    /// Prompts for it so far.
    prompts: usize,
    /// What was wrong, in words.
    why: String,
}

/// Plan, move to and grab pose `index`, recording its frames in the session; `None` when the planner
/// has no pose left that shows the rig. `again` is a planned pose whose last prompt was not met.
#[allow(clippy::too_many_arguments)]
fn acquire(
    spec: &RunSpec<'_>,
    hw: &mut Hardware,
    session: &mut SessionWriter,
    sink: &mut dyn EventSink,
    stop: &AtomicBool,
    index: usize,
    planning: &mut Option<plan::Planning>,
    coverage: &Coverage,
    move_limit: Duration,
    again: Option<Again>,
) -> Result<Option<Acquired>, StationError> {
    let cfg = spec.config;
    let fpp = cfg.camera.frames_per_pose.max(1) as usize;
    let timeout = Duration::from_millis(cfg.camera.grab_timeout_ms);
    let total = hw.poses.len();
    let moving = matches!(hw.poses, Poses::Angles(_) | Poses::Stage { .. });
    if stop.load(Ordering::SeqCst) {
        return Err(StationError::Interrupted {
            pose: index,
            total,
            session: spec.run_dir.join(crate::run::SESSION),
        });
    }
    let manual = hw.turntable.is_manual();
    let has_tilt = matches!(hw.poses, Poses::Stage { .. });
    let mut chosen = None;
    let not_met = again.as_ref().map(|a| a.why.clone());
    let (planned, tilt, target) = match &hw.poses {
        Poses::Angles(a) => (Some(a[index]), None, None),
        Poses::Stage { sweep: Some(s), .. } => {
            (Some(s[index].rotation_deg), Some(s[index].tilt_deg), None)
        }
        Poses::Stage { sweep: None, .. } => {
            let (choice, prompts) = match again {
                Some(a) => (Some(a.choice), a.prompts),
                None => (planning.as_mut().and_then(|p| p.choose()), 1),
            };
            let Some(choice) = choice else {
                tracing::info!(
                    poses = index,
                    "no candidate pose left that shows the rig; ending the plan"
                );
                return Ok(None);
            };
            sink.event(&Event::PoseChosen {
                index,
                rotation_deg: choice.pose.rotation_deg,
                tilt_deg: choice.pose.tilt_deg,
                corners: choice.corners,
                predicted: choice.sigma.clone(),
            });
            // Where the predicted corners land: their mean, and the empty cells they fill.
            let n = choice.points.len().max(1) as f64;
            let mean = choice.points.iter().sum::<nalgebra::Vector2<f64>>() / n;
            let target = (
                coverage.region_of(&mean),
                coverage.newly_covered(&choice.points),
            );
            let pose = (
                Some(choice.pose.rotation_deg),
                Some(choice.pose.tilt_deg),
                Some(target),
            );
            chosen = Some((choice, prompts));
            pose
        }
        Poses::Frames { angles } => (angles[index], None, None),
    };
    // A person moving the stage gets the whole pose in words (never empty for a manual pose).
    // Asked again, it first says what was wrong with the last attempt.
    let instruction = (manual && moving).then(|| {
        let words = plan::instruction(
            plan::StagePose {
                rotation_deg: planned.unwrap_or(0.0),
                tilt_deg: tilt.unwrap_or(0.0),
            },
            has_tilt,
            target,
        );
        match &not_met {
            Some(why) => format!("not there yet, {why}; {words}"),
            None => words,
        }
    });
    sink.event(&Event::PosePlanned {
        index,
        total,
        angle_deg: planned,
        instruction: instruction.clone(),
    });
    let mut angle = planned;
    if moving && let Some(rotation) = planned {
        let rotation = Degrees::checked(rotation)?;
        let tilt_target = tilt.map(Degrees::checked).transpose()?;
        let settled = match &instruction {
            Some(text) => notify::alive_during(sink, move_limit, || {
                hw.turntable.by_hand(text, rotation, tilt_target)
            })?,
            None => {
                let settled_tilt = match tilt_target {
                    Some(t) => {
                        sink.event(&Event::Tilting {
                            index,
                            tilt_deg: t.0,
                        });
                        Some(notify::alive_during(sink, move_limit, || {
                            hw.turntable.tilt_to(t)
                        })?)
                    }
                    None => None,
                };
                sink.event(&Event::Moving {
                    index,
                    angle_deg: rotation.0,
                });
                let r = notify::alive_during(sink, move_limit, || hw.turntable.move_to(rotation))?;
                (r, settled_tilt)
            }
        };
        if let (Some(cell), Some(t)) = (&hw.tilt, settled.1) {
            cell.set(t.0);
        }
        if let Some(cell) = &hw.angle {
            cell.set(settled.0.0);
        }
        angle = Some(settled.0.0);
        sink.event(&Event::Settled {
            index,
            angle_deg: settled.0.0,
        });
        if cfg.turntable.settle_ms > 0 {
            std::thread::sleep(Duration::from_millis(cfg.turntable.settle_ms));
        }
    }
    sink.event(&Event::Alive);
    let flushed = if moving { hw.source.flush()? } else { 0 };
    let mut frames = Vec::with_capacity(fpp);
    let mut grabbed = Grabbed::default();
    for _ in 0..fpp {
        let before = frames.len();
        grabbed.grab(hw.source.as_mut(), timeout, angle, session, &mut frames)?;
        if sink.wants_frames()
            && frames.len() > before
            && let Some(f) = frames.last()
        {
            sink.event(&Event::Frame {
                index,
                sequence: f.sequence,
                grabbed_unix_ms: grabbed.grabbed_unix_ms,
                image: event::FrameImage(std::sync::Arc::new(f.image.clone())),
            });
        }
        sink.event(&Event::Alive);
    }
    let name = (grabbed.source.take()).unwrap_or_else(|| format!("pose{index:02}"));
    let last = frames.last().map(|f| f.sequence).unwrap_or_default();
    sink.event(&Event::FrameGrabbed {
        index,
        sequence: last,
        flushed,
    });
    Ok(Some(Acquired {
        frames,
        name,
        grabbed,
        angle,
        planned,
        tilt,
        choice: chosen,
        events: Vec::new(),
    }))
}

/// Detect and check the frames of `batch` ([`examine`]), each pose with a finder of its own and
/// all but the first on threads of their own; the results in the order of `batch`.
fn examine_batch(
    spec: &RunSpec<'_>,
    finders: &mut [CornerFinder],
    batch: &mut [Acquired],
) -> Vec<Result<PoseData, StationError>> {
    let one = |finder: &mut CornerFinder, a: &mut Acquired| {
        let name = std::mem::take(&mut a.name);
        let grabbed = std::mem::take(&mut a.grabbed);
        let mut pose = examine(spec, finder, &a.frames, name, grabbed, a.angle)?;
        pose.record.tilt_deg = a.tilt;
        Ok(pose)
    };
    let one = &one;
    std::thread::scope(|scope| {
        let mut jobs = batch.iter_mut().zip(finders.iter_mut());
        let first = jobs.next();
        let others: Vec<_> = jobs
            .map(|(a, finder)| scope.spawn(move || one(finder, a)))
            .collect();
        let mut out: Vec<_> = first
            .map(|(a, finder)| one(finder, a))
            .into_iter()
            .collect();
        out.extend(others.into_iter().map(|h| match h.join() {
            Ok(r) => r,
            Err(panic) => std::panic::resume_unwind(panic),
        }));
        out
    })
}

/// The corners of a pose's last frame for [`Event::Detected`]: the accepted view's, else those the
/// detector labelled in a view it rejected (none when it rejected the view before detecting).
fn detected_event(
    index: usize,
    sequence: u64,
    info: &SourceInfo,
    pose: &PoseData,
    rig: &Rig,
) -> Event {
    let mut faces: Vec<event::DetectedFace> = Vec::new();
    let mut push = |face: &str, uv: &nalgebra::Vector2<f64>| {
        let corner = [uv.x as f32, uv.y as f32];
        match faces.iter_mut().find(|f| f.face == face) {
            Some(f) => f.corners.push(corner),
            None => faces.push(event::DetectedFace {
                face: face.to_string(),
                corners: vec![corner],
            }),
        }
    };
    if let Some((view, names)) = &pose.view {
        for (p, name) in view.points.iter().zip(names) {
            push(name, &p.uv);
        }
    } else if let Some(det) = pose.preview.as_ref().and_then(|p| p.detection.as_ref()) {
        for f in &det.faces {
            let name = rig.faces.get(f.face).map_or("?", |face| face.name.as_str());
            for c in &f.corners {
                push(name, &c.uv);
            }
        }
    }
    Event::Detected {
        index,
        sequence,
        width: info.width,
        height: info.height,
        faces,
    }
}

/// What the grabs of one pose left besides their frames: the session file of the last, the name of
/// the user's file behind it (photo runs), why a photo could not be used, and when the last grab
/// returned (wall clock, ms since the Unix epoch; for the live page's latency).
#[derive(Debug, Default)]
struct Grabbed {
    frame_file: Option<String>,
    source: Option<String>,
    unusable: Option<String>,
    grabbed_unix_ms: f64,
}

impl Grabbed {
    /// Grab one frame into `frames` and record it in the session: a user's file as it is, any
    /// other frame encoded. A photo that cannot be used ([`CaptureError::Image`]) is recorded with
    /// its reason and leaves the run going; any other grab error ends it.
    fn grab(
        &mut self,
        source: &mut dyn crate::capture::FrameSource,
        timeout: Duration,
        angle: Option<f64>,
        session: &mut SessionWriter,
        frames: &mut Vec<crate::capture::Frame>,
    ) -> Result<(), StationError> {
        let grabbed = source.grab(timeout);
        self.grabbed_unix_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64() * 1e3);
        let file = source.take_source_file();
        let recorded = match (file, &grabbed) {
            (Some(file), Err(CaptureError::Image { .. }) | Ok(_)) => {
                self.source = Some(file.name.clone());
                let (sequence, timestamp) = grabbed
                    .as_ref()
                    .map_or((session.frame_count() as u64, Duration::ZERO), |f| {
                        (f.sequence, f.timestamp)
                    });
                session.add_source_file(file, sequence, timestamp, angle)?
            }
            (None, Ok(f)) => session.add_frame(f, angle)?,
            (_, Err(_)) => return grabbed.map(|_| ()).map_err(StationError::from),
        };
        self.frame_file = (!recorded.is_empty()).then_some(recorded);
        match grabbed {
            Ok(f) => frames.push(f),
            Err(CaptureError::Image { reason, .. }) => self.unusable = Some(reason),
            Err(e) => return Err(e.into()),
        }
        Ok(())
    }
}

/// Detect and check one pose's frames ([`examine_frames`]) and reduce the last to thumbnail size,
/// with what the detector found when the view is rejected (an accepted view's observations say it).
fn examine(
    spec: &RunSpec<'_>,
    finder: &mut CornerFinder,
    frames: &[crate::capture::Frame],
    name: String,
    grabbed: Grabbed,
    angle: Option<f64>,
) -> Result<PoseData, StationError> {
    let (mut pose, rejected_detection) =
        examine_frames(spec, finder, frames, name, grabbed, angle)?;
    if let (Some(file), Some(last)) = (&pose.record.frame, frames.last())
        && !pose.unusable
    {
        pose.preview = Some(crate::run::preview::FramePreview::of(
            file.clone(),
            &last.image,
            rejected_detection,
        ));
    }
    Ok(pose)
}

/// Detect and check one pose's frames; a view rejected after detection comes with its detection.
fn examine_frames(
    spec: &RunSpec<'_>,
    finder: &mut CornerFinder,
    frames: &[crate::capture::Frame],
    name: String,
    grabbed: Grabbed,
    angle: Option<f64>,
) -> Result<(PoseData, Option<crate::detect::FrameDetection>), StationError> {
    let qa = &spec.config.qa;
    let mut record = ViewRecord {
        name,
        frame: grabbed.frame_file,
        angle_deg: angle,
        tilt_deg: None,
        accepted: false,
        reason: None,
        faces: 0,
        corners: 0,
        blur_px: None,
        motion: None,
    };
    let reject = |mut record: ViewRecord, reason: String| PoseData {
        record: {
            record.reason = Some(reason);
            record
        },
        view: None,
        detection: None,
        image: None,
        unusable: false,
        preview: None,
    };
    if let Some(reason) = grabbed.unusable {
        let mut pose = reject(record, reason);
        pose.unusable = true;
        return Ok((pose, None));
    }
    let Some(last) = frames.last() else {
        return Ok((reject(record, "no frame".into()), None));
    };
    if frames.len() >= 2 {
        let m = sharpness::motion_fraction(&frames[frames.len() - 2].image, &last.image);
        record.motion = Some(m);
        if m > qa.max_motion {
            return Ok((
                reject(
                    record,
                    format!(
                        "the image changed between consecutive frames ({:.1} % of the image): the rig or camera was still moving; increase turntable.settle_ms or fix the camera mount",
                        100.0 * m
                    ),
                ),
                None,
            ));
        }
    }
    let det = match crate::detect::detect(finder, &last.image, spec.rig) {
        Ok(d) => d,
        Err(e) => return Ok((reject(record, format!("detection failed: {e}")), None)),
    };
    let rejected =
        |record: ViewRecord, reason: String| Ok((reject(record, reason), Some(det.clone())));
    record.faces = det.faces.len();
    record.corners = det.faces.iter().map(|f| f.corners.len()).sum();
    if det.faces.is_empty() {
        if let Some(b) = sharpness::frame_blur_px(&last.image)
            && b > qa.max_blur_px
        {
            record.blur_px = Some(b);
            return rejected(
                record,
                format!(
                    "image blurred: edges spread over σ ≈ {b:.1} px (at most {:.1}) and no rig face could be found; focus the camera on the rig",
                    qa.max_blur_px
                ),
            );
        }
        let mut why: Vec<String> = det.rejected.iter().map(|r| r.reason.clone()).collect();
        why.dedup();
        why.truncate(3);
        return rejected(
            record,
            format!(
                "no rig face labelled ({}); check that the rig is in view and that the rig file matches the printed rig",
                if why.is_empty() {
                    "nothing found".to_string()
                } else {
                    why.join("; ")
                }
            ),
        );
    }
    if record.corners < qa.min_corners {
        return rejected(
            record.clone(),
            format!(
                "only {} corners labelled (at least {} needed)",
                record.corners, qa.min_corners
            ),
        );
    }
    let blur = sharpness::blur_px(&last.image, &det.faces);
    record.blur_px = blur;
    if let Some(b) = blur
        && b > qa.max_blur_px
    {
        return rejected(
            record,
            format!(
                "image blurred: edges spread over σ ≈ {b:.1} px (at most {:.1}); focus the camera on the rig",
                qa.max_blur_px
            ),
        );
    }
    let (points, faces) = view_points(spec.rig, &det);
    record.accepted = true;
    // A remark on an accepted view: its labels may be shifted or turned within the board's plane.
    record.reason = det
        .faces
        .iter()
        .find_map(|f| f.ambiguous_pose.as_ref())
        .map(|why| {
            format!(
                "pose not trusted, intrinsics used: {why} (labels certain up to a motion that moves only this view's pose, never the intrinsics)"
            )
        });
    Ok((
        PoseData {
            view: Some((
                View {
                    name: record.name.clone(),
                    points,
                },
                faces,
            )),
            record,
            detection: Some(det),
            image: Some(last.image.clone()),
            unusable: false,
            preview: None,
        },
        None,
    ))
}

/// A detection's labelled corners as a view's points, with each point's face name.
fn view_points(
    rig: &crate::rig::Rig,
    det: &crate::detect::FrameDetection,
) -> (Vec<Correspondence>, Vec<String>) {
    let mut points = Vec::new();
    let mut faces = Vec::new();
    for f in &det.faces {
        let face_name = rig
            .faces
            .get(f.face)
            .map(|x| x.name.clone())
            .unwrap_or_default();
        for c in &f.corners {
            points.push(Correspondence {
                xyz: c.xyz,
                uv: c.uv,
                cov: c.covariance(),
            });
            faces.push(face_name.clone());
        }
    }
    (points, faces)
}

/// Grids the views' frames could not label on their own, settled by the camera of the accepted views
/// (`detect::settle`): a preliminary solve of the views to fit, then each frame with a proven face
/// and rejected grids scores every labelling of those grids in its pose. Admitted grids join their
/// view; every decision, with its margin, is returned as a note.
fn settle_candidates(
    spec: &RunSpec<'_>,
    poses: &mut [PoseData],
    image_size: [u32; 2],
    n_fit: usize,
    sink: &mut dyn EventSink,
) -> Vec<String> {
    let has_candidates = poses.iter().any(|p| {
        p.view.is_some()
            && p.detection.as_ref().is_some_and(|d| {
                d.rejected
                    .iter()
                    .any(|r| r.corners.len() >= crate::detect::settle::MIN_CORNERS)
            })
    });
    if !has_candidates || spec.rig.faces.len() < 2 {
        return Vec::new();
    }
    let fit: Vec<View> = poses
        .iter()
        .filter_map(|p| p.view.as_ref().map(|v| v.0.clone()))
        .take(n_fit)
        .collect();
    let Ok(opts) = spec.config.solve_options("station config") else {
        return Vec::new();
    };
    // Watchdog pings continue through the solve (a slow station computer takes seconds).
    let Ok(cal) = notify::alive_during(sink, SOLVE_LIMIT, || {
        crate::calib::solve(&fit, image_size, &opts)
    }) else {
        return Vec::new();
    };
    let mut notes = Vec::new();
    for p in poses.iter_mut() {
        let (Some((view, faces)), Some(det)) = (p.view.as_mut(), p.detection.as_mut()) else {
            continue;
        };
        let decisions = crate::detect::settle::settle(spec.rig, &cal.camera, det, &view.name);
        if decisions.iter().any(|d| d.admitted.is_some()) {
            let (points, names) = view_points(spec.rig, det);
            p.record.corners = points.len();
            p.record.faces = det.faces.len();
            view.points = points;
            *faces = names;
        }
        notes.extend(
            decisions
                .into_iter()
                .map(|d| format!("{}: grid {}", view.name, d.text)),
        );
    }
    notes
}

/// Whether the accepted views already meet coverage and the σ targets (for `stop_when_sufficient`).
fn sufficient(spec: &RunSpec<'_>, poses: &[PoseData], coverage: &Coverage, w: u32, h: u32) -> bool {
    let cfg = spec.config;
    let views: Vec<View> = poses
        .iter()
        .filter_map(|p| p.view.as_ref().map(|v| v.0.clone()))
        .collect();
    if views.len() < cfg.qa.min_views + cfg.plan.held_out
        || coverage.fraction() < cfg.qa.min_coverage
    {
        return false;
    }
    let fit = &views[..views.len() - cfg.plan.held_out];
    let Ok(opts) = cfg.solve_options("station config") else {
        return false;
    };
    match solve_views(spec, fit, [w, h], &opts) {
        Ok((cal, _)) => {
            use crate::camera::idx;
            // k3 must be determined too when the solve would otherwise fix it
            let k3_ok = !cfg.solve.fix_undetermined_k3
                || crate::calib::insignificant_at_border(&cal, idx::K3).is_none();
            cal.std_dev[idx::FX] / cal.camera.fx() <= cfg.plan.target_sigma_fx_rel
                && cal.std_dev[idx::FY] / cal.camera.fy() <= cfg.plan.target_sigma_fx_rel
                && cal.std_dev[idx::CX] <= cfg.plan.target_sigma_cx_px
                && cal.std_dev[idx::CY] <= cfg.plan.target_sigma_cx_px
                && k3_ok
        }
        Err(_) => false,
    }
}

fn solve_and_judge(
    spec: &RunSpec<'_>,
    info: &SourceInfo,
    poses: Vec<PoseData>,
    sink: &mut dyn EventSink,
    laps: &mut Laps,
) -> Result<RunResult, StationError> {
    let cfg = spec.config;
    let image_size = [info.width, info.height];
    let mut poses = poses;
    // The last `held_out` views check the calibration (when enough views remain to fit); settling
    // candidates adds faces to views and never adds or drops a view, so the split holds throughout.
    let n_views = poses.iter().filter(|p| p.view.is_some()).count();
    let n_held = if n_views > cfg.plan.held_out + 1 {
        cfg.plan.held_out
    } else {
        0
    };
    let n_fit = n_views - n_held;
    let settled = settle_candidates(spec, &mut poses, image_size, n_fit, sink);
    laps.lap("settle candidates");
    let mut accepted: Vec<(View, Vec<String>, Option<String>)> = poses
        .iter()
        .filter_map(|p| {
            p.view
                .as_ref()
                .map(|(v, f)| (v.clone(), f.clone(), p.record.frame.clone()))
        })
        .collect();
    let mut fit: Vec<View> = accepted[..n_fit].iter().map(|a| a.0.clone()).collect();
    let mut held: Vec<View> = accepted[n_fit..].iter().map(|a| a.0.clone()).collect();
    // observations.json: the accepted views with faces, frames and held-out marks.
    let observations_path = spec.run_dir.join(crate::run::OBSERVATIONS);
    let observations_json = |accepted: &[(View, Vec<String>, Option<String>)]| {
        let raw = RawObservations {
            image_size,
            views: accepted
                .iter()
                .enumerate()
                .map(|(i, (v, faces, frame))| RawView {
                    name: Some(v.name.clone()),
                    points: v
                        .points
                        .iter()
                        .zip(faces)
                        .map(|(c, f)| RawPoint {
                            xyz: c.xyz.into(),
                            uv: c.uv.into(),
                            face: Some(f.clone()),
                            cov: c.cov.as_ref().map(crate::calib::observations::cov_to_array),
                        })
                        .collect(),
                    frame: frame.clone(),
                    held_out: i >= n_fit,
                })
                .collect(),
        };
        json_bytes(&observations_path, &raw)
    };
    // Written (fsync included) beside the solves, on a thread of its own; joined before the file is
    // written again and before the run goes on, so that its error still ends the run.
    let first = observations_json(&accepted)?;
    std::thread::scope(|scope| {
        let mut writing = Some(scope.spawn(|| write_file(&observations_path, &first)));
        laps.lap("observations.json");
        let views: Vec<ViewRecord> = poses.iter().map(|p| p.record.clone()).collect();
        let mut coverage = Coverage::new(info.width, info.height, cfg.qa.coverage_grid);
        for v in &fit {
            for p in &v.points {
                coverage.add(&p.uv);
            }
        }
        let mut notes = settled;
        let mut result = RunResult {
            verdict: Verdict::default(),
            calibration: None,
            held_out: Vec::new(),
            views,
            profile: None,
            profile_waits_for: None,
            run_dir: spec.run_dir.to_path_buf(),
            device: info.clone(),
            notes: Vec::new(),
            solve_error: None,
            previews: Vec::new(),
        };
        if fit.len() < 2 {
            result.verdict = judge::too_few_views(fit.len(), cfg, &result.views);
            finish_write(&mut writing)?;
            return Ok(result);
        }
        sink.event(&Event::Solving {
            views: fit.len(),
            points: fit.iter().map(|v| v.points.len()).sum(),
        });
        let mut opts = cfg.solve_options("station config")?;
        let candidates = cfg.model_candidates("station config")?;
        let (mut cal, mut rig_solve) = match notify::alive_during(sink, SOLVE_LIMIT, || {
            solve_choosing_model(spec, &fit, &held, image_size, &mut opts, &candidates)
        }) {
            Ok((c, note)) => {
                notes.extend(note);
                c
            }
            Err(e) => {
                result.solve_error = Some(e.to_string());
                result.verdict = judge::solve_failed(&e, fit.len(), cfg);
                finish_write(&mut writing)?;
                return Ok(result);
            }
        };
        laps.lap("solve");
        let mut fixed = configured_fixes(&opts, image_size);
        // The highest radial term: Brown–Conrady's k3, the fisheye's k4.
        let (top, top_name) = if opts.model == crate::camera::DistortionModel::Kb4 {
            (crate::camera::idx::K4, "k4")
        } else {
            (crate::camera::idx::K3, "k3")
        };
        if cfg.solve.fix_undetermined_k3
            && let Some(k3) = crate::calib::insignificant_at_border(&cal, top)
        {
            let (k3, k3_sd) = (k3.value, k3.std_dev);
            if top_name == "k4" {
                opts.fix.k4 = true;
            } else {
                opts.fix.k3 = true;
            }
            match notify::alive_during(sink, SOLVE_LIMIT, || {
                solve_views(spec, &fit, image_size, &opts)
            }) {
                Ok((c, r)) => {
                    let why = format!(
                        "these views do not determine it ({top_name} = {k3:.3} ± {k3_sd:.3}, within {}σ of 0, and 1σ moves the image border by {:.1} px); add poses with the rig near the image corners to estimate it",
                        crate::calib::SIGNIFICANCE_SIGMAS,
                        crate::calib::insignificant_at_border(&cal, top)
                            .map_or(0.0, |u| u.effect_px)
                    );
                    notes.push(format!("{top_name} fixed at 0: {why}"));
                    fixed.push(crate::run::FixedParameter {
                        name: top_name.into(),
                        value: 0.0,
                        reason: why,
                    });
                    (cal, rig_solve) = (c, r);
                }
                Err(e) => {
                    tracing::warn!(error = %e, "re-solve with {top_name} fixed failed; keeping it")
                }
            }
        }
        laps.lap("k3 check");
        // The corners fitted again in the undistorted coordinates of the solved lens (unbiased where
        // distortion bends the edges; issue 19), kept when the solve's residuals fall.
        let recorded: Vec<_> = (poses.iter())
            .filter_map(|p| {
                Some(crate::detect::undistorted::Recorded {
                    name: &p.view.as_ref()?.0.name,
                    frame: p.image.as_ref()?,
                    detection: p.detection.as_ref()?,
                })
            })
            .collect();
        let refitted = (recorded.len() == accepted.len())
            .then(|| {
                notify::alive_during(sink, SOLVE_LIMIT, || {
                    let views = crate::detect::undistorted::refit_recorded(&recorded, &cal.camera)?;
                    let c = solve_views(spec, &views[..n_fit], image_size, &opts).ok()?;
                    Some((views, c))
                })
            })
            .flatten();
        if let Some((views, (c, r))) = refitted
            && c.rms_px < cal.rms_px
        {
            tracing::info!(
                before = cal.rms_px,
                after = c.rms_px,
                "corners refitted with the lens"
            );
            (fit, held, cal) = (views[..n_fit].to_vec(), views[n_fit..].to_vec(), c);
            rig_solve = r;
            (accepted.iter_mut().zip(views)).for_each(|(a, v)| a.0 = v);
            let refitted = observations_json(&accepted)?;
            finish_write(&mut writing)?;
            let path = &observations_path;
            writing = Some(scope.spawn(move || write_file(path, &refitted)));
        }
        laps.lap("lens refit and its solve");
        // With the rig refined, the held-out views (and the fitted ones, for their residuals) are
        // placed on the refined rig.
        match rig_solve {
            Some(Ok(refined)) => {
                notes.push(format!(
                    "rig refined jointly with the camera (reference face '{}'): {}",
                    spec.rig.faces[refined.reference_face].name,
                    (refined.faces.iter())
                        .map(crate::calib::FaceCorrection::describe)
                        .collect::<Vec<_>>()
                        .join("; ")
                ));
                let placed = place_on(&fit, spec.rig, &refined.rig)
                    .and_then(|f| Ok((f, place_on(&held, spec.rig, &refined.rig)?)));
                match placed {
                    Ok((f, h)) => (fit, held) = (f, h),
                    Err(e) => tracing::warn!(error = %e, "views not placed on the refined rig"),
                }
            }
            Some(Err(e)) => {
                tracing::warn!(error = %e, "rig not refined");
                notes.push(format!(
                    "rig not refined ({e}); the rig file's faces were used"
                ));
            }
            None => {}
        }
        let mut held_out = Vec::new();
        let mut held_failures = Vec::new();
        for v in &held {
            match crate::calib::pose::solve_pose(&cal.camera, v) {
                Ok(fit) => {
                    let m = fit.cam_from_rig.rotation.matrix();
                    held_out.push(HeldOut {
                        name: v.name.clone(),
                        rms_px: fit.rms_px,
                        max_px: fit.max_px,
                        rotation: [
                            [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                            [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                            [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
                        ],
                        translation: fit.cam_from_rig.translation.into(),
                    });
                }
                Err(e) => held_failures.push((v.name.clone(), e)),
            }
        }
        let max_residual = judge::max_residual(&cal, &fit);
        result.verdict = judge::judge(&judge::Inputs {
            cfg,
            cal: &cal,
            fit_views: fit.len(),
            coverage: &coverage,
            max_residual_px: max_residual,
            held_out: &held_out,
            held_failures: &held_failures,
            views: &result.views,
        });
        result.verdict.fixed = fixed;
        if let Some(missing) = missing_without_tilt(spec, &poses, &cal, &fit, &coverage) {
            tracing::info!(%missing, "placements a tilt axis would add");
            if let Some(c) =
                (result.verdict.checks.iter_mut()).find(|c| c.name == "coverage" && !c.pass)
            {
                c.hint = Some(match c.hint.take() {
                    Some(h) => format!("{h}; {missing}"),
                    None => missing.clone(),
                });
            }
            notes.push(missing);
        }
        for u in crate::calib::undetermined_parameters(&cal) {
            notes.push(format!(
                "{} is not determined by these views ({:.4} ± {:.4}; 1σ moves the image border by {:.1} px)",
                u.name, u.value, u.std_dev, u.effect_px
            ));
        }
        result.calibration = Some(CalibrationReport::from(&cal));
        result.held_out = held_out;
        result.notes = notes;
        laps.lap("held out and verdict");
        finish_write(&mut writing)?;
        Ok(result)
    })
}

/// A solve of the station's views: the camera, and with `solve.refine_rig` the rig refinement
/// ([`crate::calib::solve_rig`]) whose camera it is — or why the rig could not be refined, the
/// camera then being the plain solve's with the rig file's faces.
type Solved = (
    crate::calib::Calibration,
    Option<Result<crate::calib::RigCalibration, crate::calib::CalibError>>,
);

/// Solve `views` with `opts` (see [`Solved`]).
/// Solve with the one model of `candidates`; with several (`solve.model = "auto"`), solve with each
/// and judge them by their held-out views, reprojected with their poses solved in each camera: a model
/// with more freedom always lowers the fitted views' RMS, so only views it was not fitted to can tell a
/// better lens model from overfitting. The first candidate (Brown–Conrady, which every tool reads) is
/// kept unless a later one lowers the held-out views' sum of squared residuals by more than
/// [`MODEL_SWITCH_CHI2`] × the noise variance (the best-fitting candidate's fitted residual
/// variance): two models that both fit the lens
/// (a mild lens is as well a fisheye with small k) differ by noise there, and the choice between
/// them must not be a coin toss. `opts.model` is set to the model kept; the note gives each
/// candidate's figures and the reason.
/// How much a later lens-model candidate must lower the held-out views' sum of squared residuals, in
/// units of the noise variance, to be chosen over it: a χ² difference
/// beyond 3σ of one degree of freedom's.
pub const MODEL_SWITCH_CHI2: f64 = 9.0;

fn solve_choosing_model(
    spec: &RunSpec<'_>,
    fit: &[View],
    held: &[View],
    image_size: [u32; 2],
    opts: &mut crate::calib::SolveOptions,
    candidates: &[crate::camera::DistortionModel],
) -> Result<(Solved, Option<String>), crate::calib::CalibError> {
    if candidates.len() < 2 {
        return Ok((solve_views(spec, fit, image_size, opts)?, None));
    }
    if held.is_empty() {
        opts.model = candidates[0];
        let note = format!(
            "solve.model = auto: no held-out view to choose the lens model by (plan.held_out = 0 or too few views); {} used",
            opts.model.name()
        );
        return Ok((solve_views(spec, fit, image_size, opts)?, Some(note)));
    }
    let mut scored = Vec::new();
    let mut last_error = None;
    for &model in candidates {
        let o = crate::calib::SolveOptions {
            model,
            ..opts.clone()
        };
        match solve_views(spec, fit, image_size, &o) {
            Ok(solved) => {
                // Σ r² over the held-out coordinates, and their number.
                let (mut sum, mut n) = (0.0, 0usize);
                for v in held {
                    match crate::calib::pose::solve_pose(&solved.0.camera, v) {
                        Ok(p) => {
                            sum += p.residuals.iter().map(|r| r.norm_squared()).sum::<f64>();
                            n += 2 * p.residuals.len();
                        }
                        Err(_) => sum = f64::INFINITY,
                    }
                }
                if n == 0 {
                    sum = f64::INFINITY;
                }
                tracing::info!(
                    model = model.name(),
                    held_ss = sum,
                    fit_rms = solved.0.rms_px,
                    "lens model candidate"
                );
                scored.push((model, sum, n, solved));
            }
            Err(e) => {
                tracing::info!(model = model.name(), error = %e, "lens model candidate failed");
                last_error = Some((model, e));
            }
        }
    }
    if scored.is_empty() {
        return Err(last_error.map_or(
            crate::calib::CalibError::Degenerate {
                reason: "no lens model candidate".into(),
            },
            |(_, e)| e,
        ));
    }
    // The first that solved, unless a later one beats it by the margin; then the best of those.
    // The noise variance: the best-fitting candidate's fitted residual variance (a model that
    // does not fit the lens inflates its own).
    let variance = (scored.iter())
        .map(|s| s.3.0.rms_px.powi(2))
        .fold(f64::INFINITY, f64::min)
        .max(f64::MIN_POSITIVE);
    let gain = |i: usize| (scored[0].1 - scored[i].1) / variance;
    let best = (1..scored.len())
        .filter(|&i| gain(i) > MODEL_SWITCH_CHI2)
        .max_by(|&a, &b| gain(a).total_cmp(&gain(b)))
        .unwrap_or(0);
    let mut parts: Vec<String> = (scored.iter())
        .map(|(m, ss, n, s)| {
            if ss.is_finite() {
                format!(
                    "{} {:.4} px held out (fitted views {:.4} px)",
                    m.name(),
                    (ss / (*n).max(1) as f64).sqrt(),
                    s.0.rms_px
                )
            } else {
                format!(
                    "{}: a held-out view's pose cannot be solved in its camera (fitted views {:.4} px)",
                    m.name(),
                    s.0.rms_px
                )
            }
        })
        .collect();
    if let Some((m, e)) = &last_error {
        parts.push(format!("{} did not solve ({e})", m.name()));
    }
    let why = if best == 0 {
        match (1..scored.len()).map(gain).max_by(f64::total_cmp) {
            Some(g) => format!(
                "no other model lowers the held-out views' squared residuals by over {MODEL_SWITCH_CHI2} σ² (best {g:.1} σ²), so the first, read by every tool, is kept"
            ),
            None => "the only one that solved".to_string(),
        }
    } else if gain(best).is_finite() {
        format!(
            "it lowers the held-out views' squared residuals by {:.1} σ² (over {MODEL_SWITCH_CHI2})",
            gain(best)
        )
    } else {
        format!(
            "it fits the held-out views, which {} cannot",
            scored[0].0.name()
        )
    };
    let (model, _, _, solved) = scored.swap_remove(best);
    opts.model = model;
    let note = format!(
        "lens model {} chosen by the held-out views (not the fitted views' RMS): {why}; {}",
        model.name(),
        parts.join("; ")
    );
    Ok((solved, Some(note)))
}

fn solve_views(
    spec: &RunSpec<'_>,
    views: &[View],
    image_size: [u32; 2],
    opts: &crate::calib::SolveOptions,
) -> Result<Solved, crate::calib::CalibError> {
    if !spec.config.solve.refine_rig {
        return Ok((crate::calib::solve(views, image_size, opts)?, None));
    }
    match refine_rig(spec.rig, views, image_size, opts) {
        Ok(r) => Ok((r.calibration.clone(), Some(Ok(r)))),
        Err(e) => Ok((crate::calib::solve(views, image_size, opts)?, Some(Err(e)))),
    }
}

/// The camera solved with the rig's faces refined ([`crate::calib::solve_rig`]; model, fixes and
/// loss as `opts`); an unconverged fit is an error.
fn refine_rig(
    rig: &Rig,
    views: &[View],
    image_size: [u32; 2],
    opts: &crate::calib::SolveOptions,
) -> Result<crate::calib::RigCalibration, crate::calib::CalibError> {
    use crate::calib::{RigRefineOptions, RigView, Weighting};
    let mut labelled = (views.iter())
        .map(|v| RigView::from_view(v, rig))
        .collect::<Result<Vec<_>, _>>()?;
    // Corners weighted alike because the detector's σ miss its bias (solve.weighting, issue 29):
    // then those σ are not the yardstick of a rig that fits either, the faces' residuals are.
    if opts.weighting == Weighting::Equal {
        for p in labelled.iter_mut().flat_map(|v| v.points.iter_mut()) {
            p.sigma_px = None;
        }
    }
    let ropts = RigRefineOptions {
        solve: opts.clone(),
        ..RigRefineOptions::default()
    };
    let refined = crate::calib::solve_rig(rig, &labelled, image_size, &ropts)?;
    if !refined.calibration.termination.is_converged() {
        return Err(crate::calib::CalibError::Degenerate {
            reason: format!(
                "the fit with the rig refined did not converge ({})",
                refined.calibration.termination.as_str()
            ),
        });
    }
    Ok(refined)
}

/// `views` (corners of `nominal`) with each corner where `refined` puts it.
fn place_on(
    views: &[View],
    nominal: &Rig,
    refined: &Rig,
) -> Result<Vec<View>, crate::calib::CalibError> {
    (views.iter())
        .map(|v| crate::calib::RigView::from_view(v, nominal)?.to_view(refined))
        .collect()
}

/// On a turntable without a tilt axis: which cells the rig never reached and the tilted placements
/// that would fill them ([`plan::missing_without_tilt`]), from the solved camera and the fitted
/// views' poses at their recorded angles. `None` on a two-axis stage, without a turntable, and when
/// nothing is missing.
fn missing_without_tilt(
    spec: &RunSpec<'_>,
    poses: &[PoseData],
    cal: &crate::calib::Calibration,
    fit: &[View],
    coverage: &Coverage,
) -> Option<String> {
    use config::TurntableKind;
    let t = &spec.config.turntable;
    if t.has_tilt() || matches!(t.kind, TurntableKind::None) {
        return None;
    }
    let records: Vec<&ViewRecord> = (poses.iter())
        .filter(|p| p.view.is_some())
        .map(|p| &p.record)
        .collect();
    if records
        .iter()
        .any(|r| r.angle_deg.is_none() || r.tilt_deg.is_some())
    {
        return None;
    }
    let views: Vec<(crate::camera::Pose, f64)> = (fit.iter().zip(&cal.views))
        .filter_map(|(v, solved)| {
            let r = records.iter().find(|r| r.name == v.name)?;
            Some((solved.cam_from_rig, r.angle_deg?))
        })
        .collect();
    let t = &spec.config.turntable;
    let planner = plan::Planner::for_station(
        spec.config,
        spec.rig,
        Some((t.tilt_min_deg, t.tilt_max_deg)),
    );
    plan::missing_without_tilt(&planner, &cal.camera, &views, coverage)
}

/// Wait for a file being written on a thread of its own (if it still is) and return how it went.
fn finish_write(
    writing: &mut Option<std::thread::ScopedJoinHandle<'_, Result<(), StationError>>>,
) -> Result<(), StationError> {
    match writing.take().map(std::thread::ScopedJoinHandle::join) {
        None => Ok(()),
        Some(Ok(r)) => r,
        Some(Err(panic)) => std::panic::resume_unwind(panic),
    }
}

/// The parameters the solve options hold fixed, each with its value and the reason (the config).
fn configured_fixes(
    opts: &crate::calib::SolveOptions,
    image_size: [u32; 2],
) -> Vec<crate::run::FixedParameter> {
    let mut out = Vec::new();
    let mut push = |name: &str, value: f64, reason: &str| {
        out.push(crate::run::FixedParameter {
            name: name.into(),
            value,
            reason: reason.into(),
        })
    };
    let f = &opts.fix;
    if let Some(a) = f.aspect_ratio {
        push(
            "fx/fy",
            a,
            "configured (solve.fix = aspect): square pixels assumed",
        );
    }
    if f.principal_point {
        let c = crate::calib::init::image_centre(image_size);
        let why = "configured (solve.fix = principal-point): held at the image centre";
        push("cx", c.x, why);
        push("cy", c.y, why);
    }
    if f.skew {
        push(
            "skew",
            0.0,
            "held at 0 by default: modern sensors have none",
        );
    }
    if matches!(
        opts.model,
        crate::camera::DistortionModel::Brown5 | crate::camera::DistortionModel::Brown8
    ) {
        if f.tangential {
            let why = "configured (solve.fix = tangential)";
            push("p1", 0.0, why);
            push("p2", 0.0, why);
        }
        if f.k3 {
            push("k3", 0.0, "configured (solve.fix = k3)");
        }
    }
    out
}

/// Write the profile of a passing run: `RUN_DIR/profile.json` always, and into the per-device store
/// when `output.store` is set (atomic, versioned; a jump beyond `qa.max_jump_sigma` from the previous
/// profile is noted). Returns where the profile went (the store's `current.json` when stored).
fn write_profile(
    spec: &RunSpec<'_>,
    hw: &Hardware,
    result: &mut RunResult,
    calibration: CalibrationReport,
    sink: &mut dyn EventSink,
) -> Result<PathBuf, StationError> {
    use crate::profile::{Identity, IdentityOrigin, Profile, RigRef, SessionRef};
    use sha2::{Digest, Sha256};
    let hex = |b: &[u8]| -> String {
        Sha256::digest(b)
            .iter()
            .map(|x| format!("{x:02x}"))
            .collect()
    };
    let manifest = spec
        .run_dir
        .join(crate::run::SESSION)
        .join(crate::capture::session::MANIFEST);
    let manifest_sha256 = std::fs::read(&manifest)
        .map(|b| hex(&b))
        .map_err(|source| StationError::Write {
            path: manifest.clone(),
            source,
        })?;
    let origin = if hw.device.is_some() {
        IdentityOrigin::Device
    } else if hw.replayed.is_some() {
        IdentityOrigin::Session
    } else {
        IdentityOrigin::User
    };
    let profile = Profile {
        identity: Identity {
            id: hw
                .identity
                .clone()
                .unwrap_or_else(|| result.device.identity.clone()),
            origin,
            device: hw.device.clone(),
        },
        calibration,
        verdict: result.verdict.clone(),
        controls: hw.controls.clone(),
        format: hw.capture,
        rig: RigRef {
            name: spec.rig.name.clone(),
            sha256: hex(spec.rig_toml.as_bytes()),
        },
        // Absolute, so that the profile names its session wherever it is read from (a run directory
        // given as a relative --out would otherwise mean another place from another directory).
        session: Some(SessionRef {
            path: std::path::absolute(spec.run_dir.join(crate::run::SESSION)).map_err(
                |source| StationError::Write {
                    path: spec.run_dir.to_path_buf(),
                    source,
                },
            )?,
            manifest_sha256,
        }),
        software_version: env!("CARGO_PKG_VERSION").to_string(),
        created: crate::profile::now_rfc3339(),
        change: None,
    };
    let path = spec.run_dir.join("profile.json");
    // The store's document format (with format_version), so that `cubecal profile diff` and
    // `cubecal report` read a run's profile.json like any stored profile.
    write_file(&path, &crate::profile::to_document(&profile))?;
    let Some(store_value) = &spec.config.output.store else {
        return Ok(path);
    };
    let provenance = crate::profile::Provenance {
        // the run's own profile.json (its creation time and session hash make it unique): a second
        // commit of the same run stores nothing new
        run_id: hex(&crate::profile::to_document(&profile)),
        station: station_name(),
        report: Some(spec.run_dir.display().to_string()),
    };
    let options = crate::profile::CommitOptions {
        jump_sigma: spec.config.qa.max_jump_sigma,
    };
    let spool = crate::profile::spool::Spool::new(spec.config.output.spool_dir());
    let opened = crate::profile::open_store(
        store_value,
        spec.config.output.store_password_file.as_deref(),
    );
    // The store unreachable (at the start of the commit or during it): the profile waits in the
    // spool, and the run goes on as a pass that says where its profile is.
    let spooled = |e: crate::profile::ProfileError,
                   result: &mut RunResult,
                   sink: &mut dyn EventSink|
     -> Result<PathBuf, StationError> {
        let store = crate::profile::backend::describe_location(store_value);
        let reason = crate::profile::error_chain(&e);
        let path = spool.put(&store, &profile, &options, &provenance, &reason)?;
        let waiting = spool.depth()?;
        result.notes.push(format!(
            "the profile store {store} could not be reached ({reason}): the profile waits in {} and is committed when the store returns (the next run with this store, `cubecal serve`, or `cubecal profile sync --store {store} --spool {}`)",
            path.display(),
            spool.dir().display()
        ));
        result.profile_waits_for = Some(store.clone());
        sink.event(&Event::ProfileSpooled {
            path: path.clone(),
            store,
            reason,
            waiting,
        });
        Ok(path)
    };
    let store = match opened {
        Ok(store) => store,
        Err(e) if e.is_unreachable() => return spooled(e, result, sink),
        Err(e) => return Err(e.into()),
    };
    // Profiles that waited for this store go first, so the store's order is the runs' order.
    if spool.depth()? > 0 {
        let drained = spool.drain(store.as_ref())?;
        sink.event(&Event::SpoolDrained {
            store: store.describe(),
            committed: drained.committed.len(),
            already_stored: drained.already_stored.len(),
            failed: drained.failed.len(),
            waiting: drained.waiting,
        });
    }
    let outcome = match store.commit_run(&profile, &options, &provenance) {
        Ok(o) => o,
        Err(e) if e.is_unreachable() => return spooled(e, result, sink),
        Err(e) => return Err(e.into()),
    };
    if outcome.jump {
        result.notes.push(format!(
            "the profile moved by more than {}σ from the previous one of this camera (see `cubecal profile diff`): a bumped lens or a different camera?",
            spec.config.qa.max_jump_sigma
        ));
    }
    Ok(outcome.location)
}

/// The station's name in a profile's provenance: the host name (`/etc/hostname`, else `HOSTNAME`,
/// else `unknown`).
fn station_name() -> String {
    std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "unknown".to_string())
}

/// `YYYY-MM-DDTHH-MM-SSZ` (UTC, file-name safe) for run directory names: RFC 3339 with `-` for `:`.
pub fn utc_stamp(t: std::time::SystemTime) -> String {
    let secs = t
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    crate::profile::rfc3339_from_unix(secs).replace(':', "-")
}
