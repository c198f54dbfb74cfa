//! The control path's recent latencies, for status and benchmarks, in bounded memory.

/// The last [`LatencyRing::CAPACITY`] latencies (ns) and the count of all ever noted.
#[derive(Debug, Default, Clone)]
pub struct LatencyRing {
    values_ns: Vec<u32>,
    next: usize,
    total: u64,
}

impl LatencyRing {
    pub const CAPACITY: usize = 1 << 16;

    /// Notes one latency: a negative one (clocks read on two threads) as 0, one past `u32::MAX` ns (4.3 s) as
    /// that; once full, over the oldest.
    pub fn push(&mut self, ns: i64) {
        let v = u32::try_from(ns.max(0)).unwrap_or(u32::MAX);
        if self.values_ns.len() < Self::CAPACITY {
            self.values_ns.push(v);
        } else {
            self.values_ns[self.next] = v;
        }
        self.next = (self.next + 1) % Self::CAPACITY;
        self.total += 1;
    }

    /// The latencies held, ns, in no particular order.
    pub fn values_ns(&self) -> &[u32] {
        &self.values_ns
    }

    /// All latencies ever noted, including those the ring no longer holds.
    pub fn total(&self) -> u64 {
        self.total
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ring_keeps_the_newest_capacity_values_and_counts_all() {
        let mut ring = LatencyRing::default();
        ring.push(-5);
        ring.push(i64::MAX);
        assert_eq!(ring.values_ns(), [0, u32::MAX]);
        let cap = LatencyRing::CAPACITY as i64;
        for ns in 2..cap + 3 {
            ring.push(ns);
        }
        assert_eq!(ring.total(), cap as u64 + 3);
        assert_eq!(ring.values_ns().len(), LatencyRing::CAPACITY);
        // The three oldest (-5, MAX and 2) were written over by the three newest.
        let mut held: Vec<u32> = ring.values_ns().to_vec();
        held.sort_unstable();
        let expected: Vec<u32> = (3..cap + 3).map(|v| v as u32).collect();
        assert_eq!(held, expected);
    }
}
