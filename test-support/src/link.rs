//! Site-side helpers to talk to a coordinator: connect, join, frames, datagrams, streams.
//! A bare second site client for tests only; the product's site link is `cosurg::link`.
//!
//! ```no_run
//! # async fn f() -> Result<(), Box<dyn std::error::Error>> {
//! use cosurg_test_support::link;
//! use server::tls;
//! let cfg = tls::client_config_pinned("AB:CD:...")?;
//! let endpoint = link::client_endpoint(cfg)?;
//! let invitation = proto::Credential::Invitation("csi1.…".into());
//! let join = link::join_message("kyoto", proto::Role::Trainee, "lap-chole", invitation, "<scene sha-256>");
//! let mut site = link::connect_and_join(&endpoint, "127.0.0.1:4433".parse()?, "localhost", &join).await?;
//! println!("joined as site {}", site.welcome.site);
//! // site.conn.read_datagram(), site.next_control(), site.conn.accept_uni() ...
//! # Ok(()) }
//! ```

use std::net::SocketAddr;
use std::time::Duration;

use bytes::Bytes;
use proto::{Credential, FrameDecoder, Join, Message, Refusal, Role, Welcome};
use quinn::{Connection, Endpoint, RecvStream, SendStream};

/// Errors of a site link.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    #[error("connection: {0}")]
    Connection(#[from] quinn::ConnectionError),
    #[error("refused: {reason:?}: {text}", reason = .0.reason, text = .0.text)]
    Refused(Refusal),
    #[error("stream write: {0}")]
    Write(#[from] quinn::WriteError),
    #[error("stream read: {0}")]
    Read(#[from] quinn::ReadError),
    #[error("stream read: {0}")]
    ReadToEnd(#[from] quinn::ReadToEndError),
    #[error("framing: {0}")]
    Frame(#[from] proto::FrameError),
    #[error("datagram: {0}")]
    Datagram(#[from] quinn::SendDatagramError),
    #[error(transparent)]
    TooLarge(#[from] proto::DatagramTooLarge),
    #[error("protocol: {0}")]
    Protocol(String),
    #[error("timed out")]
    Timeout,
    #[error("io: {0}")]
    Io(#[from] std::io::Error),
}

/// A client endpoint on an ephemeral port of the IPv4 (or, for v6 targets, IPv6) wildcard
/// address, with `config` as default client configuration.
pub fn client_endpoint(config: quinn::ClientConfig) -> std::io::Result<Endpoint> {
    client_endpoint_on(SocketAddr::from(([0, 0, 0, 0], 0)), config)
}

/// A client endpoint bound to `bind`.
pub fn client_endpoint_on(
    bind: SocketAddr,
    config: quinn::ClientConfig,
) -> std::io::Result<Endpoint> {
    let mut e = Endpoint::client(bind)?;
    e.set_default_client_config(config);
    Ok(e)
}

/// A `Join` for the current protocol version (`credential`: the instructor token or an
/// invitation).
pub fn join_message(
    site_name: &str,
    role: Role,
    session: &str,
    credential: Credential,
    scene_hash: &str,
) -> Join {
    Join {
        protocol_version: proto::PROTOCOL_VERSION,
        scene_hash: scene_hash.to_string(),
        role,
        site_name: site_name.to_string(),
        session: session.to_string(),
        credential,
        time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
    }
}

/// A joined site: its connection and session-control stream.
pub struct SiteLink {
    pub conn: Connection,
    pub control_send: SendStream,
    pub control_recv: RecvStream,
    pub decoder: FrameDecoder,
    pub welcome: Welcome,
}

/// Connect to `addr` (TLS name `server_name`), open the control stream, send `join` and wait
/// for `Welcome` (10 s). A `Refusal` becomes [`LinkError::Refused`].
pub async fn connect_and_join(
    endpoint: &Endpoint,
    addr: SocketAddr,
    server_name: &str,
    join: &Join,
) -> Result<SiteLink, LinkError> {
    tokio::time::timeout(Duration::from_secs(10), async {
        let conn = endpoint.connect(addr, server_name)?.await?;
        let (mut send, mut recv) = conn.open_bi().await?;
        write_frame(&mut send, &Message::Join(join.clone())).await?;
        let mut dec = FrameDecoder::default();
        match read_frame(&mut recv, &mut dec).await {
            Ok(Some(Message::Welcome(welcome))) => Ok(SiteLink {
                conn,
                control_send: send,
                control_recv: recv,
                decoder: dec,
                welcome,
            }),
            Ok(Some(Message::Refusal(r))) => Err(LinkError::Refused(r)),
            Ok(Some(other)) => Err(LinkError::Protocol(format!(
                "expected Welcome, got {}",
                other.kind()
            ))),
            Ok(None) => match conn.close_reason() {
                Some(e) => Err(e.into()),
                None => Err(LinkError::Protocol(
                    "control stream ended before Welcome".into(),
                )),
            },
            Err(e) => Err(e),
        }
    })
    .await
    .map_err(|_| LinkError::Timeout)?
}

/// Write one message as a frame.
pub async fn write_frame(send: &mut SendStream, msg: &Message) -> Result<(), LinkError> {
    send.write_all(&proto::encode_frame(msg)).await?;
    Ok(())
}

/// Read the next message from a framed stream; `None` at a clean end of stream.
pub async fn read_frame(
    recv: &mut RecvStream,
    dec: &mut FrameDecoder,
) -> Result<Option<Message>, LinkError> {
    loop {
        if let Some(m) = dec.next_message()? {
            return Ok(Some(m));
        }
        match recv.read_chunk(64 * 1024, true).await? {
            Some(c) => dec.push(&c.bytes),
            None => {
                dec.finish()?;
                return Ok(None);
            }
        }
    }
}

/// Send `msg` as a datagram, checking it against `min(budget, max_datagram_size())`.
pub fn send_datagram(conn: &Connection, msg: &Message) -> Result<(), LinkError> {
    let max = conn
        .max_datagram_size()
        .unwrap_or(0)
        .min(proto::DEFAULT_DATAGRAM_BUDGET);
    let bytes = proto::encode_datagram(msg, max)?;
    conn.send_datagram(Bytes::from(bytes))?;
    Ok(())
}

/// Send `msg` on a new unidirectional stream (one frame), at `priority`, and finish it.
pub async fn send_uni(
    conn: &Connection,
    msg: &Message,
    priority: i32,
) -> Result<SendStream, LinkError> {
    let mut s = conn.open_uni().await?;
    let _ = s.set_priority(priority);
    s.write_all(&proto::encode_frame(msg)).await?;
    let _ = s.finish();
    Ok(s)
}

/// Read a whole unidirectional stream holding one frame.
pub async fn read_uni(mut recv: RecvStream, max_frame: usize) -> Result<Message, LinkError> {
    let buf = recv
        .read_to_end(max_frame + proto::codec::FRAME_HEADER_LEN)
        .await?;
    let mut dec = FrameDecoder::new(max_frame);
    dec.push(&buf);
    let m = dec
        .next_message()?
        .ok_or_else(|| LinkError::Protocol("empty stream".into()))?;
    dec.finish()?;
    if dec.buffered() != 0 {
        return Err(LinkError::Protocol(
            "more than one frame on a stream".into(),
        ));
    }
    Ok(m)
}

impl SiteLink {
    /// Send a message on the control stream.
    pub async fn send_control(&mut self, msg: &Message) -> Result<(), LinkError> {
        write_frame(&mut self.control_send, msg).await
    }

    /// Next message on the control stream (`None`: stream ended).
    pub async fn next_control(&mut self) -> Result<Option<Message>, LinkError> {
        read_frame(&mut self.control_recv, &mut self.decoder).await
    }

    /// Read the next datagram, decoded.
    pub async fn next_datagram(&self) -> Result<Message, LinkError> {
        let d = self.conn.read_datagram().await?;
        proto::decode(&d).map_err(|e| LinkError::Protocol(format!("bad datagram: {e}")))
    }

    /// Accept the next unidirectional stream and read its single message.
    pub async fn next_uni(&self) -> Result<Message, LinkError> {
        let r = self.conn.accept_uni().await?;
        read_uni(r, proto::DEFAULT_MAX_FRAME).await
    }

    /// Send `Leave` and close politely.
    pub async fn leave(mut self, reason: &str) {
        let site = self.welcome.site;
        let _ = self
            .send_control(&Message::Leave(proto::Leave {
                site,
                reason: reason.to_string(),
            }))
            .await;
        let _ = self.control_send.finish();
        // The coordinator closes the connection once it has processed the Leave.
        let _ = tokio::time::timeout(Duration::from_secs(2), self.conn.closed()).await;
    }
}
