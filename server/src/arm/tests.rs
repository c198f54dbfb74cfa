//! The arm shell's own tests: a real simulator bridge and the tick task on a real tokio runtime.

use super::*;
use phone2act_bridges::Health;
use phone2act_bridges::sim::{SimBridge, SimConfig};
use phone2act_core::BridgeHealth;
use std::time::{Duration, Instant};

#[derive(Debug)]
struct Nobody;

impl RevocationSink for Nobody {
    fn revoked(&self, _: &str, _: &str) {}
}

/// The embedded default's arm on a simulator, in absolute mode.
fn sim_arm() -> Arc<ArmController> {
    let config = crate::config::Config::embedded_default().unwrap();
    let a = &config.arms[0];
    let bridge = SimBridge::start_with_clock(SimConfig::default(), monotonic_ns).unwrap();
    Arc::new(
        ArmController::new(
            "main",
            "sim",
            bridge,
            &a.teleop,
            &a.chunk,
            ActionMode::Absolute,
            Isometry3::identity(),
        )
        .unwrap(),
    )
}

/// Polls `done` until it holds or `limit` passes; returns whether it held.
async fn eventually(limit: Duration, done: impl Fn() -> bool) -> bool {
    let start = Instant::now();
    while start.elapsed() < limit {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    done()
}

/// A simulator whose bridge reports a warning, as the SO-101 bridge does for a servo alarm it works through.
#[derive(Debug)]
struct Warned(Arc<SimBridge>);

impl Bridge for Warned {
    fn kind(&self) -> &'static str {
        self.0.kind()
    }
    fn joint_names(&self) -> &[String] {
        self.0.joint_names()
    }
    fn send(&self, command: phone2act_bridges::Command) {
        self.0.send(command);
    }
    fn feedback(&self) -> Option<Feedback> {
        self.0.feedback()
    }
    fn health(&self) -> Health {
        self.0.health()
    }
    fn warning(&self) -> Option<String> {
        Some("servo 6 (gripper): overload (0x20)".into())
    }
    fn control(&self, request: phone2act_bridges::Control) -> Result<(), phone2act_bridges::BridgeError> {
        self.0.control(request)
    }
    fn shutdown(&self) {
        self.0.shutdown();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ready_bridge_warning_is_the_arm_health_message() {
    let config = crate::config::Config::embedded_default().unwrap();
    let a = &config.arms[0];
    let bridge = SimBridge::start_with_clock(SimConfig::default(), monotonic_ns).unwrap();
    let arm = ArmController::new(
        "main",
        "sim",
        Arc::new(Warned(bridge)),
        &a.teleop,
        &a.chunk,
        ActionMode::Absolute,
        Isometry3::identity(),
    )
    .unwrap();
    // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
    assert!(
        eventually(Duration::from_secs(10), || arm.snapshot().health
            == BridgeHealth::Ready)
        .await
    );
    assert_eq!(
        arm.snapshot().health_message,
        "servo 6 (gripper): overload (0x20)"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_tick_task_sleeps_while_idle_and_wakes_to_play_a_chunk_to_its_end() {
    let arm = sim_arm();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let ticking = tokio::spawn(run_ticks(vec![Arc::clone(&arm)], 500.0, stopped));
    // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
    assert!(
        eventually(Duration::from_secs(10), || arm.snapshot().health
            == BridgeHealth::Ready)
        .await
    );
    // Nobody drives: whatever the scheduler does, no tick runs (a count, not a time bound).
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(arm.stats().ticks(), 0, "an idle arm ticks");

    arm.claim_for_policy(1, "test", Arc::new(Nobody), 30.0).unwrap();
    let here = arm.snapshot().robot_from_ee.unwrap();
    let steps: Vec<Vec<f64>> = (0..5)
        .map(|k| {
            let target = Isometry3::translation(0.002 * f64::from(k), 0.0, 0.0) * here;
            phone2act_core::absolute_action(&target, 0.0)
        })
        .collect();
    let sent_before = arm.snapshot().counters.sent;
    let now = monotonic_s();
    arm.push_chunk(1, &steps, 0.05, now, now, here, ActionMode::Absolute)
        .unwrap();
    // The push plays step 0; only the woken tick task can play steps 1-4 and reach the last step's target
    // (the chunk lasts 0.25 s; 10 s covers any stall of a loaded machine, and a task that was never woken
    // never gets there). A tick more than a step late plays the step due then, so a stall may skip a
    // middle step: the count says only that the tick task sent something.
    let last = Isometry3::translation(0.008, 0.0, 0.0) * here;
    assert!(
        eventually(Duration::from_secs(10), || {
            let s = arm.snapshot();
            s.counters.sent >= sent_before + 2
                && (s.robot_from_target.translation.vector - last.translation.vector).norm() < 1e-9
        })
        .await,
        "the chunk did not play to its end: {:?}",
        arm.snapshot().counters
    );
    stop.send(true).unwrap();
    ticking.await.unwrap();
}

/// Notes when it is told of a revocation.
#[derive(Debug, Default)]
struct RevokedAt(parking_lot::Mutex<Option<f64>>);

impl RevocationSink for RevokedAt {
    fn revoked(&self, _: &str, _: &str) {
        self.0.lock().get_or_insert(monotonic_s());
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_policy_is_released_at_its_deadline_not_at_the_next_periodic_tick() {
    let arm = sim_arm();
    // One periodic tick every 30 s: a release that waited for one would come 30 s late.
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let ticking = tokio::spawn(run_ticks(vec![Arc::clone(&arm)], 1.0 / 30.0, stopped));
    // 10 s for a 50 Hz simulator to report once: a starved 2-core machine stalls for far less.
    assert!(
        eventually(Duration::from_secs(10), || arm.snapshot().health
            == BridgeHealth::Ready)
        .await
    );
    let sink = Arc::new(RevokedAt::default());
    let silence_s = 0.3;
    let ticks_before = arm.stats().ticks();
    let claimed_s = monotonic_s();
    arm.claim_for_policy(
        1,
        "silent",
        Arc::clone(&sink) as Arc<dyn RevocationSink>,
        silence_s,
    )
    .unwrap();
    assert!(
        eventually(Duration::from_secs(20), || sink.0.lock().is_some()).await,
        "the silent policy still owns the arm"
    );
    let late_s = sink.0.lock().unwrap() - (claimed_s + silence_s);
    let ticks = arm.stats().ticks() - ticks_before;
    println!(
        "released {:.1} ms after the silence deadline, {ticks} ticks",
        late_s * 1e3
    );
    // Never before the deadline (the claim came after `claimed_s`, so the true deadline is later still).
    assert!(late_s >= 0.0, "released {late_s} s early");
    // The timer wakes within milliseconds; a 2-core machine at load 20 delays a ready task by tens of
    // milliseconds, far below the 30 s a periodic tick would take.
    assert!(late_s < 2.0, "released {late_s} s after the deadline");
    // The tick task slept: the tick the claim's wake-up runs (which reads the deadline), the deadline's
    // tick, and at most one tick that the timer ran just short of the deadline (the monotonic clock and
    // tokio's timer are read apart; that tick finds the same deadline and sleeps the rest). A periodic
    // 500 Hz tick would have made about 150 over the 0.3 s.
    assert!(
        ticks <= 3,
        "{ticks} ticks while the arm waited for a silent policy"
    );
    assert_eq!(arm.snapshot().driver, phone2act_core::Driver::None);
    stop.send(true).unwrap();
    ticking.await.unwrap();
}
