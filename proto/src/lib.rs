//! cosurg wire protocol: messages, codec, framing and sans-IO session state machines.
//!
//! This crate knows nothing about sockets, async runtimes or wall clocks: time is passed in
//! as `u64` microseconds, bytes in and out as slices and vectors (the model is quinn-proto
//! under quinn). The coordinator (`cosurg-server`) and the sites (`cosurg`) drive it.
//!
//! * [`msg`] — every message ([`Message`]) with its fields and units;
//! * [`codec`] — [`encode`]/[`decode`] (version tag + postcard), [`FrameDecoder`] for
//!   length-prefixed stream frames, datagram budget checks;
//! * [`quant`] — quantised node states with a stated, tested error bound;
//! * [`join`] — [`JoinHandshake`]: validate a join against the [`SessionConfig`];
//! * [`invite`] — invitations: [`InviteKey`] signs and verifies `csi1.…` credentials;
//! * [`ownership`] — [`OwnershipArbiter`]: region ownership, instructor first, then earlier claim;
//! * [`baseline`] — [`BaselineTracker`]: which keyframes each receiver acknowledged;
//! * [`clock`] — [`ClockFilter`]: NTP-style offset/RTT with minimum-delay window and slewing;
//! * [`liveness`] — [`PeerLiveness`]: heartbeats, timeout after 2.4 intervals;
//! * [`streams`] — [`KeyframeStreams`]: the keyframe-stream scheduler of sites and
//!   coordinator (newest wins, up to eight per region in flight, stalled ones reset).
//!
//! ## Channels
//! | channel | messages |
//! |---|---|
//! | session-control bidi stream (opened by the site), frames | Join, Welcome, Refusal, KeyframeAck, Ownership*, Teaching, Command, Leave, Status, SiteJoined (and TreeDelta too big for a datagram) |
//! | datagrams (≤ 1100 B) | ClockPing/Pong, SimTime, ToolPose, ToolPoseHistory, TreeDelta, Heartbeat |
//! | one uni stream per message, one frame | Keyframe, Snapshot |
//! | control stream of an admin connection (not a site): one request, one answer | Admin → Invitation, SessionCreated or Refusal |

pub mod baseline;
pub mod clock;
pub mod codec;
pub mod invite;
pub mod join;
pub mod liveness;
pub mod msg;
pub mod ownership;
pub mod quant;
pub mod streams;

/// Protocol version carried in [`msg::Join`]; its low byte is the wire tag of every message.
///
/// Version 2: `Join` carries a [`msg::Credential`] (instructor token or invitation) instead of
/// one shared token; refusals for invitations and rate limiting; admin requests.
/// Version 3: topology operations (`Message::Topology`, cuts), the snapshot's `topology`
/// and the keyframe's `topology` epoch; sessions created at run time
/// (`AdminAction::CreateSession` → `Message::SessionCreated`); tool input histories
/// (`Message::ToolPoseHistory`, the hybrid strategy's datagrams).
/// Version 4: attachment releases (`TopologyKind::Release`, hook dissection).
/// Version 5: a topology operation carries the simulated time it was made at
/// (`TopologyOp::sim_time`), so that every site applies it at that time.
/// Version 6: clips (`TopologyKind::Clip`, the clip applier).
/// Version 7: a keyframe acknowledgement says whether its site shows the owner's keyframes
/// instead of simulating the region (`KeyframeAck::shows_keyframes`).
/// Version 8: a join says its time scale (`Join::time_scale_milli`), and a site whose scale
/// differs from the session's is refused (`RefusalReason::WrongTimeScale`).
/// Version 9: tool-following refinement decided on one site (`TopologyKind::Refine`),
/// applied by every site at its simulated time.
pub const PROTOCOL_VERSION: u16 = 9;

/// A keyframe stream is reset in favour of a newer keyframe of the same region only after
/// it has been in flight this long. Resetting younger streams starves paths whose round
/// trip is longer than the keyframe interval: nothing would ever arrive.
pub const KEYFRAME_STALL: std::time::Duration = std::time::Duration::from_millis(300);

/// Send priority of keyframe and snapshot streams (the control stream has 0), at sites
/// and coordinator alike.
pub const KEYFRAME_PRIORITY: i32 = -1;

/// Time a keyframe or snapshot stream may take to arrive completely.
pub const STREAM_READ_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// ALPN identifier of the protocol, used by both TLS sides.
pub const ALPN: &[u8] = b"cosurg/1";

/// QUIC application error codes used when closing a connection.
pub mod close_code {
    /// Normal end of session (leave, coordinator shutdown).
    pub const NORMAL: u32 = 0;
    pub const WRONG_TOKEN: u32 = 1;
    pub const WRONG_VERSION: u32 = 2;
    pub const WRONG_SCENE: u32 = 3;
    pub const WRONG_SESSION: u32 = 4;
    pub const NAME_TAKEN: u32 = 5;
    pub const FULL: u32 = 6;
    pub const KICKED: u32 = 7;
    pub const MALFORMED: u32 = 8;
    /// The peer violated the protocol after joining (e.g. bad control frame).
    pub const PROTOCOL_ERROR: u32 = 9;
    /// No Join within the allowed time.
    pub const JOIN_TIMEOUT: u32 = 10;
    /// The peer could not keep up with its reliable control traffic.
    pub const OVERLOADED: u32 = 11;
    /// The peer stopped sending heartbeats (after having sent some).
    pub const TIMED_OUT: u32 = 12;
    pub const INVALID_INVITATION: u32 = 13;
    pub const INVITATION_EXPIRED: u32 = 14;
    pub const INVITATION_REVOKED: u32 = 15;
    pub const WRONG_ROLE: u32 = 16;
    pub const WRONG_SITE: u32 = 17;
    pub const RATE_LIMITED: u32 = 18;
    pub const WRONG_TIME_SCALE: u32 = 19;
}

/// QUIC stream error codes (`SendStream::reset`, `RecvStream::stop`).
pub mod stream_code {
    /// A newer keyframe of the same region superseded this stream's keyframe.
    pub const SUPERSEDED: u32 = 1;
    /// The stream's content was malformed or too large; the receiver stopped reading.
    pub const MALFORMED: u32 = 2;
    /// The receiver does not accept this kind of stream from this sender (e.g. observer).
    pub const REFUSED: u32 = 3;
}

pub use baseline::{BaselineConfig, BaselineEvent, BaselineTracker};
pub use clock::{ClockFilter, ClockFilterConfig, ClockSample};
pub use codec::{
    DEFAULT_DATAGRAM_BUDGET, DEFAULT_MAX_FRAME, DatagramTooLarge, DecodeError, FrameDecoder,
    FrameError, decode, encode, encode_datagram, encode_frame,
};
pub use invite::{InvitationClaims, InviteError, InviteKey, Nonce};
pub use join::{JoinHandshake, SessionConfig};
pub use liveness::{LivenessEvent, PeerLiveness};
pub use msg::*;
pub use ownership::{OwnershipArbiter, OwnershipOutcome};
pub use quant::{QuantError, QuantisedNodes};
pub use streams::{
    KEYFRAME_STREAMS_PER_REGION, KeyframeStreams, StreamAction, StreamToken, stall_time,
};
