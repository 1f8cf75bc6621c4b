//! Refine / coarsen / XOR-state application per tet on a 16×4×4-cell beam.
//!
//! Run with `cargo bench -p cosurg-sim-lattice`. Mesh sizes are printed first.

use cosurg_sim_lattice::{Lattice, LatticeParams, NodeId, TopologyEvent};
use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use nalgebra::Vector3;

const LEVELS: u8 = 3;
const MAX_DEPTH: u8 = 9;

fn beam() -> Lattice {
    let mut cells = vec![];
    for z in 0..4 {
        for y in 0..4 {
            for x in 0..16 {
                cells.push([x, y, z]);
            }
        }
    }
    let params = LatticeParams {
        origin: Vector3::zeros(),
        cell: 0.01,
        max_depth: MAX_DEPTH,
    };
    Lattice::from_cells(params, &cells).expect("beam lattice")
}

/// The beam refined uniformly `LEVELS` levels, and the diamond centres created.
fn refined() -> (Lattice, Vec<NodeId>) {
    let mut l = beam();
    let mut ev = vec![];
    l.refine_where(|_, t| t.level() < LEVELS, &mut ev);
    let added = ev
        .iter()
        .filter_map(|e| match e {
            TopologyEvent::NodeAdded { node, .. } => Some(*node),
            _ => None,
        })
        .collect();
    (l, added)
}

fn all_roots(l: &Lattice) -> Vec<u32> {
    (0..l.root_count()).collect()
}

fn main() {
    let b = beam();
    let (r, added) = refined();
    println!(
        "beam 16x4x4 cells: {} root tets, {} nodes; refined {LEVELS} levels: {} leaf tets, {} nodes, {} diamonds",
        b.root_count(),
        b.node_count(),
        r.leaf_count(),
        r.node_count(),
        added.len()
    );
    let state = r.region_state(&all_roots(&r));
    println!(
        "refined beam region state: {} split tets, {} bytes encoded",
        state.split_count(),
        state.to_bytes().len()
    );
    divan::main();
}

/// Uniform refinement of the beam by `LEVELS` levels; counted per tet split.
#[divan::bench]
fn refine_uniform(bencher: Bencher) {
    let split = refined().0.leaf_count() - beam().leaf_count();
    bencher
        .counter(ItemsCount::new(split))
        .with_inputs(|| (beam(), Vec::with_capacity(1 << 16)))
        .bench_local_values(|(mut l, mut ev)| {
            l.refine_where(|_, t| t.level() < LEVELS, &mut ev);
            black_box(l)
        });
}

/// Merging every diamond of the refined beam, finest first; counted per tet merged.
#[divan::bench]
fn coarsen_uniform(bencher: Bencher) {
    let merged = refined().0.leaf_count() - beam().leaf_count();
    bencher
        .counter(ItemsCount::new(merged))
        .with_inputs(|| (refined(), Vec::with_capacity(1 << 16)))
        .bench_local_values(|((mut l, added), mut ev)| {
            for &n in added.iter().rev() {
                l.coarsen_diamond(n, &mut ev).expect("diamond");
            }
            black_box(l)
        });
}

/// `apply_state` from the coarse beam to the refined state; counted per tet split.
#[divan::bench]
fn apply_state_refine(bencher: Bencher) {
    let (r, _) = refined();
    let roots = all_roots(&r);
    let target = r.region_state(&roots);
    bencher
        .counter(ItemsCount::new(target.split_count()))
        .with_inputs(|| (beam(), Vec::with_capacity(1 << 16)))
        .bench_local_values(|(mut l, mut ev)| {
            l.apply_state(&target, &mut ev).expect("apply");
            black_box(l)
        });
}

/// `apply_state` from the refined beam back to the coarse state; counted per tet merged.
#[divan::bench]
fn apply_state_coarsen(bencher: Bencher) {
    let b = beam();
    let roots = all_roots(&b);
    let target = b.region_state(&roots);
    let merged = refined().0.region_state(&roots).split_count();
    bencher
        .counter(ItemsCount::new(merged))
        .with_inputs(|| (refined().0, Vec::with_capacity(1 << 16)))
        .bench_local_values(|(mut l, mut ev)| {
            l.apply_state(&target, &mut ev).expect("apply");
            black_box(l)
        });
}

/// Snapshot + encode of the refined beam's state; counted per split tet.
#[divan::bench]
fn region_state_to_bytes(bencher: Bencher) {
    let (r, _) = refined();
    let roots = all_roots(&r);
    let n = r.region_state(&roots).split_count();
    bencher
        .counter(ItemsCount::new(n))
        .bench_local(|| black_box(r.region_state(&roots).to_bytes()));
}

/// Local adaptive refinement: one leaf of the refined beam to `MAX_DEPTH` (with the
/// forced splits around it); counted per tet split.
#[divan::bench]
fn refine_local_to_max_depth(bencher: Bencher) {
    let p = Vector3::new(0.0813, 0.0217, 0.0191);
    let split = {
        let (mut l, _) = refined();
        let mut ev = vec![];
        refine_at(&mut l, &p, &mut ev)
    };
    bencher
        .counter(ItemsCount::new(split))
        .with_inputs(|| (refined().0, Vec::with_capacity(1024)))
        .bench_local_values(|(mut l, mut ev)| {
            refine_at(&mut l, &p, &mut ev);
            black_box(l)
        });
}

fn refine_at(l: &mut Lattice, p: &Vector3<f64>, ev: &mut Vec<TopologyEvent>) -> usize {
    let mut split = 0;
    loop {
        let (t, _) = l.point_location(p).expect("inside");
        if t.level() >= MAX_DEPTH {
            return split;
        }
        split += l.refine(t, ev).expect("refine");
    }
}

/// Leaf lookup of a world point in the refined beam.
#[divan::bench]
fn point_location(bencher: Bencher) {
    let (r, _) = refined();
    let pts: Vec<Vector3<f64>> = (0..1000)
        .map(|i| {
            let f = i as f64;
            Vector3::new(
                (f * 0.618_034).fract() * 0.16,
                (f * 0.414_214).fract() * 0.04,
                (f * 0.732_051).fract() * 0.04,
            )
        })
        .collect();
    bencher.counter(ItemsCount::new(pts.len())).bench_local(|| {
        for p in &pts {
            black_box(r.point_location(black_box(p)));
        }
    });
}
