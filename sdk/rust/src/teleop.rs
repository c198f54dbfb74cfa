//! The Teleop service: a phone's stream of samples to one arm, fed through one depth-1 latest-wins outbox.
//!
//! Two ways to drive it share that outbox:
//! - [`TeleopSession`]: one stream, opened now, the SDK numbering the samples (scripts, tests, examples);
//! - [`TeleopLink`]: a stream that opens on the first sample and opens again after the server went away,
//!   passing the caller's own sample numbers through (the phone gateway: a phone's seq comes back in its
//!   feedback so the page can show its round trip).

use crate::{AuthChannel, Client, Error, Result};
use parking_lot::Mutex;
use phone2act_proto::PendingSample;
use phone2act_proto::v1;
use phone2act_proto::v1::teleop_client::TeleopClient;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{Notify, mpsc};
use tokio::task::JoinHandle;
use tonic::Code;

impl Client {
    /// Opens a teleop session bound to `arm`. Samples are sent through a depth-1 queue: if the network is slower
    /// than the phone, [`TeleopSession::send`] reports the sample as superseded instead of queueing it.
    pub async fn teleop(&self, arm: &str, options: TeleopOptions) -> Result<TeleopSession> {
        TeleopSession::open(self.teleop_raw(), arm, options).await
    }

    /// A teleop stream to `arm` that opens on the first [`TeleopLink::send`] and again after a stream broke
    /// for a reason that may pass (the server restarting), until the server refuses it. What happens is told
    /// on `events`.
    pub fn teleop_link(&self, arm: &str, events: mpsc::Sender<TeleopEvent>) -> TeleopLink {
        TeleopLink::start(self.teleop_raw(), arm.to_owned(), events)
    }

    /// The raw generated Teleop client.
    pub fn teleop_raw(&self) -> TeleopClient<AuthChannel> {
        TeleopClient::with_interceptor(self.transport(), self.auth())
    }
}

/// Options for [`Client::teleop`].
#[derive(Clone, Debug, Default)]
pub struct TeleopOptions {
    /// Client name shown in status displays.
    pub client_name: String,
    /// Take the arm even if another phone owns it.
    pub take_over: bool,
}

#[derive(Debug, Default)]
struct OutboxState {
    pending: PendingSample,
    /// The sender closed its end: the request stream ends once the pending sample is taken.
    closed: bool,
    /// The request stream is gone (the call ended) and no other will follow: nothing offered now would reach
    /// the server.
    gone: bool,
    /// Samples folded into a newer one before they went out.
    superseded: u64,
}

/// The depth-1 latest-wins outbox between a sender and its gRPC request stream: the stream takes the pending
/// sample when HTTP/2 flow control lets it send, and a sample offered meanwhile is folded into the pending one
/// ([`PendingSample::push`]) so the newest pose is what goes out and no button event is lost (a lost "stop
/// recording" is worse than a late one).
#[derive(Debug, Default)]
struct Outbox {
    state: Mutex<OutboxState>,
    /// A sample is pending, or the outbox closed.
    put: Notify,
    /// The stream took the pending sample, or went away.
    taken: Notify,
}

impl Outbox {
    /// Folds `sample` in; false if another one was still pending.
    fn offer(&self, sample: v1::PhoneSample) -> Result<bool> {
        let mut state = self.state.lock();
        if state.gone {
            return Err(Error::Closed);
        }
        let was_empty = state.pending.is_empty();
        if !was_empty {
            state.superseded += 1;
        }
        state.pending.push(sample);
        drop(state);
        self.put.notify_one();
        Ok(was_empty)
    }

    /// Puts `sample` once nothing is pending.
    async fn put_when_empty(&self, sample: v1::PhoneSample) -> Result<()> {
        let mut sample = Some(sample);
        loop {
            {
                let mut state = self.state.lock();
                if state.gone {
                    return Err(Error::Closed);
                }
                if state.pending.is_empty() {
                    state.pending.push(sample.take().expect("put once"));
                    drop(state);
                    self.put.notify_one();
                    return Ok(());
                }
            }
            // `notify_one` keeps a permit when nobody waits yet, so a take between the check and here wakes us.
            self.taken.notified().await;
        }
    }

    /// Waits for the next sample; `None` once closed and drained.
    async fn take(&self) -> Option<v1::PhoneSample> {
        loop {
            {
                let mut state = self.state.lock();
                if let Some(sample) = state.pending.take() {
                    drop(state);
                    self.taken.notify_one();
                    return Some(sample);
                }
                if state.closed {
                    return None;
                }
            }
            self.put.notified().await;
        }
    }

    fn close(&self) {
        self.state.lock().closed = true;
        self.put.notify_one();
    }

    fn is_closed(&self) -> bool {
        self.state.lock().closed
    }

    fn superseded(&self) -> u64 {
        self.state.lock().superseded
    }

    /// The request stream of one call: `first` (already taken), then what the outbox is given. With
    /// `last_call`, the outbox refuses samples once tonic drops the stream (the call ended); otherwise what is
    /// offered meanwhile waits for the next call.
    fn requests(
        self: &Arc<Self>,
        first: Option<v1::PhoneSample>,
        last_call: bool,
    ) -> impl tokio_stream::Stream<Item = v1::PhoneSample> + Send + 'static {
        let taker = OutboxTaker {
            outbox: Arc::clone(self),
            last_call,
        };
        futures_util::stream::unfold((first, taker), |(first, taker)| async move {
            let sample = match first {
                Some(sample) => sample,
                None => taker.outbox.take().await?,
            };
            Some((sample, (None, taker)))
        })
    }
}

/// A request stream's hold on the outbox: when tonic drops the stream (the call ended) and no call follows,
/// senders learn it.
struct OutboxTaker {
    outbox: Arc<Outbox>,
    last_call: bool,
}

impl Drop for OutboxTaker {
    fn drop(&mut self) {
        if self.last_call {
            self.outbox.state.lock().gone = true;
            self.outbox.taken.notify_one();
        }
    }
}

/// An open teleop session.
#[derive(Debug)]
pub struct TeleopSession {
    outbox: Arc<Outbox>,
    feedback: tonic::Streaming<v1::TeleopFeedback>,
    seq: u64,
}

impl TeleopSession {
    async fn open(mut client: TeleopClient<AuthChannel>, arm: &str, options: TeleopOptions) -> Result<Self> {
        let outbox = Arc::new(Outbox::default());
        let hello = v1::PhoneSample {
            seq: 0,
            arm: arm.to_owned(),
            client_name: options.client_name,
            take_over: options.take_over,
            ..v1::PhoneSample::default()
        };
        outbox.offer(hello)?;
        let feedback = client.stream(outbox.requests(None, true)).await?.into_inner();
        Ok(Self {
            outbox,
            feedback,
            seq: 0,
        })
    }

    /// Sends one sample (its `seq` is assigned here) without waiting. Returns false if the previous sample was
    /// still waiting for the network: the two are then folded into one (latest wins: the newest pose and seq
    /// go out, with the button events of both in order), so a burst never queues stale poses and never loses
    /// a button.
    pub fn send(&mut self, mut sample: v1::PhoneSample) -> Result<bool> {
        self.seq += 1;
        sample.seq = self.seq;
        self.outbox.offer(sample)
    }

    /// Sends one sample, waiting until the previous one went out instead of folding them (for scripted clients
    /// that need every sample to reach the server on its own).
    pub async fn send_wait(&mut self, mut sample: v1::PhoneSample) -> Result<u64> {
        self.seq += 1;
        sample.seq = self.seq;
        self.outbox.put_when_empty(sample).await?;
        Ok(self.seq)
    }

    /// Sends a pose with optional button events, waiting for room.
    pub async fn send_pose(
        &mut self,
        tracking_from_phone: v1::Pose,
        buttons: Vec<v1::ButtonEvent>,
        capture_time_ns: i64,
    ) -> Result<u64> {
        self.send_wait(v1::PhoneSample {
            tracking_from_phone: Some(tracking_from_phone),
            tracking: v1::TrackingState::Tracking as i32,
            buttons,
            capture_time_ns,
            ..v1::PhoneSample::default()
        })
        .await
    }

    /// Sends button events without a pose.
    pub async fn send_buttons(&mut self, buttons: Vec<v1::ButtonEvent>) -> Result<u64> {
        self.send_wait(v1::PhoneSample {
            buttons,
            ..v1::PhoneSample::default()
        })
        .await
    }

    /// Hands the arm back to the policy waiting for it (`ArmState::waiting_policy_id`); returns the sample's
    /// seq. Nothing moves: the arm holds until the policy's first chunk answering an observation taken after
    /// the hand-back. Without a waiting policy the feedback's `error` says so.
    pub async fn hand_back(&mut self) -> Result<u64> {
        self.send_buttons(vec![phone2act_proto::buttons::hand_back()])
            .await
    }

    /// The next feedback message; `Ok(None)` when the server ended the stream.
    pub async fn feedback(&mut self) -> Result<Option<v1::TeleopFeedback>> {
        Ok(self.feedback.message().await?)
    }

    /// Waits for the feedback that answers sample `seq` (or a later one).
    pub async fn feedback_for(&mut self, seq: u64) -> Result<v1::TeleopFeedback> {
        loop {
            match self.feedback.message().await? {
                Some(fb) if fb.echoed_seq >= seq => return Ok(fb),
                Some(_) => {}
                None => return Err(Error::Closed),
            }
        }
    }

    /// Samples folded locally into a newer one because the previous one was still in flight.
    pub fn superseded(&self) -> u64 {
        self.outbox.superseded()
    }
}

impl Drop for TeleopSession {
    /// Ends the request stream (after any pending sample went out), as dropping a sender would.
    fn drop(&mut self) {
        self.outbox.close();
    }
}

/// What a [`TeleopLink`] reports.
#[derive(Debug)]
pub enum TeleopEvent {
    /// The server accepted the stream.
    Open { arm: String },
    /// Feedback for one processed sample.
    Feedback {
        arm: String,
        feedback: Box<v1::TeleopFeedback>,
    },
    /// The stream broke for a reason that may pass (server restarting); retrying in `retry_in`.
    Retrying {
        arm: String,
        message: String,
        retry_in: Duration,
    },
    /// The server refused the session (unknown arm, arm taken, bad token); no retry.
    Refused {
        arm: String,
        code: Code,
        message: String,
    },
}

/// A teleop stream to one arm that outlives the server's restarts (see [`Client::teleop_link`]). Samples go
/// through the same latest-wins outbox as a [`TeleopSession`]'s; what is offered while no stream is open waits
/// (folded) for the next one. Every new stream is a new session on the server, which starts it disengaged:
/// a reconnect never resumes a motion. Dropping the link closes the stream.
#[derive(Debug)]
pub struct TeleopLink {
    arm: String,
    outbox: Arc<Outbox>,
    task: JoinHandle<()>,
}

impl TeleopLink {
    fn start(client: TeleopClient<AuthChannel>, arm: String, events: mpsc::Sender<TeleopEvent>) -> Self {
        let outbox = Arc::new(Outbox::default());
        let task = tokio::spawn(run_link(client, arm.clone(), Arc::clone(&outbox), events));
        Self { arm, outbox, task }
    }

    /// The arm this link drives.
    pub fn arm(&self) -> &str {
        &self.arm
    }

    /// Queues a sample as it is (its `seq` is the caller's), folding it into any unsent one; the arm name is
    /// filled in. Never waits.
    pub fn send(&self, mut sample: v1::PhoneSample) {
        sample.arm.clone_from(&self.arm);
        // Only a closed outbox refuses, and the link never closes it before it is dropped.
        let _ = self.outbox.offer(sample);
    }

    /// True once the link has given up (the server refused the session).
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Samples folded into a newer one before they went out.
    pub fn superseded(&self) -> u64 {
        self.outbox.superseded()
    }
}

impl Drop for TeleopLink {
    fn drop(&mut self) {
        self.outbox.close();
        // The request stream ends with the outbox; aborting as well makes sure a stream stuck waiting for
        // response headers does not outlive its sender.
        self.task.abort();
    }
}

/// Codes that retrying cannot change: the session is refused, not interrupted.
fn is_permanent(code: Code) -> bool {
    matches!(
        code,
        Code::NotFound
            | Code::AlreadyExists
            | Code::InvalidArgument
            | Code::PermissionDenied
            | Code::Unauthenticated
            | Code::FailedPrecondition
            | Code::Unimplemented
    )
}

async fn run_link(
    mut client: TeleopClient<AuthChannel>,
    arm: String,
    outbox: Arc<Outbox>,
    events: mpsc::Sender<TeleopEvent>,
) {
    const MIN_BACKOFF: Duration = Duration::from_millis(100);
    const MAX_BACKOFF: Duration = Duration::from_secs(2);
    let mut backoff = MIN_BACKOFF;
    loop {
        // Connect only when there is something to send, so an idle sender does not hold an arm.
        let Some(first) = outbox.take().await else { return };
        let status = match client.stream(outbox.requests(Some(first), false)).await {
            Ok(response) => {
                backoff = MIN_BACKOFF;
                let _ = events.send(TeleopEvent::Open { arm: arm.clone() }).await;
                let mut inbound = response.into_inner();
                loop {
                    match inbound.message().await {
                        Ok(Some(feedback)) => {
                            // Feedback is periodic: if the receiver reads slowly, dropping one is harmless.
                            let _ = events.try_send(TeleopEvent::Feedback {
                                arm: arm.clone(),
                                feedback: Box::new(feedback),
                            });
                        }
                        Ok(None) => break tonic::Status::unavailable("server ended the teleop stream"),
                        Err(status) => break status,
                    }
                }
            }
            Err(status) => status,
        };
        if is_permanent(status.code()) {
            tracing::info!(arm, code = ?status.code(), message = status.message(), "teleop session refused");
            let _ = events
                .send(TeleopEvent::Refused {
                    arm,
                    code: status.code(),
                    message: status.message().to_owned(),
                })
                .await;
            return;
        }
        if outbox.is_closed() {
            return;
        }
        tracing::warn!(arm, code = ?status.code(), message = status.message(), "teleop stream lost, retrying");
        let _ = events
            .send(TeleopEvent::Retrying {
                arm: arm.clone(),
                message: status.message().to_owned(),
                retry_in: backoff,
            })
            .await;
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(MAX_BACKOFF);
    }
}

#[cfg(test)]
// Values pass through untouched: exact equality is the property under test.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use phone2act_proto::buttons::clutch;
    use phone2act_proto::v1::{Pose, clutch_command};

    fn pose_sample(seq: u64, x: f64) -> v1::PhoneSample {
        v1::PhoneSample {
            seq,
            tracking_from_phone: Some(Pose::from_parts([x, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])),
            ..v1::PhoneSample::default()
        }
    }

    #[tokio::test]
    async fn latest_pose_wins_but_buttons_survive() {
        let outbox = Outbox::default();
        let mut first = pose_sample(1, 0.1);
        first.buttons.push(clutch(clutch_command::Kind::Engage));
        assert!(outbox.offer(first).unwrap());
        assert!(!outbox.offer(pose_sample(2, 0.2)).unwrap());
        let mut button_only = v1::PhoneSample {
            seq: 3,
            ..v1::PhoneSample::default()
        };
        button_only.buttons.push(clutch(clutch_command::Kind::Disengage));
        assert!(!outbox.offer(button_only).unwrap());
        let got = outbox.take().await.unwrap();
        assert_eq!(got.seq, 3);
        assert_eq!(got.tracking_from_phone.unwrap().position_m.unwrap().x, 0.2);
        assert_eq!(
            got.buttons,
            vec![
                clutch(clutch_command::Kind::Engage),
                clutch(clutch_command::Kind::Disengage)
            ]
        );
        assert_eq!(outbox.superseded(), 2);
        outbox.close();
        assert!(outbox.take().await.is_none());
    }

    #[tokio::test]
    async fn take_waits_for_an_offer_from_another_task() {
        let outbox = Arc::new(Outbox::default());
        let o2 = outbox.clone();
        let waiter = tokio::spawn(async move { o2.take().await.map(|s| s.seq) });
        // Not a timing bound: the waiter must still be waiting however long it ran, as nothing was offered.
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!waiter.is_finished());
        outbox.offer(pose_sample(7, 0.0)).unwrap();
        assert_eq!(waiter.await.unwrap(), Some(7));
    }

    #[tokio::test]
    async fn a_stream_that_ends_refuses_samples_only_when_no_call_follows() {
        use tokio_stream::StreamExt;
        let outbox = Arc::new(Outbox::default());
        drop(outbox.requests(Some(pose_sample(1, 0.0)), false));
        assert!(
            outbox.offer(pose_sample(2, 0.0)).unwrap(),
            "a reconnecting sender keeps offering"
        );
        let mut last = Box::pin(outbox.requests(None, true));
        assert_eq!(last.next().await.map(|s| s.seq), Some(2));
        drop(last);
        assert!(matches!(outbox.offer(pose_sample(3, 0.0)), Err(Error::Closed)));
    }
}
