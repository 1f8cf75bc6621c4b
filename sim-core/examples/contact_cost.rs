//! Cost of the tool pass (contact detection + response, adaptivity) per step on the
//! default scene, driven by its scripts: `cargo run --release -p cosurg-sim-core
//! --example contact_cost [steps]`.

use std::time::Instant;

use cosurg_sim_core::{Interaction, SimOptions, Simulation};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(2500);
    let scene = cosurg_sim_core::sim_scene::builtin::cholecystectomy();
    println!("scene {} ({})", scene.file, &scene.hash[..12]);
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene, options)?;
    let mut ia = Interaction::new(&sim);
    println!(
        "leaves {}, nodes {}, tools {} (samples {:?})",
        sim.lattice().leaf_count(),
        sim.lattice().node_count(),
        ia.tools.len(),
        ia.tools
            .tools
            .iter()
            .map(|t| t.sample_count())
            .collect::<Vec<_>>()
    );
    let mut contact_us = Vec::with_capacity(steps);
    let mut step_us = Vec::with_capacity(steps);
    let mut adapt_us = Vec::new();
    for _ in 0..steps {
        let inputs = ia.scripted_inputs(&sim, sim.time());
        let t0 = Instant::now();
        let r = ia.before_step(&mut sim, &inputs)?;
        let t1 = Instant::now();
        sim.step()?;
        let t2 = Instant::now();
        if r.adapt.ran {
            adapt_us.push((t1 - t0).as_secs_f64() * 1e6);
        } else {
            contact_us.push((t1 - t0).as_secs_f64() * 1e6);
        }
        step_us.push((t2 - t1).as_secs_f64() * 1e6);
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let p99 = v
            .get((v.len() as f64 * 0.99) as usize)
            .copied()
            .unwrap_or(0.0);
        (mean, v.get(v.len() / 2).copied().unwrap_or(0.0), p99)
    };
    let (m, med, p99) = stats(&mut contact_us);
    println!(
        "contact pass (steps without adaptivity work): mean {m:.1} µs, median {med:.1} µs, p99 {p99:.1} µs"
    );
    let adapt_passes = adapt_us.len();
    let (m, med, p99) = stats(&mut adapt_us);
    println!(
        "tool pass on steps where adaptivity looked at the lattice ({adapt_passes}): mean {m:.0} µs, median {med:.0} µs, p99 {p99:.0} µs"
    );
    let (m, med, p99) = stats(&mut step_us);
    println!("simulation step: mean {m:.0} µs, median {med:.0} µs, p99 {p99:.0} µs");
    let st = ia.state().stats;
    println!(
        "passes run {}, narrow tests/pass {:.0}, candidate triangles/pass {:.0}, leaf tests/pass {:.0}, cache rebuilds {}, adaptivity passes {adapt_passes}, leaves now {}, samples nearest inverted leaves {}",
        st.passes_run,
        st.narrow_tests as f64 / st.passes_run as f64,
        st.candidate_triangles as f64 / st.passes_run as f64,
        st.leaf_tests as f64 / st.passes_run as f64,
        st.cache_rebuilds,
        sim.lattice().leaf_count(),
        st.samples_on_inverted
    );
    for t in &ia.state().tools {
        println!(
            "{}: force {:?} N, contacts {}, grasped {}",
            t.name,
            t.force.as_slice(),
            t.contacts.len(),
            t.grasped
        );
    }
    Ok(())
}
