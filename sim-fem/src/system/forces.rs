//! Element kernels: small-strain stiffness (dense, template or gradient), internal forces
//! and elastic energy of the three models, and their Newton tangents.

use nalgebra::Matrix3;

use super::{FemSystem, V3, gather};
use crate::element::{Mat12, apply_dense, apply_k_gradient, edge_matrix, k_lambda_mu};
use crate::model::Model;
use crate::parallel::split_ranges;
use crate::polar::PolarMethod;
use crate::system::StiffnessMode;

impl FemSystem {
    /// Small-strain element stiffness `K_e` (N/m) in the element's rest frame.
    pub(super) fn k0_matrix(&self, ei: usize, mode: StiffnessMode) -> Mat12 {
        let e = &self.mesh.elements[ei];
        let m = &self.mesh.materials[e.material];
        match (mode, e.template, &self.caches.dense) {
            (StiffnessMode::Dense, _, Some(d)) => d[ei],
            (StiffnessMode::Template | StiffnessMode::TemplateSparse, Some((_, h)), _) => {
                self.mesh.combos[e.combo] * h
            }
            _ => {
                let (kl, km) = k_lambda_mu(&e.grads, e.volume);
                kl * m.lambda + km * m.mu
            }
        }
    }

    /// `K_e u` in the rest frame.
    #[inline]
    pub(super) fn apply_k0(&self, ei: usize, u: &[V3; 4], mode: StiffnessMode) -> [V3; 4] {
        let e = &self.mesh.elements[ei];
        let m = &self.mesh.materials[e.material];
        match (mode, e.template, &self.caches.dense) {
            (StiffnessMode::Dense, _, Some(d)) => apply_dense(&d[ei], u),
            (StiffnessMode::Template, Some((_, h)), _) => {
                let y = apply_dense(&self.mesh.combos[e.combo], u);
                [y[0] * h, y[1] * h, y[2] * h, y[3] * h]
            }
            (StiffnessMode::TemplateSparse, Some((t, h)), _) => {
                self.mesh.templates[t].apply(h, m.lambda, m.mu, u)
            }
            _ => apply_k_gradient(&e.grads, e.volume, m.lambda, m.mu, u),
        }
    }

    /// Elastic energy (J) and, if `forces` is given, internal forces `f_int = −∂W/∂x` (N)
    /// *added* into it. Co-rotational uses `rotations` (per source) or the stored ones.
    pub fn elastic(
        &self,
        x: &[V3],
        model: Model,
        mode: StiffnessMode,
        rotations: Option<&[Matrix3<f64>]>,
        forces: Option<&mut [V3]>,
    ) -> f64 {
        let one = |ei: usize| self.element_force(ei, x, model, mode, rotations);
        let Some(out) = forces else {
            return (0..self.mesh.elements.len()).map(|ei| one(ei).0).sum();
        };
        let scatter = |out: &mut [V3], offset: usize, ei: usize| {
            let (energy, fe) = one(ei);
            for (&k, f) in self.mesh.elements[ei].nodes.iter().zip(&fe) {
                out[k - offset] += f;
            }
            energy
        };
        if model == Model::Corotational
            && self.active_partition().is_some()
            && self.sums_most_sources()
            && let Some(energy) = self.elastic_by_source(x, mode, rotations, out)
        {
            return energy;
        }
        match self.active_partition() {
            Some(part) => {
                use rayon::prelude::*;
                let inner: f64 = split_ranges(out, &part.node_start)
                    .into_par_iter()
                    .zip(part.elements.par_iter())
                    .zip(part.node_start.par_iter())
                    .map(|((rows, els), &start)| {
                        els.iter()
                            .map(|&ei| scatter(rows, start, ei as usize))
                            .sum::<f64>()
                    })
                    .sum();
                let edge: f64 = part
                    .interface
                    .iter()
                    .map(|&ei| scatter(out, 0, ei as usize))
                    .sum();
                inner + edge
            }
            _ => {
                if model == Model::Corotational
                    && let Some(energy) = self.elastic_by_source(x, mode, rotations, out)
                {
                    return energy;
                }
                (0..self.mesh.elements.len())
                    .map(|ei| scatter(out, 0, ei))
                    .sum()
            }
        }
    }

    /// Elastic energy (J) and internal forces (N) of one element.
    #[inline]
    pub(super) fn element_force(
        &self,
        ei: usize,
        x: &[V3],
        model: Model,
        mode: StiffnessMode,
        rotations: Option<&[Matrix3<f64>]>,
    ) -> (f64, [V3; 4]) {
        let e = &self.mesh.elements[ei];
        let mut energy = 0.0;
        let xe = gather(x, &e.nodes);
        let xr = gather(&self.mesh.rest, &e.nodes);
        let fe: [V3; 4] = match model {
            Model::Linear => {
                let u = [xe[0] - xr[0], xe[1] - xr[1], xe[2] - xr[2], xe[3] - xr[3]];
                let y = self.apply_k0(ei, &u, mode);
                energy += 0.5 * (0..4).map(|a| u[a].dot(&y[a])).sum::<f64>();
                [-y[0], -y[1], -y[2], -y[3]]
            }
            Model::Corotational => {
                let r = self.element_rotation_of(ei, rotations);
                let rt = r.transpose();
                // Relative to node 0: K annihilates translations, so this equals
                // Rᵀx − X in K's range and cancels large translations exactly.
                let mut u = [V3::zeros(); 4];
                for a in 1..4 {
                    u[a] = rt * (xe[a] - xe[0]) - (xr[a] - xr[0]);
                }
                let y = self.apply_k0(ei, &u, mode);
                energy += 0.5 * (0..4).map(|a| u[a].dot(&y[a])).sum::<f64>();
                [-(r * y[0]), -(r * y[1]), -(r * y[2]), -(r * y[3])]
            }
            Model::StVK => {
                let m = &self.mesh.materials[e.material];
                let f = edge_matrix(&xe) * e.dm_inv;
                let green = (f.transpose() * f - Matrix3::identity()) * 0.5;
                let tr = green.trace();
                energy += e.volume * (m.mu * green.norm_squared() + 0.5 * m.lambda * tr * tr);
                let s = green * (2.0 * m.mu) + Matrix3::identity() * (m.lambda * tr);
                let p = f * s * e.volume;
                [
                    -(p * e.grads[0]),
                    -(p * e.grads[1]),
                    -(p * e.grads[2]),
                    -(p * e.grads[3]),
                ]
            }
        };
        (energy, fe)
    }

    /// Consistent StVK tangent of one element at `x` (N/m):
    /// `K_ab = V[(g_bᵀ S g_a) I + λ (F g_a)(F g_b)ᵀ + μ (g_a·g_b) F Fᵀ + μ (F g_b)(F g_a)ᵀ]`.
    pub(super) fn stvk_tangent(&self, ei: usize, x: &[V3]) -> Mat12 {
        let e = &self.mesh.elements[ei];
        let m = &self.mesh.materials[e.material];
        let f = edge_matrix(&gather(x, &e.nodes)) * e.dm_inv;
        let green = (f.transpose() * f - Matrix3::identity()) * 0.5;
        let s = green * (2.0 * m.mu) + Matrix3::identity() * (m.lambda * green.trace());
        let ff_t = f * f.transpose();
        let fg: [V3; 4] = [
            f * e.grads[0],
            f * e.grads[1],
            f * e.grads[2],
            f * e.grads[3],
        ];
        let mut k = Mat12::zeros();
        for a in 0..4 {
            for b in 0..4 {
                let ga = e.grads[a];
                let gb = e.grads[b];
                let blk = Matrix3::identity() * gb.dot(&(s * ga))
                    + fg[a] * fg[b].transpose() * m.lambda
                    + ff_t * (m.mu * ga.dot(&gb))
                    + fg[b] * fg[a].transpose() * m.mu;
                k.fixed_view_mut::<3, 3>(3 * a, 3 * b)
                    .copy_from(&(blk * e.volume));
            }
        }
        k
    }

    /// Consistent co-rotational tangent of an element that owns its rotation (R = polar
    /// factor of its own F). With `S = RᵀF`, the force is `f_a = −V P g_a`,
    /// `P = 2μ(F − R) + λ tr(S − I) R`, so
    /// `dP = 2μ dF + λ tr(RᵀdF) R + (λ tr(S − I) − 2μ) dR`, `dR = R [ω]×`,
    /// `ω = (tr(S) I − S)⁻¹ axial(RᵀdF − dFᵀR)` (derivative of the polar factor).
    /// Falls back to `R K Rᵀ` when `tr(S) I − S` is singular (element flattened).
    pub(super) fn corot_tangent_consistent(
        &self,
        ei: usize,
        x: &[V3],
        r: &Matrix3<f64>,
    ) -> Option<Mat12> {
        let e = &self.mesh.elements[ei];
        let m = &self.mesh.materials[e.material];
        let f = edge_matrix(&gather(x, &e.nodes)) * e.dm_inv;
        let sm = r.transpose() * f;
        let sm = (sm + sm.transpose()) * 0.5;
        let tr_s = sm.trace();
        let a_inv = (Matrix3::identity() * tr_s - sm).try_inverse()?;
        let c_r = m.lambda * (tr_s - 3.0) - 2.0 * m.mu;
        let mut k = Mat12::zeros();
        for b in 0..4 {
            for c in 0..3 {
                let mut dx = V3::zeros();
                dx[c] = 1.0;
                let df = dx * e.grads[b].transpose();
                let mm = r.transpose() * df;
                let w = mm - mm.transpose();
                let omega = a_inv * V3::new(w[(2, 1)], w[(0, 2)], w[(1, 0)]);
                let dr = r * omega.cross_matrix();
                let dp = df * (2.0 * m.mu) + r * (m.lambda * mm.trace()) + dr * c_r;
                for a in 0..4 {
                    let col = dp * e.grads[a] * e.volume;
                    k.fixed_view_mut::<3, 1>(3 * a, 3 * b + c).copy_from(&col);
                }
            }
        }
        Some(k)
    }

    /// `R K Rᵀ` of one element as a 12×12 matrix.
    pub(super) fn rotated_k(&self, ei: usize, r: &Matrix3<f64>, mode: StiffnessMode) -> Mat12 {
        let k0 = self.k0_matrix(ei, mode);
        let mut k = Mat12::zeros();
        for a in 0..4 {
            for b in 0..4 {
                let blk = r * k0.fixed_view::<3, 3>(3 * a, 3 * b) * r.transpose();
                k.fixed_view_mut::<3, 3>(3 * a, 3 * b).copy_from(&blk);
            }
        }
        k
    }

    /// Tangent element matrices for Newton at `x`: StVK consistent; co-rotational consistent
    /// (incl. the derivative of R) for elements owning their rotation, `R K Rᵀ` for
    /// elements sharing a source; linear `K`.
    pub(super) fn tangent_mats(&self, x: &[V3], model: Model, mode: StiffnessMode) -> Vec<Mat12> {
        (0..self.mesh.elements.len())
            .map(|ei| match model {
                Model::StVK => self.stvk_tangent(ei, x),
                Model::Linear => self.rotated_k(ei, &Matrix3::identity(), mode),
                Model::Corotational => {
                    let e = &self.mesh.elements[ei];
                    let src = &self.rotations.sources[e.source];
                    let own = e.source == e.own_source;
                    own.then(|| self.corot_tangent_consistent(ei, x, &src.rotation))
                        .flatten()
                        .unwrap_or_else(|| self.rotated_k(ei, &src.rotation, mode))
                }
            })
            .collect()
    }

    /// `K_T(x) p` (N) with the Newton tangent of the model (StVK: consistent; co-rotational:
    /// consistent for elements owning their rotation — stored rotations must be those of
    /// `x`, see [`FemSystem::update_rotations`] — else `R K Rᵀ`; linear: `K`), without
    /// Dirichlet projection.
    pub fn apply_tangent(&self, x: &[V3], model: Model, mode: StiffnessMode, p: &[V3]) -> Vec<V3> {
        let mut out = vec![V3::zeros(); self.mesh.rest.len()];
        for ei in 0..self.mesh.elements.len() {
            let e = &self.mesh.elements[ei];
            let pe = gather(p, &e.nodes);
            let y = match model {
                Model::StVK => apply_dense(&self.stvk_tangent(ei, x), &pe),
                Model::Linear => self.apply_k0(ei, &pe, mode),
                Model::Corotational => {
                    let src = &self.rotations.sources[e.source];
                    let consistent = (e.source == e.own_source)
                        .then(|| self.corot_tangent_consistent(ei, x, &src.rotation))
                        .flatten();
                    match consistent {
                        Some(k) => apply_dense(&k, &pe),
                        None => {
                            let r = src.rotation;
                            let rt = r.transpose();
                            let u = [rt * pe[0], rt * pe[1], rt * pe[2], rt * pe[3]];
                            let y = self.apply_k0(ei, &u, mode);
                            [r * y[0], r * y[1], r * y[2], r * y[3]]
                        }
                    }
                }
            };
            for a in 0..4 {
                out[e.nodes[a]] += y[a];
            }
        }
        out
    }

    /// Internal elastic forces at `x` (N), rotations extracted fresh (not stored).
    pub fn internal_forces(&self, x: &[V3], model: Model, mode: StiffnessMode) -> Vec<V3> {
        let rots = if model == Model::Corotational {
            self.compute_rotations(x, &PolarMethod::default())
        } else {
            Vec::new()
        };
        let mut f = vec![V3::zeros(); self.mesh.rest.len()];
        self.elastic(x, model, mode, Some(&rots), Some(&mut f));
        f
    }
}
