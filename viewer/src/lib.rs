//! # cosurg-viewer
//!
//! The window of a cosurg site: it draws what the site's simulation publishes and turns
//! the user's mouse and keyboard into tool and session commands.
//!
//! * [`frame`]: the published picture ([`ViewFrame`]), built from a simulation by
//!   [`FrameBuilder`]; the slot it is published through ([`ViewSlot`]: the simulation
//!   swaps one pointer, never waits for the renderer); the commands sent back
//!   ([`ViewerCommand`]).
//! * [`camera`]: the laparoscope and orbit cameras and the mouse-to-tool mapping.
//! * [`render`]: three-d drawing of a frame; [`hud`]: the egui heads-up display.
//! * [`replay`]: playback of a recorded session ([`replay::run_replay_window`]: play,
//!   pause, scrub, speed).
//! * [`window`]: the window's event loop ([`run_window`]) and off-screen screenshots
//!   ([`screenshot`]).
//!
//! Units: SI (m, s, N) in the scene's world frame, +z up.

pub mod camera;
pub mod frame;
pub mod hud;
pub mod render;
pub mod replay;
pub mod window;

pub use frame::{
    CameraPort, ForceArrow, FrameBuilder, HudInfo, LatticeEdge, RegionOwner, Role, Segment,
    SessionCommand, SurfaceTopology, TissueKind, ToolCommand, ToolView, ViewFrame, ViewSlot,
    ViewerCommand,
};
/// The graphics stack, re-exported so that callers can build input events for tests.
pub use three_d;
pub use window::{
    Hands, Picture, ViewerError, WindowOptions, WindowStats, render_picture, run_window, screenshot,
};
