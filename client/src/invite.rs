//! `cosurg invite`: the instructor mints an invitation through the running coordinator, so
//! that inviting a trainee needs no shell on the coordinator's host. A short-lived admin
//! connection, authenticated by the instructor token (see `server::admin`); the
//! instructor's own site, if running, is not disturbed.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args;
use proto::Role;
use server::admin::{AdminError, InvitationRequest, mint_remote};

use crate::cli::Refused;

#[derive(Debug, Args, Clone)]
pub struct InviteArgs {
    /// Coordinator address, HOST:PORT.
    #[arg(long)]
    pub server: String,
    /// Session name.
    #[arg(long)]
    pub session: String,
    /// The instructor's token (or COSURG_TOKEN).
    #[arg(long, env = "COSURG_TOKEN", hide_env_values = true)]
    pub token: String,
    /// Role the invitation admits: trainee or observer.
    #[arg(long, value_parser = server::cli::parse_invite_role)]
    pub role: Role,
    /// Admit only a site of this name.
    #[arg(long)]
    pub site: Option<String>,
    /// Lifetime, e.g. 90m, 12h, 7d.
    #[arg(long, default_value = "24h", value_parser = humantime::parse_duration)]
    pub expires: Duration,
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

/// Mint and print the invitation (one line on stdout; what it grants on stderr). A refusal
/// exits with code 3 like a refused join.
pub fn invite(args: InviteArgs) -> Result<()> {
    let client_config = match (&args.pin, &args.ca) {
        (Some(p), _) => server::tls::client_config_pinned(p)?,
        (None, Some(ca)) => {
            let pem = std::fs::read(ca).with_context(|| format!("CA file {}", ca.display()))?;
            server::tls::client_config_ca(&pem)?
        }
        (None, None) => bail!("give --pin FINGERPRINT (printed by cosurg-server) or --ca PEM"),
    };
    let addr = crate::join::resolve(&args.server)?;
    let request = InvitationRequest {
        session: args.session.clone(),
        token: args.token.clone(),
        role: args.role,
        site: args.site.clone(),
        valid_for: args.expires,
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    let issued = rt.block_on(async {
        let bind = if addr.is_ipv6() {
            std::net::SocketAddr::from((std::net::Ipv6Addr::UNSPECIFIED, 0))
        } else {
            std::net::SocketAddr::from(([0, 0, 0, 0], 0))
        };
        let mut endpoint = quinn::Endpoint::client(bind).context("opening a UDP socket")?;
        endpoint.set_default_client_config(client_config);
        let r = mint_remote(&endpoint, addr, &args.server_name, &request).await;
        endpoint.wait_idle().await;
        match r {
            Ok(i) => Ok(i),
            Err(AdminError::Refused(r)) => Err(anyhow::Error::new(Refused(format!(
                "{:?}: {}",
                r.reason, r.text
            )))),
            Err(e) => Err(anyhow::Error::new(e).context(format!("asking {addr}"))),
        }
    })?;
    eprintln!("{}", server::cli::describe(&args.session, &issued));
    println!("{}", issued.invitation);
    Ok(())
}
