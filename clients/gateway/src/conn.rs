//! The per-socket loop shared by both protocols: read frames, enforce the size limit, hand text to the
//! protocol handler, relay session events and status snapshots, write through a bounded queue, ping idle
//! peers, and close on shutdown.
//!
//! Writes go through their own task so that a phone that stops reading never stalls the reading side (and
//! with it the pose path); when the queue is full, messages are dropped rather than buffered.
//!
//! The phone page's camera preview has its own slot of one frame (latest wins) beside that queue: the writer
//! sends it only when no control message is waiting and the page has acknowledged the previous frame, so at
//! most one preview frame is ever on the link and feedback never waits behind a queue of images.
//!
//! rosbridge's camera images (base64 text, tens of kB each) go through an [`ImageLane`] beside the queue for the
//! same reason: one waiting image per topic, the newest winning, sent only when no control message waits.

use crate::session::SessionEvent;
use axum::body::Bytes;
use axum::extract::ws::{CloseFrame, Message, WebSocket, close_code};
use futures_util::{SinkExt, StreamExt};
use parking_lot::Mutex;
use phone2act_proto::v1::SystemStatus;
use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::{Notify, mpsc, watch};

/// Outgoing queue depth per socket.
const OUT_QUEUE: usize = 256;
/// A peer silent for this long (no message, no pong) is considered gone; the Phone2Act app and the page
/// both send at 30–60 Hz, so this only fires on a dead Wi-Fi link, and frees the arm for the reconnect.
const IDLE_TIMEOUT: Duration = Duration::from_secs(15);
const PING_INTERVAL: Duration = Duration::from_secs(5);

/// The sending half a handler writes to.
#[derive(Clone, Debug)]
pub(crate) struct Out(mpsc::Sender<Message>);

impl Out {
    /// Queues a text frame; dropped if the peer is not reading.
    pub(crate) fn text(&self, text: String) {
        if self.0.try_send(Message::Text(text.into())).is_err() {
            tracing::debug!("outgoing queue full, message dropped");
        }
    }

    /// Queues a close frame.
    pub(crate) fn close(&self, code: u16, reason: &str) {
        let _ = self.0.try_send(Message::Close(Some(CloseFrame {
            code,
            reason: reason.to_owned().into(),
        })));
    }
}

/// One socket's camera preview frame waiting to go out: a slot of one (a newer frame replaces an unsent
/// one), sent only when the control queue is empty and the page has acknowledged the frame before.
#[derive(Debug, Default)]
pub(crate) struct PreviewSlot {
    /// The preview's generation (a new one at every start and stop, so a fetch that finishes after its
    /// preview was stopped stores nothing) and the frame waiting.
    frame: Mutex<(u64, Option<Bytes>)>,
    /// A frame went out and the page has not acknowledged it yet.
    in_flight: AtomicBool,
    changed: Notify,
}

impl PreviewSlot {
    /// Starts a new preview; its frames are put with the generation returned.
    pub(crate) fn open(&self) -> u64 {
        let mut slot = self.frame.lock();
        slot.0 += 1;
        slot.1 = None;
        slot.0
    }

    /// Offers a frame of preview `generation`; it replaces one not sent yet. Ignored once that preview has
    /// been stopped.
    pub(crate) fn put(&self, generation: u64, jpeg: Bytes) {
        let mut slot = self.frame.lock();
        if slot.0 == generation {
            slot.1 = Some(jpeg);
            drop(slot);
            self.changed.notify_one();
        }
    }

    /// True while a frame waits in the slot or is on its way to the page: fetching another now would only
    /// replace it.
    pub(crate) fn busy(&self) -> bool {
        self.in_flight.load(Ordering::Acquire) || self.frame.lock().1.is_some()
    }

    /// The page has the last frame sent.
    pub(crate) fn ack(&self) {
        self.in_flight.store(false, Ordering::Release);
        self.changed.notify_one();
    }

    /// Stops the preview: the waiting frame is dropped and no frame of it is accepted any more. A frame
    /// already on the link stays in flight until the page acknowledges it (the page acknowledges every
    /// binary message, wanted or not), so a preview restarted at once never puts a second frame beside it.
    pub(crate) fn close(&self) {
        let mut slot = self.frame.lock();
        slot.0 += 1;
        slot.1 = None;
    }

    /// The frame to send now, if there is one and the previous one was acknowledged.
    fn take_sendable(&self) -> Option<Bytes> {
        if self.in_flight.load(Ordering::Acquire) {
            return None;
        }
        let frame = self.frame.lock().1.take()?;
        self.in_flight.store(true, Ordering::Release);
        Some(frame)
    }
}

/// One socket's rosbridge camera images waiting to go out: at most one per topic (a newer image replaces an
/// unsent one), sent in the order their topics first waited, and only when the control queue is empty. Each
/// subscription puts with the generation [`ImageLane::open`] gave it, so an image fetched after its
/// subscription ended is never sent.
#[derive(Debug, Default)]
pub(crate) struct ImageLane {
    state: Mutex<LaneState>,
    changed: Notify,
}

#[derive(Debug, Default)]
struct LaneState {
    /// The last generation handed out.
    generation: u64,
    /// The generation of each open topic.
    open: Vec<(String, u64)>,
    /// Text frames waiting, one per topic.
    waiting: VecDeque<(String, String)>,
}

impl LaneState {
    fn drop_waiting(&mut self, topic: &str) {
        self.waiting.retain(|(t, _)| t != topic);
    }
}

impl ImageLane {
    /// Opens (or reopens) `topic`; its images are put with the generation returned. An image of the topic's
    /// previous opening that has not gone out yet is dropped.
    pub(crate) fn open(&self, topic: &str) -> u64 {
        let mut state = self.state.lock();
        state.generation += 1;
        let generation = state.generation;
        state.open.retain(|(t, _)| t != topic);
        state.open.push((topic.to_owned(), generation));
        state.drop_waiting(topic);
        generation
    }

    /// Closes `topic`: its waiting image is dropped and no image of it is accepted any more.
    pub(crate) fn close(&self, topic: &str) {
        let mut state = self.state.lock();
        state.open.retain(|(t, _)| t != topic);
        state.drop_waiting(topic);
    }

    /// Offers `text` for `topic`, replacing its image not sent yet; false (and nothing stored) once that
    /// opening of the topic was closed or replaced.
    pub(crate) fn put(&self, topic: &str, generation: u64, text: String) -> bool {
        let mut state = self.state.lock();
        if !state.open.iter().any(|(t, g)| t == topic && *g == generation) {
            return false;
        }
        match state.waiting.iter_mut().find(|(t, _)| t == topic) {
            Some(slot) => slot.1 = text,
            None => state.waiting.push_back((topic.to_owned(), text)),
        }
        drop(state);
        self.changed.notify_one();
        true
    }

    /// True while an image of `topic` waits: the socket is slower than the topic's rate, and fetching another
    /// now would only replace it.
    pub(crate) fn is_waiting(&self, topic: &str) -> bool {
        self.state.lock().waiting.iter().any(|(t, _)| t == topic)
    }

    fn take(&self) -> Option<String> {
        self.state.lock().waiting.pop_front().map(|(_, text)| text)
    }
}

/// What a protocol does with the socket's input.
pub(crate) trait Handler: Send {
    /// One text message within the size limit.
    fn on_text(&mut self, text: &str);
    /// A message larger than the configured limit (refused, connection kept).
    fn on_oversized(&mut self, len: usize);
    /// An event from one of this socket's teleop sessions.
    fn on_session_event(&mut self, event: SessionEvent);
    /// A status snapshot from the watcher this handler started.
    fn on_status(&mut self, _status: Box<SystemStatus>) {}
    /// Set once the handler wants the socket closed (after its close frame is queued).
    fn wants_close(&self) -> bool {
        false
    }
}

/// Channels a handler needs besides `Out`.
#[derive(Debug)]
pub(crate) struct Wiring {
    pub out: Out,
    pub session_events: mpsc::Sender<SessionEvent>,
    pub status_events: mpsc::Sender<Box<SystemStatus>>,
    /// The camera preview's frame slot (only the phone page fills it).
    pub preview: Arc<PreviewSlot>,
    /// The camera images of rosbridge subscriptions.
    pub images: Arc<ImageLane>,
}

/// Writes control messages as they come and, when none is waiting, the preview frame if the page took the
/// last one, then the camera images waiting; ends after a close frame or a failed write.
async fn write_loop<S>(
    mut sink: S,
    mut out_rx: mpsc::Receiver<Message>,
    preview: Arc<PreviewSlot>,
    images: Arc<ImageLane>,
) where
    S: futures_util::Sink<Message> + Unpin,
{
    loop {
        let msg = match out_rx.try_recv() {
            Ok(msg) => msg,
            Err(mpsc::error::TryRecvError::Disconnected) => break,
            Err(mpsc::error::TryRecvError::Empty) => {
                if let Some(jpeg) = preview.take_sendable() {
                    Message::Binary(jpeg)
                } else if let Some(text) = images.take() {
                    Message::Text(text.into())
                } else {
                    tokio::select! {
                        msg = out_rx.recv() => match msg {
                            Some(msg) => msg,
                            None => break,
                        },
                        () = preview.changed.notified() => continue,
                        () = images.changed.notified() => continue,
                    }
                }
            }
        };
        let closing = matches!(msg, Message::Close(_));
        if sink.send(msg).await.is_err() || closing {
            break;
        }
    }
    let _ = sink.close().await;
}

/// Runs one socket until the peer leaves, the handler closes it, or shutdown.
pub(crate) async fn run<H, F>(
    socket: WebSocket,
    max_message_bytes: usize,
    mut shutdown: watch::Receiver<bool>,
    make: F,
) where
    H: Handler,
    F: FnOnce(Wiring) -> H,
{
    let (sink, mut stream) = socket.split();
    let (out_tx, out_rx) = mpsc::channel::<Message>(OUT_QUEUE);
    let preview = Arc::new(PreviewSlot::default());
    let images = Arc::new(ImageLane::default());
    let writer = tokio::spawn(write_loop(sink, out_rx, preview.clone(), images.clone()));
    let (session_tx, mut session_rx) = mpsc::channel(64);
    let (status_tx, mut status_rx) = mpsc::channel(4);
    let out = Out(out_tx);
    let mut handler = make(Wiring {
        out: out.clone(),
        session_events: session_tx,
        status_events: status_tx,
        preview,
        images,
    });
    let mut last_heard = Instant::now();
    let mut ping = tokio::time::interval(PING_INTERVAL);
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            frame = stream.next() => {
                last_heard = Instant::now();
                match frame {
                    Some(Ok(Message::Text(text))) => {
                        if text.len() > max_message_bytes {
                            handler.on_oversized(text.len());
                        } else {
                            handler.on_text(text.as_str());
                        }
                    }
                    Some(Ok(Message::Binary(bytes))) => {
                        // rosbridge decodes binary frames as UTF-8 JSON; so do we.
                        if bytes.len() > max_message_bytes {
                            handler.on_oversized(bytes.len());
                        } else {
                            handler.on_text(&String::from_utf8_lossy(&bytes));
                        }
                    }
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => {}
                    Some(Ok(Message::Close(_)) | Err(_)) | None => {
                        if let Some(Err(e)) = &frame {
                            tracing::debug!(error = %e, "socket read failed");
                            if e.to_string().contains("too long") || e.to_string().contains("Space limit") {
                                out.close(close_code::SIZE, "message too big");
                            }
                        }
                        break;
                    }
                }
                if handler.wants_close() {
                    break;
                }
            }
            Some(event) = session_rx.recv() => handler.on_session_event(event),
            Some(status) = status_rx.recv() => handler.on_status(status),
            _ = ping.tick() => {
                if last_heard.elapsed() > IDLE_TIMEOUT {
                    tracing::info!("peer silent for {:?}, closing", IDLE_TIMEOUT);
                    out.close(close_code::AWAY, "idle");
                    break;
                }
                let _ = out.0.try_send(Message::Ping(Vec::new().into()));
            }
            _ = shutdown.wait_for(|stop| *stop) => {
                out.close(close_code::AWAY, "gateway shutting down");
                break;
            }
        }
    }
    // Dropping the handler drops its sessions, which ends their gRPC streams.
    drop(handler);
    drop(out);
    let _ = tokio::time::timeout(Duration::from_secs(1), writer).await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_preview_slot_keeps_one_frame_and_waits_for_the_ack() {
        let slot = PreviewSlot::default();
        let preview = slot.open();
        assert!(!slot.busy());
        slot.put(preview, Bytes::from_static(b"old"));
        slot.put(preview, Bytes::from_static(b"new"));
        assert!(slot.busy());
        // Latest wins: one frame, the newest.
        assert_eq!(slot.take_sendable().as_deref(), Some(&b"new"[..]));
        assert_eq!(slot.take_sendable(), None);
        // On its way and not acknowledged: busy, and the next frame waits.
        assert!(slot.busy());
        slot.put(preview, Bytes::from_static(b"next"));
        assert_eq!(slot.take_sendable(), None);
        slot.ack();
        assert_eq!(slot.take_sendable().as_deref(), Some(&b"next"[..]));
    }

    #[test]
    fn a_stopped_preview_leaves_nothing_to_send() {
        let slot = PreviewSlot::default();
        let stopped = slot.open();
        slot.put(stopped, Bytes::from_static(b"waiting"));
        slot.close();
        assert!(!slot.busy());
        assert_eq!(slot.take_sendable(), None);
        // A fetch of the stopped preview that finishes late stores nothing, even after a new one started.
        let current = slot.open();
        slot.put(stopped, Bytes::from_static(b"late"));
        assert_eq!(slot.take_sendable(), None);
        slot.put(current, Bytes::from_static(b"fresh"));
        assert_eq!(slot.take_sendable().as_deref(), Some(&b"fresh"[..]));
    }

    #[test]
    fn the_image_lane_keeps_the_newest_image_per_topic_in_the_order_topics_waited() {
        let lane = ImageLane::default();
        let front = lane.open("/front");
        let wrist = lane.open("/wrist");
        assert!(lane.put("/wrist", wrist, "wrist 1".into()));
        assert!(lane.put("/front", front, "front 1".into()));
        assert!(lane.put("/wrist", wrist, "wrist 2".into()));
        assert!(lane.is_waiting("/front") && lane.is_waiting("/wrist"));
        assert_eq!(lane.take().as_deref(), Some("wrist 2"));
        assert_eq!(lane.take().as_deref(), Some("front 1"));
        assert_eq!(lane.take(), None);
        assert!(!lane.is_waiting("/front"));
    }

    #[test]
    fn a_closed_or_reopened_topic_sends_nothing_of_its_old_subscription() {
        let lane = ImageLane::default();
        let old = lane.open("/front");
        assert!(lane.put("/front", old, "waiting".into()));
        lane.close("/front");
        assert_eq!(lane.take(), None, "closing drops the waiting image");
        assert!(
            !lane.put("/front", old, "late".into()),
            "a fetch that ends after the close"
        );
        let new = lane.open("/front");
        assert!(
            !lane.put("/front", old, "late".into()),
            "still refused after a new subscription"
        );
        assert!(lane.put("/front", new, "fresh".into()));
        assert_eq!(lane.take().as_deref(), Some("fresh"));
    }

    #[test]
    fn a_restarted_preview_waits_for_the_ack_of_the_frame_still_on_the_link() {
        let slot = PreviewSlot::default();
        let old = slot.open();
        slot.put(old, Bytes::from_static(b"old"));
        assert!(slot.take_sendable().is_some());
        // The page switches camera while the old frame is on its way.
        slot.close();
        let new = slot.open();
        slot.put(new, Bytes::from_static(b"new"));
        assert_eq!(slot.take_sendable(), None, "one frame on the link at a time");
        assert!(slot.busy());
        slot.ack();
        assert_eq!(slot.take_sendable().as_deref(), Some(&b"new"[..]));
    }
}
