//! The command-line surface of `cosurg`: every sub-command and its dispatch. The product's
//! commands live in the `cosurg` library, the benchmarks in `cosurg-bench`; this crate is the
//! only one that sees both, so neither depends on the other's command line.

use anyhow::Result;
use clap::{Parser, Subcommand};

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
    Demo(cosurg::demo::DemoArgs),
    /// Join a session as one site.
    // A repeated option: the last one wins (scripts and tests append to a base command).
    #[command(args_override_self = true)]
    Join(Box<cosurg::join::JoinArgs>),
    /// Mint an invitation through a running coordinator (instructor token); prints it.
    Invite(cosurg::invite::InviteArgs),
    /// Simulate a scene on this machine alone and write VTU/PVD + OBJ results.
    Run(cosurg::run::RunArgs),
    /// Static equilibrium of a scene under its loads and gravity.
    Solve(cosurg::solve::SolveArgs),
    /// Benchmarks: cantilever, sweep, stress, sync.
    Bench(bench::BenchArgs),
    /// User-space network impairment relay (UDP) between sites and a coordinator.
    Netem(netem::NetemArgs),
    /// Skill scores of one site's acts from a session recording.
    Score(cosurg::score::ScoreArgs),
    /// Play a session recording back (headless: --export-vtu DIR).
    Replay(cosurg::replay::ReplayArgs),
}

pub fn dispatch(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo(a) => cosurg::demo::demo(a),
        Command::Join(a) => cosurg::join::join(*a),
        Command::Invite(a) => cosurg::invite::invite(a),
        Command::Run(a) => cosurg::run::run(a),
        Command::Solve(a) => cosurg::solve::solve(a),
        Command::Bench(a) => bench::run(a),
        Command::Score(a) => cosurg::score::score(a),
        Command::Replay(a) => cosurg::replay::replay(a),
        Command::Netem(a) => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(|e| anyhow::anyhow!("starting the tokio runtime: {e}"))?
            .block_on(netem::run_cli(a)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn solve_model(arg: &str) -> Result<&'static str, clap::Error> {
        let cli = Cli::try_parse_from(["cosurg", "solve", "builtin:cantilever", "--model", arg])?;
        match cli.command {
            Command::Solve(a) => Ok(a.model.name()),
            other => panic!("parsed as {other:?}"),
        }
    }

    #[test]
    fn bench_sync_site_args_split_on_whitespace_and_may_start_with_dashes() {
        let cli = Cli::try_parse_from([
            "cosurg",
            "bench",
            "sync",
            "--site-args",
            "--adaptivity false",
        ])
        .unwrap();
        let Command::Bench(bench::BenchArgs {
            which: bench::BenchCommand::Sync(a),
        }) = cli.command
        else {
            panic!("parsed as {:?}", cli.command);
        };
        assert_eq!(a.site_args, ["--adaptivity", "false"]);
    }

    #[test]
    fn model_names_are_the_scene_files_and_nonlinear_is_an_alias() {
        for name in ["linear", "corotational", "stvk"] {
            assert_eq!(solve_model(name).unwrap(), name);
        }
        assert_eq!(solve_model("nonlinear").unwrap(), "stvk");
        let err = solve_model("fancy").unwrap_err().to_string();
        assert!(
            err.contains("[possible values: linear, corotational, stvk]"),
            "{err}"
        );
    }
}
