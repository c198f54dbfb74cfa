//! A rosbridge v2 client connection: publishes on mapped topics become teleop samples for the arm the topic's
//! namespace names; subscriptions to the feedback topics, `/joint_states` and `/tf` are served from
//! `System.WatchStatus`, camera topics from `Policy.GetObservation` (see `ros_topics`).
//!
//! Camera images never run on the control path's runtime: each image topic's poller fetches and encodes
//! (JPEG to base64 JSON, tens of kB) on the video runtime with its own connection to the server, and hands
//! the text to the socket's [`ImageLane`], which sends it only when no control message waits.
//!
//! Errors go back as `{"op":"status","level":"error",...}` (with the message's `id`) to clients that asked for
//! them with `set_level` (or to every client when `rosbridge_status_level` says so). rosbridge never sends
//! `status`, and roslibpy raises on an op it has no handler for, so unasked status would break such clients.

use crate::config::TopicRole;
use crate::conn::{Handler, ImageLane, Wiring};
use crate::feedback::{arm_json, pose_parts, recording_json};
use crate::ros_topics::{self, Builtin};
use crate::rosbridge::{self, Op, StatusLevel, WireError};
use crate::session::{Session, SessionEvent};
use crate::shared::Shared;
use crate::takeover::Claim;
use crate::upstream::Upstream;
use phone2act_proto::buttons;
use phone2act_proto::v1::{
    ButtonEvent, GetStatusRequest, PhoneSample, Pose, SystemStatus, TrackingState, WatchStatusRequest,
    clutch_command,
};
use serde_json::Value;
use std::collections::{HashMap, HashSet};
use std::net::IpAddr;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::task::JoinHandle;

/// After the server refuses an arm, publishes to it are dropped for this long instead of opening a new
/// stream per message (the app publishes at 50 Hz).
const REFUSED_BACKOFF: Duration = Duration::from_secs(2);
/// Rate of the status watch behind subscriptions.
const WATCH_INTERVAL_S: f64 = 0.05;
/// Fastest camera image rate per subscription (10 Hz): a JPEG as base64 JSON is tens of kB, and a viewer
/// on Wi-Fi gains nothing from the recorder's full rate.
const MIN_CAMERA_PERIOD: Duration = Duration::from_millis(100);

/// Where a subscribed topic's messages come from.
#[derive(Debug)]
enum Source {
    /// A per-arm feedback topic of the topic map.
    Arm { arm: String, role: TopicRole },
    /// `/joint_states`, `/tf` or a camera (see `ros_topics`).
    Builtin(Builtin),
}

#[derive(Debug)]
struct Subscription {
    source: Source,
    ids: HashSet<String>,
    throttle: Duration,
    last_sent: Option<Instant>,
    /// The camera poller behind an image topic, stopped when the last subscriber leaves.
    poller: Option<CameraPoller>,
}

/// An image topic's poller task and its place in the socket's image lane; dropping it stops both.
#[derive(Debug)]
struct CameraPoller {
    task: JoinHandle<()>,
    lane: Arc<ImageLane>,
    topic: String,
}

impl Drop for CameraPoller {
    fn drop(&mut self) {
        self.task.abort();
        // The task may be mid-fetch on the video thread: closing the topic makes its late image be refused.
        self.lane.close(&self.topic);
    }
}

/// State of one rosbridge socket.
pub(crate) struct RosbridgeHandler {
    shared: Arc<Shared>,
    wiring: Wiring,
    /// This socket's id in the gateway's arm-holder registry, and the address it came from.
    conn: u64,
    peer: IpAddr,
    client_name: &'static str,
    level: StatusLevel,
    advertised: HashMap<String, String>,
    sessions: HashMap<String, Session>,
    refused_until: HashMap<String, Instant>,
    volume: HashMap<String, [i64; 2]>,
    subscriptions: HashMap<String, Subscription>,
    watcher: Option<JoinHandle<()>>,
    seq: u64,
}

impl RosbridgeHandler {
    pub(crate) fn new(shared: Arc<Shared>, wiring: Wiring, peer: IpAddr) -> Self {
        // Validated when the gateway starts.
        let level = StatusLevel::parse(&shared.config.rosbridge_status_level).unwrap_or(StatusLevel::None);
        let conn = shared.next_connection();
        Self {
            shared,
            wiring,
            conn,
            peer,
            client_name: "rosbridge",
            level,
            advertised: HashMap::new(),
            sessions: HashMap::new(),
            refused_until: HashMap::new(),
            volume: HashMap::new(),
            subscriptions: HashMap::new(),
            watcher: None,
            seq: 0,
        }
    }

    fn status(&self, level: StatusLevel, msg: &str, id: Option<&Value>) {
        if level >= self.level && level != StatusLevel::None {
            self.wiring.out.text(rosbridge::status(level, msg, id));
        }
    }

    fn handle(&mut self, id: Option<&Value>, op: Op) -> Result<(), WireError> {
        match op {
            Op::Advertise { topic, msg_type } => {
                let known = self.resolve(&topic);
                if let Some((_, role)) = known {
                    check_type(&topic, role, &msg_type)?;
                }
                self.advertised.insert(topic.clone(), msg_type);
                if known.is_none() {
                    // Kept advertised (the app streams IMU topics we do not use), but said once, here.
                    return Err(WireError(format!(
                        "unknown topic {topic}: the gateway ignores what is published on it"
                    )));
                }
            }
            Op::Unadvertise { topic } => {
                self.advertised.remove(&topic);
            }
            Op::Publish { topic, msg_type, msg } => self.publish(id, &topic, msg_type.as_deref(), &msg)?,
            Op::Subscribe {
                topic,
                sub_id,
                msg_type,
                throttle_rate_ms,
            } => {
                let source = if let Some(builtin) = Builtin::resolve(&topic) {
                    if let Some(t) = msg_type.as_deref().filter(|t| *t != builtin.msg_type()) {
                        return Err(WireError(format!(
                            "{topic} carries {}, not {t}",
                            builtin.msg_type()
                        )));
                    }
                    Source::Builtin(builtin)
                } else if let Some((arm, role)) = self.resolve(&topic).filter(|(_, r)| r.is_output()) {
                    if let Some(t) = &msg_type {
                        check_type(&topic, role, t)?;
                    }
                    Source::Arm { arm, role }
                } else {
                    return Err(WireError(format!(
                        "unknown topic {topic}: nothing is published on it (call /rosapi/topics for the list)"
                    )));
                };
                let throttle = Duration::from_millis(throttle_rate_ms);
                let camera = match &source {
                    Source::Builtin(Builtin::Camera(name)) => Some(name.clone()),
                    _ => None,
                };
                let sub = self
                    .subscriptions
                    .entry(topic.clone())
                    .or_insert_with(|| Subscription {
                        source,
                        ids: HashSet::new(),
                        throttle,
                        last_sent: None,
                        poller: None,
                    });
                sub.ids.insert(sub_id.unwrap_or_default());
                sub.throttle = throttle;
                match camera {
                    Some(name) => {
                        // A new throttle takes effect by restarting the poller.
                        sub.poller = None;
                        let (runtime, upstream) = if self.shared.images_on_control_runtime {
                            (tokio::runtime::Handle::current(), self.shared.upstream.clone())
                        } else {
                            self.shared.camera_runtime()
                        };
                        sub.poller = Some(spawn_camera_poller(
                            &runtime,
                            upstream,
                            self.wiring.images.clone(),
                            topic,
                            name,
                            throttle,
                        ));
                    }
                    None => self.ensure_watcher(),
                }
            }
            Op::Unsubscribe { topic, sub_id } => {
                if let Some(sub) = self.subscriptions.get_mut(&topic) {
                    match sub_id {
                        Some(sid) => {
                            sub.ids.remove(&sid);
                        }
                        None => sub.ids.clear(),
                    }
                    if sub.ids.is_empty() {
                        self.subscriptions.remove(&topic);
                    }
                }
                if !self
                    .subscriptions
                    .values()
                    .any(|s| !matches!(s.source, Source::Builtin(Builtin::Camera(_))))
                    && let Some(w) = self.watcher.take()
                {
                    w.abort();
                }
            }
            Op::CallService { service, args } => self.call_service(service, args, id),
            Op::SetLevel { level } => self.level = level,
            Op::Ignored => {}
        }
        Ok(())
    }

    /// Answers the `rosapi` services; the topic list needs the server's arms and cameras, so those calls
    /// are answered from a task once `System.GetStatus` returns.
    fn call_service(&self, service: String, args: Value, id: Option<&Value>) {
        let out = self.wiring.out.clone();
        let id = id.cloned();
        if !ros_topics::needs_catalogue(&service) {
            let reply = match ros_topics::rosapi_values(&service, &args, &[], wall_now_ns()) {
                Some(values) => rosbridge::service_success(&service, values, id.as_ref()),
                None => rosbridge::service_failure(
                    &service,
                    &format!("service {service} is not provided by the phone2act gateway"),
                    id.as_ref(),
                ),
            };
            out.text(reply);
            return;
        }
        let shared = self.shared.clone();
        tokio::spawn(async move {
            let reply = match shared.upstream.system().get_status(GetStatusRequest {}).await {
                Ok(status) => {
                    let status = status.into_inner();
                    let arms: Vec<String> = status.arms.iter().map(|a| a.arm.clone()).collect();
                    let cameras: Vec<String> = status.cameras.iter().map(|c| c.camera.clone()).collect();
                    let catalogue = ros_topics::catalogue(
                        &shared.config.topics,
                        &shared.config.default_arm,
                        &arms,
                        &cameras,
                    );
                    let values = ros_topics::rosapi_values(&service, &args, &catalogue, wall_now_ns())
                        .unwrap_or(Value::Null);
                    rosbridge::service_success(&service, values, id.as_ref())
                }
                Err(status) => rosbridge::service_failure(
                    &service,
                    &format!("the phone2act server did not answer: {}", status.message()),
                    id.as_ref(),
                ),
            };
            out.text(reply);
        });
    }

    fn resolve(&self, topic: &str) -> Option<(String, TopicRole)> {
        self.shared
            .config
            .topics
            .resolve(topic, &self.shared.config.default_arm)
    }

    fn publish(
        &mut self,
        id: Option<&Value>,
        topic: &str,
        msg_type: Option<&str>,
        msg: &Value,
    ) -> Result<(), WireError> {
        let Some((arm, role)) = self.resolve(topic) else {
            // The app also streams IMU and GPS topics; they have no use here and are not errors.
            self.status(
                StatusLevel::Warning,
                &format!("topic {topic} is not mapped to an arm; ignored"),
                id,
            );
            return Ok(());
        };
        if role.is_output() {
            return Err(WireError(format!(
                "{topic} is published by the gateway, not by clients"
            )));
        }
        if let Some(t) = msg_type.or_else(|| self.advertised.get(topic).map(String::as_str)) {
            check_type(topic, role, t)?;
        }
        self.seq += 1;
        let mut sample = PhoneSample {
            seq: self.seq,
            client_name: self.client_name.to_owned(),
            ..PhoneSample::default()
        };
        match role {
            TopicRole::Pose => {
                let pose = rosbridge::parse_pose_stamped(msg)?;
                // The server refuses it too, but only the sample it reads: poses fold latest-wins on the
                // way, so a newer pose could replace this one and its error would never be reported.
                phone2act_proto::convert_arm::check_wire_pose(pose.position_m, pose.quat_xyzw)
                    .map_err(|e| WireError(format!("{topic}: pose refused: {e}")))?;
                if topic.contains("Phone2Act/") || topic.contains("bros2/") {
                    self.client_name = "phone2act-android";
                    self.client_name.clone_into(&mut sample.client_name);
                }
                sample.capture_time_ns = pose.stamp_ns.unwrap_or_else(phone2act_clock::monotonic_ns);
                // Raw, in the phone's tracking frame: the server's planner owns the axis mapping.
                sample.tracking_from_phone = Some(Pose::from_parts(pose.position_m, pose.quat_xyzw));
                sample.tracking = TrackingState::Tracking.into();
            }
            TopicRole::Volume => {
                // The app's toggle *states*, read as the original planner reads them: the app is the source
                // of truth, so a reconnect or a lost message cannot desynchronise anything.
                let state = rosbridge::parse_volume(msg)?;
                if let Some(bad) = state.iter().find(|v| !matches!(v, 0 | 1)) {
                    return Err(WireError(format!(
                        "volume toggle states must be 0 or 1, got {bad}"
                    )));
                }
                self.volume.insert(arm.clone(), state);
                sample.buttons.extend(volume_buttons(state));
            }
            TopicRole::Gripper => {
                let position = rosbridge::parse_float32(msg)?;
                if !(0.0..=1.0).contains(&position) {
                    return Err(WireError(format!("gripper position {position} outside [0, 1]")));
                }
                sample.buttons.push(buttons::gripper_set(position));
            }
            TopicRole::Clutch => {
                let engage = rosbridge::parse_bool(msg)?;
                sample.buttons.push(buttons::clutch(if engage {
                    clutch_command::Kind::Engage
                } else {
                    clutch_command::Kind::Disengage
                }));
            }
            TopicRole::RobotFeedback | TopicRole::TargetPose | TopicRole::Status => {
                unreachable!("checked above")
            }
        }
        self.send(arm, sample);
        Ok(())
    }

    fn send(&mut self, arm: String, mut sample: PhoneSample) {
        let now = Instant::now();
        if self.refused_until.get(&arm).is_some_and(|until| now < *until) {
            return;
        }
        let live = self.sessions.get(&arm).is_some_and(|s| !s.is_finished());
        if !live {
            let silence = self.shared.takeover_silence();
            let inherited = match self
                .shared
                .holders
                .claim(&arm, self.conn, self.peer, now, silence)
            {
                Claim::Bind => None,
                Claim::TakeOver { volume } => {
                    tracing::info!(
                        arm,
                        peer = %self.peer,
                        "rosbridge: a new connection from the arm's own address takes it over from its silent one"
                    );
                    sample.take_over = true;
                    volume
                }
                // The holder spoke less than a staleness timeout ago; the next message asks again.
                Claim::Wait => return,
                Claim::Held { by } => {
                    let message = format!(
                        "arm {arm} is driven by another phone ({by}); it is free once that phone disconnects"
                    );
                    tracing::warn!(arm, peer = %self.peer, holder = %by, "rosbridge client refused: arm held by another address");
                    self.status(StatusLevel::Error, &message, None);
                    self.refused_until.insert(arm, now + REFUSED_BACKOFF);
                    return;
                }
            };
            // A new session starts disengaged: tell it the app's state this connection last heard (possibly
            // while the arm was not yet its own), else the state of the connection it takes over from.
            if let Some(state) = self.volume.get(&arm).copied().or(inherited) {
                self.volume.insert(arm.clone(), state);
                if sample.buttons.is_empty() {
                    sample.buttons = volume_buttons(state);
                }
            }
            let session =
                crate::session::start(&self.shared.upstream, &arm, self.wiring.session_events.clone());
            self.sessions.insert(arm.clone(), session);
        }
        self.shared
            .holders
            .heard(&arm, self.conn, now, self.volume.get(&arm).copied());
        if let Some(session) = self.sessions.get(&arm) {
            session.send(sample);
        }
    }

    fn ensure_watcher(&mut self) {
        if self.watcher.as_ref().is_some_and(|w| !w.is_finished()) {
            return;
        }
        let upstream = self.shared.upstream.clone();
        let tx = self.wiring.status_events.clone();
        self.watcher = Some(tokio::spawn(async move {
            loop {
                match upstream
                    .system()
                    .watch_status(WatchStatusRequest {
                        interval_s: WATCH_INTERVAL_S,
                    })
                    .await
                {
                    Ok(response) => {
                        let mut stream = response.into_inner();
                        while let Ok(Some(status)) = stream.message().await {
                            if tx.is_closed() {
                                return;
                            }
                            // Snapshots replace each other; a full queue means the socket is behind.
                            let _ = tx.try_send(Box::new(status));
                        }
                    }
                    Err(status) => tracing::debug!(%status, "status watch failed"),
                }
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }));
    }
}

impl Drop for RosbridgeHandler {
    fn drop(&mut self) {
        self.shared.holders.release_all(self.conn);
        if let Some(w) = self.watcher.take() {
            w.abort();
        }
    }
}

/// Nanoseconds since the Unix epoch: ROS tools want wall-clock stamps.
fn wall_now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// Fetches one camera's JPEG through `Policy.GetObservation` (read-only: it takes no control) on `runtime`
/// through `upstream` (the video runtime's connection), encodes it as a rosbridge message there and puts it
/// in `lane`, at most once per `throttle` (at least `MIN_CAMERA_PERIOD`), until dropped with the last
/// unsubscribe. No fetch while the topic's last image still waits: a slow reader lowers the rate instead of
/// costing fetches that would only replace each other.
fn spawn_camera_poller(
    runtime: &tokio::runtime::Handle,
    upstream: Upstream,
    lane: Arc<ImageLane>,
    topic: String,
    camera: String,
    throttle: Duration,
) -> CameraPoller {
    let period = throttle.max(MIN_CAMERA_PERIOD);
    let generation = lane.open(&topic);
    let task = runtime.spawn({
        let (lane, topic) = (lane.clone(), topic.clone());
        async move {
            let mut warned = false;
            loop {
                if !lane.is_waiting(&topic) {
                    match upstream.camera_jpeg(&camera).await {
                        Ok(Some(jpeg)) => {
                            let msg = ros_topics::compressed_image(&camera, &jpeg, wall_now_ns());
                            if !lane.put(&topic, generation, rosbridge::publish(&topic, msg)) {
                                return;
                            }
                        }
                        Err(status) if !warned => {
                            warned = true;
                            tracing::warn!(camera, %status, "rosbridge: camera image unavailable");
                        }
                        Ok(None) | Err(_) => {}
                    }
                }
                // After the fetch, so that images are stamped at least `period` apart whatever a fetch takes.
                tokio::time::sleep(period).await;
            }
        }
    });
    CameraPoller { task, lane, topic }
}

fn check_type(topic: &str, role: TopicRole, msg_type: &str) -> Result<(), WireError> {
    if msg_type == role.msg_type() {
        Ok(())
    } else {
        Err(WireError(format!(
            "{topic} carries {}, not {msg_type}",
            role.msg_type()
        )))
    }
}

/// The app's `[up, down]` state as commands, as the original planner reads it: `down` 1 holds (clutch
/// disengaged), 0 follows (engage: a re-index from the measured pose, so it never moves the arm; the server
/// ignores an engage while engaged); `up` 0 closes the gripper (1.0), 1 opens it (0.0).
fn volume_buttons(state: [i64; 2]) -> Vec<ButtonEvent> {
    let [up, down] = state;
    vec![
        buttons::gripper_set(if up == 0 { 1.0 } else { 0.0 }),
        buttons::clutch(if down == 1 {
            clutch_command::Kind::Disengage
        } else {
            clutch_command::Kind::Engage
        }),
    ]
}

impl Handler for RosbridgeHandler {
    fn on_text(&mut self, text: &str) {
        match rosbridge::parse(text) {
            Ok(incoming) => {
                if let Err(e) = self.handle(incoming.id.as_ref(), incoming.op) {
                    self.status(StatusLevel::Error, &e.0, incoming.id.as_ref());
                }
            }
            Err((id, e)) => self.status(StatusLevel::Error, &e.0, id.as_ref()),
        }
    }

    fn on_oversized(&mut self, len: usize) {
        self.status(
            StatusLevel::Error,
            &format!(
                "message of {len} bytes exceeds the limit of {} bytes; ignored",
                self.shared.config.max_message_bytes
            ),
            None,
        );
    }

    fn on_session_event(&mut self, event: SessionEvent) {
        match event {
            SessionEvent::Open { arm } => {
                let volume = self.volume.get(&arm).copied();
                self.shared
                    .holders
                    .hold(&arm, self.conn, self.peer, Instant::now(), volume);
                self.status(StatusLevel::Info, &format!("driving arm {arm}"), None);
            }
            SessionEvent::Feedback { arm, feedback } => {
                if !feedback.error.is_empty() {
                    self.status(
                        StatusLevel::Error,
                        &format!("arm {arm}: {}", feedback.error),
                        None,
                    );
                }
            }
            SessionEvent::Retrying {
                arm,
                message,
                retry_in,
            } => self.status(
                StatusLevel::Warning,
                &format!("arm {arm}: server unavailable ({message}); retrying in {retry_in:?}"),
                None,
            ),
            SessionEvent::Refused { arm, code, message } => {
                // The client may not listen to status messages: make sure the operator sees it.
                tracing::warn!(arm, ?code, message, "rosbridge client refused by the server");
                self.status(
                    StatusLevel::Error,
                    &format!("arm {arm}: {code:?}: {message}"),
                    None,
                );
                self.sessions.remove(&arm);
                self.shared.holders.release(&arm, self.conn);
                self.refused_until.insert(arm, Instant::now() + REFUSED_BACKOFF);
            }
        }
    }

    fn on_status(&mut self, status: Box<SystemStatus>) {
        let now = Instant::now();
        let wall_ns = wall_now_ns();
        for (topic, sub) in &mut self.subscriptions {
            if sub
                .last_sent
                .is_some_and(|t| now.duration_since(t) < sub.throttle)
            {
                continue;
            }
            let (arm_name, role) = match &sub.source {
                Source::Arm { arm, role } => (arm, *role),
                Source::Builtin(Builtin::JointStates) => {
                    sub.last_sent = Some(now);
                    let msg = ros_topics::joint_states(&status, wall_ns);
                    self.wiring.out.text(rosbridge::publish(topic, msg));
                    continue;
                }
                Source::Builtin(Builtin::Tf) => {
                    sub.last_sent = Some(now);
                    let msg = ros_topics::tf(&status, wall_ns);
                    self.wiring.out.text(rosbridge::publish(topic, msg));
                    continue;
                }
                Source::Builtin(Builtin::Camera(_)) => continue,
            };
            let Some(arm) = status.arms.iter().find(|a| &a.arm == arm_name) else {
                continue;
            };
            let text = match role {
                TopicRole::RobotFeedback | TopicRole::TargetPose => {
                    let pose = if role == TopicRole::RobotFeedback {
                        &arm.robot_from_ee
                    } else {
                        &arm.robot_from_target
                    };
                    let (p, q) = pose_parts(pose.as_ref());
                    let stamp_ns = if arm.feedback_time_ns > 0 {
                        arm.feedback_time_ns
                    } else {
                        status.server_time_ns
                    };
                    rosbridge::publish_pose(topic, "robot_base", stamp_ns, p, q)
                }
                TopicRole::Status => {
                    let mut v = arm_json(arm);
                    v["recording"] = recording_json(status.recording.as_ref());
                    rosbridge::publish_string(topic, &v.to_string())
                }
                _ => continue,
            };
            sub.last_sent = Some(now);
            self.wiring.out.text(text);
        }
    }
}
