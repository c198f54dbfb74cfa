//! Pushed camera frames: the checks a frame passes before anyone decodes it.

use crate::v1;

/// The pixels of a pushed frame whose size and encoding were checked against its camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PushedPixels<'a> {
    /// Packed RGB, exactly width × height × 3 bytes.
    Rgb8(&'a [u8]),
    /// A JPEG still to decode (its own size is checked after decoding).
    Jpeg(&'a [u8]),
}

/// Why a pushed frame was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("frame is {got_width}x{got_height}, camera {camera:?} is configured for {width}x{height}")]
    WrongSize {
        camera: String,
        got_width: u32,
        got_height: u32,
        width: u32,
        height: u32,
    },
    #[error("RGB8 frame has {got} bytes, expected {expected}")]
    WrongLength { got: usize, expected: usize },
    #[error("unsupported image encoding {0}")]
    UnsupportedEncoding(i32),
}

/// Checks `frame` against a camera configured at `width`×`height`.
pub fn pushed_pixels(
    frame: &v1::CameraFrame,
    width: u32,
    height: u32,
) -> Result<PushedPixels<'_>, FrameError> {
    if frame.width != width || frame.height != height {
        return Err(FrameError::WrongSize {
            camera: frame.camera.clone(),
            got_width: frame.width,
            got_height: frame.height,
            width,
            height,
        });
    }
    match v1::ImageEncoding::try_from(frame.encoding) {
        Ok(v1::ImageEncoding::Rgb8) => {
            let expected = width as usize * height as usize * 3;
            if frame.data.len() == expected {
                Ok(PushedPixels::Rgb8(&frame.data))
            } else {
                Err(FrameError::WrongLength {
                    got: frame.data.len(),
                    expected,
                })
            }
        }
        Ok(v1::ImageEncoding::Jpeg) => Ok(PushedPixels::Jpeg(&frame.data)),
        _ => Err(FrameError::UnsupportedEncoding(frame.encoding)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(width: u32, height: u32, encoding: v1::ImageEncoding, len: usize) -> v1::CameraFrame {
        v1::CameraFrame {
            camera: "wrist".into(),
            width,
            height,
            encoding: encoding as i32,
            data: vec![0; len],
            ..v1::CameraFrame::default()
        }
    }

    #[test]
    fn size_length_and_encoding_are_checked_before_decoding() {
        let ok = frame(4, 2, v1::ImageEncoding::Rgb8, 24);
        assert_eq!(pushed_pixels(&ok, 4, 2), Ok(PushedPixels::Rgb8(&[0; 24])));
        assert_eq!(
            pushed_pixels(&ok, 8, 2).unwrap_err().to_string(),
            "frame is 4x2, camera \"wrist\" is configured for 8x2"
        );
        assert_eq!(
            pushed_pixels(&frame(4, 2, v1::ImageEncoding::Rgb8, 23), 4, 2)
                .unwrap_err()
                .to_string(),
            "RGB8 frame has 23 bytes, expected 24"
        );
        assert!(matches!(
            pushed_pixels(&frame(4, 2, v1::ImageEncoding::Jpeg, 3), 4, 2),
            Ok(PushedPixels::Jpeg(_))
        ));
        assert_eq!(
            pushed_pixels(&frame(4, 2, v1::ImageEncoding::None, 0), 4, 2),
            Err(FrameError::UnsupportedEncoding(v1::ImageEncoding::None as i32))
        );
    }
}
