//! `cubecal devices` and `cubecal record`.
//!
//! ## `cubecal devices`
//! Lists every V4L2 node that can capture video: path, driver, card, bus, USB vendor:product and serial
//! (from sysfs), and the formats cubecal can convert with their sizes (the others are counted). `--json`
//! prints one JSON object `{"devices": [...], "skipped": [...]}` with every format.
//!
//! **Exit codes:** 0 when at least one capture device was found; **4 (`exit::DEVICE`) when there is
//! none** — the message says so ("no V4L2 capture devices found") and, for nodes that exist but could
//! not be opened, why (permission: add the user to the `video` group; busy: another program). A station
//! script can therefore test `cubecal devices >/dev/null` for "a camera is present".
//!
//! ## `cubecal record`
//! Opens the camera with locked controls, records `--frames` frames into a session directory
//! (PNG frames + `manifest.json`, see `cubecal::capture::session`) and prints a summary. Device
//! problems exit 4, an unusable output directory 3.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use cubecal::capture::convert::PixelFormat;
use cubecal::capture::session::{RigRef, SessionHeader, SessionWriter};
use cubecal::capture::v4l2::{self, DeviceInfo, FrameSizes, LockSettings, V4l2Config, V4l2Source};
use cubecal::capture::{CaptureError, FrameSource};
use cubecal::exit;

use super::Output;

#[derive(Debug, clap::Args)]
pub struct DevicesArgs {}

#[derive(Debug, clap::Args)]
pub struct RecordArgs {
    /// V4L2 device node, e.g. /dev/video0.
    #[arg(long)]
    pub device: std::path::PathBuf,
    /// Output session directory (created; must not already hold a session).
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// Number of frames to record.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: u32,
    /// Frame width (default: the device's current width).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub width: Option<u32>,
    /// Frame height (default: the device's current height).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub height: Option<u32>,
    /// Pixel format FourCC (GREY, Y16, YUYV, UYVY, NV12, RGB3, BGR3, XR24, MJPG); default: best offered.
    #[arg(long, value_parser = parse_format)]
    pub format: Option<PixelFormat>,
    /// Requested frame rate.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub fps: Option<u32>,
    /// Per-frame timeout in milliseconds.
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout_ms: u64,
    /// Fixed focus value (default: the value when autofocus is switched off).
    #[arg(long)]
    pub focus: Option<i64>,
    /// Fixed exposure, driver units (UVC: 100 µs).
    #[arg(long)]
    pub exposure: Option<i64>,
    /// Fixed gain.
    #[arg(long)]
    pub gain: Option<i64>,
    /// Fixed white balance temperature in kelvin.
    #[arg(long)]
    pub white_balance_k: Option<i64>,
    /// Fixed zoom.
    #[arg(long)]
    pub zoom: Option<i64>,
    /// Leave the camera's automatic controls alone (not for calibration).
    #[arg(long)]
    pub no_lock: bool,
    /// Rig description file to note in the manifest.
    #[arg(long)]
    pub rig: Option<PathBuf>,
}

/// A FourCC cubecal converts, checked while parsing (before any device is opened).
fn parse_format(f: &str) -> Result<PixelFormat, String> {
    let mut code = [b' '; 4];
    if f.len() > 4 {
        return Err(format!("'{f}' is not a FourCC (at most 4 characters)"));
    }
    for (c, b) in code.iter_mut().zip(f.to_ascii_uppercase().bytes()) {
        *c = b;
    }
    PixelFormat::from_fourcc(code).ok_or_else(|| {
        format!(
            "cubecal converts only {}",
            PixelFormat::ALL.map(|p| p.to_string()).join(", ")
        )
    })
}

fn sizes_text(s: &FrameSizes) -> String {
    match s {
        FrameSizes::Discrete { sizes } if sizes.is_empty() => "sizes unknown".into(),
        FrameSizes::Discrete { sizes } => sizes
            .iter()
            .map(|(w, h)| format!("{w}x{h}"))
            .collect::<Vec<_>>()
            .join(" "),
        FrameSizes::Stepwise { min, max, step } => format!(
            "{}x{} .. {}x{} step {}x{}",
            min.0, min.1, max.0, max.1, step.0, step.1
        ),
    }
}

/// Human-readable description of one device (also used by the VM test through the library types).
fn device_text(d: &DeviceInfo) -> String {
    let mut s = format!(
        "{}: {} (driver {}, bus {})\n  identity: {}\n",
        d.path.display(),
        d.card,
        d.driver,
        d.bus,
        d.identity()
    );
    if let Some(u) = &d.usb {
        s += &format!(
            "  usb: {}:{} serial {} {}\n",
            u.vendor,
            u.product,
            u.serial.as_deref().unwrap_or("(none)"),
            [u.manufacturer.as_deref(), u.product_name.as_deref()]
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    let others = d.formats.iter().filter(|f| !f.supported).count();
    for f in d.formats.iter().filter(|f| f.supported) {
        s += &format!(
            "  {:<4} {:<28} {}\n",
            f.fourcc.trim_end(),
            f.description,
            sizes_text(&f.sizes)
        );
    }
    if others > 0 {
        s += &format!("  (+ {others} formats cubecal cannot convert; `--json` lists all)\n");
    }
    s
}

fn hint(e: &CaptureError) -> &'static str {
    let kind = match e {
        CaptureError::Open { source, .. } => Some(source.kind()),
        _ => None,
    };
    match kind {
        Some(std::io::ErrorKind::PermissionDenied) => {
            " (permission denied: add the user to the 'video' group or install cubecal's udev rule)"
        }
        Some(std::io::ErrorKind::NotFound) => " (the node disappeared while listing)",
        _ => "",
    }
}

pub fn run_devices(_args: DevicesArgs, out: Output) -> anyhow::Result<u8> {
    let (devices, skipped) = v4l2::discover();
    let code = if devices.is_empty() {
        exit::DEVICE
    } else {
        exit::SUCCESS
    };
    let mut w = std::io::stdout().lock();
    if out.json {
        let skipped: Vec<_> = skipped
            .iter()
            .map(|s| serde_json::json!({"path": s.path, "error": error_chain(&s.error)}))
            .collect();
        writeln!(
            w,
            "{}",
            serde_json::json!({ "devices": devices, "skipped": skipped })
        )?;
        return Ok(code);
    }
    for d in &devices {
        writeln!(w, "{}", device_text(d))?;
    }
    let mut e = std::io::stderr().lock();
    for s in &skipped {
        writeln!(e, "warning: {}{}", error_chain(&s.error), hint(&s.error))?;
    }
    if devices.is_empty() {
        writeln!(
            e,
            "no V4L2 capture devices found ({} /dev/video* node(s) present{}); connect a camera and check `dmesg`",
            v4l2::video_nodes(std::path::Path::new("/dev")).len(),
            if skipped.is_empty() {
                ""
            } else {
                ", see the warnings above"
            }
        )?;
    }
    Ok(code)
}

fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s += &format!(": {c}");
        cur = c.source();
    }
    s
}

pub fn run_record(args: RecordArgs, out: Output) -> anyhow::Result<u8> {
    let format = args.format;
    let cfg = V4l2Config {
        width: args.width,
        height: args.height,
        format,
        fps: args.fps,
        buffers: 4,
        lock: (!args.no_lock).then_some(LockSettings {
            focus: args.focus,
            exposure: args.exposure,
            gain: args.gain,
            white_balance_k: args.white_balance_k,
            zoom: args.zoom,
        }),
    };
    let mut src = V4l2Source::open(&args.device, &cfg)?;
    let header = SessionHeader {
        source: src.describe(),
        device: Some(src.device_info().clone()),
        capture: Some(src.negotiated()),
        controls: src.locked_controls().to_vec(),
        rig: args.rig.as_ref().map(|p| RigRef {
            path: Some(p.clone()),
            name: None,
        }),
        config: serde_json::to_value(&cfg)?,
    };
    let mut writer = SessionWriter::create(&args.out, header)?;
    let timeout = Duration::from_millis(args.timeout_ms);
    for i in 0..args.frames {
        let frame = src
            .grab(timeout)
            .with_context(|| format!("recording frame {} of {}", i + 1, args.frames))?;
        writer.add_frame(&frame, None)?;
        tracing::info!(frame = i, sequence = frame.sequence, "recorded");
    }
    let manifest = writer.finish()?;
    let n = src.negotiated();
    let mut w = std::io::stdout().lock();
    if out.json {
        writeln!(
            w,
            "{}",
            serde_json::json!({
                "session": args.out, "manifest": manifest, "frames": args.frames,
                "source": src.describe(), "capture": n, "controls": src.locked_controls(),
                "dropped_corrupt": src.dropped_frames(),
            })
        )?;
    } else {
        writeln!(
            w,
            "recorded {} frames from {} ({} {}x{}, stride {}) to {}",
            args.frames,
            args.device.display(),
            n.format,
            n.width,
            n.height,
            n.stride,
            args.out.display()
        )?;
        for c in src.locked_controls() {
            writeln!(
                w,
                "  locked {:<32} requested {:>6}  accepted {:>6}",
                c.name, c.requested, c.accepted
            )?;
        }
        if src.dropped_frames() > 0 {
            writeln!(w, "  dropped {} corrupt frame(s)", src.dropped_frames())?;
        }
    }
    Ok(exit::SUCCESS)
}
