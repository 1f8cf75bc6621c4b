//! Parameters of a dynamic step ([`crate::FemSystem::step`]): one struct, [`StepParams`],
//! with the model, the stiffness kernel and CG operator, the CG budget, gravity, the
//! rotation extractor and its rest skip, Newton control, the robust fallbacks and threads.
//! Callers (sim-core's `SimOptions`) embed it rather than copy its fields.

use super::V3;
use crate::model::Model;
use crate::polar::PolarMethod;
use crate::solver::SolverParams;

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

/// The linear solver of the linearised step (scene key `simulation.solver`, `--solver`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LinearSolver {
    /// CG with the Jacobi (diagonal) preconditioner.
    #[default]
    JacobiPcg,
    /// CG preconditioned by a geometric multigrid V-cycle over the hierarchy given with
    /// [`crate::FemSystem::set_multigrid_hierarchy`] (Jacobi-PCG while none is set). Uses
    /// the assembled operator whatever [`StepParams::operator`] says.
    MgPcg,
    /// Sparse Cholesky of the assembled matrix on the free nodes ([`crate::direct`]):
    /// exact up to round-off, whatever the iteration budget says. The symbolic analysis is
    /// kept until the pattern or the fixed nodes change; the numeric factorisation runs
    /// every step. Newton and static solves (tangents that may be indefinite) stay on CG.
    Direct,
    /// Chosen on the first solve, which runs Jacobi-PCG: MG-PCG from then on if that solve
    /// needed more than [`crate::AUTO_MG_ABOVE_JACOBI_ITERATIONS`] iterations to the
    /// tolerance and the system has more than [`crate::AUTO_MG_MIN_FREE_NODES`] free
    /// nodes, else Jacobi-PCG: the crossover
    /// measured in `cosurg bench scale` (docs/RESULTS.md, "Choosing the solver"). Chosen
    /// once, so that sites starting from the same state with the same CG budget choose
    /// alike (a site that joins late decides on the state it joins at, and a budget that
    /// stops the first solve makes the estimate an extrapolation: near the crossover two
    /// such sites can choose differently; MG-PCG's smoother also depends on the thread
    /// count). [`StepStats::solver`](crate::StepStats) says which solver a step used.
    Auto,
}

impl LinearSolver {
    /// Every concrete solver (`jacobi-pcg`, `mg-pcg`, `direct`; not [`LinearSolver::Auto`],
    /// which picks one of the first two).
    pub const ALL: [LinearSolver; 3] = [
        LinearSolver::JacobiPcg,
        LinearSolver::MgPcg,
        LinearSolver::Direct,
    ];

    /// The name used in scenes and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LinearSolver::JacobiPcg => "jacobi-pcg",
            LinearSolver::MgPcg => "mg-pcg",
            LinearSolver::Direct => "direct",
            LinearSolver::Auto => "auto",
        }
    }
}

/// An unknown linear solver name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown linear solver {0:?} (expected jacobi-pcg, mg-pcg, direct or auto)")]
pub struct UnknownLinearSolver(pub String);

impl std::str::FromStr for LinearSolver {
    type Err = UnknownLinearSolver;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .chain([LinearSolver::Auto])
            .find(|l| l.name() == s)
            .ok_or_else(|| UnknownLinearSolver(s.to_string()))
    }
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
    /// Preconditioner of CG in the linearised step.
    pub linear_solver: LinearSolver,
    /// With [`LinearSolver::MgPcg`]: rebuild the coarse operators (Galerkin `Pᵀ A P`)
    /// every this many steps (and whenever dt or the fixed nodes change); in between the
    /// V-cycle uses the previous coarse operators with the current fine matrix (0 = 1).
    pub mg_refresh_steps: usize,
    /// With [`LinearSolver::MgPcg`]: block Gauss–Seidel sweeps before (forward) and after
    /// (backward) the coarse correction on every level (0 = 1).
    pub mg_sweeps: usize,
    /// Gravity (m/s²).
    pub gravity: V3,
    /// Rotation extractor.
    pub polar: PolarMethod,
    /// Reuse a source's rotation if none of its nodes moved more than this since the last
    /// extraction (m); 0 disables the skip.
    pub rest_threshold: f64,
    /// Newton iterations of the StVK step (backward Euler with Newton on the incremental
    /// potential). Linear and co-rotational steps are linearised (one linear solve) and
    /// ignore this; their robust fallback uses [`FALLBACK_NEWTON`]. Default: 1 iteration.
    pub newton: NewtonParams,
    /// Robust fallback of the linearised co-rotational step (degrees; 0 = off): when a
    /// rotation source turned by more than this angle since the previous step (fast spin,
    /// or the flip of an inverted element's least-stretch direction), the linearisation
    /// about `x_n` with R frozen is not to be trusted (it can pump energy), and the step is taken
    /// as backward Euler with [`FALLBACK_NEWTON`] iterations (consistent tangent, line
    /// search on the incremental potential) instead. See [`StepStats::fallback`](crate::StepStats::fallback).
    pub fallback_angle_deg: f64,
    /// Threads for the linearised step (1 = the calling thread only). With more, rotation
    /// extraction, element forces, the assembly and the sparse products of the assembled
    /// co-rotational/linear operator run on a pool of that many threads (see
    /// `parallel.rs`), with MG-PCG also its finest level's sweeps, and the energy guard's
    /// check for inverted elements; Newton steps, the matrix-free operator and the energy
    /// guard's energies stay sequential. Results equal the sequential ones up to the order
    /// of floating-point sums (and, with MG-PCG, the iterations of a split smoother).
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
            linear_solver: LinearSolver::JacobiPcg,
            mg_refresh_steps: 4,
            mg_sweeps: 1,
            gravity: V3::new(0.0, 0.0, -9.81),
            polar: PolarMethod::default(),
            rest_threshold: 0.0,
            newton: NewtonParams {
                max_iters: 1,
                tol: 0.0,
            },
            fallback_angle_deg: 0.0,
            threads: 1,
            energy_guard: false,
        }
    }
}
