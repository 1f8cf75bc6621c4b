//! The coordinator's session logic, sans IO: joins, roles, relay decisions, ownership, the
//! latest keyframe per region, the site table. The async shell in [`crate::coordinator`]
//! feeds it decoded messages with the coordinator time (µs) and executes the returned
//! [`Action`]s; nothing here touches a socket or a clock.

use std::collections::{BTreeMap, BTreeSet};

use bytes::Bytes;
use proto::{
    Command, JoinHandshake, KeyframeId, Leave, Message, Nonce, OwnershipArbiter, PeerLiveness,
    Refusal, RefusalReason, RegionId, RegionKeyframe, Role, SessionConfig, SiteEntry, SiteId,
    SiteStatus, Snapshot, Status, TeachingTrajectory, Welcome, close_code,
};

/// Recipients of a control message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    One(SiteId),
    AllExcept(SiteId),
    All,
}

impl Target {
    pub fn includes(&self, site: SiteId) -> bool {
        match *self {
            Target::One(s) => s == site,
            Target::AllExcept(s) => s != site,
            Target::All => true,
        }
    }
}

/// Why a message was not relayed or applied.
/// Topology operations kept per scene epoch (cuts of one training session are a few
/// dozen; the bound keeps a misbehaving site from growing the coordinator's memory).
pub const MAX_TOPOLOGY_OPS: usize = 4096;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DropReason {
    /// Observers only receive.
    Observer,
    /// Only instructors may send this.
    NotInstructor,
    /// The sender does not own the region.
    NotOwner,
    /// Message of an older topology epoch.
    StaleEpoch,
    /// Keyframe not newer than the one held.
    StaleKeyframe,
    /// Internally inconsistent content (e.g. node arrays of different lengths).
    Inconsistent,
    /// Message kind not accepted from a site on this channel.
    NotAllowed,
    /// No recipient (e.g. ack for a region whose owner left).
    NoRecipient,
    /// Sender is not (or no longer) a member.
    UnknownSite,
    /// The sender exceeded its relay budget ([`RelayBudget`]).
    OverBudget,
}

/// Something the shell must do.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Send `msg` reliably on the control stream of every site in `to`.
    Control { to: Target, msg: Message },
    /// Close a site's connection once its queued control frames are flushed.
    Close {
        site: SiteId,
        code: u32,
        reason: String,
    },
    /// A message from `site` was dropped (count and log it).
    Drop {
        site: SiteId,
        kind: &'static str,
        reason: DropReason,
    },
}

/// What to do with a datagram.
#[derive(Debug, Clone, PartialEq)]
pub enum DatagramVerdict {
    /// Relay to all other sites. `restamped`: the message differs from what was received
    /// (sender id corrected), so the received bytes cannot be forwarded as they are.
    Relay {
        msg: Message,
        restamped: bool,
    },
    /// Answer the sender with this message (a clock pong: the shell fills in `t3_us`).
    Reply(Message),
    /// Consumed by the coordinator.
    Consumed,
    Drop(DropReason),
}

/// A stored keyframe: the decoded message and its encoded frame for relaying.
#[derive(Debug, Clone)]
pub struct StoredKeyframe {
    pub keyframe: RegionKeyframe,
    /// The length-prefixed frame as relayed.
    pub frame: Bytes,
}

/// Per-site state.
#[derive(Debug, Clone)]
pub struct SiteState {
    pub entry: SiteEntry,
    pub sim_time_s: f64,
    pub step: u64,
    /// Coordinator time of the last sim-time stamp (µs).
    pub sim_time_at_us: u64,
    pub rtt_us: u32,
    pub joined_at_us: u64,
    /// Armed by the site's first heartbeat.
    pub liveness: Option<PeerLiveness>,
    /// Coordinator time anything (datagram, control frame, keyframe) was last heard from the
    /// site (µs); the join time until then.
    pub last_heard_us: u64,
    /// Relay tokens left as of `relay_tokens_at_us` ([`RelayBudget`]).
    pub relay_tokens: f64,
    pub relay_tokens_at_us: u64,
}

/// Result of a successful join.
#[derive(Debug, Clone)]
pub struct Joined {
    pub welcome: Welcome,
    /// Snapshot to send on a unidirectional stream right after the Welcome.
    pub snapshot: Snapshot,
    /// Further actions (SiteJoined to others, teaching state to the newcomer; when the join
    /// resumed a silent member of the same name, that member's departure and close first).
    pub actions: Vec<Action>,
    /// The silent member this join replaced (see [`Session::join`]).
    pub replaced: Option<SiteId>,
}

/// How many datagrams per second one site may have relayed (tool poses, pose histories,
/// clock stamps, tree deltas): a token bucket per site. A site's relayed datagram costs the
/// coordinator one decryption and one encryption per peer, so without a bound one site
/// sending as fast as loopback allows takes the coordinator's CPU from every session. The
/// default leaves a normal site (hybrid: 125 input datagrams/s, 20 stamps/s, up to ~33
/// deltas/s, so under 200/s) five times its rate and a catch-up burst of half a second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelayBudget {
    /// Sustained datagrams per second.
    pub rate_per_s: f64,
    /// Bucket size (datagrams).
    pub burst: f64,
}

impl Default for RelayBudget {
    fn default() -> Self {
        Self {
            rate_per_s: 1000.0,
            burst: 500.0,
        }
    }
}

/// A join may replace a member of the same name and role that has been silent for this
/// many heartbeat intervals (see [`Session::join`]).
pub const RESUME_SILENCE_INTERVALS: u64 = 2;

/// Session logic.
#[derive(Debug)]
pub struct Session {
    join: JoinHandshake,
    arbiter: OwnershipArbiter,
    sites: BTreeMap<SiteId, SiteState>,
    keyframes: BTreeMap<RegionId, StoredKeyframe>,
    epoch: u32,
    trajectories: BTreeMap<u32, TeachingTrajectory>,
    /// Topology operations (cuts) of the current epoch, in arrival order, for late joiners.
    topology: Vec<proto::TopologyOp>,
    playback: Option<Command>,
    relay_budget: RelayBudget,
}

impl Session {
    pub fn new(config: SessionConfig) -> Self {
        Self {
            join: JoinHandshake::new(config),
            arbiter: OwnershipArbiter::default(),
            sites: BTreeMap::new(),
            keyframes: BTreeMap::new(),
            epoch: 0,
            trajectories: BTreeMap::new(),
            topology: Vec::new(),
            playback: None,
            relay_budget: RelayBudget::default(),
        }
    }

    /// Change the per-site relay budget (applies from the next datagram on).
    pub fn set_relay_budget(&mut self, budget: RelayBudget) {
        self.relay_budget = budget;
    }

    pub fn config(&self) -> &SessionConfig {
        self.join.config()
    }

    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    pub fn site(&self, site: SiteId) -> Option<&SiteState> {
        self.sites.get(&site)
    }

    pub fn sites(&self) -> impl Iterator<Item = &SiteState> {
        self.sites.values()
    }

    pub fn role(&self, site: SiteId) -> Option<Role> {
        self.sites.get(&site).map(|s| s.entry.role)
    }

    pub fn owner(&self, region: RegionId) -> Option<SiteId> {
        self.arbiter.owner(region)
    }

    pub fn keyframe(&self, region: RegionId) -> Option<&StoredKeyframe> {
        self.keyframes.get(&region)
    }

    /// Newest simulation time reported by any site (s).
    pub fn max_sim_time(&self) -> f64 {
        self.sites
            .values()
            .map(|s| s.sim_time_s)
            .fold(0.0, f64::max)
    }

    /// Current snapshot for a late joiner.
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            sim_time_s: self.max_sim_time(),
            epoch: self.epoch,
            owners: self.arbiter.owners(),
            keyframes: self
                .keyframes
                .values()
                .map(|k| k.keyframe.clone())
                .collect(),
            topology: self.topology.clone(),
        }
    }

    /// The member a join of this name and role may replace: one of the same name and role
    /// that has not been heard for [`RESUME_SILENCE_INTERVALS`] heartbeat intervals.
    fn resumable(&self, join: &proto::Join, now_us: u64) -> Option<SiteId> {
        let silence = RESUME_SILENCE_INTERVALS * self.config().heartbeat_interval_us;
        self.sites
            .values()
            .find(|s| s.entry.name == join.site_name)
            .filter(|s| {
                s.entry.role == join.role && now_us.saturating_sub(s.last_heard_us) >= silence
            })
            .map(|s| s.entry.site)
    }

    /// Handle a Join at coordinator time `now_us`.
    ///
    /// **Resume.** A site whose connection broke reconnects before the coordinator noticed
    /// the loss (liveness needs 2.4 heartbeat intervals, the QUIC idle timeout 10 s); its
    /// name is then still taken. If the join passes every other check (version, session,
    /// token, scene, name) and the member holding the name has the same role and has been
    /// silent for [`RESUME_SILENCE_INTERVALS`] heartbeat intervals, that member is removed
    /// (as if timed out: ownership released, `Leave` to the others, its connection closed
    /// with `close_code::TIMED_OUT`) and the join proceeds with a new site id. A member that
    /// is still talking keeps its name ([`RefusalReason::NameTaken`]).
    pub fn join(&mut self, join: &proto::Join, now_us: u64) -> Result<Joined, Refusal> {
        let mut actions = Vec::new();
        let mut replaced = None;
        if let Err(r) = self.join.validate(join, now_us)
            && r.reason == proto::RefusalReason::NameTaken
            && let Some(old) = self.resumable(join, now_us)
        {
            actions.extend(self.site_left(old, "replaced by its reconnection"));
            actions.push(Action::Close {
                site: old,
                code: close_code::TIMED_OUT,
                reason: "silent; replaced by a new connection of the same site".into(),
            });
            replaced = Some(old);
        }
        // After a replacement this cannot fail: the name and a slot were just freed.
        let welcome = self.join.handle_join(join, now_us)?;
        let entry = SiteEntry {
            site: welcome.site,
            name: join.site_name.clone(),
            role: join.role,
        };
        self.sites.insert(
            welcome.site,
            SiteState {
                entry: entry.clone(),
                sim_time_s: 0.0,
                step: 0,
                sim_time_at_us: now_us,
                rtt_us: 0,
                joined_at_us: now_us,
                liveness: None,
                last_heard_us: now_us,
                relay_tokens: self.relay_budget.burst,
                relay_tokens_at_us: now_us,
            },
        );
        let site = welcome.site;
        actions.push(Action::Control {
            to: Target::AllExcept(site),
            msg: Message::SiteJoined(entry),
        });
        for t in self.trajectories.values() {
            actions.push(Action::Control {
                to: Target::One(site),
                msg: Message::Teaching(t.clone()),
            });
        }
        if let Some(p) = &self.playback {
            actions.push(Action::Control {
                to: Target::One(site),
                msg: Message::Command(p.clone()),
            });
        }
        Ok(Joined {
            welcome,
            snapshot: self.snapshot(),
            actions,
            replaced,
        })
    }

    /// Check an administrative request (instructor token; see
    /// [`proto::JoinHandshake::validate_admin`]).
    pub fn validate_admin(&self, req: &proto::AdminRequest) -> Result<(), Refusal> {
        self.join.validate_admin(req)
    }

    /// Replace the revocation list. Members admitted by an invitation now revoked are
    /// removed: a [`RefusalReason::InvitationRevoked`] refusal to them, their departure to
    /// the others, their connection closed.
    pub fn set_revoked(&mut self, revoked: BTreeSet<Nonce>) -> Vec<Action> {
        let mut actions = Vec::new();
        for site in self.join.set_revoked(revoked) {
            actions.push(Action::Control {
                to: Target::One(site),
                msg: Message::Refusal(Refusal {
                    reason: RefusalReason::InvitationRevoked,
                    text: "the invitation this site joined with was revoked".into(),
                }),
            });
            actions.extend(self.site_left(site, "invitation revoked"));
            actions.push(Action::Close {
                site,
                code: close_code::INVITATION_REVOKED,
                reason: "invitation revoked".into(),
            });
        }
        actions
    }

    /// A site is gone (left, lost, kicked, timed out). Idempotent.
    pub fn site_left(&mut self, site: SiteId, reason: &str) -> Vec<Action> {
        if self.sites.remove(&site).is_none() {
            return Vec::new();
        }
        self.join.leave(site);
        let mut actions: Vec<Action> = self
            .arbiter
            .site_left(site)
            .into_iter()
            .map(|r| Action::Control {
                to: Target::All,
                msg: Message::OwnershipRelease(r),
            })
            .collect();
        actions.push(Action::Control {
            to: Target::AllExcept(site),
            msg: Message::Leave(Leave {
                site,
                reason: reason.to_string(),
            }),
        });
        actions
    }

    fn heard(&mut self, site: SiteId, now_us: u64) {
        if let Some(s) = self.sites.get_mut(&site) {
            s.last_heard_us = s.last_heard_us.max(now_us);
            if let Some(l) = s.liveness.as_mut() {
                l.on_heard(now_us);
            }
        }
    }

    fn drop_action(site: SiteId, msg: &Message, reason: DropReason) -> Vec<Action> {
        vec![Action::Drop {
            site,
            kind: msg.kind(),
            reason,
        }]
    }

    /// Checks shared by datagram and control paths for relayed state messages; returns the
    /// message with its sender id corrected.
    fn check_state_msg(
        &mut self,
        site: SiteId,
        msg: Message,
        now_us: u64,
    ) -> Result<(Message, bool), DropReason> {
        let budget = self.relay_budget;
        let Some(state) = self.sites.get_mut(&site) else {
            return Err(DropReason::UnknownSite);
        };
        let elapsed_s = now_us.saturating_sub(state.relay_tokens_at_us) as f64 * 1e-6;
        state.relay_tokens = (state.relay_tokens + elapsed_s * budget.rate_per_s).min(budget.burst);
        state.relay_tokens_at_us = state.relay_tokens_at_us.max(now_us);
        if state.relay_tokens < 1.0 {
            return Err(DropReason::OverBudget);
        }
        state.relay_tokens -= 1.0;
        if state.entry.role == Role::Observer {
            return Err(DropReason::Observer);
        }
        let mut restamped = false;
        let msg = match msg {
            Message::SimTime(mut s) => {
                restamped |= s.site != site;
                s.site = site;
                if s.sim_time_s.is_finite() {
                    state.sim_time_s = s.sim_time_s;
                    state.step = s.step;
                    state.sim_time_at_us = now_us;
                }
                Message::SimTime(s)
            }
            Message::ToolPose(mut p) => {
                restamped |= p.site != site;
                p.site = site;
                Message::ToolPose(p)
            }
            Message::ToolPoseHistory(mut p) => {
                restamped |= p.site != site;
                p.site = site;
                Message::ToolPoseHistory(p)
            }
            Message::TreeDelta(mut d) => {
                if d.epoch != self.epoch {
                    return Err(DropReason::StaleEpoch);
                }
                if self.arbiter.owner(d.region).is_some_and(|o| o != site) {
                    return Err(DropReason::NotOwner);
                }
                restamped |= d.site != site;
                d.site = site;
                Message::TreeDelta(d)
            }
            _ => return Err(DropReason::NotAllowed),
        };
        Ok((msg, restamped))
    }

    /// Handle a datagram from `site`, received at coordinator time `now_us`.
    pub fn on_datagram(&mut self, site: SiteId, msg: Message, now_us: u64) -> DatagramVerdict {
        if !self.sites.contains_key(&site) {
            return DatagramVerdict::Drop(DropReason::UnknownSite);
        }
        self.heard(site, now_us);
        match msg {
            Message::ClockPing(p) => DatagramVerdict::Reply(Message::ClockPong(proto::ClockPong {
                seq: p.seq,
                t1_us: p.t1_us,
                t2_us: now_us,
                t3_us: now_us,
            })),
            Message::Heartbeat(_) => {
                let interval = self.config().heartbeat_interval_us;
                if let Some(s) = self.sites.get_mut(&site)
                    && s.liveness.is_none()
                {
                    s.liveness = Some(PeerLiveness::new(interval, now_us));
                }
                DatagramVerdict::Consumed
            }
            m @ (Message::SimTime(_)
            | Message::ToolPose(_)
            | Message::ToolPoseHistory(_)
            | Message::TreeDelta(_)) => match self.check_state_msg(site, m, now_us) {
                Ok((msg, restamped)) => DatagramVerdict::Relay { msg, restamped },
                Err(r) => DatagramVerdict::Drop(r),
            },
            _ => DatagramVerdict::Drop(DropReason::NotAllowed),
        }
    }

    /// Validate and store a keyframe received from `site` on a unidirectional stream. On
    /// success returns the frame to relay to all other sites (re-encoded if the owner field
    /// had to be corrected).
    pub fn on_keyframe(
        &mut self,
        site: SiteId,
        mut kf: RegionKeyframe,
        frame: Bytes,
        now_us: u64,
    ) -> Result<StoredKeyframe, DropReason> {
        let Some(role) = self.role(site) else {
            return Err(DropReason::UnknownSite);
        };
        self.heard(site, now_us);
        if role == Role::Observer {
            return Err(DropReason::Observer);
        }
        if kf.epoch != self.epoch {
            return Err(DropReason::StaleEpoch);
        }
        if self.arbiter.owner(kf.region).is_some_and(|o| o != site) {
            return Err(DropReason::NotOwner);
        }
        if !kf.nodes.is_consistent() {
            return Err(DropReason::Inconsistent);
        }
        if self
            .keyframes
            .get(&kf.region)
            .is_some_and(|k| k.keyframe.keyframe_id >= kf.keyframe_id)
        {
            return Err(DropReason::StaleKeyframe);
        }
        let frame = if kf.owner != site {
            kf.owner = site;
            Bytes::from(proto::encode_frame(&Message::Keyframe(kf.clone())))
        } else {
            frame
        };
        let stored = StoredKeyframe {
            keyframe: kf,
            frame,
        };
        self.keyframes
            .insert(stored.keyframe.region, stored.clone());
        Ok(stored)
    }

    /// Newest stored keyframe id of a region.
    pub fn latest_keyframe_id(&self, region: RegionId) -> Option<KeyframeId> {
        self.keyframes.get(&region).map(|k| k.keyframe.keyframe_id)
    }

    /// Handle a message from `site`'s control stream.
    pub fn on_control(&mut self, site: SiteId, msg: Message, now_us: u64) -> Vec<Action> {
        let Some(role) = self.role(site) else {
            return Self::drop_action(site, &msg, DropReason::UnknownSite);
        };
        self.heard(site, now_us);
        let instructor = role == Role::Instructor;
        match msg {
            Message::KeyframeAck(mut a) => {
                a.site = site;
                match self.keyframes.get(&a.region).map(|k| k.keyframe.owner) {
                    Some(owner) if owner != site && self.sites.contains_key(&owner) => {
                        vec![Action::Control {
                            to: Target::One(owner),
                            msg: Message::KeyframeAck(a),
                        }]
                    }
                    _ => Self::drop_action(site, &Message::KeyframeAck(a), DropReason::NoRecipient),
                }
            }
            Message::OwnershipRequest(r) => {
                let o = self.arbiter.request(site, role, r, now_us);
                vec![Action::Control {
                    to: o.recipient().map_or(Target::All, Target::One),
                    msg: o.message(),
                }]
            }
            Message::OwnershipRelease(r) => {
                let o = self.arbiter.release(site, r.region);
                vec![Action::Control {
                    to: o.recipient().map_or(Target::All, Target::One),
                    msg: o.message(),
                }]
            }
            Message::Teaching(t) => {
                if !instructor {
                    return Self::drop_action(
                        site,
                        &Message::Teaching(t),
                        DropReason::NotInstructor,
                    );
                }
                self.trajectories.insert(t.id, t.clone());
                // Keep memory bounded: at most 16 trajectories.
                while self.trajectories.len() > 16 {
                    self.trajectories.pop_first();
                }
                vec![Action::Control {
                    to: Target::AllExcept(site),
                    msg: Message::Teaching(t),
                }]
            }
            Message::Command(c) => {
                if !instructor {
                    // Refused with a reason the site can show, and counted as dropped.
                    let refusal = Message::CommandRefused(proto::CommandRefusal {
                        command: c.name().into(),
                        reason: format!("only the instructor may {}", c.name()),
                    });
                    let mut a =
                        Self::drop_action(site, &Message::Command(c), DropReason::NotInstructor);
                    a.push(Action::Control {
                        to: Target::One(site),
                        msg: refusal,
                    });
                    return a;
                }
                self.command(site, c)
            }
            Message::Leave(l) => {
                let mut a = self.site_left(site, &format!("left: {}", l.reason));
                a.push(Action::Close {
                    site,
                    code: close_code::NORMAL,
                    reason: "bye".into(),
                });
                a
            }
            Message::Heartbeat(_) => Vec::new(),
            Message::Topology(mut op) => {
                if role == Role::Observer {
                    return Self::drop_action(site, &Message::Topology(op), DropReason::Observer);
                }
                if op.epoch != self.epoch {
                    return Self::drop_action(site, &Message::Topology(op), DropReason::StaleEpoch);
                }
                // The op is the sender's: its id is the sender's site id.
                op.site = site;
                if matches!(op.kind, proto::TopologyKind::Refine { .. }) {
                    // Refinement is relayed, not kept: late joiners take the regions'
                    // tree states from the keyframes, and a session of an hour makes
                    // thousands of these.
                    return vec![Action::Control {
                        to: Target::AllExcept(site),
                        msg: Message::Topology(op),
                    }];
                }
                if self
                    .topology
                    .iter()
                    .any(|o| (o.site, o.seq) == (op.site, op.seq))
                {
                    return Vec::new();
                }
                if self.topology.len() >= MAX_TOPOLOGY_OPS {
                    return Self::drop_action(
                        site,
                        &Message::Topology(op),
                        DropReason::Inconsistent,
                    );
                }
                self.topology.push(op.clone());
                vec![Action::Control {
                    to: Target::AllExcept(site),
                    msg: Message::Topology(op),
                }]
            }
            m @ (Message::SimTime(_)
            | Message::ToolPose(_)
            | Message::ToolPoseHistory(_)
            | Message::TreeDelta(_)) => {
                let kind = m.kind();
                match self.check_state_msg(site, m, now_us) {
                    Ok((msg, _)) => vec![Action::Control {
                        to: Target::AllExcept(site),
                        msg,
                    }],
                    Err(reason) => vec![Action::Drop { site, kind, reason }],
                }
            }
            other => Self::drop_action(site, &other, DropReason::NotAllowed),
        }
    }

    fn command(&mut self, site: SiteId, c: Command) -> Vec<Action> {
        match c {
            Command::ResetScene { sim_time_s, .. } => {
                self.epoch = self.epoch.wrapping_add(1);
                self.keyframes.clear();
                self.topology.clear();
                self.arbiter.clear();
                self.playback = None;
                vec![Action::Control {
                    to: Target::All,
                    msg: Message::Command(Command::ResetScene {
                        epoch: self.epoch,
                        sim_time_s,
                    }),
                }]
            }
            Command::KickSite {
                site: target,
                reason,
            } => {
                let Some((entry, refusal)) = self.join.kick(target, &reason) else {
                    return vec![Action::Drop {
                        site,
                        kind: "command",
                        reason: DropReason::NoRecipient,
                    }];
                };
                // `join.kick` removed the member and banned its name; `site_left` below
                // completes the departure (ownership, site table, Leave to the others).
                let _ = entry;
                let mut a = vec![Action::Control {
                    to: Target::One(target),
                    msg: Message::Refusal(refusal),
                }];
                a.extend(self.site_left(target, &format!("kicked: {reason}")));
                a.push(Action::Close {
                    site: target,
                    code: close_code::KICKED,
                    reason: format!("kicked by the instructor: {reason}"),
                });
                a
            }
            c @ Command::StartPlayback { .. } => {
                self.playback = Some(c.clone());
                vec![Action::Control {
                    to: Target::AllExcept(site),
                    msg: Message::Command(c),
                }]
            }
            c @ Command::StopPlayback { .. } => {
                self.playback = None;
                vec![Action::Control {
                    to: Target::AllExcept(site),
                    msg: Message::Command(c),
                }]
            }
        }
    }

    /// Record the transport RTT of a site.
    pub fn set_rtt(&mut self, site: SiteId, rtt_us: u32) {
        if let Some(s) = self.sites.get_mut(&site) {
            s.rtt_us = rtt_us;
        }
    }

    /// Liveness check: sites that sent heartbeats and then fell silent for 2.4 intervals.
    pub fn poll_liveness(&mut self, now_us: u64) -> Vec<Action> {
        let dead: Vec<SiteId> = self
            .sites
            .iter_mut()
            .filter_map(|(&id, s)| {
                let l = s.liveness.as_mut()?;
                (l.poll(now_us) == Some(proto::LivenessEvent::TimedOut)).then_some(id)
            })
            .collect();
        let mut actions = Vec::new();
        for site in dead {
            actions.extend(self.site_left(site, "timed out"));
            actions.push(Action::Close {
                site,
                code: close_code::TIMED_OUT,
                reason: "no heartbeat".into(),
            });
        }
        actions
    }

    /// The site table.
    pub fn status(&self, now_us: u64) -> Status {
        Status {
            coordinator_time_us: now_us,
            sites: self
                .sites
                .values()
                .map(|s| SiteStatus {
                    site: s.entry.site,
                    name: s.entry.name.clone(),
                    role: s.entry.role,
                    sim_time_s: s.sim_time_s,
                    step: s.step,
                    rtt_us: s.rtt_us,
                })
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests;
