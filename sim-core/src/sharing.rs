//! Hierarchical rotation sharing (DESIGN §1(a), speed-up 1).
//!
//! Rotations of descendants are close to their ancestor's. Above the root cubes the
//! lattice continues as a hierarchy of blocks of `2^k` cubes per axis (a block of 8
//! half-size cubes is exactly what three bisection levels make of one cube, so this is the
//! same diamond hierarchy, coarser). A block exists only where all its `8^k` cubes exist
//! (so its rotation describes material that is actually connected). Each block's rotation
//! comes from one Kuhn tet spanning the block: corners `c`, `c + s x̂`, `c + s(x̂ + ŷ)`,
//! `c + s(x̂ + ŷ + ẑ)`, all of them lattice nodes. The blocks are the FEM system's shared
//! rotation sources ([`sim_fem::FemDesc::rotation_sources`]).
//!
//! Each step, top-down from the coarsest blocks: a block whose rotation `R_m` agrees with
//! every existing face-neighbour block's `R_n` at the same level,
//! `‖R_m − R_n‖²_F < 4(1 − cos θ_tol)`, and has at least one such neighbour (an isolated
//! block gives no evidence that the rotation field is smooth across it), gives its
//! rotation to every leaf inside it; otherwise the test descends to its sub-blocks, down
//! to single cubes. Leaves of a cube that fails the test extract their own rotation.
//! θ_tol = 0 disables sharing.
//!
//! Two rules keep the shared forces continuous where the field is not smooth: a block that
//! holds an inverted element (det F ≤ 0, a signed-volume test per element) never shares,
//! and a block whose leaves used their own rotations in the previous step starts sharing
//! again only when its neighbours agree within θ_tol / 2 (hysteresis). Without them a pull
//! through inversion switched blocks between shared and own rotations every step and each
//! switch released tens of J (`cosurg bench stress`).
//!
//! Block rotations are extracted lazily by the FEM system
//! ([`FemSystem::shared_source_rotation`]) only for the blocks the test visits (and their
//! neighbours); the FEM then extracts only the sources some element references
//! ([`FemSystem::set_rotation_assignment`]), and a step's
//! [`sim_fem::StepStats::rotations_extracted`] counts both.

use std::collections::{HashMap, HashSet};

use nalgebra::{Matrix3, Vector3};
use sim_fem::{ElementDesc, FemError, FemSystem, RotationSourceDesc};
use sim_lattice::{Lattice, NodeId};

use crate::options::SimOptions;

type V3 = Vector3<f64>;

/// One block of `2^level` cubes per axis with its spanning tet (= shared source of the
/// same index).
#[derive(Clone, Debug)]
struct Block {
    nodes: [usize; 4],
    dm_inv: Matrix3<f64>,
    /// Enclosing block one level up, if it exists.
    parent: Option<usize>,
    /// Face neighbours at the same level (−x, +x, −y, +y, −z, +z).
    neighbours: [Option<usize>; 6],
}

/// What one sharing update did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct SharingUpdate {
    /// Elements using a block rotation.
    pub shared_elements: usize,
    /// Blocks whose neighbour test ran.
    pub blocks_tested: usize,
}

/// The sharing state of one FEM system: the block hierarchy and which element sits in
/// which cube.
#[derive(Clone, Debug, Default)]
pub(crate) struct RotationSharing {
    /// `‖R_m − R_n‖²_F` threshold; `None`: sharing off.
    threshold_sq: Option<f64>,
    /// Stricter threshold (θ_tol / 2) for a block whose leaves did not share a rotation
    /// in the previous update to start sharing again (see [`RotationSharing::update`]).
    enter_threshold_sq: f64,
    /// No update since the hierarchy was (re)built: every block is tested at θ_tol (a
    /// rebuild after a topology change must not look like a block that stopped sharing).
    fresh: bool,
    /// Blocks, finest level first (so coarser blocks come later; the top-down pass walks
    /// the array backwards).
    blocks: Vec<Block>,
    /// Level-0 block (the cube) of each element, in `FemDesc::elements` order.
    element_block: Vec<usize>,
    /// Scratch: block → assigned source of the last update.
    assigned: Vec<Option<usize>>,
    /// Per-element assignment of the last update (`None`: own rotation).
    assignment: Vec<Option<usize>>,
}

impl RotationSharing {
    pub(crate) fn new(angle_deg: Option<f64>) -> Self {
        RotationSharing {
            threshold_sq: angle_deg
                .filter(|a| *a > 0.0)
                .map(|a| sim_fem::rotation_threshold_sq(a.to_radians())),
            enter_threshold_sq: angle_deg.map_or(0.0, |a| {
                sim_fem::rotation_threshold_sq(0.5 * a.to_radians())
            }),
            ..Default::default()
        }
    }

    /// Builds the block hierarchy for the current leaves and returns the shared rotation
    /// sources (the blocks) for [`sim_fem::FemDesc::rotation_sources`]. Elements keep
    /// their own rotation until [`RotationSharing::update`] assigns them.
    pub(crate) fn sources(
        &mut self,
        lattice: &Lattice,
        elements: &mut [ElementDesc],
    ) -> Vec<RotationSourceDesc> {
        self.blocks.clear();
        self.element_block.clear();
        self.assigned.clear();
        self.assignment.clear();
        for e in elements.iter_mut() {
            e.rotation_source = None;
        }
        if self.threshold_sq.is_none() {
            return Vec::new();
        }
        let upc = lattice.units_per_cell();
        let by_grid: HashMap<[i64; 3], NodeId> =
            lattice.nodes().map(|n| (lattice.node_grid(n), n)).collect();
        // Cube of every element: the min corner of its nodes (leaves lie inside their
        // root cube).
        let element_cube: Vec<[i32; 3]> = elements
            .iter()
            .map(|e| {
                let mut lo = [i64::MAX; 3];
                for &n in &e.nodes {
                    let g = lattice.node_grid(NodeId(n as u32));
                    for k in 0..3 {
                        lo[k] = lo[k].min(g[k]);
                    }
                }
                lo.map(|v| v.div_euclid(upc) as i32)
            })
            .collect();
        let cube_set: HashSet<[i32; 3]> = lattice.cells().iter().copied().collect();
        let cell = lattice.params().cell;
        let origin = lattice.params().origin;
        // Full blocks per level: level 0 = the cubes; a block at level k+1 is full when
        // its 8 sub-blocks at level k are.
        let mut index: HashMap<(u8, [i32; 3]), usize> = HashMap::new();
        let mut level_coords: Vec<[i32; 3]> = {
            let mut c: Vec<[i32; 3]> = cube_set.iter().copied().collect();
            c.sort_unstable();
            c
        };
        let mut level = 0u8;
        while !level_coords.is_empty() {
            let s = 1i64 << level;
            let mut made = 0usize;
            for &coord in &level_coords {
                let c0 = coord.map(|v| i64::from(v) * s);
                let corners = [
                    [c0[0], c0[1], c0[2]],
                    [c0[0] + s, c0[1], c0[2]],
                    [c0[0] + s, c0[1] + s, c0[2]],
                    [c0[0] + s, c0[1] + s, c0[2] + s],
                ];
                let ids: Option<Vec<NodeId>> = corners
                    .iter()
                    .map(|c| by_grid.get(&c.map(|v| v * upc)).copied())
                    .collect();
                let Some(ids) = ids else { continue };
                let rest: Vec<V3> = corners
                    .iter()
                    .map(|c| origin + V3::from_fn(|k, _| c[k] as f64 * cell))
                    .collect();
                let dm = Matrix3::from_columns(&[
                    rest[1] - rest[0],
                    rest[2] - rest[0],
                    rest[3] - rest[0],
                ]);
                let Some(dm_inv) = dm.try_inverse() else {
                    continue;
                };
                index.insert((level, coord), self.blocks.len());
                self.blocks.push(Block {
                    nodes: [ids[0], ids[1], ids[2], ids[3]].map(|n| n.0 as usize),
                    dm_inv,
                    parent: None,
                    neighbours: [None; 6],
                });
                made += 1;
            }
            // Coarser blocks would span the whole organ; a level with a handful of blocks
            // is the top (their neighbour test still needs a neighbour).
            if made <= 8 || level >= 12 {
                break;
            }
            // Candidate parents: coordinates all of whose 8 children exist at this level.
            let mut parents: Vec<[i32; 3]> =
                level_coords.iter().map(|c| c.map(|v| v >> 1)).collect();
            parents.sort_unstable();
            parents.dedup();
            parents.retain(|p| {
                (0..8).all(|k| {
                    let child = [
                        2 * p[0] + (k & 1),
                        2 * p[1] + ((k >> 1) & 1),
                        2 * p[2] + ((k >> 2) & 1),
                    ];
                    index.contains_key(&(level, child))
                })
            });
            level_coords = parents;
            level += 1;
        }
        // Links: parents and neighbours.
        let keys: Vec<((u8, [i32; 3]), usize)> = index.iter().map(|(k, v)| (*k, *v)).collect();
        for ((lvl, coord), bi) in keys {
            self.blocks[bi].parent = index.get(&(lvl + 1, coord.map(|v| v >> 1))).copied();
            for axis in 0..3 {
                for (side, d) in [-1, 1].into_iter().enumerate() {
                    let mut c = coord;
                    c[axis] += d;
                    self.blocks[bi].neighbours[2 * axis + side] = index.get(&(lvl, c)).copied();
                }
            }
        }
        self.element_block = element_cube.iter().map(|c| index[&(0, *c)]).collect();
        self.assigned = vec![None; self.blocks.len()];
        self.fresh = true;
        self.assignment = vec![None; elements.len()];
        self.blocks
            .iter()
            .map(|b| RotationSourceDesc {
                nodes: b.nodes,
                rest_inverse_edges: Some(b.dm_inv),
            })
            .collect()
    }

    /// Runs the neighbour test from the coarsest level down (extracting block rotations on
    /// demand through the FEM system) and hands the per-element assignment to the FEM
    /// system. `None` when sharing is off or the model has no rotations.
    pub(crate) fn update(
        &mut self,
        fem: &mut FemSystem,
        x: &[V3],
        options: &SimOptions,
    ) -> Result<Option<SharingUpdate>, FemError> {
        let Some(thr) = self.threshold_sq else {
            return Ok(None);
        };
        if options.step.model != sim_fem::Model::Corotational || self.blocks.is_empty() {
            return Ok(None);
        }
        let mut out = SharingUpdate::default();
        let polar = options.step.polar;
        let rest = options.step.rest_threshold;
        // Hysteresis: leaves keep their block's rotation while the test holds at θ_tol, but
        // a block whose leaves extracted their own rotations last time starts sharing only
        // when its neighbours agree within θ_tol / 2. Without it, a block whose neighbour
        // differences sit at the threshold (a tangled or inverted region at rest) switches
        // between shared and own rotations every step, and each switch changes the elastic
        // forces discontinuously: the body never comes to rest (`cosurg bench stress`).
        let was_shared: Vec<bool> = self
            .assigned
            .iter()
            .map(|a| self.fresh || a.is_some())
            .collect();
        self.fresh = false;
        // A block holding an inverted element never shares: an inverted leaf's elastic
        // force and energy under a foreign rotation differ wildly from those under its own
        // (inversion-aware) one, and switching between the two as the block passes and
        // fails the test injected tens of J per switch into a pull through inversion.
        // Blocks are stored finest first with parents later, so one forward pass
        // propagates the flag upwards.
        let mut inverted = vec![false; self.blocks.len()];
        for (ei, &b) in self.element_block.iter().enumerate() {
            if !inverted[b] && fem.element_inverted(ei, x) {
                inverted[b] = true;
            }
        }
        for bi in 0..self.blocks.len() {
            if inverted[bi]
                && let Some(p) = self.blocks[bi].parent
            {
                inverted[p] = true;
            }
        }
        // Blocks are stored finest level first: walk backwards = coarsest first, so a
        // block's parent is decided before the block.
        for bi in (0..self.blocks.len()).rev() {
            let b = &self.blocks[bi];
            if let Some(p) = b.parent
                && let Some(src) = self.assigned[p]
            {
                self.assigned[bi] = Some(src);
                continue;
            }
            out.blocks_tested += 1;
            let neighbours = b.neighbours;
            let mut coherent = !inverted[bi] && neighbours.iter().any(Option::is_some);
            if coherent {
                let rm = fem.shared_source_rotation(bi, x, &polar, rest);
                let limit = if was_shared[bi] {
                    thr
                } else {
                    self.enter_threshold_sq
                };
                for n in neighbours.into_iter().flatten() {
                    let rn = fem.shared_source_rotation(n, x, &polar, rest);
                    if (rm - rn).norm_squared() >= limit {
                        coherent = false;
                        break;
                    }
                }
            }
            self.assigned[bi] = coherent.then_some(bi);
        }
        for (a, &b) in self.assignment.iter_mut().zip(&self.element_block) {
            *a = self.assigned[b];
        }
        out.shared_elements = self.assignment.iter().filter(|a| a.is_some()).count();
        fem.set_rotation_assignment(&self.assignment)?;
        Ok(Some(out))
    }
}
