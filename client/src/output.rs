//! ParaView output of a running simulation: per frame, the lattice's leaf tets (level,
//! type, material, tree), each embedded surface and the tools, collected into one PVD
//! time series; OBJ of the deformed surfaces at the end.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use nalgebra::{UnitQuaternion, Vector3};
use sim_core::Simulation;
use sim_core::sim_scene::vtk::{self, Cells, DataArray, Encoding, Pvd, UnstructuredGrid};

type V3 = Vector3<f64>;

/// A tool as drawn in a frame: pose, jaw opening and the force it feels.
#[derive(Clone, Debug)]
pub struct ToolFrame {
    pub name: String,
    pub position: V3,
    pub orientation: UnitQuaternion<f64>,
    /// Jaw opening angle (rad); 0 for tools without jaws.
    pub jaw: f64,
    /// Force on the tool (N).
    pub force: V3,
}

/// One embedded surface of a captured frame.
#[derive(Clone, Debug)]
pub struct SurfaceFrame {
    pub name: String,
    pub deformed: Vec<V3>,
    pub displacement: Vec<V3>,
    pub triangles: Vec<[u32; 3]>,
}

/// Everything one output frame shows, copied out of the simulation so that writing can
/// happen off the simulation thread.
#[derive(Clone, Debug)]
pub struct Frame {
    pub time: f64,
    pub points: Vec<V3>,
    pub displacement: Vec<V3>,
    pub velocity: Vec<V3>,
    pub contact_force: Vec<V3>,
    pub fixed: Vec<i32>,
    pub tets: Vec<[u32; 4]>,
    pub level: Vec<i32>,
    pub tet_type: Vec<i32>,
    pub material: Vec<i32>,
    pub root: Vec<u32>,
    pub heap: Vec<u32>,
    pub surfaces: Vec<SurfaceFrame>,
    pub tools: Vec<ToolFrame>,
}

impl Frame {
    /// Copies the lattice (live nodes renumbered compactly), surfaces and tools.
    pub fn capture(sim: &Simulation, tools: &[ToolFrame], node_force: Option<&[V3]>) -> Frame {
        let lattice = sim.lattice();
        let n = lattice.node_count();
        let mut compact = vec![u32::MAX; lattice.node_capacity()];
        let (mut points, mut displacement, mut velocity, mut contact_force, mut fixed) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        let (x, v) = (sim.positions(), sim.velocities());
        for node in lattice.nodes() {
            let i = node.0 as usize;
            compact[i] = points.len() as u32;
            points.push(x[i]);
            displacement.push(x[i] - lattice.node_rest(node));
            velocity.push(v[i]);
            contact_force.push(
                node_force
                    .and_then(|nf| nf.get(i).copied())
                    .unwrap_or_default(),
            );
            fixed.push(sim.is_fixed(node) as i32);
        }
        // After a cut, the elements are the leaves' copies (virtual node algorithm) and the
        // virtual nodes follow the lattice's nodes.
        let elements: Vec<(sim_core::TetId, [usize; 4])> = match sim.separation() {
            Some(sep) => {
                compact.resize(sep.dof_count(), u32::MAX);
                for (k, node) in sep.virtual_nodes.iter().enumerate() {
                    let i = sep.capacity + k;
                    compact[i] = points.len() as u32;
                    points.push(x[i]);
                    displacement.push(x[i] - lattice.node_rest(*node));
                    velocity.push(v[i]);
                    contact_force.push(V3::zeros());
                    fixed.push(sim.is_fixed(*node) as i32);
                }
                sep.copies.iter().map(|c| (c.leaf, c.dofs)).collect()
            }
            None => lattice
                .leaves()
                .iter()
                .map(|&t| (t, lattice.tet_nodes(t).map(|n| n.0 as usize)))
                .collect(),
        };
        Frame {
            time: sim.time(),
            tets: elements
                .iter()
                .map(|(_, dofs)| dofs.map(|d| compact[d]))
                .collect(),
            level: elements
                .iter()
                .map(|(t, _)| i32::from(lattice.tet_level(*t)))
                .collect(),
            tet_type: elements
                .iter()
                .map(|(t, _)| lattice.tet_type(*t) as i32)
                .collect(),
            material: elements
                .iter()
                .map(|(t, _)| sim.leaf_material(*t).map_or(-1, |m| m as i32))
                .collect(),
            root: elements.iter().map(|(t, _)| t.root).collect(),
            heap: elements.iter().map(|(t, _)| t.heap).collect(),
            points,
            displacement,
            velocity,
            contact_force,
            fixed,
            surfaces: sim
                .surfaces()
                .iter()
                .map(|s| SurfaceFrame {
                    name: s.name.clone(),
                    displacement: s
                        .deformed
                        .iter()
                        .zip(&s.rest.vertices)
                        .map(|(a, b)| a - b)
                        .collect(),
                    deformed: s.deformed.clone(),
                    triangles: s.rest.triangles.clone(),
                })
                .collect(),
            tools: tools.to_vec(),
        }
    }
}

/// Writes a VTU/PVD time series into one folder.
pub struct SeriesWriter {
    dir: PathBuf,
    pvd: Pvd,
    frame: usize,
}

impl SeriesWriter {
    /// A writer into `dir` (created).
    pub fn new(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        Ok(SeriesWriter {
            dir: dir.to_path_buf(),
            pvd: Pvd::new(),
            frame: 0,
        })
    }

    /// The output folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes one frame at the simulation's current time. `node_force` (N, by node id) is
    /// written as the lattice's `contact_force` point array when given.
    pub fn write_frame(
        &mut self,
        sim: &Simulation,
        tools: &[ToolFrame],
        node_force: Option<&[V3]>,
    ) -> Result<()> {
        self.write(&Frame::capture(sim, tools, node_force))
    }

    /// Writes a captured frame (may run on another thread than the simulation).
    pub fn write(&mut self, fr: &Frame) -> Result<()> {
        let f = self.frame;
        let t = fr.time;
        let grid = UnstructuredGrid::new(&fr.points, Cells::Tets(&fr.tets))
            .with_point_data(DataArray::vectors("displacement", &fr.displacement))
            .with_point_data(DataArray::vectors("velocity", &fr.velocity))
            .with_point_data(DataArray::vectors("contact_force", &fr.contact_force))
            .with_point_data(DataArray::ints("fixed", &fr.fixed))
            .with_cell_data(DataArray::ints("level", &fr.level))
            .with_cell_data(DataArray::ints("type", &fr.tet_type))
            .with_cell_data(DataArray::ints("material", &fr.material))
            .with_cell_data(DataArray::uints("tree_root", &fr.root))
            .with_cell_data(DataArray::uints("tree_heap_index", &fr.heap));
        let name = format!("lattice_{f:05}.vtu");
        vtk::write_vtu_file(self.dir.join(&name), &grid, Encoding::Binary)?;
        self.pvd.push(t, 0, name);

        for (k, s) in fr.surfaces.iter().enumerate() {
            let grid = UnstructuredGrid::new(&s.deformed, Cells::Triangles(&s.triangles))
                .with_point_data(DataArray::vectors("displacement", &s.displacement));
            let name = format!("surface_{}_{f:05}.vtu", sanitize(&s.name));
            vtk::write_vtu_file(self.dir.join(&name), &grid, Encoding::Binary)?;
            self.pvd.push(t, 1 + k as u32, name);
        }

        if !fr.tools.is_empty() {
            let tools = &fr.tools;
            let poses: Vec<(V3, UnitQuaternion<f64>)> =
                tools.iter().map(|t| (t.position, t.orientation)).collect();
            let jaw: Vec<f64> = tools.iter().map(|t| t.jaw).collect();
            let force: Vec<V3> = tools.iter().map(|t| t.force).collect();
            let name = format!("tools_{f:05}.vtu");
            let path = self.dir.join(&name);
            let file = std::fs::File::create(&path)
                .with_context(|| format!("creating {}", path.display()))?;
            let mut w = std::io::BufWriter::new(file);
            vtk::write_poses_vtu(
                &mut w,
                &poses,
                vec![
                    DataArray::scalars("jaw_angle_rad", &jaw),
                    DataArray::vectors("force_N", &force),
                ],
                Encoding::Ascii,
            )
            .with_context(|| format!("writing {}", path.display()))?;
            self.pvd.push(t, 1 + fr.surfaces.len() as u32, name);
        }
        self.pvd.write_file(self.dir.join("series.pvd"))?;
        self.frame += 1;
        Ok(())
    }

    /// Writes each deformed surface as `<name>_final.obj`.
    pub fn write_obj(&self, sim: &Simulation) -> Result<Vec<PathBuf>> {
        let mut out = Vec::new();
        for s in sim.surfaces() {
            let path = self.dir.join(format!("{}_final.obj", sanitize(&s.name)));
            vtk::write_surface_obj(
                &path,
                &s.deformed,
                &s.rest.triangles,
                6,
                &format!(
                    "cosurg deformed surface {} at t = {} s, scene {}",
                    s.name,
                    sim.time(),
                    sim.scene().hash
                ),
            )
            .with_context(|| format!("writing {}", path.display()))?;
            out.push(path);
        }
        Ok(out)
    }
}

fn sanitize(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}
