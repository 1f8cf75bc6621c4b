//! The site's simulation loop.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use serde::{Deserialize, Serialize};
use tracing::{debug, info, warn};

use proto::{Message, Role};
use sim_core::sim_scene::{LoadedScene, ToolScript};
use sim_core::{SimOptions, Simulation};

use super::glue::{self, Outgoing, SyncState};
use super::pacing::{PeerClocks, PlayoutLag};
use crate::cli::Refused;
use crate::link::{Link, LinkConfig, LinkEvent};
use crate::output::{Frame, SeriesWriter};
use crate::stats::percentile;

/// How the sites share the interaction (`--strategy`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    /// The report's method: keyframes of owned local regions, tree-state XOR and
    /// second-order extrapolation between keyframes.
    Keyframe,
    /// Every node of the organ, every frame, from the owning site.
    FullState,
    /// Only tool poses; every site simulates every tool's contacts itself.
    InputOnly,
}

impl Strategy {
    pub fn name(self) -> &'static str {
        match self {
            Strategy::Keyframe => "keyframe",
            Strategy::FullState => "full-state",
            Strategy::InputOnly => "input-only",
        }
    }
}

/// Progress report: (simulated time in s, a short status line).
pub type ProgressCallback = Box<dyn FnMut(f64, &str) + Send>;

/// Everything a site needs to run.
pub struct SiteConfig {
    pub name: String,
    pub role: Role,
    pub scene: LoadedScene,
    pub options: SimOptions,
    /// The scene tool this site drives (by name); `None`: no local tool (observer).
    pub tool: Option<String>,
    /// Trajectory of the local tool, played in simulation time from `script_start`.
    pub script: Option<ToolScript>,
    pub script_start: f64,
    /// Simulated seconds to run.
    pub seconds: f64,
    pub strategy: Strategy,
    /// Extra CPU cost per step as a factor of the step's own cost (1 = none, 3 = three
    /// times slower), like a laptop beside a workstation.
    pub slowdown: f64,
    /// Output folder: surface recordings (`surfaces.surf`), VTU/PVD frames, report.
    pub out: Option<PathBuf>,
    /// Simulated time between VTU frames (s); `None`: no VTU.
    pub vtu_interval: Option<f64>,
    /// Coordinator link; `None`: a site on its own.
    pub link: Option<LinkConfig>,
    /// Start the simulation only when this many sites (including this one) have joined.
    pub expect_sites: usize,
    /// Pace steps to wall-clock time (true) or run as fast as possible (false).
    pub realtime: bool,
    /// How far a site that follows another site's regions or tool keeps its simulation
    /// time behind that site's (`site::pacing`).
    pub playout_lag: PlayoutLag,
    /// Run the 1 kHz haptic loop beside the simulation.
    pub haptics: bool,
    /// Where the local tool's input comes from: the script, or a real device over UDP
    /// (the tool then follows the device and the haptic loop renders forces back to it;
    /// needs `haptics`).
    pub device: glue::DeviceSpec,
    /// SCHED_FIFO priority of the haptic thread (`None`: normal priority; fails soft).
    pub rt_priority: Option<i32>,
    /// Called about every 0.25 s of simulated time with (sim time s, a short status).
    pub on_progress: Option<ProgressCallback>,
}

/// What a site did, printed by `cosurg join` and collected by `cosurg demo`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SiteReport {
    pub name: String,
    pub role: String,
    pub strategy: String,
    pub site_id: Option<u16>,
    pub scene_hash: String,
    /// Simulated seconds and the wall-clock seconds they took.
    pub sim_seconds: f64,
    pub wall_seconds: f64,
    /// Simulation steps per wall-clock second.
    pub sim_rate_hz: f64,
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
    pub keyframes_sent: u64,
    pub keyframes_received: u64,
    pub keyframes_applied: u64,
    /// CPU time per applied keyframe (µs): tree-state XOR, takeover, extrapolation setup.
    pub apply_us_per_keyframe: f64,
    /// Application bytes per second over the run (UDP bytes in `udp_*`).
    pub up_bytes_per_s: f64,
    pub down_bytes_per_s: f64,
    pub udp_up_bytes_per_s: f64,
    pub udp_down_bytes_per_s: f64,
    /// Filled by the demo / sync bench from the recordings of all sites (mm).
    pub divergence_max_mm: Option<f64>,
    pub divergence_rms_mm: Option<f64>,
    /// Clock estimate against the coordinator at the end (µs).
    pub clock_offset_us: Option<f64>,
    pub rtt_us: Option<u64>,
    /// Region ownership this site held: (region, from sim time s, to sim time s).
    pub owned: Vec<(u32, f64, f64)>,
    /// Surface recordings (every 50 ms of simulated time).
    pub surf_file: Option<PathBuf>,
    pub reconnects: u64,
    /// Haptic loop: ticks per second and p99 period jitter (µs).
    pub haptic_rate_hz: Option<f64>,
    pub haptic_jitter_p99_us: Option<f64>,
    /// Haptic tick period p50 / p99 (µs), ticks more than half a period late, largest
    /// force sent to the device (N), and the device's name.
    pub haptic_period_p50_us: Option<f64>,
    pub haptic_period_p99_us: Option<f64>,
    pub haptic_overruns: Option<u64>,
    pub haptic_max_force_n: Option<f64>,
    pub haptic_device: Option<String>,
    /// UDP device (`--device udp:…`): pose datagrams accepted, force datagrams sent.
    pub device_poses_received: Option<u64>,
    pub device_forces_sent: Option<u64>,
    /// Teaching, instructor: trajectories sent to the session, and the newest one saved
    /// as a tool script (`<out>/teaching.toml`).
    pub teaching_sent: Option<u64>,
    pub teaching_file: Option<PathBuf>,
    /// Teaching, trainee: the guide force felt on the haptic device during playback (N),
    /// and the distance between the local tool tip and the recorded tip (mm).
    pub guide_force_max_n: Option<f64>,
    pub guide_force_mean_n: Option<f64>,
    pub playback_distance_mm: Option<f64>,
    pub playback_distance_max_mm: Option<f64>,
    /// Contact force on the local tool, max magnitude over the run (N).
    pub max_tool_force_n: f64,
    /// Wall time spent waiting so as not to run ahead of the owners' clocks (s).
    #[serde(default)]
    pub paced_seconds: f64,
    /// Display delay: mean simulation-time lag behind the sites followed (ms), over the
    /// steps this site followed another without leading itself; 0 if it never did.
    #[serde(default)]
    pub playout_lag_ms: f64,
    /// The playout lag aimed at at the end of the run (ms).
    #[serde(default)]
    pub playout_target_ms: f64,
}

/// Simulated time between surface recordings (s).
pub const RECORD_INTERVAL: f64 = 0.05;
/// A site releases a region this long after its tool last touched it (s).
const RELEASE_AFTER: f64 = 0.4;

/// Runs a site to completion.
pub fn run_site(mut cfg: SiteConfig) -> Result<SiteReport> {
    let dt = cfg.options.dt;
    let steps = (cfg.seconds / dt).round().max(1.0) as u64;
    let scene_hash = cfg.scene.hash.clone();
    let mut sim = Simulation::new(cfg.scene.clone(), cfg.options.clone())?;
    let mut tools = glue::Tools::new(&sim, cfg.tool.as_deref(), cfg.strategy)?;
    let mut sync = SyncState::new(&sim, cfg.strategy);
    let mut recorder = glue::Recorder::new(&sim, RECORD_INTERVAL);
    // VTU frames are captured on the simulation thread and written on another, so that
    // file output never stretches a step.
    let writer = match (&cfg.out, cfg.vtu_interval) {
        (Some(dir), Some(_)) => {
            let mut w = SeriesWriter::new(&dir.join("vtu"))?;
            let (tx, rx) = std::sync::mpsc::channel::<Frame>();
            let handle = std::thread::spawn(move || -> Result<SeriesWriter> {
                for frame in rx {
                    w.write(&frame)?;
                }
                Ok(w)
            });
            Some((tx, handle))
        }
        _ => None,
    };
    let mut report = SiteReport {
        name: cfg.name.clone(),
        role: format!("{:?}", cfg.role).to_lowercase(),
        strategy: cfg.strategy.name().into(),
        scene_hash: scene_hash.clone(),
        ..Default::default()
    };

    // The link lives on a small tokio runtime of its own; the simulation thread only
    // polls it.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the network runtime")?;
    let link = match cfg.link.clone() {
        Some(lc) => Some(Link::start(lc, runtime.handle())?),
        None => None,
    };
    let mut pending: Vec<Message> = Vec::new();
    let mut me: Option<u16> = None;
    let mut sites: BTreeMap<u16, (String, Role)> = BTreeMap::new();
    if let Some(link) = &link {
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut got_snapshot = false;
        let mut welcomed_at: Option<Instant> = None;
        // Join, then wait for the expected number of sites: all sites then start their
        // simulation clocks within about one round trip of each other.
        loop {
            if Instant::now() > deadline {
                bail!(
                    "site {}: timed out waiting for the session ({} of {} sites)",
                    cfg.name,
                    sites.len(),
                    cfg.expect_sites
                );
            }
            match link.recv_timeout(Duration::from_millis(50)) {
                Some(LinkEvent::Welcome(w)) => {
                    welcomed_at = Some(Instant::now());
                    me = Some(w.site);
                    for s in w.sites {
                        sites.insert(s.site, (s.name, s.role));
                    }
                }
                Some(LinkEvent::Refused(r)) => {
                    return Err(Refused(format!("{:?}: {}", r.reason, r.text)).into());
                }
                Some(LinkEvent::Stopped { reason }) => bail!("link stopped: {reason}"),
                Some(LinkEvent::ConnectFailed { error, will_retry }) => {
                    warn!(site = %cfg.name, %error, will_retry, "connect failed");
                    if !will_retry {
                        bail!("cannot connect: {error}");
                    }
                }
                Some(LinkEvent::Message(Message::SiteJoined(s))) => {
                    sites.insert(s.site, (s.name, s.role));
                }
                Some(LinkEvent::Message(Message::Snapshot(s))) => {
                    // A late joiner takes the session's simulated time, so that the
                    // snapshot's keyframes (and everything after) are current for it.
                    if s.sim_time_s > sim.time() {
                        info!(site = %cfg.name, t = s.sim_time_s, "joining a running session");
                        sim.set_time(s.sim_time_s);
                    }
                    got_snapshot = true;
                    pending.push(Message::Snapshot(s));
                }
                Some(LinkEvent::Message(m)) => pending.push(m),
                Some(other) => debug!(?other, "link event before start"),
                None => {}
            }
            // The coordinator follows every Welcome with a snapshot (possibly empty); a
            // late joiner must see it before its clock starts.
            let snapshot_wait_over =
                welcomed_at.is_some_and(|w: Instant| w.elapsed() > Duration::from_secs(3));
            if me.is_some()
                && sites.len() >= cfg.expect_sites
                && (got_snapshot || snapshot_wait_over)
            {
                break;
            }
        }
        info!(site = %cfg.name, id = ?me, sites = sites.len(), "session complete, starting");
    }
    report.site_id = me;
    sync.set_sites(me.unwrap_or(0), sites.keys().copied());
    let follows_device = cfg.device.is_device();
    if follows_device && !cfg.haptics {
        bail!("a haptic device needs the haptic loop (drop --no-haptics)");
    }
    let mut haptic = if cfg.haptics {
        Some(glue::HapticLoop::start(
            std::mem::take(&mut cfg.device),
            cfg.script.as_ref(),
            cfg.script_start,
            &tools,
            cfg.rt_priority,
        )?)
    } else {
        None
    };
    // Acts follow the script unless the tool follows a device (then: the whole run).
    let mut teaching = glue::Teaching::new(
        cfg.role,
        &tools,
        cfg.script.as_ref().filter(|_| !follows_device),
        cfg.script_start,
    );

    let start = Instant::now();
    let mut step_ms: Vec<f64> = Vec::with_capacity(steps as usize);
    let mut apply_us: Vec<f64> = Vec::new();
    let mut owned: BTreeMap<u32, f64> = BTreeMap::new();
    let mut requested: BTreeSet<u32> = BTreeSet::new();
    let mut last_touch: HashMap<u32, f64> = HashMap::new();
    let mut next_simtime_stamp = 0.0;
    let mut next_vtu = 0.0;
    let mut next_progress = 0.0;
    let mut clocks = PeerClocks::new(cfg.playout_lag);
    // Until the first time stamps arrive: a round trip to the coordinator is about two
    // one-way hops, owner → coordinator → us.
    if let Some(rtt) = link.as_ref().and_then(|l| l.clock().rtt_us) {
        clocks.seed_delay(rtt as f64 / 1e6);
    }
    // Display delay: sum and count of per-step lags while following.
    let (mut behind_sum, mut behind_steps) = (0.0f64, 0u64);
    let mut next_due = start;
    let mut next_pose = 0.0;
    let vtu_interval = cfg.vtu_interval.unwrap_or(f64::INFINITY);

    // Run until the session's simulated time reaches `seconds` (a late joiner starts
    // from the session's time, not from zero).
    let mut k: u64 = 0;
    while sim.time() + 0.5 * dt < cfg.seconds {
        k += 1;
        let t = sim.time();
        // 1. Network input, without waiting.
        let mut inbox = std::mem::take(&mut pending);
        if let Some(link) = &link {
            while let Some(ev) = link.try_recv() {
                match ev {
                    LinkEvent::Message(m) => inbox.push(m),
                    LinkEvent::Refused(r) => {
                        return Err(Refused(format!("{:?}: {}", r.reason, r.text)).into());
                    }
                    LinkEvent::Reconnected(w) => {
                        info!(site = %cfg.name, id = w.site, "reconnected");
                        me = Some(w.site);
                        report.reconnects += 1;
                        // Ownership does not survive a reconnect: the coordinator released
                        // our regions when we dropped.
                        owned.clear();
                        requested.clear();
                    }
                    LinkEvent::Disconnected { reason, .. } => {
                        warn!(site = %cfg.name, %reason, "disconnected");
                    }
                    other => debug!(?other, "link event"),
                }
            }
        }
        for m in inbox {
            match m {
                Message::ToolPose(p) if Some(p.site) != me => {
                    clocks.tool_heard(p.site, wall(start));
                    tools.remote_pose(&p);
                }
                Message::Keyframe(kf) if Some(kf.owner) != me => {
                    clocks.keyframe_arrived(kf.owner, kf.sim_time_s, wall(start));
                    let t0 = Instant::now();
                    let applied = sync.receive(&mut sim, kf);
                    acknowledge(&link, &applied, me, &mut report, &mut apply_us, t0);
                }
                Message::Snapshot(s) => {
                    for kf in s.keyframes {
                        if Some(kf.owner) != me {
                            let t0 = Instant::now();
                            let applied = sync.receive(&mut sim, kf);
                            acknowledge(&link, &applied, me, &mut report, &mut apply_us, t0);
                        }
                    }
                    for o in s.owners {
                        sync.set_owner(o.region, Some(o.site), me);
                        if Some(o.site) != me {
                            clocks.owners.insert(o.region, o.site);
                        }
                    }
                }
                Message::OwnershipGrant(g) => {
                    requested.remove(&g.region);
                    sync.set_owner(g.region, Some(g.site), me);
                    if Some(g.site) == me {
                        clocks.owners.remove(&g.region);
                    } else {
                        clocks.owners.insert(g.region, g.site);
                    }
                    if Some(g.site) == me {
                        owned.insert(g.region, t);
                    } else if let Some(since) = owned.remove(&g.region) {
                        report.owned.push((g.region, since, t));
                    }
                }
                Message::SimTime(s) if Some(s.site) != me => {
                    let transit = link.as_ref().and_then(|l| stamp_transit(l, s.wall_send_us));
                    clocks.heard(s.site, s.sim_time_s, wall(start), transit);
                }
                Message::OwnershipRelease(r) => {
                    // The release takes effect when our clock reaches the owner's time
                    // of release (as heard now), not on arrival: a lagging follower
                    // still has the owner's last frames to play.
                    let at = clocks.release_time(r.site, wall(start));
                    sync.release_remote(r.region, at, me);
                    clocks.owners.remove(&r.region);
                    if let Some(since) = owned.remove(&r.region) {
                        report.owned.push((r.region, since, t));
                    }
                }
                Message::TreeDelta(d) if Some(d.site) != me => {
                    let t0 = Instant::now();
                    let applied = sync.receive_delta(&mut sim, d);
                    acknowledge(&link, &applied, me, &mut report, &mut apply_us, t0);
                }
                Message::KeyframeAck(a) => sync.on_ack(&a),
                Message::OwnershipDeny(d) => {
                    requested.remove(&d.region);
                }
                Message::SiteJoined(s) => {
                    sites.insert(s.site, (s.name, s.role));
                    sync.set_sites(me.unwrap_or(0), sites.keys().copied());
                }
                Message::Leave(l) => {
                    sites.remove(&l.site);
                    sync.set_sites(me.unwrap_or(0), sites.keys().copied());
                }
                Message::Teaching(tr) => teaching.on_trajectory(tr),
                Message::Command(c) => teaching.on_command(c, haptic.as_ref()),
                other => debug!(kind = other.kind(), "ignored message"),
            }
        }

        let t0 = Instant::now();
        let applied = sync.apply_due(&mut sim);
        acknowledge(&link, &applied, me, &mut report, &mut apply_us, t0);

        // 2. Tools and contact.
        let local = if follows_device {
            haptic.as_mut().and_then(|h| h.device_input())
        } else {
            tools.local_input(cfg.script.as_ref(), t - cfg.script_start)
        };
        if let Some(m) = teaching.record(t, local.as_ref()) {
            send_control(&link, m);
        }
        let touched = tools.before_step(&mut sim, local, &sync)?;
        report.max_tool_force_n = report.max_tool_force_n.max(tools.local_force().norm());
        if let Some(h) = &haptic {
            h.publish(&tools, t);
        }
        let tip = tools
            .local_haptic()
            .map(|(input, _)| input.pose.translation.vector);
        teaching.playback_step(t, tip, haptic.as_ref());

        // 3. Ownership of the regions our tool touches. Input-only sites claim too: the
        // coordinator's ownership then says whose organ the others are compared with.
        if link.is_some() && cfg.role != Role::Observer {
            for region in touched {
                last_touch.insert(region, t);
                if !owned.contains_key(&region) && requested.insert(region) {
                    let claim = link.as_ref().map_or(0, |l| l.coordinator_time_us());
                    send_control(
                        &link,
                        Message::OwnershipRequest(proto::OwnershipRequest {
                            region,
                            claim_time_us: claim,
                        }),
                    );
                }
            }
            let stale: Vec<u32> = owned
                .keys()
                .copied()
                .filter(|r| last_touch.get(r).is_none_or(|lt| t - lt > RELEASE_AFTER))
                .collect();
            for region in stale {
                // A last keyframe first, so that the others end where we are.
                if let (Some(out), Some(link)) = (sync.release(&sim, region), &link) {
                    send_outgoing(link, out);
                }
                let since = owned.remove(&region).unwrap_or(t);
                report.owned.push((region, since, t));
                send_control(
                    &link,
                    Message::OwnershipRelease(proto::OwnershipRelease {
                        region,
                        site: me.unwrap_or(0),
                    }),
                );
            }
        }

        // 4. Remote regions follow their owners; then the step.
        sync.drive(&mut sim);
        let t0 = Instant::now();
        sim.step()
            .with_context(|| format!("site {} at t = {:.3} s", cfg.name, t))?;
        let cost = t0.elapsed();
        if cfg.slowdown > 1.0 {
            burn(cost.mul_f64(cfg.slowdown - 1.0));
        }
        step_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        let t = sim.time();

        // 5. What we owe the others.
        if let Some(link) = &link
            && cfg.role != Role::Observer
        {
            // Poses are the state itself under input-only; otherwise they only draw the
            // remote tool, and ~60 Hz leaves a lossy path's congestion window to the
            // keyframe streams.
            let pose_due = cfg.strategy == Strategy::InputOnly || t >= next_pose;
            if pose_due && let Some(pose) = tools.local_pose_message(me.unwrap_or(0), t) {
                next_pose = t + POSE_INTERVAL;
                link.send_datagram(Message::ToolPose(pose));
            }
            for out in sync.outgoing(&sim) {
                send_outgoing(link, out);
            }
            if t >= next_simtime_stamp {
                next_simtime_stamp = t + RECORD_INTERVAL;
                link.send_datagram(Message::SimTime(proto::SimTimeStamp {
                    site: me.unwrap_or(0),
                    sim_time_s: t,
                    step: sim.steps(),
                    wall_send_us: link.coordinator_time_us(),
                }));
            }
        }

        // 6. Recordings.
        recorder.record(&sim);
        if let Some((tx, _)) = &writer
            && t + 1e-9 >= next_vtu
        {
            next_vtu += vtu_interval;
            let _ = tx.send(Frame::capture(
                &sim,
                &tools.frames(),
                Some(tools.node_forces()),
            ));
        }

        if let Some(cb) = cfg.on_progress.as_mut()
            && t >= next_progress
        {
            next_progress = t + 0.25;
            let (sent, received) = link.as_ref().map_or((0, 0), |l| {
                let s = l.stats();
                (s.keyframes_sent, s.keyframes_received)
            });
            cb(
                t,
                &format!(
                    "kf out {sent} in {received} applied {}",
                    report.keyframes_applied
                ),
            );
        }

        // 7. Pacing. A leading site (it owns or claims a region, or drives its tool)
        // runs level with the other leaders; a follower keeps the playout lag behind the
        // sites it follows, by slewing its step rate (`site::pacing`).
        let leading = !owned.is_empty() || !requested.is_empty() || tools.local_active();
        let pace = clocks.pace(sim.time(), wall(start), leading, cfg.realtime);
        if let Some(b) = pace.behind {
            behind_sum += b;
            behind_steps += 1;
        }
        if cfg.realtime {
            // The next step is due dt / rate of wall time after this one was.
            next_due += Duration::from_secs_f64(dt / pace.rate);
            let now = Instant::now();
            if next_due > now {
                std::thread::sleep(next_due - now);
            }
        }
        // Never run ahead of the owners whose regions we show (their keyframes would
        // arrive from our past).
        if pace.hold > 0.0 {
            report.paced_seconds += pace.hold;
            std::thread::sleep(Duration::from_secs_f64(pace.hold));
            next_due += Duration::from_secs_f64(pace.hold);
        }
    }
    report.playout_lag_ms = if behind_steps > 0 {
        behind_sum / behind_steps as f64 * 1e3
    } else {
        0.0
    };
    report.playout_target_ms = clocks.target_lag() * 1e3;
    let wall = start.elapsed().as_secs_f64();
    for (region, since) in owned {
        report.owned.push((region, since, sim.time()));
    }

    report.sim_seconds = sim.time();
    report.wall_seconds = wall;
    report.sim_rate_hz = k as f64 / wall;
    report.step_ms_p50 = percentile(&step_ms, 50.0);
    report.step_ms_p99 = percentile(&step_ms, 99.0);
    report.apply_us_per_keyframe = if apply_us.is_empty() {
        0.0
    } else {
        apply_us.iter().sum::<f64>() / apply_us.len() as f64
    };
    // An act still running at the end (e.g. a device-driven instructor) is sent now.
    if let Some(m) = teaching.finish() {
        send_control(&link, m);
    }
    report.teaching_file = teaching.save(cfg.out.as_deref(), haptic.as_ref())?;
    teaching.report(&mut report);
    if let Some(h) = haptic {
        h.stop().report(&mut report);
    }
    if let Some(link) = link {
        let st = link.stats();
        let clock = link.clock();
        report.keyframes_sent = st.keyframes_sent;
        report.keyframes_received = st.keyframes_received;
        report.up_bytes_per_s = st.bytes_up as f64 / wall;
        report.down_bytes_per_s = st.bytes_down as f64 / wall;
        report.udp_up_bytes_per_s = st.udp_bytes_up as f64 / wall;
        report.udp_down_bytes_per_s = st.udp_bytes_down as f64 / wall;
        report.clock_offset_us = clock.offset_us;
        report.rtt_us = clock.rtt_us;
        link.close();
    }
    if let Some(dir) = &cfg.out {
        std::fs::create_dir_all(dir)?;
        let surf = dir.join("surfaces.surf");
        recorder.write(&surf)?;
        report.surf_file = Some(surf);
        if let Some((tx, handle)) = writer {
            drop(tx);
            let w = handle
                .join()
                .map_err(|_| anyhow::anyhow!("VTU writer thread panicked"))??;
            w.write_obj(&sim)?;
        }
        std::fs::write(
            dir.join("report.json"),
            serde_json::to_string_pretty(&report)?,
        )?;
    }
    drop(runtime);
    Ok(report)
}

/// Simulated time between tool-pose datagrams, except under input-only (s).
const POSE_INTERVAL: f64 = 0.016;

/// Wall seconds since `start` (the pacing's clock).
fn wall(start: Instant) -> f64 {
    start.elapsed().as_secs_f64()
}

/// One-way transit (s) of a time stamp sent at coordinator time `sent_us` (both clocks
/// synchronised with the coordinator's); `None` while ours is not. A sender not yet
/// synchronised gives an implausible value, which the pacing ignores.
fn stamp_transit(link: &Link, sent_us: u64) -> Option<f64> {
    link.clock().offset_us?;
    let now = link.coordinator_time_us();
    Some((now as f64 - sent_us as f64) / 1e6)
}

/// Counts applied keyframes (and their CPU time) and acknowledges them to their owner.
fn acknowledge(
    link: &Option<Link>,
    applied: &[(u32, u64)],
    me: Option<u16>,
    report: &mut SiteReport,
    apply_us: &mut Vec<f64>,
    started: Instant,
) {
    if applied.is_empty() {
        return;
    }
    let per = started.elapsed().as_secs_f64() * 1e6 / applied.len() as f64;
    for &(region, keyframe) in applied {
        apply_us.push(per);
        report.keyframes_applied += 1;
        send_control(
            link,
            Message::KeyframeAck(proto::KeyframeAck {
                region,
                keyframe,
                site: me.unwrap_or(0),
            }),
        );
    }
}

fn send_outgoing(link: &Link, out: Outgoing) {
    match out {
        Outgoing::Keyframe(kf) => link.send_keyframe(kf),
        Outgoing::Delta(d) => link.send_datagram(Message::TreeDelta(d)),
    }
}

fn send_control(link: &Option<Link>, m: Message) {
    if let Some(l) = link {
        l.send_control(m);
    }
}

/// Spends `d` of real CPU time (the `--slowdown` cost, not a sleep).
fn burn(d: Duration) {
    let end = Instant::now() + d;
    let mut x = 1.0f64;
    while Instant::now() < end {
        for _ in 0..256 {
            x = std::hint::black_box(x * 1.000_000_1 + 1e-9);
        }
    }
    std::hint::black_box(x);
}
