//! `cosurg bench stress`: robustness of the co-rotational product configuration on long
//! runs with large time steps, a 1000× stiffness contrast, pulls that invert elements and
//! violent random impulses.
//!
//! The body is the cantilever beam (clamped at x = 0, gravity −z, soft tissue E = 1e5 Pa)
//! with a stiff capsule inclusion along its axis (E = 1e8 Pa). Every case has an
//! *injection* phase (a pull through the body, or random nodal impulses) and a *free*
//! phase. Reported per case: whether any state became non-finite (must never happen), the
//! energy growth in the free phase `max (E − E_min) / (E_release − E_min)` (E = elastic +
//! kinetic + gravitational energy; ≤ 1 for a passive system, E_min the free phase's
//! minimum), the number of steps until the body is back at rest (max node speed
//! < 1 mm/s), the most inverted elements seen, and the smallest det F.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use sim_core::NodeId;
use sim_core::sim_fem::Model;
use sim_core::sim_scene::builtin::cantilever_with;
use sim_core::sim_scene::{Capsule, Inclusion, LoadedScene, Material};

use super::beam::{RunConfig, build};
use cosurg::cli::out_dir;
use cosurg::plot::{Chart, Series};

type V3 = Vector3<f64>;

#[derive(Debug, Args)]
pub struct StressArgs {
    /// Print JSON (stdout) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Folder for the JSON (default out/bench-stress-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Reduced set for CI: 2,000 steps per case.
    #[arg(long)]
    pub quick: bool,
    /// Steps per case (default 100,000; 2,000 with --quick).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Lattice cell (m); default 0.05 (192 tets).
    #[arg(long, default_value_t = 0.05)]
    pub cell: f64,
    /// Random seed of the impulses.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Run only the cases whose name contains this (e.g. `pull-through-10ms`).
    #[arg(long)]
    pub case: Option<String>,
    /// Run only this solver configuration (`product`, `cg-converged`, `mg-pcg`,
    /// `mg-pcg-budget`); default all.
    #[arg(long)]
    pub config: Option<String>,
}

#[derive(Debug, Serialize)]
pub struct CaseResult {
    pub name: String,
    /// Solver configuration: `product` (co-rotational all-on, the scene's 50-iteration CG
    /// budget), `cg-converged` (same, CG up to 2,000 iterations to 1e-6), `mg-pcg` (same,
    /// MG-PCG up to 2,000 iterations to 1e-6) or `mg-pcg-budget` (MG-PCG with the
    /// product's 50-iteration budget).
    pub config: String,
    /// CG iterations per step (mean) and steps that fell back to Newton.
    pub cg_per_step: f64,
    pub fallback_steps: usize,
    /// Of the fallback steps, those redone because the linearised step created energy.
    pub energy_guard_steps: usize,
    pub dt: f64,
    pub steps: usize,
    pub tets: usize,
    pub stiffness_contrast: f64,
    /// Any non-finite state (the engine rolls such a step back and reports it).
    pub nan: bool,
    /// Steps in the injection phase.
    pub injection_steps: usize,
    /// Energy growth after release, `max (E − E_min)/(E_release − E_min)` (≤ 1 passive).
    pub max_energy_rel: f64,
    /// Energy at release (J, relative to the rest pose).
    pub energy_release_j: f64,
    /// Largest energy seen in the whole run (J).
    pub energy_max_j: f64,
    /// Steps after release until max node speed < 1 mm/s (None: not within the run).
    pub steps_to_rest: Option<usize>,
    /// Most elements with det F ≤ 0 at once.
    pub max_inverted: usize,
    /// Smallest det F seen.
    pub min_det_f: f64,
    /// Largest node speed (m/s).
    pub max_speed: f64,
    pub wall_s: f64,
    /// About 500 samples over the run: (time s, energy J, max node speed m/s).
    pub trace: Vec<(f64, f64, f64)>,
}

#[derive(Debug, Serialize)]
pub struct StressReport {
    pub scene_hash: String,
    pub cases: Vec<CaseResult>,
}

/// Mass-proportional Rayleigh damping of the tissue in the stress scene (1/s): about 5 %
/// of critical for the beam's first bending mode (≈ 3 Hz). Undamped, a body comes to rest
/// only through backward Euler's numerical damping, which at dt = 1 ms takes minutes.
pub const TISSUE_DAMPING: f64 = 2.0;

/// The beam with a stiff axial capsule: 1000× contrast, damped tissue.
pub fn inclusion_beam(cell: f64) -> Result<LoadedScene> {
    let mut scene = cantilever_with(1e5, cell)?;
    scene.modify(|sc| {
        for m in sc.materials.values_mut() {
            m.rayleigh_mass = TISSUE_DAMPING;
        }
        sc.materials.insert(
            "stiff".into(),
            Material {
                young: 1e8,
                poisson: 0.45,
                density: 1000.0,
                rayleigh_mass: 0.0,
                rayleigh_stiffness: 0.0,
            },
        );
        sc.bodies[0].inclusions.push(Inclusion {
            name: Some("rod".into()),
            material: "stiff".into(),
            capsules: Some(vec![Capsule {
                a: V3::new(0.1, 0.05, 0.05),
                b: V3::new(0.3, 0.05, 0.05),
                radius: 0.035,
            }]),
            mesh: None,
            refine_boundary: false,
        });
    })?;
    Ok(scene)
}

#[derive(Clone, Copy, Debug)]
enum Injection {
    /// Drag the tip face to x = `to_x` over `seconds`, hold `hold` s, release.
    Pull { to_x: f64, seconds: f64, hold: f64 },
    /// `count` random impulses (Δv up to `dv` m/s on single nodes) over `seconds`.
    Impulses { count: usize, dv: f64, seconds: f64 },
}

struct Case {
    name: &'static str,
    dt: f64,
    injection: Injection,
}

const CASES: [Case; 4] = [
    Case {
        name: "pull-through-10ms",
        dt: 0.01,
        injection: Injection::Pull {
            to_x: -0.2,
            seconds: 1.0,
            hold: 0.5,
        },
    },
    Case {
        name: "pull-through-33ms",
        dt: 0.033,
        injection: Injection::Pull {
            to_x: -0.2,
            seconds: 1.0,
            hold: 0.5,
        },
    },
    Case {
        name: "impulses-1ms",
        dt: 0.001,
        injection: Injection::Impulses {
            count: 50,
            dv: 20.0,
            seconds: 1.0,
        },
    },
    Case {
        name: "impulses-33ms",
        dt: 0.033,
        injection: Injection::Impulses {
            count: 50,
            dv: 20.0,
            seconds: 2.0,
        },
    },
];

pub fn run(args: StressArgs) -> Result<()> {
    let steps = args
        .steps
        .unwrap_or(if args.quick { 2_000 } else { 100_000 });
    let scene = inclusion_beam(args.cell).context("inclusion beam scene")?;
    let selected: Vec<&Case> = CASES
        .iter()
        .filter(|c| {
            args.case
                .as_ref()
                .is_none_or(|f| c.name.contains(f.as_str()))
        })
        .collect();
    if selected.is_empty() {
        anyhow::bail!(
            "no stress case matches {:?}; cases: {}",
            args.case.as_deref().unwrap_or(""),
            CASES.iter().map(|c| c.name).collect::<Vec<_>>().join(", ")
        );
    }
    let run_configs: Vec<RunConfig> = configs()
        .into_iter()
        .filter(|c| args.config.as_ref().is_none_or(|f| c.variant == *f))
        .collect();
    if run_configs.is_empty() {
        anyhow::bail!(
            "no stress configuration {:?}; configurations: {}",
            args.config.as_deref().unwrap_or(""),
            configs().map(|c| c.variant).join(", ")
        );
    }
    let bar = if args.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new((run_configs.len() * steps * selected.len()) as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% eta {eta:>4} {msg}")
            .expect("static template"),
    );
    let mut cases = Vec::new();
    for case in selected {
        for config in &run_configs {
            bar.set_message(format!("{} {}", case.name, config.variant));
            cases.push(run_case(&scene, case, config, steps, args.seed, &bar)?);
        }
    }
    bar.finish_and_clear();
    let report = StressReport {
        scene_hash: scene.hash.clone(),
        cases,
    };
    let dir = out_dir(&args.out, "bench-stress");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let json = serde_json::to_string_pretty(&report)?;
    std::fs::write(dir.join("stress.json"), &json)?;
    let plots = plot(&dir, &report)?;
    if args.json {
        println!("{json}");
    } else {
        println!(
            "stress: beam with a 1000× stiffer rod, tissue damping α = {TISSUE_DAMPING}/s, co-rotational all-on, {steps} steps per case"
        );
        println!(
            "{:<18} {:<12} {:>5} {:>5} {:>4} {:>9} {:>10} {:>11} {:>8} {:>9} {:>8} {:>6} {:>6} {:>6} {:>7}",
            "case",
            "config",
            "dt ms",
            "tets",
            "NaN",
            "E growth",
            "E rel. J",
            "steps→rest",
            "max inv",
            "min detF",
            "max v",
            "cg/st",
            "fallbk",
            "guard",
            "wall s"
        );
        for c in &report.cases {
            println!(
                "{:<18} {:<12} {:>5} {:>5} {:>4} {:>9.3} {:>10.3e} {:>11} {:>8} {:>9.2} {:>8.2} {:>6.0} {:>6} {:>6} {:>7.1}",
                c.name,
                c.config,
                c.dt * 1e3,
                c.tets,
                if c.nan { "YES" } else { "no" },
                c.max_energy_rel,
                c.energy_release_j,
                c.steps_to_rest.map_or("never".into(), |s| s.to_string()),
                c.max_inverted,
                c.min_det_f,
                c.max_speed,
                c.cg_per_step,
                c.fallback_steps,
                c.energy_guard_steps,
                c.wall_s
            );
        }
        println!("wrote {}", dir.join("stress.json").display());
        for p in plots {
            println!("wrote {}", p.display());
        }
    }
    Ok(())
}

/// Energy and largest node speed against time, one series per case and configuration.
fn plot(dir: &std::path::Path, r: &StressReport) -> Result<Vec<PathBuf>> {
    let series = |value: fn(&(f64, f64, f64)) -> f64| -> Vec<Series> {
        r.cases
            .iter()
            .map(|c| Series {
                label: format!("{} {}", c.name, c.config),
                points: c.trace.iter().map(|s| (s.0, value(s))).collect(),
            })
            .collect()
    };
    // Energy relative to the rest pose can be negative (gravity): plot it shifted by the
    // run's minimum so the log axis shows decay and growth alike.
    let energy: Vec<Series> = r
        .cases
        .iter()
        .map(|c| {
            let min = c.trace.iter().map(|s| s.1).fold(f64::INFINITY, f64::min);
            Series {
                label: format!("{} {}", c.name, c.config),
                points: c.trace.iter().map(|s| (s.0, s.1 - min + 1e-9)).collect(),
            }
        })
        .collect();
    let mut out = cosurg::plot::write_chart(
        dir,
        "stress_energy",
        &Chart {
            title: "stress: energy above its minimum",
            x_label: "simulated time (s)",
            y_label: "E - E_min (J)",
            log_x: false,
            log_y: true,
            scatter: false,
        },
        &energy,
    )?;
    out.extend(cosurg::plot::write_chart(
        dir,
        "stress_speed",
        &Chart {
            title: "stress: largest node speed",
            x_label: "simulated time (s)",
            y_label: "max |v| (m/s)",
            log_x: false,
            log_y: true,
            scatter: false,
        },
        &series(|s| s.2.max(1e-9)),
    )?);
    Ok(out)
}

/// The solver configurations every case runs with.
fn configs() -> [RunConfig; 4] {
    let on = || RunConfig::all_on(Model::Corotational);
    [
        on().with("product", |_| {}),
        on().with("cg-converged", |c| c.cg_iterations = 2000),
        on().with_mg_pcg(2000).with("mg-pcg", |_| {}),
        // what a scene with `solver = "mg-pcg"` runs: the scene's budget
        on().with_mg_pcg(50).with("mg-pcg-budget", |_| {}),
    ]
}

fn run_case(
    scene: &LoadedScene,
    case: &Case,
    config: &RunConfig,
    steps: usize,
    seed: u64,
    bar: &ProgressBar,
) -> Result<CaseResult> {
    let wall = Instant::now();
    let (mut sim, _) = build(scene, config, case.dt)?;
    let nodes: Vec<NodeId> = sim.lattice().nodes().collect();
    let tets = sim.lattice().leaf_count();
    let free: Vec<NodeId> = nodes
        .iter()
        .copied()
        .filter(|n| !sim.is_fixed(*n))
        .collect();
    let tip: Vec<NodeId> = nodes
        .iter()
        .copied()
        .filter(|n| sim.lattice().node_rest(*n).x > 0.4 - 1e-9)
        .collect();
    let mass: Vec<f64> = sim.fem()?.lumped_mass().to_vec();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (injection_steps, impulse_every) = match case.injection {
        Injection::Pull { seconds, hold, .. } => (((seconds + hold) / case.dt).round() as usize, 0),
        Injection::Impulses { count, seconds, .. } => {
            let n = (seconds / case.dt).round() as usize;
            (n, (n / count.max(1)).max(1))
        }
    };
    let injection_steps = injection_steps.min(steps / 2);
    let mut out = CaseResult {
        name: case.name.into(),
        config: config.variant.clone(),
        cg_per_step: 0.0,
        fallback_steps: 0,
        energy_guard_steps: 0,
        dt: case.dt,
        steps: 0,
        tets,
        stiffness_contrast: 1000.0,
        nan: false,
        injection_steps,
        max_energy_rel: 0.0,
        energy_release_j: 0.0,
        energy_max_j: f64::NEG_INFINITY,
        steps_to_rest: None,
        max_inverted: 0,
        min_det_f: f64::INFINITY,
        max_speed: 0.0,
        wall_s: 0.0,
        trace: Vec::new(),
    };
    let trace_every = (steps / 500).max(1);
    let mut free_energies: Vec<f64> = Vec::new();
    let mut rest_run = 0usize;
    for k in 0..steps {
        if k < injection_steps {
            match case.injection {
                Injection::Pull { to_x, seconds, .. } => {
                    let s = ((k + 1) as f64 * case.dt / seconds).min(1.0);
                    for &n in &tip {
                        let r = sim.lattice().node_rest(n);
                        sim.prescribe(n, V3::new(r.x + s * (to_x - r.x), r.y, r.z));
                    }
                }
                Injection::Impulses { dv, .. } => {
                    if k % impulse_every == 0 {
                        let n = free[rng.random_range(0..free.len())];
                        let dir = V3::new(
                            rng.random_range(-1.0..1.0),
                            rng.random_range(-1.0..1.0),
                            rng.random_range(-1.0..1.0),
                        );
                        let dir = dir.try_normalize(1e-9).unwrap_or(V3::z());
                        let m = mass[n.0 as usize];
                        // Δv over one step: F = m Δv / dt.
                        sim.add_force(n, dir * (m * dv * rng.random_range(0.5..1.0) / case.dt));
                    }
                }
            }
        }
        match sim.step() {
            Ok(r) => {
                out.cg_per_step += r.fem.cg_iterations as f64;
                out.fallback_steps += r.fem.fallback as usize;
                out.energy_guard_steps += r.fem.energy_guard as usize;
            }
            Err(sim_core::SimError::NonFinite { .. }) => {
                out.nan = true;
                break;
            }
            Err(e) => return Err(e).context(case.name),
        }
        out.steps = k + 1;
        bar.inc(1);
        let x = sim.positions();
        if !x.iter().all(|p| p.iter().all(|c| c.is_finite())) {
            out.nan = true;
            break;
        }
        let vmax = sim
            .velocities()
            .iter()
            .map(|v| v.norm())
            .fold(0.0, f64::max);
        out.max_speed = out.max_speed.max(vmax);
        // Inversion statistics during the injection and shortly after.
        if k < injection_steps + 200 || k % 100 == 0 {
            let x = x.to_vec();
            let fem = sim.fem()?;
            let mut inverted = 0;
            for e in 0..fem.num_elements() {
                let d = fem.deformation_gradient(e, &x).determinant();
                out.min_det_f = out.min_det_f.min(d);
                inverted += (d <= 0.0) as usize;
            }
            out.max_inverted = out.max_inverted.max(inverted);
        }
        let e = sim.energy()?;
        if !e.is_finite() {
            out.nan = true;
            break;
        }
        out.energy_max_j = out.energy_max_j.max(e);
        if k % trace_every == 0 {
            out.trace.push(((k + 1) as f64 * case.dt, e, vmax));
        }
        if k + 1 == injection_steps {
            out.energy_release_j = e;
        }
        if k + 1 >= injection_steps {
            free_energies.push(e);
            if out.steps_to_rest.is_none() {
                if vmax < 1e-3 {
                    rest_run += 1;
                    if rest_run >= 10 {
                        out.steps_to_rest = Some(k + 1 - injection_steps - 9);
                    }
                } else {
                    rest_run = 0;
                }
            }
        }
    }
    bar.inc((steps - out.steps) as u64);
    out.cg_per_step /= out.steps.max(1) as f64;
    if let Some(&e0) = free_energies.first() {
        let emin = free_energies.iter().copied().fold(f64::INFINITY, f64::min);
        let emax = free_energies
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        out.max_energy_rel = if e0 - emin > 0.0 {
            (emax - emin) / (e0 - emin)
        } else {
            1.0
        };
    }
    out.wall_s = wall.elapsed().as_secs_f64();
    Ok(out)
}
