//! Block Gauss–Seidel on a symmetric 3×3-block matrix stored as its blocks on and above
//! the diagonal (the fine level's [`BlockPattern`] slots or a coarse [`UpperCsr`]).
//!
//! Why Gauss–Seidel: with one sweep each way MG-PCG needed 17.8 iterations on the stiff
//! 12,288-tet beam at dt 10 ms where 2+2 damped block-Jacobi sweeps needed 20.2 (see
//! docs/RESULTS.md), and it needs no damping factor (the Jacobi smoother spent 15 power
//! iterations per level and refresh on one).
//! The V-cycle pre-smooths with forward sweeps and post-smooths with backward sweeps (the
//! adjoint), so the preconditioner stays symmetric and CG stays valid.
//!
//! The sweeps a V-cycle with coarse levels runs are those of `full_rows.rs` (in half
//! precision, one thread) and `hybrid_rows.rs` (several threads); the ones here serve a
//! one-level V-cycle and the tests' references.
//!
//! Row `i` of `A` is its stored upper part (`A_ij`, `j > i`, in slots after the diagonal)
//! and its lower part (`A_ij = A_jiᵀ`, `j < i`, stored in row `j`): the lower part is
//! indexed once per structure (`lower_*`), so that a sweep reads every block once.

use nalgebra::{Matrix3, Vector3};

use super::galerkin::UpperCsr;
use crate::solver::BlockPattern;

type V3 = Vector3<f64>;

/// The row structure of a symmetric upper-stored block matrix, for Gauss–Seidel sweeps.
#[derive(Clone, Debug, Default)]
pub(super) struct SymRows {
    /// Slot of each row's diagonal block; the row's upper blocks follow it up to
    /// `upper_end[i]`.
    diag: Vec<u32>,
    upper_end: Vec<u32>,
    /// Column of every slot (slot-indexed; slots below the diagonal are unused).
    cols: Vec<u32>,
    /// Row `i`'s lower blocks: `lower_slots[lower_ptr[i]..lower_ptr[i + 1]]` (stored in
    /// row `lower_cols[k] < i`, used transposed).
    lower_ptr: Vec<u32>,
    lower_slots: Vec<u32>,
    lower_cols: Vec<u32>,
}

impl SymRows {
    fn from_rows(
        n: usize,
        slots: usize,
        upper: impl Fn(usize) -> (usize, usize),
        col: impl Fn(usize) -> usize,
    ) -> Self {
        let mut diag = Vec::with_capacity(n);
        let mut upper_end = Vec::with_capacity(n);
        let mut cols = vec![0u32; slots];
        let mut lower_count = vec![0u32; n + 1];
        for i in 0..n {
            let (d, e) = upper(i);
            diag.push(d as u32);
            upper_end.push(e as u32);
            for (k, c) in cols.iter_mut().enumerate().take(e).skip(d) {
                *c = col(k) as u32;
                if k > d {
                    lower_count[*c as usize + 1] += 1;
                }
            }
        }
        let mut lower_ptr = lower_count;
        for i in 0..n {
            lower_ptr[i + 1] += lower_ptr[i];
        }
        let total = lower_ptr[n] as usize;
        let mut fill: Vec<u32> = lower_ptr[..n].to_vec();
        let mut lower_slots = vec![0u32; total];
        let mut lower_cols = vec![0u32; total];
        // Rows visited in ascending order: each row's lower entries come out sorted.
        for i in 0..n {
            let (a, b) = (diag[i] as usize + 1, upper_end[i] as usize);
            for (k, &j) in (a..b).zip(&cols[a..b]) {
                let j = j as usize;
                let at = fill[j] as usize;
                lower_slots[at] = k as u32;
                lower_cols[at] = i as u32;
                fill[j] += 1;
            }
        }
        Self {
            diag,
            upper_end,
            cols,
            lower_ptr,
            lower_slots,
            lower_cols,
        }
    }

    /// The structure of the fine level's upper-stored [`BlockPattern`] blocks.
    pub fn of_pattern(pat: &BlockPattern) -> Self {
        let n = pat.num_rows();
        let mut row_end = vec![0usize; n];
        let mut col_of = vec![0usize; pat.num_blocks()];
        for (i, end) in row_end.iter_mut().enumerate() {
            for (s, j) in pat.row(i) {
                col_of[s] = j;
                *end = s + 1;
            }
        }
        let diag = pat.diagonal_slots();
        Self::from_rows(
            n,
            pat.num_blocks(),
            |i| (diag[i], row_end[i]),
            |s| col_of[s],
        )
    }

    /// The structure of a coarse level's [`UpperCsr`].
    pub fn of_upper(s: &UpperCsr) -> Self {
        Self::from_rows(
            s.num_rows(),
            s.cols.len(),
            |i| (s.row_ptr[i], s.row_ptr[i + 1]),
            |k| s.cols[k] as usize,
        )
    }

    pub fn num_rows(&self) -> usize {
        self.diag.len()
    }

    /// The diagonal blocks' inverses (zero for `skip` rows and singular blocks: those
    /// rows are left at zero by every sweep).
    pub fn diagonal_inverses(&self, blocks: &[Matrix3<f64>], skip: &[bool]) -> Vec<Matrix3<f64>> {
        self.diag
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                if skip.get(i).copied().unwrap_or(false) {
                    Matrix3::zeros()
                } else {
                    blocks[d as usize]
                        .try_inverse()
                        .unwrap_or_else(Matrix3::zeros)
                }
            })
            .collect()
    }

    /// Row `i`'s lower entries `(slot, column)`: blocks stored in the rows above, to be
    /// taken transposed.
    pub fn lower_entries(&self, i: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        let (a, b) = (self.lower_ptr[i] as usize, self.lower_ptr[i + 1] as usize);
        self.lower_slots[a..b]
            .iter()
            .zip(&self.lower_cols[a..b])
            .map(|(&s, &j)| (s as usize, j as usize))
    }

    /// Row `i`'s upper entries `(slot, column)`, diagonal excluded.
    pub fn upper_entries(&self, i: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        let (a, b) = (self.diag[i] as usize + 1, self.upper_end[i] as usize);
        (a..b).zip(&self.cols[a..b]).map(|(s, &j)| (s, j as usize))
    }

    /// Slot of row `i`'s diagonal block.
    pub fn diagonal_slot(&self, i: usize) -> usize {
        self.diag[i] as usize
    }

    /// `Σ_{j<i} A_ij z_j` of row `i`.
    #[inline]
    fn lower_product(&self, blocks: &[Matrix3<f64>], z: &[V3], i: usize) -> V3 {
        let (a, b) = (self.lower_ptr[i] as usize, self.lower_ptr[i + 1] as usize);
        let mut acc = V3::zeros();
        for (&s, &j) in self.lower_slots[a..b].iter().zip(&self.lower_cols[a..b]) {
            acc += blocks[s as usize].tr_mul(&z[j as usize]);
        }
        acc
    }

    /// `Σ_{j>i} A_ij z_j` of row `i`.
    #[inline]
    fn upper_product(&self, blocks: &[Matrix3<f64>], z: &[V3], i: usize) -> V3 {
        let (a, b) = (self.diag[i] as usize + 1, self.upper_end[i] as usize);
        let mut acc = V3::zeros();
        for (blk, &j) in blocks[a..b].iter().zip(&self.cols[a..b]) {
            acc += blk * z[j as usize];
        }
        acc
    }

    /// One forward sweep from `z = 0`: `(D + L) z = r`. Rows with a zero inverse stay 0.
    pub fn forward_from_zero(
        &self,
        blocks: &[Matrix3<f64>],
        dinv: &[Matrix3<f64>],
        r: &[V3],
        z: &mut [V3],
    ) {
        for i in 0..self.num_rows() {
            let s = r[i] - self.lower_product(blocks, z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// The residual `r − A z` right after [`SymRows::forward_from_zero`]: `−U z` (half a
    /// product, as `(D + L) z = r`).
    pub fn residual_after_forward_from_zero(
        &self,
        blocks: &[Matrix3<f64>],
        z: &[V3],
        out: &mut [V3],
    ) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = -self.upper_product(blocks, z, i);
        }
    }

    /// One forward sweep `z_i ← D_i⁻¹ (r_i − Σ_{j≠i} A_ij z_j)`, rows ascending.
    pub fn forward(&self, blocks: &[Matrix3<f64>], dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in 0..self.num_rows() {
            let s = r[i] - self.lower_product(blocks, z, i) - self.upper_product(blocks, z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// One backward sweep (rows descending): the adjoint of [`SymRows::forward`].
    pub fn backward(&self, blocks: &[Matrix3<f64>], dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in (0..self.num_rows()).rev() {
            let s = r[i] - self.lower_product(blocks, z, i) - self.upper_product(blocks, z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// `out = r − A z`.
    pub fn residual(&self, blocks: &[Matrix3<f64>], r: &[V3], z: &[V3], out: &mut [V3]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.residual_row(blocks, r, z, i);
        }
    }

    /// `(r − A z)_i`.
    #[inline]
    fn residual_row(&self, blocks: &[Matrix3<f64>], r: &[V3], z: &[V3], i: usize) -> V3 {
        let d = blocks[self.diag[i] as usize] * z[i];
        r[i] - d - self.lower_product(blocks, z, i) - self.upper_product(blocks, z, i)
    }
}

/// Pre-smoothing: `sweeps` forward sweeps from `z = 0`, leaving the residual `r − A z` in
/// `res`.
pub(super) fn pre_smooth(
    rows: &SymRows,
    blocks: &[Matrix3<f64>],
    dinv: &[Matrix3<f64>],
    r: &[V3],
    z: &mut [V3],
    res: &mut [V3],
    sweeps: usize,
) {
    rows.forward_from_zero(blocks, dinv, r, z);
    if sweeps <= 1 {
        rows.residual_after_forward_from_zero(blocks, z, res);
        return;
    }
    for _ in 1..sweeps {
        rows.forward(blocks, dinv, r, z);
    }
    rows.residual(blocks, r, z, res);
}

/// Post-smoothing: `sweeps` backward sweeps on `z`.
pub(super) fn post_smooth(
    rows: &SymRows,
    blocks: &[Matrix3<f64>],
    dinv: &[Matrix3<f64>],
    r: &[V3],
    z: &mut [V3],
    sweeps: usize,
) {
    for _ in 0..sweeps {
        rows.backward(blocks, dinv, r, z);
    }
}

/// `sweeps` symmetric sweeps (forward then backward) from `z = 0`: a symmetric
/// approximate inverse, for a coarsest level too large for the dense solve.
pub(super) fn symmetric_smooth(
    rows: &SymRows,
    blocks: &[Matrix3<f64>],
    dinv: &[Matrix3<f64>],
    r: &[V3],
    z: &mut [V3],
    sweeps: usize,
) {
    rows.forward_from_zero(blocks, dinv, r, z);
    rows.backward(blocks, dinv, r, z);
    for _ in 1..sweeps {
        rows.forward(blocks, dinv, r, z);
        rows.backward(blocks, dinv, r, z);
    }
}
