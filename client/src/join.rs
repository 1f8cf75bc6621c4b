//! `cosurg join`: run this machine as one site of a session.

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, ValueEnum};
use proto::Role;
use sim_core::SimOptions;
use sim_core::sim_scene::ToolScript;

use crate::cli::SimKnobs;
use crate::link::{LinkConfig, LinkImpairment, Trust};
use crate::scene_arg::load_scene_with_cell;
use crate::site::{SiteConfig, SiteReport, SiteView, run_site};
use sim_core::sync::SyncStrategy;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum RoleArg {
    Instructor,
    Trainee,
    Observer,
}

/// `--follow`: how a hybrid site follows the regions other sites own.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FollowArg {
    /// `keyframes` when this site's CG budget (`--cg-iterations`) is below the scene's,
    /// else `simulate`.
    Auto,
    /// Simulate them from every site's tool input; the owners' keyframes correct,
    /// blended.
    Simulate,
    /// Show the owners' keyframes, interpolated, as keyframe sync does (the owners then
    /// also send on dead-reckoning drift).
    Keyframes,
}

impl FollowArg {
    /// Whether a site with these solver `options` on a scene whose own options are
    /// `scene` shows keyframes. A site whose solve is cut short departs from the owners'
    /// copy in fast motion: measured with a 5-iteration CG, 10.9 mm at a grasp's release,
    /// more than blended corrections every 0.1 s bring back.
    pub fn shows_keyframes(self, options: &SimOptions, scene: &SimOptions) -> bool {
        match self {
            FollowArg::Auto => options.step.solver.max_iters < scene.step.solver.max_iters,
            FollowArg::Simulate => false,
            FollowArg::Keyframes => true,
        }
    }
}

impl From<RoleArg> for Role {
    fn from(r: RoleArg) -> Role {
        match r {
            RoleArg::Instructor => Role::Instructor,
            RoleArg::Trainee => Role::Trainee,
            RoleArg::Observer => Role::Observer,
        }
    }
}

#[derive(Debug, Args, Clone)]
pub struct JoinArgs {
    /// Coordinator address, HOST:PORT.
    #[arg(long)]
    pub server: String,
    /// Session name.
    #[arg(long)]
    pub session: String,
    /// The instructor's token (or COSURG_TOKEN); admits the instructor role only.
    #[arg(long, env = "COSURG_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Invitation (csi1.…, from `cosurg-server invite` or `cosurg invite`) for a trainee or
    /// observer (or COSURG_INVITE). Takes precedence over --token.
    #[arg(long, env = "COSURG_INVITE", hide_env_values = true)]
    pub invite: Option<String>,
    /// This site's role.
    #[arg(long, value_enum)]
    pub role: RoleArg,
    /// This site's name, unique in the session.
    #[arg(long)]
    pub site: String,
    /// SHA-256 fingerprint of the coordinator's certificate (printed by cosurg-server).
    #[arg(long, conflicts_with = "ca")]
    pub pin: Option<String>,
    /// CA certificate (PEM) that signed the coordinator's certificate.
    #[arg(long)]
    pub ca: Option<PathBuf>,
    /// TLS server name to check with --ca.
    #[arg(long, default_value = "localhost")]
    pub server_name: String,
    /// Scene file or builtin:NAME (must match the session's scene hash).
    #[arg(long)]
    pub scene: Option<String>,
    /// Lattice cell size (m) of every body, instead of the scene's (a finer organ; every
    /// site of the session gives the same).
    #[arg(long, value_name = "M", long_help = crate::scene_arg::CELL_HELP)]
    pub cell: Option<f64>,
    /// Tool this site drives (scene tool name); default: the script's or the first tool.
    /// Several (`--tool "forceps,clip applier,blade"`): the site exchanges the
    /// instrument in hand as the script's tracks for them begin, the first in hand at the
    /// start.
    #[arg(long, value_delimiter = ',')]
    pub tool: Vec<String>,
    /// Drive no tool (a trainee who only watches and feels).
    #[arg(long, conflicts_with = "tool")]
    pub no_tool: bool,
    /// A canned script drives the local tool: FILE (sim-scene script format), or without
    /// FILE the scene's own script for that tool. Without `--script` (and without a
    /// device) the window's mouse and keyboard drive it, and headless it stays still.
    #[arg(long, value_name = "FILE")]
    pub script: Option<Option<PathBuf>>,
    /// Simulated time at which the script starts (s).
    #[arg(long, default_value_t = 0.0)]
    pub script_start: f64,
    /// Leave after this many simulated seconds (default: 10 headless; with a window, when
    /// it is closed or after an hour).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Instructor: reset the scene for every site when the simulated time reaches
    /// SECONDS (may be repeated).
    #[arg(long, value_name = "SECONDS")]
    pub reset_at: Vec<f64>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
    /// How sites share the interaction: hybrid (every site simulates every tool from
    /// repeated input samples; owners' keyframes correct, blended), keyframe (owners'
    /// keyframes), full-state[:K] (every K steps), input-only. Every site of a session
    /// should use the same.
    #[arg(long, default_value = "hybrid")]
    pub strategy: SyncStrategy,
    /// Slow this site's simulation by a factor (real extra CPU per step).
    #[arg(long, default_value_t = 1.0)]
    pub slowdown: f64,
    /// Impair this site's own QUIC traffic in-process with a netem preset.
    #[arg(long)]
    pub preset: Option<String>,
    /// Seed of the impairment.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Run this site this many times slower than real time, as the coordinator
    /// (`cosurg-server --time-scale`): time-dilated measurement of a session on a machine
    /// too slow for its sites. The impairment (`--preset`, `--outage`) is stretched to
    /// match, so the session sees the path it names.
    #[arg(long, default_value = "1", value_name = "FACTOR")]
    pub time_scale: server::TimeScale,
    /// Cut this site's link completely (100 % loss both ways) for DURATION seconds,
    /// START seconds after it starts: `--outage START,DURATION`.
    #[arg(long, value_name = "START,DURATION")]
    pub outage: Option<String>,
    /// Output folder (surface recordings, VTU/PVD, report.json).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Simulated seconds between VTU frames (0: none).
    #[arg(long, default_value_t = 0.5)]
    pub vtu_interval: f64,
    /// Do not write the session recording `<out>/<site>.cosrec`.
    #[arg(long)]
    pub no_record: bool,
    /// Start simulating once this many sites have joined.
    #[arg(long, default_value_t = 1)]
    pub expect_sites: usize,
    /// Do not pace to wall-clock time.
    #[arg(long)]
    pub no_realtime: bool,
    /// While following another site's regions or tool, keep this site's simulated time
    /// this far behind it, so that keyframes and poses arrive before they are due and are
    /// interpolated rather than extrapolated: `auto` (measured delay + jitter margin + one
    /// keyframe interval, at most 600 ms) or milliseconds (0: no lag).
    #[arg(long, default_value = "auto")]
    pub playout_lag: crate::site::PlayoutLag,
    /// Under hybrid sync, how this site follows the regions other sites own: `simulate`
    /// (its own simulation, corrected by the owners' keyframes), `keyframes` (the owners'
    /// keyframes, interpolated, as keyframe sync shows them) or `auto` (`keyframes` when
    /// `--cg-iterations` is below the scene's budget: a solve cut short to keep up does
    /// not reproduce fast motion).
    #[arg(long, value_enum, default_value = "auto")]
    pub follow: FollowArg,
    /// Do not run the 1 kHz haptic loop.
    #[arg(long)]
    pub no_haptics: bool,
    /// Haptic device for the local tool: `script` (the tool follows its script) or
    /// `udp:HOST:PORT` (the tool follows a device driver's pose datagrams on that address
    /// and the haptic loop sends it forces; see docs/haptics.md).
    #[arg(long, default_value = "script", conflicts_with = "no_haptics")]
    pub device: String,
    /// Run the haptic thread at this SCHED_FIFO priority (1–99; warns and runs at normal
    /// priority if not permitted).
    #[arg(long, value_parser = clap::value_parser!(i32).range(1..=99))]
    pub rt_priority: Option<i32>,
    /// Announce this protocol version instead of ours (to test refusals).
    #[arg(long, hide = true)]
    pub protocol_version: Option<u16>,
    /// No window, even when a display is available.
    #[arg(long)]
    pub headless: bool,
    /// Join, simulate to `--at` seconds, render one picture (PNG) of this site and leave;
    /// needs a display (Xvfb will do).
    #[arg(long, value_name = "FILE.png", conflicts_with = "headless")]
    pub screenshot: Option<PathBuf>,
    /// Simulated time of the screenshot (s; default: `--seconds`, else 10).
    #[arg(long, requires = "screenshot")]
    pub at: Option<f64>,
    /// Window or screenshot size in pixels.
    #[arg(long, default_value = "1280x720", value_parser = crate::run_window::parse_size)]
    pub size: (u32, u32),
    /// Print `PROGRESS <sim time> …` lines on stdout (used by `cosurg demo`).
    #[arg(long, hide = true)]
    pub progress_lines: bool,
    #[command(flatten)]
    pub knobs: SimKnobs,
}

pub fn resolve(server: &str) -> Result<SocketAddr> {
    server
        .to_socket_addrs()
        .with_context(|| format!("resolving {server}"))?
        .next()
        .ok_or_else(|| anyhow!("{server} resolves to no address"))
}

pub fn site_config(args: &JoinArgs) -> Result<SiteConfig> {
    let scene = load_scene_with_cell(args.scene.as_deref(), args.cell)?;
    let mut options = SimOptions::from_scene(&scene.scene);
    args.knobs.apply(&mut options);
    let mut script = match &args.script {
        Some(Some(p)) => {
            Some(ToolScript::load(p).with_context(|| format!("script {}", p.display()))?)
        }
        _ => None,
    };
    let tools: Vec<String> = match (
        args.tool.is_empty(),
        RoleArg::Observer == args.role || args.no_tool,
    ) {
        (_, true) => Vec::new(),
        (false, _) => args.tool.clone(),
        (true, _) => script
            .as_ref()
            .and_then(|s| s.tools().next().map(String::from))
            .or_else(|| scene.scene.tools.first().map(|t| t.name.clone()))
            .into_iter()
            .collect(),
    };
    for t in &tools {
        if !scene.scene.tools.iter().any(|s| &s.name == t) {
            bail!(
                "tool {t:?} is not in the scene (tools: {:?})",
                scene
                    .scene
                    .tools
                    .iter()
                    .map(|t| &t.name)
                    .collect::<Vec<_>>()
            );
        }
    }
    if let Some(t) = tools
        .iter()
        .enumerate()
        .find_map(|(i, t)| tools[..i].contains(t).then_some(t))
    {
        bail!("--tool {t:?} is given twice");
    }
    // `--script` without a file: the scene's scripts for the tools, one track each.
    if matches!(args.script, Some(None)) {
        if tools.is_empty() {
            bail!("--script: this site drives no tool");
        }
        let mut merged = sim_core::sim_scene::ToolScript::default();
        for t in &tools {
            let s = scene
                .scripts
                .get(t)
                .with_context(|| format!("--script: the scene has no script for tool {t:?}"))?;
            let track = s
                .tracks
                .get(t)
                .or_else(|| s.tracks.values().next())
                .with_context(|| format!("--script: the scene's script for {t:?} is empty"))?;
            merged.tracks.insert(t.clone(), track.clone());
            merged.commands.extend(s.commands.iter().cloned());
            if merged.title.is_none() {
                merged.title = s.title.clone();
            }
        }
        merged.commands.sort_by(|a, b| a.t.total_cmp(&b.t));
        script = Some(merged);
    }
    let view = view_of(args)?;
    let seconds = match (&view, args.seconds) {
        (Some(SiteView::Screenshot { .. }), _) => args.at.or(args.seconds).unwrap_or(10.0),
        (_, Some(s)) => s,
        (Some(SiteView::Window { .. }), None) => WINDOW_SECONDS,
        (None, None) => 10.0,
    };
    if !(seconds.is_finite() && seconds >= 0.0) {
        bail!("{seconds} s: the simulated time must be a non-negative number of seconds");
    }
    let trust = match (&args.pin, &args.ca) {
        (Some(p), _) => Trust::Pinned(p.clone()),
        (None, Some(ca)) => Trust::Ca(ca.clone()),
        (None, None) => bail!("give --pin FINGERPRINT (printed by cosurg-server) or --ca PEM"),
    };
    let credential = match (&args.invite, &args.token) {
        (Some(i), _) => proto::Credential::Invitation(i.trim().to_string()),
        (None, Some(t)) => proto::Credential::Token(t.clone()),
        (None, None) => {
            bail!("give --invite INVITATION (trainee, observer) or --token TOKEN (instructor)")
        }
    };
    let mut link = LinkConfig::new(
        resolve(&args.server)?,
        "",
        &args.session,
        credential,
        args.role.into(),
        &args.site,
        &scene.hash,
    );
    link.trust = trust;
    link.server_name = args.server_name.clone();
    if let Some(v) = args.protocol_version {
        link.protocol_version = v;
    }
    link.time_scale = args.time_scale;
    if let Some(p) = &args.preset {
        link.impairment = Some(LinkImpairment::preset(p, args.seed)?);
    }
    if let Some(o) = &args.outage {
        let parts: Vec<f64> = o
            .split(',')
            .map(|v| v.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| anyhow!("--outage {o:?}: {e} (expected START,DURATION in seconds)"))?;
        let [start_s, duration_s] = parts[..] else {
            bail!("--outage {o:?}: expected START,DURATION in seconds");
        };
        let mut imp = match link.impairment.take() {
            Some(i) => i,
            None => LinkImpairment::preset("none", args.seed)?,
        };
        let outage = netem::Outage {
            start_s,
            duration_s,
        };
        imp.up.outage = Some(outage);
        imp.down.outage = Some(outage);
        link.impairment = Some(imp);
    }
    // Scene resets: `--reset-at` (simulated time) and the script's `[[command]]`s
    // (script time).
    let reset_at = args
        .reset_at
        .iter()
        .copied()
        .chain(script.iter().flat_map(|s| {
            s.commands
                .iter()
                .filter(|c| c.command == sim_core::sim_scene::SessionCommand::ResetScene)
                .map(|c| c.t + args.script_start)
        }))
        .collect();
    let shows_keyframes = args.strategy == SyncStrategy::Hybrid
        && args
            .follow
            .shows_keyframes(&options, &SimOptions::from_scene(&scene.scene));
    Ok(SiteConfig {
        name: args.site.clone(),
        role: args.role.into(),
        options,
        tools,
        script,
        script_start: args.script_start,
        seconds,
        strategy: args.strategy,
        slowdown: args.slowdown,
        out: args.out.clone(),
        vtu_interval: (args.vtu_interval > 0.0).then_some(args.vtu_interval),
        record: !args.no_record,
        link: Some(link),
        expect_sites: args.expect_sites,
        realtime: !args.no_realtime,
        playout_lag: args.playout_lag,
        shows_keyframes,
        haptics: !args.no_haptics,
        device: crate::haptic::site::DeviceSpec::parse(&args.device)?,
        rt_priority: args.rt_priority,
        on_progress: None,
        reset_at,
        status: None,
        hands: view.is_some(),
        view,
        scene,
        cell_m: args.cell,
        time_scale: args.time_scale,
    })
}

/// Simulated seconds of a site with a window and no `--seconds`: until the window is
/// closed, at most an hour.
const WINDOW_SECONDS: f64 = 3600.0;

/// The window, the screenshot or neither: a window when a display is available and
/// `--headless` is not given.
fn view_of(args: &JoinArgs) -> Result<Option<SiteView>> {
    if let Some(path) = &args.screenshot {
        return Ok(Some(SiteView::Screenshot {
            path: path.clone(),
            size: args.size,
        }));
    }
    if args.headless {
        return Ok(None);
    }
    if !crate::run_window::display_available() {
        tracing::info!("no display (DISPLAY is not set): joining headless");
        return Ok(None);
    }
    Ok(Some(SiteView::Window {
        title: format!(
            "cosurg — {} ({}) in {}",
            args.site,
            Role::from(args.role),
            args.session
        ),
        size: args.size,
    }))
}

pub fn join(args: JoinArgs) -> Result<()> {
    let mut cfg = site_config(&args)?;
    if args.progress_lines {
        cfg.on_progress = Some(Box::new(|t, msg| println!("PROGRESS {t:.3} {msg}")));
    }
    let report = run_site(cfg)?;
    if let Some(p) = &report.screenshot_file
        && !args.json
    {
        println!("wrote {}", p.display());
    }
    print_report(&report, args.json)
}

pub fn print_report(r: &SiteReport, json: bool) -> Result<()> {
    if json {
        println!("{}", serde_json::to_string(r)?);
    } else {
        println!(
            "site {} ({}, {}): {:.2} s simulated in {:.2} s wall, {:.0} steps/s, step p50 {:.3} ms p99 {:.3} ms max {:.3} ms, keyframes sent {} received {} applied {}, up {:.0} B/s down {:.0} B/s",
            r.name,
            r.role,
            r.strategy,
            r.sim_seconds,
            r.wall_seconds,
            r.sim_rate_hz,
            r.step_ms_p50,
            r.step_ms_p99,
            r.step_ms_max,
            r.keyframes_sent,
            r.keyframes_received,
            r.keyframes_applied,
            r.up_bytes_per_s,
            r.down_bytes_per_s
        );
    }
    Ok(())
}
