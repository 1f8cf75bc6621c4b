//! Release scheduler shared by the relay and the impaired socket: a binary heap of pending
//! datagrams ordered by release time, drained by one tokio task with `sleep_until`
//! (tokio's timer has 1 ms granularity, so packets leave up to ≈ 1 ms late).

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::fmt;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

use serde::{Deserialize, Serialize};
use tokio::net::UdpSocket;
use tokio::sync::{mpsc, watch};
use tokio::time::{Instant, sleep_until};

use crate::model::Counters;

/// A received datagram handed to an in-process consumer.
#[derive(Debug)]
pub(crate) struct Datagram {
    pub data: Vec<u8>,
    pub from: SocketAddr,
}

/// Where a released datagram goes.
#[derive(Debug, Clone)]
pub(crate) enum Sink {
    /// Send on a UDP socket; `dest: None` means the socket is connected.
    Udp {
        sock: Arc<UdpSocket>,
        dest: Option<SocketAddr>,
    },
    /// Hand to an in-process receiver.
    Chan {
        tx: mpsc::UnboundedSender<Datagram>,
        from: SocketAddr,
    },
}

#[derive(Debug)]
pub(crate) struct Job {
    pub at: Instant,
    pub data: Vec<u8>,
    pub sink: Sink,
    pub stats: Arc<LinkStats>,
}

struct Entry {
    at: Instant,
    seq: u64,
    job: Job,
}

impl PartialEq for Entry {
    fn eq(&self, o: &Self) -> bool {
        (self.at, self.seq) == (o.at, o.seq)
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Entry {
    // Reversed: BinaryHeap is a max-heap, we want the earliest release on top.
    fn cmp(&self, o: &Self) -> Ordering {
        (o.at, o.seq).cmp(&(self.at, self.seq))
    }
}

/// Live I/O statistics of one direction (the model's counters live in the model).
#[derive(Debug, Default)]
pub(crate) struct LinkStats {
    forwarded: AtomicU64,
    send_errors: AtomicU64,
    pending: AtomicU64,
    late_sum_us: AtomicU64,
    late_max_us: AtomicU64,
}

impl LinkStats {
    pub fn error(&self) {
        self.send_errors.fetch_add(1, Relaxed);
    }

    pub fn snapshot(&self, model: Counters) -> DirectionStats {
        let forwarded = self.forwarded.load(Relaxed);
        let errors = self.send_errors.load(Relaxed);
        let released = forwarded + errors;
        DirectionStats {
            model,
            forwarded,
            send_errors: errors,
            pending: self.pending.load(Relaxed),
            late_mean_us: if released == 0 {
                0.0
            } else {
                self.late_sum_us.load(Relaxed) as f64 / released as f64
            },
            late_max_us: self.late_max_us.load(Relaxed),
        }
    }
}

/// Counters of one direction of an impaired link: the model's verdicts plus what the I/O
/// layer did with the released datagrams.
///
/// Once nothing is pending: `model.released() == forwarded + send_errors`, and
/// `model.sent == model.delivered + model.dropped()`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct DirectionStats {
    pub model: Counters,
    /// Datagrams written to the far side.
    pub forwarded: u64,
    /// Datagrams whose final write failed (socket error, receiver gone).
    pub send_errors: u64,
    /// Datagrams released by the model but not yet written; after the link stopped, the ones
    /// that were discarded because they were not yet due.
    pub pending: u64,
    /// Mean lateness of actual release vs scheduled release, microseconds.
    pub late_mean_us: f64,
    /// Maximum lateness, microseconds.
    pub late_max_us: u64,
}

impl fmt::Display for DirectionStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}; forwarded {}, send errors {}, pending {}, release lateness mean {:.0} µs max {} µs",
            self.model,
            self.forwarded,
            self.send_errors,
            self.pending,
            self.late_mean_us,
            self.late_max_us
        )
    }
}

/// Handle to push jobs into the scheduler task.
#[derive(Debug, Clone)]
pub(crate) struct Scheduler {
    tx: mpsc::UnboundedSender<Job>,
}

impl Scheduler {
    /// Spawn the scheduler task; it ends on `shutdown` or when every `Scheduler` clone is
    /// dropped and the heap is empty.
    pub fn spawn(shutdown: watch::Receiver<bool>) -> (Self, tokio::task::JoinHandle<()>) {
        let (tx, rx) = mpsc::unbounded_channel();
        let task = tokio::spawn(run(rx, shutdown));
        (Self { tx }, task)
    }

    pub fn push(&self, job: Job) {
        job.stats.pending.fetch_add(1, Relaxed);
        // If the scheduler already stopped, the datagram stays counted as pending: it was
        // discarded because the link stopped.
        let _ = self.tx.send(job);
    }
}

async fn run(mut rx: mpsc::UnboundedReceiver<Job>, mut shutdown: watch::Receiver<bool>) {
    let mut heap: BinaryHeap<Entry> = BinaryHeap::new();
    let mut seq = 0u64;
    let mut closed = false;
    loop {
        let now = Instant::now();
        while heap.peek().is_some_and(|e| e.at <= now) {
            let Some(e) = heap.pop() else { break };
            release(e.job, now).await;
        }
        if closed && heap.is_empty() {
            break;
        }
        let next = heap.peek().map(|e| e.at);
        tokio::select! {
            biased;
            r = shutdown.changed() => {
                if r.is_err() || *shutdown.borrow() {
                    break;
                }
            }
            job = rx.recv(), if !closed => match job {
                Some(job) => {
                    seq += 1;
                    heap.push(Entry { at: job.at, seq, job });
                }
                None => closed = true,
            },
            _ = sleep_until(next.unwrap_or(now)), if next.is_some() => {}
        }
    }
    tracing::debug!(discarded = heap.len(), "netem scheduler stopped");
}

async fn release(job: Job, now: Instant) {
    let Job {
        at,
        data,
        sink,
        stats,
    } = job;
    let late = now.saturating_duration_since(at).as_micros() as u64;
    stats.late_sum_us.fetch_add(late, Relaxed);
    stats.late_max_us.fetch_max(late, Relaxed);
    stats.pending.fetch_sub(1, Relaxed);
    let ok = match sink {
        Sink::Udp { sock, dest } => {
            let r = match dest {
                Some(d) => sock.send_to(&data, d).await,
                None => sock.send(&data).await,
            };
            if let Err(e) = &r {
                tracing::debug!(error = %e, ?dest, "netem: send failed");
            }
            r.is_ok()
        }
        Sink::Chan { tx, from } => tx.send(Datagram { data, from }).is_ok(),
    };
    if ok {
        stats.forwarded.fetch_add(1, Relaxed);
    } else {
        stats.error();
    }
}

/// Derive independent seeds (splitmix64 step).
pub(crate) fn derive_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Microseconds since `epoch`.
pub(crate) fn micros_since(epoch: Instant) -> u64 {
    Instant::now().saturating_duration_since(epoch).as_micros() as u64
}
