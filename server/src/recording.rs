//! Wiring between the arms, the cameras and the recorder: the dataset spec (feature names in the core's
//! layout, prefixed per arm when there are several; GR00T modality groups), the robot source the recorder's
//! tick samples, and the recording layer's errors.

use crate::arm::ArmController;
use crate::config::Config;
use parking_lot::Mutex;
use phone2act_core::episode_clock::{EpisodeClock, EpisodeLimits, Observed, Step};
use phone2act_dataset::error::RecorderError;
use phone2act_dataset::spec::{CameraSpec, DatasetSpec, ModalityGroup};
use phone2act_recorder::recorder::{Phase, RecorderStatus, RobotSample, RobotSource};
use std::sync::Arc;

/// Why a recording request failed.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("the recorder is closed (server shutting down)")]
    Closed,
    #[error(transparent)]
    Recorder(#[from] RecorderError),
    #[error("cannot start the recorder watch thread: {0}")]
    WatchThread(#[source] std::io::Error),
    #[error("recorder.fps must be a whole number for LeRobot datasets, got {0}")]
    FractionalFps(f64),
    #[error("{0}")]
    Config(String),
}

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
        // The task is done when every arm that has a scene has done its own (a bimanual sim has two scenes).
        // Without any scene nothing measures it: false, until the operator's outcome marks the last frame.
        let mut success = true;
        let mut scenes = 0;
        let mut activity = Vec::with_capacity(self.arms.len());
        for arm in &self.arms {
            let sample = arm.state_and_action()?;
            activity.push(sample.activity);
            state.extend(sample.state);
            action.extend(sample.action);
            oldest_ns = oldest_ns.min(sample.capture_time_ns);
            if arm.has_scene() {
                scenes += 1;
                success &= sample.task_success;
            }
        }
        Some(RobotSample {
            state,
            action,
            success: success && scenes > 0,
            capture_time_ns: oldest_ns,
            arms: activity,
        })
    }
}

/// The episode time limit and reset period of `[recorder]`: the core's [`EpisodeClock`] and the task and
/// operator the next episode starts with.
#[derive(Debug)]
pub struct EpisodeTiming {
    clock: Mutex<EpisodeClock>,
    /// The task and operator of the newest episode seen recording.
    last: Mutex<(String, String)>,
}

/// Where the shell stands, for the recording status.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimingStatus {
    /// Seconds left of the episode's limit or of the reset period.
    pub remaining_s: Option<f64>,
    pub resetting: bool,
}

fn observed(s: &RecorderStatus) -> Observed {
    Observed {
        recording: s.phase != Phase::Idle,
        duration_s: s.duration_s,
        episodes_saved: s.episodes_saved,
    }
}

impl EpisodeTiming {
    pub fn new(limits: EpisodeLimits) -> Self {
        Self {
            clock: Mutex::new(EpisodeClock::new(limits)),
            last: Mutex::new((String::new(), String::new())),
        }
    }

    pub fn limits(&self) -> EpisodeLimits {
        self.clock.lock().limits()
    }

    /// The task and operator the next episode starts with.
    pub fn last_episode(&self) -> (String, String) {
        self.last.lock().clone()
    }

    /// The clock's view at `now_ns` of the recorder state `s`.
    pub fn status(&self, s: &RecorderStatus, now_ns: i64) -> TimingStatus {
        let clock = self.clock.lock();
        TimingStatus {
            remaining_s: clock.remaining_s(observed(s), now_ns),
            resetting: clock.resetting(observed(s)),
        }
    }

    /// Feeds the clock the recorder's state at `now_ns`; returns the step to carry out.
    pub fn observe(&self, s: &RecorderStatus, now_ns: i64) -> Option<Step> {
        if s.phase != Phase::Idle && !s.task.is_empty() {
            *self.last.lock() = (s.task.clone(), s.operator.clone());
        }
        self.clock.lock().observe(observed(s), now_ns)
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
pub fn dataset_spec(config: &Config, arms: &[Arc<ArmController>]) -> Result<DatasetSpec, RecordingError> {
    let fps = config.recorder.fps;
    if fps.fract() != 0.0 {
        return Err(RecordingError::FractionalFps(fps));
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
        format: config.recorder.format,
        fps: fps as u32,
        // `next.success` is the scene's success flag when an arm has a scene (the simulator's); hardware arms
        // get the column from `[recorder] success`, set by the operator's outcome at Stop.
        success: config.recorder.success || arms.iter().any(|a| a.has_scene()),
        intervention: config.recorder.intervention,
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
}
