//! An emulated STS3215 bus on a pseudo-terminal, for clients outside this crate (lerobot's `FeetechMotorsBus`
//! in `tests/feetech_upstream`). Prints the device path on the first line of stdout, then serves until killed.
//!
//! `feetech-emulator [--servo ID:RAW]... [--multi-turn ID]...`
//!
//! `--servo` adds a servo with its shaft at raw position RAW (default: ids 1..6 at 2047); `--multi-turn` leaves
//! `Phase` bit 4 set on that servo, as some ship from the factory. Commands on stdin, one a line, each answered
//! by one line on stdout (`ok ...` or `error ...`), change the bus while it runs:
//!
//! - `alarm ID BITS`: latch alarm bits (decimal or 0x..) on a servo; `clear ID` clears them.
//! - `move ID RAW`: put a shaft at RAW (raw counts before the homing offset), as a hand would.
//! - `speed ID COUNTS_PER_S`: how fast a servo with torque on moves to its goal (0 holds the shaft).
//! - `get ID ADDRESS LEN`: a register value (LEN 1 or 2), e.g. `get 5 18 1` for `Phase`.
//! - `set ID ADDRESS LEN VALUE`: a register as the factory would leave it, whatever `Lock` says (e.g.
//!   `set 5 18 1 16` for a servo that arrives in multi-turn feedback mode).
//! - `present ID`: `Present_Position` as the servo reports it (sign-magnitude decoded).
//! - `ids`: the ids on the bus.

use phone2act_bridges::feetech::FeetechEmulator;
use phone2act_bridges::feetech::protocol::{PHASE_MULTI_TURN_FEEDBACK, register};
use std::io::{BufRead as _, Write as _};

const USAGE: &str = "feetech-emulator [--servo ID:RAW]... [--multi-turn ID]...";

fn parse_u16(text: &str) -> Result<u16, String> {
    let parsed = match text.strip_prefix("0x") {
        Some(hex) => u16::from_str_radix(hex, 16),
        None => text.parse(),
    };
    parsed.map_err(|e| format!("{text:?}: {e}"))
}

fn parse_u8(text: &str) -> Result<u8, String> {
    u8::try_from(parse_u16(text)?).map_err(|e| format!("{text:?}: {e}"))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut servos: Vec<(u8, u16)> = Vec::new();
    let mut multi_turn: Vec<u8> = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{a} needs a value\n{USAGE}"));
        match a.as_str() {
            "--servo" => {
                let v = value()?;
                let (id, raw) = v
                    .split_once(':')
                    .ok_or_else(|| format!("--servo {v}: want ID:RAW"))?;
                servos.push((parse_u8(id)?, parse_u16(raw)?));
            }
            "--multi-turn" => multi_turn.push(parse_u8(&value()?)?),
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other}\n{USAGE}").into()),
        }
    }
    if servos.is_empty() {
        servos = (1..=6).map(|id| (id, 2047)).collect();
    }
    let emulator = FeetechEmulator::start(&servos)?;
    for id in multi_turn {
        emulator
            .with_servo(id, |s| {
                let phase = s.register(register::PHASE);
                s.set_factory_register(register::PHASE, phase | u16::from(PHASE_MULTI_TURN_FEEDBACK));
            })
            .ok_or_else(|| format!("--multi-turn {id}: no such servo"))?;
    }
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}", emulator.port_path().display())?;
    out.flush()?;
    for line in std::io::stdin().lock().lines() {
        let line = line?;
        let words: Vec<&str> = line.split_whitespace().collect();
        let answer = command(&emulator, &words).unwrap_or_else(|e| format!("error {e}"));
        writeln!(out, "{answer}")?;
        out.flush()?;
    }
    // Stdin closed: the caller only needs the bus, which serves until the process is killed.
    loop {
        std::thread::park();
    }
}

fn command(emulator: &FeetechEmulator, words: &[&str]) -> Result<String, String> {
    let servo = |text: &str| -> Result<u8, String> {
        let id = parse_u8(text)?;
        if emulator.servo(id).is_some() {
            Ok(id)
        } else {
            Err(format!("no servo {id}"))
        }
    };
    match words {
        ["alarm", id, bits] => {
            emulator.latch_alarm(servo(id)?, parse_u8(bits)?);
            Ok("ok".into())
        }
        ["clear", id] => {
            emulator.clear_alarm(servo(id)?);
            Ok("ok".into())
        }
        ["move", id, raw] => {
            let raw: f64 = raw.parse().map_err(|e| format!("{raw:?}: {e}"))?;
            emulator.set_actual_position(servo(id)?, raw);
            Ok("ok".into())
        }
        ["speed", id, counts_s] => {
            let v: f64 = counts_s.parse().map_err(|e| format!("{counts_s:?}: {e}"))?;
            emulator.with_servo(servo(id)?, |s| s.speed_counts_s = v);
            Ok("ok".into())
        }
        ["get", id, address, len] => {
            let entry = (parse_u8(address)?, parse_u8(len)?);
            if !matches!(entry.1, 1 | 2) {
                return Err("LEN must be 1 or 2".into());
            }
            let value = emulator
                .servo(servo(id)?)
                .map(|s| s.register(entry))
                .unwrap_or_default();
            Ok(format!("ok {value}"))
        }
        ["set", id, address, len, value] => {
            let entry = (parse_u8(address)?, parse_u8(len)?);
            if !matches!(entry.1, 1 | 2) {
                return Err("LEN must be 1 or 2".into());
            }
            let value = parse_u16(value)?;
            emulator.with_servo(servo(id)?, |s| s.set_factory_register(entry, value));
            Ok("ok".into())
        }
        ["present", id] => {
            let value = emulator
                .servo(servo(id)?)
                .map(|s| s.present_position())
                .unwrap_or_default();
            Ok(format!("ok {value}"))
        }
        ["ids"] => {
            let ids: Vec<String> = emulator.ids().iter().map(u8::to_string).collect();
            Ok(format!("ok {}", ids.join(" ")))
        }
        _ => Err(format!("unknown command {:?}", words.join(" "))),
    }
}
