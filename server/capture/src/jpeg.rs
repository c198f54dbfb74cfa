//! JPEG helpers for frames that travel over the network (`Cameras.Push`, policy observations): decode to
//! packed RGB, encode from packed RGB. Pure Rust, so the server does not need an FFmpeg context per call.

use crate::camera::Frame;
use std::sync::Arc;

/// Largest accepted side, in pixels: anything bigger is not a camera frame (and would cost memory).
pub const MAX_SIDE_PX: u32 = 8192;

/// Why a JPEG could not be decoded or encoded.
#[derive(Debug, thiserror::Error)]
pub enum JpegError {
    #[error("not a decodable JPEG: {0}")]
    Decode(String),
    #[error("JPEG is {width}x{height}, larger than {MAX_SIDE_PX} px on a side")]
    TooLarge { width: u32, height: u32 },
    #[error("unsupported JPEG pixel format {0}")]
    PixelFormat(String),
    #[error("RGB buffer of {len} bytes does not hold {width}x{height} pixels")]
    BadBuffer { len: usize, width: u32, height: u32 },
    #[error("cannot encode JPEG: {0}")]
    Encode(String),
}

/// Decodes a baseline or progressive JPEG (RGB or grayscale) into an RGB [`Frame`] with
/// `capture_time_ns` and `seq` zero (the caller stamps them).
pub fn decode_jpeg(bytes: &[u8]) -> Result<Frame, JpegError> {
    let mut dec = jpeg_decoder::Decoder::new(bytes);
    dec.read_info().map_err(|e| JpegError::Decode(e.to_string()))?;
    let info = dec.info().ok_or_else(|| JpegError::Decode("no header".into()))?;
    let (width, height) = (u32::from(info.width), u32::from(info.height));
    if width > MAX_SIDE_PX || height > MAX_SIDE_PX || width == 0 || height == 0 {
        return Err(JpegError::TooLarge { width, height });
    }
    let pixels = dec.decode().map_err(|e| JpegError::Decode(e.to_string()))?;
    let rgb = match info.pixel_format {
        jpeg_decoder::PixelFormat::RGB24 => pixels,
        jpeg_decoder::PixelFormat::L8 => pixels.iter().flat_map(|l| [*l, *l, *l]).collect(),
        other => return Err(JpegError::PixelFormat(format!("{other:?}"))),
    };
    if rgb.len() != width as usize * height as usize * 3 {
        return Err(JpegError::Decode("truncated image data".into()));
    }
    Ok(Frame {
        width,
        height,
        rgb: Arc::new(rgb),
        capture_time_ns: 0,
        seq: 0,
    })
}

/// Encodes packed RGB as a JPEG of `quality` 1..=100.
pub fn encode_jpeg(rgb: &[u8], width: u32, height: u32, quality: u8) -> Result<Vec<u8>, JpegError> {
    if rgb.len() != width as usize * height as usize * 3 || width == 0 || height == 0 {
        return Err(JpegError::BadBuffer {
            len: rgb.len(),
            width,
            height,
        });
    }
    let (w, h) = (
        u16::try_from(width).map_err(|_| JpegError::TooLarge { width, height })?,
        u16::try_from(height).map_err(|_| JpegError::TooLarge { width, height })?,
    );
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, quality.clamp(1, 100))
        .encode(rgb, w, h, jpeg_encoder::ColorType::Rgb)
        .map_err(|e| JpegError::Encode(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::draw_test_pattern;

    #[test]
    fn jpeg_round_trip_is_close() {
        let mut rgb = Vec::new();
        draw_test_pattern(64, 48, 5, &mut rgb);
        let jpg = encode_jpeg(&rgb, 64, 48, 95).unwrap();
        assert_eq!(&jpg[..2], &[0xFF, 0xD8]);
        let f = decode_jpeg(&jpg).unwrap();
        assert_eq!((f.width, f.height, f.rgb.len()), (64, 48, rgb.len()));
        let mean_err: f64 = f
            .rgb
            .iter()
            .zip(&rgb)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / rgb.len() as f64;
        assert!(mean_err < 6.0, "mean abs error {mean_err}");
    }

    #[test]
    fn garbage_and_bad_buffers_are_errors() {
        assert!(matches!(decode_jpeg(b"not a jpeg"), Err(JpegError::Decode(_))));
        assert!(matches!(decode_jpeg(&[]), Err(JpegError::Decode(_))));
        assert!(matches!(
            encode_jpeg(&[0; 10], 4, 4, 80),
            Err(JpegError::BadBuffer { .. })
        ));
    }
}
