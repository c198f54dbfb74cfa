//! Configuration of the simulated SO-101 arm and its pick-and-place scene (`[arms.sim]` in the server
//! config). Every field has a default, so an empty table is a working scene.

use crate::BridgeError;
pub use crate::scene::TableArea;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_core::kinematics::{IkWeights, SO101_JOINT_LIMITS_RAD, So101Joints, So101Kinematics};
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
    /// Ball centre on the table at start, (x, y) in the robot base frame, until the first scene reset.
    pub ball_xy_m: [f64; 2],
    /// Where a scene reset draws the ball's start from. Every point must be reachable with the tool pointing
    /// down at the ball (checked at load).
    pub ball_area_m: TableArea,
    /// Where a scene reset draws the basket's centre from; unset keeps the basket at `basket_xy_m`.
    pub basket_area_m: Option<TableArea>,
    /// First seed of the arm's scene sequence: a reset without a seed uses the one after the last used.
    pub seed: u64,
    pub ball_radius_m: f64,
    /// Basket centre on the table, (x, y) in the robot base frame.
    pub basket_xy_m: [f64; 2],
    /// Inner radius of the (cylindrical) basket.
    pub basket_radius_m: f64,
    pub basket_height_m: f64,
    /// A closing gripper takes the ball only if its centre is between the fingers and within this distance of
    /// the tool centre point.
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
            // In front of the arm on the side away from the basket, 0.16-0.30 m from the base: inside the
            // SO-101's reach with the tool pointing straight down (which ends about 0.3 m out), and in
            // the default camera's view.
            ball_area_m: TableArea {
                x_min_m: 0.16,
                x_max_m: 0.26,
                y_min_m: -0.14,
                y_max_m: -0.04,
            },
            basket_area_m: None,
            seed: 0,
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

/// Checks a configured table area: finite, minimum not above maximum.
fn validate_area(area: &TableArea, name: &str) -> Result<(), BridgeError> {
    finite(name, &[area.x_min_m, area.x_max_m, area.y_min_m, area.y_max_m])?;
    if area.x_min_m > area.x_max_m || area.y_min_m > area.y_max_m {
        return Err(BridgeError::Config(format!(
            "sim.{name}: x_min_m/y_min_m must not exceed x_max_m/y_max_m, got {area:?}"
        )));
    }
    Ok(())
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
        if self.ball_radius_m >= super::world::OPEN_HALF_GAP_M {
            return Err(BridgeError::Config(format!(
                "sim.ball_radius_m must be below {} m: a larger ball does not fit between the open fingers",
                super::world::OPEN_HALF_GAP_M
            )));
        }
        self.validate_areas()?;
        let eye = nalgebra::Vector3::from(self.camera.eye_m);
        if (eye - nalgebra::Vector3::from(self.camera.look_at_m)).norm() < 1e-3 {
            return Err(BridgeError::Config(
                "sim.camera.eye_m and look_at_m must differ".into(),
            ));
        }
        Ok(())
    }
}

impl SimConfig {
    /// The areas are well formed, every corner of the ball's area can be reached with a grasp pose, and no
    /// ball drawn from it can start inside (or against the wall of) any basket the basket's area allows.
    fn validate_areas(&self) -> Result<(), BridgeError> {
        validate_area(&self.ball_area_m, "ball_area_m")?;
        if let Some(area) = &self.basket_area_m {
            validate_area(area, "basket_area_m")?;
        }
        let kinematics = So101Kinematics::new();
        for corner in self.ball_area_m.corners() {
            let solution = kinematics.inverse(
                &grasp_pose_at(corner, self.ball_radius_m),
                &self.initial_joints_rad,
                IkWeights::FULL,
            );
            if !solution.position_reached {
                return Err(BridgeError::Config(format!(
                    "sim.ball_area_m corner ({:.3}, {:.3}) is out of the arm's reach with the tool pointing down \
                     (closest {:.3} m away)",
                    corner[0], corner[1], solution.position_error_m
                )));
            }
        }
        // Closest a basket centre can come to the ball area, against the clearance a ball needs to start
        // outside the basket wall.
        let clearance_m = self.basket_radius_m + self.ball_radius_m;
        let closest_m = match &self.basket_area_m {
            None => self.ball_area_m.distance_to(self.basket_xy_m),
            Some(area) => {
                let dx = (area.x_min_m - self.ball_area_m.x_max_m)
                    .max(self.ball_area_m.x_min_m - area.x_max_m)
                    .max(0.0);
                let dy = (area.y_min_m - self.ball_area_m.y_max_m)
                    .max(self.ball_area_m.y_min_m - area.y_max_m)
                    .max(0.0);
                dx.hypot(dy)
            }
        };
        if closest_m < clearance_m {
            return Err(BridgeError::Config(format!(
                "sim.ball_area_m comes within {closest_m:.3} m of a basket centre; it must stay {clearance_m:.3} m \
                 (basket radius + ball radius) away so that no ball starts in or on the basket"
            )));
        }
        Ok(())
    }
}

/// The tool pointing straight down with its centre at the height of a resting ball's centre over (x, y),
/// turned to face away from the base: how a grasp from above is held.
pub fn grasp_pose_at([x, y]: [f64; 2], ball_radius_m: f64) -> Isometry3<f64> {
    let zero = So101Kinematics::new().forward(&[0.0; 5]).rotation;
    let down = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2) * zero;
    let facing = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), y.atan2(x));
    Isometry3::from_parts(Translation3::new(x, y, ball_radius_m), facing * down)
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

    #[test]
    fn every_corner_of_the_default_ball_area_is_reachable_with_a_grasp_pose() {
        let config = SimConfig::default();
        let kinematics = So101Kinematics::new();
        // The corners and the middle: a grasp from above, reached to the solver's tolerance, and the tool
        // really pointing down (the approach axis within 0.05 rad of vertical).
        let area = config.ball_area_m;
        for xy in area.corners().into_iter().chain([area.point_at(0.5, 0.5)]) {
            let target = grasp_pose_at(xy, config.ball_radius_m);
            let solution = kinematics.inverse(&target, &config.initial_joints_rad, IkWeights::FULL);
            assert!(solution.position_reached, "{xy:?}: {solution:?}");
            assert!(solution.orientation_error_rad < 0.05, "{xy:?}: {solution:?}");
        }
    }

    #[test]
    fn areas_out_of_reach_or_over_the_basket_are_refused_with_the_reason() {
        let far: SimConfig =
            toml::from_str("[ball_area_m]\nx_min_m = 0.2\nx_max_m = 0.7\ny_min_m = -0.1\ny_max_m = 0.0")
                .unwrap();
        assert!(
            matches!(far.validate(), Err(BridgeError::Config(m)) if m.contains("out of the arm's reach")),
            "{:?}",
            far.validate()
        );
        let over: SimConfig =
            toml::from_str("[ball_area_m]\nx_min_m = 0.18\nx_max_m = 0.26\ny_min_m = 0.0\ny_max_m = 0.1")
                .unwrap();
        assert!(
            matches!(over.validate(), Err(BridgeError::Config(m)) if m.contains("basket")),
            "{:?}",
            over.validate()
        );
        let moving_basket: SimConfig =
            toml::from_str("[basket_area_m]\nx_min_m = 0.2\nx_max_m = 0.25\ny_min_m = -0.12\ny_max_m = 0.15")
                .unwrap();
        assert!(moving_basket.validate().is_err());
        let inverted: SimConfig =
            toml::from_str("[ball_area_m]\nx_min_m = 0.3\nx_max_m = 0.2\ny_min_m = -0.1\ny_max_m = 0.0")
                .unwrap();
        assert!(matches!(inverted.validate(), Err(BridgeError::Config(m)) if m.contains("must not exceed")));
        let ok: SimConfig = toml::from_str(
            "seed = 7\n[basket_area_m]\nx_min_m = 0.2\nx_max_m = 0.26\ny_min_m = 0.1\ny_max_m = 0.16",
        )
        .unwrap();
        ok.validate().unwrap();
    }
}
