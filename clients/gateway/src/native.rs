//! The phone page's own JSON protocol over `wss://host:8443/ws`.
//!
//! Page → gateway:
//! - `{"type":"hello","arm":"left","take_over":false}` picks (or switches) the arm;
//! - `{"type":"release"}` ends this socket's stream and frees its arm (the page hands the arm to a headset
//!   controller's own socket);
//! - `{"type":"sample","seq":1,"t_ns":…,"pose":{"p":[x,y,z],"q":[x,y,z,w]},"tracking":"tracking","buttons":[…]}`
//!   with buttons `{"clutch":"engage"|"disengage"|"toggle"}`, `{"gripper":"toggle"}` or `{"gripper":0.4}`,
//!   `{"record":"start","task":"…"}`, `{"record":"stop"}` (with `"outcome":"success"` or `"failure"`, the
//!   operator's verdict on the episode), `{"record":"discard"}`, `{"record":"highlight","task":"…"}` (save the
//!   last seconds the recorder kept while idle as an episode, optionally with an `"outcome"`).
//!
//! - `{"type":"video_offer","camera":"front","sdp":"…","host":"192.168.1.20"}` asks for the camera's live
//!   WebRTC video (see `webrtc`; `host` is where the page reached the gateway), `{"type":"video_off"}` ends it;
//!   `{"type":"clock","t_page_ms":…}` is answered with the gateway's wall clock for the page's clock offset;
//! - `{"type":"hand_back"}` hands the arm back to the policy waiting for it (the feedback's `state.waiting_policy`
//!   names it): the page's teleop stream carries it as a `HandBackCommand` button; nothing moves until the
//!   policy's next chunk answering a newer observation;
//! - `{"type":"preview","camera":"front","max_fps":5,"width":320}` turns the camera preview on (see
//!   `web_preview`), `{"type":"preview_off"}` off; `{"type":"preview_ack"}` says a preview frame arrived.
//!
//! Gateway → page: `welcome` (arms, cameras, headset controller → arm map), `session` (open/retrying/refused),
//! `feedback` (with `preview`, the driving policy's plan, at most 5 times a second: see
//! [`crate::feedback::PreviewPacer`]), `error`, `preview`
//! (`on` with the settings, `off` with the reason), and while the preview is on, binary messages of one JPEG.

use crate::conn::{Handler, Wiring};
use crate::feedback::{PreviewPacer, page_feedback, preview_json};
use crate::rosbridge::parse_json;
use crate::session::{Session, SessionEvent};
use crate::shared::Shared;
use crate::web_preview::{self, PreviewRequest};
use phone2act_proto::v1::{
    ButtonEvent, EpisodeOutcome, PhoneSample, Pose, TrackingState, clutch_command, record_command,
};
use phone2act_proto::{MAX_TASK_BYTES, buttons};
use serde::Deserialize;
use serde_json::{Value, json};
use std::sync::Arc;
use tokio::task::JoinHandle;

#[derive(Debug, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
enum PageMsg {
    Hello {
        arm: String,
        #[serde(default)]
        take_over: bool,
    },
    Sample {
        seq: u64,
        #[serde(default)]
        t_ns: f64,
        #[serde(default)]
        pose: Option<PagePose>,
        #[serde(default)]
        tracking: Option<String>,
        #[serde(default)]
        buttons: Vec<Value>,
    },
    Preview(PreviewRequest),
    PreviewOff,
    HandBack {
        #[serde(default)]
        seq: u64,
    },
    PreviewAck,
    Release,
    VideoOffer {
        camera: String,
        sdp: String,
        #[serde(default)]
        host: Option<String>,
    },
    VideoOff,
    Clock {
        t_page_ms: f64,
    },
}

#[derive(Debug, Deserialize)]
struct PagePose {
    p: [Option<f64>; 3],
    q: [Option<f64>; 4],
}

fn finite<const N: usize>(values: [Option<f64>; N]) -> Option<[f64; N]> {
    let mut out = [0.0; N];
    for (o, v) in out.iter_mut().zip(values) {
        *o = v.filter(|x| x.is_finite())?;
    }
    Some(out)
}

fn parse_button(v: &Value) -> Result<ButtonEvent, String> {
    if let Some(c) = v.get("clutch") {
        let kind = match c.as_str() {
            Some("engage") => clutch_command::Kind::Engage,
            Some("disengage") => clutch_command::Kind::Disengage,
            Some("toggle") => clutch_command::Kind::Toggle,
            _ => return Err(format!("clutch must be engage, disengage or toggle, got {c}")),
        };
        Ok(buttons::clutch(kind))
    } else if let Some(g) = v.get("gripper") {
        match (g.as_str(), g.as_f64()) {
            (Some("toggle"), _) => Ok(buttons::gripper_toggle()),
            (_, Some(position)) if (0.0..=1.0).contains(&position) => Ok(buttons::gripper_set(position)),
            _ => Err(format!(
                "gripper must be \"toggle\" or a number in [0, 1], got {g}"
            )),
        }
    } else if let Some(r) = v.get("record") {
        let task = v.get("task").and_then(Value::as_str).unwrap_or_default();
        let check_task = |what: &str| {
            if task.trim().is_empty() {
                return Err(format!("record {what} needs a task"));
            }
            if task.len() > MAX_TASK_BYTES {
                return Err(format!("task text is longer than {MAX_TASK_BYTES} bytes"));
            }
            Ok(())
        };
        let outcome = || match v.get("outcome").map(|o| (o, o.as_str())) {
            None => Ok(EpisodeOutcome::Unspecified),
            Some((_, Some("success"))) => Ok(EpisodeOutcome::Success),
            Some((_, Some("failure"))) => Ok(EpisodeOutcome::Failure),
            Some((o, _)) => Err(format!("outcome must be success or failure, got {o}")),
        };
        let kind = match r.as_str() {
            Some("start") => {
                check_task("start")?;
                record_command::Kind::Start
            }
            Some("stop") => return Ok(buttons::record_stop_with(outcome()?)),
            Some("highlight") => {
                check_task("highlight")?;
                return Ok(buttons::save_highlight(task, outcome()?));
            }
            Some("discard") => record_command::Kind::Discard,
            _ => {
                return Err(format!(
                    "record must be start, stop, highlight or discard, got {r}"
                ));
            }
        };
        Ok(buttons::record(kind, task))
    } else {
        Err(format!("unknown button {v}"))
    }
}

/// Converts a page sample into a wire sample, or says what is wrong with it.
fn to_sample(
    seq: u64,
    t_ns: f64,
    pose: Option<PagePose>,
    tracking: Option<&str>,
    buttons: &[Value],
) -> Result<PhoneSample, String> {
    let mut sample = PhoneSample {
        seq,
        capture_time_ns: if t_ns.is_finite() { t_ns as i64 } else { 0 },
        client_name: "phone-web".into(),
        ..PhoneSample::default()
    };
    if let Some(pose) = pose {
        let p = finite(pose.p).ok_or("pose position contains NaN, infinity or null")?;
        let q = finite(pose.q).ok_or("pose orientation contains NaN, infinity or null")?;
        // Refused here, not only by the server: samples fold latest-wins on the way, so a newer pose could
        // replace this one before the server reads it and its error would be lost.
        phone2act_proto::convert_arm::check_wire_pose(p, q).map_err(|e| format!("pose refused: {e}"))?;
        // Raw WebXR viewer pose (+X right, +Y up, -Z forward): the server's planner maps axes.
        sample.tracking_from_phone = Some(Pose::from_parts(p, q));
        sample.tracking = match tracking.unwrap_or("tracking") {
            "tracking" => TrackingState::Tracking,
            "limited" => TrackingState::Limited,
            "lost" => TrackingState::Lost,
            other => return Err(format!("tracking must be tracking, limited or lost, got {other}")),
        }
        .into();
    } else if tracking == Some("lost") {
        sample.tracking = TrackingState::Lost.into();
    }
    sample.buttons = buttons.iter().map(parse_button).collect::<Result<_, _>>()?;
    Ok(sample)
}

/// Reads one page message. A well-formed one (every sample) is read in one pass, straight into its type; the
/// rest goes the tolerant way ([`parse_json`], then the type), which accepts what that one refuses (the bare
/// `NaN` of a broken page, a repeated key: the last one counts) and words the error.
fn parse_page_msg(text: &str) -> Result<PageMsg, String> {
    serde_json::from_str::<PageMsg>(text).or_else(|_| {
        parse_json(text)
            .map_err(|e| e.0)
            .and_then(|v| serde_json::from_value::<PageMsg>(v).map_err(|e| format!("bad message: {e}")))
    })
}

/// State of one page socket.
pub(crate) struct PageHandler {
    shared: Arc<Shared>,
    wiring: Wiring,
    session: Option<Session>,
    /// The camera preview's fetch task, while the page wants one.
    preview: Option<JoinHandle<()>>,
    /// The page's WebRTC viewer task, while it watches.
    video: Option<JoinHandle<()>>,
    /// Where the page's socket comes from (a page on this machine gets video without congestion control).
    peer: std::net::IpAddr,
    /// Which feedback carries the plan preview.
    plan_preview: PreviewPacer,
    close: bool,
}

impl PageHandler {
    pub(crate) fn new(shared: Arc<Shared>, wiring: Wiring, peer: std::net::IpAddr) -> Self {
        Self {
            shared,
            wiring,
            session: None,
            preview: None,
            video: None,
            peer,
            plan_preview: PreviewPacer::default(),
            close: false,
        }
    }

    /// Tells the page which arms (for the picker) and cameras (for the preview) exist; called once after
    /// connecting.
    pub(crate) fn welcome(&self, arms: &[String], cameras: &[String]) {
        self.wiring.out.text(
            json!({
                "type": "welcome",
                "arms": arms,
                "cameras": cameras,
                "default_arm": self.shared.config.default_arm,
                "rosbridge_port": self.shared.rosbridge_port,
                "controllers": self.shared.config.controllers,
                "video": self.shared.config.video.enabled,
            })
            .to_string(),
        );
    }

    fn error(&self, message: &str, seq: Option<u64>) {
        self.wiring
            .out
            .text(json!({"type": "error", "message": message, "seq": seq}).to_string());
    }

    fn start(&mut self, arm: &str, take_over: bool) {
        // Ends the old stream first so the server frees that arm before the new one is claimed.
        self.session = None;
        let session = crate::session::start(&self.shared.upstream, arm, self.wiring.session_events.clone());
        // A first sample without a pose claims the arm right away, so the page learns at once whether the
        // arm exists and is free.
        session.send(PhoneSample {
            take_over,
            client_name: "phone-web".into(),
            ..PhoneSample::default()
        });
        self.session = Some(session);
    }

    fn start_video(&mut self, camera: &str, sdp: &str, host: Option<&str>) {
        self.stop_video();
        let reply = if camera.is_empty() || camera.len() > 64 {
            Err("video camera name must be 1 to 64 characters".to_owned())
        } else if let Some(ip) = crate::webrtc::bind_ip(
            host,
            self.shared.config.https_listen,
            self.shared.config.public_host.as_deref(),
        ) {
            crate::webrtc::start_viewer(
                &self.shared.video,
                &self.shared.upstream,
                camera,
                sdp,
                (ip, self.peer),
                self.wiring.out.clone(),
            )
        } else {
            Err(
                "no address for the video: open the page by IP address or set [gateway] public_host"
                    .to_owned(),
            )
        };
        let text = match reply {
            Ok((answer, task)) => {
                self.video = Some(task);
                json!({"type": "video_answer", "camera": camera, "sdp": answer})
            }
            Err(message) => json!({"type": "video", "state": "error", "camera": camera, "message": message}),
        };
        self.wiring.out.text(text.to_string());
    }

    fn stop_video(&mut self) {
        if let Some(task) = self.video.take() {
            task.abort();
        }
    }

    fn stop_preview(&mut self) {
        if let Some(task) = self.preview.take() {
            task.abort();
        }
        self.wiring.preview.close();
    }
}

impl Drop for PageHandler {
    fn drop(&mut self) {
        self.stop_preview();
        self.stop_video();
    }
}

impl Handler for PageHandler {
    fn on_text(&mut self, text: &str) {
        match parse_page_msg(text) {
            Ok(PageMsg::Hello { arm, take_over }) => {
                if arm.is_empty() || arm.len() > 64 {
                    self.error("arm name must be 1 to 64 characters", None);
                } else {
                    self.start(&arm, take_over);
                }
            }
            Ok(PageMsg::Sample {
                seq,
                t_ns,
                pose,
                tracking,
                buttons,
            }) => match to_sample(seq, t_ns, pose, tracking.as_deref(), &buttons) {
                Ok(sample) => {
                    if self.session.as_ref().is_none_or(Session::is_finished) {
                        let arm = self
                            .session
                            .as_ref()
                            .map_or_else(|| self.shared.config.default_arm.clone(), |s| s.arm().to_owned());
                        self.start(&arm, false);
                    }
                    if let Some(session) = &self.session {
                        session.send(sample);
                    }
                }
                Err(e) => self.error(&e, Some(seq)),
            },
            Ok(PageMsg::Preview(request)) => match request.check() {
                Ok(params) => {
                    self.stop_preview();
                    let (runtime, upstream) = self.shared.camera_runtime();
                    self.preview = Some(web_preview::spawn(
                        &runtime,
                        upstream,
                        params,
                        self.wiring.preview.clone(),
                        self.wiring.out.clone(),
                    ));
                }
                // A bad request leaves a running preview as it was.
                Err(e) => self.error(&e, None),
            },
            Ok(PageMsg::PreviewOff) => {
                self.stop_preview();
                self.wiring
                    .out
                    .text(json!({"type": "preview", "state": "off", "reason": "asked"}).to_string());
            }
            Ok(PageMsg::PreviewAck) => self.wiring.preview.ack(),
            Ok(PageMsg::HandBack { seq }) => match self.session.as_ref().filter(|s| !s.is_finished()) {
                Some(session) => session.send(PhoneSample {
                    seq,
                    client_name: "phone-web".into(),
                    buttons: vec![buttons::hand_back()],
                    ..PhoneSample::default()
                }),
                None => self.error(
                    "no arm to hand back: the page drives none (send hello first)",
                    None,
                ),
            },
            // Dropping the session ends its stream, which frees the arm on the server.
            Ok(PageMsg::Release) => self.session = None,
            Ok(PageMsg::VideoOffer { camera, sdp, host }) => self.start_video(&camera, &sdp, host.as_deref()),
            Ok(PageMsg::VideoOff) => self.stop_video(),
            Ok(PageMsg::Clock { t_page_ms }) => {
                let now_ms = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0.0, |d| d.as_secs_f64() * 1e3);
                self.wiring.out.text(
                    json!({"type": "clock", "t_page_ms": t_page_ms, "t_gateway_unix_ms": now_ms}).to_string(),
                );
            }
            Err(e) => self.error(&e, None),
        }
    }

    fn on_oversized(&mut self, len: usize) {
        self.error(
            &format!(
                "message of {len} bytes exceeds the limit of {} bytes; ignored",
                self.shared.config.max_message_bytes
            ),
            None,
        );
    }

    fn on_session_event(&mut self, event: SessionEvent) {
        let text = match event {
            SessionEvent::Open { arm } => json!({"type": "session", "state": "open", "arm": arm}),
            SessionEvent::Feedback { arm, feedback } => {
                let superseded = self.session.as_ref().map_or(0, Session::superseded);
                let mut v = page_feedback(&arm, &feedback, superseded);
                if let Some(state) = &feedback.arm_state
                    && let Some(preview) = self
                        .plan_preview
                        .pace(preview_json(state), std::time::Instant::now())
                {
                    v["preview"] = preview;
                }
                v
            }
            SessionEvent::Retrying {
                arm,
                message,
                retry_in,
            } => json!({
                "type": "session", "state": "retrying", "arm": arm, "message": message,
                "retry_in_s": retry_in.as_secs_f64(),
            }),
            SessionEvent::Refused { arm, code, message } => {
                if self.session.as_ref().is_some_and(|s| s.arm() == arm) {
                    self.session = None;
                }
                json!({"type": "session", "state": "refused", "arm": arm, "code": format!("{code:?}"), "message": message})
            }
        };
        self.wiring.out.text(text.to_string());
    }

    fn wants_close(&self) -> bool {
        self.close
    }
}

#[cfg(test)]
// Values pass through untouched: exact equality is the property under test.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;

    fn sample(text: &str) -> Result<PhoneSample, String> {
        let PageMsg::Sample {
            seq,
            t_ns,
            pose,
            tracking,
            buttons,
        } = serde_json::from_value(parse_json(text).unwrap()).map_err(|e| e.to_string())?
        else {
            panic!("not a sample")
        };
        to_sample(seq, t_ns, pose, tracking.as_deref(), &buttons)
    }

    #[test]
    fn a_page_sample_becomes_a_phone_sample() {
        let s = sample(
            r#"{"type":"sample","seq":4,"t_ns":1.5e9,"pose":{"p":[0.1,1.2,-0.3],"q":[0,0,0,1]},
                "buttons":[{"clutch":"engage"},{"gripper":"toggle"},{"record":"start","task":"pick the ball"}]}"#,
        )
        .unwrap();
        assert_eq!(s.seq, 4);
        assert_eq!(s.capture_time_ns, 1_500_000_000);
        assert_eq!(s.tracking, TrackingState::Tracking as i32);
        let p = s.tracking_from_phone.unwrap().position_m.unwrap();
        assert_eq!(
            [p.x, p.y, p.z],
            [0.1, 1.2, -0.3],
            "the gateway must not remap axes"
        );
        assert_eq!(s.buttons.len(), 3);
        let Some(phone2act_proto::v1::button_event::Event::Record(r)) = &s.buttons[2].event else {
            panic!()
        };
        assert_eq!(r.task, "pick the ball");
    }

    #[test]
    fn the_one_pass_read_and_the_tolerant_one_agree() {
        let text = r#"{"type":"sample","seq":9,"t_ns":2e9,"pose":{"p":[0.1,0.2,0.3],"q":[0,0,0,1]},"buttons":[{"clutch":"engage"}]}"#;
        let PageMsg::Sample { seq, t_ns, pose, .. } = parse_page_msg(text).unwrap() else {
            panic!("not a sample")
        };
        assert_eq!((seq, t_ns), (9, 2e9));
        assert_eq!(pose.unwrap().p, [Some(0.1), Some(0.2), Some(0.3)]);
        // What only the tolerant read accepts still comes through it: a repeated key (the last counts) and
        // Python's bare NaN, which reaches `to_sample` as null and is refused there with its field named.
        let PageMsg::Sample { seq, .. } = parse_page_msg(r#"{"type":"sample","seq":1,"seq":2}"#).unwrap()
        else {
            panic!("not a sample")
        };
        assert_eq!(seq, 2);
        let Ok(PageMsg::Sample { pose, .. }) =
            parse_page_msg(r#"{"type":"sample","seq":1,"pose":{"p":[NaN,0,0],"q":[0,0,0,1]}}"#)
        else {
            panic!("a NaN sample must parse, to be refused with a reason")
        };
        assert_eq!(pose.unwrap().p[0], None);
        let bad = parse_page_msg(r#"{"type":"dance"}"#).unwrap_err();
        assert!(bad.starts_with("bad message"), "{bad}");
        assert!(parse_page_msg("{").unwrap_err().contains("malformed JSON"));
    }

    #[test]
    fn a_stop_carries_the_operators_outcome() {
        let outcome = |text: &str| -> Result<i32, String> {
            let s = sample(text)?;
            match &s.buttons[0].event {
                Some(phone2act_proto::v1::button_event::Event::Record(r)) => Ok(r.outcome),
                other => panic!("{other:?}"),
            }
        };
        let stop =
            |extra: &str| format!(r#"{{"type":"sample","seq":1,"buttons":[{{"record":"stop"{extra}}}]}}"#);
        assert_eq!(outcome(&stop("")), Ok(EpisodeOutcome::Unspecified as i32));
        assert_eq!(
            outcome(&stop(r#","outcome":"success""#)),
            Ok(EpisodeOutcome::Success as i32)
        );
        assert_eq!(
            outcome(&stop(r#","outcome":"failure""#)),
            Ok(EpisodeOutcome::Failure as i32)
        );
        let bad = outcome(&stop(r#","outcome":"maybe""#)).unwrap_err();
        assert!(bad.contains("success or failure"), "{bad}");
    }

    #[test]
    fn bad_samples_are_refused_with_a_reason() {
        let nan = sample(r#"{"type":"sample","seq":1,"pose":{"p":[NaN,0,0],"q":[0,0,0,1]}}"#).unwrap_err();
        assert!(nan.contains("NaN"), "{nan}");
        let null = sample(r#"{"type":"sample","seq":1,"pose":{"p":[0,0,0],"q":[null,0,0,1]}}"#).unwrap_err();
        assert!(null.contains("orientation"), "{null}");
        assert!(sample(r#"{"type":"sample","seq":1,"buttons":[{"record":"start","task":" "}]}"#).is_err());
        assert!(sample(r#"{"type":"sample","seq":1,"buttons":[{"gripper":2}]}"#).is_err());
        assert!(sample(r#"{"type":"sample","seq":1,"buttons":[{"jump":true}]}"#).is_err());
        assert!(serde_json::from_value::<PageMsg>(json!({"type": "dance"})).is_err());
    }

    #[test]
    fn a_non_unit_quaternion_is_refused_here_with_the_servers_tolerance() {
        // Refused by the gateway itself: a newer sample folded over it would hide the server's error.
        let err = sample(r#"{"type":"sample","seq":1,"pose":{"p":[0,0,0],"q":[0,0,0,2]}}"#).unwrap_err();
        assert!(err.contains("quaternion norm 2"), "{err}");
        // Within the tolerance the server renormalises, so the gateway passes it on.
        assert!(sample(r#"{"type":"sample","seq":1,"pose":{"p":[0,0,0],"q":[0,0,0,1.0009]}}"#).is_ok());
        assert!(sample(r#"{"type":"sample","seq":1,"pose":{"p":[0,0,0],"q":[0,0,0,1.0011]}}"#).is_err());
    }
}
