//! # cosurg-sim-fem
//!
//! Mesh-agnostic finite elements for real-time soft tissue: rotation extraction (polar
//! decomposition), linear tetrahedra with a template stiffness table, linear /
//! co-rotational / St Venant–Kirchhoff models, linearised and Newton backward Euler,
//! Jacobi-PCG (matrix-free or block-CSR), and a static Newton solver with load stepping.
//!
//! The caller (sim-core) passes plain arrays: node rest positions, tets (4 node ids,
//! positively oriented), optional shape keys + scale, materials, rotation sources and a
//! fixed-node mask — see [`FemDesc`]. SI units throughout (m, s, kg, N, Pa).

pub mod direct;
pub mod element;
mod lanes;
pub mod mesh;
pub mod mg;
pub mod model;
mod parallel;
pub mod polar;
mod prefetch;
pub mod solver;
pub mod system;

pub use element::{Mat12, Template, TetGeometry, lame};
pub use model::{Model, UnknownModel};
pub use polar::{
    ByersXu, MullerIterative, PolarMethod, PolarResult, RotationExtractor, ShapeMatching, SvdPolar,
    WarmStart, rotation_threshold_sq, rotations_within,
};
pub use solver::{CgResult, SolverParams};
pub use system::{
    AUTO_MG_ABOVE_JACOBI_ITERATIONS, AUTO_MG_MIN_FREE_NODES, ElementDesc, FALLBACK_NEWTON, FemDesc,
    FemSystem, LinearSolver, Material, NewtonParams, OperatorMode, RotationSourceDesc, ShapeRef,
    StaticParams, StaticStats, StepParams, StepStats, StiffnessMode, TemplateInfo,
    UnknownLinearSolver,
};

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum FemError {
    /// An array has the wrong length.
    #[error("{what}: expected length {expected}, got {got}")]
    Size {
        /// Which array.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// An element is invalid.
    #[error("element {element}: {reason}")]
    BadElement {
        /// Element index (usize::MAX when not known).
        element: usize,
        /// What is wrong.
        reason: String,
    },
    /// A rotation source is invalid.
    #[error("rotation source {index}: {reason}")]
    BadSource {
        /// Source index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// A material is invalid.
    #[error("material {material}: {reason}")]
    BadMaterial {
        /// Material index.
        material: usize,
        /// What is wrong.
        reason: String,
    },
    /// A parameter is out of range.
    #[error("bad parameter: {0}")]
    BadParameter(String),
    /// The state became non-finite.
    #[error("non-finite state after step")]
    NonFinite,
    /// The sparse direct solver failed (e.g. a matrix not positive definite).
    #[error("direct solver: {0}")]
    Solver(String),
}
