//! Capture: the [`FrameSource`] trait the station sees cameras through, and its implementations —
//! V4L2 (real cameras), replay of recorded sessions, and synthetic rendering (`synthetic`).
//!
//! The trait is shaped by what the station needs, not by what drivers offer: describe the source, grab
//! one owned grayscale frame within a deadline, and flush frames queued before a turntable move.
//! Frames carry a sequence number and a timestamp, so stale frames are recognisable.

use std::time::Duration;

pub mod synthetic;

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
}

impl CaptureError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            CaptureError::Timeout { .. } | CaptureError::Io { .. } => crate::exit::DEVICE,
            CaptureError::EndOfStream { .. } => crate::exit::BAD_INPUT,
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
}
