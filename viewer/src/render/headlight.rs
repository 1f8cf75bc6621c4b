//! A cheap shading model for the laparoscope's view: one headlight along the view
//! direction, Lambert diffuse plus a Blinn–Phong highlight, ambient, per-vertex (or
//! per-instance) colours, and three-d's tone and colour mapping.
//!
//! Why not three-d's `PhysicalMaterial`: without a GPU, Mesa's llvmpipe runs every
//! fragment shader on the CPU, and the physical model (a GGX specular term, a Fresnel
//! term and a light loop per pixel) cost most of each 1280×720 frame; the window then
//! took a whole core from a 2-core site and the simulation's step p99 rose with it. This
//! shader does the work of one light in a few multiply-adds. Its look is close to the
//! physical one it replaces (same light direction, same ambient level, a soft wet
//! highlight on tissue).

use three_d::{
    ColorMapping, EffectMaterialId, Light, Material, MaterialType, Program, RenderStates, Srgba,
    ToneMapping, Vec3, Viewer,
};

/// Material of everything in the 3D view (organ surface, vessels, tools, ghosts, arrows).
#[derive(Clone, Copy, Debug)]
pub struct HeadlightMaterial {
    /// Multiplies the vertex or instance colours (alpha < 1: drawn transparent).
    pub tint: Srgba,
    /// Direction the headlight shines (world frame, need not be unit length).
    pub light_direction: Vec3,
    /// Light that reaches every surface whatever its orientation (fraction of the colour).
    pub ambient: f32,
    /// Diffuse strength of the headlight (fraction of the colour at normal incidence).
    pub diffuse: f32,
    /// Strength of the white highlight.
    pub specular: f32,
    /// Blinn–Phong exponent of the highlight (larger: smaller and sharper).
    pub shininess: f32,
}

/// ID of this shader in three-d's program cache (three-d keeps 0x0000–0x4FFF for
/// materials defined outside the crate).
const HEADLIGHT_MATERIAL_ID: u16 = 0x0C05;

impl HeadlightMaterial {
    /// The view's default: the light level of the physical model it replaces (ambient
    /// 0.35, headlight 2.2 W/m² over π) and a soft highlight.
    pub fn new(tint: Srgba, light_direction: Vec3) -> Self {
        HeadlightMaterial {
            tint,
            light_direction,
            ambient: 0.35,
            diffuse: 2.2 / std::f32::consts::PI,
            specular: 0.12,
            shininess: 24.0,
        }
    }

    fn is_transparent(&self) -> bool {
        self.tint.a < 255
    }
}

impl Material for HeadlightMaterial {
    fn fragment_shader_source(&self, _lights: &[&dyn Light]) -> String {
        let mut source = String::new();
        source.push_str(ToneMapping::fragment_shader_source());
        source.push_str(ColorMapping::fragment_shader_source());
        source.push_str(FRAGMENT_SHADER);
        source
    }

    fn id(&self) -> EffectMaterialId {
        EffectMaterialId(HEADLIGHT_MATERIAL_ID)
    }

    fn use_uniforms(&self, program: &Program, viewer: &dyn Viewer, _lights: &[&dyn Light]) {
        viewer.tone_mapping().use_uniforms(program);
        viewer.color_mapping().use_uniforms(program);
        program.use_uniform("cameraPosition", viewer.position());
        program.use_uniform("lightDirection", -self.light_direction);
        program.use_uniform("tint", self.tint.to_linear_srgb());
        program.use_uniform("ambient", self.ambient);
        program.use_uniform("diffuse", self.diffuse);
        program.use_uniform("specular", self.specular);
        program.use_uniform("shininess", self.shininess);
    }

    fn render_states(&self) -> RenderStates {
        if self.is_transparent() {
            RenderStates {
                write_mask: three_d::WriteMask::COLOR,
                blend: three_d::Blend::TRANSPARENCY,
                ..Default::default()
            }
        } else {
            RenderStates::default()
        }
    }

    fn material_type(&self) -> MaterialType {
        if self.is_transparent() {
            MaterialType::Transparent
        } else {
            MaterialType::Opaque
        }
    }
}

/// `pos`, `nor` and `col` come from three-d's mesh vertex shader (world position, world
/// normal, vertex times instance colour in linear sRGB). `lightDirection` points from the
/// surface towards the light.
const FRAGMENT_SHADER: &str = "
uniform vec3 cameraPosition;
uniform vec3 lightDirection;
uniform vec4 tint;
uniform float ambient;
uniform float diffuse;
uniform float specular;
uniform float shininess;

in vec3 pos;
in vec3 nor;
in vec4 col;

layout (location = 0) out vec4 outColor;

void main()
{
    vec4 base = tint * col;
    vec3 n = normalize(gl_FrontFacing ? nor : -nor);
    vec3 l = normalize(lightDirection);
    vec3 v = normalize(cameraPosition - pos);
    float lambert = max(dot(n, l), 0.0);
    float highlight = lambert > 0.0 ? pow(max(dot(n, normalize(l + v)), 0.0), shininess) : 0.0;
    vec3 colour = base.rgb * (ambient + diffuse * lambert) + vec3(specular * highlight);
    outColor.rgb = color_mapping(tone_mapping(colour));
    outColor.a = base.a;
}
";
