//! Per-arm teleop configuration: phone-to-robot mapping, safety gate and gripper.
//!
//! Every struct deserialises with `deny_unknown_fields` and fills missing keys from `Default`, so the server
//! can embed them as TOML tables (`[arms.main.teleop]`, `[arms.main.teleop.gate]`, …) and a typo is an
//! error rather than a silently ignored setting. Defaults suit the simulated SO-101 arm.

use nalgebra::{Matrix3, Rotation3};
use serde::{Deserialize, Serialize};

/// A configuration value that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    #[error(
        "mapping matrix is not a proper rotation (orthonormality error {orthonormality_error:.2e}, det {det:.6})"
    )]
    NotARotation { orthonormality_error: f64, det: f64 },
    #[error("{name} must be finite and > 0, got {value}")]
    NotPositive { name: &'static str, value: f64 },
    #[error("{name} must be finite, got {value}")]
    NotFinite { name: &'static str, value: f64 },
    #[error("{name} needs {expected} values (or one for all), got {got}")]
    WrongLength {
        name: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("workspace axis {axis}: min {min_m} m must be below max {max_m} m")]
    EmptyWorkspace { axis: char, min_m: f64, max_m: f64 },
    #[error("{name} must be in ({min}, {max}], got {value}")]
    OutOfRange {
        name: &'static str,
        min: f64,
        max: f64,
        value: f64,
    },
}

/// How the phone's tracking frame is turned to the robot frame when no explicit matrix is given.
///
/// The robot frame is x forward, y left, z up; the operator stands behind the robot facing its +x.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum AxisPreset {
    /// Tracking frame with +X right, +Y up, −Z forward (WebXR, ARCore display-oriented poses, the phone held
    /// in landscape): x_robot = −z, y_robot = −x, z_robot = +y (protocols spec §2.2, RUB→FLU).
    #[default]
    Landscape,
    /// Tracking frame fixed by a landscape-native camera sensor while the phone is held in portrait: +X up,
    /// +Y left, +Z back. x_robot = −z, y_robot = +y, z_robot = +x.
    Portrait,
    /// The tracking frame already is the robot frame (scripted clients, tests).
    Identity,
}

impl AxisPreset {
    /// The `robot_from_tracking` rotation matrix, rows are robot axes.
    pub fn matrix(self) -> [[f64; 3]; 3] {
        match self {
            AxisPreset::Landscape => [[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            AxisPreset::Portrait => [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
            AxisPreset::Identity => [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }
}

/// Phone-to-robot mapping: `p_target = p_ref_robot + M·(Δp_phone·S)` and the phone's rotation since the
/// reference, turned into the robot frame by `M`, scaled and composed onto the robot's reference orientation.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct MappingConfig {
    /// Axis alignment used when `matrix` is absent.
    pub preset: AxisPreset,
    /// Explicit `robot_from_tracking` rotation (rows are robot axes); overrides `preset`.
    pub matrix: Option<[[f64; 3]; 3]>,
    /// Robot metres per phone metre.
    pub position_scale: f64,
    /// Fraction of the phone's rotation angle applied to the robot (1 = follow exactly).
    pub rotation_scale: f64,
    /// Keep the orientation at its reference (arms that cannot follow orientation).
    pub position_only: bool,
}

impl Default for MappingConfig {
    fn default() -> Self {
        Self {
            preset: AxisPreset::Landscape,
            matrix: None,
            position_scale: 1.0,
            rotation_scale: 1.0,
            position_only: false,
        }
    }
}

/// Tolerance on `MᵀM = I` for an explicit mapping matrix; hand-typed matrices are exact signed
/// permutations or come from a calibration with at least this many digits.
const ROTATION_TOLERANCE: f64 = 1e-6;

/// Longest episode task text accepted, in bytes, by the recorder and by every client that checks before
/// sending. lerobot stores it as a parquet string and GR00T tokenises it; anything longer is a pasted
/// document, not an instruction.
pub const MAX_TASK_BYTES: usize = 4096;

impl MappingConfig {
    /// The validated `robot_from_tracking` rotation.
    pub fn robot_from_tracking(&self) -> Result<Rotation3<f64>, ConfigError> {
        let rows = self.matrix.unwrap_or_else(|| self.preset.matrix());
        let m = Matrix3::from_fn(|r, c| rows[r][c]);
        let orthonormality_error = (m.transpose() * m - Matrix3::identity()).abs().max();
        let det = m.determinant();
        if !orthonormality_error.is_finite()
            || orthonormality_error > ROTATION_TOLERANCE
            || (det - 1.0).abs() > ROTATION_TOLERANCE
        {
            return Err(ConfigError::NotARotation {
                orthonormality_error,
                det,
            });
        }
        // Re-orthonormalise so that tolerated calibration noise cannot accumulate into the targets.
        Ok(Rotation3::from_matrix(&m))
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        self.robot_from_tracking()?;
        positive("position_scale", self.position_scale)?;
        positive("rotation_scale", self.rotation_scale)?;
        Ok(())
    }
}

/// Safety gate limits, all in the robot base frame.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct GateConfig {
    /// Workspace box (m); targets are clamped into it axis by axis.
    pub workspace_min_m: [f64; 3],
    pub workspace_max_m: [f64; 3],
    /// A target farther than this from the gate's reference is dropped (m).
    pub jump_position_m: f64,
    /// A target rotated more than this from the gate's reference is dropped (rad).
    pub jump_rotation_rad: f64,
    /// Optional cap on the target's linear speed (m/s).
    pub max_linear_speed_m_s: Option<f64>,
    /// Optional cap on the target's angular speed (rad/s).
    pub max_angular_speed_rad_s: Option<f64>,
    /// With no valid command for this long the arm holds (s).
    pub stale_timeout_s: f64,
}

impl Default for GateConfig {
    fn default() -> Self {
        Self {
            // SO-101: base at the origin, z up, about 0.4 m of reach; keeps the gripper off the table.
            workspace_min_m: [0.10, -0.25, 0.02],
            workspace_max_m: [0.40, 0.25, 0.35],
            jump_position_m: 0.06,
            // About 29°: a wrist turn faster than this within one 20–50 ms sample is a tracking glitch.
            jump_rotation_rad: 0.5,
            max_linear_speed_m_s: None,
            max_angular_speed_rad_s: None,
            // Phones send at 30–50 Hz; a few lost Wi-Fi frames must not stop the arm, a dead stream must.
            stale_timeout_s: 0.3,
        }
    }
}

impl GateConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (axis, (min_m, max_m)) in ['x', 'y', 'z']
            .into_iter()
            .zip(self.workspace_min_m.into_iter().zip(self.workspace_max_m))
        {
            finite("workspace_min_m", min_m)?;
            finite("workspace_max_m", max_m)?;
            if min_m >= max_m {
                return Err(ConfigError::EmptyWorkspace { axis, min_m, max_m });
            }
        }
        positive("jump_position_m", self.jump_position_m)?;
        positive("jump_rotation_rad", self.jump_rotation_rad)?;
        if let Some(v) = self.max_linear_speed_m_s {
            positive("max_linear_speed_m_s", v)?;
        }
        if let Some(v) = self.max_angular_speed_rad_s {
            positive("max_angular_speed_rad_s", v)?;
        }
        positive("stale_timeout_s", self.stale_timeout_s)?;
        Ok(())
    }
}

/// Gripper behaviour.
#[derive(Debug, Clone, PartialEq, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct GripperConfig {
    /// Snap every command to fully open (0) or fully closed (1).
    pub binary: bool,
}

/// Everything one arm's teleop path needs.
#[derive(Debug, Clone, PartialEq, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TeleopConfig {
    pub mapping: MappingConfig,
    pub gate: GateConfig,
    pub gripper: GripperConfig,
}

impl TeleopConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.mapping.validate()?;
        self.gate.validate()
    }
}

fn positive(name: &'static str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(ConfigError::NotPositive { name, value })
    }
}

fn finite(name: &'static str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ConfigError::NotFinite { name, value })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn defaults_validate_and_landscape_is_rub_to_flu() {
        TeleopConfig::default().validate().unwrap();
        let m = MappingConfig::default().robot_from_tracking().unwrap();
        // Phone forward (−Z) is robot forward, phone right (+X) is robot right (−y), phone up is robot up.
        assert!((m * Vector3::new(0.0, 0.0, -1.0) - Vector3::x()).norm() < 1e-15);
        assert!((m * Vector3::x() + Vector3::y()).norm() < 1e-15);
        assert!((m * Vector3::y() - Vector3::z()).norm() < 1e-15);
        let portrait = MappingConfig {
            preset: AxisPreset::Portrait,
            ..MappingConfig::default()
        };
        let p = portrait.robot_from_tracking().unwrap();
        assert!(
            (p * Vector3::x() - Vector3::z()).norm() < 1e-15,
            "portrait +X is up"
        );
    }

    #[test]
    fn toml_tables_fill_defaults_and_refuse_typos() {
        let cfg: TeleopConfig = toml::from_str(
            "[mapping]\npreset = \"portrait\"\nposition_scale = 1.5\n[gate]\njump_position_m = 0.04\nmax_linear_speed_m_s = 0.5\n",
        )
        .unwrap();
        assert_eq!(cfg.mapping.preset, AxisPreset::Portrait);
        assert!((cfg.mapping.position_scale - 1.5).abs() < 1e-15);
        assert!((cfg.gate.jump_position_m - 0.04).abs() < 1e-15);
        assert_eq!(cfg.gate.max_linear_speed_m_s, Some(0.5));
        assert_eq!(
            cfg.gate.workspace_max_m.map(f64::to_bits),
            GateConfig::default().workspace_max_m.map(f64::to_bits)
        );
        assert!(toml::from_str::<TeleopConfig>("[gate]\njump_positon_m = 0.04\n").is_err());
        assert!(toml::from_str::<TeleopConfig>("[mapping]\npreset = \"diagonal\"\n").is_err());
    }

    #[test]
    fn invalid_values_are_refused() {
        let mirror = MappingConfig {
            matrix: Some([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            ..MappingConfig::default()
        };
        assert!(matches!(mirror.validate(), Err(ConfigError::NotARotation { .. })));
        let skew = MappingConfig {
            matrix: Some([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            ..MappingConfig::default()
        };
        assert!(skew.validate().is_err());
        let phone2act_so101 = MappingConfig {
            matrix: Some([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
            ..MappingConfig::default()
        };
        phone2act_so101.validate().unwrap();
        let zero_scale = MappingConfig {
            position_scale: 0.0,
            ..MappingConfig::default()
        };
        assert!(matches!(
            zero_scale.validate(),
            Err(ConfigError::NotPositive {
                name: "position_scale",
                ..
            })
        ));
        let empty = GateConfig {
            workspace_min_m: [0.5, -0.25, 0.02],
            ..GateConfig::default()
        };
        assert!(matches!(
            empty.validate(),
            Err(ConfigError::EmptyWorkspace { axis: 'x', .. })
        ));
        let nan_speed = GateConfig {
            max_angular_speed_rad_s: Some(f64::NAN),
            ..GateConfig::default()
        };
        assert!(nan_speed.validate().is_err());
    }
}
