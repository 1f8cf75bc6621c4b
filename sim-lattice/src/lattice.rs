//! The tet forest: construction, conforming bisection refine/coarsen, queries.
//!
//! **Bisection.** A tet stores its vertices in Maubach order `(x_0, x_1, x_2, x_3)` with tag
//! `k = 3 − level mod 3`; its refinement edge is `x_0 – x_k` and its children are
//! `(x_0..x_{k−1}, z, x_{k+1}..)` (heap `2i`) and `(x_1..x_k, z, x_{k+1}..)` (heap `2i+1`),
//! `z` the edge midpoint. A root tet is the path from the cube's all-even corner to its
//! all-odd corner. Because neighbouring cubes are mirror images, neighbouring root tets are
//! reflections of each other with matching vertex order, which is Maubach's condition for
//! the bisection to stay conforming and the tets to cycle through three similarity types.
//!
//! **Layout.** Tet records live in one flat vector; a split allocates the two children as an
//! adjacent pair (recycled through a free list), so a [`TetId`] is found by walking
//! `level` child links from its root record. Leaves are kept in a dense vector with
//! back-pointers for O(1) removal. Nodes are a slot vector with a free list; a diamond
//! centre node remembers its split edge and one tet of its diamond, so diamonds are keyed
//! by their centre vertex without a hash map.
//!
//! **Adjacency without tables.** The tet across a face is found by exact point location of
//! the face centroid, symbolically pushed off the face away from the opposite vertex: cell
//! lookup in a dense index, the root containing the point, then one orientation test per
//! level down the tree. The same walk, stopped at a given level, moves around an edge
//! through the tets of a diamond; refine and coarsen need nothing else, so there is no
//! face or edge hash to keep up to date.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};
use tracing::debug;

use crate::geom::{AXES, Grid, add, midpoint, orient, orient_perturbed, scale, sub};
use crate::{LatticeError, LatticeParams, NodeId, ShapeKey, TetId, TetType, TopologyEvent};

pub(crate) const NONE: u32 = u32::MAX;

/// A diamond has at most 8 tets; a longer walk around an edge means a broken invariant.
const MAX_RING: usize = 16;

/// Largest number of cells in the bounding box of the root cells (dense cell index).
const MAX_CELL_BOX: usize = 1 << 26;

/// The six axis permutations; the Kuhn tet `p` of a cube walks from the even corner along
/// axis `PERMS[p][0]`, then `PERMS[p][1]`, then `PERMS[p][2]`.
const PERMS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// Maubach tag of a tet at `level`: its refinement edge is `x_0 – x_tag`.
#[inline]
pub(crate) fn tag(level: u8) -> usize {
    3 - usize::from(level % 3)
}

/// Children of the bisection-ordered tet `x` with tag `k` split at midpoint `z` of
/// `x_0 – x_k` (Maubach 1995): `(x_0..x_{k−1}, z, x_{k+1}..)` and `(x_1..x_k, z, x_{k+1}..)`.
#[inline]
pub(crate) fn child_nodes<T: Copy>(x: [T; 4], k: usize, z: T) -> [[T; 4]; 2] {
    let mut c1 = x;
    c1[k] = z;
    let mut c2 = x;
    c2[..k].copy_from_slice(&x[1..=k]);
    c2[k] = z;
    [c1, c2]
}

/// One tet of the forest. Records of live tets never move; a split allocates its two
/// children as an adjacent pair (reused through a free list after a merge).
#[derive(Clone, Debug)]
pub(crate) struct TetRec {
    /// Vertices in bisection (Maubach) order; the refinement edge is `nodes[0]–nodes[tag]`.
    pub nodes: [NodeId; 4],
    /// First of the two child records, `NONE` for a leaf.
    pub first_child: u32,
    /// Position in `Lattice::leaves`, `NONE` unless a leaf.
    pub leaf_slot: u32,
    pub id: TetId,
    pub level: u8,
    /// Whether the bisection order is positively oriented.
    pub positive: bool,
}

#[derive(Clone, Debug)]
struct NodeRec {
    grid: Grid,
    /// For a diamond centre: the split edge; `(NONE, NONE)` for a cube corner.
    edge: (NodeId, NodeId),
    /// For a diamond centre: the record of one split tet of the diamond.
    diamond: u32,
    alive: bool,
}

/// The adaptive Kuhn lattice: a forest of bisection trees over root cubes.
#[derive(Clone, Debug)]
pub struct Lattice {
    params: LatticeParams,
    /// Grid units per cell (a power of two).
    units: i64,
    cells: Vec<[i32; 3]>,
    cell_min: [i32; 3],
    cell_dims: [usize; 3],
    /// Dense index over the cells' bounding box: cell slot or `NONE`.
    cell_slots: Vec<u32>,
    pub(crate) tets: Vec<TetRec>,
    free_pairs: Vec<u32>,
    leaves: Vec<TetId>,
    leaf_recs: Vec<u32>,
    nodes: Vec<NodeRec>,
    free_nodes: Vec<u32>,
    live_nodes: usize,
    generation: u64,
}

/// Iterator over live node ids.
pub struct NodeIter<'a> {
    nodes: std::iter::Enumerate<std::slice::Iter<'a, NodeRec>>,
}

impl Iterator for NodeIter<'_> {
    type Item = NodeId;
    fn next(&mut self) -> Option<NodeId> {
        self.nodes
            .by_ref()
            .find(|(_, n)| n.alive)
            .map(|(i, _)| NodeId(i as u32))
    }
}

impl Lattice {
    /// Lattice of the given cube cells (duplicates ignored), six Kuhn root tets per cell.
    /// Root `6 s + p` is Kuhn tet `p` of the `s`-th distinct cell.
    pub fn from_cells(params: LatticeParams, cells: &[[i32; 3]]) -> Result<Self, LatticeError> {
        if !(params.cell.is_finite() && params.cell > 0.0) {
            return Err(LatticeError::InvalidParams(format!(
                "cell size must be positive and finite, got {}",
                params.cell
            )));
        }
        if !params.origin.iter().all(|v| v.is_finite()) {
            return Err(LatticeError::InvalidParams("origin is not finite".into()));
        }
        if params.max_depth > LatticeParams::MAX_DEPTH_LIMIT {
            return Err(LatticeError::InvalidParams(format!(
                "max_depth {} exceeds the limit {}",
                params.max_depth,
                LatticeParams::MAX_DEPTH_LIMIT
            )));
        }
        let mut seen = std::collections::HashSet::with_capacity(cells.len());
        let cells: Vec<[i32; 3]> = cells.iter().copied().filter(|c| seen.insert(*c)).collect();
        if cells.is_empty() {
            return Err(LatticeError::Empty("no cells given".into()));
        }
        let mut lo = cells[0];
        let mut hi = cells[0];
        for c in &cells {
            for i in 0..3 {
                lo[i] = lo[i].min(c[i]);
                hi[i] = hi[i].max(c[i]);
            }
        }
        let dims = [0, 1, 2].map(|i| (i64::from(hi[i]) - i64::from(lo[i]) + 1) as usize);
        let boxed = dims
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .filter(|&n| n <= MAX_CELL_BOX)
            .ok_or_else(|| {
                LatticeError::InvalidParams(format!(
                    "cells span a {dims:?} box, more than {MAX_CELL_BOX} cells"
                ))
            })?;
        // Splits at level l create points on the grid of spacing cell / 2^(l/3 + 1).
        let units = 1i64 << (params.max_depth / 3 + 1);

        let mut lattice = Lattice {
            params,
            units,
            cells: Vec::new(),
            cell_min: lo,
            cell_dims: dims,
            cell_slots: vec![NONE; boxed],
            tets: Vec::with_capacity(cells.len() * 6),
            free_pairs: Vec::new(),
            leaves: Vec::with_capacity(cells.len() * 6),
            leaf_recs: Vec::with_capacity(cells.len() * 6),
            nodes: Vec::new(),
            free_nodes: Vec::new(),
            live_nodes: 0,
            generation: 0,
        };
        let mut corner_nodes: HashMap<Grid, NodeId> = HashMap::with_capacity(cells.len() * 2);
        for (slot, c) in cells.iter().enumerate() {
            let idx = lattice
                .cell_box_index(c.map(i64::from))
                .expect("cell in its own box");
            lattice.cell_slots[idx] = slot as u32;
            // The diagonal runs from the all-even corner to the all-odd corner: neighbouring
            // cubes are mirror images, the root layout of one diamond hierarchy.
            let even = c.map(|v| i64::from(v) + i64::from(v.rem_euclid(2)));
            let odd = c.map(|v| i64::from(v) + 1 - i64::from(v.rem_euclid(2)));
            let step = [0, 1, 2].map(|i| odd[i] - even[i]);
            for (p, perm) in PERMS.iter().enumerate() {
                let x0 = scale(even, units);
                let mut x1 = x0;
                x1[perm[0]] += step[perm[0]] * units;
                let mut x2 = x1;
                x2[perm[1]] += step[perm[1]] * units;
                let x3 = scale(odd, units);
                let nodes = [x0, x1, x2, x3].map(|g| {
                    *corner_nodes.entry(g).or_insert_with(|| {
                        lattice.alloc_node(g, (NodeId(NONE), NodeId(NONE)), NONE)
                    })
                });
                let id = TetId {
                    root: (slot * 6 + p) as u32,
                    heap: 1,
                };
                let rec = TetRec {
                    nodes,
                    first_child: NONE,
                    leaf_slot: NONE,
                    id,
                    level: 0,
                    positive: orient(x0, x1, x2, x3) > 0,
                };
                lattice.tets.push(rec);
                lattice.push_leaf(id.root);
            }
        }
        lattice.cells = cells;
        debug!(
            cells = lattice.cells.len(),
            roots = lattice.root_count(),
            nodes = lattice.live_nodes,
            units_per_cell = units,
            "built Kuhn lattice"
        );
        Ok(lattice)
    }

    /// Lattice of the cubes that overlap the interior of a closed triangle surface, plus
    /// every cube that contains a surface vertex or is crossed by a triangle (separating
    /// axis test). Inside/outside is decided by ray parity along +x, the majority of three
    /// rays jittered off each cell's centre line; the surface should be closed.
    pub fn from_surface(
        params: LatticeParams,
        vertices: &[Vector3<f64>],
        triangles: &[[u32; 3]],
    ) -> Result<Self, LatticeError> {
        let cells = crate::surface::cells_covering(&params, vertices, triangles)?;
        if cells.is_empty() {
            return Err(LatticeError::Empty(
                "the surface mesh encloses no cube cell".into(),
            ));
        }
        Self::from_cells(params, &cells)
    }

    pub fn params(&self) -> &LatticeParams {
        &self.params
    }

    /// Integer grid units per cube edge (a power of two).
    pub fn units_per_cell(&self) -> i64 {
        self.units
    }

    /// The distinct root cells, in root order (cell `s` holds roots `6s .. 6s + 6`).
    pub fn cells(&self) -> &[[i32; 3]] {
        &self.cells
    }

    pub fn root_count(&self) -> u32 {
        (self.cells.len() * 6) as u32
    }

    /// Leaf tets. The order is stable between topology changes and changes arbitrarily
    /// (swap-remove) on refine/coarsen.
    pub fn leaves(&self) -> &[TetId] {
        &self.leaves
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    pub fn node_count(&self) -> usize {
        self.live_nodes
    }

    /// One past the largest node id ever live: size per-node arrays by this.
    pub fn node_capacity(&self) -> usize {
        self.nodes.len()
    }

    /// Incremented by every split and merge; lets followers (e.g. [`crate::Embedding`])
    /// skip work when nothing changed.
    pub fn topology_generation(&self) -> u64 {
        self.generation
    }

    pub fn nodes(&self) -> NodeIter<'_> {
        NodeIter {
            nodes: self.nodes.iter().enumerate(),
        }
    }

    pub fn node_alive(&self, n: NodeId) -> bool {
        self.nodes.get(n.0 as usize).is_some_and(|r| r.alive)
    }

    /// Rest position (m).
    ///
    /// # Panics
    /// If `n` was never allocated.
    pub fn node_rest(&self, n: NodeId) -> Vector3<f64> {
        let g = self.nodes[n.0 as usize].grid;
        let s = self.params.cell / self.units as f64;
        self.params.origin + Vector3::new(g[0] as f64, g[1] as f64, g[2] as f64) * s
    }

    /// Rest position in integer grid units (`units_per_cell` per cube edge).
    pub fn node_grid(&self, n: NodeId) -> [i64; 3] {
        self.nodes[n.0 as usize].grid
    }

    /// For a diamond-centre node, the edge whose midpoint it is; `None` for cube corners.
    pub fn node_parent_edge(&self, n: NodeId) -> Option<(NodeId, NodeId)> {
        let r = self.nodes.get(n.0 as usize)?;
        (r.alive && r.edge.0.0 != NONE).then_some(r.edge)
    }

    /// Record index of `t`, walking down from its root (O(level)).
    #[inline]
    pub(crate) fn rec_of(&self, t: TetId) -> Option<u32> {
        if t.root >= self.root_count() || t.heap == 0 {
            return None;
        }
        let level = t.level();
        let mut r = t.root;
        for bit in (0..level).rev() {
            let fc = self.tets[r as usize].first_child;
            if fc == NONE {
                return None;
            }
            r = fc + ((t.heap >> bit) & 1);
        }
        Some(r)
    }

    fn rec(&self, t: TetId) -> &TetRec {
        match self.rec_of(t) {
            Some(r) => &self.tets[r as usize],
            None => panic!("tet {t:?} does not exist"),
        }
    }

    pub fn tet_exists(&self, t: TetId) -> bool {
        self.rec_of(t).is_some()
    }

    pub fn is_leaf(&self, t: TetId) -> bool {
        self.rec_of(t)
            .is_some_and(|r| self.tets[r as usize].first_child == NONE)
    }

    pub fn tet_level(&self, t: TetId) -> u8 {
        t.level()
    }

    pub fn tet_type(&self, t: TetId) -> TetType {
        match t.level() % 3 {
            0 => TetType::Type0,
            1 => TetType::Type1,
            _ => TetType::Type2,
        }
    }

    /// Vertices of an existing tet (leaf or ancestor), positively oriented: the rest edge
    /// matrix `[x1 − x0, x2 − x0, x3 − x0]` has positive determinant. This is the
    /// bisection order with the last two vertices swapped when that order is negative.
    ///
    /// # Panics
    /// If `t` does not exist.
    pub fn tet_nodes(&self, t: TetId) -> [NodeId; 4] {
        oriented(self.rec(t))
    }

    /// Vertices in bisection (Maubach) order: the refinement edge is `[0]–[3]` for TYPE0,
    /// `[0]–[2]` for TYPE1, `[0]–[1]` for TYPE2. Orientation alternates.
    pub fn tet_nodes_bisection_order(&self, t: TetId) -> [NodeId; 4] {
        self.rec(t).nodes
    }

    /// [`Lattice::tet_nodes`] of `leaves()[i]` without the walk from the root.
    pub fn leaf_tet_nodes(&self, i: usize) -> [NodeId; 4] {
        oriented(&self.tets[self.leaf_recs[i] as usize])
    }

    /// The refinement edge of `t` (the edge its split bisects).
    pub fn refinement_edge(&self, t: TetId) -> (NodeId, NodeId) {
        let r = self.rec(t);
        (r.nodes[0], r.nodes[tag(r.level)])
    }

    fn h_units(&self, level: u8) -> i64 {
        self.units >> (level / 3 + 1)
    }

    pub fn tet_shape(&self, t: TetId) -> ShapeKey {
        let r = self.rec(t);
        let n = oriented(r);
        let h = self.h_units(r.level);
        let g0 = self.grid(n[0]);
        let e = |j: usize| sub(self.grid(n[j]), g0).map(|v| (v / h) as i8);
        ShapeKey {
            tet_type: self.tet_type(t),
            edges: [e(1), e(2), e(3)],
        }
    }

    /// Length scale `h_e` (m): rest edges are `h_e` times the template edges of
    /// [`Lattice::tet_shape`]. Equals half the edge of the cube of the tet's bisection
    /// cycle (`cell / 2^(level/3 + 1)`).
    pub fn tet_scale(&self, t: TetId) -> f64 {
        self.h_units(t.level()) as f64 * self.params.cell / self.units as f64
    }

    /// Six times the rest volume in cubic grid units, exact.
    pub fn tet_volume6_grid(&self, t: TetId) -> i128 {
        let n = self.tet_nodes(t);
        orient(
            self.grid(n[0]),
            self.grid(n[1]),
            self.grid(n[2]),
            self.grid(n[3]),
        )
    }

    /// Rest volume (m³).
    pub fn tet_rest_volume(&self, t: TetId) -> f64 {
        let s = self.params.cell / self.units as f64;
        self.tet_volume6_grid(t) as f64 * s * s * s / 6.0
    }

    /// Parent id (`None` for a root); pure id arithmetic.
    pub fn parent(&self, t: TetId) -> Option<TetId> {
        (t.heap > 1).then_some(TetId {
            root: t.root,
            heap: t.heap / 2,
        })
    }

    /// Children of an existing split tet.
    pub fn children(&self, t: TetId) -> Option<[TetId; 2]> {
        let r = self.rec_of(t)?;
        (self.tets[r as usize].first_child != NONE).then_some([
            TetId {
                root: t.root,
                heap: 2 * t.heap,
            },
            TetId {
                root: t.root,
                heap: 2 * t.heap + 1,
            },
        ])
    }

    /// Leaf neighbours across the faces of `t`: entry `j` is across the face opposite
    /// `tet_nodes(t)[j]`, `None` on the domain boundary. In a conforming mesh a leaf has
    /// exactly one leaf neighbour per interior face. For a split `t`, entry `j` is the leaf
    /// just outside the centroid of face `j`.
    ///
    /// # Panics
    /// If `t` does not exist.
    pub fn face_neighbors(&self, t: TetId) -> [Option<TetId>; 4] {
        let n = self.tet_nodes(t);
        [0, 1, 2, 3].map(|j| {
            let face = [n[(j + 1) % 4], n[(j + 2) % 4], n[(j + 3) % 4]];
            self.neighbor_across(face, n[j], None)
                .map(|r| self.tets[r as usize].id)
        })
    }

    // ----------------------------------------------------------------------------------
    // Construction helpers

    #[inline]
    pub(crate) fn grid(&self, n: NodeId) -> Grid {
        self.nodes[n.0 as usize].grid
    }

    fn cell_box_index(&self, c: [i64; 3]) -> Option<usize> {
        let mut idx = 0usize;
        for i in (0..3).rev() {
            let d = c[i] - i64::from(self.cell_min[i]);
            if d < 0 || d >= self.cell_dims[i] as i64 {
                return None;
            }
            idx = idx * self.cell_dims[i] + d as usize;
        }
        Some(idx)
    }

    /// Slot of the cell with integer coordinates `c`, if it is part of the lattice.
    #[inline]
    pub(crate) fn cell_slot(&self, c: [i64; 3]) -> Option<u32> {
        let s = self.cell_slots[self.cell_box_index(c)?];
        (s != NONE).then_some(s)
    }

    fn alloc_node(&mut self, grid: Grid, edge: (NodeId, NodeId), diamond: u32) -> NodeId {
        let rec = NodeRec {
            grid,
            edge,
            diamond,
            alive: true,
        };
        self.live_nodes += 1;
        match self.free_nodes.pop() {
            Some(i) => {
                self.nodes[i as usize] = rec;
                NodeId(i)
            }
            None => {
                self.nodes.push(rec);
                NodeId(self.nodes.len() as u32 - 1)
            }
        }
    }

    fn free_node(&mut self, n: NodeId) {
        let r = &mut self.nodes[n.0 as usize];
        debug_assert!(r.alive);
        r.alive = false;
        r.edge = (NodeId(NONE), NodeId(NONE));
        r.diamond = NONE;
        self.free_nodes.push(n.0);
        self.live_nodes -= 1;
    }

    fn push_leaf(&mut self, r: u32) {
        self.tets[r as usize].leaf_slot = self.leaves.len() as u32;
        self.leaves.push(self.tets[r as usize].id);
        self.leaf_recs.push(r);
    }

    fn remove_leaf(&mut self, r: u32) {
        let slot = self.tets[r as usize].leaf_slot as usize;
        self.leaves.swap_remove(slot);
        self.leaf_recs.swap_remove(slot);
        if slot < self.leaf_recs.len() {
            let moved = self.leaf_recs[slot];
            self.tets[moved as usize].leaf_slot = slot as u32;
        }
        self.tets[r as usize].leaf_slot = NONE;
    }

    // ----------------------------------------------------------------------------------
    // Exact point location

    /// The tet containing the symbolically perturbed point `p3 + ε dirs[0] + ε² dirs[1] …`,
    /// where `p3` is in units of 1/3 grid unit (so face centroids are exact). Descends to a
    /// leaf, or stops at `stop_level`.
    pub(crate) fn locate_perturbed(
        &self,
        p3: Grid,
        dirs: &[Grid],
        stop_level: Option<u8>,
    ) -> Option<u32> {
        let m = 3 * self.units;
        let mut cell = [0i64; 3];
        for i in 0..3 {
            cell[i] = p3[i].div_euclid(m);
            if p3[i].rem_euclid(m) == 0 {
                // On a cell boundary plane: the perturbation decides the side.
                let d = dirs.iter().map(|d| d[i]).find(|&v| v != 0).unwrap_or(0);
                if d < 0 {
                    cell[i] -= 1;
                }
            }
        }
        let slot = self.cell_slot(cell)?;
        let g3 = |n: NodeId| scale(self.grid(n), 3);
        let mut r = (0..6u32).map(|p| slot * 6 + p).find(|&r| {
            let x = self.tets[r as usize].nodes.map(g3);
            (0..4).all(|j| {
                let (a, b, c) = (x[(j + 1) % 4], x[(j + 2) % 4], x[(j + 3) % 4]);
                let inside = orient(a, b, c, x[j]).signum() as i32;
                orient_perturbed(a, b, c, p3, dirs) == inside
            })
        })?;
        loop {
            let rec = &self.tets[r as usize];
            if rec.first_child == NONE || stop_level.is_some_and(|s| rec.level >= s) {
                return Some(r);
            }
            let k = tag(rec.level);
            let x = rec.nodes.map(g3);
            let z = midpoint(x[0], x[k]);
            let (o1, o2) = others(k);
            let side_x0 = orient(z, x[o1], x[o2], x[0]).signum() as i32;
            let side_p = orient_perturbed(z, x[o1], x[o2], p3, dirs);
            r = rec.first_child + u32::from(side_p != side_x0);
        }
    }

    /// The tet across face `face` (opposite vertex `opposite`), at `stop_level` or a leaf.
    pub(crate) fn neighbor_across(
        &self,
        face: [NodeId; 3],
        opposite: NodeId,
        stop_level: Option<u8>,
    ) -> Option<u32> {
        let c3 = add(
            add(self.grid(face[0]), self.grid(face[1])),
            self.grid(face[2]),
        );
        let outward = sub(c3, scale(self.grid(opposite), 3));
        self.locate_perturbed(c3, &[outward, AXES[0], AXES[1], AXES[2]], stop_level)
    }

    /// Leaf containing the world point `p`, with weights paired with `tet_nodes(t)`.
    /// Points on shared faces go to either tet; points outside all cubes (beyond a
    /// rounding tolerance) give `None`.
    pub fn point_location(&self, p: &Vector3<f64>) -> Option<(TetId, [f64; 4])> {
        let (r, w) = self.locate_f64(p, 1e-12)?;
        let rec = &self.tets[r as usize];
        Some((rec.id, oriented_weights(rec, w)))
    }

    /// Rest position in (floating) grid units.
    pub(crate) fn to_grid_f64(&self, p: &Vector3<f64>) -> Vector3<f64> {
        (p - self.params.origin) * (self.units as f64 / self.params.cell)
    }

    /// Barycentric weights (bisection order) of grid-unit point `g` in record `r`.
    pub(crate) fn barycentric(&self, r: u32, g: &Vector3<f64>) -> [f64; 4] {
        let x = self.tets[r as usize].nodes.map(|n| {
            let v = self.grid(n);
            Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
        });
        let m = Matrix3::from_columns(&[x[1] - x[0], x[2] - x[0], x[3] - x[0]]);
        let l = m.try_inverse().expect("tets are never degenerate") * (g - x[0]);
        [1.0 - l.x - l.y - l.z, l.x, l.y, l.z]
    }

    /// Root-cell lookup then descent by the bisection weights; weights in bisection order.
    pub(crate) fn locate_f64(&self, p: &Vector3<f64>, tol: f64) -> Option<(u32, [f64; 4])> {
        let g = self.to_grid_f64(p);
        let u = self.units as f64;
        let home = [g.x, g.y, g.z].map(|v| (v / u).floor() as i64);
        let mut best: Option<(u32, [f64; 4], f64)> = None;
        let consider = |cell: [i64; 3], best: &mut Option<(u32, [f64; 4], f64)>| {
            if let Some(slot) = self.cell_slot(cell) {
                for r in slot * 6..slot * 6 + 6 {
                    let w = self.barycentric(r, &g);
                    let min = w.iter().copied().fold(f64::INFINITY, f64::min);
                    if best.as_ref().is_none_or(|b| min > b.2) {
                        *best = Some((r, w, min));
                    }
                }
            }
        };
        consider(home, &mut best);
        if best.as_ref().is_none_or(|b| b.2 < -tol) {
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if (dx, dy, dz) != (0, 0, 0) {
                            consider([home[0] + dx, home[1] + dy, home[2] + dz], &mut best);
                        }
                    }
                }
            }
        }
        let (r, w, min) = best?;
        (min >= -tol).then(|| self.descend_weights(r, w))
    }

    /// Descends from record `r` to the leaf holding the point with weights `w`.
    pub(crate) fn descend_weights(&self, mut r: u32, mut w: [f64; 4]) -> (u32, [f64; 4]) {
        loop {
            let rec = &self.tets[r as usize];
            if rec.first_child == NONE {
                return (r, w);
            }
            let (side, cw) = weights_to_child(w, tag(rec.level));
            w = cw;
            r = rec.first_child + side;
        }
    }

    /// Record index of `leaves()[i]`.
    pub(crate) fn leaf_rec(&self, i: usize) -> u32 {
        self.leaf_recs[i]
    }
}

/// The two vertex positions that are not on the refinement edge `0–k`.
#[inline]
fn others(k: usize) -> (usize, usize) {
    match k {
        1 => (2, 3),
        2 => (1, 3),
        _ => (1, 2),
    }
}

#[inline]
fn same_edge(a: (NodeId, NodeId), b: (NodeId, NodeId)) -> bool {
    a == b || (a.0 == b.1 && a.1 == b.0)
}

#[inline]
fn oriented(rec: &TetRec) -> [NodeId; 4] {
    let n = rec.nodes;
    if rec.positive {
        n
    } else {
        [n[0], n[1], n[3], n[2]]
    }
}

/// Weights in bisection order → weights paired with [`Lattice::tet_nodes`].
#[inline]
pub(crate) fn oriented_weights(rec: &TetRec, w: [f64; 4]) -> [f64; 4] {
    if rec.positive {
        w
    } else {
        [w[0], w[1], w[3], w[2]]
    }
}

/// Barycentric weights of a point in the child that holds it. With `x_k = 2z − x_0`,
/// child 0 (`x_k` replaced by `z`) holds the point when `λ_0 ≥ λ_k`.
#[inline]
pub(crate) fn weights_to_child(w: [f64; 4], k: usize) -> (u32, [f64; 4]) {
    if w[0] >= w[k] {
        let mut c = w;
        c[0] = w[0] - w[k];
        c[k] = 2.0 * w[k];
        (0, c)
    } else {
        // Child 1 is (x_1..x_k, z, x_{k+1}..) and x_0 = 2z − x_k.
        let mut c = w;
        c[..k - 1].copy_from_slice(&w[1..k]);
        c[k - 1] = w[k] - w[0];
        c[k] = 2.0 * w[0];
        (1, c)
    }
}

/// Inverse of [`weights_to_child`]: weights in the parent of a point given in child `side`.
#[inline]
pub(crate) fn weights_to_parent(c: [f64; 4], k: usize, side: u32) -> [f64; 4] {
    let mut w = c;
    if side == 0 {
        w[k] = 0.5 * c[k];
        w[0] = c[0] + 0.5 * c[k];
    } else {
        w[1..k].copy_from_slice(&c[..k - 1]);
        w[0] = 0.5 * c[k];
        w[k] = c[k - 1] + 0.5 * c[k];
    }
    w
}

mod bisection;
#[cfg(test)]
mod tests;
