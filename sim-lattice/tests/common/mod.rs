#![allow(dead_code)]

use std::collections::{HashMap, HashSet};

use cosurg_sim_lattice::{Lattice, LatticeParams, NodeId, TetId, TopologyEvent};
use nalgebra::Vector3;

pub fn params(max_depth: u8) -> LatticeParams {
    LatticeParams {
        origin: Vector3::new(0.1, -0.2, 0.3),
        cell: 0.01,
        max_depth,
    }
}

/// A 2×2×1 block plus one cell sticking out (odd and even parities, a concave corner).
pub fn small_lattice(max_depth: u8) -> Lattice {
    let mut cells = vec![];
    for x in -1..1 {
        for y in 0..2 {
            cells.push([x, y, 0]);
        }
    }
    cells.push([0, 0, 1]);
    Lattice::from_cells(params(max_depth), &cells).unwrap()
}

pub fn all_roots(l: &Lattice) -> Vec<u32> {
    (0..l.root_count()).collect()
}

/// One random topology operation on leaf `pick % leaves`: refine it (below max depth) or
/// coarsen its parent's diamond.
pub fn random_op(l: &mut Lattice, refine: bool, pick: usize, events: &mut Vec<TopologyEvent>) {
    let t = l.leaves()[pick % l.leaf_count()];
    if refine {
        if t.level() < l.params().max_depth {
            let n = l.refine(t, events).unwrap();
            assert!(n >= 1);
        } else {
            assert!(l.refine(t, events).is_err());
        }
    } else if let Some(p) = l.parent(t) {
        l.coarsen(p, events).unwrap();
    }
}

pub fn sorted_leaves(l: &Lattice) -> Vec<TetId> {
    let mut v = l.leaves().to_vec();
    v.sort();
    v
}

pub fn node_snapshot(l: &Lattice) -> HashMap<NodeId, [i64; 3]> {
    l.nodes().map(|n| (n, l.node_grid(n))).collect()
}

fn sorted3(mut f: [NodeId; 3]) -> [NodeId; 3] {
    f.sort();
    f
}

/// Conformity, exact volume, no hanging nodes, orientation, face neighbours.
pub fn check_invariants(l: &Lattice) {
    let u = l.units_per_cell();
    // Volumes: 6·V of a Kuhn tet is U³.
    let total: i128 = l.leaves().iter().map(|&t| l.tet_volume6_grid(t)).sum();
    assert_eq!(total, i128::from(l.root_count()) * i128::from(u).pow(3));

    let mut faces: HashMap<[NodeId; 3], u32> = HashMap::new();
    let mut used: HashSet<NodeId> = HashSet::new();
    for (i, &t) in l.leaves().iter().enumerate() {
        assert!(l.is_leaf(t));
        let n = l.tet_nodes(t);
        assert_eq!(n, l.leaf_tet_nodes(i));
        assert!(l.tet_volume6_grid(t) > 0, "{t:?} not positively oriented");
        for j in 0..4 {
            used.insert(n[j]);
            *faces
                .entry(sorted3([n[(j + 1) % 4], n[(j + 2) % 4], n[(j + 3) % 4]]))
                .or_default() += 1;
        }
    }
    let cells: HashSet<[i32; 3]> = l.cells().iter().copied().collect();
    let positions: HashSet<[i64; 3]> = l.nodes().map(|n| l.node_grid(n)).collect();
    assert_eq!(used.len(), l.node_count(), "orphan nodes");
    for &t in l.leaves() {
        let n = l.tet_nodes(t);
        let g = n.map(|x| l.node_grid(x));
        let nb = l.face_neighbors(t);
        for j in 0..4 {
            let face = [n[(j + 1) % 4], n[(j + 2) % 4], n[(j + 3) % 4]];
            let count = faces[&sorted3(face)];
            assert!(count <= 2, "face shared by {count} leaves");
            match nb[j] {
                Some(o) => {
                    assert_eq!(count, 2);
                    let on = l.tet_nodes(o);
                    assert!(face.iter().all(|f| on.contains(f)), "neighbour misses face");
                }
                None => {
                    assert_eq!(count, 1, "interior face without neighbour");
                    // A boundary face: just outside its centroid there is no root cube.
                    let c: Vector3<f64> = face
                        .iter()
                        .map(|&f| {
                            let g = l.node_grid(f);
                            Vector3::new(g[0] as f64, g[1] as f64, g[2] as f64)
                        })
                        .sum::<Vector3<f64>>()
                        / 3.0;
                    let d = Vector3::new(g[j][0] as f64, g[j][1] as f64, g[j][2] as f64);
                    let p = (c + (c - d) * 1e-3) / u as f64;
                    let cell = [p.x.floor() as i32, p.y.floor() as i32, p.z.floor() as i32];
                    assert!(!cells.contains(&cell), "unmatched face inside the domain");
                }
            }
        }
        // No node in the interior of a leaf edge (midpoint or quarter points).
        for a in 0..4 {
            for b in a + 1..4 {
                for (wa, wb) in [(1, 1), (1, 3), (3, 1)] {
                    let s: [i64; 3] = [0, 1, 2].map(|i| wa * g[a][i] + wb * g[b][i]);
                    if s.iter().all(|v| v % (wa + wb) == 0) {
                        let p = s.map(|v| v / (wa + wb));
                        assert!(!positions.contains(&p), "hanging node on an edge of {t:?}");
                    }
                }
            }
        }
    }
}

/// All existing tets (leaves and ancestors).
pub fn all_tets(l: &Lattice) -> Vec<TetId> {
    let mut out = vec![];
    let mut stack: Vec<TetId> = (0..l.root_count())
        .map(|root| TetId { root, heap: 1 })
        .collect();
    while let Some(t) = stack.pop() {
        out.push(t);
        if let Some(c) = l.children(t) {
            stack.extend(c);
        }
    }
    out
}
