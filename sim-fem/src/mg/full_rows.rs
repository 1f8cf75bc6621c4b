//! The finest level's matrix as the sequential Gauss–Seidel sweeps read it: every row's
//! off-diagonal blocks in one contiguous run (its lower part, transposed from the upper
//! storage, then its upper part), in single precision, rebuilt from the step's assembled
//! blocks every solve.
//!
//! Why: `perf` over 60 steps of the 12,288-tet soft beam at dt 10 ms (MG-PCG to 1e-6, one
//! thread, 2026-11-27) put 20 % of the step in the lower-part products of [`SymRows`],
//! which gather every block from the row that stores it, against 10 % for the upper part
//! that reads its own row in order. Here both parts are read in order, once per sweep,
//! and each block takes 48 bytes instead of 72. A preconditioner needs no more precision:
//! CG's own products stay in f64; the smoothed matrix's blocks are rounded to f32 (a lower
//! block is the rounded upper one, transposed), and the sweeps read the iterate in f32 too,
//! so the V-cycle is symmetric and linear only to single precision (below).
//!
//! The products are 4-lane single-precision vectors ([`wide::f32x4`]: SSE on x86-64, NEON
//! on aarch64, scalar elsewhere): a block is its three columns, each padded to four lanes,
//! and `A z` is three lane-wise multiply-adds (one accumulator per column, so that the
//! sweep does not wait on one long chain) with the broadcast components of `z`, read from
//! an f32 copy of the iterate that each sweep keeps current. Scalar f64 products of f32
//! blocks spent most of their instructions converting the nine entries to f64 (callgrind,
//! 12,288-tet soft beam, 2026-11-27: see docs/RESULTS.md). Summing in f32 makes the
//! V-cycle symmetric to single precision (about 1e-7 relative) rather than to f64; CG to
//! the step's 1e-6 takes the same iterations as with f64 sums, and MG-PCG still matches
//! the dense Cholesky solve at 1e-9 (the V-cycle symmetry test allows 1e-6 on this path).
//! The sums multiply then add (no fused multiply-add, whatever the build's target
//! features), so that every site computes the same bits.

use nalgebra::{Matrix3, Vector3};
use wide::f32x4;

use super::smoother::SymRows;

type V3 = Vector3<f64>;

/// A 3×3 block in single precision: its columns, each `[a_0k, a_1k, a_2k, 0]`.
type Block32 = [f32x4; 3];

/// Bit of [`FullRows::src`] marking a block taken transposed.
const TRANSPOSED: u32 = 1 << 31;

/// The finest level's off-diagonal blocks by full rows (see the module documentation).
#[derive(Clone, Debug, Default)]
pub(super) struct FullRows {
    /// Row `i`'s entries are `row_ptr[i]..row_ptr[i + 1]`; its lower ones (columns below
    /// `i`) end at `upper_start[i]`.
    row_ptr: Vec<u32>,
    upper_start: Vec<u32>,
    cols: Vec<u32>,
    /// Slot of each entry in the fine block storage ([`TRANSPOSED`]: taken transposed).
    src: Vec<u32>,
    /// The entries' blocks, refreshed by [`FullRows::fill`].
    blocks: Vec<Block32>,
    /// Diagonal blocks (f64: the sweeps divide by them through their inverses, kept by
    /// the caller; the residual of several sweeps multiplies by them).
    diag: Vec<Matrix3<f64>>,
    /// The iterate in single precision, `[x, y, z, 0]` per node, as the products read it:
    /// set from `z` when a sweep starts and updated row by row as the sweep writes `z`.
    z32: Vec<[f32; 4]>,
}

#[inline]
fn to_f32(v: &V3) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, 0.0]
}

#[inline]
fn to_v3(a: f32x4) -> V3 {
    let [x, y, z, _] = a.to_array();
    V3::new(f64::from(x), f64::from(y), f64::from(z))
}

impl FullRows {
    /// The layout of `rows` (blocks zero until [`FullRows::fill`]).
    pub fn of(rows: &SymRows) -> Self {
        let n = rows.num_rows();
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut upper_start = Vec::with_capacity(n);
        let mut cols = Vec::new();
        let mut src = Vec::new();
        row_ptr.push(0);
        for i in 0..n {
            for (slot, j) in rows.lower_entries(i) {
                cols.push(j as u32);
                src.push(slot as u32 | TRANSPOSED);
            }
            upper_start.push(cols.len() as u32);
            for (slot, j) in rows.upper_entries(i) {
                cols.push(j as u32);
                src.push(slot as u32);
            }
            row_ptr.push(cols.len() as u32);
        }
        let entries = cols.len();
        Self {
            row_ptr,
            upper_start,
            cols,
            src,
            blocks: vec![[f32x4::ZERO; 3]; entries],
            diag: vec![Matrix3::zeros(); n],
            z32: vec![[0.0; 4]; n],
        }
    }

    /// Copies the step's blocks (`fine`: the upper storage `rows` indexes) in.
    pub fn fill(&mut self, rows: &SymRows, fine: &[Matrix3<f64>]) {
        for (out, &s) in self.blocks.iter_mut().zip(&self.src) {
            let b = &fine[(s & !TRANSPOSED) as usize];
            let b = if s & TRANSPOSED != 0 {
                b.transpose()
            } else {
                *b
            };
            // nalgebra stores column-major: column k is `b.column(k)`.
            *out = std::array::from_fn(|k| {
                f32x4::new([b[(0, k)] as f32, b[(1, k)] as f32, b[(2, k)] as f32, 0.0])
            });
        }
        for (i, d) in self.diag.iter_mut().enumerate() {
            *d = fine[rows.diagonal_slot(i)];
        }
    }

    fn num_rows(&self) -> usize {
        self.upper_start.len()
    }

    /// The f32 copy of the iterate set from `z`.
    fn load(&mut self, z: &[V3]) {
        for (a, v) in self.z32.iter_mut().zip(z) {
            *a = to_f32(v);
        }
    }

    /// `Σ A_ij z_j` over entries `from..to`, from the f32 iterate.
    #[inline]
    fn product(&self, from: usize, to: usize) -> V3 {
        // One accumulator per column: three independent chains of multiply-adds rather
        // than one three times as long (the sweep waits on this sum row after row).
        let (mut a0, mut a1, mut a2) = (f32x4::ZERO, f32x4::ZERO, f32x4::ZERO);
        for (b, &j) in self.blocks[from..to].iter().zip(&self.cols[from..to]) {
            let zj = &self.z32[j as usize];
            // Multiply, then add: `mul_add` would fuse in builds with FMA enabled and
            // change the bits between sites built differently.
            a0 += b[0] * f32x4::splat(zj[0]);
            a1 += b[1] * f32x4::splat(zj[1]);
            a2 += b[2] * f32x4::splat(zj[2]);
        }
        to_v3(a0 + a1 + a2)
    }

    #[inline]
    fn lower(&self, i: usize) -> V3 {
        self.product(self.row_ptr[i] as usize, self.upper_start[i] as usize)
    }

    #[inline]
    fn upper(&self, i: usize) -> V3 {
        self.product(self.upper_start[i] as usize, self.row_ptr[i + 1] as usize)
    }

    #[inline]
    fn off_diagonal(&self, i: usize) -> V3 {
        self.product(self.row_ptr[i] as usize, self.row_ptr[i + 1] as usize)
    }

    /// Row `i` of a sweep: `z_i = D_i⁻¹ (r_i − Σ_{j≠i} A_ij z_j)` (only the lower part
    /// from zero), in both copies of the iterate.
    #[inline]
    fn relax(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3], i: usize, lower: bool) {
        let off = if lower {
            self.lower(i)
        } else {
            self.off_diagonal(i)
        };
        z[i] = dinv[i] * (r[i] - off);
        self.z32[i] = to_f32(&z[i]);
    }

    /// One forward sweep from `z = 0` ([`SymRows::forward_from_zero`]): the lower part
    /// reads only rows this sweep has already written.
    pub fn forward_from_zero(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in 0..self.num_rows() {
            self.relax(dinv, r, z, i, true);
        }
    }

    /// The residual right after [`FullRows::forward_from_zero`]: `−U z`.
    #[cfg(test)]
    pub fn residual_after_forward_from_zero(&mut self, z: &[V3], out: &mut [V3]) {
        self.load(z);
        for (i, o) in out.iter_mut().enumerate() {
            *o = -self.upper(i);
        }
    }

    /// One forward sweep (`z32` must hold `z`).
    fn forward_loaded(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in 0..self.num_rows() {
            self.relax(dinv, r, z, i, false);
        }
    }

    /// One backward sweep (the forward sweep's adjoint; `z32` must hold `z`).
    fn backward_loaded(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in (0..self.num_rows()).rev() {
            self.relax(dinv, r, z, i, false);
        }
    }

    /// One backward sweep from `z`.
    #[cfg(test)]
    pub fn backward(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        self.load(z);
        self.backward_loaded(dinv, r, z);
    }

    /// `out = r − A z` (`z32` must hold `z`).
    fn residual_loaded(&self, r: &[V3], z: &[V3], out: &mut [V3]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = r[i] - self.diag[i] * z[i] - self.off_diagonal(i);
        }
    }

    /// Pre-smoothing: `sweeps` forward sweeps from zero, then the residual into `res`
    /// (as [`super::smoother::pre_smooth`]).
    pub fn pre_smooth(
        &mut self,
        dinv: &[Matrix3<f64>],
        r: &[V3],
        z: &mut [V3],
        res: &mut [V3],
        sweeps: usize,
    ) {
        self.forward_from_zero(dinv, r, z);
        if sweeps <= 1 {
            // z32 holds z: the sweep wrote every row of both.
            for (i, o) in res.iter_mut().enumerate() {
                *o = -self.upper(i);
            }
            return;
        }
        for _ in 1..sweeps {
            self.forward_loaded(dinv, r, z);
        }
        self.residual_loaded(r, z, res);
    }

    /// Post-smoothing: `sweeps` backward sweeps from `z`.
    pub fn post_smooth(&mut self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3], sweeps: usize) {
        self.load(z);
        for _ in 0..sweeps {
            self.backward_loaded(dinv, r, z);
        }
    }
}
