//! Layout of the `observation.state` and `action` vectors, and conversions between a target pose and an
//! action.
//!
//! - `observation.state`: joint positions (rad) in bridge order, then `ee_x ee_y ee_z` (m), `ee_roll
//!   ee_pitch ee_yaw` (rad, `R = Rz(yaw)·Ry(pitch)·Rx(roll)`, robot base frame), then `gripper` (0 open, 1
//!   closed).
//! - `action`, delta mode (the paper's action space): `delta_x delta_y delta_z` = target − measured position
//!   (m, base frame); `delta_roll delta_pitch delta_yaw` = target − measured roll/pitch/yaw, each wrapped to
//!   (−π, π]; then the gripper target. Absolute mode: the target's `x y z roll pitch yaw` and the gripper.
//!
//! The delta is taken against the measured end-effector pose of the same frame, so a policy that outputs
//! the recorded action from the recorded observation reproduces the recorded target exactly (to rounding),
//! including at ±90° pitch where roll and yaw are not unique individually.

use crate::pose::{rotation_from_rpy, rpy_from_rotation, wrap_angle_rad};
use nalgebra::{Isometry3, Translation3};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Width of one arm's action vector.
pub const ACTION_WIDTH: usize = 7;

const EE_STATE_NAMES: [&str; 7] = ["ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw", "gripper"];
const DELTA_ACTION_NAMES: [&str; 7] = [
    "delta_x",
    "delta_y",
    "delta_z",
    "delta_roll",
    "delta_pitch",
    "delta_yaw",
    "gripper",
];
const ABSOLUTE_ACTION_NAMES: [&str; 7] = ["x", "y", "z", "roll", "pitch", "yaw", "gripper"];

/// How an action vector encodes the end-effector target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ActionMode {
    /// 6-DoF delta from the measured pose, plus gripper.
    #[default]
    Delta,
    /// Absolute target pose in the base frame, plus gripper.
    Absolute,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LayoutError {
    #[error("{what} has {got} values, expected {expected}")]
    WrongWidth {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("{what}[{index}] is not finite: {value}")]
    NonFinite {
        what: &'static str,
        index: usize,
        value: f64,
    },
    #[error("unknown arm {0:?}")]
    UnknownArm(String),
}

/// Vector layout of one arm.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArmLayout {
    joint_names: Vec<String>,
}

impl ArmLayout {
    pub fn new(joint_names: Vec<String>) -> Self {
        Self { joint_names }
    }

    pub fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    pub fn state_width(&self) -> usize {
        self.joint_names.len() + EE_STATE_NAMES.len()
    }

    pub fn state_names(&self) -> Vec<String> {
        self.joint_names
            .iter()
            .cloned()
            .chain(EE_STATE_NAMES.iter().map(|s| (*s).to_owned()))
            .collect()
    }

    pub fn action_names(&self, mode: ActionMode) -> Vec<String> {
        let names = match mode {
            ActionMode::Delta => DELTA_ACTION_NAMES,
            ActionMode::Absolute => ABSOLUTE_ACTION_NAMES,
        };
        names.iter().map(|s| (*s).to_owned()).collect()
    }

    /// The `observation.state` row for one frame.
    pub fn state_vector(
        &self,
        joints_rad: &[f64],
        robot_from_ee: &Isometry3<f64>,
        gripper: f64,
    ) -> Result<Vec<f64>, LayoutError> {
        if joints_rad.len() != self.joint_names.len() {
            return Err(LayoutError::WrongWidth {
                what: "joint positions",
                expected: self.joint_names.len(),
                got: joints_rad.len(),
            });
        }
        let p = robot_from_ee.translation.vector;
        let [roll, pitch, yaw] = rpy_from_rotation(&robot_from_ee.rotation);
        let mut v = Vec::with_capacity(self.state_width());
        v.extend_from_slice(joints_rad);
        v.extend_from_slice(&[p.x, p.y, p.z, roll, pitch, yaw, gripper]);
        Ok(v)
    }

    /// The action that, applied to `robot_from_ee_measured`, gives `robot_from_target` and `gripper_target`.
    pub fn action_from_target(
        &self,
        robot_from_ee_measured: &Isometry3<f64>,
        robot_from_target: &Isometry3<f64>,
        gripper_target: f64,
        mode: ActionMode,
    ) -> Vec<f64> {
        let t = robot_from_target.translation.vector;
        let rpy_t = rpy_from_rotation(&robot_from_target.rotation);
        match mode {
            ActionMode::Absolute => vec![t.x, t.y, t.z, rpy_t[0], rpy_t[1], rpy_t[2], gripper_target],
            ActionMode::Delta => {
                let m = robot_from_ee_measured.translation.vector;
                let rpy_m = rpy_from_rotation(&robot_from_ee_measured.rotation);
                vec![
                    t.x - m.x,
                    t.y - m.y,
                    t.z - m.z,
                    wrap_angle_rad(rpy_t[0] - rpy_m[0]),
                    wrap_angle_rad(rpy_t[1] - rpy_m[1]),
                    wrap_angle_rad(rpy_t[2] - rpy_m[2]),
                    gripper_target,
                ]
            }
        }
    }

    /// The target pose and gripper target an action asks for. The gripper is clamped to [0, 1].
    pub fn target_from_action(
        &self,
        robot_from_ee_measured: &Isometry3<f64>,
        action: &[f64],
        mode: ActionMode,
    ) -> Result<(Isometry3<f64>, f64), LayoutError> {
        check_action(action)?;
        let a = action;
        let (position, rpy) = match mode {
            ActionMode::Absolute => ([a[0], a[1], a[2]], [a[3], a[4], a[5]]),
            ActionMode::Delta => {
                let m = robot_from_ee_measured.translation.vector;
                let rpy_m = rpy_from_rotation(&robot_from_ee_measured.rotation);
                (
                    [m.x + a[0], m.y + a[1], m.z + a[2]],
                    [rpy_m[0] + a[3], rpy_m[1] + a[4], rpy_m[2] + a[5]],
                )
            }
        };
        let pose = Isometry3::from_parts(
            Translation3::new(position[0], position[1], position[2]),
            rotation_from_rpy(rpy),
        );
        Ok((pose, a[6].clamp(0.0, 1.0)))
    }
}

fn check_action(action: &[f64]) -> Result<(), LayoutError> {
    if action.len() != ACTION_WIDTH {
        return Err(LayoutError::WrongWidth {
            what: "action",
            expected: ACTION_WIDTH,
            got: action.len(),
        });
    }
    if let Some((index, &value)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(LayoutError::NonFinite {
            what: "action",
            index,
            value,
        });
    }
    Ok(())
}

/// Layouts of several arms concatenated in a fixed order. Names get an `{arm}_` prefix only when there is
/// more than one arm, so a single-arm dataset keeps the plain LeRobot names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MultiArmLayout {
    arms: Vec<(String, ArmLayout)>,
}

impl MultiArmLayout {
    pub fn new(arms: Vec<(String, ArmLayout)>) -> Self {
        Self { arms }
    }

    pub fn arms(&self) -> impl Iterator<Item = (&str, &ArmLayout)> {
        self.arms.iter().map(|(n, l)| (n.as_str(), l))
    }

    fn prefixed(&self, arm: &str, names: Vec<String>) -> Vec<String> {
        if self.arms.len() > 1 {
            names.into_iter().map(|n| format!("{arm}_{n}")).collect()
        } else {
            names
        }
    }

    pub fn state_names(&self) -> Vec<String> {
        self.arms
            .iter()
            .flat_map(|(arm, l)| self.prefixed(arm, l.state_names()))
            .collect()
    }

    pub fn action_names(&self, mode: ActionMode) -> Vec<String> {
        self.arms
            .iter()
            .flat_map(|(arm, l)| self.prefixed(arm, l.action_names(mode)))
            .collect()
    }

    pub fn state_width(&self) -> usize {
        self.arms.iter().map(|(_, l)| l.state_width()).sum()
    }

    pub fn action_width(&self) -> usize {
        self.arms.len() * ACTION_WIDTH
    }

    fn index(&self, arm: &str) -> Result<usize, LayoutError> {
        self.arms
            .iter()
            .position(|(n, _)| n == arm)
            .ok_or_else(|| LayoutError::UnknownArm(arm.to_owned()))
    }

    /// Where an arm's values sit in the concatenated state vector.
    pub fn state_range(&self, arm: &str) -> Result<Range<usize>, LayoutError> {
        let i = self.index(arm)?;
        let start: usize = self.arms[..i].iter().map(|(_, l)| l.state_width()).sum();
        Ok(start..start + self.arms[i].1.state_width())
    }

    /// Where an arm's values sit in the concatenated action vector.
    pub fn action_range(&self, arm: &str) -> Result<Range<usize>, LayoutError> {
        let i = self.index(arm)?;
        Ok(i * ACTION_WIDTH..(i + 1) * ACTION_WIDTH)
    }

    /// Splits a concatenated action into per-arm slices.
    pub fn split_action<'a>(&self, action: &'a [f64]) -> Result<Vec<(&str, &'a [f64])>, LayoutError> {
        if action.len() != self.action_width() {
            return Err(LayoutError::WrongWidth {
                what: "action",
                expected: self.action_width(),
                got: action.len(),
            });
        }
        Ok(self
            .arms
            .iter()
            .zip(action.chunks_exact(ACTION_WIDTH))
            .map(|((n, _), a)| (n.as_str(), a))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::pose_distance;
    use nalgebra::{Quaternion, UnitQuaternion};
    use proptest::prelude::*;
    use std::f64::consts::FRAC_PI_2;

    fn so101() -> ArmLayout {
        ArmLayout::new(
            [
                "shoulder_pan",
                "shoulder_lift",
                "elbow_flex",
                "wrist_flex",
                "wrist_roll",
            ]
            .iter()
            .map(|s| (*s).to_owned())
            .collect(),
        )
    }

    #[test]
    fn names_and_state_vector() {
        let l = so101();
        assert_eq!(l.state_names().len(), 12);
        assert_eq!(&l.state_names()[5..], &EE_STATE_NAMES.map(str::to_owned));
        assert_eq!(l.action_names(ActionMode::Delta)[3], "delta_roll");
        assert_eq!(l.action_names(ActionMode::Absolute)[5], "yaw");
        let ee = Isometry3::from_parts(
            Translation3::new(0.2, -0.1, 0.3),
            rotation_from_rpy([0.1, 0.2, 0.3]),
        );
        let v = l.state_vector(&[1.0, 2.0, 3.0, 4.0, 5.0], &ee, 0.5).unwrap();
        assert_eq!(v.len(), 12);
        let expected = [1.0, 2.0, 3.0, 4.0, 5.0, 0.2, -0.1, 0.3, 0.1, 0.2, 0.3, 0.5];
        assert!(
            v.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12),
            "{v:?}"
        );
        assert!(matches!(
            l.state_vector(&[1.0], &ee, 0.5),
            Err(LayoutError::WrongWidth {
                expected: 5,
                got: 1,
                ..
            })
        ));
    }

    #[test]
    fn delta_action_wraps_across_pi() {
        let l = so101();
        let m = Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.2),
            rotation_from_rpy([0.0, 0.0, 3.1]),
        );
        let t = Isometry3::from_parts(
            Translation3::new(0.21, 0.0, 0.2),
            rotation_from_rpy([0.0, 0.0, -3.1]),
        );
        let a = l.action_from_target(&m, &t, 1.0, ActionMode::Delta);
        assert!((a[0] - 0.01).abs() < 1e-12);
        assert!(
            (a[5] - (2.0 * std::f64::consts::PI - 6.2)).abs() < 1e-12,
            "yaw delta goes the short way: {}",
            a[5]
        );
        assert!(matches!(
            l.target_from_action(&m, &a[..6], ActionMode::Delta),
            Err(LayoutError::WrongWidth { .. })
        ));
        let mut bad = a.clone();
        bad[2] = f64::NAN;
        assert!(matches!(
            l.target_from_action(&m, &bad, ActionMode::Delta),
            Err(LayoutError::NonFinite { index: 2, .. })
        ));
    }

    #[test]
    fn multi_arm_names_are_prefixed() {
        let single = MultiArmLayout::new(vec![("main".into(), so101())]);
        assert_eq!(single.state_names(), so101().state_names());
        let two = MultiArmLayout::new(vec![("left".into(), so101()), ("right".into(), so101())]);
        assert_eq!(two.state_names()[0], "left_shoulder_pan");
        assert_eq!(two.action_names(ActionMode::Delta)[7], "right_delta_x");
        assert_eq!(two.state_range("right").unwrap(), 12..24);
        assert_eq!(two.action_range("right").unwrap(), 7..14);
        let action: Vec<f64> = (0..14).map(f64::from).collect();
        let split = two.split_action(&action).unwrap();
        assert_eq!(split[1].0, "right");
        assert!((split[1].1[0] - 7.0).abs() < 1e-15);
        assert!(two.split_action(&action[..13]).is_err());
        assert!(matches!(
            two.action_range("middle"),
            Err(LayoutError::UnknownArm(_))
        ));
    }

    fn any_pose() -> impl Strategy<Value = Isometry3<f64>> {
        (
            prop::array::uniform3(-1.0..1.0f64),
            prop::array::uniform4(-1.0..1.0f64),
            0..4u8,
            -1e-7..1e-7f64,
            -3.2..3.2f64,
        )
            .prop_map(|(p, q, kind, dp, angle)| {
                let quat = Quaternion::new(q[3], q[0], q[1], q[2]);
                let rotation = match kind {
                    // A quarter of the poses sit at or next to ±90° pitch.
                    0 => rotation_from_rpy([angle, FRAC_PI_2 + dp, q[0] * 3.0]),
                    1 => rotation_from_rpy([q[1] * 3.0, -FRAC_PI_2 + dp, angle]),
                    _ if quat.norm() < 1e-3 => UnitQuaternion::identity(),
                    _ => UnitQuaternion::new_normalize(quat),
                };
                Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), rotation)
            })
    }

    proptest! {
        #[test]
        fn action_round_trip_is_exact(measured in any_pose(), target in any_pose(), gripper in 0.0..=1.0f64, absolute in prop::bool::ANY) {
            let l = so101();
            let mode = if absolute { ActionMode::Absolute } else { ActionMode::Delta };
            let action = l.action_from_target(&measured, &target, gripper, mode);
            prop_assert_eq!(action.len(), ACTION_WIDTH);
            prop_assert!(action.iter().all(|v| v.is_finite()));
            if !absolute {
                prop_assert!(action[3..6].iter().all(|a| *a > -std::f64::consts::PI && *a <= std::f64::consts::PI));
            }
            let (back, g) = l.target_from_action(&measured, &action, mode).unwrap();
            let (dp, da) = pose_distance(&back, &target);
            prop_assert!(dp < 1e-9 && da < 1e-9, "position error {} m, angle error {} rad", dp, da);
            prop_assert!((g - gripper).abs() < 1e-15);
        }
    }
}
