//! Scene description and file I/O for cosurg.
//!
//! * [`scene`]: the scene TOML format (documented in `SCENE_FORMAT.md`), its serde types,
//!   validation ([`Scene::validate`], [`Scene::validate_selection`]), loading with every
//!   referenced mesh and script ([`Scene::load`]) and the [`scene_hash`].
//! * [`mesh`]: [`TriMesh`] with OBJ/STL/PLY loading, OBJ writing and geometric checks.
//! * [`vtk`]: VTU / PVD / OBJ output writers.
//! * [`surf`]: the `.surf` surface-recording file format (reader and writer).
//! * [`script`]: timed tool poses (teaching mode, scripted runs) with interpolation.
//! * [`builtin`]: the shipped scenes (`cantilever`, `cholecystectomy`), embedded in the
//!   binary, and the generator of their organ meshes and tool scripts.
//!
//! ```
//! use cosurg_sim_scene::{builtin, BodyShape};
//! let loaded = builtin::cholecystectomy();
//! let organ = &loaded.scene.bodies[0];
//! assert!(matches!(organ.shape(), BodyShape::Mesh(_)));
//! assert!(loaded.body_mesh(organ).unwrap().is_closed());
//! let forceps = loaded.scripts["forceps"].sample("forceps", 2.5).unwrap();
//! assert_eq!(forceps.jaw, 0.0); // closed on the fundus while lifting
//! assert_eq!(loaded.hash.len(), 64);
//! ```
//!
//! This crate knows nothing of the lattice or the FEM; it describes scenes and reads and
//! writes files. SI units throughout (m, s, kg, Pa, N), +z up.

#![warn(missing_docs)]

pub mod builtin;
pub mod containment;
pub mod mesh;
pub mod scene;
pub mod script;
pub mod surf;
pub mod vtk;

pub use containment::Containment;
pub use mesh::{MeshError, MeshFormat, TriMesh};
pub use scene::{
    Aabb, Attachment, Body, BodyShape, CameraSpec, Capsule, DEFAULT_CAMERA_FOV_DEG, FORMAT_VERSION,
    Features, FileReader, Fix, Inclusion, InclusionShape, LinearSolver, Load, LoadedScene,
    Material, Model, NodeSelection, PolarMethod, Probe, Scene, SceneError, SimulationSettings,
    ToolKind, ToolSpec, scene_hash,
};
pub use script::{ScriptCommand, ScriptError, SessionCommand, ToolPose, ToolScript, ToolWaypoint};
