//! Tools, contact, grasping and tool-following adaptivity (sim-core `contact`, `tools`,
//! `adapt`).

use std::path::Path;

use cosurg_sim_core::contact::closest_point_triangle;
use cosurg_sim_core::sim_fem::{Model, StiffnessMode};
use cosurg_sim_core::sim_scene::{LoadedScene, Scene};
use cosurg_sim_core::{
    AdaptParams, ContactParams, Interaction, NodeId, SimOptions, Simulation, ToolInput,
};
use nalgebra::{UnitQuaternion, Vector3};

type V3 = Vector3<f64>;

/// An 8 × 8 × 4 cm block (E = 20 kPa) clamped at its bottom face, no gravity, with a
/// probe of radius 5 mm above the centre of its top face (z = 0.04).
fn block_scene(max_depth: u32, tool: bool, inclusion: bool, adaptivity: bool) -> LoadedScene {
    let mut text = format!(
        r#"
version = 1
gravity = [0.0, 0.0, 0.0]
[material.tissue]
young = 2.0e4
poisson = 0.3
density = 1000.0
rayleigh_mass = 5.0
rayleigh_stiffness = 0.01
[material.hard]
young = 1.0e5
poisson = 0.3
density = 1000.0
[[body]]
name = "block"
box = {{ min = [0.0, 0.0, 0.0], max = [0.08, 0.08, 0.04] }}
cell = 0.02
max_depth = {max_depth}
material = "tissue"
{inc}
[[fix]]
box = {{ min = [-1.0, -1.0, -0.001], max = [1.0, 1.0, 0.001] }}
[simulation]
dt = 0.002
cg_iterations = 200
cg_tolerance = 1.0e-9
contact_stiffness = 500.0
[features]
adaptivity = {adaptivity}
contact = true
"#,
        inc = if inclusion {
            r#"[[body.inclusion]]
material = "hard"
capsules = [{ a = [0.0, 0.0, 0.02], b = [0.0, 0.08, 0.02], radius = 0.006 }]
refine_boundary = true"#
        } else {
            ""
        }
    );
    if tool {
        text.push_str(
            r#"
[[tool]]
name = "probe"
kind = "probe"
position = [0.04, 0.04, 0.05]
radius = 0.005
length = 0.02
"#,
        );
    }
    Scene::from_str(&text, Path::new("."), "test:block").expect("valid block scene")
}

fn sim_of(scene: LoadedScene) -> Simulation {
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).expect("simulation")
}

fn probe_at(z: f64, x: f64) -> ToolInput {
    ToolInput::new(V3::new(x, 0.04, z), UnitQuaternion::identity(), 0.0)
}

/// Tip height for a position-driven press: from 5 cm down to `bottom` over `t_down`.
fn press(t: f64, bottom: f64, t_down: f64) -> f64 {
    0.05 + (bottom - 0.05) * (t / t_down).min(1.0)
}

/// Checks that the tool's force and torque (about the tip) are minus the sum of the node
/// forces (and their moments at the node positions the pass used), to 1e-9 relative.
fn check_balance(ia: &Interaction, sim: &Simulation, tool: usize) -> f64 {
    let st = ia.state();
    let tip = ia.tools.tools[tool].tip();
    let x = sim.positions();
    let mut f = V3::zeros();
    let mut tau = V3::zeros();
    let mut scale: f64 = 0.0;
    for (i, fi) in st.node_force.iter().enumerate() {
        f += fi;
        tau += (x[i] - tip).cross(fi);
        scale += fi.norm();
    }
    let t = &st.tools[tool];
    let ef = (t.force + f).norm();
    let et = (t.torque + tau).norm();
    let lever = t
        .contacts
        .iter()
        .map(|c| (c.point - tip).norm())
        .fold(0.0, f64::max)
        + ia.tools.tools[tool].length;
    assert!(
        ef <= 1e-9 * scale,
        "force balance: {ef} N vs scale {scale} N"
    );
    assert!(
        et <= 1e-9 * scale * lever,
        "torque balance: {et} N m vs scale {} N m",
        scale * lever
    );
    scale
}

/// Static check: a position-driven probe pressed 4 mm into the block comes to rest where
/// the reaction on the tool balances the clamp's support reaction (the elastic forces on
/// the fixed nodes), and the penetration is what the penalty stiffness allows.
#[test]
fn probe_press_reaches_force_equilibrium() {
    let mut sim = sim_of(block_scene(0, true, false, false));
    let mut ia = Interaction::new(&sim);
    let k_c = ia.contact.params.stiffness;
    let dt = sim.options().dt;
    let steps = 600; // 1.2 s: 0.3 s down, 0.9 s hold
    for _ in 0..steps {
        let z = press(sim.time(), 0.036, 0.3);
        ia.before_step(&mut sim, &[probe_at(z, 0.04)]).unwrap();
        check_balance(&ia, &sim, 0);
        sim.step().unwrap();
    }
    // One more pass at rest to read the contact forces at the final state.
    ia.before_step(&mut sim, &[probe_at(0.036, 0.04)]).unwrap();
    let tool = ia.state().tools[0].clone();
    let vmax = sim
        .velocities()
        .iter()
        .map(|v| v.norm())
        .fold(0.0, f64::max);
    assert!(vmax < 1e-4, "not at rest: max node speed {vmax} m/s");
    let x = sim.positions().to_vec();
    let fint = sim
        .fem()
        .unwrap()
        .internal_forces(&x, Model::Corotational, StiffnessMode::Template);
    let support: V3 = (0..x.len())
        .filter(|&i| sim.is_fixed(NodeId(i as u32)))
        .map(|i| fint[i])
        .sum();
    // Tool pushed up by the tissue; the clamp holds the block down with the same force.
    let f = tool.force;
    assert!(f.z > 0.5, "probe should be pushed back, got {f:?} N");
    let err = (f + support).norm();
    assert!(
        err <= 1e-4 * f.norm(),
        "tool reaction {f:?} N vs support reaction {:?} N (err {err} N)",
        -support
    );
    let n = tool.contacts.len();
    let bound = f.norm() / (k_c * n as f64);
    let mean_depth = tool.contacts.iter().map(|c| c.depth).sum::<f64>() / n as f64;
    eprintln!(
        "press: tool force {:?} N, support {:?} N, err {err:.2e} N, {n} samples, mean depth \
         {mean_depth:.3e} m, max depth {:.3e} m, |F|/k_c {:.3e} m",
        f.as_slice(),
        (-support).as_slice(),
        tool.max_depth,
        f.norm() / k_c
    );
    // All contact forces push (k_c d_i ≥ 0), so the mean depth is |F_n|/(k_c n) and no
    // sample can be deeper than |F|/k_c.
    assert!(
        (mean_depth - bound).abs() <= 0.05 * bound,
        "mean penetration {mean_depth} m vs |F|/(k_c n) = {bound} m ({n} samples)"
    );
    assert!(
        tool.max_depth <= f.norm() / k_c && tool.max_depth < 0.003,
        "max penetration {} m vs |F|/k_c = {} m",
        tool.max_depth,
        f.norm() / k_c
    );
    let _ = dt;
}

/// Force and torque balance to 1e-9 relative while a tilted probe presses and slides
/// (friction anchors slipping), and the local linear model predicts small displacements.
#[test]
fn tool_reaction_balances_node_forces() {
    let mut sim = sim_of(block_scene(0, true, false, false));
    let mut ia = Interaction::new(&sim);
    let tilt = UnitQuaternion::from_axis_angle(&V3::y_axis(), 0.4);
    let mut checked = 0;
    for step in 0..300 {
        let t = sim.time();
        let z = press(t, 0.035, 0.2);
        let x = 0.035 + 0.02 * ((t - 0.2).max(0.0) / 0.4).min(1.0);
        let input = ToolInput::new(V3::new(x, 0.04, z), tilt, 0.0);
        ia.before_step(&mut sim, &[input]).unwrap();
        if !ia.state().tools[0].contacts.is_empty() {
            let scale = check_balance(&ia, &sim, 0);
            assert!(scale > 0.0);
            checked += 1;
        }
        if step == 150 {
            let tool = &ia.state().tools[0];
            assert!(
                tool.contacts.iter().any(|c| !c.sticking),
                "sliding should slip"
            );
            // Local model: top-left block is −Σ k n nᵀ (+ sticking friction): negative
            // semi-definite and symmetric.
            let k = tool.local.stiffness;
            assert!((k - k.transpose()).norm() <= 1e-9 * k.norm());
            assert!(k.symmetric_eigenvalues().max() <= 1e-9 * k.norm());
            assert!(k[(2, 2)] < 0.0);
        }
        sim.step().unwrap();
    }
    assert!(
        checked > 100,
        "contact should last most of the run ({checked} steps)"
    );
}

/// No tool: the pass is skipped; contact off: skipped; a far tool: the pass runs but no
/// narrow-phase (point–triangle) test.
#[test]
fn contact_work_is_skipped_when_not_needed() {
    let mut sim = sim_of(block_scene(0, false, false, false));
    let mut ia = Interaction::new(&sim);
    for _ in 0..5 {
        let r = ia.before_step(&mut sim, &[]).unwrap();
        assert!(!r.contact_ran);
        sim.step().unwrap();
    }
    let st = ia.state().stats;
    assert_eq!((st.passes_run, st.passes_skipped), (0, 5));
    assert_eq!(st.root_tests + st.narrow_tests, 0);

    // A tool 1 m above the block.
    let mut sim = sim_of(block_scene(0, true, false, false));
    let mut ia = Interaction::new(&sim);
    for _ in 0..5 {
        let r = ia.before_step(&mut sim, &[probe_at(1.0, 0.04)]).unwrap();
        assert!(r.contact_ran);
        assert_eq!(r.narrow_tests, 0);
        sim.step().unwrap();
    }
    let st = ia.state().stats;
    assert_eq!(st.passes_run, 5);
    assert!(st.root_tests > 0);
    assert_eq!(
        (st.leaf_tests, st.candidate_triangles, st.narrow_tests),
        (0, 0, 0)
    );

    // Contact switched off.
    let mut opts = sim.options().clone();
    opts.contact = false;
    sim.set_options(opts);
    let before = ia.state().stats;
    ia.before_step(&mut sim, &[probe_at(0.03, 0.04)]).unwrap();
    let st = ia.state().stats;
    assert_eq!(st.passes_run, before.passes_run);
    assert_eq!(st.passes_skipped, before.passes_skipped + 1);
    assert!(ia.state().node_force.iter().all(|f| *f == V3::zeros()));
}

/// Adaptivity refines around the contact and, after the probe left, coarsens back to the
/// initial leaf count — never below the static refinement along the inclusion.
#[test]
fn adaptivity_follows_the_tool_and_coarsens_back() {
    let mut sim = sim_of(block_scene(3, true, true, true));
    let initial = sim.lattice().leaf_count();
    assert!(initial > 4 * 4 * 2 * 6, "the inclusion refines statically");
    let adapt = AdaptParams {
        every: 5,
        distance: 0.01,
        hold_time: 0.1,
        max_level: 3,
    };
    let mut ia = Interaction::with_params(&sim, ContactParams::from_sim(&sim), adapt);
    let mut peak = initial;
    let mut max_level = 0;
    for _ in 0..150 {
        let z = press(sim.time(), 0.036, 0.1);
        let r = ia.before_step(&mut sim, &[probe_at(z, 0.04)]).unwrap();
        peak = peak.max(r.adapt.leaves);
        sim.step().unwrap();
    }
    for &t in sim.lattice().leaves() {
        let c = sim
            .lattice()
            .tet_nodes(t)
            .iter()
            .map(|&n| sim.lattice().node_rest(n))
            .sum::<V3>()
            / 4.0;
        if (c - V3::new(0.04, 0.04, 0.04)).norm() < 0.01 {
            max_level = max_level.max(t.level());
        }
    }
    assert_eq!(max_level, 3, "leaves at the contact reach max_depth");
    assert!(peak > initial + 20, "refined: {initial} -> {peak} leaves");
    assert!(ia.adapt.created_diamonds() > 0);
    // Lift the probe away and wait past the hold time.
    for _ in 0..150 {
        ia.before_step(&mut sim, &[probe_at(0.1, 0.04)]).unwrap();
        sim.step().unwrap();
    }
    assert_eq!(ia.adapt.created_diamonds(), 0);
    assert_eq!(sim.lattice().leaf_count(), initial, "coarsened back");
    assert!(
        sim.positions()
            .iter()
            .all(|p| p.iter().all(|c| c.is_finite()))
    );
}

/// The leaves of `sim`, sorted (a lattice's identity, independent of its history).
fn leaf_set(sim: &Simulation) -> Vec<cosurg_sim_core::TetId> {
    let mut leaves = sim.lattice().leaves().to_vec();
    leaves.sort_unstable();
    leaves
}

/// Refinement decided on one site and applied on two whose states differ (another contact
/// stiffness: apart under the probe) keeps their lattices equal at every step,
/// refines around the contact on both and coarsens both back — by the merges of the site
/// that drove the probe, after it stopped driving; the other site decides nothing.
#[test]
fn refinement_decided_on_one_site_gives_two_sites_the_same_lattice() {
    let mut a = sim_of(block_scene(3, true, true, true));
    let mut b = sim_of(block_scene(3, true, true, true));
    let initial = leaf_set(&a);
    let params = AdaptParams {
        every: 5,
        distance: 0.01,
        hold_time: 0.1,
        max_level: 3,
    };
    let mut ia = Interaction::with_params(&a, ContactParams::from_sim(&a), params);
    let mut cb = ContactParams::from_sim(&b);
    cb.stiffness *= 0.2;
    let mut ib = Interaction::with_params(&b, cb, params);
    for (i, site) in [&mut ia, &mut ib].into_iter().enumerate() {
        site.adapt.apply_own = false;
        site.adapt.site = i as u32;
    }
    // Only site A drives the probe, for the first 150 steps; B simulates it.
    ib.adapt.enabled = vec![false];
    let (mut ops, mut peak, mut apart) = (0, initial.len(), 0.0f64);
    for k in 0..300 {
        let input = if k < 150 {
            probe_at(press(a.time(), 0.036, 0.1), 0.04)
        } else {
            ia.adapt.enabled = vec![false];
            probe_at(0.1, 0.04)
        };
        ia.before_step(&mut a, &[input]).unwrap();
        ib.before_step(&mut b, &[input]).unwrap();
        assert!(
            ib.adapt.made.is_empty(),
            "a site that never drove decides nothing"
        );
        let made: Vec<_> = ia.adapt.made.drain(..).collect();
        for op in made {
            ops += 1;
            a.apply_topology_op(op.clone()).unwrap();
            b.apply_topology_op(op).unwrap();
        }
        assert_eq!(leaf_set(&a), leaf_set(&b), "step {k}: lattices differ");
        peak = peak.max(a.lattice().leaf_count());
        a.step().unwrap();
        b.step().unwrap();
        let n = a.positions().len().min(b.positions().len());
        for i in 0..n {
            apart = apart.max((a.positions()[i] - b.positions()[i]).norm());
        }
    }
    assert!(apart > 3e-4, "the two states differ: {apart:.2e} m apart");
    assert!(ops >= 2, "{ops} ops");
    assert!(
        peak > initial.len() + 20,
        "refined: {} -> {peak}",
        initial.len()
    );
    assert_eq!(
        leaf_set(&a),
        initial,
        "coarsened back to the static refinement"
    );
}

/// A refinement op splits exactly to its level every leaf whose rest box lies within its
/// distance of a focus point (checked leaf by leaf against the boxes), and malformed ops
/// are refused with their problem named.
#[test]
fn a_refinement_op_splits_what_lies_within_its_distance_and_malformed_ones_are_refused() {
    use cosurg_sim_core::adapt::{REFINE_SEQ_BASE, RefineOp};
    use cosurg_sim_core::cut::OpId;
    let mut sim = sim_of(block_scene(3, true, false, true));
    let before = sim.lattice().leaf_count();
    let focus = [0.04, 0.04, 0.04];
    let op = RefineOp {
        id: OpId {
            site: 1,
            seq: REFINE_SEQ_BASE,
        },
        focus: vec![focus],
        distance: 0.006,
        level: 3,
        merge: Vec::new(),
    };
    let change = sim.apply_refine(&op).unwrap();
    assert!(change.split > 0 && sim.lattice().leaf_count() > before);
    let lat = sim.lattice();
    let f = V3::from(focus);
    let mut near = 0;
    for (i, t) in lat.leaves().iter().enumerate() {
        let nodes = lat.leaf_tet_nodes(i);
        let (mut lo, mut hi) = (V3::repeat(f64::INFINITY), V3::repeat(f64::NEG_INFINITY));
        for n in nodes {
            lo = lo.inf(&lat.node_rest(n));
            hi = hi.sup(&lat.node_rest(n));
        }
        let gap = (0..3)
            .map(|k| (lo[k] - f[k]).max(f[k] - hi[k]).max(0.0).powi(2))
            .sum::<f64>()
            .sqrt();
        if gap <= 0.006 {
            near += 1;
            assert_eq!(t.level(), 3, "leaf {t:?} within the distance");
        }
    }
    assert!(near > 0);
    // Applying it again changes nothing.
    assert_eq!(sim.apply_refine(&op).unwrap().split, 0);
    let mut bad = |edit: fn(&mut RefineOp)| {
        let mut o = op.clone();
        edit(&mut o);
        sim.apply_refine(&o).unwrap_err().to_string()
    };
    assert!(bad(|o| o.focus[0][1] = f64::NAN).contains("focus point 0 is not finite"));
    assert!(bad(|o| o.distance = -1.0).contains("distance -1 m"));
    assert!(bad(|o| o.focus = vec![[0.0; 3]; 5000]).contains("5000 focus points"));
}

/// The default scene: the forceps follows its script — approaches the fundus with open
/// jaws, closes them (grasp), lifts 3 cm, holds, opens them (release) — and the tissue
/// comes back to rest afterwards. The probe is parked at its initial pose (3 cm below the
/// neck, no contact).
#[test]
fn forceps_grasps_lifts_and_releases_the_gallbladder() {
    let scene = cosurg_sim_core::sim_scene::builtin::cholecystectomy();
    let mut sim = sim_of(scene);
    let mut ia = Interaction::new(&sim);
    let forceps = ia.tools.index("forceps").unwrap();
    let probe = ia.tools.index("probe").unwrap();
    let probe_rest = ToolInput {
        pose: *ia.tools.tools[probe].pose(),
        jaw: 0.0,
    };
    let mean_z = |pts: &[V3]| pts.iter().map(|p| p.z).sum::<f64>() / pts.len() as f64;
    let mut grasp_z: Option<f64> = None;
    let mut lifted_z: Option<f64> = None;
    let mut grasped_max = 0;
    let mut released_at = None;
    let t_end = 6.2;
    let mut peak_ke: f64 = 0.0;
    let initial_leaves = sim.lattice().leaf_count();
    let mut peak_leaves = initial_leaves;
    let started = std::time::Instant::now();
    while sim.time() < t_end {
        let t = sim.time();
        let mut inputs = ia.scripted_inputs(&sim, t);
        inputs[probe] = probe_rest;
        let r = ia.before_step(&mut sim, &inputs).unwrap();
        let tool = &ia.state().tools[forceps];
        if tool.grasped > 0 {
            grasped_max = grasped_max.max(tool.grasped);
            let z = mean_z(&tool.grasped_points);
            grasp_z.get_or_insert(z);
            if t >= 4.4 {
                lifted_z = Some(z);
            }
            if tool.grasped > 0 && t < 1.8 {
                panic!("grasped before the jaws closed (t = {t} s)");
            }
        } else if grasp_z.is_some() && released_at.is_none() {
            released_at = Some(t);
        }
        peak_leaves = peak_leaves.max(r.adapt.leaves);
        if sim.steps().is_multiple_of(50) {
            // Grasp springs (and contacts) balance too; the probe touches nothing.
            check_balance(&ia, &sim, forceps);
            assert_eq!(ia.state().tools[probe].force, V3::zeros());
        }
        sim.step().unwrap();
        let v = sim.velocities().to_vec();
        let ke = sim.fem().unwrap().kinetic_energy(&v);
        assert!(ke.is_finite());
        if released_at.is_some() {
            peak_ke = peak_ke.max(ke);
        }
    }
    let v = sim.velocities().to_vec();
    let ke = sim.fem().unwrap().kinetic_energy(&v);
    let (z0, z1) = (
        grasp_z.expect("never grasped"),
        lifted_z.expect("lost the grasp"),
    );
    eprintln!(
        "grasp: {grasped_max} points, mean z {z0:.4} -> {z1:.4} m, released at {released_at:?} s, \
         KE peak after release {peak_ke:.3e} J, final {ke:.3e} J, leaves {initial_leaves} -> {peak_leaves} -> {}, \
         {:.1} s wall",
        sim.lattice().leaf_count(),
        started.elapsed().as_secs_f64()
    );
    assert!(z1 - z0 >= 0.025, "lifted only {} m", z1 - z0);
    let released = released_at.expect("never released");
    // The scene has adaptivity on: refined around the jaws, coarsened back after release.
    assert!(peak_leaves > initial_leaves);
    assert_eq!(sim.lattice().leaf_count(), initial_leaves);
    assert!((4.6..5.0).contains(&released), "released at {released} s");
    assert!(
        sim.positions()
            .iter()
            .all(|p| p.iter().all(|c| c.is_finite()))
    );
    // Back to rest 1.5 s after the release.
    assert!(
        ke < 1e-6 * peak_ke && ke < 1e-9,
        "not at rest: KE {ke} J (peak after release {peak_ke} J)"
    );
}

/// A grasp tears loose when its tissue is pulled more than `grasp_tear` from the jaws —
/// unless tearing is off for that tool (`grasp_tears`: a site that simulates another
/// site's forceps leaves that decision to the site that drives it); then only opening the
/// jaws lets go.
#[test]
fn a_grasp_tears_only_where_tearing_is_on_and_always_lets_go_when_the_jaws_open() {
    for tears in [true, false] {
        let mut sim = sim_of(cosurg_sim_core::sim_scene::builtin::cholecystectomy());
        let mut ia = Interaction::new(&sim);
        let forceps = ia.tools.index("forceps").unwrap();
        ia.contact.grasp_tears[forceps] = tears;
        // The script closes the jaws on the fundus at 1.5–2.0 s; hold there until 2.3 s.
        while sim.time() < 2.3 {
            let inputs = ia.scripted_inputs(&sim, sim.time());
            ia.before_step(&mut sim, &inputs).unwrap();
            sim.step().unwrap();
        }
        assert!(
            ia.contact.is_grasping(forceps),
            "the script's grasp did not take"
        );
        let mut inputs = ia.scripted_inputs(&sim, sim.time());
        assert!(inputs[forceps].jaw < 0.05, "jaws not closed");
        // Snap the closed jaws away in one step: twice the tear distance.
        let tear = ia.contact.params.grasp_tear;
        inputs[forceps].pose.translation.vector.z += 2.0 * tear;
        ia.before_step(&mut sim, &inputs).unwrap();
        let on_off = if tears { "on" } else { "off" };
        assert_eq!(
            ia.contact.is_grasping(forceps),
            !tears,
            "tearing {on_off}: pulled {} m from the jaws (tear distance {tear} m)",
            2.0 * tear
        );
        if !tears {
            // The grasp pulls the tissue towards the jaws, finitely; opening them lets go.
            assert!(ia.state().tools[forceps].grasped > 0);
            sim.step().unwrap();
            assert!(
                sim.positions()
                    .iter()
                    .all(|p| p.iter().all(|c| c.is_finite()))
            );
            inputs[forceps].jaw = 0.6;
            ia.before_step(&mut sim, &inputs).unwrap();
            assert!(
                !ia.contact.is_grasping(forceps),
                "opening the jaws did not let go"
            );
        }
    }
}

/// Tool 0's samples that lie under (against the normal of) their nearest surface triangle
/// within `margin`, by brute force over all triangles of the deformed surfaces (no
/// hierarchy, no candidates): what plain nearest-triangle contact would take for
/// penetration.
fn samples_under_nearest_triangle(sim: &Simulation, ia: &Interaction, margin: f64) -> usize {
    let x = sim.positions();
    let mut triangles: Vec<[V3; 3]> = Vec::new();
    for (s, surface) in sim.surfaces().iter().enumerate() {
        let at = |v: u32| {
            let (n, w) = sim.surface_vertex_host(s, v as usize);
            (0..4).map(|j| x[n[j]] * w[j]).sum::<V3>()
        };
        triangles.extend(surface.rest.triangles.iter().map(|t| t.map(at)));
    }
    ia.tools.tools[0]
        .world_samples()
        .iter()
        .filter(|s| {
            // Nearest point; where several triangles share it (an edge or a vertex), the
            // one that sees the sample most squarely decides the side, as in contact.
            let hits: Vec<(f64, f64)> = triangles
                .iter()
                .map(|t| {
                    let p = closest_point_triangle(s, &t[0], &t[1], &t[2]).0;
                    let n = (t[1] - t[0]).cross(&(t[2] - t[0])).normalize();
                    ((p - **s).norm(), (p - **s).dot(&n))
                })
                .collect();
            let nearest = hits.iter().map(|h| h.0).fold(f64::INFINITY, f64::min);
            let squarest = hits
                .iter()
                .filter(|h| h.0 <= nearest + 1e-12 * margin)
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
            nearest <= margin && squarest.is_some_and(|h| h.1 > 0.0)
        })
        .count()
}

/// The host leaf of the block's top-face centre vertex: its nodes, and which of them the
/// vertex sits on.
fn centre_vertex_host(sim: &Simulation) -> ([usize; 4], usize) {
    let centre = V3::new(0.04, 0.04, 0.04);
    let surface = &sim.surfaces()[0];
    let v = (0..surface.rest.vertices.len())
        .find(|&v| (surface.rest.vertices[v] - centre).norm() < 1e-9)
        .expect("a surface vertex at the top face's centre");
    let (nodes, w) = sim.surface_vertex_host(0, v);
    let k = (0..4).max_by(|&a, &b| w[a].total_cmp(&w[b])).unwrap();
    assert!(w[k] > 1.0 - 1e-9, "the vertex sits on a lattice node");
    (nodes, k)
}

/// Node `k` of leaf `nodes` moved towards the plane of the other three by `fraction` of
/// its distance to it: the leaf's volume ratio becomes `1 − fraction` (2: mirrored).
fn towards_opposite_face(sim: &Simulation, nodes: [usize; 4], k: usize, fraction: f64) -> V3 {
    let x = sim.positions();
    let o: Vec<V3> = (0..4).filter(|&j| j != k).map(|j| x[nodes[j]]).collect();
    let n = (o[1] - o[0]).cross(&(o[2] - o[0])).normalize();
    x[nodes[k]] - n * (x[nodes[k]] - o[0]).dot(&n) * fraction
}

/// A leaf turned inside out turns the surface triangles it hosts inside out too: their
/// normals point into the tissue. A tool beside them must not read that as penetration:
/// it would push the tissue further through itself (on the default organ with its
/// gallbladder at level 5 it did, 2026-11-29: one inverted element became 155 within
/// 0.5 s, 154 samples of the hook read as penetrating and it felt 68 N). Here the host
/// leaf of the top face's centre vertex is inverted by mirroring that vertex's node
/// through the leaf's opposite face, and a probe is held over the vertex.
#[test]
fn a_tool_does_not_push_on_surface_turned_inside_out_by_an_inverted_leaf() {
    let probe_at_centre_vertex = |invert: bool, lift: f64| {
        let mut sim = sim_of(block_scene(0, true, false, false));
        let (nodes, k) = centre_vertex_host(&sim);
        // Mirrored through the plane of the other three: det F changes sign.
        let moved = towards_opposite_face(&sim, nodes, k, if invert { 2.0 } else { 0.0 });
        sim.set_node_state(NodeId(nodes[k] as u32), moved, V3::zeros());
        let mut ia = Interaction::new(&sim);
        let input = probe_at(moved.z + lift, moved.x);
        ia.before_step(&mut sim, &[input]).unwrap();
        let st = ia.state();
        let under = samples_under_nearest_triangle(&sim, &ia, ia.contact.params.margin);
        (
            st.tools[0].contacts.len(),
            st.tools[0].force,
            st.stats.samples_on_inverted,
            moved,
            under,
        )
    };
    // Untouched: 4 mm under the vertex the probe is pushed up, by as many samples as lie
    // under their nearest triangle (detection works here); 4 mm over it, it is in the air.
    let (contacts, force, on_inverted, _, under) = probe_at_centre_vertex(false, -0.004);
    assert!(
        contacts > 0 && force.z > 0.0,
        "{contacts} contacts, force {force:?} N"
    );
    assert_eq!((on_inverted, contacts), (0, under));
    assert_eq!(probe_at_centre_vertex(false, 0.004).0, 0);
    // Inverted: the vertex's node now lies on the block's side face, the top face folds
    // over to it, and the probe 2-6 mm over the vertex is in the air above the top face.
    // Yet some of its samples lie under their nearest (inside-out) triangle, found here by
    // brute force: what contact used to take for penetration (at 4 mm: 2 samples, 7.2 N).
    // They must touch nothing.
    for lift in [0.006, 0.004, 0.002] {
        let (contacts, force, on_inverted, moved, under) = probe_at_centre_vertex(true, lift);
        assert!(moved.x < 0.001, "the node went to the side face: {moved:?}");
        assert!(
            under > 0,
            "{lift} m over: no sample under its nearest triangle"
        );
        assert!(
            on_inverted > 0,
            "{lift} m over: no sample nearest the inverted leaf"
        );
        assert_eq!(
            contacts, 0,
            "{lift} m over: force {force:?} N from inside-out triangles"
        );
    }
}

/// Contact fades as a leaf collapses towards inversion rather than switching off when it
/// inverts: every contact's normal force is `ω k_c d`, with `ω` its triangle's vertex
/// weights `clamp(J / J_fade, 0, 1)` interpolated at the contact point, `J` the volume
/// ratio of each vertex's host leaf (recomputed here from the positions). The top face's
/// centre node is moved 7/8 of the way to the opposite face of its vertex's host leaf
/// (that leaf at J = 1/8), and a still probe presses 4 mm into the face beside it.
#[test]
fn contact_weakens_in_proportion_as_its_leaf_collapses() {
    let mut sim = sim_of(block_scene(0, true, false, false));
    let (nodes, k) = centre_vertex_host(&sim);
    let moved = towards_opposite_face(&sim, nodes, k, 7.0 / 8.0);
    sim.set_node_state(NodeId(nodes[k] as u32), moved, V3::zeros());
    let mut ia = Interaction::new(&sim);
    let params = ia.contact.params;
    let input = probe_at(0.036, 0.03);
    // Twice at the same pose: the second pass sees a still tool (no damping force).
    ia.before_step(&mut sim, &[input]).unwrap();
    ia.before_step(&mut sim, &[input]).unwrap();

    let x = sim.positions();
    let volume = |p: [V3; 4]| (p[1] - p[0]).dot(&(p[2] - p[0]).cross(&(p[3] - p[0])));
    let ratio =
        |d: [usize; 4]| volume(d.map(|d| x[d])) / volume(d.map(|d| sim.dof_rest_position(d)));
    // The construction's own J, independent of the contact code: 1/8.
    assert!((ratio(nodes) - 0.125).abs() < 1e-12, "J = {}", ratio(nodes));
    // Per vertex ω = clamp(J / J_fade, 0, 1); at a point, 0 if a vertex's is, else the
    // vertices' interpolated.
    let weight = |surface: usize, triangle: usize, bary: &[f64; 3]| {
        let omega: Vec<f64> = sim.surfaces()[surface].rest.triangles[triangle]
            .iter()
            .map(|&v| {
                let j = ratio(sim.surface_vertex_host(surface, v as usize).0);
                (j / params.fade_volume_ratio).clamp(0.0, 1.0)
            })
            .collect();
        if omega.contains(&0.0) {
            0.0
        } else {
            omega.iter().zip(bary).map(|(o, b)| o * b).sum()
        }
    };
    let contacts = &ia.state().tools[0].contacts;
    assert!(!contacts.is_empty(), "the probe should touch the face");
    let mut faded = 0;
    for c in contacts {
        let omega = weight(c.surface, c.triangle, &c.bary);
        assert!(
            (c.weight - omega).abs() <= 1e-12,
            "reported ω {} vs {omega}",
            c.weight
        );
        // `force` is what the sample applies to the tissue: inwards, against the normal.
        let normal = -c.force.dot(&c.normal);
        let expected = omega * params.stiffness * c.depth;
        assert!(
            (normal - expected).abs() <= 1e-9 * params.stiffness * c.depth,
            "sample {}: normal force {normal} N, expected ω = {omega} × {} N",
            c.sample,
            params.stiffness * c.depth
        );
        if omega > 0.0 && omega < 1.0 {
            faded += 1;
        }
    }
    assert!(faded > 0, "no contact on the collapsing leaf's triangles");
}
