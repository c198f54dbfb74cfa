//! Who drove each frame (issue 27): a policy drives the simulated arm through the Policy API, the operator
//! takes over from the phone (the Teleop stream the gateway speaks for the phone page and the app), corrects,
//! releases, and hands the arm back to the policy, which waited. The dataset records LeRobot's DAgger
//! column `intervention` at every frame, the events sidecar says which arm and which policy, and the
//! episode's provenance names the policy.

use phone2act_dataset::events::{EpisodeEvent, EventKind, read_events};
use phone2act_dataset::parquet_io::{Row, read_rows};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, PolicySession, TeleopOptions, TeleopSession, buttons};
use phone2act_server::config::DatasetFormat;
use phone2act_tests::{
    TestServer, arm_state, bimanual_config, default_config, keep_for_conformance, wait_until,
};
use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;

const POLICY: &str = "dagger-test-policy";
const FPS: f64 = 20.0;

fn phone_pose(x: f64, y: f64, z: f64) -> v1::Pose {
    v1::Pose::from_parts([x, y, z], [0.0, 0.0, 0.0, 1.0])
}

/// Answers every observation with a short chunk for each of `arms` creeping along +x (4 mm/s, relative to
/// that observation) until the session loses them; returns why it lost them. While it waits for a hand-back
/// of an arm, that arm's chunks are refused (rejected events) and it keeps answering.
fn drive(mut policy: PolicySession, arms: &'static [&'static str]) -> JoinHandle<String> {
    tokio::spawn(async move {
        loop {
            match policy.next_event().await {
                Ok(Some(v1::policy_event::Event::Observation(obs))) => {
                    for arm in arms {
                        let chunk = v1::ActionChunk {
                            arm: (*arm).into(),
                            steps: (1..=10)
                                .map(|k| v1::ActionStep {
                                    values: vec![0.0002 * f64::from(k), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                                })
                                .collect(),
                            step_period_s: 0.05,
                            observation_id: obs.observation_id,
                            mode: v1::ActionMode::DeltaEe as i32,
                            blend_steps: 0,
                            keep_steps: 0,
                        };
                        if policy.push_chunk(chunk).await.is_err() {
                            return "session closed".to_owned();
                        }
                    }
                }
                Ok(Some(v1::policy_event::Event::Revoked(r))) => return r.reason,
                Ok(Some(_)) => {}
                Ok(None) | Err(_) => return "session ended".to_owned(),
            }
        }
    })
}

async fn policy_drives(client: &Client) -> bool {
    policy_drives_arm(client, "main").await
}

async fn policy_drives_arm(client: &Client, arm: &str) -> bool {
    // The policy's first chunk arrives within one observation period (50 ms); 10 s covers a stalled machine.
    wait_until(Duration::from_secs(10), || async {
        arm_state(client, arm).await.owner() == v1::ControlSource::Policy
    })
    .await
}

/// The operator hands `arm` back with the phone's gesture; the waiting policy then drives it again.
async fn hand_back(phone: &mut TeleopSession, client: &Client, arm: &str) {
    let seq = phone.hand_back().await.unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.is_empty(), "{}", fb.error);
    assert!(
        policy_drives_arm(client, arm).await,
        "the policy did not take {arm} back"
    );
}

/// Per frame, whether a `start` .. `stop` span of the events sidecar is open there.
fn spans(events: &[EpisodeEvent], frames: usize, start: EventKind, stop: EventKind) -> Vec<bool> {
    let mut state = false;
    let mut next = events.iter().peekable();
    (0..frames)
        .map(|i| {
            while let Some(e) = next.next_if(|e| e.frame_index as usize <= i) {
                if e.kind == start {
                    state = true;
                } else if e.kind == stop {
                    state = false;
                }
            }
            state
        })
        .collect()
}

fn position(row: &Row) -> [f64; 3] {
    [
        f64::from(row.action[0]),
        f64::from(row.action[1]),
        f64::from(row.action[2]),
    ]
}

fn read(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .unwrap()
}

async fn human_in_the_loop(format: DatasetFormat, conformance_name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.recorder.format = format;
    config.recorder.intervention = true;
    config.recorder.fps = FPS;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();

    let first = client
        .policy(phone2act_tests::policy_hello(&["main"], POLICY, 2.0))
        .await
        .unwrap();
    let first = drive(first, &["main"]);
    assert!(policy_drives(&client).await, "the policy never drove the arm");
    let mut episodes = client.episodes();
    episodes.start("correct the policy").await.unwrap();
    // About 20 policy frames before the take-over (how many does not matter: every frame is checked).
    tokio::time::sleep(Duration::from_secs(1)).await;

    // Take-over: the clutch engages at the phone's origin and the policy waits.
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let engage_sent = Instant::now();
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, 0.0), vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let engaged_at = Instant::now();
    assert!(
        fb.error.is_empty() && fb.arm_state.unwrap().engaged,
        "{}",
        fb.error
    );
    assert!(
        arm_state(&client, "main")
            .await
            .waiting_policy_id
            .starts_with(&format!("{POLICY}:")),
        "the policy waits for the hand-back"
    );
    // The correction: 3 cm along the phone's +y streamed as a phone streams it, 1 mm a sample about every
    // 15 ms, each answered before the next. (Steps 150 ms apart, as this once sent, let a loaded machine stretch
    // a gap past the 0.3 s stale timeout, and the re-index after it absorbed a whole centimetre; here a stall
    // costs at most one millimetre.)
    for i in 1..=30 {
        let seq = phone
            .send_pose(phone_pose(0.0, 0.001 * f64::from(i), 0.0), vec![], 0)
            .await
            .unwrap();
        phone.feedback_for(seq).await.unwrap();
        tokio::time::sleep(Duration::from_millis(15)).await;
    }
    tokio::time::sleep(Duration::from_millis(150)).await;
    let release_sent = Instant::now();
    let seq = phone
        .send_pose(phone_pose(0.0, 0.03, 0.0), vec![buttons::clutch_disengage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let released_at = Instant::now();
    assert!(!fb.arm_state.unwrap().engaged);

    // Hand-back: the policy drives again; its chunks answer fresh observations.
    hand_back(&mut phone, &client, "main").await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let saved = episodes.stop().await.unwrap().episode.unwrap();
    assert!(!first.is_finished(), "the policy session lost the arm");
    first.abort();
    drop(phone);
    server.shutdown().await.unwrap();

    let root = dir.path();
    let data = match format {
        DatasetFormat::V30 => root.join("data/chunk-000/file-000.parquet"),
        DatasetFormat::V21 => root.join("data/chunk-000/episode_000000.parquet"),
    };
    let rows = read_rows(&data).unwrap();
    assert_eq!(rows.len() as u64, saved.length_frames);
    let flags: Vec<bool> = rows
        .iter()
        .map(|r| r.intervention.expect("every frame has an intervention value"))
        .collect();
    let events = read_events(root, 0)
        .unwrap()
        .expect("the episode has an events sidecar");
    let human = spans(
        &events,
        rows.len(),
        EventKind::ClutchEngage,
        EventKind::ClutchRelease,
    );
    let policy = spans(&events, rows.len(), EventKind::PolicyStart, EventKind::PolicyStop);

    // The column is the arbiter's driver at every frame: a person exactly where the clutch was in, never
    // where a policy drove, and the policy everywhere before the take-over.
    let first_human = flags.iter().position(|&f| f).expect("the take-over is recorded");
    let after = first_human + flags[first_human..].iter().take_while(|&&f| f).count();
    assert!(
        flags[after..].iter().all(|&f| !f),
        "one take-over, one run of intervention frames: {flags:?}"
    );
    for (i, &f) in flags.iter().enumerate() {
        assert_eq!(
            f, human[i],
            "frame {i}: intervention {f}, clutch engaged {}",
            human[i]
        );
        assert!(
            !(human[i] && policy[i]),
            "frame {i}: a person and a policy both drove"
        );
        if i < first_human {
            assert!(policy[i], "frame {i}: the policy drove before the take-over");
        }
    }
    let second_start = policy[after..]
        .iter()
        .position(|&p| p)
        .map(|k| after + k)
        .expect("the policy drives again after the hand-back");
    assert!(policy[second_start..].iter().all(|&p| p), "{policy:?}");
    for e in events
        .iter()
        .filter(|e| matches!(e.kind, EventKind::PolicyStart | EventKind::PolicyStop))
    {
        assert_eq!((e.arm.as_str(), e.detail.as_str()), ("main", POLICY), "{e:?}");
    }
    // The run is as long as the phone drove. The server engaged between `engage_sent` and `engaged_at` and
    // released between `release_sent` and `released_at`; the frames add one tick of rounding at each end and
    // a sample captured up to one bridge period (20 ms) before its tick; a late tick (counted) may move a
    // boundary by one more. A pause would drop frames, and the loaded machine may pause: then only the upper
    // bound holds.
    let n_human = after - first_human;
    let margin = 2.0 + saved.late_ticks as f64;
    let most = (released_at - engage_sent).as_secs_f64() * FPS + margin;
    let least = (release_sent - engaged_at).as_secs_f64() * FPS - margin;
    assert!(
        n_human as f64 <= most,
        "{n_human} intervention frames, at most {most:.1}"
    );
    if saved.paused_ticks == 0 {
        assert!(
            n_human as f64 >= least,
            "{n_human} intervention frames, at least {least:.1}"
        );
    }
    // The correction is in the actions the person's frames record (3 cm of phone motion), while the policy's
    // own frames before it crept at 4 mm/s.
    let (a, b) = (position(&rows[first_human]), position(&rows[after - 1]));
    let moved_m = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    assert!(moved_m > 0.015, "the correction moved the target {moved_m} m");

    // LeRobot's DAgger feature, the policy in the provenance, GR00T's modality.json.
    let info = read(&root.join("meta/info.json"));
    assert_eq!(
        info["features"]["intervention"],
        json!({"dtype": "bool", "shape": [1], "names": null})
    );
    let provenance = read(&root.join("meta/phone2act_provenance.json"));
    assert_eq!(provenance["episodes"][0]["policies"], json!([POLICY]));
    let fraction = n_human as f64 / rows.len() as f64;
    match format {
        DatasetFormat::V30 => {
            let stats = &read(&root.join("meta/stats.json"))["intervention"];
            assert_eq!(
                (&stats["min"], &stats["max"]),
                (&json!([0.0]), &json!([1.0])),
                "{stats}"
            );
            assert!(
                (stats["mean"][0].as_f64().unwrap() - fraction).abs() < 1e-6,
                "{stats}"
            );
        }
        DatasetFormat::V21 => {
            let line = std::fs::read_to_string(root.join("meta/episodes_stats.jsonl")).unwrap();
            let stats: Value = serde_json::from_str(line.lines().next().unwrap()).unwrap();
            let stats = &stats["stats"]["intervention"];
            assert_eq!(
                (&stats["min"], &stats["max"]),
                (&json!([false]), &json!([true])),
                "{stats}"
            );
            assert!(
                (stats["mean"][0].as_f64().unwrap() - fraction).abs() < 1e-6,
                "{stats}"
            );
            let modality = read(&root.join("meta/modality.json"));
            assert_eq!(
                modality["annotation"]["human.intervention"],
                json!({"original_key": "intervention"})
            );
        }
    }
    keep_for_conformance(conformance_name, root);
    if let Some(dir) = std::env::var_os("PHONE2ACT_CONFORMANCE_DIR") {
        let expect = json!({"episodes": 1, "intervention_frames": n_human});
        std::fs::write(
            Path::new(&dir)
                .join(conformance_name)
                .join("phone2act_expect.json"),
            expect.to_string(),
        )
        .unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_correction_is_recorded_as_lerobot_dagger_data_v30() {
    human_in_the_loop(DatasetFormat::V30, "dagger_v30").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_correction_is_recorded_as_lerobot_dagger_data_v21() {
    human_in_the_loop(DatasetFormat::V21, "dagger_v21").await;
}

/// Bimanual: one policy session drives `left` and `right`; the operator corrects `left` only and hands it
/// back. The robot's one DAgger column is true exactly while the left clutch is in (LeRobot has one column
/// for the robot), the events say which arm the person drove, and the policy drove `right` all along: its
/// target kept creeping while `left` was corrected.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_correction_of_one_arm_of_two_is_recorded_for_that_arm_while_the_policy_drives_the_other() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = bimanual_config(dir.path());
    for cam in &mut config.cameras {
        (cam.width, cam.height, cam.fps) = (320, 240, 15.0);
    }
    config.recorder.intervention = true;
    config.recorder.fps = FPS;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let session = client
        .policy(phone2act_tests::policy_hello(&["left", "right"], POLICY, 2.0))
        .await
        .unwrap();
    let policy = drive(session, &["left", "right"]);
    assert!(policy_drives_arm(&client, "left").await && policy_drives_arm(&client, "right").await);
    let mut episodes = client.episodes();
    episodes.start("correct the left arm").await.unwrap();
    tokio::time::sleep(Duration::from_secs(1)).await;

    let mut phone = client.teleop("left", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(phone_pose(0.0, 0.0, 0.0), vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(
        fb.error.is_empty() && fb.arm_state.unwrap().engaged,
        "{}",
        fb.error
    );
    // 3 cm streamed 1 mm a sample, as in the single-arm test (a stall then costs at most one millimetre).
    for i in 1..=30 {
        let seq = phone
            .send_pose(phone_pose(0.0, 0.001 * f64::from(i), 0.0), vec![], 0)
            .await
            .unwrap();
        phone.feedback_for(seq).await.unwrap();
        tokio::time::sleep(Duration::from_millis(15)).await;
    }
    tokio::time::sleep(Duration::from_millis(150)).await;
    assert_eq!(
        arm_state(&client, "right").await.owner(),
        v1::ControlSource::Policy,
        "the other arm stays the policy's"
    );
    let seq = phone
        .send_pose(phone_pose(0.0, 0.03, 0.0), vec![buttons::clutch_disengage()], 0)
        .await
        .unwrap();
    phone.feedback_for(seq).await.unwrap();
    hand_back(&mut phone, &client, "left").await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let saved = episodes.stop().await.unwrap().episode.unwrap();
    assert!(!policy.is_finished(), "the policy session lost its arms");
    policy.abort();
    drop(phone);
    server.shutdown().await.unwrap();

    let root = dir.path();
    let rows = read_rows(&root.join("data/chunk-000/file-000.parquet")).unwrap();
    assert_eq!(rows.len() as u64, saved.length_frames);
    let flags: Vec<bool> = rows.iter().map(|r| r.intervention.unwrap()).collect();
    let events = read_events(root, 0).unwrap().expect("an events sidecar");
    let of_arm =
        |arm: &str| -> Vec<EpisodeEvent> { events.iter().filter(|e| e.arm == arm).cloned().collect() };
    let (left, right) = (of_arm("left"), of_arm("right"));
    let left_human = spans(
        &left,
        rows.len(),
        EventKind::ClutchEngage,
        EventKind::ClutchRelease,
    );
    assert_eq!(
        flags, left_human,
        "intervention is the left arm's clutch, frame by frame"
    );
    let first_human = flags.iter().position(|&f| f).expect("the correction is recorded");
    let after = first_human + flags[first_human..].iter().take_while(|&&f| f).count();
    assert!(flags[after..].iter().all(|&f| !f), "{flags:?}");
    assert!(
        left.iter()
            .any(|e| e.kind == EventKind::PolicyResume && e.detail == POLICY),
        "the hand-back is in the left arm's events: {left:?}"
    );
    assert!(
        right.iter().all(|e| !matches!(
            e.kind,
            EventKind::PolicyStop | EventKind::ClutchEngage | EventKind::ClutchRelease
        )),
        "nobody but the policy drove the right arm: {right:?}"
    );
    let right_policy = spans(&right, rows.len(), EventKind::PolicyStart, EventKind::PolicyStop);
    assert!(
        right_policy.iter().all(|&p| p),
        "the policy drove the right arm at every frame"
    );

    let info = read(&root.join("meta/info.json"));
    let names: Vec<&str> = info["features"]["action"]["names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap())
        .collect();
    let index = |name: &str| {
        names
            .iter()
            .position(|n| *n == name)
            .unwrap_or_else(|| panic!("{name} in {names:?}"))
    };
    let right_x = index("right_x");
    // The person moved the left target 3 cm (phone axes map onto the robot's by the arm's configuration);
    // meanwhile the policy's right target crept along +x at 4 mm/s (each chunk's first step 0.2 mm past the
    // pose it observed, one chunk a frame).
    let moved = |col: usize| f64::from(rows[after - 1].action[col] - rows[first_human].action[col]);
    let left_moved_m = ["left_x", "left_y", "left_z"]
        .map(|n| moved(index(n)).powi(2))
        .iter()
        .sum::<f64>()
        .sqrt();
    assert!(
        left_moved_m > 0.015,
        "the correction moved the left target {left_moved_m} m"
    );
    // At least one of the policy's chunks played on the right arm during the correction (0.2 mm each): a
    // stalled machine delivers fewer of them, an arm the policy no longer drove would not move at all.
    assert!(
        moved(right_x) > 0.0001,
        "the right target moved {} m along x while the left arm was corrected",
        moved(right_x)
    );
    assert_eq!(
        read(&root.join("meta/phone2act_provenance.json"))["episodes"][0]["policies"],
        json!([POLICY])
    );
}
