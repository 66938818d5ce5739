//! `V4l2Source` against a REAL kernel driver: vivid, inside the qemu guest booted by `tests/vm/run.sh`.
//!
//! Every test here is `#[ignore]`d, so a plain `cargo test` on a machine without vivid reports them as
//! ignored (not passed). The VM harness runs them with `--ignored`; there a missing device or
//! environment variable FAILS the test, it never skips.
//!
//! Environment (set by `tests/vm/guest.sh`):
//! - `CUBECAL_VIVID_WEBCAM`: vivid webcam capture node
//! - `CUBECAL_VIVID_HDMI_CAP` / `CUBECAL_VIVID_HDMI_OUT`: vivid HDMI capture + output (loop_video)
//! - `CUBECAL_VIVID_UNPLUG`: a second webcam node, disconnected by the unplug test
//! - `CUBECAL_VM_OUT` (optional): directory for evidence (captured PNGs)
//! - `CUBECAL_VM_RENDER`: a host-rendered rig frame (`frame_000.png`/`.json`) and its `rig.toml`
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout)]

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::time::{Duration, Instant};

use cubecal::capture::convert::{PixelFormat, encode_gray};
use cubecal::capture::session::{ReplaySource, SessionHeader, SessionWriter};
use cubecal::capture::v4l2::{
    self, LockSettings, V4l2Config, V4l2Output, V4l2Source, list_controls, set_control,
};
use cubecal::capture::{CaptureError, FrameSource, GrayImage, check_contract};

const IGNORE: &str = "needs the vivid driver: run by tests/vm/run.sh";

fn env_path(var: &str) -> PathBuf {
    match std::env::var_os(var) {
        Some(p) => PathBuf::from(p),
        None => panic!("{var} is not set: this test runs inside the VM (tests/vm/run.sh)"),
    }
}

fn result(name: &str, ok: bool, detail: &str) {
    println!(
        "RESULT: {name} {} {detail}",
        if ok { "PASS" } else { "FAIL" }
    );
}

fn set_named(dev: &v4l::Device, path: &str, name: &str, value: i64) -> i64 {
    let ctrls = list_controls(dev, path).unwrap();
    let c = ctrls
        .iter()
        .find(|c| c.name == name)
        .unwrap_or_else(|| panic!("{path}: no control {name:?}"));
    set_control(dev, path, c, value).unwrap().accepted
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_discovery_lists_capture_nodes_only() {
    let _ = IGNORE;
    let (devs, skipped) = v4l2::discover();
    for d in &devs {
        println!(
            "found {} driver={} card={:?} bus={} identity={} formats={}",
            d.path.display(),
            d.driver,
            d.card,
            d.bus,
            d.identity(),
            d.formats.len()
        );
    }
    assert!(skipped.is_empty(), "skipped nodes: {skipped:?}");
    let paths: Vec<_> = devs.iter().map(|d| d.path.clone()).collect();
    for var in ["CUBECAL_VIVID_WEBCAM", "CUBECAL_VIVID_HDMI_CAP"] {
        assert!(
            paths.contains(&env_path(var)),
            "{var} not discovered: {paths:?}"
        );
    }
    assert!(
        !paths.contains(&env_path("CUBECAL_VIVID_HDMI_OUT")),
        "an output-only node was listed"
    );
    assert!(devs.iter().all(|d| d.driver == "vivid"));
    let webcam = devs
        .iter()
        .find(|d| d.path == env_path("CUBECAL_VIVID_WEBCAM"))
        .unwrap();
    let yuyv = webcam.formats.iter().find(|f| f.fourcc == "YUYV").unwrap();
    assert!(yuyv.supported && yuyv.sizes.contains(640, 480), "{yuyv:?}");
    result("discovery", true, &format!("{} capture nodes", devs.len()));
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_webcam_negotiates_formats_and_honours_stride() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    // 640x360 then 320x180: vivid keeps a stale (wider) stride unless S_FMT asks for the natural one
    let cases = [
        (PixelFormat::Yuyv, 640, 360),
        (PixelFormat::Yuyv, 320, 180),
        (PixelFormat::Grey, 640, 480),
        (PixelFormat::Rgb3, 640, 480),
        (PixelFormat::Bgr3, 320, 180),
        (PixelFormat::Xr24, 320, 180),
        (PixelFormat::Uyvy, 320, 180),
        (PixelFormat::Nv12, 320, 180),
        (PixelFormat::Y16, 320, 180),
    ];
    let mut failed = Vec::new();
    for (format, w, h) in cases {
        let cfg = V4l2Config {
            width: Some(w),
            height: Some(h),
            format: Some(format),
            fps: Some(30),
            buffers: 3,
            lock: None,
        };
        let r = V4l2Source::open(&path, &cfg).and_then(|mut src| {
            let n = src.negotiated();
            let a = src.grab(Duration::from_secs(5))?;
            let b = src.grab(Duration::from_secs(5))?;
            Ok((n, a, b))
        });
        match r {
            Ok((n, a, b)) => {
                let ok = n.format == format
                    && (n.width, n.height) == (w, h)
                    && a.image.dimensions() == (w, h)
                    && b.sequence > a.sequence
                    && b.timestamp > a.timestamp
                    && n.stride as usize == format.min_stride(w).unwrap();
                let detail = format!(
                    "{w}x{h} stride {} interval {}/{} seq {}->{}",
                    n.stride, n.interval.0, n.interval.1, a.sequence, b.sequence
                );
                result(&format!("webcam_format_{format}"), ok, &detail);
                if !ok {
                    failed.push(format!("{format}: {detail}"));
                }
            }
            Err(e) => {
                result(&format!("webcam_format_{format}"), false, &e.to_string());
                failed.push(format!("{format}: {e}"));
            }
        }
    }
    assert!(failed.is_empty(), "{failed:?}");
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_webcam_controls_listed_set_read_back_and_locked() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let name = path.display().to_string();
    let dev = v4l::Device::with_path(&path).unwrap();
    let ctrls = list_controls(&dev, &name).unwrap();
    println!(
        "{} controls: {:?}",
        ctrls.len(),
        ctrls.iter().map(|c| c.name.as_str()).collect::<Vec<_>>()
    );
    assert!(ctrls.len() > 10);
    assert_eq!(set_named(&dev, &name, "Brightness", 200), 200);
    assert_eq!(set_named(&dev, &name, "Brightness", 128), 128);
    // clamping is reported, not hidden: vivid's brightness range is 0..255
    let b = ctrls.iter().find(|c| c.name == "Brightness").unwrap();
    let s = set_control(&dev, &name, b, b.maximum + 1000);
    println!("brightness beyond range: {s:?}");
    if let Ok(s) = s {
        assert_eq!(s.accepted, b.maximum);
    }
    set_named(&dev, &name, "Brightness", 128);
    drop(dev);

    let cfg = V4l2Config {
        width: Some(640),
        height: Some(480),
        format: Some(PixelFormat::Yuyv),
        fps: Some(30),
        buffers: 3,
        lock: Some(LockSettings {
            gain: Some(42),
            ..LockSettings::default()
        }),
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    let locked = src.locked_controls().to_vec();
    println!("locked: {locked:?}");
    let autogain = locked.iter().find(|c| c.id == 0x0098_0912);
    let gain = locked.iter().find(|c| c.id == 0x0098_0913);
    assert_eq!(
        autogain.map(|c| c.accepted),
        Some(0),
        "autogain not switched off"
    );
    assert_eq!(gain.map(|c| c.accepted), Some(42), "gain not fixed");
    let now = src.controls().unwrap();
    assert_eq!(
        now.iter()
            .find(|c| c.id == 0x0098_0913)
            .and_then(|c| c.value),
        Some(42)
    );
    src.grab(Duration::from_secs(5)).unwrap();
    result(
        "controls_lock",
        true,
        &format!("{} controls, locked {locked:?}", ctrls.len()),
    );
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_webcam_waits_have_deadlines_and_flush_drops_queued_frames() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let cfg = V4l2Config {
        width: Some(640),
        height: Some(480),
        format: Some(PixelFormat::Yuyv),
        fps: Some(5), // slow on purpose: a 200 ms frame interval
        buffers: 4,
        lock: None,
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    let interval = src.negotiated().interval;
    // vivid delivers a frame right at STREAMON; the next one is a frame interval (200 ms) away, so a
    // grab with a 2 ms deadline right after a frame must time out
    let first = src.grab(Duration::from_secs(5)).unwrap();
    let t = Instant::now();
    let r = src.grab(Duration::from_millis(2));
    let waited = t.elapsed();
    let r = r.map(|f| (f.sequence, f.timestamp.saturating_sub(first.timestamp)));
    assert!(
        matches!(r, Err(CaptureError::Timeout { .. })),
        "interval {interval:?}: {r:?}"
    );
    assert_eq!(
        r.as_ref().map_err(|e| e.exit_code()).err(),
        Some(cubecal::exit::DEVICE)
    );
    assert!(
        waited < Duration::from_millis(300),
        "timeout took {waited:?}"
    );
    // the stream is still usable after a timeout (the v4l crate's Stream is not)
    let a = src.grab(Duration::from_secs(5)).unwrap();
    let b = src.grab(Duration::from_secs(5)).unwrap();
    assert!(b.sequence > a.sequence);
    std::thread::sleep(Duration::from_millis(700)); // let ~3 frames queue up
    let flushed = src.flush().unwrap();
    let c = src.grab(Duration::from_secs(5)).unwrap();
    assert!(flushed >= 1, "flush dropped nothing");
    assert!(c.sequence > b.sequence + flushed as u64 - 1);
    result(
        "timeouts_and_flush",
        true,
        &format!(
            "interval {interval:?}; 2 ms grab -> Timeout after {waited:?}; flushed {flushed}; seq {} -> {}",
            b.sequence, c.sequence
        ),
    );
}

/// A rendered rig stand-in: a checkerboard with `square` px squares, shifted by `k` squares, with
/// mid-gray levels that survive every format exactly, and its inner corners (ground truth, pixel-centre
/// convention: a corner between pixels x-1 and x lies at x - 0.5).
fn checkerboard(w: u32, h: u32, square: u32, k: u32) -> (GrayImage, Vec<(f64, f64)>) {
    let img = GrayImage::from_fn(w, h, |x, y| {
        image::Luma([if (x / square + y / square + k).is_multiple_of(2) {
            220
        } else {
            30
        }])
    });
    let mut corners = Vec::new();
    for cy in 1..h.div_ceil(square) {
        for cx in 1..w.div_ceil(square) {
            corners.push((
                cx as f64 * square as f64 - 0.5,
                cy as f64 * square as f64 - 0.5,
            ));
        }
    }
    (img, corners)
}

/// Detect the corners in `captured` with the project's detector (X-corner front end, grid assembly,
/// sub-pixel fit and completion of the largest grid) and compare them with the ground truth `gt`:
/// every true corner must be found within [`LOOP_CORNER_TOLERANCE_PX`], and they must form one complete
/// grid.
fn detect_corners_and_compare_to_ground_truth(captured: &GrayImage, gt: &[(f64, f64)]) {
    let mut finder = cubecal::detect::CornerFinder::new().unwrap();
    let corners = finder.find(captured).unwrap();
    let grids = cubecal::detect::grid::assemble(&corners);
    let fitted: Vec<nalgebra::Vector2<f64>> = grids
        .first()
        .map(|g| {
            let lines = g.rows.max(g.cols) + 2;
            cubecal::detect::complete::complete(captured, &corners, g, lines)
                .cells
                .into_iter()
                .flatten()
                .map(|f| f.uv)
                .collect()
        })
        .unwrap_or_default();
    let mut worst = 0.0f64;
    let mut missing = 0;
    for &(x, y) in gt {
        let best = fitted
            .iter()
            .map(|uv| ((uv.x - x).powi(2) + (uv.y - y).powi(2)).sqrt())
            .fold(f64::INFINITY, f64::min);
        if best > 1.0 {
            missing += 1;
        } else {
            worst = worst.max(best);
        }
    }
    let largest = fitted.len();
    println!(
        "corner detector on the captured frame: {} of {} ground-truth corners found, max error {worst:.4} px, largest grid {largest} corners",
        gt.len() - missing,
        gt.len()
    );
    assert_eq!(missing, 0, "ground-truth corners not detected");
    assert!(
        worst < LOOP_CORNER_TOLERANCE_PX,
        "max corner error {worst} px"
    );
    assert_eq!(
        largest,
        gt.len(),
        "the corners do not form one complete grid"
    );
}

/// Corner error allowed on the looped (byte-exact) checkerboard.
const LOOP_CORNER_TOLERANCE_PX: f64 = 0.05;

/// The same comparison on the host, on the frames the VM test writes: the guest receives them byte-exact,
/// so this proves the detector half of the loop check wherever the VM cannot run.
#[test]
fn detector_finds_the_loop_checkerboards_exactly() {
    for k in 0..4 {
        let (img, gt) = checkerboard(1280, 720, 40, k);
        detect_corners_and_compare_to_ground_truth(&img, &gt);
    }
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_loop_rendered_checkerboard_is_captured_exactly() {
    let cap_path = env_path("CUBECAL_VIVID_HDMI_CAP");
    let out_path = env_path("CUBECAL_VIVID_HDMI_OUT");
    let cap_name = cap_path.display().to_string();
    {
        // vivid: loop the output into the capture, and no OSD text drawn over the looped image
        let dev = v4l::Device::with_path(&cap_path).unwrap();
        assert_eq!(set_named(&dev, &cap_name, "Loop Video", 1), 1);
        assert_eq!(set_named(&dev, &cap_name, "OSD Text Mode", 2), 2);
    }
    let formats = [
        PixelFormat::Yuyv,
        PixelFormat::Grey,
        PixelFormat::Rgb3,
        PixelFormat::Xr24,
        PixelFormat::Bgr3,
        PixelFormat::Uyvy,
        PixelFormat::Nv12,
    ];
    let required = [PixelFormat::Yuyv, PixelFormat::Grey, PixelFormat::Rgb3];
    let mut failed = Vec::new();
    for format in formats {
        match loop_one(&cap_path, &out_path, format) {
            Ok((exact, n, detail)) => {
                // the first frame(s) may still be vivid's own pattern from before the output started
                let ok = exact + 2 >= n;
                result(&format!("loop_{format}"), ok, &detail);
                if !ok && required.contains(&format) {
                    failed.push(format!("{format}: {detail}"));
                }
            }
            Err(e) => {
                result(&format!("loop_{format}"), false, &e.to_string());
                if required.contains(&format) {
                    failed.push(format!("{format}: {e}"));
                }
            }
        }
    }
    assert!(failed.is_empty(), "{failed:?}");
}

fn loop_one(
    cap_path: &std::path::Path,
    out_path: &std::path::Path,
    format: PixelFormat,
) -> Result<(usize, usize, String), CaptureError> {
    let cfg = V4l2Config {
        format: Some(format),
        buffers: 4,
        lock: None,
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(cap_path, &cfg)?;
    let n = src.negotiated();
    let mut out = V4l2Output::open(out_path, format, n.width, n.height, 4)?;
    let stride = out.negotiated().stride as usize;
    let boards: Vec<_> = (0..4)
        .map(|k| checkerboard(n.width, n.height, 40, k))
        .collect();
    let raw: Vec<Vec<u8>> = boards
        .iter()
        .map(|(g, _)| encode_gray(format, g, stride).unwrap())
        .collect();
    let stop = Arc::new(AtomicBool::new(false));
    let written = Arc::new(AtomicU32::new(0));
    let writer = {
        let (stop, written) = (stop.clone(), written.clone());
        std::thread::spawn(move || -> Result<(), CaptureError> {
            let mut i = 0;
            while !stop.load(Ordering::Relaxed) {
                out.write(&raw[i % raw.len()], Duration::from_secs(2))?;
                written.fetch_add(1, Ordering::Relaxed);
                i += 1;
            }
            Ok(())
        })
    };
    // start capturing once the output streams (frames captured before show vivid's own pattern)
    let t0 = Instant::now();
    while written.load(Ordering::Relaxed) < 6
        && t0.elapsed() < Duration::from_secs(10)
        && !writer.is_finished()
    {
        std::thread::sleep(Duration::from_millis(5));
    }
    let frames = 10;
    let mut matched = Vec::new();
    let mut worst = 0u8;
    let mut saved = false;
    let mut grab_err = None;
    for _ in 0..frames {
        match src.grab(Duration::from_secs(5)) {
            Ok(f) => {
                let m = boards.iter().position(|(b, _)| b == &f.image);
                if m.is_none() {
                    let d = boards
                        .iter()
                        .map(|(b, _)| {
                            b.as_raw()
                                .iter()
                                .zip(f.image.as_raw())
                                .map(|(x, y)| x.abs_diff(*y))
                                .max()
                                .unwrap_or(255)
                        })
                        .min()
                        .unwrap_or(255);
                    worst = worst.max(d);
                }
                if let Some(k) = m
                    && !saved
                {
                    detect_corners_and_compare_to_ground_truth(&f.image, &boards[k].1);
                    if let Some(dir) = std::env::var_os("CUBECAL_VM_OUT") {
                        let p = PathBuf::from(dir).join(format!("loop_{format}.png"));
                        let _ = f.image.save(&p);
                    }
                    saved = true;
                }
                matched.push(m.map_or(-1, |k| k as i32));
            }
            Err(e) => {
                grab_err = Some(e);
                break;
            }
        }
    }
    stop.store(true, Ordering::Relaxed);
    let w = writer.join().unwrap();
    if let Some(e) = grab_err {
        return Err(e);
    }
    w?;
    let exact = matched.iter().filter(|&&m| m >= 0).count();
    Ok((
        exact,
        frames,
        format!(
            "{}x{} stride {}: {exact}/{frames} captured frames equal a written frame (pattern index per frame {matched:?}, worst non-exact max|diff| {worst}), {} written",
            n.width,
            n.height,
            n.stride,
            written.load(Ordering::Relaxed)
        ),
    ))
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_recorded_session_replays_identically() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let dir = tempfile::tempdir().unwrap();
    let cfg = V4l2Config {
        width: Some(320),
        height: Some(180),
        format: Some(PixelFormat::Yuyv),
        fps: Some(30),
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    let header = SessionHeader {
        source: src.describe(),
        device: Some(src.device_info().clone()),
        capture: Some(src.negotiated()),
        controls: src.locked_controls().to_vec(),
        rig: None,
        config: serde_json::to_value(&cfg).unwrap(),
    };
    let mut w = SessionWriter::create(dir.path(), header).unwrap();
    let mut recorded = Vec::new();
    for i in 0..5 {
        let f = src.grab(Duration::from_secs(5)).unwrap();
        w.add_frame(&f, Some(i as f64 * 10.0)).unwrap();
        recorded.push(f);
    }
    w.finish().unwrap();
    let mut replay = ReplaySource::open(dir.path()).unwrap();
    assert_eq!(replay.describe(), src.describe());
    for want in &recorded {
        assert_eq!(&replay.grab(Duration::ZERO).unwrap(), want);
    }
    result("record_replay", true, "5 vivid frames replayed identically");
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_unplug_mid_stream_is_a_typed_error_within_the_timeout() {
    let path = env_path("CUBECAL_VIVID_UNPLUG");
    let name = path.display().to_string();
    let cfg = V4l2Config {
        width: Some(320),
        height: Some(180),
        format: Some(PixelFormat::Yuyv),
        fps: Some(30),
        lock: None,
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    src.grab(Duration::from_secs(5)).unwrap();
    // vivid's "Disconnect" control simulates a USB unplug: every later ioctl gives ENODEV
    let dev = v4l::Device::with_path(&path).unwrap();
    let ctrls = list_controls(&dev, &name).unwrap();
    let disconnect = ctrls.iter().find(|c| c.name == "Disconnect").unwrap();
    let _ = dev.set_control(v4l::control::Control {
        id: disconnect.id,
        value: v4l::control::Value::None,
    });
    let t = Instant::now();
    let timeout = Duration::from_secs(3);
    let mut r = src.grab(timeout);
    // up to the frames already dequeued-ready before the disconnect may still come out
    for _ in 0..8 {
        if r.is_err() {
            break;
        }
        r = src.grab(timeout);
    }
    let took = t.elapsed();
    let r = r.map(|f| f.sequence);
    println!("after disconnect: {r:?} in {took:?}");
    assert!(matches!(r, Err(CaptureError::Unplugged { .. })), "{r:?}");
    assert_eq!(
        r.as_ref().map_err(|e| e.exit_code()).err(),
        Some(cubecal::exit::DEVICE)
    );
    assert!(took < timeout + Duration::from_secs(1));
    // and it stays dead, without touching the device again
    assert!(matches!(
        src.grab(timeout),
        Err(CaptureError::Unplugged { .. })
    ));
    result(
        "unplug",
        true,
        &format!(
            "Unplugged after {took:?}: {}",
            r.err().map(|e| e.to_string()).unwrap_or_default()
        ),
    );
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_driver_flagged_corrupt_frames_are_dropped_and_counted() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let name = path.display().to_string();
    let cfg = V4l2Config {
        width: Some(320),
        height: Some(180),
        format: Some(PixelFormat::Yuyv),
        fps: Some(30),
        lock: None,
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    let first = src.grab(Duration::from_secs(5)).unwrap().sequence;
    assert_eq!(src.dropped_frames(), 0);
    // vivid marks the next buffer with V4L2_BUF_FLAG_ERROR when this button is pressed
    let dev = v4l::Device::with_path(&path).unwrap();
    let inject = list_controls(&dev, &name)
        .unwrap()
        .into_iter()
        .find(|c| c.name == "Inject V4L2_BUF_FLAG_ERROR")
        .unwrap();
    dev.set_control(v4l::control::Control {
        id: inject.id,
        value: v4l::control::Value::None,
    })
    .unwrap();
    let mut seqs = vec![first];
    for _ in 0..6 {
        seqs.push(src.grab(Duration::from_secs(5)).unwrap().sequence);
    }
    assert_eq!(src.dropped_frames(), 1, "sequences returned: {seqs:?}");
    // the dropped frame leaves a gap in the sequence numbers the station sees
    assert!(seqs.windows(2).any(|w| w[1] == w[0] + 2), "{seqs:?}");
    result(
        "corrupt_frame_dropped",
        true,
        &format!("1 driver-flagged frame dropped, sequences {seqs:?}"),
    );
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_device_in_use_is_reported_busy() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let cfg = V4l2Config {
        width: Some(320),
        height: Some(180),
        format: Some(PixelFormat::Yuyv),
        lock: None,
        ..V4l2Config::default()
    };
    let mut first = V4l2Source::open(&path, &cfg).unwrap();
    first.grab(Duration::from_secs(5)).unwrap();
    let other = V4l2Config {
        width: Some(640),
        height: Some(480),
        ..cfg
    };
    let second = V4l2Source::open(&path, &other);
    let err = second.err().map(|e| (e.exit_code(), e.to_string()));
    println!("second open while streaming: {err:?}");
    assert!(
        matches!(&err, Some((4, m)) if m.contains("busy")),
        "{err:?}"
    );
    result("busy", true, &format!("{err:?}"));
}

#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_webcam_keeps_the_frame_source_contract() {
    let path = env_path("CUBECAL_VIVID_WEBCAM");
    let cfg = V4l2Config {
        width: Some(640),
        height: Some(480),
        format: Some(PixelFormat::Yuyv),
        fps: Some(30),
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(&path, &cfg).unwrap();
    check_contract(
        &mut src,
        10,
        Duration::from_secs(2),
        Duration::from_millis(500),
    )
    .unwrap();
    result("contract_v4l2", true, "10 frames");
}

/// A frame of the cube rig rendered on the host by `cubecal render` (tests/vm/run.sh puts it, its
/// ground truth and the rig in `CUBECAL_VM_RENDER`) goes out through vivid's HDMI output, comes back
/// through `V4l2Source`, and the detector labels its faces against the rig: every labelled corner must
/// match its ground-truth position and every face must be found.
#[test]
#[ignore = "needs the vivid driver: run by tests/vm/run.sh"]
fn vivid_loop_rendered_rig_is_detected_against_ground_truth() {
    let dir = env_path("CUBECAL_VM_RENDER");
    let (rig, _) = cubecal::rig::Rig::load(&dir.join("rig.toml")).unwrap();
    let rendered = image::open(dir.join("frame_000.png")).unwrap().to_luma8();
    let gt: cubecal::render::GroundTruth =
        serde_json::from_str(&std::fs::read_to_string(dir.join("frame_000.json")).unwrap())
            .unwrap();
    let cap_path = env_path("CUBECAL_VIVID_HDMI_CAP");
    let out_path = env_path("CUBECAL_VIVID_HDMI_OUT");
    {
        let dev = v4l::Device::with_path(&cap_path).unwrap();
        let name = cap_path.display().to_string();
        assert_eq!(set_named(&dev, &name, "Loop Video", 1), 1);
        assert_eq!(set_named(&dev, &name, "OSD Text Mode", 2), 2);
    }
    let format = PixelFormat::Grey;
    let cfg = V4l2Config {
        format: Some(format),
        buffers: 4,
        lock: None,
        ..V4l2Config::default()
    };
    let mut src = V4l2Source::open(&cap_path, &cfg).unwrap();
    let n = src.negotiated();
    assert_eq!(
        (n.width, n.height),
        rendered.dimensions(),
        "render size must match vivid's HDMI loop size"
    );
    let mut out = V4l2Output::open(&out_path, format, n.width, n.height, 4).unwrap();
    let raw = encode_gray(format, &rendered, out.negotiated().stride as usize).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let writer = {
        let stop = stop.clone();
        std::thread::spawn(move || -> Result<(), CaptureError> {
            while !stop.load(Ordering::Relaxed) {
                out.write(&raw, Duration::from_secs(2))?;
            }
            Ok(())
        })
    };
    let mut captured = None;
    for _ in 0..30 {
        let f = src.grab(Duration::from_secs(5)).unwrap();
        if f.image == rendered {
            captured = Some(f.image);
            break;
        }
    }
    stop.store(true, Ordering::Relaxed);
    writer.join().unwrap().unwrap();
    let captured = captured.expect("no captured frame equals the rendered frame");
    let mut finder = cubecal::detect::CornerFinder::new().unwrap();
    let det = cubecal::detect::detect(&mut finder, &captured, &rig).unwrap();
    let truth: std::collections::HashMap<(usize, usize, usize), [f64; 2]> = gt
        .visible()
        .filter_map(|c| Some(((c.face_index, c.row, c.col), c.uv?)))
        .collect();
    let (mut sq, mut count, mut worst, mut mislabelled) = (0.0, 0usize, 0.0f64, 0usize);
    for face in &det.faces {
        for c in &face.corners {
            match truth.get(&(face.face, c.row, c.col)) {
                Some(t) => {
                    let e = ((c.uv.x - t[0]).powi(2) + (c.uv.y - t[1]).powi(2)).sqrt();
                    if e > 1.0 {
                        mislabelled += 1;
                    }
                    sq += e * e;
                    count += 1;
                    worst = worst.max(e);
                }
                None => mislabelled += 1,
            }
        }
    }
    let rms = (sq / count.max(1) as f64).sqrt();
    let ok = det.faces.len() == rig.faces.len()
        && mislabelled == 0
        && count == truth.len()
        && rms < 0.05;
    result(
        "loop_rendered_rig_detected",
        ok,
        &format!(
            "{} of {} faces, {count} of {} corners labelled, RMS {rms:.4} px, max {worst:.4} px, mislabelled {mislabelled}, rejected {:?}",
            det.faces.len(),
            rig.faces.len(),
            truth.len(),
            det.rejected
        ),
    );
    assert!(ok);
}
