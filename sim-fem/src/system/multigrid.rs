//! The multigrid preconditioner of a step's MG-PCG ([`LinearSolver::MgPcg`]): the caller's
//! hierarchy, the [`Multigrid`] built on it for the current Dirichlet mask, and when its
//! coarse operators are rebuilt.

use super::operator::SysOp;
use super::{FemSystem, V3};
use crate::FemError;
use crate::mg::{Hierarchy, MgParams, Multigrid};
use crate::solver::{CgResult, Preconditioner, pcg_with};
use crate::system::{LinearSolver, StepParams};

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
        p.linear_solver == LinearSolver::MgPcg && self.caches.mg_hierarchy.is_some()
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
