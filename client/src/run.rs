//! `cosurg run`: one site, no network. With a display it opens the window and the user's
//! mouse and keyboard drive the local tool (`run_window`); `--headless` (or no display)
//! simulates a scene for a number of simulated seconds and writes the lattice, surfaces
//! and tools as a VTU/PVD series plus OBJ; `--screenshot` renders one picture.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use sim_core::{Interaction, SimOptions, Simulation};

use crate::cli::{SimKnobs, out_dir};
use crate::output::{SeriesWriter, ToolFrame};
use crate::scene_arg::load_scene_with_cell;
use crate::stats::percentile;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Scene file (TOML) or builtin:NAME; default: the built-in cholecystectomy-bodies scene.
    pub scene: Option<String>,
    /// Simulated time (s): headless and `--bench-window` runs (default 2), the screenshot's
    /// default `--at`; with a window, stop after it (default: when the window closes).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Output folder (default out/run-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Simulated time between written frames (s).
    #[arg(long, default_value_t = 0.05)]
    pub frame_interval: f64,
    /// Do not drive the scene's tools by their scripts (headless runs).
    #[arg(long)]
    pub no_tools: bool,
    /// No window: simulate `--seconds`, tools scripted, write VTU/PVD + OBJ (also the
    /// behaviour when no display is available).
    #[arg(long)]
    pub headless: bool,
    /// With a window or `--screenshot`: the scene's scripts drive the tools (teaching
    /// replay) instead of the mouse and keyboard.
    #[arg(long)]
    pub script: bool,
    /// Render one picture (PNG) at `--at` seconds and exit; needs a display (Xvfb will do).
    #[arg(long, value_name = "FILE.png")]
    pub screenshot: Option<PathBuf>,
    /// Simulated time of the screenshot (s; default: `--seconds`).
    #[arg(long, requires = "screenshot")]
    pub at: Option<f64>,
    /// Window or screenshot size in pixels.
    #[arg(long, default_value = "1280x720", value_parser = crate::run_window::parse_size)]
    pub size: (u32, u32),
    /// Draw the lattice wireframe in the screenshot (coloured by refinement level).
    #[arg(long, requires = "screenshot")]
    pub lattice: bool,
    /// Measure the window: run the real-time loop for `--seconds` with the window (or,
    /// with `--no-window`, the same loop without it), waiting for every frame to be
    /// rendered, then print step and frame statistics as JSON.
    #[arg(long, conflicts_with_all = ["headless", "screenshot"])]
    pub bench_window: bool,
    /// With `--bench-window`: the same loop without a window, for comparison.
    #[arg(long, requires = "bench_window")]
    pub no_window: bool,
    /// With a window (or `--bench-window`): write the run's statistics to this file at the
    /// end, with the local site at the start and end and every command of the hands.
    #[arg(long, conflicts_with_all = ["headless", "screenshot"])]
    pub stats_json: Option<PathBuf>,
    /// Lattice cell size (m) of every body, instead of the scene's (a finer organ).
    #[arg(long, value_name = "M", long_help = crate::scene_arg::CELL_HELP)]
    pub cell: Option<f64>,
    #[command(flatten)]
    pub knobs: SimKnobs,
}

/// Simulated time of a run without a window when `--seconds` is not given (s).
const DEFAULT_SECONDS: f64 = 2.0;

pub fn run(args: RunArgs) -> Result<()> {
    let seconds = args.seconds.unwrap_or(DEFAULT_SECONDS);
    let scene = load_scene_with_cell(args.scene.as_deref(), args.cell)?;
    let label = scene.file.clone();
    let hash = scene.hash.clone();
    let mut options = SimOptions::from_scene(&scene.scene);
    args.knobs.apply(&mut options);
    if let Some(path) = &args.screenshot {
        let at = args.at.unwrap_or(seconds);
        if !(at.is_finite() && at >= 0.0) {
            anyhow::bail!(
                "--at {at}: the screenshot time must be a non-negative number of seconds"
            );
        }
        return crate::run_window::run_screenshot(
            scene,
            options,
            args.script,
            at,
            args.size,
            args.lattice,
            path,
        );
    }
    if args.bench_window {
        if !args.no_window && !crate::run_window::display_available() {
            anyhow::bail!("--bench-window needs a display (DISPLAY is not set); Xvfb will do");
        }
        let stats = crate::run_window::run_with_window(
            scene,
            options,
            &crate::run_window::WindowRun {
                scripted: args.script,
                size: args.size,
                seconds: Some(seconds),
                window: !args.no_window,
                finish_frames: true,
            },
        )?;
        let json = serde_json::to_string_pretty(&stats)?;
        if let Some(p) = &args.stats_json {
            std::fs::write(p, &json)?;
        }
        println!("{json}");
        return Ok(());
    }
    if !args.headless {
        if crate::run_window::display_available() {
            let stats = crate::run_window::run_with_window(
                scene,
                options,
                &crate::run_window::WindowRun {
                    scripted: args.script,
                    size: args.size,
                    seconds: args.seconds,
                    window: true,
                    finish_frames: false,
                },
            )?;
            if let Some(p) = &args.stats_json {
                std::fs::write(p, serde_json::to_string_pretty(&stats)?)
                    .with_context(|| format!("writing {}", p.display()))?;
            }
            println!(
                "simulated {:.3} s in {} steps: step p50 {:.3} ms, p99 {:.3} ms; {} frames, {:.1} fps",
                stats.sim_seconds,
                stats.steps,
                stats.step_ms_p50,
                stats.step_ms_p99,
                stats.frames,
                stats.fps
            );
            return Ok(());
        }
        eprintln!("no display (DISPLAY is not set): running headless");
    }
    let dt = options.dt;
    let mut sim = Simulation::new(scene, options)?;
    let dir = out_dir(&args.out, "run");
    let mut writer = SeriesWriter::new(&dir)?;
    eprintln!(
        "scene {label} (sha256 {hash}): {} leaf tets, {} nodes, dt {} s",
        sim.lattice().leaf_count(),
        sim.lattice().node_count(),
        dt
    );
    let steps = (seconds / dt).round() as u64;
    let frame_every = ((args.frame_interval / dt).round() as u64).max(1);
    let bar = ProgressBar::new(steps).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} steps  {msg}").expect("static template"),
    );
    let mut interaction = Interaction::new(&sim);
    let frames = |i: &Interaction| -> Vec<ToolFrame> {
        i.tools
            .tools
            .iter()
            .zip(&i.state().tools)
            .map(|(t, c)| ToolFrame {
                name: t.name.clone(),
                position: t.pose().translation.vector,
                orientation: t.pose().rotation,
                jaw: t.jaw(),
                force: -c.force,
            })
            .collect()
    };
    writer.write_frame(&sim, &frames(&interaction), None)?;
    let mut step_ms = Vec::with_capacity(steps as usize);
    // The largest force on any tool, which tool and when: a spike points at the script's
    // moment where contact misbehaves.
    let mut max_force: (f64, usize, f64) = (0.0, 0, 0.0);
    // Steps and CG iterations per linear solver (`auto` may move from one to another).
    let mut solves: std::collections::BTreeMap<&'static str, (u64, usize)> = Default::default();
    for k in 1..=steps {
        // The time of this step's tool pass (its forces are reported below, after the step).
        let pass_time = sim.time();
        let t0 = Instant::now();
        if !args.no_tools {
            let inputs = interaction.scripted_inputs(&sim, sim.time());
            interaction.before_step(&mut sim, &inputs)?;
        }
        let report = sim.step()?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        step_ms.push(ms);
        if ms > sim.options().dt * 1e3 {
            tracing::debug!(
                t = sim.time(),
                ms,
                rebuilt = report.rebuilt,
                cg_iterations = report.fem.cg_iterations,
                newton_iterations = report.fem.newton_iterations,
                fallback = report.fem.fallback,
                inverted = report.fem.inverted,
                "step longer than its simulated time"
            );
        }
        let entry = solves.entry(report.fem.solver.name()).or_default();
        entry.0 += 1;
        entry.1 += report.fem.cg_iterations;
        for (i, c) in interaction.state().tools.iter().enumerate() {
            if c.force.norm() > max_force.0 {
                max_force = (c.force.norm(), i, pass_time);
            }
        }
        if k % frame_every == 0 {
            writer.write_frame(
                &sim,
                &frames(&interaction),
                Some(&interaction.state().node_force),
            )?;
        }
        if k % 50 == 0 {
            bar.set_position(k);
            bar.set_message(format!("t = {:.3} s", sim.time()));
        }
    }
    bar.finish_and_clear();
    let objs = writer.write_obj(&sim)?;
    // The longest step too: a refinement that overruns the step by tens of milliseconds
    // (as new tets' materials once did) is a hitch the user feels, yet invisible in p99.
    println!(
        "simulated {:.3} s in {} steps: step p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms",
        sim.time(),
        steps,
        percentile(&step_ms, 50.0),
        percentile(&step_ms, 99.0),
        percentile(&step_ms, 100.0)
    );
    for (solver, (n, iterations)) in &solves {
        println!(
            "linear solver {solver}: {n} steps, CG iterations mean {:.1}",
            *iterations as f64 / *n as f64
        );
    }
    match interaction.tools.tools.get(max_force.1) {
        Some(tool) if max_force.0 > 0.0 => println!(
            "largest tool force {:.3} N ({} at t = {:.3} s)",
            max_force.0, tool.name, max_force.2
        ),
        _ => println!("largest tool force 0.000 N"),
    }
    for (name, p) in sim.probes() {
        println!("probe {name}: [{:.6}, {:.6}, {:.6}] m", p.x, p.y, p.z);
    }
    println!(
        "wrote {} (open series.pvd in ParaView) and {} OBJ file(s)",
        dir.display(),
        objs.len()
    );
    Ok(())
}
