//! Joint models a remote bridge declares when it attaches: a model the server knows by name (`so101`, `cr5`)
//! or an explicit chain of revolute joints in URDF terms with each joint's speed limit. With one, the server
//! solves the bridge's targets and limits their joint steps itself ([`crate::joint_motion`]), exactly as for its
//! own SO-101 and CR5 bridges; without one the bridge solves its own joints and the server can only watch their
//! speeds ([`crate::joint_limit::JointSpeedWatch`]).
//!
//! Everything a declaration holds is checked here, so a malformed one is refused at attach with the reason
//! instead of driving a robot with a model that means nothing.

use crate::joint_motion::{
    ArmJointStage, CR5_MAX_VELOCITY_RAD_S, JointLimitConfig, JointStage, STS3215_MAX_VELOCITY_RAD_S,
    So101JointStage,
};
use crate::kinematics::{CR5_DOF, ChainKinematics, SO101_ARM_DOF, UrdfJoint};

/// Fewest and most joints of a declared chain (a position needs three; the longest common arms have seven).
pub const DECLARED_JOINTS: std::ops::RangeInclusive<usize> = 3..=7;

/// One joint of a declared chain.
#[derive(Debug, Clone, PartialEq)]
pub struct DeclaredJoint {
    pub name: String,
    /// Origin on the parent link (URDF `<origin xyz rpy>`), metres and radians.
    pub origin_xyz_m: [f64; 3],
    pub origin_rpy_rad: [f64; 3],
    /// Axis of rotation in the joint's frame (URDF `<axis>`), any non-zero length.
    pub axis: [f64; 3],
    pub lower_rad: f64,
    pub upper_rad: f64,
    /// Largest speed, rad/s.
    pub max_velocity_rad_s: f64,
    /// Largest acceleration, rad/s² (`None`: not limited).
    pub max_acceleration_rad_s2: Option<f64>,
}

/// A joint model declared by a remote bridge.
#[derive(Debug, Clone, PartialEq)]
pub enum DeclaredModel {
    /// A model the server knows: `so101` (five arm joints) or `cr5` (six).
    Known(String),
    /// An explicit chain, base to last link, and the tool's origin on the last link.
    Chain {
        joints: Vec<DeclaredJoint>,
        tool_xyz_m: [f64; 3],
        tool_rpy_rad: [f64; 3],
    },
}

/// Why a declared model was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    #[error("unknown joint model {0:?} (known: \"so101\", \"cr5\"; or declare the chain)")]
    UnknownModel(String),
    #[error("joint model {model} has {expected} joints, the bridge names {got}")]
    JointCount {
        model: String,
        expected: usize,
        got: usize,
    },
    #[error("a declared chain needs {min} to {max} joints, got {got}", min = DECLARED_JOINTS.start(), max = DECLARED_JOINTS.end())]
    ChainLength { got: usize },
    #[error("declared joint {index} is named {declared:?}, the bridge's joint {index} is {bridge:?}")]
    JointName {
        index: usize,
        declared: String,
        bridge: String,
    },
    #[error("joint {joint:?}: {field} must be finite")]
    NotFinite { joint: String, field: &'static str },
    #[error("joint {joint:?}: the axis is zero")]
    ZeroAxis { joint: String },
    #[error("joint {joint:?}: lower limit {lower_rad} rad is above the upper limit {upper_rad} rad")]
    InvertedLimits {
        joint: String,
        lower_rad: f64,
        upper_rad: f64,
    },
    #[error("joint {joint:?}: {field} must be finite and > 0, got {value}")]
    NotPositive {
        joint: String,
        field: &'static str,
        value: f64,
    },
    #[error("the tool origin must be finite")]
    ToolNotFinite,
    #[error("the arm's joint_limits: {0}")]
    Configured(#[from] crate::config::ConfigError),
}

/// The joint stage for a bridge that declared `model` for its joints `joint_names` (the names it attached
/// with). `configured` is the arm's `[arms.<name>.joint_limits]`: when it sets speeds, they lower the model's
/// (a configured speed never raises a declared one). `orientation_weight` is 1 for a bridge that follows
/// orientation, 0 for a position-only one.
pub fn declared_stage(
    model: &DeclaredModel,
    joint_names: &[String],
    configured: &JointLimitConfig,
    orientation_weight: f64,
) -> Result<ArmJointStage, ModelError> {
    let lowered = |model_speeds: Vec<f64>| -> Result<Vec<f64>, ModelError> {
        if configured.max_velocity_rad_s.is_empty() {
            return Ok(model_speeds);
        }
        let configured = configured.resolve(model_speeds.len(), f64::INFINITY)?;
        Ok(model_speeds
            .iter()
            .zip(configured)
            .map(|(m, c)| m.min(c))
            .collect())
    };
    let count = |model: &str, expected: usize| {
        if joint_names.len() == expected {
            Ok(())
        } else {
            Err(ModelError::JointCount {
                model: model.to_owned(),
                expected,
                got: joint_names.len(),
            })
        }
    };
    let stage = match model {
        DeclaredModel::Known(name) if name == "so101" => {
            count(name, SO101_ARM_DOF)?;
            let speeds = lowered(vec![STS3215_MAX_VELOCITY_RAD_S; SO101_ARM_DOF])?;
            ArmJointStage::So101(So101JointStage::new(speeds, orientation_weight)?)
        }
        DeclaredModel::Known(name) if name == "cr5" => {
            count(name, CR5_DOF)?;
            let speeds = lowered(vec![CR5_MAX_VELOCITY_RAD_S; CR5_DOF])?;
            // Through `with_kinematics`, so a position-only bridge's weight applies to a CR5 too.
            ArmJointStage::Cr5(JointStage::with_kinematics(
                crate::kinematics::Cr5Kinematics::new(),
                speeds,
                orientation_weight,
            )?)
        }
        DeclaredModel::Known(name) => return Err(ModelError::UnknownModel(name.clone())),
        DeclaredModel::Chain {
            joints,
            tool_xyz_m,
            tool_rpy_rad,
        } => {
            check_chain(joints, joint_names)?;
            if !tool_xyz_m.iter().chain(tool_rpy_rad).all(|v| v.is_finite()) {
                return Err(ModelError::ToolNotFinite);
            }
            let urdf: Vec<UrdfJoint> = joints
                .iter()
                .map(|j| UrdfJoint {
                    origin_xyz_m: j.origin_xyz_m,
                    origin_rpy_rad: j.origin_rpy_rad,
                    axis: j.axis,
                    limits_rad: (j.lower_rad, j.upper_rad),
                })
                .collect();
            let speeds = lowered(joints.iter().map(|j| j.max_velocity_rad_s).collect())?;
            let chain = ChainStage {
                urdf: &urdf,
                tool: (*tool_xyz_m, *tool_rpy_rad),
                speeds,
                orientation_weight,
            };
            let stage = match urdf.len() {
                3 => ArmJointStage::Chain3(chain.build()?),
                4 => ArmJointStage::Chain4(chain.build()?),
                5 => ArmJointStage::Chain5(chain.build()?),
                6 => ArmJointStage::Chain6(chain.build()?),
                7 => ArmJointStage::Chain7(chain.build()?),
                got => return Err(ModelError::ChainLength { got }),
            };
            let declared: Vec<f64> = joints
                .iter()
                .map(|j| j.max_acceleration_rad_s2.unwrap_or(f64::INFINITY))
                .collect();
            return with_accelerations(stage, Some(declared), configured);
        }
    };
    with_accelerations(stage, None, configured)
}

/// `stage` with the declared accelerations (infinite where none), lowered by the configured ones; unchanged
/// when neither sets any.
fn with_accelerations(
    stage: ArmJointStage,
    declared: Option<Vec<f64>>,
    configured: &JointLimitConfig,
) -> Result<ArmJointStage, ModelError> {
    let joints = stage.joints();
    let configured = configured.resolve_acceleration(joints)?;
    let accelerations = match (declared, configured) {
        (None, None) => return Ok(stage),
        (Some(d), None) => d,
        (None, Some(c)) => c,
        (Some(d), Some(c)) => d.iter().zip(c).map(|(d, c)| d.min(c)).collect(),
    };
    if accelerations.iter().all(|a| a.is_infinite()) {
        return Ok(stage);
    }
    Ok(stage.with_max_acceleration_rad_s2(accelerations)?)
}

/// The parts of a declared chain's stage, for one joint count.
struct ChainStage<'a> {
    urdf: &'a [UrdfJoint],
    tool: ([f64; 3], [f64; 3]),
    speeds: Vec<f64>,
    orientation_weight: f64,
}

impl ChainStage<'_> {
    fn build<const N: usize>(self) -> Result<JointStage<N>, ModelError> {
        let joints: &[UrdfJoint; N] = self
            .urdf
            .try_into()
            .map_err(|_| ModelError::ChainLength { got: self.urdf.len() })?;
        let kinematics = ChainKinematics::from_urdf(joints, self.tool.0, self.tool.1);
        Ok(JointStage::with_kinematics(
            kinematics,
            self.speeds,
            self.orientation_weight,
        )?)
    }
}

/// Refuses a chain whose joints do not match the bridge's names or hold values that are not a joint.
fn check_chain(joints: &[DeclaredJoint], joint_names: &[String]) -> Result<(), ModelError> {
    if !DECLARED_JOINTS.contains(&joints.len()) {
        return Err(ModelError::ChainLength { got: joints.len() });
    }
    if joints.len() != joint_names.len() {
        return Err(ModelError::JointCount {
            model: "declared chain".to_owned(),
            expected: joints.len(),
            got: joint_names.len(),
        });
    }
    for (index, (j, bridge)) in joints.iter().zip(joint_names).enumerate() {
        if j.name != *bridge {
            return Err(ModelError::JointName {
                index,
                declared: j.name.clone(),
                bridge: bridge.clone(),
            });
        }
        let not_finite = |field| ModelError::NotFinite {
            joint: j.name.clone(),
            field,
        };
        if !j
            .origin_xyz_m
            .iter()
            .chain(&j.origin_rpy_rad)
            .all(|v| v.is_finite())
        {
            return Err(not_finite("origin"));
        }
        if !j.axis.iter().all(|v| v.is_finite()) {
            return Err(not_finite("axis"));
        }
        // Below this an axis's direction is rounding noise, not a direction.
        if j.axis.iter().map(|v| v * v).sum::<f64>().sqrt() < 1e-9 {
            return Err(ModelError::ZeroAxis {
                joint: j.name.clone(),
            });
        }
        if !(j.lower_rad.is_finite() && j.upper_rad.is_finite()) {
            return Err(not_finite("the position limits"));
        }
        if j.lower_rad > j.upper_rad {
            return Err(ModelError::InvertedLimits {
                joint: j.name.clone(),
                lower_rad: j.lower_rad,
                upper_rad: j.upper_rad,
            });
        }
        let positive = |field, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(ModelError::NotPositive {
                    joint: j.name.clone(),
                    field,
                    value,
                })
            }
        };
        positive("max_velocity_rad_s", j.max_velocity_rad_s)?;
        if let Some(a) = j.max_acceleration_rad_s2 {
            positive("max_acceleration_rad_s2", a)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{CR5_JOINT_NAMES, SO101_ARM_JOINT_NAMES};

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| (*s).to_owned()).collect()
    }

    fn joint(name: &str) -> DeclaredJoint {
        DeclaredJoint {
            name: name.to_owned(),
            origin_xyz_m: [0.0, 0.0, 0.1],
            origin_rpy_rad: [0.0, 0.0, 0.0],
            axis: [0.0, 1.0, 0.0],
            lower_rad: -2.0,
            upper_rad: 2.0,
            max_velocity_rad_s: 1.5,
            max_acceleration_rad_s2: None,
        }
    }

    fn chain(joints: Vec<DeclaredJoint>) -> DeclaredModel {
        DeclaredModel::Chain {
            joints,
            tool_xyz_m: [0.0, 0.0, 0.05],
            tool_rpy_rad: [0.0; 3],
        }
    }

    fn four() -> Vec<DeclaredJoint> {
        let mut j: Vec<_> = ["a", "b", "c", "d"].iter().map(|n| joint(n)).collect();
        j[0].axis = [0.0, 0.0, 1.0];
        j
    }

    #[test]
    fn known_models_get_their_robots_stage_and_speeds() {
        let none = JointLimitConfig::default();
        let so101 = declared_stage(
            &DeclaredModel::Known("so101".into()),
            &names(&SO101_ARM_JOINT_NAMES),
            &none,
            1.0,
        )
        .unwrap();
        assert!(matches!(so101, ArmJointStage::So101(_)));
        assert_eq!(so101.max_velocity_rad_s(), &[STS3215_MAX_VELOCITY_RAD_S; 5]);
        let cr5 = declared_stage(
            &DeclaredModel::Known("cr5".into()),
            &names(&CR5_JOINT_NAMES),
            &none,
            0.0,
        )
        .unwrap();
        assert!(matches!(cr5, ArmJointStage::Cr5(_)));
        assert_eq!(cr5.joints(), 6);
        // A configured speed lowers the model's, never raises it.
        let configured = JointLimitConfig {
            max_velocity_rad_s: vec![1.0, 9.0, 1.0, 9.0, 1.0, 9.0],
            ..JointLimitConfig::default()
        };
        let cr5 = declared_stage(
            &DeclaredModel::Known("cr5".into()),
            &names(&CR5_JOINT_NAMES),
            &configured,
            1.0,
        )
        .unwrap();
        let pi = CR5_MAX_VELOCITY_RAD_S;
        assert_eq!(cr5.max_velocity_rad_s(), &[1.0, pi, 1.0, pi, 1.0, pi]);
        let e =
            declared_stage(&DeclaredModel::Known("cr5".into()), &names(&["a"; 5]), &none, 1.0).unwrap_err();
        assert_eq!(
            e,
            ModelError::JointCount {
                model: "cr5".into(),
                expected: 6,
                got: 5
            }
        );
        let e =
            declared_stage(&DeclaredModel::Known("ur5".into()), &names(&["a"; 6]), &none, 1.0).unwrap_err();
        assert!(e.to_string().contains("unknown joint model \"ur5\""), "{e}");
    }

    #[test]
    fn a_declared_chain_gets_a_stage_of_its_length_and_speeds() {
        let none = JointLimitConfig::default();
        let mut joints = four();
        joints[2].max_velocity_rad_s = 0.5;
        let stage = declared_stage(&chain(joints), &names(&["a", "b", "c", "d"]), &none, 1.0).unwrap();
        assert!(matches!(stage, ArmJointStage::Chain4(_)));
        assert_eq!(stage.max_velocity_rad_s(), &[1.5, 1.5, 0.5, 1.5]);
        for n in [3, 5, 6, 7] {
            let joints: Vec<_> = (0..n).map(|i| joint(&format!("j{i}"))).collect();
            let bridge: Vec<String> = joints.iter().map(|j| j.name.clone()).collect();
            let stage = declared_stage(&chain(joints), &bridge, &none, 1.0).unwrap();
            assert_eq!(stage.joints(), n);
        }
    }

    /// Declared accelerations reach the stage, lowered by configured ones; none declared and none configured
    /// leaves the stage without acceleration limits.
    #[test]
    fn accelerations_are_declared_and_lowered_by_the_configuration() {
        let bridge = names(&["a", "b", "c", "d"]);
        let none = JointLimitConfig::default();
        let stage = declared_stage(&chain(four()), &bridge, &none, 1.0).unwrap();
        assert!(accelerations(&stage).is_none());
        let mut joints = four();
        joints[1].max_acceleration_rad_s2 = Some(3.0);
        let stage = declared_stage(&chain(joints.clone()), &bridge, &none, 1.0).unwrap();
        let inf = f64::INFINITY;
        assert_eq!(accelerations(&stage).unwrap(), vec![inf, 3.0, inf, inf]);
        let configured = JointLimitConfig {
            max_acceleration_rad_s2: vec![2.0, 9.0, 9.0, 9.0],
            ..JointLimitConfig::default()
        };
        let stage = declared_stage(&chain(joints), &bridge, &configured, 1.0).unwrap();
        assert_eq!(accelerations(&stage).unwrap(), vec![2.0, 3.0, 9.0, 9.0]);
        let configured = JointLimitConfig {
            max_acceleration_rad_s2: vec![5.0],
            ..JointLimitConfig::default()
        };
        let so101 = declared_stage(
            &DeclaredModel::Known("so101".into()),
            &names(&SO101_ARM_JOINT_NAMES),
            &configured,
            1.0,
        )
        .unwrap();
        assert_eq!(accelerations(&so101).unwrap(), vec![5.0; 5]);
        let bad = JointLimitConfig {
            max_acceleration_rad_s2: vec![1.0, 2.0],
            ..JointLimitConfig::default()
        };
        assert!(declared_stage(&chain(four()), &bridge, &bad, 1.0).is_err());
    }

    fn accelerations(stage: &ArmJointStage) -> Option<Vec<f64>> {
        stage.max_acceleration_rad_s2().map(<[f64]>::to_vec)
    }

    type Edit<'a> = &'a dyn Fn(&mut Vec<DeclaredJoint>);

    /// Every malformed declaration is refused, each with its own reason.
    #[test]
    fn a_malformed_chain_is_refused_with_the_reason() {
        let none = JointLimitConfig::default();
        let bridge = names(&["a", "b", "c", "d"]);
        let refuse = |edit: &dyn Fn(&mut Vec<DeclaredJoint>)| {
            let mut j = four();
            edit(&mut j);
            declared_stage(&chain(j), &bridge, &none, 1.0)
                .unwrap_err()
                .to_string()
        };
        let cases: [(Edit, &str); 14] = [
            (
                &|j| j[1].origin_xyz_m[0] = f64::NAN,
                "joint \"b\": origin must be finite",
            ),
            (
                &|j| j[1].origin_rpy_rad[2] = f64::INFINITY,
                "joint \"b\": origin must be finite",
            ),
            (&|j| j[2].axis = [0.0; 3], "joint \"c\": the axis is zero"),
            // Shorter than 1e-9 is no direction either.
            (
                &|j| j[2].axis = [5e-10, 0.0, 0.0],
                "joint \"c\": the axis is zero",
            ),
            (
                &|j| j[2].axis = [f64::NAN, 0.0, 1.0],
                "joint \"c\": axis must be finite",
            ),
            (
                &|j| j[3].lower_rad = 2.5,
                "joint \"d\": lower limit 2.5 rad is above the upper limit 2 rad",
            ),
            (&|j| j[3].upper_rad = f64::NAN, "position limits must be finite"),
            (
                &|j| j[0].max_velocity_rad_s = 0.0,
                "joint \"a\": max_velocity_rad_s must be finite and > 0, got 0",
            ),
            (
                &|j| j[0].max_velocity_rad_s = f64::NAN,
                "joint \"a\": max_velocity_rad_s must be finite and > 0, got NaN",
            ),
            (
                &|j| j[0].max_velocity_rad_s = f64::INFINITY,
                "joint \"a\": max_velocity_rad_s must be finite and > 0, got inf",
            ),
            (
                &|j| j[0].max_acceleration_rad_s2 = Some(-1.0),
                "joint \"a\": max_acceleration_rad_s2 must be finite and > 0",
            ),
            (
                &|j| j[0].max_acceleration_rad_s2 = Some(0.0),
                "joint \"a\": max_acceleration_rad_s2 must be finite and > 0, got 0",
            ),
            (
                &|j| j[1].name = "x".into(),
                "declared joint 1 is named \"x\", the bridge's joint 1 is \"b\"",
            ),
            (
                &|j| {
                    j.pop();
                },
                "has 3 joints, the bridge names 4",
            ),
        ];
        for (edit, reason) in cases {
            let e = refuse(edit);
            assert!(e.contains(reason), "{e:?} lacks {reason:?}");
        }
        // A joint whose range is one value (held there) is a joint, not an inverted range; a short axis is one.
        let mut fixed = four();
        fixed[3].lower_rad = 0.5;
        fixed[3].upper_rad = 0.5;
        fixed[1].axis = [2e-9, 0.0, 0.0];
        assert!(declared_stage(&chain(fixed), &bridge, &none, 1.0).is_ok());
        let two = vec![joint("a"), joint("b")];
        let e = declared_stage(&chain(two), &names(&["a", "b"]), &none, 1.0).unwrap_err();
        assert_eq!(e, ModelError::ChainLength { got: 2 });
        let eight: Vec<_> = (0..8).map(|i| joint(&format!("j{i}"))).collect();
        let bridge8: Vec<String> = eight.iter().map(|j| j.name.clone()).collect();
        assert_eq!(
            declared_stage(&chain(eight), &bridge8, &none, 1.0).unwrap_err(),
            ModelError::ChainLength { got: 8 }
        );
        let bad_tool = DeclaredModel::Chain {
            joints: four(),
            tool_xyz_m: [0.0, f64::NAN, 0.0],
            tool_rpy_rad: [0.0; 3],
        };
        assert_eq!(
            declared_stage(&bad_tool, &bridge, &none, 1.0).unwrap_err(),
            ModelError::ToolNotFinite
        );
        // The arm's configured speeds must fit the declared joints.
        let configured = JointLimitConfig {
            max_velocity_rad_s: vec![1.0, 1.0],
            ..JointLimitConfig::default()
        };
        let e = declared_stage(&chain(four()), &bridge, &configured, 1.0).unwrap_err();
        assert!(matches!(e, ModelError::Configured(_)), "{e:?}");
    }

    /// A declared chain's stage limits joint steps like the built-in robots': a far target arrives as a ramp.
    #[test]
    fn a_declared_chain_is_rate_limited() {
        let none = JointLimitConfig::default();
        let mut stage = declared_stage(&chain(four()), &names(&["a", "b", "c", "d"]), &none, 0.0).unwrap();
        let start = [0.0, 0.3, 0.3, 0.3];
        stage.reset(&start, 0.0);
        let target = stage.forward(&[1.0, 0.8, -0.2, 0.6]).unwrap();
        let mut previous = start.to_vec();
        let mut t = 0.0;
        for _ in 0..200 {
            t += 0.02;
            let q = stage.plan(&target, t);
            let step = q
                .iter()
                .zip(&previous)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(step <= 1.5 * 0.02 * (1.0 + 1e-9), "{step}");
            previous = q;
            if !stage.behind() {
                break;
            }
        }
        assert!(!stage.behind());
        assert!(stage.counters().limited > 10, "{:?}", stage.counters());
        let reached = stage.forward(&previous).unwrap();
        assert!((reached.translation.vector - target.translation.vector).norm() < 1e-3);
    }
}
