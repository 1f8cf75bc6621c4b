//! A device that plays a tool script and records the forces it is sent.

use std::time::Duration;

use nalgebra::{UnitQuaternion, Vector3};
use sim_scene::{ToolPose, ToolScript};

use super::{HapticDevice, HapticError, ToolInput};

/// One force the loop sent to a [`ScriptedDevice`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AppliedForce {
    /// Loop time of the read that preceded it.
    pub t: Duration,
    /// The tip position the device reported at that read, m.
    pub position: Vector3<f64>,
    /// Force, N.
    pub force: Vector3<f64>,
    /// Torque, N·m.
    pub torque: Vector3<f64>,
}

/// Plays one tool's track of a [`ToolScript`] by loop time (`script time = t · speed +
/// offset`, holding the first/last pose outside the script), and records every force
/// it receives (up to a limit, default 10 minutes at 1 kHz).
#[derive(Debug, Clone)]
pub struct ScriptedDevice {
    name: String,
    script: ToolScript,
    tool: String,
    speed: f64,
    offset: f64,
    last: ToolInput,
    forces: Vec<AppliedForce>,
    limit: usize,
    dropped: u64,
}

impl ScriptedDevice {
    /// Plays the track of `tool` (error if the script has none).
    pub fn new(script: ToolScript, tool: &str) -> Result<Self, HapticError> {
        if !script.tracks.contains_key(tool) {
            return Err(HapticError::NoTrack {
                file: script.title.clone().unwrap_or_else(|| "script".into()),
                tool: tool.into(),
                available: script.tools().collect::<Vec<_>>().join(", "),
            });
        }
        Ok(ScriptedDevice {
            name: format!("scripted:{tool}"),
            script,
            tool: tool.into(),
            speed: 1.0,
            offset: 0.0,
            last: ToolInput::default(),
            forces: Vec::with_capacity(4096),
            limit: 600_000,
            dropped: 0,
        })
    }

    /// Loads a script file and plays `tool` (default: the script's first tool).
    pub fn load(
        path: impl AsRef<std::path::Path>,
        tool: Option<&str>,
    ) -> Result<Self, HapticError> {
        let path = path.as_ref();
        let script = ToolScript::load(path)?;
        let tool = match tool {
            Some(t) => t.to_string(),
            None => script.tools().next().unwrap_or_default().to_string(),
        };
        Self::new(script, &tool).map_err(|e| match e {
            HapticError::NoTrack {
                tool, available, ..
            } => HapticError::NoTrack {
                file: path.display().to_string(),
                tool,
                available,
            },
            e => e,
        })
    }

    /// A device that holds one pose forever.
    pub fn stationary(tool: &str, pose: ToolPose) -> Self {
        let mut script = ToolScript::default();
        script.tracks.insert(
            tool.into(),
            vec![sim_scene::ToolWaypoint {
                t: 0.0,
                pose,
                label: None,
            }],
        );
        Self::new(script, tool).expect("track inserted")
    }

    /// A device that holds `position` with the identity orientation and closed jaws.
    pub fn at(position: Vector3<f64>) -> Self {
        Self::stationary(
            "probe",
            ToolPose {
                position,
                orientation: UnitQuaternion::identity(),
                jaw: 0.0,
            },
        )
    }

    /// Plays at `speed` times real time, starting at script time `offset` s.
    pub fn with_timing(mut self, speed: f64, offset: f64) -> Self {
        self.speed = speed;
        self.offset = offset;
        self
    }

    /// Keeps at most `n` force records (later ones are counted in `dropped_records`).
    pub fn with_record_limit(mut self, n: usize) -> Self {
        self.limit = n;
        self
    }

    /// The script being played.
    pub fn script(&self) -> &ToolScript {
        &self.script
    }

    /// The pose at loop time `t`.
    pub fn pose_at(&self, t: Duration) -> ToolPose {
        self.script
            .sample(&self.tool, t.as_secs_f64() * self.speed + self.offset)
            .expect("track exists")
    }

    /// Forces received, in order.
    pub fn forces(&self) -> &[AppliedForce] {
        &self.forces
    }

    /// Takes the recorded forces out.
    pub fn take_forces(&mut self) -> Vec<AppliedForce> {
        std::mem::take(&mut self.forces)
    }

    /// Forces not recorded because of the limit.
    pub fn dropped_records(&self) -> u64 {
        self.dropped
    }
}

impl HapticDevice for ScriptedDevice {
    fn read(&mut self, t: Duration) -> ToolInput {
        let p = self.pose_at(t);
        self.last = ToolInput {
            time: t,
            position: p.position,
            orientation: p.orientation,
            jaw: p.jaw,
            buttons: 0,
        };
        self.last
    }

    fn apply(&mut self, force: Vector3<f64>, torque: Vector3<f64>) {
        if self.forces.len() < self.limit {
            self.forces.push(AppliedForce {
                t: self.last.time,
                position: self.last.position,
                force,
                torque,
            });
        } else {
            self.dropped += 1;
        }
    }

    fn name(&self) -> &str {
        &self.name
    }
}
