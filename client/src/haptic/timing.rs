//! Tick timing: absolute-deadline sleeping and a period histogram.

use std::time::{Duration, Instant};

/// Largest period the histogram resolves, µs; longer periods land in the last bucket.
const MAX_US: usize = 100_000;

/// Histogram of tick periods with 1 µs buckets (fixed memory, no allocation per tick).
#[derive(Debug, Clone)]
pub struct PeriodHistogram {
    buckets: Vec<u32>,
    count: u64,
    sum_ns: u128,
    max_ns: u64,
}

impl Default for PeriodHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl PeriodHistogram {
    /// An empty histogram.
    pub fn new() -> Self {
        PeriodHistogram {
            buckets: vec![0; MAX_US + 1],
            count: 0,
            sum_ns: 0,
            max_ns: 0,
        }
    }

    /// Records one period.
    pub fn record(&mut self, period: Duration) {
        let ns = period.as_nanos().min(u128::from(u64::MAX)) as u64;
        let us = ((ns + 500) / 1000).min(MAX_US as u64) as usize;
        self.buckets[us] = self.buckets[us].saturating_add(1);
        self.count += 1;
        self.sum_ns += u128::from(ns);
        self.max_ns = self.max_ns.max(ns);
    }

    /// Number of recorded periods.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Mean period, µs (NaN when empty).
    pub fn mean_us(&self) -> f64 {
        if self.count == 0 {
            return f64::NAN;
        }
        self.sum_ns as f64 / self.count as f64 / 1000.0
    }

    /// Longest period, µs.
    pub fn max_us(&self) -> f64 {
        self.max_ns as f64 / 1000.0
    }

    /// Nearest-rank percentile `p` ∈ [0, 100] of the period, µs (NaN when empty).
    pub fn percentile_us(&self, p: f64) -> f64 {
        percentile_of(self.buckets.iter().map(|&c| u64::from(c)), self.count, p)
    }

    /// Nearest-rank percentile of `|period − nominal|`, µs (NaN when empty).
    pub fn jitter_percentile_us(&self, nominal: Duration, p: f64) -> f64 {
        let nom = ((nominal.as_nanos() + 500) / 1000).min(MAX_US as u128) as usize;
        let mut dev = vec![0u64; MAX_US + 1];
        for (us, &c) in self.buckets.iter().enumerate() {
            dev[us.abs_diff(nom)] += u64::from(c);
        }
        percentile_of(dev.into_iter(), self.count, p)
    }
}

fn percentile_of(buckets: impl Iterator<Item = u64>, count: u64, p: f64) -> f64 {
    if count == 0 {
        return f64::NAN;
    }
    let rank = ((p / 100.0) * count as f64).ceil().max(1.0) as u64;
    let mut seen = 0;
    for (us, c) in buckets.enumerate() {
        seen += c;
        if seen >= rank {
            return us as f64;
        }
    }
    MAX_US as f64
}

/// What a haptic loop did. Periods are the times between consecutive tick starts.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct HapticStats {
    /// Ticks run.
    pub ticks: u64,
    /// Mean tick rate, Hz (ticks per second between the first and the last tick).
    pub rate_hz: f64,
    /// Median period, µs.
    pub period_p50_us: f64,
    /// 99th percentile period, µs.
    pub period_p99_us: f64,
    /// Longest period, µs.
    pub period_max_us: f64,
    /// 99th percentile of |period − nominal period|, µs. With absolute deadlines one late
    /// tick gives two deviations (a long period, then a short one).
    pub jitter_p99_us: f64,
    /// 99th percentile of the tick start's lateness after its deadline, µs.
    pub lateness_p99_us: f64,
    /// Ticks that started more than half a period after their deadline.
    pub overruns: u64,
    /// Times the schedule fell a whole period behind and was re-anchored (ticks skipped).
    pub reanchors: u64,
    /// Largest force magnitude sent to the device, N.
    pub max_force: f64,
    /// Ticks whose force the limit or the rate limit changed.
    pub clamped_ticks: u64,
    /// Ticks with stale device input (force fading out).
    pub stale_input_ticks: u64,
    /// Ticks whose newest model was older than the model timeout (force fading out).
    pub stale_model_ticks: u64,
    /// Ticks on which the model cell could not be read consistently (previous one kept).
    pub model_read_misses: u64,
    /// Distinct model versions the loop rendered.
    pub models_seen: u64,
    /// Ticks with a teaching guide active.
    pub guide_ticks: u64,
    /// Largest and mean teaching guide force over those ticks, N (before the device
    /// limit and the safety fade; 0 without a guide).
    pub guide_force_max: f64,
    pub guide_force_mean: f64,
}

impl HapticStats {
    /// One line for reports.
    pub fn summary(&self) -> String {
        format!(
            "{} ticks, {:.1} Hz, period p50 {:.0} µs p99 {:.0} µs max {:.0} µs, jitter p99 {:.0} µs, \
             lateness p99 {:.0} µs, {} overruns, max force {:.3} N",
            self.ticks,
            self.rate_hz,
            self.period_p50_us,
            self.period_p99_us,
            self.period_max_us,
            self.jitter_p99_us,
            self.lateness_p99_us,
            self.overruns,
            self.max_force
        )
    }
}

/// Absolute-deadline pacing: `wait()` returns at `start + k·period` for k = 1, 2, …:
/// sleeps until `spin` before the deadline, then busy-waits for the rest.
#[derive(Debug)]
pub(crate) struct Pacer {
    period: Duration,
    spin: Duration,
    next: Instant,
    pub(crate) overruns: u64,
    pub(crate) reanchors: u64,
}

impl Pacer {
    pub(crate) fn new(start: Instant, period: Duration, spin: Duration) -> Self {
        Pacer {
            period,
            spin,
            next: start,
            overruns: 0,
            reanchors: 0,
        }
    }

    /// Waits for the next deadline and returns the tick's start time and its lateness.
    pub(crate) fn wait(&mut self) -> (Instant, Duration) {
        self.next += self.period;
        let now = Instant::now();
        if now < self.next {
            if let Some(wake) = self.next.checked_sub(self.spin)
                && now < wake
            {
                std::thread::sleep(wake - now);
            }
            let mut now = Instant::now();
            while now < self.next {
                std::hint::spin_loop();
                now = Instant::now();
            }
            return (now, now - self.next);
        }
        let late = now - self.next;
        if late > self.period / 2 {
            self.overruns += 1;
        }
        if late >= self.period {
            // Do not burst to catch up: continue the grid from now.
            self.reanchors += 1;
            self.next = now;
        }
        (now, late)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_percentiles_and_jitter() {
        let mut h = PeriodHistogram::new();
        for _ in 0..98 {
            h.record(Duration::from_micros(1000));
        }
        h.record(Duration::from_micros(1200));
        h.record(Duration::from_micros(700));
        assert_eq!(h.count(), 100);
        assert_eq!(h.percentile_us(50.0), 1000.0);
        assert_eq!(h.percentile_us(99.0), 1000.0);
        assert_eq!(h.percentile_us(100.0), 1200.0);
        assert_eq!(h.percentile_us(1.0), 700.0);
        let nominal = Duration::from_millis(1);
        assert_eq!(h.jitter_percentile_us(nominal, 98.0), 0.0);
        assert_eq!(h.jitter_percentile_us(nominal, 99.0), 200.0);
        assert_eq!(h.jitter_percentile_us(nominal, 100.0), 300.0);
        assert_eq!(h.max_us(), 1200.0);
        h.record(Duration::from_secs(5));
        assert_eq!(h.percentile_us(100.0), MAX_US as f64, "overflow bucket");
        assert!(PeriodHistogram::new().percentile_us(50.0).is_nan());
    }

    #[test]
    fn pacer_reanchors_instead_of_bursting() {
        let start = Instant::now();
        let mut p = Pacer::new(start, Duration::from_millis(1), Duration::ZERO);
        let (t1, _) = p.wait();
        assert!(t1 >= start + Duration::from_millis(1));
        std::thread::sleep(Duration::from_millis(5));
        let (t2, late) = p.wait();
        assert!(late >= Duration::from_millis(4));
        assert_eq!((p.overruns, p.reanchors), (1, 1));
        let (t3, _) = p.wait();
        assert!(t3 >= t2 + Duration::from_millis(1), "no catch-up burst");
    }
}
