use super::*;
use sim_core::SimOptions;
use sim_core::sim_scene::builtin;

fn sim() -> Simulation {
    let scene = builtin::cholecystectomy();
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).expect("built-in scene builds")
}

#[test]
fn frame_of_the_builtin_scene() {
    let sim = sim();
    let interaction = Interaction::new(&sim);
    let mut builder = FrameBuilder::new(&sim).unwrap();
    let frame = builder.build(&sim, Some(&interaction), true, HudInfo::default());

    // counts: every surface vertex and triangle of the simulation, in order
    let nv: usize = sim.surfaces().iter().map(|s| s.rest.vertices.len()).sum();
    let nt: usize = sim.surfaces().iter().map(|s| s.rest.triangles.len()).sum();
    assert_eq!(frame.positions.len(), nv);
    assert_eq!(frame.topology.vertex_tissue.len(), nv);
    assert_eq!(frame.topology.triangles.len(), nt);
    assert!(
        frame
            .topology
            .triangles
            .iter()
            .flatten()
            .all(|&i| (i as usize) < nv)
    );
    assert_eq!(frame.positions[..], sim.surfaces()[0].deformed[..]);

    // bounds: the organ mesh's own bounding box (at t = 0 the surface is at rest,
    // interpolation reproduces it to rounding)
    let (lo, hi) = frame.surface_bounds().unwrap();
    let rest = sim.surfaces()[0].rest.bounding_box().unwrap();
    assert!((lo - rest.min).amax() < 1e-9 && (hi - rest.max).amax() < 1e-9);

    // tools: both scene tools, local, at their scene positions
    let names: Vec<_> = frame.tools.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["forceps", "probe"]);
    for (t, spec) in frame.tools.iter().zip(&sim.scene().scene.tools) {
        assert!(t.site.is_none());
        assert!((t.pose.translation.vector - spec.position).norm() < 1e-12);
        // shaft starts at the hinge (tip + length along the tool axis)
        let axis = t.pose.rotation * Vector3::z();
        let hinge = spec.position + axis * spec.length;
        assert!((t.shaft.a - hinge).norm() < 1e-12);
        assert!(((t.shaft.b - t.shaft.a).norm() - SHAFT_LENGTH).abs() < 1e-12);
    }
    assert_eq!(frame.tools[0].parts.len(), 2, "forceps have two jaws");
    assert_eq!(frame.tools[1].parts.len(), 1, "the probe is one rod");

    // vessels: the two capsule inclusions have two capsules each, at rest
    assert_eq!(frame.vessels.len(), 4);
    let caps: Vec<_> = sim.scene().scene.bodies[0]
        .inclusions
        .iter()
        .filter_map(|i| i.capsules.clone())
        .flatten()
        .collect();
    for ((seg, r), c) in frame.vessels.iter().zip(&caps) {
        assert!((seg.a - c.a).norm() < 1e-9 && (seg.b - c.b).norm() < 1e-9);
        assert_eq!(*r, c.radius);
    }

    // lattice: every leaf's six edges, once each; levels within the scene's depth
    let edges = frame.lattice.as_ref().unwrap();
    let mut pairs = std::collections::BTreeSet::new();
    for &t in sim.lattice().leaves() {
        let n = sim.lattice().tet_nodes(t);
        for (i, j) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
            pairs.insert((n[i].0.min(n[j].0), n[i].0.max(n[j].0)));
        }
    }
    assert_eq!(edges.len(), pairs.len());
    let max_depth = sim.scene().scene.bodies[0].max_depth as u8;
    assert!(edges.iter().all(|e| e.level <= max_depth));
    assert!(edges.iter().any(|e| e.level == 0));
    assert!(
        edges.iter().any(|e| e.level > 0),
        "inclusion boundaries are refined"
    );

    // without asking, no wireframe
    let plain = builder.build(&sim, Some(&interaction), false, HudInfo::default());
    assert!(plain.lattice.is_none());
}

#[test]
fn tissues_follow_the_inclusions() {
    let sim = sim();
    let builder = FrameBuilder::new(&sim).unwrap();
    let topo = builder.topology();
    let gb = sim.scene().meshes[std::path::Path::new("meshes/gallbladder.obj")].clone();
    let surface = &sim.surfaces()[0].rest;
    let nearest_gb = |p: &V3| {
        gb.vertices
            .iter()
            .map(|q| (q - p).norm())
            .fold(f64::INFINITY, f64::min)
    };
    let mut counts = std::collections::HashMap::new();
    for (p, t) in surface.vertices.iter().zip(&topo.vertex_tissue) {
        *counts.entry(*t).or_insert(0usize) += 1;
        match t {
            // a gallbladder-coloured vertex lies on the gallbladder (within about one
            // edge of its mesh: the union mesh is sampled independently)
            TissueKind::Gallbladder => assert!(nearest_gb(p) < 0.008, "{p:?}"),
            // and a vertex well away from the gallbladder is not coloured as it
            TissueKind::Parenchyma => {}
            TissueKind::Vessel => {}
        }
        if nearest_gb(p) > 0.02 {
            assert_ne!(*t, TissueKind::Gallbladder);
        }
    }
    let n = surface.vertices.len() as f64;
    let gb_share = counts[&TissueKind::Gallbladder] as f64 / n;
    let liver_share = counts[&TissueKind::Parenchyma] as f64 / n;
    // independent estimate: the organ vertices lying on the gallbladder's own mesh
    // (within 2 mm of one of its vertices, about a third of its edge length)
    let near = surface
        .vertices
        .iter()
        .filter(|p| nearest_gb(p) < 0.002)
        .count() as f64
        / n;
    eprintln!("gallbladder share {gb_share:.4}, vertices near its mesh {near:.4}");
    assert!(gb_share > 0.01, "gallbladder share {gb_share}");
    assert!(
        gb_share > 0.5 * near && gb_share < 2.0 * near,
        "gallbladder share {gb_share} vs {near} near its mesh"
    );
    assert!(liver_share > 0.5, "liver share {liver_share}");
}

#[test]
fn default_port_looks_at_the_organ() {
    let mut scene = builtin::cholecystectomy();
    scene.scene.camera = None;
    let port = port_of(&scene);
    let bounds = scene.body_bounds(0).unwrap();
    assert!((port.target - bounds.center()).norm() < 1e-12);
    assert!((port.position - port.target - V3::new(0.0, -0.25, -0.15)).norm() < 1e-12);
    // the built-in scene sets its own port
    let builtin = builtin::cholecystectomy();
    let cam = builtin
        .scene
        .camera
        .as_ref()
        .expect("built-in scene has a [camera]");
    assert_eq!(port_of(&builtin).position, cam.position);
}

#[test]
fn the_slot_hands_over_the_latest_frame() {
    let sim = sim();
    let mut builder = FrameBuilder::new(&sim).unwrap();
    let mut hud = HudInfo::default();
    let slot = ViewSlot::new(builder.build(&sim, None, false, hud.clone()));
    let reader = slot.clone();
    hud.sim_time = 1.5;
    let held = reader.latest();
    slot.publish(builder.build(&sim, None, false, hud));
    // a reader keeps the frame it holds; the next read sees the new one
    assert_eq!(held.hud.sim_time, 0.0);
    assert_eq!(reader.latest().hud.sim_time, 1.5);
    assert!(!reader.wants_lattice());
    slot.set_wants_lattice(true);
    assert!(reader.wants_lattice());
}
