//! [`ImageFiles`]: photos a user already took (a folder, or a list of files) as a [`FrameSource`] —
//! the way OpenCV, ROS and Kalibr users calibrate today, with no turntable. PNG, JPEG and TIFF of any
//! size and colour type are read and converted to 8-bit grey (16-bit images are scaled, not clipped).
//! A folder is read in file-name order; files of other types in it are ignored.
//!
//! Each photo keeps its name ([`labels`]: the file name, or the path as given when two share one) in
//! every output, and its bytes are handed to the recorder as they are ([`FrameSource::take_source_file`]):
//! a run's session holds the user's files, checksummed, not re-encoded copies, and replays them through
//! the same [`decode`]. A photo that is missing, empty, not an image or of another size than the
//! first usable one fails its own grab with [`CaptureError::Image`] (the station rejects that view and
//! goes on); opening fails only when no photo is usable at all, or a folder holds no images.

use std::path::{Path, PathBuf};
use std::time::Duration;

use super::{CaptureError, Frame, FrameSource, GrayImage, SourceFile, SourceInfo};

/// File extensions read from a folder (case-insensitive).
pub const EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "tif", "tiff"];

/// A list of image files played back in order, one frame each, then end of stream. The
/// [`READ_AHEAD`] photos after the one just grabbed are read and decoded on threads of their own
/// meanwhile (the station detects the ones it has).
#[derive(Debug)]
pub struct ImageFiles {
    files: Vec<PathBuf>,
    labels: Vec<String>,
    identity: String,
    width: u32,
    height: u32,
    next: usize,
    last: Option<SourceFile>,
    /// The photos from `next` on, being read and decoded (at most [`READ_AHEAD`], each with its
    /// index, in order).
    ahead: std::collections::VecDeque<(usize, std::thread::JoinHandle<Loaded>)>,
}

/// How many photos are read and decoded ahead of the station: as many as it grabs before it detects
/// them (one a core, two here), so that a grab finds its photo decoded.
pub const READ_AHEAD: usize = 2;

/// A photo's bytes (or why they cannot be read) and its frame (or why it cannot be used).
type Loaded = (Result<Vec<u8>, String>, Result<GrayImage, String>);

/// Read and decode one photo for a run of `size`.
fn load(path: &Path, size: (u32, u32)) -> Loaded {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read: {e}"));
    let decoded = match &bytes {
        Ok(b) => decode(b, Some(size)),
        Err(e) => Err(e.clone()),
    };
    (bytes, decoded)
}

fn has_image_extension(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

/// A file's extension, lower case and restricted to ASCII letters and digits (for the name of its
/// recorded copy); `img` when it has none.
pub fn extension(p: &Path) -> String {
    let e: String = p
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or_default()
        .chars()
        .filter(char::is_ascii_alphanumeric)
        .map(|c| c.to_ascii_lowercase())
        .take(8)
        .collect();
    if e.is_empty() { "img".into() } else { e }
}

/// The name each file is known by in a run's outputs (view names, events, result, report): its file
/// name, or the path as given when another file of the run has the same file name.
pub fn labels(files: &[PathBuf]) -> Vec<String> {
    let name = |f: &PathBuf| {
        f.file_name().map_or_else(
            || f.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        )
    };
    let names: Vec<String> = files.iter().map(name).collect();
    names
        .iter()
        .zip(files)
        .map(|(n, f)| {
            if names.iter().filter(|m| *m == n).count() > 1 {
                f.display().to_string()
            } else {
                n.clone()
            }
        })
        .collect()
}

/// Decode a photo's bytes to 8-bit grey, checking its size against `size` (the run's resolution)
/// when given. The error is the reason the photo cannot be used, without its name. A photo run and
/// the replay of its session both decode through here, so they see the same pixels and reasons.
pub fn decode(bytes: &[u8], size: Option<(u32, u32)>) -> Result<GrayImage, String> {
    if bytes.is_empty() {
        return Err("empty file (0 bytes)".into());
    }
    // The JPEG decoder fills a truncated file's missing part with grey instead of failing: a JPEG
    // ends with an end-of-image marker after its scan data (where 0xFF is always escaped).
    if bytes.starts_with(&[0xFF, 0xD8]) {
        let scan = bytes.windows(2).position(|w| w == [0xFF, 0xDA]);
        let end = scan.and_then(|s| bytes[s..].windows(2).position(|w| w == [0xFF, 0xD9]));
        if end.is_none() {
            return Err("truncated JPEG: no end-of-image marker after its image data".into());
        }
    }
    let img = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| format!("cannot read: {e}"))?
        .decode()
        .map_err(|e| format!("not a readable PNG, JPEG or TIFF image: {e}"))?
        .into_luma8();
    match size {
        Some((w, h)) if img.dimensions() != (w, h) => Err(format!(
            "image is {}×{} but the run's photos are {w}×{h}: one calibration needs one camera resolution",
            img.width(),
            img.height()
        )),
        _ => Ok(img),
    }
}

/// Why a run has no photo: each photo's name (the first eight) and the first one's reason, names
/// first (error lines are cut at their end).
pub fn unusable(names: &[String], first_reason: &str) -> String {
    let mut list = names.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
    if names.len() > 8 {
        list.push_str(", …");
    }
    format!(
        "not one of the {} photo(s) can be used: {list} ({}: {first_reason})",
        names.len(),
        names.first().map_or("", String::as_str)
    )
}

/// The size in a file's header, or why it cannot be had.
fn header_size(f: &Path) -> Result<(u32, u32), String> {
    image::ImageReader::open(f)
        .map_err(|e| format!("cannot read: {e}"))?
        .with_guessed_format()
        .map_err(|e| format!("cannot read: {e}"))?
        .into_dimensions()
        .map_err(|e| format!("not a readable PNG, JPEG or TIFF image: {e}"))
}

impl ImageFiles {
    /// Collect the images named by `paths` (each a file, or a folder whose images are taken in name
    /// order). The run's resolution is that of the first file whose header reads; the others are
    /// checked when grabbed. `identity` names the camera (e.g. `--device-id`). Fails (bad input) for
    /// a folder that cannot be listed or holds no images, and when no file is a readable image.
    pub fn open(paths: &[PathBuf], identity: &str) -> Result<ImageFiles, CaptureError> {
        let mut files = Vec::new();
        for p in paths {
            if !p.is_dir() {
                // A missing or unreadable file is that view's problem (rejected when grabbed).
                files.push(p.clone());
                continue;
            }
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| CaptureError::Image {
                    path: p.display().to_string(),
                    reason: format!("cannot list the folder: {e}"),
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| f.is_file() && has_image_extension(f))
                .collect();
            found.sort();
            if found.is_empty() {
                return Err(CaptureError::Image {
                    path: p.display().to_string(),
                    reason: format!(
                        "no images in this folder (looked for .{})",
                        EXTENSIONS.join(", .")
                    ),
                });
            }
            files.extend(found);
        }
        let labels = labels(&files);
        let mut why = None;
        let mut size = None;
        for f in &files {
            match header_size(f) {
                Ok(d) => {
                    size = Some(d);
                    break;
                }
                Err(e) => {
                    why.get_or_insert(e);
                }
            }
        }
        let Some((width, height)) = size else {
            return Err(CaptureError::Image {
                path: "--images".into(),
                reason: match why {
                    None => "no image files given".into(),
                    Some(first) => unusable(&labels, &first),
                },
            });
        };
        Ok(ImageFiles {
            labels,
            files,
            identity: identity.to_string(),
            width,
            height,
            next: 0,
            last: None,
            ahead: std::collections::VecDeque::new(),
        })
    }

    /// The files, in playback order.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    pub fn len(&self) -> usize {
        self.files.len()
    }

    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

impl FrameSource for ImageFiles {
    fn describe(&self) -> SourceInfo {
        SourceInfo {
            identity: self.identity.clone(),
            name: format!("{} image file(s)", self.files.len()),
            width: self.width,
            height: self.height,
            format: "FILE".into(),
        }
    }

    /// The next photo; [`CaptureError::Image`] when it cannot be used (the next grab goes on with
    /// the photo after it).
    fn grab(&mut self, _timeout: Duration) -> Result<Frame, CaptureError> {
        let (Some(path), Some(label)) = (self.files.get(self.next), self.labels.get(self.next))
        else {
            return Err(CaptureError::EndOfStream {
                source_name: "image files".into(),
            });
        };
        let index = self.next;
        let seq = index as u64;
        self.next += 1;
        let size = (self.width, self.height);
        let ahead = match self.ahead.front() {
            Some((i, _)) if *i == index => self.ahead.pop_front(),
            _ => None,
        };
        let (bytes, decoded) = match ahead.map(|(_, reading)| reading.join()) {
            Some(Ok(loaded)) => loaded,
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => load(path, size),
        };
        let mut after = self.ahead.back().map_or(self.next, |(i, _)| i + 1);
        while let Some(file) = self
            .files
            .get(after)
            .filter(|_| after < self.next + READ_AHEAD)
        {
            let file = file.clone();
            match std::thread::Builder::new()
                .name("photo-reader".into())
                .spawn(move || load(&file, size))
            {
                Ok(reading) => self.ahead.push_back((after, reading)),
                // No thread (resources exhausted): its grab reads it itself.
                Err(_) => break,
            }
            after += 1;
        }
        self.last = Some(SourceFile {
            name: label.clone(),
            extension: extension(path),
            bytes,
        });
        let image = decoded.map_err(|reason| CaptureError::Image {
            path: label.clone(),
            reason,
        })?;
        Ok(Frame {
            sequence: seq,
            timestamp: Duration::from_millis(seq),
            image,
        })
    }

    fn flush(&mut self) -> Result<usize, CaptureError> {
        Ok(0)
    }

    fn take_source_file(&mut self) -> Option<SourceFile> {
        self.last.take()
    }

    fn recorded(&self) -> bool {
        true
    }
}
