//! Reading frames back out of a dataset's video: the few frames `phone2act dataset plot` shows per camera.

use crate::error::RecorderError;
use crate::frame::Frame;
use ffmpeg_next as ffmpeg;
use ffmpeg_next::format::Pixel;
use ffmpeg_next::software::scaling;
use ffmpeg_next::util::frame::video::Video as VideoFrame;
use std::path::Path;
use std::sync::Arc;

fn video_error(path: &Path, detail: impl std::fmt::Display) -> RecorderError {
    RecorderError::Video {
        camera: path.display().to_string(),
        detail: detail.to_string(),
    }
}

/// The frames presented at `times_s` (seconds from the start of the file), as RGB no wider
/// than `max_width_px` (aspect kept). Each is the first frame whose presentation time is at or after the
/// time asked for, less half a frame (so `i / fps` finds frame *i* despite rounding); a time past the last
/// frame gets the last frame. An empty file or a file without a video stream is an error.
pub fn frames_at(path: &Path, times_s: &[f64], max_width_px: u32) -> Result<Vec<Frame>, RecorderError> {
    crate::av::init_ffmpeg();
    let mut input =
        ffmpeg::format::input(path).map_err(|e| video_error(path, format!("cannot open: {e}")))?;
    let stream = input
        .streams()
        .best(ffmpeg::media::Type::Video)
        .ok_or_else(|| video_error(path, "no video stream"))?;
    let index = stream.index();
    let time_base = f64::from(stream.time_base());
    let rate = stream.avg_frame_rate();
    let half_frame_s = if rate.numerator() > 0 {
        0.5 / f64::from(rate)
    } else {
        1e-3
    };
    let parameters = stream.parameters();
    let context = ffmpeg::codec::context::Context::from_parameters(parameters)
        .map_err(|e| video_error(path, format!("cannot read the codec parameters: {e}")))?;
    // FFmpeg's own AV1 decoder needs a hardware accelerator; dav1d decodes in software.
    let av1 = context.id() == ffmpeg::codec::Id::AV1;
    let mut decoder = {
        let _guard = crate::av::CODEC_LOCK.lock();
        match ffmpeg::decoder::find_by_name("libdav1d").filter(|_| av1) {
            Some(codec) => context
                .decoder()
                .open_as(codec)
                .and_then(ffmpeg::decoder::Opened::video),
            None => context.decoder().video(),
        }
    }
    .map_err(|e| video_error(path, format!("no decoder for this stream: {e}")))?;

    let mut scaler: Option<scaling::Context> = None;
    let pts_s = |frame: &VideoFrame| frame.timestamp().or(frame.pts()).unwrap_or(0) as f64 * time_base;
    // The newest decoded frame and a spare to receive into, swapped rather than copied, so that only the
    // frames shown are converted to RGB.
    let (mut current, mut spare) = (VideoFrame::empty(), VideoFrame::empty());
    let mut current_s: Option<f64> = None;
    let mut eof = false;
    // Seeking helps only where keyframes are close (lerobot and phone2act write one every 2 frames); an AV1
    // file recorded before the recorder asked SVT-AV1 for periodic keyframes has one per episode, where every
    // seek would go back to the first frame: then decode straight on.
    let mut straight_on = false;
    let mut out = Vec::with_capacity(times_s.len());
    for &t_s in times_s {
        let ahead = current_s.is_some_and(|c| c - half_frame_s <= t_s);
        if !(ahead && (straight_on || current_s.is_some_and(|c| t_s - c < SEEK_GAP_S))) {
            let before = current_s.filter(|_| ahead);
            // To the keyframe at or before t (AV_TIME_BASE units).
            let target_us = (t_s.max(0.0) * 1e6) as i64;
            input
                .seek(target_us, ..target_us + 1)
                .map_err(|e| video_error(path, format!("cannot seek to {t_s:.3} s: {e}")))?;
            decoder.flush();
            (eof, current_s) = (false, None);
            if next_frame(&mut input, &mut decoder, index, &mut spare, &mut eof)
                .map_err(|e| video_error(path, e))?
            {
                std::mem::swap(&mut current, &mut spare);
                let landed_s = pts_s(&current);
                current_s = Some(landed_s);
                straight_on |= before.is_some_and(|b| landed_s <= b);
            }
        }
        while current_s.is_none_or(|c| c + half_frame_s < t_s) {
            if !next_frame(&mut input, &mut decoder, index, &mut spare, &mut eof)
                .map_err(|e| video_error(path, e))?
            {
                // Past the last frame: the last frame.
                break;
            }
            std::mem::swap(&mut current, &mut spare);
            current_s = Some(pts_s(&current));
        }
        if current_s.is_none() {
            return Err(video_error(path, format!("no frame at or before {t_s:.3} s")));
        }
        out.push(to_rgb(path, &current, max_width_px, &mut scaler)?);
    }
    Ok(out)
}

/// A gap between two frames asked for, s, beyond which seeking is tried rather than decoding through it.
const SEEK_GAP_S: f64 = 1.0;

/// Receives the next decoded frame of stream `index` into `frame`; `false` at the end of the stream.
fn next_frame(
    input: &mut ffmpeg::format::context::Input,
    decoder: &mut ffmpeg::decoder::Video,
    index: usize,
    frame: &mut VideoFrame,
    eof: &mut bool,
) -> Result<bool, String> {
    loop {
        if decoder.receive_frame(frame).is_ok() {
            return Ok(true);
        }
        if *eof {
            return Ok(false);
        }
        if let Some((_, packet)) = input.packets().find(|(s, _)| s.index() == index) {
            decoder
                .send_packet(&packet)
                .map_err(|e| format!("cannot decode: {e}"))?;
        } else {
            let _ = decoder.send_eof();
            *eof = true;
        }
    }
}

/// Packed RGB of a decoded frame, scaled down to at most `max_width_px` wide.
fn to_rgb(
    path: &Path,
    frame: &VideoFrame,
    max_width_px: u32,
    scaler: &mut Option<scaling::Context>,
) -> Result<Frame, RecorderError> {
    let (w, h) = (frame.width(), frame.height());
    let out_w = w.min(max_width_px.max(2));
    let out_h = ((u64::from(h) * u64::from(out_w) / u64::from(w.max(1))) as u32).max(1);
    let stale = scaler.as_ref().is_none_or(|s| {
        let i = s.input();
        (i.format, i.width, i.height) != (frame.format(), w, h)
    });
    if stale {
        *scaler = Some(
            scaling::Context::get(
                frame.format(),
                w,
                h,
                Pixel::RGB24,
                out_w,
                out_h,
                scaling::Flags::BILINEAR,
            )
            .map_err(|e| video_error(path, format!("cannot convert to RGB: {e}")))?,
        );
    }
    let mut rgb = VideoFrame::empty();
    scaler
        .as_mut()
        .map(|s| s.run(frame, &mut rgb))
        .transpose()
        .map_err(|e| video_error(path, format!("cannot convert to RGB: {e}")))?;
    let stride = rgb.stride(0);
    let row = out_w as usize * 3;
    let data = rgb.data(0);
    let mut packed = Vec::with_capacity(row * out_h as usize);
    for y in 0..out_h as usize {
        packed.extend_from_slice(&data[y * stride..y * stride + row]);
    }
    Ok(Frame {
        width: out_w,
        height: out_h,
        rgb: Arc::new(packed),
        capture_time_ns: 0,
        seq: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// lerobot's v3.0 fixture: 30 frames of 128x96 at 10 fps (three episodes in one AV1 file).
    const FIXTURE: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/lerobot_sample_v30/videos/observation.images.front/chunk-000/file-000.mp4"
    );

    #[test]
    fn frames_at_times_decode_scaled_and_past_the_end_repeat_the_last() {
        let frames = frames_at(Path::new(FIXTURE), &[0.0, 1.0, 2.9, 50.0], 64).unwrap();
        assert_eq!(frames.len(), 4);
        for f in &frames {
            assert_eq!((f.width, f.height), (64, 48));
            assert_eq!(f.rgb.len(), 64 * 48 * 3);
        }
        assert_eq!(frames[2].rgb, frames[3].rgb, "past the end: the last frame");
        assert_ne!(
            frames[0].rgb, frames[1].rgb,
            "the fixture's frames change over time"
        );
        // Each time is sought on its own: asked alone, or in another order, the same frame.
        let alone = frames_at(Path::new(FIXTURE), &[1.0], 64).unwrap();
        assert_eq!(alone[0].rgb, frames[1].rgb);
        let reversed = frames_at(Path::new(FIXTURE), &[2.9, 0.0], 64).unwrap();
        assert_eq!(
            (&reversed[0].rgb, &reversed[1].rgb),
            (&frames[2].rgb, &frames[0].rgb)
        );
        let err = frames_at(Path::new("/nonexistent.mp4"), &[0.0], 64).unwrap_err();
        assert!(err.to_string().contains("cannot open"), "{err}");
    }

    #[test]
    fn missing_files_are_named() {
        let err = frames_at(Path::new("/nonexistent.mp4"), &[0.0], 64).unwrap_err();
        assert!(err.to_string().contains("cannot open"), "{err}");
    }
}
