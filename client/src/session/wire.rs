//! The one conversion between sim-core's sync frames and `proto`'s wire messages.

use proto::{Epoch, SiteId};
use sim_core::sync::{RegionKeyframe, RegionTreeDelta, SyncFrame};
use tracing::warn;

/// A sync frame that arrived from another site, in sim-core's terms.
pub fn keyframe_from_wire(kf: &proto::RegionKeyframe) -> SyncFrame {
    let n = kf.nodes.len();
    SyncFrame::Keyframe(RegionKeyframe {
        region: kf.region,
        keyframe_id: kf.keyframe_id,
        sim_time: kf.sim_time,
        tree_bits: kf.tree_bits.clone(),
        positions: (0..n).map(|i| kf.nodes.position(i)).collect(),
        velocities: (0..n).map(|i| kf.nodes.velocity(i)).collect(),
    })
}

/// A tree delta that arrived from another site, in sim-core's terms.
pub fn delta_from_wire(d: proto::TreeDelta) -> SyncFrame {
    SyncFrame::TreeDelta(RegionTreeDelta {
        region: d.region,
        sim_time: d.sim_time,
        base_keyframe: d.base_keyframe,
        xor_bits: d.xor_bits,
    })
}

/// A frame of ours on its way out: keyframes go on their own stream, deltas as datagrams.
#[derive(Debug, Clone, PartialEq)]
pub enum WireFrame {
    Keyframe(proto::RegionKeyframe),
    Delta(proto::TreeDelta),
}

/// One of our sync frames as the wire message of site `me` in scene epoch `epoch`;
/// `None` if its node states cannot be quantised (logged).
pub fn frame_to_wire(frame: SyncFrame, me: SiteId, epoch: Epoch) -> Option<WireFrame> {
    match frame {
        SyncFrame::Keyframe(kf) => {
            let ids: Vec<u32> = (0..kf.positions.len() as u32).collect();
            let nodes =
                match proto::QuantisedNodes::encode_default(&ids, &kf.positions, &kf.velocities) {
                    Ok(n) => n,
                    Err(e) => {
                        warn!(region = kf.region, error = %e, "keyframe not quantisable; not sent");
                        return None;
                    }
                };
            Some(WireFrame::Keyframe(proto::RegionKeyframe {
                region: kf.region,
                keyframe_id: kf.keyframe_id,
                owner: me,
                sim_time: kf.sim_time,
                epoch,
                tree_bits: kf.tree_bits,
                nodes,
                topology: 0,
            }))
        }
        SyncFrame::TreeDelta(d) => Some(WireFrame::Delta(proto::TreeDelta {
            region: d.region,
            site: me,
            epoch,
            sim_time: d.sim_time,
            base_keyframe: d.base_keyframe,
            xor_bits: d.xor_bits,
        })),
    }
}

/// Simulated time of a frame (s).
pub fn frame_time(f: &SyncFrame) -> f64 {
    match f {
        SyncFrame::Keyframe(k) => k.sim_time,
        SyncFrame::TreeDelta(d) => d.sim_time,
    }
}
