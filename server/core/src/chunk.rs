//! Execution schedule of a policy's action chunks.
//!
//! A chunk is `H` steps (target pose, gripper) anchored in time: step `k` owns the window
//! `[anchor_time_s + k·step_period_s, anchor_time_s + (k+1)·step_period_s)`. The anchor is normally the
//! time of the observation the chunk answers, so by the time a chunk arrives its first steps are already in
//! the past: replacing aligns by time and skips them instead of replaying stale steps late. A new chunk
//! replaces whatever the older one still had from the new chunk's first live step on; the older chunk
//! keeps running only before that (a chunk anchored slightly ahead). Optionally the first `N` live steps
//! are blended from the old plan into the new one to avoid a visible kink. Once the schedule runs out,
//! [`ChunkExecutor::target_at`] returns `None` and the arm holds.

use crate::config::ConfigError;
use crate::pose::{PoseError, check_pose};
use nalgebra::{Isometry3, Translation3};
use serde::{Deserialize, Serialize};

const TIME_EPSILON_S: f64 = 1e-9;

/// One step of a chunk: where the end effector should be, and the gripper target (0 open, 1 closed).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
pub struct ChunkStep {
    pub robot_from_target: Isometry3<f64>,
    pub gripper: f64,
}

/// A policy's chunk, already converted from action vectors to targets.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
pub struct ActionChunk {
    pub steps: Vec<ChunkStep>,
    /// Time of step 0 on the caller's clock (s).
    pub anchor_time_s: f64,
    pub step_period_s: f64,
}

/// Limits and blending of the chunk executor.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ChunkConfig {
    /// Number of live steps over which a new chunk is blended in from the old plan (0 = switch at once).
    pub blend_steps: usize,
    /// Longest accepted step period (s); anything slower is a unit mistake (ms sent as s).
    pub max_step_period_s: f64,
    /// Shortest accepted step period (s).
    pub min_step_period_s: f64,
    /// Longest accepted chunk.
    pub max_steps: usize,
    /// How far ahead of now a chunk may be anchored (s); more means a clock mix-up.
    pub max_anchor_lead_s: f64,
    /// How long a policy session may hold the arm while it loads (a `PolicyLoading` message) before its first
    /// chunk (s), counted from its first loading message and never extended by later ones; past it the arm
    /// is released. Generous by default: a large VLA on a cold GPU takes minutes.
    pub max_loading_s: f64,
}

/// The longest `max_loading_s` accepted: an hour. More would let a hung loader keep an arm indefinitely.
pub const MAX_LOADING_LIMIT_S: f64 = 3600.0;

impl Default for ChunkConfig {
    fn default() -> Self {
        Self {
            blend_steps: 0,
            max_step_period_s: 1.0,
            min_step_period_s: 1e-3,
            max_steps: 10_000,
            max_anchor_lead_s: 2.0,
            max_loading_s: 300.0,
        }
    }
}

impl ChunkConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, value) in [
            ("max_step_period_s", self.max_step_period_s),
            ("min_step_period_s", self.min_step_period_s),
            ("max_anchor_lead_s", self.max_anchor_lead_s),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(ConfigError::NotPositive { name, value });
            }
        }
        if self.min_step_period_s >= self.max_step_period_s {
            return Err(ConfigError::NotPositive {
                name: "max_step_period_s - min_step_period_s",
                value: self.max_step_period_s - self.min_step_period_s,
            });
        }
        if !(self.max_loading_s > 0.0 && self.max_loading_s <= MAX_LOADING_LIMIT_S) {
            return Err(ConfigError::OutOfRange {
                name: "max_loading_s",
                min: 0.0,
                max: MAX_LOADING_LIMIT_S,
                value: self.max_loading_s,
            });
        }
        if self.max_steps == 0 {
            return Err(ConfigError::NotPositive {
                name: "max_steps",
                value: 0.0,
            });
        }
        Ok(())
    }
}

/// Why a chunk was refused. A refused chunk changes nothing: the previous schedule keeps running.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChunkError {
    #[error("chunk has no steps")]
    Empty,
    #[error("chunk has {len} steps, more than the limit of {max}")]
    TooLong { len: usize, max: usize },
    #[error("step period {step_period_s} s is outside [{min_s}, {max_s}] s")]
    InvalidStepPeriod {
        step_period_s: f64,
        min_s: f64,
        max_s: f64,
    },
    #[error("anchor time is not finite: {0}")]
    NonFiniteAnchor(f64),
    #[error("current time is not finite: {0}")]
    NonFiniteTime(f64),
    #[error("chunk starts {lead_s:.3} s in the future, more than the limit of {max_s} s")]
    AnchorTooFarAhead { lead_s: f64, max_s: f64 },
    #[error("step {index}: {source}")]
    InvalidStep { index: usize, source: PoseError },
    #[error("step {index}: gripper target is not finite: {value}")]
    NonFiniteGripper { index: usize, value: f64 },
    #[error("all {steps} steps lie in the past (chunk ended {late_s:.3} s ago)")]
    EntirelyInPast { steps: usize, late_s: f64 },
}

/// What [`ChunkExecutor::replace`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
pub struct ReplaceReport {
    /// Steps of the new chunk now on the schedule.
    pub scheduled: usize,
    /// Steps of the new chunk dropped because their window had already ended.
    pub skipped: usize,
    /// Steps of the new chunk blended with the old plan.
    pub blended: usize,
    /// Future steps of the older chunk that the new one replaced.
    pub replaced: usize,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct TimedStep {
    start_s: f64,
    end_s: f64,
    step: ChunkStep,
}

/// A policy's plan from one instant on, read from the schedule in place (see [`ChunkExecutor::plan`]): a
/// display picks a few of its steps without copying the rest.
#[derive(Debug, Clone, Copy)]
pub struct Plan<'a> {
    executor: &'a ChunkExecutor,
    from_s: f64,
    period_s: f64,
    len: usize,
}

impl<'a> Plan<'a> {
    /// Number of steps.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Time between two steps, s (0 when empty).
    pub fn period_s(&self) -> f64 {
        self.period_s
    }

    /// Step `k` (None from [`Self::len`] on).
    pub fn get(&self, k: usize) -> Option<ChunkStep> {
        if k < self.len {
            self.executor.target_at(self.time_s(k))
        } else {
            None
        }
    }

    /// The steps in order.
    pub fn iter(&self) -> impl Iterator<Item = ChunkStep> + 'a {
        let plan = *self;
        (0..plan.len).filter_map(move |k| plan.get(k))
    }

    /// When step `k` plays (multiplied, not accumulated, as the schedule's windows are).
    fn time_s(&self, k: usize) -> f64 {
        self.from_s + k as f64 * self.period_s
    }
}

/// The running schedule of one arm under policy control.
#[derive(Debug, Clone)]
pub struct ChunkExecutor {
    config: ChunkConfig,
    schedule: Vec<TimedStep>,
}

impl ChunkExecutor {
    pub fn new(config: ChunkConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            schedule: Vec::new(),
        })
    }

    pub fn config(&self) -> &ChunkConfig {
        &self.config
    }

    /// Drops the schedule (source change, stop).
    pub fn clear(&mut self) {
        self.schedule.clear();
    }

    /// Time at which the schedule runs out, if anything is scheduled.
    pub fn end_time_s(&self) -> Option<f64> {
        self.schedule.last().map(|s| s.end_s)
    }

    /// Steps whose window has not ended at `now_s` (including the current one).
    pub fn remaining_steps(&self, now_s: f64) -> usize {
        self.schedule.iter().filter(|s| s.end_s > now_s).count()
    }

    /// The plan from `from_s` on, on the time grid of the step playing then: the step at `from_s + k · period`
    /// for k = 0, 1, … while the schedule lasts (at most `max_steps`), and that period. Empty when nothing
    /// plays at `from_s`. What a real-time-chunking policy is told is still to come (see `ActionChunk`'s
    /// `keep_steps` on the wire). Read in place: nothing is copied until a step is asked for.
    pub fn plan(&self, from_s: f64) -> Plan<'_> {
        let mut plan = Plan {
            executor: self,
            from_s,
            period_s: 0.0,
            len: 0,
        };
        let i = self.schedule.partition_point(|s| s.start_s <= from_s);
        let Some(current) = i.checked_sub(1).and_then(|i| self.schedule.get(i)) else {
            return plan;
        };
        if from_s >= current.end_s {
            return plan;
        }
        // A blended or truncated step is shorter; the first full window of the chunk gives its period.
        let period_s = self.schedule[i - 1..]
            .iter()
            .map(|s| s.end_s - s.start_s)
            .fold(0.0, f64::max);
        if period_s <= 0.0 {
            return plan;
        }
        plan.period_s = period_s;
        plan.len = (0..self.config.max_steps)
            .take_while(|&k| self.target_at(plan.time_s(k)).is_some())
            .count();
        plan
    }

    /// [`Self::plan`]'s steps, copied, and its period.
    pub fn plan_from(&self, from_s: f64) -> (Vec<ChunkStep>, f64) {
        let plan = self.plan(from_s);
        (plan.iter().collect(), plan.period_s())
    }

    /// Replaces the rest of the schedule with `chunk`, aligned by time (see the module documentation).
    pub fn replace(&mut self, chunk: ActionChunk, now_s: f64) -> Result<ReplaceReport, ChunkError> {
        self.validate(&chunk, now_s)?;
        let (anchor_s, period_s, len) = (chunk.anchor_time_s, chunk.step_period_s, chunk.steps.len());
        // Multiplied, not accumulated, so long chunks do not drift off their anchor.
        let window = |k: usize| {
            (
                anchor_s + k as f64 * period_s,
                anchor_s + (k + 1) as f64 * period_s,
            )
        };
        let skipped = (0..len).take_while(|&k| window(k).1 <= now_s).count();
        let scheduled = len - skipped;
        if scheduled == 0 {
            return Err(ChunkError::EntirelyInPast {
                steps: len,
                late_s: now_s - window(len - 1).1,
            });
        }
        let new_start_s = window(skipped).0;

        let mut blended = 0;
        let mut new_steps = Vec::with_capacity(scheduled);
        for (i, (k, mut step)) in chunk.steps.into_iter().enumerate().skip(skipped).enumerate() {
            let (start_s, end_s) = window(k);
            if i < self.config.blend_steps {
                // The old plan at the moment this step starts executing (now, for the current step).
                if let Some(old) = self.target_at(start_s.max(now_s)) {
                    let new_weight = (i + 1) as f64 / (self.config.blend_steps + 1) as f64;
                    step = blend(&old, &step, new_weight);
                    blended += 1;
                }
            }
            new_steps.push(TimedStep { start_s, end_s, step });
        }

        // Windows computed from different anchors differ by rounding; an old step starting within a
        // nanosecond of the new chunk's first step is the same slot and is replaced, not kept for 1e-16 s.
        let takeover_s = new_start_s - TIME_EPSILON_S;
        let replaced = self
            .schedule
            .iter()
            .filter(|s| s.end_s > now_s && s.start_s >= takeover_s)
            .count();
        // Keep what the older chunk still has before the new chunk takes over; past steps go.
        self.schedule
            .retain(|s| s.end_s > now_s && s.start_s < takeover_s);
        if let Some(last) = self.schedule.last_mut() {
            last.end_s = last.end_s.min(new_start_s);
        }
        self.schedule.extend(new_steps);
        Ok(ReplaceReport {
            scheduled,
            skipped,
            blended,
            replaced,
        })
    }

    /// The step to execute at `now_s`, or `None` before the schedule starts and after it runs out.
    pub fn target_at(&self, now_s: f64) -> Option<ChunkStep> {
        if !now_s.is_finite() {
            return None;
        }
        let i = self.schedule.partition_point(|s| s.start_s <= now_s);
        let s = self.schedule.get(i.checked_sub(1)?)?;
        (now_s < s.end_s).then_some(s.step)
    }

    fn validate(&self, chunk: &ActionChunk, now_s: f64) -> Result<(), ChunkError> {
        let cfg = &self.config;
        if !now_s.is_finite() {
            return Err(ChunkError::NonFiniteTime(now_s));
        }
        if chunk.steps.is_empty() {
            return Err(ChunkError::Empty);
        }
        if chunk.steps.len() > cfg.max_steps {
            return Err(ChunkError::TooLong {
                len: chunk.steps.len(),
                max: cfg.max_steps,
            });
        }
        let p = chunk.step_period_s;
        if !(p.is_finite() && p >= cfg.min_step_period_s && p <= cfg.max_step_period_s) {
            return Err(ChunkError::InvalidStepPeriod {
                step_period_s: p,
                min_s: cfg.min_step_period_s,
                max_s: cfg.max_step_period_s,
            });
        }
        if !chunk.anchor_time_s.is_finite() {
            return Err(ChunkError::NonFiniteAnchor(chunk.anchor_time_s));
        }
        let lead_s = chunk.anchor_time_s - now_s;
        if lead_s > cfg.max_anchor_lead_s {
            return Err(ChunkError::AnchorTooFarAhead {
                lead_s,
                max_s: cfg.max_anchor_lead_s,
            });
        }
        for (index, step) in chunk.steps.iter().enumerate() {
            check_pose(&step.robot_from_target)
                .map_err(|source| ChunkError::InvalidStep { index, source })?;
            if !step.gripper.is_finite() {
                return Err(ChunkError::NonFiniteGripper {
                    index,
                    value: step.gripper,
                });
            }
        }
        Ok(())
    }
}

/// Linear in position and gripper, spherical in rotation; `new_weight` 0 gives `old`, 1 gives `new`.
fn blend(old: &ChunkStep, new: &ChunkStep, new_weight: f64) -> ChunkStep {
    let (a, b) = (&old.robot_from_target, &new.robot_from_target);
    let position = a.translation.vector.lerp(&b.translation.vector, new_weight);
    // nalgebra takes the short way round and gives up only when the two orientations are within ~1e-9 rad
    // of each other (no well-defined arc): either end is then the answer, switch at the midpoint.
    let rotation = a
        .rotation
        .try_slerp(&b.rotation, new_weight, 1e-9)
        .unwrap_or(if new_weight < 0.5 { a.rotation } else { b.rotation });
    ChunkStep {
        robot_from_target: Isometry3::from_parts(Translation3::from(position), rotation),
        gripper: old.gripper + (new.gripper - old.gripper) * new_weight,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::angle_between_rad;
    use nalgebra::{UnitQuaternion, Vector3};
    use proptest::prelude::*;

    fn step(x: f64) -> ChunkStep {
        ChunkStep {
            robot_from_target: Isometry3::translation(x, 0.0, 0.2),
            gripper: x,
        }
    }

    fn chunk(xs: &[f64], anchor_time_s: f64, step_period_s: f64) -> ActionChunk {
        ActionChunk {
            steps: xs.iter().map(|&x| step(x)).collect(),
            anchor_time_s,
            step_period_s,
        }
    }

    fn x_at(e: &ChunkExecutor, t: f64) -> Option<f64> {
        e.target_at(t).map(|s| s.robot_from_target.translation.x)
    }

    #[test]
    fn steps_follow_the_clock_and_run_out() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        assert_eq!(x_at(&e, 0.0), None);
        let r = e
            .replace(chunk(&[0.0, 0.1, 0.2, 0.3, 0.4], 1.0, 0.1), 1.0)
            .unwrap();
        assert_eq!(
            r,
            ReplaceReport {
                scheduled: 5,
                skipped: 0,
                blended: 0,
                replaced: 0
            }
        );
        assert_eq!(x_at(&e, 0.99), None);
        assert_eq!(x_at(&e, 1.0), Some(0.0));
        assert_eq!(x_at(&e, 1.25), Some(0.2));
        assert_eq!(x_at(&e, 1.49), Some(0.4));
        assert_eq!(x_at(&e, 1.5), None, "the arm holds once the chunk has run out");
        assert_eq!(e.remaining_steps(1.25), 3);
        assert!((e.end_time_s().unwrap() - 1.5).abs() < 1e-12);
    }

    #[test]
    fn the_plan_from_an_instant_is_what_plays_then_on_its_grid() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        assert_eq!(e.plan_from(1.0), (Vec::new(), 0.0), "nothing playing");
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3, 0.4], 1.0, 0.1), 1.0)
            .unwrap();
        let xs = |(steps, _): (Vec<ChunkStep>, f64)| -> Vec<f64> {
            steps.iter().map(|s| s.robot_from_target.translation.x).collect()
        };
        // Mid-step: step 0 is the one playing, then one step per period until the plan ends.
        assert_eq!(xs(e.plan_from(1.25)), [0.2, 0.3, 0.4]);
        assert!((e.plan_from(1.25).1 - 0.1).abs() < 1e-12);
        assert!(e.plan_from(1.5).0.is_empty(), "run out");
        // A chunk answering an observation at 1.25 that repeats that plan as its first steps continues it on
        // its own grid: every target is the old plan's now or one step before, never a value it did not have.
        let mut again = e.clone();
        again
            .replace(chunk(&[0.2, 0.3, 0.4, 0.5], 1.25, 0.1), 1.3)
            .unwrap();
        for t in [1.3, 1.36, 1.44, 1.49] {
            let new = x_at(&again, t);
            assert!(new == x_at(&e, t) || new == x_at(&e, t - 0.1), "{t}: {new:?}");
        }
        assert_eq!(x_at(&again, 1.56), Some(0.5));
    }

    #[test]
    fn a_plan_read_in_place_ends_at_the_first_gap_and_has_nothing_past_its_end() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        assert!(
            e.plan(1.0).is_empty() && e.plan(1.0).period_s() == 0.0,
            "nothing playing"
        );
        e.replace(chunk(&[0.0, 0.1, 0.2], 1.0, 0.1), 1.0).unwrap();
        // Anchored 0.1 s after the first chunk ends: nothing plays in between.
        e.replace(chunk(&[0.5, 0.6], 1.4, 0.1), 1.0).unwrap();
        let plan = e.plan(1.05);
        assert_eq!(plan.len(), 3, "the gap at 1.3 ends the plan");
        let xs: Vec<f64> = plan.iter().map(|s| s.robot_from_target.translation.x).collect();
        assert_eq!(xs, [0.0, 0.1, 0.2]);
        assert_eq!(plan.get(2).map(|s| s.robot_from_target.translation.x), Some(0.2));
        assert_eq!(plan.get(3), None);
        assert_eq!(e.plan_from(1.05), (plan.iter().collect(), plan.period_s()));
        assert!(!e.plan(f64::NAN).iter().any(|_| true), "no time, no plan");
    }

    #[test]
    fn a_late_chunk_skips_its_past_steps_and_replaces_the_rest() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3, 0.4], 1.0, 0.1), 1.0)
            .unwrap();
        // Answers an observation taken at 1.1; arrives at 1.23 (130 ms of inference).
        let r = e
            .replace(chunk(&[1.0, 1.1, 1.2, 1.3, 1.4, 1.5], 1.1, 0.1), 1.23)
            .unwrap();
        assert_eq!(r.skipped, 1);
        assert_eq!(r.scheduled, 5);
        assert_eq!(r.replaced, 3, "old steps 2, 3, 4 were still to come");
        assert_eq!(x_at(&e, 1.23), Some(1.1));
        assert_eq!(x_at(&e, 1.35), Some(1.2));
        assert_eq!(x_at(&e, 1.75), None);
    }

    #[test]
    fn a_chunk_anchored_ahead_lets_the_old_one_finish_first() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3, 0.4], 1.0, 0.1), 1.0)
            .unwrap();
        let r = e.replace(chunk(&[2.0, 2.1], 1.25, 0.05), 1.12).unwrap();
        assert_eq!(
            r,
            ReplaceReport {
                scheduled: 2,
                skipped: 0,
                blended: 0,
                replaced: 2
            }
        );
        assert_eq!(x_at(&e, 1.12), Some(0.1));
        assert_eq!(
            x_at(&e, 1.24),
            Some(0.2),
            "old step 2 is cut short at the new anchor"
        );
        assert_eq!(x_at(&e, 1.25), Some(2.0));
        assert_eq!(x_at(&e, 1.31), Some(2.1));
        assert_eq!(x_at(&e, 1.35), None);
    }

    #[test]
    fn bad_chunks_are_refused_and_change_nothing() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1], 1.0, 0.1), 1.0).unwrap();
        let cases: Vec<(ActionChunk, f64)> = vec![
            (chunk(&[], 1.0, 0.1), 1.0),
            (chunk(&[0.5], 1.0, 0.0), 1.0),
            (chunk(&[0.5], 1.0, -0.1), 1.0),
            (chunk(&[0.5], 1.0, f64::NAN), 1.0),
            (chunk(&[0.5], 1.0, 30.0), 1.0),
            (chunk(&[0.5], f64::INFINITY, 0.1), 1.0),
            (chunk(&[0.5], 60.0, 0.1), 1.0),
            (chunk(&[0.5, 0.6], 0.0, 0.1), 1.0),
            (chunk(&[0.5], 1.0, 0.1), f64::NAN),
            (chunk(&[f64::NAN], 1.0, 0.1), 1.0),
            (chunk(&vec![0.5; 10_001], 1.0, 0.1), 1.0),
        ];
        for (c, now_s) in cases {
            let err = e.replace(c, now_s).unwrap_err();
            assert!(!err.to_string().is_empty());
        }
        let mut skewed = chunk(&[0.5], 1.0, 0.1);
        skewed.steps[0].robot_from_target.rotation =
            UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(2.0, 0.0, 0.0, 0.0));
        assert!(matches!(
            e.replace(skewed, 1.0),
            Err(ChunkError::InvalidStep { index: 0, .. })
        ));
        let mut nan_gripper = chunk(&[0.5], 1.0, 0.1);
        nan_gripper.steps[0].gripper = f64::NAN;
        assert!(matches!(
            e.replace(nan_gripper, 1.0),
            Err(ChunkError::NonFiniteGripper { index: 0, .. })
        ));
        assert!(matches!(
            e.replace(chunk(&[0.5, 0.6], 0.0, 0.1), 1.0),
            Err(ChunkError::EntirelyInPast { steps: 2, .. })
        ));
        assert_eq!(x_at(&e, 1.05), Some(0.0));
        assert_eq!(x_at(&e, 1.15), Some(0.1));
        assert!(
            ChunkExecutor::new(ChunkConfig {
                max_step_period_s: 0.0,
                ..ChunkConfig::default()
            })
            .is_err()
        );
    }

    #[test]
    fn blending_eases_from_the_old_plan_into_the_new_one() {
        let mut e = ChunkExecutor::new(ChunkConfig {
            blend_steps: 3,
            ..ChunkConfig::default()
        })
        .unwrap();
        let turned = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.8);
        let mut old = chunk(&[0.0; 10], 0.0, 0.1);
        for s in &mut old.steps {
            s.gripper = 0.0;
        }
        e.replace(old, 0.0).unwrap();
        let mut new = chunk(&[0.4; 6], 0.2, 0.1);
        for s in &mut new.steps {
            s.robot_from_target.rotation = turned;
            s.gripper = 1.0;
        }
        let r = e.replace(new, 0.2).unwrap();
        assert_eq!(r.blended, 3);
        for (k, w) in [(0, 0.25), (1, 0.5), (2, 0.75), (3, 1.0), (5, 1.0)] {
            let s = e.target_at(0.2 + 0.1 * f64::from(k) + 0.01).unwrap();
            assert!(
                (s.robot_from_target.translation.x - 0.4 * w).abs() < 1e-12,
                "step {k}"
            );
            assert!((s.gripper - w).abs() < 1e-12);
            let angle = angle_between_rad(&UnitQuaternion::identity(), &s.robot_from_target.rotation);
            assert!((angle - 0.8 * w).abs() < 1e-12, "step {k}: {angle}");
        }
        // With nothing left of the old plan there is nothing to blend with.
        e.clear();
        assert_eq!(e.replace(chunk(&[0.4; 3], 5.0, 0.1), 5.0).unwrap().blended, 0);
        assert_eq!(x_at(&e, 5.0), Some(0.4));
    }

    #[test]
    fn configs_with_a_limit_that_is_not_positive_are_refused() {
        for value in [0.0, -0.5, f64::INFINITY, f64::NAN] {
            let configs = [
                ChunkConfig {
                    min_step_period_s: value,
                    ..ChunkConfig::default()
                },
                ChunkConfig {
                    max_step_period_s: value,
                    ..ChunkConfig::default()
                },
                ChunkConfig {
                    max_anchor_lead_s: value,
                    ..ChunkConfig::default()
                },
            ];
            for config in configs {
                assert!(config.validate().is_err(), "{config:?}");
            }
        }
        let inverted = ChunkConfig {
            min_step_period_s: 0.5,
            max_step_period_s: 0.25,
            ..ChunkConfig::default()
        };
        assert_eq!(
            inverted.validate(),
            Err(ConfigError::NotPositive {
                name: "max_step_period_s - min_step_period_s",
                value: -0.25,
            })
        );
        let config = ChunkConfig {
            blend_steps: 2,
            ..ChunkConfig::default()
        };
        assert_eq!(ChunkExecutor::new(config.clone()).unwrap().config(), &config);
    }

    #[test]
    fn a_step_whose_window_ended_is_not_remaining() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        // Windows [1, 1.5) and [1.5, 2), exact in binary.
        e.replace(chunk(&[0.0, 0.1], 1.0, 0.5), 1.0).unwrap();
        assert_eq!(e.remaining_steps(1.0), 2);
        assert_eq!(e.remaining_steps(1.5), 1);
        assert_eq!(e.remaining_steps(2.0), 0);
    }

    #[test]
    fn a_chunk_entirely_in_the_past_says_how_late_it_is() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        // Windows [0, 0.25) and [0.25, 0.5): the last one ended 0.5 s before now = 1.
        assert_eq!(
            e.replace(chunk(&[0.0, 0.1], 0.0, 0.25), 1.0),
            Err(ChunkError::EntirelyInPast {
                steps: 2,
                late_s: 0.5
            })
        );
    }

    #[test]
    fn an_old_step_that_ended_just_now_is_not_counted_as_replaced() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3], 1.0, 0.25), 1.0).unwrap();
        // At 1.5 the old step [1.25, 1.5) has just ended; only [1.5, 1.75) and [1.75, 2) were still to come.
        let r = e.replace(chunk(&[1.0, 1.1], 1.0, 0.75), 1.5).unwrap();
        assert_eq!((r.skipped, r.replaced), (0, 2));
        assert_eq!(x_at(&e, 1.5), Some(1.0));
    }

    #[test]
    fn past_steps_leave_the_schedule() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3], 1.0, 0.25), 1.0).unwrap();
        // At 1.5, [1.25, 1.5) has just ended: it goes, although it starts before the new chunk.
        e.replace(chunk(&[1.0], 1.6, 0.25), 1.5).unwrap();
        assert_eq!(x_at(&e, 1.3), None);
        assert_eq!(x_at(&e, 1.55), Some(0.2));
        assert_eq!(x_at(&e, 1.6), Some(1.0));
    }

    #[test]
    fn an_old_step_a_rounding_error_before_the_new_chunk_is_the_same_slot() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1], 2.0 - TIME_EPSILON_S, 0.25), 1.9)
            .unwrap();
        let r = e.replace(chunk(&[1.0, 1.1], 2.0, 0.25), 1.9).unwrap();
        assert_eq!(r.replaced, 2);
        assert_eq!(
            x_at(&e, 2.0 - TIME_EPSILON_S),
            None,
            "no 1 ns sliver of the old chunk"
        );
        assert_eq!(x_at(&e, 2.0), Some(1.0));
    }

    #[test]
    fn a_chunk_of_exactly_the_step_limit_is_accepted() {
        let mut e = ChunkExecutor::new(ChunkConfig {
            max_steps: 3,
            ..ChunkConfig::default()
        })
        .unwrap();
        assert!(e.replace(chunk(&[0.0; 3], 1.0, 0.1), 1.0).is_ok());
        assert_eq!(
            e.replace(chunk(&[0.0; 4], 1.0, 0.1), 1.0),
            Err(ChunkError::TooLong { len: 4, max: 3 })
        );
    }

    #[test]
    fn clear_stops_the_schedule_at_once() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        e.replace(chunk(&[0.0, 0.1, 0.2, 0.3], 1.0, 0.1), 1.0).unwrap();
        // A source change or stop mid-chunk: the policy must not keep driving until the chunk runs out.
        e.clear();
        assert_eq!(x_at(&e, 1.15), None);
        assert_eq!(e.end_time_s(), None);
        assert_eq!(e.remaining_steps(1.15), 0);
    }

    #[test]
    fn the_anchor_lead_limit_is_inclusive_and_measured_from_now() {
        let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
        // Exactly the 2 s limit ahead (both values exact in binary): accepted.
        assert!(e.replace(chunk(&[0.5], 3.0, 0.1), 1.0).is_ok());
        // 2.5 s ahead of now = 10 s: refused, although 12.5 / 10 or 12.5 - 10.0 * 0 would not be.
        assert!(matches!(
            e.replace(chunk(&[0.5], 12.5, 0.1), 10.0),
            Err(ChunkError::AnchorTooFarAhead { .. })
        ));
        // 1.5 s ahead: accepted (12.5 + 11 would be far beyond the limit).
        assert!(e.replace(chunk(&[0.5], 12.5, 0.1), 11.0).is_ok());
    }

    #[test]
    fn gripper_blending_stays_between_the_two_plans() {
        let mut e = ChunkExecutor::new(ChunkConfig {
            blend_steps: 1,
            ..ChunkConfig::default()
        })
        .unwrap();
        let mut old = chunk(&[0.0; 10], 0.0, 0.1);
        for s in &mut old.steps {
            s.gripper = 0.6;
        }
        e.replace(old, 0.0).unwrap();
        let mut new = chunk(&[0.2; 4], 0.2, 0.1);
        for s in &mut new.steps {
            s.gripper = 1.0;
        }
        e.replace(new, 0.2).unwrap();
        // Half way from 0.6 to 1.0 on the one blended step, then the new plan.
        let g = e.target_at(0.25).unwrap().gripper;
        assert!((g - 0.8).abs() < 1e-12, "{g}");
        assert!((e.target_at(0.35).unwrap().gripper - 1.0).abs() < 1e-12);
    }

    proptest! {
        /// After any sequence of replacements, the step executed at time t is the newest chunk's step
        /// floor((t − anchor)/period) wherever that chunk covers t, and nothing is executed after the end.
        #[test]
        fn the_newest_chunk_owns_its_time(
            chunks in prop::collection::vec((1..40usize, -0.5..0.3f64, 0.01..0.2f64, 0.0..0.3f64), 1..6),
        ) {
            let mut e = ChunkExecutor::new(ChunkConfig::default()).unwrap();
            let mut now_s = 10.0;
            let mut newest: Option<(f64, f64, usize, usize)> = None;
            for (c, (len, anchor_offset, period, advance)) in chunks.into_iter().enumerate() {
                now_s += advance;
                let anchor = now_s + anchor_offset;
                let xs: Vec<f64> = (0..len).map(|k| (c * 1000 + k) as f64).collect();
                match e.replace(chunk(&xs, anchor, period), now_s) {
                    Ok(r) => {
                        prop_assert_eq!(r.scheduled + r.skipped, len);
                        newest = Some((anchor, period, len, c));
                    }
                    Err(ChunkError::EntirelyInPast { .. }) => {
                        prop_assert!(anchor + len as f64 * period <= now_s + 1e-9);
                    }
                    Err(other) => prop_assert!(false, "unexpected {}", other),
                }
            }
            let Some((anchor, period, len, c)) = newest else { return Ok(()) };
            for i in 0..50 {
                let t = now_s + f64::from(i) * 0.013;
                let got = x_at(&e, t);
                let k = ((t - anchor) / period).floor();
                if t >= anchor && k < len as f64 {
                    // Exactly on a window edge the float floor may pick either neighbour.
                    let fract = ((t - anchor) / period).fract();
                    let on_edge = !(1e-9..=1.0 - 1e-9).contains(&fract);
                    let got = got.unwrap();
                    let expected = (c * 1000) as f64 + k;
                    prop_assert!((got - expected).abs() < 1e-9 || (on_edge && ((got - expected).abs() - 1.0).abs() < 1e-9), "t {} got {} expected {}", t, got, expected);
                } else if t >= anchor + len as f64 * period + 1e-9 {
                    prop_assert_eq!(got, None);
                }
            }
        }
    }
}
