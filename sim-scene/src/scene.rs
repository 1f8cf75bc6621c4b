//! The scene description: serde types, validation, loading and hashing.
//!
//! See `SCENE_FORMAT.md` in this crate for the file format. Parsing (serde, with
//! `deny_unknown_fields`) and validation ([`Scene::validate`]) are separate passes;
//! [`Scene::load`] and [`Scene::from_str`] run both and also read every referenced file.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::mesh::{MeshError, MeshFormat, TriMesh};
use crate::script::ToolScript;

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

/// Deformation models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Model {
    /// Co-rotational linear FEM (default).
    #[default]
    Corotational,
    /// Plain linear FEM (reference; volume grows under rotation).
    Linear,
    /// Non-linear hyperelastic reference (StVK/Neo-Hookean with Newton).
    Nonlinear,
}

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
    /// Deformation model (default `corotational`).
    pub model: Model,
    /// Maximum conjugate-gradient iterations per step (≥ 1, default 50).
    pub cg_iterations: u32,
    /// Relative CG residual tolerance (> 0, default 1e-6).
    pub cg_tolerance: f64,
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

/// SHA-256 (lower-case hex) identifying a scene and everything it references.
///
/// Hashed, in order: the ASCII tag `cosurg-scene-v1`, then for the scene text and each
/// referenced file (in the order they are referenced: bodies in order — the body mesh
/// then its inclusion meshes — then tool scripts in tool order; a file referenced twice
/// counts once): the file's name as written in the scene (`""` for the scene text) and its
/// bytes, each preceded by its length as a little-endian u64. Line endings are not
/// normalised, so the hash identifies the exact bytes.
pub fn scene_hash<'a>(
    scene_text: &[u8],
    files: impl IntoIterator<Item = (&'a str, &'a [u8])>,
) -> String {
    let mut h = Sha256::new();
    h.update(b"cosurg-scene-v1");
    let mut put = |name: &str, bytes: &[u8]| {
        h.update((name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    put("", scene_text);
    for (name, bytes) in files {
        put(name, bytes);
    }
    hex::encode(h.finalize())
}

/// Deserialises TOML, reporting errors as (key path, "message (line L, column C)").
pub(crate) fn parse_toml<T: serde::de::DeserializeOwned>(
    text: &str,
) -> Result<T, (Option<String>, String)> {
    let locate = |e: &toml::de::Error| -> String {
        match e.span() {
            Some(span) => {
                let before = &text[..span.start.min(text.len())];
                let line = before.matches('\n').count() + 1;
                let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
                format!("{} (line {line}, column {col})", e.message().trim_end())
            }
            None => e.message().trim_end().to_string(),
        }
    };
    let de = toml::Deserializer::parse(text).map_err(|e| (None, locate(&e)))?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let msg = inner.message();
        let mut key = if path == "." { String::new() } else { path };
        // the path ends at the table that lacks a required key: name the key
        if let Some(rest) = msg.strip_prefix("missing field `")
            && let Some(end) = rest.find('`')
        {
            if !key.is_empty() {
                key.push('.');
            }
            key.push_str(&rest[..end]);
        }
        ((!key.is_empty()).then_some(key), locate(&inner))
    })
}

fn check_vec(file: &str, key: &str, v: &Vector3<f64>) -> Result<(), SceneError> {
    if v.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(SceneError::invalid(file, key, "must be finite"))
    }
}

fn check_positive(file: &str, key: &str, x: f64, unit: &str) -> Result<(), SceneError> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(SceneError::invalid(
            file,
            key,
            format!("must be positive and finite, got {x}{unit}"),
        ))
    }
}

fn check_box(file: &str, key: &str, b: &Aabb, allow_flat: bool) -> Result<(), SceneError> {
    check_vec(file, &format!("{key}.min"), &b.min)?;
    check_vec(file, &format!("{key}.max"), &b.max)?;
    let bad = if allow_flat {
        !b.is_ordered()
    } else {
        b.is_empty()
    };
    if bad {
        return Err(SceneError::invalid(
            file,
            key,
            format!(
                "box is empty: max must be {} min on every axis (min = {:?}, max = {:?})",
                if allow_flat { "≥" } else { ">" },
                b.min.as_slice(),
                b.max.as_slice()
            ),
        ));
    }
    Ok(())
}

impl Scene {
    /// Parses TOML text without validating (use [`Scene::validate`] next).
    pub fn parse(text: &str, file: &str) -> Result<Scene, SceneError> {
        parse_toml(text).map_err(|(key, message)| SceneError::Parse {
            file: file.to_string(),
            key,
            message,
        })
    }

    /// Serialises the scene back to TOML (a parse of the output equals `self`).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("scene serialises")
    }

    /// Checks every value that can be checked without reading files or knowing the
    /// lattice. `file` labels errors.
    pub fn validate(&self, file: &str) -> Result<(), SceneError> {
        if let Some(v) = self.version
            && (v == 0 || v > FORMAT_VERSION)
        {
            return Err(SceneError::invalid(
                file,
                "version",
                format!("unsupported format version {v} (this build reads 1..={FORMAT_VERSION})"),
            ));
        }
        check_vec(file, "gravity", &self.gravity)?;
        if let Some(cam) = &self.camera {
            check_vec(file, "camera.position", &cam.position)?;
            check_vec(file, "camera.target", &cam.target)?;
            if (cam.position - cam.target).norm() < 1e-6 {
                return Err(SceneError::invalid(
                    file,
                    "camera.target",
                    "must differ from camera.position (the camera needs a direction)",
                ));
            }
            if !(cam.fov_deg > 1.0 && cam.fov_deg < 170.0) {
                return Err(SceneError::invalid(
                    file,
                    "camera.fov_deg",
                    format!("{} is outside (1, 170) degrees", cam.fov_deg),
                ));
            }
        }
        for (name, m) in &self.materials {
            let k = |f: &str| format!("material.{name}.{f}");
            check_positive(file, &k("young"), m.young, " Pa")?;
            if !(m.poisson > -1.0 && m.poisson < 0.5) {
                return Err(SceneError::invalid(
                    file,
                    k("poisson"),
                    format!("must satisfy -1 < poisson < 0.5, got {}", m.poisson),
                ));
            }
            check_positive(file, &k("density"), m.density, " kg/m^3")?;
            for (f, v) in [
                ("rayleigh_mass", m.rayleigh_mass),
                ("rayleigh_stiffness", m.rayleigh_stiffness),
            ] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(SceneError::invalid(
                        file,
                        k(f),
                        format!("must be non-negative and finite, got {v}"),
                    ));
                }
            }
        }
        if self.bodies.is_empty() {
            return Err(SceneError::invalid(
                file,
                "body",
                "the scene defines no [[body]]",
            ));
        }
        let material_ok = |key: String, name: &str| {
            if self.materials.contains_key(name) {
                Ok(())
            } else {
                let known: Vec<&str> = self.materials.keys().map(String::as_str).collect();
                Err(SceneError::invalid(
                    file,
                    key,
                    format!("undefined material \"{name}\" (defined: {known:?})"),
                ))
            }
        };
        let mut names = BTreeSet::new();
        for (i, b) in self.bodies.iter().enumerate() {
            let k = |f: &str| format!("body[{i}].{f}");
            if b.name.is_empty() {
                return Err(SceneError::invalid(file, k("name"), "must not be empty"));
            }
            if !names.insert(b.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    k("name"),
                    format!("duplicate body name \"{}\"", b.name),
                ));
            }
            match (&b.box_shape, &b.mesh) {
                (Some(_), Some(_)) => {
                    return Err(SceneError::invalid(
                        file,
                        format!("body[{i}]"),
                        "give either `box` or `mesh`, not both",
                    ));
                }
                (None, None) => {
                    return Err(SceneError::invalid(
                        file,
                        format!("body[{i}]"),
                        "needs a shape: `box = { min = [..], max = [..] }` or `mesh = \"file\"`",
                    ));
                }
                (Some(bx), None) => check_box(file, &k("box"), bx, false)?,
                (None, Some(_)) => {}
            }
            check_positive(file, &k("cell"), b.cell, " m")?;
            if b.max_depth > 24 {
                return Err(SceneError::invalid(
                    file,
                    k("max_depth"),
                    format!("must be at most 24, got {}", b.max_depth),
                ));
            }
            material_ok(k("material"), &b.material)?;
            for (j, inc) in b.inclusions.iter().enumerate() {
                let ik = |f: &str| format!("body[{i}].inclusion[{j}].{f}");
                material_ok(ik("material"), &inc.material)?;
                match (&inc.capsules, &inc.mesh) {
                    (Some(_), Some(_)) => {
                        return Err(SceneError::invalid(
                            file,
                            format!("body[{i}].inclusion[{j}]"),
                            "give either `capsules` or `mesh`, not both",
                        ));
                    }
                    (None, None) => {
                        return Err(SceneError::invalid(
                            file,
                            format!("body[{i}].inclusion[{j}]"),
                            "needs `capsules = [{ a = [..], b = [..], radius = .. }, ..]` or `mesh = \"file\"`",
                        ));
                    }
                    (Some(caps), None) => {
                        if caps.is_empty() {
                            return Err(SceneError::invalid(
                                file,
                                ik("capsules"),
                                "must list at least one capsule",
                            ));
                        }
                        for (c, cap) in caps.iter().enumerate() {
                            let ck = format!("body[{i}].inclusion[{j}].capsules[{c}]");
                            check_vec(file, &format!("{ck}.a"), &cap.a)?;
                            check_vec(file, &format!("{ck}.b"), &cap.b)?;
                            check_positive(file, &format!("{ck}.radius"), cap.radius, " m")?;
                        }
                    }
                    (None, Some(_)) => {}
                }
            }
        }
        for (i, f) in self.fixes.iter().enumerate() {
            check_box(file, &format!("fix[{i}].box"), &f.region, true)?;
        }
        for (i, l) in self.loads.iter().enumerate() {
            check_box(file, &format!("load[{i}].box"), &l.region, true)?;
            check_vec(file, &format!("load[{i}].force"), &l.force)?;
        }
        let mut names = BTreeSet::new();
        for (i, p) in self.probes.iter().enumerate() {
            if !names.insert(p.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    format!("probe[{i}].name"),
                    format!("duplicate probe name \"{}\"", p.name),
                ));
            }
            check_vec(file, &format!("probe[{i}].point"), &p.point)?;
        }
        let mut names = BTreeSet::new();
        for (i, t) in self.tools.iter().enumerate() {
            let k = |f: &str| format!("tool[{i}].{f}");
            if t.name.is_empty() {
                return Err(SceneError::invalid(file, k("name"), "must not be empty"));
            }
            if !names.insert(t.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    k("name"),
                    format!("duplicate tool name \"{}\"", t.name),
                ));
            }
            check_vec(file, &k("position"), &t.position)?;
            let n2: f64 = t.orientation.iter().map(|c| c * c).sum();
            if !(n2.is_finite() && n2 > 1e-12) {
                return Err(SceneError::invalid(
                    file,
                    k("orientation"),
                    "quaternion [w, x, y, z] must be finite and non-zero",
                ));
            }
            check_positive(file, &k("radius"), t.radius, " m")?;
            check_positive(file, &k("length"), t.length, " m")?;
        }
        let s = &self.simulation;
        check_positive(file, "simulation.dt", s.dt, " s")?;
        if s.cg_iterations == 0 {
            return Err(SceneError::invalid(
                file,
                "simulation.cg_iterations",
                "must be at least 1",
            ));
        }
        check_positive(file, "simulation.cg_tolerance", s.cg_tolerance, "")?;
        check_positive(file, "simulation.polar_tolerance", s.polar_tolerance, "")?;
        check_positive(
            file,
            "simulation.contact_stiffness",
            s.contact_stiffness,
            " N/m",
        )?;
        let a = self.features.rotation_sharing_angle_deg;
        if !(a.is_finite() && (0.0..=180.0).contains(&a)) {
            return Err(SceneError::invalid(
                file,
                "features.rotation_sharing_angle_deg",
                format!("must be within [0, 180] degrees, got {a}"),
            ));
        }
        Ok(())
    }

    /// Every referenced file as `(key, path as written)`, in hashing order.
    pub fn referenced_files(&self) -> Vec<(String, PathBuf)> {
        let mut out: Vec<(String, PathBuf)> = Vec::new();
        let mut push = |key: String, p: &PathBuf| {
            if !out.iter().any(|(_, q)| q == p) {
                out.push((key, p.clone()));
            }
        };
        for (i, b) in self.bodies.iter().enumerate() {
            if let Some(m) = &b.mesh {
                push(format!("body[{i}].mesh"), m);
            }
            for (j, inc) in b.inclusions.iter().enumerate() {
                if let Some(m) = &inc.mesh {
                    push(format!("body[{i}].inclusion[{j}].mesh"), m);
                }
            }
        }
        for (i, t) in self.tools.iter().enumerate() {
            if let Some(s) = &t.script {
                push(format!("tool[{i}].script"), s);
            }
        }
        out
    }

    /// Reads, parses and validates a scene file and every file it references (relative
    /// paths are resolved against the scene file's directory).
    pub fn load(path: impl AsRef<Path>) -> Result<LoadedScene, SceneError> {
        let path = path.as_ref();
        let label = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            file: label.clone(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("")).to_path_buf();
        Self::from_str(&text, &base, &label)
    }

    /// Like [`Scene::load`] for scene text already in memory; referenced files are read
    /// relative to `base_dir`; `file_label` names the scene in errors.
    #[allow(clippy::should_implement_trait)]
    pub fn from_str(
        text: &str,
        base_dir: &Path,
        file_label: &str,
    ) -> Result<LoadedScene, SceneError> {
        let mut loaded = Self::from_parts(text, file_label, &mut |rel: &Path| {
            let full = if rel.is_absolute() {
                rel.to_path_buf()
            } else {
                base_dir.join(rel)
            };
            std::fs::read(&full).map_err(|e| (full, e))
        })?;
        loaded.base_dir = Some(base_dir.to_path_buf());
        Ok(loaded)
    }

    /// Like [`Scene::from_str`], with referenced files supplied by `read` (given the path
    /// as written; returns the bytes, or the resolved path and the error).
    pub fn from_parts(
        text: &str,
        file_label: &str,
        read: &mut FileReader<'_>,
    ) -> Result<LoadedScene, SceneError> {
        let file = file_label;
        let scene = Scene::parse(text, file)?;
        scene.validate(file)?;
        let mut meshes = BTreeMap::new();
        let mut scripts = BTreeMap::new();
        let mut blobs: Vec<(String, Vec<u8>)> = Vec::new();
        for (key, rel) in scene.referenced_files() {
            let is_script = key.ends_with(".script");
            if !is_script && MeshFormat::from_path(&rel).is_none() {
                return Err(SceneError::Mesh {
                    file: file.to_string(),
                    key,
                    source: MeshError::UnsupportedFormat { path: rel },
                });
            }
            let bytes = read(&rel).map_err(|(path, source)| SceneError::MissingFile {
                file: file.to_string(),
                key: key.clone(),
                path,
                source,
            })?;
            if is_script {
                let label = rel.display().to_string();
                let script = ToolScript::parse(
                    std::str::from_utf8(&bytes).map_err(|_| {
                        SceneError::invalid(file, &key, format!("{label}: not UTF-8 text"))
                    })?,
                    &label,
                )
                .map_err(|e| SceneError::invalid(file, &key, e.to_string()))?;
                for (i, t) in scene.tools.iter().enumerate() {
                    if t.script.as_ref() == Some(&rel) {
                        let mut own = script.clone();
                        if !own.tracks.contains_key(&t.name) {
                            // a single-track script drives whichever tool references it
                            if own.tracks.len() != 1 {
                                return Err(SceneError::invalid(
                                    file,
                                    format!("tool[{i}].script"),
                                    format!(
                                        "{label} has no poses for tool \"{}\" (tools: {:?})",
                                        t.name,
                                        script.tools().collect::<Vec<_>>()
                                    ),
                                ));
                            }
                            let track = own.tracks.pop_first().map(|(_, k)| k).unwrap_or_default();
                            own.tracks.insert(t.name.clone(), track);
                        }
                        scripts.insert(t.name.clone(), own);
                    }
                }
            } else {
                let mesh_err = |source| SceneError::Mesh {
                    file: file.to_string(),
                    key: key.clone(),
                    source,
                };
                let format = MeshFormat::from_path(&rel)
                    .ok_or_else(|| mesh_err(MeshError::UnsupportedFormat { path: rel.clone() }))?;
                let mesh = TriMesh::from_bytes(&bytes, format, &rel).map_err(mesh_err)?;
                if !mesh.is_closed() {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: format!(
                            "mesh is not closed: {} edges are not shared by exactly two triangles",
                            mesh.non_manifold_or_boundary_edges()
                        ),
                    }));
                }
                if !mesh.is_consistently_oriented() {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: "mesh triangles are not consistently oriented".into(),
                    }));
                }
                if mesh.signed_volume() <= 0.0 {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: "mesh is oriented inward (negative volume); flip its triangles"
                            .into(),
                    }));
                }
                meshes.insert(rel.clone(), mesh);
            }
            blobs.push((rel.to_string_lossy().into_owned(), bytes));
        }
        let hash = scene_hash(
            text.as_bytes(),
            blobs.iter().map(|(n, b)| (n.as_str(), b.as_slice())),
        );
        tracing::info!(scene = file, %hash, bodies = scene.bodies.len(), "scene loaded");
        Ok(LoadedScene {
            scene,
            meshes,
            scripts,
            file: file.to_string(),
            base_dir: None,
            hash,
        })
    }

    /// Selects the lattice nodes of every `[[fix]]` and `[[load]]` box. The engine calls
    /// this once node positions are known; a box that selects no node is an error naming
    /// `fix[i].box` / `load[i].box`.
    pub fn validate_selection(
        &self,
        file: &str,
        nodes: &[Vector3<f64>],
    ) -> Result<NodeSelection, SceneError> {
        let select = |key: String, b: &Aabb| -> Result<Vec<usize>, SceneError> {
            let sel: Vec<usize> = nodes
                .iter()
                .enumerate()
                .filter(|(_, p)| b.contains(p))
                .map(|(i, _)| i)
                .collect();
            if sel.is_empty() {
                let range = Aabb::from_points(nodes.iter())
                    .map(|r| format!("{:?}..{:?}", r.min.as_slice(), r.max.as_slice()))
                    .unwrap_or_else(|| "none".into());
                return Err(SceneError::invalid(
                    file,
                    key,
                    format!(
                        "selects no node (box {:?}..{:?}; {} nodes span {range})",
                        b.min.as_slice(),
                        b.max.as_slice(),
                        nodes.len()
                    ),
                ));
            }
            Ok(sel)
        };
        let fixed = self
            .fixes
            .iter()
            .enumerate()
            .map(|(i, f)| select(format!("fix[{i}].box"), &f.region))
            .collect::<Result<_, _>>()?;
        let loaded = self
            .loads
            .iter()
            .enumerate()
            .map(|(i, l)| select(format!("load[{i}].box"), &l.region))
            .collect::<Result<_, _>>()?;
        Ok(NodeSelection { fixed, loaded })
    }

    /// The material of body `body` (after validation).
    pub fn body_material(&self, body: &Body) -> &Material {
        &self.materials[&body.material]
    }
}

impl LoadedScene {
    /// Changes the scene in memory (e.g. a benchmark overriding `young` or `cell`),
    /// validates it again and updates [`hash`](Self::hash) so that results still name
    /// exactly what ran: the new hash is [`scene_hash`] of the modified scene's canonical
    /// TOML ([`Scene::to_toml`]) with one extra entry named `base` holding the previous
    /// hash (hex). Referenced files cannot be swapped: every mesh and script the modified
    /// scene names must already be loaded. On error the scene is left unchanged.
    pub fn modify(&mut self, f: impl FnOnce(&mut Scene)) -> Result<(), SceneError> {
        let mut scene = self.scene.clone();
        f(&mut scene);
        scene.validate(&self.file)?;
        for (key, rel) in scene.referenced_files() {
            let loaded = if key.ends_with(".script") {
                self.scene
                    .tools
                    .iter()
                    .any(|t| t.script.as_ref() == Some(&rel))
            } else {
                self.meshes.contains_key(&rel)
            };
            if !loaded {
                return Err(SceneError::invalid(
                    &self.file,
                    key,
                    format!(
                        "{} is not loaded; a modified scene cannot add files",
                        rel.display()
                    ),
                ));
            }
        }
        let hash = scene_hash(scene.to_toml().as_bytes(), [("base", self.hash.as_bytes())]);
        tracing::info!(scene = %self.file, old = %self.hash, new = %hash, "scene modified");
        self.scene = scene;
        self.hash = hash;
        Ok(())
    }

    /// [`Scene::validate_selection`] with this scene's file label.
    pub fn validate_selection(&self, nodes: &[Vector3<f64>]) -> Result<NodeSelection, SceneError> {
        self.scene.validate_selection(&self.file, nodes)
    }

    /// The loaded mesh of a path as written in the scene.
    pub fn mesh(&self, rel: &Path) -> Option<&TriMesh> {
        self.meshes.get(rel)
    }

    /// The loaded mesh of a body with `mesh = ...`.
    pub fn body_mesh(&self, body: &Body) -> Option<&TriMesh> {
        body.mesh.as_deref().and_then(|m| self.meshes.get(m))
    }

    /// Bounding box of body `i` (its box, or its mesh's bounding box).
    pub fn body_bounds(&self, i: usize) -> Option<Aabb> {
        let b = self.scene.bodies.get(i)?;
        match b.shape() {
            BodyShape::Box(bx) => Some(*bx),
            BodyShape::Mesh(m) => self.meshes.get(m)?.bounding_box(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The example from the task description / SCENE_FORMAT.md.
    pub(crate) const EXAMPLE: &str = r#"
gravity = [0.0, 0.0, -9.81]

[material.tissue]
young = 1.0e5        # Pa
poisson = 0.45
density = 1000.0     # kg/m^3

[[body]]
name = "beam"
box = { min = [0.0, 0.0, 0.0], max = [0.4, 0.1, 0.1] }   # or: mesh = "organ.obj"
cell = 0.025         # lattice cube size, m
max_depth = 3        # bisection levels allowed below the root tets
material = "tissue"

[[fix]]              # nodes inside the box are clamped
box = { min = [-0.001, -1.0, -1.0], max = [0.001, 1.0, 1.0] }

[[load]]             # total force in N, spread over the nodes inside the box
box = { min = [0.399, -1.0, -1.0], max = [0.401, 1.0, 1.0] }
force = [0.0, 0.0, -1.0]

[[probe]]            # a point reported by solvers, interpolated like an embedded vertex
name = "tip"
point = [0.4, 0.05, 0.05]
"#;

    fn load(text: &str) -> Result<LoadedScene, SceneError> {
        Scene::from_str(text, Path::new("/nonexistent-dir"), "s.toml")
    }

    #[test]
    fn camera_port() {
        let ok = load(&format!(
            "{EXAMPLE}\n[camera]\nposition = [0.2, -0.3, 0.05]\ntarget = [0.2, 0.05, 0.05]\n"
        ))
        .unwrap();
        let cam = ok.scene.camera.as_ref().unwrap();
        assert_eq!(cam.position, Vector3::new(0.2, -0.3, 0.05));
        assert_eq!(cam.fov_deg, DEFAULT_CAMERA_FOV_DEG);
        assert!(load(EXAMPLE).unwrap().scene.camera.is_none());
        // round trip through TOML keeps it
        let again = Scene::parse(&ok.scene.to_toml(), "t.toml").unwrap();
        assert_eq!(again.camera, ok.scene.camera);
        let e = err(&format!(
            "{EXAMPLE}\n[camera]\nposition = [0.1, 0.0, 0.0]\ntarget = [0.1, 0.0, 0.0]\n"
        ));
        assert!(
            e.starts_with("s.toml: `camera.target`: must differ from camera.position"),
            "{e}"
        );
        let e = err(&format!(
            "{EXAMPLE}\n[camera]\nposition = [0.0, 0.0, 0.0]\ntarget = [1.0, 0.0, 0.0]\nfov_deg = 180.0\n"
        ));
        assert!(
            e.starts_with("s.toml: `camera.fov_deg`: 180 is outside (1, 170) degrees"),
            "{e}"
        );
        let e = err(&format!(
            "{EXAMPLE}\n[camera]\nposition = [0.0, 0.0, 0.0]\n"
        ));
        assert!(
            e.contains("`camera.target`: missing field `target`")
                || e.contains("missing field `target`"),
            "{e}"
        );
    }

    fn err(text: &str) -> String {
        load(text).unwrap_err().to_string()
    }

    /// EXAMPLE with `from` replaced by `to` (which must occur).
    fn edit(from: &str, to: &str) -> String {
        assert!(EXAMPLE.contains(from), "{from}");
        EXAMPLE.replacen(from, to, 1)
    }

    #[test]
    fn example_parses_with_meanings_and_defaults() {
        let l = load(EXAMPLE).unwrap();
        let s = &l.scene;
        assert_eq!(s.gravity, Vector3::new(0.0, 0.0, -9.81));
        let m = &s.materials["tissue"];
        assert_eq!((m.young, m.poisson, m.density), (1e5, 0.45, 1000.0));
        assert_eq!((m.rayleigh_mass, m.rayleigh_stiffness), (0.0, 0.0));
        let (lambda, mu) = m.lame();
        assert!((mu - 1e5 / 2.9).abs() < 1e-6);
        assert!((lambda - 1e5 * 0.45 / (1.45 * 0.1)).abs() < 1e-6);
        let b = &s.bodies[0];
        assert_eq!(
            b.shape(),
            BodyShape::Box(&Aabb::new(Vector3::zeros(), Vector3::new(0.4, 0.1, 0.1)))
        );
        assert_eq!(
            (b.cell, b.max_depth, b.material.as_str()),
            (0.025, 3, "tissue")
        );
        assert_eq!(s.fixes[0].region.min.x, -0.001);
        assert_eq!(s.loads[0].force, Vector3::new(0.0, 0.0, -1.0));
        assert_eq!(s.probes[0].name, "tip");
        assert_eq!(s.simulation, SimulationSettings::default());
        assert_eq!(s.features, Features::default());
        assert_eq!(s.simulation.dt, 0.002);
        assert!(s.features.template_stiffness && s.features.skip_rest && !s.features.adaptivity);
        assert_eq!(l.hash, scene_hash(EXAMPLE.as_bytes(), []));
        assert_eq!(l.hash.len(), 64);
        assert_eq!(l.body_bounds(0).unwrap().max.x, 0.4);
    }

    #[test]
    fn serialise_roundtrip() {
        let l = load(EXAMPLE).unwrap();
        let text = l.scene.to_toml();
        let back = Scene::parse(&text, "re.toml").unwrap();
        assert_eq!(back, l.scene);
        let c = crate::builtin::cholecystectomy();
        let back = Scene::parse(&c.scene.to_toml(), "re.toml").unwrap();
        assert_eq!(back, c.scene);
    }

    #[test]
    fn full_feature_set_parses() {
        let dir = tempfile::tempdir().unwrap();
        crate::builtin::write_generated_files(dir.path()).unwrap();
        let text = r#"
version = 1
[material.a]
young = 1e4
poisson = 0.3
density = 1000
rayleigh_mass = 0.5
rayleigh_stiffness = 0.01
[material.v]
young = 2e5
poisson = 0.4
density = 1100
[[body]]
name = "organ"
mesh = "meshes/liver.obj"
cell = 0.02
material = "a"
[[body.inclusion]]
material = "v"
capsules = [{ a = [0, 0, 0], b = [0.01, 0, 0], radius = 0.002 }]
refine_boundary = true
[[body.inclusion]]
name = "gb"
material = "v"
mesh = "meshes/gallbladder.obj"
[[tool]]
name = "f"
kind = "forceps"
position = [0, 0, 0.1]
orientation = [0, 1, 0, 0]
script = "scripts/grasp_lift.toml"
[[tool]]
name = "h"
kind = "hook"
position = [0, 0, 0.2]
[simulation]
dt = 0.001
model = "nonlinear"
cg_iterations = 100
cg_tolerance = 1e-8
polar = "shape-matching"
polar_tolerance = 1e-9
[features]
adaptivity = true
rotation_sharing = true
rotation_sharing_angle_deg = 2.5
template_stiffness = false
contact = false
skip_rest = false
"#;
        let path = dir.path().join("full.toml");
        std::fs::write(&path, text).unwrap();
        let l = Scene::load(&path).unwrap();
        let s = &l.scene;
        assert_eq!(s.materials["a"].rayleigh_stiffness, 0.01);
        assert_eq!(s.simulation.model, Model::Nonlinear);
        assert_eq!(s.simulation.polar, PolarMethod::ShapeMatching);
        assert_eq!(s.features.rotation_sharing_angle_deg, 2.5);
        assert!(!s.features.contact);
        assert_eq!(s.tools[1].kind, ToolKind::Hook);
        assert_eq!(s.tools[1].orientation, [1.0, 0.0, 0.0, 0.0]);
        assert!((s.tools[0].rotation().angle() - std::f64::consts::PI).abs() < 1e-12);
        assert_eq!(l.meshes.len(), 2);
        assert!(l.body_mesh(&s.bodies[0]).unwrap().is_outward_oriented());
        assert!(
            matches!(s.bodies[0].inclusions[0].shape(), InclusionShape::Capsules(c) if c.len() == 1)
        );
        assert!(s.bodies[0].inclusions[0].refine_boundary);
        assert!(l.scripts["f"].duration() > 5.0);
        assert_eq!(l.base_dir.as_deref(), Some(dir.path()));
        // hash covers the mesh bytes: changing a mesh file changes the hash
        let h0 = l.hash.clone();
        assert_eq!(Scene::load(&path).unwrap().hash, h0, "stable");
        let gb = dir.path().join("meshes/gallbladder.obj");
        let mut bytes = std::fs::read(&gb).unwrap();
        bytes.extend_from_slice(b"# comment\n");
        std::fs::write(&gb, bytes).unwrap();
        assert_ne!(Scene::load(&path).unwrap().hash, h0);
    }

    #[test]
    fn hash_is_documented_construction() {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        h.update(b"cosurg-scene-v1");
        h.update(0u64.to_le_bytes());
        h.update(3u64.to_le_bytes());
        h.update(b"abc");
        h.update(5u64.to_le_bytes());
        h.update(b"m.obj");
        h.update(2u64.to_le_bytes());
        h.update(b"xy");
        assert_eq!(
            scene_hash(b"abc", [("m.obj", &b"xy"[..])]),
            hex::encode(h.finalize())
        );
        // known value, so that an accidental change of the construction is noticed
        assert_eq!(
            scene_hash(b"", []),
            "c06cddf3a2890d50ee6f1d8eccdd380eaced3a85f10c40971205640cb4296a4b"
        );
    }

    #[test]
    fn syntax_and_unknown_keys() {
        assert_eq!(
            err("gravity = [0, 0"),
            "s.toml: unclosed array, expected `]` (line 1, column 16)"
        );
        let e = err(&edit("young = 1.0e5", "youngs = 1.0e5"));
        assert!(
            e.starts_with(
                "s.toml: `material.tissue.youngs`: unknown field `youngs`, expected one of `young`"
            ),
            "{e}"
        );
        assert!(e.ends_with("(line 5, column 1)"), "{e}");
        let e = err(&format!("{EXAMPLE}\n[features]\nadaptive = true\n"));
        assert!(
            e.starts_with("s.toml: `features.adaptive`: unknown field `adaptive`"),
            "{e}"
        );
        let e = err(&format!("colour = 1\n{EXAMPLE}"));
        assert!(
            e.starts_with("s.toml: `colour`: unknown field `colour`"),
            "{e}"
        );
        let e = err(&edit("max = [0.4, 0.1, 0.1]", "mx = [0.4, 0.1, 0.1]"));
        assert!(
            e.starts_with("s.toml: `body[0].box.mx`: unknown field `mx`"),
            "{e}"
        );
        let e = err(&edit("name = \"beam\"\n", ""));
        assert!(
            e.starts_with("s.toml: `body[0].name`: missing field `name`"),
            "{e}"
        );
        let e = err(&edit("max_depth = 3", "max_depth = -3"));
        assert!(e.starts_with("s.toml: `body[0].max_depth`: "), "{e}");
        let e = err(&edit("density = 1000.0", "density = \"heavy\""));
        assert!(
            e.starts_with(
                "s.toml: `material.tissue.density`: invalid type: string \"heavy\", expected f64"
            ),
            "{e}"
        );
        let e = err(&format!("{EXAMPLE}\n[simulation]\nmodel = \"fancy\"\n"));
        assert!(
            e.starts_with("s.toml: `simulation.model`: unknown variant `fancy`, expected one of `corotational`, `linear`, `nonlinear`"),
            "{e}"
        );
        let e = err("version = 2\n");
        assert_eq!(
            e,
            "s.toml: `version`: unsupported format version 2 (this build reads 1..=1)"
        );
    }

    #[test]
    fn non_physical_material_values() {
        let cases = [
            (
                "young = 1.0e5",
                "young = -1.0",
                "s.toml: `material.tissue.young`: must be positive and finite, got -1 Pa",
            ),
            (
                "young = 1.0e5",
                "young = 0.0",
                "s.toml: `material.tissue.young`: must be positive and finite, got 0 Pa",
            ),
            (
                "poisson = 0.45",
                "poisson = 0.5",
                "s.toml: `material.tissue.poisson`: must satisfy -1 < poisson < 0.5, got 0.5",
            ),
            (
                "poisson = 0.45",
                "poisson = -1.0",
                "s.toml: `material.tissue.poisson`: must satisfy -1 < poisson < 0.5, got -1",
            ),
            (
                "density = 1000.0",
                "density = 0.0",
                "s.toml: `material.tissue.density`: must be positive and finite, got 0 kg/m^3",
            ),
            (
                "density = 1000.0",
                "density = 1000.0\nrayleigh_mass = -1.0",
                "s.toml: `material.tissue.rayleigh_mass`: must be non-negative and finite, got -1",
            ),
            (
                "density = 1000.0",
                "density = 1000.0\nrayleigh_stiffness = nan",
                "s.toml: `material.tissue.rayleigh_stiffness`: must be non-negative and finite, got NaN",
            ),
        ];
        for (from, to, msg) in cases {
            assert_eq!(err(&edit(from, to)), msg);
        }
    }

    #[test]
    fn body_errors() {
        assert_eq!(
            err(&edit("cell = 0.025", "cell = 0.0")),
            "s.toml: `body[0].cell`: must be positive and finite, got 0 m"
        );
        assert_eq!(
            err(&edit("max = [0.4, 0.1, 0.1]", "max = [0.4, 0.0, 0.1]")),
            "s.toml: `body[0].box`: box is empty: max must be > min on every axis (min = [0.0, 0.0, 0.0], max = [0.4, 0.0, 0.1])"
        );
        assert_eq!(
            err(&edit("material = \"tissue\"", "material = \"bone\"")),
            "s.toml: `body[0].material`: undefined material \"bone\" (defined: [\"tissue\"])"
        );
        assert_eq!(
            err(&edit("cell = 0.025", "mesh = \"organ.obj\"\ncell = 0.025")),
            "s.toml: `body[0]`: give either `box` or `mesh`, not both"
        );
        assert_eq!(
            err(&edit(
                "box = { min = [0.0, 0.0, 0.0], max = [0.4, 0.1, 0.1] }   # or: mesh = \"organ.obj\"",
                ""
            )),
            "s.toml: `body[0]`: needs a shape: `box = { min = [..], max = [..] }` or `mesh = \"file\"`"
        );
        assert_eq!(
            err(&edit("max_depth = 3", "max_depth = 30")),
            "s.toml: `body[0].max_depth`: must be at most 24, got 30"
        );
        let two = format!(
            "{EXAMPLE}\n[[body]]\nname = \"beam\"\nbox = {{ min = [0,0,0], max = [1,1,1] }}\ncell = 0.1\nmaterial = \"tissue\"\n"
        );
        assert_eq!(
            err(&two),
            "s.toml: `body[1].name`: duplicate body name \"beam\""
        );
        assert_eq!(
            err("[material.a]\nyoung = 1\npoisson = 0\ndensity = 1\n"),
            "s.toml: `body`: the scene defines no [[body]]"
        );
    }

    #[test]
    fn inclusion_errors() {
        let inc = |s: &str| format!("{EXAMPLE}\n[[body.inclusion]]\n{s}\n");
        // note: [[body.inclusion]] after [[probe]] attaches to the last body
        assert_eq!(
            err(&inc(
                "material = \"steel\"\ncapsules = [{ a = [0,0,0], b = [1,0,0], radius = 0.1 }]"
            )),
            "s.toml: `body[0].inclusion[0].material`: undefined material \"steel\" (defined: [\"tissue\"])"
        );
        assert_eq!(
            err(&inc(
                "material = \"tissue\"\ncapsules = [{ a = [0,0,0], b = [1,0,0], radius = 0.0 }]"
            )),
            "s.toml: `body[0].inclusion[0].capsules[0].radius`: must be positive and finite, got 0 m"
        );
        assert_eq!(
            err(&inc("material = \"tissue\"\ncapsules = []")),
            "s.toml: `body[0].inclusion[0].capsules`: must list at least one capsule"
        );
        assert_eq!(
            err(&inc("material = \"tissue\"")),
            "s.toml: `body[0].inclusion[0]`: needs `capsules = [{ a = [..], b = [..], radius = .. }, ..]` or `mesh = \"file\"`"
        );
        assert_eq!(
            err(&inc(
                "material = \"tissue\"\nmesh = \"a.obj\"\ncapsules = [{ a = [0,0,0], b = [1,0,0], radius = 0.1 }]"
            )),
            "s.toml: `body[0].inclusion[0]`: give either `capsules` or `mesh`, not both"
        );
    }

    #[test]
    fn file_errors() {
        let dir = tempfile::tempdir().unwrap();
        let scene = |body_mesh: &str| {
            let text = edit(
                "box = { min = [0.0, 0.0, 0.0], max = [0.4, 0.1, 0.1] }   # or: mesh = \"organ.obj\"",
                &format!("mesh = \"{body_mesh}\""),
            );
            let p = dir.path().join("s.toml");
            std::fs::write(&p, text).unwrap();
            Scene::load(&p).unwrap_err().to_string()
        };
        let sp = dir.path().join("s.toml").display().to_string();
        let e = scene("organ.obj");
        assert!(
            e.starts_with(&format!(
                "{sp}: `body[0].mesh`: cannot read {}: ",
                dir.path().join("organ.obj").display()
            )),
            "{e}"
        );
        std::fs::write(dir.path().join("bad.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
        let e = scene("bad.obj");
        assert!(
            e.starts_with(&format!("{sp}: `body[0].mesh`: bad.obj: ")),
            "{e}"
        );
        std::fs::write(
            dir.path().join("open.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        assert_eq!(
            scene("open.obj"),
            format!(
                "{sp}: `body[0].mesh`: open.obj: mesh is not closed: 3 edges are not shared by exactly two triangles"
            )
        );
        let mut cube = crate::mesh::tests::cube();
        cube.flip();
        cube.write_obj(dir.path().join("inward.obj")).unwrap();
        assert_eq!(
            scene("inward.obj"),
            format!(
                "{sp}: `body[0].mesh`: inward.obj: mesh is oriented inward (negative volume); flip its triangles"
            )
        );
        let mut cube = crate::mesh::tests::cube();
        cube.triangles[0].swap(1, 2);
        cube.write_obj(dir.path().join("mixed.obj")).unwrap();
        assert_eq!(
            scene("mixed.obj"),
            format!(
                "{sp}: `body[0].mesh`: mixed.obj: mesh triangles are not consistently oriented"
            )
        );
        assert_eq!(
            scene("organ.vtk"),
            format!(
                "{sp}: `body[0].mesh`: organ.vtk: unsupported mesh format (expected .obj, .stl or .ply)"
            )
        );
        crate::mesh::tests::cube()
            .write_obj(dir.path().join("cube.obj"))
            .unwrap();
        let text = format!(
            "{EXAMPLE}\n[[tool]]\nname = \"f\"\nkind = \"forceps\"\nposition = [0,0,0]\nscript = \"s.txt\"\n"
        );
        std::fs::write(
            dir.path().join("s.txt"),
            "tool = \"g\"\n[[pose]]\nt = 0\nposition = [0,0,0]\n",
        )
        .unwrap();
        let l = Scene::from_str(&text, dir.path(), "x.toml").unwrap();
        assert!(
            l.scripts["f"].sample("f", 0.0).is_some(),
            "single track renamed"
        );
        std::fs::write(dir.path().join("s.txt"), "tool = \"g\"\n[[pose]]\nt = 0\nposition = [0,0,0]\n[[pose]]\ntool = \"h\"\nt = 0\nposition = [0,0,0]\n").unwrap();
        assert_eq!(
            Scene::from_str(&text, dir.path(), "x.toml")
                .unwrap_err()
                .to_string(),
            "x.toml: `tool[0].script`: s.txt has no poses for tool \"f\" (tools: [\"g\", \"h\"])"
        );
        std::fs::write(dir.path().join("s.txt"), "tool = \"f\"\n").unwrap();
        assert_eq!(
            Scene::from_str(&text, dir.path(), "x.toml")
                .unwrap_err()
                .to_string(),
            "x.toml: `tool[0].script`: s.txt: `pose`: the script has no [[pose]]"
        );
        let missing_script = format!(
            "{EXAMPLE}\n[[tool]]\nname = \"f\"\nkind = \"forceps\"\nposition = [0,0,0]\nscript = \"gone.toml\"\n"
        );
        let e = Scene::from_str(&missing_script, dir.path(), "x.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "x.toml: `tool[0].script`: cannot read {}: ",
                dir.path().join("gone.toml").display()
            )),
            "{e}"
        );
        let missing_inc = format!(
            "{EXAMPLE}\n[[body.inclusion]]\nmaterial = \"tissue\"\nmesh = \"vessel.stl\"\n"
        );
        let e = Scene::from_str(&missing_inc, dir.path(), "x.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "x.toml: `body[0].inclusion[0].mesh`: cannot read {}: ",
                dir.path().join("vessel.stl").display()
            )),
            "{e}"
        );
        let e = Scene::load(dir.path().join("none.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "{}: cannot read scene: ",
                dir.path().join("none.toml").display()
            )),
            "{e}"
        );
    }

    #[test]
    fn fix_load_probe_tool_simulation_feature_errors() {
        assert_eq!(
            err(&edit("max = [0.001, 1.0, 1.0]", "max = [-0.002, 1.0, 1.0]")),
            "s.toml: `fix[0].box`: box is empty: max must be ≥ min on every axis (min = [-0.001, -1.0, -1.0], max = [-0.002, 1.0, 1.0])"
        );
        assert_eq!(
            err(&edit("max = [0.401, 1.0, 1.0]", "max = [0.398, 1.0, 1.0]")),
            "s.toml: `load[0].box`: box is empty: max must be ≥ min on every axis (min = [0.399, -1.0, -1.0], max = [0.398, 1.0, 1.0])"
        );
        assert_eq!(
            err(&edit(
                "force = [0.0, 0.0, -1.0]",
                "force = [0.0, inf, -1.0]"
            )),
            "s.toml: `load[0].force`: must be finite"
        );
        assert_eq!(
            err(&edit(
                "point = [0.4, 0.05, 0.05]",
                "point = [0.4, nan, 0.05]"
            )),
            "s.toml: `probe[0].point`: must be finite"
        );
        let p2 = format!("{EXAMPLE}\n[[probe]]\nname = \"tip\"\npoint = [0,0,0]\n");
        assert_eq!(
            err(&p2),
            "s.toml: `probe[1].name`: duplicate probe name \"tip\""
        );
        let tool = |extra: &str| {
            format!(
                "{EXAMPLE}\n[[tool]]\nname = \"f\"\nkind = \"forceps\"\nposition = [0,0,0]\n{extra}\n"
            )
        };
        assert_eq!(
            err(&tool("orientation = [0, 0, 0, 0]")),
            "s.toml: `tool[0].orientation`: quaternion [w, x, y, z] must be finite and non-zero"
        );
        assert_eq!(
            err(&tool("radius = -0.001")),
            "s.toml: `tool[0].radius`: must be positive and finite, got -0.001 m"
        );
        assert_eq!(
            err(&tool("length = 0")),
            "s.toml: `tool[0].length`: must be positive and finite, got 0 m"
        );
        let e = err(&tool("kind = \"scalpel\""));
        assert!(e.contains("duplicate key") || e.contains("kind"), "{e}");
        let e = err(&format!(
            "{EXAMPLE}\n[[tool]]\nname = \"f\"\nkind = \"scalpel\"\nposition = [0,0,0]\n"
        ));
        assert!(
            e.contains("unknown variant `scalpel`, expected one of `forceps`, `probe`, `hook`"),
            "{e}"
        );
        let twice = format!(
            "{}\n[[tool]]\nname = \"f\"\nkind = \"probe\"\nposition = [0,0,0]\n",
            tool("")
        );
        assert_eq!(
            err(&twice),
            "s.toml: `tool[1].name`: duplicate tool name \"f\""
        );
        let sim = |s: &str| err(&format!("{EXAMPLE}\n[simulation]\n{s}\n"));
        assert_eq!(
            sim("dt = 0"),
            "s.toml: `simulation.dt`: must be positive and finite, got 0 s"
        );
        assert_eq!(
            sim("cg_iterations = 0"),
            "s.toml: `simulation.cg_iterations`: must be at least 1"
        );
        assert_eq!(
            sim("cg_tolerance = -1"),
            "s.toml: `simulation.cg_tolerance`: must be positive and finite, got -1"
        );
        assert_eq!(
            sim("polar_tolerance = 0"),
            "s.toml: `simulation.polar_tolerance`: must be positive and finite, got 0"
        );
        assert_eq!(
            sim("contact_stiffness = 0"),
            "s.toml: `simulation.contact_stiffness`: must be positive and finite, got 0 N/m"
        );
        assert_eq!(
            err(&format!(
                "{EXAMPLE}\n[features]\nrotation_sharing_angle_deg = 200\n"
            )),
            "s.toml: `features.rotation_sharing_angle_deg`: must be within [0, 180] degrees, got 200"
        );
        assert_eq!(
            err(&edit(
                "gravity = [0.0, 0.0, -9.81]",
                "gravity = [0.0, nan, -9.81]"
            )),
            "s.toml: `gravity`: must be finite"
        );
    }

    #[test]
    fn modify_revalidates_and_rehashes() {
        let mut l = crate::builtin::cantilever();
        let h0 = l.hash.clone();
        l.modify(|s| {
            s.materials.get_mut("tissue").unwrap().young = 1e6;
            s.bodies[0].cell = 0.05;
        })
        .unwrap();
        assert_eq!(l.scene.bodies[0].cell, 0.05);
        assert_ne!(l.hash, h0);
        let expect = scene_hash(l.scene.to_toml().as_bytes(), [("base", h0.as_bytes())]);
        assert_eq!(l.hash, expect);
        let h1 = l.hash.clone();
        let e = l
            .modify(|s| s.bodies[0].cell = -1.0)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "builtin:cantilever: `body[0].cell`: must be positive and finite, got -1 m"
        );
        assert_eq!(
            (l.scene.bodies[0].cell, l.hash.as_str()),
            (0.05, h1.as_str()),
            "unchanged on error"
        );
        let e = l
            .modify(|s| {
                s.bodies[0].box_shape = None;
                s.bodies[0].mesh = Some("other.obj".into());
            })
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "builtin:cantilever: `body[0].mesh`: other.obj is not loaded; a modified scene cannot add files"
        );
    }

    #[test]
    fn selection() {
        let l = load(EXAMPLE).unwrap();
        // nodes of a 0.1 m grid over the beam
        let mut nodes = Vec::new();
        for i in 0..=4 {
            for j in 0..=1 {
                for k in 0..=1 {
                    nodes.push(Vector3::new(i as f64 * 0.1, j as f64 * 0.1, k as f64 * 0.1));
                }
            }
        }
        let sel = l.validate_selection(&nodes).unwrap();
        assert_eq!(sel.fixed, vec![vec![0, 1, 2, 3]]);
        assert_eq!(sel.loaded, vec![vec![16, 17, 18, 19]]);
        assert_eq!(sel.all_fixed(), vec![0, 1, 2, 3]);
        let shifted: Vec<_> = nodes
            .iter()
            .map(|p| p + Vector3::new(0.05, 0.0, 0.0))
            .collect();
        assert_eq!(
            l.validate_selection(&shifted).unwrap_err().to_string(),
            "s.toml: `fix[0].box`: selects no node (box [-0.001, -1.0, -1.0]..[0.001, 1.0, 1.0]; 20 nodes span [0.05, 0.0, 0.0]..[0.45, 0.1, 0.1])"
        );
        let short: Vec<_> = nodes.iter().filter(|p| p.x < 0.35).copied().collect();
        let e = l.validate_selection(&short).unwrap_err().to_string();
        assert!(
            e.starts_with("s.toml: `load[0].box`: selects no node"),
            "{e}"
        );
    }
}
