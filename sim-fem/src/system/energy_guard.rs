//! The energy guard of the linearised co-rotational step ([`StepParams::energy_guard`])
//! and the energies it compares.

use super::{FemSystem, V3, gather};
use crate::model::Model;
use crate::system::{StepParams, StepStats};

/// The state a guarded step started from, to compare with and to return to.
pub(super) struct GuardStart {
    /// Positions (m) and velocities (m/s) at the start of the step.
    x: Vec<V3>,
    v: Vec<V3>,
    /// Total energy at the start (J).
    energy: f64,
    /// Elastic + kinetic energy at the start (J), the scale of the round-off allowance.
    scale: f64,
}

impl GuardStart {
    /// Puts the step's start state back into `(x, v)`.
    pub(super) fn restore(self, x: &mut [V3], v: &mut [V3]) {
        x.copy_from_slice(&self.x);
        v.copy_from_slice(&self.v);
    }
}

impl FemSystem {
    /// Arms the guard for a linearised step from `(x, v)` with elastic energy `elastic_n`
    /// (J) at `x`, or None where it does not apply. Energy guard: only where rotations
    /// can jump (elements inverted before or after the step, checked by
    /// [`FemSystem::energy_guard_rejects`]), no boundary moves and no contact springs act
    /// (their work and stored energy are not known here; a tool is an energy source anyway).
    pub(super) fn energy_guard_start(
        &self,
        x: &[V3],
        v: &[V3],
        elastic_n: f64,
        p: &StepParams,
    ) -> Option<GuardStart> {
        (p.energy_guard
            && p.model == Model::Corotational
            && self.k_ext.is_empty()
            && !self
                .mesh
                .fixed
                .iter()
                .zip(v.iter())
                .any(|(f, vi)| *f && *vi != V3::zeros()))
        .then(|| {
            let energy = self.total_energy(elastic_n, x, v, &p.gravity);
            let scale = elastic_n + self.kinetic_energy(v);
            GuardStart {
                x: x.to_vec(),
                v: v.to_vec(),
                energy,
                scale,
            }
        })
    }

    /// Whether the linearised step to `(x, v)` must be redone: elements were inverted
    /// before or after it (`attempt`: its statistics) and it raised the total energy by
    /// more than the external forces' work.
    pub(super) fn energy_guard_rejects(
        &self,
        start: &GuardStart,
        x: &[V3],
        v: &[V3],
        f_ext: &[V3],
        p: &StepParams,
        attempt: &StepStats,
    ) -> bool {
        if !(attempt.inverted > 0 || self.any_inverted_in_either(&start.x, x)) {
            return false;
        }
        // Energy at x_{n+1} with its own rotations (stored state untouched).
        let rotations = self.compute_rotations(x, &p.polar);
        let elastic = self.elastic(x, p.model, p.stiffness, Some(&rotations), None);
        let energy = self.total_energy(elastic, x, v, &p.gravity);
        let fixed = &self.mesh.fixed;
        let work: f64 = (0..x.len())
            .filter(|&i| !fixed[i])
            .map(|i| f_ext[i].dot(&(x[i] - start.x[i])))
            .sum();
        // Round-off allowance: 1e-6 of the elastic + kinetic energy.
        let rejected = energy > start.energy + work + 1e-6 * start.scale + 1e-12;
        if rejected {
            tracing::debug!(
                gained_j = energy - start.energy - work,
                inverted = attempt.inverted,
                cg_iterations = attempt.cg_iterations,
                cg_residual = attempt.cg_residual,
                "linearised step created energy; redone with Newton"
            );
        }
        rejected
    }

    /// Elastic (given) + kinetic + gravitational energy (J).
    pub(super) fn total_energy(&self, elastic: f64, x: &[V3], v: &[V3], gravity: &V3) -> f64 {
        elastic + self.kinetic_energy(v) + self.gravity_energy(x, gravity)
    }

    /// Whether some element has `det F ≤ 0` at `x`.
    pub fn any_inverted(&self, x: &[V3]) -> bool {
        self.any_element(|ei| self.element_inverted(ei, x))
    }

    /// Whether some element has `det F ≤ 0` at `x` or at `y` (one pass over the elements'
    /// nodes for both states of a step).
    fn any_inverted_in_either(&self, x: &[V3], y: &[V3]) -> bool {
        self.any_element(|ei| self.element_inverted(ei, x) || self.element_inverted(ei, y))
    }

    /// Whether `pred` holds for some element index; on the step's threads when it has
    /// several.
    fn any_element(&self, pred: impl Fn(usize) -> bool + Sync + Send) -> bool {
        let n = self.mesh.elements.len();
        if self.active_partition().is_some() {
            use rayon::prelude::*;
            return (0..n).into_par_iter().with_min_len(4096).any(pred);
        }
        (0..n).any(pred)
    }

    /// Whether element `ei` has `det F ≤ 0` at `x`: rest elements are positively oriented,
    /// so this is the sign of `det D_s = (b − a)·((c − a) × (d − a))`.
    #[inline]
    pub fn element_inverted(&self, ei: usize, x: &[V3]) -> bool {
        let [a, b, c, d] = gather(x, &self.mesh.elements[ei].nodes);
        (b - a).dot(&(c - a).cross(&(d - a))) <= 0.0
    }

    /// Kinetic energy ½ vᵀ M v (J).
    pub fn kinetic_energy(&self, v: &[V3]) -> f64 {
        0.5 * v
            .iter()
            .zip(&self.mesh.mass)
            .map(|(vi, m)| m * vi.norm_squared())
            .sum::<f64>()
    }

    /// Gravitational potential −Σ m_i g·x_i (J), zero at the origin.
    pub fn gravity_energy(&self, x: &[V3], gravity: &V3) -> f64 {
        -x.iter()
            .zip(&self.mesh.mass)
            .map(|(xi, m)| m * gravity.dot(xi))
            .sum::<f64>()
    }
}
