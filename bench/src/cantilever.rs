//! `cosurg bench cantilever`: accuracy and speed of the models and speed-ups on the beam of
//! `scenes/cantilever.toml` (0.4 × 0.1 × 0.1 m, clamped at x = 0, ν = 0.45,
//! ρ = 1000 kg/m³, gravity −z), soft (E = 1e5 Pa) and stiff (1e6 Pa), cells of 25 and
//! 12.5 mm, dt = 1 and 10 ms, 2 s simulated per run.
//!
//! Deviation is measured against the non-linear reference (StVK, backward Euler with
//! Newton, accurate CG) run at the same dt, comparing every live node every 10 ms of
//! simulated time. The reference runs once per (material, cell, dt) and is reused by every
//! run of that group.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use sim_core::Simulation;
use sim_core::sim_fem::Model;
use sim_core::sim_scene::builtin::{cantilever, cantilever_with};

use super::beam::{Knobs, Polar, RunConfig, Runner, Trace, build, deviation, model_name, simulate};
use cosurg::cli::out_dir;
use cosurg::plot::{Chart, Series, write_chart};

#[derive(Debug, Args)]
pub struct CantileverArgs {
    /// Print JSON (stdout) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Folder for JSON and plots (default out/bench-cantilever-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Reduced set for CI: coarse mesh, dt 10 ms, 0.5 s, core variants, no 1 kHz sweep.
    #[arg(long)]
    pub quick: bool,
    /// Simulated time per run (s); default 2 (0.5 with --quick).
    #[arg(long)]
    pub t_end: Option<f64>,
    /// Cell sizes (m), comma-separated; default 0.025,0.0125 (0.025 with --quick).
    #[arg(long, value_delimiter = ',')]
    pub cells: Vec<f64>,
    /// Time steps (s), comma-separated; default 0.001,0.01 (0.01 with --quick).
    #[arg(long, value_delimiter = ',')]
    pub dts: Vec<f64>,
    /// Run every co-rotational variant on every mesh and dt (by default the fine mesh at
    /// dt 1 ms runs only linear, all-on and one run per technique switched off: sharing,
    /// template stiffness, Byers–Xu).
    #[arg(long)]
    pub full: bool,
    /// Skip the "largest mesh at 1 kHz" sweep.
    #[arg(long)]
    pub no_khz: bool,
    /// Also run this MuJoCo peer script (e.g. ../shared/peers/mujoco_beam.py from the
    /// project's directory) on the soft beam of every mesh and dt, in this session, for
    /// comparison.
    #[arg(long)]
    pub peer: Option<PathBuf>,
}

/// One run as reported.
#[derive(Debug, Serialize)]
pub struct RunRow {
    pub model: String,
    pub material: String,
    pub young: f64,
    pub cell: f64,
    pub dt: f64,
    pub options: Knobs,
    pub tets: usize,
    pub nodes: usize,
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
    pub us_per_element: f64,
    pub max_dev_m: f64,
    pub rms_dev_m: f64,
    /// Rotation extractions per step (mean).
    pub rotations_per_step: f64,
    /// CG iterations per step (mean).
    pub cg_per_step: f64,
    /// Tip (x = 0.4 m, y = z = 0.05 m) vertical displacement at the end (m).
    pub tip_dz_m: f64,
    /// Steps that fell back to Newton (co-rotational, rotation change > 30°/step).
    pub fallback_steps: usize,
    pub steps: usize,
    pub non_finite: bool,
    pub scene_hash: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct KhzPoint {
    /// FEM step threads.
    pub threads: usize,
    pub cell: f64,
    pub tets: usize,
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
}

#[derive(Debug, Serialize)]
pub struct PeerRow {
    pub peer: String,
    pub mesh: String,
    pub tets: usize,
    pub dt: f64,
    pub median_ms: f64,
    pub tip_z_disp_m: f64,
    /// Our co-rotational all-on p50 for the same mesh, dt and material (ms).
    pub cosurg_corot_p50_ms: Option<f64>,
    /// The same on two threads (ms).
    pub cosurg_corot_2_threads_p50_ms: Option<f64>,
    /// Our co-rotational all-on step run alone like the peer (not interleaved with other
    /// runs, whose steps evict it from the caches between its steps), 2 s or at most
    /// 1,000 steps: p50 on one thread and on two (ms).
    pub cosurg_corot_solo_p50_ms: f64,
    pub cosurg_corot_solo_2_threads_p50_ms: f64,
    pub note: String,
}

#[derive(Debug, Serialize)]
pub struct Speedup {
    pub technique: String,
    /// p50(technique off) / p50(all on), per (material, cell, dt) group.
    pub per_group: Vec<(String, f64)>,
    pub median: f64,
}

#[derive(Debug, Serialize)]
pub struct CantileverReport {
    pub scene_hash: String,
    pub t_end_s: f64,
    pub sample_interval_s: f64,
    pub runs: Vec<RunRow>,
    pub speedups: Vec<Speedup>,
    pub khz_sweep: Vec<KhzPoint>,
    /// Largest mesh whose co-rotational (all-on) step p50 ≤ 1 ms at dt 1 ms, one core.
    pub largest_1khz: Option<KhzPoint>,
    /// The same with the step on two threads.
    pub largest_1khz_2_threads: Option<KhzPoint>,
    pub peers: Vec<PeerRow>,
    pub wall_s: f64,
}

const MATERIALS: [(&str, f64); 2] = [("soft", 1e5), ("stiff", 1e6)];
const SAMPLE_INTERVAL: f64 = 0.01;

/// Co-rotational all-on with every step converged (relative residual 1e-6, budget 500) by
/// the multigrid-preconditioned CG, where the others stop at the 50-iteration Jacobi-PCG
/// budget.
fn mg_pcg() -> RunConfig {
    RunConfig::all_on(Model::Corotational)
        .with_mg_pcg(500)
        .with(MG_PCG, |_| {})
}

fn variants(all: bool) -> Vec<RunConfig> {
    let on = || RunConfig::all_on(Model::Corotational);
    let mut v = vec![
        RunConfig::all_on(Model::Linear).with("default", |_| {}),
        on(),
        on().with("no-sharing", |c| c.sharing_angle_deg = 0.0),
        on().with("dense", |c| c.template_stiffness = false),
        on().with("polar-svd", |c| c.polar = Polar::Svd),
        on().with(TWO_THREADS, |c| c.threads = 2),
        mg_pcg(),
        mg_pcg().with("all-on-mg-pcg-1e-4", |c| c.cg_tolerance = 1e-4),
        mg_pcg().with("all-on-mg-pcg-1e-3", |c| c.cg_tolerance = 1e-3),
    ];
    if all {
        v.push(RunConfig::all_off(Model::Corotational));
        v.push(on().with("no-skip-rest", |c| c.skip_rest = false));
        v.push(on().with("polar-shape-matching", |c| c.polar = Polar::ShapeMatching));
        v.push(on().with("polar-muller", |c| c.polar = Polar::Muller));
    }
    v
}

pub fn run(args: CantileverArgs) -> Result<()> {
    let wall = std::time::Instant::now();
    let t_end = args.t_end.unwrap_or(if args.quick { 0.5 } else { 2.0 });
    let cells = if !args.cells.is_empty() {
        args.cells.clone()
    } else if args.quick {
        vec![0.025]
    } else {
        vec![0.025, 0.0125]
    };
    let dts = if !args.dts.is_empty() {
        args.dts.clone()
    } else if args.quick {
        vec![0.01]
    } else {
        vec![0.001, 0.01]
    };
    let base_hash = cantilever().hash;
    // Plan: groups (material, cell, dt) with their variant lists.
    let mut plan = Vec::new();
    for &(mat, young) in &MATERIALS {
        for &cell in &cells {
            for &dt in &dts {
                let expensive = cell < 0.02 && dt < 0.005;
                let list = if args.quick {
                    vec![
                        RunConfig::all_on(Model::Linear).with("default", |_| {}),
                        RunConfig::all_on(Model::Corotational),
                        RunConfig::all_off(Model::Corotational),
                        RunConfig::all_on(Model::Corotational).with(TWO_THREADS, |c| c.threads = 2),
                        mg_pcg(),
                    ]
                } else {
                    variants(args.full || !expensive)
                };
                plan.push((mat, young, cell, dt, list));
            }
        }
    }
    let total_steps: u64 = plan
        .iter()
        .map(|(_, _, _, dt, list)| ((t_end / dt).round() as u64) * (list.len() as u64 + 1))
        .sum();
    let bar = if args.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total_steps)
    };
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% eta {eta:>4} {msg}")
            .expect("static template"),
    );
    let mut rows = Vec::new();
    for (mat, young, cell, dt, list) in plan {
        let scene = cantilever_with(young, cell).context("cantilever scene")?;
        let steps = (t_end / dt).round() as usize;
        let every = ((SAMPLE_INTERVAL / dt).round() as usize).max(1);
        // The reference and every variant advance in lockstep, one step each in turn, so
        // that load from other processes on the machine falls on all of them alike.
        bar.set_message(format!(
            "{mat} {:.1} mm dt {} ms: reference + {} runs in lockstep",
            cell * 1e3,
            dt * 1e3,
            list.len()
        ));
        let mut configs = vec![RunConfig::reference()];
        configs.extend(list);
        let mut runners = Vec::with_capacity(configs.len());
        let mut knobs = Vec::with_capacity(configs.len());
        for rc in &configs {
            let (sim, k) = build(&scene, rc, dt)?;
            runners.push(Runner::new(sim, steps, every)?);
            knobs.push(k);
        }
        for _ in 0..steps {
            for r in &mut runners {
                r.step()?;
            }
            bar.inc(runners.len() as u64);
        }
        if runners[0].trace.non_finite {
            anyhow::bail!("non-linear reference became non-finite ({mat}, cell {cell}, dt {dt})");
        }
        let reference = runners[0].trace.samples.clone();
        for ((rc, k), r) in configs.iter().zip(knobs).zip(&runners) {
            let dev = if r.trace.non_finite {
                (f64::NAN, f64::NAN)
            } else {
                let (m, rms, _) = deviation(&r.trace.samples, &reference)?;
                (m, rms)
            };
            rows.push(row(
                &scene.hash,
                mat,
                young,
                cell,
                dt,
                model_name(rc.model),
                k,
                &r.trace,
                dev,
                tip_dz(&r.sim),
            ));
        }
    }
    bar.finish_and_clear();
    let khz = if args.no_khz || args.quick {
        Vec::new()
    } else {
        khz_sweep()?
    };
    let largest = |threads: usize| {
        khz.iter()
            .filter(|p| p.threads == threads && p.step_ms_p50 <= 1.0)
            .max_by_key(|p| p.tets)
            .cloned()
    };
    let (largest_1khz, largest_1khz_2_threads) = (largest(1), largest(2));
    let peers = match &args.peer {
        Some(script) => run_peers(script, &cells, &dts, t_end, &rows)?,
        None => Vec::new(),
    };
    let report = CantileverReport {
        scene_hash: base_hash,
        t_end_s: t_end,
        sample_interval_s: SAMPLE_INTERVAL,
        speedups: speedups(&rows),
        runs: rows,
        khz_sweep: khz,
        largest_1khz,
        largest_1khz_2_threads,
        peers,
        wall_s: wall.elapsed().as_secs_f64(),
    };
    let dir = out_dir(&args.out, "bench-cantilever");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let json = serde_json::to_string_pretty(&report)?;
    std::fs::write(dir.join("cantilever.json"), &json)?;
    let plots = plot(&dir, &report)?;
    if args.json {
        println!("{json}");
    } else {
        print_table(&report);
        println!("wrote {}", dir.join("cantilever.json").display());
        for p in plots {
            println!("wrote {}", p.display());
        }
    }
    Ok(())
}

fn tip_dz(sim: &Simulation) -> f64 {
    sim.probes()
        .into_iter()
        .zip(sim.probe_rest())
        .find(|((name, _), _)| name == "tip")
        .map_or(f64::NAN, |((_, p), r)| p.z - r.z)
}

#[allow(clippy::too_many_arguments)]
fn row(
    hash: &str,
    material: &str,
    young: f64,
    cell: f64,
    dt: f64,
    model: &str,
    options: Knobs,
    t: &Trace,
    dev: (f64, f64),
    tip_dz_m: f64,
) -> RunRow {
    let p50 = t.p50();
    let n = t.step_ms.len().max(1) as f64;
    RunRow {
        model: model.into(),
        material: material.into(),
        young,
        cell,
        dt,
        options,
        tets: t.tets,
        nodes: t.nodes,
        step_ms_p50: p50,
        step_ms_p99: t.p99(),
        us_per_element: p50 * 1e3 / t.tets.max(1) as f64,
        max_dev_m: dev.0,
        rms_dev_m: dev.1,
        rotations_per_step: t.rotations_extracted as f64 / n,
        cg_per_step: t.cg_iterations as f64 / n,
        tip_dz_m,
        fallback_steps: t.fallback_steps,
        steps: t.step_ms.len(),
        non_finite: t.non_finite,
        scene_hash: hash.into(),
    }
}

fn group_key(r: &RunRow) -> String {
    format!("{} {:.1}mm dt{}ms", r.material, r.cell * 1e3, r.dt * 1e3)
}

/// Variant label of the all-on configuration stepped on two threads.
const TWO_THREADS: &str = "all-on-2-threads";
const MG_PCG: &str = "all-on-mg-pcg";

/// p50 of each single-technique-off variant over p50 of all-on, per group (and all-on
/// over all-on on two threads: what the second core gives).
fn speedups(rows: &[RunRow]) -> Vec<Speedup> {
    let techniques = [
        ("rotation sharing (θ 5° vs off)", "no-sharing"),
        ("template stiffness (vs dense)", "dense"),
        ("polar Byers-Xu (vs SVD)", "polar-svd"),
        ("polar Byers-Xu (vs shape matching)", "polar-shape-matching"),
        ("polar Byers-Xu (vs Müller)", "polar-muller"),
        ("skip-rest (vs off)", "no-skip-rest"),
        ("all speed-ups (vs all off)", "all-off"),
        ("second core (2 threads vs 1)", TWO_THREADS),
    ];
    let mut on: BTreeMap<String, f64> = BTreeMap::new();
    for r in rows
        .iter()
        .filter(|r| r.model == "corotational" && r.options.variant == "all-on")
    {
        on.insert(group_key(r), r.step_ms_p50);
    }
    techniques
        .iter()
        .filter_map(|(name, variant)| {
            let per_group: Vec<(String, f64)> = rows
                .iter()
                .filter(|r| r.model == "corotational" && r.options.variant == *variant)
                .filter_map(|r| {
                    on.get(&group_key(r)).map(|p| {
                        let ratio = if *variant == TWO_THREADS {
                            p / r.step_ms_p50
                        } else {
                            r.step_ms_p50 / p
                        };
                        (group_key(r), ratio)
                    })
                })
                .collect();
            if per_group.is_empty() {
                return None;
            }
            let v: Vec<f64> = per_group.iter().map(|(_, s)| *s).collect();
            Some(Speedup {
                technique: (*name).into(),
                median: cosurg::stats::percentile(&v, 50.0),
                per_group,
            })
        })
        .collect()
}

/// Cell sizes that divide the 0.1 m beam cross-section, coarse to fine.
const KHZ_CELLS: [f64; 8] = [
    0.05,
    0.1 / 3.0,
    0.025,
    0.02,
    0.1 / 6.0,
    0.1 / 7.0,
    0.0125,
    0.01,
];

/// Co-rotational (all-on), soft beam, dt 1 ms, 0.3 s per mesh until the p50 exceeds 1 ms;
/// on one thread, then on two.
fn khz_sweep() -> Result<Vec<KhzPoint>> {
    let mut out = Vec::new();
    let bar = ProgressBar::new(2 * KHZ_CELLS.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} 1 kHz sweep {msg}").expect("static"),
    );
    for threads in [1, 2] {
        for cell in KHZ_CELLS {
            let scene = cantilever_with(1e5, cell)?;
            let rc = RunConfig::all_on(Model::Corotational).with("all-on", |c| c.threads = threads);
            let (sim, _) = build(&scene, &rc, 0.001)?;
            let (t, _) = simulate(sim, 300, 1000, &ProgressBar::hidden())?;
            let p = KhzPoint {
                threads,
                cell,
                tets: t.tets,
                step_ms_p50: t.p50(),
                step_ms_p99: t.p99(),
            };
            bar.set_message(format!(
                "{threads} thread(s), {} tets: {:.3} ms",
                p.tets, p.step_ms_p50
            ));
            bar.inc(1);
            let over = p.step_ms_p50 > 1.0;
            out.push(p);
            if over {
                break;
            }
        }
    }
    bar.finish_and_clear();
    Ok(out)
}

/// Runs the MuJoCo peer script on the soft beam (coarse = 25 mm, fine = 12.5 mm cells).
fn run_peers(
    script: &std::path::Path,
    cells: &[f64],
    dts: &[f64],
    t_end: f64,
    rows: &[RunRow],
) -> Result<Vec<PeerRow>> {
    let results = std::env::temp_dir().join(format!("cosurg-peers-{}", std::process::id()));
    let mut out = Vec::new();
    for &cell in cells {
        let mesh = if (cell - 0.025).abs() < 1e-9 {
            "coarse"
        } else if (cell - 0.0125).abs() < 1e-9 {
            "fine"
        } else {
            continue;
        };
        for &dt in dts {
            eprintln!("peer: mujoco {mesh} dt {} ms ...", dt * 1e3);
            let status = std::process::Command::new("python3")
                .arg(script)
                .args([
                    "--mesh",
                    mesh,
                    "--dt",
                    &dt.to_string(),
                    "--t-end",
                    &t_end.to_string(),
                ])
                .env("PEERS_RESULTS", &results)
                .stdout(std::process::Stdio::null())
                .status()
                .with_context(|| format!("running python3 {}", script.display()))?;
            if !status.success() {
                eprintln!("peer script failed ({status}); skipping");
                continue;
            }
            let file = results.join(format!(
                "mujoco_stvk_{mesh}_dt{}ms_discrete.json",
                fmt_g(dt * 1e3)
            ));
            let text = std::fs::read_to_string(&file)
                .with_context(|| format!("reading {}", file.display()))?;
            let v: serde_json::Value = serde_json::from_str(&text)?;
            let solo = |threads: usize| -> Result<f64> {
                let scene = cantilever_with(1e5, cell)?;
                let rc =
                    RunConfig::all_on(Model::Corotational).with("solo", |c| c.threads = threads);
                let (sim, _) = build(&scene, &rc, dt)?;
                let steps = ((t_end / dt).round() as usize).min(1000);
                let (t, _) = simulate(sim, steps, steps, &ProgressBar::hidden())?;
                Ok(t.p50())
            };
            let ours = |variant: &str| {
                rows.iter()
                    .find(|r| {
                        r.model == "corotational"
                            && r.options.variant == variant
                            && r.material == "soft"
                            && (r.cell - cell).abs() < 1e-9
                            && (r.dt - dt).abs() < 1e-12
                    })
                    .map(|r| r.step_ms_p50)
            };
            out.push(PeerRow {
                peer: format!("mujoco {}", v["version"].as_str().unwrap_or("?")),
                mesh: mesh.into(),
                tets: v["tets"].as_u64().unwrap_or(0) as usize,
                dt,
                median_ms: v["median_ms"].as_f64().unwrap_or(f64::NAN),
                tip_z_disp_m: v["tip_z_disp_m"].as_f64().unwrap_or(f64::NAN),
                cosurg_corot_p50_ms: ours("all-on"),
                cosurg_corot_2_threads_p50_ms: ours(TWO_THREADS),
                cosurg_corot_solo_p50_ms: solo(1)?,
                cosurg_corot_solo_2_threads_p50_ms: solo(2)?,
                note: "StVK flex, implicit (discrete), Rayleigh β = 0.3 s; cosurg runs undamped"
                    .into(),
            });
        }
    }
    Ok(out)
}

/// Python's `%g` for the few values used in peer file names (1, 10, 33, 0.5 …).
fn fmt_g(v: f64) -> String {
    let s = format!("{v}");
    s.strip_suffix(".0").map(str::to_string).unwrap_or(s)
}

fn plot(dir: &std::path::Path, r: &CantileverReport) -> Result<Vec<PathBuf>> {
    let mut by: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for row in &r.runs {
        if row.model == model_name(Model::StVK) || !row.max_dev_m.is_finite() {
            continue;
        }
        let label = if row.model == "corotational" {
            format!("corotational {}", row.options.variant)
        } else {
            row.model.clone()
        };
        by.entry(label)
            .or_default()
            .push((row.step_ms_p50, row.max_dev_m.max(1e-9)));
    }
    let series: Vec<Series> = by
        .into_iter()
        .map(|(label, points)| Series { label, points })
        .collect();
    write_chart(
        dir,
        "cantilever_deviation_vs_step_time",
        &Chart {
            title: "cantilever: max node deviation from StVK vs step time (p50)",
            x_label: "step time p50 (ms)",
            y_label: "max deviation (m)",
            log_x: true,
            log_y: true,
            scatter: true,
        },
        &series,
    )
}

fn print_table(r: &CantileverReport) {
    println!(
        "cantilever (scene {}), {} s simulated per run, deviation vs StVK every {} ms",
        &r.scene_hash[..12.min(r.scene_hash.len())],
        r.t_end_s,
        r.sample_interval_s * 1e3
    );
    println!(
        "{:<13} {:<21} {:<5} {:>5} {:>4} {:>6} {:>8} {:>8} {:>7} {:>10} {:>10} {:>7} {:>9}",
        "model",
        "variant",
        "mat",
        "cell",
        "dt",
        "tets",
        "p50 ms",
        "p99 ms",
        "µs/el",
        "max dev m",
        "rms dev m",
        "rot/st",
        "tip dz m"
    );
    for x in &r.runs {
        println!(
            "{:<13} {:<21} {:<5} {:>5.1} {:>4} {:>6} {:>8.3} {:>8.3} {:>7.3} {:>10.3e} {:>10.3e} {:>7.0} {:>9.4}",
            x.model,
            x.options.variant,
            x.material,
            x.cell * 1e3,
            x.dt * 1e3,
            x.tets,
            x.step_ms_p50,
            x.step_ms_p99,
            x.us_per_element,
            x.max_dev_m,
            x.rms_dev_m,
            x.rotations_per_step,
            x.tip_dz_m
        );
    }
    if !r.speedups.is_empty() {
        println!("\nspeed-up of the co-rotational step (p50 with the technique off / all on):");
        for s in &r.speedups {
            let groups: Vec<String> = s
                .per_group
                .iter()
                .map(|(g, v)| format!("{g} {v:.2}×"))
                .collect();
            println!(
                "  {:<36} median {:.2}×  ({})",
                s.technique,
                s.median,
                groups.join(", ")
            );
        }
    }
    if !r.khz_sweep.is_empty() {
        println!("\n1 kHz sweep (co-rotational all-on, soft, dt 1 ms):");
        for p in &r.khz_sweep {
            println!(
                "  {} thread(s)  cell {:>6.2} mm  {:>6} tets  p50 {:.3} ms  p99 {:.3} ms",
                p.threads,
                p.cell * 1e3,
                p.tets,
                p.step_ms_p50,
                p.step_ms_p99
            );
        }
        match &r.largest_1khz {
            Some(p) => println!(
                "largest mesh stepping at 1 kHz on one core: {} tets (cell {:.2} mm, p50 {:.3} ms)",
                p.tets,
                p.cell * 1e3,
                p.step_ms_p50
            ),
            None => println!("no mesh of the sweep steps at 1 kHz"),
        }
        if let Some(p) = &r.largest_1khz_2_threads {
            println!(
                "largest mesh stepping at 1 kHz on two threads: {} tets (cell {:.2} mm, p50 {:.3} ms)",
                p.tets,
                p.cell * 1e3,
                p.step_ms_p50
            );
        }
    }
    for p in &r.peers {
        println!(
            "peer {} {} ({} tets) dt {} ms: median {:.3} ms/step, tip dz {:.4} m; cosurg corotational all-on p50 {} ms, on 2 threads {} ms (interleaved); alone {:.3} ms, on 2 threads {:.3} ms ({})",
            p.peer,
            p.mesh,
            p.tets,
            p.dt * 1e3,
            p.median_ms,
            p.tip_z_disp_m,
            p.cosurg_corot_p50_ms
                .map_or("-".into(), |v| format!("{v:.3}")),
            p.cosurg_corot_2_threads_p50_ms
                .map_or("-".into(), |v| format!("{v:.3}")),
            p.cosurg_corot_solo_p50_ms,
            p.cosurg_corot_solo_2_threads_p50_ms,
            p.note
        );
    }
    println!("wall time {:.1} s", r.wall_s);
}
