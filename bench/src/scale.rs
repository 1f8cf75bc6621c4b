//! `cosurg bench scale`: Jacobi-PCG, MG-PCG (multigrid-preconditioned CG over the lattice
//! hierarchy) and the sparse direct solver on the soft (E = 1e5 Pa) and stiff (1e6 Pa)
//! cantilever beams at 1,536 and 12,288 tets (finer with `--cells`), dt 1 and 10 ms, every
//! step solved to a relative residual of 1e-6, then the default organ scene (the liver and
//! its gallbladder at their lattice's resolution, or at the cells of `--organ-cells`, no
//! tool touching) the same way: CG
//! iterations, wall time per step (p50, p99, one thread) and the most heap each row held;
//! and the exponent of p50 time against tets between the beam sizes run. Each scene
//! runs with its own features (the beams share no rotations) unless `--sharing-angle`
//! sets the product's rotation sharing for every row.

use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use serde::Serialize;
use sim_core::sim_fem::LinearSolver;
use sim_core::sim_scene::builtin::cantilever_with;
use sim_core::{SimOptions, Simulation};

use cosurg::stats::percentile;

#[derive(Debug, Args)]
pub struct ScaleArgs {
    /// Print JSON (stdout) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Cell sizes (m), comma-separated; default 0.025,0.0125 (1,536 and 12,288 tets).
    #[arg(long, value_delimiter = ',')]
    pub cells: Vec<f64>,
    /// Time steps (s), comma-separated; default 0.001,0.01.
    #[arg(long, value_delimiter = ',')]
    pub dts: Vec<f64>,
    /// Timed steps per run (after 3 untimed ones); default 40.
    #[arg(long, default_value_t = 40)]
    pub steps: usize,
    /// Solvers to run, comma-separated; default all (jacobi-pcg, mg-pcg, direct).
    #[arg(long, value_delimiter = ',')]
    pub solvers: Vec<LinearSolver>,
    /// Leave out the default organ scene's rows (run after the beams).
    #[arg(long)]
    pub no_organ: bool,
    /// Lattice cell sizes (m) of the organ's rows, comma-separated: every body's cell, as
    /// `cosurg run --cell` (e.g. 0.02,0.013333333 for the default 2 cm and the 1.33 cm
    /// organ). Default: the scene's own.
    #[arg(long, value_delimiter = ',')]
    pub organ_cells: Vec<f64>,
    /// Rotation-sharing angle θ_tol (degrees) for every row; 0 turns sharing off. Default:
    /// each scene's own (the beams share no rotations, the organ shares within 5°); 5 is
    /// the product's configuration (`cosurg bench cantilever`'s all-on).
    #[arg(long)]
    pub sharing_angle: Option<f64>,
    /// Threads of every row's FEM step (`StepParams::threads`); 1, the default, is what a
    /// site runs (its second core runs the haptic loop and the network).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub threads: u16,
}

/// How p50 time grows with the mesh for one (beam, dt, solver): `t ∝ tets^exponent`
/// between its smallest and largest mesh.
#[derive(Debug, Serialize)]
pub struct ScaleExponent {
    pub material: &'static str,
    pub dt_s: f64,
    pub solver: &'static str,
    pub tets_from: usize,
    pub tets_to: usize,
    pub exponent: f64,
}

/// Everything `--json` prints.
#[derive(Debug, Serialize)]
pub struct ScaleReport {
    pub rows: Vec<ScaleRow>,
    pub exponents: Vec<ScaleExponent>,
}

/// The exponent of each (beam, dt, solver) run at two or more sizes.
fn exponents(rows: &[ScaleRow]) -> Vec<ScaleExponent> {
    let mut out: Vec<ScaleExponent> = Vec::new();
    for r in rows {
        if out
            .iter()
            .any(|e| e.material == r.material && e.dt_s == r.dt_s && e.solver == r.solver)
        {
            continue;
        }
        let same: Vec<&ScaleRow> = rows
            .iter()
            .filter(|s| s.material == r.material && s.dt_s == r.dt_s && s.solver == r.solver)
            .collect();
        let small = same.iter().min_by_key(|s| s.tets).expect("r itself");
        let big = same.iter().max_by_key(|s| s.tets).expect("r itself");
        if big.tets > small.tets && small.ms_p50 > 0.0 {
            out.push(ScaleExponent {
                material: r.material,
                dt_s: r.dt_s,
                solver: r.solver,
                tets_from: small.tets,
                tets_to: big.tets,
                exponent: (big.ms_p50 / small.ms_p50).ln()
                    / (big.tets as f64 / small.tets as f64).ln(),
            });
        }
    }
    out
}

/// One (beam or organ, dt, solver) run.
#[derive(Debug, Serialize)]
pub struct ScaleRow {
    /// `soft` or `stiff` (the beams), `organ` (the default scene, its own materials).
    pub material: &'static str,
    /// The beam's Young's modulus (Pa); `None` for the organ.
    pub young_pa: Option<f64>,
    /// Lattice cell size (m): the beam's, or the organ's bodies' (the first body's when
    /// they differ).
    pub cell_m: f64,
    pub tets: usize,
    pub dt_s: f64,
    pub solver: &'static str,
    pub tolerance: f64,
    pub steps: usize,
    /// Mean CG iterations per timed step.
    pub iterations_mean: f64,
    pub iterations_max: usize,
    pub ms_p50: f64,
    pub ms_p99: f64,
    /// Largest relative residual of a timed step (≤ tolerance unless the budget ran out).
    pub residual_max: f64,
    /// Whether each solve started from the previous converged step's Δv (the scene's
    /// options: off, see `SimOptions::from_scene`).
    pub warm_start: bool,
    /// Rotation-sharing angle θ_tol (degrees) of the run; `None`: no sharing.
    pub sharing_angle_deg: Option<f64>,
    /// Rotation extractions per timed step (mean).
    pub rotations_per_step: f64,
    /// Threads of the FEM step.
    pub threads: usize,
    /// Most heap the row held (MiB): scene, lattice, FEM system and solver while it was
    /// built and stepped, over every thread ([`crate::memory`]); `None` when the binary
    /// does not count its heap.
    pub heap_peak_mib: Option<f64>,
}

const MATERIALS: [(&str, f64); 2] = [("soft", 1e5), ("stiff", 1e6)];
const TOLERANCE: f64 = 1e-6;

/// The beam or the organ to step.
#[derive(Clone, Copy, Debug)]
enum Subject {
    Beam {
        young: f64,
        cell: f64,
    },
    /// The built-in default scene (the liver with the gallbladder), untouched by tools;
    /// with `cell`, every body on that lattice cell (m) instead of the scene's.
    Organ {
        cell: Option<f64>,
    },
}

fn run_one(
    subject: Subject,
    dt: f64,
    solver: LinearSolver,
    steps: usize,
    sharing_angle: Option<f64>,
    threads: usize,
) -> Result<ScaleRow> {
    let heap = crate::memory::HeapScope::open();
    let scene = match subject {
        Subject::Beam { young, cell } => {
            cantilever_with(young, cell).context("cantilever scene")?
        }
        Subject::Organ { cell } => cosurg::scene_arg::load_scene_with_cell(None, cell)
            .context("the organ at --organ-cells")?,
    };
    let cell_m = scene.scene.bodies.first().map_or(f64::NAN, |b| b.cell);
    let mut o = SimOptions::from_scene(&scene.scene);
    o.dt = dt;
    o.step.linear_solver = solver;
    o.step.solver.tol = TOLERANCE;
    o.step.solver.max_iters = 20_000;
    o.step.threads = threads;
    if let Some(a) = sharing_angle {
        o.sharing_angle_deg = (a > 0.0).then_some(a);
    }
    let (warm_start, sharing_angle_deg) = (o.step.solver.warm_start, o.sharing_angle_deg);
    let mut sim = Simulation::new(scene, o)?;
    let tets = sim.lattice().leaf_count();
    for _ in 0..3 {
        sim.step()?;
    }
    let mut ms = Vec::with_capacity(steps);
    let mut iters = Vec::with_capacity(steps);
    let mut residual_max: f64 = 0.0;
    let mut rotations = 0usize;
    for _ in 0..steps {
        let t = Instant::now();
        let r = sim.step()?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        iters.push(r.fem.cg_iterations);
        residual_max = residual_max.max(r.fem.cg_residual);
        rotations += r.fem.rotations_extracted;
    }
    Ok(ScaleRow {
        material: "",
        young_pa: match subject {
            Subject::Beam { young, .. } => Some(young),
            Subject::Organ { .. } => None,
        },
        cell_m,
        tets,
        dt_s: dt,
        solver: solver.name(),
        tolerance: TOLERANCE,
        steps,
        iterations_mean: iters.iter().sum::<usize>() as f64 / steps.max(1) as f64,
        iterations_max: iters.iter().copied().max().unwrap_or(0),
        ms_p50: percentile(&ms, 50.0),
        ms_p99: percentile(&ms, 99.0),
        residual_max,
        warm_start,
        sharing_angle_deg,
        rotations_per_step: rotations as f64 / steps.max(1) as f64,
        threads,
        heap_peak_mib: heap.map(|h| h.peak_bytes() as f64 / (1024.0 * 1024.0)),
    })
}

pub fn run(args: ScaleArgs) -> Result<()> {
    let cells = if args.cells.is_empty() {
        vec![0.025, 0.0125]
    } else {
        args.cells.clone()
    };
    let dts = if args.dts.is_empty() {
        vec![0.001, 0.01]
    } else {
        args.dts.clone()
    };
    let solvers = if args.solvers.is_empty() {
        LinearSolver::ALL.to_vec()
    } else {
        args.solvers.clone()
    };
    let mut subjects: Vec<(&'static str, Subject)> = Vec::new();
    for &(material, young) in &MATERIALS {
        for &cell in &cells {
            subjects.push((material, Subject::Beam { young, cell }));
        }
    }
    if !args.no_organ {
        if args.organ_cells.is_empty() {
            subjects.push(("organ", Subject::Organ { cell: None }));
        }
        for &cell in &args.organ_cells {
            subjects.push(("organ", Subject::Organ { cell: Some(cell) }));
        }
    }
    let mut rows = Vec::new();
    for &(material, subject) in &subjects {
        for &dt in &dts {
            for &solver in &solvers {
                let mut row = run_one(
                    subject,
                    dt,
                    solver,
                    args.steps,
                    args.sharing_angle,
                    usize::from(args.threads),
                )?;
                row.material = material;
                if !args.json {
                    println!(
                        "{:<5} {:>6} tets  dt {:>4.1} ms  {:<10} {} thr  iters {:>6.1} (max {:>4})  ms/step p50 {:>7.2} p99 {:>7.2}  rot/step {:>6.0}  heap {:>7} MiB",
                        row.material,
                        row.tets,
                        row.dt_s * 1e3,
                        row.solver,
                        row.threads,
                        row.iterations_mean,
                        row.iterations_max,
                        row.ms_p50,
                        row.ms_p99,
                        row.rotations_per_step,
                        row.heap_peak_mib
                            .map_or("-".to_string(), |m| format!("{m:.1}"))
                    );
                }
                rows.push(row);
            }
        }
    }
    let exponents = exponents(&rows);
    if args.json {
        let report = ScaleReport { rows, exponents };
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for e in &exponents {
            println!(
                "{:<5} dt {:>4.1} ms  {:<10}  time ∝ tets^{:.2} ({} → {} tets)",
                e.material,
                e.dt_s * 1e3,
                e.solver,
                e.exponent,
                e.tets_from,
                e.tets_to
            );
        }
    }
    Ok(())
}
