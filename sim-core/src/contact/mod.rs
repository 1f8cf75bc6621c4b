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
//! the surface so that the spring sits at the cap. On tissue collapsing towards inversion
//! `k_c`, `c` and `k_t` are scaled by a weight `ω` that falls from 1 to 0 with the host
//! leaves' volume ratio ([`ContactParams::fade_volume_ratio`]); a sample nearest to a
//! triangle with a vertex in an inverted leaf (inside out: its normal points into the
//! tissue) touches nothing. Each force is spread onto the lattice nodes with the weights
//! `β_v w_{v,i}` (triangle barycentrics × each vertex's host-tet weights), so that
//! `Σ w_i x_i` is the application point and force and torque balance exactly. Its stiffness goes into the implicit step as row-sum-lumped diagonal blocks
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
//!
//! One file per concern: detection (`detection.rs`: the hierarchy, candidate triangles,
//! nearest surface points), response (`response.rs`: penalty, friction, grasp, the tool's
//! reaction and local model), and here the pipeline's state and its pass
//! ([`ContactPipeline::run`]). The [`Interaction`] facade (tools + contact + adaptivity)
//! has a file of its own (`interaction.rs`).

mod detection;
mod response;
#[cfg(test)]
mod tests;

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use sim_lattice::{Embedding, NodeId};

use crate::adapt::FocusPoints;
use crate::engine::Simulation;
use crate::tools::ToolSet;

pub use crate::interaction::{Interaction, InteractionReport};
pub use detection::closest_point_triangle;

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
    /// Volume ratio `J = det F` of a host leaf below which contact on the surface
    /// triangles it hosts weakens in proportion, to none at `J ≤ 0` (dimensionless).
    /// An inverted leaf turns its triangles inside out; this keeps contact from
    /// switching off in one step as a leaf collapses. 0: full contact until `J ≤ 0`.
    pub fade_volume_ratio: f64,
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
    /// contact fading below a quarter of a leaf's rest volume (tissue a tool presses
    /// keeps `J` near 1 at ν ≈ 0.45; only a leaf collapsing towards inversion passes it),
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
            fade_volume_ratio: 0.25,
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
    /// Samples whose nearest surface point (within the margin, penetrating or not) lies on
    /// a triangle with a vertex in an inverted leaf: they are given no surface point.
    pub samples_on_inverted: u64,
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
    /// The same point on the surface's rest pose (m).
    pub rest: V3,
    /// Outward surface normal.
    pub normal: V3,
    /// Contact weight `ω` in (0, 1] that scaled this sample's stiffness, damping and
    /// friction ([`ContactParams::fade_volume_ratio`]).
    pub weight: f64,
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
    /// moving lever arm neglected). Its top-left block is `−Σ K_s` (e.g. `−Σ ω k_c n nᵀ`).
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
    /// Rest positions of the grasped points (m), in the order of `grasped_points`.
    pub grasped_rest: Vec<V3>,
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
    /// Contact weight in [0, 1] at the point (`ContactPipeline::contact_weight`).
    weight: f64,
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
    /// Contact weight of each vertex at the pass's positions (when `weight_stamp` is the
    /// pass): 1, less as its host leaf collapses towards inversion, 0 once inverted
    /// ([`ContactParams::fade_volume_ratio`]).
    vert_weight: Vec<f64>,
    weight_stamp: Vec<u32>,
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
    /// Per tool: whether its grasp may tear loose here (a grasped point farther than
    /// [`ContactParams::grasp_tear`] from its jaw lets go). All true by default. A site
    /// that simulates another site's tool from that site's input turns it off for that
    /// tool: whether a grasp tore is the driving site's decision (its tissue, its
    /// pull), and a follower whose copy of the tissue a keyframe has just corrected
    /// would otherwise tear a grasp the driver still holds and drop the organ.
    pub grasp_tears: Vec<bool>,
}

impl ContactPipeline {
    /// A pipeline for `sim`'s surfaces and `tools`.
    pub fn new(sim: &Simulation, tools: &ToolSet, params: ContactParams) -> Self {
        let (tri_owner, tri_edge, vert_base, verts) = surface_tables(sim);
        ContactPipeline {
            params,
            topo: Topology::default(),
            tri_stamp: vec![0; tri_owner.len()],
            tri_owner,
            tri_edge,
            vert_base,
            vert_pos: vec![V3::zeros(); verts as usize],
            vert_weight: vec![1.0; verts as usize],
            weight_stamp: vec![0; verts as usize],
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
            grasp_tears: vec![true; tools.tools.len()],
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

    /// Contact points and grasped points of the last pass, one list per tool in scene
    /// order, where they are now and in rest coordinates (m): a contact's closest point on
    /// its triangle's rest pose (taken when the contact was found, so a cut since does not
    /// move it), a grasped point's rest position. What tool-following adaptivity decides on ([`crate::adapt`]).
    pub fn focus_points_by_tool(&self) -> FocusPoints {
        let mut focus = FocusPoints::default();
        for t in &self.state.tools {
            let rest = t.contacts.iter().map(|c| c.rest);
            focus
                .rest
                .push(rest.chain(t.grasped_rest.iter().copied()).collect());
            let now = t.contacts.iter().map(|c| c.point);
            focus
                .deformed
                .push(now.chain(t.grasped_points.iter().copied()).collect());
        }
        focus
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
            t.grasped_rest.clear();
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
            self.weight_stamp.iter_mut().for_each(|s| *s = 0);
            self.pass = 1;
        }
        // Node slots: the lattice's, then (after a cut) the virtual nodes'.
        let cap = sim.positions().len();
        if self.state.node_force.len() != cap {
            self.state.node_force.resize(cap, V3::zeros());
            self.node_k.resize(cap, Matrix3::zeros());
            self.node_mark.resize(cap, false);
        }
        // A cut re-meshes the surfaces (cut and capped): index them again.
        let (tris, verts) = sim.surfaces().iter().fold((0, 0), |(t, v), s| {
            (t + s.rest.triangles.len(), v + s.rest.vertices.len())
        });
        if tris != self.tri_owner.len() || verts != self.vert_pos.len() {
            let (tri_owner, tri_edge, vert_base, verts) = surface_tables(sim);
            self.tri_stamp = vec![0; tri_owner.len()];
            self.tri_owner = tri_owner;
            self.tri_edge = tri_edge;
            self.vert_base = vert_base;
            self.vert_pos = vec![V3::zeros(); verts as usize];
            self.vert_weight = vec![1.0; verts as usize];
            self.weight_stamp = vec![0; verts as usize];
            self.vert_stamp = vec![0; verts as usize];
            self.topo = Topology::default();
            self.last_cands.clear();
            for m in &mut self.memory {
                m.anchors.iter_mut().for_each(|a| *a = None);
            }
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
                tracing::debug!(tool = %tool.name, t = sim.time(), jaw = tool.jaw(), "grasp released");
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
}

/// [`surface_tables`]: owner (surface, triangle) and longest rest edge (m) of every global
/// triangle, first global vertex of each surface, and the vertex count.
type SurfaceTables = (Vec<(u32, u32)>, Vec<f64>, Vec<u32>, u32);

/// Global triangle ids of every surface's rest mesh ([`SurfaceTables`]).
fn surface_tables(sim: &Simulation) -> SurfaceTables {
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
    (tri_owner, tri_edge, vert_base, verts)
}
