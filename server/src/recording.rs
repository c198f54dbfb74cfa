//! Wiring between the arms, the cameras and the recorder: the dataset spec (feature names in the core's
//! layout, prefixed per arm when there are several; GR00T modality groups), the robot source the recorder's
//! tick samples, and the translation of recorder errors into gRPC statuses.

use crate::arm::ArmController;
use crate::config::{Config, DatasetFormat};
use phone2act_proto::v1;
use phone2act_recorder::dataset::EpisodeSummary;
use phone2act_recorder::error::RecorderError;
use phone2act_recorder::recorder::{Phase, RecorderStatus, RobotSample, RobotSource};
use phone2act_recorder::spec::{CameraSpec, DatasetSpec, Format, ModalityGroup};
use std::sync::Arc;
use tonic::Status;

/// Samples every arm: concatenated state and executed action, stamped with the oldest feedback time so a
/// stale arm is never hidden behind a fresh one.
pub struct ArmsSource {
    pub arms: Vec<Arc<ArmController>>,
}

impl RobotSource for ArmsSource {
    fn sample(&self) -> Option<RobotSample> {
        let mut state = Vec::new();
        let mut action = Vec::new();
        let mut oldest_ns = i64::MAX;
        // The task is done when every arm that has one has done its own (a bimanual sim has two scenes).
        let mut success = true;
        for arm in &self.arms {
            let sample = arm.state_and_action()?;
            state.extend(sample.state);
            action.extend(sample.action);
            oldest_ns = oldest_ns.min(sample.capture_time_ns);
            success &= sample.task_success || !arm.has_scene();
        }
        Some(RobotSample {
            state,
            action,
            success,
            capture_time_ns: oldest_ns,
        })
    }
}

fn prefixed(arm: &str, names: Vec<String>, several: bool) -> Vec<String> {
    if several {
        names.into_iter().map(|n| format!("{arm}_{n}")).collect()
    } else {
        names
    }
}

/// The dataset spec for `config` and its arms.
pub fn dataset_spec(config: &Config, arms: &[Arc<ArmController>]) -> Result<DatasetSpec, String> {
    let fps = config.recorder.fps;
    if fps.fract() != 0.0 {
        return Err(format!(
            "recorder.fps must be a whole number for LeRobot datasets, got {fps}"
        ));
    }
    let several = arms.len() > 1;
    let mut state_names = Vec::new();
    let mut action_names = Vec::new();
    let mut modality = Vec::new();
    for arm in arms {
        let s = prefixed(&arm.name, arm.layout.state_names(), several);
        let a = prefixed(
            &arm.name,
            arm.layout.recorded_action_names(arm.action_mode),
            several,
        );
        let (s0, a0) = (state_names.len(), action_names.len());
        let prefix = if several {
            format!("{}_", arm.name)
        } else {
            String::new()
        };
        // GR00T groups: the arm (joints + end effector in the state, the end-effector target in the action)
        // and the gripper. Datasets record absolute targets whatever mode the arm's policies push (see
        // `phone2act_core::layout`), so GR00T pads past an episode's end with the last target: hold.
        modality.push(ModalityGroup {
            name: format!("{prefix}arm"),
            state_range: s0..s0 + s.len() - 1,
            action_range: a0..a0 + a.len() - 1,
            action_absolute: true,
        });
        modality.push(ModalityGroup {
            name: format!("{prefix}gripper"),
            state_range: s0 + s.len() - 1..s0 + s.len(),
            action_range: a0 + a.len() - 1..a0 + a.len(),
            action_absolute: true,
        });
        state_names.extend(s);
        action_names.extend(a);
    }
    Ok(DatasetSpec {
        root: config.recorder.root.clone(),
        format: match config.recorder.format {
            DatasetFormat::V30 => Format::V30,
            DatasetFormat::V21 => Format::V21,
        },
        fps: fps as u32,
        // `next.success` is the scene's success flag: recorded when an arm has a scene (the simulator's).
        success: arms.iter().any(|a| a.has_scene()),
        robot_type: config.recorder.robot_type.clone(),
        video_codec: config.recorder.video_codec.clone(),
        state_names,
        action_names,
        cameras: config
            .cameras
            .iter()
            .map(|c| CameraSpec {
                name: c.name.clone(),
                width: c.width,
                height: c.height,
            })
            .collect(),
        modality,
        provenance: serde_json::json!({
            "software": "phone2act",
            "version": env!("CARGO_PKG_VERSION"),
            "config": config.to_redacted_toml().unwrap_or_else(|e| format!("<not serialisable: {e}>")),
        }),
    })
}

/// A recorder error as a gRPC status with the right code.
pub fn status_of(e: &RecorderError) -> Status {
    let msg = e.to_string();
    match e {
        RecorderError::AlreadyRecording(_)
        | RecorderError::NotRecording
        | RecorderError::NothingToRerecord
        | RecorderError::FpsMismatch { .. }
        | RecorderError::FormatMismatch { .. }
        | RecorderError::FeatureMismatch { .. }
        | RecorderError::InvalidSpec(_) => Status::failed_precondition(msg),
        RecorderError::TaskTooLong { .. } | RecorderError::EmptyTask | RecorderError::EmptyEpisode(_) => {
            Status::invalid_argument(msg)
        }
        RecorderError::DiskFull { .. } => Status::resource_exhausted(msg),
        _ => Status::internal(msg),
    }
}

/// Recorder status on the wire.
pub fn status_to_proto(s: &RecorderStatus, config: &Config) -> v1::RecordingStatus {
    v1::RecordingStatus {
        phase: match s.phase {
            Phase::Idle => v1::RecordingPhase::Idle,
            Phase::Recording => v1::RecordingPhase::Recording,
            Phase::Paused => v1::RecordingPhase::Paused,
            Phase::Saving => v1::RecordingPhase::Saving,
        } as i32,
        dataset_root: config.recorder.root.display().to_string(),
        dataset_format: config.recorder.format.as_str().to_owned(),
        episode_index: s.episode_index,
        task: s.task.clone(),
        frames_recorded: s.frames_recorded,
        duration_s: s.duration_s,
        held_ticks: s.held_ticks,
        paused_ticks: s.paused_ticks,
        dropped_frames: s.dropped_frames,
        episodes_saved: s.episodes_saved,
        warning: s.warning.clone().unwrap_or_default(),
        fps: f64::from(s.fps),
        late_ticks: s.late_ticks,
    }
}

/// A saved episode on the wire.
pub fn episode_to_proto(e: &EpisodeSummary) -> v1::EpisodeInfo {
    v1::EpisodeInfo {
        episode_index: e.index,
        task: e.task.clone(),
        length_frames: e.length_frames,
        duration_s: e.duration_s,
        held_ticks: e.held_ticks,
        paused_ticks: e.paused_ticks,
        start_unix_ns: e.start_unix_ns,
        late_ticks: e.late_ticks,
        dropped_frames: e.dropped_frames,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modality_groups_are_absolute_whatever_mode_policies_push() {
        use phone2act_core::ActionMode;
        let config = Config::embedded_default().unwrap();
        let arm = |name: &str, mode: ActionMode| {
            let joints = (0..6).map(|j| format!("j{j}")).collect();
            let bridge = phone2act_bridges::remote::RemoteBridge::with_joint_names(name, joints);
            let a = &config.arms[0];
            Arc::new(
                ArmController::new(
                    name,
                    "remote",
                    bridge,
                    &a.teleop,
                    &a.chunk,
                    mode,
                    nalgebra::Isometry3::identity(),
                )
                .unwrap(),
            )
        };
        // A relative arm's policies push steps relative to their observation, but the dataset records the
        // absolute target (the one definition in `phone2act_core::layout`), so GR00T must pad it with the last
        // value (hold), never with zero.
        let arms = [
            arm("left", ActionMode::Relative),
            arm("right", ActionMode::Absolute),
        ];
        let spec = dataset_spec(&config, &arms).unwrap();
        let flags: Vec<(&str, usize, usize, bool)> = spec
            .modality
            .iter()
            .map(|g| {
                (
                    g.name.as_str(),
                    g.action_range.start,
                    g.action_range.end,
                    g.action_absolute,
                )
            })
            .collect();
        assert_eq!(
            flags,
            [
                ("left_arm", 0, 9, true),
                ("left_gripper", 9, 10, true),
                ("right_arm", 10, 19, true),
                ("right_gripper", 19, 20, true),
            ]
        );
        assert_eq!(spec.action_names[0], "left_x");
        assert_eq!(spec.action_names[9], "left_gripper");
        assert!(!spec.action_names.iter().any(|n| n.contains("delta")));
    }

    #[test]
    fn sync_counters_reach_the_wire() {
        let config = Config::embedded_default().unwrap();
        let status = RecorderStatus {
            phase: Phase::Recording,
            episode_index: 4,
            task: "pick".into(),
            frames_recorded: 120,
            duration_s: 6.0,
            held_ticks: 3,
            paused_ticks: 2,
            late_ticks: 7,
            dropped_frames: 1,
            episodes_saved: 4,
            warning: None,
            fps: 20,
            version: 9,
        };
        let wire = status_to_proto(&status, &config);
        assert_eq!(
            (
                wire.held_ticks,
                wire.paused_ticks,
                wire.late_ticks,
                wire.dropped_frames
            ),
            (3, 2, 7, 1)
        );
        let episode = EpisodeSummary {
            index: 4,
            late_ticks: 5,
            dropped_frames: 6,
            paused_ticks: 2,
            ..EpisodeSummary::default()
        };
        let wire = episode_to_proto(&episode);
        assert_eq!(
            (wire.paused_ticks, wire.late_ticks, wire.dropped_frames),
            (2, 5, 6)
        );
    }
}
