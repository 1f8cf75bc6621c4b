//! CG's sparse product from the symmetric operator's upper blocks, copied once per step
//! into contiguous rows, for a matrix that outgrows the cache:
//! `(A p)_i = Σ_{j ≥ i} A_ij p_j + Σ_{j < i} A_jiᵀ p_j`, each stored block used twice, for
//! its own row and, transposed, for its column's row.
//!
//! Why: at 98,304 tets the step is bound by the bytes it streams from memory, not by its
//! arithmetic, and CG's product by full rows ([`BlockPattern::multiply_full`]) streams
//! every block twice (19 MB) every iteration, against 10 MB for the upper blocks. On
//! the 98,304-tet beam's pattern (`cargo bench -p cosurg-sim-fem --bench product`,
//! 2026-11-29, medians of three runs on a noisy machine) this product takes 448–463 µs
//! against 745–878 µs for the full rows, and its copy 0.79–1.0 ms against 2.4–2.8 ms for
//! the full-row copy. In the cache (12,288 tets) the upper rows gain nothing (55.9–98.2
//! µs against 54.9–61.0 µs for the full rows, the same runs); there the full rows stay
//! (below the size of
//! [`crate::prefetch::outgrows_cache`] this product is not used, so a smaller mesh steps
//! on the same bits as before).
//!
//! Why a copy: read in place, in the assembly's storage, where each row's lower slots
//! (unused by a symmetric assembly) lie between its upper blocks and the next row's,
//! the same vectorised product took 1.70 ms; the scalar in-place product
//! ([`BlockPattern::multiply_upper`]) takes 1.76–1.94 ms.
//!
//! **The transposed product.** A block is read as its three columns `c_k` (four lanes from
//! its `k`-th column's first entry; the last column's fourth lane masked to zero).
//! `A_ijᵀ p_i` is the three dot products `c_k · p_i`: multiplied lane-wise with
//! `[p_i, 0]`, then summed pairwise, `(l₀ + l₁) + (l₂ + l₃)`, where the fourth lane is the
//! next column's first entry times zero. Each row's transposed products gather in a
//! four-lane buffer of the column's row, which the row reads, adds its own sum to, and
//! zeroes when it is reached (a row's transposed products all fall on later rows).
//!
//! **Same bits on every machine**, as for the full-row product: the portable path does the
//! AVX path's IEEE operations in the same order, the zero-times-entry terms included (test
//! `avx_and_portable_upper_products_are_bit_identical`).

use std::sync::Mutex;

use nalgebra::{Matrix3, Vector3};

use super::BlockPattern;

type V3 = Vector3<f64>;

/// The upper blocks of a symmetric block matrix, row by row and contiguous, for
/// [`UpperRows::multiply`]: row `i`'s are `pat.upper_ptr[i]..pat.upper_ptr[i + 1]`, its
/// diagonal block first, in the columns `pat.upper_cols` of the [`BlockPattern`] it was
/// copied with (the pattern keeps the index, so that a copy is the blocks alone).
#[derive(Debug, Default)]
pub struct UpperRows {
    blocks: Vec<Matrix3<f64>>,
    /// Per part of a product ([`UpperRows::multiply_parts`]), the transposed products
    /// gathered for the rows from the part's first on (lane 3 is not read): all zero
    /// between products.
    sums: Mutex<Vec<Vec<[f64; 4]>>>,
}

impl Clone for UpperRows {
    fn clone(&self) -> Self {
        UpperRows {
            blocks: self.blocks.clone(),
            // All zero between products.
            sums: Mutex::default(),
        }
    }
}

impl UpperRows {
    /// The rows of `pat`'s upper blocks `upper` (slot-indexed, as
    /// [`BlockPattern::multiply_upper`] reads them), into this storage (reused).
    pub fn copy_from(&mut self, pat: &BlockPattern, upper: &[Matrix3<f64>]) {
        assert_eq!(
            upper.len(),
            pat.cols.len(),
            "one block per slot of the pattern"
        );
        self.blocks.clear();
        self.blocks.reserve(pat.upper_cols.len());
        for (i, &d) in pat.diag.iter().enumerate() {
            self.blocks.extend_from_slice(&upper[d..pat.row_ptr[i + 1]]);
        }
    }

    /// `out = A p`, vectorised where the CPU has AVX, with the same result bit for bit
    /// elsewhere.
    pub fn multiply(&self, pat: &BlockPattern, p: &[V3], out: &mut [V3]) {
        self.multiply_parts(pat, p, out, &[0, out.len()]);
    }

    /// [`UpperRows::multiply`] with the rows split at `node_start` (first 0, last the
    /// node count), each part on its own thread ([`crate::parallel::run_parts`]). A part
    /// gathers the transposed products that fall on later parts' rows in its own buffer;
    /// those are added to the later rows after all parts, in the parts' order, so that
    /// one split always gives the same bits (one part: those of [`UpperRows::multiply`]).
    pub fn multiply_parts(
        &self,
        pat: &BlockPattern,
        p: &[V3],
        out: &mut [V3],
        node_start: &[usize],
    ) {
        let n = pat.num_rows();
        assert!(
            p.len() == n && out.len() == n && self.blocks.len() == pat.upper_cols.len(),
            "vectors of the pattern's {n} nodes, blocks copied with it"
        );
        assert!(
            node_start.first() == Some(&0)
                && node_start.last() == Some(&n)
                && node_start.windows(2).all(|w| w[0] <= w[1]),
            "parts from 0 to {n}: {node_start:?}"
        );
        let parts = node_start.len() - 1;
        let mut sums = self.sums.lock().unwrap_or_else(|e| {
            // A product that panicked may have left sums behind: start from zero.
            let mut sums = e.into_inner();
            sums.clear();
            sums
        });
        sums.resize_with(parts, Vec::new);
        for (k, s) in sums.iter_mut().enumerate() {
            s.resize(n - node_start[k], [0.0; 4]);
        }
        let outs = crate::parallel::split_ranges(out, node_start);
        let items: Vec<_> = outs.into_iter().zip(sums.iter_mut()).collect();
        let run = |k: usize, (out, sums): (&mut [V3], &mut Vec<[f64; 4]>)| {
            let first = node_start[k];
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx") {
                // SAFETY: the CPU has AVX (checked just above).
                unsafe { self.multiply_avx(pat, p, first, out, sums) };
                return;
            }
            self.multiply_portable(pat, p, first, out, sums);
        };
        if parts == 1 {
            // On the calling thread, without a parallel region.
            run(0, items.into_iter().next().expect("one part"));
            return;
        }
        crate::parallel::run_parts(items, run);
        // The transposed products that fell on later parts' rows.
        for k in 1..parts {
            for j in node_start[k]..node_start[k + 1] {
                for (q, s) in sums.iter_mut().enumerate().take(k) {
                    let t = std::mem::replace(&mut s[j - node_start[q]], [0.0; 4]);
                    out[j] += V3::new(t[0], t[1], t[2]);
                }
            }
        }
    }

    /// Rows `first..first + out.len()` of [`UpperRows::multiply`] in plain Rust (the
    /// reference order of operations), with `sums` the transposed products of rows
    /// `first..` (all zero on entry; the rows of `out` zero again on return).
    pub(crate) fn multiply_portable(
        &self,
        pat: &BlockPattern,
        p: &[V3],
        first: usize,
        out: &mut [V3],
        sums: &mut [[f64; 4]],
    ) {
        assert!(sums.len() + first == p.len() && out.len() <= sums.len());
        for (r, o) in out.iter_mut().enumerate() {
            let i = first + r;
            let (d, end) = (pat.upper_ptr[i] as usize, pat.upper_ptr[i + 1] as usize);
            let pi = &p[i];
            let (mut a0, mut a1, mut a2) = ([0.0; 3], [0.0; 3], [0.0; 3]);
            for s in d..end {
                let b = self.blocks[s].as_slice();
                let pj = &p[pat.upper_cols[s] as usize];
                for l in 0..3 {
                    a0[l] += b[l] * pj.x;
                    a1[l] += b[3 + l] * pj.y;
                    a2[l] += b[6 + l] * pj.z;
                }
                if s > d {
                    let t = &mut sums[pat.upper_cols[s] as usize - first];
                    for k in 0..3 {
                        // Lane 3: the next column's first entry (none for the last) times
                        // the zero lane of `[p_i, 0]`.
                        let next = if k < 2 { b[3 * k + 3] } else { 0.0 };
                        let c = &b[3 * k..3 * k + 3];
                        t[k] += (c[0] * pi.x + c[1] * pi.y) + (c[2] * pi.z + next * 0.0);
                    }
                }
            }
            let t = std::mem::replace(&mut sums[r], [0.0; 4]);
            *o = V3::from_fn(|l, _| t[l] + ((a0[l] + a1[l]) + a2[l]));
        }
    }

    /// [`UpperRows::multiply`] on 4-lane AVX vectors.
    ///
    /// # Safety
    /// The CPU must support AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    pub(crate) unsafe fn multiply_avx(
        &self,
        pat: &BlockPattern,
        p: &[V3],
        first: usize,
        out: &mut [V3],
        sums: &mut [[f64; 4]],
    ) {
        use std::arch::x86_64::{
            _mm256_add_pd, _mm256_broadcast_sd, _mm256_hadd_pd, _mm256_loadu_pd,
            _mm256_maskload_pd, _mm256_mul_pd, _mm256_permute2f128_pd, _mm256_set_epi64x,
            _mm256_setzero_pd, _mm256_storeu_pd,
        };
        assert!(sums.len() + first == p.len() && out.len() <= sums.len());
        // Lanes 0–2: a block's last column, or `[p_i, 0]`.
        let three = _mm256_set_epi64x(0, -1, -1, -1);
        for (r, o) in out.iter_mut().enumerate() {
            let i = first + r;
            let (d, end) = (pat.upper_ptr[i] as usize, pat.upper_ptr[i + 1] as usize);
            // SAFETY (every block below): `p`, `blocks` and `sums` are indexed within
            // bounds (a row's blocks, nodes of their columns); a block holds 9 f64: the
            // loads at 0 and 3 read four each, the masked load at 6 three (the masked
            // lane is not accessed); a `p` entry holds 3 f64, of which the masked load
            // reads three and each broadcast one; a `sums` entry holds four.
            unsafe {
                let pi = _mm256_maskload_pd(p[i].as_ptr(), three);
                let (mut a0, mut a1, mut a2) = (
                    _mm256_setzero_pd(),
                    _mm256_setzero_pd(),
                    _mm256_setzero_pd(),
                );
                for s in d..end {
                    let c = self.blocks[s].as_ptr();
                    let (c0, c1, c2) = (
                        _mm256_loadu_pd(c),
                        _mm256_loadu_pd(c.add(3)),
                        _mm256_maskload_pd(c.add(6), three),
                    );
                    let j = pat.upper_cols[s] as usize;
                    let pj = &p[j];
                    a0 = _mm256_add_pd(a0, _mm256_mul_pd(c0, _mm256_broadcast_sd(&pj.x)));
                    a1 = _mm256_add_pd(a1, _mm256_mul_pd(c1, _mm256_broadcast_sd(&pj.y)));
                    a2 = _mm256_add_pd(a2, _mm256_mul_pd(c2, _mm256_broadcast_sd(&pj.z)));
                    if s > d {
                        // [c0·l01, c1·l01, c0·l23, c1·l23] and [c2·l01, c2·l01, c2·l23, c2·l23]
                        let h01 = _mm256_hadd_pd(_mm256_mul_pd(c0, pi), _mm256_mul_pd(c1, pi));
                        let m2 = _mm256_mul_pd(c2, pi);
                        let h2 = _mm256_hadd_pd(m2, m2);
                        let dots = _mm256_add_pd(
                            _mm256_permute2f128_pd::<0x20>(h01, h2),
                            _mm256_permute2f128_pd::<0x31>(h01, h2),
                        );
                        let t = sums[j - first].as_mut_ptr();
                        _mm256_storeu_pd(t, _mm256_add_pd(_mm256_loadu_pd(t), dots));
                    }
                }
                let t = sums[r].as_mut_ptr();
                let row = _mm256_add_pd(_mm256_add_pd(a0, a1), a2);
                let mut lanes = [0.0; 4];
                _mm256_storeu_pd(lanes.as_mut_ptr(), _mm256_add_pd(_mm256_loadu_pd(t), row));
                _mm256_storeu_pd(t, _mm256_setzero_pd());
                *o = V3::new(lanes[0], lanes[1], lanes[2]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::full_product::tests::random_upper;

    #[test]
    fn upper_rows_product_equals_the_scalar_one_and_leaves_its_sums_zero() {
        for seed in 0..5 {
            let (pat, upper, p) = random_upper(seed);
            let n = p.len();
            let (mut want, mut got) = (vec![V3::zeros(); n], vec![V3::zeros(); n]);
            pat.multiply_upper(&upper, &p, &mut want);
            let mut rows = UpperRows::default();
            rows.copy_from(&pat, &upper);
            // Twice: the second product starts from the sums the first left.
            for _ in 0..2 {
                rows.multiply(&pat, &p, &mut got);
                for (w, g) in want.iter().zip(&got) {
                    assert!(
                        (w - g).norm() <= 1e-13 * (1.0 + w.norm()),
                        "{w} against {g}"
                    );
                }
                let sums = rows.sums.lock().unwrap();
                assert!(sums.iter().flatten().all(|s| *s == [0.0; 4]), "seed {seed}");
            }
        }
    }

    #[test]
    fn avx_and_portable_upper_products_are_bit_identical() {
        for seed in 0..6 {
            let (pat, mut upper, p) = random_upper(seed);
            if seed == 5 {
                // Infinite entries where the fourth lanes read them (each column's next
                // column's first entry): `inf · 0` is NaN in both paths, or in neither.
                for b in upper.iter_mut().step_by(3) {
                    b[(0, 1)] = f64::INFINITY;
                    b[(0, 2)] = f64::NEG_INFINITY;
                }
            }
            let n = p.len();
            let mut rows = UpperRows::default();
            rows.copy_from(&pat, &upper);
            // The whole product, and a part of it from row 17 on (its transposed products
            // for rows past 25 left in its buffer).
            for (first, end) in [(0, n), (17, 25)] {
                let mut portable = vec![V3::zeros(); end - first];
                let mut sums = vec![[0.0; 4]; n - first];
                rows.multiply_portable(&pat, &p, first, &mut portable, &mut sums);
                #[cfg(target_arch = "x86_64")]
                if !std::arch::is_x86_feature_detected!("avx") {
                    eprintln!("no AVX on this CPU: only the portable path was run");
                }
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx") {
                    let mut avx = vec![V3::zeros(); end - first];
                    let mut avx_sums = vec![[0.0; 4]; n - first];
                    // SAFETY: AVX detected.
                    unsafe { rows.multiply_avx(&pat, &p, first, &mut avx, &mut avx_sums) };
                    for (a, b) in avx.iter().zip(&portable) {
                        for k in 0..3 {
                            assert_eq!(a[k].to_bits(), b[k].to_bits(), "seed {seed}");
                        }
                    }
                    for (a, b) in avx_sums.iter().zip(&sums) {
                        for k in 0..3 {
                            assert_eq!(a[k].to_bits(), b[k].to_bits(), "seed {seed}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn split_upper_rows_products_equal_the_whole_one_and_repeat_their_bits() {
        for seed in 0..5 {
            let (pat, upper, p) = random_upper(seed);
            let n = p.len();
            let mut rows = UpperRows::default();
            rows.copy_from(&pat, &upper);
            let mut whole = vec![V3::zeros(); n];
            rows.multiply(&pat, &p, &mut whole);
            for split in [
                vec![0, 17, n],
                vec![0, 9, 30, n],
                vec![0, 9, 9, 30, n],
                vec![0, n],
            ] {
                let mut first = vec![V3::zeros(); n];
                rows.multiply_parts(&pat, &p, &mut first, &split);
                for (w, g) in whole.iter().zip(&first) {
                    assert!(
                        (w - g).norm() <= 1e-13 * (1.0 + w.norm()),
                        "{split:?}: {w} against {g}"
                    );
                }
                let mut again = vec![V3::zeros(); n];
                rows.multiply_parts(&pat, &p, &mut again, &split);
                assert_eq!(first, again, "{split:?}");
                if split.len() == 2 {
                    assert_eq!(first, whole, "one part is the whole product");
                }
                let sums = rows.sums.lock().unwrap();
                assert!(sums.iter().flatten().all(|s| *s == [0.0; 4]), "{split:?}");
            }
        }
    }
}
