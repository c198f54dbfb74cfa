//! The simulated world, as a pure state machine: SO-101 joints with first-order dynamics toward the IK
//! solution of the command in force, a first-order gripper whose fingers, palm and wrist push a resting ball,
//! and a ball that can be grasped from between the fingers, carried, dropped and land in a basket. No threads
//! and no clock reads: [`SimWorld::step`] advances by an explicit `dt_s`, and [`SimWorld::apply_command_at`]
//! puts a command in force at the time it was issued, so the arm's path is a function of the command history
//! and time alone, whoever calls it and whenever.

use super::config::SimConfig;
pub use crate::scene::{BallState, SceneState};
use crate::{BridgeError, Command, Feedback};
use nalgebra::{Isometry3, Point3, Vector3};
use phone2act_core::kinematics::{
    IkSolution, IkWeights, So101Joints, So101Kinematics, So101LinkPoses, clamp_to_limits,
};
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::{RngCore, SeedableRng};

/// The two-finger gripper, in the tool frame (z: approach, y: the direction the fingers close along, x: the
/// fingers' width). Each finger is a plate with rounded edges from the palm (z = `FINGER_ROOT_M`) to its tip
/// (z = `FINGER_TIP_M`), `2 * FINGER_HALF_WIDTH_M` wide; the palm is a plate across the finger roots, the wrist
/// body a rod behind it. All are solids for a resting ball; the ball can be taken only from between the
/// fingers.
pub(crate) const FINGER_TIP_M: f64 = 0.008;
pub(crate) const FINGER_ROOT_M: f64 = -0.055;
pub(crate) const FINGER_HALF_WIDTH_M: f64 = 0.012;
/// Half the thickness of a finger (the radius of its rounded edges).
pub(crate) const FINGER_HALF_THICKNESS_M: f64 = 0.006;
/// Gap between each finger's inner face and the tool axis when the gripper is fully open (position 0); it
/// shrinks linearly with the gripper position to 0 at fully closed (1). A 2 cm ball fits with 1.4 cm to spare
/// on each side.
pub(crate) const OPEN_HALF_GAP_M: f64 = 0.034;
const PALM_HALF_THICKNESS_M: f64 = 0.008;
const WRIST_RADIUS_M: f64 = 0.017;
/// A held ball is let go once the gripper has opened this far past the ball's width (hysteresis, so that
/// noise on a gripper closed on the ball does not drop and re-grasp it).
const RELEASE_MARGIN: f64 = 0.1;
/// Contact passes per substep: a push by one solid can put the ball into another (a finger into the palm).
const CONTACT_PASSES: usize = 8;
const GRAVITY_M_S2: f64 = 9.81;
/// Longest step taken in one go; a stalled thread resumes without the ball tunnelling through the table.
const MAX_STEP_S: f64 = 0.02;
/// Thickness of the basket floor.
pub(crate) const BASKET_FLOOR_M: f64 = 0.004;

/// What the renderer needs of one instant of the world.
#[derive(Clone, Debug)]
pub struct SceneSnapshot {
    pub links: So101LinkPoses,
    pub gripper_position: f64,
    pub ball_center_m: Vector3<f64>,
    pub ball_radius_m: f64,
    pub ball_state: BallState,
    pub basket_xy_m: [f64; 2],
    pub basket_radius_m: f64,
    pub basket_height_m: f64,
    pub task_success: bool,
}

/// Result of handing a command to the world.
#[derive(Clone, Debug, PartialEq)]
pub enum CommandOutcome {
    /// Joint targets updated; the IK solution (residuals, reachability) is attached.
    Applied(Box<IkSolution>),
    /// Not finite (pose or gripper); nothing changed.
    Rejected,
    /// The arm is disabled; nothing changed.
    Disabled,
}

/// An IK problem detached from the world (see [`SimWorld::ik_request`]).
#[derive(Clone, Debug)]
pub struct IkRequest {
    kinematics: So101Kinematics,
    seed: So101Joints,
    weights: IkWeights,
}

impl IkRequest {
    /// The joints the command asks for: its joint targets when the server solved them (then the solution
    /// reports their forward kinematics against the command's pose), otherwise the IK of its pose.
    pub fn solve(&self, command: &Command) -> IkSolution {
        match command.joint_targets_rad.as_deref().map(<So101Joints>::try_from) {
            Some(Ok(joints)) => self.given(&joints, &command.robot_from_target),
            // Joint targets of another width are no SO-101's: refused like a non-finite pose.
            Some(Err(_)) => IkSolution {
                invalid_input: true,
                ..self.given(&self.seed, &command.robot_from_target)
            },
            None => self
                .kinematics
                .inverse(&command.robot_from_target, &self.seed, self.weights),
        }
    }

    fn given(&self, joints: &So101Joints, target: &Isometry3<f64>) -> IkSolution {
        let solver = &self.kinematics.solver;
        let invalid_input = !joints.iter().all(|q| q.is_finite());
        let joints_rad = clamp_to_limits(joints);
        let achieved = self.kinematics.forward(&joints_rad);
        let position_error_m = (target.translation.vector - achieved.translation.vector).norm();
        let orientation_error_rad = target.rotation.angle_to(&achieved.rotation);
        IkSolution {
            joints_rad,
            achieved,
            position_error_m,
            orientation_error_rad,
            iterations: 0,
            position_reached: position_error_m <= solver.position_tolerance_m,
            orientation_reached: orientation_error_rad <= solver.orientation_tolerance_rad,
            invalid_input,
        }
    }
}

/// The simulated arm and scene.
#[derive(Clone, Debug)]
pub struct SimWorld {
    config: SimConfig,
    kinematics: So101Kinematics,
    joints_rad: So101Joints,
    joint_targets_rad: So101Joints,
    gripper: f64,
    gripper_target: f64,
    ball_center_m: Vector3<f64>,
    ball_state: BallState,
    task_success: bool,
    basket_xy_m: [f64; 2],
    /// Seed of the current scene and the one a reset without a seed uses.
    seed: u64,
    next_seed: u64,
    resets: u64,
    applied_seq: u64,
    enabled: bool,
    /// The instant the state describes, on the clock commands are stamped with (`Command::issue_time_ns`).
    time_ns: i64,
}

impl SimWorld {
    /// A world in its initial state. Fails on an invalid configuration.
    pub fn new(config: SimConfig) -> Result<Self, BridgeError> {
        config.validate()?;
        let joints = clamp_to_limits(&config.initial_joints_rad);
        let mut world = Self {
            kinematics: So101Kinematics::new(),
            joints_rad: joints,
            joint_targets_rad: joints,
            gripper: config.initial_gripper,
            gripper_target: config.initial_gripper,
            ball_center_m: Vector3::zeros(),
            ball_state: BallState::Resting,
            task_success: false,
            basket_xy_m: config.basket_xy_m,
            seed: 0,
            next_seed: config.seed,
            resets: 0,
            applied_seq: 0,
            enabled: true,
            time_ns: 0,
            config,
        };
        world.place_ball(world.config.ball_xy_m);
        Ok(world)
    }

    /// Draws a new scene from `seed` (or the next seed of the sequence): the basket's centre from its area
    /// if one is configured, then the ball's start from its area, where the ball is put at rest. With
    /// `home_arm` the arm is also put at its initial joints with the gripper at its initial opening, at rest
    /// (a teleport: the caller makes sure nobody is driving). Returns the seed used.
    pub fn reset_scene(&mut self, seed: Option<u64>, home_arm: bool) -> u64 {
        let seed = seed.unwrap_or(self.next_seed);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // 53 random bits: every f64 in [0, 1) the generator can give, the same on every platform.
        let mut unit = || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        if let Some(area) = self.config.basket_area_m {
            self.basket_xy_m = area.point_at(unit(), unit());
        }
        let ball_xy_m = self.config.ball_area_m.point_at(unit(), unit());
        self.place_ball(ball_xy_m);
        if home_arm {
            let joints = clamp_to_limits(&self.config.initial_joints_rad);
            self.joints_rad = joints;
            self.joint_targets_rad = joints;
            self.gripper = self.config.initial_gripper;
            self.gripper_target = self.config.initial_gripper;
        }
        self.seed = seed;
        self.next_seed = seed.wrapping_add(1);
        self.resets += 1;
        seed
    }

    /// Puts the ball at rest on the table (or the basket floor) at (x, y).
    fn place_ball(&mut self, [x, y]: [f64; 2]) {
        self.ball_center_m = Vector3::new(x, y, self.ball_floor_z(x, y));
        self.ball_state = BallState::Resting;
        self.task_success = self.in_basket(x, y);
    }

    /// The scene now.
    pub fn scene_state(&self) -> SceneState {
        SceneState {
            seed: self.seed,
            resets: self.resets,
            ball_center_m: self.ball_center_m,
            ball_state: self.ball_state,
            ball_radius_m: self.config.ball_radius_m,
            basket_xy_m: self.basket_xy_m,
            basket_radius_m: self.config.basket_radius_m,
            basket_height_m: self.config.basket_height_m,
            task_success: self.task_success,
            ball_area_m: self.config.ball_area_m,
            basket_area_m: self.config.basket_area_m,
        }
    }

    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The same world with its present at `time_ns` on the caller's clock. Meant for a fresh world: it is at
    /// rest, so no motion is skipped by moving its clock.
    #[must_use]
    pub fn starting_at_ns(mut self, time_ns: i64) -> Self {
        self.time_ns = time_ns;
        self
    }

    /// Advances the world to `time_ns`; a time not after the present changes nothing (the past is already
    /// simulated).
    pub fn advance_to_ns(&mut self, time_ns: i64) {
        if time_ns > self.time_ns {
            self.step((time_ns - self.time_ns) as f64 * 1e-9);
            self.time_ns = time_ns;
        }
    }

    /// Advances the world to the moment `command` takes effect: the time it was issued, but not later than
    /// `horizon_ns` (the caller's present: a command stamped on a clock ahead of the world's takes effect on
    /// arrival instead of waiting) and not before the world's present (a command issued before the world
    /// last advanced takes effect now).
    pub fn advance_to_issue(&mut self, command: &Command, horizon_ns: i64) {
        self.advance_to_ns(command.issue_time_ns.min(horizon_ns));
    }

    /// [`Self::advance_to_issue`], then [`Self::apply_command`]: the command in force from its issue time on.
    pub fn apply_command_at(&mut self, command: &Command, horizon_ns: i64) -> CommandOutcome {
        self.advance_to_issue(command, horizon_ns);
        self.apply_command(command)
    }

    /// Solves IK for the command's target (seeded with the current joint targets so that consecutive
    /// commands stay on one branch) and makes the solution the new joint target.
    pub fn apply_command(&mut self, command: &Command) -> CommandOutcome {
        let Some(request) = self.ik_request() else {
            return CommandOutcome::Disabled;
        };
        let solution = request.solve(command);
        self.apply_solution(command, solution)
    }

    /// What solving a command needs, so a caller can run the IK without holding a lock on the world.
    /// `None` while disabled.
    pub fn ik_request(&self) -> Option<IkRequest> {
        self.enabled.then(|| IkRequest {
            kinematics: self.kinematics.clone(),
            seed: self.joint_targets_rad,
            weights: IkWeights {
                orientation: self.config.ik_orientation_weight,
            },
        })
    }

    /// Makes a solution from [`IkRequest::solve`] the new target (unless the arm was disabled meanwhile or
    /// the command is not finite).
    pub fn apply_solution(&mut self, command: &Command, solution: IkSolution) -> CommandOutcome {
        if !self.enabled {
            return CommandOutcome::Disabled;
        }
        if !command.gripper_target.is_finite() || solution.invalid_input {
            return CommandOutcome::Rejected;
        }
        self.joint_targets_rad = solution.joints_rad;
        self.gripper_target = command.gripper_target.clamp(0.0, 1.0);
        self.applied_seq = command.seq;
        CommandOutcome::Applied(Box::new(solution))
    }

    /// Disabling freezes the arm where it is; commands are ignored until enabled again.
    pub fn set_enabled(&mut self, enabled: bool) {
        if !enabled {
            self.joint_targets_rad = self.joints_rad;
            self.gripper_target = self.gripper;
        }
        self.enabled = enabled;
    }

    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// Advances the world by `dt_s` seconds (ignored unless finite and positive; long steps are split). The
    /// clock of [`Self::time_ns`] does not move: use [`Self::advance_to_ns`] to keep the two together.
    pub fn step(&mut self, dt_s: f64) {
        if !dt_s.is_finite() || dt_s <= 0.0 {
            return;
        }
        let mut remaining = dt_s;
        while remaining > 0.0 {
            let dt = remaining.min(MAX_STEP_S);
            self.substep(dt);
            remaining -= dt;
        }
    }

    fn substep(&mut self, dt_s: f64) {
        // Exact discretisation of a first-order lag: stable for any dt.
        let joint_alpha = 1.0 - (-dt_s / self.config.joint_time_constant_s).exp();
        for (q, target) in self.joints_rad.iter_mut().zip(self.joint_targets_rad) {
            *q += (target - *q) * joint_alpha;
        }
        let previous_gripper = self.gripper;
        let gripper_alpha = 1.0 - (-dt_s / self.config.gripper_time_constant_s).exp();
        self.gripper += (self.gripper_target - self.gripper) * gripper_alpha;

        let poses = self.kinematics.link_poses(&self.joints_rad);
        let tcp = poses.tcp;
        let on_ball = self.gripper_on_ball();
        match self.ball_state {
            BallState::Held { tcp_from_ball } => {
                if self.gripper < on_ball - RELEASE_MARGIN {
                    self.ball_state = BallState::Falling {
                        velocity_m_s: Vector3::zeros(),
                    };
                } else {
                    self.gripper = self.gripper.min(on_ball);
                    self.ball_center_m = (tcp * Point3::from(tcp_from_ball)).coords;
                }
            }
            BallState::Resting | BallState::Falling { .. } => {
                // The fingers reach the ball's width in this step: it is taken if it is between them.
                let closing_onto = previous_gripper < on_ball && self.gripper >= on_ball;
                if closing_onto && self.between_fingers(&tcp, previous_gripper) {
                    self.ball_state = BallState::Held {
                        tcp_from_ball: tcp.rotation.inverse() * (self.ball_center_m - tcp.translation.vector),
                    };
                    self.task_success = false;
                    self.gripper = self.gripper.min(on_ball);
                } else if self.ball_state == BallState::Resting {
                    let wrist = poses.links[4].translation.vector;
                    self.push_ball(&tcp, &wrist);
                }
            }
        }
        if let BallState::Falling { mut velocity_m_s } = self.ball_state {
            velocity_m_s.z -= GRAVITY_M_S2 * dt_s;
            self.ball_center_m += velocity_m_s * dt_s;
            let (x, y) = (self.ball_center_m.x, self.ball_center_m.y);
            let floor_z = self.ball_floor_z(x, y);
            if self.ball_center_m.z <= floor_z {
                self.ball_center_m.z = floor_z;
                self.ball_state = BallState::Resting;
                self.task_success = self.in_basket(x, y);
            } else {
                self.ball_state = BallState::Falling { velocity_m_s };
            }
        }
    }

    /// Gripper position at which the fingers' inner faces touch the ball: where a gripper closed on it stops.
    fn gripper_on_ball(&self) -> f64 {
        1.0 - self.config.ball_radius_m / OPEN_HALF_GAP_M
    }

    /// The ball's centre lies between the fingers of a gripper at `gripper`: within their width and length
    /// (below the palm by at least its radius), between their inner faces, and within the grasp radius of the
    /// tool centre point.
    fn between_fingers(&self, tcp: &Isometry3<f64>, gripper: f64) -> bool {
        let offset = self.ball_center_m - tcp.translation.vector;
        let local = tcp.rotation.inverse() * offset;
        local.x.abs() <= FINGER_HALF_WIDTH_M
            && local.y.abs() <= half_gap_m(gripper)
            && (FINGER_ROOT_M + self.config.ball_radius_m..=FINGER_TIP_M).contains(&local.z)
            && offset.norm() <= self.config.grasp_radius_m
    }

    /// The gripper cannot pass through a ball resting on the table, open or closed: where a finger, the palm or
    /// the wrist overlaps the ball, the ball slides away from it across the table, just far enough to touch.
    /// A ball between open fingers touches none of them and stays. A ball in the basket stays (its wall holds
    /// it), and so does a ball the push would carry over the basket's wall.
    fn push_ball(&mut self, tcp: &Isometry3<f64>, wrist_m: &Vector3<f64>) {
        if self.task_success {
            return;
        }
        let radius_m = self.config.ball_radius_m;
        let solids = gripper_solids(tcp, wrist_m, self.gripper);
        let mut ball = self.ball_center_m;
        for _ in 0..CONTACT_PASSES {
            let mut touched = false;
            for solid in &solids {
                let nearest = solid.nearest_point(&ball);
                let offset = ball - nearest;
                let contact_m = radius_m + solid.radius_m;
                // A hair inside contact counts as touching, so a ball just pushed to touch is left alone.
                if offset.norm() >= contact_m - 1e-9 {
                    continue;
                }
                // Straight down onto the ball: away from the tool axis, else along the fingers' width.
                let direction = horizontal(&offset)
                    .or_else(|| horizontal(&(ball - tcp.translation.vector)))
                    .or_else(|| horizontal(&(tcp.rotation * Vector3::x())))
                    .unwrap_or_else(Vector3::x);
                let reach_m = (contact_m * contact_m - offset.z * offset.z).max(0.0).sqrt();
                ball.x = nearest.x + direction.x * reach_m;
                ball.y = nearest.y + direction.y * reach_m;
                touched = true;
            }
            if !touched {
                break;
            }
        }
        let [bx, by] = self.basket_xy_m;
        if (ball.x - bx).hypot(ball.y - by) <= self.config.basket_radius_m + radius_m {
            return;
        }
        self.ball_center_m = ball;
    }

    /// True if a ball centred at (x, y) fits inside the basket wall.
    fn in_basket(&self, x: f64, y: f64) -> bool {
        let [bx, by] = self.basket_xy_m;
        (x - bx).hypot(y - by) <= self.config.basket_radius_m - self.config.ball_radius_m
    }

    /// Height of the ball centre when resting at (x, y): on the basket floor or on the table.
    fn ball_floor_z(&self, x: f64, y: f64) -> f64 {
        let floor = if self.in_basket(x, y) { BASKET_FLOOR_M } else { 0.0 };
        floor + self.config.ball_radius_m
    }

    pub fn joints_rad(&self) -> So101Joints {
        self.joints_rad
    }

    pub fn joint_targets_rad(&self) -> So101Joints {
        self.joint_targets_rad
    }

    /// `base_from_tcp` of the current joints.
    pub fn tool_pose(&self) -> Isometry3<f64> {
        self.kinematics.forward(&self.joints_rad)
    }

    pub fn gripper_position(&self) -> f64 {
        self.gripper
    }

    pub fn ball_center_m(&self) -> Vector3<f64> {
        self.ball_center_m
    }

    pub fn ball_state(&self) -> BallState {
        self.ball_state
    }

    /// The ball rests in the basket.
    pub fn task_success(&self) -> bool {
        self.task_success
    }

    pub fn applied_seq(&self) -> u64 {
        self.applied_seq
    }

    /// The instant the state describes (see [`Self::advance_to_ns`]).
    pub fn time_ns(&self) -> i64 {
        self.time_ns
    }

    /// The current state as bridge feedback, stamped `capture_time_ns`.
    pub fn feedback(&self, capture_time_ns: i64) -> Feedback {
        Feedback {
            capture_time_ns,
            joint_positions_rad: self.joints_rad.to_vec(),
            robot_from_ee: self.tool_pose(),
            gripper_position: self.gripper,
            applied_seq: self.applied_seq,
            task_success: self.task_success,
        }
    }

    /// What the renderer draws.
    pub fn snapshot(&self) -> SceneSnapshot {
        SceneSnapshot {
            links: self.kinematics.link_poses(&self.joints_rad),
            gripper_position: self.gripper,
            ball_center_m: self.ball_center_m,
            ball_radius_m: self.config.ball_radius_m,
            ball_state: self.ball_state,
            basket_xy_m: self.basket_xy_m,
            basket_radius_m: self.config.basket_radius_m,
            basket_height_m: self.config.basket_height_m,
            task_success: self.task_success,
        }
    }
}

/// Gap between a finger's inner face and the tool axis at gripper position `gripper` (0 open, 1 closed).
pub(crate) fn half_gap_m(gripper: f64) -> f64 {
    OPEN_HALF_GAP_M * (1.0 - gripper.clamp(0.0, 1.0))
}

/// A solid of the gripper: the points within `radius_m` of a rectangle (centre, half extents `half_u_m` along
/// unit `u` and `half_v_m` along unit `v`; a segment when `half_v_m` is 0).
#[derive(Clone, Copy, Debug)]
struct Solid {
    centre_m: Vector3<f64>,
    u: Vector3<f64>,
    half_u_m: f64,
    v: Vector3<f64>,
    half_v_m: f64,
    radius_m: f64,
}

impl Solid {
    /// The rectangle's point nearest `p`.
    fn nearest_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        let d = p - self.centre_m;
        let s = d.dot(&self.u).clamp(-self.half_u_m, self.half_u_m);
        let t = d.dot(&self.v).clamp(-self.half_v_m, self.half_v_m);
        self.centre_m + self.u * s + self.v * t
    }

    /// Distance from `p` to the solid's surface (negative inside).
    #[cfg(test)]
    fn distance_m(&self, p: &Vector3<f64>) -> f64 {
        (p - self.nearest_point(p)).norm() - self.radius_m
    }
}

/// The gripper's solids in the base frame: the two fingers, the palm across their roots, and the wrist from
/// `wrist_m` (the wrist roll joint) to the palm.
fn gripper_solids(tcp: &Isometry3<f64>, wrist_m: &Vector3<f64>, gripper: f64) -> [Solid; 4] {
    let width = tcp.rotation * Vector3::x();
    let across = tcp.rotation * Vector3::y();
    let approach = tcp.rotation * Vector3::z();
    let origin = tcp.translation.vector;
    let finger_offset_m = half_gap_m(gripper) + FINGER_HALF_THICKNESS_M;
    let finger = |side: f64| Solid {
        centre_m: origin
            + approach * (0.5 * (FINGER_TIP_M + FINGER_ROOT_M))
            + across * (side * finger_offset_m),
        u: approach,
        half_u_m: 0.5 * (FINGER_TIP_M - FINGER_ROOT_M),
        v: width,
        half_v_m: FINGER_HALF_WIDTH_M,
        radius_m: FINGER_HALF_THICKNESS_M,
    };
    let palm_centre = origin + approach * (FINGER_ROOT_M - PALM_HALF_THICKNESS_M);
    let wrist_end = origin + approach * (FINGER_ROOT_M - 2.0 * PALM_HALF_THICKNESS_M);
    let wrist_axis = wrist_end - wrist_m;
    let wrist_length_m = wrist_axis.norm();
    let wrist = Solid {
        centre_m: 0.5 * (wrist_end + wrist_m),
        u: wrist_axis.try_normalize(1e-9).unwrap_or(approach),
        half_u_m: 0.5 * wrist_length_m,
        v: width,
        half_v_m: 0.0,
        radius_m: WRIST_RADIUS_M,
    };
    [
        finger(-1.0),
        finger(1.0),
        Solid {
            centre_m: palm_centre,
            u: across,
            half_u_m: finger_offset_m,
            v: width,
            half_v_m: FINGER_HALF_WIDTH_M,
            radius_m: PALM_HALF_THICKNESS_M,
        },
        wrist,
    ]
}

/// The horizontal part of `v`, as a unit vector; `None` if it has (almost) none.
fn horizontal(v: &Vector3<f64>) -> Option<Vector3<f64>> {
    Vector3::new(v.x, v.y, 0.0).try_normalize(1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::TableArea;
    use nalgebra::{Translation3, UnitQuaternion};
    use phone2act_core::kinematics::So101Kinematics;

    fn command(seq: u64, target: Isometry3<f64>, gripper: f64) -> Command {
        Command {
            seq,
            robot_from_target: target,
            gripper_target: gripper,
            issue_time_ns: 0,
            joint_targets_rad: None,
        }
    }

    fn world() -> SimWorld {
        SimWorld::new(SimConfig::default()).unwrap()
    }

    fn run(world: &mut SimWorld, seconds: f64) {
        for _ in 0..(seconds * 200.0).round() as usize {
            world.step(0.005);
        }
    }

    #[test]
    fn home_pose_is_inside_the_teleop_workspace() {
        let p = world().tool_pose().translation.vector;
        assert!(
            (0.10..=0.40).contains(&p.x) && (-0.25..=0.25).contains(&p.y) && (0.02..=0.35).contains(&p.z),
            "{p:?}"
        );
        // Above the table with room to move down toward the ball.
        assert!(p.z > 0.08, "{p:?}");
    }

    #[test]
    fn joints_follow_a_first_order_lag() {
        let mut w = world();
        let start = w.joints_rad();
        let mut target = w.tool_pose();
        target.translation.vector += Vector3::new(0.03, 0.04, -0.03);
        let CommandOutcome::Applied(solution) = w.apply_command(&command(1, target, 0.0)) else {
            panic!()
        };
        let goal = solution.joints_rad;
        // After one time constant a first-order lag has covered 1 - 1/e of every joint's distance.
        run(&mut w, 0.05);
        for i in 0..5 {
            if (goal[i] - start[i]).abs() > 1e-3 {
                let covered = (w.joints_rad()[i] - start[i]) / (goal[i] - start[i]);
                assert!(
                    (covered - (1.0 - (-1.0f64).exp())).abs() < 0.01,
                    "joint {i}: {covered}"
                );
            }
        }
        run(&mut w, 0.5);
        assert!((w.tool_pose().translation.vector - target.translation.vector).norm() < 1e-3);
        assert_eq!(w.applied_seq(), 1);
    }

    #[test]
    fn step_is_independent_of_how_time_is_sliced() {
        let mut a = world();
        let mut b = world();
        let mut target = a.tool_pose();
        target.translation.vector += Vector3::new(-0.05, 0.02, 0.03);
        a.apply_command(&command(1, target, 1.0));
        b.apply_command(&command(1, target, 1.0));
        for _ in 0..40 {
            a.step(0.0025);
        }
        b.step(0.1);
        for (qa, qb) in a.joints_rad().iter().zip(b.joints_rad()) {
            assert!((qa - qb).abs() < 1e-9, "{qa} vs {qb}");
        }
        assert!((a.gripper_position() - b.gripper_position()).abs() < 1e-9);
    }

    /// The arm's path is a function of the command history and time: commands handed over in one batch after
    /// a stall give the same state as commands handed over at 200 Hz ticks, because each is put in force at
    /// the time it was issued, not when the world hears of it.
    #[test]
    fn commands_take_effect_at_their_issue_time_however_late_they_are_handed_over() {
        let t0_ns = 1_000_000_000;
        let start = world().tool_pose();
        let commands: Vec<Command> = (1..=8u32)
            .map(|k| {
                let mut target = start;
                target.translation.vector += f64::from(k) * Vector3::new(0.005, -0.004, 0.003);
                Command {
                    seq: u64::from(k),
                    robot_from_target: target,
                    gripper_target: if k > 4 { 1.0 } else { 0.0 },
                    issue_time_ns: t0_ns + i64::from(k) * 20_000_000,
                    joint_targets_rad: None,
                }
            })
            .collect();
        let end_ns = t0_ns + 300_000_000;
        let mut stalled = world().starting_at_ns(t0_ns);
        for c in &commands {
            stalled.apply_command_at(c, end_ns);
        }
        stalled.advance_to_ns(end_ns);
        let mut ticked = world().starting_at_ns(t0_ns);
        let mut pending = commands.iter().peekable();
        for tick in 1..=60 {
            let now_ns = t0_ns + tick * 5_000_000;
            while let Some(c) = pending.next_if(|c| c.issue_time_ns <= now_ns) {
                ticked.apply_command_at(c, now_ns);
            }
            ticked.advance_to_ns(now_ns);
        }
        assert_eq!((stalled.time_ns(), ticked.time_ns()), (end_ns, end_ns));
        assert_eq!((stalled.applied_seq(), ticked.applied_seq()), (8, 8));
        // Exact discretisation: slicing changes only rounding.
        for (a, b) in stalled.joints_rad().iter().zip(ticked.joints_rad()) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        assert!((stalled.gripper_position() - ticked.gripper_position()).abs() < 1e-12);
        // Applied only at the end, the same commands leave the arm elsewhere: the test can tell.
        let mut late = world().starting_at_ns(t0_ns);
        late.advance_to_ns(end_ns - 1);
        for c in &commands {
            late.apply_command_at(c, end_ns);
        }
        late.advance_to_ns(end_ns);
        let moved = (late.tool_pose().translation.vector - stalled.tool_pose().translation.vector).norm();
        assert!(moved > 1e-3, "{moved} m");
    }

    #[test]
    fn a_command_takes_effect_no_earlier_than_the_present_and_no_later_than_the_horizon() {
        let mut w = world().starting_at_ns(1_000);
        let mut c = command(1, w.tool_pose(), 1.0);
        // Stamped before the world's present (or unstamped): in force now.
        w.apply_command_at(&c, 5_000);
        assert_eq!(w.time_ns(), 1_000);
        // Stamped on a clock ahead of the caller's: in force at the caller's present, not later.
        c.issue_time_ns = 1_000_000_000;
        w.apply_command_at(&c, 5_000);
        assert_eq!(w.time_ns(), 5_000);
        w.advance_to_ns(2_000);
        assert_eq!(w.time_ns(), 5_000, "time never runs back");
    }

    #[test]
    fn non_finite_commands_change_nothing() {
        let mut w = world();
        let before = w.joint_targets_rad();
        let bad = Isometry3::from_parts(Translation3::new(f64::NAN, 0.0, 0.1), UnitQuaternion::identity());
        assert_eq!(w.apply_command(&command(5, bad, 0.0)), CommandOutcome::Rejected);
        assert_eq!(
            w.apply_command(&command(6, w.tool_pose(), f64::NAN)),
            CommandOutcome::Rejected
        );
        assert_eq!(w.joint_targets_rad().map(f64::to_bits), before.map(f64::to_bits));
        assert_eq!(w.applied_seq(), 0);
        w.step(f64::NAN);
        w.step(-1.0);
        assert!(w.joints_rad().iter().all(|q| q.is_finite()));
    }

    #[test]
    fn disabled_arm_holds() {
        let mut w = world();
        let start = w.tool_pose();
        w.set_enabled(false);
        let mut target = start;
        target.translation.vector.z -= 0.05;
        assert_eq!(
            w.apply_command(&command(1, target, 1.0)),
            CommandOutcome::Disabled
        );
        run(&mut w, 0.3);
        assert!((w.tool_pose().translation.vector - start.translation.vector).norm() < 1e-9);
    }

    /// The tool pointing straight down at (x, y, z).
    fn down_at(x: f64, y: f64, z: f64) -> Isometry3<f64> {
        let zero = So101Kinematics::new().forward(&[0.0; 5]).rotation;
        let down = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2) * zero;
        Isometry3::from_parts(Translation3::new(x, y, z), down)
    }

    #[test]
    fn deterministic_pick_and_place() {
        let mut w = world();
        let [bx, by] = w.config().ball_xy_m;
        let [kx, ky] = w.config().basket_xy_m;
        let script = [
            (down_at(bx, by, 0.10), 0.0),
            (down_at(bx, by, 0.02), 0.0),
            (down_at(bx, by, 0.02), 1.0),
            (down_at(bx, by, 0.12), 1.0),
            (down_at(kx, ky, 0.13), 1.0),
        ];
        for (seq, (target, gripper)) in script.into_iter().enumerate() {
            // Re-sent every 20 ms like a teleop stream, so IK keeps refining from the current targets.
            for _ in 0..25 {
                w.apply_command(&command(seq as u64 + 1, target, gripper));
                run(&mut w, 0.02);
            }
        }
        assert!(matches!(w.ball_state(), BallState::Held { .. }));
        let carried = w.ball_center_m();
        assert!((carried.x - kx).hypot(carried.y - ky) < 0.03, "{carried:?}");
        assert!(!w.task_success());
        w.apply_command(&command(9, down_at(kx, ky, 0.13), 0.0));
        // Gripper opens (tens of ms), then the ball falls about 0.1 m (about 0.15 s).
        run(&mut w, 0.15);
        assert!(
            matches!(w.ball_state(), BallState::Falling { .. }),
            "{:?}",
            w.ball_state()
        );
        run(&mut w, 0.5);
        assert_eq!(w.ball_state(), BallState::Resting);
        assert!(w.task_success());
        assert!((w.ball_center_m().z - (BASKET_FLOOR_M + w.config().ball_radius_m)).abs() < 1e-12);
        // A reset puts it back on the table, inside the ball's area, and clears success.
        assert_eq!(w.reset_scene(Some(3), false), 3);
        assert!(!w.task_success());
        assert_eq!(w.ball_state(), BallState::Resting);
        let [x, y] = [w.ball_center_m().x, w.ball_center_m().y];
        assert!(w.config().ball_area_m.distance_to([x, y]) < 1e-12);
    }

    #[test]
    fn closing_away_from_the_ball_grasps_nothing_and_a_released_ball_lands() {
        let mut w = world();
        w.apply_command(&command(1, w.tool_pose(), 1.0));
        run(&mut w, 0.5);
        assert_eq!(w.ball_state(), BallState::Resting);
        assert!(w.gripper_position() > 0.95, "closes fully on nothing");
        // A ball dropped from height over the table lands on the table, not in the basket.
        w.ball_state = BallState::Falling {
            velocity_m_s: Vector3::zeros(),
        };
        w.ball_center_m = Vector3::new(0.3, -0.15, 0.2);
        run(&mut w, 0.5);
        assert_eq!(w.ball_state(), BallState::Resting);
        assert!((w.ball_center_m().z - w.config().ball_radius_m).abs() < 1e-12);
        assert!(!w.task_success());
    }

    #[test]
    fn a_closed_gripper_pushes_a_resting_ball_instead_of_passing_through_it() {
        let mut w = world();
        let [bx, by] = w.config().ball_xy_m;
        let radius = w.config().ball_radius_m;
        // Closed, at the ball's height, 8 cm to its -y side, then swept through where the ball is to 4 cm
        // past it.
        for (seq, y) in [(1, by - 0.08), (2, by - 0.04), (3, by), (4, by + 0.04)] {
            for _ in 0..25 {
                w.apply_command(&command(seq, down_at(bx, y, radius), 1.0));
                run(&mut w, 0.02);
                let overlap = overlap_m(&w);
                assert!(overlap < 1e-6, "the gripper is {overlap} m inside the ball");
            }
        }
        assert_eq!(w.ball_state(), BallState::Resting);
        let ball = w.ball_center_m();
        assert!(ball.y > by + 0.04, "pushed ahead of the jaws along +y: {ball:?}");
        // The jaws' path between targets is the joints' lag, not a straight line: the ball goes where they go.
        assert!((ball.x - bx).abs() < 0.03, "{ball:?}");
        assert!((ball.z - radius).abs() < 1e-12, "still on the table: {ball:?}");
        assert!(!w.task_success());
        // Opening does not take the ball: it was never between the jaws.
        w.apply_command(&command(5, w.tool_pose(), 0.0));
        run(&mut w, 0.3);
        assert_eq!(w.ball_state(), BallState::Resting);
    }

    /// How deep the gripper's deepest solid is inside the ball (negative: clear of it).
    fn overlap_m(w: &SimWorld) -> f64 {
        let poses = w.kinematics.link_poses(&w.joints_rad);
        let wrist = poses.links[4].translation.vector;
        gripper_solids(&poses.tcp, &wrist, w.gripper_position())
            .iter()
            .map(|s| w.config().ball_radius_m - s.distance_m(&w.ball_center_m()))
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Streams `target` for `seconds` like a teleop stream (re-sent every 20 ms), checking after every 20 ms
    /// that the gripper never sinks into a resting ball.
    fn drive(w: &mut SimWorld, seq: u64, target: Isometry3<f64>, gripper: f64, seconds: f64) {
        for _ in 0..(seconds / 0.02).round() as usize {
            w.apply_command(&command(seq, target, gripper));
            run(w, 0.02);
            if w.ball_state() == BallState::Resting {
                let overlap = overlap_m(w);
                assert!(overlap < 1e-6, "the gripper is {overlap} m inside the ball");
            }
        }
    }

    /// The tool's closing direction (its y axis) in the base frame for the straight-down pose.
    fn across(w: &SimWorld, x: f64, y: f64) -> Vector3<f64> {
        let _ = w;
        down_at(x, y, 0.1).rotation * Vector3::y()
    }

    #[test]
    fn an_open_gripper_descending_off_centre_pushes_the_ball_aside() {
        let mut w = world();
        let ball = w.ball_center_m();
        let radius = w.config().ball_radius_m;
        let across = across(&w, ball.x, ball.y);
        // The tool axis 4.5 cm from the ball's centre along the closing direction: the finger on that side
        // (its middle 4 cm out) comes down on the ball's top, just inside the ball's centre.
        let aside = ball - across * 0.045;
        drive(&mut w, 1, down_at(aside.x, aside.y, 0.10), 0.0, 0.6);
        assert_eq!(w.ball_center_m(), ball, "nothing touched it from above");
        drive(&mut w, 1, down_at(aside.x, aside.y, radius), 0.0, 0.8);
        let moved = w.ball_center_m() - ball;
        assert_eq!(w.ball_state(), BallState::Resting);
        assert!(
            moved.dot(&across) > 0.015,
            "pushed outward, away from the gripper: {moved:?}"
        );
        assert!((w.ball_center_m().z - radius).abs() < 1e-12, "still on the table");
        // Closing there takes nothing: the ball is outside the fingers.
        drive(&mut w, 2, down_at(aside.x, aside.y, radius), 1.0, 0.5);
        assert_eq!(w.ball_state(), BallState::Resting);
        assert!(w.gripper_position() > 0.95, "closes fully on nothing");
    }

    #[test]
    fn an_open_gripper_descending_centred_encloses_the_ball_and_closing_grasps_it() {
        let mut w = world();
        let ball = w.ball_center_m();
        let radius = w.config().ball_radius_m;
        // 8 mm off along the closing direction: still within the gap (1.4 cm to spare on each side).
        let near = ball - across(&w, ball.x, ball.y) * 0.008;
        drive(&mut w, 1, down_at(near.x, near.y, 0.10), 0.0, 0.6);
        drive(&mut w, 1, down_at(near.x, near.y, radius), 0.0, 0.8);
        assert_eq!(w.ball_center_m(), ball, "the open fingers pass either side of it");
        assert!(w.between_fingers(&w.tool_pose(), w.gripper_position()));
        drive(&mut w, 2, down_at(near.x, near.y, radius), 1.0, 0.5);
        assert!(
            matches!(w.ball_state(), BallState::Held { .. }),
            "{:?}",
            w.ball_state()
        );
        // Stopped on the ball's width; the closing finger centred the ball between the two.
        assert!((w.gripper_position() - w.gripper_on_ball()).abs() < 1e-9);
        let local = w.tool_pose().rotation.inverse() * (w.ball_center_m() - w.tool_pose().translation.vector);
        assert!(local.y.abs() < 1e-3, "{local:?}");
        drive(&mut w, 3, down_at(near.x, near.y, 0.12), 1.0, 0.5);
        assert!(
            w.ball_center_m().z > 0.09,
            "lifted with the tool: {:?}",
            w.ball_center_m()
        );
    }

    #[test]
    fn closing_beside_the_ball_squeezes_it_out_and_takes_nothing() {
        let mut w = world();
        let ball = w.ball_center_m();
        let radius = w.config().ball_radius_m;
        // 2 cm off along the fingers' width: within the grasp radius of the tool centre point, clear of the
        // open fingers' edges, but not between them (they are 2.4 cm wide).
        let width = down_at(ball.x, ball.y, 0.1).rotation * Vector3::x();
        let beside = ball - width * 0.02;
        drive(&mut w, 1, down_at(beside.x, beside.y, 0.10), 0.0, 0.6);
        drive(&mut w, 1, down_at(beside.x, beside.y, radius), 0.0, 0.8);
        assert_eq!(w.ball_center_m(), ball, "the open fingers pass beside it");
        assert!((w.ball_center_m() - w.tool_pose().translation.vector).norm() < w.config().grasp_radius_m);
        drive(&mut w, 2, down_at(beside.x, beside.y, radius), 1.0, 0.5);
        assert_eq!(
            w.ball_state(),
            BallState::Resting,
            "not between the fingers: not taken"
        );
        let moved = w.ball_center_m() - ball;
        assert!(
            moved.dot(&width) > 0.003,
            "squeezed out along the width: {moved:?}"
        );
    }

    #[test]
    fn the_palm_descending_onto_the_ball_pushes_it() {
        let mut w = world();
        let ball = w.ball_center_m();
        let radius = w.config().ball_radius_m;
        // Centred between the open fingers, then on down: the palm (5.5 cm above the tool centre) reaches the
        // ball's top once the tool centre is below the table's surface (the kinematic arm passes through the
        // table; only the ball is a solid).
        drive(&mut w, 1, down_at(ball.x, ball.y, 0.10), 0.0, 0.6);
        drive(&mut w, 1, down_at(ball.x, ball.y, radius), 0.0, 0.6);
        assert_eq!(w.ball_center_m(), ball);
        drive(&mut w, 2, down_at(ball.x, ball.y, -0.03), 0.0, 1.0);
        let tcp = w.tool_pose().translation.vector;
        assert!(tcp.z < -0.02, "{tcp:?}");
        let moved = (w.ball_center_m() - ball).norm();
        assert!(moved > 0.02, "squeezed out from under the palm: {moved} m");
        assert_eq!(w.ball_state(), BallState::Resting);
        // Out of the fingers' gap: closing grasps nothing.
        drive(&mut w, 3, down_at(ball.x, ball.y, -0.03), 1.0, 0.5);
        assert_eq!(w.ball_state(), BallState::Resting);
    }

    #[test]
    fn a_seed_draws_the_same_scene_and_home_teleports_the_arm() {
        let config = SimConfig {
            basket_area_m: Some(TableArea {
                x_min_m: 0.18,
                x_max_m: 0.26,
                y_min_m: 0.10,
                y_max_m: 0.16,
            }),
            seed: 40,
            ..SimConfig::default()
        };
        let mut a = SimWorld::new(config.clone()).unwrap();
        let mut b = SimWorld::new(config).unwrap();
        // Moved and holding nothing: a reset without home leaves the arm alone.
        let mut target = a.tool_pose();
        target.translation.vector.z -= 0.04;
        a.apply_command(&command(1, target, 1.0));
        run(&mut a, 0.5);
        let moved = a.joints_rad();
        assert_eq!(
            a.reset_scene(None, false),
            40,
            "the first unseeded reset uses the configured seed"
        );
        assert_eq!(a.joints_rad().map(f64::to_bits), moved.map(f64::to_bits));
        assert_eq!(b.reset_scene(Some(40), false), 40);
        let (sa, sb) = (a.scene_state(), b.scene_state());
        assert_eq!(
            sa.ball_center_m.map(f64::to_bits),
            sb.ball_center_m.map(f64::to_bits)
        );
        assert_eq!(sa.basket_xy_m.map(f64::to_bits), sb.basket_xy_m.map(f64::to_bits));
        assert_eq!((sa.seed, sa.resets), (40, 1));
        assert_eq!(a.reset_scene(None, false), 41);
        assert_ne!(a.scene_state().ball_center_m, sa.ball_center_m);
        assert_ne!(
            a.scene_state().basket_xy_m.map(f64::to_bits),
            sa.basket_xy_m.map(f64::to_bits)
        );
        // Home: the initial joints and gripper, at rest (targets equal), whatever was commanded before.
        a.reset_scene(Some(7), true);
        let initial = a.config().initial_joints_rad.map(f64::to_bits);
        assert_eq!(a.joints_rad().map(f64::to_bits), initial);
        assert_eq!(a.joint_targets_rad().map(f64::to_bits), initial);
        assert_eq!(
            a.gripper_position().to_bits(),
            a.config().initial_gripper.to_bits()
        );
        run(&mut a, 0.2);
        assert_eq!(a.joints_rad().map(f64::to_bits), initial, "nothing pulls it away");
    }
}
