//! Cost of one co-rotational step on the cantilever beam with every speed-up on (the
//! configuration `cosurg bench cantilever` calls `all-on`), for profiling the FEM step
//! without the client: `cargo run --release -p cosurg-sim-core --example step_cost --
//! [young Pa] [cell m] [dt s] [steps] [threads] [energy guard 1|0] [CG iterations]`, e.g.
//! `1e5 0.0125 0.01 200 1 1 50`. Prints the p50 / p99 step time, mean CG iterations and
//! the tip position (to check that an optimisation changed nothing but the time).

use std::time::Instant;

use cosurg_sim_core::sim_fem::{ByersXu, PolarMethod, SolverParams, StiffnessMode};
use cosurg_sim_core::{SimOptions, Simulation};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let arg = |i: usize, default: f64| -> f64 {
        std::env::args()
            .nth(i)
            .and_then(|s| s.parse().ok())
            .unwrap_or(default)
    };
    let (young, cell, dt) = (arg(1, 1e5), arg(2, 0.0125), arg(3, 0.01));
    let steps = arg(4, 200.0) as usize;
    let threads = arg(5, 1.0) as usize;
    let scene = cosurg_sim_core::sim_scene::builtin::cantilever_with(young, cell)?;
    let mut o = SimOptions::from_scene(&scene.scene);
    o.dt = dt;
    o.step.polar = PolarMethod::ByersXu(ByersXu {
        tol: 1e-6,
        ..ByersXu::default()
    });
    o.sharing_angle_deg = Some(5.0);
    o.step.stiffness = StiffnessMode::Template;
    o.step.rest_threshold = 1e-6;
    o.step.solver = SolverParams {
        max_iters: 50,
        tol: 1e-6,
        warm_start: false,
    };
    o.step.threads = threads;
    o.step.energy_guard = arg(6, 1.0) != 0.0;
    o.step.solver.max_iters = arg(7, 50.0) as usize;
    let mut sim = Simulation::new(scene, o)?;
    sim.fem()?;
    let mut ms = Vec::with_capacity(steps);
    let mut cg = 0usize;
    for _ in 0..steps {
        let t0 = Instant::now();
        let r = sim.step()?;
        ms.push(t0.elapsed().as_secs_f64() * 1e3);
        cg += r.fem.cg_iterations;
    }
    ms.sort_by(f64::total_cmp);
    let tip = sim.probes().into_iter().next().map(|p| p.1);
    println!(
        "{} tets, dt {dt} s, {threads} thread(s): step p50 {:.3} ms, p99 {:.3} ms, CG {:.1}/step, tip {:?}",
        sim.lattice().leaf_count(),
        ms[ms.len() / 2],
        ms[(ms.len() * 99) / 100],
        cg as f64 / steps as f64,
        tip
    );
    Ok(())
}
