//! Bodies joined by a connective layer (`[[attachment]]`): a block tied under a fixed
//! block hangs from it; untied (every spring released) it falls freely; releases are
//! topology operations whose result does not depend on their order.

use std::path::Path;

use cosurg_sim_core::cut::{OpId, ReleaseOp, TopologyOp};
use cosurg_sim_core::sim_scene::Scene;
use cosurg_sim_core::{Interaction, SimError, SimOptions, Simulation};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// Host block (fixed at its top) above a hanging block, one empty 1 cm cell between them,
/// tied by a layer of 200 N/m over the hanging block's top face. No damping on the hanging
/// block, so that its free fall has a closed form.
fn two_blocks(attachment: bool) -> String {
    two_blocks_with(attachment, "")
}

/// [`two_blocks`] with extra scene text (tools).
fn two_blocks_with(attachment: bool, extra: &str) -> String {
    let layer = if attachment {
        r#"
[[attachment]]
name = "layer"
bodies = ["host", "hanging"]
box = { min = [-0.001, -0.001, 0.019], max = [0.041, 0.041, 0.021] }
stiffness = 200.0
reach = 0.015
release_rate = 100.0
release_force = 0.0
release_radius = 0.01
"#
    } else {
        ""
    };
    format!(
        r#"
version = 1
gravity = [0.0, 0.0, -9.81]

[material.host]
young = 5.0e4
poisson = 0.4
density = 1000.0
rayleigh_mass = 2.0

[material.soft]
young = 5.0e4
poisson = 0.4
density = 1000.0

[[body]]
name = "host"
box = {{ min = [0.0, 0.0, 0.03], max = [0.04, 0.04, 0.05] }}
cell = 0.01
material = "host"

[[body]]
name = "hanging"
box = {{ min = [0.0, 0.0, 0.0], max = [0.04, 0.04, 0.02] }}
cell = 0.01
material = "soft"

[[fix]]
box = {{ min = [-1.0, -1.0, 0.049], max = [1.0, 1.0, 0.051] }}
{layer}
{extra}
[simulation]
dt = 0.002
model = "corotational"

[features]
contact = false
"#
    )
}

fn sim_of(text: &str) -> Result<Simulation, SimError> {
    let scene = Scene::from_str(text, Path::new("."), "two-blocks")?;
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options)
}

/// Mean of the hanging block's surface vertices (m).
fn hanging_centroid(sim: &Simulation) -> V3 {
    let s = &sim.surfaces()[1];
    s.deformed.iter().sum::<V3>() / s.deformed.len() as f64
}

fn release_all(sim: &Simulation, site: u32) -> TopologyOp {
    TopologyOp::Release(ReleaseOp {
        id: OpId { site, seq: 0 },
        layer: 0,
        springs: (0..sim.attachments().layers[0].springs.len() as u32).collect(),
    })
}

#[test]
fn tied_block_hangs_and_untied_block_falls() {
    let mut tied = sim_of(&two_blocks(true)).expect("tied scene");
    let layer = &tied.attachments().layers[0];
    // The hanging block's top face has 5 x 5 surface vertices, each 1 cm below a host one.
    assert_eq!(layer.springs.len(), 25);
    assert!(
        layer
            .springs
            .iter()
            .all(|s| (s.rest_length - 0.01).abs() < 1e-12)
    );
    let mut untied = sim_of(&two_blocks(true)).expect("untied scene");
    let op = release_all(&untied, 0);
    let change = untied.apply_topology_op(op).expect("release");
    assert_eq!(change.released, 25);
    assert_eq!(untied.attachments().layers[0].holding(), 0);
    let mut loose = sim_of(&two_blocks(false)).expect("scene without the layer");

    let c0 = hanging_centroid(&tied);
    let steps = 100; // 0.2 s
    for _ in 0..steps {
        tied.step().expect("tied step");
        untied.step().expect("untied step");
        loose.step().expect("loose step");
    }
    let t = steps as f64 * 0.002;
    // Backward Euler under constant gravity from rest: x_n = g dt² n (n + 1) / 2.
    let free_fall = 9.81 * 0.002 * 0.002 * (steps * (steps + 1)) as f64 / 2.0;
    for (what, sim) in [("released", &untied), ("without a layer", &loose)] {
        let drop = c0.z - hanging_centroid(sim).z;
        assert!(
            (drop - free_fall).abs() < 0.01 * free_fall,
            "{what}: the block fell {drop} m in {t} s, free fall is {free_fall} m"
        );
    }
    // Tied: the layer carries the block's weight, m g / k = 0.032 kg · 9.81 / 200 N/m =
    // 1.57 mm of stretch, plus the host's sag; it swings about that (no damping on the
    // hanging block), so it stays within twice the stretch plus 1 mm.
    let mut worst: f64 = 0.0;
    for _ in 0..150 {
        tied.step().expect("tied step");
        worst = worst.max(c0.z - hanging_centroid(&tied).z);
    }
    let stretch = 0.032 * 9.81 / 200.0;
    let drop = c0.z - hanging_centroid(&tied).z;
    assert!(drop > 0.2 * stretch, "tied block moved only {drop} m");
    assert!(
        worst < 2.0 * stretch + 0.001,
        "tied block dropped up to {worst} m, the layer's stretch is {stretch} m"
    );
}

#[test]
fn releases_in_any_order_give_the_same_topology() {
    let ops: Vec<TopologyOp> = (0..5u32)
        .map(|k| {
            TopologyOp::Release(ReleaseOp {
                id: OpId {
                    site: k % 2,
                    seq: k,
                },
                layer: 0,
                // Overlapping sets: springs released twice stay released once.
                springs: (k * 4..k * 4 + 6).collect(),
            })
        })
        .collect();
    let mut a = sim_of(&two_blocks(true)).expect("scene");
    let mut b = sim_of(&two_blocks(true)).expect("scene");
    for op in &ops {
        a.apply_topology_op(op.clone()).expect("apply");
    }
    for op in ops.iter().rev().chain(ops.iter()) {
        b.apply_topology_op(op.clone()).expect("apply");
    }
    assert_eq!(a.topology().epoch(), 5);
    assert_eq!(b.topology().epoch(), 5);
    assert_eq!(a.topology().digest(), b.topology().digest());
    assert_eq!(
        a.attachments().layers[0].released_indices(),
        (0..22).collect::<Vec<u32>>()
    );
    // Fewer ops: another digest.
    let mut c = sim_of(&two_blocks(true)).expect("scene");
    for op in &ops[..4] {
        c.apply_topology_op(op.clone()).expect("apply");
    }
    assert_ne!(a.topology().digest(), c.topology().digest());
}

#[test]
fn bad_releases_and_touching_bodies_are_rejected() {
    let mut sim = sim_of(&two_blocks(true)).expect("scene");
    let bad = TopologyOp::Release(ReleaseOp {
        id: OpId { site: 0, seq: 0 },
        layer: 0,
        springs: vec![25],
    });
    let e = sim.apply_topology_op(bad).unwrap_err().to_string();
    assert!(e.contains("no spring 25"), "{e}");
    let bad = TopologyOp::Release(ReleaseOp {
        id: OpId { site: 0, seq: 1 },
        layer: 3,
        springs: vec![0],
    });
    let e = sim.apply_topology_op(bad).unwrap_err().to_string();
    assert!(e.contains("no attachment layer 3"), "{e}");
    assert_eq!(sim.topology().epoch(), 0);

    // The hanging block moved up against the host: their cells touch.
    let touching = two_blocks(true)
        .replace("max = [0.04, 0.04, 0.02] }", "max = [0.04, 0.04, 0.025] }")
        .replace("[0.041, 0.041, 0.021]", "[0.041, 0.041, 0.026]")
        .replace(
            "min = [-0.001, -0.001, 0.019]",
            "min = [-0.001, -0.001, 0.024]",
        );
    let e = sim_of(&touching).err().expect("rejected").to_string();
    assert!(e.contains("share lattice nodes"), "{e}");
}

/// The tied blocks with a hook held still in the middle of the layer; its release radius
/// widened from 0.01 to 0.015 m: the 3 x 3 springs around the centre (midpoints 0, 0.01
/// and 0.0141 m away) are within reach.
fn hook_over_the_centre() -> String {
    let hook = r#"
[[tool]]
name = "hook"
kind = "hook"
position = [0.02, 0.02, 0.025]
"#;
    two_blocks_with(true, hook).replace("release_radius = 0.01", "release_radius = 0.015")
}

/// A hook held still in the middle of the layer releases the springs within its radius at
/// the layer's rate, nearest first, and only those carrying at least the threshold force.
#[test]
fn hook_releases_springs_near_its_tip_at_the_rate() {
    let text = hook_over_the_centre();
    let run = |text: &str, steps: usize| {
        let mut sim = sim_of(text).expect("scene");
        let mut interaction = Interaction::new(&sim);
        let mut released = 0;
        for _ in 0..steps {
            let inputs = interaction.scripted_inputs(&sim, sim.time());
            released += interaction
                .before_step(&mut sim, &inputs)
                .expect("hook")
                .released;
            sim.step().expect("step");
        }
        (sim, released, interaction.hooks.made.len())
    };
    // 100 springs/s over 0.03 s: 3 releases gained (within one of it: float sums).
    let (sim, released, ops) = run(&text, 15);
    assert!((2..=3).contains(&released), "{released} released in 0.03 s");
    assert_eq!(sim.topology().epoch() as usize, ops);
    // Over 0.2 s the nine within reach go, nearest first, and no other.
    let (sim, released, _) = run(&text, 100);
    assert_eq!(released, 9);
    let layer = &sim.attachments().layers[0];
    for (i, s) in layer.springs.iter().enumerate() {
        let off = ((s.attached.x - 0.02).powi(2) + (s.attached.y - 0.02).powi(2)).sqrt();
        assert_eq!(layer.is_released(i), off < 0.015, "spring {i} at {off} m");
    }
    // A threshold above what the springs carry (the block's 0.31 N over 25 springs, with
    // its swing): nothing releases.
    let strong = text.replace("release_force = 0.0", "release_force = 1.0");
    let (_, released, _) = run(&strong, 100);
    assert_eq!(released, 0);
}

/// A hook whose site schedules its releases (`apply_own` off, as under hybrid sync) makes
/// the same releases as one that applies them at once, but applies none itself, and never
/// puts a spring it released into a second op while the first is pending.
#[test]
fn a_scheduling_hook_releases_each_spring_once_and_applies_nothing_itself() {
    let text = hook_over_the_centre();
    let mut sim = sim_of(&text).expect("scene");
    let mut interaction = Interaction::new(&sim);
    interaction.hooks.apply_own = false;
    for _ in 0..100 {
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        let report = interaction.before_step(&mut sim, &inputs).expect("hook");
        assert_eq!(report.released, 0, "nothing applied by the hook itself");
        sim.step().expect("step");
    }
    assert_eq!(sim.topology().epoch(), 0);
    let mut springs: Vec<u32> = interaction
        .hooks
        .made
        .iter()
        .flat_map(|op| match op {
            TopologyOp::Release(r) => r.springs.clone(),
            other => panic!("a hook made {other:?}"),
        })
        .collect();
    let n = springs.len();
    springs.sort_unstable();
    springs.dedup();
    assert_eq!(springs.len(), n, "a spring in two ops: {springs:?}");
    // The nine within reach, as when applied at once (the test above).
    assert_eq!(n, 9);
    // Applied later (by the session, at the op's time): the same springs go.
    for op in interaction.hooks.made.clone() {
        sim.apply_topology_op(op).expect("release");
    }
    let layer = &sim.attachments().layers[0];
    for (i, s) in layer.springs.iter().enumerate() {
        let off = ((s.attached.x - 0.02).powi(2) + (s.attached.y - 0.02).powi(2)).sqrt();
        assert_eq!(layer.is_released(i), off < 0.015, "spring {i} at {off} m");
    }
}

/// A blade cuts the tied block in two (a vertical sheet at x = 20.1 mm, through the
/// hanging block only): every spring then pulls on the part on its own side of the cut,
/// and both parts keep hanging from the layer.
#[test]
fn a_cut_through_a_tied_block_splits_its_springs_and_both_parts_hang() {
    use cosurg_sim_core::cut::CutOp;
    let cut_x = 0.0201;
    let mut sim = sim_of(&two_blocks(true)).expect("scene");
    let c0 = hanging_centroid(&sim);
    let (y0, y1, z0, z1) = (-0.01, 0.05, -0.01, 0.025);
    let op = TopologyOp::Cut(CutOp {
        id: OpId { site: 0, seq: 0 },
        triangles: vec![
            [[cut_x, y0, z0], [cut_x, y1, z0], [cut_x, y1, z1]],
            [[cut_x, y0, z0], [cut_x, y1, z1], [cut_x, y0, z1]],
        ],
    });
    let change = sim.apply_topology_op(op).expect("cut");
    assert!(change.crossed > 0 && change.virtual_nodes > 0, "{change:?}");

    // Parts of the element graph (copies sharing a degree of freedom).
    let sep = sim.separation().expect("cut").clone();
    let mut parent: Vec<usize> = (0..sep.dof_count()).collect();
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
    let layer = &sim.attachments().layers[0];
    let mut part = [None, None]; // left, right of the cut
    for (i, s) in layer.springs.iter().enumerate() {
        let parts: Vec<usize> = layer
            .end_dofs(2 * i)
            .iter()
            .map(|&d| find(&mut parent, d))
            .collect();
        assert!(
            parts.iter().all(|&p| p == parts[0]),
            "spring {i} (attached at {:?}) pulls on both parts: {parts:?}",
            s.attached
        );
        let side = usize::from(s.attached.x > cut_x);
        match part[side] {
            None => part[side] = Some(parts[0]),
            Some(p) => assert_eq!(p, parts[0], "spring {i} pulls on another part"),
        }
    }
    assert_ne!(
        part[0], part[1],
        "the cut left the hanging block in one part"
    );

    // Both parts hang: each half of the block stays within the layer's stretch (see
    // `tied_block_hangs_and_untied_block_falls`) of where it was; a part that the layer
    // no longer held would fall 1.2 m in 0.5 s.
    for _ in 0..250 {
        sim.step().expect("step");
    }
    let s = &sim.surfaces()[1];
    for (side, keep) in [("left", true), ("right", false)] {
        let pts: Vec<V3> = s
            .rest
            .vertices
            .iter()
            .zip(&s.deformed)
            .filter(|(r, _)| (r.x < cut_x - 0.002) == keep && (r.x - cut_x).abs() > 0.002)
            .map(|(_, d)| *d)
            .collect();
        let z = pts.iter().map(|p| p.z).sum::<f64>() / pts.len() as f64;
        let drop = c0.z - z;
        let stretch = 0.032 * 9.81 / 200.0;
        assert!(
            drop < 2.0 * stretch + 0.002,
            "{side} part dropped {drop} m (layer stretch {stretch} m)"
        );
    }
}
