//! `Lattice::from_surface` keeps the cubes a closed surface needs.

use std::collections::HashSet;

use cosurg_sim_lattice::{Embedding, Lattice, LatticeError, LatticeParams};
use nalgebra::Vector3;

type V = Vector3<f64>;

fn uv_sphere(centre: V, r: f64, n_lon: usize, n_lat: usize) -> (Vec<V>, Vec<[u32; 3]>) {
    let mut v = vec![centre + V::new(0., 0., r), centre - V::new(0., 0., r)];
    for i in 1..n_lat {
        let th = std::f64::consts::PI * i as f64 / n_lat as f64;
        for j in 0..n_lon {
            let ph = 2. * std::f64::consts::PI * j as f64 / n_lon as f64;
            v.push(centre + r * V::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
        }
    }
    let ring = |i: usize, j: usize| (2 + (i - 1) * n_lon + j % n_lon) as u32;
    let mut t = vec![];
    for j in 0..n_lon {
        t.push([0, ring(1, j), ring(1, j + 1)]);
        t.push([1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)]);
        for i in 1..n_lat - 1 {
            t.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
            t.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
        }
    }
    (v, t)
}

fn enclosed_volume(v: &[V], t: &[[u32; 3]]) -> f64 {
    t.iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| v[i as usize]);
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum::<f64>()
        .abs()
}

fn params() -> LatticeParams {
    LatticeParams {
        origin: V::new(0.003, -0.001, 0.002),
        cell: 0.02,
        max_depth: 6,
    }
}

#[test]
fn sphere_keeps_the_cubes_it_needs() {
    let centre = V::new(0.031, 0.017, -0.013);
    let r = 0.05;
    let (v, t) = uv_sphere(centre, r, 24, 12);
    let p = params();
    let l = Lattice::from_surface(p, &v, &t).unwrap();
    // Every surface vertex lies in a kept tet.
    for x in &v {
        assert!(l.point_location(x).is_some(), "vertex {x} not hosted");
    }
    assert_eq!(Embedding::new(&l, &v).unwrap().outside_count(), 0);
    // Kept volume covers the enclosed volume.
    let kept = l.cells().len() as f64 * p.cell.powi(3);
    assert!(kept >= enclosed_volume(&v, &t));
    let cells: HashSet<[i32; 3]> = l.cells().iter().copied().collect();
    for c in l.cells() {
        // No kept cube lies entirely outside the sphere's ball.
        let lo = p.origin + V::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2])) * p.cell;
        let nearest = centre.zip_zip_map(&lo, &(lo + V::repeat(p.cell)), |x, a, b| x.clamp(a, b));
        assert!(
            (nearest - centre).norm() <= r * 1.000_001,
            "cube {c:?} outside"
        );
    }
    // Every cube whose centre is well inside is kept.
    for i in -5..6 {
        for j in -5..6 {
            for k in -5..6 {
                let mid = p.origin
                    + (V::new(f64::from(i), f64::from(j), f64::from(k)).add_scalar(0.5)) * p.cell;
                if (mid - centre).norm() < 0.9 * r {
                    assert!(
                        cells.contains(&[i, j, k]),
                        "inner cube {:?} missing",
                        [i, j, k]
                    );
                }
            }
        }
    }
}

#[test]
fn box_keeps_exactly_the_overlapping_cubes() {
    let lo = V::new(0.013, 0.021, -0.017);
    let hi = V::new(0.071, 0.052, 0.033);
    let c = |i: usize| {
        V::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    };
    let v: Vec<V> = (0..8).map(c).collect();
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let t: Vec<[u32; 3]> = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    let p = params();
    let l = Lattice::from_surface(p, &v, &t).unwrap();
    let cell = |x: f64, o: f64| ((x - o) / p.cell).floor() as i32;
    let mut expect = HashSet::new();
    for i in cell(lo.x, p.origin.x)..=cell(hi.x, p.origin.x) {
        for j in cell(lo.y, p.origin.y)..=cell(hi.y, p.origin.y) {
            for k in cell(lo.z, p.origin.z)..=cell(hi.z, p.origin.z) {
                expect.insert([i, j, k]);
            }
        }
    }
    let got: HashSet<[i32; 3]> = l.cells().iter().copied().collect();
    assert_eq!(got, expect);
}

#[test]
fn bad_inputs_give_clear_errors() {
    let p = params();
    assert!(matches!(
        Lattice::from_cells(p, &[]),
        Err(LatticeError::Empty(_))
    ));
    assert!(matches!(
        Lattice::from_surface(p, &[V::zeros()], &[[0, 1, 2]]),
        Err(LatticeError::InvalidSurface(_))
    ));
    assert!(matches!(
        Lattice::from_surface(p, &[], &[]),
        Err(LatticeError::InvalidSurface(_))
    ));
    let bad = LatticeParams { cell: -1.0, ..p };
    assert!(matches!(
        Lattice::from_cells(bad, &[[0, 0, 0]]),
        Err(LatticeError::InvalidParams(_))
    ));
}
