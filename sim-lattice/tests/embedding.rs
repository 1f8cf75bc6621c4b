//! Embedded points reproduce themselves and follow affine maps exactly, across topology
//! changes.

mod common;

use common::*;
use cosurg_sim_lattice::{Embedding, Lattice, RegionState};
use nalgebra::{Matrix3, Vector3};
use proptest::prelude::*;

type V = Vector3<f64>;

fn node_positions(l: &Lattice, f: impl Fn(V) -> V) -> Vec<V> {
    let mut x = vec![V::repeat(f64::NAN); l.node_capacity()];
    for n in l.nodes() {
        x[n.0 as usize] = f(l.node_rest(n));
    }
    x
}

fn check_affine(l: &Lattice, e: &Embedding, points: &[V], a: &Matrix3<f64>, b: &V) {
    let mut out = vec![V::zeros(); points.len()];
    e.interpolate(l, &node_positions(l, |p| p), &mut out);
    for (o, p) in out.iter().zip(points) {
        assert!((o - p).norm() < 1e-12, "rest pose: {o} vs {p}");
    }
    e.interpolate(l, &node_positions(l, |p| a * p + b), &mut out);
    for (o, p) in out.iter().zip(points) {
        assert!((o - (a * p + b)).norm() < 1e-12, "affine");
    }
    for i in 0..e.len() {
        let (t, w, nodes) = e.host(i);
        assert!(l.is_leaf(t));
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        let tn = l.tet_nodes(t);
        assert!(nodes.iter().all(|n| tn.contains(n)));
    }
}

fn points(l: &Lattice, seed: u64) -> Vec<V> {
    let mut s = seed;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    let cell = l.params().cell;
    let o = l.params().origin;
    let mut pts: Vec<V> = (0..200)
        .map(|_| {
            let c = l.cells()[(rnd() * 1e6) as usize % l.cells().len()];
            o + V::new(
                f64::from(c[0]) + rnd(),
                f64::from(c[1]) + rnd(),
                f64::from(c[2]) + rnd(),
            ) * cell
        })
        .collect();
    // Nodes, a face point, and points just outside the lattice.
    pts.push(o);
    pts.push(o + V::new(0.5, 0.5, 0.0) * cell);
    pts.push(o + V::new(0.3, 0.6, -0.05) * cell);
    pts.push(o + V::new(-2.2, 1.0, 0.5) * cell);
    pts
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    #[test]
    fn embedded_points_follow_affine_maps(
        ops1 in prop::collection::vec((prop::bool::weighted(0.8), any::<usize>()), 0..30),
        ops2 in prop::collection::vec((prop::bool::weighted(0.4), any::<usize>()), 0..30),
        m in prop::array::uniform9(-0.3f64..0.3),
        seed in any::<u64>(),
    ) {
        let a = Matrix3::identity() + Matrix3::from_row_slice(&m);
        let b = V::new(0.01, -0.02, 0.03);
        let mut l = small_lattice(6);
        let mut ev = vec![];
        for (r, p) in ops1 { random_op(&mut l, r, p, &mut ev); }
        let pts = points(&l, seed);
        let mut e = Embedding::new(&l, &pts).unwrap();
        prop_assert_eq!(e.outside_count(), 2);
        check_affine(&l, &e, &pts, &a, &b);
        for (r, p) in ops2 {
            random_op(&mut l, r, p, &mut ev);
            e.update(&l);
        }
        check_affine(&l, &e, &pts, &a, &b);
        // Uniform refinement to the bottom and full coarsening back.
        l.refine_where(|_, _| true, &mut ev);
        e.update(&l);
        check_affine(&l, &e, &pts, &a, &b);
        l.apply_state(&RegionState::unrefined(&all_roots(&l)), &mut ev).unwrap();
        e.update(&l);
        prop_assert_eq!(l.leaf_count(), 30);
        check_affine(&l, &e, &pts, &a, &b);
    }
}
