//! Arm controllers: one per configured arm, the shell around its [`Arbiter`] (the source-arbitration rules,
//! in `phone2act_core::arbiter`). The shell reads the bridge and the clock, hands the arbiter one input at a
//! time under a lock, and carries out what it returns: commands go to [`Bridge::send`] in order, a revoked
//! policy session is told, and the tick task is woken when the arbiter needs ticks.
//!
//! The critical section is a `parking_lot::Mutex` (it does not poison: see the `inner` field) held for
//! microseconds and never across an `.await`, so the control path is a straight function call from the gRPC
//! handler to the bridge (which never blocks).

use crate::flight_log::FlightLogWriter;
use nalgebra::Isometry3;
use parking_lot::Mutex;
use phone2act_bridges::sim::SceneState;
use phone2act_bridges::{Bridge, BridgeError, Feedback, Health};
use phone2act_clock::monotonic_ns;
use phone2act_core::kinematics::{SO101_ARM_JOINT_NAMES, So101Kinematics};
use phone2act_core::{
    ActionChunk, ActionMode, Arbiter, ArbiterError, ArmJointStage, ArmLayout, ArmSnapshot, ArmVectors,
    BridgeHealth, ChunkConfig, Effects, FlightEntry, FlightHeader, Input, LayoutError, Measured, Outcome,
    PREVIEW_MAX_POINTS, Reading, ReplaceReport, Robot, Sample, TeleopConfig, TeleopRound, TickNeed,
};
use phone2act_recorder::events::ArmActivity;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::sync::Notify;

/// Seconds on the process monotonic clock.
pub fn now_s() -> f64 {
    monotonic_ns() as f64 * 1e-9
}

/// Where a policy session hears that it lost an arm. Called after the arm's lock is released; must not
/// block (the control path calls it).
pub trait RevocationSink: Send + Sync + std::fmt::Debug {
    fn revoked(&self, arm: &str, reason: &str);
}

/// Largest distance between the robot's reported tool position and the joint model's position of its reported
/// joints for the server to drive the arm through the model: 5 mm, well above the model's rounding (the CR5
/// URDF gives its lengths to the millimetre) and far below what a wrong base frame, tool or joint zero gives.
const MODEL_MATCH_M: f64 = 5e-3;
/// The same for the orientation: 0.05 rad (about 3°).
const MODEL_MATCH_RAD: f64 = 0.05;

/// What one teleop round did.
#[derive(Debug, Clone)]
pub struct TeleopOutcome {
    /// Per-sample error for the phone (invalid pose, bad gripper value); empty when fine.
    pub error: String,
    /// Server time the last command (if any) was handed to the bridge.
    pub command_time_ns: Option<i64>,
}

/// Errors of an arm controller: building it, and inputs it refused (a refusal changes nothing).
#[derive(Debug, thiserror::Error)]
pub enum ArmError {
    #[error("arm {arm}: {source}")]
    Config {
        arm: String,
        #[source]
        source: phone2act_core::ConfigError,
    },
    #[error(
        "arm {arm}: action_mode = \"joint\" needs SO-101 kinematics (bridge joints {joints:?}); use \"relative\" or \"absolute\""
    )]
    JointModeUnsupported { arm: String, joints: Vec<String> },
    #[error(
        "arm {arm}: dataset_layout = \"lerobot_so101\" needs an SO-101 (sim or so101 bridge) with action_mode = \"joint\""
    )]
    LerobotLayoutUnsupported { arm: String },
    #[error("arm {arm}: {source}")]
    FlightLog {
        arm: String,
        #[source]
        source: crate::flight_log::FlightLogError,
    },
    #[error("arm {arm}: joint limits are enforced in the server only for SO-101 and Dobot CR5 joints")]
    JointStageUnsupported { arm: String },
    #[error(
        "arm {arm}: the robot's reported tool pose is {off_mm:.1} mm and {off_deg:.1}° from the joint model's pose of its reported joints; joint limits cannot be enforced with this model"
    )]
    JointModelMismatch { arm: String, off_mm: f64, off_deg: f64 },
    #[error("arm {arm:?} {source}")]
    Refused {
        arm: String,
        #[source]
        source: ArbiterError,
    },
    #[error("arm {arm:?} step {step}: {source}")]
    InvalidStep {
        arm: String,
        step: usize,
        #[source]
        source: LayoutError,
    },
    /// The bridge refused (a scene request to an arm without a scene is [`BridgeError::Unsupported`]).
    #[error("arm {arm:?}: {source}")]
    Bridge {
        arm: String,
        #[source]
        source: BridgeError,
    },
}

/// The last [`LatencyRing::CAPACITY`] latencies, for benchmarks and status (bounded memory).
#[derive(Debug, Default)]
pub struct LatencyRing {
    values_ns: Vec<u32>,
    next: usize,
    total: u64,
}

impl LatencyRing {
    pub const CAPACITY: usize = 1 << 16;

    fn push(&mut self, ns: i64) {
        let v = u32::try_from(ns.max(0)).unwrap_or(u32::MAX);
        if self.values_ns.len() < Self::CAPACITY {
            self.values_ns.push(v);
        } else {
            self.values_ns[self.next] = v;
        }
        self.next = (self.next + 1) % Self::CAPACITY;
        self.total += 1;
    }
}

#[derive(Debug)]
struct Inner {
    arbiter: Arbiter,
    /// The owning policy session's event sink (the arbiter knows only its id).
    policy_sink: Option<(u64, Arc<dyn RevocationSink>)>,
    /// The last joint action computed for a joint arm without a joint stage (a remote bridge with SO-101
    /// joints): the seed of the next, so the recorder's inverse kinematics follows its own solutions.
    joint_seed: Option<Vec<f64>>,
    /// The flight recorder, when on: every input handed to the arbiter, in order, under this lock.
    flight: Option<FlightLogWriter>,
    /// Arms whose kinematics the server knows (sim, so101, dobot): every command's joints are solved and
    /// rate-limited here, once; the bridge drives to them and the recorder records them.
    joints: Option<ArmJointStage>,
    /// `seq` of the last command handed to the bridge (a catch-up command repeats it: same target).
    last_seq: u64,
}

impl Inner {
    /// The arbiter's need, and ticks at the rate while the joint stage is still catching up with the target.
    fn tick_need(&self) -> TickNeed {
        if self.joints.as_ref().is_some_and(ArmJointStage::behind) {
            TickNeed::Periodic
        } else {
            self.arbiter.tick_need()
        }
    }
}

/// One input handled under the lock, with what is left to do once it is released.
struct Handled {
    effects: Effects,
    /// Server time the last command was handed to the bridge.
    command_time_ns: Option<i64>,
    /// The revoked policy session's sink, to be told without the lock.
    revoked: Option<Arc<dyn RevocationSink>>,
}

/// One arm.
pub struct ArmController {
    pub name: String,
    pub kind: &'static str,
    pub bridge: Arc<dyn Bridge>,
    pub layout: ArmLayout,
    pub action_mode: ActionMode,
    /// Forward/inverse kinematics for joint actions (arms whose joints are the SO-101's).
    kinematics: Option<So101Kinematics>,
    /// Not poisoned by a panicking holder: a panic under the lock leaves the arbiter between two inputs, never
    /// half way through a send, so the next caller carries on with it.
    inner: Mutex<Inner>,
    /// Wakes this arm's tick task when the arbiter starts needing ticks.
    wake: Notify,
    /// Control-path latency of recent teleop commands (sample received → handed to the bridge), ns.
    latencies_ns: Mutex<LatencyRing>,
    samples_received: AtomicU64,
    /// Ticks run since start (an idle arm runs none).
    ticks: AtomicU64,
}

impl std::fmt::Debug for ArmController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ArmController")
            .field("name", &self.name)
            .field("kind", &self.kind)
            .finish_non_exhaustive()
    }
}

fn robot_of(health: Health, feedback: Option<&Feedback>) -> Robot {
    Robot {
        health: match health {
            Health::Ready => BridgeHealth::Ready,
            Health::Connecting => BridgeHealth::Connecting,
            Health::Error(m) => BridgeHealth::Error(m),
            Health::Disconnected(m) => BridgeHealth::Disconnected(m),
        },
        feedback: feedback.map(|f| Measured {
            robot_from_ee: f.robot_from_ee,
            capture_time_s: f.capture_time_ns as f64 * 1e-9,
        }),
    }
}

impl ArmController {
    /// A controller for `bridge`, starting from the robot's measured pose (or `fallback` before feedback).
    pub fn new(
        name: &str,
        kind: &'static str,
        bridge: Arc<dyn Bridge>,
        teleop: &TeleopConfig,
        chunk: &ChunkConfig,
        action_mode: ActionMode,
        fallback: Isometry3<f64>,
    ) -> Result<Self, ArmError> {
        let feedback = bridge.feedback();
        let measured = feedback.as_ref().map_or(fallback, |f| f.robot_from_ee);
        let gripper = feedback.as_ref().map_or(0.0, |f| f.gripper_position);
        let layout = ArmLayout::new(bridge.joint_names().to_vec());
        let kinematics = (bridge.joint_names() == SO101_ARM_JOINT_NAMES).then(So101Kinematics::new);
        if action_mode == ActionMode::Joint && kinematics.is_none() {
            return Err(ArmError::JointModeUnsupported {
                arm: name.to_owned(),
                joints: bridge.joint_names().to_vec(),
            });
        }
        let arbiter =
            Arbiter::new(teleop, chunk.clone(), measured, gripper).map_err(|source| ArmError::Config {
                arm: name.to_owned(),
                source,
            })?;
        Ok(Self {
            name: name.to_owned(),
            kind,
            bridge,
            layout,
            action_mode,
            kinematics,
            inner: Mutex::new(Inner {
                arbiter,
                policy_sink: None,
                joint_seed: None,
                flight: None,
                joints: None,
                last_seq: 0,
            }),
            wake: Notify::new(),
            latencies_ns: Mutex::new(LatencyRing::default()),
            samples_received: AtomicU64::new(0),
            ticks: AtomicU64::new(0),
        })
    }

    /// Logs every input of this arm's arbiter from now on to a new file in `dir` (see
    /// [`crate::flight_log`]), its header made of the `teleop` and `chunk` settings the arm was built with and
    /// the pose and gripper the arbiter holds. Called before the arm takes any input (so that pose is the one
    /// it started from, and the log replays from its start).
    pub fn with_flight_log(
        self,
        dir: &std::path::Path,
        max_bytes: u64,
        teleop: &TeleopConfig,
        chunk: &ChunkConfig,
    ) -> Result<Self, ArmError> {
        let (measured, gripper) = self.inner.lock().arbiter.target();
        let header = FlightHeader::new(&self.name, teleop, chunk, measured, gripper);
        let log = FlightLogWriter::create(dir, &header, max_bytes).map_err(|source| ArmError::FlightLog {
            arm: self.name.clone(),
            source,
        })?;
        tracing::info!(arm = %self.name, path = %log.path().display(), "flight log on");
        self.inner.lock().flight = Some(log);
        Ok(self)
    }

    /// Solves this arm's commands in the server with `stage` (an SO-101's or a CR5's): each target once,
    /// seeded with the joints last commanded, through the stage's joint speed limits. See
    /// `phone2act_core::joint_motion`. Refused for a bridge whose joints are not the stage's, and when the
    /// robot's own tool pose disagrees with the model's pose of its reported joints (a controller whose base
    /// frame, tool or joint zeros differ from the model would be driven somewhere else than asked).
    pub fn with_joint_stage(self, mut stage: ArmJointStage) -> Result<Self, ArmError> {
        let fits = match &stage {
            ArmJointStage::So101(_) => self.kinematics.is_some(),
            other => self.bridge.joint_names().len() == other.joints(),
        };
        if !fits {
            return Err(ArmError::JointStageUnsupported {
                arm: self.name.clone(),
            });
        }
        if let Some(feedback) = self.bridge.feedback() {
            self.model_matches(&stage, &feedback)?;
            stage.reset(&feedback.joint_positions_rad, now_s());
        } else {
            tracing::warn!(arm = %self.name, "no feedback at start: the joint model was not checked against the robot");
        }
        self.inner.lock().joints = Some(stage);
        Ok(self)
    }

    /// Puts `stage` in place of the arm's joint stage (for a remote bridge, at every attach: the stage of the
    /// joint model it declared, or none). A new stage starts from the next measured joints, so the first
    /// command after an attach is limited from where that robot is. Returns the stage it replaced.
    pub fn replace_joint_stage(&self, stage: Option<ArmJointStage>) -> Option<ArmJointStage> {
        std::mem::replace(&mut self.inner.lock().joints, stage)
    }

    /// Refuses feedback whose reported tool pose disagrees with the arm's joint model's pose of its reported
    /// joints (the check [`Self::with_joint_stage`] makes at start, for a stage put in place later). Ok
    /// without a joint stage or for joints of another width.
    pub fn check_joint_model(&self, feedback: &Feedback) -> Result<(), ArmError> {
        match self.inner.lock().joints.as_ref() {
            Some(stage) => self.model_matches(stage, feedback),
            None => Ok(()),
        }
    }

    /// Ok if `stage`'s pose of the reported joints is within [`MODEL_MATCH_M`] and [`MODEL_MATCH_RAD`] of the
    /// reported tool pose (or the joints are not the stage's width).
    fn model_matches(&self, stage: &ArmJointStage, feedback: &Feedback) -> Result<(), ArmError> {
        let Some(model) = stage.forward(&feedback.joint_positions_rad) else {
            return Ok(());
        };
        let off_m = (model.translation.vector - feedback.robot_from_ee.translation.vector).norm();
        let off_rad = model.rotation.angle_to(&feedback.robot_from_ee.rotation);
        if off_m > MODEL_MATCH_M || off_rad > MODEL_MATCH_RAD {
            return Err(ArmError::JointModelMismatch {
                arm: self.name.clone(),
                off_mm: off_m * 1e3,
                off_deg: off_rad.to_degrees(),
            });
        }
        Ok(())
    }

    /// Switches the arm's state and joint actions to lerobot `so101_follower` names and units (see
    /// `phone2act_core::LerobotSo101Units`). Joint arms with SO-101 kinematics only.
    pub fn with_lerobot_so101(mut self, units: phone2act_core::LerobotSo101Units) -> Result<Self, ArmError> {
        if self.action_mode != ActionMode::Joint || self.kinematics.is_none() {
            return Err(ArmError::LerobotLayoutUnsupported {
                arm: self.name.clone(),
            });
        }
        self.layout = self.layout.with_lerobot_so101(units);
        Ok(self)
    }

    /// Hands `input` to the arbiter at `now` (s, [`now_s`]) with the bridge's state read now, and carries out
    /// the effects. Returns them and the time the last command was handed to the bridge.
    fn apply(&self, input: Input, now: f64) -> Result<(Effects, Option<i64>), ArbiterError> {
        self.apply_with(input, now, None)
    }

    /// [`Self::apply`]; if the input is accepted, `sink` becomes the owning policy's (in the same critical
    /// section, so a revocation right after a claim finds it).
    fn apply_with(
        &self,
        input: Input,
        now: f64,
        sink: Option<(u64, Arc<dyn RevocationSink>)>,
    ) -> Result<(Effects, Option<i64>), ArbiterError> {
        // One feedback read and the caller's one clock read serve the readiness check, the planner and the
        // joint stage.
        let feedback = self.bridge.feedback();
        let robot = robot_of(self.bridge.health(), feedback.as_ref());
        let mut inner = self.inner.lock();
        let measured_joints = feedback.as_ref().map(|f| f.joint_positions_rad.as_slice());
        let handled = self.handle_locked(&mut inner, input, &robot, measured_joints, now, sink)?;
        drop(inner);
        Ok(self.finish(handled))
    }

    /// Hands `input` to the arbiter under the held lock and sends its commands. The caller releases the lock
    /// and then [`Self::finish`]es.
    fn handle_locked(
        &self,
        inner: &mut Inner,
        input: Input,
        robot: &Robot,
        measured_joints: Option<&[f64]>,
        now: f64,
        sink: Option<(u64, Arc<dyn RevocationSink>)>,
    ) -> Result<Handled, ArbiterError> {
        let need_before = inner.tick_need();
        let logged = inner.flight.is_some().then(|| input.clone());
        let result = inner.arbiter.handle(input, robot, now);
        if let (Some(input), Some(log)) = (logged, inner.flight.as_mut()) {
            log.record(FlightEntry {
                now_s: now,
                input,
                robot: robot.clone(),
                outcome: Outcome::of(&result),
            });
        }
        let effects = result?;
        if sink.is_some() {
            inner.policy_sink = sink;
        }
        // A new source starts from where the arm is, as the arbiter's planner does.
        if let (Some(stage), Some(joints)) = (inner.joints.as_mut(), measured_joints)
            && (effects.reindexed || stage.commanded().is_none())
        {
            stage.reset(joints, now);
        }
        let mut command_time_ns = None;
        // Sent under the lock, so the bridge sees commands in `seq` order.
        for c in &effects.commands {
            command_time_ns = Some(self.send_locked(inner, c.seq, &c.robot_from_target, c.gripper));
        }
        // The last command did not get there within the joint limits: solve it again next tick.
        if effects.commands.is_empty() && inner.joints.as_ref().is_some_and(ArmJointStage::behind) {
            let (target, gripper) = inner.arbiter.target();
            command_time_ns = Some(self.send_locked(inner, inner.last_seq, &target, gripper));
        }
        let sink = effects.revoked.as_ref().and_then(|r| {
            inner
                .policy_sink
                .take_if(|(session, _)| *session == r.session)
                .map(|(_, sink)| sink)
        });
        if inner.tick_need() != need_before {
            self.wake.notify_one();
        }
        Ok(Handled {
            effects,
            command_time_ns,
            revoked: sink,
        })
    }

    /// Hands one command to the bridge, with its joints when this arm has a joint stage. Returns the issue
    /// time.
    fn send_locked(&self, inner: &mut Inner, seq: u64, target: &Isometry3<f64>, gripper: f64) -> i64 {
        let issue_time_ns = monotonic_ns();
        // A stage that has no joints to start from (no measurement since it was put in place) cannot limit
        // the step: the robot holds rather than be sent a target it might jump to.
        if inner.joints.as_ref().is_some_and(|j| j.commanded().is_none()) {
            tracing::warn!(arm = %self.name, seq, "no measured joints to limit from: command held");
            return issue_time_ns;
        }
        let joint_targets_rad = inner
            .joints
            .as_mut()
            .map(|stage| stage.plan(target, issue_time_ns as f64 * 1e-9));
        self.bridge.send(phone2act_bridges::Command {
            seq,
            robot_from_target: *target,
            gripper_target: gripper,
            issue_time_ns,
            joint_targets_rad,
        });
        inner.last_seq = seq;
        issue_time_ns
    }

    /// Tells a revoked policy session that it lost the arm (without the lock: the sink must not be called
    /// under it). Returns the effects and the time the last command was handed to the bridge.
    fn finish(&self, handled: Handled) -> (Effects, Option<i64>) {
        let Handled {
            effects,
            command_time_ns,
            revoked,
        } = handled;
        if let (Some(sink), Some(r)) = (revoked, &effects.revoked) {
            tracing::info!(arm = %self.name, policy = ?r.policy, reason = %r.reason, "policy control revoked");
            sink.revoked(&self.name, &r.reason);
        }
        (effects, command_time_ns)
    }

    fn refused(&self, source: ArbiterError) -> ArmError {
        ArmError::Refused {
            arm: self.name.clone(),
            source,
        }
    }

    fn bridge_error(&self, source: BridgeError) -> ArmError {
        ArmError::Bridge {
            arm: self.name.clone(),
            source,
        }
    }

    /// Binds a teleop session. A second phone is refused unless it takes over.
    pub fn bind_teleop(&self, session: u64, take_over: bool) -> Result<(), ArmError> {
        self.apply(Input::BindTeleop { session, take_over }, now_s())
            .map(drop)
            .map_err(|e| self.refused(e))
    }

    /// Ends a teleop session; the arm holds if it was driving.
    pub fn unbind_teleop(&self, session: u64) {
        // Unbinding refuses nothing.
        let _ = self.apply(Input::UnbindTeleop { session }, now_s());
    }

    /// Records one control-path latency and the number of samples a round merged.
    pub fn note_round(&self, samples: u64, latency_ns: Option<i64>) {
        self.samples_received.fetch_add(samples, Ordering::Relaxed);
        if let Some(ns) = latency_ns {
            self.latencies_ns.lock().push(ns);
        }
    }

    /// Recent control-path latencies (ns, unordered) and the count of all latencies ever recorded.
    pub fn latencies_ns(&self) -> (Vec<u32>, u64) {
        let ring = self.latencies_ns.lock();
        (ring.values_ns.clone(), ring.total)
    }

    /// Teleop samples received (including those superseded by newer ones) since start.
    pub fn samples_received(&self) -> u64 {
        self.samples_received.load(Ordering::Relaxed)
    }

    /// Ticks run since start.
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Ordering::Relaxed)
    }

    /// Clears the latency ring (between benchmark phases).
    pub fn reset_latencies(&self) {
        *self.latencies_ns.lock() = LatencyRing::default();
    }

    /// Processes one round of teleop input for the bound session.
    pub fn teleop_input(&self, session: u64, round: TeleopRound) -> Result<TeleopOutcome, ArmError> {
        let (effects, command_time_ns) = self
            .apply(Input::Teleop { session, round }, now_s())
            .map_err(|e| self.refused(e))?;
        Ok(TeleopOutcome {
            error: effects.phone_error,
            command_time_ns,
        })
    }

    /// Gives the arm to a policy session. Refused while a phone drives it.
    pub fn claim_for_policy(
        &self,
        session: u64,
        name: &str,
        events: Arc<dyn RevocationSink>,
        silence_timeout_s: f64,
    ) -> Result<(), ArmError> {
        let claim = Input::ClaimPolicy {
            session,
            name: name.to_owned(),
            silence_timeout_s,
        };
        self.apply_with(claim, now_s(), Some((session, events)))
            .map(drop)
            .map_err(|e| self.refused(e))
    }

    /// Releases the arm if `session` owns it; the arm holds.
    pub fn release_policy(&self, session: u64, reason: &str) {
        // Releasing refuses nothing.
        let release = Input::ReleasePolicy {
            session,
            reason: reason.to_owned(),
        };
        let _ = self.apply(release, now_s());
    }

    /// The plan of the policy driving the arm from `from_s` on (see `Arbiter::policy_plan_from`), as steps in
    /// `mode` against an observation at `reference`: the values a chunk answering that observation would carry
    /// to command the same targets. Empty (and period 0) when no policy plan plays.
    pub fn pending_steps(
        &self,
        from_s: f64,
        reference: &Isometry3<f64>,
        mode: ActionMode,
    ) -> (Vec<Vec<f64>>, f64) {
        let (plan, period_s) = self.inner.lock().arbiter.policy_plan_from(from_s);
        if plan.is_empty() {
            return (Vec::new(), 0.0);
        }
        let feedback = self.bridge.feedback();
        let measured = feedback.as_ref().map(|f| f.joint_positions_rad.as_slice());
        match self.vectors().plan_steps(&plan, reference, mode, measured) {
            Some(steps) => (steps, period_s),
            None => (Vec::new(), 0.0),
        }
    }

    /// Notes that the owning policy session `session` is loading: the arm holds until its first chunk or its
    /// loading deadline. Returns the seconds left until that deadline.
    pub fn policy_loading(&self, session: u64) -> Result<f64, ArmError> {
        let now = now_s();
        self.apply(Input::PolicyLoading { session }, now)
            .map_err(|e| self.refused(e))?;
        let deadline_s = self.inner.lock().arbiter.policy_loading_until();
        Ok(deadline_s.map_or(0.0, |d| (d - now).max(0.0)))
    }

    /// Schedules a chunk for the owning policy session. `reference` is the measured pose of the observation
    /// the chunk answers (relative steps are composed onto it), `observed_s` the time it was taken (after a
    /// hand-back only chunks answering later observations drive) and `anchor_s` the time of step 0.
    #[allow(clippy::too_many_arguments)]
    pub fn push_chunk(
        &self,
        session: u64,
        actions: &[Vec<f64>],
        step_period_s: f64,
        anchor_s: f64,
        observed_s: f64,
        reference: Isometry3<f64>,
        mode: ActionMode,
    ) -> Result<ReplaceReport, ArmError> {
        let steps = self
            .vectors()
            .chunk_steps(actions, &reference, mode)
            .map_err(|e| ArmError::InvalidStep {
                arm: self.name.clone(),
                step: e.step,
                source: e.source,
            })?;
        let chunk = ActionChunk {
            steps,
            anchor_time_s: anchor_s,
            step_period_s,
        };
        let (effects, _) = self
            .apply(
                Input::Chunk {
                    session,
                    chunk,
                    observed_s,
                },
                now_s(),
            )
            .map_err(|e| self.refused(e))?;
        Ok(effects
            .chunk
            .expect("an accepted chunk reports what it scheduled"))
    }

    /// Plays due chunk steps and applies the silence and staleness rules at `now` (s, [`now_s`]).
    pub fn tick(&self, now: f64) {
        self.ticks.fetch_add(1, Ordering::Relaxed);
        // A tick refuses nothing.
        let _ = self.apply(Input::Tick, now);
    }

    /// Re-draws the arm's scene (see `phone2act.v1.Scene.Reset`). `home_arm` is a teleport, so the arbiter
    /// refuses it while a source drives; afterwards the arm holds the homed pose and both sources re-index
    /// from it, so a phone or policy that takes the arm next starts where the arm now is.
    pub fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<SceneState, ArmError> {
        // Held across the reset so that no source can start driving between the check and the teleport.
        let mut inner = self.inner.lock();
        // An arm without a scene says so whoever drives it; its refusal changes nothing.
        if let Err(BridgeError::Unsupported(_)) = self.bridge.scene() {
            return self
                .bridge
                .reset_scene(seed, home_arm)
                .map_err(|e| self.bridge_error(e));
        }
        if home_arm {
            inner.arbiter.may_home().map_err(|e| self.refused(e))?;
        }
        let state = self
            .bridge
            .reset_scene(seed, home_arm)
            .map_err(|e| self.bridge_error(e))?;
        if home_arm && let Some(feedback) = self.bridge.feedback() {
            let robot = robot_of(self.bridge.health(), Some(&feedback));
            let homed = Input::Homed {
                gripper: feedback.gripper_position,
            };
            // Nobody drives (checked above under this lock): the arbiter accepts, sends nothing, revokes nobody.
            let now = now_s();
            if let Some(stage) = inner.joints.as_mut() {
                stage.reset(&feedback.joint_positions_rad, now);
            }
            let handled = self
                .handle_locked(
                    &mut inner,
                    homed,
                    &robot,
                    Some(&feedback.joint_positions_rad),
                    now,
                    None,
                )
                .map_err(|e| self.refused(e))?;
            inner.joint_seed = None;
            drop(inner);
            self.finish(handled);
        }
        Ok(state)
    }

    /// True if the arm works in a scene with a success flag (the simulator's pick-and-place).
    pub fn has_scene(&self) -> bool {
        self.bridge.scene().is_ok()
    }

    /// The arm's scene now.
    pub fn scene(&self) -> Result<SceneState, ArmError> {
        self.bridge.scene().map_err(|e| self.bridge_error(e))
    }

    /// The arm's layout, kinematics and action mode, which its vectors are converted with.
    fn vectors(&self) -> ArmVectors<'_> {
        ArmVectors {
            layout: &self.layout,
            kinematics: self.kinematics.as_ref(),
            action_mode: self.action_mode,
        }
    }

    /// How soon the arm needs a tick.
    fn tick_need(&self) -> TickNeed {
        self.inner.lock().tick_need()
    }

    /// A snapshot for the API.
    pub fn snapshot(&self) -> ArmSnapshot {
        let feedback = self.bridge.feedback();
        let robot = robot_of(self.bridge.health(), feedback.as_ref());
        let now_ns = monotonic_ns();
        let not_ready = robot.not_ready(now_ns as f64 * 1e-9).map(|why| why.to_string());
        let (health, health_message) = match robot.health {
            BridgeHealth::Connecting => (BridgeHealth::Connecting, not_ready.unwrap_or_default()),
            // READY means movable: a bridge that is up but has no fresh measured pose is not.
            BridgeHealth::Ready => match not_ready {
                // Ready, and what the operator should still know (a servo alarm the arm works through).
                None => (BridgeHealth::Ready, self.bridge.warning().unwrap_or_default()),
                Some(why) if feedback.is_none() => (BridgeHealth::Connecting, why),
                Some(why) => (BridgeHealth::Error(why.clone()), why),
            },
            BridgeHealth::Error(m) => (BridgeHealth::Error(m.clone()), m),
            BridgeHealth::Disconnected(m) => (BridgeHealth::Disconnected(m.clone()), m),
        };
        let inner = self.inner.lock();
        let a = &inner.arbiter;
        let owner_id = match a.driver() {
            phone2act_core::Driver::None => String::new(),
            phone2act_core::Driver::Teleop => a.teleop_session().map(|s| s.to_string()).unwrap_or_default(),
            phone2act_core::Driver::Policy => a
                .policy_owner()
                .map(|(session, name)| format!("{name}:{session}"))
                .unwrap_or_default(),
        };
        let (robot_from_target, gripper_target) = a.target();
        ArmSnapshot {
            arm: self.name.clone(),
            bridge_kind: self.kind.to_owned(),
            health,
            health_message,
            driver: a.driver(),
            owner_id,
            engaged: a.engaged(),
            robot_from_target,
            gripper_target,
            robot_from_ee: feedback.as_ref().map(|f| f.robot_from_ee),
            joint_positions_rad: feedback
                .as_ref()
                .map(|f| f.joint_positions_rad.clone())
                .unwrap_or_default(),
            joint_names: self.layout.joint_names().to_vec(),
            gripper_position: feedback.as_ref().map_or(0.0, |f| f.gripper_position),
            last_decision: a.last_decision().clone(),
            feedback_time_ns: feedback.as_ref().map_or(0, |f| f.capture_time_ns),
            feedback_age_s: feedback
                .as_ref()
                .map_or(-1.0, |f| (now_ns - f.capture_time_ns) as f64 * 1e-9),
            counters: a.counters(),
            joint_counters: inner
                .joints
                .as_ref()
                .map(ArmJointStage::counters)
                .unwrap_or_default(),
            joint_targets_rad: inner
                .joints
                .as_ref()
                .and_then(ArmJointStage::commanded)
                .unwrap_or_default(),
            joint_targets_time_ns: inner
                .joints
                .as_ref()
                .filter(|j| j.commanded().is_some())
                .map_or(0, |j| (j.commanded_time_s() * 1e9).round() as i64),
            task_success: feedback.as_ref().is_some_and(|f| f.task_success),
            policy_loading: a.policy_loading_until().is_some(),
            waiting_policy_id: a
                .waiting_policy()
                .map(|(session, name)| format!("{name}:{session}"))
                .unwrap_or_default(),
            plan_preview: a.plan_preview(now_ns as f64 * 1e-9, PREVIEW_MAX_POINTS),
        }
    }

    /// `observation.state` and the executed `action` for the recorder and for policies: the action is the
    /// last gated target, absolute (see `phone2act_core::layout`), so it means the same from any frame; a
    /// joint arm's is the joints that target asks for.
    pub fn state_and_action(&self) -> Option<ArmSample> {
        let feedback = self.bridge.feedback()?;
        let warning = self.bridge.warning().unwrap_or_default();
        let reading = Reading {
            joint_positions_rad: &feedback.joint_positions_rad,
            robot_from_ee: &feedback.robot_from_ee,
            gripper_position: feedback.gripper_position,
        };
        // The activity is read with the target, under the same lock: the recorder's events then describe the
        // very command the frame's action records, and a tick locks each arm once.
        let Sample {
            state,
            action,
            activity,
        } = {
            let mut inner = self.inner.lock();
            let inner = &mut *inner;
            self.vectors().sample(
                &reading,
                &inner.arbiter,
                inner.joints.as_ref(),
                &mut inner.joint_seed,
            )?
        };
        let activity = ArmActivity {
            arm: self.name.clone(),
            arbiter: activity,
            warning,
        };
        Some(ArmSample {
            state,
            action,
            task_success: feedback.task_success,
            robot_from_ee: feedback.robot_from_ee,
            capture_time_ns: feedback.capture_time_ns,
            activity,
        })
    }
}

/// One arm's recorded quantities at one instant.
#[derive(Debug, Clone)]
pub struct ArmSample {
    /// `observation.state` in the core layout.
    pub state: Vec<f64>,
    /// The executed action: the last gated target and gripper target, absolute.
    pub action: Vec<f64>,
    /// The scene's success flag in the same feedback (false for arms without a scene).
    pub task_success: bool,
    /// The measured pose both are taken at.
    pub robot_from_ee: Isometry3<f64>,
    /// Server monotonic time of the feedback.
    pub capture_time_ns: i64,
    /// The clutch and the gate's counters when the action's target was read (the episode's events).
    pub activity: ArmActivity,
}

/// Runs every arm's tick task until shutdown.
pub async fn run_ticks(
    arms: Vec<Arc<ArmController>>,
    rate_hz: f64,
    shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let period = Duration::from_secs_f64(1.0 / rate_hz);
    let tasks: Vec<_> = arms
        .into_iter()
        .map(|arm| tokio::spawn(tick_arm(arm, period, shutdown.clone())))
        .collect();
    for task in tasks {
        let _ = task.await;
    }
}

/// Ticks one arm only while its arbiter has work: at `period` while a chunk plays, a phone drives or the joint
/// stage catches up; once at the arbiter's deadline while a policy owns the arm between chunks (its silence
/// timeout or loading deadline), or earlier if an input changes what the arbiter needs; and not at all when
/// idle (it sleeps until an input wakes it).
async fn tick_arm(
    arm: Arc<ArmController>,
    period: Duration,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        // `notify_one` keeps a permit when nobody waits, so a wake between reading the need and waiting
        // below is not lost.
        match arm.tick_need() {
            TickNeed::Periodic => {
                tokio::select! {
                    _ = ticker.tick() => {}
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
            TickNeed::At(deadline_s) => {
                // The arbiter's rules are "later than" the deadline; the timer's millisecond rounding up gets
                // there, and a tick that comes too early only finds the same deadline again.
                let left_s = deadline_s - now_s();
                let wait = Duration::try_from_secs_f64(left_s).unwrap_or(if left_s > 0.0 {
                    Duration::MAX
                } else {
                    Duration::ZERO
                });
                tokio::select! {
                    () = tokio::time::sleep(wait) => {}
                    // An input changed the need (a chunk, a new deadline, a release): read it again.
                    () = arm.wake.notified() => continue,
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
            TickNeed::Idle => {
                tokio::select! {
                    () = arm.wake.notified() => {}
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
        }
        arm.tick(now_s());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_bridges::sim::{SimBridge, SimConfig};
    use std::time::Instant;

    #[derive(Debug)]
    struct Nobody;

    impl RevocationSink for Nobody {
        fn revoked(&self, _: &str, _: &str) {}
    }

    /// The embedded default's arm on a simulator, in absolute mode.
    fn sim_arm() -> Arc<ArmController> {
        let config = crate::config::Config::embedded_default().unwrap();
        let a = &config.arms[0];
        let bridge = SimBridge::start_with_clock(SimConfig::default(), monotonic_ns).unwrap();
        Arc::new(
            ArmController::new(
                "main",
                "sim",
                bridge,
                &a.teleop,
                &a.chunk,
                ActionMode::Absolute,
                Isometry3::identity(),
            )
            .unwrap(),
        )
    }

    /// Polls `done` until it holds or `limit` passes; returns whether it held.
    async fn eventually(limit: Duration, done: impl Fn() -> bool) -> bool {
        let start = Instant::now();
        while start.elapsed() < limit {
            if done() {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        done()
    }

    /// A simulator whose bridge reports a warning, as the SO-101 bridge does for a servo alarm it works through.
    #[derive(Debug)]
    struct Warned(Arc<SimBridge>);

    impl Bridge for Warned {
        fn kind(&self) -> &'static str {
            self.0.kind()
        }
        fn joint_names(&self) -> &[String] {
            self.0.joint_names()
        }
        fn send(&self, command: phone2act_bridges::Command) {
            self.0.send(command);
        }
        fn feedback(&self) -> Option<Feedback> {
            self.0.feedback()
        }
        fn health(&self) -> Health {
            self.0.health()
        }
        fn warning(&self) -> Option<String> {
            Some("servo 6 (gripper): overload (0x20)".into())
        }
        fn control(&self, request: phone2act_bridges::Control) -> Result<(), phone2act_bridges::BridgeError> {
            self.0.control(request)
        }
        fn shutdown(&self) {
            self.0.shutdown();
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_ready_bridge_warning_is_the_arm_health_message() {
        let config = crate::config::Config::embedded_default().unwrap();
        let a = &config.arms[0];
        let bridge = SimBridge::start_with_clock(SimConfig::default(), monotonic_ns).unwrap();
        let arm = ArmController::new(
            "main",
            "sim",
            Arc::new(Warned(bridge)),
            &a.teleop,
            &a.chunk,
            ActionMode::Absolute,
            Isometry3::identity(),
        )
        .unwrap();
        // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
        assert!(
            eventually(Duration::from_secs(10), || arm.snapshot().health
                == BridgeHealth::Ready)
            .await
        );
        assert_eq!(
            arm.snapshot().health_message,
            "servo 6 (gripper): overload (0x20)"
        );
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_tick_task_sleeps_while_idle_and_wakes_to_play_a_chunk_to_its_end() {
        let arm = sim_arm();
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let ticking = tokio::spawn(run_ticks(vec![Arc::clone(&arm)], 500.0, stopped));
        // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
        assert!(
            eventually(Duration::from_secs(10), || arm.snapshot().health
                == BridgeHealth::Ready)
            .await
        );
        // Nobody drives: whatever the scheduler does, no tick runs (a count, not a time bound).
        tokio::time::sleep(Duration::from_millis(200)).await;
        assert_eq!(arm.ticks(), 0, "an idle arm ticks");

        arm.claim_for_policy(1, "test", Arc::new(Nobody), 30.0).unwrap();
        let here = arm.snapshot().robot_from_ee.unwrap();
        let steps: Vec<Vec<f64>> = (0..5)
            .map(|k| {
                let target = Isometry3::translation(0.002 * f64::from(k), 0.0, 0.0) * here;
                phone2act_core::absolute_action(&target, 0.0)
            })
            .collect();
        let sent_before = arm.snapshot().counters.sent;
        let now = now_s();
        arm.push_chunk(1, &steps, 0.05, now, now, here, ActionMode::Absolute)
            .unwrap();
        // The push plays step 0; only the woken tick task can play steps 1-4 and reach the last step's target
        // (the chunk lasts 0.25 s; 10 s covers any stall of a loaded machine, and a task that was never woken
        // never gets there). A tick more than a step late plays the step due then, so a stall may skip a
        // middle step: the count says only that the tick task sent something.
        let last = Isometry3::translation(0.008, 0.0, 0.0) * here;
        assert!(
            eventually(Duration::from_secs(10), || {
                let s = arm.snapshot();
                s.counters.sent >= sent_before + 2
                    && (s.robot_from_target.translation.vector - last.translation.vector).norm() < 1e-9
            })
            .await,
            "the chunk did not play to its end: {:?}",
            arm.snapshot().counters
        );
        stop.send(true).unwrap();
        ticking.await.unwrap();
    }

    /// Notes when it is told of a revocation.
    #[derive(Debug, Default)]
    struct RevokedAt(parking_lot::Mutex<Option<f64>>);

    impl RevocationSink for RevokedAt {
        fn revoked(&self, _: &str, _: &str) {
            self.0.lock().get_or_insert(now_s());
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_silent_policy_is_released_at_its_deadline_not_at_the_next_periodic_tick() {
        let arm = sim_arm();
        // One periodic tick every 30 s: a release that waited for one would come 30 s late.
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let ticking = tokio::spawn(run_ticks(vec![Arc::clone(&arm)], 1.0 / 30.0, stopped));
        // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
        assert!(
            eventually(Duration::from_secs(10), || arm.snapshot().health
                == BridgeHealth::Ready)
            .await
        );
        let sink = Arc::new(RevokedAt::default());
        let silence_s = 0.3;
        let ticks_before = arm.ticks();
        let claimed_s = now_s();
        arm.claim_for_policy(
            1,
            "silent",
            Arc::clone(&sink) as Arc<dyn RevocationSink>,
            silence_s,
        )
        .unwrap();
        assert!(
            eventually(Duration::from_secs(20), || sink.0.lock().is_some()).await,
            "the silent policy still owns the arm"
        );
        let late_s = sink.0.lock().unwrap() - (claimed_s + silence_s);
        let ticks = arm.ticks() - ticks_before;
        println!(
            "released {:.1} ms after the silence deadline, {ticks} ticks",
            late_s * 1e3
        );
        // Never before the deadline (the claim came after `claimed_s`, so the true deadline is later still).
        assert!(late_s >= 0.0, "released {late_s} s early");
        // The timer wakes within milliseconds; a 2-core machine at load 20 delays a ready task by tens of
        // milliseconds, far below the 30 s a periodic tick would take.
        assert!(late_s < 2.0, "released {late_s} s after the deadline");
        // The tick task slept: the tick the claim's wake-up runs (which reads the deadline), the deadline's
        // tick, and at most one tick that the timer ran just short of the deadline (the monotonic clock and
        // tokio's timer are read apart; that tick finds the same deadline and sleeps the rest). A periodic
        // 500 Hz tick would have made about 150 over the 0.3 s.
        assert!(
            ticks <= 3,
            "{ticks} ticks while the arm waited for a silent policy"
        );
        assert_eq!(arm.snapshot().driver, phone2act_core::Driver::None);
        stop.send(true).unwrap();
        ticking.await.unwrap();
    }
}
