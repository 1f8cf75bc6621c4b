//! Frames from other sites waiting for this site's simulated time, and releases waiting
//! for the owner's last frames to be played.

use std::collections::BTreeMap;

use proto::{Epoch, KeyframeId, RegionId};
use sim_core::Simulation;
use sim_core::sync::{SiteSync, SyncFrame};
use tracing::{debug, warn};

use super::wire::frame_time;

/// Keyframes and tree deltas held until the site's clock reaches their simulated time
/// (a receiver never extrapolates backwards), and deferred remote releases.
#[derive(Debug, Default)]
pub struct Inbox {
    /// Frames from sites ahead of us in simulated time, waiting for our clock, with
    /// their scene epoch (frames of the next epoch may arrive before our reset).
    pending: Vec<(Epoch, SyncFrame)>,
    /// Regions released by their owner, and the simulated time of the release: the
    /// release takes effect once our clock reaches it and the owner's last frames are
    /// played.
    deferred_release: BTreeMap<RegionId, f64>,
}

impl Inbox {
    pub fn push(&mut self, epoch: Epoch, frame: SyncFrame) {
        self.pending.push((epoch, frame));
    }

    /// Another site released `region` at about its simulated time `at` (s; `None`:
    /// unknown): takes effect in [`Inbox::apply_due`].
    pub fn defer_release(&mut self, region: RegionId, at: Option<f64>) {
        debug!(region, ?at, "remote release");
        self.deferred_release
            .insert(region, at.unwrap_or(f64::NEG_INFINITY));
    }

    /// A new owner took `region`: a release still waiting no longer applies.
    pub fn cancel_release(&mut self, region: RegionId) {
        self.deferred_release.remove(&region);
    }

    /// Scene reset to `epoch`: frames of other epochs and releases are stale.
    pub fn reset(&mut self, epoch: Epoch) {
        self.pending.retain(|(e, _)| *e == epoch);
        self.deferred_release.clear();
    }

    pub fn is_idle(&self) -> bool {
        self.pending.is_empty() && self.deferred_release.is_empty()
    }

    /// Applies the pending frames that the simulated time has reached, oldest first, and
    /// the releases whose time has come; then holds each region's next pending keyframe
    /// for interpolation. Only frames of `epoch` are applied; frames of a later epoch wait
    /// for the reset. Returns the keyframes applied (region, id), to acknowledge.
    pub fn apply_due(
        &mut self,
        epoch: Epoch,
        sync: &mut SiteSync,
        sim: &mut Simulation,
    ) -> Vec<(RegionId, KeyframeId)> {
        if self.is_idle() {
            return Vec::new();
        }
        let now = sim.time() + 0.5 * sim.options().dt;
        let (due, later): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pending)
            .into_iter()
            .partition(|(e, f)| *e == epoch && frame_time(f) <= now);
        self.pending = later;
        let mut due: Vec<SyncFrame> = due.into_iter().map(|(_, f)| f).collect();
        due.sort_by(|a, b| frame_time(a).total_cmp(&frame_time(b)));
        let mut applied = Vec::new();
        for frame in due {
            debug!(
                region = frame.region(),
                t = frame_time(&frame),
                now = sim.time(),
                "apply frame"
            );
            match sync.on_frame(sim, &frame) {
                Ok(Some(id)) => applied.push((frame.region(), id)),
                Ok(None) => debug!(
                    region = frame.region(),
                    "sync frame ignored (stale, owned or released)"
                ),
                Err(e) => warn!(region = frame.region(), error = %e, "sync frame not applied"),
            }
        }
        let done: Vec<RegionId> = self
            .deferred_release
            .iter()
            .filter(|&(r, at)| *at <= now && !self.pending.iter().any(|(_, f)| f.region() == *r))
            .map(|(r, _)| *r)
            .collect();
        for r in done {
            self.deferred_release.remove(&r);
            sync.on_remote_release(r);
        }
        self.hold_next_keyframes(epoch, sync, sim);
        applied
    }

    /// Offers each region's earliest pending frame, if it is a keyframe, to sim-core as
    /// the next keyframe to interpolate towards (a tree delta first changes the nodes).
    fn hold_next_keyframes(&self, epoch: Epoch, sync: &mut SiteSync, sim: &Simulation) {
        let mut earliest: BTreeMap<RegionId, &SyncFrame> = BTreeMap::new();
        for (_, f) in self.pending.iter().filter(|(e, _)| *e == epoch) {
            let e = earliest.entry(f.region()).or_insert(f);
            if frame_time(f) < frame_time(e) {
                *e = f;
            }
        }
        for f in earliest.into_values() {
            if let SyncFrame::Keyframe(kf) = f {
                sync.hold_next(sim, kf);
            }
        }
    }
}
