//! Clips: a clip applier closes a clip across a vessel before it is cut.
//!
//! A clip is a [`ClipOp`]: the segment of the clip applier's closed jaws (tip → `length`
//! along the shaft) mapped to **rest** coordinates by the site that placed it (the one
//! place where floating-point state enters, as for a blade's cut). Every site embeds the
//! two ends in the lattice leaf holding them (after a cut: the element copy on their side),
//! so a clip moves with the tissue it closed and stays on its stump when the vessel is cut
//! beside it. Clips are topology operations: ordered by [`crate::cut::OpId`], idempotent,
//! digested with the cuts and releases ([`crate::cut::TopologyLog`]) and carried to every
//! site and to late joiners.
//!
//! A clip has no mechanical effect: the vessels are solid strands (no lumen, no flow), so
//! there is nothing for it to hold shut. It marks where the vessel is closed, which is
//! what the cut that follows must respect.
//!
//! [`ClipApplication`] turns a clip applier's closing jaws into ops: the moment an enabled
//! applier's jaws close ([`crate::tools::Tool::jaws_closed`]) with tissue between them (a
//! point of the jaw segment inside the lattice's leaves), one clip is placed; the jaws
//! must open again before the next.

#[cfg(test)]
mod tests;

use nalgebra::Vector3;
use sim_lattice::{Embedding, Lattice, NodeId, TetId};
use sim_scene::ToolKind;

use crate::cut::{OpId, TopologyOp};
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

/// Sequence numbers of a site's clips start here, so that they never collide with the
/// same site's cuts (from 0) or releases (from [`crate::attach::hook::RELEASE_SEQ_BASE`]).
pub const CLIP_SEQ_BASE: u32 = 1 << 30;

/// Shortest clip (m): the ends of an op must be at least this far apart at rest.
pub const MIN_CLIP_LENGTH: f64 = 1e-4;

/// A clip: the segment of the closed jaws, rest coordinates (m).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ClipOp {
    /// Identity and order.
    pub id: OpId,
    /// The two ends (the jaws' tip and hinge), rest coordinates (m).
    pub ends: [[f64; 3]; 2],
}

impl ClipOp {
    /// The ends as vectors.
    pub fn end_points(&self) -> [V3; 2] {
        self.ends.map(|p| V3::new(p[0], p[1], p[2]))
    }

    /// Checks that the ends are finite and apart.
    pub fn validate(&self) -> Result<(), String> {
        let [a, b] = self.end_points();
        if !a.iter().chain(b.iter()).all(|v| v.is_finite()) {
            return Err(format!("clip {:?}: an end is not finite", self.id));
        }
        if (a - b).norm() < MIN_CLIP_LENGTH {
            return Err(format!(
                "clip {:?}: its ends are {:.2e} m apart (at least {MIN_CLIP_LENGTH} m)",
                self.id,
                (a - b).norm()
            ));
        }
        Ok(())
    }

    /// Bytes of the op as carried (id + 6 f64).
    pub fn wire_bytes(&self) -> usize {
        8 + 48
    }
}

/// The clips of a simulation, embedded in its lattice (ends `2 i`, `2 i + 1` of clip `i`,
/// clips in [`OpId`] order).
#[derive(Clone, Debug, Default)]
pub struct Clips {
    rest: Vec<V3>,
    ends: Option<Embedding>,
    /// Once a cut has separated elements: the degrees of freedom each end follows (the
    /// copy of its host leaf on its side). `None`: the host leaf's lattice nodes.
    end_dofs: Option<Vec<[usize; 4]>>,
}

impl Clips {
    /// Number of clips.
    pub fn len(&self) -> usize {
        self.rest.len() / 2
    }

    /// Whether there is no clip.
    pub fn is_empty(&self) -> bool {
        self.rest.is_empty()
    }

    /// Re-embeds every clip (rest ends in canonical order).
    pub(crate) fn rebuild(&mut self, lattice: &Lattice, rest: Vec<V3>) -> Result<(), SimError> {
        let ends =
            Embedding::new(lattice, &rest).map_err(|e| SimError::Topology(format!("clip: {e}")))?;
        self.rest = rest;
        self.ends = Some(ends);
        self.end_dofs = None;
        Ok(())
    }

    /// Re-hosts the ends after a lattice topology change.
    pub(crate) fn update(&mut self, lattice: &Lattice) {
        if let Some(e) = &mut self.ends {
            e.update(lattice);
        }
    }

    /// After a cut: every end follows `dofs(host leaf, its nodes, end's rest position)`.
    pub(crate) fn follow_cut(&mut self, dofs: impl Fn(TetId, [NodeId; 4], &V3) -> [usize; 4]) {
        let Some(e) = &self.ends else { return };
        self.end_dofs = Some(
            (0..e.len())
                .map(|k| {
                    let (t, _, nodes) = e.host(k);
                    dofs(t, nodes, &self.rest[k])
                })
                .collect(),
        );
    }

    /// Clip `i`'s two ends at node positions `x` (m, indexed by degree of freedom).
    pub fn ends(&self, x: &[V3], i: usize) -> [V3; 2] {
        [2 * i, 2 * i + 1].map(|k| {
            let Some(e) = &self.ends else {
                return self.rest[k];
            };
            let (_, w, nodes) = e.host(k);
            let dofs = match &self.end_dofs {
                Some(d) => d[k],
                None => nodes.map(|n| n.0 as usize),
            };
            (0..4)
                .map(|j| w[j] * x.get(dofs[j]).copied().unwrap_or_else(V3::zeros))
                .sum()
        })
    }
}

/// The clip appliers of a simulation and the clips they placed.
#[derive(Clone, Debug)]
pub struct ClipApplication {
    /// This site's id in the ops it makes.
    pub site: u32,
    next_seq: u32,
    /// Whether each tool's jaws were closed at the last step (a clip needs them to open
    /// and close again).
    closed: Vec<bool>,
    /// Ops made so far, in order (the caller shares them with the other sites).
    pub made: Vec<TopologyOp>,
    /// Which tools may clip here (default: every clip applier). A networked site lets only
    /// the applier it drives clip: the others' clips arrive as their ops.
    pub enabled: Vec<bool>,
}

impl ClipApplication {
    /// Clipping by the clip appliers among `tools`.
    pub fn new(tools: &ToolSet, site: u32) -> Self {
        ClipApplication {
            site,
            next_seq: 0,
            closed: tools.tools.iter().map(|t| t.jaws_closed()).collect(),
            made: Vec::new(),
            enabled: vec![true; tools.tools.len()],
        }
    }

    /// One step of every enabled clip applier: places (applies) a clip where jaws have
    /// just closed on tissue. Returns how many clips were placed. A clip does not move the
    /// tissue, so unlike a cut it needs no scheduling under hybrid sync: it is applied here
    /// at once, as a hook's releases are.
    pub fn update(&mut self, sim: &mut Simulation, tools: &ToolSet) -> Result<usize, SimError> {
        self.closed.resize(tools.tools.len(), false);
        self.enabled.resize(tools.tools.len(), true);
        let mut placed = 0;
        for (ti, tool) in tools.tools.iter().enumerate() {
            let closed = tool.jaws_closed();
            let was = std::mem::replace(&mut self.closed[ti], closed);
            if tool.kind != ToolKind::ClipApplier || !self.enabled[ti] || !closed || was {
                continue;
            }
            let Some((a, b)) = tool.clip_segment() else {
                continue;
            };
            // Tissue between the jaws: a point of the segment inside the lattice's leaves.
            let holds_tissue = (0..=8).any(|k| {
                let p = a + (b - a) * (k as f64 / 8.0);
                sim.rest_point_inside(&p).is_some()
            });
            if !holds_tissue {
                tracing::debug!(tool = %tool.name, "clip applier closed on nothing");
                continue;
            }
            let (Some((ra, _)), Some((rb, _))) = (sim.rest_point_of(&a), sim.rest_point_of(&b))
            else {
                continue;
            };
            let clip = ClipOp {
                id: OpId {
                    site: self.site,
                    seq: CLIP_SEQ_BASE.wrapping_add(self.next_seq),
                },
                ends: [ra.into(), rb.into()],
            };
            if let Err(e) = clip.validate() {
                tracing::warn!(tool = %tool.name, error = %e, "clip not placed");
                continue;
            }
            let op = TopologyOp::Clip(clip);
            self.next_seq += 1;
            sim.apply_topology_op(op.clone())?;
            tracing::info!(tool = %tool.name, "clip placed");
            self.made.push(op);
            placed += 1;
        }
        Ok(placed)
    }
}
