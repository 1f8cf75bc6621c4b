//! NTP-style clock offset estimation against the coordinator (the session's clock reference).
//!
//! A [`ClockSample`] holds the four timestamps of a ping/pong exchange: `t1` client send,
//! `t2` coordinator receive, `t3` coordinator send, `t4` client receive (client times on the
//! local clock, coordinator times on its clock, all µs). Then
//! `offset = ((t2 − t1) + (t3 − t4)) / 2` (coordinator − local) and
//! `delay = (t4 − t1) − (t3 − t2)` (round trip without the coordinator's processing time).
//! The offset of one sample is off by at most half the path asymmetry, which is smallest for
//! the samples with the lowest delay.
//!
//! [`ClockFilter`] keeps the last `window` samples, takes the offset of the lowest-delay one
//! as its target, and **slews** its published estimate towards the target at no more than
//! `max_slew` (default 5 %) of elapsed local time, so the coordinator time it derives never
//! jumps and never runs backwards. Only the first sample sets the estimate directly (and,
//! optionally, errors above `step_threshold_us`).

use std::collections::VecDeque;

/// Four timestamps of one clock exchange (µs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockSample {
    pub t1_us: u64,
    pub t2_us: u64,
    pub t3_us: u64,
    pub t4_us: u64,
}

impl ClockSample {
    /// From a pong and the local receive time.
    pub fn from_pong(pong: &crate::msg::ClockPong, t4_us: u64) -> Self {
        Self {
            t1_us: pong.t1_us,
            t2_us: pong.t2_us,
            t3_us: pong.t3_us,
            t4_us,
        }
    }

    /// Coordinator clock minus local clock (µs).
    pub fn offset_us(&self) -> f64 {
        let (t1, t2, t3, t4) = (
            self.t1_us as i128,
            self.t2_us as i128,
            self.t3_us as i128,
            self.t4_us as i128,
        );
        ((t2 - t1) + (t3 - t4)) as f64 / 2.0
    }

    /// Round-trip network delay (µs); may be slightly negative with coarse clocks.
    pub fn delay_us(&self) -> i64 {
        let (t1, t2, t3, t4) = (
            self.t1_us as i128,
            self.t2_us as i128,
            self.t3_us as i128,
            self.t4_us as i128,
        );
        ((t4 - t1) - (t3 - t2)).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }

    /// Plausible: the client did not receive before sending and the coordinator did not send
    /// before receiving.
    pub fn is_plausible(&self) -> bool {
        self.t4_us >= self.t1_us && self.t3_us >= self.t2_us
    }
}

/// Tuning of a [`ClockFilter`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockFilterConfig {
    /// Number of recent samples kept.
    pub window: usize,
    /// Maximum slew rate of the estimate (fraction of elapsed local time).
    pub max_slew: f64,
    /// If set, an error above this jumps instead of slewing (µs).
    pub step_threshold_us: Option<u64>,
}

impl Default for ClockFilterConfig {
    fn default() -> Self {
        Self {
            window: 8,
            max_slew: 0.05,
            step_threshold_us: None,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Kept {
    offset_us: f64,
    delay_us: i64,
}

/// Offset/RTT estimator with minimum-delay selection and slewing.
#[derive(Debug, Clone)]
pub struct ClockFilter {
    config: ClockFilterConfig,
    samples: VecDeque<Kept>,
    estimate_us: Option<f64>,
    last_local_us: u64,
    accepted: u64,
    rejected: u64,
}

impl Default for ClockFilter {
    fn default() -> Self {
        Self::new(ClockFilterConfig::default())
    }
}

impl ClockFilter {
    pub fn new(config: ClockFilterConfig) -> Self {
        Self {
            config,
            samples: VecDeque::new(),
            estimate_us: None,
            last_local_us: 0,
            accepted: 0,
            rejected: 0,
        }
    }

    /// Move the estimate towards the target for the time elapsed up to `local_now_us`.
    fn advance(&mut self, local_now_us: u64) {
        let Some(est) = self.estimate_us else { return };
        let dt = local_now_us.saturating_sub(self.last_local_us) as f64;
        self.last_local_us = self.last_local_us.max(local_now_us);
        let Some(target) = self.target_offset_us() else {
            return;
        };
        let max_step = self.config.max_slew * dt;
        let diff = target - est;
        self.estimate_us = Some(est + diff.clamp(-max_step, max_step));
    }

    /// Add a sample (its `t4` is taken as the local time now). Returns `false` if rejected
    /// as implausible.
    pub fn add_sample(&mut self, s: ClockSample) -> bool {
        if !s.is_plausible() {
            self.rejected += 1;
            return false;
        }
        self.advance(s.t4_us);
        self.accepted += 1;
        self.samples.push_back(Kept {
            offset_us: s.offset_us(),
            delay_us: s.delay_us().max(0),
        });
        while self.samples.len() > self.config.window.max(1) {
            self.samples.pop_front();
        }
        let target = self.target_offset_us().expect("non-empty window");
        match self.estimate_us {
            None => {
                self.estimate_us = Some(target);
                self.last_local_us = s.t4_us;
            }
            Some(est) => {
                if let Some(th) = self.config.step_threshold_us
                    && (target - est).abs() > th as f64
                {
                    self.estimate_us = Some(target);
                }
            }
        }
        true
    }

    /// Offset of the lowest-delay sample in the window (µs).
    pub fn target_offset_us(&self) -> Option<f64> {
        self.samples
            .iter()
            .min_by_key(|k| k.delay_us)
            .map(|k| k.offset_us)
    }

    /// Current slewed offset estimate (coordinator − local, µs) as of the last update.
    pub fn estimate_us(&self) -> Option<f64> {
        self.estimate_us
    }

    /// Slewed offset estimate at `local_now_us` (µs).
    pub fn offset_at(&mut self, local_now_us: u64) -> Option<f64> {
        self.advance(local_now_us);
        self.estimate_us
    }

    /// Coordinator time corresponding to local time `local_now_us` (µs).
    pub fn coordinator_time(&mut self, local_now_us: u64) -> Option<u64> {
        let off = self.offset_at(local_now_us)?;
        Some((local_now_us as f64 + off).max(0.0).round() as u64)
    }

    /// Lowest round-trip delay in the window (µs).
    pub fn rtt_us(&self) -> Option<u64> {
        self.samples.iter().map(|k| k.delay_us as u64).min()
    }

    /// True once at least one sample was accepted.
    pub fn is_synchronised(&self) -> bool {
        self.estimate_us.is_some()
    }

    /// (accepted, rejected) sample counts.
    pub fn counts(&self) -> (u64, u64) {
        (self.accepted, self.rejected)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random generator (xorshift) for the fake network.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn uniform(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    /// Fake world: coordinator clock = local + `offset`. One-way delays = base + jitter, and
    /// with probability 1/4 an asymmetric outlier of up to 40 ms on one direction.
    struct World {
        offset: i64,
        rng: Rng,
    }

    impl World {
        fn exchange(&mut self, t1: u64) -> ClockSample {
            let mut up = 2_000 + self.rng.uniform(500);
            let mut down = 2_000 + self.rng.uniform(500);
            if self.rng.uniform(4) == 0 {
                if self.rng.uniform(2) == 0 {
                    up += 5_000 + self.rng.uniform(35_000);
                } else {
                    down += 5_000 + self.rng.uniform(35_000);
                }
            }
            let t2 = (t1 as i64 + up as i64 + self.offset) as u64;
            let t3 = t2 + 50 + self.rng.uniform(100);
            let t4 = (t3 as i64 - self.offset) as u64 + down;
            ClockSample {
                t1_us: t1,
                t2_us: t2,
                t3_us: t3,
                t4_us: t4,
            }
        }
    }

    #[test]
    fn sample_math() {
        // offset 1000, delays 10 up / 30 down, processing 5
        let s = ClockSample {
            t1_us: 100,
            t2_us: 1110,
            t3_us: 1115,
            t4_us: 145,
        };
        assert_eq!(s.delay_us(), 40);
        assert_eq!(s.offset_us(), 990.0); // error = asymmetry/2 = -10
        assert!(s.is_plausible());
    }

    #[test]
    fn converges_to_known_offset_despite_jitter_and_outliers() {
        for (seed, offset) in [(1u64, 1_234_567i64), (7, -987_654), (99, 42)] {
            let mut w = World {
                offset,
                rng: Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1),
            };
            let mut f = ClockFilter::default();
            let mut t = 10_000_000u64;
            for _ in 0..60 {
                assert!(f.add_sample(w.exchange(t)));
                t += 100_000;
            }
            let est = f.offset_at(t).unwrap();
            // error bound: half the maximum asymmetry of a non-outlier exchange (250 µs)
            assert!(
                (est - offset as f64).abs() <= 300.0,
                "seed {seed}: estimate {est} vs {offset}"
            );
            let rtt = f.rtt_us().unwrap();
            assert!((4_000..=5_000).contains(&rtt), "rtt {rtt}");
        }
    }

    #[test]
    fn slews_at_most_five_percent_and_never_runs_backwards() {
        let mut w = World {
            offset: 0,
            rng: Rng(12345),
        };
        let mut f = ClockFilter::default();
        let mut t = 1_000_000u64;
        for _ in 0..20 {
            f.add_sample(w.exchange(t));
            t += 100_000;
        }
        // The coordinator clock steps by +200 ms.
        w.offset = 200_000;
        let mut prev_est = f.offset_at(t).unwrap();
        let mut prev_coord = f.coordinator_time(t).unwrap();
        let mut max_rate = 0.0f64;
        for _ in 0..100 {
            let s = w.exchange(t);
            f.add_sample(s);
            for tick in [s.t4_us, s.t4_us + 50_000] {
                let est = f.offset_at(tick).unwrap();
                let coord = f.coordinator_time(tick).unwrap();
                assert!(coord >= prev_coord, "coordinator time ran backwards");
                prev_coord = coord;
                let _ = est;
            }
            let est = f.offset_at(t + 100_000).unwrap();
            max_rate = max_rate.max((est - prev_est).abs() / 100_000.0);
            prev_est = est;
            t += 100_000;
        }
        assert!(max_rate <= 0.05 + 1e-9, "slew rate {max_rate}");
        // 200 ms at 5 % takes 4 s; 10 s have passed.
        assert!((prev_est - 200_000.0).abs() <= 300.0, "estimate {prev_est}");
    }

    #[test]
    fn step_threshold_jumps() {
        let mut f = ClockFilter::new(ClockFilterConfig {
            window: 1,
            step_threshold_us: Some(50_000),
            ..Default::default()
        });
        let mk = |t1: u64, off: i64| ClockSample {
            t1_us: t1,
            t2_us: (t1 as i64 + 1000 + off) as u64,
            t3_us: (t1 as i64 + 1000 + off) as u64,
            t4_us: t1 + 2000,
        };
        f.add_sample(mk(0, 0));
        f.add_sample(mk(10_000, 10_000));
        assert!((f.estimate_us().unwrap() - 0.0).abs() <= 0.05 * 10_000.0 + 1.0);
        f.add_sample(mk(20_000, 1_000_000));
        assert_eq!(f.estimate_us(), Some(1_000_000.0));
    }

    #[test]
    fn implausible_samples_rejected() {
        let mut f = ClockFilter::default();
        assert!(!f.add_sample(ClockSample {
            t1_us: 100,
            t2_us: 0,
            t3_us: 0,
            t4_us: 50
        }));
        assert!(!f.add_sample(ClockSample {
            t1_us: 0,
            t2_us: 10,
            t3_us: 5,
            t4_us: 50
        }));
        assert!(!f.is_synchronised());
        assert_eq!(f.counts(), (0, 2));
        assert_eq!(f.coordinator_time(10), None);
    }
}
