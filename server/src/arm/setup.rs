//! Building an arm controller from its configuration: the arbiter from the robot's measured pose, the optional
//! flight log, the joint stage and its check against the robot's own reported pose, and lerobot's SO-101 units.

use super::{ArmController, ArmError, Inner};
use crate::control_stats::ControlStats;
use crate::flight_log::FlightLogWriter;
use nalgebra::Isometry3;
use parking_lot::Mutex;
use phone2act_bridges::{Bridge, Feedback};
use phone2act_clock::monotonic_s;
use phone2act_core::kinematics::{SO101_ARM_JOINT_NAMES, So101Kinematics};
use phone2act_core::{
    ActionMode, Arbiter, ArmControl, ArmJointStage, ArmLayout, ChunkConfig, FlightHeader, TeleopConfig,
};
use std::sync::Arc;
use tokio::sync::Notify;

impl ArmController {
    /// A controller for `bridge`, starting from the robot's measured pose (or `fallback` before feedback).
    pub fn new(
        name: &str,
        kind: &'static str,
        bridge: Arc<dyn Bridge>,
        teleop: &TeleopConfig,
        chunk: &ChunkConfig,
        action_mode: ActionMode,
        fallback: Isometry3<f64>,
    ) -> Result<Self, ArmError> {
        let feedback = bridge.feedback();
        let measured = feedback.as_ref().map_or(fallback, |f| f.robot_from_ee);
        let gripper = feedback.as_ref().map_or(0.0, |f| f.gripper_position);
        let layout = ArmLayout::new(bridge.joint_names().to_vec());
        let kinematics = (bridge.joint_names() == SO101_ARM_JOINT_NAMES).then(So101Kinematics::new);
        if action_mode == ActionMode::Joint && kinematics.is_none() {
            return Err(ArmError::JointModeUnsupported {
                arm: name.to_owned(),
                joints: bridge.joint_names().to_vec(),
            });
        }
        let arbiter =
            Arbiter::new(teleop, chunk.clone(), measured, gripper).map_err(|source| ArmError::Config {
                arm: name.to_owned(),
                source,
            })?;
        Ok(Self {
            name: name.to_owned(),
            kind,
            bridge,
            layout,
            action_mode,
            kinematics,
            inner: Mutex::new(Inner {
                control: ArmControl::new(arbiter),
                policy_sink: None,
                flight: None,
            }),
            wake: Notify::new(),
            stats: ControlStats::default(),
        })
    }

    /// Logs every input of this arm's arbiter from now on to a new file in `dir` (see
    /// [`crate::flight_log`]), its header made of the `teleop` and `chunk` settings the arm was built with and
    /// the pose and gripper the arbiter holds. Called before the arm takes any input (so that pose is the one
    /// it started from, and the log replays from its start).
    pub fn with_flight_log(
        self,
        dir: &std::path::Path,
        max_bytes: u64,
        teleop: &TeleopConfig,
        chunk: &ChunkConfig,
    ) -> Result<Self, ArmError> {
        let (measured, gripper) = self.inner.lock().control.arbiter().target();
        let header = FlightHeader::new(&self.name, teleop, chunk, measured, gripper);
        let log = FlightLogWriter::create(dir, &header, max_bytes).map_err(|source| ArmError::FlightLog {
            arm: self.name.clone(),
            source,
        })?;
        tracing::info!(arm = %self.name, path = %log.path().display(), "flight log on");
        self.inner.lock().flight = Some(log);
        Ok(self)
    }

    /// Solves this arm's commands in the server with `stage` (an SO-101's or a CR5's): each target once,
    /// seeded with the joints last commanded, through the stage's joint speed limits. See
    /// `phone2act_core::joint_motion`. Refused for a bridge whose joints are not the stage's, and when the
    /// robot's own tool pose disagrees with the model's pose of its reported joints (a controller whose base
    /// frame, tool or joint zeros differ from the model would be driven somewhere else than asked).
    pub fn with_joint_stage(self, mut stage: ArmJointStage) -> Result<Self, ArmError> {
        if !stage.fits(self.bridge.joint_names()) {
            return Err(ArmError::JointStageUnsupported {
                arm: self.name.clone(),
            });
        }
        if let Some(feedback) = self.bridge.feedback() {
            self.model_matches(&stage, &feedback)?;
            stage.reset(&feedback.joint_positions_rad, monotonic_s());
        } else {
            tracing::warn!(arm = %self.name, "no feedback at start: the joint model was not checked against the robot");
        }
        self.inner.lock().control.replace_joint_stage(Some(stage));
        Ok(self)
    }

    /// Puts `stage` in place of the arm's joint stage (for a remote bridge, at every attach: the stage of the
    /// joint model it declared, or none). A new stage starts from the next measured joints, so the first
    /// command after an attach is limited from where that robot is. Returns the stage it replaced.
    pub fn replace_joint_stage(&self, stage: Option<ArmJointStage>) -> Option<ArmJointStage> {
        self.inner.lock().control.replace_joint_stage(stage)
    }

    /// Refuses feedback whose reported tool pose disagrees with the arm's joint model's pose of its reported
    /// joints (the check [`Self::with_joint_stage`] makes at start, for a stage put in place later). Ok
    /// without a joint stage or for joints of another width.
    pub fn check_joint_model(&self, feedback: &Feedback) -> Result<(), ArmError> {
        match self.inner.lock().control.joint_stage() {
            Some(stage) => self.model_matches(stage, feedback),
            None => Ok(()),
        }
    }

    /// See `ArmJointStage::model_mismatch`.
    fn model_matches(&self, stage: &ArmJointStage, feedback: &Feedback) -> Result<(), ArmError> {
        match stage.model_mismatch(&feedback.joint_positions_rad, &feedback.robot_from_ee) {
            None => Ok(()),
            Some(off) => Err(ArmError::JointModelMismatch {
                arm: self.name.clone(),
                off_mm: off.off_m * 1e3,
                off_deg: off.off_rad.to_degrees(),
            }),
        }
    }

    /// Switches the arm's state and joint actions to lerobot `so101_follower` names and units (see
    /// `phone2act_core::LerobotSo101Units`). Joint arms with SO-101 kinematics only.
    pub fn with_lerobot_so101(mut self, units: phone2act_core::LerobotSo101Units) -> Result<Self, ArmError> {
        if self.action_mode != ActionMode::Joint || self.kinematics.is_none() {
            return Err(ArmError::LerobotLayoutUnsupported {
                arm: self.name.clone(),
            });
        }
        self.layout = self.layout.with_lerobot_so101(units);
        Ok(self)
    }
}
