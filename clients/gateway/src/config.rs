//! Gateway configuration: the `[gateway]` table of the server config, also used by the standalone binary.
//!
//! Every field has a default, so an empty table (or none at all) gives a gateway that a phone on the same
//! LAN can reach: rosbridge on `0.0.0.0:9090` (what the Phone2Act app expects) and the phone page on
//! `https://0.0.0.0:8443` with a self-signed certificate and a pairing token.

use crate::error::GatewayError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

/// Messages larger than this close the socket with code 1009 (the WebSocket "message too big" close);
/// messages between [`GatewayConfig::max_message_bytes`] and this are refused with an error and the
/// connection stays up.
pub const HARD_MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// The `[gateway]` table.
// Independent on/off switches of a config file, not a state machine.
#[allow(clippy::struct_excessive_bools)]
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct GatewayConfig {
    /// Run the gateway inside `phone2act serve` ([`crate::serve`] only waits for shutdown when false).
    pub enabled: bool,
    /// Serve rosbridge v2 on plain `ws://` (the Phone2Act Android app, roslibjs, roslibpy).
    pub rosbridge: bool,
    /// Where the rosbridge socket listens. The default binds every interface because the phone is another
    /// machine on the LAN; use `127.0.0.1:9090` to keep it local (e.g. with `adb reverse`).
    pub rosbridge_listen: SocketAddr,
    /// Serve the phone page and its `wss://` socket over HTTPS.
    pub https: bool,
    /// Where the HTTPS server listens (every interface by default, for the same reason).
    pub https_listen: SocketAddr,
    /// Directory that keeps the generated certificate, key and pairing token across restarts, so a phone
    /// accepts the certificate once. Default: `$XDG_DATA_HOME/phone2act/gateway` (or
    /// `~/.local/share/phone2act/gateway`).
    pub cert_dir: Option<PathBuf>,
    /// A certificate chain (PEM) to use instead of the generated one; needs `key_file`.
    pub cert_file: Option<PathBuf>,
    /// The private key (PEM) for `cert_file`.
    pub key_file: Option<PathBuf>,
    /// Refuse phone-page sockets that do not carry the pairing token (`?token=`).
    pub require_token: bool,
    /// The pairing token. When absent and `require_token` is set, one is generated on first start and kept
    /// in `cert_dir`. It is printed in the URL and the QR code.
    pub token: Option<String>,
    /// Also require the token on the plain rosbridge port (`ws://host:9090/?token=...`). Off by default
    /// because the Phone2Act app and most rosbridge clients cannot send one.
    pub rosbridge_require_token: bool,
    /// Host name or address printed in the URL and QR code. Default: the address of the interface that
    /// routes to the LAN.
    pub public_host: Option<String>,
    /// Lowest level of `{"op":"status"}` messages sent to a rosbridge client until it sends `set_level`:
    /// "none" (default), "error", "warning" or "info". rosbridge itself never sends status, and some
    /// clients (roslibpy) fail on messages they do not expect, so errors are reported only to clients that
    /// ask with `set_level` unless this says otherwise.
    pub rosbridge_status_level: String,
    /// Messages above this size are refused with an error; the connection stays up.
    pub max_message_bytes: usize,
    /// Print the phone URL and a QR code on start.
    pub print_qr: bool,
    /// Arm driven by topics without a namespace and by the page until the user picks one.
    pub default_arm: String,
    /// rosbridge topic names and their mapping to arms.
    pub topics: TopicConfig,
    /// How long opening the phone page with the pairing token lets that phone's address use rosbridge
    /// (the Phone2Act app cannot send a token). 0 disables pairing by address.
    pub pair_for_s: u64,
    /// Addresses always let in on rosbridge without a token or pairing (a robot PC's own tablet, a lab
    /// machine running roslibpy). Exact addresses, IPv4 or IPv6.
    pub allow: Vec<IpAddr>,
    /// Addresses that count as this machine and are let in on rosbridge without a token or pairing. Default
    /// (absent): every loopback address, so the Phone2Act app reaches the arm through `adb reverse`. `[]`
    /// trusts no address: loopback clients then pair or carry the token like any other (see
    /// `docs/gateway-security.md`). Tests narrow it to `["127.0.0.1"]` so that a client bound to 127.0.0.2
    /// plays a phone.
    pub local_addresses: Option<Vec<IpAddr>>,
    /// A rosbridge connection from the same address as the one holding an arm takes the arm over once
    /// the holder has sent nothing for this long (the app's second tap on "connect" leaves the old socket
    /// open and silent). Match the arms' `stale_timeout_s`.
    pub takeover_silence_ms: u64,
    /// Headset controllers on the phone page: WebXR handedness (`left`, `right`) → arm. Empty (the
    /// default): each controller drives the arm of its own name when the server has one, otherwise the right
    /// controller drives the arm picked on the page.
    pub controllers: BTreeMap<String, String>,
    /// The phone page's live WebRTC video (`[gateway.video]`).
    pub video: VideoConfig,
}

/// The `[gateway.video]` table: the phone page's live WebRTC video of a camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct VideoConfig {
    /// Offer live video at all. Off: the page shows no video switch and a video offer is refused; the JPEG
    /// preview stays.
    pub enabled: bool,
    /// The least bits per second the encoder is given however slow a viewer's link looks; below about 150
    /// kbit/s one camera frame in three is sent, below 300 one in two.
    pub min_bitrate_kbps: u32,
    /// The most, and where the bitrate starts before a link estimate exists.
    pub max_bitrate_kbps: u32,
    /// The highest frame rate sent: a faster camera has frames skipped.
    pub max_fps: u32,
    /// The largest picture sent: a larger camera is scaled down to fit, keeping its aspect.
    pub max_width_px: u32,
    pub max_height_px: u32,
    /// Pages watching at once (each viewer is a connection of its own); a page beyond this gets the JPEG
    /// preview instead.
    pub max_viewers: u32,
}

impl Default for VideoConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            // str0m paces at 1.1 times its estimate: an encoder above what a slow link's estimate falls to fills
            // the pacer's queue, so the floor stays low.
            min_bitrate_kbps: 60,
            // 640x480 at 30 fps, sharp enough to read the scene, a small share of a Wi-Fi link.
            max_bitrate_kbps: 1500,
            max_fps: 30,
            max_width_px: 1280,
            max_height_px: 720,
            // An operator and an observer or two; each viewer costs the gateway a connection and its packets.
            max_viewers: 4,
        }
    }
}

/// Bounds of the `[gateway.video]` keys.
const VIDEO_BITRATE_KBPS: std::ops::RangeInclusive<u32> = 30..=50_000;
const VIDEO_FPS: std::ops::RangeInclusive<u32> = 1..=60;
const VIDEO_SIDE_PX: std::ops::RangeInclusive<u32> = 16..=4096;
const VIDEO_VIEWERS: std::ops::RangeInclusive<u32> = 1..=32;

impl VideoConfig {
    /// The checks serde cannot make.
    pub fn validate(&self) -> Result<(), GatewayError> {
        let range = |key: &str, value: u32, range: &std::ops::RangeInclusive<u32>| {
            if range.contains(&value) {
                Ok(())
            } else {
                Err(GatewayError::Config(format!(
                    "gateway.video.{key} must be in {}..={}, got {value}",
                    range.start(),
                    range.end()
                )))
            }
        };
        range("min_bitrate_kbps", self.min_bitrate_kbps, &VIDEO_BITRATE_KBPS)?;
        range("max_bitrate_kbps", self.max_bitrate_kbps, &VIDEO_BITRATE_KBPS)?;
        if self.min_bitrate_kbps > self.max_bitrate_kbps {
            return Err(GatewayError::Config(format!(
                "gateway.video.min_bitrate_kbps ({}) must not exceed max_bitrate_kbps ({})",
                self.min_bitrate_kbps, self.max_bitrate_kbps
            )));
        }
        range("max_fps", self.max_fps, &VIDEO_FPS)?;
        range("max_width_px", self.max_width_px, &VIDEO_SIDE_PX)?;
        range("max_height_px", self.max_height_px, &VIDEO_SIDE_PX)?;
        range("max_viewers", self.max_viewers, &VIDEO_VIEWERS)
    }

    /// The bitrate floor, in bits per second.
    pub fn min_bitrate_bps(&self) -> u64 {
        u64::from(self.min_bitrate_kbps) * 1000
    }

    /// The bitrate ceiling, in bits per second.
    pub fn max_bitrate_bps(&self) -> u64 {
        u64::from(self.max_bitrate_kbps) * 1000
    }

    /// The size a `width` x `height` camera is sent at: scaled down to fit the caps with its aspect kept, even
    /// sides (4:2:0 chroma halves both), at least 2 x 2.
    pub fn sent_size(&self, width: u32, height: u32) -> (u32, u32) {
        let scale = (f64::from(self.max_width_px) / f64::from(width.max(1)))
            .min(f64::from(self.max_height_px) / f64::from(height.max(1)))
            .min(1.0);
        let side = |px: u32| ((f64::from(px) * scale) as u32 & !1).max(2);
        (side(width), side(height))
    }
}

impl Default for GatewayConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            rosbridge: true,
            rosbridge_listen: SocketAddr::from(([0, 0, 0, 0], 9090)),
            https: true,
            https_listen: SocketAddr::from(([0, 0, 0, 0], 8443)),
            cert_dir: None,
            cert_file: None,
            key_file: None,
            require_token: true,
            token: None,
            rosbridge_require_token: false,
            public_host: None,
            rosbridge_status_level: "none".to_owned(),
            max_message_bytes: 64 * 1024,
            print_qr: true,
            default_arm: "main".to_owned(),
            topics: TopicConfig::default(),
            // A working day: pair in the morning, work until evening.
            pair_for_s: 8 * 3600,
            allow: Vec::new(),
            local_addresses: None,
            takeover_silence_ms: 300,
            controllers: BTreeMap::new(),
            video: VideoConfig::default(),
        }
    }
}

impl GatewayConfig {
    /// Reads the `[gateway]` table of a server config (defaults for what it leaves out) and validates it.
    pub fn from_table(table: &toml::Table) -> Result<Self, GatewayError> {
        let config: Self = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e: toml::de::Error| GatewayError::Config(format!("[gateway]: {}", e.message())))?;
        config.validate()?;
        Ok(config)
    }

    /// The addresses rosbridge admits without a token or pairing because they count as this machine, as text
    /// for a start-up warning; `None` when rosbridge admits no address that way. With a server token set,
    /// these addresses drive the arms without any credential.
    pub fn trusted_local_addresses(&self) -> Option<String> {
        if !self.enabled || !self.rosbridge || self.rosbridge_require_token {
            return None;
        }
        match &self.local_addresses {
            None => Some("every loopback address (127.0.0.0/8, ::1)".to_owned()),
            Some(list) if list.is_empty() => None,
            Some(list) => Some(
                list.iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", "),
            ),
        }
    }

    /// What to log at start when the server requires a token: the gateway forwards what it admits with that
    /// token, so the addresses it trusts as this machine drive the arms without one. That is what the
    /// Phone2Act app needs through `adb reverse`, and also what any local process, SSH tunnel or local proxy
    /// gets; the message says so and how to narrow it. `None` when no address is trusted that way.
    pub fn local_trust_warning(&self) -> Option<String> {
        let trusted = self.trusted_local_addresses()?;
        Some(format!(
            "the server requires a token, but the phone gateway's rosbridge port ({}) admits {trusted} without \
             one: any process on this machine, or an SSH tunnel or proxy ending here, can drive the arms. Kept for \
             the Phone2Act app through `adb reverse`; to require pairing or the token from this machine too, set \
             [gateway] local_addresses = [] (docs/gateway-security.md)",
            self.rosbridge_listen
        ))
    }

    /// The checks serde cannot make; every way of starting a gateway runs them.
    pub fn validate(&self) -> Result<(), GatewayError> {
        for (hand, arm) in &self.controllers {
            if !matches!(hand.as_str(), "left" | "right") {
                return Err(GatewayError::Config(format!(
                    "gateway.controllers: {hand:?} is not a controller; use left or right"
                )));
            }
            if arm.is_empty() || arm.len() > 64 {
                return Err(GatewayError::Config(format!(
                    "gateway.controllers.{hand}: arm name must be 1 to 64 characters"
                )));
            }
        }
        if crate::rosbridge::StatusLevel::parse(&self.rosbridge_status_level).is_none() {
            return Err(GatewayError::Config(format!(
                "gateway.rosbridge_status_level must be none, error, warning or info, not {:?}",
                self.rosbridge_status_level
            )));
        }
        self.video.validate()?;
        // Below 1 KiB a rosbridge advertise with a long topic name is refused.
        if !(1024..=HARD_MAX_MESSAGE_BYTES).contains(&self.max_message_bytes) {
            return Err(GatewayError::Config(format!(
                "gateway.max_message_bytes must be in 1024..={HARD_MAX_MESSAGE_BYTES}, got {}",
                self.max_message_bytes
            )));
        }
        Ok(())
    }
}

/// Topic names (relative to an arm namespace) and the namespace → arm map.
///
/// A topic `/<ns>/<rest>` whose first segment is a key of `namespaces` drives that arm; any other topic
/// drives `default_arm`. `<rest>` is then compared, case-sensitively as ROS does, with the lists below.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct TopicConfig {
    /// `geometry_msgs/PoseStamped` phone pose topics (tracking frame of the phone).
    pub pose: Vec<String>,
    /// `std_msgs/Int32MultiArray` volume-key toggle states `[up, down]`, read as the app's state like the
    /// original planner: `down` 1 holds the arm, 0 lets the phone drive; `up` 0 closes the gripper, 1 opens it.
    pub volume: Vec<String>,
    /// `std_msgs/Float32` absolute gripper position (0 open, 1 closed).
    pub gripper: Vec<String>,
    /// `std_msgs/Bool` clutch: true engages (the phone drives the arm), false disengages.
    pub clutch: Vec<String>,
    /// Published to subscribers: the measured end effector as `geometry_msgs/PoseStamped` (robot base frame).
    pub robot_feedback: String,
    /// Published to subscribers: the target after the safety gate as `geometry_msgs/PoseStamped`.
    pub target_pose: String,
    /// Published to subscribers: arm and recording state as JSON text in a `std_msgs/String`.
    pub status: String,
    /// First topic segment → arm name.
    pub namespaces: BTreeMap<String, String>,
}

impl Default for TopicConfig {
    fn default() -> Self {
        Self {
            // The app's default, its older package name, and a neutral name for hand-written clients.
            pose: vec![
                "Phone2Act/ar_pose".into(),
                "bros2/ar_pose".into(),
                "phone/pose".into(),
            ],
            volume: vec!["Phone2Act/volume".into(), "bros2/volume".into()],
            gripper: vec!["phone2act/gripper".into()],
            clutch: vec!["phone2act/clutch".into()],
            robot_feedback: "phone2act/robot_feedback".into(),
            target_pose: "phone2act/target_pose".into(),
            status: "phone2act/status".into(),
            namespaces: [("left", "left"), ("right", "right")]
                .into_iter()
                .map(|(ns, arm)| (ns.to_owned(), arm.to_owned()))
                .collect(),
        }
    }
}

/// What a topic means once its namespace is resolved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TopicRole {
    Pose,
    Volume,
    Gripper,
    Clutch,
    RobotFeedback,
    TargetPose,
    Status,
}

impl TopicRole {
    /// The normalised (`pkg/Type`) message type of this topic.
    pub fn msg_type(self) -> &'static str {
        match self {
            Self::Pose | Self::RobotFeedback | Self::TargetPose => "geometry_msgs/PoseStamped",
            Self::Volume => "std_msgs/Int32MultiArray",
            Self::Gripper => "std_msgs/Float32",
            Self::Clutch => "std_msgs/Bool",
            Self::Status => "std_msgs/String",
        }
    }

    /// True for topics the gateway publishes (clients subscribe), false for topics clients publish.
    pub fn is_output(self) -> bool {
        matches!(self, Self::RobotFeedback | Self::TargetPose | Self::Status)
    }
}

impl TopicConfig {
    /// Splits a normalised absolute topic into (arm, role), or `None` for a topic the gateway does not know.
    pub fn resolve(&self, topic: &str, default_arm: &str) -> Option<(String, TopicRole)> {
        let path = topic.strip_prefix('/')?;
        let (arm, rest) = match path.split_once('/') {
            Some((first, rest)) if self.namespaces.contains_key(first) => {
                (self.namespaces[first].clone(), rest)
            }
            _ => (default_arm.to_owned(), path),
        };
        let any = |list: &[String]| list.iter().any(|t| t.trim_start_matches('/') == rest);
        let role = if any(&self.pose) {
            TopicRole::Pose
        } else if any(&self.volume) {
            TopicRole::Volume
        } else if any(&self.gripper) {
            TopicRole::Gripper
        } else if any(&self.clutch) {
            TopicRole::Clutch
        } else if self.robot_feedback.trim_start_matches('/') == rest {
            TopicRole::RobotFeedback
        } else if self.target_pose.trim_start_matches('/') == rest {
            TopicRole::TargetPose
        } else if self.status.trim_start_matches('/') == rest {
            TopicRole::Status
        } else {
            return None;
        };
        Some((arm, role))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn namespaces_pick_the_arm_and_plain_topics_use_the_default() {
        let topics = TopicConfig::default();
        assert_eq!(
            topics.resolve("/Phone2Act/ar_pose", "main"),
            Some(("main".into(), TopicRole::Pose))
        );
        assert_eq!(
            topics.resolve("/left/Phone2Act/ar_pose", "main"),
            Some(("left".into(), TopicRole::Pose))
        );
        assert_eq!(
            topics.resolve("/right/Phone2Act/volume", "main"),
            Some(("right".into(), TopicRole::Volume))
        );
        assert_eq!(
            topics.resolve("/left/phone2act/robot_feedback", "main"),
            Some(("left".into(), TopicRole::RobotFeedback))
        );
        // ROS names are case-sensitive: the planner's outputs are lower case, the phone's inputs are not.
        assert_eq!(topics.resolve("/phone2act/ar_pose", "main"), None);
        assert_eq!(topics.resolve("/middle/Phone2Act/ar_pose", "main"), None);
    }

    #[test]
    fn unknown_keys_are_refused() {
        let err =
            serde_json::from_str::<GatewayConfig>(r#"{"rosbrige_listen": "0.0.0.0:9090"}"#).unwrap_err();
        assert!(err.to_string().contains("unknown field"), "{err}");
        let ok: GatewayConfig =
            serde_json::from_str(r#"{"topics": {"namespaces": {"a": "arm_a"}}}"#).unwrap();
        assert_eq!(ok.topics.namespaces.len(), 1);
        assert_eq!(ok.rosbridge_listen.port(), 9090);
    }

    #[test]
    fn a_server_config_table_gets_defaults_and_checks() {
        let table: toml::Table = toml::from_str("print_qr = false\n").unwrap();
        let config = GatewayConfig::from_table(&table).unwrap();
        assert!(!config.print_qr);
        assert_eq!(config.takeover_silence_ms, 300);
        for (text, needle) in [
            (
                "max_message_bytes = 1000000000000",
                "gateway.max_message_bytes must be in 1024..=16777216",
            ),
            ("max_message_bytes = 1000", "got 1000"),
            ("rosbridge_status_level = \"loud\"", "rosbridge_status_level"),
            ("rosbrige = true", "unknown field"),
            (
                "controllers = { middle = \"a\" }",
                "\"middle\" is not a controller",
            ),
            (
                "controllers = { left = \"\" }",
                "gateway.controllers.left: arm name",
            ),
            (
                "video = { max_bitrate_kbps = 10 }",
                "gateway.video.max_bitrate_kbps must be in 30..=50000, got 10",
            ),
            (
                "video = { min_bitrate_kbps = 2000 }",
                "gateway.video.min_bitrate_kbps (2000) must not exceed max_bitrate_kbps (1500)",
            ),
            (
                "video = { max_fps = 0 }",
                "gateway.video.max_fps must be in 1..=60, got 0",
            ),
            ("video = { max_width_px = 8 }", "gateway.video.max_width_px"),
            ("video = { max_height_px = 5000 }", "gateway.video.max_height_px"),
            ("video = { max_viewers = 0 }", "gateway.video.max_viewers"),
            ("video = { max_fps = -1 }", "invalid value"),
            ("video = { bitrate = 1 }", "unknown field `bitrate`"),
            ("video = { enabled = \"no\" }", "invalid type"),
        ] {
            let err = GatewayConfig::from_table(&toml::from_str(text).unwrap())
                .unwrap_err()
                .to_string();
            assert!(err.contains(needle), "{text}: {err}");
        }
    }

    #[test]
    fn video_keys_have_defaults_and_a_large_camera_is_scaled_to_fit() {
        let table: toml::Table = toml::from_str("[video]\nmax_fps = 15\nmax_viewers = 2\n").unwrap();
        let video = GatewayConfig::from_table(&table).unwrap().video;
        assert_eq!((video.max_fps, video.max_viewers), (15, 2));
        assert_eq!(
            (video.min_bitrate_bps(), video.max_bitrate_bps()),
            (60_000, 1_500_000)
        );
        assert!(video.enabled);
        // Under the caps: sent as captured.
        assert_eq!(video.sent_size(640, 480), (640, 480));
        // 1920x1080 into 1280x720: both sides scale by 2/3.
        assert_eq!(video.sent_size(1920, 1080), (1280, 720));
        // A tall camera is held by the height cap, its aspect kept; odd sides become even.
        assert_eq!(video.sent_size(1000, 1440), (500, 720));
        let small = VideoConfig {
            max_width_px: 321,
            max_height_px: 4096,
            ..VideoConfig::default()
        };
        assert_eq!(small.sent_size(640, 480), (320, 240));
    }

    #[test]
    fn only_a_trusting_rosbridge_names_its_trusted_addresses() {
        let default = GatewayConfig::default();
        assert!(default.trusted_local_addresses().unwrap().contains("loopback"));
        let narrowed = GatewayConfig {
            local_addresses: Some(vec!["127.0.0.1".parse().unwrap()]),
            ..GatewayConfig::default()
        };
        assert_eq!(narrowed.trusted_local_addresses().as_deref(), Some("127.0.0.1"));
        for quiet in [
            GatewayConfig {
                local_addresses: Some(Vec::new()),
                ..GatewayConfig::default()
            },
            GatewayConfig {
                rosbridge_require_token: true,
                ..GatewayConfig::default()
            },
            GatewayConfig {
                rosbridge: false,
                ..GatewayConfig::default()
            },
        ] {
            assert_eq!(quiet.trusted_local_addresses(), None, "{quiet:?}");
        }
    }

    /// Key paths of the leaves of `table` (the user's namespace map counts as one key).
    fn leaf_keys(table: &toml::Table, prefix: &str, out: &mut std::collections::BTreeSet<String>) {
        for (key, value) in table {
            let path = format!("{prefix}{key}");
            match value {
                toml::Value::Table(inner) if key != "namespaces" => {
                    leaf_keys(inner, &format!("{path}."), out);
                }
                _ => {
                    out.insert(path);
                }
            }
        }
    }

    #[test]
    fn the_server_reference_config_shows_every_gateway_key_and_no_other() {
        // The server's reference config documents the `[gateway]` table; its commented examples
        // (`# token = "change-me"`) count as shown.
        let reference = include_str!("../../../server/config/reference.toml");
        let (_, after) = reference
            .split_once("\n[gateway]\n")
            .expect("reference has [gateway]");
        let section: String = std::iter::once("[gateway]")
            .chain(after.lines())
            .take_while(|l| !l.starts_with('[') || l.starts_with("[gateway"))
            .map(|l| match l.strip_prefix("# ") {
                Some(example)
                    if example
                        .split_once(" = ")
                        .is_some_and(|(k, _)| k.chars().all(|c| c.is_ascii_lowercase() || c == '_')) =>
                {
                    example
                }
                _ => l,
            })
            .collect::<Vec<_>>()
            .join("\n");
        let parsed: toml::Table = toml::from_str(&section).unwrap();
        let shown_table = parsed["gateway"].as_table().unwrap();
        // Unknown keys are refused by the type itself.
        GatewayConfig::from_table(shown_table).unwrap();
        let populated = GatewayConfig {
            cert_dir: Some("d".into()),
            cert_file: Some("c".into()),
            key_file: Some("k".into()),
            token: Some("t".into()),
            public_host: Some("h".into()),
            local_addresses: Some(Vec::new()),
            controllers: [
                ("left".to_owned(), "a".to_owned()),
                ("right".to_owned(), "b".to_owned()),
            ]
            .into(),
            ..GatewayConfig::default()
        };
        let (mut every, mut shown) = Default::default();
        leaf_keys(&toml::Table::try_from(&populated).unwrap(), "", &mut every);
        leaf_keys(shown_table, "", &mut shown);
        assert_eq!(
            every, shown,
            "server/config/reference.toml [gateway] against GatewayConfig"
        );
    }
}
