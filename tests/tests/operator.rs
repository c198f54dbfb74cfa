//! The scripted operator end to end: a real in-process server (simulated arm, rendered camera), the
//! operator driving it through `Teleop.Stream` as a phone does, episodes saved only when the ball ends in
//! the basket, and the dataset read back.

use phone2act_recorder::parquet_io::read_rows;
use phone2act_tests::operator::{self, OperatorOptions};
use phone2act_tests::{TestServer, default_config, keep_for_conformance};

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

    let mut files: Vec<_> = std::fs::read_dir(dir.path().join("data/chunk-000"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let rows: Vec<_> = files.iter().flat_map(|f| read_rows(f).unwrap()).collect();
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
