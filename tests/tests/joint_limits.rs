//! Joint limits end to end (issue 24), on the simulated SO-101 through a real server: a phone turned a full
//! circle about the vertical and about both horizontal axes, and a policy driving the same turn in the
//! absolute and relative modes and a wrist jump in the joint mode. Every joint target the server hands the
//! bridge (`ArmState.joint_targets_rad`, stamped with its issue time) moves no joint faster than its limit,
//! the tool stays on the target's position while only the orientation moves, and the recorded episode has
//! no jump.
//!
//! The bounds hold however the threads are scheduled: the limit is checked between the server's own issue
//! times (a late command is allowed the motion of the time that passed, which is the rule), and the position
//! is compared within one snapshot (target and joints are read under one lock).

use nalgebra::{Isometry3, Unit, UnitQuaternion, Vector3};
use phone2act_core::joint_motion::STS3215_MAX_VELOCITY_RAD_S;
use phone2act_core::kinematics::So101Kinematics;
use phone2act_core::layout::{absolute_action, pose_from_state_tail, relative_step};
use phone2act_core::{ActionMode, ArmLayout, AxisPreset};
use phone2act_dataset::parquet_io::read_rows;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, buttons};
use phone2act_tests::{TestServer, arm_state, default_config};
use std::f64::consts::PI;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Twice the inverse kinematics' position tolerance (1e-4 m): with the position held, the joint stage shrinks
/// the orientation step until the solution fits the joint limits, so every command is a converged solution
/// for the position (`joint_motion` module documentation).
const POSITION_BOUND_M: f64 = 2e-4;

/// The largest joint change between two recorded frames. One frame period at the limit is 4.7 rad/s / 20 fps
/// = 0.235 rad. A recorder tick that wakes late on a loaded machine records the motion of every period it
/// missed, so this allows four periods (a tick 150 ms late); the jump being ruled out is the inverse
/// kinematics switching branch, 1.9 rad of wrist roll in one period.
const RECORDED_JUMP_BOUND_RAD: f64 = 1.0;

const FPS: f64 = 20.0;
/// The policy test's timeline: a full turn in this many steps, chunks of HORIZON steps asked for every
/// REPLAN steps.
const STEPS_TOTAL: f64 = 80.0;
const HORIZON: usize = 32;
const REPLAN: usize = 8;

/// One snapshot of the commanded joints.
#[derive(Clone, Debug)]
struct Commanded {
    time_ns: i64,
    joints_rad: [f64; 5],
    target: Isometry3<f64>,
}

fn pose_of(p: &v1::Pose) -> Isometry3<f64> {
    let (t, q) = (p.position_m.unwrap(), p.orientation.unwrap());
    phone2act_core::validate_pose([t.x, t.y, t.z], [q.x, q.y, q.z, q.w]).unwrap()
}

fn commanded(state: &v1::ArmState) -> Option<Commanded> {
    let joints_rad: [f64; 5] = state.joint_targets_rad.as_slice().try_into().ok()?;
    Some(Commanded {
        time_ns: state.joint_targets_time_ns,
        joints_rad,
        target: pose_of(state.robot_from_target.as_ref()?),
    })
}

/// What the snapshots show: the largest joint step as a fraction of what the limit allows for the time
/// between the two issue times, and the largest distance of the commanded tool position from the target's.
#[derive(Debug, Default)]
struct Report {
    commands: usize,
    largest_step_of_limit: f64,
    largest_position_error_m: f64,
}

fn report(samples: &[Commanded], check_position: bool) -> Report {
    let k = So101Kinematics::new();
    let mut r = Report::default();
    let mut previous: Option<&Commanded> = None;
    for s in samples {
        if previous.is_some_and(|p| p.time_ns == s.time_ns) {
            continue;
        }
        r.commands += 1;
        if let Some(p) = previous {
            let dt = (s.time_ns - p.time_ns) as f64 * 1e-9;
            for j in 0..5 {
                let ratio = (s.joints_rad[j] - p.joints_rad[j]).abs() / (STS3215_MAX_VELOCITY_RAD_S * dt);
                r.largest_step_of_limit = r.largest_step_of_limit.max(ratio);
            }
        }
        if check_position {
            let tool = k.forward(&s.joints_rad).translation.vector;
            r.largest_position_error_m = r
                .largest_position_error_m
                .max((tool - s.target.translation.vector).norm());
        }
        previous = Some(s);
    }
    r
}

/// The largest joint change between consecutive recorded frames, in `observation.state` and in `action`
/// (the phone2act layout starts both with the five joints, radians, on a joint arm).
fn recorded_jumps(root: &Path) -> (f64, f64) {
    let mut rows = Vec::new();
    for chunk in std::fs::read_dir(root.join("data")).unwrap() {
        for f in std::fs::read_dir(chunk.unwrap().path()).unwrap() {
            rows.extend(read_rows(&f.unwrap().path()).unwrap());
        }
    }
    rows.sort_by_key(|r| r.index);
    let largest = |of: &dyn Fn(&phone2act_dataset::parquet_io::Row) -> &[f32]| {
        rows.windows(2)
            .map(|w| {
                (0..5)
                    .map(|j| f64::from((of(&w[1])[j] - of(&w[0])[j]).abs()))
                    .fold(0.0, f64::max)
            })
            .fold(0.0, f64::max)
    };
    (largest(&|r| &r.state), largest(&|r| &r.action))
}

async fn start(root: &Path, mode: ActionMode) -> (TestServer, Client) {
    let mut config = default_config(root);
    config.arms[0].action_mode = mode;
    // Phone rotations are robot rotations: the script turns the tool about the robot's axes.
    config.arms[0].teleop.mapping.preset = AxisPreset::Identity;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(10), || async {
            commanded(&arm_state(&client, "main").await).is_some()
        })
        .await,
        "the arm never reported its joints"
    );
    (server, client)
}

async fn start_recording(client: &Client) {
    client.episodes().start("turn").await.unwrap();
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(20), || async {
            client.episodes().status().await.unwrap().frames_recorded > 0
        })
        .await,
        "the recorder wrote no frame"
    );
}

fn quat_msg(q: &UnitQuaternion<f64>) -> [f64; 4] {
    let c = q.quaternion();
    [c.i, c.j, c.k, c.w]
}

/// A phone on the arm `main`, its clutch engaged at the identity pose.
async fn engaged_phone(client: &Client) -> phone2act_sdk::TeleopSession {
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let seq = phone
        .send_pose(
            v1::Pose::from_parts([0.0; 3], quat_msg(&UnitQuaternion::identity())),
            vec![buttons::clutch_engage()],
            0,
        )
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.arm_state.as_ref().unwrap().engaged, "{}", fb.error);
    phone
}

/// Turns the phone a full circle about `axis` (robot frame) in 200 samples at 50 Hz, holding its position,
/// and returns every command the feedback showed plus the recorded jumps.
async fn turn_the_phone(axis: Unit<Vector3<f64>>) -> (Report, (f64, f64), v1::ArmState) {
    let dir = tempfile::tempdir().unwrap();
    let (server, client) = start(dir.path(), ActionMode::Joint).await;
    start_recording(&client).await;
    let mut phone = engaged_phone(&client).await;
    let mut samples = Vec::new();
    let mut tick = tokio::time::interval(Duration::from_millis(20));
    let frames = 200;
    // A further 25 samples hold the final pose while the arm catches up.
    for i in 1..=frames + 25 {
        tick.tick().await;
        let angle = 2.0 * PI * f64::from(i.min(frames)) / f64::from(frames);
        let seq = phone
            .send_pose(
                v1::Pose::from_parts([0.0; 3], quat_msg(&UnitQuaternion::from_axis_angle(&axis, angle))),
                vec![],
                0,
            )
            .await
            .unwrap();
        let fb = phone.feedback_for(seq).await.unwrap();
        assert!(fb.error.is_empty(), "{}", fb.error);
        samples.extend(fb.arm_state.as_ref().and_then(commanded));
    }
    client.episodes().stop().await.unwrap();
    let state = arm_state(&client, "main").await;
    drop(phone);
    server.shutdown().await.unwrap();
    (report(&samples, true), recorded_jumps(dir.path()), state)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_phone_turn_about_any_axis_moves_no_joint_past_its_limit() {
    for (name, axis) in [
        ("vertical", Vector3::z_axis()),
        ("forward", Vector3::x_axis()),
        ("sideways", Vector3::y_axis()),
    ] {
        let (r, (state_jump, action_jump), state) = turn_the_phone(axis).await;
        println!(
            "phone turn about {name}: {} commands, largest joint step {:.3} of the limit, position error {:.4} mm; \
             recorded jumps state {state_jump:.3} rad, action {action_jump:.3} rad; limited {}, orientation unreachable {}",
            r.commands,
            r.largest_step_of_limit,
            r.largest_position_error_m * 1e3,
            state.commands_joint_limited,
            state.commands_orientation_unreachable,
        );
        assert!(r.commands > 100, "{name}: {r:?}");
        assert!(r.largest_step_of_limit <= 1.0 + 1e-6, "{name}: {r:?}");
        assert!(r.largest_position_error_m <= POSITION_BOUND_M, "{name}: {r:?}");
        assert!(
            state_jump <= RECORDED_JUMP_BOUND_RAD && action_jump <= RECORDED_JUMP_BOUND_RAD,
            "{name}: recorded jump state {state_jump} action {action_jump}"
        );
    }
}

/// Polls the arm's state until stopped: every snapshot of the commanded joints.
fn watch(client: &Client, stop: Arc<AtomicBool>) -> tokio::task::JoinHandle<Vec<Commanded>> {
    let client = client.clone();
    tokio::spawn(async move {
        let mut samples = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            samples.extend(commanded(&arm_state(&client, "main").await));
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        samples
    })
}

/// A policy in `mode` drives the arm: a full turn about the vertical at the tool's position (absolute and
/// relative), or the wrist roll stepping faster than its limit (joint). Returns what the watcher saw, the
/// recorded jumps and the arm's final state.
async fn drive_by_policy(mode: ActionMode) -> (Report, (f64, f64), v1::ArmState) {
    let dir = tempfile::tempdir().unwrap();
    let (server, client) = start(dir.path(), mode).await;
    let layout = ArmLayout::new(
        phone2act_core::kinematics::SO101_ARM_JOINT_NAMES
            .iter()
            .map(|s| (*s).to_owned())
            .collect(),
    );
    let start_state = arm_state(&client, "main").await;
    let start_pose = pose_of(start_state.robot_from_ee.as_ref().unwrap());
    let start_joints: [f64; 5] = start_state.joint_positions_rad.as_slice().try_into().unwrap();
    let mut policy = client
        .policy(v1::PolicyHello {
            arms: vec!["main".into()],
            image_encoding: v1::ImageEncoding::None as i32,
            request_control: true,
            policy_name: "turner".into(),
            silence_timeout_s: 10.0,
            ..v1::PolicyHello::default()
        })
        .await
        .unwrap();
    start_recording(&client).await;
    let stop = Arc::new(AtomicBool::new(false));
    let watcher = watch(&client, Arc::clone(&stop));
    // The chunks follow one timeline, indexed by the observation's time, and overlap: a new one is asked for
    // every REPLAN steps while each covers HORIZON. The arbiter skips the steps of a chunk whose time has
    // passed, so a timeline kept by a loop counter would jump at a chunk that arrives late; here the step
    // that runs at any moment is the timeline's at that moment, whichever chunk it comes from, and the arm
    // only holds (and jumps on) if an observation and its push take longer than (HORIZON - REPLAN) steps,
    // 1.2 s, which even a loaded 2-core machine answers well within.
    let period_ns = 1e9 / FPS;
    let mut first_observation_ns = None;
    loop {
        policy.request_observation().await.unwrap();
        let obs = policy.next_observation().await.unwrap();
        let t0_ns = *first_observation_ns.get_or_insert(obs.timestamp_ns);
        // Steps of the timeline before this observation (fractional: chunks are anchored at its instant).
        let k_obs = (obs.timestamp_ns - t0_ns) as f64 / period_ns;
        if k_obs >= STEPS_TOTAL {
            break;
        }
        let observed = pose_from_state_tail(&obs.arms[0].state[layout.ee_state_range()])
            .unwrap()
            .0;
        let steps = (0..HORIZON)
            .map(|i| {
                // Step i runs during [obs + i, obs + i + 1) periods and reaches the timeline's value at its end.
                let k = (k_obs + i as f64 + 1.0).min(STEPS_TOTAL);
                let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2.0 * PI * k / STEPS_TOTAL);
                let target = Isometry3::from_parts(start_pose.translation, turn * start_pose.rotation);
                let values = match mode {
                    ActionMode::Absolute => absolute_action(&target, 0.0),
                    ActionMode::Relative => relative_step(&observed, &target, 0.0),
                    ActionMode::Joint => {
                        // The wrist roll between two angles 0.45 rad apart, a step each period (9 rad/s at 20
                        // steps a second): every change is faster than the limit and, whichever steps are
                        // skipped or replaced, never past the gate's 0.5 rad jump threshold.
                        let mut q = start_joints.to_vec();
                        q[4] = start_joints[4] + 0.45 * (k.round() % 2.0);
                        q.push(0.0);
                        q
                    }
                };
                v1::ActionStep { values }
            })
            .collect();
        let wire_mode = match mode {
            ActionMode::Absolute => v1::ActionMode::AbsoluteEe,
            ActionMode::Relative => v1::ActionMode::DeltaEe,
            ActionMode::Joint => v1::ActionMode::Joint,
        };
        let accepted = policy
            .push_chunk_checked(
                &client,
                v1::ActionChunk {
                    arm: "main".into(),
                    steps,
                    step_period_s: 1.0 / FPS,
                    observation_id: obs.observation_id,
                    mode: wire_mode as i32,
                    blend_steps: 0,
                    keep_steps: 0,
                },
            )
            .await
            .unwrap();
        assert!(accepted.steps_scheduled > 0, "{accepted:?}");
        tokio::time::sleep(Duration::from_secs_f64(REPLAN as f64 / FPS)).await;
    }
    // Let the last steps arrive at the limit.
    tokio::time::sleep(Duration::from_secs(1)).await;
    stop.store(true, Ordering::Relaxed);
    let samples = watcher.await.unwrap();
    client.episodes().stop().await.unwrap();
    let state = arm_state(&client, "main").await;
    println!(
        "policy {mode:?}: limited {}, orientation unreachable {}, rejected {}",
        state.commands_joint_limited, state.commands_orientation_unreachable, state.commands_rejected
    );
    drop(policy);
    server.shutdown().await.unwrap();
    // The joint mode's steps are joint targets, whose position moves with the wrist: only the limit applies.
    let r = report(&samples, mode != ActionMode::Joint);
    (r, recorded_jumps(dir.path()), state)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_in_every_action_mode_moves_no_joint_past_its_limit() {
    for mode in [ActionMode::Absolute, ActionMode::Relative, ActionMode::Joint] {
        let (r, (state_jump, action_jump), state) = drive_by_policy(mode).await;
        println!(
            "policy {mode:?}: {} commands seen, largest joint step {:.3} of the limit, position error {:.4} mm; \
             recorded jumps state {state_jump:.3} rad, action {action_jump:.3} rad",
            r.commands,
            r.largest_step_of_limit,
            r.largest_position_error_m * 1e3
        );
        assert!(r.commands > 20, "{mode:?}: {r:?}");
        assert_eq!(
            state.commands_rejected, 0,
            "{mode:?}: the gate refused steps meant to pass it"
        );
        if mode == ActionMode::Joint {
            assert!(
                state.commands_joint_limited > 0,
                "the joint steps were meant to exceed the limit"
            );
        }
        assert!(r.largest_step_of_limit <= 1.0 + 1e-6, "{mode:?}: {r:?}");
        assert!(r.largest_position_error_m <= POSITION_BOUND_M, "{mode:?}: {r:?}");
        assert!(
            state_jump <= RECORDED_JUMP_BOUND_RAD,
            "{mode:?}: state jump {state_jump}"
        );
        // Absolute and relative arms record the end-effector target, not joints.
        if mode == ActionMode::Joint {
            assert!(
                action_jump <= RECORDED_JUMP_BOUND_RAD,
                "{mode:?}: action jump {action_jump}"
            );
        }
    }
}

/// The shipped CR5 configuration pointed at the Dobot controller emulator, without cameras, every joint
/// limited to `max_velocity_rad_s`, phone rotations taken as robot rotations.
fn cr5_config(
    emu: &phone2act_bridges::dobot::emulator::DobotEmulator,
    dataset: &Path,
    max_velocity_rad_s: f64,
) -> phone2act_server::Config {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../server/config/dobot-cr5.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let mut config = phone2act_server::Config::from_toml_str(&text, path, Vec::new()).unwrap();
    let arm = &mut config.arms[0];
    let dobot = arm.dobot.as_mut().unwrap();
    "127.0.0.1".clone_into(&mut dobot.host);
    dobot.dashboard_port = emu.dashboard_addr().port();
    dobot.feedback_port = emu.feedback_addr().port();
    arm.joint_limits.max_velocity_rad_s = vec![max_velocity_rad_s];
    arm.teleop.mapping.preset = AxisPreset::Identity;
    config.cameras.clear();
    dataset.clone_into(&mut config.recorder.root);
    config
}

/// A CR5 on the Dobot controller emulator: the phone turns 1.5 rad about the vertical in five 0.3 rad
/// samples (each within the gate's jump limit) and then holds. The server solves the CR5's joints and sends
/// them as `ServoJ`; at 0.5 rad/s the turn takes about three seconds of small steps. Unlimited, each sample
/// would reach the controller as one 0.3 rad joint step.
///
/// The limit holds between the server's issue times, which the emulator does not see; it sees receive times.
/// Two commands' issue-to-receive delays differ by at most `SEND_JITTER_S` (a bridge thread stalled that long
/// for one command and not its neighbour), so a step is checked against the limit over the receive gap plus
/// that; 0.25 s at 0.5 rad/s is 0.125 rad, still less than half the unlimited step.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cr5_orientation_jump_reaches_the_controller_as_servo_j_steps_within_the_limit() {
    use phone2act_bridges::dobot::emulator::{DobotEmulator, EmulatorConfig};
    const LIMIT_RAD_S: f64 = 0.5;
    const SEND_JITTER_S: f64 = 0.25;
    const TURN_RAD: f64 = 1.5;
    let emu = DobotEmulator::start(EmulatorConfig::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(cr5_config(&emu, dir.path(), LIMIT_RAD_S))
        .await
        .unwrap();
    let client = server.client().await.unwrap();
    assert!(
        phone2act_tests::wait_until(Duration::from_secs(10), || async {
            arm_state(&client, "main").await.joint_targets_rad.len() == 6
        })
        .await,
        "the CR5 arm never reported its joints"
    );
    let start = emu.snapshot();
    let goal = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), TURN_RAD) * start.pose.rotation;
    let mut phone = engaged_phone(&client).await;
    let mut tick = tokio::time::interval(Duration::from_millis(20));
    let mut arrived = false;
    // Five turning samples, then the final pose held until the emulated arm gets there (or 30 s).
    for i in 1..=1500 {
        tick.tick().await;
        let angle = TURN_RAD * f64::from(i.min(5)) / 5.0;
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle);
        let seq = phone
            .send_pose(v1::Pose::from_parts([0.0; 3], quat_msg(&turn)), vec![], 0)
            .await
            .unwrap();
        let fb = phone.feedback_for(seq).await.unwrap();
        assert!(fb.error.is_empty(), "{}", fb.error);
        if i > 5 && emu.snapshot().pose.rotation.angle_to(&goal) < 0.01 {
            arrived = true;
            break;
        }
    }
    let end = emu.snapshot();
    let state = arm_state(&client, "main").await;
    drop(phone);
    server.shutdown().await.unwrap();
    assert!(arrived, "the emulated CR5 never turned to the target: {end:?}");
    let log = &end.servo_j_log;
    let mut largest_step_of_limit: f64 = 0.0;
    let mut largest_step_rad: f64 = 0.0;
    for pair in log.windows(2) {
        let ((t0, q0), (t1, q1)) = (pair[0], pair[1]);
        let step = q0.iter().zip(&q1).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        let allowed = LIMIT_RAD_S * ((t1 - t0).as_secs_f64() + SEND_JITTER_S);
        largest_step_of_limit = largest_step_of_limit.max(step / allowed);
        largest_step_rad = largest_step_rad.max(step);
    }
    let travel: f64 = (0..6)
        .map(|j| (log.last().unwrap().1[j] - log[0].1[j]).abs())
        .fold(0.0, f64::max);
    let span_s = (log.last().unwrap().0 - log[0].0).as_secs_f64();
    let position_moved_m = (end.pose.translation.vector - start.pose.translation.vector).norm();
    println!(
        "CR5 turn: {} ServoJ, largest step {largest_step_rad:.4} rad ({largest_step_of_limit:.3} of the limit with the \
         jitter allowance), largest joint travel {travel:.3} rad in {span_s:.2} s, tool moved {:.3} mm; limited {}",
        log.len(),
        position_moved_m * 1e3,
        state.commands_joint_limited
    );
    assert!(
        end.last_servo_command
            .as_deref()
            .is_some_and(|c| c.starts_with("ServoJ(")),
        "{:?}",
        end.last_servo_command
    );
    assert!(travel > 1.0, "the turn moved no joint far: {travel} rad");
    assert!(
        largest_step_of_limit <= 1.0,
        "a ServoJ step of {largest_step_rad} rad"
    );
    // The whole turn cannot have gone faster than the limit either.
    assert!(
        travel <= LIMIT_RAD_S * (span_s + SEND_JITTER_S),
        "{travel} rad in {span_s} s"
    );
    // The turn is about the tool's own position: a 6-DoF arm keeps it (the inverse kinematics' 0.1 mm
    // tolerance, and the emulator's straight joint-space line between two close solutions).
    assert!(position_moved_m < 1e-3, "the tool moved {position_moved_m} m");
}
