//! Pacing a site's simulation clock against the sites it follows: the playout lag.
//!
//! A site that shows regions owned by another site (or simulates another site's tool under
//! input-only) receives that site's keyframes and poses one network delay after they were
//! produced. Running at the owner's simulation time, it could only extrapolate from the
//! past; at a grasp release (tissue springs back in 0.3 s) extrapolation is wrong by tens
//! of millimetres. So a *follower* keeps its simulation time about `L` behind the owner's
//! current simulation time — like entity interpolation in game networking or a jitter
//! buffer — and frames arrive before its clock reaches them: each is applied at its exact
//! simulation time and the region is interpolated between consecutive keyframes.
//!
//! * `L` is `--playout-lag auto` (smoothed one-way delay owner → coordinator → us, plus a
//!   jitter margin of four mean deviations, plus one keyframe interval; capped at
//!   [`MAX_AUTO_LAG`]) or a fixed value (`0`: no lag, the behaviour before playout lag).
//! * Under hybrid sync the follower simulates the owner's tool from its input samples and
//!   only needs those in time; keyframes merely correct it, and a late one is skipped. So
//!   `auto` there follows the inputs' path alone: smoothed one-way delay of the time
//!   stamps (they travel like the inputs, as datagrams) plus [`HYBRID_JITTER_DEVS`] mean
//!   deviations plus one input-datagram interval (a lost datagram's samples come in the
//!   next one), capped only at [`MAX_HYBRID_LAG`] (a safety stop, not a tuning). Keyframe
//!   ages, which include stream retransmissions, do not raise it. Inputs that still come
//!   later than the lag by more than the tools are carried on past their newest sample
//!   ([`INPUT_EXTRAPOLATION_S`]) raise it ([`PeerClocks::input_shortfall`]).
//! * The followed sites' current times are estimated from their stamps' *send* times
//!   (clocks synchronised with the coordinator's), not their arrivals: over a path that
//!   keeps packet order, stamps arrive bunched behind a delayed one, and a rate taken from
//!   arrivals put the owner up to 0.4 s ahead of where it was (measured under `poor`:
//!   the follower then held back twice the path's delay, 1.0–1.1 s).
//! * The lag is reached and kept by slewing the step rate within
//!   [`MIN_RATE`]–[`MAX_RATE`] of real time (under hybrid up to [`HYBRID_MAX_RATE`], and
//!   [`HYBRID_CATCH_UP_RATE`] when far behind), never by jumps.
//! * A *leading* site (its tool moved within the last half second, or, except under
//!   hybrid, it owns or has claimed a region) keeps no lag: it runs level with the
//!   other leaders it follows, so two owners following each other never wait for each
//!   other. When ownership moves, or a resting tool begins to move, the new leader
//!   catches up and the old one falls back to the lag (under hybrid a follower gets there
//!   by waiting, see [`HYBRID_HOLD_BEYOND`]; a leader ahead of one catching up keeps real
//!   time).
//! * Under hybrid a site follows the sites whose tools move, not the owners: it simulates
//!   every region from the inputs, so a still owner (holding an organ) keeps the lag
//!   behind a moving site like any follower, and sees that site's tool in time.
//! * Independently of the lag, a site never runs more than [`MAX_LEAD`] ahead of an owner
//!   it follows (owners' keyframes would arrive from its past); during a change of leader
//!   that cap is relaxed by [`MAX_AUTO_LAG`] so that the change slews instead of freezing
//!   the old leader. Not under hybrid, where a late keyframe is compared with the local
//!   history at its time (up to `sim_core::sync::HybridConfig::max_history_age_s`, 1 s:
//!   a still owner's keyframes come a path's delay late) or skipped.
//!
//! Sans-IO: every time is passed in (wall seconds since any fixed origin), so the pacing
//! is unit-tested with a fake clock.

use std::collections::{BTreeMap, BTreeSet, HashMap};

/// How far (s of simulated time) a site may run ahead of the owners it follows.
pub const MAX_LEAD: f64 = 0.03;
/// Largest automatic playout lag (s).
pub const MAX_AUTO_LAG: f64 = 0.6;
/// One keyframe interval during motion (s): the owner sends at most every 30 ms
/// (`SyncConfig::min_interval_s`), and interpolation needs the next keyframe in hand.
pub const KEYFRAME_INTERVAL: f64 = 0.04;
/// Under hybrid: jitter margin of the automatic lag, in mean deviations of the delay. A
/// sample later than the lag leaves the remote tool carried on at its last rate for up to
/// [`INPUT_EXTRAPOLATION_S`] (and the owner's keyframes correct what that changes), so
/// the lag needs no margin above the inputs' mean transit: measured with `cosurg bench
/// sync` (2026-11-25, 19:30 UTC, three seeds of good, average, poor, intercontinental and
/// burst), 0.5 deviations with 80 ms of extrapolation gave display delays 15–45 ms above
/// the path as its packets experienced it, none with 150 ms gave 8–29 ms; divergence
/// ≤ 1.4 and ≤ 2.3 mm (earlier, 1.0 deviation with 40 ms: 94–148 ms above the path's
/// nominal delay under poor).
pub const HYBRID_JITTER_DEVS: f64 = 0.0;
/// Under hybrid: the interval of the input datagrams (s, `session::POSE_HISTORY_INTERVAL`).
const HYBRID_INPUT_INTERVAL: f64 = 0.008;
/// Under hybrid: a follower this far (s) short of its target lag waits instead of slewing.
const HYBRID_HOLD_BEYOND: f64 = 0.02;
/// A follower within this much (s) of its target lag has reached it (for the report's
/// display delay without a late start's catch-up, `SessionStats::lag_reached_at`).
pub const LAG_REACHED_WITHIN: f64 = HYBRID_HOLD_BEYOND;
/// Under hybrid: largest automatic playout lag (s).
pub const MAX_HYBRID_LAG: f64 = 2.0;
/// Under hybrid: headroom (s) the automatic lag keeps above the largest input shortfall
/// seen (one input datagram interval and one 4 ms step).
const INPUT_HEADROOM: f64 = HYBRID_INPUT_INTERVAL + 0.004;
/// How far (s of simulated time) a remote tool's motion is carried on past its newest
/// sample (the site's pose tracks). An input later than the follower's clock by less than
/// this costs little (the tool moved on at its last rate, and the owner's keyframes
/// correct the rest), so the automatic lag only grows for inputs later than that. 150 ms
/// covers the jitter of every preset (`poor`: 30 ms per hop, and a packet waits for the
/// ones before it); see [`HYBRID_JITTER_DEVS`] for the measurement.
pub const INPUT_EXTRAPOLATION_S: f64 = 0.15;
/// Under hybrid: how fast (s of lag per wall s) the lag floor set by input shortfalls
/// comes back down while the inputs arrive in time.
const INPUT_FLOOR_DECAY: f64 = 0.01;
/// Under hybrid: a sample later than this (s) is not taken as a measure of the path (the
/// first samples after an outage or a reconnection).
const MAX_INPUT_SHORTFALL: f64 = 0.5;
/// Slowest and fastest step rate while slewing towards the target lag (× real time).
pub const MIN_RATE: f64 = 0.8;
pub const MAX_RATE: f64 = 1.05;
/// Under hybrid: fastest step rate while catching up to a smaller target lag (× real
/// time): a follower that built too large a lag (early delay estimates are high) gets back
/// to it in seconds, not tens of seconds.
pub const HYBRID_MAX_RATE: f64 = 1.25;
/// Under hybrid: a follower more than this (s) behind its target lag catches up at up to
/// [`HYBRID_CATCH_UP_RATE`], as fast as its processor allows. It is that far behind when it
/// learned late that the session started (the message that completes it travels on a
/// reliable stream, and under `poor` a lost packet and its retransmission timeouts cost a
/// site up to 1.6 s: measured with `cosurg bench sync --time-scale 3`, 2026-11-27), and at
/// 1.25× such a start took 6 s to make up, raising the run's mean display delay by
/// 230 ms. The view fast-forwards for a fraction of a second instead.
const HYBRID_CATCH_UP_BEYOND: f64 = 0.25;
/// Under hybrid: fastest step rate while far behind the target lag (× real time).
pub const HYBRID_CATCH_UP_RATE: f64 = 3.0;
/// Rate change per second of lag error (1/s): an error of 0.1 s slews at 0.8× or 1.02×.
const GAIN: f64 = 2.0;
/// A remote tool counts as active (its site is followed) this long after its last pose
/// (wall s).
const TOOL_ACTIVE_FOR: f64 = 0.5;
/// A tool pose this far (s of simulated time) or more after the one before it is not
/// part of a driven tool's stream (a driven tool sends every step or every 16 ms): it is a
/// resting tool's announcement (every 0.25 s, `site::tools::IDLE_POSE_INTERVAL_S`), or the
/// first pose of a new stream, and does not make its site followed.
const TOOL_STREAM_GAP_S: f64 = 0.1;
/// A tool pose that differs from the tool's last one by no more than this in every
/// coordinate (m, unit quaternion, rad) did not move: a script holding a pose interpolates
/// between equal waypoints to within rounding.
const TOOL_STILL: f32 = 1e-6;
/// A site unheard for this long (wall s) is not assumed to advance any further.
const SILENT_AFTER: f64 = 0.5;
/// Transit samples outside 0..this (s) come from clocks not yet synchronised; ignored.
const MAX_TRANSIT: f64 = 5.0;
/// For this long (wall s) after a followed site appears mid-session (a join, or a rejoin
/// under a new id) or our own link comes back, samples carry the gap, not the path: input
/// shortfalls and stamp transits (of every site: one estimate serves them all) neither
/// raise the hybrid lag nor enter the delay estimate. It starts when a site is first
/// heard and again when its clock first advances: a site waiting to start announces
/// itself with stamps of a clock that stands still (`SiteSession::announce_presence`),
/// up to seconds before its first step. At a session's start this also holds for a
/// second once a second site is heard; keyframe ages (the keyframe lag model) are not
/// held back. Measured after the
/// `outage` preset's cut: inputs 0.4–0.6 s late and stamp transits of 0.2–0.4 s on a
/// 80 ms path, which left a trainee's lag at 430–670 ms for the rest of the run.
const QUIET_AFTER_JOIN_S: f64 = 1.0;

/// `--playout-lag`: `auto` or milliseconds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PlayoutLag {
    /// From the measured delay and jitter (see the module documentation).
    Auto,
    /// Fixed lag (s); 0 disables the lag.
    Fixed(f64),
}

impl PlayoutLag {
    /// Whether followers keep any lag at all.
    pub fn enabled(self) -> bool {
        !matches!(self, PlayoutLag::Fixed(l) if l <= 0.0)
    }
}

impl std::str::FromStr for PlayoutLag {
    type Err = String;
    /// `auto` or a number of milliseconds (`0`: no lag).
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(PlayoutLag::Auto);
        }
        match s.trim_end_matches("ms").parse::<f64>() {
            Ok(ms) if ms.is_finite() && ms >= 0.0 => Ok(PlayoutLag::Fixed(ms / 1e3)),
            _ => Err(format!(
                "--playout-lag {s:?}: expected `auto` or milliseconds ≥ 0"
            )),
        }
    }
}

impl std::fmt::Display for PlayoutLag {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlayoutLag::Auto => f.write_str("auto"),
            PlayoutLag::Fixed(l) => write!(f, "{}", l * 1e3),
        }
    }
}

/// Smoothed delay and its mean deviation (RFC 6298's estimator, in seconds).
#[derive(Clone, Copy, Debug, Default)]
struct DelayFilter {
    mean: Option<f64>,
    dev: f64,
    /// Deviation assumed with the first sample, as a fraction of it (RFC 6298: ½).
    first_dev: f64,
}

impl DelayFilter {
    fn sample(&mut self, d: f64) {
        match self.mean {
            None => {
                self.mean = Some(d);
                self.dev = d * self.first_dev;
            }
            Some(m) => {
                self.dev = 0.75 * self.dev + 0.25 * (d - m).abs();
                self.mean = Some(0.875 * m + 0.125 * d);
            }
        }
    }

    /// Delay plus a jitter margin of `devs` deviations (s).
    fn with_margin(&self, devs: f64) -> Option<f64> {
        self.mean.map(|m| m + devs * self.dev)
    }
}

/// Another site's simulation clock from its time stamps.
#[derive(Clone, Copy, Debug)]
struct PeerClock {
    /// Simulation time of the last stamp (s) and when it was heard (wall s).
    sim_time: f64,
    heard_at: f64,
    /// When the last stamp left its site (our wall s: heard minus its own measured
    /// transit), when the clocks are synchronised.
    sent_at: Option<f64>,
    /// Simulated seconds per wall second.
    rate: f64,
    /// Smoothed one-way transit of its stamps to us (s), when measured.
    transit: Option<f64>,
    /// Whether this stamp's simulation time is past the one before (false for the first
    /// stamp heard and for a clock standing still: a site waiting to start).
    advancing: bool,
    /// Whether its clock was ever seen to advance, and whether, before that, it was seen
    /// standing still (a site waiting to start).
    moved: bool,
    waited: bool,
}

/// What the pacing asks of the next step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pace {
    /// Step rate (× real time).
    pub rate: f64,
    /// How far our simulation time is behind the followed sites' estimated current time
    /// (s), while following as a non-leader (the "display delay").
    pub behind: Option<f64>,
    /// Wall time to wait before the next step (s): hard cap on running ahead of an owner,
    /// or (without real-time pacing) holding the lag.
    pub hold: f64,
}

/// A tool pose as [`PeerClocks::tool_pose`] compares it: position (m), orientation
/// (wxyz), jaw (rad).
pub fn pose_key(position: [f32; 3], orientation: [f32; 4], jaw: f32) -> [f32; 8] {
    let [x, y, z] = position;
    let [w, i, j, k] = orientation;
    [x, y, z, w, i, j, k, jaw]
}

/// Other sites' simulation clocks, which of them this site follows, and the playout lag.
#[derive(Clone, Debug)]
pub struct PeerClocks {
    peers: HashMap<u16, PeerClock>,
    /// Regions owned by other sites, and their owners.
    pub owners: BTreeMap<u32, u16>,
    /// Sites whose tool poses we receive, and when the last one was heard (wall s).
    tools: HashMap<u16, f64>,
    /// Simulation time of the newest tool pose of each site (s).
    tool_times: HashMap<u16, f64>,
    /// The newest pose of each site's tools (see [`PeerClocks::tool_pose`]).
    tool_poses: HashMap<(u16, u8), [f32; 8]>,
    /// One-way delay from the followed sites to us: stamp transits and (except under
    /// hybrid) keyframe ages.
    delay: DelayFilter,
    lag: PlayoutLag,
    /// Hybrid sync: the lag follows the input path only (see the module documentation).
    inputs_only: bool,
    /// Hybrid sync: a lag (s) found too short by the inputs themselves (see
    /// [`PeerClocks::input_shortfall`]), and when it was last raised or decayed (wall s).
    input_floor: f64,
    input_floor_at: f64,
    /// Until this wall time (s) samples say nothing of the path ([`QUIET_AFTER_JOIN_S`]).
    quiet_until: f64,
}

impl PeerClocks {
    pub fn new(lag: PlayoutLag) -> Self {
        PeerClocks {
            peers: HashMap::new(),
            owners: BTreeMap::new(),
            tools: HashMap::new(),
            tool_times: HashMap::new(),
            tool_poses: HashMap::new(),
            delay: DelayFilter {
                mean: None,
                dev: 0.0,
                first_dev: 0.5,
            },
            lag,
            inputs_only: false,
            input_floor: 0.0,
            input_floor_at: 0.0,
            quiet_until: f64::NEG_INFINITY,
        }
    }

    /// Our link came back at `now` (wall s): see [`QUIET_AFTER_JOIN_S`].
    pub fn quiet(&mut self, now: f64) {
        self.quiet_until = self.quiet_until.max(now + QUIET_AFTER_JOIN_S);
    }

    /// Under hybrid, a new input sample of a remote tool this follower simulates arrived
    /// `shortfall` seconds after its time (`at`, s: the simulated time the follower is
    /// about to step to, minus the sample's; negative: that much early) at wall time
    /// `now` (s). A shortfall beyond what the pose tracks carry on
    /// ([`INPUT_EXTRAPOLATION_S`]) means the lag was too short for the inputs' real path
    /// (a jitter spike the delay estimate's margin does not cover): the lag must grow by
    /// the uncovered part and a margin. The floor this sets rises at once and decays
    /// slowly ([`INPUT_FLOOR_DECAY`]) while the inputs are in time. (The 50–170 ms
    /// shortfalls measured under `poor` on 2026-11-24 were most likely the owner's time
    /// misestimated from bunched arrivals, see [`PeerClocks::heard`].) Only the samples of
    /// a site this follower follows raise it: a tool held still is carried on exactly, and
    /// a site whose tool rests keeps a lag of its own, so its samples come late by that
    /// lag. Counted, they raised two trainees' lags in turn, each by the other's, to
    /// 0.95 s within 3 s of the default demo under `average`.
    pub fn input_shortfall(&mut self, site: u16, shortfall: f64, at: f64, now: f64) {
        if !self.inputs_only
            || !shortfall.is_finite()
            || shortfall > MAX_INPUT_SHORTFALL
            || now < self.quiet_until
        {
            return;
        }
        let elapsed = (now - self.input_floor_at).max(0.0);
        self.input_floor = (self.input_floor - INPUT_FLOOR_DECAY * elapsed).max(0.0);
        self.input_floor_at = now;
        let uncovered = shortfall - INPUT_EXTRAPOLATION_S;
        if uncovered + INPUT_HEADROOM > 0.0 && self.followed(now).contains(&site) {
            let behind = self
                .followed(now)
                .into_iter()
                .filter_map(|s| self.estimate_now(s, now))
                .reduce(f64::min)
                .map(|lead| lead - at);
            // A follower that has not reached its lag yet (the session just started, or a
            // tool just began to move) is early by construction: its late samples say
            // nothing of the path. Measured: without this, the first samples of a run
            // under `poor` set the floor to about 1 s for the rest of it.
            let settled = |behind: f64| behind >= self.target_lag() - HYBRID_HOLD_BEYOND;
            if let Some(behind) = behind.filter(|b| settled(*b)) {
                let needed = behind + uncovered + INPUT_HEADROOM;
                self.input_floor = self.input_floor.max(needed.min(MAX_HYBRID_LAG));
            }
        }
    }

    /// The lag model of `strategy`: under hybrid the inputs' path alone.
    pub fn for_strategy(mut self, strategy: sim_core::sync::SyncStrategy) -> Self {
        self.inputs_only = strategy == sim_core::sync::SyncStrategy::Hybrid;
        if self.inputs_only {
            // The inputs' lag grows only as far as measured jitter asks: no assumed
            // deviation, no round-trip seed (the handshake's round trip includes its
            // retransmissions on a lossy path).
            self.delay.first_dev = 0.0;
        }
        self
    }

    /// A time stamp of `site`: simulation time `sim_time` (s) heard at `now` (wall s);
    /// `transit` is its measured one-way transit (s) when both clocks are synchronised
    /// with the coordinator's.
    pub fn heard(&mut self, site: u16, sim_time: f64, now: f64, transit: Option<f64>) {
        let transit = transit.filter(|d| (0.0..MAX_TRANSIT).contains(d));
        let prev = self.peers.get(&site).copied();
        let advancing = prev.is_some_and(|p| sim_time > p.sim_time);
        let starts_moving = advancing && prev.is_some_and(|p| p.waited && !p.moved);
        if (prev.is_none() || starts_moving) && self.delay.mean.is_some() {
            // A site that appears, or starts its clock, once the session runs: see
            // `QUIET_AFTER_JOIN_S`.
            self.quiet(now);
        }
        let sent_at = transit.map(|d| now - d);
        // The rate is measured between send times where both are known: arrival times
        // carry the path's jitter (stamps 50 ms apart may arrive together after a
        // delayed packet), and a rate of 1.6 taken from them put the owner 0.3 s ahead of
        // where it was over a 0.45 s transit (measured under `poor`). Only between two
        // stamps of a running clock: across the last stamp of a clock that stood still (a
        // site waiting to start) it would count the wait, and across a site's first stamp
        // the time before it.
        let rate = match prev {
            Some(p) if advancing && p.advancing => {
                let measured = match (p.sent_at, sent_at) {
                    (Some(a), Some(b)) if b > a => Some((sim_time - p.sim_time) / (b - a)),
                    (Some(_), Some(_)) => None,
                    _ => (now > p.heard_at).then(|| (sim_time - p.sim_time) / (now - p.heard_at)),
                };
                // Smooth: stamps are 50 ms of simulated time apart.
                measured.map_or(p.rate, |m| (0.8 * p.rate + 0.2 * m).clamp(0.05, 2.0))
            }
            Some(p) => p.rate,
            None => 1.0,
        };
        let smoothed = match (prev.and_then(|p| p.transit), transit) {
            (Some(old), Some(d)) => Some(0.875 * old + 0.125 * d),
            (old, d) => d.or(old),
        };
        if let Some(d) = transit
            && now >= self.quiet_until
        {
            self.delay.sample(d);
        }
        self.peers.insert(
            site,
            PeerClock {
                sim_time,
                heard_at: now,
                sent_at,
                rate,
                transit: smoothed,
                advancing,
                moved: advancing || prev.is_some_and(|p| p.moved),
                waited: prev.is_some_and(|p| p.waited || (!p.moved && sim_time == p.sim_time)),
            },
        );
    }

    /// The sites whose clock stamps we have heard.
    pub fn stamped_sites(&self) -> impl Iterator<Item = u16> + '_ {
        self.peers.keys().copied()
    }

    /// A tool pose of `site` arrived at `now` (wall s): its site is followed for a while.
    pub fn tool_heard(&mut self, site: u16, now: f64) {
        self.tools.insert(site, now);
    }

    /// A tool pose of `site`'s tool `tool` with simulation time `sim_time` (s; the newest
    /// of a datagram) and `pose` (position m, orientation wxyz, jaw rad) arrived at `now`
    /// (wall s): its site is followed ([`Self::tool_heard`]) if the pose continues a
    /// driven tool's stream ([`TOOL_STREAM_GAP_S`]) and moved since the tool's last pose
    /// ([`TOOL_STILL`]). Followers of resting tools' announcements would pace against
    /// sites that drive nothing: the sites of a session, each following the others,
    /// slowed one another to 0.9× real time (measured in the default demo, 225 Hz instead
    /// of 250). The same holds for a tool its script or hand holds still: its site does
    /// not lead (`site::Tools::local_moving`), and sites following one another's still
    /// tools held each other back to 59 Hz.
    pub fn tool_pose(&mut self, site: u16, tool: u8, sim_time: f64, pose: [f32; 8], now: f64) {
        let previous = self.tool_times.insert(site, sim_time);
        let moved = self
            .tool_poses
            .insert((site, tool), pose)
            .is_none_or(|old| {
                old.iter()
                    .zip(&pose)
                    .any(|(a, b)| (a - b).abs() > TOOL_STILL)
            });
        if moved && previous.is_some_and(|p| sim_time > p && sim_time - p < TOOL_STREAM_GAP_S) {
            self.tool_heard(site, now);
        }
    }

    /// A keyframe of `owner` with simulation time `sim_time` arrived at `now`: its age
    /// (how long after its simulation time it arrived) is a delay sample that includes
    /// stream retransmissions and the sender's queue.
    pub fn keyframe_arrived(&mut self, owner: u16, sim_time: f64, now: f64) {
        if self.inputs_only {
            return;
        }
        if let Some(est) = self.estimate_now(owner, now) {
            let age = est - sim_time;
            if (0.0..MAX_TRANSIT).contains(&age) {
                self.delay.sample(age);
            }
        }
    }

    /// A delay estimate (s) to start from before any sample (e.g. the round trip to the
    /// coordinator: two one-way hops).
    pub fn seed_delay(&mut self, d: f64) {
        if !self.inputs_only && self.delay.mean.is_none() && d.is_finite() && d >= 0.0 {
            self.delay.sample(d);
        }
    }

    /// The sites this site follows now: owners of regions it shows and sites whose tool
    /// poses are arriving and moving. Under hybrid the moving tools alone: a follower
    /// simulates every region from the inputs, so only the inputs need to be in time,
    /// and the tool of an owner that holds still is carried on exactly. (Following owners
    /// there made a still owner, holding the gallbladder, lead and simulate a moving
    /// site's hook from late samples; see [`PeerClocks::leads_by_claims`].)
    fn followed(&self, now: f64) -> BTreeSet<u16> {
        let owners = (!self.inputs_only).then_some(&self.owners);
        owners
            .into_iter()
            .flat_map(|o| o.values().copied())
            .chain(
                self.tools
                    .iter()
                    .filter(|(_, at)| now - **at <= TOOL_ACTIVE_FOR)
                    .map(|(s, _)| *s),
            )
            .collect()
    }

    /// Whether a site that claims or owns regions leads for that alone. Not under hybrid:
    /// there a site leads while its tool moves, and a still owner keeps the playout lag
    /// behind the moving sites, so it simulates their tools from samples in time.
    /// Measured in the default demo: the instructor, holding the gallbladder still and
    /// leading by its claims, simulated trainee B's hook from samples a path's delay late
    /// at the end of the dissection, and both trainees, which agreed with each other,
    /// showed 2–4 mm (`average`) and 5–8 mm (`poor`) against it.
    pub fn leads_by_claims(&self) -> bool {
        !self.inputs_only
    }

    /// Estimated current simulation time of `site` (s): its last stamp advanced by its
    /// rate since the stamp was sent (clocks synchronised), else over the smoothed
    /// transit and the time since it was heard.
    fn estimate_now(&self, site: u16, now: f64) -> Option<f64> {
        let p = self.peers.get(&site)?;
        if let Some(sent) = p.sent_at {
            return Some(p.sim_time + p.rate * (now - sent));
        }
        let transit = p.transit.or(self.delay.mean).unwrap_or(0.0);
        Some(p.sim_time + p.rate * (now - p.heard_at + transit))
    }

    /// Simulation time of `site` as last heard, advanced by its rate (s): the time of the
    /// messages arriving from it now.
    fn heard_time(&self, site: u16, now: f64) -> Option<f64> {
        let p = self.peers.get(&site)?;
        Some(p.sim_time + p.rate * (now - p.heard_at))
    }

    /// Simulation time (s) at which a release by `site` heard at `now` took effect there:
    /// its time as heard, but not advanced past [`SILENT_AFTER`] of silence (a site that
    /// dropped out is released by the coordinator long after its last stamp).
    pub fn release_time(&self, site: u16, now: f64) -> Option<f64> {
        let p = self.peers.get(&site)?;
        Some(p.sim_time + p.rate * (now - p.heard_at).min(SILENT_AFTER))
    }

    /// How far `t` is ahead of the slowest owner we follow (s), measured against the
    /// owners' time as last heard (the time of the frames arriving now); −∞ when no other
    /// site owns anything.
    fn ahead_of_owners(&self, t: f64, now: f64) -> f64 {
        self.owners
            .values()
            .filter_map(|s| self.heard_time(*s, now))
            .map(|heard| t - heard)
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// The terms of the automatic lag, for the logs: smoothed delay, its mean deviation,
    /// the input shortfall floor and the target (ms).
    pub fn lag_terms(&self) -> [f64; 4] {
        [
            self.delay.mean.unwrap_or(f64::NAN) * 1e3,
            self.delay.dev * 1e3,
            self.input_floor * 1e3,
            self.target_lag() * 1e3,
        ]
    }

    /// The lag a non-leading follower keeps behind the sites it follows (s).
    pub fn target_lag(&self) -> f64 {
        match self.lag {
            PlayoutLag::Fixed(l) => l.max(0.0),
            PlayoutLag::Auto if self.inputs_only => {
                let delay = self.delay.with_margin(HYBRID_JITTER_DEVS).unwrap_or(0.1);
                (delay + HYBRID_INPUT_INTERVAL)
                    .max(self.input_floor)
                    .min(MAX_HYBRID_LAG)
            }
            PlayoutLag::Auto => {
                let delay = self.delay.with_margin(4.0).unwrap_or(0.1);
                (delay + KEYFRAME_INTERVAL).min(MAX_AUTO_LAG)
            }
        }
    }

    /// The pace of the next step for a site at simulation time `t` (s) at wall time
    /// `now` (s); `leading`: its tool is moving, or (except under hybrid) it owns or
    /// claims a region ([`SiteSession::leads`](super::SiteSession::leads)).
    pub fn pace(&self, t: f64, now: f64, leading: bool, realtime: bool) -> Pace {
        let lead = self
            .followed(now)
            .into_iter()
            .filter_map(|s| self.estimate_now(s, now))
            .reduce(f64::min);
        let mut pace = Pace {
            rate: 1.0,
            behind: None,
            hold: 0.0,
        };
        if let Some(lead) = lead {
            let behind = lead - t;
            if !leading {
                pace.behind = Some(behind);
            }
            if self.lag.enabled() {
                let target = if leading { 0.0 } else { self.target_lag() };
                let error = behind - target;
                let max_rate = if !self.inputs_only {
                    MAX_RATE
                } else if error > HYBRID_CATCH_UP_BEYOND {
                    HYBRID_CATCH_UP_RATE
                } else {
                    HYBRID_MAX_RATE
                };
                pace.rate = (1.0 + GAIN * error).clamp(MIN_RATE, max_rate);
                if !realtime && error < 0.0 {
                    pace.hold = (-error).min(0.02);
                }
                if self.inputs_only && leading {
                    // Under hybrid a leader ahead of another (one whose tool just began to
                    // move after a rest, with its lag still to make up) keeps real time:
                    // the one behind catches up. Slowing or waiting here paused the view
                    // and the tissue under the haptic loop of a site driving its tool
                    // whenever another site's tool began to move.
                    pace.rate = pace.rate.max(1.0);
                } else if self.inputs_only && error < -HYBRID_HOLD_BEYOND {
                    // Under hybrid a follower ahead of the inputs simulates the remote tool
                    // from stale samples, and the keyframes that would correct it arrive
                    // too old to use: rather than slewing there over seconds, it waits (the
                    // view pauses; nothing jumps).
                    pace.hold = pace.hold.max((-error - HYBRID_HOLD_BEYOND).min(0.02));
                }
            }
        }
        // Never run ahead of an owner's frames. A leader may be ahead of a new leader by
        // up to the largest lag while the two slew level.
        let cap = if leading && self.lag.enabled() {
            MAX_LEAD + MAX_AUTO_LAG.max(self.target_lag())
        } else {
            MAX_LEAD
        };
        // Under hybrid an owner's keyframes only correct, and a late one is compared with
        // the local history or skipped: no cap (a still owner lags behind moving sites).
        let ahead = if self.inputs_only {
            f64::NEG_INFINITY
        } else {
            self.ahead_of_owners(t, now)
        };
        if ahead > cap {
            pace.hold = pace.hold.max((ahead - cap).min(0.02));
        }
        pace
    }
}

#[cfg(test)]
mod tests;
