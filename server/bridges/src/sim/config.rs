//! Configuration of the simulated SO-101 arm and its pick-and-place scene (`[arms.sim]` in the server
//! config). Every field has a default, so an empty table is a working scene.

use crate::BridgeError;
use phone2act_core::kinematics::{SO101_JOINT_LIMITS_RAD, So101Joints};
use serde::{Deserialize, Serialize};

/// Simulated arm and scene parameters.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Time constant of the first-order joint response to a new target. 0.05 s is close to a Feetech
    /// STS3215 under lerobot's default P gain for small moves.
    pub joint_time_constant_s: f64,
    /// Time constant of the gripper.
    pub gripper_time_constant_s: f64,
    /// Physics and feedback rate of the simulation thread.
    pub step_hz: f64,
    /// Joint angles at start and after a scene reset (shoulder_pan .. wrist_roll).
    pub initial_joints_rad: So101Joints,
    /// Gripper at start: 0 = open, 1 = closed.
    pub initial_gripper: f64,
    /// Orientation weight of the IK (0 = position only, 1 = as much orientation as a 5-DoF arm allows).
    pub ik_orientation_weight: f64,
    /// Ball centre on the table at start, (x, y) in the robot base frame.
    pub ball_xy_m: [f64; 2],
    pub ball_radius_m: f64,
    /// Basket centre on the table, (x, y) in the robot base frame.
    pub basket_xy_m: [f64; 2],
    /// Inner radius of the (cylindrical) basket.
    pub basket_radius_m: f64,
    pub basket_height_m: f64,
    /// The gripper closes on the ball when the tool centre point is within this distance of its centre.
    pub grasp_radius_m: f64,
    /// Camera of [`crate::sim::SimBridge::render_rgb`].
    pub camera: SimCameraConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            joint_time_constant_s: 0.05,
            gripper_time_constant_s: 0.08,
            step_hz: 200.0,
            // Tool about 0.2 m in front of the base and 0.15 m above the table, pointing down and forward.
            initial_joints_rad: [0.0, -0.8, 0.6, 1.1, 0.0],
            initial_gripper: 0.0,
            ik_orientation_weight: 1.0,
            ball_xy_m: [0.25, -0.10],
            ball_radius_m: 0.02,
            basket_xy_m: [0.22, 0.13],
            basket_radius_m: 0.06,
            basket_height_m: 0.05,
            grasp_radius_m: 0.03,
            camera: SimCameraConfig::default(),
        }
    }
}

/// A fixed pinhole camera looking at the scene.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimCameraConfig {
    /// Camera position in the robot base frame.
    pub eye_m: [f64; 3],
    /// Point the camera looks at.
    pub look_at_m: [f64; 3],
    /// Vertical field of view.
    pub vertical_fov_deg: f64,
}

impl Default for SimCameraConfig {
    fn default() -> Self {
        Self {
            eye_m: [0.6, -0.34, 0.36],
            look_at_m: [0.2, 0.02, 0.07],
            vertical_fov_deg: 48.0,
        }
    }
}

fn positive(name: &str, value: f64) -> Result<(), BridgeError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(BridgeError::Config(format!(
            "sim.{name} must be a positive number, got {value}"
        )))
    }
}

fn finite(name: &str, values: &[f64]) -> Result<(), BridgeError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(BridgeError::Config(format!(
            "sim.{name} must be finite, got {values:?}"
        )))
    }
}

impl SimConfig {
    /// Checks ranges that serde cannot: positive time constants and sizes, joints inside their limits, a
    /// ball that does not start inside the basket wall.
    pub fn validate(&self) -> Result<(), BridgeError> {
        positive("joint_time_constant_s", self.joint_time_constant_s)?;
        positive("gripper_time_constant_s", self.gripper_time_constant_s)?;
        positive("step_hz", self.step_hz)?;
        positive("ball_radius_m", self.ball_radius_m)?;
        positive("basket_radius_m", self.basket_radius_m)?;
        positive("basket_height_m", self.basket_height_m)?;
        positive("grasp_radius_m", self.grasp_radius_m)?;
        positive("camera.vertical_fov_deg", self.camera.vertical_fov_deg)?;
        if self.camera.vertical_fov_deg >= 170.0 {
            return Err(BridgeError::Config(
                "sim.camera.vertical_fov_deg must be below 170".into(),
            ));
        }
        finite("initial_joints_rad", &self.initial_joints_rad)?;
        finite("ball_xy_m", &self.ball_xy_m)?;
        finite("basket_xy_m", &self.basket_xy_m)?;
        finite("camera.eye_m", &self.camera.eye_m)?;
        finite("camera.look_at_m", &self.camera.look_at_m)?;
        for (i, (q, (lo, hi))) in self
            .initial_joints_rad
            .iter()
            .zip(SO101_JOINT_LIMITS_RAD)
            .enumerate()
        {
            if !(lo..=hi).contains(q) {
                return Err(BridgeError::Config(format!(
                    "sim.initial_joints_rad[{i}] = {q} is outside the joint limits {lo}..{hi}"
                )));
            }
        }
        if !(0.0..=1.0).contains(&self.initial_gripper) {
            return Err(BridgeError::Config(format!(
                "sim.initial_gripper must be in 0..1, got {}",
                self.initial_gripper
            )));
        }
        if !(0.0..=1.0).contains(&self.ik_orientation_weight) {
            return Err(BridgeError::Config(format!(
                "sim.ik_orientation_weight must be in 0..1, got {}",
                self.ik_orientation_weight
            )));
        }
        if self.basket_radius_m <= self.ball_radius_m {
            return Err(BridgeError::Config(
                "sim.basket_radius_m must be larger than sim.ball_radius_m".into(),
            ));
        }
        let eye = nalgebra::Vector3::from(self.camera.eye_m);
        if (eye - nalgebra::Vector3::from(self.camera.look_at_m)).norm() < 1e-3 {
            return Err(BridgeError::Config(
                "sim.camera.eye_m and look_at_m must differ".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_table_is_the_default_and_valid() {
        let config: SimConfig = toml::from_str("").unwrap();
        assert_eq!(config, SimConfig::default());
        config.validate().unwrap();
    }

    #[test]
    fn unknown_keys_and_bad_values_are_rejected() {
        assert!(toml::from_str::<SimConfig>("joint_time_constant = 0.1").is_err());
        assert!(toml::from_str::<SimConfig>("[camera]\nfov = 3").is_err());
        let config: SimConfig =
            toml::from_str("joint_time_constant_s = 0.2\nball_xy_m = [0.3, 0.0]").unwrap();
        assert!((config.joint_time_constant_s - 0.2).abs() < 1e-12);
        config.validate().unwrap();
        let bad: SimConfig = toml::from_str("initial_joints_rad = [0.0, 0.0, 3.0, 0.0, 0.0]").unwrap();
        assert!(matches!(bad.validate(), Err(BridgeError::Config(m)) if m.contains("initial_joints_rad[2]")));
        let bad: SimConfig = toml::from_str("joint_time_constant_s = 0.0").unwrap();
        assert!(bad.validate().is_err());
    }
}
