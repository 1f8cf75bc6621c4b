//! The FEM system: nodes, elements, materials, rotation sources; forces, tangents,
//! the implicit integrators and the static Newton solver.
//!
//! Units: positions m, velocities m/s, forces N, time s, E and λ, μ in Pa, ρ kg/m³,
//! Rayleigh α 1/s (mass-proportional), β s (stiffness-proportional).
//!
//! **Mass** is lumped: node i gets `m_i = Σ_e ρ_e V_e / 4` over its elements.
//! **Damping** is Rayleigh per element: `D = Σ_e α_e M_e + β_e K_e`, with `K_e` the
//! model's (co-rotated) small-strain stiffness — never an indefinite StVK tangent.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use crate::FemError;
use crate::element::{
    Mat12, Template, TetGeometry, apply_dense, apply_k_gradient, edge_matrix, k_lambda_mu, lame,
};
use crate::parallel::{Partition, multiply_upper_parts, split_ranges};
use crate::polar::{PolarMethod, RotationExtractor, WarmStart};
use crate::solver::{BlockPattern, CgResult, LinearOperator, SolverParams, pcg};

type V3 = Vector3<f64>;

/// Material of an element.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Material {
    /// Young's modulus E (Pa).
    pub young: f64,
    /// Poisson ratio ν (dimensionless, < 0.5).
    pub poisson: f64,
    /// Density ρ (kg/m³).
    pub density: f64,
    /// Rayleigh mass-proportional damping α (1/s).
    pub rayleigh_mass: f64,
    /// Rayleigh stiffness-proportional damping β (s).
    pub rayleigh_stiffness: f64,
}

impl Material {
    /// Undamped material.
    pub fn new(young: f64, poisson: f64, density: f64) -> Self {
        Self {
            young,
            poisson,
            density,
            rayleigh_mass: 0.0,
            rayleigh_stiffness: 0.0,
        }
    }
    /// Lamé `(λ, μ)` (Pa).
    pub fn lame(&self) -> (f64, f64) {
        lame(self.young, self.poisson)
    }
}

/// Shape of a template element: tets with equal `key` differ only by translation and
/// uniform scale `scale` (= h_e, m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShapeRef {
    /// Caller's hashable shape key.
    pub key: u64,
    /// Uniform scale h_e (m).
    pub scale: f64,
}

/// One element as the caller describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElementDesc {
    /// Node ids, positively oriented (rest volume > 0).
    pub nodes: [usize; 4],
    /// Index into the material array.
    pub material: usize,
    /// Shape key and scale for the template stiffness table (None: dense/gradient path).
    pub shape: Option<ShapeRef>,
    /// Index of the rotation source whose R this element uses initially (None: its own).
    /// Every element also gets a source of its own, so
    /// [`FemSystem::set_rotation_assignment`] can switch between the two at any step.
    pub rotation_source: Option<usize>,
}

/// A tet whose rotation other elements may share (e.g. a coarse ancestor whose four
/// vertices are nodes of the mesh).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RotationSourceDesc {
    /// Node ids.
    pub nodes: [usize; 4],
    /// `D_m⁻¹` of its rest edges (1/m); None: computed from the rest positions.
    pub rest_inverse_edges: Option<Matrix3<f64>>,
}

/// Everything needed to build a [`FemSystem`].
#[derive(Clone, Debug, Default)]
pub struct FemDesc {
    /// Rest positions (m).
    pub rest: Vec<V3>,
    /// Elements.
    pub elements: Vec<ElementDesc>,
    /// Materials.
    pub materials: Vec<Material>,
    /// Dirichlet mask per node (empty: none fixed).
    pub fixed: Vec<bool>,
    /// Shared rotation sources referenced by `ElementDesc::rotation_source`.
    pub rotation_sources: Vec<RotationSourceDesc>,
}

/// Constitutive model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Model {
    /// Small-strain linear elasticity `f = −K (x − X)`.
    Linear,
    /// Co-rotational linear: `f_e = −R_e K_e (R_eᵀ x_e − X_e)`, tangent `R K Rᵀ` with R
    /// frozen during a step (as SOFA).
    #[default]
    Corotational,
    /// St Venant–Kirchhoff: `ψ = μ E:E + λ/2 tr²E`, `E = ½(FᵀF − I)`, consistent tangent.
    StVK,
}

/// How the small-strain element stiffness is applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum StiffnessMode {
    /// Per-element dense 12×12 matrix (built lazily, 1.15 kB per element).
    Dense,
    /// `h_e K̂[s, m]` with `K̂[s, m] = λ_m K̂_λ[s] + μ_m K̂_μ[s]` one dense 12×12 per
    /// (shape, material) pair — no per-element storage; elements without a shape key use
    /// `Gradient`.
    #[default]
    Template,
    /// `h_e (λ K̂_λ[s] + μ K̂_μ[s])` evaluated from the template's non-zero entries only
    /// (zero entries skipped); elements without a shape key use `Gradient`.
    TemplateSparse,
    /// `K u = V σ(ε(u)) g` from the shape gradients, no matrix at all.
    Gradient,
}

/// How the system matrix enters CG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum OperatorMode {
    /// Element-by-element products every CG iteration.
    MatrixFree,
    /// 3×3-block CSR assembled once per linear solve (default: measured 3–4× faster per
    /// step than matrix-free at 1,536 and 12,288 tets with 25 CG iterations).
    #[default]
    Assembled,
}

/// Newton iteration control for the non-linear dynamic step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NewtonParams {
    /// Maximum Newton iterations per step.
    pub max_iters: usize,
    /// Stop when the force residual (free DOFs, 2-norm) is below this (N).
    pub tol: f64,
}

/// Parameters of a dynamic step.
#[derive(Clone, Copy, Debug)]
pub struct StepParams {
    /// Constitutive model.
    pub model: Model,
    /// Stiffness kernel.
    pub stiffness: StiffnessMode,
    /// Matrix-free or assembled CG.
    pub operator: OperatorMode,
    /// CG budget.
    pub solver: SolverParams,
    /// Gravity (m/s²).
    pub gravity: V3,
    /// Rotation extractor.
    pub polar: PolarMethod,
    /// Reuse a source's rotation if none of its nodes moved more than this since the last
    /// extraction (m); 0 disables the skip.
    pub rest_threshold: f64,
    /// None: linearised backward Euler (Linear, Corotational). Some: backward Euler with
    /// Newton iterations (always used for StVK; default 1 iteration if None).
    pub newton: Option<NewtonParams>,
    /// Robust fallback of the linearised co-rotational step (degrees; 0 = off): when a
    /// rotation source turned by more than this angle since the previous step (fast spin,
    /// or the flip of an inverted element's least-stretch direction), the linearisation
    /// about `x_n` with R frozen is not to be trusted (it can pump energy), and the step is taken
    /// as backward Euler with [`FALLBACK_NEWTON`] iterations (consistent tangent, line
    /// search on the incremental potential) instead. See [`StepStats::fallback`].
    pub fallback_angle_deg: f64,
    /// Threads for the linearised step (1 = the calling thread only). With more, rotation
    /// extraction, element forces, the assembly and the sparse products of the assembled
    /// co-rotational/linear operator run on a pool of that many threads (see
    /// `parallel.rs`); Newton steps, the matrix-free operator and the energy guard's extra
    /// work stay sequential. Results equal the sequential ones up to the order of
    /// floating-point sums.
    pub threads: usize,
    /// Energy guard of the linearised co-rotational step: on steps with inverted elements
    /// before or after them (whose rotations can jump as they pass through degenerate
    /// shapes), no prescribed motion and no contact stiffness, the step is redone with the
    /// Newton fallback ([`FALLBACK_NEWTON`]) when it raised the total energy (elastic +
    /// kinetic + gravitational) by more than the external forces' work. Backward Euler
    /// must not create energy; without the guard a pull through inversion gained tens of J
    /// in one step. Every step then pays a copy of x and v and a signed-volume scan of the
    /// elements; steps with inverted elements also a rotation pass and an energy
    /// evaluation.
    pub energy_guard: bool,
}

/// Newton control of the robust fallback step ([`StepParams::fallback_angle_deg`]).
pub const FALLBACK_NEWTON: NewtonParams = NewtonParams {
    max_iters: 4,
    tol: 1e-6,
};

impl Default for StepParams {
    fn default() -> Self {
        Self {
            model: Model::Corotational,
            stiffness: StiffnessMode::Template,
            operator: OperatorMode::Assembled,
            solver: SolverParams::realtime(),
            gravity: V3::new(0.0, 0.0, -9.81),
            polar: PolarMethod::default(),
            rest_threshold: 0.0,
            newton: None,
            fallback_angle_deg: 0.0,
            threads: 1,
            energy_guard: false,
        }
    }
}

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
}

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

/// Template zero statistics (see [`Template`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TemplateInfo {
    /// Shape key.
    pub key: u64,
    /// Zero fraction of the 144 entries.
    pub zero_fraction: f64,
    /// Zero fraction of the 16 blocks.
    pub zero_block_fraction: f64,
    /// Elements using it.
    pub elements: usize,
}

#[derive(Clone, Debug)]
struct Element {
    nodes: [usize; 4],
    material: usize,
    dm_inv: Matrix3<f64>,
    grads: [V3; 4],
    volume: f64,
    template: Option<(usize, f64)>,
    combo: usize,
    /// The source whose rotation the element uses now.
    source: usize,
    /// The element's own source (its own F).
    own_source: usize,
}

#[derive(Clone, Debug)]
struct Source {
    nodes: [usize; 4],
    dm_inv: Matrix3<f64>,
    rotation: Matrix3<f64>,
    x_last: [V3; 4],
    sigma: Option<(f64, f64)>,
    valid: bool,
    /// Extracted at the current positions (since the last [`FemSystem::update_rotations`]).
    fresh: bool,
    /// Elements currently using this source.
    users: u32,
    /// Rotation pass ([`FemSystem::update_rotations`] count) of the last extraction.
    pass: u64,
}

/// Extraction counters `(extracted, reused, polar iterations, inverted)`.
#[derive(Clone, Copy, Debug, Default)]
struct ExtractCount {
    extracted: usize,
    reused: usize,
    iterations: usize,
    inverted: usize,
    /// Max `‖R_new − R_old‖²_F` over sources extracted in consecutive passes.
    max_change_sq: f64,
}

impl ExtractCount {
    fn merge(self, o: Self) -> Self {
        Self {
            extracted: self.extracted + o.extracted,
            reused: self.reused + o.reused,
            iterations: self.iterations + o.iterations,
            inverted: self.inverted + o.inverted,
            max_change_sq: self.max_change_sq.max(o.max_change_sq),
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct MatData {
    lambda: f64,
    mu: f64,
    beta: f64,
}

/// Element matrices entering a linear operator.
enum ElemMats {
    /// `coef_e · R_e K_e R_eᵀ` (R = I if `rotated` is false).
    Rotated { coef: Vec<f64>, rotated: bool },
    /// Explicit per-element 12×12 matrices.
    Dense(Vec<Mat12>),
}

/// A finite-element system on a fixed mesh. See the module docs for units.
#[derive(Clone, Debug)]
pub struct FemSystem {
    rest: Vec<V3>,
    elements: Vec<Element>,
    materials: Vec<MatData>,
    fixed: Vec<bool>,
    mass: Vec<f64>,
    mass_damping: Vec<f64>,
    sources: Vec<Source>,
    /// Caller's (shared) sources are `sources[..num_shared]`.
    num_shared: usize,
    /// Extractions of shared sources requested between steps.
    pending: ExtractCount,
    /// Rotation passes done (1-based numbering of the current one).
    pass: u64,
    /// Statistics of the last rotation pass.
    last_pass: ExtractCount,
    templates: Vec<Template>,
    template_uses: Vec<usize>,
    combos: Vec<Mat12>,
    dense: Option<Vec<Mat12>>,
    k_ext: Vec<(usize, Matrix3<f64>)>,
    warm_dv: Vec<V3>,
    pattern: Option<BlockPattern>,
    /// Element indices grouped by their current rotation source (assembly order), and
    /// whether the assignment changed since it was built.
    by_source: Vec<u32>,
    by_source_stale: bool,
    /// Block storage of the assembled operator, kept between steps to avoid reallocating.
    block_buf: Vec<Matrix3<f64>>,
    /// Thread pool of multi-threaded steps ([`StepParams::threads`]), built on first use.
    pool: Option<std::sync::Arc<rayon::ThreadPool>>,
    /// Threads of the step in progress (1 outside multi-threaded steps).
    threads: usize,
    /// Split of nodes and elements for `threads` (rebuilt with `by_source`).
    partition: Option<Partition>,
}

fn gather(x: &[V3], n: &[usize; 4]) -> [V3; 4] {
    [x[n[0]], x[n[1]], x[n[2]], x[n[3]]]
}

fn dot(a: &[V3], b: &[V3]) -> f64 {
    a.iter().zip(b).map(|(p, q)| p.dot(q)).sum()
}

impl FemSystem {
    /// Build from arrays. Errors on out-of-range ids, non-positive rest volumes, bad
    /// materials, or an element whose geometry does not match its shape template.
    pub fn new(desc: &FemDesc) -> Result<Self, FemError> {
        let n = desc.rest.len();
        if !desc.fixed.is_empty() && desc.fixed.len() != n {
            return Err(FemError::Size {
                what: "fixed",
                expected: n,
                got: desc.fixed.len(),
            });
        }
        let mut materials = Vec::with_capacity(desc.materials.len());
        for (i, m) in desc.materials.iter().enumerate() {
            if !(m.young > 0.0 && m.poisson > -1.0 && m.poisson < 0.5 && m.density > 0.0)
                || m.rayleigh_mass < 0.0
                || m.rayleigh_stiffness < 0.0
            {
                return Err(FemError::BadMaterial {
                    material: i,
                    reason: format!("{m:?}: need E > 0, −1 < ν < 0.5, ρ > 0, α, β ≥ 0"),
                });
            }
            let (lambda, mu) = m.lame();
            materials.push(MatData {
                lambda,
                mu,
                beta: m.rayleigh_stiffness,
            });
        }
        let mut sources = Vec::with_capacity(desc.rotation_sources.len() + desc.elements.len());
        for (i, s) in desc.rotation_sources.iter().enumerate() {
            if s.nodes.iter().any(|&k| k >= n) {
                return Err(FemError::BadSource {
                    index: i,
                    reason: "node id out of range".into(),
                });
            }
            let dm_inv = match s.rest_inverse_edges {
                Some(m) => m,
                None => {
                    TetGeometry::new(&gather(&desc.rest, &s.nodes))
                        .map_err(|e| FemError::BadSource {
                            index: i,
                            reason: e.to_string(),
                        })?
                        .dm_inv
                }
            };
            sources.push(Source {
                nodes: s.nodes,
                dm_inv,
                rotation: Matrix3::identity(),
                x_last: gather(&desc.rest, &s.nodes),
                sigma: None,
                valid: false,
                fresh: false,
                users: 0,
                pass: 0,
            });
        }
        let mut templates: Vec<Template> = Vec::new();
        let mut template_uses = Vec::new();
        let mut by_key: HashMap<u64, usize> = HashMap::new();
        let mut combos: Vec<Mat12> = Vec::new();
        let mut by_combo: HashMap<(usize, usize), usize> = HashMap::new();
        let mut elements = Vec::with_capacity(desc.elements.len());
        let mut mass = vec![0.0; n];
        let mut mass_damping = vec![0.0; n];
        for (ei, e) in desc.elements.iter().enumerate() {
            if e.nodes.iter().any(|&k| k >= n) {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: "node id out of range".into(),
                });
            }
            let Some(mat) = desc.materials.get(e.material) else {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: format!("material {} out of range", e.material),
                });
            };
            let xr = gather(&desc.rest, &e.nodes);
            let geom = TetGeometry::new(&xr).map_err(|err| match err {
                FemError::BadElement { reason, .. } => FemError::BadElement {
                    element: ei,
                    reason,
                },
                other => other,
            })?;
            let template = match e.shape {
                None => None,
                Some(s) => {
                    let ti = match by_key.get(&s.key) {
                        Some(&t) => t,
                        None => {
                            templates.push(Template::new(s.key, &xr, s.scale)?);
                            template_uses.push(0);
                            by_key.insert(s.key, templates.len() - 1);
                            templates.len() - 1
                        }
                    };
                    let expect = templates[ti].dm_inv_hat / s.scale;
                    if (expect - geom.dm_inv).norm() > 1e-9 * geom.dm_inv.norm() {
                        return Err(FemError::BadElement {
                            element: ei,
                            reason: format!(
                                "geometry does not match shape key {} at scale {} m",
                                s.key, s.scale
                            ),
                        });
                    }
                    template_uses[ti] += 1;
                    Some((ti, s.scale))
                }
            };
            let combo = match template {
                None => usize::MAX,
                Some((ti, _)) => *by_combo.entry((ti, e.material)).or_insert_with(|| {
                    let t = &templates[ti];
                    let (l, m) = mat.lame();
                    combos.push(t.k_lambda * l + t.k_mu * m);
                    combos.len() - 1
                }),
            };
            if let Some(s) = e.rotation_source
                && s >= desc.rotation_sources.len()
            {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: format!("rotation source {s} out of range"),
                });
            }
            sources.push(Source {
                nodes: e.nodes,
                dm_inv: geom.dm_inv,
                rotation: Matrix3::identity(),
                x_last: xr,
                sigma: None,
                valid: false,
                fresh: false,
                users: 0,
                pass: 0,
            });
            let own_source = sources.len() - 1;
            let source = e.rotation_source.unwrap_or(own_source);
            sources[source].users += 1;
            let m4 = mat.density * geom.volume / 4.0;
            for &k in &e.nodes {
                mass[k] += m4;
                mass_damping[k] += mat.rayleigh_mass * m4;
            }
            elements.push(Element {
                nodes: e.nodes,
                material: e.material,
                dm_inv: geom.dm_inv,
                grads: geom.grads,
                volume: geom.volume,
                template,
                combo,
                source,
                own_source,
            });
        }
        let fixed = if desc.fixed.is_empty() {
            vec![false; n]
        } else {
            desc.fixed.clone()
        };
        tracing::debug!(
            nodes = n,
            elements = elements.len(),
            sources = sources.len(),
            templates = templates.len(),
            "built FemSystem"
        );
        Ok(Self {
            rest: desc.rest.clone(),
            elements,
            materials,
            fixed,
            mass,
            mass_damping,
            sources,
            num_shared: desc.rotation_sources.len(),
            pending: ExtractCount::default(),
            pass: 1,
            last_pass: ExtractCount::default(),
            templates,
            template_uses,
            combos,
            dense: None,
            k_ext: Vec::new(),
            warm_dv: vec![V3::zeros(); n],
            pattern: None,
            by_source: Vec::new(),
            by_source_stale: true,
            block_buf: Vec::new(),
            pool: None,
            threads: 1,
            partition: None,
        })
    }

    /// Number of nodes.
    pub fn num_nodes(&self) -> usize {
        self.rest.len()
    }
    /// Number of elements.
    pub fn num_elements(&self) -> usize {
        self.elements.len()
    }
    /// Rest positions (m).
    pub fn rest_positions(&self) -> &[V3] {
        &self.rest
    }
    /// Lumped nodal masses (kg).
    pub fn lumped_mass(&self) -> &[f64] {
        &self.mass
    }
    /// Dirichlet mask.
    pub fn fixed(&self) -> &[bool] {
        &self.fixed
    }
    /// Change the Dirichlet mask (same length as the node array).
    pub fn set_fixed(&mut self, fixed: Vec<bool>) -> Result<(), FemError> {
        if fixed.len() != self.rest.len() {
            return Err(FemError::Size {
                what: "fixed",
                expected: self.rest.len(),
                got: fixed.len(),
            });
        }
        self.fixed = fixed;
        Ok(())
    }
    /// Number of rotation sources: the caller's shared ones first, then one per element.
    pub fn num_rotation_sources(&self) -> usize {
        self.sources.len()
    }
    /// Number of the caller's (shared) rotation sources, `FemDesc::rotation_sources.len()`.
    pub fn num_shared_sources(&self) -> usize {
        self.num_shared
    }
    /// Rotation sources some element uses now (only these are extracted by a step).
    pub fn num_referenced_sources(&self) -> usize {
        self.sources.iter().filter(|s| s.users > 0).count()
    }
    /// The shared source element `ei` uses, or None when it uses its own rotation.
    pub fn element_source(&self, ei: usize) -> Option<usize> {
        let e = &self.elements[ei];
        (e.source != e.own_source).then_some(e.source)
    }

    /// Switch the rotation source of every element: `Some(s)` uses shared source `s`
    /// (`s < num_shared_sources()`), `None` the element's own F. Takes effect at the next
    /// force evaluation / step; only sources that some element references are extracted.
    /// Cost O(elements); an unchanged assignment changes nothing.
    pub fn set_rotation_assignment(
        &mut self,
        assignment: &[Option<usize>],
    ) -> Result<(), FemError> {
        if assignment.len() != self.elements.len() {
            return Err(FemError::Size {
                what: "rotation assignment",
                expected: self.elements.len(),
                got: assignment.len(),
            });
        }
        if let Some((ei, s)) = assignment
            .iter()
            .enumerate()
            .find_map(|(ei, a)| a.filter(|s| *s >= self.num_shared).map(|s| (ei, s)))
        {
            return Err(FemError::BadElement {
                element: ei,
                reason: format!(
                    "rotation source {s} out of range ({} shared sources)",
                    self.num_shared
                ),
            });
        }
        for (e, a) in self.elements.iter_mut().zip(assignment) {
            let new = a.unwrap_or(e.own_source);
            if new != e.source {
                self.sources[e.source].users -= 1;
                self.sources[new].users += 1;
                e.source = new;
                self.by_source_stale = true;
            }
        }
        Ok(())
    }

    /// Rotation of shared source `s` at positions `x`, extracted now unless it already was
    /// at these positions (since the last step) or its nodes are at rest (`rest_threshold`,
    /// m, as in [`StepParams::rest_threshold`]). The extraction counts towards the next
    /// step's [`StepStats::rotations_extracted`], and the step does not extract it again.
    /// For the caller's sharing test; `s < num_shared_sources()`.
    pub fn shared_source_rotation(
        &mut self,
        s: usize,
        x: &[V3],
        polar: &PolarMethod,
        rest_threshold: f64,
    ) -> Matrix3<f64> {
        assert!(s < self.num_shared, "shared source {s} out of range");
        let src = &mut self.sources[s];
        if !src.fresh {
            extract_source(src, x, polar, rest_threshold, self.pass, &mut self.pending);
        }
        src.rotation
    }
    /// Current rotation of a source (valid after a step / force evaluation).
    pub fn source_rotation(&self, source: usize) -> Matrix3<f64> {
        self.sources[source].rotation
    }
    /// Current rotation used by an element.
    pub fn element_rotation(&self, element: usize) -> Matrix3<f64> {
        self.sources[self.elements[element].source].rotation
    }
    /// Template zero statistics per shape key.
    pub fn template_info(&self) -> Vec<TemplateInfo> {
        self.templates
            .iter()
            .zip(&self.template_uses)
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
        let fixed = self.fixed.clone();
        let rotated = p.model == Model::Corotational;
        let op = self.build_operator(
            mass_coef,
            ElemMats::Rotated { coef, rotated },
            dt * dt,
            p.stiffness,
            OperatorMode::Assembled,
        );
        let pat = op.sys.pattern.as_ref().expect("assembled");
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
    fn linearised_coefficients(&self, dt: f64) -> (Vec<f64>, Vec<f64>) {
        let mass_coef = (0..self.rest.len())
            .map(|i| self.mass[i] + dt * self.mass_damping[i])
            .collect();
        let coef = self
            .elements
            .iter()
            .map(|e| dt * self.materials[e.material].beta + dt * dt)
            .collect();
        (mass_coef, coef)
    }

    /// Elastic (given) + kinetic + gravitational energy (J).
    fn total_energy(&self, elastic: f64, x: &[V3], v: &[V3], gravity: &V3) -> f64 {
        elastic + self.kinetic_energy(v) + self.gravity_energy(x, gravity)
    }

    /// The Newton fallback of a linearised step, from the state it started at (rotations
    /// already extracted there), with the statistics of the linearised attempt added.
    fn fallback_step(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
        attempt: &StepStats,
    ) -> Result<StepStats, FemError> {
        let q = StepParams {
            newton: Some(FALLBACK_NEWTON),
            ..*p
        };
        let mut s = self.step_newton(x, v, f_ext, dt, &q, true)?;
        s.rotations_extracted += attempt.rotations_extracted;
        s.polar_iterations += attempt.polar_iterations;
        s.cg_iterations += attempt.cg_iterations;
        s.inverted = attempt.inverted;
        s.max_rotation_change_sq = attempt.max_rotation_change_sq;
        s.fallback = true;
        Ok(s)
    }

    /// The partition, when the step in progress runs on several threads.
    fn active_partition(&self) -> Option<&Partition> {
        self.partition
            .as_ref()
            .filter(|part| self.threads > 1 && part.threads == self.threads)
    }

    /// Whether some element has `det F ≤ 0` at `x`.
    pub fn any_inverted(&self, x: &[V3]) -> bool {
        (0..self.elements.len()).any(|ei| self.element_inverted(ei, x))
    }

    /// Whether element `ei` has `det F ≤ 0` at `x`: rest elements are positively oriented,
    /// so this is the sign of `det D_s = (b − a)·((c − a) × (d − a))`.
    #[inline]
    pub fn element_inverted(&self, ei: usize, x: &[V3]) -> bool {
        let [a, b, c, d] = gather(x, &self.elements[ei].nodes);
        (b - a).dot(&(c - a).cross(&(d - a))) <= 0.0
    }

    /// Rest volume of all elements (m³).
    pub fn rest_volume(&self) -> f64 {
        self.elements.iter().map(|e| e.volume).sum()
    }

    /// Deformed volume Σ det(F_e) V_e (m³).
    pub fn deformed_volume(&self, x: &[V3]) -> f64 {
        self.elements
            .iter()
            .map(|e| (edge_matrix(&gather(x, &e.nodes)) * e.dm_inv).determinant() * e.volume)
            .sum()
    }

    /// Kinetic energy ½ vᵀ M v (J).
    pub fn kinetic_energy(&self, v: &[V3]) -> f64 {
        0.5 * v
            .iter()
            .zip(&self.mass)
            .map(|(vi, m)| m * vi.norm_squared())
            .sum::<f64>()
    }

    /// Gravitational potential −Σ m_i g·x_i (J), zero at the origin.
    pub fn gravity_energy(&self, x: &[V3], gravity: &V3) -> f64 {
        -x.iter()
            .zip(&self.mass)
            .map(|(xi, m)| m * gravity.dot(xi))
            .sum::<f64>()
    }

    fn ensure_dense(&mut self) {
        if self.dense.is_none() {
            let d = (0..self.elements.len())
                .map(|ei| self.k0_matrix(ei, StiffnessMode::Gradient))
                .collect();
            self.dense = Some(d);
        }
    }

    /// Small-strain element stiffness `K_e` (N/m) in the element's rest frame.
    fn k0_matrix(&self, ei: usize, mode: StiffnessMode) -> Mat12 {
        let e = &self.elements[ei];
        let m = &self.materials[e.material];
        match (mode, e.template, &self.dense) {
            (StiffnessMode::Dense, _, Some(d)) => d[ei],
            (StiffnessMode::Template | StiffnessMode::TemplateSparse, Some((_, h)), _) => {
                self.combos[e.combo] * h
            }
            _ => {
                let (kl, km) = k_lambda_mu(&e.grads, e.volume);
                kl * m.lambda + km * m.mu
            }
        }
    }

    /// `K_e u` in the rest frame.
    #[inline]
    fn apply_k0(&self, ei: usize, u: &[V3; 4], mode: StiffnessMode) -> [V3; 4] {
        let e = &self.elements[ei];
        let m = &self.materials[e.material];
        match (mode, e.template, &self.dense) {
            (StiffnessMode::Dense, _, Some(d)) => apply_dense(&d[ei], u),
            (StiffnessMode::Template, Some((_, h)), _) => {
                let y = apply_dense(&self.combos[e.combo], u);
                [y[0] * h, y[1] * h, y[2] * h, y[3] * h]
            }
            (StiffnessMode::TemplateSparse, Some((t, h)), _) => {
                self.templates[t].apply(h, m.lambda, m.mu, u)
            }
            _ => apply_k_gradient(&e.grads, e.volume, m.lambda, m.mu, u),
        }
    }

    fn element_rotation_of(&self, ei: usize, rotations: Option<&[Matrix3<f64>]>) -> Matrix3<f64> {
        let s = self.elements[ei].source;
        match rotations {
            Some(r) => r[s],
            None => self.sources[s].rotation,
        }
    }

    /// Extract rotations at `x` of all sources some element uses, without touching stored
    /// state (unused sources keep their stored rotation).
    pub fn compute_rotations(&self, x: &[V3], polar: &PolarMethod) -> Vec<Matrix3<f64>> {
        self.sources
            .iter()
            .map(|s| {
                if s.users == 0 {
                    return s.rotation;
                }
                let f = edge_matrix(&gather(x, &s.nodes)) * s.dm_inv;
                let warm = WarmStart {
                    rotation: s.valid.then_some(s.rotation),
                    sigma_bounds: None,
                };
                polar.extract(&f, Some(&warm)).rotation
            })
            .collect()
    }

    /// Update stored rotations at `x` of the sources some element uses, skipping sources
    /// whose nodes all moved less than `rest_threshold` (m) since their last extraction
    /// and those already extracted at `x` by [`FemSystem::shared_source_rotation`].
    /// Returns `(extracted, reused, polar iterations, inverted)`, including the shared
    /// extractions requested since the previous call.
    pub fn update_rotations(
        &mut self,
        x: &[V3],
        polar: &PolarMethod,
        rest_threshold: f64,
    ) -> (usize, usize, usize, usize) {
        let mut c = std::mem::take(&mut self.pending);
        let pass = self.pass;
        let visit = |s: &mut Source, c: &mut ExtractCount| {
            if s.fresh {
                s.fresh = false;
            } else if s.users > 0 {
                extract_source(s, x, polar, rest_threshold, pass, c);
                s.fresh = false;
            }
        };
        if self.threads > 1 {
            use rayon::prelude::*;
            let counts = self
                .sources
                .par_iter_mut()
                .with_min_len(64)
                .fold(ExtractCount::default, |mut c, s| {
                    visit(s, &mut c);
                    c
                })
                .reduce(ExtractCount::default, ExtractCount::merge);
            c = c.merge(counts);
        } else {
            for s in &mut self.sources {
                visit(s, &mut c);
            }
        }
        self.pass += 1;
        self.last_pass = c;
        (c.extracted, c.reused, c.iterations, c.inverted)
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
            return (0..self.elements.len()).map(|ei| one(ei).0).sum();
        };
        let scatter = |out: &mut [V3], offset: usize, ei: usize| {
            let (energy, fe) = one(ei);
            for (&k, f) in self.elements[ei].nodes.iter().zip(&fe) {
                out[k - offset] += f;
            }
            energy
        };
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
            _ => (0..self.elements.len()).map(|ei| scatter(out, 0, ei)).sum(),
        }
    }

    /// Elastic energy (J) and internal forces (N) of one element.
    #[inline]
    fn element_force(
        &self,
        ei: usize,
        x: &[V3],
        model: Model,
        mode: StiffnessMode,
        rotations: Option<&[Matrix3<f64>]>,
    ) -> (f64, [V3; 4]) {
        let e = &self.elements[ei];
        let mut energy = 0.0;
        let xe = gather(x, &e.nodes);
        let xr = gather(&self.rest, &e.nodes);
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
                let m = &self.materials[e.material];
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
    fn stvk_tangent(&self, ei: usize, x: &[V3]) -> Mat12 {
        let e = &self.elements[ei];
        let m = &self.materials[e.material];
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
    fn corot_tangent_consistent(&self, ei: usize, x: &[V3], r: &Matrix3<f64>) -> Option<Mat12> {
        let e = &self.elements[ei];
        let m = &self.materials[e.material];
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
    fn rotated_k(&self, ei: usize, r: &Matrix3<f64>, mode: StiffnessMode) -> Mat12 {
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

    fn build_operator<'a>(
        &'a mut self,
        mass_coef: Vec<f64>,
        elem: ElemMats,
        ext_coef: f64,
        mode: StiffnessMode,
        operator: OperatorMode,
    ) -> SysOp<'a> {
        if operator == OperatorMode::Assembled || self.threads > 1 {
            self.refresh_order();
        }
        let buf = std::mem::take(&mut self.block_buf);
        let this: &'a FemSystem = self;
        let mut op = SysOp {
            sys: this,
            mass_coef,
            elem,
            ext_coef,
            mode,
            assembled: None,
        };
        if operator == OperatorMode::Assembled {
            op.assemble(buf);
        }
        op
    }

    /// Brings the block pattern, the assembly order and (on multi-threaded steps) the
    /// partition up to date.
    fn refresh_order(&mut self) {
        if self.pattern.is_none() {
            let conn: Vec<[usize; 4]> = self.elements.iter().map(|e| e.nodes).collect();
            self.pattern = Some(BlockPattern::new(self.rest.len(), &conn));
        }
        if self.by_source_stale {
            self.group_by_source();
        }
    }

    /// Counting sort of the elements by their current rotation source (O(elements +
    /// sources)), the order in which assembly visits them; on multi-threaded steps also
    /// the partition (its element lists follow that order).
    fn group_by_source(&mut self) {
        let mut start = vec![0u32; self.sources.len() + 1];
        for e in &self.elements {
            start[e.source + 1] += 1;
        }
        for s in 0..self.sources.len() {
            start[s + 1] += start[s];
        }
        self.by_source.clear();
        self.by_source.resize(self.elements.len(), 0);
        for (ei, e) in self.elements.iter().enumerate() {
            let slot = &mut start[e.source];
            self.by_source[*slot as usize] = ei as u32;
            *slot += 1;
        }
        self.by_source_stale = false;
        // A partition's element lists follow this order: rebuild it, or drop it when the
        // step is single-threaded (the next multi-threaded step rebuilds it).
        self.partition = None;
        if self.threads > 1
            && let Some(pat) = &self.pattern
        {
            let elements = &self.elements;
            let mut part =
                Partition::new(self.threads, &pat.upper_row_work(), &self.by_source, |e| {
                    elements[e].nodes
                });
            part.set_spill_ends(pat);
            self.partition = Some(part);
        }
    }

    /// Deformation gradient `F = D_s D_m⁻¹` of element `ei` at `x`.
    pub fn deformation_gradient(&self, ei: usize, x: &[V3]) -> Matrix3<f64> {
        let e = &self.elements[ei];
        edge_matrix(&gather(x, &e.nodes)) * e.dm_inv
    }

    /// Node ids of element `ei`.
    pub fn element_nodes(&self, ei: usize) -> [usize; 4] {
        self.elements[ei].nodes
    }

    /// `K_T(x) p` (N) with the Newton tangent of the model (StVK: consistent; co-rotational:
    /// consistent for elements owning their rotation — stored rotations must be those of
    /// `x`, see [`FemSystem::update_rotations`] — else `R K Rᵀ`; linear: `K`), without
    /// Dirichlet projection.
    pub fn apply_tangent(&self, x: &[V3], model: Model, mode: StiffnessMode, p: &[V3]) -> Vec<V3> {
        let mut out = vec![V3::zeros(); self.rest.len()];
        for ei in 0..self.elements.len() {
            let e = &self.elements[ei];
            let pe = gather(p, &e.nodes);
            let y = match model {
                Model::StVK => apply_dense(&self.stvk_tangent(ei, x), &pe),
                Model::Linear => self.apply_k0(ei, &pe, mode),
                Model::Corotational => {
                    let src = &self.sources[e.source];
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
        let mut f = vec![V3::zeros(); self.rest.len()];
        self.elastic(x, model, mode, Some(&rots), Some(&mut f));
        f
    }

    /// Dynamic step (see [`StepParams::newton`] for which integrator).
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
        let pool = match &self.pool {
            Some(pool) if pool.current_num_threads() == p.threads => pool.clone(),
            _ => {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(p.threads)
                    .thread_name(|i| format!("cosurg-fem-{i}"))
                    .build()
                    .map_err(|e| {
                        FemError::BadParameter(format!("{} FEM threads: {e}", p.threads))
                    })?;
                let pool = std::sync::Arc::new(pool);
                self.pool = Some(pool.clone());
                pool
            }
        };
        if self.partition.as_ref().map(|q| q.threads) != Some(p.threads) {
            self.by_source_stale = true;
        }
        self.threads = p.threads;
        // The whole step runs inside the pool so that each fork is a cheap work-steal.
        let result = pool.install(|| self.step_on_this_thread(x, v, f_ext, dt, p));
        self.threads = 1;
        result
    }

    fn step_on_this_thread(
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
        if p.newton.is_some() || p.model == Model::StVK {
            return self.step_newton(x, v, f_ext, dt, p, false);
        }
        let n = self.rest.len();
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
            stats.max_rotation_change_sq = self.last_pass.max_change_sq;
            if p.fallback_angle_deg > 0.0
                && stats.max_rotation_change_sq
                    > crate::polar::rotation_threshold_sq(p.fallback_angle_deg.to_radians())
            {
                return self.fallback_step(x, v, f_ext, dt, p, &stats);
            }
        }
        if self.threads > 1 {
            // The parallel force loop needs the partition.
            self.refresh_order();
        }
        let mut fint = vec![V3::zeros(); n];
        let elastic_n = self.elastic(x, p.model, p.stiffness, None, Some(&mut fint));
        // Energy guard: only where rotations can jump (elements inverted before or after
        // the step, checked below), no boundary moves and no contact springs act (their
        // work and stored energy are not known here; a tool is an energy source anyway).
        let guard = (p.energy_guard
            && p.model == Model::Corotational
            && self.k_ext.is_empty()
            && !self
                .fixed
                .iter()
                .zip(v.iter())
                .any(|(f, vi)| *f && *vi != V3::zeros()))
        .then(|| {
            let energy = self.total_energy(elastic_n, x, v, &p.gravity);
            let scale = elastic_n + self.kinetic_energy(v);
            (x.to_vec(), v.to_vec(), energy, scale)
        });
        let (mass_coef, coef) = self.linearised_coefficients(dt);
        let warm = std::mem::take(&mut self.warm_dv);
        let (mass, mass_damping) = (self.mass.clone(), self.mass_damping.clone());
        let fixed = self.fixed.clone();
        let op = self.build_operator(
            mass_coef.clone(),
            ElemMats::Rotated {
                coef,
                rotated: p.model == Model::Corotational,
            },
            dt * dt,
            p.stiffness,
            p.operator,
        );
        let mut av = vec![V3::zeros(); n];
        op.apply(v, &mut av);
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
        let res: CgResult = pcg(&op, &fixed, &rhs, &mut dv, &p.solver);
        self.block_buf = op.into_blocks();
        stats.cg_iterations = res.iterations;
        stats.cg_residual = res.relative_residual;
        for i in 0..n {
            if !fixed[i] {
                v[i] += dv[i];
            }
            x[i] += v[i] * dt;
        }
        if !x.iter().all(|p| p.iter().all(|c| c.is_finite())) {
            return Err(FemError::NonFinite);
        }
        self.warm_dv = dv;
        if let Some((x0, v0, energy_n, scale)) = guard
            && (stats.inverted > 0 || self.any_inverted(&x0) || self.any_inverted(x))
        {
            // Energy at x_{n+1} with its own rotations (stored state untouched).
            let rotations = self.compute_rotations(x, &p.polar);
            let elastic = self.elastic(x, p.model, p.stiffness, Some(&rotations), None);
            let energy = self.total_energy(elastic, x, v, &p.gravity);
            let work: f64 = (0..n)
                .filter(|&i| !fixed[i])
                .map(|i| f_ext[i].dot(&(x[i] - x0[i])))
                .sum();
            // Round-off allowance: 1e-6 of the elastic + kinetic energy.
            if energy > energy_n + work + 1e-6 * scale + 1e-12 {
                tracing::debug!(
                    gained_j = energy - energy_n - work,
                    inverted = stats.inverted,
                    "linearised step created energy; redone with Newton"
                );
                x.copy_from_slice(&x0);
                v.copy_from_slice(&v0);
                // The rejected step's Δv is no guess for the next one.
                self.warm_dv = vec![V3::zeros(); n];
                let mut s = self.fallback_step(x, v, f_ext, dt, p, &stats)?;
                s.energy_guard = true;
                return Ok(s);
            }
        }
        Ok(stats)
    }

    fn check_sizes(&self, x: &[V3], v: Option<&[V3]>, f: &[V3]) -> Result<(), FemError> {
        let n = self.rest.len();
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

    /// Tangent element matrices for Newton at `x`: StVK consistent; co-rotational consistent
    /// (incl. the derivative of R) for elements owning their rotation, `R K Rᵀ` for
    /// elements sharing a source; linear `K`.
    fn tangent_mats(&self, x: &[V3], model: Model, mode: StiffnessMode) -> Vec<Mat12> {
        (0..self.elements.len())
            .map(|ei| match model {
                Model::StVK => self.stvk_tangent(ei, x),
                Model::Linear => self.rotated_k(ei, &Matrix3::identity(), mode),
                Model::Corotational => {
                    let e = &self.elements[ei];
                    let src = &self.sources[e.source];
                    let own = e.source == e.own_source;
                    own.then(|| self.corot_tangent_consistent(ei, x, &src.rotation))
                        .flatten()
                        .unwrap_or_else(|| self.rotated_k(ei, &src.rotation, mode))
                }
            })
            .collect()
    }

    /// Backward Euler with Newton iterations on the incremental potential (scaled by dt²)
    /// `Φ(x) = ½‖x − x̂‖²_M + ½ dt ‖x − x_n‖²_{D_n} + dt² [W(x) − (f_ext + M g)ᵀx
    /// + ½‖x − x_n‖²_{K_c}]`, `x̂ = x_n + dt v_n`, `D_n = C + Σ β_e R_e K_e R_eᵀ` frozen at
    /// `x_n`; backtracking (Armijo) line search on Φ, CG truncated at negative curvature.
    ///
    /// `rotations_current`: the stored rotations are already those at `x` (the fallbacks of
    /// the linearised step extracted them); extracting again would count every source as
    /// reused and hide the rotation change from the next step's fallback test.
    fn step_newton(
        &mut self,
        x: &mut [V3],
        v: &mut [V3],
        f_ext: &[V3],
        dt: f64,
        p: &StepParams,
        rotations_current: bool,
    ) -> Result<StepStats, FemError> {
        let n = self.rest.len();
        let np = p.newton.unwrap_or(NewtonParams {
            max_iters: 1,
            tol: 0.0,
        });
        let mut stats = StepStats::default();
        // Rotations enter the co-rotational model and the Rayleigh β damping; the StVK
        // reference without β needs none (a polar decomposition per element and line-search
        // trial would dominate its cost).
        let corot = p.model == Model::Corotational;
        let need_rotations = corot || self.materials.iter().any(|m| m.beta != 0.0);
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
        let damp: Vec<Mat12> = (0..self.elements.len())
            .map(|ei| {
                let beta = self.materials[self.elements[ei].material].beta;
                if beta == 0.0 {
                    Mat12::zeros()
                } else {
                    let r = self.sources[self.elements[ei].source].rotation;
                    self.rotated_k(ei, &r, p.stiffness) * (dt * beta)
                }
            })
            .collect();
        let mass_coef: Vec<f64> = (0..n)
            .map(|i| self.mass[i] + dt * self.mass_damping[i])
            .collect();
        let load: Vec<V3> = (0..n)
            .map(|i| f_ext[i] + p.gravity * self.mass[i])
            .collect();
        x.copy_from_slice(&x_hat);
        let fixed = self.fixed.clone();
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
                val += 0.5 * sys.mass[i] * dh.norm_squared()
                    + 0.5 * dt * sys.mass_damping[i] * d[i].norm_squared()
                    - dt2 * load[i].dot(&x[i]);
                g[i] = dh * sys.mass[i] + d[i] * (dt * sys.mass_damping[i])
                    - (fint[i] + load[i]) * dt2;
            }
            for (ei, e) in sys.elements.iter().enumerate() {
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
                for (s, r) in self.sources.iter_mut().zip(&rots) {
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
            self.block_buf = op.into_blocks();
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
        let n = self.rest.len();
        let load: Vec<V3> = (0..n)
            .map(|i| f_ext[i] + p.gravity * self.mass[i])
            .collect();
        let fixed = self.fixed.clone();
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
                val -= s * load[i].dot(&(x[i] - sys.rest[i]));
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
                    for (src, rr) in self.sources.iter_mut().zip(&rots) {
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
                self.block_buf = op.into_blocks();
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

/// Extract (or, at rest, reuse) one source's rotation at `x` and mark it fresh.
fn extract_source(
    s: &mut Source,
    x: &[V3],
    polar: &PolarMethod,
    rest_threshold: f64,
    pass: u64,
    c: &mut ExtractCount,
) {
    let xs = gather(x, &s.nodes);
    s.fresh = true;
    let thr2 = rest_threshold * rest_threshold;
    if s.valid
        && rest_threshold > 0.0
        && xs
            .iter()
            .zip(&s.x_last)
            .all(|(a, b)| (a - b).norm_squared() < thr2)
    {
        c.reused += 1;
        return;
    }
    let f = edge_matrix(&xs) * s.dm_inv;
    let warm = WarmStart {
        rotation: s.valid.then_some(s.rotation),
        sigma_bounds: if s.valid { s.sigma } else { None },
    };
    let r = polar.extract(&f, Some(&warm));
    // Rotation change per step; a source not extracted in the previous pass (e.g. one
    // that was shared) has no meaningful previous rotation.
    if s.valid && s.pass + 1 >= pass {
        c.max_change_sq = c
            .max_change_sq
            .max((r.rotation - s.rotation).norm_squared());
    }
    s.pass = pass;
    s.rotation = r.rotation;
    s.sigma = Some(r.sigma_bounds);
    s.x_last = xs;
    s.valid = true;
    c.extracted += 1;
    c.iterations += r.iterations as usize;
    c.inverted += r.inverted as usize;
}

/// Armijo backtracking along `dx` from `x` (updated in place). If `dx` is not a descent
/// direction, the negative gradient is used. Returns the new (value, aux, gradient).
fn line_search<A>(
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

/// The operator `A p = diag(mass_coef) p + Σ_e (element matrix) p_e + ext_coef K_c p`.
struct SysOp<'a> {
    sys: &'a FemSystem,
    mass_coef: Vec<f64>,
    elem: ElemMats,
    ext_coef: f64,
    mode: StiffnessMode,
    assembled: Option<Vec<Matrix3<f64>>>,
}

/// Smallest mesh (nodes) whose sparse products are split over threads: on 2 cores the
/// coarse cantilever beam (425 nodes, about 4 µs per product) stepped 25 % slower with
/// a split product at dt = 10 ms (50 CG iterations), the 12,288-tet one (2,673 nodes)
/// 1.5× faster (`examples/step_cost.rs`).
const PARALLEL_PRODUCT_MIN_NODES: usize = 1000;

/// The 16 3×3 blocks (index `4a + b`) of `R K Rᵀ` for a symmetric 12×12 `K` (`r = None`:
/// `K` itself). Only the 10 blocks with `a ≤ b` are rotated; the others are their
/// transposes.
fn rotated_blocks(k: &Mat12, r: Option<&Matrix3<f64>>) -> [Matrix3<f64>; 16] {
    let mut out = [Matrix3::zeros(); 16];
    for a in 0..4 {
        for b in a..4 {
            let kab: Matrix3<f64> = k.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
            let blk = match r {
                Some(r) => r * kab * r.transpose(),
                None => kab,
            };
            out[4 * a + b] = blk;
            if a != b {
                out[4 * b + a] = blk.transpose();
            }
        }
    }
    out
}

/// The 16 blocks of `R K Rᵀ` of an isotropic linear tet straight from its shape-function
/// gradients `g` (1/m) and volume `v` (m³): `K_ab = v [λ g_a g_bᵀ + μ g_b g_aᵀ + μ (g_a·g_b)
/// I]`, so with `r_a = R g_a` a rotated block is `v [λ r_a r_bᵀ + μ r_b r_aᵀ + μ (g_a·g_b)
/// I]` — about a third of the flops of rotating each block of `K`.
fn rotated_iso_blocks(
    g: &[V3; 4],
    v: f64,
    lambda: f64,
    mu: f64,
    r: Option<&Matrix3<f64>>,
    out: &mut [Matrix3<f64>; 16],
) {
    let rg = match r {
        Some(r) => [r * g[0], r * g[1], r * g[2], r * g[3]],
        None => *g,
    };
    for a in 0..4 {
        for b in a..4 {
            let mut blk =
                rg[a] * rg[b].transpose() * (v * lambda) + rg[b] * rg[a].transpose() * (v * mu);
            let d = v * mu * g[a].dot(&g[b]);
            blk[(0, 0)] += d;
            blk[(1, 1)] += d;
            blk[(2, 2)] += d;
            out[4 * a + b] = blk;
            if a != b {
                out[4 * b + a] = blk.transpose();
            }
        }
    }
}

/// `blocks[slots[i]] += c · local[i]` for the blocks of one element whose bit is set in
/// `mask` (all 16, or those on and above the diagonal for symmetric storage).
#[inline]
fn scatter_blocks(
    blocks: &mut [Matrix3<f64>],
    slots: &[usize; 16],
    mask: u16,
    local: &[Matrix3<f64>; 16],
    c: f64,
) {
    for (i, (s, l)) in slots.iter().zip(local).enumerate() {
        if mask & (1 << i) != 0 {
            blocks[*s] += l * c;
        }
    }
}

impl SysOp<'_> {
    /// Hands back the assembled block storage (for reuse by the next step).
    fn into_blocks(self) -> Vec<Matrix3<f64>> {
        self.assembled.unwrap_or_default()
    }

    /// Adds `coef_e · R_e K_e R_eᵀ` (upper blocks) of `elements` (grouped by rotation
    /// source) into `blocks`, which holds the pattern's blocks from index `offset` on.
    /// With template stiffness `R C Rᵀ` is formed once per (source, template-material
    /// combination) and shared by every element of the group, scaled by its size `h`: with
    /// rotation sharing most elements then cost a scaled scatter only (the point of
    /// combining sharing with templates).
    fn add_rotated(
        &self,
        elements: &[u32],
        blocks: &mut [Matrix3<f64>],
        offset: usize,
        coef: &[f64],
        rotated: bool,
    ) {
        let sys = self.sys;
        let pat = sys.pattern.as_ref().expect("pattern built");
        let templated = matches!(
            self.mode,
            StiffnessMode::Template | StiffnessMode::TemplateSparse
        );
        // Per group: the combos seen and `R C Rᵀ` of each (C = template stiffness at unit
        // size: the element's own blocks over its size h). Few per group.
        const CACHE: usize = 8;
        let mut cache_combo = [usize::MAX; CACHE];
        let mut cache = [[Matrix3::zeros(); 16]; CACHE];
        let mut cached = 0;
        let mut group = usize::MAX;
        let mut local = [Matrix3::zeros(); 16];
        let mut slots = [0usize; 16];
        for &ei in elements {
            let ei = ei as usize;
            let e = &sys.elements[ei];
            for (s, abs) in slots.iter_mut().zip(pat.element_slots(ei)) {
                *s = abs - offset;
            }
            // `R K Rᵀ` is symmetric: store the upper triangle only.
            let upper = pat.element_upper(ei);
            let r = rotated.then(|| &sys.sources[e.source].rotation);
            let m = &sys.materials[e.material];
            match (templated, e.template, self.mode) {
                (true, Some((_, h)), _) => {
                    // Unrotated: one group for all elements.
                    let key = if rotated { e.source } else { 0 };
                    if key != group {
                        cached = 0;
                        group = key;
                    }
                    let hit = cache_combo[..cached].iter().position(|c| *c == e.combo);
                    let i = match hit {
                        Some(i) => i,
                        None => {
                            // A full cache (rare) recycles its last entry.
                            let i = cached.min(CACHE - 1);
                            cached = (cached + 1).min(CACHE);
                            cache_combo[i] = e.combo;
                            let v = e.volume / h;
                            rotated_iso_blocks(&e.grads, v, m.lambda, m.mu, r, &mut cache[i]);
                            i
                        }
                    };
                    scatter_blocks(blocks, &slots, upper, &cache[i], coef[ei] * h);
                }
                (_, _, StiffnessMode::Dense) => {
                    let k0 = sys.k0_matrix(ei, self.mode);
                    let k = rotated_blocks(&k0, r);
                    scatter_blocks(blocks, &slots, upper, &k, coef[ei]);
                }
                _ => {
                    rotated_iso_blocks(&e.grads, e.volume, m.lambda, m.mu, r, &mut local);
                    scatter_blocks(blocks, &slots, upper, &local, coef[ei]);
                }
            }
        }
    }

    /// Assembles `A` into `blocks` (reused storage): element blocks (on the parts of a
    /// multi-threaded step in parallel, then the interface), mass and external stiffness.
    fn assemble(&mut self, mut blocks: Vec<Matrix3<f64>>) {
        let sys = self.sys;
        let pat = sys.pattern.as_ref().expect("pattern built");
        blocks.clear();
        blocks.resize(pat.num_blocks(), Matrix3::zeros());
        match &self.elem {
            ElemMats::Dense(m) => {
                // Newton tangents (possibly unsymmetric): every block as given.
                for (ei, k) in m.iter().enumerate() {
                    let slots = pat.element_slots(ei);
                    for a in 0..4 {
                        for b in 0..4 {
                            blocks[slots[4 * a + b]] += k.fixed_view::<3, 3>(3 * a, 3 * b);
                        }
                    }
                }
            }
            ElemMats::Rotated { coef, rotated } => match sys.active_partition() {
                Some(part) => {
                    use rayon::prelude::*;
                    // A part's elements only touch its nodes' rows: a contiguous block range.
                    let bounds: Vec<usize> = part
                        .node_start
                        .iter()
                        .map(|&s| pat.row_block_range(s, s).0)
                        .collect();
                    split_ranges(&mut blocks, &bounds)
                        .into_par_iter()
                        .zip(part.elements.par_iter())
                        .zip(bounds.par_iter())
                        .for_each(|((b, els), &offset)| {
                            self.add_rotated(els, b, offset, coef, *rotated)
                        });
                    self.add_rotated(&part.interface, &mut blocks, 0, coef, *rotated);
                }
                _ => self.add_rotated(&sys.by_source, &mut blocks, 0, coef, *rotated),
            },
        }
        for (i, d) in pat.diagonal_slots().iter().enumerate() {
            blocks[*d] += Matrix3::identity() * self.mass_coef[i];
        }
        for (k, blk) in &self.sys.k_ext {
            blocks[pat.diagonal_slots()[*k]] += blk * self.ext_coef;
        }
        self.assembled = Some(blocks);
    }
}

impl LinearOperator for SysOp<'_> {
    fn apply(&self, p: &[V3], out: &mut [V3]) {
        if let Some(blocks) = &self.assembled {
            let pat = self.sys.pattern.as_ref().expect("pattern");
            match (&self.elem, self.sys.active_partition()) {
                // Below PARALLEL_PRODUCT_MIN_NODES a product is a few µs of work, less than
                // forking and joining costs: one thread does it.
                (ElemMats::Rotated { .. }, Some(part))
                    if out.len() >= PARALLEL_PRODUCT_MIN_NODES =>
                {
                    multiply_upper_parts(pat, blocks, p, out, part)
                }
                (ElemMats::Rotated { .. }, _) => pat.multiply_upper(blocks, p, out),
                (ElemMats::Dense(_), _) => pat.multiply(blocks, p, out),
            }
            return;
        }
        for (i, o) in out.iter_mut().enumerate() {
            *o = p[i] * self.mass_coef[i];
        }
        match &self.elem {
            ElemMats::Dense(m) => {
                for (ei, e) in self.sys.elements.iter().enumerate() {
                    let y = apply_dense(&m[ei], &gather(p, &e.nodes));
                    for a in 0..4 {
                        out[e.nodes[a]] += y[a];
                    }
                }
            }
            ElemMats::Rotated { coef, rotated } => {
                for (ei, e) in self.sys.elements.iter().enumerate() {
                    let pe = gather(p, &e.nodes);
                    if *rotated {
                        let r = self.sys.sources[e.source].rotation;
                        let rt = r.transpose();
                        let u = [rt * pe[0], rt * pe[1], rt * pe[2], rt * pe[3]];
                        let y = self.sys.apply_k0(ei, &u, self.mode);
                        let c = coef[ei];
                        for a in 0..4 {
                            out[e.nodes[a]] += r * y[a] * c;
                        }
                    } else {
                        let y = self.sys.apply_k0(ei, &pe, self.mode);
                        for a in 0..4 {
                            out[e.nodes[a]] += y[a] * coef[ei];
                        }
                    }
                }
            }
        }
        for (k, blk) in &self.sys.k_ext {
            out[*k] += blk * p[*k] * self.ext_coef;
        }
    }

    fn diagonal(&self) -> Vec<V3> {
        if let Some(blocks) = &self.assembled {
            let pat = self.sys.pattern.as_ref().expect("pattern");
            return pat
                .diagonal_slots()
                .iter()
                .map(|&d| blocks[d].diagonal())
                .collect();
        }
        let mut d: Vec<V3> = self.mass_coef.iter().map(|m| V3::repeat(*m)).collect();
        for ei in 0..self.sys.elements.len() {
            let e = &self.sys.elements[ei];
            match &self.elem {
                ElemMats::Dense(m) => {
                    for a in 0..4 {
                        for c in 0..3 {
                            d[e.nodes[a]][c] += m[ei][(3 * a + c, 3 * a + c)];
                        }
                    }
                }
                ElemMats::Rotated { coef, rotated } => {
                    // diag(R K_aa Rᵀ) from the 3×3 diagonal blocks of K (cheap: from the
                    // gradients, K_aa = V[λ g gᵀ + μ(|g|² I + g gᵀ)]).
                    let m = &self.sys.materials[e.material];
                    let r = if *rotated {
                        self.sys.sources[e.source].rotation
                    } else {
                        Matrix3::identity()
                    };
                    for a in 0..4 {
                        let g = e.grads[a];
                        let kaa = (g * g.transpose() * (m.lambda + m.mu)
                            + Matrix3::identity() * (m.mu * g.norm_squared()))
                            * e.volume;
                        let rk = r * kaa * r.transpose();
                        d[e.nodes[a]] += rk.diagonal() * coef[ei];
                    }
                }
            }
        }
        for (k, blk) in &self.sys.k_ext {
            d[*k] += blk.diagonal() * self.ext_coef;
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, SMatrix};

    /// Element stiffness the textbook way, `V Bᵀ D B` with Voigt strains (independent of
    /// the gradient formula under test).
    fn voigt_stiffness(g: &[V3; 4], v: f64, lambda: f64, mu: f64) -> Mat12 {
        let mut b = SMatrix::<f64, 6, 12>::zeros();
        for (a, ga) in g.iter().enumerate() {
            let (x, y, z) = (ga.x, ga.y, ga.z);
            let c = 3 * a;
            b[(0, c)] = x;
            b[(1, c + 1)] = y;
            b[(2, c + 2)] = z;
            b[(3, c)] = y;
            b[(3, c + 1)] = x;
            b[(4, c + 1)] = z;
            b[(4, c + 2)] = y;
            b[(5, c)] = z;
            b[(5, c + 2)] = x;
        }
        let mut d = SMatrix::<f64, 6, 6>::zeros();
        for i in 0..3 {
            for j in 0..3 {
                d[(i, j)] = lambda;
            }
            d[(i, i)] += 2.0 * mu;
            d[(i + 3, i + 3)] = mu;
        }
        b.transpose() * d * b * v
    }

    #[test]
    fn rotated_gradient_blocks_match_rotated_voigt_stiffness() {
        let x = [
            V3::new(0.0, 0.0, 0.0),
            V3::new(0.031, 0.002, -0.004),
            V3::new(0.003, 0.027, 0.001),
            V3::new(-0.002, 0.004, 0.022),
        ];
        let geom = TetGeometry::new(&x).unwrap();
        let (lambda, mu) = lame(1e5, 0.45);
        let k = voigt_stiffness(&geom.grads, geom.volume, lambda, mu);
        let r = *Rotation3::from_scaled_axis(V3::new(0.7, -1.1, 0.4)).matrix();
        let mut big_r = Mat12::zeros();
        for a in 0..4 {
            big_r.fixed_view_mut::<3, 3>(3 * a, 3 * a).copy_from(&r);
        }
        let expect = big_r * k * big_r.transpose();
        let mut got = [Matrix3::zeros(); 16];
        rotated_iso_blocks(&geom.grads, geom.volume, lambda, mu, Some(&r), &mut got);
        let via_blocks = rotated_blocks(&k, Some(&r));
        let scale = expect.amax();
        for a in 0..4 {
            for b in 0..4 {
                let e = expect.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
                assert!(
                    (got[4 * a + b] - e).amax() < 1e-12 * scale,
                    "iso block ({a},{b})"
                );
                assert!(
                    (via_blocks[4 * a + b] - e).amax() < 1e-12 * scale,
                    "block ({a},{b})"
                );
            }
        }
    }
}
