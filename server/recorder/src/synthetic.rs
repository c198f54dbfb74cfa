//! A synthetic robot source for demos, tests and benchmarks: smooth, distinct signals per element, stamped
//! with the current monotonic time, in the core's layout (joints, end-effector pose, gripper).

use crate::recorder::{RobotSample, RobotSource};
use phone2act_clock::monotonic_ns;

/// Six joints, end-effector pose and gripper; the action is the pose delta plus gripper.
#[derive(Debug, Default)]
pub struct SyntheticRobot;

impl SyntheticRobot {
    /// State element names (an SO-100/CR5-like single arm).
    pub fn state_names() -> Vec<String> {
        [
            "j0", "j1", "j2", "j3", "j4", "j5", "ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw",
            "gripper",
        ]
        .iter()
        .map(|s| (*s).to_owned())
        .collect()
    }

    /// Action element names.
    pub fn action_names() -> Vec<String> {
        [
            "delta_x",
            "delta_y",
            "delta_z",
            "delta_roll",
            "delta_pitch",
            "delta_yaw",
            "gripper",
        ]
        .iter()
        .map(|s| (*s).to_owned())
        .collect()
    }

    /// GR00T modality groups for this layout: the pose delta is relative, the gripper target absolute.
    pub fn modality() -> Vec<phone2act_dataset::spec::ModalityGroup> {
        vec![
            phone2act_dataset::spec::ModalityGroup {
                name: "main_arm".into(),
                state_range: 0..12,
                action_range: 0..6,
                action_absolute: false,
            },
            phone2act_dataset::spec::ModalityGroup {
                name: "main_gripper".into(),
                state_range: 12..13,
                action_range: 6..7,
                action_absolute: true,
            },
        ]
    }
}

impl RobotSource for SyntheticRobot {
    fn sample(&self) -> Option<RobotSample> {
        let now = monotonic_ns();
        let t = now as f64 / 1e9;
        let state = (0..13)
            .map(|i| (t * (0.3 + 0.1 * f64::from(i))).sin() + f64::from(i))
            .collect();
        let action = (0..7)
            .map(|i| 0.01 * (t * (0.5 + 0.1 * f64::from(i))).cos())
            .collect();
        Some(RobotSample {
            state,
            action,
            success: false,
            capture_time_ns: now,
            arms: Vec::new(),
        })
    }
}
