//! rosbridge v2 wire format: parsing what clients send (ops, type and topic names, the message types the
//! Phone2Act app uses) and building what the gateway sends back (`publish`, `status`, `service_response`).
//!
//! Parsing is lenient where real clients differ (extra keys such as the app's `type` on `publish`, ints for
//! floats, `sec/nanosec` or ROS 1 `secs/nsecs`, `pkg/Type` or `pkg/msg/Type`, Python's bare `NaN`) and strict
//! where a value would reach the robot (every pose component must be a finite number).

use serde_json::{Map, Value, json};
use std::borrow::Cow;

/// A parse or validation error, phrased for the client.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct WireError(pub String);

fn err<T>(msg: impl Into<String>) -> Result<T, WireError> {
    Err(WireError(msg.into()))
}

/// One client → server rosbridge operation.
#[derive(Debug, Clone, PartialEq)]
pub enum Op {
    Advertise {
        topic: String,
        msg_type: String,
    },
    Unadvertise {
        topic: String,
    },
    Publish {
        topic: String,
        msg_type: Option<String>,
        msg: Value,
    },
    Subscribe {
        topic: String,
        sub_id: Option<String>,
        msg_type: Option<String>,
        throttle_rate_ms: u64,
    },
    Unsubscribe {
        topic: String,
        sub_id: Option<String>,
    },
    CallService {
        service: String,
        /// The request's fields (`null` when the client sent none).
        args: Value,
    },
    SetLevel {
        level: StatusLevel,
    },
    /// `auth`, `advertise_service`, ...: accepted and ignored, as rosbridge does.
    Ignored,
}

/// A parsed message: the op and the `id` to echo in replies.
#[derive(Debug, Clone, PartialEq)]
pub struct Incoming {
    pub id: Option<Value>,
    pub op: Op,
}

/// `set_level` levels, ordered by severity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum StatusLevel {
    Info,
    Warning,
    Error,
    None,
}

impl StatusLevel {
    /// Parses a wire name.
    pub fn parse(text: &str) -> Option<Self> {
        Some(match text {
            "info" => Self::Info,
            "warning" => Self::Warning,
            "error" => Self::Error,
            "none" => Self::None,
            _ => return None,
        })
    }

    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Info => "info",
            Self::Warning => "warning",
            Self::Error => "error",
            Self::None => "none",
        }
    }
}

/// Parses one text frame. The error carries the `id` when one could be read, so the reply can echo it.
pub fn parse(text: &str) -> Result<Incoming, (Option<Value>, WireError)> {
    let value = parse_json(text).map_err(|e| (None, e))?;
    let Value::Object(mut obj) = value else {
        return Err((
            None,
            WireError("a rosbridge message must be a JSON object".into()),
        ));
    };
    let id = obj.remove("id");
    match parse_op(obj, id.as_ref()) {
        Ok(op) => Ok(Incoming { id, op }),
        Err(e) => Err((id, e)),
    }
}

/// Parses JSON, accepting the bare `NaN`/`Infinity` tokens Python's `json` emits so that the error can say
/// which field was not finite instead of "malformed JSON".
pub fn parse_json(text: &str) -> Result<Value, WireError> {
    match serde_json::from_str::<Value>(text) {
        Ok(v) => Ok(v),
        Err(first) => {
            let Cow::Owned(cleaned) = replace_non_finite_tokens(text) else {
                return err(format!("malformed JSON: {first}"));
            };
            serde_json::from_str::<Value>(&cleaned).or_else(|_| err(format!("malformed JSON: {first}")))
        }
    }
}

/// Replaces `NaN`, `Infinity` and `-Infinity` outside strings with `null`.
fn replace_non_finite_tokens(text: &str) -> Cow<'_, str> {
    const TOKENS: [&str; 3] = ["-Infinity", "Infinity", "NaN"];
    let bytes = text.as_bytes();
    let mut out: Option<String> = None;
    let mut in_string = false;
    let mut escaped = false;
    let mut copied_to = 0;
    let mut i = 0;
    while i < bytes.len() {
        let b = bytes[i];
        if in_string {
            if escaped {
                escaped = false;
            } else if b == b'\\' {
                escaped = true;
            } else if b == b'"' {
                in_string = false;
            }
            i += 1;
            continue;
        }
        if b == b'"' {
            in_string = true;
            i += 1;
            continue;
        }
        // Compared as bytes: `i` may sit inside a multi-byte character (a stray emoji outside a string).
        // A match starts with an ASCII byte, so `copied_to` and `i` are char boundaries whenever text is cut.
        if let Some(token) = TOKENS.iter().find(|t| bytes[i..].starts_with(t.as_bytes())) {
            let o = out.get_or_insert_with(|| String::with_capacity(text.len()));
            o.push_str(text.get(copied_to..i).unwrap_or_default());
            o.push_str("null");
            i += token.len();
            copied_to = i;
            continue;
        }
        i += 1;
    }
    match out {
        Some(mut o) => {
            o.push_str(text.get(copied_to..).unwrap_or_default());
            Cow::Owned(o)
        }
        None => Cow::Borrowed(text),
    }
}

fn str_field<'a>(obj: &'a Map<String, Value>, key: &str) -> Result<&'a str, WireError> {
    match obj.get(key) {
        Some(Value::String(s)) => Ok(s),
        Some(_) => err(format!("field '{key}' must be a string")),
        None => err(format!("missing field '{key}'")),
    }
}

fn opt_str(obj: &Map<String, Value>, key: &str) -> Option<String> {
    obj.get(key).and_then(Value::as_str).map(str::to_owned)
}

/// `obj` is taken apart rather than copied: a published message moves into the [`Op`] as it was parsed.
fn parse_op(mut obj: Map<String, Value>, id: Option<&Value>) -> Result<Op, WireError> {
    let op = match obj.remove("op") {
        Some(Value::String(op)) => op,
        Some(_) => return err("field 'op' must be a string"),
        None => return err("missing field 'op'"),
    };
    let obj = &mut obj;
    Ok(match op.as_str() {
        "advertise" => Op::Advertise {
            topic: normalize_topic(str_field(obj, "topic")?)?,
            msg_type: normalize_type(str_field(obj, "type")?)?,
        },
        "unadvertise" => Op::Unadvertise {
            topic: normalize_topic(str_field(obj, "topic")?)?,
        },
        "publish" => Op::Publish {
            topic: normalize_topic(str_field(obj, "topic")?)?,
            // Not in the spec, but the Phone2Act app sends it; rosbridge ignores it, we use it as a check.
            msg_type: opt_str(obj, "type").map(|t| normalize_type(&t)).transpose()?,
            msg: match obj.remove("msg") {
                None => Value::Object(Map::new()),
                Some(v @ Value::Object(_)) => v,
                Some(_) => return err("field 'msg' must be a JSON object"),
            },
        },
        "subscribe" => Op::Subscribe {
            topic: normalize_topic(str_field(obj, "topic")?)?,
            sub_id: id.map(id_text),
            msg_type: opt_str(obj, "type").map(|t| normalize_type(&t)).transpose()?,
            throttle_rate_ms: obj.get("throttle_rate").and_then(Value::as_u64).unwrap_or(0),
        },
        "unsubscribe" => Op::Unsubscribe {
            topic: normalize_topic(str_field(obj, "topic")?)?,
            sub_id: id.map(id_text),
        },
        "call_service" => Op::CallService {
            service: str_field(obj, "service")?.to_owned(),
            args: obj.remove("args").unwrap_or(Value::Null),
        },
        "set_level" => Op::SetLevel {
            level: StatusLevel::parse(str_field(obj, "level")?)
                .ok_or_else(|| WireError("level must be one of info, warning, error, none".into()))?,
        },
        "auth" | "advertise_service" | "unadvertise_service" | "service_response" => Op::Ignored,
        "fragment" | "png" => return err(format!("op '{op}' is not supported by this gateway")),
        other => return err(format!("unknown op '{other}'")),
    })
}

fn id_text(id: &Value) -> String {
    match id {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// `pkg/Type` and `pkg/msg/Type` → `pkg/Type`.
pub fn normalize_type(msg_type: &str) -> Result<String, WireError> {
    let parts: Vec<&str> = msg_type.split('/').collect();
    let valid = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    match parts.as_slice() {
        [pkg, name] | [pkg, "msg", name] if valid(pkg) && valid(name) => Ok(format!("{pkg}/{name}")),
        _ => err(format!(
            "invalid message type '{msg_type}' (expected pkg/Type or pkg/msg/Type)"
        )),
    }
}

/// Makes a topic absolute and checks it against the ROS 2 naming rules.
pub fn normalize_topic(topic: &str) -> Result<String, WireError> {
    let abs = if topic.starts_with('/') {
        Cow::Borrowed(topic)
    } else {
        Cow::Owned(format!("/{topic}"))
    };
    let ok = abs.len() > 1
        && !abs.ends_with('/')
        && !abs.contains("//")
        && abs
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/');
    if ok {
        Ok(abs.into_owned())
    } else {
        err(format!("invalid topic name '{topic}'"))
    }
}

/// A phone pose from `geometry_msgs/PoseStamped`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    /// Header stamp in nanoseconds, if the message had one.
    pub stamp_ns: Option<i64>,
    pub position_m: [f64; 3],
    pub quat_xyzw: [f64; 4],
}

fn get_path<'a>(v: &'a Value, path: &[&str]) -> Option<&'a Value> {
    path.iter().try_fold(v, |v, key| v.get(key))
}

fn finite(v: &Value, path: &[&str]) -> Result<f64, WireError> {
    match get_path(v, path) {
        Some(Value::Number(n)) => n
            .as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| WireError(format!("{} is not a finite number", path.join(".")))),
        None => err(format!("missing field {}", path.join("."))),
        // Python's NaN arrives here as null (see parse_json), JavaScript's as null too.
        Some(Value::Null) => err(format!("{} is NaN, infinite or null", path.join("."))),
        Some(_) => err(format!("{} must be a number", path.join("."))),
    }
}

/// Reads a `builtin_interfaces/Time` in ROS 2 (`sec`, `nanosec`) or ROS 1 (`secs`, `nsecs`) spelling.
fn parse_stamp(stamp: &Value) -> Result<i64, WireError> {
    let int = |keys: [&str; 2]| -> Result<i64, WireError> {
        match keys.iter().find_map(|k| stamp.get(k)) {
            None => Ok(0),
            Some(Value::Number(n)) => n
                .as_i64()
                .or_else(|| {
                    n.as_f64()
                        .filter(|f| f.fract() == 0.0 && f.is_finite())
                        .map(|f| f as i64)
                })
                .ok_or_else(|| WireError(format!("header.stamp.{} must be an integer", keys[0]))),
            Some(_) => err(format!("header.stamp.{} must be an integer", keys[0])),
        }
    };
    let sec = int(["sec", "secs"])?;
    let nanosec = int(["nanosec", "nsecs"])?;
    sec.checked_mul(1_000_000_000)
        .and_then(|s| s.checked_add(nanosec))
        .ok_or_else(|| WireError("header.stamp out of range".into()))
}

/// Parses the `msg` of a `geometry_msgs/PoseStamped` publish.
pub fn parse_pose_stamped(msg: &Value) -> Result<StampedPose, WireError> {
    let stamp_ns = match get_path(msg, &["header", "stamp"]) {
        // rosbridge accepts the literal "now".
        None | Some(Value::String(_)) => None,
        Some(stamp) => Some(parse_stamp(stamp)?),
    };
    let p = |axis| finite(msg, &["pose", "position", axis]);
    let q = |axis| finite(msg, &["pose", "orientation", axis]);
    let position_m = [p("x")?, p("y")?, p("z")?];
    let quat_xyzw = [q("x")?, q("y")?, q("z")?, q("w")?];
    Ok(StampedPose {
        stamp_ns,
        position_m,
        quat_xyzw,
    })
}

/// Parses the `data` of a `std_msgs/Int32MultiArray` volume message: the `[up, down]` toggle states.
pub fn parse_volume(msg: &Value) -> Result<[i64; 2], WireError> {
    let Some(Value::Array(data)) = msg.get("data") else {
        return err("std_msgs/Int32MultiArray needs a 'data' array");
    };
    if data.len() < 2 {
        return err(format!(
            "volume data needs 2 entries [up, down], got {}",
            data.len()
        ));
    }
    let int = |v: &Value| {
        v.as_i64()
            .ok_or_else(|| WireError("volume data must be integers".into()))
    };
    Ok([int(&data[0])?, int(&data[1])?])
}

/// Parses `std_msgs/Float32` (`data` finite).
pub fn parse_float32(msg: &Value) -> Result<f64, WireError> {
    finite(msg, &["data"])
}

/// Parses `std_msgs/Bool`.
pub fn parse_bool(msg: &Value) -> Result<bool, WireError> {
    msg.get("data")
        .and_then(Value::as_bool)
        .ok_or_else(|| WireError("std_msgs/Bool needs a boolean 'data'".into()))
}

/// `{"op":"status", ...}`.
pub fn status(level: StatusLevel, msg: &str, id: Option<&Value>) -> String {
    let mut v = json!({"op": "status", "level": level.as_str(), "msg": msg});
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v.to_string()
}

/// `{"op":"service_response", ...}` for a failed call.
pub fn service_failure(service: &str, message: &str, id: Option<&Value>) -> String {
    let mut v = json!({"op": "service_response", "service": service, "values": message, "result": false});
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v.to_string()
}

/// `{"op":"service_response", ...}` for a successful call.
pub fn service_success(service: &str, values: Value, id: Option<&Value>) -> String {
    let mut v = json!({"op": "service_response", "service": service, "result": true});
    v["values"] = values;
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v.to_string()
}

/// `{"op":"publish", ...}` of any message.
pub fn publish(topic: &str, msg: Value) -> String {
    let mut v = json!({"op": "publish", "topic": topic});
    v["msg"] = msg;
    v.to_string()
}

/// `{"op":"publish", ...}` of a `geometry_msgs/PoseStamped` in ROS 2 JSON.
pub fn publish_pose(
    topic: &str,
    frame_id: &str,
    stamp_ns: i64,
    position_m: [f64; 3],
    quat_xyzw: [f64; 4],
) -> String {
    json!({
        "op": "publish",
        "topic": topic,
        "msg": {
            "header": {
                "stamp": {"sec": stamp_ns.div_euclid(1_000_000_000), "nanosec": stamp_ns.rem_euclid(1_000_000_000)},
                "frame_id": frame_id,
            },
            "pose": {
                "position": {"x": position_m[0], "y": position_m[1], "z": position_m[2]},
                "orientation": {"x": quat_xyzw[0], "y": quat_xyzw[1], "z": quat_xyzw[2], "w": quat_xyzw[3]},
            },
        },
    })
    .to_string()
}

/// `{"op":"publish", ...}` of a `std_msgs/String`.
pub fn publish_string(topic: &str, data: &str) -> String {
    json!({"op": "publish", "topic": topic, "msg": {"data": data}}).to_string()
}

#[cfg(test)]
// Values pass through untouched: exact equality is the property under test.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;

    /// Byte for byte what the Phone2Act Android app sends (bepinyd/Phone2Act `lib/ros_manager.dart`).
    const APP_ADVERTISE: &str =
        r#"{"op":"advertise","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped"}"#;
    const APP_POSE: &str = r#"{"op":"publish","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped","msg":{"header":{"stamp":{"sec":1763726400,"nanosec":123456000},"frame_id":"phone_ar_frame"},"pose":{"position":{"x":0.01,"y":-0.02,"z":-0.3},"orientation":{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}"#;
    const APP_VOLUME: &str = r#"{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{"layout":{"dim":[],"data_offset":0},"data":[1,0]}}"#;

    #[test]
    fn the_apps_messages_parse() {
        let adv = parse(APP_ADVERTISE).unwrap();
        assert_eq!(
            adv.op,
            Op::Advertise {
                topic: "/Phone2Act/ar_pose".into(),
                msg_type: "geometry_msgs/PoseStamped".into()
            }
        );
        let Op::Publish { topic, msg_type, msg } = parse(APP_POSE).unwrap().op else {
            panic!("not a publish")
        };
        assert_eq!(topic, "/Phone2Act/ar_pose");
        assert_eq!(msg_type.as_deref(), Some("geometry_msgs/PoseStamped"));
        let pose = parse_pose_stamped(&msg).unwrap();
        assert_eq!(pose.stamp_ns, Some(1_763_726_400_123_456_000));
        assert_eq!(pose.position_m, [0.01, -0.02, -0.3]);
        assert_eq!(pose.quat_xyzw, [0.0, 0.0, 0.0, 1.0]);
        let Op::Publish { msg_type, msg, .. } = parse(APP_VOLUME).unwrap().op else {
            panic!("not a publish")
        };
        assert_eq!(msg_type.as_deref(), Some("std_msgs/Int32MultiArray"));
        assert_eq!(parse_volume(&msg).unwrap(), [1, 0]);
    }

    #[test]
    fn ros1_stamps_ints_for_floats_and_a_missing_header_are_accepted() {
        let msg: Value = serde_json::from_str(
            r#"{"header":{"seq":3,"stamp":{"secs":2,"nsecs":5},"frame_id":""},
                "pose":{"position":{"x":1,"y":0,"z":0},"orientation":{"x":0,"y":0,"z":0,"w":1}}}"#,
        )
        .unwrap();
        let pose = parse_pose_stamped(&msg).unwrap();
        assert_eq!(pose.stamp_ns, Some(2_000_000_005));
        assert_eq!(pose.position_m[0], 1.0);
        let bare: Value = serde_json::from_str(
            r#"{"pose":{"position":{"x":0,"y":0,"z":0},"orientation":{"x":0,"y":0,"z":0,"w":1}}}"#,
        )
        .unwrap();
        assert_eq!(parse_pose_stamped(&bare).unwrap().stamp_ns, None);
    }

    #[test]
    fn type_names_in_both_spellings_normalise_and_bad_ones_fail() {
        assert_eq!(
            normalize_type("std_msgs/msg/Int32MultiArray").unwrap(),
            "std_msgs/Int32MultiArray"
        );
        assert_eq!(
            normalize_type("std_msgs/Int32MultiArray").unwrap(),
            "std_msgs/Int32MultiArray"
        );
        assert!(normalize_type("std_msgs/srv/Trigger").is_err());
        assert!(normalize_type("PoseStamped").is_err());
        assert!(normalize_type("a/b/c/d").is_err());
    }

    #[test]
    fn topics_are_made_absolute_and_checked() {
        assert_eq!(
            normalize_topic("Phone2Act/ar_pose").unwrap(),
            "/Phone2Act/ar_pose"
        );
        for bad in ["", "/", "/a//b", "/a/", "/a b", "/a-b"] {
            assert!(normalize_topic(bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn nan_is_named_not_reported_as_malformed() {
        // Python's json.dumps(float("nan")) writes a bare NaN.
        let text = r#"{"op":"publish","topic":"/p","msg":{"pose":{"position":{"x":NaN,"y":0,"z":0},"orientation":{"x":0,"y":0,"z":0,"w":1}}}}"#;
        let Op::Publish { msg, .. } = parse(text).unwrap().op else {
            panic!()
        };
        let e = parse_pose_stamped(&msg).unwrap_err();
        assert!(e.0.contains("pose.position.x"), "{e}");
        // A NaN inside a string is left alone.
        assert_eq!(
            replace_non_finite_tokens(r#"{"a":"NaN"}"#),
            Cow::Borrowed(r#"{"a":"NaN"}"#)
        );
        assert_eq!(
            replace_non_finite_tokens(r#"[NaN,-Infinity,"x\"NaN"]"#),
            r#"[null,null,"x\"NaN"]"#
        );
    }

    #[test]
    fn non_ascii_outside_strings_is_malformed_json_not_a_panic() {
        for text in [
            "{\"op\":\"x\"} 😀",
            "😀NaN",
            "é",
            "[NaN,\u{e9}Infinity]",
            "{\"a\":1}\u{ff}-Infinity",
        ] {
            assert!(parse(text).is_err(), "{text:?} accepted");
        }
        assert_eq!(replace_non_finite_tokens("[\u{e9},NaN]"), "[\u{e9},null]");
    }

    #[test]
    fn bad_messages_give_reasons_and_keep_the_id() {
        assert!(parse("{not json").unwrap_err().1.0.contains("malformed JSON"));
        assert!(parse("[1,2]").unwrap_err().1.0.contains("JSON object"));
        let (id, e) = parse(r#"{"op":"teleport","id":"x:1"}"#).unwrap_err();
        assert_eq!(id, Some(Value::String("x:1".into())));
        assert!(e.0.contains("unknown op 'teleport'"));
        assert!(parse(r#"{"topic":"/a"}"#).unwrap_err().1.0.contains("'op'"));
        assert!(parse(r#"{"op":"publish","topic":"/a","msg":5}"#).is_err());
        let msg: Value = serde_json::from_str(r#"{"data":[1]}"#).unwrap();
        assert!(parse_volume(&msg).is_err());
    }

    #[test]
    fn replies_are_rosbridge_shaped() {
        let s: Value =
            serde_json::from_str(&status(StatusLevel::Error, "boom", Some(&json!("p:1")))).unwrap();
        assert_eq!(s, json!({"op":"status","level":"error","msg":"boom","id":"p:1"}));
        let p: Value = serde_json::from_str(&publish_pose(
            "/fb",
            "robot_base",
            1_500_000_000,
            [1.0, 2.0, 3.0],
            [0.0, 0.0, 0.0, 1.0],
        ))
        .unwrap();
        assert_eq!(
            p["msg"]["header"]["stamp"],
            json!({"sec":1,"nanosec":500_000_000})
        );
        assert_eq!(p["msg"]["pose"]["position"]["z"], json!(3.0));
    }
}
