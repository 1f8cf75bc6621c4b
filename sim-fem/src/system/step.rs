//! The entry point of a dynamic step: [`StepStats`], the thread pool, and the choice
//! between the linearised step and the Newton step.

use super::{FemSystem, V3};
use crate::FemError;
use crate::model::Model;
use crate::system::{LinearSolver, StepParams, StiffnessMode};

/// What a step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// CG iterations (summed over Newton iterations).
    pub cg_iterations: usize,
    /// Last CG relative residual ‖b − A x‖/‖b‖.
    pub cg_residual: f64,
    /// Newton iterations (1 for the linearised step).
    pub newton_iterations: usize,
    /// Final force residual of the Newton step (N); NaN for the linearised step.
    pub newton_residual: f64,
    /// Rotation extractions (polar decompositions) since the previous step, including
    /// those of shared sources requested by [`FemSystem::shared_source_rotation`]
    /// (the rotation-sharing test). Sources no element references are not extracted.
    pub rotations_extracted: usize,
    /// Referenced rotation sources whose R was reused (at rest).
    pub rotations_reused: usize,
    /// Polar iterations summed over extractions.
    pub polar_iterations: usize,
    /// Sources found inverted (det F ≤ 0).
    pub inverted: usize,
    /// The linearised step fell back to Newton ([`StepParams::fallback_angle_deg`], or
    /// the energy guard: see `energy_guard`).
    pub fallback: bool,
    /// The step was redone with Newton because the linearised one created energy
    /// ([`StepParams::energy_guard`]).
    pub energy_guard: bool,
    /// Largest rotation change of a source since the previous step, as
    /// `‖R_new − R_old‖²_F = 4(1 − cos θ)` (0 when none was extracted).
    pub max_rotation_change_sq: f64,
    /// The linear solver of the step's linearised solve ([`LinearSolver::Auto`] resolved).
    /// A linearised step redone with Newton reports its attempt's; a Newton step (StVK)
    /// reports Jacobi-PCG, which its CG solves use whatever was asked for.
    pub solver: LinearSolver,
}

impl FemSystem {
    /// Dynamic step: linearised backward Euler for the linear and co-rotational models,
    /// backward Euler with Newton iterations ([`StepParams::newton`]) for StVK.
    ///
    /// **Linearised backward Euler** (Linear, Corotational; one linear solve):
    /// with `K` the stiffness at `x_n` (co-rotated with R frozen), `C = Σ α_e M_e`,
    /// `K_β = Σ β_e K_e`, `K_c` the external (contact) stiffness,
    /// `(M + dt C + dt K_β + dt² (K + K_c)) Δv =
    ///  dt (f_int(x_n) + f_ext + M g − C v_n − K_β v_n) − dt² (K + K_c) v_n`,
    /// then `v_{n+1} = v_n + Δv`, `x_{n+1} = x_n + dt v_{n+1}`. For a uniform material this
    /// is `(M(1+α dt) + (β dt + dt²) K) Δv = dt (f_int + f_ext + M g − α M v − (β + dt) K v)`.
    ///
    /// **Fixed nodes**: `Δv = 0` there (projection in CG); they move with the velocity the
    /// caller gives them (`x += dt v`), so prescribed motion = set `v` of fixed nodes.
    ///
    /// **Threads**: with [`StepParams::threads`] > 1 the step runs on a pool of that many
    /// threads (built on first use, kept for the next steps).
    pub fn step(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
    ) -> Result<StepStats, FemError> {
        if p.threads <= 1 {
            return self.step_on_this_thread(x, v, f_ext, dt, p);
        }
        let pool = self.thread_pool(p.threads)?;
        if self.exec.partition.as_ref().map(|q| q.threads) != Some(p.threads) {
            self.caches.by_source_stale = true;
        }
        self.exec.threads = p.threads;
        // The whole step runs inside the pool so that each fork is a cheap work-steal.
        let result = pool.install(|| self.step_on_this_thread(x, v, f_ext, dt, p));
        self.exec.threads = 1;
        result
    }

    pub(super) fn step_on_this_thread(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
    ) -> Result<StepStats, FemError> {
        self.check_sizes(x, Some(v), f_ext)?;
        if !(dt > 0.0 && dt.is_finite()) {
            return Err(FemError::BadParameter(format!("dt = {dt} s")));
        }
        if p.stiffness == StiffnessMode::Dense {
            self.ensure_dense();
        }
        match p.model {
            Model::StVK => self.step_newton(x, v, f_ext, dt, p, false),
            Model::Linear | Model::Corotational => self.step_linearised(x, v, f_ext, dt, p),
        }
    }
}
