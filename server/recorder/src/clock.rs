//! The server's monotonic clock: nanoseconds since a process-wide epoch, shared by camera threads, the
//! recorder tick and the gRPC adapters so that every `*_time_ns` in the process is comparable.

use std::sync::OnceLock;
use std::time::Instant;

static EPOCH: OnceLock<Instant> = OnceLock::new();

/// Nanoseconds since the process epoch (the first call), on a monotonic clock.
pub fn monotonic_ns() -> i64 {
    let epoch = *EPOCH.get_or_init(Instant::now);
    i64::try_from(epoch.elapsed().as_nanos()).unwrap_or(i64::MAX)
}

/// The `Instant` that corresponds to [`monotonic_ns`] zero.
pub fn epoch() -> Instant {
    *EPOCH.get_or_init(Instant::now)
}
