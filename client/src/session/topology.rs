//! Topology operations (cuts, releases of attachment springs, clips, refinement decisions) between sim-core and the wire, and their handling in the
//! session: ops made here go to the coordinator on the control stream (reliable, ordered)
//! and are relayed to every other site; the coordinator keeps them for late joiners' snapshots.
//! Every site applies every op it receives (for cuts, releases and clips duplicates are
//! no-ops and the order does not matter: `sim_core::cut`; refinements are applied in
//! (time, site, seq) order and not kept by the coordinator: `sim_core::adapt`), when its
//! clock reaches the simulated time the op was made at
//! (a site behind holds it, as it holds keyframes). A keyframe whose sender had applied more ops than we have is
//! dropped (`SiteSession::handle_message`): its nodes belong to a topology we have not
//! reached, and the owner's next keyframe replaces it.

use proto::{Epoch, SiteId};
use sim_core::adapt::RefineOp;
use sim_core::clip::ClipOp;
use sim_core::cut::{CutOp, OpId, ReleaseOp, TopologyOp};

/// An op of ours, applied at simulated time `sim_time` (s), as the wire message of scene
/// epoch `epoch`.
pub fn topology_to_wire(op: &TopologyOp, epoch: Epoch, sim_time: f64) -> proto::TopologyOp {
    match op {
        TopologyOp::Cut(c) => proto::TopologyOp {
            epoch,
            site: c.id.site as SiteId,
            seq: c.id.seq,
            sim_time,
            kind: proto::TopologyKind::Cut {
                triangles: c.triangles.clone(),
            },
        },
        TopologyOp::Release(r) => proto::TopologyOp {
            epoch,
            site: r.id.site as SiteId,
            seq: r.id.seq,
            sim_time,
            kind: proto::TopologyKind::Release {
                layer: r.layer,
                springs: r.springs.clone(),
            },
        },
        TopologyOp::Clip(c) => proto::TopologyOp {
            epoch,
            site: c.id.site as SiteId,
            seq: c.id.seq,
            sim_time,
            kind: proto::TopologyKind::Clip { ends: c.ends },
        },
        TopologyOp::Refine(r) => proto::TopologyOp {
            epoch,
            site: r.id.site as SiteId,
            seq: r.id.seq,
            sim_time,
            kind: proto::TopologyKind::Refine {
                focus: r.focus.clone(),
                distance: r.distance,
                level: r.level,
                merge: r.merge.clone(),
            },
        },
    }
}

/// A received op in sim-core's terms.
pub fn topology_from_wire(op: &proto::TopologyOp) -> TopologyOp {
    match &op.kind {
        proto::TopologyKind::Cut { triangles } => TopologyOp::Cut(CutOp {
            id: OpId {
                site: u32::from(op.site),
                seq: op.seq,
            },
            triangles: triangles.clone(),
        }),
        proto::TopologyKind::Release { layer, springs } => TopologyOp::Release(ReleaseOp {
            id: OpId {
                site: u32::from(op.site),
                seq: op.seq,
            },
            layer: *layer,
            springs: springs.clone(),
        }),
        proto::TopologyKind::Clip { ends } => TopologyOp::Clip(ClipOp {
            id: OpId {
                site: u32::from(op.site),
                seq: op.seq,
            },
            ends: *ends,
        }),
        proto::TopologyKind::Refine {
            focus,
            distance,
            level,
            merge,
        } => TopologyOp::Refine(RefineOp {
            id: OpId {
                site: u32::from(op.site),
                seq: op.seq,
            },
            focus: focus.clone(),
            distance: *distance,
            level: *level,
            merge: merge.clone(),
        }),
    }
}
