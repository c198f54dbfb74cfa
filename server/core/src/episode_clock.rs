//! The episode time limit and the reset period between episodes (LeRobot's `episode_time_s` /
//! `reset_time_s`), as a state machine fed with what the recorder reports and the time: no clock reads, no
//! I/O. The server's shell calls [`EpisodeClock::observe`] on every recorder change and a few times a second,
//! and carries out the [`Step`]s it returns.
//!
//! - An episode is timed by its *recorded* length (frames / fps, so paused ticks do not count): at the limit
//!   the clock asks for a save, once.
//! - After any save (the limit's, or the operator's Stop), a reset period of `reset_time_s` begins: the clock
//!   asks for the scenes to be reset and, at its end, for the next episode if `auto_start` is set (as
//!   lerobot's record loop goes on to the next episode). A discard starts no reset period.
//! - An episode started during a reset period (the operator cuts it short) ends the period.

/// The configured limits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeLimits {
    /// Save an episode when its recorded length reaches this.
    pub episode_time_s: Option<f64>,
    /// Time between a save and the next episode, in which nothing is recorded and scenes reset.
    pub reset_time_s: Option<f64>,
    /// Start the next episode (same task and operator) when the reset period ends.
    pub auto_start: bool,
}

impl EpisodeLimits {
    /// Whether any limit is set (without one the clock never acts).
    pub fn any(&self) -> bool {
        self.episode_time_s.is_some() || self.reset_time_s.is_some()
    }
}

/// What the recorder reports, as the clock needs it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observed {
    /// An episode is in progress (recording, paused, or being saved).
    pub recording: bool,
    /// The episode's recorded length.
    pub duration_s: f64,
    /// Episodes saved so far (a save shows as this growing when the episode ends).
    pub episodes_saved: u64,
}

/// The clock's phase, as the operator sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ClockPhase {
    Idle,
    Recording,
    /// Between a save and the next episode, until `until_ns`.
    Resetting {
        until_ns: i64,
    },
}

/// What the shell must do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// Save the episode in progress (as the operator's Stop does, without an outcome).
    SaveEpisode,
    /// Reset the scenes (a simulated arm's scene re-draws itself; hardware has none).
    ResetScenes,
    /// Start the next episode with the previous one's task and operator.
    StartNext,
}

/// The state machine.
#[derive(Clone, Debug)]
pub struct EpisodeClock {
    limits: EpisodeLimits,
    phase: ClockPhase,
    saved: Option<u64>,
    save_asked: bool,
    /// The recorded length last seen: a shorter one is a new take (a re-record), which gets its own limit.
    last_duration_s: f64,
    /// The reset period is over and the next episode was asked for: the period is shown until it records (so
    /// a phone sees the reset end as the next episode's start), or ends idle if it did not start.
    start_asked: bool,
}

impl EpisodeClock {
    pub fn new(limits: EpisodeLimits) -> Self {
        Self {
            limits,
            phase: ClockPhase::Idle,
            saved: None,
            save_asked: false,
            last_duration_s: 0.0,
            start_asked: false,
        }
    }

    pub fn limits(&self) -> EpisodeLimits {
        self.limits
    }

    pub fn phase(&self) -> ClockPhase {
        self.phase
    }

    /// Takes the recorder's state at `now_ns` and returns what to do (at most one step).
    pub fn observe(&mut self, obs: Observed, now_ns: i64) -> Option<Step> {
        let saved_before = self.saved.replace(obs.episodes_saved);
        match (self.phase, obs.recording) {
            (ClockPhase::Idle | ClockPhase::Resetting { .. }, true) => {
                self.phase = ClockPhase::Recording;
                self.save_asked = false;
                self.last_duration_s = 0.0;
                self.start_asked = false;
                self.limit_step(obs)
            }
            (ClockPhase::Recording, true) => self.limit_step(obs),
            (ClockPhase::Recording, false) => {
                let was_saved = saved_before.is_some_and(|s| obs.episodes_saved > s);
                match self.limits.reset_time_s {
                    Some(reset_s) if was_saved => {
                        self.phase = ClockPhase::Resetting {
                            until_ns: now_ns.saturating_add((reset_s * 1e9) as i64),
                        };
                        Some(Step::ResetScenes)
                    }
                    _ => {
                        self.phase = ClockPhase::Idle;
                        None
                    }
                }
            }
            (ClockPhase::Resetting { until_ns }, false) if now_ns >= until_ns => {
                if self.limits.auto_start && !self.start_asked {
                    self.start_asked = true;
                    return Some(Step::StartNext);
                }
                self.phase = ClockPhase::Idle;
                self.start_asked = false;
                None
            }
            (ClockPhase::Resetting { .. } | ClockPhase::Idle, false) => None,
        }
    }

    fn limit_step(&mut self, obs: Observed) -> Option<Step> {
        if obs.duration_s < self.last_duration_s {
            self.save_asked = false;
        }
        self.last_duration_s = obs.duration_s;
        let limit = self.limits.episode_time_s?;
        if obs.duration_s >= limit && !self.save_asked {
            self.save_asked = true;
            return Some(Step::SaveEpisode);
        }
        None
    }

    /// Seconds left of the episode's limit (recording) or of the reset period (resetting); `None` when no
    /// limit applies now.
    pub fn remaining_s(&self, obs: Observed, now_ns: i64) -> Option<f64> {
        // The recorder's state decides what counts down: the clock is fed that state a moment later, and a
        // status read right after a Start must already count the new episode down.
        if obs.recording {
            return self.limits.episode_time_s.map(|l| (l - obs.duration_s).max(0.0));
        }
        match self.phase {
            ClockPhase::Resetting { until_ns } => Some(((until_ns - now_ns) as f64 / 1e9).max(0.0)),
            _ => None,
        }
    }

    /// Whether a reset period shows now: the clock is in one and the recorder has not started the next
    /// episode (an operator may cut the period short before the clock is fed that).
    pub fn resetting(&self, obs: Observed) -> bool {
        !obs.recording && matches!(self.phase, ClockPhase::Resetting { .. })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: i64 = 1_000_000_000;

    fn obs(recording: bool, duration_s: f64, episodes_saved: u64) -> Observed {
        Observed {
            recording,
            duration_s,
            episodes_saved,
        }
    }

    fn limits(episode: Option<f64>, reset: Option<f64>, auto_start: bool) -> EpisodeLimits {
        EpisodeLimits {
            episode_time_s: episode,
            reset_time_s: reset,
            auto_start,
        }
    }

    #[test]
    fn the_limit_saves_once_then_resets_then_starts_the_next() {
        let mut c = EpisodeClock::new(limits(Some(10.0), Some(3.0), true));
        assert_eq!(c.observe(obs(false, 0.0, 0), 0), None);
        assert_eq!(c.observe(obs(true, 0.0, 0), S), None);
        assert_eq!(c.remaining_s(obs(true, 4.0, 0), 5 * S), Some(6.0));
        assert_eq!(c.observe(obs(true, 9.95, 0), 11 * S), None);
        assert_eq!(c.observe(obs(true, 10.0, 0), 11 * S), Some(Step::SaveEpisode));
        // Asked once: the save takes a while and the recorder still reports the episode meanwhile.
        assert_eq!(c.observe(obs(true, 10.0, 0), 11 * S + 1), None);
        assert_eq!(c.observe(obs(false, 0.0, 1), 12 * S), Some(Step::ResetScenes));
        assert_eq!(c.phase(), ClockPhase::Resetting { until_ns: 15 * S });
        assert_eq!(c.remaining_s(obs(false, 0.0, 1), 13 * S), Some(2.0));
        assert_eq!(c.observe(obs(false, 0.0, 1), 15 * S - 1), None);
        assert_eq!(c.observe(obs(false, 0.0, 1), 15 * S), Some(Step::StartNext));
        // Shown as the reset (0 s left) until the next episode records: no idle moment in between.
        assert_eq!(c.phase(), ClockPhase::Resetting { until_ns: 15 * S });
        assert_eq!(c.remaining_s(obs(false, 0.0, 1), 15 * S), Some(0.0));
        // The next episode gets its own limit.
        assert_eq!(c.observe(obs(true, 0.05, 1), 16 * S), None);
        assert_eq!(c.observe(obs(true, 10.0, 1), 26 * S), Some(Step::SaveEpisode));
    }

    #[test]
    fn an_operator_stop_also_starts_a_reset_and_a_discard_does_not() {
        let mut c = EpisodeClock::new(limits(None, Some(2.0), false));
        c.observe(obs(false, 0.0, 4), 0);
        c.observe(obs(true, 0.0, 4), S);
        assert_eq!(c.remaining_s(obs(true, 1.0, 4), 2 * S), None, "no episode limit");
        assert_eq!(c.observe(obs(false, 0.0, 5), 3 * S), Some(Step::ResetScenes));
        // Without auto_start the period ends idle.
        assert_eq!(c.observe(obs(false, 0.0, 5), 5 * S), None);
        assert_eq!(c.phase(), ClockPhase::Idle);
        c.observe(obs(true, 0.0, 5), 6 * S);
        assert_eq!(
            c.observe(obs(false, 0.0, 5), 7 * S),
            None,
            "discarded: nothing saved"
        );
        assert_eq!(c.phase(), ClockPhase::Idle);
    }

    #[test]
    fn a_next_episode_that_does_not_start_ends_the_reset_idle() {
        let mut c = EpisodeClock::new(limits(None, Some(1.0), true));
        c.observe(obs(true, 0.0, 0), 0);
        c.observe(obs(false, 0.0, 1), S);
        assert_eq!(c.observe(obs(false, 0.0, 1), 2 * S), Some(Step::StartNext));
        // The start failed (the shell observes again after carrying it out): idle, asked only once.
        assert_eq!(c.observe(obs(false, 0.0, 1), 2 * S + 1), None);
        assert_eq!(c.phase(), ClockPhase::Idle);
        assert_eq!(c.observe(obs(false, 0.0, 1), 3 * S), None);
    }

    #[test]
    fn a_retake_seen_only_as_a_shorter_episode_gets_its_own_limit() {
        let mut c = EpisodeClock::new(limits(Some(2.0), None, false));
        c.observe(obs(true, 0.0, 0), 0);
        assert_eq!(c.observe(obs(true, 2.0, 0), 2 * S), Some(Step::SaveEpisode));
        // The save did not happen (the operator re-recorded at that moment); the new take starts over.
        assert_eq!(c.observe(obs(true, 0.1, 0), 3 * S), None);
        assert_eq!(c.observe(obs(true, 2.0, 0), 5 * S), Some(Step::SaveEpisode));
    }

    #[test]
    fn starting_during_the_reset_cuts_it_short() {
        let mut c = EpisodeClock::new(limits(Some(5.0), Some(10.0), true));
        c.observe(obs(true, 0.0, 0), 0);
        c.observe(obs(false, 0.0, 1), S);
        assert!(matches!(c.phase(), ClockPhase::Resetting { .. }));
        assert_eq!(c.observe(obs(true, 0.0, 1), 2 * S), None);
        assert_eq!(c.phase(), ClockPhase::Recording);
        // The old period's end asks for nothing.
        assert_eq!(c.observe(obs(true, 1.0, 1), 11 * S), None);
    }

    #[test]
    fn paused_time_does_not_count_and_without_limits_nothing_happens() {
        let mut c = EpisodeClock::new(limits(Some(2.0), None, true));
        c.observe(obs(true, 0.0, 0), 0);
        // A minute of wall time with only 1.5 s recorded (the episode was paused): not at the limit.
        assert_eq!(c.observe(obs(true, 1.5, 0), 60 * S), None);
        assert_eq!(c.remaining_s(obs(true, 1.5, 0), 60 * S), Some(0.5));
        assert_eq!(
            c.observe(obs(false, 0.0, 1), 61 * S),
            None,
            "no reset period configured"
        );
        let mut none = EpisodeClock::new(limits(None, None, false));
        assert!(!none.limits().any());
        for t in 0..5 {
            assert_eq!(none.observe(obs(t % 2 == 0, 100.0, t as u64), t * S), None);
        }
    }

    /// A status read between a Start and the clock's next look at the recorder counts the episode down, and
    /// one read after a start that cut a reset period short shows no reset.
    #[test]
    fn the_countdown_follows_the_recorder_before_the_clock_has_seen_it() {
        let mut clock = EpisodeClock::new(limits(Some(10.0), Some(3.0), false));
        assert_eq!(clock.remaining_s(obs(true, 0.5, 0), 0), Some(9.5));
        assert!(!clock.resetting(obs(true, 0.5, 0)));
        clock.observe(obs(true, 1.0, 0), S);
        clock.observe(obs(false, 2.0, 1), 2 * S);
        assert!(clock.resetting(obs(false, 2.0, 1)));
        assert_eq!(clock.remaining_s(obs(false, 2.0, 1), 3 * S), Some(2.0));
        // The operator starts during the reset period, before the clock looks again.
        assert_eq!(clock.remaining_s(obs(true, 0.0, 1), 3 * S), Some(10.0));
        assert!(!clock.resetting(obs(true, 0.0, 1)));
    }
}
