//! Geometric multigrid as the preconditioner of CG: a V-cycle over a nested hierarchy of
//! node sets given by the caller as sparse prolongations (sim-core builds them from the
//! lattice's bisection hierarchy: weight 1 for a node kept on the coarser level, ½ and ½
//! from the two ends of the edge a node bisects), Galerkin coarse operators `Pᵀ A P`
//! refreshed every few steps (CG stays convergent with a slightly stale preconditioner),
//! symmetric 3×3-block Gauss–Seidel smoothing (forward sweeps down, backward sweeps up:
//! `smoother.rs`, in single precision by full rows: `full_rows.rs`) and a dense Cholesky
//! solve on the coarsest level (`dense.rs`).
//!
//! Fixed (Dirichlet) nodes: their prolongation rows are zero on the finest level, and a
//! coarse node that is the image (weight 1) of a fixed node is dropped from the coarse
//! levels, as is a coarse node no free fine node interpolates from. Coarse levels thus
//! hold free nodes only and need no projection.

mod dense;
mod full_rows;
mod galerkin;
mod hybrid_rows;
mod smoother;
#[cfg(test)]
mod tests;
mod vcycle;

pub use vcycle::{MgParams, Multigrid};

use crate::FemError;

/// A sparse prolongation from a coarse node set to a finer one: fine node `i` takes
/// `Σ w · coarse[c]` over its row's entries `(c, w)`. Scalar weights; they act on each of
/// the three displacement components alike.
#[derive(Clone, Debug, PartialEq)]
pub struct Prolongation {
    coarse_len: usize,
    row_ptr: Vec<u32>,
    cols: Vec<u32>,
    weights: Vec<f64>,
}

impl Prolongation {
    /// From one row per fine node (empty rows allowed: the node gets no coarse
    /// correction). Errors name the first bad entry: a column out of range or a
    /// non-finite weight.
    pub fn from_rows(coarse_len: usize, rows: &[Vec<(usize, f64)>]) -> Result<Self, FemError> {
        let mut row_ptr = Vec::with_capacity(rows.len() + 1);
        let mut cols = Vec::new();
        let mut weights = Vec::new();
        row_ptr.push(0);
        for (i, row) in rows.iter().enumerate() {
            for &(c, w) in row {
                if c >= coarse_len || !w.is_finite() {
                    return Err(FemError::BadParameter(format!(
                        "prolongation row {i}: entry ({c}, {w}) with {coarse_len} coarse nodes"
                    )));
                }
                cols.push(c as u32);
                weights.push(w);
            }
            row_ptr.push(cols.len() as u32);
        }
        Ok(Self {
            coarse_len,
            row_ptr,
            cols,
            weights,
        })
    }

    /// Number of fine nodes (rows).
    pub fn fine_len(&self) -> usize {
        self.row_ptr.len() - 1
    }

    /// Number of coarse nodes (columns).
    pub fn coarse_len(&self) -> usize {
        self.coarse_len
    }

    /// Entries `(coarse node, weight)` of fine node `i`.
    #[inline]
    pub fn row(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let (a, b) = (self.row_ptr[i] as usize, self.row_ptr[i + 1] as usize);
        self.cols[a..b]
            .iter()
            .zip(&self.weights[a..b])
            .map(|(c, w)| (*c as usize, *w))
    }

    /// Number of stored entries.
    pub fn num_entries(&self) -> usize {
        self.cols.len()
    }
}

/// A hierarchy of prolongations, finest first: `levels[0]` maps level 1 onto the FEM
/// nodes, `levels[k]` level `k + 1` onto level `k`. Consecutive sizes must match.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Hierarchy {
    /// Prolongations, finest first.
    pub levels: Vec<Prolongation>,
}

impl Hierarchy {
    /// Checks that the levels chain (`coarse_len` of one = `fine_len` of the next) and
    /// that the finest has `nodes` rows.
    pub fn validate(&self, nodes: usize) -> Result<(), FemError> {
        let mut expect = nodes;
        for (k, p) in self.levels.iter().enumerate() {
            if p.fine_len() != expect {
                return Err(FemError::BadParameter(format!(
                    "multigrid level {k}: prolongation has {} fine rows, expected {expect}",
                    p.fine_len()
                )));
            }
            expect = p.coarse_len();
        }
        Ok(())
    }
}
