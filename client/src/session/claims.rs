//! Region ownership as this site sees it: what it owns, what it asked for, when its tool
//! last touched each region, and the ownership intervals it held (for the report).

use std::collections::{BTreeMap, BTreeSet, HashMap};

use proto::RegionId;

/// A site releases a region this long after its tool last touched it (s of sim time)...
pub const RELEASE_AFTER: f64 = 0.4;

/// ...and once the region has come to rest: no node faster than this (m/s). Tissue keeps
/// moving after a tool lets go (a released fold springs back, a freed gallbladder swings);
/// without an owner nobody would send keyframes of that motion and every site's copy would
/// settle on its own.
pub const SETTLED_SPEED: f64 = 0.005;

/// A region still moving this long after the tool left (s) is released all the same (a
/// bound, so that a region that never quite settles is not held for ever).
pub const HOLD_MOVING_AT_MOST: f64 = 3.0;

#[derive(Debug, Default, Clone)]
pub struct Claims {
    /// Regions we own, and the simulated time since when (s).
    owned: BTreeMap<RegionId, f64>,
    /// Regions requested and not yet granted or denied.
    requested: BTreeSet<RegionId>,
    /// Simulated time our tool last touched each region (s).
    last_touch: HashMap<RegionId, f64>,
    /// Ownership held: (region, from, to) in sim time (s).
    held: Vec<(RegionId, f64, f64)>,
}

impl Claims {
    /// Our tool touches `region` at `t`; returns true if a request must be sent.
    pub fn touch(&mut self, region: RegionId, t: f64) -> bool {
        self.last_touch.insert(region, t);
        !self.owned.contains_key(&region) && self.requested.insert(region)
    }

    /// Owned regions to release at `t`: left alone by our tool for longer than
    /// [`RELEASE_AFTER`] and at rest (`speed(region)`, m/s, at most [`SETTLED_SPEED`]), or
    /// left alone for longer than [`HOLD_MOVING_AT_MOST`] whatever their speed.
    pub fn stale(&self, t: f64, speed: impl Fn(RegionId) -> f64) -> Vec<RegionId> {
        self.owned
            .keys()
            .copied()
            .filter(|r| {
                let idle = self.last_touch.get(r).map_or(f64::INFINITY, |lt| t - lt);
                idle > RELEASE_AFTER && (speed(*r) <= SETTLED_SPEED || idle > HOLD_MOVING_AT_MOST)
            })
            .collect()
    }

    /// The coordinator granted `region` to us at sim time `t`.
    pub fn granted(&mut self, region: RegionId, t: f64) {
        self.requested.remove(&region);
        self.owned.insert(region, t);
    }

    /// `region` is no longer ours (released by us, or granted to another) at `t`.
    pub fn lost(&mut self, region: RegionId, t: f64) {
        self.requested.remove(&region);
        if let Some(since) = self.owned.remove(&region) {
            self.held.push((region, since, t));
        }
    }

    pub fn denied(&mut self, region: RegionId) {
        self.requested.remove(&region);
    }

    /// Ownership does not survive a reconnect or a scene reset: the coordinator dropped
    /// it. Intervals still open are closed at `t`.
    pub fn clear(&mut self, t: f64) {
        let owned: Vec<RegionId> = self.owned.keys().copied().collect();
        for r in owned {
            self.lost(r, t);
        }
        self.requested.clear();
        self.last_touch.clear();
    }

    pub fn owns(&self, region: RegionId) -> bool {
        self.owned.contains_key(&region)
    }

    /// Whether we own or claim anything (the site then leads in simulated time).
    pub fn any(&self) -> bool {
        !self.owned.is_empty() || !self.requested.is_empty()
    }

    pub fn owned(&self) -> impl Iterator<Item = RegionId> + '_ {
        self.owned.keys().copied()
    }

    /// Ownership intervals, the open ones closed at `t`.
    pub fn intervals(&self, t: f64) -> Vec<(RegionId, f64, f64)> {
        let mut all = self.held.clone();
        all.extend(self.owned.iter().map(|(&r, &since)| (r, since, t)));
        all
    }
}
