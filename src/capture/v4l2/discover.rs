//! Device discovery: every `/dev/video*` node that can capture video, with its identity (driver, card,
//! bus, and for USB cameras vendor:product and serial from sysfs) and the formats and sizes it offers.

use std::path::{Path, PathBuf};

use v4l::capability::Flags;
use v4l::device::Device;
use v4l::framesize::FrameSizeEnum;
use v4l::video::Capture;

use crate::capture::CaptureError;
use crate::capture::convert::PixelFormat;

/// USB identity read from sysfs.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct UsbId {
    /// `idVendor`, 4 hex digits.
    pub vendor: String,
    /// `idProduct`, 4 hex digits.
    pub product: String,
    pub serial: Option<String>,
    pub manufacturer: Option<String>,
    pub product_name: Option<String>,
}

/// A frame size a format offers.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum FrameSizes {
    Discrete {
        sizes: Vec<(u32, u32)>,
    },
    Stepwise {
        min: (u32, u32),
        max: (u32, u32),
        step: (u32, u32),
    },
}

impl FrameSizes {
    /// Whether `width × height` is offered.
    pub fn contains(&self, width: u32, height: u32) -> bool {
        match self {
            FrameSizes::Discrete { sizes } => sizes.contains(&(width, height)),
            FrameSizes::Stepwise { min, max, step } => {
                let ok = |v: u32, lo: u32, hi: u32, st: u32| {
                    v >= lo && v <= hi && (st == 0 || (v - lo).is_multiple_of(st))
                };
                ok(width, min.0, max.0, step.0) && ok(height, min.1, max.1, step.1)
            }
        }
    }

    /// The largest offered size (by pixel count).
    pub fn largest(&self) -> Option<(u32, u32)> {
        match self {
            FrameSizes::Discrete { sizes } => sizes.iter().copied().max_by_key(|(w, h)| w * h),
            FrameSizes::Stepwise { max, .. } => Some(*max),
        }
    }
}

/// One format a device offers.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct FormatInfo {
    /// FourCC, e.g. "YUYV".
    pub fourcc: String,
    pub description: String,
    /// Whether cubecal can convert it.
    pub supported: bool,
    pub sizes: FrameSizes,
}

/// A capture-capable V4L2 device node.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DeviceInfo {
    pub path: PathBuf,
    pub driver: String,
    pub card: String,
    pub bus: String,
    pub usb: Option<UsbId>,
    pub formats: Vec<FormatInfo>,
}

impl DeviceInfo {
    /// Stable identity: `usb:VVVV:PPPP:SERIAL` for USB cameras with a serial number, otherwise
    /// `v4l2:<driver>:<bus>:<card>` (which does not survive moving the camera to another port).
    pub fn identity(&self) -> String {
        match &self.usb {
            Some(u) => format!(
                "usb:{}:{}:{}",
                u.vendor,
                u.product,
                u.serial.as_deref().unwrap_or("no-serial")
            ),
            None => format!("v4l2:{}:{}:{}", self.driver, self.bus, self.card),
        }
    }
}

/// A node that exists but could not be inspected (permission, busy, …).
#[derive(Debug)]
pub struct SkippedNode {
    pub path: PathBuf,
    pub error: CaptureError,
}

/// The `/dev/video*` nodes, in numeric order.
pub fn video_nodes(dev_dir: &Path) -> Vec<PathBuf> {
    let mut nodes: Vec<(u32, PathBuf)> = std::fs::read_dir(dev_dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let n = name.strip_prefix("video")?.parse::<u32>().ok()?;
            Some((n, e.path()))
        })
        .collect();
    nodes.sort();
    nodes.into_iter().map(|(_, p)| p).collect()
}

/// Discover every capture-capable node under `/dev`. Nodes that cannot capture (output, metadata, …)
/// are left out; nodes that cannot be opened are returned in the second list with their error.
pub fn discover() -> (Vec<DeviceInfo>, Vec<SkippedNode>) {
    let mut found = Vec::new();
    let mut skipped = Vec::new();
    for path in video_nodes(Path::new("/dev")) {
        match inspect(&path) {
            Ok(Some(info)) => found.push(info),
            Ok(None) => tracing::debug!(path = %path.display(), "not a video capture node"),
            Err(error) => skipped.push(SkippedNode { path, error }),
        }
    }
    (found, skipped)
}

/// Open a device node and query its capabilities; errors name the node.
pub(crate) fn open_device(
    path: &Path,
) -> Result<(String, Device, v4l::capability::Capabilities), CaptureError> {
    let name = path.display().to_string();
    let dev = Device::with_path(path).map_err(|e| CaptureError::Open {
        device: name.clone(),
        source: e,
    })?;
    let caps = dev
        .query_caps()
        .map_err(|e| CaptureError::from_io(&name, "VIDIOC_QUERYCAP", e))?;
    Ok((name, dev, caps))
}

/// Inspect one node; `Ok(None)` when it cannot capture single-planar video.
pub fn inspect(path: &Path) -> Result<Option<DeviceInfo>, CaptureError> {
    let (name, dev, caps) = open_device(path)?;
    if !caps.capabilities.contains(Flags::VIDEO_CAPTURE) {
        return Ok(None);
    }
    let formats = list_formats(&dev, &name)?;
    Ok(Some(DeviceInfo {
        path: path.to_path_buf(),
        driver: caps.driver,
        card: caps.card,
        bus: caps.bus,
        usb: usb_identity(path),
        formats,
    }))
}

pub(crate) fn list_formats(dev: &Device, name: &str) -> Result<Vec<FormatInfo>, CaptureError> {
    let descs = Capture::enum_formats(dev)
        .map_err(|e| CaptureError::from_io(name, "VIDIOC_ENUM_FMT", e))?;
    let mut out = Vec::with_capacity(descs.len());
    for d in descs {
        let sizes = Capture::enum_framesizes(dev, d.fourcc).unwrap_or_default();
        let mut discrete = Vec::new();
        let mut stepwise = None;
        for s in sizes {
            match s.size {
                FrameSizeEnum::Discrete(x) => discrete.push((x.width, x.height)),
                FrameSizeEnum::Stepwise(x) => {
                    stepwise = Some(FrameSizes::Stepwise {
                        min: (x.min_width, x.min_height),
                        max: (x.max_width, x.max_height),
                        step: (x.step_width, x.step_height),
                    })
                }
            }
        }
        out.push(FormatInfo {
            fourcc: String::from_utf8_lossy(&d.fourcc.repr).into_owned(),
            description: d.description,
            supported: PixelFormat::from_fourcc(d.fourcc.repr).is_some(),
            sizes: stepwise.unwrap_or(FrameSizes::Discrete { sizes: discrete }),
        });
    }
    Ok(out)
}

/// USB vendor/product/serial of the device behind `/dev/videoN`, from
/// `/sys/class/video4linux/videoN/device` (the USB interface) and its ancestors (the USB device).
pub fn usb_identity(node: &Path) -> Option<UsbId> {
    let name = node.file_name()?.to_str()?;
    let dev = std::fs::canonicalize(
        Path::new("/sys/class/video4linux")
            .join(name)
            .join("device"),
    )
    .ok()?;
    let read = |dir: &Path, f: &str| -> Option<String> {
        let s = std::fs::read_to_string(dir.join(f)).ok()?;
        let s = s.trim();
        (!s.is_empty()).then(|| s.to_string())
    };
    // the interface directory is usually one level below the device that has idVendor
    dev.ancestors().take(4).find_map(|dir| {
        Some(UsbId {
            vendor: read(dir, "idVendor")?,
            product: read(dir, "idProduct")?,
            serial: read(dir, "serial"),
            manufacturer: read(dir, "manufacturer"),
            product_name: read(dir, "product"),
        })
    })
}
