//! The teleop planner: phone pose in, robot target out, relative to a floating reference.
//!
//! With `P` the phone pose in its tracking frame, `R` the robot reference pose and `M = robot_from_tracking`:
//!
//! - position: `p_target = p_R + M·((p_P − p_Pref)·S)`;
//! - orientation: the phone's rotation since the reference, `D = q_Pref⁻¹·q_P`, is a rotation about an axis
//!   of the phone's reference body frame. `q_Pref` carries that axis into the tracking frame and `M` into the
//!   robot frame, so the same physical rotation seen from the robot is `E = (M·q_Pref)·D·(M·q_Pref)⁻¹`. It is
//!   scaled as an axis-angle (`E^s`) and applied on the world side of the robot reference: `q_target = E^s·q_R`.
//!
//! Tilting the phone forward therefore pitches the gripper forward about the robot's own y axis whatever
//! the gripper's current orientation, and combined or large rotations compose exactly. No Euler angle is
//! involved anywhere here.

use crate::config::{ConfigError, MappingConfig};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// Mapping resolved from a [`MappingConfig`] into the numbers used per sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Mapping {
    pub robot_from_tracking: UnitQuaternion<f64>,
    pub position_scale: f64,
    pub rotation_scale: f64,
    pub position_only: bool,
}

impl Mapping {
    pub fn from_config(config: &MappingConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Self {
            robot_from_tracking: UnitQuaternion::from_rotation_matrix(&config.robot_from_tracking()?),
            position_scale: config.position_scale,
            rotation_scale: config.rotation_scale,
            position_only: config.position_only,
        })
    }
}

/// The floating zero: the phone and robot poses that currently correspond to each other.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    pub tracking_from_phone: Isometry3<f64>,
    pub robot_from_ee: Isometry3<f64>,
}

/// Maps phone poses to robot targets relative to a [`Reference`].
#[derive(Debug, Clone)]
pub struct Planner {
    mapping: Mapping,
    reference: Option<Reference>,
}

impl Planner {
    pub fn new(mapping: Mapping) -> Self {
        Self {
            mapping,
            reference: None,
        }
    }

    pub fn mapping(&self) -> &Mapping {
        &self.mapping
    }

    pub fn reference(&self) -> Option<&Reference> {
        self.reference.as_ref()
    }

    /// Makes `tracking_from_phone` correspond to `robot_from_ee`: the next target for this same phone pose is
    /// exactly `robot_from_ee`.
    pub fn reindex(&mut self, tracking_from_phone: Isometry3<f64>, robot_from_ee: Isometry3<f64>) {
        self.reference = Some(Reference {
            tracking_from_phone,
            robot_from_ee,
        });
    }

    /// Forgets the reference; [`Planner::target`] returns `None` until the next [`Planner::reindex`].
    pub fn clear(&mut self) {
        self.reference = None;
    }

    /// The robot target for a phone pose, or `None` without a reference.
    pub fn target(&self, tracking_from_phone: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        let reference = self.reference.as_ref()?;
        Some(map_pose(&self.mapping, reference, tracking_from_phone))
    }
}

/// The planner equation for one sample (see the module documentation).
pub fn map_pose(
    mapping: &Mapping,
    reference: &Reference,
    tracking_from_phone: &Isometry3<f64>,
) -> Isometry3<f64> {
    let m = &mapping.robot_from_tracking;
    let delta_tracking =
        tracking_from_phone.translation.vector - reference.tracking_from_phone.translation.vector;
    let position = reference.robot_from_ee.translation.vector + m * (delta_tracking * mapping.position_scale);

    let rotation = if mapping.position_only {
        reference.robot_from_ee.rotation
    } else {
        // (M·q_Pref)·(q_Pref⁻¹·q_P)·(M·q_Pref)⁻¹ simplifies to M·(q_P·q_Pref⁻¹)·M⁻¹: one product fewer.
        let world_delta = tracking_from_phone.rotation * reference.tracking_from_phone.rotation.inverse();
        let robot_delta = m * world_delta * m.inverse();
        let scaled = if (mapping.rotation_scale - 1.0).abs() <= f64::EPSILON {
            robot_delta
        } else {
            // powf takes the shortest arc, so a scale of 0.5 halves the physical rotation rather than
            // following the other side of the quaternion double cover.
            robot_delta.powf(mapping.rotation_scale)
        };
        scaled * reference.robot_from_ee.rotation
    };
    Isometry3::from_parts(Translation3::from(position), rotation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::AxisPreset;
    use crate::pose::{angle_between_rad, pose_distance};
    use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
    use proptest::prelude::*;

    fn mapping(preset: AxisPreset, position_scale: f64, rotation_scale: f64) -> Mapping {
        Mapping::from_config(&MappingConfig {
            preset,
            position_scale,
            rotation_scale,
            ..MappingConfig::default()
        })
        .unwrap()
    }

    fn pose(xyz: [f64; 3], rotation: UnitQuaternion<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(xyz[0], xyz[1], xyz[2]), rotation)
    }

    #[test]
    fn landscape_moves_follow_the_operator() {
        let mut planner = Planner::new(mapping(AxisPreset::Landscape, 2.0, 1.0));
        let phone0 = pose([0.1, 1.2, -0.3], UnitQuaternion::identity());
        let robot0 = pose(
            [0.25, 0.0, 0.15],
            UnitQuaternion::from_euler_angles(0.0, 0.5, 0.0),
        );
        assert!(planner.target(&phone0).is_none());
        planner.reindex(phone0, robot0);
        assert!(pose_distance(&planner.target(&phone0).unwrap(), &robot0).0 < 1e-15);
        // Phone 5 cm forward (−Z) and 1 cm up → robot 10 cm along +x and 2 cm up (scale 2).
        let moved = pose([0.1, 1.21, -0.35], UnitQuaternion::identity());
        let t = planner.target(&moved).unwrap();
        assert!((t.translation.vector - Vector3::new(0.35, 0.0, 0.17)).norm() < 1e-12);
        // Turning the phone left about its up axis (+Y tracking) yaws the robot left about +z.
        let turned = pose(
            [0.1, 1.2, -0.3],
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.4),
        );
        let t = planner.target(&turned).unwrap();
        let expected = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4) * robot0.rotation;
        assert!(angle_between_rad(&t.rotation, &expected) < 1e-12);
    }

    #[test]
    fn position_only_keeps_the_reference_orientation() {
        let cfg = MappingConfig {
            position_only: true,
            ..MappingConfig::default()
        };
        let mut planner = Planner::new(Mapping::from_config(&cfg).unwrap());
        let robot0 = pose([0.2, 0.0, 0.1], UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3));
        planner.reindex(Isometry3::identity(), robot0);
        let t = planner
            .target(&pose(
                [0.0, 0.01, 0.0],
                UnitQuaternion::from_euler_angles(1.0, -1.0, 2.0),
            ))
            .unwrap();
        assert_eq!(t.rotation, robot0.rotation);
        assert!((t.translation.vector - Vector3::new(0.2, 0.0, 0.11)).norm() < 1e-15);
    }

    fn any_rotation() -> impl Strategy<Value = UnitQuaternion<f64>> {
        (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
            .prop_filter("non-zero", |(a, b, c, d)| a * a + b * b + c * c + d * d > 1e-3)
            .prop_map(|(w, x, y, z)| UnitQuaternion::new_normalize(nalgebra::Quaternion::new(w, x, y, z)))
    }

    fn any_preset() -> impl Strategy<Value = AxisPreset> {
        prop_oneof![
            Just(AxisPreset::Landscape),
            Just(AxisPreset::Portrait),
            Just(AxisPreset::Identity)
        ]
    }

    proptest! {
        /// Cross-checks the quaternion pipeline against rotation matrices and an axis-angle construction:
        /// the physical axis of the phone's rotation, carried into the robot frame by M, scaled in angle.
        #[test]
        fn composition_agrees_with_matrix_axis_angle_math(
            preset in any_preset(),
            phone_ref in any_rotation(),
            phone_now in any_rotation(),
            robot_ref in any_rotation(),
            scale in 0.2..1.5f64,
        ) {
            let planner_mapping = mapping(preset, 1.0, scale);
            let reference = Reference { tracking_from_phone: pose([0.0; 3], phone_ref), robot_from_ee: pose([0.2, 0.0, 0.2], robot_ref) };
            let target = map_pose(&planner_mapping, &reference, &pose([0.0; 3], phone_now));

            let rows = preset.matrix();
            let m = Matrix3::from_fn(|r, c| rows[r][c]);
            // World-frame rotation of the phone in matrices.
            let world = phone_now.to_rotation_matrix().matrix() * phone_ref.to_rotation_matrix().matrix().transpose();
            let world = Rotation3::from_matrix_unchecked(world);
            let expected = match world.axis_angle() {
                Some((axis, angle)) => {
                    let robot_axis = Unit::new_normalize(m * axis.into_inner());
                    Rotation3::from_axis_angle(&robot_axis, angle * scale) * robot_ref.to_rotation_matrix()
                }
                None => robot_ref.to_rotation_matrix(),
            };
            let expected = UnitQuaternion::from_rotation_matrix(&expected);
            // Axis extraction near 180° is the least precise step of the reference computation.
            prop_assert!(angle_between_rad(&target.rotation, &expected) < 1e-7,
                "error {} rad", angle_between_rad(&target.rotation, &expected));
        }

        /// Moving the phone and coming back returns the robot to the same target (no drift from composition).
        #[test]
        fn returning_the_phone_returns_the_target(
            phone_ref in any_rotation(), detour in any_rotation(), robot_ref in any_rotation(),
            dx in -0.2..0.2f64, dy in -0.2..0.2f64, dz in -0.2..0.2f64,
        ) {
            let mut planner = Planner::new(mapping(AxisPreset::Landscape, 1.3, 0.7));
            let phone0 = pose([0.0, 1.0, 0.0], phone_ref);
            let robot0 = pose([0.25, 0.0, 0.2], robot_ref);
            planner.reindex(phone0, robot0);
            let away = planner.target(&pose([dx, 1.0 + dy, dz], detour * phone_ref)).unwrap();
            prop_assert!(away.translation.vector.iter().all(|v| v.is_finite()));
            let back = planner.target(&phone0).unwrap();
            let (dp, da) = pose_distance(&back, &robot0);
            prop_assert!(dp < 1e-12 && da < 1e-12);
        }
    }
}
