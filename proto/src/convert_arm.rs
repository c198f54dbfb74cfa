//! Arm types between the core domain and the wire: poses, gate decisions, the arm's state and a phone's
//! button events. The server's services and every client convert here, so a field means one thing
//! everywhere.

use crate::v1;
use nalgebra::Isometry3;
use phone2act_core::{
    ArmSnapshot, BridgeHealth, ClutchKind, Driver, GateDecision, GateVerdict, GripperCommand, PoseError,
    TeleopButton,
};

/// Why a wire pose is not a pose.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseFromWireError {
    #[error("pose has no position_m")]
    NoPosition,
    #[error("pose has no orientation")]
    NoOrientation,
    #[error(transparent)]
    Invalid(#[from] PoseError),
}

/// Wire pose from an isometry.
pub fn pose_to_proto(pose: &Isometry3<f64>) -> v1::Pose {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    v1::Pose::from_parts([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// Validates a wire pose into an isometry (finite, unit quaternion).
pub fn pose_from_proto(pose: &v1::Pose) -> Result<Isometry3<f64>, PoseFromWireError> {
    let p = pose.position_m.as_ref().ok_or(PoseFromWireError::NoPosition)?;
    let q = pose
        .orientation
        .as_ref()
        .ok_or(PoseFromWireError::NoOrientation)?;
    Ok(phone2act_core::validate_pose(
        [p.x, p.y, p.z],
        [q.x, q.y, q.z, q.w],
    )?)
}

/// Checks wire pose values as [`pose_from_proto`] will on the server (finite, a quaternion within
/// `phone2act_core::pose::QUATERNION_NORM_TOLERANCE` of unit norm): a client-facing edge that folds samples
/// latest-wins, such as the gateway, refuses a bad one at once, so its error cannot be lost to a newer pose.
pub fn check_wire_pose(position_m: [f64; 3], quat_xyzw: [f64; 4]) -> Result<(), PoseError> {
    phone2act_core::validate_pose(position_m, quat_xyzw).map(|_| ())
}

impl From<GateVerdict> for v1::GateVerdict {
    fn from(verdict: GateVerdict) -> Self {
        match verdict {
            GateVerdict::Accepted => Self::Accepted,
            GateVerdict::Clamped => Self::Clamped,
            GateVerdict::RejectedJump => Self::RejectedJump,
            GateVerdict::RejectedInvalid => Self::RejectedInvalid,
            GateVerdict::HeldStale => Self::HeldStale,
        }
    }
}

/// Wire gate decision from the core's.
pub fn decision_to_proto(d: &GateDecision) -> v1::GateDecision {
    v1::GateDecision {
        verdict: v1::GateVerdict::from(d.verdict) as i32,
        reason: d.reason.clone(),
        workspace_clamped: d.workspace_clamped,
        velocity_limited: d.velocity_limited,
        position_step_m: d.position_step_m,
        rotation_step_rad: d.rotation_step_rad,
    }
}

impl From<Driver> for v1::ControlSource {
    fn from(driver: Driver) -> Self {
        match driver {
            Driver::None => Self::None,
            Driver::Teleop => Self::Teleop,
            Driver::Policy => Self::Policy,
        }
    }
}

impl From<&BridgeHealth> for v1::BridgeHealth {
    fn from(health: &BridgeHealth) -> Self {
        match health {
            BridgeHealth::Ready => Self::Ready,
            BridgeHealth::Connecting => Self::Connecting,
            BridgeHealth::Error(_) => Self::Error,
            BridgeHealth::Disconnected(_) => Self::Disconnected,
        }
    }
}

/// Wire arm state from a snapshot.
pub fn arm_state_to_proto(s: &ArmSnapshot) -> v1::ArmState {
    v1::ArmState {
        arm: s.arm.clone(),
        bridge_kind: s.bridge_kind.clone(),
        health: v1::BridgeHealth::from(&s.health) as i32,
        health_message: s.health_message.clone(),
        owner: v1::ControlSource::from(s.driver) as i32,
        owner_id: s.owner_id.clone(),
        engaged: s.engaged,
        robot_from_target: Some(pose_to_proto(&s.robot_from_target)),
        robot_from_ee: s.robot_from_ee.as_ref().map(pose_to_proto),
        joint_positions_rad: s.joint_positions_rad.clone(),
        joint_names: s.joint_names.clone(),
        gripper_position: s.gripper_position,
        gripper_target: s.gripper_target,
        last_decision: Some(decision_to_proto(&s.last_decision)),
        feedback_time_ns: s.feedback_time_ns,
        feedback_age_s: s.feedback_age_s,
        commands_sent: s.counters.sent,
        commands_rejected: s.counters.rejected,
        commands_clamped: s.counters.clamped,
        commands_joint_limited: s.joint_counters.limited,
        commands_orientation_unreachable: s.joint_counters.orientation_unreachable,
        joint_targets_rad: s.joint_targets_rad.clone(),
        joint_targets_time_ns: s.joint_targets_time_ns,
        task_success: s.task_success,
        policy_loading: s.policy_loading,
        waiting_policy_id: s.waiting_policy_id.clone(),
        plan_preview: (!s.plan_preview.positions_m.is_empty()).then(|| v1::PlanPreview {
            positions_m: s
                .plan_preview
                .positions_m
                .iter()
                .map(|&[x, y, z]| v1::Vec3 { x, y, z })
                .collect(),
            grippers: s.plan_preview.grippers.clone(),
            point_period_s: s.plan_preview.point_period_s,
        }),
    }
}

/// A phone's button event, split by who handles it: the arm, or the recorder.
#[derive(Debug, Clone, PartialEq)]
pub enum ButtonInput {
    Arm(TeleopButton),
    Record(v1::RecordCommand),
}

/// Decodes one button event; an undecodable one becomes [`TeleopButton::Invalid`] with its reason, so it is
/// reported in order with the others.
pub fn button_from_proto(event: v1::ButtonEvent) -> ButtonInput {
    let arm = match event.event {
        Some(v1::button_event::Event::Clutch(c)) => match v1::clutch_command::Kind::try_from(c.kind) {
            Ok(v1::clutch_command::Kind::Toggle) => TeleopButton::Clutch(ClutchKind::Toggle),
            Ok(v1::clutch_command::Kind::Engage) => TeleopButton::Clutch(ClutchKind::Engage),
            Ok(v1::clutch_command::Kind::Disengage) => TeleopButton::Clutch(ClutchKind::Disengage),
            _ => TeleopButton::Invalid(format!("unknown clutch kind {}", c.kind)),
        },
        Some(v1::button_event::Event::Gripper(g)) => match v1::gripper_command::Kind::try_from(g.kind) {
            Ok(v1::gripper_command::Kind::Toggle) => TeleopButton::Gripper(GripperCommand::Toggle),
            Ok(v1::gripper_command::Kind::Set) => TeleopButton::Gripper(GripperCommand::Set(g.position)),
            _ => TeleopButton::Invalid(format!("unknown gripper kind {}", g.kind)),
        },
        Some(v1::button_event::Event::Record(r)) => return ButtonInput::Record(r),
        Some(v1::button_event::Event::HandBack(v1::HandBackCommand {})) => TeleopButton::HandBack,
        None => TeleopButton::Invalid("empty button event".to_owned()),
    };
    ButtonInput::Arm(arm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn a_pose_survives_the_wire_and_a_broken_one_is_named() {
        let pose = Isometry3::from_parts(
            Translation3::new(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
        );
        let back = pose_from_proto(&pose_to_proto(&pose)).unwrap();
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-9);
        let mut wire = pose_to_proto(&pose);
        wire.orientation = None;
        assert_eq!(pose_from_proto(&wire), Err(PoseFromWireError::NoOrientation));
        let half = v1::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 0.5]);
        assert!(matches!(
            pose_from_proto(&half),
            Err(PoseFromWireError::Invalid(_))
        ));
    }

    #[test]
    fn buttons_split_between_arm_and_recorder() {
        let clutch = |kind: i32| v1::ButtonEvent {
            event: Some(v1::button_event::Event::Clutch(v1::ClutchCommand { kind })),
        };
        assert_eq!(
            button_from_proto(clutch(v1::clutch_command::Kind::Engage as i32)),
            ButtonInput::Arm(TeleopButton::Clutch(ClutchKind::Engage))
        );
        assert_eq!(
            button_from_proto(clutch(99)),
            ButtonInput::Arm(TeleopButton::Invalid("unknown clutch kind 99".into()))
        );
        let record = v1::RecordCommand::default();
        assert_eq!(
            button_from_proto(v1::ButtonEvent {
                event: Some(v1::button_event::Event::Record(record.clone()))
            }),
            ButtonInput::Record(record)
        );
    }
}
