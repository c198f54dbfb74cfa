//! Turning server state (`TeleopFeedback`, `ArmState`, `RecordingStatus`) into the JSON the phone page and
//! rosbridge status subscribers read. Field names are short and stable: the page is the only consumer.

use phone2act_proto::v1::{ArmState, ControlSource, GateVerdict, Pose, RecordingStatus, TeleopFeedback};
use serde_json::{Value, json};

/// Position and quaternion of a wire pose, identity when absent.
pub fn pose_parts(pose: Option<&Pose>) -> ([f64; 3], [f64; 4]) {
    let p = pose
        .and_then(|p| p.position_m.as_ref())
        .map_or([0.0; 3], |v| [v.x, v.y, v.z]);
    let q = pose
        .and_then(|p| p.orientation.as_ref())
        .map_or([0.0, 0.0, 0.0, 1.0], |q| [q.x, q.y, q.z, q.w]);
    (p, q)
}

fn verdict_name(verdict: i32) -> &'static str {
    match GateVerdict::try_from(verdict).unwrap_or(GateVerdict::Unspecified) {
        GateVerdict::Unspecified => "none",
        GateVerdict::Accepted => "accepted",
        GateVerdict::Clamped => "clamped",
        GateVerdict::RejectedJump => "rejected_jump",
        GateVerdict::RejectedInvalid => "rejected_invalid",
        GateVerdict::HeldStale => "held_stale",
    }
}

/// Recorder state as JSON.
pub fn recording_json(rec: Option<&RecordingStatus>) -> Value {
    let Some(rec) = rec else {
        return json!({"phase": "unknown"});
    };
    json!({
        "phase": phone2act_proto::convert_episode::phase_name(rec.phase),
        "task": rec.task,
        "episode": rec.episode_index,
        "frames": rec.frames_recorded,
        "duration_s": rec.duration_s,
        "saved": rec.episodes_saved,
        "warning": rec.warning,
        "upload": rec.upload_summary,
        // `[recorder] episode_time_s` / `reset_time_s`: the countdown (null when no limit applies).
        "remaining_s": rec.remaining_s,
        "resetting": rec.resetting,
    })
}

/// Who drives the arm: `teleop`, `policy` or `none`, and for a policy its name (the owner id is
/// `name:session`).
fn owner_parts(arm: &ArmState) -> (&'static str, &str) {
    match ControlSource::try_from(arm.owner).unwrap_or(ControlSource::Unspecified) {
        ControlSource::Teleop => ("teleop", ""),
        ControlSource::Policy => (
            "policy",
            arm.owner_id
                .rsplit_once(':')
                .map_or(arm.owner_id.as_str(), |(name, _)| name),
        ),
        ControlSource::None | ControlSource::Unspecified => ("none", ""),
    }
}

/// Arm state as JSON (no poses beyond the end-effector position).
pub fn arm_json(arm: &ArmState) -> Value {
    let decision = arm.last_decision.clone().unwrap_or_default();
    let (ee, _) = pose_parts(arm.robot_from_ee.as_ref());
    let (owner, policy) = owner_parts(arm);
    json!({
        "arm": arm.arm,
        "engaged": arm.engaged,
        "owner": owner,
        "policy": policy,
        "policy_loading": arm.policy_loading,
        "verdict": verdict_name(decision.verdict),
        "reason": decision.reason,
        "workspace_clamped": decision.workspace_clamped,
        "velocity_limited": decision.velocity_limited,
        "gripper": arm.gripper_position,
        "gripper_target": arm.gripper_target,
        "ee_m": ee,
        "rejected": arm.commands_rejected,
        "clamped": arm.commands_clamped,
        "sent": arm.commands_sent,
        "health_message": arm.health_message,
    })
}

/// One feedback message for the phone page.
pub fn page_feedback(arm: &str, fb: &TeleopFeedback, gateway_superseded: u64) -> Value {
    let mut v = json!({
        "type": "feedback",
        "arm": arm,
        "seq": fb.echoed_seq,
        "t_ns": fb.echoed_capture_time_ns,
        "error": fb.error,
        "superseded": fb.superseded_samples + gateway_superseded,
        "recording": recording_json(fb.recording.as_ref()),
    });
    if let Some(state) = &fb.arm_state {
        v["state"] = arm_json(state);
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_proto::v1::GateDecision;

    #[test]
    fn the_page_learns_who_drives_and_whether_a_policy_is_still_loading() {
        let policy = ArmState {
            owner: ControlSource::Policy.into(),
            owner_id: "gr00t:n1.5:7".into(),
            policy_loading: true,
            ..ArmState::default()
        };
        let v = arm_json(&policy);
        assert_eq!(
            (v["owner"].as_str(), v["policy"].as_str()),
            (Some("policy"), Some("gr00t:n1.5"))
        );
        assert_eq!(v["policy_loading"], true);
        let phone = ArmState {
            owner: ControlSource::Teleop.into(),
            owner_id: "3".into(),
            ..ArmState::default()
        };
        let v = arm_json(&phone);
        assert_eq!(
            (v["owner"].as_str(), v["policy"].as_str()),
            (Some("teleop"), Some(""))
        );
        assert_eq!(arm_json(&ArmState::default())["owner"], "none");
    }

    #[test]
    fn feedback_names_the_verdict_and_phase() {
        let fb = TeleopFeedback {
            echoed_seq: 9,
            echoed_capture_time_ns: 123,
            arm_state: Some(ArmState {
                arm: "left".into(),
                engaged: true,
                last_decision: Some(GateDecision {
                    verdict: GateVerdict::RejectedJump.into(),
                    reason: "too far".into(),
                    ..GateDecision::default()
                }),
                commands_rejected: 4,
                ..ArmState::default()
            }),
            recording: Some(RecordingStatus {
                phase: phone2act_proto::v1::RecordingPhase::Recording.into(),
                task: "pick".into(),
                upload_summary: "2 uploaded, 1 pending".into(),
                ..RecordingStatus::default()
            }),
            superseded_samples: 1,
            ..TeleopFeedback::default()
        };
        let v = page_feedback("left", &fb, 2);
        assert_eq!(v["seq"], 9);
        assert_eq!(v["superseded"], 3);
        assert_eq!(v["state"]["verdict"], "rejected_jump");
        assert_eq!(v["state"]["rejected"], 4);
        assert_eq!(v["recording"]["phase"], "recording");
        assert_eq!(v["recording"]["task"], "pick");
        assert_eq!(v["recording"]["upload"], "2 uploaded, 1 pending");
    }
}
