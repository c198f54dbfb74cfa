//! One phone ↔ one arm: a `Teleop.Stream` fed from a depth-1 slot (latest wins) and kept alive across
//! server restarts.
//!
//! The slot is what keeps stale poses from queueing: the WebSocket side overwrites the pending sample, the
//! gRPC request stream takes it only when HTTP/2 flow control lets it send. Button events are the exception:
//! they are carried over into the newer sample, because a lost "stop recording" is worse than a late one.

use crate::upstream::Upstream;
use parking_lot::Mutex;
use phone2act_proto::PendingSample;
use phone2act_proto::v1::{PhoneSample, TeleopFeedback};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::sync::{Notify, mpsc};
use tokio::task::JoinHandle;
use tonic::Code;

/// What a session reports to its WebSocket connection.
#[derive(Debug)]
pub enum SessionEvent {
    /// The server accepted the stream.
    Open { arm: String },
    /// Feedback for one processed sample.
    Feedback {
        arm: String,
        feedback: Box<TeleopFeedback>,
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

#[derive(Debug, Default)]
struct SlotState {
    pending: PendingSample,
    closed: bool,
}

/// The depth-1 latest-wins slot between a WebSocket reader and a gRPC request stream.
#[derive(Debug, Default)]
pub struct Slot {
    state: Mutex<SlotState>,
    notify: Notify,
    superseded: AtomicU64,
}

impl Slot {
    /// Offers a sample. A pending one is folded into it ([`PendingSample::push`]: the newest pose wins, every
    /// button event survives in order).
    pub fn put(&self, sample: PhoneSample) {
        let mut state = self.state.lock();
        if !state.pending.is_empty() {
            self.superseded.fetch_add(1, Ordering::Relaxed);
        }
        state.pending.push(sample);
        drop(state);
        self.notify.notify_one();
    }

    /// Waits for the next sample; `None` once closed and drained.
    pub async fn take(&self) -> Option<PhoneSample> {
        loop {
            {
                let mut state = self.state.lock();
                if let Some(sample) = state.pending.take() {
                    return Some(sample);
                }
                if state.closed {
                    return None;
                }
            }
            self.notify.notified().await;
        }
    }

    /// Ends the request stream after any pending sample has been taken.
    pub fn close(&self) {
        self.state.lock().closed = true;
        self.notify.notify_one();
    }

    /// Samples replaced before they were sent.
    pub fn superseded(&self) -> u64 {
        self.superseded.load(Ordering::Relaxed)
    }
}

/// A running teleop session for one arm. Dropping it closes the gRPC stream.
#[derive(Debug)]
pub struct Session {
    pub arm: String,
    slot: Arc<Slot>,
    task: JoinHandle<()>,
}

impl Session {
    /// Starts the session task; it connects on the first sample.
    pub fn start(upstream: Upstream, arm: String, events: mpsc::Sender<SessionEvent>) -> Self {
        let slot = Arc::new(Slot::default());
        let task = tokio::spawn(run(upstream, arm.clone(), slot.clone(), events));
        Self { arm, slot, task }
    }

    /// Queues a sample, superseding any unsent one. The arm name is filled in.
    pub fn send(&self, mut sample: PhoneSample) {
        sample.arm.clone_from(&self.arm);
        self.slot.put(sample);
    }

    /// True once the task has ended (refused by the server).
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Samples superseded in the gateway's slot.
    pub fn superseded(&self) -> u64 {
        self.slot.superseded()
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        self.slot.close();
        // The request stream ends with the slot; aborting as well makes sure a stream stuck waiting for
        // response headers does not outlive the phone.
        self.task.abort();
    }
}

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

async fn run(upstream: Upstream, arm: String, slot: Arc<Slot>, events: mpsc::Sender<SessionEvent>) {
    const MIN_BACKOFF: Duration = Duration::from_millis(100);
    const MAX_BACKOFF: Duration = Duration::from_secs(2);
    let mut backoff = MIN_BACKOFF;
    loop {
        // Connect only when there is something to send, so an idle socket does not hold an arm.
        let Some(first) = slot.take().await else { return };
        let requests =
            futures_util::stream::unfold((Some(first), slot.clone()), |(first, slot)| async move {
                match first {
                    Some(sample) => Some((sample, (None, slot))),
                    None => slot.take().await.map(|s| (s, (None, slot))),
                }
            });
        let result = upstream.teleop().stream(requests).await;
        let status = match result {
            Ok(response) => {
                backoff = MIN_BACKOFF;
                let _ = events.send(SessionEvent::Open { arm: arm.clone() }).await;
                let mut inbound = response.into_inner();
                loop {
                    match inbound.message().await {
                        Ok(Some(feedback)) => {
                            // Feedback is periodic: if the phone reads slowly, dropping one is harmless.
                            let _ = events.try_send(SessionEvent::Feedback {
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
                .send(SessionEvent::Refused {
                    arm,
                    code: status.code(),
                    message: status.message().to_owned(),
                })
                .await;
            return;
        }
        if slot.state.lock().closed {
            return;
        }
        tracing::warn!(arm, code = ?status.code(), message = status.message(), "teleop stream lost, retrying");
        let _ = events
            .send(SessionEvent::Retrying {
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

    fn pose_sample(seq: u64, x: f64) -> PhoneSample {
        PhoneSample {
            seq,
            tracking_from_phone: Some(Pose::from_parts([x, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])),
            ..PhoneSample::default()
        }
    }

    #[tokio::test]
    async fn latest_pose_wins_but_buttons_survive() {
        let slot = Slot::default();
        let mut first = pose_sample(1, 0.1);
        first.buttons.push(clutch(clutch_command::Kind::Engage));
        slot.put(first);
        slot.put(pose_sample(2, 0.2));
        let mut button_only = PhoneSample {
            seq: 3,
            ..PhoneSample::default()
        };
        button_only.buttons.push(clutch(clutch_command::Kind::Disengage));
        slot.put(button_only);
        let got = slot.take().await.unwrap();
        assert_eq!(got.seq, 3);
        assert_eq!(got.tracking_from_phone.unwrap().position_m.unwrap().x, 0.2);
        assert_eq!(
            got.buttons,
            vec![
                clutch(clutch_command::Kind::Engage),
                clutch(clutch_command::Kind::Disengage)
            ]
        );
        assert_eq!(slot.superseded(), 2);
        slot.close();
        assert!(slot.take().await.is_none());
    }

    #[tokio::test]
    async fn take_waits_for_a_put_from_another_task() {
        let slot = Arc::new(Slot::default());
        let s2 = slot.clone();
        let waiter = tokio::spawn(async move { s2.take().await.map(|s| s.seq) });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!waiter.is_finished());
        slot.put(pose_sample(7, 0.0));
        assert_eq!(waiter.await.unwrap(), Some(7));
    }
}
