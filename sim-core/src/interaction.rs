//! The interaction facade of one simulation: the scene's tools, tool–tissue contact
//! ([`crate::contact`]) and refinement following the tools ([`crate::adapt`]), run in that
//! order before every step.

use crate::adapt::{AdaptParams, AdaptReport, Adaptivity};
use crate::attach::hook::HookDissection;
use crate::contact::{ContactParams, ContactPipeline, ContactState};
use crate::cut::BladeStrokes;
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::{ToolInput, ToolSet};

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
    /// Cuts a blade committed (and applied) in this pass.
    pub cuts: usize,
    /// Attachment springs a hook released (and applied) in this pass.
    pub released: usize,
    /// Clips a clip applier placed (and applied) in this pass.
    pub clips: usize,
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
    /// The blades' strokes (cuts); ops they made are in `blades.made`.
    pub blades: BladeStrokes,
    /// The hooks' dissection (releases of attachment springs); ops in `hooks.made`.
    pub hooks: HookDissection,
    /// The clip appliers' clips; ops in `clips.made`.
    pub clips: crate::clip::ClipApplication,
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
            blades: BladeStrokes::new(sim, &tools, 0),
            hooks: HookDissection::new(&tools, 0),
            clips: crate::clip::ClipApplication::new(&tools, 0),
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
        let cuts = self.blades.update(sim, &self.tools)?;
        let released = self.hooks.update(sim, &self.tools)?;
        let clips = self.clips.update(sim, &self.tools)?;
        let focus = self.contact.focus_points_by_tool();
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
            cuts,
            released,
            clips,
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
