//! The typed server configuration, read from TOML. Every table denies unknown keys so a typo fails at start
//! with the file, the line and what was expected. `PHONE2ACT_<SECTION>__<KEY>=value` environment variables
//! override single values (`PHONE2ACT_SERVER__LISTEN=0.0.0.0:50051`); values are parsed as TOML when they
//! parse, else taken as strings.

use serde::Deserialize;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// Prefix of environment overrides.
pub const ENV_PREFIX: &str = "PHONE2ACT_";

/// The embedded default configuration: one simulated arm `main`, one synthetic camera, datasets under
/// `./datasets/`, gRPC on 127.0.0.1:50051.
pub const EMBEDDED_DEFAULT: &str = include_str!("../config/default.toml");

/// Errors reading the configuration.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A syntax or type error, located in the file.
    #[error("{origin}:{line}:{column}: {message}")]
    Parse {
        origin: String,
        line: usize,
        column: usize,
        message: String,
    },
    /// A value that parses but makes no sense (duplicate arm names, fps out of range, ...).
    #[error("{origin}: {message}")]
    Invalid { origin: String, message: String },
    #[error("environment override {var}: {message}")]
    Env { var: String, message: String },
}

/// The whole configuration.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub server: ServerConfig,
    /// Arms in dataset order. Names must be unique.
    #[serde(default)]
    pub arms: Vec<ArmConfig>,
    /// Cameras in dataset order. Names must be unique.
    #[serde(default)]
    pub cameras: Vec<CameraConfig>,
    #[serde(default)]
    pub recorder: RecorderConfig,
    /// The phone gateway `phone2act serve` embeds: rosbridge v2 on ws://:9090 (the Phone2Act Android app,
    /// roslibjs/roslibpy) and the zero-install phone page over HTTPS on :8443.
    #[serde(default)]
    pub gateway: phone2act_gateway::GatewayConfig,
}

/// gRPC listener and access.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// gRPC listen address.
    #[serde(default = "default_listen")]
    pub listen: SocketAddr,
    /// Bearer token required on every call when set.
    #[serde(default)]
    pub token: Option<String>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: default_listen(),
            token: None,
        }
    }
}

fn default_listen() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50051))
}

/// Which bridge drives an arm.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum BridgeKind {
    /// The simulated SO-101 arm with its pick-and-place scene.
    Sim,
    /// A Dobot CR5 over TCP.
    Dobot,
    /// A LeRobot SO-101 over a Feetech serial bus.
    So101,
    /// An out-of-process bridge attached over `Bridge.Attach`.
    Remote,
}

impl BridgeKind {
    /// The name used on the wire and in status displays.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sim => "sim",
            Self::Dobot => "dobot",
            Self::So101 => "so101",
            Self::Remote => "remote",
        }
    }
}

/// Names and units of an arm's state and action columns.
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum DatasetLayout {
    #[default]
    Phone2act,
    LerobotSo101,
}

/// One arm.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ArmConfig {
    /// Name used in the API and as the dataset prefix when several arms are recorded (`left`, `right`).
    pub name: String,
    pub bridge: BridgeKind,
    /// Phone mapping, safety gate and gripper behaviour.
    #[serde(default)]
    pub teleop: phone2act_core::TeleopConfig,
    /// Policy chunk execution limits and blending.
    #[serde(default)]
    pub chunk: phone2act_core::ChunkConfig,
    /// Action representation policies are told to push (and trained with): "relative" (to the chunk's
    /// observation; "delta" is accepted as its old name), "absolute", or "joint" (SO-101 arms: joint targets,
    /// recorded and pushed). End-effector arms record absolute targets, from which a trainer derives
    /// relative chunks.
    #[serde(default)]
    pub action_mode: phone2act_core::ActionMode,
    /// Names and units of the arm's state and actions: "phone2act" (joints rad, end-effector pose, gripper 0..1)
    /// or "lerobot_so101" (lerobot's `so101_follower`: `shoulder_pan.pos` … in degrees, `gripper.pos` 0..100;
    /// needs action_mode = "joint" on an SO-101), so datasets merge with lerobot's own SO-101 datasets.
    #[serde(default)]
    pub dataset_layout: DatasetLayout,
    /// Simulated arm settings (bridge = "sim").
    #[serde(default)]
    pub sim: Option<phone2act_bridges::sim::SimConfig>,
    /// Dobot CR5 connection and ServoP settings (bridge = "dobot").
    #[serde(default)]
    pub dobot: Option<phone2act_bridges::dobot::DobotConfig>,
    /// SO-101 serial bus and calibration (bridge = "so101").
    #[serde(default)]
    pub so101: Option<phone2act_bridges::so101::So101Config>,
    /// Out-of-process bridge settings (bridge = "remote").
    #[serde(default)]
    pub remote: Option<RemoteArmConfig>,
}

/// A remote arm: the joints its bridge will report, so the dataset layout is known before it attaches.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RemoteArmConfig {
    /// Joint names in feedback order; a bridge that attaches with other names is refused.
    pub joint_names: Vec<String>,
}

/// Kinds of camera source.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum CameraKind {
    /// Synthetic colour bars with a moving bar and an encoded frame number.
    TestPattern,
    /// A V4L2 webcam through libavdevice.
    V4l2,
    /// The simulated arm's scene rendered from a fixed camera.
    SimRender,
    /// Frames pushed over `Cameras.Push`.
    Remote,
}

impl CameraKind {
    /// The name used on the wire and in status displays.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::TestPattern => "test_pattern",
            Self::V4l2 => "v4l2",
            Self::SimRender => "sim_render",
            Self::Remote => "remote",
        }
    }
}

/// One camera.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Dataset key suffix: `observation.images.<name>`.
    pub name: String,
    pub kind: CameraKind,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_height")]
    pub height: u32,
    #[serde(default = "default_camera_fps")]
    pub fps: f64,
    /// V4L2 device path (kind = "v4l2").
    #[serde(default)]
    pub device: Option<String>,
    /// Ask a V4L2 webcam for MJPEG (most reach 30 fps at 640x480 only in MJPEG); false asks for raw frames.
    #[serde(default = "default_true")]
    pub mjpeg: bool,
    /// Which simulated arm a "sim_render" camera shows (default: the first simulated arm).
    #[serde(default)]
    pub arm: Option<String>,
}

fn default_true() -> bool {
    true
}
fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}
fn default_camera_fps() -> f64 {
    30.0
}

/// Dataset format written by the recorder.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
pub enum DatasetFormat {
    /// LeRobot v3.0 (lerobot >= 0.4).
    #[serde(rename = "v3.0")]
    V30,
    /// LeRobot v2.1 with GR00T's `meta/modality.json` (lerobot 0.3.x, GR00T N1.5).
    #[serde(rename = "v2.1")]
    V21,
}

impl DatasetFormat {
    /// `codebase_version` string.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::V30 => "v3.0",
            Self::V21 => "v2.1",
        }
    }
}

/// The recorder.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RecorderConfig {
    /// Dataset directory (created on first save).
    #[serde(default = "default_dataset_root")]
    pub root: PathBuf,
    #[serde(default = "default_format")]
    pub format: DatasetFormat,
    /// Dataset rate, 1..=60.
    #[serde(default = "default_dataset_fps")]
    pub fps: f64,
    /// `robot_type` in info.json.
    #[serde(default = "default_robot_type")]
    pub robot_type: String,
    /// Video codec; default libsvtav1 for v3.0 and libx264 for v2.1.
    #[serde(default)]
    pub video_codec: Option<String>,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            root: default_dataset_root(),
            format: default_format(),
            fps: default_dataset_fps(),
            robot_type: default_robot_type(),
            video_codec: None,
        }
    }
}

impl RecorderConfig {
    /// The codec actually used.
    pub fn effective_video_codec(&self) -> &str {
        match (&self.video_codec, self.format) {
            (Some(codec), _) => codec,
            (None, DatasetFormat::V30) => "libsvtav1",
            (None, DatasetFormat::V21) => "libx264",
        }
    }
}

fn default_dataset_root() -> PathBuf {
    PathBuf::from("./datasets/phone2act")
}
fn default_format() -> DatasetFormat {
    DatasetFormat::V30
}
fn default_dataset_fps() -> f64 {
    20.0
}
fn default_robot_type() -> String {
    "so101_sim".to_owned()
}

impl Config {
    /// The embedded default, with environment overrides applied.
    pub fn embedded_default() -> Result<Self, ConfigError> {
        Self::from_toml_str(EMBEDDED_DEFAULT, "<embedded default>", std::env::vars())
    }

    /// Reads `path`, applying environment overrides from the process environment.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string(), std::env::vars())
    }

    /// Parses TOML text; `origin` names it in errors; `env` supplies `PHONE2ACT_*` overrides.
    pub fn from_toml_str(
        text: &str,
        origin: &str,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self, ConfigError> {
        let mut table: toml::Table = toml::from_str(text).map_err(|e| parse_error(&e, text, origin))?;
        apply_env_overrides(&mut table, env)?;
        // Re-serialise so that spans in type errors point at the file when no override touched it.
        let config: Config = if table_equals_text(&table, text) {
            toml::from_str(text).map_err(|e| parse_error(&e, text, origin))?
        } else {
            let merged = toml::to_string(&table).map_err(|e| ConfigError::Invalid {
                origin: origin.to_owned(),
                message: e.to_string(),
            })?;
            toml::from_str(&merged)
                .map_err(|e| parse_error(&e, &merged, &format!("{origin} (with PHONE2ACT_* overrides)")))?
        };
        config.validate(origin)?;
        Ok(config)
    }

    fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let invalid = |message: String| ConfigError::Invalid {
            origin: origin.to_owned(),
            message,
        };
        let mut names = std::collections::HashSet::new();
        for arm in &self.arms {
            if arm.name.is_empty() || !arm.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(invalid(format!(
                    "arm name {:?} must be non-empty ASCII letters, digits or '_'",
                    arm.name
                )));
            }
            if !names.insert(arm.name.as_str()) {
                return Err(invalid(format!("arm name {:?} appears twice", arm.name)));
            }
            if arm.bridge == BridgeKind::Remote
                && arm.remote.as_ref().is_none_or(|r| r.joint_names.is_empty())
            {
                return Err(invalid(format!(
                    "arm {:?}: bridge \"remote\" needs [arms.remote] joint_names = [...] (the joints its bridge reports)",
                    arm.name
                )));
            }
        }
        let mut cams = std::collections::HashSet::new();
        for cam in &self.cameras {
            if cam.name.is_empty() || !cam.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(invalid(format!(
                    "camera name {:?} must be non-empty ASCII letters, digits or '_'",
                    cam.name
                )));
            }
            if !cams.insert(cam.name.as_str()) {
                return Err(invalid(format!("camera name {:?} appears twice", cam.name)));
            }
            if cam.width == 0 || cam.height == 0 || cam.width % 2 == 1 || cam.height % 2 == 1 {
                return Err(invalid(format!(
                    "camera {:?}: width and height must be even and non-zero (yuv420p), got {}x{}",
                    cam.name, cam.width, cam.height
                )));
            }
            if !(1.0..=120.0).contains(&cam.fps) {
                return Err(invalid(format!(
                    "camera {:?}: fps must be in 1..=120, got {}",
                    cam.name, cam.fps
                )));
            }
            if cam.kind == CameraKind::V4l2 && cam.device.is_none() {
                return Err(invalid(format!(
                    "camera {:?}: kind \"v4l2\" needs `device`",
                    cam.name
                )));
            }
        }
        if !(1.0..=60.0).contains(&self.recorder.fps) {
            return Err(invalid(format!(
                "recorder.fps must be in 1..=60, got {}",
                self.recorder.fps
            )));
        }
        Ok(())
    }
}

fn table_equals_text(table: &toml::Table, text: &str) -> bool {
    toml::from_str::<toml::Table>(text).is_ok_and(|t| &t == table)
}

fn parse_error(e: &toml::de::Error, text: &str, origin: &str) -> ConfigError {
    let (line, column) = e.span().map_or((0, 0), |span| line_col(text, span.start));
    ConfigError::Parse {
        origin: origin.to_owned(),
        line,
        column,
        message: e.message().to_owned(),
    }
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before
        .rfind('\n')
        .map_or(before.len(), |nl| before.len() - nl - 1)
        + 1;
    (line, column)
}

fn apply_env_overrides(
    table: &mut toml::Table,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<(), ConfigError> {
    let mut vars: Vec<(String, String)> = env
        .into_iter()
        .filter(|(k, _)| k.starts_with(ENV_PREFIX) && k.contains("__"))
        .collect();
    vars.sort();
    for (var, raw) in vars {
        let path: Vec<String> = var[ENV_PREFIX.len()..]
            .split("__")
            .map(str::to_ascii_lowercase)
            .collect();
        if path.iter().any(String::is_empty) {
            return Err(ConfigError::Env {
                var,
                message: "empty path segment".to_owned(),
            });
        }
        let value = parse_env_value(&raw);
        let mut cursor = &mut *table;
        for key in &path[..path.len() - 1] {
            let entry = cursor
                .entry(key.clone())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            cursor = match entry {
                toml::Value::Table(t) => t,
                _ => {
                    return Err(ConfigError::Env {
                        var,
                        message: format!(
                            "`{key}` is not a table (arrays of arms/cameras cannot be overridden)"
                        ),
                    });
                }
            };
        }
        cursor.insert(path[path.len() - 1].clone(), value);
    }
    Ok(())
}

fn parse_env_value(raw: &str) -> toml::Value {
    // `value = <raw>` parses ints, floats, bools and arrays; anything else (addresses, paths) is a string.
    toml::from_str::<toml::Table>(&format!("value = {raw}"))
        .ok()
        .and_then(|mut t| t.remove("value"))
        .unwrap_or_else(|| toml::Value::String(raw.to_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, ConfigError> {
        Config::from_toml_str(text, "test.toml", Vec::new())
    }

    #[test]
    fn embedded_default_has_main_arm_and_a_camera() {
        let config = Config::from_toml_str(EMBEDDED_DEFAULT, "embedded", Vec::new()).unwrap();
        assert_eq!(config.arms.len(), 1);
        assert_eq!(config.arms[0].name, "main");
        assert_eq!(config.arms[0].bridge, BridgeKind::Sim);
        assert_eq!(config.cameras.len(), 1);
        assert_eq!(config.server.listen, "127.0.0.1:50051".parse().unwrap());
        assert!(config.recorder.root.starts_with("./datasets"));
    }

    #[test]
    fn unknown_field_names_file_line_and_expected_keys() {
        let err = parse("[server]\nlisten = \"127.0.0.1:1\"\nlisen = 3\n")
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml:3:"), "{err}");
        assert!(err.contains("unknown field `lisen`"), "{err}");
        assert!(err.contains("listen"), "should list expected keys: {err}");
    }

    #[test]
    fn wrong_type_names_line_and_expected_type() {
        let err = parse("[recorder]\nfps = \"fast\"\n").unwrap_err().to_string();
        assert!(err.starts_with("test.toml:2:"), "{err}");
        assert!(err.contains("expected"), "{err}");
    }

    #[test]
    fn duplicate_arm_is_refused() {
        let err =
            parse("[[arms]]\nname = \"a\"\nbridge = \"sim\"\n[[arms]]\nname = \"a\"\nbridge = \"sim\"\n")
                .unwrap_err()
                .to_string();
        assert!(err.contains("appears twice"), "{err}");
    }

    #[test]
    fn every_shipped_config_parses() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/config");
        let mut seen = 0;
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let text = std::fs::read_to_string(&path).unwrap();
                Config::from_toml_str(&text, &path.display().to_string(), Vec::new())
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                seen += 1;
            }
        }
        assert!(
            seen >= 4,
            "expected the default, reference, bimanual and hardware configs, saw {seen}"
        );
    }

    #[test]
    fn a_remote_arm_needs_its_joint_names() {
        let err = parse("[[arms]]\nname = \"r\"\nbridge = \"remote\"\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("joint_names"), "{err}");
        let ok = parse(
            "[[arms]]\nname = \"r\"\nbridge = \"remote\"\n[arms.remote]\njoint_names = [\"j1\", \"j2\"]\n",
        );
        assert!(ok.is_ok(), "{ok:?}");
    }

    #[test]
    fn env_overrides_replace_values() {
        let env = vec![
            ("PHONE2ACT_SERVER__LISTEN".to_owned(), "0.0.0.0:6000".to_owned()),
            ("PHONE2ACT_RECORDER__FPS".to_owned(), "30".to_owned()),
            ("OTHER".to_owned(), "x".to_owned()),
        ];
        let config = Config::from_toml_str(EMBEDDED_DEFAULT, "embedded", env).unwrap();
        assert_eq!(config.server.listen, "0.0.0.0:6000".parse().unwrap());
        assert!((config.recorder.fps - 30.0).abs() < f64::EPSILON);
    }

    #[test]
    fn env_override_with_bad_type_is_an_error() {
        let env = vec![("PHONE2ACT_RECORDER__FPS".to_owned(), "fast".to_owned())];
        let err = Config::from_toml_str(EMBEDDED_DEFAULT, "embedded", env)
            .unwrap_err()
            .to_string();
        assert!(err.contains("PHONE2ACT_"), "{err}");
    }
}
