//! The simulated arm's command queue: bounded, oldest first. Commands are kept (not replaced) so the sim can
//! put each one in force at the time it was issued; when the queue is full the oldest is dropped and
//! counted, so a thread that never catches up still ends on the newest command (latest wins).

use parking_lot::{Condvar, Mutex};
use std::collections::VecDeque;
use std::time::Duration;

/// Commands pending for the sim thread. At teleop's fastest phone rate (about 90 Hz) 64 commands are 0.7 s
/// of a stalled sim thread before anything is dropped; a stall that long is a suspended process.
pub(super) const CAPACITY: usize = 64;

#[derive(Debug)]
pub(super) struct BoundedQueue<T> {
    state: Mutex<(VecDeque<T>, u64)>,
    ready: Condvar,
    capacity: usize,
}

impl<T> BoundedQueue<T> {
    pub(super) fn new(capacity: usize) -> Self {
        Self {
            state: Mutex::new((VecDeque::with_capacity(capacity), 0)),
            ready: Condvar::new(),
            capacity: capacity.max(1),
        }
    }

    /// Appends `value`; never blocks. Returns true if the queue was full and its oldest value was dropped.
    pub(super) fn push(&self, value: T) -> bool {
        let mut guard = self.state.lock();
        let dropped = guard.0.len() >= self.capacity;
        if dropped {
            guard.0.pop_front();
            guard.1 += 1;
        }
        guard.0.push_back(value);
        drop(guard);
        self.ready.notify_one();
        dropped
    }

    /// Moves every queued value, oldest first, to the end of `out`.
    pub(super) fn drain_into(&self, out: &mut Vec<T>) {
        out.extend(self.state.lock().0.drain(..));
    }

    /// Waits up to `timeout` for the queue to hold something; true if it does.
    pub(super) fn wait_nonempty(&self, timeout: Duration) -> bool {
        let mut guard = self.state.lock();
        self.ready.wait_while_for(&mut guard, |s| s.0.is_empty(), timeout);
        !guard.0.is_empty()
    }

    /// Values dropped because the queue was full, since creation.
    pub(super) fn dropped(&self) -> u64 {
        self.state.lock().1
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn keeps_order_and_drops_the_oldest_when_full() {
        let q = BoundedQueue::new(3);
        assert!(!q.push(1));
        assert!(!q.push(2));
        assert!(!q.push(3));
        assert!(q.push(4));
        assert!(q.push(5));
        let mut out = vec![0];
        q.drain_into(&mut out);
        assert_eq!(out, [0, 3, 4, 5]);
        assert_eq!(q.dropped(), 2);
        q.drain_into(&mut out);
        assert_eq!(out.len(), 4, "drained means empty");
    }

    #[test]
    fn wakes_a_waiting_consumer() {
        let q = Arc::new(BoundedQueue::new(4));
        let producer = Arc::clone(&q);
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            producer.push(7u32);
        });
        // Generous: the producer sleeps 20 ms; the wait ends as soon as it pushes.
        assert!(q.wait_nonempty(Duration::from_secs(5)));
        t.join().unwrap();
        let mut out = Vec::new();
        q.drain_into(&mut out);
        assert_eq!(out, [7]);
        assert!(!q.wait_nonempty(Duration::from_millis(10)));
    }
}
