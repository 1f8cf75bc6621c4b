//! The coordinator's state directory: what must survive a restart.
//!
//! | file | content |
//! |---|---|
//! | `coordinator-cert.pem`, `coordinator-key.pem` | the self-signed certificate (see [`crate::tls`]) |
//! | `invite-key` | the invitation signing key, 64 hex digits (mode 0600) |
//! | `revoked-invitations` | one revoked invitation nonce (32 hex digits) per line; `#` comments |
//! | `session` | the name of the session last served (default of `cosurg-server invite`) |
//! | `sessions.toml` | the sessions hosted from a sessions file or created at run time, with their instructor tokens (mode 0600; see [`crate::sessions`]) |
//!
//! `cosurg-server invite` and `revoke` work on these files directly, on the coordinator's
//! host, also while the coordinator runs: it re-reads the revocation list when the file
//! changes (see [`crate::coordinator`]).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use proto::invite::{self, KEY_LEN, NONCE_LEN};
use proto::{InvitationClaims, InvitationIssued, InviteKey, Nonce, Role};

/// File name of the invitation signing key.
pub const INVITE_KEY_FILE: &str = "invite-key";
/// File name of the revocation list.
pub const REVOKED_FILE: &str = "revoked-invitations";
/// File name of the recorded session name.
pub const SESSION_FILE: &str = "session";

/// State-directory failure.
#[derive(Debug, thiserror::Error)]
pub enum StateError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {detail}")]
    Bad { path: PathBuf, detail: String },
    #[error("invitations are for trainees and observers; the instructor uses the session token")]
    InstructorInvitation,
    #[error("site name must be 1..=64 bytes without control characters")]
    BadSiteName,
    #[error("{0:?} is neither an invitation (csi1.…) nor a nonce (32 hex digits): {1}")]
    NotRevocable(String, String),
}

/// A state directory.
#[derive(Debug, Clone)]
pub struct StateDir {
    path: PathBuf,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StateError + '_ {
    move |source| StateError::Io {
        path: path.to_path_buf(),
        source,
    }
}

impl StateDir {
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self { path: path.into() }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn file(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// Load the invitation key, or create it (32 random bytes) on first use. Returns the
    /// key and whether it was created.
    pub fn invite_key(&self) -> Result<(InviteKey, bool), StateError> {
        let path = self.file(INVITE_KEY_FILE);
        match std::fs::read_to_string(&path) {
            Ok(text) => {
                let bad = |detail: &str| StateError::Bad {
                    path: path.clone(),
                    detail: detail.into(),
                };
                let t = text.trim();
                if t.len() != 2 * KEY_LEN {
                    return Err(bad("expected 64 hex digits"));
                }
                let mut key = [0u8; KEY_LEN];
                hex::decode_to_slice(t, &mut key).map_err(|e| bad(&e.to_string()))?;
                Ok((InviteKey::from_bytes(key), false))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                std::fs::create_dir_all(&self.path).map_err(io(&self.path))?;
                let key = InviteKey::from_bytes(rand::random());
                crate::tls::write_private_file(&path, hex::encode(key.secret()).as_bytes())
                    .map_err(io(&path))?;
                Ok((key, true))
            }
            Err(e) => Err(io(&path)(e)),
        }
    }

    /// The revoked nonces (empty if the file does not exist). Lines that are not a nonce
    /// are errors, so that a typo does not silently leave an invitation valid.
    pub fn revoked(&self) -> Result<BTreeSet<Nonce>, StateError> {
        let path = self.file(REVOKED_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(BTreeSet::new()),
            Err(e) => return Err(io(&path)(e)),
        };
        let mut out = BTreeSet::new();
        for (i, line) in text.lines().enumerate() {
            let l = line.split('#').next().unwrap_or("").trim();
            if l.is_empty() {
                continue;
            }
            out.insert(invite::parse_nonce(l).ok_or_else(|| StateError::Bad {
                path: path.clone(),
                detail: format!("line {}: {l:?} is not a nonce (32 hex digits)", i + 1),
            })?);
        }
        Ok(out)
    }

    /// Modification time of the revocation list (`None`: no list).
    pub fn revoked_mtime(&self) -> Option<SystemTime> {
        std::fs::metadata(self.file(REVOKED_FILE))
            .and_then(|m| m.modified())
            .ok()
    }

    /// Revoke an invitation given as the invitation itself or its nonce (hex). Returns the
    /// nonce. Idempotent.
    pub fn revoke(&self, what: &str) -> Result<Nonce, StateError> {
        let (nonce, note) = match invite::parse_nonce(what) {
            Some(n) => (n, String::new()),
            None => {
                let c = invite::peek_claims(what)
                    .map_err(|e| StateError::NotRevocable(what.into(), e.to_string()))?;
                (
                    c.nonce,
                    format!(
                        " # {} {}{}",
                        c.session,
                        c.role,
                        c.site.map(|s| format!(" {s}")).unwrap_or_default()
                    ),
                )
            }
        };
        if self.revoked()?.contains(&nonce) {
            return Ok(nonce);
        }
        std::fs::create_dir_all(&self.path).map_err(io(&self.path))?;
        use std::io::Write;
        let path = self.file(REVOKED_FILE);
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io(&path))?;
        writeln!(f, "{}{note}", invite::hex(&nonce)).map_err(io(&path))?;
        Ok(nonce)
    }

    /// Record the session name served (the default session of `invite`).
    pub fn record_session(&self, name: &str) -> Result<(), StateError> {
        std::fs::create_dir_all(&self.path).map_err(io(&self.path))?;
        let path = self.file(SESSION_FILE);
        std::fs::write(&path, format!("{name}\n")).map_err(io(&path))
    }

    /// The recorded session name, if any.
    pub fn session(&self) -> Option<String> {
        std::fs::read_to_string(self.file(SESSION_FILE))
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
    }
}

/// Mint an invitation with a fresh random nonce. `now_unix_s`: wall-clock time (s).
pub fn mint(
    key: &InviteKey,
    session: &str,
    role: Role,
    site: Option<&str>,
    valid_for_s: u64,
    now_unix_s: u64,
) -> Result<InvitationIssued, StateError> {
    if role == Role::Instructor {
        return Err(StateError::InstructorInvitation);
    }
    if let Some(s) = site
        && (s.trim().is_empty()
            || s.len() > proto::join::MAX_SITE_NAME
            || s.chars().any(char::is_control))
    {
        return Err(StateError::BadSiteName);
    }
    let nonce: [u8; NONCE_LEN] = rand::random();
    let claims = InvitationClaims {
        key_id: key.id(),
        session: session.to_string(),
        role,
        site: site.map(String::from),
        expires_unix_s: now_unix_s.saturating_add(valid_for_s),
        nonce,
    };
    Ok(InvitationIssued {
        invitation: key.sign(&claims),
        role,
        site: claims.site,
        expires_unix_s: claims.expires_unix_s,
        nonce_hex: invite::hex(&nonce),
    })
}

/// Wall-clock Unix time (s).
pub fn unix_now_s() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_persisted_revocations_appended() {
        let dir = tempfile::tempdir().unwrap();
        let st = StateDir::new(dir.path().join("nested"));
        let (k1, created) = st.invite_key().unwrap();
        assert!(created);
        let (k2, created) = st.invite_key().unwrap();
        assert!(!created);
        assert_eq!(k1, k2);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(st.path().join(INVITE_KEY_FILE))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        let a = mint(&k1, "s", Role::Trainee, Some("kyoto"), 60, 1000).unwrap();
        let b = mint(&k1, "s", Role::Observer, None, 60, 1000).unwrap();
        assert_ne!(a.nonce_hex, b.nonce_hex, "nonces are random");
        assert_eq!(a.expires_unix_s, 1060);
        assert!(st.revoked().unwrap().is_empty());
        assert!(st.revoked_mtime().is_none());
        let n = st.revoke(&a.invitation).unwrap();
        assert_eq!(invite::hex(&n), a.nonce_hex);
        st.revoke(&b.nonce_hex.to_uppercase()).unwrap();
        st.revoke(&a.nonce_hex).unwrap(); // idempotent
        let text = std::fs::read_to_string(st.path().join(REVOKED_FILE)).unwrap();
        assert_eq!(text.lines().count(), 2, "{text}");
        assert!(text.contains("kyoto"), "{text}");
        assert_eq!(st.revoked().unwrap().len(), 2);
        assert!(matches!(
            st.revoke("nonsense"),
            Err(StateError::NotRevocable(..))
        ));
        std::fs::write(st.path().join(REVOKED_FILE), "beef\n").unwrap();
        assert!(st.revoked().unwrap_err().to_string().contains("line 1"));
        assert!(mint(&k1, "s", Role::Instructor, None, 60, 0).is_err());
        assert!(mint(&k1, "s", Role::Trainee, Some(""), 60, 0).is_err());
        st.record_session("lap-chole").unwrap();
        assert_eq!(st.session().as_deref(), Some("lap-chole"));
    }

    #[test]
    fn bad_key_file_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(INVITE_KEY_FILE), "abc").unwrap();
        let e = StateDir::new(dir.path()).invite_key().unwrap_err();
        assert!(e.to_string().contains(INVITE_KEY_FILE), "{e}");
    }
}
