//! The link's async task: connect, join, the per-connection session loop, reconnection.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use bytes::Bytes;
use proto::{
    ClockSample, FrameDecoder, FrameError, KEYFRAME_PRIORITY, KeyframeStreams, LivenessEvent,
    Message, PeerLiveness, Refusal, RefusalReason, RegionId, RegionKeyframe, STREAM_READ_TIMEOUT,
    SiteId, StreamAction, StreamToken, Welcome, close_code, stream_code,
};
use quinn::{Connection, ConnectionError, Endpoint, RecvStream, SendStream, VarInt};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tracing::{debug, info, warn};

use super::{LinkConfig, LinkEvent, Shared, add};

/// Period of the session loop's housekeeping tick (pings, heartbeats, liveness, stats).
const TICK: Duration = Duration::from_millis(50);
/// Number of clock pings sent every [`TICK`] right after joining, for a quick first estimate.
const FAST_PINGS: u32 = 5;
/// Time allowed for the coordinator to close the connection after our Leave.
const LEAVE_WAIT: Duration = Duration::from_secs(2);
/// Smallest accepted heartbeat interval (µs), whatever the Welcome says.
const MIN_HEARTBEAT_US: u64 = 50_000;

/// Event sender that ignores a dropped receiver.
#[derive(Clone)]
struct Events(std::sync::mpsc::Sender<LinkEvent>);

impl Events {
    fn send(&self, e: LinkEvent) {
        let _ = self.0.send(e);
    }
}

/// A joined connection, right after the Welcome.
struct JoinedConnection {
    conn: Connection,
    send: SendStream,
    recv: RecvStream,
    /// Holds whatever the coordinator pipelined after the Welcome.
    dec: FrameDecoder,
    welcome: Welcome,
}

enum AttemptError {
    Refused(Refusal),
    Failed(String),
}

/// How a session ended.
enum End {
    /// The site closed the link.
    Closed,
    /// Refused mid-session (kicked).
    Refused(Refusal),
    /// Connection lost.
    Lost(String),
}

/// The refusal a close code stands for, if it is one (fallback when the Refusal frame itself
/// could not be read before the connection closed).
fn refusal_from_close(code: u64, text: &str) -> Option<Refusal> {
    let code = u32::try_from(code).ok()?;
    let reason = match code {
        close_code::WRONG_TOKEN => RefusalReason::WrongToken,
        close_code::WRONG_VERSION => RefusalReason::WrongVersion {
            server: 0,
            client: proto::PROTOCOL_VERSION,
        },
        close_code::WRONG_SCENE => RefusalReason::WrongScene {
            expected: String::new(),
        },
        close_code::WRONG_SESSION => RefusalReason::WrongSession,
        close_code::NAME_TAKEN => RefusalReason::NameTaken,
        close_code::FULL => RefusalReason::Full,
        close_code::KICKED => RefusalReason::Kicked,
        close_code::MALFORMED => RefusalReason::Malformed,
        close_code::INVALID_INVITATION => RefusalReason::InvalidInvitation,
        close_code::INVITATION_EXPIRED => RefusalReason::InvitationExpired,
        close_code::INVITATION_REVOKED => RefusalReason::InvitationRevoked,
        close_code::WRONG_ROLE => RefusalReason::WrongRole,
        close_code::WRONG_SITE => RefusalReason::WrongSite,
        close_code::RATE_LIMITED => RefusalReason::RateLimited { retry_after_ms: 0 },
        close_code::WRONG_TIME_SCALE => RefusalReason::WrongTimeScale {
            server_milli: 0,
            client_milli: 0,
        },
        _ => return None,
    };
    Some(Refusal {
        reason,
        text: text.to_string(),
    })
}

/// Human-readable cause of a connection error.
fn describe(e: &ConnectionError) -> String {
    match e {
        ConnectionError::ApplicationClosed(c) => format!(
            "coordinator closed the connection (code {}): {}",
            c.error_code,
            String::from_utf8_lossy(&c.reason)
        ),
        ConnectionError::TimedOut => "connection timed out (idle)".into(),
        ConnectionError::LocallyClosed => "closed locally".into(),
        other => other.to_string(),
    }
}

fn attempt_error(e: ConnectionError) -> AttemptError {
    if let ConnectionError::ApplicationClosed(c) = &e
        && let Some(r) = refusal_from_close(
            c.error_code.into_inner(),
            &String::from_utf8_lossy(&c.reason),
        )
    {
        return AttemptError::Refused(r);
    }
    AttemptError::Failed(describe(&e))
}

/// Connect, open the control stream, send Join, wait for Welcome or Refusal.
async fn connect(
    cfg: &LinkConfig,
    endpoint: &Endpoint,
    shared: &Shared,
    rejoin: bool,
) -> Result<JoinedConnection, AttemptError> {
    let limit = if rejoin {
        cfg.connect_timeout.min(REJOIN_ATTEMPT_TIMEOUT)
    } else {
        cfg.connect_timeout
    };
    // A session dilated F× waits F× as long in real time, the same in session time.
    let limit = cfg.time_scale.to_real(limit);
    let attempt = async {
        let connecting = endpoint
            .connect(cfg.server, &cfg.server_name)
            .map_err(|e| AttemptError::Failed(format!("connect: {e}")))?;
        let conn = connecting.await.map_err(attempt_error)?;
        let (mut send, mut recv) = conn.open_bi().await.map_err(attempt_error)?;
        let frame = proto::encode_frame(&Message::Join(cfg.join_message()));
        add(&shared.counters.bytes_up, frame.len() as u64);
        add(&shared.counters.control_sent, 1);
        if let Err(e) = send.write_all(&frame).await {
            return Err(match conn.close_reason() {
                Some(c) => attempt_error(c),
                None => AttemptError::Failed(format!("sending Join: {e}")),
            });
        }
        let mut dec = FrameDecoder::new(cfg.max_frame);
        let first = loop {
            match dec.next_message() {
                Ok(Some(m)) => break m,
                Ok(None) => {}
                Err(e) => {
                    add(&shared.counters.malformed, 1);
                    conn.close(VarInt::from_u32(close_code::PROTOCOL_ERROR), b"bad Welcome");
                    return Err(AttemptError::Failed(format!("bad answer to Join: {e}")));
                }
            }
            match recv.read_chunk(64 * 1024, true).await {
                Ok(Some(c)) => {
                    add(&shared.counters.bytes_down, c.bytes.len() as u64);
                    dec.push(&c.bytes);
                }
                Ok(None) => {
                    let _ = tokio::time::timeout(Duration::from_secs(1), conn.closed()).await;
                    return Err(match conn.close_reason() {
                        Some(c) => attempt_error(c),
                        None => AttemptError::Failed("control stream ended before Welcome".into()),
                    });
                }
                Err(e) => {
                    return Err(match conn.close_reason() {
                        Some(c) => attempt_error(c),
                        None => AttemptError::Failed(format!("reading Welcome: {e}")),
                    });
                }
            }
        };
        add(&shared.counters.control_received, 1);
        match first {
            Message::Welcome(welcome) => Ok(JoinedConnection {
                conn,
                send,
                recv,
                dec,
                welcome,
            }),
            Message::Refusal(r) => Err(AttemptError::Refused(r)),
            other => {
                conn.close(
                    VarInt::from_u32(close_code::PROTOCOL_ERROR),
                    b"expected Welcome",
                );
                Err(AttemptError::Failed(format!(
                    "expected Welcome, got {}",
                    other.kind()
                )))
            }
        }
    };
    match tokio::time::timeout(limit, attempt).await {
        Ok(r) => r,
        Err(_) => Err(AttemptError::Failed(format!("no Welcome within {limit:?}"))),
    }
}

/// Time allowed for one attempt to rejoin after a loss (at most the configured
/// `connect_timeout`). An attempt made while the path is still down waits for the QUIC
/// handshake's retransmissions, whose timer doubles each time (0.15, 0.3, 0.6, 1.2, 2.4 s
/// … from the 50 ms initial round trip): after a 3 s outage one site's attempt was still
/// waiting 3 s later (`bench sync`, outage row, one run of ten). A fresh attempt starts
/// with a fresh timer.
const REJOIN_ATTEMPT_TIMEOUT: Duration = Duration::from_secs(2);

/// Resolves when the site asked to close the link.
async fn close_requested(shared: &Shared) {
    loop {
        if shared.outbox().close.is_some() {
            return;
        }
        shared.wake.notified().await;
    }
}

fn jittered(d: Duration) -> Duration {
    d.mul_f64(0.75 + 0.5 * rand::random::<f64>())
}

/// The link task.
pub(super) async fn run(
    cfg: LinkConfig,
    endpoint: Endpoint,
    shared: Arc<Shared>,
    events: std::sync::mpsc::Sender<LinkEvent>,
    // Dropped when the task ends, which wakes `Link::close`.
    _done: std::sync::mpsc::Sender<()>,
) {
    let ev = Events(events);
    let mut backoff = cfg.backoff.initial;
    let mut joined_before = false;
    let stop_reason: String = loop {
        let attempt = tokio::select! {
            r = connect(&cfg, &endpoint, &shared, joined_before) => r,
            _ = close_requested(&shared) => break "closed by the site".into(),
        };
        match attempt {
            Ok(j) => {
                backoff = cfg.backoff.initial;
                let welcome = j.welcome.clone();
                shared
                    .site
                    .store(u32::from(welcome.site), Ordering::Relaxed);
                add(&shared.counters.connects, 1);
                if joined_before {
                    add(&shared.counters.reconnects, 1);
                    info!(site = welcome.site, "rejoined the session");
                    ev.send(LinkEvent::Reconnected(welcome));
                } else {
                    info!(site = welcome.site, session = %welcome.session.name, "joined the session");
                    ev.send(LinkEvent::Welcome(welcome));
                }
                joined_before = true;
                let end = ConnectionLoop::new(&cfg, &shared, &ev, j).run().await;
                shared.site.store(0, Ordering::Relaxed);
                let n = shared.discard_outbox();
                add(&shared.counters.dropped_on_loss, n as u64);
                match end {
                    End::Closed => break "closed by the site".into(),
                    End::Refused(r) => {
                        warn!(reason = ?r.reason, text = %r.text, "removed from the session");
                        let reason = format!("refused: {:?}: {}", r.reason, r.text);
                        ev.send(LinkEvent::Refused(r));
                        break reason;
                    }
                    End::Lost(reason) => {
                        add(&shared.counters.disconnects, 1);
                        warn!(%reason, reconnect = cfg.reconnect, "connection to the coordinator lost");
                        ev.send(LinkEvent::Disconnected {
                            reason: reason.clone(),
                            will_reconnect: cfg.reconnect,
                        });
                        if !cfg.reconnect {
                            break reason;
                        }
                    }
                }
            }
            // Our previous connection may still be registered under our name until the
            // coordinator notices its loss: keep trying.
            Err(AttemptError::Refused(r))
                if joined_before && cfg.reconnect && r.reason == RefusalReason::NameTaken =>
            {
                debug!(text = %r.text, "name still taken by our previous connection; retrying");
                ev.send(LinkEvent::ConnectFailed {
                    error: format!("name taken: {}", r.text),
                    will_retry: true,
                });
            }
            Err(AttemptError::Refused(r)) => {
                warn!(reason = ?r.reason, text = %r.text, "join refused");
                let reason = format!("refused: {:?}: {}", r.reason, r.text);
                ev.send(LinkEvent::Refused(r));
                break reason;
            }
            Err(AttemptError::Failed(error)) => {
                debug!(%error, retry = cfg.reconnect, "connection attempt failed");
                ev.send(LinkEvent::ConnectFailed {
                    error: error.clone(),
                    will_retry: cfg.reconnect,
                });
                if !cfg.reconnect {
                    break error;
                }
            }
        }
        // Session time, as the rest of a dilated session (`LinkConfig::time_scale`).
        let pause = cfg.time_scale.to_real(jittered(backoff));
        backoff = (backoff * 2).min(cfg.backoff.max.max(cfg.backoff.initial));
        tokio::select! {
            _ = tokio::time::sleep(pause) => {}
            _ = close_requested(&shared) => break "closed by the site".into(),
        }
    };
    shared.site.store(0, Ordering::Relaxed);
    ev.send(LinkEvent::Stopped {
        reason: stop_reason,
    });
    endpoint.close(VarInt::from_u32(close_code::NORMAL), b"site stopped");
    let _ = tokio::time::timeout(Duration::from_millis(500), endpoint.wait_idle()).await;
}

/// How a session ends when its connection closed with `e`.
fn lost(e: ConnectionError) -> End {
    if let ConnectionError::ApplicationClosed(c) = &e
        && c.error_code == VarInt::from_u32(close_code::KICKED)
    {
        return End::Refused(Refusal {
            reason: RefusalReason::Kicked,
            text: String::from_utf8_lossy(&c.reason).into_owned(),
        });
    }
    End::Lost(describe(&e))
}

/// What the control reader hands to the session loop.
enum Inbound {
    Msg(Message),
    /// The stream ended or failed (not a framing error).
    Ended(String),
    /// Framing broke: the stream cannot be resynchronised.
    Broken(String),
}

/// One connection's session loop.
struct ConnectionLoop<'a> {
    cfg: &'a LinkConfig,
    shared: &'a Arc<Shared>,
    ev: &'a Events,
    conn: Connection,
    site: SiteId,
    heartbeat_us: u64,
    ctrl: Option<mpsc::UnboundedSender<Bytes>>,
    inbound: mpsc::UnboundedReceiver<Inbound>,
    tasks: JoinSet<()>,
    /// Which keyframe goes on a stream now, which waits, which stream is reset.
    streams: KeyframeStreams<Bytes>,
    /// Cancel handles of the keyframe streams in flight.
    cancels: HashMap<StreamToken, (RegionId, oneshot::Sender<()>)>,
    /// Waiting keyframes replaced, as already added to the link's counters.
    superseded_counted: u64,
    ping_seq: u32,
    /// UDP byte counters of earlier connections (up, down).
    udp_base: (u64, u64),
    malformed_logged: u32,
}

impl<'a> ConnectionLoop<'a> {
    fn new(
        cfg: &'a LinkConfig,
        shared: &'a Arc<Shared>,
        ev: &'a Events,
        j: JoinedConnection,
    ) -> Self {
        let JoinedConnection {
            conn,
            send,
            recv,
            dec,
            welcome,
        } = j;
        let mut tasks = JoinSet::new();
        let (ctrl_tx, ctrl_rx) = mpsc::unbounded_channel();
        tasks.spawn(control_writer(send, ctrl_rx));
        let (in_tx, in_rx) = mpsc::unbounded_channel();
        tasks.spawn(control_reader(recv, dec, shared.clone(), in_tx));
        tasks.spawn(uni_acceptor(
            conn.clone(),
            shared.clone(),
            ev.clone(),
            cfg.max_frame,
        ));
        let c = &shared.counters;
        Self {
            cfg,
            shared,
            ev,
            conn,
            site: welcome.site,
            heartbeat_us: welcome.session.heartbeat_interval_us.max(MIN_HEARTBEAT_US),
            ctrl: Some(ctrl_tx),
            inbound: in_rx,
            tasks,
            streams: KeyframeStreams::default(),
            cancels: HashMap::new(),
            superseded_counted: 0,
            ping_seq: 0,
            udp_base: (
                c.udp_bytes_up.load(Ordering::Relaxed),
                c.udp_bytes_down.load(Ordering::Relaxed),
            ),
            malformed_logged: 0,
        }
    }

    async fn run(mut self) -> End {
        let end = self.serve().await;
        self.update_udp_stats();
        // Stop the helpers (readers, writer, keyframe senders) of this connection.
        self.tasks.abort_all();
        end
    }

    async fn serve(&mut self) -> End {
        let local = self.shared.local;
        let mut liveness = PeerLiveness::with_factor(
            self.heartbeat_us,
            self.cfg.silence_factor.max(1.0),
            local.now_us(),
        );
        let mut last_rx_packets = self.conn.stats().udp_rx.datagrams;
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut next_ping = tokio::time::Instant::now();
        let mut fast_pings = FAST_PINGS;
        let mut next_path_log = tokio::time::Instant::now();
        let close = self.shared.outbox().close.clone();
        if let Some(reason) = close {
            return self.leave(reason).await;
        }
        self.drain();
        loop {
            tokio::select! {
                _ = self.shared.wake.notified() => {
                    let close = self.shared.outbox().close.clone();
                    if let Some(reason) = close {
                        return self.leave(reason).await;
                    }
                    self.drain();
                }
                r = self.conn.read_datagram() => match r {
                    Ok(d) => {
                        liveness.on_heard(local.now_us());
                        self.on_datagram(d);
                    }
                    Err(e) => return lost(e),
                },
                m = self.inbound.recv() => match m {
                    Some(Inbound::Msg(Message::Refusal(r))) => return End::Refused(r),
                    Some(Inbound::Msg(m)) => {
                        liveness.on_heard(local.now_us());
                        self.ev.send(LinkEvent::Message(m));
                    }
                    Some(Inbound::Broken(e)) => {
                        self.conn.close(
                            VarInt::from_u32(close_code::PROTOCOL_ERROR),
                            b"control stream framing broken",
                        );
                        return End::Lost(format!("control stream from the coordinator: {e}"));
                    }
                    Some(Inbound::Ended(why)) => {
                        // The coordinator finishes the control stream just before closing.
                        let e = match tokio::time::timeout(LEAVE_WAIT, self.conn.closed()).await {
                            Ok(e) => e,
                            Err(_) => {
                                self.conn.close(VarInt::from_u32(close_code::NORMAL), b"control stream ended");
                                return End::Lost(format!("control stream ended: {why}"));
                            }
                        };
                        return lost(e);
                    }
                    None => return End::Lost("control reader stopped".into()),
                },
                e = self.conn.closed() => return lost(e),
                _ = tick.tick() => {
                    self.pump_held_keyframes();
                    let now = local.now_us();
                    // Any packet from the coordinator (ACKs, keep-alives, …) proves it alive.
                    let rx = self.conn.stats().udp_rx.datagrams;
                    if rx != last_rx_packets {
                        last_rx_packets = rx;
                        liveness.on_heard(now);
                    }
                    self.update_udp_stats();
                    if tokio::time::Instant::now() >= next_path_log {
                        next_path_log += std::time::Duration::from_secs(1);
                        let p = self.conn.stats().path;
                        debug!(
                            rtt_ms = p.rtt.as_secs_f64() * 1e3,
                            cwnd = p.cwnd,
                            congestion_events = p.congestion_events,
                            lost_packets = p.lost_packets,
                            sent_packets = p.sent_packets,
                            "QUIC path to the coordinator"
                        );
                    }
                    match liveness.poll(now) {
                        Some(LivenessEvent::SendHeartbeat) => self.heartbeat(),
                        Some(LivenessEvent::TimedOut) => {
                            let silent_ms = liveness.silence_us(now) / 1000;
                            self.conn.close(VarInt::from_u32(close_code::TIMED_OUT), b"coordinator silent");
                            return End::Lost(format!("nothing heard from the coordinator for {silent_ms} ms"));
                        }
                        None => {}
                    }
                    if tokio::time::Instant::now() >= next_ping {
                        self.ping();
                        let iv = if fast_pings > 0 {
                            fast_pings -= 1;
                            TICK
                        } else {
                            self.cfg.clock_interval
                        };
                        next_ping = tokio::time::Instant::now() + iv;
                    }
                    while self.tasks.try_join_next().is_some() {}
                    self.reap_keyframe_streams();
                }
            }
        }
    }

    fn update_udp_stats(&self) {
        let s = self.conn.stats();
        let c = &self.shared.counters;
        c.udp_bytes_up
            .store(self.udp_base.0 + s.udp_tx.bytes, Ordering::Relaxed);
        c.udp_bytes_down
            .store(self.udp_base.1 + s.udp_rx.bytes, Ordering::Relaxed);
    }

    fn datagram_budget(&self) -> usize {
        self.conn
            .max_datagram_size()
            .unwrap_or(0)
            .min(proto::DEFAULT_DATAGRAM_BUDGET)
    }

    /// Send a link-internal datagram (ping, heartbeat); failures are not interesting.
    fn send_raw_datagram(&self, msg: &Message) -> bool {
        let bytes = proto::encode(msg);
        let n = bytes.len() as u64;
        if self.conn.send_datagram(Bytes::from(bytes)).is_ok() {
            add(&self.shared.counters.bytes_up, n);
            true
        } else {
            false
        }
    }

    fn ping(&mut self) {
        self.ping_seq = self.ping_seq.wrapping_add(1);
        let msg = Message::ClockPing(proto::ClockPing {
            seq: self.ping_seq,
            t1_us: self.shared.local.now_us(),
        });
        if self.send_raw_datagram(&msg) {
            add(&self.shared.counters.clock_pings, 1);
        }
    }

    fn heartbeat(&self) {
        let msg = Message::Heartbeat(proto::Heartbeat {
            site: self.site,
            time_us: self.shared.coordinator_now_us(),
        });
        if self.send_raw_datagram(&msg) {
            add(&self.shared.counters.heartbeats_sent, 1);
        }
    }

    fn on_datagram(&mut self, d: Bytes) {
        let c = &self.shared.counters;
        add(&c.bytes_down, d.len() as u64);
        let msg = match proto::decode(&d) {
            Ok(m) => m,
            Err(e) => {
                add(&c.malformed, 1);
                if self.malformed_logged < 5 {
                    self.malformed_logged += 1;
                    warn!(len = d.len(), error = %e, "malformed datagram from the coordinator dropped");
                }
                return;
            }
        };
        match msg {
            Message::ClockPong(p) => {
                let t4 = self.shared.local.now_us();
                // Only answers to our own pings of this connection count.
                if p.seq == 0 || p.seq > self.ping_seq || p.t1_us > t4 {
                    add(&c.malformed, 1);
                    return;
                }
                add(&c.clock_pongs, 1);
                self.shared
                    .clock()
                    .add_sample(ClockSample::from_pong(&p, t4));
            }
            Message::Heartbeat(_) => {}
            m => {
                add(&c.datagrams_received, 1);
                self.ev.send(LinkEvent::Message(m));
            }
        }
    }

    /// Queue one control frame for the writer.
    fn send_control(&self, msg: &Message) {
        let Some(tx) = &self.ctrl else { return };
        let frame = proto::encode_frame(msg);
        add(&self.shared.counters.bytes_up, frame.len() as u64);
        add(&self.shared.counters.control_sent, 1);
        let _ = tx.send(Bytes::from(frame));
    }

    /// Send everything queued by the site.
    fn drain(&mut self) {
        let (control, datagrams, keyframes) = {
            let mut o = self.shared.outbox();
            (
                std::mem::take(&mut o.control),
                std::mem::take(&mut o.datagrams),
                std::mem::take(&mut o.keyframes),
            )
        };
        // Senders fill in their own site id (the site's session knows it); the
        // coordinator checks it.
        for m in control {
            self.send_control(&m);
        }
        for m in datagrams {
            self.send_datagram(m);
        }
        for kf in keyframes {
            self.send_keyframe(kf);
        }
    }

    fn send_datagram(&self, msg: Message) {
        let c = &self.shared.counters;
        let max = self.datagram_budget();
        let bytes = match proto::encode_datagram(&msg, max) {
            Ok(b) => b,
            Err(e) => {
                debug!(%e, "too large for a datagram; sending on the control stream");
                add(&c.datagram_fallbacks, 1);
                self.send_control(&msg);
                return;
            }
        };
        let n = bytes.len() as u64;
        match self.conn.send_datagram(Bytes::from(bytes)) {
            Ok(()) => {
                add(&c.bytes_up, n);
                add(&c.datagrams_sent, 1);
            }
            Err(quinn::SendDatagramError::TooLarge) => {
                add(&c.datagram_fallbacks, 1);
                self.send_control(&msg);
            }
            Err(e) => {
                add(&c.datagrams_dropped, 1);
                debug!(error = %e, kind = msg.kind(), "datagram not sent");
            }
        }
    }

    /// Sends a keyframe on a stream of its own as the keyframe-stream scheduler decides
    /// ([`proto::KeyframeStreams`]: up to eight per region in flight, newest wins,
    /// stalled ones reset).
    fn send_keyframe(&mut self, kf: RegionKeyframe) {
        let region = kf.region;
        let frame = Bytes::from(proto::encode_frame(&Message::Keyframe(kf)));
        self.reap_keyframe_streams();
        let stall = proto::stall_time(self.conn.rtt());
        let actions = self
            .streams
            .submit(region, frame, std::time::Instant::now(), stall);
        self.execute(actions);
    }

    /// Resets stalled streams that have a newer keyframe behind them and sends waiting
    /// keyframes once a stream is free.
    fn pump_held_keyframes(&mut self) {
        self.reap_keyframe_streams();
        let stall = proto::stall_time(self.conn.rtt());
        let actions = self.streams.poll(std::time::Instant::now(), stall);
        self.execute(actions);
    }

    /// Tells the scheduler about keyframe streams whose task ended.
    fn reap_keyframe_streams(&mut self) {
        let ended: Vec<(StreamToken, RegionId)> = self
            .cancels
            .iter()
            .filter(|(_, (_, c))| c.is_closed())
            .map(|(t, (r, _))| (*t, *r))
            .collect();
        for (token, region) in ended {
            self.cancels.remove(&token);
            self.streams.finished(region, token);
        }
    }

    fn execute(&mut self, actions: Vec<StreamAction<Bytes>>) {
        let waiting_replaced = self.streams.superseded_waiting();
        add(
            &self.shared.counters.keyframes_superseded,
            waiting_replaced - self.superseded_counted,
        );
        self.superseded_counted = waiting_replaced;
        for a in actions {
            match a {
                StreamAction::Open {
                    token,
                    region,
                    payload,
                } => {
                    let (tx, rx) = oneshot::channel();
                    self.cancels.insert(token, (region, tx));
                    add(&self.shared.counters.bytes_up, payload.len() as u64);
                    self.tasks.spawn(keyframe_stream(
                        self.conn.clone(),
                        payload,
                        rx,
                        self.shared.clone(),
                    ));
                }
                StreamAction::Reset { token, .. } => {
                    if let Some((_, cancel)) = self.cancels.remove(&token) {
                        let _ = cancel.send(());
                    }
                }
            }
        }
    }

    /// Send Leave (after anything still queued), finish the control stream and wait for
    /// the coordinator to close the connection.
    async fn leave(&mut self, reason: String) -> End {
        self.drain();
        self.send_control(&Message::Leave(proto::Leave {
            site: self.site,
            reason,
        }));
        // Dropping the sender lets the writer finish the stream after the Leave.
        self.ctrl = None;
        let _ = tokio::time::timeout(LEAVE_WAIT, self.conn.closed()).await;
        self.conn
            .close(VarInt::from_u32(close_code::NORMAL), b"site left");
        End::Closed
    }
}

async fn control_writer(mut send: SendStream, mut rx: mpsc::UnboundedReceiver<Bytes>) {
    while let Some(b) = rx.recv().await {
        if let Err(e) = send.write_chunk(b).await {
            debug!(error = %e, "control stream write failed");
            return;
        }
    }
    let _ = send.finish();
    // Keep the stream (and its unacknowledged data) alive until the peer has it.
    let _ = send.stopped().await;
}

async fn control_reader(
    mut recv: RecvStream,
    mut dec: FrameDecoder,
    shared: Arc<Shared>,
    tx: mpsc::UnboundedSender<Inbound>,
) {
    let c = &shared.counters;
    loop {
        loop {
            match dec.next_message() {
                Ok(Some(m)) => {
                    add(&c.control_received, 1);
                    let _ = tx.send(Inbound::Msg(m));
                }
                Ok(None) => break,
                Err(FrameError::Decode(e)) => {
                    add(&c.malformed, 1);
                    warn!(error = %e, "undecodable control frame from the coordinator dropped");
                }
                Err(e) => {
                    add(&c.malformed, 1);
                    warn!(error = %e, "control stream framing broken");
                    let _ = tx.send(Inbound::Broken(e.to_string()));
                    return;
                }
            }
        }
        match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(chunk)) => {
                add(&c.bytes_down, chunk.bytes.len() as u64);
                dec.push(&chunk.bytes);
            }
            Ok(None) => {
                let why = match dec.finish() {
                    Ok(()) => "finished by the coordinator".to_string(),
                    Err(e) => {
                        add(&c.malformed, 1);
                        format!("finished mid-frame: {e}")
                    }
                };
                let _ = tx.send(Inbound::Ended(why));
                return;
            }
            Err(e) => {
                let _ = tx.send(Inbound::Ended(e.to_string()));
                return;
            }
        }
    }
}

async fn uni_acceptor(conn: Connection, shared: Arc<Shared>, ev: Events, max_frame: usize) {
    let mut readers = JoinSet::new();
    while let Ok(recv) = conn.accept_uni().await {
        readers.spawn(read_uni(recv, shared.clone(), ev.clone(), max_frame));
        while readers.try_join_next().is_some() {}
    }
}

/// Read one keyframe or snapshot stream.
async fn read_uni(mut recv: RecvStream, shared: Arc<Shared>, ev: Events, max_frame: usize) {
    let c = &shared.counters;
    let bad = |recv: &mut RecvStream, what: String| {
        add(&c.malformed, 1);
        warn!("{what}; stream from the coordinator dropped");
        let _ = recv.stop(VarInt::from_u32(stream_code::MALFORMED));
    };
    let limit = max_frame + proto::codec::FRAME_HEADER_LEN;
    let buf = match tokio::time::timeout(STREAM_READ_TIMEOUT, recv.read_to_end(limit)).await {
        Ok(Ok(b)) => b,
        Ok(Err(quinn::ReadToEndError::TooLong)) => {
            return bad(&mut recv, format!("stream longer than {limit} bytes"));
        }
        Ok(Err(quinn::ReadToEndError::Read(quinn::ReadError::Reset(code)))) => {
            debug!(%code, "incoming stream reset (superseded)");
            return;
        }
        Ok(Err(e)) => {
            debug!(error = %e, "incoming stream aborted");
            return;
        }
        Err(_) => return bad(&mut recv, "stream too slow".into()),
    };
    add(&c.bytes_down, buf.len() as u64);
    let mut dec = FrameDecoder::new(max_frame);
    dec.push(&buf);
    let msg = match (dec.next_message(), dec.finish()) {
        (Ok(Some(m)), Ok(())) => m,
        (Ok(Some(_)), Err(e)) => return bad(&mut recv, format!("trailing data: {e}")),
        (Ok(None), Err(e)) | (Err(e), _) => {
            return bad(&mut recv, format!("bad stream ({} bytes): {e}", buf.len()));
        }
        (Ok(None), Ok(())) => return bad(&mut recv, "empty stream".into()),
    };
    match &msg {
        Message::Keyframe(_) => add(&c.keyframes_received, 1),
        Message::Snapshot(_) => add(&c.snapshots_received, 1),
        other => {
            return bad(
                &mut recv,
                format!("unexpected {} on a stream", other.kind()),
            );
        }
    }
    ev.send(LinkEvent::Message(msg));
}

/// Send one keyframe frame on its own stream and wait for its acknowledgement; reset the
/// stream with `SUPERSEDED` if `cancel` fires first.
async fn keyframe_stream(
    conn: Connection,
    frame: Bytes,
    cancel: oneshot::Receiver<()>,
    shared: Arc<Shared>,
) {
    let c = &shared.counters;
    // A dropped sender (session over) is not a cancellation.
    let cancelled = async move {
        if cancel.await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    tokio::pin!(cancelled);
    let mut s = tokio::select! {
        s = conn.open_uni() => match s {
            Ok(s) => s,
            Err(e) => {
                debug!(error = %e, "cannot open a keyframe stream");
                return;
            }
        },
        _ = &mut cancelled => {
            add(&c.keyframes_superseded, 1);
            return;
        }
    };
    let _ = s.set_priority(KEYFRAME_PRIORITY);
    let result = {
        let write = async {
            s.write_chunk(frame).await.map_err(|e| e.to_string())?;
            s.finish().map_err(|e| e.to_string())?;
            match s.stopped().await {
                Ok(None) => Ok(()),
                Ok(Some(code)) => Err(format!("coordinator stopped the stream (code {code})")),
                Err(e) => Err(e.to_string()),
            }
        };
        tokio::select! {
            r = write => Some(r),
            _ = &mut cancelled => None,
        }
    };
    match result {
        Some(Ok(())) => add(&c.keyframes_sent, 1),
        Some(Err(e)) => debug!(error = %e, "keyframe stream failed"),
        None => {
            let _ = s.reset(VarInt::from_u32(stream_code::SUPERSEDED));
            add(&c.keyframes_superseded, 1);
        }
    }
}
