//! The episode time limit and reset period (issue 27, LeRobot's `episode_time_s` / `reset_time_s`) on the
//! simulated arm, over gRPC: an episode is saved at its limit with exactly `episode_time_s * fps` frames, the
//! status counts down the episode and then the reset period (`remaining_s`, `resetting`), the scene re-draws
//! itself during the reset, and the next episode starts by itself with the same task and operator.

use phone2act_sdk::proto as v1;
use phone2act_tests::{TestServer, default_config, wait_until};

use std::time::Duration;

const EPISODE_S: f64 = 0.5;
const RESET_S: f64 = 1.0;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn episodes_are_saved_at_their_limit_and_the_next_starts_after_the_reset() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.recorder.episode_time_s = Some(EPISODE_S);
    config.recorder.reset_time_s = Some(RESET_S);
    config.recorder.start_next_after_reset = true;
    let fps = config.recorder.fps;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    let resets_before = client.scene().get("main").await.unwrap().resets;

    episodes
        .start_by("put the ball in the basket", "timer")
        .await
        .unwrap();
    let status = episodes.status().await.unwrap();
    let remaining = status.remaining_s.expect("a limited episode counts down");
    assert!((0.0..=EPISODE_S).contains(&remaining), "{status:?}");
    assert!(!status.resetting);

    // Watch the transitions as a phone would: the reset period shows up with its own countdown, then the
    // next episode records. Each wait is a few times the configured period; 30 s covers a stalled machine.
    let mut saw_reset = None;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let mut reached = false;
    while tokio::time::Instant::now() < deadline {
        let s = episodes.status().await.unwrap();
        if s.resetting && saw_reset.is_none() {
            saw_reset = Some(s.clone());
        }
        if s.episodes_saved >= 1 && s.phase() == v1::RecordingPhase::Recording && !s.resetting {
            reached = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(reached, "the next episode never started by itself");
    let reset = saw_reset.expect("the status showed the reset period");
    assert_eq!(
        reset.phase(),
        v1::RecordingPhase::Idle,
        "nothing records while resetting"
    );
    let left = reset.remaining_s.expect("the reset period counts down");
    assert!(left > 0.0 && left <= RESET_S, "{reset:?}");

    // The next episode keeps the task and the operator; the scene was re-drawn in between.
    let status = episodes.status().await.unwrap();
    assert_eq!(status.task, "put the ball in the basket");
    let resets = client.scene().get("main").await.unwrap().resets;
    // At least once: on a stalled machine the next episode may already have had its own limit and reset.
    assert!(
        resets > resets_before,
        "the scene was not re-drawn during the reset period"
    );
    let saved = episodes.list().await.unwrap().episodes;
    let first = &saved[0];
    assert_eq!(first.operator, "timer");
    // Saved at the limit, with exactly the limit's frames whenever the save came.
    assert_eq!(first.length_frames, (EPISODE_S * fps).round() as u64, "{first:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_starts_the_reset_period_a_start_cuts_it_short_and_a_discard_starts_none() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    // A reset period long enough that the test's own steps, on a stalled machine, happen inside it.
    config.recorder.reset_time_s = Some(60.0);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    let idle = episodes.status().await.unwrap();
    assert!(idle.remaining_s.is_none() && !idle.resetting, "{idle:?}");

    episodes.start("put the ball in the basket").await.unwrap();
    let s = episodes.status().await.unwrap();
    assert!(s.remaining_s.is_none(), "no episode limit, no countdown: {s:?}");
    let framed = wait_until(Duration::from_secs(10), || {
        let mut e = client.episodes();
        async move { e.status().await.is_ok_and(|s| s.frames_recorded >= 2) }
    })
    .await;
    assert!(framed, "the episode records");
    episodes.stop().await.unwrap();
    let resetting = wait_until(Duration::from_secs(10), || {
        let mut e = client.episodes();
        async move { e.status().await.is_ok_and(|s| s.resetting) }
    })
    .await;
    assert!(resetting, "a stop starts the reset period");
    let s = episodes.status().await.unwrap();
    let left = s.remaining_s.expect("the reset counts down");
    assert!(left > 0.0 && left <= 60.0, "{s:?}");
    // Starting during the reset cuts it short.
    episodes.start("put the ball in the basket").await.unwrap();
    let cut = wait_until(Duration::from_secs(10), || {
        let mut e = client.episodes();
        async move {
            e.status()
                .await
                .is_ok_and(|s| !s.resetting && s.phase() == v1::RecordingPhase::Recording)
        }
    })
    .await;
    assert!(cut, "a start ends the reset period");
    // A discard saves nothing and starts no reset period.
    episodes.discard().await.unwrap();
    // The shell looks at every recorder change; 300 ms is six of its polls, and a reset it wrongly started
    // would stay on for 60 s, so a late look still sees it.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let s = episodes.status().await.unwrap();
    assert!(!s.resetting && s.remaining_s.is_none(), "{s:?}");
}
