//! Blade strokes: the surface a blade's cutting edge sweeps through a body, turned into
//! [`CutOp`]s.
//!
//! Every step the blade's edge (world coordinates) is mapped to rest coordinates through
//! the element that holds it ([`Simulation::rest_point_of`]). While the edge is inside the
//! body, a new edge sample is kept whenever an end moved more than `spacing` (m) since the
//! last one; the edge before entering and the edge after leaving are kept too, so the swept
//! sheet reaches beyond the body. When the edge leaves the body the stroke is committed as
//! one cut op: two triangles between consecutive edge samples. Only the cutting site runs
//! this; the op carries the rest-space triangles to every site.

use nalgebra::Vector3;

use super::{CutOp, OpId, TopologyOp, predicates};
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

/// Number of points along the edge tested for being inside the body.
const EDGE_PROBES: usize = 5;

#[derive(Clone, Debug, Default)]
struct Stroke {
    /// Edge samples (rest coordinates) of the stroke under way.
    edges: Vec<[V3; 2]>,
    /// The edge of the previous step (rest coordinates) while outside the body.
    before: Option<[V3; 2]>,
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
        }
    }

    /// Follows every blade for one step; commits and applies the strokes that ended.
    /// Returns how many cuts were applied.
    pub fn update(&mut self, sim: &mut Simulation, tools: &ToolSet) -> Result<usize, SimError> {
        let mut applied = 0;
        self.strokes.resize(tools.tools.len(), Stroke::default());
        for (tool, stroke) in tools.tools.iter().zip(self.strokes.iter_mut()) {
            let Some((a, b)) = tool.blade_edge() else {
                continue;
            };
            let mut inside = false;
            for k in 0..EDGE_PROBES {
                let s = k as f64 / (EDGE_PROBES - 1) as f64;
                if let Some((_, true)) = sim.rest_point_of(&(a + s * (b - a))) {
                    inside = true;
                    break;
                }
            }
            let (Some((ra, _)), Some((rb, _))) = (sim.rest_point_of(&a), sim.rest_point_of(&b))
            else {
                continue;
            };
            let edge = [ra, rb];
            if inside {
                if stroke.edges.is_empty() {
                    stroke.edges.push(stroke.before.unwrap_or(edge));
                }
                let last = stroke.edges.last().expect("non-empty");
                if (last[0] - edge[0]).norm().max((last[1] - edge[1]).norm()) > self.spacing {
                    stroke.edges.push(edge);
                }
                stroke.before = None;
            } else {
                if !stroke.edges.is_empty() {
                    stroke.edges.push(edge);
                    let edges = std::mem::take(&mut stroke.edges);
                    if let Some(op) = strip(&edges, OpId {
                        site: self.site,
                        seq: self.next_seq,
                    }) {
                        self.next_seq += 1;
                        tracing::info!(
                            tool = %tool.name,
                            triangles = op.triangles.len(),
                            "blade stroke committed as a cut"
                        );
                        let op = TopologyOp::Cut(op);
                        sim.apply_topology_op(op.clone())?;
                        self.made.push(op);
                        applied += 1;
                    }
                }
                stroke.before = Some(edge);
            }
        }
        Ok(applied)
    }
}

/// The triangles between consecutive edge samples (degenerate ones dropped); `None` if
/// none is left.
pub fn strip(edges: &[[V3; 2]], id: OpId) -> Option<CutOp> {
    let mut triangles = Vec::new();
    for w in edges.windows(2) {
        let ([a0, b0], [a1, b1]) = (w[0], w[1]);
        for t in [[a0, b0, b1], [a0, b1, a1]] {
            if predicates::non_degenerate(&t) {
                triangles.push(t.map(|p| [p.x, p.y, p.z]));
            }
        }
    }
    (!triangles.is_empty()).then_some(CutOp { id, triangles })
}
