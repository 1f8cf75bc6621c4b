//! Static equilibrium: Newton with load stepping and a line search on the potential.

use super::newton::line_search;
use super::operator::ElemMats;
use super::{FemSystem, V3, dot};
use crate::FemError;
use crate::model::Model;
use crate::polar::PolarMethod;
use crate::solver::{SolverParams, pcg};
use crate::system::{OperatorMode, StiffnessMode};

/// Parameters of [`FemSystem::solve_static`].
#[derive(Clone, Copy, Debug)]
pub struct StaticParams {
    /// Stiffness kernel for Linear / Corotational tangents.
    pub stiffness: StiffnessMode,
    /// CG settings for each Newton system (use [`SolverParams::accurate`]).
    pub solver: SolverParams,
    /// Gravity (m/s²), part of the load.
    pub gravity: V3,
    /// Rotation extractor.
    pub polar: PolarMethod,
    /// Convergence: residual 2-norm ≤ `tol_abs` (N) or ≤ `tol_rel` · ‖load‖.
    pub tol_abs: f64,
    /// Relative residual tolerance.
    pub tol_rel: f64,
    /// Newton iterations allowed per load increment before it is halved.
    pub max_newton: usize,
    /// First load increment (fraction of the full load).
    pub initial_increment: f64,
    /// Smallest increment before giving up.
    pub min_increment: f64,
}

impl Default for StaticParams {
    fn default() -> Self {
        Self {
            stiffness: StiffnessMode::Template,
            solver: SolverParams::accurate(),
            gravity: V3::zeros(),
            polar: PolarMethod::default(),
            tol_abs: 1e-9,
            tol_rel: 1e-9,
            max_newton: 25,
            initial_increment: 1.0,
            min_increment: 1e-4,
        }
    }
}

/// What a static solve did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StaticStats {
    /// Newton iterations over all accepted and rejected increments.
    pub iterations: usize,
    /// Accepted load increments.
    pub load_steps: usize,
    /// Rejected (halved) increments.
    pub rejected_steps: usize,
    /// Final residual 2-norm over free DOFs (N).
    pub residual: f64,
    /// Residual tolerance that was applied (N).
    pub tolerance: f64,
    /// Full load reached and converged.
    pub converged: bool,
    /// CG iterations in total.
    pub cg_iterations: usize,
}

impl FemSystem {
    /// Static equilibrium `f_int(x) + s (f_ext + M g) = 0` on the free nodes for the load
    /// factor s → 1, by Newton (consistent tangent for StVK, `R K Rᵀ` for co-rotational,
    /// CG truncated at negative curvature) with Armijo backtracking on the potential
    /// `Π = W(x) − s (f_ext + M g)ᵀ x` and adaptive load increments (halved when an
    /// increment does not converge within `max_newton`, grown ×1.5 after quick ones).
    /// `x` is the initial guess and carries the prescribed positions of fixed nodes.
    pub fn solve_static(
        &mut self,
        model: Model,
        x: &mut [V3],
        f_ext: &[V3],
        p: &StaticParams,
    ) -> Result<StaticStats, FemError> {
        self.check_sizes(x, None, f_ext)?;
        if p.stiffness == StiffnessMode::Dense {
            self.ensure_dense();
        }
        let n = self.mesh.rest.len();
        let load: Vec<V3> = (0..n)
            .map(|i| f_ext[i] + p.gravity * self.mesh.mass[i])
            .collect();
        let fixed = self.mesh.fixed.clone();
        let load_norm = load
            .iter()
            .zip(&fixed)
            .filter(|(_, f)| !**f)
            .map(|(l, _)| l.norm_squared())
            .sum::<f64>()
            .sqrt();
        let tol = p.tol_abs.max(p.tol_rel * load_norm);
        let mut stats = StaticStats {
            tolerance: tol,
            ..Default::default()
        };
        let potential = |sys: &FemSystem, x: &[V3], s: f64, grad: Option<&mut [V3]>| {
            let rots = if model == Model::Corotational {
                sys.compute_rotations(x, &p.polar)
            } else {
                Vec::new()
            };
            let mut fint = vec![V3::zeros(); n];
            let w = sys.elastic(x, model, p.stiffness, Some(&rots), Some(&mut fint));
            let mut val = w;
            for i in 0..n {
                val -= s * load[i].dot(&(x[i] - sys.mesh.rest[i]));
            }
            if let Some(g) = grad {
                for i in 0..n {
                    g[i] = if fixed[i] {
                        V3::zeros()
                    } else {
                        -(fint[i] + load[i] * s)
                    };
                }
            }
            (val, rots)
        };
        let mut s = 0.0;
        let mut ds = p.initial_increment.clamp(p.min_increment, 1.0);
        let mut grad = vec![V3::zeros(); n];
        while s < 1.0 {
            let s_try = (s + ds).min(1.0);
            let x_save = x.to_vec();
            let mut converged = false;
            let mut its = 0;
            let (mut val, mut rots) = potential(self, x, s_try, Some(&mut grad));
            loop {
                let r = dot(&grad, &grad).sqrt();
                stats.residual = r;
                if r <= tol {
                    converged = true;
                    break;
                }
                if its >= p.max_newton || !r.is_finite() {
                    break;
                }
                its += 1;
                stats.iterations += 1;
                if model == Model::Corotational {
                    for (src, rr) in self.rotations.sources.iter_mut().zip(&rots) {
                        src.rotation = *rr;
                    }
                }
                let mats = self.tangent_mats(x, model, p.stiffness);
                let ext: Vec<f64> = vec![0.0; n];
                let op = self.build_operator(
                    ext,
                    ElemMats::Dense(mats),
                    0.0,
                    p.stiffness,
                    OperatorMode::Assembled,
                );
                let rhs: Vec<V3> = grad.iter().map(|g| -g).collect();
                let mut dx = vec![V3::zeros(); n];
                let res = pcg(&op, &fixed, &rhs, &mut dx, &p.solver);
                let buffers = op.into_buffers();
                self.caches.recycle(buffers);
                stats.cg_iterations += res.iterations;
                let (nv, nr, ng) = line_search(self, x, &dx, &grad, val, |sys, xt, g| {
                    potential(sys, xt, s_try, g)
                });
                val = nv;
                rots = nr;
                grad = ng;
            }
            if converged {
                s = s_try;
                stats.load_steps += 1;
                if its <= p.max_newton / 3 {
                    ds = (ds * 1.5).min(1.0);
                }
                tracing::debug!(
                    load = s,
                    newton = its,
                    residual = stats.residual,
                    "increment"
                );
            } else {
                x.copy_from_slice(&x_save);
                stats.rejected_steps += 1;
                ds *= 0.5;
                tracing::debug!(load = s_try, ds, "increment rejected");
                if ds < p.min_increment {
                    tracing::warn!(load = s, "static solve did not converge");
                    return Ok(stats);
                }
            }
        }
        if model == Model::Corotational {
            self.update_rotations(x, &p.polar, 0.0);
        }
        stats.converged = true;
        Ok(stats)
    }
}
