//! Similarity types, the bisection cycle, dihedral-angle bound, shape keys.

mod common;

use std::collections::HashMap;

use common::*;
use cosurg_sim_lattice::{Lattice, ShapeKey, TetId, TetType};
use nalgebra::Vector3;

type V = Vector3<f64>;

fn v(x: f64, y: f64, z: f64) -> V {
    V::new(x, y, z)
}

/// Canonical tets: the Kuhn tet of the unit cube, its child and grandchild under bisection
/// of the longest edge (the textbook construction), independent of the crate.
fn canonical(t: TetType) -> [V; 4] {
    match t {
        TetType::Type0 => [v(0., 0., 0.), v(1., 0., 0.), v(1., 1., 0.), v(1., 1., 1.)],
        TetType::Type1 => [
            v(0., 0., 0.),
            v(1., 0., 0.),
            v(1., 1., 0.),
            v(0.5, 0.5, 0.5),
        ],
        TetType::Type2 => [
            v(0., 0., 0.),
            v(1., 0., 0.),
            v(0.5, 0.5, 0.),
            v(0.5, 0.5, 0.5),
        ],
    }
}

fn dihedral_angles(x: &[V; 4]) -> Vec<f64> {
    let mut out = vec![];
    for a in 0..4 {
        for b in a + 1..4 {
            let o: Vec<usize> = (0..4).filter(|&i| i != a && i != b).collect();
            let e = (x[b] - x[a]).normalize();
            let perp = |p: V| {
                let d = p - x[a];
                d - e * d.dot(&e)
            };
            let (u, w) = (perp(x[o[0]]), perp(x[o[1]]));
            out.push((u.dot(&w) / (u.norm() * w.norm())).clamp(-1., 1.).acos());
        }
    }
    out
}

fn min_dihedral(x: &[V; 4]) -> f64 {
    dihedral_angles(x).into_iter().fold(f64::INFINITY, f64::min)
}

fn sorted_sq_edges_normalised(x: &[V; 4]) -> Vec<f64> {
    let mut e = vec![];
    for a in 0..4 {
        for b in a + 1..4 {
            e.push((x[b] - x[a]).norm_squared());
        }
    }
    e.sort_by(f64::total_cmp);
    let m = e[0];
    e.into_iter().map(|v| v / m).collect()
}

fn vol(x: &[V; 4]) -> f64 {
    (x[1] - x[0]).cross(&(x[2] - x[0])).dot(&(x[3] - x[0])) / 6.0
}

fn grid_pos(l: &Lattice, t: TetId) -> [V; 4] {
    l.tet_nodes(t).map(|n| {
        let g = l.node_grid(n);
        v(g[0] as f64, g[1] as f64, g[2] as f64)
    })
}

#[test]
fn canonical_types_have_the_described_right_angles() {
    let orth = |a: V, b: V| a.dot(&b).abs() < 1e-15;
    // TYPE0: a path of three mutually orthogonal edges.
    let x = canonical(TetType::Type0);
    let (e1, e2, e3) = (x[1] - x[0], x[2] - x[1], x[3] - x[2]);
    assert!(orth(e1, e2) && orth(e2, e3) && orth(e1, e3));
    // TYPE1: a pair of orthogonal opposite edges.
    let x = canonical(TetType::Type1);
    assert!(orth(x[2] - x[0], x[3] - x[1]));
    // TYPE2: three orthogonal edges at one vertex (x[2]).
    let x = canonical(TetType::Type2);
    let (a, b, c) = (x[0] - x[2], x[1] - x[2], x[3] - x[2]);
    assert!(orth(a, b) && orth(b, c) && orth(a, c));
    // Volumes 1/6, 1/12, 1/24 of the cube.
    for (t, f) in [
        (TetType::Type0, 6.),
        (TetType::Type1, 12.),
        (TetType::Type2, 24.),
    ] {
        assert!((vol(&canonical(t)).abs() - 1. / f).abs() < 1e-15);
    }
}

#[test]
fn every_tet_is_similar_to_its_type_and_dihedral_bound_holds() {
    let mut l = small_lattice(7);
    let mut ev = vec![];
    l.refine_where(|_, _| true, &mut ev);
    let types = [TetType::Type0, TetType::Type1, TetType::Type2];
    let bound_per_type: HashMap<TetType, f64> = types
        .iter()
        .map(|&t| (t, min_dihedral(&canonical(t))))
        .collect();
    let bound = bound_per_type
        .values()
        .copied()
        .fold(f64::INFINITY, f64::min);
    // TYPE0 (path orthoscheme) has the smallest angles: 45° and 60° (π/4 exactly).
    assert!(
        (bound - std::f64::consts::FRAC_PI_4).abs() < 1e-12,
        "bound {bound}"
    );

    let u = l.units_per_cell() as f64;
    let mut global_min = f64::INFINITY;
    let mut keys: HashMap<ShapeKey, usize> = HashMap::new();
    let tets = all_tets(&l);
    assert_eq!(tets.len(), 30 * 255);
    for t in tets {
        let ty = l.tet_type(t);
        // The bisection cycle: the type follows the level.
        let expect = types[usize::from(t.level() % 3)];
        assert_eq!(ty, expect);
        let x = grid_pos(&l, t);
        let canon = canonical(ty);
        let a = sorted_sq_edges_normalised(&x);
        let b = sorted_sq_edges_normalised(&canon);
        for (p, q) in a.iter().zip(&b) {
            assert!((p - q).abs() < 1e-12, "{t:?} not similar to {ty:?}");
        }
        let cube = u / f64::from(1u32 << (t.level() / 3));
        assert!((vol(&x) - vol(&canon) * cube.powi(3)).abs() < 1e-9 * cube.powi(3));
        let m = min_dihedral(&x);
        assert!((m - bound_per_type[&ty]).abs() < 1e-12);
        global_min = global_min.min(m);
        // Shape key: rest edges are h_e times the template edges.
        let key = l.tet_shape(t);
        assert_eq!(key.tet_type, ty);
        let h = l.tet_scale(t) / l.params().cell * u;
        let tv = key.template_vertices();
        for j in 1..4 {
            assert!(((x[j] - x[0]) - (tv[j] * h)).norm() < 1e-12);
        }
        let rest: Vec<V> = l.tet_nodes(t).iter().map(|&n| l.node_rest(n)).collect();
        let s = l.tet_scale(t);
        for j in 1..4 {
            assert!(((rest[j] - rest[0]) - tv[j] * s).norm() < 1e-14);
        }
        assert!((l.tet_rest_volume(t) - vol(&tv) * s.powi(3)).abs() < 1e-20);
        *keys.entry(key).or_default() += 1;
    }
    assert!((global_min - bound).abs() < 1e-12);
    // Type × orientation: a small table (48 orientations of the cube per type at most).
    assert!(keys.len() <= 3 * 48, "{} shape keys", keys.len());
}

#[test]
fn point_location_is_consistent_with_tet_nodes() {
    let mut l = small_lattice(6);
    let mut ev = vec![];
    for i in 0..40 {
        random_op(&mut l, i % 4 != 0, i * 104_729, &mut ev);
    }
    let mut seed = 7u64;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let p0 = l.params().origin;
    let cell = l.params().cell;
    for _ in 0..500 {
        let c = l.cells()[(rnd() * l.cells().len() as f64) as usize % l.cells().len()];
        let p = p0
            + v(
                f64::from(c[0]) + rnd(),
                f64::from(c[1]) + rnd(),
                f64::from(c[2]) + rnd(),
            ) * cell;
        let (t, w) = l.point_location(&p).expect("inside");
        assert!(l.is_leaf(t));
        assert!(w.iter().all(|&x| x >= -1e-12));
        let q: V = l
            .tet_nodes(t)
            .iter()
            .zip(w)
            .map(|(&n, w)| l.node_rest(n) * w)
            .sum();
        assert!((q - p).norm() < 1e-14);
    }
    assert!(l.point_location(&(p0 + v(10., 0., 0.) * cell)).is_none());
}
