//! The finest level's Gauss–Seidel sweeps on several threads: ℓ1 hybrid Gauss–Seidel
//! (Gauss–Seidel inside contiguous parts of the rows, Jacobi between them) with each part
//! swept by its own [`FullRows`], the half-precision sweeps of one thread.
//!
//! Each part sweeps its own rows in order and reads the other parts' values as they were
//! when the sweep began. Each interface row's diagonal block is enlarged by the ℓ1 norm of
//! its entries in other parts (Baker, Falgout, Kolev and Yang, "Multigrid smoothers for
//! ultraparallel computing", SIAM J. Sci. Comput. 2011), which keeps the smoother
//! convergent in the energy norm for any split, so the V-cycle stays a valid CG
//! preconditioner. The backward sweep is the forward one's adjoint.
//!
//! A part's [`FullRows`] holds only the blocks between its own rows. The blocks between
//! parts (the *coupling*, a thin layer of rows with the lattice's spatially ordered
//! nodes) are applied here, on one thread, before a sweep (to its right-hand side) and
//! after it (to the residual). They are rounded exactly as the parts' blocks are
//! ([`rounded_block`]), so that every sweep acts on the same matrix `A'` and the V-cycle
//! stays symmetric to single precision, as on one thread.
//!
//! In the correction form of ℓ1 Gauss–Seidel, `z_i += D̃_i⁻¹ (b_i − Σ_j A_ij z_j)` with
//! `D̃_i = D_i + diag(ℓ1_i)`; a part's sweep computes `z_i = D̃_i⁻¹ (b'_i − Σ_{j≠i} A_ij
//! z_j)` over its own columns, which is the same update for `b'_i = b_i − Σ_{j∉part}
//! A_ij z_j + ℓ1_i ∘ z_i` (old values, taken before the sweep).
//!
//! Why (2026-11-28): the hybrid sweeps had been made on [`SymRows`] in f64, reading each
//! lower block from the row that stores it. With two threads an MG-PCG step of the
//! 12,288-tet beams took 5.9–6.8 ms against 3.8–4.9 ms on one thread, which sweeps
//! [`FullRows`] (interleaved runs, docs/RESULTS.md, with the measurements since).
//!
//! Results depend on the split, not on the threads that run it: each part writes only its
//! own rows, and the coupling is applied on one thread in row order.

use nalgebra::{Matrix3, Vector3};

use super::full_rows::{FullRows, rounded_block};
use super::smoother::SymRows;
use crate::parallel::{run_parts, split_ranges};

type V3 = Vector3<f64>;

/// The finest level's rows in contiguous parts, each swept by its own thread.
#[derive(Clone, Debug)]
pub(super) struct HybridRows {
    /// Row where each part starts, then the row count (`parts + 1` entries).
    bounds: Vec<usize>,
    /// Each part's own blocks.
    parts: Vec<FullRows>,
    /// Rows with blocks in other parts (ascending) and their entries in
    /// `coupling_ptr[k]..coupling_ptr[k + 1]`.
    coupling_rows: Vec<u32>,
    coupling_ptr: Vec<u32>,
    /// Per entry: the block's slot in the fine storage, whether it is taken transposed,
    /// and its column.
    coupling_src: Vec<(u32, bool, u32)>,
    /// Per entry, the block as the sweeps see it (refreshed by [`HybridRows::fill`]).
    coupling_blocks: Vec<Matrix3<f64>>,
    /// Per part, the index of its first row in `coupling_rows`, then their count.
    coupling_start: Vec<usize>,
    /// Per coupling row, the ℓ1 enlargement of its diagonal, `D̃_i − D_i`.
    l1: Vec<V3>,
    /// Per coupling row, `b'_i − r_i` of the sweep being prepared.
    delta: Vec<V3>,
    /// The right-hand side of a sweep (`b'` of the module documentation).
    rhs: Vec<V3>,
}

/// Row `i`'s ℓ1 norms, per scalar row of its block, of its entries outside `s..e`.
fn l1_outside(rows: &SymRows, blocks: &[Matrix3<f64>], i: usize, (s, e): (usize, usize)) -> V3 {
    let mut l1 = V3::zeros();
    for (slot, j) in rows.lower_entries(i) {
        if j < s {
            // Row i's block is the stored one transposed: its row sums are the stored
            // block's column sums.
            let m = blocks[slot].abs();
            l1 += V3::new(m.column(0).sum(), m.column(1).sum(), m.column(2).sum());
        }
    }
    for (slot, j) in rows.upper_entries(i) {
        if j >= e {
            let m = blocks[slot].abs();
            l1 += V3::new(m.row(0).sum(), m.row(1).sum(), m.row(2).sum());
        }
    }
    l1
}

impl HybridRows {
    /// A split of `rows` at `bounds` (ascending, first 0, last the row count), or `None`
    /// when it has fewer than two parts or is not such a split.
    pub fn new(rows: &SymRows, bounds: &[usize]) -> Option<Self> {
        let n = rows.num_rows();
        let ok = bounds.len() >= 3
            && bounds[0] == 0
            && bounds.last() == Some(&n)
            && bounds.windows(2).all(|w| w[0] <= w[1]);
        if !ok {
            return None;
        }
        let parts = bounds
            .windows(2)
            .map(|w| FullRows::of_range(rows, w[0], w[1]))
            .collect();
        let (mut coupling_rows, mut coupling_ptr, mut coupling_src) = (vec![], vec![0], vec![]);
        let mut coupling_start = vec![0];
        for w in bounds.windows(2) {
            for i in w[0]..w[1] {
                let outside = |j: &usize| !(w[0]..w[1]).contains(j);
                let before = coupling_src.len();
                coupling_src.extend(
                    rows.lower_entries(i)
                        .filter(|(_, j)| outside(j))
                        .map(|(slot, j)| (slot as u32, true, j as u32)),
                );
                coupling_src.extend(
                    rows.upper_entries(i)
                        .filter(|(_, j)| outside(j))
                        .map(|(slot, j)| (slot as u32, false, j as u32)),
                );
                if coupling_src.len() > before {
                    coupling_rows.push(i as u32);
                    coupling_ptr.push(coupling_src.len() as u32);
                }
            }
            coupling_start.push(coupling_rows.len());
        }
        let coupled = coupling_rows.len();
        Some(Self {
            bounds: bounds.to_vec(),
            parts,
            coupling_blocks: vec![Matrix3::zeros(); coupling_src.len()],
            coupling_rows,
            coupling_ptr,
            coupling_src,
            coupling_start,
            l1: vec![V3::zeros(); coupled],
            delta: vec![V3::zeros(); coupled],
            rhs: vec![V3::zeros(); n],
        })
    }

    pub fn bounds(&self) -> &[usize] {
        &self.bounds
    }

    /// The part holding row `i`: its range.
    fn part_of(&self, i: usize) -> (usize, usize) {
        let p = self.bounds.partition_point(|&b| b <= i) - 1;
        (self.bounds[p], self.bounds[p + 1])
    }

    /// ℓ1 diagonal inverses: `(A_ii + diag(Σ_{j in other parts} Σ_c |(A_ij)_rc|))⁻¹` per
    /// row `r` of the block (zero for `skip` rows and singular blocks), every part at
    /// once.
    pub fn diagonal_inverses(
        &self,
        rows: &SymRows,
        blocks: &[Matrix3<f64>],
        skip: &[bool],
    ) -> Vec<Matrix3<f64>> {
        let mut out = vec![Matrix3::zeros(); rows.num_rows()];
        let bounds = &self.bounds;
        run_parts(split_ranges(&mut out, bounds), |p, part| {
            let (s, e) = (bounds[p], bounds[p + 1]);
            for (i, d) in (s..e).zip(part) {
                if skip.get(i).copied().unwrap_or(false) {
                    continue;
                }
                let l1 = l1_outside(rows, blocks, i, (s, e));
                if let Some(inv) =
                    (blocks[rows.diagonal_slot(i)] + Matrix3::from_diagonal(&l1)).try_inverse()
                {
                    *d = inv;
                }
            }
        });
        out
    }

    /// Copies the step's blocks (`fine`, indexed by `rows`) and the ℓ1 diagonal inverses
    /// of [`HybridRows::diagonal_inverses`] in, every part at once.
    pub fn fill(&mut self, rows: &SymRows, fine: &[Matrix3<f64>], dinv: &[Matrix3<f64>]) {
        run_parts(self.parts.iter_mut().collect(), |_, part| {
            part.fill(rows, fine, dinv)
        });
        let scale = |j: usize| {
            let p = self.bounds.partition_point(|&b| b <= j) - 1;
            self.parts[p].row_scale(j - self.bounds[p])
        };
        for (k, &i) in self.coupling_rows.iter().enumerate() {
            let i = i as usize;
            let si = scale(i);
            let (a, b) = (
                self.coupling_ptr[k] as usize,
                self.coupling_ptr[k + 1] as usize,
            );
            for (out, &(slot, transposed, j)) in self.coupling_blocks[a..b]
                .iter_mut()
                .zip(&self.coupling_src[a..b])
            {
                *out = rounded_block(fine, slot as usize, transposed, si, scale(j as usize));
            }
            // A row the sweeps leave at zero (zero inverse) needs no enlargement.
            self.l1[k] = if dinv[i] == Matrix3::zeros() {
                V3::zeros()
            } else {
                l1_outside(rows, fine, i, self.part_of(i))
            };
        }
    }

    /// `Σ_{j∉part} A'_ij z_j` of coupling row `k`.
    fn coupling_product(&self, k: usize, z: &[V3]) -> V3 {
        let (a, b) = (
            self.coupling_ptr[k] as usize,
            self.coupling_ptr[k + 1] as usize,
        );
        self.coupling_blocks[a..b]
            .iter()
            .zip(&self.coupling_src[a..b])
            .map(|(blk, &(_, _, j))| blk * z[j as usize])
            .sum()
    }

    /// The sweep's right-hand side's differences from `r` on the coupling rows, from `z`
    /// (one thread): `b'_i − r_i = ℓ1_i ∘ z_i − Σ_{j∉part} A'_ij z_j` into `delta`.
    fn sweep_deltas(&mut self, z: &[V3]) {
        for k in 0..self.coupling_rows.len() {
            let i = self.coupling_rows[k] as usize;
            self.delta[k] = self.l1[k].component_mul(&z[i]) - self.coupling_product(k, z);
        }
    }

    /// One sweep (`backward`, else forward) from `z` in every part at once, each part
    /// first writing its rows of the right-hand side `r + delta` (see
    /// [`HybridRows::sweep_deltas`]).
    fn sweep_from(&mut self, r: &[V3], z: &mut [V3], backward: bool) {
        self.sweep_deltas(z);
        let (rows, starts, delta) = (&self.coupling_rows, &self.coupling_start, &self.delta);
        let bounds = &self.bounds;
        each_part(
            &mut self.parts,
            bounds,
            r,
            z,
            &mut self.rhs,
            |p, part, rp, zp, rhs| {
                rhs.copy_from_slice(rp);
                for k in starts[p]..starts[p + 1] {
                    rhs[rows[k] as usize - bounds[p]] += delta[k];
                }
                if backward {
                    part.backward(rhs, zp);
                } else {
                    part.forward(rhs, zp);
                }
            },
        );
    }

    /// Pre-smoothing as [`FullRows::pre_smooth`], every part at once: `sweeps` forward
    /// sweeps from zero, then the residual `r − A' z` into `res`.
    pub fn pre_smooth(&mut self, r: &[V3], z: &mut [V3], res: &mut [V3], sweeps: usize) {
        let bounds = &self.bounds;
        if sweeps <= 1 {
            // From zero the right-hand side is `r`; right after the sweep, on a part's
            // rows, `r − D z − L z = ℓ1 ∘ z` (the sweep solved `(D̃ + L) z = r`). On a
            // row the sweeps leave at zero (a fixed node) this is not its residual; the
            // prolongation leaves those rows out.
            each_part(
                &mut self.parts,
                bounds,
                r,
                z,
                res,
                |_, part, rp, zp, resp| {
                    part.forward_from_zero(rp, zp);
                    part.minus_upper_after_forward(zp, resp);
                },
            );
            for k in 0..self.coupling_rows.len() {
                let i = self.coupling_rows[k] as usize;
                res[i] += self.l1[k].component_mul(&z[i]) - self.coupling_product(k, z);
            }
            return;
        }
        each_part(
            &mut self.parts,
            bounds,
            r,
            z,
            &mut [],
            |_, part, rp, zp, _| part.forward_from_zero(rp, zp),
        );
        for _ in 1..sweeps {
            self.sweep_from(r, z, false);
        }
        let bounds = &self.bounds;
        each_part(
            &mut self.parts,
            bounds,
            r,
            z,
            res,
            |_, part, rp, zp, resp| part.residual(rp, zp, resp),
        );
        for k in 0..self.coupling_rows.len() {
            let i = self.coupling_rows[k] as usize;
            res[i] -= self.coupling_product(k, z);
        }
    }

    /// Post-smoothing as [`FullRows::post_smooth`], every part at once: `sweeps` backward
    /// sweeps from `z`.
    pub fn post_smooth(&mut self, r: &[V3], z: &mut [V3], sweeps: usize) {
        for _ in 0..sweeps {
            self.sweep_from(r, z, true);
        }
    }
}

/// Runs `f(p, part, r_p, z_p, out_p)` on every part `p` at once, with its rows of `r`, of
/// `z` and of `out` (empty: none).
fn each_part(
    parts: &mut [FullRows],
    bounds: &[usize],
    r: &[V3],
    z: &mut [V3],
    out: &mut [V3],
    f: impl Fn(usize, &mut FullRows, &[V3], &mut [V3], &mut [V3]) + Sync,
) {
    let outs = if out.is_empty() {
        (0..parts.len()).map(|_| &mut [][..]).collect()
    } else {
        split_ranges(out, bounds)
    };
    let items: Vec<_> = parts
        .iter_mut()
        .zip(split_ranges(z, bounds))
        .zip(outs)
        .collect();
    run_parts(items, |p, ((part, zp), op)| {
        f(p, part, &r[bounds[p]..bounds[p + 1]], zp, op)
    });
}
