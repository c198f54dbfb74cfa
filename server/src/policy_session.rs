//! Policy sessions: which arms and cameras a session opened, the observations it was sent (so a chunk can be
//! anchored on the pose of the observation it answers), its capability id, and the rules for building an
//! observation and scheduling a chunk. The `Policy` service adapter only validates and converts around this.

use crate::app::{App, LookupError};
use crate::arm::{ArmController, ArmError, RevocationSink};
use nalgebra::Isometry3;
use parking_lot::Mutex;
use phone2act_capture::jpeg::JpegError;
use phone2act_clock::{monotonic_ns, monotonic_s};
use phone2act_core::{ActionMode, ReplaceReport};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// Observations a session remembers for anchoring chunks (at 50 Hz, about 2.5 s).
pub const OBSERVATION_MEMORY: usize = 128;

/// Why a policy request was refused.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error(transparent)]
    Lookup(#[from] LookupError),
    #[error("arm {0:?} has no robot feedback yet")]
    NoFeedback(String),
    #[error("camera {camera}: {source}")]
    Jpeg {
        camera: String,
        #[source]
        source: JpegError,
    },
    #[error("this session did not open arm {0:?}")]
    ArmNotOpened(String),
    #[error("chunk has no steps")]
    EmptyChunk,
    #[error("step {step} has {got} values; arm {arm:?} takes {width} ({names})")]
    StepWidth {
        step: usize,
        got: usize,
        arm: String,
        width: usize,
        names: String,
    },
    #[error("step {step} value {index} is not finite")]
    NotFinite { step: usize, index: usize },
    #[error("step_period_s must be > 0, got {0}")]
    StepPeriod(f64),
    #[error("keep_steps {keep} must be less than the chunk's {steps} steps")]
    KeepSteps { keep: usize, steps: usize },
    #[error("observation {0} is unknown or too old (this session remembers its last {OBSERVATION_MEMORY})")]
    UnknownObservation(u64),
    #[error("observation {id} has no arm {arm:?}")]
    ObservationLacksArm { id: u64, arm: String },
    /// One answer for a malformed, unknown or wrongly keyed id, so guessing learns nothing.
    #[error("no open policy session with this session_id (use SessionReady.session_id)")]
    UnknownSession,
    #[error("no randomness for a session id: {0}")]
    NoRandomness(#[source] getrandom::Error),
    /// The arm controller refused.
    #[error(transparent)]
    Arm(#[from] ArmError),
}

/// How an observation carries camera frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameEncoding {
    /// No frames.
    None,
    /// Packed RGB.
    Rgb8,
    /// JPEG at a quality of 1..=100.
    Jpeg { quality: u8 },
}

/// One arm in an observation.
#[derive(Debug, Clone)]
pub struct ArmObservation {
    pub arm: String,
    pub state: Vec<f64>,
    pub state_names: Vec<String>,
    pub action_names: Vec<String>,
    pub robot_from_ee: Isometry3<f64>,
    /// The driving policy's plan from the observation on, in the arm's action mode against this observation
    /// (real-time chunking's leftover); empty when no plan plays.
    pub pending_steps: Vec<Vec<f64>>,
    pub pending_step_period_s: f64,
}

/// One camera frame in an observation, encoded as asked.
#[derive(Debug, Clone)]
pub struct ObservedFrame {
    pub camera: String,
    pub width: u32,
    pub height: u32,
    /// JPEG bytes when true, packed RGB otherwise.
    pub jpeg: bool,
    pub data: Vec<u8>,
    pub capture_time_ns: i64,
    pub seq: u64,
}

/// What the robot and its cameras looked like at one instant.
#[derive(Debug, Clone)]
pub struct Observation {
    /// Never 0 (0 means "no observation" in chunks).
    pub id: u64,
    pub timestamp_ns: i64,
    pub arms: Vec<ArmObservation>,
    pub frames: Vec<ObservedFrame>,
    /// The task of the episode in progress.
    pub task: String,
    /// The session's measured inference delay (see [`InferenceDelay`]); 0 outside a session.
    pub inference_delay_s: f64,
    pub inference_delay_steps: u32,
}

/// Chunks whose delay [`InferenceDelay`] keeps: LeRobot's RTC takes the largest of its recent latencies.
pub const DELAY_MEMORY: usize = 10;

/// A session's inference delay: observation time to the arrival of the chunk answering it, over its last
/// [`DELAY_MEMORY`] chunks.
#[derive(Debug, Default)]
struct InferenceDelay {
    /// (delay s, that chunk's step period s), newest last.
    recent: VecDeque<(f64, f64)>,
}

impl InferenceDelay {
    fn note(&mut self, delay_s: f64, step_period_s: f64) {
        if self.recent.len() == DELAY_MEMORY {
            self.recent.pop_front();
        }
        self.recent.push_back((delay_s.max(0.0), step_period_s));
    }

    /// The largest recent delay, and it in steps of the newest chunk's period (rounded up).
    fn current(&self) -> (f64, u32) {
        let Some(&(_, period_s)) = self.recent.back() else {
            return (0.0, 0);
        };
        let delay_s = self.recent.iter().map(|d| d.0).fold(0.0, f64::max);
        // Within a nanosecond of a whole number of steps is that number (float noise, not a late step).
        let steps = (delay_s / period_s - 1e-9).ceil().max(0.0);
        (delay_s, steps.min(f64::from(u32::MAX)) as u32)
    }
}

/// What a chunk needs from the observation it answers.
#[derive(Debug, Clone)]
struct ObservationAnchor {
    id: u64,
    time_s: f64,
    poses: Vec<(String, Isometry3<f64>)>,
}

/// What a session asks for when it opens (already validated by the adapter).
#[derive(Debug, Clone)]
pub struct SessionRequest {
    /// Arms to observe (and drive, with `request_control`); empty means every arm.
    pub arms: Vec<String>,
    /// Cameras whose frames go into observations; empty means every camera.
    pub cameras: Vec<String>,
    pub encoding: FrameEncoding,
    /// Empty for a generated `policy-<id>`.
    pub name: String,
    pub silence_timeout_s: f64,
    pub request_control: bool,
}

/// A chunk of steps for one arm, as the session schedules it.
#[derive(Debug, Clone, Copy)]
pub struct ChunkRequest<'a> {
    pub arm: &'a str,
    /// The observation the chunk answers; 0 anchors it on the arm's pose now.
    pub observation_id: u64,
    pub mode: ActionMode,
    pub step_period_s: f64,
    pub steps: &'a [Vec<f64>],
    /// Leading steps not played: the replaced plan keeps their windows (real-time chunking).
    pub keep_steps: usize,
}

/// One open policy session.
#[derive(Debug)]
pub struct PolicySession {
    id: u64,
    name: String,
    arms: Vec<String>,
    cameras: Vec<String>,
    encoding: FrameEncoding,
    /// Where the arms tell the session it lost control (the service layer turns that into a wire event).
    revocations: Arc<dyn RevocationSink>,
    anchors: Mutex<VecDeque<ObservationAnchor>>,
    delay: Mutex<InferenceDelay>,
    /// 128 random bits in `SessionReady.session_id`: `PushChunk` must name them, so a session id is a
    /// capability that only the session's own client holds, not a small integer anyone can guess.
    secret: String,
}

/// The open sessions and the observation counter they share.
#[derive(Debug)]
pub struct PolicySessions {
    app: Arc<App>,
    /// A map of Arcs: an insert or remove that panicked left it whole, so the lock's lack of poisoning is
    /// safe here.
    open: Mutex<HashMap<u64, Arc<PolicySession>>>,
    observations: AtomicU64,
}

fn random_secret() -> Result<String, PolicyError> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes).map_err(PolicyError::NoRandomness)?;
    Ok(format!("{:032x}", u128::from_le_bytes(bytes)))
}

/// Compares in time independent of where the first difference is, so timing does not reveal a prefix.
fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl PolicySessions {
    /// No session open yet, over `app`'s arms and cameras.
    pub fn new(app: Arc<App>) -> Self {
        Self {
            app,
            open: Mutex::new(HashMap::new()),
            // Never 0: 0 means "no observation" in chunks.
            observations: AtomicU64::new(1),
        }
    }

    /// The server the sessions run on.
    pub fn app(&self) -> &Arc<App> {
        &self.app
    }

    /// Opens a session that hears of lost control through `revocations`, claiming its arms if it asks for control (all or
    /// none: an arm it cannot take releases the ones already taken).
    pub fn open(
        &self,
        request: SessionRequest,
        revocations: Arc<dyn RevocationSink>,
    ) -> Result<Arc<PolicySession>, PolicyError> {
        let arms = if request.arms.is_empty() {
            self.app.arm_names()
        } else {
            request.arms
        };
        let controllers = arms
            .iter()
            .map(|name| self.app.find_arm(name))
            .collect::<Result<Vec<_>, _>>()?;
        for cam in &request.cameras {
            self.app.find_camera(cam)?;
        }
        let id = self.app.next_session_id();
        let name = if request.name.is_empty() {
            format!("policy-{id}")
        } else {
            request.name
        };
        let session = Arc::new(PolicySession {
            id,
            name,
            arms,
            cameras: request.cameras,
            encoding: request.encoding,
            revocations,
            anchors: Mutex::new(VecDeque::with_capacity(OBSERVATION_MEMORY)),
            delay: Mutex::new(InferenceDelay::default()),
            secret: random_secret()?,
        });
        if request.request_control {
            for (k, arm) in controllers.iter().enumerate() {
                if let Err(e) = arm.claim_for_policy(
                    id,
                    &session.name,
                    Arc::clone(&session.revocations),
                    request.silence_timeout_s,
                ) {
                    for done in &controllers[..k] {
                        done.release_policy(id, "session could not take every arm");
                    }
                    return Err(PolicyError::Arm(e));
                }
            }
        }
        self.open.lock().insert(id, Arc::clone(&session));
        Ok(session)
    }

    /// The session a `SessionReady.session_id` capability names.
    pub fn find(&self, capability: &str) -> Result<Arc<PolicySession>, PolicyError> {
        let (id, secret) = capability.split_once('.').ok_or(PolicyError::UnknownSession)?;
        let id: u64 = id.parse().map_err(|_| PolicyError::UnknownSession)?;
        self.open
            .lock()
            .get(&id)
            .filter(|s| same_secret(&s.secret, secret))
            .cloned()
            .ok_or(PolicyError::UnknownSession)
    }

    /// Ends `session`: its arms hold and its id stops working.
    pub fn close(&self, session: &PolicySession) {
        session.release(&self.app, "session ended");
        self.open.lock().remove(&session.id);
    }

    /// Builds an observation of `arms` with the latest frames of `cameras` (every camera when empty).
    pub fn observe(
        &self,
        arms: &[String],
        cameras: &[String],
        encoding: FrameEncoding,
    ) -> Result<Observation, PolicyError> {
        self.observe_anchored(arms, cameras, encoding)
            .map(|(observation, _)| observation)
    }

    fn observe_anchored(
        &self,
        arms: &[String],
        cameras: &[String],
        encoding: FrameEncoding,
    ) -> Result<(Observation, ObservationAnchor), PolicyError> {
        let id = self.observations.fetch_add(1, Ordering::Relaxed);
        let timestamp_ns = monotonic_ns();
        let mut out = Vec::with_capacity(arms.len());
        let mut poses = Vec::with_capacity(arms.len());
        for name in arms {
            let arm = self.app.find_arm(name)?;
            let sample = arm
                .state_and_action()
                .ok_or_else(|| PolicyError::NoFeedback(name.clone()))?;
            poses.push((name.clone(), sample.robot_from_ee));
            let (pending_steps, pending_step_period_s) =
                arm.pending_steps(timestamp_ns as f64 * 1e-9, &sample.robot_from_ee, arm.action_mode);
            out.push(ArmObservation {
                arm: name.clone(),
                state: sample.state,
                state_names: arm.layout.state_names(),
                action_names: arm.layout.action_names(arm.action_mode),
                robot_from_ee: sample.robot_from_ee,
                pending_steps,
                pending_step_period_s,
            });
        }
        let mut frames = Vec::new();
        if encoding != FrameEncoding::None {
            for cam in self.app.cameras() {
                if !cameras.is_empty() && !cameras.contains(&cam.config().name) {
                    continue;
                }
                let Some(frame) = cam.slot().latest() else {
                    continue;
                };
                let data = if let FrameEncoding::Jpeg { quality } = encoding {
                    phone2act_capture::jpeg::encode_jpeg(&frame.rgb, frame.width, frame.height, quality)
                        .map_err(|source| PolicyError::Jpeg {
                            camera: cam.config().name.clone(),
                            source,
                        })?
                } else {
                    frame.rgb.as_ref().clone()
                };
                frames.push(ObservedFrame {
                    camera: cam.config().name.clone(),
                    width: frame.width,
                    height: frame.height,
                    jpeg: matches!(encoding, FrameEncoding::Jpeg { .. }),
                    data,
                    capture_time_ns: frame.capture_time_ns,
                    seq: frame.seq,
                });
            }
        }
        let observation = Observation {
            id,
            timestamp_ns,
            arms: out,
            frames,
            task: self.app.current_task(),
            inference_delay_s: 0.0,
            inference_delay_steps: 0,
        };
        let anchor = ObservationAnchor {
            id,
            time_s: timestamp_ns as f64 * 1e-9,
            poses,
        };
        Ok((observation, anchor))
    }

    /// Builds an observation for `session` and remembers its poses, so chunks answering it are anchored there.
    pub fn observe_for(&self, session: &PolicySession) -> Result<Observation, PolicyError> {
        let (mut observation, anchor) =
            self.observe_anchored(&session.arms, &session.cameras, session.encoding)?;
        session.remember(anchor);
        (observation.inference_delay_s, observation.inference_delay_steps) = session.delay.lock().current();
        Ok(observation)
    }

    /// `session` is loading: every arm it owns holds until its first chunk or its loading deadline. Returns the
    /// arms that hold and the seconds until the earliest deadline; an error when it owns none.
    pub fn loading(&self, session: &PolicySession) -> Result<(Vec<String>, f64), PolicyError> {
        let mut holding = Vec::new();
        let mut remaining_s = f64::INFINITY;
        let mut refusal = None;
        for name in &session.arms {
            match self.app.find_arm(name)?.policy_loading(session.id) {
                Ok(left_s) => {
                    holding.push(name.clone());
                    remaining_s = remaining_s.min(left_s);
                }
                Err(e) => refusal = Some(e),
            }
        }
        match refusal {
            Some(e) if holding.is_empty() => Err(PolicyError::Arm(e)),
            _ => Ok((holding, if remaining_s.is_finite() { remaining_s } else { 0.0 })),
        }
    }

    /// Schedules `chunk` for `session` on its arm: steps are checked against the arm's layout and anchored
    /// on the observation they answer (or the arm's pose now).
    pub fn push_chunk(
        &self,
        session: &PolicySession,
        chunk: &ChunkRequest<'_>,
    ) -> Result<ReplaceReport, PolicyError> {
        let arm = self.app.find_arm(chunk.arm)?;
        if !session.arms.iter().any(|a| a == chunk.arm) {
            return Err(PolicyError::ArmNotOpened(chunk.arm.to_owned()));
        }
        check_steps(&arm, chunk)?;
        // A chunk answering no observation is anchored on the arm's pose at its arrival: it counts as observed
        // then (a hand-back before it does not make it stale).
        let (anchor_s, reference) = if chunk.observation_id == 0 {
            let sample = arm
                .state_and_action()
                .ok_or_else(|| PolicyError::NoFeedback(chunk.arm.to_owned()))?;
            (monotonic_s(), sample.robot_from_ee)
        } else {
            let anchored = session.anchor(chunk.observation_id, chunk.arm)?;
            session
                .delay
                .lock()
                .note(monotonic_s() - anchored.0, chunk.step_period_s);
            anchored
        };
        // Kept steps: the replaced plan plays their windows; this chunk starts at its step `keep_steps`,
        // still on the observation's grid.
        let keep = chunk.keep_steps;
        arm.push_chunk(
            session.id,
            &chunk.steps[keep..],
            chunk.step_period_s,
            anchor_s + keep as f64 * chunk.step_period_s,
            anchor_s,
            reference,
            chunk.mode,
        )
        .map_err(PolicyError::Arm)
    }
}

fn check_steps(arm: &ArmController, chunk: &ChunkRequest<'_>) -> Result<(), PolicyError> {
    if chunk.steps.is_empty() {
        return Err(PolicyError::EmptyChunk);
    }
    let names = arm.layout.action_names(chunk.mode);
    for (step, values) in chunk.steps.iter().enumerate() {
        if values.len() != names.len() {
            return Err(PolicyError::StepWidth {
                step,
                got: values.len(),
                arm: chunk.arm.to_owned(),
                width: names.len(),
                names: names.join(", "),
            });
        }
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            return Err(PolicyError::NotFinite { step, index });
        }
    }
    if !chunk.step_period_s.is_finite() || chunk.step_period_s <= 0.0 {
        return Err(PolicyError::StepPeriod(chunk.step_period_s));
    }
    if chunk.keep_steps >= chunk.steps.len() {
        return Err(PolicyError::KeepSteps {
            keep: chunk.keep_steps,
            steps: chunk.steps.len(),
        });
    }
    Ok(())
}

impl PolicySession {
    /// The session's number (logs and ownership), not its capability.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// The policy's name as operators see it.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The arms the session opened.
    pub fn arms(&self) -> &[String] {
        &self.arms
    }

    /// `"<id>.<32 hex digits>"`: the sequential id keeps logs readable, the random part makes it unguessable.
    pub fn capability(&self) -> String {
        format!("{}.{}", self.id, self.secret)
    }

    /// Gives up control of every arm the session drives; they hold.
    pub fn release(&self, app: &App, reason: &str) {
        for name in &self.arms {
            if let Ok(arm) = app.find_arm(name) {
                arm.release_policy(self.id, reason);
            }
        }
    }

    fn remember(&self, anchor: ObservationAnchor) {
        let mut anchors = self.anchors.lock();
        if anchors.len() == OBSERVATION_MEMORY {
            anchors.pop_front();
        }
        anchors.push_back(anchor);
    }

    /// The time and pose of `arm` in observation `id`.
    fn anchor(&self, id: u64, arm: &str) -> Result<(f64, Isometry3<f64>), PolicyError> {
        let anchors = self.anchors.lock();
        let anchor = anchors
            .iter()
            .find(|a| a.id == id)
            .ok_or(PolicyError::UnknownObservation(id))?;
        anchor
            .poses
            .iter()
            .find(|(name, _)| name == arm)
            .map(|(_, pose)| (anchor.time_s, *pose))
            .ok_or_else(|| PolicyError::ObservationLacksArm {
                id,
                arm: arm.to_owned(),
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn session() -> PolicySession {
        #[derive(Debug)]
        struct Nobody;
        impl RevocationSink for Nobody {
            fn revoked(&self, _arm: &str, _reason: &str) {}
        }
        PolicySession {
            id: 7,
            name: "p".into(),
            arms: vec!["left".into()],
            cameras: Vec::new(),
            encoding: FrameEncoding::None,
            revocations: Arc::new(Nobody),
            anchors: Mutex::new(VecDeque::new()),
            delay: Mutex::new(InferenceDelay::default()),
            secret: "ab".repeat(16),
        }
    }

    fn anchor(id: u64) -> ObservationAnchor {
        ObservationAnchor {
            id,
            time_s: id as f64,
            poses: vec![("left".into(), Isometry3::translation(id as f64, 0.0, 0.0))],
        }
    }

    #[test]
    fn a_chunk_anchors_on_a_remembered_observation_until_it_is_forgotten() {
        let s = session();
        let count = OBSERVATION_MEMORY as u64 + 1;
        for id in 1..=count {
            s.remember(anchor(id));
        }
        let (time_s, pose) = s.anchor(count, "left").unwrap();
        assert_eq!((time_s, pose.translation.x), (count as f64, count as f64));
        // The oldest fell out of the bounded memory; the second oldest is still there.
        assert!(matches!(
            s.anchor(1, "left"),
            Err(PolicyError::UnknownObservation(1))
        ));
        assert!(s.anchor(2, "left").is_ok());
        assert!(matches!(
            s.anchor(2, "right"),
            Err(PolicyError::ObservationLacksArm { id: 2, .. })
        ));
    }

    #[test]
    fn the_inference_delay_is_the_largest_recent_one_in_steps_of_the_newest_chunk() {
        let mut d = InferenceDelay::default();
        assert_eq!(d.current(), (0.0, 0), "before the first chunk");
        d.note(0.31, 0.1);
        assert_eq!(d.current(), (0.31, 4), "rounded up: 3.1 steps are four windows");
        d.note(0.3, 0.1);
        assert_eq!(d.current(), (0.31, 4));
        d.note(0.1, 0.05);
        assert_eq!(d.current(), (0.31, 7), "in the newest chunk's period");
        for _ in 0..DELAY_MEMORY {
            d.note(0.2, 0.1);
        }
        assert_eq!(d.current(), (0.2, 2), "only the last {DELAY_MEMORY} count");
        d.note(-1.0, 0.1);
        assert_eq!(
            d.current(),
            (0.2, 2),
            "a negative delay (clock jitter) counts as 0"
        );
    }

    #[test]
    fn the_capability_is_the_id_and_the_secret_and_secrets_compare_whole() {
        let s = session();
        assert_eq!(s.capability(), format!("7.{}", "ab".repeat(16)));
        assert!(same_secret(&s.secret, &"ab".repeat(16)));
        assert!(!same_secret(&s.secret, &"ab".repeat(15)));
        assert!(!same_secret(&s.secret, &format!("{}ac", "ab".repeat(15))));
        assert_eq!(random_secret().unwrap().len(), 32);
        assert_ne!(random_secret().unwrap(), random_secret().unwrap());
    }
}
