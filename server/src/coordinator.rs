//! The coordinator's async shell: QUIC endpoint, one task per connection, relaying.
//!
//! Channels (see also the table in `proto`'s crate docs):
//! * **session-control stream** — a bidirectional stream the site opens first; length-prefixed
//!   frames. Site → coordinator: `Join` first, then ownership requests/releases, keyframe
//!   acks, teaching trajectories and commands (instructor), `Leave`. Coordinator → site:
//!   `Welcome`/`Refusal`, grants/denials/releases, relayed acks, commands, `SiteJoined`,
//!   `Leave`, periodic `Status`.
//! * **datagrams** — clock pings (answered by the coordinator, which is the session's clock
//!   reference), heartbeats (both ways), and sim-time stamps, tool poses and small tree
//!   deltas, relayed to every other site with the sender's id enforced.
//! * **unidirectional streams** — one per keyframe (site → coordinator → every other site,
//!   at priority [`KEYFRAME_PRIORITY`]; a stream still unacknowledged when a newer keyframe of
//!   the same region arrives is reset with `stream_code::SUPERSEDED`) and one snapshot per
//!   late joiner right after its Welcome.
//!
//! A site may itself reset a keyframe stream it is still sending with
//! `stream_code::SUPERSEDED` when it produced a newer keyframe of the region; such streams are
//! counted apart (`superseded_streams_in`), not as malformed. A site's `Leave` reason is
//! logged and relayed to the others (`left: REASON`). A quick reconnection whose name is still
//! held by the site's silent previous connection replaces it (see
//! [`crate::session::Session::join`]).
//!
//! A site that sends garbage (undecodable datagrams, truncated or oversized streams, bad
//! control frames) only has those messages dropped and counted ([`CoordinatorStats`]); other
//! sites are not affected. A control stream whose framing breaks closes that site's
//! connection with `close_code::PROTOCOL_ERROR`.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use bytes::Bytes;
use proto::{
    FrameDecoder, FrameError, Heartbeat, KEYFRAME_PRIORITY, KeyframeStreams, Message, Role,
    STREAM_READ_TIMEOUT, SessionConfig, SiteId, StreamAction, StreamToken, close_code, stream_code,
};
use quinn::{Connection, Endpoint, RecvStream, SendStream, VarInt};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tracing::{debug, info, warn};

use crate::admission::Admission;
pub use crate::clock::{SessionClock, TimeScale, WallClock};
use crate::ratelimit::RateLimitConfig;
use crate::recording::CoordinatorRecording;
use crate::session::{Action, DatagramVerdict, DropReason, RelayBudget, Session, Target};
pub use crate::stats::CoordinatorStats;
use crate::stats::{Counters, add, inc};
use crate::tls::{Identity, TlsError};

mod hub;
mod relay;
pub use hub::session_config;
use hub::{Hub, accept_loop, handle_admin, no_such_session, revocation_loop};
use relay::{relay_streams, send_stream_once, uni_loop};

/// Queue length of a site's control-stream writer; a site that lets it overflow is closed
/// with `close_code::OVERLOADED`.
pub const CONTROL_QUEUE: usize = 4096;

/// Coordinator errors.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error(transparent)]
    Tls(#[from] TlsError),
    #[error("session: {0}")]
    Session(String),
    #[error("metrics on {addr}: {source}")]
    Metrics {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot record the session into {dir}: {source}")]
    Record {
        dir: PathBuf,
        #[source]
        source: debrief::RecordError,
    },
}

/// Configuration of a coordinator.
#[derive(Debug, Clone)]
pub struct CoordinatorConfig {
    /// UDP address to listen on (`127.0.0.1:0` picks a free port).
    pub listen: SocketAddr,
    pub session: SessionConfig,
    pub identity: Identity,
    /// Interval of the status log line and `Status` broadcast; `None`: off.
    pub status_interval: Option<Duration>,
    /// Time a new connection has to open its control stream and send `Join`.
    pub join_timeout: Duration,
    /// Maximum frame size on streams (bytes).
    pub max_frame: usize,
    /// State directory whose revocation list is watched (`None`: no revocations).
    pub state_dir: Option<PathBuf>,
    /// Failed joins per source address.
    pub rate_limit: RateLimitConfig,
    /// Further sessions served on the same endpoint besides `session` (names must differ);
    /// each isolated from the others (see the `hub` module).
    pub more_sessions: Vec<SessionConfig>,
    /// The operator's secret that allows creating sessions at run time
    /// ([`proto::AdminAction::CreateSession`]); `None`: no sessions are created at run time.
    pub admin_token: Option<String>,
    /// Maximum number of sessions hosted (configured and created at run time).
    pub max_sessions: usize,
    /// Serve Prometheus metrics over HTTP on this (local) address; `None`: off.
    pub metrics: Option<SocketAddr>,
    /// Record the session into `DIR/<session>.cosrec` ([`crate::recording`]); `None`: off.
    pub record_dir: Option<PathBuf>,
    /// Datagrams per second each site may have relayed ([`RelayBudget`]).
    pub relay_budget: RelayBudget,
    /// The session clock's dilation ([`TimeScale`]); every site must use the same.
    pub time_scale: TimeScale,
}

impl CoordinatorConfig {
    /// Defaults: listen on `127.0.0.1:0`, status every 5 s, join timeout 10 s.
    pub fn new(session: SessionConfig, identity: Identity) -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            session,
            identity,
            status_interval: Some(Duration::from_secs(5)),
            join_timeout: Duration::from_secs(10),
            max_frame: proto::DEFAULT_MAX_FRAME,
            state_dir: None,
            rate_limit: RateLimitConfig::default(),
            more_sessions: Vec::new(),
            admin_token: None,
            max_sessions: 256,
            metrics: None,
            record_dir: None,
            relay_budget: RelayBudget::default(),
            time_scale: TimeScale::REAL,
        }
    }

    /// Same with a fresh in-memory self-signed identity (tests, in-process demo).
    pub fn ephemeral(session: SessionConfig) -> Result<Self, TlsError> {
        let (id, _, _) = Identity::generate_self_signed()?;
        Ok(Self::new(session, id))
    }
}

enum CtrlItem {
    Frame(Bytes),
    CloseAfterFlush { code: u32, reason: String },
}

struct Peer {
    conn: Connection,
    ctrl: mpsc::Sender<CtrlItem>,
    /// Relayed keyframe streams to this peer: which goes out now, which waits, which is
    /// reset (the same scheduler as the sites' links).
    streams: KeyframeStreams<Bytes>,
    cancels: HashMap<StreamToken, oneshot::Sender<()>>,
    /// (udp rx bytes, udp tx bytes) at the last status line.
    last_bytes: (u64, u64),
}

struct State {
    session: Session,
    peers: HashMap<SiteId, Peer>,
    /// The session's recording, if `--record` (fed by the `// recording:` calls).
    recording: Option<CoordinatorRecording>,
}

/// One hosted session: its state and the peers of its sites.
struct Shared {
    name: String,
    clock: WallClock,
    state: Mutex<State>,
    counters: Counters,
    max_frame: usize,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock would be a bug; keep serving regardless.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Execute session actions. Called with the state locked.
    fn execute(&self, st: &mut State, actions: Vec<Action>) {
        for a in actions {
            // recording: every control message the coordinator sends.
            if let (Some(r), Action::Control { msg, .. }) = (st.recording.as_mut(), &a) {
                r.on_control(msg);
            }
            match a {
                Action::Control { to, msg } => {
                    let frame = Bytes::from(proto::encode_frame(&msg));
                    let mut overloaded = Vec::new();
                    for (&id, peer) in st.peers.iter() {
                        if !to.includes(id) {
                            continue;
                        }
                        match peer.ctrl.try_send(CtrlItem::Frame(frame.clone())) {
                            Ok(()) => {
                                inc(&self.counters.control_frames_out);
                                add(&self.counters.bytes_relayed, frame.len());
                            }
                            Err(mpsc::error::TrySendError::Full(_)) => overloaded.push(id),
                            Err(mpsc::error::TrySendError::Closed(_)) => {}
                        }
                    }
                    for id in overloaded {
                        inc(&self.counters.overloaded);
                        warn!(site = id, "control queue overflow; closing the site");
                        if let Some(p) = st.peers.remove(&id) {
                            p.conn.close(
                                VarInt::from_u32(close_code::OVERLOADED),
                                b"control queue overflow",
                            );
                        }
                        let more = st.session.site_left(id, "overloaded");
                        self.execute(st, more);
                    }
                }
                Action::Close { site, code, reason } => {
                    if let Some(p) = st.peers.remove(&site)
                        && p.ctrl
                            .try_send(CtrlItem::CloseAfterFlush {
                                code,
                                reason: reason.clone(),
                            })
                            .is_err()
                    {
                        p.conn.close(VarInt::from_u32(code), reason.as_bytes());
                    }
                }
                Action::Drop { site, kind, reason } => {
                    inc(&self.counters.dropped_messages);
                    debug!(site, kind, ?reason, "message dropped");
                }
            }
        }
    }
}

/// Handle of a running coordinator.
pub struct CoordinatorHandle {
    hub: Arc<Hub>,
    /// The first session (`CoordinatorConfig::session`).
    shared: Arc<Shared>,
    endpoint: Endpoint,
    tasks: JoinSet<()>,
    local_addr: SocketAddr,
    fingerprint: String,
    metrics_addr: Option<SocketAddr>,
}

/// Receive buffer asked for the coordinator's one UDP socket (bytes). Every site's datagrams
/// arrive on this socket: at 128 sites that is about 12,000 packets/s, and the kernel's
/// default buffer (208 KiB, some 250 small packets on loopback) overflows whenever the
/// endpoint is not scheduled for about 20 ms, which the load bench saw as datagram loss.
/// 4 MiB is Linux's default `net.core.rmem_max`; the kernel caps the request there.
pub const RECV_BUFFER_BYTES: usize = 4 << 20;

/// A QUIC endpoint on a UDP socket bound to `addr`, with a receive buffer of
/// [`RECV_BUFFER_BYTES`] where the system grants it (a smaller grant is logged, not an
/// error); a server when `server_config` is given. Must be called within a tokio runtime.
pub fn bind_endpoint(
    server_config: Option<quinn::ServerConfig>,
    addr: SocketAddr,
) -> std::io::Result<Endpoint> {
    let socket = std::net::UdpSocket::bind(addr)?;
    let sock = socket2::SockRef::from(&socket);
    if let Err(e) = sock.set_recv_buffer_size(RECV_BUFFER_BYTES) {
        warn!(error = %e, "could not enlarge the UDP receive buffer");
    }
    let granted = sock.recv_buffer_size().unwrap_or(0);
    debug!(granted, asked = RECV_BUFFER_BYTES, "UDP receive buffer");
    let runtime =
        quinn::default_runtime().ok_or_else(|| std::io::Error::other("no async runtime found"))?;
    Endpoint::new(
        quinn::EndpointConfig::default(),
        server_config,
        socket,
        runtime,
    )
}

/// The coordinator.
pub struct Coordinator;

impl Coordinator {
    /// Bind the endpoint and start serving. Must be called within a tokio runtime.
    /// Returns the handle and the bound address.
    pub fn bind(config: CoordinatorConfig) -> Result<(CoordinatorHandle, SocketAddr), ServerError> {
        let server_config = crate::tls::server_config(&config.identity)?;
        let endpoint = bind_endpoint(Some(server_config), config.listen).map_err(|source| {
            ServerError::Bind {
                addr: config.listen,
                source,
            }
        })?;
        let local_addr = endpoint.local_addr().map_err(|source| ServerError::Bind {
            addr: config.listen,
            source,
        })?;
        if let Some(dir) = &config.record_dir {
            // An unusable recording folder fails the start, not the sessions one by one.
            std::fs::create_dir_all(dir).map_err(|e| ServerError::Record {
                dir: dir.clone(),
                source: e.into(),
            })?;
        }
        let hub = Arc::new(Hub::new(&config));
        let refused = |r: proto::Refusal| ServerError::Session(r.text);
        let shared = hub.add_session(config.session.clone()).map_err(refused)?;
        for more in &config.more_sessions {
            hub.add_session(more.clone()).map_err(refused)?;
        }
        hub.apply_revocations();
        let mut tasks = JoinSet::new();
        tasks.spawn(accept_loop(hub.clone(), endpoint.clone()));
        tasks.spawn(revocation_loop(hub.clone(), Duration::from_secs(1)));
        let metrics_addr = match config.metrics {
            Some(addr) => Some(crate::metrics::serve(hub.clone(), addr, &mut tasks)?),
            None => None,
        };
        let fingerprint = config.identity.fingerprint();
        info!(
            %local_addr,
            session = %config.session.name,
            sessions = 1 + config.more_sessions.len(),
            max_sites = config.session.max_sites,
            %fingerprint,
            "coordinator listening"
        );
        Ok((
            CoordinatorHandle {
                hub,
                shared,
                metrics_addr,
                endpoint,
                tasks,
                local_addr,
                fingerprint,
            },
            local_addr,
        ))
    }
}

impl CoordinatorHandle {
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// SHA-256 fingerprint of the certificate presented (`AB:CD:…`).
    pub fn fingerprint(&self) -> &str {
        &self.fingerprint
    }

    /// Counters of the whole coordinator (all sessions).
    pub fn stats(&self) -> CoordinatorStats {
        let mut total = self.hub.counters.snapshot();
        for s in self.hub.all() {
            total += s.counters.snapshot();
        }
        total
    }

    /// Counters of one session (`None`: no such session).
    pub fn session_stats(&self, session: &str) -> Option<CoordinatorStats> {
        Some(self.hub.session(session)?.counters.snapshot())
    }

    /// The names of the hosted sessions.
    pub fn sessions(&self) -> Vec<String> {
        self.hub.all().iter().map(|s| s.name.clone()).collect()
    }

    /// The current site table of the first session.
    pub fn status(&self) -> proto::Status {
        let now = self.shared.clock.now_us();
        self.shared.lock().session.status(now)
    }

    /// The current site table of session `session`.
    pub fn session_status(&self, session: &str) -> Option<proto::Status> {
        let s = self.hub.session(session)?;
        let now = s.clock.now_us();
        let status = s.lock().session.status(now);
        Some(status)
    }

    /// Address of the metrics endpoint, when serving one.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// Coordinator clock now (µs).
    pub fn now_us(&self) -> u64 {
        self.shared.clock.now_us()
    }

    /// Close all connections and stop serving.
    pub async fn shutdown(mut self) {
        self.endpoint.close(
            VarInt::from_u32(close_code::NORMAL),
            b"coordinator shutting down",
        );
        self.tasks.abort_all();
        self.hub.abort_all();
        let _ = tokio::time::timeout(Duration::from_secs(1), self.endpoint.wait_idle()).await;
        // recording: closed with each session.
        for shared in self.hub.all() {
            if let Some(r) = shared.lock().recording.as_mut() {
                r.finish();
            }
        }
        info!("coordinator stopped");
    }
}

/// Periodic: coordinator heartbeats, liveness, RTT table.
async fn housekeeping(shared: Arc<Shared>, interval: Duration) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let now = shared.clock.now_us();
        let mut st = shared.lock();
        let st = &mut *st;
        let hb = Bytes::from(proto::encode(&Message::Heartbeat(Heartbeat {
            site: proto::COORDINATOR_SITE,
            time_us: now,
        })));
        for (&id, p) in st.peers.iter() {
            let _ = p.conn.send_datagram(hb.clone());
            st.session
                .set_rtt(id, p.conn.rtt().as_micros().min(u32::MAX as u128) as u32);
        }
        // Stalled keyframe streams with a newer keyframe behind them are reset.
        let ids: Vec<SiteId> = st.peers.keys().copied().collect();
        for id in ids {
            if let Some(p) = st.peers.get_mut(&id) {
                let stall = proto::stall_time(p.conn.rtt());
                let more = p.streams.poll(Instant::now(), stall);
                relay_streams(&shared, p, id, more);
            }
        }
        let actions = st.session.poll_liveness(now);
        for a in &actions {
            if let Action::Close { site, .. } = a {
                warn!(session = %shared.name, site, "site timed out (no heartbeat)");
            }
        }
        shared.execute(st, actions);
    }
}

/// Periodic status line (tracing) and `Status` broadcast.
async fn status_loop(shared: Arc<Shared>, interval: Duration) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tick.tick().await;
    let mut last = Instant::now();
    loop {
        tick.tick().await;
        let dt = last.elapsed().as_secs_f64().max(1e-3);
        last = Instant::now();
        let now = shared.clock.now_us();
        let mut st = shared.lock();
        let st = &mut *st;
        let max_sim = st.session.max_sim_time();
        let mut parts = Vec::new();
        let (mut up_total, mut down_total) = (0.0, 0.0);
        for s in st.session.sites() {
            let id = s.entry.site;
            let mut cwnd_kb = 0.0;
            let (up, down) = match st.peers.get_mut(&id) {
                Some(p) => {
                    let stats = p.conn.stats();
                    cwnd_kb = stats.path.cwnd as f64 / 1000.0;
                    let (rx, tx) = (stats.udp_rx.bytes, stats.udp_tx.bytes);
                    let r = (
                        (rx - p.last_bytes.0.min(rx)) as f64 / dt,
                        (tx - p.last_bytes.1.min(tx)) as f64 / dt,
                    );
                    p.last_bytes = (rx, tx);
                    r
                }
                None => (0.0, 0.0),
            };
            up_total += up;
            down_total += down;
            parts.push(format!(
                "#{id} {} ({}) sim {:.3} s lag {:.3} s rtt {:.1} ms cwnd {cwnd_kb:.1} kB up {:.1} kB/s down {:.1} kB/s",
                s.entry.name,
                s.entry.role,
                s.sim_time_s,
                max_sim - s.sim_time_s,
                s.rtt_us as f64 / 1000.0,
                up / 1000.0,
                down / 1000.0
            ));
        }
        let c = shared.counters.snapshot();
        info!(
            session = %shared.name,
            sites = parts.len(),
            up_kB_s = format!("{:.1}", up_total / 1000.0),
            down_kB_s = format!("{:.1}", down_total / 1000.0),
            malformed = c.malformed_datagrams + c.malformed_streams + c.malformed_control,
            dropped = c.dropped_messages,
            "status: {}",
            if parts.is_empty() {
                "no sites".to_string()
            } else {
                parts.join("; ")
            }
        );
        let status = st.session.status(now);
        shared.execute(
            st,
            vec![Action::Control {
                to: Target::All,
                msg: Message::Status(status),
            }],
        );
    }
}

/// Write a refusal on the control stream, wait briefly for it to be acknowledged, then
/// close the connection with the refusal's application error code.
async fn refuse(conn: &Connection, send: Option<&mut SendStream>, refusal: proto::Refusal) {
    let code = refusal.reason.close_code();
    let text = refusal.text.clone();
    if let Some(send) = send {
        let frame = proto::encode_frame(&Message::Refusal(refusal));
        if send.write_all(&frame).await.is_ok() && send.finish().is_ok() {
            let _ = tokio::time::timeout(Duration::from_secs(2), send.stopped()).await;
        }
    }
    conn.close(VarInt::from_u32(code), text.as_bytes());
}

fn alpn_of(conn: &Connection) -> Option<Vec<u8>> {
    conn.handshake_data()?
        .downcast::<quinn::crypto::rustls::HandshakeData>()
        .ok()?
        .protocol
}

async fn handle_incoming(hub: Arc<Hub>, incoming: quinn::Incoming) {
    let remote = incoming.remote_address();
    let conn = match incoming.await {
        Ok(c) => c,
        Err(e) => {
            inc(&hub.counters.handshake_failures);
            info!(%remote, error = %e, "handshake failed");
            return;
        }
    };
    if alpn_of(&conn).as_deref() != Some(proto::ALPN) {
        inc(&hub.counters.handshake_failures);
        warn!(%remote, "connection without the cosurg ALPN; closing");
        conn.close(
            VarInt::from_u32(close_code::PROTOCOL_ERROR),
            b"ALPN cosurg/1 required",
        );
        return;
    }
    let deadline = tokio::time::Instant::now() + hub.join_timeout;
    let (mut send, mut recv) = match tokio::time::timeout_at(deadline, conn.accept_bi()).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => {
            debug!(%remote, error = %e, "connection ended before opening a control stream");
            return;
        }
        Err(_) => {
            conn.close(
                VarInt::from_u32(close_code::JOIN_TIMEOUT),
                b"no control stream",
            );
            return;
        }
    };
    let mut dec = FrameDecoder::new(hub.max_frame.min(64 * 1024));
    let first = tokio::time::timeout_at(deadline, read_one(&mut recv, &mut dec)).await;
    let now = hub.clock.now_us();
    if let Ok(Ok(_)) = &first
        && let Some(refusal) = hub.admission.blocked(remote.ip(), now)
    {
        inc(&hub.counters.refused);
        debug!(%remote, "join from a blocked address refused");
        refuse(&conn, Some(&mut send), refusal).await;
        return;
    }
    let join = match first {
        Ok(Ok(Message::Join(j))) => j,
        Ok(Ok(Message::Admin(req))) => {
            handle_admin(&hub, &conn, &mut send, remote, req).await;
            return;
        }
        Ok(Ok(other)) => {
            inc(&hub.counters.refused);
            warn!(%remote, kind = other.kind(), "first control message is not a Join");
            let refusal = proto::Refusal {
                reason: proto::RefusalReason::Malformed,
                text: format!("expected Join, got {}", other.kind()),
            };
            hub.admission.record(remote.ip(), &refusal, now);
            refuse(&conn, Some(&mut send), refusal).await;
            return;
        }
        Ok(Err(e)) => {
            inc(&hub.counters.refused);
            let refusal = match e {
                // A peer of another protocol version: its messages carry another wire tag.
                FirstMessageError::Frame(FrameError::Decode(
                    proto::DecodeError::UnknownVersion { got },
                )) => proto::Refusal {
                    reason: proto::RefusalReason::WrongVersion {
                        server: proto::PROTOCOL_VERSION,
                        client: got.into(),
                    },
                    text: format!(
                        "protocol version {got} not supported; the coordinator speaks {}",
                        proto::PROTOCOL_VERSION
                    ),
                },
                e => {
                    inc(&hub.counters.malformed_control);
                    warn!(%remote, error = %e, "bad Join");
                    proto::Refusal {
                        reason: proto::RefusalReason::Malformed,
                        text: format!("bad Join: {e}"),
                    }
                }
            };
            if let Some(blocked) = hub.admission.blocked(remote.ip(), now) {
                refuse(&conn, Some(&mut send), blocked).await;
                return;
            }
            hub.admission.record(remote.ip(), &refusal, now);
            refuse(&conn, Some(&mut send), refusal).await;
            return;
        }
        Err(_) => {
            conn.close(
                VarInt::from_u32(close_code::JOIN_TIMEOUT),
                b"no Join received",
            );
            return;
        }
    };
    // The session the site names; the connection belongs to it for its whole life.
    let Some(shared) = hub.session(&join.session) else {
        inc(&hub.counters.refused);
        let refusal = no_such_session(&join.session);
        info!(%remote, site = %join.site_name, session = %join.session, "join for an unknown session refused");
        hub.admission.record(remote.ip(), &refusal, now);
        refuse(&conn, Some(&mut send), refusal).await;
        return;
    };
    // From here on control frames may be large (teaching trajectories); frames pipelined
    // after the Join stay buffered in `dec`.
    dec.set_max_frame(shared.max_frame);

    let (tx, rx) = mpsc::channel(CONTROL_QUEUE);
    let joined = {
        let mut st = shared.lock();
        let st = &mut *st;
        match st.session.join(&join, now) {
            Err(r) => Err(r),
            Ok(j) => {
                let site = j.welcome.site;
                let _ = tx.try_send(CtrlItem::Frame(Bytes::from(proto::encode_frame(
                    &Message::Welcome(j.welcome.clone()),
                ))));
                st.peers.insert(
                    site,
                    Peer {
                        conn: conn.clone(),
                        ctrl: tx,
                        streams: KeyframeStreams::default(),
                        cancels: HashMap::new(),
                        last_bytes: (0, 0),
                    },
                );
                shared.execute(st, j.actions);
                Ok((site, j.snapshot, j.replaced))
            }
        }
    };
    let (site, snapshot, replaced) = match joined {
        Ok(x) => x,
        Err(refusal) => {
            inc(&shared.counters.refused);
            info!(%remote, site = %join.site_name, reason = ?refusal.reason, "join refused");
            hub.admission.record(remote.ip(), &refusal, now);
            refuse(&conn, Some(&mut send), refusal).await;
            return;
        }
    };
    inc(&shared.counters.joined);
    if let Some(old) = replaced {
        inc(&shared.counters.resumed);
        info!(%remote, site, old, name = %join.site_name, "site reconnected; replaced its silent previous connection");
    }
    info!(%remote, session = %shared.name, site, name = %join.site_name, role = %join.role, "site joined");
    tokio::spawn(control_writer(conn.clone(), send, rx));
    {
        let frame = Bytes::from(proto::encode_frame(&Message::Snapshot(snapshot)));
        let conn = conn.clone();
        tokio::spawn(async move {
            if let Err(e) = send_stream_once(&conn, frame, None).await {
                debug!(site, error = %e, "snapshot not delivered");
            }
        });
    }

    let reason = tokio::select! {
        r = control_reader(&shared, site, &conn, recv, dec) => r,
        r = datagram_loop(&shared, site, &conn) => r,
        r = uni_loop(&shared, site, &conn) => r,
    };

    // Cleanup: unless a Close action already took the peer out (leave/kick/timeout, whose
    // writer closes after flushing), close the connection now.
    let close_now = {
        let mut st = shared.lock();
        let st = &mut *st;
        let ours = st
            .peers
            .get(&site)
            .is_some_and(|p| p.conn.stable_id() == conn.stable_id());
        if ours {
            st.peers.remove(&site);
        }
        let actions = st.session.site_left(site, &reason);
        shared.execute(st, actions);
        ours
    };
    if close_now {
        conn.close(VarInt::from_u32(close_code::NORMAL), reason.as_bytes());
    }
    inc(&shared.counters.left);
    info!(site, %reason, "site left");
}

/// Why the first message of a connection could not be read.
#[derive(Debug, thiserror::Error)]
enum FirstMessageError {
    #[error(transparent)]
    Frame(FrameError),
    #[error("{0}")]
    Stream(String),
}

/// Read exactly one message from a stream (used for the Join).
async fn read_one(
    recv: &mut RecvStream,
    dec: &mut FrameDecoder,
) -> Result<Message, FirstMessageError> {
    loop {
        match dec.next_message() {
            Ok(Some(m)) => return Ok(m),
            Ok(None) => {}
            Err(e) => return Err(FirstMessageError::Frame(e)),
        }
        match recv
            .read_chunk(dec.wanted().clamp(1, 64 * 1024), true)
            .await
        {
            Ok(Some(c)) => dec.push(&c.bytes),
            Ok(None) => {
                return Err(dec.finish().err().map_or(
                    FirstMessageError::Stream("control stream ended before Join".into()),
                    FirstMessageError::Frame,
                ));
            }
            Err(e) => return Err(FirstMessageError::Stream(e.to_string())),
        }
    }
}

async fn control_writer(conn: Connection, mut send: SendStream, mut rx: mpsc::Receiver<CtrlItem>) {
    while let Some(item) = rx.recv().await {
        match item {
            CtrlItem::Frame(b) => {
                if let Err(e) = send.write_chunk(b).await {
                    debug!(error = %e, "control stream write failed");
                    return;
                }
            }
            CtrlItem::CloseAfterFlush { code, reason } => {
                if send.finish().is_ok() {
                    let _ = tokio::time::timeout(Duration::from_secs(2), send.stopped()).await;
                }
                conn.close(VarInt::from_u32(code), reason.as_bytes());
                return;
            }
        }
    }
    let _ = send.finish();
}

async fn control_reader(
    shared: &Shared,
    site: SiteId,
    conn: &Connection,
    mut recv: RecvStream,
    mut dec: FrameDecoder,
) -> String {
    loop {
        loop {
            match dec.next_message() {
                Ok(Some(m)) => {
                    inc(&shared.counters.control_frames_in);
                    let leaving = match &m {
                        Message::Leave(l) => Some(l.reason.clone()),
                        _ => None,
                    };
                    let now = shared.clock.now_us();
                    {
                        let mut st = shared.lock();
                        let st = &mut *st;
                        let actions = st.session.on_control(site, m, now);
                        shared.execute(st, actions);
                    }
                    if let Some(reason) = leaving {
                        // The session closes the connection once the writer has flushed;
                        // nothing after a Leave matters.
                        return format!("left: {reason}");
                    }
                }
                Ok(None) => break,
                Err(FrameError::Decode(e)) => {
                    inc(&shared.counters.malformed_control);
                    warn!(site, error = %e, "undecodable control frame dropped");
                }
                Err(e) => {
                    inc(&shared.counters.malformed_control);
                    warn!(site, error = %e, "control stream framing broken; closing the site");
                    conn.close(
                        VarInt::from_u32(close_code::PROTOCOL_ERROR),
                        format!("control stream: {e}").as_bytes(),
                    );
                    return format!("protocol error: {e}");
                }
            }
        }
        match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(c)) => dec.push(&c.bytes),
            Ok(None) => {
                if let Err(e) = dec.finish() {
                    inc(&shared.counters.malformed_control);
                    warn!(site, error = %e, "control stream ended mid-frame");
                }
                return "control stream closed".into();
            }
            Err(e) => return format!("control stream: {e}"),
        }
    }
}

async fn datagram_loop(shared: &Shared, site: SiteId, conn: &Connection) -> String {
    let mut malformed_logged = 0u64;
    loop {
        let d = match conn.read_datagram().await {
            Ok(d) => d,
            Err(e) => return format!("connection: {e}"),
        };
        inc(&shared.counters.datagrams_in);
        let now = shared.clock.now_us();
        let msg = match proto::decode(&d) {
            Ok(m) => m,
            Err(e) => {
                let n = shared
                    .counters
                    .malformed_datagrams
                    .fetch_add(1, Ordering::Relaxed);
                // Log the first few per connection, then every 1000th.
                if malformed_logged < 5 || n.is_multiple_of(1000) {
                    warn!(site, len = d.len(), error = %e, "malformed datagram dropped");
                }
                malformed_logged += 1;
                continue;
            }
        };
        let mut st = shared.lock();
        let st = &mut *st;
        match st.session.on_datagram(site, msg, now) {
            DatagramVerdict::Relay { msg, restamped } => {
                // recording: tool poses and simulation clocks.
                if let Some(r) = st.recording.as_mut() {
                    r.on_datagram(&msg);
                }
                let bytes = if restamped {
                    Bytes::from(proto::encode(&msg))
                } else {
                    d
                };
                let mut fallback = Vec::new();
                for (&id, p) in st.peers.iter() {
                    if id == site {
                        continue;
                    }
                    match p.conn.send_datagram(bytes.clone()) {
                        Ok(()) => {
                            inc(&shared.counters.datagrams_relayed);
                            add(&shared.counters.bytes_relayed, bytes.len());
                        }
                        Err(quinn::SendDatagramError::TooLarge)
                            if matches!(msg, Message::TreeDelta(_)) =>
                        {
                            fallback.push(id)
                        }
                        Err(e) => {
                            inc(&shared.counters.datagrams_send_failed);
                            debug!(to = id, error = %e, "datagram relay failed");
                        }
                    }
                }
                let actions = fallback
                    .into_iter()
                    .map(|id| Action::Control {
                        to: Target::One(id),
                        msg: msg.clone(),
                    })
                    .collect();
                shared.execute(st, actions);
            }
            DatagramVerdict::Reply(mut m) => {
                if let Message::ClockPong(p) = &mut m {
                    p.t3_us = shared.clock.now_us();
                }
                let _ = conn.send_datagram(Bytes::from(proto::encode(&m)));
            }
            DatagramVerdict::Consumed => {}
            DatagramVerdict::Drop(reason) => {
                inc(&shared.counters.dropped_messages);
                if reason == DropReason::OverBudget {
                    inc(&shared.counters.over_budget);
                }
                debug!(site, ?reason, "datagram dropped");
            }
        }
    }
}
