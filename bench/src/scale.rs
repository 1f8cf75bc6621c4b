//! `cosurg bench scale`: Jacobi-PCG, MG-PCG (multigrid-preconditioned CG over the lattice
//! hierarchy) and the sparse direct solver on the soft (E = 1e5 Pa) and stiff (1e6 Pa)
//! cantilever beams at 1,536 and 12,288 tets (finer with `--cells`), dt 1 and 10 ms, every
//! step solved to a relative residual of 1e-6, then the default organ scene (the liver and
//! its gallbladder at their lattice's resolution, or at the cells of `--organ-cells`, no
//! tool touching) the same way: CG
//! iterations, wall time per step (p50, p99, one thread) and the most heap each row held;
//! and the exponent of p50 time against tets between the beam sizes run (`--repeat N`:
//! every row N times in interleaved rounds, medians and each round's exponent). Each scene
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
    /// Runs of every row, in rounds (each round runs every row once, so that a machine
    /// whose speed drifts slows the small and the large meshes alike): a row's p50 and
    /// p99 are the medians of its runs', and each exponent is given from those medians
    /// and from each round alone (its spread). On a shared machine one run's exponent
    /// can be off by 0.1 (docs/RESULTS.md).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=100))]
    pub repeat: u16,
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
    /// From the rows' p50s (with `--repeat`, the medians of their runs').
    pub exponent: f64,
    /// From each round's p50s alone, in round order (one entry without `--repeat`).
    pub exponent_runs: Vec<f64>,
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
                exponent: exponent(small.tets, small.ms_p50, big.tets, big.ms_p50),
                exponent_runs: small
                    .ms_p50_runs
                    .iter()
                    .zip(&big.ms_p50_runs)
                    .map(|(&a, &b)| exponent(small.tets, a, big.tets, b))
                    .collect(),
            });
        }
    }
    out
}

/// `e` in `t ∝ tets^e` through two points.
fn exponent(tets_a: usize, ms_a: f64, tets_b: usize, ms_b: f64) -> f64 {
    (ms_b / ms_a).ln() / (tets_b as f64 / tets_a as f64).ln()
}

/// The median of `v` (the mean of the middle two for an even count).
fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// One (beam or organ, dt, solver) row: one run, or the medians of `--repeat` runs.
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
    /// Each run's p50, in round order (one entry without `--repeat`).
    pub ms_p50_runs: Vec<f64>,
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
        ms_p50_runs: vec![percentile(&ms, 50.0)],
        residual_max,
        warm_start,
        sharing_angle_deg,
        rotations_per_step: rotations as f64 / steps.max(1) as f64,
        threads,
        heap_peak_mib: heap.map(|h| h.peak_bytes() as f64 / (1024.0 * 1024.0)),
    })
}

/// One configuration's runs as one row: the medians of the runs' p50 and p99, the mean
/// of their mean iterations (the steps are deterministic, so the runs agree), the
/// largest iteration count, residual and heap.
fn merge_runs(runs: Vec<ScaleRow>) -> ScaleRow {
    let n = runs.len() as f64;
    let p50: Vec<f64> = runs.iter().map(|r| r.ms_p50).collect();
    let p99: Vec<f64> = runs.iter().map(|r| r.ms_p99).collect();
    let heap = runs.iter().filter_map(|r| r.heap_peak_mib).reduce(f64::max);
    let iterations_mean = runs.iter().map(|r| r.iterations_mean).sum::<f64>() / n;
    let iterations_max = runs.iter().map(|r| r.iterations_max).max().unwrap_or(0);
    let residual_max = runs.iter().map(|r| r.residual_max).fold(0.0, f64::max);
    let mut row = runs.into_iter().next().expect("at least one run");
    row.ms_p50 = median(&p50);
    row.ms_p99 = median(&p99);
    row.ms_p50_runs = p50;
    row.heap_peak_mib = heap;
    row.iterations_mean = iterations_mean;
    row.iterations_max = iterations_max;
    row.residual_max = residual_max;
    row
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
    let mut configs = Vec::new();
    for &(material, subject) in &subjects {
        for &dt in &dts {
            for &solver in &solvers {
                configs.push((material, subject, dt, solver));
            }
        }
    }
    let repeat = usize::from(args.repeat);
    // Runs by configuration, every configuration once per round.
    let mut runs: Vec<Vec<ScaleRow>> = (0..configs.len()).map(|_| Vec::new()).collect();
    for round in 0..repeat {
        for (&(material, subject, dt, solver), runs) in configs.iter().zip(&mut runs) {
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
                let round = if repeat > 1 {
                    format!("[{}/{repeat}] ", round + 1)
                } else {
                    String::new()
                };
                println!(
                    "{round}{:<5} {:>6} tets  dt {:>4.1} ms  {:<10} {} thr  iters {:>6.1} (max {:>4})  ms/step p50 {:>7.2} p99 {:>7.2}  rot/step {:>6.0}  heap {:>7} MiB",
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
            runs.push(row);
        }
    }
    let rows: Vec<ScaleRow> = runs.into_iter().map(merge_runs).collect();
    if !args.json && repeat > 1 {
        for row in &rows {
            println!(
                "{:<5} {:>6} tets  dt {:>4.1} ms  {:<10} median of {repeat}: p50 {:>7.2} p99 {:>7.2}",
                row.material,
                row.tets,
                row.dt_s * 1e3,
                row.solver,
                row.ms_p50,
                row.ms_p99
            );
        }
    }
    let exponents = exponents(&rows);
    if args.json {
        let report = ScaleReport { rows, exponents };
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for e in &exponents {
            let spread = if e.exponent_runs.len() > 1 {
                let lo = e
                    .exponent_runs
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min);
                let hi = e
                    .exponent_runs
                    .iter()
                    .copied()
                    .fold(f64::NEG_INFINITY, f64::max);
                format!(", rounds {lo:.2}–{hi:.2}")
            } else {
                String::new()
            };
            println!(
                "{:<5} dt {:>4.1} ms  {:<10}  time ∝ tets^{:.2} ({} → {} tets{spread})",
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
