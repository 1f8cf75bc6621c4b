//! Adaptive embedded tetrahedral lattice for cosurg.
//!
//! A body is covered by cubes of edge `cell` on a grid. Every cube holds six Kuhn
//! tetrahedra around its main diagonal; the diagonal runs from the cube's all-even corner
//! to its all-odd corner, so neighbouring cubes are mirror images and the whole lattice is
//! one diamond hierarchy (DESIGN §2½). Each root tet is the root of a binary tree of
//! newest-vertex (Maubach) bisections that cycles TYPE0 → TYPE1 → TYPE2 → TYPE0.
//!
//! * [`Lattice`] — the forest, conforming [`Lattice::refine`] / [`Lattice::coarsen`],
//!   exact integer point location and face neighbours.
//! * [`RegionState`] / [`RegionDelta`] — the split state of a set of root trees as bit
//!   sets over heap indices, their XOR, and [`Lattice::apply_state`].
//! * [`Embedding`] — points (surface vertices, tool samples) hosted by leaf tets with
//!   barycentric weights, kept exact across topology changes.
//!
//! All rest geometry lives on an integer dyadic grid: a cell is `2^k` grid units with `k`
//! chosen so that every bisection midpoint down to `max_depth` is an integer average.
//! Orientation and point-location predicates are therefore exact (`i128` determinants).

mod embedding;
mod geom;
mod lattice;
mod state;
mod surface;

pub use embedding::Embedding;
pub use lattice::{Lattice, NodeIter};
pub use state::{ApplyStats, RegionDelta, RegionState, StateDecodeError};

use nalgebra::Vector3;

/// Where the lattice sits in space and how deep it may refine.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LatticeParams {
    /// World position (m) of grid cell `[0, 0, 0]`'s minimum corner.
    pub origin: Vector3<f64>,
    /// Edge length of a root cube (m).
    pub cell: f64,
    /// Maximum bisection level of any tet (a root tet has level 0). At most
    /// [`LatticeParams::MAX_DEPTH_LIMIT`]; three levels halve the edge length.
    pub max_depth: u8,
}

impl LatticeParams {
    /// Heap indices are `u32`, so a tree can be at most 30 levels deep.
    pub const MAX_DEPTH_LIMIT: u8 = 30;
}

/// A lattice node (tet vertex). Ids of surviving nodes are stable across refine/coarsen;
/// size per-node arrays by [`Lattice::node_capacity`] and index them by `id.0 as usize`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeId(pub u32);

/// A tet in the forest: its root tet and its heap index in that root's binary tree
/// (root = 1, children of `i` are `2i` and `2i + 1`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TetId {
    pub root: u32,
    pub heap: u32,
}

impl TetId {
    /// Bisection level: 0 for a root tet.
    pub fn level(self) -> u8 {
        (31 - self.heap.max(1).leading_zeros()) as u8
    }
}

/// The three similarity classes of Kuhn-cube bisection; a tet of level `l` has type
/// `l mod 3`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TetType {
    /// The Kuhn tet: a path orthoscheme (three orthogonal edges in a path), 1/6 cube.
    Type0,
    /// A pair of orthogonal opposite edges; 1/12 cube.
    Type1,
    /// Trirectangular (three orthogonal edges at one vertex); 1/24 cube.
    Type2,
}

/// Shape of a tet up to translation and scale, in the node order of
/// [`Lattice::tet_nodes`]: the rest edge vectors `x_j − x_0` (j = 1, 2, 3) divided by
/// [`Lattice::tet_scale`] are exactly `edges[j − 1]`. Tets with equal keys share the
/// template stiffness `K_e = h_e (λ K_λ + μ K_μ)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ShapeKey {
    pub tet_type: TetType,
    pub edges: [[i8; 3]; 3],
}

impl ShapeKey {
    /// Template vertex positions (unit scale): `[0, e_1, e_2, e_3]`.
    pub fn template_vertices(&self) -> [Vector3<f64>; 4] {
        let v = |e: [i8; 3]| Vector3::new(f64::from(e[0]), f64::from(e[1]), f64::from(e[2]));
        [
            Vector3::zeros(),
            v(self.edges[0]),
            v(self.edges[1]),
            v(self.edges[2]),
        ]
    }
}

/// A change of lattice topology that per-node simulation state must follow.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TopologyEvent {
    /// `node` was created at the midpoint of `edge`; interpolate its position and
    /// velocity as the average of the two edge nodes.
    NodeAdded {
        node: NodeId,
        edge: (NodeId, NodeId),
    },
    /// `node` (a diamond centre) was removed by a merge; its id may be reused later.
    NodeRemoved { node: NodeId },
}

/// Errors of lattice construction and topology operations.
#[derive(Debug, thiserror::Error)]
pub enum LatticeError {
    #[error("invalid lattice parameters: {0}")]
    InvalidParams(String),
    #[error("empty lattice: {0}")]
    Empty(String),
    #[error("invalid surface mesh: {0}")]
    InvalidSurface(String),
    #[error("tet {0:?} does not exist")]
    NoSuchTet(TetId),
    #[error("tet {tet:?} is at the maximum depth {max_depth} and cannot be split")]
    MaxDepth { tet: TetId, max_depth: u8 },
    #[error("node {0:?} is not the centre of a split diamond")]
    NoSuchDiamond(NodeId),
    #[error("invalid region state: {0}")]
    InvalidState(String),
    #[error("embedding: {0}")]
    Embedding(String),
    #[error("internal lattice inconsistency: {0}")]
    Internal(&'static str),
}
