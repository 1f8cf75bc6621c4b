//! A level's matrix (or one part's rows of the finest, `hybrid_rows.rs`) as the
//! Gauss–Seidel sweeps of one thread read it: every row's
//! off-diagonal blocks in one contiguous run (its lower part, transposed from the upper
//! storage, then its upper part), in half precision and summed in single precision; the
//! finest level's rebuilt from the step's assembled blocks every solve, a coarse level's
//! with its Galerkin operator.
//!
//! The coarse levels' sweeps moved here from [`SymRows`] on 2026-11-28: on the 12,288-tet
//! beam (levels of 400 and 81 nodes) their gathered lower parts were 4–5 % of an MG-PCG
//! step, and the step went from 5.40 to 5.24 ms (stiff) and 5.61 to 5.24 ms (soft), the
//! medians of five interleaved runs (docs/RESULTS.md).
//!
//! Why: `perf` over 60 steps of the 12,288-tet soft beam at dt 10 ms (MG-PCG to 1e-6, one
//! thread, 2026-11-27) put 20 % of the step in the lower-part products of [`SymRows`],
//! which gather every block from the row that stores it, against 10 % for the upper part
//! that reads its own row in order. Here both parts are read in order, once per sweep,
//! and each block took 48 bytes instead of 72 (24 since the blocks are in half precision,
//! below). A preconditioner needs no more precision: CG's own products stay in f64; the
//! smoothed matrix's blocks are rounded (a lower block is the rounded upper one,
//! transposed), and the sweeps read the iterate in f32, so the V-cycle is symmetric and
//! linear only to single precision (below).
//!
//! The products are lane-wise single-precision sums: a block is its three columns, each
//! padded to four lanes, and `A z` is three lane-wise multiply-adds (one accumulator per
//! column, so that the sweep does not wait on one long chain) with the broadcast
//! components of `z`, read from an f32 copy of the iterate that each sweep keeps current.
//! Scalar f64 products of f32 blocks spent most of their instructions converting the nine
//! entries to f64 (callgrind, 12,288-tet soft beam, 2026-11-27: see docs/RESULTS.md).
//! Summing in f32 makes the
//! V-cycle symmetric to single precision (about 1e-7 relative) rather than to f64; CG to
//! the step's 1e-6 takes the same iterations as with f64 sums, and MG-PCG still matches
//! the dense Cholesky solve at 1e-9 (the V-cycle symmetry test allows 1e-6 on this path).
//! The sums multiply then add (no fused multiply-add, whatever the build's target
//! features), so that every site computes the same bits.
//!
//! **Blocks in pairs** (2026-11-28): a row's blocks are stored two by two, column `k` of
//! the first block in lanes 0–3 and of the second in lanes 4–7 of an 8-lane row, so that
//! on a CPU with AVX one 8-lane multiply and add takes two blocks, with `[z_j | z_j']`
//! loaded once and each component spread over its half by an in-lane permute. The
//! portable path sums the same lanes in the same order (the two halves added at the end
//! of each product), so both give the same bits (test
//! `avx_and_portable_paired_sweeps_are_bit_identical`). A row's lower and upper parts
//! are each padded to whole pairs with a zero block whose column is a zero entry past the
//! last node.
//!
//! **The chained neighbour** (2026-11-28, second session): a sweep's row `i` waits on the
//! row written just before it (`i − 1` forward, `i + 1` backward), which on the lattice
//! is nearly always a neighbour. That block is kept out of the pairs and applied last,
//! premultiplied by `D_i⁻¹` ([`FullRows::chain`]), so the wait per row is one 3×3
//! product. On the 12,288-tet beam's finest level (2,673 nodes) a forward sweep from
//! zero went from 32.9 to 22.4 µs and a backward sweep from 39.6 to 34.8 µs, and the
//! MG-PCG step from 4.93 to 4.68 ms (soft) and 4.82 to 4.57 ms (stiff), the medians of
//! five interleaved runs, with the same iterations (docs/RESULTS.md).
//!
//! **Half precision** (same session): the sweeps stream their blocks from the level-3
//! cache (1.8 MB of pairs at 2,673 nodes; 1 MiB of level-2 cache per core), so the pairs
//! are now stored in f16, 48 bytes per pair instead of 96, each row scaled by a power of
//! two ([`FullRows::scale`]) so that any scene's matrix fits f16's range exactly (test
//! `full_row_sweeps_are_exact_under_power_of_two_scaling`). The chain blocks, the
//! diagonal inverses and every sum stay in f32. On the 12,288-tet beam's finest level a
//! forward sweep from zero went from 22.4 to about 17.5 µs, `−U z` from 21.1 to 16.2 µs
//! and a backward sweep from 34.8 to 27 µs, while the fill went from 97 to 155 µs; the
//! MG-PCG step went from 5.14 to 4.61 ms (soft) and 4.60 to 4.21 ms (stiff), the medians
//! of six interleaved runs, with the same iterations (17.2 and 17.8), and the 98,304-tet
//! step from 72 to 61 ms. The rounding (2⁻¹¹ relative) changes the smoother, not what CG
//! converges to: CG's products stay in f64.

use half::{f16, slice::HalfFloatSliceExt};
use nalgebra::{Matrix3, Vector3};

use super::smoother::SymRows;

type V3 = Vector3<f64>;

/// Two 3×3 blocks in half precision, scaled (see [`FullRows::scale`]): for each column
/// `k`, `[b_0k, b_1k, b_2k, 0]` of the first block then of the second.
type Pair16 = [[f16; 8]; 3];

/// One 3×3 block in single precision by columns `[a_0k, a_1k, a_2k, 0]`.
type Block32 = [[f32; 4]; 3];

/// Rows ahead whose pairs a sweep prefetches.
const PREFETCH_ROWS: usize = 16;

/// Pairs ahead whose blocks the fill prefetches from the step's storage.
const FILL_AHEAD_PAIRS: usize = 8;

/// Bit of [`FullRows::src`] marking a block taken transposed.
const TRANSPOSED: u32 = 1 << 31;

/// [`FullRows::src`] of a padding block (zero).
const PAD: u32 = u32::MAX;

/// One pass over the rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pass {
    /// Forward sweep from `z = 0` (lower parts only).
    ForwardFromZero,
    /// Forward sweep from `z` (`z32` holds `z`).
    Forward,
    /// Backward sweep from `z` (`z32` holds `z`).
    Backward,
    /// `out = −U z` (`z32` holds `z`).
    MinusUpper,
    /// `out = r − A z` (`z32` holds `z`).
    Residual,
}

/// The finest level's off-diagonal blocks by full rows (see the module documentation).
#[derive(Clone, Debug, Default)]
pub(super) struct FullRows {
    /// Row `i`'s pairs are `row_ptr[i]..row_ptr[i + 1]`; its lower ones (columns below
    /// `i`) end at `upper_start[i]`.
    row_ptr: Vec<u32>,
    upper_start: Vec<u32>,
    /// Columns of each pair's two blocks (a padding block's: the zero entry `n` of `z32`).
    cols: Vec<[u32; 2]>,
    /// Slot of each block in the fine block storage ([`TRANSPOSED`]: taken transposed;
    /// [`PAD`]: a zero block).
    src: Vec<[u32; 2]>,
    /// The pairs' blocks, refreshed by [`FullRows::fill`].
    blocks: Vec<Pair16>,
    /// Row `i`'s blocks with its neighbours `i − 1` (first half) and `i + 1` (second
    /// half), zero where those are not neighbours; they are not among the pairs (see
    /// [`FullRows::chain`]).
    near: Vec<Pair16>,
    /// Slots of the two near blocks (as [`FullRows::src`]).
    near_src: Vec<[u32; 2]>,
    /// `D_i⁻¹ A_{i,i−1}` and `D_i⁻¹ A_{i,i+1}` in f32. A forward sweep's row `i` waits on
    /// row `i − 1`, the row just written (a backward sweep's on `i + 1`), and nothing
    /// else recent: it computes `w = D_i⁻¹ (r_i − Σ_{j≠i−1} A_ij z_j)` from older rows
    /// while the previous row finishes, then `z_i = w − (D_i⁻¹ A_{i,i−1}) z_{i−1}` with
    /// `z_{i−1}` still in a register. The wait per row is one 3×3 product instead of the
    /// whole row's tail (its reduction and the product by `D_i⁻¹`): see
    /// docs/RESULTS.md for the measurement.
    chain: Vec<[Block32; 2]>,
    /// Row `i`'s scale `s_i`, a power of two near `1 / √max_k A_ii[k][k]`: the pairs
    /// hold `B_ij = s_i s_j A_ij`, whose entries are less than 4 in magnitude (`|a_pq| ≤
    /// √(a_pp a_qq)` in a positive-definite matrix), so that half precision holds any
    /// scene's matrix, and `z32` holds `y_i = z_i / s_i`. Powers of two make both scalings
    /// exact: the sweeps act on `A' = S⁻¹ B' S⁻¹` with `B'` the rounded blocks, a
    /// symmetric matrix (a lower block is the rounded upper one, transposed). (`s_i` is
    /// kept in f32, which holds it for diagonals between about 2⁻²⁵⁰ and 2²⁵⁰.)
    scale: Vec<f32>,
    /// `1 / s_i`: `Σ_j A'_ij z_j = (Σ_j B'_ij y_j) / s_i`.
    unscale: Vec<f32>,
    /// Diagonal blocks (f64: the residual of several sweeps multiplies by them).
    diag: Vec<Matrix3<f64>>,
    /// The diagonal blocks' inverses in f32, by columns `[d_0k, d_1k, d_2k, 0]` (zero for
    /// rows the sweeps leave at zero): a row's update is all in single precision, so that
    /// the next row, which waits on it, waits less (below).
    dinv: Vec<[[f32; 4]; 3]>,
    /// The iterate in single precision, `[x, y, z, 0]` per node, as the products read it:
    /// set from `z` when a sweep starts and updated row by row as the sweep writes `z`.
    /// One more entry, always zero, for padding blocks.
    z32: Vec<[f32; 4]>,
    /// The row of the level's matrix that is this one's row 0: a part of the rows
    /// ([`FullRows::of_range`]) indexes the level's blocks, diagonal slots and diagonal
    /// inverses from there.
    first: usize,
    /// Never use AVX (tests).
    portable: bool,
    /// Whether the passes and the fill prefetch: whether the blocks [`FullRows::fill`]
    /// copies from outgrow the cache ([`crate::prefetch::outgrows_cache`]; the finest
    /// level's are the step's, a coarse level's its Galerkin operator, which never does).
    prefetch: bool,
}

/// Whether this CPU converts to half precision in hardware (F16C, with AVX).
fn has_f16c() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx")
        && std::arch::is_x86_feature_detected!("f16c");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// `v[j]` in f64, zero past the end (the padding column `n`, whose blocks are zero).
#[inline(always)]
fn scale_of(v: &[f32], j: u32) -> f64 {
    v.get(j as usize).map_or(0.0, |&s| f64::from(s))
}

/// A pair's blocks (slots `srcs`, columns `cols`, as [`FullRows::src`]) scaled by
/// `s_i s_j` (`si`, `scale`) in f32 lanes: the values [`round_to_f16`] rounds.
#[inline(always)]
fn scaled_pair(
    fine: &[Matrix3<f64>],
    srcs: &[u32; 2],
    cols: &[u32; 2],
    si: f64,
    scale: &[f32],
) -> [f32; 24] {
    let mut t = [0.0f32; 24];
    for (half, (&s, &j)) in srcs.iter().zip(cols).enumerate() {
        if s == PAD {
            continue;
        }
        let f = si * scale_of(scale, j);
        // Column-major: entry (row, k) at 3k + row; a transposed block's at 3row + k.
        let b = fine[(s & !TRANSPOSED) as usize].as_slice();
        if s & TRANSPOSED != 0 {
            for k in 0..3 {
                for row in 0..3 {
                    t[8 * k + 4 * half + row] = (b[3 * row + k] * f) as f32;
                }
            }
        } else {
            for k in 0..3 {
                for row in 0..3 {
                    t[8 * k + 4 * half + row] = (b[3 * k + row] * f) as f32;
                }
            }
        }
    }
    t
}

/// Block `slot` of `fine` (transposed if `transposed`) as the sweeps of rows with scales
/// `si` and `sj` hold it ([`FullRows::scale`]): `s_i s_j A` rounded to f32, then to f16
/// (to nearest even, as the pairs), scaled back (exactly: powers of two). The hybrid
/// sweeps' blocks between parts (`hybrid_rows.rs`), so that they act on the same matrix
/// `A'` as the parts' own sweeps.
pub(super) fn rounded_block(
    fine: &[Matrix3<f64>],
    slot: usize,
    transposed: bool,
    si: f32,
    sj: f32,
) -> Matrix3<f64> {
    let f = f64::from(si) * f64::from(sj);
    let b = if transposed {
        fine[slot].transpose()
    } else {
        fine[slot]
    };
    b.map(|a| f64::from(f16::from_f32((a * f) as f32).to_f32()) / f)
}

/// A pair's 24 lanes rounded to half precision, to nearest even (the same bits on every
/// CPU). `F16C`: only where the CPU has AVX and F16C, inlined into code compiled for them.
#[inline(always)]
fn round_to_f16<const F16C: bool>(src: &[f32; 24], dst: &mut Pair16) {
    #[cfg(target_arch = "x86_64")]
    if F16C {
        use std::arch::x86_64::{
            __m128i, _MM_FROUND_TO_NEAREST_INT, _mm_storeu_si128, _mm256_cvtps_ph, _mm256_loadu_ps,
        };
        for (s, d) in src.chunks_exact(8).zip(dst.iter_mut()) {
            // SAFETY: AVX and F16C (this function's contract); `s` holds 8 f32 and `d` 8
            // f16 (16 bytes).
            unsafe {
                let h = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm256_loadu_ps(s.as_ptr()));
                _mm_storeu_si128(d.as_mut_ptr().cast::<__m128i>(), h);
            }
        }
        return;
    }
    dst.as_flattened_mut().convert_from_f32_slice(src);
}

/// Eight half-precision lanes in f32 (exact). `F16C`: as [`round_to_f16`].
#[inline(always)]
fn widen<const F16C: bool>(h: &[f16; 8]) -> [f32; 8] {
    #[cfg(target_arch = "x86_64")]
    if F16C {
        use std::arch::x86_64::{__m128i, _mm_loadu_si128, _mm256_cvtph_ps, _mm256_storeu_ps};
        let mut out = [0.0f32; 8];
        // SAFETY: AVX and F16C (the contract of `F16C`); `h` holds 8 f16, `out` 8 f32.
        unsafe {
            let w = _mm256_cvtph_ps(_mm_loadu_si128(h.as_ptr().cast::<__m128i>()));
            _mm256_storeu_ps(out.as_mut_ptr(), w);
        }
        return out;
    }
    h.map(f16::to_f32_const)
}

#[inline]
fn to_f32(v: &V3) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, 0.0]
}

impl FullRows {
    /// The layout of `rows` (blocks zero until [`FullRows::fill`]).
    pub fn of(rows: &SymRows) -> Self {
        Self::of_range(rows, 0, rows.num_rows())
    }

    /// The layout of rows `first..end` of `rows` with only their blocks in columns
    /// `first..end`, numbered from `first` (a part of the hybrid sweeps, `hybrid_rows.rs`:
    /// the blocks with other parts' columns are left out).
    pub fn of_range(rows: &SymRows, first: usize, end: usize) -> Self {
        let n = end - first;
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut upper_start = Vec::with_capacity(n);
        let mut cols = Vec::new();
        let mut src = Vec::new();
        // Entries `(slot with flags, column)` two by two, the last padded.
        let pairs = |entries: Vec<(u32, u32)>, cols: &mut Vec<[u32; 2]>, src: &mut Vec<_>| {
            for two in entries.chunks(2) {
                let second = two.get(1).copied().unwrap_or((PAD, n as u32));
                cols.push([two[0].1, second.1]);
                src.push([two[0].0, second.0]);
            }
        };
        let mut near_src = vec![[PAD; 2]; n];
        row_ptr.push(0);
        let inside = |j: usize| (first..end).contains(&j).then(|| j - first);
        for (i, near) in near_src.iter_mut().enumerate() {
            let mut lower = Vec::new();
            for (slot, j) in rows.lower_entries(first + i) {
                let Some(j) = inside(j) else { continue };
                if j + 1 == i {
                    near[0] = slot as u32 | TRANSPOSED;
                } else {
                    lower.push((slot as u32 | TRANSPOSED, j as u32));
                }
            }
            pairs(lower, &mut cols, &mut src);
            upper_start.push(cols.len() as u32);
            let mut upper = Vec::new();
            for (slot, j) in rows.upper_entries(first + i) {
                let Some(j) = inside(j) else { continue };
                if j == i + 1 {
                    near[1] = slot as u32;
                } else {
                    upper.push((slot as u32, j as u32));
                }
            }
            pairs(upper, &mut cols, &mut src);
            row_ptr.push(cols.len() as u32);
        }
        let len = cols.len();
        Self {
            row_ptr,
            upper_start,
            cols,
            src,
            blocks: vec![[[f16::ZERO; 8]; 3]; len],
            near: vec![[[f16::ZERO; 8]; 3]; n],
            near_src,
            chain: vec![[[[0.0; 4]; 3]; 2]; n],
            scale: vec![1.0; n],
            unscale: vec![1.0; n],
            diag: vec![Matrix3::zeros(); n],
            dinv: vec![[[0.0; 4]; 3]; n],
            z32: vec![[0.0; 4]; n + 1],
            first,
            portable: false,
            prefetch: false,
        }
    }

    /// Copies the step's blocks (`fine`: the upper storage `rows` indexes) and the
    /// diagonal blocks' inverses the sweeps divide by (zero: the row stays zero; indexed
    /// as the level's rows, not from [`FullRows::first`]) in.
    pub fn fill(&mut self, rows: &SymRows, fine: &[Matrix3<f64>], dinv: &[Matrix3<f64>]) {
        self.prefetch = crate::prefetch::outgrows_cache(fine);
        let dinv = &dinv[self.first..self.first + self.num_rows()];
        for (out, d) in self.dinv.iter_mut().zip(dinv) {
            *out = std::array::from_fn(|k| {
                [d[(0, k)] as f32, d[(1, k)] as f32, d[(2, k)] as f32, 0.0]
            });
        }
        for (i, d) in self.diag.iter_mut().enumerate() {
            *d = fine[rows.diagonal_slot(self.first + i)];
            let top = d[(0, 0)].max(d[(1, 1)]).max(d[(2, 2)]);
            // top = m 2^e with 1 ≤ m < 2: s = 2^−⌊e/2⌋ puts s² top in [1, 4).
            let s = if top > 0.0 && top.is_normal() {
                let e = ((top.to_bits() >> 52) & 0x7ff) as i64 - 1023;
                f64::from_bits(((1023 - e.div_euclid(2)) as u64) << 52)
            } else {
                1.0
            };
            self.scale[i] = s as f32;
            self.unscale[i] = (1.0 / s) as f32;
        }
        #[cfg(target_arch = "x86_64")]
        if !self.portable && has_f16c() {
            // SAFETY: the CPU has AVX and F16C (checked just above).
            unsafe { self.fill_pairs_f16c(fine, dinv) };
            return;
        }
        self.fill_pairs::<false>(fine, dinv);
    }

    /// [`FullRows::fill_pairs`] compiled for AVX and F16C.
    ///
    /// # Safety
    /// The CPU must support AVX and F16C.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx,f16c")]
    unsafe fn fill_pairs_f16c(&mut self, fine: &[Matrix3<f64>], dinv: &[Matrix3<f64>]) {
        self.fill_pairs::<true>(fine, dinv);
    }

    /// The pairs, near pairs and chain blocks of [`FullRows::fill`], the scales set: each
    /// pair's scaled blocks in f32, then rounded to f16 (to nearest even, the same bits
    /// on every CPU: by F16C where `F16C`, else by `half`).
    #[inline(always)]
    fn fill_pairs<const F16C: bool>(&mut self, fine: &[Matrix3<f64>], dinv: &[Matrix3<f64>]) {
        let n = self.num_rows();
        let (scale, unscale) = (&self.scale, &self.unscale);
        for i in 0..n {
            let si = f64::from(scale[i]);
            let (from, to) = (self.row_ptr[i] as usize, self.row_ptr[i + 1] as usize);
            for p in from..to {
                // The blocks a few pairs ahead, gathered from the step's storage.
                if self.prefetch
                    && let Some(ahead) = self.src.get(p + FILL_AHEAD_PAIRS)
                {
                    for &s in ahead {
                        crate::prefetch::prefetch(fine, (s & !TRANSPOSED) as usize);
                    }
                }
                let (srcs, cols) = (&self.src[p], &self.cols[p]);
                round_to_f16::<F16C>(
                    &scaled_pair(fine, srcs, cols, si, scale),
                    &mut self.blocks[p],
                );
            }
            let near_cols = self.near_cols(Pass::Residual, i).expect("both neighbours");
            let t = scaled_pair(fine, &self.near_src[i], &near_cols, si, scale);
            round_to_f16::<F16C>(&t, &mut self.near[i]);
            // The chain blocks from the rounded near blocks, so that every pass sweeps
            // the same matrix `A'`.
            let near: [[f32; 8]; 3] = std::array::from_fn(|k| widen::<F16C>(&self.near[i][k]));
            for (half, &j) in near_cols.iter().enumerate() {
                let u = f64::from(unscale[i]) * scale_of(unscale, j);
                let b = Matrix3::from_fn(|row, k| f64::from(near[k][4 * half + row]) * u);
                let c = dinv[i] * b;
                self.chain[i][half] = std::array::from_fn(|k| {
                    [c[(0, k)] as f32, c[(1, k)] as f32, c[(2, k)] as f32, 0.0]
                });
            }
        }
    }

    fn num_rows(&self) -> usize {
        self.upper_start.len()
    }

    /// Row `i`'s scale `s_i` (see [`FullRows::scale`]; `i` counted from
    /// [`FullRows::first`]).
    pub fn row_scale(&self, i: usize) -> f32 {
        self.scale[i]
    }

    /// The f32 copy of the iterate set from `z` (the padding entry stays zero).
    fn load(&mut self, z: &[V3]) {
        for ((a, v), &u) in self.z32.iter_mut().zip(z).zip(&self.unscale) {
            *a = to_f32(v).map(|c| c * u);
        }
    }

    /// The pairs `pass` sums in row `i`: the lower ones, the upper ones or all.
    #[inline(always)]
    fn pair_range(&self, pass: Pass, i: usize) -> (usize, usize) {
        let (lower, upper, end) = (
            self.row_ptr[i] as usize,
            self.upper_start[i] as usize,
            self.row_ptr[i + 1] as usize,
        );
        match pass {
            Pass::ForwardFromZero => (lower, upper),
            Pass::MinusUpper => (upper, end),
            Pass::Forward | Pass::Backward | Pass::Residual => (lower, end),
        }
    }

    /// The columns by which `pass` multiplies row `i`'s near pair: the zero entry `n`
    /// for a half it leaves out (the neighbour it chains on, or a part it does not sum).
    #[inline(always)]
    fn near_cols(&self, pass: Pass, i: usize) -> Option<[u32; 2]> {
        let n = self.num_rows();
        let zero = n as u32;
        let below = if i == 0 { zero } else { (i - 1) as u32 };
        let above = if i + 1 < n { (i + 1) as u32 } else { zero };
        match pass {
            Pass::ForwardFromZero => None,
            Pass::Forward | Pass::MinusUpper => Some([zero, above]),
            Pass::Backward => Some([below, zero]),
            Pass::Residual => Some([below, above]),
        }
    }

    /// `Σ A_ij z_j` over the blocks `pass` reads in row `i` (its pairs, then its near
    /// pair), from the f32 iterate: the reference order of operations. Per column `k` an
    /// 8-lane sum of `block_k · z_j[k]` (first block of each pair in lanes 0–3, second in
    /// 4–7), the halves added at the end, then the columns: `(s_0 + s_1) + s_2` (lane 3
    /// is zero).
    #[inline(always)]
    fn sum_portable(&self, pass: Pass, i: usize) -> [f32; 4] {
        let (from, to) = self.pair_range(pass, i);
        let mut acc = [[0.0f32; 8]; 3];
        let z32 = &self.z32;
        let mut add = |b: &Pair16, cols: &[u32; 2]| {
            let (z0, z1) = (&z32[cols[0] as usize], &z32[cols[1] as usize]);
            for (k, (a, bk)) in acc.iter_mut().zip(b).enumerate() {
                for l in 0..4 {
                    // Multiply, then add: `mul_add` would fuse in builds with FMA
                    // enabled and change the bits between sites built differently.
                    a[l] += bk[l].to_f32() * z0[k];
                    a[4 + l] += bk[4 + l].to_f32() * z1[k];
                }
            }
        };
        for (b, cols) in self.blocks[from..to].iter().zip(&self.cols[from..to]) {
            add(b, cols);
        }
        if let Some(cols) = self.near_cols(pass, i) {
            add(&self.near[i], &cols);
        }
        let s: [[f32; 4]; 3] =
            std::array::from_fn(|k| std::array::from_fn(|l| acc[k][l] + acc[k][4 + l]));
        let u = self.unscale[i];
        std::array::from_fn(|l| ((s[0][l] + s[1][l]) + s[2][l]) * u)
    }

    /// One pair's multiply-adds of [`FullRows::sum_avx`].
    ///
    /// # Safety
    /// The CPU must support AVX and F16C; only called from functions compiled for them, into which
    /// it is inlined.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn add_pair_avx(
        &self,
        acc: &mut [std::arch::x86_64::__m256; 3],
        b: &Pair16,
        cols: &[u32; 2],
    ) {
        use std::arch::x86_64::{
            __m128i, _mm_loadu_si128, _mm256_add_ps, _mm256_cvtph_ps, _mm256_loadu2_m128,
            _mm256_mul_ps, _mm256_permute_ps,
        };
        // SAFETY: AVX and F16C (this function's contract); every pointer read is within
        // its array: a pair's column holds 8 f16 (16 bytes), a `z32` entry 4 f32.
        unsafe {
            let column =
                |k: usize| _mm256_cvtph_ps(_mm_loadu_si128(b[k].as_ptr().cast::<__m128i>()));
            let z = _mm256_loadu2_m128(
                self.z32[cols[1] as usize].as_ptr(),
                self.z32[cols[0] as usize].as_ptr(),
            );
            acc[0] = _mm256_add_ps(acc[0], _mm256_mul_ps(column(0), _mm256_permute_ps(z, 0x00)));
            acc[1] = _mm256_add_ps(acc[1], _mm256_mul_ps(column(1), _mm256_permute_ps(z, 0x55)));
            acc[2] = _mm256_add_ps(acc[2], _mm256_mul_ps(column(2), _mm256_permute_ps(z, 0xAA)));
        }
    }

    /// [`FullRows::sum_portable`] on 8-lane AVX registers (same operations, same order).
    ///
    /// # Safety
    /// The CPU must support AVX and F16C; only called from functions compiled for them, into which
    /// it is inlined.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn sum_avx(&self, pass: Pass, i: usize) -> std::arch::x86_64::__m128 {
        use std::arch::x86_64::{
            _mm_add_ps, _mm_mul_ps, _mm_set1_ps, _mm256_castps256_ps128, _mm256_extractf128_ps,
            _mm256_setzero_ps,
        };
        // SAFETY: AVX and F16C (this function's contract).
        unsafe {
            let (from, to) = self.pair_range(pass, i);
            let mut acc = [_mm256_setzero_ps(); 3];
            for (b, cols) in self.blocks[from..to].iter().zip(&self.cols[from..to]) {
                self.add_pair_avx(&mut acc, b, cols);
            }
            if let Some(cols) = self.near_cols(pass, i) {
                self.add_pair_avx(&mut acc, &self.near[i], &cols);
            }
            let half = |a| _mm_add_ps(_mm256_castps256_ps128(a), _mm256_extractf128_ps(a, 1));
            _mm_mul_ps(
                _mm_add_ps(_mm_add_ps(half(acc[0]), half(acc[1])), half(acc[2])),
                _mm_set1_ps(self.unscale[i]),
            )
        }
    }

    /// The sum of [`FullRows::sum_portable`] as f64.
    #[inline(always)]
    fn product<const AVX: bool>(&self, pass: Pass, i: usize) -> V3 {
        #[cfg(target_arch = "x86_64")]
        if AVX {
            use std::arch::x86_64::_mm_storeu_ps;
            let mut s = [0.0f32; 4];
            // SAFETY: `AVX` is true only in `run_avx`, compiled for AVX and F16C and
            // called after the CPU was found to have them; `s` holds four f32.
            unsafe { _mm_storeu_ps(s.as_mut_ptr(), self.sum_avx(pass, i)) };
            return V3::new(f64::from(s[0]), f64::from(s[1]), f64::from(s[2]));
        }
        let s = self.sum_portable(pass, i);
        V3::new(f64::from(s[0]), f64::from(s[1]), f64::from(s[2]))
    }

    /// Row `i` of a sweep: `z_i = D_i⁻¹ (r_i − Σ_{j≠i} A_ij z_j)` (only the lower part
    /// from zero), in both copies of the iterate, all in single precision and in two
    /// parts (see [`FullRows::chain`]): `d = r_i − s` over every block but the chained
    /// neighbour's, `w = (D⁻¹_0 d_x + D⁻¹_1 d_y) + D⁻¹_2 d_z` by columns, then
    /// `z_i = w − ((C_0 p_x + C_1 p_y) + C_2 p_z)` with `C` the chain block and `p` the
    /// row this pass wrote last (`prev`). Returns `z_i` in f32.
    ///
    /// Why single precision here too: a forward or backward sweep waits, row after row,
    /// on the previous row's `z`, so its time is the chain from one row's `z` to the
    /// next; an update in f64 added conversions to that chain.
    #[inline(always)]
    fn relax<const AVX: bool>(
        &mut self,
        pass: Pass,
        r: &[V3],
        z: &mut [V3],
        i: usize,
        prev: [f32; 4],
    ) -> [f32; 4] {
        let ri = [r[i].x as f32, r[i].y as f32, r[i].z as f32, 0.0];
        let zi = 'zi: {
            #[cfg(target_arch = "x86_64")]
            if AVX {
                // SAFETY: `AVX` is true only in `run_avx`, compiled for AVX and F16C
                // and called after the CPU was found to have them.
                break 'zi unsafe { self.relax_avx(pass, i, &ri, &prev) };
            }
            let s = self.sum_portable(pass, i);
            let d: [f32; 4] = std::array::from_fn(|l| ri[l] - s[l]);
            let c = &self.dinv[i];
            let w: [f32; 4] =
                std::array::from_fn(|l| (c[0][l] * d[0] + c[1][l] * d[1]) + c[2][l] * d[2]);
            let ch = &self.chain[i][usize::from(pass == Pass::Backward)];
            std::array::from_fn(|l| {
                w[l] - ((ch[0][l] * prev[0] + ch[1][l] * prev[1]) + ch[2][l] * prev[2])
            })
        };
        let u = self.unscale[i];
        self.z32[i] = zi.map(|c| c * u);
        z[i] = V3::new(f64::from(zi[0]), f64::from(zi[1]), f64::from(zi[2]));
        zi
    }

    /// [`FullRows::relax`]'s arithmetic on SSE/AVX registers (same operations, same
    /// order).
    ///
    /// # Safety
    /// The CPU must support AVX and F16C; only called from functions compiled for them.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn relax_avx(&self, pass: Pass, i: usize, ri: &[f32; 4], prev: &[f32; 4]) -> [f32; 4] {
        use std::arch::x86_64::{
            __m128, _mm_add_ps, _mm_loadu_ps, _mm_mul_ps, _mm_permute_ps, _mm_storeu_ps, _mm_sub_ps,
        };
        // `(c_0 v_x + c_1 v_y) + c_2 v_z` for a block `c` by columns.
        #[inline(always)]
        unsafe fn apply(c: &Block32, v: __m128) -> __m128 {
            // SAFETY: AVX (the caller's contract); the loads read 4 f32 each.
            unsafe {
                _mm_add_ps(
                    _mm_add_ps(
                        _mm_mul_ps(_mm_loadu_ps(c[0].as_ptr()), _mm_permute_ps(v, 0x00)),
                        _mm_mul_ps(_mm_loadu_ps(c[1].as_ptr()), _mm_permute_ps(v, 0x55)),
                    ),
                    _mm_mul_ps(_mm_loadu_ps(c[2].as_ptr()), _mm_permute_ps(v, 0xAA)),
                )
            }
        }
        // SAFETY: AVX (this function's contract); the loads read 4 f32 each.
        unsafe {
            let s = self.sum_avx(pass, i);
            let d = _mm_sub_ps(_mm_loadu_ps(ri.as_ptr()), s);
            let w = apply(&self.dinv[i], d);
            let ch = &self.chain[i][usize::from(pass == Pass::Backward)];
            let z = _mm_sub_ps(w, apply(ch, _mm_loadu_ps(prev.as_ptr())));
            let mut out = [0.0f32; 4];
            _mm_storeu_ps(out.as_mut_ptr(), z);
            out
        }
    }

    /// When this matrix prefetches, asks for the pairs and columns of the row
    /// [`PREFETCH_ROWS`] after row `i` in the pass's direction (`backward`: before it),
    /// if there is one ([`crate::prefetch`]).
    #[inline(always)]
    fn prefetch_ahead(&self, i: usize, backward: bool) {
        if !self.prefetch {
            return;
        }
        let ahead = if backward {
            i.checked_sub(PREFETCH_ROWS)
        } else {
            Some(i + PREFETCH_ROWS).filter(|&j| j < self.num_rows())
        };
        if let Some(j) = ahead {
            let (from, to) = (self.row_ptr[j] as usize, self.row_ptr[j + 1] as usize);
            crate::prefetch::prefetch_range(&self.blocks, from..to);
            crate::prefetch::prefetch_range(&self.cols, from..to);
        }
    }

    /// One pass over the rows (see [`Pass`]); `out` is written by the residual passes.
    #[inline(always)]
    fn pass<const AVX: bool>(&mut self, pass: Pass, r: &[V3], z: &mut [V3], out: &mut [V3]) {
        let n = self.num_rows();
        let mut prev = [0.0f32; 4];
        match pass {
            Pass::ForwardFromZero | Pass::Forward => {
                for i in 0..n {
                    self.prefetch_ahead(i, false);
                    prev = self.relax::<AVX>(pass, r, z, i, prev);
                }
            }
            Pass::Backward => {
                for i in (0..n).rev() {
                    self.prefetch_ahead(i, true);
                    prev = self.relax::<AVX>(pass, r, z, i, prev);
                }
            }
            Pass::MinusUpper => {
                for (i, o) in out.iter_mut().enumerate() {
                    self.prefetch_ahead(i, false);
                    *o = -self.product::<AVX>(pass, i);
                }
            }
            Pass::Residual => {
                for (i, o) in out.iter_mut().enumerate() {
                    self.prefetch_ahead(i, false);
                    *o = r[i] - self.diag[i] * z[i] - self.product::<AVX>(pass, i);
                }
            }
        }
    }

    /// [`FullRows::pass`] compiled for AVX and F16C.
    ///
    /// # Safety
    /// The CPU must support AVX and F16C.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx,f16c")]
    unsafe fn run_avx(&mut self, pass: Pass, r: &[V3], z: &mut [V3], out: &mut [V3]) {
        self.pass::<true>(pass, r, z, out);
    }

    /// [`FullRows::pass`] on AVX where the CPU has it (`portable`: never).
    fn run(&mut self, pass: Pass, r: &[V3], z: &mut [V3], out: &mut [V3], portable: bool) {
        #[cfg(target_arch = "x86_64")]
        if !portable
            && std::arch::is_x86_feature_detected!("avx")
            && std::arch::is_x86_feature_detected!("f16c")
        {
            // SAFETY: the CPU has AVX and F16C (checked just above).
            unsafe { self.run_avx(pass, r, z, out) };
            return;
        }
        let _ = portable;
        self.pass::<false>(pass, r, z, out);
    }

    /// One forward sweep from `z = 0` ([`SymRows::forward_from_zero`]): the lower part
    /// reads only rows this sweep has already written.
    pub fn forward_from_zero(&mut self, r: &[V3], z: &mut [V3]) {
        self.run(Pass::ForwardFromZero, r, z, &mut [], self.portable);
    }

    /// The residual right after [`FullRows::forward_from_zero`]: `−U z`.
    #[cfg(test)]
    pub fn residual_after_forward_from_zero(&mut self, z: &[V3], out: &mut [V3]) {
        self.load(z);
        self.minus_upper_after_forward(&mut z.to_vec(), out);
    }

    /// One backward sweep from `z`.
    pub fn backward(&mut self, r: &[V3], z: &mut [V3]) {
        self.load(z);
        self.run(Pass::Backward, r, z, &mut [], self.portable);
    }

    /// One forward sweep from `z`.
    pub fn forward(&mut self, r: &[V3], z: &mut [V3]) {
        self.load(z);
        self.run(Pass::Forward, r, z, &mut [], self.portable);
    }

    /// `out = −U z` right after [`FullRows::forward_from_zero`] wrote `z` (the f32 copy
    /// it keeps is `z`), the residual of that sweep; `z` is not written.
    pub fn minus_upper_after_forward(&mut self, z: &mut [V3], out: &mut [V3]) {
        self.run(Pass::MinusUpper, &[], z, out, self.portable);
    }

    /// `out = r − A z`; `z` is not written.
    pub fn residual(&mut self, r: &[V3], z: &mut [V3], out: &mut [V3]) {
        self.load(z);
        self.run(Pass::Residual, r, z, out, self.portable);
    }

    /// Sweeps and products without AVX from now on (tests compare both paths).
    #[cfg(test)]
    pub fn set_portable(&mut self, portable: bool) {
        self.portable = portable;
    }

    /// Passes prefetch rows ahead (or not) until the next [`FullRows::fill`], whatever
    /// the matrix's size (tests).
    #[cfg(test)]
    pub fn set_prefetch(&mut self, prefetch: bool) {
        self.prefetch = prefetch;
    }

    /// Pre-smoothing: `sweeps` forward sweeps from zero, then the residual into `res`
    /// (as [`super::smoother::pre_smooth`]).
    pub fn pre_smooth(&mut self, r: &[V3], z: &mut [V3], res: &mut [V3], sweeps: usize) {
        let portable = self.portable;
        self.run(Pass::ForwardFromZero, r, z, &mut [], portable);
        if sweeps <= 1 {
            // z32 holds z: the sweep wrote every row of both.
            self.run(Pass::MinusUpper, r, z, res, portable);
            return;
        }
        for _ in 1..sweeps {
            self.run(Pass::Forward, r, z, &mut [], portable);
        }
        self.run(Pass::Residual, r, z, res, portable);
    }

    /// Post-smoothing: `sweeps` backward sweeps from `z`.
    pub fn post_smooth(&mut self, r: &[V3], z: &mut [V3], sweeps: usize) {
        self.load(z);
        for _ in 0..sweeps {
            self.run(Pass::Backward, r, z, &mut [], self.portable);
        }
    }
}
