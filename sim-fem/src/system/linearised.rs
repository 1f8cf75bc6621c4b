//! The linearised backward-Euler step (one linear solve with R frozen at `x_n`), and the
//! matrix of that step for solver comparisons.

use nalgebra::Matrix3;

use super::direct::solve_direct;
use super::multigrid::solve_with_multigrid;
use super::operator::ElemMats;
use super::{FemSystem, V3};
use crate::FemError;
use crate::model::Model;
use crate::parallel::with_helper;
use crate::solver::{CgResult, pcg};
use crate::system::{LinearSolver, OperatorMode, StepParams, StepStats};

impl FemSystem {
    /// The matrix of the linearised step at `x`, `M + dt C + (β dt + dt²) R K Rᵀ + dt² K_c`
    /// with the rotations extracted at `x` (model and stiffness kernel of `p`), as 3×3
    /// blocks `(row node, column node, block)` of both triangles, without the fixed nodes'
    /// rows and columns. For comparing linear solvers on the step's own system
    /// (`examples/direct_vs_cg.rs`); a step does not go through it. Like a step, it stores
    /// the rotations it extracts (the next step starts from them).
    pub fn step_matrix(
        &mut self,
        x: &[V3],
        dt: f64,
        p: &StepParams,
    ) -> Result<Vec<(usize, usize, Matrix3<f64>)>, FemError> {
        self.check_sizes(x, None, x)?;
        if p.model == Model::Corotational {
            self.update_rotations(x, &p.polar, 0.0);
        }
        let (mass_coef, coef) = self.linearised_coefficients(dt);
        let fixed = self.mesh.fixed.clone();
        let rotated = p.model == Model::Corotational;
        let op = self.build_operator(
            mass_coef,
            ElemMats::Rotated { coef, rotated },
            dt * dt,
            p.stiffness,
            OperatorMode::Assembled,
        );
        let pat = op.sys.caches.pattern.as_ref().expect("assembled");
        let blocks = op.assembled.as_ref().expect("assembled");
        let mut out = Vec::new();
        for i in 0..pat.num_rows() {
            for (k, j) in pat.row(i) {
                // Upper storage: mirror the blocks above the diagonal.
                if j < i || fixed[i] || fixed[j] {
                    continue;
                }
                out.push((i, j, blocks[k]));
                if j != i {
                    out.push((j, i, blocks[k].transpose()));
                }
            }
        }
        Ok(out)
    }

    /// Coefficients of the linearised step's matrix: per node `m_i + dt α m_i` (lumped mass
    /// and mass damping) and per element `β_e dt + dt²` (stiffness damping and stiffness).
    pub(super) fn linearised_coefficients(&self, dt: f64) -> (Vec<f64>, Vec<f64>) {
        let mass_coef = (0..self.mesh.rest.len())
            .map(|i| self.mesh.mass[i] + dt * self.mesh.mass_damping[i])
            .collect();
        let coef = self
            .mesh
            .elements
            .iter()
            .map(|e| dt * self.mesh.materials[e.material].beta + dt * dt)
            .collect();
        (mass_coef, coef)
    }

    /// The linearised backward-Euler step (see [`FemSystem::step`]) with its fallbacks: to
    /// the Newton step when a rotation turned by more than
    /// [`StepParams::fallback_angle_deg`], and the energy guard.
    pub(super) fn step_linearised(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
    ) -> Result<StepStats, FemError> {
        let n = self.mesh.rest.len();
        let mut stats = StepStats {
            newton_iterations: 1,
            newton_residual: f64::NAN,
            ..Default::default()
        };
        if p.model == Model::Corotational {
            let (e, r, it, inv) = self.update_rotations(x, &p.polar, p.rest_threshold);
            stats.rotations_extracted = e;
            stats.rotations_reused = r;
            stats.polar_iterations = it;
            stats.inverted = inv;
            stats.max_rotation_change_sq = self.rotations.last_pass.max_change_sq;
            if p.fallback_angle_deg > 0.0
                && stats.max_rotation_change_sq
                    > crate::polar::rotation_threshold_sq(p.fallback_angle_deg.to_radians())
            {
                // Δv from before such a turn is no guess for the steps after it.
                self.caches.warm_dv = Vec::new();
                return self.fallback_step(x, v, f_ext, dt, p, &stats);
            }
        }
        if self.exec.threads > 1 {
            // The parallel force loop needs the partition.
            self.refresh_order();
        }
        if p.model == Model::Corotational {
            self.refresh_source_stiffness(p.stiffness);
        }
        let mut fint = vec![V3::zeros(); n];
        let elastic_n = self.elastic(x, p.model, p.stiffness, None, Some(&mut fint));
        let guard = self.energy_guard_start(x, v, elastic_n, p);
        let (mass_coef, coef) = self.linearised_coefficients(dt);
        let warm = std::mem::take(&mut self.caches.warm_dv);
        let (mass, mass_damping) = (self.mesh.mass.clone(), self.mesh.mass_damping.clone());
        let fixed = self.mesh.fixed.clone();
        // On two threads an iterative solve's many short parallel regions share a helper
        // kept awake for its length (`parallel/spin.rs`; it hands out halves only, and a
        // direct solve has no such regions).
        let two_parts = self
            .active_partition()
            .is_some_and(|q| q.node_start.len() == 3);
        let mut mg = None;
        let mut operator = p.operator;
        if self.uses_multigrid(p) {
            operator = OperatorMode::Assembled;
            self.refresh_order();
            let mut c = self.take_multigrid(p)?;
            // On several threads the finest level's smoothing is split as the products are.
            let bounds = self
                .active_partition()
                .map_or(&[][..], |q| &q.node_start[..]);
            c.mg.set_fine_parts(bounds);
            mg = Some(c);
        }
        let mut direct = None;
        if self.uses_direct(p) {
            operator = OperatorMode::Assembled;
            direct = Some(self.take_direct()?);
        }
        let op = self.build_operator(
            mass_coef.clone(),
            ElemMats::Rotated {
                coef,
                rotated: p.model == Model::Corotational,
            },
            dt * dt,
            p.stiffness,
            operator,
        );
        let mut av = vec![V3::zeros(); n];
        op.apply_once(v, &mut av);
        let mut rhs = vec![V3::zeros(); n];
        for i in 0..n {
            if fixed[i] {
                continue;
            }
            rhs[i] = (fint[i] + f_ext[i] + p.gravity * mass[i] - v[i] * mass_damping[i]) * dt
                - (av[i] - v[i] * mass_coef[i]);
        }
        let mut dv = if p.solver.warm_start && warm.len() == n {
            warm
        } else {
            vec![V3::zeros(); n]
        };
        let mut solve = || match (mg.as_mut(), &direct) {
            (Some(c), _) => (
                solve_with_multigrid(c, &op, &fixed, &rhs, &mut dv, dt, p),
                LinearSolver::MgPcg,
            ),
            (None, Some(d)) => (
                solve_direct(d, &op, &fixed, &rhs, &mut dv, &p.solver),
                LinearSolver::Direct,
            ),
            (None, None) => (
                pcg(&op, &fixed, &rhs, &mut dv, &p.solver),
                LinearSolver::JacobiPcg,
            ),
        };
        let (res, solver): (CgResult, _) = if two_parts && direct.is_none() {
            with_helper(solve)
        } else {
            solve()
        };
        let buffers = op.into_buffers();
        self.caches.recycle(buffers);
        if let Some(c) = mg {
            self.put_multigrid(c);
        }
        if let Some(d) = direct {
            self.put_direct(d);
        }
        stats.cg_iterations = res.iterations;
        stats.cg_residual = res.relative_residual;
        stats.solver = solver;
        if solver == LinearSolver::JacobiPcg {
            self.auto_observe_jacobi(p, &res);
        }
        for i in 0..n {
            if !fixed[i] {
                v[i] += dv[i];
            }
            x[i] += v[i] * dt;
        }
        if !x.iter().all(|p| p.iter().all(|c| c.is_finite())) {
            return Err(FemError::NonFinite);
        }
        // Only a converged Δv is the next step's guess: a truncated one (the budget ran
        // out) carries its error on, and warm starts from truncated solves pumped about
        // 9 kJ into the stress beam after violent impulses at dt = 33 ms.
        self.caches.warm_dv = if res.relative_residual <= p.solver.tol {
            dv
        } else {
            Vec::new()
        };
        if let Some(start) = guard
            && self.energy_guard_rejects(&start, x, v, f_ext, p, &stats)
        {
            start.restore(x, v);
            // The rejected step's Δv is no guess for the next one.
            self.caches.warm_dv = Vec::new();
            let mut s = self.fallback_step(x, v, f_ext, dt, p, &stats)?;
            s.energy_guard = true;
            return Ok(s);
        }
        Ok(stats)
    }
}
