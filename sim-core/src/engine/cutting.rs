//! The simulation side of cutting: applying topology operations, keeping the virtual
//! nodes' state across topology changes, the element copies of the FEM system, the cut
//! surfaces, and mapping deformed points back to rest coordinates (for the blade).
//!
//! Layout of the node arrays once a cut exists: slots `0..capacity` are the lattice's
//! nodes as before (indexed by [`NodeId`]), slots `capacity..` are the virtual nodes of
//! [`Separation::virtual_nodes`]. A lattice topology change moves the virtual block (its
//! state follows the element copies, see [`Simulation::reseparate`]).

use nalgebra::Vector3;
use sim_lattice::{NodeId, TetId, TopologyEvent};
use sim_scene::TriMesh;

use super::Simulation;
use crate::cut::{Separation, Sheet, TopologyOp, cut_surface, separate::separate};
use crate::error::SimError;

type V3 = Vector3<f64>;

/// A point whose smallest barycentric coordinate in an element is at least this is inside
/// it ([`Simulation::rest_point_of`]).
const INSIDE_TOLERANCE: f64 = -1e-9;

/// Margin (m) of the element boxes [`Simulation::rest_point_inside`] tests: wide enough
/// that every element containing a point within [`INSIDE_TOLERANCE`] passes (the
/// tolerance is relative to the element's size, under a metre here).
const BOX_MARGIN_M: f64 = 1e-8;

/// A point in an element: its smallest barycentric coordinate, the element's degrees of
/// freedom and the coordinates.
type ElementHit = (f64, [usize; 4], [f64; 4]);

/// Inverse of the element's edge matrix `[p₁ − p₀, p₂ − p₀, p₃ − p₀]` (`None`: degenerate).
fn edge_matrix_inverse(p: &[V3; 4]) -> Option<nalgebra::Matrix3<f64>> {
    nalgebra::Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]).try_inverse()
}

/// Barycentric coordinates of `q` in the element `p` (`inv` from [`edge_matrix_inverse`])
/// and the smallest of them.
fn barycentric(p: &[V3; 4], inv: &nalgebra::Matrix3<f64>, q: &V3) -> (f64, [f64; 4]) {
    let l = inv * (q - p[0]);
    let w = [1.0 - l.x - l.y - l.z, l.x, l.y, l.z];
    (w.iter().copied().fold(f64::INFINITY, f64::min), w)
}

/// Cut state of a simulation (present once a cut op is applied).
#[derive(Clone, Debug)]
pub(crate) struct CutState {
    pub(crate) sheet: Sheet,
    pub(crate) separation: Separation,
    /// Every surface's rest mesh before any cut (cuts are recomputed from it).
    pub(crate) original: Vec<TriMesh>,
    /// Per surface and vertex: the degrees of freedom and weights it is interpolated from.
    pub(crate) hosts: Vec<Vec<([usize; 4], [f64; 4])>>,
    /// Why a surface could not be cut (it is then left uncut), per surface.
    pub(crate) surface_errors: Vec<Option<String>>,
}

impl CutState {
    /// The degrees of freedom that a point embedded in leaf `t` (corner nodes `nodes`, in
    /// the order its weights use: an [`sim_lattice::Embedding`]'s bisection order) at rest
    /// position `p` (m) follows, in that same order: the copy of the leaf holding the
    /// nearest corner that `p` reaches without crossing the sheet (exact test); the
    /// lattice nodes themselves when the leaf is not crossed.
    ///
    /// A copy lists its corners in [`sim_lattice::Lattice::tet_nodes`] order (oriented),
    /// which differs from the bisection order by a swap in half of the leaves: the copy's
    /// degrees of freedom are permuted back to `nodes`' order.
    pub(crate) fn copy_dofs(
        &self,
        lat: &sim_lattice::Lattice,
        t: TetId,
        nodes: [NodeId; 4],
        p: &V3,
    ) -> [usize; 4] {
        let copies = self.separation.copies_of(t);
        if copies.is_empty() {
            return nodes.map(|n| n.0 as usize);
        }
        let oriented = lat.tet_nodes(t);
        // perm[j]: the copy's corner index of `nodes[j]`.
        let perm = nodes.map(|n| {
            oriented
                .iter()
                .position(|&m| m == n)
                .expect("an embedding's nodes are its host leaf's corners")
        });
        let copy = match copies.len() {
            1 => &copies[0],
            _ => {
                let mut order: Vec<(f64, usize)> = (0..4)
                    .map(|k| ((lat.node_rest(oriented[k]) - p).norm_squared(), k))
                    .collect();
                order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let corner = order.iter().map(|o| o.1).find(|&k| {
                    self.sheet
                        .crossing(p, &lat.node_rest(oriented[k]))
                        .is_none()
                });
                corner
                    .and_then(|k| copies.iter().find(|c| c.mask & (1 << k) != 0))
                    .unwrap_or_else(|| {
                        copies
                            .iter()
                            .max_by(|a, b| a.fraction.total_cmp(&b.fraction))
                            .expect("two or more copies")
                    })
            }
        };
        perm.map(|k| copy.dofs[k])
    }
}

/// What applying a topology op did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TopologyChange {
    /// Whether the op was new (false: a duplicate, nothing changed).
    pub applied: bool,
    /// Leaves split to reach the deepest level along the cut (or by a refinement op).
    pub refined: usize,
    /// Leaves separated into copies (all cuts).
    pub crossed: usize,
    /// Virtual nodes (all cuts).
    pub virtual_nodes: usize,
    /// Attachment springs this op released (that were holding).
    pub released: usize,
    /// Diamonds a refinement op merged.
    pub merged: usize,
}

impl Simulation {
    /// Applies a topology operation (a cut, a release of attachment springs, a clip or a
    /// refinement). Cuts, releases and clips are idempotent: one already applied (same
    /// [`crate::cut::OpId`]) changes nothing, and the result depends only on the set of
    /// them applied, not on their order.
    /// A refinement ([`TopologyOp::Refine`]) is applied with [`Simulation::apply_refine`]
    /// and not logged; its `applied` says whether it changed the lattice.
    pub fn apply_topology_op(&mut self, op: TopologyOp) -> Result<TopologyChange, SimError> {
        if let TopologyOp::Refine(r) = &op {
            let change = self.apply_refine(r)?;
            return Ok(TopologyChange {
                applied: change.split + change.merged > 0,
                refined: change.split,
                merged: change.merged,
                ..TopologyChange::default()
            });
        }
        match &op {
            TopologyOp::Cut(c) => c.validate().map_err(SimError::Topology)?,
            TopologyOp::Release(r) => self.attachments.validate(r).map_err(SimError::Topology)?,
            TopologyOp::Clip(c) => c.validate().map_err(SimError::Topology)?,
            TopologyOp::Refine(_) => unreachable!("handled above"),
        }
        // Releases and clips leave the lattice and its separation as they are.
        if !matches!(op, TopologyOp::Cut(_)) {
            if !self.topology.insert(op.clone()) {
                return Ok(TopologyChange::default());
            }
            let released = match &op {
                TopologyOp::Release(r) => self.attachments.release(r),
                _ => {
                    self.clips
                        .rebuild(&self.lattice, self.topology.clip_ends())?;
                    self.clips_follow_cut();
                    0
                }
            };
            self.update_topology_digest();
            let (crossed, virtual_nodes) = self.cut.as_ref().map_or((0, 0), |c| {
                (c.separation.crossed.len(), c.separation.virtual_nodes.len())
            });
            return Ok(TopologyChange {
                applied: true,
                released,
                crossed,
                virtual_nodes,
                ..TopologyChange::default()
            });
        }
        if !self.topology.insert(op) {
            return Ok(TopologyChange::default());
        }
        let sheet = self.topology.sheet();
        if self.cut.is_none() {
            let original = self.surfaces.iter().map(|s| s.rest.clone()).collect();
            self.cut = Some(CutState {
                sheet: sheet.clone(),
                separation: Separation {
                    copies: Vec::new(),
                    capacity: self.lattice.node_capacity(),
                    virtual_nodes: Vec::new(),
                    crossed: Vec::new(),
                },
                original,
                hosts: Vec::new(),
                surface_errors: Vec::new(),
            });
            // Rotation sharing indexes lattice nodes only (the multigrid hierarchy gives the
            // virtual nodes their lattice node's rows: `multigrid::hierarchy_with_copies`).
            self.sharing = crate::sharing::RotationSharing::new(None);
        }
        let cut = self.cut.as_mut().expect("set above");
        cut.sheet = sheet;
        let old = self.detach_virtual();
        let refined = self.refine_along_sheet()?;
        self.cut_surfaces()?;
        self.reseparate(old)?;
        self.update_topology_digest();
        let cut = self.cut.as_ref().expect("set above");
        Ok(TopologyChange {
            applied: true,
            released: 0,
            refined,
            crossed: cut.separation.crossed.len(),
            virtual_nodes: cut.separation.virtual_nodes.len(),
            merged: 0,
        })
    }

    /// Recomputes the topology digest from the ops, the separation and the released
    /// attachment springs.
    fn update_topology_digest(&mut self) {
        let released = self.attachments.released_sets();
        self.topology
            .update_digest(self.cut.as_ref().map(|c| &c.separation), &released);
    }

    /// Takes the virtual nodes' state out of the node arrays (they then have the lattice
    /// layout again); `None` without a cut.
    pub(crate) fn detach_virtual(&mut self) -> Option<(Separation, Vec<V3>, Vec<V3>)> {
        let cut = self.cut.as_ref()?;
        let sep = cut.separation.clone();
        let cap = sep.capacity;
        let xs = if self.x.len() > cap {
            self.x.split_off(cap)
        } else {
            Vec::new()
        };
        let vs = if self.v.len() > cap {
            self.v.split_off(cap)
        } else {
            Vec::new()
        };
        for a in [&mut self.f_extra, &mut self.f_scene] {
            a.truncate(cap);
        }
        self.fixed_scene.truncate(cap);
        Some((sep, xs, vs))
    }

    /// Refines every leaf the sheet may touch to the lattice's deepest level.
    fn refine_along_sheet(&mut self) -> Result<usize, SimError> {
        let Some(cut) = &self.cut else { return Ok(0) };
        let sheet = cut.sheet.clone();
        let mut events = Vec::new();
        let split = self.lattice.refine_where(
            |lat, t| sheet.may_touch_tet(&lat.tet_nodes(t).map(|n| lat.node_rest(n))),
            &mut events,
        );
        self.apply_lattice_events(&events)?;
        Ok(split)
    }

    /// Recomputes every surface's cut from its original mesh.
    fn cut_surfaces(&mut self) -> Result<(), SimError> {
        let Some(cut) = &mut self.cut else {
            return Ok(());
        };
        cut.surface_errors.clear();
        for (s, original) in self.surfaces.iter_mut().zip(&cut.original) {
            match cut_surface(original, &cut.sheet) {
                Ok(c) => {
                    s.embedding = sim_lattice::Embedding::new(&self.lattice, &c.mesh.vertices)?;
                    s.rest = c.mesh;
                    cut.surface_errors.push(None);
                }
                Err(e) => {
                    tracing::warn!(surface = %s.name, error = %e, "surface left uncut");
                    cut.surface_errors.push(Some(e.to_string()));
                }
            }
        }
        Ok(())
    }

    /// Separates the current leaves along the sheet and lays the node arrays out for the
    /// new degrees of freedom. Every degree of freedom takes its state from the one its
    /// first (copy, corner) had before: the old copy of the same leaf whose real corners
    /// include the new copy's (cuts only split components), or the lattice node for a
    /// leaf that did not exist (refinement).
    pub(crate) fn reseparate(
        &mut self,
        old: Option<(Separation, Vec<V3>, Vec<V3>)>,
    ) -> Result<(), SimError> {
        let Some(cut) = &self.cut else { return Ok(()) };
        let sep = separate(&self.lattice, &cut.sheet);
        let cap = sep.capacity;
        let n = sep.dof_count();
        let mut x = self.x.clone();
        let mut v = self.v.clone();
        x.resize(n, V3::zeros());
        v.resize(n, V3::zeros());
        let mut done = vec![false; n];
        for c in &sep.copies {
            for k in 0..4 {
                let d = c.dofs[k];
                if done[d] {
                    continue;
                }
                done[d] = true;
                let node = sep.dof_node(d).0 as usize;
                let mut state = (self.x[node], self.v[node]);
                if let Some((old_sep, xs, vs)) = &old {
                    let prev = old_sep
                        .copies_of(c.leaf)
                        .iter()
                        .find(|o| o.mask & c.mask == c.mask)
                        .map(|o| o.dofs[k]);
                    if let Some(od) = prev {
                        state = if od < old_sep.capacity {
                            (self.x[od], self.v[od])
                        } else {
                            (xs[od - old_sep.capacity], vs[od - old_sep.capacity])
                        };
                    }
                }
                x[d] = state.0;
                v[d] = state.1;
            }
        }
        self.x = x;
        self.v = v;
        self.f_extra.resize(n, V3::zeros());
        self.f_scene.resize(n, V3::zeros());
        let mut fixed = self.fixed_scene.clone();
        fixed.resize(n, false);
        for (k, node) in sep.virtual_nodes.iter().enumerate() {
            fixed[cap + k] = self.fixed_scene[node.0 as usize];
        }
        self.fixed_scene = fixed;
        self.prescribed.retain(|n, _| (n.0 as usize) < cap);
        let cut = self.cut.as_mut().expect("checked above");
        cut.separation = sep;
        self.update_cut_hosts();
        self.fem = None;
        self.update_surfaces();
        Ok(())
    }

    /// Which copy of its host leaf every surface vertex and every attachment spring end
    /// follows (see [`CutState::copy_dofs`]).
    fn update_cut_hosts(&mut self) {
        let Some(cut) = &mut self.cut else { return };
        let lat = &self.lattice;
        cut.hosts = self
            .surfaces
            .iter()
            .map(|s| {
                (0..s.embedding.len())
                    .map(|i| {
                        let (t, w, nodes) = s.embedding.host(i);
                        (cut.copy_dofs(lat, t, nodes, &s.rest.vertices[i]), w)
                    })
                    .collect()
            })
            .collect();
        // A cut through a connective layer splits its springs with it: each end pulls on
        // the copy on its own side, not on the original lattice node.
        let cut = &*cut;
        self.attachments
            .follow_cut(|t, nodes, p| cut.copy_dofs(lat, t, nodes, p));
        self.clips
            .follow_cut(|t, nodes, p| cut.copy_dofs(lat, t, nodes, p));
    }

    /// After a clip is embedded anew: its ends follow the element copies on their side of
    /// any cut.
    fn clips_follow_cut(&mut self) {
        if let Some(cut) = &self.cut {
            let lat = &self.lattice;
            self.clips
                .follow_cut(|t, nodes, p| cut.copy_dofs(lat, t, nodes, p));
        }
    }

    /// The degrees of freedom (node slots) and weights that vertex `v` of surface `s`
    /// follows: its host leaf's lattice nodes, or once a cut exists the nodes of the leaf's
    /// copy on its side (virtual nodes included). What contact pushes and reads.
    pub fn surface_vertex_host(&self, s: usize, v: usize) -> ([usize; 4], [f64; 4]) {
        if let Some(h) = self
            .cut
            .as_ref()
            .and_then(|c| c.hosts.get(s))
            .and_then(|h| h.get(v))
        {
            return *h;
        }
        let (_, w, n) = self.surfaces[s].embedding.host(v);
        (n.map(|n| n.0 as usize), w)
    }

    /// Rest position (m) of degree of freedom `d`: a lattice node's, or once a cut exists
    /// a virtual node's (the rest position of the node it copies).
    pub fn dof_rest_position(&self, d: usize) -> V3 {
        let node = match &self.cut {
            Some(c) => c.separation.dof_node(d),
            None => NodeId(d as u32),
        };
        self.lattice.node_rest(node)
    }

    /// The clips placed on the tissue ([`crate::clip`]).
    pub fn clips(&self) -> &crate::clip::Clips {
        &self.clips
    }

    /// Every clip's two ends where the tissue has carried them (m, world).
    pub fn clip_positions(&self) -> Vec<[V3; 2]> {
        (0..self.clips.len())
            .map(|i| self.clips.ends(&self.x, i))
            .collect()
    }

    /// The elements of the FEM system when a cut exists: (degrees of freedom, leaf,
    /// volume fraction) of every copy.
    pub(crate) fn cut_elements(&self) -> Option<Vec<([usize; 4], TetId, f64)>> {
        let cut = self.cut.as_ref()?;
        Some(
            cut.separation
                .copies
                .iter()
                .map(|c| (c.dofs, c.leaf, c.fraction))
                .collect(),
        )
    }

    /// Rest position of every degree of freedom (lattice slots, then virtual nodes).
    pub(crate) fn dof_rest(&self) -> Vec<V3> {
        let mut rest = vec![V3::zeros(); self.x.len().max(self.lattice.node_capacity())];
        for n in self.lattice.nodes() {
            rest[n.0 as usize] = self.lattice.node_rest(n);
        }
        if let Some(cut) = &self.cut {
            let cap = cut.separation.capacity;
            for (k, n) in cut.separation.virtual_nodes.iter().enumerate() {
                rest[cap + k] = self.lattice.node_rest(*n);
            }
        }
        rest
    }

    /// Whether every degree-of-freedom slot holds a live node.
    pub(crate) fn dof_alive(&self) -> Vec<bool> {
        let cap = self.lattice.node_capacity();
        let mut alive: Vec<bool> = (0..cap)
            .map(|i| self.lattice.node_alive(NodeId(i as u32)))
            .collect();
        alive.resize(self.x.len().max(cap), true);
        alive
    }

    /// Interpolates the cut surfaces (returns false without a cut).
    pub(crate) fn interpolate_cut_surfaces(&mut self) -> bool {
        let Some(cut) = &self.cut else { return false };
        for (s, hosts) in self.surfaces.iter_mut().zip(&cut.hosts) {
            s.deformed.resize(hosts.len(), V3::zeros());
            for (p, (dofs, w)) in s.deformed.iter_mut().zip(hosts) {
                *p = (0..4).map(|k| w[k] * self.x[dofs[k]]).sum();
            }
        }
        true
    }

    /// Re-separates after a lattice topology change (adaptivity) when a cut exists.
    pub(crate) fn after_lattice_change_cut(
        &mut self,
        old: Option<(Separation, Vec<V3>, Vec<V3>)>,
    ) -> Result<(), SimError> {
        if self.cut.is_none() {
            return Ok(());
        }
        self.refine_along_sheet()?;
        self.reseparate(old)
    }

    /// Whether coarsening the diamond around `node` could merge a separated leaf (the
    /// adaptivity keeps such diamonds): the node lies within a root cell of the sheet's
    /// bounding box.
    pub fn cut_pins_node(&self, node: NodeId) -> bool {
        let Some(cut) = &self.cut else { return false };
        self.node_near_sheet(node, &cut.sheet)
    }

    fn node_near_sheet(&self, node: NodeId, sheet: &Sheet) -> bool {
        let p = self.lattice.node_rest(node);
        let h = self.lattice.params().cell;
        sheet.overlaps_box(&p.add_scalar(-h), &p.add_scalar(h))
    }

    /// The applied topology operations, epoch and digest.
    pub fn topology(&self) -> &crate::cut::TopologyLog {
        &self.topology
    }

    /// Sets the state of degree of freedom `dof` (a lattice node slot, or a cut's virtual
    /// node `capacity + k`): position (m) and velocity (m/s). Out of range: nothing.
    pub fn set_dof_state(&mut self, dof: usize, x: V3, v: V3) {
        if dof < self.x.len() {
            self.x[dof] = x;
            self.v[dof] = v;
        }
    }

    /// The separation of the lattice by the cuts (`None` before the first cut).
    pub fn separation(&self) -> Option<&Separation> {
        self.cut.as_ref().map(|c| &c.separation)
    }

    /// Per surface, why it could not be cut (`None`: cut and capped, or no cut).
    pub fn surface_cut_errors(&self) -> Vec<Option<String>> {
        self.cut
            .as_ref()
            .map(|c| c.surface_errors.clone())
            .unwrap_or_else(|| vec![None; self.surfaces.len()])
    }

    /// Total rest volume of the elements (m³): with a cut, each copy counts with its
    /// volume fraction.
    pub fn element_rest_volume(&self) -> f64 {
        match &self.cut {
            Some(c) => c
                .separation
                .copies
                .iter()
                .map(|e| e.fraction * self.lattice.tet_rest_volume(e.leaf))
                .sum(),
            None => self
                .lattice
                .leaves()
                .iter()
                .map(|&t| self.lattice.tet_rest_volume(t))
                .sum(),
        }
    }

    /// Maps a deformed (world) point to rest coordinates through the element that
    /// contains it, or, outside the body, the element it is least outside of (affine
    /// extrapolation). Returns the rest point and whether the point is inside the body.
    /// Not shared state: only the cutting site calls it, and its op carries the result.
    pub fn rest_point_of(&self, q: &V3) -> Option<(V3, bool)> {
        let (worst, dofs, w) = self.best_element(q)?;
        Some((self.rest_of(&dofs, &w), worst >= INSIDE_TOLERANCE))
    }

    /// [`Simulation::rest_point_of`] for a point inside the body (`None` outside): the
    /// same rest point, found by testing only the elements whose bounding box holds the
    /// point. The blade maps its edge every step and the clip applier tests its jaws when
    /// they close; with the full search (a 3×3 inverse per element for a point outside)
    /// the blade's idle edge took 17 % of the default scene's step (`perf`, 2026-11-27).
    pub fn rest_point_inside(&self, q: &V3) -> Option<V3> {
        self.rest_points_inside(std::slice::from_ref(q))[0]
    }

    /// [`Simulation::rest_point_inside`] of several points in one pass over the elements
    /// (each element's box is built once for all of them).
    pub fn rest_points_inside(&self, qs: &[V3]) -> Vec<Option<V3>> {
        let Some((all_lo, all_hi)) = qs
            .iter()
            .map(|q| (*q, *q))
            .reduce(|(lo, hi), (q, _)| (lo.inf(&q), hi.sup(&q)))
        else {
            return Vec::new();
        };
        let margin = V3::repeat(BOX_MARGIN_M);
        // Each degree of freedom's side of the query box, per axis (bit `2k`: its element
        // boxes, widened by the margin, end below the queries; bit `2k + 1`: they start
        // above them). An element whose four codes share a bit cannot hold a query, which
        // spares it the box below: the blade asks every step, and building every
        // element's box was 5 % of a step on the 1.33 cm organ (`perf`, 2026-11-28).
        // `x − m` and `x + m` round monotonically, so the test is exactly the box test's.
        let side: Vec<u8> = self
            .x
            .iter()
            .map(|x| {
                (0..3).fold(0u8, |code, k| {
                    code | (u8::from(all_lo[k] > x[k] + margin[k]) << (2 * k))
                        | (u8::from(all_hi[k] < x[k] - margin[k]) << (2 * k + 1))
                })
            })
            .collect();
        let mut best: Vec<Option<ElementHit>> = vec![None; qs.len()];
        let mut visit = |dofs: [usize; 4]| {
            if dofs.iter().fold(u8::MAX, |all, &d| all & side[d]) != 0 {
                return;
            }
            let p = dofs.map(|d| self.x[d]);
            let lo = p[0].inf(&p[1]).inf(&p[2]).inf(&p[3]) - margin;
            let hi = p[0].sup(&p[1]).sup(&p[2]).sup(&p[3]) + margin;
            if (0..3).any(|k| all_hi[k] < lo[k] || all_lo[k] > hi[k]) {
                return;
            }
            let mut inv = None;
            for (q, b) in qs.iter().zip(best.iter_mut()) {
                if (0..3).any(|k| q[k] < lo[k] || q[k] > hi[k]) {
                    continue;
                }
                let Some(inv) = inv.get_or_insert_with(|| edge_matrix_inverse(&p)) else {
                    return;
                };
                let (worst, w) = barycentric(&p, inv, q);
                if b.as_ref().is_none_or(|b| worst > b.0) {
                    *b = Some((worst, dofs, w));
                }
            }
        };
        self.for_each_element(&mut visit);
        best.into_iter()
            .map(|b| {
                let (worst, dofs, w) = b?;
                (worst >= INSIDE_TOLERANCE).then(|| self.rest_of(&dofs, &w))
            })
            .collect()
    }

    /// The element whose smallest barycentric coordinate of `q` is largest: (that
    /// coordinate, its degrees of freedom, the coordinates).
    fn best_element(&self, q: &V3) -> Option<ElementHit> {
        let mut best: Option<ElementHit> = None;
        let mut visit = |dofs: [usize; 4]| {
            let p = dofs.map(|d| self.x[d]);
            // Box pre-test: a point outside this element's box cannot beat a containing
            // element (worst barycentric < 0 either way).
            if best.as_ref().is_some_and(|b| b.0 >= 0.0) {
                let lo = p[0].inf(&p[1]).inf(&p[2]).inf(&p[3]);
                let hi = p[0].sup(&p[1]).sup(&p[2]).sup(&p[3]);
                if (0..3).any(|k| q[k] < lo[k] || q[k] > hi[k]) {
                    return;
                }
            }
            let Some(inv) = edge_matrix_inverse(&p) else {
                return;
            };
            let (worst, w) = barycentric(&p, &inv, q);
            if best.as_ref().is_none_or(|b| worst > b.0) {
                best = Some((worst, dofs, w));
            }
        };
        self.for_each_element(&mut visit);
        best
    }

    /// Calls `visit` with the degrees of freedom of every element (the cut's copies, or
    /// the lattice's leaves before a cut).
    fn for_each_element(&self, visit: &mut impl FnMut([usize; 4])) {
        match &self.cut {
            Some(c) => c.separation.copies.iter().for_each(|e| visit(e.dofs)),
            None => self
                .lattice
                .leaves()
                .iter()
                .for_each(|&t| visit(self.lattice.tet_nodes(t).map(|n| n.0 as usize))),
        }
    }

    /// The rest point with barycentric coordinates `w` in the element of `dofs`.
    fn rest_of(&self, dofs: &[usize; 4], w: &[f64; 4]) -> V3 {
        (0..4).map(|k| w[k] * self.dof_rest_position(dofs[k])).sum()
    }

    /// Applies lattice events that the cut code itself caused (refinement along a sheet).
    fn apply_lattice_events(&mut self, events: &[TopologyEvent]) -> Result<(), SimError> {
        self.apply_lattice_events_only(events)
    }
}
