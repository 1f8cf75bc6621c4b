use nalgebra::{Matrix3, Matrix6, Vector6};

use super::*;

#[test]
fn closest_point_regions() {
    let (a, b, c) = (V3::zeros(), V3::x(), V3::y());
    let (p, w) = closest_point_triangle(&V3::new(0.2, 0.2, 1.0), &a, &b, &c);
    assert!((p - V3::new(0.2, 0.2, 0.0)).norm() < 1e-15);
    assert!((w[0] - 0.6).abs() < 1e-15);
    let (p, w) = closest_point_triangle(&V3::new(2.0, -1.0, 0.5), &a, &b, &c);
    assert_eq!(p, b);
    assert_eq!(w, [0.0, 1.0, 0.0]);
    let (p, w) = closest_point_triangle(&V3::new(1.0, 1.0, 0.0), &a, &b, &c);
    assert!((p - V3::new(0.5, 0.5, 0.0)).norm() < 1e-15);
    assert!((w[1] - 0.5).abs() < 1e-15 && (w[2] - 0.5).abs() < 1e-15);
}

#[test]
fn local_model_is_symmetric() {
    let k = Matrix3::new(2.0, 0.5, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 3.0);
    let r = V3::new(0.01, -0.02, 0.03);
    let rx = r.cross_matrix();
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-k));
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(k * rx));
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-(rx * k)));
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&(rx * k * rx));
    assert!((m - m.transpose()).norm() < 1e-15);
    // Finite check: F = −K (δ + θ × r), τ = r × F.
    let th = V3::new(1e-3, -2e-3, 5e-4);
    let d = V3::new(1e-4, 0.0, -2e-4);
    let f = -(k * (d + th.cross(&r)));
    let tau = r.cross(&f);
    let pred = m * Vector6::new(d.x, d.y, d.z, th.x, th.y, th.z);
    assert!((pred.fixed_rows::<3>(0) - f).norm() < 1e-15);
    assert!((pred.fixed_rows::<3>(3) - tau).norm() < 1e-15);
}
