//! Adapters between the site loop and the engine: the scene's tools and their contact
//! (sim-core's `Interaction`), the sync state (sim-core's `SiteSync`) with its conversion
//! to and from `proto` messages and its pacing by simulated time, and the surface
//! recorder.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::Path;

use anyhow::{Context, Result};
use nalgebra::Vector3;
use sim_core::contact::LocalModel;
use sim_core::sim_scene::ToolScript;
use sim_core::sync::{
    self, RegionKeyframe, RegionMap, RegionTreeDelta, SiteSync, SyncConfig, SyncFrame, SyncStrategy,
};
use sim_core::{Interaction, Simulation, ToolInput};
use tracing::warn;

use super::Strategy;
use crate::output::ToolFrame;

type V3 = Vector3<f64>;

/// The scene's tools and their contact with the organ (sim-core's [`Interaction`]).
///
/// The local tool follows this site's input. Remote tools follow their owners' pose
/// datagrams; under the input-only strategy they touch the local organ too, otherwise
/// they are only drawn (their effect arrives with the keyframes).
pub struct Tools {
    interaction: Interaction,
    local: Option<usize>,
    remote_contact: bool,
    /// Poses of each tool from other sites, by their simulation time.
    remote_track: Vec<PoseTrack>,
    /// Each remote pose sampled at this step's simulation time (what is simulated and
    /// drawn).
    remote: Vec<Option<ToolInput>>,
    /// Whether the local tool is being driven this step (its script is running).
    local_active: bool,
    /// Touch radius around contacts for region ownership (m).
    touch_radius: f64,
}

impl Tools {
    pub fn new(sim: &Simulation, local: Option<&str>, strategy: Strategy) -> Result<Self> {
        let interaction = Interaction::new(sim);
        let local = match local {
            Some(name) => Some(
                interaction
                    .tools
                    .index(name)
                    .with_context(|| format!("tool {name:?} is not in the scene"))?,
            ),
            None => None,
        };
        Ok(Tools {
            remote: vec![None; interaction.tools.len()],
            remote_track: vec![PoseTrack::default(); interaction.tools.len()],
            interaction,
            local,
            remote_contact: strategy == Strategy::InputOnly,
            local_active: false,
            touch_radius: 2.0 * sim.lattice().params().cell,
        })
    }

    /// The local tool's input at script time `t` (s), while the script runs.
    pub fn local_input(&self, script: Option<&ToolScript>, t: f64) -> Option<ToolInput> {
        let tool = &self.interaction.tools.tools[self.local?];
        let s = script?;
        if t < 0.0 || t > s.duration() {
            return None;
        }
        // A script with one track drives whichever tool it is given to.
        s.sample(&tool.name, t)
            .or_else(|| s.tools().next().and_then(|n| s.sample(n, t)))
            .map(|p| ToolInput::from(&p))
    }

    /// Sets every tool's input, runs contact (and tool-following adaptivity) before the
    /// step, and returns the regions the local tool touches.
    pub fn before_step(
        &mut self,
        sim: &mut Simulation,
        local: Option<ToolInput>,
        sync: &SyncState,
    ) -> Result<Vec<u32>> {
        self.local_active = local.is_some();
        // A pose stamped t + dt is the input its site used for the step from t: sample
        // the remote tracks there, so that a follower behind the owner in simulated time
        // replays the owner's tool as it was then rather than its latest pose.
        let at = sim.time() + sim.options().dt;
        for (slot, track) in self.remote.iter_mut().zip(&self.remote_track) {
            *slot = track.sample(at);
        }
        let inputs: Vec<ToolInput> = self
            .interaction
            .tools
            .tools
            .iter()
            .enumerate()
            .map(|(i, tool)| {
                let keep = ToolInput {
                    pose: *tool.pose(),
                    jaw: tool.jaw(),
                };
                if Some(i) == self.local {
                    // Between its own acts, a site's tool follows whoever else drives it
                    // (input-only: every site simulates every tool).
                    match (local, self.remote_contact) {
                        (Some(l), _) => l,
                        (None, true) => self.remote[i].unwrap_or(keep),
                        (None, false) => keep,
                    }
                } else if self.remote_contact {
                    self.remote[i].unwrap_or(keep)
                } else {
                    keep
                }
            })
            .collect();
        self.interaction.before_step(sim, &inputs)?;
        let Some(i) = self.local else {
            return Ok(Vec::new());
        };
        let st = &self.interaction.state().tools[i];
        if st.contacts.is_empty() && st.grasped == 0 {
            return Ok(Vec::new());
        }
        // Every region within reach of what the tool touches or holds: contact points,
        // grasped points and the tip, inflated by one lattice cell.
        let tip = self.interaction.tools.tools[i].tip();
        let (mut lo, mut hi) = (tip, tip);
        for p in st
            .contacts
            .iter()
            .map(|c| &c.point)
            .chain(&st.grasped_points)
        {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        let centre = 0.5 * (lo + hi);
        let radius = 0.5 * (hi - lo).norm() + self.touch_radius;
        Ok(sync.regions_near(sim, &centre, radius))
    }

    /// A pose of a tool from another site (held until our simulation time reaches it).
    pub fn remote_pose(&mut self, p: &proto::ToolPose) {
        if let Some(track) = self.remote_track.get_mut(p.tool as usize) {
            let q = p.orientation.map(f64::from);
            track.insert(
                p.sim_time_s,
                ToolInput::new(
                    V3::new(
                        p.position[0].into(),
                        p.position[1].into(),
                        p.position[2].into(),
                    ),
                    sim_core::sim_scene::script::quat_wxyz(q),
                    p.jaw_rad.into(),
                ),
            );
        }
    }

    /// Whether the local tool was driven in the last step (its site then leads).
    pub fn local_active(&self) -> bool {
        self.local_active
    }

    /// Force of the tissue on the local tool (N).
    pub fn local_force(&self) -> V3 {
        self.local
            .and_then(|i| self.interaction.state().tools.get(i))
            .map_or(V3::zeros(), |t| t.force)
    }

    /// Index of the local tool in the scene's tools.
    pub fn local_index(&self) -> Option<usize> {
        self.local
    }

    /// Name of the local tool.
    pub fn local_name(&self) -> Option<&str> {
        let i = self.local?;
        Some(self.interaction.tools.tools[i].name.as_str())
    }

    /// Whether the local tool holds tissue (its haptic model is then bilateral).
    pub fn local_grasped(&self) -> bool {
        self.local
            .and_then(|i| self.interaction.state().tools.get(i))
            .is_some_and(|t| t.grasped > 0)
    }

    /// Torque of the tissue on the local tool about its tip (N·m).
    pub fn local_torque(&self) -> V3 {
        self.local
            .and_then(|i| self.interaction.state().tools.get(i))
            .map_or(V3::zeros(), |t| t.torque)
    }

    /// The local tool's pose and its contact's local linear model (haptics).
    pub fn local_haptic(&self) -> Option<(ToolInput, LocalModel)> {
        let i = self.local?;
        let tool = &self.interaction.tools.tools[i];
        let model = self.interaction.state().tools.get(i)?.local;
        Some((
            ToolInput {
                pose: *tool.pose(),
                jaw: tool.jaw(),
            },
            model,
        ))
    }

    /// The local tool's pose for the others, while it is being driven.
    pub fn local_pose_message(&self, site: u16, t: f64) -> Option<proto::ToolPose> {
        if !self.local_active {
            return None;
        }
        let i = self.local?;
        let tool = &self.interaction.tools.tools[i];
        let pose = tool.pose();
        let p = pose.translation.vector;
        let q = sim_core::sim_scene::script::wxyz(&pose.rotation);
        let v = tool.velocity();
        let w = tool.angular_velocity();
        Some(proto::ToolPose {
            site,
            tool: i as u8,
            sim_time_s: t,
            position: [p.x as f32, p.y as f32, p.z as f32],
            orientation: q.map(|v| v as f32),
            jaw_rad: tool.jaw() as f32,
            velocity: [v.x as f32, v.y as f32, v.z as f32],
            angular_velocity: [w.x as f32, w.y as f32, w.z as f32],
        })
    }

    /// Every tool as drawn: local and contacting tools at their simulated pose, remote
    /// tools at their owners' pose for our simulated time (sampled in `before_step`).
    pub fn frames(&self) -> Vec<ToolFrame> {
        let st = self.interaction.state();
        self.interaction
            .tools
            .tools
            .iter()
            .enumerate()
            .map(|(i, tool)| {
                let (pose, jaw) = match self.remote[i] {
                    Some(r) if Some(i) != self.local && !self.remote_contact => (r.pose, r.jaw),
                    _ => (*tool.pose(), tool.jaw()),
                };
                ToolFrame {
                    name: tool.name.clone(),
                    position: pose.translation.vector,
                    orientation: pose.rotation,
                    jaw,
                    force: st.tools.get(i).map_or(V3::zeros(), |t| t.force),
                }
            })
            .collect()
    }

    /// Contact forces on the lattice nodes (N, by node id).
    pub fn node_forces(&self) -> &[V3] {
        &self.interaction.state().node_force
    }
}

/// Poses of one remote tool by simulation time, sampled by linear interpolation (slerp
/// for the orientation); before the first or after the newest pose, the nearest one.
#[derive(Clone, Debug, Default)]
struct PoseTrack {
    poses: VecDeque<(f64, ToolInput)>,
}

impl PoseTrack {
    /// Simulated seconds of poses kept behind the newest (covers any playout lag).
    const KEEP_S: f64 = 2.0;

    fn insert(&mut self, t: f64, input: ToolInput) {
        // Datagrams may be reordered: keep the track sorted by time.
        let i = self.poses.partition_point(|(pt, _)| *pt < t);
        match self.poses.get_mut(i) {
            Some(slot) if slot.0 == t => slot.1 = input,
            _ => self.poses.insert(i, (t, input)),
        }
        let newest = self.poses.back().map_or(t, |p| p.0);
        while self.poses.len() > 2
            && self
                .poses
                .front()
                .is_some_and(|p| newest - p.0 > Self::KEEP_S)
        {
            self.poses.pop_front();
        }
    }

    fn sample(&self, t: f64) -> Option<ToolInput> {
        let (first, last) = (self.poses.front()?, self.poses.back()?);
        if t <= first.0 {
            return Some(first.1);
        }
        if t >= last.0 {
            return Some(last.1);
        }
        let i = self.poses.partition_point(|(pt, _)| *pt <= t);
        let ((t0, a), (t1, b)) = (self.poses[i - 1], self.poses[i]);
        let s = ((t - t0) / (t1 - t0)).clamp(0.0, 1.0);
        let position = a
            .pose
            .translation
            .vector
            .lerp(&b.pose.translation.vector, s);
        let rotation = a
            .pose
            .rotation
            .try_slerp(&b.pose.rotation, s, 1e-9)
            .unwrap_or(if s < 0.5 {
                a.pose.rotation
            } else {
                b.pose.rotation
            });
        Some(ToolInput {
            pose: nalgebra::Isometry3::from_parts(position.into(), rotation),
            jaw: a.jaw + (b.jaw - a.jaw) * s,
        })
    }
}

/// The site's sync state (sim-core's [`SiteSync`]) and its conversion to and from the
/// wire messages of `proto`.
pub struct SyncState {
    sync: SiteSync,
    /// Keyframe ids acknowledged per region and receiving site.
    acked: HashMap<u32, HashMap<u16, u64>>,
    /// Sites that receive our frames (all others in the session).
    receivers: BTreeSet<u16>,
    me: u16,
    /// Keyframes from sites ahead of us in simulated time, waiting for our clock.
    pending: Vec<SyncFrame>,
    /// Regions released by their owner, and the simulated time of the release: the
    /// release takes effect once our clock reaches it and the owner's last frames are
    /// played.
    deferred_release: BTreeMap<u32, f64>,
}

impl SyncState {
    pub fn new(sim: &Simulation, strategy: Strategy) -> Self {
        let strategy = match strategy {
            Strategy::Keyframe => SyncStrategy::Keyframe,
            // Every frame: one full copy of the organ per simulation step.
            Strategy::FullState => SyncStrategy::FullState { every_steps: 1 },
            Strategy::InputOnly => SyncStrategy::InputOnly,
        };
        // Extrapolation stays gentle: tissue under a surgeon's hand does not accelerate
        // at tens of m/s², and a receiver never extrapolates far (see `receive`).
        let config = SyncConfig {
            max_accel_m_s2: 5.0,
            max_extrapolation_s: 0.06,
            // At most ~33 keyframes per second per region.
            min_interval_s: 0.03,
            ..SyncConfig::default()
        };
        SyncState {
            sync: SiteSync::new(strategy, RegionMap::for_simulation(sim), config),
            pending: Vec::new(),
            deferred_release: BTreeMap::new(),
            acked: HashMap::new(),
            receivers: BTreeSet::new(),
            me: 0,
        }
    }

    /// Our site id and the other sites of the session (they acknowledge our keyframes).
    pub fn set_sites(&mut self, me: u16, others: impl IntoIterator<Item = u16>) {
        self.me = me;
        self.receivers = others.into_iter().filter(|s| *s != me).collect();
    }

    /// Regions near the deformed point (m) within `radius` (m).
    pub fn regions_near(&self, sim: &Simulation, p: &V3, radius: f64) -> Vec<u32> {
        self.sync.map.regions_near_deformed(sim, p, radius)
    }

    /// Takes a keyframe from another site. Frames from a site whose simulation is ahead of
    /// ours wait until our simulated time reaches them (the simulation-time difference
    /// between sites paces their application), so a receiver never extrapolates
    /// backwards. Returns the keyframes applied now, to acknowledge.
    pub fn receive(&mut self, sim: &mut Simulation, kf: proto::RegionKeyframe) -> Vec<(u32, u64)> {
        if self.sync.strategy == SyncStrategy::InputOnly {
            return Vec::new();
        }
        let n = kf.nodes.len();
        self.pending.push(SyncFrame::Keyframe(RegionKeyframe {
            region: kf.region,
            keyframe_id: kf.keyframe,
            sim_time: kf.sim_time_s,
            tree_bits: kf.tree_bits,
            positions: (0..n).map(|i| kf.nodes.position(i)).collect(),
            velocities: (0..n).map(|i| kf.nodes.velocity(i)).collect(),
        }));
        self.apply_due(sim)
    }

    /// Takes a tree-state delta from another site (paced like keyframes).
    pub fn receive_delta(&mut self, sim: &mut Simulation, d: proto::TreeDelta) -> Vec<(u32, u64)> {
        if self.sync.strategy == SyncStrategy::InputOnly {
            return Vec::new();
        }
        self.pending.push(SyncFrame::TreeDelta(RegionTreeDelta {
            region: d.region,
            sim_time: d.sim_time_s,
            base_keyframe: d.base_keyframe,
            xor_bits: d.xor_bits,
        }));
        self.apply_due(sim)
    }

    /// Applies the pending frames that our simulated time has reached, oldest first, and
    /// the releases whose time has come; then holds each region's next pending keyframe
    /// for interpolation.
    pub fn apply_due(&mut self, sim: &mut Simulation) -> Vec<(u32, u64)> {
        if self.pending.is_empty() && self.deferred_release.is_empty() {
            return Vec::new();
        }
        let now = sim.time() + 0.5 * sim.options().dt;
        let time = |f: &SyncFrame| match f {
            SyncFrame::Keyframe(k) => k.sim_time,
            SyncFrame::TreeDelta(d) => d.sim_time,
        };
        let (mut due, later): (Vec<SyncFrame>, Vec<SyncFrame>) = std::mem::take(&mut self.pending)
            .into_iter()
            .partition(|f| time(f) <= now);
        self.pending = later;
        due.sort_by(|a, b| time(a).total_cmp(&time(b)));
        let mut applied = Vec::new();
        for frame in due {
            tracing::debug!(
                region = frame.region(),
                t = time(&frame),
                now = sim.time(),
                "apply frame"
            );
            match self.sync.on_frame(sim, &frame) {
                Ok(Some(id)) => applied.push((frame.region(), id)),
                Ok(None) => tracing::debug!(
                    region = frame.region(),
                    "sync frame ignored (stale, owned or released)"
                ),
                Err(e) => warn!(region = frame.region(), error = %e, "sync frame not applied"),
            }
        }
        let done: Vec<u32> = self
            .deferred_release
            .iter()
            .filter(|&(r, at)| *at <= now && !self.pending.iter().any(|f| f.region() == *r))
            .map(|(r, _)| *r)
            .collect();
        for r in done {
            self.deferred_release.remove(&r);
            self.sync.on_remote_release(r);
        }
        self.hold_next_keyframes(sim);
        applied
    }

    /// Offers each region's earliest pending frame, if it is a keyframe, to sim-core as
    /// the next keyframe to interpolate towards (a tree delta first changes the nodes).
    fn hold_next_keyframes(&mut self, sim: &Simulation) {
        let mut earliest: BTreeMap<u32, &SyncFrame> = BTreeMap::new();
        for f in &self.pending {
            let t = |f: &SyncFrame| match f {
                SyncFrame::Keyframe(k) => k.sim_time,
                SyncFrame::TreeDelta(d) => d.sim_time,
            };
            let e = earliest.entry(f.region()).or_insert(f);
            if t(f) < t(e) {
                *e = f;
            }
        }
        for f in earliest.into_values() {
            if let SyncFrame::Keyframe(kf) = f {
                self.sync.hold_next(sim, kf);
            }
        }
    }

    /// A receiver acknowledged one of our keyframes.
    pub fn on_ack(&mut self, ack: &proto::KeyframeAck) {
        let e = self
            .acked
            .entry(ack.region)
            .or_default()
            .entry(ack.site)
            .or_insert(0);
        *e = (*e).max(ack.keyframe);
    }

    /// Ownership of `region` changed to `owner`.
    pub fn set_owner(&mut self, region: u32, owner: Option<u16>, me: Option<u16>) {
        tracing::debug!(region, ?owner, ?me, "ownership");
        match owner {
            Some(o) if Some(o) == me => self.sync.on_grant(region),
            Some(_) => self.sync.on_remote_grant(region),
            None => self.release_remote(region, None, me),
        }
        if owner.is_some() {
            self.deferred_release.remove(&region);
        }
    }

    /// Another site released `region` at about its simulated time `at` (s; `None`:
    /// unknown). The release takes effect, in `apply_due`, once our clock reaches `at`
    /// and the owner's last frames, which may still be waiting for our clock, are played.
    pub fn release_remote(&mut self, region: u32, at: Option<f64>, me: Option<u16>) {
        tracing::debug!(region, ?at, ?me, "remote release");
        self.deferred_release
            .insert(region, at.unwrap_or(f64::NEG_INFINITY));
    }

    /// We release `region`: the final keyframe, if the strategy sends one.
    pub fn release(&mut self, sim: &Simulation, region: u32) -> Option<Outgoing> {
        let frame = self.sync.release(sim, region)?;
        self.acked.remove(&region);
        self.to_wire(frame)
    }

    /// Before the step: remote regions follow their owners.
    pub fn drive(&mut self, sim: &mut Simulation) {
        self.sync.before_step(sim);
    }

    /// After the step: what we owe the others for the regions we own.
    pub fn outgoing(&mut self, sim: &Simulation) -> Vec<Outgoing> {
        let acked = &self.acked;
        let receivers = &self.receivers;
        // A delta may reference only a keyframe every receiver has acknowledged.
        let base = |region: u32| -> Option<u64> {
            let per_site = acked.get(&region)?;
            receivers
                .iter()
                .map(|s| per_site.get(s).copied())
                .min()
                .flatten()
        };
        let frames = self.sync.after_step(sim, base);
        frames.into_iter().filter_map(|f| self.to_wire(f)).collect()
    }

    fn to_wire(&self, frame: SyncFrame) -> Option<Outgoing> {
        match frame {
            SyncFrame::Keyframe(kf) => {
                let ids: Vec<u32> = (0..kf.positions.len() as u32).collect();
                let nodes = match proto::QuantisedNodes::encode_default(
                    &ids,
                    &kf.positions,
                    &kf.velocities,
                ) {
                    Ok(n) => n,
                    Err(e) => {
                        warn!(region = kf.region, error = %e, "keyframe not quantisable; not sent");
                        return None;
                    }
                };
                Some(Outgoing::Keyframe(proto::RegionKeyframe {
                    region: kf.region,
                    keyframe: kf.keyframe_id,
                    owner: self.me,
                    sim_time_s: kf.sim_time,
                    epoch: 0,
                    tree_bits: kf.tree_bits,
                    nodes,
                }))
            }
            SyncFrame::TreeDelta(d) => Some(Outgoing::Delta(proto::TreeDelta {
                region: d.region,
                site: self.me,
                epoch: 0,
                sim_time_s: d.sim_time,
                base_keyframe: d.base_keyframe,
                xor_bits: d.xor_bits,
            })),
        }
    }
}

/// A frame for the link: keyframes go on their own stream, deltas as datagrams.
pub enum Outgoing {
    Keyframe(proto::RegionKeyframe),
    Delta(proto::TreeDelta),
}

/// Surface recordings at fixed simulated-time marks (sim-core's `.surf` format).
pub struct Recorder(sync::SurfaceRecorder);

impl Recorder {
    pub fn new(sim: &Simulation, interval: f64) -> Self {
        Recorder(sync::SurfaceRecorder::new(sim, interval))
    }
    pub fn record(&mut self, sim: &Simulation) {
        self.0.record(sim);
    }
    pub fn write(&self, path: &Path) -> Result<()> {
        let file =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        self.0
            .recording()
            .write_to(std::io::BufWriter::new(file))
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// The site's 1 kHz haptic loop, its device and teaching mode (`site/haptics.rs`).
pub use super::haptics::{DeviceSpec, HapticLoop, HapticSummary, Teaching};

#[cfg(test)]
mod tests {
    use super::*;

    fn input(x: f64, jaw: f64) -> ToolInput {
        ToolInput::new(
            V3::new(x, 0.0, 0.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, x),
            jaw,
        )
    }

    #[test]
    fn pose_track_samples_by_simulated_time() {
        let mut track = PoseTrack::default();
        assert!(track.sample(0.0).is_none());
        // Out of order, as datagrams may arrive.
        track.insert(0.2, input(0.2, 0.4));
        track.insert(0.1, input(0.1, 0.2));
        let mid = track.sample(0.15).unwrap();
        assert!((mid.pose.translation.vector.x - 0.15).abs() < 1e-12);
        assert!((mid.jaw - 0.3).abs() < 1e-12);
        assert!((mid.pose.rotation.angle() - 0.15).abs() < 1e-9);
        // Before the first and after the newest pose: the nearest one (hold).
        assert_eq!(track.sample(0.0).unwrap().jaw, 0.2);
        assert_eq!(track.sample(9.0).unwrap().jaw, 0.4);
        // Old poses are dropped beyond the kept window.
        track.insert(5.0, input(5.0, 1.0));
        assert_eq!(track.poses.len(), 2);
    }
}
