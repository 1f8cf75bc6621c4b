//! # cosurg-sim-core
//!
//! The deformation engine of one site: it ties the adaptive embedded lattice
//! ([`sim_lattice`]), the finite elements ([`sim_fem`]) and a scene ([`sim_scene`])
//! together into a [`Simulation`] that steps at a fixed time step.
//!
//! * [`Simulation`] — one organ (all bodies of a scene share one lattice): per-node state
//!   indexed by lattice [`NodeId`], per-leaf materials from the scene's inclusions,
//!   embedded surfaces and probes, fixed nodes and loads, and the FEM system rebuilt
//!   whenever the lattice topology changes.
//! * [`SimOptions`] — every knob of a step (model, polar method and tolerance, rotation
//!   sharing angle, stiffness kernel, solver budget), defaulted from the scene.
//! * [`cut`] — cutting (virtual node algorithm on the lattice, cut and capped surfaces)
//!   as topology operations shared across sites ([`Simulation::apply_topology_op`]).
//! * [`attach`] — connective layers tying two bodies (attachment springs) and their
//!   release by a hook (dissection), releases being topology operations like cuts.
//! * [`clip`] — clips a clip applier leaves on a vessel, topology operations like cuts.
//! * [`Interaction`] — the scene's tools ([`tools`]), tool–tissue contact and grasping
//!   ([`contact`]) and refinement following the tools ([`adapt`]): call
//!   [`Interaction::before_step`] with the tool inputs before every [`Simulation::step`].
//!
//! No IO beyond what the scene already loaded (surface recordings are collected in memory;
//! their `.surf` file format is [`sim_scene::surf`]'s), no threads, no async: for a given
//! input sequence a simulation is deterministic.
//!
//! Units: SI throughout (m, s, kg, N, Pa).

pub mod adapt;
pub mod attach;
pub mod clip;
pub mod contact;
pub mod cut;
mod engine;
mod error;
mod interaction;
pub mod multigrid;
mod options;
mod sharing;
pub mod sync;
pub mod tools;

pub use adapt::{AdaptParams, AdaptReport, Adaptivity, FocusPoints};
pub use contact::{
    ContactParams, ContactPipeline, ContactState, ContactStats, Interaction, InteractionReport,
    LocalModel, ToolContact,
};
pub use engine::{Simulation, StepReport, Surface, TopologyChange};
pub use error::SimError;
pub use multigrid::lattice_hierarchy;
pub use options::SimOptions;
pub use sim_fem;
pub use sim_lattice;
pub use sim_lattice::{NodeId, TetId};
pub use sim_scene;
pub use tools::{Tool, ToolInput, ToolSet};
