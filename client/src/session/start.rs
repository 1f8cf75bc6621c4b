//! Joining and starting: the Welcome, and when the site may start its clock (the sites
//! present, the join snapshot, every known site's clock heard).

use std::collections::BTreeSet;
use std::time::Instant;

use proto::{Role, SiteId, Welcome};
use sim_core::Simulation;
use tracing::info;

use super::{Now, PRESENCE_WAIT, SIM_TIME_INTERVAL, SNAPSHOT_WAIT, SiteSession};

impl SiteSession {
    /// The coordinator welcomed us (first join).
    pub fn handle_welcome(&mut self, w: &Welcome, now: Now) {
        info!(site = w.site, sites = w.sites.len(), "welcomed");
        self.sites.welcome(w);
        self.welcomed_at = Some(now.wall);
    }

    /// Whether the site may start its clock: welcomed, `expect_sites` present, the join
    /// snapshot seen (or [`SNAPSHOT_WAIT`] passed without it), and the clock of every
    /// site it knows of heard (or [`PRESENCE_WAIT`] passed since the rest was true).
    ///
    /// Sites learn of each other on the reliable control stream (the Welcome and
    /// `SiteJoined`), and under `poor` a lost packet there and its retransmission
    /// timeouts, behind a snapshot filling the 500 kbit/s link, told one site 1.1 s of
    /// session time after the other (measured in `tests/e2e.rs`, 2026-11-29, dilated ×3).
    /// Whichever learnt first started alone: a trainee started that far behind the
    /// instructor and its mean display delay rose by 200–250 ms while it caught up, or
    /// ran that far ahead of it and then waited 1.5 s, receiving the instructor's first
    /// inputs late (2.1 mm of divergence). So the sites also announce themselves with
    /// clock stamps while they wait ([`Self::announce_presence`]), datagrams repeated
    /// every [`SIM_TIME_INTERVAL`]: a site counts as present once its stamps arrive, even
    /// before the table lists it, and a site starts once it has heard every other site's
    /// clock (observers send none). The sites then start within a path's delay of one
    /// another, the followers near their lag.
    pub fn is_ready(&mut self, expect_sites: usize, now: Instant) -> bool {
        let heard: BTreeSet<SiteId> = self.clocks.stamped_sites().collect();
        let stamped_only = heard
            .iter()
            .filter(|&&s| {
                self.sites.is_other(s) && !self.sites.contains(s) && !self.sites.departed(s)
            })
            .count();
        let complete = self.sites.me().is_some()
            && self.sites.len() + stamped_only >= expect_sites
            && self.snapshot_taken(now);
        if !complete {
            self.complete_at = None;
            return false;
        }
        let complete_at = *self.complete_at.get_or_insert(now);
        let unheard = self
            .sites
            .receivers()
            .filter(|&s| self.sites.role(s) != Some(Role::Observer) && !heard.contains(&s))
            .count();
        unheard == 0 || now.duration_since(complete_at) > PRESENCE_WAIT
    }

    /// While waiting to start, a welcomed site (not an observer) that has its join
    /// snapshot sends its clock as it stands every [`SIM_TIME_INTERVAL`] of wall time: the
    /// others count it as present and wait for it ([`Self::is_ready`]). Call it in the
    /// wait loop; nothing once started.
    pub fn announce_presence(&mut self, sim: &Simulation, now: Now) {
        // Not before the snapshot: a late joiner takes the session's time from it, and a
        // stamp at 0 followed by one at that time would read as a clock running fast.
        if self.started
            || !self.cfg.linked
            || self.cfg.role == Role::Observer
            || !self.snapshot_taken(now.wall)
        {
            return;
        }
        let Some(me) = self.sites.me() else { return };
        let wall = self.wall(now.wall);
        if wall < self.next_presence {
            return;
        }
        self.next_presence = wall + SIM_TIME_INTERVAL;
        self.send_clock(me, sim, now);
    }

    /// Whether the join snapshot was seen, or [`SNAPSHOT_WAIT`] passed since the Welcome
    /// without it.
    fn snapshot_taken(&self, now: Instant) -> bool {
        self.got_snapshot
            || self
                .welcomed_at
                .is_some_and(|w| now.duration_since(w) > SNAPSHOT_WAIT)
    }

    /// The simulation clock starts now; `rtt_us`: the link's round trip, if measured
    /// (seeds the playout lag: about two one-way hops, owner → coordinator → us).
    pub fn start(&mut self, now: Instant, rtt_us: Option<u64>) {
        self.started = true;
        self.next_due = now;
        if let Some(rtt) = rtt_us {
            self.clocks.seed_delay(rtt as f64 / 1e6);
        }
    }
}
