//! lerobot-compatible SO-101 calibration: the JSON file (`{"shoulder_pan": {"id":1,"drive_mode":0,
//! "homing_offset":-1924,"range_min":767,"range_max":3425}, ...}`), the raw ⇄ degrees / percent mappings of
//! lerobot's `DEGREES` and `RANGE_0_100` modes, and the calibration procedure (half-turn homing, then a range
//! sweep) that writes the same values into the motors.

use crate::feetech::protocol::{
    COUNTS_PER_TURN, HOMING_OFFSET_SIGN_BIT, PHASE_MULTI_TURN_FEEDBACK, encode_sign_magnitude, register,
    single_turn_position,
};
use crate::feetech::{BusError, FeetechBus};
use phone2act_core::kinematics::SO101_JOINT_NAMES;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

/// Largest raw position (4095).
pub const MAX_RAW: u16 = COUNTS_PER_TURN - 1;
/// lerobot's half turn: homing puts the middle of the range at this raw value.
pub const HALF_TURN: i32 = 2047;
/// The joint that turns without end stops; lerobot records its range as the full turn.
pub const FULL_TURN_MOTOR: &str = "wrist_roll";

/// One motor's calibration, as lerobot stores it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct MotorCalibration {
    pub id: u8,
    pub drive_mode: u8,
    pub homing_offset: i32,
    pub range_min: u16,
    pub range_max: u16,
}

impl MotorCalibration {
    fn mid(&self) -> f64 {
        f64::midpoint(f64::from(self.range_min), f64::from(self.range_max))
    }

    fn sign(&self) -> f64 {
        if self.drive_mode == 0 { 1.0 } else { -1.0 }
    }

    /// lerobot `DEGREES`: `(raw − mid)·360/4095`, negated for drive mode 1.
    pub fn raw_to_deg(&self, raw: u16) -> f64 {
        self.sign() * (f64::from(raw) - self.mid()) * 360.0 / f64::from(MAX_RAW)
    }

    /// Inverse of [`Self::raw_to_deg`], clamped to the recorded range so the goal never leaves it.
    pub fn deg_to_raw(&self, deg: f64) -> u16 {
        let raw = self.sign() * deg * f64::from(MAX_RAW) / 360.0 + self.mid();
        raw.round()
            .clamp(f64::from(self.range_min), f64::from(self.range_max)) as u16
    }

    /// lerobot `RANGE_0_100`: 0 at `range_min`, 100 at `range_max` (reversed for drive mode 1).
    pub fn raw_to_percent(&self, raw: u16) -> f64 {
        let span = f64::from(self.range_max.saturating_sub(self.range_min)).max(1.0);
        let v = ((f64::from(raw) - f64::from(self.range_min)) / span * 100.0).clamp(0.0, 100.0);
        if self.drive_mode == 0 { v } else { 100.0 - v }
    }

    /// Inverse of [`Self::raw_to_percent`].
    pub fn percent_to_raw(&self, percent: f64) -> u16 {
        let p = percent.clamp(0.0, 100.0);
        let p = if self.drive_mode == 0 { p } else { 100.0 - p };
        let span = f64::from(self.range_max.saturating_sub(self.range_min));
        (f64::from(self.range_min) + p / 100.0 * span).round() as u16
    }
}

/// A calibration file: motor name → calibration, in SO-101 motor order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Calibration {
    pub motors: Vec<(String, MotorCalibration)>,
}

/// Calibration file and procedure errors.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error("calibration file {path}: {message}")]
    File { path: String, message: String },
    #[error("calibration of {motor}: {message}")]
    Invalid { motor: String, message: String },
    #[error("bus: {0}")]
    Bus(#[from] BusError),
}

impl Calibration {
    /// An SO-101 calibration with motor ids 1 to 6 in [`SO101_JOINT_NAMES`] order, no homing offset and no
    /// reversed drive, each motor's `(range_min, range_max)` as given: how tests and benchmarks describe
    /// servos that were homed and swept (the bus emulator's start).
    pub fn so101_with_ranges(ranges: [(u16, u16); SO101_JOINT_NAMES.len()]) -> Self {
        Calibration {
            motors: SO101_JOINT_NAMES
                .iter()
                .zip(ranges)
                .zip(1u8..)
                .map(|((name, (range_min, range_max)), id)| {
                    let motor = MotorCalibration {
                        id,
                        drive_mode: 0,
                        homing_offset: 0,
                        range_min,
                        range_max,
                    };
                    ((*name).to_owned(), motor)
                })
                .collect(),
        }
    }

    /// Parses lerobot's JSON. Motors are ordered as the SO-101's (then any others by name).
    pub fn from_json(text: &str) -> Result<Self, String> {
        let map: BTreeMap<String, MotorCalibration> =
            serde_json::from_str(text).map_err(|e| e.to_string())?;
        let mut motors: Vec<(String, MotorCalibration)> = Vec::with_capacity(map.len());
        for name in SO101_JOINT_NAMES {
            if let Some(m) = map.get(name) {
                motors.push((name.to_owned(), *m));
            }
        }
        for (name, m) in &map {
            if !SO101_JOINT_NAMES.contains(&name.as_str()) {
                motors.push((name.clone(), *m));
            }
        }
        Ok(Self { motors })
    }

    /// Reads a calibration file.
    pub fn load(path: &Path) -> Result<Self, CalibrationError> {
        let err = |message: String| CalibrationError::File {
            path: path.display().to_string(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        Self::from_json(&text).map_err(err)
    }

    /// lerobot's layout: one object per motor, four-space indent, motor order kept.
    pub fn to_json(&self) -> String {
        let mut out = String::from("{\n");
        for (i, (name, m)) in self.motors.iter().enumerate() {
            let comma = if i + 1 == self.motors.len() { "" } else { "," };
            let name = serde_json::to_string(name).unwrap_or_else(|_| "\"?\"".to_owned());
            let _ = write!(
                out,
                "    {name}: {{\n        \"id\": {},\n        \"drive_mode\": {},\n        \"homing_offset\": {},\n        \
                 \"range_min\": {},\n        \"range_max\": {}\n    }}{comma}\n",
                m.id, m.drive_mode, m.homing_offset, m.range_min, m.range_max
            );
        }
        out.push('}');
        out
    }

    /// Writes the file (through a temporary file and a rename, so a crash never leaves half a file).
    pub fn save(&self, path: &Path) -> Result<(), CalibrationError> {
        let err = |e: std::io::Error| CalibrationError::File {
            path: path.display().to_string(),
            message: e.to_string(),
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(err)?;
        }
        let tmp = path.with_extension("json.tmp");
        std::fs::write(&tmp, self.to_json()).map_err(err)?;
        std::fs::rename(&tmp, path).map_err(err)
    }

    pub fn get(&self, name: &str) -> Option<&MotorCalibration> {
        self.motors.iter().find(|(n, _)| n == name).map(|(_, m)| m)
    }

    /// Checks that every SO-101 motor is present with a usable range.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        for name in SO101_JOINT_NAMES {
            let invalid = |message: String| CalibrationError::Invalid {
                motor: name.to_owned(),
                message,
            };
            let m = self
                .get(name)
                .ok_or_else(|| invalid("missing from the calibration file".into()))?;
            if m.range_min >= m.range_max || m.range_max > MAX_RAW {
                return Err(invalid(format!(
                    "range {}..{} is empty or beyond 0..{MAX_RAW}",
                    m.range_min, m.range_max
                )));
            }
            if m.homing_offset.abs() > (1 << HOMING_OFFSET_SIGN_BIT) - 1 {
                return Err(invalid(format!("homing offset {} beyond ±2047", m.homing_offset)));
            }
            if m.drive_mode > 1 {
                return Err(invalid(format!("drive mode {} is not 0 or 1", m.drive_mode)));
            }
        }
        Ok(())
    }
}

/// True if the servo reports its full (multi-turn) angle (`Phase` bit 4).
pub fn multi_turn_feedback(bus: &mut FeetechBus, id: u8) -> Result<bool, BusError> {
    Ok(bus.read_value(id, register::PHASE)? as u8 & PHASE_MULTI_TURN_FEEDBACK != 0)
}

/// Clears `Phase` bit 4 so the servo reports single-turn angles, as lerobot's `configure_motors` does (the bit
/// is EPROM: torque off and `Lock` 0 first). Returns whether it was set. Reading before writing leaves the
/// other phase bits (drive direction, ...) as the factory set them.
pub fn clear_multi_turn_feedback(bus: &mut FeetechBus, id: u8) -> Result<bool, BusError> {
    let phase = bus.read_value(id, register::PHASE)? as u8;
    if phase & PHASE_MULTI_TURN_FEEDBACK == 0 {
        return Ok(false);
    }
    bus.write_value(id, register::PHASE, u16::from(phase & !PHASE_MULTI_TURN_FEEDBACK))?;
    tracing::info!(
        servo = id,
        "feetech: cleared Phase bit 4 (multi-turn angle feedback)"
    );
    Ok(true)
}

fn disable_torque(bus: &mut FeetechBus, id: u8) -> Result<(), BusError> {
    bus.write_value(id, register::TORQUE_ENABLE, 0)?;
    bus.write_value(id, register::LOCK, 0)
}

fn read_present(bus: &mut FeetechBus, ids: &[u8]) -> Result<Vec<u16>, BusError> {
    let (address, len) = register::PRESENT_POSITION;
    Ok(bus
        .sync_read(address, len, ids)?
        .iter()
        .map(|b| single_turn_position(u16::from_le_bytes([b[0], b[1]])))
        .collect())
}

/// Runs lerobot's calibration on `motors` (name, id) with torque off:
/// 1. `at_middle()` returns once the operator has put every joint at the middle of its range; the homing
///    offset is set so that this pose reads 2047 (half-turn homing);
/// 2. positions are sampled while `sweeping()` returns true, as the operator moves every joint through its
///    whole range; the wrist roll is given the full turn;
/// 3. homing offsets and position limits are written into the motors and returned as a [`Calibration`].
pub fn run_calibration(
    bus: &mut FeetechBus,
    motors: &[(String, u8)],
    at_middle: impl FnOnce(),
    mut sweeping: impl FnMut() -> bool,
) -> Result<Calibration, CalibrationError> {
    let ids: Vec<u8> = motors.iter().map(|(_, id)| *id).collect();
    for &id in &ids {
        disable_torque(bus, id)?;
        bus.write_value(id, register::OPERATING_MODE, 0)?;
        // A multi-turn reading past the seam would record a range beyond 0..4095.
        clear_multi_turn_feedback(bus, id)?;
    }
    at_middle();
    for &id in &ids {
        bus.write_value(id, register::HOMING_OFFSET, 0)?;
    }
    let raw = read_present(bus, &ids)?;
    let mut homing = Vec::with_capacity(ids.len());
    for (&id, &r) in ids.iter().zip(&raw) {
        let offset = i32::from(r) - HALF_TURN;
        bus.write_value(
            id,
            register::HOMING_OFFSET,
            encode_sign_magnitude(offset, HOMING_OFFSET_SIGN_BIT),
        )?;
        homing.push(offset);
    }
    let start = read_present(bus, &ids)?;
    let mut mins = start.clone();
    let mut maxs = start;
    let mut last_sample = Instant::now();
    while sweeping() {
        let now = read_present(bus, &ids)?;
        for ((lo, hi), v) in mins.iter_mut().zip(maxs.iter_mut()).zip(now) {
            *lo = (*lo).min(v);
            *hi = (*hi).max(v);
        }
        // Sampling faster than the servos move only loads the bus.
        if let Some(rest) = Duration::from_millis(10).checked_sub(last_sample.elapsed()) {
            std::thread::sleep(rest);
        }
        last_sample = Instant::now();
    }
    let mut calibration = Calibration {
        motors: Vec::with_capacity(motors.len()),
    };
    for (i, (name, id)) in motors.iter().enumerate() {
        let (range_min, range_max) = if name == FULL_TURN_MOTOR {
            (0, MAX_RAW)
        } else {
            (mins[i], maxs[i])
        };
        if range_min >= range_max {
            return Err(CalibrationError::Invalid {
                motor: name.clone(),
                message: format!("did not move during the sweep (stayed at {range_min})"),
            });
        }
        bus.write_value(*id, register::MIN_POSITION_LIMIT, range_min)?;
        bus.write_value(*id, register::MAX_POSITION_LIMIT, range_max)?;
        calibration.motors.push((
            name.clone(),
            MotorCalibration {
                id: *id,
                drive_mode: 0,
                homing_offset: homing[i],
                range_min,
                range_max,
            },
        ));
    }
    Ok(calibration)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shape of lerobot's file; shoulder_pan is Phone2Act's real entry, the others are made up.
    const PHONE2ACT_FILE: &str = r#"{
        "shoulder_pan": {"id": 1, "drive_mode": 0, "homing_offset": -1924, "range_min": 767, "range_max": 3425},
        "shoulder_lift": {"id": 2, "drive_mode": 0, "homing_offset": 1130, "range_min": 818, "range_max": 3229},
        "elbow_flex": {"id": 3, "drive_mode": 0, "homing_offset": -1342, "range_min": 868, "range_max": 3075},
        "wrist_flex": {"id": 4, "drive_mode": 0, "homing_offset": -1040, "range_min": 849, "range_max": 3224},
        "wrist_roll": {"id": 5, "drive_mode": 0, "homing_offset": -1574, "range_min": 0, "range_max": 4095},
        "gripper": {"id": 6, "drive_mode": 0, "homing_offset": 1312, "range_min": 2031, "range_max": 3483}
    }"#;

    #[test]
    fn lerobot_file_round_trips_in_motor_order() {
        let c = Calibration::from_json(PHONE2ACT_FILE).unwrap();
        c.validate().unwrap();
        let names: Vec<&str> = c.motors.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, SO101_JOINT_NAMES);
        assert_eq!(c.get("shoulder_pan").unwrap().homing_offset, -1924);
        let again = Calibration::from_json(&c.to_json()).unwrap();
        assert_eq!(again, c);
        assert!(
            c.to_json()
                .starts_with("{\n    \"shoulder_pan\": {\n        \"id\": 1,")
        );
    }

    #[test]
    fn degrees_mapping_matches_lerobot() {
        let m = MotorCalibration {
            id: 1,
            drive_mode: 0,
            homing_offset: 0,
            range_min: 767,
            range_max: 3425,
        };
        // mid = 2096: 0 deg there, 4095 counts per 360 deg.
        assert!((m.raw_to_deg(2096)).abs() < 1e-12);
        assert!((m.raw_to_deg(2096 + 1023) - 1023.0 * 360.0 / 4095.0).abs() < 1e-12);
        for deg in [-60.0, -1.0, 0.0, 33.3, 90.0] {
            assert!((m.raw_to_deg(m.deg_to_raw(deg)) - deg).abs() < 0.09, "{deg}");
        }
        // Goals beyond the recorded range are clamped into it.
        assert_eq!(m.deg_to_raw(400.0), 3425);
        let flipped = MotorCalibration { drive_mode: 1, ..m };
        assert!((flipped.raw_to_deg(m.deg_to_raw(20.0)) + 20.0).abs() < 0.09);
    }

    #[test]
    fn percent_mapping_is_range_0_100() {
        let g = MotorCalibration {
            id: 6,
            drive_mode: 0,
            homing_offset: 0,
            range_min: 2031,
            range_max: 3483,
        };
        assert!((g.raw_to_percent(2031)).abs() < 1e-12);
        assert!((g.raw_to_percent(3483) - 100.0).abs() < 1e-12);
        assert_eq!(g.percent_to_raw(50.0), 2757);
        assert!((g.raw_to_percent(100) - 0.0).abs() < 1e-12, "clamped below");
    }

    #[test]
    fn invalid_files_are_named() {
        assert!(Calibration::from_json("{").is_err());
        let mut c = Calibration::from_json(PHONE2ACT_FILE).unwrap();
        c.motors.retain(|(n, _)| n != "gripper");
        assert!(matches!(c.validate(), Err(CalibrationError::Invalid { motor, .. }) if motor == "gripper"));
        let mut c = Calibration::from_json(PHONE2ACT_FILE).unwrap();
        c.motors[2].1.range_max = c.motors[2].1.range_min;
        assert!(
            matches!(c.validate(), Err(CalibrationError::Invalid { motor, .. }) if motor == "elbow_flex")
        );
    }
}
