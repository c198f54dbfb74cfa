//! `phone2act.v1.Policy`: observations out, action chunks in. The adapter validates and converts; the session
//! rules (anchoring, claiming, scheduling) live in [`crate::policy_session`]. Chunks go through the arm
//! controller's chunk executor and the same safety gate and bridge as teleop.

use crate::arm::RevocationSink;
use crate::policy_session::{ChunkRequest, FrameEncoding, PolicySession, PolicySessions, SessionRequest};
use crate::services::convert::observation;
use crate::services::error::{RequestError, check_len};
use phone2act_proto::convert_policy::{action_mode, requested_encoding};
use phone2act_proto::v1;
use phone2act_proto::v1::policy_server::Policy;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

/// Highest observation rate a session may ask for.
const MAX_OBSERVATION_RATE_HZ: f64 = 200.0;
/// Bounds of `silence_timeout_s`: shorter than a control tick is meaningless; longer than an hour leaves a
/// hung policy in control of an arm for longer than anyone watches it. (Replaying a long episode asks for its
/// duration plus a margin.)
const MIN_SILENCE_TIMEOUT_S: f64 = 0.05;
const MAX_SILENCE_TIMEOUT_S: f64 = 3600.0;
/// Longest `policy_name` accepted (it is logged and shown to operators).
const MAX_POLICY_NAME_BYTES: usize = 128;
/// JPEG quality when a request leaves it unset.
const DEFAULT_JPEG_QUALITY: u8 = 85;

/// The Policy service adapter.
#[derive(Debug, Clone)]
pub struct PolicyService {
    sessions: Arc<PolicySessions>,
}

impl PolicyService {
    pub fn new(app: Arc<crate::app::App>) -> Self {
        Self {
            sessions: Arc::new(PolicySessions::new(app)),
        }
    }
}

type EventStream = Pin<Box<dyn Stream<Item = Result<v1::PolicyEvent, Status>> + Send>>;

/// Checks a hello's bounds and turns it into a session request.
fn session_request(hello: v1::PolicyHello) -> Result<SessionRequest, RequestError> {
    if !hello.observation_rate_hz.is_finite()
        || !(0.0..=MAX_OBSERVATION_RATE_HZ).contains(&hello.observation_rate_hz)
    {
        return Err(RequestError::OutOfRange {
            field: "observation_rate_hz",
            range: format!("in 0..={MAX_OBSERVATION_RATE_HZ}"),
            value: hello.observation_rate_hz,
        });
    }
    check_len("policy_name", &hello.policy_name, MAX_POLICY_NAME_BYTES)?;
    // 0 is proto3's "unset": the documented default. Anything else outside the range is refused: a
    // negative or NaN timeout means nothing, and a huge one lets a hung policy keep an arm forever.
    let silence_timeout_s = if hello.silence_timeout_s == 0.0 {
        1.0
    } else if (MIN_SILENCE_TIMEOUT_S..=MAX_SILENCE_TIMEOUT_S).contains(&hello.silence_timeout_s) {
        hello.silence_timeout_s
    } else {
        return Err(RequestError::OutOfRange {
            field: "silence_timeout_s",
            range: format!("in {MIN_SILENCE_TIMEOUT_S}..={MAX_SILENCE_TIMEOUT_S} s (0 for the 1 s default)"),
            value: hello.silence_timeout_s,
        });
    };
    Ok(SessionRequest {
        arms: hello.arms,
        cameras: hello.cameras,
        encoding: frame_encoding(hello.image_encoding, hello.jpeg_quality),
        name: hello.policy_name,
        silence_timeout_s,
        request_control: hello.request_control,
    })
}

/// The frames a request asks for: unset encoding means JPEG, unset quality the default.
fn frame_encoding(encoding: i32, jpeg_quality: u32) -> FrameEncoding {
    match requested_encoding(encoding) {
        v1::ImageEncoding::None => FrameEncoding::None,
        v1::ImageEncoding::Rgb8 => FrameEncoding::Rgb8,
        v1::ImageEncoding::Jpeg | v1::ImageEncoding::Unspecified => FrameEncoding::Jpeg {
            quality: if jpeg_quality == 0 {
                DEFAULT_JPEG_QUALITY
            } else {
                u8::try_from(jpeg_quality.min(100)).unwrap_or(100)
            },
        },
    }
}

/// Converts and schedules one chunk; the answer is the event the policy gets.
fn push(
    sessions: &PolicySessions,
    session: &PolicySession,
    chunk: &v1::ActionChunk,
) -> Result<v1::ChunkAccepted, Status> {
    let mode = action_mode(chunk.mode).map_err(|e| crate::services::error::wire(&e))?;
    let steps: Vec<Vec<f64>> = chunk.steps.iter().map(|s| s.values.clone()).collect();
    let report = sessions.push_chunk(
        session,
        &ChunkRequest {
            arm: &chunk.arm,
            observation_id: chunk.observation_id,
            mode,
            step_period_s: chunk.step_period_s,
            steps: &steps,
            keep_steps: chunk.keep_steps as usize,
        },
    )?;
    Ok(v1::ChunkAccepted {
        arm: chunk.arm.clone(),
        observation_id: chunk.observation_id,
        steps_scheduled: report.scheduled as u32,
        steps_skipped: report.skipped as u32,
    })
}

/// How many events other than observations may wait for a session that does not read its stream: chunk
/// verdicts, take-overs, hand-backs, revocations and loading answers, which a policy must not miss. They come a
/// few a second at most, so a session that falls this far behind has stopped reading for many seconds.
const EVENT_QUEUE: usize = 64;

/// The session's events, shared with the arm controllers (revocations, take-overs, hand-backs). Observations
/// are latest-only: a policy that is busy inferring gets the newest one when it reads again, not a backlog of
/// stale ones. Every other event is queued in order, so falling behind on observations never costs a
/// `ControlPaused` or a `ControlRevoked`.
#[derive(Debug, Clone)]
struct Events {
    queue: mpsc::Sender<v1::PolicyEvent>,
    observation: Arc<ObservationSlot>,
}

/// The newest observation not yet forwarded. Taken out by the forwarder, not copied: with images it is large.
#[derive(Debug, Default)]
struct ObservationSlot {
    newest: parking_lot::Mutex<Option<v1::Observation>>,
    filled: tokio::sync::Notify,
}

impl Events {
    fn notify(&self, event: v1::policy_event::Event) {
        match event {
            v1::policy_event::Event::Observation(obs) => {
                *self.observation.newest.lock() = Some(obs);
                self.observation.filled.notify_one();
            }
            other => {
                if self.queue.try_send(other.into()).is_err() {
                    tracing::warn!(
                        "a policy session has not read its stream for a long time: an event was dropped"
                    );
                }
            }
        }
    }
}

/// Forwards a session's events to its stream: queued events first, in order, then the newest observation.
/// It ends when every holder of the session's [`Events`] has let go (the queue closes) or the stream is gone.
async fn forward_events(
    mut queue: mpsc::Receiver<v1::PolicyEvent>,
    observation: Arc<ObservationSlot>,
    out: mpsc::Sender<Result<v1::PolicyEvent, Status>>,
) {
    loop {
        let event = tokio::select! {
            biased;
            queued = queue.recv() => match queued {
                Some(event) => event,
                None => break,
            },
            () = observation.filled.notified() => {
                // A permit left by an observation already forwarded finds the slot empty.
                match observation.newest.lock().take() {
                    Some(obs) => v1::policy_event::Event::Observation(obs).into(),
                    None => continue,
                }
            }
        };
        if out.send(Ok(event)).await.is_err() {
            break;
        }
    }
}

/// A session hears that it lost an arm on its event channel. If the queue is full the session is stalled
/// anyway and will see the closed ownership on its next chunk.
impl RevocationSink for Events {
    fn revoked(&self, arm: &str, reason: &str) {
        self.notify(v1::policy_event::Event::Revoked(v1::ControlRevoked {
            arm: arm.to_owned(),
            reason: reason.to_owned(),
        }));
    }

    fn paused(&self, arm: &str, reason: &str) {
        self.notify(v1::policy_event::Event::Paused(v1::ControlPaused {
            arm: arm.to_owned(),
            reason: reason.to_owned(),
        }));
    }

    fn resumed(&self, arm: &str) {
        self.notify(v1::policy_event::Event::Resumed(v1::ControlResumed {
            arm: arm.to_owned(),
        }));
    }
}

fn send_observation(sessions: &PolicySessions, session: &PolicySession, events: &Events) {
    match sessions.observe_for(session) {
        Ok(o) => events.notify(v1::policy_event::Event::Observation(observation(
            sessions.app(),
            o,
        ))),
        Err(e) => tracing::debug!(error = %e, "observation skipped"),
    }
}

#[tonic::async_trait]
impl Policy for PolicyService {
    type SessionStream = EventStream;

    async fn session(
        &self,
        request: Request<Streaming<v1::PolicyRequest>>,
    ) -> Result<Response<Self::SessionStream>, Status> {
        let mut inbound = request.into_inner();
        let hello = match inbound.message().await? {
            Some(v1::PolicyRequest {
                request: Some(v1::policy_request::Request::Hello(h)),
            }) => h,
            Some(_) => {
                return Err(RequestError::NoHello(
                    "the first message of a policy session must be a PolicyHello",
                )
                .into());
            }
            None => return Err(RequestError::NoHello("the stream ended before its PolicyHello").into()),
        };
        let rate_hz = hello.observation_rate_hz;
        let request = session_request(hello)?;
        let control = request.request_control;
        let (tx, rx) = mpsc::channel::<v1::PolicyEvent>(EVENT_QUEUE);
        let observation = Arc::new(ObservationSlot::default());
        let sessions = Arc::clone(&self.sessions);
        let events = Events {
            queue: tx.clone(),
            observation: Arc::clone(&observation),
        };
        let session = sessions.open(request, Arc::new(events.clone()))?;
        let app = sessions.app();
        let ready = v1::SessionReady {
            session_id: session.capability(),
            arms: session
                .arms()
                .iter()
                .filter_map(|n| app.arm(n))
                .map(|arm| v1::ArmObservation {
                    arm: arm.name.clone(),
                    state_names: arm.layout.state_names(),
                    action_names: arm.layout.action_names(arm.action_mode),
                    ..v1::ArmObservation::default()
                })
                .collect(),
        };
        if tx.try_send(v1::policy_event::Event::Ready(ready).into()).is_err() {
            sessions.close(&session);
            return Err(RequestError::Internal("event queue".to_owned()).into());
        }
        if control {
            events.notify(v1::policy_event::Event::Granted(v1::ControlGranted {
                arms: session.arms().to_vec(),
            }));
        }
        // Debug formatting escapes control characters: a policy name cannot forge log lines.
        tracing::info!(session = session.id(), policy = ?session.name(), arms = ?session.arms(), control, "policy session opened");

        // Two slots: what waits for a lagging reader waits in `forward_events`' queue and observation slot, where
        // an observation is replaced by a newer one, not here.
        let (out_tx, out_rx) = mpsc::channel::<Result<v1::PolicyEvent, Status>>(2);
        tokio::spawn(forward_events(rx, observation, out_tx.clone()));
        let mut shutdown = app.shutdown_signal();
        tokio::spawn(async move {
            let mut ticker = tokio::time::interval(Duration::from_secs_f64(if rate_hz > 0.0 {
                1.0 / rate_hz
            } else {
                3600.0
            }));
            ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            loop {
                tokio::select! {
                    _ = ticker.tick(), if rate_hz > 0.0 => send_observation(&sessions, &session, &events),
                    msg = inbound.message() => match msg {
                        Ok(Some(v1::PolicyRequest { request: Some(request) })) => match request {
                            v1::policy_request::Request::Chunk(chunk) => {
                                events.notify(match push(&sessions, &session, &chunk) {
                                    Ok(accepted) => v1::policy_event::Event::Accepted(accepted),
                                    Err(status) => v1::policy_event::Event::Rejected(v1::ChunkRejected {
                                        arm: chunk.arm.clone(),
                                        observation_id: chunk.observation_id,
                                        reason: status.message().to_owned(),
                                    }),
                                });
                            }
                            v1::policy_request::Request::Observe(_) => send_observation(&sessions, &session, &events),
                            v1::policy_request::Request::Release(_) => session.release(sessions.app(), "released"),
                            v1::policy_request::Request::Loading(_) => {
                                let answer = match sessions.loading(&session) {
                                    Ok((arms, remaining_s)) => v1::LoadingAccepted {
                                        arms,
                                        remaining_s,
                                        error: String::new(),
                                    },
                                    Err(e) => v1::LoadingAccepted {
                                        error: e.to_string(),
                                        ..v1::LoadingAccepted::default()
                                    },
                                };
                                events.notify(v1::policy_event::Event::Loading(answer));
                            }
                            v1::policy_request::Request::Hello(_) => {
                                let _ = out_tx.send(Err(RequestError::HelloTwice("PolicyHello").into())).await;
                                break;
                            }
                        },
                        Ok(Some(_)) => {}
                        Ok(None) => break,
                        // An undecodable or oversized message (a 100,000-step chunk): the session ends with that
                        // status, not with OK, so the policy knows it lost control.
                        Err(status) => {
                            tracing::warn!(session = session.id(), %status, "policy session stream refused a message");
                            let _ = out_tx.send(Err(status)).await;
                            break;
                        }
                    },
                    () = crate::runtime::stopped(&mut shutdown) => break,
                }
            }
            sessions.close(&session);
            tracing::info!(session = session.id(), "policy session closed");
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(out_rx),
        )))
    }

    async fn get_observation(
        &self,
        request: Request<v1::GetObservationRequest>,
    ) -> Result<Response<v1::Observation>, Status> {
        let req = request.into_inner();
        let arms = if req.arms.is_empty() {
            self.sessions.app().arm_names()
        } else {
            req.arms
        };
        let sessions = Arc::clone(&self.sessions);
        let encoding = frame_encoding(req.image_encoding, 0);
        // JPEG-encoding camera frames takes milliseconds each (far more in a debug build): off the async
        // workers that carry the teleop streams, so a camera view polling this never delays control.
        let observed = tokio::task::spawn_blocking(move || sessions.observe(&arms, &req.cameras, encoding))
            .await
            .map_err(|e| RequestError::Internal(format!("observation failed: {e}")))??;
        Ok(Response::new(observation(self.sessions.app(), observed)))
    }

    async fn push_chunk(
        &self,
        request: Request<v1::PushChunkRequest>,
    ) -> Result<Response<v1::ChunkAccepted>, Status> {
        let req = request.into_inner();
        let session = self.sessions.find(&req.session_id)?;
        let chunk = req.chunk.ok_or(RequestError::Missing("chunk"))?;
        Ok(Response::new(push(&self.sessions, &session, &chunk)?))
    }
}
