//! What a site is given ([`SiteConfig`]) and what it reports ([`SiteReport`]).

use std::path::PathBuf;

use proto::Role;
use serde::{Deserialize, Serialize};
use sim_core::SimOptions;
use sim_core::sim_scene::{LoadedScene, ToolScript};
use sim_core::sync::SyncStrategy;

use super::status::StatusBoard;
use super::view::SiteView;
use crate::haptic::site::DeviceSpec;
use crate::link::LinkConfig;
use crate::session::PlayoutLag;

/// Progress report: (simulated time in s, a short status line).
pub type ProgressCallback = Box<dyn FnMut(f64, &str) + Send>;

/// Everything a site needs to run.
pub struct SiteConfig {
    pub name: String,
    pub role: Role,
    pub scene: LoadedScene,
    /// The lattice cell (m) `scene`'s bodies were put on instead of their own
    /// (`--cell`), reported with the scene's hash.
    pub cell_m: Option<f64>,
    pub options: SimOptions,
    /// The scene tools this site drives (by name), the one in hand at the start first; a
    /// script with tracks for several exchanges them as its tracks begin. Empty: no local
    /// tool (observer).
    pub tools: Vec<String>,
    /// Trajectory of the local tool, played in simulation time from `script_start`.
    pub script: Option<ToolScript>,
    pub script_start: f64,
    /// Simulated seconds to run.
    pub seconds: f64,
    pub strategy: SyncStrategy,
    /// Extra CPU cost per step as a factor of the step's own cost (1 = none, 3 = three
    /// times slower), like a laptop beside a workstation.
    pub slowdown: f64,
    /// Output folder: surface recordings (`surfaces.surf`), VTU/PVD frames, report.
    pub out: Option<PathBuf>,
    /// Simulated time between VTU frames (s); `None`: no VTU.
    pub vtu_interval: Option<f64>,
    /// Write the session recording `<out>/<site>.cosrec` (when `out` is set).
    pub record: bool,
    /// Coordinator link; `None`: a site on its own.
    pub link: Option<LinkConfig>,
    /// Start the simulation only when this many sites (including this one) have joined.
    pub expect_sites: usize,
    /// Pace steps to wall-clock time (true) or run as fast as possible (false).
    pub realtime: bool,
    /// How far a site that follows another site's regions or tool keeps its simulation
    /// time behind that site's (`site::pacing`).
    pub playout_lag: PlayoutLag,
    /// Under hybrid: show the regions other sites own from their keyframes instead of
    /// simulating them (`--follow`, resolved).
    pub shows_keyframes: bool,
    /// Run the 1 kHz haptic loop beside the simulation.
    pub haptics: bool,
    /// Where the local tool's input comes from: the script, or a real device over UDP
    /// (the tool then follows the device and the haptic loop renders forces back to it;
    /// needs `haptics`).
    pub device: DeviceSpec,
    /// SCHED_FIFO priority of the haptic thread (`None`: normal priority; fails soft).
    pub rt_priority: Option<i32>,
    /// Called about every 0.25 s of simulated time with (sim time s, a short status).
    pub on_progress: Option<ProgressCallback>,
    /// Instructor: reset the scene when the simulated time reaches this (s); from
    /// `--reset-at` and the script's `[[command]]` entries.
    pub reset_at: Vec<f64>,
    /// Where the site publishes its state every step (a window or HUD reads it).
    pub status: Option<StatusBoard>,
    /// A window (or a screenshot at the end); `None`: headless.
    pub view: Option<SiteView>,
    /// The window's mouse and keyboard drive the local tool (no script, no device).
    pub hands: bool,
    /// The session's time dilation (`--time-scale`; the coordinator's): the site paces,
    /// stamps and measures in session time.
    pub time_scale: server::TimeScale,
}

/// What a site did, printed by `cosurg join` and collected by `cosurg demo`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SiteReport {
    /// Topology at the end: epoch (topology ops applied), digest of the ops and the
    /// separated element set (hex; equal on sites with the same topology), ops received and
    /// applied, their mean apply time (µs), keyframes dropped for a topology not reached
    /// yet, and the bytes of the ops this site sent.
    #[serde(default)]
    pub topology_epoch: u32,
    #[serde(default)]
    pub topology_digest: String,
    /// What the topology holds at the end: cuts, clips and attachment springs released.
    #[serde(default)]
    pub cuts: u32,
    #[serde(default)]
    pub clips: u32,
    #[serde(default)]
    pub springs_released: u32,
    #[serde(default)]
    pub topology_ops_received: u64,
    #[serde(default)]
    pub topology_apply_us_mean: f64,
    #[serde(default)]
    pub keyframes_topology_dropped: u64,
    #[serde(default)]
    pub topology_bytes_sent: u64,
    /// Refinement decisions applied here (every site's, at their simulated time).
    #[serde(default)]
    pub refinements_applied: u64,
    /// Of those, applied after their time (they arrived late).
    #[serde(default)]
    pub refinements_late: u64,
    /// Refinements that could not be applied (malformed; dropped).
    #[serde(default)]
    pub refinements_dropped: u64,
    /// Keyframes and tree deltas dropped because they were made before a refinement
    /// applied here and would have undone it.
    #[serde(default)]
    pub frames_refinement_dropped: u64,
    pub name: String,
    pub role: String,
    pub strategy: String,
    pub site_id: Option<u16>,
    pub scene_hash: String,
    /// The lattice cell (m) every body was put on instead of the scene's (`--cell`), if
    /// any: with the hash, what finds a built-in scene again.
    #[serde(default)]
    pub cell_m: Option<f64>,
    /// Under hybrid: session seconds the simulation waited for late inputs of remote tools
    /// touching tissue (instead of carrying them on).
    #[serde(default)]
    pub input_wait_s: f64,
    /// The session's time dilation when not real time (`--time-scale`): times and rates
    /// in this report are in session time, except the CPU costs (`step_ms_*`,
    /// `recording_ms_*`, `apply_us_*`, `topology_apply_us_mean`) and the haptic loop's
    /// figures, which are real.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_scale: Option<f64>,
    /// Simulated seconds and the wall-clock seconds they took.
    pub sim_seconds: f64,
    pub wall_seconds: f64,
    /// Simulation steps per wall-clock second.
    pub sim_rate_hz: f64,
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
    /// The longest step (ms): a hitch the user feels (a refinement, a rebuild) shows
    /// here before it shows in p99. Absent from reports of earlier versions.
    #[serde(default)]
    pub step_ms_max: f64,
    /// Wall time of the session recording's work per step (ms), p50 and p99; `None`
    /// when not recording.
    #[serde(default)]
    pub recording_ms_p50: Option<f64>,
    #[serde(default)]
    pub recording_ms_p99: Option<f64>,
    pub keyframes_sent: u64,
    pub keyframes_received: u64,
    pub keyframes_applied: u64,
    /// CPU time per applied keyframe (µs): tree-state XOR, takeover, extrapolation setup.
    pub apply_us_per_keyframe: f64,
    /// Application bytes per second over the run (UDP bytes in `udp_*`).
    pub up_bytes_per_s: f64,
    pub down_bytes_per_s: f64,
    pub udp_up_bytes_per_s: f64,
    pub udp_down_bytes_per_s: f64,
    /// With an impaired link (`--netem`): the mean one-way delay it added to the packets
    /// it delivered, up (to the coordinator) and down (ms), jitter and the wait for earlier
    /// packets included.
    #[serde(default)]
    pub link_up_delay_ms: Option<f64>,
    #[serde(default)]
    pub link_down_delay_ms: Option<f64>,
    /// Filled by the demo / sync bench from the recordings of all sites (mm).
    pub divergence_max_mm: Option<f64>,
    pub divergence_rms_mm: Option<f64>,
    /// Clock estimate against the coordinator at the end (µs).
    pub clock_offset_us: Option<f64>,
    pub rtt_us: Option<u64>,
    /// Region ownership this site held: (region, from sim time s, to sim time s).
    pub owned: Vec<(u32, f64, f64)>,
    /// Surface recordings (every 50 ms of simulated time).
    pub surf_file: Option<PathBuf>,
    /// The session recording (`<out>/<site>.cosrec`) and its size (bytes).
    #[serde(default)]
    pub recording_file: Option<PathBuf>,
    #[serde(default)]
    pub recording_bytes: Option<u64>,
    pub reconnects: u64,
    /// The screenshot written at the end (`--screenshot`).
    #[serde(default)]
    pub screenshot_file: Option<PathBuf>,
    /// The window (if one was open): frames drawn and frames per second of its life.
    #[serde(default)]
    pub window_frames: Option<u64>,
    #[serde(default)]
    pub window_fps: Option<f64>,
    /// Haptic loop: ticks per second and p99 period jitter (µs).
    pub haptic_rate_hz: Option<f64>,
    pub haptic_jitter_p99_us: Option<f64>,
    /// Haptic tick period p50 / p99 (µs), ticks more than half a period late, largest
    /// force sent to the device (N), and the device's name.
    pub haptic_period_p50_us: Option<f64>,
    pub haptic_period_p99_us: Option<f64>,
    pub haptic_overruns: Option<u64>,
    pub haptic_max_force_n: Option<f64>,
    pub haptic_device: Option<String>,
    /// UDP device (`--device udp:…`): pose datagrams accepted, force datagrams sent.
    pub device_poses_received: Option<u64>,
    pub device_forces_sent: Option<u64>,
    /// Teaching, instructor: trajectories sent to the session, and the newest one saved
    /// as a tool script (`<out>/teaching.toml`).
    pub teaching_sent: Option<u64>,
    pub teaching_file: Option<PathBuf>,
    /// Teaching, trainee: the guide force felt on the haptic device during playback (N),
    /// and the distance between the local tool tip and the recorded tip (mm).
    pub guide_force_max_n: Option<f64>,
    pub guide_force_mean_n: Option<f64>,
    pub playback_distance_mm: Option<f64>,
    pub playback_distance_max_mm: Option<f64>,
    /// Contact force on the local tool, max magnitude over the run (N).
    pub max_tool_force_n: f64,
    /// Wall time spent waiting so as not to run ahead of the owners' clocks (s).
    #[serde(default)]
    pub paced_seconds: f64,
    /// Under hybrid: remote tools' input samples that arrived after the simulation had
    /// passed their time (the playout lag was too short then).
    #[serde(default)]
    pub late_inputs: u64,
    /// Display delay: mean simulation-time lag behind the sites followed (ms), over the
    /// steps this site followed another without leading itself; 0 if it never did.
    #[serde(default)]
    pub playout_lag_ms: f64,
    /// The playout lag aimed at at the end of the run (ms).
    #[serde(default)]
    pub playout_target_ms: f64,
    /// Simulated time (s) at which this site, following, first came within 20 ms of its
    /// target lag (`session::pacing::LAG_REACHED_WITHIN`); `None` if it never did.
    #[serde(default)]
    pub lag_reached_at_s: Option<f64>,
    /// Display delay from then on (ms): [`Self::playout_lag_ms`] without the catch-up of
    /// a late start.
    #[serde(default)]
    pub playout_lag_reached_ms: Option<f64>,
    /// Scene epoch at the end (one more per scene reset of the session).
    #[serde(default)]
    pub epoch: u32,
    /// Scene resets this site went through.
    #[serde(default)]
    pub resets: u64,
}

impl SiteReport {
    /// Simulated seconds per session second, a follower's counted with its (mean) playout
    /// lag, which it runs behind by design: about 1 for a site that kept real time.
    pub fn kept_real_time(&self) -> f64 {
        (self.sim_seconds + self.playout_lag_ms * 1e-3) / self.wall_seconds.max(1e-9)
    }
}
