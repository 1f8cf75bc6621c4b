//! The lattice hierarchy: every prolongation reproduces linear fields exactly (the nested
//! P1 spaces of bisection), levels shrink, and adaptive lattices work.

use nalgebra::Vector3;
use sim_lattice::{Lattice, LatticeParams, NodeId};

use super::lattice_hierarchy_with_grids;

type V3 = Vector3<f64>;

fn box_lattice(n: [i32; 3], max_depth: u8) -> Lattice {
    lattice_of_box_cells(n, max_depth, |_| true)
}

/// The cells of the box `n` for which `keep` holds.
fn lattice_of_box_cells(n: [i32; 3], max_depth: u8, keep: impl Fn([i32; 3]) -> bool) -> Lattice {
    let mut cells = Vec::new();
    for i in 0..n[0] {
        for j in 0..n[1] {
            for k in 0..n[2] {
                if keep([i, j, k]) {
                    cells.push([i, j, k]);
                }
            }
        }
    }
    let params = LatticeParams {
        origin: V3::new(0.1, -0.2, 0.3),
        cell: 0.02,
        max_depth,
    };
    Lattice::from_cells(params, &cells).unwrap()
}

/// A linear field (m).
fn linear(p: &V3) -> V3 {
    V3::new(
        0.3 + 2.0 * p.x - p.y,
        -1.0 + 0.5 * p.z,
        p.x + p.y + 3.0 * p.z,
    )
}

/// Walks the hierarchy with each level's rest positions (the coarse levels' from their
/// grid points, which may lie outside the lattice); at every level the prolongation of the
/// linear field sampled on the coarse nodes must equal the field on the fine nodes, and the
/// prolongation must have full column rank (`PᵀP` positive definite: no coarse node
/// unused, none a combination of others), so that the Galerkin coarse operators of a
/// positive-definite matrix are positive definite. Returns the level sizes, finest (live
/// nodes) first.
fn check_linear_exactness(lat: &Lattice) -> Vec<usize> {
    let (h, grids) = lattice_hierarchy_with_grids(lat).unwrap();
    h.validate(lat.node_capacity()).unwrap();
    assert_eq!(grids.len(), h.levels.len());
    let unit = lat.params().cell / lat.units_per_cell() as f64;
    let world =
        |g: &[i64; 3]| lat.params().origin + V3::new(g[0] as f64, g[1] as f64, g[2] as f64) * unit;
    // Rest position of each row of the current level (None: a dead slot).
    let mut fine: Vec<Option<V3>> = (0..lat.node_capacity())
        .map(|i| {
            let n = NodeId(i as u32);
            lat.node_alive(n).then(|| lat.node_rest(n))
        })
        .collect();
    let mut sizes = vec![fine.iter().flatten().count()];
    for (p, grid) in h.levels.iter().zip(&grids) {
        assert_eq!(p.coarse_len(), grid.len());
        let coarse_val: Vec<V3> = grid.iter().map(|g| linear(&world(g))).collect();
        for (i, x) in fine.iter().enumerate() {
            let Some(x) = x else {
                assert_eq!(p.row(i).count(), 0, "dead slot {i} has an empty row");
                continue;
            };
            let got: V3 = p.row(i).map(|(c, w)| coarse_val[c] * w).sum();
            let want = linear(x);
            assert!(
                (got - want).norm() < 1e-12 * (1.0 + want.norm()),
                "row {i}: {got:?} vs {want:?}"
            );
        }
        let nc = p.coarse_len();
        let mut ptp = nalgebra::DMatrix::<f64>::zeros(nc, nc);
        for i in 0..p.fine_len() {
            for (c1, w1) in p.row(i) {
                for (c2, w2) in p.row(i) {
                    ptp[(c1, c2)] += w1 * w2;
                }
            }
        }
        assert!(
            ptp.cholesky().is_some(),
            "level of {nc} nodes: PᵀP is singular"
        );
        fine = grid.iter().map(|g| Some(world(g))).collect();
        sizes.push(p.coarse_len());
    }
    sizes
}

#[test]
fn uniform_lattice_hierarchy_interpolates_linear_fields_exactly() {
    let mut lat = box_lattice([8, 4, 4], 3);
    let mut ev = Vec::new();
    lat.refine_where(|_, _| true, &mut ev);
    let sizes = check_linear_exactness(&lat);
    // 17×9×9 grid → 9×5×5 (root corners) → 5×3×3 → 3×2×2, then boundary leftovers.
    assert_eq!(
        sizes[..4],
        [17 * 9 * 9, 9 * 5 * 5, 5 * 3 * 3, 3 * 2 * 2],
        "{sizes:?}"
    );
    assert!(sizes.windows(2).all(|w| w[1] < w[0]), "{sizes:?}");
}

#[test]
fn adaptive_lattice_hierarchy_interpolates_linear_fields_exactly() {
    // Refined to depth 5 where x < 3 cells, conformity grades the rest: a non-uniform
    // lattice with a 7-cell (odd) length, whose coarse levels take nodes outside it.
    let mut lat = box_lattice([7, 3, 2], 5);
    let mut ev = Vec::new();
    lat.refine_where(
        |l, t| {
            let c: V3 = l.tet_nodes(t).iter().map(|&n| l.node_rest(n)).sum::<V3>() / 4.0;
            c.x < 0.1 + 3.0 * 0.02
        },
        &mut ev,
    );
    let sizes = check_linear_exactness(&lat);
    assert!(sizes.len() >= 3, "{sizes:?}");
    assert!(sizes.windows(2).all(|w| w[1] < w[0]), "{sizes:?}");
}

#[test]
fn a_box_whose_cell_counts_are_not_powers_of_two_coarsens_on_its_far_planes() {
    // 12 × 3 × 3 cells, halved once: the far planes x = 12 and y, z = 3 cells have no
    // parents inside the box on the coarse levels. Their parents lie outside it (on the
    // padded grid): along y and z (in cells) 0, 1, 2, 3 → 0, 2, 4 → 0, 4; along x 0, 2,
    // …, 12 → 0, 4, 8, 12 → 0, 8, 16 → 0, 16, as on a box of 16 × 4 × 4 cells, keeping
    // only the points some finer node takes (the Kuhn diagonals need 9 of the 3 × 2 × 2
    // points at the 4-cell level). Every level still reproduces linear fields.
    let mut lat = box_lattice([12, 3, 3], 3);
    let mut ev = Vec::new();
    lat.refine_where(|_, _| true, &mut ev);
    let sizes = check_linear_exactness(&lat);
    // Before the far planes coarsened: 1,225, 208, 119, 116, 115 (they stayed on every
    // level).
    assert_eq!(sizes, [25 * 7 * 7, 13 * 4 * 4, 7 * 3 * 3, 4 * 2 * 2, 9, 8]);
}

#[test]
fn an_l_shaped_lattice_coarsens_with_full_rank_levels() {
    // 8 × 4 × 4 cells less the block x ≥ 4, y ≥ 2: a re-entrant corner, padded nodes
    // inside the missing block as well as beyond the far planes.
    let mut lat = lattice_of_box_cells([8, 4, 4], 3, |[i, j, _]| !(i >= 4 && j >= 2));
    let mut ev = Vec::new();
    lat.refine_where(|_, _| true, &mut ev);
    let sizes = check_linear_exactness(&lat);
    assert!(sizes.len() >= 4, "{sizes:?}");
}
