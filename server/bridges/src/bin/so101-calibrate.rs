//! Calibrates an SO-101 follower arm as lerobot does and writes a lerobot-compatible calibration file.
//!
//! `so101-calibrate --port /dev/ttyACM0 --out ~/.cache/huggingface/lerobot/calibration/robots/so101_follower/my_arm.json`
//!
//! Torque is switched off; put every joint at the middle of its range and press Enter (half-turn homing), then
//! move every joint except the wrist roll through its whole range and press Enter again. The homing offsets and
//! position limits are written into the motors and the file.

use phone2act_bridges::feetech::FeetechBus;
use phone2act_bridges::so101::calibration::run_calibration;
use phone2act_bridges::so101::expand_home;
use phone2act_core::kinematics::SO101_JOINT_NAMES;
use std::io::BufRead as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

const USAGE: &str = "so101-calibrate --port DEVICE --out FILE.json [--baudrate 1000000] [--ids 1,2,3,4,5,6] \
                     [--timeout-ms 50]";

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut port = None;
    let mut out = None;
    let mut baudrate = 1_000_000u32;
    let mut ids: Vec<u8> = (1..=6).collect();
    let mut timeout_ms = 50u64;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{a} needs a value\n{USAGE}"));
        match a.as_str() {
            "--port" => port = Some(value()?),
            "--out" => out = Some(PathBuf::from(value()?)),
            "--baudrate" => baudrate = value()?.parse()?,
            "--timeout-ms" => timeout_ms = value()?.parse()?,
            "--ids" => {
                ids = value()?
                    .split(',')
                    .map(|s| s.trim().parse::<u8>())
                    .collect::<Result<_, _>>()?;
            }
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other}\n{USAGE}").into()),
        }
    }
    let port = port.ok_or(USAGE)?;
    let out = expand_home(&out.ok_or(USAGE)?);
    if ids.len() != SO101_JOINT_NAMES.len() {
        return Err(format!(
            "--ids needs {} ids, one per motor: {SO101_JOINT_NAMES:?}",
            SO101_JOINT_NAMES.len()
        )
        .into());
    }
    let motors: Vec<(String, u8)> = SO101_JOINT_NAMES
        .iter()
        .map(|n| (*n).to_owned())
        .zip(ids)
        .collect();

    let mut bus = FeetechBus::open(&port, baudrate, Duration::from_millis(timeout_ms))?;
    for (name, id) in &motors {
        bus.ping(*id).map_err(|e| format!("{name} (id {id}): {e}"))?;
    }
    println!(
        "All {} motors answer on {port}. Torque will be switched off.",
        motors.len()
    );

    let done = Arc::new(AtomicBool::new(false));
    let calibration = run_calibration(
        &mut bus,
        &motors,
        || {
            println!("Move every joint to the middle of its range, then press Enter.");
            let _ = std::io::stdin().lock().read_line(&mut String::new());
            println!(
                "Now move every joint except wrist_roll through its whole range; press Enter when done."
            );
            let done = Arc::clone(&done);
            std::thread::spawn(move || {
                let _ = std::io::stdin().lock().read_line(&mut String::new());
                done.store(true, Ordering::SeqCst);
            });
        },
        || !done.load(Ordering::SeqCst),
    )?;
    calibration.save(&out)?;
    println!("Wrote {}:", out.display());
    println!("{}", calibration.to_json());
    Ok(())
}
