//! The safety gate every target passes before it reaches a bridge, teleop and policy alike.
//!
//! Order of checks for one proposed target:
//! 1. reject NaN, infinities, non-unit quaternions and a non-finite time (`RejectedInvalid`);
//! 2. clamp the position into the workspace box;
//! 3. reject the target if the clamped step from the gate's reference exceeds the position or angle jump
//!    threshold (`RejectedJump`). The step is measured after clamping so that pushing the phone past a wall
//!    slowly keeps the target sliding along the wall instead of tripping the jump filter;
//! 4. shorten the step to the optional linear and angular speed limits;
//! 5. the output becomes the new reference.
//!
//! The reference is the last target that passed, or whatever [`SafetyGate::reset_reference`] set. Callers
//! reset it at every re-index (clutch release, source change) from the robot's measured pose: a reference
//! that is never reset is what makes the paper's filter reject every command after the robot moved while
//! clutched.

use crate::config::{ConfigError, GateConfig};
use crate::pose::{angle_between_rad, check_pose};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// Longest interval the velocity limits credit to one step (s). A sample after a pause must not be allowed
/// to cover the whole pause at full speed in one jump; this is also the interval assumed right after a reset.
pub const MAX_VELOCITY_INTERVAL_S: f64 = 0.25;

/// Rounding left in the angle between a rotation and itself (~1e-17 rad from the quaternion product). The
/// angular speed limit ignores it: at zero elapsed time (a re-index checks its anchor at the reset instant)
/// it would otherwise report every re-index of a rotated pose as speed-limited.
const ROTATION_ROUNDING_RAD: f64 = 1e-12;

/// What the gate did with one command (mirrors `phone2act.v1.GateVerdict`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum GateVerdict {
    Accepted,
    Clamped,
    RejectedJump,
    RejectedInvalid,
    HeldStale,
}

impl GateVerdict {
    /// True if a target was handed on (possibly clamped).
    pub fn passed(self) -> bool {
        matches!(self, GateVerdict::Accepted | GateVerdict::Clamped)
    }

    pub fn rejected(self) -> bool {
        matches!(self, GateVerdict::RejectedJump | GateVerdict::RejectedInvalid)
    }
}

/// The gate's decision on one command, with the reason in words (mirrors `phone2act.v1.GateDecision`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GateDecision {
    pub verdict: GateVerdict,
    /// Empty when accepted unchanged.
    pub reason: String,
    pub workspace_clamped: bool,
    pub velocity_limited: bool,
    /// Step of the output from the reference when passed; the attempted step when rejected (m).
    pub position_step_m: f64,
    /// Same for the orientation (rad).
    pub rotation_step_rad: f64,
}

impl GateDecision {
    /// A decision that carries no step: used for events that did not consult the limits.
    pub fn note(verdict: GateVerdict, reason: impl Into<String>) -> Self {
        Self {
            verdict,
            reason: reason.into(),
            workspace_clamped: false,
            velocity_limited: false,
            position_step_m: 0.0,
            rotation_step_rad: 0.0,
        }
    }
}

/// Workspace clamp, jump filter, validity check, velocity limits and staleness for one arm.
#[derive(Debug, Clone)]
pub struct SafetyGate {
    config: GateConfig,
    reference: Isometry3<f64>,
    reference_time_s: Option<f64>,
    last_input_s: Option<f64>,
    stale_reported: bool,
}

impl SafetyGate {
    pub fn new(config: &GateConfig, reference: Isometry3<f64>) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Self {
            config: config.clone(),
            reference,
            reference_time_s: None,
            last_input_s: None,
            stale_reported: false,
        })
    }

    pub fn config(&self) -> &GateConfig {
        &self.config
    }

    /// The pose the next step is measured from.
    pub fn reference(&self) -> &Isometry3<f64> {
        &self.reference
    }

    /// Restarts the jump filter from `pose` (normally the measured end-effector pose) without a time: the
    /// next step gets the velocity allowance of [`MAX_VELOCITY_INTERVAL_S`] and staleness restarts with the
    /// next command.
    pub fn reset_reference(&mut self, pose: Isometry3<f64>) {
        self.reference = pose;
        self.reference_time_s = None;
        self.last_input_s = None;
        self.stale_reported = false;
    }

    /// Like [`SafetyGate::reset_reference`], and counts `now_s` as fresh input for the staleness timeout.
    pub fn reset_reference_at(&mut self, pose: Isometry3<f64>, now_s: f64) {
        self.reset_reference(pose);
        if now_s.is_finite() {
            self.reference_time_s = Some(now_s);
            self.last_input_s = Some(now_s);
        }
    }

    /// Checks one proposed target at time `now_s`. Returns the target to send (`None` when dropped) and the
    /// decision. A dropped target leaves the reference unchanged.
    pub fn check(&mut self, proposed: Isometry3<f64>, now_s: f64) -> (Option<Isometry3<f64>>, GateDecision) {
        if !now_s.is_finite() {
            return (
                None,
                GateDecision::note(
                    GateVerdict::RejectedInvalid,
                    format!("command time is not finite: {now_s}"),
                ),
            );
        }
        if let Err(e) = check_pose(&proposed) {
            return (
                None,
                GateDecision::note(GateVerdict::RejectedInvalid, format!("invalid target: {e}")),
            );
        }
        self.last_input_s = Some(self.last_input_s.map_or(now_s, |t| t.max(now_s)));
        self.stale_reported = false;

        let cfg = &self.config;
        let mut position = proposed.translation.vector;
        let mut clamped_axes = [false; 3];
        for axis in 0..3 {
            let (min_m, max_m) = (cfg.workspace_min_m[axis], cfg.workspace_max_m[axis]);
            clamped_axes[axis] = position[axis] < min_m || position[axis] > max_m;
            position[axis] = position[axis].clamp(min_m, max_m);
        }
        let workspace_clamped = clamped_axes.iter().any(|&c| c);

        let step = position - self.reference.translation.vector;
        let position_step_m = step.norm();
        let rotation_step_rad = angle_between_rad(&self.reference.rotation, &proposed.rotation);
        if let Some(reason) = jump_reason(cfg, position_step_m, rotation_step_rad) {
            let decision = GateDecision {
                verdict: GateVerdict::RejectedJump,
                reason,
                workspace_clamped,
                velocity_limited: false,
                position_step_m,
                rotation_step_rad,
            };
            return (None, decision);
        }

        let interval_s = self.reference_time_s.map_or(MAX_VELOCITY_INTERVAL_S, |t| {
            (now_s - t).clamp(0.0, MAX_VELOCITY_INTERVAL_S)
        });
        let (mut out_position, linear_limited) = match cfg.max_linear_speed_m_s {
            Some(speed) if position_step_m > speed * interval_s => (
                self.reference.translation.vector + step * (speed * interval_s / position_step_m),
                true,
            ),
            _ => (position, false),
        };
        // A reference outside the box (a reset to a measured pose out there) puts the shortened step
        // outside too. The box wins over the speed limit; per axis the result still lies between the
        // reference and the clamped target, so it stays within the jump threshold just checked.
        for axis in 0..3 {
            out_position[axis] =
                out_position[axis].clamp(cfg.workspace_min_m[axis], cfg.workspace_max_m[axis]);
        }
        let (out_rotation, angular_limited) = match cfg.max_angular_speed_rad_s {
            Some(speed) if rotation_step_rad > speed * interval_s + ROTATION_ROUNDING_RAD => {
                let delta: UnitQuaternion<f64> = self.reference.rotation.inverse() * proposed.rotation;
                let fraction = speed * interval_s / rotation_step_rad;
                (self.reference.rotation * delta.powf(fraction), true)
            }
            _ => (proposed.rotation, false),
        };
        let velocity_limited = linear_limited || angular_limited;
        let output = Isometry3::from_parts(Translation3::from(out_position), out_rotation);
        let out_position_step_m = (out_position - self.reference.translation.vector).norm();
        let out_rotation_step_rad = if angular_limited {
            angle_between_rad(&self.reference.rotation, &out_rotation)
        } else {
            rotation_step_rad
        };

        let (verdict, reason) = if workspace_clamped || velocity_limited {
            (
                GateVerdict::Clamped,
                clamp_reason(clamped_axes, linear_limited, angular_limited, cfg),
            )
        } else {
            (GateVerdict::Accepted, String::new())
        };
        self.reference = output;
        self.reference_time_s = Some(now_s);
        let decision = GateDecision {
            verdict,
            reason,
            workspace_clamped,
            velocity_limited,
            position_step_m: out_position_step_m,
            rotation_step_rad: out_rotation_step_rad,
        };
        (Some(output), decision)
    }

    /// True if no valid command arrived within the staleness timeout (never before the first command).
    pub fn is_stale(&self, now_s: f64) -> bool {
        self.last_input_s
            .is_some_and(|t| now_s - t > self.config.stale_timeout_s)
    }

    /// Reports the moment the input goes stale: `Some(HeldStale)` once per silence, `None` otherwise. The
    /// arm holds its last target; nothing here moves it.
    pub fn check_stale(&mut self, now_s: f64) -> Option<GateDecision> {
        if self.stale_reported || !self.is_stale(now_s) {
            return None;
        }
        self.stale_reported = true;
        let silent_s = now_s - self.last_input_s.unwrap_or(now_s);
        Some(GateDecision::note(
            GateVerdict::HeldStale,
            format!(
                "no valid command for {silent_s:.2} s (timeout {:.2} s): holding",
                self.config.stale_timeout_s
            ),
        ))
    }
}

fn jump_reason(cfg: &GateConfig, position_step_m: f64, rotation_step_rad: f64) -> Option<String> {
    let mut parts = Vec::new();
    if position_step_m > cfg.jump_position_m {
        parts.push(format!(
            "position step {position_step_m:.3} m exceeds jump threshold {:.3} m",
            cfg.jump_position_m
        ));
    }
    if rotation_step_rad > cfg.jump_rotation_rad {
        parts.push(format!(
            "rotation step {rotation_step_rad:.3} rad exceeds jump threshold {:.3} rad",
            cfg.jump_rotation_rad
        ));
    }
    (!parts.is_empty()).then(|| parts.join("; "))
}

fn clamp_reason(clamped_axes: [bool; 3], linear: bool, angular: bool, cfg: &GateConfig) -> String {
    let mut parts = Vec::new();
    if clamped_axes.iter().any(|&c| c) {
        let axes: Vec<&str> = ["x", "y", "z"]
            .into_iter()
            .zip(clamped_axes)
            .filter_map(|(n, c)| c.then_some(n))
            .collect();
        parts.push(format!("clamped to workspace on {}", axes.join(", ")));
    }
    if linear {
        parts.push(format!(
            "linear speed limited to {:.3} m/s",
            cfg.max_linear_speed_m_s.unwrap_or_default()
        ));
    }
    if angular {
        parts.push(format!(
            "angular speed limited to {:.3} rad/s",
            cfg.max_angular_speed_rad_s.unwrap_or_default()
        ));
    }
    parts.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::pose_distance;
    use nalgebra::{Quaternion, Vector3};
    use proptest::prelude::*;

    fn at(x: f64, y: f64, z: f64) -> Isometry3<f64> {
        Isometry3::translation(x, y, z)
    }

    fn gate(config: &GateConfig) -> SafetyGate {
        SafetyGate::new(config, at(0.25, 0.0, 0.2)).unwrap()
    }

    #[test]
    fn accepts_small_steps_and_reports_them() {
        let mut g = gate(&GateConfig::default());
        let (out, d) = g.check(at(0.27, 0.0, 0.2), 0.0);
        assert_eq!(d.verdict, GateVerdict::Accepted);
        assert!(d.reason.is_empty());
        assert!((d.position_step_m - 0.02).abs() < 1e-12);
        assert_eq!(out.unwrap(), at(0.27, 0.0, 0.2));
        assert_eq!(*g.reference(), at(0.27, 0.0, 0.2));
    }

    #[test]
    fn rejects_jumps_with_a_reason_and_keeps_the_reference() {
        let mut g = gate(&GateConfig::default());
        let (out, d) = g.check(at(0.25, 0.081, 0.2), 0.0);
        assert!(out.is_none());
        assert_eq!(d.verdict, GateVerdict::RejectedJump);
        assert_eq!(d.reason, "position step 0.081 m exceeds jump threshold 0.060 m");
        assert_eq!(*g.reference(), at(0.25, 0.0, 0.2));
        let turned = Isometry3::from_parts(
            Translation3::new(0.25, 0.0, 0.2),
            UnitQuaternion::from_euler_angles(0.6, 0.0, 0.0),
        );
        let (out, d) = g.check(turned, 0.01);
        assert!(out.is_none());
        assert!(d.reason.starts_with("rotation step 0.600 rad"), "{}", d.reason);
        // After a reset the same target is a small step again.
        g.reset_reference(at(0.25, 0.07, 0.2));
        assert_eq!(
            g.check(at(0.25, 0.081, 0.2), 0.02).1.verdict,
            GateVerdict::Accepted
        );
    }

    #[test]
    fn clamps_to_the_workspace_and_slides_along_the_wall() {
        let mut g = gate(&GateConfig::default());
        g.reset_reference(at(0.39, 0.0, 0.2));
        let mut last = None;
        for i in 0..20 {
            // The phone keeps pushing 1 cm per sample past the x = 0.40 wall while moving sideways.
            let (out, d) = g.check(
                at(0.39 + 0.01 * f64::from(i), 0.005 * f64::from(i), 0.2),
                f64::from(i) * 0.02,
            );
            assert!(d.verdict.passed(), "{d:?}");
            last = out;
        }
        let last = last.unwrap();
        assert!((last.translation.x - 0.40).abs() < 1e-15);
        assert!((last.translation.y - 0.095).abs() < 1e-12);
        let (_, d) = g.check(at(0.6, 0.1, 0.2), 0.5);
        assert_eq!(d.verdict, GateVerdict::Clamped);
        assert!(d.workspace_clamped);
        assert_eq!(d.reason, "clamped to workspace on x");
    }

    #[test]
    fn rejects_invalid_targets() {
        let mut g = gate(&GateConfig::default());
        let nan = at(f64::NAN, 0.0, 0.2);
        assert_eq!(g.check(nan, 0.0).1.verdict, GateVerdict::RejectedInvalid);
        let skewed = Isometry3::from_parts(
            Translation3::new(0.25, 0.0, 0.2),
            UnitQuaternion::new_unchecked(Quaternion::new(1.1, 0.0, 0.0, 0.0)),
        );
        let (out, d) = g.check(skewed, 0.0);
        assert!(out.is_none());
        assert!(d.reason.contains("quaternion norm"), "{}", d.reason);
        assert_eq!(
            g.check(at(0.25, 0.0, 0.2), f64::NAN).1.verdict,
            GateVerdict::RejectedInvalid
        );
        assert_eq!(*g.reference(), at(0.25, 0.0, 0.2));
    }

    #[test]
    fn velocity_limits_shorten_steps() {
        let mut g = gate(&GateConfig {
            max_linear_speed_m_s: Some(0.5),
            max_angular_speed_rad_s: Some(1.0),
            ..GateConfig::default()
        });
        g.reset_reference_at(at(0.25, 0.0, 0.2), 0.0);
        let target = Isometry3::from_parts(
            Translation3::new(0.30, 0.0, 0.2),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3),
        );
        let (out, d) = g.check(target, 0.02);
        let out = out.unwrap();
        assert_eq!(d.verdict, GateVerdict::Clamped);
        assert!(d.velocity_limited && !d.workspace_clamped);
        assert!(
            (out.translation.x - 0.26).abs() < 1e-12,
            "0.5 m/s for 20 ms is 1 cm"
        );
        assert!((d.rotation_step_rad - 0.02).abs() < 1e-12, "1 rad/s for 20 ms");
        assert_eq!(
            d.reason,
            "linear speed limited to 0.500 m/s; angular speed limited to 1.000 rad/s"
        );
        // No time elapsed: no motion allowed.
        let (out2, _) = g.check(target, 0.02);
        assert!(pose_distance(&out2.unwrap(), &out).0 < 1e-15);
    }

    fn speed_limited() -> GateConfig {
        GateConfig {
            max_linear_speed_m_s: Some(0.5),
            max_angular_speed_rad_s: Some(1.0),
            ..GateConfig::default()
        }
    }

    #[test]
    fn a_reindex_checked_at_the_same_instant_passes_the_anchor_unchanged() {
        // Teleop re-indexes exactly like this: reset at the measured pose, then check that pose at the same
        // now_s. A zero step in zero time must pass as is; 0/0 in the speed limit would make it NaN.
        let mut g = gate(&speed_limited());
        let anchor = Isometry3::from_parts(
            Translation3::new(0.3, 0.1, 0.2),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        );
        g.reset_reference_at(anchor, 2.0);
        let (out, d) = g.check(anchor, 2.0);
        assert_eq!(out, Some(anchor));
        assert_eq!(d.verdict, GateVerdict::Accepted, "{d:?}");
        assert!(!d.velocity_limited);
        assert_eq!(*g.reference(), anchor);
    }

    #[test]
    fn speed_limits_move_towards_the_target() {
        let mut g = gate(&speed_limited());
        let start = Isometry3::from_parts(
            Translation3::new(0.25, 0.0, 0.2),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.2),
        );
        g.reset_reference_at(start, 0.0);
        let target = Isometry3::from_parts(
            Translation3::new(0.25, -0.05, 0.2),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.5),
        );
        let (out, d) = g.check(target, 0.02);
        let out = out.unwrap();
        assert!(d.velocity_limited);
        // 1 rad/s for 20 ms: 0.02 rad of the 0.3 rad turn, so 0.28 rad remain (not 0.32: the wrong way).
        let turned = angle_between_rad(&start.rotation, &out.rotation);
        let left = angle_between_rad(&out.rotation, &target.rotation);
        assert!((turned - 0.02).abs() < 1e-12, "{turned}");
        assert!((left - 0.28).abs() < 1e-12, "{left}");
        assert!((out.translation.y + 0.01).abs() < 1e-12, "{out:?}");
    }

    #[test]
    fn a_sample_older_than_the_last_one_does_not_move_the_arm() {
        let mut g = gate(&speed_limited());
        g.reset_reference_at(at(0.25, 0.0, 0.2), 1.0);
        let (first, _) = g.check(at(0.30, 0.0, 0.2), 1.02);
        let first = first.unwrap();
        // Out of order by 100 ms: a negative interval would carry the arm 5 cm backwards (0.5 m/s × 0.1 s).
        let (out, d) = g.check(at(0.30, 0.0, 0.2), 0.92);
        assert!(d.velocity_limited);
        assert!(pose_distance(&out.unwrap(), &first).0 < 1e-15, "{out:?}");
    }

    #[test]
    fn a_reset_without_time_allows_the_longest_interval() {
        let mut g = gate(&speed_limited());
        g.check(at(0.26, 0.0, 0.2), 7.0);
        // A reset forgets the time of the last check: a check at that same instant is not a zero interval.
        g.reset_reference(at(0.25, 0.0, 0.2));
        let (out, d) = g.check(at(0.30, 0.0, 0.2), 7.0);
        // 0.5 m/s over MAX_VELOCITY_INTERVAL_S (0.25 s) allows 12.5 cm: the 5 cm step passes whole.
        assert_eq!(d.verdict, GateVerdict::Accepted, "{d:?}");
        assert_eq!(out, Some(at(0.30, 0.0, 0.2)));
    }

    #[test]
    fn the_box_wins_over_the_speed_limit_after_a_reset_outside_it() {
        let mut g = gate(&GateConfig {
            max_linear_speed_m_s: Some(0.5),
            ..GateConfig::default()
        });
        // Measured 2 cm beyond the x wall; re-indexed there at t = 1 s and checked at the same instant.
        g.reset_reference_at(at(0.42, 0.0, 0.2), 1.0);
        let (out, d) = g.check(at(0.42, 0.0, 0.2), 1.0);
        let out = out.unwrap();
        assert!((out.translation.x - 0.40).abs() < 1e-15, "{out:?}");
        assert!(d.workspace_clamped && d.velocity_limited);
        assert_eq!(d.verdict, GateVerdict::Clamped);
    }

    #[test]
    fn staleness_is_reported_once_per_silence() {
        let mut g = gate(&GateConfig::default());
        assert!(
            g.check_stale(100.0).is_none(),
            "nothing is stale before the first command"
        );
        g.check(at(0.25, 0.0, 0.2), 1.0);
        assert!(g.check_stale(1.2).is_none());
        let d = g.check_stale(1.35).unwrap();
        assert_eq!(d.verdict, GateVerdict::HeldStale);
        assert!(d.reason.contains("0.35 s"), "{}", d.reason);
        assert!(g.check_stale(1.5).is_none());
        g.check(at(0.25, 0.0, 0.2), 2.0);
        assert!(!g.is_stale(2.1));
        assert!(g.check_stale(2.4).is_some());
    }

    #[test]
    fn a_reset_restarts_staleness() {
        let mut g = gate(&GateConfig::default());
        g.check(at(0.25, 0.0, 0.2), 1.0);
        assert!(g.check_stale(1.5).is_some());
        // A timed reset is fresh input, and a new silence after it is reported again.
        g.reset_reference_at(at(0.25, 0.0, 0.2), 2.0);
        assert!(!g.is_stale(2.2));
        assert!(g.check_stale(2.5).is_some());
        // An untimed reset: nothing is stale until the next command.
        g.reset_reference(at(0.25, 0.0, 0.2));
        assert!(!g.is_stale(100.0));
        assert!(g.check_stale(100.0).is_none());
    }

    #[test]
    fn limits_are_inclusive() {
        // Thresholds and targets exact in binary, so the comparisons meet on the boundary itself.
        let config = GateConfig {
            jump_position_m: 0.0625,
            stale_timeout_s: 0.25,
            ..GateConfig::default()
        };
        let mut g = gate(&config);
        assert_eq!(g.config(), &config);
        // A step of exactly the jump threshold passes.
        let (out, d) = g.check(at(0.3125, 0.0, 0.2), 1.0);
        assert_eq!(
            (out, d.verdict),
            (Some(at(0.3125, 0.0, 0.2)), GateVerdict::Accepted)
        );
        // Silent for exactly the timeout: not stale yet.
        assert!(!g.is_stale(1.25));
        assert!(g.is_stale(1.5));
        // A turn of exactly the rotation threshold (as the gate measures it) passes too.
        let turned = Isometry3::from_parts(
            Translation3::new(0.25, 0.0, 0.2),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.3),
        );
        let threshold_rad = angle_between_rad(&UnitQuaternion::identity(), &turned.rotation);
        let mut g2 = gate(&GateConfig {
            jump_rotation_rad: threshold_rad,
            ..GateConfig::default()
        });
        assert_eq!(g2.check(turned, 1.0).1.verdict, GateVerdict::Accepted);
        // A target on the walls is inside the box: accepted, not clamped.
        for wall in [at(0.40, 0.25, 0.35), at(0.10, -0.25, 0.02)] {
            g.reset_reference(wall);
            let (out, d) = g.check(wall, 2.0);
            assert_eq!((out, d.verdict), (Some(wall), GateVerdict::Accepted), "{d:?}");
        }
    }

    #[test]
    fn verdicts_say_whether_a_target_passed_or_was_refused() {
        use GateVerdict::{Accepted, Clamped, HeldStale, RejectedInvalid, RejectedJump};
        for (verdict, passed, rejected) in [
            (Accepted, true, false),
            (Clamped, true, false),
            (RejectedJump, false, true),
            (RejectedInvalid, false, true),
            (HeldStale, false, false),
        ] {
            assert_eq!(
                (verdict.passed(), verdict.rejected()),
                (passed, rejected),
                "{verdict:?}"
            );
        }
    }

    /// One proposal of a random walk: a small move, sometimes a large jump, sometimes garbage.
    fn any_move() -> impl Strategy<Value = ([f64; 3], [f64; 3], u8)> {
        (
            prop::array::uniform3(-0.05..0.05f64),
            prop::array::uniform3(-0.3..0.3f64),
            0..30u8,
        )
    }

    fn walk(moves: &[([f64; 3], [f64; 3], u8)]) -> Vec<Isometry3<f64>> {
        let mut pose = at(0.25, 0.0, 0.2);
        moves
            .iter()
            .map(|&(dp, dr, kind)| {
                let scale = if kind < 4 { 10.0 } else { 1.0 };
                pose = Isometry3::from_parts(
                    Translation3::from(pose.translation.vector + Vector3::from(dp) * scale),
                    UnitQuaternion::from_scaled_axis(Vector3::from(dr) * scale) * pose.rotation,
                );
                let mut sent = pose;
                match kind {
                    4 => sent.translation.x = f64::NAN,
                    5 => sent.translation.z = f64::INFINITY,
                    6 => sent.rotation = UnitQuaternion::new_unchecked(pose.rotation.into_inner() * 1.5),
                    _ => {}
                }
                sent
            })
            .collect()
    }

    proptest! {
        /// Whatever arrives, every output is finite, inside the box, and within the jump thresholds of the
        /// previous output (or of the last reset).
        #[test]
        fn outputs_stay_inside_and_never_jump(
            moves in prop::collection::vec(any_move(), 1..80),
            resets in prop::collection::vec(0..60usize, 0..3),
            limited in prop::bool::ANY,
        ) {
            let config = GateConfig {
                max_linear_speed_m_s: limited.then_some(0.8),
                max_angular_speed_rad_s: limited.then_some(3.0),
                ..GateConfig::default()
            };
            let mut g = SafetyGate::new(&config, at(0.25, 0.0, 0.2)).unwrap();
            let mut previous = *g.reference();
            let mut previous_time_s: Option<f64> = None;
            let mut previous_outside = false;
            for (i, target) in walk(&moves).into_iter().enumerate() {
                let now_s = i as f64 * 0.02;
                if resets.contains(&i) {
                    // Every other reset lands outside the box, like a measured pose out there, and is
                    // timed, so the speed limit allows almost nothing on the next step.
                    previous_outside = i % 2 == 1;
                    if previous_outside {
                        previous = at(0.43, 0.1, 0.1);
                        previous_time_s = Some(now_s - 0.001);
                        g.reset_reference_at(previous, now_s - 0.001);
                    } else {
                        previous = at(0.3, 0.1, 0.1);
                        previous_time_s = None;
                        g.reset_reference(previous);
                    }
                }
                let (out, d) = g.check(target, now_s);
                prop_assert_eq!(out.is_some(), d.verdict.passed());
                if let Some(out) = out {
                    let p = out.translation.vector;
                    prop_assert!(p.iter().all(|v| v.is_finite()));
                    prop_assert!(out.rotation.coords.iter().all(|v| v.is_finite()));
                    for axis in 0..3 {
                        prop_assert!(p[axis] >= config.workspace_min_m[axis] && p[axis] <= config.workspace_max_m[axis]);
                    }
                    let (dp, da) = pose_distance(&out, &previous);
                    prop_assert!(dp <= config.jump_position_m + 1e-12, "step {} m", dp);
                    prop_assert!(da <= config.jump_rotation_rad + 1e-12, "step {} rad", da);
                    if limited {
                        let interval_s = previous_time_s.map_or(MAX_VELOCITY_INTERVAL_S, |t| (now_s - t).min(MAX_VELOCITY_INTERVAL_S));
                        // Only a reference outside the box may be left faster than the limit (the box wins).
                        prop_assert!(previous_outside || dp <= 0.8 * interval_s + 1e-12, "{} m in {} s", dp, interval_s);
                        prop_assert!(da <= 3.0 * interval_s + 1e-12, "{} rad in {} s", da, interval_s);
                    }
                    previous = out;
                    previous_time_s = Some(now_s);
                    previous_outside = false;
                }
                prop_assert_eq!(*g.reference(), previous);
            }
        }
    }
}
