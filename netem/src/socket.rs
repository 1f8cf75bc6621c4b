//! In-process impaired UDP socket for quinn.
//!
//! [`ImpairedSocket`] implements [`quinn::AsyncUdpSocket`] over a plain tokio UDP socket.
//! Outgoing datagrams (*up*) go through one model, incoming ones (*down*) through another;
//! released datagrams are sent / handed to quinn by the release scheduler. GSO and GRO are off
//! (`max_transmit_segments() == 1`), so one quinn transmit is one packet. `try_send` never
//! blocks: the emulated link accepts every packet and the model decides (rate-cap queue
//! overflow is a drop, as on a real bottleneck). ECN marks are not carried.

use std::fmt;
use std::io::{self, IoSliceMut};
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, ready};
use std::time::Duration;

use quinn::udp::{RecvMeta, Transmit};
use quinn::{AsyncUdpSocket, Endpoint, EndpointConfig, ServerConfig, TokioRuntime, UdpPoller};
use serde::{Deserialize, Serialize};
use tokio::net::UdpSocket;
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;

use crate::model::{Impairment, ImpairmentConfig, Outage, Verdict};
use crate::sched::{
    Datagram, DirectionStats, Job, LinkStats, Scheduler, Sink, derive_seed, micros_since,
};

/// Counters of an impaired socket.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LinkCounters {
    /// Outgoing.
    pub up: DirectionStats,
    /// Incoming.
    pub down: DirectionStats,
}

impl fmt::Display for LinkCounters {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "  up   (outgoing): {}", self.up)?;
        write!(f, "  down (incoming): {}", self.down)
    }
}

struct LinkInner {
    epoch: Instant,
    up: Mutex<Impairment>,
    down: Mutex<Impairment>,
    up_stats: Arc<LinkStats>,
    down_stats: Arc<LinkStats>,
}

/// Control and counters of an impaired socket (cheap to clone).
#[derive(Clone)]
pub struct ImpairedLink(Arc<LinkInner>);

impl fmt::Debug for ImpairedLink {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ImpairedLink").finish_non_exhaustive()
    }
}

impl ImpairedLink {
    pub fn counters(&self) -> LinkCounters {
        let i = &self.0;
        LinkCounters {
            up: i.up_stats.snapshot(i.up.lock().unwrap().counters()),
            down: i.down_stats.snapshot(i.down.lock().unwrap().counters()),
        }
    }

    /// Time since the socket was created (the clock of scheduled outages).
    pub fn elapsed(&self) -> Duration {
        self.0.epoch.elapsed()
    }

    /// Replace both impairments (model state, RNG and counters are kept).
    pub fn set_impairment(&self, up: ImpairmentConfig, down: ImpairmentConfig) {
        self.0.up.lock().unwrap().set_config(up);
        self.0.down.lock().unwrap().set_config(down);
    }

    /// Start a 100 % loss outage in both directions now, lasting `duration`.
    pub fn start_outage(&self, duration: Duration) {
        let outage = Some(Outage {
            start_s: self.elapsed().as_secs_f64(),
            duration_s: duration.as_secs_f64(),
        });
        for m in [&self.0.up, &self.0.down] {
            let mut m = m.lock().unwrap();
            let mut c = m.config().clone();
            c.outage = outage;
            m.set_config(c);
        }
    }
}

/// A [`quinn::AsyncUdpSocket`] whose traffic goes through the impairment models.
pub struct ImpairedSocket {
    io: Arc<UdpSocket>,
    local: SocketAddr,
    link: ImpairedLink,
    sched: Scheduler,
    rx: Mutex<mpsc::UnboundedReceiver<Datagram>>,
    stop: watch::Sender<bool>,
}

impl fmt::Debug for ImpairedSocket {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ImpairedSocket")
            .field("local", &self.local)
            .finish_non_exhaustive()
    }
}

impl ImpairedSocket {
    /// Bind `bind` and start the receive pump and release scheduler. Must be called inside a
    /// tokio runtime. `up` applies to outgoing datagrams, `down` to incoming ones.
    pub fn bind(
        bind: SocketAddr,
        up: ImpairmentConfig,
        down: ImpairmentConfig,
        seed: u64,
    ) -> io::Result<(Self, ImpairedLink)> {
        for c in [&up, &down] {
            c.validate()
                .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        }
        let std_sock = std::net::UdpSocket::bind(bind)?;
        std_sock.set_nonblocking(true)?;
        let io = Arc::new(UdpSocket::from_std(std_sock)?);
        let local = io.local_addr()?;
        let link = ImpairedLink(Arc::new(LinkInner {
            epoch: Instant::now(),
            up: Mutex::new(Impairment::new(up, derive_seed(seed, 0))),
            down: Mutex::new(Impairment::new(down, derive_seed(seed, 1))),
            up_stats: Arc::default(),
            down_stats: Arc::default(),
        }));
        let (stop, stop_rx) = watch::channel(false);
        let (sched, _task) = Scheduler::spawn(stop_rx.clone());
        let (tx, rx) = mpsc::unbounded_channel();
        tokio::spawn(recv_pump(
            io.clone(),
            link.clone(),
            sched.clone(),
            tx,
            stop_rx,
        ));
        Ok((
            Self {
                io,
                local,
                link: link.clone(),
                sched,
                rx: Mutex::new(rx),
                stop,
            },
            link,
        ))
    }
}

impl Drop for ImpairedSocket {
    fn drop(&mut self) {
        self.stop.send_replace(true);
    }
}

async fn recv_pump(
    io: Arc<UdpSocket>,
    link: ImpairedLink,
    sched: Scheduler,
    tx: mpsc::UnboundedSender<Datagram>,
    mut stop: watch::Receiver<bool>,
) {
    let mut buf = vec![0u8; 65_536];
    let inner = &link.0;
    loop {
        let (n, from) = tokio::select! {
            _ = stop.changed() => break,
            r = io.recv_from(&mut buf) => match r {
                Ok(x) => x,
                Err(e) => {
                    tracing::debug!(error = %e, "netem socket: receive error");
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                }
            },
        };
        let now = micros_since(inner.epoch);
        let verdict = inner.down.lock().unwrap().on_packet(now, n);
        if let Verdict::Deliver { at_us } = verdict {
            for at in at_us {
                sched.push(Job {
                    at: inner.epoch + Duration::from_micros(at),
                    data: buf[..n].to_vec(),
                    sink: Sink::Chan {
                        tx: tx.clone(),
                        from,
                    },
                    stats: inner.down_stats.clone(),
                });
            }
        }
    }
}

#[derive(Debug)]
struct AlwaysWritable;

impl UdpPoller for AlwaysWritable {
    fn poll_writable(self: Pin<&mut Self>, _cx: &mut Context) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

impl AsyncUdpSocket for ImpairedSocket {
    fn create_io_poller(self: Arc<Self>) -> Pin<Box<dyn UdpPoller>> {
        Box::pin(AlwaysWritable)
    }

    fn try_send(&self, transmit: &Transmit) -> io::Result<()> {
        let inner = &self.link.0;
        let seg = transmit
            .segment_size
            .unwrap_or(transmit.contents.len())
            .max(1);
        let now = micros_since(inner.epoch);
        for chunk in transmit.contents.chunks(seg) {
            let verdict = inner.up.lock().unwrap().on_packet(now, chunk.len());
            if let Verdict::Deliver { at_us } = verdict {
                for at in at_us {
                    self.sched.push(Job {
                        at: inner.epoch + Duration::from_micros(at),
                        data: chunk.to_vec(),
                        sink: Sink::Udp {
                            sock: self.io.clone(),
                            dest: Some(transmit.destination),
                        },
                        stats: inner.up_stats.clone(),
                    });
                }
            }
        }
        Ok(())
    }

    fn poll_recv(
        &self,
        cx: &mut Context,
        bufs: &mut [IoSliceMut<'_>],
        meta: &mut [RecvMeta],
    ) -> Poll<io::Result<usize>> {
        let mut rx = self.rx.lock().unwrap();
        let max = bufs.len().min(meta.len());
        let mut count = 0;
        while count < max {
            let d = if count == 0 {
                match ready!(rx.poll_recv(cx)) {
                    Some(d) => d,
                    None => {
                        return Poll::Ready(Err(io::Error::new(
                            io::ErrorKind::BrokenPipe,
                            "impaired socket receive pump stopped",
                        )));
                    }
                }
            } else {
                match rx.try_recv() {
                    Ok(d) => d,
                    Err(_) => break,
                }
            };
            let len = d.data.len().min(bufs[count].len());
            bufs[count][..len].copy_from_slice(&d.data[..len]);
            meta[count] = RecvMeta {
                addr: d.from,
                len,
                stride: len,
                ecn: None,
                dst_ip: None,
            };
            count += 1;
        }
        Poll::Ready(Ok(count))
    }

    fn local_addr(&self) -> io::Result<SocketAddr> {
        Ok(self.local)
    }

    fn max_transmit_segments(&self) -> usize {
        1
    }

    fn max_receive_segments(&self) -> usize {
        1
    }
}

/// A quinn endpoint whose UDP traffic goes through seeded impairment models: `up` for
/// outgoing packets, `down` for incoming ones. Must be called inside a tokio runtime.
pub fn impaired_endpoint(
    bind: SocketAddr,
    server_config: Option<ServerConfig>,
    up: ImpairmentConfig,
    down: ImpairmentConfig,
    seed: u64,
) -> io::Result<(Endpoint, ImpairedLink)> {
    let (sock, link) = ImpairedSocket::bind(bind, up, down, seed)?;
    let endpoint = Endpoint::new_with_abstract_socket(
        EndpointConfig::default(),
        server_config,
        Arc::new(sock),
        Arc::new(TokioRuntime),
    )?;
    Ok((endpoint, link))
}
