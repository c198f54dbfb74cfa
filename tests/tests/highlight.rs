//! "Save the last N seconds" end to end (issue 27, LeRobot's `highlight`): a server with `[recorder]
//! highlight_s` keeps the last seconds of the sim while idle; the operator moves the arm from the phone without
//! recording, then saves them through the API, the phone's record button and as the start of an episode that
//! records on. Each episode is read back with the project's reader: about N·fps rows, frame indices and
//! timestamps contiguous from 0, one video frame per row (`verify`), the phone's motion in its actions and the
//! clutch in its events. The dataset goes to the lerobot conformance run.

use phone2act_dataset::dataset::timestamp_s;
use phone2act_dataset::parquet_io::read_rows;
use phone2act_dataset::readback::read_episode;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, buttons};
use phone2act_tests::{TestServer, data_files, default_config, keep_for_conformance_expecting, wait_until};
use serde_json::json;
use std::path::Path;
use std::time::Duration;

const KEEP_S: f64 = 3.0;
const FPS: u32 = 20;
/// Waits are for a few seconds of recorder ticks; a tick written late is still written (never skipped), so
/// only a stalled server takes this long, even beside parallel builds on two cores.
const WAIT: Duration = Duration::from_mins(1);

async fn buffered_at_least(client: &Client, seconds: f64) -> bool {
    wait_until(WAIT, || {
        let mut e = client.episodes();
        async move { e.status().await.is_ok_and(|s| s.highlight_buffered_s >= seconds) }
    })
    .await
}

/// Moves the phone 4 cm along x with the clutch in over 1.5 s, then releases it and holds still.
async fn move_arm(client: &Client) {
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let q = [0.0, 0.0, 0.0, 1.0];
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0, 0.0, 0.0], q),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.arm_state.unwrap().engaged, "{}", fb.error);
    let mut tick = tokio::time::interval(Duration::from_millis(20));
    for i in 1..=75 {
        tick.tick().await;
        let x = 0.04 * f64::from(i) / 75.0;
        phone
            .send_pose(v1::Pose::from_parts([x, 0.0, 0.0], q), vec![], 0)
            .await
            .unwrap();
    }
    phone
        .send_pose(
            v1::Pose::from_parts([0.04, 0.0, 0.0], q),
            vec![buttons::clutch_disengage()],
            0,
        )
        .await
        .unwrap();
}

/// Episode `index` read back: frame indices 0..n, exact timestamps, one state and action row per frame;
/// returns its actions.
fn read_back(root: &Path, index: u64) -> Vec<Vec<f64>> {
    let ep = read_episode(root, index).unwrap();
    let n = ep.frame_index.len();
    assert_eq!(
        ep.frame_index,
        (0..n as i64).collect::<Vec<_>>(),
        "episode {index}"
    );
    assert_eq!(ep.vectors.len(), 2);
    assert!(ep.vectors.iter().all(|v| v.rows.len() == n));
    assert_eq!(ep.videos.len(), 1, "the sim's camera");
    let mut stamps = Vec::new();
    for f in data_files(&root.join("data")) {
        for row in read_rows(&f).unwrap() {
            if row.episode_index == index as i64 {
                stamps.push((row.frame_index, row.timestamp));
            }
        }
    }
    stamps.sort_by_key(|s| s.0);
    assert_eq!(stamps.len(), n);
    for (k, t) in stamps {
        assert_eq!(t.to_bits(), timestamp_s(k as u64, FPS).to_bits(), "frame {k}");
    }
    ep.vectors[1].rows.clone()
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_last_seconds_are_saved_from_the_api_the_phone_and_as_a_live_start() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_owned();
    let mut config = default_config(&root);
    config.recorder.highlight_s = Some(KEEP_S);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    let status = episodes.status().await.unwrap();
    assert!((status.highlight_s - KEEP_S).abs() < 1e-9, "{status:?}");
    assert_eq!(status.phase(), v1::RecordingPhase::Idle);

    // 1. The operator moves the arm without recording, then saves the last 3 s through the API.
    assert!(buffered_at_least(&client, 1.0).await, "the ring fills");
    move_arm(&client).await;
    assert!(buffered_at_least(&client, KEEP_S).await, "3 s kept");
    let status = episodes.status().await.unwrap();
    assert!(status.highlight_video_bytes > 0, "{status:?}");
    // An outcome this server does not know is refused before anything is taken from the ring.
    let mut raw = client.episodes_raw();
    let err = raw
        .save_highlight(v1::SaveHighlightRequest {
            task: "bad".into(),
            outcome: 9,
            ..v1::SaveHighlightRequest::default()
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err}");
    let err = raw
        .save_highlight(v1::SaveHighlightRequest::default())
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "no task: {err}");
    let saved = episodes
        .save_highlight("push the ball along x", v1::EpisodeOutcome::Success)
        .await
        .unwrap();
    let ep = saved.episode.expect("saved at once");
    let keep = (KEEP_S * f64::from(FPS)) as u64;
    // From the oldest kept tick at a multiple of the video GOP (2): N·fps frames, or one more.
    assert!(
        (keep..=keep + 1).contains(&ep.length_frames),
        "{} frames",
        ep.length_frames
    );
    assert_eq!(ep.episode_index, 0);
    assert_eq!(ep.outcome(), v1::EpisodeOutcome::Success);
    assert_eq!(ep.dropped_frames, 0);
    assert_eq!(saved.status.unwrap().phase(), v1::RecordingPhase::Idle);
    let actions = read_back(&root, 0);
    // The phone's 4 cm are in the actions (the motion took 1.5 s of the 3 kept), and the arm held its last
    // target afterwards: the last actions are one value, as in an episode recorded with Start.
    let moved = actions
        .iter()
        .map(|a| distance(a, &actions[0]))
        .fold(0.0, f64::max);
    assert!(moved > 0.02, "actions moved {moved}");
    let last = actions.last().unwrap();
    assert!(actions[actions.len() - 5..].iter().all(|a| a == last));
    let events = std::fs::read_to_string(root.join(phone2act_dataset::events::events_path(0))).unwrap();
    assert!(
        events.contains("clutch"),
        "the clutch is in the episode's events: {events}"
    );

    // 2. From the phone's record button (the page's {"record":"highlight"}).
    assert!(buffered_at_least(&client, 1.0).await, "the ring starts again");
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_buttons(vec![buttons::save_highlight(
            "saved from the phone",
            v1::EpisodeOutcome::Unspecified,
        )])
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    assert_eq!(fb.recording.unwrap().episodes_saved, 2);
    let n = read_back(&root, 1).len() as u64;
    assert!(n >= u64::from(FPS) - 1 && n <= keep + 1, "{n} frames");

    // 3. As the start of an episode that records on until Stop (LeRobot's highlight strategy).
    assert!(buffered_at_least(&client, KEEP_S).await);
    let r = episodes
        .save_highlight_with(v1::SaveHighlightRequest {
            task: "kept and recorded on".into(),
            operator: "ana".into(),
            keep_recording: true,
            ..v1::SaveHighlightRequest::default()
        })
        .await
        .unwrap();
    assert!(r.episode.is_none());
    let status = r.status.unwrap();
    assert_eq!(status.phase(), v1::RecordingPhase::Recording);
    assert!(status.frames_recorded >= keep, "{status:?}");
    // While recording it is refused: the episode in progress holds these seconds.
    let err = episodes
        .save_highlight("again", v1::EpisodeOutcome::Unspecified)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("FailedPrecondition") && err.contains("being recorded"),
        "{err}"
    );
    assert!(
        wait_until(WAIT, || {
            let mut e = client.episodes();
            async move { e.status().await.is_ok_and(|s| s.frames_recorded >= keep + 20) }
        })
        .await
    );
    let stopped = episodes.stop().await.unwrap().episode.unwrap();
    assert!(stopped.length_frames >= keep + 20);
    assert_eq!(stopped.operator, "ana");
    assert_eq!(read_back(&root, 2).len() as u64, stopped.length_frames);

    let report = phone2act_dataset::verify::verify(&root);
    assert!(report.ok(), "{}", report.problems.join("\n"));
    server.shutdown().await.unwrap();
    keep_for_conformance_expecting(
        "highlight_v30",
        &root,
        &json!({"episodes": 3, "tasks": ["push the ball along x", "saved from the phone", "kept and recorded on"]}),
    );
}

/// Without `[recorder] highlight_s` nothing is kept: the request says how to turn it on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_highlight_s_the_request_says_how_to_turn_it_on() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    assert!(episodes.status().await.unwrap().highlight_s.abs() < 1e-9, "off");
    let err = episodes
        .save_highlight("anything", v1::EpisodeOutcome::Unspecified)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("FailedPrecondition") && err.contains("highlight_s"),
        "{err}"
    );
    server.shutdown().await.unwrap();
}
