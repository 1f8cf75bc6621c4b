//! What dissecting and cutting cost, on `scenes/cholecystectomy-bodies.toml` (the default
//! scene; or the scene given), all its tool scripts on one site: step times (tools + FEM
//! step) before the hook reaches the bed, while it releases springs, after, and the step
//! that commits a cut; the time a second simulation takes to apply each release, clip and
//! cut it receives; the ops' bytes; the two digests.
//!
//! `cargo run --release -p cosurg-sim-core --example dissect_cost [-- SCENE [SECONDS]]`

use std::path::PathBuf;
use std::time::Instant;

use cosurg_sim_core::cut::TopologyOp;
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

fn row(what: &str, v: &[f64]) {
    println!(
        "{what:<44} p50 {:.3} ms  p99 {:.3} ms  max {:.3} ms  ({} steps)",
        percentile(v, 50.0),
        percentile(v, 99.0),
        percentile(v, 100.0),
        v.len()
    );
}

fn main() {
    let mut args = std::env::args().skip(1);
    let given = args.next();
    let label = given
        .clone()
        .unwrap_or_else(|| "scenes/cholecystectomy-bodies.toml".into());
    let path = given.map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenes/cholecystectomy-bodies.toml")
    });
    // The scripts end with the blade's stroke through the duct at 16.8 s.
    let seconds: f64 = args.next().map_or(17.2, |s| s.parse().expect("seconds"));
    let scene = Scene::load(&path).expect("scene");
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene.clone(), options.clone()).expect("simulation");
    let mut receiver = Simulation::new(scene, options).expect("simulation");
    let mut interaction = Interaction::new(&sim);
    let dt = sim.options().dt;
    let springs: usize = sim
        .attachments()
        .layers
        .iter()
        .map(|l| l.springs.len())
        .sum();
    let (mut before, mut dissecting, mut after) = (Vec::new(), Vec::new(), Vec::new());
    let (mut apply_ms, mut release_bytes, mut release_ops, mut released) =
        (Vec::new(), 0usize, 0usize, 0usize);
    let mut cut_steps = Vec::new();
    let (mut clip_apply_ms, mut cut_apply_ms) = (Vec::new(), Vec::new());
    let steps = (seconds / dt).round() as usize;
    for _ in 0..steps {
        let t0 = Instant::now();
        let inputs = interaction.scripted_inputs(&sim, sim.time());
        let r = interaction.before_step(&mut sim, &inputs).expect("tools");
        sim.step().expect("step");
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        released += r.released;
        let holding: usize = sim.attachments().layers.iter().map(|l| l.holding()).sum();
        if r.cuts > 0 {
            cut_steps.push(ms);
        } else if released == 0 {
            before.push(ms);
        } else if holding > 0 || r.released > 0 {
            dissecting.push(ms);
        } else {
            after.push(ms);
        }
        // The receiver applies what this site made (as a remote site would).
        let made: Vec<TopologyOp> = interaction
            .hooks
            .made
            .drain(..)
            .chain(interaction.blades.made.drain(..))
            .chain(interaction.clips.made.drain(..))
            .collect();
        for op in made {
            if let TopologyOp::Release(_) = &op {
                release_ops += 1;
                release_bytes += op.wire_bytes();
                let t = Instant::now();
                receiver.apply_topology_op(op).expect("apply");
                apply_ms.push(t.elapsed().as_secs_f64() * 1e3);
            } else {
                let is_cut = matches!(op, TopologyOp::Cut(_));
                let t = Instant::now();
                receiver.apply_topology_op(op).expect("apply clip or cut");
                let ms = t.elapsed().as_secs_f64() * 1e3;
                if is_cut {
                    cut_apply_ms.push(ms);
                } else {
                    clip_apply_ms.push(ms);
                }
            }
        }
    }
    println!(
        "{label} ({} s simulated, dt {} s, {} springs in the layers)",
        seconds, dt, springs
    );
    row("step before the hook releases", &before);
    row("step while the hook releases springs", &dissecting);
    row("step after the bed is released", &after);
    row("step that committed a cut", &cut_steps);
    println!(
        "springs released {released} in {release_ops} ops, {release_bytes} bytes as carried \
         ({:.1} bytes per op)",
        release_bytes as f64 / release_ops.max(1) as f64
    );
    println!(
        "applying a received release op: p50 {:.4} ms  p99 {:.4} ms  max {:.4} ms",
        percentile(&apply_ms, 50.0),
        percentile(&apply_ms, 99.0),
        percentile(&apply_ms, 100.0)
    );
    println!(
        "applying a received clip: {:?} ms; a received cut: {:?} ms",
        clip_apply_ms
            .iter()
            .map(|v| (v * 1e3).round() / 1e3)
            .collect::<Vec<_>>(),
        cut_apply_ms
            .iter()
            .map(|v| (v * 10.0).round() / 10.0)
            .collect::<Vec<_>>()
    );
    println!(
        "topology epoch {} / {}, digest {:016x} / {:016x} (cutting site / receiver)",
        sim.topology().epoch(),
        receiver.topology().epoch(),
        sim.topology().digest(),
        receiver.topology().digest()
    );
}
