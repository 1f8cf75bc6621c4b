use sim_fem::FemError;
use sim_lattice::LatticeError;
use sim_scene::SceneError;

/// Errors of building or stepping a [`crate::Simulation`].
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The scene is invalid (names the file, the key and the problem).
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The lattice could not be built or changed.
    #[error("lattice: {0}")]
    Lattice(#[from] LatticeError),
    /// The finite-element system rejected its input or diverged.
    #[error("finite elements: {0}")]
    Fem(#[from] FemError),
    /// A body of the scene cannot be simulated as written.
    #[error("{file}: body[{index}] ({name}): {problem}")]
    Body {
        file: String,
        index: usize,
        name: String,
        problem: String,
    },
    /// The state stopped being finite; the step was rolled back.
    #[error("simulation state became non-finite at t = {time} s; step rolled back")]
    NonFinite { time: f64 },
    /// A topology operation (a cut) is malformed.
    #[error("topology operation rejected: {0}")]
    Topology(String),
}
