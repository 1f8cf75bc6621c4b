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

use std::time::{Duration, Instant};

use proto::{Epoch, Message, Role, SiteId};
use sim_core::sync::RegionMap;
use sim_core::{SimError, Simulation};
use tracing::{debug, info, warn};

use super::{SiteSession, topology_lead};
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

impl SiteSession {
    /// Takes a received topology op of the current epoch: held for its time when our
    /// clock is behind its maker's and ops are timed, applied at once otherwise.
    pub(super) fn take_topology(
        &mut self,
        sim: &mut Simulation,
        op: proto::TopologyOp,
    ) -> Result<(), SimError> {
        if self.times_topology()
            && op.sim_time.is_finite()
            && op.sim_time > sim.time() + 0.5 * sim.options().dt
        {
            self.hold_topology(op);
            Ok(())
        } else {
            self.apply_topology(sim, &op)
        }
    }

    /// Holds an op until its time, in the order every site applies them: by simulated
    /// time, then by its id (site, seq), whatever order they arrived in.
    pub(super) fn hold_topology(&mut self, op: proto::TopologyOp) {
        let key = |h: &proto::TopologyOp| (h.sim_time, h.site, h.seq);
        let i = self
            .held_topology
            .partition_point(|h| key(h).partial_cmp(&key(&op)) == Some(std::cmp::Ordering::Less));
        self.held_topology.insert(i, op);
    }

    /// Whether a keyframe of `region` made at `sim_time` (s) would take the region's tree
    /// back to before a refinement op we applied after that time: under hybrid and
    /// input-only sync every site applies the op at its time, and the owner's later
    /// keyframes include it.
    pub(super) fn undoes_refinement(
        &self,
        sim: &Simulation,
        region: proto::RegionId,
        sim_time: f64,
        tree_bits: &[u8],
    ) -> bool {
        if !self.times_topology() || sim_time >= self.refined_at || !self.map.contains(region) {
            return false;
        }
        tree_differs(sim, &self.map, region, tree_bits)
    }

    /// Applies a received topology op (a duplicate changes nothing); counts it and its
    /// CPU time.
    pub(super) fn apply_topology(
        &mut self,
        sim: &mut Simulation,
        op: &proto::TopologyOp,
    ) -> Result<(), SimError> {
        let t0 = Instant::now();
        let op_here = topology_from_wire(op);
        if let sim_core::cut::TopologyOp::Refine(r) = &op_here {
            // A refinement that cannot be applied is dropped, not fatal: it is one site's
            // decision, and the owners' keyframes carry their regions' trees.
            let change = match sim.apply_refine(r) {
                Ok(c) => c,
                Err(e) => {
                    warn!(site = op.site, seq = op.seq, error = %e, "refinement dropped");
                    self.stats.refinements_dropped += 1;
                    return Ok(());
                }
            };
            if change.split + change.merged > 0 {
                let at = if op.sim_time.is_finite() {
                    op.sim_time.min(sim.time())
                } else {
                    sim.time()
                };
                self.refined_at = self.refined_at.max(at);
            }
            self.stats.refinements_applied += 1;
            let late = sim.time() - op.sim_time;
            if self.times_topology() && late > 0.5 * sim.options().dt {
                self.stats.refinements_late += 1;
                debug!(
                    site = op.site,
                    seq = op.seq,
                    late,
                    "refinement applied late"
                );
            }
            debug!(
                site = op.site,
                seq = op.seq,
                t = sim.time(),
                split = change.split,
                merged = change.merged,
                "refinement applied"
            );
            return Ok(());
        }
        let change = sim.apply_topology_op(op_here)?;
        if change.applied && Some(op.site) == self.sites.me() {
            // One of our own cuts, at the time we scheduled it for.
            self.own_cut_applied = true;
            info!(seq = op.seq, t = sim.time(), "our cut applied");
        } else if change.applied {
            self.stats.topology_applied += 1;
            self.stats.topology_apply_us_total += t0.elapsed().as_secs_f64() * 1e6;
            info!(
                site = op.site,
                seq = op.seq,
                epoch = sim.topology().epoch(),
                crossed = change.crossed,
                "topology op applied"
            );
        }
        Ok(())
    }

    /// Sends the topology ops our own tools made at simulated time `t` (s) to the others.
    /// Under hybrid and input-only sync, cuts, releases of attachment springs and
    /// refinement decisions were not applied here (the blade's, the hook's and
    /// adaptivity's `apply_own` are off on a linked site): they
    /// are scheduled [`topology_lead`] ahead, for every site, this one included, so that
    /// the tissue parts or lets go at the same simulated moment everywhere — also on the
    /// sites that lead like us and would otherwise receive them after their time. Clips
    /// (which move nothing), and every op under keyframe and full-state sync, were applied
    /// here at `t`. `rtt`: the round trip to the coordinator, when known.
    pub fn share_topology(
        &mut self,
        ops: &[sim_core::cut::TopologyOp],
        t: f64,
        rtt: Option<Duration>,
    ) {
        if self.cfg.role == Role::Observer {
            return;
        }
        for op in ops {
            let at = match op {
                sim_core::cut::TopologyOp::Cut(_)
                | sim_core::cut::TopologyOp::Release(_)
                | sim_core::cut::TopologyOp::Refine(_)
                    if self.times_topology() =>
                {
                    t + topology_lead(rtt)
                }
                _ => t,
            };
            let wire = topology_to_wire(op, self.epoch, at);
            if at > t {
                self.hold_topology(wire.clone());
            }
            let msg = Message::Topology(wire);
            self.stats.topology_bytes_sent += proto::encode_frame(&msg).len() as u64;
            self.control(msg);
        }
    }
}

/// Whether `tree_bits` (a keyframe's) differ from the region's tree state here; bits that
/// do not decode count as equal (the keyframe's own checks report them).
fn tree_differs(
    sim: &Simulation,
    map: &RegionMap,
    region: proto::RegionId,
    tree_bits: &[u8],
) -> bool {
    sim_core::sim_lattice::RegionState::from_bytes(tree_bits)
        .is_ok_and(|theirs| theirs != map.state(sim.lattice(), region))
}
