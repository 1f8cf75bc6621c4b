//! What the window draws ([`ViewFrame`]), how the simulation publishes it ([`ViewSlot`])
//! and what the window sends back ([`ViewerCommand`]).
//!
//! The simulation thread builds a `ViewFrame` and swaps it into the slot (one pointer
//! swap under a mutex held for nanoseconds); the render thread clones the `Arc` of the
//! latest frame and draws it at its own pace. Neither ever waits for the other's work.
//!
//! Units: SI (m, s, N), world frame of the scene (+z up).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use nalgebra::{Isometry3, Point3, Vector3};
use sim_core::sim_scene::{BodyShape, InclusionShape, LoadedScene, ToolKind};
use sim_core::{Interaction, Simulation};
use sim_lattice::Embedding;

type V3 = Vector3<f64>;

/// How a surface vertex or a vessel is coloured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TissueKind {
    /// Liver parenchyma (the body's own material).
    Parenchyma,
    /// Gallbladder (an inclusion whose name or material mentions it).
    Gallbladder,
    /// Vessels and ducts (capsule inclusions, or names mentioning vessel, duct, artery).
    Vessel,
}

/// The organ surface's connectivity and per-vertex tissue: fixed for a scene, shared by
/// every frame (only vertex positions change).
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceTopology {
    /// Triangles (indices into the frame's vertex positions), outward-oriented.
    pub triangles: Vec<[u32; 3]>,
    /// Tissue of every vertex.
    pub vertex_tissue: Vec<TissueKind>,
}

/// A straight segment drawn as a tube: lattice edges, tool parts, guide path, vessels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Start (m).
    pub a: V3,
    /// End (m).
    pub b: V3,
}

/// A lattice edge with the refinement level of the finest leaf it bounds (0 = root).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LatticeEdge {
    /// The edge.
    pub segment: Segment,
    /// Refinement level (bisection depth below the root tets).
    pub level: u8,
}

/// A tool as drawn.
#[derive(Clone, Debug, PartialEq)]
pub struct ToolView {
    /// Tool name from the scene.
    pub name: String,
    /// Tool kind.
    pub kind: ToolKind,
    /// Tool frame → world (tip at the origin, shaft along local +z).
    pub pose: Isometry3<f64>,
    /// Jaw opening angle (rad, 0 = closed).
    pub jaw: f64,
    /// Tip radius (m).
    pub radius: f64,
    /// Jaw or rod segments in world coordinates (m).
    pub parts: Vec<Segment>,
    /// The shaft from the hinge back towards the port (m).
    pub shaft: Segment,
    /// Force on the tool (N), what a haptic device would render.
    pub force: V3,
    /// Whether the tool holds tissue.
    pub grasping: bool,
    /// For remote tools: the site that moves it; `None` for the local site's tools.
    pub site: Option<String>,
}

/// An arrow (force) to draw: from `origin` (m) along `force` (N).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ForceArrow {
    /// Where the force acts (m).
    pub origin: V3,
    /// The force (N).
    pub force: V3,
}

/// Who owns one region of the organ (sync).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RegionOwner {
    /// Region label.
    pub region: String,
    /// Owning site.
    pub site: String,
}

/// Session role of the site the window belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Role {
    /// Runs the session: may reset it and start or stop teaching replay.
    #[default]
    Instructor,
    /// Practises.
    Trainee,
    /// Watches.
    Observer,
}

impl Role {
    /// Lower-case name as on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Instructor => "instructor",
            Role::Trainee => "trainee",
            Role::Observer => "observer",
        }
    }
}

/// The numbers of the heads-up display. Fields that a mode does not have are `None`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct HudInfo {
    /// Site name.
    pub site: String,
    /// Session role.
    pub role: Role,
    /// Simulated time (s).
    pub sim_time: f64,
    /// How far this site's view lags the owners' simulated time (s).
    pub lag: Option<f64>,
    /// 99th percentile of the recent step wall times (ms).
    pub step_p99_ms: Option<f64>,
    /// Keyframes sent and received per second.
    pub keyframes_per_s: Option<f64>,
    /// Application bytes sent and received per second.
    pub bytes_per_s: Option<f64>,
    /// Divergence from the owners' state (m, largest node distance).
    pub divergence: Option<f64>,
    /// Region owners.
    pub region_owners: Vec<RegionOwner>,
    /// Whether teaching replay is on.
    pub teaching: bool,
    /// Name of the tool the user's hands drive, if any.
    pub active_tool: Option<String>,
    /// A short message for the user (e.g. a command the coordinator refused).
    pub notice: Option<String>,
}

/// Where the laparoscope sits and looks (from the scene, or a default).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPort {
    /// Port (camera position) (m).
    pub position: V3,
    /// Point looked at (m).
    pub target: V3,
    /// Vertical field of view (degrees).
    pub fov_deg: f64,
}

/// One published picture of a site.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewFrame {
    /// Surface connectivity and tissues (shared between frames).
    pub topology: Arc<SurfaceTopology>,
    /// Deformed surface vertex positions (m), one per topology vertex.
    pub positions: Vec<V3>,
    /// Deformed vessel centre segments with their radius (m).
    pub vessels: Vec<(Segment, f64)>,
    /// Clips on the tissue, where the tissue has carried them (m).
    pub clips: Vec<Segment>,
    /// Lattice wireframe (only when asked for: building it costs the simulation thread).
    pub lattice: Option<Vec<LatticeEdge>>,
    /// Local and remote tools.
    pub tools: Vec<ToolView>,
    /// Teaching guide path (m).
    pub guide: Vec<V3>,
    /// Contact and grasp forces.
    pub forces: Vec<ForceArrow>,
    /// Heads-up display fields.
    pub hud: HudInfo,
    /// The laparoscope's port.
    pub port: CameraPort,
}

impl ViewFrame {
    /// Axis-aligned bounds of the surface `(min, max)` (m); `None` without vertices.
    pub fn surface_bounds(&self) -> Option<(V3, V3)> {
        let first = self.positions.first()?;
        Some(
            self.positions
                .iter()
                .fold((*first, *first), |(lo, hi), p| (lo.inf(p), hi.sup(p))),
        )
    }
}

/// Commands from the user's hands to the local tool.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ToolCommand {
    /// Move the active tool's tip to this position (m) — the view-plane drag and wheel
    /// depth both end up as a target position.
    MoveTo(V3),
    /// Close (`true`) or open (`false`) the jaws.
    Jaw(bool),
    /// Make the next tool the active one.
    NextTool,
}

/// The instructor's session controls.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SessionCommand {
    /// Reset the scene to its initial state.
    Reset,
    /// Start teaching replay.
    TeachingStart,
    /// Stop teaching replay.
    TeachingStop,
}

/// Everything the window sends back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ViewerCommand {
    /// Drive the local tool.
    Tool(ToolCommand),
    /// Session control (only ever emitted for the instructor role).
    Session(SessionCommand),
    /// The window was closed.
    Closed,
}

/// The slot a simulation publishes frames into and a window reads them from.
#[derive(Clone, Debug)]
pub struct ViewSlot {
    latest: Arc<Mutex<Arc<ViewFrame>>>,
    wants_lattice: Arc<AtomicBool>,
    closed: Arc<AtomicBool>,
}

impl ViewSlot {
    /// A slot holding `first`.
    pub fn new(first: ViewFrame) -> Self {
        ViewSlot {
            latest: Arc::new(Mutex::new(Arc::new(first))),
            wants_lattice: Arc::new(AtomicBool::new(false)),
            closed: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Replaces the published frame (the lock guards one pointer swap; the old frame is
    /// dropped after the lock is released, so the publisher never frees under the lock).
    pub fn publish(&self, frame: ViewFrame) {
        let new = Arc::new(frame);
        let old = {
            let mut guard = self.latest.lock().unwrap_or_else(|e| e.into_inner());
            std::mem::replace(&mut *guard, new)
        };
        drop(old);
    }

    /// The latest published frame.
    pub fn latest(&self) -> Arc<ViewFrame> {
        self.latest
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Whether the window currently shows the lattice wireframe (publishers include it
    /// only then).
    pub fn wants_lattice(&self) -> bool {
        self.wants_lattice.load(Ordering::Relaxed)
    }

    /// Set by the window when the user toggles the wireframe.
    pub fn set_wants_lattice(&self, on: bool) {
        self.wants_lattice.store(on, Ordering::Relaxed);
    }

    /// Asks the window to close (the simulation has ended); it does at its next frame.
    pub fn close(&self) {
        self.closed.store(true, Ordering::Relaxed);
    }

    /// Whether [`Self::close`] was called.
    pub fn is_closed(&self) -> bool {
        self.closed.load(Ordering::Relaxed)
    }
}

/// Length of the drawn shaft behind a tool's hinge (m).
pub const SHAFT_LENGTH: f64 = 0.25;

/// How far inside the surface a vertex's tissue is sampled (m): surface vertices lie on
/// the inclusion boundaries, so the point itself is ambiguous.
const TISSUE_PROBE_DEPTH: f64 = 0.0015;

fn tissue_of_inclusion(name: Option<&str>, material: &str, capsules: bool) -> TissueKind {
    let text = format!("{} {}", name.unwrap_or(""), material).to_lowercase();
    if text.contains("gall") {
        TissueKind::Gallbladder
    } else if capsules
        || ["vessel", "duct", "artery", "vein"]
            .iter()
            .any(|w| text.contains(w))
    {
        TissueKind::Vessel
    } else {
        TissueKind::Parenchyma
    }
}

/// Builds [`ViewFrame`]s from a [`Simulation`]: holds the fixed surface topology and
/// the embedding of the vessels' centre lines.
pub struct FrameBuilder {
    topology: Arc<SurfaceTopology>,
    /// Offsets of every surface's first vertex in the concatenated vertex list.
    surface_offsets: Vec<usize>,
    vessel_points: Embedding,
    /// Pairs of indices into the vessel points, with the radius (m).
    vessel_segments: Vec<(usize, usize, f64)>,
    port: CameraPort,
}

impl FrameBuilder {
    /// Prepares the builder for a simulation (computes vertex tissues once).
    pub fn new(sim: &Simulation) -> Result<Self, sim_lattice::LatticeError> {
        let scene = sim.scene();
        let mut triangles = Vec::new();
        let mut vertex_tissue = Vec::new();
        let mut surface_offsets = Vec::new();
        for surface in sim.surfaces() {
            let base = vertex_tissue.len();
            surface_offsets.push(base);
            let mesh = &surface.rest;
            let normals = mesh.vertex_normals();
            for (p, n) in mesh.vertices.iter().zip(&normals) {
                vertex_tissue.push(tissue_at(scene, &(p - n * TISSUE_PROBE_DEPTH)));
            }
            triangles.extend(mesh.triangles.iter().map(|t| t.map(|i| i + base as u32)));
        }
        let mut points = Vec::new();
        let mut vessel_segments = Vec::new();
        for body in &scene.scene.bodies {
            // A vessel that is a body of its own has its own surface: a tube along its
            // inclusion would only bridge a cut through it.
            if tissue_of_inclusion(Some(&body.name), &body.material, false) == TissueKind::Vessel {
                continue;
            }
            for inc in &body.inclusions {
                if let InclusionShape::Capsules(caps) = inc.shape() {
                    for c in caps {
                        let i = points.len();
                        points.push(c.a);
                        points.push(c.b);
                        vessel_segments.push((i, i + 1, c.radius));
                    }
                }
            }
        }
        let vessel_points = Embedding::new(sim.lattice(), &points)?;
        Ok(FrameBuilder {
            topology: Arc::new(SurfaceTopology {
                triangles,
                vertex_tissue,
            }),
            surface_offsets,
            vessel_points,
            vessel_segments,
            port: port_of(scene),
        })
    }

    /// The shared surface topology.
    pub fn topology(&self) -> &Arc<SurfaceTopology> {
        &self.topology
    }

    /// The frame of the simulation's current state. `interaction` supplies the local
    /// tools and their forces; `with_lattice` adds the wireframe.
    pub fn build(
        &mut self,
        sim: &Simulation,
        interaction: Option<&Interaction>,
        with_lattice: bool,
        hud: HudInfo,
    ) -> ViewFrame {
        let mut positions = Vec::with_capacity(self.topology.vertex_tissue.len());
        for surface in sim.surfaces() {
            positions.extend_from_slice(&surface.deformed);
        }
        debug_assert_eq!(self.surface_offsets.len(), sim.surfaces().len());
        self.vessel_points.update(sim.lattice());
        let mut vp = vec![V3::zeros(); self.vessel_points.len()];
        self.vessel_points
            .interpolate(sim.lattice(), sim.positions(), &mut vp);
        let vessels = self
            .vessel_segments
            .iter()
            .map(|&(a, b, r)| (Segment { a: vp[a], b: vp[b] }, r))
            .collect();
        let clips = sim
            .clip_positions()
            .into_iter()
            .map(|[a, b]| Segment { a, b })
            .collect();
        let lattice = with_lattice.then(|| lattice_edges(sim));
        let mut tools = Vec::new();
        let mut forces = Vec::new();
        if let Some(inter) = interaction {
            for (i, (tool, contact)) in inter
                .tools
                .tools
                .iter()
                .zip(&inter.state().tools)
                .enumerate()
            {
                let view = tool_view(tool, contact.force, inter.contact.is_grasping(i), None);
                if contact.force.norm() > 1e-6 {
                    forces.push(ForceArrow {
                        origin: tool.tip(),
                        force: contact.force,
                    });
                }
                tools.push(view);
            }
        }
        ViewFrame {
            topology: self.topology.clone(),
            positions,
            vessels,
            clips,
            lattice,
            tools,
            guide: Vec::new(),
            forces,
            hud,
            port: self.port,
        }
    }
}

/// A tool's drawing from the simulation's tool state.
pub fn tool_view(
    tool: &sim_core::Tool,
    force: V3,
    grasping: bool,
    site: Option<String>,
) -> ToolView {
    let hinge = (tool.pose() * Point3::new(0.0, 0.0, tool.length)).coords;
    let back = (tool.pose() * Point3::new(0.0, 0.0, tool.length + SHAFT_LENGTH)).coords;
    ToolView {
        name: tool.name.clone(),
        kind: tool.kind,
        pose: *tool.pose(),
        jaw: tool.jaw(),
        radius: tool.radius,
        parts: tool
            .segments()
            .into_iter()
            .map(|(a, b)| Segment { a, b })
            .collect(),
        shaft: Segment { a: hinge, b: back },
        force,
        grasping,
        site,
    }
}

/// Every edge of the lattice's leaves, once, with the finest adjacent leaf's level.
pub fn lattice_edges(sim: &Simulation) -> Vec<LatticeEdge> {
    let lattice = sim.lattice();
    let x = sim.positions();
    // edge (lower node, higher node) → index into `edges`
    let mut index: HashMap<(u32, u32), usize> = HashMap::new();
    let mut edges: Vec<((u32, u32), u8)> = Vec::new();
    for &t in lattice.leaves() {
        let level = lattice.tet_level(t);
        let n = lattice.tet_nodes(t);
        for i in 0..4 {
            for j in (i + 1)..4 {
                let key = (n[i].0.min(n[j].0), n[i].0.max(n[j].0));
                match index.get(&key) {
                    Some(&k) => edges[k].1 = edges[k].1.max(level),
                    None => {
                        index.insert(key, edges.len());
                        edges.push((key, level));
                    }
                }
            }
        }
    }
    edges
        .into_iter()
        .map(|((a, b), level)| LatticeEdge {
            segment: Segment {
                a: x[a as usize],
                b: x[b as usize],
            },
            level,
        })
        .collect()
}

/// Tissue at a rest-space point: the last inclusion containing it (as the simulation
/// assigns materials), else parenchyma.
pub fn tissue_at(scene: &LoadedScene, p: &V3) -> TissueKind {
    // The body holding the point (the last in scene order, where bodies overlap: the
    // vessels start inside the gallbladder's neck) gives the base tissue, by its name and
    // material (a scene of separate bodies); its inclusions override it.
    let mut kind = TissueKind::Parenchyma;
    for body in &scene.scene.bodies {
        let inside = match body.shape() {
            BodyShape::Box(b) => b.contains(p),
            BodyShape::Mesh(path) => scene.mesh(path).is_some_and(|m| m.contains(p)),
        };
        if inside {
            kind = tissue_of_inclusion(Some(&body.name), &body.material, false);
        }
    }
    for body in &scene.scene.bodies {
        for inc in &body.inclusions {
            let inside = match inc.shape() {
                InclusionShape::Capsules(c) => c.iter().any(|c| c.signed_distance(p) <= 0.0),
                InclusionShape::Mesh(path) => scene.mesh(path).is_some_and(|m| m.contains(p)),
            };
            if inside {
                kind = tissue_of_inclusion(
                    inc.name.as_deref(),
                    &inc.material,
                    matches!(inc.shape(), InclusionShape::Capsules(_)),
                );
            }
        }
    }
    kind
}

/// The scene's laparoscope port, or a default: 25 cm in front of (−y), 15 cm below and
/// looking at the centre of the bodies' bounds, 50° field of view.
pub fn port_of(scene: &LoadedScene) -> CameraPort {
    if let Some(cam) = &scene.scene.camera {
        return CameraPort {
            position: cam.position,
            target: cam.target,
            fov_deg: cam.fov_deg,
        };
    }
    let bounds = (0..scene.scene.bodies.len())
        .filter_map(|i| scene.body_bounds(i))
        .reduce(|a, b| a.union(&b));
    let target = bounds.map(|b| b.center()).unwrap_or_else(V3::zeros);
    CameraPort {
        position: target + V3::new(0.0, -0.25, -0.15),
        target,
        fov_deg: sim_core::sim_scene::DEFAULT_CAMERA_FOV_DEG,
    }
}

#[cfg(test)]
mod tests;
