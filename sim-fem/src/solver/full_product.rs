//! CG's sparse product by full rows: the symmetric operator's upper blocks copied once per
//! step into every row in full (the lower ones transposed), each block as its three
//! columns (nine f64, column-major), so that `(A p)_i = Σ_j A_ij p_j` is three lane-wise
//! multiply-adds per block with the broadcast components of `p_j`: a column is read as
//! four lanes starting at its first entry, the fourth lane (the next column's first entry,
//! or nothing for the last column: a masked load) accumulating a sum that is thrown away.
//!
//! Why nine and not twelve f64 per block (each column padded to four lanes, as until
//! 2026-11-28): the product streams the whole matrix every CG iteration and is bound by
//! that stream, not by its arithmetic. At 72 instead of 96 bytes per block the 5,184-tet
//! beam's matrix is 1.1 MB, about what the level-2 cache of this machine's cores holds
//! (1 MiB), against 1.47 MB (`benches/product.rs`, measured in docs/RESULTS.md).
//!
//! Why: the symmetric upper product ([`BlockPattern::multiply_upper`]) does 36 scalar
//! flops per stored block, half of them for the transposed product it scatters to another
//! row; it was 43 % of the instructions of a step of the 5,184-tet beam at dt 1 ms
//! (Jacobi-PCG, callgrind, 2026-11-27). On a CPU with AVX the full-row product takes
//! six vector operations (three multiplies, three adds) per block of the full matrix,
//! against 18 scalar flops per full block for the upper product.
//!
//! **Same bits on every machine.** Sites simulate the same scene from the same inputs
//! and compare states, so the product must not depend on the CPU: the AVX path and the
//! portable path do the same IEEE operations in the same order (multiplies then adds, no
//! fused multiply-add: per lane, three running sums, one per column, added at the end).
//! The test `avx_and_portable_full_products_are_bit_identical` checks it.

use nalgebra::{Matrix3, Vector3};

use super::BlockPattern;

type V3 = Vector3<f64>;

/// Slots ahead whose mirror block the full-row copy prefetches.
const COPY_AHEAD_SLOTS: usize = 8;

/// A 3×3 block as its columns, `[a_00, a_10, a_20, a_01, a_11, a_21, a_02, a_12, a_22]`.
pub type RowBlock = [f64; 9];

impl BlockPattern {
    /// The full rows of the symmetric matrix whose blocks on and above the diagonal are
    /// `upper` (slot-indexed as [`BlockPattern::multiply_upper`] reads them), into `out`
    /// (its storage reused): one block per slot of the pattern, below-diagonal slots
    /// taken from their mirror, transposed.
    pub fn full_rows_into(&self, upper: &[Matrix3<f64>], out: &mut Vec<RowBlock>) {
        // Every slot is overwritten: storage of the right length (the previous step's)
        // is not cleared first.
        out.resize(self.cols.len(), [0.0; 9]);
        self.copy_full_rows(upper, 0..self.row_ptr.len() - 1, out);
    }

    /// The full rows `rows` of [`BlockPattern::full_rows_into`] into `out` (their slots).
    fn copy_full_rows(
        &self,
        upper: &[Matrix3<f64>],
        rows: std::ops::Range<usize>,
        out: &mut [RowBlock],
    ) {
        let mut blocks = out.iter_mut();
        let prefetch = crate::prefetch::outgrows_cache(upper);
        for i in rows {
            for s in self.row_ptr[i]..self.row_ptr[i + 1] {
                // A lower slot's block is its mirror's, in an earlier row: gathered, so
                // prefetched a few slots ahead (an upper slot's mirror lies in a later
                // row and is not read here).
                if prefetch
                    && let Some(&m) = self.mirror.get(s + COPY_AHEAD_SLOTS)
                    && m < s + COPY_AHEAD_SLOTS
                {
                    crate::prefetch::prefetch(upper, m);
                }
                let b = if self.cols[s] >= i {
                    upper[s]
                } else {
                    upper[self.mirror[s]].transpose()
                };
                // nalgebra is column-major: columns at 0..3, 3..6, 6..9.
                let out = blocks.next().expect("one block per slot");
                out.copy_from_slice(b.as_slice());
            }
        }
    }

    /// [`BlockPattern::full_rows_into`] with the rows split at `node_start` (first 0, last
    /// the row count), each part copied on its own thread ([`crate::parallel::run_parts`]).
    pub fn full_rows_into_parts(
        &self,
        upper: &[Matrix3<f64>],
        out: &mut Vec<RowBlock>,
        node_start: &[usize],
    ) {
        out.resize(self.cols.len(), [0.0; 9]);
        let starts: Vec<usize> = node_start.iter().map(|&i| self.row_ptr[i]).collect();
        crate::parallel::run_parts(crate::parallel::split_ranges(out, &starts), |k, part| {
            self.copy_full_rows(upper, node_start[k]..node_start[k + 1], part)
        });
    }

    /// [`BlockPattern::full_rows_into`] a new vector.
    pub fn full_rows(&self, upper: &[Matrix3<f64>]) -> Vec<RowBlock> {
        let mut out = Vec::new();
        self.full_rows_into(upper, &mut out);
        out
    }

    /// `out = A p` from [`BlockPattern::full_rows`]: vectorised where the CPU has AVX,
    /// with the same result bit for bit elsewhere.
    pub fn multiply_full(&self, full: &[RowBlock], p: &[V3], out: &mut [V3]) {
        assert!(
            out.len() + 1 == self.row_ptr.len(),
            "vectors of the pattern's {} nodes",
            self.row_ptr.len() - 1
        );
        self.multiply_full_rows(full, p, 0, out);
    }

    /// Rows `start..start + out.len()` of [`BlockPattern::multiply_full`] into `out` (a
    /// thread's share of the product).
    pub fn multiply_full_rows(&self, full: &[RowBlock], p: &[V3], start: usize, out: &mut [V3]) {
        assert_eq!(full.len(), self.cols.len(), "full rows of this pattern");
        assert!(
            p.len() + 1 == self.row_ptr.len() && start + out.len() <= p.len(),
            "rows {start}.. ({}) of the pattern's {} nodes",
            out.len(),
            self.row_ptr.len() - 1
        );
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            unsafe { self.multiply_full_avx(full, p, start, out) };
            return;
        }
        self.multiply_full_portable(full, p, start, out);
    }

    /// [`BlockPattern::multiply_full_rows`] in plain Rust (the reference order of
    /// operations).
    pub(crate) fn multiply_full_portable(
        &self,
        full: &[RowBlock],
        p: &[V3],
        start: usize,
        out: &mut [V3],
    ) {
        for (i, o) in (start..).zip(out.iter_mut()) {
            let (mut a0, mut a1, mut a2) = ([0.0; 3], [0.0; 3], [0.0; 3]);
            let (from, to) = (self.row_ptr[i], self.row_ptr[i + 1]);
            for (b, &j) in full[from..to].iter().zip(&self.cols[from..to]) {
                let pj = &p[j];
                for l in 0..3 {
                    a0[l] += b[l] * pj.x;
                    a1[l] += b[3 + l] * pj.y;
                    a2[l] += b[6 + l] * pj.z;
                }
            }
            *o = V3::new(
                a0[0] + a1[0] + a2[0],
                a0[1] + a1[1] + a2[1],
                a0[2] + a1[2] + a2[2],
            );
        }
    }

    /// [`BlockPattern::multiply_full_rows`] on 4-lane AVX vectors.
    ///
    /// (A second set of accumulators, for a row's odd blocks, did not make it faster on
    /// this machine: the loop is bound by its loads, three of the block and three
    /// broadcasts per block, not by the additions' latency.)
    ///
    /// # Safety
    /// The CPU must support AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    pub(crate) unsafe fn multiply_full_avx(
        &self,
        full: &[RowBlock],
        p: &[V3],
        start: usize,
        out: &mut [V3],
    ) {
        use std::arch::x86_64::{
            _mm256_add_pd, _mm256_broadcast_sd, _mm256_loadu_pd, _mm256_maskload_pd, _mm256_mul_pd,
            _mm256_set_epi64x, _mm256_setzero_pd, _mm256_storeu_pd,
        };
        // Lanes 0–2 of the last column; lane 3 would read past the block.
        let last = _mm256_set_epi64x(0, -1, -1, -1);
        for (i, o) in (start..).zip(out.iter_mut()) {
            let (mut a0, mut a1, mut a2) = (
                _mm256_setzero_pd(),
                _mm256_setzero_pd(),
                _mm256_setzero_pd(),
            );
            let (from, to) = (self.row_ptr[i], self.row_ptr[i + 1]);
            for (b, &j) in full[from..to].iter().zip(&self.cols[from..to]) {
                let pj = &p[j];
                // SAFETY: `b` holds 9 f64: the loads at 0 and 3 read four of them each,
                // the masked load at 6 reads three (the masked lane is not accessed); the
                // broadcasts read one f64 each of `pj`.
                unsafe {
                    let c = b.as_ptr();
                    a0 = _mm256_add_pd(
                        a0,
                        _mm256_mul_pd(_mm256_loadu_pd(c), _mm256_broadcast_sd(&pj.x)),
                    );
                    a1 = _mm256_add_pd(
                        a1,
                        _mm256_mul_pd(_mm256_loadu_pd(c.add(3)), _mm256_broadcast_sd(&pj.y)),
                    );
                    a2 = _mm256_add_pd(
                        a2,
                        _mm256_mul_pd(
                            _mm256_maskload_pd(c.add(6), last),
                            _mm256_broadcast_sd(&pj.z),
                        ),
                    );
                }
            }
            let mut lanes = [0.0; 4];
            // SAFETY: `lanes` holds four f64.
            unsafe {
                _mm256_storeu_pd(lanes.as_mut_ptr(), _mm256_add_pd(_mm256_add_pd(a0, a1), a2))
            };
            *o = V3::new(lanes[0], lanes[1], lanes[2]);
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A random symmetric block matrix on a small Kuhn-like tet set, upper-stored.
    pub(in crate::solver) fn random_upper(seed: u64) -> (BlockPattern, Vec<Matrix3<f64>>, Vec<V3>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = 40;
        let tets: Vec<[usize; 4]> = (0..60)
            .map(|_| {
                loop {
                    let t: [usize; 4] = std::array::from_fn(|_| rng.random_range(0..n));
                    if (0..4).all(|a| (a + 1..4).all(|b| t[a] != t[b])) {
                        break t;
                    }
                }
            })
            .collect();
        let pat = BlockPattern::new(n, &tets);
        let mut upper = vec![Matrix3::zeros(); pat.num_blocks()];
        for i in 0..n {
            for (s, j) in pat.row(i) {
                if j >= i {
                    upper[s] = Matrix3::from_fn(|_, _| rng.random_range(-1.0..1.0));
                    if j == i {
                        upper[s] = upper[s] + upper[s].transpose();
                    }
                }
            }
        }
        let p = (0..n)
            .map(|_| V3::from_fn(|_, _| rng.random_range(-1.0..1.0)))
            .collect();
        (pat, upper, p)
    }

    #[test]
    fn full_rows_product_equals_the_symmetric_upper_product() {
        for seed in 0..5 {
            let (pat, upper, p) = random_upper(seed);
            let n = p.len();
            let (mut want, mut got) = (vec![V3::zeros(); n], vec![V3::zeros(); n]);
            pat.multiply_upper(&upper, &p, &mut want);
            pat.multiply_full(&pat.full_rows(&upper), &p, &mut got);
            for (w, g) in want.iter().zip(&got) {
                assert!(
                    (w - g).norm() <= 1e-13 * (1.0 + w.norm()),
                    "{w} against {g}"
                );
            }
        }
    }

    /// The full-row copy of a matrix whose blocks outgrow the cache (so that the copy
    /// prefetches its lower blocks' mirrors, `prefetch.rs`) holds every block of the
    /// plain one: the upper ones as stored, the lower ones transposed.
    #[test]
    fn the_full_row_copy_that_prefetches_holds_every_block() {
        // A strip of tets over consecutive nodes: 7 blocks a row, 17,000 rows, 8.5 MB
        // of blocks.
        let n = 17_000;
        let tets: Vec<[usize; 4]> = (0..n - 3).map(|k| [k, k + 1, k + 2, k + 3]).collect();
        let pat = BlockPattern::new(n, &tets);
        let upper: Vec<Matrix3<f64>> = (0..pat.num_blocks())
            .map(|s| Matrix3::from_fn(|r, c| (9 * s + 3 * r + c) as f64))
            .collect();
        assert!(crate::prefetch::outgrows_cache(&upper));
        let full = pat.full_rows(&upper);
        for i in 0..n {
            for s in pat.row_ptr[i]..pat.row_ptr[i + 1] {
                let want = if pat.cols[s] >= i {
                    upper[s]
                } else {
                    upper[pat.mirror[s]].transpose()
                };
                assert_eq!(full[s], *want.as_slice(), "row {i}, slot {s}");
            }
        }
    }

    #[test]
    fn avx_and_portable_full_products_are_bit_identical() {
        for seed in 0..5 {
            let (pat, upper, p) = random_upper(seed);
            let full = pat.full_rows(&upper);
            let n = p.len();
            let mut portable = vec![V3::zeros(); n];
            pat.multiply_full_portable(&full, &p, 0, &mut portable);
            #[cfg(target_arch = "x86_64")]
            if !std::arch::is_x86_feature_detected!("avx") {
                eprintln!("no AVX on this CPU: only the portable path was run");
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx") {
                let mut avx = vec![V3::zeros(); n];
                // SAFETY: AVX detected.
                unsafe { pat.multiply_full_avx(&full, &p, 0, &mut avx) };
                for (a, b) in avx.iter().zip(&portable) {
                    for k in 0..3 {
                        assert_eq!(a[k].to_bits(), b[k].to_bits(), "seed {seed}");
                    }
                }
            }
        }
    }
}
