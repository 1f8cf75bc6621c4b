//! Adapters between the site loop and the engine's tools, contact and sync state.
//! PROVISIONAL: replaced by the sim-core interaction and sync modules as they land.

use std::path::Path;

use anyhow::Result;
use nalgebra::{UnitQuaternion, Vector3};
use sim_core::Simulation;
use sim_core::sim_scene::ToolScript;

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

pub struct SyncState;

impl SyncState {
    pub fn new(_sim: &Simulation, _strategy: Strategy) -> Self {
        SyncState
    }
    pub fn receive(&mut self, _sim: &mut Simulation, _kf: &proto::RegionKeyframe) -> Result<bool> {
        Ok(false)
    }
    pub fn set_owner(&mut self, _region: u32, _owner: Option<u16>, _me: Option<u16>) {}
    pub fn keyframe(
        &mut self,
        _sim: &Simulation,
        _region: u32,
        _me: u16,
    ) -> Option<proto::RegionKeyframe> {
        None
    }
    pub fn drive(&mut self, _sim: &mut Simulation) {}
    pub fn outgoing(
        &mut self,
        _sim: &Simulation,
        _owned: impl Iterator<Item = u32>,
        _me: u16,
    ) -> Vec<proto::RegionKeyframe> {
        Vec::new()
    }
}

pub struct Recorder;

impl Recorder {
    pub fn new(_sim: &Simulation, _interval: f64) -> Self {
        Recorder
    }
    pub fn record(&mut self, _sim: &Simulation) {}
    pub fn write(&self, _path: &Path, _hash: &str) -> Result<()> {
        Ok(())
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
