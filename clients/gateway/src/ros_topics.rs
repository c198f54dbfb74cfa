//! The topics and services ROS tools look for, so that Foxglove, a roslibjs page or roslibpy can show
//! phone2act without ROS installed: `/joint_states`, `/tf`, `/cameras/<name>/image/compressed`, and the
//! `rosapi` services that list them.
//!
//! Message shapes follow ROS 2 rosbridge's JSON (stamps as `sec`/`nanosec`, `uint8[]` as base64 text);
//! `rosapi` answers follow its `.srv` definitions (`Topics`: `topics`, `types`; `TopicType`: `type`;
//! `Services`: `services`; `GetTime`: `time`, in both Time spellings for roslibpy). Stamps are wall-clock
//! time taken when the message is built (the caller passes it in): the server's snapshot times are monotonic
//! and mean nothing to a ROS tool.

use crate::config::{TopicConfig, TopicRole};
use crate::feedback::pose_parts;
use base64::Engine as _;
use phone2act_proto::v1::{ArmState, Pose, SystemStatus};
use serde_json::{Value, json};

pub(crate) const JOINT_STATES: &str = "/joint_states";
pub(crate) const TF: &str = "/tf";
const CAMERA_PREFIX: &str = "/cameras/";
const CAMERA_SUFFIX: &str = "/image/compressed";

pub(crate) const JOINT_STATE_TYPE: &str = "sensor_msgs/JointState";
pub(crate) const TF_TYPE: &str = "tf2_msgs/TFMessage";
pub(crate) const COMPRESSED_IMAGE_TYPE: &str = "sensor_msgs/CompressedImage";

/// The services this gateway answers (everything else gets a failed `service_response`).
pub(crate) const SERVICES: [&str; 4] = [
    "/rosapi/topics",
    "/rosapi/topic_type",
    "/rosapi/services",
    "/rosapi/get_time",
];

/// A topic the gateway publishes from the server's state, besides the per-arm mapped topics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Builtin {
    JointStates,
    Tf,
    /// The compressed image of the named camera.
    Camera(String),
}

impl Builtin {
    /// Recognises a normalised absolute topic.
    pub(crate) fn resolve(topic: &str) -> Option<Self> {
        match topic {
            JOINT_STATES => Some(Self::JointStates),
            TF => Some(Self::Tf),
            _ => topic
                .strip_prefix(CAMERA_PREFIX)
                .and_then(|rest| rest.strip_suffix(CAMERA_SUFFIX))
                .filter(|name| !name.is_empty() && !name.contains('/'))
                .map(|name| Self::Camera(name.to_owned())),
        }
    }

    /// The normalised (`pkg/Type`) message type.
    pub(crate) fn msg_type(&self) -> &'static str {
        match self {
            Self::JointStates => JOINT_STATE_TYPE,
            Self::Tf => TF_TYPE,
            Self::Camera(_) => COMPRESSED_IMAGE_TYPE,
        }
    }
}

/// The topic a camera's images are published on.
pub(crate) fn camera_topic(camera: &str) -> String {
    format!("{CAMERA_PREFIX}{camera}{CAMERA_SUFFIX}")
}

/// `pkg/Type` → `pkg/msg/Type`, the spelling ROS 2 tools list.
pub(crate) fn ros2_type(msg_type: &str) -> String {
    msg_type.replacen('/', "/msg/", 1)
}

/// `builtin_interfaces/Time` from nanoseconds since the Unix epoch.
pub(crate) fn stamp(wall_ns: i64) -> Value {
    json!({"sec": wall_ns.div_euclid(1_000_000_000), "nanosec": wall_ns.rem_euclid(1_000_000_000)})
}

/// The TF frame of an arm's base (ROS-Industrial's `base_link`, prefixed by the arm as multi-arm URDFs do).
pub(crate) fn base_frame(arm: &str) -> String {
    format!("{arm}_base_link")
}

/// The TF frame of an arm's measured end effector (ROS-Industrial's `tool0`).
pub(crate) fn ee_frame(arm: &str) -> String {
    format!("{arm}_tool0")
}

/// The TF frame of an arm's target after the safety gate.
pub(crate) fn target_frame(arm: &str) -> String {
    format!("{arm}_target")
}

/// `sensor_msgs/JointState` of every arm that reports joints; joint names are prefixed by the arm so two
/// arms of one model stay distinct. Positions in radians; no velocities or efforts (the server has none).
pub(crate) fn joint_states(status: &SystemStatus, wall_ns: i64) -> Value {
    let mut names = Vec::new();
    let mut positions_rad = Vec::new();
    for arm in &status.arms {
        for (name, position_rad) in arm.joint_names.iter().zip(&arm.joint_positions_rad) {
            names.push(format!("{}_{name}", arm.arm));
            positions_rad.push(*position_rad);
        }
    }
    json!({
        "header": {"stamp": stamp(wall_ns), "frame_id": ""},
        "name": names,
        "position": positions_rad,
        "velocity": [],
        "effort": [],
    })
}

fn transform(parent: &str, child: &str, pose: Option<&Pose>, wall_ns: i64) -> Value {
    let (p, q) = pose_parts(pose);
    json!({
        "header": {"stamp": stamp(wall_ns), "frame_id": parent},
        "child_frame_id": child,
        "transform": {
            "translation": {"x": p[0], "y": p[1], "z": p[2]},
            "rotation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]},
        },
    })
}

fn arm_transforms(arm: &ArmState, wall_ns: i64) -> [Value; 2] {
    [
        transform(
            &base_frame(&arm.arm),
            &ee_frame(&arm.arm),
            arm.robot_from_ee.as_ref(),
            wall_ns,
        ),
        transform(
            &base_frame(&arm.arm),
            &target_frame(&arm.arm),
            arm.robot_from_target.as_ref(),
            wall_ns,
        ),
    ]
}

/// `tf2_msgs/TFMessage`: per arm, base → measured end effector and base → target.
pub(crate) fn tf(status: &SystemStatus, wall_ns: i64) -> Value {
    let transforms: Vec<Value> = status
        .arms
        .iter()
        .flat_map(|arm| arm_transforms(arm, wall_ns))
        .collect();
    json!({ "transforms": transforms })
}

/// `sensor_msgs/CompressedImage` of a JPEG, `data` base64 as rosbridge sends `uint8[]`.
pub(crate) fn compressed_image(camera: &str, jpeg: &[u8], wall_ns: i64) -> Value {
    json!({
        "header": {"stamp": stamp(wall_ns), "frame_id": format!("{camera}_optical_frame")},
        "format": "jpeg",
        "data": base64::engine::general_purpose::STANDARD.encode(jpeg),
    })
}

/// Every topic a client can use on this gateway, with its `pkg/Type`: for each arm the server reports, its
/// input and output topics (under its namespace, or at the root for the default arm), then the builtins
/// and one image topic per camera. Arms no topic reaches (no namespace, not the default) are left out.
pub(crate) fn catalogue(
    topics: &TopicConfig,
    default_arm: &str,
    arms: &[String],
    cameras: &[String],
) -> Vec<(String, &'static str)> {
    let mut out = Vec::new();
    for arm in arms {
        let prefix = match topics.namespaces.iter().find(|(_, a)| *a == arm) {
            Some((ns, _)) => format!("/{ns}/"),
            None if arm == default_arm => "/".to_owned(),
            None => continue,
        };
        let first = |list: &[String]| list.first().cloned();
        let named = [
            (first(&topics.pose), TopicRole::Pose),
            (first(&topics.volume), TopicRole::Volume),
            (first(&topics.gripper), TopicRole::Gripper),
            (first(&topics.clutch), TopicRole::Clutch),
            (Some(topics.robot_feedback.clone()), TopicRole::RobotFeedback),
            (Some(topics.target_pose.clone()), TopicRole::TargetPose),
            (Some(topics.status.clone()), TopicRole::Status),
        ];
        for (name, role) in named {
            if let Some(name) = name {
                out.push((
                    format!("{prefix}{}", name.trim_start_matches('/')),
                    role.msg_type(),
                ));
            }
        }
    }
    out.push((JOINT_STATES.to_owned(), JOINT_STATE_TYPE));
    out.push((TF.to_owned(), TF_TYPE));
    for camera in cameras {
        out.push((camera_topic(camera), COMPRESSED_IMAGE_TYPE));
    }
    out
}

/// `GetTime`'s `time`: ROS 2's `sec`/`nanosec` (what a ROS 2 rosapi answers) and the same instant in ROS 1's
/// `secs`/`nsecs`, which roslibpy's `Ros.get_time()` reads. A reader of one spelling skips the other pair, and
/// a stamp sent back as it is still reads right: rosbridge (and this gateway) take a Time in either spelling.
fn get_time_stamp(wall_ns: i64) -> Value {
    let (sec, nanosec) = (
        wall_ns.div_euclid(1_000_000_000),
        wall_ns.rem_euclid(1_000_000_000),
    );
    json!({"sec": sec, "nanosec": nanosec, "secs": sec, "nsecs": nanosec})
}

/// The `values` of a `rosapi` call, or `None` for a service this gateway does not provide.
pub(crate) fn rosapi_values(
    service: &str,
    args: &Value,
    catalogue: &[(String, &'static str)],
    wall_ns: i64,
) -> Option<Value> {
    Some(match service {
        "/rosapi/topics" => json!({
            "topics": catalogue.iter().map(|(t, _)| t.as_str()).collect::<Vec<_>>(),
            "types": catalogue.iter().map(|(_, ty)| ros2_type(ty)).collect::<Vec<_>>(),
        }),
        "/rosapi/topic_type" => {
            let asked = args.get("topic").and_then(Value::as_str).unwrap_or_default();
            let asked = crate::rosbridge::normalize_topic(asked).unwrap_or_default();
            // rosapi answers an unknown topic with an empty type, not a failure.
            let found = catalogue.iter().find(|(t, _)| *t == asked);
            json!({"type": found.map(|(_, ty)| ros2_type(ty)).unwrap_or_default()})
        }
        "/rosapi/services" => json!({"services": SERVICES}),
        "/rosapi/get_time" => json!({"time": get_time_stamp(wall_ns)}),
        _ => return None,
    })
}

/// True if the service needs the server's arm and camera lists.
pub(crate) fn needs_catalogue(service: &str) -> bool {
    matches!(service, "/rosapi/topics" | "/rosapi/topic_type")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arm(name: &str) -> ArmState {
        ArmState {
            arm: name.into(),
            joint_names: vec!["shoulder".into(), "elbow".into()],
            joint_positions_rad: vec![0.5, -1.25],
            robot_from_ee: Some(Pose::from_parts([0.3, 0.0, 0.2], [0.0, 0.0, 0.0, 1.0])),
            ..ArmState::default()
        }
    }

    #[test]
    fn builtin_topics_resolve_and_others_do_not() {
        assert_eq!(Builtin::resolve("/joint_states"), Some(Builtin::JointStates));
        assert_eq!(Builtin::resolve("/tf"), Some(Builtin::Tf));
        assert_eq!(
            Builtin::resolve("/cameras/front/image/compressed"),
            Some(Builtin::Camera("front".into()))
        );
        for other in [
            "/cameras//image/compressed",
            "/cameras/a/b/image/compressed",
            "/tf_static",
            "/x",
        ] {
            assert_eq!(Builtin::resolve(other), None, "{other}");
        }
    }

    #[test]
    fn joint_states_carry_every_arms_joints_with_a_wall_clock_stamp() {
        let status = SystemStatus {
            arms: vec![arm("left"), arm("right")],
            ..SystemStatus::default()
        };
        let msg = joint_states(&status, 1_700_000_000_250_000_000);
        assert_eq!(
            msg["header"]["stamp"],
            json!({"sec": 1_700_000_000_i64, "nanosec": 250_000_000})
        );
        assert_eq!(
            msg["name"],
            json!(["left_shoulder", "left_elbow", "right_shoulder", "right_elbow"])
        );
        assert_eq!(msg["position"], json!([0.5, -1.25, 0.5, -1.25]));
    }

    #[test]
    fn tf_has_measured_and_target_frames_per_arm() {
        let status = SystemStatus {
            arms: vec![arm("left")],
            ..SystemStatus::default()
        };
        let msg = tf(&status, 5);
        let t = &msg["transforms"];
        assert_eq!(t.as_array().map(Vec::len), Some(2));
        assert_eq!(t[0]["header"]["frame_id"], "left_base_link");
        assert_eq!(t[0]["child_frame_id"], "left_tool0");
        assert_eq!(t[0]["transform"]["translation"]["x"], json!(0.3));
        assert_eq!(t[1]["child_frame_id"], "left_target");
    }

    #[test]
    fn rosapi_lists_what_the_gateway_serves_in_ros2_spelling() {
        let topics = TopicConfig::default();
        let cat = catalogue(
            &topics,
            "main",
            &["main".into(), "left".into(), "orphan".into()],
            &["front".into()],
        );
        let v = rosapi_values("/rosapi/topics", &Value::Null, &cat, 0).unwrap();
        let names: Vec<&str> = v["topics"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(Value::as_str)
            .collect();
        assert!(names.contains(&"/phone2act/robot_feedback"), "{names:?}");
        assert!(names.contains(&"/left/Phone2Act/ar_pose"), "{names:?}");
        assert!(names.contains(&"/cameras/front/image/compressed"), "{names:?}");
        assert!(!names.iter().any(|n| n.contains("orphan")), "{names:?}");
        assert_eq!(
            v["topics"].as_array().unwrap().len(),
            v["types"].as_array().unwrap().len()
        );
        let ty = rosapi_values("/rosapi/topic_type", &json!({"topic": "joint_states"}), &cat, 0).unwrap();
        assert_eq!(ty, json!({"type": "sensor_msgs/msg/JointState"}));
        let none = rosapi_values("/rosapi/topic_type", &json!({"topic": "/nope"}), &cat, 0).unwrap();
        assert_eq!(none, json!({"type": ""}));
        assert!(rosapi_values("/rosapi/nodes", &Value::Null, &cat, 0).is_none());
    }

    #[test]
    fn get_time_answers_in_both_ros_spellings_of_the_same_instant() {
        let v = rosapi_values("/rosapi/get_time", &Value::Null, &[], 1_700_000_000_250_000_000).unwrap();
        assert_eq!(
            v["time"],
            json!({"sec": 1_700_000_000_i64, "nanosec": 250_000_000, "secs": 1_700_000_000_i64, "nsecs": 250_000_000})
        );
        // Before 1970 the nanoseconds stay in [0, 1e9) in both pairs, as `builtin_interfaces/Time` requires.
        let v = rosapi_values("/rosapi/get_time", &Value::Null, &[], -1).unwrap();
        assert_eq!(v["time"]["secs"], json!(-1));
        assert_eq!(v["time"]["nsecs"], json!(999_999_999));
        assert_eq!(v["time"]["sec"], v["time"]["secs"]);
    }

    #[test]
    fn compressed_images_are_base64_jpeg() {
        let msg = compressed_image("front", &[0xff, 0xd8, 0xff], 0);
        assert_eq!(msg["format"], "jpeg");
        assert_eq!(msg["data"], "/9j/");
    }
}
