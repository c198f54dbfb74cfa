//! Streaming video encoding: RGB frames in, a constant-frame-rate mp4 out, frame *i* presented at *i/fps*.
//! Each camera gets its own thread fed through a bounded queue so that encoding never blocks the tick;
//! a frame that does not fit in the queue is counted as dropped and replaced in the video by a repeat of
//! the previous frame, so the video keeps exactly one frame per parquet row.

use ffmpeg_next as ffmpeg;
use ffmpeg_next::format::Pixel;
use ffmpeg_next::software::scaling;
use ffmpeg_next::util::frame::video::Video as VideoFrame;
use ffmpeg_next::{Dictionary, Packet, Rational, codec, encoder, format};
use phone2act_capture::camera::Frame;
use phone2act_dataset::av::{CODEC_LOCK, init_ffmpeg};
use phone2act_dataset::dataset::EncodeReport;
use phone2act_dataset::error::RecorderError;
use phone2act_dataset::spec::VideoSettings;
use phone2act_dataset::stats::ImageStats;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::thread::JoinHandle;

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

/// A synchronous encoder writing one mp4, or keeping its newest packets in memory (a ring: see
/// [`VideoEncoder::ring`]) until [`VideoEncoder::attach`] starts the mp4 from one of them. Opened with the first
/// frame: SVT-AV1 hangs when an encoder that never received a frame is flushed, so an encoder without frames
/// must never exist.
pub struct VideoEncoder {
    /// Always `Some` until dropped; an `Option` so that [`Drop`] can free it under [`CODEC_LOCK`].
    encoder: Option<encoder::Video>,
    eof_sent: bool,
    scaler: Option<(u32, u32, scaling::Context)>,
    rgb: VideoFrame,
    yuv: VideoFrame,
    encoder_tb: Rational,
    fps: u32,
    gop: u32,
    frames: u64,
    width: u32,
    height: u32,
    /// The mp4 (or, for a ring, the camera) named in errors.
    path: PathBuf,
    packet: Packet,
    sink: Sink,
}

/// Where an encoder's packets go.
enum Sink {
    File(FileSink),
    Ring(PacketRing),
}

/// An mp4 being written, one packet late (the last one is only known at the flush, see
/// [`VideoEncoder::finish`]).
struct FileSink {
    octx: format::context::Output,
    stream_tb: Rational,
    /// The encoder's frame number that is the file's frame 0 (not 0 for a file started from a ring).
    first_frame: u64,
    /// Whether a packet was written: the first must be the key frame of `first_frame`.
    started: bool,
    held: Option<Packet>,
}

/// The newest encoded packets of a ring encoder, oldest first, starting at a key frame; at least `keep_frames`
/// frames once that many were encoded, at most `keep_frames` plus a GOP.
struct PacketRing {
    packets: std::collections::VecDeque<Packet>,
    keep_frames: u64,
    bytes: usize,
}

impl PacketRing {
    fn push(&mut self, packet: Packet) {
        self.bytes += packet.size();
        let newest = packet.pts().unwrap_or(0);
        self.packets.push_back(packet);
        // Drop everything before the newest key frame that still leaves `keep_frames` frames behind it (the
        // packets are in frame order, so only a prefix can qualify).
        let cut = self
            .packets
            .iter()
            .enumerate()
            .skip(1)
            .take_while(|(_, p)| newest + 1 - p.pts().unwrap_or(0) >= self.keep_frames as i64)
            .filter(|(_, p)| p.is_key())
            .map(|(i, _)| i)
            .last();
        if let Some(cut) = cut {
            for p in self.packets.drain(..cut) {
                self.bytes -= p.size();
            }
        }
    }
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

fn open_codec(
    path: &Path,
    width: u32,
    height: u32,
    fps: u32,
    settings: &VideoSettings,
) -> Result<encoder::Video, RecorderError> {
    init_ffmpeg();
    let codec_impl = encoder::find_by_name(&settings.encoder).ok_or_else(|| RecorderError::Video {
        camera: path.display().to_string(),
        detail: format!(
            "FFmpeg has no {} encoder (install an FFmpeg built with it)",
            settings.encoder
        ),
    })?;
    let mut enc = codec::context::Context::new_with_codec(codec_impl)
        .encoder()
        .video()
        .map_err(|e| ff_err(path, "video encoder for", e))?;
    enc.set_width(width);
    enc.set_height(height);
    enc.set_format(Pixel::YUV420P);
    enc.set_time_base(Rational::new(1, fps as i32));
    enc.set_frame_rate(Some(Rational::new(fps as i32, 1)));
    enc.set_gop(settings.gop);
    if settings.encoder != "libsvtav1" {
        // With a GOP of 2, B-frames save nothing, and their reordering makes torchcodec's approximate
        // seek (lerobot's default decoder) fail on an episode's last frame. They also add flush latency.
        enc.set_max_b_frames(0);
    }
    // The output is always an mp4, whose muxer wants the codec's headers out of band.
    enc.set_flags(codec::Flags::GLOBAL_HEADER);
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
    encoder
}

impl FileSink {
    /// Creates `path` with a stream of `encoder`'s parameters and writes its header.
    fn create(
        path: &Path,
        encoder: &encoder::Video,
        fps: u32,
        first_frame: u64,
    ) -> Result<FileSink, RecorderError> {
        let encoder_tb = Rational::new(1, fps as i32);
        let mut octx = format::output_as(&path, "mp4").map_err(|e| ff_err(path, "cannot create", e))?;
        let codec_impl = encoder::find(encoder.id());
        let mut ost = octx
            .add_stream(codec_impl)
            .map_err(|e| ff_err(path, "cannot add stream to", e))?;
        ost.set_parameters(encoder);
        ost.set_time_base(encoder_tb);
        ost.set_rate(Rational::new(fps as i32, 1));
        ost.set_avg_frame_rate(Rational::new(fps as i32, 1));
        octx.write_header()
            .map_err(|e| ff_err(path, "cannot write header of", e))?;
        // The muxer picks its own time base (mp4: 1/15360 at 30 fps); read it after write_header.
        let stream_tb = octx.stream(0).map_or(encoder_tb, |s| s.time_base());
        Ok(FileSink {
            octx,
            stream_tb,
            first_frame,
            started: false,
            held: None,
        })
    }

    /// Writes the packet before `packet` (in the encoder's time base), shifted to the file's frame 0; a packet
    /// of a frame before the file's first is left out.
    fn write(&mut self, mut packet: Packet, encoder_tb: Rational, path: &Path) -> Result<(), RecorderError> {
        let first = self.first_frame as i64;
        let pts = packet.pts().unwrap_or(0);
        if pts < first {
            return Ok(());
        }
        if !self.started {
            if pts != first || !packet.is_key() {
                return Err(RecorderError::Video {
                    camera: path.display().to_string(),
                    detail: format!(
                        "frame {first} is not a key frame (the video cannot start there): the encoder does not keep its GOP"
                    ),
                });
            }
            self.started = true;
        }
        packet.set_pts(Some(pts - first));
        packet.set_dts(packet.dts().map(|d| d - first));
        packet.rescale_ts(encoder_tb, self.stream_tb);
        if let Some(previous) = self.held.replace(packet) {
            previous
                .write_interleaved(&mut self.octx)
                .map_err(|e| ff_err(path, "cannot write", e))?;
        }
        Ok(())
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
        let encoder = open_codec(path, width, height, fps, settings)?;
        let sink = match FileSink::create(path, &encoder, fps, 0) {
            Ok(sink) => sink,
            Err(e) => {
                // A full disk at the first frame: the encoder has no frame yet and must not be freed as is.
                discard_encoder(encoder, 0, width, height);
                return Err(e);
            }
        };
        Ok(Self::with_sink(
            encoder,
            Sink::File(sink),
            path,
            width,
            height,
            fps,
            settings,
        ))
    }

    /// An encoder for `width`x`height` at `fps` that writes no file: it keeps the packets of (at least) its
    /// newest `keep_frames` frames, from a key frame, until [`VideoEncoder::attach`]. Every frame whose number
    /// is a multiple of the GOP is made a key frame, so that any such frame can start a video and every camera
    /// of a recorder has its key frames at the same numbers. `camera` names it in errors.
    pub fn ring(
        camera: &str,
        width: u32,
        height: u32,
        fps: u32,
        settings: &VideoSettings,
        keep_frames: u64,
    ) -> Result<Self, RecorderError> {
        let path = Path::new(camera);
        let encoder = open_codec(path, width, height, fps, settings)?;
        let sink = Sink::Ring(PacketRing {
            packets: std::collections::VecDeque::new(),
            keep_frames: keep_frames.max(1),
            bytes: 0,
        });
        Ok(Self::with_sink(encoder, sink, path, width, height, fps, settings))
    }

    fn with_sink(
        encoder: encoder::Video,
        sink: Sink,
        path: &Path,
        width: u32,
        height: u32,
        fps: u32,
        settings: &VideoSettings,
    ) -> Self {
        VideoEncoder {
            encoder: Some(encoder),
            eof_sent: false,
            scaler: None,
            rgb: VideoFrame::new(Pixel::RGB24, width, height),
            yuv: VideoFrame::new(Pixel::YUV420P, width, height),
            encoder_tb: Rational::new(1, fps as i32),
            fps,
            gop: settings.gop.max(1),
            frames: 0,
            width,
            height,
            path: path.to_owned(),
            packet: Packet::empty(),
            sink,
        }
    }

    /// Starts writing `path` from frame `first_frame` of a ring encoder (a multiple of the GOP, not older than
    /// the ring keeps): its kept packets from that frame are written now, and every later one as it comes.
    /// The file's frame 0 is `first_frame`. An encoder already writing a file refuses.
    pub fn attach(&mut self, path: &Path, first_frame: u64) -> Result<(), RecorderError> {
        let Sink::Ring(ring) = &mut self.sink else {
            return Err(RecorderError::Video {
                camera: path.display().to_string(),
                detail: "the encoder already writes a file".into(),
            });
        };
        let packets = std::mem::take(&mut ring.packets);
        let oldest = packets.front().and_then(Packet::pts);
        if oldest.is_some_and(|p| p > first_frame as i64) {
            return Err(RecorderError::Video {
                camera: path.display().to_string(),
                detail: format!(
                    "frame {first_frame} is no longer kept (the oldest is {})",
                    oldest.unwrap_or(0)
                ),
            });
        }
        let encoder = self.encoder.as_ref().expect("the encoder lives until drop");
        let mut sink = FileSink::create(path, encoder, self.fps, first_frame)?;
        for packet in packets {
            sink.write(packet, self.encoder_tb, path)?;
        }
        path.clone_into(&mut self.path);
        self.sink = Sink::File(sink);
        Ok(())
    }

    /// The oldest frame number a ring keeps (its first packet's), if any.
    pub fn oldest_kept(&self) -> Option<u64> {
        match &self.sink {
            Sink::Ring(ring) => ring
                .packets
                .front()
                .and_then(Packet::pts)
                .map(|p| p.max(0) as u64),
            Sink::File(_) => None,
        }
    }

    /// Bytes of encoded video a ring keeps (0 for an encoder writing a file).
    pub fn kept_bytes(&self) -> usize {
        match &self.sink {
            Sink::Ring(ring) => ring.bytes,
            Sink::File(_) => 0,
        }
    }

    /// Frames of the file: encoded since its frame 0.
    pub fn file_frames(&self) -> u64 {
        match &self.sink {
            Sink::File(f) => self.frames.saturating_sub(f.first_frame),
            Sink::Ring(_) => 0,
        }
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
        if matches!(self.sink, Sink::Ring(_)) && self.frames.is_multiple_of(u64::from(self.gop)) {
            self.yuv.set_kind(ffmpeg::picture::Type::I);
        }
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
            let packet = std::mem::replace(&mut self.packet, Packet::empty());
            match &mut self.sink {
                Sink::File(file) => file.write(packet, self.encoder_tb, &self.path)?,
                Sink::Ring(ring) => ring.push(packet),
            }
        }
        Ok(())
    }

    /// Flushes the encoder and writes the mp4 trailer; returns the number of frames of the file (a ring that
    /// was never attached writes nothing and returns 0).
    pub fn finish(mut self) -> Result<u64, RecorderError> {
        self.eof_sent = true;
        self.enc()
            .send_eof()
            .map_err(|e| ff_err(&self.path, "cannot flush", e))?;
        self.drain()?;
        let frames = self.file_frames();
        let Sink::File(file) = &mut self.sink else {
            return Ok(0);
        };
        if let Some(mut last) = file.held.take() {
            // The last frame lasts one tick of the stream's time base longer than a period (65 µs at 30 fps).
            // Readers derive the average rate as frames / duration; with the exact duration float64 can put it
            // an ulp above fps (22 frames at 30 fps give 30.000000000000004), and GR00T N1.6, which snaps
            // timestamps to multiples of 1 / average rate, then lands an ulp before frame k's start and reads
            // frame k - 1. One tick more keeps the rate 1 / (frames * ticks per period) below fps: every
            // snapped time falls inside its frame, drifting less than 1 % of a frame by the end (GR00T's
            // refusal threshold) up to 156 fps. A single frame needs none (frame 0 snaps to 0 at any rate), and
            // with it the stream's guessed rate would be the one duration's, 19.96 at 20 fps, which lerobot's
            // aggregate reads as 19 fps and refuses to join with the dataset's other videos.
            if frames > 1 {
                last.set_duration(last.duration() + 1);
            }
            last.write_interleaved(&mut file.octx)
                .map_err(|e| ff_err(&self.path, "cannot write", e))?;
        }
        file.octx
            .write_trailer()
            .map_err(|e| ff_err(&self.path, "cannot finish", e))?;
        Ok(frames)
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

enum Msg {
    Frame {
        index: u64,
        frame: Frame,
    },
    /// A ring encoder starts its episode's file at this frame (see [`EncoderThread::attach`]).
    Attach {
        path: PathBuf,
        first_frame: u64,
    },
    Finish {
        total_frames: u64,
    },
}

/// What an encoder thread writes until told otherwise.
enum Output {
    /// An episode's mp4.
    File(PathBuf),
    /// Nothing: the newest `keep_frames` frames are kept encoded until an [`Msg::Attach`].
    Ring { keep_frames: u64 },
}

/// A camera's encoder thread and the sending end of its bounded queue.
pub struct EncoderThread {
    camera: String,
    tx: SyncSender<Msg>,
    dropped: Arc<AtomicU64>,
    failed: Arc<AtomicBool>,
    /// Bytes of encoded video a ring thread keeps.
    kept_bytes: Arc<AtomicU64>,
    /// A ring thread's frames keeps at most, and the numbers of its newest dropped frames: an episode started
    /// from the ring counts only its own (see [`EncoderThread::attach`]).
    ring_drops: Option<parking_lot::Mutex<(u64, std::collections::VecDeque<u64>)>>,
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
        Self::spawn_with(
            camera,
            Output::File(path),
            (width, height, fps),
            settings,
            queue_frames,
        )
    }

    /// Starts a thread that encodes frames for `camera` and keeps the newest `keep_frames` of them encoded (see
    /// [`VideoEncoder::ring`]) until [`EncoderThread::attach`] makes them the start of an episode's mp4.
    /// Frames are numbered from 0 by the ring until then.
    pub fn spawn_ring(
        camera: &str,
        width: u32,
        height: u32,
        fps: u32,
        settings: VideoSettings,
        queue_frames: usize,
        keep_frames: u64,
    ) -> Result<Self, RecorderError> {
        let mut thread = Self::spawn_with(
            camera,
            Output::Ring { keep_frames },
            (width, height, fps),
            settings,
            queue_frames,
        )?;
        thread.ring_drops = Some(parking_lot::Mutex::new((
            keep_frames,
            std::collections::VecDeque::new(),
        )));
        Ok(thread)
    }

    fn spawn_with(
        camera: &str,
        output: Output,
        (width, height, fps): (u32, u32, u32),
        settings: VideoSettings,
        queue_frames: usize,
    ) -> Result<Self, RecorderError> {
        let (tx, rx) = sync_channel(queue_frames.max(1));
        let dropped = Arc::new(AtomicU64::new(0));
        let failed = Arc::new(AtomicBool::new(false));
        let kept_bytes = Arc::new(AtomicU64::new(0));
        let (cam, drop2, fail2, kept2) = (
            camera.to_owned(),
            Arc::clone(&dropped),
            Arc::clone(&failed),
            Arc::clone(&kept_bytes),
        );
        let handle = std::thread::Builder::new()
            .name(format!("encode-{camera}"))
            .spawn(move || {
                let mut finish_seen = false;
                let mut job = EncodeJob {
                    camera: &cam,
                    output,
                    width,
                    height,
                    fps,
                    settings: &settings,
                    dropped: &drop2,
                    kept_bytes: &kept2,
                };
                let r = job.run(&rx, &mut finish_seen);
                if r.is_err() {
                    fail2.store(true, Ordering::Relaxed);
                    // Keep draining so the tick thread never blocks on a dead encoder, until told to finish.
                    // A failure while flushing came after the Finish: waiting for another would never end
                    // (a full disk at Stop hung the recorder that way).
                    while !finish_seen {
                        match rx.recv() {
                            Ok(Msg::Finish { .. }) | Err(_) => finish_seen = true,
                            Ok(Msg::Frame { .. } | Msg::Attach { .. }) => {}
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
            kept_bytes,
            ring_drops: None,
            handle: Some(handle),
        })
    }

    /// Makes a ring thread's kept frames from `first_frame` on (a multiple of the GOP) the start of `path`;
    /// frames queued after this are numbered from the file's frame 0, and [`EncoderThread::dropped`] counts the
    /// file's frames only. Blocks while the queue is full (it drains at encoder speed).
    pub fn attach(&mut self, path: PathBuf, first_frame: u64) {
        if let Some(drops) = self.ring_drops.take() {
            let kept = drops.lock().1.iter().filter(|i| **i >= first_frame).count();
            self.dropped.store(kept as u64, Ordering::Relaxed);
        }
        let _ = self.tx.send(Msg::Attach { path, first_frame });
    }

    /// Bytes of encoded video a ring thread keeps.
    pub fn kept_bytes(&self) -> u64 {
        self.kept_bytes.load(Ordering::Relaxed)
    }

    /// Queues frame `index` without blocking; returns false (and counts a drop) when the queue is full.
    pub fn push(&self, index: u64, frame: Frame) -> bool {
        match self.tx.try_send(Msg::Frame { index, frame }) {
            Ok(()) => true,
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                if let Some(drops) = &self.ring_drops {
                    let mut drops = drops.lock();
                    let keep = drops.0;
                    drops.1.push_back(index);
                    while drops.1.front().is_some_and(|i| *i + keep < index) {
                        drops.1.pop_front();
                    }
                }
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

/// What an encoder thread runs.
struct EncodeJob<'a> {
    camera: &'a str,
    output: Output,
    width: u32,
    height: u32,
    fps: u32,
    settings: &'a VideoSettings,
    dropped: &'a AtomicU64,
    kept_bytes: &'a AtomicU64,
}

impl EncodeJob<'_> {
    fn with_camera(&self, e: RecorderError) -> RecorderError {
        match e {
            RecorderError::Video { detail, .. } => RecorderError::Video {
                camera: self.camera.to_owned(),
                detail,
            },
            other => other,
        }
    }

    fn open(&self) -> Result<VideoEncoder, RecorderError> {
        let (w, h, fps) = (self.width, self.height, self.fps);
        match &self.output {
            Output::File(path) => VideoEncoder::create(path, w, h, fps, self.settings),
            Output::Ring { keep_frames } => {
                VideoEncoder::ring(self.camera, w, h, fps, self.settings, *keep_frames)
            }
        }
        .map_err(|e| self.with_camera(e))
    }

    fn run(&mut self, rx: &Receiver<Msg>, finish_seen: &mut bool) -> Result<EncodeReport, RecorderError> {
        let mut enc: Option<VideoEncoder> = None;
        let mut last: Option<Frame> = None;
        let mut stats = ImageStats::new(self.fps);
        // A ring's sampled frames, by frame number, until its file starts: one per second (see `ImageStats`).
        let mut ring_stats: std::collections::VecDeque<(u64, ImageStats)> = std::collections::VecDeque::new();
        // The encoder's frame number of the file's frame 0.
        let mut base = 0;
        let total = loop {
            let Ok(msg) = rx.recv() else {
                *finish_seen = true;
                break 0;
            };
            match msg {
                Msg::Frame { index, frame } => {
                    let e = match &mut enc {
                        Some(e) => e,
                        None => enc.insert(self.open()?),
                    };
                    let at = base + index;
                    // Frames lost to a full queue become repeats of the previous one: one video frame per row.
                    while e.frames() < at {
                        let f = last.as_ref().unwrap_or(&frame);
                        e.push_rgb(&f.rgb, f.width, f.height)
                            .map_err(|e| self.with_camera(e))?;
                    }
                    if e.frames() == at {
                        e.push_rgb(&frame.rgb, frame.width, frame.height)
                            .map_err(|e| self.with_camera(e))?;
                        if matches!(self.output, Output::Ring { .. }) {
                            if index.is_multiple_of(u64::from(self.fps.max(1))) {
                                let mut one = ImageStats::new(self.fps);
                                one.observe(0, &frame);
                                ring_stats.push_back((index, one));
                            }
                            let oldest = e.oldest_kept().unwrap_or(0);
                            while ring_stats.front().is_some_and(|(i, _)| *i < oldest) {
                                ring_stats.pop_front();
                            }
                            self.kept_bytes.store(e.kept_bytes() as u64, Ordering::Relaxed);
                        } else {
                            stats.observe(index, &frame);
                        }
                    }
                    last = Some(frame);
                }
                Msg::Attach { path, first_frame } => {
                    if let Some(e) = &mut enc {
                        e.attach(&path, first_frame).map_err(|e| self.with_camera(e))?;
                        base = first_frame;
                    } else {
                        // No frame reached the ring (all dropped): the file starts with the next frame, and the
                        // frames before it repeat it.
                        base = 0;
                    }
                    for (_, s) in ring_stats.drain(..).filter(|(i, _)| *i >= first_frame) {
                        stats.merge(&s);
                    }
                    self.kept_bytes.store(0, Ordering::Relaxed);
                    self.output = Output::File(path);
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
                    while e.frames() < base + total {
                        e.push_rgb(&f.rgb, f.width, f.height)
                            .map_err(|e| self.with_camera(e))?;
                    }
                }
                e.finish().map_err(|e| self.with_camera(e))?
            }
            None => 0,
        };
        let path = match &self.output {
            Output::File(path) => path.clone(),
            Output::Ring { .. } => PathBuf::new(),
        };
        Ok(EncodeReport {
            camera: self.camera.to_owned(),
            path,
            frames,
            dropped: self.dropped.load(Ordering::Relaxed),
            image_stats: stats,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_dataset::spec::Format;

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

    /// A ring encoder keeps its newest frames from a key frame, and a file started from one of its frames
    /// numbered a multiple of the GOP holds that frame and every later one, from 0; a frame not kept, and a
    /// frame that is not a key frame, are refused rather than written as a video that cannot start there.
    #[test]
    fn a_ring_encoder_starts_a_file_at_a_kept_key_frame() {
        let dir = tempfile::tempdir().unwrap();
        for codec in ["av1", "h264"] {
            let settings = VideoSettings::parse(Some(codec), Format::V30).unwrap();
            let frame = |i: u64| vec![(i * 11 % 200) as u8; 64 * 64 * 3];
            let mut enc = VideoEncoder::ring("cam", 64, 64, 20, &settings, 10).unwrap();
            for i in 0..40 {
                enc.push_rgb(&frame(i), 64, 64).unwrap();
            }
            // At least 10 frames behind the newest packet out of the encoder, which lags the newest frame in
            // (x264's lookahead holds about ten at this size).
            let oldest = enc.oldest_kept().unwrap();
            assert!((12..=30).contains(&oldest), "{codec}: oldest kept {oldest}");
            assert!(enc.kept_bytes() > 0);
            let path = dir.path().join(format!("{codec}-old.mp4"));
            let err = enc.attach(&path, oldest - 2).unwrap_err().to_string();
            assert!(err.contains("no longer kept"), "{codec}: {err}");

            let mut enc = VideoEncoder::ring("cam", 64, 64, 20, &settings, 10).unwrap();
            for i in 0..40 {
                enc.push_rgb(&frame(i), 64, 64).unwrap();
            }
            let path = dir.path().join(format!("{codec}-odd.mp4"));
            let err = enc.attach(&path, 33).unwrap_err().to_string();
            assert!(err.contains("not a key frame"), "{codec}: {err}");

            let mut enc = VideoEncoder::ring("cam", 64, 64, 20, &settings, 10).unwrap();
            for i in 0..40 {
                enc.push_rgb(&frame(i), 64, 64).unwrap();
            }
            let path = dir.path().join(format!("{codec}.mp4"));
            enc.attach(&path, 32).unwrap();
            for i in 40..45 {
                enc.push_rgb(&frame(i), 64, 64).unwrap();
            }
            assert_eq!(enc.finish().unwrap(), 13, "{codec}: frames 32..45");
            let keys = key_flags(&path);
            assert_eq!(keys.len(), 13, "{codec}");
            assert!(keys[0], "{codec}: the file starts at a key frame");
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

    /// phone2act's own videos read back by the dataset's decoder, both defaults: AV1 and H.264, a keyframe every 2 frames (sought). Frame i is a flat grey of level 4i, so every frame found can be
    /// told from its neighbours.
    #[test]
    fn our_videos_give_the_frame_asked_for_in_both_codecs() {
        use phone2act_dataset::av::decode::frames_at;
        use phone2act_dataset::spec::{Format, VideoSettings};
        let dir = tempfile::tempdir().unwrap();
        for format in [Format::V30, Format::V21] {
            let path = dir.path().join(format!("{format:?}.mp4"));
            let settings = VideoSettings::parse(None, format).unwrap();
            let mut encoder = VideoEncoder::create(&path, 64, 64, 20, &settings).unwrap();
            for i in 0..60_u8 {
                encoder.push_rgb(&vec![4 * i; 64 * 64 * 3], 64, 64).unwrap();
            }
            encoder.finish().unwrap();
            // Gaps over a second (seek or decode on), under it (decode on), backwards, and past the end.
            let frames = [0_u8, 27, 28, 55, 12, 59];
            let mut times: Vec<f64> = frames.iter().map(|&i| f64::from(i) / 20.0).collect();
            times.push(20.0);
            let got = frames_at(&path, &times, 64).unwrap();
            for (k, frame) in got.iter().enumerate() {
                let mean = frame.rgb.iter().map(|&v| f64::from(v)).sum::<f64>() / frame.rgb.len() as f64;
                let want = 4.0 * f64::from(*frames.get(k).unwrap_or(&59));
                // Neighbouring frames are 4 levels apart; a flat grey comes back within 1 (seen: 1 off).
                assert!(
                    (mean - want).abs() < 1.5,
                    "{format:?} time {}: level {mean}, want {want}",
                    times[k]
                );
            }
        }
    }
}
