//! A bus of emulated STS3215 servos on a pseudo-terminal: open [`FeetechEmulator::port_path`] with any serial
//! library and it answers PING, READ, WRITE, SYNC_READ and SYNC_WRITE as the servos do.
//!
//! Each servo has the STS3215 register map with its factory values. `Present_Position = actual − Homing_Offset`
//! (sign-magnitude, bit 11), goals are clamped to the position limits, and with torque on the shaft moves toward
//! the goal at a fixed speed. EPROM writes are ignored while `Lock` is 1, as on the real servo. Faults can be
//! injected per servo: silence, a corrupt checksum, an error byte, a latched alarm, the multi-turn feedback bit.
//!
//! What the real servo does and where that is written down:
//! - factory values: firmware 3.10 and model 777 (see [`protocol::STS3215_FIRMWARE`],
//!   [`protocol::STS3215_MODEL`]); position limits 0 and 4095, `Max_Temperature_Limit` 70 °C, status level 1,
//!   baud code 0 (Feetech STS memory table §2.2, "Initial Value" column, wiki.aifitlab.com "Feetech STS Servo
//!   – Memory Table Analysis"); `Return_Delay_Time` 250 (= 500 µs, lerobot `FeetechMotorsBus.configure_motors`
//!   comment).
//! - `Phase` bit 4 ([`protocol::PHASE_MULTI_TURN_FEEDBACK`]): with it set, `Present_Position` keeps counting
//!   past the seam instead of wrapping to 0..4095 (memory table §3.1; lerobot PR #3373 shows readings out of
//!   0..4095 on such servos). The count starts from the single-turn angle at power-on.
//! - alarms ([`protocol::alarm`]): a servo keeps answering with the alarm bits in every status packet's error
//!   byte and in its `Status` register (65) for as long as the condition holds (memory table §3.2; the
//!   Feetech SDK returns the byte with every reply). The emulator holds an injected alarm until it is cleared,
//!   as a gripper squeezing an object holds overload and a 7.4 V servo on 12 V holds over-voltage.
//! - broadcast PING: every servo answers, one status packet each, back to back. lerobot's reader
//!   (`FeetechMotorsBus._broadcast_ping`) collects every byte until its timeout of `3 ms × 252 + 16 ms` plus
//!   the transfer time, then parses the packets in a row, so every answer must arrive within that window and
//!   none may overlap another. The emulator sends them in ascending id order; Feetech documents no order, and
//!   lerobot's reader accepts any.
//! - writing `ID` (5, with `Lock` 0): the servo acknowledges under its old id, then answers to the new one.
//!   feetech-servo-sdk 1.0.0 (`protocol_packet_handler.txRxPacket`) accepts only a status packet whose id is the
//!   instruction's, and lerobot's `setup_motor` writes the id to the old one, requires that acknowledgement,
//!   then writes the baud rate to the new id.

use super::protocol::{
    self, BROADCAST_ID, Decoded, STS3215_FIRMWARE, STS3215_MODEL, decode_sign_magnitude,
    encode_sign_magnitude, instruction, register, status_packet,
};
use nix::fcntl::{FcntlArg, OFlag, fcntl};
use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
use nix::pty::openpty;
use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
use parking_lot::Mutex;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{ErrorKind, Read, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

const MEMORY: usize = 128;

/// SO-101 ranges centred on raw 2047 (homing done), about ±88° for the body joints, the wrist roll over the
/// full turn and the gripper over its travel: the calibration the emulator's SO-101 tests and benchmarks use
/// (`Calibration::so101_with_ranges`).
pub const SO101_CENTRED_RANGES: [(u16, u16); 6] = [
    (1000, 3094),
    (1050, 3044),
    (1080, 3014),
    (1000, 3094),
    (0, 4095),
    (2000, 3400),
];

/// One emulated servo.
#[derive(Clone, Debug)]
pub struct ServoState {
    pub id: u8,
    memory: [u8; MEMORY],
    /// Shaft position in raw encoder counts (before the homing offset), fractional for smooth motion.
    actual: f64,
    /// Counts per second with torque on.
    pub speed_counts_s: f64,
    pub mute: bool,
    pub corrupt_checksums: bool,
    pub error_byte: u8,
    /// Alarm bits the servo holds ([`protocol::alarm`]): in every status packet and the `Status` register.
    alarm: u8,
    pub reply_delay: Duration,
}

impl ServoState {
    fn new(id: u8, actual: u16) -> Self {
        let mut memory = [0u8; MEMORY];
        let mut set = |entry: (u8, u8), value: u16| {
            let a = usize::from(entry.0);
            memory[a..a + usize::from(entry.1)].copy_from_slice(&protocol::value_bytes(value, entry.1));
        };
        set(register::FIRMWARE_MAJOR_VERSION, u16::from(STS3215_FIRMWARE.0));
        set(register::FIRMWARE_MINOR_VERSION, u16::from(STS3215_FIRMWARE.1));
        set(register::MODEL_NUMBER, STS3215_MODEL);
        set(register::ID, u16::from(id));
        set(register::BAUD_RATE, 0);
        set(register::RESPONSE_STATUS_LEVEL, 1);
        set(register::RETURN_DELAY_TIME, 250);
        set(register::MIN_POSITION_LIMIT, 0);
        set(register::MAX_POSITION_LIMIT, 4095);
        set(register::MAX_TEMPERATURE_LIMIT, 70);
        set(register::MAX_TORQUE_LIMIT, 1000);
        set(register::P_COEFFICIENT, 32);
        set(register::LOCK, 1);
        set(register::PRESENT_VOLTAGE, 120);
        set(register::PRESENT_TEMPERATURE, 30);
        let mut s = Self {
            id,
            memory,
            actual: f64::from(actual),
            speed_counts_s: 4000.0,
            mute: false,
            corrupt_checksums: false,
            error_byte: 0,
            alarm: 0,
            reply_delay: Duration::ZERO,
        };
        let goal = s.present_from_actual();
        s.set(
            register::GOAL_POSITION,
            encode_sign_magnitude(goal, protocol::POSITION_SIGN_BIT),
        );
        s.refresh_present();
        s
    }

    fn get(&self, entry: (u8, u8)) -> u16 {
        let a = usize::from(entry.0);
        protocol::bytes_value(&self.memory[a..a + usize::from(entry.1)])
    }

    fn set(&mut self, entry: (u8, u8), value: u16) {
        let a = usize::from(entry.0);
        self.memory[a..a + usize::from(entry.1)].copy_from_slice(&protocol::value_bytes(value, entry.1));
    }

    fn homing_offset(&self) -> i32 {
        decode_sign_magnitude(
            self.get(register::HOMING_OFFSET),
            protocol::HOMING_OFFSET_SIGN_BIT,
        )
    }

    fn present_from_actual(&self) -> i32 {
        let present = self.actual.round() as i32 - self.homing_offset();
        if self.get(register::PHASE) as u8 & protocol::PHASE_MULTI_TURN_FEEDBACK != 0 {
            // The full angle, as far as the 15-bit magnitude reaches.
            present.clamp(-0x7FFF, 0x7FFF)
        } else {
            present.rem_euclid(4096)
        }
    }

    fn refresh_present(&mut self) {
        let present = self.present_from_actual();
        self.set(
            register::PRESENT_POSITION,
            encode_sign_magnitude(present, protocol::POSITION_SIGN_BIT),
        );
    }

    /// Moves the shaft toward the goal for `dt` seconds if torque is on.
    fn step(&mut self, dt: f64) {
        if self.get(register::TORQUE_ENABLE) == 1 {
            let min = i32::from(self.get(register::MIN_POSITION_LIMIT));
            let max = i32::from(self.get(register::MAX_POSITION_LIMIT));
            let goal = decode_sign_magnitude(self.get(register::GOAL_POSITION), protocol::POSITION_SIGN_BIT);
            let goal = if min < max { goal.clamp(min, max) } else { goal };
            let goal_actual = f64::from(goal + self.homing_offset());
            let delta = goal_actual - self.actual;
            let max_step = self.speed_counts_s * dt;
            self.actual += delta.clamp(-max_step, max_step);
            self.set(register::MOVING, u16::from(delta.abs() > 0.5));
        }
        self.refresh_present();
    }

    fn write(&mut self, address: u8, data: &[u8]) {
        let locked = self.get(register::LOCK) == 1;
        for (i, b) in data.iter().enumerate() {
            let a = usize::from(address) + i;
            if a >= MEMORY {
                break;
            }
            // Read-only status registers are not writable; EPROM only with the lock off.
            let is_present = (56..=70).contains(&a);
            let is_eprom = a < usize::from(register::FIRST_SRAM);
            if is_present || (is_eprom && locked) || a < 5 {
                continue;
            }
            self.memory[a] = *b;
        }
        self.refresh_present();
    }

    /// The error byte of this servo's status packets.
    fn status_error(&self) -> u8 {
        self.error_byte | self.alarm
    }

    /// Latches alarm bits ([`protocol::alarm`]) until [`Self::clear_alarm`].
    pub fn latch_alarm(&mut self, bits: u8) {
        self.alarm |= bits;
        self.set(register::STATUS, u16::from(self.alarm));
    }

    /// The condition is gone (the gripper let go, the supply is right): the servo reports no alarm.
    pub fn clear_alarm(&mut self) {
        self.alarm = 0;
        self.set(register::STATUS, 0);
    }

    /// Sets a register as the factory left it, whatever `Lock` says (e.g. `Phase` bit 4 on some servos).
    pub fn set_factory_register(&mut self, entry: (u8, u8), value: u16) {
        self.set(entry, value);
        self.refresh_present();
    }

    fn read(&self, address: u8, len: u8) -> Vec<u8> {
        let a = usize::from(address);
        let end = (a + usize::from(len)).min(MEMORY);
        if a >= end {
            Vec::new()
        } else {
            self.memory[a..end].to_vec()
        }
    }

    /// `Present_Position` as the bus reports it.
    pub fn present_position(&self) -> i32 {
        decode_sign_magnitude(self.get(register::PRESENT_POSITION), protocol::POSITION_SIGN_BIT)
    }

    /// `Goal_Position` as last written.
    pub fn goal_position(&self) -> i32 {
        decode_sign_magnitude(self.get(register::GOAL_POSITION), protocol::POSITION_SIGN_BIT)
    }

    pub fn torque_enabled(&self) -> bool {
        self.get(register::TORQUE_ENABLE) == 1
    }

    pub fn locked(&self) -> bool {
        self.get(register::LOCK) == 1
    }

    pub fn homing_offset_value(&self) -> i32 {
        self.homing_offset()
    }

    pub fn position_limits(&self) -> (u16, u16) {
        (
            self.get(register::MIN_POSITION_LIMIT),
            self.get(register::MAX_POSITION_LIMIT),
        )
    }

    /// A register value (for tests).
    pub fn register(&self, entry: (u8, u8)) -> u16 {
        self.get(entry)
    }
}

#[derive(Debug)]
struct BusState {
    servos: BTreeMap<u8, ServoState>,
    last_step: Instant,
    packets: u64,
}

impl BusState {
    fn advance(&mut self) {
        let now = Instant::now();
        let dt = now.saturating_duration_since(self.last_step).as_secs_f64();
        self.last_step = now;
        for s in self.servos.values_mut() {
            s.step(dt);
        }
    }
}

/// The running emulator. Dropping it stops the thread and closes the pseudo-terminal.
#[derive(Debug)]
pub struct FeetechEmulator {
    state: Arc<Mutex<BusState>>,
    stop: Arc<AtomicBool>,
    path: PathBuf,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl FeetechEmulator {
    /// Starts a bus with servos `(id, initial raw shaft position)`.
    pub fn start(servos: &[(u8, u16)]) -> std::io::Result<Self> {
        let pty = openpty(None, None).map_err(std::io::Error::from)?;
        // Raw mode on the servo side too, so no byte is translated or echoed before the client sets its own.
        let mut termios = tcgetattr(&pty.slave).map_err(std::io::Error::from)?;
        cfmakeraw(&mut termios);
        tcsetattr(&pty.slave, SetArg::TCSANOW, &termios).map_err(std::io::Error::from)?;
        let path = nix::unistd::ttyname(&pty.slave).map_err(std::io::Error::from)?;
        let flags = fcntl(&pty.master, FcntlArg::F_GETFL).map_err(std::io::Error::from)?;
        fcntl(
            &pty.master,
            FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
        )
        .map_err(std::io::Error::from)?;
        let state = Arc::new(Mutex::new(BusState {
            servos: servos
                .iter()
                .map(|&(id, pos)| (id, ServoState::new(id, pos)))
                .collect(),
            last_step: Instant::now(),
            packets: 0,
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let state = Arc::clone(&state);
            let stop = Arc::clone(&stop);
            let master = pty.master;
            // The servo side stays open in the emulator so the master never sees a hang-up between clients.
            let slave = pty.slave;
            std::thread::Builder::new()
                .name("feetech-emu".into())
                .spawn(move || serve(&state, &stop, master, slave))?
        };
        Ok(Self {
            state,
            stop,
            path,
            thread: Mutex::new(Some(thread)),
        })
    }

    /// The device path to open (`/dev/pts/N`).
    pub fn port_path(&self) -> &std::path::Path {
        &self.path
    }

    /// A copy of one servo's state, advanced to now.
    pub fn servo(&self, id: u8) -> Option<ServoState> {
        let mut s = self.state.lock();
        s.advance();
        s.servos.get(&id).cloned()
    }

    /// Packets handled so far.
    pub fn packets(&self) -> u64 {
        self.state.lock().packets
    }

    /// Changes one servo (fault injection, moving the shaft by hand, speed).
    pub fn with_servo<R>(&self, id: u8, f: impl FnOnce(&mut ServoState) -> R) -> Option<R> {
        let mut s = self.state.lock();
        s.advance();
        s.servos.get_mut(&id).map(f)
    }

    /// Latches alarm bits on one servo ([`ServoState::latch_alarm`]).
    pub fn latch_alarm(&self, id: u8, bits: u8) {
        self.with_servo(id, |s| s.latch_alarm(bits));
    }

    /// Clears one servo's alarms.
    pub fn clear_alarm(&self, id: u8) {
        self.with_servo(id, ServoState::clear_alarm);
    }

    /// The ids on the bus, ascending.
    pub fn ids(&self) -> Vec<u8> {
        self.state.lock().servos.keys().copied().collect()
    }

    /// Moves a shaft as a hand would (works with torque off).
    pub fn set_actual_position(&self, id: u8, raw: f64) {
        self.with_servo(id, |s| {
            s.actual = raw;
            s.refresh_present();
        });
    }

    /// Stops the emulator. Idempotent.
    pub fn shutdown(&self) {
        self.stop.store(true, Ordering::SeqCst);
        let thread = self.thread.lock().take();
        if let Some(t) = thread {
            let _ = t.join();
        }
    }
}

impl Drop for FeetechEmulator {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn serve(state: &Mutex<BusState>, stop: &AtomicBool, master: OwnedFd, _slave: OwnedFd) {
    let mut file = File::from(master);
    let mut rx: Vec<u8> = Vec::with_capacity(512);
    let mut chunk = [0u8; 1024];
    while !stop.load(Ordering::SeqCst) {
        let mut fds = [PollFd::new(file.as_fd(), PollFlags::POLLIN)];
        match poll(&mut fds, PollTimeout::from(20u8)) {
            Ok(0) | Err(nix::errno::Errno::EINTR) => continue,
            Ok(_) => {}
            Err(_) => return,
        }
        match file.read(&mut chunk) {
            Ok(0) => continue,
            Ok(n) => rx.extend_from_slice(&chunk[..n]),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::Interrupted) => continue,
            // EIO while no client has the port open: wait for one.
            Err(_) => {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
        }
        loop {
            match protocol::decode(&rx) {
                Decoded::Packet(p, used) => {
                    rx.drain(..used);
                    let replies = handle(state, &p);
                    for (reply, delay) in replies {
                        if !delay.is_zero() {
                            std::thread::sleep(delay);
                        }
                        let _ = file.write_all(&reply);
                    }
                }
                // A corrupt instruction is ignored, as a servo does: the client times out.
                Decoded::Error(_, skip) => {
                    rx.drain(..skip);
                }
                Decoded::Incomplete(garbage) => {
                    rx.drain(..garbage);
                    break;
                }
            }
        }
    }
}

fn reply_for(servo: &ServoState, params: &[u8]) -> Option<(Vec<u8>, Duration)> {
    if servo.mute {
        return None;
    }
    let mut packet = status_packet(servo.id, servo.status_error(), params);
    if servo.corrupt_checksums
        && let Some(last) = packet.last_mut()
    {
        *last ^= 0x5A;
    }
    Some((packet, servo.reply_delay))
}

fn handle(state: &Mutex<BusState>, p: &protocol::Packet) -> Vec<(Vec<u8>, Duration)> {
    let mut s = state.lock();
    s.packets += 1;
    s.advance();
    let answers = |servo: &ServoState| servo.get(register::RESPONSE_STATUS_LEVEL) >= 1;
    match p.code {
        // BTreeMap order is ascending id, the order the servos answer a broadcast ping in.
        instruction::PING if p.id == BROADCAST_ID => s
            .servos
            .values()
            .filter_map(|servo| reply_for(servo, &[]))
            .collect(),
        instruction::PING => match s.servos.get(&p.id) {
            Some(servo) => reply_for(servo, &[]).into_iter().collect(),
            None => Vec::new(),
        },
        instruction::READ => match (s.servos.get(&p.id), p.params.as_slice()) {
            (Some(servo), [address, len]) => reply_for(servo, &servo.read(*address, *len))
                .into_iter()
                .collect(),
            _ => Vec::new(),
        },
        instruction::WRITE => {
            let Some((&address, data)) = p.params.split_first() else {
                return Vec::new();
            };
            if p.id == BROADCAST_ID {
                for servo in s.servos.values_mut() {
                    servo.write(address, data);
                }
                return Vec::new();
            }
            let Some(servo) = s.servos.get_mut(&p.id) else {
                return Vec::new();
            };
            servo.write(address, data);
            let reply = if answers(servo) {
                reply_for(servo, &[]).into_iter().collect()
            } else {
                Vec::new()
            };
            // Acknowledged under the old id, then the servo answers to the new one.
            let new_id = servo.get(register::ID) as u8;
            if new_id != p.id && new_id <= protocol::MAX_ID && !s.servos.contains_key(&new_id) {
                if let Some(mut moved) = s.servos.remove(&p.id) {
                    moved.id = new_id;
                    s.servos.insert(new_id, moved);
                }
            } else if new_id != p.id
                && let Some(servo) = s.servos.get_mut(&p.id)
            {
                // Two servos on one id would answer on top of each other; a servo refusing an id already on the
                // bus keeps its own (the emulator's choice: the real bus would just garble both answers).
                servo.set(register::ID, u16::from(p.id));
            }
            reply
        }
        instruction::SYNC_WRITE => {
            let [address, len, items @ ..] = p.params.as_slice() else {
                return Vec::new();
            };
            let stride = usize::from(*len) + 1;
            if *len == 0 || items.len() % stride != 0 {
                return Vec::new();
            }
            for item in items.chunks(stride) {
                if let Some(servo) = s.servos.get_mut(&item[0]) {
                    servo.write(*address, &item[1..]);
                }
            }
            Vec::new()
        }
        instruction::SYNC_READ => {
            let [address, len, ids @ ..] = p.params.as_slice() else {
                return Vec::new();
            };
            ids.iter()
                .filter_map(|id| s.servos.get(id))
                .filter_map(|servo| reply_for(servo, &servo.read(*address, *len)))
                .collect()
        }
        _ => Vec::new(),
    }
}
