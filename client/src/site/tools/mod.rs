//! The scene's tools at a site: the local tool's input, remote tools sampled at the site's
//! simulated time, and their contact with the organ (sim-core's `Interaction`).

use std::collections::VecDeque;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::Vector3;
use sim_core::contact::LocalModel;
use sim_core::sim_scene::ToolScript;
use sim_core::sync::SyncStrategy;
use sim_core::{Interaction, Simulation, ToolInput};

use crate::output::ToolFrame;
use crate::session::SiteSession;
use crate::session::pacing::INPUT_EXTRAPOLATION_S;

/// A local tool that rests after this site drove it still announces its pose (and its
/// jaw) this often (s of simulated time), until another site drives it. A site that missed
/// its last samples (a link lost, a late join) would otherwise go on simulating it where
/// it last heard of it. Measured: after the `outage` preset's 3 s cut, the instructor's
/// script ended before its link came back, and a trainee's copy of the forceps stayed
/// closed on the tissue, holding its organ 12.5 mm from the instructor's to the end.
pub const IDLE_POSE_INTERVAL_S: f64 = 0.25;

/// A remote tool's sample more than this (s of simulated time) after the one before it
/// starts its stream again (longer than [`IDLE_POSE_INTERVAL_S`]).
const STREAM_GAP_S: f64 = 0.3;
/// The local tool counts as moving (its site leads) for this long (s of simulated time)
/// after its input last moved it.
pub const LEADS_AFTER_MOTION_S: f64 = 0.5;
/// Input changes at or below these (m, rad, rad of jaw) are no motion: a script holding a
/// pose interpolates between equal waypoints to within rounding.
const STILL_M: f64 = 1e-7;
const STILL_RAD: f64 = 1e-6;

/// Under hybrid: the longest a follower's step waits for a late input of a remote tool that
/// touches tissue (s of session time), and the latest such an input may be (s of simulated
/// time) for the wait to start ([`Tools::input_awaited`], [`InputWait`]). Past it the tool
/// is carried on at its last rate for up to [`INPUT_EXTRAPOLATION_S`] past its newest
/// sample, then held. (The two are equal by choice, not by necessity: a wait as long as the
/// carrying on covers the same lateness.)
///
/// Measured with `cosurg bench sync` (hybrid, ×2, seeds 11–15, 2026-11-28). At 50 ms, the
/// value before, every equal-sites mark above 0.1 mm was a tool carried on past a stop
/// after its wait ran out: the forceps' approach stopping on the fundus (2.0 s) or the lift
/// stopping (3.5 s), pushed on 1.5–2 mm by a follower whose samples came about 130 ms late
/// after a long loss burst; worst seed of `burst` 1.13 mm in two runs of three, of `poor`
/// 1.37. At 150 ms: 0.13 and 0.12 mm. Without the lateness bound every step of a 3 s
/// outage waited (display delay 1.35 s); with it, a stream that stays silent is waited for
/// once.
pub const MAX_INPUT_WAIT_S: f64 = INPUT_EXTRAPOLATION_S;

/// A follower's wait for a late remote input (see [`MAX_INPUT_WAIT_S`]): at most that long
/// (session time) for each newest sample, so a stream that stays silent (an outage, a site
/// gone) costs one wait, and a burst of losses one per sample that arrives still late.
#[derive(Debug, Default)]
pub struct InputWait {
    /// The remote tool and its newest sample (simulated time) waited past, and since when
    /// (several tools may have samples of the same time).
    waiting: Option<((usize, f64), Instant)>,
}

impl InputWait {
    /// Whether to wait now: `awaited` is [`Tools::input_awaited`]'s answer for this step
    /// (shortfall and newest sample time), `now` the session clock. Returns the shortfall
    /// (s) while the step should wait.
    pub fn waits(&mut self, awaited: Option<(f64, (usize, f64))>, now: Instant) -> Option<f64> {
        let (short, newest) = awaited?;
        let since = match self.waiting {
            Some((sample, since)) if sample == newest => since,
            _ => {
                self.waiting = Some((newest, now));
                now
            }
        };
        ((now - since).as_secs_f64() < MAX_INPUT_WAIT_S).then_some(short)
    }
}

type V3 = Vector3<f64>;

/// The scene's tools and their contact with the organ (sim-core's [`Interaction`]).
///
/// The local tool follows this site's input. Remote tools follow their owners' pose
/// datagrams; under the input-only strategy they touch the local organ too, otherwise
/// they are only drawn (their effect arrives with the keyframes).
pub struct Tools {
    interaction: Interaction,
    /// The tool in this site's hand now (scene index).
    local: Option<usize>,
    /// Every tool this site drives, the one in hand at the start first: a script with
    /// tracks for several of them exchanges the instrument in hand as its tracks begin
    /// (one instrument at a time, as through one port).
    instruments: Vec<usize>,
    remote_contact: bool,
    /// Under hybrid a follower waits for a late input ([`Tools::input_awaited`]).
    waits_for_inputs: bool,
    /// Poses of each tool from other sites, by their simulation time.
    remote_track: Vec<PoseTrack>,
    /// Each remote pose sampled at this step's simulation time (what is simulated and
    /// drawn).
    remote: Vec<Option<ToolInput>>,
    /// The site whose poses each remote tool follows (the newest pose's sender).
    remote_site: Vec<Option<proto::SiteId>>,
    /// Whether the local tool is being driven this step (its script is running).
    local_active: bool,
    /// Simulated time (s) at which the local input last moved the tool in hand.
    local_moved_at: Option<f64>,
    /// While the local tool rests after this site drove it (and nobody else has driven it
    /// since): that tool and the simulated time its held pose is next announced (see
    /// [`IDLE_POSE_INTERVAL_S`]).
    idle_announce: Option<(usize, f64)>,
    /// Per remote tool: the step (`at`, s) at which its stream last resumed after a gap;
    /// every sample arriving for that step (one datagram carries several) is exempt from
    /// the lateness count.
    resumed_at: Vec<Option<f64>>,
    /// Touch radius around contacts for region ownership (m).
    touch_radius: f64,
}

impl Tools {
    /// The scene's tools; this site drives `instruments` (scene tool names, the one in
    /// hand at the start first; empty: none).
    pub fn new(sim: &Simulation, instruments: &[String], strategy: SyncStrategy) -> Result<Self> {
        let mut interaction = Interaction::new(sim);
        let instruments = instruments
            .iter()
            .map(|name| {
                interaction
                    .tools
                    .index(name)
                    .with_context(|| format!("tool {name:?} is not in the scene"))
            })
            .collect::<Result<Vec<_>>>()?;
        Self::enable_own(&mut interaction, &instruments);
        Ok(Tools {
            remote: vec![None; interaction.tools.len()],
            remote_site: vec![None; interaction.tools.len()],
            remote_track: vec![PoseTrack::default(); interaction.tools.len()],
            resumed_at: vec![None; interaction.tools.len()],
            interaction,
            local: instruments.first().copied(),
            instruments,
            remote_contact: strategy.simulates_remote_tools(),
            waits_for_inputs: strategy == SyncStrategy::Hybrid,
            local_active: false,
            local_moved_at: None,
            idle_announce: None,
            touch_radius: 2.0 * sim.lattice().params().cell,
        })
    }

    /// The topology ops (cuts, releases, clips, refinement decisions) our tools made
    /// since the last call, to share.
    pub fn take_topology_ops(&mut self) -> Vec<sim_core::cut::TopologyOp> {
        let mut ops = std::mem::take(&mut self.interaction.blades.made);
        ops.append(&mut self.interaction.hooks.made);
        ops.append(&mut self.interaction.clips.made);
        ops.append(&mut self.interaction.adapt.made);
        ops
    }

    /// Only the tools this site drives tear their grasp loose: a remote tool lets go when
    /// its site opens the jaws (see `ContactPipeline::grasp_tears`). Cutting, dissecting
    /// and clipping are enabled step by step in [`Tools::before_step`]: the others' cuts,
    /// releases and clips arrive as ops.
    fn enable_own(interaction: &mut Interaction, instruments: &[usize]) {
        let own: Vec<bool> = (0..interaction.tools.len())
            .map(|i| instruments.contains(&i))
            .collect();
        let none = vec![false; own.len()];
        interaction.blades.enabled = none.clone();
        interaction.hooks.enabled = none.clone();
        interaction.clips.enabled = none;
        interaction.contact.grasp_tears = own;
    }

    /// After a scene reset: contact starts again on the rebuilt simulation (grasps and
    /// contact state of the old one are gone); remote tool tracks are kept.
    pub fn reset(&mut self, sim: &Simulation) {
        self.interaction = Interaction::new(sim);
        Self::enable_own(&mut self.interaction, &self.instruments);
        self.local = self.instruments.first().copied();
        self.idle_announce = None;
        self.local_moved_at = None;
        self.touch_radius = 2.0 * sim.lattice().params().cell;
    }

    /// The local tool's input at script time `t` (s), while the script runs.
    ///
    /// With several instruments, the one whose track spans `t` is taken in hand (the first
    /// in instrument order if tracks overlap); between tracks none is driven and the last
    /// one stays in hand.
    pub fn local_input(&mut self, script: Option<&ToolScript>, t: f64) -> Option<ToolInput> {
        let s = script?;
        if t < 0.0 || t > s.duration() {
            return None;
        }
        if self.instruments.len() > 1 {
            let tools = &self.interaction.tools.tools;
            let (i, pose) = self.instruments.iter().find_map(|&i| {
                let name = &tools[i].name;
                let (start, end) = s.track_span(name)?;
                (start <= t && t <= end).then(|| s.sample(name, t).map(|p| (i, p)))?
            })?;
            self.local = Some(i);
            return Some(ToolInput::from(&pose));
        }
        let tool = &self.interaction.tools.tools[self.local?];
        // A script with one track drives whichever tool it is given to.
        s.sample(&tool.name, t)
            .or_else(|| s.tools().next().and_then(|n| s.sample(n, t)))
            .map(|p| ToolInput::from(&p))
    }

    /// Every tool this site drives (scene indices), the one in hand at the start first.
    pub fn instruments(&self) -> &[usize] {
        &self.instruments
    }

    /// Takes the next instrument in hand (the window's `T`): the next of this site's tools
    /// in scene order after the one in hand, wrapping round. Returns its name; `None` when
    /// the site has fewer than two instruments.
    pub fn next_instrument(&mut self) -> Option<&str> {
        if self.instruments.len() < 2 {
            return None;
        }
        let mut order = self.instruments.clone();
        order.sort_unstable();
        let pos = self
            .local
            .and_then(|l| order.iter().position(|&i| i == l))
            .map_or(0, |p| (p + 1) % order.len());
        self.local = Some(order[pos]);
        Some(self.interaction.tools.tools[order[pos]].name.as_str())
    }

    /// Sets every tool's input, runs contact (and tool-following adaptivity) before the
    /// step, and returns the regions the local tool touches.
    pub fn before_step(
        &mut self,
        sim: &mut Simulation,
        local: Option<ToolInput>,
        session: &SiteSession,
    ) -> Result<Vec<u32>> {
        self.note_local_motion(local.as_ref(), sim.time());
        self.note_local_input(local.is_some(), sim.time());
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
                // Between its own acts, a site's tool follows whoever else drives it
                // (hybrid and input-only: every site simulates every tool).
                if Some(i) == self.local
                    && let Some(l) = local
                {
                    l
                } else if self.remote_contact {
                    self.remote[i].unwrap_or(keep)
                } else {
                    keep
                }
            })
            .collect();
        // Only the instrument in hand, while this site drives it, cuts, dissects and
        // clips: a site that simulates another site's act with a tool it also drives at
        // other times would otherwise make the same cut twice.
        let inter = &mut self.interaction;
        for i in 0..inputs.len() {
            let driven = Some(i) == self.local && local.is_some();
            inter.blades.enabled[i] = driven;
            inter.hooks.enabled[i] = driven;
            inter.clips.enabled[i] = driven;
        }
        // Under hybrid and input-only sync, refinement around a tool is decided by the
        // site that drives it and applied everywhere at the time its session schedules
        // (`sim_core::adapt`); otherwise a site decides for every tool. Every tool keeps
        // diamonds from merging.
        let shared = session.times_topology();
        inter.adapt.enabled = (0..inputs.len())
            .map(|i| !shared || (Some(i) == self.local && local.is_some()))
            .collect();
        self.interaction.blades.site = session.site_id().map_or(0, u32::from);
        // Under hybrid and input-only sync our cuts and releases are applied when the
        // session schedules them (see `SiteSession::share_topology`).
        self.interaction.blades.apply_own = !session.times_topology();
        self.interaction.hooks.apply_own = !session.times_topology();
        self.interaction.adapt.apply_own = !session.times_topology();
        self.interaction.adapt.site = self.interaction.blades.site;
        self.interaction.hooks.site = self.interaction.blades.site;
        self.interaction.clips.site = self.interaction.blades.site;
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
        Ok(session.regions_near(sim, &centre, radius))
    }

    /// A pose of a tool from another site (held until our simulation time reaches it).
    ///
    /// `at` (s) is the simulated time of the next step's input (`sim.time() + dt`).
    /// Returns how late a new sample of a tool this site simulates arrived: `at` minus
    /// its time (positive: the simulation had already used a held pose in its place);
    /// `None` for repeats, for samples older than one already held (they fill a gap), for
    /// tools that are only drawn, and for the samples handled at the step the tool's stream
    /// starts or resumes after a gap ([`STREAM_GAP_S`]).
    pub fn remote_pose(&mut self, p: &proto::ToolPose, at: f64) -> Option<f64> {
        if let Some(site) = self.remote_site.get_mut(p.tool as usize) {
            *site = Some(p.site);
        }
        if self
            .idle_announce
            .is_some_and(|(tool, _)| tool == p.tool as usize)
            && !self.local_active
        {
            // Another site drives our instrument now: its pose is no longer ours to tell.
            self.idle_announce = None;
        }
        let simulated = self.remote_contact && Some(p.tool as usize) != self.local;
        if let Some(track) = self.remote_track.get_mut(p.tool as usize) {
            // The first sample after a gap in the tool's stream (its site was cut off,
            // rejoined, or its tool rested unannounced) was not waited for: its lateness
            // says nothing of the path (measured: samples 0.3–0.5 s late after the
            // `outage` preset's cut raised a trainee's lag to 450 ms for the rest of the
            // run).
            let gap = track
                .poses
                .back()
                .is_none_or(|(newest, _)| p.sim_time_s - newest > STREAM_GAP_S);
            let resumed = match self.resumed_at.get_mut(p.tool as usize) {
                Some(slot) => {
                    if gap {
                        *slot = Some(at);
                    }
                    gap || *slot == Some(at)
                }
                None => gap,
            };
            // Only a sample newer than any before tells how late its datagram came: the
            // older ones a datagram repeats (handed over after its newest) fill gaps.
            let newest = track.poses.back().is_none_or(|(t, _)| p.sim_time_s > *t);
            let q = p.orientation.map(f64::from);
            let new = track.insert(
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
            return (new && newest && simulated && !resumed).then_some(at - p.sim_time_s);
        }
        None
    }

    /// How far (s) the newest sample of a remote tool this site simulates falls short of
    /// `at` (the next step's input time), for a tool that is being driven (its newest two
    /// samples within [`PoseTrack::RATE_FROM_WITHIN_S`]) and touches or holds tissue. There
    /// a jaw that closes or opens decides what the tissue does, and a tool carried on past
    /// its newest sample grasps or lets go late: in `cosurg bench sync` (hybrid, `average`,
    /// 2026-11-27) every divergence above 0.1 mm on equal sites came at the grasp (2.0 s)
    /// or the release (5.25 s), with inputs 40–56 ms late. Only a shortfall of at most
    /// `within` (s) counts (a stream silent for longer has stopped or lost samples for
    /// good, and is carried on); only under hybrid (input-only's lag keeps a margin, and
    /// its rows were measured without waiting). Returns the largest such shortfall, and that
    /// tool with its newest sample time; `None`: nothing to wait for.
    pub fn input_awaited(&self, at: f64, within: f64) -> Option<(f64, (usize, f64))> {
        if !self.waits_for_inputs {
            return None;
        }
        let state = self.interaction.state();
        self.remote_track
            .iter()
            .enumerate()
            .filter(|(i, _)| Some(*i) != self.local)
            .filter(|(i, _)| {
                state
                    .tools
                    .get(*i)
                    .is_some_and(|c| c.grasped > 0 || !c.contacts.is_empty())
            })
            .filter_map(|(i, track)| {
                let mut times = track.poses.iter().rev().map(|p| p.0);
                let (t1, t0) = (times.next()?, times.next()?);
                let driven = t1 - t0 <= PoseTrack::RATE_FROM_WITHIN_S;
                (driven && at > t1 && at - t1 <= within).then_some((at - t1, (i, t1)))
            })
            .reduce(|a, b| if b.0 > a.0 { b } else { a })
    }

    /// The site that last sent a pose of tool `i` (the one that moves it), if any.
    pub fn remote_site(&self, i: usize) -> Option<proto::SiteId> {
        self.remote_site.get(i).copied().flatten()
    }

    /// Whether the local tool was driven in the last step (its poses are then sent every
    /// step).
    pub fn local_active(&self) -> bool {
        self.local_active
    }

    /// Whether the local tool is driven and moved within [`LEADS_AFTER_MOTION_S`] before
    /// simulated time `t` (s): its site then leads (runs level with the other leaders, no
    /// playout lag). A tool held still by its script or its hand, touching nothing, does
    /// not: its site keeps the lag behind the sites it follows and gets their inputs in
    /// time. (Counting every driven step, the demo's trainees, whose scripts hold a
    /// resting pose for seconds, ran level with the instructor and simulated its grasp
    /// from inputs a path's delay late: 4.6–5.3 mm off during the lift under `average`.)
    /// A tool at rest that touches tissue still makes its site lead through the regions
    /// it claims.
    pub fn local_moving(&self, t: f64) -> bool {
        self.local_active
            && self
                .local_moved_at
                .is_some_and(|m| t - m <= LEADS_AFTER_MOTION_S)
    }

    /// Force of the tissue on the local tool (N).
    pub fn local_force(&self) -> V3 {
        self.local
            .and_then(|i| self.interaction.state().tools.get(i))
            .map_or(V3::zeros(), |t| t.force)
    }

    /// The tools and their contact state (what a recording samples).
    pub fn interaction(&self) -> &Interaction {
        &self.interaction
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

    /// Before the local input of the step from `t` (s) is set: whether it moves the tool
    /// in hand (see [`Tools::local_moving`]).
    fn note_local_motion(&mut self, local: Option<&ToolInput>, t: f64) {
        if let Some((input, i)) = local.zip(self.local) {
            let tool = &self.interaction.tools.tools[i];
            let moved = (input.pose.translation.vector - tool.pose().translation.vector).norm()
                > STILL_M
                || input.pose.rotation.angle_to(&tool.pose().rotation) > STILL_RAD
                || (input.jaw - tool.jaw()).abs() > STILL_RAD;
            if moved {
                self.local_moved_at = Some(t);
            }
        }
    }

    /// The local tool is driven this step (`active`, at simulated time `t`, s) or rests.
    /// Once it rests, its pose keeps being announced every [`IDLE_POSE_INTERVAL_S`].
    fn note_local_input(&mut self, active: bool, t: f64) {
        self.local_active = active;
        if active && let Some(i) = self.local {
            self.idle_announce = Some((i, t + IDLE_POSE_INTERVAL_S));
        }
    }

    /// The local tool's pose for the others: while it is being driven, and every
    /// [`IDLE_POSE_INTERVAL_S`] while it rests after this site drove it.
    pub fn local_pose_message(&mut self, site: proto::SiteId, t: f64) -> Option<proto::ToolPose> {
        let i = self.local?;
        if !self.local_active {
            // Only the instrument this site drove last, while in hand.
            if !self
                .idle_announce
                .is_some_and(|(tool, at)| tool == i && t >= at)
            {
                return None;
            }
            self.idle_announce = Some((i, t + IDLE_POSE_INTERVAL_S));
        }
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
/// for the orientation); before the first pose, the first one; after the newest, the
/// newest one's position and jaw carried on at their last rate for at most
/// [`INPUT_EXTRAPOLATION_S`] (the orientation held), then held.
///
/// Why extrapolate: a sample that arrives after the follower's clock needs it (jitter
/// beyond the playout lag) would otherwise leave the tool frozen at its newest pose for
/// those steps, and a jaw frozen just short of its release angle lets go of the tissue
/// late (the fundus then springs back tens of millimetres on the owner only). Carried on
/// at its last rate, the jaw crosses the angle within a step of the owner's.
#[derive(Clone, Debug, Default)]
struct PoseTrack {
    poses: VecDeque<(f64, ToolInput)>,
}

impl PoseTrack {
    /// Simulated seconds of poses kept behind the newest (covers any playout lag).
    const KEEP_S: f64 = 2.0;
    /// The last two samples give the rate to carry on only if they are this close (s).
    const RATE_FROM_WITHIN_S: f64 = 0.05;

    /// Adds a sample; whether it is new (not a repeat carried by a later datagram).
    fn insert(&mut self, t: f64, input: ToolInput) -> bool {
        // Datagrams may be reordered: keep the track sorted by time.
        let i = self.poses.partition_point(|(pt, _)| *pt < t);
        let new = match self.poses.get_mut(i) {
            Some(slot) if slot.0 == t => {
                slot.1 = input;
                false
            }
            _ => {
                self.poses.insert(i, (t, input));
                true
            }
        };
        let newest = self.poses.back().map_or(t, |p| p.0);
        while self.poses.len() > 2
            && self
                .poses
                .front()
                .is_some_and(|p| newest - p.0 > Self::KEEP_S)
        {
            self.poses.pop_front();
        }
        new
    }

    /// The newest pose carried on to `t` (≥ its time); see the type's documentation.
    fn extrapolate(&self, t: f64) -> ToolInput {
        let n = self.poses.len();
        let (t1, b) = self.poses[n - 1];
        let Some(&(t0, a)) = (n >= 2).then(|| &self.poses[n - 2]) else {
            return b;
        };
        let span = t1 - t0;
        if !(span > 0.0 && span <= Self::RATE_FROM_WITHIN_S) {
            return b;
        }
        let s = (t - t1).min(INPUT_EXTRAPOLATION_S) / span;
        let position =
            b.pose.translation.vector + (b.pose.translation.vector - a.pose.translation.vector) * s;
        ToolInput {
            pose: nalgebra::Isometry3::from_parts(position.into(), b.pose.rotation),
            // Jaw angles are ≥ 0 (closed).
            jaw: (b.jaw + (b.jaw - a.jaw) * s).max(0.0),
        }
    }

    fn sample(&self, t: f64) -> Option<ToolInput> {
        let (first, last) = (self.poses.front()?, self.poses.back()?);
        if t <= first.0 {
            return Some(first.1);
        }
        if t >= last.0 {
            return Some(self.extrapolate(t));
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

#[cfg(test)]
mod tests;
