//! Cameras read through libavdevice: V4L2 webcams (size, fps, MJPEG or raw input) and, for tests on
//! machines without `/dev/video*`, FFmpeg's `lavfi` sources such as `testsrc2`. Each camera runs on its own
//! thread, decodes to RGB and publishes into a [`FrameSlot`] stamped with the time the frame arrived.

use crate::camera::{CaptureThread, Frame, FrameSlot};
use ffmpeg_next::format::Pixel;
use ffmpeg_next::software::scaling;
use ffmpeg_next::util::frame::video::Video as VideoFrame;
use ffmpeg_next::{Dictionary, Rational, codec, format, media};
use phone2act_clock::monotonic_ns;
use phone2act_dataset::av::init_ffmpeg;
use phone2act_dataset::error::RecorderError;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::sync_channel;
use std::time::{Duration, Instant};

/// How to open an FFmpeg input device.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AvCaptureConfig {
    /// libavdevice input format: `v4l2` (alias `video4linux2`) or `lavfi`.
    pub device_format: String,
    /// Device path (`/dev/video0`) or lavfi graph (`testsrc2=size=640x480:rate=30`).
    pub url: String,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub fps: Option<u32>,
    /// V4L2 pixel format to ask for, e.g. `mjpeg` (most webcams only reach 30 fps at 640x480 in MJPEG).
    pub input_format: Option<String>,
    /// Sleep until each frame's presentation time: lavfi sources run as fast as the CPU allows otherwise.
    pub pace_by_pts: bool,
}

impl AvCaptureConfig {
    /// A V4L2 webcam.
    pub fn v4l2(device: &str, width: u32, height: u32, fps: u32, mjpeg: bool) -> Self {
        AvCaptureConfig {
            device_format: "v4l2".into(),
            url: device.into(),
            width: Some(width),
            height: Some(height),
            fps: Some(fps),
            input_format: mjpeg.then(|| "mjpeg".to_owned()),
            pace_by_pts: false,
        }
    }

    /// FFmpeg's `testsrc2` through lavfi, paced to real time: a stand-in webcam.
    pub fn lavfi_testsrc(width: u32, height: u32, fps: u32) -> Self {
        AvCaptureConfig {
            device_format: "lavfi".into(),
            url: format!("testsrc2=size={width}x{height}:rate={fps}"),
            width: None,
            height: None,
            fps: None,
            input_format: None,
            pace_by_pts: true,
        }
    }
}

fn find_input_format(name: &str) -> Option<format::format::Format> {
    let want: &[&str] = if name == "v4l2" || name == "video4linux2" {
        &["video4linux2", "v4l2"]
    } else {
        &[name]
    };
    ffmpeg_next::device::input::video()
        .chain(ffmpeg_next::device::input::audio())
        .find(|f| f.name().split(',').any(|n| want.contains(&n)))
}

/// Opens the device and starts its capture thread. Fails (without a thread) if the device cannot be
/// opened or has no video stream.
pub fn spawn_av_capture(
    name: &str,
    cfg: AvCaptureConfig,
    slot: Arc<FrameSlot>,
) -> Result<CaptureThread, RecorderError> {
    init_ffmpeg();
    ffmpeg_next::device::register_all();
    let stop = Arc::new(AtomicBool::new(false));
    let stop_flag = Arc::clone(&stop);
    let (ready_tx, ready_rx) = sync_channel::<Result<(), RecorderError>>(1);
    let cam = name.to_owned();
    let handle = std::thread::Builder::new()
        .name(format!("camera-{name}"))
        .spawn(move || {
            if let Err(e) = capture(&cam, &cfg, &slot, &stop_flag, &ready_tx) {
                // Before the device opened, the caller gets the error; after, the camera just goes
                // stale and the recorder's freshness gate reports it.
                if ready_tx.try_send(Err(clone_shallow(&e))).is_err() {
                    tracing::error!(camera = %cam, error = %e, "camera stopped");
                }
            }
        })
        .map_err(|e| RecorderError::io("camera thread", e))?;
    match ready_rx.recv_timeout(Duration::from_secs(10)) {
        Ok(Ok(())) => Ok(CaptureThread::from_parts(stop, handle)),
        Ok(Err(e)) => {
            let _ = handle.join();
            Err(e)
        }
        Err(_) => {
            stop.store(true, Ordering::Relaxed);
            Err(RecorderError::Camera(
                name.to_owned(),
                "device did not open within 10 s".into(),
            ))
        }
    }
}

/// The error as the caller gets it from the capture thread (which keeps its own for the log).
fn clone_shallow(e: &RecorderError) -> RecorderError {
    match e {
        RecorderError::Camera(a, b) => RecorderError::Camera(a.clone(), b.clone()),
        other => RecorderError::Camera(String::new(), other.to_string()),
    }
}

fn capture(
    name: &str,
    cfg: &AvCaptureConfig,
    slot: &FrameSlot,
    stop: &AtomicBool,
    ready: &std::sync::mpsc::SyncSender<Result<(), RecorderError>>,
) -> Result<(), RecorderError> {
    let err = |what: &str, e: &dyn std::fmt::Display| {
        RecorderError::Camera(name.to_owned(), format!("{what}: {e}"))
    };
    let fmt = find_input_format(&cfg.device_format)
        .ok_or_else(|| err("no such libavdevice input", &cfg.device_format))?;
    let mut opts = Dictionary::new();
    if let (Some(w), Some(h)) = (cfg.width, cfg.height) {
        opts.set("video_size", &format!("{w}x{h}"));
    }
    if let Some(f) = cfg.fps {
        opts.set("framerate", &f.to_string());
    }
    if let Some(p) = &cfg.input_format {
        opts.set("input_format", p);
    }
    let guard = phone2act_dataset::av::CODEC_LOCK.lock();
    let ctx =
        format::open_with(&cfg.url, &fmt, opts).map_err(|e| err(&format!("cannot open {}", cfg.url), &e))?;
    let format::context::Context::Input(mut input) = ctx else {
        return Err(err("not an input", &cfg.url));
    };
    let stream = input
        .streams()
        .best(media::Type::Video)
        .ok_or_else(|| err("no video stream in", &cfg.url))?;
    let index = stream.index();
    let tb: Rational = stream.time_base();
    let mut decoder = codec::context::Context::from_parameters(stream.parameters())
        .and_then(|c| c.decoder().video())
        .map_err(|e| err("no decoder", &e))?;
    drop(guard);
    let _ = ready.try_send(Ok(()));
    tracing::info!(camera = name, url = %cfg.url, "camera opened");
    let mut scaler: Option<(Pixel, u32, u32, scaling::Context)> = None;
    let mut decoded = VideoFrame::empty();
    let mut rgb = VideoFrame::empty();
    let start = Instant::now();
    let mut first_pts: Option<i64> = None;
    let mut seq = 0u64;
    for (s, packet) in input.packets() {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        if s.index() != index {
            continue;
        }
        decoder.send_packet(&packet).map_err(|e| err("decode", &e))?;
        while decoder.receive_frame(&mut decoded).is_ok() {
            let (f, w, h) = (decoded.format(), decoded.width(), decoded.height());
            if !matches!(&scaler, Some((pf, pw, ph, _)) if *pf == f && *pw == w && *ph == h) {
                let ctx = scaling::Context::get(f, w, h, Pixel::RGB24, w, h, scaling::Flags::BILINEAR)
                    .map_err(|e| err("pixel conversion", &e))?;
                scaler = Some((f, w, h, ctx));
            }
            if let Some((_, _, _, sc)) = &mut scaler {
                sc.run(&decoded, &mut rgb)
                    .map_err(|e| err("pixel conversion", &e))?;
            }
            if cfg.pace_by_pts
                && let Some(pts) = decoded.pts()
            {
                let p0 = *first_pts.get_or_insert(pts);
                let at = Duration::from_secs_f64(((pts - p0) as f64 * f64::from(tb)).max(0.0));
                if let Some(wait) = (start + at).checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
            let stride = rgb.stride(0);
            let row = w as usize * 3;
            let mut packed = Vec::with_capacity(row * h as usize);
            for y in 0..h as usize {
                packed.extend_from_slice(&rgb.data(0)[y * stride..y * stride + row]);
            }
            slot.publish(Frame {
                width: w,
                height: h,
                rgb: Arc::new(packed),
                capture_time_ns: monotonic_ns(),
                seq,
            });
            seq += 1;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lavfi_testsrc_stands_in_for_a_webcam() {
        let slot = Arc::new(FrameSlot::default());
        let cam = spawn_av_capture(
            "lavfi",
            AvCaptureConfig::lavfi_testsrc(64, 48, 50),
            Arc::clone(&slot),
        )
        .unwrap();
        std::thread::sleep(Duration::from_millis(300));
        cam.stop();
        let n = slot.frames_captured();
        // Paced by pts: 50 fps for 0.3 s is about 15 frames, not thousands.
        assert!((5..=30).contains(&n), "got {n} frames");
        let f = slot.latest().unwrap();
        assert_eq!((f.width, f.height, f.rgb.len()), (64, 48, 64 * 48 * 3));
    }

    #[test]
    fn a_missing_device_is_a_clear_error() {
        let slot = Arc::new(FrameSlot::default());
        let e = spawn_av_capture(
            "cam0",
            AvCaptureConfig::v4l2("/dev/video-none", 640, 480, 30, true),
            slot,
        )
        .unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("cam0") && msg.contains("/dev/video-none"), "{msg}");
    }
}
