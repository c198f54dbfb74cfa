//! What one arm's controller holds under its lock, and what it computes there: an input handed to the
//! arbiter, turned into the commands to send (each solved by the joint stage at its issue time), the API's
//! snapshot and the recorder's sample. The server's shell reads the bridge and the clock, takes the lock,
//! calls these and does the I/O they ask for (sending, logging, waking the tick task, telling a policy).

use crate::arbiter::{
    Arbiter, ArbiterError, ArmSnapshot, BridgeHealth, Command, Driver, Effects, Input, Measured,
    PREVIEW_MAX_POINTS, Robot, TickNeed,
};
use crate::arm_vectors::{ArmVectors, Reading, Sample};
use crate::joint_motion::ArmJointStage;

/// What the arbiter needs of a bridge that reports `health` and `reading` (None before its first feedback).
pub fn robot(health: BridgeHealth, reading: Option<&Reading<'_>>) -> Robot {
    Robot {
        health,
        feedback: reading.map(|r| Measured {
            robot_from_ee: *r.robot_from_ee,
            capture_time_s: r.capture_time_ns as f64 * 1e-9,
        }),
    }
}

/// The health an arm shows and its message: READY means movable now, so a bridge that is up but has no fresh
/// measured pose is not ready; a ready arm's message is what the operator should still know (`warning`, a
/// servo alarm the arm works through).
pub fn shown_health(robot: &Robot, warning: Option<String>, now_s: f64) -> (BridgeHealth, String) {
    let not_ready = robot.not_ready(now_s).map(|why| why.to_string());
    match &robot.health {
        BridgeHealth::Connecting => (BridgeHealth::Connecting, not_ready.unwrap_or_default()),
        BridgeHealth::Ready => match not_ready {
            None => (BridgeHealth::Ready, warning.unwrap_or_default()),
            Some(why) if robot.feedback.is_none() => (BridgeHealth::Connecting, why),
            Some(why) => (BridgeHealth::Error(why.clone()), why),
        },
        BridgeHealth::Error(m) => (BridgeHealth::Error(m.clone()), m.clone()),
        BridgeHealth::Disconnected(m) => (BridgeHealth::Disconnected(m.clone()), m.clone()),
    }
}

/// The names an arm's snapshot carries (fixed when the arm is built).
#[derive(Debug, Clone, Copy)]
pub struct ArmNames<'a> {
    pub arm: &'a str,
    pub bridge_kind: &'a str,
    pub joint_names: &'a [String],
}

/// One input handled: the arbiter's effects and the commands to hand to the bridge.
#[derive(Debug, Clone, PartialEq)]
pub struct Handled {
    pub effects: Effects,
    /// The held target again, for a joint stage that did not get there within its limits last time.
    pub catch_up: Option<Command>,
}

impl Handled {
    /// The commands to hand to the bridge, in order (each through [`ArmControl::issue`]).
    pub fn commands(&self) -> impl Iterator<Item = &Command> {
        self.effects.commands.iter().chain(&self.catch_up)
    }
}

/// What to hand the bridge for one command.
#[derive(Debug, Clone, PartialEq)]
pub enum Issue {
    /// Nothing: the joint stage has no joints to start from (no measurement since it was put in place), so it
    /// cannot limit the step; the robot holds rather than be sent a target it might jump to.
    Held,
    /// The command, with the joints the stage solved for it when the arm has one.
    Send { joint_targets_rad: Option<Vec<f64>> },
}

/// One arm's state under its controller's lock.
#[derive(Debug)]
pub struct ArmControl {
    arbiter: Arbiter,
    /// Arms whose kinematics the server knows (sim, so101, dobot): every command's joints are solved and
    /// rate-limited here, once; the bridge drives to them and the recorder records them.
    joints: Option<ArmJointStage>,
    /// The last joint action computed for a joint arm without a joint stage (a remote bridge with SO-101
    /// joints): the seed of the next, so the recorder's inverse kinematics follows its own solutions.
    joint_seed: Option<Vec<f64>>,
    /// `seq` of the last command sent (a catch-up command repeats it: same target).
    last_seq: u64,
}

impl ArmControl {
    pub fn new(arbiter: Arbiter) -> Self {
        Self {
            arbiter,
            joints: None,
            joint_seed: None,
            last_seq: 0,
        }
    }

    pub fn arbiter(&self) -> &Arbiter {
        &self.arbiter
    }

    pub fn joint_stage(&self) -> Option<&ArmJointStage> {
        self.joints.as_ref()
    }

    /// Puts `stage` in place of the joint stage; returns the one it replaced.
    pub fn replace_joint_stage(&mut self, stage: Option<ArmJointStage>) -> Option<ArmJointStage> {
        std::mem::replace(&mut self.joints, stage)
    }

    /// The arbiter's need, and ticks at the rate while the joint stage is still catching up with the target.
    pub fn tick_need(&self) -> TickNeed {
        if self.joints.as_ref().is_some_and(ArmJointStage::behind) {
            TickNeed::Periodic
        } else {
            self.arbiter.tick_need()
        }
    }

    /// Hands `input` to the arbiter at `now_s` with the bridge reporting `robot` and `measured_joints_rad`. A
    /// new source starts the joint stage from where the arm is, as the arbiter's planner does; a held target
    /// the stage did not reach is sent again when nothing newer is.
    pub fn handle(
        &mut self,
        input: Input,
        robot: &Robot,
        measured_joints_rad: Option<&[f64]>,
        now_s: f64,
    ) -> Result<Handled, ArbiterError> {
        let effects = self.arbiter.handle(input, robot, now_s)?;
        if let (Some(stage), Some(joints)) = (self.joints.as_mut(), measured_joints_rad)
            && (effects.reindexed || stage.commanded().is_none())
        {
            stage.reset(joints, now_s);
        }
        let catch_up = (effects.commands.is_empty()
            && self.joints.as_ref().is_some_and(ArmJointStage::behind))
        .then(|| {
            let (robot_from_target, gripper) = self.arbiter.target();
            Command {
                seq: self.last_seq,
                robot_from_target,
                gripper,
            }
        });
        Ok(Handled { effects, catch_up })
    }

    /// What to hand the bridge for `command`, issued at `issue_time_s`: its joints solved and limited by the
    /// joint stage, when the arm has one.
    pub fn issue(&mut self, command: &Command, issue_time_s: f64) -> Issue {
        if self.joints.as_ref().is_some_and(|j| j.commanded().is_none()) {
            return Issue::Held;
        }
        let joint_targets_rad = self
            .joints
            .as_mut()
            .map(|stage| stage.plan(&command.robot_from_target, issue_time_s));
        self.last_seq = command.seq;
        Issue::Send { joint_targets_rad }
    }

    /// The arm was teleported (a scene reset that homed it) to `joints_rad` at `now_s`, before the arbiter
    /// hears of it ([`Input::Homed`]): the joint stage starts from there and recorded joint actions are solved
    /// afresh.
    pub fn teleported(&mut self, joints_rad: &[f64], now_s: f64) {
        if let Some(stage) = self.joints.as_mut() {
            stage.reset(joints_rad, now_s);
        }
        self.joint_seed = None;
    }

    /// The recorded sample of `reading` (see [`ArmVectors::sample`]).
    pub fn sample(&mut self, vectors: &ArmVectors<'_>, reading: &Reading<'_>) -> Option<Sample> {
        vectors.sample(reading, &self.arbiter, self.joints.as_ref(), &mut self.joint_seed)
    }

    /// What the API shows of the arm at `now_ns` (server monotonic ns): the arbiter's state and what its bridge
    /// reports (`health`, `reading`, None before feedback, and `warning`), with a preview of the driving
    /// policy's plan.
    pub fn snapshot(
        &self,
        names: &ArmNames<'_>,
        health: BridgeHealth,
        reading: Option<&Reading<'_>>,
        warning: Option<String>,
        now_ns: i64,
    ) -> ArmSnapshot {
        let now_s = now_ns as f64 * 1e-9;
        let (health, health_message) = shown_health(&robot(health, reading), warning, now_s);
        let a = &self.arbiter;
        let owner_id = match a.driver() {
            Driver::None => String::new(),
            Driver::Teleop => a.teleop_session().map(|s| s.to_string()).unwrap_or_default(),
            Driver::Policy => a
                .policy_owner()
                .map(|(session, name)| format!("{name}:{session}"))
                .unwrap_or_default(),
        };
        let (robot_from_target, gripper_target) = a.target();
        let joints = self.joints.as_ref();
        ArmSnapshot {
            arm: names.arm.to_owned(),
            bridge_kind: names.bridge_kind.to_owned(),
            health,
            health_message,
            driver: a.driver(),
            owner_id,
            engaged: a.engaged(),
            robot_from_target,
            gripper_target,
            robot_from_ee: reading.map(|r| *r.robot_from_ee),
            joint_positions_rad: reading
                .map(|r| r.joint_positions_rad.to_vec())
                .unwrap_or_default(),
            joint_names: names.joint_names.to_vec(),
            gripper_position: reading.map_or(0.0, |r| r.gripper_position),
            last_decision: a.last_decision().clone(),
            feedback_time_ns: reading.map_or(0, |r| r.capture_time_ns),
            feedback_age_s: reading.map_or(-1.0, |r| (now_ns - r.capture_time_ns) as f64 * 1e-9),
            counters: a.counters(),
            joint_counters: joints.map(ArmJointStage::counters).unwrap_or_default(),
            joint_targets_rad: joints.and_then(ArmJointStage::commanded).unwrap_or_default(),
            joint_targets_time_ns: joints
                .filter(|j| j.commanded().is_some())
                .map_or(0, |j| (j.commanded_time_s() * 1e9).round() as i64),
            task_success: reading.is_some_and(|r| r.task_success),
            policy_loading: a.policy_loading_until().is_some(),
            waiting_policy_id: a
                .waiting_policy()
                .map(|(session, name)| format!("{name}:{session}"))
                .unwrap_or_default(),
            plan_preview: a.plan_preview(now_s, PREVIEW_MAX_POINTS),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arbiter::{Counters, PlanPreview};
    use crate::chunk::ChunkConfig;
    use crate::config::TeleopConfig;
    use crate::joint_motion::So101JointStage;
    use crate::kinematics::{SO101_ARM_DOF, SO101_ARM_JOINT_NAMES, So101Kinematics};
    use crate::layout::{ActionMode, ArmLayout};
    use nalgebra::Isometry3;

    const POLICY: u64 = 7;
    /// Joints inside every SO-101 limit, away from the straight-arm singularity.
    const JOINTS_RAD: [f64; SO101_ARM_DOF] = [0.1, -0.4, 0.6, 0.3, -0.2];
    const NS: i64 = 1_000_000_000;

    fn home() -> Isometry3<f64> {
        So101Kinematics::new().forward(&JOINTS_RAD)
    }

    fn reading(pose: &Isometry3<f64>, capture_time_ns: i64) -> Reading<'_> {
        Reading {
            joint_positions_rad: &JOINTS_RAD,
            robot_from_ee: pose,
            gripper_position: 0.25,
            capture_time_ns,
            task_success: true,
        }
    }

    fn names(joint_names: &[String]) -> ArmNames<'_> {
        ArmNames {
            arm: "left",
            bridge_kind: "sim",
            joint_names,
        }
    }

    /// An arm at `home()` with an SO-101 joint stage this slow (rad/s), started from `JOINTS_RAD` at t = 1.
    fn arm_with_stage(max_velocity_rad_s: f64) -> ArmControl {
        let arbiter = Arbiter::new(&TeleopConfig::default(), ChunkConfig::default(), home(), 0.0).unwrap();
        let mut state = ArmControl::new(arbiter);
        let mut stage =
            ArmJointStage::So101(So101JointStage::new(vec![max_velocity_rad_s; SO101_ARM_DOF], 1.0).unwrap());
        stage.reset(&JOINTS_RAD, 1.0);
        assert!(state.replace_joint_stage(Some(stage)).is_none());
        state
    }

    fn claim(state: &mut ArmControl, robot: &Robot, now_s: f64) {
        let claim = Input::ClaimPolicy {
            session: POLICY,
            name: "p".into(),
            silence_timeout_s: 5.0,
        };
        state.handle(claim, robot, Some(&JOINTS_RAD), now_s).unwrap();
    }

    fn chunk(targets: &[Isometry3<f64>], anchor_s: f64) -> Input {
        crate::test_support::chunk_input(POLICY, anchor_s, targets)
    }

    #[test]
    fn the_robot_is_the_bridge_health_and_the_measured_pose_in_seconds() {
        let pose = home();
        let r = robot(BridgeHealth::Ready, Some(&reading(&pose, 1_500_000_000)));
        assert_eq!(r.health, BridgeHealth::Ready);
        let measured = r.feedback.unwrap();
        assert_eq!(measured.robot_from_ee, pose);
        assert!((measured.capture_time_s - 1.5).abs() < 1e-15);
        assert_eq!(robot(BridgeHealth::Connecting, None).feedback, None);
    }

    #[test]
    fn ready_means_movable_now_and_a_ready_arm_shows_its_warning() {
        let pose = home();
        let fresh = robot(BridgeHealth::Ready, Some(&reading(&pose, NS)));
        let warning = || Some("servo 6: overload".to_owned());
        assert_eq!(
            shown_health(&fresh, warning(), 1.5),
            (BridgeHealth::Ready, "servo 6: overload".into())
        );
        assert_eq!(
            shown_health(&fresh, None, 1.5),
            (BridgeHealth::Ready, String::new())
        );
        // Up, but nothing measured yet: still connecting, and why.
        let (health, why) = shown_health(&robot(BridgeHealth::Ready, None), warning(), 1.5);
        assert_eq!(health, BridgeHealth::Connecting);
        assert!(why.contains("no valid feedback"), "{why}");
        // Up, but the last measurement is old: an error, and the warning gives way to the reason.
        let (health, why) = shown_health(&fresh, warning(), 3.0);
        assert_eq!(health, BridgeHealth::Error(why.clone()));
        assert!(why.contains("old"), "{why}");
        let connecting = robot(BridgeHealth::Connecting, Some(&reading(&pose, NS)));
        assert_eq!(
            shown_health(&connecting, warning(), 1.5),
            (BridgeHealth::Connecting, "its bridge is still connecting".into())
        );
        for down in [
            BridgeHealth::Error("robot mode 9".into()),
            BridgeHealth::Disconnected("refused".into()),
        ] {
            let r = robot(down.clone(), Some(&reading(&pose, NS)));
            let message = match &down {
                BridgeHealth::Error(m) | BridgeHealth::Disconnected(m) => m.clone(),
                _ => unreachable!(),
            };
            assert_eq!(shown_health(&r, warning(), 1.5), (down, message));
        }
    }

    /// A command goes out with the joints the stage solved at its issue time; a stage left behind by its speed
    /// limits has the held target sent again (same `seq`) when nothing newer comes, until it gets there.
    #[test]
    fn commands_carry_the_stage_joints_and_a_stage_behind_catches_up_on_the_same_seq() {
        let mut state = arm_with_stage(0.05);
        let pose = home();
        let robot = robot(BridgeHealth::Ready, Some(&reading(&pose, NS)));
        claim(&mut state, &robot, 1.0);
        let target = So101Kinematics::new().forward(&JOINTS_RAD.map(|q| q + 0.03));
        let handled = state
            .handle(chunk(&[target], 1.0), &robot, Some(&JOINTS_RAD), 1.0)
            .unwrap();
        let commands: Vec<Command> = handled.commands().copied().collect();
        assert_eq!(commands.len(), 1, "{handled:?}");
        assert_eq!(handled.catch_up, None);
        let Issue::Send {
            joint_targets_rad: Some(joints),
        } = state.issue(&commands[0], 1.02)
        else {
            panic!("no joints");
        };
        // 0.05 rad/s for 20 ms: 1 mrad of the 30 asked.
        let moved = joints
            .iter()
            .zip(&JOINTS_RAD)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(moved > 0.0 && moved <= 0.001 + 1e-9, "{joints:?}");
        assert_eq!(state.tick_need(), TickNeed::Periodic, "behind: ticks at the rate");

        // The chunk has ended: the arbiter sends nothing new, so the held target goes again.
        let robot = robot_at(&pose, 1_300_000_000);
        let handled = state.handle(Input::Tick, &robot, Some(&JOINTS_RAD), 1.3).unwrap();
        assert!(handled.effects.commands.is_empty());
        let again = handled.catch_up.expect("a catch-up");
        assert_eq!(again.seq, commands[0].seq);
        assert_eq!(again.robot_from_target, state.arbiter().target().0);
        assert!(matches!(
            state.issue(&again, 1.3),
            Issue::Send {
                joint_targets_rad: Some(_)
            }
        ));
    }

    fn robot_at(pose: &Isometry3<f64>, capture_time_ns: i64) -> Robot {
        robot(BridgeHealth::Ready, Some(&reading(pose, capture_time_ns)))
    }

    #[test]
    fn a_stage_with_no_joints_to_start_from_holds_instead_of_sending() {
        let mut state = arm_with_stage(1.0);
        // A stage put in place before any measurement (a remote bridge's, at attach).
        let stage = ArmJointStage::So101(So101JointStage::new(vec![1.0; SO101_ARM_DOF], 1.0).unwrap());
        state.replace_joint_stage(Some(stage));
        let pose = home();
        let robot = robot_at(&pose, NS);
        // No measured joints come with the input either.
        let claim_input = Input::ClaimPolicy {
            session: POLICY,
            name: "p".into(),
            silence_timeout_s: 5.0,
        };
        state.handle(claim_input, &robot, None, 1.0).unwrap();
        let handled = state.handle(chunk(&[pose], 1.0), &robot, None, 1.0).unwrap();
        let command = *handled.commands().next().unwrap();
        assert_eq!(state.issue(&command, 1.0), Issue::Held);
        // The next input with measured joints starts the stage, and its commands go out.
        let next = Isometry3::translation(0.001, 0.0, 0.0) * pose;
        let handled = state
            .handle(chunk(&[next], 1.05), &robot, Some(&JOINTS_RAD), 1.05)
            .unwrap();
        let command = *handled.commands().next().unwrap();
        assert!(matches!(
            state.issue(&command, 1.05),
            Issue::Send {
                joint_targets_rad: Some(_)
            }
        ));
    }

    #[test]
    fn a_teleported_arm_starts_its_stage_and_its_recorded_joints_afresh() {
        let kinematics = So101Kinematics::new();
        let joint_names: Vec<String> = SO101_ARM_JOINT_NAMES.iter().map(|&n| n.to_owned()).collect();
        let layout = ArmLayout::new(joint_names);
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: Some(&kinematics),
            action_mode: ActionMode::Joint,
        };
        // Without a stage the recorded joint action seeds the next: the seed is kept between samples.
        let arbiter = Arbiter::new(&TeleopConfig::default(), ChunkConfig::default(), home(), 0.0).unwrap();
        let mut state = ArmControl::new(arbiter);
        let pose = home();
        let sample = state.sample(&vectors, &reading(&pose, NS)).unwrap();
        assert!(state.joint_seed.is_some());
        assert_eq!(sample.action.len(), SO101_ARM_DOF + 1, "joints and gripper");
        state.teleported(&JOINTS_RAD, 2.0);
        assert_eq!(state.joint_seed, None);

        let mut state = arm_with_stage(1.0);
        let moved = JOINTS_RAD.map(|q| q + 0.2);
        state.teleported(&moved, 2.0);
        let stage = state.joint_stage().unwrap();
        assert_eq!(stage.commanded().unwrap(), moved.to_vec());
        assert!((stage.commanded_time_s() - 2.0).abs() < 1e-12);
    }

    #[test]
    fn the_snapshot_shows_the_arbiter_the_stage_and_the_reading() {
        let joint_names: Vec<String> = SO101_ARM_JOINT_NAMES.iter().map(|&n| n.to_owned()).collect();
        let mut state = arm_with_stage(1.0);
        let pose = home();
        let at = reading(&pose, NS);
        let s = state.snapshot(
            &names(&joint_names),
            BridgeHealth::Ready,
            Some(&at),
            None,
            1_250_000_000,
        );
        assert_eq!((s.arm.as_str(), s.bridge_kind.as_str()), ("left", "sim"));
        assert_eq!(s.health, BridgeHealth::Ready);
        assert_eq!(s.driver, Driver::None);
        assert_eq!(s.owner_id, "");
        assert_eq!(s.robot_from_ee, Some(pose));
        assert_eq!(s.joint_positions_rad, JOINTS_RAD.to_vec());
        assert_eq!(s.joint_names, joint_names);
        assert!((s.gripper_position - 0.25).abs() < 1e-15);
        assert_eq!(s.feedback_time_ns, NS);
        assert!((s.feedback_age_s - 0.25).abs() < 1e-12);
        assert!(s.task_success);
        assert_eq!(s.counters, Counters::default());
        assert_eq!(s.joint_targets_rad, JOINTS_RAD.to_vec(), "the stage's start");
        assert_eq!(s.joint_targets_time_ns, NS);
        assert_eq!(s.plan_preview, PlanPreview::default());

        let robot = robot_at(&pose, NS);
        claim(&mut state, &robot, 1.0);
        let targets: Vec<_> = (0..4)
            .map(|k| Isometry3::translation(0.001 * f64::from(k), 0.0, 0.0) * pose)
            .collect();
        state
            .handle(chunk(&targets, 1.0), &robot, Some(&JOINTS_RAD), 1.0)
            .unwrap();
        let s = state.snapshot(
            &names(&joint_names),
            BridgeHealth::Ready,
            Some(&at),
            None,
            1_050_000_000,
        );
        assert_eq!(s.driver, Driver::Policy);
        assert_eq!(s.owner_id, "p:7");
        assert_eq!(s.counters.sent, 1);
        assert_eq!(s.plan_preview.positions_m.len(), 4, "{:?}", s.plan_preview);
        assert_eq!(
            s.plan_preview,
            state.arbiter().plan_preview(1.05, PREVIEW_MAX_POINTS)
        );

        // Before any feedback: no pose, no joints, and an age that says so.
        let s = state.snapshot(&names(&joint_names), BridgeHealth::Connecting, None, None, NS);
        assert_eq!(s.robot_from_ee, None);
        assert!(s.joint_positions_rad.is_empty());
        assert!((s.feedback_age_s + 1.0).abs() < 1e-15);
        assert_eq!(s.feedback_time_ns, 0);
        assert!(!s.task_success);
    }
}
