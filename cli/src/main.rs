//! `cosurg`: the site client and the project's command line.
//!
//! Exit codes: 0 success, 1 failure, 2 bad usage (clap), 3 refused by the coordinator
//! (the reason is printed).

use clap::Parser;

mod command;

fn main() {
    let cli = command::Cli::parse();
    init_tracing(cli.verbose);
    let code = match command::dispatch(cli) {
        Ok(()) => 0,
        Err(e) => {
            let code = cosurg::cli::exit_code(&e);
            eprintln!("error: {e:#}");
            code
        }
    };
    std::process::exit(code);
}

fn init_tracing(verbose: u8) {
    use tracing_subscriber::EnvFilter;
    let default = match verbose {
        0 => "warn,cosurg::=info",
        1 => "info",
        2 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_env("COSURG_LOG").unwrap_or_else(|_| EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}
