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

    /// The same path for a session run `factor` times slower than real time (time
    /// dilation, `cosurg bench sync --time-scale`): delays, jitter and the outage
    /// stretched by `factor`, the rate cap divided by it; losses are per packet and stay.
    /// In the session's own time the dilated path is the original one.
    pub fn dilated(&self, factor: f64) -> Self {
        let mut c = self.clone();
        c.delay_ms *= factor;
        c.jitter_ms *= factor;
        c.rate_kbps = c.rate_kbps.map(|r| r / factor);
        c.outage = c.outage.map(|o| Outage {
            start_s: o.start_s * factor,
            duration_s: o.duration_s * factor,
        });
        c
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
mod tests;
