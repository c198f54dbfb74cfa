//! What an arm controller refuses: its configuration when it is built, and inputs the arbiter or the bridge
//! turned down (a refusal changes nothing).

use phone2act_bridges::BridgeError;
use phone2act_core::{ArbiterError, LayoutError};

/// Errors of an arm controller: building it, and inputs it refused (a refusal changes nothing).
#[derive(Debug, thiserror::Error)]
pub enum ArmError {
    #[error("arm {arm}: {source}")]
    Config {
        arm: String,
        #[source]
        source: phone2act_core::ConfigError,
    },
    #[error(
        "arm {arm}: action_mode = \"joint\" needs SO-101 kinematics (bridge joints {joints:?}); use \"relative\" or \"absolute\""
    )]
    JointModeUnsupported { arm: String, joints: Vec<String> },
    #[error(
        "arm {arm}: dataset_layout = \"lerobot_so101\" needs an SO-101 (sim or so101 bridge) with action_mode = \"joint\""
    )]
    LerobotLayoutUnsupported { arm: String },
    #[error("arm {arm}: {source}")]
    FlightLog {
        arm: String,
        #[source]
        source: crate::flight_log::FlightLogError,
    },
    #[error("arm {arm}: joint limits are enforced in the server only for SO-101 and Dobot CR5 joints")]
    JointStageUnsupported { arm: String },
    #[error(
        "arm {arm}: the robot's reported tool pose is {off_mm:.1} mm and {off_deg:.1}° from the joint model's pose of its reported joints; joint limits cannot be enforced with this model"
    )]
    JointModelMismatch { arm: String, off_mm: f64, off_deg: f64 },
    #[error("arm {arm:?} {source}")]
    Refused {
        arm: String,
        #[source]
        source: ArbiterError,
    },
    #[error("arm {arm:?} step {step}: {source}")]
    InvalidStep {
        arm: String,
        step: usize,
        #[source]
        source: LayoutError,
    },
    /// The bridge refused (a scene request to an arm without a scene is [`BridgeError::Unsupported`]).
    #[error("arm {arm:?}: {source}")]
    Bridge {
        arm: String,
        #[source]
        source: BridgeError,
    },
}
