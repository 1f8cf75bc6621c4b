//! [`Simulation`]: one site's organ — lattice, node state, materials, surfaces, FEM.

use std::collections::HashMap;

use nalgebra::Vector3;
use sim_fem::{
    ElementDesc, FemDesc, FemSystem, LinearSolver, Model, RotationSourceDesc, ShapeRef, StepStats,
};
use sim_lattice::{Embedding, Lattice, LatticeParams, NodeId, ShapeKey, TetId, TopologyEvent};
use sim_scene::{Aabb, BodyShape, Containment, InclusionShape, LoadedScene, TriMesh};

use crate::attach::Attachments;
use crate::cut::TopologyLog;
use crate::error::SimError;
use crate::options::SimOptions;

mod cutting;
mod materials;
use crate::sharing::RotationSharing;
pub use cutting::TopologyChange;
use materials::{MaterialMap, Region};

type V3 = Vector3<f64>;

/// An embedded triangle surface (a body's boundary) and its deformed vertices.
#[derive(Clone, Debug)]
pub struct Surface {
    /// Body name.
    pub name: String,
    /// Rest-pose mesh (m).
    pub rest: TriMesh,
    /// Host leaf tet and barycentric weights of every vertex.
    pub embedding: Embedding,
    /// Current vertex positions (m), interpolated from the lattice after every step.
    pub deformed: Vec<V3>,
}

/// What one [`Simulation::step`] did.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepReport {
    /// The FEM step's statistics.
    pub fem: StepStats,
    /// Whether the FEM system had to be rebuilt (topology or fixed set changed).
    pub rebuilt: bool,
    /// Leaves sharing an ancestor's rotation this step.
    pub shared_rotations: usize,
    /// Blocks whose rotation-sharing neighbour test ran this step.
    pub sharing_blocks_tested: usize,
}

/// One site's deformable organ. All bodies of a scene share one lattice.
pub struct Simulation {
    scene: LoadedScene,
    options: SimOptions,
    lattice: Lattice,
    /// Node positions (m), indexed by `NodeId.0`; dead slots hold their last value.
    x: Vec<V3>,
    /// Node velocities (m/s).
    v: Vec<V3>,
    /// Scene loads per node (N), recomputed after topology changes.
    f_scene: Vec<V3>,
    /// Extra forces for the next step (N): contact, haptics, tests.
    f_extra: Vec<V3>,
    /// Extra stiffness blocks `−∂f_extra/∂x` for the next step (N/m): contact, grasp.
    k_extra: Vec<(usize, nalgebra::Matrix3<f64>)>,
    /// Nodes clamped by the scene's `[[fix]]` boxes.
    fixed_scene: Vec<bool>,
    /// Nodes whose motion is prescribed for the next step (sync takeover): target
    /// position at the end of the step.
    prescribed: HashMap<NodeId, V3>,
    /// Whether the last step had prescribed nodes (they must be freed again).
    prescribed_last_step: bool,
    materials: Vec<sim_fem::Material>,
    material_names: Vec<String>,
    material_map: MaterialMap,
    leaf_material: HashMap<TetId, usize>,
    /// Fill of every leaf (scene feature `fill_weighting`; empty without it), see
    /// `engine/materials.rs`.
    leaf_fill: HashMap<TetId, f64>,
    /// Bodies containing each fill sample point asked so far (`engine/materials.rs`).
    fill_inside: HashMap<[u64; 3], u64>,
    shape_ids: HashMap<ShapeKey, u64>,
    fem: Option<FemSystem>,
    fem_fixed: Vec<bool>,
    /// [`LinearSolver::Auto`]'s choice (made on the first solve): kept across the FEM
    /// rebuilds of topology changes.
    auto_multigrid: Option<bool>,
    sharing: RotationSharing,
    surfaces: Vec<Surface>,
    probe_names: Vec<String>,
    probes: Embedding,
    time: f64,
    steps: u64,
    /// Applied topology operations (cuts), epoch and digest.
    topology: TopologyLog,
    /// Separation, virtual nodes and cut surfaces; `None` before the first cut.
    cut: Option<cutting::CutState>,
    /// Connective layers between bodies (attachment springs) and what is released.
    attachments: Attachments,
    /// Clips placed on the tissue (embedded ends).
    clips: crate::clip::Clips,
    /// Grid positions of the diamond centres of the scene's static refinement (material
    /// boundaries): no refinement op merges them ([`crate::adapt`]).
    static_diamonds: std::collections::HashSet<[i64; 3]>,
}

impl Simulation {
    /// Builds the lattice of every body, refines it along the inclusions that ask for it,
    /// embeds the surfaces and probes, and selects the fixed and loaded nodes.
    pub fn new(scene: LoadedScene, options: SimOptions) -> Result<Self, SimError> {
        let sc = &scene.scene;
        let file = scene.file.clone();
        let body_err = |index: usize, name: &str, problem: String| SimError::Body {
            file: file.clone(),
            index,
            name: name.to_string(),
            problem,
        };
        let first = sc
            .bodies
            .first()
            .ok_or_else(|| body_err(0, "", "the scene has no body".into()))?;
        if sc.features.fill_weighting && sc.bodies.len() > materials::MAX_FILL_BODIES {
            let b = materials::MAX_FILL_BODIES;
            return Err(body_err(
                b,
                &sc.bodies[b].name,
                format!("fill_weighting handles at most {b} bodies"),
            ));
        }
        let cell = first.cell;
        let max_depth = sc.bodies.iter().map(|b| b.max_depth).max().unwrap_or(0);
        let max_depth = u8::try_from(max_depth)
            .ok()
            .filter(|d| *d <= LatticeParams::MAX_DEPTH_LIMIT)
            .ok_or_else(|| body_err(0, &first.name, format!("max_depth {max_depth} too large")))?;
        let params = LatticeParams {
            origin: V3::zeros(),
            cell,
            max_depth,
        };

        // Material table: scene materials in name order.
        let material_names: Vec<String> = sc.materials.keys().cloned().collect();
        let materials: Vec<sim_fem::Material> = sc
            .materials
            .values()
            .map(|m| sim_fem::Material {
                young: m.young,
                poisson: m.poisson,
                density: m.density,
                rayleigh_mass: m.rayleigh_mass,
                rayleigh_stiffness: m.rayleigh_stiffness,
            })
            .collect();
        let material_index = |name: &str| material_names.iter().position(|n| n == name);

        // Cells of every body (one lattice), and their surfaces.
        let mut cells: Vec<[i32; 3]> = Vec::new();
        let mut surface_meshes: Vec<(String, TriMesh)> = Vec::new();
        let mut map = MaterialMap {
            bodies: Vec::new(),
            inclusions: Vec::new(),
        };
        for (i, body) in sc.bodies.iter().enumerate() {
            if (body.cell - cell).abs() > 1e-12 * cell {
                return Err(body_err(
                    i,
                    &body.name,
                    format!(
                        "cell {} m differs from body[0]'s {} m; bodies share one lattice",
                        body.cell, cell
                    ),
                ));
            }
            let mat = material_index(&body.material).ok_or_else(|| {
                body_err(i, &body.name, format!("unknown material {}", body.material))
            })?;
            match body.shape() {
                BodyShape::Box(b) => {
                    cells.extend(box_cells(b, cell));
                    surface_meshes.push((body.name.clone(), box_surface(b, cell)));
                    map.bodies.push((Region::Box(*b), mat));
                }
                BodyShape::Mesh(path) => {
                    let mesh = scene.mesh(path).ok_or_else(|| {
                        body_err(i, &body.name, format!("mesh {} not loaded", path.display()))
                    })?;
                    let tmp = Lattice::from_surface(params, &mesh.vertices, &mesh.triangles)?;
                    cells.extend_from_slice(tmp.cells());
                    surface_meshes.push((body.name.clone(), mesh.clone()));
                    map.bodies
                        .push((Region::Mesh(Box::new(Containment::new(mesh.clone()))), mat));
                }
            }
            for inc in &body.inclusions {
                let mi = material_index(&inc.material).ok_or_else(|| {
                    body_err(i, &body.name, format!("unknown material {}", inc.material))
                })?;
                let region = match inc.shape() {
                    InclusionShape::Capsules(c) => Region::Capsules(c.to_vec()),
                    InclusionShape::Mesh(path) => Region::Mesh(Box::new(Containment::new(
                        scene
                            .mesh(path)
                            .ok_or_else(|| {
                                body_err(
                                    i,
                                    &body.name,
                                    format!("mesh {} not loaded", path.display()),
                                )
                            })?
                            .clone(),
                    ))),
                };
                map.inclusions.push((region, mi, inc.refine_boundary));
            }
        }
        cells.sort_unstable();
        cells.dedup();
        let mut lattice = Lattice::from_cells(params, &cells)?;

        // Static refinement along material boundaries (report: refinement follows
        // material inhomogeneity). A leaf straddles a boundary when its vertices and
        // centroid do not all lie on the same side.
        let mut events = Vec::new();
        if map.inclusions.iter().any(|(_, _, refine)| *refine) {
            let mut inside_cache: HashMap<([i64; 3], usize), bool> = HashMap::new();
            let refined = &map.inclusions;
            lattice.refine_where(
                |lat, t| {
                    let nodes = lat.tet_nodes(t);
                    refined.iter().enumerate().any(|(k, (region, _, refine))| {
                        if !*refine {
                            return false;
                        }
                        let mut inside = nodes.iter().map(|&n| {
                            *inside_cache
                                .entry((lat.node_grid(n), k))
                                .or_insert_with(|| region.contains(&lat.node_rest(n)))
                        });
                        let first = inside.next().unwrap_or(false);
                        inside.any(|s| s != first)
                    })
                },
                &mut events,
            );
        }
        events.clear();

        let cap = lattice.node_capacity();
        let mut x = vec![V3::zeros(); cap];
        for n in lattice.nodes() {
            x[n.0 as usize] = lattice.node_rest(n);
        }
        let surfaces = surface_meshes
            .into_iter()
            .map(|(name, rest)| {
                let embedding = Embedding::new(&lattice, &rest.vertices)?;
                let deformed = rest.vertices.clone();
                Ok(Surface {
                    name,
                    rest,
                    embedding,
                    deformed,
                })
            })
            .collect::<Result<Vec<_>, SimError>>()?;
        let rest_surfaces: Vec<&TriMesh> = surfaces.iter().map(|s| &s.rest).collect();
        let attachments = Attachments::build(sc, &scene.file, &lattice, &rest_surfaces)?;
        let probe_points: Vec<V3> = sc.probes.iter().map(|p| p.point).collect();
        let probes = Embedding::new(&lattice, &probe_points)?;
        let probe_names = sc.probes.iter().map(|p| p.name.clone()).collect();
        let sharing = RotationSharing::new(options.sharing_angle_deg);

        let mut sim = Simulation {
            options,
            lattice,
            v: vec![V3::zeros(); cap],
            x,
            f_scene: vec![V3::zeros(); cap],
            f_extra: vec![V3::zeros(); cap],
            k_extra: Vec::new(),
            fixed_scene: vec![false; cap],
            prescribed: HashMap::new(),
            prescribed_last_step: false,
            materials,
            material_names,
            material_map: map,
            leaf_material: HashMap::new(),
            leaf_fill: HashMap::new(),
            fill_inside: HashMap::new(),
            shape_ids: HashMap::new(),
            fem: None,
            fem_fixed: Vec::new(),
            auto_multigrid: None,
            sharing,
            surfaces,
            probe_names,
            probes,
            time: 0.0,
            steps: 0,
            topology: TopologyLog::default(),
            cut: None,
            attachments,
            clips: crate::clip::Clips::default(),
            static_diamonds: std::collections::HashSet::new(),
            scene,
        };
        sim.static_diamonds = sim
            .lattice
            .nodes()
            .filter(|&n| sim.lattice.node_parent_edge(n).is_some())
            .map(|n| sim.lattice.node_grid(n))
            .collect();
        sim.select_nodes()?;
        sim.assign_materials();
        sim.rebuild_fem()?;
        Ok(sim)
    }

    /// Fixed and loaded nodes from the scene's boxes (errors name the box that selects no
    /// node).
    fn select_nodes(&mut self) -> Result<(), SimError> {
        let live: Vec<NodeId> = self.lattice.nodes().collect();
        let rest: Vec<V3> = live.iter().map(|&n| self.lattice.node_rest(n)).collect();
        let selection = self.scene.validate_selection(&rest)?;
        let cap = self.lattice.node_capacity();
        self.fixed_scene = vec![false; cap];
        self.f_scene = vec![V3::zeros(); cap];
        for i in selection.all_fixed() {
            self.fixed_scene[live[i].0 as usize] = true;
        }
        for (load, nodes) in self.scene.scene.loads.iter().zip(&selection.loaded) {
            let share = load.force / nodes.len() as f64;
            for &i in nodes {
                self.f_scene[live[i].0 as usize] += share;
            }
        }
        Ok(())
    }

    fn assign_materials(&mut self) {
        let lattice = &self.lattice;
        let map = &self.material_map;
        let leaf_material = &mut self.leaf_material;
        leaf_material.retain(|t, _| lattice.is_leaf(*t));
        if self.scene.scene.features.fill_weighting {
            let (leaf_fill, inside) = (&mut self.leaf_fill, &mut self.fill_inside);
            leaf_fill.retain(|t, _| lattice.is_leaf(*t));
            for &t in lattice.leaves() {
                if let std::collections::hash_map::Entry::Vacant(slot) = leaf_material.entry(t) {
                    let x = lattice.tet_nodes(t).map(|n| lattice.node_rest(n));
                    let (material, fill) = map.material_and_fill(&x, inside);
                    slot.insert(material);
                    leaf_fill.insert(t, fill);
                }
            }
            return;
        }
        for &t in lattice.leaves() {
            leaf_material.entry(t).or_insert_with(|| {
                let c = lattice
                    .tet_nodes(t)
                    .iter()
                    .map(|&n| lattice.node_rest(n))
                    .sum::<V3>()
                    / 4.0;
                map.material_at(&c)
            });
        }
    }

    /// Rebuilds the FEM system from the current leaves (after a topology change).
    fn rebuild_fem(&mut self) -> Result<(), SimError> {
        let rest = self.dof_rest();
        let alive = self.dof_alive();
        let mut materials = self.materials.clone();
        let mut elements = Vec::with_capacity(self.lattice.leaf_count());
        let cut_elements = self.cut_elements().unwrap_or_else(|| {
            self.lattice
                .leaves()
                .iter()
                .map(|&t| (self.lattice.tet_nodes(t).map(|n| n.0 as usize), t, 1.0))
                .collect()
        });
        // The scaled material of each (base material, fill).
        let mut filled: HashMap<(usize, u64), usize> = HashMap::new();
        for (nodes, t, fraction) in cut_elements {
            let shape = if self.options.template_stiffness() {
                let key = self.lattice.tet_shape(t);
                let next_id = self.shape_ids.len() as u64;
                let id = *self.shape_ids.entry(key).or_insert(next_id);
                Some(ShapeRef {
                    key: id,
                    scale: self.lattice.tet_scale(t),
                })
            } else {
                None
            };
            let base = self.leaf_material[&t];
            // A copy of a cut leaf carries its volume fraction of the leaf's stiffness and
            // mass (virtual node algorithm): a material scaled by the fraction (E and ρ
            // scale, ν and the Rayleigh coefficients stay). A fill (fill weighting)
            // scales the same way; the fills are few (`materials.rs`), and the leaves of
            // one fill share its material, and with it their template stiffness.
            let fill = self.leaf_fill(t);
            let scaled = |materials: &mut Vec<sim_fem::Material>, factor: f64| {
                let m = self.materials[base];
                materials.push(sim_fem::Material {
                    young: m.young * factor,
                    density: m.density * factor,
                    ..m
                });
                materials.len() - 1
            };
            let material = if fraction < 1.0 {
                scaled(&mut materials, fraction * fill)
            } else if fill < 1.0 {
                *filled
                    .entry((base, fill.to_bits()))
                    .or_insert_with(|| scaled(&mut materials, fill))
            } else {
                base
            };
            elements.push(ElementDesc {
                nodes,
                material,
                shape,
                rotation_source: None,
            });
        }
        let rotation_sources: Vec<RotationSourceDesc> =
            self.sharing.sources(&self.lattice, &mut elements);
        let fixed = self.effective_fixed(&alive);
        let mut fem = FemSystem::new(&FemDesc {
            rest,
            elements,
            materials,
            fixed: fixed.clone(),
            rotation_sources,
        })?;
        // Auto needs the hierarchy where it chose MG-PCG, and before it chooses where it
        // could choose it (more than `AUTO_MG_MIN_FREE_NODES` free nodes).
        let free = fixed.iter().filter(|f| !**f).count();
        let wants_hierarchy = match self.options.step.linear_solver {
            LinearSolver::MgPcg => true,
            LinearSolver::Auto => match self.auto_multigrid {
                Some(chosen) => chosen,
                None => free > sim_fem::AUTO_MG_MIN_FREE_NODES,
            },
            LinearSolver::JacobiPcg | LinearSolver::Direct => false,
        };
        fem.set_auto_multigrid(self.auto_multigrid);
        if wants_hierarchy {
            let mut hierarchy = crate::multigrid::lattice_hierarchy(&self.lattice)?;
            if let Some(cut) = &self.cut {
                let sep = &cut.separation;
                hierarchy =
                    crate::multigrid::hierarchy_with_copies(hierarchy, fem.num_nodes(), |d| {
                        sep.dof_node(d).0 as usize
                    })?;
            }
            fem.set_multigrid_hierarchy(hierarchy)?;
        }
        self.fem_fixed = fixed;
        self.fem = Some(fem);
        Ok(())
    }

    fn effective_fixed(&self, alive: &[bool]) -> Vec<bool> {
        let mut fixed: Vec<bool> = alive
            .iter()
            .zip(&self.fixed_scene)
            .map(|(a, f)| !a || *f)
            .collect();
        for n in self.prescribed.keys() {
            if let Some(f) = fixed.get_mut(n.0 as usize) {
                *f = true;
            }
        }
        fixed
    }

    /// Advances the simulation by one time step `options().dt`.
    ///
    /// Forces added with [`Simulation::add_force`] and motions prescribed with
    /// [`Simulation::prescribe`] apply to this step only. On a non-finite state the step
    /// is rolled back and an error returned.
    pub fn step(&mut self) -> Result<StepReport, SimError> {
        let dt = self.options.dt;
        let mut report = StepReport::default();
        if self.fem.is_none() {
            self.rebuild_fem()?;
            report.rebuilt = true;
        }
        // Prescribed nodes are Dirichlet nodes for this step; the FEM moves fixed nodes by
        // `dt v`, so their velocity is the one that reaches the target.
        // The Dirichlet set changes only with prescriptions (a rebuild already used the
        // current ones), so a step without them, after one without them, skips this.
        if !report.rebuilt && (!self.prescribed.is_empty() || self.prescribed_last_step) {
            let alive = self.dof_alive();
            let fixed = self.effective_fixed(&alive);
            if fixed != self.fem_fixed {
                self.fem
                    .as_mut()
                    .expect("built above")
                    .set_fixed(fixed.clone())?;
                self.fem_fixed = fixed;
            }
        }
        self.prescribed_last_step = !self.prescribed.is_empty();
        let fem = self.fem.as_mut().expect("built above");
        for (n, target) in &self.prescribed {
            let i = n.0 as usize;
            self.v[i] = (target - self.x[i]) / dt;
        }
        for (i, f) in self.fixed_scene.iter().enumerate() {
            if *f {
                self.v[i] = V3::zeros();
            }
        }
        let mut f_ext: Vec<V3> = self
            .f_scene
            .iter()
            .zip(&self.f_extra)
            .map(|(a, b)| a + b)
            .collect();
        self.attachments
            .add_forces(&self.x, &mut f_ext, &mut self.k_extra);
        let (x0, v0) = (self.x.clone(), self.v.clone());
        if let Some(shared) = self.sharing.update(fem, &self.x, &self.options)? {
            report.shared_rotations = shared.shared_elements;
            report.sharing_blocks_tested = shared.blocks_tested;
        }
        let params = self.options.step;
        // Extra stiffness (contact, attachments) applies to this step only.
        fem.set_external_stiffness(&self.k_extra);
        let result = fem.step(&mut self.x, &mut self.v, &f_ext, dt, &params);
        fem.clear_external_stiffness();
        self.auto_multigrid = fem.auto_chose_multigrid();
        self.k_extra.clear();
        let stats = match result {
            Ok(s) => s,
            Err(sim_fem::FemError::NonFinite) => {
                self.x = x0;
                self.v = v0;
                return Err(SimError::NonFinite { time: self.time });
            }
            Err(e) => return Err(e.into()),
        };
        report.fem = stats;
        self.prescribed.clear();
        self.f_extra.iter_mut().for_each(|f| *f = V3::zeros());
        self.time += dt;
        self.steps += 1;
        self.update_surfaces();
        Ok(report)
    }

    /// Recomputes the deformed surfaces and probes from the node positions.
    pub fn update_surfaces(&mut self) {
        if self.interpolate_cut_surfaces() {
            return;
        }
        for s in &mut self.surfaces {
            s.embedding
                .interpolate(&self.lattice, &self.x, &mut s.deformed);
        }
    }

    /// Adds a force (N) on a node for the next step only.
    pub fn add_force(&mut self, node: NodeId, f: V3) {
        if let Some(slot) = self.f_extra.get_mut(node.0 as usize) {
            *slot += f;
        }
    }

    /// Adds a stiffness block `K = −∂f/∂x` (N/m, symmetric positive semi-definite) on a
    /// node for the next step only: the implicit step treats the matching force added with
    /// [`Simulation::add_force`] as `f − K (x_{n+1} − x_n)` (stiff contact stays stable).
    ///
    /// Once a cut exists `node` may also be a virtual node's slot (a degree of freedom past
    /// the lattice's capacity, as [`Simulation::surface_vertex_host`] returns).
    pub fn add_stiffness(&mut self, node: NodeId, k: nalgebra::Matrix3<f64>) {
        let d = node.0 as usize;
        let virtual_slot = d >= self.lattice.node_capacity() && d < self.x.len();
        if virtual_slot || self.lattice.node_alive(node) {
            self.k_extra.push((d, k));
        }
    }

    /// Prescribes the position (m) a node reaches at the end of the next step.
    pub fn prescribe(&mut self, node: NodeId, target: V3) {
        if self.lattice.node_alive(node) {
            self.prescribed.insert(node, target);
        }
    }

    /// Sets position and velocity of a node directly (sync takeover, tests).
    pub fn set_node_state(&mut self, node: NodeId, x: V3, v: V3) {
        let i = node.0 as usize;
        if i < self.x.len() {
            self.x[i] = x;
            self.v[i] = v;
        }
    }

    /// Applies lattice topology events to the node state: new nodes start at their edge's
    /// midpoint with the average velocity. Then re-hosts surfaces, reassigns materials,
    /// reselects fixed/loaded nodes and marks the FEM system for rebuilding. With a cut,
    /// the lattice is refined along the cut again and re-separated (virtual nodes keep
    /// their state).
    pub fn after_topology_change(&mut self, events: &[TopologyEvent]) -> Result<(), SimError> {
        if events.is_empty() {
            return Ok(());
        }
        let old = self.detach_virtual();
        self.apply_lattice_events_only(events)?;
        self.after_lattice_change_cut(old)?;
        self.update_surfaces();
        Ok(())
    }

    /// [`Simulation::after_topology_change`] on the lattice layout of the node arrays
    /// (no virtual nodes), without the cut's re-separation.
    fn apply_lattice_events_only(&mut self, events: &[TopologyEvent]) -> Result<(), SimError> {
        if events.is_empty() {
            return Ok(());
        }
        let cap = self.lattice.node_capacity();
        self.x.resize(cap, V3::zeros());
        self.v.resize(cap, V3::zeros());
        self.f_extra.resize(cap, V3::zeros());
        for e in events {
            if let TopologyEvent::NodeAdded { node, edge: (a, b) } = *e {
                let (i, a, b) = (node.0 as usize, a.0 as usize, b.0 as usize);
                self.x[i] = 0.5 * (self.x[a] + self.x[b]);
                self.v[i] = 0.5 * (self.v[a] + self.v[b]);
            }
        }
        for s in &mut self.surfaces {
            s.embedding.update(&self.lattice);
        }
        self.probes.update(&self.lattice);
        self.attachments.update(&self.lattice);
        self.clips.update(&self.lattice);
        self.prescribed.retain(|n, _| self.lattice.node_alive(*n));
        self.assign_materials();
        self.select_nodes()?;
        self.fem = None;
        Ok(())
    }

    /// Splits the diamond of leaf `t` (and whatever conformity forces).
    pub fn refine(&mut self, t: TetId) -> Result<usize, SimError> {
        let mut events = Vec::new();
        let n = self.lattice.refine(t, &mut events)?;
        self.after_topology_change(&events)?;
        Ok(n)
    }

    /// Merges the diamond of `parent` back if allowed.
    pub fn coarsen(&mut self, parent: TetId) -> Result<bool, SimError> {
        let mut events = Vec::new();
        let merged = self.lattice.coarsen(parent, &mut events)?;
        self.after_topology_change(&events)?;
        Ok(merged)
    }

    /// Gives mutable access to the lattice together with an event sink; the caller must
    /// pass the events to [`Simulation::after_topology_change`].
    pub fn lattice_mut(&mut self) -> &mut Lattice {
        &mut self.lattice
    }

    // --- read access ---

    /// The scene this simulation was built from.
    pub fn scene(&self) -> &LoadedScene {
        &self.scene
    }
    /// The options in force.
    pub fn options(&self) -> &SimOptions {
        &self.options
    }
    /// Changes options; a change of stiffness kernel, sharing or linear solver rebuilds the
    /// FEM system.
    pub fn set_options(&mut self, options: SimOptions) {
        if options.template_stiffness() != self.options.template_stiffness()
            || options.sharing_angle_deg != self.options.sharing_angle_deg
            || options.step.linear_solver != self.options.step.linear_solver
        {
            self.sharing = RotationSharing::new(options.sharing_angle_deg);
            self.fem = None;
        }
        self.options = options;
    }
    /// The lattice.
    pub fn lattice(&self) -> &Lattice {
        &self.lattice
    }
    /// Node positions (m) by `NodeId.0`.
    pub fn positions(&self) -> &[V3] {
        &self.x
    }
    /// Node velocities (m/s) by `NodeId.0`.
    pub fn velocities(&self) -> &[V3] {
        &self.v
    }
    /// Rest position (m) of every node slot (zeros for dead slots), virtual nodes of cuts
    /// after the lattice's slots.
    pub fn rest_positions(&self) -> Vec<V3> {
        self.dof_rest()
    }
    /// Whether a node is clamped by the scene.
    pub fn is_fixed(&self, n: NodeId) -> bool {
        self.fixed_scene.get(n.0 as usize).copied().unwrap_or(false)
    }
    /// The connective layers between bodies and their released springs.
    pub fn attachments(&self) -> &Attachments {
        &self.attachments
    }
    /// The embedded surfaces.
    /// Whether the diamond centred at grid position `g` belongs to the scene's static
    /// refinement (never merged by tool-following adaptivity).
    pub fn is_static_diamond(&self, g: &[i64; 3]) -> bool {
        self.static_diamonds.contains(g)
    }

    pub fn surfaces(&self) -> &[Surface] {
        &self.surfaces
    }
    /// Simulated time (s).
    pub fn time(&self) -> f64 {
        self.time
    }
    /// Moves the simulation clock (s), e.g. a late joiner taking the session's time.
    pub fn set_time(&mut self, t: f64) {
        self.time = t;
    }
    /// Steps taken.
    pub fn steps(&self) -> u64 {
        self.steps
    }
    /// Material index of a leaf, and the material table with names.
    pub fn leaf_material(&self, t: TetId) -> Option<usize> {
        self.leaf_material.get(&t).copied()
    }
    /// Material names, in index order.
    pub fn material_names(&self) -> &[String] {
        &self.material_names
    }
    /// Materials, in index order.
    pub fn materials(&self) -> &[sim_fem::Material] {
        &self.materials
    }
    /// The fraction of leaf `t` that scales its stiffness and mass: its fill under the
    /// scene feature `fill_weighting` (in tenths, from 0.3 to 1), else 1.
    pub fn leaf_fill(&self, t: TetId) -> f64 {
        self.leaf_fill.get(&t).copied().unwrap_or(1.0)
    }
    /// The FEM system (built lazily after topology changes).
    pub fn fem(&mut self) -> Result<&mut FemSystem, SimError> {
        if self.fem.is_none() {
            self.rebuild_fem()?;
        }
        Ok(self.fem.as_mut().expect("built"))
    }
    /// Probe names and their current positions (m).
    pub fn probes(&self) -> Vec<(String, V3)> {
        let mut out = vec![V3::zeros(); self.probes.len()];
        self.probes.interpolate(&self.lattice, &self.x, &mut out);
        self.probe_names.iter().cloned().zip(out).collect()
    }
    /// Probe rest positions (m).
    pub fn probe_rest(&self) -> Vec<V3> {
        self.scene.scene.probes.iter().map(|p| p.point).collect()
    }
    /// Total external force of the scene's loads plus gravity on the lumped masses (N).
    pub fn scene_loads(&self) -> &[V3] {
        &self.f_scene
    }

    /// Static equilibrium under the scene's loads and gravity with `model`, starting from
    /// the current state (the rest pose on a fresh simulation). Returns the FEM statistics.
    pub fn solve_static(
        &mut self,
        model: Model,
        params: &sim_fem::StaticParams,
    ) -> Result<sim_fem::StaticStats, SimError> {
        let f = self.f_scene.clone();
        let mut x = self.x.clone();
        let stats = self.fem()?.solve_static(model, &mut x, &f, params)?;
        self.x = x;
        self.v.iter_mut().for_each(|v| *v = V3::zeros());
        self.update_surfaces();
        Ok(stats)
    }

    /// Elastic + kinetic + gravitational energy relative to the rest pose (J).
    pub fn energy(&mut self) -> Result<f64, SimError> {
        let g = self.options.step.gravity;
        let (x, v) = (self.x.clone(), self.v.clone());
        let rest = self.rest_positions();
        let params = self.options.step;
        let fem = self.fem()?;
        // Co-rotational elastic energy with the rotations at the current positions (the
        // stored ones are those of the previous step: for an inverted element whose
        // rotation flipped in the step they would be far off), extracted without touching
        // the stored state.
        let rotations = (params.model == sim_fem::Model::Corotational)
            .then(|| fem.compute_rotations(&x, &params.polar));
        let elastic = fem.elastic(
            &x,
            params.model,
            params.stiffness,
            rotations.as_deref(),
            None,
        );
        Ok(
            elastic + fem.kinetic_energy(&v) + fem.gravity_energy(&x, &g)
                - fem.gravity_energy(&rest, &g)
                + self.attachments.energy(&x),
        )
    }
}

/// Cells of the lattice that overlap the box (with a tolerance of 1e-9 cells so that a
/// box edge on a cell boundary does not add a sliver cell).
fn box_cells(b: &Aabb, cell: f64) -> Vec<[i32; 3]> {
    let lo: Vec<i32> = (0..3)
        .map(|k| (b.min[k] / cell + 1e-9).floor() as i32)
        .collect();
    let hi: Vec<i32> = (0..3)
        .map(|k| ((b.max[k] / cell - 1e-9).ceil() as i32).max(lo[k] + 1))
        .collect();
    let mut cells = Vec::new();
    for i in lo[0]..hi[0] {
        for j in lo[1]..hi[1] {
            for k in lo[2]..hi[2] {
                cells.push([i, j, k]);
            }
        }
    }
    cells
}

/// The boundary of a box as an outward-oriented triangle mesh with about one quad per
/// lattice cell on each face.
fn box_surface(b: &Aabb, cell: f64) -> TriMesh {
    let size = b.size();
    let n: [usize; 3] = std::array::from_fn(|k| ((size[k] / cell).round() as usize).max(1));
    let mut vertices: Vec<V3> = Vec::new();
    let mut index: HashMap<[usize; 3], u32> = HashMap::new();
    let mut triangles = Vec::new();
    let mut vid = |g: [usize; 3], vertices: &mut Vec<V3>| -> u32 {
        *index.entry(g).or_insert_with(|| {
            vertices.push(V3::from_fn(|k, _| {
                b.min[k] + size[k] * g[k] as f64 / n[k] as f64
            }));
            (vertices.len() - 1) as u32
        })
    };
    // For each axis a and side s, the face spans the other two axes (u, w) with u × w
    // pointing along +a; flip on the min side.
    for a in 0..3 {
        let (u, w) = ((a + 1) % 3, (a + 2) % 3);
        for side in [0usize, 1] {
            for i in 0..n[u] {
                for j in 0..n[w] {
                    let g = |di: usize, dj: usize| {
                        let mut g = [0usize; 3];
                        g[a] = side * n[a];
                        g[u] = i + di;
                        g[w] = j + dj;
                        g
                    };
                    let p00 = vid(g(0, 0), &mut vertices);
                    let p10 = vid(g(1, 0), &mut vertices);
                    let p11 = vid(g(1, 1), &mut vertices);
                    let p01 = vid(g(0, 1), &mut vertices);
                    if side == 1 {
                        triangles.push([p00, p10, p11]);
                        triangles.push([p00, p11, p01]);
                    } else {
                        triangles.push([p00, p11, p10]);
                        triangles.push([p00, p01, p11]);
                    }
                }
            }
        }
    }
    TriMesh {
        vertices,
        triangles,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_surface_is_closed_and_outward() {
        let b = Aabb::new(V3::zeros(), V3::new(0.4, 0.1, 0.1));
        let m = box_surface(&b, 0.025);
        assert!(m.is_closed());
        assert!(m.is_outward_oriented());
        assert!((m.signed_volume() - 0.004).abs() < 1e-12);
    }

    #[test]
    fn box_cells_cover_the_box_exactly() {
        let b = Aabb::new(V3::zeros(), V3::new(0.4, 0.1, 0.1));
        assert_eq!(box_cells(&b, 0.025).len(), 16 * 4 * 4);
    }
}
