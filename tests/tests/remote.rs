//! Out-of-process bridges (Bridge.Attach) and pushed cameras (Cameras.Push) end to end.

use phone2act_proto::v1::bridge_client::BridgeClient;
use phone2act_proto::v1::cameras_client::CamerasClient;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{TeleopOptions, buttons};
use phone2act_server::Config;
use phone2act_tests::bridge::{self, upstream};
use phone2act_tests::{TestServer, pos};
use std::time::Duration;
use tokio_stream::StreamExt;

const CONFIG: &str = r#"
[[arms]]
name = "ext"
bridge = "remote"
[arms.remote]
joint_names = ["a", "b", "c"]

[[arms]]
name = "sim"
bridge = "sim"

[[cameras]]
name = "pushed"
kind = "remote"
width = 64
height = 64
fps = 30
"#;

fn config(dir: &std::path::Path) -> Config {
    let mut c = Config::from_toml_str(CONFIG, "remote-test", Vec::new()).unwrap();
    dir.clone_into(&mut c.recorder.root);
    c
}

fn feedback(pose: v1::Pose, applied_seq: u64) -> v1::BridgeUpstream {
    upstream(v1::bridge_upstream::Message::Feedback(v1::RobotFeedback {
        capture_time_ns: 0,
        joint_positions_rad: vec![0.1, 0.2, 0.3],
        robot_from_ee: Some(pose),
        gripper_position: 0.0,
        applied_seq,
    }))
}

/// A server with the test config, and a channel to it.
async fn start() -> (tempfile::TempDir, TestServer, tonic::transport::Channel) {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(config(dir.path())).await.unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    (dir, server, channel)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_bridge_receives_gated_commands_and_its_feedback_is_the_arm_state() {
    let (_dir, server, channel) = start().await;
    let mut bridge = BridgeClient::new(channel.clone());

    // Wrong arm and wrong joints are refused with clear statuses.
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(upstream(v1::bridge_upstream::Message::Hello(v1::BridgeHello {
        arm: "sim".into(),
        joint_names: vec!["a".into()],
        ..v1::BridgeHello::default()
    })))
    .await
    .unwrap();
    let err = bridge
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::NotFound, "{err}");
    assert!(err.message().contains("ext"), "{err}");
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(upstream(v1::bridge_upstream::Message::Hello(v1::BridgeHello {
        arm: "ext".into(),
        joint_names: vec!["x".into(), "y".into()],
        ..v1::BridgeHello::default()
    })))
    .await
    .unwrap();
    let err = bridge
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err}");

    // A well-behaved bridge: hello, then feedback at a start pose.
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(upstream(v1::bridge_upstream::Message::Hello(v1::BridgeHello {
        arm: "ext".into(),
        bridge_name: "test".into(),
        joint_names: vec!["a".into(), "b".into(), "c".into()],
        supports_orientation: true,
        ..v1::BridgeHello::default()
    })))
    .await
    .unwrap();
    let mut down = bridge
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    match down.next().await.unwrap().unwrap().message {
        Some(v1::bridge_downstream::Message::Welcome(w)) => assert_eq!(w.arm, "ext"),
        other => panic!("expected welcome, got {other:?}"),
    }
    let start = v1::Pose::from_parts([0.2, 0.05, 0.1], [0.0, 0.0, 0.0, 1.0]);
    tx.send(feedback(start, 0)).await.unwrap();
    // The bridge follows every command at once and reports it back.
    let echo_tx = tx.clone();
    let last_seq = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let seen = std::sync::Arc::clone(&last_seq);
    let echo = tokio::spawn(async move {
        while let Some(msg) = down.next().await {
            let msg = match msg {
                Ok(m) => m,
                Err(status) => return Some(status),
            };
            if let Some(v1::bridge_downstream::Message::Command(c)) = msg.message {
                let _ = echo_tx.send(feedback(c.robot_from_target.unwrap(), c.seq)).await;
                seen.store(c.seq, std::sync::atomic::Ordering::Relaxed);
            }
        }
        None
    });
    let client = server.client().await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let arm = phone2act_tests::arm_state(&client, "ext").await;
    assert_eq!(arm.joint_names, ["a", "b", "c"]);
    assert!((pos(arm.robot_from_ee.as_ref().unwrap())[1] - 0.05).abs() < 1e-9);

    let mut phone = client.teleop("ext", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 1.0]),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();
    for i in 1..=4 {
        // Phone forward (-Z) 1 cm per sample.
        let seq = phone
            .send_pose(
                v1::Pose::from_parts([0.0, 0.0, -0.01 * f64::from(i)], [0.0, 0.0, 0.0, 1.0]),
                vec![],
                0,
            )
            .await
            .unwrap();
        phone.feedback_for(seq).await.unwrap();
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let arm = phone2act_tests::arm_state(&client, "ext").await;
    let ee = pos(arm.robot_from_ee.as_ref().unwrap());
    assert!(
        (ee[0] - 0.24).abs() < 1e-6,
        "the remote robot should be 4 cm forward: {ee:?}"
    );
    assert!(arm.commands_sent >= 4);

    assert!(last_seq.load(std::sync::atomic::Ordering::Relaxed) >= 4);
    // Bad feedback (NaN pose) is not ignored: the bridge's stream ends with INVALID_ARGUMENT saying why,
    // and the arm is disconnected (it holds; nothing moves it until a bridge attaches and measures again).
    tx.send(feedback(
        v1::Pose::from_parts([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
        99,
    ))
    .await
    .unwrap();
    let status = tokio::time::timeout(Duration::from_secs(10), echo)
        .await
        .expect("the bridge stream ends")
        .unwrap()
        .expect("with a status, not OK");
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status}");
    assert!(status.message().contains("not finite"), "{status}");
    drop(tx);
    drop(phone);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let arm = phone2act_tests::arm_state(&client, "ext").await;
    assert_eq!(arm.health(), v1::BridgeHealth::Disconnected, "{arm:?}");
    server.shutdown().await.unwrap();
}

fn frame(camera: &str, w: u32, h: u32, seq: u64) -> v1::CameraFrame {
    v1::CameraFrame {
        camera: camera.into(),
        width: w,
        height: h,
        encoding: v1::ImageEncoding::Rgb8 as i32,
        data: vec![(seq % 255) as u8; (w * h * 3) as usize],
        capture_time_ns: 0,
        frame_seq: seq,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pushed_frames_fill_a_remote_camera_and_bad_frames_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(config(dir.path())).await.unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut cameras = CamerasClient::new(channel).max_encoding_message_size(64 << 20);

    let frames: Vec<_> = (0..10).map(|i| frame("pushed", 64, 64, i)).collect();
    let summary = cameras
        .push(tokio_stream::iter(frames))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (
            summary.camera.as_str(),
            summary.frames_accepted,
            summary.frames_rejected
        ),
        ("pushed", 10, 0)
    );
    let client = server.client().await.unwrap();
    let cams = client.system().list_cameras().await.unwrap();
    assert_eq!(cams[0].frames_captured, 10);

    let err = cameras
        .push(tokio_stream::iter(vec![frame("pushed", 32, 64, 0)]))
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument);
    assert!(err.message().contains("64x64"), "{err}");
    let err = cameras
        .push(tokio_stream::iter(vec![frame("nope", 64, 64, 0)]))
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::NotFound, "{err}");
    // A 10 MB frame is refused by the transport limit, and the camera keeps working afterwards.
    let mut huge = frame("pushed", 64, 64, 0);
    huge.data = vec![0; 10 << 20];
    let err = cameras.push(tokio_stream::iter(vec![huge])).await.unwrap_err();
    assert!(
        matches!(
            err.code(),
            tonic::Code::OutOfRange | tonic::Code::ResourceExhausted | tonic::Code::Internal
        ),
        "{err}"
    );
    let summary = cameras
        .push(tokio_stream::iter(vec![frame("pushed", 64, 64, 11)]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(summary.frames_accepted, 1);
    server.shutdown().await.unwrap();
}

/// Attaches a bridge for "ext" that declares a scene; returns its streams once welcomed.
async fn attach_with_scene(
    channel: tonic::transport::Channel,
) -> (
    tokio::sync::mpsc::Sender<v1::BridgeUpstream>,
    tonic::Streaming<v1::BridgeDownstream>,
) {
    let hello = v1::BridgeHello {
        arm: "ext".into(),
        joint_names: vec!["a".into(), "b".into(), "c".into()],
        has_scene: true,
        ..v1::BridgeHello::default()
    };
    let (tx, mut down) = bridge::attach(channel, hello, 16).await.unwrap();
    assert!(matches!(
        down.next().await.unwrap().unwrap().message,
        Some(v1::bridge_downstream::Message::Welcome(_))
    ));
    (tx, down)
}

/// A remote bridge that declares a scene answers Scene.Get and Scene.Reset over its own stream, as the
/// built-in simulator answers them in process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_bridge_with_a_scene_answers_the_scene_api() {
    let (_dir, server, channel) = start().await;
    let client = server.client().await.unwrap();
    let mut scene = client.scene();
    // Before any bridge declares one, the remote arm has no scene.
    let err = scene.get("ext").await.unwrap_err();
    assert!(
        err.to_string().contains("UNIMPLEMENTED") || format!("{err:?}").contains("Unimplemented"),
        "{err:?}"
    );

    let state = |seed: u64, success: bool| v1::SceneState {
        seed,
        ball_position_m: Some(v1::Vec3::new(0.2, 0.01 * seed as f64, 0.02)),
        ball_state: v1::BallState::Resting as i32,
        ball_radius_m: 0.012,
        basket_position_m: Some(v1::Vec3::new(0.25, 0.1, 0.0)),
        basket_radius_m: 0.045,
        basket_height_m: 0.035,
        success,
        resets: seed,
        ..v1::SceneState::default()
    };
    let scene_report = |s: v1::SceneState, answers: u64, error: &str| {
        upstream(v1::bridge_upstream::Message::Scene(v1::BridgeScene {
            state: Some(s),
            reset_request_id: answers,
            error: error.into(),
        }))
    };
    let (tx, mut down) = attach_with_scene(channel).await;
    let start = v1::Pose::from_parts([0.2, 0.05, 0.1], [0.0, 0.0, 0.0, 1.0]);
    tx.send(feedback(start, 0)).await.unwrap();
    tx.send(scene_report(state(0, false), 0, "")).await.unwrap();

    // The bridge side: answers seed 5 with its scene (success set, to see it reach the arm) and refuses seed 6.
    let answer_tx = tx.clone();
    let bridge = tokio::spawn(async move {
        let mut resets = Vec::new();
        while let Some(Ok(msg)) = down.next().await {
            if let Some(v1::bridge_downstream::Message::SceneReset(r)) = msg.message {
                resets.push(r);
                let seed = r.seed.unwrap_or(0);
                let error = if seed == 6 { "no scene for seed 6" } else { "" };
                answer_tx.send(feedback(start, 0)).await.unwrap();
                answer_tx
                    .send(scene_report(state(seed, seed == 5), r.request_id, error))
                    .await
                    .unwrap();
                if resets.len() == 2 {
                    return resets;
                }
            }
        }
        resets
    });
    // The first report arrives with the stream's next messages; a loaded machine may take a moment.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    let got = loop {
        match scene.get("ext").await {
            Ok(s) => break s,
            Err(_) if tokio::time::Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => panic!("no scene from the bridge: {e:?}"),
        }
    };
    assert_eq!((got.arm.as_str(), got.seed, got.success), ("ext", 0, false));

    let reset = scene.reset("ext", Some(5), true).await.unwrap();
    assert_eq!((reset.seed, reset.success), (5, true));
    assert!((reset.ball_position_m.unwrap().y - 0.05).abs() < 1e-12);
    assert_eq!(scene.get("ext").await.unwrap().seed, 5);
    // The scene's success is the arm's.
    let arm = phone2act_tests::arm_state(&client, "ext").await;
    assert!(arm.task_success, "{arm:?}");
    // A refused reset fails with the bridge's reason; the scene is what the bridge reports (seed 6, no success).
    let err = scene.reset("ext", Some(6), false).await.unwrap_err();
    assert!(format!("{err:?}").contains("no scene for seed 6"), "{err:?}");
    let resets = bridge.await.unwrap();
    assert_eq!(
        resets.iter().map(|r| (r.seed, r.home_arm)).collect::<Vec<_>>(),
        [(Some(5), true), (Some(6), false)]
    );
}

/// A remote bridge may take its time to re-draw its scene (up to the server's 10 s answer limit). Meanwhile the
/// arm's sources are served: a phone driving the arm is answered while the bridge still holds the reset. The
/// bridge here answers only after the phone's round came back, so an arm locked across the wait would leave
/// the round waiting for the reset's 10 s timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_remote_scene_reset_does_not_hold_up_the_phone() {
    let (_dir, server, channel) = start().await;
    let client = server.client().await.unwrap();
    let (tx, mut down) = attach_with_scene(channel).await;
    let start = v1::Pose::from_parts([0.2, 0.05, 0.1], [0.0, 0.0, 0.0, 1.0]);
    let scene = |request_id: u64| {
        upstream(v1::bridge_upstream::Message::Scene(v1::BridgeScene {
            state: Some(v1::SceneState {
                seed: request_id,
                ball_position_m: Some(v1::Vec3::new(0.2, 0.0, 0.02)),
                ball_state: v1::BallState::Resting as i32,
                ball_radius_m: 0.012,
                basket_position_m: Some(v1::Vec3::new(0.25, 0.1, 0.0)),
                basket_radius_m: 0.045,
                basket_height_m: 0.035,
                ..v1::SceneState::default()
            }),
            reset_request_id: request_id,
            error: String::new(),
        }))
    };
    tx.send(scene(0)).await.unwrap();
    // The bridge: fresh feedback every 20 ms (the arm stays ready), and the reset's answer only when told.
    let (answer_now, mut answer) = tokio::sync::oneshot::channel::<()>();
    let (reset_seen, seen) = tokio::sync::oneshot::channel::<u64>();
    let bridge_tx = tx.clone();
    let bridge = tokio::spawn(async move {
        let mut reset_seen = Some(reset_seen);
        let mut pending = None;
        let mut ticker = tokio::time::interval(Duration::from_millis(20));
        loop {
            tokio::select! {
                _ = ticker.tick() => {
                    bridge_tx.send(feedback(start, 0)).await.unwrap();
                }
                msg = down.next() => match msg {
                    Some(Ok(v1::BridgeDownstream { message: Some(v1::bridge_downstream::Message::SceneReset(r)) })) => {
                        pending = Some(r.request_id);
                        if let Some(s) = reset_seen.take() {
                            s.send(r.request_id).unwrap();
                        }
                    }
                    Some(Ok(_)) => {}
                    _ => return,
                },
                Ok(()) = &mut answer, if pending.is_some() => {
                    bridge_tx.send(scene(pending.take().unwrap())).await.unwrap();
                }
            }
        }
    });
    // The arm is ready once its feedback is in (10 s covers a stalled machine).
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(10), || async {
            phone2act_tests::arm_state(&client, "ext")
                .await
                .robot_from_ee
                .is_some()
        })
        .await
    );
    let mut phone = client.teleop("ext", TeleopOptions::default()).await.unwrap();
    let pose = v1::Pose::from_parts([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]);
    let seq = phone
        .send_pose(pose, vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();

    let mut scenes = client.scene();
    let reset = tokio::spawn(async move { scenes.reset("ext", Some(3), false).await });
    let request_id = seen.await.unwrap();
    // The reset waits for the bridge. A phone round now must not wait for it: 5 s is far beyond a round's few
    // milliseconds on a loaded machine and well under the reset's 10 s limit that a locked arm would wait for.
    let moved = v1::Pose::from_parts([0.0, 0.01, 0.0], [0.0, 0.0, 0.0, 1.0]);
    // (Timed with a clock read too: a server blocked on the arm would block this runtime's timers with it.)
    let started = std::time::Instant::now();
    let round = tokio::time::timeout(Duration::from_secs(5), async {
        let seq = phone.send_pose(moved, vec![], 0).await.unwrap();
        phone.feedback_for(seq).await.unwrap()
    })
    .await
    .expect("the phone's round waited for the scene reset");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "the phone's round took {:?}: it waited for the scene reset",
        started.elapsed()
    );
    assert!(round.error.is_empty(), "{}", round.error);
    assert!(!reset.is_finished(), "the bridge has not answered the reset yet");
    answer_now.send(()).unwrap();
    // The bridge's answer (its scene reports the request it answers as its seed) is the reset's.
    let state = reset.await.unwrap().unwrap();
    assert_eq!(state.seed, request_id);
    bridge.abort();
}
