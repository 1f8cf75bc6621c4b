//! A site whose link to the coordinator was lost and comes back: which regions it asks
//! for again. The coordinator drops a lost site's regions; releases the site made while
//! cut off (noticed or not yet) reached nobody, and so did the motions its own tool
//! caused meanwhile. Measured (`cosurg bench sync`, outage row, 2026-11-25): without
//! asking again, the sites' copies stayed 8–11 mm apart a second after the tools stopped
//! in one or two seeds of five.

use std::collections::BTreeSet;

use proto::{Message, RegionId, Role, Welcome};
use sim_core::Simulation;
use tracing::info;

use super::{Now, SiteSession};

/// Simulated seconds before a lost link is noticed in which our releases may have gone
/// unheard: the link gives up on a silent coordinator after 2.5 heartbeat intervals
/// (1.25 s at the default 0.5 s), with margin.
pub const RELEASES_UNHEARD: f64 = 2.0;

/// A region our copy moved by more than this (m) while our tool acted cut off from the
/// coordinator is asked for when the link is back.
pub const MOVED_WHILE_CUT_OFF: f64 = 1e-3;

/// Our state when the link was lost, kept until it is back.
#[derive(Clone, Debug)]
struct CutOff {
    /// Node positions (m) when the link was lost.
    positions: Vec<nalgebra::Vector3<f64>>,
    /// Whether our tool touched the organ since.
    drove: bool,
}

/// What a site keeps while its link is lost, for when it is back.
#[derive(Clone, Debug, Default)]
pub(super) struct Rejoin {
    /// Regions we owned when the link was lost, or released shortly before.
    owned_when_cut_off: BTreeSet<RegionId>,
    /// Set while the link is lost.
    cut_off: Option<CutOff>,
}

impl Rejoin {
    /// Our tool touched `touched` this step (noted while cut off).
    pub(super) fn touched(&mut self, touched: &[RegionId]) {
        if let Some(cut) = self.cut_off.as_mut() {
            cut.drove |= !touched.is_empty();
        }
    }
}

impl SiteSession {
    /// The link to the coordinator was lost (it will be tried again). When it is back we
    /// ask again for the regions we own now or released in the [`RELEASES_UNHEARD`]
    /// before (a release while cut off, noticed or not yet, tells nobody, and its final
    /// keyframe is lost), and, if our tool acted while we were cut off, for every region
    /// our copy moved more than [`MOVED_WHILE_CUT_OFF`] meanwhile: the others did not see
    /// those motions (a lifted region drags its neighbours, which nobody owns).
    pub fn handle_disconnected(&mut self, sim: &Simulation) {
        let t = sim.time();
        let recent = self
            .claims
            .intervals(t)
            .into_iter()
            .filter(|&(_, _, to)| to >= t - RELEASES_UNHEARD)
            .map(|(r, _, _)| r);
        self.rejoin.owned_when_cut_off.extend(recent);
        if self.rejoin.cut_off.is_none() {
            self.rejoin.cut_off = Some(CutOff {
                positions: sim.positions().to_vec(),
                drove: false,
            });
        }
    }

    /// The regions to ask for again after a loss (see [`SiteSession::handle_disconnected`]).
    fn regions_to_reclaim(&mut self, sim: &Simulation) -> BTreeSet<RegionId> {
        let mut regions: BTreeSet<RegionId> = self.claims.owned().collect();
        regions.append(&mut self.rejoin.owned_when_cut_off);
        if let Some(cut) = self.rejoin.cut_off.take().filter(|c| c.drove) {
            let now = sim.positions();
            let moved: Vec<nalgebra::Vector3<f64>> = if now.len() == cut.positions.len() {
                now.iter().zip(&cut.positions).map(|(a, b)| a - b).collect()
            } else {
                // The lattice changed while cut off: every region counts as moved.
                vec![nalgebra::Vector3::repeat(f64::INFINITY); now.len()]
            };
            let by_region = self.map.max_speeds(sim.lattice(), &moved);
            regions.extend(
                by_region
                    .iter()
                    .enumerate()
                    .filter(|&(_, &d)| d > MOVED_WHILE_CUT_OFF)
                    .map(|(r, _)| r as RegionId),
            );
        }
        regions
    }

    /// We joined again after a loss (the site id may differ). Ownership does not survive
    /// a reconnect: the coordinator released our regions when we dropped.
    pub fn handle_reconnected(&mut self, w: &Welcome, sim: &Simulation, now: Now) {
        let t = sim.time();
        info!(site = w.site, "reconnected");
        self.sites.welcome(w);
        self.welcomed_at = Some(now.wall);
        self.stats.reconnects += 1;
        let wall = self.wall(now.wall);
        self.clocks.quiet(wall);
        // The coordinator dropped our regions with the link. Ask for them again (and for
        // those we moved unseen), as if our tool had just touched them: while we own them
        // we send their keyframes, and we release them (with a final keyframe) once they
        // are at rest. Without this, a region whose tool had stopped by the time the link
        // came back was owned by nobody, and the sites' copies, apart since the outage,
        // stayed apart (measured: 8–11 mm a second after the tools stopped, `bench sync`
        // outage row, one to two seeds of five).
        let reclaim = self.regions_to_reclaim(sim);
        self.claims.clear(t);
        self.baselines.clear();
        if self.cfg.linked && self.cfg.role != Role::Observer {
            for region in reclaim {
                if self.claims.touch(region, t) {
                    self.control(Message::OwnershipRequest(proto::OwnershipRequest {
                        region,
                        claim_time_us: now.coordinator_us,
                    }));
                }
            }
        }
    }
}
