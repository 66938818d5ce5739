//! Pixel-format conversion to gray: every format, odd widths and padded strides, and MJPG frames that
//! are empty, truncated or garbage (dropped with an error, never a panic).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use cubecal::capture::GrayImage;
use cubecal::capture::convert::{ConvertError, PixelFormat, decode_jpeg, encode_gray, to_gray};

/// A deterministic gray test image with every value 0..=255 present and no symmetry.
fn pattern(w: u32, h: u32) -> GrayImage {
    GrayImage::from_fn(w, h, |x, y| {
        image::Luma([((x * 7 + y * 13 + (x * y) % 5) % 256) as u8])
    })
}

#[test]
fn every_raw_format_round_trips_exactly_with_odd_sizes_and_padded_strides() {
    for format in PixelFormat::ALL {
        if format == PixelFormat::Mjpg {
            continue;
        }
        for (w, h) in [(1, 1), (7, 5), (64, 48), (33, 17)] {
            let min = format.min_stride(w).unwrap_or(0);
            for pad in [0, 1, 3, 64] {
                let stride = min + pad;
                let gray = pattern(w, h);
                let raw = encode_gray(format, &gray, stride).unwrap();
                let back = to_gray(format, w, h, stride, &raw);
                assert_eq!(back, Ok(gray), "{format} {w}x{h} stride {stride}");
            }
        }
    }
}

#[test]
fn known_pixel_values_per_format() {
    // one 2x1 image, hand-built bytes (not via encode_gray) so the converter is checked independently
    let cases: [(PixelFormat, Vec<u8>, [u8; 2]); 8] = [
        (PixelFormat::Grey, vec![10, 200], [10, 200]),
        (PixelFormat::Y16, vec![0xff, 10, 0x00, 200], [10, 200]),
        (PixelFormat::Yuyv, vec![10, 90, 200, 240], [10, 200]),
        (PixelFormat::Uyvy, vec![90, 10, 240, 200], [10, 200]),
        // NV12: luma row, then one chroma row (2 bytes)
        (PixelFormat::Nv12, vec![10, 200, 128, 128], [10, 200]),
        // pure red and pure blue: BT.601 weights 77/256 and 29/256
        (PixelFormat::Rgb3, vec![255, 0, 0, 0, 0, 255], [77, 29]),
        (PixelFormat::Bgr3, vec![0, 0, 255, 255, 0, 0], [77, 29]),
        (
            PixelFormat::Xr24,
            vec![0, 0, 255, 9, 255, 0, 0, 9],
            [77, 29],
        ),
    ];
    for (format, raw, want) in cases {
        let stride = format.min_stride(2).unwrap_or(0);
        let g = to_gray(format, 2, 1, stride, &raw);
        assert_eq!(g.map(|g| g.into_raw()), Ok(want.to_vec()), "{format}");
    }
    // green is the heaviest weight
    let g = to_gray(PixelFormat::Rgb3, 1, 1, 3, &[0, 255, 0]);
    assert_eq!(g.map(|g| g.into_raw()), Ok(vec![149]));
}

#[test]
fn padding_bytes_are_never_read_as_pixels() {
    // stride 10 for a 3-pixel GREY row; padding full of 255 must not leak into the image
    let raw = [1, 2, 3, 255, 255, 255, 255, 255, 255, 255, 4, 5, 6];
    let g = to_gray(PixelFormat::Grey, 3, 2, 10, &raw);
    assert_eq!(g.map(|g| g.into_raw()), Ok(vec![1, 2, 3, 4, 5, 6]));
}

#[test]
fn short_frames_and_small_strides_are_errors_not_panics() {
    for format in PixelFormat::ALL {
        if format == PixelFormat::Mjpg {
            continue;
        }
        let min = format.min_stride(9).unwrap_or(0);
        let raw = vec![0u8; min * 5];
        assert!(
            matches!(
                to_gray(format, 9, 6, min, &raw),
                Err(ConvertError::ShortFrame { .. })
            ),
            "{format} short frame"
        );
        assert!(
            matches!(
                to_gray(format, 9, 6, min - 1, &raw),
                Err(ConvertError::StrideTooSmall { .. })
            ),
            "{format} small stride"
        );
        assert!(
            matches!(
                to_gray(format, 9, 6, min, &[]),
                Err(ConvertError::ShortFrame { .. })
            ),
            "{format} empty"
        );
    }
}

fn jpeg_of(gray: &GrayImage) -> Vec<u8> {
    let mut v = Vec::new();
    let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut v, 95);
    gray.write_with_encoder(enc).unwrap();
    v
}

#[test]
fn mjpg_decodes_to_gray_within_jpeg_tolerance() {
    let gray = pattern(64, 48);
    let jpg = jpeg_of(&gray);
    assert!(jpg.len() > 100, "encoder produced {} bytes", jpg.len());
    let back = to_gray(PixelFormat::Mjpg, 64, 48, 0, &jpg);
    let back = back.unwrap();
    assert_eq!(back.dimensions(), (64, 48));
    let mean_abs: f64 = gray
        .as_raw()
        .iter()
        .zip(back.as_raw())
        .map(|(a, b)| a.abs_diff(*b) as f64)
        .sum::<f64>()
        / (64.0 * 48.0);
    assert!(mean_abs < 6.0, "mean |diff| {mean_abs}");
    // zero padding after EOI (some cameras pad to bytesused) is accepted
    let mut padded = jpg.clone();
    padded.extend_from_slice(&[0; 100]);
    assert!(decode_jpeg(64, 48, &padded).is_ok());
}

#[test]
fn corrupt_mjpg_frames_are_errors_never_panics() {
    let jpg = jpeg_of(&pattern(64, 48));
    assert_eq!(decode_jpeg(64, 48, &[]), Err(ConvertError::EmptyJpeg));
    // truncated at many points: every one is an error
    for cut in [1, 2, 3, 10, 100, jpg.len() / 2, jpg.len() - 1] {
        let r = decode_jpeg(64, 48, &jpg[..cut]);
        assert!(r.is_err(), "truncated at {cut} bytes accepted");
    }
    // garbage, and garbage with valid markers around it
    let mut seed = 0x2545_f491_u32;
    let mut garbage = vec![0u8; 4096];
    for b in &mut garbage {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        *b = seed as u8;
    }
    assert!(decode_jpeg(64, 48, &garbage).is_err());
    let mut framed = vec![0xFF, 0xD8];
    framed.extend_from_slice(&garbage);
    framed.extend_from_slice(&[0xFF, 0xD9]);
    assert!(decode_jpeg(64, 48, &framed).is_err());
    // the real header with a garbage body
    let mut body = jpg.clone();
    let n = body.len();
    for (i, b) in body[n / 2..n - 2].iter_mut().enumerate() {
        *b = (i * 31 % 251) as u8;
    }
    let _ = decode_jpeg(64, 48, &body); // may decode to noise or fail; must not panic
    // wrong size
    assert!(matches!(
        decode_jpeg(32, 48, &jpg),
        Err(ConvertError::JpegSize { .. })
    ));
}

#[test]
fn fourcc_names_round_trip() {
    for f in PixelFormat::ALL {
        assert_eq!(PixelFormat::from_fourcc(f.fourcc()), Some(f));
    }
    assert_eq!(PixelFormat::from_fourcc(*b"H264"), None);
    assert_eq!(PixelFormat::Y16.to_string(), "Y16");
}
