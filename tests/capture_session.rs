//! The session format: round trip through `ReplaySource` (checksums equal), and refusal of damaged
//! sessions with a message naming the file: no manifest (interrupted recording), truncated manifest,
//! checksum mismatch, missing frame, wrong version, path escapes.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::time::Duration;

use cubecal::capture::session::{
    FORMAT_VERSION, MANIFEST, ReplaySource, RigRef, Session, SessionError, SessionHeader,
    SessionWriter,
};
use cubecal::capture::{CaptureError, Frame, FrameSource, GrayImage, SourceInfo, check_contract};
use cubecal::exit;
use sha2::{Digest, Sha256};

fn header(w: u32, h: u32) -> SessionHeader {
    SessionHeader {
        source: SourceInfo {
            identity: "test:checkerboard".into(),
            name: "unit test".into(),
            width: w,
            height: h,
            format: "GREY".into(),
        },
        device: None,
        capture: None,
        controls: vec![],
        rig: Some(RigRef {
            path: Some("rigs/cube.toml".into()),
            name: Some("cube".into()),
        }),
        config: serde_json::json!({"frames": 3}),
    }
}

fn frames(w: u32, h: u32, n: u64) -> Vec<Frame> {
    (0..n)
        .map(|k| Frame {
            sequence: 100 + 2 * k, // with gaps, as a real driver may give
            timestamp: Duration::from_micros(1_000_000 + 33_333 * k),
            image: GrayImage::from_fn(w, h, |x, y| {
                image::Luma([if ((x / 4) + (y / 4) + k as u32).is_multiple_of(2) {
                    230
                } else {
                    20
                }])
            }),
        })
        .collect()
}

fn record(dir: &Path, n: u64) -> Vec<Frame> {
    let fr = frames(24, 16, n);
    let mut w = SessionWriter::create(dir, header(24, 16)).unwrap();
    for (i, f) in fr.iter().enumerate() {
        w.add_frame(f, Some(i as f64 * 15.0)).unwrap();
    }
    w.finish().unwrap();
    fr
}

fn sha(bytes: &[u8]) -> Vec<u8> {
    Sha256::digest(bytes).to_vec()
}

#[test]
fn replay_gives_exactly_the_recorded_frames() {
    let dir = tempfile::tempdir().unwrap();
    let recorded = record(dir.path(), 3);
    let mut src = ReplaySource::open(dir.path()).unwrap();
    assert_eq!(src.describe(), header(24, 16).source);
    assert_eq!(src.peek().and_then(|e| e.angle_deg), Some(0.0));
    for want in &recorded {
        let got = src.grab(Duration::from_millis(1)).unwrap();
        assert_eq!(got.sequence, want.sequence);
        assert_eq!(got.timestamp, want.timestamp);
        assert_eq!(
            sha(got.image.as_raw()),
            sha(want.image.as_raw()),
            "pixel checksums differ"
        );
        assert_eq!(&got, want);
    }
    assert!(matches!(
        src.grab(Duration::from_millis(1)),
        Err(CaptureError::EndOfStream { .. })
    ));
    assert_eq!(src.flush().unwrap(), 0);
    let m = &src.session().manifest;
    assert_eq!(m.format_version, FORMAT_VERSION);
    assert_eq!(
        m.header.rig.as_ref().and_then(|r| r.name.as_deref()),
        Some("cube")
    );
    assert_eq!(m.frames[2].angle_deg, Some(30.0));
}

#[test]
fn interrupted_recording_without_manifest_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let fr = frames(24, 16, 2);
    let mut w = SessionWriter::create(dir.path(), header(24, 16)).unwrap();
    w.add_frame(&fr[0], None).unwrap();
    drop(w); // crash before finish()
    let err = Session::open(dir.path()).unwrap_err();
    assert!(matches!(err, SessionError::NoManifest { .. }), "{err}");
    assert!(err.to_string().contains("incomplete"), "{err}");
    let err = ReplaySource::open(dir.path()).unwrap_err();
    assert_eq!(err.exit_code(), exit::BAD_INPUT);
}

#[test]
fn truncated_manifest_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 2);
    let m = dir.path().join(MANIFEST);
    let bytes = std::fs::read(&m).unwrap();
    std::fs::write(&m, &bytes[..bytes.len() / 2]).unwrap();
    let err = Session::open(dir.path()).unwrap_err();
    assert!(matches!(err, SessionError::Manifest { .. }), "{err}");
    assert!(err.to_string().contains("manifest.json"), "{err}");
}

#[test]
fn altered_frame_fails_its_checksum_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 3);
    let f = dir.path().join("frame_000001.png");
    // re-encode a different image: a valid PNG, but not the recorded one
    GrayImage::from_pixel(24, 16, image::Luma([7]))
        .save(&f)
        .unwrap();
    let err = Session::open(dir.path()).unwrap_err();
    assert!(matches!(err, SessionError::Checksum { .. }), "{err}");
    assert!(err.to_string().contains("frame_000001.png"), "{err}");
    // truncation is caught the same way
    record_truncated(dir.path());
}

fn record_truncated(_: &Path) {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 2);
    let f = dir.path().join("frame_000000.png");
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes[..bytes.len() - 5]).unwrap();
    let err = Session::open(dir.path()).unwrap_err();
    assert!(matches!(err, SessionError::Checksum { .. }), "{err}");
}

#[test]
fn missing_frame_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 3);
    std::fs::remove_file(dir.path().join("frame_000002.png")).unwrap();
    let err = Session::open(dir.path()).unwrap_err();
    assert!(matches!(err, SessionError::MissingFrame { .. }), "{err}");
    assert!(err.to_string().contains("frame_000002.png"), "{err}");
}

#[test]
fn other_versions_and_escaping_paths_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 1);
    let m = dir.path().join(MANIFEST);
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&m).unwrap()).unwrap();
    v["format_version"] = 99.into();
    std::fs::write(&m, serde_json::to_vec(&v).unwrap()).unwrap();
    assert!(matches!(
        Session::open(dir.path()),
        Err(SessionError::Version { found: 99, .. })
    ));
    v["format_version"] = FORMAT_VERSION.into();
    v["frames"][0]["file"] = "../etc/passwd".into();
    std::fs::write(&m, serde_json::to_vec(&v).unwrap()).unwrap();
    assert!(matches!(
        Session::open(dir.path()),
        Err(SessionError::Invalid { .. })
    ));
}

#[test]
fn writer_refuses_to_overwrite_a_session() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 1);
    assert!(matches!(
        SessionWriter::create(dir.path(), header(24, 16)),
        Err(SessionError::Exists { .. })
    ));
}

#[test]
fn sixteen_bit_png_frames_replay_as_high_byte() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 1);
    let f = dir.path().join("frame_000000.png");
    let img16 = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(24, 16, |x, _| {
        image::Luma([(x as u16) << 8 | 0x7f])
    });
    img16.save(&f).unwrap();
    let m = dir.path().join(MANIFEST);
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&m).unwrap()).unwrap();
    let digest: String = sha(&std::fs::read(&f).unwrap())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    v["frames"][0]["sha256"] = digest.into();
    std::fs::write(&m, serde_json::to_vec(&v).unwrap()).unwrap();
    let mut src = ReplaySource::open(dir.path()).unwrap();
    let fr = src.grab(Duration::ZERO).unwrap();
    assert_eq!(fr.image.get_pixel(5, 3)[0], 5);
}

#[test]
fn replay_keeps_the_frame_source_contract() {
    let dir = tempfile::tempdir().unwrap();
    record(dir.path(), 6);
    let mut src = ReplaySource::open(dir.path()).unwrap();
    check_contract(
        &mut src,
        6,
        Duration::from_millis(100),
        Duration::from_millis(400),
    )
    .unwrap();
}
