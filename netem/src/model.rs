//! Sans-IO, seeded network impairment model for one direction of a link.
//!
//! Nothing in here knows about sockets, clocks or async: the caller passes the arrival time of
//! every packet (`now_us`, microseconds since an epoch of its choosing) and gets back a
//! [`Verdict`]: either the packet is dropped (and why), or the absolute times (same clock) at
//! which one or more copies of it should be released on the far side.
//!
//! # Pipeline (per packet, in this order)
//! 1. **Outage** – inside a scheduled outage window every packet is lost.
//! 2. **Random loss** – independent Bernoulli loss with probability `loss_pct`.
//! 3. **Burst loss** – Gilbert–Elliott two-state Markov chain (state changes once per packet,
//!    then the packet is lost with the loss probability of the new state).
//! 4. **Rate cap** – token-bucket shaper with a FIFO queue; a packet arriving while the queue
//!    already holds `queue_pkts` packets is dropped (`DropReason::Rate`).
//! 5. **Delay + jitter** – one-way delay plus a normal or uniform jitter sample (clamped at 0).
//!    Without reordering a packet is never released before the previously released one:
//!    `release = max(sample, previous release)`.
//! 6. **Duplication** – with probability `dup_pct` a second copy is released, with its own
//!    delay sample (it does not use rate-cap tokens).
//!
//! # Units and presets
//! All delays in the configuration are **one-way, per direction, in milliseconds**. A preset
//! applied to both directions of a link therefore has a round-trip time of twice its delay:
//! `poor` (200 ms ± 30) is a ≈ 400 ms RTT link. "± J" is the standard deviation of a normal
//! jitter (or the half-width of a uniform one). Percentages are 0–100.

use std::collections::VecDeque;
use std::fmt;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

/// Shape of the jitter added to the base delay.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JitterDist {
    /// Normal distribution with standard deviation `jitter_ms` (clamped so delay ≥ 0).
    #[default]
    Normal,
    /// Uniform in `[delay - jitter, delay + jitter]` (clamped so delay ≥ 0).
    Uniform,
}

/// Gilbert–Elliott bursty loss parameters (probabilities in 0..=1, per packet).
///
/// The chain is in the *good* or *bad* state; on every packet it first moves (good→bad with
/// `p_gb`, bad→good with `p_bg`), then loses the packet with `loss_good` / `loss_bad`.
/// With `loss_good = 0`, `loss_bad = 1` (the classic Gilbert model) the mean burst length is
/// `1 / p_bg` packets and the long-run loss rate is `p_gb / (p_gb + p_bg)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GilbertElliott {
    pub p_gb: f64,
    pub p_bg: f64,
    #[serde(default)]
    pub loss_good: f64,
    #[serde(default = "one")]
    pub loss_bad: f64,
}

fn one() -> f64 {
    1.0
}

impl GilbertElliott {
    /// Classic Gilbert model: no loss in the good state, all packets lost in the bad state.
    pub fn new(p_gb: f64, p_bg: f64) -> Self {
        Self {
            p_gb,
            p_bg,
            loss_good: 0.0,
            loss_bad: 1.0,
        }
    }

    /// Long-run fraction of packets lost by this chain.
    pub fn stationary_loss(&self) -> f64 {
        let denom = self.p_gb + self.p_bg;
        if denom <= 0.0 {
            return self.loss_good;
        }
        let pi_bad = self.p_gb / denom;
        pi_bad * self.loss_bad + (1.0 - pi_bad) * self.loss_good
    }

    /// Mean length (packets) of a run of consecutive bad-state packets, `1 / p_bg`: the
    /// mean loss burst of the classic Gilbert model (`loss_bad = 1`, `loss_good = 0`).
    pub fn mean_bad_run(&self) -> f64 {
        if self.p_bg <= 0.0 {
            f64::INFINITY
        } else {
            1.0 / self.p_bg
        }
    }
}

/// A scheduled outage: every packet arriving in `[start_s, start_s + duration_s)` (seconds
/// since the model's epoch) is lost.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Outage {
    pub start_s: f64,
    pub duration_s: f64,
}

impl Outage {
    fn contains(&self, now_us: u64) -> bool {
        let t = now_us as f64 * 1e-6;
        t >= self.start_s && t < self.start_s + self.duration_s
    }
}

/// Impairment of one direction of a link. `Default` is a perfect pass-through link.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ImpairmentConfig {
    /// One-way base delay in milliseconds.
    pub delay_ms: f64,
    /// Jitter in milliseconds (standard deviation for `Normal`, half-width for `Uniform`).
    pub jitter_ms: f64,
    pub jitter_dist: JitterDist,
    /// Allow packets to overtake each other when their delay samples say so.
    pub reorder: bool,
    /// Independent random loss, percent.
    pub loss_pct: f64,
    /// Bursty loss (applied in addition to `loss_pct`).
    pub burst: Option<GilbertElliott>,
    /// Probability that a delivered packet is duplicated, percent.
    pub dup_pct: f64,
    /// Token-bucket rate cap in kbit/s (1 kbit = 1000 bit); `None` = unlimited.
    pub rate_kbps: Option<f64>,
    /// Token-bucket size in bytes (burst allowance at line rate).
    pub bucket_bytes: u32,
    /// Maximum number of packets waiting in the rate-cap queue; more are dropped.
    pub queue_pkts: usize,
    /// Scheduled outage (100 % loss) relative to the model's epoch.
    pub outage: Option<Outage>,
}

impl Default for ImpairmentConfig {
    fn default() -> Self {
        Self {
            delay_ms: 0.0,
            jitter_ms: 0.0,
            jitter_dist: JitterDist::Normal,
            reorder: false,
            loss_pct: 0.0,
            burst: None,
            dup_pct: 0.0,
            rate_kbps: None,
            bucket_bytes: DEFAULT_BUCKET_BYTES,
            queue_pkts: DEFAULT_QUEUE_PKTS,
            outage: None,
        }
    }
}

/// Default token-bucket size: ten full-size 1500-byte packets.
pub const DEFAULT_BUCKET_BYTES: u32 = 15_000;
/// Default rate-cap queue limit in packets (Linux netem's default `limit`).
pub const DEFAULT_QUEUE_PKTS: usize = 1000;

/// Names of the built-in presets, in order of increasing badness (plus `none`), then the
/// two that fail differently: bursts of loss and a 3 s outage.
pub const PRESET_NAMES: &[&str] = &[
    "none",
    "lan",
    "metro",
    "good",
    "intercontinental",
    "average",
    "poor",
    "burst",
    "outage",
];

/// The `burst` preset's Gilbert chain: good→bad and bad→good probability per packet.
pub const BURST_P_GB: f64 = 0.01;
pub const BURST_P_BG: f64 = 0.2;
/// The `outage` preset's outage: start and length (s after the link starts).
pub const OUTAGE_START_S: f64 = 3.0;
pub const OUTAGE_DURATION_S: f64 = 3.0;

/// Problems with an impairment configuration.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConfigError {
    #[error(
        "unknown preset `{0}` (known: none, lan, metro, good, intercontinental, average, poor)"
    )]
    UnknownPreset(String),
    #[error("{field}: {value} is out of range ({range})")]
    OutOfRange {
        field: &'static str,
        value: f64,
        range: &'static str,
    },
    #[error("{field}: cannot parse `{text}`: {why}")]
    Parse {
        field: &'static str,
        text: String,
        why: String,
    },
}

impl ImpairmentConfig {
    /// Perfect link.
    pub fn none() -> Self {
        Self::default()
    }

    /// Preset by name; delays are one-way per direction (see module docs).
    ///
    /// | name | one-way delay | jitter (sd) | loss |
    /// |---|---|---|---|
    /// | `none` | 0 | 0 | 0 |
    /// | `lan` | 0.2 ms | 0 | 0 |
    /// | `metro` | 5 ms | 1 ms | 0 |
    /// | `good` | 40 ms | 6 ms | 0.2 % |
    /// | `average` | 100 ms | 15 ms | 2 % |
    /// | `poor` | 200 ms | 30 ms | 10 % |
    /// | `intercontinental` | 160 ms | 10 ms | 1 % |
    /// | `burst` | 100 ms | 15 ms | Gilbert burst loss: `p_gb` 0.01, `p_bg` 0.2 (4.8 %, bursts of 5 packets on average) |
    /// | `outage` | 40 ms | 6 ms | 0.2 %, and everything lost from 3 s to 6 s after the link starts |
    ///
    /// `burst` is `average`'s delay with its independent loss replaced by a classic Gilbert
    /// chain ([`GilbertElliott::new`]`(0.01, 0.2)`): long-run loss `p_gb / (p_gb + p_bg)`
    /// = 4.8 %, mean burst `1 / p_bg` = 5 packets. Bursts are counted in packets, so their
    /// length in time depends on the flow: 40 ms of a tool's 125 input datagrams/s, but
    /// 0.2–0.25 s of a watching site's 20–25 packets/s. (Mean bursts of 20 packets, tried
    /// first, silenced watching sites for over a second often enough that the session's
    /// liveness check dropped them: that is the `outage` preset's case.)
    /// `outage` is `good` with a 3 s [`Outage`] mid-session.
    ///
    /// Presets do not reorder (`reorder = false`), have no rate cap and no duplication.
    pub fn preset(name: &str) -> Result<Self, ConfigError> {
        match name.to_ascii_lowercase().as_str() {
            "burst" => {
                return Ok(Self {
                    burst: Some(GilbertElliott::new(BURST_P_GB, BURST_P_BG)),
                    ..Self::preset("average")?
                }
                .without_random_loss());
            }
            "outage" => {
                return Ok(Self::preset("good")?.with_outage(OUTAGE_START_S, OUTAGE_DURATION_S));
            }
            _ => {}
        }
        let (delay_ms, jitter_ms, loss_pct) = match name.to_ascii_lowercase().as_str() {
            "none" | "off" => (0.0, 0.0, 0.0),
            "lan" => (0.2, 0.0, 0.0),
            "metro" => (5.0, 1.0, 0.0),
            "good" => (40.0, 6.0, 0.2),
            "average" => (100.0, 15.0, 2.0),
            "poor" => (200.0, 30.0, 10.0),
            "intercontinental" => (160.0, 10.0, 1.0),
            _ => return Err(ConfigError::UnknownPreset(name.to_string())),
        };
        Ok(Self {
            delay_ms,
            jitter_ms,
            loss_pct,
            ..Self::default()
        })
    }

    fn without_random_loss(mut self) -> Self {
        self.loss_pct = 0.0;
        self
    }

    /// Builder: set a scheduled outage.
    pub fn with_outage(mut self, start_s: f64, duration_s: f64) -> Self {
        self.outage = Some(Outage {
            start_s,
            duration_s,
        });
        self
    }

    /// True when the configuration cannot change any packet (except for an outage check).
    pub fn is_passthrough(&self) -> bool {
        self.delay_ms == 0.0
            && self.jitter_ms == 0.0
            && self.loss_pct == 0.0
            && self.burst.is_none()
            && self.dup_pct == 0.0
            && self.rate_kbps.is_none()
            && self.outage.is_none()
    }

    /// Check ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        fn check(
            field: &'static str,
            value: f64,
            lo: f64,
            hi: f64,
            range: &'static str,
        ) -> Result<(), ConfigError> {
            if value.is_finite() && value >= lo && value <= hi {
                Ok(())
            } else {
                Err(ConfigError::OutOfRange {
                    field,
                    value,
                    range,
                })
            }
        }
        check("delay", self.delay_ms, 0.0, 3.6e6, "0..=3600000 ms")?;
        check("jitter", self.jitter_ms, 0.0, 3.6e6, "0..=3600000 ms")?;
        check("loss", self.loss_pct, 0.0, 100.0, "0..=100 %")?;
        check("dup", self.dup_pct, 0.0, 100.0, "0..=100 %")?;
        if let Some(b) = &self.burst {
            check("burst p_gb", b.p_gb, 0.0, 1.0, "0..=1")?;
            check("burst p_bg", b.p_bg, 0.0, 1.0, "0..=1")?;
            check("burst loss_good", b.loss_good, 0.0, 1.0, "0..=1")?;
            check("burst loss_bad", b.loss_bad, 0.0, 1.0, "0..=1")?;
        }
        if let Some(r) = self.rate_kbps {
            check("rate", r, 1e-3, 1e9, "0.001..=1e9 kbit/s")?;
            check(
                "bucket",
                self.bucket_bytes as f64,
                1.0,
                1e9,
                "1..=1e9 bytes",
            )?;
        }
        if let Some(o) = &self.outage {
            check("outage start", o.start_s, 0.0, 1e9, "0..=1e9 s")?;
            check("outage duration", o.duration_s, 0.0, 1e9, "0..=1e9 s")?;
        }
        Ok(())
    }
}

/// Why a packet was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DropReason {
    /// Independent random loss.
    Loss,
    /// Gilbert–Elliott burst loss.
    Burst,
    /// Rate-cap queue overflow.
    Rate,
    /// Scheduled outage.
    Outage,
}

/// What happens to one packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    Drop(DropReason),
    /// Release times (same clock as `now_us`); more than one entry means duplicates.
    Deliver {
        at_us: Vec<u64>,
    },
}

/// Per-direction counters. Invariant: `sent == delivered + dropped()`; the number of datagrams
/// released is `delivered + duplicated`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    pub sent: u64,
    pub delivered: u64,
    pub dropped_loss: u64,
    pub dropped_burst: u64,
    pub dropped_rate: u64,
    pub dropped_outage: u64,
    /// Extra copies released.
    pub duplicated: u64,
    /// Released copies that overtake an earlier-released copy (only with `reorder`).
    pub reordered: u64,
    pub bytes_sent: u64,
    /// Bytes of delivered packets (duplicates not included).
    pub bytes_delivered: u64,
    /// Sum over delivered packets (duplicates not included) of the time each was held:
    /// delay, jitter, queueing behind the rate cap and, without `reorder`, waiting for an
    /// earlier packet (µs). See [`Counters::mean_delay_ms`].
    #[serde(default)]
    pub delay_sum_us: u64,
}

impl Counters {
    pub fn dropped(&self) -> u64 {
        self.dropped_loss + self.dropped_burst + self.dropped_rate + self.dropped_outage
    }

    /// Datagrams released (delivered + duplicates).
    pub fn released(&self) -> u64 {
        self.delivered + self.duplicated
    }

    /// Mean one-way delay the link added to its delivered packets (ms), as they
    /// experienced it: with jitter and no reordering this is above the configured delay,
    /// since a packet waits for every earlier one. `None` before any delivery.
    pub fn mean_delay_ms(&self) -> Option<f64> {
        (self.delivered > 0).then(|| self.delay_sum_us as f64 / self.delivered as f64 / 1e3)
    }

    pub fn add(&mut self, o: &Counters) {
        self.sent += o.sent;
        self.delivered += o.delivered;
        self.dropped_loss += o.dropped_loss;
        self.dropped_burst += o.dropped_burst;
        self.dropped_rate += o.dropped_rate;
        self.dropped_outage += o.dropped_outage;
        self.duplicated += o.duplicated;
        self.reordered += o.reordered;
        self.bytes_sent += o.bytes_sent;
        self.bytes_delivered += o.bytes_delivered;
        self.delay_sum_us += o.delay_sum_us;
    }
}

impl fmt::Display for Counters {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "sent {} ({} B), delivered {} ({} B), dropped {} [loss {}, burst {}, rate {}, outage {}], duplicated {}, reordered {}",
            self.sent,
            self.bytes_sent,
            self.delivered,
            self.bytes_delivered,
            self.dropped(),
            self.dropped_loss,
            self.dropped_burst,
            self.dropped_rate,
            self.dropped_outage,
            self.duplicated,
            self.reordered
        )
    }
}

/// Token-bucket shaper state.
#[derive(Debug, Clone, Default)]
struct Shaper {
    tokens: f64,
    /// Time at which `tokens` is valid (= departure of the last accepted packet).
    tb_time_us: u64,
    /// Departure times of packets still waiting (departure > arrival of the newest packet).
    queue: VecDeque<u64>,
    primed: bool,
}

/// The seeded per-direction model. Deterministic for a given config, seed and input sequence.
#[derive(Debug, Clone)]
pub struct Impairment {
    config: ImpairmentConfig,
    rng: ChaCha8Rng,
    ge_bad: bool,
    shaper: Shaper,
    /// Latest release time handed out so far.
    last_release_us: u64,
    counters: Counters,
}

impl Impairment {
    /// New model with its own ChaCha8 stream seeded from `seed`. Never panics: probabilities
    /// outside their range saturate (call [`ImpairmentConfig::validate`] to reject them).
    pub fn new(config: ImpairmentConfig, seed: u64) -> Self {
        Self {
            config,
            rng: ChaCha8Rng::seed_from_u64(seed),
            ge_bad: false,
            shaper: Shaper::default(),
            last_release_us: 0,
            counters: Counters::default(),
        }
    }

    pub fn config(&self) -> &ImpairmentConfig {
        &self.config
    }

    /// Replace the configuration, keeping counters, RNG and queue state.
    pub fn set_config(&mut self, config: ImpairmentConfig) {
        self.config = config;
    }

    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// Decide the fate of a packet of `len` bytes arriving at `now_us`.
    ///
    /// `now_us` should be non-decreasing between calls.
    pub fn on_packet(&mut self, now_us: u64, len: usize) -> Verdict {
        let c = &mut self.counters;
        c.sent += 1;
        c.bytes_sent += len as u64;

        if let Some(o) = &self.config.outage
            && o.contains(now_us)
        {
            c.dropped_outage += 1;
            return Verdict::Drop(DropReason::Outage);
        }
        if self.config.loss_pct > 0.0 && self.rng.random_bool(pct(self.config.loss_pct)) {
            c.dropped_loss += 1;
            return Verdict::Drop(DropReason::Loss);
        }
        if let Some(ge) = self.config.burst {
            let flip = if self.ge_bad { ge.p_bg } else { ge.p_gb };
            if self.rng.random_bool(prob(flip)) {
                self.ge_bad = !self.ge_bad;
            }
            let p = if self.ge_bad {
                ge.loss_bad
            } else {
                ge.loss_good
            };
            if p > 0.0 && self.rng.random_bool(prob(p)) {
                c.dropped_burst += 1;
                return Verdict::Drop(DropReason::Burst);
            }
        }
        let depart_us = match self.config.rate_kbps {
            Some(kbps) => match self.shape(now_us, len, kbps) {
                Some(t) => t,
                None => {
                    self.counters.dropped_rate += 1;
                    return Verdict::Drop(DropReason::Rate);
                }
            },
            None => now_us,
        };
        self.counters.delivered += 1;
        self.counters.bytes_delivered += len as u64;

        let mut at_us = Vec::with_capacity(1);
        let first = self.release_time(depart_us);
        self.counters.delay_sum_us += first.saturating_sub(now_us);
        at_us.push(first);
        if self.config.dup_pct > 0.0 && self.rng.random_bool(pct(self.config.dup_pct)) {
            self.counters.duplicated += 1;
            let second = self.release_time(depart_us);
            at_us.push(second);
        }
        Verdict::Deliver { at_us }
    }

    /// Token bucket + FIFO queue: departure time, or `None` when the queue is full.
    fn shape(&mut self, now_us: u64, len: usize, kbps: f64) -> Option<u64> {
        let bucket = self.config.bucket_bytes.max(1) as f64;
        let s = &mut self.shaper;
        if !s.primed {
            s.primed = true;
            s.tokens = bucket;
            s.tb_time_us = now_us;
        }
        while s.queue.front().is_some_and(|&t| t <= now_us) {
            s.queue.pop_front();
        }
        if s.queue.len() >= self.config.queue_pkts {
            return None;
        }
        let bytes_per_us = kbps * 1000.0 / 8.0 / 1e6;
        let start = now_us.max(s.tb_time_us);
        let tokens = (s.tokens + (start - s.tb_time_us) as f64 * bytes_per_us).min(bucket);
        let need = (len as f64).min(bucket);
        let depart = if tokens >= need {
            s.tokens = tokens - len as f64;
            start
        } else {
            let wait_us = ((need - tokens) / bytes_per_us).ceil();
            s.tokens = need - len as f64;
            start + wait_us as u64
        };
        s.tb_time_us = depart;
        if depart > now_us {
            s.queue.push_back(depart);
        }
        Some(depart)
    }

    fn release_time(&mut self, depart_us: u64) -> u64 {
        let cfg = &self.config;
        let mut d = cfg.delay_ms;
        if cfg.jitter_ms > 0.0 {
            d += match cfg.jitter_dist {
                JitterDist::Normal => Normal::new(0.0, cfg.jitter_ms)
                    .map(|n| n.sample(&mut self.rng))
                    .unwrap_or(0.0),
                JitterDist::Uniform => self.rng.random_range(-cfg.jitter_ms..=cfg.jitter_ms),
            };
        }
        let mut at = depart_us + (d.max(0.0) * 1000.0).round() as u64;
        if cfg.reorder {
            if at < self.last_release_us {
                self.counters.reordered += 1;
            }
        } else {
            at = at.max(self.last_release_us);
        }
        self.last_release_us = self.last_release_us.max(at);
        at
    }
}

fn prob(p: f64) -> f64 {
    if p.is_nan() { 0.0 } else { p.clamp(0.0, 1.0) }
}

fn pct(p: f64) -> f64 {
    prob(p / 100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deliver(v: &Verdict) -> &[u64] {
        match v {
            Verdict::Deliver { at_us } => at_us,
            Verdict::Drop(_) => &[],
        }
    }

    #[test]
    fn presets_parse_and_are_one_way() {
        for name in PRESET_NAMES {
            let c = ImpairmentConfig::preset(name).unwrap();
            c.validate().unwrap();
            assert!(!c.reorder);
        }
        let p = ImpairmentConfig::preset("poor").unwrap();
        assert_eq!((p.delay_ms, p.jitter_ms, p.loss_pct), (200.0, 30.0, 10.0));
        assert!(ImpairmentConfig::preset("moon").is_err());
    }

    #[test]
    fn passthrough_delivers_immediately() {
        let mut m = Impairment::new(ImpairmentConfig::none(), 1);
        for i in 0..100 {
            assert_eq!(
                m.on_packet(i * 10, 100),
                Verdict::Deliver {
                    at_us: vec![i * 10]
                }
            );
        }
        assert_eq!(m.counters().delivered, 100);
    }

    #[test]
    fn deterministic_for_seed() {
        let cfg = ImpairmentConfig::preset("poor").unwrap();
        let run = |seed| {
            let mut m = Impairment::new(cfg.clone(), seed);
            (0..1000)
                .map(|i| m.on_packet(i * 1000, 500))
                .collect::<Vec<_>>()
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7), run(8));
    }

    /// Loss fraction within 4 binomial standard deviations.
    #[test]
    fn loss_fraction_binomial() {
        for (loss, seed) in [(0.2, 1u64), (2.0, 2), (10.0, 3), (50.0, 4)] {
            let cfg = ImpairmentConfig {
                loss_pct: loss,
                ..Default::default()
            };
            let mut m = Impairment::new(cfg, seed);
            let n = 200_000u64;
            for i in 0..n {
                m.on_packet(i * 100, 100);
            }
            let c = m.counters();
            assert_eq!(c.sent, c.delivered + c.dropped());
            let p = loss / 100.0;
            let sd = (n as f64 * p * (1.0 - p)).sqrt();
            let dev = (c.dropped_loss as f64 - n as f64 * p).abs();
            assert!(
                dev < 4.0 * sd,
                "loss {loss}: {} lost, sd {sd}",
                c.dropped_loss
            );
        }
    }

    /// The mean delay counted is what the packets experienced: exactly the configured
    /// delay without jitter; with jitter and packet order kept, above it by the wait for
    /// earlier packets (compared with the release times the model returned).
    #[test]
    fn mean_delay_is_what_packets_experienced() {
        let steady = ImpairmentConfig {
            delay_ms: 40.0,
            ..Default::default()
        };
        let mut m = Impairment::new(steady, 1);
        assert_eq!(m.counters().mean_delay_ms(), None);
        for i in 0..100 {
            m.on_packet(i * 8_000, 100);
        }
        assert_eq!(m.counters().mean_delay_ms(), Some(40.0));

        let cfg = ImpairmentConfig::preset("poor").unwrap();
        let mut m = Impairment::new(cfg, 3);
        let mut held_us = Vec::new();
        for i in 0..20_000u64 {
            if let Verdict::Deliver { at_us } = m.on_packet(i * 8_000, 100) {
                held_us.push((at_us[0] - i * 8_000) as f64);
            }
        }
        let expected = held_us.iter().sum::<f64>() / held_us.len() as f64 / 1e3;
        let mean = m.counters().mean_delay_ms().unwrap();
        assert!((mean - expected).abs() < 1e-9, "{mean} against {expected}");
        // Packets 8 ms apart with 30 ms of jitter wait for one another.
        assert!(mean > 210.0, "{mean} ms");
    }

    fn mean_sd(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var.sqrt())
    }

    #[test]
    fn delay_distribution_normal_and_uniform() {
        let n = 100_000;
        for (dist, want_sd) in [
            (JitterDist::Normal, 15.0),
            (JitterDist::Uniform, 15.0 / 3f64.sqrt()),
        ] {
            let cfg = ImpairmentConfig {
                delay_ms: 100.0,
                jitter_ms: 15.0,
                jitter_dist: dist,
                reorder: true,
                ..Default::default()
            };
            let mut m = Impairment::new(cfg, 11);
            let mut delays = Vec::with_capacity(n);
            for i in 0..n as u64 {
                let now = i * 1000;
                let v = m.on_packet(now, 100);
                delays.push((deliver(&v)[0] - now) as f64 / 1000.0);
            }
            let (mean, sd) = mean_sd(&delays);
            // Standard error of the mean is 15/sqrt(1e5) ≈ 0.05 ms.
            assert!((mean - 100.0).abs() < 0.3, "{dist:?} mean {mean}");
            assert!((sd - want_sd).abs() < 0.02 * want_sd, "{dist:?} sd {sd}");
            if dist == JitterDist::Uniform {
                assert!(delays.iter().all(|&d| (84.999..=115.001).contains(&d)));
            }
            // Packets 1 ms apart with 15 ms jitter overtake each other often.
            assert!(m.counters().reordered > n as u64 / 10);
        }
    }

    #[test]
    fn no_reordering_when_disabled() {
        let cfg = ImpairmentConfig {
            delay_ms: 50.0,
            jitter_ms: 20.0,
            dup_pct: 5.0,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 5);
        let mut last = 0;
        for i in 0..50_000u64 {
            let now = i * 500;
            for &at in deliver(&m.on_packet(now, 100)) {
                assert!(at >= last, "release went backwards");
                assert!(at >= now);
                last = at;
            }
        }
        assert_eq!(m.counters().reordered, 0);
        assert!(m.counters().duplicated > 2000);
    }

    #[test]
    fn duplication_fraction() {
        let cfg = ImpairmentConfig {
            dup_pct: 10.0,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 9);
        let n = 100_000u64;
        let mut copies = 0u64;
        for i in 0..n {
            copies += deliver(&m.on_packet(i, 10)).len() as u64;
        }
        let c = m.counters();
        assert_eq!(copies, c.released());
        let sd = (n as f64 * 0.1 * 0.9).sqrt();
        assert!((c.duplicated as f64 - 0.1 * n as f64).abs() < 4.0 * sd);
    }

    #[test]
    fn rate_cap_throughput_and_queue_drops() {
        // 800 kbit/s = 100 kB/s; offer 1000-byte packets at 200 kB/s for 10 s.
        let cfg = ImpairmentConfig {
            rate_kbps: Some(800.0),
            bucket_bytes: 3000,
            queue_pkts: 50,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 3);
        let mut releases = Vec::new();
        for i in 0..2000u64 {
            let now = i * 5000; // 5 ms apart
            releases.extend_from_slice(deliver(&m.on_packet(now, 1000)));
        }
        let c = m.counters();
        assert_eq!(c.sent, c.delivered + c.dropped_rate);
        assert!(c.dropped_rate > 900, "{c}");
        // Throughput over the whole run: delivered bytes / span of departures.
        let span_s = (*releases.last().unwrap() - releases[0]) as f64 * 1e-6;
        let rate = (c.bytes_delivered - 1000) as f64 / span_s; // first packet starts the span
        assert!((rate - 100_000.0).abs() < 1000.0, "rate {rate} B/s");
        // Nothing departs before it arrives, and FIFO order holds.
        assert!(releases.windows(2).all(|w| w[0] <= w[1]));

        // Under the rate: no drops, no queueing beyond the packet's own transmission.
        let mut m = Impairment::new(
            ImpairmentConfig {
                rate_kbps: Some(800.0),
                queue_pkts: 5,
                ..Default::default()
            },
            3,
        );
        for i in 0..1000u64 {
            let now = i * 20_000; // 50 kB/s
            assert_eq!(deliver(&m.on_packet(now, 1000)), &[now]);
        }
        assert_eq!(m.counters().dropped_rate, 0);
    }

    #[test]
    fn rate_cap_bounds_queueing_delay() {
        let cfg = ImpairmentConfig {
            rate_kbps: Some(80.0), // 10 kB/s: a 1000-byte packet every 100 ms
            bucket_bytes: 1000,
            queue_pkts: 10,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 3);
        let mut max_wait = 0;
        for i in 0..1000u64 {
            let now = i * 10_000;
            if let Verdict::Deliver { at_us } = m.on_packet(now, 1000) {
                max_wait = max_wait.max(at_us[0] - now);
            }
        }
        // At most 10 queued packets ahead + own transmission: ≤ 1.1 s.
        assert!((900_000..=1_100_000).contains(&max_wait), "{max_wait}");
    }

    #[test]
    fn gilbert_elliott_burst_length() {
        let ge = GilbertElliott::new(0.01, 0.25);
        let cfg = ImpairmentConfig {
            burst: Some(ge),
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 17);
        let n = 400_000u64;
        let mut bursts = Vec::new();
        let mut run = 0u64;
        for i in 0..n {
            match m.on_packet(i * 100, 100) {
                Verdict::Drop(DropReason::Burst) => run += 1,
                Verdict::Drop(r) => panic!("unexpected {r:?}"),
                Verdict::Deliver { .. } => {
                    if run > 0 {
                        bursts.push(run as f64);
                    }
                    run = 0;
                }
            }
        }
        let (mean, sd) = mean_sd(&bursts);
        // Geometric with mean 1/p_bg = 4, sd sqrt(1-p)/p ≈ 3.46.
        let se = sd / (bursts.len() as f64).sqrt();
        assert!((mean - 4.0).abs() < 4.0 * se, "mean burst {mean} (se {se})");
        let loss = m.counters().dropped_burst as f64 / n as f64;
        let want = ge.stationary_loss();
        assert!((loss - want).abs() < 0.15 * want, "loss {loss} want {want}");
    }

    #[test]
    fn outage_window() {
        let cfg = ImpairmentConfig::preset("lan")
            .unwrap()
            .with_outage(1.0, 2.0);
        let mut m = Impairment::new(cfg, 1);
        for ms in 0..5000u64 {
            let v = m.on_packet(ms * 1000, 100);
            let in_outage = (1000..3000).contains(&ms);
            assert_eq!(
                matches!(v, Verdict::Drop(DropReason::Outage)),
                in_outage,
                "{ms}"
            );
        }
        let c = m.counters();
        assert_eq!(c.dropped_outage, 2000);
        assert_eq!(c.delivered, 3000);
    }

    #[test]
    fn validate_rejects_bad_values() {
        let bad = ImpairmentConfig {
            loss_pct: 150.0,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let bad = ImpairmentConfig {
            burst: Some(GilbertElliott::new(2.0, 0.1)),
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }

    /// Loss rate and mean burst of a classic Gilbert chain, measured over `n` packets.
    fn gilbert_measure(ge: GilbertElliott, seed: u64, n: u64) -> (f64, f64, usize) {
        let cfg = ImpairmentConfig {
            burst: Some(ge),
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, seed);
        let (mut lost, mut run, mut bursts, mut burst_sum) = (0u64, 0u64, 0usize, 0u64);
        for i in 0..n {
            if matches!(m.on_packet(i * 100, 100), Verdict::Drop(_)) {
                lost += 1;
                run += 1;
            } else if run > 0 {
                bursts += 1;
                burst_sum += run;
                run = 0;
            }
        }
        let mean_burst = burst_sum as f64 / bursts.max(1) as f64;
        (lost as f64 / n as f64, mean_burst, bursts)
    }

    #[test]
    fn burst_preset_matches_its_closed_form() {
        let c = ImpairmentConfig::preset("burst").unwrap();
        assert_eq!(c.loss_pct, 0.0);
        let ge = c.burst.unwrap();
        assert!((ge.stationary_loss() - 0.01 / 0.21).abs() < 1e-12);
        assert_eq!(ge.mean_bad_run(), 5.0);
        // 2 M packets: ~19,000 bursts; the burst mean (geometric, sd = √0.8 / 0.2 ≈ 4.47)
        // has a standard error of ≈ 0.03 packets (4 se allowed); the loss rate is held to
        // 10 %.
        let (loss, mean_burst, bursts) = gilbert_measure(ge, 5, 2_000_000);
        let se_burst = 0.8f64.sqrt() / 0.2 / (bursts as f64).sqrt();
        assert!(
            (mean_burst - 5.0).abs() < 4.0 * se_burst,
            "mean burst {mean_burst} packets over {bursts} bursts"
        );
        assert!(
            (loss - ge.stationary_loss()).abs() < 0.1 * ge.stationary_loss(),
            "loss {loss}"
        );
        let o = ImpairmentConfig::preset("outage").unwrap().outage.unwrap();
        assert_eq!((o.start_s, o.duration_s), (3.0, 3.0));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(16))]
        /// For any classic Gilbert chain, the measured loss rate and mean burst length match
        /// the closed forms `p_gb / (p_gb + p_bg)` and `1 / p_bg` (tolerances: several
        /// standard errors of 400,000 packets; bursts counted only with enough of them).
        #[test]
        fn gilbert_loss_and_burst_follow_closed_form(
            p_gb in 0.002f64..0.05, p_bg in 0.05f64..0.8, seed: u64,
        ) {
            let ge = GilbertElliott::new(p_gb, p_bg);
            let (loss, mean_burst, bursts) = gilbert_measure(ge, seed, 400_000);
            let want = ge.stationary_loss();
            // Loss indicators are correlated over ~1/(p_gb+p_bg) packets: the standard error
            // of the rate is about sqrt(want (1-want) / n * (2/(p_gb+p_bg))).
            let corr = 2.0 / (p_gb + p_bg);
            let se = (want * (1.0 - want) / 400_000.0 * corr).sqrt();
            proptest::prop_assert!((loss - want).abs() < 5.0 * se, "loss {} want {} se {}", loss, want, se);
            let sd = (1.0 - p_bg).sqrt() / p_bg;
            let se_b = sd / (bursts as f64).sqrt();
            proptest::prop_assert!(
                (mean_burst - ge.mean_bad_run()).abs() < 5.0 * se_b + 1e-9,
                "burst {} want {} se {}", mean_burst, ge.mean_bad_run(), se_b
            );
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// For any configuration: every packet is accounted for, nothing is released before it
        /// arrives, and without `reorder` releases never go backwards.
        #[test]
        fn accounting_invariants(
            delay in 0.0f64..50.0, jitter in 0.0f64..20.0, reorder: bool, loss in 0.0f64..30.0,
            burst: bool, dup in 0.0f64..20.0, rate in proptest::option::of(10.0f64..5000.0),
            queue in 1usize..50, seed: u64,
            gaps in proptest::collection::vec((0u64..5000, 1usize..1500), 1..400),
        ) {
            let cfg = ImpairmentConfig {
                delay_ms: delay, jitter_ms: jitter, reorder, loss_pct: loss,
                burst: burst.then(|| GilbertElliott::new(0.05, 0.3)), dup_pct: dup,
                rate_kbps: rate, queue_pkts: queue, ..Default::default()
            };
            let mut m = Impairment::new(cfg, seed);
            let (mut now, mut last, mut released) = (0u64, 0u64, 0u64);
            for (gap, len) in gaps {
                now += gap;
                for &at in deliver(&m.on_packet(now, len)) {
                    proptest::prop_assert!(at >= now);
                    if !reorder {
                        proptest::prop_assert!(at >= last);
                    }
                    last = last.max(at);
                    released += 1;
                }
            }
            let c = m.counters();
            proptest::prop_assert_eq!(c.sent, c.delivered + c.dropped());
            proptest::prop_assert_eq!(released, c.released());
            if rate.is_none() {
                proptest::prop_assert_eq!(c.dropped_rate, 0);
            }
        }
    }
}
