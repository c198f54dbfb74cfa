//! Operator video over WebRTC: a live H.264 view of one camera for each page that asks, beside the control
//! socket and never in its way.
//!
//! - Signalling rides the page's own authenticated socket (`{"type":"video_offer","camera":…,"sdp":…}` →
//!   `{"type":"video_answer","sdp":…}`), so only a page with the pairing token gets video, as for control.
//! - Video never runs on the control path's thread: the feeds and viewers (and the JPEG preview's fetches, see
//!   `web_preview`, and rosbridge's image topics, see `rosbridge_conn`) run on a runtime of their own (one
//!   thread, `video-io`) with a connection of their own to the server, and the encoder on a thread per camera;
//!   both threads run at a lower scheduling priority (nice +10 on Linux), so on a busy machine the control
//!   path's threads get the CPU first and the video is what slows down.
//! - Per camera one feed task fetches the newest raw frame from the server (`Policy.GetObservation`, RGB) and
//!   hands it to its encoder thread (`phone2act_capture::av::live`) through a slot of one frame, the newest
//!   winning: an encoder that falls behind skips frames, it never queues them. Each frame is encoded once and
//!   published on a broadcast channel. A viewer that falls behind loses the oldest frames (the channel's lag)
//!   and waits for a keyframe.
//! - Per viewer one task drives a [`str0m::Rtc`] (sans-IO: this module owns the UDP socket and the clock) as
//!   an ICE-lite peer on a host candidate, writes each access unit with its RTP time taken from the frame's
//!   capture time (90 kHz), after moving str0m's clock to the present (it stamps the packets it sends with
//!   its clock, and congestion control compares those stamps with the page's arrival times), and sends
//!   `{"rtp":…,"capture_unix_ms":…,"bitrate_bps":…}` on the page's data channel so that the page can show
//!   glass-to-glass latency (its clock offset comes from `clock` round trips on the control socket) and the
//!   bitrate.
//! - The bitrate follows the link: each viewer's str0m runs Google congestion control on the page's
//!   transport-wide feedback (TWCC), and the encoder aims at the lowest estimate of its viewers (within
//!   `[gateway.video]`'s `min_bitrate_kbps`..`max_bitrate_kbps`), so a slow link gets fewer bits instead of a
//!   queue that would also hold up the control socket's packets. x264 is given that rate spread over the frames
//!   it actually encodes (see `Cadence`), so that a busy machine's fewer frames still carry it.
//! - `[gateway.video]` ([`VideoConfig`]) also caps the frame rate, the picture's size (a larger camera is scaled
//!   down in the encoder's colour conversion) and the number of viewers, or turns the video off.
//! - A page on this very machine (its socket comes from the address the viewer's UDP socket is bound to) has no
//!   link to congest: its viewer runs without congestion control and pacing and gets the ceiling. On a busy
//!   machine the estimator reads the scheduler's delays as queueing and would lower the bitrate to its floor
//!   for nothing. A page elsewhere always gets the estimator, however near.
//! - The feed stops when its last viewer leaves; a page's viewer ends with its socket, a new offer or
//!   `video_off`.

use crate::config::VideoConfig;
use crate::conn::Out;
use crate::upstream::{Upstream, unix_ns};
use parking_lot::Mutex;
use phone2act_capture::av::live::H264Encoder;
use phone2act_proto::v1::ImageEncoding;
use serde_json::json;
use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime};
use str0m::bwe::{Bitrate, BweKind};
use str0m::change::SdpOffer;
use str0m::format::Codec;
use str0m::media::{MediaKind, MediaTime, Mid};
use str0m::net::{Protocol, Receive};
use str0m::{Candidate, Event, IceConnectionState, Input, Output, Rtc, RtcConfig};
use tokio::net::UdpSocket;
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

/// Frames a viewer may fall behind before it loses the oldest (about 130 ms at 30 fps).
const VIEWER_QUEUE: usize = 4;
/// Frame-rate steps for a low bitrate, so that each frame keeps enough bits to be legible: below the first
/// bitrate one frame in the second is encoded.
const FRAME_STEPS: [(u64, u64); 2] = [(150_000, 3), (300_000, 2)];
/// The share of a viewer's link estimate given to the video: the rest is headroom for the control socket, the
/// data channel's notes and the estimate's own error.
const LINK_SHARE: f64 = 0.85;
/// A new target within this fraction of the encoder's bitrate is not worth a rate-control change.
const RETARGET_FRACTION: f64 = 0.1;
/// How much less CPU priority the video's threads get than the control path's (nice steps).
const VIDEO_NICE: i32 = phone2act_capture::priority::BACKGROUND_NICE;
/// A viewer that has seen nothing from its page for this long (no ICE keep-alive) is over.
const VIEWER_IDLE: Duration = Duration::from_secs(30);

/// One encoded frame of a camera.
#[derive(Debug)]
pub(crate) struct EncodedFrame {
    pub data: Arc<[u8]>,
    pub keyframe: bool,
    /// Capture time on this gateway's wall clock (Unix), in nanoseconds.
    pub capture_unix_ns: i64,
    pub seq: u64,
    /// The bitrate the encoder aimed at for this frame.
    pub bitrate_bps: u64,
}

#[derive(Debug)]
struct Feed {
    tx: broadcast::Sender<Arc<EncodedFrame>>,
    /// A viewer joined or lost frames: the next frame is a keyframe.
    force_key: AtomicBool,
    task: Mutex<Option<JoinHandle<()>>>,
    /// Each viewer's share of its link (bits per second), by viewer id; the encoder aims at the lowest.
    link_bps: Mutex<HashMap<u64, u64>>,
    /// The lowest of `link_bps` (the ceiling while no viewer has an estimate).
    target_bps: AtomicU64,
    config: VideoConfig,
}

impl Feed {
    fn new(config: VideoConfig) -> Self {
        Self {
            tx: broadcast::channel(VIEWER_QUEUE).0,
            force_key: AtomicBool::new(true),
            task: Mutex::new(None),
            link_bps: Mutex::new(HashMap::new()),
            target_bps: AtomicU64::new(config.max_bitrate_bps()),
            config,
        }
    }

    fn set_link(&self, viewer: u64, bps: Option<u64>) {
        let mut links = self.link_bps.lock();
        match bps {
            Some(bps) => links.insert(viewer, bps),
            None => links.remove(&viewer),
        };
        let target = links
            .values()
            .copied()
            .min()
            .unwrap_or(self.config.max_bitrate_bps());
        self.target_bps.store(target, Ordering::Release);
    }
}

/// A viewer's entry in its feed's `link_bps`, removed when dropped.
struct ViewerLink<'a> {
    feed: &'a Feed,
    viewer: u64,
}

impl Drop for ViewerLink<'_> {
    fn drop(&mut self) {
        self.feed.set_link(self.viewer, None);
    }
}

/// The bitrate to give a viewer whose link is estimated at `estimate_bps`.
fn share_of_link(estimate_bps: u64, config: &VideoConfig) -> u64 {
    ((estimate_bps as f64 * LINK_SHARE) as u64).clamp(config.min_bitrate_bps(), config.max_bitrate_bps())
}

/// Of the camera's frames, one in this many is encoded at `target_bps`.
fn frame_divisor(target_bps: u64) -> u64 {
    FRAME_STEPS
        .iter()
        .find(|(below, _)| target_bps < *below)
        .map_or(1, |(_, n)| *n)
}

/// The spacing of the frames an encoder actually encodes, on their capture clock: an average that follows a change
/// within about `CADENCE_WEIGHT`'s reciprocal of frames.
#[derive(Debug, Default)]
struct Cadence {
    last_capture_ns: Option<i64>,
    mean_interval_s: Option<f64>,
}

/// The weight of each new interval in `Cadence`'s average (about the last five frames).
const CADENCE_WEIGHT: f64 = 0.2;

impl Cadence {
    fn encoded(&mut self, capture_unix_ns: i64) {
        if let Some(last) = self.last_capture_ns
            && capture_unix_ns > last
        {
            let interval_s = (capture_unix_ns - last) as f64 / 1e9;
            self.mean_interval_s = Some(
                self.mean_interval_s
                    .map_or(interval_s, |m| m + CADENCE_WEIGHT * (interval_s - m)),
            );
        }
        self.last_capture_ns = Some(capture_unix_ns);
    }

    /// The bitrate to give x264 so that the frames encoded at this cadence carry `link_bps` on the wire. x264
    /// spreads its bitrate over `fps` frames a second (it is opened at the camera's rate and counts frames), so a
    /// stream of fewer frames (ours skipped by `frame_divisor`, the CPU's or the server's missed) would carry
    /// only that fraction of the link's rate. Before two frames the skipping of `divisor` is all there is to go by.
    fn encoder_bps(&self, link_bps: u64, fps: u32, divisor: u64) -> u64 {
        let fps = f64::from(fps.max(1));
        let frames_per_encoded = match self.mean_interval_s {
            // At least one (never more than the camera's rate), at most a frame a second.
            Some(interval_s) => (interval_s * fps).clamp(1.0, fps),
            None => divisor as f64,
        };
        (link_bps as f64 * frames_per_encoded) as u64
    }
}

/// The video's own runtime thread and its connection to the server.
#[derive(Debug)]
struct VideoIo {
    handle: tokio::runtime::Handle,
    upstream: Upstream,
    /// Dropped with the hub: the thread's runtime ends, and with it every feed and viewer.
    _stop: tokio::sync::oneshot::Sender<()>,
}

/// Starts the `video-io` thread: a single-threaded runtime at a lower priority, with its own connection to the
/// server (`upstream` dialled again there).
fn start_io(upstream: &Upstream) -> Result<VideoIo, String> {
    let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel(1);
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let upstream = upstream.clone();
    std::thread::Builder::new()
        .name("video-io".into())
        .spawn(move || {
            lower_priority();
            let runtime = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                Ok(r) => r,
                Err(e) => {
                    let _ = ready_tx.send(Err(format!("video runtime: {e}")));
                    return;
                }
            };
            let own = {
                let _in_runtime = runtime.enter();
                upstream.separate()
            };
            let _ = ready_tx.send(Ok((runtime.handle().clone(), own)));
            runtime.block_on(async {
                let _ = stop_rx.await;
            });
        })
        .map_err(|e| format!("video thread: {e}"))?;
    // The thread answers once its runtime is built: a millisecond, once per gateway.
    let (handle, upstream) = ready_rx
        .recv()
        .map_err(|_| "video thread ended at start".to_owned())??;
    Ok(VideoIo {
        handle,
        upstream,
        _stop: stop_tx,
    })
}

/// Lowers the calling thread's CPU priority (threads it starts inherit it).
fn lower_priority() {
    phone2act_capture::priority::lower_current_thread(VIDEO_NICE);
}

/// The cameras' feeds, shared by every page socket.
#[derive(Debug)]
pub(crate) struct VideoHub {
    config: VideoConfig,
    feeds: Mutex<HashMap<String, Arc<Feed>>>,
    io: Mutex<Option<VideoIo>>,
    viewers: AtomicU64,
    /// Viewers running now (at most `config.max_viewers`).
    watching: Arc<AtomicU32>,
}

/// A place among the hub's viewers, given back when dropped.
struct ViewerPlace(Arc<AtomicU32>);

impl Drop for ViewerPlace {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

impl VideoHub {
    pub(crate) fn new(config: VideoConfig) -> Self {
        Self {
            config,
            feeds: Mutex::new(HashMap::new()),
            io: Mutex::new(None),
            viewers: AtomicU64::new(0),
            watching: Arc::new(AtomicU32::new(0)),
        }
    }

    /// A place for one more viewer, if `[gateway.video]` allows it.
    fn take_place(&self) -> Result<ViewerPlace, String> {
        if !self.config.enabled {
            return Err("live video is off on this gateway ([gateway.video] enabled = false)".into());
        }
        let max = self.config.max_viewers;
        self.watching
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .map(|_| ViewerPlace(self.watching.clone()))
            .map_err(|_| format!("{max} pages already watch the video ([gateway.video] max_viewers)"))
    }

    /// The video runtime's handle and connection, starting it on first use.
    fn io(&self, upstream: &Upstream) -> Result<(tokio::runtime::Handle, Upstream), String> {
        let mut io = self.io.lock();
        if io.is_none() {
            *io = Some(start_io(upstream)?);
        }
        let io = io.as_ref().expect("just started");
        Ok((io.handle.clone(), io.upstream.clone()))
    }

    /// Where other camera work of the sockets runs (the JPEG preview's fetches, rosbridge's image topics): the
    /// video runtime and its connection, or, if its thread cannot start, the caller's runtime and connection.
    pub(crate) fn background(&self, upstream: &Upstream) -> (tokio::runtime::Handle, Upstream) {
        self.io(upstream).unwrap_or_else(|e| {
            tracing::warn!("camera work stays on the control thread: {e}");
            (tokio::runtime::Handle::current(), upstream.clone())
        })
    }

    /// A receiver of `camera`'s frames, starting its feed (on the video runtime) if none runs.
    fn subscribe(
        &self,
        runtime: &tokio::runtime::Handle,
        upstream: &Upstream,
        camera: &str,
    ) -> (broadcast::Receiver<Arc<EncodedFrame>>, Arc<Feed>) {
        let mut feeds = self.feeds.lock();
        let feed = feeds
            .entry(camera.to_owned())
            .or_insert_with(|| Arc::new(Feed::new(self.config)))
            .clone();
        let rx = feed.tx.subscribe();
        feed.force_key.store(true, Ordering::Release);
        let mut task = feed.task.lock();
        if task.as_ref().is_none_or(JoinHandle::is_finished) {
            *task = Some(runtime.spawn(run_feed(upstream.clone(), camera.to_owned(), feed.clone())));
        }
        drop(task);
        (rx, feed)
    }
}

/// A raw frame on its way to the encoder thread.
struct RawFrame {
    rgb: Vec<u8>,
    width: u32,
    height: u32,
    fps: u32,
    capture_unix_ns: i64,
}

/// The one frame waiting for the encoder: a newer frame replaces it, so an encoder that falls behind encodes
/// the newest frame next and never works through a queue.
#[derive(Default)]
struct FrameSlot {
    frame: Mutex<Option<RawFrame>>,
    closed: AtomicBool,
    ready: parking_lot::Condvar,
}

impl FrameSlot {
    /// Puts `frame` in the slot; true when it replaced one the encoder had not taken.
    fn put(&self, frame: RawFrame) -> bool {
        let replaced = self.frame.lock().replace(frame).is_some();
        self.ready.notify_one();
        replaced
    }

    /// The newest frame, waiting for one; `None` once closed.
    fn take(&self) -> Option<RawFrame> {
        let mut slot = self.frame.lock();
        loop {
            if self.closed.load(Ordering::Acquire) {
                return None;
            }
            if let Some(frame) = slot.take() {
                return Some(frame);
            }
            self.ready.wait(&mut slot);
        }
    }

    fn close(&self) {
        let _slot = self.frame.lock();
        self.closed.store(true, Ordering::Release);
        self.ready.notify_one();
    }
}

/// Closes the slot when the fetch loop ends, however it ends (an aborted task too).
struct CloseOnDrop(Arc<FrameSlot>);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// Encodes one camera's frames on a thread of its own (FFmpeg's contexts stay on the thread that made them)
/// at the video's lower priority, at the bitrate its viewers' links allow, and publishes them. Ends when the
/// slot closes.
fn encode_thread(camera: &str, feed: &Feed, frames: &FrameSlot) {
    lower_priority();
    let mut encoder: Option<H264Encoder> = None;
    let mut seq = 0u64;
    let mut taken = 0u64;
    let mut cadence = Cadence::default();
    // The link rate the encoder's bitrate was last set for (what the frames carry on the wire).
    let mut aimed_bps = 0;
    // The frame rate the encoder was opened at, which its bitrate is spread over.
    let mut encoder_fps = 0;
    while let Some(frame) = frames.take() {
        let link = feed.target_bps.load(Ordering::Acquire);
        let divisor = frame_divisor(link);
        taken += 1;
        if !taken.is_multiple_of(divisor) {
            continue;
        }
        cadence.encoded(frame.capture_unix_ns);
        let reuse = encoder
            .take()
            .filter(|e| e.size() == (frame.width & !1, frame.height & !1));
        if reuse.is_none() {
            encoder_fps = frame.fps;
        }
        let target = cadence.encoder_bps(link, encoder_fps, divisor);
        let enc = if let Some(e) = reuse {
            e
        } else {
            let bitrate = usize::try_from(target).unwrap_or(usize::MAX);
            let out = feed.config.sent_size(frame.width, frame.height);
            match H264Encoder::scaled(frame.width, frame.height, out, frame.fps, bitrate) {
                Ok(e) => {
                    aimed_bps = link;
                    e
                }
                Err(e) => {
                    tracing::warn!("video of camera {camera}: {e}");
                    return;
                }
            }
        };
        let enc = encoder.insert(enc);
        let current = enc.bitrate_bps() as u64;
        if current.abs_diff(target) as f64 > current as f64 * RETARGET_FRACTION {
            tracing::debug!("video of camera {camera}: {current} -> {target} bit/s");
            enc.set_bitrate_bps(usize::try_from(target).unwrap_or(usize::MAX));
            aimed_bps = link;
        }
        let key = feed.force_key.swap(false, Ordering::AcqRel);
        match enc.encode(&frame.rgb, frame.width, key) {
            Ok(Some((data, keyframe))) => {
                seq += 1;
                let _ = feed.tx.send(Arc::new(EncodedFrame {
                    data: data.into(),
                    keyframe,
                    capture_unix_ns: frame.capture_unix_ns,
                    seq,
                    bitrate_bps: aimed_bps,
                }));
            }
            Ok(None) => {}
            Err(e) => tracing::warn!("video of camera {camera}: {e}"),
        }
    }
}

/// Fetches one camera's frames while anyone watches and hands them to its encoder thread.
async fn run_feed(upstream: Upstream, camera: String, feed: Arc<Feed>) {
    let slot = Arc::new(FrameSlot::default());
    let thread = {
        let (camera, feed, slot) = (camera.clone(), feed.clone(), slot.clone());
        std::thread::Builder::new()
            .name(format!("video-{camera}"))
            .spawn(move || encode_thread(&camera, &feed, &slot))
    };
    if let Err(e) = thread {
        tracing::warn!("video of camera {camera}: no encoder thread: {e}");
        return;
    }
    let _close = CloseOnDrop(slot.clone());
    let mut last: Option<(u64, i64)> = None; // (frame_seq, capture_time_ns on the server's clock)
    let shortest = Duration::from_secs_f64(1.0 / f64::from(feed.config.max_fps));
    let mut period = shortest;
    let mut failing = false;
    while feed.tx.receiver_count() > 0 {
        let timed = match upstream.camera_frame(&camera, ImageEncoding::Rgb8).await {
            Ok(Some(t)) => t,
            Ok(None) => {
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
            Err(e) => {
                if !failing {
                    tracing::warn!("video of camera {camera}: {}", e.message());
                    failing = true;
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        let (frame, capture_unix_ns) = (timed.frame, timed.capture_unix_ns);
        failing = false;
        if last.is_some_and(|(s, _)| s == frame.frame_seq) {
            // Not captured yet: poll again soon (a few ms of latency at most, a cheap call on loopback).
            tokio::time::sleep(Duration::from_millis(3)).await;
            continue;
        }
        if let Some((s, t)) = last
            && frame.frame_seq == s + 1
            && frame.capture_time_ns > t
        {
            let measured = Duration::from_nanos((frame.capture_time_ns - t).unsigned_abs());
            period = measured.max(shortest);
        }
        last = Some((frame.frame_seq, frame.capture_time_ns));
        let raw = RawFrame {
            rgb: frame.data,
            width: frame.width,
            height: frame.height,
            fps: (1.0 / period.as_secs_f64()).round() as u32,
            capture_unix_ns,
        };
        if slot.put(raw) {
            tracing::trace!("video of camera {camera}: the encoder skipped a frame");
        }
        // The next frame is due one period after this one was captured.
        let age =
            Duration::from_nanos(u64::try_from(unix_ns(SystemTime::now()) - capture_unix_ns).unwrap_or(0));
        if let Some(wait) = period.checked_sub(age + Duration::from_millis(2)) {
            tokio::time::sleep(wait).await;
        }
    }
}

/// Where the viewer's UDP socket listens: the address the page reached this gateway at, when it is one.
pub(crate) fn bind_ip(
    page_host: Option<&str>,
    https_listen: SocketAddr,
    public_host: Option<&str>,
) -> Option<IpAddr> {
    let parse = |h: &str| h.trim_matches(['[', ']']).parse::<IpAddr>().ok();
    page_host
        .and_then(parse)
        .or_else(|| (!https_listen.ip().is_unspecified()).then(|| https_listen.ip()))
        .or_else(|| public_host.and_then(parse))
}

/// Whether a page whose socket comes from `page_ip` runs on this machine, the viewer's socket being bound to
/// `bind_ip` (the address the page reached the gateway at): a local connection's source address is its
/// destination's.
fn same_host(bind_ip: IpAddr, page_ip: IpAddr) -> bool {
    bind_ip == page_ip
}

/// Answers `offer_sdp` for `camera` and starts the viewer on the video runtime; its task ends with the returned
/// handle's abort. `ips` is (where the viewer's UDP socket binds, where the page's socket comes from).
pub(crate) fn start_viewer(
    hub: &VideoHub,
    upstream: &Upstream,
    camera: &str,
    offer_sdp: &str,
    ips: (IpAddr, IpAddr),
    out: Out,
) -> Result<(String, JoinHandle<()>), String> {
    let (ip, page_ip) = ips;
    let local_page = same_host(ip, page_ip);
    let place = hub.take_place()?;
    let offer = SdpOffer::from_sdp_string(offer_sdp).map_err(|e| format!("bad video offer: {e}"))?;
    // A std socket here; the video runtime registers it with its own reactor.
    let socket = std::net::UdpSocket::bind(SocketAddr::new(ip, 0))
        .and_then(|s| s.set_nonblocking(true).map(|()| s))
        .map_err(|e| format!("video socket on {ip}: {e}"))?;
    let local = socket.local_addr().map_err(|e| e.to_string())?;
    let mut rtc = RtcConfig::new()
        .clear_codecs()
        .enable_h264(true)
        .set_ice_lite(true)
        // Send-side bandwidth estimation on the page's transport-wide feedback, from the top rate down; none for a
        // page on this machine (no estimate: the ceiling, unpaced).
        .enable_bwe((!local_page).then(|| Bitrate::bps(hub.config.max_bitrate_bps())))
        .build(Instant::now());
    let candidate = Candidate::host(local, "udp").map_err(|e| format!("video candidate: {e}"))?;
    rtc.add_local_candidate(candidate)
        .ok_or_else(|| "video candidate refused".to_owned())?;
    let answer = rtc
        .sdp_api()
        .accept_offer(offer)
        .map_err(|e| format!("video offer refused: {e}"))?;
    let (runtime, video_upstream) = hub.io(upstream)?;
    let (rx, feed) = hub.subscribe(&runtime, &video_upstream, camera);
    let viewer = hub.viewers.fetch_add(1, Ordering::Relaxed);
    let camera = camera.to_owned();
    let task = runtime.spawn(async move {
        // Forgets this viewer's link and gives its place back however the task ends (`video_off` and a new
        // offer abort it).
        let _share = ViewerLink { feed: &feed, viewer };
        let _place = place;
        let ended = match UdpSocket::from_std(socket) {
            // Boxed: the Rtc is large, and the task's future need not carry it inline.
            Ok(socket) => Box::pin(run_viewer(rtc, socket, local, rx, &feed, viewer)).await,
            Err(e) => Err(format!("video socket: {e}")),
        };
        if let Err(e) = ended {
            tracing::debug!("video viewer of {camera} ended: {e}");
        }
        out.text(json!({"type": "video", "state": "off", "camera": camera}).to_string());
    });
    Ok((answer.to_sdp_string(), task))
}

/// The H.264 payload type the page offered that every browser decodes: packetization mode 1, constrained
/// baseline first.
fn h264_pt(rtc: &mut Rtc, mid: Mid) -> Option<str0m::format::PayloadParams> {
    let writer = rtc.writer(mid)?;
    let mut best: Option<(u8, str0m::format::PayloadParams)> = None;
    for p in writer.payload_params() {
        let spec = p.spec();
        if spec.codec != Codec::H264 || spec.format.packetization_mode != Some(1) {
            continue;
        }
        let rank = match spec.format.profile_level_id {
            Some(0x0042_e01f) => 0,
            Some(id) if id >> 16 == 0x42 => 1,
            _ => 2,
        };
        if best.as_ref().is_none_or(|(r, _)| rank < *r) {
            best = Some((rank, *p));
        }
    }
    best.map(|(_, p)| p)
}

async fn run_viewer(
    mut rtc: Rtc,
    socket: UdpSocket,
    local: SocketAddr,
    mut rx: broadcast::Receiver<Arc<EncodedFrame>>,
    feed: &Feed,
    viewer: u64,
) -> Result<(), String> {
    let mut buf = vec![0u8; 2048];
    let mut video: Option<(Mid, str0m::format::PayloadParams)> = None;
    let mut channel = None;
    let mut connected = false;
    // A decoder starts at a keyframe: until one went out to this viewer, other frames are skipped.
    let mut need_key = true;
    let mut last_heard = Instant::now();
    let mut estimate_bps: Option<u64> = None;
    loop {
        let deadline = loop {
            match rtc.poll_output().map_err(|e| e.to_string())? {
                Output::Timeout(t) => break t,
                Output::Transmit(t) => {
                    // A full socket buffer drops the datagram, like the network would: never wait here.
                    let _ = socket.try_send_to(&t.contents, t.destination);
                }
                Output::Event(e) => match e {
                    Event::Connected => {
                        connected = true;
                        // Probe up to the top rate: the estimate can then rise back after a slow spell.
                        rtc.bwe()
                            .set_desired_bitrate(Bitrate::bps(feed.config.max_bitrate_bps()));
                    }
                    Event::EgressBitrateEstimate(
                        BweKind::Twcc { estimate, .. } | BweKind::Remb { estimate, .. },
                    ) => {
                        let bps = estimate.as_u64();
                        estimate_bps = Some(bps);
                        feed.set_link(viewer, Some(share_of_link(bps, &feed.config)));
                    }
                    Event::MediaAdded(m) if m.kind == MediaKind::Video => {
                        video = h264_pt(&mut rtc, m.mid).map(|p| (m.mid, p));
                        if video.is_none() {
                            return Err("the page offered no H.264 this gateway can send".into());
                        }
                    }
                    Event::ChannelOpen(id, _) => channel = Some(id),
                    Event::KeyframeRequest(_) => feed.force_key.store(true, Ordering::Release),
                    Event::IceConnectionStateChange(IceConnectionState::Disconnected) => {
                        return Err("the page went away".into());
                    }
                    _ => {}
                },
            }
        };
        if !rtc.is_alive() || last_heard.elapsed() > VIEWER_IDLE {
            return Err("connection over".into());
        }
        let sleep = tokio::time::sleep_until(tokio::time::Instant::from_std(deadline.max(Instant::now())));
        tokio::select! {
            r = socket.recv_from(&mut buf) => {
                let (n, source) = r.map_err(|e| e.to_string())?;
                last_heard = Instant::now();
                let Ok(contents) = buf[..n].try_into() else { continue };
                let input = Input::Receive(Instant::now(), Receive { proto: Protocol::Udp, source, destination: local, contents });
                if rtc.accepts(&input) {
                    rtc.handle_input(input).map_err(|e| e.to_string())?;
                }
            }
            frame = rx.recv() => match frame {
                Ok(frame) => {
                    let Some((mid, params)) = video.filter(|_| connected) else { continue };
                    if need_key && !frame.keyframe {
                        feed.force_key.store(true, Ordering::Release);
                        continue;
                    }
                    need_key = false;
                    let rtp_90k = u64::try_from(frame.capture_unix_ns).unwrap_or(0) / 100_000 * 9;
                    // str0m stamps each packet it sends with the time of its last input, and the estimator
                    // compares those stamps with the page's arrival times. Its clock is moved to now first: the
                    // frame's packets go out now, and stamped with the last input before it (a feedback or a
                    // timer, up to tens of milliseconds earlier, more on a busy machine) they looked delayed in
                    // the network by the difference, which the estimator read as a growing queue.
                    let now = Instant::now();
                    rtc.handle_input(Input::Timeout(now)).map_err(|e| e.to_string())?;
                    if let Some(writer) = rtc.writer(mid) {
                        writer
                            .write(params.pt(), now, MediaTime::from_90khz(rtp_90k), frame.data.clone())
                            .map_err(|e| e.to_string())?;
                    }
                    if let Some(mut ch) = channel.and_then(|id| rtc.channel(id)) {
                        let msg = json!({
                            "rtp": rtp_90k & 0xffff_ffff,
                            "capture_unix_ms": frame.capture_unix_ns as f64 / 1e6,
                            "seq": frame.seq,
                            "key": frame.keyframe,
                            "bitrate_bps": frame.bitrate_bps,
                            "link_estimate_bps": estimate_bps,
                        });
                        // A full SCTP buffer drops the note; the page skips that frame's latency.
                        let _ = ch.write(false, msg.to_string().as_bytes());
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    // This viewer lost the oldest frames: resume at a keyframe.
                    need_key = true;
                    feed.force_key.store(true, Ordering::Release);
                }
                Err(broadcast::error::RecvError::Closed) => return Err("feed ended".into()),
            },
            () = sleep => {
                rtc.handle_input(Input::Timeout(Instant::now())).map_err(|e| e.to_string())?;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_page_from_the_viewers_own_address_counts_as_this_machine() {
        let ip = |s: &str| s.parse::<IpAddr>().unwrap();
        assert!(same_host(ip("127.0.0.1"), ip("127.0.0.1")));
        assert!(same_host(ip("192.168.1.20"), ip("192.168.1.20")));
        // Another loopback address plays another machine (the throttled-link test's relay), and a LAN peer is one.
        assert!(!same_host(ip("127.0.0.1"), ip("127.0.0.2")));
        assert!(!same_host(ip("192.168.1.20"), ip("192.168.1.30")));
        assert!(!same_host(ip("::1"), ip("127.0.0.1")));
    }

    #[test]
    fn the_viewer_binds_where_the_page_reached_the_gateway() {
        let any: SocketAddr = "0.0.0.0:8443".parse().unwrap();
        let lan: SocketAddr = "192.168.1.20:8443".parse().unwrap();
        assert_eq!(
            bind_ip(Some("127.0.0.1"), any, None),
            Some("127.0.0.1".parse().unwrap())
        );
        assert_eq!(bind_ip(Some("[::1]"), any, None), Some("::1".parse().unwrap()));
        assert_eq!(bind_ip(Some("robot.local"), lan, None), Some(lan.ip()));
        assert_eq!(
            bind_ip(Some("robot.local"), any, Some("10.0.0.5")),
            Some("10.0.0.5".parse().unwrap())
        );
        assert_eq!(bind_ip(None, any, Some("robot.local")), None);
    }

    fn raw(capture_unix_ns: i64) -> RawFrame {
        RawFrame {
            rgb: Vec::new(),
            width: 2,
            height: 2,
            fps: 30,
            capture_unix_ns,
        }
    }

    #[test]
    fn the_encoder_takes_the_newest_frame_and_stops_when_closed() {
        let slot = FrameSlot::default();
        assert!(!slot.put(raw(1)));
        // The encoder was busy: the newer frame replaces the waiting one.
        assert!(slot.put(raw(2)));
        assert_eq!(slot.take().map(|f| f.capture_unix_ns), Some(2));
        let slot = Arc::new(slot);
        let waiter = {
            let slot = slot.clone();
            std::thread::spawn(move || slot.take().map(|f| f.capture_unix_ns))
        };
        slot.close();
        assert_eq!(
            waiter.join().unwrap(),
            None,
            "a waiting encoder ends when the feed closes"
        );
    }

    #[test]
    fn the_bitrate_follows_the_slowest_viewer_within_bounds() {
        let config = VideoConfig::default();
        let feed = Feed::new(config);
        let target = || feed.target_bps.load(Ordering::Acquire);
        assert_eq!(share_of_link(1_000_000, &config), 850_000);
        assert_eq!(share_of_link(10_000_000, &config), 1_500_000);
        assert_eq!(share_of_link(10_000, &config), 60_000);
        let narrow = VideoConfig {
            min_bitrate_kbps: 200,
            max_bitrate_kbps: 800,
            ..config
        };
        assert_eq!(share_of_link(10_000_000, &narrow), 800_000);
        assert_eq!(share_of_link(10_000, &narrow), 200_000);
        feed.set_link(1, Some(share_of_link(1_000_000, &config)));
        feed.set_link(2, Some(share_of_link(400_000, &config)));
        assert_eq!(target(), 340_000, "the slower viewer's share");
        feed.set_link(2, None);
        assert_eq!(target(), 850_000, "the slow viewer left");
        feed.set_link(1, None);
        assert_eq!(target(), 1_500_000, "no estimate: the top rate");
        assert_eq!(frame_divisor(1_500_000), 1);
        assert_eq!(frame_divisor(299_999), 2);
        assert_eq!(frame_divisor(60_000), 3);
    }

    #[test]
    fn the_encoder_is_given_the_link_rate_spread_over_the_frames_it_actually_encodes() {
        let ms = |t: i64| t * 1_000_000;
        let mut cadence = Cadence::default();
        // Before two frames: only the frames skipped on purpose count.
        assert_eq!(cadence.encoder_bps(200_000, 30, 2), 400_000);
        cadence.encoded(ms(0));
        assert_eq!(cadence.encoder_bps(200_000, 30, 2), 400_000);
        // Every third frame of 30 fps (100 ms apart): x264, counting 30 a second, is given three times the link.
        for i in 1..=20 {
            cadence.encoded(ms(100 * i));
        }
        assert_eq!(cadence.encoder_bps(200_000, 30, 1), 600_000);
        // A starved encoder that gets a frame every 500 ms: fifteen times, so each frame carries its half second.
        for i in 1..=40 {
            cadence.encoded(ms(2_000 + 500 * i));
        }
        let starved = cadence.encoder_bps(200_000, 30, 1);
        assert!((2_990_000..=3_000_000).contains(&starved), "{starved}");
        // Frames at the camera's rate (or faster, on a capture clock's jitter): the link's rate as it is.
        for i in 1..=60 {
            cadence.encoded(ms(30_000 + 20 * i));
        }
        assert_eq!(cadence.encoder_bps(200_000, 30, 1), 200_000);
        // Seconds between frames: at most one frame a second's worth, the camera's rate times the link.
        cadence.encoded(ms(60_000));
        cadence.encoded(ms(70_000));
        assert_eq!(cadence.encoder_bps(200_000, 30, 1), 6_000_000);
        // A capture time that goes back is not an interval.
        let before = cadence.mean_interval_s;
        cadence.encoded(ms(50_000));
        assert_eq!(cadence.mean_interval_s, before);
    }

    #[test]
    fn viewers_beyond_the_cap_and_a_disabled_video_are_refused() {
        let hub = VideoHub::new(VideoConfig {
            max_viewers: 2,
            ..VideoConfig::default()
        });
        let (a, b) = (hub.take_place().unwrap(), hub.take_place().unwrap());
        let refused = hub.take_place().err().unwrap();
        assert!(refused.contains("2 pages already watch"), "{refused}");
        drop(a);
        let _c = hub.take_place().expect("a viewer left: its place is free");
        drop(b);
        let off = VideoHub::new(VideoConfig {
            enabled: false,
            ..VideoConfig::default()
        });
        let refused = off.take_place().err().unwrap();
        assert!(refused.contains("enabled = false"), "{refused}");
    }
}
