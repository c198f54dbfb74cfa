//! The Dobot bridge against the emulated controller over loopback TCP, driven only through the `Bridge` trait.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_bridges::dobot::emulator::{Corruption, DobotEmulator, EmulatorConfig, tool_down};
use phone2act_bridges::dobot::feedback::EulerConvention;
use phone2act_bridges::dobot::gripper::GripperOutput;
use phone2act_bridges::dobot::protocol::{ErrorIds, Firmware, Terminator};
use phone2act_bridges::dobot::{ControlRequest, DobotBridge, DobotConfig};
use phone2act_bridges::{Bridge, BridgeError, Command, Control, Health};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn bridge_config(emu: &DobotEmulator, firmware: Firmware) -> DobotConfig {
    let mut c = DobotConfig::new("127.0.0.1");
    c.firmware = firmware;
    c.dashboard_port = emu.dashboard_addr().port();
    c.motion_port = Some(emu.motion_addr().port());
    c.feedback_port = emu.feedback_addr().port();
    c.servo_t_s = 0.02;
    c
}

fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

fn command(seq: u64, pose: Isometry3<f64>, gripper: f64) -> Command {
    Command {
        seq,
        robot_from_target: pose,
        gripper_target: gripper,
        issue_time_ns: 0,
        joint_targets_rad: None,
    }
}

/// A smooth path around `start` (the kind of target stream the planner produces).
fn path_pose(start: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let offset = Vector3::new(0.05 * (s * 6.0).sin(), 0.04 * (1.0 - (s * 6.0).cos()), -0.03 * s);
    let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * s)
        * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.1 * s);
    Isometry3::from_parts(
        Translation3::from(start.translation.vector + offset),
        turn * start.rotation,
    )
}

/// Streams `n` targets at about 100 Hz and returns the last one.
fn stream(
    bridge: &Arc<DobotBridge>,
    start: &Isometry3<f64>,
    first_seq: u64,
    n: u64,
) -> (u64, Isometry3<f64>) {
    let mut last = *start;
    for i in 0..n {
        last = path_pose(start, i as f64 / n as f64);
        bridge.send(command(first_seq + i, last, 0.0));
        std::thread::sleep(Duration::from_millis(10));
    }
    (first_seq + n - 1, last)
}

/// An emulated V4 controller with `config` and a bridge with the test defaults, ready.
fn ready(config: EmulatorConfig) -> (DobotEmulator, Arc<DobotBridge>) {
    let emu = DobotEmulator::start(config).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    (emu, bridge)
}

/// Sends a target a fraction `s` along the test path and waits until the robot accepted it.
fn apply(bridge: &DobotBridge, seq: u64, s: f64) {
    let start = bridge.feedback().unwrap().robot_from_ee;
    bridge.send(command(seq, path_pose(&start, s), 0.0));
    wait_for("applied", Duration::from_secs(2), || {
        bridge.feedback().is_some_and(|f| f.applied_seq == seq)
    });
}

fn assert_close(what: &str, a: &Isometry3<f64>, b: &Isometry3<f64>, tol_m: f64, tol_rad: f64) {
    let dp = (a.translation.vector - b.translation.vector).norm();
    let dr = a.rotation.angle_to(&b.rotation);
    assert!(
        dp <= tol_m && dr <= tol_rad,
        "{what}: off by {:.2} mm and {:.3} deg",
        dp * 1e3,
        dr.to_degrees()
    );
}

#[test]
fn v4_servo_stream_is_followed_and_fed_back() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    assert_eq!(bridge.kind(), "dobot");
    assert_eq!(bridge.joint_names().len(), 6);
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let snap = emu.snapshot();
    assert!(snap.enabled, "the bridge enables the robot at start");
    assert_eq!(snap.speed_factor, 30);

    let start = bridge
        .feedback()
        .expect("feedback before any command")
        .robot_from_ee;
    assert_close(
        "initial feedback",
        &start,
        &EmulatorConfig::default().initial_pose,
        1e-6,
        1e-6,
    );
    let (last_seq, last) = stream(&bridge, &start, 1, 60);
    wait_for("the arm to settle", Duration::from_secs(2), || {
        let p = emu.snapshot().pose;
        (p.translation.vector - last.translation.vector).norm() < 1e-4
    });
    let snap = emu.snapshot();
    assert_close("emulated robot vs last target", &snap.pose, &last, 1e-4, 1e-3);
    assert!(
        snap.servo_commands >= 30,
        "only {} ServoP commands arrived",
        snap.servo_commands
    );
    let sent = snap.last_servo_command.unwrap();
    assert!(
        sent.contains("t=0.02") && sent.contains("aheadtime=50") && sent.contains("gain=500"),
        "{sent}"
    );

    // Feedback is the packet stream: wait for a packet taken after the arm settled.
    wait_for("feedback of the last target", Duration::from_secs(1), || {
        bridge.feedback().is_some_and(|f| {
            f.applied_seq == last_seq
                && (f.robot_from_ee.translation.vector - last.translation.vector).norm() < 1e-4
        })
    });
    let fb = bridge.feedback().unwrap();
    assert_close(
        "bridge feedback vs last target",
        &fb.robot_from_ee,
        &last,
        2e-4,
        2e-3,
    );
    assert_eq!(fb.joint_positions_rad.len(), 6);
    let stats = bridge.stats();
    assert_eq!(stats.convention, EulerConvention::ExtrinsicXyz);
    assert!(stats.convention_verified);
    assert_eq!(stats.servo_rejected, 0);
    assert!(stats.packets_ok > 10);
    bridge.shutdown();
    bridge.shutdown();
}

#[test]
fn v3_uses_the_separate_motion_port_without_optional_params_or_terminator() {
    let emu = DobotEmulator::start(EmulatorConfig {
        firmware: Firmware::V3,
        ..EmulatorConfig::default()
    })
    .unwrap();
    assert_ne!(emu.motion_addr(), emu.dashboard_addr());
    let mut config = bridge_config(&emu, Firmware::V3);
    config.terminator = Terminator::None;
    let bridge = DobotBridge::start(config).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let start = bridge.feedback().unwrap().robot_from_ee;
    let target = path_pose(&start, 0.5);
    bridge.send(command(7, target, 0.0));
    wait_for("applied", Duration::from_secs(2), || {
        bridge.feedback().is_some_and(|f| f.applied_seq == 7)
    });
    let snap = emu.snapshot();
    assert_eq!(snap.rejected_commands, 0, "V3 controller rejected a command");
    assert!(!snap.last_servo_command.unwrap().contains("t="));
    // ServoP on the V3 dashboard port is an unknown command: the bridge must not have sent it there.
    let reply = bridge.dashboard("ServoP(1,2,3,4,5,6)").unwrap();
    assert_eq!(reply.error_id, -10000);
}

#[test]
fn injected_robot_error_is_reported_held_and_cleared() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let start = bridge.feedback().unwrap().robot_from_ee;

    emu.inject_error(22);
    wait_for(
        "error health naming the controller's error id",
        Duration::from_secs(1),
        || matches!(bridge.health(), Health::Error(m) if m.contains("Error mode (9)") && m.contains("22")),
    );
    let before = emu.snapshot();
    for i in 0..10 {
        bridge.send(command(100 + i, path_pose(&start, 0.8), 0.0));
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(Duration::from_millis(60));
    let after = emu.snapshot();
    assert_eq!(
        after.servo_commands, before.servo_commands,
        "targets must be held while the robot is in error"
    );
    assert_close("held pose", &after.pose, &before.pose, 1e-9, 1e-9);
    assert!(bridge.stats().targets_held >= 1);

    bridge.control(Control::ClearError).unwrap();
    wait_for("ready after ClearError", Duration::from_secs(1), || {
        bridge.health() == Health::Ready
    });
    let target = path_pose(&start, 0.3);
    bridge.send(command(200, target, 0.0));
    wait_for("following again", Duration::from_secs(2), || {
        (emu.snapshot().pose.translation.vector - target.translation.vector).norm() < 1e-4
    });
}

#[test]
fn dropped_connection_is_reported_and_reconnected_on_request() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let start = bridge.feedback().unwrap().robot_from_ee;

    emu.drop_connections();
    wait_for("disconnected health", Duration::from_secs(2), || {
        matches!(bridge.health(), Health::Disconnected(_))
    });
    // Commands while down are held, not queued for later.
    bridge.send(command(1, path_pose(&start, 0.9), 0.0));
    std::thread::sleep(Duration::from_millis(80));
    assert_eq!(emu.snapshot().servo_commands, 0);

    bridge.control(Control::Reconnect).unwrap();
    assert_eq!(bridge.health(), Health::Ready);
    assert!(emu.snapshot().enabled);
    let target = path_pose(&start, 0.4);
    bridge.send(command(2, target, 0.0));
    wait_for("following after reconnect", Duration::from_secs(2), || {
        (emu.snapshot().pose.translation.vector - target.translation.vector).norm() < 1e-4
    });
    assert_eq!(bridge.stats().reconnects, 1);
}

#[test]
fn corrupt_and_short_feedback_packets_are_rejected_and_the_stream_recovers() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let before = emu.snapshot().pose;
    for (i, (corruption, text)) in [
        (Corruption::Truncate, "declares size"),
        (Corruption::BadTestValue, "test value"),
        (Corruption::BadSize, "size"),
    ]
    .into_iter()
    .enumerate()
    {
        let rejected = bridge.stats().packets_rejected;
        emu.corrupt_next_feedback(corruption);
        wait_for("a rejected packet", Duration::from_secs(1), || {
            bridge.stats().packets_rejected > rejected
        });
        let stats = bridge.stats();
        let last = stats.last_packet_error.unwrap();
        // A truncated packet shows up as the next packet's header at the wrong place: a size or test-value error.
        assert!(
            last.contains(text) || (i == 0 && last.contains("test value")),
            "{corruption:?}: {last}"
        );
        let ok = stats.packets_ok;
        wait_for("good packets again", Duration::from_secs(1), || {
            bridge.stats().packets_ok > ok + 3
        });
        assert_eq!(bridge.health(), Health::Ready);
    }
    let fb = bridge.feedback().unwrap();
    assert_close(
        "feedback after corruption",
        &fb.robot_from_ee,
        &before,
        1e-6,
        1e-6,
    );
    assert_close("arm held", &emu.snapshot().pose, &before, 1e-9, 1e-9);
}

#[test]
fn euler_convention_is_detected_and_a_wrong_configured_one_blocks_motion() {
    let initial = tool_down(-0.35, 0.1, 0.3, 0.4);
    let emu_cfg = EmulatorConfig {
        convention: EulerConvention::IntrinsicXyz,
        initial_pose: initial,
        ..EmulatorConfig::default()
    };

    // Detected: targets land with the right orientation even though the controller uses the other convention.
    let emu = DobotEmulator::start(emu_cfg.clone()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("verified", Duration::from_secs(1), || {
        bridge.stats().convention_verified
    });
    assert_eq!(bridge.stats().convention, EulerConvention::IntrinsicXyz);
    assert_close(
        "feedback pose",
        &bridge.feedback().unwrap().robot_from_ee,
        &initial,
        1e-6,
        1e-6,
    );
    let target = path_pose(&initial, 1.0);
    bridge.send(command(1, target, 0.0));
    wait_for("target reached", Duration::from_secs(2), || {
        emu.snapshot().pose.rotation.angle_to(&target.rotation) < 1e-3
    });
    drop(bridge);
    drop(emu);

    // Configured wrongly: reported, and nothing is sent.
    let emu = DobotEmulator::start(emu_cfg).unwrap();
    let mut config = bridge_config(&emu, Firmware::V4);
    config.euler_convention = Some(EulerConvention::ExtrinsicXyz);
    let bridge = DobotBridge::start(config).unwrap();
    wait_for(
        "convention error",
        Duration::from_secs(1),
        || matches!(bridge.health(), Health::Error(m) if m.contains("Euler convention")),
    );
    bridge.send(command(1, target, 0.0));
    std::thread::sleep(Duration::from_millis(80));
    assert_eq!(emu.snapshot().servo_commands, 0);
}

#[test]
fn gripper_over_modbus_http_and_tool_output() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let mut config = bridge_config(&emu, Firmware::V4);
    config.gripper = GripperOutput::ModbusHttp {
        port: emu.http_addr().port(),
        path: "/interface/toolDataExchange".into(),
        slave: 1,
        register: 0x0103,
        open_value: 1000,
        closed_value: 0,
    };
    let bridge = DobotBridge::start(config).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let start = bridge.feedback().unwrap().robot_from_ee;
    bridge.send(command(1, start, 1.0));
    wait_for("gripper closed", Duration::from_secs(2), || {
        emu.snapshot().gripper_register == Some(0)
    });
    wait_for("gripper feedback", Duration::from_secs(1), || {
        bridge.feedback().is_some_and(|f| f.gripper_position > 0.99)
    });
    bridge.send(command(2, start, 0.0));
    wait_for("gripper open", Duration::from_secs(2), || {
        emu.snapshot().gripper_register == Some(1000)
    });
    drop(bridge);

    let mut config = bridge_config(&emu, Firmware::V4);
    config.gripper = GripperOutput::ToolDo {
        index: 2,
        closed_high: true,
    };
    let bridge = DobotBridge::start(config).unwrap();
    bridge.send(command(1, start, 1.0));
    wait_for("tool output 2 high", Duration::from_secs(2), || {
        emu.snapshot().tool_outputs == 0b10
    });
    bridge.send(command(2, start, 0.0));
    wait_for("tool output 2 low", Duration::from_secs(2), || {
        emu.snapshot().tool_outputs == 0
    });
}

#[test]
fn disabled_robot_holds_and_enable_resumes() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let start = bridge.feedback().unwrap().robot_from_ee;
    bridge.control(Control::Disable).unwrap();
    wait_for(
        "not enabled",
        Duration::from_secs(1),
        || matches!(bridge.health(), Health::Error(m) if m.contains("not enabled")),
    );
    bridge.send(command(1, path_pose(&start, 0.5), 0.0));
    std::thread::sleep(Duration::from_millis(60));
    assert_eq!(emu.snapshot().servo_commands, 0);
    bridge.control(Control::Enable).unwrap();
    wait_for("ready", Duration::from_secs(1), || {
        bridge.health() == Health::Ready
    });
    bridge.send(command(2, path_pose(&start, 0.5), 0.0));
    wait_for("applied", Duration::from_secs(1), || {
        bridge.feedback().is_some_and(|f| f.applied_seq == 2)
    });
}

#[test]
fn non_finite_targets_are_dropped_without_a_command() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let mut bad = bridge.feedback().unwrap().robot_from_ee;
    bad.translation.vector.x = f64::NAN;
    bridge.send(command(1, bad, 0.0));
    wait_for("held", Duration::from_secs(1), || {
        bridge.stats().targets_held == 1
    });
    assert_eq!(emu.snapshot().servo_commands, 0);
    assert_eq!(bridge.health(), Health::Ready);
}

#[test]
fn start_fails_cleanly_when_nothing_listens() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let mut config = bridge_config(&emu, Firmware::V4);
    drop(emu);
    config.connect_timeout_s = 0.3;
    match DobotBridge::start(config) {
        Err(BridgeError::Connect { target, .. }) => assert!(target.starts_with("127.0.0.1:")),
        other => panic!("expected a connect error, got {other:?}"),
    }
}

#[test]
fn example_config_parses() {
    #[derive(serde::Deserialize)]
    struct Arm {
        bridge: String,
        dobot: DobotConfig,
        teleop: phone2act_core::TeleopConfig,
    }
    #[derive(serde::Deserialize)]
    struct File {
        arms: Vec<Arm>,
    }
    let text =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/dobot-cr5.toml")).unwrap();
    let file: File = toml::from_str(&text).unwrap();
    let arm = &file.arms[0];
    assert_eq!(arm.bridge, "dobot");
    arm.dobot.validate().unwrap();
    arm.teleop.validate().unwrap();
    assert!(
        arm.teleop.gate.workspace_max_m[0] <= 0.0,
        "the CR5 example must not use the SO-101 workspace"
    );
    assert_eq!(arm.dobot.effective_motion_port(), 29999);
}

/// A controller that answers a `\r\n` after a command as a command of its own (`-10000,{},;`). The default
/// configuration sends no terminator, as Dobot's clients do; one configured to send `\r\n` anyway has each
/// stray reply set aside by its echo, never read as the answer to the next command.
#[test]
fn a_controller_answering_stray_terminators_gets_no_reply_misattributed() {
    let emu = DobotEmulator::start(EmulatorConfig {
        answer_stray_terminator: true,
        ..EmulatorConfig::default()
    })
    .unwrap();

    // The default: nothing after the right parenthesis, so nothing stray to answer.
    let bridge = DobotBridge::start(bridge_config(&emu, Firmware::V4)).unwrap();
    assert_eq!(bridge.config().terminator, Terminator::None);
    assert_eq!(bridge.kind(), "dobot");
    assert!(bridge.supports_orientation());
    assert_eq!(bridge.warning(), None);
    assert!(
        emu.snapshot().received.iter().all(|c| !c.contains('\n')),
        "a command carried a line end"
    );
    assert_eq!(bridge.stats().replies_discarded, 0);
    bridge.shutdown();

    // `\r\n` configured: every stray answer is set aside, every command gets its own reply.
    let mut config = bridge_config(&emu, Firmware::V4);
    config.terminator = Terminator::Crlf;
    let bridge = DobotBridge::start(config).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let mode = bridge.dashboard("RobotMode()").unwrap();
    assert_eq!((mode.error_id, mode.values.clone()), (0, vec!["5".to_owned()]));
    assert_eq!(mode.echo, "RobotMode()");
    let start = bridge.feedback().unwrap().robot_from_ee;
    let (last_seq, last) = stream(&bridge, &start, 1, 30);
    wait_for("the last target applied", Duration::from_secs(2), || {
        bridge.feedback().is_some_and(|f| f.applied_seq == last_seq)
    });
    wait_for("the arm at the last target", Duration::from_secs(2), || {
        (emu.snapshot().pose.translation.vector - last.translation.vector).norm() < 1e-4
    });
    let stats = bridge.stats();
    assert_eq!(
        stats.servo_rejected, 0,
        "a stray reply was taken for a ServoP reply"
    );
    assert_eq!(stats.last_command_error, None);
    assert!(
        stats.replies_discarded >= stats.servo_sent,
        "{} stray replies set aside for {} ServoP sent",
        stats.replies_discarded,
        stats.servo_sent
    );
}

/// V4.6+ firmware takes commands over TCP only after `RequestControl()`; the bridge sends it before
/// enabling. Older V4 answers it as unknown, which the bridge reads as "not needed".
#[test]
fn request_control_is_sent_where_the_firmware_wants_it() {
    assert!(
        !DobotEmulator::start(EmulatorConfig::default())
            .unwrap()
            .snapshot()
            .tcp_control,
        "V4.6 starts without TCP control"
    );
    let (emu, bridge) = ready(EmulatorConfig::default());
    let snap = emu.snapshot();
    assert_eq!(snap.control_requests, 1);
    let position = |name: &str| snap.received.iter().position(|c| c.starts_with(name)).unwrap();
    assert!(position("RequestControl") < position("EnableRobot"));
    assert_eq!(bridge.stats().control_request, ControlRequest::Granted);
    bridge.shutdown();

    let (_older, bridge) = ready(EmulatorConfig {
        firmware_version: (4, 5),
        ..EmulatorConfig::default()
    });
    assert_eq!(bridge.stats().control_request, ControlRequest::NotSupported);
}

/// Without the control request, a V4.6 controller leaves `EnableRobot` unanswered: the bridge says so
/// within its enable timeout and keeps the link (no motion, nothing torn down).
#[test]
fn an_unanswered_enable_is_an_error_not_a_hang() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let mut config = bridge_config(&emu, Firmware::V4);
    config.request_control = false;
    config.enable_timeout_s = 0.3;
    let started = Instant::now();
    let bridge = DobotBridge::start(config).unwrap();
    // 0.3 s for the enable plus the connect steps; 5 s leaves room for a loaded machine.
    assert!(started.elapsed() < Duration::from_secs(5));
    wait_for(
        "an error naming EnableRobot",
        Duration::from_secs(2),
        || matches!(bridge.health(), Health::Error(m) if m.contains("EnableRobot")),
    );
    let before = emu.snapshot().servo_commands;
    bridge.send(command(1, tool_down(-0.38, 0.0, 0.35, 0.0), 0.0));
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(
        emu.snapshot().servo_commands,
        before,
        "a disabled robot was sent a target"
    );
}

/// `EnableRobot` answered after 1.5 s (longer than the 1 s reply timeout of other commands) neither fails
/// the start nor closes the link.
#[test]
fn a_slow_enable_robot_does_not_tear_the_link_down() {
    // 1.5 s: past the 1 s reply timeout of other commands, well inside the 10 s enable bound however
    // slowly this machine runs the bridge.
    let (_emu, bridge) = ready(EmulatorConfig {
        enable_delay: Duration::from_millis(1500),
        ..EmulatorConfig::default()
    });
    apply(&bridge, 5, 0.4);
    assert_eq!(bridge.stats().reconnects, 0);
}

/// An enable slower than the configured bound: an error of that command; its late reply, when it comes,
/// is set aside rather than taken for the ServoP sent after it.
#[test]
fn a_late_enable_reply_is_set_aside_not_taken_for_the_next_command() {
    let emu = DobotEmulator::start(EmulatorConfig {
        enable_delay: Duration::from_secs(2),
        ..EmulatorConfig::default()
    })
    .unwrap();
    // The reply cannot exist before 2 s; the bridge gives up after 0.1 s. Only a bridge thread stalled for
    // the 1.9 s between could still find it in time.
    let mut config = bridge_config(&emu, Firmware::V4);
    config.enable_timeout_s = 0.1;
    let bridge = DobotBridge::start(config).unwrap();
    assert!(matches!(bridge.health(), Health::Error(m) if m.contains("EnableRobot")));
    wait_for("the controller enabled late", Duration::from_secs(5), || {
        emu.snapshot().enabled
    });
    // Targets are dropped until the bridge's feedback shows the robot enabled.
    wait_for(
        "the bridge to see the robot enabled",
        Duration::from_secs(2),
        || !matches!(bridge.health(), Health::Error(m) if m.contains("not enabled")),
    );
    apply(&bridge, 9, 0.2);
    let stats = bridge.stats();
    assert_eq!(stats.replies_discarded, 1, "the late EnableRobot reply");
    assert_eq!(stats.servo_rejected, 0);
}

/// `GetErrorID` answers seven lists (controller, then J1..J6); health names the servo.
#[test]
fn a_servo_alarm_is_named_by_joint() {
    let (emu, bridge) = ready(EmulatorConfig::default());
    emu.inject_alarm(Some(3), 4368);
    wait_for(
        "an error naming J3's servo alarm",
        Duration::from_secs(2),
        || matches!(bridge.health(), Health::Error(m) if m.contains("J3 servo alarm 4368")),
    );
    let reply = bridge.dashboard("GetErrorID()").unwrap();
    let ids = ErrorIds::parse(&reply.values.join(",")).unwrap();
    assert_eq!(ids.servos[2], vec![4368]);
    assert!(ids.controller.is_empty());
}

/// `MovJ` is a queue command: its id comes back at once, the move takes its motion time.
#[test]
fn movj_answers_its_command_id_and_runs_for_its_motion_time() {
    let (emu, bridge) = ready(EmulatorConfig::default());
    // 100 mm at 25 % of 0.25 m/s (SpeedFactor 30 gives 0.075 m/s): well over a second.
    let reply = bridge.dashboard("MovJ(pose={-300,0,350,180,0,0})").unwrap();
    assert_eq!(reply.error_id, 0);
    let id: u64 = reply.values[0].parse().unwrap();
    let snap = emu.snapshot();
    assert_eq!(snap.current_command_id, id);
    assert_eq!(snap.mode.code(), 7, "running while the move lasts");
    assert!((snap.pose.translation.vector - snap.target.translation.vector).norm() > 0.05);
    let joint = bridge.dashboard("MovJ(joint={-30,0,35,180,0,0})").unwrap();
    assert_eq!(joint.values, vec![(id + 1).to_string()]);
    let positional = bridge.dashboard("MovJ(-300,0,350,180,0,0)").unwrap();
    assert!(positional.error_id < 0, "V4 wants pose= or joint=");
}

/// The gripper endpoint takes a POST to its path and nothing else.
#[test]
fn the_gripper_endpoint_refuses_a_wrong_method_or_path() {
    use phone2act_bridges::dobot::emulator::TOOL_DATA_EXCHANGE_PATH;
    use phone2act_bridges::dobot::gripper::{http_post_json, modbus_http_body, modbus_write_register};
    use std::io::{Read, Write};
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let port = emu.http_addr().port();
    let body = modbus_http_body(&modbus_write_register(1, 0x0103, 1000));
    let timeout = Duration::from_secs(2);
    assert_eq!(
        http_post_json("127.0.0.1", port, TOOL_DATA_EXCHANGE_PATH, &body, timeout).unwrap(),
        200
    );
    assert_eq!(
        http_post_json("127.0.0.1", port, "/interface/tooldata", &body, timeout).unwrap(),
        404
    );
    let mut get = std::net::TcpStream::connect(emu.http_addr()).unwrap();
    get.write_all(format!("GET {TOOL_DATA_EXCHANGE_PATH} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes())
        .unwrap();
    let mut response = String::new();
    get.read_to_string(&mut response).unwrap();
    assert!(response.starts_with("HTTP/1.1 405"), "{response}");
    assert_eq!(emu.snapshot().http_refused, 2);
    assert_eq!(emu.snapshot().gripper_register, Some(1000));
}
