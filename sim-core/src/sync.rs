//! Sans-IO sync state of DESIGN §1(c): regions, keyframe encode/apply, second-order
//! extrapolation with blended corrections, the owner's dead-reckoning send decision, the
//! bench strategies, and surface divergence recording (`.surf` files).
//!
//! # Regions
//! [`RegionMap`] partitions the root tets into blocks of `B × B × B` lattice cells
//! (block `⌊(cell − min cell) / B⌋` per axis). Region ids are the non-empty
//! blocks in lexicographic block order, so two sites loading the same scene get the same
//! map. The *canonical node order* of a region is the set of live vertices of its roots'
//! leaves sorted by integer grid coordinate ([`sim_lattice::Lattice::node_grid`]): equal on
//! two sites whose region tree states are equal, so keyframes carry no node ids.
//!
//! # Per step, on a site
//! * Owner of a region: [`SendPolicy::poll`] (or [`SendPolicy::should_send`] +
//!   [`SendPolicy::encode`]) after the step; send the returned [`SyncFrame`]s. On release,
//!   send [`SendPolicy::release`]'s final keyframe.
//! * Receiver: [`RemoteRegion::apply_keyframe`] / [`RemoteRegion::apply_tree_delta`] when
//!   frames arrive, and [`RemoteRegion::drive`] before every step. [`SiteSync`] bundles all
//!   of this for a site.
//!
//! # Extrapolation and blending
//! A keyframe at sim time `t_k` gives each node `x_k, v_k`; `a = (v_k − v_{k−1}) / (t_k −
//! t_{k−1})` from the previous keyframe (clamped to [`SyncConfig::max_accel_m_s2`]). The
//! receiver shows `x_k + v_k Δt + ½ a Δt²` with `Δt = t − t_k` clamped to
//! ±[`SyncConfig::max_extrapolation_s`] (DIS "FVW" dead reckoning), plus a correction
//! offset: when a keyframe arrives at receiver time `t_r`, the offset is the receiver's
//! current position minus the new extrapolation at `t_r`, and it decays linearly to zero
//! over [`SyncConfig::blend_window_s`]. A node therefore never jumps: per step the shown
//! position departs from the pure extrapolation by at most `|offset| · dt / window` more.
//! A window of 0 snaps (position and velocity taken over at once).
//!
//! # Interpolation
//! A receiver that runs behind the owner in simulated time (a playout lag) often holds the
//! region's *next* keyframe before its clock reaches it ([`RemoteRegion::hold_next`]).
//! Between the last applied keyframe and the held one at `t_n` it then shows the
//! extrapolation plus the difference to the held keyframe, made up over a tail before
//! `t_n` (one step when no keyframe is missing in between — the owner's dead reckoning
//! kept the extrapolation within its threshold until then —, else estimated from the held
//! velocities; see [`RemoteRegion::motion_at`]), and applies the held keyframe at `t_n` as
//! usual (its correction offset is then about zero). Only a keyframe of the region's
//! current tree state is held (its nodes are the current nodes); otherwise extrapolation
//! as above.
//!
//! # Dead reckoning
//! [`SendPolicy`] keeps, per owned region, the same extrapolation the receivers run from
//! its last sent keyframe and sends when the largest node distance between it and the
//! actual positions exceeds [`SyncConfig::drift_threshold_m`], when the region's tree
//! state changed (a [`RegionTreeDelta`] if the drift is small and an acknowledged baseline
//! exists, else a keyframe), or on the heartbeat; at most once per
//! [`SyncConfig::min_interval_s`]. Its estimate excludes the receivers' still-decaying
//! correction offsets and the wire quantisation (≤ 5 µm with proto's defaults).
//!
//! # Converting to `proto`
//! * [`RegionKeyframe`] → `proto::Message::Keyframe(RegionKeyframe { region, keyframe:
//!   keyframe_id, owner, sim_time_s: sim_time, epoch, tree_bits, nodes })` with `nodes =
//!   QuantisedNodes::encode_default(&(0..n as u32).collect::<Vec<_>>(), &positions,
//!   &velocities)`: the ids are canonical indices. Back: `positions`/`velocities` from
//!   `nodes.iter()` in id order (reject frames whose ids are not `0..n`).
//! * [`RegionTreeDelta`] ↔ `proto::Message::TreeDelta { region, site, epoch, sim_time_s:
//!   sim_time, base_keyframe, xor_bits }`.
//! * Acknowledge every keyframe [`SiteSync::on_frame`] returns an id for; pass the
//!   baseline tracker's all-acknowledged keyframe as `acked_base` to
//!   [`SiteSync::after_step`].
//!
//! # Limitations
//! * A receiver must not run its own adaptivity inside (or, through conformity, next to)
//!   a region it does not own: a forced split there makes the next keyframe merge it back,
//!   or fail with [`SyncError::Residual`] when a finer split outside blocks the merge.
//! * Nodes on the face between a remote region and a local one are prescribed by the
//!   remote region.
//! * Time is simulation time; a receiver whose clock lags the owner's extrapolates
//!   backwards (clamped to [`SyncConfig::max_extrapolation_s`]).
//!
//! Units: SI (m, s, m/s, m/s²). Times are simulation times (s).

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::io::Write;

use nalgebra::Vector3;
use sim_lattice::{Lattice, LatticeError, NodeId, RegionState, StateDecodeError, TetId};

use crate::engine::Simulation;
use crate::error::SimError;

type V3 = Vector3<f64>;
/// Integer rest-grid coordinate of a node (the site-independent node name).
pub type Grid = [i64; 3];
/// Region identifier (matches `proto::RegionId`).
pub type RegionId = u32;
/// Keyframe identifier (matches `proto::KeyframeId`): per region, strictly increasing.
pub type KeyframeId = u64;

/// The pseudo-region of [`SyncStrategy::FullState`] frames: every root of the organ.
pub const FULL_STATE_REGION: RegionId = u32::MAX;

/// Default block edge (cells) of a region: the default scene (cholecystectomy, 10 × 8 × 4
/// cells of 2 cm) gets 24 regions of at most 3 × 3 × 3 cells (6 cm).
pub const DEFAULT_REGION_BLOCK: u32 = 3;

/// Errors of the sync layer (malformed or inconsistent frames, lattice failures).
#[derive(Debug, thiserror::Error)]
pub enum SyncError {
    #[error("region {0} does not exist in this scene")]
    UnknownRegion(RegionId),
    #[error("region {region}: tree bits: {source}")]
    TreeBits {
        region: RegionId,
        source: StateDecodeError,
    },
    #[error("region {region}: tree state names roots other than the region's")]
    TreeRoots { region: RegionId },
    #[error("region {region}: tree state cannot be applied: {source}")]
    Lattice {
        region: RegionId,
        source: LatticeError,
    },
    #[error(
        "region {region}: after matching the tree state {residual} split bits still differ \
         (a merge was blocked by refinement outside the region)"
    )]
    Residual { region: RegionId, residual: usize },
    #[error("region {region}: frame has {got} nodes, the region has {expected}")]
    NodeCount {
        region: RegionId,
        expected: usize,
        got: usize,
    },
    #[error("region {region}: frame has {positions} positions but {velocities} velocities")]
    LengthMismatch {
        region: RegionId,
        positions: usize,
        velocities: usize,
    },
    #[error("region {region}: non-finite node state in frame")]
    NonFinite { region: RegionId },
    #[error(
        "region {region}: tree delta names base keyframe {base}, which this site does not hold"
    )]
    UnknownBase { region: RegionId, base: KeyframeId },
    #[error("region {region}: frame is for region {got}")]
    WrongRegion { region: RegionId, got: RegionId },
    #[error(transparent)]
    Sim(#[from] SimError),
}

// ---------------------------------------------------------------------------------------
// Configuration
// ---------------------------------------------------------------------------------------

/// Knobs of extrapolation, blending and the owner's send decision.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SyncConfig {
    /// Corrections decay linearly to zero over this window (s); 0 snaps.
    pub blend_window_s: f64,
    /// Acceleration estimates are clamped to this magnitude (m/s²).
    pub max_accel_m_s2: f64,
    /// Extrapolation stops (holds) this far from the keyframe time (s).
    pub max_extrapolation_s: f64,
    /// The owner sends when its copy of the receivers' extrapolation drifts from the actual
    /// node positions by more than this (m).
    pub drift_threshold_m: f64,
    /// The owner sends a keyframe at least this often while owning (s of sim time).
    pub heartbeat_s: f64,
    /// The owner sends at most one frame per region per this interval (s of sim time);
    /// first and final keyframes are exempt.
    pub min_interval_s: f64,
    /// Keyframe tree states kept (owner and receiver) as tree-delta baselines.
    pub baseline_history: usize,
}

impl Default for SyncConfig {
    fn default() -> Self {
        SyncConfig {
            blend_window_s: 0.1,
            max_accel_m_s2: 50.0,
            max_extrapolation_s: 0.5,
            drift_threshold_m: 5e-4,
            heartbeat_s: 0.25,
            min_interval_s: 0.01,
            baseline_history: 16,
        }
    }
}

/// How sites share the organ (the sync bench compares them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SyncStrategy {
    /// Keyframes of owned regions on dead-reckoning demand, extrapolated and blended.
    Keyframe,
    /// Every node of the organ every `every_steps` steps ([`encode_full_state`] /
    /// [`apply_full_state`]); receivers take the state over directly.
    FullState { every_steps: u32 },
    /// Only tool poses are shared; every site simulates everything (nothing here).
    InputOnly,
}

impl SyncStrategy {
    /// Short name for tables and command lines: `keyframe`, `full-state`, `input-only`.
    pub fn name(&self) -> &'static str {
        match self {
            SyncStrategy::Keyframe => "keyframe",
            SyncStrategy::FullState { .. } => "full-state",
            SyncStrategy::InputOnly => "input-only",
        }
    }
}

impl std::fmt::Display for SyncStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SyncStrategy::FullState { every_steps } if *every_steps != 1 => {
                write!(f, "full-state:{every_steps}")
            }
            s => f.write_str(s.name()),
        }
    }
}

impl std::str::FromStr for SyncStrategy {
    type Err = String;
    /// `keyframe`, `input-only`, `full-state` (every step) or `full-state:K`.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "keyframe" => Ok(SyncStrategy::Keyframe),
            "input-only" => Ok(SyncStrategy::InputOnly),
            "full-state" => Ok(SyncStrategy::FullState { every_steps: 1 }),
            _ => match s.strip_prefix("full-state:").map(str::parse::<u32>) {
                Some(Ok(k)) if k > 0 => Ok(SyncStrategy::FullState { every_steps: k }),
                _ => Err(format!(
                    "unknown sync strategy {s:?} (keyframe, full-state[:K], input-only)"
                )),
            },
        }
    }
}

// ---------------------------------------------------------------------------------------
// Regions
// ---------------------------------------------------------------------------------------

/// Deterministic partition of the root tets into blocks of `B × B × B` cells, counted from
/// the lattice's lowest cell on each axis.
#[derive(Clone, Debug)]
pub struct RegionMap {
    block: u32,
    /// Block coordinate of each region, increasing.
    blocks: Vec<[i32; 3]>,
    /// Roots of each region, increasing.
    roots: Vec<Vec<u32>>,
    /// Region of each root.
    root_region: Vec<RegionId>,
    /// Rest bounding box of each region's cells (m).
    bounds: Vec<(V3, V3)>,
    all_roots: Vec<u32>,
}

impl RegionMap {
    /// Blocks of `block` cells per axis (0 is treated as 1).
    pub fn new(lattice: &Lattice, block: u32) -> RegionMap {
        let block = block.max(1);
        let b = block as i32;
        let cells = lattice.cells();
        // Blocks start at the lowest cell of the lattice on each axis (same scene, same
        // cells, same blocks).
        let lo = cells
            .iter()
            .fold([i32::MAX; 3], |m, c| [0, 1, 2].map(|k| m[k].min(c[k])));
        let block_of = |c: &[i32; 3]| [0, 1, 2].map(|k| (c[k] - lo[k]).div_euclid(b));
        let mut blocks: Vec<[i32; 3]> = cells.iter().map(block_of).collect();
        blocks.sort_unstable();
        blocks.dedup();
        let index: HashMap<[i32; 3], usize> =
            blocks.iter().enumerate().map(|(i, b)| (*b, i)).collect();
        let mut roots = vec![Vec::new(); blocks.len()];
        let mut root_region = Vec::with_capacity(cells.len() * 6);
        let p = lattice.params();
        let mut bounds =
            vec![(V3::repeat(f64::INFINITY), V3::repeat(f64::NEG_INFINITY)); blocks.len()];
        for (s, c) in cells.iter().enumerate() {
            let r = index[&block_of(c)];
            for k in 0..6 {
                roots[r].push((s * 6 + k) as u32);
                root_region.push(r as RegionId);
            }
            let lo = p.origin + V3::new(c[0] as f64, c[1] as f64, c[2] as f64) * p.cell;
            let hi = lo + V3::repeat(p.cell);
            bounds[r].0 = bounds[r].0.inf(&lo);
            bounds[r].1 = bounds[r].1.sup(&hi);
        }
        RegionMap {
            block,
            blocks,
            roots,
            root_region,
            bounds,
            all_roots: (0..lattice.root_count()).collect(),
        }
    }

    /// The map of a simulation with [`DEFAULT_REGION_BLOCK`].
    pub fn for_simulation(sim: &Simulation) -> RegionMap {
        RegionMap::new(sim.lattice(), DEFAULT_REGION_BLOCK)
    }

    /// Block edge in cells.
    pub fn block(&self) -> u32 {
        self.block
    }

    /// Number of regions.
    pub fn len(&self) -> usize {
        self.roots.len()
    }

    /// Whether there is no region.
    pub fn is_empty(&self) -> bool {
        self.roots.is_empty()
    }

    /// Region ids, increasing.
    pub fn regions(&self) -> impl Iterator<Item = RegionId> + '_ {
        0..self.roots.len() as RegionId
    }

    /// Region of a root tet.
    pub fn region_of_root(&self, root: u32) -> Option<RegionId> {
        self.root_region.get(root as usize).copied()
    }

    /// Region of a tet.
    pub fn region_of_tet(&self, t: TetId) -> Option<RegionId> {
        self.region_of_root(t.root)
    }

    /// Roots of a region, increasing ([`FULL_STATE_REGION`] gives every root; an unknown
    /// region none).
    pub fn roots(&self, region: RegionId) -> &[u32] {
        if region == FULL_STATE_REGION {
            return &self.all_roots;
        }
        self.roots.get(region as usize).map_or(&[], Vec::as_slice)
    }

    /// Block coordinate of a region (cells `min + block · b .. min + block · (b + 1)` per
    /// axis, `min` the lattice's lowest cell).
    pub fn block_of(&self, region: RegionId) -> Option<[i32; 3]> {
        self.blocks.get(region as usize).copied()
    }

    /// Rest-space bounding box of a region's cells (m).
    pub fn bounds(&self, region: RegionId) -> Option<(V3, V3)> {
        self.bounds.get(region as usize).copied()
    }

    /// Regions whose rest-space cell box lies within `radius` (m) of `point`, increasing.
    pub fn regions_near(&self, point: &V3, radius: f64) -> Vec<RegionId> {
        self.bounds
            .iter()
            .enumerate()
            .filter(|(_, (lo, hi))| box_distance(lo, hi, point) <= radius)
            .map(|(r, _)| r as RegionId)
            .collect()
    }

    /// Regions whose *deformed* nodes' bounding box lies within `radius` (m) of `point`
    /// (for a tool touching tissue that has moved away from its rest place). O(leaves).
    pub fn regions_near_deformed(
        &self,
        sim: &Simulation,
        point: &V3,
        radius: f64,
    ) -> Vec<RegionId> {
        let lat = sim.lattice();
        let x = sim.positions();
        let mut bounds =
            vec![(V3::repeat(f64::INFINITY), V3::repeat(f64::NEG_INFINITY)); self.len()];
        for &t in lat.leaves() {
            let Some(r) = self.region_of_root(t.root) else {
                continue;
            };
            let b = &mut bounds[r as usize];
            for n in lat.tet_nodes(t) {
                let p = x[n.0 as usize];
                b.0 = b.0.inf(&p);
                b.1 = b.1.sup(&p);
            }
        }
        bounds
            .iter()
            .enumerate()
            .filter(|(_, (lo, hi))| lo.x <= hi.x && box_distance(lo, hi, point) <= radius)
            .map(|(r, _)| r as RegionId)
            .collect()
    }

    /// Whether `region` names a region of this map or [`FULL_STATE_REGION`].
    pub fn contains(&self, region: RegionId) -> bool {
        region == FULL_STATE_REGION || (region as usize) < self.roots.len()
    }

    /// Canonical node order of a region: live vertices of its roots' leaves sorted by grid
    /// coordinate ([`FULL_STATE_REGION`]: every live node).
    pub fn canonical_nodes(&self, lattice: &Lattice, region: RegionId) -> Vec<NodeId> {
        let mut nodes: Vec<NodeId> = if region == FULL_STATE_REGION {
            lattice.nodes().collect()
        } else {
            let mut set = HashSet::new();
            for &t in lattice.leaves() {
                if self.region_of_root(t.root) == Some(region) {
                    set.extend(lattice.tet_nodes(t));
                }
            }
            set.into_iter().collect()
        };
        nodes.sort_unstable_by_key(|&n| lattice.node_grid(n));
        nodes
    }

    /// The tree state of a region.
    pub fn state(&self, lattice: &Lattice, region: RegionId) -> RegionState {
        lattice.region_state(self.roots(region))
    }
}

fn box_distance(lo: &V3, hi: &V3, p: &V3) -> f64 {
    let d = V3::from_fn(|k, _| (lo[k] - p[k]).max(p[k] - hi[k]).max(0.0));
    d.norm()
}

/// Canonical nodes cached per topology generation.
#[derive(Clone, Debug, Default)]
struct NodeCache {
    generation: Option<u64>,
    nodes: Vec<NodeId>,
    grids: Vec<Grid>,
}

impl NodeCache {
    fn get(
        &mut self,
        map: &RegionMap,
        lattice: &Lattice,
        region: RegionId,
    ) -> (&[NodeId], &[Grid]) {
        let g = lattice.topology_generation();
        if self.generation != Some(g) {
            self.nodes = map.canonical_nodes(lattice, region);
            self.grids = self.nodes.iter().map(|&n| lattice.node_grid(n)).collect();
            self.generation = Some(g);
        }
        (&self.nodes, &self.grids)
    }
}

// ---------------------------------------------------------------------------------------
// Frames
// ---------------------------------------------------------------------------------------

/// Full state of one region (field set of `proto::Message::Keyframe` minus what the client
/// adds: owner, epoch; the wire's node `ids` are the canonical indices `0..n`).
#[derive(Clone, Debug, PartialEq)]
pub struct RegionKeyframe {
    pub region: RegionId,
    pub keyframe_id: KeyframeId,
    /// Owner's simulation time of the state (s).
    pub sim_time: f64,
    /// [`RegionState::to_bytes`] of the region's trees.
    pub tree_bits: Vec<u8>,
    /// Node positions (m) in canonical order.
    pub positions: Vec<[f64; 3]>,
    /// Node velocities (m/s) in canonical order.
    pub velocities: Vec<[f64; 3]>,
}

/// Change of a region's tree state against a keyframe every receiver acknowledged (field
/// set of `proto::Message::TreeDelta` minus site and epoch).
#[derive(Clone, Debug, PartialEq)]
pub struct RegionTreeDelta {
    pub region: RegionId,
    /// Owner's simulation time of the new tree state (s).
    pub sim_time: f64,
    pub base_keyframe: KeyframeId,
    /// XOR of the base keyframe's split bits and the current ones, encoded like
    /// [`RegionState::to_bytes`] over the region's roots.
    pub xor_bits: Vec<u8>,
}

/// What an owner sends.
#[derive(Clone, Debug, PartialEq)]
pub enum SyncFrame {
    Keyframe(RegionKeyframe),
    TreeDelta(RegionTreeDelta),
}

impl SyncFrame {
    pub fn region(&self) -> RegionId {
        match self {
            SyncFrame::Keyframe(k) => k.region,
            SyncFrame::TreeDelta(d) => d.region,
        }
    }
}

/// Encodes the region's state (any region id of `map`, or [`FULL_STATE_REGION`]).
pub fn encode_keyframe(
    sim: &Simulation,
    map: &RegionMap,
    region: RegionId,
    keyframe_id: KeyframeId,
) -> Result<RegionKeyframe, SyncError> {
    if !map.contains(region) {
        return Err(SyncError::UnknownRegion(region));
    }
    let nodes = map.canonical_nodes(sim.lattice(), region);
    Ok(keyframe_from_nodes(sim, map, region, keyframe_id, &nodes))
}

fn keyframe_from_nodes(
    sim: &Simulation,
    map: &RegionMap,
    region: RegionId,
    keyframe_id: KeyframeId,
    nodes: &[NodeId],
) -> RegionKeyframe {
    let (x, v) = (sim.positions(), sim.velocities());
    RegionKeyframe {
        region,
        keyframe_id,
        sim_time: sim.time(),
        tree_bits: map.state(sim.lattice(), region).to_bytes(),
        positions: nodes.iter().map(|n| x[n.0 as usize].into()).collect(),
        velocities: nodes.iter().map(|n| v[n.0 as usize].into()).collect(),
    }
}

/// [`SyncStrategy::FullState`]: every node of the organ and every root's tree state.
pub fn encode_full_state(
    sim: &Simulation,
    map: &RegionMap,
    keyframe_id: KeyframeId,
) -> RegionKeyframe {
    let nodes = map.canonical_nodes(sim.lattice(), FULL_STATE_REGION);
    keyframe_from_nodes(sim, map, FULL_STATE_REGION, keyframe_id, &nodes)
}

/// [`SyncStrategy::FullState`] receiver: matches the whole tree state and takes over every
/// node's position and velocity directly (no extrapolation, no blending).
pub fn apply_full_state(
    sim: &mut Simulation,
    map: &RegionMap,
    kf: &RegionKeyframe,
) -> Result<(), SyncError> {
    if kf.region != FULL_STATE_REGION {
        return Err(SyncError::WrongRegion {
            region: FULL_STATE_REGION,
            got: kf.region,
        });
    }
    let nodes = match_tree_and_nodes(sim, map, kf)?;
    for (i, &n) in nodes.iter().enumerate() {
        sim.set_node_state(n, V3::from(kf.positions[i]), V3::from(kf.velocities[i]));
    }
    sim.update_surfaces();
    Ok(())
}

/// Checks the frame, makes the region's tree state match it, and returns the region's
/// canonical nodes (as many as the frame has).
fn match_tree_and_nodes(
    sim: &mut Simulation,
    map: &RegionMap,
    kf: &RegionKeyframe,
) -> Result<Vec<NodeId>, SyncError> {
    let region = kf.region;
    if !map.contains(region) {
        return Err(SyncError::UnknownRegion(region));
    }
    if kf.positions.len() != kf.velocities.len() {
        return Err(SyncError::LengthMismatch {
            region,
            positions: kf.positions.len(),
            velocities: kf.velocities.len(),
        });
    }
    if kf
        .positions
        .iter()
        .chain(&kf.velocities)
        .any(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(SyncError::NonFinite { region });
    }
    let target = RegionState::from_bytes(&kf.tree_bits)
        .map_err(|source| SyncError::TreeBits { region, source })?;
    apply_tree(sim, map, region, &target)?;
    let nodes = map.canonical_nodes(sim.lattice(), region);
    if nodes.len() != kf.positions.len() {
        return Err(SyncError::NodeCount {
            region,
            expected: nodes.len(),
            got: kf.positions.len(),
        });
    }
    Ok(nodes)
}

/// Makes the region's trees equal `target` and lets the simulation follow.
fn apply_tree(
    sim: &mut Simulation,
    map: &RegionMap,
    region: RegionId,
    target: &RegionState,
) -> Result<(), SyncError> {
    if target.roots() != map.roots(region) {
        return Err(SyncError::TreeRoots { region });
    }
    let mut events = Vec::new();
    let stats = sim
        .lattice_mut()
        .apply_state(target, &mut events)
        .map_err(|source| SyncError::Lattice { region, source });
    // Whatever changed before an error must still reach the node state.
    sim.after_topology_change(&events)?;
    let stats = stats?;
    if stats.residual != 0 {
        return Err(SyncError::Residual {
            region,
            residual: stats.residual,
        });
    }
    Ok(())
}

/// Encodes a set of split tets over `roots` exactly like [`RegionState::to_bytes`] (the
/// lattice crate has no public constructor from tets; the format is documented there and
/// a test checks that both encoders agree).
pub fn encode_split_set(roots: &[u32], tets: impl IntoIterator<Item = TetId>) -> Vec<u8> {
    let mut per_root: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for t in tets {
        per_root.entry(t.root).or_default().push(t.heap);
    }
    let mut out = Vec::new();
    out.extend_from_slice(b"CSRS");
    out.push(1);
    put_varint(&mut out, roots.len() as u64);
    for &root in roots {
        let mut heaps = per_root.remove(&root).unwrap_or_default();
        heaps.sort_unstable();
        heaps.dedup();
        let mut words: Vec<(u32, u64)> = Vec::new();
        for h in heaps {
            let (w, b) = (h >> 6, 1u64 << (h & 63));
            match words.last_mut() {
                Some(last) if last.0 == w => last.1 |= b,
                _ => words.push((w, b)),
            }
        }
        put_varint(&mut out, u64::from(root));
        put_varint(&mut out, words.len() as u64);
        let mut prev = 0;
        for (i, &(w, bits)) in words.iter().enumerate() {
            put_varint(&mut out, u64::from(if i == 0 { w } else { w - prev }));
            prev = w;
            out.extend_from_slice(&bits.to_le_bytes());
        }
    }
    out
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// `base` with the split state of every tet named by `delta` toggled.
fn xor_state(base: &RegionState, delta: &RegionState) -> Result<RegionState, StateDecodeError> {
    let mut set: HashSet<TetId> = base.split_tets().collect();
    for t in delta.split_tets() {
        if !set.remove(&t) {
            set.insert(t);
        }
    }
    RegionState::from_bytes(&encode_split_set(base.roots(), set))
}

/// The XOR of two tree states of the same roots, encoded for [`RegionTreeDelta::xor_bits`].
pub fn encode_tree_xor(base: &RegionState, current: &RegionState) -> Vec<u8> {
    encode_split_set(current.roots(), current.xor(base).tets())
}

// ---------------------------------------------------------------------------------------
// Motion model (shared by owner and receiver)
// ---------------------------------------------------------------------------------------

/// Second-order motion of one node from a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Motion {
    x: V3,
    v: V3,
    a: V3,
    t0: f64,
}

impl Motion {
    fn eval(&self, t: f64, horizon: f64) -> (V3, V3) {
        let d = (t - self.t0).clamp(-horizon, horizon);
        (
            self.x + self.v * d + 0.5 * self.a * (d * d),
            self.v + self.a * d,
        )
    }

    fn average(a: &Motion, b: &Motion) -> Motion {
        Motion {
            x: 0.5 * (a.x + b.x),
            v: 0.5 * (a.v + b.v),
            a: 0.5 * (a.a + b.a),
            t0: a.t0.max(b.t0),
        }
    }
}

/// Node motions of a region from its keyframes, by grid coordinate.
#[derive(Clone, Debug, Default)]
struct MotionSet {
    motions: HashMap<Grid, Motion>,
    /// Velocities and time of the latest keyframe (for the next acceleration estimate).
    last_velocities: HashMap<Grid, V3>,
    last_time: Option<f64>,
}

impl MotionSet {
    /// Takes a keyframe (canonical grids and states) as the new motion.
    fn take_keyframe(&mut self, grids: &[Grid], kf: &RegionKeyframe, max_accel: f64) {
        let dt = self.last_time.map(|t| kf.sim_time - t);
        let mut motions = HashMap::with_capacity(grids.len());
        let mut velocities = HashMap::with_capacity(grids.len());
        for (i, g) in grids.iter().enumerate() {
            let x = V3::from(kf.positions[i]);
            let v = V3::from(kf.velocities[i]);
            let mut a = match (dt, self.last_velocities.get(g)) {
                (Some(dt), Some(v0)) if dt > 1e-9 => (v - v0) / dt,
                _ => V3::zeros(),
            };
            let n = a.norm();
            if n.is_nan() || n > max_accel {
                a = if n.is_finite() {
                    a * (max_accel / n)
                } else {
                    V3::zeros()
                };
            }
            motions.insert(
                *g,
                Motion {
                    x,
                    v,
                    a,
                    t0: kf.sim_time,
                },
            );
            velocities.insert(*g, v);
        }
        self.motions = motions;
        self.last_velocities = velocities;
        self.last_time = Some(kf.sim_time);
    }

    /// The motion of a node, derived for nodes created since the keyframe from the motions
    /// of the edge they split (recursively), the same way on owner and receiver.
    fn motion(&mut self, lattice: &Lattice, n: NodeId) -> Option<Motion> {
        let g = lattice.node_grid(n);
        if let Some(m) = self.motions.get(&g) {
            return Some(*m);
        }
        let (a, b) = lattice.node_parent_edge(n)?;
        let ma = self.motion(lattice, a)?;
        let mb = self.motion(lattice, b)?;
        let m = Motion::average(&ma, &mb);
        self.motions.insert(g, m);
        Some(m)
    }
}

// ---------------------------------------------------------------------------------------
// Receiver
// ---------------------------------------------------------------------------------------

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
    released: bool,
    cache: NodeCache,
    keyframes_applied: u64,
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
            deltas_applied: 0,
        }
    }

    pub fn region(&self) -> RegionId {
        self.region
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
        let nodes = match_tree_and_nodes(sim, map, kf)?;
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
        for (i, &n) in nodes.iter().enumerate() {
            if sim.is_fixed(n) {
                continue;
            }
            let (x, v) = self.motions.motions[&grids[i]].eval(t, h);
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
        let target =
            xor_state(base, &delta).map_err(|source| SyncError::TreeBits { region, source })?;
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
        if !same_tree || grids.len() != kf.positions.len() {
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

// ---------------------------------------------------------------------------------------
// Owner: dead reckoning
// ---------------------------------------------------------------------------------------

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
    counters: SendCounters,
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

// ---------------------------------------------------------------------------------------
// A site's sync state
// ---------------------------------------------------------------------------------------

/// Everything a site keeps for [`SyncStrategy::Keyframe`] and [`SyncStrategy::FullState`]:
/// the region map, the owner policy, and the remote regions.
#[derive(Clone, Debug)]
pub struct SiteSync {
    pub strategy: SyncStrategy,
    pub map: RegionMap,
    pub policy: SendPolicy,
    remote: BTreeMap<RegionId, RemoteRegion>,
    config: SyncConfig,
    full_state_next_id: KeyframeId,
    full_state_last: Option<KeyframeId>,
    /// Newest keyframe id sent or applied per region: ids stay strictly increasing per
    /// region across changes of ownership (including a site taking a region back), so
    /// receivers and the coordinator never mistake a new keyframe for a stale one.
    newest_id: BTreeMap<RegionId, KeyframeId>,
    /// Regions another site released; late frames for them are ignored once their
    /// remote state has blended out.
    released: std::collections::BTreeSet<RegionId>,
}

impl SiteSync {
    pub fn new(strategy: SyncStrategy, map: RegionMap, config: SyncConfig) -> Self {
        SiteSync {
            strategy,
            map,
            policy: SendPolicy::new(config),
            remote: BTreeMap::new(),
            config,
            full_state_next_id: 1,
            full_state_last: None,
            newest_id: BTreeMap::new(),
            released: Default::default(),
        }
    }

    /// Remote region state (created on its first keyframe).
    pub fn remote(&self, region: RegionId) -> Option<&RemoteRegion> {
        self.remote.get(&region)
    }

    /// Regions currently driven by another site.
    pub fn remote_regions(&self) -> impl Iterator<Item = RegionId> + '_ {
        self.remote.keys().copied()
    }

    /// Before every step: drives remote regions (drops those back to local simulation).
    pub fn before_step(&mut self, sim: &mut Simulation) {
        let map = &self.map;
        self.remote
            .retain(|_, r| r.drive(sim, map) != DriveStatus::Local);
    }

    /// After every step, as owner: frames to send. Under `FullState`, the owner of any
    /// region (the one site with a tool on the organ) sends the whole organ every k steps.
    pub fn after_step(
        &mut self,
        sim: &Simulation,
        acked_base: impl Fn(RegionId) -> Option<KeyframeId>,
    ) -> Vec<SyncFrame> {
        match self.strategy {
            SyncStrategy::Keyframe => {
                let frames = self.policy.poll(sim, &self.map, sim.time(), acked_base);
                for f in &frames {
                    if let SyncFrame::Keyframe(kf) = f {
                        self.note_id(kf.region, kf.keyframe_id);
                    }
                }
                frames
            }
            SyncStrategy::FullState { every_steps } => {
                if self.policy.regions.is_empty()
                    || !sim.steps().is_multiple_of(u64::from(every_steps.max(1)))
                {
                    return Vec::new();
                }
                let id = self.full_state_next_id;
                self.full_state_next_id += 1;
                self.policy.counters.keyframes += 1;
                vec![SyncFrame::Keyframe(encode_full_state(sim, &self.map, id))]
            }
            SyncStrategy::InputOnly => Vec::new(),
        }
    }

    /// Holds the next keyframe of a remote region before this site's clock reaches it
    /// ([`RemoteRegion::hold_next`]); returns whether it is held.
    pub fn hold_next(&mut self, sim: &Simulation, kf: &RegionKeyframe) -> bool {
        if self.strategy != SyncStrategy::Keyframe || self.policy.is_owned(kf.region) {
            return false;
        }
        match self.remote.get_mut(&kf.region) {
            Some(r) => r.hold_next(sim, &self.map, kf),
            None => false,
        }
    }

    /// This site was granted `region`; numbering continues after the newest id seen.
    pub fn on_grant(&mut self, region: RegionId) {
        self.released.remove(&region);
        if let Some(k) = self.remote.remove(&region).and_then(|r| r.last_keyframe()) {
            self.note_id(region, k);
        }
        let next = self.newest_id.get(&region).map_or(1, |k| k + 1);
        self.policy.acquire(region, next);
    }

    fn note_id(&mut self, region: RegionId, id: KeyframeId) {
        let e = self.newest_id.entry(region).or_insert(0);
        *e = (*e).max(id);
    }

    /// This site releases `region`: the final keyframe to send (Keyframe strategy).
    pub fn release(&mut self, sim: &Simulation, region: RegionId) -> Option<SyncFrame> {
        let kf = self.policy.release(sim, &self.map, region)?;
        self.note_id(region, kf.keyframe_id);
        (self.strategy == SyncStrategy::Keyframe).then_some(SyncFrame::Keyframe(kf))
    }

    /// Another site released `region` (after sending its final keyframe).
    pub fn on_remote_release(&mut self, region: RegionId) {
        self.released.insert(region);
        if let Some(r) = self.remote.get_mut(&region) {
            r.release();
        }
    }

    /// Another site was granted `region`: its keyframes drive the region again.
    pub fn on_remote_grant(&mut self, region: RegionId) {
        self.released.remove(&region);
        if let Some(r) = self.remote.get_mut(&region) {
            r.released = false;
        }
    }

    /// A frame from another site. Returns the keyframe id to acknowledge, if any. Frames for
    /// regions this site owns, and late frames for a released region that is already back
    /// to local simulation, are ignored.
    pub fn on_frame(
        &mut self,
        sim: &mut Simulation,
        frame: &SyncFrame,
    ) -> Result<Option<KeyframeId>, SyncError> {
        match frame {
            SyncFrame::Keyframe(kf) if kf.region == FULL_STATE_REGION => {
                if self.full_state_last.is_some_and(|k| kf.keyframe_id <= k) {
                    return Ok(None);
                }
                apply_full_state(sim, &self.map, kf)?;
                self.full_state_last = Some(kf.keyframe_id);
                Ok(None)
            }
            SyncFrame::Keyframe(kf) => {
                if self.policy.is_owned(kf.region)
                    || (self.released.contains(&kf.region) && !self.remote.contains_key(&kf.region))
                {
                    return Ok(None);
                }
                let config = self.config;
                let r = self
                    .remote
                    .entry(kf.region)
                    .or_insert_with(|| RemoteRegion::new(kf.region, config));
                let applied = r.apply_keyframe(sim, &self.map, kf)? == Applied::Applied;
                if applied {
                    self.note_id(kf.region, kf.keyframe_id);
                }
                Ok(applied.then_some(kf.keyframe_id))
            }
            SyncFrame::TreeDelta(d) => {
                match self.remote.get_mut(&d.region) {
                    Some(r) => {
                        r.apply_tree_delta(sim, &self.map, d)?;
                    }
                    None => {
                        return Err(SyncError::UnknownBase {
                            region: d.region,
                            base: d.base_keyframe,
                        });
                    }
                }
                Ok(None)
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Divergence and `.surf` recordings
// ---------------------------------------------------------------------------------------

/// Max and RMS distance (m) between corresponding vertices of two surfaces; compares the
/// first `min(a.len(), b.len())` vertices; `(0, 0)` when there are none.
pub fn surface_divergence(a: &[V3], b: &[V3]) -> (f64, f64) {
    let n = a.len().min(b.len());
    if n == 0 {
        return (0.0, 0.0);
    }
    let (mut max, mut sum): (f64, f64) = (0.0, 0.0);
    for (p, q) in a.iter().zip(b) {
        let d2 = (p - q).norm_squared();
        max = max.max(d2);
        sum += d2;
    }
    (max.sqrt(), (sum / n as f64).sqrt())
}

/// Magic of a `.surf` file.
pub const SURF_MAGIC: &[u8; 8] = b"CSURF01\n";
const SURF_MAX_HASH: u32 = 1024;
const SURF_MAX_SURFACES: u32 = 4096;
const SURF_MAX_VERTICES: u64 = 1 << 24;

/// A malformed `.surf` file (or two recordings that cannot be compared).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SurfError {
    #[error(".surf: bad magic (not a cosurg surface recording, or another version)")]
    BadMagic,
    #[error(".surf: truncated in {what} at byte {offset}")]
    Truncated { what: &'static str, offset: usize },
    #[error(".surf: {what} {value} exceeds the limit {max}")]
    TooLarge {
        what: &'static str,
        value: u64,
        max: u64,
    },
    #[error(".surf: scene hash is not UTF-8")]
    HashNotUtf8,
    #[error(".surf: mark interval {0} s is not positive and finite")]
    BadInterval(f64),
    #[error(".surf: {remaining} trailing bytes do not form a whole record of {record_size} bytes")]
    PartialRecord {
        remaining: usize,
        record_size: usize,
    },
    #[error(".surf: record {index}: time {time} s is not finite or not increasing")]
    BadTime { index: usize, time: f64 },
    #[error(".surf: record {index}: non-finite vertex coordinate")]
    NonFinite { index: usize },
    #[error("surface recordings differ in {what}: {a} vs {b}")]
    Mismatch {
        what: &'static str,
        a: String,
        b: String,
    },
}

/// One sample of every surface vertex at a sim-time mark.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceRecord {
    /// Simulation time of the mark (s).
    pub time_s: f64,
    /// Vertex positions (m) of all surfaces, concatenated in surface order.
    pub vertices: Vec<[f32; 3]>,
}

/// Surface vertex positions at fixed sim-time marks, as stored in a `.surf` file.
///
/// # `.surf` format (little-endian)
/// ```text
/// 8 bytes   magic "CSURF01\n"
/// u32       scene hash length H (≤ 1024), then H bytes of UTF-8 scene hash
/// f64       mark interval (s), positive
/// u32       surface count S (≤ 4096), then S × u32 vertex counts; N = their sum (≤ 2^24)
/// records until the end of the file, each: f64 time (s, increasing), N × 3 f32 xyz (m)
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceRecording {
    pub scene_hash: String,
    pub interval_s: f64,
    /// Vertex count of each surface.
    pub surface_sizes: Vec<u32>,
    pub records: Vec<SurfaceRecord>,
}

/// Divergence between two recordings at one mark.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DivergenceSample {
    pub time_s: f64,
    pub max_m: f64,
    pub rms_m: f64,
}

impl SurfaceRecording {
    /// Total vertex count per record.
    pub fn vertex_count(&self) -> usize {
        self.surface_sizes.iter().map(|&n| n as usize).sum()
    }

    /// Bytes of the header.
    fn header_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(SURF_MAGIC);
        out.extend_from_slice(&(self.scene_hash.len() as u32).to_le_bytes());
        out.extend_from_slice(self.scene_hash.as_bytes());
        out.extend_from_slice(&self.interval_s.to_le_bytes());
        out.extend_from_slice(&(self.surface_sizes.len() as u32).to_le_bytes());
        for n in &self.surface_sizes {
            out.extend_from_slice(&n.to_le_bytes());
        }
        out
    }

    fn record_bytes(r: &SurfaceRecord, out: &mut Vec<u8>) {
        out.extend_from_slice(&r.time_s.to_le_bytes());
        for v in &r.vertices {
            for c in v {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = self.header_bytes();
        for r in &self.records {
            Self::record_bytes(r, &mut out);
        }
        out
    }

    /// Writes the file.
    pub fn write_to<W: Write>(&self, mut w: W) -> std::io::Result<()> {
        w.write_all(&self.to_bytes())
    }

    /// Parses a file; rejects malformed input with a [`SurfError`], never panics.
    pub fn from_bytes(bytes: &[u8]) -> Result<SurfaceRecording, SurfError> {
        let mut pos = 0usize;
        let mut take = |n: usize, what: &'static str| -> Result<&[u8], SurfError> {
            let s = bytes
                .get(pos..pos.saturating_add(n))
                .ok_or(SurfError::Truncated { what, offset: pos })?;
            pos += n;
            Ok(s)
        };
        if take(8, "magic").map_err(|_| SurfError::BadMagic)? != SURF_MAGIC {
            return Err(SurfError::BadMagic);
        }
        let u32_of = |s: &[u8]| u32::from_le_bytes(s.try_into().expect("4 bytes"));
        let hash_len = u32_of(take(4, "hash length")?);
        if hash_len > SURF_MAX_HASH {
            return Err(SurfError::TooLarge {
                what: "scene hash length",
                value: hash_len.into(),
                max: SURF_MAX_HASH.into(),
            });
        }
        let scene_hash = std::str::from_utf8(take(hash_len as usize, "scene hash")?)
            .map_err(|_| SurfError::HashNotUtf8)?
            .to_string();
        let interval_s = f64::from_le_bytes(take(8, "interval")?.try_into().expect("8 bytes"));
        if !(interval_s.is_finite() && interval_s > 0.0) {
            return Err(SurfError::BadInterval(interval_s));
        }
        let n_surfaces = u32_of(take(4, "surface count")?);
        if n_surfaces > SURF_MAX_SURFACES {
            return Err(SurfError::TooLarge {
                what: "surface count",
                value: n_surfaces.into(),
                max: SURF_MAX_SURFACES.into(),
            });
        }
        let mut surface_sizes = Vec::with_capacity(n_surfaces as usize);
        let mut total: u64 = 0;
        for _ in 0..n_surfaces {
            let n = u32_of(take(4, "vertex counts")?);
            total += u64::from(n);
            surface_sizes.push(n);
        }
        if total > SURF_MAX_VERTICES {
            return Err(SurfError::TooLarge {
                what: "vertex count",
                value: total,
                max: SURF_MAX_VERTICES,
            });
        }
        let n = total as usize;
        let record_size = 8 + 12 * n;
        let rest = &bytes[pos..];
        if !rest.len().is_multiple_of(record_size) {
            return Err(SurfError::PartialRecord {
                remaining: rest.len() % record_size,
                record_size,
            });
        }
        let mut records = Vec::with_capacity(rest.len() / record_size);
        let mut prev = f64::NEG_INFINITY;
        for (index, rec) in rest.chunks_exact(record_size).enumerate() {
            let time_s = f64::from_le_bytes(rec[..8].try_into().expect("8 bytes"));
            if !(time_s.is_finite() && time_s > prev) {
                return Err(SurfError::BadTime {
                    index,
                    time: time_s,
                });
            }
            prev = time_s;
            let mut vertices = Vec::with_capacity(n);
            for v in rec[8..].chunks_exact(12) {
                let c =
                    |k: usize| f32::from_le_bytes(v[4 * k..4 * k + 4].try_into().expect("4 bytes"));
                let p = [c(0), c(1), c(2)];
                if p.iter().any(|c| !c.is_finite()) {
                    return Err(SurfError::NonFinite { index });
                }
                vertices.push(p);
            }
            records.push(SurfaceRecord { time_s, vertices });
        }
        Ok(SurfaceRecording {
            scene_hash,
            interval_s,
            surface_sizes,
            records,
        })
    }

    /// Divergence at every mark present in both recordings (times equal within 1 µs).
    /// Errors if the scene hashes or surface sizes differ.
    pub fn divergence(&self, other: &SurfaceRecording) -> Result<Vec<DivergenceSample>, SurfError> {
        if self.scene_hash != other.scene_hash {
            return Err(SurfError::Mismatch {
                what: "scene hash",
                a: self.scene_hash.clone(),
                b: other.scene_hash.clone(),
            });
        }
        if self.surface_sizes != other.surface_sizes {
            return Err(SurfError::Mismatch {
                what: "surface sizes",
                a: format!("{:?}", self.surface_sizes),
                b: format!("{:?}", other.surface_sizes),
            });
        }
        let mut out = Vec::new();
        let mut j = 0;
        for r in &self.records {
            while j < other.records.len() && other.records[j].time_s < r.time_s - 1e-6 {
                j += 1;
            }
            let Some(o) = other.records.get(j) else { break };
            if (o.time_s - r.time_s).abs() <= 1e-6 {
                let to64 = |v: &[[f32; 3]]| -> Vec<V3> {
                    v.iter()
                        .map(|p| V3::new(p[0].into(), p[1].into(), p[2].into()))
                        .collect()
                };
                let (max_m, rms_m) = surface_divergence(&to64(&r.vertices), &to64(&o.vertices));
                out.push(DivergenceSample {
                    time_s: r.time_s,
                    max_m,
                    rms_m,
                });
            }
        }
        Ok(out)
    }
}

/// Records every surface's vertices at marks `k · interval` of sim time (linearly
/// interpolated between the two steps around a mark). Call [`SurfaceRecorder::record`]
/// after every step (and once before the first).
#[derive(Clone, Debug)]
pub struct SurfaceRecorder {
    recording: SurfaceRecording,
    next_mark: u64,
    prev: Option<(f64, Vec<V3>)>,
}

/// Default mark interval of [`SurfaceRecorder`]: 50 ms of sim time.
pub const DEFAULT_MARK_INTERVAL_S: f64 = 0.05;

impl SurfaceRecorder {
    /// A recorder for the simulation's surfaces; `interval_s` ≤ 0 or non-finite falls back
    /// to [`DEFAULT_MARK_INTERVAL_S`].
    pub fn new(sim: &Simulation, interval_s: f64) -> Self {
        let interval_s = if interval_s.is_finite() && interval_s > 0.0 {
            interval_s
        } else {
            DEFAULT_MARK_INTERVAL_S
        };
        SurfaceRecorder {
            recording: SurfaceRecording {
                scene_hash: sim.scene().hash.clone(),
                interval_s,
                surface_sizes: sim
                    .surfaces()
                    .iter()
                    .map(|s| s.deformed.len() as u32)
                    .collect(),
                records: Vec::new(),
            },
            next_mark: (sim.time() / interval_s - 1e-9).ceil().max(0.0) as u64,
            prev: None,
        }
    }

    /// Samples the marks passed since the last call.
    pub fn record(&mut self, sim: &Simulation) {
        let t = sim.time();
        let cur: Vec<V3> = sim
            .surfaces()
            .iter()
            .flat_map(|s| s.deformed.iter().copied())
            .collect();
        let dt = self.recording.interval_s;
        loop {
            let mark = self.next_mark as f64 * dt;
            if mark > t + 1e-9 {
                break;
            }
            let pts: Vec<[f32; 3]> = match &self.prev {
                Some((tp, prev)) if *tp < mark - 1e-9 && t - tp > 1e-12 => {
                    let w = (mark - tp) / (t - tp);
                    prev.iter()
                        .zip(&cur)
                        .map(|(a, b)| to_f32(&(a + (b - a) * w)))
                        .collect()
                }
                _ => cur.iter().map(to_f32).collect(),
            };
            self.recording.records.push(SurfaceRecord {
                time_s: mark,
                vertices: pts,
            });
            self.next_mark += 1;
        }
        self.prev = Some((t, cur));
    }

    pub fn recording(&self) -> &SurfaceRecording {
        &self.recording
    }

    pub fn into_recording(self) -> SurfaceRecording {
        self.recording
    }
}

fn to_f32(p: &V3) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}
