//! A refinement decision as an operation ([`RefineOp`]) and its application.
//!
//! The op names what to split and what to merge in rest space and grid coordinates only —
//! focus points in rest coordinates (m, exact `f64`), a distance, a level, and diamond
//! centres by their integer grid position — so applying it reads no floating-point state:
//! two sites with the same lattice that apply the same op end with the same lattice. The
//! state enters once, on the deciding site, where contacts and grasped points are mapped to
//! rest space ([`super::Adaptivity`]).

use std::collections::{HashMap, HashSet};

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use sim_lattice::{NodeId, TetId};

use crate::cut::OpId;
use crate::engine::Simulation;
use crate::error::SimError;

type V3 = Vector3<f64>;

/// Sequence numbers of refinement ops start here (cuts from 0, clips from `1 << 30`,
/// releases from `1 << 31`), so that one site's ops of every kind have distinct ids.
pub const REFINE_SEQ_BASE: u32 = 3 << 30;

/// Most focus points one op may carry.
pub const MAX_REFINE_FOCUS: usize = 4096;

/// Most diamonds one op may merge.
pub const MAX_REFINE_MERGES: usize = 65_536;

/// Largest refinement distance an op may state, in root cells of the lattice it is
/// applied to: a focus point refines what lies within this of it, so a larger value is a
/// malformed op (it would refine the whole organ to the deepest level), not a decision.
pub const MAX_REFINE_DISTANCE_CELLS: f64 = 2.0;

/// Tool-following refinement decided on one site and applied on every site at the same
/// simulated time: every leaf whose **rest** box comes within `distance` of a focus point
/// splits (with what conformity forces) until it reaches `level`; then the diamonds
/// centred on `merge` merge back where they still can (finest first; a diamond along a
/// cut, or of the scene's static refinement, never merges).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RefineOp {
    /// Identity (its seq from [`REFINE_SEQ_BASE`]).
    pub id: OpId,
    /// Focus points in rest coordinates (m).
    pub focus: Vec<[f64; 3]>,
    /// Refinement distance (m, rest).
    pub distance: f64,
    /// Level to refine to (clamped to the lattice's maximum depth).
    pub level: u8,
    /// Diamond centres to merge, by grid position, finest first.
    pub merge: Vec<[i64; 3]>,
}

/// What applying a [`RefineOp`] changed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RefineChange {
    /// Tets split (including conformity splits).
    pub split: usize,
    /// Diamonds merged.
    pub merged: usize,
}

impl RefineOp {
    /// Checks the op's sizes and that its numbers are finite and in range.
    pub fn validate(&self) -> Result<(), String> {
        if self.focus.len() > MAX_REFINE_FOCUS {
            return Err(format!(
                "refinement {:?} has {} focus points (at most {MAX_REFINE_FOCUS})",
                self.id,
                self.focus.len()
            ));
        }
        if self.merge.len() > MAX_REFINE_MERGES {
            return Err(format!(
                "refinement {:?} merges {} diamonds (at most {MAX_REFINE_MERGES})",
                self.id,
                self.merge.len()
            ));
        }
        if let Some(i) = self
            .focus
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(format!(
                "refinement {:?}: focus point {i} is not finite",
                self.id
            ));
        }
        if !(self.distance.is_finite() && self.distance >= 0.0) {
            return Err(format!(
                "refinement {:?}: distance {} m is not a length",
                self.id, self.distance
            ));
        }
        Ok(())
    }

    /// Bytes of the op as carried (id, 24 per focus point, distance, level, 24 per merge).
    pub fn wire_bytes(&self) -> usize {
        8 + 4 + 24 * self.focus.len() + 8 + 1 + 4 + 24 * self.merge.len()
    }

    /// The focus points as vectors (m, rest).
    pub fn focus_points(&self) -> impl Iterator<Item = V3> + '_ {
        self.focus.iter().map(|p| V3::new(p[0], p[1], p[2]))
    }
}

impl Simulation {
    /// Applies a refinement op (see [`RefineOp`]). Not logged with the cuts: refinement
    /// is not part of the cut topology, its epoch or its digest (the regions' tree states
    /// carry it in keyframes).
    /// Errors (nothing changed) for an op that fails [`RefineOp::validate`] or states a
    /// distance of more than [`MAX_REFINE_DISTANCE_CELLS`] root cells.
    pub fn apply_refine(&mut self, op: &RefineOp) -> Result<RefineChange, SimError> {
        op.validate().map_err(SimError::Topology)?;
        let cell = self.lattice().params().cell;
        if op.distance > MAX_REFINE_DISTANCE_CELLS * cell {
            return Err(SimError::Topology(format!(
                "refinement {:?}: distance {} m is more than {MAX_REFINE_DISTANCE_CELLS} \
                 cells ({} m)",
                op.id,
                op.distance,
                MAX_REFINE_DISTANCE_CELLS * cell
            )));
        }
        let mut change = RefineChange::default();
        let max_level = op.level.min(self.lattice().params().max_depth);
        let focus: Vec<V3> = op.focus_points().collect();
        if !focus.is_empty() && max_level > 0 {
            change.split = refine_near(self, &focus, op.distance, max_level, Space::Rest)?;
        }
        if !op.merge.is_empty() {
            change.merged = merge_diamonds(self, &op.merge)?;
        }
        Ok(change)
    }
}

/// Which positions a refinement decision reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Space {
    /// Rest positions: exact, the same on every site (decisions carried as ops).
    Rest,
    /// Current (deformed) positions: where the tissue is now (decisions applied at once
    /// on the site that takes them).
    Deformed,
}

/// Box of leaf `i` (m) in `space`.
pub(super) fn leaf_box(sim: &Simulation, i: usize, space: Space) -> (V3, V3) {
    let lat = sim.lattice();
    let x = sim.positions();
    let mut lo = V3::repeat(f64::INFINITY);
    let mut hi = V3::repeat(f64::NEG_INFINITY);
    for n in lat.leaf_tet_nodes(i) {
        let p = match space {
            Space::Rest => lat.node_rest(n),
            Space::Deformed => x[n.0 as usize],
        };
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    (lo, hi)
}

/// Splits every leaf below `max_level` whose box in `space` comes within `d` of a focus
/// point (m, in the same space), one level per round, until none is left. Returns the tets
/// split.
pub(super) fn refine_near(
    sim: &mut Simulation,
    focus: &[V3],
    d: f64,
    max_level: u8,
    space: Space,
) -> Result<usize, SimError> {
    let (flo, fhi) = padded_box(focus, d);
    let mut split = 0;
    // Each round splits the near leaves one level (and what conformity forces).
    for _ in 0..=(3 * usize::from(max_level) + 3) {
        let todo: Vec<TetId> = sim
            .lattice()
            .leaves()
            .iter()
            .enumerate()
            .filter(|(_, t)| t.level() < max_level)
            .filter(|(i, _)| {
                let (lo, hi) = leaf_box(sim, *i, space);
                if (0..3).any(|k| lo[k] > fhi[k] || hi[k] < flo[k]) {
                    return false;
                }
                focus.iter().any(|p| box_distance(&lo, &hi, p) <= d)
            })
            .map(|(_, t)| *t)
            .collect();
        if todo.is_empty() {
            break;
        }
        let mut events = Vec::new();
        for t in todo {
            let lat = sim.lattice_mut();
            if lat.is_leaf(t) {
                split += lat.refine(t, &mut events)?;
            }
        }
        sim.after_topology_change(&events)?;
    }
    Ok(split)
}

/// Merges the diamonds centred on `centres` (grid positions) where they can be, in the
/// order given, again while any merged (a coarser diamond waits for its finer ones).
/// Returns the diamonds merged.
pub(super) fn merge_diamonds(
    sim: &mut Simulation,
    centres: &[[i64; 3]],
) -> Result<usize, SimError> {
    let wanted: HashSet<[i64; 3]> = centres.iter().copied().collect();
    let node_of: HashMap<[i64; 3], NodeId> = {
        let lat = sim.lattice();
        lat.nodes()
            .filter_map(|n| {
                let g = lat.node_grid(n);
                wanted.contains(&g).then_some((g, n))
            })
            .collect()
    };
    let mut done: HashSet<[i64; 3]> = HashSet::new();
    let mut merged = 0;
    let mut events = Vec::new();
    loop {
        let mut progress = false;
        for g in centres {
            if done.contains(g) {
                continue;
            }
            let Some(&n) = node_of.get(g) else { continue };
            // A diamond along a cut stays: merging it would reconnect separated material;
            // so does the scene's static refinement.
            if sim.cut_pins_node(n) || sim.is_static_diamond(g) {
                continue;
            }
            let lat = sim.lattice_mut();
            if !lat.node_alive(n) || lat.node_grid(n) != *g || lat.node_parent_edge(n).is_none() {
                done.insert(*g);
                continue;
            }
            if lat.coarsen_diamond(n, &mut events)? {
                done.insert(*g);
                merged += 1;
                progress = true;
            }
        }
        if !progress {
            break;
        }
    }
    sim.after_topology_change(&events)?;
    Ok(merged)
}

/// Distance from `p` to the box `lo..hi` (0 inside).
pub(super) fn box_distance(lo: &V3, hi: &V3, p: &V3) -> f64 {
    let mut d2 = 0.0;
    for k in 0..3 {
        let e = (lo[k] - p[k]).max(p[k] - hi[k]).max(0.0);
        d2 += e * e;
    }
    d2.sqrt()
}

/// The box around `points` padded by `d` on every side (m).
pub(super) fn padded_box(points: &[V3], d: f64) -> (V3, V3) {
    let mut lo = V3::repeat(f64::INFINITY);
    let mut hi = V3::repeat(f64::NEG_INFINITY);
    for p in points {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    (lo.add_scalar(-d), hi.add_scalar(d))
}
