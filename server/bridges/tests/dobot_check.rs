//! `dobot-check` against the emulated controller on loopback TCP.

use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
use std::process::Command;

fn run_check(emu: &DobotEmulator, extra: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dobot-check"))
        .args(["--host", "127.0.0.1"])
        .args(["--dashboard-port", &emu.dashboard_addr().port().to_string()])
        .args(["--feedback-port", &emu.feedback_addr().port().to_string()])
        .args(["--http-port", &emu.http_addr().port().to_string()])
        .args(extra)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    (out.status.success(), text)
}

#[test]
fn a_healthy_controller_passes_and_its_firmware_generation_is_named() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let (ok, text) = run_check(&emu, &["--request-control", "--gripper-test"]);
    assert!(ok, "{text}");
    for line in [
        "OK   RobotMode() without a terminator answered with its own echo",
        "OK   robot mode Disabled (4)",
        "OK   a trailing \\r\\n is ignored",
        "OK   RequestControl() granted: firmware V4.6 or newer",
        "OK   GetErrorID(): no alarms",
        "OK   robot type 5 (CR5)",
        "answered 200",
    ] {
        assert!(text.contains(line), "missing {line:?} in\n{text}");
    }
    assert!(text.lines().last().unwrap().starts_with("OK ("), "{text}");
    assert_eq!(
        emu.snapshot().gripper_register,
        Some(0),
        "the test closed the gripper last"
    );

    let older = DobotEmulator::start(EmulatorConfig {
        firmware_version: (4, 5),
        ..EmulatorConfig::default()
    })
    .unwrap();
    let (ok, text) = run_check(&older, &["--request-control"]);
    assert!(ok, "{text}");
    assert!(text.contains("firmware older than V4.6"), "{text}");
}

#[test]
fn alarms_and_a_controller_answering_stray_line_ends_are_reported() {
    let emu = DobotEmulator::start(EmulatorConfig {
        answer_stray_terminator: true,
        ..EmulatorConfig::default()
    })
    .unwrap();
    emu.inject_alarm(Some(3), 4368);
    let (ok, text) = run_check(&emu, &[]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("WARN the controller answers a stray \\r\\n"),
        "{text}"
    );
    assert!(text.contains("FAIL robot mode Error (9)"), "{text}");
    assert!(text.contains("FAIL GetErrorID(): J3 servo alarm 4368"), "{text}");
    assert!(text.contains("SKIP RequestControl()"), "{text}");
    assert!(text.lines().last().unwrap().starts_with("NOT READY"), "{text}");
    assert_eq!(emu.snapshot().servo_commands, 0);
    assert!(!emu.snapshot().enabled, "the check enabled the robot");
}
