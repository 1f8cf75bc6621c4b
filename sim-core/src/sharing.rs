//! Hierarchical rotation sharing (DESIGN §1(a), speed-up 1).
//!
//! Rotations of descendants are close to their ancestor's. Above the root cubes the
//! lattice continues as a hierarchy of blocks of `2^k` cubes (a block of 8 half-size
//! cubes is exactly what three bisection levels make of one cube, so this is the same
//! diamond hierarchy, coarser). Each block's rotation is extracted from one Kuhn tet
//! spanning the block: corners `c`, `c + s x̂`, `c + s(x̂ + ŷ)`, `c + s(x̂ + ŷ + ẑ)`, all of
//! them lattice nodes.
//!
//! Each step, starting at the coarsest blocks: a block whose rotation `R_m` agrees with
//! every existing face-neighbour block's `R_n` at the same level,
//! `‖R_m − R_n‖²_F < 4(1 − cos θ_tol)`, gives its rotation to every leaf inside it;
//! otherwise the test descends to its eight sub-blocks, down to single cubes. Leaves of a
//! cube that fails the test extract their own rotation. θ_tol = 0 disables sharing.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};
use sim_fem::{ElementDesc, FemSystem, RotationExtractor, RotationSourceDesc, WarmStart};
use sim_lattice::{Lattice, NodeId};

use crate::options::SimOptions;

type V3 = Vector3<f64>;

/// One block of `2^level` cubes per axis with its spanning tet.
#[derive(Clone, Debug)]
struct Block {
    /// Block coordinates at its level (cube index >> level).
    coord: [i32; 3],
    level: u8,
    nodes: [usize; 4],
    dm_inv: Matrix3<f64>,
    rotation: Matrix3<f64>,
    valid: bool,
}

/// The sharing state of one FEM system: blocks per level and which element sits in
/// which cube.
#[derive(Clone, Debug, Default)]
pub(crate) struct RotationSharing {
    /// `‖R_m − R_n‖²_F` threshold; `None`: sharing off.
    threshold_sq: Option<f64>,
    /// Blocks by (level, coord) → index into `blocks`.
    index: HashMap<(u8, [i32; 3]), usize>,
    blocks: Vec<Block>,
    /// Cube of each element (index into `FemDesc::elements` order).
    element_cube: Vec<[i32; 3]>,
    coarsest: u8,
    /// Per-element assignment of the last update (`None`: own rotation).
    assignment: Vec<Option<usize>>,
}

impl RotationSharing {
    pub(crate) fn new(angle_deg: Option<f64>) -> Self {
        RotationSharing {
            threshold_sq: angle_deg
                .filter(|a| *a > 0.0)
                .map(|a| sim_fem::rotation_threshold_sq(a.to_radians())),
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
        self.index.clear();
        self.blocks.clear();
        self.element_cube.clear();
        self.assignment.clear();
        if self.threshold_sq.is_none() {
            return Vec::new();
        }
        let upc = lattice.units_per_cell();
        let by_grid: HashMap<[i64; 3], NodeId> =
            lattice.nodes().map(|n| (lattice.node_grid(n), n)).collect();
        for &t in lattice.leaves() {
            let nodes = lattice.tet_nodes(t);
            let mut lo = [i64::MAX; 3];
            for n in nodes {
                let g = lattice.node_grid(n);
                for k in 0..3 {
                    lo[k] = lo[k].min(g[k]);
                }
            }
            self.element_cube.push(lo.map(|v| v.div_euclid(upc) as i32));
        }
        let cell = lattice.params().cell;
        let origin = lattice.params().origin;
        let mut level = 0u8;
        loop {
            let mut coords: Vec<[i32; 3]> = self
                .element_cube
                .iter()
                .map(|c| c.map(|v| v >> level))
                .collect();
            coords.sort_unstable();
            coords.dedup();
            let mut made = 0;
            for coord in coords {
                let s = 1i64 << level;
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
                self.index.insert((level, coord), self.blocks.len());
                self.blocks.push(Block {
                    coord,
                    level,
                    nodes: [ids[0], ids[1], ids[2], ids[3]].map(|n| n.0 as usize),
                    dm_inv,
                    rotation: Matrix3::identity(),
                    valid: false,
                });
                made += 1;
            }
            // Stop when a level has at most a handful of blocks: coarser blocks would
            // span the whole organ and never pass the neighbour test anyway.
            if made <= 8 || level >= 10 {
                self.coarsest = level;
                break;
            }
            level += 1;
        }
        self.assignment = vec![None; elements.len()];
        for e in elements.iter_mut() {
            e.rotation_source = None;
        }
        self.blocks
            .iter()
            .map(|b| RotationSourceDesc {
                nodes: b.nodes,
                rest_inverse_edges: Some(b.dm_inv),
            })
            .collect()
    }

    /// Extracts block rotations, runs the neighbour test from the coarsest level down and
    /// hands the per-element assignment to the FEM system. Returns the number of
    /// elements sharing a block rotation, or `None` when sharing is off.
    pub(crate) fn update(
        &mut self,
        _lattice: &Lattice,
        fem: &mut FemSystem,
        x: &[V3],
        options: &SimOptions,
    ) -> Option<usize> {
        let thr = self.threshold_sq?;
        if self.blocks.is_empty() {
            return Some(0);
        }
        for b in &mut self.blocks {
            let xs = b.nodes.map(|n| x[n]);
            let f =
                Matrix3::from_columns(&[xs[1] - xs[0], xs[2] - xs[0], xs[3] - xs[0]]) * b.dm_inv;
            let warm = WarmStart {
                rotation: b.valid.then_some(b.rotation),
                sigma_bounds: None,
            };
            b.rotation = options.polar.extract(&f, Some(&warm)).rotation;
            b.valid = true;
        }
        // Coherent blocks: those agreeing with all face neighbours at their level.
        let coherent: Vec<bool> = self
            .blocks
            .iter()
            .map(|b| {
                let mut ok = true;
                for axis in 0..3 {
                    for d in [-1, 1] {
                        let mut c = b.coord;
                        c[axis] += d;
                        if let Some(&j) = self.index.get(&(b.level, c)) {
                            let diff = (b.rotation - self.blocks[j].rotation).norm_squared();
                            ok &= diff < thr;
                        }
                    }
                }
                ok
            })
            .collect();
        let mut shared = 0;
        for (e, cube) in self.element_cube.iter().enumerate() {
            let mut chosen = None;
            for level in (0..=self.coarsest).rev() {
                let coord = cube.map(|v| v >> level);
                if let Some(&j) = self.index.get(&(level, coord))
                    && coherent[j]
                {
                    chosen = Some(j);
                    break;
                }
            }
            shared += chosen.is_some() as usize;
            self.assignment[e] = chosen;
        }
        // TODO(lead): hand the assignment to the FEM system once it can switch sources.
        let _ = fem;
        Some(shared)
    }
}
