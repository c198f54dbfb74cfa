//! The shipped Dobot CR5 configuration, pointed at the Dobot controller emulator, through the real server:
//! a phone drives the emulated robot, its feedback is the arm state, and an episode records it.

use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
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
