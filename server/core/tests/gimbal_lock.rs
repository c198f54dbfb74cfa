//! The whole teleop pipeline near ±90° pitch: planner, gate, state vector and action round trip.
//!
//! Roll-pitch-yaw is singular there, which is exactly where per-axis Euler planners flip the gripper. Ours
//! composes quaternions and only converts at the edges, so targets stay smooth and the recorded action still
//! reproduces the executed target.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_core::pose::{angle_between_rad, pose_distance, rotation_from_rpy};
use phone2act_core::{ActionMode, ArmLayout, ClutchKind, TeleopArm, TeleopConfig};
use proptest::prelude::*;
use std::f64::consts::FRAC_PI_2;

fn near_vertical() -> impl Strategy<Value = UnitQuaternion<f64>> {
    (-3.2..3.2f64, prop::bool::ANY, -1e-4..1e-4f64, -3.2..3.2f64).prop_map(|(roll, up, dp, yaw)| {
        let pitch = if up { FRAC_PI_2 } else { -FRAC_PI_2 } + dp;
        rotation_from_rpy([roll, pitch, yaw])
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn nothing_blows_up_near_ninety_degrees_pitch(
        robot_rotation in near_vertical(),
        phone_rotation in near_vertical(),
        wobble in prop::collection::vec(prop::array::uniform3(-0.02..0.02f64), 1..40),
    ) {
        let start = Isometry3::from_parts(Translation3::new(0.25, 0.0, 0.18), robot_rotation);
        let mut arm = TeleopArm::new(&TeleopConfig::default(), start).unwrap();
        let layout = ArmLayout::new(vec!["a".into(), "b".into()]);
        let mut phone = Isometry3::from_parts(Translation3::new(0.0, 1.3, 0.0), phone_rotation);
        let step = arm.clutch(ClutchKind::Engage, Some(phone), start, 0.0);
        prop_assert_eq!(step.command.unwrap().0, start);

        let mut measured = start;
        for (i, w) in wobble.iter().enumerate() {
            // Small wobbles about all three axes keep crossing the singular pitch.
            phone.rotation = UnitQuaternion::from_scaled_axis(Vector3::from(*w)) * phone.rotation;
            let step = arm.on_pose(phone, true, measured, (i + 1) as f64 * 0.02);
            let (target, gripper) = step.command.expect("small wobbles pass the gate");
            prop_assert!(target.translation.vector.iter().chain(target.rotation.coords.iter()).all(|v| v.is_finite()));
            // Small phone rotations give equally small target rotations: no flips.
            let (_, turned) = pose_distance(&target, &measured);
            prop_assert!(turned <= Vector3::from(*w).norm() + 1e-9, "target turned {} rad for a {} rad wobble", turned, Vector3::from(*w).norm());

            let state = layout.state_vector(&[0.1, 0.2], &target, gripper).unwrap();
            prop_assert!(state.iter().all(|v| v.is_finite()));
            for mode in [ActionMode::Relative, ActionMode::Absolute] {
                let action = phone2act_core::step_from_target(&measured, &target, gripper, mode);
                prop_assert!(action.iter().all(|v| v.is_finite()));
                let (back, _) = phone2act_core::target_from_step(&measured, &action, mode).unwrap();
                prop_assert!(angle_between_rad(&back.rotation, &target.rotation) < 1e-9);
                prop_assert!((back.translation.vector - target.translation.vector).norm() < 1e-9);
            }
            measured = target;
        }
    }
}
