//! A site's window (`cosurg join` with a display) and its screenshot (`--screenshot`).
//!
//! The site's driver ([`super::run_site`]) owns a [`SiteViewer`]: between steps it drains
//! the window's commands without waiting, and about 60 times a second it builds a
//! [`ViewFrame`] of the site (organ, local and remote tools, guide, forces, HUD from the
//! session's state) and swaps it into the [`ViewSlot`] the render thread reads. The
//! renderer never touches the simulation and the simulation never waits for it.
//!
//! Without a script or a device the local tool follows the window's hands
//! ([`SiteHands`]), through the same `viewer::Hands` → `ToolCommand` path as `cosurg run`.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::mpsc::{self, Receiver};
use std::thread::JoinHandle;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nalgebra::{Isometry3, Vector3};
use sim_core::{Simulation, ToolInput};
use viewer::{
    FrameBuilder, HudInfo, RegionOwner, SessionCommand, ToolCommand, ToolView, ViewFrame, ViewSlot,
    ViewerCommand, WindowOptions,
};

use super::tools::Tools;
use crate::link::LinkStats;
use crate::run_window::HandTarget;
use crate::session::SiteSession;
use crate::stats::percentile;

type V3 = Vector3<f64>;

/// Wall time between published frames (s).
const PUBLISH_PERIOD: f64 = 1.0 / 60.0;
/// Step times kept for the HUD's p99.
const STEP_WINDOW: usize = 500;
/// The hands drive the tool (the site leads, sends poses, records an act) until they have
/// been still for this long (simulated s) and the tool has reached its target.
const HANDS_HOLD_S: f64 = 0.5;
/// Wall time over which the HUD's rates are averaged (s).
const RATE_WINDOW_S: f64 = 1.0;

/// How a site shows itself.
#[derive(Clone, Debug, PartialEq)]
pub enum SiteView {
    /// A window of `size` pixels, open for the whole run (closing it ends the run).
    Window { title: String, size: (u32, u32) },
    /// One picture at the end of the run (`--seconds`), written as PNG; needs a display
    /// for the OpenGL context (Xvfb will do).
    Screenshot { path: PathBuf, size: (u32, u32) },
}

/// What the window asks of the site's driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewRequest {
    /// Instructor: reset the scene for the session.
    Reset,
    /// Instructor: start / stop teaching replay of the newest trajectory.
    TeachingStart,
    TeachingStop,
    /// The window was closed: the site leaves.
    Closed,
    /// The hands take the site's next instrument (`T`): see [`Tools::next_instrument`].
    NextInstrument,
}

/// The local tool under the window's hands.
#[derive(Clone, Copy, Debug, Default)]
pub struct SiteHands {
    hold: HandTarget,
    /// Simulated time of the newest command (s); `None` before the first.
    last_command: Option<f64>,
}

impl SiteHands {
    /// Takes one tool command at simulated time `t`. `NextTool` (an instrument exchange,
    /// made by the driver) leaves the hands at rest until they move the new instrument.
    pub fn command(&mut self, c: ToolCommand, t: f64) {
        match c {
            ToolCommand::MoveTo(p) => self.hold.target = Some(p),
            ToolCommand::Jaw(closed) => self.hold.jaw_closed = closed,
            ToolCommand::NextTool => {
                *self = SiteHands::default();
                return;
            }
        }
        self.last_command = Some(t);
    }

    /// The local tool's input for the step from `t`, while the hands act (they moved it
    /// less than [`HANDS_HOLD_S`] ago or it has not reached their target); `None` before
    /// the first command and while the hands rest (the tool then stays where it is).
    pub fn input(&self, tools: &Tools, dt: f64, t: f64) -> Option<ToolInput> {
        let since = self.last_command?;
        let tool = &tools.interaction().tools.tools[tools.local_index()?];
        let acting = t - since < HANDS_HOLD_S || !self.hold.reached(tool);
        acting.then(|| self.hold.drive(tool, dt))
    }

    /// Forgets the target (after a scene reset the tool is back at its start).
    pub fn reset(&mut self) {
        *self = SiteHands::default();
    }
}

/// Link counters at one moment, for rates.
#[derive(Clone, Copy, Debug)]
struct RateSample {
    at: Instant,
    keyframes: u64,
    bytes: u64,
}

/// The HUD's per-second rates of the link's counters.
#[derive(Debug, Default)]
struct Rates {
    base: Option<RateSample>,
    keyframes_per_s: Option<f64>,
    bytes_per_s: Option<f64>,
}

impl Rates {
    fn update(&mut self, stats: &LinkStats, now: Instant) {
        let sample = RateSample {
            at: now,
            keyframes: stats.keyframes_sent + stats.keyframes_received,
            bytes: stats.bytes_up + stats.bytes_down,
        };
        let Some(base) = self.base else {
            self.base = Some(sample);
            return;
        };
        let dt = now.duration_since(base.at).as_secs_f64();
        if dt >= RATE_WINDOW_S {
            self.keyframes_per_s =
                Some(sample.keyframes.saturating_sub(base.keyframes) as f64 / dt);
            self.bytes_per_s = Some(sample.bytes.saturating_sub(base.bytes) as f64 / dt);
            self.base = Some(sample);
        }
    }
}

/// What the driver knows at a publish that the frame shows besides the simulation.
pub struct FrameContext<'a> {
    pub sim: &'a Simulation,
    pub tools: &'a Tools,
    pub session: &'a SiteSession,
    pub link: Option<LinkStats>,
    /// Lag behind the sites followed (s).
    pub behind: Option<f64>,
    pub teaching: bool,
    pub guide: Vec<V3>,
}

/// The render thread and what it returns.
type WindowThread = JoinHandle<Result<viewer::WindowStats, viewer::ViewerError>>;

/// The window (or screenshot) of one site.
pub struct SiteViewer {
    name: String,
    role: viewer::Role,
    builder: FrameBuilder,
    slot: ViewSlot,
    window: Option<(Receiver<ViewerCommand>, WindowThread)>,
    screenshot: Option<(PathBuf, (u32, u32))>,
    /// `Some` when the window's hands drive the local tool.
    pub hands: Option<SiteHands>,
    last_publish: Option<Instant>,
    recent_steps: VecDeque<f64>,
    rates: Rates,
    /// Names of the sites seen (kept after they leave, for their tools' labels).
    names: std::collections::BTreeMap<proto::SiteId, String>,
    /// The newest lag behind the sites followed (s).
    last_behind: Option<f64>,
    /// A message for the HUD (a refused command, a teaching request without a trajectory).
    pub notice: Option<String>,
}

/// The HUD's role for a session role.
pub fn hud_role(role: proto::Role) -> viewer::Role {
    match role {
        proto::Role::Instructor => viewer::Role::Instructor,
        proto::Role::Trainee => viewer::Role::Trainee,
        proto::Role::Observer => viewer::Role::Observer,
    }
}

impl SiteViewer {
    /// Starts the window thread (for [`SiteView::Window`]); `hands`: the window's hands
    /// drive the local tool.
    pub fn start(
        view: SiteView,
        sim: &Simulation,
        name: &str,
        role: proto::Role,
        hands: bool,
    ) -> Result<Self> {
        let mut builder = FrameBuilder::new(sim).context("preparing the window's frames")?;
        let first = builder.build(
            sim,
            None,
            false,
            HudInfo {
                site: name.to_string(),
                role: hud_role(role),
                ..Default::default()
            },
        );
        let mut viewer = SiteViewer {
            name: name.to_string(),
            role: hud_role(role),
            slot: ViewSlot::new(first),
            builder,
            window: None,
            screenshot: None,
            hands: hands.then(SiteHands::default),
            last_publish: None,
            recent_steps: VecDeque::with_capacity(STEP_WINDOW + 1),
            rates: Rates::default(),
            names: Default::default(),
            last_behind: None,
            notice: None,
        };
        match view {
            SiteView::Window { title, size } => {
                let (tx, rx) = mpsc::channel();
                let slot = viewer.slot.clone();
                let handle = std::thread::Builder::new()
                    .name("window".into())
                    .spawn(move || {
                        viewer::run_window(
                            slot,
                            tx,
                            WindowOptions {
                                title,
                                size,
                                ..Default::default()
                            },
                        )
                    })
                    .context("starting the window thread")?;
                viewer.window = Some((rx, handle));
            }
            SiteView::Screenshot { path, size } => viewer.screenshot = Some((path, size)),
        }
        Ok(viewer)
    }

    /// Drains the window's commands without waiting: tool commands go to the hands (at
    /// simulated time `t`), the rest to the driver.
    pub fn requests(&mut self, t: f64) -> Vec<ViewRequest> {
        let mut out = Vec::new();
        let Some((rx, _)) = &self.window else {
            return out;
        };
        for cmd in rx.try_iter() {
            match cmd {
                ViewerCommand::Tool(c) => {
                    if let Some(h) = self.hands.as_mut() {
                        h.command(c, t);
                        if c == ToolCommand::NextTool {
                            out.push(ViewRequest::NextInstrument);
                        }
                    }
                }
                ViewerCommand::Session(SessionCommand::Reset) => out.push(ViewRequest::Reset),
                ViewerCommand::Session(SessionCommand::TeachingStart) => {
                    out.push(ViewRequest::TeachingStart)
                }
                ViewerCommand::Session(SessionCommand::TeachingStop) => {
                    out.push(ViewRequest::TeachingStop)
                }
                ViewerCommand::Closed => out.push(ViewRequest::Closed),
            }
        }
        out
    }

    /// The local tool's input from the hands for the step from `t`.
    pub fn hands_input(&self, tools: &Tools, dt: f64, t: f64) -> Option<ToolInput> {
        self.hands.as_ref()?.input(tools, dt, t)
    }

    /// After a scene reset: frames are built for the new simulation.
    pub fn reset(&mut self, sim: &Simulation) -> Result<()> {
        self.builder = FrameBuilder::new(sim).context("preparing the window's frames")?;
        if let Some(h) = self.hands.as_mut() {
            h.reset();
        }
        Ok(())
    }

    /// Records one step's wall time (ms) for the HUD's p99.
    pub fn step_time(&mut self, ms: f64) {
        self.recent_steps.push_back(ms);
        if self.recent_steps.len() > STEP_WINDOW {
            self.recent_steps.pop_front();
        }
    }

    /// Whether it is time for [`Self::publish`] (about 60 times a second).
    pub fn publish_due(&self, now: Instant) -> bool {
        self.last_publish
            .is_none_or(|l| now.duration_since(l).as_secs_f64() >= PUBLISH_PERIOD)
    }

    /// Follows the session's figures (rates, site names, lag) and, for a window, builds
    /// the frame of the site's current state and publishes it.
    pub fn publish(&mut self, ctx: FrameContext<'_>, now: Instant) {
        self.last_publish = Some(now);
        self.observe(&ctx, now);
        if self.window.is_some() {
            let lattice = self.slot.wants_lattice();
            let frame = self.frame(ctx, lattice);
            self.slot.publish(frame);
        }
    }

    fn observe(&mut self, ctx: &FrameContext<'_>, now: Instant) {
        if let Some(s) = &ctx.link {
            self.rates.update(s, now);
        }
        let sites = ctx.session.sites();
        for id in sites.receivers() {
            if let Some(n) = sites.name(id) {
                self.names.insert(id, n.to_string());
            }
        }
        if ctx.behind.is_some() {
            self.last_behind = ctx.behind;
        }
    }

    /// The frame of the site's current state.
    pub fn frame(&mut self, ctx: FrameContext<'_>, with_lattice: bool) -> ViewFrame {
        let snapshot = ctx.session.snapshot();
        let names = &self.names;
        let site_name = |id: proto::SiteId| {
            ctx.session
                .sites()
                .name(id)
                .or_else(|| names.get(&id).map(String::as_str))
                .map_or_else(|| format!("site {id}"), String::from)
        };
        let mut region_owners: Vec<(u32, String)> = snapshot
            .owned
            .iter()
            .map(|&r| (r, self.name.clone()))
            .chain(
                snapshot
                    .remote_owners
                    .iter()
                    .map(|&(r, s)| (r, site_name(s))),
            )
            .collect();
        region_owners.sort();
        let recent: Vec<f64> = self.recent_steps.iter().copied().collect();
        let hud = HudInfo {
            site: self.name.clone(),
            role: self.role,
            sim_time: ctx.sim.time(),
            lag: ctx.behind.or(self.last_behind),
            step_p99_ms: (!recent.is_empty()).then(|| percentile(&recent, 99.0)),
            keyframes_per_s: self.rates.keyframes_per_s,
            bytes_per_s: self.rates.bytes_per_s,
            // at the newest keyframe from an owner (the demo also measures it afterwards
            // from the sites' surface recordings)
            divergence: snapshot.divergence_m,
            region_owners: region_owners
                .into_iter()
                .map(|(r, site)| RegionOwner {
                    region: format!("region {r}"),
                    site,
                })
                .collect(),
            teaching: ctx.teaching,
            active_tool: ctx.tools.local_name().map(String::from),
            notice: self.notice.clone(),
        };
        let mut frame =
            self.builder
                .build(ctx.sim, Some(ctx.tools.interaction()), with_lattice, hud);
        let drawn = ctx.tools.frames();
        // Every instrument of this site is the window's (its hands cycle through them with
        // `T`, in scene order, as `Tools::next_instrument` does).
        let own = ctx.tools.instruments();
        for (i, view) in frame.tools.iter_mut().enumerate() {
            if own.contains(&i) {
                continue;
            }
            view.site = Some(
                ctx.tools
                    .remote_site(i)
                    .map_or_else(|| "nobody".to_string(), site_name),
            );
            if let Some(d) = drawn.get(i) {
                let to = Isometry3::from_parts(d.position.into(), d.orientation);
                move_tool(view, &to);
            }
        }
        frame.guide = ctx.guide;
        frame
    }

    /// End of the run: writes the screenshot (if asked) and closes the window; fills the
    /// report's screenshot and window fields.
    pub fn finish(mut self, ctx: FrameContext<'_>, report: &mut super::SiteReport) -> Result<()> {
        let shot = match self.screenshot.take() {
            Some((path, size)) => {
                let frame = self.frame(ctx, false);
                viewer::screenshot(&frame, size, &path)
                    .with_context(|| format!("screenshot at t = {:.3} s", frame.hud.sim_time))?;
                Some(path)
            }
            None => None,
        };
        report.screenshot_file = shot;
        if let Some((rx, handle)) = self.window.take() {
            // The window closes at its next frame.
            self.slot.close();
            drop(rx);
            match handle.join() {
                Ok(r) => {
                    let stats = r?;
                    tracing::info!(
                        frames = stats.frame_ms.len(),
                        fps = stats.fps(),
                        "window closed"
                    );
                    report.window_frames = Some(stats.frame_ms.len() as u64);
                    report.window_fps = Some(stats.fps());
                }
                Err(_) => bail!("the window thread panicked"),
            }
        }
        Ok(())
    }
}

/// Moves a drawn tool rigidly to pose `to` (remote tools are drawn at their owner's pose,
/// not at the local simulation's).
fn move_tool(view: &mut ToolView, to: &Isometry3<f64>) {
    let by = to * view.pose.inverse();
    let map = |p: &mut V3| *p = by.transform_point(&(*p).into()).coords;
    for s in view.parts.iter_mut() {
        map(&mut s.a);
        map(&mut s.b);
    }
    map(&mut view.shaft.a);
    map(&mut view.shaft.b);
    view.pose = *to;
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim_core::sim_scene::builtin;

    #[test]
    fn hands_drive_the_tool_while_acting_then_rest() {
        let scene = builtin::cholecystectomy();
        let options = sim_core::SimOptions::from_scene(&scene.scene);
        let sim = Simulation::new(scene, options).unwrap();
        let tools = Tools::new(
            &sim,
            &["forceps".into()],
            sim_core::sync::SyncStrategy::Keyframe,
        )
        .unwrap();
        let mut hands = SiteHands::default();
        let dt = 0.004;
        assert!(hands.input(&tools, dt, 0.0).is_none(), "no command yet");
        let tip = tools.interaction().tools.tools[0].pose().translation.vector;
        let target = tip + V3::new(0.0, 0.0, 0.01);
        hands.command(ToolCommand::MoveTo(target), 1.0);
        let input = hands.input(&tools, dt, 1.0).expect("acting");
        // at most 0.25 m/s: one 4 ms step moves 1 mm towards the target
        let moved = input.pose.translation.vector - tip;
        assert!((moved.norm() - 0.001).abs() < 1e-12, "{moved}");
        assert!(moved.dot(&(target - tip)) > 0.0);
        // far from the target it keeps acting long after the command…
        assert!(hands.input(&tools, dt, 5.0).is_some());
        // …and at the target it rests once the hands have been still for a while
        let mut at = SiteHands::default();
        at.command(ToolCommand::MoveTo(tip), 1.0);
        assert!(at.input(&tools, dt, 1.2).is_some());
        assert!(at.input(&tools, dt, 1.0 + HANDS_HOLD_S + 0.01).is_none());
        // the jaw key alone acts too
        let mut jaw = SiteHands::default();
        jaw.command(ToolCommand::Jaw(true), 0.0);
        assert_eq!(jaw.input(&tools, dt, 0.1).unwrap().jaw, 0.0);
    }

    #[test]
    fn a_moved_tool_keeps_its_shape() {
        let scene = builtin::cholecystectomy();
        let options = sim_core::SimOptions::from_scene(&scene.scene);
        let sim = Simulation::new(scene, options).unwrap();
        let inter = sim_core::Interaction::new(&sim);
        let tool = &inter.tools.tools[0];
        let mut view = viewer::frame::tool_view(tool, V3::zeros(), false, None);
        let before = view.clone();
        let to = Isometry3::new(V3::new(0.01, -0.02, 0.03), V3::new(0.0, 0.3, 0.1));
        move_tool(&mut view, &to);
        assert_eq!(view.pose, to);
        let len = |s: &viewer::Segment| (s.b - s.a).norm();
        assert!((len(&view.shaft) - len(&before.shaft)).abs() < 1e-12);
        // the hinge (shaft start) sits at the same place in the tool's frame
        let local = |pose: &Isometry3<f64>, p: &V3| pose.inverse_transform_point(&(*p).into());
        assert!(
            (local(&view.pose, &view.shaft.a) - local(&before.pose, &before.shaft.a)).norm()
                < 1e-12
        );
    }
}
