//! Pure phone2act domain logic: poses, the teleop planner, the safety gate, chunk-executor math, kinematics
//! and the action/state vector layouts. No I/O, no tokio, no clock reads: every time is an argument, so
//! everything here is deterministic and property-testable.

pub mod arbiter;
pub mod arm_control;
pub mod arm_vectors;
pub mod chunk;
pub mod config;
pub mod episode_clock;
pub mod flight;
pub mod gate;
pub mod gripper;
pub mod joint_limit;
pub mod joint_model;
pub mod joint_motion;
pub mod kinematics;
pub mod latency;
pub mod layout;
pub mod planner;
pub mod pose;
pub mod teleop;
#[cfg(test)]
mod test_support;

pub use arbiter::{
    Arbiter, ArbiterError, ArmSnapshot, BridgeHealth, Command, Counters, Driver, Effects, FEEDBACK_MAX_AGE_S,
    Input, Measured, NotReady, Owner, PREVIEW_MAX_POINTS, PlanPreview, PolicyTurn, Revocation, Robot,
    TeleopButton, TeleopRound, TickNeed,
};
pub use arm_control::{ArmControl, ArmNames, Handled, Issue};
pub use arm_vectors::{Activity, ArmVectors, Reading, Sample, StepError};
pub use chunk::{ActionChunk, ChunkConfig, ChunkError, ChunkExecutor, ChunkStep, ReplaceReport};
pub use config::{AxisPreset, ConfigError, GateConfig, GripperConfig, MappingConfig, TeleopConfig};
pub use flight::{
    Divergence, FLIGHT_FORMAT_VERSION, FlightEntry, FlightHeader, Outcome, ReplayCounts, ReplayError,
    Replayer, replay,
};
pub use gate::{GateDecision, GateVerdict, SafetyGate};
pub use gripper::{Gripper, GripperCommand, GripperError};
pub use joint_limit::{JointRateLimiter, LimitedStep};
pub use joint_motion::{
    ArmJointStage, Cr5JointStage, JointCounters, JointLimitConfig, JointStage, MODEL_MATCH_M,
    MODEL_MATCH_RAD, ModelMismatch, PlannedJoints, So101JointStage,
};
pub use latency::LatencyRing;
pub use layout::{
    ACTION_WIDTH, ActionMode, ArmLayout, LayoutError, LerobotSo101Units, RELATIVE_STEP_WIDTH,
    absolute_action, joint_action, relative_step, step_from_target, target_from_joint_step, target_from_step,
};
pub use planner::{Mapping, Planner, Reference};
pub use pose::{PoseError, rotation_from_rpy, rpy_from_rotation, validate_pose, wrap_angle_rad};
pub use teleop::{ClutchKind, TeleopArm, TeleopStep};
