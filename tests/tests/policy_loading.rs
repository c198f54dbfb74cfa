//! A policy may load (issue 27): a policy session holds its arm while it loads, bounded by the arm's
//! `chunk.max_loading_s`, over the real Policy API. The tests shorten the limit to a couple of seconds (the
//! arbiter's unit tests run the default 300 s and a three-minute load with time as an argument); what they
//! check is the same rule: the silence timeout waits, the first chunk drives, the limit releases, the
//! operator can take over.

use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, PolicySession, TeleopOptions, buttons};
use phone2act_tests::{TestServer, arm_state, default_config, sim_pose_of, wait_until};
use std::time::{Duration, Instant};

/// The policy's silence timeout in these tests: a loading policy must outlive it many times over.
const SILENCE_S: f64 = 0.2;

async fn server_with_loading_limit(dir: &std::path::Path, limit_s: f64) -> (TestServer, Client) {
    let mut config = default_config(dir);
    config.arms[0].chunk.max_loading_s = limit_s;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    // The sim reports its first pose within a few bridge periods; a claim needs it.
    assert!(
        wait_until(Duration::from_secs(10), || async {
            arm_state(&client, "main").await.robot_from_ee.is_some()
        })
        .await
    );
    (server, client)
}

/// Sends `PolicyLoading` and returns the server's answer.
async fn say_loading(policy: &mut PolicySession) -> v1::LoadingAccepted {
    policy.loading().await.unwrap();
    tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            if let Some(v1::policy_event::Event::Loading(answer)) = policy.next_event().await.unwrap() {
                return answer;
            }
        }
    })
    .await
    .expect("the server answers PolicyLoading")
}

async fn revocation(policy: &mut PolicySession, within: Duration) -> v1::ControlRevoked {
    tokio::time::timeout(within, async {
        loop {
            if let Some(v1::policy_event::Event::Revoked(r)) = policy.next_event().await.unwrap() {
                return r;
            }
        }
    })
    .await
    .expect("the policy is told it lost the arm")
}

/// A server whose arm's loading limit is `limit_s`, and a policy session `name` that owns its arm and has
/// said it is loading, with the server's answer.
async fn loading_policy(
    dir: &std::path::Path,
    limit_s: f64,
    name: &str,
) -> (TestServer, Client, PolicySession, v1::LoadingAccepted) {
    let (server, client) = server_with_loading_limit(dir, limit_s).await;
    let mut policy = client
        .policy(phone2act_tests::policy_hello(&["main"], name, SILENCE_S))
        .await
        .unwrap();
    let answer = say_loading(&mut policy).await;
    (server, client, policy, answer)
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loading_policy_holds_its_arm_then_its_first_chunk_drives() {
    let dir = tempfile::tempdir().unwrap();
    // Long enough that the loading below never reaches it, even on a stalled machine.
    let (server, client, mut policy, answer) = loading_policy(dir.path(), 60.0, "big-vla").await;
    assert_eq!(answer.arms, ["main"], "{answer:?}");
    assert!(answer.error.is_empty());
    assert!(
        answer.remaining_s > 50.0 && answer.remaining_s <= 60.0,
        "{answer:?}"
    );
    let state = arm_state(&client, "main").await;
    assert!(state.policy_loading, "status says the policy is loading");
    assert_eq!(state.owner(), v1::ControlSource::Policy);
    assert!(state.last_decision.unwrap().reason.contains("loading"));
    let held = sim_pose_of(&client, "main").await;

    // Ten silence timeouts pass: still the policy's, still holding.
    tokio::time::sleep(Duration::from_secs_f64(10.0 * SILENCE_S)).await;
    let again = say_loading(&mut policy).await;
    assert!(
        again.remaining_s <= answer.remaining_s,
        "a keep-alive never extends the limit"
    );
    let state = arm_state(&client, "main").await;
    assert_eq!(state.owner(), v1::ControlSource::Policy);
    assert!(state.policy_loading);
    assert!(
        dist(sim_pose_of(&client, "main").await, held) < 0.002,
        "the arm holds while loading"
    );

    // The first chunk drives: 3 cm along +x over 0.5 s, relative to the arm's pose when it arrives
    // (observation 0: the observations queued while loading are older than the chunk's steps).
    let start = sim_pose_of(&client, "main").await;
    let chunk = v1::ActionChunk {
        arm: "main".into(),
        steps: (1..=10)
            .map(|k| v1::ActionStep {
                values: vec![0.003 * f64::from(k), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            })
            .collect(),
        step_period_s: 0.05,
        observation_id: 0,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    policy.push_chunk_checked(&client, chunk).await.unwrap();
    assert!(
        !arm_state(&client, "main").await.policy_loading,
        "the first chunk ends the loading"
    );
    // The sim follows within its joint time constant; 10 s covers a stalled machine.
    assert!(
        wait_until(Duration::from_secs(10), || async {
            (sim_pose_of(&client, "main").await[0] - start[0] - 0.03).abs() < 0.006
        })
        .await,
        "the chunk moved the arm 3 cm (from {start:?} to {:?})",
        sim_pose_of(&client, "main").await
    );
    // Driving again, the silence timeout applies: silent past it, the arm is released.
    let revoked = revocation(&mut policy, Duration::from_secs(10)).await;
    assert!(revoked.reason.contains("silent"), "{}", revoked.reason);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_loading_past_the_limit_is_released_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let limit_s = 1.5;
    // The server's loading clock starts after this instant.
    let started = Instant::now();
    let (server, client, mut policy, answer) = loading_policy(dir.path(), limit_s, "cold-gpu").await;
    assert_eq!(answer.arms, ["main"]);
    let held = sim_pose_of(&client, "main").await;
    // Keep-alives all along: the limit counts from the first one.
    let revoked = tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            tokio::select! {
                event = policy.next_event() => {
                    if let Some(v1::policy_event::Event::Revoked(r)) = event.unwrap() {
                        return r;
                    }
                }
                () = tokio::time::sleep(Duration::from_millis(300)) => policy.loading().await.unwrap(),
            }
        }
    })
    .await
    .expect("released at the loading limit despite keep-alives");
    // Not before the limit (the server's clock starts at or after `started`).
    assert!(
        started.elapsed().as_secs_f64() >= limit_s,
        "{:?}",
        started.elapsed()
    );
    assert!(revoked.reason.contains("loading limit"), "{}", revoked.reason);
    let state = arm_state(&client, "main").await;
    assert_eq!(state.owner(), v1::ControlSource::None);
    assert!(!state.policy_loading);
    assert!(state.last_decision.unwrap().reason.contains("loading limit"));
    assert!(
        dist(sim_pose_of(&client, "main").await, held) < 0.002,
        "released holding"
    );
    // A loading message from the session that lost its arm is answered with the reason.
    let refused = say_loading(&mut policy).await;
    assert!(
        refused.arms.is_empty() && !refused.error.is_empty(),
        "{refused:?}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operator_takes_over_from_a_loading_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (server, client, mut policy, _) = loading_policy(dir.path(), 60.0, "big-vla").await;
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    let state = fb.arm_state.unwrap();
    assert!(state.engaged && !state.policy_loading);
    assert_eq!(state.owner(), v1::ControlSource::Teleop);
    // The loading policy waits for a hand-back (tests/tests/hand_back.rs); its keep-alive says why nothing
    // holds for it now.
    assert!(state.waiting_policy_id.starts_with("big-vla:"), "{state:?}");
    let refused = say_loading(&mut policy).await;
    assert!(
        refused.arms.is_empty() && refused.error.contains("waits"),
        "{refused:?}"
    );
    server.shutdown().await.unwrap();
}
