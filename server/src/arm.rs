//! Arm controllers: one per configured arm, the shell around its [`ArmControl`] (the arbiter's source
//! arbitration, the joint stage and what is computed from them, in `phone2act_core::arm_control`). The shell
//! reads the bridge and the clock, hands the state one input at a time under a lock, and carries out what it
//! returns: commands go to [`Bridge::send`] in order, inputs to the flight log, a revoked policy session is
//! told, and the tick task is woken when the arm needs ticks.
//!
//! Building a controller from its configuration is in `setup`, its refusals in `error`, the tick task in `ticks`.
//!
//! The critical section is a `parking_lot::Mutex` (it does not poison: see the `inner` field) held for
//! microseconds and never across an `.await`, so the control path is a straight function call from the gRPC
//! handler to the bridge (which never blocks).

use crate::control_stats::ControlStats;
use crate::flight_log::FlightLogWriter;
use nalgebra::Isometry3;
use parking_lot::Mutex;
use phone2act_bridges::sim::SceneState;
use phone2act_bridges::{Bridge, BridgeError, Feedback};
use phone2act_clock::{monotonic_ns, monotonic_s};
use phone2act_core::arm_control::robot;
use phone2act_core::kinematics::So101Kinematics;
use phone2act_core::{
    ActionChunk, ActionMode, ArbiterError, ArmControl, ArmLayout, ArmNames, ArmSnapshot, ArmVectors, Command,
    Driver, Effects, FlightEntry, Input, Issue, Outcome, ReplaceReport, Robot, Sample, TeleopRound, TickNeed,
};
use phone2act_dataset::events::ArmActivity;
use std::sync::Arc;
use tokio::sync::Notify;

/// Where a policy session hears that it lost an arm, or that the operator took it or handed it back. Called
/// after the arm's lock is released; must not block (the control path calls it).
pub trait RevocationSink: Send + Sync + std::fmt::Debug {
    fn revoked(&self, arm: &str, reason: &str);
    /// The operator took the arm: the session waits, keeping it reserved.
    fn paused(&self, _arm: &str, _reason: &str) {}
    /// The operator handed the arm back to the waiting session.
    fn resumed(&self, _arm: &str) {}
}

/// What one teleop round did.
#[derive(Debug, Clone)]
pub struct TeleopOutcome {
    /// Per-sample error for the phone (invalid pose, bad gripper value); empty when fine.
    pub error: String,
    /// Server time the last command (if any) was handed to the bridge.
    pub command_time_ns: Option<i64>,
}

#[derive(Debug)]
struct Inner {
    control: ArmControl,
    /// The owning policy session's event sink (the arbiter knows only its id).
    policy_sink: Option<(u64, Arc<dyn RevocationSink>)>,
    /// The flight recorder, when on: every input handed to the arbiter, in order, under this lock.
    flight: Option<FlightLogWriter>,
}

/// One input handled under the lock, with what is left to do once it is released.
struct AfterUnlock {
    effects: Effects,
    /// Server time the last command was handed to the bridge.
    command_time_ns: Option<i64>,
    /// The revoked policy session's sink, to be told without the lock.
    revoked: Option<Arc<dyn RevocationSink>>,
    /// The sink of the session the operator took the arm from or handed it back to.
    turned: Option<Arc<dyn RevocationSink>>,
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
    /// Wakes this arm's tick task when the arm starts needing ticks.
    wake: Notify,
    stats: ControlStats,
}

impl std::fmt::Debug for ArmController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ArmController")
            .field("name", &self.name)
            .field("kind", &self.kind)
            .finish_non_exhaustive()
    }
}

impl ArmController {
    /// The bridge's feedback and state, read once for one input.
    fn read_bridge(&self) -> (Option<Feedback>, Robot) {
        let feedback = self.bridge.feedback();
        let robot = robot(
            self.bridge.health().into(),
            feedback.as_ref().map(Feedback::reading).as_ref(),
        );
        (feedback, robot)
    }

    /// Hands `input` to the arm at `now` (s, [`monotonic_s`]) with the bridge's state read now, and carries out
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
        let (feedback, robot) = self.read_bridge();
        let measured_joints = feedback.as_ref().map(|f| f.joint_positions_rad.as_slice());
        let mut inner = self.inner.lock();
        let handled = self.handle_locked(&mut inner, input, &robot, measured_joints, now, sink)?;
        drop(inner);
        Ok(self.finish(handled))
    }

    /// Hands `input` to the arm's state under the held lock, logs it, and sends its commands. The caller
    /// releases the lock and then [`Self::finish`]es.
    fn handle_locked(
        &self,
        inner: &mut Inner,
        input: Input,
        robot: &Robot,
        measured_joints: Option<&[f64]>,
        now: f64,
        sink: Option<(u64, Arc<dyn RevocationSink>)>,
    ) -> Result<AfterUnlock, ArbiterError> {
        let need_before = inner.control.tick_need();
        let logged = inner.flight.is_some().then(|| input.clone());
        let result = inner.control.handle(input, robot, measured_joints, now);
        if let (Some(input), Some(log)) = (logged, inner.flight.as_mut()) {
            log.record(FlightEntry {
                now_s: now,
                input,
                robot: robot.clone(),
                outcome: Outcome::of(result.as_ref().map(|h| &h.effects)),
            });
        }
        let handled = result?;
        if sink.is_some() {
            inner.policy_sink = sink;
        }
        let mut command_time_ns = None;
        // Sent under the lock, so the bridge sees commands in `seq` order.
        for c in handled.commands() {
            command_time_ns = Some(self.send_locked(&mut inner.control, c));
        }
        let effects = handled.effects;
        let turned = effects.turn.as_ref().and_then(|t| {
            inner
                .policy_sink
                .as_ref()
                .filter(|(session, _)| *session == t.session)
                .map(|(_, sink)| Arc::clone(sink))
        });
        let sink = effects.revoked.as_ref().and_then(|r| {
            inner
                .policy_sink
                .take_if(|(session, _)| *session == r.session)
                .map(|(_, sink)| sink)
        });
        if inner.control.tick_need() != need_before {
            self.wake.notify_one();
        }
        Ok(AfterUnlock {
            effects,
            command_time_ns,
            revoked: sink,
            turned,
        })
    }

    /// Hands one command to the bridge, with its joints when this arm has a joint stage. Returns the issue
    /// time.
    fn send_locked(&self, control: &mut ArmControl, command: &Command) -> i64 {
        let issue_time_ns = monotonic_ns();
        match control.issue(command, issue_time_ns as f64 * 1e-9) {
            Issue::Held => {
                tracing::warn!(arm = %self.name, seq = command.seq, "no measured joints to limit from: command held");
            }
            Issue::Send { joint_targets_rad } => self.bridge.send(phone2act_bridges::Command {
                seq: command.seq,
                robot_from_target: command.robot_from_target,
                gripper_target: command.gripper,
                issue_time_ns,
                joint_targets_rad,
            }),
        }
        issue_time_ns
    }

    /// Tells a revoked policy session that it lost the arm (without the lock: the sink must not be called
    /// under it). Returns the effects and the time the last command was handed to the bridge.
    fn finish(&self, handled: AfterUnlock) -> (Effects, Option<i64>) {
        let AfterUnlock {
            effects,
            command_time_ns,
            revoked,
            turned,
        } = handled;
        if let (Some(sink), Some(t)) = (turned, &effects.turn) {
            if t.resumed {
                tracing::info!(arm = %self.name, session = t.session, "arm handed back to the waiting policy");
                sink.resumed(&self.name);
            } else {
                tracing::info!(arm = %self.name, session = t.session, "operator took the arm; the policy waits");
                sink.paused(&self.name, "the operator took the arm; it waits for a hand-back");
            }
        }
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
        self.apply(Input::BindTeleop { session, take_over }, monotonic_s())
            .map(drop)
            .map_err(|e| self.refused(e))
    }

    /// Ends a teleop session; the arm holds if it was driving.
    pub fn unbind_teleop(&self, session: u64) {
        // Unbinding refuses nothing.
        let _ = self.apply(Input::UnbindTeleop { session }, monotonic_s());
    }

    /// The arm's control-path counters (latencies, samples, ticks).
    pub fn stats(&self) -> &ControlStats {
        &self.stats
    }

    /// Processes one round of teleop input for the bound session.
    pub fn teleop_input(&self, session: u64, round: TeleopRound) -> Result<TeleopOutcome, ArmError> {
        let (effects, command_time_ns) = self
            .apply(Input::Teleop { session, round }, monotonic_s())
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
        self.apply_with(claim, monotonic_s(), Some((session, events)))
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
        let _ = self.apply(release, monotonic_s());
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
        // Copied under the lock, converted (inverse kinematics for joint steps) after it.
        let (plan, period_s) = self.inner.lock().control.arbiter().policy_plan_from(from_s);
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
        let now = monotonic_s();
        self.apply(Input::PolicyLoading { session }, now)
            .map_err(|e| self.refused(e))?;
        let deadline_s = self.inner.lock().control.arbiter().policy_loading_until();
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
                monotonic_s(),
            )
            .map_err(|e| self.refused(e))?;
        Ok(effects
            .chunk
            .expect("an accepted chunk reports what it scheduled"))
    }

    /// Plays due chunk steps and applies the silence and staleness rules at `now` (s, [`monotonic_s`]).
    pub fn tick(&self, now: f64) {
        self.stats.note_tick();
        // A tick refuses nothing.
        let _ = self.apply(Input::Tick, now);
    }

    /// Re-draws the arm's scene (see `phone2act.v1.Scene.Reset`). `home_arm` is a teleport, so the arbiter
    /// refuses it while a source drives; afterwards the arm holds the homed pose and both sources re-index
    /// from it, so a phone or policy that takes the arm next starts where the arm now is.
    pub fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<SceneState, ArmError> {
        // Re-drawing the objects leaves the arm where it is, so the arm's lock stays free for its sources while a
        // remote bridge takes its time (up to its answer limit). An arm without a scene says so whoever drives
        // it; its refusal changes nothing.
        if !home_arm || matches!(self.bridge.scene(), Err(BridgeError::Unsupported(_))) {
            return self
                .bridge
                .reset_scene(seed, home_arm)
                .map_err(|e| self.bridge_error(e));
        }
        // A teleport: held across it so that no source can start driving between the check and the teleport.
        let mut inner = self.inner.lock();
        inner.control.arbiter().may_home().map_err(|e| self.refused(e))?;
        let state = self
            .bridge
            .reset_scene(seed, home_arm)
            .map_err(|e| self.bridge_error(e))?;
        if let Some(feedback) = self.bridge.feedback() {
            let robot = robot(self.bridge.health().into(), Some(&feedback.reading()));
            let homed = Input::Homed {
                gripper: feedback.gripper_position,
            };
            let now = monotonic_s();
            inner.control.teleported(&feedback.joint_positions_rad, now);
            // Nobody drives (checked above under this lock): the arbiter accepts, sends nothing, revokes nobody.
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
        self.inner.lock().control.tick_need()
    }

    /// Who drives the arm now (what a full [`Self::snapshot`] would say, without building one).
    pub fn driver(&self) -> Driver {
        self.inner.lock().control.arbiter().driver()
    }

    /// A snapshot for the API.
    pub fn snapshot(&self) -> ArmSnapshot {
        let feedback = self.bridge.feedback();
        let health = self.bridge.health().into();
        let warning = self.bridge.warning();
        let now_ns = monotonic_ns();
        let names = ArmNames {
            arm: &self.name,
            bridge_kind: self.kind,
            joint_names: self.layout.joint_names(),
        };
        let reading = feedback.as_ref().map(Feedback::reading);
        self.inner
            .lock()
            .control
            .snapshot(&names, health, reading.as_ref(), warning, now_ns)
    }

    /// `observation.state` and the executed `action` for the recorder and for policies: the action is the
    /// last gated target, absolute (see `phone2act_core::layout`), so it means the same from any frame; a
    /// joint arm's is the joints that target asks for.
    pub fn state_and_action(&self) -> Option<ArmSample> {
        let feedback = self.bridge.feedback()?;
        let warning = self.bridge.warning().unwrap_or_default();
        // The activity is read with the target, under the same lock: the recorder's events then describe the
        // very command the frame's action records, and a tick locks each arm once.
        let Sample {
            state,
            action,
            activity,
        } = self
            .inner
            .lock()
            .control
            .sample(&self.vectors(), &feedback.reading())?;
        Some(ArmSample {
            state,
            action,
            task_success: feedback.task_success,
            robot_from_ee: feedback.robot_from_ee,
            capture_time_ns: feedback.capture_time_ns,
            activity: ArmActivity {
                arm: self.name.clone(),
                arbiter: activity,
                warning,
            },
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

mod error;
mod setup;
mod ticks;

pub use error::ArmError;
pub use ticks::run_ticks;

#[cfg(test)]
mod tests;
