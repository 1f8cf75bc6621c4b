//! User-space UDP relay applying an impairment per direction.
//!
//! Clients send to `listen`; each client source address gets its own upstream socket
//! (connected to `upstream`, like a NAT mapping) and its own pair of seeded models, so every
//! client sees an independent link (its own rate cap, its own loss process). *Up* is
//! client → upstream, *down* is upstream → client. All models share the relay's epoch, so a
//! scheduled outage happens at the same wall-clock time for every client.

use std::collections::HashMap;
use std::fmt;
use std::io;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use serde::{Deserialize, Serialize};
use tokio::net::UdpSocket;
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tracing::{debug, info, warn};

use crate::args::NetemArgs;
use crate::model::{Counters, Impairment, ImpairmentConfig, Outage, Verdict};
use crate::sched::{DirectionStats, Job, LinkStats, Scheduler, Sink, derive_seed, micros_since};

/// Relay configuration.
#[derive(Debug, Clone)]
pub struct RelayConfig {
    /// Address clients send to (port 0 picks a free one; see [`RelayHandle::local_addr`]).
    pub listen: SocketAddr,
    /// The real server.
    pub upstream: SocketAddr,
    /// Client → upstream impairment.
    pub up: ImpairmentConfig,
    /// Upstream → client impairment.
    pub down: ImpairmentConfig,
    pub seed: u64,
    /// Forget a client (and close its upstream socket) after this long without traffic.
    pub client_timeout: Duration,
}

impl RelayConfig {
    /// Pass-through relay.
    pub fn new(listen: SocketAddr, upstream: SocketAddr) -> Self {
        Self {
            listen,
            upstream,
            up: ImpairmentConfig::none(),
            down: ImpairmentConfig::none(),
            seed: 1,
            client_timeout: Duration::from_secs(120),
        }
    }

    /// Same impairment both ways.
    pub fn symmetric(mut self, config: ImpairmentConfig) -> Self {
        self.up = config.clone();
        self.down = config;
        self
    }

    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    pub fn from_args(args: &NetemArgs) -> anyhow::Result<Self> {
        let (up, down) = args.impair.configs().context("netem impairment flags")?;
        anyhow::ensure!(
            args.client_timeout.is_finite() && args.client_timeout > 0.0,
            "--client-timeout must be > 0 s"
        );
        Ok(Self {
            listen: args.listen,
            upstream: args.upstream,
            up,
            down,
            seed: args.impair.seed,
            client_timeout: Duration::from_secs_f64(args.client_timeout),
        })
    }
}

/// Counters of a relay, aggregated over all clients (past and present).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct RelayCounters {
    /// Client → upstream.
    pub up: DirectionStats,
    /// Upstream → client.
    pub down: DirectionStats,
    /// Clients currently mapped.
    pub clients: usize,
    /// Clients ever mapped.
    pub clients_total: u64,
}

impl fmt::Display for RelayCounters {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "netem relay: {} clients ({} active)",
            self.clients_total, self.clients
        )?;
        writeln!(f, "  up   (client -> upstream): {}", self.up)?;
        write!(f, "  down (upstream -> client): {}", self.down)
    }
}

/// The relay (see [`Relay::spawn`]).
pub struct Relay;

struct Session {
    sock: Arc<UdpSocket>,
    up: Mutex<Impairment>,
    down: Mutex<Impairment>,
    last_seen_us: AtomicU64,
    task: Mutex<Option<JoinHandle<()>>>,
}

struct Shared {
    epoch: Instant,
    upstream: SocketAddr,
    listen: Arc<UdpSocket>,
    configs: Mutex<(ImpairmentConfig, ImpairmentConfig)>,
    sessions: Mutex<HashMap<SocketAddr, Arc<Session>>>,
    retired: Mutex<(Counters, Counters)>,
    up_stats: Arc<LinkStats>,
    down_stats: Arc<LinkStats>,
    seed: u64,
    clients_total: AtomicU64,
    sched: Scheduler,
    client_timeout: Duration,
}

/// A running relay. Dropping it stops the relay (without waiting); [`RelayHandle::shutdown`]
/// stops it and returns the final counters.
pub struct RelayHandle {
    /// The address clients should send to.
    pub local_addr: SocketAddr,
    shared: Arc<Shared>,
    stop: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
}

impl Relay {
    /// Bind `config.listen` and start relaying. Must be called inside a tokio runtime.
    pub async fn spawn(config: RelayConfig) -> io::Result<RelayHandle> {
        for c in [&config.up, &config.down] {
            c.validate()
                .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        }
        let listen = Arc::new(UdpSocket::bind(config.listen).await?);
        let local_addr = listen.local_addr()?;
        let (stop, stop_rx) = watch::channel(false);
        let (sched, sched_task) = Scheduler::spawn(stop_rx.clone());
        let shared = Arc::new(Shared {
            epoch: Instant::now(),
            upstream: config.upstream,
            listen,
            configs: Mutex::new((config.up, config.down)),
            sessions: Mutex::new(HashMap::new()),
            retired: Mutex::new(Default::default()),
            up_stats: Arc::default(),
            down_stats: Arc::default(),
            seed: config.seed,
            clients_total: AtomicU64::new(0),
            sched,
            client_timeout: config.client_timeout,
        });
        let main = tokio::spawn(client_loop(shared.clone(), stop_rx.clone()));
        let sweeper = tokio::spawn(sweep_loop(shared.clone(), stop_rx));
        info!(%local_addr, upstream = %config.upstream, "netem relay started");
        Ok(RelayHandle {
            local_addr,
            shared,
            stop,
            tasks: vec![main, sweeper, sched_task],
        })
    }
}

impl RelayHandle {
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// Time since the relay started (the clock of scheduled outages).
    pub fn elapsed(&self) -> Duration {
        self.shared.epoch.elapsed()
    }

    /// Current counters, summed over all clients.
    pub fn counters(&self) -> RelayCounters {
        self.shared.counters()
    }

    /// Replace the impairment of both directions for all current and future clients
    /// (model state, RNG and counters are kept).
    pub fn set_impairment(&self, up: ImpairmentConfig, down: ImpairmentConfig) {
        let sessions = self.shared.sessions.lock().unwrap();
        for s in sessions.values() {
            s.up.lock().unwrap().set_config(up.clone());
            s.down.lock().unwrap().set_config(down.clone());
        }
        *self.shared.configs.lock().unwrap() = (up, down);
    }

    /// Start a 100 % loss outage in both directions now, lasting `duration`.
    pub fn start_outage(&self, duration: Duration) {
        let outage = Some(Outage {
            start_s: self.elapsed().as_secs_f64(),
            duration_s: duration.as_secs_f64(),
        });
        let (mut up, mut down) = self.shared.configs.lock().unwrap().clone();
        up.outage = outage;
        down.outage = outage;
        self.set_impairment(up, down);
    }

    /// Stop the relay, wait for its tasks and return the final counters. Datagrams still
    /// waiting for their release time are discarded (reported as `pending`).
    pub async fn shutdown(mut self) -> RelayCounters {
        self.stop.send_replace(true);
        for t in self.tasks.drain(..) {
            let _ = t.await;
        }
        let tasks: Vec<_> = {
            let sessions = self.shared.sessions.lock().unwrap();
            sessions
                .values()
                .filter_map(|s| s.task.lock().unwrap().take())
                .collect()
        };
        for t in tasks {
            let _ = t.await;
        }
        let c = self.shared.counters();
        info!("netem relay stopped");
        c
    }
}

impl Drop for RelayHandle {
    fn drop(&mut self) {
        self.stop.send_replace(true);
    }
}

impl Shared {
    fn counters(&self) -> RelayCounters {
        let sessions = self.sessions.lock().unwrap();
        let (mut up, mut down) = *self.retired.lock().unwrap();
        for s in sessions.values() {
            up.add(&s.up.lock().unwrap().counters());
            down.add(&s.down.lock().unwrap().counters());
        }
        RelayCounters {
            up: self.up_stats.snapshot(up),
            down: self.down_stats.snapshot(down),
            clients: sessions.len(),
            clients_total: self.clients_total.load(Relaxed),
        }
    }

    async fn session(
        self: &Arc<Self>,
        client: SocketAddr,
        stop: &watch::Receiver<bool>,
    ) -> io::Result<Arc<Session>> {
        if let Some(s) = self.sessions.lock().unwrap().get(&client) {
            return Ok(s.clone());
        }
        let bind: SocketAddr = if self.upstream.is_ipv4() {
            (Ipv4Addr::UNSPECIFIED, 0).into()
        } else {
            (Ipv6Addr::UNSPECIFIED, 0).into()
        };
        let sock = UdpSocket::bind(bind).await?;
        sock.connect(self.upstream).await?;
        let n = self.clients_total.fetch_add(1, Relaxed);
        let (up, down) = self.configs.lock().unwrap().clone();
        let session = Arc::new(Session {
            sock: Arc::new(sock),
            up: Mutex::new(Impairment::new(up, derive_seed(self.seed, 2 * n))),
            down: Mutex::new(Impairment::new(down, derive_seed(self.seed, 2 * n + 1))),
            last_seen_us: AtomicU64::new(micros_since(self.epoch)),
            task: Mutex::new(None),
        });
        let task = tokio::spawn(upstream_loop(
            self.clone(),
            session.clone(),
            client,
            stop.clone(),
        ));
        *session.task.lock().unwrap() = Some(task);
        debug!(%client, upstream_local = ?session.sock.local_addr().ok(), "netem: new client");
        self.sessions
            .lock()
            .unwrap()
            .insert(client, session.clone());
        Ok(session)
    }
}

fn schedule(shared: &Shared, verdict: Verdict, data: &[u8], sink: Sink, stats: &Arc<LinkStats>) {
    if let Verdict::Deliver { at_us } = verdict {
        for at in at_us {
            shared.sched.push(Job {
                at: shared.epoch + Duration::from_micros(at),
                data: data.to_vec(),
                sink: sink.clone(),
                stats: stats.clone(),
            });
        }
    }
}

/// Client → upstream.
async fn client_loop(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let mut buf = vec![0u8; 65_536];
    loop {
        let (n, client) = tokio::select! {
            _ = stop.changed() => break,
            r = shared.listen.recv_from(&mut buf) => match r {
                Ok(x) => x,
                Err(e) => {
                    debug!(error = %e, "netem: listen socket receive error");
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                }
            },
        };
        let session = match shared.session(client, &stop).await {
            Ok(s) => s,
            Err(e) => {
                warn!(%client, error = %e, "netem: cannot open upstream socket; packet dropped");
                shared.up_stats.error();
                continue;
            }
        };
        let now = micros_since(shared.epoch);
        session.last_seen_us.store(now, Relaxed);
        let verdict = session.up.lock().unwrap().on_packet(now, n);
        let sink = Sink::Udp {
            sock: session.sock.clone(),
            dest: None,
        };
        schedule(&shared, verdict, &buf[..n], sink, &shared.up_stats);
    }
}

/// Upstream → one client.
async fn upstream_loop(
    shared: Arc<Shared>,
    session: Arc<Session>,
    client: SocketAddr,
    mut stop: watch::Receiver<bool>,
) {
    let mut buf = vec![0u8; 65_536];
    let sink = Sink::Udp {
        sock: shared.listen.clone(),
        dest: Some(client),
    };
    loop {
        let n = tokio::select! {
            _ = stop.changed() => break,
            r = session.sock.recv(&mut buf) => match r {
                Ok(n) => n,
                Err(e) => {
                    // e.g. ECONNREFUSED after an ICMP port unreachable from the upstream.
                    debug!(%client, error = %e, "netem: upstream socket receive error");
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                }
            },
        };
        let now = micros_since(shared.epoch);
        session.last_seen_us.store(now, Relaxed);
        let verdict = session.down.lock().unwrap().on_packet(now, n);
        schedule(
            &shared,
            verdict,
            &buf[..n],
            sink.clone(),
            &shared.down_stats,
        );
    }
}

/// Forget idle clients.
async fn sweep_loop(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let period =
        (shared.client_timeout / 4).clamp(Duration::from_millis(50), Duration::from_secs(5));
    let timeout_us = shared.client_timeout.as_micros() as u64;
    loop {
        tokio::select! {
            _ = stop.changed() => break,
            _ = tokio::time::sleep(period) => {}
        }
        let now = micros_since(shared.epoch);
        let mut sessions = shared.sessions.lock().unwrap();
        let idle: Vec<SocketAddr> = sessions
            .iter()
            .filter(|(_, s)| now.saturating_sub(s.last_seen_us.load(Relaxed)) > timeout_us)
            .map(|(a, _)| *a)
            .collect();
        for client in idle {
            if let Some(s) = sessions.remove(&client) {
                if let Some(t) = s.task.lock().unwrap().take() {
                    t.abort();
                }
                let mut retired = shared.retired.lock().unwrap();
                retired.0.add(&s.up.lock().unwrap().counters());
                retired.1.add(&s.down.lock().unwrap().counters());
                debug!(%client, "netem: client timed out");
            }
        }
    }
}

/// `cosurg netem`: run a relay until Ctrl-C or `--seconds`, then print the counters.
pub async fn run_cli(args: NetemArgs) -> anyhow::Result<()> {
    let config = RelayConfig::from_args(&args)?;
    info!(up = ?config.up, down = ?config.down, "netem impairment");
    let relay = Relay::spawn(config)
        .await
        .with_context(|| format!("netem: cannot listen on {}", args.listen))?;
    // Scripts read these lines (e.g. with `--listen 127.0.0.1:0`).
    println!("netem listening: {}", relay.local_addr());
    println!("netem upstream: {}", args.upstream);
    match args.seconds {
        Some(s) => {
            anyhow::ensure!(s.is_finite() && s >= 0.0, "--seconds must be ≥ 0");
            tokio::select! {
                _ = tokio::time::sleep(Duration::from_secs_f64(s)) => {}
                r = tokio::signal::ctrl_c() => r.context("waiting for Ctrl-C")?,
            }
        }
        None => tokio::signal::ctrl_c()
            .await
            .context("waiting for Ctrl-C")?,
    }
    let counters = relay.shutdown().await;
    println!("{counters}");
    Ok(())
}
