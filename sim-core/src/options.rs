use nalgebra::Vector3;
use sim_fem::{
    ByersXu, Model, MullerIterative, NewtonParams, OperatorMode, PolarMethod, SolverParams,
    StepParams, StiffnessMode,
};
use sim_scene::Scene;

/// Every knob of a simulation step. [`SimOptions::from_scene`] takes the scene's
/// `[simulation]` and `[features]` tables; callers (CLI, benches) override fields.
#[derive(Clone, Debug)]
pub struct SimOptions {
    /// Time step (s).
    pub dt: f64,
    /// Constitutive model.
    pub model: Model,
    /// Rotation extractor (co-rotational model).
    pub polar: PolarMethod,
    /// Hierarchical rotation sharing: angle tolerance θ_tol in degrees; `None` (or 0)
    /// extracts every leaf's rotation itself.
    pub sharing_angle_deg: Option<f64>,
    /// Template stiffness table (true) or per-element dense 12×12 matrices (false).
    pub template_stiffness: bool,
    /// Matrix-free or assembled CG operator.
    pub operator: OperatorMode,
    /// CG iteration budget and tolerance per step.
    pub solver: SolverParams,
    /// Newton iterations of the non-linear model's dynamic step.
    pub newton: NewtonParams,
    /// Skip rotation extraction for elements whose nodes moved less than this since the
    /// last extraction (m); 0 disables the skip.
    pub rest_threshold: f64,
    /// Robust fallback of the co-rotational step (degrees, 0 = off): a step in which an
    /// element's rotation turns by more than this is taken with Newton iterations
    /// ([`StepParams::fallback_angle_deg`]). Default 30°.
    pub fallback_angle_deg: f64,
    /// Online refinement near tools (scene feature `adaptivity`).
    pub adaptivity: bool,
    /// Tool contact (scene feature `contact`).
    pub contact: bool,
    /// Gravity (m/s²).
    pub gravity: Vector3<f64>,
    /// Threads of the FEM step ([`StepParams::threads`]); 1 (default) keeps the step on
    /// the simulation's own thread, as a site that runs a haptic loop beside it wants.
    pub threads: usize,
    /// Energy guard of the co-rotational step ([`StepParams::energy_guard`]); on by default.
    pub energy_guard: bool,
}

impl SimOptions {
    /// Options as the scene file asks for them.
    pub fn from_scene(scene: &Scene) -> Self {
        let s = &scene.simulation;
        let f = &scene.features;
        let polar = match s.polar {
            sim_scene::PolarMethod::ByersXu => PolarMethod::ByersXu(ByersXu {
                tol: s.polar_tolerance,
                ..ByersXu::default()
            }),
            sim_scene::PolarMethod::Svd => PolarMethod::Svd,
            sim_scene::PolarMethod::Muller => PolarMethod::Muller(MullerIterative {
                tol: s.polar_tolerance,
                ..MullerIterative::default()
            }),
            sim_scene::PolarMethod::ShapeMatching => PolarMethod::ShapeMatching,
        };
        SimOptions {
            dt: s.dt,
            model: model_from_scene(s.model),
            polar,
            sharing_angle_deg: (f.rotation_sharing && f.rotation_sharing_angle_deg > 0.0)
                .then_some(f.rotation_sharing_angle_deg),
            template_stiffness: f.template_stiffness,
            // Assembled block-CSR beat matrix-free at 1.5k and 12k tets (sim-fem benches).
            operator: OperatorMode::Assembled,
            solver: SolverParams {
                max_iters: s.cg_iterations as usize,
                tol: s.cg_tolerance,
                // Cold start: with the 50-iteration budget at dt = 33 ms, starting CG from
                // the previous step's Δv pumped about 9 kJ into the stress beam after violent
                // impulses (`cosurg bench stress --case impulses-33ms`; 1.02× with a cold
                // start). It saves only a few iterations where CG converges (dt ≤ 1 ms).
                warm_start: false,
            },
            newton: NewtonParams {
                max_iters: 8,
                tol: 1e-6,
            },
            // 1 µm: far below what a user sees or feels, far above round-off.
            rest_threshold: if f.skip_rest { 1e-6 } else { 0.0 },
            // `cosurg bench stress`: a beam with a 1000× stiffer rod, pulled through
            // itself and released at dt = 33 ms with the 50-iteration CG budget, reached
            // 1e5 J (from 40 J) without it and stayed below 40 J with it.
            fallback_angle_deg: 30.0,
            adaptivity: f.adaptivity,
            contact: f.contact,
            gravity: scene.gravity,
            threads: 1,
            energy_guard: true,
        }
    }

    /// The FEM step parameters these options mean.
    pub fn step_params(&self) -> StepParams {
        StepParams {
            model: self.model,
            stiffness: if self.template_stiffness {
                StiffnessMode::Template
            } else {
                StiffnessMode::Dense
            },
            operator: self.operator,
            solver: self.solver,
            gravity: self.gravity,
            polar: self.polar,
            rest_threshold: self.rest_threshold,
            newton: (self.model == Model::StVK).then_some(self.newton),
            fallback_angle_deg: self.fallback_angle_deg,
            threads: self.threads,
            energy_guard: self.energy_guard,
        }
    }
}

/// The scene's model names mapped to the FEM models (`nonlinear` is St Venant–Kirchhoff).
pub fn model_from_scene(m: sim_scene::Model) -> Model {
    match m {
        sim_scene::Model::Corotational => Model::Corotational,
        sim_scene::Model::Linear => Model::Linear,
        sim_scene::Model::Nonlinear => Model::StVK,
    }
}
