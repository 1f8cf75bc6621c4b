//! `cosurg`: the site client and the project's command line.
//!
//! Exit codes: 0 success, 1 failure, 2 bad usage (clap), 3 refused by the coordinator
//! (the reason is printed).

use clap::Parser;

mod command;

/// Counts heap bytes for the benches' memory columns (off unless a bench measures).
#[global_allocator]
static ALLOC: bench::memory::CountingAlloc = bench::memory::CountingAlloc;

fn main() {
    // Mesa's software OpenGL (llvmpipe) draws on the window thread alone unless the user
    // says otherwise: its default, one worker per core, competed with the simulation for
    // the cores of a small machine (docs/RESULTS.md, "The window": step p99 with the
    // window 3.0 ms against 9.7 ms with the workers, 2.1 ms without a window). Set before
    // any thread exists; the demo's site processes inherit it. No effect on hardware GL.
    if std::env::var_os("LP_NUM_THREADS").is_none() {
        // SAFETY: the first statement of main, before any other thread is started.
        unsafe { std::env::set_var("LP_NUM_THREADS", "0") };
    }
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
