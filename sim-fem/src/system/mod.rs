//! The FEM system: nodes, elements, materials, rotation sources; forces, tangents,
//! the implicit integrators and the static Newton solver.
//!
//! Units: positions m, velocities m/s, forces N, time s, E and λ, μ in Pa, ρ kg/m³,
//! Rayleigh α 1/s (mass-proportional), β s (stiffness-proportional).
//!
//! **Mass** is lumped: node i gets `m_i = Σ_e ρ_e V_e / 4` over its elements.
//! **Damping** is Rayleigh per element: `D = Σ_e α_e M_e + β_e K_e`, with `K_e` the
//! model's (co-rotated) small-strain stiffness — never an indefinite StVK tangent.
//!
//! One file per part of [`FemSystem`]:
//!
//! | file | what |
//! |---|---|
//! | `desc.rs` | what the caller describes: [`FemDesc`], [`Material`], [`ElementDesc`] |
//! | `step_params.rs` | [`StepParams`], the parameters of a dynamic step |
//! | `construct.rs` | [`FemSystem::new`]: validation, lumped masses, stiffness templates |
//! | `rotations.rs` | rotation sources, their assignment and extraction passes |
//! | `caches.rs` | dense stiffness, CG warm start, block pattern and assembly order |
//! | `execution.rs` | thread pool and partition of multi-threaded steps |
//! | `forces.rs` | element stiffness kernels, internal forces, energies' elastic part, tangents |
//! | `step.rs` | [`FemSystem::step`]: [`StepStats`], the choice of integrator |
//! | `linearised.rs` | the linearised backward-Euler step and its matrix |
//! | `energy_guard.rs` | the energy guard of the linearised step, kinetic and potential energy |
//! | `newton.rs` | backward Euler with Newton (StVK, fallback), the line search |
//! | `statics.rs` | [`FemSystem::solve_static`] |
//! | `multigrid.rs` | the multigrid hierarchy a step's MG-PCG uses, and its refresh |
//! | `operator.rs` | the system operator: matrix-free products or assembled block CSR |

mod caches;
mod construct;
mod desc;
mod direct;
mod element_blocks;
mod energy_guard;
mod execution;
mod forces;
mod linearised;
mod multigrid;
mod newton;
mod operator;
mod rotations;
mod source_stiffness;
mod statics;
mod step;
mod step_params;
#[cfg(test)]
mod tests;

use nalgebra::{Matrix3, Vector3};

pub use crate::model::Model;
pub use desc::{ElementDesc, FemDesc, Material, RotationSourceDesc, ShapeRef, TemplateInfo};
pub use multigrid::{AUTO_MG_ABOVE_JACOBI_ITERATIONS, AUTO_MG_MIN_FREE_NODES};
pub use statics::{StaticParams, StaticStats};
pub use step::StepStats;
pub use step_params::{
    FALLBACK_NEWTON, LinearSolver, NewtonParams, OperatorMode, StepParams, StiffnessMode,
    UnknownLinearSolver,
};

use crate::FemError;
use crate::element::{Mat12, Template, edge_matrix};
use caches::Caches;
use execution::Execution;
use rotations::RotationState;

type V3 = Vector3<f64>;

/// A finite-element system on a fixed mesh. See the module docs for units.
#[derive(Clone, Debug)]
pub struct FemSystem {
    /// Nodes, elements, materials, masses and stiffness templates (fixed at construction
    /// but for the Dirichlet mask).
    mesh: MeshData,
    /// Rotation sources and extraction passes.
    rotations: RotationState,
    /// External (contact) stiffness blocks `(node, K)` (N/m), see
    /// [`FemSystem::set_external_stiffness`].
    k_ext: Vec<(usize, Matrix3<f64>)>,
    /// What steps keep for the next one: storage, orderings, warm starts.
    caches: Caches,
    /// Thread pool and partition of multi-threaded steps.
    exec: Execution,
}

/// The mesh as the system uses it.
#[derive(Clone, Debug)]
struct MeshData {
    /// Rest positions (m).
    rest: Vec<V3>,
    elements: Vec<Element>,
    materials: Vec<MatData>,
    /// Dirichlet mask per node.
    fixed: Vec<bool>,
    /// Lumped mass per node (kg).
    mass: Vec<f64>,
    /// Rayleigh mass damping per node, `α m_i` (kg/s).
    mass_damping: Vec<f64>,
    /// Stiffness templates, one per shape key.
    templates: Vec<Template>,
    /// Elements per template.
    template_uses: Vec<usize>,
    /// `λ K̂_λ + μ K̂_μ` per (template, material) pair in use.
    combos: Vec<Mat12>,
}

/// One element.
#[derive(Clone, Debug)]
struct Element {
    nodes: [usize; 4],
    material: usize,
    /// Inverse rest edge matrix `D_m⁻¹` (1/m).
    dm_inv: Matrix3<f64>,
    /// Shape-function gradients (1/m).
    grads: [V3; 4],
    /// Rest volume (m³).
    volume: f64,
    /// Template index and scale h_e (m), if the element has a shape key.
    template: Option<(usize, f64)>,
    /// Index into `MeshData::combos` (`usize::MAX` without template).
    combo: usize,
    /// The source whose rotation the element uses now.
    source: usize,
    /// The element's own source (its own F).
    own_source: usize,
}

/// A material as the kernels use it: Lamé parameters (Pa) and Rayleigh β (s).
#[derive(Clone, Copy, Debug)]
struct MatData {
    lambda: f64,
    mu: f64,
    beta: f64,
}

fn gather(x: &[V3], n: &[usize; 4]) -> [V3; 4] {
    [x[n[0]], x[n[1]], x[n[2]], x[n[3]]]
}

fn dot(a: &[V3], b: &[V3]) -> f64 {
    a.iter().zip(b).map(|(p, q)| p.dot(q)).sum()
}

impl FemSystem {
    /// Number of nodes.
    pub fn num_nodes(&self) -> usize {
        self.mesh.rest.len()
    }

    /// Number of elements.
    pub fn num_elements(&self) -> usize {
        self.mesh.elements.len()
    }

    /// Rest positions (m).
    pub fn rest_positions(&self) -> &[V3] {
        &self.mesh.rest
    }

    /// Lumped nodal masses (kg).
    pub fn lumped_mass(&self) -> &[f64] {
        &self.mesh.mass
    }

    /// Dirichlet mask.
    pub fn fixed(&self) -> &[bool] {
        &self.mesh.fixed
    }

    /// Change the Dirichlet mask (same length as the node array).
    pub fn set_fixed(&mut self, fixed: Vec<bool>) -> Result<(), FemError> {
        if fixed.len() != self.mesh.rest.len() {
            return Err(FemError::Size {
                what: "fixed",
                expected: self.mesh.rest.len(),
                got: fixed.len(),
            });
        }
        self.mesh.fixed = fixed;
        Ok(())
    }

    /// Template zero statistics per shape key.
    pub fn template_info(&self) -> Vec<TemplateInfo> {
        self.mesh
            .templates
            .iter()
            .zip(&self.mesh.template_uses)
            .map(|(t, &u)| TemplateInfo {
                key: t.key,
                zero_fraction: t.zero_fraction,
                zero_block_fraction: t.zero_block_fraction,
                elements: u,
            })
            .collect()
    }

    /// Contact (or any external) stiffness `K_ext = −∂f_ext/∂x` as 3×3 blocks on nodes
    /// (N/m). It is added to the implicit system (`dt² K_ext`) of every following step until
    /// replaced or cleared; the matching forces go into `f_ext`. Blocks should be symmetric
    /// positive semi-definite (penalty springs).
    pub fn set_external_stiffness(&mut self, blocks: &[(usize, Matrix3<f64>)]) {
        self.k_ext.clear();
        self.k_ext.extend_from_slice(blocks);
    }

    /// Remove all external stiffness blocks.
    pub fn clear_external_stiffness(&mut self) {
        self.k_ext.clear();
    }

    /// Deformation gradient `F = D_s D_m⁻¹` of element `ei` at `x`.
    pub fn deformation_gradient(&self, ei: usize, x: &[V3]) -> Matrix3<f64> {
        let e = &self.mesh.elements[ei];
        edge_matrix(&gather(x, &e.nodes)) * e.dm_inv
    }

    /// Node ids of element `ei`.
    pub fn element_nodes(&self, ei: usize) -> [usize; 4] {
        self.mesh.elements[ei].nodes
    }

    /// Rest volume of all elements (m³).
    pub fn rest_volume(&self) -> f64 {
        self.mesh.elements.iter().map(|e| e.volume).sum()
    }

    /// Deformed volume Σ det(F_e) V_e (m³).
    pub fn deformed_volume(&self, x: &[V3]) -> f64 {
        self.mesh
            .elements
            .iter()
            .map(|e| (edge_matrix(&gather(x, &e.nodes)) * e.dm_inv).determinant() * e.volume)
            .sum()
    }

    /// Errors unless `x`, `v` (when given) and `f` have one entry per node.
    pub(super) fn check_sizes(&self, x: &[V3], v: Option<&[V3]>, f: &[V3]) -> Result<(), FemError> {
        let n = self.mesh.rest.len();
        for (what, len) in [
            ("x", x.len()),
            ("v", v.map_or(n, |v| v.len())),
            ("f_ext", f.len()),
        ] {
            if len != n {
                return Err(FemError::Size {
                    what,
                    expected: n,
                    got: len,
                });
            }
        }
        Ok(())
    }
}
