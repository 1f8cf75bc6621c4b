//! The command-line surface of `cosurg`.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Parser, Subcommand, ValueEnum};
use sim_core::SimOptions;
use sim_core::sim_fem::Model;

/// cosurg: multi-site surgical training on one shared soft-tissue simulation.
#[derive(Debug, Parser)]
#[command(name = "cosurg", version, about, long_about = None)]
pub struct Cli {
    /// More logging (-v info, -vv debug, -vvv trace); COSURG_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// The multi-site demo: a coordinator and N sites on loopback over QUIC/TLS.
    Demo(crate::demo::DemoArgs),
    /// Join a session as one site.
    Join(Box<crate::join::JoinArgs>),
    /// Mint an invitation through a running coordinator (instructor token); prints it.
    Invite(crate::invite::InviteArgs),
    /// Simulate a scene on this machine alone and write VTU/PVD + OBJ results.
    Run(crate::run::RunArgs),
    /// Static equilibrium of a scene under its loads and gravity.
    Solve(crate::solve::SolveArgs),
    /// Benchmarks: cantilever, sweep, stress, sync.
    Bench(crate::bench::BenchArgs),
    /// User-space network impairment relay (UDP) between sites and a coordinator.
    Netem(netem::NetemArgs),
}

/// Deformation models on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ModelArg {
    /// Co-rotational linear FEM (the product's model).
    Corotational,
    /// Plain linear FEM (reference).
    Linear,
    /// St Venant–Kirchhoff with Newton (non-linear reference).
    Nonlinear,
}

impl ModelArg {
    pub fn fem(self) -> Model {
        match self {
            ModelArg::Corotational => Model::Corotational,
            ModelArg::Linear => Model::Linear,
            ModelArg::Nonlinear => Model::StVK,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ModelArg::Corotational => "corotational",
            ModelArg::Linear => "linear",
            ModelArg::Nonlinear => "nonlinear",
        }
    }
}

/// Solver knobs shared by the simulation commands; unset ones come from the scene.
#[derive(Debug, Clone, Args, Default)]
pub struct SimKnobs {
    /// Deformation model.
    #[arg(long, value_enum)]
    pub model: Option<ModelArg>,
    /// Time step (s).
    #[arg(long)]
    pub dt: Option<f64>,
    /// CG iteration budget per step.
    #[arg(long)]
    pub cg_iterations: Option<usize>,
    /// Rotation-sharing angle tolerance θ_tol (degrees); 0 disables sharing.
    #[arg(long)]
    pub sharing_angle: Option<f64>,
    /// Switch the scene's tool-following refinement on or off.
    #[arg(long)]
    pub adaptivity: Option<bool>,
    /// Threads of the FEM step (default 1: the step stays on the simulation thread).
    #[arg(long)]
    pub threads: Option<usize>,
}

impl SimKnobs {
    pub fn apply(&self, o: &mut SimOptions) {
        if let Some(m) = self.model {
            o.model = m.fem();
        }
        if let Some(dt) = self.dt {
            o.dt = dt;
        }
        if let Some(n) = self.cg_iterations {
            o.solver.max_iters = n;
        }
        if let Some(a) = self.adaptivity {
            o.adaptivity = a;
        }
        if let Some(a) = self.sharing_angle {
            o.sharing_angle_deg = (a > 0.0).then_some(a);
        }
        if let Some(t) = self.threads {
            o.threads = t.max(1);
        }
    }
}

/// Where a command writes its files: `--out DIR`, else `out/<command>-<timestamp>`.
pub fn out_dir(arg: &Option<PathBuf>, command: &str) -> PathBuf {
    arg.clone().unwrap_or_else(|| {
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        PathBuf::from("out").join(format!("{command}-{stamp}"))
    })
}

/// Marker error: the coordinator refused us (exit code 3).
#[derive(Debug, thiserror::Error)]
#[error("refused by the coordinator: {0}")]
pub struct Refused(pub String);

pub fn exit_code(e: &anyhow::Error) -> i32 {
    if e.downcast_ref::<Refused>().is_some() {
        3
    } else {
        1
    }
}

pub fn dispatch(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo(a) => crate::demo::demo(a),
        Command::Join(a) => crate::join::join(*a),
        Command::Invite(a) => crate::invite::invite(a),
        Command::Run(a) => crate::run::run(a),
        Command::Solve(a) => crate::solve::solve(a),
        Command::Bench(a) => crate::bench::run(a),
        Command::Netem(a) => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(|e| anyhow::anyhow!("starting the tokio runtime: {e}"))?
            .block_on(netem::run_cli(a)),
    }
}
