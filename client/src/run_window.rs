//! `cosurg run` with a window (the user's hands drive the local tool) and
//! `cosurg run --screenshot` (simulate, then render one picture off-screen).
//!
//! The simulation runs on the calling thread in real time and publishes a
//! [`ViewFrame`](viewer::ViewFrame) about 60 times a second into a [`ViewSlot`]; the
//! window runs on its own thread and only ever reads the slot. Commands come back over a
//! channel that the simulation drains between steps, so neither side waits for the other.

use std::path::Path;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use nalgebra::{Isometry3, Translation3, Vector3};
use sim_core::sim_scene::LoadedScene;
use sim_core::{Interaction, SimOptions, Simulation, ToolInput};
use viewer::{
    FrameBuilder, HudInfo, Role, SessionCommand, ToolCommand, ViewSlot, ViewerCommand,
    WindowOptions,
};

use crate::stats::percentile;

/// Jaw opening the hands use for "open" (rad), as the built-in scripts.
const JAW_OPEN: f64 = 0.6;
/// Fastest the hands move a tool tip (m/s): a mouse jump becomes a quick, bounded motion.
const HAND_SPEED: f64 = 0.25;
/// Wall time between published frames (s).
const PUBLISH_PERIOD: f64 = 1.0 / 60.0;
/// Step times kept for the HUD's p99.
const STEP_WINDOW: usize = 500;

/// Whether a window can be opened (an X11 or Wayland display is named).
pub fn display_available() -> bool {
    ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|k| std::env::var_os(k).is_some_and(|v| !v.is_empty()))
}

/// Parses `WxH`.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WIDTHxHEIGHT, e.g. 1280x720"))?;
    let p = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| (16..=8192).contains(&n))
            .ok_or_else(|| format!("`{s}`: sizes are whole pixels in 16..=8192"))
    };
    Ok((p(w)?, p(h)?))
}

fn new_site(scene: &LoadedScene, options: &SimOptions) -> Result<(Simulation, Interaction)> {
    let sim = Simulation::new(scene.clone(), options.clone())?;
    let interaction = Interaction::new(&sim);
    Ok((sim, interaction))
}

/// What the hands want of one tool: where its tip should go and whether its jaws are
/// closed. Shared by `cosurg run` and `cosurg join` with a window.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HandTarget {
    /// Where the tip is being moved to (m); `None`: where it is.
    pub target: Option<Vector3<f64>>,
    /// Jaws closed.
    pub jaw_closed: bool,
}

impl HandTarget {
    /// The tool's input for the next step of `dt` seconds: towards the target at most
    /// [`HAND_SPEED`], jaws at the hands' setting.
    pub fn drive(&self, tool: &sim_core::Tool, dt: f64) -> ToolInput {
        let here = tool.pose().translation.vector;
        let mut pose = *tool.pose();
        if let Some(target) = self.target {
            let d = target - here;
            let max = HAND_SPEED * dt;
            let step = if d.norm() > max {
                d * (max / d.norm())
            } else {
                d
            };
            pose = Isometry3::from_parts(Translation3::from(here + step), tool.pose().rotation);
        }
        ToolInput {
            pose,
            jaw: if self.jaw_closed { 0.0 } else { JAW_OPEN },
        }
    }

    /// Whether the tool's tip is within 0.1 mm of the target (or there is none).
    pub fn reached(&self, tool: &sim_core::Tool) -> bool {
        self.target
            .is_none_or(|t| (t - tool.pose().translation.vector).norm() < 1e-4)
    }
}

/// The hands' state in `run`: which tool they hold and where they want it.
struct LocalHands {
    active: usize,
    hold: HandTarget,
}

impl LocalHands {
    fn inputs(&self, interaction: &Interaction, dt: f64) -> Vec<ToolInput> {
        interaction
            .tools
            .tools
            .iter()
            .enumerate()
            .map(|(i, tool)| {
                if i == self.active {
                    self.hold.drive(tool, dt)
                } else {
                    ToolInput {
                        pose: *tool.pose(),
                        jaw: tool.jaw(),
                    }
                }
            })
            .collect()
    }
}

/// One site without network whose tools follow the window's commands (or, in teaching
/// replay, the scene's scripts).
pub struct LocalSite {
    scene: LoadedScene,
    options: SimOptions,
    /// The simulation.
    pub sim: Simulation,
    /// Tools and contact.
    pub interaction: Interaction,
    hands: LocalHands,
    /// Teaching replay: the scripts drive the tools.
    pub teaching: bool,
}

impl LocalSite {
    /// A fresh site; `teaching`: start with the scripts driving the tools.
    pub fn new(scene: LoadedScene, options: SimOptions, teaching: bool) -> Result<Self> {
        let (sim, interaction) = new_site(&scene, &options)?;
        Ok(LocalSite {
            scene,
            options,
            sim,
            interaction,
            hands: LocalHands {
                active: 0,
                hold: HandTarget::default(),
            },
            teaching,
        })
    }

    /// Name of the tool the hands drive.
    pub fn active_tool(&self) -> String {
        self.interaction
            .tools
            .tools
            .get(self.hands.active)
            .map(|t| t.name.clone())
            .unwrap_or_default()
    }

    /// Applies a command from the window; returns `false` when the window closed.
    pub fn apply(&mut self, cmd: ViewerCommand) -> Result<bool> {
        match cmd {
            ViewerCommand::Closed => return Ok(false),
            ViewerCommand::Tool(ToolCommand::MoveTo(p)) => self.hands.hold.target = Some(p),
            ViewerCommand::Tool(ToolCommand::Jaw(closed)) => self.hands.hold.jaw_closed = closed,
            ViewerCommand::Tool(ToolCommand::NextTool) => {
                let n = self.interaction.tools.tools.len().max(1);
                self.hands.active = (self.hands.active + 1) % n;
                self.hands.hold = HandTarget::default();
            }
            ViewerCommand::Session(SessionCommand::Reset) => {
                (self.sim, self.interaction) = new_site(&self.scene, &self.options)?;
                self.hands.hold = HandTarget::default();
                tracing::info!("scene reset");
            }
            ViewerCommand::Session(SessionCommand::TeachingStart) => self.teaching = true,
            ViewerCommand::Session(SessionCommand::TeachingStop) => {
                self.teaching = false;
                // the hands take over where the replay left the tool
                self.hands.hold.target = None;
            }
        }
        Ok(true)
    }

    /// One step with the tools driven by the hands (or the scripts in teaching replay).
    pub fn step(&mut self) -> Result<()> {
        let inputs = if self.teaching {
            self.interaction.scripted_inputs(&self.sim, self.sim.time())
        } else {
            self.hands.inputs(&self.interaction, self.options.dt)
        };
        self.interaction.before_step(&mut self.sim, &inputs)?;
        self.sim.step()?;
        Ok(())
    }

    /// The frame to publish.
    pub fn frame(
        &self,
        builder: &mut FrameBuilder,
        with_lattice: bool,
        step_p99_ms: Option<f64>,
    ) -> viewer::ViewFrame {
        let name = self.active_tool();
        let mut frame = builder.build(
            &self.sim,
            Some(&self.interaction),
            with_lattice,
            HudInfo {
                site: "local".into(),
                role: Role::Instructor,
                sim_time: self.sim.time(),
                step_p99_ms,
                teaching: self.teaching,
                active_tool: Some(name.clone()),
                ..Default::default()
            },
        );
        if self.teaching {
            frame.guide = guide_path(&self.scene, &name);
        }
        frame
    }
}

impl LocalSite {
    /// The site's state now (`frame`: a frame of it, for the gallbladder's surface).
    pub fn state(&self, frame: &viewer::ViewFrame) -> SiteState {
        let tool = self.interaction.tools.tools.get(self.hands.active);
        let gallbladder: Vec<&Vector3<f64>> = frame
            .positions
            .iter()
            .zip(&frame.topology.vertex_tissue)
            .filter(|(_, k)| **k == viewer::TissueKind::Gallbladder)
            .map(|(p, _)| p)
            .collect();
        let centroid = (!gallbladder.is_empty()).then(|| {
            let sum: Vector3<f64> = gallbladder.iter().copied().sum();
            (sum / gallbladder.len() as f64).into()
        });
        SiteState {
            t: self.sim.time(),
            tool: self.active_tool(),
            tip: tool.map(|t| t.tip().into()).unwrap_or_default(),
            jaw: tool.map(|t| t.jaw()).unwrap_or_default(),
            grasping: self.interaction.contact.is_grasping(self.hands.active),
            gallbladder_centroid: centroid,
        }
    }
}

/// What `--stats-json` says about one command of the hands.
fn hand_log(cmd: &ViewerCommand, site: SiteState) -> Option<HandCommandLog> {
    let (command, target) = match cmd {
        ViewerCommand::Tool(ToolCommand::MoveTo(p)) => ("move_to", Some((*p).into())),
        ViewerCommand::Tool(ToolCommand::Jaw(true)) => ("jaw_closed", None),
        ViewerCommand::Tool(ToolCommand::Jaw(false)) => ("jaw_open", None),
        ViewerCommand::Tool(ToolCommand::NextTool) => ("next_tool", None),
        _ => return None,
    };
    Some(HandCommandLog {
        command: command.into(),
        target,
        site,
    })
}

/// The guide path of a tool's script (sampled every 20 ms), empty without a script.
pub fn guide_path(scene: &LoadedScene, tool: &str) -> Vec<Vector3<f64>> {
    let Some(script) = scene.scripts.get(tool) else {
        return Vec::new();
    };
    let n = (script.duration() / 0.02).ceil().max(1.0) as usize;
    (0..=n)
        .filter_map(|k| script.sample(tool, k as f64 * script.duration() / n as f64))
        .map(|p| p.position)
        .collect()
}

/// How `cosurg run` with a window runs and ends.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowRun {
    /// The tools follow their scripts (else the hands drive the active tool).
    pub scripted: bool,
    /// Window size (pixels).
    pub size: (u32, u32),
    /// Stop after this many simulated seconds (else when the window is closed).
    pub seconds: Option<f64>,
    /// Open the window (`false`: the same real-time loop without one, to compare).
    pub window: bool,
    /// Measure frames as rendered (`glFinish` after each; benchmarks).
    pub finish_frames: bool,
}

/// What a `cosurg run` with a window measured.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WindowRunStats {
    /// The scene's label and hash (a scene changed on the command line, e.g. `--cell`,
    /// has its own hash).
    #[serde(default)]
    pub scene: String,
    #[serde(default)]
    pub scene_hash: String,
    pub window: bool,
    pub size: (u32, u32),
    pub sim_seconds: f64,
    pub wall_seconds: f64,
    pub steps: usize,
    /// Wall time of `Simulation::step` with the tools' contact (ms).
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
    /// Frames the window drew, per second of its life, and their wall time (ms).
    pub frames: usize,
    pub fps: f64,
    pub frame_ms_p50: f64,
    pub frame_ms_p99: f64,
    /// Wall time of building and publishing one frame on the simulation thread (ms).
    pub publish_ms_p50: f64,
    pub publish_ms_p99: f64,
    /// The site when the loop started and when it ended.
    pub start: Option<SiteState>,
    pub end: Option<SiteState>,
    /// Every tool command the window's hands sent, with the site as the command arrived.
    pub hands: Vec<HandCommandLog>,
}

/// The local site at one moment, as `--stats-json` reports it (positions in m).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SiteState {
    /// Simulated time (s).
    pub t: f64,
    /// The tool the hands drive, its tip, its jaw angle (rad) and whether it grasps.
    pub tool: String,
    pub tip: [f64; 3],
    pub jaw: f64,
    pub grasping: bool,
    /// Mean of the gallbladder's surface vertices (none without a gallbladder).
    pub gallbladder_centroid: Option<[f64; 3]>,
}

/// One command from the window's hands and the site when it arrived.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HandCommandLog {
    /// `move_to`, `jaw_closed`, `jaw_open` or `next_tool`.
    pub command: String,
    /// Where a `move_to` puts the tip (m).
    pub target: Option<[f64; 3]>,
    /// The site just before the command applies.
    pub site: SiteState,
}

/// `cosurg run` with a window (or, to compare, the same real-time loop without one).
pub fn run_with_window(
    scene: LoadedScene,
    options: SimOptions,
    run: &WindowRun,
) -> Result<WindowRunStats> {
    let title = format!("cosurg run — {}", scene.file);
    let (scene_label, scene_hash) = (scene.file.clone(), scene.hash.clone());
    let mut site = LocalSite::new(scene, options, run.scripted)?;
    let mut builder = FrameBuilder::new(&site.sim)?;
    let slot = ViewSlot::new(site.frame(&mut builder, false, None));
    let (tx, rx) = mpsc::channel();
    let render = if run.window {
        let window_slot = slot.clone();
        let options = WindowOptions {
            title,
            size: run.size,
            finish_frames: run.finish_frames,
            ..Default::default()
        };
        Some(
            std::thread::Builder::new()
                .name("window".into())
                .spawn(move || viewer::run_window(window_slot, tx, options))
                .context("starting the window thread")?,
        )
    } else {
        drop(tx);
        None
    };

    let mut step_ms: Vec<f64> = Vec::new();
    let mut publish_ms: Vec<f64> = Vec::new();
    let mut hands_log: Vec<HandCommandLog> = Vec::new();
    let start_state = site.state(&site.frame(&mut builder, false, None));
    let mut recent: std::collections::VecDeque<f64> = Default::default();
    let mut last_publish = Instant::now();
    let started = Instant::now();
    let mut wall_start = Instant::now();
    let mut sim_start = site.sim.time();
    'outer: while run
        .seconds
        .is_none_or(|s| site.sim.time() + 0.5 * site.sim.options().dt < s)
    {
        for cmd in rx.try_iter() {
            if matches!(cmd, ViewerCommand::Tool(_)) {
                let state = site.state(&site.frame(&mut builder, false, None));
                hands_log.extend(hand_log(&cmd, state));
            }
            let reset = cmd == ViewerCommand::Session(SessionCommand::Reset);
            if !site.apply(cmd)? {
                break 'outer;
            }
            if reset {
                builder = FrameBuilder::new(&site.sim)?;
                wall_start = Instant::now();
                sim_start = site.sim.time();
            }
        }
        let t0 = Instant::now();
        site.step()?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        step_ms.push(ms);
        recent.push_back(ms);
        if recent.len() > STEP_WINDOW {
            recent.pop_front();
        }
        if render.is_some() && last_publish.elapsed().as_secs_f64() >= PUBLISH_PERIOD {
            last_publish = Instant::now();
            let window: Vec<f64> = recent.iter().copied().collect();
            slot.publish(site.frame(
                &mut builder,
                slot.wants_lattice(),
                Some(percentile(&window, 99.0)),
            ));
            publish_ms.push(last_publish.elapsed().as_secs_f64() * 1e3);
        }
        // real time: never run ahead of the wall clock
        let ahead = (site.sim.time() - sim_start) - wall_start.elapsed().as_secs_f64();
        if ahead > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(ahead));
        }
    }
    slot.close();
    drop(rx);
    let end_state = site.state(&site.frame(&mut builder, false, None));
    let frames = match render.map(|r| r.join()) {
        None => viewer::WindowStats::default(),
        Some(Ok(r)) => r?,
        Some(Err(_)) => bail!("the window thread panicked"),
    };
    let p = |v: &[f64], q: f64| if v.is_empty() { 0.0 } else { percentile(v, q) };
    Ok(WindowRunStats {
        scene: scene_label,
        scene_hash,
        window: run.window,
        size: run.size,
        sim_seconds: site.sim.time(),
        wall_seconds: started.elapsed().as_secs_f64(),
        steps: step_ms.len(),
        step_ms_p50: p(&step_ms, 50.0),
        step_ms_p99: p(&step_ms, 99.0),
        frames: frames.frame_ms.len(),
        fps: if run.window { frames.fps() } else { 0.0 },
        frame_ms_p50: p(&frames.frame_ms, 50.0),
        frame_ms_p99: p(&frames.frame_ms, 99.0),
        publish_ms_p50: p(&publish_ms, 50.0),
        publish_ms_p99: p(&publish_ms, 99.0),
        start: Some(start_state),
        end: Some(end_state),
        hands: hands_log,
    })
}

/// `cosurg run --screenshot`: simulate to `at` seconds (tools scripted if `scripted`,
/// else at rest), then render one picture off-screen and write it as PNG.
pub fn run_screenshot(
    scene: LoadedScene,
    options: SimOptions,
    scripted: bool,
    at: f64,
    size: (u32, u32),
    lattice: bool,
    path: &Path,
) -> Result<()> {
    let steps = (at / options.dt).round() as u64;
    let mut site = LocalSite::new(scene, options, scripted)?;
    let mut step_ms = Vec::with_capacity(steps as usize);
    for _ in 0..steps {
        let t0 = Instant::now();
        site.step()?;
        step_ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let mut builder = FrameBuilder::new(&site.sim)?;
    let p99 = (!step_ms.is_empty()).then(|| percentile(&step_ms, 99.0));
    let frame = site.frame(&mut builder, lattice, p99);
    viewer::screenshot(&frame, size, path)
        .with_context(|| format!("screenshot at t = {:.3} s", site.sim.time()))?;
    println!(
        "wrote {} ({}x{}, t = {:.3} s)",
        path.display(),
        size.0,
        size.1,
        site.sim.time()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes() {
        assert_eq!(parse_size("1280x720"), Ok((1280, 720)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        assert!(parse_size("1280").unwrap_err().contains("WIDTHxHEIGHT"));
        assert!(parse_size("0x10").unwrap_err().contains("16..=8192"));
        assert!(parse_size("axb").is_err());
    }
}
