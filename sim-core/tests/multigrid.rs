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

/// The scene's options with `solver`, every solve to a relative residual of 1e-6 (budget
/// 20,000 iterations).
fn converged(scene: &LoadedScene, solver: LinearSolver) -> SimOptions {
    let mut o = SimOptions::from_scene(&scene.scene);
    o.step.linear_solver = solver;
    o.step.solver.max_iters = 20_000;
    o.step.solver.tol = 1e-6;
    o
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
    let mut o = converged(scene, solver);
    o.step.threads = threads;
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
        let mut o = converged(&scene, solver);
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

/// Steps the 12k-tet beam notched from the top at x ≈ 0.21 m (a cut through its upper
/// half, 1.5 cm into the clamped-to-free span) 3 times with `solver` to 1e-6; returns the
/// positions, the CG iterations of each step and the number of virtual nodes.
fn run_notched(solver: LinearSolver) -> (Vec<V3>, Vec<usize>, usize) {
    let scene = beam_scene(false);
    let o = converged(&scene, solver);
    let mut sim = Simulation::new(scene, o).unwrap();
    refine(&mut sim, 3, |_| true);
    // The sheet lies off the lattice's planes (x = 0.2109 m) and spans the beam's width
    // and its upper half (z from 0.045 m to above the top).
    let (x, z0, z1, y0, y1) = (0.2109, 0.045, 0.12, -0.02, 0.12);
    let op = cosurg_sim_core::cut::TopologyOp::Cut(cosurg_sim_core::cut::CutOp {
        id: cosurg_sim_core::cut::OpId { site: 1, seq: 0 },
        triangles: vec![
            [[x, y0, z0], [x, y1, z0], [x, y1, z1]],
            [[x, y0, z0], [x, y1, z1], [x, y0, z1]],
        ],
    });
    sim.apply_topology_op(op).unwrap();
    let copies = sim
        .separation()
        .expect("the notch cuts")
        .virtual_nodes
        .len();
    let iters = (0..3)
        .map(|_| {
            let r = sim.step().unwrap();
            assert!(r.fem.cg_residual <= 1e-6, "{:?}", r.fem);
            r.fem.cg_iterations
        })
        .collect();
    (sim.positions().to_vec(), iters, copies)
}

#[test]
fn mg_pcg_after_a_cut_solves_the_steps_of_jacobi_pcg() {
    // After a cut the virtual nodes (copies of lattice nodes) take their node's row of
    // the finest prolongation: the same converged steps, still in a fraction of
    // Jacobi-PCG's iterations (the uncut beam's MG-PCG takes about 17).
    let (xj, jacobi, copies) = run_notched(LinearSolver::JacobiPcg);
    let (xm, mg, _) = run_notched(LinearSolver::MgPcg);
    eprintln!("notched beam, {copies} virtual nodes: Jacobi-PCG {jacobi:?}, MG-PCG {mg:?}");
    assert!(copies > 50, "{copies} virtual nodes");
    for (m, j) in mg.iter().zip(&jacobi) {
        assert!(3 * m <= *j, "MG-PCG {mg:?} vs Jacobi-PCG {jacobi:?}");
    }
    let d = max_diff(&xm, &xj);
    assert!(d < 1e-6, "max position difference {d:e} m");
}

/// Steps a beam (`rounds` refinements of the 1,536-tet one, 12,288 tets at 3) with the
/// scene's default solver, `auto`, to 1e-6 under a CG budget; returns each step's solver.
fn auto_solvers(scene: &LoadedScene, rounds: u32, dt: f64, budget: usize) -> Vec<LinearSolver> {
    let mut o = SimOptions::from_scene(&scene.scene);
    assert_eq!(
        o.step.linear_solver,
        LinearSolver::Auto,
        "the scenes' default"
    );
    o.dt = dt;
    o.step.solver.max_iters = budget;
    o.step.solver.tol = 1e-6;
    let mut sim = Simulation::new(scene.clone(), o).unwrap();
    refine(&mut sim, rounds, |_| true);
    (0..4).map(|_| sim.step().unwrap().fem.solver).collect()
}

#[test]
fn auto_moves_the_fine_stiff_step_to_mg_pcg_and_leaves_the_easy_one_on_jacobi() {
    use LinearSolver::{JacobiPcg, MgPcg};
    let scene = beam_scene(false);
    // 12,288 tets at dt 10 ms: Jacobi-PCG needs about 220 iterations, so the first step
    // is its last; the same under a 50-iteration budget (stopped at a residual of about
    // 0.2, extrapolated to several hundred).
    assert_eq!(
        auto_solvers(&scene, 3, 0.01, 20_000),
        [JacobiPcg, MgPcg, MgPcg, MgPcg]
    );
    assert_eq!(
        auto_solvers(&scene, 3, 0.01, 50),
        [JacobiPcg, MgPcg, MgPcg, MgPcg]
    );
    // 1,536 tets at dt 2 ms: about 25 iterations, where Jacobi-PCG was the faster.
    assert_eq!(
        auto_solvers(&scene, 0, 0.002, 20_000),
        [JacobiPcg, JacobiPcg, JacobiPcg, JacobiPcg]
    );
}

#[test]
fn auto_keeps_its_first_choice_across_a_refinement_and_for_good() {
    // Chosen on the first solve (sites that start alike choose alike) and kept across the
    // FEM rebuild of a refinement, which must not go back to Jacobi-PCG. Both ways: the
    // rod's beam at dt 10 ms (Jacobi-PCG needs hundreds of iterations) and the plain one
    // at dt 1 ms (a few dozen), which stays on Jacobi-PCG after the refinement too.
    for (rod, dt, chosen) in [
        (true, 0.01, LinearSolver::MgPcg),
        (false, 0.001, LinearSolver::JacobiPcg),
    ] {
        let scene = beam_scene(rod);
        let mut o = converged(&scene, LinearSolver::Auto);
        o.dt = dt;
        let mut sim = Simulation::new(scene, o).unwrap();
        refine(&mut sim, 1, |_| true);
        let first = sim.step().unwrap().fem;
        assert_eq!(first.solver, LinearSolver::JacobiPcg);
        assert_eq!(sim.step().unwrap().fem.solver, chosen, "rod {rod}");
        refine(&mut sim, 1, |c| c.x < 0.2);
        let r = sim.step().unwrap();
        assert_eq!(r.fem.solver, chosen, "rod {rod}, after the refinement");
        assert!(r.fem.cg_residual <= 1e-6, "{:?}", r.fem);
    }
}
