//! Typed events the station emits while it runs. The library never prints: the CLI renders these as a
//! progress bar and per-pose lines (or one JSON object per line with `--json`), the service as
//! systemd `STATUS=` lines and watchdog pings, the live page ([`crate::live`]) as a web page.
//!
//! Two events carry pixels and are made only for sinks that ask for them
//! ([`EventSink::wants_frames`], false by default): [`Event::Frame`], each frame as it is grabbed, and
//! [`Event::Detected`], where the detector found the labelled corners. Without such a sink the
//! station neither copies a frame nor builds them, so a run without the live page does no extra work;
//! the CLI's and the service's renderers ignore both.

use serde::Serialize;

use crate::run::Verdict;

/// Something that happened during a run. Serialised with a `"event"` tag (snake_case names).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    /// The camera and the turntable are open (the service says `READY=1` here).
    Opened {
        source: String,
        width: u32,
        height: u32,
        turntable: String,
    },
    /// The stage is homing before the first pose; `instruction` is what a manual operator is asked.
    Homing { instruction: Option<String> },
    /// Pose `index` (0-based) of `total` planned; `instruction` is what a manual operator is asked.
    PosePlanned {
        index: usize,
        total: usize,
        angle_deg: Option<f64>,
        instruction: Option<String>,
    },
    /// The planner chose the stage pose of pose `index` (two-axis stages): the corners it predicts
    /// there and the σ it predicts once that view is added ([`crate::station::plan`]).
    PoseChosen {
        index: usize,
        rotation_deg: f64,
        tilt_deg: f64,
        corners: usize,
        predicted: Vec<crate::station::plan::PredictedSigma>,
    },
    /// The stage is tilting for pose `index`.
    Tilting { index: usize, tilt_deg: f64 },
    /// The turntable is moving to pose `index`.
    Moving { index: usize, angle_deg: f64 },
    /// The turntable reports it has settled.
    Settled { index: usize, angle_deg: f64 },
    /// A frame just grabbed for pose `index` (made only for sinks that [want
    /// frames](EventSink::wants_frames)). `grabbed_unix_ms` is the wall-clock time at which the grab
    /// returned, for the page's grab-to-screen latency. The pixels are not serialised.
    Frame {
        index: usize,
        sequence: u64,
        grabbed_unix_ms: f64,
        #[serde(skip)]
        image: FrameImage,
    },
    /// Where the detector found labelled corners in pose `index`'s last frame (frame `sequence`),
    /// per face, in full-frame pixels (made only for sinks that want frames): the view's corners when
    /// it was accepted, the detection's when it was rejected after detection.
    Detected {
        index: usize,
        sequence: u64,
        width: u32,
        height: u32,
        faces: Vec<DetectedFace>,
    },
    /// A frame was grabbed for pose `index` after dropping `flushed` stale frames.
    FrameGrabbed {
        index: usize,
        sequence: u64,
        flushed: usize,
    },
    /// The view of pose `index` was accepted.
    ViewAccepted {
        index: usize,
        name: String,
        faces: usize,
        corners: usize,
    },
    /// The view of pose `index` was rejected, with a reason a person can act on.
    ViewRejected {
        index: usize,
        name: String,
        reason: String,
    },
    /// Coverage after the latest view: fraction of the image grid cells holding corners.
    /// `grid` is `[cols, rows]` and `counts` the corners per cell, row-major (the map a page draws).
    Coverage {
        views: usize,
        fraction: f64,
        cells_covered: usize,
        cells_total: usize,
        grid: [usize; 2],
        counts: Vec<usize>,
    },
    /// The final solve started.
    Solving { views: usize, points: usize },
    /// The verdict of the run.
    Verdict { verdict: Verdict },
    /// The profile store could not be reached: the passing profile waits in the spool at `path`
    /// until a later run, `serve` or `cubecal profile sync` commits it; `waiting` profiles in all.
    ProfileSpooled {
        path: std::path::PathBuf,
        store: String,
        reason: String,
        waiting: usize,
    },
    /// Profiles that waited in the spool were committed (`committed` now, `already_stored` found
    /// stored by a drain cut short), `failed` set aside as refused; `waiting` are left.
    SpoolDrained {
        store: String,
        committed: usize,
        already_stored: usize,
        failed: usize,
        waiting: usize,
    },
    /// Emitted by the station loop while waiting on hardware, so a service can ping its watchdog
    /// from the loop itself (a stalled loop stops the pings).
    Alive,
}

/// A grabbed frame shared with the sinks that want it (its `Debug` prints the size, not the pixels).
#[derive(Clone, PartialEq)]
pub struct FrameImage(pub std::sync::Arc<image::GrayImage>);

impl std::fmt::Debug for FrameImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FrameImage({}×{})", self.0.width(), self.0.height())
    }
}

/// One face's labelled corners in a frame ([`Event::Detected`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectedFace {
    /// The rig face's name.
    pub face: String,
    /// Corner positions `[u, v]` in full-frame pixels (pixel-centre convention).
    pub corners: Vec<[f32; 2]>,
}

/// Where events go.
pub trait EventSink {
    fn event(&mut self, event: &Event);

    /// Whether this sink wants [`Event::Frame`] and [`Event::Detected`] (the live page does); the
    /// station makes them only then.
    fn wants_frames(&self) -> bool {
        false
    }
}

/// A sink that drops everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct NullSink;

impl EventSink for NullSink {
    fn event(&mut self, _event: &Event) {}
}

/// A sink that keeps every event (tests, reports).
#[derive(Debug, Default, Clone)]
pub struct Recorder {
    pub events: Vec<Event>,
}

impl EventSink for Recorder {
    fn event(&mut self, event: &Event) {
        self.events.push(event.clone());
    }
}

impl<F: FnMut(&Event)> EventSink for F {
    fn event(&mut self, event: &Event) {
        self(event)
    }
}
