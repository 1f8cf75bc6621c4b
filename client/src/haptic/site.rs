//! The site's haptic side (see `docs/haptics.md`): the 1 kHz loop beside the simulation
//! thread, the device that drives the local tool (the site's script, or a real device
//! behind a [`UdpBridgeDevice`]), optional real-time priority, and teaching mode in the
//! session (the instructor's act is recorded and sent to the session; a trainee with the
//! same tool is guided along it when its own act starts).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicI32, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use nalgebra::{Matrix3, Vector3};
use proto::{Command, Message, Role, TeachingTrajectory, ToolSample};
use sim_core::sim_scene::script::{quat_wxyz, wxyz};
use sim_core::sim_scene::{ToolPose, ToolScript, ToolWaypoint};
use tracing::{debug, info, warn};

use crate::haptic::{
    self, GuideSpring, HapticConfig, HapticDevice, HapticHandle, HapticModel, HapticStats,
    InputReader, ScriptedDevice, TeachingPlayback, TeachingRecorder, UdpBridgeDevice,
    UdpBridgeStats,
};
use crate::site::SiteReport;
use crate::site::tools::Tools;

type V3 = Vector3<f64>;

/// Where the local tool's input comes from (`cosurg join --device`).
#[derive(Debug, Default)]
pub enum DeviceSpec {
    /// The site's script (a [`ScriptedDevice`] plays it to the haptic loop in simulated
    /// time); without a script, a device that holds the tool's starting pose.
    #[default]
    Script,
    /// A device driver in another process, over UDP (`udp:ADDR`): the local tool follows
    /// its poses and the haptic loop sends it forces.
    Udp(Box<UdpBridgeDevice>),
}

impl DeviceSpec {
    /// Parses `script` or `udp:HOST:PORT` (binds the bridge socket).
    pub fn parse(s: &str) -> Result<Self> {
        if s == "script" {
            return Ok(DeviceSpec::Script);
        }
        let Some(addr) = s.strip_prefix("udp:") else {
            bail!("--device {s:?}: expected `script` or `udp:HOST:PORT`");
        };
        let dev = UdpBridgeDevice::bind(addr).with_context(|| format!("--device {s}"))?;
        Ok(DeviceSpec::Udp(Box::new(dev)))
    }

    /// Whether the local tool follows a real device.
    pub fn is_device(&self) -> bool {
        matches!(self, DeviceSpec::Udp(_))
    }
}

/// The simulation's time as the haptic thread sees it: the newest step's time plus the
/// wall time since it was published (at most [`SimClock::MAX_AHEAD`]), so that a scripted
/// device and a teaching guide stay in step with a simulation slower than real time.
struct SimClock {
    base: Instant,
    sim_bits: AtomicU64,
    at_ns: AtomicU64,
    /// The session's time dilation: real time since a step is that much less session time.
    scale: server::TimeScale,
}

impl SimClock {
    /// Extrapolation limit past the newest published step (s).
    const MAX_AHEAD: f64 = 0.05;

    fn new(scale: server::TimeScale) -> Self {
        SimClock {
            base: Instant::now(),
            sim_bits: AtomicU64::new(0f64.to_bits()),
            at_ns: AtomicU64::new(0),
            scale,
        }
    }

    fn publish(&self, t: f64) {
        // Two independent words: a reader may pair a new time with an old stamp for one
        // tick, which only shortens or lengthens the extrapolation by one step.
        self.at_ns
            .store(self.base.elapsed().as_nanos() as u64, Ordering::Relaxed);
        self.sim_bits.store(t.to_bits(), Ordering::Release);
    }

    fn now(&self) -> f64 {
        let t = f64::from_bits(self.sim_bits.load(Ordering::Acquire));
        let at = Duration::from_nanos(self.at_ns.load(Ordering::Relaxed));
        let ahead = self
            .scale
            .to_session(self.base.elapsed().saturating_sub(at))
            .as_secs_f64();
        t + ahead.min(Self::MAX_AHEAD)
    }
}

/// The site's device as the loop sees it.
enum SiteDevice {
    /// Plays the site's script (or holds a pose) in simulated time.
    Scripted {
        dev: ScriptedDevice,
        clock: Arc<SimClock>,
    },
    Udp(UdpBridgeDevice),
}

impl HapticDevice for SiteDevice {
    fn read(&mut self, t: Duration) -> haptic::ToolInput {
        match self {
            SiteDevice::Scripted { dev, clock } => {
                let mut input = dev.read(Duration::from_secs_f64(clock.now().max(0.0)));
                input.time = t;
                input
            }
            SiteDevice::Udp(d) => d.read(t),
        }
    }
    fn apply(&mut self, force: V3, torque: V3) {
        match self {
            SiteDevice::Scripted { dev, .. } => dev.apply(force, torque),
            SiteDevice::Udp(d) => d.apply(force, torque),
        }
    }
    fn name(&self) -> &str {
        match self {
            SiteDevice::Scripted { dev, .. } => dev.name(),
            SiteDevice::Udp(d) => d.name(),
        }
    }
    fn input_stale(&self) -> bool {
        match self {
            SiteDevice::Scripted { .. } => false,
            SiteDevice::Udp(d) => d.input_stale(),
        }
    }
}

/// SCHED_FIFO priority requested for the haptic thread (0: none).
static RT_PRIORITY: AtomicI32 = AtomicI32::new(0);

/// `HapticConfig::thread_setup`: raises the haptic thread to SCHED_FIFO
/// [`RT_PRIORITY`]; warns and carries on at normal priority when not permitted.
fn raise_priority() {
    let prio = RT_PRIORITY.load(Ordering::Relaxed);
    if prio <= 0 {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        #[repr(C)]
        struct SchedParam {
            sched_priority: i32,
        }
        unsafe extern "C" {
            fn sched_setscheduler(pid: i32, policy: i32, param: *const SchedParam) -> i32;
        }
        const SCHED_FIFO: i32 = 1;
        let param = SchedParam {
            sched_priority: prio,
        };
        // SAFETY: a plain libc call; `param` is a valid `struct sched_param` for its
        // duration, and pid 0 is the calling thread.
        let r = unsafe { sched_setscheduler(0, SCHED_FIFO, &param) };
        if r == 0 {
            info!(priority = prio, "haptic thread runs at SCHED_FIFO");
        } else {
            warn!(
                priority = prio,
                error = %std::io::Error::last_os_error(),
                "cannot give the haptic thread real-time priority (needs CAP_SYS_NICE or an \
                 rtprio limit); it runs at normal priority"
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    warn!(
        priority = prio,
        "real-time priority is only implemented on Linux; the haptic thread runs at normal priority"
    );
}

/// What the haptic loop did, for the site report.
#[derive(Debug, Clone)]
pub struct HapticSummary {
    pub stats: HapticStats,
    pub device: String,
    pub udp: Option<UdpBridgeStats>,
}

/// The 1 kHz haptic loop of a site, on its own OS thread.
pub struct HapticLoop {
    handle: HapticHandle<SiteDevice>,
    input: InputReader,
    clock: Arc<SimClock>,
    follows_device: bool,
    seen_fresh: bool,
}

impl HapticLoop {
    /// Starts the loop with the site's device: a UDP bridge, or a scripted device playing
    /// `script` from simulated time `script_start` (or holding the local tool's pose).
    /// `rt_priority`: SCHED_FIFO priority for the haptic thread (fails soft).
    pub fn start(
        device: DeviceSpec,
        script: Option<&ToolScript>,
        script_start: f64,
        tools: &Tools,
        rt_priority: Option<i32>,
        time_scale: server::TimeScale,
    ) -> Result<Self> {
        let clock = Arc::new(SimClock::new(time_scale));
        let follows_device = device.is_device();
        let dev = match device {
            DeviceSpec::Udp(d) => SiteDevice::Udp(*d),
            DeviceSpec::Script => {
                let tool = tools.local_name().unwrap_or("none").to_string();
                let track = script.and_then(|s| {
                    if s.tracks.contains_key(&tool) {
                        Some(tool.clone())
                    } else {
                        s.tools().next().map(String::from)
                    }
                });
                let dev = match (script, track) {
                    (Some(s), Some(track)) => {
                        ScriptedDevice::new(s.clone(), &track)?.with_timing(1.0, -script_start)
                    }
                    _ => {
                        let pose = tools.local_haptic().map_or(
                            ToolPose {
                                position: V3::zeros(),
                                orientation: Default::default(),
                                jaw: 0.0,
                            },
                            |(i, _)| ToolPose {
                                position: i.pose.translation.vector,
                                orientation: i.pose.rotation,
                                jaw: i.jaw,
                            },
                        );
                        ScriptedDevice::stationary(&tool, pose)
                    }
                };
                SiteDevice::Scripted {
                    // Forces are summarised by the loop's statistics; keep no records.
                    dev: dev.with_record_limit(0),
                    clock: clock.clone(),
                }
            }
        };
        if let Some(p) = rt_priority {
            RT_PRIORITY.store(p.clamp(1, 99), Ordering::Relaxed);
        }
        let config = HapticConfig {
            thread_setup: rt_priority.map(|_| raise_priority as fn()),
            ..HapticConfig::default()
        };
        let handle = haptic::spawn(dev, config)?;
        info!(device = handle.device_name(), "haptic loop started");
        Ok(HapticLoop {
            input: handle.input_reader(),
            handle,
            clock,
            follows_device,
            seen_fresh: false,
        })
    }

    /// The device's newest pose as the local tool's input, when the tool follows a real
    /// device (`None` before its first pose and for scripted devices). While the device is
    /// stale the last pose is held.
    pub fn device_input(&mut self) -> Option<sim_core::ToolInput> {
        if !self.follows_device {
            return None;
        }
        let (_, input) = self.input.latest()?;
        if !self.seen_fresh {
            if self.input.stale() {
                return None;
            }
            self.seen_fresh = true;
            info!("haptic device connected: the local tool follows it");
        }
        Some(sim_core::ToolInput::new(
            input.position,
            input.orientation,
            input.jaw,
        ))
    }

    /// After the contact pass of the step at simulated time `t`: the local tool's force,
    /// torque and local linear model (translational block) for the loop.
    pub fn publish(&self, tools: &Tools, t: f64) {
        self.clock.publish(t);
        let Some((input, local)) = tools.local_haptic() else {
            return;
        };
        let stiffness: Matrix3<f64> = local.stiffness.fixed_view::<3, 3>(0, 0).into_owned();
        self.handle.publish_model(&HapticModel {
            sim_time: t,
            tool_pose_at_sample: ToolPose {
                position: input.pose.translation.vector,
                orientation: input.pose.rotation,
                jaw: input.jaw,
            },
            // The contact's force and torque on the tool (sim-core leaves
            // `LocalModel::force`/`torque` at zero; only its stiffness is filled).
            force: tools.local_force(),
            torque: tools.local_torque(),
            stiffness,
            grasped: tools.local_grasped(),
        });
    }

    /// Starts teaching playback: playback time is simulated time since `start` (s).
    pub fn guide(&self, playback: TeachingPlayback, start: f64) {
        let clock = self.clock.clone();
        self.handle
            .set_guide_with_clock(playback, Arc::new(move || clock.now() - start));
    }

    /// Ends teaching playback.
    pub fn end_guide(&self) {
        self.handle.set_guide(None);
    }

    /// Stops the loop (a final zero force goes to the device).
    pub fn stop(self) -> HapticSummary {
        let device = self.handle.device_name().to_string();
        let (dev, stats) = self.handle.stop();
        let udp = match &dev {
            SiteDevice::Udp(d) => Some(d.stats()),
            SiteDevice::Scripted { .. } => None,
        };
        HapticSummary { stats, device, udp }
    }
}

impl HapticSummary {
    /// Fills the haptic fields of the report.
    pub fn report(&self, report: &mut SiteReport) {
        let s = self;
        let finite = |v: f64| v.is_finite().then_some(v);
        report.haptic_rate_hz = finite(s.stats.rate_hz);
        report.haptic_jitter_p99_us = finite(s.stats.jitter_p99_us);
        report.haptic_period_p50_us = finite(s.stats.period_p50_us);
        report.haptic_period_p99_us = finite(s.stats.period_p99_us);
        report.haptic_overruns = Some(s.stats.overruns);
        report.haptic_max_force_n = Some(s.stats.max_force);
        report.haptic_device = Some(s.device.clone());
        if let Some(u) = s.udp {
            report.device_poses_received = Some(u.received);
            report.device_forces_sent = Some(u.sent);
        }
        if s.stats.guide_ticks > 0 {
            report.guide_force_max_n = Some(s.stats.guide_force_max);
            report.guide_force_mean_n = Some(s.stats.guide_force_mean);
        }
    }
}

/// Poses kept per second of a teaching recording.
const TEACHING_INTERVAL: Duration = Duration::from_millis(10);
/// The guide holds the last recorded pose this long after the recording's end (s).
const GUIDE_HOLD: f64 = 0.25;

/// A trajectory being played back on this site.
struct Playing {
    id: u32,
    playback: TeachingPlayback,
    start: f64,
    dist_sum: f64,
    dist_max: f64,
    samples: u64,
}

/// Teaching mode of one site. The instructor records the poses its simulation gives the
/// local tool during each act (a contiguous run of driven steps) and sends each act to the
/// session as a [`TeachingTrajectory`] when it ends; a trainee whose local tool is the
/// trajectory's tool plays the newest one back as a guide force on its haptic device when
/// its own act starts (`script_start`), or at the time of an instructor's
/// `StartPlayback` command.
pub struct Teaching {
    role: Role,
    tool: Option<(usize, String)>,
    script_start: f64,
    /// Simulated time at which the trainee's act ends (script end; ∞ without a script).
    act_end: f64,
    recorder: Option<TeachingRecorder>,
    /// The newest completed recording (saved to `teaching.toml`).
    recorded: Option<TeachingRecorder>,
    next_id: u32,
    sent: u64,
    /// Trajectories received, by id (newest kept per id).
    received: BTreeMap<u32, TeachingTrajectory>,
    /// An instructor's `StartPlayback`: (trajectory, simulated start time).
    commanded: Option<(u32, f64)>,
    playing: Option<Playing>,
    /// Trajectory ids already played.
    played: Vec<u32>,
    dist_sum: f64,
    dist_max: f64,
    dist_samples: u64,
    /// Tip positions of the newest trajectory sent (instructor; m), for a window's guide.
    last_path: Vec<V3>,
}

impl Teaching {
    pub fn new(role: Role, tools: &Tools, script: Option<&ToolScript>, script_start: f64) -> Self {
        Teaching {
            role,
            tool: tools
                .local_index()
                .zip(tools.local_name().map(String::from)),
            script_start,
            act_end: script.map_or(f64::INFINITY, |s| script_start + s.duration()),
            recorder: None,
            recorded: None,
            next_id: 1,
            sent: 0,
            received: BTreeMap::new(),
            commanded: None,
            playing: None,
            played: Vec::new(),
            dist_sum: 0.0,
            dist_max: 0.0,
            dist_samples: 0,
            last_path: Vec::new(),
        }
    }

    /// Instructor: the id of the newest trajectory sent to the session, if any.
    pub fn last_sent(&self) -> Option<u32> {
        (self.sent > 0).then(|| self.next_id - 1)
    }

    /// Trainee: whether an instructor's playback is commanded or a guide is playing.
    pub fn guiding(&self) -> bool {
        self.commanded.is_some() || self.playing.is_some()
    }

    /// The tip path (m) a window draws as the teaching guide: the trajectory being played
    /// (trainee) or the newest one sent (instructor).
    pub fn guide_path(&self) -> Vec<V3> {
        let id = self
            .playing
            .as_ref()
            .map(|p| p.id)
            .or(self.commanded.map(|c| c.0));
        match id.and_then(|id| self.received.get(&id)) {
            Some(tr) => tr
                .samples
                .iter()
                .map(|s| V3::from(s.position.map(f64::from)))
                .collect(),
            None => self.last_path.clone(),
        }
    }

    /// Instructor, every step: records `local` (the input the simulation gives the tool
    /// in hand, `held`, at simulated time `t`). Only the tool teaching was set up with is
    /// recorded: another instrument in hand ends its act. Returns the trajectory to send
    /// when an act ended.
    pub fn record(
        &mut self,
        t: f64,
        held: Option<usize>,
        local: Option<&sim_core::ToolInput>,
    ) -> Option<Message> {
        if self.role != Role::Instructor {
            return None;
        }
        let (index, name) = self.tool.as_ref()?;
        match local.filter(|_| held == Some(*index)) {
            Some(input) => {
                let rec = self.recorder.get_or_insert_with(|| {
                    debug!(t, "teaching: recording the instructor's act");
                    TeachingRecorder::new(name, TEACHING_INTERVAL)
                        .expect("valid interval and tool name")
                        .with_title(&format!("instructor's {name} trajectory (teaching)"))
                });
                rec.push(&haptic::ToolInput {
                    time: Duration::from_secs_f64(t.max(0.0)),
                    position: input.pose.translation.vector,
                    orientation: input.pose.rotation,
                    jaw: input.jaw,
                    buttons: 0,
                });
                None
            }
            None => self.finish(),
        }
    }

    /// Ends a running recording (the act ended, or the run did): the trajectory message.
    pub fn finish(&mut self) -> Option<Message> {
        let rec = self.recorder.take()?;
        let (index, _) = self.tool.as_ref()?;
        let script = rec.to_script()?;
        let keys = script.tracks.values().next()?;
        if keys.len() < 2 {
            return None;
        }
        let samples = keys
            .iter()
            .map(|k| ToolSample {
                t_s: k.t,
                position: k.pose.position.map(|v| v as f32).into(),
                orientation: wxyz(&k.pose.orientation).map(|v| v as f32),
                jaw_rad: k.pose.jaw as f32,
            })
            .collect::<Vec<_>>();
        let id = self.next_id;
        self.next_id += 1;
        self.sent += 1;
        self.last_path = keys.iter().map(|k| k.pose.position).collect();
        info!(
            id,
            samples = samples.len(),
            seconds = keys.last().map_or(0.0, |k| k.t),
            "teaching: instructor's act recorded, sending it to the session"
        );
        self.recorded = Some(rec);
        Some(Message::Teaching(TeachingTrajectory {
            id,
            tool: *index as u8,
            samples,
        }))
    }

    /// A trajectory from the session.
    pub fn on_trajectory(&mut self, tr: TeachingTrajectory) {
        if self.role != Role::Trainee {
            return;
        }
        match &self.tool {
            Some((i, _)) if *i == tr.tool as usize => {
                info!(
                    id = tr.id,
                    samples = tr.samples.len(),
                    "teaching: trajectory received"
                );
                self.received.insert(tr.id, tr);
            }
            _ => debug!(
                id = tr.id,
                tool = tr.tool,
                "teaching: trajectory for another tool, not played"
            ),
        }
    }

    /// An instructor's command relayed by the coordinator.
    pub fn on_command(&mut self, c: Command, haptic: Option<&HapticLoop>) {
        match c {
            Command::StartPlayback {
                trajectory,
                start_sim_time_s,
            } => {
                self.commanded = Some((trajectory, start_sim_time_s));
                self.played.retain(|id| *id != trajectory);
            }
            Command::StopPlayback { trajectory } => {
                if self.commanded.is_some_and(|(id, _)| id == trajectory) {
                    self.commanded = None;
                }
                if self.playing.as_ref().is_some_and(|p| p.id == trajectory) {
                    self.stop_playing(haptic);
                }
            }
            other => debug!(?other, "command not handled by the site"),
        }
    }

    fn playback_of(&self, tr: &TeachingTrajectory) -> Option<TeachingPlayback> {
        let (_, name) = self.tool.as_ref()?;
        let mut keys: Vec<ToolWaypoint> = Vec::with_capacity(tr.samples.len());
        for s in &tr.samples {
            if keys.last().is_some_and(|k: &ToolWaypoint| s.t_s <= k.t) || !s.t_s.is_finite() {
                continue;
            }
            keys.push(ToolWaypoint {
                t: s.t_s,
                pose: ToolPose {
                    position: Vector3::from(s.position.map(f64::from)),
                    orientation: quat_wxyz(s.orientation.map(f64::from)),
                    jaw: s.jaw_rad.into(),
                },
                label: None,
            });
        }
        if keys.is_empty() {
            return None;
        }
        let mut script = ToolScript::default();
        script.tracks.insert(name.clone(), keys);
        TeachingPlayback::new(script, name, GuideSpring::default()).ok()
    }

    /// Trainee, every step after the contact pass at simulated time `t`, with the local
    /// tool's tip: starts and ends playback and measures the distance to the recorded tip.
    pub fn playback_step(&mut self, t: f64, tip: Option<V3>, haptic: Option<&HapticLoop>) {
        if self.role != Role::Trainee {
            return;
        }
        if self.playing.is_none() {
            let due = match self.commanded {
                Some((id, start)) => (t >= start && !self.played.contains(&id)).then_some(id),
                None => (t >= self.script_start && t <= self.act_end)
                    .then(|| self.received.keys().next_back().copied())
                    .flatten()
                    .filter(|id| !self.played.contains(id)),
            };
            if let Some(id) = due
                && let Some(tr) = self.received.get(&id)
                && let Some(playback) = self.playback_of(tr)
            {
                let start = match self.commanded {
                    Some((_, s)) => s,
                    None => t,
                };
                info!(
                    id,
                    start, "teaching: guiding the trainee along the trajectory"
                );
                if let Some(h) = haptic {
                    h.guide(playback.clone(), start);
                }
                self.played.push(id);
                self.playing = Some(Playing {
                    id,
                    playback,
                    start,
                    dist_sum: 0.0,
                    dist_max: 0.0,
                    samples: 0,
                });
            }
        }
        let Some(p) = self.playing.as_mut() else {
            return;
        };
        let tp = t - p.start;
        let duration = p.playback.duration();
        if tp <= duration
            && let Some(x) = tip
        {
            let d = (p.playback.target(tp.max(0.0)).position - x).norm();
            p.dist_sum += d;
            p.dist_max = p.dist_max.max(d);
            p.samples += 1;
        }
        if tp > duration + GUIDE_HOLD {
            self.stop_playing(haptic);
        }
    }

    fn stop_playing(&mut self, haptic: Option<&HapticLoop>) {
        let Some(p) = self.playing.take() else {
            return;
        };
        if let Some(h) = haptic {
            h.end_guide();
        }
        info!(
            id = p.id,
            mean_mm = 1e3 * p.dist_sum / p.samples.max(1) as f64,
            max_mm = 1e3 * p.dist_max,
            "teaching: playback ended"
        );
        self.dist_sum += p.dist_sum;
        self.dist_max = self.dist_max.max(p.dist_max);
        self.dist_samples += p.samples;
    }

    /// End of the run: ends playback and writes the newest recording to
    /// `<dir>/teaching.toml` (instructor).
    pub fn save(
        &mut self,
        dir: Option<&Path>,
        haptic: Option<&HapticLoop>,
    ) -> Result<Option<PathBuf>> {
        self.stop_playing(haptic);
        let (Some(dir), Some(rec)) = (dir, &self.recorded) else {
            return Ok(None);
        };
        std::fs::create_dir_all(dir)?;
        let path = dir.join("teaching.toml");
        rec.save(&path)?;
        Ok(Some(path))
    }

    /// Fills the teaching fields of the report.
    pub fn report(&self, report: &mut SiteReport) {
        if self.sent > 0 {
            report.teaching_sent = Some(self.sent);
        }
        if self.dist_samples > 0 {
            report.playback_distance_mm = Some(1e3 * self.dist_sum / self.dist_samples as f64);
            report.playback_distance_max_mm = Some(1e3 * self.dist_max);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim_core::sim_scene::builtin;
    use sim_core::sync::SyncStrategy;
    use sim_core::{SimOptions, Simulation};

    fn input(x: f64) -> sim_core::ToolInput {
        sim_core::ToolInput::new(
            V3::new(x, -0.1, -0.04),
            nalgebra::UnitQuaternion::identity(),
            0.3,
        )
    }

    #[test]
    fn instructor_act_to_trajectory_to_trainee_playback() {
        let scene = builtin::cholecystectomy();
        let sim = Simulation::new(scene.clone(), SimOptions::from_scene(&scene.scene)).unwrap();
        let forceps = Tools::new(&sim, &["forceps".into()], SyncStrategy::Keyframe).unwrap();
        let probe = Tools::new(&sim, &["probe".into()], SyncStrategy::Keyframe).unwrap();
        let dt = 0.004;

        // Instructor: idle, then an act moving 1 cm/s along x for 1 s, then idle.
        let mut prof = Teaching::new(Role::Instructor, &forceps, None, 0.0);
        let mut sent = Vec::new();
        for k in 0..400 {
            let t = k as f64 * dt;
            let local = (0.2..=1.2).contains(&t).then(|| input(0.01 * (t - 0.2)));
            sent.extend(prof.record(t, forceps.local_index(), local.as_ref()));
        }
        assert!(prof.finish().is_none(), "the act was already sent");
        let [Message::Teaching(tr)] = &sent[..] else {
            panic!("one trajectory expected: {sent:?}")
        };
        assert_eq!(
            (tr.id, tr.tool as usize),
            (1, forceps.local_index().unwrap())
        );
        let last = tr.samples.last().unwrap();
        assert!((last.t_s - 1.0).abs() < 0.005, "{}", last.t_s);
        assert!((f64::from(last.position[0]) - 0.01 * last.t_s).abs() < 1e-6);
        assert!(tr.samples.windows(2).all(|w| w[1].t_s > w[0].t_s));

        // A trainee with another tool ignores it; one with the forceps plays it from its
        // act's start (2 s), measuring its tip 3 mm off the recorded one.
        let mut other = Teaching::new(Role::Trainee, &probe, None, 2.0);
        other.on_trajectory(tr.clone());
        let mut student = Teaching::new(Role::Trainee, &forceps, None, 2.0);
        student.on_trajectory(tr.clone());
        for k in 0..1000 {
            let t = k as f64 * dt;
            let x = 0.01 * (t - 2.0).clamp(0.0, 1.0) + 0.003;
            let tip = V3::new(x, -0.1, -0.04);
            other.playback_step(t, Some(tip), None);
            student.playback_step(t, Some(tip), None);
        }
        let mut r = SiteReport::default();
        other.report(&mut r);
        assert!(r.playback_distance_mm.is_none());
        student.report(&mut r);
        let d = r.playback_distance_mm.unwrap();
        assert!((d - 3.0).abs() < 0.05, "{d} mm");
        assert!(r.playback_distance_max_mm.unwrap() < 3.1);

        // An instructor's StartPlayback moves the start; StopPlayback ends it.
        let mut late = Teaching::new(Role::Trainee, &forceps, None, 0.0);
        late.on_trajectory(tr.clone());
        late.on_command(
            Command::StartPlayback {
                trajectory: 1,
                start_sim_time_s: 3.0,
            },
            None,
        );
        late.playback_step(2.9, Some(V3::zeros()), None);
        assert!(late.playing.is_none());
        late.playback_step(3.0, Some(V3::zeros()), None);
        assert_eq!(late.playing.as_ref().map(|p| p.start), Some(3.0));
        late.on_command(Command::StopPlayback { trajectory: 1 }, None);
        assert!(late.playing.is_none());
    }

    #[test]
    fn real_time_priority_fails_soft() {
        // Whether or not the process may use SCHED_FIFO, the call returns normally.
        RT_PRIORITY.store(1, Ordering::Relaxed);
        std::thread::spawn(raise_priority).join().unwrap();
    }
}
