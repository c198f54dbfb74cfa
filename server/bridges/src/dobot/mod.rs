//! Dobot CR5 bridge over the controller's TCP interface.
//!
//! Three sockets: the dashboard port (settings, enable, errors, outputs), the motion port (`ServoP` streaming; the
//! dashboard port itself on V4 firmware) and the 30004 feedback stream. Targets arrive in metres and unit
//! quaternions and leave as millimetres and degrees in the controller's Euler convention, which is checked
//! against the quaternion in the feedback packet before any motion is sent.
//!
//! Threads: a command thread takes the newest target from a [`LatestSlot`] and sends it (waiting for each
//! reply, so a rejected command is seen at once); a feedback thread reads packets and publishes [`Feedback`].
//! Faults (robot error mode, rejected commands, dropped sockets, silent feedback) show in [`Bridge::health`];
//! while the bridge is not ready, targets are dropped and the robot holds its last target. Recovery is on
//! request: [`Control::ClearError`], [`Control::Enable`], [`Control::Reconnect`].

#[cfg(feature = "emulators")]
pub mod emulator;
pub mod feedback;
pub mod gripper;
pub mod protocol;

use crate::runtime::{LinkContext, Measured, RobotLink, Schedule, ThreadedBridge};
use crate::sim::ClockFn;
use crate::{BridgeError, Command, Control, Health};
use feedback::{ConventionCheck, EulerConvention, FeedbackPacket, FrameReader, check_convention};
use gripper::GripperOutput;
use nalgebra::{Isometry3, Translation3};
use parking_lot::Mutex;
use protocol::{
    ErrorIds, Firmware, Reply, RobotMode, ServoParams, Terminator, echo_matches, error_text, parse_reply,
};
use serde::{Deserialize, Serialize};
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tracing::{debug, info, warn};

/// Configuration of one Dobot arm (`[arms.dobot]` in the server config).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct DobotConfig {
    /// Controller address: 192.168.5.1 wired, 192.168.1.6 wireless by default.
    pub host: String,
    #[serde(default)]
    pub firmware: Firmware,
    #[serde(default = "default_dashboard_port")]
    pub dashboard_port: u16,
    /// Port for `ServoP`; defaults to 30003 on V3 and the dashboard port (29999) on V4.
    #[serde(default)]
    pub motion_port: Option<u16>,
    #[serde(default = "default_feedback_port")]
    pub feedback_port: u16,
    #[serde(default)]
    pub terminator: Terminator,
    /// `ServoP` `t`: time to reach each target, seconds. About the command period for streaming.
    #[serde(default = "default_servo_t_s")]
    pub servo_t_s: f64,
    /// `ServoP` `aheadtime` (20..100).
    #[serde(default = "default_aheadtime")]
    pub aheadtime: f64,
    /// `ServoP` `gain` (200..1000).
    #[serde(default = "default_gain")]
    pub gain: f64,
    /// Global speed ratio set at start, percent (1..100).
    #[serde(default = "default_speed_factor")]
    pub speed_factor: u32,
    /// The controller's Euler convention; omit to detect it from the feedback packet's quaternion.
    #[serde(default)]
    pub euler_convention: Option<EulerConvention>,
    #[serde(default)]
    pub gripper: GripperOutput,
    #[serde(default = "default_connect_timeout_s")]
    pub connect_timeout_s: f64,
    /// Time the controller has to answer a command (`EnableRobot` excepted).
    #[serde(default = "default_reply_timeout_s")]
    pub reply_timeout_s: f64,
    /// Time the controller has to answer `EnableRobot`, which releases the brakes before it replies and so
    /// may take longer than other commands. Dobot's own clients wait without a limit; this bound keeps
    /// `start()` and `control(Enable)` returning when a controller never answers.
    #[serde(default = "default_enable_timeout_s")]
    pub enable_timeout_s: f64,
    /// Send `RequestControl()` (V4.6+: switch the controller to TCP control) before enabling. Firmware
    /// older than V4.6 answers it as an unknown command, which the bridge takes as "not needed". Ignored
    /// for V3 firmware.
    #[serde(default = "default_true")]
    pub request_control: bool,
    /// Feedback silence after which the link is reported down.
    #[serde(default = "default_feedback_timeout_s")]
    pub feedback_timeout_s: f64,
    #[serde(default = "default_true")]
    pub clear_error_on_start: bool,
    #[serde(default = "default_true")]
    pub enable_on_start: bool,
}

fn default_dashboard_port() -> u16 {
    29999
}
fn default_feedback_port() -> u16 {
    30004
}
fn default_servo_t_s() -> f64 {
    0.05
}
fn default_aheadtime() -> f64 {
    50.0
}
fn default_gain() -> f64 {
    500.0
}
fn default_speed_factor() -> u32 {
    30
}
fn default_connect_timeout_s() -> f64 {
    2.0
}
fn default_reply_timeout_s() -> f64 {
    1.0
}
fn default_enable_timeout_s() -> f64 {
    10.0
}
fn default_feedback_timeout_s() -> f64 {
    0.25
}
fn default_true() -> bool {
    true
}

impl DobotConfig {
    /// A config with every default, for `host`.
    pub fn new(host: impl Into<String>) -> Self {
        Self {
            host: host.into(),
            firmware: Firmware::default(),
            dashboard_port: default_dashboard_port(),
            motion_port: None,
            feedback_port: default_feedback_port(),
            terminator: Terminator::default(),
            servo_t_s: default_servo_t_s(),
            aheadtime: default_aheadtime(),
            gain: default_gain(),
            speed_factor: default_speed_factor(),
            euler_convention: None,
            gripper: GripperOutput::default(),
            connect_timeout_s: default_connect_timeout_s(),
            reply_timeout_s: default_reply_timeout_s(),
            enable_timeout_s: default_enable_timeout_s(),
            request_control: true,
            feedback_timeout_s: default_feedback_timeout_s(),
            clear_error_on_start: true,
            enable_on_start: true,
        }
    }

    /// The motion port after applying the firmware default.
    pub fn effective_motion_port(&self) -> u16 {
        self.motion_port.unwrap_or(match self.firmware {
            Firmware::V3 => Firmware::V3.default_motion_port(),
            Firmware::V4 => self.dashboard_port,
        })
    }

    /// Checks ranges the controller would reject, so a typo fails at start rather than on the first command.
    pub fn validate(&self) -> Result<(), BridgeError> {
        let bad = |m: String| Err(BridgeError::Config(format!("dobot: {m}")));
        if self.host.trim().is_empty() {
            return bad("host is empty".into());
        }
        if !(0.004..=3600.0).contains(&self.servo_t_s) {
            return bad(format!("servo_t_s {} outside [0.004, 3600]", self.servo_t_s));
        }
        if !(20.0..=100.0).contains(&self.aheadtime) {
            return bad(format!("aheadtime {} outside [20, 100]", self.aheadtime));
        }
        if !(200.0..=1000.0).contains(&self.gain) {
            return bad(format!("gain {} outside [200, 1000]", self.gain));
        }
        if !(1..=100).contains(&self.speed_factor) {
            return bad(format!("speed_factor {} outside [1, 100]", self.speed_factor));
        }
        for (name, v) in [
            ("connect_timeout_s", self.connect_timeout_s),
            ("reply_timeout_s", self.reply_timeout_s),
            ("enable_timeout_s", self.enable_timeout_s),
            ("feedback_timeout_s", self.feedback_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 60.0) {
                return bad(format!("{name} {v} outside (0, 60]"));
            }
        }
        Ok(())
    }

    fn servo_params(&self) -> Option<ServoParams> {
        // V3 `ServoP` takes exactly six parameters.
        (self.firmware == Firmware::V4).then_some(ServoParams {
            t_s: self.servo_t_s,
            aheadtime: self.aheadtime,
            gain: self.gain,
        })
    }
}

/// Counters and last faults, for status pages, tests and benchmarks.
#[derive(Clone, Debug, PartialEq)]
pub struct DobotStats {
    pub servo_sent: u64,
    pub servo_rejected: u64,
    /// Targets dropped because the robot was not ready (the arm held).
    pub targets_held: u64,
    /// Targets replaced by a newer one before they were sent.
    pub targets_superseded: u64,
    pub packets_ok: u64,
    pub packets_rejected: u64,
    pub last_packet_error: Option<String>,
    pub last_command_error: Option<String>,
    pub convention: EulerConvention,
    pub convention_verified: bool,
    pub reconnects: u64,
    /// Replies read and set aside because their echo named another command (a stray or late reply).
    pub replies_discarded: u64,
    /// What the controller answered to `RequestControl()` at the last connect.
    pub control_request: ControlRequest,
}

/// The outcome of `RequestControl()` at connect, which tells V4.6+ firmware from older V4.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ControlRequest {
    /// Not sent (V3 firmware, or `request_control = false`), or not connected yet.
    NotSent,
    /// Granted: firmware V4.6 or newer, now under TCP control.
    Granted,
    /// Answered as an unknown command: firmware older than V4.6, which has no control request.
    NotSupported,
    /// Refused with this error id (the guide allows it only while the robot is disabled or powered off).
    Refused(i32),
}

/// A request/reply connection (dashboard or motion port): sends a command, returns the reply whose echo is
/// that command. Used by the bridge and by `dobot-check`.
#[derive(Debug)]
pub struct CommandConn {
    stream: TcpStream,
    pending: Vec<u8>,
    terminator: Terminator,
    reply_timeout: Duration,
    /// Shared with the bridge's stats: replies set aside because their echo named another command.
    discarded: Arc<AtomicU64>,
}

impl CommandConn {
    /// Connects with `config`'s timeouts and terminator; `discarded` counts replies set aside.
    pub fn connect(
        addr: SocketAddr,
        config: &DobotConfig,
        discarded: Arc<AtomicU64>,
    ) -> std::io::Result<Self> {
        let stream = TcpStream::connect_timeout(&addr, Duration::from_secs_f64(config.connect_timeout_s))?;
        // Small commands at 125 Hz: Nagle would hold each one for the previous reply's ACK.
        stream.set_nodelay(true)?;
        stream.set_write_timeout(Some(Duration::from_secs_f64(config.reply_timeout_s)))?;
        Ok(Self {
            stream,
            pending: Vec::with_capacity(256),
            terminator: config.terminator,
            reply_timeout: Duration::from_secs_f64(config.reply_timeout_s),
            discarded,
        })
    }

    /// Sends a command and reads its reply within the reply timeout.
    pub fn request(&mut self, command: &str) -> Result<Reply, LinkError> {
        self.request_within(command, self.reply_timeout)
    }

    /// Sends a command and returns the reply whose echo is that command (guide §2.2.1: every reply ends
    /// with the command it answers). Replies to anything else (a late reply to a command that timed out,
    /// a controller answering a stray terminator) are set aside and counted, never taken for this one.
    pub fn request_within(&mut self, command: &str, timeout: Duration) -> Result<Reply, LinkError> {
        let mut wire = String::with_capacity(command.len() + 2);
        wire.push_str(command);
        wire.push_str(self.terminator.as_str());
        self.stream.write_all(wire.as_bytes()).map_err(LinkError::Io)?;
        let deadline = Instant::now() + timeout;
        let mut chunk = [0u8; 512];
        loop {
            while let Some(end) = self.pending.iter().position(|&b| b == b';') {
                let text: Vec<u8> = self.pending.drain(..=end).collect();
                let text = String::from_utf8_lossy(&text);
                match parse_reply(&text) {
                    Ok(reply) if echo_matches(command, &reply.echo) => return Ok(reply),
                    Ok(reply) => {
                        self.discarded.fetch_add(1, Ordering::Relaxed);
                        warn!(sent = command, echo = %reply.echo, "dobot: reply to another command set aside");
                    }
                    Err(e) => {
                        self.discarded.fetch_add(1, Ordering::Relaxed);
                        warn!(sent = command, error = %e, "dobot: unreadable reply set aside");
                    }
                }
            }
            // A controller that is not in TCP/IP mode answers with text of its own (TCP-IP-Python-V4
            // `DobotDemo.py` `parseResultId` looks for "Not Tcp"), which may never reach a `;`.
            if contains_ignore_case(&self.pending, b"not tcp") {
                self.pending.clear();
                return Err(LinkError::NotTcpMode);
            }
            if self.pending.len() > 64 * 1024 {
                self.pending.clear();
                return Err(LinkError::Protocol("reply longer than 64 KiB without ';'".into()));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(LinkError::Timeout(command.to_owned()));
            }
            self.stream.set_read_timeout(Some(left)).map_err(LinkError::Io)?;
            match self.stream.read(&mut chunk) {
                Ok(0) => {
                    return Err(LinkError::Io(std::io::Error::new(
                        ErrorKind::UnexpectedEof,
                        "closed by robot",
                    )));
                }
                Ok(n) => self.pending.extend_from_slice(&chunk[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(e) => return Err(LinkError::Io(e)),
            }
        }
    }
}

fn contains_ignore_case(haystack: &[u8], needle: &[u8]) -> bool {
    haystack
        .windows(needle.len())
        .any(|w| w.eq_ignore_ascii_case(needle))
}

/// Why a command got no usable reply.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("{0}")]
    Io(std::io::Error),
    #[error("no reply to {0} in time")]
    Timeout(String),
    #[error("{0}")]
    Protocol(String),
    #[error("the controller is not in TCP/IP control mode (set it in DobotStudio Pro, or RequestControl())")]
    NotTcpMode,
}

#[derive(Debug)]
enum Link {
    Connecting,
    Up,
    Down(String),
}

#[derive(Debug)]
struct Status {
    link: Link,
    robot_mode: Option<RobotMode>,
    last_packet_at: Option<Instant>,
    last_packet_error: Option<String>,
    last_command_error: Option<String>,
    convention: EulerConvention,
    convention_verified: bool,
    convention_error: Option<String>,
    /// The controller's error ids for the current fault, fetched once per fault.
    fault_detail: Option<String>,
    reconnects: u64,
    control_request: ControlRequest,
}

/// The feedback stream of one connection and the bytes read from it not yet parsed.
#[derive(Debug)]
struct FeedbackConn {
    socket: TcpStream,
    reader: FrameReader,
    /// The connection it belongs to: a read failing after a reconnect does not take the new link down.
    generation: u64,
}

/// The Dobot CR5's protocol side: the dashboard and motion connections, the feedback stream, the robot's
/// state as they report it.
#[derive(Debug)]
pub struct DobotLink {
    config: DobotConfig,
    joint_names: Vec<String>,
    status: Mutex<Status>,
    dashboard: Mutex<Option<CommandConn>>,
    /// `None` inside when motion shares the dashboard connection.
    motion: Mutex<Option<CommandConn>>,
    /// Read by the feedback thread.
    feedback_conn: Mutex<Option<FeedbackConn>>,
    /// A handle on the same socket, to shut it down while a read is blocked on it.
    feedback_socket: Mutex<Option<TcpStream>>,
    generation: AtomicU64,
    gripper_sent: Mutex<Option<f64>>,
    servo_sent: AtomicU64,
    servo_rejected: AtomicU64,
    packets_ok: AtomicU64,
    packets_rejected: AtomicU64,
    replies_discarded: Arc<AtomicU64>,
}

/// The Dobot CR5 bridge: [`DobotLink`] driven by the hardware-bridge runtime. Create with
/// [`DobotBridge::start`].
pub type DobotBridge = ThreadedBridge<DobotLink>;

impl ThreadedBridge<DobotLink> {
    /// Connects to the controller, clears errors, sets the speed, enables the robot (as configured), waits for
    /// the first feedback packet and starts streaming.
    pub fn start(config: DobotConfig) -> Result<Arc<Self>, BridgeError> {
        Self::start_with_clock(config, phone2act_clock::monotonic_ns)
    }

    /// As [`Self::start`], stamping feedback with `clock` (the server passes its process-wide clock).
    pub fn start_with_clock(config: DobotConfig, clock: ClockFn) -> Result<Arc<Self>, BridgeError> {
        config.validate()?;
        let link = DobotLink {
            joint_names: (1..=6).map(|i| format!("j{i}")).collect(),
            status: Mutex::new(Status {
                link: Link::Connecting,
                robot_mode: None,
                last_packet_at: None,
                last_packet_error: None,
                last_command_error: None,
                convention: config.euler_convention.unwrap_or_default(),
                convention_verified: false,
                convention_error: None,
                fault_detail: None,
                reconnects: 0,
                control_request: ControlRequest::NotSent,
            }),
            dashboard: Mutex::new(None),
            motion: Mutex::new(None),
            feedback_conn: Mutex::new(None),
            feedback_socket: Mutex::new(None),
            generation: AtomicU64::new(0),
            gripper_sent: Mutex::new(None),
            servo_sent: AtomicU64::new(0),
            servo_rejected: AtomicU64::new(0),
            packets_ok: AtomicU64::new(0),
            packets_rejected: AtomicU64::new(0),
            replies_discarded: Arc::new(AtomicU64::new(0)),
            config,
        };
        // The feedback thread runs before the connect, which waits for the packets it reads.
        let bridge = Self::spawn(link, clock)?;
        if let Err(e) = bridge.link().connect() {
            bridge.link().close(format!("start failed: {e}"));
            return Err(e);
        }
        Ok(Arc::new(bridge))
    }

    pub fn config(&self) -> &DobotConfig {
        &self.link().config
    }

    /// Counters and the last faults seen.
    pub fn stats(&self) -> DobotStats {
        let link = self.link();
        let s = link.status.lock();
        DobotStats {
            servo_sent: link.servo_sent.load(Ordering::Relaxed),
            servo_rejected: link.servo_rejected.load(Ordering::Relaxed),
            targets_held: self.context().targets_held(),
            targets_superseded: self.context().targets_superseded(),
            packets_ok: link.packets_ok.load(Ordering::Relaxed),
            packets_rejected: link.packets_rejected.load(Ordering::Relaxed),
            last_packet_error: s.last_packet_error.clone(),
            last_command_error: s.last_command_error.clone(),
            convention: s.convention,
            convention_verified: s.convention_verified,
            reconnects: s.reconnects,
            replies_discarded: link.replies_discarded.load(Ordering::Relaxed),
            control_request: s.control_request.clone(),
        }
    }

    /// Sends one dashboard command and returns the parsed reply (for tools and diagnostics).
    pub fn dashboard(&self, command: &str) -> Result<Reply, BridgeError> {
        self.link().dashboard_request(command)
    }
}

impl DobotLink {
    fn resolve(&self, port: u16) -> Result<SocketAddr, BridgeError> {
        (self.config.host.as_str(), port)
            .to_socket_addrs()
            .map_err(|e| BridgeError::Connect {
                target: format!("{}:{port}", self.config.host),
                message: e.to_string(),
            })?
            .next()
            .ok_or_else(|| BridgeError::Connect {
                target: format!("{}:{port}", self.config.host),
                message: "address did not resolve".into(),
            })
    }

    fn connect_error(&self, port: u16, e: &std::io::Error) -> BridgeError {
        BridgeError::Connect {
            target: format!("{}:{port}", self.config.host),
            message: e.to_string(),
        }
    }

    /// (Re)opens every socket, runs the start-up commands and waits for feedback.
    fn connect(&self) -> Result<(), BridgeError> {
        let generation = self.generation.fetch_add(1, Ordering::SeqCst) + 1;
        self.close_sockets();
        {
            let mut s = self.status.lock();
            s.link = Link::Connecting;
            s.last_packet_at = None;
            s.robot_mode = None;
        }
        let cfg = &self.config;
        let dashboard_addr = self.resolve(cfg.dashboard_port)?;
        let dashboard = CommandConn::connect(dashboard_addr, cfg, Arc::clone(&self.replies_discarded))
            .map_err(|e| self.connect_error(cfg.dashboard_port, &e))?;
        let motion_port = cfg.effective_motion_port();
        let motion = if motion_port == cfg.dashboard_port {
            None
        } else {
            let addr = self.resolve(motion_port)?;
            Some(
                CommandConn::connect(addr, cfg, Arc::clone(&self.replies_discarded))
                    .map_err(|e| self.connect_error(motion_port, &e))?,
            )
        };
        let feedback_addr = self.resolve(cfg.feedback_port)?;
        let feedback =
            TcpStream::connect_timeout(&feedback_addr, Duration::from_secs_f64(cfg.connect_timeout_s))
                .map_err(|e| self.connect_error(cfg.feedback_port, &e))?;
        // Bounds each read of the feedback thread, so it sees a shutdown or a reconnect within 50 ms.
        feedback.set_read_timeout(Some(Duration::from_millis(50)))?;
        *self.feedback_socket.lock() = Some(feedback.try_clone()?);
        *self.feedback_conn.lock() = Some(FeedbackConn {
            socket: feedback,
            reader: FrameReader::default(),
            generation,
        });
        *self.dashboard.lock() = Some(dashboard);
        *self.motion.lock() = motion;

        let control_request = if cfg.firmware == Firmware::V4 && cfg.request_control {
            self.request_control()?
        } else {
            ControlRequest::NotSent
        };
        self.status.lock().control_request = control_request;
        if cfg.clear_error_on_start {
            self.dashboard_ok("ClearError()")?;
        }
        self.dashboard_ok(&format!("SpeedFactor({})", cfg.speed_factor))?;
        if cfg.enable_on_start {
            // An enable refused because the robot is in error is a robot state, not a start failure: it shows
            // in health and can be retried with Control::ClearError / Control::Enable.
            if let Err(e) = self.enable_robot() {
                warn!(error = %e, "dobot: EnableRobot refused");
                self.status.lock().last_command_error = Some(e.to_string());
            }
        }
        // Wait for packets sent after the start-up commands, so health reflects them when this returns. The
        // first one may have left the controller before the enable took effect, hence two.
        let deadline = Instant::now() + Duration::from_secs_f64(cfg.connect_timeout_s);
        let packets_before = self.packets_ok.load(Ordering::SeqCst);
        while self.packets_ok.load(Ordering::SeqCst) < packets_before + 2 {
            if Instant::now() > deadline {
                return Err(BridgeError::Connect {
                    target: feedback_addr.to_string(),
                    message: "connected but no valid feedback packet arrived".into(),
                });
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        let mut s = self.status.lock();
        s.link = Link::Up;
        info!(host = %cfg.host, firmware = ?cfg.firmware, motion_port, "dobot: connected");
        Ok(())
    }

    fn close_sockets(&self) {
        // Shut the socket down first: that ends a read blocked on it, which holds `feedback_conn`.
        if let Some(s) = self.feedback_socket.lock().take() {
            let _ = s.shutdown(Shutdown::Both);
        }
        self.feedback_conn.lock().take();
        for conn in [&self.dashboard, &self.motion] {
            if let Some(c) = conn.lock().take() {
                let _ = c.stream.shutdown(Shutdown::Both);
            }
        }
    }

    /// Closes every socket and reports the link down. The first reason wins: closing one socket makes the
    /// others fail too, and their errors say less.
    fn close(&self, why: String) {
        self.close_sockets();
        let mut s = self.status.lock();
        if !matches!(s.link, Link::Down(_)) {
            s.link = Link::Down(why);
        }
    }

    /// `RequestControl()` (guide §3.132, added in V4.6.0): V4.6+ firmware takes commands over TCP only
    /// after it; older V4 firmware answers it as an unknown command (-10000), which is how the two are told
    /// apart. A refusal is logged and kept in the stats, not fatal: the guide refuses it while the robot is
    /// enabled, which a controller already under TCP control may be.
    fn request_control(&self) -> Result<ControlRequest, BridgeError> {
        let reply = self.dashboard_request("RequestControl()")?;
        let outcome = match reply.error_id {
            0 => ControlRequest::Granted,
            -10000 => ControlRequest::NotSupported,
            code => ControlRequest::Refused(code),
        };
        match &outcome {
            ControlRequest::Granted => info!("dobot: RequestControl granted (firmware V4.6 or newer)"),
            ControlRequest::NotSupported => {
                info!("dobot: firmware older than V4.6; no control request needed");
            }
            ControlRequest::Refused(code) => warn!(
                code,
                reason = error_text(*code),
                "dobot: RequestControl refused; continuing (the robot may already be under TCP control)"
            ),
            ControlRequest::NotSent => {}
        }
        Ok(outcome)
    }

    /// `EnableRobot()` with its own, longer reply timeout ([`DobotConfig::enable_timeout_s`]).
    fn enable_robot(&self) -> Result<Reply, BridgeError> {
        let timeout = Duration::from_secs_f64(self.config.enable_timeout_s);
        self.dashboard_ok_within("EnableRobot()", timeout)
    }

    fn dashboard_request(&self, command: &str) -> Result<Reply, BridgeError> {
        self.dashboard_request_within(command, Duration::from_secs_f64(self.config.reply_timeout_s))
    }

    /// One dashboard command. A reply that does not come in time is an error of this command, not of the
    /// link: the echo check sets the late reply aside when it comes, so the connection stays usable. Only
    /// a failed socket closes the link.
    fn dashboard_request_within(&self, command: &str, timeout: Duration) -> Result<Reply, BridgeError> {
        let mut guard = self.dashboard.lock();
        let conn = guard
            .as_mut()
            .ok_or_else(|| BridgeError::Protocol("dashboard not connected".into()))?;
        match conn.request_within(command, timeout) {
            Ok(reply) => Ok(reply),
            Err(e @ (LinkError::Protocol(_) | LinkError::Timeout(_) | LinkError::NotTcpMode)) => {
                Err(BridgeError::Protocol(e.to_string()))
            }
            Err(e) => {
                drop(guard);
                let why = format!("dashboard: {e}");
                self.close(why.clone());
                Err(BridgeError::Protocol(why))
            }
        }
    }

    /// A dashboard command that must succeed (ErrorID 0).
    fn dashboard_ok(&self, command: &str) -> Result<Reply, BridgeError> {
        self.dashboard_ok_within(command, Duration::from_secs_f64(self.config.reply_timeout_s))
    }

    fn dashboard_ok_within(&self, command: &str, timeout: Duration) -> Result<Reply, BridgeError> {
        let reply = self.dashboard_request_within(command, timeout)?;
        if reply.error_id == 0 {
            Ok(reply)
        } else {
            Err(BridgeError::Protocol(format!(
                "{command} failed: error {} ({})",
                reply.error_id,
                error_text(reply.error_id)
            )))
        }
    }

    fn motion_request(&self, command: &str) -> Result<Reply, LinkError> {
        let mut motion = self.motion.lock();
        if let Some(conn) = motion.as_mut() {
            return conn.request(command);
        }
        drop(motion);
        let mut dashboard = self.dashboard.lock();
        let conn = dashboard
            .as_mut()
            .ok_or_else(|| LinkError::Protocol("not connected".into()))?;
        conn.request(command)
    }

    fn health_now(&self) -> Health {
        let s = self.status.lock();
        match &s.link {
            Link::Connecting => return Health::Connecting,
            Link::Down(why) => return Health::Disconnected(why.clone()),
            Link::Up => {}
        }
        let timeout = Duration::from_secs_f64(self.config.feedback_timeout_s);
        match s.last_packet_at {
            Some(t) if t.elapsed() <= timeout => {}
            _ => {
                return Health::Disconnected(format!(
                    "no feedback packet for more than {} ms",
                    timeout.as_millis()
                ));
            }
        }
        if let Some(e) = &s.convention_error {
            return Health::Error(e.clone());
        }
        match s.robot_mode {
            Some(mode) if mode.is_fault() => {
                let detail = s
                    .fault_detail
                    .as_deref()
                    .map(|d| format!(": {d}"))
                    .unwrap_or_default();
                return Health::Error(format!("robot in {mode:?} mode ({}){detail}", mode.code()));
            }
            Some(mode) if !mode.accepts_motion() => {
                // Say why, if the bridge's own enable failed (refused, or unanswered in time).
                let why = s
                    .last_command_error
                    .as_deref()
                    .map(|e| format!(": {e}"))
                    .unwrap_or_default();
                return Health::Error(format!("robot not enabled: {mode:?} mode ({}){why}", mode.code()));
            }
            _ => {}
        }
        if let Some(e) = &s.last_command_error {
            return Health::Error(e.clone());
        }
        Health::Ready
    }

    /// One read of the feedback stream: the state of the newest good packet in it, if any.
    fn read_packets(&self) -> Option<Measured> {
        let mut chunk = [0u8; 8192];
        let mut guard = self.feedback_conn.lock();
        let Some(conn) = guard.as_mut() else {
            drop(guard);
            // Not connected: wait for a connect, without spinning.
            std::thread::sleep(Duration::from_millis(10));
            return None;
        };
        let failure = match conn.socket.read(&mut chunk) {
            Ok(0) => Some("feedback connection closed by the robot".to_owned()),
            Ok(n) => {
                conn.reader.push(&chunk[..n]);
                None
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => return None,
            Err(e) => Some(format!("feedback connection: {e}")),
        };
        if let Some(why) = failure {
            let generation = conn.generation;
            guard.take();
            drop(guard);
            if generation == self.generation.load(Ordering::SeqCst) {
                warn!("dobot: {why}");
                self.close(why);
            }
            return None;
        }
        let mut newest = None;
        while let Some(result) = conn.reader.next_packet() {
            match result {
                Ok(packet) => newest = Some(self.on_packet(&packet)),
                Err(e) => {
                    self.packets_rejected.fetch_add(1, Ordering::Relaxed);
                    warn!(error = %e, "dobot: feedback packet rejected; resynchronising");
                    self.status.lock().last_packet_error = Some(e.to_string());
                }
            }
        }
        newest
    }

    fn on_packet(&self, packet: &FeedbackPacket) -> Measured {
        self.packets_ok.fetch_add(1, Ordering::Relaxed);
        let convention = {
            let mut s = self.status.lock();
            s.last_packet_at = Some(Instant::now());
            let mode = RobotMode::from_code(packet.robot_mode);
            if s.robot_mode != Some(mode) {
                debug!(?mode, "dobot: robot mode");
            }
            if !mode.is_fault() {
                s.fault_detail = None;
            }
            s.robot_mode = Some(mode);
            if !s.convention_verified && s.convention_error.is_none() {
                Self::verify_convention(&mut s, packet, self.config.euler_convention);
            }
            s.convention
        };
        let [x, y, z, rx, ry, rz] = packet.tool_vector_actual;
        let robot_from_ee = Isometry3::from_parts(
            Translation3::new(x / 1000.0, y / 1000.0, z / 1000.0),
            convention.to_rotation(rx, ry, rz),
        );
        let gripper_position = match &self.config.gripper {
            GripperOutput::Do { index, closed_high } if (1..=64).contains(index) => {
                let high = (packet.digital_outputs >> (index - 1)) & 1 == 1;
                if high == *closed_high { 1.0 } else { 0.0 }
            }
            _ => self.gripper_sent.lock().unwrap_or(0.0),
        };
        Measured {
            joint_positions_rad: packet.q_actual_deg.iter().map(|d| d.to_radians()).collect(),
            robot_from_ee,
            gripper_position,
        }
    }

    fn verify_convention(s: &mut Status, packet: &FeedbackPacket, configured: Option<EulerConvention>) {
        let assumed = configured.unwrap_or(s.convention);
        match check_convention(packet, assumed) {
            ConventionCheck::Confirmed => {
                s.convention = assumed;
                s.convention_verified = true;
                info!(convention = ?assumed, "dobot: Euler convention confirmed by the packet quaternion");
            }
            ConventionCheck::Contradicted { fits } => {
                if configured.is_some() {
                    let m = format!(
                        "configured Euler convention {assumed:?} contradicts the robot's quaternion (it fits {fits:?}); \
                         motion disabled"
                    );
                    warn!("dobot: {m}");
                    s.convention_error = Some(m);
                } else {
                    info!(convention = ?fits, "dobot: Euler convention detected from the packet quaternion");
                    s.convention = fits;
                    s.convention_verified = true;
                }
            }
            ConventionCheck::NeitherFits => {
                let m = "the robot's Euler angles and quaternion disagree under both conventions; motion disabled";
                warn!("dobot: {m}");
                s.convention_error = Some(m.to_owned());
            }
            // Keep checking later packets: a pose with one non-zero angle cannot tell the conventions apart.
            ConventionCheck::Inconclusive => {}
        }
    }

    /// Asks the controller for its error ids once per fault, so health can say which error it is. Runs on the
    /// command thread: the feedback thread must never wait on the dashboard.
    fn fetch_fault_detail(&self) {
        let needed = {
            let s = self.status.lock();
            matches!(s.link, Link::Up)
                && s.robot_mode.is_some_and(RobotMode::is_fault)
                && s.fault_detail.is_none()
        };
        if !needed {
            return;
        }
        let detail = match self.dashboard_request("GetErrorID()") {
            Ok(reply) if reply.error_id == 0 => match ErrorIds::parse(&reply.values.join(",")) {
                Ok(ids) => ids.to_string(),
                Err(e) => format!("GetErrorID: {e}"),
            },
            Ok(reply) => format!("GetErrorID failed: {}", error_text(reply.error_id)),
            Err(e) => format!("GetErrorID failed: {e}"),
        };
        warn!(%detail, "dobot: robot fault");
        self.status.lock().fault_detail = Some(detail);
    }

    /// True if the only fault is a previously rejected command: the next target may succeed and clear it.
    fn only_command_error(&self) -> bool {
        let s = self.status.lock();
        s.last_command_error.is_some()
            && matches!(s.link, Link::Up)
            && s.convention_error.is_none()
            && s.robot_mode.is_some_and(RobotMode::accepts_motion)
    }

    /// Sends one target (finite: the runtime checked) and the gripper's.
    /// The motion command: every target the runtime accepts for the Dobot goes out here (`ServoP` of the
    /// pose), and `applied_seq` moves only on the reply that echoes it.
    fn send_target(&self, ctx: &LinkContext, command: &Command) {
        let pose = &command.robot_from_target;
        let t = pose.translation.vector;
        // Joints the server solved and rate-limited go as `ServoJ`, so the controller never gets a joint step
        // larger than the limits; otherwise the pose, which the controller solves itself.
        let joints_deg = command
            .joint_targets_rad
            .as_deref()
            .and_then(|q| <[f64; 6]>::try_from(q).ok())
            .filter(|q| q.iter().all(|v| v.is_finite()))
            .map(|q| q.map(f64::to_degrees));
        let text = if let Some(joints_deg) = joints_deg {
            protocol::servo_j(&joints_deg, self.config.servo_params())
        } else {
            let convention = self.status.lock().convention;
            let [rx, ry, rz] = convention.to_angles_deg(&pose.rotation);
            let pose_mm_deg = [t.x * 1000.0, t.y * 1000.0, t.z * 1000.0, rx, ry, rz];
            protocol::servo_p(&pose_mm_deg, self.config.servo_params())
        };
        let verb = if joints_deg.is_some() { "ServoJ" } else { "ServoP" };
        match self.motion_request(&text) {
            Ok(reply) if reply.error_id == 0 => {
                self.servo_sent.fetch_add(1, Ordering::Relaxed);
                ctx.applied(command.seq);
                self.status.lock().last_command_error = None;
            }
            Ok(reply) => {
                self.servo_rejected.fetch_add(1, Ordering::Relaxed);
                let m = format!(
                    "{verb} rejected: error {} ({})",
                    reply.error_id,
                    error_text(reply.error_id)
                );
                warn!(seq = command.seq, "dobot: {m}");
                self.status.lock().last_command_error = Some(m);
            }
            Err(e @ (LinkError::Protocol(_) | LinkError::Timeout(_) | LinkError::NotTcpMode)) => {
                self.servo_rejected.fetch_add(1, Ordering::Relaxed);
                self.status.lock().last_command_error = Some(format!("{verb}: {e}"));
            }
            Err(e) => {
                warn!(error = %e, "dobot: motion connection failed");
                self.close(format!("motion connection: {e}"));
                return;
            }
        }
        self.send_gripper(command.gripper_target.clamp(0.0, 1.0));
    }

    fn send_gripper(&self, target: f64) {
        let closed = target >= 0.5;
        let v3 = self.config.firmware == Firmware::V3;
        let (command, reported) = match &self.config.gripper {
            GripperOutput::None => {
                *self.gripper_sent.lock() = Some(target);
                return;
            }
            GripperOutput::Do { index, closed_high } => {
                let name = if v3 { "DOExecute" } else { "DOInstant" };
                (
                    format!("{name}({index},{})", u8::from(closed == *closed_high)),
                    f64::from(u8::from(closed)),
                )
            }
            GripperOutput::ToolDo { index, closed_high } => {
                let name = if v3 { "ToolDOExecute" } else { "ToolDOInstant" };
                (
                    format!("{name}({index},{})", u8::from(closed == *closed_high)),
                    f64::from(u8::from(closed)),
                )
            }
            GripperOutput::ModbusHttp {
                port,
                path,
                slave,
                register,
                open_value,
                closed_value,
            } => {
                let value = (f64::from(*open_value)
                    + (f64::from(*closed_value) - f64::from(*open_value)) * target)
                    .round()
                    .clamp(0.0, f64::from(u16::MAX)) as u16;
                let reported = if open_value == closed_value {
                    target
                } else {
                    (f64::from(value) - f64::from(*open_value))
                        / (f64::from(*closed_value) - f64::from(*open_value))
                };
                if self
                    .gripper_sent
                    .lock()
                    .is_some_and(|g| (g - reported).abs() < 1e-3)
                {
                    return;
                }
                let frame = gripper::modbus_write_register(*slave, *register, value);
                let body = gripper::modbus_http_body(&frame);
                let timeout = Duration::from_secs_f64(self.config.reply_timeout_s);
                match gripper::http_post_json(&self.config.host, *port, path, &body, timeout) {
                    Ok(200) => *self.gripper_sent.lock() = Some(reported),
                    Ok(status) => warn!(status, "dobot: gripper endpoint refused the frame"),
                    Err(e) => warn!(error = %e, "dobot: gripper endpoint unreachable"),
                }
                return;
            }
        };
        if self
            .gripper_sent
            .lock()
            .is_some_and(|g| (g - reported).abs() < 1e-9)
        {
            return;
        }
        match self.dashboard_ok(&command) {
            Ok(_) => *self.gripper_sent.lock() = Some(reported),
            Err(e) => warn!(error = %e, "dobot: gripper output failed"),
        }
    }

    /// Shutdown: closes every socket; the robot holds its last target.
    fn close_for_shutdown(&self) {
        self.generation.fetch_add(1, Ordering::SeqCst);
        self.close_sockets();
        self.status.lock().link = Link::Down("bridge shut down".into());
    }
}

impl RobotLink for DobotLink {
    fn kind(&self) -> &'static str {
        "dobot"
    }

    fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    fn schedule(&self) -> Schedule {
        // The command thread also asks a faulted robot for its error ids between targets; 50 ms bounds
        // how long that waits behind an idle slot.
        Schedule::Split {
            command_wait: Duration::from_millis(50),
        }
    }

    fn health(&self, _ctx: &LinkContext) -> Health {
        self.health_now()
    }

    /// Ready, or ready but for a rejected command: the next target may succeed and clear it.
    fn accepts_targets(&self, _ctx: &LinkContext) -> bool {
        self.health_now() == Health::Ready || self.only_command_error()
    }

    fn write_command(&self, ctx: &LinkContext, command: Option<&Command>) -> bool {
        if let Some(command) = command {
            self.send_target(ctx, command);
        }
        true
    }

    fn read_feedback(&self, _ctx: &LinkContext) -> Option<Measured> {
        self.read_packets()
    }

    fn between_commands(&self, _ctx: &LinkContext) {
        self.fetch_fault_detail();
    }

    fn control(&self, _ctx: &LinkContext, request: Control) -> Result<(), BridgeError> {
        match request {
            Control::Enable => {
                self.enable_robot()?;
            }
            Control::Disable => {
                self.dashboard_ok("DisableRobot()")?;
            }
            Control::ClearError => {
                self.dashboard_ok("ClearError()")?;
            }
            Control::Reconnect => {
                self.status.lock().reconnects += 1;
                if let Err(e) = self.connect() {
                    self.close(format!("reconnect failed: {e}"));
                    return Err(e);
                }
            }
        }
        // A fresh start: the next rejected command will set it again.
        self.status.lock().last_command_error = None;
        Ok(())
    }

    fn close(&self) {
        self.close_for_shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_and_unknown_fields() {
        let c: DobotConfig = serde_json::from_str(r#"{"host":"192.168.5.1"}"#).unwrap();
        assert_eq!(c, DobotConfig::new("192.168.5.1"));
        assert_eq!(c.effective_motion_port(), 29999);
        let v3: DobotConfig =
            serde_json::from_str(r#"{"host":"h","firmware":"v3","terminator":"none"}"#).unwrap();
        assert_eq!(v3.effective_motion_port(), 30003);
        assert_eq!(v3.servo_params(), None);
        assert!(serde_json::from_str::<DobotConfig>(r#"{"host":"h","servo_t":0.1}"#).is_err());
        let mut bad = DobotConfig::new("h");
        bad.gain = 50.0;
        assert!(matches!(bad.validate(), Err(BridgeError::Config(m)) if m.contains("gain")));
        bad = DobotConfig::new("h");
        bad.servo_t_s = 0.001;
        assert!(bad.validate().is_err());
    }
}
