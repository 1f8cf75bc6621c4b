//! The multigrid preconditioner of a step's MG-PCG ([`LinearSolver::MgPcg`]): the caller's
//! hierarchy, the [`Multigrid`] built on it for the current Dirichlet mask, and when its
//! coarse operators are rebuilt.

use super::operator::SysOp;
use super::{FemSystem, V3};
use crate::FemError;
use crate::mg::{Hierarchy, MgParams, Multigrid};
use crate::solver::{CgResult, Preconditioner, pcg_with};
use crate::system::{LinearSolver, StepParams};

/// [`LinearSolver::Auto`] moves from Jacobi-PCG to MG-PCG once a Jacobi-PCG solve needed
/// (or, stopped by its budget, would have needed) more iterations than this to the
/// tolerance. Measured with `cosurg bench scale` on the soft and stiff beams from 192 to
/// 12,288 tets and the default organ at dt 2 and 10 ms, every solve to 1e-6
/// (docs/RESULTS.md, "Choosing the solver"): MG-PCG was the faster in every row where
/// Jacobi-PCG needed 75 iterations or more, Jacobi-PCG in every row where it needed 48
/// or fewer. Re-measured on 2026-11-28 after the sweeps' half-precision blocks
/// (`cosurg bench scale --organ-cells 0.02,0.013333333`, docs/RESULTS.md): MG-PCG was
/// the faster from 61 iterations up (the 1.33 cm organ at dt 1 ms: 1.6 against 2.0 ms),
/// Jacobi-PCG up to 39 (at 28, the default organ at dt 1 ms, the two were within 5 %),
/// so the threshold moved from 64 to 48.
pub const AUTO_MG_ABOVE_JACOBI_ITERATIONS: usize = 48;

/// [`LinearSolver::Auto`] considers MG-PCG only for systems with more free nodes than
/// this. The crossover above was measured when the V-cycle stopped descending at 200
/// nodes, so that smaller systems had no coarse level; the default organ (170 free nodes
/// on 2 cm cells) stays on Jacobi-PCG, as measured.
pub const AUTO_MG_MIN_FREE_NODES: usize = 200;

/// A built preconditioner and its age.
#[derive(Clone, Debug)]
pub(super) struct MgCache {
    pub(super) mg: Multigrid,
    /// [`StepParams::mg_sweeps`] it was built with.
    sweeps: usize,
    /// Steps since the coarse operators were rebuilt (`usize::MAX`: never).
    age: usize,
    /// dt of the matrix the coarse operators come from (s).
    dt: f64,
}

impl FemSystem {
    /// Sets the multigrid hierarchy of [`LinearSolver::MgPcg`] (finest prolongation onto
    /// this system's nodes first). Errors if it does not chain onto the node count.
    pub fn set_multigrid_hierarchy(&mut self, hierarchy: Hierarchy) -> Result<(), FemError> {
        hierarchy.validate(self.num_nodes())?;
        self.caches.mg_hierarchy = Some(hierarchy);
        self.caches.mg = None;
        Ok(())
    }

    /// Node count per multigrid level (finest first) of the preconditioner the last
    /// MG-PCG step built; `None` before one.
    pub fn multigrid_level_sizes(&self) -> Option<Vec<usize>> {
        self.caches.mg.as_ref().map(|c| c.mg.level_sizes())
    }

    /// Whether the step with `p` solves with MG-PCG.
    pub(super) fn uses_multigrid(&self, p: &StepParams) -> bool {
        self.caches.mg_hierarchy.is_some()
            && match p.linear_solver {
                LinearSolver::MgPcg => true,
                LinearSolver::Auto => self.caches.auto_multigrid == Some(true),
                LinearSolver::JacobiPcg | LinearSolver::Direct => false,
            }
    }

    /// [`LinearSolver::Auto`]'s choice: `None` before its first Jacobi-PCG solve, then
    /// whether it chose MG-PCG.
    pub fn auto_chose_multigrid(&self) -> Option<bool> {
        self.caches.auto_multigrid
    }

    /// Carries [`LinearSolver::Auto`]'s choice over to a rebuilt system (a topology change
    /// rebuilds it): the choice is made once, on the first solve, so that sites that
    /// start from the same state make it alike and no site changes solver in mid-session.
    pub fn set_auto_multigrid(&mut self, choice: Option<bool>) {
        self.caches.auto_multigrid = choice;
    }

    /// After the first Jacobi-PCG solve that iterated, under [`LinearSolver::Auto`]:
    /// chooses MG-PCG for good if the solve needed more than
    /// [`AUTO_MG_ABOVE_JACOBI_ITERATIONS`] iterations, a hierarchy is set and there are
    /// more than [`AUTO_MG_MIN_FREE_NODES`] free nodes, else Jacobi-PCG for good.
    pub(super) fn auto_observe_jacobi(&mut self, p: &StepParams, res: &CgResult) {
        // A solve with nothing to solve (a zero right-hand side: no load yet) says
        // nothing about the system; the next one decides.
        if p.linear_solver != LinearSolver::Auto
            || self.caches.auto_multigrid.is_some()
            || res.iterations == 0
        {
            return;
        }
        let free = self.mesh.fixed.iter().filter(|f| !**f).count();
        let needed = jacobi_iterations_needed(res, p.solver.tol);
        let multigrid = needed > AUTO_MG_ABOVE_JACOBI_ITERATIONS as f64
            && self.caches.mg_hierarchy.is_some()
            && free > AUTO_MG_MIN_FREE_NODES;
        tracing::info!(
            jacobi_iterations = res.iterations,
            residual = res.relative_residual,
            needed,
            free,
            "auto solver: {}",
            if multigrid { "mg-pcg" } else { "jacobi-pcg" }
        );
        self.caches.auto_multigrid = Some(multigrid);
    }

    /// The preconditioner for the current Dirichlet mask, taken out of the caches (give
    /// it back with [`FemSystem::put_multigrid`]); the block pattern must exist.
    pub(super) fn take_multigrid(&mut self, p: &StepParams) -> Result<MgCache, FemError> {
        let fixed = &self.mesh.fixed;
        match self.caches.mg.take() {
            Some(c) if c.mg.fixed() == fixed.as_slice() && c.sweeps == p.mg_sweeps => Ok(c),
            _ => {
                let h = self.caches.mg_hierarchy.as_ref().expect("uses_multigrid");
                let pat = self.caches.pattern.as_ref().expect("pattern built");
                let params = MgParams {
                    smoothing_steps: p.mg_sweeps.max(1),
                    ..MgParams::default()
                };
                let mg = Multigrid::new(h, fixed, pat, params)?;
                Ok(MgCache {
                    mg,
                    sweeps: p.mg_sweeps,
                    age: usize::MAX,
                    dt: f64::NAN,
                })
            }
        }
    }

    pub(super) fn put_multigrid(&mut self, c: MgCache) {
        self.caches.mg = Some(c);
    }
}

/// The iterations a Jacobi-PCG solve needed to reach `tol`: its own count if it got
/// there, else extrapolated at the rate it had (CG's residual falls about geometrically:
/// `k · ln tol / ln r` after `k` iterations at relative residual `r`); infinite if it made
/// no progress. Called for solves that iterated (`k > 0`).
fn jacobi_iterations_needed(res: &CgResult, tol: f64) -> f64 {
    if res.relative_residual <= tol {
        res.iterations as f64
    } else if res.relative_residual.is_nan() || res.relative_residual >= 1.0 {
        f64::INFINITY
    } else {
        res.iterations as f64 * tol.ln() / res.relative_residual.ln()
    }
}

/// MG-PCG on the assembled operator `op`: rebuilds the coarse operators when they are
/// `refresh_steps` steps old or dt changed, else refreshes the finest smoother only.
pub(super) fn solve_with_multigrid(
    cache: &mut MgCache,
    op: &SysOp<'_>,
    fixed: &[bool],
    rhs: &[V3],
    dv: &mut [V3],
    dt: f64,
    p: &StepParams,
) -> CgResult {
    let (solver, refresh_steps) = (&p.solver, p.mg_refresh_steps);
    let blocks = op.assembled.as_ref().expect("MG-PCG assembles");
    if cache.age >= refresh_steps.max(1) || cache.dt != dt {
        cache.mg.refresh(blocks);
        cache.age = 0;
        cache.dt = dt;
    } else {
        cache.mg.update_fine_diagonal(blocks);
    }
    cache.age = cache.age.saturating_add(1);
    let mg = &mut cache.mg;
    let mut vcycle = |r: &[V3], z: &mut [V3]| mg.vcycle(blocks, r, z);
    pcg_with(
        op,
        fixed,
        rhs,
        dv,
        solver,
        Preconditioner::Custom(&mut vcycle),
    )
}
