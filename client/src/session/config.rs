//! What a site's session is configured with ([`SessionConfig`], the sync tuning) and what
//! it reports ([`SessionStats`], [`SessionSnapshot`]).

use proto::{Epoch, RegionId, Role, SiteId};
use sim_core::SimOptions;
use sim_core::sim_scene::LoadedScene;
use sim_core::sync::{RegionMap, SiteSync, SyncConfig, SyncStrategy};

use super::PlayoutLag;

/// What a session needs to know about its site.
#[derive(Clone)]
pub struct SessionConfig {
    pub role: Role,
    pub strategy: SyncStrategy,
    /// The scene and options the simulation is built from (and rebuilt on a reset).
    pub scene: LoadedScene,
    pub options: SimOptions,
    /// Whether the site has a link to a coordinator (without one nothing is transmitted).
    pub linked: bool,
    pub playout_lag: PlayoutLag,
    /// Pace steps to wall-clock time (true) or run as fast as possible.
    pub realtime: bool,
    /// Under hybrid: show the regions other sites own from their keyframes instead of
    /// simulating them (`cosurg join --follow keyframes`; see
    /// `sim_core::sync::SiteSync::show_keyframes`). The site then paces itself as a
    /// keyframe receiver does.
    pub shows_keyframes: bool,
}

impl SessionConfig {
    /// The sync state this site starts from (and restarts from on a scene reset).
    pub(super) fn new_sync(&self, map: RegionMap) -> SiteSync {
        let mut sync = SiteSync::new(self.strategy, map, sync_config());
        sync.show_keyframes(self.shows_keyframes);
        sync
    }

    /// The lag model: a hybrid site that shows keyframes needs them in hand, as a
    /// keyframe receiver does; other hybrid sites only need the inputs in time.
    pub(super) fn pacing_strategy(&self) -> SyncStrategy {
        if self.strategy == SyncStrategy::Hybrid && self.shows_keyframes {
            SyncStrategy::Keyframe
        } else {
            self.strategy
        }
    }
}

/// Counters for the site's report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SessionStats {
    pub keyframes_applied: u64,
    /// CPU time of applied keyframes (µs, sum): tree-state XOR, takeover, extrapolation.
    pub apply_us_total: f64,
    pub reconnects: u64,
    pub resets: u64,
    /// Wall time spent waiting so as not to run ahead of the owners' clocks (s).
    pub paced_seconds: f64,
    /// Sum and count of per-step lags behind the sites followed (s).
    pub behind_sum: f64,
    pub behind_steps: u64,
    /// Simulated time (s) at which the follower first came within
    /// [`pacing::LAG_REACHED_WITHIN`](super::pacing::LAG_REACHED_WITHIN) of its target
    /// lag, and the sum and count of its lags from then on: the display delay without the
    /// catch-up of a late start (the sites wait for one another's clocks, but at most
    /// `PRESENCE_WAIT`; see `SiteSession::is_ready`).
    pub lag_reached_at: Option<f64>,
    pub reached_behind_sum: f64,
    pub reached_behind_steps: u64,
    /// Topology ops received and applied (duplicates not counted), their CPU time (µs,
    /// sum), keyframes dropped because their topology was not reached yet, and the bytes of
    /// the topology ops we sent (framed).
    pub topology_applied: u64,
    pub topology_apply_us_total: f64,
    pub keyframes_topology_dropped: u64,
    pub topology_bytes_sent: u64,
    /// Refinement decisions applied (ours and the others', at their time).
    pub refinements_applied: u64,
    /// Of those, applied after their time (they arrived late; under hybrid and
    /// input-only sync).
    pub refinements_late: u64,
    /// Refinements that could not be applied (malformed; logged and dropped).
    pub refinements_dropped: u64,
    /// Keyframes and tree deltas made before a refinement we applied, whose trees would
    /// have undone it (dropped; the owner's next keyframe includes it).
    pub frames_refinement_dropped: u64,
    /// Under hybrid: new input samples of remote tools that arrived after the simulation
    /// had passed their time (it held the tool at its newest pose instead).
    pub late_inputs: u64,
}

/// What a renderer or HUD reads of the session (see `site::SiteStatus`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SessionSnapshot {
    pub site: Option<SiteId>,
    pub role: Option<Role>,
    pub epoch: Epoch,
    pub sites: usize,
    pub owned: Vec<RegionId>,
    pub remote_owners: Vec<(RegionId, SiteId)>,
    /// Live divergence from the owners' keyframes (m; see `SiteSync::divergence_m`).
    pub divergence_m: Option<f64>,
}

/// The sync tuning of a site. Extrapolation stays gentle: tissue under a surgeon's hand
/// does not accelerate at tens of m/s², and a receiver never extrapolates far.
pub(super) fn sync_config() -> SyncConfig {
    SyncConfig {
        max_accel_m_s2: 5.0,
        max_extrapolation_s: 0.06,
        // At most ~33 keyframes per second per region.
        min_interval_s: 0.03,
        ..SyncConfig::default()
    }
}
