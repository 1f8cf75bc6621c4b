//! `cosurg solve`: static equilibrium of a scene with a chosen model.

use std::time::Instant;

use anyhow::{Result, bail};
use clap::Args;
use serde::Serialize;
use sim_core::sim_fem::{Model, StaticParams};
use sim_core::{SimOptions, Simulation};

use crate::cli::model_parser;
use crate::scene_arg::load_scene;

#[derive(Debug, Args)]
pub struct SolveArgs {
    /// Scene file (TOML) or builtin:NAME.
    pub scene: String,
    /// Deformation model.
    #[arg(long, value_parser = model_parser(), default_value = "corotational")]
    pub model: Model,
    /// Static equilibrium (the only mode of this command; accepted for clarity).
    #[arg(long)]
    pub r#static: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Override the cell size of every body (m).
    #[arg(long)]
    pub cell: Option<f64>,
    /// Override Young's modulus of every material (Pa).
    #[arg(long)]
    pub young: Option<f64>,
}

#[derive(Debug, Serialize)]
pub struct ProbeResult {
    pub name: String,
    pub position: [f64; 3],
    pub displacement: [f64; 3],
}

#[derive(Debug, Serialize)]
pub struct SolveResult {
    pub scene_hash: String,
    pub model: String,
    pub probes: Vec<ProbeResult>,
    pub iterations: usize,
    pub residual: f64,
    pub converged: bool,
    pub time_s: f64,
}

pub fn solve(args: SolveArgs) -> Result<()> {
    let mut scene = load_scene(Some(&args.scene))?;
    if let Some(c) = args.cell {
        scene.scene.bodies.iter_mut().for_each(|b| b.cell = c);
    }
    if let Some(e) = args.young {
        scene.scene.materials.values_mut().for_each(|m| m.young = e);
    }
    let result = solve_scene(scene, args.model)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&result)?);
    } else {
        println!(
            "scene {}  model {}  Newton iterations {}  residual {:.3e} N  {:.3} s",
            result.scene_hash, result.model, result.iterations, result.residual, result.time_s
        );
        for p in &result.probes {
            println!(
                "  probe {:<12} position [{:.6}, {:.6}, {:.6}] m  displacement [{:.6}, {:.6}, {:.6}] m",
                p.name,
                p.position[0],
                p.position[1],
                p.position[2],
                p.displacement[0],
                p.displacement[1],
                p.displacement[2]
            );
        }
    }
    if !result.converged {
        bail!(
            "static solve did not converge (residual {:.3e} N)",
            result.residual
        );
    }
    Ok(())
}

/// Static solve of a loaded scene; shared with the benches.
pub fn solve_scene(scene: sim_core::sim_scene::LoadedScene, model: Model) -> Result<SolveResult> {
    let hash = scene.hash.clone();
    let mut options = SimOptions::from_scene(&scene.scene);
    options.step.model = model;
    let gravity = options.step.gravity;
    let mut sim = Simulation::new(scene, options)?;
    let rest = sim.probe_rest();
    let start = Instant::now();
    let stats = sim.solve_static(
        model,
        &StaticParams {
            gravity,
            initial_increment: 0.25,
            ..StaticParams::default()
        },
    )?;
    let time_s = start.elapsed().as_secs_f64();
    let probes = sim
        .probes()
        .into_iter()
        .zip(rest)
        .map(|((name, p), r)| ProbeResult {
            name,
            position: [p.x, p.y, p.z],
            displacement: [p.x - r.x, p.y - r.y, p.z - r.z],
        })
        .collect();
    Ok(SolveResult {
        scene_hash: hash,
        model: model.name().to_string(),
        probes,
        iterations: stats.iterations,
        residual: stats.residual,
        converged: stats.converged,
        time_s,
    })
}
