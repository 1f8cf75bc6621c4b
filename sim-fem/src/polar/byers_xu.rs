//! Byers & Xu's scaled Newton iteration, one gradient at a time or four at once.
//!
//! The iteration is written once, over [`Lanes`]: `f64` for one gradient, [`F64x4`] for
//! four. Every operation is an elementwise IEEE one (no fused multiply-add, no reordered
//! sums), so each lane of a batch computes the bits the one-gradient path computes for
//! the same input: which gradients happen to share a batch never changes a rotation, and
//! sites that batch differently (or not at all, on several threads) stay identical. The
//! test `batch_equals_one_at_a_time_bit_for_bit` checks it.
//!
//! Why four at once: the iteration is a chain of dependent divisions and square roots
//! whose latency, not their count, set its cost (about 90 ns per warm extraction,
//! `benches/polar.rs`); four independent chains in one vector fill those pipelines.

use nalgebra::Matrix3;

use crate::lanes::{F64x4, Lanes};

use super::{
    PolarResult, RotationExtractor, WarmStart, degenerate, flip_least_stretch, non_finite,
    svd_fallback,
};

/// Byers & Xu (2008) scaled Newton iteration for the polar factor
/// `X₀ = F`, `X_{k+1} = ½(ζ_k X_k + ζ_k⁻¹ X_k⁻ᵀ)`, with `ζ₀ = 1/√(ab)`,
/// `ζ₁ = √(2√(ab)/(a+b))`, `ζ_k = √(2/(ζ_{k−1} + ζ_{k−1}⁻¹))`.
///
/// Cold bounds: `a = 1/‖F⁻¹‖_F = |det F| / ‖cof F‖_F ≤ σ_min`, `b = ‖F‖_F ≥ σ_max`.
/// Stops when `‖X_{k+1} − X_k‖_F < tol`; near convergence Newton is quadratic,
/// `‖X_{k+1} − Q‖ ≈ ½‖X_k − Q‖² ≈ ½‖X_{k+1} − X_k‖²`, so the returned factor is
/// orthogonal to about `tol²` (plus rounding).
#[derive(Clone, Copy, Debug)]
pub struct ByersXu {
    /// Stopping threshold on `‖X_{k+1} − X_k‖_F` (dimensionless).
    pub tol: f64,
    /// Iteration cap (Byers–Xu converge in ≤ 9 iterations in double precision).
    pub max_iters: u32,
}

impl Default for ByersXu {
    fn default() -> Self {
        Self {
            tol: 1e-8,
            max_iters: 20,
        }
    }
}

/// A 3×3 matrix, column-major (nalgebra's order).
type M3<L> = [L; 9];

#[inline(always)]
fn cross<L: Lanes>(a: &[L], b: &[L]) -> [L; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `(cof M, det M)` with `cof M = det(M) M⁻ᵀ`: columns `m1×m2, m2×m0, m0×m1`.
#[inline(always)]
fn cofactor<L: Lanes>(m: &M3<L>) -> (M3<L>, L) {
    let (c0, c1, c2) = (&m[0..3], &m[3..6], &m[6..9]);
    let (k0, k1, k2) = (cross(c1, c2), cross(c2, c0), cross(c0, c1));
    let det = c0[0] * k0[0] + c0[1] * k0[1] + c0[2] * k0[2];
    (
        [
            k0[0], k0[1], k0[2], k1[0], k1[1], k1[2], k2[0], k2[1], k2[2],
        ],
        det,
    )
}

/// `Σ m_k²` in storage order.
#[inline(always)]
fn norm_sq<L: Lanes>(m: &M3<L>) -> L {
    let mut s = m[0] * m[0];
    for v in &m[1..] {
        s = s + *v * *v;
    }
    s
}

/// The iteration on every lane from `f` (`det f > 0` on every lane) with bounds `(a, b)`
/// where `warm` holds them, cold ones elsewhere. Returns the orthogonal factors, the
/// bounds used and each lane's iteration count; a lane stops (keeps its `X`) at the first
/// step below `tol`, the others go on.
#[inline(always)]
fn iterate<L: Lanes>(
    p: &ByersXu,
    f: &M3<L>,
    warm: &[Option<(f64, f64)>],
) -> (M3<L>, L, L, [u32; 4]) {
    let (cof, det) = cofactor(f);
    let (cold_a, cold_b) = (det.abs().div(norm_sq(&cof).sqrt()), norm_sq(f).sqrt());
    let (mut a, mut b) = (cold_a, cold_b);
    for (l, w) in warm.iter().enumerate().take(L::N) {
        if let Some((wa, wb)) = *w
            && wa > 0.0
            && wb >= wa
            && wb.is_finite()
        {
            a.set_lane(l, wa);
            b.set_lane(l, wb);
        }
    }
    let (half, one, two) = (L::splat(0.5), L::splat(1.0), L::splat(2.0));
    let mut x = *f;
    let inv_det = one.div(det);
    let mut xinvt = cof.map(|c| c * inv_det);
    let mut zeta = one.div((a * b).sqrt());
    let tol_sq = p.tol * p.tol;
    let mut iterations = [0u32; 4];
    let mut active = [false; 4];
    active[..L::N].fill(true);
    for k in 0..p.max_iters {
        let (s, t) = (half * zeta, half.div(zeta));
        let xn: M3<L> = std::array::from_fn(|i| x[i] * s + xinvt[i] * t);
        let d: M3<L> = std::array::from_fn(|i| xn[i] - x[i]);
        let diff_sq = norm_sq(&d);
        x = std::array::from_fn(|i| xn[i].select(&active, x[i]));
        for l in 0..L::N {
            if active[l] {
                iterations[l] = k + 1;
                active[l] = diff_sq.lane(l) >= tol_sq;
            }
        }
        if !active.iter().any(|a| *a) {
            break;
        }
        zeta = if k == 0 {
            (two * (a * b).sqrt()).div(a + b).sqrt()
        } else {
            two.div(zeta + one.div(zeta)).sqrt()
        };
        let (c, d) = cofactor(&x);
        let inv_d = one.div(d);
        xinvt = c.map(|ci| ci * inv_d);
    }
    (x, a, b, iterations)
}

fn to_m3(m: &Matrix3<f64>) -> M3<f64> {
    std::array::from_fn(|i| m[i])
}

fn from_m3(m: &M3<f64>) -> Matrix3<f64> {
    Matrix3::from_column_slice(m)
}

/// Whether the iteration alone gives `f`'s rotation: finite, not degenerate, not
/// inverted (the other cases take [`ByersXu::extract`]'s special paths).
fn regular(f: &Matrix3<f64>) -> bool {
    if !f.iter().all(|v| v.is_finite()) {
        return false;
    }
    let det = f.determinant();
    det > 0.0 && !degenerate(f, det)
}

impl ByersXu {
    /// [`RotationExtractor::extract`] of four gradients at once, each with its own
    /// warm-start bounds: bit for bit the four results one at a time would give (see
    /// the module documentation).
    pub fn extract4(&self, f: &[Matrix3<f64>; 4], warm: &[WarmStart; 4]) -> [PolarResult; 4] {
        if !f.iter().all(regular) {
            return std::array::from_fn(|l| self.extract(&f[l], Some(&warm[l])));
        }
        let fx: M3<F64x4> = std::array::from_fn(|i| F64x4(std::array::from_fn(|l| f[l][i])));
        let bounds = warm.map(|w| w.sigma_bounds);
        let (x, a, b, its) = self.iterate4(&fx, &bounds);
        std::array::from_fn(|l| PolarResult {
            rotation: Matrix3::from_fn(|r, c| x[3 * c + r].0[l]),
            iterations: its[l],
            inverted: false,
            sigma_bounds: (a.0[l], b.0[l]),
        })
    }

    fn iterate4(
        &self,
        f: &M3<F64x4>,
        warm: &[Option<(f64, f64)>; 4],
    ) -> (M3<F64x4>, F64x4, F64x4, [u32; 4]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { self.iterate4_avx(f, warm) };
        }
        iterate(self, f, warm)
    }

    /// [`iterate`] compiled for AVX: the same operations on 4-lane registers.
    ///
    /// # Safety
    /// The CPU must support AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn iterate4_avx(
        &self,
        f: &M3<F64x4>,
        warm: &[Option<(f64, f64)>; 4],
    ) -> (M3<F64x4>, F64x4, F64x4, [u32; 4]) {
        iterate(self, f, warm)
    }
}

impl RotationExtractor for ByersXu {
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult {
        if !f.iter().all(|v| v.is_finite()) {
            return non_finite(warm);
        }
        let det = f.determinant();
        if degenerate(f, det) {
            return svd_fallback(f, det);
        }
        let bounds = warm.and_then(|w| w.sigma_bounds);
        let (x, a, b, its) = iterate(self, &to_m3(f), &[bounds]);
        let x = from_m3(&x);
        let inverted = det < 0.0;
        let rotation = if inverted {
            flip_least_stretch(&x, f)
        } else {
            x
        };
        PolarResult {
            rotation,
            iterations: its[0],
            inverted,
            sigma_bounds: (a, b),
        }
    }
    fn name(&self) -> &'static str {
        "byers_xu"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use rand::{Rng, SeedableRng};

    fn random_f(rng: &mut rand_chacha::ChaCha8Rng, stretch: f64) -> Matrix3<f64> {
        let mut axis = || {
            Vector3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(-2.0..2.0),
            )
        };
        let (r, v) = (Rotation3::new(axis()), Rotation3::new(axis()));
        let s = Vector3::from_fn(|_, _| rng.random_range(1.0 - stretch..1.0 + stretch));
        r.into_inner() * v.into_inner() * Matrix3::from_diagonal(&s) * v.into_inner().transpose()
    }

    #[test]
    fn batch_equals_one_at_a_time_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let p = ByersXu {
            tol: 1e-6,
            max_iters: 20,
        };
        let mut mixed = 0;
        for round in 0..500 {
            // Stretches from nearly rigid to strongly deformed, so that lanes stop after
            // different iteration counts; some lanes warm, some cold.
            let f: [Matrix3<f64>; 4] =
                std::array::from_fn(|l| random_f(&mut rng, [0.01, 0.1, 0.3, 0.6][l]));
            let bounds: [Option<(f64, f64)>; 4] = std::array::from_fn(|l| {
                (round % 2 == l % 2)
                    .then(|| (rng.random_range(0.5..0.9), rng.random_range(1.1..1.6)))
            });
            let warm = bounds.map(|b| WarmStart {
                rotation: None,
                sigma_bounds: b,
            });
            let batch = p.extract4(&f, &warm);
            if batch.iter().any(|b| b.iterations != batch[0].iterations) {
                mixed += 1;
            }
            for l in 0..4 {
                let one = p.extract(&f[l], Some(&warm[l]));
                assert_eq!(
                    batch[l].iterations, one.iterations,
                    "round {round} lane {l}"
                );
                assert_eq!(batch[l].sigma_bounds, one.sigma_bounds);
                for (x, y) in batch[l].rotation.iter().zip(one.rotation.iter()) {
                    assert_eq!(x.to_bits(), y.to_bits(), "round {round} lane {l}");
                }
            }
        }
        // The per-lane stop was exercised: most batches mix iteration counts.
        assert!(mixed > 250, "{mixed} of 500 batches mixed iteration counts");
    }

    #[test]
    fn batch_with_an_irregular_lane_takes_the_special_paths() {
        let p = ByersXu::default();
        let rigid = Rotation3::new(Vector3::new(0.3, -0.2, 0.1)).into_inner();
        let inverted = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -0.5));
        let nan = Matrix3::from_element(f64::NAN);
        let flat = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0));
        // The non-finite lane keeps its warm start's rotation, as one at a time.
        let previous = Rotation3::new(Vector3::new(0.0, 0.4, 0.0)).into_inner();
        let mut warm = [WarmStart::default(); 4];
        warm[2].rotation = Some(previous);
        let out = p.extract4(&[rigid, inverted, nan, flat], &warm);
        assert!((out[0].rotation - rigid).norm() < 1e-12);
        assert!(out[1].inverted && (out[1].rotation.determinant() - 1.0).abs() < 1e-12);
        assert_eq!(out[2].rotation, previous);
        assert!(out[3].inverted);
        for o in &out {
            assert!((o.rotation.determinant() - 1.0).abs() < 1e-9);
        }
    }
}
