//! Adaptivity following the tools: every `every` steps, leaves near a contact or grasped
//! point refine to the body's maximum depth (conforming splits through the lattice), and
//! diamonds that adaptivity created coarsen back once they have been far from every such
//! point for longer than a hold time. Splits that existed when the simulation was handed
//! to [`Adaptivity::new`] (the static material-boundary refinement) are never undone:
//! only diamonds whose centre node adaptivity itself created are merged.

use std::collections::HashMap;

use nalgebra::Vector3;
use sim_lattice::{NodeId, TetId, TopologyEvent};

use crate::engine::Simulation;
use crate::error::SimError;

type V3 = Vector3<f64>;

/// Adaptivity constants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptParams {
    /// Adapt every this many calls (steps), ≥ 1.
    pub every: u32,
    /// Leaves whose deformed box comes within this distance (m) of a focus point refine.
    pub distance: f64,
    /// A created diamond merges after being far from every focus point this long (s).
    pub hold_time: f64,
    /// Deepest level to refine to (the lattice's `max_depth` by default).
    pub max_level: u8,
}

impl AdaptParams {
    /// Every 10 steps, within half a root cell, hold 0.5 s, to the lattice's max depth.
    pub fn from_sim(sim: &Simulation) -> Self {
        let p = sim.lattice().params();
        AdaptParams {
            every: 10,
            distance: 0.5 * p.cell,
            hold_time: 0.5,
            max_level: p.max_depth,
        }
    }
}

/// What one adaptivity call did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptReport {
    /// Whether this call looked at the lattice at all.
    pub ran: bool,
    /// Tets split (including conformity splits).
    pub split: usize,
    /// Diamonds merged.
    pub merged: usize,
    /// Leaves afterwards.
    pub leaves: usize,
}

#[derive(Clone, Copy, Debug)]
struct Created {
    node: NodeId,
    /// Rest length of the split edge (m): finer diamonds merge first.
    edge: f64,
    last_near: f64,
}

/// Refinement and coarsening around the tools.
#[derive(Clone, Debug)]
pub struct Adaptivity {
    /// Constants.
    pub params: AdaptParams,
    calls: u64,
    /// Diamonds created by adaptivity, by the grid position of their centre node.
    created: HashMap<[i64; 3], Created>,
    initial_leaves: usize,
    /// Calls that did any work.
    pub passes_run: u64,
}

impl Adaptivity {
    /// Adaptivity for `sim` in its current (static) refinement.
    pub fn new(sim: &Simulation, params: AdaptParams) -> Self {
        Adaptivity {
            params,
            calls: 0,
            created: HashMap::new(),
            initial_leaves: sim.lattice().leaf_count(),
            passes_run: 0,
        }
    }

    /// Leaves when adaptivity started.
    pub fn initial_leaves(&self) -> usize {
        self.initial_leaves
    }

    /// Diamonds adaptivity created that are still split.
    pub fn created_diamonds(&self) -> usize {
        self.created.len()
    }

    /// One call per step with the current focus points (contacts, grasped points; m).
    /// Works every `every` calls when the simulation's adaptivity is on and there is a
    /// focus point or a created diamond.
    pub fn update(&mut self, sim: &mut Simulation, focus: &[V3]) -> Result<AdaptReport, SimError> {
        let mut report = AdaptReport {
            leaves: sim.lattice().leaf_count(),
            ..AdaptReport::default()
        };
        if !sim.options().adaptivity {
            return Ok(report);
        }
        self.calls += 1;
        if !self
            .calls
            .is_multiple_of(u64::from(self.params.every.max(1)))
            || (focus.is_empty() && self.created.is_empty())
        {
            return Ok(report);
        }
        report.ran = true;
        self.passes_run += 1;
        let now = sim.time();
        let d = self.params.distance;
        if !focus.is_empty() {
            let mut flo = V3::repeat(f64::INFINITY);
            let mut fhi = V3::repeat(f64::NEG_INFINITY);
            for p in focus {
                flo = flo.inf(p);
                fhi = fhi.sup(p);
            }
            let (flo, fhi) = (flo.add_scalar(-d), fhi.add_scalar(d));
            let max_level = self.params.max_level.min(sim.lattice().params().max_depth);
            // Each round splits the near leaves one level (and what conformity forces).
            for _ in 0..=(3 * usize::from(max_level) + 3) {
                let todo: Vec<TetId> = {
                    let lat = sim.lattice();
                    let x = sim.positions();
                    lat.leaves()
                        .iter()
                        .enumerate()
                        .filter(|(_, t)| t.level() < max_level)
                        .filter(|(i, _)| {
                            let nodes = lat.leaf_tet_nodes(*i);
                            let mut lo = V3::repeat(f64::INFINITY);
                            let mut hi = V3::repeat(f64::NEG_INFINITY);
                            for n in nodes {
                                lo = lo.inf(&x[n.0 as usize]);
                                hi = hi.sup(&x[n.0 as usize]);
                            }
                            if (0..3).any(|k| lo[k] > fhi[k] || hi[k] < flo[k]) {
                                return false;
                            }
                            focus.iter().any(|p| box_distance(&lo, &hi, p) <= d)
                        })
                        .map(|(_, t)| *t)
                        .collect()
                };
                if todo.is_empty() {
                    break;
                }
                let mut events = Vec::new();
                for t in todo {
                    let lat = sim.lattice_mut();
                    if lat.is_leaf(t) {
                        report.split += lat.refine(t, &mut events)?;
                    }
                }
                for e in &events {
                    if let TopologyEvent::NodeAdded { node, edge } = *e {
                        let lat = sim.lattice();
                        let len = (lat.node_rest(edge.0) - lat.node_rest(edge.1)).norm();
                        self.created.insert(
                            lat.node_grid(node),
                            Created {
                                node,
                                edge: len,
                                last_near: now,
                            },
                        );
                    }
                }
                sim.after_topology_change(&events)?;
            }
        }
        // Coarsen created diamonds that have been far long enough, finest first.
        let x = sim.positions();
        let lat = sim.lattice();
        self.created
            .retain(|g, c| lat.node_alive(c.node) && lat.node_grid(c.node) == *g);
        for c in self.created.values_mut() {
            let p = x[c.node.0 as usize];
            if focus.iter().any(|f| (f - p).norm() <= d + c.edge) {
                c.last_near = now;
            }
        }
        let mut due: Vec<([i64; 3], Created)> = self
            .created
            .iter()
            .filter(|(_, c)| now - c.last_near > self.params.hold_time)
            .map(|(g, c)| (*g, *c))
            .collect();
        if due.is_empty() {
            report.leaves = sim.lattice().leaf_count();
            return Ok(report);
        }
        due.sort_by(|a, b| a.1.edge.total_cmp(&b.1.edge).then(a.0.cmp(&b.0)));
        let mut events = Vec::new();
        loop {
            let mut progress = false;
            for (g, c) in &due {
                if !self.created.contains_key(g) {
                    continue;
                }
                // A diamond along a cut stays: merging it would reconnect separated
                // material.
                if sim.cut_pins_node(c.node) {
                    continue;
                }
                let lat = sim.lattice_mut();
                if !lat.node_alive(c.node) || lat.node_grid(c.node) != *g {
                    self.created.remove(g);
                    continue;
                }
                if lat.coarsen_diamond(c.node, &mut events)? {
                    self.created.remove(g);
                    report.merged += 1;
                    progress = true;
                }
            }
            if !progress {
                break;
            }
        }
        sim.after_topology_change(&events)?;
        report.leaves = sim.lattice().leaf_count();
        Ok(report)
    }
}

/// Distance from `p` to the box `lo..hi` (0 inside).
fn box_distance(lo: &V3, hi: &V3, p: &V3) -> f64 {
    let mut d2 = 0.0;
    for k in 0..3 {
        let e = (lo[k] - p[k]).max(p[k] - hi[k]).max(0.0);
        d2 += e * e;
    }
    d2.sqrt()
}
