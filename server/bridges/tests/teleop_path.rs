//! The teleop path of phone2act-core (clutch, planner, safety gate, gripper) driving each hardware bridge
//! against its emulator, as the server's arm controller does: phone samples in, gated targets to
//! `Bridge::send`, the bridge's measured pose back into the planner for re-indexing.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
use phone2act_bridges::dobot::protocol::Firmware;
use phone2act_bridges::dobot::{DobotBridge, DobotConfig};
use phone2act_bridges::feetech::FeetechEmulator;
use phone2act_bridges::feetech::emulator::SO101_CENTRED_RANGES;
use phone2act_bridges::so101::calibration::Calibration;
use phone2act_bridges::so101::{So101Bridge, So101Config};
use phone2act_bridges::{Bridge, Command, Health};
use phone2act_core::{ClutchKind, GateConfig, GripperCommand, TeleopArm, TeleopConfig};
use std::time::{Duration, Instant};

fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// A phone held in front of the operator, moved in a 4 cm circle and turned a little.
fn phone_pose(s: f64) -> Isometry3<f64> {
    let angle = s * std::f64::consts::TAU;
    Isometry3::from_parts(
        Translation3::new(
            0.04 * angle.sin(),
            1.2 + 0.02 * (1.0 - angle.cos()),
            -0.3 - 0.03 * s,
        ),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.15 * angle.sin()),
    )
}

struct Outcome {
    last_target: Isometry3<f64>,
    last_seq: u64,
    commands: u64,
}

/// Runs a teleop session of `n` phone samples at 50 Hz against `bridge`.
fn teleop_session(bridge: &dyn Bridge, config: &TeleopConfig, n: u64) -> Outcome {
    let start = Instant::now();
    let now_s = || start.elapsed().as_secs_f64();
    let measured = || bridge.feedback().expect("feedback").robot_from_ee;
    let mut arm = TeleopArm::new(config, measured()).unwrap();
    let engaged_at = measured();
    let step = arm.clutch(ClutchKind::Engage, Some(phone_pose(0.0)), engaged_at, now_s());
    assert!(step.engaged && step.reindexed);
    // Engaging re-indexes at the measured pose: whatever it commands is where the robot already is.
    if let Some((target, _)) = step.command {
        assert!(
            (target.translation.vector - engaged_at.translation.vector).norm() < 1e-9,
            "engaging moved the arm"
        );
    }
    let mut seq = 0;
    let mut last_target = measured();
    let mut commands = 0;
    for i in 1..=n {
        if i == n / 2 {
            arm.gripper(GripperCommand::Toggle).unwrap();
        }
        let step = arm.on_pose(phone_pose(i as f64 / n as f64), true, measured(), now_s());
        assert!(
            !step.decision.verdict.rejected(),
            "sample {i}: {:?}",
            step.decision
        );
        if let Some((target, gripper)) = step.command {
            seq += 1;
            commands += 1;
            last_target = target;
            bridge.send(Command {
                seq,
                robot_from_target: target,
                gripper_target: gripper,
                issue_time_ns: 0,
                joint_targets_rad: None,
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Outcome {
        last_target,
        last_seq: seq,
        commands,
    }
}

#[test]
fn phone_teleop_drives_the_emulated_dobot() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let mut config = DobotConfig::new("127.0.0.1");
    config.firmware = Firmware::V4;
    config.dashboard_port = emu.dashboard_addr().port();
    config.feedback_port = emu.feedback_addr().port();
    config.servo_t_s = 0.03;
    let bridge = DobotBridge::start(config).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    // Phone2Act's CR5 workspace (config/dobot.yaml), in metres.
    let teleop = TeleopConfig {
        gate: GateConfig {
            workspace_min_m: [-0.8, -0.5, 0.013],
            workspace_max_m: [0.0, 0.5, 0.75],
            ..GateConfig::default()
        },
        ..TeleopConfig::default()
    };
    let start_pose = emu.snapshot().pose;
    let out = teleop_session(bridge.as_ref(), &teleop, 60);
    assert!(
        out.commands >= 55,
        "only {} commands passed the gate",
        out.commands
    );
    let moved = (out.last_target.translation.vector - start_pose.translation.vector).norm();
    assert!(moved > 0.02, "the targets barely moved ({moved} m)");
    wait_for("the robot at the last target", Duration::from_secs(2), || {
        let p = emu.snapshot().pose;
        (p.translation.vector - out.last_target.translation.vector).norm() < 5e-4
            && p.rotation.angle_to(&out.last_target.rotation) < 2e-3
    });
    wait_for("feedback of it", Duration::from_secs(1), || {
        bridge.feedback().is_some_and(|f| {
            f.applied_seq == out.last_seq
                && (f.robot_from_ee.translation.vector - out.last_target.translation.vector).norm() < 5e-4
        })
    });
    // The gripper was toggled closed half way (tool output 1 by default).
    assert_eq!(emu.snapshot().tool_outputs & 1, 1);
    assert!(bridge.feedback().unwrap().gripper_position > 0.99);
}

#[test]
fn phone_teleop_drives_the_emulated_so101() {
    let calibration = Calibration::so101_with_ranges(SO101_CENTRED_RANGES);
    let dir = tempfile::tempdir().unwrap();
    let cal_path = dir.path().join("follower.json");
    calibration.save(&cal_path).unwrap();
    // The simulated arm's start pose: tool ~0.2 m in front of the base, ~0.15 m up.
    let start_rad = [0.0f64, -0.8, 0.6, 1.1, 0.0];
    let mut servos: Vec<(u8, u16)> = calibration
        .motors
        .iter()
        .take(5)
        .zip(start_rad)
        .map(|((_, m), q)| (m.id, m.deg_to_raw(q.to_degrees())))
        .collect();
    servos.push((6, 3300));
    let emulator = FeetechEmulator::start(&servos).unwrap();
    let mut config = So101Config::new(emulator.port_path().to_str().unwrap(), &cal_path);
    config.timeout_ms = 50;
    let bridge = So101Bridge::start(config).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });

    let out = teleop_session(bridge.as_ref(), &TeleopConfig::default(), 60);
    assert!(
        out.commands >= 55,
        "only {} commands passed the gate",
        out.commands
    );
    // A 5-DoF arm: position is followed, orientation only as far as the arm allows.
    wait_for("the arm at the last target", Duration::from_secs(3), || {
        bridge.feedback().is_some_and(|f| {
            f.applied_seq == out.last_seq
                && (f.robot_from_ee.translation.vector - out.last_target.translation.vector).norm() < 3e-3
        })
    });
    wait_for("gripper closed", Duration::from_secs(2), || {
        bridge.feedback().is_some_and(|f| f.gripper_position > 0.95)
    });
    assert_eq!(emulator.servo(6).unwrap().goal_position(), 2000);
}
