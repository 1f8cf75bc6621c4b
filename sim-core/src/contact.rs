//! Tool–tissue contact on the embedded model (DESIGN §1(b)): detection through the tet
//! forest, penalty response with damping and friction, grasping, and the 6-DOF reaction
//! on each tool with a local linear model for multi-rate haptic rendering.
//!
//! **Detection.** The tet forest is a two-level bounding-volume hierarchy refit from the
//! deformed node positions every pass: one box per root tet (over the nodes of all its
//! leaves — node lists cached per topology generation), then the leaves of the roots the
//! query box hits (boxes from their four nodes). Each leaf lists the embedded surface
//! triangles having a vertex hosted in it (rebuilt on topology change), so the candidate
//! triangles of a tool are those listed in the leaves its box hits. The query box is the
//! tool's samples' box inflated by the contact margin plus the longest rest triangle edge
//! (×2 for stretch): every triangle within the margin of a sample has a vertex in that
//! box, and that vertex's host leaf (which contains it) is hit — the search is conservative
//! without walking face neighbours. Exact point–triangle closest points (Ericson) then give
//! each sample's nearest surface point with its triangle barycentrics.
//!
//! **Response.** A sample below the surface by depth `d` (along the triangle's outward
//! normal `n`) pushes the tissue with `f = −(k_c d + c ḋ) n` (no pull), plus a regularised
//! Coulomb friction spring `f_t = −k_t P (a − s)` between a surface anchor `a` and the
//! sample `s` (`P = I − n nᵀ`), capped at `μ k_c d`; when it slips, the anchor moves along
//! the surface so that the spring sits at the cap. Each force is spread onto the lattice
//! nodes with the weights `β_v w_{v,i}` (triangle barycentrics × each vertex's host-tet
//! weights), so that `Σ w_i x_i` is the application point and force and torque balance
//! exactly. Its stiffness goes into the implicit step as row-sum-lumped diagonal blocks
//! `K_i = |w_i| Σ_j |w_j| K` (`K = k_c n nᵀ + k_t P`), which dominate the exact
//! `w wᵀ ⊗ K` and keep stiff contact stable; the tissue-velocity part of the damping is
//! made implicit by adding `c/dt · n nᵀ` to the same blocks (the linearised step's
//! external force is `f_ext − dt K_ext v_{n+1}`).
//!
//! **Grasp.** When a forceps' jaw angle falls below its closing threshold (after having
//! been open), the surface points nearest to its jaw samples within the capture distance
//! attach to the jaws: their rest-frame embedding (host leaf + weights, kept across
//! topology changes) and their offset in the tool frame are stored, and a stiff damped
//! spring (implicit like contact) pulls each to its tool-frame target until the jaws open
//! again. A held forceps does not collide (the tissue sits between its jaws).

use std::collections::HashMap;

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use sim_lattice::{Embedding, NodeId, TetId};

use crate::adapt::{AdaptParams, AdaptReport, Adaptivity};
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::{ToolInput, ToolSet};

type V3 = Vector3<f64>;

/// Contact and grasp constants. [`ContactParams::from_sim`] takes the penalty stiffness
/// from the scene and derives the rest.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactParams {
    /// Penalty stiffness `k_c` per tool sample (N/m).
    pub stiffness: f64,
    /// Normal damping `c` per sample (N·s/m).
    pub damping: f64,
    /// Coulomb friction coefficient μ.
    pub friction: f64,
    /// Tangential (stick) spring `k_t` per sample (N/m).
    pub tangential_stiffness: f64,
    /// Detection margin (m): surface points farther than this from a sample are ignored.
    pub margin: f64,
    /// Grasp spring per attached point (N/m).
    pub grasp_stiffness: f64,
    /// Grasp damping per attached point (N·s/m).
    pub grasp_damping: f64,
    /// A surface point within this distance (m) of a jaw sample is grasped.
    pub grasp_capture: f64,
    /// An attached point farther than this (m) from its target tears loose.
    pub grasp_tear: f64,
}

impl ContactParams {
    /// Defaults for a simulation: `k_c` from the scene's `contact_stiffness`, `c = 0.005 s
    /// · k_c`, μ = 0.3, `k_t = k_c`, margin = twice the largest tool radius (≥ 2 mm),
    /// grasp springs `4 k_c` with `0.005 s` damping, capture distance = the largest tool
    /// radius, tearing at 2 cm.
    pub fn from_sim(sim: &Simulation) -> Self {
        let k = sim.scene().scene.simulation.contact_stiffness;
        let r = sim
            .scene()
            .scene
            .tools
            .iter()
            .map(|t| t.radius)
            .fold(0.001, f64::max);
        ContactParams {
            stiffness: k,
            damping: 0.005 * k,
            friction: 0.3,
            tangential_stiffness: k,
            margin: (2.0 * r).max(0.002),
            grasp_stiffness: 4.0 * k,
            grasp_damping: 0.005 * 4.0 * k,
            grasp_capture: r,
            grasp_tear: 0.02,
        }
    }
}

/// Work counters, cumulative over passes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ContactStats {
    /// Passes that ran detection (contact on, at least one tool).
    pub passes_run: u64,
    /// Passes skipped entirely (no tool, or contact off).
    pub passes_skipped: u64,
    /// Rebuilds of the per-topology caches (root node lists, leaf triangle lists).
    pub cache_rebuilds: u64,
    /// Root-box tests against tool query boxes.
    pub root_tests: u64,
    /// Leaf-box tests (inside roots whose box was hit).
    pub leaf_tests: u64,
    /// Candidate triangles gathered from hit leaves.
    pub candidate_triangles: u64,
    /// Exact point–triangle closest-point tests.
    pub narrow_tests: u64,
    /// Penetrating samples found.
    pub contacts: u64,
}

/// One penetrating tool sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactPoint {
    /// Tool sample index.
    pub sample: usize,
    /// Surface index and triangle.
    pub surface: usize,
    /// Triangle index within the surface.
    pub triangle: usize,
    /// Barycentrics of the closest point on the triangle.
    pub bary: [f64; 3],
    /// Closest surface point (m).
    pub point: V3,
    /// Outward surface normal.
    pub normal: V3,
    /// Penetration depth (m).
    pub depth: f64,
    /// Force on the tissue (normal + friction + damping, N).
    pub force: V3,
    /// Whether the friction spring was sticking.
    pub sticking: bool,
}

/// Linearisation of a tool's reaction about the current pose for the haptic loop:
/// `[F; τ](δ, θ) ≈ [force; torque] + stiffness · [δ; θ]` for a small tool translation δ
/// (m) and rotation vector θ (rad), torque about the tip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalModel {
    /// Force on the tool (N).
    pub force: V3,
    /// Torque on the tool about its tip (N·m).
    pub torque: V3,
    /// `∂[F; τ]/∂[δ; θ]` (symmetric, negative semi-definite; geometric terms of the
    /// moving lever arm neglected). Its top-left block is `−Σ K_s` (e.g. `−Σ k_c n nᵀ`).
    pub stiffness: Matrix6<f64>,
}

impl Default for LocalModel {
    fn default() -> Self {
        LocalModel {
            force: V3::zeros(),
            torque: V3::zeros(),
            stiffness: Matrix6::zeros(),
        }
    }
}

impl LocalModel {
    /// Force and torque predicted for a small displacement δ (m) and rotation θ (rad).
    pub fn predict(&self, delta: &V3, theta: &V3) -> (V3, V3) {
        let d = self.stiffness * Vector6::new(delta.x, delta.y, delta.z, theta.x, theta.y, theta.z);
        (
            self.force + d.fixed_rows::<3>(0),
            self.torque + d.fixed_rows::<3>(3),
        )
    }
}

/// The reaction on one tool.
#[derive(Clone, Debug, Default)]
pub struct ToolContact {
    /// Tool name.
    pub name: String,
    /// Force on the tool (N): minus the sum of the forces applied to the tissue.
    pub force: V3,
    /// Torque on the tool about its tip (N·m).
    pub torque: V3,
    /// Penetrating samples this pass.
    pub contacts: Vec<ContactPoint>,
    /// Grasped surface points (0 when not holding).
    pub grasped: usize,
    /// Current positions of the grasped points (m).
    pub grasped_points: Vec<V3>,
    /// Deepest penetration (m).
    pub max_depth: f64,
    /// Local linear model of the reaction.
    pub local: LocalModel,
}

/// What contact produced in the last pass.
#[derive(Clone, Debug, Default)]
pub struct ContactState {
    /// Force applied to each lattice node (N), by `NodeId.0` (sized by node capacity;
    /// zero where nothing was applied).
    pub node_force: Vec<V3>,
    /// Per tool, in scene order.
    pub tools: Vec<ToolContact>,
    /// Cumulative work counters.
    pub stats: ContactStats,
}

/// Per-topology caches of the hierarchy.
#[derive(Clone, Debug, Default)]
struct Topology {
    generation: Option<u64>,
    /// CSR: nodes of the leaves of each root.
    root_node_start: Vec<u32>,
    root_nodes: Vec<u32>,
    /// CSR: leaf indices (into `Lattice::leaves`) of each root.
    root_leaf_start: Vec<u32>,
    root_leaves: Vec<u32>,
    /// CSR: global triangle ids listed per leaf index.
    leaf_tri_start: Vec<u32>,
    leaf_tris: Vec<u32>,
    /// How far (m) the triangles listed in a leaf may reach beyond it: the longest rest
    /// edge among them times [`STRETCH`].
    leaf_reach: Vec<f64>,
    /// Maximum `leaf_reach` over a root's leaves.
    root_reach: Vec<f64>,
}

/// Largest edge stretch the broad phase allows for: a triangle whose deformed edges grew
/// beyond this factor of their rest length may be missed at its far end.
pub const STRETCH: f64 = 2.0;

/// A friction anchor: a point on a surface triangle.
#[derive(Clone, Copy, Debug)]
struct Anchor {
    tri: u32,
    bary: [f64; 3],
}

/// Tissue held by a forceps.
#[derive(Clone, Debug)]
struct Grasp {
    embedding: Embedding,
    offsets: Vec<V3>,
    alive: Vec<bool>,
}

/// Per-tool contact memory.
#[derive(Clone, Debug, Default)]
struct ToolMemory {
    anchors: Vec<Option<Anchor>>,
    grasp: Option<Grasp>,
    /// The jaws have been open since the last grasp (a grasp starts on closing only).
    armed: bool,
}

/// A candidate triangle of one query.
#[derive(Clone, Copy, Debug)]
struct Cand {
    tri: u32,
    v: [V3; 3],
    lo: V3,
    hi: V3,
    n: V3,
}

/// A sample's nearest surface point.
#[derive(Clone, Copy, Debug)]
struct Hit {
    tri: u32,
    bary: [f64; 3],
    point: V3,
    normal: V3,
    dist: f64,
}

/// Detection + response for all tools of a simulation.
#[derive(Clone, Debug)]
pub struct ContactPipeline {
    /// Constants.
    pub params: ContactParams,
    topo: Topology,
    /// Global triangle id → (surface, triangle).
    tri_owner: Vec<(u32, u32)>,
    /// Longest rest edge of each global triangle (m).
    tri_edge: Vec<f64>,
    /// First global vertex index of each surface.
    vert_base: Vec<u32>,
    /// Deformed vertex cache of the current pass.
    vert_pos: Vec<V3>,
    vert_stamp: Vec<u32>,
    pass: u32,
    tri_stamp: Vec<u32>,
    stamp: u32,
    root_lo: Vec<V3>,
    root_hi: Vec<V3>,
    memory: Vec<ToolMemory>,
    /// Candidate triangles of the last query (friction anchors slide over them).
    last_cands: Vec<Cand>,
    state: ContactState,
    touched: Vec<u32>,
    node_k: Vec<Matrix3<f64>>,
    node_mark: Vec<bool>,
}

impl ContactPipeline {
    /// A pipeline for `sim`'s surfaces and `tools`.
    pub fn new(sim: &Simulation, tools: &ToolSet, params: ContactParams) -> Self {
        let mut tri_owner = Vec::new();
        let mut tri_edge = Vec::new();
        let mut vert_base = Vec::new();
        let mut verts = 0u32;
        for (s, surf) in sim.surfaces().iter().enumerate() {
            vert_base.push(verts);
            verts += surf.rest.vertices.len() as u32;
            for (t, tri) in surf.rest.triangles.iter().enumerate() {
                tri_owner.push((s as u32, t as u32));
                let e = (0..3)
                    .map(|k| {
                        let a = surf.rest.vertices[tri[k] as usize];
                        let b = surf.rest.vertices[tri[(k + 1) % 3] as usize];
                        (a - b).norm()
                    })
                    .fold(0.0, f64::max);
                tri_edge.push(e);
            }
        }
        ContactPipeline {
            params,
            topo: Topology::default(),
            tri_stamp: vec![0; tri_owner.len()],
            tri_owner,
            tri_edge,
            vert_base,
            vert_pos: vec![V3::zeros(); verts as usize],
            vert_stamp: vec![0; verts as usize],
            pass: 0,
            stamp: 0,
            root_lo: Vec::new(),
            root_hi: Vec::new(),
            memory: tools
                .tools
                .iter()
                .map(|t| ToolMemory {
                    anchors: vec![None; t.sample_count()],
                    ..ToolMemory::default()
                })
                .collect(),
            last_cands: Vec::new(),
            state: ContactState {
                tools: tools
                    .tools
                    .iter()
                    .map(|t| ToolContact {
                        name: t.name.clone(),
                        ..ToolContact::default()
                    })
                    .collect(),
                ..ContactState::default()
            },
            touched: Vec::new(),
            node_k: Vec::new(),
            node_mark: Vec::new(),
        }
    }

    /// The last pass's output.
    pub fn state(&self) -> &ContactState {
        &self.state
    }

    /// Whether tool `i` holds tissue.
    pub fn is_grasping(&self, i: usize) -> bool {
        self.memory.get(i).is_some_and(|m| m.grasp.is_some())
    }

    /// Drops every grasp (e.g. after a sync takeover replaced the region).
    pub fn release_all(&mut self) {
        for m in &mut self.memory {
            m.grasp = None;
        }
    }

    /// Points that adaptivity should refine around: contact points and grasped points
    /// of the last pass (m).
    pub fn focus_points(&self) -> Vec<V3> {
        let mut out = Vec::new();
        for t in &self.state.tools {
            out.extend(t.contacts.iter().map(|c| c.point));
            out.extend(t.grasped_points.iter().copied());
        }
        out
    }

    /// Keeps the per-tool memory in step with the tool set (tools added or replaced).
    fn follow_tools(&mut self, tools: &ToolSet) {
        let same = self.memory.len() == tools.len()
            && self
                .memory
                .iter()
                .zip(&tools.tools)
                .all(|(m, t)| m.anchors.len() == t.sample_count())
            && self
                .state
                .tools
                .iter()
                .zip(&tools.tools)
                .all(|(s, t)| s.name == t.name);
        if same {
            return;
        }
        self.memory = tools
            .tools
            .iter()
            .map(|t| ToolMemory {
                anchors: vec![None; t.sample_count()],
                ..ToolMemory::default()
            })
            .collect();
        self.state.tools = tools
            .tools
            .iter()
            .map(|t| ToolContact {
                name: t.name.clone(),
                ..ToolContact::default()
            })
            .collect();
    }

    fn clear_output(&mut self) {
        for &n in &self.touched {
            self.state.node_force[n as usize] = V3::zeros();
            self.node_k[n as usize] = Matrix3::zeros();
            self.node_mark[n as usize] = false;
        }
        self.touched.clear();
        for t in &mut self.state.tools {
            t.force = V3::zeros();
            t.torque = V3::zeros();
            t.contacts.clear();
            t.grasped = 0;
            t.grasped_points.clear();
            t.max_depth = 0.0;
            t.local = LocalModel::default();
        }
    }

    /// One pass before a step: detects contacts of every tool at the current node
    /// positions, computes contact and grasp forces, and adds them with their stiffness to
    /// `sim` for the next step. Does nothing (counted as skipped) without tools or with
    /// contact off.
    pub fn run(&mut self, sim: &mut Simulation, tools: &ToolSet) {
        self.clear_output();
        self.follow_tools(tools);
        if tools.is_empty() || !sim.options().contact {
            self.state.stats.passes_skipped += 1;
            if !tools.is_empty() {
                self.release_all();
            }
            return;
        }
        self.state.stats.passes_run += 1;
        self.pass = self.pass.wrapping_add(1);
        if self.pass == 0 {
            self.vert_stamp.iter_mut().for_each(|s| *s = 0);
            self.pass = 1;
        }
        let cap = sim.lattice().node_capacity();
        if self.state.node_force.len() != cap {
            self.state.node_force.resize(cap, V3::zeros());
            self.node_k.resize(cap, Matrix3::zeros());
            self.node_mark.resize(cap, false);
        }
        self.refresh_topology(sim);
        self.refit_roots(sim);
        let dt = sim.options().dt;
        for ti in 0..tools.tools.len() {
            let tool = &tools.tools[ti];
            // Grasp bookkeeping.
            if tool.jaw() > tool.grasp.open {
                self.memory[ti].armed = true;
            }
            if self.memory[ti].grasp.is_some() && tool.wants_release() {
                self.memory[ti].grasp = None;
            }
            if let Some(grasp) = self.memory[ti].grasp.take() {
                let grasp = self.apply_grasp(sim, tools, ti, grasp, dt);
                self.memory[ti].grasp = grasp;
                continue;
            }
            let hits = self.detect(sim, tools, ti);
            let tool = &tools.tools[ti];
            if tool.wants_grasp()
                && self.memory[ti].armed
                && let Some(grasp) = self.capture(sim, tools, ti, &hits)
            {
                self.memory[ti].armed = false;
                let grasp = self.apply_grasp(sim, tools, ti, grasp, dt);
                self.memory[ti].grasp = grasp;
                continue;
            }
            self.respond(sim, tools, ti, &hits, dt);
        }
        // Hand the forces and stiffness blocks to the simulation.
        for &n in &self.touched {
            let i = n as usize;
            sim.add_force(NodeId(n), self.state.node_force[i]);
            sim.add_stiffness(NodeId(n), self.node_k[i]);
        }
    }

    fn refresh_topology(&mut self, sim: &Simulation) {
        let lat = sim.lattice();
        if self.topo.generation == Some(lat.topology_generation())
            && self.topo.root_node_start.len() == lat.root_count() as usize + 1
        {
            return;
        }
        self.state.stats.cache_rebuilds += 1;
        let roots = lat.root_count() as usize;
        let leaves = lat.leaves();
        // Leaves per root.
        let mut count = vec![0u32; roots + 1];
        for t in leaves {
            count[t.root as usize + 1] += 1;
        }
        for r in 0..roots {
            count[r + 1] += count[r];
        }
        let mut fill = count.clone();
        let mut root_leaves = vec![0u32; leaves.len()];
        for (i, t) in leaves.iter().enumerate() {
            let slot = &mut fill[t.root as usize];
            root_leaves[*slot as usize] = i as u32;
            *slot += 1;
        }
        // Unique nodes per root.
        let mut root_node_start = Vec::with_capacity(roots + 1);
        let mut root_nodes = Vec::new();
        root_node_start.push(0u32);
        let mut buf: Vec<u32> = Vec::new();
        for r in 0..roots {
            buf.clear();
            for &li in &root_leaves[count[r] as usize..count[r + 1] as usize] {
                buf.extend(lat.leaf_tet_nodes(li as usize).iter().map(|n| n.0));
            }
            buf.sort_unstable();
            buf.dedup();
            root_nodes.extend_from_slice(&buf);
            root_node_start.push(root_nodes.len() as u32);
        }
        // Triangles per leaf (by the hosts of their vertices).
        let leaf_index: HashMap<TetId, u32> = leaves
            .iter()
            .enumerate()
            .map(|(i, t)| (*t, i as u32))
            .collect();
        let mut pairs: Vec<(u32, u32)> = Vec::with_capacity(3 * self.tri_owner.len());
        let mut gid = 0u32;
        for surf in sim.surfaces() {
            let host_leaf: Vec<u32> = (0..surf.embedding.len())
                .map(|v| {
                    let (t, _, _) = surf.embedding.host(v);
                    leaf_index.get(&t).copied().unwrap_or(u32::MAX)
                })
                .collect();
            for tri in &surf.rest.triangles {
                let mut ls = tri.map(|v| host_leaf[v as usize]);
                ls.sort_unstable();
                for k in 0..3 {
                    if ls[k] != u32::MAX && (k == 0 || ls[k] != ls[k - 1]) {
                        pairs.push((ls[k], gid));
                    }
                }
                gid += 1;
            }
        }
        pairs.sort_unstable();
        let mut leaf_tri_start = vec![0u32; leaves.len() + 1];
        for &(l, _) in &pairs {
            leaf_tri_start[l as usize + 1] += 1;
        }
        for l in 0..leaves.len() {
            leaf_tri_start[l + 1] += leaf_tri_start[l];
        }
        let mut leaf_reach = vec![0.0f64; leaves.len()];
        for &(l, t) in &pairs {
            leaf_reach[l as usize] =
                leaf_reach[l as usize].max(STRETCH * self.tri_edge[t as usize]);
        }
        let root_reach = (0..roots)
            .map(|r| {
                root_leaves[count[r] as usize..count[r + 1] as usize]
                    .iter()
                    .map(|&l| leaf_reach[l as usize])
                    .fold(0.0, f64::max)
            })
            .collect();
        self.topo = Topology {
            generation: Some(lat.topology_generation()),
            leaf_reach,
            root_reach,
            root_node_start,
            root_nodes,
            root_leaf_start: count,
            root_leaves,
            leaf_tri_start,
            leaf_tris: pairs.into_iter().map(|(_, t)| t).collect(),
        };
    }

    fn refit_roots(&mut self, sim: &Simulation) {
        let x = sim.positions();
        let roots = self.topo.root_node_start.len() - 1;
        self.root_lo.resize(roots, V3::zeros());
        self.root_hi.resize(roots, V3::zeros());
        for r in 0..roots {
            let (a, b) = (
                self.topo.root_node_start[r] as usize,
                self.topo.root_node_start[r + 1] as usize,
            );
            let mut lo = V3::repeat(f64::INFINITY);
            let mut hi = V3::repeat(f64::NEG_INFINITY);
            for &n in &self.topo.root_nodes[a..b] {
                let p = &x[n as usize];
                lo = lo.inf(p);
                hi = hi.sup(p);
            }
            self.root_lo[r] = lo;
            self.root_hi[r] = hi;
        }
    }

    /// Candidate triangles whose vertices may lie within `margin` of the box `lo..hi`.
    fn candidates(&mut self, sim: &Simulation, lo: V3, hi: V3) -> Vec<Cand> {
        // A triangle within the margin of the box has a vertex within its own (deformed)
        // longest edge of the margin box, and that vertex's host leaf contains it.
        let (mlo, mhi) = (
            lo.add_scalar(-self.params.margin),
            hi.add_scalar(self.params.margin),
        );
        let lat = sim.lattice();
        let x = sim.positions();
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.tri_stamp.iter_mut().for_each(|s| *s = 0);
            self.stamp = 1;
        }
        let mut tris: Vec<u32> = Vec::new();
        let stats = &mut self.state.stats;
        for r in 0..self.root_lo.len() {
            stats.root_tests += 1;
            let reach = self.topo.root_reach[r];
            if !overlaps(
                &self.root_lo[r],
                &self.root_hi[r],
                &mlo.add_scalar(-reach),
                &mhi.add_scalar(reach),
            ) {
                continue;
            }
            let (a, b) = (
                self.topo.root_leaf_start[r] as usize,
                self.topo.root_leaf_start[r + 1] as usize,
            );
            for &li in &self.topo.root_leaves[a..b] {
                stats.leaf_tests += 1;
                let nodes = lat.leaf_tet_nodes(li as usize);
                let mut llo = V3::repeat(f64::INFINITY);
                let mut lhi = V3::repeat(f64::NEG_INFINITY);
                for n in nodes {
                    llo = llo.inf(&x[n.0 as usize]);
                    lhi = lhi.sup(&x[n.0 as usize]);
                }
                let reach = self.topo.leaf_reach[li as usize];
                if !overlaps(&llo, &lhi, &mlo.add_scalar(-reach), &mhi.add_scalar(reach)) {
                    continue;
                }
                let (ta, tb) = (
                    self.topo.leaf_tri_start[li as usize] as usize,
                    self.topo.leaf_tri_start[li as usize + 1] as usize,
                );
                for &t in &self.topo.leaf_tris[ta..tb] {
                    if self.tri_stamp[t as usize] != self.stamp {
                        self.tri_stamp[t as usize] = self.stamp;
                        tris.push(t);
                    }
                }
            }
        }
        stats.candidate_triangles += tris.len() as u64;
        let m = self.params.margin;
        let mut out = Vec::with_capacity(tris.len());
        for t in tris {
            let v = self.tri_vertices(sim, t);
            let tlo = v[0].inf(&v[1]).inf(&v[2]).add_scalar(-m);
            let thi = v[0].sup(&v[1]).sup(&v[2]).add_scalar(m);
            if !overlaps(&tlo, &thi, &lo, &hi) {
                continue;
            }
            let n = (v[1] - v[0]).cross(&(v[2] - v[0]));
            let nn = n.norm();
            if nn <= 0.0 || !nn.is_finite() {
                continue;
            }
            out.push(Cand {
                tri: t,
                v,
                lo: tlo,
                hi: thi,
                n: n / nn,
            });
        }
        out
    }

    /// Deformed vertices of global triangle `t`, interpolated from the node positions.
    /// (Cached for the pass: `x` does not change during a pass.)
    fn tri_vertices(&mut self, sim: &Simulation, t: u32) -> [V3; 3] {
        let (s, k) = self.tri_owner[t as usize];
        let surf = &sim.surfaces()[s as usize];
        let tri = surf.rest.triangles[k as usize];
        let x = sim.positions();
        let base = self.vert_base[s as usize];
        tri.map(|v| {
            let g = (base + v) as usize;
            if self.vert_stamp[g] != self.pass {
                let (_, w, n) = surf.embedding.host(v as usize);
                self.vert_pos[g] = x[n[0].0 as usize] * w[0]
                    + x[n[1].0 as usize] * w[1]
                    + x[n[2].0 as usize] * w[2]
                    + x[n[3].0 as usize] * w[3];
                self.vert_stamp[g] = self.pass;
            }
            self.vert_pos[g]
        })
    }

    /// Node weights of a point on global triangle `t` with barycentrics `bary`.
    fn tri_weights(&self, sim: &Simulation, t: u32, bary: &[f64; 3], out: &mut Vec<(u32, f64)>) {
        out.clear();
        let (s, k) = self.tri_owner[t as usize];
        let surf = &sim.surfaces()[s as usize];
        let tri = surf.rest.triangles[k as usize];
        for (v, b) in tri.iter().zip(bary) {
            let (_, w, n) = surf.embedding.host(*v as usize);
            for j in 0..4 {
                out.push((n[j].0, b * w[j]));
            }
        }
    }

    /// Nearest surface point within the margin of every sample of tool `ti`.
    fn detect(&mut self, sim: &Simulation, tools: &ToolSet, ti: usize) -> Vec<Option<Hit>> {
        let tool = &tools.tools[ti];
        let samples = tool.world_samples();
        let mut hits = vec![None; samples.len()];
        let (lo, hi) = tool.aabb(0.0);
        let cands = self.candidates(sim, lo, hi);
        if cands.is_empty() {
            return hits;
        }
        let m = self.params.margin;
        let mut tests = 0u64;
        for (s, hit) in samples.iter().zip(hits.iter_mut()) {
            let mut best: Option<Hit> = None;
            for c in &cands {
                if !contains(&c.lo, &c.hi, s) {
                    continue;
                }
                tests += 1;
                let (p, bary) = closest_point_triangle(s, &c.v[0], &c.v[1], &c.v[2]);
                let dist = (s - p).norm();
                if dist > m {
                    continue;
                }
                let better = match &best {
                    None => true,
                    Some(b) => {
                        if dist < b.dist - 1e-12 * m {
                            true
                        } else if dist <= b.dist + 1e-12 * m {
                            // Shared edge or vertex: prefer the face that sees the sample
                            // most squarely (decides inside/outside correctly at edges).
                            let d = s - p;
                            d.dot(&c.n).abs() > (s - b.point).dot(&b.normal).abs()
                        } else {
                            false
                        }
                    }
                };
                if better {
                    best = Some(Hit {
                        tri: c.tri,
                        bary,
                        point: p,
                        normal: c.n,
                        dist,
                    });
                }
            }
            *hit = best;
        }
        self.state.stats.narrow_tests += tests;
        // Friction anchors need the candidates again only on slip; keep them.
        self.last_cands = cands;
        hits
    }
}

impl ContactPipeline {
    /// Adds force `f` (N) applied at `point` with node `weights` (and, if given, the
    /// spring matrix `k` of its stiffness, lumped by rows) to the output, and its reaction
    /// to tool `ti`.
    #[allow(clippy::too_many_arguments)]
    fn apply(
        &mut self,
        ti: usize,
        tip: &V3,
        weights: &[(u32, f64)],
        point: &V3,
        f: &V3,
        k: Option<&Matrix3<f64>>,
    ) {
        let sum_abs: f64 = weights.iter().map(|(_, w)| w.abs()).sum();
        for &(n, w) in weights {
            let i = n as usize;
            if i >= self.state.node_force.len() {
                continue;
            }
            if !self.node_mark[i] {
                self.node_mark[i] = true;
                self.touched.push(n);
            }
            self.state.node_force[i] += f * w;
            if let Some(k) = k {
                self.node_k[i] += k * (w.abs() * sum_abs);
            }
        }
        let t = &mut self.state.tools[ti];
        t.force -= f;
        t.torque -= (point - tip).cross(f);
    }

    /// Adds a spring of tool-side stiffness `k` at lever arm `r` to tool `ti`'s model.
    fn add_local(&mut self, ti: usize, r: &V3, k: &Matrix3<f64>) {
        let rx = r.cross_matrix();
        let s = &mut self.state.tools[ti].local.stiffness;
        let kr = k * rx;
        let rk = rx * k;
        let rkr = rx * k * rx;
        for i in 0..3 {
            for j in 0..3 {
                s[(i, j)] -= k[(i, j)];
                s[(i, 3 + j)] += kr[(i, j)];
                s[(3 + i, j)] -= rk[(i, j)];
                s[(3 + i, 3 + j)] += rkr[(i, j)];
            }
        }
    }

    /// Point on global triangle `t` at `bary` (m).
    fn tri_point(&mut self, sim: &Simulation, t: u32, bary: &[f64; 3]) -> V3 {
        let v = self.tri_vertices(sim, t);
        v[0] * bary[0] + v[1] * bary[1] + v[2] * bary[2]
    }

    /// Nearest point to `q` on the last query's candidate triangles.
    fn project(&self, q: &V3) -> Option<(u32, [f64; 3])> {
        let mut best: Option<(u32, [f64; 3], f64)> = None;
        for c in &self.last_cands {
            let (p, bary) = closest_point_triangle(q, &c.v[0], &c.v[1], &c.v[2]);
            let d = (p - q).norm_squared();
            if best.as_ref().is_none_or(|b| d < b.2) {
                best = Some((c.tri, bary, d));
            }
        }
        best.map(|(t, b, _)| (t, b))
    }

    /// Penalty, damping and friction forces of tool `ti`'s penetrating samples.
    fn respond(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        hits: &[Option<Hit>],
        dt: f64,
    ) {
        let tool = &tools.tools[ti];
        let tip = tool.tip();
        let p = self.params;
        let v = sim.velocities();
        let mut w: Vec<(u32, f64)> = Vec::with_capacity(12);
        let mut wa: Vec<(u32, f64)> = Vec::with_capacity(12);
        for (si, hit) in hits.iter().enumerate() {
            let s = tool.world_samples()[si];
            let Some(h) = hit.filter(|h| (h.point - s).dot(&h.normal) > 0.0) else {
                self.memory[ti].anchors[si] = None;
                continue;
            };
            let n = h.normal;
            let depth = (h.point - s).dot(&n);
            self.tri_weights(sim, h.tri, &h.bary, &mut w);
            let vp: V3 = w.iter().map(|&(i, wi)| v[i as usize] * wi).sum();
            let vt = tool.point_velocity(&s);
            let fn_spring = p.stiffness * depth;
            let nn = n * n.transpose();
            // Damping −c (v_p − v_t)·n: the tissue part is implicit (c/dt in the stiffness
            // block), the tool part explicit; off when the total would pull.
            let damped = fn_spring + p.damping * (vp - vt).dot(&n) > 0.0 && p.damping > 0.0;
            let mut f = -n * fn_spring;
            let mut kn = nn * p.stiffness;
            if damped {
                f += n * (p.damping * vt.dot(&n));
                kn += nn * (p.damping / dt);
            }
            self.apply(ti, &tip, &w, &h.point, &f, Some(&kn));
            let mut total = f;
            let mut k_tool = nn * p.stiffness;
            // Friction: spring from the surface anchor to the sample, capped at μ k_c d.
            let mut sticking = false;
            if p.friction > 0.0 && p.tangential_stiffness > 0.0 {
                let cap = p.friction * fn_spring;
                let proj = Matrix3::identity() - nn;
                let mut anchor = self.memory[ti].anchors[si].unwrap_or(Anchor {
                    tri: h.tri,
                    bary: h.bary,
                });
                let mut a = self.tri_point(sim, anchor.tri, &anchor.bary);
                let mut ft = -(proj * (a - s)) * p.tangential_stiffness;
                sticking = ft.norm() <= cap;
                if !sticking {
                    // Slide the anchor so that the spring sits at the cap.
                    let ratio = cap / ft.norm();
                    let q = s + proj * (a - s) * ratio;
                    if let Some((tri, bary)) = self.project(&q) {
                        anchor = Anchor { tri, bary };
                        a = self.tri_point(sim, tri, &bary);
                        ft = -(proj * (a - s)) * p.tangential_stiffness;
                    }
                    let norm = ft.norm();
                    if norm > cap && norm > 0.0 {
                        ft *= cap / norm;
                    }
                }
                self.memory[ti].anchors[si] = Some(anchor);
                self.tri_weights(sim, anchor.tri, &anchor.bary, &mut wa);
                let kt = proj * p.tangential_stiffness;
                self.apply(ti, &tip, &wa, &a, &ft, sticking.then_some(&kt));
                if sticking {
                    k_tool += kt;
                }
                total += ft;
            }
            self.add_local(ti, &(s - tip), &k_tool);
            let t = &mut self.state.tools[ti];
            t.max_depth = t.max_depth.max(depth);
            t.contacts.push(ContactPoint {
                sample: si,
                surface: self.tri_owner[h.tri as usize].0 as usize,
                triangle: self.tri_owner[h.tri as usize].1 as usize,
                bary: h.bary,
                point: h.point,
                normal: n,
                depth,
                force: total,
                sticking,
            });
        }
        self.state.stats.contacts += self.state.tools[ti].contacts.len() as u64;
    }

    /// Attaches the surface points nearest to the jaw samples (within the capture
    /// distance, or under the surface) to the jaws.
    fn capture(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        hits: &[Option<Hit>],
    ) -> Option<Grasp> {
        let tool = &tools.tools[ti];
        let min_sep = 0.25 * tool.radius;
        let mut rest: Vec<V3> = Vec::new();
        let mut cur: Vec<V3> = Vec::new();
        for (si, h) in hits.iter().enumerate() {
            let Some(h) = h else { continue };
            let s = tool.world_samples()[si];
            let inside = (h.point - s).dot(&h.normal) > 0.0;
            if !(inside || h.dist <= self.params.grasp_capture) {
                continue;
            }
            if cur.iter().any(|c| (c - h.point).norm() < min_sep) {
                continue;
            }
            let (sidx, k) = self.tri_owner[h.tri as usize];
            let surf = &sim.surfaces()[sidx as usize];
            let tri = surf.rest.triangles[k as usize];
            rest.push(
                (0..3)
                    .map(|j| surf.rest.vertices[tri[j] as usize] * h.bary[j])
                    .sum(),
            );
            cur.push(h.point);
        }
        if rest.is_empty() {
            return None;
        }
        let embedding = match Embedding::new(sim.lattice(), &rest) {
            Ok(e) => e,
            Err(e) => {
                tracing::warn!(error = %e, tool = %tool.name, "grasp: cannot embed points");
                return None;
            }
        };
        let mut pos = vec![V3::zeros(); rest.len()];
        embedding.interpolate(sim.lattice(), sim.positions(), &mut pos);
        let inv = tool.pose().rotation.inverse();
        let offsets = pos.iter().map(|p| inv * (p - tool.tip())).collect();
        tracing::debug!(tool = %tool.name, points = rest.len(), "grasp");
        Some(Grasp {
            embedding,
            offsets,
            alive: vec![true; rest.len()],
        })
    }

    /// Grasp springs of tool `ti`; `None` when every point tore loose.
    fn apply_grasp(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        mut grasp: Grasp,
        dt: f64,
    ) -> Option<Grasp> {
        let tool = &tools.tools[ti];
        let tip = tool.tip();
        let p = self.params;
        grasp.embedding.update(sim.lattice());
        let count = grasp.embedding.len();
        let mut pos = vec![V3::zeros(); count];
        grasp
            .embedding
            .interpolate(sim.lattice(), sim.positions(), &mut pos);
        let k = Matrix3::identity() * (p.grasp_stiffness + p.grasp_damping / dt);
        let k_tool = Matrix3::identity() * p.grasp_stiffness;
        let mut w: Vec<(u32, f64)> = Vec::with_capacity(4);
        for (j, pj) in pos.iter().enumerate() {
            if !grasp.alive[j] {
                continue;
            }
            let target = tip + tool.pose().rotation * grasp.offsets[j];
            if (target - pj).norm() > p.grasp_tear {
                grasp.alive[j] = false;
                continue;
            }
            let vt = tool.point_velocity(&target);
            let f = (target - pj) * p.grasp_stiffness + vt * p.grasp_damping;
            let (_, wts, nodes) = grasp.embedding.host(j);
            w.clear();
            w.extend((0..4).map(|i| (nodes[i].0, wts[i])));
            self.apply(ti, &tip, &w, pj, &f, Some(&k));
            self.add_local(ti, &(target - tip), &k_tool);
            let t = &mut self.state.tools[ti];
            t.grasped += 1;
            t.grasped_points.push(*pj);
        }
        (self.state.tools[ti].grasped > 0).then_some(grasp)
    }
}

#[inline]
fn overlaps(alo: &V3, ahi: &V3, blo: &V3, bhi: &V3) -> bool {
    (0..3).all(|k| alo[k] <= bhi[k] && blo[k] <= ahi[k])
}

#[inline]
fn contains(lo: &V3, hi: &V3, p: &V3) -> bool {
    (0..3).all(|k| lo[k] <= p[k] && p[k] <= hi[k])
}

/// Closest point to `p` on triangle `abc` and its barycentrics (Ericson, Real-Time
/// Collision Detection §5.1.5).
pub fn closest_point_triangle(p: &V3, a: &V3, b: &V3, c: &V3) -> (V3, [f64; 3]) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (*a, [1.0, 0.0, 0.0]);
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (*b, [0.0, 1.0, 0.0]);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, [1.0 - v, v, 0.0]);
    }
    let cp = p - c;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (*c, [0.0, 0.0, 1.0]);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, [1.0 - w, 0.0, w]);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, [0.0, 1.0 - w, w]);
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, [1.0 - v - w, v, w])
}

/// What [`Interaction::before_step`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct InteractionReport {
    /// Whether the contact pass ran (false: no tool or contact off).
    pub contact_ran: bool,
    /// Penetrating samples over all tools.
    pub contacts: usize,
    /// Grasped points over all tools.
    pub grasped: usize,
    /// Exact point–triangle tests of this pass.
    pub narrow_tests: u64,
    /// Adaptivity.
    pub adapt: AdaptReport,
}

/// Tools, contact and tool-following adaptivity of one simulation.
#[derive(Clone, Debug)]
pub struct Interaction {
    /// The tools (poses set by [`Interaction::before_step`]).
    pub tools: ToolSet,
    /// Detection and response.
    pub contact: ContactPipeline,
    /// Refinement following the tools.
    pub adapt: Adaptivity,
}

impl Interaction {
    /// Tools from the scene, default contact and adaptivity parameters.
    pub fn new(sim: &Simulation) -> Self {
        Self::with_params(
            sim,
            ContactParams::from_sim(sim),
            AdaptParams::from_sim(sim),
        )
    }

    /// With explicit parameters.
    pub fn with_params(sim: &Simulation, contact: ContactParams, adapt: AdaptParams) -> Self {
        let tools = ToolSet::from_specs(&sim.scene().scene.tools);
        Interaction {
            contact: ContactPipeline::new(sim, &tools, contact),
            adapt: Adaptivity::new(sim, adapt),
            tools,
        }
    }

    /// Before each [`Simulation::step`]: sets the tool inputs (one per tool in scene
    /// order; tools without an input keep their pose and stop), adapts the topology around
    /// the last pass's contacts, then detects contacts and adds contact and grasp forces
    /// with their stiffness to `sim` for the coming step.
    pub fn before_step(
        &mut self,
        sim: &mut Simulation,
        inputs: &[ToolInput],
    ) -> Result<InteractionReport, SimError> {
        let dt = sim.options().dt;
        for (i, tool) in self.tools.tools.iter_mut().enumerate() {
            let input = inputs.get(i).copied().unwrap_or(ToolInput {
                pose: *tool.pose(),
                jaw: tool.jaw(),
            });
            tool.set_input(&input, dt);
        }
        let focus = self.contact.focus_points();
        let adapt = self.adapt.update(sim, &focus)?;
        let before = self.contact.state().stats;
        self.contact.run(sim, &self.tools);
        let st = self.contact.state();
        Ok(InteractionReport {
            contact_ran: st.stats.passes_run > before.passes_run,
            contacts: st.tools.iter().map(|t| t.contacts.len()).sum(),
            grasped: st.tools.iter().map(|t| t.grasped).sum(),
            narrow_tests: st.stats.narrow_tests - before.narrow_tests,
            adapt,
        })
    }

    /// Inputs from the scene's tool scripts at simulated time `t` (s); tools without a
    /// script keep their current pose.
    pub fn scripted_inputs(&self, sim: &Simulation, t: f64) -> Vec<ToolInput> {
        self.tools
            .tools
            .iter()
            .map(|tool| {
                sim.scene()
                    .scripts
                    .get(&tool.name)
                    .and_then(|s| s.sample(&tool.name, t))
                    .map(|p| ToolInput::from(&p))
                    .unwrap_or(ToolInput {
                        pose: *tool.pose(),
                        jaw: tool.jaw(),
                    })
            })
            .collect()
    }

    /// The last contact pass's output.
    pub fn state(&self) -> &ContactState {
        self.contact.state()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_point_regions() {
        let (a, b, c) = (V3::zeros(), V3::x(), V3::y());
        let (p, w) = closest_point_triangle(&V3::new(0.2, 0.2, 1.0), &a, &b, &c);
        assert!((p - V3::new(0.2, 0.2, 0.0)).norm() < 1e-15);
        assert!((w[0] - 0.6).abs() < 1e-15);
        let (p, w) = closest_point_triangle(&V3::new(2.0, -1.0, 0.5), &a, &b, &c);
        assert_eq!(p, b);
        assert_eq!(w, [0.0, 1.0, 0.0]);
        let (p, w) = closest_point_triangle(&V3::new(1.0, 1.0, 0.0), &a, &b, &c);
        assert!((p - V3::new(0.5, 0.5, 0.0)).norm() < 1e-15);
        assert!((w[1] - 0.5).abs() < 1e-15 && (w[2] - 0.5).abs() < 1e-15);
    }

    #[test]
    fn local_model_is_symmetric() {
        let k = Matrix3::new(2.0, 0.5, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 3.0);
        let r = V3::new(0.01, -0.02, 0.03);
        let rx = r.cross_matrix();
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-k));
        m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(k * rx));
        m.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-(rx * k)));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&(rx * k * rx));
        assert!((m - m.transpose()).norm() < 1e-15);
        // Finite check: F = −K (δ + θ × r), τ = r × F.
        let th = V3::new(1e-3, -2e-3, 5e-4);
        let d = V3::new(1e-4, 0.0, -2e-4);
        let f = -(k * (d + th.cross(&r)));
        let tau = r.cross(&f);
        let pred = m * Vector6::new(d.x, d.y, d.z, th.x, th.y, th.z);
        assert!((pred.fixed_rows::<3>(0) - f).norm() < 1e-15);
        assert!((pred.fixed_rows::<3>(3) - tau).norm() < 1e-15);
    }
}
