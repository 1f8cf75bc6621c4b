//! CG's vector updates and reductions over the unknowns as flat `f64`s, in four running
//! sums.
//!
//! Why: `perf` over 20 s of the 1.33 cm organ (Jacobi-PCG, 30 iterations a step, one
//! thread, 2026-11-28) put 15 % of the step in [`super::pcg_with`]'s own loops, against
//! 30 % in its sparse products. Over `Vector3`s each reduction was one chain of dependent
//! additions (one per node, four cycles each) and the updates scalar code. Here a vector
//! field is read as its `3 n` components, and a reduction keeps four sums, component `i`
//! going to sum `i mod 4`, added as `(s₀ + s₁) + (s₂ + s₃)` at the end: a fixed order
//! (plain multiplies and adds, no `mul_add`), so every machine computes the same bits
//! (test `sums_keep_their_fixed_order`). The step went from 1.50 to 1.37 ms (medians of
//! four interleaved runs; docs/RESULTS.md).

use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// The components of a vector field, `x₀ y₀ z₀ x₁ …`.
pub(super) fn flat(v: &[V3]) -> &[f64] {
    bytemuck::cast_slice(v)
}

/// [`flat`], mutable.
pub(super) fn flat_mut(v: &mut [V3]) -> &mut [f64] {
    bytemuck::cast_slice_mut(v)
}

/// Lanes of the running sums.
const LANES: usize = 4;

/// Combines running sums in a fixed order.
#[inline(always)]
fn total(s: [f64; LANES]) -> f64 {
    (s[0] + s[1]) + (s[2] + s[3])
}

/// Calls `f(i, l)` for every component `i < n` with its running sum `l`: `i mod 4` over
/// the whole groups of four, then the rest from lane 0 (the order [`dot`] keeps too).
#[inline(always)]
fn for_each_lane(n: usize, mut f: impl FnMut(usize, usize)) {
    let whole = n - n % LANES;
    for c in (0..whole).step_by(LANES) {
        for l in 0..LANES {
            f(c + l, l);
        }
    }
    for i in whole..n {
        f(i, i - whole);
    }
}

/// `Σ aᵢ bᵢ`.
pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len(), "dot of equal lengths");
    let mut s = [0.0; LANES];
    let (ac, at) = a.as_chunks::<LANES>();
    let (bc, bt) = b.as_chunks::<LANES>();
    for (ai, bi) in ac.iter().zip(bc) {
        for l in 0..LANES {
            s[l] += ai[l] * bi[l];
        }
    }
    for (l, (ai, bi)) in at.iter().zip(bt).enumerate() {
        s[l] += ai * bi;
    }
    total(s)
}

/// One Jacobi-PCG iteration's update after its product `ap = A p` and step `alpha`:
/// `x += α p`, `r −= α ap`, `z = d ∘ r`; returns `(rᵀr, rᵀz)`.
pub(super) fn update_jacobi(
    x: &mut [f64],
    r: &mut [f64],
    z: &mut [f64],
    p: &[f64],
    ap: &[f64],
    inv_diag: &[f64],
    alpha: f64,
) -> (f64, f64) {
    let n = x.len();
    assert!(
        [r.len(), z.len(), p.len(), ap.len(), inv_diag.len()]
            .iter()
            .all(|&l| l == n),
        "vectors of one length"
    );
    let (mut rr, mut rz) = ([0.0; LANES], [0.0; LANES]);
    for_each_lane(n, |i, l| {
        x[i] += p[i] * alpha;
        r[i] -= ap[i] * alpha;
        z[i] = r[i] * inv_diag[i];
        rr[l] += r[i] * r[i];
        rz[l] += r[i] * z[i];
    });
    (total(rr), total(rz))
}

/// `x += α p`, `r −= α ap`; returns `rᵀr` (the update with another preconditioner).
pub(super) fn update(x: &mut [f64], r: &mut [f64], p: &[f64], ap: &[f64], alpha: f64) -> f64 {
    let n = x.len();
    assert!(
        [r.len(), p.len(), ap.len()].iter().all(|&l| l == n),
        "vectors of one length"
    );
    let mut rr = [0.0; LANES];
    for_each_lane(n, |i, l| {
        x[i] += p[i] * alpha;
        r[i] -= ap[i] * alpha;
        rr[l] += r[i] * r[i];
    });
    total(rr)
}

/// `p = z + β p`.
pub(super) fn next_direction(p: &mut [f64], z: &[f64], beta: f64) {
    assert_eq!(p.len(), z.len(), "vectors of one length");
    for (pi, zi) in p.iter_mut().zip(z) {
        *pi = *zi + *pi * beta;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [−1, 1) of mixed magnitudes (a splitmix64 stream).
    fn values(seed: u64, n: usize) -> Vec<f64> {
        let mut s = seed;
        (0..n)
            .map(|i| {
                s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = s;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                let unit = (z >> 11) as f64 / (1u64 << 53) as f64;
                (2.0 * unit - 1.0) * 10f64.powi((i % 7) as i32 - 3)
            })
            .collect()
    }

    /// `Σ aᵢ bᵢ` compensated (each product split exactly by `mul_add`, Neumaier sums):
    /// the reference the four running sums are held to.
    fn dot_reference(a: &[f64], b: &[f64]) -> f64 {
        let (mut sum, mut carry) = (0.0f64, 0.0f64);
        let mut add = |v: f64| {
            let t = sum + v;
            carry += if sum.abs() >= v.abs() {
                (sum - t) + v
            } else {
                (v - t) + sum
            };
            sum = t;
        };
        for (x, y) in a.iter().zip(b) {
            let p = x * y;
            add(p);
            add(x.mul_add(*y, -p));
        }
        sum + carry
    }

    #[test]
    fn sums_match_a_compensated_reference_at_every_remainder() {
        for n in [0, 1, 2, 3, 4, 5, 7, 8, 33, 3 * 1198] {
            let (a, b) = (values(1, n), values(2, n));
            let scale: f64 = a.iter().zip(&b).map(|(x, y)| (x * y).abs()).sum();
            let err = (dot(&a, &b) - dot_reference(&a, &b)).abs();
            // Recursive summation's bound, n ε Σ|aᵢ bᵢ| (ε = 2⁻⁵³), with n ≥ 1.
            assert!(
                err <= n.max(1) as f64 * f64::EPSILON / 2.0 * scale,
                "n {n}: off by {err:e} (scale {scale:e})"
            );
        }
    }

    /// The sums' order, bit for bit, against the order written out: values where the
    /// order matters (1 + 2⁻⁵³ rounds to 1, so small terms added one by one to a large
    /// one vanish, and summed among themselves first they count).
    #[test]
    fn sums_keep_their_fixed_order() {
        let tiny = f64::EPSILON / 2.0;
        for n in [4, 7, 8, 12, 4 * 9 + 3] {
            let a: Vec<f64> = (0..n)
                .map(|i| if i % 4 == 0 { 1.0 } else { tiny })
                .collect();
            let ones = vec![1.0; n];
            let mut lanes = [0.0f64; 4];
            let whole = n - n % 4;
            for i in 0..whole {
                lanes[i % 4] += a[i];
            }
            for i in whole..n {
                lanes[i - whole] += a[i];
            }
            let want = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
            let in_turn: f64 = a.iter().sum();
            assert_ne!(want.to_bits(), in_turn.to_bits(), "n {n}: the order shows");
            assert_eq!(dot(&a, &ones).to_bits(), want.to_bits(), "n {n}");
            let (mut x, mut r, mut z) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            // r = 0 − (−a)·1 = a, z = r: rᵀr and rᵀz are Σ aᵢ² in the same order.
            let minus_a: Vec<f64> = a.iter().map(|v| -v).collect();
            let (rr, rz) = update_jacobi(&mut x, &mut r, &mut z, &ones, &minus_a, &ones, 1.0);
            let mut sq = [0.0f64; 4];
            for i in 0..whole {
                sq[i % 4] += a[i] * a[i];
            }
            for i in whole..n {
                sq[i - whole] += a[i] * a[i];
            }
            let want_sq = (sq[0] + sq[1]) + (sq[2] + sq[3]);
            assert_eq!(
                (rr.to_bits(), rz.to_bits()),
                (want_sq.to_bits(), want_sq.to_bits())
            );
        }
    }

    #[test]
    fn updates_are_the_componentwise_formulas() {
        for n in [1, 6, 7, 3 * 401] {
            let (x0, r0, p, ap, d) = (
                values(3, n),
                values(4, n),
                values(5, n),
                values(6, n),
                values(7, n),
            );
            let alpha = 0.37;
            let (mut x, mut r, mut z) = (x0.clone(), r0.clone(), vec![0.0; n]);
            let (rr, rz) = update_jacobi(&mut x, &mut r, &mut z, &p, &ap, &d, alpha);
            for i in 0..n {
                assert_eq!(x[i].to_bits(), (x0[i] + p[i] * alpha).to_bits());
                assert_eq!(r[i].to_bits(), (r0[i] - ap[i] * alpha).to_bits());
                assert_eq!(z[i].to_bits(), (r[i] * d[i]).to_bits());
            }
            let tol = |s: &[f64], t: &[f64]| {
                n as f64 * f64::EPSILON * s.iter().zip(t).map(|(a, b)| (a * b).abs()).sum::<f64>()
            };
            assert!((rr - dot_reference(&r, &r)).abs() <= tol(&r, &r), "n {n}");
            assert!((rz - dot_reference(&r, &z)).abs() <= tol(&r, &z), "n {n}");
            let (mut x2, mut r2) = (x0.clone(), r0.clone());
            let rr2 = update(&mut x2, &mut r2, &p, &ap, alpha);
            assert_eq!(
                (x2, r2, rr2.to_bits()),
                (x.clone(), r.clone(), rr.to_bits())
            );
            let mut p2 = p.clone();
            next_direction(&mut p2, &z, 0.5);
            for i in 0..n {
                assert_eq!(p2[i].to_bits(), (z[i] + p[i] * 0.5).to_bits());
            }
        }
    }
}
