//! Built-in scenes and the generator of their meshes and tool scripts.
//!
//! The scene files in the repository's `scenes/` directory are embedded in the binary
//! (`include_str!`/`include_bytes!`), so [`cholecystectomy`] and [`cantilever`] work
//! without any file; `Scene::load("scenes/cholecystectomy.toml")` gives the same scene and
//! the same hash. The organ meshes and tool scripts are written by this project:
//! [`generate_organ_meshes`] and [`generate_scripts`] compute them deterministically and a
//! test checks that the shipped files equal [`generated_files`] byte for byte
//! (regenerate with `COSURG_REGENERATE=1 cargo test -p cosurg-sim-scene regenerate -- --ignored`).
//!
//! # Geometry of the cholecystectomy scene
//! Axes: +x is the organ's long axis (right lobe at +x), +y posterior (back), −y anterior (front), +z up (cranial side of the liver, toward the
//! diaphragm). The liver is a superellipsoid-like solid ≈ 0.20 × 0.15 × 0.075 m, thicker
//! at its right lobe and at its back, thinning toward its anterior edge. The pear-shaped
//! gallbladder (≈ 8 cm long, 3 cm wide) lies under the right lobe, half sunk into it, its
//! fundus at the anterior edge, its neck pointing up and back toward the hilum.
//!
//! The engine simulates one lattice, so the organ is ONE body whose mesh (`liver.obj`) is
//! the smooth union of liver and gallbladder; the gallbladder (`gallbladder.obj`) is an
//! inclusion of softer material inside it, and the cystic duct and artery are capsule
//! inclusions of stiffer material.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};

pub mod bodies;

use crate::mesh::TriMesh;
use crate::scene::{LoadedScene, Scene};
use crate::script::{ToolPose, ToolScript, ToolWaypoint};

/// `scenes/cantilever.toml`.
pub const CANTILEVER_TOML: &str = include_str!("../../scenes/cantilever.toml");
/// `scenes/cholecystectomy.toml`.
pub const CHOLECYSTECTOMY_TOML: &str = include_str!("../../scenes/cholecystectomy.toml");
/// `scenes/meshes/liver.obj`.
pub const LIVER_OBJ: &str = include_str!("../../scenes/meshes/liver.obj");
/// `scenes/meshes/gallbladder.obj`.
pub const GALLBLADDER_OBJ: &str = include_str!("../../scenes/meshes/gallbladder.obj");
/// `scenes/scripts/grasp_lift.toml`.
pub const GRASP_LIFT_TOML: &str = include_str!("../../scenes/scripts/grasp_lift.toml");
/// `scenes/scripts/probe_dissect.toml`.
pub const PROBE_DISSECT_TOML: &str = include_str!("../../scenes/scripts/probe_dissect.toml");

/// `scenes/cholecystectomy-bodies.toml`.
pub const CHOLECYSTECTOMY_BODIES_TOML: &str =
    include_str!("../../scenes/cholecystectomy-bodies.toml");
/// The bodies scene's generated files (meshes and scripts), by path relative to `scenes/`.
const BODIES_FILES: &[(&str, &str)] = &[
    (
        "meshes/bodies/liver.obj",
        include_str!("../../scenes/meshes/bodies/liver.obj"),
    ),
    (
        "meshes/bodies/gallbladder.obj",
        include_str!("../../scenes/meshes/bodies/gallbladder.obj"),
    ),
    (
        "meshes/bodies/cystic_duct.obj",
        include_str!("../../scenes/meshes/bodies/cystic_duct.obj"),
    ),
    (
        "meshes/bodies/cystic_artery.obj",
        include_str!("../../scenes/meshes/bodies/cystic_artery.obj"),
    ),
    (
        "scripts/bodies_grasp_lift.toml",
        include_str!("../../scenes/scripts/bodies_grasp_lift.toml"),
    ),
    (
        "scripts/bodies_hook_dissect.toml",
        include_str!("../../scenes/scripts/bodies_hook_dissect.toml"),
    ),
    (
        "scripts/bodies_clip_duct.toml",
        include_str!("../../scenes/scripts/bodies_clip_duct.toml"),
    ),
    (
        "scripts/bodies_second_clip.toml",
        include_str!("../../scenes/scripts/bodies_second_clip.toml"),
    ),
    (
        "scripts/bodies_cut_duct.toml",
        include_str!("../../scenes/scripts/bodies_cut_duct.toml"),
    ),
];

/// Names accepted by [`by_name`]; the first is the default scene.
pub const NAMES: &[&str] = &["cholecystectomy-bodies", "cholecystectomy", "cantilever"];

/// The default scene ([`NAMES`]`[0]`): the cholecystectomy with separate bodies, where the
/// gallbladder is lifted, dissected from the liver, clipped and divided.
pub fn default_scene() -> LoadedScene {
    cholecystectomy_bodies()
}

/// A built-in scene's file by its path relative to `scenes/` (meshes, scripts), e.g.
/// `scripts/bodies_second_clip.toml`.
pub fn embedded_file(rel: &str) -> Option<&'static str> {
    embedded(Path::new(rel))
}

/// Embedded files by their path relative to `scenes/`.
fn embedded(rel: &Path) -> Option<&'static str> {
    Some(match rel.to_str()? {
        "meshes/liver.obj" => LIVER_OBJ,
        "meshes/gallbladder.obj" => GALLBLADDER_OBJ,
        "scripts/grasp_lift.toml" => GRASP_LIFT_TOML,
        "scripts/probe_dissect.toml" => PROBE_DISSECT_TOML,
        other => {
            return BODIES_FILES
                .iter()
                .find(|(p, _)| *p == other)
                .map(|(_, t)| *t);
        }
    })
}

fn load_embedded(name: &str, text: &str) -> LoadedScene {
    Scene::from_parts(text, &format!("builtin:{name}"), &mut |rel: &Path| {
        embedded(rel).map(|s| s.as_bytes().to_vec()).ok_or_else(|| {
            (
                rel.to_path_buf(),
                std::io::Error::new(std::io::ErrorKind::NotFound, "not embedded"),
            )
        })
    })
    .unwrap_or_else(|e| panic!("built-in scene {name} is invalid: {e}"))
}

/// The one-body cholecystectomy: a liver with the gallbladder as a softer inclusion,
/// vessels, two tools (see module docs). The default scene before the bodies scene; the
/// sync benchmarks and the haptics figures are measured on it.
pub fn cholecystectomy() -> LoadedScene {
    load_embedded("cholecystectomy", CHOLECYSTECTOMY_TOML)
}

/// The cholecystectomy with separate bodies: liver and gallbladder joined by the bed's
/// attachment layer, duct and artery to a fixed hilum ([`bodies`]).
pub fn cholecystectomy_bodies() -> LoadedScene {
    load_embedded("cholecystectomy-bodies", CHOLECYSTECTOMY_BODIES_TOML)
}

/// The 0.4 × 0.1 × 0.1 m cantilever beam clamped at x = 0 under gravity.
pub fn cantilever() -> LoadedScene {
    load_embedded("cantilever", CANTILEVER_TOML)
}

/// The cantilever with Young's modulus `young` (Pa) and lattice cell `cell` (m)
/// overridden (for the FEM benchmark); the hash changes accordingly
/// ([`LoadedScene::modify`]).
pub fn cantilever_with(young: f64, cell: f64) -> Result<LoadedScene, crate::SceneError> {
    let mut s = cantilever();
    s.modify(|sc| {
        for m in sc.materials.values_mut() {
            m.young = young;
        }
        for b in &mut sc.bodies {
            b.cell = cell;
        }
    })?;
    Ok(s)
}

/// A built-in scene by name (see [`NAMES`]).
pub fn by_name(name: &str) -> Option<LoadedScene> {
    match name {
        "cholecystectomy" => Some(cholecystectomy()),
        "cantilever" => Some(cantilever()),
        "cholecystectomy-bodies" => Some(cholecystectomy_bodies()),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------------
// Organ geometry
// ---------------------------------------------------------------------------------------

/// Decimals written to the generated OBJ files (10 µm).
pub const OBJ_DECIMALS: usize = 5;

/// Liver semi-axes (m): x, y and the largest half-thickness.
const LIVER_A: f64 = 0.10;
const LIVER_B: f64 = 0.075;

/// The gallbladder's axis and profile.
#[derive(Debug, Clone, Copy)]
pub struct Gallbladder {
    /// Fundus pole (m).
    pub fundus: Vector3<f64>,
    /// Neck pole (m).
    pub neck: Vector3<f64>,
    /// Largest radius (m).
    pub max_radius: f64,
}

/// The gallbladder of the built-in scene.
pub fn gallbladder() -> Gallbladder {
    Gallbladder {
        fundus: Vector3::new(0.035, -0.074, -0.032),
        neck: Vector3::new(0.027, 0.004, -0.014),
        max_radius: 0.015,
    }
}

impl Gallbladder {
    /// Unit axis from fundus to neck.
    pub fn axis(&self) -> Vector3<f64> {
        (self.neck - self.fundus).normalize()
    }
    /// Length (m).
    pub fn length(&self) -> f64 {
        (self.neck - self.fundus).norm()
    }
    fn shape(s: f64) -> f64 {
        (std::f64::consts::PI * s).sin().max(0.0).sqrt() * (1.0 - 0.55 * s)
    }
    /// Radius (m) at axial parameter `s` ∈ [0, 1] (0 = fundus, 1 = neck): pear-shaped,
    /// widest at s ≈ 0.37.
    pub fn radius(&self, s: f64) -> f64 {
        // max of shape() on [0, 1], found once by sampling (deterministic).
        static MAX: std::sync::OnceLock<f64> = std::sync::OnceLock::new();
        let max = *MAX.get_or_init(|| {
            (0..=1000)
                .map(|i| Self::shape(i as f64 / 1000.0))
                .fold(0.0, f64::max)
        });
        self.max_radius * Self::shape(s.clamp(0.0, 1.0)) / max
    }
    /// A unit vector perpendicular to the axis, pointing as much downward (−z) as possible:
    /// the direction of the gallbladder's exposed underside.
    pub fn down(&self) -> Vector3<f64> {
        let u = self.axis();
        let d = -Vector3::z();
        (d - u * u.dot(&d)).normalize()
    }
    /// Orthonormal frame (e1, e2) with e1 × e2 = axis, e1 = [`down`](Self::down).
    fn frame(&self) -> (Vector3<f64>, Vector3<f64>) {
        let e1 = self.down();
        let e2 = self.axis().cross(&e1);
        (e1, e2)
    }
    /// Surface point at axial parameter `s` in unit radial direction `dir` (⊥ axis).
    pub fn surface_point(&self, s: f64, dir: &Vector3<f64>) -> Vector3<f64> {
        self.fundus + self.axis() * (s * self.length()) + dir * self.radius(s)
    }
    /// Approximate signed distance (m, negative inside).
    fn distance(&self, p: &Vector3<f64>) -> f64 {
        let u = self.axis();
        let l = self.length();
        let w = p - self.fundus;
        let sl = w.dot(&u);
        if sl <= 0.0 {
            w.norm()
        } else if sl >= l {
            (p - self.neck).norm()
        } else {
            (w - u * sl).norm() - self.radius(sl / l)
        }
    }
    /// Closed, outward surface of revolution: `rings` rings of `segments` vertices plus
    /// two poles; rings are denser toward the poles.
    pub fn mesh(&self, rings: usize, segments: usize) -> TriMesh {
        let (e1, e2) = self.frame();
        let mut m = TriMesh::default();
        m.vertices.push(self.fundus);
        for i in 1..rings + 1 {
            let s = 0.5 * (1.0 - (std::f64::consts::PI * i as f64 / (rings + 1) as f64).cos());
            for j in 0..segments {
                let th = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
                let dir = e1 * th.cos() + e2 * th.sin();
                m.vertices.push(self.surface_point(s, &dir));
            }
        }
        m.vertices.push(self.neck);
        stitch_rings(&mut m, rings, segments);
        m
    }
}

/// Half-thickness (m) of the liver at (x, y): thick right lobe (+x) and back (+y).
fn liver_half_thickness(x: f64, y: f64) -> f64 {
    let right = 0.5 + 0.5 * (x / 0.04).tanh();
    (0.022 + 0.018 * right) * (0.8 + 0.2 * (y / LIVER_B).clamp(-1.0, 1.0))
}

/// Approximate signed distance (m) of the liver lobe: a superellipsoid (exponent 2.5)
/// with varying thickness and a slightly domed top.
fn liver_distance(p: &Vector3<f64>) -> f64 {
    let c = liver_half_thickness(p.x, p.y);
    let dome = 0.004 * (1.0 - (p.x / LIVER_A).powi(2)).max(0.0);
    let e = 2.5;
    let f = ((p.x / LIVER_A).abs().powf(e)
        + (p.y / LIVER_B).abs().powf(e)
        + ((p.z - dome) / c).abs().powf(e))
    .powf(1.0 / e)
        - 1.0;
    f * c
}

fn smooth_min(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

/// Signed distance (approximate, m) of the organ: smooth union of liver and gallbladder.
pub fn organ_distance(p: &Vector3<f64>) -> f64 {
    smooth_min(liver_distance(p), gallbladder().distance(p), 0.01)
}

/// Unit icosphere subdivided `level` times (outward triangles).
/// Triangles of a closed tube-like surface whose vertices are: one cap (index 0), `rings`
/// rings of `segments` vertices each, then the other cap (the last vertex). Outward when the
/// rings run from the first cap to the second and each ring turns anticlockwise seen from
/// the first cap.
fn stitch_rings(m: &mut TriMesh, rings: usize, segments: usize) {
    let last = (m.vertices.len() - 1) as u32;
    let v = |i: usize, j: usize| (1 + i * segments + j % segments) as u32;
    for j in 0..segments {
        m.triangles.push([0, v(0, j + 1), v(0, j)]);
    }
    for i in 0..rings - 1 {
        for j in 0..segments {
            let (a, b, c, d) = (v(i, j), v(i, j + 1), v(i + 1, j + 1), v(i + 1, j));
            m.triangles.push([a, b, c]);
            m.triangles.push([a, c, d]);
        }
    }
    for j in 0..segments {
        m.triangles
            .push([last, v(rings - 1, j), v(rings - 1, j + 1)]);
    }
}

fn icosphere(level: usize) -> TriMesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut m = TriMesh {
        vertices: [
            [-1.0, t, 0.0],
            [1.0, t, 0.0],
            [-1.0, -t, 0.0],
            [1.0, -t, 0.0],
            [0.0, -1.0, t],
            [0.0, 1.0, t],
            [0.0, -1.0, -t],
            [0.0, 1.0, -t],
            [t, 0.0, -1.0],
            [t, 0.0, 1.0],
            [-t, 0.0, -1.0],
            [-t, 0.0, 1.0],
        ]
        .iter()
        .map(|v| Vector3::from(*v).normalize())
        .collect(),
        triangles: vec![
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ],
    };
    for _ in 0..level {
        let mut mid: BTreeMap<(u32, u32), u32> = BTreeMap::new();
        let mut tris = Vec::with_capacity(m.triangles.len() * 4);
        for tri in &m.triangles {
            let mut e = [0u32; 3];
            for k in 0..3 {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                let key = (a.min(b), a.max(b));
                e[k] = *mid.entry(key).or_insert_with(|| {
                    let p = (m.vertices[a as usize] + m.vertices[b as usize]).normalize();
                    m.vertices.push(p);
                    (m.vertices.len() - 1) as u32
                });
            }
            tris.push([tri[0], e[0], e[2]]);
            tris.push([tri[1], e[1], e[0]]);
            tris.push([tri[2], e[2], e[1]]);
            tris.push([e[0], e[1], e[2]]);
        }
        m.triangles = tris;
    }
    m
}

/// Organ surface: an icosphere (level 4: 2562 vertices, 5120 triangles) whose vertices are
/// mapped to rays from a centre and projected onto the
/// farthest zero crossing of [`organ_distance`] along each ray. The result is closed and
/// outward by construction (a radial graph over the sphere).
fn organ_mesh() -> TriMesh {
    radial_mesh(&organ_distance)
}

/// The surface of the solid `distance < 0` around the organ's centre, as [`organ_mesh`].
fn radial_mesh(distance: &dyn Fn(&Vector3<f64>) -> f64) -> TriMesh {
    // A centre inside the liver above the gallbladder (chosen to minimise the longest
    // edge: rays should not graze the surface); rays aim at evenly spread points of an
    // ellipsoid of the liver's proportions.
    let centre = Vector3::new(0.02, -0.025, -0.01);
    let stretch = Vector3::new(LIVER_A, LIVER_B, 0.04);
    let mut m = icosphere(4);
    let step = 0.0005;
    for v in &mut m.vertices {
        let d = (v.component_mul(&stretch) - centre).normalize();
        // march outward, remembering the last inside sample
        let mut last_inside = 0.0;
        let mut r = 0.0;
        while r < 0.25 {
            if distance(&(centre + d * r)) <= 0.0 {
                last_inside = r;
            }
            r += step;
        }
        let (mut lo, mut hi) = (last_inside, last_inside + step);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if distance(&(centre + d * mid)) <= 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        *v = centre + d * (0.5 * (lo + hi));
    }
    m
}

/// The generated organ meshes.
#[derive(Debug, Clone)]
pub struct OrganMeshes {
    /// Union surface of liver and gallbladder (the body).
    pub liver: TriMesh,
    /// The gallbladder (an inclusion).
    pub gallbladder: TriMesh,
}

/// Rounds every coordinate to [`OBJ_DECIMALS`] and numbers vertices by first use, as the
/// shipped files are read back.
fn rounded(mut m: TriMesh) -> TriMesh {
    let f = 10f64.powi(OBJ_DECIMALS as i32);
    for v in &mut m.vertices {
        *v = v.map(|c| (c * f).round() / f);
    }
    m.renumbered_by_first_use()
}

/// Computes the organ meshes (deterministic; coordinates rounded to [`OBJ_DECIMALS`]).
pub fn generate_organ_meshes() -> OrganMeshes {
    static CACHE: std::sync::OnceLock<OrganMeshes> = std::sync::OnceLock::new();
    CACHE
        .get_or_init(|| OrganMeshes {
            liver: rounded(organ_mesh()),
            gallbladder: rounded(gallbladder().mesh(24, 24)),
        })
        .clone()
}

fn obj_text(m: &TriMesh, header: &str) -> String {
    let mut out = Vec::new();
    m.write_obj_to(&mut out, OBJ_DECIMALS, header)
        .expect("writing to memory");
    String::from_utf8(out).expect("ascii")
}

/// Direction mapping tool-local −z (the pointing direction) onto `tip_dir`.
fn pointing(tip_dir: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(&-Vector3::z(), tip_dir).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    })
}

fn waypoint(
    t: f64,
    position: Vector3<f64>,
    q: UnitQuaternion<f64>,
    jaw: f64,
    label: &str,
) -> ToolWaypoint {
    ToolWaypoint {
        t,
        pose: ToolPose {
            position,
            orientation: q,
            jaw,
        },
        label: (!label.is_empty()).then(|| label.to_string()),
    }
}

/// Jaw opening (rad) of an open forceps in the scripts.
pub const JAW_OPEN: f64 = 0.6;

/// The two tool scripts: (`grasp_lift`, `probe_dissect`), computed from the gallbladder.
pub fn generate_scripts() -> (ToolScript, ToolScript) {
    let gb = gallbladder();
    let u = gb.axis();
    // grasp_lift: the forceps comes along the gallbladder axis toward the fundus (from the
    // front and below), closes 6 mm inside the fundus, lifts 3 cm, holds, releases,
    // withdraws.
    let q = pointing(&u);
    let grasp = gb.fundus + u * 0.006;
    let start = gb.fundus - u * 0.04;
    let lift = Vector3::new(0.0, 0.0, 0.03);
    let mut g = ToolScript {
        title: Some("forceps grasps the gallbladder fundus, lifts it 3 cm, releases".into()),
        ..Default::default()
    };
    g.tracks.insert(
        "forceps".into(),
        vec![
            waypoint(
                0.0,
                start,
                q,
                JAW_OPEN,
                "approach the fundus with open jaws",
            ),
            waypoint(1.5, grasp, q, JAW_OPEN, ""),
            waypoint(2.0, grasp, q, 0.0, "close the jaws on the fundus"),
            waypoint(3.0, grasp + lift, q, 0.0, "lift 3 cm"),
            waypoint(4.5, grasp + lift, q, 0.0, "hold"),
            waypoint(5.0, grasp + lift, q, JAW_OPEN, "release"),
            waypoint(6.0, start + lift, q, JAW_OPEN, "withdraw"),
        ],
    );
    // probe_dissect: the probe comes from below, presses 5 mm into the underside near the
    // neck and slides along the gallbladder toward its body, following the surface.
    let e = gb.down();
    let q = pointing(&-e);
    let press = 0.005;
    let mut track = vec![waypoint(
        0.0,
        gb.surface_point(0.85, &e) + e * 0.03,
        q,
        0.0,
        "approach the neck from below",
    )];
    track.push(waypoint(
        1.0,
        gb.surface_point(0.85, &e) + e * 0.001,
        q,
        0.0,
        "touch",
    ));
    track.push(waypoint(
        1.5,
        gb.surface_point(0.85, &e) - e * press,
        q,
        0.0,
        "press 5 mm",
    ));
    for (i, s) in [0.75, 0.65, 0.55, 0.45].iter().enumerate() {
        track.push(waypoint(
            2.0 + i as f64 * 0.75,
            gb.surface_point(*s, &e) - e * press,
            q,
            0.0,
            if i == 0 {
                "slide along the gallbladder"
            } else {
                ""
            },
        ));
    }
    track.push(waypoint(
        5.0,
        gb.surface_point(0.45, &e) + e * 0.03,
        q,
        0.0,
        "withdraw",
    ));
    let mut p = ToolScript {
        title: Some("probe presses near the gallbladder neck and slides along it".into()),
        ..Default::default()
    };
    p.tracks.insert("probe".into(), track);
    (g, p)
}

/// Every generated file as (path relative to `scenes/`, content).
pub fn generated_files() -> Vec<(PathBuf, String)> {
    let m = generate_organ_meshes();
    let (g, p) = generate_scripts();
    let note = "generated by cosurg_sim_scene::builtin::generate_organ_meshes; do not edit";
    let mut files: Vec<(PathBuf, String)> = vec![
        (
            "meshes/liver.obj".into(),
            obj_text(
                &m.liver,
                &format!("liver with gallbladder (union surface), metres\n{note}"),
            ),
        ),
        (
            "meshes/gallbladder.obj".into(),
            obj_text(&m.gallbladder, &format!("gallbladder, metres\n{note}")),
        ),
        ("scripts/grasp_lift.toml".into(), g.to_toml()),
        ("scripts/probe_dissect.toml".into(), p.to_toml()),
    ];
    let note = "generated by cosurg_sim_scene::builtin::bodies; do not edit";
    let names = ["liver", "gallbladder", "cystic duct", "cystic artery"];
    for ((file, _), (mesh, name)) in BODIES_FILES
        .iter()
        .zip(bodies::meshes().into_iter().zip(names))
    {
        files.push((
            PathBuf::from(file),
            obj_text(
                &rounded(mesh),
                &format!("{name} (cholecystectomy-bodies), metres\n{note}"),
            ),
        ));
    }
    let s = bodies::scripts();
    files.push(("scripts/bodies_grasp_lift.toml".into(), s.forceps.to_toml()));
    files.push(("scripts/bodies_hook_dissect.toml".into(), s.hook.to_toml()));
    files.push(("scripts/bodies_clip_duct.toml".into(), s.clip.to_toml()));
    files.push((
        "scripts/bodies_second_clip.toml".into(),
        s.second_clip.to_toml(),
    ));
    files.push(("scripts/bodies_cut_duct.toml".into(), s.blade.to_toml()));
    files
}

/// Writes [`generated_files`] under `scenes_dir`.
pub fn write_generated_files(scenes_dir: &Path) -> std::io::Result<()> {
    for (rel, text) in generated_files() {
        let path = scenes_dir.join(rel);
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d)?;
        }
        std::fs::write(&path, text)?;
        tracing::info!(file = %path.display(), "written");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{BodyShape, InclusionShape};

    fn scenes_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes")
    }

    /// `COSURG_REGENERATE=1 cargo test -p cosurg-sim-scene regenerate -- --ignored`
    #[test]
    #[ignore]
    fn regenerate() {
        if std::env::var_os("COSURG_REGENERATE").is_some() {
            write_generated_files(&scenes_dir()).unwrap();
        }
    }

    #[test]
    fn shipped_files_equal_generator_output() {
        for (rel, text) in generated_files() {
            let shipped = std::fs::read_to_string(scenes_dir().join(&rel)).unwrap();
            assert!(
                shipped == text,
                "scenes/{} differs from the generator's output; regenerate (see module docs)",
                rel.display()
            );
            let embedded = embedded(&rel).unwrap();
            assert_eq!(embedded, text, "embedded copy of {}", rel.display());
        }
    }

    #[test]
    fn generated_meshes_are_closed_outward_and_sized() {
        let m = generate_organ_meshes();
        for (name, mesh) in [("liver", &m.liver), ("gallbladder", &m.gallbladder)] {
            assert!(mesh.is_closed(), "{name} closed");
            assert!(mesh.is_consistently_oriented(), "{name} consistent");
            assert!(mesh.is_outward_oriented(), "{name} outward");
        }
        let bb = m.liver.bounding_box().unwrap();
        let s = bb.size();
        assert!((0.18..0.22).contains(&s.x), "{s:?}");
        assert!((0.13..0.17).contains(&s.y), "{s:?}");
        assert!((0.07..0.10).contains(&s.z), "{s:?}");
        assert!((2000..10000).contains(&m.liver.triangles.len()));
        let g = m.gallbladder.bounding_box().unwrap();
        let gb = gallbladder();
        assert!((gb.length() - 0.08).abs() < 0.003, "{}", gb.length());
        let width = (0..=100)
            .map(|i| 2.0 * gb.radius(i as f64 / 100.0))
            .fold(0.0, f64::max);
        assert!((width - 0.03).abs() < 1e-4, "{width}");
        // the gallbladder hangs below the liver's mid-plane and mostly inside the union
        assert!(g.min.z < -0.035, "{g:?}");
        let inside = m
            .gallbladder
            .vertices
            .iter()
            .filter(|v| {
                let v = **v;
                let c = v + (gb.fundus + gb.axis() * 0.4 * gb.length() - v) * 0.05;
                m.liver.contains(&c)
            })
            .count();
        assert!(
            inside as f64 > 0.9 * m.gallbladder.vertices.len() as f64,
            "{inside}"
        );
        // triangle quality: no degenerate triangles after rounding
        for t in &m.liver.triangles {
            let [a, b, c] = t.map(|i| m.liver.vertices[i as usize]);
            assert!((b - a).cross(&(c - a)).norm() > 1e-8);
        }
    }

    #[test]
    fn builtin_scenes_load_and_match_files() {
        for name in NAMES {
            let b = by_name(name).unwrap();
            let f = Scene::load(scenes_dir().join(format!("{name}.toml"))).unwrap();
            assert_eq!(b.scene, f.scene);
            assert_eq!(
                b.hash, f.hash,
                "{name}: same hash from embedded and shipped files"
            );
            assert_eq!(b.meshes, f.meshes);
            assert_eq!(b.file, format!("builtin:{name}"));
        }
        assert!(by_name("nope").is_none());
        let o = cantilever_with(5e5, 0.05).unwrap();
        assert_eq!(o.scene.materials["tissue"].young, 5e5);
        assert_eq!(o.scene.bodies[0].cell, 0.05);
        assert_ne!(o.hash, cantilever().hash);
        let e = cantilever_with(-1.0, 0.05).unwrap_err().to_string();
        assert_eq!(
            e,
            "builtin:cantilever: `material.tissue.young`: must be positive and finite, got -1 Pa"
        );
        let c = cantilever();
        let body = &c.scene.bodies[0];
        assert_eq!(body.cell, 0.025);
        assert_eq!(body.max_depth, 3);
        let mat = c.scene.body_material(body);
        assert_eq!((mat.young, mat.poisson, mat.density), (1e5, 0.45, 1000.0));
        assert_eq!(c.scene.probes[0].point, Vector3::new(0.4, 0.05, 0.05));
        assert!(c.scene.loads.is_empty());
        assert_eq!(c.scene.gravity, Vector3::new(0.0, 0.0, -9.81));
    }

    #[test]
    fn cholecystectomy_is_consistent() {
        let c = cholecystectomy();
        let s = &c.scene;
        assert_eq!(s.bodies.len(), 1);
        let body = &s.bodies[0];
        let BodyShape::Mesh(mesh) = body.shape() else {
            panic!("organ is a mesh body")
        };
        let organ = &c.meshes[mesh];
        let bb = organ.bounding_box().unwrap();
        // 1–3k root tets: 6 per cube of the lattice covering the bounding box
        let cubes: f64 = (0..3).map(|k| (bb.size()[k] / body.cell).ceil()).product();
        let tets = 6.0 * cubes;
        assert!((1000.0..=3000.0).contains(&tets), "{tets} root tets");
        let liver_e = s.body_material(body).young;
        let mut saw_capsules = 0;
        for inc in &body.inclusions {
            let e = s.materials[&inc.material].young;
            match inc.shape() {
                InclusionShape::Mesh(m) => {
                    assert!(e < liver_e, "gallbladder softer");
                    assert!(inc.refine_boundary);
                    assert!(c.meshes[m].is_outward_oriented());
                }
                InclusionShape::Capsules(caps) => {
                    saw_capsules += 1;
                    assert!(
                        (10.0..=20.0).contains(&(e / liver_e)),
                        "vessels 10–20× stiffer"
                    );
                    for cap in caps {
                        assert!(
                            organ.contains(&cap.a) && organ.contains(&cap.b),
                            "{cap:?} inside organ"
                        );
                    }
                }
            }
        }
        assert!(saw_capsules >= 2);
        // the fix box holds the upper part of the organ, above the gallbladder
        let f = &s.fixes[0].region;
        assert!(f.min.z >= bb.center().z - 0.01, "{f:?}");
        assert!(
            gallbladder()
                .mesh(8, 8)
                .vertices
                .iter()
                .all(|v| !f.contains(v))
        );
        let held = organ.vertices.iter().filter(|v| f.contains(v)).count();
        assert!(held > 20, "{held}");
        assert!(s.features.adaptivity && s.features.contact && s.features.rotation_sharing);
        // tools start where their scripts start; scripts move near the gallbladder
        let gb = gallbladder();
        for t in &s.tools {
            let script = &c.scripts[&t.name];
            let p0 = script.sample(&t.name, 0.0).unwrap();
            assert!((p0.position - t.position).norm() < 1e-5, "{}", t.name);
            assert!(p0.orientation.angle_to(&t.rotation()) < 1e-5, "{}", t.name);
            assert!(
                !organ.contains(&t.position),
                "{} starts outside the organ",
                t.name
            );
        }
        let (g, p) = generate_scripts();
        assert!((5.5..=6.5).contains(&g.duration()));
        let fk = &g.tracks["forceps"];
        let grasp = fk.iter().find(|k| k.pose.jaw == 0.0).unwrap();
        assert!(
            c.meshes[Path::new("meshes/gallbladder.obj")].contains(&grasp.pose.position),
            "grasp point inside the gallbladder"
        );
        let lifted = fk
            .iter()
            .filter(|k| k.pose.jaw == 0.0)
            .map(|k| k.pose.position.z)
            .fold(f64::MIN, f64::max);
        assert!((lifted - grasp.pose.position.z - 0.03).abs() < 1e-9);
        assert!(fk.last().unwrap().pose.jaw > 0.0, "released");
        let pk = &p.tracks["probe"];
        let pressed: Vec<_> = pk
            .iter()
            .filter(|k| gb.distance(&k.pose.position) < -0.004)
            .collect();
        assert_eq!(
            pressed.len(),
            5,
            "probe presses 5 mm into the gallbladder along its path"
        );
        for k in pressed {
            assert!(organ.contains(&k.pose.position));
        }
        assert!(
            !organ.contains(&pk[0].pose.position)
                && !organ.contains(&pk.last().unwrap().pose.position)
        );
    }
}
