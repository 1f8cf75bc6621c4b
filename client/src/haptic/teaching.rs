//! Teaching mode: record an instructor's tool trajectory as a tool script, and replay it
//! on a trainee's device as a guiding spring toward the recorded tip position.

use std::path::Path;
use std::time::Duration;

use nalgebra::Vector3;
use sim_scene::{ToolPose, ToolScript, ToolWaypoint};

use super::{HapticError, ToolInput};

/// Records device inputs into a [`ToolScript`] track, one pose per `interval` (times
/// relative to the first input). Feed it from the haptic loop
/// ([`HapticHandle::start_recording`](super::HapticHandle::start_recording)) or from any
/// thread polling [`InputReader`](super::InputReader).
#[derive(Debug, Clone)]
pub struct TeachingRecorder {
    tool: String,
    title: Option<String>,
    interval: Duration,
    t0: Option<Duration>,
    last_kept: Option<Duration>,
    last_seen: Option<ToolInput>,
    waypoints: Vec<ToolWaypoint>,
}

impl TeachingRecorder {
    /// Records poses of `tool` every `interval` (at least 1 ms, so that the script's
    /// 0.1 ms time rounding keeps times strictly increasing).
    pub fn new(tool: &str, interval: Duration) -> Result<Self, HapticError> {
        if interval < Duration::from_millis(1) {
            return Err(HapticError::Invalid {
                key: "interval",
                problem: format!("{interval:?} is below 1 ms"),
            });
        }
        if tool.is_empty() {
            return Err(HapticError::Invalid {
                key: "tool",
                problem: "empty tool name".into(),
            });
        }
        Ok(TeachingRecorder {
            tool: tool.into(),
            title: None,
            interval,
            t0: None,
            last_kept: None,
            last_seen: None,
            waypoints: Vec::with_capacity(1024),
        })
    }

    /// Sets the script title.
    pub fn with_title(mut self, title: &str) -> Self {
        self.title = Some(title.into());
        self
    }

    /// Offers one input; kept if `interval` has passed since the last kept one.
    pub fn push(&mut self, input: &ToolInput) {
        let t0 = *self.t0.get_or_insert(input.time);
        self.last_seen = Some(*input);
        if let Some(k) = self.last_kept
            && input.time < k + self.interval
        {
            return;
        }
        self.keep(input, t0);
    }

    fn keep(&mut self, input: &ToolInput, t0: Duration) {
        self.last_kept = Some(input.time);
        self.waypoints.push(ToolWaypoint {
            t: input.time.saturating_sub(t0).as_secs_f64(),
            pose: ToolPose {
                position: input.position,
                orientation: input.orientation,
                jaw: input.jaw,
            },
            label: None,
        });
    }

    /// Loop time of the first input (script time 0), if any.
    pub fn start_time(&self) -> Option<Duration> {
        self.t0
    }

    /// Number of poses kept so far.
    pub fn len(&self) -> usize {
        self.waypoints.len()
    }

    /// Nothing recorded yet.
    pub fn is_empty(&self) -> bool {
        self.waypoints.is_empty()
    }

    /// The recording as a script (the newest input is appended as the final pose when it
    /// is at least 1 ms after the last kept one). `None` when nothing was recorded.
    pub fn to_script(&self) -> Option<ToolScript> {
        let mut waypoints = self.waypoints.clone();
        if let (Some(last), Some(kept), Some(t0)) = (self.last_seen, self.last_kept, self.t0)
            && last.time >= kept + Duration::from_millis(1)
        {
            let mut r = self.clone();
            r.keep(&last, t0);
            waypoints = r.waypoints;
        }
        if waypoints.is_empty() {
            return None;
        }
        let mut s = ToolScript {
            title: self.title.clone(),
            ..Default::default()
        };
        s.tracks.insert(self.tool.clone(), waypoints);
        Some(s)
    }

    /// Writes the recording as a tool script (TOML, sim-scene format).
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), HapticError> {
        let path = path.as_ref();
        let script = self.to_script().ok_or_else(|| HapticError::Invalid {
            key: "recording",
            problem: format!("nothing recorded, {} not written", path.display()),
        })?;
        std::fs::write(path, script.to_toml())
            .map_err(|e| HapticError::io(format!("writing {}", path.display()), e))
    }
}

/// The guiding spring of teaching playback: `F = ramp(t) · clamp(k (x_r − x) + b (v_r −
/// v), max_force)`, where `x_r, v_r` are the recorded tip position and velocity at the
/// playback time and `x, v` the trainee's device tip position and (filtered) velocity.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GuideSpring {
    /// Spring stiffness k, N/m (default 150 N/m: 1 cm off the path → 1.5 N).
    pub stiffness: f64,
    /// Damping b on the velocity error, N·s/m (default 2 N·s/m).
    pub damping: f64,
    /// Largest guide force, N (default 1.5 N; the loop's device limit applies on top).
    pub max_force: f64,
    /// Time over which the guide fades in at the start of playback, s (default 0.5 s), so
    /// a trainee away from the recorded start is not jerked.
    pub ramp: f64,
}

impl Default for GuideSpring {
    fn default() -> Self {
        GuideSpring {
            stiffness: 150.0,
            damping: 2.0,
            max_force: 1.5,
            ramp: 0.5,
        }
    }
}

/// Plays a recorded track back as a guide force. After the end of the recording the
/// spring holds the last pose (until the guide is removed).
#[derive(Debug, Clone)]
pub struct TeachingPlayback {
    script: ToolScript,
    tool: String,
    spring: GuideSpring,
    speed: f64,
}

impl TeachingPlayback {
    /// Plays the track of `tool` with the given spring.
    pub fn new(script: ToolScript, tool: &str, spring: GuideSpring) -> Result<Self, HapticError> {
        if !script.tracks.contains_key(tool) {
            return Err(HapticError::NoTrack {
                file: script.title.clone().unwrap_or_else(|| "script".into()),
                tool: tool.into(),
                available: script.tools().collect::<Vec<_>>().join(", "),
            });
        }
        let ok = |v: f64| v.is_finite() && v >= 0.0;
        if !(ok(spring.stiffness) && ok(spring.damping) && ok(spring.max_force) && ok(spring.ramp))
        {
            return Err(HapticError::Invalid {
                key: "guide spring",
                problem: format!("all parameters must be finite and ≥ 0: {spring:?}"),
            });
        }
        Ok(TeachingPlayback {
            script,
            tool: tool.into(),
            spring,
            speed: 1.0,
        })
    }

    /// Loads a recording (tool script file); `tool` defaults to its first tool.
    pub fn load(
        path: impl AsRef<Path>,
        tool: Option<&str>,
        spring: GuideSpring,
    ) -> Result<Self, HapticError> {
        let path = path.as_ref();
        let script = ToolScript::load(path)?;
        let tool = match tool {
            Some(t) => t.to_string(),
            None => script.tools().next().unwrap_or_default().to_string(),
        };
        Self::new(script, &tool, spring).map_err(|e| match e {
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

    /// Plays at `speed` times the recorded speed (e.g. 0.5 for a slow demonstration).
    pub fn with_speed(mut self, speed: f64) -> Self {
        self.speed = speed;
        self
    }

    /// The spring.
    pub fn spring(&self) -> &GuideSpring {
        &self.spring
    }

    /// Length of the recording at the playback speed, s.
    pub fn duration(&self) -> f64 {
        self.script.tracks[&self.tool].last().map_or(0.0, |k| k.t) / self.speed
    }

    /// The recorded pose at playback time `t` s (jaw included, for display).
    pub fn target(&self, t: f64) -> ToolPose {
        self.script
            .sample(&self.tool, t * self.speed)
            .expect("track exists")
    }

    /// The recorded tip velocity at playback time `t` (central difference over ±1 ms), m/s.
    pub fn target_velocity(&self, t: f64) -> Vector3<f64> {
        let h = 1e-3;
        let a = self.target((t - h).max(0.0)).position;
        let b = self.target(t + h).position;
        (b - a) / (t + h - (t - h).max(0.0))
    }

    /// The guide force at playback time `t` for a device at `x` moving with `v`, N.
    pub fn guide_force(&self, t: f64, x: &Vector3<f64>, v: &Vector3<f64>) -> Vector3<f64> {
        let s = &self.spring;
        let xr = self.target(t).position;
        let vr = self.target_velocity(t);
        let mut f = (xr - x) * s.stiffness + (vr - v) * s.damping;
        let n = f.norm();
        if n > s.max_force {
            f *= s.max_force / n;
        }
        let ramp = if s.ramp > 0.0 {
            (t / s.ramp).clamp(0.0, 1.0)
        } else {
            1.0
        };
        f * ramp
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn input(ms: u64, x: f64) -> ToolInput {
        ToolInput {
            time: Duration::from_millis(ms),
            position: Vector3::new(x, 0.0, 0.0),
            orientation: UnitQuaternion::identity(),
            jaw: 0.1,
            buttons: 0,
        }
    }

    #[test]
    fn recorder_decimates_and_keeps_the_end() {
        let mut r = TeachingRecorder::new("forceps", Duration::from_millis(10)).unwrap();
        for ms in 100..=125 {
            r.push(&input(ms, ms as f64 * 1e-3));
        }
        assert_eq!(r.len(), 3); // 100, 110, 120 ms
        let s = r.to_script().unwrap();
        let k = &s.tracks["forceps"];
        let times: Vec<f64> = k.iter().map(|k| k.t).collect();
        assert_eq!(times, [0.0, 0.01, 0.02, 0.025]);
        assert!(TeachingRecorder::new("x", Duration::from_micros(100)).is_err());
    }

    #[test]
    fn guide_spring_law() {
        let mut r = TeachingRecorder::new("forceps", Duration::from_millis(10)).unwrap();
        // still at x = 0.05 for 1 s, then moving along +x at 0.1 m/s for 1 s
        for ms in 0..=2000u64 {
            let x = 0.05
                + if ms > 1000 {
                    (ms - 1000) as f64 * 1e-4
                } else {
                    0.0
                };
            r.push(&input(ms, x));
        }
        let spring = GuideSpring {
            stiffness: 200.0,
            damping: 3.0,
            max_force: 1.0,
            ramp: 0.5,
        };
        let p = TeachingPlayback::new(r.to_script().unwrap(), "forceps", spring).unwrap();
        let zero = Vector3::zeros();
        // resting part, after the ramp: pure spring
        let x = Vector3::new(0.05, 0.002, -0.001);
        let f = p.guide_force(0.7, &x, &zero);
        assert!((f - Vector3::new(0.0, -0.4, 0.2)).norm() < 1e-9, "{f}");
        // during the ramp: scaled
        let f = p.guide_force(0.25, &x, &zero);
        assert!((f - Vector3::new(0.0, -0.2, 0.1)).norm() < 1e-9, "{f}");
        // moving part: the recorded velocity adds b·v_r
        let t = 1.5;
        let xr = p.target(t).position;
        let f = p.guide_force(t, &xr, &zero);
        assert!((f - Vector3::new(3.0 * 0.1, 0.0, 0.0)).norm() < 1e-6, "{f}");
        // saturation
        let f = p.guide_force(0.7, &Vector3::new(1.0, 0.0, 0.0), &zero);
        assert!((f.norm() - 1.0).abs() < 1e-12);
        assert!(f.x < 0.0);
    }
}
