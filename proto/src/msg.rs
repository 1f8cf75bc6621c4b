//! Wire messages.
//!
//! Every message is one variant of [`Message`]. The serialised form is postcard, whose enum
//! tags are the variant indices: **variants and fields are only ever appended** within one
//! [`crate::PROTOCOL_VERSION`]; any other change bumps the version (and the tag byte written by
//! [`crate::codec::encode`]).
//!
//! Units: SI (m, s, rad, m/s, rad/s). Wall-clock and coordinator timestamps are microseconds
//! (`u64`, `*_us`) on the clock named in the field's doc. Simulation times are seconds (`f64`).

use serde::{Deserialize, Serialize};

use crate::quant::QuantisedNodes;

/// Site identifier, assigned by the coordinator in [`Welcome`]. `0` is never assigned (it names
/// the coordinator itself where a sender is needed).
pub type SiteId = u16;
/// Region identifier (chosen by the scene; opaque to the protocol).
pub type RegionId = u32;
/// Keyframe identifier: per region, strictly increasing. A site that takes over a region
/// continues from the newest id it has seen for that region + 1.
pub type KeyframeId = u64;
/// Scene epoch: bumped by every scene reset; frames of another epoch are stale.
pub type Epoch = u32;
/// The coordinator's own site id in messages it originates.
pub const COORDINATOR_SITE: SiteId = 0;

/// What a site may do in the session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Role {
    /// May reset the scene, kick sites, start/stop teaching playback; wins ownership conflicts.
    Instructor,
    /// Interacts with the organ; relays tool poses and region state.
    Trainee,
    /// Receives only: anything it sends except session control is dropped by the coordinator.
    Observer,
}

impl Role {
    /// True for roles whose simulation state is relayed to the others.
    pub fn may_send_state(self) -> bool {
        !matches!(self, Role::Observer)
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Role::Instructor => "instructor",
            Role::Trainee => "trainee",
            Role::Observer => "observer",
        })
    }
}

impl std::str::FromStr for Role {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "instructor" => Ok(Role::Instructor),
            "trainee" => Ok(Role::Trainee),
            "observer" => Ok(Role::Observer),
            other => Err(format!(
                "unknown role {other:?} (instructor|trainee|observer)"
            )),
        }
    }
}

/// First message of a site, on the session-control stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Join {
    /// The sender's [`crate::PROTOCOL_VERSION`].
    pub protocol_version: u16,
    /// Lower-case hex SHA-256 of the scene the site loaded.
    pub scene_hash: String,
    pub role: Role,
    /// Human-readable site name, unique within the session.
    pub site_name: String,
    /// Session name the site wants to join.
    pub session: String,
    /// What admits the site: the instructor's token or an invitation.
    pub credential: Credential,
    /// The sender's time scale in thousandths ([`TIME_SCALE_REAL_MILLI`]: real time;
    /// 2000: every party runs twice slower than real time, `--time-scale 2`). Every party
    /// of a session must run at the same scale, or a site's clock estimate drifts from the
    /// coordinator's by the ratio.
    pub time_scale_milli: u32,
}

/// [`Join::time_scale_milli`] of a session in real time.
pub const TIME_SCALE_REAL_MILLI: u32 = 1000;

/// A site's credential in [`Join`].
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum Credential {
    /// The session's instructor secret (`cosurg-server --token`); admits the instructor role
    /// only.
    Token(String),
    /// An invitation (`csi1.…`, see [`crate::invite`]) for a trainee or observer.
    Invitation(String),
}

impl std::fmt::Debug for Credential {
    /// Never prints the secret (logs show `Join`s).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Credential::Token(_) => f.write_str("Token(…)"),
            Credential::Invitation(_) => f.write_str("Invitation(…)"),
        }
    }
}

/// Description of the session a site joined.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionInfo {
    pub name: String,
    /// Hex SHA-256 of the scene every site must run.
    pub scene_hash: String,
    pub max_sites: u16,
    pub protocol_version: u16,
    /// Interval at which sites should send [`Message::Heartbeat`] (µs).
    pub heartbeat_interval_us: u64,
}

/// One row of the site list.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SiteEntry {
    pub site: SiteId,
    pub name: String,
    pub role: Role,
}

/// Positive answer to a [`Join`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    /// The id assigned to the joining site.
    pub site: SiteId,
    pub session: SessionInfo,
    /// All sites in the session, including the new one.
    pub sites: Vec<SiteEntry>,
    /// Coordinator clock (µs) when the Welcome was produced.
    pub coordinator_time_us: u64,
}

/// Machine-readable reason of a [`Refusal`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum RefusalReason {
    WrongToken,
    WrongVersion {
        server: u16,
        client: u16,
    },
    WrongScene {
        expected: String,
    },
    WrongSession,
    NameTaken,
    Full,
    Kicked,
    Malformed,
    /// The invitation does not verify (garbage, altered, forged or minted by another
    /// coordinator).
    InvalidInvitation,
    InvitationExpired,
    InvitationRevoked,
    /// The credential does not admit the requested role (the instructor token admits the
    /// instructor only; an invitation its own role only).
    WrongRole,
    /// The invitation is bound to another site name.
    WrongSite,
    /// Too many failed joins from this address; retry after the given time.
    RateLimited {
        retry_after_ms: u64,
    },
    /// The site runs at another time scale than the session ([`Join::time_scale_milli`]).
    WrongTimeScale {
        server_milli: u32,
        client_milli: u32,
    },
}

impl RefusalReason {
    /// QUIC application error code used when the coordinator closes the connection after
    /// sending this refusal (see [`crate::close_code`]).
    pub fn close_code(&self) -> u32 {
        use crate::close_code::*;
        match self {
            RefusalReason::WrongToken => WRONG_TOKEN,
            RefusalReason::WrongVersion { .. } => WRONG_VERSION,
            RefusalReason::WrongScene { .. } => WRONG_SCENE,
            RefusalReason::WrongSession => WRONG_SESSION,
            RefusalReason::NameTaken => NAME_TAKEN,
            RefusalReason::Full => FULL,
            RefusalReason::Kicked => KICKED,
            RefusalReason::Malformed => MALFORMED,
            RefusalReason::InvalidInvitation => INVALID_INVITATION,
            RefusalReason::InvitationExpired => INVITATION_EXPIRED,
            RefusalReason::InvitationRevoked => INVITATION_REVOKED,
            RefusalReason::WrongRole => WRONG_ROLE,
            RefusalReason::WrongSite => WRONG_SITE,
            RefusalReason::RateLimited { .. } => RATE_LIMITED,
            RefusalReason::WrongTimeScale { .. } => WRONG_TIME_SCALE,
        }
    }
}

/// Negative answer to a [`Join`] (or notice of a kick). The connection is closed after it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Refusal {
    pub reason: RefusalReason,
    /// Human-readable explanation.
    pub text: String,
}

/// Clock ping (client → coordinator, datagram). `t1_us`: client clock at send.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClockPing {
    pub seq: u32,
    pub t1_us: u64,
}

/// Clock pong (coordinator → client, datagram): echoes `t1`, adds coordinator receive (`t2`)
/// and send (`t3`) times. The client adds its receive time `t4` and feeds
/// [`crate::clock::ClockSample`] to a [`crate::clock::ClockFilter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClockPong {
    pub seq: u32,
    pub t1_us: u64,
    pub t2_us: u64,
    pub t3_us: u64,
}

/// A site's simulation clock (datagram, relayed to all other sites).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimTimeStamp {
    pub site: SiteId,
    /// Simulation time (s).
    pub sim_time_s: f64,
    /// Number of simulation steps taken.
    pub step: u64,
    /// Sender's estimate of the coordinator clock at send (µs).
    pub wall_send_us: u64,
}

/// Pose of one tool (datagram, relayed).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ToolPose {
    pub site: SiteId,
    pub tool: u8,
    /// Simulation time of the pose (s).
    pub sim_time_s: f64,
    /// Tool tip position (m).
    pub position: [f32; 3],
    /// Orientation quaternion `[w, x, y, z]`.
    pub orientation: [f32; 4],
    /// Jaw opening angle (rad).
    pub jaw_rad: f32,
    /// Linear velocity (m/s).
    pub velocity: [f32; 3],
    /// Angular velocity (rad/s).
    pub angular_velocity: [f32; 3],
}

/// One sample of a tool's input: what a site needs to simulate another site's tool.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseSample {
    /// Simulation time of the pose (s).
    pub sim_time_s: f64,
    /// Tool tip position (m).
    pub position: [f32; 3],
    /// Orientation quaternion `[w, x, y, z]`.
    pub orientation: [f32; 4],
    /// Jaw opening angle (rad).
    pub jaw_rad: f32,
}

/// The newest input samples of one tool (datagram, relayed), oldest first. Each datagram
/// repeats the samples of the previous few, so that a lost datagram costs nothing as long
/// as the next one arrives, and may repeat older ones at a coarser spacing, so that a long
/// burst of losses leaves a coarse path through the gap (`SyncStrategy::Hybrid`'s input
/// channel). Receivers take the samples by their times; the spacing is the sender's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolPoseHistory {
    pub site: SiteId,
    pub tool: u8,
    pub samples: Vec<PoseSample>,
}

/// Most samples a [`ToolPoseHistory`] may carry (keeps it well inside one datagram:
/// 40 bytes per sample).
pub const MAX_POSE_SAMPLES: usize = 16;

/// Full state of one region (unidirectional stream, relayed; latest kept for late joiners).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegionKeyframe {
    pub region: RegionId,
    pub keyframe_id: KeyframeId,
    /// Site owning the region (the sender).
    pub owner: SiteId,
    /// Simulation time of the state (s).
    pub sim_time: f64,
    /// Scene epoch: bumped by a scene reset; frames of another epoch are stale.
    pub epoch: Epoch,
    /// Tree state (split bits over heap indices) of the region, opaque to the protocol.
    pub tree_bits: Vec<u8>,
    /// Node ids with quantised positions and velocities.
    pub nodes: QuantisedNodes,
    /// The sender's topology epoch (how many cuts, releases and clips it had applied;
    /// refinements do not count, the tree bits carry them): a site that
    /// has applied fewer drops the keyframe (its topology is not there yet; the owner's
    /// next keyframe replaces it).
    pub topology: u32,
}

/// Change of a region's tree state relative to an acknowledged keyframe (datagram when it
/// fits, else control stream).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TreeDelta {
    pub region: RegionId,
    pub site: SiteId,
    pub epoch: Epoch,
    /// Simulation time of the state (s).
    pub sim_time: f64,
    /// The keyframe the delta applies to; every receiver has acknowledged it.
    pub base_keyframe: KeyframeId,
    /// XOR of the base keyframe's tree bits and the current ones (opaque bytes, may be
    /// run-length or otherwise compressed by the simulation layer).
    pub xor_bits: Vec<u8>,
}

/// A receiver acknowledges a keyframe (control stream; relayed to the region's owner).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyframeAck {
    pub region: RegionId,
    pub keyframe_id: KeyframeId,
    /// The acknowledging site (filled in / overwritten by the coordinator).
    pub site: SiteId,
    /// Under hybrid sync: the acknowledging site shows the owner's keyframes instead of
    /// simulating the region itself (its own solve is cut short), so the owner also sends
    /// when the region departs from its dead reckoning, as under keyframe sync.
    pub shows_keyframes: bool,
}

/// A site asks to own a region (its tool touches it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnershipRequest {
    pub region: RegionId,
    /// When the site first touched the region, on the coordinator clock (µs). Used to let the
    /// earlier claim win when two requests cross in flight.
    pub claim_time_us: u64,
}

/// The coordinator grants a region (broadcast to all sites).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnershipGrant {
    pub region: RegionId,
    pub site: SiteId,
    /// Previous owner that lost the region to this grant, if any.
    pub previous: Option<SiteId>,
}

/// A region became free (broadcast).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnershipRelease {
    pub region: RegionId,
    pub site: SiteId,
}

/// Why an ownership request was denied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DenyReason {
    /// Another site holds the region and has precedence.
    HeldByOther,
    /// Observers never own regions.
    ObserverCannotOwn,
    /// A release for a region the site does not own.
    NotOwner,
}

/// An ownership request (or release) was denied (to the requester only).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnershipDeny {
    pub region: RegionId,
    pub holder: Option<SiteId>,
    pub reason: DenyReason,
}

/// Region ownership at snapshot time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOwner {
    pub region: RegionId,
    pub site: SiteId,
}

/// Sent to a late joiner after [`Welcome`] (unidirectional stream).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    /// Newest simulation time known to the coordinator (s).
    pub sim_time_s: f64,
    /// The session's current scene epoch: a late joiner takes it.
    pub epoch: Epoch,
    pub owners: Vec<RegionOwner>,
    /// Latest keyframe of every region.
    pub keyframes: Vec<RegionKeyframe>,
    /// Every cut, release and clip of the current scene epoch, in arrival order: a late
    /// joiner applies them all (the result does not depend on their order). Refinements
    /// are not kept: the keyframes' tree bits carry them.
    pub topology: Vec<TopologyOp>,
}

/// A topology operation on the shared scene (control stream: reliable and ordered per
/// sender; relayed to every other site and, except refinements, kept by the coordinator
/// for late joiners until the scene is reset). Every site applies it with exact
/// predicates, so the cut topology that results depends only on the set of cuts, releases
/// and clips, not on their order or duplicates. Refinements split and merge, so their
/// order matters: every site applies them at their `sim_time`, ties in (site, seq) order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TopologyOp {
    /// Scene epoch the operation belongs to (operations of another epoch are dropped).
    pub epoch: Epoch,
    /// Site that made it.
    pub site: SiteId,
    /// That site's sequence number (from 0); (site, seq) identifies and orders the op.
    pub seq: u32,
    /// Simulated time (s) at which its site applies it. Under hybrid and input-only sync a
    /// site whose clock is behind holds it until its own clock reaches that time (as it
    /// does keyframes), so that a cut parts the tissue at the same simulated moment on
    /// every site; not finite, already past, or under keyframe and full-state sync:
    /// applied on arrival.
    pub sim_time: f64,
    pub kind: TopologyKind,
}

/// What a [`TopologyOp`] does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum TopologyKind {
    /// A cut: the triangles a blade swept, in rest coordinates (m; exact `f64`, since every
    /// site decides with exact predicates on them).
    Cut { triangles: Vec<[[f64; 3]; 3]> },
    /// A release of attachment springs (dissection): springs of one attachment layer of
    /// the scene, by index (ascending). Released springs stay released.
    Release { layer: u32, springs: Vec<u32> },
    /// A clip: the segment of a clip applier's closed jaws (its two ends), in rest
    /// coordinates (m; exact `f64`, like a cut's triangles).
    Clip { ends: [[f64; 3]; 2] },
    /// Tool-following refinement decided on one site (it changes no material, so the
    /// coordinator relays it without keeping it: keyframes carry the regions' tree states
    /// to late joiners): every leaf whose rest box comes within `distance` (m) of a focus
    /// point (rest coordinates, m, exact `f64`) splits to `level`; then the diamonds whose
    /// centre nodes sit at the `merge` grid positions (integer lattice units) merge back
    /// where they can, in that order.
    Refine {
        focus: Vec<[f64; 3]>,
        distance: f64,
        level: u8,
        merge: Vec<[i64; 3]>,
    },
}

/// One timed tool sample of a teaching trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ToolSample {
    /// Time since the start of the trajectory (s).
    pub t_s: f64,
    pub position: [f32; 3],
    pub orientation: [f32; 4],
    pub jaw_rad: f32,
}

/// A recorded instructor trajectory (control stream), replayed on trainees' devices.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TeachingTrajectory {
    pub id: u32,
    pub tool: u8,
    pub samples: Vec<ToolSample>,
}

/// Instructor commands (control stream; instructor only, relayed to all sites).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Command {
    /// Instructor → coordinator: reset the scene (`epoch`: the sender's current one).
    /// Coordinator → every site: restore the scene's initial state and take `epoch`, the
    /// new scene epoch, when the site's simulated time reaches `sim_time_s` (s; at once if
    /// it is past), so that every site resets at the same simulated time.
    ResetScene {
        epoch: Epoch,
        sim_time_s: f64,
    },
    /// Remove a site from the session.
    KickSite {
        site: SiteId,
        reason: String,
    },
    /// Replay trajectory `trajectory` from simulation time `start_sim_time_s`.
    StartPlayback {
        trajectory: u32,
        start_sim_time_s: f64,
    },
    StopPlayback {
        trajectory: u32,
    },
}

/// Why the coordinator did not carry out a [`Command`] (e.g. a trainee asked for a reset).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CommandRefusal {
    /// The command's name (`reset-scene`, `kick-site`, …).
    pub command: String,
    /// Human-readable reason.
    pub reason: String,
}

impl Command {
    /// Short name, for logs and refusals.
    pub fn name(&self) -> &'static str {
        match self {
            Command::ResetScene { .. } => "reset-scene",
            Command::KickSite { .. } => "kick-site",
            Command::StartPlayback { .. } => "start-playback",
            Command::StopPlayback { .. } => "stop-playback",
        }
    }
}

/// A site leaves (control stream) or the coordinator announces a departure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Leave {
    pub site: SiteId,
    pub reason: String,
}

/// Liveness (datagram, both directions).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Heartbeat {
    pub site: SiteId,
    pub time_us: u64,
}

/// One row of [`Status`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SiteStatus {
    pub site: SiteId,
    pub name: String,
    pub role: Role,
    /// Latest simulation time reported by the site (s).
    pub sim_time_s: f64,
    pub step: u64,
    /// Round-trip time coordinator ↔ site (µs).
    pub rtt_us: u32,
}

/// Periodic site table (coordinator → all, control stream).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub coordinator_time_us: u64,
    pub sites: Vec<SiteStatus>,
}

/// An administrative request on a connection of its own (not a site): the first and only
/// message the client sends on its control stream; the coordinator answers with
/// [`Message::Invitation`] or a [`Refusal`] and closes. Authenticated by the instructor
/// token; nothing of the session (site table, relaying) sees the connection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdminRequest {
    pub protocol_version: u16,
    pub session: String,
    pub credential: Credential,
    pub action: AdminAction,
}

/// What an [`AdminRequest`] asks for.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum AdminAction {
    /// Mint an invitation for `role` (trainee or observer), optionally bound to one site
    /// name, valid for `valid_for_s` seconds.
    MintInvitation {
        role: Role,
        site: Option<String>,
        valid_for_s: u64,
    },
    /// Create a session on a coordinator hosting several (authenticated by the operator's
    /// `--admin-token`, not an instructor token; `AdminRequest::session` names the new
    /// session). `instructor_token` becomes the new session's instructor secret;
    /// `scene_hash`: required scene (`None`: the first site fixes it); `max_sites`: `0`
    /// takes the coordinator's default. Answered with [`Message::SessionCreated`].
    CreateSession {
        instructor_token: String,
        scene_hash: Option<String>,
        max_sites: u16,
    },
}

/// A minted invitation (answer to [`AdminAction::MintInvitation`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InvitationIssued {
    /// The invitation (`csi1.…`), to hand to the site.
    pub invitation: String,
    pub role: Role,
    pub site: Option<String>,
    /// Expiry, Unix time (s).
    pub expires_unix_s: u64,
    /// The nonce as hex (what `cosurg-server revoke` accepts).
    pub nonce_hex: String,
}

/// Every message of protocol version 3. Append new variants at the end only.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Message {
    Join(Join),
    Welcome(Welcome),
    Refusal(Refusal),
    ClockPing(ClockPing),
    ClockPong(ClockPong),
    SimTime(SimTimeStamp),
    ToolPose(ToolPose),
    Keyframe(RegionKeyframe),
    TreeDelta(TreeDelta),
    KeyframeAck(KeyframeAck),
    OwnershipRequest(OwnershipRequest),
    OwnershipGrant(OwnershipGrant),
    OwnershipRelease(OwnershipRelease),
    OwnershipDeny(OwnershipDeny),
    Snapshot(Snapshot),
    Teaching(TeachingTrajectory),
    Command(Command),
    Leave(Leave),
    Heartbeat(Heartbeat),
    Status(Status),
    /// A site joined (coordinator → others, control stream).
    SiteJoined(SiteEntry),
    /// Administrative request (first message of an admin connection).
    Admin(AdminRequest),
    /// Answer to an [`AdminRequest`] minting an invitation.
    Invitation(InvitationIssued),
    /// The coordinator refused a command (to the sender only, control stream).
    CommandRefused(CommandRefusal),
    /// Answer to [`AdminAction::CreateSession`]: the session now hosted.
    SessionCreated(SessionInfo),
    /// A topology operation (a cut), relayed to every other site (control stream).
    Topology(TopologyOp),
    /// A tool's newest input samples (datagram, relayed).
    ToolPoseHistory(ToolPoseHistory),
}

/// Which transport a message normally travels on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Channel {
    /// The bidirectional session-control stream (reliable, ordered).
    Control,
    /// QUIC datagrams (unreliable, newest wins). Fall back to `Control` if too large.
    Datagram,
    /// One unidirectional stream per message (reliable, may be reset when superseded).
    UniStream,
}

impl Message {
    /// Short name of the variant, for logs and counters.
    pub fn kind(&self) -> &'static str {
        match self {
            Message::Join(_) => "join",
            Message::Welcome(_) => "welcome",
            Message::Refusal(_) => "refusal",
            Message::ClockPing(_) => "clock-ping",
            Message::ClockPong(_) => "clock-pong",
            Message::SimTime(_) => "sim-time",
            Message::ToolPose(_) => "tool-pose",
            Message::Keyframe(_) => "keyframe",
            Message::TreeDelta(_) => "tree-delta",
            Message::KeyframeAck(_) => "keyframe-ack",
            Message::OwnershipRequest(_) => "ownership-request",
            Message::OwnershipGrant(_) => "ownership-grant",
            Message::OwnershipRelease(_) => "ownership-release",
            Message::OwnershipDeny(_) => "ownership-deny",
            Message::Snapshot(_) => "snapshot",
            Message::Teaching(_) => "teaching",
            Message::Command(_) => "command",
            Message::Leave(_) => "leave",
            Message::Heartbeat(_) => "heartbeat",
            Message::Status(_) => "status",
            Message::SiteJoined(_) => "site-joined",
            Message::Admin(_) => "admin",
            Message::Invitation(_) => "invitation",
            Message::CommandRefused(_) => "command-refused",
            Message::SessionCreated(_) => "session-created",
            Message::Topology(_) => "topology",
            Message::ToolPoseHistory(_) => "tool-pose-history",
        }
    }

    /// The channel this message normally uses.
    pub fn channel(&self) -> Channel {
        match self {
            Message::ClockPing(_)
            | Message::ClockPong(_)
            | Message::SimTime(_)
            | Message::ToolPose(_)
            | Message::ToolPoseHistory(_)
            | Message::TreeDelta(_)
            | Message::Heartbeat(_) => Channel::Datagram,
            Message::Keyframe(_) | Message::Snapshot(_) => Channel::UniStream,
            _ => Channel::Control,
        }
    }
}
