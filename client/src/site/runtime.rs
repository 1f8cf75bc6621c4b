//! The site's driver: the simulation loop around the sans-IO [`SiteSession`], the
//! simulation, the tools and the link.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use tracing::{debug, info, warn};

use server::SessionClock;
use sim_core::Simulation;
use sim_core::sync::SyncStrategy;

use super::config::{SiteConfig, SiteReport};
use super::recording::{Recorder, SessionRecording};
use super::status::SiteStatus;
use super::tools::{InputWait, MAX_INPUT_WAIT_S, Tools};
use super::view::{FrameContext, SiteViewer, ViewRequest};
use crate::cli::Refused;
use crate::haptic::site::{HapticLoop, Teaching};
use crate::link::{Link, LinkEvent};
use crate::output::{Frame, SeriesWriter};
use crate::session::{Now, SessionConfig, SessionEvent, SiteSession, Transmit};
use crate::stats::percentile;

/// Simulated time between surface recordings (s).
pub const RECORD_INTERVAL: f64 = 0.05;
/// Simulated time after a teaching start request at which trainees start the replay (s):
/// the command reaches them first.
const TEACHING_START_MARGIN: f64 = 0.3;
/// How often a step that waits for a late remote input looks again (`InputWait`).
const INPUT_POLL: Duration = Duration::from_millis(1);
/// Time a site waits for its session to be complete before giving up.
const JOIN_WAIT: Duration = Duration::from_secs(20);

/// Runs a site to completion.
pub fn run_site(mut cfg: SiteConfig) -> Result<SiteReport> {
    let dt = cfg.options.dt;
    let steps = (cfg.seconds / dt).round().max(1.0) as u64;
    let mut sim = Simulation::new(cfg.scene.clone(), cfg.options.clone())?;
    // The session's time: real time, or dilated by `--time-scale` (as the coordinator's).
    let clock = SessionClock::new(cfg.time_scale);
    // A hybrid site that shows keyframes does not simulate the others' tools either: the
    // regions they act on come from their owners' keyframes, as under keyframe sync.
    let tools_strategy = if cfg.shows_keyframes && cfg.strategy == SyncStrategy::Hybrid {
        SyncStrategy::Keyframe
    } else {
        cfg.strategy
    };
    let mut tools = Tools::new(&sim, &cfg.tools, tools_strategy)?;
    let mut recorder = Recorder::new(&sim, RECORD_INTERVAL);
    let writer = match (&cfg.out, cfg.vtu_interval) {
        (Some(dir), Some(_)) => Some(VtuThread::start(SeriesWriter::new(&dir.join("vtu"))?)),
        _ => None,
    };
    let mut report = SiteReport {
        name: cfg.name.clone(),
        role: cfg.role.to_string(),
        strategy: cfg.strategy.to_string(),
        scene_hash: cfg.scene.hash.clone(),
        cell_m: cfg.cell_m,
        time_scale: (!cfg.time_scale.is_real()).then(|| cfg.time_scale.factor()),
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
    let mut session = SiteSession::new(
        SessionConfig {
            role: cfg.role,
            strategy: cfg.strategy,
            scene: cfg.scene.clone(),
            options: cfg.options.clone(),
            linked: link.is_some(),
            playout_lag: cfg.playout_lag,
            realtime: cfg.realtime,
            shows_keyframes: cfg.shows_keyframes,
        },
        &sim,
        clock.now(),
    );
    if let Some(link) = &link {
        wait_for_session(&cfg, &clock, link, &mut session, &mut sim)?;
    }
    report.site_id = session.site_id();
    let follows_device = cfg.device.is_device();
    if follows_device && !cfg.haptics {
        bail!("a haptic device needs the haptic loop (drop --no-haptics)");
    }
    let mut haptic = if cfg.haptics {
        Some(HapticLoop::start(
            std::mem::take(&mut cfg.device),
            cfg.script.as_ref(),
            cfg.script_start,
            &tools,
            cfg.rt_priority,
            cfg.time_scale,
        )?)
    } else {
        None
    };
    // Acts follow the script unless the tool follows a device (then: the whole run).
    let mut teaching = Teaching::new(
        cfg.role,
        &tools,
        cfg.script.as_ref().filter(|_| !follows_device),
        cfg.script_start,
    );

    // The session recording (`<out>/<site>.cosrec`); flushed as it goes, finished at the
    // end, and flushed on drop on an error path.
    let mut session_rec = match cfg.out.as_ref().filter(|_| cfg.record) {
        Some(dir) => Some(SessionRecording::create(
            dir,
            &cfg.name,
            &cfg.role.to_string(),
            &session,
            &sim,
            &tools,
        )?),
        None => None,
    };
    let is_instructor = cfg.role == proto::Role::Instructor;
    // The window (or screenshot); its hands drive the local tool when nothing else does.
    let mut view = match cfg.view.take() {
        Some(v) => Some(SiteViewer::start(
            v,
            &sim,
            &cfg.name,
            cfg.role,
            cfg.hands && !follows_device && cfg.script.is_none(),
        )?),
        None => None,
    };
    // Instructor: the trajectory whose replay the window started.
    let mut replaying: Option<u32> = None;

    let start = clock.now();
    session.start(start, link.as_ref().and_then(|l| l.clock().rtt_us));
    let mut reset_at = cfg.reset_at.clone();
    reset_at.sort_by(f64::total_cmp);
    let mut reset_at = reset_at.into_iter().peekable();
    let mut step_ms: Vec<f64> = Vec::with_capacity(steps.min(1 << 20) as usize);
    let mut recording_ms: Vec<f64> = Vec::new();
    let mut next_vtu = 0.0;
    let mut next_progress = 0.0;
    let vtu_interval = cfg.vtu_interval.unwrap_or(f64::INFINITY);

    // Run until the session's simulated time reaches `seconds` (a late joiner starts
    // from the session's time, not from zero).
    let mut k: u64 = 0;
    // The late remote input a step last waited for (step 1b).
    let mut input_wait = InputWait::default();
    'run: while sim.time() + 0.5 * dt < cfg.seconds {
        // 0. The window's requests (instructor controls; closing it ends the run).
        if let Some(v) = view.as_mut() {
            let t = sim.time();
            for req in v.requests(t) {
                match req {
                    ViewRequest::Closed => {
                        info!(site = %cfg.name, t, "window closed: leaving the session");
                        break 'run;
                    }
                    ViewRequest::Reset => {
                        let rtt = link
                            .as_ref()
                            .and_then(|l| l.clock().rtt_us)
                            .map(Duration::from_micros);
                        v.notice = session.request_reset(t, rtt).err().map(|e| e.to_string());
                    }
                    ViewRequest::TeachingStart => match teaching.last_sent() {
                        Some(id) => {
                            session.send_control(proto::Message::Command(
                                proto::Command::StartPlayback {
                                    trajectory: id,
                                    start_sim_time_s: t + TEACHING_START_MARGIN,
                                },
                            ));
                            replaying = Some(id);
                            v.notice = None;
                        }
                        None => {
                            v.notice = Some(
                                "nothing to replay yet: act with the tool first (each act is \
                                 recorded and sent)"
                                    .into(),
                            )
                        }
                    },
                    ViewRequest::NextInstrument => {
                        if let Some(name) = tools.next_instrument() {
                            info!(site = %cfg.name, t, tool = name, "instrument exchanged");
                        }
                    }
                    ViewRequest::TeachingStop => {
                        if let Some(id) = replaying.take() {
                            session.send_control(proto::Message::Command(
                                proto::Command::StopPlayback { trajectory: id },
                            ));
                        }
                    }
                }
            }
        }
        // 1. Network input, without waiting, and what the session makes of it.
        if let Some(link) = &link {
            while let Some(ev) = link.try_recv() {
                let now = now_of(&clock, Some(link));
                match ev {
                    LinkEvent::Message(m) => session.handle_message(&mut sim, m, now)?,
                    LinkEvent::Refused(r) => {
                        return Err(Refused(format!("{:?}: {}", r.reason, r.text)).into());
                    }
                    LinkEvent::Reconnected(w) => session.handle_reconnected(&w, &sim, now),
                    LinkEvent::Disconnected { reason, .. } => {
                        warn!(site = %cfg.name, %reason, "disconnected");
                        session.handle_disconnected(&sim);
                    }
                    other => debug!(?other, "link event"),
                }
            }
        }
        session.apply_due(&mut sim)?;
        while let Some(ev) = session.poll_event() {
            match ev {
                SessionEvent::RemotePose(p) => {
                    let at = sim.time() + sim.options().dt;
                    if let Some(late) = tools.remote_pose(&p, at) {
                        session.input_lateness(p.site, late, at, now_of(&clock, link.as_ref()));
                    }
                }
                SessionEvent::SceneReset { epoch } => {
                    info!(site = %cfg.name, epoch, t = sim.time(), "scene reset");
                    tools.reset(&sim);
                    if let Some(v) = view.as_mut() {
                        v.reset(&sim)?;
                    }
                    if let Some(r) = session_rec.as_mut() {
                        r.reset(epoch, &sim)?;
                    }
                }
                SessionEvent::Teaching(tr) => {
                    if let Some(r) = session_rec.as_mut() {
                        r.other(
                            "teaching-trajectory",
                            &format!("trajectory {} ({} samples)", tr.id, tr.samples.len()),
                            &sim,
                        )?;
                    }
                    teaching.on_trajectory(tr);
                }
                SessionEvent::Playback(c) => {
                    // (The instructor's own teaching events are its acts, below.)
                    if !is_instructor && let Some(r) = session_rec.as_mut() {
                        match &c {
                            proto::Command::StartPlayback { trajectory, .. } => r.teaching(
                                true,
                                &format!("playback of trajectory {trajectory}"),
                                &sim,
                            )?,
                            proto::Command::StopPlayback { trajectory } => r.teaching(
                                false,
                                &format!("playback of trajectory {trajectory} stopped"),
                                &sim,
                            )?,
                            _ => {}
                        }
                    }
                    teaching.on_command(c, haptic.as_ref());
                }
                SessionEvent::CommandRefused { command, reason } => {
                    warn!(site = %cfg.name, %command, %reason, "command refused");
                    if let Some(v) = view.as_mut() {
                        v.notice = Some(format!("{command} refused: {reason}"));
                    }
                }
            }
        }
        let t = sim.time();
        // Scripted instructor commands.
        if reset_at.next_if(|at| t + 0.5 * dt >= *at).is_some() {
            let rtt = link
                .as_ref()
                .and_then(|l| l.clock().rtt_us)
                .map(Duration::from_micros);
            if let Err(e) = session.request_reset(t, rtt) {
                warn!(site = %cfg.name, error = %e, "scripted reset not sent");
            }
        }
        flush(link.as_ref(), &mut session);

        // 1b. Under hybrid, on a follower: a remote tool that touches tissue and whose next
        // input is late is waited for rather than carried on (see `Tools::input_awaited`
        // and `InputWait`). The schedule is not moved: after a wait the follower steps
        // without pause until it is back on it. A leader never waits: leaders run level,
        // and would wait for each other. (Under hybrid a still owner is no leader: it
        // waits like any follower, and so simulates the moving tools from their samples.)
        if !session.leads(tools.local_moving(sim.time())) {
            let now = clock.now();
            let awaited = tools.input_awaited(sim.time() + dt, MAX_INPUT_WAIT_S);
            if let Some(short) = input_wait.waits(awaited, now) {
                tracing::trace!(short_ms = short * 1e3, "waiting for a remote input");
                std::thread::sleep(clock.scale().to_real(INPUT_POLL));
                report.input_wait_s += (clock.now() - now).as_secs_f64();
                continue 'run;
            }
        }

        // 2. Tools and contact.
        let local = if follows_device {
            haptic.as_mut().and_then(|h| h.device_input())
        } else {
            tools
                .local_input(cfg.script.as_ref(), t - cfg.script_start)
                .or_else(|| view.as_ref().and_then(|v| v.hands_input(&tools, dt, t)))
        };
        if is_instructor
            && tools.local_index().is_some()
            && let Some(r) = session_rec.as_mut()
        {
            let detail = if local.is_some() {
                "instructor's act recorded for teaching"
            } else {
                "instructor's act sent"
            };
            r.teaching(local.is_some(), detail, &sim)?;
        }
        if let Some(m) = teaching.record(t, tools.local_index(), local.as_ref()) {
            session.send_control(m);
        }
        let mut touched = tools.before_step(&mut sim, local, &session)?;
        let ops = tools.take_topology_ops();
        let own_cut = session.take_own_cut_applied()
            || (!session.times_topology()
                && ops
                    .iter()
                    .any(|op| matches!(op, sim_core::cut::TopologyOp::Cut(_))));
        if own_cut {
            // The regions our cut separated are ours until they are at rest: the others
            // made their copies of the new (virtual) nodes on their own, and our keyframes
            // correct them to ours.
            touched.extend(session.regions_of_cut(&sim));
        }
        let rtt = link
            .as_ref()
            .and_then(|l| l.clock().rtt_us)
            .map(Duration::from_micros);
        session.share_topology(&ops, sim.time(), rtt);
        report.max_tool_force_n = report.max_tool_force_n.max(tools.local_force().norm());
        if let Some(h) = &haptic {
            h.publish(&tools, t);
        }
        let tip = tools
            .local_haptic()
            .map(|(input, _)| input.pose.translation.vector);
        teaching.playback_step(t, tip, haptic.as_ref());

        // 3. Ownership of the regions our tool touches.
        session.handle_touched(&sim, &touched, now_of(&clock, link.as_ref()));
        flush(link.as_ref(), &mut session);

        // 4. Remote regions follow their owners; then the step.
        session.before_step(&mut sim);
        k += 1;
        let t0 = Instant::now();
        sim.step()
            .with_context(|| format!("site {} at t = {:.3} s", cfg.name, t))?;
        let cost = t0.elapsed();
        if cfg.slowdown > 1.0 {
            burn(cost.mul_f64(cfg.slowdown - 1.0));
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        step_ms.push(ms);
        if let Some(v) = view.as_mut() {
            v.step_time(ms);
        }
        let t = sim.time();

        // 5. What we owe the others.
        if session.pose_due(t)
            && let Some(me) = session.site_id()
            && let Some(pose) = tools.local_pose_message(me, t)
        {
            session.send_pose(pose);
        }
        session.after_step(&sim, now_of(&clock, link.as_ref()));
        flush(link.as_ref(), &mut session);

        // 6. Recordings.
        recorder.record(&sim);
        if let Some(r) = session_rec.as_mut() {
            let t0 = Instant::now();
            r.after_step(&session, &sim, &tools)?;
            recording_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        if let Some(w) = &writer
            && t + 1e-9 >= next_vtu
        {
            next_vtu += vtu_interval;
            w.send(Frame::capture(
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
                    session.stats().keyframes_applied
                ),
            );
        }

        // 7. Pacing (`session::pacing`), and the state for a window to read.
        let pace = session.end_step(t, tools.local_moving(t), clock.now());
        if let Some(board) = &cfg.status {
            board.publish(SiteStatus {
                sim_time: t,
                steps: sim.steps(),
                session: session.snapshot(),
                tool_force_n: tools.local_force().norm(),
                behind_s: pace.behind,
            });
        }
        if let Some(v) = view.as_mut() {
            let now = Instant::now();
            if v.publish_due(now) {
                let teaching_on = if is_instructor {
                    replaying.is_some()
                } else {
                    teaching.guiding()
                };
                v.publish(
                    FrameContext {
                        sim: &sim,
                        tools: &tools,
                        session: &session,
                        link: link.as_ref().map(|l| l.stats()),
                        behind: pace.behind,
                        teaching: teaching_on,
                        guide: if teaching_on {
                            teaching.guide_path()
                        } else {
                            Vec::new()
                        },
                    },
                    now,
                );
            }
        }
        if let Some(wake) = session.poll_timeout() {
            let wait = clock.real_until(wake);
            if !wait.is_zero() {
                std::thread::sleep(wait);
            }
        }
    }
    // Session seconds (real seconds over a dilated session's time scale).
    let wall = (clock.now() - start).as_secs_f64();
    if let Some(v) = view.take() {
        v.finish(
            FrameContext {
                sim: &sim,
                tools: &tools,
                session: &session,
                link: link.as_ref().map(|l| l.stats()),
                behind: None,
                teaching: false,
                guide: Vec::new(),
            },
            &mut report,
        )?;
    }
    let stats = session.stats().clone();
    report.playout_lag_ms = if stats.behind_steps > 0 {
        stats.behind_sum / stats.behind_steps as f64 * 1e3
    } else {
        0.0
    };
    report.playout_target_ms = session.target_lag() * 1e3;
    report.lag_reached_at_s = stats.lag_reached_at;
    report.playout_lag_reached_ms = (stats.reached_behind_steps > 0)
        .then(|| stats.reached_behind_sum / stats.reached_behind_steps as f64 * 1e3);
    report.paced_seconds = stats.paced_seconds;
    report.late_inputs = stats.late_inputs;
    report.reconnects = stats.reconnects;
    report.resets = stats.resets;
    report.topology_epoch = sim.topology().epoch();
    report.topology_digest = format!("{:016x}", sim.topology().digest());
    for op in sim.topology().ops() {
        match op {
            sim_core::cut::TopologyOp::Cut(_) => report.cuts += 1,
            sim_core::cut::TopologyOp::Clip(_) => report.clips += 1,
            sim_core::cut::TopologyOp::Release(r) => {
                report.springs_released += r.springs.len() as u32
            }
            // Never logged (`Simulation::apply_topology_op`).
            sim_core::cut::TopologyOp::Refine(_) => {}
        }
    }
    report.refinements_applied = stats.refinements_applied;
    report.refinements_late = stats.refinements_late;
    report.refinements_dropped = stats.refinements_dropped;
    report.frames_refinement_dropped = stats.frames_refinement_dropped;
    report.topology_ops_received = stats.topology_applied;
    report.topology_apply_us_mean = if stats.topology_applied == 0 {
        0.0
    } else {
        stats.topology_apply_us_total / stats.topology_applied as f64
    };
    report.keyframes_topology_dropped = stats.keyframes_topology_dropped;
    report.topology_bytes_sent = stats.topology_bytes_sent;
    report.epoch = session.epoch();
    report.owned = session.owned_intervals(sim.time());
    report.keyframes_applied = stats.keyframes_applied;
    report.apply_us_per_keyframe = if stats.keyframes_applied == 0 {
        0.0
    } else {
        stats.apply_us_total / stats.keyframes_applied as f64
    };
    report.sim_seconds = sim.time();
    report.wall_seconds = wall;
    report.sim_rate_hz = k as f64 / wall;
    report.step_ms_p50 = percentile(&step_ms, 50.0);
    report.step_ms_p99 = percentile(&step_ms, 99.0);
    report.step_ms_max = percentile(&step_ms, 100.0);
    if !recording_ms.is_empty() {
        report.recording_ms_p50 = Some(percentile(&recording_ms, 50.0));
        report.recording_ms_p99 = Some(percentile(&recording_ms, 99.0));
    }
    // An act still running at the end (e.g. a device-driven instructor) is sent now.
    if let Some(m) = teaching.finish() {
        session.send_control(m);
        flush(link.as_ref(), &mut session);
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
        if let Some(impaired) = link.impaired() {
            let c = impaired.counters();
            // The impairment runs in real time: its delays in session time.
            let f = cfg.time_scale.factor();
            report.link_up_delay_ms = c.up.model.mean_delay_ms().map(|d| d / f);
            report.link_down_delay_ms = c.down.model.mean_delay_ms().map(|d| d / f);
        }
        link.close();
    }
    if let Some(r) = session_rec.take() {
        let path = r.path().to_path_buf();
        report.recording_bytes = Some(r.finish(&sim)?);
        report.recording_file = Some(path);
    }
    if let Some(dir) = &cfg.out {
        std::fs::create_dir_all(dir)?;
        let surf = dir.join("surfaces.surf");
        recorder.write(&surf)?;
        report.surf_file = Some(surf);
        if let Some(w) = writer {
            w.finish()?.write_obj(&sim)?;
        }
        std::fs::write(
            dir.join("report.json"),
            serde_json::to_string_pretty(&report)?,
        )?;
    }
    drop(runtime);
    Ok(report)
}

/// Joins, then waits for the expected number of sites and the join snapshot: all sites
/// then start their simulation clocks within about one round trip of each other.
fn wait_for_session(
    cfg: &SiteConfig,
    clock: &SessionClock,
    link: &Link,
    session: &mut SiteSession,
    sim: &mut Simulation,
) -> Result<()> {
    let deadline = Instant::now() + JOIN_WAIT;
    loop {
        if Instant::now() > deadline {
            bail!(
                "site {}: timed out waiting for the session ({} of {} sites)",
                cfg.name,
                session.sites().len(),
                cfg.expect_sites
            );
        }
        let event = link.recv_timeout(Duration::from_millis(50));
        let now = now_of(clock, Some(link));
        match event {
            Some(LinkEvent::Welcome(w)) => session.handle_welcome(&w, now),
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
            Some(LinkEvent::Message(m)) => session.handle_message(sim, m, now)?,
            Some(other) => debug!(?other, "link event before start"),
            None => {}
        }
        session.announce_presence(sim, now);
        flush(Some(link), session);
        if session.is_ready(cfg.expect_sites, clock.now()) {
            info!(site = %cfg.name, id = ?session.site_id(), sites = session.sites().len(), "session complete, starting");
            return Ok(());
        }
    }
}

/// The time now, as the session takes it: wall time and the coordinator's clock.
fn now_of(clock: &SessionClock, link: Option<&Link>) -> Now {
    let wall = clock.now();
    match link {
        Some(l) => Now {
            wall,
            coordinator_us: l.coordinator_time_us(),
            synced: l.clock().offset_us.is_some(),
        },
        None => Now::local(wall, 0),
    }
}

/// Hands the session's transmits to the link.
fn flush(link: Option<&Link>, session: &mut SiteSession) {
    while let Some(t) = session.poll_transmit() {
        let Some(link) = link else { continue };
        match t {
            Transmit::Control(m) => link.send_control(m),
            Transmit::Datagram(m) => link.send_datagram(m),
            Transmit::Keyframe(kf) => link.send_keyframe(kf),
        }
    }
}

/// VTU frames are captured on the simulation thread and written on another, so that file
/// output never stretches a step.
struct VtuThread {
    tx: std::sync::mpsc::Sender<Frame>,
    handle: std::thread::JoinHandle<Result<SeriesWriter>>,
}

impl VtuThread {
    fn start(mut w: SeriesWriter) -> Self {
        let (tx, rx) = std::sync::mpsc::channel::<Frame>();
        let handle = std::thread::spawn(move || -> Result<SeriesWriter> {
            for frame in rx {
                w.write(&frame)?;
            }
            Ok(w)
        });
        VtuThread { tx, handle }
    }

    fn send(&self, frame: Frame) {
        let _ = self.tx.send(frame);
    }

    fn finish(self) -> Result<SeriesWriter> {
        drop(self.tx);
        self.handle
            .join()
            .map_err(|_| anyhow::anyhow!("VTU writer thread panicked"))?
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
