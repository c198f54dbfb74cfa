//! The joint rate limiter: the last stage before a bridge. Whatever the inverse kinematics asks for, the joints
//! handed to the robot move at most `max_velocity_rad_s[j] · dt` per command, `dt` being the time between
//! the commands' issue times (an argument: the core reads no clock).
//!
//! A step that is too long is shortened by one common factor for every joint rather than joint by joint: the
//! arm then still moves along the straight joint-space line toward the solution, so the tool follows the
//! inverse kinematics' path instead of a distorted one (a per-joint clamp lets the unclamped joints arrive
//! early, which swings the tool off the target's position). Both ends of the line lie inside the joint
//! ranges, so every point of it does too.

use crate::config::ConfigError;

/// The longest time one step is allowed the motion of, s: one period of a 50 Hz control loop (a phone's
/// sample rate). A command after a pause (the arm idle, a thread stalled) would otherwise carry the whole
/// pause's worth of motion at once, a jump the robot executes as fast as it can; capped, the step is one
/// period's and the rest follows at the arm's tick rate, since a shortened step leaves the stage behind.
pub const MAX_STEP_S: f64 = 0.02;

/// A rate limiter over one arm's joints (the gripper is not one of them).
#[derive(Debug, Clone, PartialEq)]
pub struct JointRateLimiter {
    max_velocity_rad_s: Vec<f64>,
    last_rad: Option<Vec<f64>>,
    last_time_s: f64,
    max_step_s: f64,
    /// Largest acceleration of each joint, rad/s² (infinite: not limited); `None` when no joint has one.
    max_acceleration_rad_s2: Option<Vec<f64>>,
    /// Velocity of each joint over the last step, rad/s (zero after a reset).
    velocity_rad_s: Vec<f64>,
}

/// What one limited command is.
#[derive(Debug, Clone, PartialEq)]
pub struct LimitedStep {
    /// The joints to hand to the bridge.
    pub joints_rad: Vec<f64>,
    /// Fraction of the asked step taken (1 = all of it).
    pub scale: f64,
    /// True if the limit shortened the step.
    pub limited: bool,
}

impl JointRateLimiter {
    /// A limiter for joints with these largest speeds; refuses a speed that is not finite and positive.
    pub fn new(max_velocity_rad_s: Vec<f64>) -> Result<Self, ConfigError> {
        for &v in &max_velocity_rad_s {
            if !(v.is_finite() && v > 0.0) {
                return Err(ConfigError::NotPositive {
                    name: "max_velocity_rad_s",
                    value: v,
                });
            }
        }
        Ok(Self {
            max_velocity_rad_s,
            last_rad: None,
            last_time_s: f64::NEG_INFINITY,
            max_step_s: MAX_STEP_S,
            max_acceleration_rad_s2: None,
            velocity_rad_s: Vec::new(),
        })
    }

    /// The same limiter with acceleration limits (rad/s², one per joint; infinite for a joint without one).
    /// Refuses a list of another length and a value that is not positive.
    pub fn with_max_acceleration_rad_s2(
        mut self,
        max_acceleration_rad_s2: Vec<f64>,
    ) -> Result<Self, ConfigError> {
        if max_acceleration_rad_s2.len() != self.max_velocity_rad_s.len() {
            return Err(ConfigError::WrongLength {
                name: "max_acceleration_rad_s2",
                expected: self.max_velocity_rad_s.len(),
                got: max_acceleration_rad_s2.len(),
            });
        }
        if let Some(&a) = max_acceleration_rad_s2.iter().find(|a| a.is_nan() || **a <= 0.0) {
            return Err(ConfigError::NotPositive {
                name: "max_acceleration_rad_s2",
                value: a,
            });
        }
        self.max_acceleration_rad_s2 = max_acceleration_rad_s2
            .iter()
            .any(|a| a.is_finite())
            .then_some(max_acceleration_rad_s2);
        Ok(self)
    }

    /// The acceleration limits in force, if any joint has one.
    pub fn max_acceleration_rad_s2(&self) -> Option<&[f64]> {
        self.max_acceleration_rad_s2.as_deref()
    }

    /// Forgets the start: the next step is taken as the new start (see [`Self::step`]).
    pub fn forget(&mut self) {
        self.last_rad = None;
        self.velocity_rad_s.clear();
    }

    /// Replaces the last joints with `joints_rad` (the same width), stopping every joint that changed: for a
    /// joint held at a hard stop (its range) after a step.
    pub fn stop_at(&mut self, joints_rad: &[f64]) {
        if let Some(last) = self.last_rad.as_mut().filter(|l| l.len() == joints_rad.len()) {
            for ((q, new), v) in last
                .iter_mut()
                .zip(joints_rad)
                .zip(self.velocity_rad_s.iter_mut())
            {
                if q.to_bits() != new.to_bits() {
                    *q = *new;
                    *v = 0.0;
                }
            }
        }
    }

    /// The same limiter with another longest step time ([`MAX_STEP_S`] by default), s.
    #[must_use]
    pub fn with_max_step_s(mut self, max_step_s: f64) -> Self {
        self.max_step_s = max_step_s;
        self
    }

    /// The longest time one step is allowed the motion of, s (see [`MAX_STEP_S`]).
    pub fn max_step_s(&self) -> f64 {
        self.max_step_s
    }

    /// The largest speed of each joint.
    pub fn max_velocity_rad_s(&self) -> &[f64] {
        &self.max_velocity_rad_s
    }

    /// Starts from `joints_rad` (the measured joints) at `time_s`: the next step is limited from there.
    /// The arm is taken to be at rest there.
    pub fn reset(&mut self, joints_rad: &[f64], time_s: f64) {
        self.last_rad = Some(joints_rad.to_vec());
        self.last_time_s = time_s;
        self.velocity_rad_s = vec![0.0; joints_rad.len()];
    }

    /// The joints last handed out (or reset to).
    pub fn last(&self) -> Option<&[f64]> {
        self.last_rad.as_deref()
    }

    /// Time of the last step (or reset).
    pub fn last_time_s(&self) -> f64 {
        self.last_time_s
    }

    /// Seconds of motion a step at `time_s` is allowed: the time since the last step, at most the longest
    /// step time ([`MAX_STEP_S`]); 0 when time did not move on (a second command in the same instant gets no
    /// new motion) or is not a number.
    pub fn elapsed_s(&self, time_s: f64) -> f64 {
        let dt = time_s - self.last_time_s;
        if dt > 0.0 { dt.min(self.max_step_s) } else { 0.0 }
    }

    /// The fraction of the step to `desired_rad` that [`Self::step`] would take at `time_s` (1 = all of it),
    /// without taking it. 1 without a start.
    pub fn scale(&self, desired_rad: &[f64], time_s: f64) -> f64 {
        match self.last_rad.as_deref() {
            Some(last) => self.scale_of(last, desired_rad, self.elapsed_s(time_s)),
            None => 1.0,
        }
    }

    fn scale_of(&self, last: &[f64], desired_rad: &[f64], dt: f64) -> f64 {
        if !desired_rad.iter().all(|q| q.is_finite()) {
            return 0.0;
        }
        let mut scale: f64 = 1.0;
        for ((q, q_last), v) in desired_rad.iter().zip(last).zip(&self.max_velocity_rad_s) {
            let step = (q - q_last).abs();
            let allowed = v * dt;
            if step > allowed {
                scale = scale.min(allowed / step);
            }
        }
        scale
    }

    /// The joints to send for `desired_rad` at `time_s`. Without a start (never [`Self::reset`]) or with a
    /// desired vector of another width, the desired joints are taken as the start: there is nothing to limit
    /// from. A desired vector with a non-finite value holds the last joints.
    pub fn step(&mut self, desired_rad: &[f64], time_s: f64) -> LimitedStep {
        let dt = self.elapsed_s(time_s);
        self.last_time_s = self.last_time_s.max(time_s);
        let last = match self.last_rad.as_deref() {
            Some(last) if last.len() == desired_rad.len() && last.len() == self.max_velocity_rad_s.len() => {
                last
            }
            _ => {
                self.last_rad = Some(desired_rad.to_vec());
                self.velocity_rad_s = vec![0.0; desired_rad.len()];
                return LimitedStep {
                    joints_rad: desired_rad.to_vec(),
                    scale: 1.0,
                    limited: false,
                };
            }
        };
        let scale = self.scale_of(last, desired_rad, dt);
        if let Some(accelerations) = self.max_acceleration_rad_s2.as_deref()
            && scale > 0.0
            && dt > 0.0
        {
            let joints_rad = profiled(
                last,
                desired_rad,
                &self.velocity_rad_s,
                &self.max_velocity_rad_s,
                accelerations,
                dt,
            );
            let limited = joints_rad != desired_rad;
            let (moved, asked) = joints_rad
                .iter()
                .zip(desired_rad)
                .zip(last)
                .fold((0.0f64, 0.0f64), |(m, a), ((q, d), l)| {
                    (m.max((q - l).abs()), a.max((d - l).abs()))
                });
            // A joint that landed on its target stops there (see `profiled`).
            self.velocity_rad_s = joints_rad
                .iter()
                .zip(last)
                .zip(desired_rad)
                .map(|((q, l), d)| {
                    if q.to_bits() == d.to_bits() {
                        0.0
                    } else {
                        (q - l) / dt
                    }
                })
                .collect();
            self.last_rad = Some(joints_rad.clone());
            return LimitedStep {
                joints_rad,
                scale: if asked > 0.0 { moved / asked } else { 1.0 },
                limited,
            };
        }
        // No motion at all (no time passed, or a non-finite request) holds the last joints exactly; a step that
        // fits is taken exactly (`last + (q - last)` can differ from `q` in the last bit), so joint targets that
        // need no limiting reach the bridge as asked.
        let joints_rad: Vec<f64> = if scale <= 0.0 {
            last.to_vec()
        } else if scale < 1.0 {
            desired_rad
                .iter()
                .zip(last)
                .map(|(q, q_last)| q_last + (q - q_last) * scale)
                .collect()
        } else {
            desired_rad.to_vec()
        };
        // No time, no motion: the velocity of the last step stands (a second command in the same instant
        // neither stops nor starts anything).
        if dt > 0.0 {
            self.velocity_rad_s = joints_rad.iter().zip(last).map(|(q, l)| (q - l) / dt).collect();
        }
        self.last_rad = Some(joints_rad.clone());
        LimitedStep {
            joints_rad,
            scale,
            limited: scale < 1.0,
        }
    }
}

/// One step of each joint toward `desired` under speed and acceleration limits, each joint on its own: the
/// velocity changes by at most `a·dt` from the last step's, never exceeds the speed limit, and never exceeds
/// what still stops at the desired joint with deceleration `a` (`v·dt/2 + v²/(2a) ≤ distance`, the discrete
/// form of `v ≤ √(2·a·distance)`), so a joint driven to a target that stays put arrives without overshoot. A
/// joint that can land on its target in this step lands exactly. `dt > 0`.
fn profiled(
    last: &[f64],
    desired: &[f64],
    velocity: &[f64],
    v_max: &[f64],
    a_max: &[f64],
    dt: f64,
) -> Vec<f64> {
    last.iter()
        .zip(desired)
        .zip(velocity.iter().chain(std::iter::repeat(&0.0)))
        .zip(v_max.iter().zip(a_max))
        .map(|(((&q, &target), &v_prev), (&v_limit, &a))| {
            let distance = (target - q).abs();
            let stoppable = if a.is_finite() {
                a * (-0.5 * dt + (0.25 * dt * dt + 2.0 * distance / a).sqrt())
            } else {
                f64::INFINITY
            };
            let toward = (target - q).signum();
            let goal = toward * v_limit.min(distance / dt).min(stoppable);
            let v = goal
                .clamp(v_prev - a * dt, v_prev + a * dt)
                .clamp(-v_limit, v_limit);
            // Landing on the target, or a step that would pass it (the braking curve sampled at this step's time
            // can sit a rounding error below the last step's speed): the target exactly, and the joint stops
            // there, so it holds its value bit for bit and never passes a target that stays put. A joint still
            // moving when its target is where it already is (the target came back to it) brakes at the limit.
            if distance > 0.0 && v * toward * dt >= distance {
                target
            } else {
                q + v * dt
            }
        })
        .collect()
}

/// Speeds are measured over at least this long (s): feedback stamped on arrival jitters by milliseconds, which
/// over one 10 ms sample would read as a speed several times the true one.
pub const SPEED_WINDOW_S: f64 = 0.1;

/// A measured speed counts as over its limit above this multiple of it: the measurement's own error (a few
/// milliseconds of stamp jitter over the window) stays below it.
pub const OVERSPEED_MARGIN: f64 = 1.2;

/// A joint measured moving faster than its limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Overspeed {
    /// Index of the joint, base to tool.
    pub joint: usize,
    /// Its measured speed over the window, rad/s.
    pub speed_rad_s: f64,
    /// Its limit, rad/s.
    pub limit_rad_s: f64,
}

/// Watches measured joints for speeds above their limits: for a robot whose joints the server does not command
/// (a remote bridge solves its own), the limits can only be checked, not enforced. Pure: times are arguments.
#[derive(Debug, Clone, PartialEq)]
pub struct JointSpeedWatch {
    max_velocity_rad_s: Vec<f64>,
    /// The sample speeds are measured from: the newest one at least [`SPEED_WINDOW_S`] older than the last.
    anchor: Option<(Vec<f64>, f64)>,
    /// Samples after the anchor, oldest first (bounded by the window: one replaces the anchor once old enough).
    recent: std::collections::VecDeque<(Vec<f64>, f64)>,
    /// Samples that measured a joint over its limit.
    pub overspeeds: u64,
}

impl JointSpeedWatch {
    /// A watch over joints with these largest speeds; refuses a speed that is not finite and positive.
    pub fn new(max_velocity_rad_s: Vec<f64>) -> Result<Self, ConfigError> {
        JointRateLimiter::new(max_velocity_rad_s.clone())?;
        Ok(Self {
            max_velocity_rad_s,
            anchor: None,
            recent: std::collections::VecDeque::new(),
            overspeeds: 0,
        })
    }

    /// Forgets the samples measured so far (the count stays): the next sample starts a new window. For a
    /// robot moved by something other than its joints' motion, such as a simulator's reset placing the arm.
    pub fn restart(&mut self) {
        self.anchor = None;
        self.recent.clear();
    }

    /// Takes the joints measured at `time_s`. Returns the fastest joint over its limit (by the ratio of speed to
    /// limit), measured against a sample at least [`SPEED_WINDOW_S`] older, and counts it. A sample of another
    /// width, not finite, or not later than the previous one starts the watch again.
    pub fn observe(&mut self, joints_rad: &[f64], time_s: f64) -> Option<Overspeed> {
        let newest_s = self.recent.back().or(self.anchor.as_ref()).map(|(_, t)| *t);
        let usable = joints_rad.len() == self.max_velocity_rad_s.len()
            && joints_rad.iter().all(|q| q.is_finite())
            && time_s.is_finite()
            && newest_s.is_none_or(|t| time_s > t);
        if !usable {
            self.anchor = None;
            self.recent.clear();
            if joints_rad.len() == self.max_velocity_rad_s.len() && joints_rad.iter().all(|q| q.is_finite()) {
                self.anchor = Some((joints_rad.to_vec(), time_s));
            }
            return None;
        }
        // Move the anchor up to the newest sample still at least a window older than this one.
        while let Some((_, t)) = self.recent.front() {
            if time_s - t >= SPEED_WINDOW_S {
                self.anchor = self.recent.pop_front();
            } else {
                break;
            }
        }
        let found = match &self.anchor {
            Some((q0, t0)) if time_s - t0 >= SPEED_WINDOW_S => {
                let dt = time_s - t0;
                joints_rad
                    .iter()
                    .zip(q0)
                    .zip(&self.max_velocity_rad_s)
                    .enumerate()
                    .map(|(joint, ((q, q0), limit))| Overspeed {
                        joint,
                        speed_rad_s: (q - q0).abs() / dt,
                        limit_rad_s: *limit,
                    })
                    .filter(|o| o.speed_rad_s > o.limit_rad_s * OVERSPEED_MARGIN)
                    .max_by(|a, b| {
                        (a.speed_rad_s / a.limit_rad_s).total_cmp(&(b.speed_rad_s / b.limit_rad_s))
                    })
            }
            _ => None,
        };
        if self.anchor.is_none() {
            self.anchor = Some((joints_rad.to_vec(), time_s));
        } else {
            self.recent.push_back((joints_rad.to_vec(), time_s));
        }
        self.overspeeds += u64::from(found.is_some());
        found
    }
}

#[cfg(test)]
// Exact equality is the property: a step that fits, or no step, passes bit for bit.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A limiter without the step-time cap, for the properties that do not depend on it.
    fn limiter(v: &[f64]) -> JointRateLimiter {
        JointRateLimiter::new(v.to_vec())
            .unwrap()
            .with_max_step_s(f64::INFINITY)
    }

    /// After a pause, a step gets one period's motion, not the pause's; the next continues from there.
    #[test]
    fn a_step_after_a_pause_gets_one_period_of_motion() {
        let mut l = JointRateLimiter::new(vec![1.0, 2.0]).unwrap();
        l.reset(&[0.0, 0.0], 0.0);
        assert_eq!(l.elapsed_s(10.0), MAX_STEP_S);
        assert_eq!(l.elapsed_s(0.5 * MAX_STEP_S), 0.5 * MAX_STEP_S);
        let s = l.step(&[1.0, 0.0], 10.0);
        assert!(s.limited);
        assert!((s.joints_rad[0] - MAX_STEP_S).abs() < 1e-15, "{s:?}");
        let s = l.step(&[1.0, 0.0], 10.01);
        assert!((s.joints_rad[0] - MAX_STEP_S - 0.01).abs() < 1e-12, "{s:?}");
        let s = l.step(&[0.0, 0.0], 20.0);
        assert!((s.joints_rad[0] - 0.01).abs() < 1e-12, "{s:?}");
        // A step that fits in one period passes whole, however long the pause.
        let mut l = JointRateLimiter::new(vec![1.0]).unwrap();
        l.reset(&[0.0], 0.0);
        assert_eq!(l.step(&[0.015], 5.0).joints_rad, vec![0.015]);
    }

    #[test]
    fn speeds_must_be_finite_and_positive() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(JointRateLimiter::new(vec![1.0, bad]).is_err(), "{bad}");
        }
        assert_eq!(limiter(&[1.0, 2.0]).max_velocity_rad_s(), &[1.0, 2.0]);
    }

    #[test]
    fn a_step_within_the_limit_passes_unchanged() {
        let mut l = limiter(&[1.0, 1.0]);
        l.reset(&[0.0, 0.0], 10.0);
        let s = l.step(&[0.05, -0.08], 10.1);
        assert_eq!(s.joints_rad, vec![0.05, -0.08]);
        assert!(!s.limited);
        assert_eq!(s.scale, 1.0);
        assert_eq!(l.last(), Some(&[0.05, -0.08][..]));
        assert_eq!(l.last_time_s(), 10.1);
    }

    #[test]
    fn a_long_step_is_shortened_by_one_factor_for_every_joint() {
        let mut l = limiter(&[1.0, 4.0]);
        l.reset(&[0.0, 1.0], 0.0);
        // Joint 0 may move 0.1 in 0.1 s, joint 1 0.4: joint 0 sets the factor (0.1 / 0.5).
        let s = l.step(&[0.5, 2.0], 0.1);
        assert!(s.limited);
        assert!((s.scale - 0.2).abs() < 1e-12, "{s:?}");
        assert!(
            (s.joints_rad[0] - 0.1).abs() < 1e-12 && (s.joints_rad[1] - 1.2).abs() < 1e-12,
            "{s:?}"
        );
        // The next step starts where this one ended.
        let s = l.step(&[0.5, 2.0], 0.2);
        assert!(
            (s.joints_rad[0] - 0.2).abs() < 1e-12 && (s.joints_rad[1] - 1.4).abs() < 1e-12,
            "{s:?}"
        );
    }

    #[test]
    fn no_time_means_no_motion_and_time_never_runs_back() {
        let mut l = limiter(&[1.0]);
        l.reset(&[0.0], 5.0);
        let s = l.step(&[1.0], 5.0);
        assert_eq!((s.joints_rad[0], s.scale, s.limited), (0.0, 0.0, true));
        let s = l.step(&[1.0], 4.0);
        assert_eq!(s.joints_rad[0], 0.0);
        assert_eq!(l.last_time_s(), 5.0);
        assert_eq!(l.elapsed_s(f64::NAN), 0.0);
        assert_eq!(l.elapsed_s(5.5), 0.5);
        let s = l.step(&[1.0], 5.5);
        assert!((s.joints_rad[0] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn without_a_start_the_first_step_is_the_start() {
        let mut l = limiter(&[1.0, 1.0]);
        assert_eq!(l.last(), None);
        let s = l.step(&[2.0, 3.0], 0.0);
        assert_eq!((s.joints_rad, s.limited), (vec![2.0, 3.0], false));
        // A vector of another width cannot be limited from the old one: it becomes the start.
        let mut l = limiter(&[1.0, 1.0]);
        l.reset(&[0.0], 0.0);
        let s = l.step(&[2.0, 3.0], 0.0);
        assert_eq!(s.joints_rad, vec![2.0, 3.0]);
        assert_eq!(l.last(), Some(&[2.0, 3.0][..]));
    }

    #[test]
    fn a_vector_of_another_width_than_the_limits_is_a_new_start() {
        // The start has the limits' width, the request not: nothing to limit it from, even in no time.
        let mut l = limiter(&[1.0, 1.0]);
        l.reset(&[0.0, 0.0], 0.0);
        let s = l.step(&[5.0, 5.0, 5.0], 0.0);
        assert_eq!((s.joints_rad, s.limited), (vec![5.0, 5.0, 5.0], false));
        // The start and the request agree with each other but not with the limits.
        let mut l = limiter(&[1.0, 1.0]);
        l.reset(&[0.0, 0.0, 0.0], 0.0);
        let s = l.step(&[5.0, 5.0, 5.0], 0.0);
        assert_eq!((s.joints_rad, s.limited), (vec![5.0, 5.0, 5.0], false));
    }

    #[test]
    fn scale_says_what_a_step_would_take_without_taking_it() {
        let mut l = limiter(&[1.0, 2.0]);
        assert_eq!(l.scale(&[9.0, 9.0], 1.0), 1.0, "no start: nothing to limit");
        l.reset(&[0.0, 0.0], 0.0);
        assert!((l.scale(&[0.5, 0.5], 0.25) - 0.5).abs() < 1e-12);
        assert_eq!(l.scale(&[0.1, 0.1], 0.25), 1.0);
        assert_eq!(l.scale(&[f64::NAN, 0.1], 0.25), 0.0);
        assert_eq!(l.last(), Some(&[0.0, 0.0][..]));
        assert_eq!(l.last_time_s(), 0.0);
    }

    #[test]
    fn a_non_finite_request_holds() {
        let mut l = limiter(&[1.0, 1.0]);
        l.reset(&[0.1, 0.2], 0.0);
        let s = l.step(&[f64::NAN, 0.3], 1.0);
        assert_eq!(s.joints_rad, vec![0.1, 0.2]);
        assert!(s.limited);
        assert_eq!(l.last(), Some(&[0.1, 0.2][..]));
    }

    proptest! {
        /// Whatever is asked, no joint moves faster than its limit, the step keeps its direction, and a step
        /// that fits passes exactly.
        #[test]
        fn no_joint_exceeds_its_speed(
            v in prop::array::uniform3(0.1f64..8.0),
            start in prop::array::uniform3(-3.0f64..3.0),
            asks in prop::collection::vec((prop::array::uniform3(-3.0f64..3.0), 0.0f64..0.2), 1..20),
        ) {
            let mut l = limiter(&v);
            l.reset(&start, 0.0);
            let mut t = 0.0;
            let mut last = start.to_vec();
            for (ask, dt) in asks {
                t += dt;
                let s = l.step(&ask, t);
                let mut fits = true;
                for j in 0..3 {
                    let moved = s.joints_rad[j] - last[j];
                    prop_assert!(moved.abs() <= v[j] * dt * (1.0 + 1e-12) + 1e-15, "joint {j}: {moved} in {dt} s");
                    // Same direction and the same fraction for every joint.
                    prop_assert!((moved - (ask[j] - last[j]) * s.scale).abs() < 1e-12);
                    fits &= (ask[j] - last[j]).abs() <= v[j] * dt;
                }
                prop_assert_eq!(s.limited, !fits);
                if fits {
                    prop_assert_eq!(&s.joints_rad, &ask.to_vec());
                }
                last = s.joints_rad;
            }
        }
    }
    fn accelerating(v: &[f64], a: &[f64]) -> JointRateLimiter {
        JointRateLimiter::new(v.to_vec())
            .unwrap()
            .with_max_acceleration_rad_s2(a.to_vec())
            .unwrap()
    }

    #[test]
    fn accelerations_must_be_positive_and_one_per_joint() {
        let l = JointRateLimiter::new(vec![1.0, 1.0]).unwrap();
        assert!(l.clone().with_max_acceleration_rad_s2(vec![1.0]).is_err());
        for bad in [0.0, -1.0, f64::NAN] {
            assert!(
                l.clone().with_max_acceleration_rad_s2(vec![1.0, bad]).is_err(),
                "{bad}"
            );
        }
        // Infinite everywhere is no acceleration limit at all.
        let none = l
            .clone()
            .with_max_acceleration_rad_s2(vec![f64::INFINITY; 2])
            .unwrap();
        assert_eq!(none.max_acceleration_rad_s2(), None);
        let some = l.with_max_acceleration_rad_s2(vec![f64::INFINITY, 2.0]).unwrap();
        assert_eq!(some.max_acceleration_rad_s2(), Some(&[f64::INFINITY, 2.0][..]));
    }

    /// From rest toward a far target: the speed grows by a·dt per step, cruises at the limit, and slows down
    /// in time to land on the target; each step that is not the asked one counts as limited.
    #[test]
    fn a_far_target_is_reached_through_a_trapezoid() {
        let (v, a, dt) = (1.0, 4.0, 0.01);
        let mut l = accelerating(&[v], &[a]);
        l.reset(&[0.0], 0.0);
        let mut q = 0.0;
        let mut speeds = Vec::new();
        let mut limited = 0;
        for k in 1..=400 {
            let s = l.step(&[1.0], f64::from(k) * dt);
            speeds.push((s.joints_rad[0] - q) / dt);
            limited += usize::from(s.limited);
            q = s.joints_rad[0];
            if q == 1.0 {
                break;
            }
        }
        assert_eq!(q, 1.0, "not reached");
        assert!((speeds[0] - a * dt).abs() < 1e-12, "{:?}", &speeds[..3]);
        assert!(speeds.iter().any(|s| (s - v).abs() < 1e-9), "never cruised");
        // 1 rad at 1 rad/s with 0.25 s to speed up and to slow down: about 1.25 s.
        assert!((120..=135).contains(&speeds.len()), "{}", speeds.len());
        assert_eq!(limited, speeds.len() - 1);
        assert!(
            *speeds.last().unwrap() <= a * dt * 1.5,
            "arrived at {}",
            speeds.last().unwrap()
        );
        // Arrived: it holds exactly, and a step back starts again from rest.
        assert_eq!(l.step(&[1.0], 5.0).joints_rad, vec![1.0]);
        let s = l.step(&[0.0], 5.01);
        assert!((s.joints_rad[0] - (1.0 - a * dt * dt)).abs() < 1e-12, "{s:?}");
    }

    /// A joint moving away from a target that turned back keeps decelerating at the limit rather than stopping
    /// at once; a joint stopped by [`JointRateLimiter::stop_at`] starts again from rest.
    #[test]
    fn a_turned_target_is_braked_for_and_a_stop_is_a_stop() {
        let mut l = accelerating(&[2.0], &[10.0]);
        l.reset(&[0.0], 0.0);
        let mut t = 0.0;
        for _ in 0..30 {
            t += 0.01;
            l.step(&[5.0], t);
        }
        let before = l.last().unwrap()[0];
        let s = l.step(&[0.0], t + 0.01);
        assert!(
            s.joints_rad[0] > before,
            "reversed at once: {before} -> {:?}",
            s.joints_rad
        );
        l.stop_at(&[1.0]);
        assert_eq!(l.last(), Some(&[1.0][..]));
        let s = l.step(&[5.0], t + 0.02);
        assert!(
            (s.joints_rad[0] - (1.0 + 10.0 * 0.01 * 0.01)).abs() < 1e-12,
            "{s:?}"
        );
        // `forget` drops the start: the next request is the new start.
        l.forget();
        assert_eq!(l.step(&[3.0], t + 0.03).joints_rad, vec![3.0]);
    }

    /// Under acceleration limits: a request in the same instant holds (and keeps the velocity, so the next step
    /// carries on), a non-finite request holds and stops the joints (the next step starts from rest), and the
    /// reported scale is the fraction of the asked step taken.
    #[test]
    fn accelerated_steps_hold_on_bad_input_and_in_no_time() {
        let (v, a, dt) = (1.0, 10.0, 0.01);
        let mut l = accelerating(&[v, v], &[a, a]);
        l.reset(&[0.5, 0.5], 0.0);
        let mut t = dt;
        // At rest, asking for where it is moves nothing and takes all of the (empty) step.
        let s = l.step(&[0.5, 0.5], t);
        assert_eq!(
            (s.joints_rad.clone(), s.scale, s.limited),
            (vec![0.5, 0.5], 1.0, false)
        );
        // 0.1 s to reach the speed limit; twice that to be sure of cruising.
        for _ in 0..20 {
            t += dt;
            l.step(&[5.0, 5.0], t);
        }
        let cruising = l.last().unwrap().to_vec();
        assert_eq!(l.step(&cruising, t).joints_rad, cruising);
        let s = l.step(&[5.0, 5.0], t);
        assert_eq!(s.joints_rad, cruising);
        t += dt;
        let s = l.step(&[5.0, 5.0], t);
        assert!(
            (s.joints_rad[0] - cruising[0] - v * dt).abs() < 1e-12,
            "{s:?} after {cruising:?}"
        );
        assert!((s.scale - v * dt / (5.0 - cruising[0])).abs() < 1e-12, "{s:?}");
        // Asked to be where it is while cruising: it brakes at the limit rather than stopping at once.
        let here = s.joints_rad.clone();
        t += dt;
        let s = l.step(&here, t);
        assert!(
            (s.joints_rad[0] - here[0] - (v - a * dt) * dt).abs() < 1e-12,
            "{s:?} after {here:?}"
        );
        assert!(s.limited);
        let held = s.joints_rad.clone();
        t += dt;
        let s = l.step(&[f64::NAN, 5.0], t);
        assert_eq!(s.joints_rad, held);
        assert!(s.limited);
        // Stopped: the next step starts from rest.
        t += dt;
        let s = l.step(&[5.0, 5.0], t);
        assert!(
            (s.joints_rad[0] - held[0] - a * dt * dt).abs() < 1e-12,
            "{s:?} after {held:?}"
        );
    }

    proptest! {
        /// Speed and acceleration limits together, for any request sequence and any step times: no joint moves
        /// faster than its speed limit, and no joint's velocity changes by more than its acceleration limit
        /// allows in the step (velocities being each step's motion over its time).
        #[test]
        fn no_step_exceeds_the_speed_or_the_acceleration(
            v in prop::array::uniform3(0.2f64..6.0),
            a in prop::array::uniform3(0.5f64..40.0),
            start in prop::array::uniform3(-3.0f64..3.0),
            asks in prop::collection::vec((prop::array::uniform3(-3.0f64..3.0), 0.001f64..0.05, 1usize..20), 1..12),
        ) {
            let mut l = accelerating(&v, &a);
            l.reset(&start, 0.0);
            let (mut t, mut last, mut velocity) = (0.0, start.to_vec(), vec![0.0; 3]);
            for (ask, dt, repeat) in asks {
                for _ in 0..repeat {
                    t += dt;
                    let s = l.step(&ask, t);
                    let used = dt.min(MAX_STEP_S);
                    for j in 0..3 {
                        let speed = (s.joints_rad[j] - last[j]) / used;
                        prop_assert!(speed.abs() <= v[j] * (1.0 + 1e-9), "joint {j}: {speed} rad/s");
                        // A step that lands on the target may brake harder: the braking curve of a longer step
                        // time than the last lies lower, and passing the target is the worse of the two.
                        let landed = s.joints_rad[j] == ask[j];
                        prop_assert!(landed || (speed - velocity[j]).abs() <= a[j] * used * (1.0 + 1e-6) + 1e-9,
                            "joint {j}: velocity {} -> {speed} in {used} s", velocity[j]);
                        // A joint that landed stopped there.
                        velocity[j] = if landed { 0.0 } else { speed };
                    }
                    prop_assert_eq!(s.limited, s.joints_rad != ask.to_vec());
                    last = s.joints_rad;
                }
            }
        }

        /// From rest toward a target that stays put, at a steady step time: every joint approaches it without
        /// passing it and arrives, within the time a trapezoid (speeding up, cruising, slowing down) needs plus
        /// a few steps.
        #[test]
        fn a_still_target_is_reached_without_overshoot(
            v in prop::array::uniform3(0.2f64..6.0),
            a in prop::array::uniform3(0.5f64..40.0),
            start in prop::array::uniform3(-3.0f64..3.0),
            target in prop::array::uniform3(-3.0f64..3.0),
            dt in 0.001f64..0.02,
        ) {
            let mut l = accelerating(&v, &a);
            l.reset(&start, 0.0);
            let needed_s = (0..3)
                .map(|j| (target[j] - start[j]).abs() / v[j] + v[j] / a[j] + 2.0 * ((target[j] - start[j]).abs() / a[j]).sqrt())
                .fold(0.0, f64::max);
            let steps = (needed_s / dt).ceil() as usize + 10;
            let mut q = start.to_vec();
            let mut velocity = [0.0; 3];
            for k in 1..=steps {
                let s = l.step(&target, k as f64 * dt);
                for j in 0..3 {
                    // At a steady step time every step keeps the acceleration limit but the landing one, which
                    // keeps twice it: the braking curve is continuous, the steps are not, so the last one
                    // brakes the rest of a step's worth of speed (less than two steps' change).
                    let speed = (s.joints_rad[j] - q[j]) / dt;
                    let landed = s.joints_rad[j] == target[j] && q[j] != target[j];
                    let allowed = if landed { 2.0 } else { 1.0 } * a[j] * dt;
                    prop_assert!((speed - velocity[j]).abs() <= allowed * (1.0 + 1e-6) + 1e-12,
                        "joint {j}: velocity {} -> {speed} in {dt} s", velocity[j]);
                    // It stops there (see `profiled`).
                    velocity[j] = if landed { 0.0 } else { speed };
                    let before = target[j] - q[j];
                    let after = target[j] - s.joints_rad[j];
                    prop_assert!(after == 0.0 || after.signum() == before.signum(), "joint {j} passed its target");
                    prop_assert!(after.abs() <= before.abs(), "joint {j} moved away");
                }
                q = s.joints_rad;
            }
            prop_assert_eq!(q, target.to_vec());
        }
    }

    #[test]
    fn a_joint_measured_over_its_limit_is_reported_and_counted() {
        let mut w = JointSpeedWatch::new(vec![1.0, 2.0]).unwrap();
        // 0.5 rad/s and 1.5 rad/s, sampled every 10 ms: within both limits.
        for i in 0..50 {
            let t = f64::from(i) * 0.01;
            assert_eq!(w.observe(&[0.5 * t, 1.5 * t], t), None, "{t}");
        }
        // Joint 1 now at 3 rad/s (1.5 times its limit); joint 0 at 1.1 (within the margin).
        let mut seen = None;
        for i in 50..100 {
            let t = f64::from(i) * 0.01;
            let q = [0.25 + 1.1 * (t - 0.5), 0.75 + 3.0 * (t - 0.5)];
            seen = w.observe(&q, t).or(seen);
        }
        let o = seen.expect("an overspeed");
        assert_eq!(o.joint, 1);
        assert!(
            (o.speed_rad_s - 3.0).abs() < 1e-6 && o.limit_rad_s == 2.0,
            "{o:?}"
        );
        assert!(w.overspeeds > 30 && w.overspeeds <= 50, "{}", w.overspeeds);
    }

    /// A sample that is not a measurement (not finite, another width, not later than the previous one) starts
    /// the watch again: the next speed is never measured across it, from a sample taken before it.
    #[test]
    fn a_bad_sample_restarts_the_watch() {
        for (bad, at_s) in [(vec![f64::NAN], 0.1), (vec![5.0, 5.0], 0.1), (vec![0.0], 0.05)] {
            let mut w = JointSpeedWatch::new(vec![1.0]).unwrap();
            assert_eq!(w.observe(&[0.0], 0.0), None);
            assert_eq!(w.observe(&[0.0], 0.05), None);
            assert_eq!(w.observe(&bad, at_s), None, "{bad:?}");
            // 1 rad in 0.15 s from the first sample; less than a window since the restart.
            assert_eq!(w.observe(&[1.0], 0.15), None, "{bad:?}");
            if at_s > 0.05 {
                // Nor measured from the bad sample itself.
                assert_eq!(w.observe(&[1.0], 0.2), None, "{bad:?}");
            }
            assert_eq!(w.overspeeds, 0);
        }
        // A sample earlier than the last is a new start of its own: speeds are measured from it.
        let mut w = JointSpeedWatch::new(vec![1.0]).unwrap();
        assert_eq!(w.observe(&[0.0], 2.0), None);
        assert_eq!(w.observe(&[0.0], 0.5), None);
        // Not before a whole window has passed, however fast.
        assert_eq!(w.observe(&[0.05], 0.55), None);
        assert!(w.observe(&[1.0], 0.65).is_some());
    }

    #[test]
    fn jitter_within_the_window_is_not_a_speed() {
        let mut w = JointSpeedWatch::new(vec![1.0]).unwrap();
        // 0.9 rad/s, stamps jittering by up to 4 ms around a 10 ms period: one sample pair reads up to 4.5
        // rad/s, the window never more than 0.9 · 0.1 / 0.092.
        for i in 0..200 {
            let true_t = f64::from(i) * 0.01;
            let stamp = true_t + if i % 2 == 0 { 0.004 } else { -0.004 };
            assert_eq!(w.observe(&[0.9 * true_t], stamp), None, "{i}");
        }
        assert_eq!(w.overspeeds, 0);
        // A jump back in time, a wrong width or a NaN restarts it instead of reading a speed.
        assert_eq!(w.observe(&[5.0], 0.5), None);
        assert_eq!(w.observe(&[5.0, 1.0], 3.0), None);
        assert_eq!(w.observe(&[f64::NAN], 3.1), None);
        assert_eq!(w.observe(&[0.0], 3.2), None);
        assert_eq!(w.observe(&[0.05], 3.25), None);
        assert!(
            w.observe(&[0.2], 3.31).is_some(),
            "1.8 rad/s over the 0.11 s window"
        );
        assert!(JointSpeedWatch::new(vec![0.0]).is_err());
    }
}
