//! Cutting the shipped `scenes/cut-block.toml`: the blade's sweep separates the block into
//! two parts that swing apart under gravity; mass and rest volume are conserved; the cut
//! surface is closed around each part.

use std::collections::HashMap;
use std::path::PathBuf;

use cosurg_sim_core::sim_scene::{Scene, TriMesh};
use cosurg_sim_core::{Interaction, SimOptions, Simulation};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

fn cut_block() -> Simulation {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenes/cut-block.toml");
    let scene = Scene::load(&path).expect("scenes/cut-block.toml loads");
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).expect("simulation")
}

/// Connected parts of the element graph (copies sharing a degree of freedom), each as its
/// mass-weighted centroid (m) and mass (kg), sorted by centroid x.
fn parts(sim: &mut Simulation) -> Vec<(V3, f64)> {
    let x = sim.positions().to_vec();
    let mass = sim.fem().expect("fem").lumped_mass().to_vec();
    let sep = sim.separation().expect("cut").clone();
    let n = sep.dof_count();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    for c in &sep.copies {
        for k in 1..4 {
            let (a, b) = (find(&mut parent, c.dofs[0]), find(&mut parent, c.dofs[k]));
            parent[a.max(b)] = a.min(b);
        }
    }
    let mut acc: HashMap<usize, (V3, f64)> = HashMap::new();
    let mut used = vec![false; n];
    for c in &sep.copies {
        for d in c.dofs {
            used[d] = true;
        }
    }
    for d in 0..n {
        if used[d] && mass[d] > 0.0 {
            let r = find(&mut parent, d);
            let e = acc.entry(r).or_insert((V3::zeros(), 0.0));
            e.0 += mass[d] * x[d];
            e.1 += mass[d];
        }
    }
    let mut out: Vec<(V3, f64)> = acc.into_values().map(|(s, m)| (s / m, m)).collect();
    out.sort_by(|a, b| a.0.x.total_cmp(&b.0.x));
    out
}

/// Connected components of a triangle mesh (by shared vertices), as separate meshes.
fn components(mesh: &TriMesh) -> Vec<TriMesh> {
    let n = mesh.vertices.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    for t in &mesh.triangles {
        for k in 1..3 {
            let (a, b) = (
                find(&mut parent, t[0] as usize),
                find(&mut parent, t[k] as usize),
            );
            parent[a.max(b)] = a.min(b);
        }
    }
    let mut by_root: HashMap<usize, Vec<[u32; 3]>> = HashMap::new();
    for t in &mesh.triangles {
        by_root
            .entry(find(&mut parent, t[0] as usize))
            .or_default()
            .push(*t);
    }
    by_root
        .into_values()
        .map(|triangles| TriMesh {
            vertices: mesh.vertices.clone(),
            triangles,
        })
        .collect()
}

#[test]
fn blade_cuts_the_block_in_two_parts_that_swing_apart() {
    let mut sim = cut_block();
    let mut interaction = Interaction::new(&sim);
    let mass_before: f64 = sim.fem().unwrap().lumped_mass().iter().sum();
    let volume_before = sim.element_rest_volume();
    // Block 0.12 x 0.04 x 0.04 m at 1000 kg/m^3.
    assert!((volume_before - 0.12 * 0.04 * 0.04).abs() < 1e-12 * volume_before.max(1.0));
    assert!((mass_before - 1000.0 * volume_before).abs() < 1e-9 * mass_before);

    let dt = sim.options().dt;
    let mut cut_at = None;
    let mut at_cut: Vec<(V3, f64)> = Vec::new();
    let steps = (1.8 / dt).round() as usize;
    for _ in 0..steps {
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        let report = interaction
            .before_step(&mut sim, &inputs)
            .expect("before_step");
        if report.cuts > 0 {
            assert!(cut_at.is_none(), "one stroke, one cut");
            cut_at = Some(sim.time());
            at_cut = parts(&mut sim);
        }
        sim.step().expect("step");
    }
    let cut_at = cut_at.expect("the blade's stroke was committed as a cut");
    assert!(
        (0.6..0.75).contains(&cut_at),
        "the blade leaves the block (y = 0.04 m) at 0.65 s; cut at {cut_at}"
    );
    assert_eq!(sim.topology().epoch(), 1);
    assert!(
        sim.positions()
            .iter()
            .all(|p| p.iter().all(|c| c.is_finite())),
        "no NaN"
    );

    // Two parts, each about half the mass, whose centroids moved apart by more than 3 cm
    // (each half swings down from its hinge: from 6 cm apart towards 12 cm).
    assert_eq!(at_cut.len(), 2, "two parts at the cut: {at_cut:?}");
    let end = parts(&mut sim);
    assert_eq!(end.len(), 2, "two parts at the end: {end:?}");
    for (c, m) in &end {
        assert!(
            (m / mass_before - 0.5).abs() < 0.05,
            "part at {c:?} has {m} kg of {mass_before}"
        );
    }
    let gap_at_cut = (at_cut[1].0 - at_cut[0].0).norm();
    let gap_end = (end[1].0 - end[0].0).norm();
    eprintln!("cut at {cut_at} s; centroids {gap_at_cut:.4} m apart then, {gap_end:.4} m at 1.8 s");
    assert!(
        gap_end - gap_at_cut > 0.03,
        "centroids {gap_at_cut} m apart at the cut, {gap_end} m at the end"
    );

    // Mass and rest volume conserved (relative 1e-12: the copies' fractions sum to 1).
    let mass_after: f64 = sim.fem().unwrap().lumped_mass().iter().sum();
    let volume_after = sim.element_rest_volume();
    assert!(
        (mass_after - mass_before).abs() < 1e-12 * mass_before,
        "mass {mass_before} -> {mass_after} kg"
    );
    assert!(
        (volume_after - volume_before).abs() < 1e-12 * volume_before,
        "rest volume {volume_before} -> {volume_after} m^3"
    );

    // The embedded surface is cut and capped: two closed, outward parts, each closing
    // about half the block's volume.
    assert_eq!(sim.surface_cut_errors(), vec![None]);
    let surface = &sim.surfaces()[0];
    assert!(surface.rest.is_closed());
    let comps = components(&surface.rest);
    assert_eq!(comps.len(), 2, "two closed surface parts");
    for c in &comps {
        assert!(c.is_closed(), "every edge shared by exactly two triangles");
        assert!(c.is_outward_oriented());
        let v = c.signed_volume();
        assert!(
            (v / volume_before - 0.5).abs() < 0.05,
            "part volume {v} of {volume_before}"
        );
    }
    let deformed = TriMesh {
        vertices: surface.deformed.clone(),
        triangles: surface.rest.triangles.clone(),
    };
    assert!(deformed.is_closed());
}

#[test]
#[ignore]
fn debug_cut() {
    let mut sim = cut_block();
    let mut interaction = Interaction::new(&sim);
    let dt = sim.options().dt;
    for _ in 0..(0.7 / dt) as usize {
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        let r = interaction.before_step(&mut sim, &inputs).unwrap();
        if r.cuts > 0 {
            let sep = sim.separation().unwrap();
            eprintln!(
                "t {} crossed {} virtual {} copies {} leaves {}",
                sim.time(),
                sep.crossed.len(),
                sep.virtual_nodes.len(),
                sep.copies.len(),
                sim.lattice().leaf_count()
            );
            if let Some(cosurg_sim_core::cut::TopologyOp::Cut(c)) = sim.topology().ops().next() {
                for t in &c.triangles {
                    eprintln!("{t:?}");
                }
            }
            eprintln!("{:?}", parts(&mut sim));
        }
        sim.step().unwrap();
    }
}

/// A keyframe carries the cut's virtual nodes: a second simulation that received the same
/// cut (with another lattice history, so other slot numbers) and then the first one's
/// full-state frame shows the same cut block, the parts' faces at the cut included.
#[test]
fn keyframes_carry_the_virtual_nodes_of_a_cut() {
    use cosurg_sim_core::sync::{RegionMap, apply_full_state, encode_full_state};
    let mut a = cut_block();
    let mut interaction = Interaction::new(&a);
    let dt = a.options().dt;
    let mut after_cut = None;
    for _ in 0..(1.2 / dt).round() as usize {
        let inputs = interaction.scripted_inputs(&a, a.time());
        if interaction
            .before_step(&mut a, &inputs)
            .expect("blade")
            .cuts
            > 0
        {
            after_cut = Some(0);
        }
        a.step().expect("step");
        after_cut = after_cut.map(|n| n + 1);
    }
    assert!(after_cut.is_some_and(|n| n > 100), "cut, then swung apart");
    let op = a.topology().ops().next().expect("the cut").clone();

    // Another history: a corner leaf refined (the frame merges it back), so the nodes and
    // the virtual nodes have other slot numbers.
    let mut b = cut_block();
    let leaf = b.lattice().leaves()[0];
    assert!(b.refine(leaf).expect("refine") > 0);
    b.apply_topology_op(op).expect("the same cut");
    let (sep_a, sep_b) = (a.separation().unwrap(), b.separation().unwrap());
    assert_eq!(sep_a.virtual_nodes.len(), sep_b.virtual_nodes.len());
    assert_ne!(sep_a.capacity, sep_b.capacity, "the slots differ");

    let map_a = RegionMap::for_simulation(&a);
    let map_b = RegionMap::for_simulation(&b);
    let frame = encode_full_state(&a, &map_a, 1);
    assert_eq!(
        frame.positions.len(),
        a.lattice().node_count() + sep_a.virtual_nodes.len()
    );
    apply_full_state(&mut b, &map_b, &frame).expect("applies");
    let (sa, sb) = (&a.surfaces()[0], &b.surfaces()[0]);
    assert_eq!(sa.deformed.len(), sb.deformed.len());
    let worst = sa
        .deformed
        .iter()
        .zip(&sb.deformed)
        .map(|(p, q)| (p - q).norm())
        .fold(0.0f64, f64::max);
    // Both interpolate the same degrees of freedom with the same weights: equal to
    // rounding. (Without the virtual nodes the faces at the cut stay where the second
    // simulation had them: centimetres away.)
    assert!(worst < 1e-9, "surfaces differ by {worst} m after the frame");
}

/// Two equal simulations of the cut block, cut alike, the parts swinging apart under
/// gravity (accelerating): a hybrid follower that gets the other's keyframe three steps
/// late compares it with its own state at the keyframe's time, the cut's virtual nodes
/// included, agrees, and moves nothing. Setting the virtual nodes to the keyframe's state
/// advanced by its velocity (as before) moved them by about ½ g (3 Δt)² towards a wrong
/// target. A follower that does disagree at a virtual node is corrected there, blended.
#[test]
fn a_hybrid_follower_corrects_the_virtual_nodes_of_a_cut_like_the_lattice_nodes() {
    use cosurg_sim_core::sync::{
        CorrectedRegion, Correction, HybridConfig, RegionMap, StateHistory, encode_keyframe,
    };
    // Both run the same script, step for step: equal (deterministic) simulations.
    let (mut a, mut b) = (cut_block(), cut_block());
    let (mut ia, mut ib) = (Interaction::new(&a), Interaction::new(&b));
    let dt = a.options().dt;
    let mut history = StateHistory::default();
    let mut since_cut = None;
    while since_cut.is_none_or(|n| n < 20) {
        assert!(a.time() < 2.0, "the blade never cut");
        let inputs = ia.scripted_inputs(&a, a.time());
        let cuts = ia.before_step(&mut a, &inputs).expect("blade").cuts;
        let inputs = ib.scripted_inputs(&b, b.time());
        ib.before_step(&mut b, &inputs).expect("blade");
        if cuts > 0 {
            since_cut = Some(0);
        }
        history.record(&b, 0.2, false);
        a.step().expect("step");
        b.step().expect("step");
        since_cut = since_cut.map(|n| n + 1);
    }
    let map = RegionMap::for_simulation(&a);
    // A region whose keyframe carries virtual nodes.
    let (region, kf) = map
        .regions()
        .map(|r| (r, encode_keyframe(&a, &map, r, 1).expect("encodes")))
        .find(|(r, kf)| kf.positions.len() > map.canonical_nodes(a.lattice(), *r).len())
        .expect("a region with virtual nodes");
    let lattice_nodes = map.canonical_nodes(b.lattice(), region).len();
    for _ in 0..3 {
        history.record(&b, 0.2, false);
        b.step().expect("step");
    }
    assert!(b.time() > kf.sim_time + 2.5 * dt);
    let sep = b.separation().expect("cut").clone();
    let virtual_dofs = sep.capacity..sep.dof_count();
    let before: Vec<V3> = b.positions()[virtual_dofs.clone()].to_vec();
    let mut follower = CorrectedRegion::new(region, HybridConfig::default());
    match follower
        .apply_keyframe(&mut b, &map, &kf, &history)
        .expect("applies")
    {
        Correction::Agrees { max_m } => assert!(max_m <= 1e-9, "{max_m} m"),
        other => panic!("a late keyframe of an equal simulation started {other:?}"),
    }
    let moved = b.positions()[virtual_dofs.clone()]
        .iter()
        .zip(&before)
        .map(|(p, q)| (p - q).norm())
        .fold(0.0f64, f64::max);
    assert_eq!(moved, 0.0, "a virtual node moved by {moved} m");

    // One virtual node of the keyframe 2 mm off (a follower that disagrees there): the
    // correction brings it there over its steps (no physics in between here).
    let mut off = encode_keyframe(&b, &map, region, 2).expect("encodes");
    let entry = lattice_nodes;
    off.positions[entry][1] += 2e-3;
    let target = V3::from(off.positions[entry]);
    let mut follower = CorrectedRegion::new(region, HybridConfig::default());
    let steps = match follower
        .apply_keyframe(&mut b, &map, &off, &StateHistory::default())
        .expect("applies")
    {
        Correction::Started { steps, max_m } => {
            assert!((max_m - 2e-3).abs() < 1e-9, "{max_m} m");
            steps
        }
        other => panic!("a 2 mm difference started {other:?}"),
    };
    assert!(steps >= 8, "2 mm at 0.25 mm per step: {steps} steps");
    let dof = (0..sep.dof_count())
        .filter(|&d| d >= sep.capacity)
        .find(|&d| (b.positions()[d] - (target - V3::new(0.0, 2e-3, 0.0))).norm() < 1e-12)
        .expect("the entry's virtual node");
    for _ in 0..steps {
        let moved = follower.drive(&mut b);
        assert!(moved <= 2.5e-4 + 1e-12, "{moved} m in one step");
    }
    assert!(
        (b.positions()[dof] - target).norm() < 1e-9,
        "not at the keyframe"
    );

    // The same 2 mm, then a refinement before the correction runs: the separation is
    // made again from a new capacity, so the virtual node's number now names another
    // node (or none), and its entry is dropped; the lattice nodes' entries (all zero
    // here) still apply. (Here the number lands on a node of another grid point, which
    // the grid check alone catches; the separation check also covers a number that lands
    // on another copy of the same lattice node.)
    let mut off = encode_keyframe(&b, &map, region, 3).expect("encodes");
    off.positions[entry][1] += 2e-3;
    let mut follower = CorrectedRegion::new(region, HybridConfig::default());
    assert!(matches!(
        follower
            .apply_keyframe(&mut b, &map, &off, &StateHistory::default())
            .expect("applies"),
        Correction::Started { .. }
    ));
    let before = b.separation().map(|s| (s.capacity, s.dof_count()));
    let leaf = b.lattice().leaves()[0];
    assert!(b.refine(leaf).expect("refine") > 0);
    let after = b.separation().map(|s| (s.capacity, s.dof_count()));
    assert_ne!(before, after, "the refinement made the separation again");
    assert_eq!(follower.drive(&mut b), 0.0, "a virtual entry moved a node");
}

/// A cut of the bodies scene's cystic duct (a sheet across it, at rest) leaves every
/// surface it does not cross exactly where it was, and the duct's vertices away from the
/// sheet too: re-hosting the vertices on the element copies must not move them.
#[test]
fn a_cut_moves_no_surface_vertex_it_does_not_cross() {
    let scene = cosurg_sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene, options).unwrap();
    let before: Vec<Vec<V3>> = sim.surfaces().iter().map(|s| s.deformed.clone()).collect();
    // The duct runs from (0.0276, -0.0019, -0.0526) to the hilum (0, 0.05, -0.054): a
    // square sheet 2 cm wide across it at half way, normal to its axis.
    let (a, b) = (
        V3::new(0.0276, -0.0019, -0.0526),
        V3::new(0.0, 0.05, -0.054),
    );
    let mid = 0.5 * (a + b);
    let along = (b - a).normalize();
    let u = along.cross(&V3::z()).normalize();
    let w = along.cross(&u);
    let p = |s: f64, t: f64| {
        let q = mid + u * s + w * t;
        [q.x, q.y, q.z]
    };
    let op = cosurg_sim_core::cut::TopologyOp::Cut(cosurg_sim_core::cut::CutOp {
        id: cosurg_sim_core::cut::OpId { site: 1, seq: 0 },
        triangles: vec![
            [p(-0.01, -0.01), p(0.01, -0.01), p(0.01, 0.01)],
            [p(-0.01, -0.01), p(0.01, 0.01), p(-0.01, 0.01)],
        ],
    });
    sim.apply_topology_op(op).unwrap();
    for (s, b) in sim.surfaces().iter().zip(&before) {
        if s.name == "cystic duct" {
            continue;
        }
        assert_eq!(s.deformed.len(), b.len(), "{}", s.name);
        let worst = s
            .deformed
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y).norm())
            .fold(0.0, f64::max);
        assert!(worst < 1e-9, "{}: a vertex moved {worst:.3e} m", s.name);
    }
}

/// Contact after a cut: once the cut block's halves have swung apart (the cut face's
/// vertices then lie 5+ mm from where the lattice's own nodes would put them), a probe
/// pressed 2 mm into the cut face of the left half touches it. (Contact now reads the
/// vertices from the copies they are drawn from, `Simulation::surface_vertex_host`; this
/// test also passes with the lattice's nodes, whose error the neighbouring uncut triangles
/// hide here: it checks contact on a cut face, not that change.)
#[test]
fn contact_after_a_cut_touches_the_cut_face_where_it_is_drawn() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let text = std::fs::read_to_string(dir.join("cut-block.toml"))
        .unwrap()
        .replace("contact = false", "contact = true")
        + r#"
[[tool]]
name = "probe"
kind = "probe"
position = [0.3, 0.3, 0.3]
radius = 0.002
length = 0.02
"#;
    let scene = Scene::from_str(&text, &dir, "cut-block+probe.toml").unwrap();
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene, options).unwrap();
    let mut interaction = Interaction::new(&sim);
    let probe = interaction.tools.index("probe").unwrap();
    // The blade's script cuts at 0.65 s; the halves swing for 0.5 s more (the probe is
    // parked far away).
    for _ in 0..((1.15 / sim.options().dt).round() as usize) {
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        interaction.before_step(&mut sim, &inputs).unwrap();
        sim.step().unwrap();
    }
    assert!(sim.separation().is_some(), "the block is cut");
    let s = &sim.surfaces()[0];
    let lattice_point = |v: usize| -> V3 {
        let (_, w, n) = s.embedding.host(v);
        (0..4)
            .map(|k| w[k] * sim.positions()[n[k].0 as usize])
            .sum()
    };
    // The cap vertex of the left half (rest normal +x) farthest from where the lattice's
    // nodes would put it.
    let rest_normals = s.rest.vertex_normals();
    let (v, gap) = (0..s.rest.vertices.len())
        .filter(|&v| (s.rest.vertices[v].x - 0.0613).abs() < 1e-6 && rest_normals[v].x > 0.9)
        .map(|v| (v, (s.deformed[v] - lattice_point(v)).norm()))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .expect("cap vertices on the left half");
    assert!(
        gap > 0.005,
        "the halves swung apart: {gap} m between copy and lattice"
    );
    let deformed = TriMesh {
        vertices: s.deformed.clone(),
        triangles: s.rest.triangles.clone(),
    };
    let normal = deformed.vertex_normals()[v];
    let p = s.deformed[v];
    // The probe along the face's outward normal, its tip 2 mm inside.
    let shaft = nalgebra::UnitQuaternion::rotation_between(&V3::z(), &normal).unwrap();
    let mut inputs = interaction.scripted_inputs(&sim, sim.time());
    inputs[probe] = cosurg_sim_core::ToolInput::new(p - normal * 0.002, shaft, 0.0);
    let report = interaction.before_step(&mut sim, &inputs).unwrap();
    let touched = &interaction.state().tools[probe];
    assert!(
        report.contacts > 0 && touched.max_depth > 0.001,
        "the probe 2 mm into the cut face: {} contacts, depth {} m",
        report.contacts,
        touched.max_depth
    );
}

/// The blade's and the clip applier's inside-only query (`rest_points_inside`, boxes
/// first) against the full search (`rest_point_of`, every element), on a grid of points
/// in and around the cut block, deformed, before and after its cut: the same rest point
/// for every point inside (exactly: the same element wins), `None` for every point
/// outside; asked all at once and one by one (a single point's box rules out most
/// elements by their nodes' sides of it).
#[test]
fn the_inside_query_agrees_with_the_full_search_before_and_after_a_cut() {
    let mut sim = cut_block();
    let mut interaction = Interaction::new(&sim);
    let dt = sim.options().dt;
    let check = |sim: &Simulation| {
        // The block is 0.12 × 0.04 × 0.04 m; the grid reaches 1 cm beyond it.
        let mut points = Vec::new();
        for i in 0..15 {
            for j in 0..7 {
                for k in 0..7 {
                    points.push(V3::new(
                        -0.01 + 0.14 * i as f64 / 14.0 + 1e-4,
                        -0.01 + 0.06 * j as f64 / 6.0 + 2e-4,
                        -0.01 + 0.06 * k as f64 / 6.0 + 3e-4,
                    ));
                }
            }
        }
        let inside = sim.rest_points_inside(&points);
        let (mut n_in, mut n_out) = (0, 0);
        for (q, fast) in points.iter().zip(&inside) {
            let (full, is_in) = sim.rest_point_of(q).expect("elements exist");
            if is_in {
                n_in += 1;
                assert_eq!(*fast, Some(full), "{q:?}");
                assert_eq!(sim.rest_point_inside(q), Some(full), "{q:?}");
            } else {
                n_out += 1;
                assert_eq!(*fast, None, "{q:?}");
                assert_eq!(sim.rest_point_inside(q), None, "{q:?}");
            }
        }
        assert!(n_in > 50 && n_out > 50, "{n_in} inside, {n_out} outside");
    };
    let steps = (1.2 / dt).round() as usize;
    let mut checked_before = false;
    for _ in 0..steps {
        if !checked_before && sim.time() > 0.3 {
            check(&sim);
            checked_before = true;
        }
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        interaction
            .before_step(&mut sim, &inputs)
            .expect("before_step");
        sim.step().expect("step");
    }
    assert!(checked_before);
    assert!(
        sim.separation().is_some(),
        "the blade cut the block by 1.2 s"
    );
    check(&sim);
}
