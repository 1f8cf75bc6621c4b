//! Virtual-node separation (Molino, Bao & Fedkiw 2004) of the lattice's leaves along a
//! [`Sheet`].
//!
//! A leaf's four corners are grouped by the edges the sheet does not cross; each group (a
//! material component) becomes one copy of the leaf. A copy keeps the full tetrahedron
//! (no slivers: the lattice's shapes are kept) with its corners of the component as real
//! nodes and the others as virtual nodes; its material weight is the fraction of the leaf's
//! volume on its side, so mass and rest volume are conserved exactly (the fractions of a
//! leaf sum to 1). Copies that share a face and a real node on it are glued (their nodes
//! on that face are the same degree of freedom); a lattice node whose surrounding copies
//! fall into several glued groups gets one degree of freedom per group. Cuts resolve at the
//! element scale: a sheet that crosses some edges of a leaf without separating its corners
//! leaves the leaf whole (the crack tip), which is why the lattice is refined to its deepest
//! level along the sheet first.

use std::collections::{BTreeMap, HashMap};

use nalgebra::Vector3;
use sim_lattice::{Lattice, NodeId, TetId};

use super::sheet::Sheet;

type V3 = Vector3<f64>;

/// Smallest volume fraction a copy keeps, so that no copy is massless (a node lying on
/// the sheet gives a zero raw fraction); the complement takes the rest, so a leaf's
/// fractions still sum to exactly 1.
pub const MIN_FRACTION: f64 = 1e-4;

/// The local corner pairs of a tetrahedron's six edges.
const EDGES: [(usize, usize); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
/// The local corners of a tetrahedron's four faces.
const FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];

/// One element of the cut system: a leaf, or one copy of a crossed leaf.
#[derive(Clone, Debug, PartialEq)]
pub struct ElementCopy {
    /// The lattice leaf.
    pub leaf: TetId,
    /// Bit `k` set: corner `k` (in [`Lattice::tet_nodes`] order) is a real (material)
    /// node of this copy; `0b1111` for an uncut leaf.
    pub mask: u8,
    /// Fraction of the leaf's rest volume (and mass) this copy carries, in (0, 1].
    pub fraction: f64,
    /// Degree of freedom of every corner (an index into the simulation's node arrays: the
    /// lattice node's own slot, or a virtual node's slot past the lattice's capacity).
    pub dofs: [usize; 4],
}

/// The lattice's leaves separated along a sheet.
#[derive(Clone, Debug, Default)]
pub struct Separation {
    /// Every element, uncut leaves included, ordered by (leaf, mask).
    pub copies: Vec<ElementCopy>,
    /// Lattice node capacity at separation time: degrees of freedom `>= capacity` are
    /// virtual nodes.
    pub capacity: usize,
    /// The lattice node of every virtual node (`capacity + k` ↦ `virtual_nodes[k]`).
    pub virtual_nodes: Vec<NodeId>,
    /// The crossed leaves (separated into two or more copies), sorted.
    pub crossed: Vec<TetId>,
}

impl Separation {
    /// Total degrees of freedom (lattice slots + virtual nodes).
    pub fn dof_count(&self) -> usize {
        self.capacity + self.virtual_nodes.len()
    }

    /// The lattice node a degree of freedom belongs to.
    pub fn dof_node(&self, dof: usize) -> NodeId {
        if dof < self.capacity {
            NodeId(dof as u32)
        } else {
            self.virtual_nodes[dof - self.capacity]
        }
    }

    /// Copies of one leaf (empty if it is no leaf of this separation).
    pub fn copies_of(&self, leaf: TetId) -> &[ElementCopy] {
        let start = self.copies.partition_point(|c| c.leaf < leaf);
        let end = start + self.copies[start..].partition_point(|c| c.leaf == leaf);
        &self.copies[start..end]
    }
}

struct UnionFind(Vec<usize>);

impl UnionFind {
    fn find(&mut self, mut i: usize) -> usize {
        while self.0[i] != i {
            self.0[i] = self.0[self.0[i]];
            i = self.0[i];
        }
        i
    }
    fn union(&mut self, a: usize, b: usize) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b {
            // The smaller index wins: the result does not depend on the union order.
            let (lo, hi) = (a.min(b), a.max(b));
            self.0[hi] = lo;
        }
    }
}

/// Components of a leaf's corners and the crossing parameters of its edges.
pub(crate) fn leaf_components(sheet: &Sheet, p: &[V3; 4]) -> (Vec<u8>, [Option<f64>; 6]) {
    let mut cut = [None; 6];
    let mut uf = UnionFind((0..4).collect());
    for (e, &(i, j)) in EDGES.iter().enumerate() {
        cut[e] = sheet.crossing(&p[i], &p[j]);
        if cut[e].is_none() {
            uf.union(i, j);
        }
    }
    let mut masks: BTreeMap<usize, u8> = BTreeMap::new();
    for k in 0..4 {
        *masks.entry(uf.find(k)).or_default() |= 1 << k;
    }
    (masks.into_values().collect(), cut)
}

/// Crossing parameter of edge `(i, j)` measured from corner `i`.
fn param_from(cut: &[Option<f64>; 6], i: usize, j: usize) -> f64 {
    let e = EDGES
        .iter()
        .position(|&(a, b)| (a, b) == (i.min(j), i.max(j)))
        .expect("a tet edge");
    let t = cut[e].unwrap_or(0.5);
    if i < j { t } else { 1.0 - t }
}

fn tet_volume(a: &V3, b: &V3, c: &V3, d: &V3) -> f64 {
    ((b - a).cross(&(c - a))).dot(&(d - a)).abs() / 6.0
}

/// Volume fractions of a crossed leaf's components (they sum to 1): a lone corner keeps
/// the corner tetrahedron cut off at its edges' crossings; two corners keep the wedge
/// between their edges' crossings (exact for a planar sheet, the piecewise-linear
/// interface otherwise); with more than two components the raw volumes are normalised.
pub(crate) fn fractions(p: &[V3; 4], cut: &[Option<f64>; 6], masks: &[u8]) -> Vec<f64> {
    let vol = tet_volume(&p[0], &p[1], &p[2], &p[3]);
    let at = |i: usize, j: usize| p[i] + param_from(cut, i, j) * (p[j] - p[i]);
    let raw = |m: u8| -> f64 {
        let inside: Vec<usize> = (0..4).filter(|k| m & (1 << k) != 0).collect();
        let outside: Vec<usize> = (0..4).filter(|k| m & (1 << k) == 0).collect();
        match (inside.len(), outside.len()) {
            (4, 0) => 1.0,
            (1, _) => {
                let a = inside[0];
                let others: Vec<usize> = (0..4).filter(|&k| k != a).collect();
                others
                    .iter()
                    .map(|&o| {
                        if outside.contains(&o) {
                            param_from(cut, a, o)
                        } else {
                            1.0
                        }
                    })
                    .product()
            }
            (3, 1) => {
                let o = outside[0];
                1.0 - (0..4)
                    .filter(|&k| k != o)
                    .map(|k| param_from(cut, o, k))
                    .product::<f64>()
            }
            (2, 2) => {
                let (a, b) = (inside[0], inside[1]);
                let (c, d) = (outside[0], outside[1]);
                let bottom = [p[a], at(a, c), at(a, d)];
                let top = [p[b], at(b, c), at(b, d)];
                (tet_volume(&bottom[0], &bottom[1], &bottom[2], &top[0])
                    + tet_volume(&bottom[1], &bottom[2], &top[0], &top[1])
                    + tet_volume(&bottom[2], &top[0], &top[1], &top[2]))
                    / vol.max(f64::MIN_POSITIVE)
            }
            _ => 0.0,
        }
    };
    let mut f: Vec<f64> = masks
        .iter()
        .map(|&m| raw(m).clamp(MIN_FRACTION, 1.0 - MIN_FRACTION))
        .collect();
    if masks.len() == 2 {
        // Exactly complementary: the second is one minus the first.
        f[1] = 1.0 - f[0];
    } else {
        let sum: f64 = f.iter().sum();
        if sum > 0.0 {
            f.iter_mut().for_each(|v| *v /= sum);
        } else {
            let n = f.len() as f64;
            f.iter_mut().for_each(|v| *v = 1.0 / n);
        }
    }
    f
}

/// Separates the lattice's leaves along `sheet`.
pub fn separate(lattice: &Lattice, sheet: &Sheet) -> Separation {
    let capacity = lattice.node_capacity();
    let rest = |t: TetId| lattice.tet_nodes(t).map(|n| lattice.node_rest(n));
    let mut leaves: Vec<TetId> = lattice.leaves().to_vec();
    leaves.sort_unstable();

    // 1. Components of every leaf near the sheet.
    let mut split: HashMap<TetId, Vec<(u8, f64)>> = HashMap::new();
    for &t in &leaves {
        let p = rest(t);
        let lo = p[0].inf(&p[1]).inf(&p[2]).inf(&p[3]);
        let hi = p[0].sup(&p[1]).sup(&p[2]).sup(&p[3]);
        if !sheet.overlaps_box(&lo, &hi) {
            continue;
        }
        let (masks, cut) = leaf_components(sheet, &p);
        if masks.len() > 1 {
            let f = fractions(&p, &cut, &masks);
            split.insert(t, masks.into_iter().zip(f).collect());
        }
    }
    let mut crossed: Vec<TetId> = split.keys().copied().collect();
    crossed.sort_unstable();

    // 2. Copies, in (leaf, mask) order.
    let mut copies: Vec<ElementCopy> = Vec::with_capacity(leaves.len() + crossed.len());
    for &t in &leaves {
        let nodes = lattice.tet_nodes(t).map(|n| n.0 as usize);
        match split.get(&t) {
            None => copies.push(ElementCopy {
                leaf: t,
                mask: 0b1111,
                fraction: 1.0,
                dofs: nodes,
            }),
            Some(parts) => {
                let mut parts = parts.clone();
                parts.sort_by_key(|(m, _)| *m);
                for (mask, fraction) in parts {
                    copies.push(ElementCopy {
                        leaf: t,
                        mask,
                        fraction,
                        dofs: nodes,
                    });
                }
            }
        }
    }
    if crossed.is_empty() {
        return Separation {
            copies,
            capacity,
            virtual_nodes: Vec::new(),
            crossed,
        };
    }

    // 3. Nodes whose surrounding material may be separated: the corners of crossed leaves.
    let mut affected = vec![false; capacity];
    for &t in &crossed {
        for n in lattice.tet_nodes(t) {
            affected[n.0 as usize] = true;
        }
    }
    // Members: (copy, corner) pairs at affected nodes.
    let mut member_of: HashMap<(usize, usize), usize> = HashMap::new();
    let mut members: Vec<(usize, usize)> = Vec::new();
    for (ci, c) in copies.iter().enumerate() {
        for k in 0..4 {
            if affected[c.dofs[k]] {
                member_of.insert((ci, k), members.len());
                members.push((ci, k));
            }
        }
    }
    let mut uf = UnionFind((0..members.len()).collect());
    // 4. Glue copies across shared faces that hold a real node of both.
    let mut faces: HashMap<[usize; 3], Vec<(usize, [usize; 3])>> = HashMap::new();
    for (ci, c) in copies.iter().enumerate() {
        for f in FACES {
            if !f.iter().any(|&k| affected[c.dofs[k]]) {
                continue;
            }
            let mut key = f.map(|k| c.dofs[k]);
            key.sort_unstable();
            faces.entry(key).or_default().push((ci, f));
        }
    }
    let mut face_keys: Vec<&[usize; 3]> = faces.keys().collect();
    face_keys.sort_unstable();
    for key in face_keys {
        let list = &faces[key];
        for (i, &(c1, f1)) in list.iter().enumerate() {
            for &(c2, f2) in &list[i + 1..] {
                let (a, b) = (&copies[c1], &copies[c2]);
                if a.leaf == b.leaf {
                    continue;
                }
                let real = |c: &ElementCopy, f: [usize; 3]| -> Vec<usize> {
                    f.iter()
                        .filter(|&&k| c.mask & (1 << k) != 0)
                        .map(|&k| c.dofs[k])
                        .collect()
                };
                let (ra, rb) = (real(a, f1), real(b, f2));
                if !ra.iter().any(|n| rb.contains(n)) {
                    continue;
                }
                for &ka in &f1 {
                    let node = a.dofs[ka];
                    if !affected[node] {
                        continue;
                    }
                    let kb = *f2
                        .iter()
                        .find(|&&k| b.dofs[k] == node)
                        .expect("shared face");
                    uf.union(member_of[&(c1, ka)], member_of[&(c2, kb)]);
                }
            }
        }
    }
    // 5. One degree of freedom per glued group: the group holding the real corner of the
    // first copy (in (leaf, mask) order) keeps the lattice slot, the others get virtual
    // slots in (node grid, first member) order.
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for m in 0..members.len() {
        groups.entry(uf.find(m)).or_default().push(m);
    }
    let mut primary: HashMap<usize, usize> = HashMap::new(); // node -> group root
    for (&root, ms) in &groups {
        let (ci, k) = members[ms[0]];
        let node = copies[ci].dofs[k];
        let has_real = ms.iter().any(|&m| {
            let (ci, k) = members[m];
            copies[ci].mask & (1 << k) != 0
        });
        if has_real {
            primary.entry(node).or_insert(root);
        }
    }
    let mut extra: Vec<([i64; 3], usize, usize)> = groups
        .iter()
        .filter_map(|(&root, ms)| {
            let (ci, k) = members[ms[0]];
            let node = copies[ci].dofs[k];
            (primary.get(&node) != Some(&root))
                .then(|| (lattice.node_grid(NodeId(node as u32)), ms[0], root))
        })
        .collect();
    extra.sort_unstable();
    let mut group_dof: HashMap<usize, usize> = HashMap::new();
    let mut virtual_nodes = Vec::with_capacity(extra.len());
    for (k, &(_, first, root)) in extra.iter().enumerate() {
        let (ci, corner) = members[first];
        virtual_nodes.push(NodeId(copies[ci].dofs[corner] as u32));
        group_dof.insert(root, capacity + k);
    }
    let assigned: Vec<(usize, usize, usize)> = members
        .iter()
        .enumerate()
        .filter_map(|(m, &(ci, k))| {
            let root = uf.find(m);
            group_dof.get(&root).map(|&d| (ci, k, d))
        })
        .collect();
    for (ci, k, d) in assigned {
        copies[ci].dofs[k] = d;
    }
    Separation {
        copies,
        capacity,
        virtual_nodes,
        crossed,
    }
}
