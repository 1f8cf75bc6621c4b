//! Sans-IO sync state of DESIGN §1(c): regions, keyframe encode/apply, second-order
//! extrapolation with blended corrections, the owner's dead-reckoning send decision, the
//! bench strategies, and surface recording (the `.surf` file format is
//! [`sim_scene::surf`]'s).
//!
//! One file per part: configuration ([`SyncConfig`], [`SyncStrategy`], `config.rs`), the
//! region map ([`RegionMap`], `regions.rs`), frames and their encoding ([`SyncFrame`],
//! `frame.rs`), the motion model shared by owner and receiver (`motion.rs`), the receiver
//! ([`RemoteRegion`], `receiver.rs`), the sender ([`SendPolicy`], `sender.rs`), surface
//! recording ([`SurfaceRecorder`], `recorder.rs`), and here [`SiteSync`], which bundles
//! them for a site.
//!
//! # Regions
//! [`RegionMap`] partitions the root tets into blocks of `B × B × B` lattice cells
//! (block `⌊(cell − min cell) / B⌋` per axis). Region ids are the non-empty
//! blocks in lexicographic block order, so two sites loading the same scene get the same
//! map. The *canonical node order* of a region is the set of live vertices of its roots'
//! leaves sorted by integer grid coordinate ([`sim_lattice::Lattice::node_grid`]): equal on
//! two sites whose region tree states are equal, so keyframes carry no node ids.
//!
//! # Per step, on a site
//! * Owner of a region: [`SendPolicy::poll`] (or [`SendPolicy::should_send`] +
//!   [`SendPolicy::encode`]) after the step; send the returned [`SyncFrame`]s. On release,
//!   send [`SendPolicy::release`]'s final keyframe.
//! * Receiver: [`RemoteRegion::apply_keyframe`] / [`RemoteRegion::apply_tree_delta`] when
//!   frames arrive, and [`RemoteRegion::drive`] before every step. [`SiteSync`] bundles all
//!   of this for a site.
//!
//! # Extrapolation and blending
//! A keyframe at sim time `t_k` gives each node `x_k, v_k`; `a = (v_k − v_{k−1}) / (t_k −
//! t_{k−1})` from the previous keyframe (clamped to [`SyncConfig::max_accel_m_s2`]). The
//! receiver shows `x_k + v_k Δt + ½ a Δt²` with `Δt = t − t_k` clamped to
//! ±[`SyncConfig::max_extrapolation_s`] (DIS "FVW" dead reckoning), plus a correction
//! offset: when a keyframe arrives at receiver time `t_r`, the offset is the receiver's
//! current position minus the new extrapolation at `t_r`, and it decays linearly to zero
//! over [`SyncConfig::blend_window_s`]. A node therefore never jumps: per step the shown
//! position departs from the pure extrapolation by at most `|offset| · dt / window` more.
//! A window of 0 snaps (position and velocity taken over at once).
//!
//! # Interpolation
//! A receiver that runs behind the owner in simulated time (a playout lag) often holds the
//! region's *next* keyframe before its clock reaches it ([`RemoteRegion::hold_next`]).
//! Between the last applied keyframe and the held one at `t_n` it then shows the
//! extrapolation plus the difference to the held keyframe, made up over a tail before
//! `t_n` (one step when no keyframe is missing in between — the owner's dead reckoning
//! kept the extrapolation within its threshold until then —, else estimated from the held
//! velocities; see [`RemoteRegion::motion_at`]), and applies the held keyframe at `t_n` as
//! usual (its correction offset is then about zero). Only a keyframe of the region's
//! current tree state is held (its nodes are the current nodes); otherwise extrapolation
//! as above.
//!
//! # Dead reckoning
//! [`SendPolicy`] keeps, per owned region, the same extrapolation the receivers run from
//! its last sent keyframe and sends when the largest node distance between it and the
//! actual positions exceeds [`SyncConfig::drift_threshold_m`], when the region's tree
//! state changed (a [`RegionTreeDelta`] if the drift is small and an acknowledged baseline
//! exists, else a keyframe), or on the heartbeat; at most once per
//! [`SyncConfig::min_interval_s`]. Its estimate excludes the receivers' still-decaying
//! correction offsets and the wire quantisation (≤ 5 µm with proto's defaults).
//!
//! # Converting to `proto`
//! * [`RegionKeyframe`] → `proto::Message::Keyframe(RegionKeyframe { region, keyframe:
//!   keyframe_id, owner, sim_time_s: sim_time, epoch, tree_bits, nodes })` with `nodes =
//!   QuantisedNodes::encode_default(&(0..n as u32).collect::<Vec<_>>(), &positions,
//!   &velocities)`: the ids are canonical indices. Back: `positions`/`velocities` from
//!   `nodes.iter()` in id order (reject frames whose ids are not `0..n`).
//! * [`RegionTreeDelta`] ↔ `proto::Message::TreeDelta { region, site, epoch, sim_time_s:
//!   sim_time, base_keyframe, xor_bits }`.
//! * Acknowledge every keyframe [`SiteSync::on_frame`] returns an id for; pass the
//!   baseline tracker's all-acknowledged keyframe as `acked_base` to
//!   [`SiteSync::after_step`].
//!
//! # Limitations
//! * A receiver must not run its own adaptivity inside (or, through conformity, next to)
//!   a region it does not own: a forced split there makes the next keyframe merge it back,
//!   or fail with [`SyncError::Residual`] when a finer split outside blocks the merge.
//!   Under hybrid and input-only sync, linked sites refine only by decisions shared as
//!   ops ([`crate::adapt`]), applied by every site at the same simulated time.
//! * Nodes on the face between a remote region and a local one are prescribed by the
//!   remote region.
//! * Time is simulation time; a receiver whose clock lags the owner's extrapolates
//!   backwards (clamped to [`SyncConfig::max_extrapolation_s`]).
//!
//! Units: SI (m, s, m/s, m/s²). Times are simulation times (s).

mod config;
mod correction;
mod frame;
mod motion;
mod receiver;
mod recorder;
mod regions;
mod sender;
#[cfg(test)]
mod tests;

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::Vector3;
use sim_lattice::{LatticeError, StateDecodeError};

use crate::engine::Simulation;
use crate::error::SimError;

pub use config::{SyncConfig, SyncStrategy};
pub use correction::{CorrectedRegion, Correction, HybridConfig, StateHistory};
pub use frame::{
    RegionKeyframe, RegionTreeDelta, SyncFrame, apply_full_state, encode_full_state,
    encode_keyframe, encode_split_set, encode_tree_xor,
};
pub use receiver::{Applied, DriveStatus, RemoteRegion};
pub use recorder::{DEFAULT_MARK_INTERVAL_S, SurfaceRecorder};
pub use regions::RegionMap;
pub use sender::{SendCounters, SendPolicy, SendReason};
/// Max and RMS distance between two surfaces' vertices (defined beside the `.surf` format).
pub use sim_scene::surf::surface_divergence;

type V3 = Vector3<f64>;
/// Integer rest-grid coordinate of a node (the site-independent node name).
pub type Grid = [i64; 3];
/// Region identifier (matches `proto::RegionId`).
pub type RegionId = u32;
/// Keyframe identifier (matches `proto::KeyframeId`): per region, strictly increasing.
pub type KeyframeId = u64;

/// The pseudo-region of [`SyncStrategy::FullState`] frames: every root of the organ.
pub const FULL_STATE_REGION: RegionId = u32::MAX;

/// Default block edge (cells) of a region: the default scene (cholecystectomy, 10 × 8 × 4
/// cells of 2 cm) gets 24 regions of at most 3 × 3 × 3 cells (6 cm).
pub const DEFAULT_REGION_BLOCK: u32 = 3;

/// Errors of the sync layer (malformed or inconsistent frames, lattice failures).
#[derive(Debug, thiserror::Error)]
pub enum SyncError {
    #[error("region {0} does not exist in this scene")]
    UnknownRegion(RegionId),
    #[error("region {region}: tree bits: {source}")]
    TreeBits {
        region: RegionId,
        source: StateDecodeError,
    },
    #[error("region {region}: tree state names roots other than the region's")]
    TreeRoots { region: RegionId },
    #[error("region {region}: tree state cannot be applied: {source}")]
    Lattice {
        region: RegionId,
        source: LatticeError,
    },
    #[error(
        "region {region}: after matching the tree state {residual} split bits still differ \
         (a merge was blocked by refinement outside the region)"
    )]
    Residual { region: RegionId, residual: usize },
    #[error("region {region}: frame has {got} nodes, the region has {expected}")]
    NodeCount {
        region: RegionId,
        expected: usize,
        got: usize,
    },
    #[error("region {region}: frame has {positions} positions but {velocities} velocities")]
    LengthMismatch {
        region: RegionId,
        positions: usize,
        velocities: usize,
    },
    #[error("region {region}: non-finite node state in frame")]
    NonFinite { region: RegionId },
    #[error(
        "region {region}: tree delta names base keyframe {base}, which this site does not hold"
    )]
    UnknownBase { region: RegionId, base: KeyframeId },
    #[error("region {region}: frame is for region {got}")]
    WrongRegion { region: RegionId, got: RegionId },
    #[error(transparent)]
    Sim(#[from] SimError),
}

/// Everything a site keeps for [`SyncStrategy::Keyframe`], [`SyncStrategy::FullState`] and
/// [`SyncStrategy::Hybrid`]: the region map, the owner policy, and the remote regions
/// (driven by keyframes, or under hybrid simulated and corrected).
#[derive(Clone, Debug)]
pub struct SiteSync {
    pub strategy: SyncStrategy,
    pub map: RegionMap,
    pub policy: SendPolicy,
    remote: BTreeMap<RegionId, RemoteRegion>,
    /// Under [`SyncStrategy::Hybrid`]: regions other sites own, simulated here and corrected.
    corrected: BTreeMap<RegionId, CorrectedRegion>,
    /// Under hybrid, as a follower: the local states of the last steps, for late keyframes.
    history: StateHistory,
    hybrid: HybridConfig,
    config: SyncConfig,
    full_state_next_id: KeyframeId,
    full_state_last: Option<KeyframeId>,
    /// Newest keyframe id sent or applied per region: ids stay strictly increasing per
    /// region across changes of ownership (including a site taking a region back), so
    /// receivers and the coordinator never mistake a new keyframe for a stale one.
    newest_id: BTreeMap<RegionId, KeyframeId>,
    /// Regions another site released; late frames for them are ignored once their
    /// remote state has blended out.
    released: BTreeSet<RegionId>,
    /// Largest node distance (m) from the owner's keyframe at the newest keyframe applied
    /// (any region, either strategy): the site's live divergence.
    divergence_m: Option<f64>,
    /// Under hybrid: this site shows the regions others own from their keyframes, as a
    /// keyframe-strategy receiver, instead of simulating and correcting them (its own
    /// solve is cut short: see [`SiteSync::show_keyframes`]).
    shows_keyframes: bool,
}

impl SiteSync {
    pub fn new(strategy: SyncStrategy, map: RegionMap, config: SyncConfig) -> Self {
        Self::with_hybrid(strategy, map, config, HybridConfig::default())
    }

    /// As [`SiteSync::new`], with the hybrid strategy's knobs. Under hybrid the owner sends
    /// each owned region every [`HybridConfig::keyframe_interval_s`] (and on a change of its
    /// tree state), not on dead-reckoning drift: the followers do not extrapolate, they
    /// simulate.
    pub fn with_hybrid(
        strategy: SyncStrategy,
        map: RegionMap,
        config: SyncConfig,
        hybrid: HybridConfig,
    ) -> Self {
        let policy_config = if strategy == SyncStrategy::Hybrid {
            SyncConfig {
                drift_threshold_m: f64::INFINITY,
                heartbeat_s: hybrid.keyframe_interval_s,
                ..config
            }
        } else {
            config
        };
        SiteSync {
            strategy,
            map,
            policy: SendPolicy::new(policy_config),
            remote: BTreeMap::new(),
            corrected: BTreeMap::new(),
            history: StateHistory::default(),
            hybrid,
            config,
            full_state_next_id: 1,
            full_state_last: None,
            newest_id: BTreeMap::new(),
            released: Default::default(),
            divergence_m: None,
            shows_keyframes: false,
        }
    }

    /// Under hybrid: show the regions other sites own from their keyframes (extrapolated
    /// and interpolated, as [`SyncStrategy::Keyframe`] does) instead of simulating them
    /// and correcting towards the keyframes. For a site whose own simulation is not the
    /// owners' (a CG budget cut to keep up): its copy departs from the owner's in fast
    /// motion faster than blended corrections bring it back (measured: a 5-iteration
    /// solve 10.9 mm from the owner at a grasp's release). Such a site says so in its
    /// acknowledgements, and owners then also send on dead-reckoning drift
    /// ([`SiteSync::follower_shows_keyframes`]).
    pub fn show_keyframes(&mut self, on: bool) {
        self.shows_keyframes = on && self.strategy == SyncStrategy::Hybrid;
        if self.shows_keyframes {
            self.corrected.clear();
            self.history.clear();
        }
    }

    /// Whether this site shows other sites' regions from their keyframes (under
    /// [`SyncStrategy::Keyframe`], or hybrid with [`SiteSync::show_keyframes`]).
    pub fn shows_keyframes(&self) -> bool {
        self.strategy == SyncStrategy::Keyframe || self.shows_keyframes
    }

    /// Under hybrid, unless it shows keyframes: this site simulates the regions others own
    /// and corrects them towards their keyframes.
    fn simulates_remote_regions(&self) -> bool {
        self.strategy == SyncStrategy::Hybrid && !self.shows_keyframes
    }

    /// Under hybrid, as owner: a follower shows our keyframes instead of simulating (it
    /// said so in an acknowledgement). From now on we also send when a region departs
    /// from the receivers' dead reckoning by [`SyncConfig::drift_threshold_m`], as under
    /// keyframe sync, besides the hybrid heartbeat, and at most once per
    /// [`HybridConfig::shown_min_interval_s`].
    /// Returns whether this changed anything.
    pub fn follower_shows_keyframes(&mut self) -> bool {
        let change = self.strategy == SyncStrategy::Hybrid
            && self.policy.config().drift_threshold_m != self.config.drift_threshold_m;
        if change {
            self.policy
                .set_drift_threshold(self.config.drift_threshold_m);
            self.policy
                .set_min_interval(self.hybrid.shown_min_interval_s);
        }
        change
    }

    /// Remote region state (created on its first keyframe).
    /// The site's divergence from the owners (m): the largest node distance from the
    /// owner's keyframe, moved on to this site's time (or, under hybrid, measured at the
    /// keyframe's time for a late one), when the newest keyframe arrived; `None` before
    /// any.
    pub fn divergence_m(&self) -> Option<f64> {
        self.divergence_m
    }

    pub fn remote(&self, region: RegionId) -> Option<&RemoteRegion> {
        self.remote.get(&region)
    }

    /// Regions currently driven by another site.
    pub fn remote_regions(&self) -> impl Iterator<Item = RegionId> + '_ {
        self.remote.keys().copied()
    }

    /// Under hybrid: the corrected state of a region another site owns.
    pub fn corrected(&self, region: RegionId) -> Option<&CorrectedRegion> {
        self.corrected.get(&region)
    }

    /// Before every step: drives remote regions (drops those back to local simulation);
    /// under hybrid adds each correction's share for this step.
    pub fn before_step(&mut self, sim: &mut Simulation) {
        if self.simulates_remote_regions() && !self.corrected.is_empty() {
            // As the step begins, before this step's share of a correction: the state
            // a keyframe of this time is compared with (only on a site that has had
            // keyframes to correct towards).
            let correcting = self.corrected.values().any(|c| c.steps_left() > 0);
            let keep = self.hybrid.max_age_s.max(self.hybrid.max_history_age_s) + sim.options().dt;
            self.history.record(sim, keep, correcting);
        }
        for c in self.corrected.values_mut() {
            c.drive(sim);
        }
        let map = &self.map;
        self.remote
            .retain(|_, r| r.drive(sim, map) != DriveStatus::Local);
    }

    /// After every step, as owner: frames to send. Under `FullState`, the owner of any
    /// region (the one site with a tool on the organ) sends the whole organ every k steps.
    pub fn after_step(
        &mut self,
        sim: &Simulation,
        acked_base: impl Fn(RegionId) -> Option<KeyframeId>,
    ) -> Vec<SyncFrame> {
        match self.strategy {
            SyncStrategy::Keyframe | SyncStrategy::Hybrid => {
                let frames = self.policy.poll(sim, &self.map, sim.time(), acked_base);
                for f in &frames {
                    if let SyncFrame::Keyframe(kf) = f {
                        self.note_id(kf.region, kf.keyframe_id);
                    }
                }
                frames
            }
            SyncStrategy::FullState { every_steps } => {
                if self.policy.owned().next().is_none()
                    || !sim.steps().is_multiple_of(u64::from(every_steps.max(1)))
                {
                    return Vec::new();
                }
                let id = self.full_state_next_id;
                self.full_state_next_id += 1;
                self.policy.counters.keyframes += 1;
                vec![SyncFrame::Keyframe(encode_full_state(sim, &self.map, id))]
            }
            SyncStrategy::InputOnly => Vec::new(),
        }
    }

    /// Holds the next keyframe of a remote region before this site's clock reaches it
    /// ([`RemoteRegion::hold_next`]); returns whether it is held.
    pub fn hold_next(&mut self, sim: &Simulation, kf: &RegionKeyframe) -> bool {
        if !self.shows_keyframes() || self.policy.is_owned(kf.region) {
            return false;
        }
        match self.remote.get_mut(&kf.region) {
            Some(r) => r.hold_next(sim, &self.map, kf),
            None => false,
        }
    }

    /// This site was granted `region`; numbering continues after the newest id seen.
    pub fn on_grant(&mut self, region: RegionId) {
        self.released.remove(&region);
        if let Some(k) = self.remote.remove(&region).and_then(|r| r.last_keyframe()) {
            self.note_id(region, k);
        }
        if let Some(k) = self
            .corrected
            .remove(&region)
            .and_then(|r| r.last_keyframe())
        {
            self.note_id(region, k);
        }
        let next = self.newest_id.get(&region).map_or(1, |k| k + 1);
        self.policy.acquire(region, next);
    }

    fn note_id(&mut self, region: RegionId, id: KeyframeId) {
        let e = self.newest_id.entry(region).or_insert(0);
        *e = (*e).max(id);
    }

    /// This site releases `region`: the final keyframe to send (Keyframe strategy).
    pub fn release(&mut self, sim: &Simulation, region: RegionId) -> Option<SyncFrame> {
        let kf = self.policy.release(sim, &self.map, region)?;
        self.note_id(region, kf.keyframe_id);
        matches!(self.strategy, SyncStrategy::Keyframe | SyncStrategy::Hybrid)
            .then_some(SyncFrame::Keyframe(kf))
    }

    /// Another site released `region` (after sending its final keyframe).
    pub fn on_remote_release(&mut self, region: RegionId) {
        self.released.insert(region);
        if let Some(r) = self.remote.get_mut(&region) {
            r.release();
        }
    }

    /// Another site was granted `region`: its keyframes drive the region again.
    pub fn on_remote_grant(&mut self, region: RegionId) {
        self.released.remove(&region);
        if let Some(r) = self.remote.get_mut(&region) {
            r.released = false;
        }
    }

    /// A frame from another site. Returns the keyframe id to acknowledge, if any. Frames for
    /// regions this site owns, and late frames for a released region that is already back
    /// to local simulation, are ignored.
    pub fn on_frame(
        &mut self,
        sim: &mut Simulation,
        frame: &SyncFrame,
    ) -> Result<Option<KeyframeId>, SyncError> {
        match frame {
            SyncFrame::Keyframe(kf) if kf.region == FULL_STATE_REGION => {
                if self.full_state_last.is_some_and(|k| kf.keyframe_id <= k) {
                    return Ok(None);
                }
                apply_full_state(sim, &self.map, kf)?;
                self.full_state_last = Some(kf.keyframe_id);
                Ok(None)
            }
            SyncFrame::Keyframe(kf) if self.simulates_remote_regions() => {
                if self.policy.is_owned(kf.region) {
                    return Ok(None);
                }
                let hybrid = self.hybrid;
                let c = self
                    .corrected
                    .entry(kf.region)
                    .or_insert_with(|| CorrectedRegion::new(kf.region, hybrid));
                let used = match c.apply_keyframe(sim, &self.map, kf, &self.history)? {
                    Correction::Started { max_m, .. } | Correction::Agrees { max_m } => {
                        self.divergence_m = Some(max_m);
                        true
                    }
                    _ => false,
                };
                if used {
                    self.note_id(kf.region, kf.keyframe_id);
                }
                Ok(used.then_some(kf.keyframe_id))
            }
            // Hybrid followers simulate their own tree state; the next keyframe carries
            // the owner's.
            SyncFrame::TreeDelta(_) if self.simulates_remote_regions() => Ok(None),
            SyncFrame::Keyframe(kf) => {
                if self.policy.is_owned(kf.region)
                    || (self.released.contains(&kf.region) && !self.remote.contains_key(&kf.region))
                {
                    return Ok(None);
                }
                let config = self.config;
                let r = self
                    .remote
                    .entry(kf.region)
                    .or_insert_with(|| RemoteRegion::new(kf.region, config));
                let applied = r.apply_keyframe(sim, &self.map, kf)? == Applied::Applied;
                if applied {
                    self.divergence_m = Some(r.last_divergence_m());
                    self.note_id(kf.region, kf.keyframe_id);
                }
                Ok(applied.then_some(kf.keyframe_id))
            }
            SyncFrame::TreeDelta(d) => {
                match self.remote.get_mut(&d.region) {
                    Some(r) => {
                        r.apply_tree_delta(sim, &self.map, d)?;
                    }
                    None => {
                        return Err(SyncError::UnknownBase {
                            region: d.region,
                            base: d.base_keyframe,
                        });
                    }
                }
                Ok(None)
            }
        }
    }
}
