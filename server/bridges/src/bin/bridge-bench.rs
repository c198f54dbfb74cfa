//! Command rates each hardware bridge sustains against its emulator.
//!
//! `cargo run --release -p phone2act-bridges --features emulators --bin bridge-bench [-- --seconds 2]`
//!
//! Dobot: `ServoP` commands per second through the bridge (each waits for its reply), as fast as possible and
//! paced at 125 Hz, plus the feedback packet rate. SO-101: sync write of six goals + sync read of six positions
//! per second on the raw bus, and control cycles per second through the bridge. The pseudo-terminal has no
//! baud rate, so the wire time a real 1 Mbaud bus would add is printed alongside.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
use phone2act_bridges::dobot::protocol::Firmware;
use phone2act_bridges::dobot::{DobotBridge, DobotConfig};
use phone2act_bridges::feetech::emulator::SO101_CENTRED_RANGES;
use phone2act_bridges::feetech::protocol::{self, register};
use phone2act_bridges::feetech::{FeetechBus, FeetechEmulator};
use phone2act_bridges::so101::calibration::Calibration;
use phone2act_bridges::so101::{So101Bridge, So101Config};
use phone2act_bridges::{Bridge, Command, Health};
use phone2act_core::kinematics::So101Kinematics;
use std::time::{Duration, Instant};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut seconds = 2.0f64;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seconds" => seconds = args.next().ok_or("--seconds needs a value")?.parse()?,
            "-h" | "--help" => {
                println!("bridge-bench [--seconds S]");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let run = Duration::from_secs_f64(seconds);
    println!("bridge-bench: {seconds} s per measurement");
    dobot(Firmware::V4, run)?;
    dobot(Firmware::V3, run)?;
    so101(run)?;
    Ok(())
}

fn wait_ready(bridge: &dyn Bridge) -> Result<(), String> {
    let deadline = Instant::now() + Duration::from_secs(3);
    while bridge.health() != Health::Ready {
        if Instant::now() > deadline {
            return Err(format!("bridge not ready: {:?}", bridge.health()));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok(())
}

fn target(start: &Isometry3<f64>, i: u64) -> Isometry3<f64> {
    let s = i as f64 * 0.01;
    Isometry3::from_parts(
        Translation3::from(
            start.translation.vector + Vector3::new(0.03 * s.sin(), 0.03 * s.cos() - 0.03, 0.0),
        ),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.2 * s.sin()) * start.rotation,
    )
}

fn command(seq: u64, pose: Isometry3<f64>) -> Command {
    Command {
        seq,
        robot_from_target: pose,
        gripper_target: 0.0,
        issue_time_ns: 0,
        joint_targets_rad: None,
    }
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn dobot(firmware: Firmware, run: Duration) -> Result<(), Box<dyn std::error::Error>> {
    let emu = DobotEmulator::start(EmulatorConfig {
        firmware,
        ..EmulatorConfig::default()
    })?;
    let mut config = DobotConfig::new("127.0.0.1");
    config.firmware = firmware;
    config.dashboard_port = emu.dashboard_addr().port();
    config.motion_port = Some(emu.motion_addr().port());
    config.feedback_port = emu.feedback_addr().port();
    config.servo_t_s = 0.008;
    let bridge = DobotBridge::start(config)?;
    wait_ready(bridge.as_ref())?;
    let start = bridge.feedback().ok_or("no feedback")?.robot_from_ee;

    // As fast as the request/reply loop goes: a producer that always has a newer target ready.
    let before = bridge.stats();
    let t0 = Instant::now();
    let mut seq = 0;
    while t0.elapsed() < run {
        seq += 1;
        bridge.send(command(seq, target(&start, seq)));
        std::thread::sleep(Duration::from_micros(50));
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let after = bridge.stats();
    let max_rate = (after.servo_sent - before.servo_sent) as f64 / elapsed;
    let feedback_rate = (after.packets_ok - before.packets_ok) as f64 / elapsed;

    // Paced at 125 Hz, as a planner would: how many arrive, and how late the reply comes.
    std::thread::sleep(Duration::from_millis(50));
    let before = bridge.stats();
    let period = Duration::from_secs_f64(1.0 / 125.0);
    let mut issued = 0u64;
    let mut latencies = Vec::new();
    let t0 = Instant::now();
    let mut next = t0;
    while t0.elapsed() < run {
        seq += 1;
        issued += 1;
        let sent_at = Instant::now();
        let sent_before = bridge.stats().servo_sent;
        bridge.send(command(seq, target(&start, seq)));
        // The reply has been read when the sent counter moves.
        while bridge.stats().servo_sent == sent_before && sent_at.elapsed() < period {
            std::hint::spin_loop();
        }
        if bridge.stats().servo_sent > sent_before {
            latencies.push(sent_at.elapsed());
        }
        next += period;
        if let Some(rest) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(rest);
        }
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let after = bridge.stats();
    latencies.sort();
    let delivered = after.servo_sent - before.servo_sent;
    println!(
        "dobot {firmware:?}: ServoP max {max_rate:.0}/s; paced 125 Hz: {delivered}/{issued} sent ({:.1}/s), \
         send→reply p50 {:?} p99 {:?}, rejected {}; feedback {feedback_rate:.1} packets/s (controller: 125)",
        delivered as f64 / elapsed,
        percentile(&latencies, 0.5),
        percentile(&latencies, 0.99),
        after.servo_rejected,
    );
    bridge.shutdown();
    Ok(())
}

fn so101_fixture() -> (Calibration, Vec<(u8, u16)>) {
    let calibration = Calibration::so101_with_ranges(SO101_CENTRED_RANGES);
    let servos: Vec<(u8, u16)> = [2047u16, 1600, 2400, 2800, 2047, 3000]
        .into_iter()
        .zip(1u8..)
        .map(|(r, id)| (id, r))
        .collect();
    (calibration, servos)
}

fn so101(run: Duration) -> Result<(), Box<dyn std::error::Error>> {
    so101_bus(run)?;
    so101_bridge(run)
}

fn so101_bus(run: Duration) -> Result<(), Box<dyn std::error::Error>> {
    let (_, servos) = so101_fixture();
    let ids: Vec<u8> = servos.iter().map(|(id, _)| *id).collect();
    // Raw bus: one sync write of six goals and one sync read of six positions per iteration.
    let emulator = FeetechEmulator::start(&servos)?;
    let path = emulator.port_path().to_str().ok_or("pty path")?.to_owned();
    let mut bus = FeetechBus::open(&path, 1_000_000, Duration::from_millis(20))?;
    let (goal_address, goal_len) = register::GOAL_POSITION;
    let (present_address, present_len) = register::PRESENT_POSITION;
    let mut times = Vec::new();
    let t0 = Instant::now();
    let mut i = 0u16;
    while t0.elapsed() < run {
        i = i.wrapping_add(1);
        let items: Vec<(u8, Vec<u8>)> = servos
            .iter()
            .map(|(id, r)| (*id, (r + i % 50).to_le_bytes().to_vec()))
            .collect();
        let t = Instant::now();
        bus.sync_write(goal_address, goal_len, &items)?;
        bus.sync_read(present_address, present_len, &ids)?;
        times.push(t.elapsed());
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let n = times.len();
    times.sort();
    let items: Vec<(u8, Vec<u8>)> = servos
        .iter()
        .map(|(id, r)| (*id, r.to_le_bytes().to_vec()))
        .collect();
    let wire_bytes = protocol::sync_write_packet(goal_address, goal_len, &items)?.len()
        + protocol::sync_read_packet(present_address, present_len, &ids)?.len()
        + ids.len() * protocol::status_packet(1, 0, &[0, 0]).len();
    let wire_s = wire_bytes as f64 * 10.0 / 1_000_000.0;
    println!(
        "feetech bus (pty): sync write+read of 6 servos {:.0}/s, p50 {:?} p99 {:?}; on a 1 Mbaud wire the same \
         {wire_bytes} bytes take {:.2} ms (≤ {:.0}/s before servo return delays)",
        n as f64 / elapsed,
        percentile(&times, 0.5),
        percentile(&times, 0.99),
        wire_s * 1e3,
        1.0 / wire_s,
    );
    Ok(())
}

fn so101_bridge(run: Duration) -> Result<(), Box<dyn std::error::Error>> {
    let (calibration, servos) = so101_fixture();
    // Through the bridge: IK + sync write + sync read + FK per cycle.
    let dir = std::env::temp_dir().join(format!("bridge-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let cal_path = dir.join("follower.json");
    calibration.save(&cal_path)?;
    for rate_hz in [100.0, 1000.0] {
        let emulator = FeetechEmulator::start(&servos)?;
        let mut config = So101Config::new(emulator.port_path().to_str().ok_or("pty path")?, &cal_path);
        config.rate_hz = rate_hz;
        let bridge = So101Bridge::start(config)?;
        wait_ready(bridge.as_ref())?;
        let kin = So101Kinematics::new();
        let start_joints: [f64; 5] = bridge
            .feedback()
            .ok_or("no feedback")?
            .joint_positions_rad
            .try_into()
            .map_err(|_| "joint count")?;
        let before = bridge.stats();
        let t0 = Instant::now();
        let mut seq = 0u64;
        while t0.elapsed() < run {
            seq += 1;
            let s = seq as f64 * 0.002;
            let mut q = start_joints;
            q[0] += 0.3 * s.sin();
            q[1] += 0.2 * (1.0 - s.cos());
            bridge.send(command(seq, kin.forward(&q)));
            std::thread::sleep(Duration::from_micros(200));
        }
        let elapsed = t0.elapsed().as_secs_f64();
        let after = bridge.stats();
        println!(
            "so101 bridge at rate_hz {rate_hz}: {:.0} cycles/s, {:.0} goal writes/s, mean work {:.0} µs/cycle, \
             failed cycles {} (last error: {})",
            (after.cycles - before.cycles) as f64 / elapsed,
            (after.goals_written - before.goals_written) as f64 / elapsed,
            after.mean_cycle_work_us,
            after.failed_cycles - before.failed_cycles,
            after.last_error.as_deref().unwrap_or("none"),
        );
        bridge.shutdown();
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
