//! What the coordinator checks before a connection becomes a site, besides the session's
//! own join validation ([`proto::JoinHandshake`]): failed joins rate-limited per source
//! address (attempts while blocked count as failures), the revocation list of the state directory (re-read when it changes, so that
//! `cosurg-server revoke` takes effect on a running coordinator), and administrative
//! requests (minting an invitation with the instructor token, see [`crate::admin`]).

use std::collections::BTreeSet;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::SystemTime;

use proto::{AdminAction, AdminRequest, InvitationIssued, Nonce, Refusal, RefusalReason};
use tracing::warn;

use crate::ratelimit::{JoinRateLimiter, RateLimitConfig};
use crate::session::Session;
use crate::state::{self, StateDir};

/// Whether a refusal counts as a failed attempt for rate limiting: wrong or unusable
/// credentials, unknown sessions, malformed joins. Refusals a legitimate site meets in
/// normal operation (name taken, full, wrong scene or version) do not count.
pub fn counts_as_failure(reason: &RefusalReason) -> bool {
    matches!(
        reason,
        RefusalReason::WrongToken
            | RefusalReason::WrongSession
            | RefusalReason::InvalidInvitation
            | RefusalReason::InvitationExpired
            | RefusalReason::InvitationRevoked
            | RefusalReason::WrongRole
            | RefusalReason::WrongSite
            | RefusalReason::Malformed
    )
}

/// Admission state shared by the coordinator's connection tasks.
#[derive(Debug)]
pub struct Admission {
    limiter: Mutex<JoinRateLimiter>,
    state_dir: Option<StateDir>,
    /// Modification time of the revocation list last loaded (`None`: not loaded yet).
    revoked_seen: Mutex<Option<Option<SystemTime>>>,
    /// The revocation list last loaded.
    current: Mutex<Option<BTreeSet<Nonce>>>,
}

impl Admission {
    pub fn new(rate_limit: RateLimitConfig, state_dir: Option<StateDir>) -> Self {
        Self {
            limiter: Mutex::new(JoinRateLimiter::new(rate_limit)),
            state_dir,
            revoked_seen: Mutex::new(None),
            current: Mutex::new(None),
        }
    }

    fn limiter(&self) -> std::sync::MutexGuard<'_, JoinRateLimiter> {
        self.limiter.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The refusal for an address that is currently blocked, if it is. An attempt during a
    /// block is itself a failure: hammering extends the block exponentially.
    pub fn blocked(&self, ip: IpAddr, now_us: u64) -> Option<Refusal> {
        let mut limiter = self.limiter();
        let retry = limiter.check(ip, now_us).err()?;
        let retry = limiter.failure(ip, now_us).unwrap_or(retry);
        let retry_after_ms = retry.as_millis().max(1) as u64;
        Some(Refusal {
            reason: RefusalReason::RateLimited { retry_after_ms },
            text: format!(
                "rate limited: too many failed joins from {ip}; retry in {:.1} s",
                retry_after_ms as f64 / 1000.0
            ),
        })
    }

    /// Account a refusal sent to `ip`.
    pub fn record(&self, ip: IpAddr, refusal: &Refusal, now_us: u64) {
        if counts_as_failure(&refusal.reason)
            && let Some(block) = self.limiter().failure(ip, now_us)
        {
            warn!(%ip, ?block, "too many failed joins; address blocked");
        }
    }

    /// The revocation list if it changed since the last call (the first call loads it). A
    /// list that cannot be read or parsed is logged and skipped (the previous one stays in
    /// force) and retried when it changes again.
    pub fn poll_revocations(&self) -> Option<BTreeSet<Nonce>> {
        let dir = self.state_dir.as_ref()?;
        let mtime = dir.revoked_mtime();
        let mut seen = self.revoked_seen.lock().unwrap_or_else(|p| p.into_inner());
        if *seen == Some(mtime) {
            return None;
        }
        *seen = Some(mtime);
        match dir.revoked() {
            Ok(set) => {
                *self.current.lock().unwrap_or_else(|p| p.into_inner()) = Some(set.clone());
                Some(set)
            }
            Err(e) => {
                warn!(error = %e, "revocation list not loaded");
                None
            }
        }
    }
}

impl Admission {
    /// The revocation list last loaded by [`Admission::poll_revocations`], if any (for a
    /// session created after it was loaded).
    pub fn current_revocations(&self) -> Option<BTreeSet<Nonce>> {
        self.current
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }
}

/// Answer an administrative request for `session` at coordinator time `now_us` (µs since
/// the Unix epoch).
pub fn answer_admin(
    session: &Session,
    req: &AdminRequest,
    now_us: u64,
) -> Result<InvitationIssued, Refusal> {
    session.validate_admin(req)?;
    let AdminAction::MintInvitation {
        role,
        site,
        valid_for_s,
    } = &req.action
    else {
        return Err(Refusal {
            reason: RefusalReason::Malformed,
            text: "not an invitation request".into(),
        });
    };
    let config = session.config();
    let key = config.invite_key.as_ref().ok_or_else(|| Refusal {
        reason: RefusalReason::InvalidInvitation,
        text: "this coordinator has no invitation key (start it with a state directory)".into(),
    })?;
    state::mint(
        key,
        &config.name,
        *role,
        site.as_deref(),
        *valid_for_s,
        now_us / 1_000_000,
    )
    .map_err(|e| Refusal {
        reason: RefusalReason::Malformed,
        text: e.to_string(),
    })
}
