//! The per-arm teleop state machine: clutch, planner, safety gate and gripper, driven by the server.
//!
//! Engaged means the phone drives the robot; disengaged means clutched (floating zero: the phone moves
//! freely and the arm holds its last target). Every transition into driving re-indexes from the phone's
//! current pose and the robot's *measured* end-effector pose, and resets the gate's jump reference there,
//! so engaging never moves the robot. The same re-index happens automatically on the first good sample
//! after lost tracking, after a stale stream and after a rejected jump, which is how the arm recovers
//! without the operator touching the clutch. After a rejected jump with the clutch still held it anchors at
//! the last commanded target instead of the measured pose, which lags it: re-indexing at the lagging pose
//! would shift the phone-to-robot mapping for good.

use crate::config::{ConfigError, TeleopConfig};
use crate::gate::{GateDecision, GateVerdict, SafetyGate};
use crate::gripper::{Gripper, GripperCommand, GripperError};
use crate::planner::{Mapping, Planner};
use crate::pose::check_pose;
use nalgebra::Isometry3;

/// A clutch input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ClutchKind {
    /// Flip between engaged and disengaged (the Android app's volume key).
    Toggle,
    /// Start driving (hold-to-move button pressed).
    Engage,
    /// Stop driving (hold-to-move button released).
    Disengage,
}

/// What the server should do after one input.
#[derive(Debug, Clone, PartialEq)]
pub struct TeleopStep {
    /// Target pose (robot base frame) and gripper target to hand to the bridge; `None` = keep holding.
    pub command: Option<(Isometry3<f64>, f64)>,
    /// The gate's decision when a target was proposed. Inputs that propose nothing (a clutch release into
    /// floating, samples while clutched) carry a note with verdict `Accepted`, zero steps and a reason saying
    /// what happened; count sent commands from `command`, not from the verdict.
    pub decision: GateDecision,
    pub engaged: bool,
    /// True if this input re-indexed the floating zero.
    pub reindexed: bool,
}

/// Teleop state of one arm.
#[derive(Debug, Clone)]
pub struct TeleopArm {
    planner: Planner,
    gate: SafetyGate,
    gripper: Gripper,
    engaged: bool,
    needs_reindex: bool,
    /// Set by a refused jump while engaged: the pending re-index anchors at the last commanded target, not
    /// at the measured pose, which lags it by the bridge's tracking error and would shift the mapping for
    /// good. Cleared when the clutch is released (a fresh engage always starts from the measured pose).
    reindex_at_target: bool,
    target: Isometry3<f64>,
}

impl TeleopArm {
    /// Starts disengaged, holding `initial_target` (normally the measured end-effector pose).
    pub fn new(config: &TeleopConfig, initial_target: Isometry3<f64>) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Self {
            planner: Planner::new(Mapping::from_config(&config.mapping)?),
            gate: SafetyGate::new(&config.gate, initial_target)?,
            gripper: Gripper::new(&config.gripper, 0.0),
            engaged: false,
            needs_reindex: true,
            reindex_at_target: false,
            target: initial_target,
        })
    }

    pub fn engaged(&self) -> bool {
        self.engaged
    }

    /// The last target that passed the gate (or the initial one).
    pub fn target(&self) -> Isometry3<f64> {
        self.target
    }

    pub fn gripper_target(&self) -> f64 {
        self.gripper.target()
    }

    /// Makes the next tracked pose re-index, e.g. after another source (a policy) moved the arm.
    pub fn request_reindex(&mut self) {
        self.needs_reindex = true;
        self.reindex_at_target = false;
    }

    /// A clutch input. `phone` is the phone's pose at the press if the message carried one; without it the
    /// re-index waits for the next tracked pose.
    pub fn clutch(
        &mut self,
        kind: ClutchKind,
        phone: Option<Isometry3<f64>>,
        measured_ee: Isometry3<f64>,
        now_s: f64,
    ) -> TeleopStep {
        let engage = match kind {
            ClutchKind::Toggle => !self.engaged,
            ClutchKind::Engage => true,
            ClutchKind::Disengage => false,
        };
        if !engage {
            self.engaged = false;
            self.needs_reindex = true;
            self.reindex_at_target = false;
            self.planner.clear();
            return self.hold(GateDecision::note(
                GateVerdict::Accepted,
                "clutch disengaged: the phone floats, the arm holds",
            ));
        }
        if self.engaged && !self.needs_reindex {
            return self.hold(GateDecision::note(GateVerdict::Accepted, "already engaged"));
        }
        self.engaged = true;
        self.needs_reindex = true;
        // Without a pose from this very press, wait for the next tracked sample rather than re-index from
        // an older one: the phone may have moved since, and that motion would be replayed on the robot.
        if let Some(p) = phone.filter(|p| check_pose(p).is_ok()) {
            return self.reindex(p, measured_ee, now_s, "clutch engaged");
        }
        // The staleness clock starts at the press, not at the last sample before the clutch.
        self.gate.reset_reference_at(self.target, now_s);
        self.hold(GateDecision::note(
            GateVerdict::Accepted,
            "clutch engaged: re-indexing on the next tracked phone pose",
        ))
    }

    /// One phone sample.
    pub fn on_pose(
        &mut self,
        phone: Isometry3<f64>,
        tracking_ok: bool,
        measured_ee: Isometry3<f64>,
        now_s: f64,
    ) -> TeleopStep {
        if let Err(e) = check_pose(&phone) {
            return self.hold(GateDecision::note(
                GateVerdict::RejectedInvalid,
                format!("invalid phone pose: {e}"),
            ));
        }
        if !tracking_ok {
            // The tracking frame may jump when tracking returns (relocalisation): start afresh from there.
            self.needs_reindex = true;
            return self.hold(GateDecision::note(
                GateVerdict::RejectedInvalid,
                "phone tracking lost: holding until it returns",
            ));
        }
        if !self.engaged {
            return self.hold(GateDecision::note(
                GateVerdict::Accepted,
                "disengaged: the arm holds",
            ));
        }
        if self.needs_reindex {
            return self.reindex(phone, measured_ee, now_s, "re-indexed");
        }
        let Some(proposed) = self.planner.target(&phone) else {
            return self.reindex(phone, measured_ee, now_s, "re-indexed");
        };
        let (out, mut decision) = self.gate.check(proposed, now_s);
        if let Some(target) = out {
            self.target = target;
            return TeleopStep {
                command: Some((target, self.gripper.target())),
                decision,
                engaged: true,
                reindexed: false,
            };
        }
        if decision.verdict == GateVerdict::RejectedJump {
            // Recover without the operator: the next sample becomes the new floating zero, anchored where
            // the arm was last commanded to be.
            self.needs_reindex = true;
            self.reindex_at_target = true;
            decision.reason.push_str("; re-indexing on the next sample");
        }
        self.hold(decision)
    }

    /// Continues from the gripper target the arm holds, which a policy or a scene reset may have set since
    /// the phone last asked: the phone's next command must not re-send its own old setting.
    pub fn adopt_gripper(&mut self, target: f64) {
        self.gripper.adopt(target);
    }

    /// A gripper command; the server sends `(target(), returned value)`.
    pub fn gripper(&mut self, command: GripperCommand) -> Result<f64, GripperError> {
        self.gripper.apply(command)
    }

    /// Reports once when an engaged stream goes silent past the timeout. The arm holds its last target and
    /// the next sample re-indexes, so motion made during the silence is not replayed as one lurch.
    pub fn check_stale(&mut self, now_s: f64) -> Option<GateDecision> {
        if !self.engaged {
            return None;
        }
        let decision = self.gate.check_stale(now_s)?;
        self.needs_reindex = true;
        self.reindex_at_target = false;
        Some(decision)
    }

    fn reindex(
        &mut self,
        phone: Isometry3<f64>,
        measured_ee: Isometry3<f64>,
        now_s: f64,
        what: &str,
    ) -> TeleopStep {
        let (anchor, at) = if self.reindex_at_target {
            (self.target, "the last commanded target")
        } else {
            (measured_ee, "the measured pose")
        };
        if let Err(e) = check_pose(&anchor) {
            return self.hold(GateDecision::note(
                GateVerdict::RejectedInvalid,
                format!("{what}: {at} is invalid ({e}), holding"),
            ));
        }
        self.planner.reindex(phone, anchor);
        self.gate.reset_reference_at(anchor, now_s);
        // The anchor normally passes unchanged; outside the workspace it is clamped back in, and the jump
        // filter refuses that if it is far.
        let (out, mut decision) = self.gate.check(anchor, now_s);
        let Some(target) = out else {
            return self.hold(decision);
        };
        self.needs_reindex = false;
        self.reindex_at_target = false;
        self.target = target;
        if decision.reason.is_empty() {
            decision.reason = format!("{what} at {at}");
        } else {
            decision.reason = format!("{what} at {at}; {}", decision.reason);
        }
        TeleopStep {
            command: Some((target, self.gripper.target())),
            decision,
            engaged: true,
            reindexed: true,
        }
    }

    fn hold(&self, decision: GateDecision) -> TeleopStep {
        TeleopStep {
            command: None,
            decision,
            engaged: self.engaged,
            reindexed: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{AxisPreset, GateConfig, MappingConfig};
    use crate::pose::pose_distance;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use proptest::prelude::*;

    fn config() -> TeleopConfig {
        TeleopConfig {
            mapping: MappingConfig {
                preset: AxisPreset::Identity,
                ..MappingConfig::default()
            },
            ..TeleopConfig::default()
        }
    }

    fn at(x: f64, y: f64, z: f64) -> Isometry3<f64> {
        Isometry3::translation(x, y, z)
    }

    #[test]
    fn after_a_refused_jump_the_mapping_continues_from_the_commanded_target_not_the_lagging_measurement() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        let step = arm.on_pose(at(0.02, 0.0, 0.0), true, ee, 0.02);
        let commanded = step.command.unwrap().0;
        // The robot lags its target by 2 mm when the tracking frame jumps 30 cm.
        let lagging = at(0.268, 0.0, 0.2);
        let step = arm.on_pose(at(0.32, 0.0, 0.0), true, lagging, 0.04);
        assert_eq!(step.decision.verdict, GateVerdict::RejectedJump);
        let step = arm.on_pose(at(0.33, 0.0, 0.0), true, lagging, 0.06);
        assert!(step.reindexed, "{:?}", step.decision);
        assert_eq!(step.command.unwrap().0, commanded, "{}", step.decision.reason);
        assert!(step.decision.reason.contains("last commanded target"));
        // A further 1 cm of phone motion is 1 cm from the commanded target: no 2 mm shift for good.
        let step = arm.on_pose(at(0.34, 0.0, 0.0), true, lagging, 0.08);
        assert!((step.command.unwrap().0.translation.x - 0.28).abs() < 1e-12);

        // Once the clutch is released, engaging again starts from the measured pose.
        arm.on_pose(at(0.9, 0.0, 0.0), true, lagging, 0.10);
        arm.clutch(ClutchKind::Disengage, None, lagging, 0.12);
        let step = arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), lagging, 0.14);
        assert_eq!(step.command.unwrap().0, lagging);
    }

    #[test]
    fn toggle_clutch_drives_and_holds() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        assert!(!arm.engaged());
        assert!(arm.on_pose(at(1.0, 1.0, 1.0), true, ee, 0.0).command.is_none());
        // The volume key carries no pose: engage now, re-index on the next sample, never from an old one.
        let step = arm.clutch(ClutchKind::Toggle, None, ee, 0.01);
        assert!(step.engaged && !step.reindexed && step.command.is_none());
        assert!(
            arm.check_stale(0.2).is_none(),
            "the staleness clock starts at the press"
        );
        let step = arm.on_pose(at(1.4, 1.0, 1.0), true, ee, 0.015);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, ee);
        let step = arm.on_pose(at(1.42, 1.0, 1.0), true, ee, 0.02);
        assert_eq!(step.decision.verdict, GateVerdict::Accepted);
        assert!((step.command.unwrap().0.translation.vector - Vector3::new(0.27, 0.0, 0.2)).norm() < 1e-12);
        let step = arm.clutch(ClutchKind::Toggle, None, ee, 0.03);
        assert!(!step.engaged && step.command.is_none());
        assert!(arm.on_pose(at(1.5, 1.0, 1.0), true, ee, 0.04).command.is_none());
        assert!(arm.check_stale(5.0).is_none(), "a clutched arm is not stale");
        assert!(arm.clutch(ClutchKind::Toggle, None, ee, 6.0).engaged);
        assert!(
            arm.check_stale(6.1).is_none(),
            "the staleness clock starts at the press"
        );
        assert!(arm.check_stale(6.4).is_some(), "no pose since the press");
    }

    #[test]
    fn release_reindexes_from_the_measured_pose_even_after_the_robot_moved() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        arm.on_pose(at(0.03, 0.0, 0.0), true, ee, 0.02);
        arm.clutch(ClutchKind::Disengage, None, ee, 0.04);
        // While clutched the robot is moved 10 cm away (homed, pushed, or driven by a policy).
        let moved = at(0.25, 0.1, 0.2);
        let step = arm.clutch(ClutchKind::Engage, Some(at(0.5, 0.5, 0.5)), moved, 1.0);
        assert_eq!(step.command.unwrap().0, moved);
        // The paper's filter would still measure from the old target and reject this; ours does not.
        let step = arm.on_pose(at(0.51, 0.5, 0.5), true, moved, 1.02);
        assert_eq!(
            step.decision.verdict,
            GateVerdict::Accepted,
            "{:?}",
            step.decision
        );
        assert!((step.command.unwrap().0.translation.vector - Vector3::new(0.26, 0.1, 0.2)).norm() < 1e-12);
    }

    #[test]
    fn recovers_from_a_jump_lost_tracking_and_a_stale_stream() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        // Relocalisation: the tracking frame jumps 30 cm.
        let step = arm.on_pose(at(0.3, 0.0, 0.0), true, ee, 0.02);
        assert_eq!(step.decision.verdict, GateVerdict::RejectedJump);
        assert!(step.decision.reason.ends_with("re-indexing on the next sample"));
        let step = arm.on_pose(at(0.31, 0.0, 0.0), true, ee, 0.04);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, ee);
        let step = arm.on_pose(at(0.32, 0.0, 0.0), true, ee, 0.06);
        assert!((step.command.unwrap().0.translation.x - 0.26).abs() < 1e-12);

        let step = arm.on_pose(at(0.9, 0.0, 0.0), false, ee, 0.08);
        assert_eq!(step.decision.verdict, GateVerdict::RejectedInvalid);
        let measured = at(0.26, 0.0, 0.2);
        let step = arm.on_pose(at(0.9, 0.0, 0.0), true, measured, 0.10);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, measured);

        assert!(arm.check_stale(0.35).is_none());
        let stale = arm.check_stale(0.5).unwrap();
        assert_eq!(stale.verdict, GateVerdict::HeldStale);
        assert!(arm.check_stale(0.6).is_none());
        let step = arm.on_pose(at(0.95, 0.0, 0.0), true, measured, 0.7);
        assert!(
            step.reindexed,
            "the motion made during the silence is not replayed"
        );
        assert_eq!(step.command.unwrap().0, measured);
    }

    #[test]
    fn invalid_inputs_change_nothing() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        let step = arm.on_pose(at(f64::NAN, 0.0, 0.0), true, ee, 0.02);
        assert_eq!(step.decision.verdict, GateVerdict::RejectedInvalid);
        assert!(step.command.is_none());
        let step = arm.on_pose(at(0.01, 0.0, 0.0), true, ee, 0.04);
        assert!(!step.reindexed && step.command.is_some());
        assert!(
            TeleopArm::new(
                &TeleopConfig {
                    gate: GateConfig {
                        jump_position_m: -1.0,
                        ..GateConfig::default()
                    },
                    ..config()
                },
                ee
            )
            .is_err()
        );
    }

    #[test]
    fn engage_while_driving_keeps_the_mapping() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        arm.on_pose(at(0.02, 0.0, 0.0), true, ee, 0.02);
        // A repeated Engage (a second press, a retransmission) while the robot lags 2 mm behind its target:
        // re-indexing would snap the target back to the lagging measurement.
        let lagging = at(0.268, 0.0, 0.2);
        let step = arm.clutch(ClutchKind::Engage, Some(at(0.5, 0.5, 0.5)), lagging, 0.03);
        assert!(
            step.engaged && !step.reindexed && step.command.is_none(),
            "{step:?}"
        );
        let step = arm.on_pose(at(0.03, 0.0, 0.0), true, lagging, 0.04);
        assert!(!step.reindexed);
        assert!((step.command.unwrap().0.translation.x - 0.28).abs() < 1e-12);
    }

    #[test]
    fn after_another_source_moved_the_arm_teleop_starts_from_the_measured_pose() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        arm.on_pose(at(0.02, 0.0, 0.0), true, ee, 0.02);
        // A refused jump leaves a pending re-index anchored at the last target...
        let step = arm.on_pose(at(0.5, 0.0, 0.0), true, ee, 0.04);
        assert_eq!(step.decision.verdict, GateVerdict::RejectedJump);
        // ...then a policy drives the arm 10 cm away and hands control back.
        arm.request_reindex();
        let moved = at(0.27, 0.1, 0.2);
        let step = arm.on_pose(at(0.51, 0.0, 0.0), true, moved, 1.0);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, moved, "{}", step.decision.reason);
        // Without a pending jump: the old offset would replay the phone's motion from the old target.
        let step = arm.on_pose(at(0.52, 0.0, 0.0), true, moved, 1.02);
        assert!((step.command.unwrap().0.translation.vector - Vector3::new(0.28, 0.1, 0.2)).norm() < 1e-12);
        arm.request_reindex();
        let elsewhere = at(0.2, -0.1, 0.25);
        let step = arm.on_pose(at(0.53, 0.0, 0.0), true, elsewhere, 2.0);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, elsewhere);
    }

    #[test]
    fn an_engage_carrying_an_invalid_pose_waits_for_a_tracked_one() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        let step = arm.clutch(ClutchKind::Engage, Some(at(f64::NAN, 0.0, 0.0)), ee, 0.0);
        assert!(
            step.engaged && !step.reindexed && step.command.is_none(),
            "{step:?}"
        );
        let step = arm.on_pose(at(0.1, 0.0, 0.0), true, ee, 0.02);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, ee);
        let step = arm.on_pose(at(0.11, 0.0, 0.0), true, ee, 0.04);
        assert!((step.command.unwrap().0.translation.x - 0.26).abs() < 1e-12);
    }

    #[test]
    fn only_the_reindex_right_after_a_refused_jump_anchors_at_the_target() {
        let ee = at(0.25, 0.0, 0.2);
        let lagging = at(0.268, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        arm.on_pose(at(0.02, 0.0, 0.0), true, ee, 0.02);
        arm.on_pose(at(0.5, 0.0, 0.0), true, lagging, 0.04);
        let step = arm.on_pose(at(0.51, 0.0, 0.0), true, lagging, 0.06);
        assert_eq!(step.command.unwrap().0, at(0.27, 0.0, 0.2));
        // A later re-index (tracking lost and back) starts from the measured pose again.
        arm.on_pose(at(0.52, 0.0, 0.0), false, lagging, 0.08);
        let step = arm.on_pose(at(0.52, 0.0, 0.0), true, lagging, 0.10);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, lagging);

        // A refused jump followed by a stale stream: after the silence the robot has settled, so the
        // re-index anchors at the measured pose.
        arm.on_pose(at(0.9, 0.0, 0.0), true, lagging, 0.12);
        assert!(arm.check_stale(0.5).is_some());
        let settled = at(0.265, 0.0, 0.2);
        let step = arm.on_pose(at(0.91, 0.0, 0.0), true, settled, 0.6);
        assert!(step.reindexed);
        assert_eq!(step.command.unwrap().0, settled);
    }

    #[test]
    fn gripper_commands_reach_the_command_tuple() {
        let ee = at(0.25, 0.0, 0.2);
        let mut arm = TeleopArm::new(&config(), ee).unwrap();
        assert_eq!(arm.gripper(GripperCommand::Toggle), Ok(1.0));
        let step = arm.clutch(ClutchKind::Engage, Some(at(0.0, 0.0, 0.0)), ee, 0.0);
        assert!((step.command.unwrap().1 - 1.0).abs() < 1e-15);
        assert_eq!(arm.gripper(GripperCommand::Set(0.25)), Ok(0.25));
        assert!((arm.gripper_target() - 0.25).abs() < 1e-15);
        let step = arm.on_pose(at(0.0, 0.0, 0.01), true, ee, 0.02);
        let (target, gripper) = step.command.unwrap();
        assert!((gripper - 0.25).abs() < 1e-15);
        assert_eq!(arm.target(), target);
    }

    /// One scripted input: a phone move, a clutch press, a tracking drop, or a measured-pose drift.
    #[derive(Debug, Clone)]
    enum Input {
        Move { dp: [f64; 3], dr: [f64; 3], big: bool },
        Clutch(u8),
        Untracked,
        Drift([f64; 3]),
        Garbage,
    }

    fn any_input() -> impl Strategy<Value = Input> {
        prop_oneof![
            10 => (prop::array::uniform3(-0.04..0.04f64), prop::array::uniform3(-0.25..0.25f64), prop::bool::weighted(0.05))
                .prop_map(|(dp, dr, big)| Input::Move { dp, dr, big }),
            2 => (0..3u8).prop_map(Input::Clutch),
            1 => Just(Input::Untracked),
            1 => prop::array::uniform3(-0.03..0.03f64).prop_map(Input::Drift),
            1 => Just(Input::Garbage),
        ]
    }

    proptest! {
        /// Random sessions: targets stay inside the workspace and finite, every step that passes is within
        /// the jump thresholds of the previous target, and every re-index commands exactly the measured pose,
        /// except the one after a refused jump with the clutch held, which commands the last target exactly.
        #[test]
        fn sessions_are_safe(inputs in prop::collection::vec(any_input(), 1..120), preset in 0..3u8, scale in 0.5..2.0f64) {
            let preset = [AxisPreset::Landscape, AxisPreset::Portrait, AxisPreset::Identity][preset as usize];
            let cfg = TeleopConfig {
                mapping: MappingConfig { preset, position_scale: scale, rotation_scale: 1.0 / scale, ..MappingConfig::default() },
                ..TeleopConfig::default()
            };
            let gate_cfg = cfg.gate.clone();
            let start = Isometry3::from_parts(Translation3::new(0.25, 0.0, 0.2), UnitQuaternion::from_euler_angles(0.0, 1.2, 0.3));
            let mut arm = TeleopArm::new(&cfg, start).unwrap();
            let mut phone = Isometry3::from_parts(Translation3::new(0.0, 1.3, 0.0), UnitQuaternion::identity());
            let mut measured = start;
            let mut previous_target = start;
            let mut after_jump = false;
            for (i, input) in inputs.into_iter().enumerate() {
                let now_s = i as f64 * 0.02;
                let step = match input {
                    Input::Move { dp, dr, big } => {
                        let k = if big { 8.0 } else { 1.0 };
                        phone = Isometry3::from_parts(
                            Translation3::from(phone.translation.vector + Vector3::from(dp) * k),
                            UnitQuaternion::from_scaled_axis(Vector3::from(dr) * k) * phone.rotation,
                        );
                        arm.on_pose(phone, true, measured, now_s)
                    }
                    Input::Clutch(kind) => {
                        let kind = [ClutchKind::Toggle, ClutchKind::Engage, ClutchKind::Disengage][kind as usize];
                        arm.clutch(kind, Some(phone), measured, now_s)
                    }
                    Input::Untracked => arm.on_pose(phone, false, measured, now_s),
                    Input::Drift(d) => {
                        // The robot lags or is nudged: the measured pose is near, not at, the target.
                        let mut p = previous_target.translation.vector + Vector3::from(d);
                        for axis in 0..3 {
                            p[axis] = p[axis].clamp(gate_cfg.workspace_min_m[axis], gate_cfg.workspace_max_m[axis]);
                        }
                        measured = Isometry3::from_parts(Translation3::from(p), previous_target.rotation);
                        continue;
                    }
                    Input::Garbage => arm.on_pose(at(f64::NAN, 0.0, f64::INFINITY), true, measured, now_s),
                };
                prop_assert_eq!(step.engaged, arm.engaged());
                if let Some((target, gripper)) = step.command {
                    prop_assert!(gripper.is_finite());
                    let p = target.translation.vector;
                    prop_assert!(p.iter().chain(target.rotation.coords.iter()).all(|v| v.is_finite()));
                    for axis in 0..3 {
                        prop_assert!(p[axis] >= gate_cfg.workspace_min_m[axis] && p[axis] <= gate_cfg.workspace_max_m[axis]);
                    }
                    if step.reindexed {
                        // Engaging never moves the robot: the command is the measured pose, bit for bit; after
                        // a refused jump it is the pose the robot was already commanded to.
                        prop_assert_eq!(target, if after_jump { previous_target } else { measured });
                    } else {
                        let (dp, da) = pose_distance(&target, &previous_target);
                        prop_assert!(dp <= gate_cfg.jump_position_m + 1e-12, "step {} m", dp);
                        prop_assert!(da <= gate_cfg.jump_rotation_rad + 1e-12, "step {} rad", da);
                    }
                    previous_target = target;
                    measured = target;
                } else {
                    prop_assert!(!step.reindexed);
                }
                if step.decision.verdict == GateVerdict::RejectedJump {
                    after_jump = true;
                }
                if step.reindexed || !arm.engaged() {
                    after_jump = false;
                }
            }
        }
    }
}
