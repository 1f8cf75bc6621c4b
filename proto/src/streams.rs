//! Keyframe streams, sans IO: which keyframe of a region goes on a new stream now, which
//! waits, and which stream in flight is reset because a newer keyframe superseded it.
//!
//! One policy for both senders of keyframe streams, the site's link and the coordinator's
//! relay (one [`KeyframeStreams`] per receiving peer): up to
//! [`KEYFRAME_STREAMS_PER_REGION`] streams of a region in flight at once, newest wins.
//! With all of them busy a newer keyframe waits, replacing any older one waiting, unless
//! the oldest stream has stalled (in flight for longer than the stall time, see
//! [`stall_time`]), which is then reset. A stalled stream with a newer keyframe behind it
//! (in flight, delivered or waiting) is reset at the next [`KeyframeStreams::poll`]. On a lossy or
//! long path several keyframes of a region are then on their way at once — a receiver
//! that runs behind the owner interpolates between them — instead of one per round trip;
//! on a path slower than the keyframe rate they still arrive at the path's pace.
//!
//! The caller opens and resets the actual streams ([`StreamAction`]) and reports streams
//! that ended ([`KeyframeStreams::finished`]). Time is an argument.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use crate::msg::RegionId;

/// Keyframe streams of one region in flight at a time. When released tissue snaps back
/// the owner sends a keyframe every 30 ms for a few hundred ms; on a 200 ms round trip
/// eight streams carry that burst without dropping any (measured `average` preset: 2 mm
/// divergence with eight, 4–24 mm with three).
pub const KEYFRAME_STREAMS_PER_REGION: usize = 8;

/// How long a keyframe stream may be in flight before a newer keyframe supersedes it on
/// a path with round trip `rtt`: [`crate::KEYFRAME_STALL`] or four round trips (more than
/// any playout lag), whichever is longer.
pub fn stall_time(rtt: Duration) -> Duration {
    crate::KEYFRAME_STALL.max(rtt * 4)
}

/// Names one stream opened by [`StreamAction::Open`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct StreamToken(pub u64);

/// What the caller must do with its streams.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StreamAction<T> {
    /// Open a stream for this keyframe.
    Open {
        token: StreamToken,
        region: RegionId,
        payload: T,
    },
    /// Reset this stream (`stream_code::SUPERSEDED`): a newer keyframe replaces it.
    Reset {
        token: StreamToken,
        region: RegionId,
    },
}

#[derive(Debug, Clone, Copy)]
struct InFlight {
    token: StreamToken,
    started: Instant,
}

/// The keyframe streams to one peer (see the module documentation).
#[derive(Debug, Clone)]
pub struct KeyframeStreams<T> {
    max_per_region: usize,
    /// Per region, the streams in flight, oldest first.
    in_flight: HashMap<RegionId, Vec<InFlight>>,
    /// Per region, the newest keyframe waiting for a free stream.
    held: HashMap<RegionId, T>,
    /// Per region, the stream of the newest keyframe opened (in flight or delivered).
    newest: HashMap<RegionId, StreamToken>,
    next_token: u64,
    /// Waiting keyframes replaced by newer ones before a stream was free.
    superseded_waiting: u64,
}

impl<T> Default for KeyframeStreams<T> {
    fn default() -> Self {
        Self::new(KEYFRAME_STREAMS_PER_REGION)
    }
}

impl<T> KeyframeStreams<T> {
    pub fn new(max_per_region: usize) -> Self {
        KeyframeStreams {
            max_per_region: max_per_region.max(1),
            in_flight: HashMap::new(),
            held: HashMap::new(),
            newest: HashMap::new(),
            next_token: 0,
            superseded_waiting: 0,
        }
    }

    /// A newer keyframe of `region` to send at `now`; `stall`: see [`stall_time`].
    pub fn submit(
        &mut self,
        region: RegionId,
        payload: T,
        now: Instant,
        stall: Duration,
    ) -> Vec<StreamAction<T>> {
        let mut actions = Vec::new();
        let streams = self.in_flight.entry(region).or_default();
        if streams.len() >= self.max_per_region {
            if now.saturating_duration_since(streams[0].started) < stall {
                if self.held.insert(region, payload).is_some() {
                    self.superseded_waiting += 1;
                }
                return actions;
            }
            let old = streams.remove(0);
            actions.push(StreamAction::Reset {
                token: old.token,
                region,
            });
        }
        // A keyframe waiting for a stream is older than this one.
        if self.held.remove(&region).is_some() {
            self.superseded_waiting += 1;
        }
        actions.push(self.open(region, payload, now));
        actions
    }

    /// The stream `token` of `region` ended (delivered, failed or reset).
    pub fn finished(&mut self, region: RegionId, token: StreamToken) {
        if let Some(streams) = self.in_flight.get_mut(&region) {
            streams.retain(|s| s.token != token);
            if streams.is_empty() {
                self.in_flight.remove(&region);
            }
        }
    }

    /// Resets stalled streams that have a newer keyframe behind them (in flight or
    /// waiting), then opens waiting keyframes whose region has a free stream.
    pub fn poll(&mut self, now: Instant, stall: Duration) -> Vec<StreamAction<T>> {
        let mut actions = Vec::new();
        for (&region, streams) in self.in_flight.iter_mut() {
            let newer_waiting = self.held.contains_key(&region);
            let newest = self.newest.get(&region).copied();
            let mut kept = Vec::with_capacity(streams.len());
            for s in streams.drain(..) {
                // Superseded: a newer keyframe went out (in flight or delivered) or waits.
                let superseded = newer_waiting || Some(s.token) != newest;
                if superseded && now.saturating_duration_since(s.started) >= stall {
                    actions.push(StreamAction::Reset {
                        token: s.token,
                        region,
                    });
                } else {
                    kept.push(s);
                }
            }
            *streams = kept;
        }
        self.in_flight.retain(|_, s| !s.is_empty());
        let ready: Vec<RegionId> = self
            .held
            .keys()
            .copied()
            .filter(|r| {
                self.in_flight
                    .get(r)
                    .is_none_or(|s| s.len() < self.max_per_region)
            })
            .collect();
        for region in ready {
            if let Some(payload) = self.held.remove(&region) {
                actions.push(self.open(region, payload, now));
            }
        }
        actions
    }

    /// Streams in flight for `region`.
    pub fn in_flight(&self, region: RegionId) -> usize {
        self.in_flight.get(&region).map_or(0, Vec::len)
    }

    /// Whether a keyframe of `region` waits for a stream.
    pub fn is_waiting(&self, region: RegionId) -> bool {
        self.held.contains_key(&region)
    }

    /// Waiting keyframes replaced by newer ones before they were sent.
    pub fn superseded_waiting(&self) -> u64 {
        self.superseded_waiting
    }

    /// Forget everything (connection lost).
    pub fn clear(&mut self) {
        self.in_flight.clear();
        self.held.clear();
        self.newest.clear();
    }

    fn open(&mut self, region: RegionId, payload: T, now: Instant) -> StreamAction<T> {
        self.next_token += 1;
        let token = StreamToken(self.next_token);
        self.newest.insert(region, token);
        self.in_flight.entry(region).or_default().push(InFlight {
            token,
            started: now,
        });
        StreamAction::Open {
            token,
            region,
            payload,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const STALL: Duration = Duration::from_millis(300);

    fn opened<T: Clone>(a: &[StreamAction<T>]) -> Vec<T> {
        a.iter()
            .filter_map(|a| match a {
                StreamAction::Open { payload, .. } => Some(payload.clone()),
                _ => None,
            })
            .collect()
    }

    fn resets<T>(a: &[StreamAction<T>]) -> usize {
        a.iter()
            .filter(|a| matches!(a, StreamAction::Reset { .. }))
            .count()
    }

    #[test]
    fn up_to_the_limit_in_flight_then_the_newest_waits() {
        let t0 = Instant::now();
        let mut s = KeyframeStreams::new(3);
        for k in 0..3 {
            assert_eq!(opened(&s.submit(7, k, t0, STALL)), vec![k]);
        }
        assert_eq!(s.in_flight(7), 3);
        // Full and nothing stalled: 3 waits, then 4 replaces it.
        assert!(s.submit(7, 3, t0, STALL).is_empty());
        assert!(s.submit(7, 4, t0, STALL).is_empty());
        assert_eq!(s.superseded_waiting(), 1);
        // Another region is independent.
        assert_eq!(opened(&s.submit(8, 10, t0, STALL)), vec![10]);
        // A stream ends: the waiting keyframe goes out at the next poll.
        let a = s.poll(t0, STALL);
        assert!(a.is_empty(), "{a:?}");
        s.finished(7, StreamToken(1));
        assert_eq!(opened(&s.poll(t0, STALL)), vec![4]);
        assert!(!s.is_waiting(7));
    }

    #[test]
    fn stalled_streams_with_a_newer_keyframe_behind_are_reset() {
        let t0 = Instant::now();
        let mut s = KeyframeStreams::new(3);
        s.submit(1, 0, t0, STALL);
        // Alone and stalled: kept (nothing newer).
        let late = t0 + STALL * 2;
        assert_eq!(resets(&s.poll(late, STALL)), 0);
        // A newer one in flight: the stalled one is reset, the newer kept.
        s.submit(1, 1, late, STALL);
        let a = s.poll(late, STALL);
        assert_eq!(
            a,
            vec![StreamAction::Reset {
                token: StreamToken(1),
                region: 1
            }]
        );
        assert_eq!(s.in_flight(1), 1);
        // A newer keyframe delivered already supersedes a stalled older one too.
        s.submit(2, 0, late, STALL);
        s.submit(2, 1, late, STALL);
        s.finished(2, StreamToken(4));
        let a = s.poll(late + STALL, STALL);
        assert_eq!(
            a,
            vec![StreamAction::Reset {
                token: StreamToken(3),
                region: 2
            }]
        );
        // Full with the oldest stalled: a newer submission resets it and opens at once.
        s.submit(1, 2, late, STALL);
        s.submit(1, 3, late, STALL);
        let a = s.submit(1, 4, late + STALL, STALL);
        assert_eq!(resets(&a), 1);
        assert_eq!(opened(&a), vec![4]);
        assert_eq!(s.in_flight(1), 3);
    }
}
