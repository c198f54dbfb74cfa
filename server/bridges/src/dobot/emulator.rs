//! A Dobot CR5 controller on loopback TCP for tests and demos: the dashboard port (and, for V3 firmware, a
//! separate motion port) answering `ErrorID,{values},Cmd;` as the controller does, a feedback port streaming the
//! 1440-byte packet every 8 ms, and the HTTP tool-data endpoint that carries Modbus gripper frames.
//!
//! The arm follows the newest streaming target so that it arrives `t` seconds after the command: a `ServoP` pose
//! moves the tool along a straight line (capped at a maximum speed) and the joints follow by the CR5 model's
//! inverse kinematics; a `ServoJ` moves the joints along a straight joint-space line and the tool follows by its
//! forward kinematics. Both use `phone2act_core::kinematics::Cr5Kinematics` (Dobot's published CR5 URDF), so
//! the joints and the tool pose reported always agree. Faults can be injected: a robot error, dropped
//! connections, and corrupt or truncated feedback packets.

// Commands arrive from the network: slicing a `str` by byte index would panic on a multi-byte character.
#![deny(clippy::string_slice)]

use super::feedback::{EulerConvention, FeedbackPacket};
use super::gripper::parse_modbus_write_register;
use super::protocol::{ErrorIds, Firmware, RobotMode, split_command, split_top_level};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use parking_lot::Mutex;
use phone2act_core::kinematics::{Cr5Joints, Cr5Kinematics, IkWeights};
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tracing::debug;

/// Emulator settings. Ports of 0 pick free ephemeral ports.
#[derive(Clone, Debug)]
pub struct EmulatorConfig {
    pub firmware: Firmware,
    pub bind_host: String,
    pub dashboard_port: u16,
    /// Only used with [`Firmware::V3`].
    pub motion_port: u16,
    pub feedback_port: u16,
    pub http_port: u16,
    /// How the emulated controller composes `rx, ry, rz` (the bridge must detect or be told).
    pub convention: EulerConvention,
    /// False leaves the quaternion field zero, as firmware that does not fill it.
    pub fill_quaternion: bool,
    pub feedback_period: Duration,
    pub initial_pose: Isometry3<f64>,
    pub max_speed_m_s: f64,
    /// Firmware version (major, minor). From V4.6.0 the controller takes commands over TCP only after
    /// `RequestControl()` (guide `V4新增指令/README.md` §3.132 and its change log "V4.6.0-2024/03/27 增加
    /// RequestControl命令"); before it, `EnableRobot` and motion commands go unanswered, the symptom reported
    /// in issue #25. Older V4 answers `RequestControl()` as an unknown command (-10000), as it would any
    /// command it does not know (§2.2.1).
    pub firmware_version: (u8, u8),
    /// How long `EnableRobot()` takes to answer (the brakes release first).
    pub enable_delay: Duration,
    /// Answer a stray `\r\n` or `\n` after a command as a command of its own (`-10000,{},;`): the
    /// behaviour that, with a bridge that does not check echoes, shifts every reply onto the next command.
    pub answer_stray_terminator: bool,
}

impl Default for EmulatorConfig {
    fn default() -> Self {
        Self {
            firmware: Firmware::V4,
            bind_host: "127.0.0.1".to_owned(),
            dashboard_port: 0,
            motion_port: 0,
            feedback_port: 0,
            http_port: 0,
            convention: EulerConvention::ExtrinsicXyz,
            fill_quaternion: true,
            feedback_period: Duration::from_millis(8),
            initial_pose: Isometry3::from_parts(
                Translation3::new(-0.40, 0.0, 0.35),
                UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
            ),
            max_speed_m_s: 1.0,
            firmware_version: (4, 6),
            enable_delay: Duration::ZERO,
            answer_stray_terminator: false,
        }
    }
}

/// A one-shot fault applied to the next feedback packet sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Corruption {
    /// Only the first 700 bytes of the packet are sent.
    Truncate,
    /// The test value is wrong.
    BadTestValue,
    /// The size field is wrong.
    BadSize,
}

/// What the emulated controller is doing, as a test sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct EmulatorSnapshot {
    pub mode: RobotMode,
    pub enabled: bool,
    pub pose: Isometry3<f64>,
    pub target: Isometry3<f64>,
    pub servo_commands: u64,
    pub rejected_commands: u64,
    pub last_servo_command: Option<String>,
    /// The joints, radians, J1..J6.
    pub joints_rad: Cr5Joints,
    /// Every `ServoJ` accepted (the newest [`SERVO_J_LOG`]): when it arrived and its joints, radians.
    pub servo_j_log: Vec<(Instant, Cr5Joints)>,
    pub speed_factor: u32,
    pub digital_outputs: u64,
    pub tool_outputs: u8,
    /// Last value written to the Modbus gripper register, if any.
    pub gripper_register: Option<u16>,
    pub active_clients: usize,
    /// True once the controller takes commands over TCP (V4.6+: after `RequestControl()`).
    pub tcp_control: bool,
    /// `RequestControl()` commands received.
    pub control_requests: u64,
    /// Every command received, in order, as the controller read it (bounded to the last 256).
    pub received: Vec<String>,
    /// The queued motion command being executed (`CurrentCommandId` of the feedback packet).
    pub current_command_id: u64,
    /// HTTP requests refused for their method or path.
    pub http_refused: u64,
}

/// How many `ServoJ` commands [`EmulatorSnapshot::servo_j_log`] keeps.
pub const SERVO_J_LOG: usize = 4096;

#[derive(Debug)]
struct State {
    kinematics: Cr5Kinematics,
    joints_rad: Cr5Joints,
    /// The newest `ServoJ` target, while the arm moves in joint space.
    joint_target_rad: Option<Cr5Joints>,
    servo_j_log: std::collections::VecDeque<(Instant, Cr5Joints)>,
    mode: RobotMode,
    enabled: bool,
    error_ids: ErrorIds,
    pose: Isometry3<f64>,
    target: Isometry3<f64>,
    remaining_s: f64,
    last_advance: Instant,
    servo_commands: u64,
    rejected_commands: u64,
    last_servo_command: Option<String>,
    command_id: u64,
    speed_factor: u32,
    digital_outputs: u64,
    tool_outputs: u8,
    gripper_register: Option<u16>,
    corruption: Option<Corruption>,
    tcp_control: bool,
    control_requests: u64,
    received: std::collections::VecDeque<String>,
    /// The id of the motion command in progress (its move lasts `remaining_s`), then of the last done.
    current_command_id: u64,
    http_refused: u64,
}

impl State {
    /// A disabled controller standing at `pose`, its joints put there by the CR5 model, answering
    /// commands without requesting control when `tcp_control` is already granted.
    fn at_rest(pose: Isometry3<f64>, now: Instant, tcp_control: bool) -> Self {
        let kinematics = Cr5Kinematics::new();
        let joints_rad = joints_for(&kinematics, &pose);
        Self {
            kinematics,
            joints_rad,
            joint_target_rad: None,
            servo_j_log: std::collections::VecDeque::new(),
            mode: RobotMode::Disabled,
            enabled: false,
            error_ids: ErrorIds::default(),
            pose,
            target: pose,
            remaining_s: 0.0,
            last_advance: now,
            servo_commands: 0,
            rejected_commands: 0,
            last_servo_command: None,
            command_id: 0,
            speed_factor: 100,
            digital_outputs: 0,
            tool_outputs: 0,
            gripper_register: None,
            corruption: None,
            tcp_control,
            control_requests: 0,
            received: std::collections::VecDeque::with_capacity(256),
            current_command_id: 0,
            http_refused: 0,
        }
    }

    fn advance(&mut self, now: Instant, max_speed_m_s: f64) {
        let dt = now.saturating_duration_since(self.last_advance).as_secs_f64();
        self.last_advance = now;
        if dt <= 0.0 || self.remaining_s <= 0.0 && self.pose == self.target {
            return;
        }
        let frac = if self.remaining_s <= dt {
            1.0
        } else {
            dt / self.remaining_s
        };
        self.remaining_s = (self.remaining_s - dt).max(0.0);
        if let Some(goal) = self.joint_target_rad {
            for (q, g) in self.joints_rad.iter_mut().zip(goal) {
                *q += (g - *q) * frac;
            }
            self.pose = self.kinematics.forward(&self.joints_rad);
            return;
        }
        let delta = self.target.translation.vector - self.pose.translation.vector;
        let mut step = delta * frac;
        let max_step = max_speed_m_s * dt;
        if step.norm() > max_step {
            step *= max_step / step.norm();
        }
        let rotation = self
            .pose
            .rotation
            .try_slerp(&self.target.rotation, frac, 1e-9)
            .unwrap_or(self.target.rotation);
        self.pose = Isometry3::from_parts(Translation3::from(self.pose.translation.vector + step), rotation);
        if self.remaining_s <= 0.0 && step.norm() < 1e-12 {
            self.pose.rotation = self.target.rotation;
        }
        self.joints_rad = self
            .kinematics
            .inverse(&self.pose, &self.joints_rad, IkWeights::FULL)
            .joints_rad;
    }

    fn fault_mode(&self) -> RobotMode {
        if !self.error_ids.is_empty() {
            RobotMode::Error
        } else if self.enabled {
            RobotMode::Enabled
        } else {
            RobotMode::Disabled
        }
    }
}

#[derive(Debug)]
struct Shared {
    config: EmulatorConfig,
    state: Mutex<State>,
    clients: Mutex<Vec<TcpStream>>,
    stop: AtomicBool,
}

/// The running emulator. Dropping it stops every thread and closes every socket.
#[derive(Debug)]
pub struct DobotEmulator {
    shared: Arc<Shared>,
    dashboard_addr: SocketAddr,
    motion_addr: SocketAddr,
    feedback_addr: SocketAddr,
    http_addr: SocketAddr,
    threads: Mutex<Vec<JoinHandle<()>>>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PortKind {
    Dashboard,
    Motion,
    Feedback,
    Http,
}

impl DobotEmulator {
    /// Binds the listeners and starts serving.
    pub fn start(config: EmulatorConfig) -> std::io::Result<Self> {
        let bind = |port: u16| TcpListener::bind((config.bind_host.as_str(), port));
        let dashboard = bind(config.dashboard_port)?;
        let motion = if config.firmware == Firmware::V3 {
            Some(bind(config.motion_port)?)
        } else {
            None
        };
        let feedback = bind(config.feedback_port)?;
        let http = bind(config.http_port)?;
        let dashboard_addr = dashboard.local_addr()?;
        let motion_addr = motion
            .as_ref()
            .map_or(Ok(dashboard_addr), TcpListener::local_addr)?;
        let feedback_addr = feedback.local_addr()?;
        let http_addr = http.local_addr()?;
        let tcp_control = config.firmware == Firmware::V3 || config.firmware_version < (4, 6);
        let shared = Arc::new(Shared {
            state: Mutex::new(State::at_rest(config.initial_pose, Instant::now(), tcp_control)),
            config,
            clients: Mutex::new(Vec::new()),
            stop: AtomicBool::new(false),
        });
        let mut threads = Vec::new();
        let mut listeners = vec![
            (dashboard, PortKind::Dashboard),
            (feedback, PortKind::Feedback),
            (http, PortKind::Http),
        ];
        if let Some(m) = motion {
            listeners.push((m, PortKind::Motion));
        }
        for (listener, kind) in listeners {
            listener.set_nonblocking(true)?;
            let shared = Arc::clone(&shared);
            threads.push(
                std::thread::Builder::new()
                    .name(format!("dobot-emu-{kind:?}"))
                    .spawn(move || accept_loop(&shared, &listener, kind))?,
            );
        }
        Ok(Self {
            shared,
            dashboard_addr,
            motion_addr,
            feedback_addr,
            http_addr,
            threads: Mutex::new(threads),
        })
    }

    pub fn dashboard_addr(&self) -> SocketAddr {
        self.dashboard_addr
    }
    /// The motion port (the dashboard port on V4).
    pub fn motion_addr(&self) -> SocketAddr {
        self.motion_addr
    }
    pub fn feedback_addr(&self) -> SocketAddr {
        self.feedback_addr
    }
    pub fn http_addr(&self) -> SocketAddr {
        self.http_addr
    }

    /// The current state, advanced to now.
    pub fn snapshot(&self) -> EmulatorSnapshot {
        let mut s = self.shared.state.lock();
        s.advance(Instant::now(), self.shared.config.max_speed_m_s);
        EmulatorSnapshot {
            mode: s.mode,
            enabled: s.enabled,
            pose: s.pose,
            target: s.target,
            servo_commands: s.servo_commands,
            rejected_commands: s.rejected_commands,
            last_servo_command: s.last_servo_command.clone(),
            joints_rad: s.joints_rad,
            servo_j_log: s.servo_j_log.iter().copied().collect(),
            speed_factor: s.speed_factor,
            digital_outputs: s.digital_outputs,
            tool_outputs: s.tool_outputs,
            gripper_register: s.gripper_register,
            active_clients: self.shared.clients.lock().len(),
            tcp_control: s.tcp_control,
            control_requests: s.control_requests,
            received: s.received.iter().cloned().collect(),
            current_command_id: s.current_command_id,
            http_refused: s.http_refused,
        }
    }

    /// Puts the robot in the error state (mode 9) with controller alarm `error_id`, halting it where it is.
    pub fn inject_error(&self, error_id: i32) {
        self.inject_alarm(None, error_id);
    }

    /// As [`Self::inject_error`], for the servo of joint `joint` (1..=6) or, with `None`, the controller.
    pub fn inject_alarm(&self, joint: Option<usize>, error_id: i32) {
        let mut s = self.shared.state.lock();
        s.advance(Instant::now(), self.shared.config.max_speed_m_s);
        match joint.and_then(|j| j.checked_sub(1)).filter(|&j| j < 6) {
            Some(j) => s.error_ids.servos[j].push(i64::from(error_id)),
            None => s.error_ids.controller.push(i64::from(error_id)),
        }
        s.mode = RobotMode::Error;
        s.target = s.pose;
        s.joint_target_rad = None;
        s.remaining_s = 0.0;
    }

    /// Closes every client connection; the listeners stay open so clients can reconnect.
    pub fn drop_connections(&self) {
        let clients = std::mem::take(&mut *self.shared.clients.lock());
        for c in clients {
            let _ = c.shutdown(Shutdown::Both);
        }
    }

    /// Corrupts the next feedback packet sent.
    pub fn corrupt_next_feedback(&self, corruption: Corruption) {
        self.shared.state.lock().corruption = Some(corruption);
    }

    /// Stops every thread and closes every socket. Idempotent.
    pub fn shutdown(&self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.drop_connections();
        let threads = std::mem::take(&mut *self.threads.lock());
        for t in threads {
            let _ = t.join();
        }
    }
}

impl Drop for DobotEmulator {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn accept_loop(shared: &Arc<Shared>, listener: &TcpListener, kind: PortKind) {
    let mut sessions: Vec<JoinHandle<()>> = Vec::new();
    while !shared.stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, peer)) => {
                debug!(?kind, %peer, "emulator: client connected");
                let _ = stream.set_nodelay(true);
                if kind != PortKind::Http
                    && let Ok(clone) = stream.try_clone()
                {
                    shared.clients.lock().push(clone);
                }
                let shared = Arc::clone(shared);
                let spawned = std::thread::Builder::new()
                    .name(format!("dobot-emu-{kind:?}-client"))
                    .spawn(move || match kind {
                        PortKind::Dashboard | PortKind::Motion => serve_commands(&shared, stream, kind),
                        PortKind::Feedback => serve_feedback(&shared, stream),
                        PortKind::Http => serve_http(&shared, stream),
                    });
                if let Ok(handle) = spawned {
                    sessions.push(handle);
                }
                sessions.retain(|h| !h.is_finished());
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(Duration::from_millis(2)),
            Err(e) => {
                debug!(error = %e, "emulator: accept failed");
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
    for s in sessions {
        let _ = s.join();
    }
}

fn forget_client(shared: &Shared, stream: &TcpStream) {
    let Ok(addr) = stream.peer_addr() else { return };
    let Ok(local) = stream.local_addr() else { return };
    shared
        .clients
        .lock()
        .retain(|c| c.peer_addr().ok() != Some(addr) || c.local_addr().ok() != Some(local));
}

/// Takes one complete command off the front of `buffer`: the text up to the parenthesis that closes the first
/// one, or a line without parentheses. Terminators (none, `\n`, `\r\n`) and stray `;` between commands are
/// skipped, which is how the controller accepts all three.
fn next_command(buffer: &mut String) -> Option<String> {
    let start = buffer.find(|c: char| !c.is_whitespace() && c != ';')?;
    buffer.drain(..start);
    let mut depth = 0i32;
    for (i, c) in buffer.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => {
                depth -= 1;
                if depth == 0 {
                    let command: String = buffer.drain(..=i).collect();
                    return Some(command);
                }
            }
            '\n' if depth == 0 => {
                let command: String = buffer.drain(..=i).collect();
                return Some(command.trim().to_owned());
            }
            _ => {}
        }
    }
    None
}

fn serve_commands(shared: &Arc<Shared>, mut stream: TcpStream, kind: PortKind) {
    let _ = stream.set_read_timeout(Some(Duration::from_millis(20)));
    let mut text = String::new();
    let mut chunk = [0u8; 4096];
    while !shared.stop.load(Ordering::SeqCst) {
        let n = match stream.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => continue,
            Err(_) => break,
        };
        text.push_str(&String::from_utf8_lossy(&chunk[..n]));
        loop {
            let reply = if shared.config.answer_stray_terminator && take_stray_terminator(&mut text) {
                Some(reply(-10000, "", ""))
            } else if let Some(command) = next_command(&mut text) {
                // EnableRobot answers once the brakes are released; other commands queue behind it.
                if is_named(&command, "enablerobot") && !shared.config.enable_delay.is_zero() {
                    std::thread::sleep(shared.config.enable_delay);
                }
                execute(shared, &command, kind)
            } else {
                break;
            };
            if let Some(reply) = reply
                && stream.write_all(reply.as_bytes()).is_err()
            {
                forget_client(shared, &stream);
                return;
            }
        }
        if text.len() > 64 * 1024 {
            // A client streaming text with no command in it: drop it rather than grow without bound.
            text.clear();
            let _ = stream.write_all(b"-10000,{},;");
        }
    }
    forget_client(shared, &stream);
}

/// Takes a line end left between commands off the front of `buffer`.
fn take_stray_terminator(buffer: &mut String) -> bool {
    for end in ["\r\n", "\n"] {
        if buffer.starts_with(end) {
            buffer.drain(..end.len());
            return true;
        }
    }
    false
}

fn is_named(command: &str, lowercase_name: &str) -> bool {
    split_command(command).is_some_and(|(name, _)| name.eq_ignore_ascii_case(lowercase_name))
}

fn reply(code: i32, values: &str, echo: &str) -> String {
    format!("{code},{{{values}}},{echo};")
}

fn parse_f64(p: &str) -> Option<f64> {
    p.trim().parse::<f64>().ok().filter(|v| v.is_finite())
}

fn fmt6(v: &[f64; 6]) -> String {
    v.iter().map(|x| format!("{x:.4}")).collect::<Vec<_>>().join(",")
}

fn pose_mm_deg(pose: &Isometry3<f64>, convention: EulerConvention) -> [f64; 6] {
    let p = pose.translation.vector * 1000.0;
    let [rx, ry, rz] = convention.to_angles_deg(&pose.rotation);
    [p.x, p.y, p.z, rx, ry, rz]
}

/// Joints that put the flange at `pose`: the first of a few elbow-up seeds from which the solve reaches it
/// (the emulator's start; any solution will do, as long as joints and pose agree).
fn joints_for(kinematics: &Cr5Kinematics, pose: &Isometry3<f64>) -> Cr5Joints {
    use std::f64::consts::{FRAC_PI_2, PI};
    let mut best: Option<phone2act_core::kinematics::IkSolution<6>> = None;
    for j1 in [0.0, FRAC_PI_2, PI, -FRAC_PI_2] {
        for (j2, j3) in [(0.3, 1.5), (-0.3, -1.5), (0.0, 1.0)] {
            let seed = [j1, j2, j3, 0.0, FRAC_PI_2, 0.0];
            let sol = kinematics.inverse(pose, &seed, IkWeights::FULL);
            if sol.position_reached && sol.orientation_reached {
                return sol.joints_rad;
            }
            let better = best.as_ref().is_none_or(|b| {
                sol.position_error_m + sol.orientation_error_rad
                    < b.position_error_m + b.orientation_error_rad
            });
            if better {
                best = Some(sol);
            }
        }
    }
    best.map_or([0.0; 6], |b| b.joints_rad)
}

fn joints_deg(joints_rad: &Cr5Joints) -> [f64; 6] {
    joints_rad.map(f64::to_degrees)
}

/// Executes one command and returns the reply text, or `None` when the controller does not answer.
#[allow(clippy::too_many_lines)] // one arm per command reads better than a table of closures
fn execute(shared: &Shared, command: &str, kind: PortKind) -> Option<String> {
    let config = &shared.config;
    let v3 = config.firmware == Firmware::V3;
    let mut s = shared.state.lock();
    if s.received.len() == 256 {
        s.received.pop_front();
    }
    s.received.push_back(command.to_owned());
    let Some((name, params)) = split_command(command) else {
        return Some(reply(-10000, "", command));
    };
    let lname = name.to_ascii_lowercase();
    s.advance(Instant::now(), config.max_speed_m_s);
    let is_motion = matches!(lname.as_str(), "servop" | "servoj" | "movl" | "movj");
    // V3 keeps motion commands on the motion port and settings on the dashboard.
    if v3 && (is_motion != (kind == PortKind::Motion)) {
        s.rejected_commands += 1;
        return Some(reply(-10000, "", command));
    }
    // V4.6+ before `RequestControl()`: enabling, moving and outputs go unanswered (issue #25's symptom);
    // queries and the control request itself are answered.
    let needs_control = is_motion
        || matches!(
            lname.as_str(),
            "enablerobot" | "doinstant" | "tooldoinstant" | "do" | "tooldo"
        );
    if needs_control && !s.tcp_control {
        return None;
    }
    let code_and_values: (i32, String) = match lname.as_str() {
        "enablerobot" => {
            if params.len() > 5 {
                (-20000, String::new())
            } else if !s.error_ids.is_empty() {
                (-2, String::new())
            } else {
                s.enabled = true;
                s.mode = RobotMode::Enabled;
                (0, String::new())
            }
        }
        "disablerobot" => {
            s.enabled = false;
            s.mode = s.fault_mode();
            (0, String::new())
        }
        "clearerror" => {
            s.error_ids = ErrorIds::default();
            s.mode = s.fault_mode();
            (0, String::new())
        }
        "requestcontrol" if config.firmware_version < (4, 6) => (-10000, String::new()),
        "requestcontrol" => {
            s.control_requests += 1;
            // §3.132: allowed powered off or disabled; refused enabled, running, dragging, or in error
            // while enabled.
            if s.enabled {
                (-1, String::new())
            } else {
                s.tcp_control = true;
                (0, String::new())
            }
        }
        "poweron" | "stop" => (0, String::new()),
        "robotmode" => (0, s.mode.code().to_string()),
        // §3.40: seven lists, the controller's then one per servo.
        "geterrorid" => (0, s.error_ids.to_values()),
        "getpose" => (0, fmt6(&pose_mm_deg(&s.pose, config.convention))),
        "getangle" => (0, fmt6(&joints_deg(&s.joints_rad))),
        "speedfactor" => match params.as_slice() {
            [r] => match r.trim().parse::<u32>() {
                Ok(r) if (1..=100).contains(&r) => {
                    s.speed_factor = r;
                    (0, String::new())
                }
                Ok(_) => (-40001, String::new()),
                Err(_) => (-30001, String::new()),
            },
            _ => (-20000, String::new()),
        },
        "servop" => servo_p(&mut s, config, &params),
        "servoj" => servo_j(&mut s, config, &params),
        "movl" | "movj" => move_to(&mut s, config, &params),
        "do" | "doinstant" | "doexecute" | "tooldo" | "tooldoinstant" | "tooldoexecute" => {
            let v4_only = matches!(lname.as_str(), "doinstant" | "tooldoinstant");
            let v3_only = matches!(lname.as_str(), "doexecute" | "tooldoexecute");
            if (v3 && v4_only) || (!v3 && v3_only) {
                (-10000, String::new())
            } else {
                set_output(&mut s, lname.starts_with("tool"), &params)
            }
        }
        "getdo" | "gettooldo" => match params.first().and_then(|p| p.trim().parse::<u32>().ok()) {
            Some(i) if (1..=64).contains(&i) => {
                let bits = if lname == "getdo" {
                    s.digital_outputs
                } else {
                    u64::from(s.tool_outputs)
                };
                (0, ((bits >> (i - 1)) & 1).to_string())
            }
            _ => (-40001, String::new()),
        },
        _ => (-10000, String::new()),
    };
    if code_and_values.0 != 0 {
        s.rejected_commands += 1;
    }
    Some(reply(code_and_values.0, &code_and_values.1, command.trim()))
}

fn parse_pose(params: &[&str]) -> Result<[f64; 6], i32> {
    let mut pose = [0.0; 6];
    for (i, p) in params.iter().take(6).enumerate() {
        pose[i] = parse_f64(p).ok_or(-30001 - i as i32)?;
    }
    Ok(pose)
}

fn pose_from_mm_deg(v: &[f64; 6], convention: EulerConvention) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(v[0] / 1000.0, v[1] / 1000.0, v[2] / 1000.0),
        convention.to_rotation(v[3], v[4], v[5]),
    )
}

/// The checks `ServoP` and `ServoJ` share: six required values, then `t`, `aheadtime`, `gain` (V4 only), the
/// robot enabled and without error. Returns the six values and `t`, or the error id.
fn servo_values(s: &State, config: &EmulatorConfig, params: &[&str]) -> Result<([f64; 6], f64), i32> {
    let v3 = config.firmware == Firmware::V3;
    if params.len() < 6 || (v3 && params.len() != 6) || params.len() > 9 {
        return Err(-20000);
    }
    let values = parse_pose(params)?;
    let t_s = servo_t_s(params)?;
    if !s.error_ids.is_empty() {
        return Err(-2);
    }
    if !s.enabled {
        return Err(-1);
    }
    Ok((values, t_s))
}

/// Accepts `ServoJ(J1..J6[,t,aheadtime,gain])`, degrees: the joints move along a straight joint-space line to
/// arrive `t` seconds later.
fn servo_j(s: &mut State, config: &EmulatorConfig, params: &[&str]) -> (i32, String) {
    let (joints_deg, t_s) = match servo_values(s, config, params) {
        Ok(v) => v,
        Err(code) => return (code, String::new()),
    };
    let goal = joints_deg.map(f64::to_radians);
    if !s.kinematics.within_limits(&goal) {
        return (-40001, String::new());
    }
    s.joint_target_rad = Some(goal);
    s.target = s.kinematics.forward(&goal);
    s.remaining_s = t_s;
    s.servo_commands += 1;
    s.command_id += 1;
    s.current_command_id = s.command_id;
    s.mode = RobotMode::Running;
    if s.servo_j_log.len() == SERVO_J_LOG {
        s.servo_j_log.pop_front();
    }
    s.servo_j_log.push_back((Instant::now(), goal));
    s.last_servo_command = Some(format!("ServoJ({})", params.join(",")));
    (0, s.command_id.to_string())
}

fn servo_t_s(params: &[&str]) -> Result<f64, i32> {
    let mut t_s = 0.1;
    for (n, p) in params.iter().skip(6).enumerate() {
        let code_base = n as i32 + 1;
        let Some((key, value)) = p.split_once('=') else {
            return Err(-50000 - code_base);
        };
        let Some(value) = parse_f64(value) else {
            return Err(-50000 - code_base);
        };
        let ok = match key.trim().to_ascii_lowercase().as_str() {
            "t" => {
                t_s = value;
                (0.004..=3600.0).contains(&value)
            }
            "aheadtime" => (20.0..=100.0).contains(&value),
            "gain" => (200.0..=1000.0).contains(&value),
            _ => return Err(-50000 - code_base),
        };
        if !ok {
            return Err(-60000 - code_base);
        }
    }
    Ok(t_s)
}

fn servo_p(s: &mut State, config: &EmulatorConfig, params: &[&str]) -> (i32, String) {
    let (pose, t_s) = match servo_values(s, config, params) {
        Ok(v) => v,
        Err(code) => return (code, String::new()),
    };
    s.joint_target_rad = None;
    s.target = pose_from_mm_deg(&pose, config.convention);
    s.remaining_s = t_s;
    s.servo_commands += 1;
    s.command_id += 1;
    s.current_command_id = s.command_id;
    s.mode = RobotMode::Running;
    s.last_servo_command = Some(format!("ServoP({})", params.join(",")));
    (0, s.command_id.to_string())
}

/// `MovJ`/`MovL` (guide §3.74, §3.75; V3: positional on the motion port). The target is `pose={x,..}` or
/// `joint={j1,..}` (V4), six positional values (V3). Queue commands: the reply carries the command id at once
/// (§2.2.1, "队列指令value返回值指队列ID"), while the move itself takes its motion time: the robot is
/// `Running` with that id in the feedback's `CurrentCommandId` until it arrives and only then `Enabled`
/// again, which is what Dobot's demo waits for (TCP-IP-Python-V4 `DobotDemo.py`: mode 5 and the id).
fn move_to(s: &mut State, config: &EmulatorConfig, params: &[&str]) -> (i32, String) {
    let first = params.first().map(|p| p.trim()).unwrap_or_default();
    let (space, inner) = match first.split_once('=') {
        Some((key, value)) => (key.trim().to_ascii_lowercase(), Some(value.trim())),
        None => (String::new(), None),
    };
    let values: Vec<&str> = match (space.as_str(), inner) {
        ("pose" | "joint", Some(v)) if config.firmware == Firmware::V4 => {
            split_top_level(v.trim_start_matches('{').trim_end_matches('}'))
        }
        (_, Some(_)) => return (-30001, String::new()),
        _ if config.firmware == Firmware::V3 => params.to_vec(),
        // V4 wants the named form.
        _ => return (-30001, String::new()),
    };
    if values.len() != 6 {
        return (-20000, String::new());
    }
    let values = match parse_pose(&values) {
        Ok(p) => p,
        Err(code) => return (code, String::new()),
    };
    if !s.error_ids.is_empty() {
        return (-2, String::new());
    }
    if !s.enabled {
        return (-1, String::new());
    }
    // Joints (degrees) become the flange pose they put the CR5 model in.
    let target = if space == "joint" {
        s.kinematics.forward(&values.map(f64::to_radians))
    } else {
        pose_from_mm_deg(&values, config.convention)
    };
    let distance_m = (target.translation.vector - s.pose.translation.vector).norm();
    s.joint_target_rad = None;
    s.target = target;
    s.remaining_s = (distance_m / (0.25 * f64::from(s.speed_factor) / 100.0)).max(0.05);
    s.command_id += 1;
    s.current_command_id = s.command_id;
    s.mode = RobotMode::Running;
    (0, s.command_id.to_string())
}

fn set_output(s: &mut State, tool: bool, params: &[&str]) -> (i32, String) {
    if params.len() < 2 {
        return (-20000, String::new());
    }
    let Ok(index) = params[0].trim().parse::<u32>() else {
        return (-30001, String::new());
    };
    let Ok(status) = params[1].trim().parse::<u8>() else {
        return (-30002, String::new());
    };
    let max_index = if tool { 4 } else { 24 };
    if !(1..=max_index).contains(&index) {
        return (-40001, String::new());
    }
    if status > 1 {
        return (-40002, String::new());
    }
    if tool {
        let bit = 1u8 << (index - 1);
        s.tool_outputs = if status == 1 {
            s.tool_outputs | bit
        } else {
            s.tool_outputs & !bit
        };
    } else {
        let bit = 1u64 << (index - 1);
        s.digital_outputs = if status == 1 {
            s.digital_outputs | bit
        } else {
            s.digital_outputs & !bit
        };
    }
    (0, String::new())
}

fn serve_feedback(shared: &Arc<Shared>, mut stream: TcpStream) {
    let config = &shared.config;
    let mut next = Instant::now();
    while !shared.stop.load(Ordering::SeqCst) {
        let (packet, corruption) = {
            let mut s = shared.state.lock();
            s.advance(Instant::now(), config.max_speed_m_s);
            if s.mode == RobotMode::Running && s.remaining_s <= 0.0 {
                s.mode = RobotMode::Enabled;
            }
            let tool = pose_mm_deg(&s.pose, config.convention);
            let target = pose_mm_deg(&s.target, config.convention);
            let q = s.pose.rotation.into_inner();
            let packet = FeedbackPacket {
                digital_outputs: s.digital_outputs,
                robot_mode: s.mode.code(),
                timestamp_ms: SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map_or(0, |d| d.as_millis() as u64),
                q_target_deg: joints_deg(&s.joint_target_rad.unwrap_or(s.joints_rad)),
                q_actual_deg: joints_deg(&s.joints_rad),
                tool_vector_actual: tool,
                tool_vector_target: target,
                enable_status: u8::from(s.enabled),
                error_status: u8::from(!s.error_ids.is_empty()),
                current_command_id: s.current_command_id,
                actual_quaternion_wxyz: if config.fill_quaternion {
                    [q.w, q.i, q.j, q.k]
                } else {
                    [0.0; 4]
                },
                ..FeedbackPacket::default()
            };
            (packet, s.corruption.take())
        };
        let mut bytes = packet.encode();
        match corruption {
            Some(Corruption::Truncate) => bytes.truncate(700),
            Some(Corruption::BadTestValue) => bytes[50] ^= 0x5A,
            Some(Corruption::BadSize) => bytes[0..2].copy_from_slice(&1000u16.to_le_bytes()),
            None => {}
        }
        if stream.write_all(&bytes).is_err() {
            break;
        }
        next += config.feedback_period;
        let now = Instant::now();
        match next.checked_duration_since(now) {
            Some(rest) => std::thread::sleep(rest),
            // The controller keeps its 8 ms grid: late packets are followed by on-time ones, not a burst.
            None if now.duration_since(next) > config.feedback_period => next = now,
            None => {}
        }
    }
    forget_client(shared, &stream);
}

/// Path of the tool data exchange on the controller's port 22000.
pub const TOOL_DATA_EXCHANGE_PATH: &str = "/interface/toolDataExchange";

fn serve_http(shared: &Arc<Shared>, mut stream: TcpStream) {
    let _ = stream.set_read_timeout(Some(Duration::from_secs(2)));
    let mut request = Vec::new();
    let mut chunk = [0u8; 1024];
    let (head_end, content_length) = loop {
        let n = match stream.read(&mut chunk) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        request.extend_from_slice(&chunk[..n]);
        if let Some(pos) = request.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&request[..pos]).to_ascii_lowercase();
            let length = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok())
                .unwrap_or(0);
            break (pos + 4, length);
        }
        if request.len() > 16 * 1024 {
            return;
        }
    };
    while request.len() < head_end + content_length {
        match stream.read(&mut chunk) {
            Ok(0) | Err(_) => return,
            Ok(n) => request.extend_from_slice(&chunk[..n]),
        }
    }
    // The controller's web service on port 22000 routes by method and path: the tool data exchange is a
    // POST to /interface/toolDataExchange (the Phone2Act CR5 bridge, OmMandhane/Phone2Act
    // `dobot_hardware_bridge.py`; the same service answers TCP-IP-Python-V4 `GetError`'s POST
    // /interface/language and GET /protocol/getAlarm). Anything else is refused, so a wrong method or path
    // in the bridge fails here as it would on the robot.
    let request_line = String::from_utf8_lossy(&request[..head_end]);
    let mut words = request_line.split_whitespace();
    let (method, path) = (words.next().unwrap_or_default(), words.next().unwrap_or_default());
    let refusal = match (method, path) {
        ("POST", TOOL_DATA_EXCHANGE_PATH) => None,
        (_, TOOL_DATA_EXCHANGE_PATH) => Some("405 Method Not Allowed"),
        _ => Some("404 Not Found"),
    };
    if let Some(status) = refusal {
        shared.state.lock().http_refused += 1;
        let response = format!("HTTP/1.1 {status}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
        let _ = stream.write_all(response.as_bytes());
        return;
    }
    let body = &request[head_end..head_end + content_length];
    let frame: Option<Vec<u8>> = serde_json::from_slice::<serde_json::Value>(body)
        .ok()
        .and_then(|v| {
            v.get("value")?
                .as_array()?
                .iter()
                .map(|x| x.as_u64().and_then(|x| u8::try_from(x).ok()))
                .collect()
        });
    let accepted = frame.as_deref().and_then(parse_modbus_write_register);
    let (status, text) = match accepted {
        Some((_slave, _register, value)) => {
            shared.state.lock().gripper_register = Some(value);
            ("200 OK", "{\"status\":\"ok\"}")
        }
        None => ("400 Bad Request", "{\"status\":\"bad frame\"}"),
    };
    let response = format!(
        "HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{text}",
        text.len()
    );
    let _ = stream.write_all(response.as_bytes());
}

/// Rotation helper for tests: a tool pointing down (-z) as a CR5 usually holds it.
pub fn tool_down(x_m: f64, y_m: f64, z_m: f64, yaw_rad: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(x_m, y_m, z_m),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad)
            * UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_are_split_with_any_terminator() {
        let mut b =
            String::from("EnableRobot()ServoP(1,2,3,4,5,6,t=0.1)\r\nRobotMode()\nGetPose(user=0, tool=0");
        assert_eq!(next_command(&mut b).as_deref(), Some("EnableRobot()"));
        assert_eq!(next_command(&mut b).as_deref(), Some("ServoP(1,2,3,4,5,6,t=0.1)"));
        assert_eq!(next_command(&mut b).as_deref(), Some("RobotMode()"));
        assert_eq!(next_command(&mut b), None);
        b.push(')');
        assert_eq!(next_command(&mut b).as_deref(), Some("GetPose(user=0, tool=0)"));
        let mut garbage = String::from("hello\n");
        assert_eq!(next_command(&mut garbage).as_deref(), Some("hello"));
    }

    #[test]
    fn dynamics_reach_the_target_in_t() {
        let start = Instant::now();
        let pose = tool_down(-0.4, 0.0, 0.3, 0.0);
        let mut s = State::at_rest(pose, start, true);
        (s.mode, s.enabled) = (RobotMode::Enabled, true);
        s.target = tool_down(-0.35, 0.02, 0.3, 0.2);
        s.remaining_s = 0.1;
        s.advance(start + Duration::from_millis(50), 1.0);
        let halfway = (s.pose.translation.vector - pose.translation.vector).norm();
        let full = (s.target.translation.vector - pose.translation.vector).norm();
        assert!((halfway / full - 0.5).abs() < 0.05, "{halfway} of {full}");
        s.advance(start + Duration::from_millis(120), 1.0);
        assert!((s.pose.translation.vector - s.target.translation.vector).norm() < 1e-9);
        assert!(s.pose.rotation.angle_to(&s.target.rotation) < 1e-9);
        // The joints followed the pose: the model puts them where the tool is.
        let model = s.kinematics.forward(&s.joints_rad);
        assert!((model.translation.vector - s.pose.translation.vector).norm() < 2e-4);
        assert!(model.rotation.angle_to(&s.pose.rotation) < 2e-3);
    }

    #[test]
    fn servo_j_moves_the_joints_and_the_pose_follows() {
        let config = EmulatorConfig::default();
        let start = Instant::now();
        let kinematics = Cr5Kinematics::new();
        let joints_rad = joints_for(&kinematics, &config.initial_pose);
        let from = kinematics.forward(&joints_rad);
        assert!((from.translation.vector - config.initial_pose.translation.vector).norm() < 2e-4);
        let mut s = State::at_rest(from, start, true);
        (s.mode, s.enabled) = (RobotMode::Enabled, true);
        let mut goal = joints_rad;
        goal[5] += 0.4;
        let goal_deg = goal.map(f64::to_degrees).map(|v| format!("{v:.6}"));
        let mut params: Vec<&str> = goal_deg.iter().map(String::as_str).collect();
        params.push("t=0.1");
        assert_eq!(servo_j(&mut s, &config, &params).0, 0);
        s.last_advance = start;
        s.advance(start + Duration::from_millis(50), 1.0);
        assert!(
            (s.joints_rad[5] - joints_rad[5] - 0.2).abs() < 1e-3,
            "{:?}",
            s.joints_rad
        );
        s.advance(start + Duration::from_millis(120), 1.0);
        assert!((s.joints_rad[5] - goal[5]).abs() < 1e-7);
        // J6 turns the flange about its own axis: the position stays, the orientation turns by the same angle.
        assert!((s.pose.translation.vector - from.translation.vector).norm() < 1e-6);
        assert!((s.pose.rotation.angle_to(&from.rotation) - 0.4).abs() < 1e-6);
        assert_eq!(s.servo_j_log.len(), 1);
        // Out of range, too few values: refused as the controller does.
        let far = ["0", "0", "200", "0", "0", "0"];
        assert_eq!(servo_j(&mut s, &config, &far).0, -40001);
        assert_eq!(servo_j(&mut s, &config, &far[..5]).0, -20000);
    }
}
