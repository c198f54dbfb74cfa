//! Source arbitration of one arm: which source (the phone or a policy) may move it, and what each input
//! makes the arm do.
//!
//! The rules, all in [`Arbiter::handle`]:
//! - one source drives at a time ([`Driver`]);
//! - the operator always takes over from the phone: engaging stops a driving policy, which then *waits*
//!   (it keeps the arm reserved, its chunks are refused, nothing of its plan plays) until the operator hands
//!   the arm back with [`TeleopButton::HandBack`];
//! - a hand-back never moves the arm: the policy drives again but the arm holds where it is until a chunk
//!   answering an observation taken after the hand-back arrives (older ones are refused), so its next motion
//!   is planned from where the operator left the arm;
//! - a policy may claim the arm only while no phone drives it, the robot is ready and no other policy owns
//!   it or waits for it; it loses the arm on release, session end and silence;
//! - a silent source holds: nothing here moves the arm without an input asking for it;
//! - every source change re-indexes at the measured pose (the phone's floating zero, the policy's jump
//!   reference) and clears the chunk executor, so the new source never continues an old plan;
//! - nothing starts moving (engage, gripper, claim) unless the bridge is ready with a measured pose younger
//!   than [`FEEDBACK_MAX_AGE_S`]; a phone that is driving when the robot goes away is disengaged;
//! - the arm is teleported (a scene reset homes it) only while no source drives; afterwards it holds the
//!   homed pose and both sources re-index from it;
//! - time never runs backwards: an input stamped earlier than one already seen is handled at the later
//!   time, so a late caller cannot replay an earlier chunk step.
//!
//! Pure: no clock reads, no I/O. The caller passes the bridge's state ([`Robot`]) and the time, and carries
//! out the returned [`Effects`] (send these commands in order, tell that policy session it lost the arm).

use crate::chunk::{ActionChunk, ChunkConfig, ChunkError, ChunkExecutor, ChunkStep, Plan, ReplaceReport};
use crate::config::{ConfigError, TeleopConfig};
use crate::gate::{GateDecision, GateVerdict, SafetyGate};
use crate::gripper::GripperCommand;
use crate::teleop::{ClutchKind, TeleopArm};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Feedback older than this means the robot's pose is not known: nothing may start moving it. Bridges
/// report at 50 Hz or more (Dobot 125 Hz, SO-101 at its `rate_hz`, sim and remote 50 Hz), so a second is
/// dozens of missed reports, not jitter or a scheduler stall on a loaded machine.
pub const FEEDBACK_MAX_AGE_S: f64 = 1.0;

/// Who drives the arm right now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Driver {
    None,
    Teleop,
    Policy,
}

/// The bridge's connection state, as the arbiter needs it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum BridgeHealth {
    Ready,
    Connecting,
    Error(String),
    Disconnected(String),
}

/// The robot's last measured end-effector pose and when it was captured (same clock as `now_s`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Measured {
    pub robot_from_ee: Isometry3<f64>,
    pub capture_time_s: f64,
}

/// What the bridge reports at the moment of an input.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Robot {
    pub health: BridgeHealth,
    pub feedback: Option<Measured>,
}

/// Why the arm may not start moving.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NotReady {
    #[error("its bridge reports an error: {0}")]
    BridgeError(String),
    #[error("its bridge is disconnected: {0}")]
    Disconnected(String),
    #[error("its bridge is still connecting")]
    Connecting,
    #[error("its bridge has sent no valid feedback yet (no measured pose)")]
    NoFeedback,
    #[error("its last measured pose is {age_s:.2} s old (more than {FEEDBACK_MAX_AGE_S} s)")]
    StaleFeedback { age_s: f64 },
}

impl Robot {
    /// Why the arm may not be moved at `now_s`, if it may not: its bridge is not healthy, or it has no fresh
    /// measured pose. No command may start from a pose nobody measured.
    pub fn not_ready(&self, now_s: f64) -> Option<NotReady> {
        match &self.health {
            BridgeHealth::Error(m) => return Some(NotReady::BridgeError(m.clone())),
            BridgeHealth::Disconnected(m) => return Some(NotReady::Disconnected(m.clone())),
            BridgeHealth::Connecting if self.feedback.is_some() => return Some(NotReady::Connecting),
            // Ready, or connecting without feedback yet: the missing feedback is the reason given below.
            BridgeHealth::Ready | BridgeHealth::Connecting => {}
        }
        let Some(feedback) = &self.feedback else {
            return Some(NotReady::NoFeedback);
        };
        let age_s = now_s - feedback.capture_time_s;
        // A NaN capture time is not fresh either.
        let fresh = age_s
            .partial_cmp(&FEEDBACK_MAX_AGE_S)
            .is_some_and(std::cmp::Ordering::is_le);
        (!fresh).then_some(NotReady::StaleFeedback { age_s })
    }

    fn measured_or(&self, fallback: Isometry3<f64>) -> Isometry3<f64> {
        self.feedback.map_or(fallback, |f| f.robot_from_ee)
    }
}

/// The source driving an arm, as a refusal names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Owner {
    Phone { session: u64 },
    Policy { name: String },
}

impl std::fmt::Display for Owner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Phone { session } => write!(f, "a phone (teleop session {session})"),
            Self::Policy { name } => write!(f, "policy {name:?}"),
        }
    }
}

/// Why an input was refused. A refused input changes nothing.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArbiterError {
    #[error("is already bound to another phone; set take_over to replace it")]
    PhoneBound,
    #[error("was taken over by another phone")]
    PhoneReplaced,
    #[error("is driven by a phone; the operator must disengage first")]
    DrivenByPhone,
    #[error("is not ready: {0}")]
    NotReady(#[from] NotReady),
    #[error("is already controlled by policy {owner:?}")]
    NotOwner { owner: String },
    #[error("is not controlled by this policy session")]
    NotControlling,
    #[error("refused the chunk: {0}")]
    Chunk(#[from] ChunkError),
    #[error(
        "is driven by the operator's phone: policy {policy:?} waits for the operator to hand the arm back; chunk not executed"
    )]
    PolicyWaiting { policy: String },
    #[error(
        "refused the chunk: it answers an observation taken {before_s:.3} s before the operator handed the arm back; the arm holds until a chunk answers a newer observation"
    )]
    BeforeHandBack { before_s: f64 },
    #[error("is driven by {owner}; release it before homing the arm")]
    DrivenWhileHoming { owner: Owner },
}

/// One button event of a phone, already decoded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum TeleopButton {
    Clutch(ClutchKind),
    Gripper(GripperCommand),
    /// Hand the arm back to the policy that waits for it (the phone stops driving; nothing moves).
    HandBack,
    /// An event that could not be decoded; its message is reported to the phone in order with the others.
    Invalid(String),
}

/// The teleop input of one processing round: the newest pose and every button event since the last round.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TeleopRound {
    /// Newest pose (already validated) or the validation error.
    pub pose: Option<Result<Isometry3<f64>, String>>,
    pub tracking_ok: bool,
    pub buttons: Vec<TeleopButton>,
}

/// An input to the arbiter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Input {
    /// A phone asks for the arm; `take_over` replaces a bound phone.
    BindTeleop { session: u64, take_over: bool },
    /// A phone session ended.
    UnbindTeleop { session: u64 },
    /// A round of phone samples.
    Teleop { session: u64, round: TeleopRound },
    /// A policy session asks to drive the arm.
    ClaimPolicy {
        session: u64,
        name: String,
        silence_timeout_s: f64,
    },
    /// A policy session gives the arm up (release, session end).
    ReleasePolicy { session: u64, reason: String },
    /// The policy that owns the arm is loading (a keep-alive): the arm holds and the silence timeout waits,
    /// until its first chunk or until `ChunkConfig::max_loading_s` after its first loading message, whichever
    /// comes first. Later loading messages do not extend that deadline; past it the arm is released.
    PolicyLoading { session: u64 },
    /// A policy's chunk, already converted to targets. `observed_s` is when the observation it answers was
    /// taken (its arrival for a chunk that answers none: it is anchored on the arm's pose then).
    Chunk {
        session: u64,
        chunk: ActionChunk,
        #[serde(default)]
        observed_s: f64,
    },
    /// Time passes: play due chunk steps, apply the silence and staleness rules.
    Tick,
    /// The robot was teleported to its measured pose (`Robot::feedback`) with its gripper at `gripper` by
    /// no source (a scene reset homed it): the arm holds there and both sources re-index from it. Refused
    /// while a source drives (see [`Arbiter::may_home`], which the caller asks before teleporting).
    Homed { gripper: f64 },
}

/// A command for the bridge; it passed the safety gate of the source that made it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Increases by one per command: the caller sends in this order.
    pub seq: u64,
    pub robot_from_target: Isometry3<f64>,
    pub gripper: f64,
}

/// A policy session lost the arm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Revocation {
    pub session: u64,
    pub policy: String,
    pub reason: String,
}

/// The operator took the arm from a policy session, or handed it back: the session is to be told.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyTurn {
    pub session: u64,
    /// True for a hand-back, false for a take-over.
    pub resumed: bool,
}

/// What the caller must do after one input.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Effects {
    /// Commands to hand to the bridge, in order.
    pub commands: Vec<Command>,
    /// The policy session to tell that it lost the arm.
    pub revoked: Option<Revocation>,
    /// The decision now on display, if this input changed it.
    pub decision: Option<GateDecision>,
    /// True if the source changed and the new one was re-indexed at the measured pose.
    pub reindexed: bool,
    /// A per-sample problem to show on the phone (the round itself was accepted); empty when fine.
    pub phone_error: String,
    /// What a chunk did to the schedule.
    pub chunk: Option<ReplaceReport>,
    /// The policy session to tell that it waits, or drives again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turn: Option<PolicyTurn>,
}

/// How soon the arbiter needs a [`Input::Tick`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TickNeed {
    /// Nothing can change without an input: no ticks.
    Idle,
    /// Once, at this time (a policy's silence deadline).
    At(f64),
    /// At the control rate: a chunk is playing, or a phone drives and its stream may go stale.
    Periodic,
}

/// What the API shows about one arm at one moment: the arbiter's state and the bridge's.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmSnapshot {
    pub arm: String,
    pub bridge_kind: String,
    /// Ready means movable now (see [`Robot::not_ready`]); the message says why not.
    pub health: BridgeHealth,
    pub health_message: String,
    pub driver: Driver,
    /// The phone session id or `"<policy name>:<session id>"`, empty when nobody drives.
    pub owner_id: String,
    pub engaged: bool,
    pub robot_from_target: Isometry3<f64>,
    pub gripper_target: f64,
    pub robot_from_ee: Option<Isometry3<f64>>,
    pub joint_positions_rad: Vec<f64>,
    pub joint_names: Vec<String>,
    pub gripper_position: f64,
    pub last_decision: GateDecision,
    pub feedback_time_ns: i64,
    /// Negative without feedback.
    pub feedback_age_s: f64,
    pub counters: Counters,
    /// What the joint stage changed (arms whose joints the server solves; zero for the others).
    pub joint_counters: crate::joint_motion::JointCounters,
    /// The joints last commanded and their issue time (server monotonic ns); empty and 0 for other arms.
    pub joint_targets_rad: Vec<f64>,
    pub joint_targets_time_ns: i64,
    pub task_success: bool,
    /// The owning policy is loading: the arm holds until its first chunk (or the loading limit).
    pub policy_loading: bool,
    /// The policy that waits for a hand-back, as `"<policy name>:<session id>"`; empty when none waits.
    pub waiting_policy_id: String,
    /// What the driving policy is about to do (see [`Arbiter::plan_preview`]).
    pub plan_preview: PlanPreview,
}

/// A compact preview of a policy's plan for a display: the tool positions and gripper targets of the steps
/// still to play, at most [`PREVIEW_MAX_POINTS`], evenly picked and always including the last.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlanPreview {
    /// Tool positions in the robot base frame, m.
    pub positions_m: Vec<[f64; 3]>,
    /// Gripper targets, 0 open .. 1 closed.
    pub grippers: Vec<f64>,
    /// Time between two points of the preview, s (0 when empty).
    pub point_period_s: f64,
}

/// Most points in a [`PlanPreview`]: a phone draws a path from them, and they ride on every feedback message.
pub const PREVIEW_MAX_POINTS: usize = 16;

/// Commands handed out and refused so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counters {
    pub sent: u64,
    pub rejected: u64,
    pub clamped: u64,
    /// Hand-backs from the operator to a waiting policy.
    pub handed_back: u64,
}

#[derive(Debug, Clone)]
struct PolicyOwner {
    session: u64,
    name: String,
    silence_timeout_s: f64,
    last_chunk_s: f64,
    /// While the policy loads: when its loading deadline passes. Set by its first loading message, cleared by
    /// its first chunk; never moved later.
    loading_deadline_s: Option<f64>,
    /// The operator took the arm with the clutch: the policy keeps it reserved but does not drive.
    waiting: bool,
    /// When the operator last handed the arm back: only chunks answering a later observation may drive.
    handed_back_s: Option<f64>,
}

/// Source arbitration of one arm (see the module documentation).
#[derive(Debug, Clone)]
pub struct Arbiter {
    teleop: TeleopArm,
    policy_gate: SafetyGate,
    executor: ChunkExecutor,
    teleop_session: Option<u64>,
    driver: Driver,
    policy: Option<PolicyOwner>,
    target: Isometry3<f64>,
    gripper_target: f64,
    last_decision: GateDecision,
    last_policy_step: Option<ChunkStep>,
    latest_s: f64,
    seq: u64,
    counters: Counters,
}

impl Arbiter {
    /// Nobody drives; the arm holds `measured` (its measured pose, or a configured fallback before
    /// feedback) with the gripper at `gripper`. Time starts at 0.
    pub fn new(
        teleop: &TeleopConfig,
        chunk: ChunkConfig,
        measured: Isometry3<f64>,
        gripper: f64,
    ) -> Result<Self, ConfigError> {
        Ok(Self {
            teleop: TeleopArm::new(teleop, measured)?,
            policy_gate: SafetyGate::new(&teleop.gate, measured)?,
            executor: ChunkExecutor::new(chunk)?,
            teleop_session: None,
            driver: Driver::None,
            policy: None,
            target: measured,
            gripper_target: gripper,
            last_decision: GateDecision::note(GateVerdict::Accepted, "idle"),
            last_policy_step: None,
            latest_s: 0.0,
            seq: 0,
            counters: Counters::default(),
        })
    }

    /// Who drives the arm.
    pub fn driver(&self) -> Driver {
        self.driver
    }

    /// True if the driving phone's clutch is engaged: a phone drives exactly while its clutch is in (every
    /// way out of driving disengages; the property test checks it after every input).
    pub fn engaged(&self) -> bool {
        self.driver == Driver::Teleop
    }

    /// The bound phone session.
    pub fn teleop_session(&self) -> Option<u64> {
        self.teleop_session
    }

    /// The policy session that owns (drives) the arm and its name.
    pub fn policy_owner(&self) -> Option<(u64, &str)> {
        self.policy
            .as_ref()
            .filter(|o| !o.waiting)
            .map(|o| (o.session, o.name.as_str()))
    }

    /// The policy session that waits for the operator to hand the arm back, and its name.
    pub fn waiting_policy(&self) -> Option<(u64, &str)> {
        self.policy
            .as_ref()
            .filter(|o| o.waiting)
            .map(|o| (o.session, o.name.as_str()))
    }

    /// When the operator last handed the arm back to the owning policy (chunks must answer later
    /// observations).
    pub fn handed_back_s(&self) -> Option<f64> {
        self.policy.as_ref().and_then(|o| o.handed_back_s)
    }

    /// What the driving policy is about to do from `from_s` on: its plan's remaining steps, thinned to at most
    /// `max_points` (evenly, keeping the first and the last). Empty while no policy plan plays. Only the
    /// points shown are read from the plan (a snapshot takes one for every phone feedback).
    pub fn plan_preview(&self, from_s: f64, max_points: usize) -> PlanPreview {
        let Some(plan) = self.policy_plan(from_s).filter(|p| !p.is_empty()) else {
            return PlanPreview::default();
        };
        if max_points == 0 {
            return PlanPreview::default();
        }
        let last = plan.len() - 1;
        let stride = plan.len().div_ceil(max_points);
        let mut picked: Vec<usize> = (0..plan.len()).step_by(stride).collect();
        // Where the plan ends matters most to the operator: it is always shown.
        if !last.is_multiple_of(stride) {
            if picked.len() == max_points {
                picked.pop();
            }
            picked.push(last);
        }
        let (positions_m, grippers) = picked
            .into_iter()
            .filter_map(|k| plan.get(k))
            .map(|s| -> ([f64; 3], f64) {
                (
                    s.robot_from_target.translation.vector.into(),
                    s.gripper.clamp(0.0, 1.0),
                )
            })
            .unzip();
        PlanPreview {
            positions_m,
            grippers,
            point_period_s: plan.period_s() * stride as f64,
        }
    }

    /// While a policy drives: its plan from `from_s` on, on the grid of its current step (see
    /// [`ChunkExecutor::plan`]); None otherwise.
    pub fn policy_plan(&self, from_s: f64) -> Option<Plan<'_>> {
        (self.driver == Driver::Policy).then(|| self.executor.plan(from_s))
    }

    /// [`Self::policy_plan`]'s steps, copied, and its period; empty (and period 0) while no policy drives.
    pub fn policy_plan_from(&self, from_s: f64) -> (Vec<ChunkStep>, f64) {
        self.policy_plan(from_s)
            .map_or((Vec::new(), 0.0), |plan| (plan.iter().collect(), plan.period_s()))
    }

    /// While the owning policy loads: the time its loading deadline passes (then the arm is released).
    pub fn policy_loading_until(&self) -> Option<f64> {
        self.policy
            .as_ref()
            .filter(|o| !o.waiting)
            .and_then(|o| o.loading_deadline_s)
    }

    /// The last target and gripper target handed out (the arm holds them).
    pub fn target(&self) -> (Isometry3<f64>, f64) {
        (self.target, self.gripper_target)
    }

    /// The decision on display.
    pub fn last_decision(&self) -> &GateDecision {
        &self.last_decision
    }

    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// The source driving the arm, if one does.
    pub fn owner(&self) -> Option<Owner> {
        match self.driver {
            Driver::None => None,
            Driver::Teleop => Some(Owner::Phone {
                session: self.teleop_session.unwrap_or_default(),
            }),
            Driver::Policy => Some(Owner::Policy {
                name: self.policy.as_ref().map(|o| o.name.clone()).unwrap_or_default(),
            }),
        }
    }

    /// Whether the arm may be teleported now (a scene reset that homes it): not while a source drives, whose
    /// plan would continue from a pose the arm left. Ask under the same lock as the teleport and the
    /// [`Input::Homed`] that follows it, so that no source starts driving in between.
    pub fn may_home(&self) -> Result<(), ArbiterError> {
        match self.owner() {
            None => Ok(()),
            Some(owner) => Err(ArbiterError::DrivenWhileHoming { owner }),
        }
    }

    /// How soon the next [`Input::Tick`] is needed. Between inputs nothing else can change the arm.
    pub fn tick_need(&self) -> TickNeed {
        match self.driver {
            Driver::Teleop => TickNeed::Periodic,
            Driver::Policy => match (&self.policy, self.executor.end_time_s()) {
                (_, Some(end_s)) if end_s > self.latest_s => TickNeed::Periodic,
                (
                    Some(PolicyOwner {
                        loading_deadline_s: Some(deadline_s),
                        ..
                    }),
                    _,
                ) => TickNeed::At(*deadline_s),
                // The silence timeout counts from the chunk's arrival or the end of the plan, whichever is
                // later; the tick at that moment revokes (with margin: the rule is "more than").
                (Some(owner), end_s) => TickNeed::At(
                    owner.last_chunk_s.max(end_s.unwrap_or(f64::NEG_INFINITY)) + owner.silence_timeout_s,
                ),
                (None, _) => TickNeed::Idle,
            },
            Driver::None => TickNeed::Idle,
        }
    }

    /// Applies one input at `now_s` with the bridge reporting `robot`.
    pub fn handle(&mut self, input: Input, robot: &Robot, now_s: f64) -> Result<Effects, ArbiterError> {
        // Inputs from several threads may arrive slightly out of clock order: the later time stands.
        self.latest_s = self.latest_s.max(now_s);
        let now = self.latest_s;
        let mut fx = Effects::default();
        match input {
            Input::BindTeleop { session, take_over } => self.bind_teleop(session, take_over, robot, now)?,
            Input::UnbindTeleop { session } => self.unbind_teleop(session, robot, now, &mut fx),
            Input::Teleop { session, round } => self.teleop_round(session, round, robot, now, &mut fx)?,
            Input::ClaimPolicy {
                session,
                name,
                silence_timeout_s,
            } => self.claim_policy(session, name, silence_timeout_s, robot, now, &mut fx)?,
            Input::ReleasePolicy { session, reason } => {
                if self.policy.as_ref().is_some_and(|o| o.session == session) {
                    self.revoke_policy(&reason, &mut fx);
                }
            }
            Input::PolicyLoading { session } => self.policy_loading(session, now, &mut fx)?,
            Input::Chunk {
                session,
                chunk,
                observed_s,
            } => {
                let owner = self.policy.as_ref().filter(|o| o.session == session);
                match owner {
                    Some(o) if o.waiting => {
                        return Err(ArbiterError::PolicyWaiting {
                            policy: o.name.clone(),
                        });
                    }
                    Some(o) if self.driver == Driver::Policy => {
                        // Not `<`: an observation taken at the very moment of the hand-back may predate it.
                        if let Some(back_s) = o.handed_back_s
                            && observed_s.partial_cmp(&back_s) != Some(std::cmp::Ordering::Greater)
                        {
                            return Err(ArbiterError::BeforeHandBack {
                                before_s: back_s - observed_s,
                            });
                        }
                    }
                    _ => return Err(ArbiterError::NotControlling),
                }
                fx.chunk = Some(self.executor.replace(chunk, now)?);
                if let Some(owner) = self.policy.as_mut() {
                    owner.last_chunk_s = now;
                    // The first chunk ends the loading: from here the silence timeout applies again.
                    owner.loading_deadline_s = None;
                }
                self.tick(now, &mut fx);
            }
            Input::Tick => self.tick(now, &mut fx),
            Input::Homed { gripper } => self.homed(gripper, robot, now, &mut fx)?,
        }
        Ok(fx)
    }

    fn send(&mut self, target: Isometry3<f64>, gripper: f64, fx: &mut Effects) {
        self.seq += 1;
        self.target = target;
        self.gripper_target = gripper;
        // The phone's gripper is the arm's: whoever sent this, the phone's next toggle or take-over continues
        // from it, never from a setting of its own that a policy has since overridden.
        self.teleop.adopt_gripper(gripper);
        self.counters.sent += 1;
        fx.commands.push(Command {
            seq: self.seq,
            robot_from_target: target,
            gripper,
        });
    }

    fn decide(&mut self, decision: GateDecision, fx: &mut Effects) {
        match decision.verdict {
            GateVerdict::RejectedJump | GateVerdict::RejectedInvalid => self.counters.rejected += 1,
            GateVerdict::Clamped => self.counters.clamped += 1,
            GateVerdict::Accepted | GateVerdict::HeldStale => {}
        }
        fx.decision = Some(decision.clone());
        self.last_decision = decision;
    }

    fn bind_teleop(
        &mut self,
        session: u64,
        take_over: bool,
        robot: &Robot,
        now: f64,
    ) -> Result<(), ArbiterError> {
        if self.teleop_session.is_some_and(|other| other != session) && !take_over {
            return Err(ArbiterError::PhoneBound);
        }
        self.teleop_session = Some(session);
        if self.driver == Driver::Teleop {
            // The replaced phone was driving: the new one starts disengaged.
            self.driver = Driver::None;
            self.teleop
                .clutch(ClutchKind::Disengage, None, robot.measured_or(self.target), now);
        }
        Ok(())
    }

    fn unbind_teleop(&mut self, session: u64, robot: &Robot, now: f64, fx: &mut Effects) {
        if self.teleop_session != Some(session) {
            return;
        }
        self.teleop_session = None;
        if self.driver == Driver::Teleop {
            self.driver = Driver::None;
            self.teleop
                .clutch(ClutchKind::Disengage, None, robot.measured_or(self.target), now);
            self.decide(
                GateDecision::note(GateVerdict::Accepted, "phone disconnected: the arm holds"),
                fx,
            );
        }
    }

    fn teleop_round(
        &mut self,
        session: u64,
        round: TeleopRound,
        robot: &Robot,
        now: f64,
        fx: &mut Effects,
    ) -> Result<(), ArbiterError> {
        if self.teleop_session != Some(session) {
            return Err(ArbiterError::PhoneReplaced);
        }
        let not_ready = robot.not_ready(now);
        let pose = match round.pose {
            Some(Ok(p)) => Some(p),
            Some(Err(e)) => {
                // A malformed pose (non-unit quaternion, NaN) is a refused command like any other: counted and
                // shown as the verdict, unless a policy drives and the verdict on display is its own.
                if self.driver != Driver::Policy {
                    self.decide(
                        GateDecision::note(GateVerdict::RejectedInvalid, format!("invalid phone pose: {e}")),
                        fx,
                    );
                }
                fx.phone_error = e;
                None
            }
            None => None,
        };
        for button in round.buttons {
            match button {
                TeleopButton::Clutch(kind) => self.clutch(kind, pose, robot, not_ready.as_ref(), now, fx),
                TeleopButton::Gripper(command) => {
                    if let Some(why) = &not_ready {
                        fx.phone_error = format!("the arm {}", ArbiterError::NotReady(why.clone()));
                        continue;
                    }
                    // The gripper follows the phone only while the phone drives or nobody does. A press while a
                    // policy drives changes nothing, not even the phone's setting: a take-over would send it.
                    if self.driver == Driver::Policy {
                        continue;
                    }
                    match self.teleop.gripper(command) {
                        Ok(gripper) => self.send(self.target, gripper, fx),
                        Err(e) => fx.phone_error = e.to_string(),
                    }
                }
                TeleopButton::HandBack => {
                    if let Err(e) = self.hand_back(robot, not_ready.as_ref(), now, fx) {
                        fx.phone_error = e;
                    }
                }
                TeleopButton::Invalid(message) => fx.phone_error = message,
            }
        }
        let measured = robot.measured_or(self.target);
        if self.driver == Driver::Teleop
            && let Some(why) = &not_ready
        {
            // The robot went away under the phone: stop driving and say so, rather than accept samples that
            // go nowhere (or, on reconnect, continue from a pose measured before).
            self.driver = Driver::None;
            self.teleop.clutch(ClutchKind::Disengage, None, measured, now);
            let message = format!(
                "the arm {}; disengaged, the arm holds",
                ArbiterError::NotReady(why.clone())
            );
            fx.phone_error.clone_from(&message);
            self.decide(GateDecision::note(GateVerdict::HeldStale, message), fx);
        }
        if let Some(phone) = pose {
            let step = self.teleop.on_pose(phone, round.tracking_ok, measured, now);
            if self.driver == Driver::Teleop {
                if let Some((target, gripper)) = step.command {
                    self.send(target, gripper, fx);
                }
                fx.reindexed |= step.reindexed;
                self.decide(step.decision, fx);
            }
        }
        Ok(())
    }

    fn clutch(
        &mut self,
        kind: ClutchKind,
        phone: Option<Isometry3<f64>>,
        robot: &Robot,
        not_ready: Option<&NotReady>,
        now: f64,
        fx: &mut Effects,
    ) {
        let engaging = match kind {
            ClutchKind::Engage => true,
            ClutchKind::Toggle => !self.teleop.engaged(),
            ClutchKind::Disengage => false,
        };
        if engaging && let Some(why) = not_ready {
            fx.phone_error = format!("the arm {}, not engaging", ArbiterError::NotReady(why.clone()));
            return;
        }
        let step = self
            .teleop
            .clutch(kind, phone, robot.measured_or(self.target), now);
        if step.engaged {
            if self.driver == Driver::Policy {
                self.pause_policy();
                fx.turn = self.policy.as_ref().map(|o| PolicyTurn {
                    session: o.session,
                    resumed: false,
                });
            }
            self.driver = Driver::Teleop;
            // Without a command (no pose at the press) the arm keeps holding the last target it was sent.
            if let Some((target, gripper)) = step.command {
                self.send(target, gripper, fx);
            }
            fx.reindexed |= step.reindexed;
        } else if self.driver == Driver::Teleop {
            self.driver = Driver::None;
        }
        self.decide(step.decision, fx);
    }

    /// The operator takes the arm from the driving policy: it waits, keeping the arm reserved, and nothing
    /// of its plan plays (see [`Self::hand_back`]).
    fn pause_policy(&mut self) {
        self.executor.clear();
        self.last_policy_step = None;
        if let Some(owner) = self.policy.as_mut() {
            owner.waiting = true;
        }
        if self.driver == Driver::Policy {
            self.driver = Driver::None;
        }
    }

    /// The operator hands the arm back to the waiting policy. Nothing is sent: the arm holds the last target
    /// until the policy's first chunk answering an observation taken after now (re-anchored on where the
    /// operator left the arm). The phone stops driving; the policy's silence timeout counts from now, and a
    /// policy that was loading starts over as if it had just claimed the arm.
    fn hand_back(
        &mut self,
        robot: &Robot,
        not_ready: Option<&NotReady>,
        now: f64,
        fx: &mut Effects,
    ) -> Result<(), String> {
        let Some(name) = self.waiting_policy().map(|(_, name)| name.to_owned()) else {
            return Err("no policy waits for this arm: nothing to hand back".to_owned());
        };
        if let Some(why) = not_ready {
            return Err(format!(
                "the arm {}, not handing back",
                ArbiterError::NotReady(why.clone())
            ));
        }
        let measured = robot.measured_or(self.target);
        if self.driver == Driver::Teleop {
            self.teleop.clutch(ClutchKind::Disengage, None, measured, now);
        }
        self.teleop.request_reindex();
        self.policy_gate.reset_reference_at(measured, now);
        self.executor.clear();
        self.last_policy_step = None;
        self.driver = Driver::Policy;
        if let Some(owner) = self.policy.as_mut() {
            owner.waiting = false;
            owner.handed_back_s = Some(now);
            owner.last_chunk_s = now;
            owner.loading_deadline_s = None;
            fx.turn = Some(PolicyTurn {
                session: owner.session,
                resumed: true,
            });
        }
        self.counters.handed_back += 1;
        fx.reindexed = true;
        self.decide(
            GateDecision::note(
                GateVerdict::Accepted,
                format!("handed back to policy {name}: the arm holds until its next chunk"),
            ),
            fx,
        );
        Ok(())
    }

    fn claim_policy(
        &mut self,
        session: u64,
        name: String,
        silence_timeout_s: f64,
        robot: &Robot,
        now: f64,
        fx: &mut Effects,
    ) -> Result<(), ArbiterError> {
        if self.driver == Driver::Teleop {
            return Err(ArbiterError::DrivenByPhone);
        }
        if let Some(why) = robot.not_ready(now) {
            return Err(ArbiterError::NotReady(why));
        }
        if let Some(owner) = &self.policy {
            if owner.session != session {
                return Err(ArbiterError::NotOwner {
                    owner: owner.name.clone(),
                });
            }
            // Only the operator's hand-back ends the wait.
            if owner.waiting {
                return Err(ArbiterError::PolicyWaiting {
                    policy: owner.name.clone(),
                });
            }
        }
        self.policy_gate
            .reset_reference_at(robot.measured_or(self.target), now);
        self.executor.clear();
        self.last_policy_step = None;
        self.driver = Driver::Policy;
        // The phone's floating zero is stale once a policy moves the arm. (Every way out of phone driving
        // already disengages, which re-indexes too; this keeps the rule true without relying on that.)
        self.teleop.request_reindex();
        fx.reindexed = true;
        let note = GateDecision::note(GateVerdict::Accepted, format!("policy {name} in control"));
        // Claiming again does not lift a hand-back's rule: the chunk that drives must still answer an
        // observation taken after the hand-back.
        let handed_back_s = self
            .policy
            .as_ref()
            .filter(|o| o.session == session)
            .and_then(|o| o.handed_back_s);
        self.policy = Some(PolicyOwner {
            session,
            name,
            silence_timeout_s,
            last_chunk_s: now,
            loading_deadline_s: None,
            waiting: false,
            handed_back_s,
        });
        self.decide(note, fx);
        Ok(())
    }

    fn policy_loading(&mut self, session: u64, now: f64, fx: &mut Effects) -> Result<(), ArbiterError> {
        let limit_s = self.executor.config().max_loading_s;
        let owner = match self.policy.as_mut() {
            Some(owner) if owner.session == session && owner.waiting => {
                return Err(ArbiterError::PolicyWaiting {
                    policy: owner.name.clone(),
                });
            }
            Some(owner) if owner.session == session && self.driver == Driver::Policy => owner,
            _ => return Err(ArbiterError::NotControlling),
        };
        if owner.loading_deadline_s.is_some() {
            // A keep-alive: the deadline stays where the first loading message put it.
            return Ok(());
        }
        owner.loading_deadline_s = Some(now + limit_s);
        let note = format!(
            "policy {} loading (up to {limit_s:.0} s): the arm holds",
            owner.name
        );
        self.decide(GateDecision::note(GateVerdict::Accepted, note), fx);
        Ok(())
    }

    fn revoke_policy(&mut self, reason: &str, fx: &mut Effects) {
        self.executor.clear();
        self.last_policy_step = None;
        if self.driver == Driver::Policy {
            self.driver = Driver::None;
        }
        if let Some(owner) = self.policy.take() {
            fx.revoked = Some(Revocation {
                session: owner.session,
                policy: owner.name,
                reason: reason.to_owned(),
            });
        }
    }

    fn homed(&mut self, gripper: f64, robot: &Robot, now: f64, fx: &mut Effects) -> Result<(), ArbiterError> {
        self.may_home()?;
        // Without a measured pose there is nothing to hold: the arm keeps its target.
        let Some(measured) = robot.feedback else {
            return Ok(());
        };
        self.target = measured.robot_from_ee;
        self.gripper_target = gripper;
        self.teleop.adopt_gripper(gripper);
        self.executor.clear();
        self.last_policy_step = None;
        self.teleop.request_reindex();
        self.policy_gate.reset_reference_at(measured.robot_from_ee, now);
        fx.reindexed = true;
        Ok(())
    }

    fn tick(&mut self, now: f64, fx: &mut Effects) {
        match self.driver {
            Driver::Policy => self.tick_policy(now, fx),
            Driver::Teleop => {
                if let Some(decision) = self.teleop.check_stale(now) {
                    self.decide(decision, fx);
                }
            }
            Driver::None => {}
        }
    }

    fn tick_policy(&mut self, now: f64, fx: &mut Effects) {
        if let Some(step) = self.executor.target_at(now) {
            // Silence counts from when the policy's plan runs out, not from the chunk's arrival.
            if let Some(owner) = self.policy.as_mut() {
                owner.last_chunk_s = owner.last_chunk_s.max(now);
            }
            if self.last_policy_step != Some(step) {
                self.last_policy_step = Some(step);
                let (gated, decision) = self.policy_gate.check(step.robot_from_target, now);
                if let Some(target) = gated {
                    self.send(target, step.gripper.clamp(0.0, 1.0), fx);
                }
                self.decide(decision, fx);
            }
            return;
        }
        let loading = self.policy.as_ref().and_then(|o| {
            o.loading_deadline_s
                .map(|deadline_s| (deadline_s, o.name.clone()))
        });
        if let Some((deadline_s, name)) = loading {
            if now > deadline_s {
                let limit_s = self.executor.config().max_loading_s;
                let why = format!(
                    "still loading after the {limit_s:.0} s loading limit (chunk.max_loading_s) without a chunk"
                );
                self.revoke_policy(&why, fx);
                self.decide(
                    GateDecision::note(GateVerdict::HeldStale, format!("policy {name} {why}: holding")),
                    fx,
                );
            }
            // Loading: the silence timeout waits for the deadline.
            return;
        }
        let silent = self
            .policy
            .as_ref()
            .map(|o| (now - o.last_chunk_s, o.silence_timeout_s));
        if let Some((silent_s, timeout_s)) = silent
            && silent_s > timeout_s
        {
            self.revoke_policy(&format!("silent for {silent_s:.2} s"), fx);
            self.decide(
                GateDecision::note(
                    GateVerdict::HeldStale,
                    format!("policy silent for {silent_s:.2} s: holding"),
                ),
                fx,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::angle_between_rad;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use proptest::prelude::*;

    // Not 1: a session accessor that made up `Some(1)` would pass every test with a phone numbered 1.
    const PHONE: u64 = 41;
    const POLICY: u64 = 7;

    fn at(x: f64, y: f64, z: f64) -> Isometry3<f64> {
        Isometry3::translation(x, y, z)
    }

    fn assert_close(a: &Isometry3<f64>, b: &Isometry3<f64>) {
        let m = (a.translation.vector - b.translation.vector).norm();
        let rad = angle_between_rad(&a.rotation, &b.rotation);
        assert!(m < 1e-9 && rad < 1e-9, "{a:?} is {m} m, {rad} rad from {b:?}");
    }

    fn home() -> Isometry3<f64> {
        at(0.25, 0.0, 0.2)
    }

    fn arbiter() -> Arbiter {
        Arbiter::new(&TeleopConfig::default(), ChunkConfig::default(), home(), 0.0).unwrap()
    }

    /// A ready bridge measuring `pose` at `now_s`.
    fn ready(pose: Isometry3<f64>, now_s: f64) -> Robot {
        Robot {
            health: BridgeHealth::Ready,
            feedback: Some(Measured {
                robot_from_ee: pose,
                capture_time_s: now_s,
            }),
        }
    }

    fn bind_phone() -> Input {
        Input::BindTeleop {
            session: PHONE,
            take_over: false,
        }
    }

    /// Phone `session` binds, taking over from any other phone.
    fn take_over(session: u64) -> Input {
        Input::BindTeleop {
            session,
            take_over: true,
        }
    }

    fn round(pose: Option<Isometry3<f64>>, buttons: Vec<TeleopButton>) -> Input {
        Input::Teleop {
            session: PHONE,
            round: TeleopRound {
                pose: pose.map(Ok),
                tracking_ok: true,
                buttons,
            },
        }
    }

    fn engage(phone: Isometry3<f64>) -> Input {
        round(Some(phone), vec![TeleopButton::Clutch(ClutchKind::Engage)])
    }

    fn claim() -> Input {
        Input::ClaimPolicy {
            session: POLICY,
            name: "p".into(),
            silence_timeout_s: 0.5,
        }
    }

    fn chunk(anchor_s: f64, targets: &[Isometry3<f64>]) -> Input {
        crate::test_support::chunk_input(POLICY, anchor_s, targets)
    }

    /// An arbiter with a bound, disengaged phone, driven by a policy from `home()` since t = 1.
    fn phone_bound_policy_driving() -> (Arbiter, Robot) {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        a.handle(claim(), &robot, 1.0).unwrap();
        (a, robot)
    }

    /// An arbiter with a bound phone, driven by the phone from `home()` at t = 1.
    fn phone_driving() -> Arbiter {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        let fx = a.handle(engage(Isometry3::identity()), &robot, 1.0).unwrap();
        assert_eq!(a.driver(), Driver::Teleop);
        assert!(fx.reindexed);
        a
    }

    #[test]
    fn readiness_names_the_reason_the_arm_may_not_move() {
        let measured = |capture_time_s| {
            Some(Measured {
                robot_from_ee: home(),
                capture_time_s,
            })
        };
        let robot = |health, feedback| Robot { health, feedback };
        // A bridge still connecting that already measured a pose is not ready because it connects; one that
        // measured nothing yet is not ready because nothing was measured (the more useful reason).
        assert_eq!(
            robot(BridgeHealth::Connecting, measured(1.0)).not_ready(1.0),
            Some(NotReady::Connecting)
        );
        assert_eq!(
            robot(BridgeHealth::Connecting, None).not_ready(1.0),
            Some(NotReady::NoFeedback)
        );
        assert_eq!(
            robot(BridgeHealth::Ready, None).not_ready(1.0),
            Some(NotReady::NoFeedback)
        );
        // 0.75 s old at t = 3 is fresh (a ratio, 3 / 2.25, would read as stale); 1.5 s old is stale, and says
        // how old.
        assert_eq!(robot(BridgeHealth::Ready, measured(2.25)).not_ready(3.0), None);
        assert_eq!(
            robot(BridgeHealth::Ready, measured(1.5)).not_ready(3.0),
            Some(NotReady::StaleFeedback { age_s: 1.5 })
        );
        assert_eq!(
            robot(BridgeHealth::Disconnected("cable".into()), measured(3.0)).not_ready(3.0),
            Some(NotReady::Disconnected("cable".into()))
        );
    }

    #[test]
    fn engaged_only_while_the_phone_drives_with_its_clutch_in() {
        let mut a = phone_driving();
        assert!(a.engaged());
        let robot = ready(home(), 1.1);
        a.handle(
            round(
                Some(Isometry3::identity()),
                vec![TeleopButton::Clutch(ClutchKind::Disengage)],
            ),
            &robot,
            1.1,
        )
        .unwrap();
        assert_eq!(a.teleop_session(), Some(PHONE));
        assert!(!a.engaged(), "clutch out: the phone floats, the arm holds");
        let (b, _) = phone_bound_policy_driving();
        assert_eq!(b.driver(), Driver::Policy);
        assert!(!b.engaged(), "a policy drives: no phone is engaged");
    }

    #[test]
    fn a_second_phone_is_refused_unless_it_takes_over_and_then_starts_disengaged() {
        let mut a = phone_driving();
        let robot = ready(home(), 1.1);
        let err = a.handle(
            Input::BindTeleop {
                session: 2,
                take_over: false,
            },
            &robot,
            1.1,
        );
        assert_eq!(err, Err(ArbiterError::PhoneBound));
        assert_eq!(a.teleop_session(), Some(PHONE));
        a.handle(take_over(2), &robot, 1.1).unwrap();
        assert_eq!(a.driver(), Driver::None);
        assert!(!a.engaged());
        // The replaced phone's samples are refused from now on.
        let err = a.handle(round(Some(Isometry3::identity()), vec![]), &robot, 1.1);
        assert_eq!(err, Err(ArbiterError::PhoneReplaced));
    }

    #[test]
    fn the_phone_moves_the_arm_relative_to_where_it_was_engaged() {
        let mut a = phone_driving();
        let fx = a
            .handle(
                round(Some(at(0.01, 0.0, 0.0)), vec![]),
                &ready(home(), 1.02),
                1.02,
            )
            .unwrap();
        assert_eq!(fx.commands.len(), 1);
        let moved = fx.commands[0].robot_from_target.translation.vector - home().translation.vector;
        assert!((moved.norm() - 0.01).abs() < 1e-9, "{moved:?}");
    }

    #[test]
    fn a_policy_cannot_claim_while_a_phone_drives() {
        let mut a = phone_driving();
        let err = a.handle(claim(), &ready(home(), 1.1), 1.1);
        assert_eq!(err, Err(ArbiterError::DrivenByPhone));
        assert_eq!(a.driver(), Driver::Teleop);
    }

    #[test]
    fn a_second_policy_is_refused_and_names_the_owner() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let err = a.handle(
            Input::ClaimPolicy {
                session: 8,
                name: "q".into(),
                silence_timeout_s: 1.0,
            },
            &robot,
            1.0,
        );
        assert_eq!(err, Err(ArbiterError::NotOwner { owner: "p".into() }));
        let err = a.handle(
            Input::Chunk {
                session: 8,
                chunk: ActionChunk {
                    steps: vec![],
                    anchor_time_s: 1.0,
                    step_period_s: 0.1,
                },
                observed_s: 1.0,
            },
            &robot,
            1.0,
        );
        assert_eq!(err, Err(ArbiterError::NotControlling));
    }

    #[test]
    fn nothing_starts_moving_without_a_fresh_measured_pose() {
        let stale = ready(home(), 1.0);
        let now_s = 1.0 + FEEDBACK_MAX_AGE_S + 0.01;
        let mut a = arbiter();
        assert!(matches!(
            a.handle(claim(), &stale, now_s),
            Err(ArbiterError::NotReady(NotReady::StaleFeedback { .. }))
        ));
        let unhealthy = Robot {
            health: BridgeHealth::Disconnected("gone".into()),
            ..ready(home(), now_s)
        };
        assert!(matches!(
            a.handle(claim(), &unhealthy, now_s),
            Err(ArbiterError::NotReady(NotReady::Disconnected(_)))
        ));
        let blind = Robot {
            health: BridgeHealth::Ready,
            feedback: None,
        };
        assert_eq!(a.handle(claim(), &blind, now_s), Err(NotReady::NoFeedback.into()));
        a.handle(bind_phone(), &stale, now_s).unwrap();
        let fx = a.handle(engage(Isometry3::identity()), &stale, now_s).unwrap();
        assert!(fx.phone_error.contains("not engaging"), "{fx:?}");
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Gripper(GripperCommand::Set(1.0))]),
                &stale,
                now_s,
            )
            .unwrap();
        assert!(fx.phone_error.contains("not ready"), "{fx:?}");
        assert!(fx.commands.is_empty());
        assert_eq!(a.driver(), Driver::None);
        assert_eq!(a.counters().sent, 0);
    }

    #[test]
    fn a_phone_driving_when_the_robot_goes_away_is_disengaged() {
        let mut a = phone_driving();
        let gone = Robot {
            health: BridgeHealth::Error("estop".into()),
            ..ready(home(), 1.1)
        };
        let fx = a
            .handle(round(Some(at(0.01, 0.0, 0.0)), vec![]), &gone, 1.1)
            .unwrap();
        assert!(fx.commands.is_empty());
        assert_eq!(a.driver(), Driver::None);
        assert_eq!(a.last_decision().verdict, GateVerdict::HeldStale);
        // The phone is told, not only the status display.
        assert!(
            fx.phone_error.contains("estop") && fx.phone_error.contains("disengaged"),
            "{fx:?}"
        );
    }

    #[test]
    fn the_operator_takes_over_from_a_policy_which_waits_without_driving() {
        let (mut a, robot) = phone_bound_policy_driving();
        a.handle(chunk(1.0, &[at(0.26, 0.0, 0.2); 10]), &robot, 1.0)
            .unwrap();
        let moved = at(0.26, 0.0, 0.2);
        let fx = a
            .handle(engage(Isometry3::identity()), &ready(moved, 1.05), 1.05)
            .unwrap();
        assert_eq!(a.driver(), Driver::Teleop);
        assert_eq!(fx.revoked, None, "the policy keeps the arm reserved");
        assert_eq!(a.waiting_policy(), Some((POLICY, "p")));
        assert_eq!(a.policy_owner(), None);
        assert_eq!(a.plan_preview(1.05, 16), PlanPreview::default(), "no plan plays");
        // Re-indexed at the measured pose: the first command is where the arm is.
        assert_close(&fx.commands.last().unwrap().robot_from_target, &moved);
        // The paused chunk does not play on, and new chunks are refused with the reason.
        let fx = a.handle(Input::Tick, &ready(moved, 1.3), 1.3).unwrap();
        assert!(fx.commands.is_empty());
        assert_eq!(
            a.handle(chunk(1.3, &[moved]), &robot, 1.3),
            Err(ArbiterError::PolicyWaiting { policy: "p".into() })
        );
        // Another policy cannot take the reserved arm, even once the phone lets go.
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &robot,
            1.35,
        )
        .unwrap();
        assert_eq!(a.driver(), Driver::None);
        assert_eq!(
            a.handle(
                Input::ClaimPolicy {
                    session: POLICY + 1,
                    name: "q".into(),
                    silence_timeout_s: 1.0,
                },
                &robot,
                1.4
            ),
            Err(ArbiterError::NotOwner { owner: "p".into() })
        );
        // Its session ending frees the arm.
        let fx = a
            .handle(
                Input::ReleasePolicy {
                    session: POLICY,
                    reason: "session ended".into(),
                },
                &robot,
                1.5,
            )
            .unwrap();
        assert_eq!(fx.revoked.map(|r| r.session), Some(POLICY));
        assert_eq!(a.waiting_policy(), None);
    }

    fn hand_back() -> Input {
        round(None, vec![TeleopButton::HandBack])
    }

    /// A policy drove, the phone took over at t = 1.05 and moved the arm 2 cm along +y (measured there).
    fn policy_waiting_after_a_correction() -> (Arbiter, Isometry3<f64>) {
        let (mut a, robot) = phone_bound_policy_driving();
        a.handle(chunk(1.0, &[at(0.26, 0.0, 0.2); 10]), &robot, 1.0)
            .unwrap();
        let engaged_at = at(0.25, 0.0, 0.2);
        a.handle(engage(Isometry3::identity()), &ready(engaged_at, 1.05), 1.05)
            .unwrap();
        // The phone's +x maps to the robot's +y by default? Whatever the mapping, the phone moves the arm.
        let fx = a
            .handle(
                round(Some(at(0.02, 0.0, 0.0)), vec![]),
                &ready(engaged_at, 1.1),
                1.1,
            )
            .unwrap();
        let corrected = fx.commands.last().expect("the phone drives").robot_from_target;
        assert!((corrected.translation.vector - engaged_at.translation.vector).norm() > 0.019);
        (a, corrected)
    }

    /// The session hears both turns: it waits from the take-over, drives again from the hand-back.
    #[test]
    fn a_take_over_and_a_hand_back_tell_the_policy_session() {
        let (mut a, robot) = phone_bound_policy_driving();
        a.handle(chunk(1.0, &[at(0.26, 0.0, 0.2); 10]), &robot, 1.0)
            .unwrap();
        let fx = a
            .handle(engage(Isometry3::identity()), &ready(home(), 1.05), 1.05)
            .unwrap();
        let paused = PolicyTurn {
            session: POLICY,
            resumed: false,
        };
        assert_eq!(fx.turn, Some(paused));
        // Engaging again while the phone already drives is no new turn.
        let fx = a
            .handle(engage(Isometry3::identity()), &ready(home(), 1.06), 1.06)
            .unwrap();
        assert_eq!(fx.turn, None);
        let fx = a.handle(hand_back(), &ready(home(), 2.0), 2.0).unwrap();
        assert_eq!(
            fx.turn,
            Some(PolicyTurn {
                session: POLICY,
                resumed: true,
            })
        );
        // A phone with no policy behind it engages without a turn.
        let mut b = arbiter();
        b.handle(bind_phone(), &ready(home(), 1.0), 1.0).unwrap();
        let fx = b
            .handle(engage(Isometry3::identity()), &ready(home(), 1.1), 1.1)
            .unwrap();
        assert_eq!(fx.turn, None);
    }

    #[test]
    fn a_hand_back_holds_the_arm_until_a_chunk_answers_a_newer_observation() {
        let (mut a, corrected) = policy_waiting_after_a_correction();
        let robot = ready(corrected, 2.0);
        let fx = a.handle(hand_back(), &robot, 2.0).unwrap();
        assert_eq!(fx.phone_error, "");
        assert!(fx.commands.is_empty(), "a hand-back never moves the arm");
        assert_eq!(a.driver(), Driver::Policy);
        assert!(!a.engaged(), "the phone stopped driving");
        assert_eq!(a.policy_owner(), Some((POLICY, "p")));
        assert_eq!(a.handed_back_s(), Some(2.0));
        assert_eq!(a.counters().handed_back, 1);
        assert!(a.last_decision().reason.contains("handed back to policy p"));
        assert_close(&a.target().0, &corrected);
        // Time passes: the arm holds, the old plan is gone.
        for t in [2.05, 2.1, 2.2] {
            assert!(a.handle(Input::Tick, &robot, t).unwrap().commands.is_empty());
        }
        // A chunk answering an observation from before the hand-back (or at its very moment) is refused and
        // changes nothing.
        for observed_s in [1.9, 2.0] {
            let mut stale = chunk(2.2, &[at(0.26, 0.0, 0.2)]);
            if let Input::Chunk { observed_s: o, .. } = &mut stale {
                *o = observed_s;
            }
            assert!(matches!(
                a.handle(stale, &robot, 2.2),
                Err(ArbiterError::BeforeHandBack { before_s }) if (before_s - (2.0 - observed_s)).abs() < 1e-12
            ));
            assert!(a.handle(Input::Tick, &robot, 2.25).unwrap().commands.is_empty());
        }
        // The first chunk answering a newer observation drives.
        let next = Isometry3::translation(0.002, 0.0, 0.0) * corrected;
        let fx = a.handle(chunk(2.3, &[next, next]), &robot, 2.3).unwrap();
        assert_eq!(fx.commands.len(), 1);
        assert_close(&fx.commands[0].robot_from_target, &next);
    }

    /// The handed-back session claiming the arm again (it already holds it) keeps the hand-back's rule.
    #[test]
    fn claiming_again_after_a_hand_back_still_needs_a_newer_observation() {
        let (mut a, corrected) = policy_waiting_after_a_correction();
        let robot = ready(corrected, 2.0);
        a.handle(hand_back(), &robot, 2.0).unwrap();
        a.handle(claim(), &robot, 2.1).unwrap();
        assert_eq!(a.handed_back_s(), Some(2.0));
        let mut stale = chunk(2.2, &[at(0.26, 0.0, 0.2)]);
        if let Input::Chunk { observed_s, .. } = &mut stale {
            *observed_s = 2.0;
        }
        assert!(matches!(
            a.handle(stale, &robot, 2.2),
            Err(ArbiterError::BeforeHandBack { .. })
        ));
        assert!(a.handle(Input::Tick, &robot, 2.25).unwrap().commands.is_empty());
    }

    #[test]
    fn a_hand_back_needs_a_waiting_policy_and_a_ready_robot() {
        let mut a = phone_driving();
        let robot = ready(home(), 1.1);
        let fx = a.handle(hand_back(), &robot, 1.1).unwrap();
        assert!(fx.phone_error.contains("no policy waits"), "{fx:?}");
        assert_eq!(a.driver(), Driver::Teleop, "nothing changed");

        let (mut a, corrected) = policy_waiting_after_a_correction();
        let stale = ready(corrected, 1.0);
        let fx = a.handle(hand_back(), &stale, 3.0).unwrap();
        assert!(fx.phone_error.contains("not ready"), "{fx:?}");
        assert_eq!(a.waiting_policy(), Some((POLICY, "p")));
        assert_eq!(a.counters().handed_back, 0);
    }

    #[test]
    fn a_handed_back_policy_is_silent_from_the_hand_back_and_the_operator_can_take_it_again() {
        let (mut a, corrected) = policy_waiting_after_a_correction();
        let robot = ready(corrected, 5.0);
        a.handle(hand_back(), &robot, 5.0).unwrap();
        assert_eq!(
            a.tick_need(),
            TickNeed::At(5.5),
            "silence counts from the hand-back"
        );
        // The operator takes it again before the policy answered: it waits again.
        let fx = a.handle(engage(Isometry3::identity()), &robot, 5.2).unwrap();
        assert_eq!(fx.revoked, None);
        assert_eq!(a.waiting_policy(), Some((POLICY, "p")));
        // Handed back again, and silent past its timeout: it loses the arm, which holds.
        a.handle(hand_back(), &robot, 5.3).unwrap();
        let fx = a.handle(Input::Tick, &robot, 5.9).unwrap();
        assert!(fx.commands.is_empty());
        assert!(fx.revoked.unwrap().reason.contains("silent"));
        assert_eq!(a.counters().handed_back, 2);
    }

    #[test]
    fn the_preview_shows_at_most_the_asked_points_of_the_remaining_plan_ending_with_its_last() {
        let (mut a, robot) = phone_bound_policy_driving();
        let targets: Vec<_> = (0..40)
            .map(|k| at(0.25 + 0.001 * f64::from(k), 0.0, 0.2))
            .collect();
        a.handle(chunk(1.0, &targets), &robot, 1.0).unwrap();
        // At 1.0 all 40 steps remain: every third (stride 3) from the first, which ends on the last (39).
        let p = a.plan_preview(1.0, 16);
        assert_eq!(p.positions_m.len(), 14);
        assert!((p.positions_m[0][0] - 0.25).abs() < 1e-12);
        assert!((p.positions_m[1][0] - 0.253).abs() < 1e-12);
        assert!((p.positions_m.last().unwrap()[0] - 0.289).abs() < 1e-12);
        assert!((p.point_period_s - 0.3).abs() < 1e-12);
        assert_eq!(p.grippers, vec![0.5; 14]);
        // Half way: the 20 remaining steps 20..=39, every second (20, 22, .., 38) and then the last.
        let p = a.plan_preview(3.0, 16);
        assert!((p.positions_m[0][0] - 0.27).abs() < 1e-12);
        assert!((p.positions_m[9][0] - 0.288).abs() < 1e-12);
        assert!((p.positions_m.last().unwrap()[0] - 0.289).abs() < 1e-12);
        assert_eq!(p.positions_m.len(), 11);
        // Few steps: all of them.
        let p = a.plan_preview(4.75, 16);
        assert_eq!(p.positions_m.len(), 3);
        assert_eq!(
            a.plan_preview(9.0, 16),
            PlanPreview::default(),
            "the plan is over"
        );
    }

    /// The preview reads only the points it shows; it shows what thinning the whole copied plan shows, for
    /// plans of every length up to 3 × 16 points and every point budget up to 17, read mid-step.
    #[test]
    fn the_preview_picks_the_same_points_as_thinning_the_copied_plan() {
        fn thinned(plan: &[ChunkStep], period_s: f64, max_points: usize) -> PlanPreview {
            if plan.is_empty() || max_points == 0 {
                return PlanPreview::default();
            }
            let last = plan.len() - 1;
            let stride = plan.len().div_ceil(max_points);
            let mut picked: Vec<&ChunkStep> = plan.iter().step_by(stride).collect();
            if !last.is_multiple_of(stride) {
                if picked.len() == max_points {
                    picked.pop();
                }
                picked.push(&plan[last]);
            }
            PlanPreview {
                positions_m: picked
                    .iter()
                    .map(|s| s.robot_from_target.translation.vector.into())
                    .collect(),
                grippers: picked.iter().map(|s| s.gripper.clamp(0.0, 1.0)).collect(),
                point_period_s: period_s * stride as f64,
            }
        }
        for len in 1..=48u32 {
            let (mut a, robot) = phone_bound_policy_driving();
            let targets: Vec<_> = (0..len)
                .map(|k| at(0.25 + 0.001 * f64::from(k), 0.0, 0.2))
                .collect();
            a.handle(chunk(1.0, &targets), &robot, 1.0).unwrap();
            let from_s = 1.03;
            let (plan, period_s) = a.policy_plan_from(from_s);
            assert_eq!(plan.len(), len as usize);
            for max_points in 0..=17 {
                assert_eq!(
                    a.plan_preview(from_s, max_points),
                    thinned(&plan, period_s, max_points),
                    "{len} steps, {max_points} points"
                );
            }
        }
    }

    #[test]
    fn engaging_without_a_pose_keeps_holding_the_last_target_sent() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        a.handle(claim(), &robot, 1.0).unwrap();
        let moved = at(0.28, 0.0, 0.2);
        a.handle(chunk(1.0, &[moved; 3]), &robot, 1.0).unwrap();
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Clutch(ClutchKind::Engage)]),
                &ready(moved, 1.1),
                1.1,
            )
            .unwrap();
        assert!(fx.commands.is_empty());
        // A gripper press now must not send the phone's old target (where it was before the policy moved).
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Gripper(GripperCommand::Set(1.0))]),
                &ready(moved, 1.1),
                1.1,
            )
            .unwrap();
        assert_eq!(fx.commands.len(), 1);
        assert_eq!(fx.commands[0].robot_from_target, moved);
        // The first pose after the press is the phone's new zero: the round says it re-indexed (the recorder
        // marks it), and the arm stays where it is.
        let fx = a
            .handle(round(Some(at(0.5, 0.5, 0.5)), vec![]), &ready(moved, 1.12), 1.12)
            .unwrap();
        assert!(fx.reindexed, "{fx:?}");
        assert_close(&fx.commands[0].robot_from_target, &moved);
    }

    #[test]
    fn a_phone_after_a_policy_starts_from_the_measured_pose_not_its_old_offset() {
        let mut a = phone_driving();
        let robot = ready(home(), 1.0);
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &robot,
            1.0,
        )
        .unwrap();
        a.handle(claim(), &robot, 1.0).unwrap();
        let moved = at(0.28, 0.0, 0.2);
        a.handle(chunk(1.0, &[moved; 3]), &robot, 1.0).unwrap();
        a.handle(
            Input::ReleasePolicy {
                session: POLICY,
                reason: "done".into(),
            },
            &robot,
            1.2,
        )
        .unwrap();
        // Engage with the phone where it was: the arm must stay where the policy left it.
        let fx = a
            .handle(engage(Isometry3::identity()), &ready(moved, 1.3), 1.3)
            .unwrap();
        assert_close(&fx.commands.last().unwrap().robot_from_target, &moved);
    }

    #[test]
    fn a_policy_is_gated_from_where_the_phone_left_the_arm() {
        let mut a = phone_driving();
        let mut measured = home();
        for k in 1..=10 {
            let now_s = 1.0 + f64::from(k) * 0.02;
            let fx = a
                .handle(
                    round(Some(at(0.01 * f64::from(k), 0.0, 0.0)), vec![]),
                    &ready(measured, now_s),
                    now_s,
                )
                .unwrap();
            measured = fx.commands[0].robot_from_target;
        }
        let robot = ready(measured, 1.3);
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &robot,
            1.3,
        )
        .unwrap();
        a.handle(claim(), &robot, 1.3).unwrap();
        // A step back to where the arm was 10 cm ago is a jump from where it is now.
        let fx = a.handle(chunk(1.3, &[home()]), &robot, 1.3).unwrap();
        assert!(fx.commands.is_empty(), "{fx:?}");
        assert_eq!(a.last_decision().verdict, GateVerdict::RejectedJump);
    }

    #[test]
    fn a_policy_holds_when_its_plan_runs_out_and_loses_the_arm_when_silent() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let fx = a
            .handle(
                chunk(1.0, &[at(0.251, 0.0, 0.2), at(0.252, 0.0, 0.2)]),
                &robot,
                1.0,
            )
            .unwrap();
        assert_eq!(fx.commands.len(), 1, "the due step plays at once");
        assert_eq!(a.tick_need(), TickNeed::Periodic);
        assert_eq!(a.handle(Input::Tick, &robot, 1.1).unwrap().commands.len(), 1);
        // Plan over (ended at 1.2): hold, then revoke once silent for more than 0.5 s.
        assert!(a.handle(Input::Tick, &robot, 1.25).unwrap().commands.is_empty());
        let TickNeed::At(deadline_s) = a.tick_need() else {
            panic!("{:?}", a.tick_need());
        };
        assert!((deadline_s - 1.7).abs() < 0.051, "{deadline_s}");
        let fx = a.handle(Input::Tick, &robot, 1.6).unwrap();
        assert!(fx.revoked.is_none() && fx.commands.is_empty());
        let fx = a.handle(Input::Tick, &robot, deadline_s + 1e-6).unwrap();
        assert_eq!(fx.revoked.map(|r| r.session), Some(POLICY));
        assert_eq!(a.driver(), Driver::None);
        assert_eq!(a.tick_need(), TickNeed::Idle);
    }

    fn loading() -> Input {
        Input::PolicyLoading { session: POLICY }
    }

    #[test]
    fn a_loading_policy_holds_the_arm_past_its_silence_timeout_until_its_first_chunk() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let fx = a.handle(loading(), &robot, 1.0).unwrap();
        assert!(fx.commands.is_empty(), "loading never moves the arm");
        assert!(
            a.last_decision().reason.contains("loading"),
            "{:?}",
            a.last_decision()
        );
        assert_eq!(a.policy_loading_until(), Some(301.0));
        assert_eq!(a.tick_need(), TickNeed::At(301.0));
        // Three minutes of loading (silence timeout 0.5 s): the arm holds, the policy keeps it.
        for t in [1.6, 60.0, 181.0] {
            let fx = a.handle(Input::Tick, &ready(home(), t), t).unwrap();
            assert!(fx.revoked.is_none() && fx.commands.is_empty(), "{t}: {fx:?}");
        }
        assert_eq!(a.driver(), Driver::Policy);
        // The first chunk drives and ends the loading; silence counts again after its plan.
        let robot = ready(home(), 181.0);
        let fx = a
            .handle(chunk(181.0, &[at(0.251, 0.0, 0.2)]), &robot, 181.0)
            .unwrap();
        assert_eq!(fx.commands.len(), 1);
        assert_eq!(a.policy_loading_until(), None);
        let fx = a.handle(Input::Tick, &robot, 182.0).unwrap();
        assert!(fx.revoked.is_some(), "silent again after the plan: revoked");
    }

    #[test]
    fn loading_is_bounded_from_the_first_message_and_keep_alives_do_not_extend_it() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        a.handle(loading(), &robot, 1.0).unwrap();
        // Keep-alives every minute do not move the deadline.
        for t in [60.0, 120.0, 240.0, 300.0] {
            a.handle(loading(), &ready(home(), t), t).unwrap();
            assert_eq!(a.policy_loading_until(), Some(301.0));
        }
        assert!(a.handle(Input::Tick, &robot, 301.0).unwrap().revoked.is_none());
        let fx = a.handle(Input::Tick, &robot, 301.001).unwrap();
        let revoked = fx.revoked.expect("released past the loading limit");
        assert!(
            revoked.reason.contains("300 s loading limit"),
            "{}",
            revoked.reason
        );
        assert_eq!(a.driver(), Driver::None);
        assert!(
            a.last_decision().reason.contains("loading limit"),
            "{:?}",
            a.last_decision()
        );
        assert!(fx.commands.is_empty(), "released holding, not moving");
        // Its late chunk is refused.
        assert_eq!(
            a.handle(chunk(302.0, &[at(0.251, 0.0, 0.2)]), &robot, 302.0),
            Err(ArbiterError::NotControlling)
        );
    }

    #[test]
    fn the_operator_takes_over_from_a_loading_policy_and_others_cannot_claim_its_loading() {
        let (mut a, robot) = phone_bound_policy_driving();
        // Only the owner may say it loads.
        assert_eq!(
            a.handle(Input::PolicyLoading { session: POLICY + 1 }, &robot, 1.0),
            Err(ArbiterError::NotControlling)
        );
        a.handle(loading(), &robot, 1.0).unwrap();
        let fx = a.handle(engage(Isometry3::identity()), &robot, 2.0).unwrap();
        assert_eq!(a.driver(), Driver::Teleop);
        assert_eq!(fx.revoked, None, "the loading policy waits");
        assert_eq!(a.waiting_policy(), Some((POLICY, "p")));
        assert_eq!(a.policy_loading_until(), None, "not loading while it waits");
        // Its keep-alives are refused while it waits, and its loading limit does not release it then.
        assert_eq!(
            a.handle(loading(), &robot, 2.1),
            Err(ArbiterError::PolicyWaiting { policy: "p".into() })
        );
        let fx = a.handle(Input::Tick, &ready(home(), 400.0), 400.0).unwrap();
        assert_eq!(fx.revoked, None);
    }

    #[test]
    fn a_stale_phone_stream_ending_leaves_the_new_phone_bound() {
        let mut a = phone_driving();
        let robot = ready(home(), 1.1);
        a.handle(take_over(2), &robot, 1.1).unwrap();
        // The replaced phone's stream ends late: the new phone keeps the arm.
        a.handle(Input::UnbindTeleop { session: PHONE }, &robot, 1.2)
            .unwrap();
        assert_eq!(a.teleop_session(), Some(2));
        // The new phone drives, then its stream ends: the arm holds and says why; the arm is free again.
        a.handle(
            Input::Teleop {
                session: 2,
                round: TeleopRound {
                    pose: Some(Ok(Isometry3::identity())),
                    tracking_ok: true,
                    buttons: vec![TeleopButton::Clutch(ClutchKind::Engage)],
                },
            },
            &robot,
            1.2,
        )
        .unwrap();
        assert_eq!(a.driver(), Driver::Teleop);
        let fx = a.handle(Input::UnbindTeleop { session: 2 }, &robot, 1.3).unwrap();
        assert!(fx.commands.is_empty());
        assert_eq!(a.driver(), Driver::None);
        assert_eq!(a.teleop_session(), None);
        assert_eq!(a.last_decision().reason, "phone disconnected: the arm holds");
        // A third phone binds without having to take over.
        a.handle(bind_phone(), &robot, 1.4).unwrap();
        assert_eq!(a.teleop_session(), Some(PHONE));
    }

    #[test]
    fn engaging_sends_the_hold_target_and_shows_the_clutch_decision() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        let fx = a.handle(engage(Isometry3::identity()), &robot, 1.0).unwrap();
        // The press holds the arm where it is; the round's pose, the new zero, then commands the same pose.
        assert_eq!(fx.commands.len(), 2, "{fx:?}");
        assert_close(&fx.commands[0].robot_from_target, &home());
        assert_close(&fx.commands[1].robot_from_target, &home());
        assert!(fx.decision.is_some(), "{fx:?}");
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
                &robot,
                1.02,
            )
            .unwrap();
        assert!(
            fx.decision.is_some(),
            "releasing the clutch shows its decision: {fx:?}"
        );
    }

    #[test]
    fn the_gripper_target_is_what_was_last_sent() {
        let mut a = phone_driving();
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Gripper(GripperCommand::Set(0.75))]),
                &ready(home(), 1.02),
                1.02,
            )
            .unwrap();
        assert!((fx.commands[0].gripper - 0.75).abs() < 1e-12);
        assert!((a.target().1 - 0.75).abs() < 1e-12, "{:?}", a.target());
    }

    #[test]
    fn a_silent_phone_and_a_silent_policy_are_shown_as_held() {
        let mut a = phone_driving();
        a.handle(Input::Tick, &ready(home(), 3.0), 3.0).unwrap();
        assert_eq!(
            a.last_decision().verdict,
            GateVerdict::HeldStale,
            "{:?}",
            a.last_decision()
        );

        let mut b = arbiter();
        let robot = ready(home(), 1.0);
        let fx = b.handle(claim(), &robot, 1.0).unwrap();
        assert!(fx.reindexed, "a claim re-indexes the phone's floating zero");
        assert_eq!(b.last_decision().reason, "policy p in control");
        let fx = b.handle(Input::Tick, &robot, 1.6).unwrap();
        assert!(fx.revoked.is_some());
        assert_eq!(b.last_decision().verdict, GateVerdict::HeldStale);
        assert!(
            b.last_decision().reason.starts_with("policy silent for"),
            "{:?}",
            b.last_decision()
        );
    }

    #[test]
    fn a_chunk_that_starts_later_restarts_the_silence_clock_when_it_arrives() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        // 0.4 s after the claim (silence timeout 0.5 s) a chunk arrives whose first step is 0.2 s ahead.
        let fx = a.handle(chunk(1.6, &[at(0.251, 0.0, 0.2)]), &robot, 1.4).unwrap();
        assert!(fx.commands.is_empty(), "nothing due yet");
        // 0.55 s after the claim but 0.15 s after the chunk: the policy is not silent.
        let fx = a.handle(Input::Tick, &robot, 1.55).unwrap();
        assert!(fx.revoked.is_none(), "{fx:?}");
        let fx = a.handle(Input::Tick, &robot, 1.6).unwrap();
        assert_eq!(fx.commands.len(), 1);
    }

    #[test]
    fn while_a_policy_drives_the_phone_neither_grips_nor_overwrites_its_verdict() {
        let invalid = |a: &mut Arbiter, robot: &Robot, now_s: f64| {
            let round = TeleopRound {
                pose: Some(Err("quaternion norm 2, not 1".to_owned())),
                tracking_ok: true,
                buttons: vec![TeleopButton::Gripper(GripperCommand::Set(1.0))],
            };
            a.handle(
                Input::Teleop {
                    session: PHONE,
                    round,
                },
                robot,
                now_s,
            )
            .unwrap()
        };
        // Nobody drives: the malformed pose is a refused command (counted, shown), and the gripper follows.
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        let fx = invalid(&mut a, &robot, 1.0);
        assert_eq!(a.last_decision().verdict, GateVerdict::RejectedInvalid);
        assert_eq!(a.counters().rejected, 1);
        assert!(fx.phone_error.contains("quaternion"), "{fx:?}");
        assert_eq!(
            fx.commands.len(),
            1,
            "the gripper button sends with nobody driving"
        );
        assert!((fx.commands[0].gripper - 1.0).abs() < 1e-12);

        // A policy drives: the phone hears about its pose, but the verdict on display stays the policy's and
        // the gripper stays where the policy put it.
        let (mut b, robot) = phone_bound_policy_driving();
        let policy_verdict = b.last_decision().clone();
        let fx = invalid(&mut b, &robot, 1.0);
        assert!(fx.phone_error.contains("quaternion"), "{fx:?}");
        assert!(fx.commands.is_empty(), "{fx:?}");
        assert_eq!(b.last_decision(), &policy_verdict);
        assert_eq!(b.counters().rejected, 0);
    }

    #[test]
    fn each_gate_decision_counts_once_in_its_own_counter() {
        // An arm 1 cm under the workspace ceiling (0.35 m); the default landscape mapping turns the phone's +y
        // into the robot's +z.
        let under_ceiling = at(0.25, 0.0, 0.34);
        let mut a = Arbiter::new(
            &TeleopConfig::default(),
            ChunkConfig::default(),
            under_ceiling,
            0.0,
        )
        .unwrap();
        let robot = ready(under_ceiling, 1.0);
        a.handle(bind_phone(), &robot, 1.0).unwrap();
        a.handle(engage(Isometry3::identity()), &robot, 1.0).unwrap();
        let counts = |a: &Arbiter| (a.counters().clamped, a.counters().rejected);
        assert_eq!(counts(&a), (0, 0));
        // Lifted 3 cm: clamped at the ceiling.
        let fx = a
            .handle(round(Some(at(0.0, 0.03, 0.0)), vec![]), &robot, 1.02)
            .unwrap();
        assert_eq!(a.last_decision().verdict, GateVerdict::Clamped, "{fx:?}");
        assert!((fx.commands[0].robot_from_target.translation.z - 0.35).abs() < 1e-12);
        assert_eq!(counts(&a), (1, 0));
        // 13 cm sideways (phone +x is robot −y), inside the box: a jump, refused.
        let fx = a
            .handle(round(Some(at(0.13, 0.0, 0.0)), vec![]), &robot, 1.04)
            .unwrap();
        assert_eq!(a.last_decision().verdict, GateVerdict::RejectedJump, "{fx:?}");
        assert!(fx.commands.is_empty());
        assert_eq!(counts(&a), (1, 1));
        // Back in the box: accepted, no count.
        a.handle(round(Some(at(0.0, 0.0, 0.0)), vec![]), &robot, 1.06)
            .unwrap();
        assert_eq!(a.last_decision().verdict, GateVerdict::Accepted);
        assert_eq!(counts(&a), (1, 1));
    }

    #[test]
    fn a_plan_that_ends_now_needs_only_its_silence_deadline() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let Input::Chunk {
            session, mut chunk, ..
        } = chunk(1.0, &[at(0.251, 0.0, 0.2), at(0.252, 0.0, 0.2)])
        else {
            unreachable!()
        };
        // Binary fractions: the plan ends at exactly 1.5 s.
        chunk.step_period_s = 0.25;
        a.handle(
            Input::Chunk {
                session,
                chunk,
                observed_s: 1.0,
            },
            &robot,
            1.0,
        )
        .unwrap();
        assert_eq!(a.tick_need(), TickNeed::Periodic);
        a.handle(Input::Tick, &robot, 1.25).unwrap();
        assert_eq!(
            a.tick_need(),
            TickNeed::Periodic,
            "the second step plays until 1.5"
        );
        a.handle(Input::Tick, &robot, 1.5).unwrap();
        // The last window has closed: only the silence deadline is left, 0.5 s after the plan's end.
        assert_eq!(a.tick_need(), TickNeed::At(2.0));
    }

    #[test]
    fn a_refused_chunk_changes_nothing() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let err = a.handle(chunk(10.0, &[home()]), &robot, 1.0);
        assert!(matches!(
            err,
            Err(ArbiterError::Chunk(ChunkError::AnchorTooFarAhead { .. }))
        ));
        // The silence clock was not restarted by the refused chunk.
        let fx = a.handle(Input::Tick, &robot, 1.51).unwrap();
        assert!(fx.revoked.is_some());
    }

    #[test]
    fn an_idle_arm_needs_no_ticks_and_an_engaged_phone_does() {
        let mut a = arbiter();
        assert_eq!(a.tick_need(), TickNeed::Idle);
        a.handle(bind_phone(), &ready(home(), 1.0), 1.0).unwrap();
        assert_eq!(a.tick_need(), TickNeed::Idle);
        a.handle(engage(Isometry3::identity()), &ready(home(), 1.0), 1.0)
            .unwrap();
        assert_eq!(a.tick_need(), TickNeed::Periodic);
        a.handle(Input::UnbindTeleop { session: PHONE }, &ready(home(), 1.0), 1.0)
            .unwrap();
        assert_eq!(a.tick_need(), TickNeed::Idle);
    }

    #[test]
    fn homing_is_refused_naming_the_source_that_drives() {
        let mut a = phone_driving();
        assert_eq!(
            a.may_home(),
            Err(ArbiterError::DrivenWhileHoming {
                owner: Owner::Phone { session: PHONE }
            })
        );
        let refused = a.handle(Input::Homed { gripper: 0.0 }, &ready(home(), 1.1), 1.1);
        assert_eq!(
            refused.unwrap_err().to_string(),
            "is driven by a phone (teleop session 41); release it before homing the arm"
        );
        let (a, _) = phone_bound_policy_driving();
        assert_eq!(
            a.may_home().unwrap_err().to_string(),
            "is driven by policy \"p\"; release it before homing the arm"
        );
        // A bound phone that does not drive is no reason to refuse.
        let mut a = arbiter();
        a.handle(bind_phone(), &ready(home(), 1.0), 1.0).unwrap();
        assert_eq!(a.may_home(), Ok(()));
    }

    #[test]
    fn after_homing_the_arm_holds_the_homed_pose_and_both_sources_start_from_it() {
        let mut a = phone_driving();
        let moved = a
            .handle(
                round(Some(at(0.03, 0.0, 0.0)), vec![]),
                &ready(home(), 1.02),
                1.02,
            )
            .unwrap()
            .commands[0]
            .robot_from_target;
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &ready(moved, 1.1),
            1.1,
        )
        .unwrap();
        // A scene reset teleports the arm 10 cm away: farther than any gate lets a source jump.
        let homed = at(0.25, 0.1, 0.2);
        let fx = a
            .handle(Input::Homed { gripper: 0.4 }, &ready(homed, 1.2), 1.2)
            .unwrap();
        assert!(fx.commands.is_empty() && fx.reindexed, "{fx:?}");
        assert_eq!(a.target(), (homed, 0.4));
        // The phone engages where it left off: the arm stays at the homed pose, not the phone's old offset.
        let fx = a
            .handle(engage(at(0.03, 0.0, 0.0)), &ready(homed, 1.3), 1.3)
            .unwrap();
        assert_close(&fx.commands.last().unwrap().robot_from_target, &homed);
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &ready(homed, 1.4),
            1.4,
        )
        .unwrap();
        // A policy is gated from the homed pose too: a step there passes, one at the old pose is a jump.
        let mut b = arbiter();
        let robot = ready(home(), 1.0);
        b.handle(claim(), &robot, 1.0).unwrap();
        b.handle(
            Input::ReleasePolicy {
                session: POLICY,
                reason: "done".into(),
            },
            &robot,
            1.0,
        )
        .unwrap();
        b.handle(Input::Homed { gripper: 0.0 }, &ready(homed, 1.1), 1.1)
            .unwrap();
        b.handle(claim(), &ready(homed, 1.1), 1.1).unwrap();
        let fx = b.handle(chunk(1.1, &[home()]), &ready(homed, 1.1), 1.1).unwrap();
        assert!(fx.commands.is_empty(), "{fx:?}");
        assert_eq!(b.last_decision().verdict, GateVerdict::RejectedJump);
        let near = at(0.25, 0.101, 0.2);
        let fx = b.handle(chunk(1.2, &[near]), &ready(homed, 1.2), 1.2).unwrap();
        assert_close(&fx.commands[0].robot_from_target, &near);
    }

    #[test]
    fn time_going_backwards_replays_no_earlier_step() {
        let mut a = arbiter();
        let robot = ready(home(), 1.0);
        a.handle(claim(), &robot, 1.0).unwrap();
        let steps = [at(0.251, 0.0, 0.2), at(0.252, 0.0, 0.2), at(0.253, 0.0, 0.2)];
        a.handle(chunk(1.0, &steps), &robot, 1.0).unwrap();
        assert_eq!(a.handle(Input::Tick, &robot, 1.15).unwrap().commands.len(), 1);
        assert!(a.handle(Input::Tick, &robot, 1.05).unwrap().commands.is_empty());
        assert!(
            a.handle(Input::Tick, &robot, f64::NAN)
                .unwrap()
                .commands
                .is_empty()
        );
    }

    /// The phone's gripper setting is only what the phone last asked for; the arm's gripper may since have
    /// been moved by a policy or a scene reset. Driving on must not silently re-send the old setting.
    #[test]
    fn taking_over_or_homing_keeps_the_gripper_where_the_arm_has_it() {
        let (mut a, robot) = phone_bound_policy_driving();
        // The policy closes the gripper (0.5 in every step of `chunk`) on something.
        a.handle(chunk(1.0, &[home(); 3]), &robot, 1.0).unwrap();
        a.handle(Input::Tick, &robot, 1.05).unwrap();
        assert!((a.target().1 - 0.5).abs() < 1e-12);
        // A press while the policy drives is not kept for later.
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Gripper(GripperCommand::Set(0.0))]),
                &robot,
                1.06,
            )
            .unwrap();
        assert!(fx.commands.is_empty(), "{fx:?}");
        let phone = at(0.5, 0.5, 0.5);
        let fx = a.handle(engage(phone), &ready(home(), 1.1), 1.1).unwrap();
        for c in &fx.commands {
            assert!(
                (c.gripper - 0.5).abs() < 1e-12,
                "the take-over moved the gripper: {c:?}"
            );
        }
        let fx = a
            .handle(
                round(Some(at(0.51, 0.5, 0.5)), vec![]),
                &ready(home(), 1.12),
                1.12,
            )
            .unwrap();
        assert!(!fx.commands.is_empty());
        for c in &fx.commands {
            assert!(
                (c.gripper - 0.5).abs() < 1e-12,
                "the first pose after a take-over moved the gripper: {c:?}"
            );
        }
        // A toggle then acts on the arm's gripper (half closed or more: open).
        let fx = a
            .handle(
                round(None, vec![TeleopButton::Gripper(GripperCommand::Toggle)]),
                &ready(home(), 1.13),
                1.13,
            )
            .unwrap();
        assert!((fx.commands[0].gripper - 0.0).abs() < 1e-12, "{:?}", fx.commands);

        // The phone closes the gripper, lets go, and the scene is reset with the gripper open.
        a.handle(
            round(None, vec![TeleopButton::Gripper(GripperCommand::Set(1.0))]),
            &ready(home(), 1.2),
            1.2,
        )
        .unwrap();
        a.handle(
            round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            &ready(home(), 1.25),
            1.25,
        )
        .unwrap();
        let homed = at(0.3, 0.0, 0.25);
        a.handle(Input::Homed { gripper: 0.0 }, &ready(homed, 1.3), 1.3)
            .unwrap();
        let fx = a.handle(engage(phone), &ready(homed, 1.4), 1.4).unwrap();
        let fx2 = a
            .handle(round(Some(at(0.51, 0.5, 0.5)), vec![]), &ready(homed, 1.42), 1.42)
            .unwrap();
        for c in fx.commands.iter().chain(&fx2.commands) {
            assert!(
                c.gripper.abs() < 1e-12,
                "the phone's old setting closed the homed gripper: {c:?}"
            );
        }
    }

    // ---- Property tests of the safety contracts over random input sequences. ----

    #[derive(Debug, Clone)]
    enum Op {
        Advance(f64),
        Bind(u64, bool),
        Unbind(u64),
        Sample {
            phone: u64,
            pose: [f64; 6],
            tracking_ok: bool,
            button: u8,
        },
        Claim(u64),
        Release(u64),
        Loading(u64),
        Chunk {
            session: u64,
            offsets: Vec<[f64; 3]>,
            lead_s: f64,
            /// Steps around `home()` rather than around the measured pose: a policy that plans from a pose
            /// the arm has left.
            from_home: bool,
            /// How long before now the observation it answers was taken (negative: a clock ahead of ours).
            observed_lag_s: f64,
        },
        Tick,
        Health(u8),
        /// A scene reset teleports the arm to this offset from `home()` (only when nobody drives, as the
        /// shell asks [`Arbiter::may_home`] first).
        Home([f64; 3]),
    }

    fn any_op() -> impl Strategy<Value = Op> {
        prop_oneof![
            3 => (-0.2..0.4f64).prop_map(Op::Advance),
            1 => (1..3u64, any::<bool>()).prop_map(|(p, t)| Op::Bind(p, t)),
            1 => (1..3u64).prop_map(Op::Unbind),
            5 => (1..3u64, prop::array::uniform6(-0.1..0.1f64), prop::bool::weighted(0.9), 0..12u8).prop_map(
                |(phone, pose, tracking_ok, button)| Op::Sample { phone, pose, tracking_ok, button }
            ),
            1 => (7..9u64).prop_map(Op::Claim),
            1 => (7..9u64).prop_map(Op::Release),
            1 => (7..9u64).prop_map(Op::Loading),
            3 => (
                7..9u64,
                prop::collection::vec(prop::array::uniform3(-0.05..0.05f64), 1..6),
                -0.3..0.2f64,
                prop::bool::weighted(0.3),
                -0.1..0.8f64,
            )
                .prop_map(|(session, offsets, lead_s, from_home, observed_lag_s)| Op::Chunk {
                    session, offsets, lead_s, from_home, observed_lag_s,
                }),
            4 => Just(Op::Tick),
            1 => (0..8u8).prop_map(Op::Health),
            1 => prop::array::uniform3(-0.1..0.1f64).prop_map(Op::Home),
        ]
    }

    /// The phone's pose after a move `p`: mostly a small step (the operator's hand), sometimes a leap (a
    /// tracking glitch).
    fn phone_pose(phone: &Isometry3<f64>, p: [f64; 6]) -> Isometry3<f64> {
        let scale = if p[0] > 0.09 { 3.0 } else { 0.4 };
        Isometry3::from_parts(
            Translation3::from(phone.translation.vector + Vector3::new(p[0], p[1], p[2]) * scale),
            UnitQuaternion::from_scaled_axis(Vector3::new(p[3], p[4], p[5]) * scale) * phone.rotation,
        )
    }

    fn button(b: u8) -> Vec<TeleopButton> {
        match b {
            0 => vec![TeleopButton::Clutch(ClutchKind::Engage)],
            1 => vec![TeleopButton::Clutch(ClutchKind::Disengage)],
            2 => vec![TeleopButton::Clutch(ClutchKind::Toggle)],
            3 => vec![TeleopButton::Gripper(GripperCommand::Toggle)],
            4 => vec![TeleopButton::Gripper(GripperCommand::Set(0.7))],
            5 | 6 => vec![TeleopButton::HandBack],
            _ => vec![],
        }
    }

    /// The world around the arbiter: a robot that reaches every target at once (so its measured pose is the
    /// last command), with a bridge whose health the operations change.
    struct World {
        arbiter: Arbiter,
        now_s: f64,
        latest_s: f64,
        measured: Isometry3<f64>,
        phone: Isometry3<f64>,
        health: BridgeHealth,
        feedback_age_s: f64,
        /// Sessions that lost the arm and have not claimed it again.
        revoked: Vec<u64>,
        /// The end of the newest chunk of the current owner.
        plan_end_s: f64,
        /// The time of the last hand-back, until the policy's first chunk after it is accepted.
        handed_back_s: Option<f64>,
    }

    impl World {
        fn robot(&self) -> Robot {
            Robot {
                health: self.health.clone(),
                feedback: Some(Measured {
                    robot_from_ee: self.measured,
                    capture_time_s: self.now_s - self.feedback_age_s,
                }),
            }
        }

        fn input(&mut self, op: &Op) -> Option<(Input, bool)> {
            Some(match op {
                Op::Advance(dt_s) => {
                    self.now_s += dt_s;
                    return None;
                }
                Op::Health(h) => {
                    (self.health, self.feedback_age_s) = match h {
                        0 => (BridgeHealth::Error("e".into()), 0.0),
                        1 => (BridgeHealth::Connecting, 0.0),
                        2 => (BridgeHealth::Ready, FEEDBACK_MAX_AGE_S + 0.5),
                        _ => (BridgeHealth::Ready, 0.0),
                    };
                    return None;
                }
                Op::Bind(session, take_over) => (
                    Input::BindTeleop {
                        session: *session,
                        take_over: *take_over,
                    },
                    false,
                ),
                Op::Unbind(session) => (Input::UnbindTeleop { session: *session }, false),
                Op::Sample {
                    phone,
                    pose,
                    tracking_ok,
                    button: b,
                } => {
                    self.phone = phone_pose(&self.phone, *pose);
                    (
                        Input::Teleop {
                            session: *phone,
                            round: TeleopRound {
                                // Some clutch presses come without a pose, as from a phone that lost tracking.
                                pose: (*b != 0 || pose[0] > -0.05).then_some(Ok(self.phone)),
                                tracking_ok: *tracking_ok,
                                buttons: button(*b),
                            },
                        },
                        false,
                    )
                }
                Op::Claim(session) => (
                    Input::ClaimPolicy {
                        session: *session,
                        name: format!("policy-{session}"),
                        silence_timeout_s: 0.3,
                    },
                    false,
                ),
                Op::Loading(session) => (Input::PolicyLoading { session: *session }, false),
                Op::Release(session) => (
                    Input::ReleasePolicy {
                        session: *session,
                        reason: "released".into(),
                    },
                    false,
                ),
                Op::Chunk {
                    session,
                    offsets,
                    lead_s,
                    from_home,
                    observed_lag_s,
                } => {
                    let origin = if *from_home { home() } else { self.measured };
                    let steps = offsets
                        .iter()
                        .map(|o| ChunkStep {
                            robot_from_target: Isometry3::from_parts(
                                Translation3::from(origin.translation.vector + Vector3::from(*o)),
                                origin.rotation,
                            ),
                            gripper: o[0] * 20.0,
                        })
                        .collect();
                    (
                        Input::Chunk {
                            session: *session,
                            chunk: ActionChunk {
                                steps,
                                anchor_time_s: self.now_s + lead_s,
                                step_period_s: 0.05,
                            },
                            observed_s: self.now_s - observed_lag_s,
                        },
                        true,
                    )
                }
                Op::Tick => (Input::Tick, true),
                Op::Home(offset) => {
                    if self.arbiter.may_home().is_ok() {
                        self.measured = Isometry3::from_parts(
                            Translation3::from(home().translation.vector + Vector3::from(*offset)),
                            home().rotation,
                        );
                    }
                    (Input::Homed { gripper: 0.0 }, false)
                }
            })
        }

        /// Applies `op` and checks every contract on what it did.
        fn step(&mut self, op: &Op) -> Result<(), TestCaseError> {
            let Some((input, policy_input)) = self.input(op) else {
                return Ok(());
            };
            let before = self.arbiter.clone();
            let ready_now = self.robot().not_ready(self.now_s.max(self.latest_s)).is_none();
            let backwards = self.now_s <= self.latest_s;
            let latest_before_s = self.latest_s;
            let chunk_end_s = match &input {
                Input::Chunk { chunk, .. } => {
                    chunk.anchor_time_s + chunk.steps.len() as f64 * chunk.step_period_s
                }
                _ => 0.0,
            };
            let robot = self.robot();
            let result = self.arbiter.handle(input.clone(), &robot, self.now_s);
            self.latest_s = self.latest_s.max(self.now_s);
            let a = &self.arbiter;

            // Never two drivers: a policy owns the arm exactly when it drives; a driving phone is bound; a
            // waiting policy does not drive.
            prop_assert_eq!(a.policy_owner().is_some(), a.driver() == Driver::Policy);
            prop_assert!(a.waiting_policy().is_none() || a.driver() != Driver::Policy);
            if a.driver() == Driver::Teleop {
                prop_assert!(a.teleop_session().is_some() && a.policy_owner().is_none());
            }
            // A phone drives exactly while its planner is engaged: every way out of driving disengages, and
            // an engaged planner that no longer drove would re-engage without a clutch press.
            prop_assert_eq!(a.teleop.engaged(), a.driver() == Driver::Teleop);

            if let Input::Homed { .. } = &input {
                // A teleport only while nobody drives; afterwards the arm holds where it landed.
                prop_assert_eq!(result.is_ok(), before.driver() == Driver::None);
                if result.is_ok() {
                    prop_assert_eq!(a.target().0, self.measured);
                }
            }

            let Ok(fx) = result else {
                // A refusal changes nothing.
                prop_assert_eq!(a.driver(), before.driver());
                prop_assert_eq!(a.target(), before.target());
                prop_assert_eq!(a.counters(), before.counters());
                return Ok(());
            };
            if let Some(r) = &fx.revoked {
                self.revoked.push(r.session);
            }
            // Each gate decision counts once, in its own counter.
            let verdict = fx.decision.as_ref().map(|d| d.verdict);
            let rejected = matches!(
                verdict,
                Some(GateVerdict::RejectedJump | GateVerdict::RejectedInvalid)
            );
            prop_assert_eq!(
                a.counters().rejected,
                before.counters().rejected + u64::from(rejected)
            );
            let clamped = verdict == Some(GateVerdict::Clamped);
            prop_assert_eq!(
                a.counters().clamped,
                before.counters().clamped + u64::from(clamped)
            );
            if let Input::ClaimPolicy { session, .. } = &input {
                self.revoked.retain(|s| s != session);
                self.plan_end_s = f64::NEG_INFINITY;
                // Claiming starts nothing unless the robot is ready.
                prop_assert!(ready_now, "a claim succeeded on a robot that is not ready");
            }
            if let Input::BindTeleop { take_over: true, .. } = &input {
                // (An error here would have returned above: check it did not.)
                prop_assert!(a.teleop_session().is_some());
            }
            if matches!(input, Input::Chunk { .. }) {
                self.plan_end_s = chunk_end_s;
            }
            if let Input::Teleop { round, .. } = &input
                && ready_now
                && round.buttons == [TeleopButton::Clutch(ClutchKind::Engage)]
            {
                // The operator always takes over, and the policy that drove waits instead of losing the arm.
                prop_assert_eq!(a.driver(), Driver::Teleop);
                if let Some((session, _)) = before.policy_owner() {
                    prop_assert_eq!(a.waiting_policy().map(|(s, _)| s), Some(session));
                    prop_assert!(fx.revoked.is_none());
                }
            }
            let handed_back = a.counters().handed_back > before.counters().handed_back;
            if handed_back {
                // A hand-back happens only from a waiting policy, on a ready robot, and sends nothing.
                prop_assert!(before.waiting_policy().is_some() && ready_now);
                prop_assert!(
                    fx.commands.is_empty(),
                    "a hand-back moved the arm: {:?}",
                    fx.commands
                );
                prop_assert_eq!(a.driver(), Driver::Policy);
                self.handed_back_s = Some(self.latest_s);
                self.plan_end_s = f64::NEG_INFINITY;
            } else if let Some(back_s) = self.handed_back_s {
                // Until the policy's first chunk answering an observation after the hand-back, nothing moves
                // the arm but the operator taking it again.
                if fx.chunk.is_some() {
                    let Input::Chunk { observed_s, .. } = &input else {
                        unreachable!("only a chunk input reports a chunk")
                    };
                    prop_assert!(
                        *observed_s > back_s,
                        "a chunk observed before the hand-back was accepted"
                    );
                    self.handed_back_s = None;
                } else if a.policy_owner().is_none() {
                    // Taken again, released or revoked: the next hand-back starts over.
                    self.handed_back_s = None;
                } else {
                    prop_assert!(
                        fx.commands.is_empty(),
                        "motion after a hand-back before a fresh chunk: {:?} after {:?}",
                        fx.commands,
                        op
                    );
                }
            }

            if backwards && matches!(input, Input::Tick) {
                // Time going backwards is time standing still: never an earlier step of a plan.
                let mut standing = before.clone();
                let expected = standing.handle(Input::Tick, &robot, latest_before_s);
                prop_assert_eq!(
                    Ok(fx.clone()),
                    expected,
                    "a tick at an earlier time did something else"
                );
            }
            for (seq, c) in (before.counters().sent + 1..).zip(&fx.commands) {
                prop_assert_eq!(c.seq, seq);
                // Every send passed a gate: inside the box, within the jump thresholds of where the robot is
                // (its measured pose is the previous command), a gripper target in [0, 1].
                let gate = &TeleopConfig::default().gate;
                let p = c.robot_from_target.translation.vector;
                for axis in 0..3 {
                    prop_assert!(p[axis] >= gate.workspace_min_m[axis] - 1e-12);
                    prop_assert!(p[axis] <= gate.workspace_max_m[axis] + 1e-12);
                }
                let step_m = (p - self.measured.translation.vector).norm();
                let turn_rad = angle_between_rad(&self.measured.rotation, &c.robot_from_target.rotation);
                prop_assert!(
                    step_m <= gate.jump_position_m + 1e-9,
                    "jump of {} m after {:?}",
                    step_m,
                    op
                );
                prop_assert!(
                    turn_rad <= gate.jump_rotation_rad + 1e-9,
                    "turn of {} rad",
                    turn_rad
                );
                prop_assert!((0.0..=1.0).contains(&c.gripper));
                self.measured = c.robot_from_target;
            }
            // The loading bound: after a tick no policy still holds the arm loading past its deadline, and the
            // deadline is never more than `max_loading_s` away.
            if let Some(deadline_s) = a.policy_loading_until() {
                if matches!(input, Input::Tick) {
                    prop_assert!(
                        self.latest_s <= deadline_s,
                        "loading past the deadline {}",
                        deadline_s
                    );
                }
                prop_assert!(deadline_s <= self.latest_s + ChunkConfig::default().max_loading_s + 1e-9);
            }
            if !fx.commands.is_empty() {
                if policy_input {
                    let owner = before.policy_owner().map(|(s, _)| s);
                    // Only the owning policy's plan moves the arm, and a revoked one never again.
                    prop_assert!(owner.is_some());
                    prop_assert!(!self.revoked.contains(&owner.unwrap()));
                    // A silent policy produces no motion once its newest plan is over.
                    prop_assert!(
                        self.latest_s < self.plan_end_s + 1e-9,
                        "motion after the plan ended"
                    );
                }
                if matches!(input, Input::Tick) {
                    prop_assert_eq!(before.driver(), Driver::Policy, "a tick moved a phone-driven arm");
                }
                if matches!(input, Input::PolicyLoading { .. }) {
                    prop_assert!(false, "a loading message moved the arm");
                }
                if matches!(input, Input::Teleop { .. }) {
                    prop_assert!(ready_now, "a phone moved a robot that is not ready");
                }
            }
            Ok(())
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(400))]

        #[test]
        fn the_safety_contracts_hold_over_random_inputs(ops in prop::collection::vec(any_op(), 1..120)) {
            let mut world = World {
                arbiter: arbiter(),
                now_s: 1.0,
                latest_s: 0.0,
                measured: home(),
                phone: Isometry3::identity(),
                health: BridgeHealth::Ready,
                feedback_age_s: 0.0,
                revoked: Vec::new(),
                plan_end_s: f64::NEG_INFINITY,
                handed_back_s: None,
            };
            for op in &ops {
                world.step(op)?;
            }
        }
    }
}
