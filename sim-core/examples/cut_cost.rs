//! What cutting costs, on `scenes/cut-block.toml` (or the scene given): step times before,
//! during and after the blade's stroke, the time to apply the cut on the cutting site and
//! to apply the same op received on a second site, and the op's bytes.
//!
//! `cargo run --release -p cosurg-sim-core --example cut_cost [-- SCENE [SECONDS]]`

use std::path::PathBuf;
use std::time::Instant;

use cosurg_sim_core::sim_scene::Scene;
use cosurg_sim_core::{Interaction, SimOptions, Simulation};

fn percentile(v: &[f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((p / 100.0) * (s.len() - 1) as f64).round() as usize]
}

fn main() {
    let mut args = std::env::args().skip(1);
    let given = args.next();
    let label = given
        .clone()
        .unwrap_or_else(|| "scenes/cut-block.toml".into());
    let path = given.map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenes/cut-block.toml")
    });
    let seconds: f64 = args.next().map_or(1.8, |s| s.parse().expect("seconds"));
    let scene = Scene::load(&path).expect("scene");
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene.clone(), options.clone()).expect("simulation");
    let mut receiver = Simulation::new(scene, options).expect("simulation");
    let mut interaction = Interaction::new(&sim);
    let dt = sim.options().dt;
    let (mut before, mut stroke, mut after) = (Vec::new(), Vec::new(), Vec::new());
    let mut cut_step_ms = None;
    let steps = (seconds / dt).round() as usize;
    for _ in 0..steps {
        let t0 = Instant::now();
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        let report = interaction
            .before_step(&mut sim, &inputs)
            .expect("before_step");
        sim.step().expect("step");
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let blade_in_body = interaction
            .tools
            .tools
            .iter()
            .filter_map(|t| t.blade_edge())
            .any(|(a, b)| {
                (0..5).any(|k| {
                    let q = a + (k as f64 / 4.0) * (b - a);
                    matches!(sim.rest_point_of(&q), Some((_, true)))
                })
            });
        if report.cuts > 0 {
            cut_step_ms = Some(ms);
        } else if sim.topology().epoch() > 0 {
            after.push(ms);
        } else if blade_in_body {
            stroke.push(ms);
        } else {
            before.push(ms);
        }
    }
    println!(
        "scene {label}: {} leaves, {} elements after the cut, dt {dt} s, {steps} steps",
        sim.lattice().leaf_count(),
        sim.separation().map_or(0, |s| s.copies.len())
    );
    for (name, v) in [
        ("before the stroke", &before),
        ("blade in the body", &stroke),
        ("after the cut", &after),
    ] {
        println!(
            "step {name}: {} steps, p50 {:.3} ms, p99 {:.3} ms",
            v.len(),
            percentile(v, 50.0),
            percentile(v, 99.0)
        );
    }
    if let Some(ms) = cut_step_ms {
        println!("the step that committed and applied the cut: {ms:.3} ms");
    }
    let log = sim.topology();
    println!(
        "topology epoch {}, digest {:016x}, op log {} bytes ({} triangles)",
        log.epoch(),
        log.digest(),
        log.wire_bytes(),
        log.ops()
            .map(|o| match o {
                cosurg_sim_core::cut::TopologyOp::Cut(c) => c.triangles.len(),
                _ => 0,
            })
            .sum::<usize>()
    );
    // A second site receiving the op (and then a duplicate of it).
    for op in log.ops().cloned().collect::<Vec<_>>() {
        let t0 = Instant::now();
        let change = receiver.apply_topology_op(op.clone()).expect("apply");
        let first = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        receiver.step().expect("step");
        let rebuild = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        receiver.apply_topology_op(op).expect("apply");
        let dup = t2.elapsed().as_secs_f64() * 1e3;
        println!(
            "received op applied in {first:.3} ms (refined {} leaves, {} crossed, {} virtual \
             nodes); first step after it (FEM rebuild) {rebuild:.3} ms; duplicate {dup:.4} ms",
            change.refined, change.crossed, change.virtual_nodes
        );
    }
    println!(
        "receiver digest {:016x} ({})",
        receiver.topology().digest(),
        if receiver.topology().digest() == sim.topology().digest() {
            "equal"
        } else {
            "DIFFERENT"
        }
    );
}
