//! `phone2act.v1.Policy`: observations out, action chunks in. Chunks go through the arm controller's chunk
//! executor and the same safety gate and bridge as teleop.

use crate::app::App;
use crate::arm::{now_s, pose_to_proto};
use nalgebra::Isometry3;
use phone2act_clock::monotonic_ns;
use phone2act_core::ActionMode;
use phone2act_proto::v1;
use phone2act_proto::v1::policy_server::Policy;
use std::collections::VecDeque;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

/// Observations a session remembers for anchoring chunks (at 50 Hz, about 2.5 s).
const OBSERVATION_MEMORY: usize = 128;
/// Highest observation rate a session may ask for.
const MAX_OBSERVATION_RATE_HZ: f64 = 200.0;
/// Bounds of `silence_timeout_s`: shorter than a control tick is meaningless; longer than an hour leaves a
/// hung policy in control of an arm for longer than anyone watches it. (Replaying a long episode asks for its
/// duration plus a margin.)
const MIN_SILENCE_TIMEOUT_S: f64 = 0.05;
const MAX_SILENCE_TIMEOUT_S: f64 = 3600.0;
/// Longest `policy_name` accepted (it is logged and shown to operators).
const MAX_POLICY_NAME_BYTES: usize = 128;

/// What a chunk needs from the observation it answers.
#[derive(Debug, Clone)]
struct ObservationAnchor {
    id: u64,
    time_s: f64,
    poses: Vec<(String, Isometry3<f64>)>,
}

/// One open policy session.
#[derive(Debug)]
pub struct PolicySessionState {
    pub id: u64,
    pub name: String,
    arms: Vec<String>,
    cameras: Vec<String>,
    encoding: v1::ImageEncoding,
    jpeg_quality: u8,
    events: mpsc::Sender<v1::PolicyEvent>,
    anchors: Mutex<VecDeque<ObservationAnchor>>,
    /// 128 random bits in `SessionReady.session_id`: `PushChunk` must name them, so a session id is a
    /// capability that only the session's own client holds, not a small integer anyone can guess.
    secret: String,
}

/// `"<id>.<32 hex digits>"`: the sequential id keeps logs readable, the random part makes it unguessable.
fn session_capability(id: u64, secret: &str) -> String {
    format!("{id}.{secret}")
}

fn random_secret() -> Result<String, Status> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)
        .map_err(|e| Status::internal(format!("no randomness for a session id: {e}")))?;
    Ok(format!("{:032x}", u128::from_le_bytes(bytes)))
}

/// Compares in time independent of where the first difference is, so timing does not reveal a prefix.
fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The Policy service adapter.
#[derive(Debug, Clone)]
pub struct PolicyService {
    app: Arc<App>,
}

impl PolicyService {
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

type EventStream = Pin<Box<dyn Stream<Item = Result<v1::PolicyEvent, Status>> + Send>>;

fn event(e: v1::policy_event::Event) -> v1::PolicyEvent {
    v1::PolicyEvent { event: Some(e) }
}

impl App {
    /// Builds an observation of `arms` with frames of `cameras` and remembers it for `session`.
    fn observe(
        &self,
        arms: &[String],
        cameras: &[String],
        encoding: v1::ImageEncoding,
        jpeg_quality: u8,
    ) -> Result<(v1::Observation, ObservationAnchor), Status> {
        let id = self.next_observation_id();
        let timestamp_ns = monotonic_ns();
        let mut out = Vec::with_capacity(arms.len());
        let mut poses = Vec::with_capacity(arms.len());
        for name in arms {
            let arm = self
                .arm(name)
                .ok_or_else(|| Status::not_found(format!("unknown arm {name:?}")))?;
            let snapshot = arm.snapshot();
            let Some(sample) = arm.state_and_action() else {
                return Err(Status::unavailable(format!(
                    "arm {name:?} has no robot feedback yet"
                )));
            };
            let (state, pose) = (sample.state, sample.robot_from_ee);
            poses.push((name.clone(), pose));
            out.push(v1::ArmObservation {
                arm: name.clone(),
                state,
                state_names: arm.layout.state_names(),
                action_names: arm.layout.action_names(arm.action_mode),
                robot_from_ee: Some(pose_to_proto(&pose)),
                owner: snapshot.owner,
            });
        }
        let mut frames = Vec::new();
        if encoding != v1::ImageEncoding::None {
            for cam in &self.cameras {
                if !cameras.is_empty() && !cameras.contains(&cam.config.name) {
                    continue;
                }
                if let Some(frame) = cam.slot.latest() {
                    let data = if encoding == v1::ImageEncoding::Jpeg {
                        phone2act_recorder::jpeg::encode_jpeg(
                            &frame.rgb,
                            frame.width,
                            frame.height,
                            jpeg_quality,
                        )
                        .map_err(|e| Status::internal(format!("camera {}: {e}", cam.config.name)))?
                    } else {
                        frame.rgb.as_ref().clone()
                    };
                    frames.push(v1::CameraFrame {
                        camera: cam.config.name.clone(),
                        width: frame.width,
                        height: frame.height,
                        encoding: if encoding == v1::ImageEncoding::Jpeg {
                            v1::ImageEncoding::Jpeg as i32
                        } else {
                            v1::ImageEncoding::Rgb8 as i32
                        },
                        data,
                        capture_time_ns: frame.capture_time_ns,
                        frame_seq: frame.seq,
                    });
                }
            }
        }
        let observation = v1::Observation {
            observation_id: id,
            timestamp_ns,
            arms: out,
            frames,
            task: self.current_task(),
        };
        Ok((
            observation,
            ObservationAnchor {
                id,
                time_s: timestamp_ns as f64 * 1e-9,
                poses,
            },
        ))
    }

    /// Schedules `chunk` for `session`.
    pub(crate) fn push_chunk(
        &self,
        session: &PolicySessionState,
        chunk: &v1::ActionChunk,
    ) -> Result<v1::ChunkAccepted, Status> {
        let arm = self.arm(&chunk.arm).ok_or_else(|| {
            Status::not_found(format!(
                "unknown arm {:?}; configured arms: {}",
                chunk.arm,
                self.arm_names().join(", ")
            ))
        })?;
        if !session.arms.contains(&chunk.arm) {
            return Err(Status::failed_precondition(format!(
                "this session did not open arm {:?}",
                chunk.arm
            )));
        }
        if chunk.steps.is_empty() {
            return Err(Status::invalid_argument("chunk has no steps"));
        }
        let mode = match v1::ActionMode::try_from(chunk.mode) {
            Ok(v1::ActionMode::Unspecified | v1::ActionMode::DeltaEe) => ActionMode::Relative,
            Ok(v1::ActionMode::AbsoluteEe) => ActionMode::Absolute,
            Ok(v1::ActionMode::Joint) => ActionMode::Joint,
            Err(_) => {
                return Err(Status::invalid_argument(format!(
                    "unknown action mode {}",
                    chunk.mode
                )));
            }
        };
        let width = arm.layout.action_names(mode).len();
        for (k, step) in chunk.steps.iter().enumerate() {
            if step.values.len() != width {
                return Err(Status::invalid_argument(format!(
                    "step {k} has {} values; arm {:?} takes {width} ({})",
                    step.values.len(),
                    chunk.arm,
                    arm.layout.action_names(mode).join(", ")
                )));
            }
            if let Some(i) = step.values.iter().position(|v| !v.is_finite()) {
                return Err(Status::invalid_argument(format!(
                    "step {k} value {i} is not finite"
                )));
            }
        }
        if !chunk.step_period_s.is_finite() || chunk.step_period_s <= 0.0 {
            return Err(Status::invalid_argument(format!(
                "step_period_s must be > 0, got {}",
                chunk.step_period_s
            )));
        }
        let (anchor_s, reference) = if chunk.observation_id == 0 {
            let pose = arm
                .state_and_action()
                .map(|sample| sample.robot_from_ee)
                .ok_or_else(|| {
                    Status::unavailable(format!("arm {:?} has no robot feedback yet", chunk.arm))
                })?;
            (now_s(), pose)
        } else {
            let anchors = session.anchors.lock().unwrap_or_else(PoisonError::into_inner);
            let anchor = anchors.iter().find(|a| a.id == chunk.observation_id).ok_or_else(|| {
                Status::invalid_argument(format!(
                    "observation {} is unknown or too old (this session remembers its last {OBSERVATION_MEMORY})",
                    chunk.observation_id
                ))
            })?;
            let pose = anchor
                .poses
                .iter()
                .find(|(name, _)| name == &chunk.arm)
                .map(|(_, p)| *p)
                .ok_or_else(|| {
                    Status::invalid_argument(format!("observation {} has no arm {:?}", anchor.id, chunk.arm))
                })?;
            (anchor.time_s, pose)
        };
        let actions: Vec<Vec<f64>> = chunk.steps.iter().map(|s| s.values.clone()).collect();
        let report = arm.push_chunk(
            session.id,
            &actions,
            chunk.step_period_s,
            anchor_s,
            reference,
            mode,
        )?;
        Ok(v1::ChunkAccepted {
            arm: chunk.arm.clone(),
            observation_id: chunk.observation_id,
            steps_scheduled: report.scheduled as u32,
            steps_skipped: report.skipped as u32,
        })
    }
}

impl PolicySessionState {
    fn remember(&self, anchor: ObservationAnchor) {
        let mut anchors = self.anchors.lock().unwrap_or_else(PoisonError::into_inner);
        if anchors.len() == OBSERVATION_MEMORY {
            anchors.pop_front();
        }
        anchors.push_back(anchor);
    }
}

fn send_observation(app: &App, session: &PolicySessionState) {
    match app.observe(
        &session.arms,
        &session.cameras,
        session.encoding,
        session.jpeg_quality,
    ) {
        Ok((obs, anchor)) => {
            session.remember(anchor);
            // Latest wins: a policy that is busy inferring misses an observation rather than queueing it.
            let _ = session
                .events
                .try_send(event(v1::policy_event::Event::Observation(obs)));
        }
        Err(status) => tracing::debug!(%status, "observation skipped"),
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
                return Err(Status::invalid_argument(
                    "the first message of a policy session must be a PolicyHello",
                ));
            }
            None => {
                return Err(Status::invalid_argument(
                    "the stream ended before its PolicyHello",
                ));
            }
        };
        let app = Arc::clone(&self.app);
        let arms = if hello.arms.is_empty() {
            app.arm_names()
        } else {
            hello.arms.clone()
        };
        for name in &arms {
            if app.arm(name).is_none() {
                return Err(Status::not_found(format!(
                    "unknown arm {name:?}; configured arms: {}",
                    app.arm_names().join(", ")
                )));
            }
        }
        for cam in &hello.cameras {
            if !app.cameras.iter().any(|c| &c.config.name == cam) {
                return Err(Status::not_found(format!("unknown camera {cam:?}")));
            }
        }
        if !hello.observation_rate_hz.is_finite()
            || !(0.0..=MAX_OBSERVATION_RATE_HZ).contains(&hello.observation_rate_hz)
        {
            return Err(Status::invalid_argument(format!(
                "observation_rate_hz must be in 0..={MAX_OBSERVATION_RATE_HZ}, got {}",
                hello.observation_rate_hz
            )));
        }
        if hello.policy_name.len() > MAX_POLICY_NAME_BYTES {
            return Err(Status::invalid_argument(format!(
                "policy_name is {} bytes, the limit is {MAX_POLICY_NAME_BYTES}",
                hello.policy_name.len()
            )));
        }
        // 0 is proto3's "unset": the documented default. Anything else outside the range is refused: a
        // negative or NaN timeout means nothing, and a huge one lets a hung policy keep an arm forever.
        let silence_timeout_s = if hello.silence_timeout_s == 0.0 {
            1.0
        } else if (MIN_SILENCE_TIMEOUT_S..=MAX_SILENCE_TIMEOUT_S).contains(&hello.silence_timeout_s) {
            hello.silence_timeout_s
        } else {
            return Err(Status::invalid_argument(format!(
                "silence_timeout_s must be in {MIN_SILENCE_TIMEOUT_S}..={MAX_SILENCE_TIMEOUT_S} s (0 for the 1 s default), got {}",
                hello.silence_timeout_s
            )));
        };
        let encoding =
            v1::ImageEncoding::try_from(hello.image_encoding).unwrap_or(v1::ImageEncoding::Unspecified);
        let encoding = if encoding == v1::ImageEncoding::Unspecified {
            v1::ImageEncoding::Jpeg
        } else {
            encoding
        };
        let (tx, rx) = mpsc::channel::<v1::PolicyEvent>(16);
        let id = app.next_session_id();
        let name = if hello.policy_name.is_empty() {
            format!("policy-{id}")
        } else {
            hello.policy_name.clone()
        };
        let session = Arc::new(PolicySessionState {
            id,
            name: name.clone(),
            arms: arms.clone(),
            cameras: hello.cameras.clone(),
            encoding,
            jpeg_quality: if hello.jpeg_quality == 0 {
                85
            } else {
                hello.jpeg_quality.min(100) as u8
            },
            events: tx.clone(),
            anchors: Mutex::new(VecDeque::with_capacity(OBSERVATION_MEMORY)),
            secret: random_secret()?,
        });
        if hello.request_control {
            let mut claimed = Vec::new();
            for name_ in &arms {
                let arm = app.arm(name_).expect("checked above");
                if let Err(status) = arm.claim_for_policy(id, &name, tx.clone(), silence_timeout_s) {
                    for done in &claimed {
                        let done: &Arc<crate::arm::ArmController> = done;
                        done.release_policy(id, "session could not take every arm");
                    }
                    return Err(status);
                }
                claimed.push(arm);
            }
        }
        let ready = v1::SessionReady {
            session_id: session_capability(id, &session.secret),
            arms: arms
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
        tx.try_send(event(v1::policy_event::Event::Ready(ready)))
            .map_err(|_| Status::internal("event queue"))?;
        if hello.request_control {
            let _ = tx.try_send(event(v1::policy_event::Event::Granted(v1::ControlGranted {
                arms: arms.clone(),
            })));
        }
        app.register_policy(Arc::clone(&session));
        // Debug formatting escapes control characters: a policy name cannot forge log lines.
        tracing::info!(session = id, policy = ?name, ?arms, control = hello.request_control, "policy session opened");

        let (out_tx, out_rx) = mpsc::channel::<Result<v1::PolicyEvent, Status>>(16);
        // Forward events; the events channel is shared with the arm controllers (revocations).
        let forward_tx = out_tx.clone();
        let mut events_rx = rx;
        tokio::spawn(async move {
            while let Some(e) = events_rx.recv().await {
                if forward_tx.send(Ok(e)).await.is_err() {
                    break;
                }
            }
        });
        let rate_hz = hello.observation_rate_hz;
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
                    _ = ticker.tick(), if rate_hz > 0.0 => send_observation(&app, &session),
                    msg = inbound.message() => match msg {
                        Ok(Some(v1::PolicyRequest { request: Some(request) })) => match request {
                            v1::policy_request::Request::Chunk(chunk) => {
                                let e = match app.push_chunk(&session, &chunk) {
                                    Ok(accepted) => v1::policy_event::Event::Accepted(accepted),
                                    Err(status) => v1::policy_event::Event::Rejected(v1::ChunkRejected {
                                        arm: chunk.arm.clone(),
                                        observation_id: chunk.observation_id,
                                        reason: status.message().to_owned(),
                                    }),
                                };
                                let _ = session.events.try_send(event(e));
                            }
                            v1::policy_request::Request::Observe(_) => send_observation(&app, &session),
                            v1::policy_request::Request::Release(_) => {
                                for arm in &session.arms {
                                    if let Some(a) = app.arm(arm) { a.release_policy(session.id, "released"); }
                                }
                            }
                            v1::policy_request::Request::Hello(_) => {
                                let _ = out_tx.send(Err(Status::invalid_argument("PolicyHello sent twice"))).await;
                                break;
                            }
                        },
                        Ok(Some(_)) => {}
                        Ok(None) => break,
                        // An undecodable or oversized message (a 100,000-step chunk): the session ends with that
                        // status, not with OK, so the policy knows it lost control.
                        Err(status) => {
                            tracing::warn!(session = session.id, %status, "policy session stream refused a message");
                            let _ = out_tx.send(Err(status)).await;
                            break;
                        }
                    },
                    () = crate::app::stopped(&mut shutdown) => break,
                }
            }
            for arm in &session.arms {
                if let Some(a) = app.arm(arm) {
                    a.release_policy(session.id, "session ended");
                }
            }
            app.unregister_policy(session.id);
            tracing::info!(session = session.id, "policy session closed");
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
            self.app.arm_names()
        } else {
            req.arms
        };
        let encoding =
            v1::ImageEncoding::try_from(req.image_encoding).unwrap_or(v1::ImageEncoding::Unspecified);
        let encoding = if encoding == v1::ImageEncoding::Unspecified {
            v1::ImageEncoding::Jpeg
        } else {
            encoding
        };
        let (obs, _) = self.app.observe(&arms, &req.cameras, encoding, 85)?;
        Ok(Response::new(obs))
    }

    async fn push_chunk(
        &self,
        request: Request<v1::PushChunkRequest>,
    ) -> Result<Response<v1::ChunkAccepted>, Status> {
        let req = request.into_inner();
        // One answer for a malformed, unknown or wrongly keyed id, so guessing learns nothing.
        let unknown =
            || Status::not_found("no open policy session with this session_id (use SessionReady.session_id)");
        let (id, secret) = req.session_id.split_once('.').ok_or_else(unknown)?;
        let id: u64 = id.parse().map_err(|_| unknown())?;
        let session = self
            .app
            .policy_session(id)
            .filter(|s| same_secret(&s.secret, secret))
            .ok_or_else(unknown)?;
        let chunk = req
            .chunk
            .ok_or_else(|| Status::invalid_argument("missing chunk"))?;
        Ok(Response::new(self.app.push_chunk(&session, &chunk)?))
    }
}
