//! The finest level's matrix as the sequential Gauss–Seidel sweeps read it: every row's
//! off-diagonal blocks in one contiguous run (its lower part, transposed from the upper
//! storage, then its upper part), in single precision, rebuilt from the step's assembled
//! blocks every solve.
//!
//! Why: `perf` over 60 steps of the 12,288-tet soft beam at dt 10 ms (MG-PCG to 1e-6, one
//! thread, 2026-11-27) put 20 % of the step in the lower-part products of [`SymRows`],
//! which gather every block from the row that stores it, against 10 % for the upper part
//! that reads its own row in order. Here both parts are read in order, once per sweep,
//! and each block takes 36 bytes instead of 72. A preconditioner needs no more precision:
//! CG's own products stay in f64, and the blocks' rounding (relative 6e-8) keeps the
//! smoothed matrix symmetric (a lower block is the rounded upper one, transposed) and
//! positive definite, so the V-cycle stays a valid CG preconditioner.

use nalgebra::{Matrix3, Vector3};

use super::smoother::SymRows;

type V3 = Vector3<f64>;

/// A 3×3 block in single precision, row-major.
type Block32 = [f32; 9];

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
}

#[inline]
fn mul(b: &Block32, z: &V3) -> V3 {
    let [a, bb, c, d, e, f, g, h, k] = b.map(f64::from);
    V3::new(
        a * z.x + bb * z.y + c * z.z,
        d * z.x + e * z.y + f * z.z,
        g * z.x + h * z.y + k * z.z,
    )
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
            blocks: vec![[0.0; 9]; entries],
            diag: vec![Matrix3::zeros(); n],
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
            // nalgebra stores column-major: row-major copy, element by element.
            *out = [
                b[(0, 0)] as f32,
                b[(0, 1)] as f32,
                b[(0, 2)] as f32,
                b[(1, 0)] as f32,
                b[(1, 1)] as f32,
                b[(1, 2)] as f32,
                b[(2, 0)] as f32,
                b[(2, 1)] as f32,
                b[(2, 2)] as f32,
            ];
        }
        for (i, d) in self.diag.iter_mut().enumerate() {
            *d = fine[rows.diagonal_slot(i)];
        }
    }

    fn num_rows(&self) -> usize {
        self.upper_start.len()
    }

    #[inline]
    fn product(&self, z: &[V3], from: usize, to: usize) -> V3 {
        let mut acc = V3::zeros();
        for (b, &j) in self.blocks[from..to].iter().zip(&self.cols[from..to]) {
            acc += mul(b, &z[j as usize]);
        }
        acc
    }

    #[inline]
    fn lower(&self, z: &[V3], i: usize) -> V3 {
        self.product(z, self.row_ptr[i] as usize, self.upper_start[i] as usize)
    }

    #[inline]
    fn upper(&self, z: &[V3], i: usize) -> V3 {
        self.product(
            z,
            self.upper_start[i] as usize,
            self.row_ptr[i + 1] as usize,
        )
    }

    #[inline]
    fn off_diagonal(&self, z: &[V3], i: usize) -> V3 {
        self.product(z, self.row_ptr[i] as usize, self.row_ptr[i + 1] as usize)
    }

    /// One forward sweep from `z = 0` ([`SymRows::forward_from_zero`]).
    pub fn forward_from_zero(&self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in 0..self.num_rows() {
            let s = r[i] - self.lower(z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// The residual right after [`FullRows::forward_from_zero`]: `−U z`.
    pub fn residual_after_forward_from_zero(&self, z: &[V3], out: &mut [V3]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = -self.upper(z, i);
        }
    }

    /// One forward sweep.
    pub fn forward(&self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in 0..self.num_rows() {
            let s = r[i] - self.off_diagonal(z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// One backward sweep (the forward sweep's adjoint).
    pub fn backward(&self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        for i in (0..self.num_rows()).rev() {
            let s = r[i] - self.off_diagonal(z, i);
            z[i] = dinv[i] * s;
        }
    }

    /// `out = r − A z`.
    pub fn residual(&self, r: &[V3], z: &[V3], out: &mut [V3]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = r[i] - self.diag[i] * z[i] - self.off_diagonal(z, i);
        }
    }

    /// Pre-smoothing: `sweeps` forward sweeps from zero, then the residual into `res`
    /// (as [`super::smoother::pre_smooth`]).
    pub fn pre_smooth(
        &self,
        dinv: &[Matrix3<f64>],
        r: &[V3],
        z: &mut [V3],
        res: &mut [V3],
        sweeps: usize,
    ) {
        self.forward_from_zero(dinv, r, z);
        if sweeps <= 1 {
            self.residual_after_forward_from_zero(z, res);
            return;
        }
        for _ in 1..sweeps {
            self.forward(dinv, r, z);
        }
        self.residual(r, z, res);
    }

    /// Post-smoothing: `sweeps` backward sweeps.
    pub fn post_smooth(&self, dinv: &[Matrix3<f64>], r: &[V3], z: &mut [V3], sweeps: usize) {
        for _ in 0..sweeps {
            self.backward(dinv, r, z);
        }
    }
}
