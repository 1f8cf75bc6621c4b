//! Backward Euler with Newton iterations: the StVK step and the robust fallback of the
//! linearised step, with a backtracking line search shared with statics.

use nalgebra::Matrix3;

use super::operator::ElemMats;
use super::{FemSystem, V3, dot, gather};
use crate::FemError;
use crate::element::{Mat12, apply_dense};
use crate::model::Model;
use crate::solver::pcg;
use crate::system::{FALLBACK_NEWTON, StepParams, StepStats};

impl FemSystem {
    /// The Newton fallback of a linearised step, from the state it started at (rotations
    /// already extracted there), with the statistics of the linearised attempt added.
    pub(super) fn fallback_step(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
        attempt: &StepStats,
    ) -> Result<StepStats, FemError> {
        let q = StepParams {
            newton: FALLBACK_NEWTON,
            ..*p
        };
        let mut s = self.step_newton(x, v, f_ext, dt, &q, true)?;
        s.rotations_extracted += attempt.rotations_extracted;
        s.polar_iterations += attempt.polar_iterations;
        s.cg_iterations += attempt.cg_iterations;
        s.inverted = attempt.inverted;
        s.max_rotation_change_sq = attempt.max_rotation_change_sq;
        s.solver = attempt.solver;
        s.fallback = true;
        Ok(s)
    }

    /// Backward Euler with Newton iterations on the incremental potential (scaled by dt²)
    /// `Φ(x) = ½‖x − x̂‖²_M + ½ dt ‖x − x_n‖²_{D_n} + dt² [W(x) − (f_ext + M g)ᵀx
    /// + ½‖x − x_n‖²_{K_c}]`, `x̂ = x_n + dt v_n`, `D_n = C + Σ β_e R_e K_e R_eᵀ` frozen at
    /// `x_n`; backtracking (Armijo) line search on Φ, CG truncated at negative curvature.
    ///
    /// Iterations as [`StepParams::newton`] says. `rotations_current`: the stored rotations are already those at `x` (the fallbacks of
    /// the linearised step extracted them); extracting again would count every source as
    /// reused and hide the rotation change from the next step's fallback test.
    pub(super) fn step_newton(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
        rotations_current: bool,
    ) -> Result<StepStats, FemError> {
        let n = self.mesh.rest.len();
        let np = p.newton;
        let mut stats = StepStats::default();
        // Rotations enter the co-rotational model and the Rayleigh β damping; the StVK
        // reference without β needs none (a polar decomposition per element and line-search
        // trial would dominate its cost).
        let corot = p.model == Model::Corotational;
        let need_rotations = corot || self.mesh.materials.iter().any(|m| m.beta != 0.0);
        let (e, r, it, inv) = if need_rotations && !rotations_current {
            self.update_rotations(x, &p.polar, p.rest_threshold)
        } else {
            (0, 0, 0, 0)
        };
        stats.rotations_extracted = e;
        stats.rotations_reused = r;
        stats.polar_iterations = it;
        stats.inverted = inv;
        let x_n: Vec<V3> = x.to_vec();
        let x_hat: Vec<V3> = (0..n).map(|i| x[i] + v[i] * dt).collect();
        // Damping element matrices dt β_e R K Rᵀ at x_n.
        let damp: Vec<Mat12> = (0..self.mesh.elements.len())
            .map(|ei| {
                let beta = self.mesh.materials[self.mesh.elements[ei].material].beta;
                if beta == 0.0 {
                    Mat12::zeros()
                } else {
                    let r = self.rotations.sources[self.mesh.elements[ei].source].rotation;
                    self.rotated_k(ei, &r, p.stiffness) * (dt * beta)
                }
            })
            .collect();
        let mass_coef: Vec<f64> = (0..n)
            .map(|i| self.mesh.mass[i] + dt * self.mesh.mass_damping[i])
            .collect();
        let load: Vec<V3> = (0..n)
            .map(|i| f_ext[i] + p.gravity * self.mesh.mass[i])
            .collect();
        x.copy_from_slice(&x_hat);
        let fixed = self.mesh.fixed.clone();
        let kext = self.k_ext.clone();
        let dt2 = dt * dt;
        // Φ and its gradient.
        let phi = |sys: &FemSystem, x: &[V3], rots: &[Matrix3<f64>], grad: Option<&mut [V3]>| {
            let mut fint = vec![V3::zeros(); n];
            let w = sys.elastic(x, p.model, p.stiffness, Some(rots), Some(&mut fint));
            let d: Vec<V3> = (0..n).map(|i| x[i] - x_n[i]).collect();
            let mut val = 0.0;
            let mut g = vec![V3::zeros(); n];
            for i in 0..n {
                let dh = x[i] - x_hat[i];
                val += 0.5 * sys.mesh.mass[i] * dh.norm_squared()
                    + 0.5 * dt * sys.mesh.mass_damping[i] * d[i].norm_squared()
                    - dt2 * load[i].dot(&x[i]);
                g[i] = dh * sys.mesh.mass[i] + d[i] * (dt * sys.mesh.mass_damping[i])
                    - (fint[i] + load[i]) * dt2;
            }
            for (ei, e) in sys.mesh.elements.iter().enumerate() {
                let de = gather(&d, &e.nodes);
                let y = apply_dense(&damp[ei], &de);
                for a in 0..4 {
                    val += 0.5 * de[a].dot(&y[a]);
                    g[e.nodes[a]] += y[a];
                }
            }
            for (k, blk) in &kext {
                let y = blk * d[*k];
                val += 0.5 * dt2 * d[*k].dot(&y);
                g[*k] += y * dt2;
            }
            val += dt2 * w;
            if let Some(out) = grad {
                for i in 0..n {
                    out[i] = if fixed[i] { V3::zeros() } else { g[i] };
                }
            }
            val
        };
        let rotations = |s: &FemSystem, xt: &[V3]| {
            if corot {
                s.compute_rotations(xt, &p.polar)
            } else {
                Vec::new()
            }
        };
        let mut rots = rotations(self, x);
        let mut grad = vec![V3::zeros(); n];
        let mut val = phi(self, x, &rots, Some(&mut grad));
        if corot {
            // The co-rotational fallback runs where rotations jump (inverted elements,
            // fast spins); there the predictor x̂ can sit far up the energy landscape, and
            // a few Newton iterations from it may end above the energy the step started
            // with. Starting from x_n (free nodes) when Φ is lower there bounds the step:
            // Φ(x_{n+1}) ≤ Φ(x_n) = kinetic + elastic energy at the start (no load work).
            let start: Vec<V3> = (0..n)
                .map(|i| if fixed[i] { x_hat[i] } else { x_n[i] })
                .collect();
            let start_rots = rotations(self, &start);
            let mut start_grad = vec![V3::zeros(); n];
            let start_val = phi(self, &start, &start_rots, Some(&mut start_grad));
            if start_val < val {
                x.copy_from_slice(&start);
                (rots, grad, val) = (start_rots, start_grad, start_val);
            }
        }
        for _ in 0..np.max_iters.max(1) {
            let gnorm = dot(&grad, &grad).sqrt() / dt2;
            stats.newton_residual = gnorm;
            if gnorm <= np.tol {
                break;
            }
            stats.newton_iterations += 1;
            // Tangent with rotations at the current iterate.
            if p.model == Model::Corotational {
                for (s, r) in self.rotations.sources.iter_mut().zip(&rots) {
                    s.rotation = *r;
                }
            }
            let kt = self.tangent_mats(x, p.model, p.stiffness);
            let mats: Vec<Mat12> = kt.iter().zip(&damp).map(|(k, d)| k * dt2 + d).collect();
            let op = self.build_operator(
                mass_coef.clone(),
                ElemMats::Dense(mats),
                dt2,
                p.stiffness,
                p.operator,
            );
            let rhs: Vec<V3> = grad.iter().map(|g| -g).collect();
            let mut dx = vec![V3::zeros(); n];
            let res = pcg(&op, &fixed, &rhs, &mut dx, &p.solver);
            let buffers = op.into_buffers();
            self.caches.recycle(buffers);
            stats.cg_iterations += res.iterations;
            stats.cg_residual = res.relative_residual;
            let (nv, nr, ng) = line_search(self, x, &dx, &grad, val, |s, xt, g| {
                let r = rotations(s, xt);
                let v = phi(s, xt, &r, g);
                (v, r)
            });
            val = nv;
            rots = nr;
            grad = ng;
        }
        stats.newton_residual = dot(&grad, &grad).sqrt() / dt2;
        for i in 0..n {
            v[i] = (x[i] - x_n[i]) / dt;
        }
        if !x.iter().all(|p| p.iter().all(|c| c.is_finite())) {
            return Err(FemError::NonFinite);
        }
        Ok(stats)
    }
}

/// Armijo backtracking along `dx` from `x` (updated in place). If `dx` is not a descent
/// direction, the negative gradient is used. Returns the new (value, aux, gradient).
pub(super) fn line_search<A>(
    sys: &FemSystem,
    x: &mut [V3],
    dx: &[V3],
    grad: &[V3],
    val: f64,
    mut eval: impl FnMut(&FemSystem, &[V3], Option<&mut [V3]>) -> (f64, A),
) -> (f64, A, Vec<V3>) {
    let n = x.len();
    let mut dir: Vec<V3> = dx.to_vec();
    let mut slope = dot(grad, &dir);
    if slope >= 0.0 || !slope.is_finite() {
        dir = grad.iter().map(|g| -g).collect();
        slope = -dot(grad, grad);
    }
    let x0 = x.to_vec();
    let mut alpha = 1.0;
    let mut g = vec![V3::zeros(); n];
    let mut best = None;
    for _ in 0..30 {
        for i in 0..n {
            x[i] = x0[i] + dir[i] * alpha;
        }
        let (v, aux) = eval(sys, x, Some(&mut g));
        // Armijo with a round-off allowance: near convergence Φ differences drop below
        // machine precision of Φ itself.
        if v.is_finite() && v <= val + 1e-4 * alpha * slope + 1e-13 * val.abs() {
            return (v, aux, g);
        }
        best = Some((v, aux));
        alpha *= 0.5;
    }
    let (v, aux) = best.expect("at least one trial");
    (v, aux, g)
}
