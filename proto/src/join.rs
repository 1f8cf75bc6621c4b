//! Server side of the join handshake: validate a [`Join`] against the session configuration.
//!
//! Checks, in this order (the first failing one is reported):
//! 1. protocol version → [`RefusalReason::WrongVersion`]
//! 2. session name → [`RefusalReason::WrongSession`]
//! 3. token (constant-time comparison) → [`RefusalReason::WrongToken`]
//! 4. scene hash (case-insensitive hex) → [`RefusalReason::WrongScene`]; checked after the
//!    token so that the expected hash is only revealed to token holders
//! 5. site name empty / too long / control characters → [`RefusalReason::Malformed`]
//! 6. name kicked earlier in this session → [`RefusalReason::Kicked`]
//! 7. name already in use → [`RefusalReason::NameTaken`]
//! 8. capacity → [`RefusalReason::Full`]
//!
//! If the configuration has no scene hash, the first accepted site fixes it for the session.

use std::collections::{BTreeMap, BTreeSet};

use crate::msg::{Join, Refusal, RefusalReason, Role, SessionInfo, SiteEntry, SiteId, Welcome};

/// Maximum site-name length in bytes.
pub const MAX_SITE_NAME: usize = 64;
/// Default heartbeat interval announced in [`SessionInfo`] (µs).
pub const DEFAULT_HEARTBEAT_INTERVAL_US: u64 = 500_000;

/// What a session accepts.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionConfig {
    pub name: String,
    pub token: String,
    /// Required scene hash (hex SHA-256); `None`: the first site to join fixes it.
    pub scene_hash: Option<String>,
    pub max_sites: u16,
    pub heartbeat_interval_us: u64,
}

impl SessionConfig {
    pub fn new(name: impl Into<String>, token: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            token: token.into(),
            scene_hash: None,
            max_sites: 16,
            heartbeat_interval_us: DEFAULT_HEARTBEAT_INTERVAL_US,
        }
    }
}

fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    // Length is not secret; the content comparison does not short-circuit.
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
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
    next_id: SiteId,
}

impl JoinHandshake {
    pub fn new(config: SessionConfig) -> Self {
        Self {
            config,
            sites: BTreeMap::new(),
            kicked: BTreeSet::new(),
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

    /// Check a join without changing anything.
    pub fn validate(&self, join: &Join) -> Result<(), Refusal> {
        let refuse = |reason: RefusalReason, text: String| Err(Refusal { reason, text });
        if join.protocol_version != crate::PROTOCOL_VERSION {
            return refuse(
                RefusalReason::WrongVersion {
                    server: crate::PROTOCOL_VERSION,
                    client: join.protocol_version,
                },
                format!(
                    "protocol version {} not supported; the coordinator speaks {}",
                    join.protocol_version,
                    crate::PROTOCOL_VERSION
                ),
            );
        }
        if join.session != self.config.name {
            return refuse(
                RefusalReason::WrongSession,
                format!("no session named {:?} here", join.session),
            );
        }
        if !ct_eq(join.token.as_bytes(), self.config.token.as_bytes()) {
            return refuse(RefusalReason::WrongToken, "wrong session token".into());
        }
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
        Ok(())
    }

    /// Validate and, on success, admit the site: returns the [`Welcome`] to send.
    /// `now_us` is the coordinator clock.
    pub fn handle_join(&mut self, join: &Join, now_us: u64) -> Result<Welcome, Refusal> {
        self.validate(join)?;
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
        self.sites.remove(&site)
    }

    /// Kick a site: it is removed and its name may not rejoin this session. Returns the
    /// refusal to send it before closing its connection, or `None` if no such site.
    pub fn kick(&mut self, site: SiteId, text: &str) -> Option<(SiteEntry, Refusal)> {
        let entry = self.sites.remove(&site)?;
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
mod tests {
    use super::*;
    use crate::PROTOCOL_VERSION;

    const SCENE: &str = "ab12";

    fn cfg() -> SessionConfig {
        SessionConfig {
            scene_hash: Some(SCENE.into()),
            max_sites: 3,
            ..SessionConfig::new("lap-chole", "s3cret")
        }
    }

    fn join(name: &str) -> Join {
        Join {
            protocol_version: PROTOCOL_VERSION,
            scene_hash: SCENE.into(),
            role: Role::Trainee,
            site_name: name.into(),
            session: "lap-chole".into(),
            token: "s3cret".into(),
        }
    }

    fn reason(h: &mut JoinHandshake, j: Join) -> RefusalReason {
        h.handle_join(&j, 0).unwrap_err().reason
    }

    #[test]
    fn welcome_assigns_ids_and_lists_sites() {
        let mut h = JoinHandshake::new(cfg());
        let w1 = h.handle_join(&join("kyoto"), 10).unwrap();
        let w2 = h.handle_join(&join("osaka"), 20).unwrap();
        assert_eq!(w1.site, 1);
        assert_eq!(w2.site, 2);
        assert_eq!(w2.sites.len(), 2);
        assert_eq!(w2.coordinator_time_us, 20);
        assert_eq!(w2.session.scene_hash, SCENE);
        assert_eq!(w2.session.protocol_version, PROTOCOL_VERSION);
    }

    #[test]
    fn refusals_in_order() {
        let mut h = JoinHandshake::new(cfg());
        let mut j = join("a");
        j.protocol_version = 99;
        j.token = "bad".into();
        assert_eq!(
            reason(&mut h, j),
            RefusalReason::WrongVersion {
                server: PROTOCOL_VERSION,
                client: 99
            }
        );
        let mut j = join("a");
        j.session = "other".into();
        assert_eq!(reason(&mut h, j), RefusalReason::WrongSession);
        let mut j = join("a");
        j.token = "s3creT".into();
        j.scene_hash = "ffff".into();
        assert_eq!(reason(&mut h, j), RefusalReason::WrongToken);
        let mut j = join("a");
        j.scene_hash = "ffff".into();
        assert_eq!(
            reason(&mut h, j),
            RefusalReason::WrongScene {
                expected: SCENE.into()
            }
        );
        assert_eq!(reason(&mut h, join("")), RefusalReason::Malformed);
        assert_eq!(reason(&mut h, join("a\nb")), RefusalReason::Malformed);
        assert_eq!(
            reason(&mut h, join(&"x".repeat(65))),
            RefusalReason::Malformed
        );
        assert!(h.is_empty());
    }

    #[test]
    fn scene_hash_case_insensitive() {
        let mut h = JoinHandshake::new(cfg());
        let mut j = join("a");
        j.scene_hash = "AB12".into();
        assert!(h.handle_join(&j, 0).is_ok());
    }

    #[test]
    fn name_taken_then_free_after_leave() {
        let mut h = JoinHandshake::new(cfg());
        let w = h.handle_join(&join("a"), 0).unwrap();
        assert_eq!(reason(&mut h, join("a")), RefusalReason::NameTaken);
        assert!(h.leave(w.site).is_some());
        assert!(h.leave(w.site).is_none());
        let w2 = h.handle_join(&join("a"), 0).unwrap();
        assert_ne!(w2.site, w.site, "ids are not reused immediately");
    }

    #[test]
    fn capacity() {
        let mut h = JoinHandshake::new(cfg());
        for n in ["a", "b", "c"] {
            h.handle_join(&join(n), 0).unwrap();
        }
        assert_eq!(reason(&mut h, join("d")), RefusalReason::Full);
    }

    #[test]
    fn kicked_name_cannot_rejoin() {
        let mut h = JoinHandshake::new(cfg());
        let w = h.handle_join(&join("a"), 0).unwrap();
        let (entry, r) = h.kick(w.site, "bye").unwrap();
        assert_eq!(entry.name, "a");
        assert_eq!(r.reason, RefusalReason::Kicked);
        assert!(h.kick(w.site, "again").is_none());
        assert_eq!(reason(&mut h, join("a")), RefusalReason::Kicked);
    }

    #[test]
    fn first_join_fixes_scene_when_unset() {
        let mut h = JoinHandshake::new(SessionConfig::new("lap-chole", "s3cret"));
        let mut j = join("a");
        j.scene_hash = "CAFE".into();
        let w = h.handle_join(&j, 0).unwrap();
        assert_eq!(w.session.scene_hash, "cafe");
        assert_eq!(
            reason(&mut h, join("b")),
            RefusalReason::WrongScene {
                expected: "cafe".into()
            }
        );
    }

    #[test]
    fn id_allocation_wraps_and_skips_used() {
        let mut h = JoinHandshake::new(SessionConfig {
            max_sites: 10,
            ..cfg()
        });
        h.next_id = u16::MAX;
        let a = h.handle_join(&join("a"), 0).unwrap().site;
        let b = h.handle_join(&join("b"), 0).unwrap().site;
        assert_eq!((a, b), (u16::MAX, 1));
    }
}
