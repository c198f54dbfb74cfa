//! The vectors one arm exchanges with policies and the recorder, turned into the arbiter's targets and back:
//! a pushed chunk's steps into targets, the plan still to play into steps a policy would push, and the
//! recorded sample (`observation.state`, the executed `action`, and what the arbiter was doing). The vector
//! definitions are the `layout` module's; this module applies them to an arm: its layout, its kinematics (an
//! arm whose joints are the SO-101's) and its action mode. No I/O: the caller reads the bridge and hands the
//! measurement in.

use crate::arbiter::{Arbiter, Driver};
use crate::chunk::ChunkStep;
use crate::joint_motion::ArmJointStage;
use crate::kinematics::So101Kinematics;
use crate::layout::{
    ActionMode, ArmLayout, LayoutError, absolute_action, joint_action, step_from_target,
    target_from_joint_step, target_from_step,
};
use nalgebra::Isometry3;

/// A chunk step that does not convert to a target (the whole chunk is refused).
#[derive(Debug, thiserror::Error)]
#[error("step {step}: {source}")]
pub struct StepError {
    /// Index of the step in the chunk.
    pub step: usize,
    #[source]
    pub source: LayoutError,
}

/// What the robot reported at one instant, as the sample is taken from it.
#[derive(Debug, Clone, Copy)]
pub struct Reading<'a> {
    pub joint_positions_rad: &'a [f64],
    pub robot_from_ee: &'a Isometry3<f64>,
    pub gripper_position: f64,
    /// Server monotonic time of the measurement, ns.
    pub capture_time_ns: i64,
    /// The scene's success flag (false for arms without a scene).
    pub task_success: bool,
}

/// What the arbiter was doing when a sample's action was read: the recorder derives the episode's events
/// (clutch, gate, policy) from a run of these.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Activity {
    /// A phone's clutch is in (teleop drives the arm).
    pub engaged: bool,
    /// The name of the policy driving the arm (`"unnamed"` for a policy without one); empty when none does.
    pub policy: String,
    /// Commands the safety gate refused so far.
    pub rejected: u64,
    /// Commands the safety gate clamped so far.
    pub clamped: u64,
    /// Commands the joint speed limits shortened so far (0 without a joint stage).
    pub joint_limited: u64,
    /// Hand-backs from the operator to a waiting policy so far.
    pub handed_back: u64,
    /// The reason of the gate's last decision.
    pub last_reason: String,
}

/// One arm's recorded vectors at one instant.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// `observation.state` in the arm's layout.
    pub state: Vec<f64>,
    /// The executed action in the arm's layout: the last gated target, absolute, or the joints it asks for.
    pub action: Vec<f64>,
    pub activity: Activity,
}

/// One arm's layout, kinematics and recorded action mode: everything its vectors are converted with.
#[derive(Debug, Clone, Copy)]
pub struct ArmVectors<'a> {
    pub layout: &'a ArmLayout,
    /// SO-101 kinematics, for an arm whose joints are the SO-101's (the only arms with joint actions).
    pub kinematics: Option<&'a So101Kinematics>,
    /// The mode the arm records its actions in.
    pub action_mode: ActionMode,
}

impl ArmVectors<'_> {
    /// The targets of a pushed chunk's `actions` in `mode`: joint steps (in the layout's units) by forward
    /// kinematics, end-effector steps against `reference`, the measured pose of the observation the chunk
    /// answers (relative steps are composed onto it). The first step that does not convert refuses the chunk.
    pub fn chunk_steps(
        &self,
        actions: &[Vec<f64>],
        reference: &Isometry3<f64>,
        mode: ActionMode,
    ) -> Result<Vec<ChunkStep>, StepError> {
        actions
            .iter()
            .enumerate()
            .map(|(step, action)| {
                let converted = match (mode, self.kinematics) {
                    (ActionMode::Joint, Some(kinematics)) => {
                        target_from_joint_step(kinematics, &self.layout.joint_step_to_native(action))
                    }
                    _ => target_from_step(reference, action, mode),
                };
                converted
                    .map(|(robot_from_target, gripper)| ChunkStep {
                        robot_from_target,
                        gripper,
                    })
                    .map_err(|source| StepError { step, source })
            })
            .collect()
    }

    /// `plan` (the targets still to play) as steps in `mode` against an observation at `reference`: the
    /// values a chunk answering that observation would carry to command the same targets. Joint steps are
    /// solved each seeded with the previous one's joints, from `measured_joints_rad`, as recorded joint
    /// actions are, and stop at the first target that does not solve; None without measured joints to seed
    /// them.
    pub fn plan_steps(
        &self,
        plan: &[ChunkStep],
        reference: &Isometry3<f64>,
        mode: ActionMode,
        measured_joints_rad: Option<&[f64]>,
    ) -> Option<Vec<Vec<f64>>> {
        Some(match (mode, self.kinematics) {
            (ActionMode::Joint, Some(kinematics)) => {
                let measured = measured_joints_rad?;
                let mut seed = measured.to_vec();
                let mut out = Vec::with_capacity(plan.len());
                for step in plan {
                    let Ok(native) = joint_action(kinematics, &step.robot_from_target, &seed, step.gripper)
                    else {
                        break;
                    };
                    seed = native[..native.len() - 1].to_vec();
                    out.push(self.layout.joint_step_from_native(&native));
                }
                out
            }
            _ => plan
                .iter()
                .map(|s| step_from_target(reference, &s.robot_from_target, s.gripper, mode))
                .collect(),
        })
    }

    /// The recorded sample of `reading` with the arbiter's last gated target as the action (absolute, so it
    /// means the same from any frame). A joint arm's action is the joints that target asks for: exactly those
    /// `joints` last commanded when the arm has a joint stage (no second solve with another seed); otherwise
    /// solved seeded with `joint_seed`, the last joint action (or the measured joints), which becomes this
    /// action's joints, so the recorded joints follow one solution branch. None when the reading does not fit
    /// the layout.
    pub fn sample(
        &self,
        reading: &Reading<'_>,
        arbiter: &Arbiter,
        joints: Option<&ArmJointStage>,
        joint_seed: &mut Option<Vec<f64>>,
    ) -> Option<Sample> {
        let state = self
            .layout
            .state_vector(
                reading.joint_positions_rad,
                reading.robot_from_ee,
                reading.gripper_position,
            )
            .ok()?;
        let (target, gripper) = arbiter.target();
        let activity = activity(arbiter, joints);
        let commanded = joints.and_then(ArmJointStage::commanded);
        let action = match (self.action_mode, commanded, self.kinematics) {
            (ActionMode::Joint, Some(mut native), _) => {
                native.push(gripper);
                self.layout.joint_step_from_native(&native)
            }
            (ActionMode::Joint, None, Some(kinematics)) => {
                let seed = joint_seed
                    .take()
                    .unwrap_or_else(|| reading.joint_positions_rad.to_vec());
                let native = joint_action(kinematics, &target, &seed, gripper).ok()?;
                *joint_seed = Some(native[..native.len() - 1].to_vec());
                self.layout.joint_step_from_native(&native)
            }
            _ => absolute_action(&target, gripper),
        };
        Some(Sample {
            state,
            action,
            activity,
        })
    }
}

/// What `arbiter` is doing and has counted, with the joint stage's count of shortened commands.
pub fn activity(arbiter: &Arbiter, joints: Option<&ArmJointStage>) -> Activity {
    let counters = arbiter.counters();
    Activity {
        engaged: arbiter.engaged(),
        policy: match arbiter.driver() {
            Driver::Policy => arbiter
                .policy_owner()
                // An unnamed policy still drives: the events and provenance must say so.
                .map(|(_, name)| if name.is_empty() { "unnamed" } else { name }.to_owned())
                .unwrap_or_default(),
            Driver::Teleop | Driver::None => String::new(),
        },
        rejected: counters.rejected,
        clamped: counters.clamped,
        joint_limited: joints.map_or(0, |j| j.counters().limited),
        handed_back: counters.handed_back,
        last_reason: arbiter.last_decision().reason.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arbiter::{BridgeHealth, Input, Measured, Robot};
    use crate::chunk::ChunkConfig;
    use crate::config::TeleopConfig;
    use crate::joint_motion::So101JointStage;
    use crate::kinematics::SO101_ARM_JOINT_NAMES;
    use crate::layout::{LerobotSo101Units, relative_step};
    use crate::pose::pose_distance;
    use nalgebra::{UnitQuaternion, Vector3};

    const POLICY: u64 = 7;
    /// Joints inside every SO-101 limit, away from the straight-arm singularity.
    const JOINTS_RAD: [f64; 5] = [0.1, -0.4, 0.6, 0.3, -0.2];

    fn so101_layout() -> ArmLayout {
        ArmLayout::new(SO101_ARM_JOINT_NAMES.iter().map(|&n| n.to_owned()).collect())
    }

    fn home() -> Isometry3<f64> {
        Isometry3::from_parts(
            Vector3::new(0.25, 0.0, 0.2).into(),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        )
    }

    fn ready(pose: Isometry3<f64>, now_s: f64) -> Robot {
        Robot {
            health: BridgeHealth::Ready,
            feedback: Some(Measured {
                robot_from_ee: pose,
                capture_time_s: now_s,
            }),
        }
    }

    /// An arbiter at `start`, driven by policy `name` since t = 1, which has played the first of `targets`
    /// (0.1 s apart).
    fn policy_driving(name: &str, start: Isometry3<f64>, targets: &[Isometry3<f64>]) -> Arbiter {
        let mut a = Arbiter::new(&TeleopConfig::default(), ChunkConfig::default(), start, 0.0).unwrap();
        let robot = ready(start, 1.0);
        let claim = Input::ClaimPolicy {
            session: POLICY,
            name: name.to_owned(),
            silence_timeout_s: 0.5,
        };
        a.handle(claim, &robot, 1.0).unwrap();
        a.handle(
            crate::test_support::chunk_input(POLICY, 1.0, targets),
            &robot,
            1.0,
        )
        .unwrap();
        a
    }

    fn assert_near(a: &Isometry3<f64>, b: &Isometry3<f64>, m: f64, rad: f64) {
        let (dm, drad) = pose_distance(a, b);
        assert!(dm < m && drad < rad, "{a:?} is {dm} m, {drad} rad from {b:?}");
    }

    #[test]
    fn end_effector_steps_convert_to_targets_and_the_plan_back_to_the_same_steps() {
        let layout = so101_layout();
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: None,
            action_mode: ActionMode::Absolute,
        };
        let reference = home();
        let targets: Vec<_> = (0..4)
            .map(|k| Isometry3::translation(0.01 * f64::from(k), 0.0, -0.005 * f64::from(k)) * reference)
            .collect();
        for mode in [ActionMode::Absolute, ActionMode::Relative] {
            let actions: Vec<_> = targets
                .iter()
                .map(|t| match mode {
                    ActionMode::Relative => relative_step(&reference, t, 0.25),
                    _ => absolute_action(t, 0.25),
                })
                .collect();
            let steps = vectors.chunk_steps(&actions, &reference, mode).unwrap();
            for (step, target) in steps.iter().zip(&targets) {
                assert_near(&step.robot_from_target, target, 1e-12, 1e-12);
                assert!((step.gripper - 0.25).abs() < 1e-12);
            }
            let back = vectors.plan_steps(&steps, &reference, mode, None).unwrap();
            assert_eq!(back.len(), actions.len());
            for (b, a) in back.iter().zip(&actions) {
                assert!(
                    b.iter().zip(a).all(|(x, y)| (x - y).abs() < 1e-12),
                    "{mode:?}: {b:?} != {a:?}"
                );
            }
        }
    }

    #[test]
    fn a_step_that_does_not_convert_refuses_the_chunk_and_names_its_index() {
        let layout = so101_layout();
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: None,
            action_mode: ActionMode::Absolute,
        };
        let good = absolute_action(&home(), 0.0);
        let short = vec![0.0; 3];
        let err = vectors
            .chunk_steps(&[good.clone(), good, short], &home(), ActionMode::Absolute)
            .unwrap_err();
        assert_eq!(err.step, 2);
        assert!(matches!(err.source, LayoutError::WrongWidth { .. }), "{err}");
        // Joint steps need kinematics: an arm without them refuses the first.
        let err = vectors
            .chunk_steps(&[vec![0.0; 6]], &home(), ActionMode::Joint)
            .unwrap_err();
        assert_eq!(err.step, 0);
        assert!(matches!(err.source, LayoutError::NoKinematics), "{err}");
    }

    #[test]
    fn joint_steps_in_lerobot_units_round_trip_through_their_targets() {
        let kinematics = So101Kinematics::new();
        let layout = so101_layout().with_lerobot_so101(LerobotSo101Units {
            gripper_open_pct: 0.0,
            gripper_closed_pct: 100.0,
        });
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: Some(&kinematics),
            action_mode: ActionMode::Joint,
        };
        let actions: Vec<Vec<f64>> = (0..3)
            .map(|k| {
                let mut native: Vec<f64> = JOINTS_RAD.iter().map(|q| q + 0.02 * f64::from(k)).collect();
                native.push(0.4);
                layout.joint_step_from_native(&native)
            })
            .collect();
        let steps = vectors.chunk_steps(&actions, &home(), ActionMode::Joint).unwrap();
        assert!((steps[0].gripper - 0.4).abs() < 1e-12, "40 % is 0.4");
        // Without measured joints there is no seed: no joint steps rather than a guess.
        assert_eq!(vectors.plan_steps(&steps, &home(), ActionMode::Joint, None), None);
        let back = vectors
            .plan_steps(&steps, &home(), ActionMode::Joint, Some(&JOINTS_RAD))
            .unwrap();
        assert_eq!(back.len(), 3);
        for (b, a) in back.iter().zip(&actions) {
            // Degrees: the solver stops within about 1e-3 rad of orientation (0.06°).
            assert!(
                b.iter().zip(a).all(|(x, y)| (x - y).abs() < 0.1),
                "{b:?} != {a:?}"
            );
        }
    }

    #[test]
    fn the_sample_records_the_gated_target_and_what_the_arbiter_is_doing() {
        let layout = so101_layout();
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: None,
            action_mode: ActionMode::Absolute,
        };
        let target = Isometry3::translation(0.01, 0.0, 0.0) * home();
        let a = policy_driving("", home(), &[target]);
        assert_eq!(a.target().0, target, "the gate passed the step");
        let measured = home();
        let reading = Reading {
            joint_positions_rad: &JOINTS_RAD,
            robot_from_ee: &measured,
            gripper_position: 0.2,
            capture_time_ns: 1_000_000_000,
            task_success: false,
        };
        let mut seed = None;
        let s = vectors.sample(&reading, &a, None, &mut seed).unwrap();
        assert_eq!(s.state, layout.state_vector(&JOINTS_RAD, &measured, 0.2).unwrap());
        assert_eq!(s.action, absolute_action(&target, 0.5));
        assert_eq!(seed, None, "an end-effector arm keeps no joint seed");
        assert_eq!(
            s.activity,
            Activity {
                engaged: false,
                policy: "unnamed".into(),
                rejected: 0,
                clamped: 0,
                joint_limited: 0,
                handed_back: 0,
                last_reason: a.last_decision().reason.clone(),
            }
        );
        // A reading of other joints does not fit the layout: no sample.
        let wrong = Reading {
            joint_positions_rad: &JOINTS_RAD[..4],
            ..reading
        };
        assert!(vectors.sample(&wrong, &a, None, &mut seed).is_none());
    }

    #[test]
    fn a_joint_arm_records_the_joints_it_commanded_or_follows_its_own_solutions() {
        let kinematics = So101Kinematics::new();
        let layout = so101_layout();
        let vectors = ArmVectors {
            layout: &layout,
            kinematics: Some(&kinematics),
            action_mode: ActionMode::Joint,
        };
        let measured = kinematics.forward(&JOINTS_RAD);
        let target_joints = JOINTS_RAD.map(|q| q + 0.03);
        let target = kinematics.forward(&target_joints);
        let a = policy_driving("p", measured, &[target]);
        assert_eq!(a.target().0, target, "the gate passed the step");
        let reading = Reading {
            joint_positions_rad: &JOINTS_RAD,
            robot_from_ee: &measured,
            gripper_position: 0.0,
            capture_time_ns: 1_000_000_000,
            task_success: false,
        };

        // Without a joint stage: solved from the measured joints, and the solution seeds the next.
        let mut seed = None;
        let first = vectors.sample(&reading, &a, None, &mut seed).unwrap();
        let expected = joint_action(&kinematics, &target, &JOINTS_RAD, 0.5).unwrap();
        assert_eq!(first.action, expected);
        assert_eq!(seed.as_deref(), Some(&expected[..5]));
        assert_eq!(first.activity.policy, "p");
        let mut planted = Some(vec![0.0, -0.3, 0.5, 0.2, -0.1]);
        let second = vectors.sample(&reading, &a, None, &mut planted).unwrap();
        assert_eq!(
            second.action,
            joint_action(&kinematics, &target, &[0.0, -0.3, 0.5, 0.2, -0.1], 0.5).unwrap(),
            "seeded with the last solution, not the measured joints"
        );

        // With a joint stage: exactly the joints it commanded, and the seed is left alone.
        let mut stage = ArmJointStage::So101(So101JointStage::new(vec![100.0; 5], 1.0).unwrap());
        stage.reset(&JOINTS_RAD, 0.0);
        let commanded = stage.plan(&target, 1.0);
        let mut untouched = Some(vec![9.0; 5]);
        let staged = vectors
            .sample(&reading, &a, Some(&stage), &mut untouched)
            .unwrap();
        let mut native = commanded;
        native.push(0.5);
        assert_eq!(staged.action, native);
        assert_eq!(untouched, Some(vec![9.0; 5]));
        assert_eq!(staged.activity.joint_limited, stage.counters().limited);
    }
}
