//! Adaptivity following the tools: every `every` steps, leaves near a contact or grasped
//! point refine to the body's maximum depth (conforming splits through the lattice), and
//! diamonds created since the scene was built coarsen back once they have been far from
//! every such point for longer than a hold time. The scene's static refinement (material
//! boundaries, [`Simulation::is_static_diamond`]) is never undone.
//!
//! # Decided once, applied everywhere
//! Where to refine is a threshold on continuous state (how near a leaf is to a contact),
//! and two sites whose states differ by micrometres decide differently when a leaf is near
//! the threshold: one splits a pass earlier, and the sites' simulations part by tenths of
//! a millimetre to a millimetre at that moment (`docs/RESULTS.md`, "Where the remaining
//! sync divergence comes from"). So the decision is taken on one site and carried as a
//! [`RefineOp`] in rest space only: the focus points of the tools that site drives, mapped
//! to rest coordinates, and the diamonds to merge by grid position. Applying it reads no
//! floating-point state ([`Simulation::apply_refine`]), so every site that applies it at
//! the same simulated time ends with the same lattice. A site alone applies its decisions
//! at once ([`Adaptivity::apply_own`]); a site linked under hybrid or input-only sync
//! hands them to its session
//! ([`Adaptivity::made`]), which schedules them ahead for every site, as it does cuts.
//!
//! Merges are decided by every site that drives or drove a tool, for every diamond created
//! since the scene was built (by any site's op, or along a cut; a site that applies its
//! decisions at once watches only the diamonds they split), against the focus points
//! of every tool; duplicates are harmless (merging a diamond that is gone does nothing).
//! A merge that does not happen (a finer diamond or a cut holds it) is decided again less
//! and less often.
//!
//! Under keyframe and full-state sync, where followers do not simulate the others' tools,
//! every site decides for every tool and applies its decisions at once, and the owners'
//! keyframes carry their regions' tree states. Such decisions need not be state-free, and
//! they are taken in current coordinates, on the leaves' deformed boxes around the
//! contacts where they are now: the tissue near a tool is refined where it has moved to,
//! not where it rests (deciding in rest space there made the owner coarsen under a
//! spring-back, and its followers diverged by up to 5.71 mm under `lan` on the worst
//! seed against 1.08 mm with deformed decisions, `docs/RESULTS.md`).

mod op;

use std::collections::{HashMap, HashSet};

use nalgebra::Vector3;
use sim_lattice::NodeId;

use crate::cut::{OpId, TopologyOp};
use crate::engine::Simulation;
use crate::error::SimError;

use op::Space;
pub use op::{
    MAX_REFINE_DISTANCE_CELLS, MAX_REFINE_FOCUS, MAX_REFINE_MERGES, REFINE_SEQ_BASE, RefineChange,
    RefineOp,
};

type V3 = Vector3<f64>;

/// How long (s of simulated time) a decision sent to the session counts as on its way: no
/// decision is repeated for a focus point or a diamond within that time. Longer than the
/// session's largest scheduling lead (0.5 s).
pub const PENDING_S: f64 = 0.6;

/// A merge that did not happen is decided again after `PENDING_S` plus the hold time
/// times 2, 4, … up to 2 to this power.
const MAX_MERGE_BACKOFF: u32 = 6;

/// Adaptivity constants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptParams {
    /// Adapt every this many calls (steps), ≥ 1.
    pub every: u32,
    /// Leaves whose box comes within this distance (m) of a focus point refine (rest boxes
    /// and points for decisions carried as ops, current ones for decisions applied at
    /// once).
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

/// The focus points of every tool (contacts, grasped points; m), one list per tool in
/// scene order, in rest coordinates and where they are now.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FocusPoints {
    /// Rest coordinates: what decisions carried as ops read.
    pub rest: Vec<Vec<V3>>,
    /// Current coordinates: what decisions applied at once read.
    pub deformed: Vec<Vec<V3>>,
}

/// A diamond adaptivity created, watched for merging.
#[derive(Clone, Copy, Debug)]
struct Watched {
    node: NodeId,
    /// Rest length of the split edge (m): finer diamonds merge first.
    edge: f64,
    /// Last simulated time (s) a focus point was near it.
    last_near: f64,
    /// Merges of it decided since a focus point was last near.
    attempts: u32,
    /// Not decided again before this simulated time (s).
    retry_at: f64,
}

/// The decisions of refinement and coarsening around the tools (see the module
/// documentation).
#[derive(Clone, Debug)]
pub struct Adaptivity {
    /// Constants.
    pub params: AdaptParams,
    /// Whether decisions are applied at once (a site alone; keyframe and full-state sync),
    /// or only made, into [`Self::made`], for the session to schedule.
    pub apply_own: bool,
    /// The site whose decisions these are (the ops' ids).
    pub site: u32,
    /// Per tool, in scene order: whether its focus points refine here (the tools this
    /// site drives; all by default). Every tool's focus points keep diamonds from merging.
    pub enabled: Vec<bool>,
    /// Ops made and not yet taken (when [`Self::apply_own`] is off).
    pub made: Vec<TopologyOp>,
    next_seq: u32,
    calls: u64,
    /// Whether a tool was ever enabled here: such a site decides merges (see
    /// [`Self::update`]).
    has_driven: bool,
    /// Diamonds created since the scene was built, by centre grid position.
    watched: HashMap<[i64; 3], Watched>,
    /// Lattice generation `watched` was taken at.
    watched_generation: Option<u64>,
    /// Focus points (rest) of decisions on their way, with the time they were made.
    pending_focus: Vec<(f64, V3)>,
    /// Diamond centres our own decisions split, when they are applied at once.
    own: HashSet<[i64; 3]>,
    initial_leaves: usize,
    /// Calls that did any work.
    pub passes_run: u64,
}

impl Adaptivity {
    /// Adaptivity for `sim` in its current (static) refinement.
    pub fn new(sim: &Simulation, params: AdaptParams) -> Self {
        let lat = sim.lattice();
        Adaptivity {
            params,
            apply_own: true,
            site: 0,
            enabled: Vec::new(),
            made: Vec::new(),
            next_seq: 0,
            calls: 0,
            has_driven: false,
            watched: HashMap::new(),
            watched_generation: None,
            pending_focus: Vec::new(),
            own: HashSet::new(),
            initial_leaves: lat.leaf_count(),
            passes_run: 0,
        }
    }

    /// Leaves when adaptivity started.
    pub fn initial_leaves(&self) -> usize {
        self.initial_leaves
    }

    /// Diamonds adaptivity created that are still split.
    pub fn created_diamonds(&self) -> usize {
        self.watched.len()
    }

    /// One call per step with the focus points (contacts, grasped points) of every tool.
    /// Works every `every` calls when the simulation's adaptivity is on and there is a
    /// focus point or a created diamond: refines around the focus points of the
    /// [`Self::enabled`] tools, merges created diamonds that every focus point has left
    /// for the hold time. Decisions made into ops read the rest points; decisions applied
    /// at once ([`Self::apply_own`]) the current ones (see the module documentation).
    pub fn update(
        &mut self,
        sim: &mut Simulation,
        focus: &FocusPoints,
    ) -> Result<AdaptReport, SimError> {
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
        {
            return Ok(report);
        }
        self.watch(sim);
        let space = if self.apply_own {
            Space::Deformed
        } else {
            Space::Rest
        };
        let focus_all = match space {
            Space::Rest => &focus.rest,
            Space::Deformed => &focus.deformed,
        };
        let any_focus = focus_all.iter().any(|f| !f.is_empty());
        if !any_focus && self.watched.is_empty() {
            return Ok(report);
        }
        report.ran = true;
        self.passes_run += 1;
        let now = sim.time();
        // Decisions on their way expire (a reset takes time back: they expire too).
        self.pending_focus
            .retain(|(t, _)| *t <= now && now - *t < PENDING_S);

        let enabled = |i: usize| self.enabled.get(i).copied().unwrap_or(true);
        let refine: Vec<V3> = focus_all
            .iter()
            .enumerate()
            .filter(|(i, _)| enabled(*i))
            .flat_map(|(_, f)| f.iter().copied())
            .collect();
        let mut chosen = self.refine_focus(sim, &refine, space);
        chosen.truncate(MAX_REFINE_FOCUS);
        // Only a site that drives or drove a tool decides merges: drivers run level with
        // the owners, so their decisions reach every site in time, while a follower runs
        // behind by its playout lag, and its ops would reach the leading sites after
        // their time. Once it drove, a site keeps deciding them, so that the tissue
        // coarsens back after the last tool stops.
        self.has_driven |= (0..focus_all.len().max(1)).any(enabled);
        let mut merge = if self.has_driven {
            self.due_merges(sim, focus_all, now, space)
        } else {
            Vec::new()
        };
        merge.truncate(MAX_REFINE_MERGES);
        for g in merge.iter().filter(|_| !self.apply_own) {
            // A merge sent that does not happen (a finer diamond, or one near a cut, holds
            // it) is decided again later, and less often each time. Applied at once, a
            // merge is tried again on the next pass, as a finer diamond may merge first.
            if let Some(w) = self.watched.get_mut(g) {
                w.attempts = (w.attempts + 1).min(MAX_MERGE_BACKOFF);
                w.retry_at =
                    now + PENDING_S + self.params.hold_time * f64::from(1u32 << w.attempts);
            }
        }
        if chosen.is_empty() && merge.is_empty() {
            return Ok(report);
        }
        if self.apply_own {
            let before = diamond_centres(sim);
            let max_level = self.params.max_level.min(sim.lattice().params().max_depth);
            if !chosen.is_empty() {
                report.split = op::refine_near(
                    sim,
                    &chosen,
                    self.params.distance,
                    max_level,
                    Space::Deformed,
                )?;
            }
            if !merge.is_empty() {
                report.merged = op::merge_diamonds(sim, &merge)?;
            }
            // Forget only what is gone: a merge a finer diamond or a neighbour held back
            // stays ours, to be tried again on the next pass.
            let live = diamond_centres(sim);
            self.own.retain(|g| live.contains(g));
            self.own.extend(live.difference(&before).copied());
            self.watch(sim);
        } else {
            self.pending_focus.extend(chosen.iter().map(|p| (now, *p)));
            self.made.push(TopologyOp::Refine(RefineOp {
                id: OpId {
                    site: self.site,
                    seq: REFINE_SEQ_BASE.wrapping_add(self.next_seq),
                },
                focus: chosen.iter().map(|p| [p.x, p.y, p.z]).collect(),
                distance: self.params.distance,
                level: self.params.max_level,
                merge,
            }));
            self.next_seq = self.next_seq.wrapping_add(1);
        }
        report.leaves = sim.lattice().leaf_count();
        Ok(report)
    }

    /// The focus points worth an op: those with a leaf below the level within the
    /// distance, not near a point of a decision on its way or of this one (a quarter of
    /// the distance: a later pass takes what they leave, once the decisions on their way
    /// are applied).
    fn refine_focus(&self, sim: &Simulation, points: &[V3], space: Space) -> Vec<V3> {
        let d = self.params.distance;
        let max_level = self.params.max_level.min(sim.lattice().params().max_depth);
        if points.is_empty() || max_level == 0 {
            return Vec::new();
        }
        let (flo, fhi) = op::padded_box(points, d);
        // The coarse leaves near any of the points.
        let coarse: Vec<(V3, V3)> = (0..sim.lattice().leaf_count())
            .filter(|&i| sim.lattice().leaves()[i].level() < max_level)
            .map(|i| op::leaf_box(sim, i, space))
            .filter(|(lo, hi)| !(0..3).any(|k| lo[k] > fhi[k] || hi[k] < flo[k]))
            .collect();
        let near = 0.25 * d;
        let mut chosen: Vec<V3> = Vec::new();
        for p in points {
            if self
                .pending_focus
                .iter()
                .map(|(_, q)| q)
                .chain(&chosen)
                .any(|q| (q - p).norm() <= near)
            {
                continue;
            }
            if coarse
                .iter()
                .any(|(lo, hi)| op::box_distance(lo, hi, p) <= d)
            {
                chosen.push(*p);
            }
        }
        chosen
    }

    /// Created diamonds every focus point has left for the hold time (finest first), not
    /// pinned by a cut and not on their way already. Notes which are near.
    fn due_merges(
        &mut self,
        sim: &Simulation,
        focus: &[Vec<V3>],
        now: f64,
        space: Space,
    ) -> Vec<[i64; 3]> {
        let d = self.params.distance;
        let lat = sim.lattice();
        let x = sim.positions();
        for w in self.watched.values_mut() {
            let p = match space {
                Space::Rest => lat.node_rest(w.node),
                Space::Deformed => x[w.node.0 as usize],
            };
            if focus.iter().flatten().any(|f| (f - p).norm() <= d + w.edge) {
                w.last_near = now;
                w.attempts = 0;
                w.retry_at = 0.0;
            }
        }
        let mut due: Vec<([i64; 3], f64)> = self
            .watched
            .iter()
            .filter(|(_, w)| {
                now - w.last_near > self.params.hold_time
                    && now >= w.retry_at
                    && !sim.cut_pins_node(w.node)
            })
            .map(|(g, w)| (*g, w.edge))
            .collect();
        due.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        due.into_iter().map(|(g, _)| g).collect()
    }

    /// Brings the watched diamonds up to date with the lattice: every live diamond centre
    /// that was not there at the start (whoever's op split it) is watched, from now.
    fn watch(&mut self, sim: &Simulation) {
        let lat = sim.lattice();
        let generation = lat.topology_generation();
        if self.watched_generation == Some(generation) {
            return;
        }
        self.watched_generation = Some(generation);
        let now = sim.time();
        let mut live: HashMap<[i64; 3], Watched> = HashMap::new();
        for n in lat.nodes() {
            let Some((a, b)) = lat.node_parent_edge(n) else {
                continue;
            };
            let g = lat.node_grid(n);
            // Applying our own decisions (a site alone; keyframe and full-state sync),
            // only what they split: under those strategies an owner's tree reaches us in
            // its keyframes, and merging it here (we do not see its tool's contacts)
            // would fight each keyframe (6.4 mm of divergence under `lan`, measured).
            if sim.is_static_diamond(&g) || (self.apply_own && !self.own.contains(&g)) {
                continue;
            }
            let w = match self.watched.get(&g) {
                Some(w) => Watched { node: n, ..*w },
                None => Watched {
                    node: n,
                    edge: (lat.node_rest(a) - lat.node_rest(b)).norm(),
                    last_near: now,
                    attempts: 0,
                    retry_at: 0.0,
                },
            };
            live.insert(g, w);
        }
        self.watched = live;
    }
}

/// Grid positions of every live diamond centre of `sim`'s lattice.
fn diamond_centres(sim: &Simulation) -> HashSet<[i64; 3]> {
    let lat = sim.lattice();
    lat.nodes()
        .filter(|&n| lat.node_parent_edge(n).is_some())
        .map(|n| lat.node_grid(n))
        .collect()
}
