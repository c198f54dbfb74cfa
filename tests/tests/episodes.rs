//! Episodes end to end: record through the real server (gRPC and phone buttons) into a real dataset.

use phone2act_sdk::proto as v1;
use phone2act_sdk::{TeleopOptions, buttons};
use phone2act_tests::{TestServer, default_config, keep_for_conformance};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn record_stop_list_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();

    // Nothing to stop yet: a clear precondition error.
    let err = episodes.stop().await.unwrap_err().to_string();
    assert!(
        err.contains("FailedPrecondition") && err.contains("no episode"),
        "{err}"
    );
    // 10 kB task: refused, nothing started.
    let err = episodes.start(&"x".repeat(10_000)).await.unwrap_err().to_string();
    assert!(err.contains("InvalidArgument") && err.contains("bytes"), "{err}");

    let status = episodes.start("pick the ball").await.unwrap();
    assert_eq!(status.phase(), v1::RecordingPhase::Recording);
    let err = episodes.start("again").await.unwrap_err().to_string();
    assert!(err.contains("already"), "{err}");
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let saved = episodes.stop().await.unwrap();
    let ep = saved.episode.unwrap();
    assert_eq!(ep.episode_index, 0);
    assert_eq!(ep.task, "pick the ball");
    // 24 ticks in 1.2 s; a loaded test machine may skip a few late ticks (counted, never a gap).
    assert!(
        (12..=30).contains(&ep.length_frames),
        "20 fps for ~1.2 s gave {}",
        ep.length_frames
    );
    assert!(saved.save_latency_s < 1.0, "save took {} s", saved.save_latency_s);

    // A phone records the second episode with its buttons.
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_buttons(vec![buttons::record_start("place it in the basket")])
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    assert_eq!(
        fb.recording.as_ref().unwrap().phase(),
        v1::RecordingPhase::Recording
    );
    tokio::time::sleep(Duration::from_millis(600)).await;
    let seq = phone.send_buttons(vec![buttons::record_stop()]).await.unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);

    // A third one discarded.
    episodes.start("discard me").await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(episodes.discard().await.unwrap() > 0);

    let list = episodes.list().await.unwrap();
    let tasks: Vec<_> = list.episodes.iter().map(|e| e.task.as_str()).collect();
    assert_eq!(tasks, ["pick the ball", "place it in the basket"]);
    assert!(dir.path().join("meta/info.json").exists());
    server.shutdown().await.unwrap();
    keep_for_conformance("episodes_v30", dir.path());
}
