//! Rate limiting of failed joins per source address, sans IO.
//!
//! Each address has a bucket of [`RateLimitConfig::burst`] tokens refilled at one per
//! [`RateLimitConfig::refill`]; a failed join (wrong token, bad invitation, unknown session,
//! malformed Join) takes a token. With the bucket empty, every further failure blocks the
//! address for an exponentially growing time (`base_block`, doubling, at most `max_block`);
//! joins from a blocked address are refused with "rate limited" before their credential is
//! looked at (and, see [`crate::admission`], count as failures themselves). A full bucket
//! forgets the address. Successful joins cost nothing.

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::Duration;

/// Rate-limit parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RateLimitConfig {
    /// Failures allowed in a burst.
    pub burst: u32,
    /// Time to regain one allowed failure.
    pub refill: Duration,
    /// Block after the first failure beyond the burst.
    pub base_block: Duration,
    /// Longest block.
    pub max_block: Duration,
    /// Addresses tracked at most (the least recently failing ones are forgotten first).
    pub max_addresses: usize,
}

impl Default for RateLimitConfig {
    /// 5 failures, one more every 10 s; then blocks of 1 s, 2 s, 4 s … up to 5 min.
    fn default() -> Self {
        Self {
            burst: 5,
            refill: Duration::from_secs(10),
            base_block: Duration::from_secs(1),
            max_block: Duration::from_secs(300),
            max_addresses: 65_536,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    /// Tokens left, as of `at_us`.
    tokens: f64,
    at_us: u64,
    /// Failures with an empty bucket since the bucket was last full.
    strikes: u32,
    blocked_until_us: u64,
}

/// Failed-join accounting per IP address.
#[derive(Debug)]
pub struct JoinRateLimiter {
    config: RateLimitConfig,
    entries: HashMap<IpAddr, Entry>,
}

impl JoinRateLimiter {
    pub fn new(config: RateLimitConfig) -> Self {
        Self {
            config,
            entries: HashMap::new(),
        }
    }

    fn refill(&self, e: &mut Entry, now_us: u64) {
        let per_us = self.config.refill.as_micros().max(1) as f64;
        let gained = now_us.saturating_sub(e.at_us) as f64 / per_us;
        e.tokens = (e.tokens + gained).min(self.config.burst as f64);
        e.at_us = now_us.max(e.at_us);
        if e.tokens >= self.config.burst as f64 {
            e.strikes = 0;
        }
    }

    /// `Err(retry_after)` if `ip` is blocked at `now_us` (µs, any monotonic clock).
    pub fn check(&self, ip: IpAddr, now_us: u64) -> Result<(), Duration> {
        match self.entries.get(&ip) {
            Some(e) if e.blocked_until_us > now_us => {
                Err(Duration::from_micros(e.blocked_until_us - now_us))
            }
            _ => Ok(()),
        }
    }

    /// Record a failed join from `ip`. Returns the block it caused, if any.
    pub fn failure(&mut self, ip: IpAddr, now_us: u64) -> Option<Duration> {
        if !self.entries.contains_key(&ip) && self.entries.len() >= self.config.max_addresses {
            self.evict(now_us);
        }
        let burst = self.config.burst as f64;
        let mut e = self.entries.get(&ip).copied().unwrap_or(Entry {
            tokens: burst,
            at_us: now_us,
            strikes: 0,
            blocked_until_us: 0,
        });
        self.refill(&mut e, now_us);
        let block = if e.tokens >= 1.0 {
            e.tokens -= 1.0;
            None
        } else {
            let base = self.config.base_block.as_micros() as u64;
            let max = self.config.max_block.as_micros() as u64;
            let us = base.saturating_mul(1u64 << e.strikes.min(40)).min(max);
            e.strikes += 1;
            e.blocked_until_us = now_us + us;
            Some(Duration::from_micros(us))
        };
        self.entries.insert(ip, e);
        block
    }

    /// Forget addresses whose bucket is full again and which are not blocked; if that frees
    /// nothing, the entry that failed longest ago.
    fn evict(&mut self, now_us: u64) {
        let cfg = self.config;
        let per_us = cfg.refill.as_micros().max(1) as f64;
        self.entries.retain(|_, e| {
            let tokens = e.tokens + now_us.saturating_sub(e.at_us) as f64 / per_us;
            tokens < cfg.burst as f64 || e.blocked_until_us > now_us
        });
        if self.entries.len() >= cfg.max_addresses
            && let Some(oldest) = self
                .entries
                .iter()
                .min_by_key(|(_, e)| e.at_us)
                .map(|(k, _)| *k)
        {
            self.entries.remove(&oldest);
        }
    }

    /// Addresses tracked.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: u64 = 1_000_000;

    fn ip(n: u8) -> IpAddr {
        IpAddr::from([10, 0, 0, n])
    }

    #[test]
    fn burst_then_exponential_blocks_then_recovery() {
        let mut r = JoinRateLimiter::new(RateLimitConfig::default());
        let a = ip(1);
        for _ in 0..5 {
            assert_eq!(r.failure(a, 0), None);
            assert!(r.check(a, 0).is_ok());
        }
        assert_eq!(r.failure(a, 0), Some(Duration::from_secs(1)));
        assert_eq!(r.check(a, 0), Err(Duration::from_secs(1)));
        assert!(r.check(ip(2), 0).is_ok(), "other addresses unaffected");
        assert!(r.check(a, S).is_ok(), "block over");
        // still no token at 1 s (refill 10 s): next failure doubles
        assert_eq!(r.failure(a, S), Some(Duration::from_secs(2)));
        assert_eq!(r.failure(a, 3 * S), Some(Duration::from_secs(4)));
        // capped
        let mut t = 3 * S;
        let mut last = Duration::ZERO;
        for _ in 0..20 {
            t += 1;
            last = r.failure(a, t).unwrap_or(last);
        }
        assert_eq!(last, Duration::from_secs(300));
        // one token back after 10 s: one free failure, then blocks resume where they were
        t += 310 * S;
        assert!(r.check(a, t).is_ok());
        // the bucket filled completely during 310 s: strikes forgotten
        for _ in 0..5 {
            assert_eq!(r.failure(a, t), None);
        }
        assert_eq!(r.failure(a, t), Some(Duration::from_secs(1)));
    }

    #[test]
    fn table_is_bounded() {
        let mut r = JoinRateLimiter::new(RateLimitConfig {
            max_addresses: 4,
            ..RateLimitConfig::default()
        });
        for n in 0..20 {
            r.failure(ip(n), n as u64);
        }
        assert!(r.len() <= 4, "{}", r.len());
    }
}
