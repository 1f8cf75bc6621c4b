//! The scene description: serde types, validation, loading and hashing.
//!
//! See `SCENE_FORMAT.md` in this crate for the file format. Parsing (serde, with
//! `deny_unknown_fields`) and validation ([`Scene::validate`]) are separate passes;
//! [`Scene::load`] and [`Scene::from_str`] run both and also read every referenced file.
//!
//! One file per job: the format's types and [`SceneError`] here, parsing and loading
//! (`load.rs`: [`Scene::parse`], [`Scene::load`], [`Scene::from_parts`], [`scene_hash`],
//! [`LoadedScene`]'s methods), validation (`validate.rs`: [`Scene::validate`],
//! [`Scene::validate_selection`]); tests in `tests.rs`.

mod load;
#[cfg(test)]
mod tests;
mod validate;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::mesh::{MeshError, TriMesh};
use crate::script::ToolScript;

pub(crate) use load::parse_toml;
pub use load::scene_hash;

/// The newest scene format version this crate reads (the optional top-level `version`).
pub const FORMAT_VERSION: u32 = 1;

/// Errors from reading or validating a scene. Every message starts with the scene file,
/// names the offending key in TOML path syntax (`material.tissue.poisson`, `body[0].mesh`)
/// and says what is wrong.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file itself could not be read.
    #[error("{file}: cannot read scene: {source}")]
    Io {
        /// Scene file.
        file: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// TOML syntax error, unknown key, wrong type or missing key.
    #[error("{file}: {}{message}", .key.as_deref().map(|k| format!("`{k}`: ")).unwrap_or_default())]
    Parse {
        /// Scene file.
        file: String,
        /// Key path where the error was found (e.g. `material.tissue.youngs`), when known.
        key: Option<String>,
        /// The TOML parser's message with line and column.
        message: String,
    },
    /// A value is present but not acceptable.
    #[error("{file}: `{key}`: {problem}")]
    Invalid {
        /// Scene file.
        file: String,
        /// Key path, e.g. `material.tissue.poisson`.
        key: String,
        /// What is wrong.
        problem: String,
    },
    /// A file referenced by the scene is missing or unreadable.
    #[error("{file}: `{key}`: cannot read {path}: {source}")]
    MissingFile {
        /// Scene file.
        file: String,
        /// Key path, e.g. `body[0].mesh`.
        key: String,
        /// The referenced path, resolved against the scene's directory.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A referenced mesh could not be parsed or is unusable.
    #[error("{file}: `{key}`: {source}")]
    Mesh {
        /// Scene file.
        file: String,
        /// Key path, e.g. `body[0].mesh`.
        key: String,
        /// The mesh error (names the mesh file).
        #[source]
        source: MeshError,
    },
}

impl SceneError {
    fn invalid(file: &str, key: impl Into<String>, problem: impl Into<String>) -> Self {
        SceneError::Invalid {
            file: file.to_string(),
            key: key.into(),
            problem: problem.into(),
        }
    }
}

/// Axis-aligned box in metres, written `{ min = [x, y, z], max = [x, y, z] }`.
/// Containment is inclusive on all faces.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Aabb {
    /// Lower corner.
    pub min: Vector3<f64>,
    /// Upper corner.
    pub max: Vector3<f64>,
}

impl Aabb {
    /// A box from two corners.
    pub fn new(min: Vector3<f64>, max: Vector3<f64>) -> Self {
        Self { min, max }
    }
    /// The bounding box of points (`None` when there are none).
    pub fn from_points<'a>(mut pts: impl Iterator<Item = &'a Vector3<f64>>) -> Option<Self> {
        let first = *pts.next()?;
        Some(pts.fold(Self::new(first, first), |b, p| Self {
            min: b.min.inf(p),
            max: b.max.sup(p),
        }))
    }
    /// Inclusive containment.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        (0..3).all(|k| p[k] >= self.min[k] && p[k] <= self.max[k])
    }
    /// `max − min`.
    pub fn size(&self) -> Vector3<f64> {
        self.max - self.min
    }
    /// Centre point.
    pub fn center(&self) -> Vector3<f64> {
        0.5 * (self.min + self.max)
    }
    /// Volume in m³ (0 when degenerate or inverted).
    pub fn volume(&self) -> f64 {
        let s = self.size();
        if s.iter().all(|&c| c > 0.0) {
            s.x * s.y * s.z
        } else {
            0.0
        }
    }
    /// True when the box has no interior (`max ≤ min` on some axis).
    pub fn is_empty(&self) -> bool {
        (0..3).any(|k| self.max[k] <= self.min[k])
    }
    /// True when `min ≤ max` on every axis (a flat box is still a valid selection box).
    pub fn is_ordered(&self) -> bool {
        (0..3).all(|k| self.min[k] <= self.max[k])
    }
    /// Smallest box containing both.
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb::new(self.min.inf(&o.min), self.max.sup(&o.max))
    }
    /// Grown by `d` on every side.
    pub fn inflated(&self, d: f64) -> Aabb {
        let v = Vector3::repeat(d);
        Aabb::new(self.min - v, self.max + v)
    }
}

/// An isotropic linear-elastic material (`[material.NAME]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Young's modulus E in Pa (> 0).
    pub young: f64,
    /// Poisson's ratio ν (−1 < ν < 0.5).
    pub poisson: f64,
    /// Mass density ρ in kg/m³ (> 0).
    pub density: f64,
    /// Rayleigh mass-proportional damping α in 1/s (≥ 0, default 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub rayleigh_mass: f64,
    /// Rayleigh stiffness-proportional damping β in s (≥ 0, default 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub rayleigh_stiffness: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}
fn is_false(x: &bool) -> bool {
    !*x
}

impl Material {
    /// Lamé parameters `(λ, μ)` in Pa.
    pub fn lame(&self) -> (f64, f64) {
        let (e, nu) = (self.young, self.poisson);
        let mu = e / (2.0 * (1.0 + nu));
        let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
        (lambda, mu)
    }
}

/// The region a body occupies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BodyShape<'a> {
    /// A solid box (`box = {min, max}`).
    Box(&'a Aabb),
    /// The inside of a closed triangle mesh (`mesh = "file"`), path as written in the scene.
    Mesh(&'a Path),
}

/// A deformable body (`[[body]]`): a shape embedded in a lattice of cubes of size `cell`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Body {
    /// Unique name.
    pub name: String,
    /// Box shape; exactly one of `box` and `mesh` must be given.
    #[serde(rename = "box", default, skip_serializing_if = "Option::is_none")]
    pub box_shape: Option<Aabb>,
    /// Mesh shape (OBJ/STL/PLY, relative to the scene file's directory).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<PathBuf>,
    /// Edge length of the lattice's root cubes in m (> 0).
    pub cell: f64,
    /// Bisection levels allowed below the root tets (0 = no refinement; ≤ 24).
    #[serde(default)]
    pub max_depth: u32,
    /// Name of a `[material.NAME]` table.
    pub material: String,
    /// Embedded sub-structures with their own material.
    #[serde(rename = "inclusion", default, skip_serializing_if = "Vec::is_empty")]
    pub inclusions: Vec<Inclusion>,
}

impl Body {
    /// The body's shape (call after validation; a body with neither falls back to an
    /// empty box, which validation rejects).
    pub fn shape(&self) -> BodyShape<'_> {
        match (&self.box_shape, &self.mesh) {
            (Some(b), _) => BodyShape::Box(b),
            (None, Some(m)) => BodyShape::Mesh(m),
            (None, None) => BodyShape::Box(&EMPTY_BOX),
        }
    }
}

static EMPTY_BOX: Aabb = Aabb {
    min: Vector3::new(0.0, 0.0, 0.0),
    max: Vector3::new(0.0, 0.0, 0.0),
};

/// A capsule: the set of points within `radius` of segment `a`–`b` (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Capsule {
    /// Segment start.
    pub a: Vector3<f64>,
    /// Segment end.
    pub b: Vector3<f64>,
    /// Radius in m (> 0).
    pub radius: f64,
}

impl Capsule {
    /// Signed distance (m) from `p` to the capsule surface (negative inside).
    pub fn signed_distance(&self, p: &Vector3<f64>) -> f64 {
        let ab = self.b - self.a;
        let l2 = ab.norm_squared();
        let t = if l2 > 0.0 {
            ((p - self.a).dot(&ab) / l2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (p - (self.a + t * ab)).norm() - self.radius
    }
}

/// The region an inclusion occupies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InclusionShape<'a> {
    /// Union of capsules (a vessel tree).
    Capsules(&'a [Capsule]),
    /// Inside of a closed mesh, path as written in the scene.
    Mesh(&'a Path),
}

/// An embedded sub-structure of a body with its own material (`[[body.inclusion]]`).
/// Lattice elements are assigned the inclusion's material where their centre lies inside.
/// Later inclusions override earlier ones where they overlap.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inclusion {
    /// Optional name (for output and logs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Name of a `[material.NAME]` table.
    pub material: String,
    /// Capsules; exactly one of `capsules` and `mesh` must be given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub capsules: Option<Vec<Capsule>>,
    /// Closed mesh, relative to the scene file's directory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<PathBuf>,
    /// Refine the lattice (up to the body's `max_depth`) along this inclusion's boundary.
    #[serde(default, skip_serializing_if = "is_false")]
    pub refine_boundary: bool,
}

impl Inclusion {
    /// The inclusion's shape (call after validation).
    pub fn shape(&self) -> InclusionShape<'_> {
        match (&self.capsules, &self.mesh) {
            (Some(c), _) => InclusionShape::Capsules(c),
            (None, Some(m)) => InclusionShape::Mesh(m),
            (None, None) => InclusionShape::Capsules(&[]),
        }
    }
}

/// Lattice nodes inside `box` are clamped (zero displacement) (`[[fix]]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fix {
    /// Selection box (inclusive); must select at least one node.
    #[serde(rename = "box")]
    pub region: Aabb,
}

/// A constant external force (`[[load]]`): `force` (N, total) split equally over the
/// lattice nodes inside `box`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Load {
    /// Selection box (inclusive); must select at least one node.
    #[serde(rename = "box")]
    pub region: Aabb,
    /// Total force in N.
    pub force: Vector3<f64>,
}

/// A reported point (`[[probe]]`), interpolated from its host tet like an embedded vertex.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Probe {
    /// Unique name.
    pub name: String,
    /// Rest position in m.
    pub point: Vector3<f64>,
}

/// Tool kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ToolKind {
    /// Two-jaw grasper; grasps while the jaw angle is below its closing threshold.
    Forceps,
    /// Blunt rod for pushing.
    Probe,
    /// Dissection hook.
    Hook,
    /// Blade (scalpel or scissors closing): its cutting edge runs along the shaft from the
    /// tip to `length`; the surface it sweeps through a body is cut. No contact.
    Blade,
    /// Clip applier: two jaws like the forceps, no contact; closing them on tissue leaves
    /// a clip along the closed jaws, embedded in that tissue.
    ClipApplier,
}

fn default_orientation() -> [f64; 4] {
    [1.0, 0.0, 0.0, 0.0]
}
fn default_tool_radius() -> f64 {
    0.0025
}
fn default_tool_length() -> f64 {
    0.02
}
fn is_identity(q: &[f64; 4]) -> bool {
    *q == default_orientation()
}

/// A rigid tool (`[[tool]]`). Tool frame: the tip is at the origin, the shaft runs along
/// local +z (so with the identity orientation the tool points straight down, −z).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolSpec {
    /// Unique name (also the tool name used in scripts).
    pub name: String,
    /// Kind.
    pub kind: ToolKind,
    /// Initial tip position in m.
    pub position: Vector3<f64>,
    /// Initial orientation as a quaternion `[w, x, y, z]` (normalised on use; default identity).
    #[serde(default = "default_orientation", skip_serializing_if = "is_identity")]
    pub orientation: [f64; 4],
    /// Tip radius in m (> 0, default 0.0025): contact sample points lie on this surface.
    #[serde(default = "default_tool_radius")]
    pub radius: f64,
    /// Length of the contact-active tip (jaws) in m (> 0, default 0.02).
    #[serde(default = "default_tool_length")]
    pub length: f64,
    /// Optional tool script (see `script` module), relative to the scene file's directory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub script: Option<PathBuf>,
}

impl ToolSpec {
    /// The normalised initial orientation.
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        crate::script::quat_wxyz(self.orientation)
    }
}

fn default_release_radius() -> f64 {
    0.01
}

/// A connective layer between two bodies (`[[attachment]]`), e.g. the gallbladder bed.
///
/// The layer is a set of attachment springs: every surface vertex of `bodies[1]` (the
/// attached body) inside `box` is tied to the nearest surface vertex of `bodies[0]` (the
/// host) when that one lies within `reach`. A spring joins the two embedded points (each
/// moves with its own body's lattice); its rest length is their rest distance. The two
/// bodies must not share lattice nodes (their lattice cells must not touch: leave at least
/// one empty cell between them), otherwise they are one body and the layer ties nothing.
///
/// A `hook` tool releases springs (dissection): a spring whose midpoint lies within
/// `release_radius` of the hook's tip and whose force (tension or compression) is at
/// least `release_force` is
/// released, nearest first, at most `release_rate` springs per second per hook. A released
/// spring stays released.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Attachment {
    /// Unique name.
    pub name: String,
    /// `[host, attached]` body names (distinct).
    pub bodies: [String; 2],
    /// Where the layer is (inclusive box, m): attached-body surface vertices inside it get
    /// a spring.
    #[serde(rename = "box")]
    pub region: Aabb,
    /// Total stiffness of the layer in N/m (> 0), split equally over its springs (they act
    /// in parallel).
    pub stiffness: f64,
    /// Longest spring in m (> 0): a vertex whose nearest host vertex is farther gets none.
    pub reach: f64,
    /// Dissection rate: springs a hook releases per second (≥ 0; 0: the hook cannot).
    #[serde(default)]
    pub release_rate: f64,
    /// Dissection threshold: a spring releases only when it carries at least this force
    /// (tension or compression) in N (≥ 0).
    #[serde(default)]
    pub release_force: f64,
    /// The hook works on springs whose midpoint lies within this distance of its tip (m,
    /// > 0, default 0.01).
    #[serde(default = "default_release_radius")]
    pub release_radius: f64,
}

/// Deformation models: `linear`, `corotational` (default), `stvk` (alias `nonlinear`). One
/// enum for every crate, sim-fem's.
pub use sim_fem::{LinearSolver, Model};

/// Polar-decomposition methods for the co-rotational model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PolarMethod {
    /// Scaled Newton iteration (Byers–Xu), default.
    #[default]
    ByersXu,
    /// SVD.
    Svd,
    /// Müller et al.'s iterative rotation extraction.
    Muller,
    /// Shape matching (polar factor of `A Aᵀ` via eigen-decomposition).
    ShapeMatching,
}

/// `[simulation]`: integrator and solver settings. Every key is optional.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimulationSettings {
    /// Time step in s (> 0, default 0.002 = 500 Hz).
    pub dt: f64,
    /// Deformation model: `linear`, `corotational` (default) or `stvk` (St Venant–Kirchhoff;
    /// `nonlinear` is read as `stvk`).
    pub model: Model,
    /// Maximum conjugate-gradient iterations per step (≥ 1, default 50).
    pub cg_iterations: u32,
    /// Relative CG residual tolerance (> 0, default 1e-6).
    pub cg_tolerance: f64,
    /// Linear solver of the implicit step: `auto` (default: chosen on the first step,
    /// MG-PCG if Jacobi-PCG needed more than 64 iterations there), `jacobi-pcg`, `mg-pcg` (CG
    /// preconditioned by a multigrid V-cycle over the lattice's bisection hierarchy) or
    /// `direct` (sparse Cholesky).
    pub solver: LinearSolver,
    /// Polar decomposition method (default `byers-xu`).
    pub polar: PolarMethod,
    /// Stopping tolerance of iterative polar methods, Frobenius norm of the update (> 0,
    /// default 1e-6).
    pub polar_tolerance: f64,
    /// Contact penalty stiffness in N/m per sample point (> 0, default 500).
    pub contact_stiffness: f64,
}

impl Default for SimulationSettings {
    fn default() -> Self {
        Self {
            dt: 0.002,
            model: Model::Corotational,
            cg_iterations: 50,
            cg_tolerance: 1e-6,
            solver: LinearSolver::Auto,
            polar: PolarMethod::ByersXu,
            polar_tolerance: 1e-6,
            contact_stiffness: 500.0,
        }
    }
}

/// `[features]`: switches for the method's optional parts. Every key is optional.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Features {
    /// Online refinement/coarsening of the lattice (default false).
    pub adaptivity: bool,
    /// Hierarchical rotation sharing (default false).
    pub rotation_sharing: bool,
    /// Angle tolerance for rotation sharing, degrees in [0, 180] (default 5).
    pub rotation_sharing_angle_deg: f64,
    /// Template (per-shape, scaled) element stiffness instead of per-element matrices
    /// (default true).
    pub template_stiffness: bool,
    /// Tool–surface contact (default true; skipped anyway when there are no tools).
    pub contact: bool,
    /// Skip rotation extraction for elements at rest (default true).
    pub skip_rest: bool,
    /// Fill weighting (default false): each element's stiffness and mass scaled by the
    /// fraction of its volume inside the bodies' shapes, and an element whose centre lies
    /// outside every body made of the body it overlaps most (not of the first body).
    #[serde(skip_serializing_if = "is_false")]
    pub fill_weighting: bool,
}

impl Default for Features {
    fn default() -> Self {
        Self {
            adaptivity: false,
            rotation_sharing: false,
            rotation_sharing_angle_deg: 5.0,
            template_stiffness: true,
            contact: true,
            skip_rest: true,
            fill_weighting: false,
        }
    }
}

fn default_gravity() -> Vector3<f64> {
    Vector3::new(0.0, 0.0, -9.81)
}

/// A whole scene file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Format version (optional; default and newest: [`FORMAT_VERSION`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<u32>,
    /// Free-text title.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub title: Option<String>,
    /// Free-text description.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    /// Gravity in m/s² (default `[0, 0, -9.81]`).
    #[serde(default = "default_gravity")]
    pub gravity: Vector3<f64>,
    /// Materials by name (`[material.NAME]`).
    #[serde(rename = "material", default)]
    pub materials: BTreeMap<String, Material>,
    /// Bodies (`[[body]]`); at least one. All bodies share one lattice.
    #[serde(rename = "body", default)]
    pub bodies: Vec<Body>,
    /// Fixed regions (`[[fix]]`).
    #[serde(rename = "fix", default, skip_serializing_if = "Vec::is_empty")]
    pub fixes: Vec<Fix>,
    /// Loads (`[[load]]`).
    #[serde(rename = "load", default, skip_serializing_if = "Vec::is_empty")]
    pub loads: Vec<Load>,
    /// Probes (`[[probe]]`).
    #[serde(rename = "probe", default, skip_serializing_if = "Vec::is_empty")]
    pub probes: Vec<Probe>,
    /// Tools (`[[tool]]`).
    #[serde(rename = "tool", default, skip_serializing_if = "Vec::is_empty")]
    pub tools: Vec<ToolSpec>,
    /// Connective layers tying two bodies (`[[attachment]]`).
    #[serde(rename = "attachment", default, skip_serializing_if = "Vec::is_empty")]
    pub attachments: Vec<Attachment>,
    /// Solver settings.
    #[serde(default)]
    pub simulation: SimulationSettings,
    /// Feature switches.
    #[serde(default)]
    pub features: Features,
    /// The laparoscope's port (`[camera]`, optional): where the window's default camera
    /// sits and what it looks at.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraSpec>,
}

/// Default vertical field of view of the laparoscope (degrees).
pub const DEFAULT_CAMERA_FOV_DEG: f64 = 50.0;

fn default_fov() -> f64 {
    DEFAULT_CAMERA_FOV_DEG
}

/// `[camera]`: the laparoscope port. Without it the window places the camera 25 cm in
/// front of (−y) and 15 cm below the bodies' centre, looking at that centre.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Port: the camera's position in m.
    pub position: Vector3<f64>,
    /// The point the camera looks at in m (≠ `position`).
    pub target: Vector3<f64>,
    /// Vertical field of view in degrees (in (1, 170), default 50).
    #[serde(default = "default_fov")]
    pub fov_deg: f64,
}

/// Supplies a referenced file's bytes, given its path as written in the scene; on failure
/// returns the resolved path and the error (see [`Scene::from_parts`]).
pub type FileReader<'a> = dyn FnMut(&Path) -> Result<Vec<u8>, (PathBuf, std::io::Error)> + 'a;

/// A validated scene with every referenced file loaded.
#[derive(Debug, Clone)]
pub struct LoadedScene {
    /// The scene.
    pub scene: Scene,
    /// Meshes by their path as written in the scene (e.g. `meshes/liver.obj`).
    pub meshes: BTreeMap<PathBuf, TriMesh>,
    /// Tool scripts by tool name (each holds at least a track under that tool's name; a
    /// script with a single track is renamed to the tool that references it).
    pub scripts: BTreeMap<String, ToolScript>,
    /// The scene file's label (its path, or `builtin:NAME`).
    pub file: String,
    /// Directory against which relative paths were resolved (`None` for built-ins).
    pub base_dir: Option<PathBuf>,
    /// [`scene_hash`]: SHA-256 hex of the scene text and every referenced file.
    pub hash: String,
}

/// Node indices selected by the scene's fix and load boxes (see
/// [`Scene::validate_selection`]).
#[derive(Debug, Clone, PartialEq)]
pub struct NodeSelection {
    /// `fixed[i]`: nodes inside `fix[i].box`.
    pub fixed: Vec<Vec<usize>>,
    /// `loaded[i]`: nodes inside `load[i].box`; each receives `load[i].force / len`.
    pub loaded: Vec<Vec<usize>>,
}

impl NodeSelection {
    /// All fixed nodes, sorted and deduplicated.
    pub fn all_fixed(&self) -> Vec<usize> {
        let s: BTreeSet<usize> = self.fixed.iter().flatten().copied().collect();
        s.into_iter().collect()
    }
}

impl Scene {
    /// The material of body `body` (after validation).
    pub fn body_material(&self, body: &Body) -> &Material {
        &self.materials[&body.material]
    }
}
