//! [`ImageFiles`]: photos a user already took (a folder, or a list of files) as a [`FrameSource`] —
//! the way OpenCV, ROS and Kalibr users calibrate today, with no turntable. PNG, JPEG and TIFF of any
//! size and colour type are read and converted to 8-bit grey (16-bit images are scaled, not clipped).
//! A folder is read in file-name order; files of other types in it are ignored. Every file is checked
//! up front (it exists and its header decodes), so that a bad file is named before any work is done.

use std::path::{Path, PathBuf};
use std::time::Duration;

use super::{CaptureError, Frame, FrameSource, SourceInfo};

/// File extensions read from a folder (case-insensitive).
pub const EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "tif", "tiff"];

/// A list of image files played back in order, one frame each, then end of stream.
#[derive(Debug, Clone)]
pub struct ImageFiles {
    files: Vec<PathBuf>,
    identity: String,
    width: u32,
    height: u32,
    next: usize,
}

fn has_image_extension(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

fn io_err(path: &Path, context: &str, source: std::io::Error) -> CaptureError {
    CaptureError::Io {
        source_name: path.display().to_string(),
        context: context.to_string(),
        source,
    }
}

impl ImageFiles {
    /// Collect the images named by `paths` (each a file, or a folder whose images are taken in name
    /// order). All images must have the same size (one camera, one resolution). `identity` names the
    /// camera (e.g. `--device-id`).
    pub fn open(paths: &[PathBuf], identity: &str) -> Result<ImageFiles, CaptureError> {
        let mut files = Vec::new();
        for p in paths {
            let meta = std::fs::metadata(p).map_err(|e| io_err(p, "cannot read", e))?;
            if meta.is_dir() {
                let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                    .map_err(|e| io_err(p, "cannot list the folder", e))?
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|f| f.is_file() && has_image_extension(f))
                    .collect();
                found.sort();
                if found.is_empty() {
                    return Err(CaptureError::Unsupported {
                        device: p.display().to_string(),
                        reason: format!(
                            "no images in this folder (looked for .{})",
                            EXTENSIONS.join(", .")
                        ),
                    });
                }
                files.extend(found);
            } else {
                files.push(p.clone());
            }
        }
        if files.is_empty() {
            return Err(CaptureError::Unsupported {
                device: "--images".into(),
                reason: "no image files given".into(),
            });
        }
        let mut size = None;
        for f in &files {
            let dims = image::ImageReader::open(f)
                .map_err(|e| io_err(f, "cannot open", e))?
                .with_guessed_format()
                .map_err(|e| io_err(f, "cannot read", e))?
                .into_dimensions()
                .map_err(|e| CaptureError::Unsupported {
                    device: f.display().to_string(),
                    reason: format!("not a readable PNG, JPEG or TIFF image: {e}"),
                })?;
            match size {
                None => size = Some((dims, f.clone())),
                Some((d0, ref f0)) if d0 != dims => {
                    return Err(CaptureError::Unsupported {
                        device: f.display().to_string(),
                        reason: format!(
                            "image is {}×{} but {} is {}×{}: one calibration needs one camera resolution",
                            dims.0,
                            dims.1,
                            f0.display(),
                            d0.0,
                            d0.1
                        ),
                    });
                }
                Some(_) => {}
            }
        }
        let ((width, height), _) = size.ok_or_else(|| CaptureError::Unsupported {
            device: "--images".into(),
            reason: "no image files given".into(),
        })?;
        Ok(ImageFiles {
            files,
            identity: identity.to_string(),
            width,
            height,
            next: 0,
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

    fn grab(&mut self, _timeout: Duration) -> Result<Frame, CaptureError> {
        let Some(path) = self.files.get(self.next) else {
            return Err(CaptureError::EndOfStream {
                source_name: "image files".into(),
            });
        };
        let img = image::ImageReader::open(path)
            .map_err(|e| io_err(path, "cannot open", e))?
            .with_guessed_format()
            .map_err(|e| io_err(path, "cannot read", e))?
            .decode()
            .map_err(|e| CaptureError::Unsupported {
                device: path.display().to_string(),
                reason: format!("cannot decode: {e}"),
            })?;
        let image = img.into_luma8();
        let seq = self.next as u64;
        self.next += 1;
        Ok(Frame {
            sequence: seq,
            timestamp: Duration::from_millis(seq),
            image,
        })
    }

    fn flush(&mut self) -> Result<usize, CaptureError> {
        Ok(0)
    }
}
