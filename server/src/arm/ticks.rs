//! The tick loop: one task per arm, woken only while its arbiter has work.

use super::ArmController;
use phone2act_clock::monotonic_s;
use phone2act_core::TickNeed;
use std::sync::Arc;
use std::time::Duration;

/// Runs every arm's tick task until shutdown.
pub async fn run_ticks(
    arms: Vec<Arc<ArmController>>,
    rate_hz: f64,
    shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let period = Duration::from_secs_f64(1.0 / rate_hz);
    let tasks: Vec<_> = arms
        .into_iter()
        .map(|arm| tokio::spawn(tick_arm(arm, period, shutdown.clone())))
        .collect();
    for task in tasks {
        let _ = task.await;
    }
}

/// Ticks one arm only while its arbiter has work: at `period` while a chunk plays, a phone drives or the joint
/// stage catches up; once at the arbiter's deadline while a policy owns the arm between chunks (its silence
/// timeout or loading deadline), or earlier if an input changes what the arbiter needs; and not at all when
/// idle (it sleeps until an input wakes it).
async fn tick_arm(
    arm: Arc<ArmController>,
    period: Duration,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        // `notify_one` keeps a permit when nobody waits, so a wake between reading the need and waiting
        // below is not lost.
        match arm.tick_need() {
            TickNeed::Periodic => {
                tokio::select! {
                    _ = ticker.tick() => {}
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
            TickNeed::At(deadline_s) => {
                // The arbiter's rules are "later than" the deadline; the timer's millisecond rounding up gets
                // there, and a tick that comes too early only finds the same deadline again.
                let left_s = deadline_s - monotonic_s();
                let wait = Duration::try_from_secs_f64(left_s).unwrap_or(if left_s > 0.0 {
                    Duration::MAX
                } else {
                    Duration::ZERO
                });
                tokio::select! {
                    () = tokio::time::sleep(wait) => {}
                    // An input changed the need (a chunk, a new deadline, a release): read it again.
                    () = arm.wake.notified() => continue,
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
            TickNeed::Idle => {
                tokio::select! {
                    () = arm.wake.notified() => {}
                    () = crate::runtime::stopped(&mut shutdown) => return,
                }
            }
        }
        arm.tick(monotonic_s());
    }
}
