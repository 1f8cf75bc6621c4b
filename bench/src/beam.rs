//! Shared machinery of the beam benchmarks (`cantilever`, `sweep`): the knobs of a run,
//! a timed simulation with sampled node positions, and deviations from a reference.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use nalgebra::Vector3;
use serde::Serialize;
use sim_core::sim_fem::{
    ByersXu, LinearSolver, Model, MullerIterative, NewtonParams, PolarMethod, SolverParams,
    StiffnessMode,
};
use sim_core::sim_scene::LoadedScene;
use sim_core::{NodeId, SimOptions, Simulation};

use cosurg::stats::percentile;

type V3 = Vector3<f64>;

/// Polar decomposition choices of the benchmarks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Polar {
    ByersXu,
    Svd,
    ShapeMatching,
    Muller,
}

impl Polar {
    pub fn name(self) -> &'static str {
        match self {
            Polar::ByersXu => "byers-xu",
            Polar::Svd => "svd",
            Polar::ShapeMatching => "shape-matching",
            Polar::Muller => "muller",
        }
    }
    fn method(self, tol: f64) -> PolarMethod {
        match self {
            Polar::ByersXu => PolarMethod::ByersXu(ByersXu {
                tol,
                ..ByersXu::default()
            }),
            Polar::Svd => PolarMethod::Svd,
            Polar::ShapeMatching => PolarMethod::ShapeMatching,
            Polar::Muller => PolarMethod::Muller(MullerIterative {
                tol,
                ..MullerIterative::default()
            }),
        }
    }
    fn has_tolerance(self) -> bool {
        matches!(self, Polar::ByersXu | Polar::Muller)
    }
}

/// Every knob a beam run sets, as it is reported (`options` in the JSON).
#[derive(Clone, Debug, Serialize)]
pub struct Knobs {
    /// Variant label (`all-on`, `no-sharing`, …; `reference` for the non-linear run).
    pub variant: String,
    /// Rotation extractor (co-rotational model only; `none` otherwise).
    pub polar: String,
    /// Stopping tolerance of iterative polar methods (null for closed-form ones).
    pub polar_tolerance: Option<f64>,
    /// Rotation sharing θ_tol (degrees), 0 = off.
    pub sharing_angle_deg: f64,
    /// Template stiffness table (true) or per-element dense matrices (false).
    pub template_stiffness: bool,
    /// Skip rotation extraction of elements at rest.
    pub skip_rest: bool,
    /// Rest threshold (m) when `skip_rest`.
    pub rest_threshold_m: f64,
    /// CG operator.
    pub operator: String,
    /// Linear solver of the implicit step (`jacobi-pcg`, `mg-pcg`, `direct`).
    pub linear_solver: String,
    /// CG iteration budget per linear solve.
    pub cg_iterations: usize,
    /// CG relative tolerance.
    pub cg_tolerance: f64,
    /// CG warm start from the previous step's Δv (when that solve converged).
    pub cg_warm_start: bool,
    /// Newton iterations allowed per step (non-linear model), else null.
    pub newton_iterations: Option<usize>,
    /// Newton force-residual tolerance (N), else null.
    pub newton_tolerance_n: Option<f64>,
    /// Bisection depth of the lattice below the root cubes (uniform refinement).
    pub refinement_depth: u32,
    /// Threads of the FEM step (1 = single-threaded).
    pub threads: usize,
    /// Energy guard of the co-rotational step (`StepParams::energy_guard`).
    pub energy_guard: bool,
}

/// A run's knobs before they are applied to [`SimOptions`].
#[derive(Clone, Debug)]
pub struct RunConfig {
    pub variant: String,
    pub model: Model,
    pub polar: Polar,
    pub polar_tolerance: f64,
    pub sharing_angle_deg: f64,
    pub template_stiffness: bool,
    pub skip_rest: bool,
    pub cg_iterations: usize,
    pub cg_tolerance: f64,
    /// Linear solver of the implicit step (the budget and tolerance above apply to the
    /// CG solvers; Newton's inner solves stay on CG whatever it says).
    pub linear_solver: LinearSolver,
    /// CG starts from the previous step's Δv when that solve converged (off, as in the
    /// product: see `SimOptions`).
    pub cg_warm_start: bool,
    pub newton: NewtonParams,
    /// Uniform refinement (bisection levels) of every root tet before the run.
    pub depth: u32,
    /// Threads of the FEM step.
    pub threads: usize,
}

/// Rest threshold of the skip-rest speed-up (m): the scene default.
pub const REST_THRESHOLD: f64 = 1e-6;

impl RunConfig {
    /// The product's configuration: Byers–Xu, sharing at 5°, template stiffness,
    /// skip-rest, the scene's CG budget.
    pub fn all_on(model: Model) -> Self {
        RunConfig {
            variant: "all-on".into(),
            model,
            polar: Polar::ByersXu,
            polar_tolerance: 1e-6,
            sharing_angle_deg: 5.0,
            template_stiffness: true,
            skip_rest: true,
            cg_iterations: 50,
            cg_tolerance: 1e-6,
            linear_solver: LinearSolver::JacobiPcg,
            cg_warm_start: false,
            newton: NewtonParams {
                max_iters: 8,
                tol: 1e-6,
            },
            depth: 0,
            threads: 1,
        }
    }
    /// Every speed-up off: SVD, no sharing, dense element matrices, no skip-rest.
    pub fn all_off(model: Model) -> Self {
        RunConfig {
            variant: "all-off".into(),
            polar: Polar::Svd,
            sharing_angle_deg: 0.0,
            template_stiffness: false,
            skip_rest: false,
            ..Self::all_on(model)
        }
    }
    /// The non-linear reference: StVK, backward Euler with Newton, accurate inner solves.
    pub fn reference() -> Self {
        RunConfig {
            variant: "reference".into(),
            sharing_angle_deg: 0.0,
            skip_rest: false,
            cg_iterations: 500,
            cg_tolerance: 1e-8,
            cg_warm_start: false,
            newton: NewtonParams {
                max_iters: 10,
                tol: 1e-7,
            },
            ..Self::all_on(Model::StVK)
        }
    }
    /// The linear solve switched to MG-PCG with an iteration budget.
    pub fn with_mg_pcg(mut self, budget: usize) -> Self {
        self.linear_solver = LinearSolver::MgPcg;
        self.cg_iterations = budget;
        self
    }

    pub fn with(mut self, variant: &str, f: impl FnOnce(&mut RunConfig)) -> Self {
        self.variant = variant.into();
        f(&mut self);
        self
    }

    pub fn options(&self, scene: &LoadedScene) -> SimOptions {
        let mut o = SimOptions::from_scene(&scene.scene);
        o.step.model = self.model;
        o.step.polar = self.polar.method(self.polar_tolerance);
        o.sharing_angle_deg = (self.sharing_angle_deg > 0.0).then_some(self.sharing_angle_deg);
        o.step.stiffness = if self.template_stiffness {
            StiffnessMode::Template
        } else {
            StiffnessMode::Dense
        };
        o.step.rest_threshold = if self.skip_rest { REST_THRESHOLD } else { 0.0 };
        o.step.linear_solver = self.linear_solver;
        o.step.solver = SolverParams {
            max_iters: self.cg_iterations,
            tol: self.cg_tolerance,
            warm_start: self.cg_warm_start,
        };
        o.step.newton = self.newton;
        o.step.threads = self.threads;
        o
    }

    pub fn knobs(&self, options: &SimOptions) -> Knobs {
        let corot = self.model == Model::Corotational;
        let nonlinear = self.model == Model::StVK;
        Knobs {
            variant: self.variant.clone(),
            polar: if corot { self.polar.name() } else { "none" }.into(),
            polar_tolerance: (corot && self.polar.has_tolerance()).then_some(self.polar_tolerance),
            sharing_angle_deg: if corot { self.sharing_angle_deg } else { 0.0 },
            template_stiffness: self.template_stiffness,
            skip_rest: corot && self.skip_rest,
            rest_threshold_m: if corot {
                options.step.rest_threshold
            } else {
                0.0
            },
            operator: format!("{:?}", options.step.operator).to_lowercase(),
            linear_solver: options.step.linear_solver.name().into(),
            cg_iterations: self.cg_iterations,
            cg_tolerance: self.cg_tolerance,
            cg_warm_start: self.cg_warm_start,
            newton_iterations: nonlinear.then_some(self.newton.max_iters),
            newton_tolerance_n: nonlinear.then_some(self.newton.tol),
            refinement_depth: self.depth,
            threads: options.step.threads,
            energy_guard: corot && options.step.energy_guard,
        }
    }
}

/// Model names as the benchmarks print them (the names of scene files and `--model`).
pub fn model_name(m: Model) -> &'static str {
    m.name()
}

/// A finished run: per-step wall times and the node positions at the sample times.
pub struct Trace {
    pub step_ms: Vec<f64>,
    /// Positions of `nodes` every `sample_every` steps (after the step).
    pub samples: Vec<Vec<V3>>,
    pub tets: usize,
    pub nodes: usize,
    pub rotations_extracted: usize,
    pub cg_iterations: usize,
    pub newton_iterations: usize,
    pub shared_elements: usize,
    /// Steps the co-rotational step fell back to Newton (fast rotations).
    pub fallback_steps: usize,
    pub non_finite: bool,
}

impl Trace {
    pub fn p50(&self) -> f64 {
        percentile(&self.step_ms, 50.0)
    }
    pub fn p99(&self) -> f64 {
        percentile(&self.step_ms, 99.0)
    }
}

/// Refines every leaf uniformly `depth` bisection levels.
pub fn refine_uniform(sim: &mut Simulation, depth: u32) -> Result<()> {
    for _ in 0..depth {
        let level = sim
            .lattice()
            .leaves()
            .iter()
            .map(|t| sim.lattice().tet_level(*t))
            .min();
        let Some(level) = level else { break };
        let mut events = Vec::new();
        sim.lattice_mut()
            .refine_where(|lat, t| lat.tet_level(t) <= level, &mut events);
        sim.after_topology_change(&events)?;
    }
    Ok(())
}

/// Builds the simulation of `config` on `scene`.
pub fn build(scene: &LoadedScene, config: &RunConfig, dt: f64) -> Result<(Simulation, Knobs)> {
    let mut o = config.options(scene);
    o.dt = dt;
    let knobs = config.knobs(&o);
    let mut sim = Simulation::new(scene.clone(), o)?;
    refine_uniform(&mut sim, config.depth)?;
    Ok((sim, knobs))
}

/// Live nodes of a simulation, in id order (identical for identical scenes and depths).
pub fn live_nodes(sim: &Simulation) -> Vec<NodeId> {
    sim.lattice().nodes().collect()
}

/// One run advanced step by step (so that several runs can be interleaved and share the
/// machine's load alike): times every step and samples the positions of all live nodes
/// every `sample_every` steps. A non-finite state ends the run (`non_finite`).
pub struct Runner {
    pub sim: Simulation,
    nodes: Vec<NodeId>,
    sample_every: usize,
    k: usize,
    pub trace: Trace,
}

impl Runner {
    pub fn new(mut sim: Simulation, steps: usize, sample_every: usize) -> Result<Self> {
        let nodes = live_nodes(&sim);
        let tets = sim.lattice().leaf_count();
        // Build the FEM system outside the clock.
        sim.fem()?;
        Ok(Runner {
            trace: Trace {
                step_ms: Vec::with_capacity(steps),
                samples: Vec::with_capacity(steps / sample_every.max(1) + 1),
                tets,
                nodes: nodes.len(),
                rotations_extracted: 0,
                cg_iterations: 0,
                newton_iterations: 0,
                shared_elements: 0,
                fallback_steps: 0,
                non_finite: false,
            },
            sim,
            nodes,
            sample_every: sample_every.max(1),
            k: 0,
        })
    }

    /// One timed step (nothing once the run became non-finite).
    pub fn step(&mut self) -> Result<()> {
        let t = &mut self.trace;
        if t.non_finite {
            return Ok(());
        }
        let t0 = Instant::now();
        let r = match self.sim.step() {
            Ok(r) => r,
            Err(sim_core::SimError::NonFinite { .. }) => {
                t.non_finite = true;
                return Ok(());
            }
            Err(e) => return Err(e).context("step"),
        };
        t.step_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        self.k += 1;
        t.rotations_extracted += r.fem.rotations_extracted;
        t.cg_iterations += r.fem.cg_iterations;
        t.newton_iterations += r.fem.newton_iterations;
        t.shared_elements += r.shared_rotations;
        t.fallback_steps += r.fem.fallback as usize;
        if self.k.is_multiple_of(self.sample_every) {
            let x = self.sim.positions();
            let s: Vec<V3> = self.nodes.iter().map(|n| x[n.0 as usize]).collect();
            if s.iter().any(|p| !p.iter().all(|c| c.is_finite())) {
                t.non_finite = true;
                return Ok(());
            }
            t.samples.push(s);
        }
        Ok(())
    }
}

/// Steps `sim` for `steps` steps on its own (see [`Runner`]); returns the trace and the
/// simulation in its final state.
pub fn simulate(
    sim: Simulation,
    steps: usize,
    sample_every: usize,
    bar: &ProgressBar,
) -> Result<(Trace, Simulation)> {
    let mut r = Runner::new(sim, steps, sample_every)?;
    for k in 1..=steps {
        r.step()?;
        if r.trace.non_finite {
            break;
        }
        if k % 20 == 0 {
            bar.inc(20);
        }
    }
    bar.inc((steps % 20) as u64);
    Ok((r.trace, r.sim))
}

/// Max and RMS node distance (m) between two sampled runs over their common samples;
/// also the max per sample (the deviation over time).
pub fn deviation(run: &[Vec<V3>], reference: &[Vec<V3>]) -> Result<(f64, f64, Vec<f64>)> {
    if run.len() != reference.len() {
        bail!(
            "run has {} samples, reference {} (non-finite run?)",
            run.len(),
            reference.len()
        );
    }
    let mut max: f64 = 0.0;
    let mut sum2 = 0.0;
    let mut count = 0usize;
    let mut per_sample = Vec::with_capacity(run.len());
    for (a, b) in run.iter().zip(reference) {
        let mut m: f64 = 0.0;
        for (p, q) in a.iter().zip(b) {
            let d2 = (p - q).norm_squared();
            sum2 += d2;
            m = m.max(d2);
        }
        count += a.len();
        per_sample.push(m.sqrt());
        max = max.max(m.sqrt());
    }
    let rms = if count == 0 {
        0.0
    } else {
        (sum2 / count as f64).sqrt()
    };
    Ok((max, rms, per_sample))
}
