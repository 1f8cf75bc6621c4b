//! Rotation extraction per call: random rotations with moderate stretch (σ ∈ [0.7, 1.4]),
//! cold; and a warm-started sequence of 1000 slowly rotating gradients (per sequence; divide
//! by 1000 for per call).

use cosurg_sim_fem::polar::{ByersXu, MullerIterative};
use cosurg_sim_fem::{PolarMethod, RotationExtractor, WarmStart};
use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() {
    divan::main();
}

const METHODS: [&str; 4] = ["byers_xu", "svd", "muller", "shape_matching"];

fn method(name: &str) -> PolarMethod {
    match name {
        "byers_xu" => PolarMethod::ByersXu(ByersXu::default()),
        "svd" => PolarMethod::Svd,
        "muller" => PolarMethod::Muller(MullerIterative {
            tol: 1e-8,
            max_iters: 100,
        }),
        _ => PolarMethod::ShapeMatching,
    }
}

fn random_f(rng: &mut ChaCha8Rng) -> Matrix3<f64> {
    let r = Rotation3::new(Vector3::new(
        rng.random_range(-2.0..2.0),
        rng.random_range(-2.0..2.0),
        rng.random_range(-2.0..2.0),
    ));
    let v = Rotation3::new(Vector3::new(
        rng.random_range(-2.0..2.0),
        rng.random_range(-2.0..2.0),
        rng.random_range(-2.0..2.0),
    ));
    let s = Vector3::new(
        rng.random_range(0.7..1.4),
        rng.random_range(0.7..1.4),
        rng.random_range(0.7..1.4),
    );
    r.into_inner() * v.into_inner() * Matrix3::from_diagonal(&s) * v.into_inner().transpose()
}

#[divan::bench(args = METHODS)]
fn random_cold(bencher: divan::Bencher, name: &str) {
    let m = method(name);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    bencher
        .with_inputs(|| random_f(&mut rng))
        .bench_local_refs(|f| m.extract(divan::black_box(f), None));
}

#[divan::bench(args = METHODS, sample_count = 30)]
fn warm_sequence_1000(bencher: divan::Bencher, name: &str) {
    let m = method(name);
    let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
    let seq: Vec<Matrix3<f64>> = (0..1000)
        .map(|k| {
            let t = k as f64 * 0.01;
            Rotation3::new(axis * t).into_inner()
                * Matrix3::from_diagonal(&Vector3::new(1.0 + 0.2 * (3.0 * t).sin(), 1.0, 0.9))
        })
        .collect();
    bencher.bench_local(|| {
        let mut w = WarmStart::default();
        let mut its = 0;
        for f in &seq {
            let r = m.extract(divan::black_box(f), Some(&w));
            w.rotation = Some(r.rotation);
            w.sigma_bounds = Some(r.sigma_bounds);
            its += r.iterations;
        }
        its
    });
}

/// Byers–Xu on four gradients at once ([`ByersXu::extract4`]): the warm sequence above
/// for four phase-shifted copies (per sequence of 1000 batches; divide by 4000 for per
/// gradient).
#[divan::bench(sample_count = 30)]
fn byers_xu_four_at_once_1000(bencher: divan::Bencher) {
    let m = ByersXu::default();
    let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
    let seq: Vec<[Matrix3<f64>; 4]> = (0..1000)
        .map(|k| {
            std::array::from_fn(|l| {
                let t = k as f64 * 0.01 + l as f64 * 0.37;
                Rotation3::new(axis * t).into_inner()
                    * Matrix3::from_diagonal(&Vector3::new(1.0 + 0.2 * (3.0 * t).sin(), 1.0, 0.9))
            })
        })
        .collect();
    bencher.bench_local(|| {
        let mut warm = [WarmStart::default(); 4];
        let mut its = 0;
        for f in &seq {
            let r = m.extract4(divan::black_box(f), &warm);
            for l in 0..4 {
                warm[l].rotation = Some(r[l].rotation);
                warm[l].sigma_bounds = Some(r[l].sigma_bounds);
                its += r[l].iterations;
            }
        }
        its
    });
}
