//! Turning server state (`TeleopFeedback`, `ArmState`, `RecordingStatus`) into the JSON the phone page and
//! rosbridge status subscribers read. Field names are short and stable: the page is the only consumer.

use phone2act_proto::v1::{ArmState, ControlSource, GateVerdict, Pose, RecordingStatus, TeleopFeedback};
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Fastest rate of plan previews to one page (5 Hz): feedback comes at the phone's sample rate and a preview
/// is a few hundred bytes, while a person reading a path needs no more.
pub const PREVIEW_PERIOD: Duration = Duration::from_millis(200);

/// Which feedback messages carry the plan preview: at most one per [`PREVIEW_PERIOD`], except that a plan
/// starting or ending is sent at once. A message without `preview` leaves the page's as it was.
#[derive(Debug, Default)]
pub struct PreviewPacer {
    /// When the last preview went out, and whether it showed a plan.
    last: Option<(Instant, bool)>,
}

impl PreviewPacer {
    /// `preview` (from [`preview_json`]) if it is due at `now`, else `None`.
    pub fn pace(&mut self, preview: Value, now: Instant) -> Option<Value> {
        let shows = !preview.is_null();
        let due = match self.last {
            None => true,
            Some((_, showed)) if showed != shows => true,
            Some((at, showed)) => showed && now.duration_since(at) >= PREVIEW_PERIOD,
        };
        due.then(|| {
            self.last = Some((now, shows));
            preview
        })
    }
}

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
        // `[recorder] highlight_s`: the seconds kept while idle, and how many are kept now (0 when off).
        "highlight_s": rec.highlight_s,
        "highlight_buffered_s": rec.highlight_buffered_s,
    })
}

/// The policy name of a `name:session` owner id.
fn policy_name(owner_id: &str) -> &str {
    owner_id.rsplit_once(':').map_or(owner_id, |(name, _)| name)
}

/// Who drives the arm: `teleop`, `policy` or `none`, and for a policy its name (the owner id is
/// `name:session`).
fn owner_parts(arm: &ArmState) -> (&'static str, &str) {
    match ControlSource::try_from(arm.owner).unwrap_or(ControlSource::Unspecified) {
        ControlSource::Teleop => ("teleop", ""),
        ControlSource::Policy => ("policy", policy_name(&arm.owner_id)),
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
        // The policy the operator took the arm from, waiting for a hand-back; empty when none waits.
        "waiting_policy": policy_name(&arm.waiting_policy_id),
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

/// The driving policy's plan preview for the phone page: `{"p": [[x, y, z], ...] (m, robot base frame),
/// "g": [gripper 0..1, ...], "dt_s": time between points}`, rounded to 0.1 mm and 0.001 (a display needs no
/// more, and the page's socket carries control); `null` when no plan plays.
pub fn preview_json(arm: &ArmState) -> Value {
    let Some(preview) = arm.plan_preview.as_ref().filter(|p| !p.positions_m.is_empty()) else {
        return Value::Null;
    };
    let round = |v: f64, per_unit: f64| (v * per_unit).round() / per_unit;
    json!({
        "p": preview
            .positions_m
            .iter()
            .map(|v| [round(v.x, 1e4), round(v.y, 1e4), round(v.z, 1e4)])
            .collect::<Vec<_>>(),
        "g": preview.grippers.iter().map(|&g| round(g, 1e3)).collect::<Vec<_>>(),
        "dt_s": round(preview.point_period_s, 1e3),
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
        let waiting = ArmState {
            owner: ControlSource::Teleop.into(),
            waiting_policy_id: "gr00t:n1.5:7".into(),
            ..ArmState::default()
        };
        assert_eq!(arm_json(&waiting)["waiting_policy"], "gr00t:n1.5");
        assert_eq!(arm_json(&phone)["waiting_policy"], "");
    }

    #[test]
    fn previews_go_out_at_most_every_period_but_a_plan_starting_or_ending_at_once() {
        let mut pacer = PreviewPacer::default();
        let t0 = Instant::now();
        let plan = json!({"p": [[0.0, 0.0, 0.0]]});
        assert_eq!(
            pacer.pace(Value::Null, t0),
            Some(Value::Null),
            "the first says there is none"
        );
        assert_eq!(
            pacer.pace(Value::Null, t0 + PREVIEW_PERIOD),
            None,
            "still none: nothing to say"
        );
        let t1 = t0 + Duration::from_millis(10);
        assert_eq!(pacer.pace(plan.clone(), t1), Some(plan.clone()), "a plan starts");
        assert_eq!(pacer.pace(plan.clone(), t1 + Duration::from_millis(100)), None);
        assert_eq!(pacer.pace(plan.clone(), t1 + PREVIEW_PERIOD), Some(plan.clone()));
        let t2 = t1 + PREVIEW_PERIOD + Duration::from_millis(1);
        assert_eq!(pacer.pace(Value::Null, t2), Some(Value::Null), "the plan ends");
    }

    #[test]
    fn the_preview_is_rounded_for_display_and_null_without_a_plan() {
        use phone2act_proto::v1::{PlanPreview, Vec3};
        assert_eq!(preview_json(&ArmState::default()), Value::Null);
        let arm = ArmState {
            plan_preview: Some(PlanPreview {
                positions_m: vec![
                    Vec3 {
                        x: 0.250_04,
                        y: -0.1,
                        z: 0.2,
                    },
                    Vec3 {
                        x: 0.260_06,
                        y: -0.1,
                        z: 0.2,
                    },
                ],
                grippers: vec![0.12345, 1.0],
                point_period_s: 0.1,
            }),
            ..ArmState::default()
        };
        assert_eq!(
            preview_json(&arm),
            json!({"p": [[0.25, -0.1, 0.2], [0.2601, -0.1, 0.2]], "g": [0.123, 1.0], "dt_s": 0.1})
        );
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
