//! The sender: the owner's side of dead reckoning ([`SendPolicy`]) — when to send a
//! keyframe or a tree delta of an owned region.

use std::collections::{BTreeMap, VecDeque};

use sim_lattice::RegionState;

use super::frame::keyframe_from_nodes;
use super::motion::MotionSet;
use super::regions::NodeCache;
use super::{
    KeyframeId, RegionId, RegionKeyframe, RegionMap, RegionTreeDelta, SyncConfig, SyncFrame,
    encode_tree_xor,
};
use crate::engine::Simulation;

/// Why the owner sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SendReason {
    /// Nothing sent since taking ownership.
    First,
    /// The region's tree state differs from the last sent one.
    Topology,
    /// The receivers' extrapolation drifted past the threshold.
    Drift,
    /// The heartbeat interval elapsed.
    Heartbeat,
    /// Ownership is being released.
    Final,
}

/// Counters of the owner's send decisions (all regions).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SendCounters {
    /// Decisions taken ([`SendPolicy::should_send`] calls on owned regions).
    pub decisions: u64,
    pub keyframes: u64,
    pub tree_deltas: u64,
    pub by_first: u64,
    pub by_topology: u64,
    pub by_drift: u64,
    pub by_heartbeat: u64,
    pub by_final: u64,
    /// Decisions that wanted to send but fell under the rate cap.
    pub rate_limited: u64,
    /// Largest drift (m) at a decision that did not send (≤ the threshold unless rate
    /// limited).
    pub max_unsent_drift_m: f64,
    /// Largest drift (m) seen at any decision (what receivers' error reached before a
    /// correction).
    pub max_drift_m: f64,
}

#[derive(Clone, Debug)]
struct OwnedRegion {
    next_id: KeyframeId,
    motions: MotionSet,
    sent_state: Option<RegionState>,
    checked_generation: Option<u64>,
    topology_changed: bool,
    history: VecDeque<(KeyframeId, RegionState)>,
    last_send: Option<f64>,
    last_keyframe_time: Option<f64>,
    last_drift: f64,
    pending: Option<SendReason>,
    cache: NodeCache,
}

/// The owner's side of dead reckoning: keeps, per owned region, the extrapolation the
/// receivers run from its last sent keyframe and decides when to send.
#[derive(Clone, Debug)]
pub struct SendPolicy {
    config: SyncConfig,
    regions: BTreeMap<RegionId, OwnedRegion>,
    pub(super) counters: SendCounters,
}

impl SendPolicy {
    pub fn new(config: SyncConfig) -> Self {
        SendPolicy {
            config,
            regions: BTreeMap::new(),
            counters: SendCounters::default(),
        }
    }

    pub fn config(&self) -> &SyncConfig {
        &self.config
    }

    /// Sends also when a region departs from the receivers' dead reckoning by more than
    /// `m` (m; infinite: never, the hybrid strategy's default).
    pub fn set_drift_threshold(&mut self, m: f64) {
        self.config.drift_threshold_m = m;
    }

    /// Sends at most once per `s` (s of sim time) per region.
    pub fn set_min_interval(&mut self, s: f64) {
        self.config.min_interval_s = s;
    }

    /// Starts owning a region; its keyframes are numbered from `first_id` (the newest id
    /// this site has seen for the region + 1).
    pub fn acquire(&mut self, region: RegionId, first_id: KeyframeId) {
        self.regions.insert(
            region,
            OwnedRegion {
                next_id: first_id,
                motions: MotionSet::default(),
                sent_state: None,
                checked_generation: None,
                topology_changed: false,
                history: VecDeque::new(),
                last_send: None,
                last_keyframe_time: None,
                last_drift: 0.0,
                pending: None,
                cache: NodeCache::default(),
            },
        );
    }

    pub fn is_owned(&self, region: RegionId) -> bool {
        self.regions.contains_key(&region)
    }

    /// Owned regions, increasing.
    pub fn owned(&self) -> impl Iterator<Item = RegionId> + '_ {
        self.regions.keys().copied()
    }

    pub fn counters(&self) -> &SendCounters {
        &self.counters
    }

    /// Drift (m) measured by the last decision on `region`.
    pub fn drift(&self, region: RegionId) -> Option<f64> {
        self.regions.get(&region).map(|r| r.last_drift)
    }

    /// Id the next keyframe of `region` will get.
    pub fn next_keyframe_id(&self, region: RegionId) -> Option<KeyframeId> {
        self.regions.get(&region).map(|r| r.next_id)
    }

    /// Stops owning a region and returns its final keyframe (send it before releasing).
    pub fn release(
        &mut self,
        sim: &Simulation,
        map: &RegionMap,
        region: RegionId,
    ) -> Option<RegionKeyframe> {
        let mut r = self.regions.remove(&region)?;
        self.counters.keyframes += 1;
        self.counters.by_final += 1;
        let nodes = r.cache.get(map, sim.lattice(), region).0.to_vec();
        Some(keyframe_from_nodes(sim, map, region, r.next_id, &nodes))
    }

    /// Max distance (m) between the receivers' extrapolation at `now` and the actual
    /// positions of the region's nodes (scene-fixed nodes excluded).
    fn measure_drift(
        r: &mut OwnedRegion,
        sim: &Simulation,
        map: &RegionMap,
        region: RegionId,
        h: f64,
        now: f64,
    ) -> f64 {
        let lattice = sim.lattice();
        let x = sim.positions();
        let nodes = r.cache.get(map, lattice, region).0.to_vec();
        let mut drift: f64 = 0.0;
        for n in nodes {
            if sim.is_fixed(n) {
                continue;
            }
            match r.motions.motion(lattice, n) {
                Some(m) => drift = drift.max((m.eval(now, h).0 - x[n.0 as usize]).norm()),
                None => return f64::INFINITY,
            }
        }
        drift
    }

    /// Dead-reckoning decision at sim time `now` (s): true when the region is owned and
    /// nothing was sent yet, its tree state changed, the drift exceeds the threshold, or the
    /// heartbeat is due — and the rate cap allows. Follow a `true` with
    /// [`SendPolicy::encode`].
    pub fn should_send(
        &mut self,
        sim: &Simulation,
        map: &RegionMap,
        region: RegionId,
        now: f64,
    ) -> bool {
        let cfg = self.config;
        let Some(r) = self.regions.get_mut(&region) else {
            return false;
        };
        self.counters.decisions += 1;
        let generation = sim.lattice().topology_generation();
        if r.checked_generation != Some(generation) {
            r.checked_generation = Some(generation);
            r.topology_changed = r
                .sent_state
                .as_ref()
                .is_some_and(|s| *s != map.state(sim.lattice(), region));
        }
        let drift = if r.sent_state.is_some() {
            Self::measure_drift(r, sim, map, region, cfg.max_extrapolation_s, now)
        } else {
            f64::INFINITY
        };
        r.last_drift = drift;
        if drift.is_finite() {
            self.counters.max_drift_m = self.counters.max_drift_m.max(drift);
        }
        let reason = if r.sent_state.is_none() {
            Some(SendReason::First)
        } else if r.topology_changed {
            Some(SendReason::Topology)
        } else if drift > cfg.drift_threshold_m {
            Some(SendReason::Drift)
        } else if r
            .last_keyframe_time
            .is_some_and(|t| now - t >= cfg.heartbeat_s - 1e-9)
        {
            Some(SendReason::Heartbeat)
        } else {
            None
        };
        let limited = reason.is_some_and(|reason| {
            reason != SendReason::First && r.last_send.is_some_and(|t| now - t < cfg.min_interval_s)
        });
        if limited {
            self.counters.rate_limited += 1;
        }
        if reason.is_none() || limited {
            if drift.is_finite() {
                self.counters.max_unsent_drift_m = self.counters.max_unsent_drift_m.max(drift);
            }
            r.pending = None;
            return false;
        }
        r.pending = reason;
        true
    }

    /// Builds the frame the last [`SendPolicy::should_send`] asked for (a keyframe by
    /// default) and updates the copy of the receivers' extrapolation. A topology change
    /// with small drift becomes a tree delta when `acked_base` (the newest keyframe every
    /// receiver acknowledged) is still in this owner's history.
    pub fn encode(
        &mut self,
        sim: &Simulation,
        map: &RegionMap,
        region: RegionId,
        now: f64,
        acked_base: Option<KeyframeId>,
    ) -> Option<SyncFrame> {
        let cfg = self.config;
        let r = self.regions.get_mut(&region)?;
        let reason = r.pending.take().unwrap_or(SendReason::Heartbeat);
        let current = map.state(sim.lattice(), region);
        if reason == SendReason::Topology && r.last_drift <= cfg.drift_threshold_m {
            let base = acked_base.and_then(|b| r.history.iter().find(|(k, _)| *k == b));
            if let Some((base_id, base_state)) = base {
                let d = RegionTreeDelta {
                    region,
                    sim_time: sim.time(),
                    base_keyframe: *base_id,
                    xor_bits: encode_tree_xor(base_state, &current),
                };
                r.sent_state = Some(current);
                r.topology_changed = false;
                r.last_send = Some(now);
                self.counters.tree_deltas += 1;
                self.counters.by_topology += 1;
                return Some(SyncFrame::TreeDelta(d));
            }
        }
        let (nodes, grids) = r.cache.get(map, sim.lattice(), region);
        let (nodes, grids) = (nodes.to_vec(), grids.to_vec());
        let kf = keyframe_from_nodes(sim, map, region, r.next_id, &nodes);
        r.motions.take_keyframe(&grids, &kf, cfg.max_accel_m_s2);
        r.next_id += 1;
        r.history.push_back((kf.keyframe_id, current.clone()));
        while r.history.len() > cfg.baseline_history.max(1) {
            r.history.pop_front();
        }
        r.sent_state = Some(current);
        r.topology_changed = false;
        r.last_send = Some(now);
        r.last_keyframe_time = Some(now);
        r.last_drift = 0.0;
        let c = &mut self.counters;
        c.keyframes += 1;
        match reason {
            SendReason::First => c.by_first += 1,
            SendReason::Topology => c.by_topology += 1,
            SendReason::Drift => c.by_drift += 1,
            SendReason::Heartbeat => c.by_heartbeat += 1,
            SendReason::Final => c.by_final += 1,
        }
        Some(SyncFrame::Keyframe(kf))
    }

    /// [`SendPolicy::should_send`] + [`SendPolicy::encode`] for every owned region at sim
    /// time `now`; `acked_base(region)` gives the newest keyframe all receivers hold.
    pub fn poll(
        &mut self,
        sim: &Simulation,
        map: &RegionMap,
        now: f64,
        acked_base: impl Fn(RegionId) -> Option<KeyframeId>,
    ) -> Vec<SyncFrame> {
        let owned: Vec<RegionId> = self.regions.keys().copied().collect();
        let mut out = Vec::new();
        for region in owned {
            if self.should_send(sim, map, region, now)
                && let Some(f) = self.encode(sim, map, region, now, acked_base(region))
            {
                out.push(f);
            }
        }
        out
    }
}
