//! Jacobi-PCG against MG-PCG on the cantilever beams, each step solved to a relative
//! residual of 1e-6 (the same runs as `cosurg bench scale`, without the client, so that
//! a release build needs sim-core only): `cargo run --release -p cosurg-sim-core
//! --example solver_scale -- [steps] [beam soft|stiff] [cell m] [dt s] [solver]`
//! (each filter optional, for profiling one configuration with `perf`). Environment
//! variables override: `COSURG_MG_SWEEPS` (the multigrid's Gauss–Seidel sweeps),
//! `COSURG_MG_REFRESH` (its coarse refresh period), `COSURG_THREADS` (the step's threads),
//! `COSURG_WARM_START` (0/1: start from the last converged Δv; default 0), `COSURG_TOL` (the
//! relative residual, default 1e-6) and `COSURG_SHARING_DEG` (rotation sharing θ_tol,
//! default the scene's: none). Prints one JSON object per line: beam, tets, dt, solver,
//! mean and max CG iterations, p50/p99/min wall ms and mean on-CPU ms per step (one
//! thread), the largest residual, rotation extractions per step and the multigrid's level
//! sizes.

use std::time::Instant;

use cosurg_sim_core::sim_fem::LinearSolver;
use cosurg_sim_core::{SimOptions, Simulation};

fn percentile(samples: &[f64], p: f64) -> f64 {
    let mut s = samples.to_vec();
    s.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * s.len() as f64).ceil().max(1.0) as usize;
    s[rank.min(s.len()) - 1]
}

/// On-CPU time of this thread (ms; tick-quantised on some kernels, hence a mean over the
/// steps, not a percentile) from Linux's `/proc/thread-self/schedstat` (first
/// field, ns): unlike wall time it does not count the time the thread waited for a core,
/// so it stays meaningful on a loaded machine. NaN where the file is missing.
fn thread_cpu_ms() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(f64::NAN, |ns| ns * 1e-6)
}

fn env_usize(name: &str) -> Option<usize> {
    std::env::var(name).ok()?.parse().ok()
}

fn env_f64(name: &str) -> Option<f64> {
    std::env::var(name).ok()?.parse().ok()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(40);
    let arg = |i: usize| std::env::args().nth(i);
    let want_material = arg(2);
    let num = |i: usize| arg(i).and_then(|s| s.parse::<f64>().ok());
    let cells = num(3).map_or(vec![0.025, 0.0125], |c| vec![c]);
    let dts = num(4).map_or(vec![0.001, 0.01], |d| vec![d]);
    let want_solver = arg(5);
    for (material, young) in [("soft", 1e5), ("stiff", 1e6)] {
        if want_material.as_deref().is_some_and(|m| m != material) {
            continue;
        }
        for &cell in &cells {
            for &dt in &dts {
                for solver in LinearSolver::ALL {
                    if want_solver.as_deref().is_some_and(|s| s != solver.name()) {
                        continue;
                    }
                    let scene = cosurg_sim_core::sim_scene::builtin::cantilever_with(young, cell)?;
                    let mut o = SimOptions::from_scene(&scene.scene);
                    o.dt = dt;
                    o.step.linear_solver = solver;
                    o.step.solver.tol = env_f64("COSURG_TOL").unwrap_or(1e-6);
                    o.step.solver.max_iters = 20_000;
                    if let Some(k) = env_usize("COSURG_MG_SWEEPS") {
                        o.step.mg_sweeps = k;
                    }
                    if let Some(k) = env_usize("COSURG_MG_REFRESH") {
                        o.step.mg_refresh_steps = k;
                    }
                    if let Some(w) = env_usize("COSURG_WARM_START") {
                        o.step.solver.warm_start = w != 0;
                    }
                    if let Some(a) = env_f64("COSURG_SHARING_DEG") {
                        o.sharing_angle_deg = (a > 0.0).then_some(a);
                    }
                    if let Some(t) = env_usize("COSURG_THREADS") {
                        o.step.threads = t;
                    }
                    let mut sim = Simulation::new(scene, o)?;
                    for _ in 0..3 {
                        sim.step()?;
                    }
                    let (mut ms, mut iters, mut res) = (Vec::new(), Vec::new(), 0.0f64);
                    let mut cpu = Vec::new();
                    let mut extracted = 0usize;
                    for _ in 0..steps {
                        let (t, c) = (Instant::now(), thread_cpu_ms());
                        let r = sim.step()?;
                        ms.push(t.elapsed().as_secs_f64() * 1e3);
                        cpu.push(thread_cpu_ms() - c);
                        iters.push(r.fem.cg_iterations);
                        res = res.max(r.fem.cg_residual);
                        extracted += r.fem.rotations_extracted;
                    }
                    // Node count per multigrid level, finest first (MG-PCG only).
                    let levels = sim.fem()?.multigrid_level_sizes().unwrap_or_default();
                    println!(
                        "{{\"material\":\"{material}\",\"young_pa\":{young},\"tets\":{},\"dt_s\":{dt},\"solver\":\"{}\",\"steps\":{steps},\"iterations_mean\":{:.1},\"iterations_max\":{},\"ms_p50\":{:.3},\"ms_p99\":{:.3},\"ms_min\":{:.3},\"cpu_ms_mean\":{:.3},\"residual_max\":{res:.2e},\"rotations_per_step\":{:.0},\"levels\":{levels:?}}}",
                        sim.lattice().leaf_count(),
                        solver.name(),
                        iters.iter().sum::<usize>() as f64 / steps as f64,
                        iters.iter().max().unwrap_or(&0),
                        percentile(&ms, 50.0),
                        percentile(&ms, 99.0),
                        ms.iter().copied().fold(f64::INFINITY, f64::min),
                        cpu.iter().sum::<f64>() / steps as f64,
                        extracted as f64 / steps as f64,
                    );
                }
            }
        }
    }
    Ok(())
}
