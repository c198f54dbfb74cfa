//! Checks an SO-101 follower arm before its first teleoperation: every servo answers with the STS3215 model
//! number, all run the same firmware, none is in multi-turn feedback mode, none reports an alarm, and the
//! position limits and homing offsets in the servos are the calibration file's.
//!
//! `so101-check --port /dev/ttyACM0 [--calibration FILE.json] [--ids 1,2,3,4,5,6] [--positions]`
//!
//! Prints one line per servo and a verdict; exits 1 if anything would stop the arm. Reads only: nothing is
//! written to the servos. `--positions` (needs `--calibration`) also starts the SO-101 bridge without
//! configuring or enabling the servos and prints the joint angles it reads, as lerobot names them
//! (`shoulder_pan.pos` ... in degrees, `gripper.pos` in lerobot's 0..100), on a line starting `positions `.

use phone2act_bridges::Bridge;
use phone2act_bridges::feetech::FeetechBus;
use phone2act_bridges::feetech::protocol::{
    HOMING_OFFSET_SIGN_BIT, PHASE_MULTI_TURN_FEEDBACK, STS3215_MODEL, decode_sign_magnitude, register,
    status_error_text,
};
use phone2act_bridges::so101::calibration::Calibration;
use phone2act_bridges::so101::{AlarmAction, MOTORS, So101Bridge, So101Config, alarm_action, expand_home};
use phone2act_core::kinematics::SO101_JOINT_NAMES;
use std::path::PathBuf;
use std::time::{Duration, Instant};

const USAGE: &str = "so101-check --port DEVICE [--calibration FILE.json] [--baudrate 1000000] \
                     [--ids 1,2,3,4,5,6] [--timeout-ms 50] [--positions]";

#[derive(Default)]
struct Verdict {
    warnings: usize,
    failures: usize,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut port = None;
    let mut calibration_file: Option<PathBuf> = None;
    let mut baudrate = 1_000_000u32;
    let mut ids: Option<Vec<u8>> = None;
    let mut timeout_ms = 50u64;
    let mut positions = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{a} needs a value\n{USAGE}"));
        match a.as_str() {
            "--port" => port = Some(value()?),
            "--calibration" => calibration_file = Some(expand_home(&PathBuf::from(value()?))),
            "--baudrate" => baudrate = value()?.parse()?,
            "--timeout-ms" => timeout_ms = value()?.parse()?,
            "--positions" => positions = true,
            "--ids" => {
                ids = Some(
                    value()?
                        .split(',')
                        .map(|s| s.trim().parse::<u8>())
                        .collect::<Result<_, _>>()?,
                );
            }
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other}\n{USAGE}").into()),
        }
    }
    let port = port.ok_or(format!("--port is required\n{USAGE}"))?;
    let calibration = match &calibration_file {
        Some(path) => {
            let c = Calibration::load(path)?;
            c.validate()?;
            Some(c)
        }
        None => None,
    };
    let ids: Vec<u8> = match (ids, &calibration) {
        (Some(ids), _) => ids,
        (None, Some(c)) => SO101_JOINT_NAMES
            .iter()
            .filter_map(|name| c.get(name).map(|m| m.id))
            .collect(),
        (None, None) => (1..=6).collect(),
    };
    if ids.len() != MOTORS {
        return Err(format!("{} ids given, the SO-101 has {MOTORS} servos", ids.len()).into());
    }
    let mut verdict = Verdict::default();
    {
        let mut bus = FeetechBus::open(&port, baudrate, Duration::from_millis(timeout_ms))?;
        bus.strict_status = false;
        let mut firmwares = Vec::new();
        for (motor, &id) in ids.iter().enumerate() {
            let joint = SO101_JOINT_NAMES[motor];
            let line = check_servo(&mut bus, motor, id, calibration.as_ref(), &mut verdict);
            match line {
                Ok((text, firmware)) => {
                    firmwares.push(firmware);
                    println!("servo {id} ({joint}): {text}");
                }
                Err(e) => {
                    verdict.failures += 1;
                    println!("servo {id} ({joint}): FAIL {e}");
                }
            }
        }
        firmwares.sort_unstable();
        firmwares.dedup();
        if firmwares.len() > 1 {
            verdict.failures += 1;
            let list: Vec<String> = firmwares.iter().map(|(a, b)| format!("{a}.{b}")).collect();
            println!(
                "FAIL the servos run different firmware versions ({}); lerobot refuses such a bus: update them with Feetech's FD software",
                list.join(", ")
            );
        }
    }
    if positions {
        let file = calibration_file.ok_or("--positions needs --calibration")?;
        let mut config = So101Config::new(port.clone(), file);
        config.baudrate = baudrate;
        config.timeout_ms = timeout_ms;
        config.ids = Some(std::array::from_fn(|i| ids[i]));
        config.configure_motors = false;
        config.enable_on_start = false;
        let bridge = So101Bridge::start(config)?;
        let deadline = Instant::now() + Duration::from_secs(5);
        let feedback = loop {
            if let Some(f) = bridge.feedback() {
                break f;
            }
            if Instant::now() > deadline {
                return Err(format!("no feedback from the bridge: {:?}", bridge.health()).into());
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        if let Some(w) = bridge.warning() {
            println!("bridge warning: {w}");
        }
        let (open, closed) = (
            bridge.config().gripper_open_pct,
            bridge.config().gripper_closed_pct,
        );
        let mut fields: Vec<String> = feedback
            .joint_positions_rad
            .iter()
            .zip(SO101_JOINT_NAMES)
            .map(|(q, name)| format!("\"{name}.pos\": {}", q.to_degrees()))
            .collect();
        let gripper_pct = open + (closed - open) * feedback.gripper_position;
        fields.push(format!("\"gripper.pos\": {gripper_pct}"));
        println!("positions {{{}}}", fields.join(", "));
        bridge.shutdown();
    }
    println!(
        "{}: {} warning(s), {} failure(s)",
        if verdict.failures == 0 { "OK" } else { "NOT READY" },
        verdict.warnings,
        verdict.failures
    );
    if verdict.failures > 0 {
        std::process::exit(1);
    }
    Ok(())
}

/// One servo's line, and its firmware version.
fn check_servo(
    bus: &mut FeetechBus,
    motor: usize,
    id: u8,
    calibration: Option<&Calibration>,
    verdict: &mut Verdict,
) -> Result<(String, (u16, u16)), Box<dyn std::error::Error>> {
    let alarms = bus.ping(id)?;
    let model = bus.read_value(id, register::MODEL_NUMBER)?;
    let firmware = (
        bus.read_value(id, register::FIRMWARE_MAJOR_VERSION)?,
        bus.read_value(id, register::FIRMWARE_MINOR_VERSION)?,
    );
    let phase = bus.read_value(id, register::PHASE)? as u8;
    let voltage_dv = bus.read_value(id, register::PRESENT_VOLTAGE)?;
    let temperature_c = bus.read_value(id, register::PRESENT_TEMPERATURE)?;
    let min = bus.read_value(id, register::MIN_POSITION_LIMIT)?;
    let max = bus.read_value(id, register::MAX_POSITION_LIMIT)?;
    let offset = decode_sign_magnitude(
        bus.read_value(id, register::HOMING_OFFSET)?,
        HOMING_OFFSET_SIGN_BIT,
    );
    let mut parts = vec![format!(
        "firmware {}.{}, {:.1} V, {temperature_c} °C",
        firmware.0,
        firmware.1,
        f64::from(voltage_dv) / 10.0
    )];
    if model != STS3215_MODEL {
        verdict.failures += 1;
        parts.push(format!("FAIL model {model}, not an STS3215 ({STS3215_MODEL})"));
    }
    if phase & PHASE_MULTI_TURN_FEEDBACK != 0 {
        verdict.warnings += 1;
        parts.push(format!(
            "WARN Phase {phase:#04x} has bit 4 (multi-turn angle feedback) set: the bridge clears it at start (configure_motors)"
        ));
    }
    if alarms != 0 {
        let stops = (0..8)
            .map(|b| 1u8 << b)
            .any(|bit| alarms & bit != 0 && alarm_action(motor, bit) == AlarmAction::Stop);
        if stops {
            verdict.failures += 1;
            parts.push(format!("FAIL alarm {}: stops the arm", status_error_text(alarms)));
        } else {
            verdict.warnings += 1;
            parts.push(format!(
                "WARN alarm {}: the arm works, status shows it",
                status_error_text(alarms)
            ));
        }
    }
    match calibration.and_then(|c| c.get(SO101_JOINT_NAMES[motor])) {
        Some(cal) if (cal.range_min, cal.range_max, cal.homing_offset) != (min, max, offset) => {
            verdict.warnings += 1;
            parts.push(format!(
                "WARN servo holds limits {min}..{max} and homing offset {offset}, the calibration file {}..{} and {}: the bridge writes the file's at start (configure_motors)",
                cal.range_min, cal.range_max, cal.homing_offset
            ));
        }
        Some(_) => parts.push(format!(
            "limits {min}..{max} and homing offset {offset} as calibrated"
        )),
        None => parts.push(format!("limits {min}..{max}, homing offset {offset}")),
    }
    Ok((parts.join("; "), firmware))
}
