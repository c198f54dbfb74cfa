//! The one control path end to end (issue 4): phones and policies drive simulated arms through the real
//! server over real gRPC sockets.

use phone2act_sdk::buttons;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions};
use phone2act_tests::{TestServer, bimanual_config, default_config, pos, sim_pose_of};
use std::time::Duration;
use tokio_stream::StreamExt;

fn phone_pose(x: f64, y: f64, z: f64) -> v1::Pose {
    v1::Pose::from_parts([x, y, z], [0.0, 0.0, 0.0, 1.0])
}

async fn settle() {
    tokio::time::sleep(Duration::from_millis(400)).await;
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Engages the clutch at the phone origin and returns the arm's target right after.
async fn engage(session: &mut phone2act_sdk::TeleopSession) -> v1::TeleopFeedback {
    let seq = session
        .send_pose(phone_pose(0.0, 0.0, 0.0), vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb = session.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    assert!(fb.arm_state.as_ref().unwrap().engaged, "engage must engage");
    fb
}

/// Walks the phone from its origin along `direction` in 1 cm steps to `distance_m`.
async fn walk(
    session: &mut phone2act_sdk::TeleopSession,
    direction: [f64; 3],
    distance_m: f64,
) -> v1::TeleopFeedback {
    let steps = (distance_m / 0.01).round() as usize;
    let mut last = None;
    for i in 1..=steps {
        let d = i as f64 * 0.01;
        let seq = session
            .send_pose(
                phone_pose(direction[0] * d, direction[1] * d, direction[2] * d),
                vec![],
                0,
            )
            .await
            .unwrap();
        last = Some(session.feedback_for(seq).await.unwrap());
    }
    last.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_phone_stream_moves_the_sim_arm() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let before = sim_pose_of(&client, "main").await;

    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let engaged = engage(&mut phone).await;
    let start_target = pos(engaged
        .arm_state
        .as_ref()
        .unwrap()
        .robot_from_target
        .as_ref()
        .unwrap());
    assert!(
        dist(start_target, before) < 0.01,
        "engaging must not move the target: {start_target:?} vs {before:?}"
    );

    // Phone moves 8 cm forward (-Z in the WebXR frame).
    let fb = walk(&mut phone, [0.0, 0.0, -1.0], 0.08).await;
    let state = fb.arm_state.unwrap();
    assert_eq!(fb.echoed_seq, 9);
    assert!(fb.server_receive_time_ns > 0 && fb.server_send_time_ns >= fb.server_receive_time_ns);
    let target = pos(state.robot_from_target.as_ref().unwrap());
    let moved = dist(target, start_target);
    assert!(
        (moved - 0.08).abs() < 0.005,
        "target moved {moved} m for an 8 cm phone move"
    );

    settle().await;
    let after = sim_pose_of(&client, "main").await;
    assert!(
        dist(after, target) < 0.01,
        "sim arm at {after:?}, target {target:?}"
    );
    assert!(
        dist(after, before) > 0.06,
        "sim arm did not move: {before:?} -> {after:?}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_clutch_cycle_re_indexes_without_moving_the_arm() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    engage(&mut phone).await;
    let fb = walk(&mut phone, [0.0, 0.0, -1.0], 0.05).await;
    let held = pos(fb.arm_state.unwrap().robot_from_target.as_ref().unwrap());

    // Disengage, carry the phone back 30 cm (robot must hold), re-engage there.
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, -0.05), vec![buttons::clutch_disengage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(!fb.arm_state.unwrap().engaged);
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, 0.25), vec![], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(
        dist(
            pos(fb.arm_state.unwrap().robot_from_target.as_ref().unwrap()),
            held
        ) < 1e-9
    );
    settle().await;
    let measured = sim_pose_of(&client, "main").await;

    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, 0.25), vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let state = fb.arm_state.unwrap();
    assert!(state.engaged);
    let re_indexed = pos(state.robot_from_target.as_ref().unwrap());
    assert!(
        dist(re_indexed, measured) < 1e-3,
        "re-index must start from the measured pose"
    );
    // The next move is relative to the new phone origin: 3 cm, not 33 cm.
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, 0.22), vec![], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let state = fb.arm_state.unwrap();
    assert_eq!(
        state.last_decision.as_ref().unwrap().verdict(),
        v1::GateVerdict::Accepted
    );
    let moved = dist(pos(state.robot_from_target.as_ref().unwrap()), re_indexed);
    assert!((moved - 0.03).abs() < 0.003, "moved {moved}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jump_is_rejected_and_the_arm_stays() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let fb = engage(&mut phone).await;
    let start = pos(fb.arm_state.unwrap().robot_from_target.as_ref().unwrap());
    // 12 cm in one sample: over the 60 mm jump threshold.
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, -0.12), vec![], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let state = fb.arm_state.unwrap();
    let decision = state.last_decision.as_ref().unwrap();
    assert_eq!(decision.verdict(), v1::GateVerdict::RejectedJump, "{decision:?}");
    assert!(decision.reason.contains("jump"), "{}", decision.reason);
    assert!(
        dist(pos(state.robot_from_target.as_ref().unwrap()), start) < 1e-9,
        "a rejected jump must not move"
    );
    assert!(state.commands_rejected >= 1);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_teleop_input_gets_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;

    // Unknown arm: the stream ends with NOT_FOUND naming the arm and the known ones.
    let err = client
        .teleop("ghost", TeleopOptions::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("NotFound") || err.contains("not found"), "{err}");
    assert!(err.contains("ghost") && err.contains("main"), "{err}");

    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let fb = engage(&mut phone).await;
    let start = pos(fb.arm_state.unwrap().robot_from_target.as_ref().unwrap());
    // NaN pose: a per-sample error, the stream and the arm unharmed.
    let seq = phone
        .send_pose(phone_pose(f64::NAN, 0.0, 0.0), vec![], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(
        fb.error.contains("NaN") || fb.error.contains("finite"),
        "{}",
        fb.error
    );
    // Non-unit quaternion.
    let bad_q = v1::Pose::from_parts([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]);
    let seq = phone.send_pose(bad_q, vec![], 0).await.unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.contains("quaternion"), "{}", fb.error);
    assert!(
        dist(
            pos(fb.arm_state.unwrap().robot_from_target.as_ref().unwrap()),
            start
        ) < 1e-9
    );
    // Still works afterwards.
    let fb = walk(&mut phone, [0.0, 0.0, -1.0], 0.02).await;
    assert!(fb.error.is_empty());

    // A second phone on the same arm is refused unless it takes over.
    let err = client
        .teleop("main", TeleopOptions::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("AlreadyExists") || err.contains("already"), "{err}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_phones_drive_left_and_right_independently() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(bimanual_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let left_before = sim_pose_of(&client, "left").await;
    let right_before = sim_pose_of(&client, "right").await;
    let mut left = client.teleop("left", TeleopOptions::default()).await.unwrap();
    let mut right = client.teleop("right", TeleopOptions::default()).await.unwrap();
    engage(&mut left).await;
    engage(&mut right).await;
    let (l, r) = tokio::join!(
        walk(&mut left, [0.0, 0.0, -1.0], 0.06),
        walk(&mut right, [0.0, 1.0, 0.0], 0.04)
    );
    let l = pos(l.arm_state.unwrap().robot_from_target.as_ref().unwrap());
    let r = pos(r.arm_state.unwrap().robot_from_target.as_ref().unwrap());
    assert!(
        (dist(l, left_before) - 0.06).abs() < 0.006,
        "left moved {}",
        dist(l, left_before)
    );
    assert!(
        (dist(r, right_before) - 0.04).abs() < 0.006,
        "right moved {}",
        dist(r, right_before)
    );
    // Different phone motions give different directions: no cross-talk.
    let dl = [
        l[0] - left_before[0],
        l[1] - left_before[1],
        l[2] - left_before[2],
    ];
    let dr = [
        r[0] - right_before[0],
        r[1] - right_before[1],
        r[2] - right_before[2],
    ];
    let cos = (dl[0] * dr[0] + dl[1] * dr[1] + dl[2] * dr[2]) / (0.06 * 0.04);
    assert!(cos.abs() < 0.2, "left and right moved alike: {dl:?} {dr:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_phone_leaves_the_arm_holding() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    engage(&mut phone).await;
    walk(&mut phone, [1.0, 0.0, 0.0], 0.03).await;
    // Stay silent past the staleness timeout (0.5 s by default).
    tokio::time::sleep(Duration::from_millis(900)).await;
    let arms = client.system().list_arms().await.unwrap();
    let decision = arms[0].last_decision.as_ref().unwrap();
    assert_eq!(decision.verdict(), v1::GateVerdict::HeldStale, "{decision:?}");
    let held = sim_pose_of(&client, "main").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(
        dist(sim_pose_of(&client, "main").await, held) < 1e-4,
        "the arm must hold still"
    );
    server.shutdown().await.unwrap();
}

fn chunk_steps(n: usize, dx_total: f64) -> Vec<v1::ActionStep> {
    // Delta-EE actions relative to the observation's pose: walk +x linearly, gripper open.
    (1..=n)
        .map(|k| v1::ActionStep {
            values: vec![dx_total * k as f64 / n as f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        })
        .collect()
}

async fn open_policy(client: &Client, arms: &[&str]) -> phone2act_sdk::PolicySession {
    client
        .policy(phone2act_tests::policy_hello(arms, "test", 2.0))
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_chunk_executes_through_the_gate() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let mut policy = open_policy(&client, &["main"]).await;
    let layout = &policy.ready().arms[0];
    assert_eq!(layout.action_names.len(), 7, "{:?}", layout.action_names);
    let obs = policy.next_observation().await.unwrap();
    let start = pos(obs.arms[0].robot_from_ee.as_ref().unwrap());
    let chunk = v1::ActionChunk {
        arm: "main".into(),
        steps: chunk_steps(10, 0.05),
        step_period_s: 0.05,
        observation_id: obs.observation_id,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    let accepted = policy.push_chunk_checked(&client, chunk).await.unwrap();
    assert_eq!(accepted.steps_scheduled + accepted.steps_skipped, 10);
    assert!(accepted.steps_scheduled >= 8, "{accepted:?}");
    tokio::time::sleep(Duration::from_millis(900)).await;
    let end = sim_pose_of(&client, "main").await;
    assert!(
        (end[0] - start[0] - 0.05).abs() < 0.008,
        "x moved {} (start {start:?}, end {end:?})",
        end[0] - start[0]
    );
    assert!((end[1] - start[1]).abs() < 0.005 && (end[2] - start[2]).abs() < 0.005);

    // Bad chunks: wrong width, NaN, unknown arm, each a clear status; the session lives on.
    let mut bad = v1::ActionChunk {
        arm: "main".into(),
        steps: vec![v1::ActionStep { values: vec![0.0; 5] }],
        step_period_s: 0.05,
        observation_id: 0,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    let err = policy
        .push_chunk_checked(&client, bad.clone())
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("InvalidArgument") && err.contains('7') && err.contains('5'),
        "{err}"
    );
    bad.steps = vec![v1::ActionStep {
        values: vec![f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    }];
    let err = policy
        .push_chunk_checked(&client, bad.clone())
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("InvalidArgument"), "{err}");
    bad.arm = "ghost".into();
    let err = policy
        .push_chunk_checked(&client, bad)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("NotFound"), "{err}");
    policy.next_observation().await.unwrap();
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operator_takes_over_from_a_running_policy() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    settle().await;
    let mut policy = open_policy(&client, &["main"]).await;
    let obs = policy.next_observation().await.unwrap();
    // A long, slow chunk: 4 s of motion along +x.
    let chunk = v1::ActionChunk {
        arm: "main".into(),
        steps: chunk_steps(80, 0.08),
        step_period_s: 0.05,
        observation_id: obs.observation_id,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    policy.push_chunk_checked(&client, chunk).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    // A second policy cannot take the arm.
    let err = client
        .policy(phone2act_tests::policy_hello(&["main"], "second", 0.0))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("FailedPrecondition") || err.contains("AlreadyExists"),
        "{err}"
    );

    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let fb = engage(&mut phone).await;
    let state = fb.arm_state.unwrap();
    assert_eq!(state.owner(), v1::ControlSource::Teleop);
    // The policy keeps the arm reserved and waits for a hand-back (tests/tests/hand_back.rs); its next chunk
    // is refused with the reason.
    assert!(state.waiting_policy_id.starts_with("test:"), "{state:?}");
    let obs = policy.next_observation().await.unwrap();
    let refused = policy
        .push_chunk_checked(
            &client,
            v1::ActionChunk {
                arm: "main".into(),
                steps: chunk_steps(10, 0.02),
                step_period_s: 0.05,
                observation_id: obs.observation_id,
                mode: v1::ActionMode::DeltaEe as i32,
                blend_steps: 0,
                keep_steps: 0,
            },
        )
        .await
        .unwrap_err()
        .to_string();
    assert!(refused.contains("waits for the operator"), "{refused}");
    // The chunk no longer drives the arm: it holds where the operator took over.
    let taken = sim_pose_of(&client, "main").await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(
        dist(sim_pose_of(&client, "main").await, taken) < 0.003,
        "the policy still moves the arm"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_watch_sees_the_teleop_owner() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    engage(&mut phone).await;
    let mut watch = client.system().watch_status(0.02).await.unwrap();
    let status = watch.next().await.unwrap().unwrap();
    assert_eq!(status.arms[0].owner(), v1::ControlSource::Teleop);
    assert!(status.arms[0].engaged);
    server.shutdown().await.unwrap();
}
