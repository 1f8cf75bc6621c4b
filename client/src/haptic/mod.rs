//! The haptic side of a site: a 1 kHz force loop on its own OS thread, the devices it
//! talks to, and teaching mode (record an instructor's tool trajectory, replay it on a
//! trainee's device as a guiding spring). See `docs/haptics.md`.
//!
//! # Threads and data flow
//!
//! ```text
//!  simulation thread (≈ 20–200 Hz)              haptic thread (1 kHz, never waits)
//!  ───────────────────────────────              ──────────────────────────────────
//!  ModelWriter::publish(HapticModel) ──seqlock──▶ latest model (keep previous on a torn read)
//!  InputReader::latest() ◀──────────seqlock───── ToolInput from HapticDevice::read
//!                                                F = F_s + K (x − x_s) [+ guide spring]
//!                                                → clamp |F| ≤ limit → fade if stale
//!                                                → rate limit |ΔF| → HapticDevice::apply
//! ```
//!
//! The two shared values are [`Latest`] cells: a sequence lock over atomic words, so the
//! haptic thread never blocks on the simulation thread (a reader retries a few times on a
//! concurrent write, then keeps the value it had). Newest wins in both directions.
//!
//! # Multi-rate rendering
//!
//! The simulation publishes, at each step, the force `F_s` and torque on the tool at the
//! tool tip position `x_s` it used, and the local stiffness `K = ∂F/∂x` (N/m; for contact
//! with tissue it is negative semi-definite: pushing further in increases the reaction).
//! Between steps the loop renders the local linear model `F = F_s + K (x − x_s)` with the
//! device's current tip position `x`. When the tool does not grasp tissue the contact is
//! unilateral: the extrapolated force is not allowed to pull the tool back along the
//! sampled force direction (see [`render::ForceRenderer`]).
//!
//! Units: SI (m, s, N, N·m, rad); the loop's clock is a [`Duration`](std::time::Duration)
//! since the loop started.

mod device;
mod latest;
mod measure;
pub mod render;
mod runner;
mod scripted;
pub mod site;
mod teaching;
mod timing;
pub mod udp;

pub use device::{HapticDevice, ToolInput};
pub use latest::{Latest, Words};
pub use measure::{measure_loop, measure_loop_with};
pub use render::{HapticModel, RenderConfig, Rendered};
pub use runner::{
    GuideClock, HapticConfig, HapticHandle, InputReader, ModelWriter, spawn, spawn_with_model,
};
pub use scripted::{AppliedForce, ScriptedDevice};
pub use teaching::{GuideSpring, TeachingPlayback, TeachingRecorder};
pub use timing::{HapticStats, PeriodHistogram};
pub use udp::{UdpBridgeDevice, UdpBridgeStats};

/// Errors of the haptic module.
#[derive(Debug, thiserror::Error)]
pub enum HapticError {
    /// A socket or file operation failed.
    #[error("{context}: {source}")]
    Io {
        /// What was being done (names the address or file).
        context: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// A tool script could not be read.
    #[error(transparent)]
    Script(#[from] sim_scene::ScriptError),
    /// A script has no track for the requested tool.
    #[error("{file}: no poses for tool \"{tool}\" (tools: {available})")]
    NoTrack {
        /// Script file or label.
        file: String,
        /// Requested tool.
        tool: String,
        /// Tools the script has.
        available: String,
    },
    /// A parameter is out of range.
    #[error("haptic parameter `{key}`: {problem}")]
    Invalid {
        /// Parameter name.
        key: &'static str,
        /// What is wrong.
        problem: String,
    },
}

impl HapticError {
    pub(crate) fn io(context: impl Into<String>, source: std::io::Error) -> Self {
        HapticError::Io {
            context: context.into(),
            source,
        }
    }
}
