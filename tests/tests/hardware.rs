//! The shipped hardware configurations, pointed at the robots' emulators, through the real server: a phone
//! drives the emulated CR5, its feedback is the arm state, and an episode records it; an SO-101 whose
//! gripper latches an overload keeps recording, and the episode's events say so.

use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
use phone2act_bridges::feetech::FeetechEmulator;
use phone2act_bridges::feetech::protocol::alarm;
use phone2act_bridges::so101::calibration::Calibration;
use phone2act_dataset::events::{EventKind, read_events};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{TeleopOptions, buttons};
use phone2act_server::Config;
use phone2act_server::config::CameraKind;
use phone2act_tests::{TestServer, keep_for_conformance, pos};
use std::time::Duration;

fn dobot_config(emu: &DobotEmulator, dataset: &std::path::Path) -> Config {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../server/config/dobot-cr5.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let mut config = Config::from_toml_str(&text, path, Vec::new()).unwrap();
    let dobot = config.arms[0].dobot.as_mut().unwrap();
    "127.0.0.1".clone_into(&mut dobot.host);
    dobot.dashboard_port = emu.dashboard_addr().port();
    dobot.feedback_port = emu.feedback_addr().port();
    // No webcam here: a synthetic camera stands in for /dev/video0.
    for cam in &mut config.cameras {
        (cam.kind, cam.width, cam.height, cam.fps) = (CameraKind::TestPattern, 160, 128, 15.0);
    }
    dataset.clone_into(&mut config.recorder.root);
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_phone_drives_the_emulated_cr5_and_an_episode_records_it() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dobot_config(&emu, dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut start = None;
    for _ in 0..100 {
        let arm = client.system().list_arms().await.unwrap().remove(0);
        if let (v1::BridgeHealth::Ready, Some(pose)) = (arm.health(), arm.robot_from_ee.as_ref()) {
            start = Some(pos(pose));
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let start = start.expect("the CR5 bridge reports ready with feedback");
    assert!(
        (start[0] + 0.40).abs() < 1e-3 && (start[2] - 0.35).abs() < 1e-3,
        "{start:?}"
    );

    client.episodes().start("wave the CR5").await.unwrap();
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 1.0]),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();
    // Phone 5 cm up (+Y in the WebXR frame) in 1 cm steps: the landscape preset maps it to robot +z,
    // scaled by 0.9 as the CR5 config says.
    for i in 1..=5 {
        let seq = phone
            .send_pose(
                v1::Pose::from_parts([0.0, 0.01 * f64::from(i), 0.0], [0.0, 0.0, 0.0, 1.0]),
                vec![],
                0,
            )
            .await
            .unwrap();
        let fb = phone.feedback_for(seq).await.unwrap();
        assert!(fb.error.is_empty(), "{}", fb.error);
        tokio::time::sleep(Duration::from_millis(40)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let arm = client.system().list_arms().await.unwrap().remove(0);
    let now = pos(arm.robot_from_ee.as_ref().unwrap());
    assert!(
        (now[2] - start[2] - 0.045).abs() < 0.003,
        "emulated CR5 rose {} m",
        now[2] - start[2]
    );
    assert!(arm.commands_sent >= 5);

    let saved = client.episodes().stop().await.unwrap().episode.unwrap();
    assert!(saved.length_frames >= 5, "{saved:?}");
    server.shutdown().await.unwrap();
    keep_for_conformance("dobot_cr5_v30", dir.path());
}

/// The shipped bimanual SO-101 configuration's left arm on an emulated bus, with a calibration whose every
/// range is the full turn (no homing offset): raw 2047 is each joint's zero.
fn so101_config(emu: &FeetechEmulator, dir: &std::path::Path) -> Config {
    let calibration = Calibration::so101_with_ranges([(0, 4095); 6]);
    let calibration_path = dir.join("left_follower.json");
    calibration.save(&calibration_path).unwrap();
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../server/config/bimanual-so101.toml"
    );
    let text = std::fs::read_to_string(path).unwrap();
    let mut config = Config::from_toml_str(&text, path, Vec::new()).unwrap();
    config.arms.truncate(1);
    let so101 = config.arms[0].so101.as_mut().unwrap();
    emu.port_path().to_str().unwrap().clone_into(&mut so101.port);
    so101.calibration_file = calibration_path;
    // The emulator's thread must be scheduled within it on a loaded machine; the shipped 20 ms is for a
    // real bus.
    so101.timeout_ms = 200;
    for cam in &mut config.cameras {
        (cam.kind, cam.width, cam.height, cam.fps) = (CameraKind::TestPattern, 160, 128, 15.0);
    }
    dir.join("dataset").clone_into(&mut config.recorder.root);
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_so101_gripper_overload_during_an_episode_is_a_robot_warning_event_and_recording_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let emu = FeetechEmulator::start(&(1..=6).map(|id| (id, 2047)).collect::<Vec<_>>()).unwrap();
    let server = TestServer::start(so101_config(&emu, dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let ready = |arm: &v1::ArmState| arm.health() == v1::BridgeHealth::Ready && arm.robot_from_ee.is_some();
    let mut arm = client.system().list_arms().await.unwrap().remove(0);
    for _ in 0..200 {
        if ready(&arm) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        arm = client.system().list_arms().await.unwrap().remove(0);
    }
    assert!(
        ready(&arm),
        "the SO-101 bridge reports ready with feedback: {arm:?}"
    );

    client.episodes().start("squeeze the sponge").await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    // The gripper closes on an object and its servo latches overload: a warning, not a stop.
    emu.latch_alarm(6, alarm::OVERLOAD);
    tokio::time::sleep(Duration::from_millis(800)).await;
    let arm = client.system().list_arms().await.unwrap().remove(0);
    assert_eq!(arm.health(), v1::BridgeHealth::Ready, "{arm:?}");
    // The gripper lets go.
    emu.clear_alarm(6);
    tokio::time::sleep(Duration::from_millis(800)).await;
    let saved = client.episodes().stop().await.unwrap().episode.unwrap();
    // 2.1 s at the recorder's 20 fps, less what a loaded machine delays; the arm never stopped recording.
    assert!(saved.length_frames >= 20, "{saved:?}");
    server.shutdown().await.unwrap();

    let events = read_events(&dir.path().join("dataset"), 0).unwrap().unwrap();
    let warnings: Vec<_> = events
        .iter()
        .filter(|e| matches!(e.kind, EventKind::RobotWarning | EventKind::RobotWarningCleared))
        .collect();
    assert_eq!(warnings.len(), 2, "{events:?}");
    assert_eq!(warnings[0].kind, EventKind::RobotWarning);
    assert!(
        warnings[0].detail.contains("servo 6 (gripper)") && warnings[0].detail.contains("overload"),
        "{:?}",
        warnings[0]
    );
    assert_eq!(warnings[1].kind, EventKind::RobotWarningCleared);
    assert_eq!(warnings[1].detail, warnings[0].detail);
    assert!(warnings[0].frame_index > 0 && warnings[1].frame_index > warnings[0].frame_index);
    assert_eq!(warnings[0].arm, "left");
}
