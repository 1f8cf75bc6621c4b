//! Keyframe baselines (sender side): which keyframes each receiver acknowledged, so that a
//! [`crate::msg::TreeDelta`] only references a keyframe every receiver holds.
//!
//! Protocol contract:
//! * keyframe ids of a region strictly increase;
//! * a receiver keeps at least the last [`BaselineConfig::history`] keyframes it received per
//!   region and acknowledges each with [`crate::msg::KeyframeAck`];
//! * the sender calls [`BaselineTracker::on_sent`] per receiver, [`BaselineTracker::on_ack`] on
//!   acks, and [`BaselineTracker::poll`] periodically; a [`BaselineEvent::Resend`] means "send
//!   a (fresh) keyframe of this region to this receiver"; after `max_resends` unanswered resends
//!   it gives up on the receiver ([`BaselineEvent::GiveUp`]), leaving liveness to decide its
//!   fate.
//!
//! Time is passed in as µs; there is no internal clock.

use std::collections::{BTreeMap, VecDeque};

use crate::msg::{KeyframeId, RegionId, SiteId};

/// Tuning of a [`BaselineTracker`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BaselineConfig {
    /// A keyframe not acknowledged within this time is resent (µs).
    pub ack_timeout_us: u64,
    /// Resends before giving up on a receiver for a region.
    pub max_resends: u32,
    /// Number of most recent keyframes per region a receiver is required to keep.
    pub history: usize,
}

impl Default for BaselineConfig {
    fn default() -> Self {
        Self {
            ack_timeout_us: 500_000,
            max_resends: 5,
            history: 8,
        }
    }
}

/// Something the sender must do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BaselineEvent {
    /// Send a keyframe of `region` to `receiver` again (the newest one is best).
    Resend {
        receiver: SiteId,
        region: RegionId,
        last_sent: KeyframeId,
    },
    /// `receiver` did not acknowledge `region` after all resends; no longer waited for.
    GiveUp { receiver: SiteId, region: RegionId },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Pending {
    keyframe: KeyframeId,
    sent_at_us: u64,
    resends: u32,
}

#[derive(Debug, Clone, Default)]
struct Entry {
    acked: Option<KeyframeId>,
    pending: Option<Pending>,
}

/// Per (receiver, region) acknowledgement state.
#[derive(Debug, Clone, Default)]
pub struct BaselineTracker {
    config: BaselineConfig,
    entries: BTreeMap<(SiteId, RegionId), Entry>,
    /// Most recent keyframe ids sent per region (newest last), at most `history`.
    recent: BTreeMap<RegionId, VecDeque<KeyframeId>>,
}

impl BaselineTracker {
    pub fn new(config: BaselineConfig) -> Self {
        Self {
            config,
            ..Default::default()
        }
    }

    pub fn config(&self) -> &BaselineConfig {
        &self.config
    }

    /// Record that `keyframe` of `region` was sent to `receiver` at `now_us`.
    pub fn on_sent(
        &mut self,
        receiver: SiteId,
        region: RegionId,
        keyframe: KeyframeId,
        now_us: u64,
    ) {
        let recent = self.recent.entry(region).or_default();
        if recent.back().is_none_or(|&b| keyframe > b) {
            recent.push_back(keyframe);
            while recent.len() > self.config.history.max(1) {
                recent.pop_front();
            }
        }
        let e = self.entries.entry((receiver, region)).or_default();
        let resends = match e.pending {
            // a resend of the region keeps counting
            Some(p) => p.resends,
            None => 0,
        };
        if e.pending.is_none_or(|p| keyframe >= p.keyframe) {
            e.pending = Some(Pending {
                keyframe,
                sent_at_us: now_us,
                resends,
            });
        }
    }

    /// Record an acknowledgement. Returns `true` if it advanced the receiver's baseline.
    pub fn on_ack(&mut self, receiver: SiteId, region: RegionId, keyframe: KeyframeId) -> bool {
        let Some(e) = self.entries.get_mut(&(receiver, region)) else {
            return false;
        };
        // Only keyframes that were actually sent can be acknowledged.
        let sent = e.pending.is_some_and(|p| keyframe <= p.keyframe)
            || self
                .recent
                .get(&region)
                .is_some_and(|r| r.contains(&keyframe));
        if !sent || e.acked.is_some_and(|a| a >= keyframe) {
            return false;
        }
        e.acked = Some(keyframe);
        if e.pending.is_some_and(|p| keyframe >= p.keyframe) {
            e.pending = None;
        }
        true
    }

    /// Newest keyframe of `region` acknowledged by `receiver`.
    pub fn baseline(&self, receiver: SiteId, region: RegionId) -> Option<KeyframeId> {
        self.entries.get(&(receiver, region)).and_then(|e| e.acked)
    }

    /// The newest keyframe every one of `receivers` has acknowledged and still keeps (within
    /// the last `history` keyframes sent) — the base a broadcast delta may reference. `None`:
    /// send a keyframe instead. With no receivers, `None`.
    pub fn common_baseline(
        &self,
        region: RegionId,
        receivers: impl IntoIterator<Item = SiteId>,
    ) -> Option<KeyframeId> {
        let mut min: Option<KeyframeId> = None;
        for r in receivers {
            let a = self.baseline(r, region)?;
            min = Some(min.map_or(a, |m| m.min(a)));
        }
        let base = min?;
        self.recent
            .get(&region)
            .filter(|rec| rec.contains(&base))
            .map(|_| base)
    }

    /// True if `receiver` has an unacknowledged keyframe of `region` outstanding.
    pub fn is_pending(&self, receiver: SiteId, region: RegionId) -> bool {
        self.entries
            .get(&(receiver, region))
            .is_some_and(|e| e.pending.is_some())
    }

    /// Timeouts due at `now_us`. A `Resend` restarts the timer (the caller's `on_sent` for the
    /// new keyframe does too).
    pub fn poll(&mut self, now_us: u64) -> Vec<BaselineEvent> {
        let mut out = Vec::new();
        for (&(receiver, region), e) in self.entries.iter_mut() {
            let Some(p) = e.pending.as_mut() else {
                continue;
            };
            if now_us.saturating_sub(p.sent_at_us) < self.config.ack_timeout_us {
                continue;
            }
            if p.resends >= self.config.max_resends {
                e.pending = None;
                out.push(BaselineEvent::GiveUp { receiver, region });
            } else {
                p.resends += 1;
                p.sent_at_us = now_us;
                out.push(BaselineEvent::Resend {
                    receiver,
                    region,
                    last_sent: p.keyframe,
                });
            }
        }
        out
    }

    /// Earliest time at which [`poll`](Self::poll) will have something to report.
    pub fn next_deadline(&self) -> Option<u64> {
        self.entries
            .values()
            .filter_map(|e| e.pending.map(|p| p.sent_at_us + self.config.ack_timeout_us))
            .min()
    }

    /// Forget a receiver (it left).
    pub fn remove_receiver(&mut self, receiver: SiteId) {
        self.entries.retain(|&(r, _), _| r != receiver);
    }

    /// Forget a region (ownership lost or new topology epoch).
    pub fn reset_region(&mut self, region: RegionId) {
        self.entries.retain(|&(_, g), _| g != region);
        self.recent.remove(&region);
    }

    /// Forget everything.
    pub fn clear(&mut self) {
        self.entries.clear();
        self.recent.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tracker() -> BaselineTracker {
        BaselineTracker::new(BaselineConfig {
            ack_timeout_us: 100,
            max_resends: 2,
            history: 3,
        })
    }

    #[test]
    fn ack_sets_baseline() {
        let mut t = tracker();
        assert_eq!(t.baseline(1, 9), None);
        t.on_sent(1, 9, 1, 0);
        assert!(t.is_pending(1, 9));
        assert!(t.on_ack(1, 9, 1));
        assert!(!t.is_pending(1, 9));
        assert_eq!(t.baseline(1, 9), Some(1));
        // duplicate / older acks do not move it
        assert!(!t.on_ack(1, 9, 1));
        // unknown acks ignored
        assert!(!t.on_ack(1, 9, 77));
        assert!(!t.on_ack(2, 9, 1));
    }

    #[test]
    fn old_ack_keeps_newer_pending() {
        let mut t = tracker();
        t.on_sent(1, 9, 1, 0);
        t.on_sent(1, 9, 2, 10);
        assert!(t.on_ack(1, 9, 1));
        assert!(t.is_pending(1, 9));
        assert!(t.on_ack(1, 9, 2));
        assert!(!t.is_pending(1, 9));
        assert_eq!(t.baseline(1, 9), Some(2));
    }

    #[test]
    fn common_baseline_is_min_over_receivers_and_within_history() {
        let mut t = tracker();
        for kf in 1..=2 {
            for r in [1, 2] {
                t.on_sent(r, 9, kf, kf * 10);
            }
        }
        t.on_ack(1, 9, 2);
        assert_eq!(
            t.common_baseline(9, [1, 2]),
            None,
            "receiver 2 has nothing yet"
        );
        t.on_ack(2, 9, 1);
        assert_eq!(t.common_baseline(9, [1, 2]), Some(1));
        assert_eq!(t.common_baseline(9, [1]), Some(2));
        assert_eq!(t.common_baseline(9, []), None);
        // three more keyframes: keyframe 1 falls out of the 3-keyframe history
        for kf in 3..=5 {
            t.on_sent(1, 9, kf, kf * 10);
        }
        assert_eq!(t.common_baseline(9, [1, 2]), None);
    }

    #[test]
    fn timeouts_resend_then_give_up() {
        let mut t = tracker();
        t.on_sent(1, 9, 4, 0);
        assert_eq!(t.next_deadline(), Some(100));
        assert!(t.poll(99).is_empty());
        assert_eq!(
            t.poll(100),
            vec![BaselineEvent::Resend {
                receiver: 1,
                region: 9,
                last_sent: 4
            }]
        );
        assert!(t.poll(150).is_empty());
        // caller sends a fresh keyframe 5: timer restarts, resend count is kept
        t.on_sent(1, 9, 5, 160);
        assert!(t.poll(259).is_empty());
        assert_eq!(t.poll(260).len(), 1);
        assert_eq!(
            t.poll(360),
            vec![BaselineEvent::GiveUp {
                receiver: 1,
                region: 9
            }]
        );
        assert!(!t.is_pending(1, 9));
        assert!(t.poll(10_000).is_empty());
        assert_eq!(t.next_deadline(), None);
    }

    #[test]
    fn ack_resets_resend_counter() {
        let mut t = tracker();
        t.on_sent(1, 9, 1, 0);
        t.poll(100);
        t.poll(200);
        t.on_ack(1, 9, 1);
        t.on_sent(1, 9, 2, 300);
        assert!(matches!(t.poll(400)[0], BaselineEvent::Resend { .. }));
    }

    #[test]
    fn remove_receiver_and_reset_region() {
        let mut t = tracker();
        t.on_sent(1, 9, 1, 0);
        t.on_sent(2, 9, 1, 0);
        t.on_ack(1, 9, 1);
        t.on_ack(2, 9, 1);
        t.remove_receiver(2);
        assert_eq!(t.baseline(2, 9), None);
        assert_eq!(t.common_baseline(9, [1]), Some(1));
        t.reset_region(9);
        assert_eq!(t.baseline(1, 9), None);
        assert_eq!(t.common_baseline(9, [1]), None);
    }
}
