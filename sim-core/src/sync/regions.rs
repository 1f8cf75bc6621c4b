//! The region map: a deterministic partition of the root tets into blocks, and the
//! canonical node order of a region (see the module docs of [`super`]).

use std::collections::{HashMap, HashSet};

use sim_lattice::{Lattice, NodeId, RegionState, TetId};

use super::{DEFAULT_REGION_BLOCK, FULL_STATE_REGION, Grid, RegionId, V3};
use crate::engine::Simulation;

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

    /// Fastest node speed (m/s) of every region (indexed by region id) at node
    /// velocities `v` (lattice slots; a cut's virtual nodes are not counted).
    pub fn max_speeds(&self, lattice: &Lattice, v: &[V3]) -> Vec<f64> {
        let mut speeds = vec![0.0f64; self.roots.len()];
        for &t in lattice.leaves() {
            let Some(r) = self.region_of_root(t.root) else {
                continue;
            };
            let fastest = lattice
                .tet_nodes(t)
                .iter()
                .filter_map(|n| v.get(n.0 as usize))
                .map(|v| v.norm())
                .fold(0.0f64, f64::max);
            let slot = &mut speeds[r as usize];
            *slot = slot.max(fastest);
        }
        speeds
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
pub(super) struct NodeCache {
    generation: Option<u64>,
    nodes: Vec<NodeId>,
    grids: Vec<Grid>,
}

impl NodeCache {
    pub(super) fn get(
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
