//! Server side of the join handshake: validate a [`Join`] against the session configuration.
//!
//! Checks, in this order (the first failing one is reported):
//! 1. protocol version → [`RefusalReason::WrongVersion`]
//! 2. session name → [`RefusalReason::WrongSession`]
//! 3. credential:
//!    * the instructor token (constant-time comparison) → [`RefusalReason::WrongToken`];
//!      it admits the instructor role only → [`RefusalReason::WrongRole`];
//!    * an invitation ([`crate::invite`]): signature → [`RefusalReason::InvalidInvitation`],
//!      its session → [`RefusalReason::WrongSession`], its role →
//!      [`RefusalReason::WrongRole`], its bound site name → [`RefusalReason::WrongSite`],
//!      expiry → [`RefusalReason::InvitationExpired`], revocation →
//!      [`RefusalReason::InvitationRevoked`];
//! 4. scene hash (case-insensitive hex) → [`RefusalReason::WrongScene`]; checked after the
//!    token so that the expected hash is only revealed to token holders
//! 5. time scale ([`Join::time_scale_milli`]) → [`RefusalReason::WrongTimeScale`]
//! 6. site name empty / too long / control characters → [`RefusalReason::Malformed`]
//! 7. name kicked earlier in this session → [`RefusalReason::Kicked`]
//! 8. name already in use → [`RefusalReason::NameTaken`]
//! 9. capacity → [`RefusalReason::Full`]
//!
//! If the configuration has no scene hash, the first accepted site fixes it for the session.

use std::collections::{BTreeMap, BTreeSet};

use subtle::ConstantTimeEq;

use crate::invite::{InviteKey, Nonce};
use crate::msg::{
    AdminRequest, Credential, Join, Refusal, RefusalReason, Role, SessionInfo, SiteEntry, SiteId,
    TIME_SCALE_REAL_MILLI, Welcome,
};

/// Maximum site-name length in bytes.
pub const MAX_SITE_NAME: usize = 64;
/// Default heartbeat interval announced in [`SessionInfo`] (µs).
pub const DEFAULT_HEARTBEAT_INTERVAL_US: u64 = 500_000;

/// What a session accepts.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionConfig {
    pub name: String,
    /// The instructor's secret.
    pub token: String,
    /// Key that signs and verifies invitations; `None`: invitations are refused.
    pub invite_key: Option<InviteKey>,
    /// Required scene hash (hex SHA-256); `None`: the first site to join fixes it.
    pub scene_hash: Option<String>,
    pub max_sites: u16,
    pub heartbeat_interval_us: u64,
    /// The session's time scale in thousandths ([`Join::time_scale_milli`]); a site at
    /// another scale is refused.
    pub time_scale_milli: u32,
}

impl SessionConfig {
    pub fn new(name: impl Into<String>, token: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            token: token.into(),
            invite_key: None,
            scene_hash: None,
            max_sites: 16,
            heartbeat_interval_us: DEFAULT_HEARTBEAT_INTERVAL_US,
            time_scale_milli: TIME_SCALE_REAL_MILLI,
        }
    }
}

/// Constant-time equality (`subtle`); the length is not secret.
fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    a.ct_eq(b).into()
}

fn refusal(reason: RefusalReason, text: impl Into<String>) -> Refusal {
    Refusal {
        reason,
        text: text.into(),
    }
}

fn valid_site_name(name: &str) -> bool {
    !name.trim().is_empty() && name.len() <= MAX_SITE_NAME && !name.chars().any(char::is_control)
}

/// The session's membership table and join validation.
#[derive(Debug, Clone)]
pub struct JoinHandshake {
    config: SessionConfig,
    sites: BTreeMap<SiteId, SiteEntry>,
    kicked: BTreeSet<String>,
    /// Nonces of revoked invitations.
    revoked: BTreeSet<Nonce>,
    /// The invitation each member joined with.
    invitations: BTreeMap<SiteId, Nonce>,
    next_id: SiteId,
}

impl JoinHandshake {
    pub fn new(config: SessionConfig) -> Self {
        Self {
            config,
            sites: BTreeMap::new(),
            kicked: BTreeSet::new(),
            revoked: BTreeSet::new(),
            invitations: BTreeMap::new(),
            next_id: 1,
        }
    }

    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// The scene hash in force (`None` until fixed by config or by the first join).
    pub fn scene_hash(&self) -> Option<&str> {
        self.config.scene_hash.as_deref()
    }

    fn info(&self) -> SessionInfo {
        SessionInfo {
            name: self.config.name.clone(),
            scene_hash: self.config.scene_hash.clone().unwrap_or_default(),
            max_sites: self.config.max_sites,
            protocol_version: crate::PROTOCOL_VERSION,
            heartbeat_interval_us: self.config.heartbeat_interval_us,
        }
    }

    /// Replace the set of revoked invitation nonces. Returns the members that joined with
    /// an invitation now revoked (the caller removes them).
    pub fn set_revoked(&mut self, revoked: BTreeSet<Nonce>) -> Vec<SiteId> {
        self.revoked = revoked;
        self.invitations
            .iter()
            .filter(|(_, n)| self.revoked.contains(*n))
            .map(|(&s, _)| s)
            .collect()
    }

    fn check_version(&self, version: u16) -> Result<(), Refusal> {
        if version == crate::PROTOCOL_VERSION {
            return Ok(());
        }
        Err(refusal(
            RefusalReason::WrongVersion {
                server: crate::PROTOCOL_VERSION,
                client: version,
            },
            format!(
                "protocol version {version} not supported; the coordinator speaks {}",
                crate::PROTOCOL_VERSION
            ),
        ))
    }

    fn check_session(&self, session: &str) -> Result<(), Refusal> {
        if session == self.config.name {
            return Ok(());
        }
        Err(refusal(
            RefusalReason::WrongSession,
            format!("no session named {session:?} here"),
        ))
    }

    fn check_token(&self, token: &str) -> Result<(), Refusal> {
        if ct_eq(token.as_bytes(), self.config.token.as_bytes()) {
            return Ok(());
        }
        Err(refusal(RefusalReason::WrongToken, "wrong instructor token"))
    }

    /// Check the credential of a join for `role` and `site_name` at Unix time
    /// `now_unix_s`. Returns the invitation's nonce when admitted by an invitation.
    pub fn check_credential(
        &self,
        credential: &Credential,
        role: Role,
        site_name: &str,
        now_unix_s: u64,
    ) -> Result<Option<Nonce>, Refusal> {
        match credential {
            Credential::Token(token) => {
                self.check_token(token)?;
                if role != Role::Instructor {
                    return Err(refusal(
                        RefusalReason::WrongRole,
                        format!(
                            "the instructor token admits the instructor role only; a {role} joins with an invitation (cosurg-server invite / cosurg invite)"
                        ),
                    ));
                }
                Ok(None)
            }
            Credential::Invitation(text) => {
                let Some(key) = &self.config.invite_key else {
                    return Err(refusal(
                        RefusalReason::InvalidInvitation,
                        "this coordinator accepts no invitations (no invitation key)",
                    ));
                };
                let claims = key
                    .verify(text)
                    .map_err(|e| refusal(RefusalReason::InvalidInvitation, e.to_string()))?;
                if claims.session != self.config.name {
                    return Err(refusal(
                        RefusalReason::WrongSession,
                        format!(
                            "invitation is for session {:?}, not {:?}",
                            claims.session, self.config.name
                        ),
                    ));
                }
                if claims.role != role {
                    return Err(refusal(
                        RefusalReason::WrongRole,
                        format!("invitation is for a {}, not a {role}", claims.role),
                    ));
                }
                if let Some(bound) = &claims.site
                    && bound != site_name
                {
                    return Err(refusal(
                        RefusalReason::WrongSite,
                        format!("invitation is for site {bound:?}, not {site_name:?}"),
                    ));
                }
                if now_unix_s >= claims.expires_unix_s {
                    return Err(refusal(
                        RefusalReason::InvitationExpired,
                        format!(
                            "invitation expired {} s ago",
                            now_unix_s - claims.expires_unix_s
                        ),
                    ));
                }
                if self.revoked.contains(&claims.nonce) {
                    return Err(refusal(
                        RefusalReason::InvitationRevoked,
                        format!(
                            "invitation {} was revoked",
                            crate::invite::hex(&claims.nonce)
                        ),
                    ));
                }
                Ok(Some(claims.nonce))
            }
        }
    }

    /// Check an administrative request: version, session, and the instructor token (an
    /// invitation never authorises administration).
    pub fn validate_admin(&self, req: &AdminRequest) -> Result<(), Refusal> {
        self.check_version(req.protocol_version)?;
        self.check_session(&req.session)?;
        match &req.credential {
            Credential::Token(t) => self.check_token(t),
            Credential::Invitation(_) => Err(refusal(
                RefusalReason::WrongRole,
                "administration needs the instructor token, not an invitation",
            )),
        }
    }

    /// Check a join without changing anything; `now_us` is the coordinator clock (µs since
    /// the Unix epoch, for invitation expiry). Returns the invitation nonce it was admitted
    /// with, if any.
    pub fn validate(&self, join: &Join, now_us: u64) -> Result<Option<Nonce>, Refusal> {
        let refuse = |reason: RefusalReason, text: String| Err(Refusal { reason, text });
        self.check_version(join.protocol_version)?;
        self.check_session(&join.session)?;
        let nonce = self.check_credential(
            &join.credential,
            join.role,
            &join.site_name,
            now_us / 1_000_000,
        )?;
        if let Some(expected) = &self.config.scene_hash
            && !expected.eq_ignore_ascii_case(&join.scene_hash)
        {
            return refuse(
                RefusalReason::WrongScene {
                    expected: expected.clone(),
                },
                format!(
                    "scene hash {} does not match the session's {}",
                    join.scene_hash, expected
                ),
            );
        }
        if join.time_scale_milli != self.config.time_scale_milli {
            let scale = |m: u32| f64::from(m) / 1000.0;
            return refuse(
                RefusalReason::WrongTimeScale {
                    server_milli: self.config.time_scale_milli,
                    client_milli: join.time_scale_milli,
                },
                format!(
                    "the site runs at time scale {} but the session at {} (give both the \
                     same --time-scale)",
                    scale(join.time_scale_milli),
                    scale(self.config.time_scale_milli)
                ),
            );
        }
        if !valid_site_name(&join.site_name) {
            return refuse(
                RefusalReason::Malformed,
                format!("site name must be 1..={MAX_SITE_NAME} bytes without control characters"),
            );
        }
        if self.kicked.contains(&join.site_name) {
            return refuse(
                RefusalReason::Kicked,
                format!("site {:?} was removed from this session", join.site_name),
            );
        }
        if self.sites.values().any(|s| s.name == join.site_name) {
            return refuse(
                RefusalReason::NameTaken,
                format!(
                    "a site named {:?} is already in the session",
                    join.site_name
                ),
            );
        }
        if self.sites.len() >= self.config.max_sites as usize {
            return refuse(
                RefusalReason::Full,
                format!("session is full ({} sites)", self.config.max_sites),
            );
        }
        Ok(nonce)
    }

    /// Validate and, on success, admit the site: returns the [`Welcome`] to send.
    /// `now_us` is the coordinator clock.
    pub fn handle_join(&mut self, join: &Join, now_us: u64) -> Result<Welcome, Refusal> {
        let nonce = self.validate(join, now_us)?;
        if self.config.scene_hash.is_none() {
            self.config.scene_hash = Some(join.scene_hash.to_ascii_lowercase());
        }
        let id = self.alloc_id().ok_or_else(|| Refusal {
            reason: RefusalReason::Full,
            text: "no site id left".into(),
        })?;
        self.sites.insert(
            id,
            SiteEntry {
                site: id,
                name: join.site_name.clone(),
                role: join.role,
            },
        );
        if let Some(n) = nonce {
            self.invitations.insert(id, n);
        }
        Ok(Welcome {
            site: id,
            session: self.info(),
            sites: self.sites.values().cloned().collect(),
            coordinator_time_us: now_us,
        })
    }

    fn alloc_id(&mut self) -> Option<SiteId> {
        for _ in 0..u16::MAX {
            let id = self.next_id;
            self.next_id = if self.next_id == u16::MAX {
                1
            } else {
                self.next_id + 1
            };
            if !self.sites.contains_key(&id) {
                return Some(id);
            }
        }
        None
    }

    /// A site left (or its connection was lost). Returns its entry if it was a member.
    pub fn leave(&mut self, site: SiteId) -> Option<SiteEntry> {
        self.invitations.remove(&site);
        self.sites.remove(&site)
    }

    /// Kick a site: it is removed and its name may not rejoin this session. Returns the
    /// refusal to send it before closing its connection, or `None` if no such site.
    pub fn kick(&mut self, site: SiteId, text: &str) -> Option<(SiteEntry, Refusal)> {
        let entry = self.sites.remove(&site)?;
        self.invitations.remove(&site);
        self.kicked.insert(entry.name.clone());
        Some((
            entry,
            Refusal {
                reason: RefusalReason::Kicked,
                text: text.to_string(),
            },
        ))
    }

    pub fn site(&self, site: SiteId) -> Option<&SiteEntry> {
        self.sites.get(&site)
    }

    pub fn role(&self, site: SiteId) -> Option<Role> {
        self.sites.get(&site).map(|s| s.role)
    }

    pub fn sites(&self) -> impl Iterator<Item = &SiteEntry> {
        self.sites.values()
    }

    pub fn len(&self) -> usize {
        self.sites.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sites.is_empty()
    }
}

#[cfg(test)]
mod tests;
