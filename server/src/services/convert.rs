//! Server state ⇄ wire messages for the types the proto crate cannot see (the recorder's, the app's): the
//! service layer's half of the wire boundary. Conversions of core types live in `phone2act_proto`.

use crate::app::{App, CameraHealth, CameraRuntime};
use crate::config::Config;
use crate::policy_session::Observation;
use phone2act_bridges::{Command, Control, Feedback, Health};
use phone2act_clock::monotonic_ns;
use phone2act_dataset::dataset::EpisodeSummary;
use phone2act_proto::convert_arm::{arm_state_to_proto, pose_from_proto, pose_to_proto};
use phone2act_proto::v1;
use phone2act_recorder::recorder::{Phase, RecorderStatus};
use phone2act_storage::{EpisodeUpload, Uploader};

/// Recorder status on the wire.
pub fn recording_status(s: &RecorderStatus, config: &Config) -> v1::RecordingStatus {
    v1::RecordingStatus {
        phase: match s.phase {
            Phase::Idle => v1::RecordingPhase::Idle,
            Phase::Recording => v1::RecordingPhase::Recording,
            Phase::Paused => v1::RecordingPhase::Paused,
            Phase::Saving => v1::RecordingPhase::Saving,
        } as i32,
        dataset_root: config.recorder.root.display().to_string(),
        dataset_format: config.recorder.format.codebase_version().to_owned(),
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
        // Filled in by `current_recording_status`, which knows the uploader and the episode timing.
        upload_summary: String::new(),
        remaining_s: None,
        resetting: false,
        highlight_s: s.highlight_s,
        highlight_buffered_s: s.highlight_buffered_s,
        highlight_video_bytes: s.highlight_video_bytes,
    }
}

/// The recorder's state on the wire, or an idle status that says it is closed.
pub fn current_recording_status(app: &App) -> v1::RecordingStatus {
    let mut status = recorder_status_only(app);
    if let Some(u) = app.uploader() {
        status.upload_summary = upload_summary(u);
    }
    status
}

/// The uploader's state in a few words, for the phone page's status line.
pub fn upload_summary(u: &Uploader) -> String {
    let s = u.status();
    let mut text = format!("{} uploaded, {} pending", s.episodes_uploaded, s.episodes_pending);
    if let Some(e) = s.last_error.filter(|_| s.episodes_pending > 0) {
        text.push_str("; failing: ");
        text.push_str(&e);
    }
    text
}

fn recorder_status_only(app: &App) -> v1::RecordingStatus {
    match app.recorder_status() {
        Some(status) => {
            let mut wire = recording_status(&status, app.config());
            let timing = app
                .episode_timing()
                .status(&status, phone2act_clock::monotonic_ns());
            wire.remaining_s = timing.remaining_s;
            wire.resetting = timing.resetting;
            wire
        }
        None => v1::RecordingStatus {
            phase: v1::RecordingPhase::Idle as i32,
            dataset_root: app.config().recorder.root.display().to_string(),
            dataset_format: app.config().recorder.format.codebase_version().to_owned(),
            fps: app.config().recorder.fps,
            warning: "recorder closed".to_owned(),
            ..v1::RecordingStatus::default()
        },
    }
}

/// A saved episode on the wire.
pub fn episode(e: &EpisodeSummary) -> v1::EpisodeInfo {
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
        operator: e.operator.clone(),
        station_id: e.station_id.clone(),
        outcome: match e.success {
            Some(true) => v1::EpisodeOutcome::Success,
            Some(false) => v1::EpisodeOutcome::Failure,
            None => v1::EpisodeOutcome::Unspecified,
        }
        .into(),
        ..v1::EpisodeInfo::default()
    }
}

/// An episode with its upload state.
pub fn episode_with_upload(e: &EpisodeSummary, uploader: Option<&Uploader>) -> v1::EpisodeInfo {
    let mut info = episode(e);
    if let Some(u) = uploader {
        let state = u.episode(e.index);
        info.upload_state = match &state {
            EpisodeUpload::Pending => v1::UploadState::Pending,
            EpisodeUpload::Uploading => v1::UploadState::Uploading,
            EpisodeUpload::Uploaded => v1::UploadState::Uploaded,
            EpisodeUpload::Failed(_) => v1::UploadState::Failed,
        } as i32;
        if let EpisodeUpload::Failed(reason) = state {
            info.upload_error = reason;
        }
    }
    info
}

/// The uploader's status on the wire.
pub fn storage_status(u: &Uploader) -> v1::StorageStatus {
    let s = u.status();
    v1::StorageStatus {
        url: s.url,
        station_id: s.station_id,
        episodes_uploaded: s.episodes_uploaded,
        episodes_pending: s.episodes_pending,
        last_error: s.last_error.unwrap_or_default(),
        objects_put: s.objects_put,
        objects_skipped: s.objects_skipped,
        bytes_put: s.bytes_put,
    }
}

/// A camera's configuration and health on the wire.
pub fn camera_status(cam: &CameraRuntime) -> v1::CameraStatus {
    let config = cam.config();
    let CameraHealth {
        live,
        frames_captured,
        last_frame_age_s,
    } = cam.health();
    v1::CameraStatus {
        camera: config.name.clone(),
        kind: config.kind.as_str().to_owned(),
        width: config.width,
        height: config.height,
        fps: config.fps,
        live,
        frames_captured,
        last_frame_age_s: last_frame_age_s.unwrap_or(-1.0),
        measured_fps: 0.0,
        error: String::new(),
    }
}

/// A full status snapshot.
pub fn system_status(app: &App, sequence: u64) -> v1::SystemStatus {
    v1::SystemStatus {
        version: env!("CARGO_PKG_VERSION").to_owned(),
        server_time_ns: monotonic_ns(),
        uptime_s: app.started().elapsed().as_secs_f64(),
        arms: app
            .arms()
            .iter()
            .map(|a| arm_state_to_proto(&a.snapshot()))
            .collect(),
        cameras: app.cameras().iter().map(camera_status).collect(),
        recording: Some(current_recording_status(app)),
        sequence,
    }
}

/// Feedback from an out-of-process bridge, stamped with its arrival time on the server's clock.
pub fn bridge_feedback(fb: &v1::RobotFeedback) -> Result<Feedback, String> {
    let pose = fb.robot_from_ee.as_ref().ok_or("feedback has no robot_from_ee")?;
    Ok(Feedback {
        // The bridge's clock is not ours: stamp feedback with its arrival time on the server's clock.
        capture_time_ns: monotonic_ns(),
        joint_positions_rad: fb.joint_positions_rad.clone(),
        robot_from_ee: pose_from_proto(pose).map_err(|e| e.to_string())?,
        gripper_position: fb.gripper_position,
        applied_seq: fb.applied_seq,
        task_success: false,
    })
}

/// A gated command for an out-of-process bridge.
pub fn bridge_command(c: &Command) -> v1::BridgeCommand {
    v1::BridgeCommand {
        seq: c.seq,
        robot_from_target: Some(pose_to_proto(&c.robot_from_target)),
        gripper_target: c.gripper_target,
        issue_time_ns: c.issue_time_ns,
        joint_targets_rad: c.joint_targets_rad.clone().unwrap_or_default(),
    }
}

/// The joint model a bridge declared, checked for shape (three values where three are meant); its values are
/// checked by `phone2act_core::joint_model`.
pub fn declared_model(m: &v1::JointModel) -> Result<phone2act_core::joint_model::DeclaredModel, String> {
    use phone2act_core::joint_model::{DeclaredJoint, DeclaredModel};
    use v1::joint_model::Model;
    let three = |what: &str, v: &[f64]| -> Result<[f64; 3], String> {
        v.try_into()
            .map_err(|_| format!("{what} needs 3 values, got {}", v.len()))
    };
    match &m.model {
        None => Err("joint_model names no model (set known or chain)".to_owned()),
        Some(Model::Known(name)) => Ok(DeclaredModel::Known(name.clone())),
        Some(Model::Chain(chain)) => {
            let joints = chain
                .joints
                .iter()
                .map(|j| {
                    let field = |f: &str| format!("joint {:?}: {f}", j.name);
                    Ok(DeclaredJoint {
                        name: j.name.clone(),
                        origin_xyz_m: three(&field("origin_xyz_m"), &j.origin_xyz_m)?,
                        origin_rpy_rad: three(&field("origin_rpy_rad"), &j.origin_rpy_rad)?,
                        axis: three(&field("axis"), &j.axis)?,
                        lower_rad: j.lower_rad,
                        upper_rad: j.upper_rad,
                        max_velocity_rad_s: j.max_velocity_rad_s,
                        max_acceleration_rad_s2: j.max_acceleration_rad_s2,
                    })
                })
                .collect::<Result<Vec<_>, String>>()?;
            // An unset tool origin is the last link's own frame.
            let or_zero = |what: &str, v: &[f64]| {
                if v.is_empty() {
                    Ok([0.0; 3])
                } else {
                    three(what, v)
                }
            };
            Ok(DeclaredModel::Chain {
                joints,
                tool_xyz_m: or_zero("tool_xyz_m", &chain.tool_xyz_m)?,
                tool_rpy_rad: or_zero("tool_rpy_rad", &chain.tool_rpy_rad)?,
            })
        }
    }
}

/// A control request for an out-of-process bridge.
pub fn bridge_control(c: Control) -> v1::BridgeControl {
    let kind = match c {
        Control::Enable => v1::bridge_control::Kind::Enable,
        Control::Disable => v1::bridge_control::Kind::Disable,
        Control::ClearError => v1::bridge_control::Kind::ClearError,
        Control::Reconnect => v1::bridge_control::Kind::Reconnect,
    };
    v1::BridgeControl { kind: kind as i32 }
}

/// A bridge's health report; anything but ready, connecting or error counts as disconnected.
pub fn bridge_health(report: v1::BridgeStatusReport) -> Health {
    match v1::BridgeHealth::try_from(report.health) {
        Ok(v1::BridgeHealth::Ready) => Health::Ready,
        Ok(v1::BridgeHealth::Connecting) => Health::Connecting,
        Ok(v1::BridgeHealth::Error) => Health::Error(report.message),
        _ => Health::Disconnected(report.message),
    }
}

/// An observation on the wire; each arm says who drives it now.
pub fn observation(app: &App, o: Observation) -> v1::Observation {
    v1::Observation {
        observation_id: o.id,
        timestamp_ns: o.timestamp_ns,
        arms: o
            .arms
            .into_iter()
            .map(|a| v1::ArmObservation {
                owner: app
                    .arm(&a.arm)
                    .map_or(0, |arm| v1::ControlSource::from(arm.driver()) as i32),
                robot_from_ee: Some(pose_to_proto(&a.robot_from_ee)),
                arm: a.arm,
                state: a.state,
                state_names: a.state_names,
                action_names: a.action_names,
                pending_steps: a
                    .pending_steps
                    .into_iter()
                    .map(|values| v1::ActionStep { values })
                    .collect(),
                pending_step_period_s: a.pending_step_period_s,
            })
            .collect(),
        frames: o
            .frames
            .into_iter()
            .map(|f| v1::CameraFrame {
                camera: f.camera,
                width: f.width,
                height: f.height,
                encoding: if f.jpeg {
                    v1::ImageEncoding::Jpeg
                } else {
                    v1::ImageEncoding::Rgb8
                } as i32,
                data: f.data,
                capture_time_ns: f.capture_time_ns,
                frame_seq: f.seq,
            })
            .collect(),
        task: o.task,
        inference_delay_s: o.inference_delay_s,
        inference_delay_steps: o.inference_delay_steps,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sync_counters_reach_the_wire() {
        let config = Config::embedded_default().unwrap();
        let status = RecorderStatus {
            phase: Phase::Recording,
            episode_index: 4,
            task: "pick".into(),
            operator: String::new(),
            frames_recorded: 120,
            duration_s: 6.0,
            held_ticks: 3,
            paused_ticks: 2,
            late_ticks: 7,
            dropped_frames: 1,
            episodes_saved: 4,
            warning: None,
            fps: 20,
            highlight_s: 10.0,
            highlight_buffered_s: 4.5,
            highlight_video_bytes: 123,
            version: 9,
        };
        let wire = recording_status(&status, &config);
        assert_eq!(
            (
                wire.highlight_s,
                wire.highlight_buffered_s,
                wire.highlight_video_bytes
            ),
            (10.0, 4.5, 123)
        );
        assert_eq!(
            (
                wire.held_ticks,
                wire.paused_ticks,
                wire.late_ticks,
                wire.dropped_frames
            ),
            (3, 2, 7, 1)
        );
        let summary = EpisodeSummary {
            index: 4,
            late_ticks: 5,
            dropped_frames: 6,
            paused_ticks: 2,
            ..EpisodeSummary::default()
        };
        let wire = episode(&summary);
        assert_eq!(
            (wire.paused_ticks, wire.late_ticks, wire.dropped_frames),
            (2, 5, 6)
        );
    }
}
