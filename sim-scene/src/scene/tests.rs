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
fn model_names_are_sim_fem_s_and_nonlinear_is_an_alias() {
    for (name, model) in [
        ("linear", Model::Linear),
        ("corotational", Model::Corotational),
        ("stvk", Model::StVK),
        ("nonlinear", Model::StVK),
    ] {
        let l = load(&format!("{EXAMPLE}\n[simulation]\nmodel = \"{name}\"\n")).unwrap();
        assert_eq!(l.scene.simulation.model, model, "{name}");
        // Written back under its one name.
        let text = l.scene.to_toml();
        assert!(
            text.contains(&format!("model = \"{}\"", model.name())),
            "{name}: {text}"
        );
        assert_eq!(Scene::parse(&text, "re.toml").unwrap(), l.scene);
    }
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
solver = "mg-pcg"
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
    assert_eq!(
        s.simulation.model,
        Model::StVK,
        "`nonlinear` is read as `stvk`"
    );
    assert_eq!(s.simulation.polar, PolarMethod::ShapeMatching);
    assert_eq!(s.simulation.solver, crate::LinearSolver::MgPcg);
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
        e.starts_with("s.toml: `simulation.model`: unknown variant `fancy`, expected one of `linear`, `corotational`, `nonlinear`, `stvk`"),
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
        format!("{sp}: `body[0].mesh`: mixed.obj: mesh triangles are not consistently oriented")
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
    let missing_inc =
        format!("{EXAMPLE}\n[[body.inclusion]]\nmaterial = \"tissue\"\nmesh = \"vessel.stl\"\n");
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

#[test]
fn unknown_linear_solver_is_named() {
    let e = err(&format!("{EXAMPLE}\n[simulation]\nsolver = \"cholesky\"\n"));
    assert!(
        e.starts_with("s.toml: `simulation.solver`: unknown variant `cholesky`, expected one of `jacobi-pcg`, `mg-pcg`, `direct`, `auto`"),
        "{e}"
    );
}

#[test]
fn attachment_parses_and_errors_name_the_key() {
    let layer = r#"
[[body]]
name = "hanging"
box = { min = [0.0, 0.0, -0.2], max = [0.4, 0.1, -0.1] }
cell = 0.025
material = "tissue"

[[attachment]]
name = "layer"
bodies = ["beam", "hanging"]
box = { min = [0.0, 0.0, -0.11], max = [0.4, 0.1, -0.09] }
stiffness = 200.0
reach = 0.12
"#;
    let ok = load(&format!("{EXAMPLE}{layer}")).unwrap();
    let a = &ok.scene.attachments[0];
    assert_eq!(a.bodies, ["beam".to_string(), "hanging".to_string()]);
    assert_eq!((a.stiffness, a.reach), (200.0, 0.12));
    // Defaults: no dissection rate, no threshold, 1 cm reach of the hook.
    assert_eq!(
        (a.release_rate, a.release_force, a.release_radius),
        (0.0, 0.0, 0.01)
    );
    let again = Scene::parse(&ok.scene.to_toml(), "re.toml").unwrap();
    assert_eq!(again, ok.scene);

    let bad = |from: &str, to: &str| err(&format!("{EXAMPLE}{}", layer.replacen(from, to, 1)));
    assert_eq!(
        bad("[\"beam\", \"hanging\"]", "[\"beam\", \"liver\"]"),
        "s.toml: `attachment[0].bodies[1]`: undefined body \"liver\" (defined: [\"beam\", \"hanging\"])"
    );
    assert_eq!(
        bad("[\"beam\", \"hanging\"]", "[\"beam\", \"beam\"]"),
        "s.toml: `attachment[0].bodies`: ties body \"beam\" to itself; name two bodies"
    );
    assert_eq!(
        bad("stiffness = 200.0", "stiffness = -1.0"),
        "s.toml: `attachment[0].stiffness`: must be positive and finite, got -1 N/m"
    );
    assert_eq!(
        bad("reach = 0.12", "reach = 0.12\nrelease_rate = -2.0"),
        "s.toml: `attachment[0].release_rate`: must be non-negative and finite, got -2"
    );
    assert!(bad("reach = 0.12", "reach = 0.12\nspeed = 1.0").contains("speed"));
}
