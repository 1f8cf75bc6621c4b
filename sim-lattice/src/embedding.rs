//! Points embedded in the lattice by host leaf tet and barycentric weights.

use nalgebra::Vector3;

use crate::lattice::{tag, weights_to_parent};
use crate::{Lattice, LatticeError, NodeId, TetId};

/// Points (surface vertices, tool samples) hosted by leaf tets.
///
/// Weights are kept in the host's bisection order and moved between parent and children by
/// the exact linear maps of bisection (`x_k = 2z − x_0`: only halving, doubling and one
/// subtraction), so a point keeps its rest position across refine/coarsen, and any affine
/// deformation of the nodes is reproduced exactly (up to rounding) at every level.
///
/// A point outside every tet (beyond rounding) is hosted by the nearest leaf tet with
/// extrapolated weights (some negative, still summing to one): it then follows that tet's
/// affine motion, which is exact for affine deformations and a good approximation for a
/// point just outside the lattice.
#[derive(Clone, Debug)]
pub struct Embedding {
    hosts: Vec<TetId>,
    /// Weights paired with `nodes`, bisection order of the host.
    weights: Vec<[f64; 4]>,
    nodes: Vec<[NodeId; 4]>,
    outside: usize,
    generation: u64,
}

impl Embedding {
    /// Hosts every point (rest pose, m) in the current leaves.
    ///
    /// # Errors
    /// [`LatticeError::Embedding`] for a non-finite point.
    pub fn new(lattice: &Lattice, points: &[Vector3<f64>]) -> Result<Embedding, LatticeError> {
        let mut e = Embedding {
            hosts: Vec::with_capacity(points.len()),
            weights: Vec::with_capacity(points.len()),
            nodes: Vec::with_capacity(points.len()),
            outside: 0,
            generation: lattice.topology_generation(),
        };
        for (i, p) in points.iter().enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                return Err(LatticeError::Embedding(format!("point {i} is not finite")));
            }
            let (r, w) = match lattice.locate_f64(p, 1e-12) {
                Some(found) => found,
                None => {
                    e.outside += 1;
                    nearest_leaf(lattice, p)
                }
            };
            let rec = lattice.tet_rec(r);
            e.hosts.push(rec.id);
            e.weights.push(w);
            e.nodes.push(rec.nodes);
        }
        if e.outside > 0 {
            tracing::debug!(
                outside = e.outside,
                points = points.len(),
                "embedding: points outside the lattice hosted by their nearest tet"
            );
        }
        Ok(e)
    }

    pub fn len(&self) -> usize {
        self.hosts.len()
    }

    pub fn is_empty(&self) -> bool {
        self.hosts.is_empty()
    }

    /// Number of points that lay outside every tet when embedded.
    pub fn outside_count(&self) -> usize {
        self.outside
    }

    /// Host leaf, weights, and the nodes the weights belong to (paired entry by entry), for
    /// spreading a force `f` on point `i` as `w[j] f` onto `nodes[j]`.
    pub fn host(&self, i: usize) -> (TetId, [f64; 4], [NodeId; 4]) {
        (self.hosts[i], self.weights[i], self.nodes[i])
    }

    /// Re-hosts points whose host is no longer a leaf: descends into the children of a
    /// split host, ascends to the nearest existing ancestor of a merged one. No-op when the
    /// lattice topology did not change since the last update.
    pub fn update(&mut self, lattice: &Lattice) {
        if lattice.topology_generation() == self.generation {
            return;
        }
        for i in 0..self.hosts.len() {
            let mut t = self.hosts[i];
            let mut w = self.weights[i];
            let rec = match lattice.rec_of(t) {
                Some(r) => r,
                None => {
                    // Merged away: climb, mapping the weights up, until the tet exists.
                    loop {
                        let parent = TetId {
                            root: t.root,
                            heap: t.heap / 2,
                        };
                        w = weights_to_parent(w, tag(parent.level()), t.heap & 1);
                        t = parent;
                        if let Some(r) = lattice.rec_of(t) {
                            break r;
                        }
                    }
                }
            };
            let (leaf, w) = lattice.descend_weights(rec, w);
            let r = lattice.tet_rec(leaf);
            self.hosts[i] = r.id;
            self.weights[i] = w;
            self.nodes[i] = r.nodes;
        }
        self.generation = lattice.topology_generation();
    }

    /// Positions of the embedded points for node positions indexed by `NodeId.0`.
    ///
    /// # Panics
    /// If `out` is shorter than the number of points or a host node is out of range of
    /// `node_positions` (call [`Embedding::update`] after topology changes).
    pub fn interpolate(
        &self,
        lattice: &Lattice,
        node_positions: &[Vector3<f64>],
        out: &mut [Vector3<f64>],
    ) {
        debug_assert_eq!(
            lattice.topology_generation(),
            self.generation,
            "Embedding::update must follow topology changes"
        );
        for ((o, w), n) in out.iter_mut().zip(&self.weights).zip(&self.nodes) {
            *o = node_positions[n[0].0 as usize] * w[0]
                + node_positions[n[1].0 as usize] * w[1]
                + node_positions[n[2].0 as usize] * w[2]
                + node_positions[n[3].0 as usize] * w[3];
        }
    }
}

/// Nearest leaf (Euclidean distance to the tet) and the extrapolated weights; O(leaves),
/// only used for points outside the lattice.
fn nearest_leaf(lattice: &Lattice, p: &Vector3<f64>) -> (u32, [f64; 4]) {
    let g = lattice.to_grid_f64(p);
    let mut best = (u32::MAX, f64::INFINITY);
    for (i, _) in lattice.leaves().iter().enumerate() {
        let r = lattice.leaf_rec(i);
        let x = lattice.tet_rec(r).nodes.map(|n| {
            let v = lattice.grid(n);
            Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
        });
        let d = (0..4)
            .map(|j| {
                point_triangle_distance2(&g, &x[(j + 1) % 4], &x[(j + 2) % 4], &x[(j + 3) % 4])
            })
            .fold(f64::INFINITY, f64::min);
        if d < best.1 {
            best = (r, d);
        }
    }
    (best.0, lattice.barycentric(best.0, &g))
}

/// Squared distance from `p` to triangle `abc` (Ericson, Real-Time Collision Detection 5.1.5).
fn point_triangle_distance2(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> f64 {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return ap.norm_squared();
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return bp.norm_squared();
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (p - (a + ab * v)).norm_squared();
    }
    let cp = p - c;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return cp.norm_squared();
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (p - (a + ac * w)).norm_squared();
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (p - (b + (c - b) * w)).norm_squared();
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (p - (a + ab * v + ac * w)).norm_squared()
}
