//! What the caller describes: materials, elements, shared rotation sources and the
//! Dirichlet mask ([`FemDesc`]), and what the system reports back about its templates.

use nalgebra::Matrix3;

use super::V3;
use crate::element::lame;

/// Material of an element.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Material {
    /// Young's modulus E (Pa).
    pub young: f64,
    /// Poisson ratio ν (dimensionless, < 0.5).
    pub poisson: f64,
    /// Density ρ (kg/m³).
    pub density: f64,
    /// Rayleigh mass-proportional damping α (1/s).
    pub rayleigh_mass: f64,
    /// Rayleigh stiffness-proportional damping β (s).
    pub rayleigh_stiffness: f64,
}

impl Material {
    /// Undamped material.
    pub fn new(young: f64, poisson: f64, density: f64) -> Self {
        Self {
            young,
            poisson,
            density,
            rayleigh_mass: 0.0,
            rayleigh_stiffness: 0.0,
        }
    }
    /// Lamé `(λ, μ)` (Pa).
    pub fn lame(&self) -> (f64, f64) {
        lame(self.young, self.poisson)
    }
}

/// Shape of a template element: tets with equal `key` differ only by translation and
/// uniform scale `scale` (= h_e, m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShapeRef {
    /// Caller's hashable shape key.
    pub key: u64,
    /// Uniform scale h_e (m).
    pub scale: f64,
}

/// One element as the caller describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElementDesc {
    /// Node ids, positively oriented (rest volume > 0).
    pub nodes: [usize; 4],
    /// Index into the material array.
    pub material: usize,
    /// Shape key and scale for the template stiffness table (None: dense/gradient path).
    pub shape: Option<ShapeRef>,
    /// Index of the rotation source whose R this element uses initially (None: its own).
    /// Every element also gets a source of its own, so
    /// [`FemSystem::set_rotation_assignment`](crate::FemSystem::set_rotation_assignment) can switch between the two at any step.
    pub rotation_source: Option<usize>,
}

/// A tet whose rotation other elements may share (e.g. a coarse ancestor whose four
/// vertices are nodes of the mesh).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RotationSourceDesc {
    /// Node ids.
    pub nodes: [usize; 4],
    /// `D_m⁻¹` of its rest edges (1/m); None: computed from the rest positions.
    pub rest_inverse_edges: Option<Matrix3<f64>>,
}

/// Everything needed to build a [`FemSystem`](crate::FemSystem).
#[derive(Clone, Debug, Default)]
pub struct FemDesc {
    /// Rest positions (m).
    pub rest: Vec<V3>,
    /// Elements.
    pub elements: Vec<ElementDesc>,
    /// Materials.
    pub materials: Vec<Material>,
    /// Dirichlet mask per node (empty: none fixed).
    pub fixed: Vec<bool>,
    /// Shared rotation sources referenced by `ElementDesc::rotation_source`.
    pub rotation_sources: Vec<RotationSourceDesc>,
}

/// Template zero statistics (see [`Template`](crate::Template)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TemplateInfo {
    /// Shape key.
    pub key: u64,
    /// Zero fraction of the 144 entries.
    pub zero_fraction: f64,
    /// Zero fraction of the 16 blocks.
    pub zero_block_fraction: f64,
    /// Elements using it.
    pub elements: usize,
}
