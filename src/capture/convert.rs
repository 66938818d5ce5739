//! Pixel formats a camera may deliver, and their conversion to the 8-bit gray image the station uses.
//!
//! Pure functions, no I/O: every conversion takes the negotiated `width`, `height` and the driver's
//! `stride` (V4L2 `bytesperline`), which may be larger than the packed row size and must be honoured.
//!
//! ## Gray levels
//! - **Y′CbCr formats** (YUYV, UYVY, NV12): the luma byte is taken as is (no limited→full range
//!   expansion). Corner detection does not care about the black level, and keeping Y′ unchanged makes the
//!   conversion exact and invertible for tests.
//! - **RGB formats** (RGB3, BGR3, XR24): BT.601 luma with integer weights that sum to 256,
//!   `Y = (77·R + 150·G + 29·B + 128) >> 8`, so a gray pixel `R = G = B = g` gives exactly `g`.
//! - **Y16**: little-endian 16-bit, the high byte is kept (`Y >> 8`).
//! - **MJPG**: decoded with `image`'s JPEG decoder to luma. A frame that is empty, truncated (no EOI
//!   marker), undecodable or of the wrong size is an error ([`ConvertError`]); the V4L2 source drops and
//!   counts such frames rather than failing the stream.

use image::GrayImage;

/// A pixel format cubecal can convert, named by its V4L2 FourCC.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum PixelFormat {
    /// `GREY`: 8-bit luma.
    Grey,
    /// `Y16 `: 16-bit little-endian luma.
    Y16,
    /// `YUYV`: packed 4:2:2, bytes Y0 U Y1 V.
    Yuyv,
    /// `UYVY`: packed 4:2:2, bytes U Y0 V Y1.
    Uyvy,
    /// `NV12`: planar luma (`height` rows of `stride`) followed by interleaved CbCr at half height.
    Nv12,
    /// `RGB3`: packed R G B.
    Rgb3,
    /// `BGR3`: packed B G R.
    Bgr3,
    /// `XR24`: packed B G R X (DRM XRGB8888, little-endian).
    Xr24,
    /// `MJPG`: one JPEG image per frame.
    Mjpg,
}

impl PixelFormat {
    /// Every supported format, in order of preference when negotiating (cheapest exact gray first;
    /// MJPG last because it is lossy).
    pub const ALL: [PixelFormat; 9] = [
        PixelFormat::Grey,
        PixelFormat::Y16,
        PixelFormat::Yuyv,
        PixelFormat::Uyvy,
        PixelFormat::Nv12,
        PixelFormat::Rgb3,
        PixelFormat::Bgr3,
        PixelFormat::Xr24,
        PixelFormat::Mjpg,
    ];

    /// The V4L2 FourCC code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Grey => *b"GREY",
            PixelFormat::Y16 => *b"Y16 ",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Uyvy => *b"UYVY",
            PixelFormat::Nv12 => *b"NV12",
            PixelFormat::Rgb3 => *b"RGB3",
            PixelFormat::Bgr3 => *b"BGR3",
            PixelFormat::Xr24 => *b"XR24",
            PixelFormat::Mjpg => *b"MJPG",
        }
    }

    /// The FourCC as text, e.g. `"YUYV"` (`"Y16 "` keeps its trailing space).
    pub fn name(self) -> String {
        String::from_utf8_lossy(&self.fourcc()).into_owned()
    }

    /// The format for a FourCC, if cubecal can convert it.
    pub fn from_fourcc(code: [u8; 4]) -> Option<PixelFormat> {
        PixelFormat::ALL.into_iter().find(|f| f.fourcc() == code)
    }

    /// Bytes per pixel of the first plane for packed/planar formats; `None` for compressed MJPG.
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            PixelFormat::Grey | PixelFormat::Nv12 => Some(1),
            PixelFormat::Y16 | PixelFormat::Yuyv | PixelFormat::Uyvy => Some(2),
            PixelFormat::Rgb3 | PixelFormat::Bgr3 => Some(3),
            PixelFormat::Xr24 => Some(4),
            PixelFormat::Mjpg => None,
        }
    }

    /// The smallest valid stride (bytes per row of the first plane) for `width`.
    pub fn min_stride(self, width: u32) -> Option<usize> {
        let w = width as usize;
        match self {
            // 4:2:2 formats pack two pixels into four bytes; an odd width rounds up to a whole pair.
            PixelFormat::Yuyv | PixelFormat::Uyvy => Some(w.div_ceil(2) * 4),
            f => f.bytes_per_pixel().map(|b| b * w),
        }
    }

    /// Bytes a raw frame needs with this stride; `None` for MJPG.
    pub fn frame_len(self, height: u32, stride: usize) -> Option<usize> {
        let h = height as usize;
        match self {
            PixelFormat::Mjpg => None,
            // luma plane + CbCr plane of ceil(h/2) rows with the same stride
            PixelFormat::Nv12 => Some(stride * (h + h.div_ceil(2))),
            _ => Some(stride * h),
        }
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name().trim_end())
    }
}

/// Why a frame could not be converted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    #[error("{format} {width}x{height}: stride {stride} is smaller than a row ({min} bytes)")]
    StrideTooSmall {
        format: PixelFormat,
        width: u32,
        height: u32,
        stride: usize,
        min: usize,
    },
    #[error("{format} {width}x{height} stride {stride}: frame has {got} bytes, needs {need}")]
    ShortFrame {
        format: PixelFormat,
        width: u32,
        height: u32,
        stride: usize,
        got: usize,
        need: usize,
    },
    #[error("empty JPEG frame")]
    EmptyJpeg,
    #[error("truncated JPEG frame ({len} bytes, no end-of-image marker)")]
    TruncatedJpeg { len: usize },
    #[error("corrupt JPEG frame ({len} bytes): {reason}")]
    CorruptJpeg { len: usize, reason: String },
    #[error("JPEG frame is {got_w}x{got_h}, the negotiated size is {width}x{height}")]
    JpegSize {
        width: u32,
        height: u32,
        got_w: u32,
        got_h: u32,
    },
}

/// Convert one frame to 8-bit gray. `stride` is the driver's `bytesperline` (ignored for MJPG).
pub fn to_gray(
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: usize,
    data: &[u8],
) -> Result<GrayImage, ConvertError> {
    if format == PixelFormat::Mjpg {
        return decode_jpeg(width, height, data);
    }
    let min = format.min_stride(width).unwrap_or(0);
    if stride < min {
        return Err(ConvertError::StrideTooSmall {
            format,
            width,
            height,
            stride,
            min,
        });
    }
    // The last row needs only its packed bytes, not a full stride (some drivers size buffers so).
    let need = match format.frame_len(height, stride) {
        Some(n) if height > 0 => n - (stride - min),
        _ => 0,
    };
    if data.len() < need {
        return Err(ConvertError::ShortFrame {
            format,
            width,
            height,
            stride,
            got: data.len(),
            need,
        });
    }
    let (w, h) = (width as usize, height as usize);
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        let row = &data[y * stride..];
        let dst = &mut out[y * w..(y + 1) * w];
        match format {
            PixelFormat::Grey | PixelFormat::Nv12 => dst.copy_from_slice(&row[..w]),
            PixelFormat::Y16 => {
                for x in 0..w {
                    dst[x] = row[2 * x + 1];
                }
            }
            PixelFormat::Yuyv => {
                for x in 0..w {
                    dst[x] = row[2 * x];
                }
            }
            PixelFormat::Uyvy => {
                for x in 0..w {
                    dst[x] = row[2 * x + 1];
                }
            }
            PixelFormat::Rgb3 => {
                for x in 0..w {
                    dst[x] = luma(row[3 * x], row[3 * x + 1], row[3 * x + 2]);
                }
            }
            PixelFormat::Bgr3 => {
                for x in 0..w {
                    dst[x] = luma(row[3 * x + 2], row[3 * x + 1], row[3 * x]);
                }
            }
            PixelFormat::Xr24 => {
                for x in 0..w {
                    dst[x] = luma(row[4 * x + 2], row[4 * x + 1], row[4 * x]);
                }
            }
            PixelFormat::Mjpg => {}
        }
    }
    GrayImage::from_raw(width, height, out).ok_or(ConvertError::ShortFrame {
        format,
        width,
        height,
        stride,
        got: data.len(),
        need,
    })
}

/// BT.601 luma with weights summing to 256 (gray in → same gray out).
fn luma(r: u8, g: u8, b: u8) -> u8 {
    ((77 * r as u32 + 150 * g as u32 + 29 * b as u32 + 128) >> 8) as u8
}

/// Encode a gray image into a raw frame of `format` with the given stride (padding bytes are 0xAA so
/// that a converter reading them is caught). Chroma is neutral (128), RGB channels are equal, so
/// [`to_gray`] returns exactly `gray`. Used to feed V4L2 output devices and by tests. `None` for MJPG.
pub fn encode_gray(format: PixelFormat, gray: &GrayImage, stride: usize) -> Option<Vec<u8>> {
    let (width, height) = gray.dimensions();
    if stride < format.min_stride(width)? {
        return None;
    }
    let (w, h) = (width as usize, height as usize);
    let mut out = vec![0xAAu8; format.frame_len(height, stride)?];
    for y in 0..h {
        let src = &gray.as_raw()[y * w..(y + 1) * w];
        let row = &mut out[y * stride..];
        for x in 0..w {
            let g = src[x];
            match format {
                PixelFormat::Grey | PixelFormat::Nv12 => row[x] = g,
                PixelFormat::Y16 => row[2 * x..2 * x + 2].copy_from_slice(&[0, g]),
                PixelFormat::Yuyv => row[2 * x..2 * x + 2].copy_from_slice(&[g, 128]),
                PixelFormat::Uyvy => row[2 * x..2 * x + 2].copy_from_slice(&[128, g]),
                PixelFormat::Rgb3 | PixelFormat::Bgr3 => {
                    row[3 * x..3 * x + 3].copy_from_slice(&[g, g, g])
                }
                PixelFormat::Xr24 => row[4 * x..4 * x + 4].copy_from_slice(&[g, g, g, 0]),
                PixelFormat::Mjpg => return None,
            }
        }
        if matches!(format, PixelFormat::Yuyv | PixelFormat::Uyvy) && w % 2 == 1 {
            // complete the last pair of an odd-width row
            let i = 2 * w;
            row[i..i + 2].copy_from_slice(if format == PixelFormat::Yuyv {
                &[0, 128]
            } else {
                &[128, 0]
            });
        }
    }
    if format == PixelFormat::Nv12 {
        let chroma_start = stride * h;
        for row in out[chroma_start..].chunks_mut(stride) {
            row[..w].fill(128);
        }
    }
    Some(out)
}

/// Decode one MJPG frame to gray, refusing empty, truncated, corrupt or wrongly sized frames.
pub fn decode_jpeg(width: u32, height: u32, data: &[u8]) -> Result<GrayImage, ConvertError> {
    use image::ImageDecoder;
    let len = data.len();
    if len == 0 {
        return Err(ConvertError::EmptyJpeg);
    }
    // Some cameras pad the JPEG with zeros up to bytesused; the EOI marker must end the real data.
    let end = data.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
    if end < 4 || data[..2] != [0xFF, 0xD8] {
        return Err(ConvertError::CorruptJpeg {
            len,
            reason: "no start-of-image marker".into(),
        });
    }
    if data[end - 2..end] != [0xFF, 0xD9] {
        return Err(ConvertError::TruncatedJpeg { len });
    }
    let corrupt = |e: image::ImageError| ConvertError::CorruptJpeg {
        len,
        reason: e.to_string(),
    };
    let decoder = image::codecs::jpeg::JpegDecoder::new(std::io::Cursor::new(&data[..end]))
        .map_err(corrupt)?;
    let (got_w, got_h) = decoder.dimensions();
    if (got_w, got_h) != (width, height) {
        return Err(ConvertError::JpegSize {
            width,
            height,
            got_w,
            got_h,
        });
    }
    let img = image::DynamicImage::from_decoder(decoder).map_err(corrupt)?;
    Ok(img.into_luma8())
}
