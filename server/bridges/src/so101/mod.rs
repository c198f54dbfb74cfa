//! LeRobot SO-101 bridge over a Feetech STS3215 bus.
//!
//! One thread runs a fixed-rate cycle (100 Hz by default): take the newest target (its joint targets when the
//! server solved them, otherwise the inverse kinematics seeded with the previous goal, position first,
//! orientation weighted), move the goal toward it by at most what each joint's speed limit allows since the
//! last cycle, sync-write the six goal positions, sync-read the six present positions and publish forward
//! kinematics as [`Feedback`]. A target farther than one cycle's travel reaches the servos as a ramp over
//! several cycles, whoever sent it. Joint angles
//! are lerobot's `DEGREES` values (0 at the middle of each calibrated range), which is the zero of the "new
//! calib" URDF; the gripper uses lerobot's `RANGE_0_100`.
//!
//! A servo that does not answer or a corrupt reply fails the cycle: health turns to `Error` naming the servo,
//! no new goals are written (the servos hold the last one) and the next good read clears it. A failed port
//! (adapter unplugged) is `Disconnected` until [`Control::Reconnect`].
//!
//! Servo alarms come with every answer and are sorted by [`alarm_action`]: a warning (over-voltage; overload on
//! the gripper) keeps the arm working and is shown by [`Bridge::warning`] and logged once when it appears and
//! when it clears; any other alarm stops the arm (no new goals, `Error` naming the servo and the alarm) until
//! [`Control::ClearError`] once the servo no longer reports it.
//!
//! Positions are read as single-turn angles even from a servo left in multi-turn feedback mode (`Phase` bit 4,
//! which configuring clears, as lerobot does).

pub mod calibration;

use crate::feetech::protocol::{
    POSITION_SIGN_BIT, alarm, encode_sign_magnitude, register, single_turn_position, status_error_text,
};
use crate::feetech::{BusError, BusStats, FeetechBus};
use crate::runtime::{LinkContext, Measured, RobotLink, Schedule, ThreadedBridge};
use crate::sim::ClockFn;
use crate::{BridgeError, Command, Control, Health};
use calibration::{Calibration, MotorCalibration, multi_turn_feedback};
use parking_lot::Mutex;
use phone2act_core::JointRateLimiter;
use phone2act_core::joint_motion::STS3215_MAX_VELOCITY_RAD_S;
use phone2act_core::kinematics::{
    IkWeights, SO101_ARM_DOF, SO101_ARM_JOINT_NAMES, SO101_JOINT_NAMES, So101Joints, So101Kinematics,
    clamp_to_limits,
};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tracing::{info, warn};

/// Number of motors: five arm joints and the gripper.
pub const MOTORS: usize = SO101_ARM_DOF + 1;

/// Configuration of one SO-101 follower arm (`[arms.so101]` in the server config).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct So101Config {
    /// Serial device of the bus adapter, e.g. `/dev/ttyACM0` (or a `/dev/serial/by-id/...` link).
    pub port: String,
    #[serde(default = "default_baudrate")]
    pub baudrate: u32,
    /// lerobot calibration JSON (e.g. `~/.cache/huggingface/lerobot/calibration/robots/so101_follower/<id>.json`).
    pub calibration_file: PathBuf,
    /// Servo ids of shoulder_pan, shoulder_lift, elbow_flex, wrist_flex, wrist_roll, gripper. Defaults to the
    /// calibration file's ids.
    #[serde(default)]
    pub ids: Option<[u8; MOTORS]>,
    /// Control and feedback rate.
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
    /// Time a servo has to answer.
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: u64,
    /// Orientation weight of the IK (0 = position only, 1 = as much orientation as a 5-DoF arm allows).
    #[serde(default = "default_orientation_weight")]
    pub ik_orientation_weight: f64,
    /// Gripper positions (lerobot `RANGE_0_100`) for open and closed.
    #[serde(default = "default_gripper_open_pct")]
    pub gripper_open_pct: f64,
    #[serde(default)]
    pub gripper_closed_pct: f64,
    /// Write lerobot's motor settings (PID, acceleration, gripper current limits) and the calibration into
    /// the servos at start, as lerobot's `configure()` does.
    #[serde(default = "default_true")]
    pub configure_motors: bool,
    #[serde(default = "default_true")]
    pub enable_on_start: bool,
    /// Largest speed of each arm joint (rad/s) the goal ramps at. Not a key of `[arms.so101]`: the server
    /// sets it from the arm's `[arms.<name>.joint_limits]`, so the servos and the server's commands share
    /// one limit.
    #[serde(skip, default = "default_max_velocity_rad_s")]
    pub max_velocity_rad_s: Vec<f64>,
}

fn default_max_velocity_rad_s() -> Vec<f64> {
    vec![STS3215_MAX_VELOCITY_RAD_S; SO101_ARM_DOF]
}

fn default_baudrate() -> u32 {
    1_000_000
}
fn default_rate_hz() -> f64 {
    100.0
}
fn default_timeout_ms() -> u64 {
    20
}
fn default_orientation_weight() -> f64 {
    1.0
}
fn default_gripper_open_pct() -> f64 {
    100.0
}
fn default_true() -> bool {
    true
}

impl So101Config {
    /// A config with every default.
    pub fn new(port: impl Into<String>, calibration_file: impl Into<PathBuf>) -> Self {
        Self {
            port: port.into(),
            baudrate: default_baudrate(),
            calibration_file: calibration_file.into(),
            ids: None,
            rate_hz: default_rate_hz(),
            timeout_ms: default_timeout_ms(),
            ik_orientation_weight: default_orientation_weight(),
            gripper_open_pct: default_gripper_open_pct(),
            gripper_closed_pct: 0.0,
            configure_motors: true,
            enable_on_start: true,
            max_velocity_rad_s: default_max_velocity_rad_s(),
        }
    }

    pub fn validate(&self) -> Result<(), BridgeError> {
        let bad = |m: String| Err(BridgeError::Config(format!("so101: {m}")));
        if self.port.trim().is_empty() {
            return bad("port is empty".into());
        }
        if !(self.rate_hz.is_finite() && (1.0..=1000.0).contains(&self.rate_hz)) {
            return bad(format!("rate_hz {} outside [1, 1000]", self.rate_hz));
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return bad(format!("timeout_ms {} outside [1, 1000]", self.timeout_ms));
        }
        if self.max_velocity_rad_s.len() != SO101_ARM_DOF
            || JointRateLimiter::new(self.max_velocity_rad_s.clone()).is_err()
        {
            return bad(format!(
                "max_velocity_rad_s {:?} is not {SO101_ARM_DOF} finite positive speeds",
                self.max_velocity_rad_s
            ));
        }
        if !(0.0..=1.0).contains(&self.ik_orientation_weight) {
            return bad(format!(
                "ik_orientation_weight {} outside [0, 1]",
                self.ik_orientation_weight
            ));
        }
        for (name, v) in [
            ("gripper_open_pct", self.gripper_open_pct),
            ("gripper_closed_pct", self.gripper_closed_pct),
        ] {
            if !(0.0..=100.0).contains(&v) {
                return bad(format!("{name} {v} outside [0, 100]"));
            }
        }
        if let Some(ids) = self.ids {
            let mut sorted = ids.to_vec();
            sorted.sort_unstable();
            sorted.dedup();
            if sorted.len() != MOTORS || ids.iter().any(|&id| id > crate::feetech::protocol::MAX_ID) {
                return bad(format!("ids {ids:?} must be {MOTORS} distinct values in 0..=252"));
            }
        }
        Ok(())
    }
}

/// Counters and the last fault, for status pages, tests and benchmarks.
#[derive(Clone, Debug, PartialEq)]
pub struct So101Stats {
    pub cycles: u64,
    pub goals_written: u64,
    pub failed_cycles: u64,
    pub targets_superseded: u64,
    /// Targets whose IK did not reach the position (out of reach); the closest pose was sent.
    pub unreachable_targets: u64,
    pub last_error: Option<String>,
    /// The alarms that keep the arm working, as [`Bridge::warning`] shows them.
    pub warning: Option<String>,
    /// Each servo's alarm bits in the last good read, in motor order.
    pub alarms: [u8; MOTORS],
    /// Mean work time of a cycle (IK, sync write, sync read), microseconds.
    pub mean_cycle_work_us: f64,
    pub bus: BusStats,
}

#[derive(Debug)]
enum Link {
    Up,
    Down(String),
}

#[derive(Debug)]
struct Status {
    link: Link,
    /// The last cycle's failure, cleared by the next good read.
    cycle_error: Option<String>,
    last_error: Option<String>,
    enabled: bool,
    bus_time_total: Duration,
    /// Each servo's alarm bits in the last good read.
    alarms: [u8; MOTORS],
    /// An alarm that stopped the arm, held until [`Control::ClearError`].
    alarm_stop: Option<String>,
}

/// What a servo alarm does to the arm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AlarmAction {
    /// The arm keeps working; status and the log say so.
    Warn,
    /// No new goals until the operator clears it.
    Stop,
}

/// Decides per alarm bit ([`alarm`]; Feetech STS memory table §3.2 "Servo Status", SDK `ERRBIT_*`) what it does
/// to the arm, for the motor at `motor` (index in [`SO101_JOINT_NAMES`]):
/// - input voltage: warn. The servo keeps driving; 7.4 V STS3215s on the 12 V supply of a 12 V arm report it
///   all the time (huggingface/lerobot issue #1010), and lerobot's read and write loop ignores it.
/// - overload on the gripper: warn. Squeezing an object is the gripper's job, and the servo limits its own
///   torque (`Protective_Torque`) while the alarm holds.
/// - overload on an arm joint: stop. The arm is pushing against something (a collision, a payload past what the
///   joint holds); new goals would push harder.
/// - angle sensor: stop. The encoder is the position feedback: forward kinematics and goals would be wrong.
/// - overheat, overcurrent: stop. The servo is at its protection limit (by default it drops torque); driving on
///   heats or loads it further.
/// - bits the memory table does not document: stop, since what they mean is unknown.
pub fn alarm_action(motor: usize, bit: u8) -> AlarmAction {
    let gripper = motor == MOTORS - 1;
    match bit {
        alarm::VOLTAGE => AlarmAction::Warn,
        alarm::OVERLOAD if gripper => AlarmAction::Warn,
        _ => AlarmAction::Stop,
    }
}

/// The bits of `error` from the motor at `motor` that stop the arm.
fn stopping_bits(motor: usize, error: u8) -> u8 {
    (0..8)
        .map(|b| 1u8 << b)
        .filter(|&bit| error & bit != 0 && alarm_action(motor, bit) == AlarmAction::Stop)
        .fold(0, |acc, bit| acc | bit)
}

/// "servo 6 (gripper): overload (0x20)" for each motor with bits in `bits`, joined by "; ".
fn describe_alarms(ids: [u8; MOTORS], bits: [u8; MOTORS]) -> Option<String> {
    let parts: Vec<String> = (0..MOTORS)
        .filter(|&i| bits[i] != 0)
        .map(|i| {
            format!(
                "servo {} ({}): {}",
                ids[i],
                SO101_JOINT_NAMES[i],
                status_error_text(bits[i])
            )
        })
        .collect();
    (!parts.is_empty()).then(|| parts.join("; "))
}

/// The goal the servos are ramped toward.
#[derive(Debug)]
struct Ramp {
    /// Starts at the present positions when torque comes on; its last value is the goal last written.
    limiter: JointRateLimiter,
    /// Joints, gripper target and seq of the newest command; `None` before any.
    target: Option<(So101Joints, f64, u64)>,
    /// True until the goal written equals the target.
    moving: bool,
}

/// The SO-101's protocol side: configure, write goals, read positions, over the Feetech bus.
#[derive(Debug)]
pub struct So101Link {
    config: So101Config,
    calibration: [MotorCalibration; MOTORS],
    ids: [u8; MOTORS],
    joint_names: Vec<String>,
    kinematics: So101Kinematics,
    bus: Mutex<Option<FeetechBus>>,
    status: Mutex<Status>,
    /// Goal joints of the last command (IK seed), radians.
    goal_rad: Mutex<Option<So101Joints>>,
    /// The newest command's joints and the limiter that ramps the written goal toward them.
    ramp: Mutex<Ramp>,
    cycles: AtomicU64,
    goals_written: AtomicU64,
    failed_cycles: AtomicU64,
    unreachable: AtomicU64,
    clock: ClockFn,
}

/// The SO-101 bridge: [`So101Link`] driven by the hardware-bridge runtime. Create with
/// [`So101Bridge::start`].
pub type So101Bridge = ThreadedBridge<So101Link>;

fn bus_error(e: &BusError) -> BridgeError {
    match e {
        BusError::Open { port, message } => BridgeError::Connect {
            target: port.clone(),
            message: message.clone(),
        },
        other => BridgeError::Protocol(other.to_string()),
    }
}

impl ThreadedBridge<So101Link> {
    /// Loads the calibration, opens the bus, checks every servo answers, configures them, sets each goal to
    /// the present position (so enabling torque does not move the arm) and starts the control cycle.
    pub fn start(config: So101Config) -> Result<Arc<Self>, BridgeError> {
        Self::start_with_clock(config, phone2act_clock::monotonic_ns)
    }

    /// As [`Self::start`], stamping feedback with `clock` (the server passes its process-wide clock).
    pub fn start_with_clock(config: So101Config, clock: ClockFn) -> Result<Arc<Self>, BridgeError> {
        config.validate()?;
        let file = Calibration::load(&expand_home(&config.calibration_file))
            .map_err(|e| BridgeError::Config(e.to_string()))?;
        file.validate().map_err(|e| BridgeError::Config(e.to_string()))?;
        let calibration: [MotorCalibration; MOTORS] =
            std::array::from_fn(|i| *file.get(SO101_JOINT_NAMES[i]).expect("validated above"));
        let ids = config.ids.unwrap_or(calibration.map(|m| m.id));
        let bus = FeetechBus::open(
            &config.port,
            config.baudrate,
            Duration::from_millis(config.timeout_ms),
        )
        .map_err(|e| bus_error(&e))?;
        let link = So101Link {
            calibration,
            ids,
            joint_names: SO101_ARM_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            kinematics: So101Kinematics::new(),
            bus: Mutex::new(Some(bus)),
            status: Mutex::new(Status {
                link: Link::Up,
                cycle_error: None,
                last_error: None,
                enabled: false,
                bus_time_total: Duration::ZERO,
                alarms: [0; MOTORS],
                alarm_stop: None,
            }),
            goal_rad: Mutex::new(None),
            ramp: Mutex::new(Ramp {
                // Two bus periods of motion at most per write: a loop slower than 50 Hz keeps its full speed,
                // and a stalled write does not turn into one long jump.
                limiter: JointRateLimiter::new(config.max_velocity_rad_s.clone())
                    .map_err(|e| BridgeError::Config(format!("so101: {e}")))?
                    .with_max_step_s((2.0 / config.rate_hz).max(phone2act_core::joint_limit::MAX_STEP_S)),
                target: None,
                moving: false,
            }),
            cycles: AtomicU64::new(0),
            goals_written: AtomicU64::new(0),
            failed_cycles: AtomicU64::new(0),
            unreachable: AtomicU64::new(0),
            clock,
            config,
        };
        link.prepare()?;
        Ok(Arc::new(Self::spawn(link, clock)?))
    }

    pub fn config(&self) -> &So101Config {
        &self.link().config
    }

    pub fn stats(&self) -> So101Stats {
        let inner = self.link();
        let s = inner.status.lock();
        let cycles = inner.cycles.load(Ordering::Relaxed);
        So101Stats {
            warning: inner.warning_of(&s),
            alarms: s.alarms,
            cycles,
            goals_written: inner.goals_written.load(Ordering::Relaxed),
            failed_cycles: inner.failed_cycles.load(Ordering::Relaxed),
            targets_superseded: self.context().targets_superseded(),
            unreachable_targets: inner.unreachable.load(Ordering::Relaxed),
            last_error: s.last_error.clone(),
            mean_cycle_work_us: if cycles == 0 {
                0.0
            } else {
                s.bus_time_total.as_secs_f64() * 1e6 / cycles as f64
            },
            bus: inner
                .bus
                .lock()
                .as_ref()
                .map(FeetechBus::stats)
                .unwrap_or_default(),
        }
    }
}

impl So101Link {
    fn with_bus<R>(&self, f: impl FnOnce(&mut FeetechBus) -> Result<R, BusError>) -> Result<R, BusError> {
        let mut guard = self.bus.lock();
        let bus = guard.as_mut().ok_or_else(|| {
            BusError::Io(std::io::Error::new(
                std::io::ErrorKind::NotConnected,
                "serial port closed",
            ))
        })?;
        f(bus)
    }

    /// Start-up sequence on an open bus. An alarm that stops the arm fails it, naming the servo; a warning is
    /// logged and shown, and the arm starts.
    fn prepare(&self) -> Result<(), BridgeError> {
        let mut alarms = [0u8; MOTORS];
        self.with_bus(|bus| {
            // Alarms are read from every answer and judged here, not by the bus.
            bus.strict_status = false;
            for (i, &id) in self.ids.iter().enumerate() {
                alarms[i] = bus.ping(id)?;
            }
            Ok(())
        })
        .map_err(|e| bus_error(&e))?;
        let stopping: [u8; MOTORS] = std::array::from_fn(|i| stopping_bits(i, alarms[i]));
        if let Some(why) = describe_alarms(self.ids, stopping) {
            return Err(BridgeError::Protocol(format!(
                "{why}: an alarm that stops the arm; remove its cause and start again"
            )));
        }
        self.update_alarms(alarms);
        self.with_bus(|bus| {
            for (i, &id) in self.ids.iter().enumerate() {
                if self.config.configure_motors {
                    configure_motor(bus, id, &self.calibration[i], i == MOTORS - 1)?;
                } else if multi_turn_feedback(bus, id)? {
                    warn!(
                        servo = id,
                        joint = SO101_JOINT_NAMES[i],
                        "so101: Phase bit 4 (multi-turn angle feedback) is set and configure_motors is off; positions are read modulo one turn"
                    );
                }
            }
            Ok(())
        })
        .map_err(|e| bus_error(&e))?;
        if self.config.enable_on_start {
            self.enable().map_err(|e| bus_error(&e))?;
        }
        Ok(())
    }

    /// Records the alarm bits of a good read: logs each change once, and latches an alarm that stops the arm.
    fn update_alarms(&self, alarms: [u8; MOTORS]) {
        let mut s = self.status.lock();
        if s.alarms == alarms {
            return;
        }
        for i in 0..MOTORS {
            let (was, now) = (s.alarms[i], alarms[i]);
            if was == now {
                continue;
            }
            let (id, joint) = (self.ids[i], SO101_JOINT_NAMES[i]);
            if now == 0 {
                info!(servo = id, joint, "so101: servo alarm cleared");
            } else if stopping_bits(i, now) != 0 {
                warn!(servo = id, joint, alarm = %status_error_text(now), "so101: servo alarm stops the arm");
            } else {
                warn!(servo = id, joint, alarm = %status_error_text(now), "so101: servo alarm; the arm keeps working");
            }
        }
        // Names every alarm that stops the arm now; once they are gone, the last ones stay named until cleared.
        let stopping: [u8; MOTORS] = std::array::from_fn(|i| stopping_bits(i, alarms[i]));
        if let Some(why) = describe_alarms(self.ids, stopping) {
            s.alarm_stop = Some(why);
        }
        s.alarms = alarms;
    }

    /// The alarms that keep the arm working, if any.
    fn warning_of(&self, s: &Status) -> Option<String> {
        let warnings: [u8; MOTORS] = std::array::from_fn(|i| s.alarms[i] & !stopping_bits(i, s.alarms[i]));
        describe_alarms(self.ids, warnings)
    }

    /// Goal = present, then torque on and lock (lerobot `enable_torque`).
    fn enable(&self) -> Result<(), BusError> {
        let (raw, _) = self.with_bus(|bus| read_positions(bus, self.ids))?;
        self.with_bus(|bus| {
            let (address, len) = register::GOAL_POSITION;
            bus.sync_write(address, len, &goal_items(&self.ids, raw))?;
            for &id in &self.ids {
                bus.write_value(id, register::TORQUE_ENABLE, 1)?;
                bus.write_value(id, register::LOCK, 1)?;
            }
            Ok(())
        })?;
        let present = self.arm_rad(&raw);
        *self.goal_rad.lock() = Some(present);
        {
            // Torque off, the arm may have been moved by hand: ramps start where it is, toward nothing.
            let mut ramp = self.ramp.lock();
            ramp.limiter.reset(&present, (self.clock)() as f64 * 1e-9);
            ramp.target = None;
            ramp.moving = false;
        }
        self.status.lock().enabled = true;
        Ok(())
    }

    fn disable(&self) -> Result<(), BusError> {
        self.status.lock().enabled = false;
        self.with_bus(|bus| {
            for &id in &self.ids {
                bus.write_value(id, register::TORQUE_ENABLE, 0)?;
                bus.write_value(id, register::LOCK, 0)?;
            }
            Ok(())
        })
    }

    fn arm_rad(&self, raw: &[u16; MOTORS]) -> So101Joints {
        std::array::from_fn(|i| self.calibration[i].raw_to_deg(raw[i]).to_radians())
    }

    /// Gripper 0 = open .. 1 = closed from a raw position.
    fn gripper_position(&self, raw: u16) -> f64 {
        let pct = self.calibration[MOTORS - 1].raw_to_percent(raw);
        let (open, closed) = (self.config.gripper_open_pct, self.config.gripper_closed_pct);
        if (closed - open).abs() < 1e-9 {
            0.0
        } else {
            ((pct - open) / (closed - open)).clamp(0.0, 1.0)
        }
    }

    fn gripper_raw(&self, target: f64) -> u16 {
        let (open, closed) = (self.config.gripper_open_pct, self.config.gripper_closed_pct);
        self.calibration[MOTORS - 1].percent_to_raw(open + (closed - open) * target.clamp(0.0, 1.0))
    }

    /// True while new goals may be written: the bus is up, the last cycle read, no alarm stops the arm
    /// and torque is on.
    fn healthy(&self) -> bool {
        let s = self.status.lock();
        !matches!(s.link, Link::Down(_)) && s.cycle_error.is_none() && s.alarm_stop.is_none() && s.enabled
    }

    /// A failed write or read: logged once per distinct failure; a failed port takes the link down.
    fn record_failure(&self, e: &BusError, bus_time: Duration) {
        self.cycles.fetch_add(1, Ordering::Relaxed);
        self.failed_cycles.fetch_add(1, Ordering::Relaxed);
        let message = e.to_string();
        let mut s = self.status.lock();
        s.bus_time_total += bus_time;
        if s.cycle_error.as_deref() != Some(message.as_str()) {
            warn!(error = %message, "so101: bus cycle failed; arm holds its last goal");
        }
        s.last_error = Some(message.clone());
        if e.is_link_failure() {
            s.link = Link::Down(message);
            drop(s);
            *self.bus.lock() = None;
        } else {
            s.cycle_error = Some(message);
        }
    }

    /// Makes `command` the target the goal ramps toward: its joint targets, or the IK of its pose.
    fn accept(&self, command: &Command) {
        let joints = if let Some(given) = command.joint_targets_rad.as_deref() {
            So101Joints::try_from(given)
                .ok()
                .filter(|joints| joints.iter().all(|q| q.is_finite()))
                .map(|joints| clamp_to_limits(&joints))
        } else {
            let seed = self.goal_rad.lock().unwrap_or([0.0; SO101_ARM_DOF]);
            let weights = IkWeights {
                orientation: self.config.ik_orientation_weight,
            };
            let solution = self
                .kinematics
                .inverse(&command.robot_from_target, &seed, weights);
            if !solution.position_reached && !solution.invalid_input {
                self.unreachable.fetch_add(1, Ordering::Relaxed);
            }
            (!solution.invalid_input).then_some(solution.joints_rad)
        };
        let Some(joints) = joints.filter(|_| command.gripper_target.is_finite()) else {
            warn!(seq = command.seq, "so101: non-finite target dropped; arm holds");
            return;
        };
        *self.goal_rad.lock() = Some(joints);
        let mut ramp = self.ramp.lock();
        ramp.target = Some((joints, command.gripper_target, command.seq));
        ramp.moving = true;
    }

    /// Writes the next goal of the ramp toward the target, if it is not there yet.
    fn write_goal(&self, ctx: &LinkContext) -> Result<(), BusError> {
        let mut ramp = self.ramp.lock();
        let Some((target, gripper_target, seq)) = ramp.target.filter(|_| ramp.moving) else {
            return Ok(());
        };
        let now_s = (self.clock)() as f64 * 1e-9;
        let before = ramp.limiter.clone();
        let step = ramp.limiter.step(&target, now_s);
        let mut raw = [0u16; MOTORS];
        for (i, q) in step.joints_rad.iter().enumerate() {
            raw[i] = self.calibration[i].deg_to_raw(q.to_degrees());
        }
        raw[MOTORS - 1] = self.gripper_raw(gripper_target);
        let (address, len) = register::GOAL_POSITION;
        let items = goal_items(&self.ids, raw);
        if let Err(e) = self.with_bus(|bus| bus.sync_write(address, len, &items)) {
            // Not written: the next cycle ramps from the goal the servos still hold.
            ramp.limiter = before;
            return Err(e);
        }
        ramp.moving = step.limited;
        self.goals_written.fetch_add(1, Ordering::Relaxed);
        ctx.applied(seq);
        Ok(())
    }

    fn health_of(&self, ctx: &LinkContext) -> Health {
        let s = self.status.lock();
        if let Link::Down(why) = &s.link {
            return Health::Disconnected(why.clone());
        }
        if let Some(e) = &s.cycle_error {
            return Health::Error(e.clone());
        }
        if let Some(why) = &s.alarm_stop {
            return Health::Error(format!(
                "{why}: the arm holds; clear the error once the servo no longer reports it"
            ));
        }
        if !s.enabled {
            return Health::Error("torque disabled".into());
        }
        if !ctx.has_feedback() {
            return Health::Connecting;
        }
        Health::Ready
    }

    fn reconnect(&self) -> Result<(), BusError> {
        *self.bus.lock() = None;
        let bus = FeetechBus::open(
            &self.config.port,
            self.config.baudrate,
            Duration::from_millis(self.config.timeout_ms),
        )?;
        *self.bus.lock() = Some(bus);
        self.with_bus(|bus| {
            bus.strict_status = false;
            Ok(())
        })?;
        {
            let mut s = self.status.lock();
            s.link = Link::Up;
            s.cycle_error = None;
        }
        let was_enabled = self.status.lock().enabled;
        self.with_bus(|bus| {
            for &id in &self.ids {
                bus.ping(id)?;
            }
            Ok(())
        })?;
        if was_enabled || self.config.enable_on_start {
            self.enable()
        } else {
            Ok(())
        }
    }

    /// Shutdown: no more goals; the servos keep their last goal with torque on, so the arm holds.
    fn close_bus(&self) {
        self.status.lock().link = Link::Down("bridge shut down".into());
        *self.bus.lock() = None;
    }
}

/// `~/...` relative to `$HOME`, as lerobot's default calibration paths are written.
pub fn expand_home(path: &std::path::Path) -> PathBuf {
    match (path.strip_prefix("~"), std::env::var_os("HOME")) {
        (Ok(rest), Some(home)) => PathBuf::from(home).join(rest),
        _ => path.to_path_buf(),
    }
}

/// Present positions (single-turn, 0..4095) and each servo's alarm bits.
fn read_positions(
    bus: &mut FeetechBus,
    ids: [u8; MOTORS],
) -> Result<([u16; MOTORS], [u8; MOTORS]), BusError> {
    let (address, len) = register::PRESENT_POSITION;
    let replies = bus.sync_read_with_status(address, len, &ids)?;
    let mut raw = [0u16; MOTORS];
    let mut alarms = [0u8; MOTORS];
    for ((r, a), reply) in raw.iter_mut().zip(alarms.iter_mut()).zip(&replies) {
        *r = single_turn_position(u16::from_le_bytes([reply.data[0], reply.data[1]]));
        *a = reply.error;
    }
    Ok((raw, alarms))
}

/// lerobot `configure()` for one motor plus its calibration (torque off while EPROM is written).
fn configure_motor(
    bus: &mut FeetechBus,
    id: u8,
    cal: &MotorCalibration,
    gripper: bool,
) -> Result<(), BusError> {
    bus.write_value(id, register::TORQUE_ENABLE, 0)?;
    bus.write_value(id, register::LOCK, 0)?;
    bus.write_value(id, register::RETURN_DELAY_TIME, 0)?;
    bus.write_value(id, register::MAXIMUM_ACCELERATION, 254)?;
    bus.write_value(id, register::ACCELERATION, 254)?;
    bus.write_value(id, register::OPERATING_MODE, 0)?;
    bus.write_value(id, register::P_COEFFICIENT, 16)?;
    bus.write_value(id, register::I_COEFFICIENT, 0)?;
    bus.write_value(id, register::D_COEFFICIENT, 32)?;
    calibration::clear_multi_turn_feedback(bus, id)?;
    if gripper {
        bus.write_value(id, register::MAX_TORQUE_LIMIT, 500)?;
        bus.write_value(id, register::PROTECTION_CURRENT, 250)?;
        bus.write_value(id, register::OVERLOAD_TORQUE, 25)?;
    }
    let offset = encode_sign_magnitude(
        cal.homing_offset,
        crate::feetech::protocol::HOMING_OFFSET_SIGN_BIT,
    );
    bus.write_value(id, register::HOMING_OFFSET, offset)?;
    bus.write_value(id, register::MIN_POSITION_LIMIT, cal.range_min)?;
    bus.write_value(id, register::MAX_POSITION_LIMIT, cal.range_max)?;
    Ok(())
}

impl RobotLink for So101Link {
    fn kind(&self) -> &'static str {
        "so101"
    }

    fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    fn schedule(&self) -> Schedule {
        Schedule::Cycle {
            period: Duration::from_secs_f64(1.0 / self.config.rate_hz),
        }
    }

    fn health(&self, ctx: &LinkContext) -> Health {
        self.health_of(ctx)
    }

    fn warning(&self) -> Option<String> {
        let s = self.status.lock();
        self.warning_of(&s)
    }

    fn accepts_targets(&self, _ctx: &LinkContext) -> bool {
        self.healthy()
    }

    /// Makes `command` the target, then writes the next goal of the ramp toward it.
    fn write_command(&self, ctx: &LinkContext, command: Option<&Command>) -> bool {
        if matches!(self.status.lock().link, Link::Down(_)) {
            return false;
        }
        if !self.healthy() {
            // No goals while faulted; still read, so a recovered bus or a cleared alarm is seen.
            return true;
        }
        let started = Instant::now();
        if let Some(command) = command {
            self.accept(command);
        }
        match self.write_goal(ctx) {
            Ok(()) => {
                self.status.lock().bus_time_total += started.elapsed();
                true
            }
            Err(e) => {
                self.record_failure(&e, started.elapsed());
                false
            }
        }
    }

    /// Reads present positions and alarms, and computes the tool pose.
    fn read_feedback(&self, _ctx: &LinkContext) -> Option<Measured> {
        let started = Instant::now();
        match self.with_bus(|bus| read_positions(bus, self.ids)) {
            Ok((raw, alarms)) => {
                self.cycles.fetch_add(1, Ordering::Relaxed);
                self.update_alarms(alarms);
                let joints = self.arm_rad(&raw);
                let mut s = self.status.lock();
                s.bus_time_total += started.elapsed();
                if s.cycle_error.take().is_some() {
                    info!("so101: bus answering again");
                }
                drop(s);
                Some(Measured {
                    joint_positions_rad: joints.to_vec(),
                    robot_from_ee: self.kinematics.forward(&joints),
                    gripper_position: self.gripper_position(raw[MOTORS - 1]),
                })
            }
            Err(e) => {
                self.record_failure(&e, started.elapsed());
                None
            }
        }
    }

    fn control(&self, _ctx: &LinkContext, request: Control) -> Result<(), BridgeError> {
        let result = match request {
            Control::Enable => self.enable(),
            Control::Disable => self.disable(),
            Control::ClearError => {
                let mut s = self.status.lock();
                s.cycle_error = None;
                // Raised again by the next read if the servo still reports it.
                s.alarm_stop = None;
                s.alarms = [0; MOTORS];
                Ok(())
            }
            Control::Reconnect => self.reconnect(),
        };
        result.map_err(|e| {
            let err = bus_error(&e);
            if e.is_link_failure() {
                self.status.lock().link = Link::Down(e.to_string());
            }
            err
        })
    }

    fn close(&self) {
        self.close_bus();
    }
}

/// A `SYNC_WRITE` of `Goal_Position`: each servo's raw goal in the register's sign-magnitude encoding.
fn goal_items(ids: &[u8], raw: impl IntoIterator<Item = u16>) -> Vec<(u8, Vec<u8>)> {
    ids.iter()
        .zip(raw)
        .map(|(&id, r)| {
            let value = encode_sign_magnitude(i32::from(r), POSITION_SIGN_BIT);
            (id, value.to_le_bytes().to_vec())
        })
        .collect()
}
