//! `cosurg-server` command line.
//!
//! ```text
//! cosurg-server --listen 0.0.0.0:4433 --session lap-chole --token s3cret \
//!     [--cert cert.pem --key key.pem] [--scene-hash HEX] [--state-dir DIR] \
//!     [--max-sites N] [--status-interval S] [--seconds S]
//! ```
//! Without `--cert/--key` a self-signed certificate is created in the state directory on
//! first start and reused afterwards (default state directory: `$XDG_DATA_HOME/cosurg`, else
//! `~/.local/share/cosurg`, else `./.cosurg`). The certificate's SHA-256 fingerprint is
//! printed on standard output (`fingerprint: AB:CD:…`) for sites to pin.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;

use crate::coordinator::{Coordinator, CoordinatorConfig};
use crate::tls::{self, Identity};

/// The cosurg coordinator: relays simulation clocks and state between sites over QUIC.
#[derive(Debug, Parser)]
#[command(name = "cosurg-server", version)]
pub struct Args {
    /// UDP address to listen on.
    #[arg(long, default_value = "0.0.0.0:4433")]
    pub listen: SocketAddr,
    /// Session name sites must give.
    #[arg(long)]
    pub session: String,
    /// Session token (shared secret). Also read from $COSURG_TOKEN.
    #[arg(long, env = "COSURG_TOKEN", hide_env_values = true)]
    pub token: String,
    /// Certificate chain (PEM). Requires --key.
    #[arg(long, requires = "key")]
    pub cert: Option<PathBuf>,
    /// Private key (PEM). Requires --cert.
    #[arg(long, requires = "cert")]
    pub key: Option<PathBuf>,
    /// Required scene hash (hex SHA-256). Default: the first site to join fixes it.
    #[arg(long)]
    pub scene_hash: Option<String>,
    /// Directory for the persisted self-signed certificate.
    #[arg(long)]
    pub state_dir: Option<PathBuf>,
    /// Maximum number of sites (all roles).
    #[arg(long, default_value_t = 16)]
    pub max_sites: u16,
    /// Seconds between status lines (0: off).
    #[arg(long, default_value_t = 5.0)]
    pub status_interval: f64,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// Run the coordinator with the given arguments until Ctrl-C or `--seconds`.
pub async fn run(args: Args) -> anyhow::Result<()> {
    let identity = match (&args.cert, &args.key) {
        (Some(c), Some(k)) => Identity::load(c, k).context("loading --cert/--key")?,
        _ => {
            let dir = args
                .state_dir
                .clone()
                .unwrap_or_else(tls::default_state_dir);
            let (id, created) = Identity::load_or_create(&dir)
                .with_context(|| format!("certificate in state dir {}", dir.display()))?;
            if created {
                println!(
                    "created self-signed certificate {}",
                    dir.join(tls::CERT_FILE).display()
                );
            } else {
                println!("using certificate {}", dir.join(tls::CERT_FILE).display());
            }
            id
        }
    };
    let mut session = proto::SessionConfig::new(args.session.clone(), args.token.clone());
    session.scene_hash = args.scene_hash.as_ref().map(|h| h.to_ascii_lowercase());
    session.max_sites = args.max_sites;
    let mut config = CoordinatorConfig::new(session, identity);
    config.listen = args.listen;
    config.status_interval =
        (args.status_interval > 0.0).then(|| Duration::from_secs_f64(args.status_interval));
    let (handle, addr) = Coordinator::bind(config)?;
    println!("listening: {addr}");
    println!("fingerprint: {}", handle.fingerprint());
    println!("session: {}", args.session);
    let stop = async {
        match args.seconds {
            Some(s) => tokio::time::sleep(Duration::from_secs_f64(s.max(0.0))).await,
            None => std::future::pending::<()>().await,
        }
    };
    tokio::select! {
        _ = stop => {}
        r = tokio::signal::ctrl_c() => { r.context("waiting for Ctrl-C")?; }
    }
    let stats = handle.stats();
    handle.shutdown().await;
    println!("stopped: {stats:?}");
    Ok(())
}

/// Entry point of the `cosurg-server` binary: parse arguments, set up logging
/// (`RUST_LOG`, default `info`), run.
pub fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    rt.block_on(run(args))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_runs_briefly_with_a_persisted_certificate() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().to_str().unwrap();
        let args = Args::try_parse_from([
            "cosurg-server",
            "--listen",
            "127.0.0.1:0",
            "--session",
            "s",
            "--token",
            "t",
            "--state-dir",
            state,
            "--seconds",
            "0.2",
            "--status-interval",
            "0.05",
            "--scene-hash",
            "ABCD",
            "--max-sites",
            "3",
        ])
        .unwrap();
        assert_eq!(args.max_sites, 3);
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(run(args)).unwrap();
        assert!(dir.path().join(tls::CERT_FILE).exists());
        assert!(dir.path().join(tls::KEY_FILE).exists());
        // --cert without --key is rejected
        assert!(
            Args::try_parse_from([
                "cosurg-server",
                "--session",
                "s",
                "--token",
                "t",
                "--cert",
                "c.pem"
            ])
            .is_err()
        );
    }
}
