//! Faults that are not a clean kill, over real sockets against a real server: every refusal is a non-OK
//! status, nothing saved is deleted by a refused or misdirected call, and client-supplied sizes, counts
//! and durations are bounded.

// Sessions and streams have no Debug, so `expect_err` cannot print them: `.err().expect(..)` instead.
#![allow(clippy::err_expect)]

use phone2act_sdk::proto as v1;
use phone2act_tests::bridge::upstream as up;
use phone2act_tests::{TestServer, default_config, remote_config};
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

fn hello(joints: Vec<String>) -> v1::BridgeUpstream {
    up(v1::bridge_upstream::Message::Hello(v1::BridgeHello {
        arm: "ext".into(),
        bridge_name: "robustness".into(),
        joint_names: joints,
        supports_orientation: true,
        ..v1::BridgeHello::default()
    }))
}

fn abc() -> Vec<String> {
    vec!["a".into(), "b".into(), "c".into()]
}

async fn ext_arm(client: &phone2act_sdk::Client) -> v1::ArmState {
    phone2act_tests::arm_state(client, "ext").await
}

type Down = tonic::Streaming<v1::BridgeDownstream>;

async fn attach(
    server: &TestServer,
    joints: Vec<String>,
) -> Result<(tokio::sync::mpsc::Sender<v1::BridgeUpstream>, Down), tonic::Status> {
    let mut bridge = phone2act_proto::v1::bridge_client::BridgeClient::connect(server.url())
        .await
        .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(hello(joints)).await.unwrap();
    let down = bridge
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    Ok((tx, down))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_arm_without_valid_feedback_is_not_ready_and_nothing_moves_it() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(remote_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    // Right joint names, and then silence.
    let (_tx, mut down) = attach(&server, abc()).await.unwrap();
    let welcome = down.message().await.unwrap().unwrap();
    assert!(matches!(
        welcome.message,
        Some(v1::bridge_downstream::Message::Welcome(_))
    ));
    let arm = ext_arm(&client).await;
    assert_ne!(arm.health(), v1::BridgeHealth::Ready, "{arm:?}");
    assert!(arm.health_message.contains("no valid feedback"), "{arm:?}");
    // A phone cannot engage it, and says why; the gripper does not move it either.
    let mut phone = client
        .teleop("ext", phone2act_sdk::TeleopOptions::default())
        .await
        .unwrap();
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 1.0]),
            vec![phone2act_sdk::buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.contains("not ready"), "{fb:?}");
    assert!(fb.error.contains("no valid feedback"), "{fb:?}");
    for i in 1..=3 {
        let seq = phone
            .send_pose(
                v1::Pose::from_parts([0.0, 0.0, -0.01 * f64::from(i)], [0.0, 0.0, 0.0, 1.0]),
                vec![phone2act_sdk::buttons::gripper_toggle()],
                0,
            )
            .await
            .unwrap();
        phone.feedback_for(seq).await.unwrap();
    }
    // A policy cannot claim it.
    let err = client
        .policy(phone2act_tests::policy_hello(&["ext"], "test", 0.0))
        .await
        .err()
        .expect("claim refused")
        .to_string();
    assert!(
        err.contains("FailedPrecondition") && err.contains("not ready"),
        "{err}"
    );
    // And the bridge was sent no command (a real robot would have jumped to a pose nobody measured).
    let got = tokio::time::timeout(Duration::from_millis(300), down.message()).await;
    assert!(got.is_err(), "the bridge received {got:?}");
    assert_eq!(ext_arm(&client).await.commands_sent, 0);
    drop(phone);
    server.shutdown().await.unwrap();
}

fn fb(joints: Vec<f64>) -> v1::BridgeUpstream {
    up(v1::bridge_upstream::Message::Feedback(v1::RobotFeedback {
        capture_time_ns: 0,
        joint_positions_rad: joints,
        robot_from_ee: Some(v1::Pose::from_parts([0.2, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0])),
        gripper_position: 0.0,
        applied_seq: 0,
    }))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_remote_feedback_and_oversized_hellos_are_errors_not_silence() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(remote_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    for (bad, why) in [
        (vec![0.1, 0.2], "2 joint positions, expected 3"),
        (vec![0.1, f64::NAN, 0.3], "non-finite"),
    ] {
        let (tx, mut down) = attach(&server, abc()).await.unwrap();
        down.message().await.unwrap().unwrap();
        tx.send(fb(vec![0.0; 3])).await.unwrap();
        // Valid feedback makes it ready...
        let t0 = std::time::Instant::now();
        while ext_arm(&client).await.health() != v1::BridgeHealth::Ready {
            // Feedback crosses one loopback hop; 10 s is far beyond any stall on a loaded machine.
            assert!(t0.elapsed() < Duration::from_secs(10), "never ready");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // ...and bad feedback ends the bridge's stream with the reason; the arm is not ready after it.
        tx.send(fb(bad)).await.unwrap();
        // Bounded: without the fix the stream just stays open, and the test must fail, not hang.
        let status = tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                match down.message().await {
                    Ok(Some(_)) => {}
                    Ok(None) => panic!("the stream ended OK after bad feedback"),
                    Err(s) => break s,
                }
            }
        })
        .await
        .unwrap_or_else(|_| panic!("bad feedback ({why}) left the bridge stream open"));
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status}");
        assert!(status.message().contains(why), "{status}");
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_ne!(ext_arm(&client).await.health(), v1::BridgeHealth::Ready);
    }
    // 10,000 joint names: a short, clear refusal, not a 78 KB one the client sees as "Stream removed".
    let many: Vec<String> = (0..10_000).map(|i| format!("joint_{i}")).collect();
    let err = attach(&server, many).await.err().expect("refused");
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err}");
    assert!(err.message().len() < 200, "{} bytes", err.message().len());
    assert!(err.message().contains("10000 joint names"), "{err}");
    server.shutdown().await.unwrap();
}

fn frame(w: u32, h: u32, seq: u64) -> v1::CameraFrame {
    v1::CameraFrame {
        camera: "pushed".into(),
        width: w,
        height: h,
        encoding: v1::ImageEncoding::Rgb8 as i32,
        data: vec![7; (w * h * 3) as usize],
        capture_time_ns: 0,
        frame_seq: seq,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_size_camera_frame_after_good_ones_ends_the_push_with_an_error() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(remote_config(dir.path())).await.unwrap();
    let mut cameras = phone2act_proto::v1::cameras_client::CamerasClient::connect(server.url())
        .await
        .unwrap();
    let frames = vec![
        frame(64, 64, 0),
        frame(64, 64, 1),
        frame(32, 64, 2),
        frame(64, 64, 3),
    ];
    let err = cameras
        .push(tokio_stream::iter(frames))
        .await
        .expect_err("a refused frame is not OK");
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err}");
    assert!(
        err.message().contains("frame 3 refused after 2 accepted"),
        "{err}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn policy_session_refusals_are_statuses() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    // silence_timeout_s out of range: refused, not silently 1 s (or forever).
    for bad in [-1.0, f64::NAN, 1e300, f64::INFINITY, 0.001] {
        let err = client
            .policy(v1::PolicyHello {
                arms: vec!["main".into()],
                request_control: true,
                silence_timeout_s: bad,
                ..v1::PolicyHello::default()
            })
            .await
            .err()
            .unwrap_or_else(|| panic!("silence_timeout_s {bad} accepted"))
            .to_string();
        assert!(
            err.contains("InvalidArgument") && err.contains("silence_timeout_s"),
            "{bad}: {err}"
        );
    }
    // A 1 MB policy name: refused (it would be logged and shown).
    let err = client
        .policy(v1::PolicyHello {
            arms: vec!["main".into()],
            policy_name: "p".repeat(1 << 20),
            ..v1::PolicyHello::default()
        })
        .await
        .err()
        .expect("refused")
        .to_string();
    assert!(
        err.contains("InvalidArgument") && err.contains("policy_name"),
        "{err}"
    );
    // A 100,000-step chunk on the session stream: the session ends with a non-OK status.
    let mut session = client
        .policy(phone2act_tests::policy_hello(&["main"], "test", 2.0))
        .await
        .unwrap();
    let steps = vec![v1::ActionStep { values: vec![0.0; 7] }; 100_000];
    let sent = session
        .push_chunk(v1::ActionChunk {
            arm: "main".into(),
            steps,
            step_period_s: 0.05,
            observation_id: 0,
            mode: v1::ActionMode::DeltaEe as i32,
            blend_steps: 0,
            keep_steps: 0,
        })
        .await;
    let end = tokio::time::timeout(Duration::from_secs(20), async {
        if let Err(e) = sent {
            return Err(e.to_string());
        }
        loop {
            match session.next_event().await {
                Ok(Some(_)) => {}
                Ok(None) => return Ok(()),
                Err(e) => return Err(e.to_string()),
            }
        }
    })
    .await
    .expect("the session ends");
    let err = end.expect_err("the session ended OK after an oversized chunk");
    assert!(
        err.contains("OutOfRange") || err.contains("ResourceExhausted") || err.contains("InvalidArgument"),
        "{err}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_teleop_stream_that_never_sends_is_closed_and_names_are_bounded() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    // A stream that never sends: closed with DEADLINE_EXCEEDED after the first-sample timeout (10 s).
    let (_tx, rx) = tokio::sync::mpsc::channel::<v1::PhoneSample>(1);
    let t0 = std::time::Instant::now();
    let r = tokio::time::timeout(
        Duration::from_mins(1),
        client
            .teleop_raw()
            .stream(tokio_stream::wrappers::ReceiverStream::new(rx)),
    )
    .await
    .expect("the server closes an idle stream by itself");
    let err = r.expect_err("an idle stream is refused");
    assert_eq!(err.code(), tonic::Code::DeadlineExceeded, "{err}");
    assert!(t0.elapsed() >= Duration::from_secs(9), "{:?}", t0.elapsed());
    // A 1 MB client name with a forged log line: refused.
    let err = client
        .teleop(
            "main",
            phone2act_sdk::TeleopOptions {
                client_name: format!(
                    "x\n2026-01-01T00:00:00Z INFO forged\x1b[31m{}",
                    "y".repeat(1 << 20)
                ),
                take_over: false,
            },
        )
        .await
        .err()
        .expect("refused")
        .to_string();
    assert!(
        err.contains("InvalidArgument") && err.contains("client_name"),
        "{err}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_phone_is_told_when_the_bridge_disconnects_under_it() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(remote_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let (tx, mut down) = attach(&server, abc()).await.unwrap();
    down.message().await.unwrap().unwrap();
    // Feed valid feedback until the phone is engaged.
    let feeder = {
        let tx = tx.clone();
        tokio::spawn(async move {
            while tx.send(fb(vec![0.0; 3])).await.is_ok() {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };
    let t0 = std::time::Instant::now();
    while ext_arm(&client).await.health() != v1::BridgeHealth::Ready {
        // One loopback hop; 10 s is far beyond any stall on a loaded machine.
        assert!(t0.elapsed() < Duration::from_secs(10), "never ready");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut phone = client
        .teleop("ext", phone2act_sdk::TeleopOptions::default())
        .await
        .unwrap();
    let pose = |z: f64| v1::Pose::from_parts([0.0, 0.0, z], [0.0, 0.0, 0.0, 1.0]);
    let seq = phone
        .send_pose(pose(0.0), vec![phone2act_sdk::buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb0 = phone.feedback_for(seq).await.unwrap();
    assert!(fb0.error.is_empty(), "{fb0:?}");
    // The bridge process goes away.
    feeder.abort();
    let _ = feeder.await;
    drop(tx);
    drop(down);
    let t0 = std::time::Instant::now();
    while ext_arm(&client).await.health() != v1::BridgeHealth::Disconnected {
        assert!(t0.elapsed() < Duration::from_secs(10), "never disconnected");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let seq = phone.send_pose(pose(-0.01), vec![], 0).await.unwrap();
    let fb1 = phone.feedback_for(seq).await.unwrap();
    assert!(fb1.error.contains("disconnected"), "{fb1:?}");
    let arm = ext_arm(&client).await;
    assert!(!arm.engaged, "{arm:?}");
    let decision = arm.last_decision.unwrap();
    assert_ne!(decision.verdict(), v1::GateVerdict::Accepted, "{decision:?}");
    server.shutdown().await.unwrap();
}

struct Unmount(std::path::PathBuf);
impl Drop for Unmount {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

/// Writes `filler` until the filesystem at `mnt` has about `free` bytes left.
fn fill_leaving(mnt: &std::path::Path, filler: &std::path::Path, free: u64) {
    use std::io::Write;
    let out = std::process::Command::new("df")
        .args(["--output=avail", "-B1"])
        .arg(mnt)
        .output()
        .unwrap();
    let avail: u64 = String::from_utf8_lossy(&out.stdout)
        .lines()
        .nth(1)
        .and_then(|l| l.trim().parse().ok())
        .unwrap();
    let mut f = std::fs::File::create(filler).unwrap();
    let mut left = avail.saturating_sub(free);
    let block = [0xa5u8; 4096];
    while left > 0 {
        let n = left.min(4096) as usize;
        if f.write_all(&block[..n]).is_err() {
            break;
        }
        left -= n as u64;
    }
}

/// The dataset on a 30 MB tmpfs (as in the report) that fills while episodes are saved: every Stop
/// answers (an error status or a saved episode), the recorder stays usable, and the server shuts down.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_during_saves_never_locks_the_server() {
    let _serial = SERIAL.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("mnt");
    std::fs::create_dir_all(&mnt).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=30m", "tmpfs"])
        .arg(&mnt)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("SKIPPED: cannot mount a tmpfs here (needs root) to fill a disk");
        return;
    }
    let _unmount = Unmount(mnt.clone());
    let root = mnt.join("ds");
    let server = TestServer::start(default_config(&root)).await.unwrap();
    let client = server.client().await.unwrap();
    let mut episodes = client.episodes();
    let filler = mnt.join("filler");
    let mut saved = 0usize;
    let mut refused = 0usize;
    // Seconds: a save takes milliseconds; a minute only separates an answer from a hang.
    let answer = Duration::from_mins(1);
    // From nothing left (the encoder fails as it opens its file: on the code before the fix, Stop never
    // answered) to the 16-330 KB at which the report saw saves hang.
    for free_kb in [0u64, 4, 8, 16, 32, 64, 147, 197, 330] {
        fill_leaving(&mnt, &filler, free_kb * 1024);
        episodes.start("tight").await.unwrap();
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let stopped = tokio::time::timeout(answer, episodes.stop())
            .await
            .unwrap_or_else(|_| panic!("Stop with {free_kb} KB free did not answer: the recorder is locked"));
        match stopped {
            Ok(_) => saved += 1,
            Err(_) => refused += 1,
        }
        std::fs::remove_file(&filler).unwrap();
        let st = tokio::time::timeout(answer, episodes.status())
            .await
            .unwrap()
            .unwrap();
        assert_eq!(st.phase(), v1::RecordingPhase::Idle, "{free_kb} KB: {st:?}");
        // With room again, the next episode saves.
        tokio::time::timeout(answer, episodes.start("room"))
            .await
            .unwrap()
            .unwrap();
        tokio::time::sleep(Duration::from_millis(500)).await;
        tokio::time::timeout(answer, episodes.stop())
            .await
            .unwrap()
            .unwrap();
        saved += 1;
    }
    assert!(refused > 0, "the disk never filled: the test proves nothing");
    let list = tokio::time::timeout(answer, episodes.list())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(list.episodes.len(), saved);
    tokio::time::timeout(answer, server.shutdown())
        .await
        .expect("the server shuts down")
        .unwrap();
    let report = phone2act_dataset::verify::verify(&root);
    assert!(report.ok(), "{:?}", report.problems);
}
