//! Recorded sessions: a directory of gray PNG frames plus `manifest.json`, and [`ReplaySource`], which
//! plays one back as a [`FrameSource`].
//!
//! ## Format (version 1)
//! ```text
//! session/
//!   frame_000000.png     8-bit gray (16-bit gray PNGs are accepted on replay and reduced to 8 bits)
//!   frame_000001.png
//!   frame_000002.jpg     a user's photo, its bytes as given (photo runs)
//!   manifest.json        written LAST, atomically (temp file + rename)
//! ```
//! The manifest holds the source (identity, name, size, format), optional device details and the
//! negotiated capture format, the control values the driver accepted, the rig (optional path/name),
//! free-form config, and per frame: file name, sequence, timestamp (ns), optional turntable angle and
//! the SHA-256 of the file's bytes.
//!
//! A photo run records the user's files as they are ([`SessionWriter::add_source_file`]): the
//! entry's `source` names the photo (as in the run's outputs), its file keeps the photo's extension
//! and bytes, and replay decodes it with [`super::images::decode`], as the photo run did. A photo
//! that could not be read has an entry with its `error` and no file, so that a replay rejects that
//! view for the same reason.
//!
//! Because the manifest is written last, a session whose recording was interrupted has no manifest and
//! is refused ([`SessionError::NoManifest`]); a frame file that is missing, or whose bytes do not match
//! the checksum (truncated, edited), is refused naming that file. [`Session::open`] verifies every frame
//! up front, so a replay never fails half-way through because of a damaged file.

use std::path::{Path, PathBuf};
use std::time::Duration;

use sha2::{Digest, Sha256};

use super::v4l2::{ControlSetting, DeviceInfo, Negotiated};
use super::{CaptureError, Frame, FrameSource, GrayImage, SourceFile, SourceInfo};

/// Name of the manifest inside a session directory.
pub const MANIFEST: &str = "manifest.json";
/// The manifest format this version reads and writes.
pub const FORMAT_VERSION: u32 = 1;

/// Errors reading or writing a session. Every variant names the file or directory concerned.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error(
        "{dir}: no {MANIFEST}; the recording is incomplete (the manifest is written last) or this is not a session directory"
    )]
    NoManifest { dir: PathBuf },
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not a valid session manifest (truncated or edited?)")]
    Manifest {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{path}: manifest format version {found}, this cubecal reads version {supported}")]
    Version {
        path: PathBuf,
        found: u32,
        supported: u32,
    },
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("{path}: frame file listed in the manifest is missing")]
    MissingFrame { path: PathBuf },
    #[error(
        "{path}: checksum mismatch (manifest sha256 {expected}, file {actual}); the frame was altered or truncated"
    )]
    Checksum {
        path: PathBuf,
        expected: String,
        actual: String,
    },
    #[error("{path}: cannot decode PNG frame")]
    Decode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("{dir}: already contains a session ({MANIFEST}); choose another output directory")]
    Exists { dir: PathBuf },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot encode frame {path}")]
    Encode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
}

impl SessionError {
    /// Every session problem is bad input (or an unusable output directory): [`crate::exit::BAD_INPUT`].
    pub fn exit_code(&self) -> u8 {
        match self {
            SessionError::NoManifest { .. }
            | SessionError::Read { .. }
            | SessionError::Manifest { .. }
            | SessionError::Version { .. }
            | SessionError::Invalid { .. }
            | SessionError::MissingFrame { .. }
            | SessionError::Checksum { .. }
            | SessionError::Decode { .. }
            | SessionError::Exists { .. }
            | SessionError::Write { .. }
            | SessionError::Encode { .. } => crate::exit::BAD_INPUT,
        }
    }
}

/// The rig a session was recorded with.
#[derive(Debug, Clone, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct RigRef {
    pub path: Option<PathBuf>,
    pub name: Option<String>,
}

/// One recorded frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FrameEntry {
    /// File name inside the session directory (no directories).
    pub file: String,
    pub sequence: u64,
    pub timestamp_ns: u64,
    /// Turntable angle in degrees when the frame was taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
    /// Lower-case hex SHA-256 of the file's bytes (empty with `error`).
    pub sha256: String,
    /// The user's photo this frame is, by the name the run's outputs give it; its bytes are recorded
    /// as they were (any image format), not as an encoded gray frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// Why the photo `source` could not be read when recorded (then `file` is empty).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Everything known about a session except its frames.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SessionHeader {
    pub source: SourceInfo,
    /// Device identity and formats when recorded from a V4L2 camera.
    #[serde(default)]
    pub device: Option<DeviceInfo>,
    /// The capture format the driver agreed to.
    #[serde(default)]
    pub capture: Option<Negotiated>,
    /// Locked control values, as accepted by the driver.
    #[serde(default)]
    pub controls: Vec<ControlSetting>,
    #[serde(default)]
    pub rig: Option<RigRef>,
    /// The configuration used (free-form JSON, e.g. the station config).
    #[serde(default)]
    pub config: serde_json::Value,
}

/// The manifest file.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    #[serde(flatten)]
    pub header: SessionHeader,
    pub frames: Vec<FrameEntry>,
    /// Whether the recording ran to its end (`false`: a fault or a signal stopped it). Absent in
    /// sessions recorded before it was kept at the top level (and by `cubecal record`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub complete: Option<bool>,
    /// What ended an incomplete recording (the error's message).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<String>,
}

impl Manifest {
    /// Whether the recording was ended early: `complete: false` at the top level, or (sessions of
    /// earlier versions) under the station config.
    pub fn incomplete(&self) -> bool {
        self.complete == Some(false)
            || self.header.config.get("complete") == Some(&serde_json::Value::Bool(false))
    }
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Writes a session: frames as they come, the manifest last. With [`SessionWriter::create_background`]
/// the frames are encoded and written by a worker thread (a station encodes while the turntable moves),
/// and a failed write is reported by the next [`add_frame`](SessionWriter::add_frame) or by
/// [`finish`](SessionWriter::finish).
#[derive(Debug)]
pub struct SessionWriter {
    dir: PathBuf,
    header: SessionHeader,
    frames: Vec<FrameEntry>,
    queued: usize,
    worker: Option<Worker>,
    outcome: Option<(bool, Option<String>)>,
}

type Job = (usize, Payload, Option<f64>);

/// What a recorded frame is made from.
#[derive(Debug)]
enum Payload {
    /// A camera's (or renderer's) frame, encoded as gray PNG.
    Encode(Frame),
    /// A user's file, copied as it is (or its read error recorded).
    Copy {
        file: SourceFile,
        sequence: u64,
        timestamp: Duration,
    },
}

/// The session file name of a user's file recorded as frame `index` (empty when it was unreadable).
fn copy_name(index: usize, file: &SourceFile) -> String {
    if file.bytes.is_ok() {
        format!("frame_{index:06}.{}", file.extension)
    } else {
        String::new()
    }
}

impl Payload {
    /// The name of the file this payload is written to (empty when it has none).
    fn file_name(&self, index: usize) -> String {
        match self {
            Payload::Encode(_) => format!("frame_{index:06}.png"),
            Payload::Copy { file, .. } => copy_name(index, file),
        }
    }

    fn write(
        self,
        dir: &Path,
        index: usize,
        angle_deg: Option<f64>,
    ) -> Result<FrameEntry, SessionError> {
        match self {
            Payload::Encode(frame) => write_frame_file(dir, index, &frame, angle_deg),
            Payload::Copy {
                file,
                sequence,
                timestamp,
            } => {
                let mut entry = FrameEntry {
                    file: copy_name(index, &file),
                    sequence,
                    timestamp_ns: u64::try_from(timestamp.as_nanos()).unwrap_or(u64::MAX),
                    angle_deg,
                    sha256: String::new(),
                    source: Some(file.name),
                    error: None,
                };
                match file.bytes {
                    Ok(bytes) => {
                        let path = dir.join(&entry.file);
                        std::fs::write(&path, &bytes)
                            .map_err(|source| SessionError::Write { path, source })?;
                        entry.sha256 = sha256_hex(&bytes);
                    }
                    Err(e) => entry.error = Some(e),
                }
                Ok(entry)
            }
        }
    }
}

#[derive(Debug)]
struct Worker {
    jobs: std::sync::mpsc::SyncSender<Job>,
    results: std::sync::mpsc::Receiver<Result<FrameEntry, SessionError>>,
    thread: std::thread::JoinHandle<()>,
}

/// Encode one frame as PNG into `dir` and describe it.
fn write_frame_file(
    dir: &Path,
    index: usize,
    frame: &Frame,
    angle_deg: Option<f64>,
) -> Result<FrameEntry, SessionError> {
    let file = format!("frame_{index:06}.png");
    let path = dir.join(&file);
    // Fast compression: a station writes every frame while it waits for the next move, and the
    // default level costs several times as much for ~10 % smaller files of noisy frames.
    let mut png = Vec::new();
    {
        use image::ImageEncoder;
        use image::codecs::png::{CompressionType, FilterType, PngEncoder};
        PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive)
            .write_image(
                frame.image.as_raw(),
                frame.image.width(),
                frame.image.height(),
                image::ExtendedColorType::L8,
            )
            .map_err(|e| SessionError::Encode {
                path: path.clone(),
                source: e,
            })?;
    }
    std::fs::write(&path, &png).map_err(|e| SessionError::Write {
        path: path.clone(),
        source: e,
    })?;
    Ok(FrameEntry {
        file,
        sequence: frame.sequence,
        timestamp_ns: u64::try_from(frame.timestamp.as_nanos()).unwrap_or(u64::MAX),
        angle_deg,
        sha256: sha256_hex(&png),
        source: None,
        error: None,
    })
}

impl SessionWriter {
    /// Create (or reuse an existing directory without a manifest) `dir` for a new session.
    pub fn create(dir: &Path, header: SessionHeader) -> Result<SessionWriter, SessionError> {
        if dir.join(MANIFEST).exists() {
            return Err(SessionError::Exists {
                dir: dir.to_path_buf(),
            });
        }
        std::fs::create_dir_all(dir).map_err(|e| SessionError::Write {
            path: dir.to_path_buf(),
            source: e,
        })?;
        Ok(SessionWriter {
            dir: dir.to_path_buf(),
            header,
            frames: Vec::new(),
            queued: 0,
            worker: None,
            outcome: None,
        })
    }

    /// Like [`create`](SessionWriter::create), with frames encoded and written by a worker thread
    /// (at most 4 frames queued; `add_frame` waits when the disk is slower than the camera).
    pub fn create_background(
        dir: &Path,
        header: SessionHeader,
    ) -> Result<SessionWriter, SessionError> {
        let mut w = SessionWriter::create(dir, header)?;
        let (jobs, rx) = std::sync::mpsc::sync_channel::<Job>(4);
        let (tx, results) = std::sync::mpsc::channel();
        let dir = w.dir.clone();
        let thread = std::thread::Builder::new()
            .name("session-writer".into())
            .spawn(move || {
                for (index, payload, angle) in rx {
                    if tx.send(payload.write(&dir, index, angle)).is_err() {
                        break;
                    }
                }
            })
            .map_err(|e| SessionError::Write {
                path: w.dir.clone(),
                source: e,
            })?;
        w.worker = Some(Worker {
            jobs,
            results,
            thread,
        });
        Ok(w)
    }

    /// Take the worker's finished frames; the first failed write is returned.
    fn collect(&mut self) -> Result<(), SessionError> {
        if let Some(w) = &self.worker {
            while let Ok(r) = w.results.try_recv() {
                self.frames.push(r?);
            }
        }
        Ok(())
    }

    /// Write one frame as PNG and remember its checksum (queued to the worker in background mode).
    /// Returns the frame's file name in the session.
    pub fn add_frame(
        &mut self,
        frame: &Frame,
        angle_deg: Option<f64>,
    ) -> Result<String, SessionError> {
        self.add(Payload::Encode(frame.clone()), angle_deg)
    }

    /// Record a user's file as it is: its bytes copied (checksummed) under the session's next frame
    /// name with the file's extension, or, when it could not be read, an entry with the reason and
    /// no file. `sequence` and `timestamp` are those of the frame decoded from it (or of its place
    /// in the stream). Returns the file name in the session (empty for an unreadable file).
    pub fn add_source_file(
        &mut self,
        file: SourceFile,
        sequence: u64,
        timestamp: Duration,
        angle_deg: Option<f64>,
    ) -> Result<String, SessionError> {
        self.add(
            Payload::Copy {
                file,
                sequence,
                timestamp,
            },
            angle_deg,
        )
    }

    fn add(&mut self, payload: Payload, angle_deg: Option<f64>) -> Result<String, SessionError> {
        let index = self.queued;
        let name = payload.file_name(index);
        match &self.worker {
            None => {
                let entry = payload.write(&self.dir, index, angle_deg)?;
                self.frames.push(entry);
            }
            Some(w) => {
                if w.jobs.send((index, payload, angle_deg)).is_err() {
                    // The worker stopped: its error is waiting in the results.
                    self.collect()?;
                }
                self.collect()?;
            }
        }
        self.queued += 1;
        Ok(name)
    }

    /// Frames added so far (queued or written).
    pub fn frame_count(&self) -> usize {
        self.queued
    }

    /// The header the manifest will carry (e.g. to record how the session ended before `finish`).
    pub fn header_mut(&mut self) -> &mut SessionHeader {
        &mut self.header
    }

    /// Record how the recording ended, for the manifest's top-level `complete` and `ended_by`.
    pub fn set_outcome(&mut self, complete: bool, ended_by: Option<String>) {
        self.outcome = Some((complete, ended_by));
    }

    /// Write the manifest atomically (temp file in the directory, fsync, rename) and return its path.
    pub fn finish(mut self) -> Result<PathBuf, SessionError> {
        if let Some(w) = self.worker.take() {
            drop(w.jobs);
            let results: Vec<_> = w.results.iter().collect();
            if w.thread.join().is_err() {
                return Err(SessionError::Write {
                    path: self.dir.clone(),
                    source: std::io::Error::other("the session writer thread panicked"),
                });
            }
            for r in results {
                self.frames.push(r?);
            }
        }
        let path = self.dir.join(MANIFEST);
        let manifest = Manifest {
            format_version: FORMAT_VERSION,
            header: self.header,
            frames: self.frames,
            complete: self.outcome.as_ref().map(|o| o.0),
            ended_by: self.outcome.and_then(|o| o.1),
        };
        let json = serde_json::to_vec_pretty(&manifest).map_err(|e| SessionError::Write {
            path: path.clone(),
            source: e.into(),
        })?;
        let werr = |e: std::io::Error| SessionError::Write {
            path: path.clone(),
            source: e,
        };
        // An ordinary file like the frames beside it (0644 before the umask), not a private temporary.
        crate::rig::write_atomic(&path, &json).map_err(werr)?;
        Ok(path)
    }
}

/// A session read from disk, its manifest parsed and every frame verified.
#[derive(Debug, Clone)]
pub struct Session {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl Session {
    /// Read and verify a session: the manifest exists and parses, every frame file exists and matches
    /// its checksum.
    pub fn open(dir: &Path) -> Result<Session, SessionError> {
        let path = dir.join(MANIFEST);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(SessionError::NoManifest {
                    dir: dir.to_path_buf(),
                });
            }
            Err(e) => return Err(SessionError::Read { path, source: e }),
        };
        // check the version before the full parse, so that a newer format says so
        #[derive(serde::Deserialize)]
        struct Version {
            format_version: u32,
        }
        if let Ok(v) = serde_json::from_slice::<Version>(&bytes)
            && v.format_version != FORMAT_VERSION
        {
            return Err(SessionError::Version {
                path,
                found: v.format_version,
                supported: FORMAT_VERSION,
            });
        }
        let manifest: Manifest =
            serde_json::from_slice(&bytes).map_err(|e| SessionError::Manifest {
                path: path.clone(),
                source: e,
            })?;
        let session = Session {
            dir: dir.to_path_buf(),
            manifest,
        };
        for (i, f) in session.manifest.frames.iter().enumerate() {
            if f.error.is_some() {
                continue; // a photo that could not be read: no file
            }
            let plain = Path::new(&f.file)
                .file_name()
                .is_some_and(|n| n == std::ffi::OsStr::new(&f.file));
            if !plain {
                return Err(SessionError::Invalid {
                    path: path.clone(),
                    reason: format!("frames[{i}].file {:?} is not a plain file name", f.file),
                });
            }
            session.read_verified(i)?;
        }
        Ok(session)
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.manifest.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.manifest.frames.is_empty()
    }

    /// The bytes of frame `i`, verified against the manifest checksum.
    fn read_verified(&self, i: usize) -> Result<Vec<u8>, SessionError> {
        let entry = &self.manifest.frames[i];
        let path = self.dir.join(&entry.file);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(SessionError::MissingFrame { path });
            }
            Err(e) => return Err(SessionError::Read { path, source: e }),
        };
        let actual = sha256_hex(&bytes);
        if !actual.eq_ignore_ascii_case(&entry.sha256) {
            return Err(SessionError::Checksum {
                path,
                expected: entry.sha256.clone(),
                actual,
            });
        }
        Ok(bytes)
    }

    /// A recorded photo (an entry with `source`): its file as the source gave it, and its decoded
    /// frame or why it cannot be used ([`super::images::decode`], the photo run's own decoding).
    pub fn photo(&self, i: usize) -> Result<(SourceFile, Result<Frame, String>), SessionError> {
        let entry = &self.manifest.frames[i];
        let name = entry.source.clone().unwrap_or_else(|| entry.file.clone());
        let bytes = match &entry.error {
            Some(e) => Err(e.clone()),
            None => Ok(self.read_verified(i)?),
        };
        let src = &self.manifest.header.source;
        let frame = match &bytes {
            Ok(b) => super::images::decode(b, Some((src.width, src.height))).map(|image| Frame {
                sequence: entry.sequence,
                timestamp: Duration::from_nanos(entry.timestamp_ns),
                image,
            }),
            Err(e) => Err(e.clone()),
        };
        let file = SourceFile {
            name,
            extension: super::images::extension(Path::new(&entry.file)),
            bytes,
        };
        Ok((file, frame))
    }

    /// Decode frame `i` (verified) to an 8-bit gray frame.
    pub fn frame(&self, i: usize) -> Result<Frame, SessionError> {
        let entry = &self.manifest.frames[i];
        let path = self.dir.join(&entry.file);
        if entry.source.is_some() {
            return self
                .photo(i)?
                .1
                .map_err(|reason| SessionError::Invalid { path, reason });
        }
        let bytes = self.read_verified(i)?;
        let img =
            image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).map_err(|e| {
                SessionError::Decode {
                    path: path.clone(),
                    source: e,
                }
            })?;
        let image: GrayImage = match img {
            image::DynamicImage::ImageLuma8(g) => g,
            image::DynamicImage::ImageLuma16(g) => {
                let (w, h) = g.dimensions();
                GrayImage::from_fn(w, h, |x, y| {
                    image::Luma([(g.get_pixel(x, y)[0] >> 8) as u8])
                })
            }
            _ => {
                return Err(SessionError::Invalid {
                    path,
                    reason: "frame is not a gray PNG".into(),
                });
            }
        };
        let src = &self.manifest.header.source;
        if image.dimensions() != (src.width, src.height) {
            return Err(SessionError::Invalid {
                path,
                reason: format!(
                    "frame is {}x{}, the manifest says {}x{}",
                    image.width(),
                    image.height(),
                    src.width,
                    src.height
                ),
            });
        }
        Ok(Frame {
            sequence: entry.sequence,
            timestamp: Duration::from_nanos(entry.timestamp_ns),
            image,
        })
    }
}

/// Plays a recorded session back, frame by frame, then [`CaptureError::EndOfStream`].
#[derive(Debug)]
pub struct ReplaySource {
    session: Session,
    next: usize,
    last: Option<SourceFile>,
}

impl ReplaySource {
    /// Open and verify the session in `dir`.
    pub fn open(dir: &Path) -> Result<ReplaySource, CaptureError> {
        Ok(ReplaySource {
            session: Session::open(dir)?,
            next: 0,
            last: None,
        })
    }

    pub fn session(&self) -> &Session {
        &self.session
    }

    /// The manifest entry of the frame the next `grab` returns.
    pub fn peek(&self) -> Option<&FrameEntry> {
        self.session.manifest.frames.get(self.next)
    }
}

impl FrameSource for ReplaySource {
    fn describe(&self) -> SourceInfo {
        self.session.manifest.header.source.clone()
    }

    /// Returns the next recorded frame immediately (a recording never makes you wait). A recorded
    /// photo that cannot be used fails with [`CaptureError::Image`] and the reason the photo run gave.
    fn grab(&mut self, _timeout: Duration) -> Result<Frame, CaptureError> {
        let Some(entry) = self.session.manifest.frames.get(self.next) else {
            return Err(CaptureError::EndOfStream {
                source_name: self.session.dir.display().to_string(),
            });
        };
        let i = self.next;
        self.next += 1;
        if entry.source.is_none() {
            return Ok(self.session.frame(i)?);
        }
        let (file, frame) = self.session.photo(i)?;
        let path = file.name.clone();
        self.last = Some(file);
        frame.map_err(|reason| CaptureError::Image { path, reason })
    }

    /// A recording has no frames queued behind the station's back: nothing to drop.
    fn flush(&mut self) -> Result<usize, CaptureError> {
        Ok(0)
    }

    /// Recorded photos are handed on as they are, so that a run replaying a photo session records
    /// the same files.
    fn take_source_file(&mut self) -> Option<SourceFile> {
        self.last.take()
    }

    fn recorded(&self) -> bool {
        true
    }
}
