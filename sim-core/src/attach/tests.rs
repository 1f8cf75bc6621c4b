//! Unit tests of the attachment layers: see also `sim-core/tests/attach.rs`.

use super::*;

#[test]
fn node_components_separate_disjoint_cells() {
    let params = sim_lattice::LatticeParams {
        origin: V3::zeros(),
        cell: 0.01,
        max_depth: 0,
    };
    // Two cubes with one empty cell between them, and a third touching the first.
    let lattice = Lattice::from_cells(params, &[[0, 0, 0], [2, 0, 0], [0, 1, 0]]).unwrap();
    let comp = node_components(&lattice);
    let at = |p: V3| {
        let (t, _) = lattice.point_location(&p).unwrap();
        comp[lattice.tet_nodes(t)[0].0 as usize]
    };
    assert_eq!(
        at(V3::new(0.005, 0.005, 0.005)),
        at(V3::new(0.005, 0.015, 0.005))
    );
    assert_ne!(
        at(V3::new(0.005, 0.005, 0.005)),
        at(V3::new(0.025, 0.005, 0.005))
    );
}
