//! A synthetic camera behind a real V4L2 driver: the rig rendered at the angle a simulated turntable
//! reports ([`TurntableScene`]), written to a V4L2 *output* device ([`V4l2Output`]) whose driver loops
//! it into a capture device (vivid's "Loop Video", v4l2loopback). A station reading the capture side
//! then runs its real V4L2 path, against the real serial protocol of the simulator, with a picture
//! that follows the turntable — the test rig of tests/vm/service.sh (`cubecal turntable simulate
//! --feed`).
//!
//! ## One loop
//! The feeder thread reads the stage's position from the simulator's [`StageView`]; when the stage
//! is at rest at a position it has not rendered, it renders the rig there (seconds under emulation),
//! then writes that frame to the output over and over. After `buffers + 1` writes every buffer the
//! driver still holds is the new frame, so the picture on the capture side is the new pose: only then
//! does it tell the view, and only then does the simulator report the move finished
//! ([`crate::turntable::sim::grbl_pair_seen`]). The station, which grabs after "settled" and after
//! dropping queued frames, therefore never sees the previous pose's picture. While a move runs the
//! last picture stays on the output (a render per intermediate position would only delay the
//! final one). Rendered frames are kept by position: a plan that comes back to where it homed shows
//! the same picture without rendering it again.
//!
//! The output device may not exist yet when the feeder starts (the test loads vivid after starting
//! the simulator, so that the service udev starts finds its turntable): the feeder waits for it.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::convert::{PixelFormat, encode_gray};
use super::synthetic::{AngleCell, TurntableScene};
use super::v4l2::{Negotiated, V4l2Output, enable_vivid_loop};
use super::{CaptureError, FrameSource};
use crate::render::SyntheticError;
use crate::turntable::sim::StageView;

/// Errors that end a feeder.
#[derive(Debug, thiserror::Error)]
pub enum FeedError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Synthetic(#[from] SyntheticError),
    #[error("output device {path} did not appear within {waited:?}")]
    NoDevice { path: PathBuf, waited: Duration },
    #[error("cannot encode a {width}x{height} frame as {format} with stride {stride}")]
    Encode {
        format: PixelFormat,
        width: u32,
        height: u32,
        stride: u32,
    },
    #[error("degrees per unit must be finite and non-zero, got {0}")]
    Scale(f64),
}

impl FeedError {
    pub fn exit_code(&self) -> u8 {
        match self {
            FeedError::Capture(e) => e.exit_code(),
            FeedError::Synthetic(e) => e.exit_code(),
            FeedError::NoDevice { .. } => crate::exit::DEVICE,
            FeedError::Encode { .. } => crate::exit::USAGE,
            FeedError::Scale(_) => crate::exit::USAGE,
        }
    }
}

/// Where and how to feed.
#[derive(Debug, Clone, PartialEq)]
pub struct FeedConfig {
    /// The V4L2 output node.
    pub output: PathBuf,
    /// Pixel format of the output; must be the capture side's format for vivid's loop.
    pub format: PixelFormat,
    /// Table degrees per native unit of the simulator (GRBL: degrees per axis unit).
    pub degrees_per_unit: f64,
    /// A vivid capture node to switch to looping the output ([`enable_vivid_loop`]).
    pub vivid_loop: Option<PathBuf>,
    /// Output buffers to request.
    pub buffers: u32,
    /// How long to wait for the output node (and the loop's capture node) to appear.
    pub wait_for_device: Duration,
}

/// Counters of a running feeder (shared with its thread).
#[derive(Debug, Default)]
pub struct FeedStats {
    renders: AtomicU64,
    writes: AtomicU64,
    /// Microseconds spent rendering, all renders together.
    render_us: AtomicU64,
}

impl FeedStats {
    pub fn renders(&self) -> u64 {
        self.renders.load(Ordering::Relaxed)
    }
    pub fn writes(&self) -> u64 {
        self.writes.load(Ordering::Relaxed)
    }
    pub fn render_time(&self) -> Duration {
        Duration::from_micros(self.render_us.load(Ordering::Relaxed))
    }
}

/// A running feeder thread; [`Feeder::stop`] (or drop) ends it.
#[derive(Debug)]
pub struct Feeder {
    stop: Arc<AtomicBool>,
    stats: Arc<FeedStats>,
    thread: Option<JoinHandle<Result<(), FeedError>>>,
}

/// Shortest wait between looks at the stage while nothing needs rendering and the output is not open.
const POLL: Duration = Duration::from_millis(50);
/// Rendered frames kept (about 1 MB each at 1280×720 GREY).
const RENDER_CACHE: usize = 32;
/// Longest wait for the driver to take a frame.
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);

impl Feeder {
    /// Start feeding `scene` (whose [`AngleCell`] is `angle`) at the positions `view` reports.
    pub fn spawn(
        scene: TurntableScene,
        angle: AngleCell,
        view: StageView,
        cfg: FeedConfig,
    ) -> Result<Feeder, FeedError> {
        if !(cfg.degrees_per_unit.is_finite() && cfg.degrees_per_unit != 0.0) {
            return Err(FeedError::Scale(cfg.degrees_per_unit));
        }
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(FeedStats::default());
        let (flag, counters) = (Arc::clone(&stop), Arc::clone(&stats));
        let thread = std::thread::Builder::new()
            .name("feeder".into())
            .spawn(move || feed(scene, angle, &view, &cfg, &flag, &counters))
            .map_err(|source| CaptureError::Io {
                source_name: "feeder".into(),
                context: "spawning the feeder thread".into(),
                source,
            })?;
        Ok(Feeder {
            stop,
            stats,
            thread: Some(thread),
        })
    }

    pub fn stats(&self) -> &FeedStats {
        &self.stats
    }

    /// Whether the thread still runs (it ends on an error, e.g. the device was removed).
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Stop the thread and return how it ended.
    pub fn stop(mut self) -> Result<(), FeedError> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Result<(), FeedError> {
        self.stop.store(true, Ordering::Relaxed);
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(FeedError::Capture(CaptureError::Io {
                source_name: "feeder".into(),
                context: "the feeder thread panicked".into(),
                source: std::io::Error::other("panic"),
            })),
            None => Ok(()),
        }
    }
}

impl Drop for Feeder {
    fn drop(&mut self) {
        if let Err(e) = self.shutdown() {
            tracing::warn!(error = %e, "feeder ended with an error");
        }
    }
}

/// Wait until `path` exists, or `stop`, or `limit`.
fn wait_for(path: &Path, limit: Duration, stop: &AtomicBool) -> Result<bool, FeedError> {
    let start = Instant::now();
    while !path.exists() {
        if stop.load(Ordering::Relaxed) {
            return Ok(false);
        }
        if start.elapsed() >= limit {
            return Err(FeedError::NoDevice {
                path: path.to_path_buf(),
                waited: limit,
            });
        }
        std::thread::sleep(POLL);
    }
    Ok(true)
}

fn feed(
    mut scene: TurntableScene,
    angle: AngleCell,
    view: &StageView,
    cfg: &FeedConfig,
    stop: &AtomicBool,
    stats: &FeedStats,
) -> Result<(), FeedError> {
    let info = scene.describe();
    for path in std::iter::once(&cfg.output).chain(cfg.vivid_loop.as_ref()) {
        if !wait_for(path, cfg.wait_for_device, stop)? {
            return Ok(());
        }
    }
    // udev may still be applying the node's permissions and links: give it a moment.
    std::thread::sleep(POLL * 4);
    if let Some(capture) = &cfg.vivid_loop {
        enable_vivid_loop(capture)?;
    }
    let mut out = V4l2Output::open(
        &cfg.output,
        cfg.format,
        info.width,
        info.height,
        cfg.buffers,
    )?;
    let n = out.negotiated();
    tracing::info!(
        output = %cfg.output.display(),
        format = %cfg.format,
        width = n.width,
        height = n.height,
        "feeding the rendered rig"
    );
    // (position on the output, its frame, writes of it so far)
    let mut current: Option<(f64, Vec<u8>, u64)> = None;
    // Frames already rendered, by position (a plan often comes back to 0°, where it homed).
    let mut rendered: HashMap<u64, Vec<u8>> = HashMap::new();
    let shown_after = u64::from(cfg.buffers.max(2)) + 1;
    while !stop.load(Ordering::Relaxed) {
        let (position, moving) = view.position_and_motion();
        let stale = current.as_ref().is_none_or(|(p, _, _)| *p != position);
        if stale && !moving {
            let raw = match rendered.get(&position.to_bits()) {
                Some(raw) => raw.clone(),
                None => {
                    let raw = render(&mut scene, &angle, position, cfg, n, stats)?;
                    if rendered.len() >= RENDER_CACHE {
                        rendered.clear();
                    }
                    rendered.insert(position.to_bits(), raw.clone());
                    raw
                }
            };
            current = Some((position, raw, 0));
        }
        match current.as_mut() {
            Some((p, raw, writes)) => {
                out.write(raw, WRITE_TIMEOUT)?;
                stats.writes.fetch_add(1, Ordering::Relaxed);
                *writes += 1;
                if *writes == shown_after {
                    view.set_shown(*p);
                }
            }
            None => std::thread::sleep(POLL),
        }
    }
    Ok(())
}

/// Render the rig with the stage at `position` (native units) and encode it for the output.
fn render(
    scene: &mut TurntableScene,
    angle: &AngleCell,
    position: f64,
    cfg: &FeedConfig,
    n: Negotiated,
    stats: &FeedStats,
) -> Result<Vec<u8>, FeedError> {
    let degrees = position * cfg.degrees_per_unit;
    angle.set(degrees);
    let start = Instant::now();
    let frame = scene.grab(WRITE_TIMEOUT)?;
    let took = start.elapsed();
    stats.renders.fetch_add(1, Ordering::Relaxed);
    stats.render_us.fetch_add(
        u64::try_from(took.as_micros()).unwrap_or(u64::MAX),
        Ordering::Relaxed,
    );
    tracing::info!(degrees, took_s = took.as_secs_f64(), "rendered the rig");
    encode_gray(cfg.format, &frame.image, n.stride as usize).ok_or(FeedError::Encode {
        format: cfg.format,
        width: n.width,
        height: n.height,
        stride: n.stride,
    })
}
