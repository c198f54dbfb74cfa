//! The operator's outcome (issue 27): a hardware arm (an out-of-process bridge, no scene) records
//! `next.success` with `[recorder] success = true`; the outcome given with `Episodes.Stop` is the last frame's
//! value, every other frame is false, and the outcome is kept in the episode's provenance and listed. Both
//! dataset formats; the datasets go to the lerobot conformance run, which checks the values lerobot reads.

use phone2act_dataset::parquet_io::read_rows;
use phone2act_sdk::proto as v1;
use phone2act_server::Config;
use phone2act_server::config::DatasetFormat;
use phone2act_tests::bridge::{self, upstream};
use phone2act_tests::{TestServer, data_files, keep_for_conformance_expecting, wait_until};
use serde_json::{Value, json};
use std::time::Duration;

const CONFIG: &str = r#"
[recorder]
success = true

[[arms]]
name = "ext"
bridge = "remote"
[arms.remote]
joint_names = ["a", "b", "c"]
"#;

/// Attaches a bridge to `ext` that reports a fixed pose every 10 ms (well inside the recorder's 0.25 s hold
/// tolerance) until the returned sender is dropped.
async fn attach_bridge(server: &TestServer) -> tokio::task::JoinHandle<()> {
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let hello = v1::BridgeHello {
        arm: "ext".into(),
        bridge_name: "success-test".into(),
        joint_names: vec!["a".into(), "b".into(), "c".into()],
        supports_orientation: true,
        ..v1::BridgeHello::default()
    };
    let (tx, mut down) = bridge::attach(channel, hello, 8).await.unwrap();
    tokio::spawn(async move {
        // Drain the downstream (welcome, commands) so the server never blocks on it.
        let drain = tokio::spawn(async move { while let Some(Ok(_)) = down.message().await.transpose() {} });
        let pose = v1::Pose::from_parts([0.2, 0.05, 0.1], [0.0, 0.0, 0.0, 1.0]);
        loop {
            let feedback = v1::RobotFeedback {
                capture_time_ns: 0,
                joint_positions_rad: vec![0.1, 0.2, 0.3],
                robot_from_ee: Some(pose),
                gripper_position: 0.0,
                applied_seq: 0,
            };
            if tx
                .send(upstream(v1::bridge_upstream::Message::Feedback(feedback)))
                .await
                .is_err()
            {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        drain.abort();
    })
}

async fn outcomes(format: DatasetFormat, conformance_name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let mut config = Config::from_toml_str(CONFIG, "success-test", Vec::new()).unwrap();
    config.recorder.root.clone_from(&root);
    config.recorder.format = format;
    let server = TestServer::start(config).await.unwrap();
    let bridge = attach_bridge(&server).await;
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();

    // (outcome given, what the episode reports and its last frame holds)
    let takes = [
        (v1::EpisodeOutcome::Success, Some(true)),
        (v1::EpisodeOutcome::Failure, Some(false)),
        (v1::EpisodeOutcome::Unspecified, None),
    ];
    for (i, (outcome, _)) in takes.iter().enumerate() {
        episodes
            .start_by("put the part in the tray", "tester")
            .await
            .unwrap();
        // 8 frames at 20 fps take 0.4 s; 20 s covers a machine stalled by parallel builds.
        let recorded = wait_until(Duration::from_secs(20), || {
            let mut e = client.episodes();
            async move { e.status().await.is_ok_and(|s| s.frames_recorded >= 8) }
        })
        .await;
        assert!(recorded, "episode {i} records frames from the bridge's feedback");
        if i == 0 {
            // An outcome this server does not know is refused before anything stops: still recording.
            let mut raw = phone2act_proto::v1::episodes_client::EpisodesClient::new(
                tonic::transport::Endpoint::from_shared(server.url())
                    .unwrap()
                    .connect()
                    .await
                    .unwrap(),
            );
            let err = raw.stop(v1::StopEpisodeRequest { outcome: 7 }).await.unwrap_err();
            assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err}");
            assert!(err.message().contains("outcome"), "{err}");
            let status = episodes.status().await.unwrap();
            assert_eq!(status.phase(), v1::RecordingPhase::Recording, "{status:?}");
        }
        let saved = episodes.stop_with(*outcome).await.unwrap();
        let ep = saved.episode.unwrap();
        assert_eq!(ep.episode_index, i as u64);
        assert_eq!(ep.outcome(), *outcome);
    }
    bridge.abort();

    let listed = episodes.list().await.unwrap().episodes;
    let listed: Vec<v1::EpisodeOutcome> = listed.iter().map(v1::EpisodeInfo::outcome).collect();
    assert_eq!(listed, takes.map(|t| t.0));

    // The rows: false everywhere but the last frame of the episode stopped as a success.
    let rows: Vec<_> = data_files(&root.join("data"))
        .iter()
        .flat_map(|f| read_rows(f).unwrap())
        .collect();
    let mut success_frames = 0;
    for (i, (_, last)) in takes.iter().enumerate() {
        let ep: Vec<_> = rows.iter().filter(|r| r.episode_index == i as i64).collect();
        assert!(ep.len() >= 8, "episode {i} has {} frames", ep.len());
        let flags: Vec<bool> = ep
            .iter()
            .map(|r| r.success.expect("every frame has next.success"))
            .collect();
        assert!(
            !flags[..flags.len() - 1].iter().any(|&f| f),
            "episode {i}: only the last frame can carry the outcome: {flags:?}"
        );
        assert_eq!(flags[flags.len() - 1], last.unwrap_or(false), "episode {i}");
        success_frames += flags.iter().filter(|&&f| f).count();
    }
    assert_eq!(success_frames, 1);

    let read =
        |p: &str| -> Value { serde_json::from_str(&std::fs::read_to_string(root.join(p)).unwrap()).unwrap() };
    let info = read("meta/info.json");
    assert_eq!(
        info["features"]["next.success"],
        json!({"dtype": "bool", "shape": [1], "names": null})
    );
    let provenance = read("meta/phone2act_provenance.json");
    let recorded: Vec<&Value> = (0..3).map(|i| &provenance["episodes"][i]["success"]).collect();
    assert_eq!(recorded, [&json!(true), &json!(false), &Value::Null]);
    if format == DatasetFormat::V21 {
        // GR00T reaches the column through modality.json's annotations, as it reaches `intervention`.
        assert_eq!(
            read("meta/modality.json")["annotation"]["human.success"],
            json!({"original_key": "next.success"})
        );
    }
    if format == DatasetFormat::V30 {
        // Stats count the outcome: one true frame among all of them.
        let stats = &read("meta/stats.json")["next.success"];
        assert_eq!(
            (&stats["min"], &stats["max"]),
            (&json!([0.0]), &json!([1.0])),
            "{stats}"
        );
        let mean = stats["mean"][0].as_f64().unwrap();
        assert!((mean - 1.0 / rows.len() as f64).abs() < 1e-6, "{stats}");
    }

    let expect = json!({"episodes": 3, "success_last": [true, false, false], "success_frames": 1});
    keep_for_conformance_expecting(conformance_name, &root, &expect);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_outcome_marks_a_hardware_episode_v30() {
    outcomes(DatasetFormat::V30, "success_marking_v30").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_outcome_marks_a_hardware_episode_v21() {
    outcomes(DatasetFormat::V21, "success_marking_v21").await;
}
