//! The site's protocol state, sans IO: [`SiteSession`].
//!
//! Shaped like quinn-proto's `Connection` and the coordinator's own
//! `server::session::Session`: inputs are `handle_*` calls carrying the time they happen
//! at ([`Now`]), outputs are polled ([`SiteSession::poll_transmit`],
//! [`SiteSession::poll_event`], [`SiteSession::poll_timeout`]). No sockets, no threads, no
//! async runtime, no clock of its own, so that it is unit-tested with a fake clock
//! (`tests.rs`) and driven by `site::run_site` with a real link.
//!
//! It owns the joining and the start of the clock (`start.rs`: the site starts once every
//! site it knows of is heard), the site table ([`sites`]), region claims and releases
//! ([`claims`]), the keyframe acknowledgements and delta baselines (`proto`'s [`BaselineTracker`]), the
//! frames waiting for the site's simulated time ([`inbox`]), the playout clock
//! ([`pacing`]) and the scene epoch; and it is the only place where sim-core's sync frames
//! become `proto` messages and back ([`wire`]). The simulation itself stays with the
//! driver: the calls that read or change it take it as an argument.
//!
//! ## Scene reset
//! Only the instructor may reset ([`SiteSession::request_reset`]; the coordinator refuses
//! others with [`proto::CommandRefusal`]). The coordinator bumps the epoch and sends
//! `ResetScene { epoch }` to every site; on it a session rebuilds the simulation from the
//! scene (its initial state, at the current simulated time), forgets ownership, pending
//! frames and baselines, adopts the epoch and from then on sends and accepts frames of
//! that epoch only. A late joiner takes the current epoch from its join snapshot.

pub mod claims;
mod config;
pub mod inbox;
mod inputs;
pub mod pacing;
mod reconnect;
pub mod sites;
mod start;
pub mod topology;
pub mod wire;

#[cfg(test)]
mod tests;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use proto::{
    BaselineConfig, BaselineTracker, Command, Epoch, Message, RegionId, Role, SiteId,
    TeachingTrajectory,
};
use sim_core::sync::{RegionMap, SiteSync, SyncStrategy};
use sim_core::{SimError, Simulation};
use tracing::{debug, info, warn};

use claims::Claims;
use config::sync_config;
pub use config::{SessionConfig, SessionSnapshot, SessionStats};
use inbox::Inbox;
pub use pacing::{Pace, PeerClocks, PlayoutLag};
pub use reconnect::{MOVED_WHILE_CUT_OFF, RELEASES_UNHEARD};
use sites::SiteTable;
pub use wire::WireFrame;

/// Simulated time between the site's time stamps (s).
pub const SIM_TIME_INTERVAL: f64 = 0.05;
/// Simulated time between tool-pose datagrams, except under input-only (s): poses only
/// draw the remote tool then, and ~60 Hz leaves a lossy path's congestion window to the
/// keyframe streams.
pub const POSE_INTERVAL: f64 = 0.016;
pub use inputs::POSE_HISTORY_INTERVAL;
/// Least and largest simulated time between a reset request and the reset (s).
pub const RESET_MARGIN: f64 = 0.02;
pub const MAX_RESET_MARGIN: f64 = 1.0;
/// A late joiner waits this long after its Welcome for the coordinator's snapshot.
pub const SNAPSHOT_WAIT: Duration = Duration::from_secs(3);
/// A site whose session is complete waits at most this long (session time) for the
/// clock stamps of every site it knows of before it starts anyway (see
/// [`SiteSession::is_ready`]; the longest wait measured was 1.1 s).
pub const PRESENCE_WAIT: Duration = Duration::from_secs(3);

/// The time an input happens at: wall time (pacing) and the coordinator's clock as the
/// link estimates it (claims, time stamps).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Now {
    pub wall: Instant,
    /// Estimated coordinator clock (µs); the local clock before synchronisation.
    pub coordinator_us: u64,
    /// Whether `coordinator_us` is synchronised with the coordinator.
    pub synced: bool,
}

impl Now {
    /// A clock that is not synchronised with any coordinator (a site on its own, tests).
    pub fn local(wall: Instant, local_us: u64) -> Self {
        Now {
            wall,
            coordinator_us: local_us,
            synced: false,
        }
    }
}

/// A message for the link, on the channel it travels on.
#[derive(Debug, Clone, PartialEq)]
pub enum Transmit {
    /// Reliable, ordered: ownership, acknowledgements, commands, teaching.
    Control(Message),
    /// Newest wins: tool poses, time stamps, tree deltas.
    Datagram(Message),
    /// One stream per keyframe (newest wins per region).
    Keyframe(proto::RegionKeyframe),
}

/// Something the driver (or a future window) must know about.
#[derive(Debug, Clone, PartialEq)]
pub enum SessionEvent {
    /// The scene was reset: the simulation was rebuilt; tools and contact must be too.
    SceneReset { epoch: Epoch },
    /// The coordinator refused one of our commands.
    CommandRefused { command: String, reason: String },
    /// An instructor trajectory arrived (teaching).
    Teaching(TeachingTrajectory),
    /// A playback command arrived (teaching).
    Playback(Command),
    /// Another site's tool pose (the site's tools sample it at their simulated time).
    RemotePose(proto::ToolPose),
}

/// Why a reset request was not sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ResetError {
    #[error("only the instructor may reset the scene (this site is a {0})")]
    NotInstructor(Role),
}

/// How far ahead (s of simulated time) a site schedules its own cuts and releases: the path of the op
/// to the other sites that lead (owners and tool drivers run level, at most
/// `pacing::MAX_LEAD` apart) is one round trip to the coordinator (two hops), plus that
/// lead and a margin; at least 50 ms, at most 0.5 s (on longer paths a leader applies
/// the cut on arrival, late, and the owner's keyframes correct it).
pub fn topology_lead(rtt: Option<Duration>) -> f64 {
    let rtt = rtt.map_or(0.0, |d| d.as_secs_f64());
    (1.25 * rtt + pacing::MAX_LEAD + 0.01).clamp(0.05, 0.5)
}

/// The site's protocol state machine (see the module documentation).
pub struct SiteSession {
    cfg: SessionConfig,
    sites: SiteTable,
    epoch: Epoch,
    map: RegionMap,
    sync: SiteSync,
    inbox: Inbox,
    baselines: BaselineTracker,
    claims: Claims,
    clocks: PeerClocks,
    /// Wall-time origin of the pacing's clock: the session's creation, not the start of
    /// its simulation clock, so that stamps heard while waiting to start keep their
    /// times (a site may start on them, see [`Self::is_ready`]).
    origin: Instant,
    next_stamp: f64,
    next_pose: f64,
    /// Under hybrid: the local tool's recent samples.
    pose_history: inputs::InputHistory,
    /// Next step due (wall).
    next_due: Instant,
    /// When the driver should run the next step (wall).
    wake: Option<Instant>,
    welcomed_at: Option<Instant>,
    /// When, waiting to start, the session was first complete but for the other sites'
    /// clocks ([`Self::is_ready`]).
    complete_at: Option<Instant>,
    /// Wall time (s, pacing origin) of the next presence stamp while waiting to start.
    next_presence: f64,
    got_snapshot: bool,
    started: bool,
    /// A reset to apply when the simulated time reaches it: (new epoch, sim time s).
    scheduled_reset: Option<(Epoch, f64)>,
    /// Topology ops of the current epoch received before our clock reached the simulated
    /// time they were made at, in order of that time: applied by [`Self::apply_due`].
    held_topology: Vec<proto::TopologyOp>,
    /// Topology ops of the epoch a scheduled reset leads to, made by sites that reset
    /// before us: taken when we reset.
    next_epoch_topology: Vec<proto::TopologyOp>,
    /// Simulated time (s) of the last refinement op that changed our lattice: a frame
    /// made before it would take a region's tree back to before it.
    refined_at: f64,
    /// One of our own cuts was applied since [`Self::take_own_cut_applied`].
    own_cut_applied: bool,
    /// What to ask for again once a lost link is back (see `reconnect`).
    rejoin: reconnect::Rejoin,
    transmits: VecDeque<Transmit>,
    events: VecDeque<SessionEvent>,
    stats: SessionStats,
    /// Our simulation's topology epoch when frames were last produced (stamped on our
    /// keyframes).
    topology_epoch: u32,
}

impl SiteSession {
    /// A session for a site whose simulation is `sim`, at wall time `now`.
    pub fn new(cfg: SessionConfig, sim: &Simulation, now: Instant) -> Self {
        let map = RegionMap::for_simulation(sim);
        let config = sync_config();
        SiteSession {
            sync: cfg.new_sync(map.clone()),
            map,
            baselines: BaselineTracker::new(BaselineConfig {
                history: config.baseline_history,
                ..BaselineConfig::default()
            }),
            clocks: PeerClocks::new(cfg.playout_lag).for_strategy(cfg.pacing_strategy()),
            cfg,
            sites: SiteTable::default(),
            epoch: 0,
            inbox: Inbox::default(),
            claims: Claims::default(),
            origin: now,
            next_stamp: 0.0,
            next_pose: 0.0,
            pose_history: inputs::InputHistory::default(),
            next_due: now,
            wake: None,
            welcomed_at: None,
            complete_at: None,
            next_presence: 0.0,
            got_snapshot: false,
            started: false,
            scheduled_reset: None,
            held_topology: Vec::new(),
            next_epoch_topology: Vec::new(),
            refined_at: f64::NEG_INFINITY,
            own_cut_applied: false,
            rejoin: reconnect::Rejoin::default(),
            transmits: VecDeque::new(),
            events: VecDeque::new(),
            stats: SessionStats::default(),
            topology_epoch: 0,
        }
    }

    // ----- state -------------------------------------------------------------------

    pub fn site_id(&self) -> Option<SiteId> {
        self.sites.me()
    }

    pub fn epoch(&self) -> Epoch {
        self.epoch
    }

    pub fn role(&self) -> Role {
        self.cfg.role
    }

    pub fn sites(&self) -> &SiteTable {
        &self.sites
    }

    pub fn stats(&self) -> &SessionStats {
        &self.stats
    }

    /// Ownership intervals held, the open ones closed at `t` (s of sim time).
    pub fn owned_intervals(&self, t: f64) -> Vec<(RegionId, f64, f64)> {
        self.claims.intervals(t)
    }

    /// Whether this site is linked to a session (else it runs alone).
    pub fn linked(&self) -> bool {
        self.cfg.linked
    }

    /// Whether topology ops are applied at their simulated time (held until our clock
    /// reaches it; our own cuts scheduled a little ahead): linked, under the strategies
    /// whose sites simulate every tool (hybrid, input-only), where a cut must part the
    /// tissue at the same moment everywhere. Under keyframe and full-state sync the
    /// owners' frames carry the shape and ops are applied on arrival: holding them there
    /// was measured to make the dissection demo worse (a claim tussle after the duct's
    /// cut, up to 284 mm, and a step p99 of 45–60 ms, one run).
    pub fn times_topology(&self) -> bool {
        self.cfg.linked && self.cfg.strategy.simulates_remote_tools()
    }

    /// Whether one of our own cuts was applied (at its scheduled time) since the last
    /// call: the driver then claims the regions it separated.
    pub fn take_own_cut_applied(&mut self) -> bool {
        std::mem::take(&mut self.own_cut_applied)
    }

    /// The playout lag aimed at now (s).
    pub fn target_lag(&self) -> f64 {
        self.clocks.target_lag()
    }

    /// Under hybrid: a new input sample of `site`'s remote tool this site simulates arrived
    /// `late` seconds after the simulation needed it (negative: that much early) while
    /// the simulation was about to step to `at` (s). A late input raises the playout lag
    /// (see `PeerClocks::input_shortfall`).
    pub fn input_lateness(&mut self, site: SiteId, late: f64, at: f64, now: Now) {
        if late > 0.0 {
            self.stats.late_inputs += 1;
            tracing::trace!(
                late_ms = late * 1e3,
                at,
                target_ms = self.clocks.target_lag() * 1e3,
                "late input"
            );
        }
        let wall = self.wall(now.wall);
        self.clocks.input_shortfall(site, late, at, wall);
    }

    /// The regions holding an element that a cut separated (none without a cut).
    pub fn regions_of_cut(&self, sim: &Simulation) -> Vec<RegionId> {
        let mut regions: Vec<RegionId> = sim
            .separation()
            .map(|sep| {
                sep.crossed
                    .iter()
                    .filter_map(|t| self.map.region_of_root(t.root))
                    .collect()
            })
            .unwrap_or_default();
        regions.sort_unstable();
        regions.dedup();
        regions
    }

    /// Regions near the deformed point `p` (m) within `radius` (m).
    pub fn regions_near(
        &self,
        sim: &Simulation,
        p: &nalgebra::Vector3<f64>,
        radius: f64,
    ) -> Vec<RegionId> {
        self.map.regions_near_deformed(sim, p, radius)
    }

    /// What a window or HUD shows of the session.
    pub fn snapshot(&self) -> SessionSnapshot {
        SessionSnapshot {
            site: self.sites.me(),
            role: Some(self.cfg.role),
            epoch: self.epoch,
            sites: self.sites.len(),
            owned: self.claims.owned().collect(),
            remote_owners: self.clocks.owners.iter().map(|(&r, &s)| (r, s)).collect(),
            divergence_m: self.sync.divergence_m(),
        }
    }

    fn wall(&self, now: Instant) -> f64 {
        now.saturating_duration_since(self.origin).as_secs_f64()
    }

    // ----- inputs ------------------------------------------------------------------

    /// A message from the coordinator or relayed from another site. Frames whose
    /// simulated time has come are applied to `sim` at once; a reset rebuilds `sim`.
    pub fn handle_message(
        &mut self,
        sim: &mut Simulation,
        msg: Message,
        now: Now,
    ) -> Result<(), SimError> {
        let t = sim.time();
        let wall = self.wall(now.wall);
        match msg {
            Message::ToolPose(p) if self.sites.is_other(p.site) => {
                let pose = pacing::pose_key(p.position, p.orientation, p.jaw_rad);
                self.clocks
                    .tool_pose(p.site, p.tool, p.sim_time_s, pose, wall);
                self.events.push_back(SessionEvent::RemotePose(p));
            }
            Message::ToolPoseHistory(h) if self.sites.is_other(h.site) => {
                if let Some(newest) = h.samples.last() {
                    let pose =
                        pacing::pose_key(newest.position, newest.orientation, newest.jaw_rad);
                    self.clocks
                        .tool_pose(h.site, h.tool, newest.sim_time_s, pose, wall);
                }
                // Newest first: the older samples a datagram repeats then fill gaps
                // behind the newest, and only the newest tells how late the datagram came
                // (`Tools::remote_pose`).
                let skip = h.samples.len().saturating_sub(proto::MAX_POSE_SAMPLES);
                for s in h.samples.into_iter().skip(skip).rev() {
                    if !s.sim_time_s.is_finite() {
                        continue;
                    }
                    self.events
                        .push_back(SessionEvent::RemotePose(proto::ToolPose {
                            site: h.site,
                            tool: h.tool,
                            sim_time_s: s.sim_time_s,
                            position: s.position,
                            orientation: s.orientation,
                            jaw_rad: s.jaw_rad,
                            velocity: [0.0; 3],
                            angular_velocity: [0.0; 3],
                        }));
                }
            }
            Message::Keyframe(kf) if self.sites.is_other(kf.owner) => {
                // Ops we hold for their time count: they are applied before a keyframe
                // made after them is due.
                // (Refinements are not counted in the topology epoch.)
                let counted =
                    |h: &&proto::TopologyOp| !matches!(h.kind, proto::TopologyKind::Refine { .. });
                let reachable = if kf.epoch == self.epoch {
                    let held = self.held_topology.iter().filter(counted).count();
                    sim.topology().epoch() + held as u32
                } else {
                    // A keyframe of the coming epoch: the simulation our reset builds
                    // starts with no op, and takes the ops of that epoch we hold.
                    let next = self
                        .next_epoch_topology
                        .iter()
                        .filter(|h| h.epoch == kf.epoch);
                    next.filter(counted).count() as u32
                };
                if kf.topology > reachable {
                    debug!(
                        region = kf.region,
                        topology = kf.topology,
                        "keyframe of a topology not reached yet dropped"
                    );
                    self.stats.keyframes_topology_dropped += 1;
                    return Ok(());
                }
                if !self.accepts_epoch(kf.epoch) {
                    debug!(
                        region = kf.region,
                        epoch = kf.epoch,
                        "keyframe of another epoch dropped"
                    );
                    return Ok(());
                }
                self.clocks.keyframe_arrived(kf.owner, kf.sim_time, wall);
                if self.undoes_refinement(sim, kf.region, kf.sim_time, &kf.tree_bits) {
                    debug!(
                        region = kf.region,
                        t = kf.sim_time,
                        refined_at = self.refined_at,
                        "keyframe made before a refinement we applied dropped"
                    );
                    self.stats.frames_refinement_dropped += 1;
                    return Ok(());
                }
                self.receive(sim, kf.epoch, wire::keyframe_from_wire(&kf))?;
            }
            Message::Snapshot(s) => {
                if !self.started && s.sim_time_s > sim.time() {
                    // A late joiner takes the session's simulated time, so that the
                    // snapshot's keyframes (and everything after) are current for it.
                    info!(t = s.sim_time_s, "joining a running session");
                    sim.set_time(s.sim_time_s);
                }
                self.got_snapshot = true;
                if s.epoch != self.epoch {
                    if self.scheduled_reset.is_some_and(|(e, _)| e == s.epoch) {
                        // The reset to it is on its way: its ops wait for it.
                        for op in s.topology.iter().filter(|o| o.epoch == s.epoch) {
                            let known = self
                                .next_epoch_topology
                                .iter()
                                .any(|h| (h.site, h.seq) == (op.site, op.seq));
                            if !known {
                                self.next_epoch_topology.push(op.clone());
                            }
                        }
                    } else if self.started {
                        // Back after a reset we missed (a lost link): our simulation is
                        // of an older epoch, so it is rebuilt like at a reset.
                        info!(epoch = s.epoch, "the session was reset while we were away");
                        self.scheduled_reset = None;
                        self.reset(sim, s.epoch)?;
                    } else {
                        info!(epoch = s.epoch, "taking the session's scene epoch");
                        self.scheduled_reset = None;
                        self.epoch = s.epoch;
                    }
                }
                for op in &s.topology {
                    if op.epoch == self.epoch {
                        self.apply_topology(sim, op)?;
                    }
                }
                for kf in s.keyframes {
                    if self.sites.is_other(kf.owner)
                        && kf.epoch == self.epoch
                        && kf.topology <= sim.topology().epoch()
                    {
                        self.receive(sim, kf.epoch, wire::keyframe_from_wire(&kf))?;
                    }
                }
                for o in s.owners {
                    self.set_owner(o.region, o.site);
                }
            }
            Message::OwnershipGrant(g) => {
                self.set_owner(g.region, g.site);
                if self.sites.me() == Some(g.site) {
                    self.claims.granted(g.region, t);
                } else {
                    self.claims.lost(g.region, t);
                }
            }
            Message::OwnershipRelease(r) => {
                // The release takes effect when our clock reaches the owner's time of
                // release (as heard now), not on arrival: a lagging follower still has
                // the owner's last frames to play.
                let at = self.clocks.release_time(r.site, wall);
                self.inbox.defer_release(r.region, at);
                self.clocks.owners.remove(&r.region);
                self.claims.lost(r.region, t);
            }
            Message::OwnershipDeny(d) => self.claims.denied(d.region),
            Message::SimTime(s) if self.sites.is_other(s.site) => {
                let transit = now
                    .synced
                    .then(|| (now.coordinator_us as f64 - s.wall_send_us as f64) / 1e6);
                self.clocks.heard(s.site, s.sim_time_s, wall, transit);
            }
            Message::TreeDelta(d) if self.sites.is_other(d.site) => {
                if !self.accepts_epoch(d.epoch) {
                    debug!(
                        region = d.region,
                        epoch = d.epoch,
                        "tree delta of another epoch dropped"
                    );
                    return Ok(());
                }
                if self.times_topology() && d.sim_time < self.refined_at {
                    debug!(
                        region = d.region,
                        "tree delta made before a refinement we applied dropped"
                    );
                    self.stats.frames_refinement_dropped += 1;
                    return Ok(());
                }
                self.receive(sim, d.epoch, wire::delta_from_wire(d))?;
            }
            Message::KeyframeAck(a) => {
                self.baselines.on_ack(a.site, a.region, a.keyframe_id);
                if a.shows_keyframes && self.sync.follower_shows_keyframes() {
                    info!(
                        site = a.site,
                        "a follower shows our keyframes: sending on drift as well"
                    );
                }
            }
            Message::SiteJoined(s) => self.sites.joined(s),
            Message::Leave(l) => {
                self.sites.left(l.site);
                self.baselines.remove_receiver(l.site);
            }
            Message::Command(Command::ResetScene { epoch, sim_time_s }) => {
                if epoch != self.epoch {
                    info!(epoch, at = sim_time_s, "scene reset scheduled");
                    self.scheduled_reset = Some((epoch, sim_time_s));
                    self.apply_due(sim)?;
                }
            }
            Message::Command(c) => self.events.push_back(SessionEvent::Playback(c)),
            Message::CommandRefused(r) => {
                warn!(command = %r.command, reason = %r.reason, "command refused by the coordinator");
                self.events.push_back(SessionEvent::CommandRefused {
                    command: r.command,
                    reason: r.reason,
                });
            }
            Message::Teaching(tr) => self.events.push_back(SessionEvent::Teaching(tr)),
            Message::Topology(op) => {
                if op.epoch == self.epoch {
                    self.take_topology(sim, op)?;
                } else if self.scheduled_reset.is_some_and(|(e, _)| e == op.epoch) {
                    // Its maker reset before us (it runs ahead): the op waits for our
                    // reset, as the new epoch's frames wait in the inbox.
                    debug!(epoch = op.epoch, "topology op of the coming epoch held");
                    self.next_epoch_topology.push(op);
                } else {
                    debug!(epoch = op.epoch, "topology op of another epoch dropped");
                }
            }
            other => debug!(kind = other.kind(), "ignored message"),
        }
        Ok(())
    }

    /// Takes a frame from another site (held until our clock reaches it) and applies
    /// what is due. Under input-only nothing is applied.
    fn receive(
        &mut self,
        sim: &mut Simulation,
        epoch: Epoch,
        frame: sim_core::sync::SyncFrame,
    ) -> Result<(), SimError> {
        if self.cfg.strategy == SyncStrategy::InputOnly {
            return Ok(());
        }
        self.inbox.push(epoch, frame);
        self.apply_due(sim)
    }

    /// Frames of the current epoch, and of the one a scheduled reset leads to (they wait
    /// in the inbox for the reset), are accepted.
    fn accepts_epoch(&self, epoch: Epoch) -> bool {
        epoch == self.epoch || self.scheduled_reset.is_some_and(|(e, _)| e == epoch)
    }

    /// Ownership of `region` is `owner`'s.
    fn set_owner(&mut self, region: RegionId, owner: SiteId) {
        debug!(region, owner, me = ?self.sites.me(), "ownership");
        if self.sites.me() == Some(owner) {
            self.sync.on_grant(region);
            self.clocks.owners.remove(&region);
        } else {
            self.sync.on_remote_grant(region);
            self.clocks.owners.insert(region, owner);
        }
        self.inbox.cancel_release(region);
    }

    /// Applies a scheduled reset, then the frames and releases whose simulated time has
    /// come (before the step), then the topology ops held for it, and acknowledges the
    /// keyframes applied. Frames go first: a frame stamped `t` was made before its owner
    /// applied the ops of time `t` (at the start of its next step), so applied after them
    /// it would take back what they changed.
    pub fn apply_due(&mut self, sim: &mut Simulation) -> Result<(), SimError> {
        if let Some((epoch, at)) = self.scheduled_reset
            && at <= sim.time() + 0.5 * sim.options().dt
        {
            self.scheduled_reset = None;
            self.reset(sim, epoch)?;
        }
        let started = Instant::now();
        let applied = self.inbox.apply_due(self.epoch, &mut self.sync, sim);
        if !applied.is_empty() {
            self.stats.apply_us_total += started.elapsed().as_secs_f64() * 1e6;
        }
        for (region, keyframe_id) in applied {
            self.stats.keyframes_applied += 1;
            if let Some(me) = self.sites.me() {
                self.control(Message::KeyframeAck(proto::KeyframeAck {
                    region,
                    keyframe_id,
                    site: me,
                    shows_keyframes: self.sync.shows_keyframes(),
                }));
            }
        }
        let due = self
            .held_topology
            .partition_point(|h| h.sim_time <= sim.time() + 0.5 * sim.options().dt);
        for op in self.held_topology.drain(..due).collect::<Vec<_>>() {
            self.apply_topology(sim, &op)?;
        }
        Ok(())
    }

    /// The regions the local tool touches at `t`: claims the new ones and releases those
    /// left alone for [`claims::RELEASE_AFTER`] once they are at rest (with a final
    /// keyframe first, so that the others end where we are). Input-only sites claim too: ownership then says whose
    /// organ the others are compared with. Observers never claim.
    pub fn handle_touched(&mut self, sim: &Simulation, touched: &[RegionId], now: Now) {
        self.topology_epoch = sim.topology().epoch();
        self.rejoin.touched(touched);
        if !self.cfg.linked || self.cfg.role == Role::Observer {
            return;
        }
        let Some(me) = self.sites.me() else { return };
        let t = sim.time();
        for &region in touched {
            if self.claims.touch(region, t) {
                self.control(Message::OwnershipRequest(proto::OwnershipRequest {
                    region,
                    claim_time_us: now.coordinator_us,
                }));
            }
        }
        // Region speeds only when a release is due.
        let idle = self.claims.stale(t, |_| 0.0);
        let speeds = if idle.is_empty() {
            Vec::new()
        } else {
            self.map.max_speeds(sim.lattice(), sim.velocities())
        };
        let speed = |r: RegionId| speeds.get(r as usize).copied().unwrap_or(0.0);
        for region in self.claims.stale(t, speed) {
            if let Some(frame) = self.sync.release(sim, region) {
                self.send_frame(frame, me, now);
            }
            self.baselines.reset_region(region);
            self.claims.lost(region, t);
            self.control(Message::OwnershipRelease(proto::OwnershipRelease {
                region,
                site: me,
            }));
        }
    }

    /// Before the step: remote regions follow their owners.
    pub fn before_step(&mut self, sim: &mut Simulation) {
        self.sync.before_step(sim);
    }

    /// After the step: the frames we owe the others for the regions we own, and our time
    /// stamp.
    pub fn after_step(&mut self, sim: &Simulation, now: Now) {
        self.topology_epoch = sim.topology().epoch();
        if !self.cfg.linked || self.cfg.role == Role::Observer {
            return;
        }
        let Some(me) = self.sites.me() else { return };
        let baselines = &self.baselines;
        let receivers: Vec<SiteId> = self.sites.receivers().collect();
        // A delta may reference only a keyframe every receiver has acknowledged.
        let frames = self.sync.after_step(sim, |region| {
            baselines.common_baseline(region, receivers.iter().copied())
        });
        for f in frames {
            self.send_frame(f, me, now);
        }
        let t = sim.time();
        if t >= self.next_stamp {
            self.next_stamp = t + SIM_TIME_INTERVAL;
            self.send_clock(me, sim, now);
        }
    }

    /// Our simulation clock as it stands, to every other site (a datagram).
    fn send_clock(&mut self, me: SiteId, sim: &Simulation, now: Now) {
        self.datagram(Message::SimTime(proto::SimTimeStamp {
            site: me,
            sim_time_s: sim.time(),
            step: sim.steps(),
            wall_send_us: now.coordinator_us,
        }));
    }

    /// Whether the local tool's pose is due at `t` (every step under input-only and
    /// hybrid, where poses drive the others' simulations; else every [`POSE_INTERVAL`]).
    pub fn pose_due(&self, t: f64) -> bool {
        self.cfg.linked
            && self.cfg.role != Role::Observer
            && self.sites.me().is_some()
            && (self.cfg.strategy.simulates_remote_tools() || t >= self.next_pose)
    }

    /// The local tool's pose (made by the site's tools with our id) goes out. Under
    /// hybrid it joins the tool's recent samples, sent every [`POSE_HISTORY_INTERVAL`] as
    /// one [`proto::ToolPoseHistory`] (what it repeats: `inputs::InputHistory`).
    pub fn send_pose(&mut self, pose: proto::ToolPose) {
        if self.cfg.strategy != SyncStrategy::Hybrid {
            self.next_pose = pose.sim_time_s + POSE_INTERVAL;
            self.datagram(Message::ToolPose(pose));
            return;
        }
        self.pose_history.push(pose);
        // Half a step of slack: sample times are multiples of dt in floating point.
        if pose.sim_time_s + 0.5 * self.cfg.options.dt < self.next_pose {
            return;
        }
        self.next_pose = pose.sim_time_s + POSE_HISTORY_INTERVAL;
        let samples = self.pose_history.datagram(self.cfg.options.dt);
        self.datagram(Message::ToolPoseHistory(proto::ToolPoseHistory {
            site: pose.site,
            tool: pose.tool,
            samples,
        }));
    }

    /// A control message of the site's own (teaching trajectories).
    pub fn send_control(&mut self, msg: Message) {
        self.control(msg);
    }

    /// An instructor's window (or script) asks for a scene reset at simulated time `t`
    /// (s). Every site resets when its clock reaches `t` plus a margin that covers the
    /// round trip to the coordinator (`rtt`), so the instructor's own reset is not late.
    /// Without a link the reset happens locally at the next step.
    pub fn request_reset(&mut self, t: f64, rtt: Option<Duration>) -> Result<(), ResetError> {
        if self.cfg.role != Role::Instructor {
            return Err(ResetError::NotInstructor(self.cfg.role));
        }
        if self.cfg.linked {
            let margin =
                (2.0 * rtt.map_or(0.0, |d| d.as_secs_f64())).clamp(RESET_MARGIN, MAX_RESET_MARGIN);
            info!(
                epoch = self.epoch,
                at = t + margin,
                "requesting a scene reset"
            );
            self.control(Message::Command(Command::ResetScene {
                epoch: self.epoch,
                sim_time_s: t + margin,
            }));
        } else {
            self.scheduled_reset = Some((self.epoch.wrapping_add(1), t));
        }
        Ok(())
    }

    /// The step ended at simulated time `t`: pacing against the sites followed. A leading
    /// site (`tool_active`: its tool is moving, or, except under hybrid, it owns or claims
    /// a region) runs level with the other leaders; a follower keeps the playout lag
    /// behind the sites it follows by slewing its step rate. The next step is due at
    /// [`Self::poll_timeout`].
    pub fn end_step(&mut self, t: f64, tool_active: bool, now: Instant) -> Pace {
        let leading = self.leads(tool_active);
        let pace = self
            .clocks
            .pace(t, self.wall(now), leading, self.cfg.realtime);
        if let Some(b) = pace.behind {
            self.stats.behind_sum += b;
            self.stats.behind_steps += 1;
            let error = b - self.clocks.target_lag();
            if self.stats.lag_reached_at.is_none() && error.abs() <= pacing::LAG_REACHED_WITHIN {
                self.stats.lag_reached_at = Some(t);
            }
            if self.stats.lag_reached_at.is_some() {
                self.stats.reached_behind_sum += b;
                self.stats.reached_behind_steps += 1;
            }
            if self.stats.behind_steps.is_multiple_of(50) {
                tracing::trace!(
                    t,
                    behind_ms = b * 1e3,
                    rate = pace.rate,
                    lag = ?self.clocks.lag_terms(),
                    "pacing"
                );
            }
        }
        let dt = self.cfg.options.dt;
        let mut wake = now;
        if self.cfg.realtime {
            // The next step is due dt / rate of wall time after this one was.
            self.next_due += Duration::from_secs_f64(dt / pace.rate);
            wake = wake.max(self.next_due);
        }
        // Never run ahead of the owners whose regions we show (their keyframes would
        // arrive from our past); not under hybrid, see `pacing`.
        if pace.hold > 0.0 {
            let hold = Duration::from_secs_f64(pace.hold);
            self.stats.paced_seconds += pace.hold;
            wake += hold;
            self.next_due += hold;
        }
        self.wake = Some(wake);
        pace
    }

    /// Whether this site leads (owns or claims a region, except under hybrid, or
    /// `tool_active`: its tool is moving, `site::Tools::local_moving`; it then keeps no
    /// playout lag, see [`pacing`]) rather than follows.
    pub fn leads(&self, tool_active: bool) -> bool {
        (self.claims.any() && self.clocks.leads_by_claims()) || tool_active
    }

    // ----- outputs -----------------------------------------------------------------

    /// When the next step is due (wall); `None`: at once.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.wake
    }

    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.transmits.pop_front()
    }

    pub fn poll_event(&mut self) -> Option<SessionEvent> {
        self.events.pop_front()
    }

    // ----- internals ---------------------------------------------------------------

    fn control(&mut self, msg: Message) {
        if self.cfg.linked {
            self.transmits.push_back(Transmit::Control(msg));
        }
    }

    fn datagram(&mut self, msg: Message) {
        if self.cfg.linked {
            self.transmits.push_back(Transmit::Datagram(msg));
        }
    }

    fn send_frame(&mut self, frame: sim_core::sync::SyncFrame, me: SiteId, now: Now) {
        match wire::frame_to_wire(frame, me, self.epoch) {
            Some(WireFrame::Keyframe(mut kf)) => {
                kf.topology = self.topology_epoch;
                for r in self.sites.receivers() {
                    self.baselines
                        .on_sent(r, kf.region, kf.keyframe_id, now.coordinator_us);
                }
                if self.cfg.linked {
                    self.transmits.push_back(Transmit::Keyframe(kf));
                }
            }
            Some(WireFrame::Delta(d)) => self.datagram(Message::TreeDelta(d)),
            None => {}
        }
    }

    /// The scene restarts from its initial state in epoch `epoch`, at the current
    /// simulated time; ownership, pending frames and baselines of the old epoch are gone.
    fn reset(&mut self, sim: &mut Simulation, epoch: Epoch) -> Result<(), SimError> {
        if epoch == self.epoch {
            debug!(epoch, "reset to the current epoch ignored");
            return Ok(());
        }
        let t = sim.time();
        info!(from = self.epoch, to = epoch, t, "scene reset");
        let mut fresh = Simulation::new(self.cfg.scene.clone(), self.cfg.options.clone())?;
        fresh.set_time(t);
        *sim = fresh;
        self.epoch = epoch;
        self.sync = self.cfg.new_sync(self.map.clone());
        self.pose_history.clear();
        self.inbox.reset(epoch);
        self.held_topology.clear();
        self.refined_at = f64::NEG_INFINITY;
        self.baselines.clear();
        self.claims.clear(t);
        self.clocks.owners.clear();
        self.stats.resets += 1;
        self.events.push_back(SessionEvent::SceneReset { epoch });
        // Ops of this epoch made by sites that reset before us: held and applied by
        // their time, after the frames of that time, like every op (those already due go
        // at the end of this `apply_due`).
        for op in std::mem::take(&mut self.next_epoch_topology) {
            if op.epoch != epoch {
                continue;
            }
            if self.times_topology() {
                self.hold_topology(op);
            } else {
                self.apply_topology(sim, &op)?;
            }
        }
        Ok(())
    }
}
