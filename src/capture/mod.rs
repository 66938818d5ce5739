//! Capture: the [`FrameSource`] trait the station sees cameras through, and its implementations —
//! V4L2 (real cameras), replay of recorded sessions, photos, and synthetic cameras (`synthetic`).
//!
//! The trait is shaped by what the station needs, not by what drivers offer: describe the source, grab
//! one owned grayscale frame within a deadline, and flush frames queued before a turntable move.
//! Frames carry a sequence number and a timestamp, so stale frames are recognisable.
//!
//! - [`v4l2`]: real cameras ([`v4l2::V4l2Source`]), device discovery, locked controls.
//! - [`session`]: recorded sessions on disk and [`session::ReplaySource`].
//! - [`convert`]: pixel formats and their conversion to gray.
//! - [`synthetic`]: synthetic cameras grabbing from the renderer ([`crate::render`]); [`feed`]: the
//!   synthetic camera in front of a simulated stage.
//!
//! Errors keep the device or file they concern and the OS error kind, because the actions differ: a
//! [`CaptureError::Timeout`] may be retried, an [`CaptureError::Unplugged`] camera must be reconnected,
//! a [`CaptureError::Session`] error means the recording on disk is incomplete or was altered.

use std::time::Duration;

pub mod convert;
pub mod feed;
pub mod images;
pub mod session;
pub mod synthetic;
pub mod v4l2;

/// An owned 8-bit grayscale image, row-major, `width × height` bytes.
pub type GrayImage = image::GrayImage;

/// One captured frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Driver or source sequence number; increases by one per frame produced (gaps mean dropped frames).
    pub sequence: u64,
    /// Capture time, monotonic, relative to an epoch fixed by the source (e.g. stream start).
    pub timestamp: Duration,
    /// The image, converted to 8-bit grayscale.
    pub image: GrayImage,
}

/// What a source is: enough to identify the camera and the format in a session or profile.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct SourceInfo {
    /// Stable identity of the device (e.g. USB vendor:product:serial, or "synthetic:<rig>").
    pub identity: String,
    /// Human-readable name (card name, file path).
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Pixel format as delivered by the device (FourCC such as "YUYV"), before conversion to gray.
    pub format: String,
}

/// Errors from frame sources.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// No frame arrived before the deadline.
    #[error("no frame from {source_name} within {timeout:?}")]
    Timeout {
        source_name: String,
        timeout: Duration,
    },
    /// The source has no more frames (end of a replayed session).
    #[error("{source_name}: end of stream")]
    EndOfStream { source_name: String },
    /// An I/O error talking to the device or reading files.
    #[error("{source_name}: {context}")]
    Io {
        source_name: String,
        context: String,
        #[source]
        source: std::io::Error,
    },
    /// The device node could not be opened (missing, permission, busy: see the source's kind).
    #[error("cannot open {device}")]
    Open {
        device: String,
        #[source]
        source: std::io::Error,
    },
    /// The device went away (ENODEV): unplugged, or its driver disconnected it. Reconnect and reopen.
    #[error("{device} disconnected (unplugged?) while {context}")]
    Unplugged {
        device: String,
        context: String,
        #[source]
        source: std::io::Error,
    },
    /// The device is in use by another process (EBUSY).
    #[error("{device} is busy ({context}); is another program using the camera?")]
    Busy {
        device: String,
        context: String,
        #[source]
        source: std::io::Error,
    },
    /// The device cannot do what cubecal needs (not a capture device, no convertible format, size).
    #[error("{device}: {reason}")]
    Unsupported { device: String, reason: String },
    /// A control could not be set or read back.
    #[error("{device}: {context}")]
    Control {
        device: String,
        context: String,
        #[source]
        source: std::io::Error,
    },
    /// A recorded session is missing, incomplete, altered or cannot be written.
    #[error(transparent)]
    Session(#[from] session::SessionError),
    /// A photo the user gave cannot be used (missing, unreadable, empty, not an image, another
    /// size): bad input. From [`FrameSource::grab`] it concerns that one frame — the station
    /// rejects the view with `reason` and goes on; from opening a source, no photo was usable.
    #[error("{path}: {reason}")]
    Image { path: String, reason: String },
}

/// `ENODEV`: the device was removed.
const ENODEV: i32 = 19;
/// `EBUSY`: the device is in use.
const EBUSY: i32 = 16;

impl CaptureError {
    /// Sort an OS error from a device ioctl into the variant that says what to do about it.
    pub fn from_io(device: &str, context: &str, source: std::io::Error) -> CaptureError {
        match source.raw_os_error() {
            Some(ENODEV) => CaptureError::Unplugged {
                device: device.to_string(),
                context: context.to_string(),
                source,
            },
            Some(EBUSY) => CaptureError::Busy {
                device: device.to_string(),
                context: context.to_string(),
                source,
            },
            _ => CaptureError::Io {
                source_name: device.to_string(),
                context: context.to_string(),
                source,
            },
        }
    }
}

impl CaptureError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            CaptureError::Timeout { .. }
            | CaptureError::Io { .. }
            | CaptureError::Open { .. }
            | CaptureError::Unplugged { .. }
            | CaptureError::Busy { .. }
            | CaptureError::Unsupported { .. }
            | CaptureError::Control { .. } => crate::exit::DEVICE,
            CaptureError::EndOfStream { .. } | CaptureError::Image { .. } => crate::exit::BAD_INPUT,
            CaptureError::Session(e) => e.exit_code(),
        }
    }
}

/// A source of grayscale frames: a camera, a recorded session, or a renderer.
pub trait FrameSource {
    /// Identity, resolution and native format.
    fn describe(&self) -> SourceInfo;
    /// Wait at most `timeout` for the next frame.
    fn grab(&mut self, timeout: Duration) -> Result<Frame, CaptureError>;
    /// Drop every frame already queued (e.g. captured while the turntable was moving); returns how
    /// many were dropped.
    fn flush(&mut self) -> Result<usize, CaptureError>;
    /// The file behind the frame the last `grab` returned or failed on, for sources that read files
    /// a user gave (photos, and sessions that recorded photos): the recorder keeps its bytes as they
    /// are instead of encoding the decoded frame. `None` (the default) for cameras and renderers.
    fn take_source_file(&mut self) -> Option<SourceFile> {
        None
    }
    /// Whether the frames were taken before the run (photos, a recorded session): they are the
    /// same whenever they are grabbed, so the station may grab a pose before it has detected the
    /// one before. `false` (the default) for cameras and renderers.
    fn recorded(&self) -> bool {
        false
    }
}

/// A user's image file as it was read, to be recorded byte for byte (see
/// [`FrameSource::take_source_file`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceFile {
    /// The name the file is known by in every output: its file name, or the path as given when
    /// two files of a run share a file name ([`images::labels`]).
    pub name: String,
    /// Its extension, lower case (`jpg`, `png`, `tif`, …), for the recorded copy's file name.
    pub extension: String,
    /// Its bytes, or why it could not be read (missing, a folder, no permission).
    pub bytes: Result<Vec<u8>, String>,
}

/// A way in which a [`FrameSource`] broke the trait's contract (see [`check_contract`]).
#[derive(Debug, thiserror::Error)]
pub enum ContractViolation {
    #[error("frame {index}: grab failed")]
    Grab {
        index: usize,
        #[source]
        source: CaptureError,
    },
    #[error("flush failed")]
    Flush {
        #[source]
        source: CaptureError,
    },
    #[error("frame {index}: image is {got:?}, describe() says {want:?}")]
    Size {
        index: usize,
        got: (u32, u32),
        want: (u32, u32),
    },
    #[error("frame {index}: sequence {got} does not increase (previous {previous})")]
    Sequence {
        index: usize,
        previous: u64,
        got: u64,
    },
    #[error("frame {index}: timestamp {got:?} goes backwards (previous {previous:?})")]
    Timestamp {
        index: usize,
        previous: Duration,
        got: Duration,
    },
    #[error("grab({timeout:?}) took {took:?}")]
    Deadline { timeout: Duration, took: Duration },
}

/// The contract every [`FrameSource`] keeps, checked over `frames` grabs: each grab returns within
/// its timeout (plus `slack` for scheduling), frames have the size `describe()` reports, sequence numbers
/// strictly increase, timestamps never go backwards, and `flush` succeeds between grabs. Run by the
/// tests of every implementation (replay on the host, V4L2 against vivid in the VM test).
pub fn check_contract(
    src: &mut dyn FrameSource,
    frames: usize,
    timeout: Duration,
    slack: Duration,
) -> Result<(), ContractViolation> {
    let info = src.describe();
    let want = (info.width, info.height);
    let mut last: Option<(u64, Duration)> = None;
    for index in 0..frames {
        if index == frames / 2 {
            src.flush()
                .map_err(|source| ContractViolation::Flush { source })?;
        }
        let t = std::time::Instant::now();
        let f = src
            .grab(timeout)
            .map_err(|source| ContractViolation::Grab { index, source })?;
        let took = t.elapsed();
        if took > timeout + slack {
            return Err(ContractViolation::Deadline { timeout, took });
        }
        if f.image.dimensions() != want {
            return Err(ContractViolation::Size {
                index,
                got: f.image.dimensions(),
                want,
            });
        }
        if let Some((previous, previous_ts)) = last {
            if f.sequence <= previous {
                return Err(ContractViolation::Sequence {
                    index,
                    previous,
                    got: f.sequence,
                });
            }
            if f.timestamp < previous_ts {
                return Err(ContractViolation::Timestamp {
                    index,
                    previous: previous_ts,
                    got: f.timestamp,
                });
            }
        }
        last = Some((f.sequence, f.timestamp));
    }
    Ok(())
}
