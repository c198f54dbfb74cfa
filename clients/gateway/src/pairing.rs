//! Who may use the rosbridge port. The gateway forwards every admitted connection to gRPC with the server's
//! own token, so it must never admit a peer that proved nothing.
//!
//! The Phone2Act app cannot send a token, so a phone is admitted by its address: opening the phone page with
//! the pairing token (the printed URL or QR code) pairs the address the page came from for
//! [`crate::GatewayConfig::pair_for_s`]. The addresses that count as this machine
//! ([`crate::GatewayConfig::local_addresses`], every loopback address unless narrowed; `[]` trusts none) and
//! the `allow` list are admitted, a rosbridge URL with `?token=` is admitted, everything else is refused and
//! logged with the address and how to pair it. Time is an argument so the rules are tested without sleeping.

use parking_lot::Mutex;
use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

/// Paired addresses kept at most; a LAN has far fewer phones, and the bound keeps a flood of page visits
/// from growing memory (the oldest pairing is dropped first).
const MAX_PAIRED: usize = 256;
/// A refused address is logged at most this often, so a client retrying in a loop cannot flood the log.
const LOG_EVERY: Duration = Duration::from_secs(10);

/// Why a connection was let in, or that it was not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    /// One of this machine's addresses.
    Local,
    /// Listed in `allow`.
    Allowed,
    /// Carried the pairing token.
    Token,
    /// Paired through the phone page, until the given instant.
    Paired(Instant),
    /// The gateway has no token at all: the operator turned authentication off.
    Open,
    /// None of the above.
    Refused,
}

impl Admission {
    pub fn admitted(self) -> bool {
        self != Self::Refused
    }
}

/// The pairing table and the address rules.
#[derive(Debug)]
pub struct Pairing {
    local: Option<Vec<IpAddr>>,
    allow: Vec<IpAddr>,
    pair_for: Duration,
    paired_until: Mutex<HashMap<IpAddr, Instant>>,
    last_logged: Mutex<HashMap<IpAddr, Instant>>,
}

/// IPv4 peers of a dual-stack listener arrive as `::ffff:a.b.c.d`; compare them as IPv4.
fn canonical(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
        IpAddr::V4(_) => ip,
    }
}

impl Pairing {
    pub fn new(local: Option<Vec<IpAddr>>, allow: Vec<IpAddr>, pair_for: Duration) -> Self {
        Self {
            local: local.map(|l| l.into_iter().map(canonical).collect()),
            allow: allow.into_iter().map(canonical).collect(),
            pair_for,
            paired_until: Mutex::new(HashMap::new()),
            last_logged: Mutex::new(HashMap::new()),
        }
    }

    /// True for this machine's addresses.
    pub fn is_local(&self, ip: IpAddr) -> bool {
        let ip = canonical(ip);
        match &self.local {
            None => ip.is_loopback(),
            Some(list) => list.contains(&ip),
        }
    }

    /// Pairs `ip` from `now` for the configured time (no-op when pairing is disabled or `ip` is local).
    pub fn pair(&self, ip: IpAddr, now: Instant) -> Option<Instant> {
        let ip = canonical(ip);
        if self.pair_for.is_zero() || self.is_local(ip) {
            return None;
        }
        let until = now + self.pair_for;
        let mut table = self.paired_until.lock();
        table.retain(|_, t| *t > now);
        if table.len() >= MAX_PAIRED
            && !table.contains_key(&ip)
            && let Some(oldest) = table.iter().min_by_key(|(_, t)| **t).map(|(ip, _)| *ip)
        {
            table.remove(&oldest);
        }
        table.insert(ip, until);
        Some(until)
    }

    /// Decides a rosbridge connection from `ip`. `token_ok` says whether it carried the right token,
    /// `has_token` whether the gateway has one at all.
    pub fn admit(&self, ip: IpAddr, token_ok: bool, has_token: bool, now: Instant) -> Admission {
        let ip = canonical(ip);
        if self.is_local(ip) {
            return Admission::Local;
        }
        if self.allow.contains(&ip) {
            return Admission::Allowed;
        }
        if !has_token {
            return Admission::Open;
        }
        if token_ok {
            return Admission::Token;
        }
        match self.paired_until.lock().get(&ip) {
            Some(until) if *until > now => Admission::Paired(*until),
            _ => Admission::Refused,
        }
    }

    /// True when a refusal of `ip` should be logged now (at most once per [`LOG_EVERY`] per address).
    pub fn should_log_refusal(&self, ip: IpAddr, now: Instant) -> bool {
        let mut logged = self.last_logged.lock();
        logged.retain(|_, t| now.duration_since(*t) < LOG_EVERY);
        if logged.contains_key(&ip) || logged.len() >= MAX_PAIRED {
            return false;
        }
        logged.insert(ip, now);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn loopback_allow_token_and_pairing_admit_and_pairing_expires() {
        let p = Pairing::new(None, vec![ip("10.0.0.9")], Duration::from_mins(1));
        let t0 = Instant::now();
        assert_eq!(p.admit(ip("127.0.0.2"), false, true, t0), Admission::Local);
        assert_eq!(p.admit(ip("::1"), false, true, t0), Admission::Local);
        assert_eq!(p.admit(ip("::ffff:127.0.0.1"), false, true, t0), Admission::Local);
        assert_eq!(p.admit(ip("10.0.0.9"), false, true, t0), Admission::Allowed);
        assert_eq!(p.admit(ip("10.0.0.5"), false, true, t0), Admission::Refused);
        assert_eq!(p.admit(ip("10.0.0.5"), true, true, t0), Admission::Token);
        assert_eq!(p.admit(ip("10.0.0.5"), false, false, t0), Admission::Open);
        let until = p.pair(ip("::ffff:10.0.0.5"), t0).unwrap();
        assert_eq!(p.admit(ip("10.0.0.5"), false, true, t0), Admission::Paired(until));
        assert!(
            p.admit(ip("10.0.0.5"), false, true, t0 + Duration::from_secs(59))
                .admitted()
        );
        assert_eq!(
            p.admit(ip("10.0.0.5"), false, true, t0 + Duration::from_mins(1)),
            Admission::Refused
        );
        // Another address on the same network is not paired by it.
        assert_eq!(p.admit(ip("10.0.0.6"), false, true, t0), Admission::Refused);
    }

    #[test]
    fn a_narrowed_local_list_makes_other_loopback_addresses_remote() {
        let p = Pairing::new(Some(vec![ip("127.0.0.1")]), Vec::new(), Duration::ZERO);
        let t0 = Instant::now();
        assert!(p.is_local(ip("127.0.0.1")));
        assert_eq!(p.admit(ip("127.0.0.2"), false, true, t0), Admission::Refused);
        // Pairing disabled: the page admits nothing on rosbridge.
        assert_eq!(p.pair(ip("127.0.0.2"), t0), None);
        assert_eq!(p.admit(ip("127.0.0.2"), false, true, t0), Admission::Refused);
    }

    #[test]
    fn an_empty_local_list_trusts_no_loopback_address() {
        // `local_addresses = []`: loopback proves nothing, so it pairs or carries the token like a phone.
        let p = Pairing::new(Some(Vec::new()), Vec::new(), Duration::from_mins(1));
        let t0 = Instant::now();
        for lo in ["127.0.0.1", "::1", "::ffff:127.0.0.1"] {
            assert!(!p.is_local(ip(lo)), "{lo}");
            assert_eq!(p.admit(ip(lo), false, true, t0), Admission::Refused, "{lo}");
            assert_eq!(p.admit(ip(lo), true, true, t0), Admission::Token, "{lo}");
        }
        let until = p.pair(ip("127.0.0.1"), t0).unwrap();
        assert_eq!(
            p.admit(ip("127.0.0.1"), false, true, t0),
            Admission::Paired(until)
        );
    }

    #[test]
    fn the_table_is_bounded_and_refusals_are_logged_sparingly() {
        let p = Pairing::new(None, Vec::new(), Duration::from_mins(1));
        let t0 = Instant::now();
        for i in 0..(MAX_PAIRED as u32 + 10) {
            let addr = IpAddr::from(std::net::Ipv4Addr::from(0x0a00_0000 + i));
            p.pair(addr, t0 + Duration::from_millis(u64::from(i)));
        }
        assert_eq!(p.paired_until.lock().len(), MAX_PAIRED);
        // The newest survives, the oldest went first.
        let newest = IpAddr::from(std::net::Ipv4Addr::from(0x0a00_0000 + MAX_PAIRED as u32 + 9));
        assert!(
            p.admit(newest, false, true, t0 + Duration::from_secs(1))
                .admitted()
        );
        assert!(
            !p.admit(ip("10.0.0.0"), false, true, t0 + Duration::from_secs(1))
                .admitted()
        );
        assert!(p.should_log_refusal(ip("10.1.0.1"), t0));
        assert!(!p.should_log_refusal(ip("10.1.0.1"), t0 + Duration::from_secs(1)));
        assert!(p.should_log_refusal(ip("10.1.0.1"), t0 + LOG_EVERY));
    }
}
