//! `cosurg bench sweep`: step time against error over the knobs of the co-rotational model
//! on the coarse soft cantilever (25 mm cells, E = 1e5 Pa): polar tolerance, sharing angle
//! θ_tol, uniform refinement depth, CG iterations and time step, one at a time from the
//! product configuration plus a small grid of (CG iterations × θ_tol × dt). The error is
//! the max distance of the root-lattice nodes from the non-linear reference (StVK,
//! dt = 1 ms, same lattice depth 0) every 10 ms of simulated time, `max_dev_m`; and, to
//! isolate what the knobs cost in accuracy from what the model costs, the same distance
//! from the converged co-rotational run (SVD rotations, no sharing, no skip-rest, CG to
//! 1e-10, dt = 1 ms), `knob_dev_m`. The Pareto front over (step time, knob_dev_m) (no
//! other run both faster and more accurate) is printed and plotted.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use sim_core::sim_fem::Model;
use sim_core::sim_scene::builtin::cantilever_with;

use super::beam::{Knobs, RunConfig, Runner, build, deviation, simulate};
use cosurg::cli::out_dir;
use cosurg::plot::{Chart, Series, write_chart};

#[derive(Debug, Args)]
pub struct SweepArgs {
    /// Print JSON (stdout) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Folder for JSON and plots (default out/bench-sweep-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Simulated time per run (s).
    #[arg(long, default_value_t = 1.0)]
    pub t_end: f64,
    /// Fewer points (CI).
    #[arg(long)]
    pub quick: bool,
}

#[derive(Debug, Serialize)]
pub struct SweepPoint {
    /// Which knob this point varies (`base`, `polar_tolerance`, `sharing_angle_deg`,
    /// `refinement_depth`, `cg_iterations`, `dt`, `grid`).
    pub knob: String,
    pub dt: f64,
    pub options: Knobs,
    pub tets: usize,
    pub step_ms_p50: f64,
    /// Wall time per simulated second (s/s): p50 step time / dt.
    pub wall_per_sim_s: f64,
    pub max_dev_m: f64,
    pub rms_dev_m: f64,
    /// Max node distance from the converged co-rotational run (m).
    pub knob_dev_m: f64,
    pub pareto: bool,
}

#[derive(Debug, Serialize)]
pub struct SweepReport {
    pub scene_hash: String,
    pub reference: String,
    pub t_end_s: f64,
    pub points: Vec<SweepPoint>,
}

const SAMPLE_INTERVAL: f64 = 0.01;
const REF_DT: f64 = 0.001;

fn plan(quick: bool) -> Vec<(String, f64, RunConfig)> {
    let base = || RunConfig::all_on(Model::Corotational);
    let mut v: Vec<(String, f64, RunConfig)> = vec![("base".into(), 0.001, base())];
    let tols: &[f64] = if quick {
        &[1e-2]
    } else {
        &[1e-1, 1e-2, 1e-4, 1e-8]
    };
    for &t in tols {
        v.push((
            "polar_tolerance".into(),
            0.001,
            base().with(&format!("polar-tol-{t:e}"), |c| c.polar_tolerance = t),
        ));
    }
    let angles: &[f64] = if quick {
        &[0.0]
    } else {
        &[0.0, 1.0, 2.0, 10.0, 20.0]
    };
    for &a in angles {
        v.push((
            "sharing_angle_deg".into(),
            0.001,
            base().with(&format!("theta-{a}"), |c| c.sharing_angle_deg = a),
        ));
    }
    let depths: &[u32] = if quick { &[] } else { &[1, 2] };
    for &d in depths {
        v.push((
            "refinement_depth".into(),
            0.001,
            base().with(&format!("depth-{d}"), |c| c.depth = d),
        ));
    }
    let cgs: &[usize] = if quick { &[10] } else { &[5, 10, 25, 100, 200] };
    for &n in cgs {
        v.push((
            "cg_iterations".into(),
            0.001,
            base().with(&format!("cg-{n}"), |c| c.cg_iterations = n),
        ));
    }
    let dts: &[f64] = if quick {
        &[0.01]
    } else {
        &[0.002, 0.005, 0.01]
    };
    for &dt in dts {
        v.push((
            "dt".into(),
            dt,
            base().with(&format!("dt-{}ms", dt * 1e3), |_| {}),
        ));
    }
    if !quick {
        for &n in &[10usize, 25] {
            for &a in &[2.0, 10.0] {
                for &dt in &[0.002, 0.005] {
                    v.push((
                        "grid".into(),
                        dt,
                        base().with(&format!("cg-{n} theta-{a} dt-{}ms", dt * 1e3), |c| {
                            c.cg_iterations = n;
                            c.sharing_angle_deg = a;
                        }),
                    ));
                }
            }
        }
    }
    v
}

pub fn run(args: SweepArgs) -> Result<()> {
    let scene = cantilever_with(1e5, 0.025).context("cantilever scene")?;
    let t_end = if args.quick {
        args.t_end.min(0.3)
    } else {
        args.t_end
    };
    let runs = plan(args.quick);
    let steps_of = |dt: f64| (t_end / dt).round() as usize;
    let total: usize =
        2 * steps_of(REF_DT) + runs.iter().map(|(_, dt, _)| steps_of(*dt)).sum::<usize>();
    let bar = if args.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% eta {eta:>4} {msg}")
            .expect("static template"),
    );
    bar.set_message("reference");
    let rc = RunConfig::reference();
    let (sim, _) = build(&scene, &rc, REF_DT)?;
    let nodes = super::beam::live_nodes(&sim);
    let every_ref = (SAMPLE_INTERVAL / REF_DT).round() as usize;
    let (reference, _) = simulate(sim, steps_of(REF_DT), every_ref, &bar)?;
    bar.set_message("converged co-rotational");
    let converged_cfg = RunConfig::all_off(Model::Corotational).with("converged", |c| {
        c.template_stiffness = true;
        c.cg_iterations = 2000;
        c.cg_tolerance = 1e-10;
    });
    let (sim, _) = build(&scene, &converged_cfg, REF_DT)?;
    let (converged, _) = simulate(sim, steps_of(REF_DT), every_ref, &bar)?;
    // All runs advance in lockstep by simulated time (the one furthest behind steps
    // next), so that load from other processes falls on every run alike.
    bar.set_message(format!("{} runs in lockstep", runs.len()));
    let mut runners = Vec::with_capacity(runs.len());
    let mut knobs = Vec::with_capacity(runs.len());
    for (_, dt, rc) in &runs {
        let (sim, k) = build(&scene, rc, *dt)?;
        let every = ((SAMPLE_INTERVAL / dt).round() as usize).max(1);
        runners.push(Runner::new(sim, steps_of(*dt), every)?);
        knobs.push(k);
    }
    let mut done = vec![0usize; runs.len()];
    loop {
        let next = (0..runs.len())
            .filter(|&i| done[i] < steps_of(runs[i].1))
            .min_by(|&a, &b| (done[a] as f64 * runs[a].1).total_cmp(&(done[b] as f64 * runs[b].1)));
        let Some(i) = next else { break };
        runners[i].step()?;
        done[i] += 1;
        bar.inc(1);
    }
    let mut points = Vec::new();
    for (((knob, dt, _), k), r) in runs.into_iter().zip(knobs).zip(&runners) {
        let t = &r.trace;
        // Compare the root-lattice nodes only (refined runs have more).
        let ids = super::beam::live_nodes(&r.sim);
        let keep: Vec<usize> = nodes
            .iter()
            .map(|n| ids.iter().position(|m| m == n).expect("root node survives"))
            .collect();
        let samples: Vec<Vec<_>> = t
            .samples
            .iter()
            .map(|s| keep.iter().map(|&i| s[i]).collect())
            .collect();
        let (max, rms, knob_dev) = if t.non_finite {
            (f64::NAN, f64::NAN, f64::NAN)
        } else {
            let (m, r, _) = deviation(&samples, &reference.samples)?;
            let (kd, _, _) = deviation(&samples, &converged.samples)?;
            (m, r, kd)
        };
        let p50 = t.p50();
        points.push(SweepPoint {
            knob,
            dt,
            options: k,
            tets: t.tets,
            step_ms_p50: p50,
            wall_per_sim_s: p50 * 1e-3 / dt,
            max_dev_m: max,
            rms_dev_m: rms,
            knob_dev_m: knob_dev,
            pareto: false,
        });
    }
    bar.finish_and_clear();
    mark_pareto(&mut points);
    let report = SweepReport {
        scene_hash: scene.hash.clone(),
        reference: "max_dev_m: StVK backward Euler + Newton, dt 1 ms, depth 0; knob_dev_m: \
                    co-rotational with SVD, no sharing, CG 1e-10, dt 1 ms"
            .into(),
        t_end_s: t_end,
        points,
    };
    let dir = out_dir(&args.out, "bench-sweep");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let json = serde_json::to_string_pretty(&report)?;
    std::fs::write(dir.join("sweep.json"), &json)?;
    let all: Vec<(f64, f64)> = report
        .points
        .iter()
        .map(|p| (p.step_ms_p50, p.knob_dev_m.max(1e-9)))
        .collect();
    let mut front: Vec<(f64, f64)> = report
        .points
        .iter()
        .filter(|p| p.pareto)
        .map(|p| (p.step_ms_p50, p.knob_dev_m.max(1e-9)))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let files = write_chart(
        &dir,
        "sweep_pareto",
        &Chart {
            title: "sweep: deviation from converged co-rotational vs step time (coarse soft beam)",
            x_label: "step time p50 (ms)",
            y_label: "max deviation from converged run (m)",
            log_x: true,
            log_y: true,
            scatter: true,
        },
        &[
            Series {
                label: "all runs".into(),
                points: all,
            },
            Series {
                label: "Pareto front".into(),
                points: front,
            },
        ],
    )?;
    if args.json {
        println!("{json}");
    } else {
        println!(
            "sweep: coarse soft cantilever, {t_end} s per run; max node deviation from StVK (dt 1 ms) \
             and from the converged co-rotational run (knob dev); front over (p50, knob dev)"
        );
        println!(
            "{:<18} {:<30} {:>5} {:>6} {:>8} {:>10} {:>10} {:>10} {:>6}",
            "knob",
            "variant",
            "dt ms",
            "tets",
            "p50 ms",
            "max dev m",
            "rms dev m",
            "knob dev m",
            "front"
        );
        for p in &report.points {
            println!(
                "{:<18} {:<30} {:>5} {:>6} {:>8.3} {:>10.3e} {:>10.3e} {:>10.3e} {:>6}",
                p.knob,
                p.options.variant,
                p.dt * 1e3,
                p.tets,
                p.step_ms_p50,
                p.max_dev_m,
                p.rms_dev_m,
                p.knob_dev_m,
                if p.pareto { "*" } else { "" }
            );
        }
        println!("wrote {}", dir.join("sweep.json").display());
        for f in files {
            println!("wrote {}", f.display());
        }
    }
    Ok(())
}

/// A point is on the front when no other point is at least as fast and as accurate and
/// strictly better in one of the two.
fn mark_pareto(points: &mut [SweepPoint]) {
    let v: Vec<(f64, f64)> = points
        .iter()
        .map(|p| (p.step_ms_p50, p.knob_dev_m))
        .collect();
    for (i, p) in points.iter_mut().enumerate() {
        let (t, e) = v[i];
        if !(t.is_finite() && e.is_finite()) {
            continue;
        }
        p.pareto = !v
            .iter()
            .enumerate()
            .any(|(j, &(tj, ej))| j != i && tj <= t && ej <= e && (tj < t || ej < e));
    }
}
