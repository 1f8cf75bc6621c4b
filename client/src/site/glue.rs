//! Adapters between the site loop and the engine's tools, contact and sync state.
//! PROVISIONAL: replaced by the sim-core interaction and sync modules as they land.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;

use anyhow::{Context, Result};
use nalgebra::{UnitQuaternion, Vector3};
use sim_core::Simulation;
use sim_core::sim_scene::ToolScript;
use sim_core::sync::{
    self, RegionKeyframe, RegionMap, RegionTreeDelta, SiteSync, SyncConfig, SyncFrame, SyncStrategy,
};
use tracing::warn;

use super::Strategy;
use crate::output::ToolFrame;

type V3 = Vector3<f64>;

/// The local tool's input for one step.
#[derive(Clone, Copy, Debug)]
pub struct LocalToolInput {
    pub position: V3,
    pub orientation: UnitQuaternion<f64>,
    pub jaw: f64,
}

pub struct Tools {
    names: Vec<String>,
    local: Option<usize>,
    poses: Vec<Option<LocalToolInput>>,
    node_forces: Vec<V3>,
}

impl Tools {
    pub fn new(sim: &Simulation, local: Option<&str>, _strategy: Strategy) -> Result<Self> {
        let names: Vec<String> = sim
            .scene()
            .scene
            .tools
            .iter()
            .map(|t| t.name.clone())
            .collect();
        let local = local.and_then(|n| names.iter().position(|m| m == n));
        Ok(Tools {
            poses: vec![None; names.len()],
            names,
            local,
            node_forces: Vec::new(),
        })
    }
    pub fn local_input(&self, script: Option<&ToolScript>, t: f64) -> Option<LocalToolInput> {
        let name = &self.names[self.local?];
        let s = script?;
        if t < 0.0 || t > s.duration() {
            return None;
        }
        s.sample(name, t).map(|p| LocalToolInput {
            position: p.position,
            orientation: p.orientation,
            jaw: p.jaw,
        })
    }
    pub fn before_step(
        &mut self,
        _sim: &mut Simulation,
        local: Option<LocalToolInput>,
    ) -> Result<Vec<u32>> {
        if let (Some(i), Some(p)) = (self.local, local) {
            self.poses[i] = Some(p);
        }
        Ok(Vec::new())
    }
    pub fn remote_pose(&mut self, p: &proto::ToolPose) {
        if let Some(slot) = self.poses.get_mut(p.tool as usize) {
            let q = p.orientation.map(f64::from);
            *slot = Some(LocalToolInput {
                position: V3::new(
                    p.position[0].into(),
                    p.position[1].into(),
                    p.position[2].into(),
                ),
                orientation: sim_core::sim_scene::script::quat_wxyz(q),
                jaw: p.jaw_rad.into(),
            });
        }
    }
    pub fn local_force(&self) -> V3 {
        V3::zeros()
    }
    pub fn local_pose_message(&self, site: u16, t: f64) -> Option<proto::ToolPose> {
        let i = self.local?;
        let p = self.poses[i]?;
        let q = sim_core::sim_scene::script::wxyz(&p.orientation);
        Some(proto::ToolPose {
            site,
            tool: i as u8,
            sim_time_s: t,
            position: [
                p.position.x as f32,
                p.position.y as f32,
                p.position.z as f32,
            ],
            orientation: q.map(|v| v as f32),
            jaw_rad: p.jaw as f32,
            velocity: [0.0; 3],
            angular_velocity: [0.0; 3],
        })
    }
    pub fn frames(&self) -> Vec<ToolFrame> {
        self.names
            .iter()
            .zip(&self.poses)
            .filter_map(|(n, p)| {
                p.map(|p| ToolFrame {
                    name: n.clone(),
                    position: p.position,
                    orientation: p.orientation,
                    jaw: p.jaw,
                    force: V3::zeros(),
                })
            })
            .collect()
    }
    pub fn node_forces(&self) -> &[V3] {
        &self.node_forces
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
}

impl SyncState {
    pub fn new(sim: &Simulation, strategy: Strategy) -> Self {
        let strategy = match strategy {
            Strategy::Keyframe => SyncStrategy::Keyframe,
            // Every frame: one full copy of the organ per simulation step.
            Strategy::FullState => SyncStrategy::FullState { every_steps: 1 },
            Strategy::InputOnly => SyncStrategy::InputOnly,
        };
        SyncState {
            sync: SiteSync::new(
                strategy,
                RegionMap::for_simulation(sim),
                SyncConfig::default(),
            ),
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

    /// Applies a keyframe from another site. Returns whether it was applied (and should
    /// be acknowledged).
    pub fn receive(&mut self, sim: &mut Simulation, kf: &proto::RegionKeyframe) -> Result<bool> {
        if self.sync.strategy == SyncStrategy::InputOnly {
            return Ok(false);
        }
        let n = kf.nodes.len();
        let frame = SyncFrame::Keyframe(RegionKeyframe {
            region: kf.region,
            keyframe_id: kf.keyframe,
            sim_time: kf.sim_time_s,
            tree_bits: kf.tree_bits.clone(),
            positions: (0..n).map(|i| kf.nodes.position(i)).collect(),
            velocities: (0..n).map(|i| kf.nodes.velocity(i)).collect(),
        });
        match self.sync.on_frame(sim, &frame) {
            Ok(ack) => Ok(ack.is_some() || kf.region == sync::FULL_STATE_REGION),
            Err(e) => {
                warn!(region = kf.region, keyframe = kf.keyframe, error = %e, "keyframe not applied");
                Ok(false)
            }
        }
    }

    /// Applies a tree-state delta from another site; returns whether it was applied.
    pub fn receive_delta(&mut self, sim: &mut Simulation, d: &proto::TreeDelta) -> bool {
        let frame = SyncFrame::TreeDelta(RegionTreeDelta {
            region: d.region,
            sim_time: d.sim_time_s,
            base_keyframe: d.base_keyframe,
            xor_bits: d.xor_bits.clone(),
        });
        match self.sync.on_frame(sim, &frame) {
            Ok(_) => true,
            Err(e) => {
                warn!(region = d.region, error = %e, "tree delta not applied");
                false
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
        match owner {
            Some(o) if Some(o) == me => self.sync.on_grant(region),
            Some(_) => self.sync.on_remote_grant(region),
            None => self.sync.on_remote_release(region),
        }
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

pub struct HapticLoop;

impl HapticLoop {
    pub fn start() -> Self {
        HapticLoop
    }
    pub fn publish(&self, _tools: &Tools) {}
    pub fn stop(self) -> (f64, f64) {
        (0.0, 0.0)
    }
}
