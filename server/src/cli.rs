//! `cosurg-server` command line.
//!
//! ```text
//! cosurg-server --listen 0.0.0.0:4433 --session lap-chole --token s3cret \
//!     [--cert cert.pem --key key.pem] [--scene-hash HEX] [--state-dir DIR] \
//!     [--max-sites N] [--status-interval S] [--seconds S] [--record DIR]
//! cosurg-server --sessions sessions.toml [--admin-token SECRET] [--metrics 127.0.0.1:9464] \
//!     [--log-json] [--record DIR] …
//! cosurg-server invite --role trainee|observer [--site NAME] [--expires DURATION] \
//!     [--session NAME] [--state-dir DIR]
//! cosurg-server revoke INVITATION|NONCE [--state-dir DIR]
//! cosurg-server create-session --coordinator HOST:PORT --pin FP --admin-token SECRET \
//!     --session NAME --token INSTRUCTOR-SECRET [--scene-hash HEX] [--max-sites N]
//! ```
//! **Many sessions.** One process may host several sessions, each isolated from the others:
//! from a sessions file (`--sessions FILE.toml`, format in [`crate::sessions`]), created at
//! run time by the operator (`create-session`, allowed by the coordinator's `--admin-token`),
//! and resumed from the state directory, where both kinds are persisted
//! (`sessions.toml`). The single-session command line (`--session --token`) works as before;
//! its session is not persisted (the command line gives it again).
//! The token is the instructor's secret and admits the instructor role only; trainees and
//! observers join with invitations signed by the key in the state directory (default:
//! `$XDG_DATA_HOME/cosurg`, else `~/.local/share/cosurg`, else `./.cosurg`), which also holds
//! the self-signed certificate (created on first start when no `--cert/--key` is given, so
//! the fingerprint survives restarts) and the revocation list (see [`crate::state`]). The
//! certificate's SHA-256 fingerprint is printed on standard output (`fingerprint: AB:CD:…`)
//! for sites to pin.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};
use proto::Role;

use crate::coordinator::{Coordinator, CoordinatorConfig};
use crate::sessions::{SessionSpec, SessionsFile};
use crate::state::StateDir;
use crate::tls::{self, Identity};

/// The cosurg coordinator: relays simulation clocks and state between sites over QUIC.
/// Without a subcommand it serves a session.
#[derive(Debug, Parser)]
#[command(
    name = "cosurg-server",
    version,
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Option<Sub>,
    #[command(flatten)]
    pub serve: Args,
}

/// Subcommands working on the state directory (run them on the coordinator's host).
#[derive(Debug, Subcommand)]
pub enum Sub {
    /// Mint an invitation for a trainee or observer; prints it as one line.
    Invite(InviteArgs),
    /// Revoke an invitation (also takes effect on a running coordinator within a second).
    Revoke(RevokeArgs),
    /// Create a session on a running coordinator (needs its --admin-token); the session is
    /// persisted in the coordinator's state directory.
    CreateSession(CreateSessionArgs),
}

/// `cosurg-server create-session`.
#[derive(Debug, clap::Args)]
pub struct CreateSessionArgs {
    /// The coordinator, HOST:PORT.
    #[arg(long)]
    pub coordinator: String,
    /// Name of the new session.
    #[arg(long)]
    pub session: String,
    /// The new session's instructor token.
    #[arg(long)]
    pub token: String,
    /// The coordinator's admin token (or COSURG_ADMIN_TOKEN).
    #[arg(long, env = "COSURG_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: String,
    /// Required scene hash (hex SHA-256). Default: the first site to join fixes it.
    #[arg(long)]
    pub scene_hash: Option<String>,
    /// Maximum number of sites (default: the coordinator's).
    #[arg(long, default_value_t = 0)]
    pub max_sites: u16,
    /// SHA-256 fingerprint of the coordinator's certificate.
    #[arg(long, conflicts_with = "ca")]
    pub pin: Option<String>,
    /// CA certificate (PEM) that signed the coordinator's certificate.
    #[arg(long)]
    pub ca: Option<PathBuf>,
    /// TLS server name to check with --ca.
    #[arg(long, default_value = "localhost")]
    pub server_name: String,
}

/// `cosurg-server invite`.
#[derive(Debug, clap::Args)]
pub struct InviteArgs {
    /// Role the invitation admits: trainee or observer.
    #[arg(long, value_parser = parse_invite_role)]
    pub role: Role,
    /// Admit only a site of this name.
    #[arg(long)]
    pub site: Option<String>,
    /// Lifetime, e.g. 90m, 12h, 7d.
    #[arg(long, default_value = "24h", value_parser = humantime::parse_duration)]
    pub expires: Duration,
    /// Session the invitation is for (default: the session the coordinator with this state
    /// directory serves or last served).
    #[arg(long)]
    pub session: Option<String>,
    /// State directory holding the invitation key.
    #[arg(long)]
    pub state_dir: Option<PathBuf>,
}

/// `cosurg-server create-session`: ask a running coordinator to host a new session.
pub fn create_session(a: CreateSessionArgs) -> anyhow::Result<()> {
    let client_config = match (&a.pin, &a.ca) {
        (Some(p), _) => tls::client_config_pinned(p)?,
        (None, Some(ca)) => {
            let pem = std::fs::read(ca).with_context(|| format!("CA file {}", ca.display()))?;
            tls::client_config_ca(&pem)?
        }
        (None, None) => {
            anyhow::bail!("give --pin FINGERPRINT (printed by cosurg-server) or --ca PEM")
        }
    };
    let request = crate::admin::SessionRequest {
        session: a.session.clone(),
        admin_token: a.admin_token.clone(),
        instructor_token: a.token.clone(),
        scene_hash: a.scene_hash.clone(),
        max_sites: a.max_sites,
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    let info = rt.block_on(async {
        let addr = tokio::net::lookup_host(&a.coordinator)
            .await
            .with_context(|| format!("resolving {}", a.coordinator))?
            .next()
            .with_context(|| format!("{} resolves to no address", a.coordinator))?;
        let bind = if addr.is_ipv6() {
            SocketAddr::from((std::net::Ipv6Addr::UNSPECIFIED, 0))
        } else {
            SocketAddr::from(([0, 0, 0, 0], 0))
        };
        let mut endpoint = quinn::Endpoint::client(bind).context("opening a UDP socket")?;
        endpoint.set_default_client_config(client_config);
        let r = crate::admin::create_session_remote(&endpoint, addr, &a.server_name, &request)
            .await
            .with_context(|| format!("asking {addr}"));
        endpoint.wait_idle().await;
        r
    })?;
    println!(
        "session {:?} created (max {} sites{})",
        info.name,
        info.max_sites,
        if info.scene_hash.is_empty() {
            String::new()
        } else {
            format!(", scene {}", info.scene_hash)
        }
    );
    Ok(())
}

/// `cosurg-server revoke`.
#[derive(Debug, clap::Args)]
pub struct RevokeArgs {
    /// The invitation (csi1.…) or its nonce (32 hex digits, printed when it was minted).
    pub invitation: String,
    /// State directory holding the revocation list.
    #[arg(long)]
    pub state_dir: Option<PathBuf>,
}

/// Role of an invitation: trainee or observer.
pub fn parse_invite_role(s: &str) -> Result<Role, String> {
    match s.parse::<Role>()? {
        Role::Instructor => Err(
            "the instructor joins with the session token; invitations are for trainee or observer"
                .into(),
        ),
        r => Ok(r),
    }
}

/// Serving a session.
#[derive(Debug, Parser)]
#[command(name = "cosurg-server", version)]
pub struct Args {
    /// UDP address to listen on.
    #[arg(long, default_value = "0.0.0.0:4433")]
    pub listen: SocketAddr,
    /// Session name sites must give (one session; see also --sessions).
    #[arg(long)]
    pub session: Option<String>,
    /// The instructor's secret of --session: admits the instructor role only (trainees and
    /// observers join with invitations). Also read from $COSURG_TOKEN.
    #[arg(long, env = "COSURG_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Host the sessions of this TOML file (name, token, scene_hash, max_sites per
    /// [[session]]); they are persisted in the state directory and resumed on restart.
    #[arg(long)]
    pub sessions: Option<PathBuf>,
    /// Operator secret that allows creating sessions at run time (`cosurg-server
    /// create-session`). Also read from $COSURG_ADMIN_TOKEN. Default: no run-time creation.
    #[arg(long, env = "COSURG_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: Option<String>,
    /// Maximum number of sessions hosted.
    #[arg(long, default_value_t = 256)]
    pub max_sessions: usize,
    /// Datagrams per second one site may have relayed (tool poses, stamps, deltas; a
    /// normal site sends under 200/s); beyond it, with a burst allowance of half a second,
    /// its datagrams are dropped and counted (metric `cosurg_session_over_budget_total`),
    /// so that one site cannot take the coordinator's CPU from the other sessions.
    #[arg(long, default_value_t = 1000.0, value_name = "PER_SECOND")]
    pub relay_rate: f64,
    /// Serve Prometheus metrics at http://ADDR/metrics (no authentication: use a loopback
    /// or private address).
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<SocketAddr>,
    /// Log as JSON lines (tracing's JSON format) instead of text.
    #[arg(long)]
    pub log_json: bool,
    /// Certificate chain (PEM). Requires --key.
    #[arg(long, requires = "key")]
    pub cert: Option<PathBuf>,
    /// Private key (PEM). Requires --cert.
    #[arg(long, requires = "cert")]
    pub key: Option<PathBuf>,
    /// Required scene hash (hex SHA-256). Default: the first site to join fixes it.
    #[arg(long)]
    pub scene_hash: Option<String>,
    /// State directory: self-signed certificate, invitation key, revocation list.
    #[arg(long)]
    pub state_dir: Option<PathBuf>,
    /// Maximum number of sites of --session (all roles).
    #[arg(long, default_value_t = crate::sessions::DEFAULT_MAX_SITES)]
    pub max_sites: u16,
    /// Seconds between status lines (0: off).
    #[arg(long, default_value_t = 5.0)]
    pub status_interval: f64,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Record the session (joins, leaves, claims, resets, teaching, every site's tool
    /// poses, keyframe metadata) into DIR/<session>.cosrec, in the debrief format
    /// (`cosurg score`, `cosurg replay`).
    #[arg(long, value_name = "DIR")]
    pub record: Option<PathBuf>,
    /// Run the session's clock this many times slower than real time (time-dilated
    /// measurement on a machine too slow for its sites; every site joins with the same
    /// `--time-scale`)
    #[arg(long, default_value = "1", value_name = "FACTOR")]
    pub time_scale: crate::TimeScale,
}

/// Run the coordinator with the given arguments until Ctrl-C or `--seconds`.
pub async fn run(args: Args) -> anyhow::Result<()> {
    let dir = args
        .state_dir
        .clone()
        .unwrap_or_else(tls::default_state_dir);
    let state = StateDir::new(&dir);
    // The sessions: persisted ones, replaced by those of --sessions, then --session.
    let mut hosted =
        SessionsFile::load_persisted(&dir).context("sessions of the state directory")?;
    if let Some(path) = &args.sessions {
        let file = SessionsFile::load(path)?;
        SessionsFile::persist(&dir, file.sessions.clone())
            .context("persisting the sessions in the state directory")?;
        hosted.upsert(file.sessions);
    }
    let single = match (&args.session, &args.token) {
        (Some(name), Some(token)) => {
            let spec = SessionSpec {
                name: name.clone(),
                token: token.clone(),
                scene_hash: args.scene_hash.clone(),
                max_sites: args.max_sites,
            };
            crate::sessions::check_spec(&spec)
                .map_err(|e| anyhow::anyhow!("--session {name:?}: {e}"))?;
            Some(spec)
        }
        (Some(_), None) => anyhow::bail!("--session needs --token (or $COSURG_TOKEN)"),
        (None, Some(_)) if args.sessions.is_none() => {
            anyhow::bail!("--token needs --session")
        }
        _ => None,
    };
    if let Some(spec) = &single {
        hosted.sessions.retain(|s| s.name != spec.name);
        hosted.sessions.insert(0, spec.clone());
    }
    if hosted.sessions.is_empty() {
        anyhow::bail!(
            "no session to serve: give --session NAME --token SECRET, or --sessions FILE.toml \
             (or a --state-dir holding sessions from an earlier run)"
        );
    }
    let identity = match (&args.cert, &args.key) {
        (Some(c), Some(k)) => Identity::load(c, k).context("loading --cert/--key")?,
        _ => {
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
    let (invite_key, created) = state
        .invite_key()
        .context("invitation key in the state directory")?;
    println!(
        "{} invitation key {}",
        if created { "created" } else { "using" },
        dir.join(crate::state::INVITE_KEY_FILE).display()
    );
    if let Some(spec) = &single {
        state
            .record_session(&spec.name)
            .context("recording the session name")?;
    }
    let mut template = proto::SessionConfig::new("", "");
    template.invite_key = Some(invite_key);
    let mut configs = hosted
        .sessions
        .iter()
        .map(|spec| crate::coordinator::session_config(spec, &template));
    let session = configs.next().context("no session")?;
    let more: Vec<_> = configs.collect();
    let names: Vec<String> = hosted.sessions.iter().map(|s| s.name.clone()).collect();
    let mut config = CoordinatorConfig::new(session, identity);
    config.listen = args.listen;
    config.state_dir = Some(dir.clone());
    config.record_dir = args.record.clone();
    config.status_interval =
        (args.status_interval > 0.0).then(|| Duration::from_secs_f64(args.status_interval));
    config.more_sessions = more;
    config.admin_token = args.admin_token.clone().filter(|t| !t.is_empty());
    config.max_sessions = args.max_sessions.max(names.len());
    config.metrics = args.metrics;
    if !(args.relay_rate.is_finite() && args.relay_rate >= 1.0) {
        anyhow::bail!("--relay-rate must be at least 1 datagram per second");
    }
    config.relay_budget = crate::session::RelayBudget {
        rate_per_s: args.relay_rate,
        burst: (args.relay_rate / 2.0).max(1.0),
    };
    config.time_scale = args.time_scale;
    let (handle, addr) = Coordinator::bind(config)?;
    println!("listening: {addr}");
    println!("fingerprint: {}", handle.fingerprint());
    for name in &names {
        println!("session: {name}");
        if let Some(d) = &args.record {
            println!(
                "recording: {}",
                crate::recording::recording_path(d, name).display()
            );
        }
    }
    if let Some(m) = handle.metrics_addr() {
        println!("metrics: http://{m}/metrics");
    }
    let stop = async {
        match args.seconds {
            Some(s) => tokio::time::sleep(Duration::from_secs_f64(s.max(0.0))).await,
            None => std::future::pending::<()>().await,
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = stop => {}
        r = tokio::signal::ctrl_c() => { r.context("waiting for Ctrl-C")?; }
        _ = terminate => {}
    }
    let stats = handle.stats();
    handle.shutdown().await;
    println!("stopped: {stats:?}");
    Ok(())
}

/// Entry point of the `cosurg-server` binary: parse arguments, set up logging
/// (`RUST_LOG`, default `info`), run.
pub fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Some(Sub::Invite(a)) => return invite(a),
        Some(Sub::Revoke(a)) => return revoke(a),
        Some(Sub::CreateSession(a)) => return create_session(a),
        None => {}
    }
    let args = cli.serve;
    let filter = || {
        tracing_subscriber::EnvFilter::try_from_default_env()
            .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"))
    };
    if args.log_json {
        let _ = tracing_subscriber::fmt()
            .json()
            .with_env_filter(filter())
            .with_writer(std::io::stderr)
            .try_init();
    } else {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(filter())
            .with_writer(std::io::stderr)
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .try_init();
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    rt.block_on(run(args))
}

/// `cosurg-server invite`: mint with the state directory's key and print the invitation
/// (one line on stdout; what it grants on stderr).
pub fn invite(a: InviteArgs) -> anyhow::Result<()> {
    let dir = a.state_dir.unwrap_or_else(tls::default_state_dir);
    let state = StateDir::new(&dir);
    let session = match a.session.or_else(|| state.session()) {
        Some(s) => s,
        None => anyhow::bail!(
            "no session recorded in {}; give --session NAME",
            dir.display()
        ),
    };
    let (key, created) = state.invite_key()?;
    if created {
        eprintln!(
            "created invitation key {}",
            dir.join(crate::state::INVITE_KEY_FILE).display()
        );
    }
    let issued = crate::state::mint(
        &key,
        &session,
        a.role,
        a.site.as_deref(),
        a.expires.as_secs(),
        crate::state::unix_now_s(),
    )?;
    eprintln!("{}", describe(&session, &issued));
    println!("{}", issued.invitation);
    Ok(())
}

/// One line saying what an invitation grants.
pub fn describe(session: &str, i: &proto::InvitationIssued) -> String {
    let expires = std::time::UNIX_EPOCH + Duration::from_secs(i.expires_unix_s);
    format!(
        "{} invitation for session {session:?}{}, expires {}, nonce {}",
        i.role,
        i.site
            .as_ref()
            .map(|s| format!(", site {s:?} only"))
            .unwrap_or_default(),
        humantime::format_rfc3339_seconds(expires),
        i.nonce_hex
    )
}

/// `cosurg-server revoke`.
pub fn revoke(a: RevokeArgs) -> anyhow::Result<()> {
    let dir = a.state_dir.unwrap_or_else(tls::default_state_dir);
    let nonce = StateDir::new(&dir).revoke(&a.invitation)?;
    println!(
        "revoked {} (in {})",
        proto::invite::hex(&nonce),
        dir.join(crate::state::REVOKED_FILE).display()
    );
    Ok(())
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
