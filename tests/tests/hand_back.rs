//! The phone during a policy session (issue 27): a policy drives the simulated arm through the Policy API,
//! the operator takes it with the clutch through the Teleop stream (the path the gateway speaks for the phone
//! page), and the policy waits: it keeps the arm reserved and its chunks are refused, not executed. One
//! hand-back gives the arm back without moving it: chunks answering observations taken before the hand-back
//! are refused and the arm holds (no command at all), and the first chunk answering a fresh observation
//! drives from where the operator left the arm. Along the way the arm's status previews the policy's plan,
//! and the episode's events record the hand-back.

use phone2act_dataset::events::{EventKind, read_events};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, PolicySession, TeleopOptions, TeleopSession, buttons};
use phone2act_tests::{TestServer, arm_state, default_config, pos, sim_pose_of, wait_until};
use std::time::Duration;

const POLICY: &str = "hand-back-test";

fn phone_pose(x: f64, y: f64, z: f64) -> v1::Pose {
    v1::Pose::from_parts([x, y, z], [0.0, 0.0, 0.0, 1.0])
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// `n` relative steps walking `dx_m` along +x over the chunk, the gripper closing from 0 to `gripper_end`.
fn chunk(observation_id: u64, n: usize, dx_m: f64, gripper_end: f64) -> v1::ActionChunk {
    v1::ActionChunk {
        arm: "main".into(),
        steps: (1..=n)
            .map(|k| {
                let f = k as f64 / n as f64;
                v1::ActionStep {
                    values: vec![dx_m * f, 0.0, 0.0, 0.0, 0.0, 0.0, gripper_end * f],
                }
            })
            .collect(),
        step_period_s: 0.05,
        observation_id,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    }
}

/// The first observation taken after `after_ns` (server monotonic time), asking for one now so that the
/// queued ones (taken earlier) are read past quickly.
async fn observation_after(policy: &mut PolicySession, after_ns: i64) -> v1::Observation {
    policy.request_observation().await.unwrap();
    // Observations come at 20 Hz besides the one asked for; 10 s covers a stalled machine.
    tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let obs = policy.next_observation().await.unwrap();
            if obs.timestamp_ns > after_ns {
                return obs;
            }
        }
    })
    .await
    .expect("a fresh observation")
}

/// The next take-over or hand-back event on the session, skipping observations and chunk verdicts.
async fn next_turn(policy: &mut PolicySession) -> v1::policy_event::Event {
    // Sent as the input is handled, a few milliseconds away; 10 s covers a stalled machine.
    tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            match policy.next_event().await.unwrap() {
                Some(e @ (v1::policy_event::Event::Paused(_) | v1::policy_event::Event::Resumed(_))) => {
                    return e;
                }
                Some(_) => {}
                None => panic!("the session ended"),
            }
        }
    })
    .await
    .expect("a take-over or hand-back event")
}

/// Waits until the measured pose stops moving (two reads 100 ms apart within 0.2 mm); returns it.
async fn settled(client: &Client) -> [f64; 3] {
    let mut last = sim_pose_of(client, "main").await;
    // The sim reaches a held target within a few of its 20 ms periods; 10 s covers a stalled machine.
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        let now = sim_pose_of(client, "main").await;
        if dist(now, last) < 2e-4 {
            return now;
        }
        last = now;
    }
    panic!("the arm never settled");
}

async fn press(
    phone: &mut TeleopSession,
    pose: v1::Pose,
    button: Vec<v1::ButtonEvent>,
) -> v1::TeleopFeedback {
    let seq = phone.send_pose(pose, button, 0).await.unwrap();
    phone.feedback_for(seq).await.unwrap()
}

/// A phone that engages the clutch at its origin on "main", taking the arm; returns it and the arm's state it
/// was answered with (the phone drives).
async fn take_over(client: &Client) -> (TeleopSession, v1::ArmState) {
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let fb = press(
        &mut phone,
        phone_pose(0.0, 0.0, 0.0),
        vec![buttons::clutch_engage()],
    )
    .await;
    assert!(fb.error.is_empty(), "{}", fb.error);
    let state = fb.arm_state.unwrap();
    assert_eq!(state.owner(), v1::ControlSource::Teleop);
    (phone, state)
}

/// The embedded default's server on a temporary dataset directory, once its simulated arm reports a pose
/// (a claim needs one).
async fn sim_server() -> (tempfile::TempDir, TestServer, Client) {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    // The sim reports its first pose within a few bridge periods (10 s: a stalled machine).
    assert!(
        wait_until(Duration::from_secs(10), || async {
            arm_state(&client, "main").await.robot_from_ee.is_some()
        })
        .await
    );
    (dir, server, client)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_taken_over_policy_waits_and_a_hand_back_holds_until_a_fresh_chunk() {
    let (dir, server, client) = sim_server().await;
    let mut policy = client
        .policy(phone2act_tests::policy_hello(&["main"], POLICY, 5.0))
        .await
        .unwrap();
    let mut episodes = client.episodes();
    episodes.start("hand the arm back").await.unwrap();

    // The policy drives: 8 cm along +x over 4 s, the gripper closing to 0.8.
    let obs = policy.next_observation().await.unwrap();
    let start = pos(obs.arms[0].robot_from_ee.as_ref().unwrap());
    policy
        .push_chunk_checked(&client, chunk(obs.observation_id, 80, 0.08, 0.8))
        .await
        .unwrap();
    // The status previews the rest of the plan: at most 16 points of it, ending with its last target.
    let state = arm_state(&client, "main").await;
    let preview = state.plan_preview.expect("a driving policy's plan is previewed");
    assert!((2..=16).contains(&preview.positions_m.len()), "{preview:?}");
    assert_eq!(preview.positions_m.len(), preview.grippers.len());
    let last = preview.positions_m.last().unwrap();
    assert!(
        dist([last.x, last.y, last.z], [start[0] + 0.08, start[1], start[2]]) < 1e-6,
        "the preview ends at the chunk's last target: {last:?} from {start:?}"
    );
    assert!((preview.grippers.last().unwrap() - 0.8).abs() < 1e-9);
    // The arm moves (5 mm: a quarter of a second of the plan; 10 s covers a stalled machine).
    assert!(
        wait_until(Duration::from_secs(10), || async {
            dist(sim_pose_of(&client, "main").await, start) > 0.005
        })
        .await
    );

    // The operator takes over with the clutch: the policy waits instead of losing the arm.
    let (mut phone, state) = take_over(&client).await;
    assert!(
        state.waiting_policy_id.starts_with(&format!("{POLICY}:")),
        "{state:?}"
    );
    assert!(
        state.plan_preview.is_none(),
        "no plan plays while the policy waits"
    );
    // The session is told, rather than left to learn it from refused chunks.
    let paused = next_turn(&mut policy).await;
    assert!(
        matches!(&paused, v1::policy_event::Event::Paused(p) if p.arm == "main" && p.reason.contains("hand-back")),
        "{paused:?}"
    );
    // Its chunks are refused with the reason, and do not move the arm: the phone holds still, so does the arm.
    let held = settled(&client).await;
    let obs = observation_after(&mut policy, 0).await;
    let refused = policy
        .push_chunk_checked(&client, chunk(obs.observation_id, 10, 0.03, 0.0))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains("FailedPrecondition")
            && refused.contains("waits for the operator to hand the arm back"),
        "{refused}"
    );
    // The whole of the refused chunk's 0.5 s: had it been taken, it would have moved the arm by now; a stalled
    // machine can only hide a wrong acceptance, never fail a correct refusal.
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(
        dist(sim_pose_of(&client, "main").await, held) < 0.001,
        "a waiting policy's chunk moved the arm"
    );

    // The correction: 2 cm of phone motion, then the clutch out.
    for i in 1..=4 {
        press(&mut phone, phone_pose(0.0, 0.005 * f64::from(i), 0.0), vec![]).await;
    }
    let fb = press(
        &mut phone,
        phone_pose(0.0, 0.02, 0.0),
        vec![buttons::clutch_disengage()],
    )
    .await;
    assert!(!fb.arm_state.as_ref().unwrap().engaged);
    let corrected = settled(&client).await;
    assert!(
        // 2 cm of the phone, scaled by the arm's mapping.
        dist(corrected, held) > 0.01,
        "the correction did not move the arm: {held:?} -> {corrected:?}, {fb:?}"
    );
    // An observation from before the hand-back, which the policy answers late.
    let stale = observation_after(&mut policy, 0).await;

    // One gesture hands the arm back; nothing moves.
    let seq = phone.hand_back().await.unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    let resumed = next_turn(&mut policy).await;
    assert!(
        matches!(&resumed, v1::policy_event::Event::Resumed(r) if r.arm == "main"),
        "{resumed:?}"
    );
    let handed_back_ns = fb.server_send_time_ns;
    let state = fb.arm_state.unwrap();
    assert_eq!(state.owner(), v1::ControlSource::Policy);
    assert!(
        state.owner_id.starts_with(&format!("{POLICY}:")),
        "{}",
        state.owner_id
    );
    assert!(state.waiting_policy_id.is_empty());
    let sent_at_hand_back = state.commands_sent;
    // The stale answer (3 s long: most of it would still be ahead if it were taken) is refused, and the arm
    // holds: no command at all, the measured pose where it was.
    let stale_answer = policy
        .push_chunk_checked(&client, chunk(stale.observation_id, 60, 0.03, 0.0))
        .await;
    // A sixth of the stale chunk's 3 s: had it been taken, its first steps would have been sent by now; a stalled
    // machine can only hide a wrong acceptance, never fail a correct hold.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let state = arm_state(&client, "main").await;
    assert_eq!(
        state.commands_sent, sent_at_hand_back,
        "a command was sent between the hand-back and a fresh chunk"
    );
    let after_stale = sim_pose_of(&client, "main").await;
    assert!(
        dist(after_stale, corrected) < 0.001,
        "the arm moved after the hand-back: {corrected:?} -> {after_stale:?}"
    );
    println!(
        "hand-back: {} commands sent and {:.2} mm measured motion in 0.5 s after a stale chunk",
        state.commands_sent - sent_at_hand_back,
        dist(after_stale, corrected) * 1e3
    );
    let refused = stale_answer.unwrap_err().to_string();
    assert!(
        refused.contains("before the operator handed the arm back"),
        "{refused}"
    );

    // A chunk answering a fresh observation drives, from where the operator left the arm.
    // (After the hand-back, and after the wait above: the observations queued meanwhile are older than a
    // chunk's length.)
    let fresh = observation_after(&mut policy, handed_back_ns.max(state.feedback_time_ns)).await;
    assert!(fresh.timestamp_ns > handed_back_ns);
    let anchor = pos(fresh.arms[0].robot_from_ee.as_ref().unwrap());
    assert!(dist(anchor, corrected) < 0.001);
    policy
        .push_chunk_checked(&client, chunk(fresh.observation_id, 20, 0.02, 0.0))
        .await
        .unwrap();
    // 2 cm in 1 s; 10 s covers a stalled machine.
    assert!(
        wait_until(Duration::from_secs(10), || async {
            dist(
                sim_pose_of(&client, "main").await,
                [corrected[0] + 0.02, corrected[1], corrected[2]],
            ) < 0.002
        })
        .await,
        "the fresh chunk did not drive the arm from the corrected pose"
    );

    let saved = episodes.stop().await.unwrap().episode.unwrap();
    drop(phone);
    drop(policy);
    server.shutdown().await.unwrap();
    let events = read_events(dir.path(), saved.episode_index)
        .unwrap()
        .expect("the episode has an events sidecar");
    let resumes: Vec<_> = events
        .iter()
        .filter(|e| e.kind == EventKind::PolicyResume)
        .collect();
    assert_eq!(resumes.len(), 1, "{events:?}");
    assert_eq!(
        (resumes[0].arm.as_str(), resumes[0].detail.as_str()),
        ("main", POLICY)
    );
}

/// A policy that stops reading its stream (a long inference) still hears the take-over that happened
/// meanwhile: its observations (full RGB frames here, so the stream's buffers fill within a second) are
/// latest-only, while the take-over is queued. Before, events went into one short queue that a backlog of
/// observations filled, and the `ControlPaused` sent into a full queue was lost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_that_stops_reading_still_hears_the_take_over() {
    let (_dir, _server, client) = sim_server().await;
    let hello = v1::PolicyHello {
        image_encoding: v1::ImageEncoding::Rgb8 as i32,
        ..phone2act_tests::policy_hello(&["main"], POLICY, 60.0)
    };
    let mut policy = client.policy(hello).await.unwrap();
    // The camera's first frame comes within a few of its 15 fps periods; 10 s covers a stalled machine.
    let obs = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let obs = policy.next_observation().await.unwrap();
            if obs.frames.iter().any(|f| f.data.len() >= 320 * 240 * 3) {
                return obs;
            }
        }
    })
    .await
    .expect("observations with full frames");
    policy
        .push_chunk_checked(&client, chunk(obs.observation_id, 40, 0.02, 0.0))
        .await
        .unwrap();

    // The policy "infers" for 3 s without reading: 60 observations of 230 kB, more than the stream's
    // HTTP/2 window and every queue on the way hold. Then the operator takes the arm.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let (_phone, _) = take_over(&client).await;
    // (The phone stays bound, holding the arm, to the end of the test.)
    tokio::time::sleep(Duration::from_secs(1)).await;

    // Reading again, the take-over comes after at most the few observations already on their way.
    let mut observations_first = 0;
    let paused = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            match policy.next_event().await.unwrap() {
                Some(v1::policy_event::Event::Observation(_)) => observations_first += 1,
                Some(e @ v1::policy_event::Event::Paused(_)) => return e,
                Some(_) => {}
                None => panic!("the session ended"),
            }
        }
    })
    .await
    .unwrap_or_else(|_| panic!("no ControlPaused: lost while the policy did not read"));
    assert!(
        matches!(&paused, v1::policy_event::Event::Paused(p) if p.arm == "main"),
        "{paused:?}"
    );
    // What was buffered before the take-over: the stream's window (2 MB, about 9 frames) and two slots.
    assert!(
        observations_first < 20,
        "{observations_first} stale observations before the take-over"
    );
}
