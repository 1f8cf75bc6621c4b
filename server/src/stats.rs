//! The coordinator's counters ([`CoordinatorStats`]).

use std::sync::atomic::{AtomicU64, Ordering};

/// Counters (monotonic since start).
#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub(crate) connections: AtomicU64,
    pub(crate) handshake_failures: AtomicU64,
    pub(crate) refused: AtomicU64,
    pub(crate) joined: AtomicU64,
    pub(crate) resumed: AtomicU64,
    pub(crate) left: AtomicU64,
    pub(crate) datagrams_in: AtomicU64,
    pub(crate) datagrams_relayed: AtomicU64,
    pub(crate) datagrams_send_failed: AtomicU64,
    pub(crate) malformed_datagrams: AtomicU64,
    pub(crate) control_frames_in: AtomicU64,
    pub(crate) malformed_control: AtomicU64,
    pub(crate) keyframes_in: AtomicU64,
    pub(crate) keyframes_relayed: AtomicU64,
    pub(crate) keyframe_streams_reset: AtomicU64,
    pub(crate) superseded_streams_in: AtomicU64,
    pub(crate) malformed_streams: AtomicU64,
    pub(crate) dropped_messages: AtomicU64,
    pub(crate) over_budget: AtomicU64,
    pub(crate) overloaded: AtomicU64,
    pub(crate) control_frames_out: AtomicU64,
    pub(crate) bytes_relayed: AtomicU64,
}

/// Snapshot of the coordinator's counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CoordinatorStats {
    /// Incoming QUIC connection attempts.
    pub connections: u64,
    /// Failed TLS/QUIC handshakes (e.g. wrong ALPN).
    pub handshake_failures: u64,
    /// Joins refused at the application layer.
    pub refused: u64,
    pub joined: u64,
    /// Joins that replaced a silent member of the same name (a quick reconnection; see
    /// [`crate::session::Session::join`]). Also counted in `joined`.
    pub resumed: u64,
    pub left: u64,
    pub datagrams_in: u64,
    /// Datagrams sent to recipients (one per recipient).
    pub datagrams_relayed: u64,
    pub datagrams_send_failed: u64,
    pub malformed_datagrams: u64,
    pub control_frames_in: u64,
    pub malformed_control: u64,
    pub keyframes_in: u64,
    /// Keyframe streams completed to recipients (one per recipient).
    pub keyframes_relayed: u64,
    /// Relayed keyframe streams reset because a newer keyframe superseded them.
    pub keyframe_streams_reset: u64,
    /// Incoming keyframe streams the sending site reset with `stream_code::SUPERSEDED`
    /// because a newer keyframe of the region replaced them (normal, not malformed).
    pub superseded_streams_in: u64,
    /// Unidirectional streams that were truncated, oversized, undecodable or not a keyframe.
    pub malformed_streams: u64,
    /// Well-formed messages dropped by policy (observer, not owner, stale, …).
    pub dropped_messages: u64,
    /// Of `dropped_messages`: relayed-state datagrams dropped because their site exceeded
    /// its relay budget ([`crate::session::RelayBudget`]).
    pub over_budget: u64,
    /// Sites closed because their control queue overflowed.
    pub overloaded: u64,
    /// Control frames queued to sites (one per recipient).
    pub control_frames_out: u64,
    /// Bytes relayed to sites: datagrams, keyframe streams and control frames (one count
    /// per recipient; QUIC overhead not included).
    pub bytes_relayed: u64,
}

impl Counters {
    pub(crate) fn snapshot(&self) -> CoordinatorStats {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        CoordinatorStats {
            connections: g(&self.connections),
            handshake_failures: g(&self.handshake_failures),
            refused: g(&self.refused),
            joined: g(&self.joined),
            resumed: g(&self.resumed),
            left: g(&self.left),
            datagrams_in: g(&self.datagrams_in),
            datagrams_relayed: g(&self.datagrams_relayed),
            datagrams_send_failed: g(&self.datagrams_send_failed),
            malformed_datagrams: g(&self.malformed_datagrams),
            control_frames_in: g(&self.control_frames_in),
            malformed_control: g(&self.malformed_control),
            keyframes_in: g(&self.keyframes_in),
            keyframes_relayed: g(&self.keyframes_relayed),
            keyframe_streams_reset: g(&self.keyframe_streams_reset),
            superseded_streams_in: g(&self.superseded_streams_in),
            malformed_streams: g(&self.malformed_streams),
            dropped_messages: g(&self.dropped_messages),
            over_budget: g(&self.over_budget),
            overloaded: g(&self.overloaded),
            control_frames_out: g(&self.control_frames_out),
            bytes_relayed: g(&self.bytes_relayed),
        }
    }
}

impl CoordinatorStats {
    /// Messages relayed to sites (datagrams, keyframes, control frames; one per recipient).
    pub fn messages_relayed(&self) -> u64 {
        self.datagrams_relayed + self.keyframes_relayed + self.control_frames_out
    }
}

impl std::ops::AddAssign for CoordinatorStats {
    fn add_assign(&mut self, o: Self) {
        self.connections += o.connections;
        self.handshake_failures += o.handshake_failures;
        self.refused += o.refused;
        self.joined += o.joined;
        self.resumed += o.resumed;
        self.left += o.left;
        self.datagrams_in += o.datagrams_in;
        self.datagrams_relayed += o.datagrams_relayed;
        self.datagrams_send_failed += o.datagrams_send_failed;
        self.malformed_datagrams += o.malformed_datagrams;
        self.control_frames_in += o.control_frames_in;
        self.malformed_control += o.malformed_control;
        self.keyframes_in += o.keyframes_in;
        self.keyframes_relayed += o.keyframes_relayed;
        self.keyframe_streams_reset += o.keyframe_streams_reset;
        self.superseded_streams_in += o.superseded_streams_in;
        self.malformed_streams += o.malformed_streams;
        self.dropped_messages += o.dropped_messages;
        self.over_budget += o.over_budget;
        self.overloaded += o.overloaded;
        self.control_frames_out += o.control_frames_out;
        self.bytes_relayed += o.bytes_relayed;
    }
}

pub(crate) fn add(a: &AtomicU64, n: usize) {
    a.fetch_add(n as u64, Ordering::Relaxed);
}

pub(crate) fn inc(a: &AtomicU64) {
    a.fetch_add(1, Ordering::Relaxed);
}
