//! The typed server configuration, read from TOML. Every table denies unknown keys so a typo fails at start
//! with the file, the line and what was expected. `PHONE2ACT_<SECTION>__<KEY>=value` environment variables
//! override single values (`PHONE2ACT_SERVER__LISTEN=0.0.0.0:50051`); values are parsed as TOML when they
//! parse, else taken as strings. Entries of the `arms` and `cameras` arrays are addressed by their index in
//! the file (`PHONE2ACT_ARMS__0__TELEOP__GATE__JUMP_POSITION_M=0.05`); an override changes an entry the
//! file has, it cannot add one.

use serde::{Deserialize, Serialize};
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
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
    /// The flight recorder: off unless this table is present.
    #[serde(default)]
    pub flight_log: Option<FlightLogConfig>,
    /// The `[gateway]` table of the phone gateway `phone2act serve` embeds (rosbridge v2 on ws://:9090, the
    /// phone page over HTTPS on :8443). Opaque here: the server library is not a client of itself, so the
    /// binary that starts the gateway reads and validates this table as the gateway's own config type.
    #[serde(default)]
    pub gateway: toml::Table,
    /// `[storage]`: upload every committed episode to S3-compatible object storage (see docs/fleet.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub storage: Option<phone2act_storage::StorageConfig>,
}

/// gRPC listener and access.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
#[derive(Debug, Clone, Copy, Deserialize, Serialize, PartialEq, Eq)]
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
#[derive(Debug, Clone, Copy, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum DatasetLayout {
    #[default]
    Phone2act,
    LerobotSo101,
}

/// One arm.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
    /// Joint speed limits (`[arms.<name>.joint_limits]`); each robot's data-sheet speed by default (see
    /// docs/joint-limits.md).
    #[serde(default)]
    pub joint_limits: phone2act_core::JointLimitConfig,
}

/// A remote arm: the joints its bridge will report, so the dataset layout is known before it attaches.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RemoteArmConfig {
    /// Joint names in feedback order; a bridge that attaches with other names is refused.
    pub joint_names: Vec<String>,
}

/// Kinds of camera source.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, PartialEq, Eq)]
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
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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

/// Dataset format written by the recorder (`"v3.0"` or `"v2.1"` in the file): the recorder's own enum.
pub use phone2act_dataset::spec::Format as DatasetFormat;

/// The flight recorder: every input of every arm's arbiter, with its time, logged to one file per arm and
/// server run, for `phone2act replay-log`.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FlightLogConfig {
    /// Directory of the logs (created at start).
    pub dir: PathBuf,
    /// Largest size of one log; past it the log ends (and says so), the arm goes on.
    #[serde(default = "default_flight_log_max_bytes")]
    pub max_bytes: u64,
}

/// 256 MiB: about an hour of a phone at 60 Hz with a policy's ticks (about 70 bytes a tick, 350 a phone
/// round).
fn default_flight_log_max_bytes() -> u64 {
    256 << 20
}

/// The recorder.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
    /// Record LeRobot's human-in-the-loop `intervention` column (bool per frame: a person drove an arm), so
    /// that episodes where a phone takes over from a policy load as LeRobot DAgger data. A dataset keeps the
    /// features it was created with: resuming one with the other setting is refused.
    #[serde(default)]
    pub intervention: bool,
    /// Record `next.success` (bool per frame) also when no arm has a scene (hardware arms): every frame is
    /// false except the last one of an episode the operator stops as a success. With a scene the column is
    /// always recorded (the scene's success flag). Like `intervention`, a dataset keeps the features it was
    /// created with.
    #[serde(default)]
    pub success: bool,
    /// Save an episode when its recorded length reaches this many seconds (LeRobot's `episode_time_s`);
    /// unset: episodes run until Stop. The episode then has exactly `episode_time_s * fps` frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episode_time_s: Option<f64>,
    /// After each save, a reset period of this many seconds (LeRobot's `reset_time_s`): nothing is recorded,
    /// simulated scenes re-draw themselves, the phone counts down. Starting an episode cuts it short.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reset_time_s: Option<f64>,
    /// At the end of the reset period, start the next episode with the same task and operator (as LeRobot's
    /// record loop goes on to its next episode). Needs `reset_time_s` (0 for none).
    #[serde(default)]
    pub start_next_after_reset: bool,
    /// While no episode is recorded, keep the last this many seconds (every camera's video, encoded, and the
    /// synced rows) so that the operator can save them as an episode after the fact (LeRobot's `highlight`
    /// ring buffer; `Episodes.SaveHighlight`, the phone's SAVE LAST button, `phone2act episode highlight`).
    /// Unset: off. Costs what an episode in progress costs (one encoder per camera) all the time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub highlight_s: Option<f64>,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            root: default_dataset_root(),
            format: default_format(),
            fps: default_dataset_fps(),
            robot_type: default_robot_type(),
            video_codec: None,
            intervention: false,
            success: false,
            episode_time_s: None,
            reset_time_s: None,
            start_next_after_reset: false,
            highlight_s: None,
        }
    }
}

/// Longest episode time limit and reset period accepted (a day): a longer one is a typo.
pub const MAX_EPISODE_TIMING_S: f64 = 86_400.0;

/// Longest `highlight_s` accepted (10 minutes): the encoded video is kept in memory (see docs/datasets.md).
pub const MAX_HIGHLIGHT_S: f64 = 600.0;

impl RecorderConfig {
    /// The episode time limit and reset period, checked (see `phone2act_core::episode_clock`).
    pub fn episode_limits(&self) -> Result<phone2act_core::episode_clock::EpisodeLimits, String> {
        let fps = self.fps;
        let check = |name: &str, v: Option<f64>, min_s: f64| match v {
            Some(s) if !(s.is_finite() && (min_s..=MAX_EPISODE_TIMING_S).contains(&s)) => Err(format!(
                "recorder.{name} must be in {min_s}..={MAX_EPISODE_TIMING_S} s, got {s}"
            )),
            _ => Ok(v),
        };
        // At least one frame: a shorter limit would save empty episodes, which are refused.
        let episode_time_s = check("episode_time_s", self.episode_time_s, 1.0 / fps.max(1.0))?;
        let reset_time_s = check("reset_time_s", self.reset_time_s, 0.0)?;
        if self.start_next_after_reset && reset_time_s.is_none() {
            return Err(
                "recorder.start_next_after_reset needs recorder.reset_time_s (0 starts the next episode at once)"
                    .to_owned(),
            );
        }
        Ok(phone2act_core::episode_clock::EpisodeLimits {
            episode_time_s,
            reset_time_s,
            auto_start: self.start_next_after_reset,
        })
    }

    /// `highlight_s`, checked: at least one frame, at most [`MAX_HIGHLIGHT_S`].
    pub fn highlight(&self) -> Result<Option<f64>, String> {
        let min_s = 1.0 / self.fps.max(1.0);
        match self.highlight_s {
            Some(s) if !(s.is_finite() && (min_s..=MAX_HIGHLIGHT_S).contains(&s)) => Err(format!(
                "recorder.highlight_s must be in {min_s}..={MAX_HIGHLIGHT_S} s, got {s}"
            )),
            v => Ok(v),
        }
    }

    /// Frames an episode holds at most under `episode_time_s`.
    pub fn frame_limit(&self) -> Option<u64> {
        self.episode_time_s
            .map(|s| ((s * self.fps).round() as u64).max(1))
    }
}

impl RecorderConfig {
    /// The codec actually used.
    pub fn effective_video_codec(&self) -> &str {
        self.video_codec
            .as_deref()
            .unwrap_or(self.format.default_encoder())
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

/// Largest camera frame side accepted, in pixels (8K UHD). A frame is allocated as `width * height * 3`
/// bytes in every queue slot, so an unbounded size aborts the process instead of failing with a message.
pub const MAX_CAMERA_WIDTH: u32 = 7680;
/// Largest camera frame height, in pixels (8K UHD).
pub const MAX_CAMERA_HEIGHT: u32 = 4320;
/// Most arms and cameras one server drives; each costs threads and a dataset feature.
pub const MAX_ARMS: usize = 16;
/// Most cameras one server records.
pub const MAX_CAMERAS: usize = 16;
/// Most joints a remote arm may declare (the dataset's state vector grows with each).
pub const MAX_REMOTE_JOINTS: usize = 64;
/// Most steps a policy chunk may be configured to accept.
pub const MAX_CHUNK_STEPS: usize = 100_000;
/// Longest arm or camera name and `robot_type`: they become dataset column names and info.json values.
pub const MAX_NAME_CHARS: usize = 64;
/// Fastest simulated arm step rate, Hz: the simulation runs on its own thread at this rate.
pub const MAX_SIM_STEP_HZ: f64 = 10_000.0;

/// Smallest flight log accepted: below it a log ends within seconds.
pub const MIN_FLIGHT_LOG_BYTES: u64 = 64 << 10;

/// What replaces a secret (server token, gateway pairing token, ...) in printed or recorded configuration.
pub const REDACTED: &str = "<redacted>";

impl Config {
    /// The embedded default, with environment overrides applied.
    pub fn embedded_default() -> Result<Self, ConfigError> {
        ConfigSource::embedded().config(std::env::vars())
    }

    /// Reads `path`, applying environment overrides from the process environment.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        ConfigSource::file(path)?.config(std::env::vars())
    }

    /// Parses TOML text; `origin` names it in errors; `env` supplies `PHONE2ACT_*` overrides.
    ///
    /// Errors in the text carry the line and column in the text; an error that only an override causes
    /// names the environment variable instead (the merged table has no lines a user could look up). No error
    /// shows the value of a secret.
    pub fn from_toml_str(
        text: &str,
        origin: &str,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self, ConfigError> {
        parse_layered(text, origin, &overrides(env), Config::validate)
    }

    /// The configuration as TOML, every default filled in and every secret replaced by [`REDACTED`]: what
    /// `serve --check` prints and what a dataset records as its provenance.
    pub fn to_redacted_toml(&self) -> Result<String, toml::ser::Error> {
        let mut value = toml::Value::try_from(self)?;
        redact_secrets(&mut value);
        toml::to_string(&value)
    }

    /// Every check `serve` would otherwise meet only while starting (bridge tables, camera sources, the
    /// recorder's rules, the dataset root), so that `serve --check` refuses exactly what `serve` refuses.
    fn validate(&self) -> Result<(), String> {
        if self.arms.is_empty() {
            return Err(
                "no arms: add one, e.g. `[[arms]]` with `name = \"main\"` and `bridge = \"sim\"` \
                 (server/config/reference.toml lists every key)"
                    .to_owned(),
            );
        }
        if self.arms.len() > MAX_ARMS || self.cameras.len() > MAX_CAMERAS {
            return Err(format!(
                "{} arms and {} cameras configured; at most {MAX_ARMS} arms and {MAX_CAMERAS} cameras",
                self.arms.len(),
                self.cameras.len()
            ));
        }
        if let Some(flight) = &self.flight_log {
            if flight.dir.as_os_str().is_empty() {
                return Err(
                    "flight_log.dir is empty: name the directory of the logs, or remove [flight_log]"
                        .to_owned(),
                );
            }
            if flight.max_bytes < MIN_FLIGHT_LOG_BYTES {
                return Err(format!(
                    "flight_log.max_bytes = {} is below {MIN_FLIGHT_LOG_BYTES} (a few seconds of inputs)",
                    flight.max_bytes
                ));
            }
        }
        let mut names = std::collections::HashSet::new();
        for arm in &self.arms {
            if arm.name.is_empty() || !arm.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(format!(
                    "arm name {:?} must be non-empty ASCII letters, digits or '_'",
                    arm.name
                ));
            }
            if arm.name.len() > MAX_NAME_CHARS {
                return Err(format!(
                    "arm name {:?} is longer than {MAX_NAME_CHARS} characters",
                    arm.name
                ));
            }
            if !names.insert(arm.name.as_str()) {
                return Err(format!("arm name {:?} appears twice", arm.name));
            }
            arm.validate()
                .map_err(|message| format!("arm {:?}: {message}", arm.name))?;
        }
        let mut cams = std::collections::HashSet::new();
        for cam in &self.cameras {
            if cam.name.is_empty() || !cam.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(format!(
                    "camera name {:?} must be non-empty ASCII letters, digits or '_'",
                    cam.name
                ));
            }
            if cam.name.len() > MAX_NAME_CHARS {
                return Err(format!(
                    "camera name {:?} is longer than {MAX_NAME_CHARS} characters",
                    cam.name
                ));
            }
            if !cams.insert(cam.name.as_str()) {
                return Err(format!("camera name {:?} appears twice", cam.name));
            }
            if cam.width == 0 || cam.height == 0 || cam.width % 2 == 1 || cam.height % 2 == 1 {
                return Err(format!(
                    "camera {:?}: width and height must be even and non-zero (yuv420p), got {}x{}",
                    cam.name, cam.width, cam.height
                ));
            }
            if cam.width > MAX_CAMERA_WIDTH || cam.height > MAX_CAMERA_HEIGHT {
                return Err(format!(
                    "camera {:?}: {}x{} is larger than {MAX_CAMERA_WIDTH}x{MAX_CAMERA_HEIGHT}",
                    cam.name, cam.width, cam.height
                ));
            }
            if !(1.0..=120.0).contains(&cam.fps) {
                return Err(format!(
                    "camera {:?}: fps must be in 1..=120, got {}",
                    cam.name, cam.fps
                ));
            }
            if cam.kind == CameraKind::V4l2 && cam.device.is_none() {
                return Err(format!("camera {:?}: kind \"v4l2\" needs `device`", cam.name));
            }
            if cam.kind == CameraKind::SimRender {
                self.check_sim_render(cam)?;
            }
        }
        if !(1.0..=60.0).contains(&self.recorder.fps) {
            return Err(format!(
                "recorder.fps must be in 1..=60, got {}",
                self.recorder.fps
            ));
        }
        if self.recorder.fps.fract() != 0.0 {
            return Err(format!(
                "recorder.fps must be a whole number (LeRobot datasets store an integer rate), got {}",
                self.recorder.fps
            ));
        }
        self.recorder.episode_limits()?;
        self.recorder.highlight()?;
        self.check_root()?;
        let cameras: Vec<_> = self
            .cameras
            .iter()
            .map(|c| phone2act_dataset::spec::CameraSpec {
                name: c.name.clone(),
                width: c.width,
                height: c.height,
            })
            .collect();
        phone2act_dataset::spec::check_cameras(
            &cameras,
            self.recorder.video_codec.as_deref(),
            self.recorder.format,
        )
        .map_err(|e| format!("recorder: {e}"))?;
        if self.recorder.robot_type.is_empty() || self.recorder.robot_type.len() > MAX_NAME_CHARS {
            return Err(format!(
                "recorder.robot_type must be 1..={MAX_NAME_CHARS} characters, got {}",
                self.recorder.robot_type.len()
            ));
        }
        Ok(())
    }

    /// A `sim_render` camera shows a simulated arm: the one it names, else the first.
    fn check_sim_render(&self, cam: &CameraConfig) -> Result<(), String> {
        let sims: Vec<&str> = self
            .arms
            .iter()
            .filter(|a| a.bridge == BridgeKind::Sim)
            .map(|a| a.name.as_str())
            .collect();
        match &cam.arm {
            None if sims.is_empty() => Err(format!(
                "camera {:?}: kind \"sim_render\" needs an arm with bridge = \"sim\", and none is configured",
                cam.name
            )),
            Some(arm) if !sims.contains(&arm.as_str()) => Err(format!(
                "camera {:?}: arm = {arm:?} is not a simulated arm (simulated arms: {})",
                cam.name,
                if sims.is_empty() {
                    "none".to_owned()
                } else {
                    sims.join(", ")
                }
            )),
            _ => Ok(()),
        }
    }

    /// The dataset root must be a directory, or a path one can be created at: an empty path passes
    /// `create_dir_all` and then fails every save, and a file in the way fails every start.
    fn check_root(&self) -> Result<(), String> {
        let root = &self.recorder.root;
        if root.as_os_str().is_empty() {
            return Err(
                "recorder.root is empty (an unset shell variable in PHONE2ACT_RECORDER__ROOT?): name the \
                 dataset directory"
                    .to_owned(),
            );
        }
        if let Some(existing) = root.ancestors().find(|a| !a.as_os_str().is_empty() && a.exists())
            && !existing.is_dir()
        {
            return Err(if existing == root.as_path() {
                format!("recorder.root {} is a file, not a directory", root.display())
            } else {
                format!(
                    "recorder.root {} cannot be created: {} is a file",
                    root.display(),
                    existing.display()
                )
            });
        }
        if let Some(storage) = &self.storage {
            storage.validate()?;
        }
        Ok(())
    }
}

impl ArmConfig {
    /// The speed limit of each arm joint (rad/s): `joint_limits.max_velocity_rad_s`, or the robot's default.
    pub fn joint_speeds_rad_s(&self) -> Result<Vec<f64>, phone2act_core::ConfigError> {
        use phone2act_core::joint_motion::{
            CR5_MAX_VELOCITY_RAD_S, REMOTE_DEFAULT_MAX_VELOCITY_RAD_S, STS3215_MAX_VELOCITY_RAD_S,
        };
        let (joints, default_rad_s) = match self.bridge {
            BridgeKind::Sim | BridgeKind::So101 => (
                phone2act_core::kinematics::SO101_ARM_DOF,
                STS3215_MAX_VELOCITY_RAD_S,
            ),
            BridgeKind::Dobot => (6, CR5_MAX_VELOCITY_RAD_S),
            BridgeKind::Remote => (
                self.remote.as_ref().map_or(0, |r| r.joint_names.len()),
                REMOTE_DEFAULT_MAX_VELOCITY_RAD_S,
            ),
        };
        let speeds = self.joint_limits.resolve(joints, default_rad_s)?;
        // A remote arm's joint count may come from its bridge: an acceleration list is checked against it then.
        if joints > 0 || self.joint_limits.max_acceleration_rad_s2.len() <= 1 {
            self.joint_limits.resolve_acceleration(joints.max(1))?;
        }
        Ok(speeds)
    }

    /// Ranges serde cannot check, for this arm and the bridge section it uses.
    fn validate(&self) -> Result<(), String> {
        self.teleop.validate().map_err(|e| format!("teleop: {e}"))?;
        self.joint_speeds_rad_s()
            .map_err(|e| format!("joint_limits: {e}"))?;
        self.chunk.validate().map_err(|e| format!("chunk: {e}"))?;
        if self.chunk.max_steps == 0 || self.chunk.max_steps > MAX_CHUNK_STEPS {
            return Err(format!(
                "chunk.max_steps must be in 1..={MAX_CHUNK_STEPS}, got {}",
                self.chunk.max_steps
            ));
        }
        if self.chunk.blend_steps > self.chunk.max_steps {
            return Err(format!(
                "chunk.blend_steps ({}) must not exceed chunk.max_steps ({})",
                self.chunk.blend_steps, self.chunk.max_steps
            ));
        }
        if let Some(sim) = &self.sim {
            sim.validate().map_err(|e| format!("sim: {e}"))?;
            if sim.step_hz > MAX_SIM_STEP_HZ {
                return Err(format!(
                    "sim.step_hz must be at most {MAX_SIM_STEP_HZ}, got {}",
                    sim.step_hz
                ));
            }
        }
        if let Some(dobot) = &self.dobot {
            dobot.validate().map_err(|e| format!("dobot: {e}"))?;
        }
        if let Some(so101) = &self.so101 {
            so101.validate().map_err(|e| format!("so101: {e}"))?;
        }
        match self.bridge {
            BridgeKind::Dobot if self.dobot.is_none() => {
                return Err(
                    "bridge \"dobot\" needs an [arms.dobot] table (at least `host`, the controller's address)"
                        .to_owned(),
                );
            }
            BridgeKind::So101 if self.so101.is_none() => {
                return Err(
                    "bridge \"so101\" needs an [arms.so101] table (at least `port` and `calibration_file`)"
                        .to_owned(),
                );
            }
            _ => {}
        }
        // Joint targets need the SO-101's kinematics: its bridges, or a remote one reporting its joints.
        let so101_joints = match self.bridge {
            BridgeKind::Sim | BridgeKind::So101 => true,
            BridgeKind::Dobot => false,
            BridgeKind::Remote => self.remote.as_ref().is_some_and(|r| {
                r.joint_names
                    .iter()
                    .map(String::as_str)
                    .eq(phone2act_core::kinematics::SO101_ARM_JOINT_NAMES.iter().copied())
            }),
        };
        if self.action_mode == phone2act_core::ActionMode::Joint && !so101_joints {
            return Err(format!(
                "action_mode = \"joint\" needs an SO-101 arm (bridge \"sim\" or \"so101\", or a remote one with \
                 joint_names {:?}); bridge \"{}\" moves by end-effector targets",
                phone2act_core::kinematics::SO101_ARM_JOINT_NAMES,
                self.bridge.as_str()
            ));
        }
        if self.dataset_layout == DatasetLayout::LerobotSo101
            && (self.action_mode != phone2act_core::ActionMode::Joint || !so101_joints)
        {
            return Err(
                "dataset_layout = \"lerobot_so101\" needs an SO-101 (sim or so101 bridge) with action_mode = \"joint\""
                    .to_owned(),
            );
        }
        if self.bridge == BridgeKind::Remote {
            let joints = self.remote.as_ref().map_or(0, |r| r.joint_names.len());
            if joints == 0 {
                return Err(
                    "bridge \"remote\" needs [arms.remote] joint_names = [...] (the joints its bridge reports)"
                        .to_owned(),
                );
            }
            if joints > MAX_REMOTE_JOINTS {
                return Err(format!(
                    "remote.joint_names has {joints} names; at most {MAX_REMOTE_JOINTS}"
                ));
            }
        }
        Ok(())
    }
}

/// Where a configuration's text comes from: a file, or the embedded default. The server's keys and the
/// `[gateway]` table are both read from it, so both locate their errors the same way.
#[derive(Debug, Clone)]
pub struct ConfigSource {
    text: String,
    origin: String,
}

impl ConfigSource {
    /// Reads `path`.
    pub fn file(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Ok(Self {
            text,
            origin: path.display().to_string(),
        })
    }

    /// The embedded default.
    pub fn embedded() -> Self {
        Self {
            text: EMBEDDED_DEFAULT.to_owned(),
            origin: "<embedded default>".to_owned(),
        }
    }

    /// How errors name this source: the file's path, or `<embedded default>`.
    pub fn origin(&self) -> &str {
        &self.origin
    }

    /// The server's configuration, with `env`'s `PHONE2ACT_*` overrides applied.
    pub fn config(&self, env: impl IntoIterator<Item = (String, String)>) -> Result<Config, ConfigError> {
        Config::from_toml_str(&self.text, &self.origin, env)
    }

    /// The `[gateway]` table as the gateway's config type `T` (defaults for what it leaves out), with the
    /// `PHONE2ACT_GATEWAY__*` overrides applied and `validate` run: its errors name the file's line or the
    /// variable exactly as the server's own keys do. `Config` keeps the table opaque (the server library is no
    /// client of itself), so the binary that starts the gateway calls this with the gateway's type.
    pub fn gateway<T>(
        &self,
        env: impl IntoIterator<Item = (String, String)>,
        validate: impl Fn(&T) -> Result<(), String>,
    ) -> Result<T, ConfigError>
    where
        T: serde::de::DeserializeOwned + Default,
    {
        let section = parse_layered(
            &self.text,
            &self.origin,
            &overrides(env),
            |s: &GatewaySection<T>| validate(&s.gateway),
        )?;
        Ok(section.gateway)
    }
}

/// Only the `[gateway]` table of a configuration; every other key is the server's and ignored here.
#[derive(Deserialize)]
#[serde(bound(deserialize = "T: serde::de::DeserializeOwned + Default"))]
struct GatewaySection<T> {
    #[serde(default)]
    gateway: T,
}

/// The `PHONE2ACT_*` overrides among `env`, in a stable order.
fn overrides(env: impl IntoIterator<Item = (String, String)>) -> Vec<(String, String)> {
    let mut overrides: Vec<(String, String)> = env
        .into_iter()
        .filter(|(k, _)| k.starts_with(ENV_PREFIX) && k.contains("__"))
        .collect();
    overrides.sort();
    overrides
}

/// Parses `text` as `T`, applies `overrides`, runs `validate`, and locates what fails: a file error by its
/// line (and the file alone when the overrides are not part of the problem), an override error by its
/// variable. Every message is cleared of the secrets the text or the overrides hold.
fn parse_layered<T: serde::de::DeserializeOwned>(
    text: &str,
    origin: &str,
    overrides: &[(String, String)],
    validate: impl Fn(&T) -> Result<(), String>,
) -> Result<T, ConfigError> {
    let file_table: toml::Table = toml::from_str(text).map_err(|e| parse_error(&e, text, origin))?;
    let secrets = Secrets::collect(&file_table, overrides);
    parse_layered_inner(text, origin, &file_table, overrides, validate).map_err(|e| secrets.redact(e))
}

fn parse_layered_inner<T: serde::de::DeserializeOwned>(
    text: &str,
    origin: &str,
    file_table: &toml::Table,
    overrides: &[(String, String)],
    validate: impl Fn(&T) -> Result<(), String>,
) -> Result<T, ConfigError> {
    let invalid = |origin: String, message: String| ConfigError::Invalid { origin, message };
    if overrides.is_empty() {
        let value: T = toml::from_str(text).map_err(|e| parse_error(&e, text, origin))?;
        validate(&value).map_err(|m| invalid(origin.to_owned(), m))?;
        return Ok(value);
    }
    let mut table = file_table.clone();
    for (var, raw) in overrides {
        apply_override(&mut table, var, raw)?;
    }
    let value = match T::deserialize(toml::Value::Table(table)) {
        Ok(value) => value,
        Err(merged) => return Err(blame::<T>(text, origin, file_table, overrides, &merged)),
    };
    if let Err(message) = validate(&value) {
        // Name the overrides only when they are part of the problem: the file alone may be fine.
        let file_alone = toml::from_str::<T>(text).map(|v| validate(&v));
        let same_in_file = matches!(&file_alone, Ok(Err(m)) if *m == message);
        // The overrides that alone bring the message about, else (a combination) all of them.
        let alone: Vec<&str> = overrides
            .iter()
            .filter(|(var, raw)| {
                let mut table = file_table.clone();
                apply_override(&mut table, var, raw).is_ok()
                    && T::deserialize(toml::Value::Table(table))
                        .is_ok_and(|v| matches!(validate(&v), Err(m) if m == message))
            })
            .map(|(k, _)| k.as_str())
            .collect();
        let names: Vec<&str> = if alone.is_empty() {
            overrides.iter().map(|(k, _)| k.as_str()).collect()
        } else {
            alone
        };
        return Err(invalid(
            if same_in_file {
                origin.to_owned()
            } else {
                format!("{origin} (with {})", names.join(", "))
            },
            message,
        ));
    }
    Ok(value)
}

/// Names the input that caused `merged`, the error of the configuration with overrides applied: the file
/// (with its line) when the file alone fails the same way, else the first override that breaks a file that
/// parses on its own.
fn blame<T: serde::de::DeserializeOwned>(
    text: &str,
    origin: &str,
    file_table: &toml::Table,
    overrides: &[(String, String)],
    merged: &toml::de::Error,
) -> ConfigError {
    match toml::from_str::<T>(text) {
        Err(e) if e.message() == merged.message() => return parse_error(&e, text, origin),
        Ok(_) => {
            for (var, raw) in overrides {
                let mut table = file_table.clone();
                if apply_override(&mut table, var, raw).is_ok()
                    && let Err(e) = T::deserialize(toml::Value::Table(table))
                {
                    return ConfigError::Env {
                        var: var.clone(),
                        message: e.message().to_owned(),
                    };
                }
            }
        }
        Err(_) => {}
    }
    let names: Vec<&str> = overrides.iter().map(|(k, _)| k.as_str()).collect();
    ConfigError::Env {
        var: names.join(", "),
        message: format!("{} (in {origin} with these overrides applied)", merged.message()),
    }
}

/// The secret values of one configuration (file and overrides), to clear from its error messages: a type
/// error quotes the value it could not use, and a token is no less secret for being mistyped.
struct Secrets(Vec<String>);

impl Secrets {
    fn collect(file: &toml::Table, overrides: &[(String, String)]) -> Self {
        fn walk(value: &toml::Value, secret: bool, out: &mut Vec<String>) {
            match value {
                toml::Value::Table(table) => {
                    for (key, v) in table {
                        walk(v, secret || is_secret_key(key), out);
                    }
                }
                toml::Value::Array(items) => items.iter().for_each(|v| walk(v, secret, out)),
                toml::Value::String(s) if secret => out.push(s.clone()),
                other if secret => out.push(other.to_string()),
                _ => {}
            }
        }
        let mut found = Vec::new();
        for (key, v) in file {
            walk(v, is_secret_key(key), &mut found);
        }
        for (var, raw) in overrides {
            if var.rsplit("__").next().is_some_and(is_secret_key) {
                found.push(raw.clone());
            }
        }
        // Longest first, so that a secret containing another is cleared whole.
        found.retain(|s| !s.is_empty());
        found.sort_by_key(|s| std::cmp::Reverse(s.len()));
        Self(found)
    }

    fn clear(&self, message: String) -> String {
        self.0
            .iter()
            .fold(message, |m, secret| m.replace(secret.as_str(), REDACTED))
    }

    fn redact(&self, error: ConfigError) -> ConfigError {
        match error {
            ConfigError::Parse {
                origin,
                line,
                column,
                message,
            } => ConfigError::Parse {
                origin,
                line,
                column,
                message: self.clear(message),
            },
            ConfigError::Invalid { origin, message } => ConfigError::Invalid {
                origin,
                message: self.clear(message),
            },
            ConfigError::Env { var, message } => ConfigError::Env {
                var,
                message: self.clear(message),
            },
            read @ ConfigError::Read { .. } => read,
        }
    }
}

/// Keys whose values are credentials (`server.token`, `gateway.token`, and any later `*_token`, `*password*`,
/// `*secret*`); `require_token` and `rosbridge_require_token` are switches about a token, not one.
fn is_secret_key(key: &str) -> bool {
    let key = key.to_ascii_lowercase();
    !key.contains("require")
        && (key == "token" || key.ends_with("_token") || key.contains("password") || key.contains("secret"))
}

fn redact_secrets(value: &mut toml::Value) {
    match value {
        toml::Value::Table(table) => {
            for (key, v) in table.iter_mut() {
                // Only strings hold credentials; `require_token = true` is a switch, shown as it is.
                if is_secret_key(key) && v.is_str() {
                    *v = toml::Value::String(REDACTED.to_owned());
                } else {
                    redact_secrets(v);
                }
            }
        }
        toml::Value::Array(items) => items.iter_mut().for_each(redact_secrets),
        _ => {}
    }
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
    let before = text.get(..offset.min(text.len())).unwrap_or(text);
    let line = before.matches('\n').count() + 1;
    let column = before
        .rfind('\n')
        .map_or(before.len(), |nl| before.len() - nl - 1)
        + 1;
    (line, column)
}

/// Applies one `PHONE2ACT_A__B__C=value` override: `A`, `B` name table keys (lower-cased) or, inside an
/// array such as `arms`, the index of an existing entry.
fn apply_override(table: &mut toml::Table, var: &str, raw: &str) -> Result<(), ConfigError> {
    let err = |message: String| ConfigError::Env {
        var: var.to_owned(),
        message,
    };
    let path: Vec<String> = var[ENV_PREFIX.len()..]
        .split("__")
        .map(str::to_ascii_lowercase)
        .collect();
    if path.iter().any(String::is_empty) {
        return Err(err("empty path segment".to_owned()));
    }
    let (last, parents) = path.split_last().ok_or_else(|| err("empty path".to_owned()))?;
    let mut cursor = table;
    let mut walked = String::new();
    let mut segments = parents.iter();
    while let Some(key) = segments.next() {
        let entry = cursor
            .entry(key.clone())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        walked = if walked.is_empty() {
            key.clone()
        } else {
            format!("{walked}.{key}")
        };
        cursor = match entry {
            toml::Value::Table(t) => t,
            toml::Value::Array(items) => {
                let count = items.len();
                let index = segments.next().ok_or_else(|| {
                    err(format!(
                        "`{walked}` is an array of {count}: name an entry by its index, e.g. {}{}__0__...",
                        ENV_PREFIX,
                        walked.to_ascii_uppercase().replace('.', "__")
                    ))
                })?;
                let item = index
                    .parse::<usize>()
                    .ok()
                    .and_then(|i| items.get_mut(i))
                    .ok_or_else(|| {
                        err(format!(
                            "`{walked}` has {count} entries (0..{count}); `{index}` is not one of them \
                             (an override changes an entry the file has, it cannot add one)"
                        ))
                    })?;
                walked = format!("{walked}[{index}]");
                match item {
                    toml::Value::Table(t) => t,
                    _ => return Err(err(format!("`{walked}` is not a table"))),
                }
            }
            _ => return Err(err(format!("`{walked}` is a value, not a table"))),
        };
    }
    // A secret is a string whatever it looks like: `123456789012345`, `0x1f`, `1e9` and `true` are tokens too.
    let value = if is_secret_key(last) {
        toml::Value::String(raw.to_owned())
    } else {
        parse_env_value(raw)
    };
    cursor.insert(last.clone(), value);
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
    fn joint_accelerations_are_checked_like_speeds() {
        let arm = "[[arms]]\nname = \"a\"\nbridge = \"sim\"\n[arms.joint_limits]\n";
        let ok = parse(&format!("{arm}max_acceleration_rad_s2 = [20.0]\n")).unwrap();
        assert_eq!(ok.arms[0].joint_limits.max_acceleration_rad_s2, vec![20.0]);
        for (value, why) in [
            ("[1.0, 2.0]", "needs 5 values"),
            ("[0.0]", "must be finite and > 0"),
        ] {
            let err = parse(&format!("{arm}max_acceleration_rad_s2 = {value}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("max_acceleration_rad_s2") && err.contains(why),
                "{err}"
            );
        }
    }

    #[test]
    fn a_flight_log_needs_a_directory_and_room_for_more_than_a_few_seconds() {
        let arm = "[[arms]]\nname = \"a\"\nbridge = \"sim\"\n";
        let ok = parse(&format!("{arm}[flight_log]\ndir = \"logs\"\n")).unwrap();
        let flight = ok.flight_log.unwrap();
        assert_eq!((flight.dir.to_str(), flight.max_bytes), (Some("logs"), 256 << 20));
        assert!(parse(arm).unwrap().flight_log.is_none(), "off unless asked for");
        let err = parse(&format!("{arm}[flight_log]\ndir = \"\"\n"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("flight_log.dir is empty"), "{err}");
        let err = parse(&format!("{arm}[flight_log]\ndir = \"l\"\nmax_bytes = 65535\n"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("max_bytes = 65535 is below 65536"), "{err}");
        parse(&format!("{arm}[flight_log]\ndir = \"l\"\nmax_bytes = 65536\n")).unwrap();
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

    const SIM: &str = "[[arms]]\nname = \"main\"\nbridge = \"sim\"\n";

    fn with_env(text: &str, env: &[(&str, &str)]) -> Result<Config, ConfigError> {
        let env = env.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned()));
        Config::from_toml_str(text, "test.toml", env)
    }

    #[test]
    fn episode_time_limit_and_reset_period_are_checked() {
        let c = with_env(
            SIM,
            &[
                ("PHONE2ACT_RECORDER__EPISODE_TIME_S", "30"),
                ("PHONE2ACT_RECORDER__RESET_TIME_S", "0"),
                ("PHONE2ACT_RECORDER__START_NEXT_AFTER_RESET", "true"),
            ],
        )
        .unwrap();
        assert_eq!(c.recorder.frame_limit(), Some(600), "30 s at 20 fps");
        let limits = c.recorder.episode_limits().unwrap();
        assert_eq!(
            (limits.episode_time_s, limits.reset_time_s, limits.auto_start),
            (Some(30.0), Some(0.0), true)
        );
        // The effective configuration (`serve --check`, provenance) shows them.
        assert!(c.to_redacted_toml().unwrap().contains("episode_time_s = 30.0"));
        assert_eq!(with_env(SIM, &[]).unwrap().recorder.frame_limit(), None);
        for (key, value, says) in [
            (
                "PHONE2ACT_RECORDER__EPISODE_TIME_S",
                "0",
                "recorder.episode_time_s must be in 0.05",
            ),
            (
                "PHONE2ACT_RECORDER__EPISODE_TIME_S",
                "nan",
                "recorder.episode_time_s",
            ),
            (
                "PHONE2ACT_RECORDER__RESET_TIME_S",
                "-1",
                "recorder.reset_time_s must be in 0",
            ),
            (
                "PHONE2ACT_RECORDER__RESET_TIME_S",
                "1e9",
                "recorder.reset_time_s must be in 0",
            ),
            (
                "PHONE2ACT_RECORDER__START_NEXT_AFTER_RESET",
                "true",
                "needs recorder.reset_time_s",
            ),
        ] {
            let err = with_env(SIM, &[(key, value)]).unwrap_err().to_string();
            assert!(err.contains(says), "{key}={value}: {err}");
        }
    }

    #[test]
    fn highlight_seconds_are_checked() {
        assert_eq!(with_env(SIM, &[]).unwrap().recorder.highlight_s, None);
        let c = with_env(SIM, &[("PHONE2ACT_RECORDER__HIGHLIGHT_S", "15")]).unwrap();
        assert_eq!(c.recorder.highlight(), Ok(Some(15.0)));
        assert!(c.to_redacted_toml().unwrap().contains("highlight_s = 15.0"));
        for value in ["0", "-1", "nan", "601"] {
            let err = with_env(SIM, &[("PHONE2ACT_RECORDER__HIGHLIGHT_S", value)])
                .unwrap_err()
                .to_string();
            assert!(err.contains("recorder.highlight_s must be in"), "{value}: {err}");
        }
    }

    #[test]
    fn storage_is_optional_checked_and_overridable_from_the_environment() {
        assert!(with_env(SIM, &[]).unwrap().storage.is_none());
        let c = with_env(
            SIM,
            &[
                ("PHONE2ACT_STORAGE__URL", "s3://fleet/lab"),
                ("PHONE2ACT_STORAGE__MAX_UPLOAD_BYTES_PER_S", "500000"),
            ],
        )
        .unwrap();
        let s = c.storage.as_ref().unwrap();
        assert_eq!(
            (s.url.as_str(), s.max_upload_bytes_per_s),
            ("s3://fleet/lab", Some(500_000))
        );
        assert!(s.retain_local);
        assert!(c.to_redacted_toml().unwrap().contains("[storage]"));
        let c = with_env(
            SIM,
            &[
                ("PHONE2ACT_STORAGE__URL", "s3://fleet/lab"),
                ("PHONE2ACT_STORAGE__RETAIN_LOCAL", "false"),
            ],
        )
        .unwrap();
        assert!(!c.storage.as_ref().unwrap().retain_local);
        for (key, value, expected) in [
            ("URL", "https://fleet/lab", "storage.url"),
            ("ENDPOINT", "minio:9000", "storage.endpoint"),
            ("MAX_UPLOAD_BYTES_PER_S", "0", "storage.max_upload_bytes_per_s"),
            ("REQUEST_TIMEOUT_S", "0", "storage.request_timeout_s"),
            ("REQUEST_TIMEOUT_S", "-1", "storage.request_timeout_s"),
            ("STATION_ID", "a/b", "storage.station_id"),
            ("RETAIN_LOCAL", "maybe", "PHONE2ACT_STORAGE__RETAIN_LOCAL"),
        ] {
            let var = format!("PHONE2ACT_STORAGE__{key}");
            let mut env = vec![(var.as_str(), value)];
            if key != "URL" {
                env.push(("PHONE2ACT_STORAGE__URL", "s3://fleet/lab"));
            }
            let err = with_env(SIM, &env).unwrap_err().to_string();
            assert!(err.contains(expected), "{key}={value}: {err}");
        }
        // Keys are never secrets: a key named like one is refused, not silently accepted.
        let err = with_env(
            SIM,
            &[
                ("PHONE2ACT_STORAGE__URL", "s3://b"),
                ("PHONE2ACT_STORAGE__SECRET_ACCESS_KEY", "x"),
            ],
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("secret_access_key"), "{err}");
    }

    #[test]
    fn huge_cameras_and_sizes_are_refused_with_the_limit() {
        let cam = |w: u32, h: u32| {
            format!("{SIM}[[cameras]]\nname = \"c\"\nkind = \"test_pattern\"\nwidth = {w}\nheight = {h}\n")
        };
        let err = parse(&cam(100_000, 100_000)).unwrap_err().to_string();
        assert!(
            err.starts_with("test.toml: camera \"c\": 100000x100000 is larger than 7680x4320"),
            "{err}"
        );
        assert!(parse(&cam(7680, 4320)).is_ok());
        for (extra, needle) in [
            ("[arms.chunk]\nmax_steps = 100000000\n", "chunk.max_steps"),
            ("[arms.chunk]\nblend_steps = 20000\n", "blend_steps"),
            // A loader may hold an arm for an hour at most; 0 or negative would release at once.
            (
                "[arms.chunk]\nmax_loading_s = 7200\n",
                "max_loading_s must be in (0, 3600]",
            ),
            ("[arms.chunk]\nmax_loading_s = 0\n", "max_loading_s"),
            ("[arms.sim]\nstep_hz = 1e9\n", "sim.step_hz"),
            ("[arms.teleop.gate]\nstale_timeout_s = -1\n", "stale_timeout_s"),
        ] {
            let err = parse(&format!("{SIM}{extra}")).unwrap_err().to_string();
            assert!(
                err.starts_with("test.toml: arm \"main\": ") && err.contains(needle),
                "{err}"
            );
        }
        let joints = (0..65)
            .map(|i| format!("\"j{i}\""))
            .collect::<Vec<_>>()
            .join(", ");
        let remote =
            format!("[[arms]]\nname = \"r\"\nbridge = \"remote\"\n[arms.remote]\njoint_names = [{joints}]\n");
        assert!(parse(&remote).unwrap_err().to_string().contains("at most 64"));
        let long = "a".repeat(65);
        let err = parse(&format!("[[arms]]\nname = \"{long}\"\nbridge = \"sim\"\n"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("longer than 64 characters"), "{err}");
        let err = parse(&format!("{SIM}[recorder]\nrobot_type = \"{long}\"\n"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("recorder.robot_type must be 1..=64"), "{err}");
        let many = (0..17)
            .map(|i| format!("[[arms]]\nname = \"a{i}\"\nbridge = \"sim\"\n"))
            .collect::<Vec<_>>()
            .concat();
        assert!(parse(&many).unwrap_err().to_string().contains("at most 16 arms"));
    }

    #[test]
    fn no_arms_names_the_file_and_what_to_add() {
        let err = parse("[server]\nlisten = \"127.0.0.1:1\"\n")
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml: no arms"), "{err}");
        assert!(
            err.contains("[[arms]]") && err.contains("bridge = \"sim\""),
            "{err}"
        );
    }

    #[test]
    fn file_errors_keep_their_line_when_overrides_are_set() {
        // Line 5 is the typo; the override is unrelated and must not move the reported line.
        let text = format!("{SIM}\n[recorder]\nfsp = 20\n");
        let err = with_env(&text, &[("PHONE2ACT_SERVER__LISTEN", "127.0.0.1:7")])
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml:6:1: unknown field `fsp`"), "{err}");
        let text = format!("[recorder]\nfps = \"x\"\n{SIM}");
        let err = with_env(&text, &[("PHONE2ACT_RECORDER__ROOT", "/tmp/x")])
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml:2:7:"), "{err}");
    }

    #[test]
    fn an_override_that_breaks_a_good_file_is_named() {
        let err = with_env(
            SIM,
            &[
                ("PHONE2ACT_RECORDER__FPS", "fast"),
                ("PHONE2ACT_SERVER__LISTEN", "127.0.0.1:7"),
            ],
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.starts_with("environment override PHONE2ACT_RECORDER__FPS: "),
            "{err}"
        );
        let err = with_env(SIM, &[("PHONE2ACT_RECORDER__FPS", "500")])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("test.toml (with PHONE2ACT_RECORDER__FPS): recorder.fps"),
            "{err}"
        );
        // Only the override to blame is named, not every variable that happens to be set.
        let err = with_env(
            SIM,
            &[
                ("PHONE2ACT_RECORDER__FPS", "500"),
                ("PHONE2ACT_SERVER__LISTEN", "127.0.0.1:7"),
            ],
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.starts_with("test.toml (with PHONE2ACT_RECORDER__FPS): recorder.fps"),
            "{err}"
        );
    }

    #[test]
    fn arms_and_cameras_are_overridden_by_index() {
        let text = format!("{SIM}[[arms]]\nname = \"second\"\nbridge = \"sim\"\n");
        let config = with_env(
            &text,
            &[
                ("PHONE2ACT_ARMS__1__TELEOP__GATE__JUMP_POSITION_M", "0.01"),
                ("PHONE2ACT_ARMS__0__ACTION_MODE", "absolute"),
                (
                    "PHONE2ACT_ARMS__1__TELEOP__GATE__WORKSPACE_MAX_M",
                    "[0.3, 0.2, 0.3]",
                ),
            ],
        )
        .unwrap();
        assert_eq!(config.arms[0].action_mode, phone2act_core::ActionMode::Absolute);
        assert!((config.arms[1].teleop.gate.jump_position_m - 0.01).abs() < 1e-12);
        assert!((config.arms[0].teleop.gate.jump_position_m - 0.06).abs() < 1e-12);
        assert!(
            config.arms[1]
                .teleop
                .gate
                .workspace_max_m
                .iter()
                .zip([0.3, 0.2, 0.3])
                .all(|(a, b)| (a - b).abs() < 1e-12)
        );
        let err = with_env(&text, &[("PHONE2ACT_ARMS__2__NAME", "x")])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("PHONE2ACT_ARMS__2__NAME") && err.contains("`arms` has 2 entries"),
            "{err}"
        );
        let err = with_env(&text, &[("PHONE2ACT_ARMS__NAME", "x")])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("name an entry by its index, e.g. PHONE2ACT_ARMS__0__"),
            "{err}"
        );
        let err = with_env(&text, &[("PHONE2ACT_ARMS__first__NAME", "x")])
            .unwrap_err()
            .to_string();
        assert!(err.contains("`first` is not one of them"), "{err}");
    }

    #[test]
    fn an_empty_root_is_refused_at_start_and_names_the_variable() {
        // `PHONE2ACT_RECORDER__ROOT= phone2act serve`: an unset shell variable used to start a server whose
        // every save failed on the empty path.
        let err = with_env(SIM, &[("PHONE2ACT_RECORDER__ROOT", "")])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("test.toml (with PHONE2ACT_RECORDER__ROOT): recorder.root is empty"),
            "{err}"
        );
        let err = parse(&format!("{SIM}[recorder]\nroot = \"\"\n"))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml: recorder.root is empty"), "{err}");
    }

    #[test]
    fn what_serve_refuses_at_start_the_config_refuses() {
        let dir = std::env::temp_dir().join(format!("phone2act-config-root-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("a-file");
        std::fs::write(&file, "x").unwrap();
        let dobot = "[[arms]]\nname = \"d\"\nbridge = \"dobot\"\n[arms.dobot]\nhost = \"h\"\n";
        let cam = |kind: &str, extra: &str| {
            format!("[[cameras]]\nname = \"c\"\nkind = \"{kind}\"\nwidth = 64\nheight = 64\n{extra}")
        };
        for (text, needle) in [
            (format!("{SIM}[recorder]\nfps = 20.5\n"), "recorder.fps must be a whole number"),
            (
                format!("{dobot}{}", cam("sim_render", "")),
                "kind \"sim_render\" needs an arm with bridge = \"sim\"",
            ),
            (
                format!("{SIM}{dobot}{}", cam("sim_render", "arm = \"d\"\n")),
                "arm = \"d\" is not a simulated arm (simulated arms: main)",
            ),
            (
                "[[arms]]\nname = \"d\"\nbridge = \"dobot\"\n".to_owned(),
                "bridge \"dobot\" needs an [arms.dobot] table",
            ),
            (
                "[[arms]]\nname = \"s\"\nbridge = \"so101\"\n".to_owned(),
                "bridge \"so101\" needs an [arms.so101] table",
            ),
            (
                "[[arms]]\nname = \"d\"\nbridge = \"dobot\"\naction_mode = \"joint\"\n[arms.dobot]\nhost = \"h\"\n"
                    .to_owned(),
                "action_mode = \"joint\" needs an SO-101 arm",
            ),
            (
                format!("{SIM}dataset_layout = \"lerobot_so101\"\n"),
                "dataset_layout = \"lerobot_so101\" needs",
            ),
            (
                format!(
                    "{SIM}[[cameras]]\nname = \"small\"\nkind = \"test_pattern\"\nwidth = 64\nheight = 48\n"
                ),
                "SVT-AV1 needs at least 64x64",
            ),
            (
                format!("{SIM}[recorder]\nroot = {:?}\n", file.display().to_string()),
                "is a file, not a directory",
            ),
            (
                format!(
                    "{SIM}[recorder]\nroot = {:?}\n",
                    file.join("ds").display().to_string()
                ),
                "cannot be created",
            ),
        ] {
            let err = parse(&text).map(|_| ()).unwrap_err().to_string();
            assert!(err.contains(needle), "{text}\n=> {err}");
        }
        // The same sizes with a codec that takes them, and a named simulated arm, are fine.
        let small = format!(
            "{SIM}[[cameras]]\nname = \"small\"\nkind = \"sim_render\"\narm = \"main\"\nwidth = 64\nheight = 48\n\
             [recorder]\nvideo_codec = \"h264\"\nroot = {:?}\n",
            dir.join("new").display().to_string()
        );
        let small = parse(&small);
        let _ = std::fs::remove_dir_all(&dir);
        small.unwrap();
    }

    #[test]
    fn secrets_from_the_environment_are_strings_whatever_they_look_like() {
        for secret in [
            "123456789012345",
            "0x1f",
            "1e9",
            "true",
            "[1, 2]",
            "inf",
            "2026-01-01",
        ] {
            let config = with_env(
                SIM,
                &[
                    ("PHONE2ACT_SERVER__TOKEN", secret),
                    ("PHONE2ACT_GATEWAY__TOKEN", secret),
                ],
            )
            .unwrap_or_else(|e| panic!("{secret}: {e}"));
            assert_eq!(config.server.token.as_deref(), Some(secret));
            assert_eq!(config.gateway["token"].as_str(), Some(secret));
        }
        // Switches about a token stay switches.
        let config = with_env(SIM, &[("PHONE2ACT_GATEWAY__REQUIRE_TOKEN", "false")]).unwrap();
        assert_eq!(config.gateway["require_token"].as_bool(), Some(false));
    }

    #[test]
    fn no_error_prints_a_secret() {
        let err = parse(&format!("[server]\ntoken = 123456789012345\n{SIM}"))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml:2:"), "{err}");
        assert!(
            !err.contains("123456789012345") && err.contains(REDACTED),
            "{err}"
        );
        // A secret that happens to appear in another error's text is cleared there too.
        let err = with_env(
            &format!("{SIM}[recorder]\nrobot_type = \"\"\n"),
            &[("PHONE2ACT_SERVER__TOKEN", "1..=64 characters")],
        )
        .unwrap_err()
        .to_string();
        assert!(!err.contains("1..=64 characters"), "{err}");
    }

    /// A stand-in for the gateway's config type: the server crate cannot see it.
    #[derive(Debug, Default, Deserialize, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Gateway {
        port: u16,
        level: String,
        token: Option<String>,
    }

    fn gateway(text: &str, env: &[(&str, &str)]) -> Result<Gateway, ConfigError> {
        let source = ConfigSource {
            text: text.to_owned(),
            origin: "test.toml".to_owned(),
        };
        let env = env.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned()));
        source.gateway(env, |g: &Gateway| {
            if g.level == "loud" {
                Err("gateway.level must be quiet".to_owned())
            } else {
                Ok(())
            }
        })
    }

    #[test]
    fn gateway_errors_name_the_line_or_the_variable_like_the_servers_own() {
        let text = format!("{SIM}\n[gateway]\nport = 1\nprot = 2\n");
        let err = gateway(&text, &[]).unwrap_err().to_string();
        assert!(err.starts_with("test.toml:7:1: unknown field `prot`"), "{err}");
        // An unrelated override does not move the blame off the file's line.
        let err = gateway(&text, &[("PHONE2ACT_RECORDER__FPS", "30")])
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("test.toml:7:1:"), "{err}");
        let text = format!("{SIM}[gateway]\nport = 1\n");
        let err = gateway(&text, &[("PHONE2ACT_GATEWAY__PORT", "fast")])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("environment override PHONE2ACT_GATEWAY__PORT: "),
            "{err}"
        );
        let err = gateway(&text, &[("PHONE2ACT_GATEWAY__LEVEL", "loud")])
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "test.toml (with PHONE2ACT_GATEWAY__LEVEL): gateway.level must be quiet"
        );
        let err = gateway(&format!("{text}level = \"loud\"\n"), &[])
            .unwrap_err()
            .to_string();
        assert_eq!(err, "test.toml: gateway.level must be quiet");
        // No table at all: the type's defaults; a token override is a string.
        let g = gateway(SIM, &[("PHONE2ACT_GATEWAY__TOKEN", "0x10")]).unwrap();
        assert_eq!(
            g,
            Gateway {
                token: Some("0x10".to_owned()),
                ..Gateway::default()
            }
        );
        let err = gateway(&format!("{text}token = 0x10\n"), &[])
            .unwrap_err()
            .to_string();
        assert!(!err.contains("0x10") && !err.contains("16"), "{err}");
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

#[cfg(test)]
mod reference_tests {
    use super::*;
    use std::collections::BTreeSet;

    /// A configuration in which every optional key and every bridge section is set, so that serialising
    /// it shows every key the config types accept. The two Dobot arms cover the gripper variants' keys.
    pub(super) const FULLY_POPULATED: &str = r#"
[server]
token = "server-secret-1"
[[arms]]
name = "a"
bridge = "sim"
[arms.teleop.mapping]
matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
[arms.teleop.gate]
max_linear_speed_m_s = 0.5
max_angular_speed_rad_s = 2.0
[arms.sim]
basket_area_m = { x_min_m = 0.18, x_max_m = 0.26, y_min_m = 0.10, y_max_m = 0.16 }
[arms.dobot]
host = "192.168.5.1"
motion_port = 30003
euler_convention = "extrinsic_xyz"
gripper = { kind = "modbus_http" }
[arms.so101]
port = "/dev/ttyACM0"
calibration_file = "cal.json"
ids = [1, 2, 3, 4, 5, 6]
[arms.remote]
joint_names = ["j1"]
[[arms]]
name = "b"
bridge = "dobot"
[arms.dobot]
host = "h"
gripper = { kind = "do", index = 1 }
[[cameras]]
name = "c"
kind = "v4l2"
device = "/dev/video0"
arm = "a"
[recorder]
video_codec = "libx264"
episode_time_s = 30.0
reset_time_s = 10.0
highlight_s = 10.0
[storage]
url = "s3://b/p"
endpoint = "http://127.0.0.1:9000"
region = "eu-west-3"
profile = "lab"
credentials_file = "creds"
max_upload_bytes_per_s = 1000000
request_timeout_s = 30
station_id = "arm-1"
[flight_log]
dir = "logs"
[gateway]
cert_dir = "d"
cert_file = "c.pem"
key_file = "k.pem"
token = "pairing-secret-2"
public_host = "h"
local_addresses = ["127.0.0.1"]
"#;

    /// Dotted key paths of every leaf, array entries merged; `namespaces` is a map of user data.
    fn key_paths(value: &toml::Value, prefix: &str, out: &mut BTreeSet<String>) {
        match value {
            toml::Value::Table(table) if !prefix.ends_with(".namespaces") => {
                for (key, v) in table {
                    let path = if prefix.is_empty() {
                        key.clone()
                    } else {
                        format!("{prefix}.{key}")
                    };
                    key_paths(v, &path, out);
                }
            }
            toml::Value::Array(items) if items.iter().all(toml::Value::is_table) && !items.is_empty() => {
                for item in items {
                    key_paths(item, prefix, out);
                }
            }
            _ => {
                out.insert(prefix.to_owned());
            }
        }
    }

    /// Tables and keys the reference shows, commented out or not (`# token = ...` documents `token`).
    fn reference_keys(text: &str) -> (BTreeSet<String>, BTreeSet<String>) {
        let (mut tables, mut keys) = (BTreeSet::new(), BTreeSet::new());
        let mut prefix = String::new();
        for line in text.lines() {
            let line = line
                .strip_prefix('#')
                .map_or(line, |l| l.strip_prefix(' ').unwrap_or(l));
            if let Some(header) = line.strip_prefix('[') {
                let name = header.trim_start_matches('[').trim_end().trim_end_matches(']');
                if !name.is_empty()
                    && name
                        .chars()
                        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '.')
                {
                    prefix = name.to_owned();
                    tables.insert(prefix.clone());
                }
            } else if let Some((key, _)) = line.split_once(" = ")
                && key.chars().next().is_some_and(|c| c.is_ascii_lowercase())
                && key
                    .chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
            {
                keys.insert(if prefix.is_empty() {
                    key.to_owned()
                } else {
                    format!("{prefix}.{key}")
                });
            }
        }
        (tables, keys)
    }

    fn all_keys() -> BTreeSet<String> {
        let config = Config::from_toml_str(FULLY_POPULATED, "populated", Vec::new()).unwrap();
        let mut keys = BTreeSet::new();
        key_paths(&toml::Value::try_from(&config).unwrap(), "", &mut keys);
        keys
    }

    #[test]
    fn reference_shows_every_key_and_no_other() {
        let reference = include_str!("../config/reference.toml");
        let (tables, shown) = reference_keys(reference);
        let keys = all_keys();
        // Server keys only (95 today): the `[gateway]` table's are checked by phone2act-gateway.
        assert!(
            keys.len() > 80,
            "the populated config should reach every key, got {}",
            keys.len()
        );
        let missing: Vec<_> = keys
            .iter()
            .filter(|k| !shown.contains(*k) && !tables.contains(*k))
            .collect();
        assert!(
            missing.is_empty(),
            "server/config/reference.toml does not show {missing:?}"
        );
        let unknown: Vec<_> = shown
            .iter()
            // `[gateway]` is opaque to this crate; the `phone2act` binary checks that section against the
            // gateway's config type.
            .filter(|k| !keys.contains(*k) && !k.starts_with("gateway."))
            .collect();
        assert!(
            unknown.is_empty(),
            "server/config/reference.toml shows keys that do not exist: {unknown:?}"
        );
    }

    #[test]
    fn the_key_walk_sees_a_key_the_reference_lacks() {
        // The check above must be able to fail: a reference without one key is caught.
        let reference = include_str!("../config/reference.toml").replace("stale_timeout_s = 0.3\n", "");
        let (tables, shown) = reference_keys(&reference);
        assert!(
            all_keys()
                .iter()
                .any(|k| !shown.contains(k) && !tables.contains(k))
        );
    }

    #[test]
    fn redacted_toml_has_every_value_but_no_secret() {
        let config = Config::from_toml_str(FULLY_POPULATED, "populated", Vec::new()).unwrap();
        let text = config.to_redacted_toml().unwrap();
        for secret in ["server-secret-1", "pairing-secret-2"] {
            assert!(!text.contains(secret), "{secret} leaked:\n{text}");
        }
        // Everything else survives: read back, with the secrets put back, it is the same configuration.
        let back = Config::from_toml_str(&text, "redacted", Vec::new()).unwrap();
        assert_eq!(back.server.token.as_deref(), Some(REDACTED));
        assert_eq!(back.gateway["token"].as_str(), Some(REDACTED));
        let mut restored = back;
        restored.server.token.clone_from(&config.server.token);
        restored.gateway["token"].clone_from(&config.gateway["token"]);
        assert_eq!(restored, config);
    }
}
