//! Unit tests of the system's private kernels.

use nalgebra::{Matrix3, Rotation3, SMatrix};

use super::V3;
use super::operator::{rotated_blocks, rotated_iso_blocks};
use crate::element::{Mat12, TetGeometry, lame};

/// Element stiffness the textbook way, `V Bᵀ D B` with Voigt strains (independent of
/// the gradient formula under test).
fn voigt_stiffness(g: &[V3; 4], v: f64, lambda: f64, mu: f64) -> Mat12 {
    let mut b = SMatrix::<f64, 6, 12>::zeros();
    for (a, ga) in g.iter().enumerate() {
        let (x, y, z) = (ga.x, ga.y, ga.z);
        let c = 3 * a;
        b[(0, c)] = x;
        b[(1, c + 1)] = y;
        b[(2, c + 2)] = z;
        b[(3, c)] = y;
        b[(3, c + 1)] = x;
        b[(4, c + 1)] = z;
        b[(4, c + 2)] = y;
        b[(5, c)] = z;
        b[(5, c + 2)] = x;
    }
    let mut d = SMatrix::<f64, 6, 6>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            d[(i, j)] = lambda;
        }
        d[(i, i)] += 2.0 * mu;
        d[(i + 3, i + 3)] = mu;
    }
    b.transpose() * d * b * v
}

#[test]
fn rotated_gradient_blocks_match_rotated_voigt_stiffness() {
    let x = [
        V3::new(0.0, 0.0, 0.0),
        V3::new(0.031, 0.002, -0.004),
        V3::new(0.003, 0.027, 0.001),
        V3::new(-0.002, 0.004, 0.022),
    ];
    let geom = TetGeometry::new(&x).unwrap();
    let (lambda, mu) = lame(1e5, 0.45);
    let k = voigt_stiffness(&geom.grads, geom.volume, lambda, mu);
    let r = *Rotation3::from_scaled_axis(V3::new(0.7, -1.1, 0.4)).matrix();
    let mut big_r = Mat12::zeros();
    for a in 0..4 {
        big_r.fixed_view_mut::<3, 3>(3 * a, 3 * a).copy_from(&r);
    }
    let expect = big_r * k * big_r.transpose();
    let mut got = [Matrix3::zeros(); 16];
    rotated_iso_blocks(&geom.grads, geom.volume, lambda, mu, Some(&r), &mut got);
    let via_blocks = rotated_blocks(&k, Some(&r));
    let scale = expect.amax();
    for a in 0..4 {
        for b in 0..4 {
            let e = expect.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
            assert!(
                (got[4 * a + b] - e).amax() < 1e-12 * scale,
                "iso block ({a},{b})"
            );
            assert!(
                (via_blocks[4 * a + b] - e).amax() < 1e-12 * scale,
                "block ({a},{b})"
            );
        }
    }
}
