//! Arm controllers: one per configured arm, the single place where teleop samples and policy chunks become
//! bridge commands. Both sources pass the same safety gate and the same bridge; one source drives an arm
//! at a time, the operator can always take over from the phone, and a source that goes silent leaves the
//! arm holding.
//!
//! The critical section is a `std::sync::Mutex` held for microseconds and never across an `.await`, so the
//! control path is a straight function call from the gRPC handler to [`Bridge::send`] (which never blocks).

use nalgebra::Isometry3;
use phone2act_bridges::sim::SceneState;
use phone2act_bridges::{Bridge, BridgeError, Command, Feedback, Health};
use phone2act_clock::monotonic_ns;
use phone2act_core::{
    ActionChunk, ActionMode, ArmLayout, ChunkConfig, ChunkExecutor, ChunkStep, ClutchKind, GateDecision,
    GateVerdict, GripperCommand, ReplaceReport, SafetyGate, TeleopArm, TeleopConfig,
};
use phone2act_proto::v1;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use tokio::sync::mpsc;
use tonic::Status;

/// Feedback older than this means the robot's pose is not known: nothing may start moving it. Bridges
/// report at 50 Hz or more (Dobot 125 Hz, SO-101 at its `rate_hz`, sim and remote 50 Hz), so a second is
/// dozens of missed reports, not jitter or a scheduler stall on a loaded machine.
const FEEDBACK_MAX_AGE_S: f64 = 1.0;

/// Seconds on the process monotonic clock.
pub fn now_s() -> f64 {
    monotonic_ns() as f64 * 1e-9
}

/// Who drives the arm right now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Driver {
    None,
    Teleop,
    Policy,
}

/// The policy session that owns (or may own) the arm.
#[derive(Debug)]
struct PolicyOwner {
    session_id: u64,
    name: String,
    events: mpsc::Sender<v1::PolicyEvent>,
    silence_timeout_s: f64,
    last_chunk_s: f64,
}

#[derive(Debug)]
struct Inner {
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
    /// The last joint action computed (joint arms): the seed of the next, so the recorder's inverse kinematics
    /// follows its solutions from one to the next as the bridge's does, rather than restarting from the
    /// lagging measured joints (which, for an orientation a 5-DoF arm cannot reach, lands elsewhere).
    joint_seed: Option<Vec<f64>>,
    seq: u64,
    commands_sent: u64,
    commands_rejected: u64,
    commands_clamped: u64,
}

/// What one teleop sample did.
#[derive(Debug, Clone)]
pub struct TeleopOutcome {
    /// Per-sample error for the phone (invalid pose, bad gripper value); empty when fine.
    pub error: String,
    /// Record button events to forward to the recorder, in order.
    pub record: Vec<v1::RecordCommand>,
    /// Server time the command (if any) was handed to the bridge.
    pub command_time_ns: Option<i64>,
}

/// The teleop input of one processing round: the newest pose and every button event since the last round.
#[derive(Debug, Default)]
pub struct TeleopInput {
    /// Newest pose (already validated) or the validation error.
    pub pose: Option<Result<Isometry3<f64>, String>>,
    pub tracking_ok: bool,
    pub buttons: Vec<v1::ButtonEvent>,
}

/// One arm.
pub struct ArmController {
    pub name: String,
    pub kind: &'static str,
    pub bridge: Arc<dyn Bridge>,
    pub layout: ArmLayout,
    pub action_mode: ActionMode,
    /// Forward/inverse kinematics for joint actions (arms whose joints are the SO-101's).
    kinematics: Option<phone2act_core::kinematics::So101Kinematics>,
    inner: Mutex<Inner>,
    /// Control-path latency of recent teleop commands (sample received → handed to the bridge), ns.
    latencies_ns: Mutex<LatencyRing>,
    samples_received: AtomicU64,
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

impl std::fmt::Debug for ArmController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ArmController")
            .field("name", &self.name)
            .field("kind", &self.kind)
            .finish_non_exhaustive()
    }
}

/// Errors building an arm controller.
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
        let config_err = |source| ArmError::Config {
            arm: name.to_owned(),
            source,
        };
        let measured = bridge.feedback().map_or(fallback, |f| f.robot_from_ee);
        let gripper = bridge.feedback().map_or(0.0, |f| f.gripper_position);
        let layout = ArmLayout::new(bridge.joint_names().to_vec());
        let kinematics = (bridge.joint_names() == phone2act_core::kinematics::SO101_ARM_JOINT_NAMES)
            .then(phone2act_core::kinematics::So101Kinematics::new);
        if action_mode == ActionMode::Joint && kinematics.is_none() {
            return Err(ArmError::JointModeUnsupported {
                arm: name.to_owned(),
                joints: bridge.joint_names().to_vec(),
            });
        }
        let inner = Inner {
            teleop: TeleopArm::new(teleop, measured).map_err(config_err)?,
            policy_gate: SafetyGate::new(&teleop.gate, measured).map_err(config_err)?,
            executor: ChunkExecutor::new(chunk.clone()).map_err(config_err)?,
            teleop_session: None,
            driver: Driver::None,
            policy: None,
            target: measured,
            gripper_target: gripper,
            last_decision: GateDecision::note(GateVerdict::Accepted, "idle"),
            last_policy_step: None,
            joint_seed: None,
            seq: 0,
            commands_sent: 0,
            commands_rejected: 0,
            commands_clamped: 0,
        };
        Ok(Self {
            name: name.to_owned(),
            kind,
            bridge,
            layout,
            action_mode,
            kinematics,
            inner: Mutex::new(inner),
            latencies_ns: Mutex::new(LatencyRing::default()),
            samples_received: AtomicU64::new(0),
        })
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

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn measured_or(&self, fallback: Isometry3<f64>) -> Isometry3<f64> {
        self.bridge.feedback().map_or(fallback, |f| f.robot_from_ee)
    }

    /// Why the arm may not be moved now, if it may not: its bridge is not healthy, or it has no fresh
    /// measured pose. Anything that starts motion (engaging, a gripper command, a policy claim) checks
    /// this, so that no command ever starts from a pose nobody measured.
    pub fn not_ready(&self) -> Option<String> {
        self.not_ready_given(self.bridge.feedback().as_ref(), monotonic_ns())
    }

    /// [`Self::not_ready`] for feedback the caller already read at `now_ns` (the per-sample path reads it once).
    fn not_ready_given(&self, feedback: Option<&Feedback>, now_ns: i64) -> Option<String> {
        match self.bridge.health() {
            Health::Error(m) => return Some(format!("its bridge reports an error: {m}")),
            Health::Disconnected(m) => return Some(format!("its bridge is disconnected: {m}")),
            Health::Connecting if feedback.is_some() => {
                return Some("its bridge is still connecting".to_owned());
            }
            // Ready, or connecting without feedback yet: the missing feedback is the reason given below.
            Health::Ready | Health::Connecting => {}
        }
        let Some(feedback) = feedback else {
            return Some("its bridge has sent no valid feedback yet (no measured pose)".to_owned());
        };
        let age_s = (now_ns - feedback.capture_time_ns) as f64 * 1e-9;
        (age_s > FEEDBACK_MAX_AGE_S)
            .then(|| format!("its last measured pose is {age_s:.2} s old (more than {FEEDBACK_MAX_AGE_S} s)"))
    }

    /// Hands a gated command to the bridge. Called with the lock held so `seq` order equals send order.
    fn send(&self, inner: &mut Inner, target: Isometry3<f64>, gripper: f64) -> i64 {
        inner.seq += 1;
        inner.target = target;
        inner.gripper_target = gripper;
        inner.commands_sent += 1;
        let issue_time_ns = monotonic_ns();
        self.bridge.send(Command {
            seq: inner.seq,
            robot_from_target: target,
            gripper_target: gripper,
            issue_time_ns,
        });
        issue_time_ns
    }

    fn record_decision(inner: &mut Inner, decision: GateDecision) {
        match decision.verdict {
            GateVerdict::RejectedJump | GateVerdict::RejectedInvalid => inner.commands_rejected += 1,
            GateVerdict::Clamped => inner.commands_clamped += 1,
            GateVerdict::Accepted | GateVerdict::HeldStale => {}
        }
        inner.last_decision = decision;
    }

    /// Binds a teleop session. A second phone is refused unless it takes over.
    pub fn bind_teleop(&self, session_id: u64, take_over: bool) -> Result<(), Status> {
        let mut inner = self.lock();
        match inner.teleop_session {
            Some(other) if other != session_id && !take_over => Err(Status::already_exists(format!(
                "arm {:?} is already bound to another phone; set take_over to replace it",
                self.name
            ))),
            _ => {
                inner.teleop_session = Some(session_id);
                if inner.driver == Driver::Teleop {
                    // The replaced phone was driving: the new one starts disengaged.
                    inner.driver = Driver::None;
                    let measured = self.measured_or(inner.target);
                    let now = now_s();
                    inner.teleop.clutch(ClutchKind::Disengage, None, measured, now);
                }
                Ok(())
            }
        }
    }

    /// Ends a teleop session; the arm holds if it was driving.
    pub fn unbind_teleop(&self, session_id: u64) {
        let mut inner = self.lock();
        if inner.teleop_session == Some(session_id) {
            inner.teleop_session = None;
            if inner.driver == Driver::Teleop {
                inner.driver = Driver::None;
                let measured = self.measured_or(inner.target);
                inner
                    .teleop
                    .clutch(ClutchKind::Disengage, None, measured, now_s());
                Self::record_decision(
                    &mut inner,
                    GateDecision::note(GateVerdict::Accepted, "phone disconnected: the arm holds"),
                );
            }
        }
    }

    /// Records one control-path latency and the number of samples a round merged.
    pub fn note_round(&self, samples: u64, latency_ns: Option<i64>) {
        self.samples_received.fetch_add(samples, Ordering::Relaxed);
        if let Some(ns) = latency_ns {
            self.latencies_ns
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .push(ns);
        }
    }

    /// Recent control-path latencies (ns, unordered) and the count of all latencies ever recorded.
    pub fn latencies_ns(&self) -> (Vec<u32>, u64) {
        let ring = self.latencies_ns.lock().unwrap_or_else(PoisonError::into_inner);
        (ring.values_ns.clone(), ring.total)
    }

    /// Teleop samples received (including those superseded by newer ones) since start.
    pub fn samples_received(&self) -> u64 {
        self.samples_received.load(Ordering::Relaxed)
    }

    /// Clears the latency ring (between benchmark phases).
    pub fn reset_latencies(&self) {
        *self.latencies_ns.lock().unwrap_or_else(PoisonError::into_inner) = LatencyRing::default();
    }

    /// True if `session_id` is the bound teleop session.
    pub fn is_teleop_bound(&self, session_id: u64) -> bool {
        self.lock().teleop_session == Some(session_id)
    }

    /// Processes one round of teleop input for the bound session.
    pub fn teleop_input(&self, session_id: u64, input: TeleopInput) -> Result<TeleopOutcome, Status> {
        let now_ns = monotonic_ns();
        let now = now_ns as f64 * 1e-9;
        let mut inner = self.lock();
        if inner.teleop_session != Some(session_id) {
            return Err(Status::aborted(format!(
                "another phone took over arm {:?}",
                self.name
            )));
        }
        let mut outcome = TeleopOutcome {
            error: String::new(),
            record: Vec::new(),
            command_time_ns: None,
        };
        let pose = match &input.pose {
            Some(Ok(p)) => Some(*p),
            Some(Err(e)) => {
                outcome.error.clone_from(e);
                // A malformed pose (non-unit quaternion, NaN) is a refused command like any other: counted and
                // shown as the verdict, unless a policy drives and the verdict on display is its own.
                if inner.driver != Driver::Policy {
                    Self::record_decision(
                        &mut inner,
                        GateDecision::note(GateVerdict::RejectedInvalid, format!("invalid phone pose: {e}")),
                    );
                }
                None
            }
            None => None,
        };
        for event in input.buttons {
            match event.event {
                Some(v1::button_event::Event::Clutch(c)) => {
                    let kind = match v1::clutch_command::Kind::try_from(c.kind) {
                        Ok(v1::clutch_command::Kind::Toggle) => ClutchKind::Toggle,
                        Ok(v1::clutch_command::Kind::Engage) => ClutchKind::Engage,
                        Ok(v1::clutch_command::Kind::Disengage) => ClutchKind::Disengage,
                        _ => {
                            outcome.error = format!("unknown clutch kind {}", c.kind);
                            continue;
                        }
                    };
                    self.clutch_locked(&mut inner, kind, pose, now, &mut outcome);
                }
                Some(v1::button_event::Event::Gripper(g)) => {
                    let command = match v1::gripper_command::Kind::try_from(g.kind) {
                        Ok(v1::gripper_command::Kind::Toggle) => GripperCommand::Toggle,
                        Ok(v1::gripper_command::Kind::Set) => GripperCommand::Set(g.position),
                        _ => {
                            outcome.error = format!("unknown gripper kind {}", g.kind);
                            continue;
                        }
                    };
                    if let Some(why) = self.not_ready() {
                        outcome.error = format!("arm {:?} is not ready: {why}", self.name);
                        continue;
                    }
                    match inner.teleop.gripper(command) {
                        Ok(gripper) => {
                            // The gripper follows the phone only while the phone drives or nobody does.
                            if inner.driver != Driver::Policy {
                                let target = inner.target;
                                outcome.command_time_ns = Some(self.send(&mut inner, target, gripper));
                            }
                        }
                        Err(e) => outcome.error = e.to_string(),
                    }
                }
                Some(v1::button_event::Event::Record(r)) => outcome.record.push(r),
                None => "empty button event".clone_into(&mut outcome.error),
            }
        }
        // One feedback read serves the readiness check and the planner: this runs for every phone sample.
        let feedback = self.bridge.feedback();
        let measured = feedback.as_ref().map_or(inner.target, |f| f.robot_from_ee);
        if inner.driver == Driver::Teleop
            && let Some(why) = self.not_ready_given(feedback.as_ref(), now_ns)
        {
            // The robot went away under the phone: stop driving and say so, rather than accept samples that
            // go nowhere (or, on reconnect, continue from a pose measured before).
            inner.driver = Driver::None;
            inner.teleop.clutch(ClutchKind::Disengage, None, measured, now);
            let message = format!(
                "arm {:?} is not ready: {why}; disengaged, the arm holds",
                self.name
            );
            outcome.error.clone_from(&message);
            Self::record_decision(&mut inner, GateDecision::note(GateVerdict::HeldStale, message));
        }
        if let Some(phone) = pose {
            let step = inner.teleop.on_pose(phone, input.tracking_ok, measured, now);
            if inner.driver == Driver::Teleop {
                if let Some((target, gripper)) = step.command {
                    outcome.command_time_ns = Some(self.send(&mut inner, target, gripper));
                }
                Self::record_decision(&mut inner, step.decision);
            }
        }
        Ok(outcome)
    }

    fn clutch_locked(
        &self,
        inner: &mut Inner,
        kind: ClutchKind,
        phone: Option<Isometry3<f64>>,
        now: f64,
        outcome: &mut TeleopOutcome,
    ) {
        let engaging = match kind {
            ClutchKind::Engage => true,
            ClutchKind::Toggle => !inner.teleop.engaged(),
            ClutchKind::Disengage => false,
        };
        if engaging && let Some(why) = self.not_ready() {
            outcome.error = format!("arm {:?} is not ready, not engaging: {why}", self.name);
            return;
        }
        let measured = self.measured_or(inner.target);
        let step = inner.teleop.clutch(kind, phone, measured, now);
        if step.engaged {
            if inner.driver == Driver::Policy {
                self.revoke_policy_locked(inner, "operator took over from phone");
            }
            inner.driver = Driver::Teleop;
            if let Some((target, gripper)) = step.command {
                outcome.command_time_ns = Some(self.send(inner, target, gripper));
            } else {
                // Engaging re-indexes at the measured pose: that is the target now.
                inner.target = inner.teleop.target();
            }
        } else if inner.driver == Driver::Teleop {
            inner.driver = Driver::None;
        }
        Self::record_decision(inner, step.decision);
    }

    fn revoke_policy_locked(&self, inner: &mut Inner, reason: &str) {
        inner.executor.clear();
        inner.last_policy_step = None;
        if inner.driver == Driver::Policy {
            inner.driver = Driver::None;
        }
        if let Some(owner) = inner.policy.take() {
            tracing::info!(arm = %self.name, policy = ?owner.name, reason, "policy control revoked");
            // Latest wins: if the session's event queue is full it is stalled anyway and will see the closed
            // ownership on its next chunk.
            let _ = owner.events.try_send(v1::PolicyEvent {
                event: Some(v1::policy_event::Event::Revoked(v1::ControlRevoked {
                    arm: self.name.clone(),
                    reason: reason.to_owned(),
                })),
            });
        }
    }

    /// Gives the arm to a policy session. Refused while a phone drives it.
    pub fn claim_for_policy(
        &self,
        session_id: u64,
        name: &str,
        events: mpsc::Sender<v1::PolicyEvent>,
        silence_timeout_s: f64,
    ) -> Result<(), Status> {
        let mut inner = self.lock();
        if inner.driver == Driver::Teleop {
            return Err(Status::failed_precondition(format!(
                "arm {:?} is driven by a phone; the operator must disengage first",
                self.name
            )));
        }
        if let Some(why) = self.not_ready() {
            return Err(Status::failed_precondition(format!(
                "arm {:?} is not ready: {why}",
                self.name
            )));
        }
        if let Some(owner) = &inner.policy
            && owner.session_id != session_id
        {
            return Err(Status::failed_precondition(format!(
                "arm {:?} is already controlled by policy {:?}",
                self.name, owner.name
            )));
        }
        let measured = self.measured_or(inner.target);
        let now = now_s();
        inner.policy_gate.reset_reference_at(measured, now);
        inner.executor.clear();
        inner.last_policy_step = None;
        inner.driver = Driver::Policy;
        inner.policy = Some(PolicyOwner {
            session_id,
            name: name.to_owned(),
            events,
            silence_timeout_s,
            last_chunk_s: now,
        });
        // The phone's floating zero is stale once a policy moves the arm.
        inner.teleop.request_reindex();
        Self::record_decision(
            &mut inner,
            GateDecision::note(GateVerdict::Accepted, format!("policy {name} in control")),
        );
        Ok(())
    }

    /// Releases the arm if `session_id` owns it; the arm holds.
    pub fn release_policy(&self, session_id: u64, reason: &str) {
        let mut inner = self.lock();
        if inner.policy.as_ref().is_some_and(|o| o.session_id == session_id) {
            self.revoke_policy_locked(&mut inner, reason);
        }
    }

    /// Schedules a chunk for the owning policy session. `reference` is the measured pose of the observation
    /// the chunk answers (relative steps are composed onto it) and `anchor_s` the time of step 0.
    pub fn push_chunk(
        &self,
        session_id: u64,
        actions: &[Vec<f64>],
        step_period_s: f64,
        anchor_s: f64,
        reference: Isometry3<f64>,
        mode: ActionMode,
    ) -> Result<ReplaceReport, Status> {
        let mut steps = Vec::with_capacity(actions.len());
        for (k, action) in actions.iter().enumerate() {
            let converted = match (mode, &self.kinematics) {
                (ActionMode::Joint, Some(kinematics)) => phone2act_core::target_from_joint_step(
                    kinematics,
                    &self.layout.joint_step_to_native(action),
                ),
                _ => phone2act_core::target_from_step(&reference, action, mode),
            };
            let (robot_from_target, gripper) = converted
                .map_err(|e| Status::invalid_argument(format!("arm {:?} step {k}: {e}", self.name)))?;
            steps.push(ChunkStep {
                robot_from_target,
                gripper,
            });
        }
        let now = now_s();
        let mut inner = self.lock();
        let driving = inner.driver == Driver::Policy;
        match &mut inner.policy {
            Some(owner) if owner.session_id == session_id && driving => {
                owner.last_chunk_s = now;
            }
            _ => {
                return Err(Status::failed_precondition(format!(
                    "this policy session does not control arm {:?}",
                    self.name
                )));
            }
        }
        let report = inner
            .executor
            .replace(
                ActionChunk {
                    steps,
                    anchor_time_s: anchor_s,
                    step_period_s,
                },
                now,
            )
            .map_err(|e| Status::invalid_argument(format!("arm {:?}: {e}", self.name)))?;
        drop(inner);
        self.tick(now);
        Ok(report)
    }

    /// Periodic work: plays due chunk steps, and applies the silence and staleness rules.
    pub fn tick(&self, now: f64) {
        let mut inner = self.lock();
        match inner.driver {
            Driver::Policy => {
                let step = inner.executor.target_at(now);
                match step {
                    Some(step) if inner.last_policy_step != Some(step) => {
                        inner.last_policy_step = Some(step);
                        // Silence counts from when the policy's plan runs out, not from the chunk's arrival.
                        if let Some(owner) = inner.policy.as_mut() {
                            owner.last_chunk_s = owner.last_chunk_s.max(now);
                        }
                        let (gated, decision) = inner.policy_gate.check(step.robot_from_target, now);
                        if let Some(target) = gated {
                            self.send(&mut inner, target, step.gripper.clamp(0.0, 1.0));
                        }
                        Self::record_decision(&mut inner, decision);
                    }
                    Some(_) => {
                        if let Some(owner) = inner.policy.as_mut() {
                            owner.last_chunk_s = owner.last_chunk_s.max(now);
                        }
                    }
                    None => {
                        let silent = inner
                            .policy
                            .as_ref()
                            .map(|o| (now - o.last_chunk_s, o.silence_timeout_s));
                        if let Some((silent_s, timeout_s)) = silent
                            && silent_s > timeout_s
                        {
                            self.revoke_policy_locked(&mut inner, &format!("silent for {silent_s:.2} s"));
                            Self::record_decision(
                                &mut inner,
                                GateDecision::note(
                                    GateVerdict::HeldStale,
                                    format!("policy silent for {silent_s:.2} s: holding"),
                                ),
                            );
                        }
                    }
                }
            }
            Driver::Teleop => {
                if let Some(decision) = inner.teleop.check_stale(now) {
                    Self::record_decision(&mut inner, decision);
                }
            }
            Driver::None => {}
        }
    }

    /// Re-draws the arm's scene (see `phone2act.v1.Scene.Reset`). `home_arm` is a teleport, so it is refused
    /// while a source drives; afterwards the target is the homed pose and both sources re-index from it, so a
    /// phone or policy that takes the arm next starts where the arm now is.
    pub fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<SceneState, Status> {
        // Held across the reset so that no source can start driving between the check and the teleport.
        let mut inner = self.lock();
        // An arm without a scene says so whoever drives it; its refusal changes nothing.
        if let Err(BridgeError::Unsupported(_)) = self.bridge.scene() {
            return self
                .bridge
                .reset_scene(seed, home_arm)
                .map_err(|e| bridge_status(&self.name, &e));
        }
        if home_arm {
            let owner = match inner.driver {
                Driver::None => None,
                Driver::Teleop => Some(format!(
                    "a phone (teleop session {})",
                    inner.teleop_session.unwrap_or_default()
                )),
                Driver::Policy => Some(format!(
                    "policy {:?}",
                    inner.policy.as_ref().map(|o| o.name.as_str()).unwrap_or_default()
                )),
            };
            if let Some(owner) = owner {
                return Err(Status::failed_precondition(format!(
                    "arm {:?} is driven by {owner}; release it before homing the arm",
                    self.name
                )));
            }
        }
        let state = self
            .bridge
            .reset_scene(seed, home_arm)
            .map_err(|e| bridge_status(&self.name, &e))?;
        if home_arm && let Some(feedback) = self.bridge.feedback() {
            let now = now_s();
            inner.target = feedback.robot_from_ee;
            inner.gripper_target = feedback.gripper_position;
            inner.joint_seed = None;
            inner.teleop.request_reindex();
            inner.policy_gate.reset_reference_at(feedback.robot_from_ee, now);
        }
        Ok(state)
    }

    /// True if the arm works in a scene with a success flag (the simulator's pick-and-place).
    pub fn has_scene(&self) -> bool {
        self.bridge.scene().is_ok()
    }

    /// The arm's scene now.
    pub fn scene(&self) -> Result<SceneState, Status> {
        self.bridge.scene().map_err(|e| bridge_status(&self.name, &e))
    }

    /// Who drives the arm.
    pub fn driver(&self) -> Driver {
        self.lock().driver
    }

    /// Last target and gripper target handed to the bridge.
    pub fn target(&self) -> (Isometry3<f64>, f64) {
        let inner = self.lock();
        (inner.target, inner.gripper_target)
    }

    /// Whether the operator's clutch is in, the gate's rejected and clamped counters, and the reason of its
    /// last decision: what the recorder turns into the episode's clutch and gate events.
    pub fn clutch_and_gate(&self) -> (bool, u64, u64, String) {
        let inner = self.lock();
        (
            inner.driver == Driver::Teleop && inner.teleop.engaged(),
            inner.commands_rejected,
            inner.commands_clamped,
            inner.last_decision.reason.clone(),
        )
    }

    /// A snapshot for the API.
    pub fn snapshot(&self) -> v1::ArmState {
        let feedback = self.bridge.feedback();
        let health = self.bridge.health();
        let inner = self.lock();
        let (owner, owner_id) = match inner.driver {
            Driver::None => (v1::ControlSource::None, String::new()),
            Driver::Teleop => (
                v1::ControlSource::Teleop,
                inner.teleop_session.map(|s| s.to_string()).unwrap_or_default(),
            ),
            Driver::Policy => (
                v1::ControlSource::Policy,
                inner
                    .policy
                    .as_ref()
                    .map(|o| format!("{}:{}", o.name, o.session_id))
                    .unwrap_or_default(),
            ),
        };
        let (health, health_message) = match health {
            Health::Connecting => (v1::BridgeHealth::Connecting, self.not_ready().unwrap_or_default()),
            // READY means movable: a bridge that is up but has no fresh measured pose is not.
            Health::Ready => match self.not_ready() {
                None => (v1::BridgeHealth::Ready, String::new()),
                Some(why) if feedback.is_none() => (v1::BridgeHealth::Connecting, why),
                Some(why) => (v1::BridgeHealth::Error, why),
            },
            Health::Error(m) => (v1::BridgeHealth::Error, m),
            Health::Disconnected(m) => (v1::BridgeHealth::Disconnected, m),
        };
        let now = monotonic_ns();
        v1::ArmState {
            arm: self.name.clone(),
            bridge_kind: self.kind.to_owned(),
            health: health as i32,
            health_message,
            owner: owner as i32,
            owner_id,
            engaged: inner.driver == Driver::Teleop && inner.teleop.engaged(),
            robot_from_target: Some(pose_to_proto(&inner.target)),
            robot_from_ee: feedback.as_ref().map(|f| pose_to_proto(&f.robot_from_ee)),
            joint_positions_rad: feedback
                .as_ref()
                .map(|f| f.joint_positions_rad.clone())
                .unwrap_or_default(),
            joint_names: self.layout.joint_names().to_vec(),
            gripper_position: feedback.as_ref().map_or(0.0, |f| f.gripper_position),
            gripper_target: inner.gripper_target,
            last_decision: Some(decision_to_proto(&inner.last_decision)),
            feedback_time_ns: feedback.as_ref().map_or(0, |f| f.capture_time_ns),
            feedback_age_s: feedback
                .as_ref()
                .map_or(-1.0, |f| (now - f.capture_time_ns) as f64 * 1e-9),
            commands_sent: inner.commands_sent,
            commands_rejected: inner.commands_rejected,
            commands_clamped: inner.commands_clamped,
            task_success: feedback.as_ref().is_some_and(|f| f.task_success),
        }
    }

    /// `observation.state` and the executed `action` for the recorder and for policies: the action is the
    /// last gated target, absolute (see `phone2act_core::layout`), so it means the same from any frame; a
    /// joint arm's is the joints that target asks for.
    pub fn state_and_action(&self) -> Option<ArmSample> {
        let feedback = self.bridge.feedback()?;
        let (target, gripper) = self.target();
        let state = self
            .layout
            .state_vector(
                &feedback.joint_positions_rad,
                &feedback.robot_from_ee,
                feedback.gripper_position,
            )
            .ok()?;
        let action = match (self.action_mode, &self.kinematics) {
            (ActionMode::Joint, Some(kinematics)) => {
                let mut inner = self.lock();
                let seed = inner
                    .joint_seed
                    .take()
                    .unwrap_or_else(|| feedback.joint_positions_rad.clone());
                let native = phone2act_core::joint_action(kinematics, &target, &seed, gripper).ok()?;
                inner.joint_seed = Some(native[..native.len() - 1].to_vec());
                drop(inner);
                self.layout.joint_step_from_native(&native)
            }
            _ => phone2act_core::absolute_action(&target, gripper),
        };
        Some(ArmSample {
            state,
            action,
            task_success: feedback.task_success,
            robot_from_ee: feedback.robot_from_ee,
            capture_time_ns: feedback.capture_time_ns,
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
}

/// A bridge's refusal as a status: a feature the bridge lacks is UNIMPLEMENTED, anything else INTERNAL.
fn bridge_status(arm: &str, error: &BridgeError) -> Status {
    match error {
        BridgeError::Unsupported(m) => Status::unimplemented(format!("arm {arm:?}: {m}")),
        other => Status::internal(format!("arm {arm:?}: {other}")),
    }
}

/// Proto pose from an isometry.
pub fn pose_to_proto(pose: &Isometry3<f64>) -> v1::Pose {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    v1::Pose::from_parts([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// Proto gate decision from the core's.
pub fn decision_to_proto(d: &GateDecision) -> v1::GateDecision {
    let verdict = match d.verdict {
        GateVerdict::Accepted => v1::GateVerdict::Accepted,
        GateVerdict::Clamped => v1::GateVerdict::Clamped,
        GateVerdict::RejectedJump => v1::GateVerdict::RejectedJump,
        GateVerdict::RejectedInvalid => v1::GateVerdict::RejectedInvalid,
        GateVerdict::HeldStale => v1::GateVerdict::HeldStale,
    };
    v1::GateDecision {
        verdict: verdict as i32,
        reason: d.reason.clone(),
        workspace_clamped: d.workspace_clamped,
        velocity_limited: d.velocity_limited,
        position_step_m: d.position_step_m,
        rotation_step_rad: d.rotation_step_rad,
    }
}

/// Validates a wire pose into an isometry, with an error the phone can show.
pub fn pose_from_proto(pose: &v1::Pose) -> Result<Isometry3<f64>, String> {
    let p = pose.position_m.as_ref().ok_or("pose has no position_m")?;
    let q = pose.orientation.as_ref().ok_or("pose has no orientation")?;
    phone2act_core::validate_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]).map_err(|e| e.to_string())
}

/// Runs `tick` on every arm at `rate_hz` until shutdown.
pub async fn run_ticks(
    arms: Vec<Arc<ArmController>>,
    rate_hz: f64,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut ticker = tokio::time::interval(std::time::Duration::from_secs_f64(1.0 / rate_hz));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = ticker.tick() => {}
            () = crate::runtime::stopped(&mut shutdown) => return,
        }
        let now = now_s();
        for arm in &arms {
            arm.tick(now);
        }
    }
}
