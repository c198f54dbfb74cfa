//! Joint targets for arms whose kinematics the server knows (the SO-101, simulated or on its servo bus, and the
//! Dobot CR5): the one place a gated task-space target becomes the joints a bridge drives to, the joints the
//! recorder records as the action, and the joints the next target is solved from. One [`JointStage`] serves
//! both, over their [`ChainKinematics`].
//!
//! Each command is solved once, seeded with the joints last commanded (not the lagging measured ones), and
//! then passes the [`JointRateLimiter`]. Two rules keep the solution continuous:
//!
//! - **The orientation aimed at moves at most one period's turn.** The solver aims at the target orientation
//!   turned toward from the commanded tool orientation by at most what the slowest arm joint turns in the
//!   time since the last command (never more than [`MAX_AIM_STEP_RAD`]). A damped least-squares solve from a
//!   seed to an orientation this close stays on the seed's branch; aimed at a target 180° away it picks
//!   whichever side the arithmetic favours, which was the jump. Past 180° minus [`TURN_HYSTERESIS_RAD`] the
//!   turn keeps the direction it had, so a target that stays near the far side does not swing the wrist back
//!   and forth.
//! - **Position first, then as much orientation as fits the joint limits.** If the solution needs a joint
//!   step longer than the limit allows in the period, the orientation step is halved and the solve repeated
//!   (down to position only, which from a commanded pose that already meets the position needs no motion);
//!   only a step that the position itself needs is shortened by the limiter's common factor. So the tool
//!   leaves the target's position only when the target's position moves faster than the joints can follow.
//!
//! A 5-DoF arm reaches only part of the orientations at a position. For the rest the arm keeps the position
//! and turns as far toward the target as the null space of the position task allows, and stays there:
//! [`PlannedJoints::orientation_unreachable`] says so and [`JointCounters::orientation_unreachable`] counts
//! the commands. The same joints go to the sim, to the SO-101 servos and into the recorded action, so the
//! three agree.

use crate::config::ConfigError;
use crate::joint_limit::JointRateLimiter;
use crate::kinematics::{
    CR5_DOF, ChainKinematics, Cr5Kinematics, IkWeights, SO101_ARM_DOF, SO101_ARM_JOINT_NAMES, So101Kinematics,
};
use nalgebra::{Isometry3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Largest speed of an SO-101 joint, rad/s. Feetech's STS3215 data sheet gives a no-load speed of 0.222 s per
/// 60° at 12 V (45 rpm = 4.71 rad/s; the 7.4 V variant 0.192 s/60°, 5.45 rad/s), and a bench test of the
/// servo in the SO-ARM100 repository (TheRobotStudio/SO-ARM100 issue 134) measured 46 rpm. No-load is an
/// upper bound: a loaded servo is slower, so the arm follows commands at this speed rather than lagging
/// behind them unseen.
pub const STS3215_MAX_VELOCITY_RAD_S: f64 = 4.7;

/// Largest speed of a Dobot CR5 joint, rad/s: 180°/s for J1–J6, as Dobot's own MoveIt configuration for the
/// CR5 gives it (`Dobot-Arm/DOBOT_6Axis_ROS2_V4` `cr5_moveit/config/joint_limits.yaml`: `max_velocity: 3.14`
/// for every joint). No data sheet reachable here states it (Dobot's URDF gives `velocity="0"`); the
/// controller limits `ServoJ` itself too (docs/joint-limits.md).
pub const CR5_MAX_VELOCITY_RAD_S: f64 = PI;

/// Joint speed assumed for a remote bridge, whose robot the server does not know: 1 rad/s (57°/s), below
/// the rated speed of common desktop and collaborative arms, so that a remote robot is never asked for more
/// than it can do without its owner saying so.
pub const REMOTE_DEFAULT_MAX_VELOCITY_RAD_S: f64 = 1.0;

/// Largest orientation step aimed at in one solve, rad. Well below 90°, so the aim is always on the near
/// side of the commanded orientation, however long the time since the last command.
pub const MAX_AIM_STEP_RAD: f64 = 0.5;

/// Within this of a half turn the remaining turn keeps its direction (rad, about 20°).
pub const TURN_HYSTERESIS_RAD: f64 = 0.35;

/// An orientation aim missed by more than this counts as unreachable (rad, about 0.6°).
pub const ORIENTATION_REACHED_RAD: f64 = 0.01;

/// Halvings of the orientation step tried before falling back to position only.
const ORIENTATION_HALVINGS: usize = 3;

/// A missed orientation aim is solved again next tick only if the last command gained this much on the target
/// for each [`crate::joint_limit::MAX_STEP_S`] of motion it was allowed (rad, a tenth of
/// [`ORIENTATION_REACHED_RAD`]), from where the joints it started from stood toward that same target.
const CATCH_UP_GAIN_RAD: f64 = 1e-3;

/// A commanded joint move smaller than this (rad) means the arm has arrived.
const SETTLED_RAD: f64 = 1e-6;

/// A command allowed less motion time than this (s) tells nothing about whether the arm has arrived or still
/// gains on its target: two commands handed out in one pass of the control loop (a late tick playing two
/// chunk steps) are microseconds apart, and the second moves nothing because no time passed, not because the
/// arm is there. A quarter of the 500 Hz tick period, so every tick is judged.
const JUDGED_STEP_S: f64 = 5e-4;

/// Largest distance between the robot's reported tool position and the joint model's position of its reported
/// joints for the server to drive the arm through the model: 5 mm, well above the model's rounding (the CR5
/// URDF gives its lengths to the millimetre) and far below what a wrong base frame, tool or joint zero gives.
pub const MODEL_MATCH_M: f64 = 5e-3;
/// The same for the orientation: 0.05 rad (about 3°).
pub const MODEL_MATCH_RAD: f64 = 0.05;

/// A robot's reported tool pose off the joint model's pose of its reported joints (see
/// [`ArmJointStage::model_mismatch`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelMismatch {
    pub off_m: f64,
    pub off_rad: f64,
}

/// `[arms.<name>.joint_limits]`: per-joint speed limits of an arm.
#[derive(Debug, Clone, PartialEq, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct JointLimitConfig {
    /// Largest speed of each arm joint (rad/s), base to tool, gripper excluded. One value applies to every
    /// joint; empty means the robot's default ([`STS3215_MAX_VELOCITY_RAD_S`] for an SO-101,
    /// [`CR5_MAX_VELOCITY_RAD_S`] for a CR5, [`REMOTE_DEFAULT_MAX_VELOCITY_RAD_S`] for a remote bridge).
    pub max_velocity_rad_s: Vec<f64>,
    /// Largest acceleration of each arm joint (rad/s²), in the same order; one value applies to every joint.
    /// Empty means none: the SO-101's servos ramp their own speed (their `Acceleration` register) and the CR5's
    /// controller plans its own acceleration, and no data sheet here gives a joint figure for either.
    pub max_acceleration_rad_s2: Vec<f64>,
}

impl JointLimitConfig {
    /// The speed of each of `joints` joints, `default_rad_s` where none is configured. Refuses a list of
    /// another length and a speed that is not finite and positive.
    pub fn resolve(&self, joints: usize, default_rad_s: f64) -> Result<Vec<f64>, ConfigError> {
        let speeds = per_joint(&self.max_velocity_rad_s, joints, "max_velocity_rad_s")?
            .unwrap_or_else(|| vec![default_rad_s; joints]);
        // The limiter refuses what is not a speed.
        JointRateLimiter::new(speeds.clone())?;
        Ok(speeds)
    }

    /// The acceleration of each of `joints` joints, `None` when none is configured. Refuses a list of another
    /// length and a value that is not finite and positive.
    pub fn resolve_acceleration(&self, joints: usize) -> Result<Option<Vec<f64>>, ConfigError> {
        let Some(values) = per_joint(&self.max_acceleration_rad_s2, joints, "max_acceleration_rad_s2")?
        else {
            return Ok(None);
        };
        if let Some(&a) = values.iter().find(|a| !(a.is_finite() && **a > 0.0)) {
            return Err(ConfigError::NotPositive {
                name: "max_acceleration_rad_s2",
                value: a,
            });
        }
        Ok(Some(values))
    }
}

/// `values` for `joints` joints: one value for every joint, or one each; `None` when there is none.
fn per_joint(values: &[f64], joints: usize, name: &'static str) -> Result<Option<Vec<f64>>, ConfigError> {
    match values {
        [] => Ok(None),
        [one] => Ok(Some(vec![*one; joints])),
        many if many.len() == joints => Ok(Some(many.to_vec())),
        many => Err(ConfigError::WrongLength {
            name,
            expected: joints,
            got: many.len(),
        }),
    }
}

/// Commands the joint stage changed, since start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct JointCounters {
    /// Commands the joint speed limits shortened (see [`PlannedJoints::limited`]).
    pub limited: u64,
    /// Commands whose orientation the arm could not turn to from where it was (a 5-DoF arm's unreachable
    /// orientations, or a joint at its range limit).
    pub orientation_unreachable: u64,
}

/// The joints one command sends, and what was given up to send them.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedJoints<const N: usize = SO101_ARM_DOF> {
    pub joints_rad: [f64; N],
    /// The tool pose these joints put the arm in.
    pub achieved: Isometry3<f64>,
    /// Distance from the achieved tool position to the target's.
    pub position_error_m: f64,
    /// Angle from the achieved tool orientation to the target's.
    pub orientation_error_rad: f64,
    /// The joint speed limits shortened the step: the rate limiter, or the orientation aimed at (capped by what
    /// the joints turn in the time since the last command) short of a reachable target's.
    pub limited: bool,
    /// The arm could not turn toward the target orientation from here (see the module documentation).
    pub orientation_unreachable: bool,
    /// The target was not finite: the arm holds.
    pub invalid_input: bool,
}

/// The joint stage of one arm of `N` joints (see the module documentation). Pure: time is an argument.
#[derive(Debug, Clone)]
pub struct JointStage<const N: usize> {
    kinematics: ChainKinematics<N>,
    orientation_weight: f64,
    limiter: JointRateLimiter,
    /// The slowest joint's speed: the turn one period of the wrist is sure to manage.
    aim_speed_rad_s: f64,
    /// Direction of the turn in progress, kept through the half-turn (see [`TURN_HYSTERESIS_RAD`]).
    turn_axis: Option<Vector3<f64>>,
    counters: JointCounters,
    behind: bool,
}

/// The SO-101's joint stage.
pub type So101JointStage = JointStage<SO101_ARM_DOF>;

/// The Dobot CR5's joint stage.
pub type Cr5JointStage = JointStage<CR5_DOF>;

impl So101JointStage {
    /// An SO-101 stage with these joint speeds (five, rad/s) and IK orientation weight (0 = position only, 1 =
    /// as much orientation as the arm allows; the bridge's `ik_orientation_weight`).
    pub fn new(max_velocity_rad_s: Vec<f64>, orientation_weight: f64) -> Result<Self, ConfigError> {
        Self::with_kinematics(So101Kinematics::new(), max_velocity_rad_s, orientation_weight)
    }
}

impl Cr5JointStage {
    /// A CR5 stage with these joint speeds (six, rad/s), aiming at the full orientation (a 6-DoF arm reaches
    /// it inside its workspace).
    pub fn new(max_velocity_rad_s: Vec<f64>) -> Result<Self, ConfigError> {
        Self::with_kinematics(Cr5Kinematics::new(), max_velocity_rad_s, 1.0)
    }
}

impl<const N: usize> JointStage<N> {
    /// A stage over `kinematics` with these joint speeds (`N`, rad/s) and IK orientation weight.
    pub fn with_kinematics(
        kinematics: ChainKinematics<N>,
        max_velocity_rad_s: Vec<f64>,
        orientation_weight: f64,
    ) -> Result<Self, ConfigError> {
        if max_velocity_rad_s.len() != N {
            return Err(ConfigError::WrongLength {
                name: "max_velocity_rad_s",
                expected: N,
                got: max_velocity_rad_s.len(),
            });
        }
        if !(0.0..=1.0).contains(&orientation_weight) {
            return Err(ConfigError::NotFinite {
                name: "ik_orientation_weight",
                value: orientation_weight,
            });
        }
        let limiter = JointRateLimiter::new(max_velocity_rad_s)?;
        let aim_speed_rad_s = limiter
            .max_velocity_rad_s()
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        Ok(Self {
            kinematics,
            orientation_weight,
            limiter,
            aim_speed_rad_s,
            turn_axis: None,
            counters: JointCounters::default(),
            behind: false,
        })
    }

    /// Starts from the measured joints at `time_s` (at start, and whenever the arm's source changes or it was
    /// teleported): the next command is solved and limited from there.
    pub fn reset(&mut self, measured_rad: &[f64], time_s: f64) {
        let joints = to_joints::<N>(measured_rad).map(|q| self.kinematics.clamp(&q));
        match joints {
            Some(q) => self.limiter.reset(&q, time_s),
            // Not this arm's joints: no start, so the next command is not limited from a wrong one.
            None => self.limiter.forget(),
        }
        self.turn_axis = None;
        self.behind = false;
    }

    /// The joints last commanded (or reset to).
    pub fn commanded(&self) -> Option<[f64; N]> {
        self.limiter.last().and_then(to_joints)
    }

    /// Time of the last command (or reset), s.
    pub fn commanded_time_s(&self) -> f64 {
        self.limiter.last_time_s()
    }

    /// True while the last command did not reach its target (the limiter shortened it, or the orientation
    /// still turns): the caller should solve the same target again each period until it is false.
    pub fn behind(&self) -> bool {
        self.behind
    }

    pub fn counters(&self) -> JointCounters {
        self.counters
    }

    /// The joint speeds in force.
    pub fn max_velocity_rad_s(&self) -> &[f64] {
        self.limiter.max_velocity_rad_s()
    }

    /// The same stage with acceleration limits (`N` values, rad/s²; infinite for a joint without one): each
    /// joint's commanded velocity then changes by at most `a·dt` per command and slows in time to stop at
    /// its target (see [`JointRateLimiter::with_max_acceleration_rad_s2`]).
    pub fn with_max_acceleration_rad_s2(
        mut self,
        max_acceleration_rad_s2: Vec<f64>,
    ) -> Result<Self, ConfigError> {
        self.limiter = self
            .limiter
            .with_max_acceleration_rad_s2(max_acceleration_rad_s2)?;
        Ok(self)
    }

    /// The joints to command for `target` at `time_s`.
    pub fn plan(&mut self, target: &Isometry3<f64>, time_s: f64) -> PlannedJoints<N> {
        let seed = self
            .commanded()
            .unwrap_or_else(|| self.kinematics.clamp(&[0.0; N]));
        let dt = self.limiter.elapsed_s(time_s);
        let from = self.kinematics.forward(&seed);
        let finite = target
            .translation
            .vector
            .iter()
            .chain(target.rotation.coords.iter())
            .all(|v| v.is_finite());
        if !finite {
            return PlannedJoints {
                joints_rad: seed,
                achieved: from,
                position_error_m: f64::INFINITY,
                orientation_error_rad: f64::INFINITY,
                limited: false,
                orientation_unreachable: false,
                invalid_input: true,
            };
        }
        let (axis, wanted_rad) = self.turn_toward(&from.rotation, &target.rotation);
        let mut aim_rad = wanted_rad.min(self.aim_speed_rad_s * dt).min(MAX_AIM_STEP_RAD);
        // The turn the chosen solve aimed at: less than the period allows when the joint limits halved it, none
        // for position only. Short of the target's, it leaves the stage behind to turn the rest.
        let mut aimed_rad = aim_rad;
        let mut solution = None;
        // Each halved solve starts halfway between the seed and the previous attempt's joints, where its answer
        // about lies: a few iterations instead of a solve from the seed. Position only starts from the seed,
        // which already meets a position that did not move, so it needs no motion then.
        let mut start = seed;
        for attempt in 0..=ORIENTATION_HALVINGS + 1 {
            let position_only = attempt > ORIENTATION_HALVINGS || self.orientation_weight <= 0.0;
            let aim = UnitQuaternion::from_axis_angle(&axis, aim_rad) * from.rotation;
            let goal = Isometry3::from_parts(target.translation, aim);
            let weights = if position_only {
                IkWeights::POSITION_ONLY
            } else {
                IkWeights::FULL
            };
            let from_joints = if position_only { &seed } else { &start };
            let ik = self.kinematics.inverse(&goal, from_joints, weights);
            let fits = self.limiter.scale(&ik.joints_rad, time_s) >= 1.0;
            let missed = !position_only && ik.orientation_error_rad > ORIENTATION_REACHED_RAD;
            if fits || position_only {
                if position_only {
                    aimed_rad = 0.0;
                }
                solution = Some((ik, missed));
                break;
            }
            for ((s, q), q0) in start.iter_mut().zip(&ik.joints_rad).zip(&seed) {
                *s = 0.5 * (q + q0);
            }
            solution = Some((ik, missed));
            aim_rad *= 0.5;
            aimed_rad = aim_rad;
        }
        let capped = aimed_rad < wanted_rad;
        let (ik, missed) = solution.expect("at least one solve");
        let step = self.limiter.step(&ik.joints_rad, time_s);
        let stepped: [f64; N] = to_joints(&step.joints_rad).expect("the limiter keeps the width");
        // A joint still moving when its target turned back may be carried past it by the acceleration limit; its
        // range is a hard stop.
        let joints_rad = self.kinematics.clamp(&stepped);
        if !self.kinematics.within_limits(&stepped) {
            self.limiter.stop_at(&joints_rad);
        }
        let achieved = self.kinematics.forward(&joints_rad);
        let moved = joints_rad
            .iter()
            .zip(&seed)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let orientation_error_rad = target.rotation.angle_to(&achieved.rotation);
        // A capped aim that was reached leaves more turn to do. One that was missed is worth another solve only
        // while the turn still gains on the target: a 5-DoF arm held at an orientation it cannot reach otherwise
        // re-solves the same pose at the full tick rate for as long as the target stays.
        //
        // The gain is measured toward this target from the joints the command started from, not against the
        // error the previous command left toward its own target: a new target's first step starts farther from
        // it than that, so a target that moved further than one aim reaches (late commands, a skipped step)
        // would stop the stage after its first step, wherever it had got to. A command allowed less than a
        // full step time gains proportionally less.
        let started_rad = target.rotation.angle_to(&from.rotation);
        let gaining =
            orientation_error_rad < started_rad - CATCH_UP_GAIN_RAD * dt / self.limiter.max_step_s();
        self.behind = if dt < JUDGED_STEP_S {
            // Too short to judge: whatever is left stays to do, and the next tick judges it.
            step.limited || capped
        } else {
            step.limited || (capped && moved > SETTLED_RAD && (!missed || gaining))
        };
        // An aim cut short by the time since the last command is a speed limit too, and the one that binds a
        // command issued soon after a late one: the command holds joints short of the target's, which a
        // dataset that records this command must say. An aim cut short at an orientation the arm cannot
        // reach is counted as unreachable instead.
        let limited = step.limited || (capped && !missed);
        self.counters.limited += u64::from(limited);
        self.counters.orientation_unreachable += u64::from(missed);
        PlannedJoints {
            joints_rad,
            achieved,
            position_error_m: (target.translation.vector - achieved.translation.vector).norm(),
            orientation_error_rad,
            limited,
            orientation_unreachable: missed,
            invalid_input: false,
        }
    }

    /// The axis and angle of the turn from `from` toward `to` that this stage aims along, scaled by the
    /// orientation weight; remembers the direction for the half-turn rule.
    fn turn_toward(
        &mut self,
        from: &UnitQuaternion<f64>,
        to: &UnitQuaternion<f64>,
    ) -> (Unit<Vector3<f64>>, f64) {
        let weight = self.orientation_weight;
        let Some((axis, angle)) = (to * from.inverse()).axis_angle() else {
            self.turn_axis = None;
            return (Vector3::z_axis(), 0.0);
        };
        let (axis, angle) = match self.turn_axis {
            Some(previous) if angle > PI - TURN_HYSTERESIS_RAD && previous.dot(&axis) < 0.0 => {
                (-axis, 2.0 * PI - angle)
            }
            _ => (axis, angle),
        };
        self.turn_axis = Some(axis.into_inner());
        (axis, angle * weight)
    }
}

/// The joint stage of an arm whose kinematics the server knows, whichever robot it is: what the arm
/// controller holds.
#[derive(Debug, Clone)]
pub enum ArmJointStage {
    So101(So101JointStage),
    Cr5(Cr5JointStage),
    /// A chain a remote bridge declared (its model checked by the `joint_model` module), by its number of joints.
    Chain3(JointStage<3>),
    Chain4(JointStage<4>),
    Chain5(JointStage<5>),
    Chain6(JointStage<6>),
    Chain7(JointStage<7>),
}

macro_rules! each_stage {
    ($self:expr, $stage:ident => $body:expr) => {
        match $self {
            ArmJointStage::So101($stage) => $body,
            ArmJointStage::Cr5($stage) => $body,
            ArmJointStage::Chain3($stage) => $body,
            ArmJointStage::Chain4($stage) => $body,
            ArmJointStage::Chain5($stage) => $body,
            ArmJointStage::Chain6($stage) => $body,
            ArmJointStage::Chain7($stage) => $body,
        }
    };
}

impl ArmJointStage {
    /// See [`JointStage::reset`].
    pub fn reset(&mut self, measured_rad: &[f64], time_s: f64) {
        each_stage!(self, s => s.reset(measured_rad, time_s));
    }

    /// See [`JointStage::plan`]: the joints to command, base to tool.
    pub fn plan(&mut self, target: &Isometry3<f64>, time_s: f64) -> Vec<f64> {
        each_stage!(self, s => s.plan(target, time_s).joints_rad.to_vec())
    }

    /// See [`JointStage::commanded`].
    pub fn commanded(&self) -> Option<Vec<f64>> {
        each_stage!(self, s => s.commanded().map(|q| q.to_vec()))
    }

    /// See [`JointStage::commanded_time_s`].
    pub fn commanded_time_s(&self) -> f64 {
        each_stage!(self, s => s.commanded_time_s())
    }

    /// See [`JointStage::behind`].
    pub fn behind(&self) -> bool {
        each_stage!(self, s => s.behind())
    }

    /// See [`JointStage::counters`].
    pub fn counters(&self) -> JointCounters {
        each_stage!(self, s => s.counters())
    }

    /// See [`JointStage::with_max_acceleration_rad_s2`].
    pub fn with_max_acceleration_rad_s2(
        self,
        max_acceleration_rad_s2: Vec<f64>,
    ) -> Result<Self, ConfigError> {
        Ok(match self {
            Self::So101(s) => Self::So101(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Cr5(s) => Self::Cr5(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Chain3(s) => Self::Chain3(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Chain4(s) => Self::Chain4(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Chain5(s) => Self::Chain5(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Chain6(s) => Self::Chain6(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
            Self::Chain7(s) => Self::Chain7(s.with_max_acceleration_rad_s2(max_acceleration_rad_s2)?),
        })
    }

    /// See [`JointStage::max_velocity_rad_s`].
    pub fn max_velocity_rad_s(&self) -> &[f64] {
        each_stage!(self, s => s.max_velocity_rad_s())
    }

    /// The acceleration limits in force, if any.
    pub fn max_acceleration_rad_s2(&self) -> Option<&[f64]> {
        each_stage!(self, s => s.limiter.max_acceleration_rad_s2())
    }

    /// Number of joints the stage drives.
    pub fn joints(&self) -> usize {
        self.max_velocity_rad_s().len()
    }

    /// True if this stage can drive a bridge with these joints: an SO-101 stage the SO-101's by name (its
    /// kinematics are the SO-101's), any other stage as many joints as it has.
    pub fn fits(&self, joint_names: &[String]) -> bool {
        match self {
            Self::So101(_) => joint_names == SO101_ARM_JOINT_NAMES,
            other => joint_names.len() == other.joints(),
        }
    }

    /// How far `robot_from_ee`, the tool pose a robot reports, is from this model's pose of the joints it
    /// reports, when more than [`MODEL_MATCH_M`] or [`MODEL_MATCH_RAD`] (a controller whose base frame, tool or
    /// joint zeros differ from the model would be driven somewhere else than asked). None when they agree or
    /// the joints are not this stage's width.
    pub fn model_mismatch(
        &self,
        joints_rad: &[f64],
        robot_from_ee: &Isometry3<f64>,
    ) -> Option<ModelMismatch> {
        let model = self.forward(joints_rad)?;
        let off_m = (model.translation.vector - robot_from_ee.translation.vector).norm();
        let off_rad = model.rotation.angle_to(&robot_from_ee.rotation);
        (off_m > MODEL_MATCH_M || off_rad > MODEL_MATCH_RAD).then_some(ModelMismatch { off_m, off_rad })
    }

    /// The tool pose of `joints_rad` in this arm's model; `None` for a vector of another length.
    pub fn forward(&self, joints_rad: &[f64]) -> Option<Isometry3<f64>> {
        each_stage!(self, s => to_joints(joints_rad).map(|q| s.kinematics.forward(&q)))
    }
}

fn to_joints<const N: usize>(v: &[f64]) -> Option<[f64; N]> {
    v.try_into().ok()
}

#[cfg(test)]
// Exact equality is the property: no time, or a non-finite target, leaves the joints bit for bit.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use crate::kinematics::{SO101_JOINT_LIMITS_RAD, So101Joints, within_limits};
    use proptest::prelude::*;

    const PERIOD_S: f64 = 0.02;

    fn stage() -> So101JointStage {
        So101JointStage::new(vec![STS3215_MAX_VELOCITY_RAD_S; SO101_ARM_DOF], 1.0).unwrap()
    }

    fn largest_step_ratio(before: &So101Joints, after: &So101Joints, dt: f64) -> f64 {
        before
            .iter()
            .zip(after)
            .map(|(a, b)| (a - b).abs() / (STS3215_MAX_VELOCITY_RAD_S * dt))
            .fold(0.0, f64::max)
    }

    /// The reported case: the tool held still while the target turns a full circle about the vertical. A
    /// solver chasing the whole target from the previous solution flips branch on the way (the old path: more
    /// than a second's worth of a servo's travel in one 20 ms frame); the stage never exceeds the limit and
    /// keeps the position.
    #[test]
    fn a_stage_fits_its_own_joints_and_names_a_model_that_disagrees_with_the_robot() {
        let so101 = ArmJointStage::So101(stage());
        let names = |n: &[&str]| n.iter().map(|&s| s.to_owned()).collect::<Vec<_>>();
        assert!(so101.fits(&names(&SO101_ARM_JOINT_NAMES)));
        assert!(
            !so101.fits(&names(&["a", "b", "c", "d", "e"])),
            "five joints, not the SO-101's"
        );
        let cr5 = ArmJointStage::Cr5(Cr5JointStage::new(vec![1.0; CR5_DOF]).unwrap());
        assert!(cr5.fits(&names(&["j1", "j2", "j3", "j4", "j5", "j6"])));
        assert!(!cr5.fits(&names(&SO101_ARM_JOINT_NAMES)));

        let joints = [0.1, -0.4, 0.6, 0.3, -0.2];
        let model = So101Kinematics::new().forward(&joints);
        assert_eq!(so101.model_mismatch(&joints, &model), None);
        // Within the tolerance: a millimetre and a hundredth of a radian.
        let near = Isometry3::translation(0.001, 0.0, 0.0)
            * model
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.01);
        assert_eq!(so101.model_mismatch(&joints, &near), None);
        let shifted = Isometry3::translation(0.0, 0.0, 0.01) * model;
        let off = so101.model_mismatch(&joints, &shifted).unwrap();
        assert!((off.off_m - 0.01).abs() < 1e-12 && off.off_rad < 1e-9, "{off:?}");
        let turned = model * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.1);
        let off = so101.model_mismatch(&joints, &turned).unwrap();
        assert!((off.off_rad - 0.1).abs() < 1e-9, "{off:?}");
        // Joints of another width are not this model's to judge.
        assert_eq!(so101.model_mismatch(&joints[..4], &shifted), None);
    }

    #[test]
    fn a_full_turn_about_the_vertical_neither_jumps_nor_moves_the_tool() {
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let home = k.forward(&start);
        let frames = 400;
        let mut s = stage();
        s.reset(&start, 0.0);
        let mut previous = start;
        let mut chased = start;
        let mut largest_chase_step: f64 = 0.0;
        let mut largest_ratio: f64 = 0.0;
        let mut largest_position_error: f64 = 0.0;
        for frame in 1..=frames {
            let turn = 2.0 * PI * f64::from(frame) / f64::from(frames);
            let target = Isometry3::from_parts(
                home.translation,
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), turn) * home.rotation,
            );
            let old = k.inverse(&target, &chased, IkWeights::FULL);
            largest_chase_step = largest_chase_step.max(
                old.joints_rad
                    .iter()
                    .zip(&chased)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max),
            );
            chased = old.joints_rad;
            let planned = s.plan(&target, f64::from(frame) * PERIOD_S);
            assert!(within_limits(&planned.joints_rad));
            largest_ratio = largest_ratio.max(largest_step_ratio(&previous, &planned.joints_rad, PERIOD_S));
            largest_position_error = largest_position_error.max(planned.position_error_m);
            previous = planned.joints_rad;
        }
        println!(
            "full turn: chasing solver's largest step {largest_chase_step:.3} rad; stage: largest step {largest_ratio:.3} of the limit, position error {:.3} mm",
            largest_position_error * 1e3
        );
        assert!(
            largest_chase_step > STS3215_MAX_VELOCITY_RAD_S * PERIOD_S * 3.0,
            "the chasing solver no longer jumps ({largest_chase_step} rad): this test lost its point"
        );
        assert!(largest_ratio <= 1.0 + 1e-9, "{largest_ratio}");
        assert!(largest_position_error < 2e-4, "{largest_position_error}");
        assert!(
            s.counters().orientation_unreachable > 0,
            "a 5-DoF arm cannot follow this turn"
        );
    }

    #[test]
    fn a_far_target_is_approached_at_the_limit_and_reached() {
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let goal = [0.8, 0.2, 0.1, 0.5, 1.0];
        let target = k.forward(&goal);
        let mut s = stage();
        s.reset(&start, 0.0);
        let mut previous = start;
        let mut t = 0.0;
        let mut limited = 0;
        for _ in 0..200 {
            t += PERIOD_S;
            let p = s.plan(&target, t);
            assert!(largest_step_ratio(&previous, &p.joints_rad, PERIOD_S) <= 1.0 + 1e-9);
            limited += u64::from(p.limited);
            previous = p.joints_rad;
            if !s.behind() {
                break;
            }
        }
        assert!(!s.behind(), "still behind after 4 s");
        assert!(limited > 5 && s.counters().limited == limited, "{limited}");
        let done = s.plan(&target, t + PERIOD_S);
        assert!(
            done.position_error_m < 1e-4 && done.orientation_error_rad < 1e-2,
            "{done:?}"
        );
    }

    /// A new target a 20 ms command does not reach in one step (recorded joint actions a late frame apart): the
    /// stage stays behind and reaches it, whether its first aim was one a 5-DoF arm misses at the new position
    /// (0.37 rad of wrist roll with the wrist flexing) or one the joint limits halved (0.095 rad of roll with a
    /// little of every joint). Before, the first stopped because the previous target had been reached (no
    /// gain counted), the second because a halved aim did not count as short of the target.
    #[test]
    fn a_new_target_is_reached_when_its_first_aim_is_missed_or_halved() {
        let k = So101Kinematics::new();
        let cases = [
            (
                [-0.06, -0.63, 0.70, 0.83, -2.05],
                [-0.03, -0.64, 0.66, 0.90, -1.67],
                true,
            ),
            (
                [-0.0409, -0.6255, 0.6469, 0.8724, -1.0960],
                [-0.0365, -0.6299, 0.6377, 0.8893, -1.0013],
                false,
            ),
        ];
        for (from, to, first_missed) in cases {
            let mut s = stage();
            s.reset(&from, 0.0);
            // At rest on the first target.
            s.plan(&k.forward(&from), PERIOD_S);
            assert!(!s.behind());
            let target = k.forward(&to);
            let first = s.plan(&target, 2.0 * PERIOD_S);
            assert_eq!(first.orientation_unreachable, first_missed, "{first:?}");
            assert!(
                first.orientation_error_rad > 0.04,
                "reached in one step: this case lost its point"
            );
            assert!(
                s.behind(),
                "the stage stopped after its first step at {:?}",
                first.joints_rad
            );
            let mut t = 2.0 * PERIOD_S;
            for _ in 0..50 {
                t += PERIOD_S;
                s.plan(&target, t);
                if !s.behind() {
                    break;
                }
            }
            let reached = s.commanded().unwrap();
            let off = reached
                .iter()
                .zip(&to)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(off < 2e-4, "settled at {reached:?}, {off} rad from {to:?}");
        }
    }

    /// A late tick plays two chunk steps, handed out microseconds apart: the second command moves nothing because
    /// no time passed. That must not stop the stage short of its target. It did: the second command counted as
    /// "arrived" (no motion), no tick followed, and the arm stayed where the first command left it (a 0.45 rad
    /// turn stopped after 0.01 rad on a loaded machine).
    #[test]
    fn a_command_microseconds_after_another_does_not_stop_the_stage() {
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let goal = [0.8, 0.2, 0.1, 0.5, 1.0];
        let target = k.forward(&goal);
        for gap_s in [0.0, 1e-9, 1e-6, 1e-4] {
            let mut s = stage();
            s.reset(&start, 0.0);
            let mut t = 0.0;
            for _ in 0..400 {
                t += PERIOD_S;
                s.plan(&target, t);
                s.plan(&target, t + gap_s);
                t += gap_s;
                if !s.behind() {
                    break;
                }
            }
            let reached = s.commanded().unwrap();
            let off = reached
                .iter()
                .zip(&goal)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                off < 1e-3,
                "gap {gap_s} s: stopped at {reached:?}, {off} rad from {goal:?}"
            );
        }
    }

    #[test]
    fn no_time_no_motion_and_a_non_finite_target_holds() {
        let k = So101Kinematics::new();
        let start = [0.1, -0.4, 0.6, 0.9, 0.2];
        let mut s = stage();
        s.reset(&start, 1.0);
        let moved = Isometry3::translation(0.01, 0.0, 0.0) * k.forward(&start);
        assert_eq!(s.plan(&moved, 1.0).joints_rad, start);
        // Nor for a turn: the arm holds, and the turn is still to do (no time passed, so nothing says it cannot
        // be done): the stage stays behind, and the next tick turns.
        let turned = Isometry3::from_parts(
            k.forward(&start).translation,
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3) * k.forward(&start).rotation,
        );
        assert_eq!(s.plan(&turned, 1.0).joints_rad, start);
        assert!(s.behind());
        let turning = s.plan(&turned, 1.0 + PERIOD_S).joints_rad;
        assert_ne!(turning, start);
        let bad = Isometry3::translation(f64::NAN, 0.0, 0.0);
        let p = s.plan(&bad, 2.0);
        assert!(p.invalid_input);
        assert_eq!(p.joints_rad, turning);
        assert_eq!(s.commanded(), Some(turning));
    }

    #[test]
    fn configured_speeds_resolve_per_joint() {
        let none = JointLimitConfig::default();
        assert_eq!(none.resolve(3, 2.0).unwrap(), vec![2.0; 3]);
        let one = JointLimitConfig {
            max_velocity_rad_s: vec![1.5],
            ..JointLimitConfig::default()
        };
        assert_eq!(one.resolve(2, 2.0).unwrap(), vec![1.5; 2]);
        let each = JointLimitConfig {
            max_velocity_rad_s: vec![1.0, 2.0],
            ..JointLimitConfig::default()
        };
        assert_eq!(each.resolve(2, 9.0).unwrap(), vec![1.0, 2.0]);
        assert!(matches!(
            each.resolve(3, 9.0),
            Err(ConfigError::WrongLength {
                expected: 3,
                got: 2,
                ..
            })
        ));
        let zero = JointLimitConfig {
            max_velocity_rad_s: vec![0.0],
            ..JointLimitConfig::default()
        };
        assert!(zero.resolve(2, 1.0).is_err());
        assert!(So101JointStage::new(vec![1.0; 4], 1.0).is_err());
        // Accelerations the same way; none configured is none.
        assert_eq!(none.resolve_acceleration(3).unwrap(), None);
        let accelerations = |v: Vec<f64>| JointLimitConfig {
            max_acceleration_rad_s2: v,
            ..JointLimitConfig::default()
        };
        assert_eq!(
            accelerations(vec![2.0]).resolve_acceleration(2).unwrap(),
            Some(vec![2.0; 2])
        );
        assert_eq!(
            accelerations(vec![1.0, 2.0]).resolve_acceleration(2).unwrap(),
            Some(vec![1.0, 2.0])
        );
        assert!(matches!(
            accelerations(vec![1.0, 2.0]).resolve_acceleration(3),
            Err(ConfigError::WrongLength {
                expected: 3,
                got: 2,
                ..
            })
        ));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(accelerations(vec![bad]).resolve_acceleration(2).is_err(), "{bad}");
        }
        assert!(So101JointStage::new(vec![1.0; 5], 1.5).is_err());
    }

    fn joints_strategy() -> impl Strategy<Value = So101Joints> {
        let r = |i: usize| (SO101_JOINT_LIMITS_RAD[i].0 * 0.8)..(SO101_JOINT_LIMITS_RAD[i].1 * 0.8);
        (r(0), r(1), r(2), r(3), r(4)).prop_map(|(a, b, c, d, e)| [a, b, c, d, e])
    }

    /// One target move as the task-space gate lets it through: a position step of at most its 6 cm jump
    /// threshold (in any direction, so toward and past the edge of reach) and a turn of at most its 0.5 rad.
    #[derive(Debug, Clone)]
    struct Move {
        dp: [f64; 3],
        axis: [f64; 3],
        turn_rad: f64,
        dt_s: f64,
        repeat: usize,
    }

    fn move_strategy(position: bool) -> impl Strategy<Value = Move> {
        let d = if position { 0.034 } else { 0.0 };
        let dp = -d..=d;
        (
            prop::array::uniform3(dp),
            prop::array::uniform3(-1.0f64..1.0),
            -0.5f64..0.5,
            0.0f64..0.06,
            1usize..30,
        )
            .prop_map(|(dp, axis, turn_rad, dt_s, repeat)| Move {
                dp,
                axis,
                turn_rad,
                dt_s,
                repeat,
            })
    }

    /// Runs `moves` (each repeated: a steady turn about one axis for up to 30 frames, 15 rad in all, so full
    /// turns about arbitrary axes are among them) and checks every command. Returns the largest position
    /// error of the commands.
    fn run(start: So101Joints, moves: &[Move]) -> Result<f64, TestCaseError> {
        run_stage(
            &So101Kinematics::new(),
            stage(),
            STS3215_MAX_VELOCITY_RAD_S,
            start,
            moves,
        )
    }

    /// [`run`] for any arm: `s` over `k`, every joint limited to `speed_rad_s`.
    fn run_stage<const N: usize>(
        k: &ChainKinematics<N>,
        mut s: JointStage<N>,
        speed_rad_s: f64,
        start: [f64; N],
        moves: &[Move],
    ) -> Result<f64, TestCaseError> {
        let step_ratio = |before: &[f64; N], after: &[f64; N], dt: f64| {
            before
                .iter()
                .zip(after)
                .map(|(a, b)| (a - b).abs() / (speed_rad_s * dt))
                .fold(0.0, f64::max)
        };
        let mut target = k.forward(&start);
        s.reset(&start, 0.0);
        let mut t = 0.0;
        let mut previous = start;
        let mut largest_error: f64 = 0.0;
        for m in moves {
            let axis = Vector3::from(m.axis);
            let turn = if axis.norm() > 1e-3 {
                UnitQuaternion::from_scaled_axis(axis.normalize() * m.turn_rad)
            } else {
                UnitQuaternion::identity()
            };
            for _ in 0..m.repeat {
                target = Isometry3::from_parts(
                    (target.translation.vector + Vector3::from(m.dp)).into(),
                    turn * target.rotation,
                );
                t += m.dt_s;
                let p = s.plan(&target, t);
                prop_assert!(k.within_limits(&p.joints_rad), "{p:?}");
                let ratio = step_ratio(&previous, &p.joints_rad, m.dt_s);
                prop_assert!(
                    ratio <= 1.0 + 1e-9 || m.dt_s == 0.0 && p.joints_rad == previous,
                    "step {ratio} of the limit"
                );
                largest_error = largest_error.max(p.position_error_m);
                previous = p.joints_rad;
            }
        }
        Ok(largest_error)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(if cfg!(debug_assertions) { 12 } else { 256 }))]

        /// Any target sequence the gate passes (positions at and past the edge of reach included): no joint
        /// step exceeds its limit.
        #[test]
        fn no_command_exceeds_the_joint_limits(start in joints_strategy(),
                                               moves in prop::collection::vec(move_strategy(true), 1..6)) {
            run(start, &moves)?;
        }

        /// The position held, the orientation anything (full turns about any axis, orientations the 5-DoF arm
        /// cannot reach): every command keeps the tool within 0.2 mm of the position, twice the solver's
        /// position tolerance (1e-4 m). It holds because the orientation step is shrunk until the solution
        /// fits the limits, down to position only, which from a pose that meets the position needs no motion:
        /// the limiter never has to cut a step short between two solutions.
        #[test]
        fn a_held_position_stays_held_whatever_the_orientation(start in joints_strategy(),
                                                               moves in prop::collection::vec(move_strategy(false), 1..6)) {
            let error = run(start, &moves)?;
            prop_assert!(error < 2e-4, "position error {error} m");
        }

        /// The CR5: any target sequence the gate passes, full turns about any axis and positions toward and past
        /// the edge of its 0.9 m reach included: no joint step exceeds its limit.
        #[test]
        fn no_cr5_command_exceeds_the_joint_limits(start in cr5_joints_strategy(),
                                                   moves in prop::collection::vec(move_strategy(true), 1..6)) {
            run_stage(&Cr5Kinematics::new(), cr5_stage(), CR5_MAX_VELOCITY_RAD_S, start, &moves)?;
        }

        /// The CR5 with the position held and the orientation anything (a 6-DoF arm reaches every orientation
        /// away from its singularities; near them the turn slows to what the joints allow): every command keeps
        /// the tool within 0.2 mm of the position, for the same reason as the SO-101's.
        #[test]
        fn a_cr5_held_position_stays_held_whatever_the_orientation(start in cr5_joints_strategy(),
                                                                   moves in prop::collection::vec(move_strategy(false), 1..6)) {
            let error = run_stage(&Cr5Kinematics::new(), cr5_stage(), CR5_MAX_VELOCITY_RAD_S, start, &moves)?;
            prop_assert!(error < 2e-4, "position error {error} m");
        }
    }

    fn cr5_stage() -> Cr5JointStage {
        Cr5JointStage::new(vec![CR5_MAX_VELOCITY_RAD_S; CR5_DOF]).unwrap()
    }

    /// CR5 starts in its usual working region: elbow bent either way, wrist away from its J5 = 0 singularity.
    fn cr5_joints_strategy() -> impl Strategy<Value = [f64; CR5_DOF]> {
        (
            -3.0f64..3.0,
            -1.2f64..1.2,
            prop_oneof![0.4f64..2.5, -2.5f64..-0.4],
            -3.0f64..3.0,
            prop_oneof![0.3f64..2.8, -2.8f64..-0.3],
            -3.0f64..3.0,
        )
            .prop_map(|(a, b, c, d, e, f)| [a, b, c, d, e, f])
    }

    /// A move the limits allow in one period arrives in that command: nothing is left to catch up on, so the
    /// arm does not tick again for it.
    #[test]
    fn a_move_that_fits_is_not_behind() {
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let mut s = stage();
        s.reset(&start, 0.0);
        let target = k.forward(&[0.01, -0.39, 0.6, 0.9, 0.01]);
        let p = s.plan(&target, PERIOD_S);
        assert!(!p.limited && p.position_error_m < 1e-4, "{p:?}");
        assert!(!s.behind());
        // And its orientation, the pose of real joints, was reached: nothing counted as unreachable.
        assert!(!p.orientation_unreachable && p.orientation_error_rad < ORIENTATION_REACHED_RAD);
        assert_eq!(s.counters(), JointCounters::default());
    }

    /// A wrist turn a frame period allows, commanded 10 ms after the previous command (a late tick followed by
    /// a punctual one), is aimed only as far as the joints turn in 10 ms: that command holds joints short of
    /// the target's, and it is counted as limited so that a dataset recording it says so.
    #[test]
    fn an_aim_cut_short_by_the_time_since_the_last_command_counts_as_limited() {
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let mut s = stage();
        s.reset(&start, 0.0);
        let turned = |roll: f64| k.forward(&[0.0, -0.4, 0.6, 0.9, roll]);
        let p = s.plan(&turned(0.08), 0.05);
        assert!(
            !p.limited && p.orientation_error_rad < ORIENTATION_REACHED_RAD,
            "{p:?}"
        );
        let p = s.plan(&turned(0.16), 0.06);
        assert!(p.limited && !p.orientation_unreachable, "{p:?}");
        assert!(p.orientation_error_rad > 0.02, "{p:?}");
        assert!(s.behind());
        assert_eq!(s.counters().limited, 1);
    }

    /// The arm controller's handle passes everything through to the robot's stage.
    #[test]
    fn the_arm_stage_is_the_robots_stage() {
        let k = Cr5Kinematics::new();
        let start = [0.0, 0.3, 1.5, 0.0, 1.5, 0.0];
        let mut direct = cr5_stage();
        let mut arm = ArmJointStage::Cr5(cr5_stage());
        assert_eq!(arm.commanded(), None);
        direct.reset(&start, 1.0);
        arm.reset(&start, 1.0);
        assert_eq!(arm.commanded(), Some(start.to_vec()));
        assert_eq!(arm.commanded_time_s(), 1.0);
        let far = k.forward(&[0.9, -0.2, 1.2, 0.6, 1.1, -1.0]);
        let planned = direct.plan(&far, 1.02);
        assert_eq!(arm.plan(&far, 1.02), planned.joints_rad.to_vec());
        assert!(arm.behind() && direct.behind());
        assert_eq!(arm.counters(), direct.counters());
        assert!(arm.counters().limited == 1);
        assert_eq!(arm.forward(&start), Some(k.forward(&start)));
        assert_eq!(arm.forward(&start[..5]), None);
        let mut so101 = ArmJointStage::So101(stage());
        so101.reset(&[0.0, -0.4, 0.6, 0.9, 0.0], 0.0);
        assert_eq!(so101.commanded().map(|q| q.len()), Some(SO101_ARM_DOF));
        assert!(!so101.behind());
        assert_eq!(
            so101.forward(&[0.0, -0.4, 0.6, 0.9, 0.0]),
            Some(So101Kinematics::new().forward(&[0.0, -0.4, 0.6, 0.9, 0.0]))
        );
    }

    /// With acceleration limits the stage reaches a far target too: every step within the speed limit, every
    /// velocity change within `a·dt` (the landing one within twice it), the joints inside their ranges.
    #[test]
    fn a_far_target_is_reached_under_acceleration_limits() {
        const A: f64 = 20.0;
        let k = So101Kinematics::new();
        let start = [0.0, -0.4, 0.6, 0.9, 0.0];
        let target = k.forward(&[0.8, 0.2, 0.1, 0.5, 1.0]);
        let mut s = stage()
            .with_max_acceleration_rad_s2(vec![A; SO101_ARM_DOF])
            .unwrap();
        assert!(stage().with_max_acceleration_rad_s2(vec![A; 4]).is_err());
        s.reset(&start, 0.0);
        let (mut previous, mut velocity, mut t) = (start, [0.0; SO101_ARM_DOF], 0.0);
        for _ in 0..400 {
            t += PERIOD_S;
            let p = s.plan(&target, t);
            assert!(within_limits(&p.joints_rad));
            for j in 0..SO101_ARM_DOF {
                let v = (p.joints_rad[j] - previous[j]) / PERIOD_S;
                assert!(
                    v.abs() <= STS3215_MAX_VELOCITY_RAD_S * (1.0 + 1e-9),
                    "joint {j}: {v}"
                );
                assert!(
                    (v - velocity[j]).abs() <= 2.0 * A * PERIOD_S * (1.0 + 1e-9),
                    "joint {j}: {} -> {v}",
                    velocity[j]
                );
                velocity[j] = v;
            }
            previous = p.joints_rad;
            if !s.behind() {
                break;
            }
        }
        assert!(!s.behind(), "still behind after 8 s");
        let done = s.plan(&target, t + PERIOD_S);
        assert!(done.position_error_m < 1e-4, "{done:?}");
    }

    /// A joint braking under its acceleration limit for a target that turned back can be carried past the old
    /// target when the commands come faster than they did while it sped up (braking at shorter steps covers
    /// more ground): here past the range of a pan driven to its stop. The range is a hard stop: the command
    /// stays inside it, and the joint, stopped there, starts back at once instead of first returning from a
    /// point beyond the stop that the arm never reached.
    #[test]
    fn a_joint_carried_to_its_range_stop_stops_there_and_starts_back_from_it() {
        const A: f64 = 20.0;
        const FAST_S: f64 = 0.001;
        let k = So101Kinematics::new();
        let (_, pan_max) = SO101_JOINT_LIMITS_RAD[0];
        let rest = [-0.4, 0.6, 0.9, 0.0];
        let at_pan = |pan: f64| k.forward(&[pan, rest[0], rest[1], rest[2], rest[3]]);
        let start_pan = pan_max - 0.6;
        let mut s = stage()
            .with_max_acceleration_rad_s2(vec![A; SO101_ARM_DOF])
            .unwrap();
        s.reset(&[start_pan, rest[0], rest[1], rest[2], rest[3]], 0.0);
        let (mut t, mut pan) = (0.0, start_pan);
        // Speed up toward the stop at 20 ms commands until braking at 1 ms commands would pass it.
        let mut turned = false;
        for _ in 0..100 {
            t += PERIOD_S;
            let p = s.plan(&at_pan(pan_max), t);
            let v = (p.joints_rad[0] - pan) / PERIOD_S;
            pan = p.joints_rad[0];
            if v > 0.0 && pan_max - pan < v * v / (2.0 * A) - v * FAST_S / 2.0 - 1e-3 {
                turned = true;
                break;
            }
        }
        assert!(turned, "the pan never came fast enough to the stop");
        let mut at_stop = None;
        let mut pans = Vec::new();
        for i in 0..600 {
            t += FAST_S;
            let p = s.plan(&at_pan(start_pan), t);
            assert!(within_limits(&p.joints_rad), "{:?}", p.joints_rad);
            pans.push(p.joints_rad[0]);
            if at_stop.is_none() && p.joints_rad[0] == pan_max {
                at_stop = Some(i);
            }
        }
        let at_stop = at_stop.expect("braking at shorter steps did not carry the pan to its stop");
        assert!(
            pans[at_stop + 1] < pan_max,
            "the pan stayed at its stop after reaching it: {:?}",
            &pans[at_stop..(at_stop + 20).min(pans.len())]
        );
        assert!(
            pans[599] < pans[at_stop + 1],
            "the pan never went back: {:?}",
            &pans[590..]
        );
    }

    /// Near the CR5's wrist singularity (J5 close to 0) a small turn of the tool needs a large turn of J4 and J6,
    /// so the orientation step is halved until it fits: down to an eighth of the aimed step before position
    /// only. Scanning J5 toward the singularity finds starts where only the eighth fits; there the tool turns
    /// by about an eighth of the aim (not by nothing, which is what giving up one halving early would do), and
    /// no command ever exceeds the limit.
    #[test]
    fn near_a_singularity_the_orientation_step_is_halved_three_times_before_giving_up() {
        let k = Cr5Kinematics::new();
        let aim_rad = CR5_MAX_VELOCITY_RAD_S * PERIOD_S;
        let mut eighths = 0;
        let mut position_only = 0;
        for i in 1..=120 {
            let j5 = f64::from(i) * 0.005;
            let start = [0.3, 0.2, 1.6, 0.4, j5, -0.2];
            let from = k.forward(&start);
            // A turn about the tool's own x axis: J5 near 0 leaves J4 and J6 to make it.
            let turn = UnitQuaternion::from_axis_angle(&(from.rotation * Vector3::x_axis()), 0.4);
            let target = Isometry3::from_parts(from.translation, turn * from.rotation);
            let mut s = cr5_stage();
            s.reset(&start, 0.0);
            let p = s.plan(&target, PERIOD_S);
            let step = start
                .iter()
                .zip(&p.joints_rad)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                step <= CR5_MAX_VELOCITY_RAD_S * PERIOD_S * (1.0 + 1e-9),
                "J5 {j5}: step {step}"
            );
            let turned = from.rotation.angle_to(&p.achieved.rotation);
            if turned > aim_rad / 12.0 && turned < aim_rad / 6.0 {
                eighths += 1;
            }
            position_only += usize::from(turned < 1e-9);
        }
        assert!(
            eighths > 0,
            "no start needed exactly three halvings ({position_only} gave up)"
        );
        assert!(
            position_only > 0,
            "no start was close enough to the singularity to give up"
        );
    }

    /// A reachable CR5 target far from the start (a 6-DoF arm: position and orientation both) is approached
    /// at the limit and reached, position and orientation.
    #[test]
    fn a_far_cr5_target_is_approached_at_the_limit_and_reached() {
        let k = Cr5Kinematics::new();
        let start = [0.0, 0.3, 1.5, 0.0, 1.5, 0.0];
        let goal = [0.9, -0.2, 1.2, 0.6, 1.1, -1.0];
        let target = k.forward(&goal);
        let mut s = cr5_stage();
        s.reset(&start, 0.0);
        let mut previous = start;
        let mut t = 0.0;
        for _ in 0..400 {
            t += PERIOD_S;
            let p = s.plan(&target, t);
            let ratio = previous
                .iter()
                .zip(&p.joints_rad)
                .map(|(a, b)| (a - b).abs() / (CR5_MAX_VELOCITY_RAD_S * PERIOD_S))
                .fold(0.0, f64::max);
            assert!(ratio <= 1.0 + 1e-9, "{ratio}");
            previous = p.joints_rad;
            if !s.behind() {
                break;
            }
        }
        assert!(!s.behind(), "still behind after 8 s");
        assert!(s.counters().limited > 5, "{:?}", s.counters());
        let done = s.plan(&target, t + PERIOD_S);
        assert!(
            done.position_error_m < 1e-4 && done.orientation_error_rad < 1e-3,
            "{done:?}"
        );
    }
}
