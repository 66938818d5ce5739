//! V4L2 cameras: discovery ([`discover`]), format negotiation, locked controls, and mmap streaming in
//! which every wait has a deadline ([`V4l2Source`]). [`V4l2Output`] feeds frames to an output device
//! (vivid's loop, v4l2loopback); the VM test uses it to push a known image through a real driver.
//!
//! ## Behaviour worth knowing
//! - **Timeouts.** `grab(timeout)` never waits longer than `timeout`: the wait is a `poll()` with the
//!   remaining time, and the dequeue is non-blocking. A stalled stream gives
//!   [`CaptureError::Timeout`]; the stream stays usable, the next `grab` may still succeed.
//! - **Unplug.** A device that disappears mid-stream (ENODEV) gives [`CaptureError::Unplugged`]; the
//!   source is dead after that and must be reopened.
//! - **Corrupt frames** (driver `V4L2_BUF_FLAG_ERROR`, truncated or undecodable MJPG, short raw
//!   frames) are dropped, counted ([`V4l2Source::dropped_frames`]) and logged; `grab` keeps waiting
//!   for a good frame within the same deadline.
//! - **Stride.** The driver's `bytesperline` is used as returned. S_FMT asks for stride 0 (natural),
//!   because some drivers (vivid) keep a stale stride from an earlier, wider format.
//! - **Sequence and timestamp** are the driver's (`v4l2_buffer.sequence`, and its monotonic timestamp,
//!   whose epoch is the boot of the machine).
//! - The `v4l` crate is used for discovery, formats and controls; buffer streaming is done by the small
//!   raw-ioctl layer in `v4l2/sys.rs`, the only `unsafe` code in cubecal (see that module for why).
//!   Known limit of `v4l` 0.14: `query_caps` and `query_controls` panic on non-UTF-8 names and unknown
//!   control types; no such device has been seen, but it is not our code and cannot be fixed here.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use v4l::FourCC;
use v4l::capability::Flags;
use v4l::device::Device;
use v4l::video::{Capture, Output};

use super::convert::{self, PixelFormat};
use super::{CaptureError, Frame, FrameSource, SourceInfo};

mod controls;
mod discover;
mod sys;

pub use controls::{
    ControlInfo, ControlSetting, LockSettings, list_controls, lock_controls, set_control,
};
pub use discover::{
    DeviceInfo, FormatInfo, FrameSizes, SkippedNode, UsbId, discover, inspect, usb_identity,
    video_nodes,
};
use sys::{BUF_FLAG_ERROR, Direction, MmapQueue};

/// `v4l::Device` without `Debug`; shows its fd.
struct Dev(Device);

impl std::fmt::Debug for Dev {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Device(fd {})", self.0.handle().fd())
    }
}

/// What to ask of the camera.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct V4l2Config {
    /// Requested size; `None` keeps the device's current size.
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Requested format; `None` picks the first of [`PixelFormat::ALL`] the device offers at the size.
    pub format: Option<PixelFormat>,
    /// Requested frame rate (the driver grants the nearest interval it supports).
    pub fps: Option<u32>,
    /// Number of mmap buffers to request.
    pub buffers: u32,
    /// Lock focus, exposure, gain, white balance and zoom (see [`lock_controls`]).
    pub lock: Option<LockSettings>,
}

impl Default for V4l2Config {
    fn default() -> Self {
        V4l2Config {
            width: None,
            height: None,
            format: None,
            fps: None,
            buffers: 4,
            lock: Some(LockSettings::default()),
        }
    }
}

/// The capture format the driver agreed to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Negotiated {
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    /// `bytesperline` as returned by the driver.
    pub stride: u32,
    /// `sizeimage` as returned by the driver.
    pub size_image: u32,
    /// Frame interval granted, as numerator/denominator seconds (0/0 if unknown).
    pub interval: (u32, u32),
}

/// A V4L2 camera as a [`FrameSource`].
#[derive(Debug)]
pub struct V4l2Source {
    path: PathBuf,
    name: String,
    info: DeviceInfo,
    negotiated: Negotiated,
    locked: Vec<ControlSetting>,
    // field order matters: the queue (mappings, STREAMOFF) must drop before the device fd closes
    queue: MmapQueue,
    dev: Dev,
    dropped: u64,
    dead: bool,
}

impl V4l2Source {
    /// Open `path`, negotiate the format, set the frame rate, lock the controls and map the buffers.
    /// Streaming starts on the first `grab`.
    pub fn open(path: &Path, cfg: &V4l2Config) -> Result<V4l2Source, CaptureError> {
        let name = path.display().to_string();
        let info = inspect(path)?.ok_or_else(|| CaptureError::Unsupported {
            device: name.clone(),
            reason: "not a video capture device (no V4L2_CAP_VIDEO_CAPTURE)".into(),
        })?;
        let dev = Device::with_path(path).map_err(|e| CaptureError::Open {
            device: name.clone(),
            source: e,
        })?;
        let mut negotiated = negotiate(&dev, &name, &info, cfg)?;
        if let Some(fps) = cfg.fps {
            let p = Capture::set_params(&dev, &v4l::video::capture::Parameters::with_fps(fps))
                .map_err(|e| {
                    CaptureError::from_io(&name, "setting the frame rate (VIDIOC_S_PARM)", e)
                })?;
            tracing::info!(device = %name, requested_fps = fps, interval = %format!("{}/{}", p.interval.numerator, p.interval.denominator), "frame interval");
        }
        if let Ok(p) = Capture::params(&dev) {
            negotiated.interval = (p.interval.numerator, p.interval.denominator);
        }
        let locked = match &cfg.lock {
            Some(want) => lock_controls(&dev, &name, want)?,
            None => Vec::new(),
        };
        let queue =
            MmapQueue::new(dev.handle(), Direction::Capture, cfg.buffers.max(2)).map_err(|e| {
                CaptureError::from_io(&name, "allocating mmap buffers (VIDIOC_REQBUFS)", e)
            })?;
        tracing::info!(device = %name, format = %negotiated.format, width = negotiated.width, height = negotiated.height, stride = negotiated.stride, buffers = queue.len(), locked = locked.len(), "V4L2 source open");
        Ok(V4l2Source {
            path: path.to_path_buf(),
            name,
            info,
            negotiated,
            locked,
            queue,
            dev: Dev(dev),
            dropped: 0,
            dead: false,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Identity, bus and formats of the device.
    pub fn device_info(&self) -> &DeviceInfo {
        &self.info
    }

    /// The format in use.
    pub fn negotiated(&self) -> Negotiated {
        self.negotiated
    }

    /// The controls that were locked, with the values the driver accepted.
    pub fn locked_controls(&self) -> &[ControlSetting] {
        &self.locked
    }

    /// All controls with their current values.
    pub fn controls(&self) -> Result<Vec<ControlInfo>, CaptureError> {
        list_controls(&self.dev.0, &self.name)
    }

    /// Frames dropped because they were corrupt (driver error flag, bad JPEG, short frame).
    pub fn dropped_frames(&self) -> u64 {
        self.dropped
    }

    fn io(&mut self, context: &str, e: std::io::Error) -> CaptureError {
        let err = CaptureError::from_io(&self.name, context, e);
        if matches!(err, CaptureError::Unplugged { .. }) {
            self.dead = true;
        }
        err
    }

    fn start(&mut self) -> Result<(), CaptureError> {
        for i in 0..self.queue.len() {
            if !self.queue.is_queued(i) {
                self.queue
                    .queue(i, 0)
                    .map_err(|e| self.io("queueing a buffer (VIDIOC_QBUF)", e))?;
            }
        }
        self.queue
            .stream_on()
            .map_err(|e| self.io("starting the stream (VIDIOC_STREAMON)", e))
    }
}

fn negotiate(
    dev: &Device,
    name: &str,
    info: &DeviceInfo,
    cfg: &V4l2Config,
) -> Result<Negotiated, CaptureError> {
    let current =
        Capture::format(dev).map_err(|e| CaptureError::from_io(name, "VIDIOC_G_FMT", e))?;
    let offered: Vec<(PixelFormat, &FormatInfo)> = info
        .formats
        .iter()
        .filter_map(|f| {
            let code: [u8; 4] = f.fourcc.as_bytes().try_into().ok()?;
            Some((PixelFormat::from_fourcc(code)?, f))
        })
        .collect();
    let size_ok = |f: &FormatInfo| match (cfg.width, cfg.height) {
        (Some(w), Some(h)) => {
            f.sizes.contains(w, h) || f.sizes == FrameSizes::Discrete { sizes: vec![] }
        }
        _ => true,
    };
    let chosen =
        match cfg.format {
            Some(want) => offered.iter().find(|(p, _)| *p == want).ok_or_else(|| {
                CaptureError::Unsupported {
                    device: name.to_string(),
                    reason: format!(
                        "format {want} not offered (offers: {})",
                        info.formats
                            .iter()
                            .map(|f| f.fourcc.trim_end())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                }
            })?,
            None => PixelFormat::ALL
                .iter()
                .find_map(|p| offered.iter().find(|(q, f)| q == p && size_ok(f)))
                .ok_or_else(|| CaptureError::Unsupported {
                    device: name.to_string(),
                    reason: format!(
                        "no format cubecal can convert at the requested size (offers: {})",
                        info.formats
                            .iter()
                            .map(|f| f.fourcc.trim_end())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                })?,
        };
    let (format, _) = *chosen;
    let mut want = current;
    want.width = cfg.width.unwrap_or(current.width);
    want.height = cfg.height.unwrap_or(current.height);
    want.fourcc = FourCC::new(&format.fourcc());
    want.field_order = v4l::format::FieldOrder::Progressive;
    want.stride = 0; // natural stride; vivid keeps a stale one otherwise
    want.size = 0;
    let got = Capture::set_format(dev, &want)
        .map_err(|e| CaptureError::from_io(name, "setting the format (VIDIOC_S_FMT)", e))?;
    if got.fourcc != want.fourcc {
        return Err(CaptureError::Unsupported {
            device: name.to_string(),
            reason: format!("asked for {format}, driver chose {}", got.fourcc),
        });
    }
    if (cfg.width.is_some() && got.width != want.width)
        || (cfg.height.is_some() && got.height != want.height)
    {
        return Err(CaptureError::Unsupported {
            device: name.to_string(),
            reason: format!(
                "asked for {}x{}, driver chose {}x{}",
                want.width, want.height, got.width, got.height
            ),
        });
    }
    if let Some(min) = format.min_stride(got.width)
        && (got.stride as usize) < min
    {
        return Err(CaptureError::Unsupported {
            device: name.to_string(),
            reason: format!(
                "driver stride {} is smaller than a {format} row ({min} bytes)",
                got.stride
            ),
        });
    }
    Ok(Negotiated {
        format,
        width: got.width,
        height: got.height,
        stride: got.stride,
        size_image: got.size,
        interval: (0, 0),
    })
}

impl FrameSource for V4l2Source {
    fn describe(&self) -> SourceInfo {
        SourceInfo {
            identity: self.info.identity(),
            name: format!("{} ({})", self.info.card, self.name),
            width: self.negotiated.width,
            height: self.negotiated.height,
            format: self.negotiated.format.to_string(),
        }
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, CaptureError> {
        if self.dead {
            return Err(CaptureError::Unplugged {
                device: self.name.clone(),
                context: "grabbing (the device went away earlier)".into(),
                source: std::io::Error::from_raw_os_error(19),
            });
        }
        let deadline = Instant::now() + timeout;
        if !self.queue.is_streaming() {
            self.start()?;
        }
        loop {
            let now = Instant::now();
            if now >= deadline {
                return Err(CaptureError::Timeout {
                    source_name: self.name.clone(),
                    timeout,
                });
            }
            let ready = self
                .queue
                .wait(deadline - now)
                .map_err(|e| self.io("waiting for a frame (poll)", e))?;
            if !ready {
                continue; // the deadline check above ends the loop
            }
            let Some(d) = self
                .queue
                .dequeue()
                .map_err(|e| self.io("dequeueing a frame (VIDIOC_DQBUF)", e))?
            else {
                continue; // spurious wake-up
            };
            let n = self.negotiated;
            let result = if d.flags & BUF_FLAG_ERROR != 0 {
                Err(None)
            } else {
                let data = &self.queue.buffer(d.index)[..d.bytesused];
                convert::to_gray(n.format, n.width, n.height, n.stride as usize, data).map_err(Some)
            };
            // hand the buffer back before anything else, so that an error never starves the queue
            self.queue
                .queue(d.index, 0)
                .map_err(|e| self.io("re-queueing a buffer (VIDIOC_QBUF)", e))?;
            match result {
                Ok(image) => {
                    return Ok(Frame {
                        sequence: u64::from(d.sequence),
                        timestamp: d.timestamp,
                        image,
                    });
                }
                Err(reason) => {
                    self.dropped += 1;
                    match reason {
                        Some(e) => {
                            tracing::warn!(device = %self.name, sequence = d.sequence, error = %e, dropped = self.dropped, "corrupt frame dropped")
                        }
                        None => {
                            tracing::warn!(device = %self.name, sequence = d.sequence, dropped = self.dropped, "driver flagged frame as corrupt; dropped")
                        }
                    }
                }
            }
        }
    }

    fn flush(&mut self) -> Result<usize, CaptureError> {
        if !self.queue.is_streaming() {
            return Ok(0);
        }
        let mut dropped = 0;
        // only what is queued now: at most one pass over the buffers, so a fast camera cannot keep
        // this loop busy forever
        for _ in 0..self.queue.len() {
            let ready = self
                .queue
                .wait(Duration::ZERO)
                .map_err(|e| self.io("poll", e))?;
            if !ready {
                break;
            }
            match self
                .queue
                .dequeue()
                .map_err(|e| self.io("flushing (VIDIOC_DQBUF)", e))?
            {
                Some(d) => {
                    self.queue
                        .queue(d.index, 0)
                        .map_err(|e| self.io("re-queueing a buffer (VIDIOC_QBUF)", e))?;
                    dropped += 1;
                }
                None => break,
            }
        }
        Ok(dropped)
    }
}

/// Feeds raw frames to a V4L2 output device (mmap). Frames must already be in the negotiated format
/// and stride (see [`convert::encode_gray`]).
#[derive(Debug)]
pub struct V4l2Output {
    name: String,
    negotiated: Negotiated,
    queue: MmapQueue,
    _dev: Dev,
    next_fresh: usize,
}

impl V4l2Output {
    /// Open an output node and set its format (stride chosen by the driver).
    pub fn open(
        path: &Path,
        format: PixelFormat,
        width: u32,
        height: u32,
        buffers: u32,
    ) -> Result<V4l2Output, CaptureError> {
        let (name, dev, caps) = discover::open_device(path)?;
        if !caps.capabilities.contains(Flags::VIDEO_OUTPUT) {
            return Err(CaptureError::Unsupported {
                device: name,
                reason: "not a video output device".into(),
            });
        }
        let mut f =
            Output::format(&dev).map_err(|e| CaptureError::from_io(&name, "VIDIOC_G_FMT", e))?;
        f.width = width;
        f.height = height;
        f.fourcc = FourCC::new(&format.fourcc());
        f.field_order = v4l::format::FieldOrder::Progressive;
        f.stride = 0;
        f.size = 0;
        let got = Output::set_format(&dev, &f).map_err(|e| {
            CaptureError::from_io(&name, "setting the output format (VIDIOC_S_FMT)", e)
        })?;
        if got.fourcc != f.fourcc || got.width != width || got.height != height {
            return Err(CaptureError::Unsupported {
                device: name,
                reason: format!(
                    "output format {format} {width}x{height} refused, driver chose {got}"
                ),
            });
        }
        let queue = MmapQueue::new(dev.handle(), Direction::Output, buffers.max(2))
            .map_err(|e| CaptureError::from_io(&name, "allocating output buffers", e))?;
        Ok(V4l2Output {
            name,
            negotiated: Negotiated {
                format,
                width: got.width,
                height: got.height,
                stride: got.stride,
                size_image: got.size,
                interval: (0, 0),
            },
            queue,
            _dev: Dev(dev),
            next_fresh: 0,
        })
    }

    pub fn negotiated(&self) -> Negotiated {
        self.negotiated
    }

    /// Queue one frame, waiting at most `timeout` for a free buffer. Streaming starts once every buffer
    /// holds a frame.
    pub fn write(&mut self, frame: &[u8], timeout: Duration) -> Result<(), CaptureError> {
        let index =
            if self.next_fresh < self.queue.len() {
                self.next_fresh += 1;
                self.next_fresh - 1
            } else {
                let deadline = Instant::now() + timeout;
                loop {
                    let now = Instant::now();
                    if now >= deadline {
                        return Err(CaptureError::Timeout {
                            source_name: self.name.clone(),
                            timeout,
                        });
                    }
                    let ready = self
                        .queue
                        .wait(deadline - now)
                        .map_err(|e| CaptureError::from_io(&self.name, "poll (output)", e))?;
                    if !ready {
                        continue;
                    }
                    if let Some(d) = self.queue.dequeue().map_err(|e| {
                        CaptureError::from_io(&self.name, "VIDIOC_DQBUF (output)", e)
                    })? {
                        break d.index;
                    }
                }
            };
        let buf = self.queue.buffer_mut(index);
        let n = frame.len().min(buf.len());
        buf[..n].copy_from_slice(&frame[..n]);
        self.queue
            .queue(index, n as u32)
            .map_err(|e| CaptureError::from_io(&self.name, "VIDIOC_QBUF (output)", e))?;
        if !self.queue.is_streaming() && self.next_fresh == self.queue.len() {
            self.queue
                .stream_on()
                .map_err(|e| CaptureError::from_io(&self.name, "VIDIOC_STREAMON (output)", e))?;
        }
        Ok(())
    }
}

/// Turn on vivid's output→capture loop on its capture node `path`: "Loop Video" on and "OSD Text
/// Mode" None (otherwise vivid draws text over the looped image). Frames written to the paired output
/// node then come back on this node when both use the same size and format (tests/vm/, and
/// /work/shared/reference/v4l2-vm/README.md for the measured recipe).
pub fn enable_vivid_loop(path: &Path) -> Result<(), CaptureError> {
    let (name, dev, _) = discover::open_device(path)?;
    let controls = list_controls(&dev, &name)?;
    for (control, value) in [("Loop Video", 1), ("OSD Text Mode", 2)] {
        let info = controls.iter().find(|c| c.name == control).ok_or_else(|| {
            CaptureError::Unsupported {
                device: name.clone(),
                reason: format!("no '{control}' control: not a vivid capture node"),
            }
        })?;
        let set = set_control(&dev, &name, info, value)?;
        if set.accepted != value {
            return Err(CaptureError::Unsupported {
                device: name.clone(),
                reason: format!("'{control}' set to {value} reads back {}", set.accepted),
            });
        }
    }
    Ok(())
}
