//! Drawing a [`ViewFrame`] with three-d: the organ surface (smooth-shaded, per-vertex
//! tissue colours), vessels, lattice wireframe, tools, ghosted remote tools, guide path
//! and force arrows. All tubes are instances of one unit cylinder.

use three_d::{
    Camera, ClearState, Context, CpuMesh, Gm, Indices, InstancedMesh, Instances, Mat4, Mesh,
    Object, Positions, Quat, RenderTarget, Srgba, Vec3, Viewport, radians, vec3,
};

mod headlight;
pub use headlight::HeadlightMaterial;

use crate::camera::View;
use crate::frame::{Segment, TissueKind, ViewFrame};

/// Colour of a tissue.
pub fn tissue_colour(t: TissueKind) -> [u8; 3] {
    match t {
        TissueKind::Parenchyma => [150, 62, 52],
        TissueKind::Gallbladder => [96, 150, 58],
        TissueKind::Vessel => [70, 92, 205],
    }
}

/// Wireframe colour of a refinement level (0 = root tets).
pub fn level_colour(level: u8) -> [u8; 3] {
    const KEY: [[u8; 3]; 5] = [
        [70, 110, 230],
        [60, 190, 90],
        [240, 190, 40],
        [240, 110, 40],
        [220, 40, 200],
    ];
    KEY[(level as usize).min(KEY.len() - 1)]
}

const TOOL_COLOUR: [u8; 3] = [190, 192, 200];
const ACTIVE_TOOL_COLOUR: [u8; 3] = [235, 225, 150];
const GUIDE_COLOUR: [u8; 3] = [40, 220, 230];
const FORCE_COLOUR: [u8; 3] = [255, 220, 0];
/// Clips: bright titanium, lighter than the tools' steel so that they stand out on the
/// vessel.
const CLIP_COLOUR: [u8; 3] = [236, 236, 248];
/// Tube radius of a clip (m): a medium-large ligation clip is about 2 mm across, closed.
const CLIP_RADIUS: f64 = 0.001;
/// Arrow length per newton (m/N).
pub const FORCE_SCALE: f64 = 0.02;
/// Drawn radius of lattice edges (m).
const WIRE_RADIUS: f32 = 0.0003;
/// Background (a dark abdominal cavity).
const BACKGROUND: [f32; 3] = [0.06, 0.05, 0.06];

fn v3(p: &nalgebra::Vector3<f64>) -> Vec3 {
    vec3(p.x as f32, p.y as f32, p.z as f32)
}

fn srgba(c: [u8; 3], a: u8) -> Srgba {
    Srgba::new(c[0], c[1], c[2], a)
}

/// The transformation taking the unit cylinder (x in [0, 1], radius 1) onto a tube.
fn tube(a: Vec3, b: Vec3, radius: f32) -> Option<Mat4> {
    let d = b - a;
    let len = (d.x * d.x + d.y * d.y + d.z * d.z).sqrt();
    // also rejects NaN lengths
    if len.is_nan() || len <= 1e-7 {
        return None;
    }
    let dir = d / len;
    let rot = Quat::from_arc(vec3(1.0, 0.0, 0.0), dir, Some(vec3(0.0, 0.0, 1.0)));
    Some(
        Mat4::from_translation(a)
            * Mat4::from(rot)
            * Mat4::from_nonuniform_scale(len, radius, radius),
    )
}

#[derive(Default)]
struct TubeList {
    transformations: Vec<Mat4>,
    colours: Vec<Srgba>,
}

impl TubeList {
    fn push(&mut self, s: &Segment, radius: f64, colour: Srgba) {
        if let Some(m) = tube(v3(&s.a), v3(&s.b), radius as f32) {
            self.transformations.push(m);
            self.colours.push(colour);
        }
    }
    fn instances(self) -> Instances {
        Instances {
            transformations: self.transformations,
            texture_transformations: None,
            colors: Some(self.colours),
        }
    }
}

/// Options of one drawing.
#[derive(Clone, Copy, Debug, Default)]
pub struct DrawOptions {
    /// Draw the lattice wireframe (if the frame carries it).
    pub wireframe: bool,
    /// Index of the local tool the user drives (highlighted).
    pub active_tool: Option<usize>,
}

/// GPU-side resources reused across frames.
pub struct Renderer {
    context: Context,
    cylinder: CpuMesh,
    cone: CpuMesh,
}

impl Renderer {
    /// Prepares the unit meshes.
    pub fn new(context: &Context) -> Self {
        Renderer {
            context: context.clone(),
            cylinder: CpuMesh::cylinder(12),
            cone: CpuMesh::cone(12),
        }
    }

    /// three-d camera for a view and viewport.
    pub fn camera(view: &View, viewport: Viewport) -> Camera {
        Camera::new_perspective(
            viewport,
            v3(&view.eye),
            v3(&view.target),
            v3(&view.up),
            radians(view.fov_y as f32),
            0.005,
            5.0,
        )
    }

    fn surface_mesh(&self, frame: &ViewFrame, light: Vec3) -> Gm<Mesh, HeadlightMaterial> {
        let topo = &frame.topology;
        let mut cpu = CpuMesh {
            positions: Positions::F32(frame.positions.iter().map(v3).collect()),
            indices: Indices::U32(topo.triangles.iter().flatten().copied().collect()),
            colors: Some(
                topo.vertex_tissue
                    .iter()
                    .map(|&t| srgba(tissue_colour(t), 255))
                    .collect(),
            ),
            ..Default::default()
        };
        cpu.compute_normals();
        Gm::new(
            Mesh::new(&self.context, &cpu),
            HeadlightMaterial::new(Srgba::WHITE, light),
        )
    }

    fn tubes(
        &self,
        list: TubeList,
        alpha: u8,
        light: Vec3,
    ) -> Option<Gm<InstancedMesh, HeadlightMaterial>> {
        if list.transformations.is_empty() {
            return None;
        }
        // instruments are metal: a brighter, sharper highlight than tissue
        let material = HeadlightMaterial {
            specular: 0.35,
            shininess: 40.0,
            ..HeadlightMaterial::new(Srgba::new(255, 255, 255, alpha), light)
        };
        Some(Gm::new(
            InstancedMesh::new(&self.context, &list.instances(), &self.cylinder),
            material,
        ))
    }

    /// Draws the 3D scene of `frame` seen from `view` into `target` (cleared first).
    pub fn draw(
        &self,
        target: &RenderTarget<'_>,
        viewport: Viewport,
        frame: &ViewFrame,
        view: &View,
        options: DrawOptions,
    ) {
        let camera = Self::camera(view, viewport);
        // the laparoscope carries its own light: a headlight along the view direction,
        // and no other (every light is paid per pixel on a CPU renderer)
        let light = v3(&view.forward());
        let surface = self.surface_mesh(frame, light);

        let mut solid = TubeList::default();
        for (seg, r) in &frame.vessels {
            solid.push(seg, *r, srgba(tissue_colour(TissueKind::Vessel), 255));
        }
        for clip in &frame.clips {
            solid.push(clip, CLIP_RADIUS, srgba(CLIP_COLOUR, 255));
        }
        let mut ghosts = TubeList::default();
        for (i, tool) in frame.tools.iter().enumerate() {
            let (list, colour) = match &tool.site {
                Some(_) => (&mut ghosts, srgba([170, 200, 255], 255)),
                None if options.active_tool == Some(i) => {
                    (&mut solid, srgba(ACTIVE_TOOL_COLOUR, 255))
                }
                None => (&mut solid, srgba(TOOL_COLOUR, 255)),
            };
            list.push(&tool.shaft, tool.radius * 1.6, colour);
            for p in &tool.parts {
                list.push(p, tool.radius * 0.8, colour);
            }
        }
        for w in frame.guide.windows(2) {
            solid.push(
                &Segment { a: w[0], b: w[1] },
                0.0008,
                srgba(GUIDE_COLOUR, 255),
            );
        }
        let mut heads = TubeList::default();
        for f in &frame.forces {
            let tip = f.origin + f.force * FORCE_SCALE;
            let len = (tip - f.origin).norm();
            if len < 1e-4 {
                continue;
            }
            let head = (0.006f64).min(0.5 * len);
            let neck = tip - (tip - f.origin) * (head / len);
            solid.push(
                &Segment {
                    a: f.origin,
                    b: neck,
                },
                0.0007,
                srgba(FORCE_COLOUR, 255),
            );
            if let Some(m) = tube(v3(&neck), v3(&tip), 0.0022) {
                // the cone's length is 1 along x like the cylinder's
                heads.transformations.push(m);
                heads.colours.push(srgba(FORCE_COLOUR, 255));
            }
        }
        if options.wireframe
            && let Some(edges) = &frame.lattice
        {
            for e in edges {
                solid.push(
                    &e.segment,
                    WIRE_RADIUS as f64,
                    srgba(level_colour(e.level), 255),
                );
            }
        }

        let solid = self.tubes(solid, 255, light);
        let ghosts = self.tubes(ghosts, 90, light);
        let heads = (!heads.transformations.is_empty()).then(|| {
            Gm::new(
                InstancedMesh::new(&self.context, &heads.instances(), &self.cone),
                HeadlightMaterial::new(Srgba::WHITE, light),
            )
        });

        let mut objects: Vec<&dyn Object> = vec![&surface];
        if let Some(s) = &solid {
            objects.push(s);
        }
        if let Some(h) = &heads {
            objects.push(h);
        }
        if let Some(g) = &ghosts {
            objects.push(g);
        }
        let [r, g, b] = BACKGROUND;
        target
            .clear(ClearState::color_and_depth(r, g, b, 1.0, 1.0))
            .render(&camera, objects, &[]);
    }
}
