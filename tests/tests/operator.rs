//! The scripted operator end to end: a real in-process server (simulated arm, rendered camera), the
//! operator driving it through `Teleop.Stream` as a phone does, episodes saved only when the ball ends in
//! the basket, and the dataset read back.

use phone2act_dataset::parquet_io::read_rows;
use phone2act_tests::operator::{self, OperatorOptions};
use phone2act_tests::{TestServer, default_config, keep_for_conformance};

/// Every frame row of the dataset at `root`, read back with the recorder's own parquet reader.
fn dataset_rows(root: &std::path::Path) -> Vec<phone2act_dataset::parquet_io::Row> {
    let mut files: Vec<_> = std::fs::read_dir(root.join("data/chunk-000"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files.iter().flat_map(|f| read_rows(f).unwrap()).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operator_records_two_successful_episodes_through_the_phone_path() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let options = OperatorOptions {
        episodes: 2,
        seed: 500,
        // Generous: an episode takes about 6 s; an unoptimised server on a loaded 2-core machine can run the
        // sim and the recorder several times slower, and a slow episode is not what this test is about.
        episode_time_s: 60.0,
        reset_time_s: 0.2,
        clutch_cycles: true,
        ..OperatorOptions::default()
    };
    let mut reports = Vec::new();
    let summary = operator::run(&client, &options, |r| reports.push(r.clone()), |_, _, _| {})
        .await
        .unwrap();
    assert_eq!(summary.seeds, vec![500, 501]);
    assert_eq!(
        (summary.attempted, summary.succeeded, summary.saved),
        (2, 2, 2),
        "{reports:#?}"
    );
    assert!((summary.success_rate() - 1.0).abs() < 1e-12);
    let listed = client.episodes().list().await.unwrap().episodes;
    assert_eq!(listed.len(), 2);
    for (report, episode) in reports.iter().zip(&listed) {
        assert_eq!(report.episode_index, Some(episode.episode_index));
        assert_eq!(report.frames, episode.length_frames);
        assert_eq!(episode.task, operator::DEFAULT_TASK);
    }
    server.shutdown().await.unwrap();

    let rows = dataset_rows(dir.path());
    let frames: u64 = listed.iter().map(|e| e.length_frames).sum();
    assert_eq!(rows.len() as u64, frames);
    // `next.success`: false while the ball is on the table or in the gripper, true once it rests in the
    // basket, and so at the end of every saved episode (the operator holds still for half a second, ten
    // frames at 20 fps, after the ball lands).
    for episode in &listed {
        let flags: Vec<bool> = rows
            .iter()
            .filter(|r| r.episode_index == episode.episode_index as i64)
            .map(|r| r.success.expect("the sim dataset has next.success"))
            .collect();
        assert!(!flags[0], "episode {} starts successful", episode.episode_index);
        assert!(
            flags.last().copied().unwrap(),
            "episode {} ends unsuccessful",
            episode.episode_index
        );
        let first_true = flags.iter().position(|f| *f).unwrap();
        assert!(
            flags[first_true..].iter().all(|f| *f),
            "success flickers in episode {}",
            episode.episode_index
        );
    }
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(
        info["features"]["next.success"],
        serde_json::json!({"dtype": "bool", "shape": [1], "names": null})
    );
    keep_for_conformance("operator_v30", dir.path());
}

/// An arm behind `Bridge.Attach` that follows every command at once and streams its pose at 50 Hz, with a
/// scene (ball, basket) that succeeds when the gripper opens above the basket after closing. Once, when the
/// gripper first closes, it goes silent for `STALL`: its measured pose goes stale, as the sim's did on a
/// starved machine, and the server refuses the phone's samples ("the arm is not ready").
mod stalling_bridge {
    use phone2act_sdk::proto as v1;
    use phone2act_tests::bridge::{self, upstream as up};
    use std::time::Duration;
    use tokio_stream::StreamExt;

    const HOME_M: [f64; 3] = [0.2, 0.0, 0.15];
    /// The ball sits on a 3 cm stand: its centre (where the operator descends to) inside the default
    /// workspace, whose floor is 2 cm above the table.
    const BALL_M: [f64; 3] = [0.23, 0.02, 0.03];
    const BASKET_M: [f64; 3] = [0.28, 0.1, 0.0];
    /// Twice the server's 1 s limit on the measured pose's age: long enough that the operator's next sample
    /// certainly finds it stale, however late a loaded machine delivers it.
    const STALL: Duration = Duration::from_secs(2);

    fn pose(p: [f64; 3]) -> v1::Pose {
        v1::Pose::from_parts(p, [0.0, 0.0, 0.0, 1.0])
    }

    fn feedback(pose: v1::Pose, gripper: f64, applied_seq: u64) -> v1::BridgeUpstream {
        up(v1::bridge_upstream::Message::Feedback(v1::RobotFeedback {
            joint_positions_rad: vec![0.0; 3],
            robot_from_ee: Some(pose),
            gripper_position: gripper,
            applied_seq,
            ..v1::RobotFeedback::default()
        }))
    }

    fn scene(seed: u64, success: bool, request_id: u64) -> v1::BridgeUpstream {
        let [bx, by, bz] = BALL_M;
        let [kx, ky, kz] = BASKET_M;
        up(v1::bridge_upstream::Message::Scene(v1::BridgeScene {
            state: Some(v1::SceneState {
                seed,
                ball_position_m: Some(v1::Vec3::new(bx, by, bz)),
                ball_state: v1::BallState::Resting as i32,
                ball_radius_m: 0.01,
                basket_position_m: Some(v1::Vec3::new(kx, ky, kz)),
                basket_radius_m: 0.045,
                basket_height_m: 0.035,
                success,
                ..v1::SceneState::default()
            }),
            reset_request_id: request_id,
            error: String::new(),
        }))
    }

    /// Attaches to arm `arm` and runs until the server ends the stream; returns how many stalls it made.
    pub(super) async fn run(channel: tonic::transport::Channel, arm: &str) -> u32 {
        let hello = v1::BridgeHello {
            arm: arm.into(),
            bridge_name: "stalling".into(),
            joint_names: vec!["a".into(), "b".into(), "c".into()],
            supports_orientation: true,
            has_scene: true,
            ..v1::BridgeHello::default()
        };
        let (tx, mut down) = bridge::attach(channel, hello, 64).await.unwrap();
        let (mut at, mut gripper, mut seq) = (pose(HOME_M), 0.0, 0);
        let (mut seed, mut closed, mut success) = (0, false, false);
        let mut stalls = 0;
        let mut silent_until = tokio::time::Instant::now();
        tx.send(feedback(at, gripper, seq)).await.unwrap();
        tx.send(scene(seed, false, 0)).await.unwrap();
        let mut every = tokio::time::interval(Duration::from_millis(20));
        loop {
            tokio::select! {
                msg = down.next() => {
                    let Some(Ok(msg)) = msg else { return stalls };
                    match msg.message {
                        Some(v1::bridge_downstream::Message::Command(c)) => {
                            at = c.robot_from_target.unwrap();
                            seq = c.seq;
                            if c.gripper_target >= 0.5 && gripper < 0.5 {
                                closed = true;
                                if stalls == 0 {
                                    stalls += 1;
                                    silent_until = tokio::time::Instant::now() + STALL;
                                }
                            }
                            let p = at.position_m.unwrap();
                            let over_basket = (p.x - BASKET_M[0]).hypot(p.y - BASKET_M[1]) < 0.03;
                            if closed && c.gripper_target < 0.5 && over_basket && !success {
                                success = true;
                                tx.send(scene(seed, true, 0)).await.unwrap();
                            }
                            gripper = c.gripper_target;
                        }
                        Some(v1::bridge_downstream::Message::SceneReset(r)) => {
                            seed = r.seed.unwrap_or(seed + 1);
                            (closed, success) = (false, false);
                            // A bridge that answers a reset is alive again.
                            silent_until = tokio::time::Instant::now();
                            if r.home_arm {
                                (at, gripper) = (pose(HOME_M), 0.0);
                            }
                            tx.send(feedback(at, gripper, seq)).await.unwrap();
                            tx.send(scene(seed, false, r.request_id)).await.unwrap();
                        }
                        _ => {}
                    }
                }
                _ = every.tick() => {}
            }
            if tokio::time::Instant::now() >= silent_until {
                tx.send(feedback(at, gripper, seq)).await.unwrap();
            }
        }
    }
}

/// The server refuses the phone's samples mid-episode (the arm's measured pose went stale): the operator
/// discards that try through the API, tries the seed again and goes on; the dataset holds only whole,
/// successful episodes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_try_is_discarded_and_its_seed_tried_again() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = phone2act_server::Config::from_toml_str(
        "[[arms]]\nname = \"main\"\nbridge = \"remote\"\n[arms.remote]\njoint_names = [\"a\", \"b\", \"c\"]\n",
        "stalling-bridge",
        Vec::new(),
    )
    .unwrap();
    dir.path().clone_into(&mut config.recorder.root);
    let server = TestServer::start(config).await.unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let bridge = tokio::spawn(stalling_bridge::run(channel, "main"));
    let client = server.client().await.unwrap();
    // The bridge's first pose and scene reach the server with the stream's first messages; a loaded machine
    // may take a moment (10 s is far beyond it).
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(10);
    while client.scene().get("main").await.is_err() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the bridge never reported a scene"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let options = OperatorOptions {
        episodes: 2,
        seed: 40,
        // Generous, as in the test above: the time limit is not what this test is about.
        episode_time_s: 60.0,
        reset_time_s: 0.2,
        ..OperatorOptions::default()
    };
    let mut reports = Vec::new();
    let mut refusals = Vec::new();
    let summary = operator::run(
        &client,
        &options,
        |r| reports.push(r.clone()),
        |seed, tries, reason| refusals.push((seed, tries, reason.to_owned())),
    )
    .await
    .unwrap();
    // The one stall cut the first try of seed 40 short. A loaded machine could delay the bridge's pose past
    // the 1 s limit again, but three times in a row on one seed it would not, so nothing is skipped.
    let (seed, tries, reason) = refusals.first().expect("the stall was refused").clone();
    assert_eq!((seed, tries), (40, 1), "{refusals:?}");
    assert!(reason.contains("not ready"), "{reason}");
    assert_eq!(summary.refused, refusals.len() as u64);
    assert!(summary.skipped.is_empty(), "{summary:?}");
    assert_eq!(summary.seeds, vec![40, 41]);
    assert_eq!(
        (summary.attempted, summary.succeeded, summary.saved),
        (2, 2, 2),
        "{reports:#?}"
    );
    // Exactly the two successful episodes were saved, each whole: nothing of the refused try remains.
    let listed = client.episodes().list().await.unwrap().episodes;
    assert_eq!(listed.len(), 2, "{listed:?}");
    server.shutdown().await.unwrap();
    assert_eq!(bridge.await.unwrap(), 1);
    let rows = dataset_rows(dir.path());
    assert_eq!(
        rows.len() as u64,
        listed.iter().map(|e| e.length_frames).sum::<u64>()
    );
    for (report, episode) in reports.iter().zip(&listed) {
        assert_eq!(report.episode_index, Some(episode.episode_index));
        assert_eq!(report.frames, episode.length_frames);
    }
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(info["total_episodes"], 2);
}
