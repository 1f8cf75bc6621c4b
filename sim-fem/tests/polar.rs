//! Polar factors against the SVD reference on random matrices (seeded), incl. near-singular
//! and inverted ones; every method must return a proper rotation.

use cosurg_sim_fem::polar::{ByersXu, MullerIterative, ShapeMatching, svd_rotation};
use cosurg_sim_fem::{RotationExtractor, WarmStart, rotation_threshold_sq, rotations_within};
use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_rotation(rng: &mut ChaCha8Rng) -> Matrix3<f64> {
    let axis = Vector3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    );
    let angle = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
    Rotation3::new(axis.normalize() * angle).into_inner()
}

/// `U diag(s) Vᵀ` with random rotations U, V; `sign` flips the last singular value
/// (inverted element). Singular values are distinct so the reference is unique.
fn random_f(rng: &mut ChaCha8Rng, kind: usize) -> Matrix3<f64> {
    let u = random_rotation(rng);
    let v = random_rotation(rng);
    let mut s = match kind {
        // moderate stretch
        0 => [
            rng.random_range(0.5..2.0),
            rng.random_range(0.5..2.0),
            rng.random_range(0.5..2.0),
        ],
        // near-singular: one singular value in [1e-8, 1e-3]
        1 => [
            rng.random_range(0.5..2.0),
            rng.random_range(0.5..2.0),
            10f64.powf(rng.random_range(-8.0..-3.0)),
        ],
        // strongly anisotropic
        _ => [
            rng.random_range(0.05..20.0),
            rng.random_range(0.05..20.0),
            rng.random_range(0.05..20.0),
        ],
    };
    s.sort_by(|a, b| b.partial_cmp(a).unwrap());
    // keep a gap between the two smallest (uniqueness of the inverted reference)
    if s[1] < 1.2 * s[2] {
        s[1] = 1.2 * s[2];
    }
    u * Matrix3::from_diagonal(&Vector3::new(s[0], s[1], s[2])) * v.transpose()
}

fn check(method: &dyn RotationExtractor, n: usize, tol: f64, seed: u64) -> (f64, u32) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut worst: f64 = 0.0;
    let mut max_it = 0;
    for i in 0..n {
        let mut f = random_f(&mut rng, i % 3);
        if i % 2 == 1 {
            // invert: reflect through a random plane
            let d = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            f = (Matrix3::identity() - 2.0 * d * d.transpose()) * f;
        }
        let reference = svd_rotation(&f);
        let r = method.extract(&f, None);
        let det = r.rotation.determinant();
        assert!(
            (det - 1.0).abs() < 1e-9,
            "{}: det {det} for F = {f}",
            method.name()
        );
        let orth = (r.rotation.transpose() * r.rotation - Matrix3::identity()).norm();
        assert!(orth < 1e-9, "{}: not orthogonal {orth}", method.name());
        let err = (r.rotation - reference).norm();
        worst = worst.max(err);
        max_it = max_it.max(r.iterations);
        assert!(
            err < tol,
            "{}: |R − R_svd|_F = {err:e} (case {i}, inverted {}), F = {f}",
            method.name(),
            f.determinant() < 0.0
        );
    }
    (worst, max_it)
}

#[test]
fn byers_xu_matches_svd_including_inverted_and_near_singular() {
    // Tolerance: 1e-8 on ‖R − R_svd‖_F. Near-singular inputs have condition ≤ 2e8, so the
    // SVD reference itself is accurate to ≈ 1e-16 · 2e8 only in the least-stretch direction.
    let (worst, it) = check(&ByersXu::default(), 3000, 1e-7, 1);
    assert!(it <= 12, "Byers–Xu needed {it} iterations");
    eprintln!("byers_xu worst {worst:e}, max iterations {it}");
}

#[test]
fn shape_matching_matches_svd() {
    // Eigen of FᵀF squares the condition number: near-singular cases lose accuracy
    // in the flipped direction (cond² ≈ 4e16), hence a looser bound here.
    let (worst, _) = check(&ShapeMatching, 3000, 1e-4, 2);
    eprintln!("shape matching worst {worst:e}");
}

#[test]
fn muller_matches_svd() {
    let m = MullerIterative {
        tol: 1e-13,
        max_iters: 2000,
    };
    let (worst, it) = check(&m, 3000, 1e-6, 3);
    eprintln!("muller worst {worst:e}, max iterations {it}");
}

#[test]
fn degenerate_and_non_finite_inputs_give_proper_rotations() {
    let cases = [
        Matrix3::zeros(),
        Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0), // flattened
        Matrix3::new(1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 1.0, 1.0, 1.0), // rank 2
        Matrix3::new(1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0), // rank 1
        Matrix3::from_element(f64::NAN),
    ];
    let methods: [&dyn RotationExtractor; 4] = [
        &ByersXu::default(),
        &cosurg_sim_fem::SvdPolar,
        &MullerIterative::default(),
        &ShapeMatching,
    ];
    for f in &cases {
        for m in methods {
            let r = m.extract(f, None).rotation;
            assert!(r.iter().all(|v| v.is_finite()), "{}", m.name());
            assert!((r.determinant() - 1.0).abs() < 1e-9, "{}: {f}", m.name());
        }
    }
    // A flattened element is rotated back as identity when it is the plain projection.
    let r = ByersXu::default().extract(&cases[1], None).rotation;
    assert!((r - Matrix3::identity()).norm() < 1e-12);
}

#[test]
fn warm_start_gives_same_rotation() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let bx = ByersXu::default();
    let mu = MullerIterative::default();
    let mut prev_b: Option<(f64, f64)> = None;
    let mut prev_r: Option<Matrix3<f64>> = None;
    let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
    let (mut warm_it, mut cold_it) = (0, 0);
    for k in 0..200 {
        let t = k as f64 * 0.01;
        let stretch = Matrix3::from_diagonal(&Vector3::new(1.0 + 0.2 * t.sin(), 1.0, 0.9));
        let f = Rotation3::new(axis * t * 3.0).into_inner() * stretch
            + Matrix3::from_fn(|_, _| rng.random_range(-1e-3..1e-3));
        let reference = svd_rotation(&f);
        let w = WarmStart {
            rotation: prev_r,
            sigma_bounds: prev_b,
        };
        let rb = bx.extract(&f, Some(&w));
        let rm = mu.extract(&f, Some(&w));
        let rc = mu.extract(&f, None);
        assert!((rb.rotation - reference).norm() < 1e-9);
        assert!((rm.rotation - reference).norm() < 1e-8);
        warm_it += rm.iterations;
        cold_it += rc.iterations;
        prev_b = Some(rb.sigma_bounds);
        prev_r = Some(rb.rotation);
    }
    eprintln!("Müller iterations over 200 frames: warm {warm_it}, cold {cold_it}");
    // Müller's iteration converges linearly; from a 0.03 rad-old rotation it is not
    // faster than from the Gram–Schmidt frame here (numbers go to the report, no assert).
}

#[test]
fn rotation_threshold_matches_angle() {
    // ‖R_m − R_n‖²_F = 4(1 − cos θ) exactly for rotations differing by θ.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..500 {
        let rm = random_rotation(&mut rng);
        let theta: f64 = rng.random_range(0.0..3.0);
        let axis = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let rn = Rotation3::new(axis * theta).into_inner() * rm;
        let lhs = (rm - rn).norm_squared();
        assert!((lhs - rotation_threshold_sq(theta)).abs() < 1e-12);
        assert!(rotations_within(&rm, &rn, theta * 1.001 + 1e-9));
        if theta > 1e-3 {
            assert!(!rotations_within(&rm, &rn, theta * 0.999));
        }
    }
}
