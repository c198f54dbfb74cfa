//! The recorder's timeline, pure (no threads, no clock reads): frame i of an episode stands for the instant
//! `first_tick + i / fps`, and holds what the sources had captured by then, whenever the tick thread gets
//! round to writing it.
//!
//! Sources keep their recent samples with their capture times in a bounded [`TimedRing`]; a tick takes the
//! newest sample captured at or before its own time ([`TimedRing::pick`]), never one captured later. Taking
//! the sample at or before rather than interpolating between the two that bracket the tick: every recorded
//! value was measured (a gripper's open/closed, a success flag, a rotation vector near ±π cannot be averaged
//! into something true), the frame shows what a policy would have seen at that instant (the newest sample,
//! as the live observation does), and the tick can be written as soon as its time has passed instead of
//! waiting for the next sample. The price is the age of the sample, at most one source period (5 ms for the
//! simulator, 33 ms for a 30 fps camera), which [`judge`] bounds by the tolerance.
//!
//! See `docs/recorder-timeline.md`.

use std::collections::VecDeque;

/// The last `capacity` samples of one source, oldest first, each with its capture time. Memory is bounded
/// by `capacity` samples, whatever the source's rate.
#[derive(Debug, Clone)]
pub struct TimedRing<T> {
    samples: VecDeque<(i64, T)>,
    capacity: usize,
}

/// What a ring holds for an instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pick<'a, T> {
    /// The newest sample captured at or before the instant.
    AtOrBefore { time_ns: i64, sample: &'a T },
    /// Every sample still held was captured after the instant: the ones before it were evicted (the
    /// reader fell more than the ring's span behind) or the source had sent nothing yet.
    After { time_ns: i64, sample: &'a T },
    /// Nothing captured yet.
    Empty,
}

impl<T> TimedRing<T> {
    /// An empty ring of `capacity` samples (at least one).
    pub fn new(capacity: usize) -> Self {
        TimedRing {
            samples: VecDeque::with_capacity(capacity.max(1)),
            capacity: capacity.max(1),
        }
    }

    /// Adds a sample captured at `time_ns`, evicting the oldest when full. A sample not newer than the newest
    /// held is refused (the same feedback read twice, or a source whose clock went back): the ring stays in
    /// capture order. Returns whether it was added.
    pub fn push(&mut self, time_ns: i64, sample: T) -> bool {
        if self.samples.back().is_some_and(|(t, _)| *t >= time_ns) {
            return false;
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back((time_ns, sample));
        true
    }

    /// The sample for the instant `t_ns` (see [`Pick`]).
    pub fn pick(&self, t_ns: i64) -> Pick<'_, T> {
        let after = self.samples.partition_point(|(t, _)| *t <= t_ns);
        if after > 0 {
            let (time_ns, sample) = &self.samples[after - 1];
            Pick::AtOrBefore {
                time_ns: *time_ns,
                sample,
            }
        } else if let Some((time_ns, sample)) = self.samples.front() {
            Pick::After {
                time_ns: *time_ns,
                sample,
            }
        } else {
            Pick::Empty
        }
    }

    /// The newest sample and its capture time.
    pub fn newest(&self) -> Option<(i64, &T)> {
        self.samples.back().map(|(t, s)| (*t, s))
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether the ring holds nothing.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The most samples it holds.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Drops every sample but the newest (a parked source keeps its last frame, not its history).
    pub fn keep_newest(&mut self) {
        while self.samples.len() > 1 {
            self.samples.pop_front();
        }
    }
}

/// How a tick's sample stands to the tick's own time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// Captured at or before the tick, within the tolerance: the frame holds the source at its time.
    OnTime,
    /// Recorded, but captured farther than the tolerance from the tick (a source that skipped samples, or a
    /// tick written after the ring had evicted its time): counted as a late tick, and an event.
    Late { off_ns: i64 },
    /// Nothing captured within the hold tolerance before the tick, and nothing to stand in: the source is
    /// gone; the episode pauses.
    Stale { age_ns: Option<i64> },
}

/// Judges `pick` for the tick at `tick_ns`: on time when captured at or before it within `tolerance_ns`;
/// late (still recorded) beyond that up to `hold_ns` before, or when only a later sample remains; stale
/// beyond `hold_ns`.
pub fn judge<T>(pick: &Pick<'_, T>, tick_ns: i64, tolerance_ns: i64, hold_ns: i64) -> Timing {
    match *pick {
        Pick::AtOrBefore { time_ns, .. } => {
            let age_ns = tick_ns - time_ns;
            if age_ns <= tolerance_ns {
                Timing::OnTime
            } else if age_ns <= hold_ns {
                Timing::Late { off_ns: age_ns }
            } else {
                Timing::Stale { age_ns: Some(age_ns) }
            }
        }
        // The sample that was current at the tick was evicted: the oldest one held is the closest known, and
        // writing it keeps every later frame at its own time, where skipping the tick would shift them all.
        // It is from the tick's future, so late however close.
        Pick::After { time_ns, .. } => Timing::Late {
            off_ns: time_ns - tick_ns,
        },
        Pick::Empty => Timing::Stale { age_ns: None },
    }
}

/// The tick grid: tick i at `origin_ns + i * 1e9 / fps`, computed from the origin every time (no drift from
/// adding a rounded period).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TickClock {
    origin_ns: i64,
    fps: u32,
}

impl TickClock {
    pub fn new(origin_ns: i64, fps: u32) -> Self {
        TickClock {
            origin_ns,
            fps: fps.max(1),
        }
    }

    /// The time of tick `i`.
    pub fn time_ns(&self, i: u64) -> i64 {
        self.origin_ns + (i128::from(i) * 1_000_000_000 / i128::from(self.fps)) as i64
    }

    /// How many ticks (from tick 0) have times at or before `t_ns`: the ticks `0..ticks_through(t)` are due
    /// once the clock reads `t`. Exactly the ticks whose (floored) [`Self::time_ns`] is at most `t_ns`.
    pub fn ticks_through(&self, t_ns: i64) -> u64 {
        if t_ns < self.origin_ns {
            return 0;
        }
        // floor(i * 1e9 / fps) <= e  <=>  i * 1e9 < (e + 1) * fps.
        let e = i128::from(t_ns - self.origin_ns);
        ((e + 1) * i128::from(self.fps) - 1) as u64 / 1_000_000_000 + 1
    }

    /// The first tick at or after `t_ns`.
    pub fn first_at_or_after(&self, t_ns: i64) -> u64 {
        self.ticks_through(t_ns - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    fn ring(times_ms: &[i64]) -> TimedRing<i64> {
        let mut r = TimedRing::new(4);
        for &t in times_ms {
            r.push(t * MS, t);
        }
        r
    }

    #[test]
    fn pick_takes_the_newest_sample_at_or_before_never_a_later_one() {
        let r = ring(&[10, 20, 30]);
        let at = |t_ms| match r.pick(t_ms * MS) {
            Pick::AtOrBefore { sample, .. } => Some(*sample),
            _ => None,
        };
        assert_eq!(
            at(20),
            Some(20),
            "a sample captured exactly at the tick is the tick's"
        );
        assert_eq!(
            at(29),
            Some(20),
            "29 ms: the 30 ms sample is in the tick's future"
        );
        assert_eq!(at(1000), Some(30));
        assert!(matches!(r.pick(5 * MS), Pick::After { sample: &10, .. }));
        assert!(matches!(TimedRing::<i64>::new(3).pick(0), Pick::Empty));
    }

    #[test]
    fn the_ring_is_bounded_and_refuses_samples_out_of_order() {
        let mut r = ring(&[10, 20, 30, 40, 50]);
        assert_eq!((r.len(), r.capacity()), (4, 4));
        assert!(
            matches!(r.pick(15 * MS), Pick::After { sample: &20, .. }),
            "10 was evicted"
        );
        assert!(!r.push(50 * MS, 99), "the same capture time again");
        assert!(!r.push(45 * MS, 99), "older than the newest");
        assert_eq!(r.newest(), Some((50 * MS, &50)));
        r.keep_newest();
        assert_eq!(r.len(), 1);
    }

    #[test]
    fn judge_separates_on_time_late_and_stale() {
        let r = ring(&[0, 100]);
        let tol = 30 * MS;
        let hold = 250 * MS;
        let j = |t_ms: i64| judge(&r.pick(t_ms * MS), t_ms * MS, tol, hold);
        assert_eq!(j(100), Timing::OnTime);
        assert_eq!(j(130), Timing::OnTime, "age exactly the tolerance");
        assert_eq!(j(131), Timing::Late { off_ns: 31 * MS });
        assert_eq!(j(350), Timing::Late { off_ns: 250 * MS });
        assert_eq!(
            j(351),
            Timing::Stale {
                age_ns: Some(251 * MS)
            }
        );
        let evicted = ring(&[500, 510]);
        assert_eq!(
            judge(&evicted.pick(400 * MS), 400 * MS, tol, hold),
            Timing::Late { off_ns: 100 * MS }
        );
        assert_eq!(
            judge(&evicted.pick(499 * MS), 499 * MS, tol, hold),
            Timing::Late { off_ns: MS },
            "a sample from the tick's future is late however close"
        );
        assert_eq!(
            judge(&TimedRing::<i64>::new(1).pick(0), 0, tol, hold),
            Timing::Stale { age_ns: None }
        );
    }

    #[test]
    fn tick_times_do_not_drift_and_due_ticks_are_counted_exactly() {
        let c = TickClock::new(1_000, 30);
        // 1e9 / 30 is not whole: added up it would drift by 10 ns per tick.
        assert_eq!(c.time_ns(30), 1_000 + 1_000_000_000);
        assert_eq!(c.time_ns(3_000), 1_000 + 100_000_000_000);
        assert_eq!(c.ticks_through(999), 0);
        assert_eq!(c.ticks_through(1_000), 1);
        assert_eq!(c.ticks_through(c.time_ns(7) - 1), 7);
        assert_eq!(c.ticks_through(c.time_ns(7)), 8);
        assert_eq!(c.first_at_or_after(c.time_ns(7)), 7);
        assert_eq!(c.first_at_or_after(c.time_ns(7) + 1), 8);
        assert_eq!(c.first_at_or_after(0), 0);
        for i in 0..1000 {
            assert_eq!(c.ticks_through(c.time_ns(i)), i + 1);
            assert_eq!(c.ticks_through(c.time_ns(i) - 1), i);
        }
    }

    /// The failure this module exists for, replayed without threads: a source sampled every 5 ms on a
    /// known trajectory, a tick thread that wakes 150 ms late and writes the three ticks it missed at once.
    /// Each tick still gets the state at its own time; taking the newest sample at wake-up (what a recorder
    /// without a timeline does) gives all three the state at the wake-up.
    #[test]
    fn a_late_wake_up_still_records_each_tick_at_its_own_time() {
        let trajectory = |t_ns: i64| (t_ns as f64 * 1e-9 * 3.0).sin();
        let mut r = TimedRing::new(512);
        for k in 0..=80 {
            r.push(k * 5 * MS, trajectory(k * 5 * MS));
        }
        let clock = TickClock::new(0, 20);
        let wake_ns = 400 * MS; // ticks 5, 6, 7 (250, 300, 350 ms) were due and missed
        for i in 5..clock.ticks_through(wake_ns - 50 * MS) {
            let tick_ns = clock.time_ns(i);
            let pick = r.pick(tick_ns);
            assert_eq!(judge(&pick, tick_ns, 10 * MS, 250 * MS), Timing::OnTime);
            let Pick::AtOrBefore { sample, time_ns } = pick else {
                panic!("tick {i}: {pick:?}")
            };
            assert!(tick_ns - time_ns < 5 * MS);
            assert!((sample - trajectory(tick_ns)).abs() < 3.0 * 0.005, "tick {i}");
            let (_, newest) = r.newest().unwrap();
            assert!(
                (newest - trajectory(tick_ns)).abs() > 0.05 || i == 7,
                "the newest sample would have been wrong by more for tick {i}"
            );
        }
    }
}
