//! One arm's control-path counters for status and benchmarks: recent latencies (sample received → command
//! handed to the bridge), samples received and ticks run. Shared by the gRPC handlers and the tick task, so
//! atomics and a short lock; the ring itself is `phone2act_core::LatencyRing`.

use parking_lot::Mutex;
use phone2act_core::LatencyRing;
use std::sync::atomic::{AtomicU64, Ordering};

#[derive(Debug, Default)]
pub struct ControlStats {
    latencies_ns: Mutex<LatencyRing>,
    samples_received: AtomicU64,
    ticks: AtomicU64,
}

impl ControlStats {
    /// Records one teleop round: the samples it merged and its control-path latency, if it sent a command.
    pub fn note_round(&self, samples: u64, latency_ns: Option<i64>) {
        self.samples_received.fetch_add(samples, Ordering::Relaxed);
        if let Some(ns) = latency_ns {
            self.latencies_ns.lock().push(ns);
        }
    }

    /// Counts one tick.
    pub fn note_tick(&self) {
        self.ticks.fetch_add(1, Ordering::Relaxed);
    }

    /// Recent control-path latencies (ns, unordered) and the count of all latencies ever recorded.
    pub fn latencies_ns(&self) -> (Vec<u32>, u64) {
        let ring = self.latencies_ns.lock();
        (ring.values_ns().to_vec(), ring.total())
    }

    /// Clears the latencies (between benchmark phases).
    pub fn reset_latencies(&self) {
        *self.latencies_ns.lock() = LatencyRing::default();
    }

    /// Teleop samples received (including those superseded by newer ones) since start.
    pub fn samples_received(&self) -> u64 {
        self.samples_received.load(Ordering::Relaxed)
    }

    /// Ticks run since start (an idle arm runs none).
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Ordering::Relaxed)
    }
}
