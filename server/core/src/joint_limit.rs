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

/// A rate limiter over one arm's joints (the gripper is not one of them).
#[derive(Debug, Clone, PartialEq)]
pub struct JointRateLimiter {
    max_velocity_rad_s: Vec<f64>,
    last_rad: Option<Vec<f64>>,
    last_time_s: f64,
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
        })
    }

    /// The largest speed of each joint.
    pub fn max_velocity_rad_s(&self) -> &[f64] {
        &self.max_velocity_rad_s
    }

    /// Starts from `joints_rad` (the measured joints) at `time_s`: the next step is limited from there.
    pub fn reset(&mut self, joints_rad: &[f64], time_s: f64) {
        self.last_rad = Some(joints_rad.to_vec());
        self.last_time_s = time_s;
    }

    /// The joints last handed out (or reset to).
    pub fn last(&self) -> Option<&[f64]> {
        self.last_rad.as_deref()
    }

    /// Time of the last step (or reset).
    pub fn last_time_s(&self) -> f64 {
        self.last_time_s
    }

    /// Seconds since the last step for a step at `time_s`: 0 when time did not move on (a second command in
    /// the same instant gets no new motion) or is not a number.
    pub fn elapsed_s(&self, time_s: f64) -> f64 {
        let dt = time_s - self.last_time_s;
        if dt > 0.0 { dt } else { 0.0 }
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
                return LimitedStep {
                    joints_rad: desired_rad.to_vec(),
                    scale: 1.0,
                    limited: false,
                };
            }
        };
        let scale = self.scale_of(last, desired_rad, dt);
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
        self.last_rad = Some(joints_rad.clone());
        LimitedStep {
            joints_rad,
            scale,
            limited: scale < 1.0,
        }
    }
}

#[cfg(test)]
// Exact equality is the property: a step that fits, or no step, passes bit for bit.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn limiter(v: &[f64]) -> JointRateLimiter {
        JointRateLimiter::new(v.to_vec()).unwrap()
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
}
