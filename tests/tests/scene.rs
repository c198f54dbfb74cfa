//! The Scene service through the real server over real sockets: seeded resets of the simulated scene, the
//! home-arm teleport and who may ask for it, and the refusals (hardware arm, unknown arm).

use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{TeleopOptions, buttons};
use phone2act_server::config::CameraKind;
use phone2act_tests::operator::{self, OperatorOptions};
use phone2act_tests::{TestServer, arm_state, default_config, keep_for_conformance, pos, sim_pose_of};
use std::time::Duration;

fn ball_xy(state: &v1::SceneState) -> [f64; 2] {
    let p = state.ball_position_m.as_ref().expect("ball position");
    [p.x, p.y]
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_seed_names_a_scene_and_different_seeds_spread_over_the_area() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut scene = client.scene();

    let before = scene.get("main").await.unwrap();
    assert_eq!((before.resets, before.ball_state()), (0, v1::BallState::Resting));

    let first = scene.reset("main", Some(11), false).await.unwrap();
    let again = scene.reset("main", Some(11), false).await.unwrap();
    assert_eq!(first.seed, 11);
    assert_eq!(
        ball_xy(&first).map(f64::to_bits),
        ball_xy(&again).map(f64::to_bits),
        "same seed, same scene bit for bit"
    );
    assert_eq!(again.resets, first.resets + 1);
    // Without a seed: the one after the last used.
    let next = scene.reset("main", None, false).await.unwrap();
    assert_eq!(next.seed, 12);
    assert_ne!(
        ball_xy(&next).map(f64::to_bits),
        ball_xy(&first).map(f64::to_bits)
    );

    let area = first.ball_area_m.unwrap();
    let mut seen: Vec<[f64; 2]> = Vec::new();
    for seed in 100..120 {
        let state = scene.reset("main", Some(seed), false).await.unwrap();
        let [x, y] = ball_xy(&state);
        assert!(
            (area.x_min_m..=area.x_max_m).contains(&x) && (area.y_min_m..=area.y_max_m).contains(&y),
            "seed {seed}: ({x}, {y}) outside {area:?}"
        );
        // At rest on the table: the centre one radius above it.
        let z = state.ball_position_m.unwrap().z;
        assert!((z - state.ball_radius_m).abs() < 1e-12, "{z}");
        assert_eq!(state.ball_state(), v1::BallState::Resting);
        assert!(!state.success);
        assert!(
            seen.iter().all(|p| (p[0] - x).hypot(p[1] - y) > 1e-9),
            "seed {seed} repeats a scene"
        );
        seen.push([x, y]);
    }
    // Twenty draws cover the area rather than bunching in a corner: each half of each axis gets some. Fails
    // only if the generator or the scaling were broken (chance of an honest miss: 4 x 2^-20).
    let mid_x = f64::midpoint(area.x_min_m, area.x_max_m);
    let mid_y = f64::midpoint(area.y_min_m, area.y_max_m);
    assert!(seen.iter().any(|p| p[0] < mid_x) && seen.iter().any(|p| p[0] > mid_x));
    assert!(seen.iter().any(|p| p[1] < mid_y) && seen.iter().any(|p| p[1] > mid_y));
    // The arm state carries the same success flag.
    assert!(!arm_state(&client, "main").await.task_success);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn homing_is_refused_while_a_phone_drives_and_a_phone_engaging_afterwards_does_not_jump() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let home = sim_pose_of(&client, "main").await;

    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let origin = v1::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 1.0]);
    let seq = phone
        .send_pose(origin, vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    assert!(phone.feedback_for(seq).await.unwrap().error.is_empty());
    // Phone 4 cm along its x in 1 cm steps: the arm moves away from home.
    for i in 1..=4 {
        let p = v1::Pose::from_parts([0.01 * f64::from(i), 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]);
        let seq = phone.send_pose(p, vec![], 0).await.unwrap();
        phone.feedback_for(seq).await.unwrap();
    }
    // The sim's joints settle within a few 50 ms time constants; 400 ms leaves room for a loaded machine,
    // and the check below only needs the arm to have moved at all.
    tokio::time::sleep(Duration::from_millis(400)).await;
    let moved = sim_pose_of(&client, "main").await;
    assert!(dist(moved, home) > 0.02, "{moved:?} vs {home:?}");
    let resets = client.scene().get("main").await.unwrap().resets;

    let refused = client.scene().reset("main", Some(5), true).await.unwrap_err();
    let phone2act_sdk::Error::Status(status) = refused else {
        panic!("{refused}")
    };
    assert_eq!(status.code(), tonic::Code::FailedPrecondition, "{status:?}");
    assert!(status.message().contains("phone"), "{}", status.message());
    // Nothing changed: no reset counted, the arm where it was.
    assert_eq!(client.scene().get("main").await.unwrap().resets, resets);
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(dist(sim_pose_of(&client, "main").await, moved) < 2e-3);

    // Released, the same request homes the arm.
    let seq = phone
        .send_buttons(vec![buttons::clutch_disengage()])
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();
    let state = client.scene().reset("main", Some(5), true).await.unwrap();
    assert_eq!((state.seed, state.resets), (5, resets + 1));
    let homed = sim_pose_of(&client, "main").await;
    assert!(dist(homed, home) < 1e-6, "a teleport: {homed:?} vs {home:?}");
    let target = arm_state(&client, "main").await.robot_from_target.unwrap();
    assert!(
        dist(pos(&target), home) < 1e-6,
        "the held target is the homed pose"
    );

    // Engaging again from where the phone now is (4 cm out) re-indexes there: the arm stays home.
    let far = v1::Pose::from_parts([0.04, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]);
    let seq = phone
        .send_pose(far, vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    assert!(phone.feedback_for(seq).await.unwrap().error.is_empty());
    let seq = phone.send_pose(far, vec![], 0).await.unwrap();
    phone.feedback_for(seq).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let after = sim_pose_of(&client, "main").await;
    assert!(
        dist(after, home) < 2e-3,
        "engaging after a home moved the arm: {after:?}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn homing_is_refused_while_a_policy_drives_but_the_ball_may_be_reset() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let policy = client
        // A 30 s silence timeout: long enough that the session keeps the arm through the calls below on a
        // loaded machine.
        .policy(phone2act_tests::policy_hello(&["main"], "evaluator", 30.0))
        .await
        .unwrap();
    let result = client.scene().reset("main", Some(9), true).await;
    let Err(phone2act_sdk::Error::Status(status)) = result else {
        panic!("{result:?}")
    };
    assert_eq!(status.code(), tonic::Code::FailedPrecondition);
    assert!(
        status.message().contains("policy \"evaluator\""),
        "{}",
        status.message()
    );
    // Without the teleport the scene can be redrawn under a running policy (an evaluation between trials).
    let state = client.scene().reset("main", Some(9), false).await.unwrap();
    assert_eq!(state.seed, 9);
    assert_eq!(
        arm_state(&client, "main").await.owner(),
        v1::ControlSource::Policy
    );
    drop(policy);
    server.shutdown().await.unwrap();
}

/// One scripted pick-and-place (the operator, through the phone path) into a v2.1 dataset: afterwards the
/// scene reports the ball in the basket, the arm state agrees, and the dataset goes to the conformance check.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_scripted_pick_and_place_the_scene_reports_success() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.recorder.format = phone2act_server::config::DatasetFormat::V21;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let options = OperatorOptions {
        episodes: 1,
        seed: 77,
        // An episode takes about 6 s; 60 s leaves room for an unoptimised build on a loaded 2-core machine.
        episode_time_s: 60.0,
        reset_time_s: 0.0,
        ..OperatorOptions::default()
    };
    let summary = operator::run(&client, &options, |_| {}, |_, _, _| {})
        .await
        .unwrap();
    assert_eq!((summary.succeeded, summary.saved), (1, 1), "{summary:?}");
    let scene = client.scene().get("main").await.unwrap();
    assert!(scene.success);
    assert_eq!((scene.seed, scene.ball_state()), (77, v1::BallState::InBasket));
    let ball = scene.ball_position_m.unwrap();
    let basket = scene.basket_position_m.unwrap();
    assert!(
        (ball.x - basket.x).hypot(ball.y - basket.y) <= scene.basket_radius_m - scene.ball_radius_m,
        "{ball:?} vs {basket:?}"
    );
    assert!(arm_state(&client, "main").await.task_success);
    // A new scene is not a success until it is done again.
    let next = client.scene().reset("main", None, false).await.unwrap();
    assert_eq!((next.seed, next.success), (78, false));
    server.shutdown().await.unwrap();
    keep_for_conformance("scene_operator_v21", dir.path());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_arm_is_not_found() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    for result in [
        client.scene().reset("ghost", None, false).await,
        client.scene().get("ghost").await,
    ] {
        let Err(phone2act_sdk::Error::Status(status)) = result else {
            panic!("{result:?}")
        };
        assert_eq!(status.code(), tonic::Code::NotFound);
        assert!(
            status.message().contains("ghost") && status.message().contains("main"),
            "{status:?}"
        );
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hardware_arm_has_no_scene_to_reset() {
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../server/config/dobot-cr5.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let mut config = phone2act_server::Config::from_toml_str(&text, path, Vec::new()).unwrap();
    let dobot = config.arms[0].dobot.as_mut().unwrap();
    "127.0.0.1".clone_into(&mut dobot.host);
    dobot.dashboard_port = emu.dashboard_addr().port();
    dobot.feedback_port = emu.feedback_addr().port();
    for cam in &mut config.cameras {
        (cam.kind, cam.width, cam.height, cam.fps) = (CameraKind::TestPattern, 64, 64, 5.0);
    }
    dir.path().clone_into(&mut config.recorder.root);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let before = emu.snapshot();

    let result = client.scene().reset("main", Some(1), true).await;
    let Err(phone2act_sdk::Error::Status(status)) = result else {
        panic!("{result:?}")
    };
    assert_eq!(status.code(), tonic::Code::Unimplemented);
    assert!(
        status
            .message()
            .contains("scene reset is not supported by the dobot bridge"),
        "{}",
        status.message()
    );
    let result = client.scene().get("main").await;
    let Err(phone2act_sdk::Error::Status(status)) = result else {
        panic!("{result:?}")
    };
    assert_eq!(status.code(), tonic::Code::Unimplemented);
    // Nothing was sent to the robot.
    assert_eq!(emu.snapshot().servo_commands, before.servo_commands);
    server.shutdown().await.unwrap();
}
