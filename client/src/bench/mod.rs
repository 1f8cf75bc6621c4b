//! `cosurg bench …`: the benchmarks that back the project's published numbers.

use anyhow::Result;
use clap::{Args, Subcommand};

mod beam;
pub mod cantilever;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub which: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Models and speed-ups on the cantilever beam: step time and deviation from StVK.
    Cantilever(cantilever::CantileverArgs),
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.which {
        BenchCommand::Cantilever(a) => cantilever::run(a),
    }
}
