//! `phone2act.v1.Teleop`: a phone session bound to one arm. Samples are processed latest-wins: every button
//! event is applied in order, but of the poses that queued up while the previous round ran only the newest
//! is planned, so a burst from the network never turns into a backlog of stale commands.

use crate::app::App;
use crate::services::convert::current_recording_status;
use crate::services::error::{RequestError, check_len};
use futures_util::FutureExt;
use phone2act_clock::monotonic_ns;
use phone2act_core::TeleopRound;
use phone2act_proto::convert_arm::{ButtonInput, arm_state_to_proto, button_from_proto, pose_from_proto};
use phone2act_proto::convert_episode::RecordAction;
use phone2act_proto::sample::tracking_lost;
use phone2act_proto::v1::teleop_server::Teleop;
use phone2act_proto::{PendingSample, v1};
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

/// Feedback is sent at least this often while the phone is idle.
const IDLE_FEEDBACK: Duration = Duration::from_millis(100);
/// A stream that has not named its arm by then is closed: an idle connection must not be held forever.
const FIRST_SAMPLE_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest `client_name` accepted (it is logged and shown to operators).
const MAX_CLIENT_NAME_BYTES: usize = 128;
/// Most samples drained in one round before planning the newest.
const MAX_DRAIN: usize = 256;

/// The Teleop service adapter.
#[derive(Debug, Clone)]
pub struct TeleopService {
    app: Arc<App>,
}

impl TeleopService {
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

type FeedbackStream = Pin<Box<dyn Stream<Item = Result<v1::TeleopFeedback, Status>> + Send>>;

#[tonic::async_trait]
impl Teleop for TeleopService {
    type StreamStream = FeedbackStream;

    async fn stream(
        &self,
        request: Request<Streaming<v1::PhoneSample>>,
    ) -> Result<Response<Self::StreamStream>, Status> {
        let mut inbound = request.into_inner();
        let first = tokio::time::timeout(FIRST_SAMPLE_TIMEOUT, inbound.message())
            .await
            .map_err(|_| RequestError::NoFirstSample {
                timeout_s: FIRST_SAMPLE_TIMEOUT.as_secs(),
            })??
            .ok_or(RequestError::NoHello("the stream ended before its first sample"))?;
        check_len("client_name", &first.client_name, MAX_CLIENT_NAME_BYTES)?;
        if first.arm.is_empty() {
            return Err(RequestError::NoHello("the first sample must name the arm (field `arm`)").into());
        }
        let arm = self.app.find_arm(&first.arm)?;
        let session = self.app.next_session_id();
        arm.bind_teleop(session, first.take_over)?;
        // Debug formatting escapes control characters: a client name cannot forge log lines.
        tracing::info!(arm = %arm.name, session, client = ?first.client_name, "teleop session bound");

        // Small bound: feedback is a status display, the newest message is what matters.
        let (tx, rx) = tokio::sync::mpsc::channel::<Result<v1::TeleopFeedback, Status>>(4);
        let app = Arc::clone(&self.app);
        let mut shutdown = app.shutdown_signal();
        tokio::spawn(async move {
            let mut superseded = 0u64;
            let mut last = (first.seq, first.capture_time_ns, monotonic_ns());
            let mut pending = Some(first);
            loop {
                let mut batch = Vec::new();
                if let Some(sample) = pending.take() {
                    batch.push(sample);
                } else {
                    tokio::select! {
                        msg = inbound.message() => match msg {
                            Ok(Some(sample)) => batch.push(sample),
                            Ok(None) => break,
                            Err(status) => {
                                tracing::debug!(%status, "teleop stream error");
                                break;
                            }
                        },
                        () = tokio::time::sleep(IDLE_FEEDBACK) => {
                            let fb = feedback(&app, &arm, last, String::new(), superseded);
                            if tx.try_send(Ok(fb)).is_err() && tx.is_closed() { break; }
                            continue;
                        }
                        () = crate::runtime::stopped(&mut shutdown) => break,
                    }
                }
                let receive_ns = monotonic_ns();
                // Take whatever else already arrived without waiting.
                let mut closed = false;
                while batch.len() < MAX_DRAIN {
                    match inbound.message().now_or_never() {
                        Some(Ok(Some(sample))) => batch.push(sample),
                        Some(Ok(None) | Err(_)) => {
                            closed = true;
                            break;
                        }
                        None => break,
                    }
                }
                let batch_len = batch.len() as u64;
                let (input, records, newest, dropped) = merge(batch);
                superseded += dropped;
                let outcome = match arm.teleop_input(session, input) {
                    Ok(o) => o,
                    Err(e) => {
                        let _ = tx.send(Err(e.into())).await;
                        break;
                    }
                };
                arm.stats()
                    .note_round(batch_len, outcome.command_time_ns.map(|t| t - receive_ns));
                let mut error = outcome.error;
                for record in records {
                    let done = RecordAction::try_from(&record)
                        .map_err(|e| e.to_string())
                        .and_then(|action| app.record_action(action).map_err(|e| e.to_string()));
                    if let Err(e) = done {
                        error = e;
                    }
                }
                last = (newest.0, newest.1, receive_ns);
                let fb = feedback(&app, &arm, last, error, superseded);
                if tx.try_send(Ok(fb)).is_err() && tx.is_closed() {
                    break;
                }
                if closed {
                    break;
                }
            }
            arm.unbind_teleop(session);
            tracing::info!(arm = %arm.name, session, "teleop session ended");
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }
}

/// Folds a batch of samples into one input with the wire's one latest-wins rule ([`PendingSample`]): every
/// button event in order, the newest pose. Returns the arm's input, the record events (for the recorder, in
/// order), the newest sample's (seq, capture time), and how many poses were superseded.
fn merge(batch: Vec<v1::PhoneSample>) -> (TeleopRound, Vec<v1::RecordCommand>, (u64, i64), u64) {
    let mut pending = PendingSample::default();
    let superseded = batch.into_iter().map(|s| u64::from(pending.push(s))).sum();
    let Some(sample) = pending.take() else {
        return (TeleopRound::default(), Vec::new(), (0, 0), 0);
    };
    let tracking_ok = !tracking_lost(sample.tracking);
    let mut input = TeleopRound {
        pose: sample
            .tracking_from_phone
            .as_ref()
            .map(|pose| pose_from_proto(pose).map_err(|e| e.to_string())),
        tracking_ok: tracking_ok && sample.tracking_from_phone.is_some(),
        buttons: Vec::with_capacity(sample.buttons.len()),
    };
    let mut records = Vec::new();
    for event in sample.buttons {
        match button_from_proto(event) {
            ButtonInput::Arm(button) => input.buttons.push(button),
            ButtonInput::Record(record) => records.push(record),
        }
    }
    (input, records, (sample.seq, sample.capture_time_ns), superseded)
}

fn feedback(
    app: &App,
    arm: &crate::arm::ArmController,
    last: (u64, i64, i64),
    error: String,
    superseded: u64,
) -> v1::TeleopFeedback {
    v1::TeleopFeedback {
        echoed_seq: last.0,
        echoed_capture_time_ns: last.1,
        server_receive_time_ns: last.2,
        arm_state: Some(arm_state_to_proto(&arm.snapshot())),
        recording: Some(current_recording_status(app)),
        error,
        superseded_samples: superseded,
        server_send_time_ns: monotonic_ns(),
    }
}
