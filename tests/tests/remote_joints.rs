//! Remote bridges that declare their joint model (issue 24): the server solves their targets and limits every
//! joint step, over real gRPC to a bridge in this process that drives a simulated SO-101 to the joints it is
//! sent and reports them (with their forward kinematics as the tool pose). A commanded orientation jump, from
//! the phone and from a policy in the absolute and joint modes, arrives as a ramp whose every step is within
//! the declared limit; a bridge without a model still gets pose targets; a malformed model is refused with the
//! reason.
//!
//! The limit is checked between the server's issue times, which every command carries (a command that reaches
//! the bridge late, or that the bridge never sees because a newer one replaced it, is allowed the motion of
//! the time that passed, which is the rule): no bound here depends on how the threads are scheduled.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use parking_lot::Mutex;
use phone2act_core::kinematics::{
    ChainKinematics, SO101_ARM_DOF, SO101_ARM_JOINT_NAMES, SO101_JOINT_LIMITS_RAD, SO101_JOINT_ORIGINS,
    SO101_TCP_ORIGIN, So101Kinematics, UrdfJoint,
};
use phone2act_core::layout::absolute_action;
use phone2act_core::{ActionMode, AxisPreset};
use phone2act_proto::v1::bridge_client::BridgeClient;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, buttons};
use phone2act_tests::bridge::upstream;
use phone2act_tests::{TestServer, arm_state};
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::StreamExt;

/// The declared speed limit, below the SO-101's default 4.7 rad/s so the test sees that the declared one is used.
const LIMIT_RAD_S: f64 = 2.0;
/// The simulated robot's start: elbow bent, wrist down, inside every range.
const START_RAD: [f64; SO101_ARM_DOF] = [0.0, -0.4, 0.6, 0.9, 0.0];
/// The commanded jump: 0.45 rad, within the gate's 0.5 rad jump threshold, so it passes the gate in one step;
/// at 2 rad/s it takes at least 0.22 s, eleven 20 ms periods.
const JUMP_RAD: f64 = 0.45;

const CONFIG: &str = r#"
[[arms]]
name = "abs"
bridge = "remote"
action_mode = "absolute"
[arms.remote]
joint_names = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]

[[arms]]
name = "joint"
bridge = "remote"
action_mode = "joint"
[arms.remote]
joint_names = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]

[[arms]]
name = "plain"
bridge = "remote"
[arms.remote]
joint_names = ["a", "b", "c"]
"#;

fn names() -> Vec<String> {
    SO101_ARM_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect()
}

/// The SO-101 as an explicit URDF chain, every joint limited to `LIMIT_RAD_S`.
fn so101_chain() -> v1::JointModel {
    let joints = (0..SO101_ARM_DOF)
        .map(|i| v1::ChainJoint {
            name: SO101_ARM_JOINT_NAMES[i].to_owned(),
            origin_xyz_m: SO101_JOINT_ORIGINS[i].0.to_vec(),
            origin_rpy_rad: SO101_JOINT_ORIGINS[i].1.to_vec(),
            axis: vec![0.0, 0.0, 1.0],
            lower_rad: SO101_JOINT_LIMITS_RAD[i].0,
            upper_rad: SO101_JOINT_LIMITS_RAD[i].1,
            max_velocity_rad_s: LIMIT_RAD_S,
            max_acceleration_rad_s2: None,
        })
        .collect();
    v1::JointModel {
        model: Some(v1::joint_model::Model::Chain(v1::JointChain {
            joints,
            tool_xyz_m: SO101_TCP_ORIGIN.0.to_vec(),
            tool_rpy_rad: SO101_TCP_ORIGIN.1.to_vec(),
        })),
    }
}

/// The same chain as the server builds it from the declaration: the bridge's forward kinematics.
fn so101_chain_kinematics() -> ChainKinematics<SO101_ARM_DOF> {
    let joints = std::array::from_fn(|i| UrdfJoint {
        origin_xyz_m: SO101_JOINT_ORIGINS[i].0,
        origin_rpy_rad: SO101_JOINT_ORIGINS[i].1,
        axis: [0.0, 0.0, 1.0],
        limits_rad: SO101_JOINT_LIMITS_RAD[i],
    });
    ChainKinematics::from_urdf(&joints, SO101_TCP_ORIGIN.0, SO101_TCP_ORIGIN.1)
}

fn pose_msg(p: &Isometry3<f64>) -> v1::Pose {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    v1::Pose::from_parts([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

fn pose_of(p: &v1::Pose) -> Isometry3<f64> {
    let t = p.position_m.as_ref().unwrap();
    let q = p.orientation.as_ref().unwrap();
    Isometry3::from_parts(
        Translation3::new(t.x, t.y, t.z),
        UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
    )
}

/// One command as the bridge received it.
#[derive(Debug, Clone)]
struct Received {
    issue_time_ns: i64,
    joints_rad: Vec<f64>,
}

/// A bridge in this process: attaches with `hello`, drives its simulated joints to every command's joint
/// targets at once (or, without them, keeps its joints and reports the commanded pose), reports feedback
/// every 20 ms, and keeps every command it received.
struct TestBridge {
    welcome: v1::BridgeWelcome,
    received: Arc<Mutex<Vec<Received>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl TestBridge {
    async fn attach(
        client: &mut BridgeClient<tonic::transport::Channel>,
        hello: v1::BridgeHello,
    ) -> Result<Self, tonic::Status> {
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        tx.send(upstream(v1::bridge_upstream::Message::Hello(hello)))
            .await
            .unwrap();
        let mut down = client
            .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await?
            .into_inner();
        let welcome = match down.next().await {
            Some(Ok(v1::BridgeDownstream {
                message: Some(v1::bridge_downstream::Message::Welcome(w)),
            })) => w,
            Some(Err(status)) => return Err(status),
            other => panic!("expected a welcome, got {other:?}"),
        };
        let kinematics = so101_chain_kinematics();
        let joints = Arc::new(Mutex::new((
            START_RAD.to_vec(),
            kinematics.forward(&START_RAD),
            0u64,
        )));
        let received = Arc::new(Mutex::new(Vec::new()));
        let feedback_joints = Arc::clone(&joints);
        let feedback_tx = tx.clone();
        let feedback = tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(20));
            loop {
                tick.tick().await;
                let (q, pose, seq) = feedback_joints.lock().clone();
                // Any field the message gains later keeps its default.
                #[allow(clippy::needless_update)]
                let fb = v1::RobotFeedback {
                    capture_time_ns: phone2act_clock::monotonic_ns(),
                    joint_positions_rad: q,
                    robot_from_ee: Some(pose_msg(&pose)),
                    gripper_position: 0.0,
                    applied_seq: seq,
                    ..v1::RobotFeedback::default()
                };
                if feedback_tx
                    .send(upstream(v1::bridge_upstream::Message::Feedback(fb)))
                    .await
                    .is_err()
                {
                    break;
                }
            }
        });
        let log = Arc::clone(&received);
        let commands = tokio::spawn(async move {
            while let Some(Ok(msg)) = down.next().await {
                let Some(v1::bridge_downstream::Message::Command(c)) = msg.message else {
                    continue;
                };
                let target = pose_of(c.robot_from_target.as_ref().unwrap());
                let mut state = joints.lock();
                if c.joint_targets_rad.len() == SO101_ARM_DOF {
                    let q: [f64; SO101_ARM_DOF] = c.joint_targets_rad.as_slice().try_into().unwrap();
                    *state = (q.to_vec(), kinematics.forward(&q), c.seq);
                } else {
                    // A bridge that solves its own joints: this one reports the pose as reached.
                    state.1 = target;
                    state.2 = c.seq;
                }
                log.lock().push(Received {
                    issue_time_ns: c.issue_time_ns,
                    joints_rad: c.joint_targets_rad,
                });
            }
            drop(tx);
        });
        Ok(Self {
            welcome,
            received,
            tasks: vec![feedback, commands],
        })
    }

    fn received(&self) -> Vec<Received> {
        self.received.lock().clone()
    }
}

impl Drop for TestBridge {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

fn hello(arm: &str, model: Option<v1::JointModel>) -> v1::BridgeHello {
    // Any field the message gains later keeps its default.
    #[allow(clippy::needless_update)]
    v1::BridgeHello {
        arm: arm.into(),
        bridge_name: "joint-model-test".into(),
        joint_names: names(),
        supports_orientation: true,
        joint_model: model,
        ..v1::BridgeHello::default()
    }
}

/// The largest joint step of `commands` as a fraction of what the declared limit allows between their issue
/// times, and the number of commands that moved.
fn largest_step_of_limit(commands: &[Received]) -> (f64, usize) {
    let mut largest: f64 = 0.0;
    let mut moving = 0;
    for pair in commands.windows(2) {
        let dt_s = (pair[1].issue_time_ns - pair[0].issue_time_ns) as f64 * 1e-9;
        let step = pair[0]
            .joints_rad
            .iter()
            .zip(&pair[1].joints_rad)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        if step > 1e-9 {
            moving += 1;
            largest = largest.max(step / (LIMIT_RAD_S * dt_s));
        }
    }
    (largest, moving)
}

/// Waits until the bridge's robot stops moving (no joint changed over 0.2 s) or 10 s pass.
async fn settled(bridge: &TestBridge) {
    let mut last = bridge.received().len();
    for _ in 0..50 {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let now = bridge.received().len();
        if now == last {
            return;
        }
        last = now;
    }
}

/// Checks what the bridge received after `from`: joint targets on every command, a ramp of more than a few
/// steps, every step within the limit, and the whole jump covered.
fn check_ramp(what: &str, received: &[Received], from: usize, wrist_moved_at_least_rad: Option<f64>) {
    let after = &received[from.saturating_sub(1)..];
    assert!(
        after.iter().all(|c| c.joints_rad.len() == SO101_ARM_DOF),
        "{what}: a command without joints"
    );
    let (largest, moving) = largest_step_of_limit(after);
    let travel = after[0]
        .joints_rad
        .iter()
        .zip(&after.last().unwrap().joints_rad)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    println!(
        "{what}: {} commands, {moving} moving, largest step {largest:.3} of the limit, travel {travel:.3} rad",
        after.len()
    );
    // At 2 rad/s and a period of at most 20 ms, 0.4 rad of travel takes ten moving commands at least.
    assert!(moving >= 5, "{what}: the jump arrived in {moving} steps");
    assert!(largest <= 1.0 + 1e-6, "{what}: a step of {largest} of the limit");
    // The first step after the arm stood still is one period's motion, not the pause's (0.2 s or more here,
    // 0.4 rad at the limit: the whole jump at once). Allowed: the longest step time plus 0.1 s of commands a
    // reader stalled on a loaded machine may have skipped (latest wins), 0.24 rad.
    let first = after
        .windows(2)
        .map(|p| {
            p[0].joints_rad
                .iter()
                .zip(&p[1].joints_rad)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max)
        })
        .find(|step| *step > 1e-9)
        .unwrap_or(0.0);
    let first_bound = LIMIT_RAD_S * (phone2act_core::joint_limit::MAX_STEP_S + 0.1);
    assert!(
        first <= first_bound,
        "{what}: the first step after a pause is {first} rad"
    );
    if let Some(at_least) = wrist_moved_at_least_rad {
        assert!(travel >= at_least, "{what}: travel {travel} rad");
    }
}

async fn start() -> (
    TestServer,
    Client,
    BridgeClient<tonic::transport::Channel>,
    tempfile::TempDir,
) {
    let dir = tempfile::tempdir().unwrap();
    let mut config = phone2act_server::Config::from_toml_str(CONFIG, "remote-joints", Vec::new()).unwrap();
    dir.path().clone_into(&mut config.recorder.root);
    for arm in &mut config.arms {
        // Phone rotations are robot rotations: the script turns the tool about the robot's axes.
        arm.teleop.mapping.preset = AxisPreset::Identity;
    }
    assert_eq!(config.arms[1].action_mode, ActionMode::Joint);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    (server, client, BridgeClient::new(channel), dir)
}

async fn ready(client: &Client, arm: &str) {
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(10), || async {
            arm_state(client, arm).await.joint_positions_rad.len() == SO101_ARM_DOF
        })
        .await,
        "arm {arm} never reported its joints"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_declared_model_turns_every_jump_into_a_ramp_within_its_limits() {
    let (server, client, mut bridges, _dir) = start().await;

    // Malformed models are refused at attach, with the reason.
    let mut zero_axis = so101_chain();
    if let Some(v1::joint_model::Model::Chain(c)) = &mut zero_axis.model {
        c.joints[2].axis = vec![0.0; 3];
    }
    let mut nan = so101_chain();
    if let Some(v1::joint_model::Model::Chain(c)) = &mut nan.model {
        c.joints[0].origin_xyz_m[1] = f64::NAN;
    }
    let mut inverted = so101_chain();
    if let Some(v1::joint_model::Model::Chain(c)) = &mut inverted.model {
        c.joints[3].lower_rad = 2.0;
        c.joints[3].upper_rad = 1.0;
    }
    let mut short = so101_chain();
    if let Some(v1::joint_model::Model::Chain(c)) = &mut short.model {
        c.joints.pop();
    }
    let known = |name: &str| v1::JointModel {
        model: Some(v1::joint_model::Model::Known(name.into())),
    };
    for (model, reason) in [
        (zero_axis, "joint \"elbow_flex\": the axis is zero"),
        (nan, "joint \"shoulder_pan\": origin must be finite"),
        (inverted, "lower limit 2 rad is above the upper limit 1 rad"),
        (short, "has 4 joints, the bridge names 5"),
        (known("ur5"), "unknown joint model \"ur5\""),
        (known("cr5"), "joint model cr5 has 6 joints, the bridge names 5"),
    ] {
        let status = TestBridge::attach(&mut bridges, hello("abs", Some(model)))
            .await
            .err()
            .expect("a malformed model attached");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status}");
        assert!(status.message().contains(reason), "{status:?} lacks {reason:?}");
    }

    // The phone path: a 0.45 rad turn about the vertical in one sample, then held.
    let abs = TestBridge::attach(&mut bridges, hello("abs", Some(so101_chain())))
        .await
        .unwrap();
    assert!(abs.welcome.joint_targets, "{:?}", abs.welcome);
    assert!(abs.welcome.joint_limits.contains("2.00"), "{:?}", abs.welcome);
    ready(&client, "abs").await;
    let mut phone = client.teleop("abs", TeleopOptions::default()).await.unwrap();
    let identity = [0.0, 0.0, 0.0, 1.0];
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0; 3], identity),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.arm_state.as_ref().unwrap().engaged, "{}", fb.error);
    // No pause here: a phone silent past the teleop timeout re-indexes on its next sample, which would make
    // the turned pose the new zero.
    let from = abs.received().len();
    let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), JUMP_RAD);
    let c = turn.quaternion();
    for _ in 0..50 {
        // Held for a second at 50 Hz: the phone keeps sending the turned pose, as a held phone does.
        let seq = phone
            .send_pose(v1::Pose::from_parts([0.0; 3], [c.i, c.j, c.k, c.w]), vec![], 0)
            .await
            .unwrap();
        let fb = phone.feedback_for(seq).await.unwrap();
        assert!(fb.error.is_empty(), "{}", fb.error);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    settled(&abs).await;
    check_ramp("phone turn", &abs.received(), from, Some(0.2));
    drop(phone);
    // The server learns of the closed stream on its own time; until then the phone still drives and a policy's
    // claim is refused. 10 s is a liveness bound for what takes milliseconds on an idle machine.
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(10), || async {
            !arm_state(&client, "abs").await.engaged
        })
        .await,
        "the phone's closed stream never released the arm"
    );

    // A policy in the absolute mode: the same jump, back again, as one chunk step.
    let state = arm_state(&client, "abs").await;
    let here = pose_of(state.robot_from_ee.as_ref().unwrap());
    let target = Isometry3::from_parts(here.translation, turn.inverse() * here.rotation);
    let from = abs.received().len();
    drive(
        &client,
        "abs",
        v1::ActionMode::AbsoluteEe,
        absolute_action(&target, 0.0),
    )
    .await;
    settled(&abs).await;
    check_ramp("policy absolute", &abs.received(), from, Some(0.2));

    // A policy in the joint mode: the wrist roll 0.45 rad away in one step.
    let joint = TestBridge::attach(&mut bridges, hello("joint", Some(so101_chain())))
        .await
        .unwrap();
    ready(&client, "joint").await;
    let mut q = START_RAD.to_vec();
    q[4] += JUMP_RAD;
    q.push(0.0);
    let from = joint.received().len();
    drive(&client, "joint", v1::ActionMode::Joint, q).await;
    settled(&joint).await;
    let received = joint.received();
    check_ramp("policy joint", &received, from, None);
    // The joint step is solved back from its pose, to the inverse kinematics' tolerance.
    let last = &received.last().unwrap().joints_rad;
    assert!((last[4] - START_RAD[4] - JUMP_RAD).abs() < 0.02, "{last:?}");
    // (Which rule shapes the ramp, the orientation aim's one-period turn or the rate limiter's shortening,
    // depends on how the commands fall in time; either keeps every step within the limit, which is checked.)

    // A bridge that declares nothing still attaches and gets pose targets, and is told so.
    let mut plain_hello = hello("plain", None);
    plain_hello.joint_names = vec!["a".into(), "b".into(), "c".into()];
    let plain = TestBridge::attach(&mut bridges, plain_hello).await.unwrap();
    assert!(!plain.welcome.joint_targets, "{:?}", plain.welcome);
    assert!(
        plain.welcome.joint_limits.contains("no joint model declared"),
        "{:?}",
        plain.welcome
    );
    drop(plain);

    // A known model by name: the SO-101's own speed limit.
    drop(abs);
    let by_name = TestBridge::attach(&mut bridges, hello("abs", Some(known("so101"))))
        .await
        .unwrap();
    assert!(
        by_name.welcome.joint_targets && by_name.welcome.joint_limits.contains("4.70"),
        "{:?}",
        by_name.welcome
    );
    drop(by_name);
    server.shutdown().await.unwrap();
}

/// A policy takes `arm` and runs one chunk of 20 steps, each `values`.
async fn drive(client: &Client, arm: &str, mode: v1::ActionMode, values: Vec<f64>) {
    let mut policy = client
        .policy(v1::PolicyHello {
            arms: vec![arm.into()],
            image_encoding: v1::ImageEncoding::None as i32,
            request_control: true,
            policy_name: "jumper".into(),
            silence_timeout_s: 10.0,
            ..v1::PolicyHello::default()
        })
        .await
        .unwrap();
    policy.request_observation().await.unwrap();
    let obs = policy.next_observation().await.unwrap();
    let accepted = policy
        .push_chunk_checked(
            client,
            v1::ActionChunk {
                arm: arm.into(),
                steps: (0..20)
                    .map(|_| v1::ActionStep {
                        values: values.clone(),
                    })
                    .collect(),
                step_period_s: 0.05,
                observation_id: obs.observation_id,
                mode: mode as i32,
                blend_steps: 0,
                keep_steps: 0,
            },
        )
        .await
        .unwrap();
    assert!(accepted.steps_scheduled > 0, "{accepted:?}");
    // The chunk's second (20 steps of 50 ms) and the ramp's 0.23 s within it.
    tokio::time::sleep(Duration::from_millis(1100)).await;
    let state = arm_state(client, arm).await;
    assert_eq!(
        state.commands_rejected, 0,
        "the gate refused a step meant to pass it"
    );
    drop(policy);
}

#[test]
fn the_declared_chain_is_the_so101() {
    let (a, b) = (
        so101_chain_kinematics().forward(&START_RAD),
        So101Kinematics::new().forward(&START_RAD),
    );
    assert!((a.translation.vector - b.translation.vector).norm() < 1e-12);
}
