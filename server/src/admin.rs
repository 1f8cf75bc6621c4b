//! The client side of administrative requests: `cosurg invite` mints an invitation through
//! a running coordinator, authenticated by the instructor token; `cosurg-server
//! create-session` creates a session on a running coordinator, authenticated by the
//! operator's admin token (the coordinator's `--admin-token`).
//!
//! It is a connection of its own, not a site: it opens the control stream, sends one
//! [`Message::Admin`] instead of a `Join`, reads the answer ([`Message::Invitation`] or a
//! [`proto::Refusal`]) and closes. The coordinator never adds it to the session, so the
//! instructor's running site is not disturbed and its name stays its own.

use std::net::SocketAddr;
use std::time::Duration;

use proto::{
    AdminAction, AdminRequest, Credential, FrameDecoder, InvitationIssued, Message, Refusal, Role,
    SessionInfo,
};
use quinn::Endpoint;

/// Failure of an administrative request.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    #[error("connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    #[error("connection: {0}")]
    Connection(#[from] quinn::ConnectionError),
    #[error("refused by the coordinator: {}", .0.text)]
    Refused(Refusal),
    #[error("stream: {0}")]
    Stream(String),
    #[error("protocol: {0}")]
    Protocol(String),
    #[error("no answer within {0:?}")]
    Timeout(Duration),
}

/// What to mint.
#[derive(Debug, Clone)]
pub struct InvitationRequest {
    pub session: String,
    /// The instructor token.
    pub token: String,
    /// Trainee or observer.
    pub role: Role,
    /// Bind the invitation to this site name.
    pub site: Option<String>,
    /// Lifetime of the invitation.
    pub valid_for: Duration,
}

/// Ask the coordinator at `addr` (TLS name `server_name`, trust in `endpoint`'s default
/// client configuration) for an invitation.
pub async fn mint_remote(
    endpoint: &Endpoint,
    addr: SocketAddr,
    server_name: &str,
    req: &InvitationRequest,
) -> Result<InvitationIssued, AdminError> {
    let request = Message::Admin(AdminRequest {
        protocol_version: proto::PROTOCOL_VERSION,
        session: req.session.clone(),
        credential: Credential::Token(req.token.clone()),
        action: AdminAction::MintInvitation {
            role: req.role,
            site: req.site.clone(),
            valid_for_s: req.valid_for.as_secs(),
        },
    });
    match request_remote(endpoint, addr, server_name, &request).await? {
        Message::Invitation(i) => Ok(i),
        other => Err(AdminError::Protocol(format!(
            "expected an invitation, got {}",
            other.kind()
        ))),
    }
}

/// A session to create on a running coordinator.
#[derive(Debug, Clone)]
pub struct SessionRequest {
    /// Name of the new session.
    pub session: String,
    /// The coordinator's admin token (its `--admin-token`).
    pub admin_token: String,
    /// The new session's instructor token.
    pub instructor_token: String,
    /// Required scene (hex SHA-256); `None`: the first site fixes it.
    pub scene_hash: Option<String>,
    /// Maximum number of sites (`0`: the coordinator's default).
    pub max_sites: u16,
}

/// Ask the coordinator at `addr` to host a new session.
pub async fn create_session_remote(
    endpoint: &Endpoint,
    addr: SocketAddr,
    server_name: &str,
    req: &SessionRequest,
) -> Result<SessionInfo, AdminError> {
    let request = Message::Admin(AdminRequest {
        protocol_version: proto::PROTOCOL_VERSION,
        session: req.session.clone(),
        credential: Credential::Token(req.admin_token.clone()),
        action: AdminAction::CreateSession {
            instructor_token: req.instructor_token.clone(),
            scene_hash: req.scene_hash.clone(),
            max_sites: req.max_sites,
        },
    });
    match request_remote(endpoint, addr, server_name, &request).await? {
        Message::SessionCreated(i) => Ok(i),
        other => Err(AdminError::Protocol(format!(
            "expected a created session, got {}",
            other.kind()
        ))),
    }
}

/// One request on a connection of its own, one answer (a refusal becomes
/// [`AdminError::Refused`]), closed.
async fn request_remote(
    endpoint: &Endpoint,
    addr: SocketAddr,
    server_name: &str,
    request: &Message,
) -> Result<Message, AdminError> {
    let limit = Duration::from_secs(10);
    tokio::time::timeout(limit, async {
        let conn = endpoint.connect(addr, server_name)?.await?;
        let (mut send, mut recv) = conn.open_bi().await?;
        send.write_all(&proto::encode_frame(request))
            .await
            .map_err(|e| AdminError::Stream(e.to_string()))?;
        let _ = send.finish();
        let mut dec = FrameDecoder::new(64 * 1024);
        let answer = loop {
            if let Some(m) = dec
                .next_message()
                .map_err(|e| AdminError::Protocol(e.to_string()))?
            {
                break m;
            }
            match recv.read_chunk(64 * 1024, true).await {
                Ok(Some(c)) => dec.push(&c.bytes),
                Ok(None) => return Err(AdminError::Protocol("no answer".into())),
                Err(quinn::ReadError::ConnectionLost(e)) => return Err(e.into()),
                Err(e) => return Err(AdminError::Stream(e.to_string())),
            }
        };
        conn.close(0u32.into(), b"done");
        match answer {
            Message::Refusal(r) => Err(AdminError::Refused(r)),
            m => Ok(m),
        }
    })
    .await
    .map_err(|_| AdminError::Timeout(limit))?
}
