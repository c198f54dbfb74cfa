//! Which rosbridge connection of this gateway holds each arm, and when another one may take it over.
//!
//! The Phone2Act app's second tap on "connect" opens a new socket, leaves the old one open (it still
//! answers pings) and publishes on the new one without advertising; it never reads replies, so a refusal
//! would lock the operator out silently. The rule: a connection from the *same address* as the holder takes
//! the arm over once the holder has sent nothing for the take-over silence (the arm's staleness timeout, so
//! the arm is already holding by then); a connection from another address never does while the holder's
//! socket is open. The new connection inherits the holder's last volume state, because the app keeps its
//! toggles across reconnects and is the source of truth. Time is an argument.

use parking_lot::Mutex;
use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy)]
struct Holder {
    conn: u64,
    peer: IpAddr,
    last_input: Instant,
    volume: Option<[i64; 2]>,
}

/// What a connection without a session may do with an arm.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Claim {
    /// No rosbridge connection of this gateway holds it (or this one does): bind normally.
    Bind,
    /// Take it over from a silent connection of the same address, continuing from its volume state.
    TakeOver { volume: Option<[i64; 2]> },
    /// Same address, but the holder spoke within the silence: drop this input, ask again on the next.
    Wait,
    /// Held by another address.
    Held { by: IpAddr },
}

/// The registry, shared by every rosbridge socket of one gateway.
#[derive(Debug, Default)]
pub struct Holders {
    arms: Mutex<HashMap<String, Holder>>,
}

impl Holders {
    /// The rule above, for connection `conn` from `peer` wanting `arm` at `now`.
    pub fn claim(&self, arm: &str, conn: u64, peer: IpAddr, now: Instant, silence: Duration) -> Claim {
        match self.arms.lock().get(arm) {
            None => Claim::Bind,
            Some(h) if h.conn == conn => Claim::Bind,
            Some(h) if h.peer != peer => Claim::Held { by: h.peer },
            Some(h) if now.saturating_duration_since(h.last_input) >= silence => {
                Claim::TakeOver { volume: h.volume }
            }
            Some(_) => Claim::Wait,
        }
    }

    /// `conn` now holds `arm` (the server accepted its stream).
    pub fn hold(&self, arm: &str, conn: u64, peer: IpAddr, now: Instant, volume: Option<[i64; 2]>) {
        self.arms.lock().insert(
            arm.to_owned(),
            Holder {
                conn,
                peer,
                last_input: now,
                volume,
            },
        );
    }

    /// `conn` sent input for `arm`; recorded only if it holds the arm.
    pub fn heard(&self, arm: &str, conn: u64, now: Instant, volume: Option<[i64; 2]>) {
        if let Some(h) = self.arms.lock().get_mut(arm)
            && h.conn == conn
        {
            h.last_input = now;
            if volume.is_some() {
                h.volume = volume;
            }
        }
    }

    /// `conn` lost or left `arm`.
    pub fn release(&self, arm: &str, conn: u64) {
        let mut arms = self.arms.lock();
        if arms.get(arm).is_some_and(|h| h.conn == conn) {
            arms.remove(arm);
        }
    }

    /// `conn` closed.
    pub fn release_all(&self, conn: u64) {
        self.arms.lock().retain(|_, h| h.conn != conn);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_address_takes_over_after_the_silence_another_address_never() {
        let h = Holders::default();
        let phone: IpAddr = "192.168.1.20".parse().unwrap();
        let other: IpAddr = "192.168.1.21".parse().unwrap();
        let silence = Duration::from_millis(300);
        let t0 = Instant::now();
        assert_eq!(h.claim("main", 1, phone, t0, silence), Claim::Bind);
        h.hold("main", 1, phone, t0, None);
        h.heard("main", 1, t0 + Duration::from_millis(100), Some([0, 0]));
        assert_eq!(h.claim("main", 1, phone, t0, silence), Claim::Bind);
        let t = t0 + Duration::from_millis(350);
        assert_eq!(h.claim("main", 2, phone, t, silence), Claim::Wait);
        // A non-holder's input does not keep the arm.
        h.heard("main", 2, t, Some([1, 1]));
        let t = t0 + Duration::from_millis(400);
        assert_eq!(
            h.claim("main", 2, phone, t, silence),
            Claim::TakeOver { volume: Some([0, 0]) }
        );
        assert_eq!(
            h.claim("main", 3, other, t + Duration::from_hours(1), silence),
            Claim::Held { by: phone }
        );
        h.hold("main", 2, phone, t, Some([0, 0]));
        h.release("main", 1);
        assert_eq!(h.claim("main", 3, other, t, silence), Claim::Held { by: phone });
        h.release_all(2);
        assert_eq!(h.claim("main", 3, other, t, silence), Claim::Bind);
    }
}
