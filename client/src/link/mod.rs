//! QUIC link from a site to the coordinator.
//!
//! The [`Link`] is the async shell between a site's simulation thread (a plain std thread
//! stepping at a fixed rate) and the coordinator. [`Link::start`] spawns one task on a tokio
//! runtime; every method of [`Link`] is non-blocking (except [`Link::close`], which waits a
//! bounded time), so the simulation is never held up by the network.
//!
//! ## Channels (see `proto`'s crate docs and `server::coordinator`)
//! * **control** — the bidirectional stream the link opens first; `Join` → `Welcome` or
//!   `Refusal`, then ownership, acks, teaching, commands, `Leave` ([`Link::send_control`]).
//! * **datagrams** — tool poses, sim-time stamps, small tree deltas
//!   ([`Link::send_datagram`], newest wins: a bounded queue that drops the oldest entry; a
//!   message larger than `min(1100, max_datagram_size())` bytes goes on the control stream),
//!   plus the link's own clock pings and heartbeats.
//! * **unidirectional streams** — one per keyframe ([`Link::send_keyframe`]), at a lower
//!   priority than the control stream; up to eight per region in flight, newest wins: a
//!   newer keyframe waits only while eight are busy (replacing any older one waiting),
//!   and a stream stalled for four round trips with a newer one behind it is reset
//!   (`stream_code::SUPERSEDED`). Keyframes and snapshots from the coordinator arrive the
//!   same way.
//!
//! ## Life cycle
//! connect (ALPN `cosurg/1`, pinned certificate or CA) → open the control stream → `Join` →
//! [`LinkEvent::Welcome`] (or [`LinkEvent::Refused`], after which the link stops for good) →
//! the coordinator's [`proto::Snapshot`] arrives as a [`LinkEvent::Message`]. On connection
//! loss (close, idle timeout, or silence of the coordinator for 2.4 heartbeat intervals):
//! [`LinkEvent::Disconnected`], then, if [`LinkConfig::reconnect`] is set, new attempts with
//! exponential backoff; a successful one gives [`LinkEvent::Reconnected`] followed by the
//! late-join snapshot. The link ends with [`LinkEvent::Stopped`].
//!
//! Outgoing messages are held while no session is established and delivered once joined.
//! When a connection is lost, whatever was still queued for it is discarded (counted in
//! [`LinkStats::dropped_on_loss`]): after `Disconnected` the simulation re-issues its state on
//! `Reconnected`, where ownership and site ids may have changed.
//!
//! ## Clock
//! The coordinator is the session's clock reference. The link pings it every
//! [`LinkConfig::clock_interval`] with datagrams and feeds the answers to a
//! [`proto::ClockFilter`] (minimum-delay window, slewing ≤ 5 %). The local clock is
//! wall-clock µs since the Unix epoch at [`Link::start`], advanced monotonically — the same
//! construction as the coordinator's — so on one machine the offset is near zero.

mod task;

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use proto::{ClockFilter, Message, Refusal, RegionKeyframe, Role, SiteId, Welcome};
use tokio::sync::Notify;

/// Default capacity of the newest-wins datagram queue (messages).
pub const DATAGRAM_QUEUE: usize = 64;
/// Default capacity of the control queue while no session is established (messages).
pub const CONTROL_QUEUE: usize = 4096;

/// How the link authenticates the coordinator.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Trust {
    /// Exactly the certificate with this SHA-256 fingerprint (`AB:CD:…` or plain hex).
    Pinned(String),
    /// WebPKI validation against the CA certificate(s) in this PEM file; the server name must
    /// match the certificate.
    Ca(PathBuf),
}

/// In-process network impairment of the link's own UDP socket (tests, demos).
#[derive(Debug, Clone, PartialEq)]
pub struct LinkImpairment {
    /// Outgoing (site → coordinator).
    pub up: netem::ImpairmentConfig,
    /// Incoming (coordinator → site).
    pub down: netem::ImpairmentConfig,
    pub seed: u64,
}

impl LinkImpairment {
    /// The same netem preset in both directions (one-way delays; the RTT is twice the delay).
    pub fn preset(name: &str, seed: u64) -> Result<Self, netem::ConfigError> {
        let c = netem::ImpairmentConfig::preset(name)?;
        Ok(Self {
            up: c.clone(),
            down: c,
            seed,
        })
    }
}

/// Reconnection backoff: `initial`, doubling up to `max`, ±25 % jitter; reset by a
/// successful join.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    pub initial: Duration,
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self {
            initial: Duration::from_millis(200),
            max: Duration::from_secs(5),
        }
    }
}

/// Configuration of a [`Link`].
#[derive(Debug, Clone)]
pub struct LinkConfig {
    /// Coordinator address.
    pub server: SocketAddr,
    /// TLS server name (checked only with [`Trust::Ca`]).
    pub server_name: String,
    pub session: String,
    /// The instructor token or an invitation.
    pub credential: proto::Credential,
    pub role: Role,
    /// Site name, unique within the session.
    pub site_name: String,
    /// Lower-case hex SHA-256 of the loaded scene.
    pub scene_hash: String,
    pub trust: Trust,
    /// Impair the link's UDP traffic in-process (netem model).
    pub impairment: Option<LinkImpairment>,
    /// Reconnect after a connection loss (never after a refusal).
    pub reconnect: bool,
    pub backoff: Backoff,
    /// Local UDP address; `None`: an ephemeral port on the wildcard address of the server's
    /// address family.
    pub bind: Option<SocketAddr>,
    /// Time allowed for one attempt: QUIC handshake, control stream, Join → Welcome.
    pub connect_timeout: Duration,
    /// Interval of clock pings once synchronised (the first few go out every 50 ms).
    pub clock_interval: Duration,
    /// The connection counts as lost after this many heartbeat intervals (announced in the
    /// Welcome) without any packet from the coordinator. Default 2.4; raise it on links
    /// whose queues may hold packets for longer than that.
    pub silence_factor: f64,
    /// Capacity of the newest-wins datagram queue.
    pub datagram_queue: usize,
    /// Maximum frame size accepted on streams (bytes).
    pub max_frame: usize,
    /// Protocol version announced in Join (tests of version refusal only; normally
    /// [`proto::PROTOCOL_VERSION`]).
    pub protocol_version: u16,
    /// The session clock's dilation (the coordinator's; [`server::TimeScale`]): the
    /// link's clock and its in-process impairment run this many times slower.
    pub time_scale: server::TimeScale,
}

impl LinkConfig {
    /// A configuration with defaults: pinned certificate, no impairment, reconnect on,
    /// connect timeout 10 s, clock pings every 200 ms.
    pub fn new(
        server: SocketAddr,
        fingerprint: &str,
        session: &str,
        credential: proto::Credential,
        role: Role,
        site_name: &str,
        scene_hash: &str,
    ) -> Self {
        Self {
            server,
            server_name: "localhost".into(),
            session: session.into(),
            credential,
            role,
            site_name: site_name.into(),
            scene_hash: scene_hash.into(),
            trust: Trust::Pinned(fingerprint.into()),
            impairment: None,
            reconnect: true,
            backoff: Backoff::default(),
            bind: None,
            connect_timeout: Duration::from_secs(10),
            clock_interval: Duration::from_millis(200),
            silence_factor: proto::liveness::DEFAULT_TIMEOUT_FACTOR,
            datagram_queue: DATAGRAM_QUEUE,
            max_frame: proto::DEFAULT_MAX_FRAME,
            protocol_version: proto::PROTOCOL_VERSION,
            time_scale: server::TimeScale::REAL,
        }
    }

    fn join_message(&self) -> proto::Join {
        proto::Join {
            protocol_version: self.protocol_version,
            scene_hash: self.scene_hash.clone(),
            role: self.role,
            site_name: self.site_name.clone(),
            session: self.session.clone(),
            credential: self.credential.clone(),
            time_scale_milli: self.time_scale.milli(),
        }
    }
}

/// Errors detected by [`Link::start`] (configuration, local socket). Everything after that
/// is reported as [`LinkEvent`]s.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error(transparent)]
    Tls(#[from] server::tls::TlsError),
    #[error("CA file {path}: {source}")]
    CaFile {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot bind the link's UDP socket on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
}

/// What the link reports to the simulation thread.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkEvent {
    /// First successful join.
    Welcome(Welcome),
    /// Joined again after a loss (the site id may differ); the snapshot follows.
    Reconnected(Welcome),
    /// The coordinator refused the join or kicked the site. The link stops (no reconnect).
    Refused(Refusal),
    /// A message from the coordinator or relayed from a peer (tool pose, sim time, keyframe,
    /// tree delta, ownership, snapshot, teaching, command, leave, status, site joined …).
    Message(Message),
    /// The connection was lost.
    Disconnected {
        reason: String,
        will_reconnect: bool,
    },
    /// A connection attempt failed.
    ConnectFailed { error: String, will_retry: bool },
    /// The link task ended (after a refusal, [`Link::close`], or a loss without reconnect).
    Stopped { reason: String },
}

/// NTP-style clock estimate against the coordinator.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ClockEstimate {
    /// Coordinator clock minus local clock (µs), slewed; `None` before the first sample.
    pub offset_us: Option<f64>,
    /// Lowest round-trip delay in the filter's window (µs).
    pub rtt_us: Option<u64>,
    /// Local clock now (µs since the Unix epoch, monotonic).
    pub local_now_us: u64,
    /// Estimated coordinator clock now (µs).
    pub coordinator_now_us: Option<u64>,
    /// Samples accepted / rejected as implausible.
    pub samples: u64,
    pub rejected: u64,
}

/// Link counters (monotonic since [`Link::start`], summed over connections).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LinkStats {
    /// Application payload bytes sent / received (encoded messages, frame headers included;
    /// clock pings and heartbeats included).
    pub bytes_up: u64,
    pub bytes_down: u64,
    /// UDP bytes sent / received according to quinn (`Connection::stats()`), all connections.
    pub udp_bytes_up: u64,
    pub udp_bytes_down: u64,
    /// Application datagrams (tool poses, sim times, deltas) sent / received.
    pub datagrams_sent: u64,
    pub datagrams_received: u64,
    /// Datagrams dropped by the newest-wins queue (overflow) or refused by quinn.
    pub datagrams_dropped: u64,
    /// Messages too large for a datagram that went on the control stream instead.
    pub datagram_fallbacks: u64,
    /// Keyframe streams sent and acknowledged / reset because superseded / received.
    pub keyframes_sent: u64,
    pub keyframes_superseded: u64,
    pub keyframes_received: u64,
    /// Snapshots received.
    pub snapshots_received: u64,
    pub control_sent: u64,
    pub control_received: u64,
    pub clock_pings: u64,
    pub clock_pongs: u64,
    pub heartbeats_sent: u64,
    /// Undecodable datagrams, frames or streams from the coordinator.
    pub malformed: u64,
    /// Queued messages discarded when a connection was lost.
    pub dropped_on_loss: u64,
    pub connects: u64,
    pub reconnects: u64,
    pub disconnects: u64,
}

#[derive(Debug, Default)]
struct Counters {
    bytes_up: AtomicU64,
    bytes_down: AtomicU64,
    udp_bytes_up: AtomicU64,
    udp_bytes_down: AtomicU64,
    datagrams_sent: AtomicU64,
    datagrams_received: AtomicU64,
    datagrams_dropped: AtomicU64,
    datagram_fallbacks: AtomicU64,
    keyframes_sent: AtomicU64,
    keyframes_superseded: AtomicU64,
    keyframes_received: AtomicU64,
    snapshots_received: AtomicU64,
    control_sent: AtomicU64,
    control_received: AtomicU64,
    clock_pings: AtomicU64,
    clock_pongs: AtomicU64,
    heartbeats_sent: AtomicU64,
    malformed: AtomicU64,
    dropped_on_loss: AtomicU64,
    connects: AtomicU64,
    reconnects: AtomicU64,
    disconnects: AtomicU64,
}

impl Counters {
    fn snapshot(&self) -> LinkStats {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        LinkStats {
            bytes_up: g(&self.bytes_up),
            bytes_down: g(&self.bytes_down),
            udp_bytes_up: g(&self.udp_bytes_up),
            udp_bytes_down: g(&self.udp_bytes_down),
            datagrams_sent: g(&self.datagrams_sent),
            datagrams_received: g(&self.datagrams_received),
            datagrams_dropped: g(&self.datagrams_dropped),
            datagram_fallbacks: g(&self.datagram_fallbacks),
            keyframes_sent: g(&self.keyframes_sent),
            keyframes_superseded: g(&self.keyframes_superseded),
            keyframes_received: g(&self.keyframes_received),
            snapshots_received: g(&self.snapshots_received),
            control_sent: g(&self.control_sent),
            control_received: g(&self.control_received),
            clock_pings: g(&self.clock_pings),
            clock_pongs: g(&self.clock_pongs),
            heartbeats_sent: g(&self.heartbeats_sent),
            malformed: g(&self.malformed),
            dropped_on_loss: g(&self.dropped_on_loss),
            connects: g(&self.connects),
            reconnects: g(&self.reconnects),
            disconnects: g(&self.disconnects),
        }
    }
}

pub(crate) fn add(a: &AtomicU64, n: u64) {
    a.fetch_add(n, Ordering::Relaxed);
}

/// Messages waiting for the link task.
#[derive(Debug, Default)]
struct Outbox {
    datagrams: VecDeque<Message>,
    keyframes: VecDeque<RegionKeyframe>,
    control: VecDeque<Message>,
    /// Close requested: send Leave with this reason, then stop.
    close: Option<String>,
}

impl Outbox {
    fn len(&self) -> usize {
        self.datagrams.len() + self.keyframes.len() + self.control.len()
    }
}

/// State shared by the [`Link`] handle and its task.
#[derive(Debug)]
struct Shared {
    outbox: Mutex<Outbox>,
    wake: Notify,
    clock: Mutex<ClockFilter>,
    local: server::WallClock,
    counters: Counters,
    /// Current site id (0: not joined).
    site: AtomicU32,
    datagram_queue: usize,
}

impl Shared {
    fn outbox(&self) -> MutexGuard<'_, Outbox> {
        self.outbox
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn clock(&self) -> MutexGuard<'_, ClockFilter> {
        self.clock
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn site(&self) -> Option<SiteId> {
        match self.site.load(Ordering::Relaxed) {
            0 => None,
            s => Some(s as SiteId),
        }
    }

    /// Estimated coordinator time now (µs), or local time before synchronisation.
    fn coordinator_now_us(&self) -> u64 {
        let local = self.local.now_us();
        self.clock().coordinator_time(local).unwrap_or(local)
    }

    /// Drop everything queued (connection lost); returns the number discarded.
    fn discard_outbox(&self) -> usize {
        let mut o = self.outbox();
        let n = o.len();
        o.datagrams.clear();
        o.keyframes.clear();
        o.control.clear();
        n
    }
}

/// A site's link to the coordinator. Owned by the simulation thread; no method blocks
/// (except [`Link::close`], bounded).
#[derive(Debug)]
pub struct Link {
    shared: Arc<Shared>,
    events: std::sync::mpsc::Receiver<LinkEvent>,
    done: std::sync::mpsc::Receiver<()>,
    task: Option<tokio::task::JoinHandle<()>>,
    impaired: Option<netem::ImpairedLink>,
    local_addr: Option<SocketAddr>,
    closed: AtomicBool,
}

/// Time [`Link::close`] waits for the Leave to be processed and the connection to close.
pub const CLOSE_WAIT: Duration = Duration::from_secs(3);

impl Link {
    /// Build the QUIC endpoint and spawn the link task on `runtime`. Connecting and joining
    /// happen in the background; watch [`Link::try_recv`] for [`LinkEvent::Welcome`].
    pub fn start(cfg: LinkConfig, runtime: &tokio::runtime::Handle) -> Result<Link, LinkError> {
        let client_config = match &cfg.trust {
            Trust::Pinned(fp) => server::tls::client_config_pinned(fp)?,
            Trust::Ca(path) => {
                let pem = std::fs::read(path).map_err(|source| LinkError::CaFile {
                    path: path.clone(),
                    source,
                })?;
                server::tls::client_config_ca(&pem)?
            }
        };
        let bind = cfg.bind.unwrap_or_else(|| {
            if cfg.server.is_ipv6() {
                SocketAddr::from((std::net::Ipv6Addr::UNSPECIFIED, 0))
            } else {
                SocketAddr::from((std::net::Ipv4Addr::UNSPECIFIED, 0))
            }
        });
        let _guard = runtime.enter();
        let bind_err = |source| LinkError::Bind { addr: bind, source };
        let (mut endpoint, impaired) = match &cfg.impairment {
            Some(imp) => {
                let f = cfg.time_scale.factor();
                let (e, l) = netem::impaired_endpoint(
                    bind,
                    None,
                    imp.up.dilated(f),
                    imp.down.dilated(f),
                    imp.seed,
                )
                .map_err(bind_err)?;
                (e, Some(l))
            }
            None => (quinn::Endpoint::client(bind).map_err(bind_err)?, None),
        };
        endpoint.set_default_client_config(client_config);
        let local_addr = endpoint.local_addr().ok();

        let shared = Arc::new(Shared {
            outbox: Mutex::new(Outbox::default()),
            wake: Notify::new(),
            clock: Mutex::new(ClockFilter::default()),
            local: server::WallClock::dilated(cfg.time_scale),
            counters: Counters::default(),
            site: AtomicU32::new(0),
            datagram_queue: cfg.datagram_queue.max(1),
        });
        let (ev_tx, ev_rx) = std::sync::mpsc::channel();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let task = runtime.spawn(task::run(cfg, endpoint, shared.clone(), ev_tx, done_tx));
        Ok(Link {
            shared,
            events: ev_rx,
            done: done_rx,
            task: Some(task),
            impaired,
            local_addr,
            closed: AtomicBool::new(false),
        })
    }

    /// Next event, if any (never blocks).
    pub fn try_recv(&self) -> Option<LinkEvent> {
        self.events.try_recv().ok()
    }

    /// Next event, waiting at most `timeout` (blocks the calling thread: not for the
    /// simulation loop nor async code).
    pub fn recv_timeout(&self, timeout: Duration) -> Option<LinkEvent> {
        self.events.recv_timeout(timeout).ok()
    }

    /// Send a message as a datagram (tool pose, sim-time stamp, tree delta). Newest wins:
    /// when the queue is full the oldest entry is dropped. Too large for a datagram, or a message whose
    /// [`proto::Channel`] is not `Datagram`: sent on the control stream.
    pub fn send_datagram(&self, msg: Message) {
        if msg.channel() != proto::Channel::Datagram {
            self.send_control(msg);
            return;
        }
        {
            let mut o = self.shared.outbox();
            while o.datagrams.len() >= self.shared.datagram_queue {
                o.datagrams.pop_front();
                add(&self.shared.counters.datagrams_dropped, 1);
            }
            o.datagrams.push_back(msg);
        }
        self.shared.wake.notify_one();
    }

    /// Send a region keyframe on its own unidirectional stream (lower priority than
    /// control). A queued older keyframe of the same region is replaced; ones still being
    /// sent go on (up to eight per region) unless stalled (see the module documentation).
    pub fn send_keyframe(&self, kf: RegionKeyframe) {
        {
            let mut o = self.shared.outbox();
            o.keyframes.retain(|k| k.region != kf.region);
            o.keyframes.push_back(kf);
        }
        self.shared.wake.notify_one();
    }

    /// Send a message on the control stream (reliable, ordered): ownership requests and
    /// releases, keyframe acks, teaching trajectories, instructor commands. While no
    /// session is established at most [`CONTROL_QUEUE`] messages are held (older ones are
    /// dropped). A [`proto::Leave`] closes the link like [`Link::close`] (without waiting).
    pub fn send_control(&self, msg: Message) {
        if let Message::Leave(l) = msg {
            // Leaving ends the session: the link must not reconnect afterwards.
            self.request_close(&l.reason);
            return;
        }
        {
            let mut o = self.shared.outbox();
            if self.shared.site().is_none() {
                while o.control.len() >= CONTROL_QUEUE {
                    o.control.pop_front();
                    add(&self.shared.counters.dropped_on_loss, 1);
                }
            }
            o.control.push_back(msg);
        }
        self.shared.wake.notify_one();
    }

    /// Clock estimate against the coordinator (µs).
    pub fn clock(&self) -> ClockEstimate {
        let local = self.shared.local.now_us();
        let mut f = self.shared.clock();
        let offset = f.offset_at(local);
        let (samples, rejected) = f.counts();
        ClockEstimate {
            offset_us: offset,
            rtt_us: f.rtt_us(),
            local_now_us: local,
            coordinator_now_us: offset.map(|o| (local as f64 + o).max(0.0).round() as u64),
            samples,
            rejected,
        }
    }

    /// Estimated coordinator clock now (µs); the local clock before the first clock sample.
    pub fn coordinator_time_us(&self) -> u64 {
        self.shared.coordinator_now_us()
    }

    /// Counters.
    pub fn stats(&self) -> LinkStats {
        self.shared.counters.snapshot()
    }

    /// Site id assigned by the coordinator in the current session (`None` while not joined).
    pub fn site_id(&self) -> Option<u16> {
        self.shared.site()
    }

    /// True while joined to a session.
    pub fn is_joined(&self) -> bool {
        self.shared.site().is_some()
    }

    /// Local UDP address of the link's endpoint.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.local_addr
    }

    /// Control and counters of the in-process impaired socket, if configured.
    pub fn impaired(&self) -> Option<&netem::ImpairedLink> {
        self.impaired.as_ref()
    }

    fn request_close(&self, reason: &str) {
        if self.closed.swap(true, Ordering::Relaxed) {
            return;
        }
        self.shared.outbox().close = Some(reason.to_string());
        self.shared.wake.notify_one();
    }

    /// Leave the session and close the connection, waiting at most [`CLOSE_WAIT`] (blocks
    /// the calling thread; from async code use [`Link::close_async`]).
    pub fn close(mut self) {
        self.request_close("site closed the link");
        let _ = self.done.recv_timeout(CLOSE_WAIT);
        if let Some(t) = self.task.take() {
            t.abort();
        }
    }

    /// Like [`Link::close`] for async callers.
    pub async fn close_async(mut self) {
        self.request_close("site closed the link");
        if let Some(t) = self.task.take() {
            let abort = t.abort_handle();
            if tokio::time::timeout(CLOSE_WAIT, t).await.is_err() {
                abort.abort();
            }
        }
    }
}

impl Drop for Link {
    /// Dropping the link leaves the session in the background (Leave, then close).
    fn drop(&mut self) {
        self.request_close("site dropped the link");
    }
}
