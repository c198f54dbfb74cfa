//! Faults that are not a clean kill, over real sockets against a real server: every refusal is a non-OK
//! status, nothing saved is deleted by a refused or misdirected call, and client-supplied sizes, counts
//! and durations are bounded.

use phone2act_sdk::proto as v1;
use phone2act_tests::{TestServer, default_config};
use std::time::Duration;

/// Tests here count the process's threads and time things: one at a time, so that another test's server
/// (its encoder threads, its blocking pool) is not counted.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

fn threads_now() -> usize {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("Threads:"))
        .and_then(|n| n.trim().parse().ok())
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rerecord_never_deletes_saved_work_and_a_refused_one_discards_nothing() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    for task in ["one", "two"] {
        episodes.start(task).await.unwrap();
        tokio::time::sleep(Duration::from_millis(400)).await;
        episodes.stop().await.unwrap();
    }
    // Nothing recording: refused, both saved episodes stay.
    let err = episodes.rerecord("").await.unwrap_err().to_string();
    assert!(err.contains("FailedPrecondition"), "{err}");
    assert_eq!(episodes.list().await.unwrap().episodes.len(), 2);

    episodes.start("three").await.unwrap();
    tokio::time::sleep(Duration::from_millis(400)).await;
    let before = episodes.status().await.unwrap().frames_recorded;
    assert!(before > 0);
    // A 1 MB task: refused for its argument, and the take in progress goes on.
    let err = episodes
        .rerecord(&"x".repeat(1 << 20))
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("InvalidArgument"), "{err}");
    let st = episodes.status().await.unwrap();
    assert_eq!(st.phase(), v1::RecordingPhase::Recording);
    assert_eq!(st.task, "three");
    assert!(st.frames_recorded >= before, "{} < {before}", st.frames_recorded);
    // A good one restarts the take.
    let st = episodes.rerecord("three, again").await.unwrap();
    assert_eq!(st.task, "three, again");
    tokio::time::sleep(Duration::from_millis(400)).await;
    episodes.stop().await.unwrap();
    let list = episodes.list().await.unwrap();
    let tasks: Vec<_> = list.episodes.iter().map(|e| e.task.as_str()).collect();
    assert_eq!(tasks, ["one", "two", "three, again"]);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn episode_watch_streams_do_not_cost_a_thread_each() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut first = client.episodes().watch(0.5).await.unwrap();
    first.message().await.unwrap().unwrap();
    let base = threads_now();
    let mut streams = Vec::new();
    for _ in 0..200 {
        let mut s = client.episodes().watch(0.5).await.unwrap();
        s.message().await.unwrap().unwrap();
        streams.push(s);
    }
    let grown = threads_now().saturating_sub(base);
    // 200 streams used to add 200 threads. What else may start meanwhile: tokio blocking-pool threads for
    // other calls and the one shared watch thread, a handful; 50 separates that from one per stream.
    assert!(grown < 50, "200 watch streams added {grown} threads");
    // They still report changes.
    client.episodes().start("watched").await.unwrap();
    let st = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let m = streams[199].message().await.unwrap().unwrap();
            if m.phase() == v1::RecordingPhase::Recording {
                return m;
            }
        }
    })
    .await
    .expect("a watcher sees the start");
    assert_eq!(st.task, "watched");
    client.episodes().discard().await.unwrap();
    drop(streams);
    server.shutdown().await.unwrap();
}
