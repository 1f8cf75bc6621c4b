//! Invitations: the credential of trainees and observers.
//!
//! The instructor holds the session token; everyone else joins with an invitation minted on
//! the coordinator's host (`cosurg-server invite`) or by the instructor through the running
//! coordinator (`cosurg invite`). An invitation is one copy-pasteable line:
//!
//! ```text
//! csi1.<base64url, no padding: postcard(InvitationClaims) ++ HMAC-SHA256(key, DOMAIN ++ claims)>
//! ```
//!
//! The claims name the session, the role, optionally the one site name allowed to use it,
//! the expiry (Unix seconds) and a random nonce (the handle for revocation), plus the key id
//! of the signing key so that an invitation minted by another coordinator is reported as
//! such rather than as a forgery. The MAC is HMAC-SHA256 (`hmac` + `sha2` crates) under a
//! 32-byte key kept in the coordinator's state directory; only the coordinator verifies, so
//! a symmetric MAC suffices. Verification ([`InviteKey::verify`]) never panics on any input
//! and compares the tag in constant time.
//!
//! An invitation stays valid until it expires or is revoked, and it may be used again (a
//! site reconnecting after a coordinator restart presents it again); one bound to a site
//! name admits one site at a time because names are unique within a session.

use base64::Engine as _;
use base64::engine::general_purpose::URL_SAFE_NO_PAD;
use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::msg::Role;

/// Prefix of every invitation (format version 1).
pub const PREFIX: &str = "csi1.";
/// Longest invitation accepted (characters), so a hostile peer cannot make the coordinator
/// decode megabytes.
pub const MAX_INVITATION_LEN: usize = 1024;
/// Length of the random nonce.
pub const NONCE_LEN: usize = 16;
/// Length of the signing key.
pub const KEY_LEN: usize = 32;
/// Length of the HMAC-SHA256 tag.
const TAG_LEN: usize = 32;
/// Domain separation of the MAC input.
const DOMAIN: &[u8] = b"cosurg invitation v1\0";
/// Domain separation of the key id.
const KEY_ID_DOMAIN: &[u8] = b"cosurg invitation key id\0";

/// The random part of an invitation; revocation lists hold nonces.
pub type Nonce = [u8; NONCE_LEN];

/// What an invitation grants (signed).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InvitationClaims {
    /// Id of the signing key ([`InviteKey::id`]).
    pub key_id: [u8; 8],
    /// The session it admits to.
    pub session: String,
    pub role: Role,
    /// The only site name it admits, if bound.
    pub site: Option<String>,
    /// Expiry, Unix time (s).
    pub expires_unix_s: u64,
    pub nonce: Nonce,
}

/// Why an invitation string could not be verified.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum InviteError {
    #[error("not an invitation (it must start with {PREFIX:?})")]
    NotAnInvitation,
    #[error("invitation too long ({0} characters, at most {MAX_INVITATION_LEN})")]
    TooLong(usize),
    #[error("invitation is not valid base64url: {0}")]
    BadEncoding(String),
    #[error("invitation is truncated or corrupted")]
    Corrupted,
    #[error(
        "invitation was minted by another coordinator (key {theirs}, this coordinator's key is {ours})"
    )]
    ForeignKey { ours: String, theirs: String },
    #[error("invitation signature does not verify (altered or forged)")]
    BadSignature,
}

/// Parse a nonce given as 32 hex digits.
pub fn parse_nonce(s: &str) -> Option<Nonce> {
    let s = s.trim();
    if s.len() != 2 * NONCE_LEN || !s.is_ascii() {
        return None;
    }
    let mut out = [0u8; NONCE_LEN];
    for (i, b) in out.iter_mut().enumerate() {
        *b = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

/// Format bytes as lower-case hex.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Read the claims of an invitation **without** checking its signature (to find the nonce
/// to revoke, or to show what an invitation says). Never trust the result for admission.
pub fn peek_claims(invitation: &str) -> Result<InvitationClaims, InviteError> {
    split(invitation).map(|(claims, _, _)| claims)
}

/// Decode the envelope: claims, their encoded bytes, the tag.
fn split(invitation: &str) -> Result<(InvitationClaims, Vec<u8>, Vec<u8>), InviteError> {
    let s = invitation.trim();
    if s.len() > MAX_INVITATION_LEN {
        return Err(InviteError::TooLong(s.len()));
    }
    let body = s.strip_prefix(PREFIX).ok_or(InviteError::NotAnInvitation)?;
    let mut raw = URL_SAFE_NO_PAD
        .decode(body)
        .map_err(|e| InviteError::BadEncoding(e.to_string()))?;
    if raw.len() <= TAG_LEN {
        return Err(InviteError::Corrupted);
    }
    let tag = raw.split_off(raw.len() - TAG_LEN);
    let (claims, rest) =
        postcard::take_from_bytes::<InvitationClaims>(&raw).map_err(|_| InviteError::Corrupted)?;
    if !rest.is_empty() {
        return Err(InviteError::Corrupted);
    }
    Ok((claims, raw, tag))
}

/// The coordinator's invitation signing key (32 bytes). `Debug` does not print it.
#[derive(Clone)]
pub struct InviteKey {
    secret: [u8; KEY_LEN],
}

impl std::fmt::Debug for InviteKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "InviteKey(id {})", hex(&self.id()))
    }
}

impl PartialEq for InviteKey {
    fn eq(&self, other: &Self) -> bool {
        use subtle::ConstantTimeEq;
        self.secret.ct_eq(&other.secret).into()
    }
}

impl InviteKey {
    pub fn from_bytes(secret: [u8; KEY_LEN]) -> Self {
        Self { secret }
    }

    /// The secret, for persisting it.
    pub fn secret(&self) -> &[u8; KEY_LEN] {
        &self.secret
    }

    /// Public id of the key: the first 8 bytes of SHA-256 over a domain tag and the key.
    pub fn id(&self) -> [u8; 8] {
        let d = Sha256::new()
            .chain_update(KEY_ID_DOMAIN)
            .chain_update(self.secret)
            .finalize();
        let mut id = [0u8; 8];
        id.copy_from_slice(&d[..8]);
        id
    }

    fn mac(&self) -> Hmac<Sha256> {
        let mut m = <Hmac<Sha256> as Mac>::new_from_slice(&self.secret)
            .expect("HMAC accepts keys of any length");
        m.update(DOMAIN);
        m
    }

    /// Mint an invitation. `nonce` must be random (the caller owns the randomness; this
    /// crate does no I/O). The key id in `claims` is ignored and set to this key's.
    pub fn sign(&self, claims: &InvitationClaims) -> String {
        let claims = InvitationClaims {
            key_id: self.id(),
            ..claims.clone()
        };
        let mut raw = postcard::to_allocvec(&claims).expect("postcard serialises the claims");
        let mut mac = self.mac();
        mac.update(&raw);
        raw.extend_from_slice(&mac.finalize().into_bytes());
        format!("{PREFIX}{}", URL_SAFE_NO_PAD.encode(raw))
    }

    /// Check an invitation's envelope and signature and return its claims. Whether the
    /// claims admit a particular join (session, role, site, expiry, revocation) is
    /// [`crate::JoinHandshake`]'s business.
    pub fn verify(&self, invitation: &str) -> Result<InvitationClaims, InviteError> {
        let (claims, raw, tag) = split(invitation)?;
        if claims.key_id != self.id() {
            return Err(InviteError::ForeignKey {
                ours: hex(&self.id()),
                theirs: hex(&claims.key_id),
            });
        }
        let mut mac = self.mac();
        mac.update(&raw);
        // `verify_slice` compares in constant time.
        mac.verify_slice(&tag)
            .map_err(|_| InviteError::BadSignature)?;
        Ok(claims)
    }
}

#[cfg(test)]
mod tests;
