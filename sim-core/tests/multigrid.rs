//! MG-PCG (`LinearSolver::MgPcg`, the lattice hierarchy) against Jacobi-PCG on the
//! simulation's own steps: same solution, far fewer iterations on the 12k-tet beam, and
//! robust on an adaptive lattice with a 1000× stiffer rod.

use std::path::Path;

use cosurg_sim_core::sim_fem::LinearSolver;
use cosurg_sim_core::sim_scene::{LoadedScene, Scene};
use cosurg_sim_core::{SimOptions, Simulation};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// The cantilever beam (0.4 × 0.1 × 0.1 m, 2.5 cm cells: 1,536 root tets), clamped at
/// x = 0 under gravity; with `rod`, a capsule along its axis 1000× stiffer.
fn beam_scene(rod: bool) -> LoadedScene {
    let inclusion = if rod {
        r#"[[body.inclusion]]
material = "stiff"
capsules = [{ a = [0.0, 0.05, 0.05], b = [0.4, 0.05, 0.05], radius = 0.015 }]"#
    } else {
        ""
    };
    let text = format!(
        r#"
version = 1
gravity = [0.0, 0.0, -9.81]
[material.tissue]
young = 1.0e5
poisson = 0.45
density = 1000.0
[material.stiff]
young = 1.0e8
poisson = 0.45
density = 1000.0
[[body]]
name = "beam"
box = {{ min = [0.0, 0.0, 0.0], max = [0.4, 0.1, 0.1] }}
cell = 0.025
max_depth = 3
material = "tissue"
{inclusion}
[[fix]]
box = {{ min = [-0.001, -1.0, -1.0], max = [0.001, 1.0, 1.0] }}
[simulation]
dt = 0.01
model = "corotational"
[features]
contact = false
"#
    );
    Scene::from_str(&text, Path::new("."), "test:beam").expect("valid beam scene")
}

/// Refines every leaf with `pred(centroid)` once per round, `rounds` rounds.
fn refine(sim: &mut Simulation, rounds: u32, pred: impl Fn(&V3) -> bool) {
    for _ in 0..rounds {
        let lat = sim.lattice();
        let centroid = |t| {
            lat.tet_nodes(t)
                .iter()
                .map(|&n| lat.node_rest(n))
                .sum::<V3>()
                / 4.0
        };
        let level = lat
            .leaves()
            .iter()
            .filter(|t| pred(&centroid(**t)))
            .map(|t| lat.tet_level(*t))
            .min()
            .unwrap();
        let mut events = Vec::new();
        sim.lattice_mut().refine_where(
            |l, t| {
                let c: V3 = l.tet_nodes(t).iter().map(|&n| l.node_rest(n)).sum::<V3>() / 4.0;
                l.tet_level(t) <= level && pred(&c)
            },
            &mut events,
        );
        sim.after_topology_change(&events).unwrap();
    }
}

/// Steps `steps` times with the given solver to a 1e-6 relative residual; returns the
/// positions and the CG iterations of each step.
fn run(
    scene: &LoadedScene,
    solver: LinearSolver,
    rounds: u32,
    pred: impl Fn(&V3) -> bool,
    steps: usize,
) -> (Vec<V3>, Vec<usize>, usize) {
    run_on(scene, solver, 1, rounds, pred, steps)
}

/// [`run`] with the step on `threads` threads.
fn run_on(
    scene: &LoadedScene,
    solver: LinearSolver,
    threads: usize,
    rounds: u32,
    pred: impl Fn(&V3) -> bool,
    steps: usize,
) -> (Vec<V3>, Vec<usize>, usize) {
    let mut o = SimOptions::from_scene(&scene.scene);
    o.step.linear_solver = solver;
    o.step.threads = threads;
    o.step.solver.max_iters = 20_000;
    o.step.solver.tol = 1e-6;
    let mut sim = Simulation::new(scene.clone(), o).unwrap();
    refine(&mut sim, rounds, pred);
    let tets = sim.lattice().leaf_count();
    let iters = (0..steps)
        .map(|_| {
            let r = sim.step().unwrap();
            assert!(r.fem.cg_residual <= 1e-6, "{:?}", r.fem);
            r.fem.cg_iterations
        })
        .collect();
    (sim.positions().to_vec(), iters, tets)
}

fn max_diff(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).norm())
        .fold(0.0, f64::max)
}

#[test]
fn mg_pcg_needs_a_third_of_jacobis_iterations_on_the_12k_tet_beam() {
    let scene = beam_scene(false);
    let (xj, jacobi, tets) = run(&scene, LinearSolver::JacobiPcg, 3, |_| true, 3);
    let (xm, mg, _) = run(&scene, LinearSolver::MgPcg, 3, |_| true, 3);
    assert_eq!(tets, 12_288);
    eprintln!("12,288 tets, dt 10 ms, to 1e-6: Jacobi-PCG {jacobi:?}, MG-PCG {mg:?}");
    for (m, j) in mg.iter().zip(&jacobi) {
        assert!(3 * m <= *j, "MG-PCG {mg:?} vs Jacobi-PCG {jacobi:?}");
    }
    // Both solve the same systems to 1e-6: the trajectories agree far below the sag
    // (millimetres after 30 ms).
    let d = max_diff(&xm, &xj);
    assert!(d < 1e-6, "max position difference {d:e} m");
}

#[test]
fn mg_pcg_on_an_adaptive_lattice_with_a_1000x_stiffer_rod() {
    let scene = beam_scene(true);
    // Refined three rounds in the clamped half only: a graded, non-uniform lattice.
    let half = |c: &V3| c.x < 0.2;
    let (xj, jacobi, tets) = run(&scene, LinearSolver::JacobiPcg, 3, half, 3);
    let (xm, mg, _) = run(&scene, LinearSolver::MgPcg, 3, half, 3);
    eprintln!("adaptive {tets} tets with rod: Jacobi-PCG {jacobi:?}, MG-PCG {mg:?}");
    assert!(tets > 2 * 1536 && tets < 12_288, "{tets}");
    for (m, j) in mg.iter().zip(&jacobi) {
        assert!(2 * m <= *j, "MG-PCG {mg:?} vs Jacobi-PCG {jacobi:?}");
    }
    let d = max_diff(&xm, &xj);
    assert!(d < 1e-6, "max position difference {d:e} m");
}

#[test]
fn mg_pcg_on_two_threads_splits_its_smoothing_and_solves_the_same_steps() {
    // Two threads: the finest level's Gauss–Seidel runs as ℓ1 hybrid sweeps over the
    // step's two node ranges. Same converged steps as Jacobi-PCG on one thread, in about
    // the iterations of the sequential sweeps, on the graded lattice with the stiff rod.
    let scene = beam_scene(true);
    let half = |c: &V3| c.x < 0.2;
    let (xj, _, _) = run(&scene, LinearSolver::JacobiPcg, 3, half, 3);
    let (_, one, _) = run(&scene, LinearSolver::MgPcg, 3, half, 3);
    let (x2, two, _) = run_on(&scene, LinearSolver::MgPcg, 2, 3, half, 3);
    eprintln!("MG-PCG iterations, 1 thread {one:?}, 2 threads {two:?}");
    // The split smoother ran: its arithmetic differs from one thread's.
    assert_ne!(two, one, "two threads took one thread's iterations exactly");
    for (t, o) in two.iter().zip(&one) {
        assert!(
            4 * t <= 5 * o + 4,
            "2 threads {two:?} against 1 thread {one:?}"
        );
    }
    let d = max_diff(&x2, &xj);
    assert!(d < 1e-6, "max position difference {d:e} m");
}

#[test]
fn direct_on_an_adaptive_lattice_with_a_1000x_stiffer_rod_across_a_refinement() {
    // The direct solver keeps its symbolic factorisation per pattern: a refinement between
    // steps (new nodes, new pattern) must give a fresh one, not a stale one.
    let scene = beam_scene(true);
    let half = |c: &V3| c.x < 0.2;
    let stepped = |solver: LinearSolver, tol: f64| {
        let mut o = SimOptions::from_scene(&scene.scene);
        o.step.linear_solver = solver;
        o.step.solver.max_iters = 20_000;
        o.step.solver.tol = tol;
        let mut sim = Simulation::new(scene.clone(), o).unwrap();
        refine(&mut sim, 2, half);
        let mut residuals = Vec::new();
        for step in 0..4 {
            if step == 2 {
                refine(&mut sim, 1, |c: &V3| c.x < 0.1);
            }
            residuals.push(sim.step().unwrap().fem.cg_residual);
        }
        (
            sim.positions().to_vec(),
            residuals,
            sim.lattice().leaf_count(),
        )
    };
    let (xd, direct, tets) = stepped(LinearSolver::Direct, 1e-6);
    let (xj, jacobi, tets_j) = stepped(LinearSolver::JacobiPcg, 1e-10);
    assert_eq!(tets, tets_j);
    eprintln!("adaptive {tets} tets with rod: direct residuals {direct:?}, Jacobi {jacobi:?}");
    assert!(direct.iter().all(|r| *r < 1e-9), "{direct:?}");
    let d = max_diff(&xd, &xj);
    assert!(d < 1e-8, "max position difference {d:e} m");
}
