//! Tool scripts: timed tool poses for teaching mode and scripted runs.
//!
//! A script is a TOML file:
//!
//! ```toml
//! version = 1                 # optional
//! title = "grasp and lift"    # optional
//! tool = "forceps"            # default tool of the poses below (optional)
//!
//! [[pose]]
//! t = 0.0                     # s, strictly increasing per tool
//! tool = "forceps"            # optional when the top-level `tool` is set
//! position = [0.03, -0.1, 0.0]          # tool tip, m
//! orientation = [1.0, 0.0, 0.0, 0.0]    # quaternion [w, x, y, z]; optional: previous pose's (first: identity)
//! jaw = 0.5                   # jaw opening angle, rad (0 = closed); optional: previous pose's (first: 0)
//! label = "approach"          # optional note shown to trainees
//!
//! [[command]]                 # optional: session commands (instructor scripts)
//! t = 4.0                     # s, script time
//! command = "reset-scene"     # every site restores the scene's initial state
//! ```
//!
//! Between poses the position and jaw angle are interpolated linearly and the orientation
//! by spherical linear interpolation (shortest arc). Before the first pose the first pose
//! holds; after the last, the last.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use nalgebra::{UnitQuaternion, Vector3};
use serde::Deserialize;

use crate::mesh::fmt_fixed;

/// Errors from parsing a script. Messages name the file and the key.
#[derive(Debug, thiserror::Error)]
pub enum ScriptError {
    /// TOML syntax, unknown key or wrong type.
    #[error("{file}: {message}")]
    Parse {
        /// Script file.
        file: String,
        /// Parser message.
        message: String,
    },
    /// A value is unacceptable.
    #[error("{file}: `{key}`: {problem}")]
    Invalid {
        /// Script file.
        file: String,
        /// Key, e.g. `pose[3].t`.
        key: String,
        /// What is wrong.
        problem: String,
    },
}

/// One tool pose at one time.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolPose {
    /// Tip position in m.
    pub position: Vector3<f64>,
    /// Orientation (tool frame: shaft along local +z, tip at the origin).
    pub orientation: UnitQuaternion<f64>,
    /// Jaw opening angle in rad (0 = closed).
    pub jaw: f64,
}

/// A tool pose at a time, with an optional label: one `[[pose]]` of a script. (Not a
/// keyframe: that word is kept for a region's state on the wire.)
#[derive(Debug, Clone, PartialEq)]
pub struct ToolWaypoint {
    /// Time in s.
    pub t: f64,
    /// The pose.
    pub pose: ToolPose,
    /// Optional teaching note.
    pub label: Option<String>,
}

/// A parsed script: waypoints per tool, sorted by time.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ToolScript {
    /// Optional title.
    pub title: Option<String>,
    /// Waypoints per tool name.
    pub tracks: BTreeMap<String, Vec<ToolWaypoint>>,
    /// Session commands at script times, sorted by time.
    pub commands: Vec<ScriptCommand>,
}

/// A session command an instructor's script issues at a script time.
#[derive(Debug, Clone, PartialEq)]
pub struct ScriptCommand {
    /// Time in s (script time).
    pub t: f64,
    /// What to do.
    pub command: SessionCommand,
}

/// What a [`ScriptCommand`] does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SessionCommand {
    /// Every site restores the scene's initial state (`"reset-scene"`).
    ResetScene,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScript {
    version: Option<u32>,
    title: Option<String>,
    tool: Option<String>,
    #[serde(default)]
    pose: Vec<RawPose>,
    #[serde(default)]
    command: Vec<RawCommand>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCommand {
    t: f64,
    command: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPose {
    t: f64,
    tool: Option<String>,
    position: [f64; 3],
    orientation: Option<[f64; 4]>,
    jaw: Option<f64>,
    label: Option<String>,
}

/// A quaternion given as `[w, x, y, z]`, normalised.
pub fn quat_wxyz(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// `[w, x, y, z]` of a unit quaternion.
pub fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}

impl ToolScript {
    /// Reads a script file.
    pub fn load(path: impl AsRef<std::path::Path>) -> Result<Self, ScriptError> {
        let path = path.as_ref();
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ScriptError::Parse {
            file: file.clone(),
            message: e.to_string(),
        })?;
        Self::parse(&text, &file)
    }

    /// Parses script text; `file` labels errors.
    pub fn parse(text: &str, file: &str) -> Result<Self, ScriptError> {
        let raw: RawScript =
            crate::scene::parse_toml(text).map_err(|(key, message)| ScriptError::Parse {
                file: file.into(),
                message: match key {
                    Some(k) => format!("`{k}`: {message}"),
                    None => message,
                },
            })?;
        let inv = |key: String, problem: String| ScriptError::Invalid {
            file: file.into(),
            key,
            problem,
        };
        if let Some(v) = raw.version
            && v != 1
        {
            return Err(inv("version".into(), format!("unsupported version {v}")));
        }
        if raw.pose.is_empty() {
            return Err(inv("pose".into(), "the script has no [[pose]]".into()));
        }
        let mut tracks: BTreeMap<String, Vec<ToolWaypoint>> = BTreeMap::new();
        for (i, p) in raw.pose.into_iter().enumerate() {
            let tool = p.tool.or_else(|| raw.tool.clone()).ok_or_else(|| {
                inv(
                    format!("pose[{i}].tool"),
                    "no tool named here and no top-level `tool`".into(),
                )
            })?;
            if !p.t.is_finite() {
                return Err(inv(format!("pose[{i}].t"), "must be finite".into()));
            }
            if !p.position.iter().all(|c| c.is_finite()) {
                return Err(inv(format!("pose[{i}].position"), "must be finite".into()));
            }
            let track = tracks.entry(tool.clone()).or_default();
            let prev = track.last();
            if let Some(prev) = prev
                && p.t <= prev.t
            {
                return Err(inv(
                    format!("pose[{i}].t"),
                    format!(
                        "times must increase for tool \"{tool}\": {} follows {}",
                        p.t, prev.t
                    ),
                ));
            }
            let orientation = match p.orientation {
                Some(q) => {
                    let n2: f64 = q.iter().map(|c| c * c).sum();
                    if !(n2.is_finite() && n2 > 1e-12) {
                        return Err(inv(
                            format!("pose[{i}].orientation"),
                            "quaternion [w, x, y, z] must be finite and non-zero".into(),
                        ));
                    }
                    quat_wxyz(q)
                }
                None => prev
                    .map(|k| k.pose.orientation)
                    .unwrap_or_else(UnitQuaternion::identity),
            };
            let jaw = match p.jaw {
                Some(j) if !j.is_finite() => {
                    return Err(inv(format!("pose[{i}].jaw"), "must be finite".into()));
                }
                Some(j) => j,
                None => prev.map(|k| k.pose.jaw).unwrap_or(0.0),
            };
            track.push(ToolWaypoint {
                t: p.t,
                pose: ToolPose {
                    position: Vector3::from(p.position),
                    orientation,
                    jaw,
                },
                label: p.label,
            });
        }
        let mut commands = Vec::with_capacity(raw.command.len());
        for (i, c) in raw.command.into_iter().enumerate() {
            if !c.t.is_finite() {
                return Err(inv(format!("command[{i}].t"), "must be finite".into()));
            }
            let command = match c.command.as_str() {
                "reset-scene" => SessionCommand::ResetScene,
                other => {
                    return Err(inv(
                        format!("command[{i}].command"),
                        format!("unknown command {other:?} (reset-scene)"),
                    ));
                }
            };
            commands.push(ScriptCommand { t: c.t, command });
        }
        commands.sort_by(|a, b| a.t.total_cmp(&b.t));
        Ok(ToolScript {
            title: raw.title,
            tracks,
            commands,
        })
    }

    /// Writes the script as TOML (every field explicit; positions with 5 decimals,
    /// quaternions with 6, times and jaw angles with 4). Parsing the output gives the
    /// same script up to that rounding.
    pub fn to_toml(&self) -> String {
        let mut s =
            String::from("# cosurg tool script (see sim-scene/SCENE_FORMAT.md)\nversion = 1\n");
        if let Some(t) = &self.title {
            let _ = writeln!(s, "title = {}", toml_string(t));
        }
        for (tool, waypoints) in &self.tracks {
            for k in waypoints {
                let p = &k.pose;
                let q = wxyz(&p.orientation);
                let _ = write!(
                    s,
                    "\n[[pose]]\nt = {}\ntool = {}\nposition = [{}, {}, {}]\norientation = [{}, {}, {}, {}]\njaw = {}\n",
                    fmt_fixed(k.t, 4),
                    toml_string(tool),
                    fmt_fixed(p.position.x, 5),
                    fmt_fixed(p.position.y, 5),
                    fmt_fixed(p.position.z, 5),
                    fmt_fixed(q[0], 6),
                    fmt_fixed(q[1], 6),
                    fmt_fixed(q[2], 6),
                    fmt_fixed(q[3], 6),
                    fmt_fixed(p.jaw, 4),
                );
                if let Some(l) = &k.label {
                    let _ = writeln!(s, "label = {}", toml_string(l));
                }
            }
        }
        for c in &self.commands {
            let name = match c.command {
                SessionCommand::ResetScene => "reset-scene",
            };
            let _ = write!(
                s,
                "\n[[command]]\nt = {}\ncommand = {}\n",
                fmt_fixed(c.t, 4),
                toml_string(name)
            );
        }
        s
    }

    /// Names of the tools that have poses.
    pub fn tools(&self) -> impl Iterator<Item = &str> {
        self.tracks.keys().map(String::as_str)
    }

    /// First and last waypoint time of `tool`'s track (s), if it has one.
    pub fn track_span(&self, tool: &str) -> Option<(f64, f64)> {
        let w = self.tracks.get(tool)?;
        Some((w.first()?.t, w.last()?.t))
    }

    /// Time of the last pose over all tools, s.
    pub fn duration(&self) -> f64 {
        self.tracks
            .values()
            .filter_map(|k| k.last())
            .map(|k| k.t)
            .fold(0.0, f64::max)
    }

    /// The pose of `tool` at time `t` (`None` when the script has no such tool).
    pub fn sample(&self, tool: &str, t: f64) -> Option<ToolPose> {
        let waypoints = self.tracks.get(tool)?;
        let first = waypoints.first()?;
        if t <= first.t {
            return Some(first.pose.clone());
        }
        let last = waypoints.last()?;
        if t >= last.t {
            return Some(last.pose.clone());
        }
        let i = waypoints.partition_point(|k| k.t <= t); // waypoints[i-1].t <= t < waypoints[i].t
        let (a, b) = (&waypoints[i - 1], &waypoints[i]);
        let s = (t - a.t) / (b.t - a.t);
        let qa = a.pose.orientation;
        let mut qb = b.pose.orientation;
        if qa.coords.dot(&qb.coords) < 0.0 {
            qb = UnitQuaternion::new_unchecked(-qb.into_inner());
        }
        let orientation = qa
            .try_slerp(&qb, s, 1e-12)
            .unwrap_or_else(|| qa.nlerp(&qb, s));
        Some(ToolPose {
            position: a.pose.position.lerp(&b.pose.position, s),
            orientation,
            jaw: a.pose.jaw + s * (b.pose.jaw - a.pose.jaw),
        })
    }
}

fn toml_string(s: &str) -> String {
    toml::Value::String(s.to_string()).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = r#"
tool = "forceps"
title = "t"
[[pose]]
t = 0.0
position = [0.0, 0.0, 0.0]
jaw = 0.5
label = "start"
[[pose]]
t = 2.0
position = [0.2, 0.0, -0.1]
orientation = [0.0, 0.0, 0.0, 1.0]
[[pose]]
t = 0.5
tool = "probe"
position = [1.0, 1.0, 1.0]
"#;

    #[test]
    fn parse_and_interpolate() {
        let s = ToolScript::parse(TEXT, "s.toml").unwrap();
        assert_eq!(s.tools().collect::<Vec<_>>(), ["forceps", "probe"]);
        assert_eq!(s.duration(), 2.0);
        let k = &s.tracks["forceps"];
        assert_eq!(k[1].pose.jaw, 0.5, "jaw carried over");
        assert_eq!(k[0].pose.orientation, UnitQuaternion::identity());
        let p = s.sample("forceps", 1.0).unwrap();
        assert!((p.position - Vector3::new(0.1, 0.0, -0.05)).norm() < 1e-12);
        // halfway between identity and 180° about z: 90° about z
        let expect =
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
        assert!(
            p.orientation.angle_to(&expect) < 1e-9,
            "{:?}",
            p.orientation
        );
        assert_eq!(
            s.sample("forceps", -1.0).unwrap().position,
            Vector3::zeros()
        );
        assert_eq!(s.sample("forceps", 9.0).unwrap().position.x, 0.2);
        assert_eq!(s.sample("probe", 3.0).unwrap().position.x, 1.0);
        assert!(s.sample("hook", 0.0).is_none());
    }

    #[test]
    fn commands_parse_sort_and_round_trip() {
        let text = format!(
            "{TEXT}\n[[command]]\nt = 3.0\ncommand = \"reset-scene\"\n[[command]]\nt = 1.5\ncommand = \"reset-scene\"\n"
        );
        let s = ToolScript::parse(&text, "s.toml").unwrap();
        let times: Vec<f64> = s.commands.iter().map(|c| c.t).collect();
        assert_eq!(times, [1.5, 3.0]);
        assert!(
            s.commands
                .iter()
                .all(|c| c.command == SessionCommand::ResetScene)
        );
        let again = ToolScript::parse(&s.to_toml(), "again.toml").unwrap();
        assert_eq!(again.commands, s.commands);
        let bad = format!("{TEXT}\n[[command]]\nt = 1.0\ncommand = \"explode\"\n");
        let e = ToolScript::parse(&bad, "bad.toml").unwrap_err().to_string();
        assert!(
            e.contains("command[0].command") && e.contains("explode"),
            "{e}"
        );
    }

    #[test]
    fn slerp_takes_shortest_arc() {
        let q1 = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.1);
        let q2 = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.3);
        let neg = UnitQuaternion::new_unchecked(-q2.into_inner());
        let mut s = ToolScript::default();
        let kf = |t: f64, q: UnitQuaternion<f64>| ToolWaypoint {
            t,
            pose: ToolPose {
                position: Vector3::zeros(),
                orientation: q,
                jaw: 0.0,
            },
            label: None,
        };
        s.tracks.insert("a".into(), vec![kf(0.0, q1), kf(1.0, neg)]);
        let mid = s.sample("a", 0.5).unwrap().orientation;
        assert!((mid.angle_to(&UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.2))) < 1e-9);
    }

    #[test]
    fn write_parse_roundtrip() {
        let s = ToolScript::parse(TEXT, "s.toml").unwrap();
        let text = s.to_toml();
        let r = ToolScript::parse(&text, "w.toml").unwrap();
        assert_eq!(r.title, s.title);
        for (tool, waypoints) in &s.tracks {
            let rk = &r.tracks[tool];
            assert_eq!(rk.len(), waypoints.len());
            for (a, b) in waypoints.iter().zip(rk) {
                assert_eq!(a.t, b.t);
                assert_eq!(a.label, b.label);
                assert!((a.pose.position - b.pose.position).norm() < 1e-5);
                assert!(a.pose.orientation.angle_to(&b.pose.orientation) < 1e-5);
                assert!((a.pose.jaw - b.pose.jaw).abs() < 1e-4);
            }
        }
        assert_eq!(r.to_toml(), text, "writing is stable");
    }

    #[test]
    fn errors() {
        let e = |t: &str| ToolScript::parse(t, "x.toml").unwrap_err().to_string();
        let m = e("[[pose]]\nt = 0.0\nposition = [0,0,0]\n");
        assert_eq!(
            m,
            "x.toml: `pose[0].tool`: no tool named here and no top-level `tool`"
        );
        let m = e(
            "tool = \"a\"\n[[pose]]\nt = 1.0\nposition = [0,0,0]\n[[pose]]\nt = 1.0\nposition = [0,0,0]\n",
        );
        assert_eq!(
            m,
            "x.toml: `pose[1].t`: times must increase for tool \"a\": 1 follows 1"
        );
        let m = e("tool = \"a\"\n[[pose]]\nt = 0.0\nposition = [0,0,0]\norientation = [0,0,0,0]\n");
        assert!(
            m.starts_with("x.toml: `pose[0].orientation`: quaternion"),
            "{m}"
        );
        let m = e("tool = \"a\"\n[[pose]]\nt = 0.0\nposition = [0,0,0]\ngrip = 1\n");
        assert!(
            m.starts_with("x.toml: ") && m.contains("unknown field `grip`"),
            "{m}"
        );
        let m = e("tool = \"a\"\n");
        assert_eq!(m, "x.toml: `pose`: the script has no [[pose]]");
        let m = e("version = 2\ntool = \"a\"\n[[pose]]\nt = 0.0\nposition = [0,0,0]\n");
        assert_eq!(m, "x.toml: `version`: unsupported version 2");
    }
}
