//! Blade strokes: the surface a blade's cutting edge sweeps through a body, turned into
//! [`CutOp`]s.
//!
//! Every step the blade's edge (world coordinates) is sampled at [`EDGE_SAMPLES`] points.
//! Samples inside the body are mapped to rest coordinates through the element that holds
//! them ([`Simulation::rest_point_inside`]); samples outside it take the displacement of the
//! nearest inside sample of the same edge (so the sheet continues straight beyond the
//! body instead of following an extrapolated element). While the edge is inside the body, a
//! new edge is kept whenever a sample moved more than `spacing` (m) since the last kept
//! edge. The edge of the step before entering and the edge after leaving are kept too, with
//! the displacements of the first and last inside edges, and both are pushed one more
//! `spacing` outward along the motion so the sheet surely reaches beyond the body. When the
//! edge leaves the body the stroke is committed as one cut op: two triangles between
//! neighbouring samples of consecutive edges. Only the cutting site runs this; the op
//! carries the rest-space triangles to every site.

use nalgebra::Vector3;

use super::{CutOp, OpId, TopologyOp, predicates};
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

/// Points along the blade's edge (both ends included).
pub const EDGE_SAMPLES: usize = 5;

type Edge = [V3; EDGE_SAMPLES];

#[derive(Clone, Debug, Default)]
struct Stroke {
    /// Kept edges (rest coordinates) of the stroke under way.
    edges: Vec<Edge>,
    /// World edge of the previous step while outside the body.
    before: Option<Edge>,
    /// Displacement (world − rest) of every sample of the last inside edge.
    last_displacement: Option<Edge>,
}

/// The strokes of a simulation's blades.
#[derive(Clone, Debug)]
pub struct BladeStrokes {
    strokes: Vec<Stroke>,
    /// This site's id in the ops it makes.
    pub site: u32,
    next_seq: u32,
    /// Minimum motion of an edge end between two kept samples (m).
    pub spacing: f64,
    /// Ops made so far, in order (the caller shares them with the other sites).
    pub made: Vec<TopologyOp>,
    /// Which tools may cut here (default: every blade). A networked site lets only the
    /// blade it drives cut: the others' cuts arrive as their ops.
    pub enabled: Vec<bool>,
    /// Whether a committed cut is applied here at once (default). A site under hybrid or
    /// input-only sync turns this off and applies its own cuts a little later, at a
    /// simulated time it shares with the op, so that every site parts the tissue at the
    /// same moment.
    pub apply_own: bool,
}

impl BladeStrokes {
    /// Strokes for the tools of `tools` (only blades cut); `spacing` defaults to a quarter
    /// of the lattice cell.
    pub fn new(sim: &Simulation, tools: &ToolSet, site: u32) -> Self {
        BladeStrokes {
            strokes: vec![Stroke::default(); tools.tools.len()],
            site,
            next_seq: 0,
            spacing: 0.25 * sim.lattice().params().cell,
            made: Vec::new(),
            enabled: vec![true; tools.tools.len()],
            apply_own: true,
        }
    }

    /// Follows every blade for one step; commits the strokes that ended and applies them
    /// (unless [`Self::apply_own`] is off). Returns how many cuts were applied.
    pub fn update(&mut self, sim: &mut Simulation, tools: &ToolSet) -> Result<usize, SimError> {
        let mut applied = 0;
        self.strokes.resize(tools.tools.len(), Stroke::default());
        self.enabled.resize(tools.tools.len(), true);
        for ((tool, stroke), _) in tools
            .tools
            .iter()
            .zip(self.strokes.iter_mut())
            .zip(&self.enabled)
            .filter(|(_, on)| **on)
        {
            let Some((a, b)) = tool.blade_edge() else {
                continue;
            };
            let world: Edge =
                std::array::from_fn(|k| a + (k as f64 / (EDGE_SAMPLES - 1) as f64) * (b - a));
            let mapped = sim.rest_points_inside(&world);
            let inside: Vec<usize> = (0..EDGE_SAMPLES).filter(|&k| mapped[k].is_some()).collect();
            if !inside.is_empty() {
                // Displacement of every sample: its own inside, the nearest inside one's
                // outside.
                let u: Edge = std::array::from_fn(|k| {
                    let j = *inside
                        .iter()
                        .min_by_key(|&&j| (j as isize - k as isize).abs())
                        .expect("non-empty");
                    world[j] - mapped[j].expect("inside")
                });
                let edge: Edge = std::array::from_fn(|k| world[k] - u[k]);
                if stroke.edges.is_empty() {
                    let before = stroke.before.unwrap_or(world);
                    let first: Edge = std::array::from_fn(|k| before[k] - u[k]);
                    stroke.edges.push(extend(&first, &edge, self.spacing));
                    stroke.edges.push(first);
                }
                let last = stroke.edges.last().expect("non-empty");
                let moved = (0..EDGE_SAMPLES)
                    .map(|k| (last[k] - edge[k]).norm())
                    .fold(0.0, f64::max);
                if moved > self.spacing {
                    stroke.edges.push(edge);
                }
                stroke.last_displacement = Some(u);
                stroke.before = None;
            } else {
                if let (false, Some(u)) = (stroke.edges.is_empty(), stroke.last_displacement) {
                    let exit: Edge = std::array::from_fn(|k| world[k] - u[k]);
                    let last = *stroke.edges.last().expect("non-empty");
                    stroke.edges.push(exit);
                    stroke.edges.push(extend(&exit, &last, self.spacing));
                    let edges = std::mem::take(&mut stroke.edges);
                    if let Some(op) = strip(
                        &edges,
                        OpId {
                            site: self.site,
                            seq: self.next_seq,
                        },
                    ) {
                        self.next_seq += 1;
                        tracing::info!(
                            tool = %tool.name,
                            triangles = op.triangles.len(),
                            "blade stroke committed as a cut"
                        );
                        let op = TopologyOp::Cut(op);
                        if self.apply_own {
                            sim.apply_topology_op(op.clone())?;
                            applied += 1;
                        }
                        self.made.push(op);
                    }
                }
                stroke.edges.clear();
                stroke.last_displacement = None;
                stroke.before = Some(world);
            }
        }
        Ok(applied)
    }
}

/// `edge` pushed `spacing` further away from `from` (along the mean motion between them;
/// by `spacing` along the first motion direction it can find otherwise).
fn extend(edge: &Edge, from: &Edge, spacing: f64) -> Edge {
    let motion: V3 = (0..EDGE_SAMPLES).map(|k| edge[k] - from[k]).sum::<V3>() / EDGE_SAMPLES as f64;
    let dir = motion.try_normalize(1e-12).unwrap_or_else(V3::zeros);
    std::array::from_fn(|k| edge[k] + spacing * dir)
}

/// The triangles between neighbouring samples of consecutive edges (degenerate ones
/// dropped); `None` if none is left.
pub fn strip(edges: &[Edge], id: OpId) -> Option<CutOp> {
    let mut triangles = Vec::new();
    for w in edges.windows(2) {
        for k in 0..EDGE_SAMPLES - 1 {
            let (a0, b0, a1, b1) = (w[0][k], w[0][k + 1], w[1][k], w[1][k + 1]);
            for t in [[a0, b0, b1], [a0, b1, a1]] {
                if predicates::non_degenerate(&t) {
                    triangles.push(t.map(|p| [p.x, p.y, p.z]));
                }
            }
        }
    }
    (!triangles.is_empty()).then_some(CutOp { id, triangles })
}
