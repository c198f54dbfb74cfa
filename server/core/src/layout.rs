//! The one definition of the `observation.state` and `action` vectors: what a dataset records, what a policy
//! is trained on and what the chunk executor does with a pushed step.
//!
//! - `observation.state`: joint positions (rad) in bridge order, then `ee_x ee_y ee_z` (m, robot base frame),
//!   then the end effector's orientation as a 6D rotation, `ee_r00 ee_r10 ee_r20 ee_r01 ee_r11 ee_r21` (the
//!   first two columns of the `robot_from_ee` rotation matrix, Zhou et al. 2019, GR00T's `rotation_6d`), then
//!   `gripper` (0 open, 1 closed).
//! - `action` as recorded: the **absolute** end-effector target the operator commanded at that frame (after
//!   the safety gate): `x y z` (m, base frame), `r00 r10 r20 r01 r11 r21` (6D, as in the state) and the gripper
//!   target. A target does not depend on where the arm was, so frame t's action means the same thing
//!   whichever earlier frame a chunk's observation came from.
//! - A pushed chunk step is read according to its [`ActionMode`]: absolute steps are the recorded layout;
//!   relative steps (GR00T's "relative" actions) are `delta_x delta_y delta_z` = target − observation position
//!   (m, base frame), `delta_rx delta_ry delta_rz` = rotation vector of `R_target·R_obsᵀ` (rad, base frame)
//!   and the gripper target, taken against the pose of the observation the chunk answers. A trainer or
//!   adapter turns recorded absolute targets into relative steps per chunk with [`relative_step`]; the
//!   executor composes them back with [`target_from_step`]; the two are exact inverses.
//! - Joint arms (`action_mode = "joint"`, arms with SO-101 kinematics) record and push joint targets
//!   instead: the joint positions (rad, bridge order) the executed target asks for, by inverse kinematics
//!   seeded with the measured joints, then the gripper target; a pushed joint step commands the pose forward
//!   kinematics gives ([`joint_action`], [`target_from_joint_step`]).
//!
//! Why 6D and not roll-pitch-yaw or a rotation vector: every 3-number orientation has a seam somewhere (RPY
//! wraps at ±π and flips at ±90° pitch; a rotation vector flips at 180° from its reference), and an arm with a
//! wrist roll reaches both sides of any seam. The 6D form is a continuous function of the rotation, so no
//! recorded dimension jumps unless the gripper does. Relative steps keep a rotation vector: it is 3 numbers,
//! zero means "stay", and a chunk's rotation relative to its own observation is far from 180°.

use crate::kinematics::{IkWeights, SO101_ARM_DOF, So101Joints, So101Kinematics};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Width of one arm's recorded action (and of an absolute chunk step): position, 6D rotation, gripper.
pub const ACTION_WIDTH: usize = 10;
/// Width of one arm's relative chunk step: position delta, rotation vector, gripper.
pub const RELATIVE_STEP_WIDTH: usize = 7;

const EE_STATE_NAMES: [&str; 10] = [
    "ee_x", "ee_y", "ee_z", "ee_r00", "ee_r10", "ee_r20", "ee_r01", "ee_r11", "ee_r21", "gripper",
];
const ABSOLUTE_ACTION_NAMES: [&str; ACTION_WIDTH] =
    ["x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "gripper"];
const RELATIVE_ACTION_NAMES: [&str; RELATIVE_STEP_WIDTH] = [
    "delta_x", "delta_y", "delta_z", "delta_rx", "delta_ry", "delta_rz", "gripper",
];

/// How a pushed chunk step encodes its end-effector target. Datasets always record absolute targets; the
/// arm's configured mode is what policies are told to push (and how they should be trained).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ActionMode {
    /// Relative to the pose of the chunk's observation (GR00T "relative"); zero holds that pose.
    #[default]
    #[serde(alias = "delta")]
    Relative,
    /// Absolute target pose in the base frame (lerobot's habit).
    Absolute,
    /// Joint targets (rad) and gripper; recorded that way too.
    Joint,
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
    #[error("the 6D rotation's columns are {what} (norms {norm_a:.3e}, {norm_b:.3e}): not a rotation")]
    DegenerateRotation {
        what: &'static str,
        norm_a: f64,
        norm_b: f64,
    },
    #[error("unknown arm {0:?}")]
    UnknownArm(String),
    #[error("joint steps need the arm's kinematics (joint mode is for arms with SO-101 kinematics)")]
    NoKinematics,
}

/// Columns shorter than this, or this close to parallel (sine of their angle), are not a rotation: they
/// would make Gram-Schmidt amplify noise into an arbitrary orientation.
const MIN_6D_COLUMN: f64 = 1e-3;

/// The 6D form of a rotation: its matrix's first two columns, `[r00 r10 r20 r01 r11 r21]`.
pub fn rot6d_from_rotation(rotation: &UnitQuaternion<f64>) -> [f64; 6] {
    let m = rotation.to_rotation_matrix();
    let m = m.matrix();
    [m[(0, 0)], m[(1, 0)], m[(2, 0)], m[(0, 1)], m[(1, 1)], m[(2, 1)]]
}

/// The rotation nearest a 6D value (Gram-Schmidt: the first column's direction is kept, the second is made
/// orthogonal to it), so a policy's slightly non-orthonormal output still commands a rotation.
pub fn rotation_from_rot6d(v: [f64; 6]) -> Result<UnitQuaternion<f64>, LayoutError> {
    let a = Vector3::new(v[0], v[1], v[2]);
    let b = Vector3::new(v[3], v[4], v[5]);
    let (norm_a, norm_b) = (a.norm(), b.norm());
    let degenerate = |what| LayoutError::DegenerateRotation { what, norm_a, norm_b };
    if !(norm_a >= MIN_6D_COLUMN && norm_b >= MIN_6D_COLUMN) {
        return Err(degenerate("too short"));
    }
    let x = a / norm_a;
    let b_perp = b - x * x.dot(&b);
    if b_perp.norm() < MIN_6D_COLUMN * norm_b {
        return Err(degenerate("parallel"));
    }
    let y = b_perp.normalize();
    let z = x.cross(&y);
    let m = Matrix3::from_columns(&[x, y, z]);
    Ok(UnitQuaternion::from_rotation_matrix(
        &Rotation3::from_matrix_unchecked(m),
    ))
}

/// The step of a relative chunk that commands `robot_from_target` from an observation at
/// `robot_from_observation`: what a trainer computes per chunk from recorded absolute targets.
pub fn relative_step(
    robot_from_observation: &Isometry3<f64>,
    robot_from_target: &Isometry3<f64>,
    gripper_target: f64,
) -> Vec<f64> {
    let dp = robot_from_target.translation.vector - robot_from_observation.translation.vector;
    let dr = (robot_from_target.rotation * robot_from_observation.rotation.inverse()).scaled_axis();
    vec![dp.x, dp.y, dp.z, dr.x, dr.y, dr.z, gripper_target]
}

/// The chunk step in `mode` that commands `robot_from_target` from an observation at
/// `robot_from_observation`: the inverse of [`target_from_step`].
pub fn step_from_target(
    robot_from_observation: &Isometry3<f64>,
    robot_from_target: &Isometry3<f64>,
    gripper_target: f64,
    mode: ActionMode,
) -> Vec<f64> {
    match mode {
        ActionMode::Absolute | ActionMode::Joint => absolute_action(robot_from_target, gripper_target),
        ActionMode::Relative => relative_step(robot_from_observation, robot_from_target, gripper_target),
    }
}

/// The joint action (recorded layout of a joint arm) of a target: the joints inverse kinematics finds for it,
/// seeded with the measured joints as the bridges seed theirs, then the gripper target.
pub fn joint_action(
    kinematics: &So101Kinematics,
    robot_from_target: &Isometry3<f64>,
    measured_joints_rad: &[f64],
    gripper_target: f64,
) -> Result<Vec<f64>, LayoutError> {
    let seed: So101Joints = measured_joints_rad
        .try_into()
        .map_err(|_| LayoutError::WrongWidth {
            what: "joint positions",
            expected: SO101_ARM_DOF,
            got: measured_joints_rad.len(),
        })?;
    let solution = kinematics.inverse(robot_from_target, &seed, IkWeights::FULL);
    let mut v = solution.joints_rad.to_vec();
    v.push(gripper_target);
    Ok(v)
}

/// The target pose and gripper target (clamped to [0, 1]) a joint step commands: forward kinematics of its
/// joints, which the bridge's inverse kinematics, seeded near them, solves back to the same joints.
pub fn target_from_joint_step(
    kinematics: &So101Kinematics,
    step: &[f64],
) -> Result<(Isometry3<f64>, f64), LayoutError> {
    check_values("action", step, SO101_ARM_DOF + 1)?;
    let joints: So101Joints = std::array::from_fn(|j| step[j]);
    Ok((kinematics.forward(&joints), step[SO101_ARM_DOF].clamp(0.0, 1.0)))
}

/// The absolute action (recorded layout) of a target.
pub fn absolute_action(robot_from_target: &Isometry3<f64>, gripper_target: f64) -> Vec<f64> {
    let t = robot_from_target.translation.vector;
    let r = rot6d_from_rotation(&robot_from_target.rotation);
    let mut v = Vec::with_capacity(ACTION_WIDTH);
    v.extend_from_slice(&[t.x, t.y, t.z]);
    v.extend_from_slice(&r);
    v.push(gripper_target);
    v
}

/// The target pose and gripper target (clamped to [0, 1]) a chunk step commands, given the pose of the
/// observation the chunk answers (used by relative steps only).
pub fn target_from_step(
    robot_from_observation: &Isometry3<f64>,
    step: &[f64],
    mode: ActionMode,
) -> Result<(Isometry3<f64>, f64), LayoutError> {
    let (pose, gripper) = match mode {
        ActionMode::Joint => return Err(LayoutError::NoKinematics),
        ActionMode::Absolute => {
            check_values("action", step, ACTION_WIDTH)?;
            let rotation = rotation_from_rot6d([step[3], step[4], step[5], step[6], step[7], step[8]])?;
            (
                Isometry3::from_parts(Translation3::new(step[0], step[1], step[2]), rotation),
                step[9],
            )
        }
        ActionMode::Relative => {
            check_values("action", step, RELATIVE_STEP_WIDTH)?;
            let p = robot_from_observation.translation.vector + Vector3::new(step[0], step[1], step[2]);
            let dr = UnitQuaternion::from_scaled_axis(Vector3::new(step[3], step[4], step[5]));
            (
                Isometry3::from_parts(Translation3::from(p), dr * robot_from_observation.rotation),
                step[6],
            )
        }
    };
    Ok((pose, gripper.clamp(0.0, 1.0)))
}

/// The end-effector pose an `observation.state` row (or its end-effector part) reports, and the gripper.
pub fn pose_from_state_tail(ee: &[f64]) -> Result<(Isometry3<f64>, f64), LayoutError> {
    check_values("end-effector state", ee, EE_STATE_NAMES.len())?;
    let rotation = rotation_from_rot6d([ee[3], ee[4], ee[5], ee[6], ee[7], ee[8]])?;
    Ok((
        Isometry3::from_parts(Translation3::new(ee[0], ee[1], ee[2]), rotation),
        ee[9],
    ))
}

fn check_values(what: &'static str, values: &[f64], expected: usize) -> Result<(), LayoutError> {
    if values.len() != expected {
        return Err(LayoutError::WrongWidth {
            what,
            expected,
            got: values.len(),
        });
    }
    if let Some((index, &value)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(LayoutError::NonFinite { what, index, value });
    }
    Ok(())
}

/// lerobot's `so101_follower` units, for datasets that merge with lerobot's own SO-101 datasets: the state and
/// action are `shoulder_pan.pos` … `wrist_roll.pos` in degrees (lerobot's `use_degrees=True`, `(raw − mid)·360/4095`,
/// which is what phone2act's SO-101 bridge reads as radians) and `gripper.pos` in percent of the calibrated
/// range (`RANGE_0_100`), here at `gripper_open_pct` for phone2act's 0 (open) and `gripper_closed_pct` for 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LerobotSo101Units {
    pub gripper_open_pct: f64,
    pub gripper_closed_pct: f64,
}

/// Vector layout of one arm.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmLayout {
    joint_names: Vec<String>,
    lerobot: Option<LerobotSo101Units>,
}

impl ArmLayout {
    pub fn new(joint_names: Vec<String>) -> Self {
        Self {
            joint_names,
            lerobot: None,
        }
    }

    /// The same arm with lerobot `so101_follower` names and units for its state and joint actions (and no
    /// end-effector columns, as lerobot has none).
    #[must_use]
    pub fn with_lerobot_so101(self, units: LerobotSo101Units) -> Self {
        Self {
            lerobot: Some(units),
            ..self
        }
    }

    /// lerobot's names: `{joint}.pos`, then `gripper.pos`.
    fn lerobot_names(&self) -> Vec<String> {
        self.joint_names
            .iter()
            .map(|n| format!("{n}.pos"))
            .chain(std::iter::once("gripper.pos".to_owned()))
            .collect()
    }

    /// A joint step in this layout's units (lerobot degrees and percent, or radians and 0..1) in radians and
    /// 0..1.
    pub fn joint_step_to_native(&self, step: &[f64]) -> Vec<f64> {
        match self.lerobot {
            None => step.to_vec(),
            Some(u) => {
                let span = u.gripper_closed_pct - u.gripper_open_pct;
                step.iter()
                    .enumerate()
                    .map(|(i, v)| {
                        if i + 1 < step.len() {
                            v.to_radians()
                        } else if span.abs() < 1e-9 {
                            0.0
                        } else {
                            (v - u.gripper_open_pct) / span
                        }
                    })
                    .collect()
            }
        }
    }

    /// The inverse of [`ArmLayout::joint_step_to_native`].
    pub fn joint_step_from_native(&self, step: &[f64]) -> Vec<f64> {
        match self.lerobot {
            None => step.to_vec(),
            Some(u) => step
                .iter()
                .enumerate()
                .map(|(i, v)| {
                    if i + 1 < step.len() {
                        v.to_degrees()
                    } else {
                        u.gripper_open_pct + (u.gripper_closed_pct - u.gripper_open_pct) * v
                    }
                })
                .collect(),
        }
    }

    pub fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    pub fn state_width(&self) -> usize {
        if self.lerobot.is_some() {
            return self.joint_names.len() + 1;
        }
        self.joint_names.len() + EE_STATE_NAMES.len()
    }

    pub fn state_names(&self) -> Vec<String> {
        if self.lerobot.is_some() {
            return self.lerobot_names();
        }
        self.joint_names
            .iter()
            .cloned()
            .chain(EE_STATE_NAMES.iter().map(|s| (*s).to_owned()))
            .collect()
    }

    /// Names of the recorded `action` of an arm configured with `mode`: absolute end-effector targets, or
    /// joint targets for a joint arm.
    pub fn recorded_action_names(&self, mode: ActionMode) -> Vec<String> {
        match mode {
            ActionMode::Joint => self.action_names(ActionMode::Joint),
            ActionMode::Absolute | ActionMode::Relative => {
                ABSOLUTE_ACTION_NAMES.iter().map(|s| (*s).to_owned()).collect()
            }
        }
    }

    /// Names of a chunk step's values in `mode`.
    pub fn action_names(&self, mode: ActionMode) -> Vec<String> {
        match mode {
            ActionMode::Absolute => self.recorded_action_names(mode),
            ActionMode::Relative => RELATIVE_ACTION_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            ActionMode::Joint if self.lerobot.is_some() => self.lerobot_names(),
            ActionMode::Joint => self
                .joint_names
                .iter()
                .cloned()
                .chain(std::iter::once("gripper".to_owned()))
                .collect(),
        }
    }

    /// Where the end-effector part (`ee_x` … `gripper`) sits in this arm's state vector (empty in the lerobot
    /// layout, which has none).
    pub fn ee_state_range(&self) -> Range<usize> {
        if self.lerobot.is_some() {
            return self.state_width()..self.state_width();
        }
        self.joint_names.len()..self.state_width()
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
        if self.lerobot.is_some() {
            let mut native = joints_rad.to_vec();
            native.push(gripper);
            return Ok(self.joint_step_from_native(&native));
        }
        let mut v = Vec::with_capacity(self.state_width());
        v.extend_from_slice(joints_rad);
        v.extend(absolute_action(robot_from_ee, gripper));
        Ok(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{SO101_JOINT_LIMITS_RAD, So101Kinematics};
    use crate::pose::{angle_between_rad, pose_distance, rotation_from_rpy};
    use nalgebra::Quaternion;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

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
        assert_eq!(l.state_names().len(), 15);
        assert_eq!(&l.state_names()[5..], &EE_STATE_NAMES.map(str::to_owned));
        assert_eq!(l.ee_state_range(), 5..15);
        assert_eq!(l.recorded_action_names(ActionMode::Relative)[3], "r00");
        assert_eq!(
            l.action_names(ActionMode::Absolute),
            l.recorded_action_names(ActionMode::Relative)
        );
        assert_eq!(l.recorded_action_names(ActionMode::Joint)[4], "wrist_roll");
        assert_eq!(l.action_names(ActionMode::Joint).len(), 6);
        assert_eq!(l.action_names(ActionMode::Relative)[5], "delta_rz");
        let ee = Isometry3::from_parts(
            Translation3::new(0.2, -0.1, 0.3),
            rotation_from_rpy([0.0, 0.0, FRAC_PI_2]),
        );
        let v = l.state_vector(&[1.0, 2.0, 3.0, 4.0, 5.0], &ee, 0.5).unwrap();
        // A quarter turn about z: the x axis points along +y, the y axis along −x.
        let expected = [
            1.0, 2.0, 3.0, 4.0, 5.0, 0.2, -0.1, 0.3, 0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.5,
        ];
        assert!(
            v.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12),
            "{v:?}"
        );
        let (back, g) = pose_from_state_tail(&v[l.ee_state_range()]).unwrap();
        assert!(pose_distance(&back, &ee).0 < 1e-15 && (g - 0.5).abs() < 1e-15);
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
    fn bad_steps_are_refused() {
        let obs = Isometry3::translation(0.2, 0.0, 0.2);
        let wrong: [(&[f64], ActionMode); 5] = [
            (&[0.0; 7], ActionMode::Absolute),
            (&[0.0; 10], ActionMode::Relative),
            (
                &[0.2, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                ActionMode::Absolute,
            ),
            (
                &[0.2, 0.0, 0.2, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0],
                ActionMode::Absolute,
            ),
            (&[0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0], ActionMode::Relative),
        ];
        for (step, mode) in wrong {
            let err = target_from_step(&obs, step, mode).unwrap_err();
            assert!(!err.to_string().is_empty(), "{step:?}");
        }
        // Zero relative step: hold the observation's pose.
        let (hold, g) =
            target_from_step(&obs, &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0], ActionMode::Relative).unwrap();
        assert_eq!(hold, obs);
        assert!((g - 1.0).abs() < 1e-15, "gripper clamped to [0, 1]");
        // A slightly non-orthonormal 6D (a policy's output) still gives the nearest rotation.
        let (p, _) = target_from_step(
            &obs,
            &[0.2, 0.0, 0.2, 1.01, 0.0, 0.02, 0.01, 0.98, 0.0, 0.0],
            ActionMode::Absolute,
        )
        .unwrap();
        assert!(angle_between_rad(&p.rotation, &UnitQuaternion::identity()) < 0.03);
    }

    fn any_rotation() -> impl Strategy<Value = UnitQuaternion<f64>> {
        (
            prop::array::uniform4(-1.0..1.0f64),
            0..4u8,
            -1e-7..1e-7f64,
            -PI..PI,
        )
            .prop_map(|(q, kind, dp, angle)| {
                let quat = Quaternion::new(q[3], q[0], q[1], q[2]);
                match kind {
                    // A quarter of the rotations sit at or next to ±90° pitch, and at ±π about some axis.
                    0 => rotation_from_rpy([angle, FRAC_PI_2 + dp, q[0] * 3.0]),
                    1 => UnitQuaternion::from_scaled_axis(
                        Vector3::new(q[0], q[1], q[2]).normalize() * (PI - dp.abs()),
                    ),
                    _ if quat.norm() < 1e-3 => UnitQuaternion::identity(),
                    _ => UnitQuaternion::new_normalize(quat),
                }
            })
    }

    fn any_pose() -> impl Strategy<Value = Isometry3<f64>> {
        (prop::array::uniform3(-1.0..1.0f64), any_rotation())
            .prop_map(|(p, r)| Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), r))
    }

    /// Largest change of the 6D form per radian of rotation: each column is a unit vector turned by at most
    /// the rotation's angle, so it moves by at most that angle (chord ≤ arc).
    const ROT6D_PER_RAD: f64 = std::f64::consts::SQRT_2;

    /// A lagging arm following a sequence of targets, sampled at frame times (for the invariant tests).
    fn lagging(targets: &[Isometry3<f64>], alpha: f64) -> Vec<Isometry3<f64>> {
        let mut measured = Vec::with_capacity(targets.len());
        let mut m = targets[0];
        for t in targets {
            measured.push(m);
            m = m.lerp_slerp(t, alpha);
        }
        measured
    }

    proptest! {
        #[test]
        fn rot6d_round_trip_is_exact(q in any_rotation()) {
            let back = rotation_from_rot6d(rot6d_from_rotation(&q)).unwrap();
            prop_assert!(angle_between_rad(&q, &back) < 1e-12);
        }

        #[test]
        fn absolute_and_relative_steps_round_trip(obs in any_pose(), target in any_pose(), gripper in 0.0..=1.0f64) {
            let a = absolute_action(&target, gripper);
            prop_assert_eq!(a.len(), ACTION_WIDTH);
            let (back, g) = target_from_step(&obs, &a, ActionMode::Absolute).unwrap();
            let (dp, da) = pose_distance(&back, &target);
            prop_assert!(dp < 1e-12 && da < 1e-9 && (g - gripper).abs() < 1e-15, "{} {}", dp, da);
            let r = relative_step(&obs, &target, gripper);
            prop_assert_eq!(r.len(), RELATIVE_STEP_WIDTH);
            let (back, g) = target_from_step(&obs, &r, ActionMode::Relative).unwrap();
            let (dp, da) = pose_distance(&back, &target);
            prop_assert!(dp < 1e-12 && da < 1e-9 && (g - gripper).abs() < 1e-15, "{} {}", dp, da);
        }

        /// The invariant, without the network: along an operator's target path followed by a lagging arm,
        /// the recorded action of frame t, pushed as step t − t0 of a chunk observed at any earlier frame t0
        /// (absolute as recorded, relative as a trainer converts it from the recorded state), commands the
        /// target of frame t. The per-frame delta the recorder used to write (target(t) − measured(t)),
        /// composed onto the observation of t0, misses by centimetres on the same path.
        #[test]
        fn recorded_actions_command_the_recorded_targets(
            start in any_pose(),
            velocity in prop::array::uniform3(-0.2..0.2f64),
            spin in prop::array::uniform3(-3.0..3.0f64),
            t0 in 0..16usize,
            k in 0..16usize,
        ) {
            let fps = 20.0;
            let targets: Vec<Isometry3<f64>> = (0..32).map(|i| {
                let s = f64::from(i) / fps;
                Isometry3::from_parts(
                    Translation3::from(start.translation.vector + Vector3::from(velocity) * s),
                    UnitQuaternion::from_scaled_axis(Vector3::from(spin) * s) * start.rotation,
                )
            }).collect();
            let measured = lagging(&targets, 0.6);
            let layout = so101();
            let states: Vec<Vec<f64>> = measured.iter().map(|m| layout.state_vector(&[0.0; 5], m, 0.0).unwrap()).collect();
            let actions: Vec<Vec<f64>> = targets.iter().map(|t| absolute_action(t, 1.0)).collect();
            let t = t0 + k;
            let (obs, _) = pose_from_state_tail(&states[t0][layout.ee_state_range()]).unwrap();
            let (abs, _) = target_from_step(&obs, &actions[t], ActionMode::Absolute).unwrap();
            // What a trainer does per chunk: recorded absolute target ⊖ recorded state of the chunk's frame.
            let (target, _) = pose_from_state_tail(&actions[t]).unwrap();
            let relative = relative_step(&obs, &target, 1.0);
            let (rel, _) = target_from_step(&obs, &relative, ActionMode::Relative).unwrap();
            for got in [abs, rel] {
                let (dp, da) = pose_distance(&got, &target);
                prop_assert!(dp < 1e-9 && da < 1e-9, "{} m {} rad", dp, da);
            }
        }

        /// No state or action dimension jumps where the pose does not: along any path of small rotation steps
        /// (through ±π about any axis, through ±90° pitch), each step of the 6D values is bounded by the
        /// rotation's own step, and positions by the position step.
        #[test]
        fn orientation_dimensions_are_continuous(
            start in any_rotation(),
            axis in prop::array::uniform3(-1.0..1.0f64),
            turn_rad in -7.0..7.0f64,
        ) {
            let axis = Vector3::from(axis);
            prop_assume!(axis.norm() > 1e-3);
            let steps = 400;
            let layout = so101();
            let mut previous: Option<(UnitQuaternion<f64>, Vec<f64>)> = None;
            for i in 0..=steps {
                let q = UnitQuaternion::from_scaled_axis(axis.normalize() * turn_rad * f64::from(i) / f64::from(steps)) * start;
                let pose = Isometry3::from_parts(Translation3::new(0.2, 0.0, 0.2), q);
                let row = layout.state_vector(&[0.0; 5], &pose, 0.0).unwrap();
                let action = absolute_action(&pose, 0.0);
                prop_assert_eq!(&row[layout.ee_state_range()], &action[..]);
                if let Some((q_prev, prev)) = &previous {
                    let dtheta = angle_between_rad(q_prev, &q);
                    let jump = prev.iter().zip(&row).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt();
                    prop_assert!(jump <= ROT6D_PER_RAD * dtheta + 1e-12, "step {}: 6D moved {} for {} rad", i, jump, dtheta);
                }
                previous = Some((q, row));
            }
        }

        /// The same over the simulated SO-101's reachable orientations: random joint paths inside the limits,
        /// through forward kinematics.
        #[test]
        fn reachable_sim_orientations_are_continuous(
            from in prop::array::uniform5(0.0..1.0f64),
            to in prop::array::uniform5(0.0..1.0f64),
        ) {
            let kin = So101Kinematics::new();
            let layout = so101();
            let joints_at = |s: f64| -> [f64; 5] {
                std::array::from_fn(|j| {
                    let (lo, hi) = SO101_JOINT_LIMITS_RAD[j];
                    let u = from[j] + (to[j] - from[j]) * s;
                    lo + (hi - lo) * u
                })
            };
            let mut previous: Option<(Isometry3<f64>, Vec<f64>)> = None;
            for i in 0..=300 {
                let joints = joints_at(f64::from(i) / 300.0);
                let pose = kin.forward(&joints);
                let row = layout.state_vector(&joints, &pose, 0.0).unwrap();
                if let Some((prev_pose, prev)) = &previous {
                    let (dp, dtheta) = pose_distance(prev_pose, &pose);
                    let r = layout.ee_state_range();
                    let position_jump = prev[r.start..r.start + 3].iter().zip(&row[r.start..r.start + 3]).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt();
                    let rot_jump = prev[r.start + 3..r.end - 1].iter().zip(&row[r.start + 3..r.end - 1]).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt();
                    prop_assert!(position_jump <= dp + 1e-12);
                    prop_assert!(rot_jump <= ROT6D_PER_RAD * dtheta + 1e-12, "step {}: {} for {} rad", i, rot_jump, dtheta);
                }
                previous = Some((pose, row));
            }
        }
    }

    proptest! {
        /// A joint action of a reachable target commands that target again: inverse kinematics seeded near the
        /// joints that reach it finds them, and forward kinematics gives the pose back.
        #[test]
        fn joint_actions_round_trip(u in prop::array::uniform5(0.05..0.95f64), nudge in prop::array::uniform5(-0.05..0.05f64)) {
            let kin = So101Kinematics::new();
            let joints: [f64; 5] = std::array::from_fn(|j| {
                let (lo, hi) = SO101_JOINT_LIMITS_RAD[j];
                lo + (hi - lo) * u[j]
            });
            let target = kin.forward(&joints);
            let seed: Vec<f64> = joints.iter().zip(nudge).map(|(q, d)| q + d).collect();
            let action = joint_action(&kin, &target, &seed, 0.3).unwrap();
            let (back, g) = target_from_joint_step(&kin, &action).unwrap();
            let (dp, da) = pose_distance(&back, &target);
            prop_assert!(dp < 1e-4 && da < 1e-3, "{} m {} rad", dp, da);
            prop_assert!((g - 0.3).abs() < 1e-15);
        }
    }

    #[test]
    fn lerobot_so101_names_and_units() {
        let units = LerobotSo101Units {
            gripper_open_pct: 100.0,
            gripper_closed_pct: 0.0,
        };
        let l = so101().with_lerobot_so101(units);
        let names = [
            "shoulder_pan.pos",
            "shoulder_lift.pos",
            "elbow_flex.pos",
            "wrist_flex.pos",
            "wrist_roll.pos",
            "gripper.pos",
        ];
        assert_eq!(l.state_names(), names);
        assert_eq!(l.action_names(ActionMode::Joint), names);
        assert_eq!(l.recorded_action_names(ActionMode::Joint), names);
        assert!(l.ee_state_range().is_empty());
        let state = l
            .state_vector(&[FRAC_PI_2, -0.5, 0.0, 0.1, -PI], &Isometry3::identity(), 0.25)
            .unwrap();
        let expected = [90.0, -0.5f64.to_degrees(), 0.0, 0.1f64.to_degrees(), -180.0, 75.0];
        assert!(
            state.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12),
            "{state:?}"
        );
        let native = l.joint_step_to_native(&state);
        let back = l.joint_step_from_native(&native);
        assert!(back.iter().zip(&state).all(|(a, b)| (a - b).abs() < 1e-12));
        assert!((native[0] - FRAC_PI_2).abs() < 1e-15 && (native[5] - 0.25).abs() < 1e-15);
    }

    #[test]
    fn joint_steps_need_kinematics_and_the_right_width() {
        let kin = So101Kinematics::new();
        assert!(matches!(
            target_from_step(&Isometry3::identity(), &[0.0; 6], ActionMode::Joint),
            Err(LayoutError::NoKinematics)
        ));
        assert!(target_from_joint_step(&kin, &[0.0; 5]).is_err());
        assert!(target_from_joint_step(&kin, &[0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0]).is_err());
        assert!(joint_action(&kin, &Isometry3::identity(), &[0.0; 3], 0.0).is_err());
    }

    /// What the recorder used to write (per-frame delta against the frame's own measured pose, roll-pitch-yaw
    /// differences), pushed as the perfect policy does: it misses by the arm's lag, and this shows the
    /// invariant test above would catch it.
    #[test]
    fn the_old_per_frame_delta_misses() {
        use crate::pose::{rpy_from_rotation, wrap_angle_rad};
        let fps = 20.0;
        let targets: Vec<Isometry3<f64>> = (0..32)
            .map(|i| Isometry3::translation(0.2 + 0.05 * f64::from(i) / fps, 0.0, 0.2))
            .collect();
        let measured = lagging(&targets, 0.6);
        let old = |t: usize| -> Vec<f64> {
            let (a, m) = (&targets[t], &measured[t]);
            let (ra, rm) = (rpy_from_rotation(&a.rotation), rpy_from_rotation(&m.rotation));
            let d = a.translation.vector - m.translation.vector;
            vec![
                d.x,
                d.y,
                d.z,
                wrap_angle_rad(ra[0] - rm[0]),
                wrap_angle_rad(ra[1] - rm[1]),
                wrap_angle_rad(ra[2] - rm[2]),
                1.0,
            ]
        };
        let (t0, k) = (8, 12);
        let step = old(t0 + k);
        let (got, _) = target_from_step(&measured[t0], &step, ActionMode::Relative).unwrap();
        let (dp, _) = pose_distance(&got, &targets[t0 + k]);
        assert!(dp > 0.02, "the old convention misses by {dp} m");
    }
}
