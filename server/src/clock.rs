//! The session clock shared by the coordinator and the sites' links.

use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// A session clock: µs since the Unix epoch at creation, advanced by a monotonic clock.
/// The coordinator's is the session's reference; each site's link keeps one of its own,
/// built the same way, so that on one machine their offset is near zero (for dilated
/// clocks, only once the link's clock pings have measured it: two dilated clocks created
/// `d` apart differ by `d (1 − 1/factor)`).
///
/// A *dilated* clock ([`WallClock::dilated`]) advances `1 / time_scale` µs per real µs:
/// a whole session (coordinator, sites, their impairment) run `time_scale` times slower
/// than real time behaves, in its own time, as on a machine that much faster (see
/// [`TimeScale`]).
#[derive(Debug, Clone, Copy)]
pub struct WallClock {
    start: Instant,
    base_us: u64,
    scale: TimeScale,
}

impl WallClock {
    pub fn new() -> Self {
        Self::dilated(TimeScale::REAL)
    }

    /// A clock that advances `1 / scale` µs per real µs.
    pub fn dilated(scale: TimeScale) -> Self {
        let base_us = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_micros() as u64)
            .unwrap_or(0);
        Self {
            start: Instant::now(),
            base_us,
            scale,
        }
    }

    /// The dilation this clock was made with.
    pub fn time_scale(&self) -> TimeScale {
        self.scale
    }

    pub fn now_us(&self) -> u64 {
        self.base_us + self.scale.to_session(self.start.elapsed()).as_micros() as u64
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}

/// Time dilation of a whole session: every party runs `factor` times slower than real
/// time, and the network impairment is stretched by the same factor (delays and outages
/// ×`factor`, rates ÷`factor`), so that, measured in the session's own time, everything
/// is as on a machine `factor` times faster. This is how the sync of three sites is
/// measured on a machine that cannot step them all in real time (time-dilated network
/// emulation: Gupta et al., "To infinity and beyond: time-warped network emulation",
/// NSDI 2006). What it does not stretch, so that these run `factor` times quicker in
/// session time than on the real path: QUIC's own constants (25 ms maximum
/// acknowledgement delay, 1 ms timer granularity, the initial round-trip estimate and
/// retransmission timeouts of a handshake, the 10 s idle timeout); a site cut off
/// therefore reconnects somewhat sooner in session time. Hence the small
/// [`TimeScale::MAX`]. The link's own reconnection timers (backoff, connect and rejoin
/// attempt timeouts) are stretched (since 2026-11-27, 14:40 UTC). The coordinator's admission (invitation expiry, rate limits)
/// runs on its session clock.
///
/// Every party of a session must use the same factor: a site's clock estimate would
/// otherwise drift from the coordinator's by the ratio.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeScale(f64);

impl TimeScale {
    /// Real time.
    pub const REAL: TimeScale = TimeScale(1.0);
    /// Largest accepted factor: QUIC's 10 s idle timeout is then still 2 s of session
    /// time, above the session's own liveness check (1.2 s).
    pub const MAX: f64 = 5.0;

    /// A factor in 1..=[`TimeScale::MAX`], rounded to thousandths: a join states the
    /// scale in thousandths ([`TimeScale::milli`]), so two parties it admits together
    /// must run at exactly that scale (1.0004 would otherwise join a real-time session
    /// as 1000 and drift 0.04 %).
    pub fn new(factor: f64) -> Result<Self, String> {
        let factor = (factor * 1000.0).round() / 1000.0;
        if factor.is_finite() && (1.0..=Self::MAX).contains(&factor) {
            Ok(TimeScale(factor))
        } else {
            Err(format!(
                "time scale {factor} is outside 1–{} (1: real time; 2: the session runs \
                 twice slower than real time)",
                Self::MAX
            ))
        }
    }

    pub fn factor(self) -> f64 {
        self.0
    }

    pub fn is_real(self) -> bool {
        self.0 == 1.0
    }

    /// The factor in thousandths, as a join states it ([`proto::Join::time_scale_milli`]).
    pub fn milli(self) -> u32 {
        (self.0 * 1000.0).round() as u32
    }

    /// Real time elapsed → session time elapsed.
    pub fn to_session(self, real: std::time::Duration) -> std::time::Duration {
        if self.is_real() {
            real
        } else {
            real.div_f64(self.0)
        }
    }

    /// Session time → real time (a sleep, a measured real delay).
    pub fn to_real(self, session: std::time::Duration) -> std::time::Duration {
        if self.is_real() {
            session
        } else {
            session.mul_f64(self.0)
        }
    }
}

impl Default for TimeScale {
    fn default() -> Self {
        TimeScale::REAL
    }
}

impl std::str::FromStr for TimeScale {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let f: f64 = s
            .trim()
            .parse()
            .map_err(|_| format!("time scale `{s}` is not a number"))?;
        TimeScale::new(f)
    }
}

impl std::fmt::Display for TimeScale {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// A monotonic clock in session time: `Instant`s that advance `1 / scale` s per real
/// second from `origin`, for the sans-IO session state, which takes `Instant`s. Sleeps
/// until such an instant go through [`SessionClock::real_until`].
#[derive(Debug, Clone, Copy)]
pub struct SessionClock {
    origin: Instant,
    scale: TimeScale,
}

impl SessionClock {
    pub fn new(scale: TimeScale) -> Self {
        SessionClock {
            origin: Instant::now(),
            scale,
        }
    }

    pub fn scale(&self) -> TimeScale {
        self.scale
    }

    /// Now, in session time.
    pub fn now(&self) -> Instant {
        self.origin + self.scale.to_session(self.origin.elapsed())
    }

    /// Real time to wait until the session instant `at` (zero if it has passed).
    pub fn real_until(&self, at: Instant) -> std::time::Duration {
        self.scale.to_real(at.saturating_duration_since(self.now()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn time_scale_parses_and_refuses_nonsense() {
        assert_eq!("2".parse::<TimeScale>().unwrap().factor(), 2.0);
        // Thousandths, as a join states it: the clock runs at the scale it announces.
        let near_real = "1.0004".parse::<TimeScale>().unwrap();
        assert!(near_real.is_real() && near_real.milli() == 1000);
        assert_eq!("2.5".parse::<TimeScale>().unwrap().milli(), 2500);
        for bad in ["0.5", "0", "-1", "NaN", "inf", "6", "x"] {
            let e = bad.parse::<TimeScale>().unwrap_err();
            assert!(e.contains("time scale"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_dilated_clock_advances_at_its_fraction_of_real_time() {
        let scale = TimeScale::new(4.0).unwrap();
        assert_eq!(
            scale.to_session(Duration::from_millis(400)),
            Duration::from_millis(100)
        );
        assert_eq!(
            scale.to_real(Duration::from_millis(100)),
            Duration::from_millis(400)
        );
        // Bracket each dilated reading between two real ones: the dilated interval lies
        // between a quarter of the inner and of the outer real interval, however the
        // thread is scheduled (to the µs rounding of the readings).
        let real = WallClock::new();
        let dilated = WallClock::dilated(scale);
        let clock = SessionClock::new(scale);
        let a = real.now_us();
        let (d0, s0) = (dilated.now_us(), clock.now());
        let b = real.now_us();
        std::thread::sleep(Duration::from_millis(40));
        let c = real.now_us();
        let (d1, s1) = (dilated.now_us(), clock.now());
        let d = real.now_us();
        let (inner, outer) = ((c - b) as f64 / 4.0, (d - a) as f64 / 4.0);
        for (what, us) in [
            ("wall clock", (d1 - d0) as f64),
            ("session clock", (s1 - s0).as_secs_f64() * 1e6),
        ] {
            assert!(
                us >= inner - 2.0 && us <= outer + 2.0,
                "{what}: {us} µs, not in {inner}..{outer}"
            );
        }
        // Sleeping until a session instant takes four times as long in real time: the
        // wait lies between four times what was left before and after it was asked.
        let before = clock.now();
        let at = before + Duration::from_millis(10);
        let wait = clock.real_until(at);
        let left_after = at.saturating_duration_since(clock.now());
        assert!(wait <= Duration::from_millis(40), "{wait:?}");
        assert!(wait >= left_after * 4, "{wait:?} < 4 × {left_after:?}");
    }
}
