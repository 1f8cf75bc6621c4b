//! The `direct` linear solver: faer's sparse Cholesky (`LLᵀ`, AMD fill-reducing ordering)
//! of the linearised step's assembled matrix, restricted to the free degrees of freedom.
//!
//! The symbolic analysis (ordering and elimination tree) depends only on the block pattern
//! and the Dirichlet mask, so it is done once and kept until either changes (a topology
//! change, a grasp that fixes nodes); every step then refactorises numerically, because
//! the rotations change the matrix. The solve is exact up to round-off: its relative
//! residual (measured after the solve, one extra product) is about 1e-14 on the beams.

use faer::linalg::solvers::SolveCore;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Mat, Side};
use nalgebra::Matrix3;

use crate::FemError;
use crate::solver::BlockPattern;

type V3 = nalgebra::Vector3<f64>;

/// One stored entry of the upper triangle: block slot of the pattern and its `(row, col)`
/// inside the 3×3 block.
#[derive(Clone, Copy, Debug)]
struct Source {
    slot: u32,
    row: u8,
    col: u8,
}

/// A symbolic Cholesky factorisation of one block pattern and Dirichlet mask, reused for
/// the numeric factorisations of every step until either changes.
#[derive(Clone, Debug)]
pub struct DirectSolver {
    fixed: Vec<bool>,
    num_blocks: usize,
    /// Scalar unknown of each free node's x component (`usize::MAX`: fixed node).
    free_dof: Vec<usize>,
    /// Upper triangle over the free unknowns, column-compressed.
    structure: SymbolicSparseColMat<usize>,
    /// Where each stored value comes from, in the structure's order.
    sources: Vec<Source>,
    symbolic: SymbolicLlt<usize>,
}

impl DirectSolver {
    /// The symbolic analysis for `pattern` (upper blocks, row node ≤ column node) with the
    /// nodes in `fixed` eliminated.
    pub fn new(pattern: &BlockPattern, fixed: &[bool]) -> Result<Self, FemError> {
        let n = pattern.num_rows();
        if fixed.len() != n {
            return Err(FemError::Size {
                what: "fixed",
                expected: n,
                got: fixed.len(),
            });
        }
        let mut free_dof = vec![usize::MAX; n];
        let mut dofs = 0;
        for (i, f) in fixed.iter().enumerate() {
            if !f {
                free_dof[i] = dofs;
                dofs += 3;
            }
        }
        // (column, row, source) of every upper entry between free unknowns.
        let mut entries: Vec<(usize, usize, Source)> = Vec::new();
        for i in 0..n {
            if fixed[i] {
                continue;
            }
            for (slot, j) in pattern.row(i) {
                if j < i || fixed[j] {
                    continue;
                }
                for a in 0..3 {
                    for b in 0..3 {
                        let (row, col) = (free_dof[i] + a, free_dof[j] + b);
                        if row <= col {
                            let source = Source {
                                slot: slot as u32,
                                row: a as u8,
                                col: b as u8,
                            };
                            entries.push((col, row, source));
                        }
                    }
                }
            }
        }
        entries.sort_unstable_by_key(|&(c, r, _)| (c, r));
        let mut col_ptr = vec![0usize; dofs + 1];
        for &(c, _, _) in &entries {
            col_ptr[c + 1] += 1;
        }
        for c in 0..dofs {
            col_ptr[c + 1] += col_ptr[c];
        }
        let row_idx = entries.iter().map(|&(_, r, _)| r).collect();
        let sources = entries.into_iter().map(|(_, _, s)| s).collect();
        let structure = SymbolicSparseColMat::new_checked(dofs, dofs, col_ptr, None, row_idx);
        let symbolic = SymbolicLlt::try_new(structure.as_ref(), Side::Upper)
            .map_err(|e| FemError::Solver(format!("sparse Cholesky analysis: {e:?}")))?;
        Ok(Self {
            fixed: fixed.to_vec(),
            num_blocks: pattern.num_blocks(),
            free_dof,
            structure,
            sources,
            symbolic,
        })
    }

    /// Whether this analysis still fits `pattern` and `fixed`.
    pub fn fits(&self, pattern: &BlockPattern, fixed: &[bool]) -> bool {
        self.num_blocks == pattern.num_blocks() && self.fixed == fixed
    }

    /// Number of scalar unknowns (3 per free node).
    pub fn num_unknowns(&self) -> usize {
        self.structure.nrows()
    }

    /// Solves `A x = b` on the free nodes for the assembled upper blocks `blocks` of the
    /// pattern this solver was built for; `x` is zero on fixed nodes. Errors if `A` is not
    /// positive definite on the free nodes (the caller falls back to CG).
    pub fn solve(&self, blocks: &[Matrix3<f64>], b: &[V3], x: &mut [V3]) -> Result<(), FemError> {
        let values: Vec<f64> = self
            .sources
            .iter()
            .map(|s| blocks[s.slot as usize][(s.row as usize, s.col as usize)])
            .collect();
        let matrix = SparseColMatRef::new(self.structure.as_ref(), &values);
        let llt = Llt::try_new_with_symbolic(self.symbolic.clone(), matrix, Side::Upper)
            .map_err(|e| FemError::Solver(format!("sparse Cholesky: {e:?}")))?;
        let mut rhs = Mat::<f64>::zeros(self.num_unknowns(), 1);
        for (i, &d) in self.free_dof.iter().enumerate() {
            if d != usize::MAX {
                for a in 0..3 {
                    rhs[(d + a, 0)] = b[i][a];
                }
            }
        }
        llt.solve_in_place_with_conj(Conj::No, rhs.as_mut());
        for (i, &d) in self.free_dof.iter().enumerate() {
            x[i] = if d == usize::MAX {
                V3::zeros()
            } else {
                V3::new(rhs[(d, 0)], rhs[(d + 1, 0)], rhs[(d + 2, 0)])
            };
        }
        Ok(())
    }
}
