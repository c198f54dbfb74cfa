//! Streaming video encoding: RGB frames in, a constant-frame-rate mp4 out, frame *i* presented at *i/fps*.
//! Each camera gets its own thread fed through a bounded queue so that encoding never blocks the tick;
//! a frame that does not fit in the queue is counted as dropped and replaced in the video by a repeat of
//! the previous frame, so the video keeps exactly one frame per parquet row.

use crate::camera::Frame;
use crate::error::RecorderError;
use crate::spec::VideoSettings;
use crate::stats::ImageStats;
use ffmpeg_next as ffmpeg;
use ffmpeg_next::format::Pixel;
use ffmpeg_next::software::scaling;
use ffmpeg_next::util::frame::video::Video as VideoFrame;
use ffmpeg_next::{Dictionary, Packet, Rational, codec, encoder, format};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Once};
use std::thread::JoinHandle;

/// Serialises opening and closing FFmpeg codecs and devices across threads. Encoder libraries set up
/// process-wide tables when an instance is created (SVT-AV1 1.4 among them) and are not safe to initialise
/// from several threads at once; a heap corruption was seen with three cameras starting together. Opening
/// takes milliseconds, once per episode and camera, so the lock costs nothing measurable.
pub static CODEC_LOCK: parking_lot::Mutex<()> = parking_lot::Mutex::new(());

/// Keeps SVT-AV1's own log (about 20 banner lines per encoder, so per episode and camera) to errors,
/// unless the user set `SVT_LOG`. The library reads the variable when an encoder is created; call this at
/// the top of `main`, before any thread starts, because changing the environment races other threads
/// reading it.
#[allow(unsafe_code)]
pub fn quiet_encoder_library_logs() {
    if std::env::var_os("SVT_LOG").is_none() {
        // SAFETY: documented to be called while the process is single-threaded (start of main), so no other
        // thread reads or writes the environment concurrently.
        unsafe { std::env::set_var("SVT_LOG", "1") };
    }
}

/// Initialises FFmpeg once per process and keeps its log to errors. (SVT-AV1 logs on its own; see
/// [`quiet_encoder_library_logs`].)
pub fn init_ffmpeg() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        let _ = ffmpeg::init();
        ffmpeg::util::log::set_level(ffmpeg::util::log::Level::Error);
    });
}

/// A synchronous encoder writing one mp4. Opened with the first frame: SVT-AV1 hangs when an encoder that
/// never received a frame is flushed, so an encoder without frames must never exist.
pub struct VideoEncoder {
    octx: format::context::Output,
    /// Always `Some` until dropped; an `Option` so that [`Drop`] can free it under [`CODEC_LOCK`].
    encoder: Option<encoder::Video>,
    eof_sent: bool,
    scaler: Option<(u32, u32, scaling::Context)>,
    rgb: VideoFrame,
    yuv: VideoFrame,
    encoder_tb: Rational,
    stream_tb: Rational,
    frames: u64,
    width: u32,
    height: u32,
    path: PathBuf,
    packet: Packet,
    /// The newest encoded packet, not yet written (see [`VideoEncoder::finish`]).
    held: Option<Packet>,
}

fn ff_err(path: &Path, what: &str, e: ffmpeg::Error) -> RecorderError {
    let detail = format!("{what} {}: {e}", path.display());
    if matches!(e, ffmpeg::Error::Other { errno } if errno == 28) || detail.contains("No space left") {
        RecorderError::DiskFull {
            path: path.to_owned(),
        }
    } else {
        RecorderError::Video {
            camera: path.display().to_string(),
            detail,
        }
    }
}

impl VideoEncoder {
    /// Creates `path` and an encoder for `width`x`height` at `fps`.
    pub fn create(
        path: &Path,
        width: u32,
        height: u32,
        fps: u32,
        settings: &VideoSettings,
    ) -> Result<Self, RecorderError> {
        init_ffmpeg();
        let codec_impl = encoder::find_by_name(&settings.encoder).ok_or_else(|| RecorderError::Video {
            camera: path.display().to_string(),
            detail: format!(
                "FFmpeg has no {} encoder (install an FFmpeg built with it)",
                settings.encoder
            ),
        })?;
        let mut octx = format::output_as(&path, "mp4").map_err(|e| ff_err(path, "cannot create", e))?;
        let global_header = octx.format().flags().contains(format::Flags::GLOBAL_HEADER);
        let encoder_tb = Rational::new(1, fps as i32);
        let mut enc = codec::context::Context::new_with_codec(codec_impl)
            .encoder()
            .video()
            .map_err(|e| ff_err(path, "video encoder for", e))?;
        enc.set_width(width);
        enc.set_height(height);
        enc.set_format(Pixel::YUV420P);
        enc.set_time_base(encoder_tb);
        enc.set_frame_rate(Some(Rational::new(fps as i32, 1)));
        enc.set_gop(settings.gop);
        if settings.encoder != "libsvtav1" {
            // With a GOP of 2, B-frames save nothing, and their reordering makes torchcodec's approximate
            // seek (lerobot's default decoder) fail on an episode's last frame. They also add flush latency.
            enc.set_max_b_frames(0);
        }
        if global_header {
            enc.set_flags(codec::Flags::GLOBAL_HEADER);
        }
        let mut opts = Dictionary::new();
        opts.set("crf", &settings.crf.to_string());
        if let Some(p) = &settings.preset {
            opts.set("preset", p);
        }
        for (k, v) in &settings.extra {
            opts.set(k, v);
        }
        let guard = CODEC_LOCK.lock();
        let encoder = enc
            .open_with(opts)
            .map_err(|e| ff_err(path, "cannot open encoder for", e));
        drop(guard);
        let encoder = encoder?;
        let header = (|| {
            let mut ost = octx
                .add_stream(codec_impl)
                .map_err(|e| ff_err(path, "cannot add stream to", e))?;
            ost.set_parameters(&encoder);
            ost.set_time_base(encoder_tb);
            ost.set_rate(Rational::new(fps as i32, 1));
            ost.set_avg_frame_rate(Rational::new(fps as i32, 1));
            octx.write_header()
                .map_err(|e| ff_err(path, "cannot write header of", e))
        })();
        if let Err(e) = header {
            // A full disk at the first frame: the encoder has no frame yet and must not be freed as is.
            discard_encoder(encoder, 0, width, height);
            return Err(e);
        }
        // The muxer picks its own time base (mp4: 1/15360 at 30 fps); read it after write_header.
        let stream_tb = octx.stream(0).map_or(encoder_tb, |s| s.time_base());
        Ok(VideoEncoder {
            octx,
            encoder: Some(encoder),
            eof_sent: false,
            scaler: None,
            rgb: VideoFrame::new(Pixel::RGB24, width, height),
            yuv: VideoFrame::new(Pixel::YUV420P, width, height),
            encoder_tb,
            stream_tb,
            frames: 0,
            width,
            height,
            path: path.to_owned(),
            packet: Packet::empty(),
            held: None,
        })
    }

    /// Frames encoded so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Encodes one packed RGB frame of `w`x`h` as the next frame (scaled if the size differs).
    pub fn push_rgb(&mut self, rgb: &[u8], w: u32, h: u32) -> Result<(), RecorderError> {
        if rgb.len() != (w as usize) * (h as usize) * 3 {
            return Err(RecorderError::Video {
                camera: self.path.display().to_string(),
                detail: format!(
                    "frame of {w}x{h} has {} bytes, expected {}",
                    rgb.len(),
                    w as usize * h as usize * 3
                ),
            });
        }
        if self.rgb.width() != w || self.rgb.height() != h {
            self.rgb = VideoFrame::new(Pixel::RGB24, w, h);
        }
        let stride = self.rgb.stride(0);
        let row = w as usize * 3;
        let data = self.rgb.data_mut(0);
        for (y, src) in rgb.chunks_exact(row).enumerate() {
            data[y * stride..y * stride + row].copy_from_slice(src);
        }
        let needs_new = !matches!(&self.scaler, Some((sw, sh, _)) if *sw == w && *sh == h);
        if needs_new {
            let ctx = scaling::Context::get(
                Pixel::RGB24,
                w,
                h,
                Pixel::YUV420P,
                self.width,
                self.height,
                scaling::Flags::BILINEAR,
            )
            .map_err(|e| ff_err(&self.path, "cannot convert frames for", e))?;
            self.scaler = Some((w, h, ctx));
        }
        // A fresh output frame each time: the encoder may still hold a reference to the previous one.
        self.yuv = VideoFrame::new(Pixel::YUV420P, self.width, self.height);
        if let Some((_, _, scaler)) = &mut self.scaler {
            scaler
                .run(&self.rgb, &mut self.yuv)
                .map_err(|e| ff_err(&self.path, "cannot convert frames for", e))?;
        }
        self.yuv.set_pts(Some(self.frames as i64));
        self.encoder
            .as_mut()
            .expect("the encoder lives until drop")
            .send_frame(&self.yuv)
            .map_err(|e| ff_err(&self.path, "cannot encode", e))?;
        self.frames += 1;
        self.drain()
    }

    fn enc(&mut self) -> &mut encoder::Video {
        self.encoder.as_mut().expect("the encoder lives until drop")
    }

    fn drain(&mut self) -> Result<(), RecorderError> {
        let Some(encoder) = self.encoder.as_mut() else {
            return Ok(());
        };
        while encoder.receive_packet(&mut self.packet).is_ok() {
            self.packet.set_stream(0);
            // Every frame lasts exactly one period; without it the mp4 loses the last frame's duration.
            self.packet.set_duration(1);
            self.packet.rescale_ts(self.encoder_tb, self.stream_tb);
            // Written one packet late: the last one is only known at the flush (see `finish`).
            let packet = std::mem::replace(&mut self.packet, Packet::empty());
            if let Some(previous) = self.held.replace(packet) {
                previous
                    .write_interleaved(&mut self.octx)
                    .map_err(|e| ff_err(&self.path, "cannot write", e))?;
            }
        }
        Ok(())
    }

    /// Flushes the encoder and writes the mp4 trailer; returns the number of frames.
    pub fn finish(mut self) -> Result<u64, RecorderError> {
        self.eof_sent = true;
        self.enc()
            .send_eof()
            .map_err(|e| ff_err(&self.path, "cannot flush", e))?;
        self.drain()?;
        if let Some(mut last) = self.held.take() {
            // The last frame lasts one tick of the stream's time base longer than a period (65 µs at 30 fps).
            // Readers derive the average rate as frames / duration; with the exact duration float64 can put it
            // an ulp above fps (22 frames at 30 fps give 30.000000000000004), and GR00T N1.6, which snaps
            // timestamps to multiples of 1 / average rate, then lands an ulp before frame k's start and reads
            // frame k - 1. One tick more keeps the rate 1 / (frames * ticks per period) below fps: every
            // snapped time falls inside its frame, drifting less than 1 % of a frame by the end (GR00T's
            // refusal threshold) up to 156 fps. A single frame needs none (frame 0 snaps to 0 at any rate), and
            // with it the stream's guessed rate would be the one duration's, 19.96 at 20 fps, which lerobot's
            // aggregate reads as 19 fps and refuses to join with the dataset's other videos.
            if self.frames > 1 {
                last.set_duration(last.duration() + 1);
            }
            last.write_interleaved(&mut self.octx)
                .map_err(|e| ff_err(&self.path, "cannot write", e))?;
        }
        self.octx
            .write_trailer()
            .map_err(|e| ff_err(&self.path, "cannot finish", e))?;
        Ok(self.frames)
    }
}

impl Drop for VideoEncoder {
    fn drop(&mut self) {
        if let Some(encoder) = self.encoder.take() {
            if self.eof_sent {
                // Encoder teardown frees what creation set up: same lock.
                let guard = CODEC_LOCK.lock();
                drop(encoder);
                drop(guard);
            } else {
                // Failed part way (a write error): quiesce it before it is freed.
                discard_encoder(encoder, self.frames, self.width, self.height);
            }
        }
    }
}

/// Frees an encoder whose output failed, without writing anything. SVT-AV1 1.4 waits forever in its
/// teardown for a packet from an encoder that never received a frame, and complains about one that was
/// never sent the end of stream; so it gets a blank frame if it has none, the end of stream, and its
/// remaining packets are thrown away.
fn discard_encoder(mut encoder: encoder::Video, frames: u64, width: u32, height: u32) {
    if frames == 0 {
        let mut blank = VideoFrame::new(Pixel::YUV420P, width, height);
        blank.set_pts(Some(0));
        let _ = encoder.send_frame(&blank);
    }
    let _ = encoder.send_eof();
    let mut packet = Packet::empty();
    while encoder.receive_packet(&mut packet).is_ok() {}
    let guard = CODEC_LOCK.lock();
    drop(encoder);
    drop(guard);
}

/// What an encoder thread reports when it finishes.
#[derive(Debug)]
pub struct EncodeReport {
    pub camera: String,
    pub path: PathBuf,
    pub frames: u64,
    /// Frames that did not fit in the queue and were replaced by a repeat of the previous frame.
    pub dropped: u64,
    pub image_stats: ImageStats,
}

enum Msg {
    Frame { index: u64, frame: Frame },
    Finish { total_frames: u64 },
}

/// A camera's encoder thread and the sending end of its bounded queue.
pub struct EncoderThread {
    camera: String,
    tx: SyncSender<Msg>,
    dropped: Arc<AtomicU64>,
    failed: Arc<AtomicBool>,
    handle: Option<JoinHandle<Result<EncodeReport, RecorderError>>>,
}

impl EncoderThread {
    /// Starts a thread that encodes frames for `camera` into `path` at `fps`, scaled to `width`x`height`.
    pub fn spawn(
        camera: &str,
        path: PathBuf,
        width: u32,
        height: u32,
        fps: u32,
        settings: VideoSettings,
        queue_frames: usize,
    ) -> Result<Self, RecorderError> {
        let (tx, rx) = sync_channel(queue_frames.max(1));
        let dropped = Arc::new(AtomicU64::new(0));
        let failed = Arc::new(AtomicBool::new(false));
        let (cam, drop2, fail2) = (camera.to_owned(), Arc::clone(&dropped), Arc::clone(&failed));
        let handle = std::thread::Builder::new()
            .name(format!("encode-{camera}"))
            .spawn(move || {
                let mut finish_seen = false;
                let r = encode_loop(
                    &cam,
                    &path,
                    width,
                    height,
                    fps,
                    &settings,
                    &rx,
                    &drop2,
                    &mut finish_seen,
                );
                if r.is_err() {
                    fail2.store(true, Ordering::Relaxed);
                    // Keep draining so the tick thread never blocks on a dead encoder, until told to finish.
                    // A failure while flushing came after the Finish: waiting for another would never end
                    // (a full disk at Stop hung the recorder that way).
                    while !finish_seen {
                        match rx.recv() {
                            Ok(Msg::Finish { .. }) | Err(_) => finish_seen = true,
                            Ok(Msg::Frame { .. }) => {}
                        }
                    }
                }
                r
            })
            .map_err(|e| RecorderError::io("encoder thread", e))?;
        Ok(EncoderThread {
            camera: camera.to_owned(),
            tx,
            dropped,
            failed,
            handle: Some(handle),
        })
    }

    /// Queues frame `index` without blocking; returns false (and counts a drop) when the queue is full.
    pub fn push(&self, index: u64, frame: Frame) -> bool {
        match self.tx.try_send(Msg::Frame { index, frame }) {
            Ok(()) => true,
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                false
            }
        }
    }

    /// Frames dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// True once the encoder hit an error (the episode cannot be saved).
    pub fn failed(&self) -> bool {
        self.failed.load(Ordering::Relaxed)
    }

    /// The camera name.
    pub fn camera(&self) -> &str {
        &self.camera
    }

    /// Pads the video to `total_frames`, flushes it and waits for the thread.
    pub fn finish(self, total_frames: u64) -> Result<EncodeReport, RecorderError> {
        self.request_finish(total_frames);
        self.join()
    }

    /// Tells the thread the episode has `total_frames` frames; it pads, flushes and closes the file.
    /// Separate from [`EncoderThread::join`] so that all cameras flush in parallel.
    pub fn request_finish(&self, total_frames: u64) {
        // A blocking send: the queue drains at encoder speed, and the episode is not saved before it does.
        let _ = self.tx.send(Msg::Finish { total_frames });
    }

    /// Waits for the thread after [`EncoderThread::request_finish`].
    pub fn join(mut self) -> Result<EncodeReport, RecorderError> {
        let handle = self.handle.take().ok_or(RecorderError::ThreadGone)?;
        handle.join().map_err(|_| RecorderError::ThreadGone)?
    }
}

impl Drop for EncoderThread {
    fn drop(&mut self) {
        if let Some(h) = self.handle.take() {
            // Discarded episode: finish with whatever is queued so SVT-AV1 is flushed only if it has frames.
            let _ = self.tx.send(Msg::Finish { total_frames: 0 });
            let _ = h.join();
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn encode_loop(
    camera: &str,
    path: &Path,
    width: u32,
    height: u32,
    fps: u32,
    settings: &VideoSettings,
    rx: &Receiver<Msg>,
    dropped: &AtomicU64,
    finish_seen: &mut bool,
) -> Result<EncodeReport, RecorderError> {
    let mut enc: Option<VideoEncoder> = None;
    let mut last: Option<Frame> = None;
    let mut stats = ImageStats::new(fps);
    let with_camera = |e: RecorderError| match e {
        RecorderError::Video { detail, .. } => RecorderError::Video {
            camera: camera.to_owned(),
            detail,
        },
        other => other,
    };
    let total = loop {
        let Ok(msg) = rx.recv() else {
            *finish_seen = true;
            break 0;
        };
        match msg {
            Msg::Frame { index, frame } => {
                let e = match &mut enc {
                    Some(e) => e,
                    None => enc.insert(
                        VideoEncoder::create(path, width, height, fps, settings).map_err(with_camera)?,
                    ),
                };
                // Frames lost to a full queue become repeats of the previous one: one video frame per row.
                while e.frames() < index {
                    let f = last.as_ref().unwrap_or(&frame);
                    e.push_rgb(&f.rgb, f.width, f.height).map_err(with_camera)?;
                }
                if e.frames() == index {
                    e.push_rgb(&frame.rgb, frame.width, frame.height)
                        .map_err(with_camera)?;
                    stats.observe(index, &frame);
                }
                last = Some(frame);
            }
            Msg::Finish { total_frames } => {
                *finish_seen = true;
                break total_frames;
            }
        }
    };
    let frames = match enc {
        Some(mut e) => {
            if let Some(f) = &last {
                while e.frames() < total {
                    e.push_rgb(&f.rgb, f.width, f.height).map_err(with_camera)?;
                }
            }
            e.finish().map_err(with_camera)?
        }
        None => 0,
    };
    Ok(EncodeReport {
        camera: camera.to_owned(),
        path: path.to_owned(),
        frames,
        dropped: dropped.load(Ordering::Relaxed),
        image_stats: stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spec::Format;

    /// Key (sync) flags of the video packets of `path`, in file order.
    fn key_flags(path: &Path) -> Vec<bool> {
        let mut input = format::input(&path).unwrap();
        let stream = input.streams().best(ffmpeg::media::Type::Video).unwrap().index();
        input
            .packets()
            .filter(|(s, _)| s.index() == stream)
            .map(|(_, p)| p.is_key())
            .collect()
    }

    /// GR00T N1.6 snaps a step's timestamp to `k / average_rate`, the rate a reader derives as frames divided
    /// by the stream's duration in float64. For every length, that snapped time must fall inside frame k
    /// (at or after its start, before the next), and stay within GR00T's 1 % of a frame of `k / fps`.
    #[test]
    fn frames_over_duration_never_puts_a_snapped_time_before_its_frame() {
        let dir = tempfile::tempdir().unwrap();
        let settings = VideoSettings::parse(Some("h264"), Format::V21).unwrap();
        for fps in [20u32, 30] {
            // 22 frames at 30 fps: an exact duration gives an average rate an ulp above 30.
            for n in [1u64, 2, 5, 22, 23, 61] {
                let path = dir.path().join(format!("{fps}-{n}.mp4"));
                let mut enc = VideoEncoder::create(&path, 64, 64, fps, &settings).unwrap();
                for i in 0..n {
                    enc.push_rgb(&vec![(i * 9) as u8; 64 * 64 * 3], 64, 64).unwrap();
                }
                enc.finish().unwrap();
                let input = format::input(&path).unwrap();
                let stream = input.streams().best(ffmpeg::media::Type::Video).unwrap();
                let tb =
                    f64::from(stream.time_base().numerator()) / f64::from(stream.time_base().denominator());
                let ticks_per_frame = i64::from(stream.time_base().denominator()) / i64::from(fps);
                let tick_s = 1.0 / f64::from(stream.time_base().denominator());
                // The rate readers guess from the packets' durations (lerobot's `get_video_info` rounds it
                // down and refuses to join files whose rates differ).
                assert_eq!(
                    stream.rate(),
                    ffmpeg::Rational::new(fps as i32, 1),
                    "{fps} fps, {n} frames"
                );
                let duration_s = stream.duration() as f64 * tb;
                let average_rate = n as f64 / duration_s;
                for k in 0..n {
                    let snapped_s = k as f64 * (1.0 / average_rate);
                    let start_s = (k as i64 * ticks_per_frame) as f64 * tick_s;
                    let next_s = ((k as i64 + 1) * ticks_per_frame) as f64 * tick_s;
                    assert!(
                        start_s <= snapped_s && snapped_s < next_s,
                        "{fps} fps, {n} frames, frame {k}: snapped {snapped_s} outside [{start_s}, {next_s})"
                    );
                    assert!((snapped_s - k as f64 / f64::from(fps)) * f64::from(fps) < 0.01);
                }
            }
        }
    }

    /// lerobot's loader seeks to the key frame before each sampled frame and decodes from there: with a GOP of
    /// 2 that is at most one frame of extra decoding. A file whose only key frame is its first makes every
    /// sample decode the episode from its start, so the default settings of each codec must give a key frame
    /// every second packet, as lerobot's own files have.
    #[test]
    fn default_settings_give_a_key_frame_every_second_frame() {
        let dir = tempfile::tempdir().unwrap();
        // SVT-AV1 refuses pictures under 64x64.
        let (w, h, fps) = (64, 64, 20);
        for codec in ["av1", "h264"] {
            let settings = VideoSettings::parse(Some(codec), Format::V30).unwrap();
            let path = dir.path().join(format!("{codec}.mp4"));
            let mut enc = VideoEncoder::create(&path, w, h, fps, &settings).unwrap();
            for i in 0..20u8 {
                // Moving content, so that no encoder could code a frame as a repeat.
                let rgb: Vec<u8> = (0..w * h * 3)
                    .map(|k| (k as u8).wrapping_mul(7).wrapping_add(i * 13))
                    .collect();
                enc.push_rgb(&rgb, w, h).unwrap();
            }
            assert_eq!(enc.finish().unwrap(), 20);
            let keys = key_flags(&path);
            assert_eq!(keys.len(), 20, "{codec}: {keys:?}");
            let want: Vec<bool> = (0..20).map(|i| i % 2 == 0).collect();
            assert_eq!(keys, want, "{codec}: key frames at the wrong packets");
        }
    }
}
