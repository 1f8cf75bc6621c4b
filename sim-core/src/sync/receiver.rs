//! The receiver: a region another site owns, as seen on this site ([`RemoteRegion`]).

use std::collections::{HashMap, VecDeque};

use sim_lattice::{Lattice, NodeId, RegionState};

use super::frame::{apply_tree, match_tree_and_nodes, xor_state};
use super::motion::MotionSet;
use super::regions::NodeCache;
use super::{
    Grid, KeyframeId, RegionId, RegionKeyframe, RegionMap, RegionTreeDelta, SyncConfig, SyncError,
    V3,
};
use crate::engine::Simulation;

/// What [`RemoteRegion::apply_keyframe`] / [`RemoteRegion::apply_tree_delta`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Applied {
    /// The frame was taken over.
    Applied,
    /// Older than what was already applied; ignored.
    Stale,
}

/// What [`RemoteRegion::drive`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DriveStatus {
    /// Nothing to drive yet (no keyframe).
    Idle,
    /// The region's nodes were prescribed for the next step (count).
    Driven(usize),
    /// Ownership was released and the last correction has blended out: the region is
    /// simulated locally again; drop this state.
    Local,
}

/// The next keyframe of a remote region, held before this site's clock reaches it (a
/// follower running behind the owner: see [`RemoteRegion::hold_next`]).
#[derive(Clone, Debug)]
struct NextKeyframe {
    id: KeyframeId,
    sim_time: f64,
    /// `Some(w)` when it directly follows the last applied keyframe (no keyframe of the
    /// region in between was lost or superseded): the owner then kept the receivers'
    /// extrapolation within its drift threshold until `w` before it, so the region follows
    /// that extrapolation and the difference is made up over the last `w` only. `None`:
    /// keyframes are missing in between; each node's tail is estimated from its velocity
    /// in the held keyframe (see [`RemoteRegion::motion_at`]).
    tail: Option<f64>,
    /// Position and velocity of every node by grid coordinate (nodes created since are
    /// derived from the edge they split, like [`MotionSet::motion`]).
    states: HashMap<Grid, (V3, V3)>,
}

impl NextKeyframe {
    fn state(&mut self, lattice: &Lattice, n: NodeId) -> Option<(V3, V3)> {
        let g = lattice.node_grid(n);
        if let Some(s) = self.states.get(&g) {
            return Some(*s);
        }
        let (a, b) = lattice.node_parent_edge(n)?;
        let (xa, va) = self.state(lattice, a)?;
        let (xb, vb) = self.state(lattice, b)?;
        let s = (0.5 * (xa + xb), 0.5 * (va + vb));
        self.states.insert(g, s);
        Some(s)
    }
}

/// A region another site owns, as seen on this site: applies its keyframes and drives its
/// nodes between them — interpolating towards the next keyframe when it is already held,
/// extrapolating from the last one otherwise.
#[derive(Clone, Debug)]
pub struct RemoteRegion {
    region: RegionId,
    config: SyncConfig,
    motions: MotionSet,
    next: Option<NextKeyframe>,
    /// A keyframe [`RemoteRegion::hold_next`] turned down for the current tree state (not
    /// checked again until the tree changes).
    refused_next: Option<KeyframeId>,
    /// Correction offset per node (m) at `corr_start`.
    offsets: HashMap<Grid, V3>,
    corr_start: f64,
    last_keyframe: Option<KeyframeId>,
    last_time: f64,
    history: VecDeque<(KeyframeId, RegionState)>,
    pub(super) released: bool,
    cache: NodeCache,
    keyframes_applied: u64,
    /// Largest distance (m) between this site's nodes and the owner's keyframe (moved on
    /// to this site's time) when the newest keyframe arrived: the live divergence.
    last_divergence_m: f64,
    deltas_applied: u64,
}

impl RemoteRegion {
    pub fn new(region: RegionId, config: SyncConfig) -> Self {
        RemoteRegion {
            region,
            config,
            motions: MotionSet::default(),
            next: None,
            refused_next: None,
            offsets: HashMap::new(),
            corr_start: f64::NEG_INFINITY,
            last_keyframe: None,
            last_time: f64::NEG_INFINITY,
            history: VecDeque::new(),
            released: false,
            cache: NodeCache::default(),
            keyframes_applied: 0,
            last_divergence_m: 0.0,
            deltas_applied: 0,
        }
    }

    pub fn region(&self) -> RegionId {
        self.region
    }

    /// Largest node distance (m) from the owner's state when the newest keyframe was
    /// applied (0 before the first).
    pub fn last_divergence_m(&self) -> f64 {
        self.last_divergence_m
    }

    /// Newest keyframe applied.
    pub fn last_keyframe(&self) -> Option<KeyframeId> {
        self.last_keyframe
    }

    /// Keyframes and tree deltas applied so far.
    pub fn applied_counts(&self) -> (u64, u64) {
        (self.keyframes_applied, self.deltas_applied)
    }

    /// Whether [`RemoteRegion::release`] was called.
    pub fn is_released(&self) -> bool {
        self.released
    }

    /// (1) matches the tree state, (2) takes over the node states — at once with a zero
    /// blend window, else by a correction offset that [`RemoteRegion::drive`] blends out —
    /// and (3) sets up the extrapolation from the keyframe's time. Keyframes not newer than
    /// the last applied one are ignored. Acknowledge an [`Applied::Applied`] keyframe.
    pub fn apply_keyframe(
        &mut self,
        sim: &mut Simulation,
        map: &RegionMap,
        kf: &RegionKeyframe,
    ) -> Result<Applied, SyncError> {
        if kf.region != self.region {
            return Err(SyncError::WrongRegion {
                region: self.region,
                got: kf.region,
            });
        }
        if self.last_keyframe.is_some_and(|k| kf.keyframe_id <= k) {
            return Ok(Applied::Stale);
        }
        let matched = match_tree_and_nodes(sim, map, kf)?;
        // The virtual nodes of a cut take the owner's state at once, advanced to our time
        // (they are few: the corners of the elements a cut crossed; only the lattice
        // nodes are extrapolated and blended).
        matched.set_virtual_dofs(sim, kf, (sim.time() - kf.sim_time).max(0.0));
        let nodes = matched.nodes;
        let lattice = sim.lattice();
        let grids: Vec<Grid> = nodes.iter().map(|&n| lattice.node_grid(n)).collect();
        self.motions
            .take_keyframe(&grids, kf, self.config.max_accel_m_s2);
        if self.next.as_ref().is_some_and(|n| n.id <= kf.keyframe_id) {
            self.next = None;
        }
        self.refused_next = None;
        let t = sim.time();
        let h = self.config.max_extrapolation_s;
        self.offsets.clear();
        self.corr_start = t;
        let mut divergence: f64 = 0.0;
        for (i, &n) in nodes.iter().enumerate() {
            if sim.is_fixed(n) {
                continue;
            }
            let (x, v) = self.motions.motions[&grids[i]].eval(t, h);
            divergence = divergence.max((sim.positions()[n.0 as usize] - x).norm());
            if self.config.blend_window_s > 0.0 {
                self.offsets
                    .insert(grids[i], sim.positions()[n.0 as usize] - x);
            } else {
                sim.set_node_state(n, x, v);
            }
        }
        if self.config.blend_window_s <= 0.0 {
            sim.update_surfaces();
        }
        let state =
            RegionState::from_bytes(&kf.tree_bits).map_err(|source| SyncError::TreeBits {
                region: kf.region,
                source,
            })?;
        self.history.push_back((kf.keyframe_id, state));
        while self.history.len() > self.config.baseline_history.max(1) {
            self.history.pop_front();
        }
        self.last_keyframe = Some(kf.keyframe_id);
        self.last_time = self.last_time.max(kf.sim_time);
        self.keyframes_applied += 1;
        self.last_divergence_m = divergence;
        Ok(Applied::Applied)
    }

    /// Applies a tree delta against a keyframe this site holds; nodes created by it follow
    /// the motion of the edges they split. Deltas older than the last applied frame are
    /// ignored.
    pub fn apply_tree_delta(
        &mut self,
        sim: &mut Simulation,
        map: &RegionMap,
        d: &RegionTreeDelta,
    ) -> Result<Applied, SyncError> {
        let region = self.region;
        if d.region != region {
            return Err(SyncError::WrongRegion {
                region,
                got: d.region,
            });
        }
        if d.sim_time < self.last_time {
            return Ok(Applied::Stale);
        }
        let base = self
            .history
            .iter()
            .find(|(k, _)| *k == d.base_keyframe)
            .map(|(_, s)| s)
            .ok_or(SyncError::UnknownBase {
                region,
                base: d.base_keyframe,
            })?;
        let delta = RegionState::from_bytes(&d.xor_bits)
            .map_err(|source| SyncError::TreeBits { region, source })?;
        if delta.roots() != base.roots() {
            return Err(SyncError::TreeRoots { region });
        }
        let target = xor_state(base, &delta);
        apply_tree(sim, map, region, &target)?;
        // The held next keyframe was checked against the old tree state.
        self.next = None;
        self.refused_next = None;
        self.last_time = d.sim_time;
        self.deltas_applied += 1;
        Ok(Applied::Applied)
    }

    /// Ownership was released (after the final keyframe): keep driving until the last
    /// correction has blended out, then [`RemoteRegion::drive`] reports
    /// [`DriveStatus::Local`] and stops prescribing, leaving the velocities continuous.
    pub fn release(&mut self) {
        self.released = true;
    }

    /// Holds `kf`, the next keyframe of the region, before this site's simulated time
    /// reaches it: until it is applied (at its own time, by
    /// [`RemoteRegion::apply_keyframe`]), [`RemoteRegion::drive`] interpolates between the
    /// last applied keyframe and this one instead of extrapolating. Only a keyframe newer
    /// than the last applied one, of the region's current tree state (so that its nodes
    /// are the region's current nodes), is held; returns whether `kf` is held.
    pub fn hold_next(&mut self, sim: &Simulation, map: &RegionMap, kf: &RegionKeyframe) -> bool {
        if self.next.as_ref().is_some_and(|n| n.id == kf.keyframe_id) {
            return true;
        }
        if self.refused_next == Some(kf.keyframe_id) {
            return false;
        }
        let newer = self
            .last_keyframe
            .is_some_and(|k| kf.keyframe_id > k && kf.sim_time > self.last_time);
        if !newer
            || kf.region != self.region
            || kf.positions.len() != kf.velocities.len()
            || kf
                .positions
                .iter()
                .chain(&kf.velocities)
                .any(|p| p.iter().any(|c| !c.is_finite()))
        {
            return false;
        }
        let same_tree = RegionState::from_bytes(&kf.tree_bits)
            .is_ok_and(|s| s == map.state(sim.lattice(), self.region));
        let grids = self.cache.get(map, sim.lattice(), self.region).1;
        // Entries past the lattice nodes are a cut's virtual nodes (not interpolated).
        if !same_tree || grids.len() > kf.positions.len() {
            self.refused_next = Some(kf.keyframe_id);
            return false;
        }
        let states = grids
            .iter()
            .zip(kf.positions.iter().zip(&kf.velocities))
            .map(|(g, (x, v))| (*g, (V3::from(*x), V3::from(*v))))
            .collect();
        // The owner checks its drift after every step and sends at the first step past
        // the threshold, unless its rate cap (`min_interval_s`) delays the send: then the
        // drift may have built up since the last keyframe.
        let gap = kf.sim_time - self.last_time;
        let dt = sim.options().dt;
        let consecutive = self.last_keyframe.is_some_and(|k| kf.keyframe_id == k + 1);
        let tail = consecutive.then(|| {
            if gap > self.config.min_interval_s + 0.5 * dt {
                dt.min(gap)
            } else {
                gap
            }
        });
        self.next = Some(NextKeyframe {
            id: kf.keyframe_id,
            sim_time: kf.sim_time,
            tail,
            states,
        });
        true
    }

    /// Whether a next keyframe is held (see [`RemoteRegion::hold_next`]).
    pub fn holds_next(&self) -> bool {
        self.next.is_some()
    }

    /// Position of a node at time `t` from the keyframes alone (m). Between the last
    /// applied keyframe and a held next one, the last keyframe's extrapolation plus the
    /// difference `e` between the held keyframe and that extrapolation at its time, made
    /// up linearly over a *tail* before it. When the held keyframe directly follows, the
    /// owner kept the extrapolation within its drift threshold until the tail (one step,
    /// or the rate-capped interval): a sudden change such as released tissue snapping back
    /// then happens when it happened at the owner instead of being smeared over the
    /// interval. When keyframes are missing in between, the tail is `|e| / |v|` with `v`
    /// the node's velocity in the held keyframe (how long the node took to cover the
    /// difference at that speed; the whole interval if it is at rest): exact for a linear
    /// motion even past the extrapolation horizon, and a snap stays a snap. Never
    /// overshoots the held position. Past the held keyframe, its linear extrapolation (at
    /// most a step, until it is applied); without one, the last keyframe's extrapolation.
    pub fn motion_at(&mut self, lattice: &Lattice, n: NodeId, t: f64) -> Option<V3> {
        let h = self.config.max_extrapolation_s;
        let m = self.motions.motion(lattice, n)?;
        if let Some(next) = self.next.as_mut()
            && t > m.t0
            && let Some((x1, v1)) = next.state(lattice, n)
        {
            let t1 = next.sim_time;
            if t >= t1 {
                return Some(x1 + v1 * (t - t1).min(h));
            }
            let e = x1 - m.eval(t1, h).0;
            let gap = t1 - m.t0;
            let tail = next.tail.unwrap_or_else(|| {
                let speed = v1.norm();
                if speed > 1e-9 {
                    (e.norm() / speed).min(gap)
                } else {
                    gap
                }
            });
            let w = if tail > 0.0 {
                ((t - (t1 - tail)) / tail).clamp(0.0, 1.0)
            } else {
                0.0
            };
            return Some(m.eval(t, h).0 + e * w);
        }
        Some(m.eval(t, h).0)
    }

    /// Shown position of a node at time `t` (m): interpolation or extrapolation plus the
    /// decayed offset.
    fn shown(&mut self, lattice: &Lattice, n: NodeId, t: f64) -> Option<V3> {
        let x = self.motion_at(lattice, n, t)?;
        let g = lattice.node_grid(n);
        let off = match self.offsets.get(&g) {
            Some(o) => *o,
            None => {
                // A node created since the keyframe: the average of its edge's offsets.
                let o = self.derived_offset(lattice, n);
                self.offsets.insert(g, o);
                o
            }
        };
        Some(x + off * self.blend_factor(t))
    }

    fn derived_offset(&self, lattice: &Lattice, n: NodeId) -> V3 {
        if let Some(o) = self.offsets.get(&lattice.node_grid(n)) {
            return *o;
        }
        match lattice.node_parent_edge(n) {
            Some((a, b)) => {
                0.5 * (self.derived_offset(lattice, a) + self.derived_offset(lattice, b))
            }
            None => V3::zeros(),
        }
    }

    /// Remaining fraction of the correction offset at time `t`.
    pub fn blend_factor(&self, t: f64) -> f64 {
        let w = self.config.blend_window_s;
        if w <= 0.0 {
            0.0
        } else {
            (1.0 - (t - self.corr_start) / w).clamp(0.0, 1.0)
        }
    }

    /// Pure extrapolated position and velocity (no correction) of the node at grid `g` at
    /// time `t`, if it was in the last keyframe or derived since.
    pub fn extrapolated(&self, g: &Grid, t: f64) -> Option<(V3, V3)> {
        self.motions
            .motions
            .get(g)
            .map(|m| m.eval(t, self.config.max_extrapolation_s))
    }

    /// Correction offset (m) of the node at grid `g` as set by the last keyframe.
    pub fn correction(&self, g: &Grid) -> Option<V3> {
        self.offsets.get(g).copied()
    }

    /// Before every step: prescribes the region's (not scene-fixed) nodes to their shown
    /// position at the end of the step. After a release whose correction has blended out it
    /// prescribes nothing and returns [`DriveStatus::Local`].
    pub fn drive(&mut self, sim: &mut Simulation, map: &RegionMap) -> DriveStatus {
        if self.last_keyframe.is_none() {
            return if self.released {
                DriveStatus::Local
            } else {
                DriveStatus::Idle
            };
        }
        let t = sim.time() + sim.options().dt;
        if self.released && self.blend_factor(sim.time()) <= 0.0 {
            return DriveStatus::Local;
        }
        let nodes = self.cache.get(map, sim.lattice(), self.region).0.to_vec();
        let mut targets = Vec::with_capacity(nodes.len());
        for n in nodes {
            if sim.is_fixed(n) {
                continue;
            }
            if let Some(p) = self.shown(sim.lattice(), n, t) {
                targets.push((n, p));
            }
        }
        let count = targets.len();
        for (n, p) in targets {
            sim.prescribe(n, p);
        }
        DriveStatus::Driven(count)
    }
}
