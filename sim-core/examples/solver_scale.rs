//! Jacobi-PCG against MG-PCG on the cantilever beams, each step solved to a relative
//! residual of 1e-6 (the same runs as `cosurg bench scale`, without the client, so that
//! a release build needs sim-core only): `cargo run --release -p cosurg-sim-core
//! --example solver_scale -- [steps]`. Prints one JSON object per line: beam, tets, dt,
//! solver, mean and max CG iterations, p50/p99 ms per step (one thread).

use std::time::Instant;

use cosurg_sim_core::sim_fem::LinearSolver;
use cosurg_sim_core::{SimOptions, Simulation};

fn percentile(samples: &[f64], p: f64) -> f64 {
    let mut s = samples.to_vec();
    s.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * s.len() as f64).ceil().max(1.0) as usize;
    s[rank.min(s.len()) - 1]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(40);
    for (material, young) in [("soft", 1e5), ("stiff", 1e6)] {
        for cell in [0.025, 0.0125] {
            for dt in [0.001, 0.01] {
                for solver in LinearSolver::ALL {
                    let scene = cosurg_sim_core::sim_scene::builtin::cantilever_with(young, cell)?;
                    let mut o = SimOptions::from_scene(&scene.scene);
                    o.dt = dt;
                    o.step.linear_solver = solver;
                    o.step.solver.tol = 1e-6;
                    o.step.solver.max_iters = 20_000;
                    let mut sim = Simulation::new(scene, o)?;
                    for _ in 0..3 {
                        sim.step()?;
                    }
                    let (mut ms, mut iters, mut res) = (Vec::new(), Vec::new(), 0.0f64);
                    for _ in 0..steps {
                        let t = Instant::now();
                        let r = sim.step()?;
                        ms.push(t.elapsed().as_secs_f64() * 1e3);
                        iters.push(r.fem.cg_iterations);
                        res = res.max(r.fem.cg_residual);
                    }
                    println!(
                        "{{\"material\":\"{material}\",\"young_pa\":{young},\"tets\":{},\"dt_s\":{dt},\"solver\":\"{}\",\"steps\":{steps},\"iterations_mean\":{:.1},\"iterations_max\":{},\"ms_p50\":{:.3},\"ms_p99\":{:.3},\"residual_max\":{res:.2e}}}",
                        sim.lattice().leaf_count(),
                        solver.name(),
                        iters.iter().sum::<usize>() as f64 / steps as f64,
                        iters.iter().max().unwrap_or(&0),
                        percentile(&ms, 50.0),
                        percentile(&ms, 99.0),
                    );
                }
            }
        }
    }
    Ok(())
}
