use sim_fem::{
    ByersXu, MullerIterative, NewtonParams, OperatorMode, PolarMethod, SolverParams, StepParams,
    StiffnessMode,
};
use sim_scene::Scene;

/// Every knob of a simulation step. [`SimOptions::from_scene`] takes the scene's
/// `[simulation]` and `[features]` tables; callers (CLI, benches) override fields. The FEM
/// step's own parameters are embedded as [`SimOptions::step`] (documented in sim-fem's
/// [`StepParams`]); the fields here are what sim-core adds around the FEM step.
#[derive(Clone, Debug)]
pub struct SimOptions {
    /// Time step (s).
    pub dt: f64,
    /// The FEM step: model, stiffness kernel (template table or per-element dense 12×12
    /// matrices), CG operator and budget, gravity (m/s²), rotation extractor and its rest
    /// skip (m), Newton iterations of the non-linear model, the co-rotational step's
    /// robust fallback (degrees) and energy guard, threads.
    pub step: StepParams,
    /// Hierarchical rotation sharing: angle tolerance θ_tol in degrees; `None` (or 0)
    /// extracts every leaf's rotation itself.
    pub sharing_angle_deg: Option<f64>,
    /// Online refinement near tools (scene feature `adaptivity`).
    pub adaptivity: bool,
    /// Tool contact (scene feature `contact`).
    pub contact: bool,
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
            step: StepParams {
                model: s.model,
                stiffness: if f.template_stiffness {
                    StiffnessMode::Template
                } else {
                    StiffnessMode::Dense
                },
                // Assembled block-CSR beat matrix-free at 1.5k and 12k tets (sim-fem benches).
                operator: OperatorMode::Assembled,
                linear_solver: s.solver,
                mg_refresh_steps: 4,
                mg_sweeps: 1,
                solver: SolverParams {
                    max_iters: s.cg_iterations as usize,
                    tol: s.cg_tolerance,
                    // Cold start: with the 50-iteration budget at dt = 33 ms, starting CG
                    // from the previous step's Δv pumped about 9 kJ into the stress beam
                    // after violent impulses (`cosurg bench stress --case impulses-33ms`;
                    // 1.02× with a cold start). It saves only a few iterations where CG
                    // converges (dt ≤ 1 ms; MG-PCG at dt 10 ms: 18.2 → 16.2 on the stiff
                    // 12,288-tet beam), and with MG-PCG it tripled the energy guard's
                    // Newton fallbacks in the 1,536-tet stress pulls (docs/RESULTS.md).
                    warm_start: false,
                },
                gravity: scene.gravity,
                polar,
                // 1 µm: far below what a user sees or feels, far above round-off.
                rest_threshold: if f.skip_rest { 1e-6 } else { 0.0 },
                // Used by the non-linear model (StVK) only.
                newton: NewtonParams {
                    max_iters: 8,
                    tol: 1e-6,
                },
                // `cosurg bench stress`: a beam with a 1000× stiffer rod, pulled through
                // itself and released at dt = 33 ms with the 50-iteration CG budget,
                // reached 1e5 J (from 40 J) without it and stayed below 40 J with it.
                fallback_angle_deg: 30.0,
                // 1 keeps the step on the simulation's own thread, as a site that runs a
                // haptic loop beside it wants.
                threads: 1,
                energy_guard: true,
            },
            sharing_angle_deg: (f.rotation_sharing && f.rotation_sharing_angle_deg > 0.0)
                .then_some(f.rotation_sharing_angle_deg),
            adaptivity: f.adaptivity,
            contact: f.contact,
        }
    }

    /// Whether elements get shape keys for the template stiffness table (the stiffness
    /// kernel is a template one); changing this rebuilds the FEM system.
    pub fn template_stiffness(&self) -> bool {
        matches!(
            self.step.stiffness,
            StiffnessMode::Template | StiffnessMode::TemplateSparse
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim_fem::Model;

    #[test]
    fn scene_settings_land_in_the_embedded_step_parameters() {
        let mut scene = sim_scene::builtin::cantilever().scene;
        scene.simulation.model = Model::StVK;
        scene.simulation.cg_iterations = 17;
        scene.features.template_stiffness = false;
        scene.features.skip_rest = true;
        let o = SimOptions::from_scene(&scene);
        assert_eq!(o.dt, scene.simulation.dt);
        assert_eq!(o.step.model, Model::StVK);
        assert_eq!(o.step.solver.max_iters, 17);
        assert_eq!(o.step.stiffness, StiffnessMode::Dense);
        assert!(!o.template_stiffness());
        assert_eq!(o.step.rest_threshold, 1e-6);
        assert_eq!(o.step.gravity, scene.gravity);
        assert_eq!((o.step.newton.max_iters, o.step.newton.tol), (8, 1e-6));
        assert!(o.step.energy_guard && o.step.fallback_angle_deg == 30.0);
        scene.features.template_stiffness = true;
        assert!(SimOptions::from_scene(&scene).template_stiffness());
    }
}
