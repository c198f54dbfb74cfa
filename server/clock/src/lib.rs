//! The process's one monotonic clock. Every `*_time_ns` a phone2act process produces (camera frames, bridge
//! feedback, arm commands, recorder ticks, gateway stamps) is nanoseconds since one epoch read here, so any
//! two of them can be subtracted. Pure code takes time as an argument (`phone2act-core` reads no clock);
//! the edges read it here and nowhere else (`clippy.toml` refuses `Instant::now` in the core).

use std::sync::OnceLock;
use std::time::Instant;

/// A monotonic clock in nanoseconds: what a component that stamps times is handed (tests hand it a fake).
pub type ClockFn = fn() -> i64;

static EPOCH: OnceLock<Instant> = OnceLock::new();

/// Nanoseconds since the process epoch (fixed by the first read), on a monotonic clock.
pub fn monotonic_ns() -> i64 {
    let epoch = EPOCH.get_or_init(Instant::now);
    i64::try_from(epoch.elapsed().as_nanos()).unwrap_or(i64::MAX)
}

/// [`monotonic_ns`] in seconds: the time the pure core is handed.
pub fn monotonic_s() -> f64 {
    monotonic_ns() as f64 * 1e-9
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_are_the_same_clock_as_nanoseconds() {
        let before_ns = monotonic_ns();
        let s = monotonic_s();
        let after_ns = monotonic_ns();
        // f64 holds the nanoseconds of a process younger than 104 days exactly; a read in between lies between.
        assert!(
            before_ns as f64 * 1e-9 <= s && s <= after_ns as f64 * 1e-9,
            "{before_ns} {s} {after_ns}"
        );
    }

    #[test]
    fn readings_move_forward_by_the_time_that_passed_on_every_thread() {
        let a = monotonic_ns();
        std::thread::sleep(std::time::Duration::from_millis(2));
        // Another thread reads the same epoch, not one of its own.
        let b = std::thread::spawn(monotonic_ns).join().unwrap();
        // A sleep of 2 ms lasts at least 2 ms on any machine, loaded or not; a second epoch fixed by the
        // other thread's first read would put `b` near zero.
        assert!(b - a >= 2_000_000, "{a} then {b}");
    }
}
