//! The phone page's camera preview: a small JPEG of one camera over the page's own socket, so the operator
//! sees what is recorded.
//!
//! Off until the page asks (`{"type":"preview","camera":"front","max_fps":5,"width":320}`); only that socket
//! gets frames, as binary WebSocket messages holding one JPEG each (the Phone2Act app speaks rosbridge on
//! another endpoint and never sees them). Frames come from the server like the rosbridge image topics
//! ([`Upstream::camera_jpeg`]), are shrunk to at most `width` pixels wide while decoding (the JPEG's own
//! 1/2, 1/4, 1/8 scaling, no resampling pass) and re-encoded at `quality`. A fetch happens at most once per
//! `1 / max_fps` and only when the previous frame has reached the page (see `conn::PreviewSlot`), so a slow
//! link lowers the preview's rate instead of queueing images in front of feedback. Before each frame a text
//! message `{"type":"preview_frame","bytes":…,"capture_unix_ms":…}` gives its capture time on the gateway's
//! clock, keyed by the frame's size, for the page's glass-to-glass latency.

use crate::conn::{Out, PreviewSlot};
use crate::upstream::Upstream;
use phone2act_proto::v1::ImageEncoding;
use serde::Deserialize;
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;

/// Default and highest preview rate: enough to see the scene; the recorder has the full rate.
pub(crate) const DEFAULT_MAX_FPS: f64 = 5.0;
pub(crate) const MAX_FPS: f64 = 10.0;
/// Default and allowed preview widths, in pixels.
pub(crate) const DEFAULT_WIDTH_PX: u32 = 320;
pub(crate) const MIN_WIDTH_PX: u32 = 16;
pub(crate) const MAX_WIDTH_PX: u32 = 640;
/// JPEG quality of the preview: about 10 kB for 320x240, legible on a phone screen.
pub(crate) const DEFAULT_QUALITY: u8 = 60;

/// The page's request, as it arrives.
#[derive(Debug, Deserialize)]
pub(crate) struct PreviewRequest {
    camera: String,
    #[serde(default)]
    max_fps: Option<f64>,
    #[serde(default)]
    width: Option<u32>,
    #[serde(default)]
    quality: Option<u8>,
}

/// A checked request.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PreviewParams {
    pub camera: String,
    pub max_fps: f64,
    pub width_px: u32,
    pub quality: u8,
}

impl PreviewRequest {
    /// Applies the defaults and refuses what is out of range (nothing is clamped silently).
    pub(crate) fn check(self) -> Result<PreviewParams, String> {
        if self.camera.is_empty() || self.camera.len() > 64 {
            return Err("preview camera name must be 1 to 64 characters".into());
        }
        let max_fps = self.max_fps.unwrap_or(DEFAULT_MAX_FPS);
        if !(max_fps > 0.0 && max_fps <= MAX_FPS) {
            return Err(format!(
                "preview max_fps must be in (0, {MAX_FPS}], got {max_fps}"
            ));
        }
        let width_px = self.width.unwrap_or(DEFAULT_WIDTH_PX);
        if !(MIN_WIDTH_PX..=MAX_WIDTH_PX).contains(&width_px) {
            return Err(format!(
                "preview width must be {MIN_WIDTH_PX} to {MAX_WIDTH_PX} px, got {width_px}"
            ));
        }
        let quality = self.quality.unwrap_or(DEFAULT_QUALITY);
        if !(1..=100).contains(&quality) {
            return Err(format!("preview quality must be 1 to 100, got {quality}"));
        }
        Ok(PreviewParams {
            camera: self.camera,
            max_fps,
            width_px,
            quality,
        })
    }
}

/// Decodes `jpeg` at the largest of 1, 1/2, 1/4, 1/8 of its size that is at most `max_width_px` wide (1/8
/// if none is: a camera wider than 8 × 640 px) and re-encodes it at `quality`.
pub(crate) fn shrink(jpeg: &[u8], max_width_px: u32, quality: u8) -> Result<Vec<u8>, String> {
    let mut decoder = jpeg_decoder::Decoder::new(jpeg);
    decoder.read_info().map_err(|e| format!("camera JPEG: {e}"))?;
    let info = decoder.info().ok_or("camera JPEG has no header")?;
    let (width, height) = (u32::from(info.width), u32::from(info.height));
    let divisor = [1, 2, 4, 8]
        .into_iter()
        .find(|d| width.div_ceil(*d) <= max_width_px)
        .unwrap_or(8);
    // The decoder picks the smallest scale whose output is at least this large: exactly 1/divisor.
    let requested = |side: u32| u16::try_from(side.div_ceil(divisor)).unwrap_or(u16::MAX);
    let (out_w, out_h) = decoder
        .scale(requested(width), requested(height))
        .map_err(|e| format!("camera JPEG: {e}"))?;
    let pixels = decoder.decode().map_err(|e| format!("camera JPEG: {e}"))?;
    let color = match decoder.info().map(|i| i.pixel_format) {
        Some(jpeg_decoder::PixelFormat::RGB24) => jpeg_encoder::ColorType::Rgb,
        Some(jpeg_decoder::PixelFormat::L8) => jpeg_encoder::ColorType::Luma,
        other => return Err(format!("camera JPEG pixel format {other:?} is not RGB or grey")),
    };
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, quality)
        .encode(&pixels, out_w, out_h, color)
        .map_err(|e| format!("preview JPEG: {e}"))?;
    Ok(out)
}

/// Starts the preview of `params.camera` for one page socket on `runtime` (the live video's, off the control
/// path's thread; `upstream` is that runtime's connection): says `preview on` (or, for a camera the server does
/// not have, an error and `preview off`), then fills `slot` at most `max_fps` times a second until aborted.
pub(crate) fn spawn(
    runtime: &tokio::runtime::Handle,
    upstream: Upstream,
    params: PreviewParams,
    slot: Arc<PreviewSlot>,
    out: Out,
) -> JoinHandle<()> {
    let generation = slot.open();
    runtime.spawn(async move {
        let camera = params.camera.clone();
        match upstream.camera_names().await {
            Ok(names) if names.contains(&camera) => {}
            Ok(names) => {
                let message = if names.is_empty() {
                    format!("unknown camera \"{camera}\": this server has no camera")
                } else {
                    format!(
                        "unknown camera \"{camera}\"; this server has: {}",
                        names.join(", ")
                    )
                };
                out.text(json!({"type": "error", "message": message}).to_string());
                out.text(json!({"type": "preview", "state": "off", "reason": message}).to_string());
                return;
            }
            Err(status) => {
                let message = format!("camera list unavailable: {}", status.message());
                out.text(json!({"type": "error", "message": message}).to_string());
                out.text(json!({"type": "preview", "state": "off", "reason": message}).to_string());
                return;
            }
        }
        out.text(
            json!({
                "type": "preview", "state": "on", "camera": camera, "max_fps": params.max_fps,
                "width": params.width_px, "quality": params.quality,
            })
            .to_string(),
        );
        // Delay: after a slow fetch the next one waits a whole period, so the rate never exceeds max_fps.
        let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / params.max_fps));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut warned = false;
        loop {
            tick.tick().await;
            if slot.busy() {
                // The page has not taken the last frame: the link is slower than max_fps.
                continue;
            }
            let result = match upstream.camera_frame(&camera, ImageEncoding::Jpeg).await {
                Ok(Some(timed)) => {
                    // Decoding and encoding a frame takes milliseconds: off the runtime's thread (its blocking
                    // threads inherit the video thread's lower priority).
                    let (width, quality) = (params.width_px, params.quality);
                    let jpeg = timed.frame.data;
                    tokio::task::spawn_blocking(move || shrink(&jpeg, width, quality))
                        .await
                        .unwrap_or_else(|e| Err(e.to_string()))
                        .map(|shrunk| (shrunk, timed.capture_unix_ns))
                }
                Ok(None) => continue,
                Err(status) => Err(status.message().to_owned()),
            };
            match result {
                Ok((shrunk, capture_unix_ns)) => {
                    // The frame's capture time, keyed by its size (the binary frame carries none), so that the
                    // page can show the preview's glass-to-glass latency as it does the video's.
                    out.text(
                        json!({
                            "type": "preview_frame",
                            "bytes": shrunk.len(),
                            "capture_unix_ms": capture_unix_ns as f64 / 1e6,
                        })
                        .to_string(),
                    );
                    slot.put(generation, shrunk.into());
                    warned = false;
                }
                Err(e) if !warned => {
                    // Once per stall, so the operator learns why the image froze (the page's own rule then
                    // turns the preview off).
                    warned = true;
                    tracing::warn!(camera, error = %e, "phone page preview: camera image unavailable");
                    let message = format!("camera {camera}: no preview image: {e}");
                    out.text(json!({"type": "error", "message": message}).to_string());
                }
                Err(_) => {}
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(text: &str) -> Result<PreviewParams, String> {
        serde_json::from_str::<PreviewRequest>(text)
            .map_err(|e| e.to_string())?
            .check()
    }

    #[test]
    fn defaults_are_small_and_bad_values_are_refused() {
        let p = request(r#"{"camera":"front"}"#).unwrap();
        assert_eq!((p.max_fps, p.width_px, p.quality), (5.0, 320, 60));
        for (text, says) in [
            (r#"{"camera":"front","max_fps":0}"#, "max_fps"),
            (r#"{"camera":"front","max_fps":30}"#, "max_fps"),
            (r#"{"camera":"front","width":4000}"#, "width"),
            (r#"{"camera":"front","quality":0}"#, "quality"),
            (r#"{"camera":""}"#, "camera"),
        ] {
            let e = request(text).unwrap_err();
            assert!(e.contains(says), "{text}: {e}");
        }
    }

    fn test_jpeg(width: u16, height: u16) -> Vec<u8> {
        // A gradient, so that the encoder has something to keep.
        let rgb: Vec<u8> = (0..u32::from(width) * u32::from(height))
            .flat_map(|i| {
                let (x, y) = (i % u32::from(width), i / u32::from(width));
                [(x % 256) as u8, (y % 256) as u8, 128]
            })
            .collect();
        let mut out = Vec::new();
        jpeg_encoder::Encoder::new(&mut out, 90)
            .encode(&rgb, width, height, jpeg_encoder::ColorType::Rgb)
            .unwrap();
        out
    }

    /// Width, height and pixel bytes of a JPEG, read back by the decoder.
    fn size(jpeg: &[u8]) -> (u16, u16, usize) {
        let mut d = jpeg_decoder::Decoder::new(jpeg);
        let pixels = d.decode().unwrap();
        let info = d.info().unwrap();
        (info.width, info.height, pixels.len())
    }

    #[test]
    fn frames_shrink_by_powers_of_two_to_fit_the_width_and_keep_their_aspect() {
        let big = test_jpeg(640, 480);
        let s = shrink(&big, 320, 60).unwrap();
        assert_eq!(size(&s), (320, 240, 320 * 240 * 3));
        assert!(s.len() < big.len(), "{} >= {}", s.len(), big.len());
        // 1/4 is the largest that fits 200 px.
        assert_eq!(size(&shrink(&big, 200, 60).unwrap()).0, 160);
        // Already small enough: the size is kept.
        assert_eq!(size(&shrink(&test_jpeg(320, 180), 320, 60).unwrap()).1, 180);
        assert!(shrink(b"not a jpeg", 320, 60).is_err());
    }
}
