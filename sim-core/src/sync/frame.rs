//! What an owner sends ([`SyncFrame`]: a [`RegionKeyframe`] or a [`RegionTreeDelta`]),
//! how a region's state is encoded into one, and how a frame's tree state and node states
//! are applied (full-state frames here, keyframes by the receiver).

use std::collections::{HashMap, HashSet};

use sim_lattice::{NodeId, RegionState, TetId};

use super::{FULL_STATE_REGION, Grid, KeyframeId, RegionId, RegionMap, SyncError, V3};
use crate::engine::Simulation;

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

pub(super) fn keyframe_from_nodes(
    sim: &Simulation,
    map: &RegionMap,
    region: RegionId,
    keyframe_id: KeyframeId,
    nodes: &[NodeId],
) -> RegionKeyframe {
    let (x, v) = (sim.positions(), sim.velocities());
    // The region's lattice nodes, then the virtual nodes a cut added to them.
    let dofs: Vec<usize> = nodes
        .iter()
        .map(|n| n.0 as usize)
        .chain(region_virtual_dofs(sim, map, region))
        .collect();
    RegionKeyframe {
        region,
        keyframe_id,
        sim_time: sim.time(),
        tree_bits: map.state(sim.lattice(), region).to_bytes(),
        positions: dofs.iter().map(|&d| x[d].into()).collect(),
        velocities: dofs.iter().map(|&d| v[d].into()).collect(),
    }
}

/// The virtual nodes of a cut (degrees of freedom `>= capacity`, see
/// [`crate::cut::Separation`]) used by the element copies of `region`'s leaves
/// ([`FULL_STATE_REGION`]: every leaf), in an order every site with the same region trees
/// and cuts agrees on: by the grid point of the node they duplicate, then by the first
/// (leaf, corner) of the region's copies that use them. Their slot numbers are no such
/// order (they depend on each site's lattice history), and neither are the copies of
/// neighbouring regions, whose trees may differ between sites.
pub(super) fn region_virtual_dofs(
    sim: &Simulation,
    map: &RegionMap,
    region: RegionId,
) -> Vec<usize> {
    let Some(sep) = sim.separation() else {
        return Vec::new();
    };
    if sep.virtual_nodes.is_empty() {
        return Vec::new();
    }
    let cap = sep.capacity;
    let mut first: HashMap<usize, (TetId, usize)> = HashMap::new();
    for c in &sep.copies {
        if region != FULL_STATE_REGION && map.region_of_root(c.leaf.root) != Some(region) {
            continue;
        }
        for (corner, &d) in c.dofs.iter().enumerate() {
            if d >= cap {
                let key = (c.leaf, corner);
                first
                    .entry(d)
                    .and_modify(|f| *f = (*f).min(key))
                    .or_insert(key);
            }
        }
    }
    let lattice = sim.lattice();
    let mut keyed: Vec<(Grid, (TetId, usize), usize)> = first
        .into_iter()
        .map(|(d, f)| (lattice.node_grid(sep.dof_node(d)), f, d))
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, _, d)| d).collect()
}

/// The frame of [`SyncStrategy::FullState`](super::SyncStrategy::FullState): every node
/// of the organ and every root's tree state.
pub fn encode_full_state(
    sim: &Simulation,
    map: &RegionMap,
    keyframe_id: KeyframeId,
) -> RegionKeyframe {
    let nodes = map.canonical_nodes(sim.lattice(), FULL_STATE_REGION);
    keyframe_from_nodes(sim, map, FULL_STATE_REGION, keyframe_id, &nodes)
}

/// The receiver of [`SyncStrategy::FullState`](super::SyncStrategy::FullState): matches
/// the whole tree state and takes over every node's position and velocity directly (no
/// extrapolation, no blending).
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
    let matched = match_tree_and_nodes(sim, map, kf)?;
    for (i, d) in matched.dofs() {
        sim.set_dof_state(d, V3::from(kf.positions[i]), V3::from(kf.velocities[i]));
    }
    sim.update_surfaces();
    Ok(())
}

/// A keyframe's entries on this site, in its canonical order: the region's lattice nodes,
/// then the cut's virtual nodes (degrees of freedom past the lattice's capacity).
pub(super) struct MatchedNodes {
    pub nodes: Vec<NodeId>,
    /// Empty when the frame's virtual nodes are not ours (see [`match_tree_and_nodes`]).
    pub virtual_dofs: Vec<usize>,
}

impl MatchedNodes {
    /// Every matched degree of freedom with its entry in the frame, lattice nodes first.
    pub fn dofs(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.nodes
            .iter()
            .map(|n| n.0 as usize)
            .chain(self.virtual_dofs.iter().copied())
            .enumerate()
    }

    /// Sets the virtual nodes to the frame's states advanced by `ahead` (s) at their
    /// velocity (the receivers that take the owner's state, not a blended correction).
    pub fn set_virtual_dofs(&self, sim: &mut Simulation, kf: &RegionKeyframe, ahead: f64) {
        for (j, &d) in self.virtual_dofs.iter().enumerate() {
            let i = self.nodes.len() + j;
            let v = V3::from(kf.velocities[i]);
            if !sim.is_fixed(NodeId(d as u32)) {
                sim.set_dof_state(d, V3::from(kf.positions[i]) + v * ahead, v);
            }
        }
    }
}

/// The grid point a degree of freedom stands for (a virtual node's: the lattice node it
/// duplicates), if it is live: what a correction checks before it moves the dof, since
/// the tree or the cuts may have changed since it was measured.
pub(super) fn dof_grid(sim: &Simulation, dof: usize) -> Option<Grid> {
    if dof >= sim.positions().len() {
        return None;
    }
    let node = match sim.separation() {
        Some(sep) if dof >= sep.capacity => sep.dof_node(dof),
        _ => NodeId(dof as u32),
    };
    let lattice = sim.lattice();
    lattice.node_alive(node).then(|| lattice.node_grid(node))
}

/// Checks the frame, makes the region's tree state match it, and returns the region's
/// canonical nodes (as many as the frame has) and, when this site's cuts made the same
/// virtual nodes for the region, those. The caller sets the states: a hybrid follower
/// corrects both kinds alike, the other receivers take the owner's.
pub(super) fn match_tree_and_nodes(
    sim: &mut Simulation,
    map: &RegionMap,
    kf: &RegionKeyframe,
) -> Result<MatchedNodes, SyncError> {
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
    let mut virtual_dofs = region_virtual_dofs(sim, map, region);
    if nodes.len() > kf.positions.len() {
        return Err(SyncError::NodeCount {
            region,
            expected: nodes.len() + virtual_dofs.len(),
            got: kf.positions.len(),
        });
    }
    if nodes.len() + virtual_dofs.len() != kf.positions.len() {
        // Same trees and cuts, other virtual nodes (a copy's connectivity runs through a
        // neighbouring region whose trees differ here): the lattice nodes still apply.
        tracing::debug!(
            region,
            ours = virtual_dofs.len(),
            theirs = kf.positions.len() - nodes.len(),
            "keyframe's virtual nodes not applied"
        );
        virtual_dofs.clear();
    }
    Ok(MatchedNodes {
        nodes,
        virtual_dofs,
    })
}

/// Makes the region's trees equal `target` and lets the simulation follow.
pub(super) fn apply_tree(
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

/// Encodes a set of split tets over `roots` like [`RegionState::to_bytes`] (see
/// [`RegionState::from_split_tets`] for what is ignored).
pub fn encode_split_set(roots: &[u32], tets: impl IntoIterator<Item = TetId>) -> Vec<u8> {
    RegionState::from_split_tets(roots, tets).to_bytes()
}

/// `base` with the split state of every tet named by `delta` toggled.
pub(super) fn xor_state(base: &RegionState, delta: &RegionState) -> RegionState {
    let mut set: HashSet<TetId> = base.split_tets().collect();
    for t in delta.split_tets() {
        if !set.remove(&t) {
            set.insert(t);
        }
    }
    RegionState::from_split_tets(base.roots(), set)
}

/// The XOR of two tree states of the same roots, encoded for [`RegionTreeDelta::xor_bits`].
pub fn encode_tree_xor(base: &RegionState, current: &RegionState) -> Vec<u8> {
    encode_split_set(current.roots(), current.xor(base).tets())
}
