//! The sparse direct solve of a linearised step ([`LinearSolver::Direct`]): the symbolic
//! factorisation kept in the caches, the numeric one per step, and the fall-back to
//! Jacobi-PCG when the matrix is not positive definite.

use super::operator::SysOp;
use super::{FemSystem, V3};
use crate::FemError;
use crate::direct::DirectSolver;
use crate::solver::{CgResult, SolverParams, pcg};
use crate::system::{LinearSolver, StepParams};

impl FemSystem {
    /// Whether the step with `p` solves with the sparse direct solver.
    pub(super) fn uses_direct(&self, p: &StepParams) -> bool {
        p.linear_solver == LinearSolver::Direct
    }

    /// The symbolic factorisation for the current pattern and Dirichlet mask, taken out
    /// of the caches (give it back with [`FemSystem::put_direct`]).
    pub(super) fn take_direct(&mut self) -> Result<DirectSolver, FemError> {
        self.refresh_order();
        let pat = self.caches.pattern.as_ref().expect("pattern built");
        match self.caches.direct.take() {
            Some(d) if d.fits(pat, &self.mesh.fixed) => Ok(d),
            _ => DirectSolver::new(pat, &self.mesh.fixed),
        }
    }

    pub(super) fn put_direct(&mut self, d: DirectSolver) {
        self.caches.direct = Some(d);
    }
}

/// Solves `op dv = rhs` on the free nodes with `direct`; the result reports no iterations
/// and the true relative residual `‖rhs − A dv‖/‖rhs‖` (one product). Falls back to
/// Jacobi-PCG with `solver` when the factorisation fails.
pub(super) fn solve_direct(
    direct: &DirectSolver,
    op: &SysOp<'_>,
    fixed: &[bool],
    rhs: &[V3],
    dv: &mut [V3],
    solver: &SolverParams,
) -> CgResult {
    let blocks = op.assembled.as_ref().expect("the direct solve assembles");
    if let Err(e) = direct.solve(blocks, rhs, dv) {
        tracing::warn!("{e}; this step falls back to Jacobi-PCG");
        dv.iter_mut().for_each(|v| *v = V3::zeros());
        return pcg(op, fixed, rhs, dv, solver);
    }
    let mut a_dv = vec![V3::zeros(); dv.len()];
    op.apply_once(dv, &mut a_dv);
    let (mut rr, mut bb) = (0.0, 0.0);
    for ((r, b), f) in a_dv.iter().zip(rhs).zip(fixed) {
        if !f {
            rr += (b - r).norm_squared();
            bb += b.norm_squared();
        }
    }
    CgResult {
        iterations: 0,
        relative_residual: if bb > 0.0 { (rr / bb).sqrt() } else { 0.0 },
        negative_curvature: false,
    }
}
