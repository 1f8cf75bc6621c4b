//! The session clock shared by the coordinator and the sites' links.

use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// A session clock: µs since the Unix epoch at creation, advanced by a monotonic clock.
/// The coordinator's is the session's reference; each site's link keeps one of its own,
/// built the same way, so that on one machine their offset is near zero.
#[derive(Debug, Clone, Copy)]
pub struct WallClock {
    start: Instant,
    base_us: u64,
}

impl WallClock {
    pub fn new() -> Self {
        let base_us = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_micros() as u64)
            .unwrap_or(0);
        Self {
            start: Instant::now(),
            base_us,
        }
    }

    pub fn now_us(&self) -> u64 {
        self.base_us + self.start.elapsed().as_micros() as u64
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}
