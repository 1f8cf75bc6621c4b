//! The follower of [`SyncStrategy::Hybrid`](super::SyncStrategy::Hybrid): its own
//! simulation, driven by every site's tool input, corrected towards the owner's keyframes
//! by a blended correction ([`CorrectedRegion`]).
//!
//! A keyframe of a region this site does not own gives the owner's node states at its
//! simulated time `t_k`. When this site's clock reaches `t_f ≥ t_k`, the target of each
//! node is the keyframe's state advanced to `t_f` at its velocity (`x_k + v_k (t_f − t_k)`;
//! `t_f − t_k` is about one step when the playout lag holds), and the correction is the
//! difference to the local state. It is not applied at once (a jump of the view and of the
//! haptic force) but spread over the next steps: every step adds the same share of the
//! position and velocity difference, with the number of steps chosen so that no node moves
//! more than [`HybridConfig::max_step_m`] per step from the correction (and at least
//! [`HybridConfig::min_steps`]). The simulation keeps running in between, so where the
//! sites agree (equal simulations, inputs in time) the correction is about zero and costs
//! nothing; where they do not, the owner's state wins within a few steps.
//!
//! A keyframe that agrees with the local state to within the wire's quantisation
//! ([`HybridConfig::agree_m`], [`HybridConfig::agree_m_s`]) starts no correction: the
//! difference is rounding, and correcting it would nudge equal simulations apart (contact
//! and grasping amplify a few micrometres into tenths of a millimetre within a second).
//!
//! A keyframe that arrives after the local clock passed its time (`t_f > t_k`) is compared
//! with the local state *at `t_k`*, from a short history of local states
//! ([`StateHistory`]), and the difference found there is carried to `t_f` (a position
//! offset plus the velocity offset times `t_f − t_k`). Advancing the keyframe's state by
//! its velocity instead is wrong by `½ a (t_f − t_k)²` in position and `a (t_f − t_k)` in
//! velocity where the tissue accelerates (a release's spring-back), and that error started
//! corrections between equal simulations. Without a usable entry (the tree changed since,
//! no step was recorded at `t_k`, or a correction ran since: its shares are not in the
//! recorded states) the keyframe's state is advanced as before.
//!
//! After a cut, the virtual nodes the keyframe carries (the corners of the element copies
//! the cut made) are corrected like the lattice nodes, with the same history: setting them
//! to the keyframe's advanced state nudged equal simulations apart by that error and by
//! the wire's rounding.
//!
//! Keyframes older than [`HybridConfig::max_age_s`] at the time the local clock reaches
//! them are not advanced by their velocity: advancing a stale state is worse than the local
//! simulation. They are compared with the history instead, up to
//! [`HybridConfig::max_history_age_s`], when it holds a usable state at their time and the
//! region's tree is the keyframe's; only the position difference found there is carried
//! (the velocity difference of a second ago says little of now). Otherwise they are not
//! used (a newer keyframe follows within a heartbeat). The history then keeps that long:
//! one copy of the node states per step, 48 bytes a node (by count, about 8.4 MB at
//! 250 Hz for the default organ's 703 nodes at rest; more where it is refined).
//!
//! Units: SI (m, m/s, s).

use sim_lattice::NodeId;

use super::frame::{dof_grid, match_tree_and_nodes};
use super::{Grid, KeyframeId, RegionId, RegionKeyframe, RegionMap, SyncError, V3};
use crate::engine::Simulation;

/// Knobs of the hybrid follower's correction and of the owner's keyframe schedule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HybridConfig {
    /// Largest displacement (m) a correction adds to a node in one step: the bound on how
    /// far the view (and the haptic proxy's contact) moves per step because of sync.
    pub max_step_m: f64,
    /// A correction is spread over at least this many steps.
    pub min_steps: u32,
    /// Keyframes this much older (s of sim time) than the local clock are not applied,
    /// unless the history holds the local state at their time (below).
    pub max_age_s: f64,
    /// Keyframes older than [`HybridConfig::max_age_s`] are still compared with the local
    /// state at their time, up to this age (s), when the history holds it: see the module
    /// documentation.
    pub max_history_age_s: f64,
    /// The owner sends each owned region this often while owning (s of sim time).
    pub keyframe_interval_s: f64,
    /// A keyframe whose every node is within this distance (m) of the local state …
    pub agree_m: f64,
    /// … and within this speed (m/s) of the local velocity agrees with it: no correction.
    pub agree_m_s: f64,
    /// The owner's rate cap per region (s of sim time) once a follower shows its
    /// keyframes ([`super::SiteSync::follower_shows_keyframes`]).
    pub shown_min_interval_s: f64,
}

impl Default for HybridConfig {
    fn default() -> Self {
        HybridConfig {
            // 0.25 mm per 4 ms step: 6 cm/s, a gentle hand speed; a 3 cm correction (a
            // missed grasp) then takes about 0.5 s.
            max_step_m: 2.5e-4,
            min_steps: 5,
            max_age_s: 0.15,
            // Under hybrid a still owner keeps the playout lag behind the moving sites like
            // any follower (`client/src/session/pacing.rs`), so its keyframes reach the
            // other followers a path's delay after their time: 0.2–0.45 s under the
            // `average` and `poor` presets. Skipped at 0.15 s, they corrected nothing, and
            // a follower that strayed during an outage stayed 13 mm off after it
            // (`cosurg bench sync`, outage, seed 14, 2026-11-29).
            max_history_age_s: 1.0,
            keyframe_interval_s: 0.1,
            // The wire's rounding (proto's default quantisation) is at most half a step per
            // axis: √3 · 5 µm ≈ 8.7 µm and √3 · 0.05 mm/s ≈ 0.087 mm/s.
            agree_m: 1e-5,
            agree_m_s: 1e-4,
            // A heartbeat keyframe must not hold back the next drift keyframe: with the
            // sessions' 30 ms cap, a grasp's release 3 ms after a heartbeat reached the
            // follower 30 ms late, and it showed 4.4 mm of divergence; 10 ms: 0.34 mm
            // (`cosurg bench sync`, lan, trainee B on 5 CG iterations, 2026-11-25).
            shown_min_interval_s: 0.01,
        }
    }
}

/// The local node states of the last steps (every node, as they were when each step began,
/// before that step's share of a correction): what a late keyframe is compared with.
#[derive(Clone, Debug, Default)]
pub struct StateHistory {
    /// Oldest first.
    states: std::collections::VecDeque<Recorded>,
}

#[derive(Clone, Debug, Default)]
struct Recorded {
    /// Simulated time (s).
    time: f64,
    /// Lattice topology generation (node slots are the same while it is).
    generation: u64,
    /// A correction was under way: shares added after this state are not in it.
    correcting: bool,
    positions: Vec<V3>,
    velocities: Vec<V3>,
}

impl StateHistory {
    /// Records the state at the simulation's current time, keeping `keep_s` (s) of them.
    /// `correcting`: a correction adds its share to some node after this state.
    pub fn record(&mut self, sim: &Simulation, keep_s: f64, correcting: bool) {
        let t = sim.time();
        // A clock set back (a reset), or a time recorded twice, drops what is not older;
        // the oldest entry dropped lends its buffers to the new one.
        let mut spare = None;
        while let Some(front) = self.states.front()
            && front.time < t - keep_s
        {
            spare = self.states.pop_front();
        }
        self.states.retain(|r| r.time < t);
        let mut entry = spare.unwrap_or_default();
        entry.time = t;
        entry.generation = sim.lattice().topology_generation();
        entry.correcting = correcting;
        entry.positions.clear();
        entry.positions.extend_from_slice(sim.positions());
        entry.velocities.clear();
        entry.velocities.extend_from_slice(sim.velocities());
        self.states.push_back(entry);
    }

    /// The recorded state at simulated time `t` (within a thousandth of `dt`), if the
    /// lattice and its cuts' degrees of freedom are still the ones it was recorded on and
    /// no correction has moved nodes since (its shares would not be in the difference
    /// measured there).
    fn at(&self, sim: &Simulation, t: f64) -> Option<(&[V3], &[V3])> {
        let tol = 1e-3 * sim.options().dt;
        let generation = sim.lattice().topology_generation();
        let k = self.states.iter().position(|r| (r.time - t).abs() <= tol)?;
        if self.states.iter().skip(k).any(|r| r.correcting) {
            return None;
        }
        let r = &self.states[k];
        // A cut that needs no refinement leaves the generation alone but adds virtual
        // nodes, which renumbers the ones after them: the dof count tells.
        (r.generation == generation && r.positions.len() == sim.positions().len())
            .then_some((r.positions.as_slice(), r.velocities.as_slice()))
    }

    /// Forgets every state (a reset, a change of strategy).
    pub fn clear(&mut self) {
        self.states.clear();
    }
}

/// What [`CorrectedRegion::apply_keyframe`] did with a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Correction {
    /// A correction was started, spread over `steps` steps; `max_m`: the largest node
    /// distance from the keyframe (m), at the local time, or at the keyframe's time for a
    /// late keyframe compared with the history.
    Started { steps: u32, max_m: f64 },
    /// Not newer than the last keyframe used; ignored.
    Stale,
    /// Older than [`HybridConfig::max_age_s`] with no usable history at its time, or
    /// older than [`HybridConfig::max_history_age_s`]; ignored.
    TooOld,
    /// Agrees with the local state to within the wire's rounding; no correction (one under
    /// way is dropped: it was measured from an older keyframe). `max_m`: the largest node
    /// distance (m).
    Agrees { max_m: f64 },
}

/// A region another site owns, as a hybrid follower sees it: simulated locally, corrected
/// towards its owner's keyframes.
#[derive(Clone, Debug)]
pub struct CorrectedRegion {
    region: RegionId,
    config: HybridConfig,
    last_keyframe: Option<KeyframeId>,
    /// Per degree of freedom (a lattice node, or a cut's virtual node): its index, the
    /// grid point it stands for (checked before use: the tree or the cuts may change), and
    /// the position and velocity added per step.
    pending: Vec<(usize, Grid, V3, V3)>,
    /// The cuts' separation when the correction started (lattice capacity, dof count):
    /// virtual nodes are numbered from the capacity in grid order, so once either changes
    /// (a refinement, a new cut) the pending virtual entries name other nodes and are
    /// dropped.
    pending_separation: Option<(usize, usize)>,
    steps_left: u32,
    corrections: u64,
}

impl CorrectedRegion {
    pub fn new(region: RegionId, config: HybridConfig) -> Self {
        CorrectedRegion {
            region,
            config,
            last_keyframe: None,
            pending: Vec::new(),
            pending_separation: None,
            steps_left: 0,
            corrections: 0,
        }
    }

    pub fn region(&self) -> RegionId {
        self.region
    }

    /// Newest keyframe used (or skipped as too old).
    pub fn last_keyframe(&self) -> Option<KeyframeId> {
        self.last_keyframe
    }

    /// Steps the current correction still runs.
    pub fn steps_left(&self) -> u32 {
        self.steps_left
    }

    /// Corrections started so far.
    pub fn corrections(&self) -> u64 {
        self.corrections
    }

    /// Matches the region's tree state to the keyframe's and starts a correction towards
    /// its node states advanced to the local time (replacing any correction under way:
    /// the new one is measured from the current, partly corrected, state, or, for a late
    /// keyframe, from `history`'s state at its time when it has a usable one: see the
    /// module documentation).
    pub fn apply_keyframe(
        &mut self,
        sim: &mut Simulation,
        map: &RegionMap,
        kf: &RegionKeyframe,
        history: &StateHistory,
    ) -> Result<Correction, SyncError> {
        if kf.region != self.region {
            return Err(SyncError::WrongRegion {
                region: self.region,
                got: kf.region,
            });
        }
        if self.last_keyframe.is_some_and(|k| kf.keyframe_id <= k) {
            return Ok(Correction::Stale);
        }
        let age = sim.time() - kf.sim_time;
        // Older than `max_age_s`: only against the history, and only on the region's own
        // tree (asked before the tree is matched, so that a keyframe that is not used
        // changes nothing: an old tree applied here would also invalidate the history).
        let old = age > self.config.max_age_s;
        let other_tree = || {
            sim_lattice::RegionState::from_bytes(&kf.tree_bits)
                .map_or(true, |theirs| theirs != map.state(sim.lattice(), kf.region))
        };
        if age > self.config.max_history_age_s
            || (old && (history.at(sim, kf.sim_time).is_none() || other_tree()))
        {
            self.last_keyframe = Some(kf.keyframe_id);
            return Ok(Correction::TooOld);
        }
        let matched = match_tree_and_nodes(sim, map, kf)?;
        let ahead = age.max(0.0);
        // The local state at the keyframe's time, when the keyframe is late and it was
        // recorded on this lattice (matching the tree above may have changed it).
        let then = if ahead > 0.5 * sim.options().dt {
            history.at(sim, kf.sim_time)
        } else {
            None
        };
        if old && then.is_none() {
            self.last_keyframe = Some(kf.keyframe_id);
            return Ok(Correction::TooOld);
        }
        let mut diffs = Vec::with_capacity(kf.positions.len());
        // Largest difference measured (m, m/s), and largest displacement to add (m).
        let (mut max_m, mut max_m_s, mut max_dx): (f64, f64, f64) = (0.0, 0.0, 0.0);
        // Differences measured at the keyframe's time need no rounding carried over.
        let measured_ahead = if then.is_some() { 0.0 } else { ahead };
        // The lattice nodes and a cut's virtual nodes alike: both are simulated here.
        for (i, j) in matched.dofs() {
            if sim.is_fixed(NodeId(j as u32)) {
                continue;
            }
            let Some(grid) = dof_grid(sim, j) else {
                continue;
            };
            let (x_k, v_k) = (V3::from(kf.positions[i]), V3::from(kf.velocities[i]));
            let (dx, dv, gap) = match then {
                // Older than `max_age_s`: the velocity difference of then says little of
                // now (a release's spring-back is over in 0.3 s); the position
                // difference alone is carried.
                Some((x, _)) if old && j < x.len() => {
                    let dx_k = x_k - x[j];
                    (dx_k, V3::zeros(), dx_k.norm())
                }
                Some((x, v)) if j < x.len() => {
                    let (dx_k, dv_k) = (x_k - x[j], v_k - v[j]);
                    (dx_k + dv_k * ahead, dv_k, dx_k.norm())
                }
                _ => {
                    let dx = x_k + v_k * ahead - sim.positions()[j];
                    (dx, v_k - sim.velocities()[j], dx.norm())
                }
            };
            max_m = max_m.max(gap);
            max_m_s = max_m_s.max(dv.norm());
            max_dx = max_dx.max(dx.norm());
            diffs.push((j, grid, dx, dv));
        }
        self.last_keyframe = Some(kf.keyframe_id);
        // The velocity's rounding is carried into the target over `ahead`.
        if max_m <= self.config.agree_m + self.config.agree_m_s * measured_ahead
            && max_m_s <= self.config.agree_m_s
        {
            self.pending.clear();
            self.steps_left = 0;
            return Ok(Correction::Agrees { max_m });
        }
        let steps = ((max_dx / self.config.max_step_m).ceil() as u32).max(self.config.min_steps);
        let share = 1.0 / f64::from(steps);
        self.pending_separation = separation_key(sim);
        self.pending = diffs
            .into_iter()
            .map(|(n, g, dx, dv)| (n, g, dx * share, dv * share))
            .collect();
        self.steps_left = steps;
        self.corrections += 1;
        Ok(Correction::Started { steps, max_m })
    }

    /// Before a step: adds this step's share of the correction under way. Returns the
    /// largest displacement added (m; ≤ [`HybridConfig::max_step_m`] by construction).
    pub fn drive(&mut self, sim: &mut Simulation) -> f64 {
        if self.steps_left == 0 {
            return 0.0;
        }
        self.steps_left -= 1;
        // Virtual nodes' entries, once the separation changed, are no longer theirs.
        let virtual_from = match self.pending_separation {
            Some((capacity, _)) if separation_key(sim) != self.pending_separation => capacity,
            _ => usize::MAX,
        };
        let mut moved: f64 = 0.0;
        for &(d, g, dx, dv) in &self.pending {
            if d >= virtual_from || dof_grid(sim, d) != Some(g) {
                continue;
            }
            let (x, v) = (sim.positions()[d], sim.velocities()[d]);
            sim.set_dof_state(d, x + dx, v + dv);
            moved = moved.max(dx.norm());
        }
        if self.steps_left == 0 {
            self.pending.clear();
        }
        // The step that follows updates the embedded surfaces.
        moved
    }
}

/// The cuts' separation as a correction checks it: lattice capacity and dof count.
fn separation_key(sim: &Simulation) -> Option<(usize, usize)> {
    sim.separation().map(|s| (s.capacity, s.dof_count()))
}
