//! The flight recorder end to end: a real server with `[flight_log]` on logs every input of its arm's arbiter
//! while a phone (over `Teleop.Stream`) and a policy (over the Policy API) drive the simulated arm, and the
//! log replays on a fresh core to the same commands and gate decisions.
//!
//! The committed fixtures under tests/fixtures/flight/ are logs of these two sessions: with
//! `PHONE2ACT_WRITE_FLIGHT_FIXTURES=1` the tests write them there again (after a deliberate change of the
//! control rules, so that `phone2act replay-log` on them, which `make test` runs, agrees with the new rules).

use phone2act_sdk::TeleopOptions;
use phone2act_sdk::buttons;
use phone2act_sdk::proto as v1;
use phone2act_server::config::FlightLogConfig;
use phone2act_server::flight_log::{Verdict, replay_file};
use phone2act_tests::{TestServer, default_config};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Starts a server logging to `logs`, runs `session` against it, stops it and returns its one log.
async fn logged<F, Fut>(logs: &Path, session: F) -> PathBuf
where
    F: FnOnce(phone2act_sdk::Client) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let data = tempfile::tempdir().unwrap();
    let mut config = default_config(data.path());
    config.flight_log = Some(FlightLogConfig {
        dir: logs.to_owned(),
        max_bytes: 16 << 20,
    });
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    // The sim's first feedback: before it the arm is not ready and every input would be a refusal.
    tokio::time::sleep(Duration::from_millis(400)).await;
    session(client).await;
    server.shutdown().await.unwrap();
    let files: Vec<PathBuf> = std::fs::read_dir(logs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(files.len(), 1, "one arm, one log: {files:?}");
    files[0].clone()
}

fn keep_as_fixture(log: &Path, name: &str) {
    if std::env::var_os("PHONE2ACT_WRITE_FLIGHT_FIXTURES").is_some() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/flight");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(log, dir.join(name)).unwrap();
    }
}

fn pose(x_m: f64, y_m: f64, yaw_rad: f64) -> v1::Pose {
    let (s, c) = (yaw_rad / 2.0).sin_cos();
    v1::Pose::from_parts([x_m, y_m, 0.0], [0.0, 0.0, s, c])
}

/// A phone on arm `main`, engaged at the tracking origin.
async fn engaged_phone(client: &phone2act_sdk::Client) -> phone2act_sdk::TeleopSession {
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(pose(0.0, 0.0, 0.0), vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();
    phone
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_phone_session_replays_to_the_same_commands_and_decisions() {
    let logs = tempfile::tempdir().unwrap();
    let log = logged(logs.path(), |client| async move {
        let mut phone = engaged_phone(&client).await;
        // A small circle with a wrist turn at 50 Hz, a jump the gate drops, a grip, a non-unit quaternion.
        for i in 1..=60u32 {
            let a = f64::from(i) * std::f64::consts::TAU / 60.0;
            let x = 0.02 * a.sin() + if i == 30 { 0.2 } else { 0.0 };
            let buttons = if i == 40 {
                vec![buttons::gripper_toggle()]
            } else {
                vec![]
            };
            phone
                .send_pose(pose(x, 0.02 * (1.0 - a.cos()), 0.3 * a.sin()), buttons, 0)
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let bad = v1::Pose::from_parts([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]);
        let seq = phone.send_pose(bad, vec![], 0).await.unwrap();
        let fb = phone.feedback_for(seq).await.unwrap();
        assert!(fb.error.contains("quaternion"), "{}", fb.error);
        let seq = phone
            .send_pose(pose(0.0, 0.0, 0.0), vec![buttons::clutch_disengage()], 0)
            .await
            .unwrap();
        phone.feedback_for(seq).await.unwrap();
    })
    .await;
    let (verdict, ending) = replay_file(&log, None).unwrap();
    let Verdict::Identical(counts) = verdict else {
        panic!("{verdict:?}")
    };
    // The session went through the arbiter. A server behind its phone folds samples into fewer rounds
    // (latest wins), so the bounds are what survives heavy folding: the bind, the engage, a few motion
    // rounds, the refused quaternion and the disengage (both awaited, so never folded away). Decisions: the
    // engage, the refusal and the disengage at least.
    assert!(counts.inputs >= 6, "{counts:?}");
    assert!(counts.commands >= 3, "{counts:?}");
    assert!(counts.decisions >= 3, "{counts:?}");
    assert_eq!(ending, "the log ends: the arm was shut down");
    keep_as_fixture(&log, "phone-session.flight");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_session_replays_to_the_same_commands_and_decisions() {
    let logs = tempfile::tempdir().unwrap();
    let log = logged(logs.path(), |client| async move {
        let mut policy = client
            .policy(phone2act_tests::policy_hello(&["main"], "flight-test", 2.0))
            .await
            .unwrap();
        for round in 0..2 {
            // Observations queue while the previous chunk plays: the chunk answers the newest one (the
            // first that is not followed by another within 20 ms), so that its steps lie ahead.
            let mut obs = policy.next_observation().await.unwrap();
            while let Ok(newer) =
                tokio::time::timeout(Duration::from_millis(20), policy.next_observation()).await
            {
                obs = newer.unwrap();
            }
            let chunk = v1::ActionChunk {
                arm: "main".into(),
                steps: (1..=20)
                    .map(|k| v1::ActionStep {
                        values: vec![
                            0.003 * f64::from(k),
                            0.0,
                            if round == 1 { -0.002 } else { 0.0 },
                            0.0,
                            0.0,
                            0.02,
                            0.5,
                        ],
                    })
                    .collect(),
                step_period_s: 0.05,
                observation_id: obs.observation_id,
                mode: v1::ActionMode::DeltaEe as i32,
                blend_steps: 0,
                keep_steps: 0,
            };
            // 20 steps of 50 ms: the chunk lies ahead unless answering took a second.
            policy.push_chunk_checked(&client, chunk).await.unwrap();
            tokio::time::sleep(Duration::from_millis(1100)).await;
        }
        // Silent past its timeout: the arm is taken back and the policy told.
        tokio::time::sleep(Duration::from_millis(2300)).await;
        drop(policy);
    })
    .await;
    let (verdict, _) = replay_file(&log, None).unwrap();
    let Verdict::Identical(counts) = verdict else {
        panic!("{verdict:?}")
    };
    // Claim, two chunks, their steps played by ticks (a chunk that arrived late skips the steps it missed).
    assert!(counts.inputs >= 20, "{counts:?}");
    assert!(counts.commands >= 10, "{counts:?}");
    keep_as_fixture(&log, "policy-session.flight");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_log_replayed_under_a_stricter_gate_names_the_first_decision_that_changes() {
    let logs = tempfile::tempdir().unwrap();
    let log = logged(logs.path(), |client| async move {
        let mut phone = engaged_phone(&client).await;
        for i in 1..=10u32 {
            // 5 mm steps: accepted by the default gate (6 cm), dropped by one that allows 1 mm.
            let seq = phone
                .send_pose(pose(0.005 * f64::from(i), 0.0, 0.0), vec![], 0)
                .await
                .unwrap();
            phone.feedback_for(seq).await.unwrap();
        }
    })
    .await;
    let data = tempfile::tempdir().unwrap();
    let mut stricter = default_config(data.path());
    stricter.arms[0].teleop.gate.jump_position_m = 0.001;
    let (verdict, _) = replay_file(&log, Some(&stricter)).unwrap();
    let Verdict::Differs(d) = verdict else {
        panic!("a stricter gate changed nothing: {verdict:?}")
    };
    assert!(d.input.starts_with("Teleop"), "{d}");
    // The stricter gate drops the first 5 mm step that the recorded one passed.
    assert_eq!(d.field, "decision", "{d}");
    assert!(!d.recorded.contains("RejectedJump"), "{d}");
    assert!(d.replayed.contains("RejectedJump"), "{d}");
    // Under its own configuration the same log replays identically.
    assert!(matches!(
        replay_file(&log, None).unwrap().0,
        Verdict::Identical(_)
    ));
}
