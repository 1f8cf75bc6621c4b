//! `cosurg bench …`: the benchmarks that back the project's published numbers.

use anyhow::Result;
use clap::{Args, Subcommand};

mod beam;
pub mod cantilever;
pub mod coordinator;
pub mod memory;
pub mod scale;
pub mod stress;
pub mod sweep;
pub mod sync;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub which: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Models and speed-ups on the cantilever beam: step time and deviation from StVK.
    Cantilever(cantilever::CantileverArgs),
    /// Linear solvers against mesh size: Jacobi-PCG vs MG-PCG to a 1e-6 residual.
    Scale(scale::ScaleArgs),
    /// Robustness: long runs, large dt, 1000× stiffness contrast, inversion, impulses.
    Stress(stress::StressArgs),
    /// Run time against error over the solver knobs; Pareto front.
    Sweep(sweep::SweepArgs),
    /// Multi-site sync quality: strategy × network preset, over real QUIC.
    Sync(sync::SyncArgs),
    /// Coordinator load: synthetic sites over real QUIC against one coordinator process,
    /// sessions × sites until it breaks; relay latency, CPU, memory, drops.
    Coordinator(coordinator::CoordinatorArgs),
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.which {
        BenchCommand::Cantilever(a) => cantilever::run(a),
        BenchCommand::Scale(a) => scale::run(a),
        BenchCommand::Stress(a) => stress::run(a),
        BenchCommand::Sweep(a) => sweep::run(a),
        BenchCommand::Sync(a) => sync::run(a),
        BenchCommand::Coordinator(a) => coordinator::run(a),
    }
}
