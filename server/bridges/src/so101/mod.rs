//! LeRobot SO-101 bridge over a Feetech STS3215 bus.
//!
//! One thread runs a fixed-rate cycle (100 Hz by default): take the newest target, solve the inverse
//! kinematics seeded with the previous goal (position first, orientation weighted), sync-write the six goal
//! positions, sync-read the six present positions and publish forward kinematics as [`Feedback`]. Joint angles
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
use crate::sim::ClockFn;
use crate::{Bridge, BridgeError, Command, Control, Feedback, FeedbackCell, Health, LatestSlot};
use calibration::{Calibration, MotorCalibration, multi_turn_feedback};
use parking_lot::Mutex;
use phone2act_core::kinematics::{
    IkWeights, SO101_ARM_DOF, SO101_ARM_JOINT_NAMES, SO101_JOINT_NAMES, So101Joints, So101Kinematics,
};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
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

#[derive(Debug)]
struct Inner {
    config: So101Config,
    calibration: [MotorCalibration; MOTORS],
    ids: [u8; MOTORS],
    joint_names: Vec<String>,
    kinematics: So101Kinematics,
    bus: Mutex<Option<FeetechBus>>,
    slot: LatestSlot<Command>,
    feedback: FeedbackCell,
    status: Mutex<Status>,
    /// Goal joints of the last command (IK seed), radians.
    goal_rad: Mutex<Option<So101Joints>>,
    applied_seq: AtomicU64,
    stop: AtomicBool,
    thread: Mutex<Option<JoinHandle<()>>>,
    cycles: AtomicU64,
    goals_written: AtomicU64,
    failed_cycles: AtomicU64,
    unreachable: AtomicU64,
    clock: ClockFn,
}

/// The SO-101 bridge. Create with [`So101Bridge::start`].
#[derive(Debug)]
pub struct So101Bridge {
    inner: Arc<Inner>,
}

fn bus_error(e: &BusError) -> BridgeError {
    match e {
        BusError::Open { port, message } => BridgeError::Connect {
            target: port.clone(),
            message: message.clone(),
        },
        other => BridgeError::Protocol(other.to_string()),
    }
}

impl So101Bridge {
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
        let inner = Arc::new(Inner {
            calibration,
            ids,
            joint_names: SO101_ARM_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            kinematics: So101Kinematics::new(),
            bus: Mutex::new(Some(bus)),
            slot: LatestSlot::default(),
            feedback: FeedbackCell::default(),
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
            applied_seq: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            thread: Mutex::new(None),
            cycles: AtomicU64::new(0),
            goals_written: AtomicU64::new(0),
            failed_cycles: AtomicU64::new(0),
            unreachable: AtomicU64::new(0),
            clock,
            config,
        });
        inner.prepare()?;
        let worker = Arc::clone(&inner);
        let handle = std::thread::Builder::new()
            .name("so101-cycle".into())
            .spawn(move || worker.run())
            .map_err(BridgeError::Io)?;
        *inner.thread.lock() = Some(handle);
        Ok(Arc::new(Self { inner }))
    }

    pub fn config(&self) -> &So101Config {
        &self.inner.config
    }

    pub fn stats(&self) -> So101Stats {
        let s = self.inner.status.lock();
        let cycles = self.inner.cycles.load(Ordering::Relaxed);
        So101Stats {
            warning: self.inner.warning_of(&s),
            alarms: s.alarms,
            cycles,
            goals_written: self.inner.goals_written.load(Ordering::Relaxed),
            failed_cycles: self.inner.failed_cycles.load(Ordering::Relaxed),
            targets_superseded: self.inner.slot.superseded(),
            unreachable_targets: self.inner.unreachable.load(Ordering::Relaxed),
            last_error: s.last_error.clone(),
            mean_cycle_work_us: if cycles == 0 {
                0.0
            } else {
                s.bus_time_total.as_secs_f64() * 1e6 / cycles as f64
            },
            bus: self
                .inner
                .bus
                .lock()
                .as_ref()
                .map(FeetechBus::stats)
                .unwrap_or_default(),
        }
    }
}

impl Drop for So101Bridge {
    fn drop(&mut self) {
        self.inner.shutdown();
    }
}

impl Inner {
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
            let items: Vec<(u8, Vec<u8>)> = self
                .ids
                .iter()
                .zip(raw)
                .map(|(&id, r)| {
                    (
                        id,
                        encode_sign_magnitude(i32::from(r), POSITION_SIGN_BIT)
                            .to_le_bytes()
                            .to_vec(),
                    )
                })
                .collect();
            bus.sync_write(address, len, &items)?;
            for &id in &self.ids {
                bus.write_value(id, register::TORQUE_ENABLE, 1)?;
                bus.write_value(id, register::LOCK, 1)?;
            }
            Ok(())
        })?;
        *self.goal_rad.lock() = Some(self.arm_rad(&raw));
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

    fn run(self: Arc<Self>) {
        let period = Duration::from_secs_f64(1.0 / self.config.rate_hz);
        let mut next = Instant::now();
        while !self.stop.load(Ordering::SeqCst) {
            self.cycle();
            next += period;
            let now = Instant::now();
            match next.checked_duration_since(now) {
                Some(rest) => std::thread::sleep(rest),
                // A late wake-up is made up by the next cycles; a long stall (more than a period) is not, so
                // the bus never sees a burst.
                None if now.duration_since(next) > period => next = now,
                None => {}
            }
        }
    }

    /// One control cycle: write the newest goal (if healthy), read positions, publish feedback.
    fn cycle(&self) {
        if matches!(self.status.lock().link, Link::Down(_)) {
            // Keep the newest target from piling up as "superseded" while down; it will not be sent.
            let _ = self.slot.take();
            return;
        }
        let started = Instant::now();
        let healthy = {
            let s = self.status.lock();
            s.cycle_error.is_none() && s.alarm_stop.is_none() && s.enabled
        };
        let mut result = Ok(());
        let command = self.slot.take();
        if let Some(command) = command.as_ref().filter(|_| healthy) {
            result = self.write_goal(command);
        }
        let read = result.and_then(|()| self.with_bus(|bus| read_positions(bus, self.ids)));
        let bus_time = started.elapsed();
        self.cycles.fetch_add(1, Ordering::Relaxed);
        match read {
            Ok((raw, alarms)) => {
                self.update_alarms(alarms);
                let joints = self.arm_rad(&raw);
                let feedback = Feedback {
                    capture_time_ns: (self.clock)(),
                    joint_positions_rad: joints.to_vec(),
                    robot_from_ee: self.kinematics.forward(&joints),
                    gripper_position: self.gripper_position(raw[MOTORS - 1]),
                    applied_seq: self.applied_seq.load(Ordering::SeqCst),
                    task_success: false,
                };
                *self.feedback.lock() = Some(feedback);
                let mut s = self.status.lock();
                s.bus_time_total += bus_time;
                if s.cycle_error.take().is_some() {
                    info!("so101: bus answering again");
                }
            }
            Err(e) => {
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
        }
    }

    fn write_goal(&self, command: &Command) -> Result<(), BusError> {
        let seed = self.goal_rad.lock().unwrap_or([0.0; SO101_ARM_DOF]);
        let weights = IkWeights {
            orientation: self.config.ik_orientation_weight,
        };
        let solution = self
            .kinematics
            .inverse(&command.robot_from_target, &seed, weights);
        if solution.invalid_input || !command.gripper_target.is_finite() {
            warn!(seq = command.seq, "so101: non-finite target dropped; arm holds");
            return Ok(());
        }
        if !solution.position_reached {
            self.unreachable.fetch_add(1, Ordering::Relaxed);
        }
        let mut raw = [0u16; MOTORS];
        for (i, q) in solution.joints_rad.iter().enumerate() {
            raw[i] = self.calibration[i].deg_to_raw(q.to_degrees());
        }
        raw[MOTORS - 1] = self.gripper_raw(command.gripper_target);
        let (address, len) = register::GOAL_POSITION;
        let items: Vec<(u8, Vec<u8>)> = self
            .ids
            .iter()
            .zip(raw)
            .map(|(&id, r)| {
                (
                    id,
                    encode_sign_magnitude(i32::from(r), POSITION_SIGN_BIT)
                        .to_le_bytes()
                        .to_vec(),
                )
            })
            .collect();
        self.with_bus(|bus| bus.sync_write(address, len, &items))?;
        *self.goal_rad.lock() = Some(solution.joints_rad);
        self.goals_written.fetch_add(1, Ordering::Relaxed);
        self.applied_seq.store(command.seq, Ordering::SeqCst);
        Ok(())
    }

    fn health(&self) -> Health {
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
        if self.feedback.lock().is_none() {
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

    fn shutdown(&self) {
        if self.stop.swap(true, Ordering::SeqCst) {
            return;
        }
        let handle = self.thread.lock().take();
        if let Some(h) = handle
            && h.thread().id() != std::thread::current().id()
        {
            let _ = h.join();
        }
        // The servos keep their last goal with torque on: the arm holds.
        *self.bus.lock() = None;
        self.status.lock().link = Link::Down("bridge shut down".into());
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

impl Bridge for So101Bridge {
    fn kind(&self) -> &'static str {
        "so101"
    }

    fn joint_names(&self) -> &[String] {
        &self.inner.joint_names
    }

    fn send(&self, command: Command) {
        self.inner.slot.put(command);
    }

    fn feedback(&self) -> Option<Feedback> {
        self.inner.feedback.lock().clone()
    }

    fn health(&self) -> Health {
        self.inner.health()
    }

    fn warning(&self) -> Option<String> {
        let s = self.inner.status.lock();
        self.inner.warning_of(&s)
    }

    fn control(&self, request: Control) -> Result<(), BridgeError> {
        if self.inner.stop.load(Ordering::SeqCst) {
            return Err(BridgeError::Protocol("bridge is shut down".into()));
        }
        let result = match request {
            Control::Enable => self.inner.enable(),
            Control::Disable => self.inner.disable(),
            Control::ClearError => {
                let mut s = self.inner.status.lock();
                s.cycle_error = None;
                // Raised again by the next read if the servo still reports it.
                s.alarm_stop = None;
                s.alarms = [0; MOTORS];
                Ok(())
            }
            Control::Reconnect => self.inner.reconnect(),
        };
        result.map_err(|e| {
            let err = bus_error(&e);
            if e.is_link_failure() {
                self.inner.status.lock().link = Link::Down(e.to_string());
            }
            err
        })
    }

    fn shutdown(&self) {
        self.inner.shutdown();
    }
}
