//! Peer liveness: heartbeats and timeouts, driven by a caller-supplied clock (µs).
//!
//! A peer is declared dead after `timeout_factor` (default 2.4) heartbeat intervals without
//! hearing anything from it (any message counts). [`PeerLiveness::poll`] also says when our
//! own heartbeat is due.

/// Default factor of heartbeat intervals after which a silent peer times out.
pub const DEFAULT_TIMEOUT_FACTOR: f64 = 2.4;

/// What the caller should do now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LivenessEvent {
    /// Send a heartbeat to the peer.
    SendHeartbeat,
    /// The peer has been silent for too long.
    TimedOut,
}

/// Liveness of one peer.
#[derive(Debug, Clone)]
pub struct PeerLiveness {
    interval_us: u64,
    timeout_us: u64,
    last_heard_us: u64,
    last_sent_us: Option<u64>,
    timed_out: bool,
}

impl PeerLiveness {
    /// Start tracking at `now_us` (counts as having heard the peer).
    pub fn new(interval_us: u64, now_us: u64) -> Self {
        Self::with_factor(interval_us, DEFAULT_TIMEOUT_FACTOR, now_us)
    }

    pub fn with_factor(interval_us: u64, factor: f64, now_us: u64) -> Self {
        Self {
            interval_us,
            timeout_us: (interval_us as f64 * factor).round() as u64,
            last_heard_us: now_us,
            last_sent_us: None,
            timed_out: false,
        }
    }

    /// We heard from the peer at `now_us`.
    pub fn on_heard(&mut self, now_us: u64) {
        self.last_heard_us = self.last_heard_us.max(now_us);
    }

    /// We sent something (a heartbeat or any message) at `now_us`.
    pub fn on_sent(&mut self, now_us: u64) {
        self.last_sent_us = Some(now_us);
    }

    pub fn timeout_us(&self) -> u64 {
        self.timeout_us
    }

    pub fn silence_us(&self, now_us: u64) -> u64 {
        now_us.saturating_sub(self.last_heard_us)
    }

    pub fn is_alive(&self, now_us: u64) -> bool {
        !self.timed_out && self.silence_us(now_us) < self.timeout_us
    }

    /// Events due at `now_us`. `TimedOut` is reported once.
    pub fn poll(&mut self, now_us: u64) -> Option<LivenessEvent> {
        if !self.timed_out && self.silence_us(now_us) >= self.timeout_us {
            self.timed_out = true;
            return Some(LivenessEvent::TimedOut);
        }
        if self.timed_out {
            return None;
        }
        let due = self
            .last_sent_us
            .is_none_or(|s| now_us.saturating_sub(s) >= self.interval_us);
        if due {
            self.last_sent_us = Some(now_us);
            Some(LivenessEvent::SendHeartbeat)
        } else {
            None
        }
    }

    /// The next time [`poll`](Self::poll) may report something.
    pub fn next_deadline(&self) -> u64 {
        let hb = self.last_sent_us.map_or(0, |s| s + self.interval_us);
        hb.min(self.last_heard_us + self.timeout_us)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_out_after_2_4_intervals() {
        let mut p = PeerLiveness::new(100, 0);
        assert_eq!(p.timeout_us(), 240);
        assert!(p.is_alive(239));
        assert!(!p.is_alive(240));
        assert_eq!(p.poll(0), Some(LivenessEvent::SendHeartbeat));
        assert_eq!(p.poll(50), None);
        assert_eq!(p.poll(100), Some(LivenessEvent::SendHeartbeat));
        assert_eq!(p.poll(200), Some(LivenessEvent::SendHeartbeat));
        assert_eq!(p.poll(240), Some(LivenessEvent::TimedOut));
        assert_eq!(p.poll(300), None);
        assert!(!p.is_alive(300));
    }

    #[test]
    fn hearing_keeps_alive_and_two_missed_heartbeats_are_tolerated() {
        let mut p = PeerLiveness::new(100, 0);
        for t in (0..10_000).step_by(100) {
            p.on_heard(t);
            assert_ne!(p.poll(t), Some(LivenessEvent::TimedOut));
        }
        // last heard at 9900; heartbeats at 10000 and 10100 missed: still alive
        assert!(p.is_alive(10_100 + 39));
        assert_eq!(
            p.poll(10_139).filter(|e| *e == LivenessEvent::TimedOut),
            None
        );
        assert_eq!(p.poll(10_140), Some(LivenessEvent::TimedOut));
    }

    #[test]
    fn deadline() {
        let mut p = PeerLiveness::new(100, 1000);
        assert_eq!(p.next_deadline(), 0);
        p.on_sent(1000);
        assert_eq!(p.next_deadline(), 1100);
        p.on_sent(1200);
        assert_eq!(p.next_deadline(), 1240);
    }
}
