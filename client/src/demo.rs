//! `cosurg demo`: a coordinator and N sites on loopback, real QUIC with TLS between real
//! processes, playing a built-in scene's scripts.
//!
//! Timeline of the default scene, `cholecystectomy-bodies` (simulated seconds; see
//! [`cast_for`]): the instructor's forceps grasps the gallbladder fundus, lifts it and
//! holds it (0.5–3.5 s, then on); trainee B's hook dissects the bed (3–9.5 s); the
//! instructor takes the clip applier and clips the cystic duct on the hilum's side
//! (11–13.5 s); trainee A takes the applier and clips it on the gallbladder's side
//! (13.5–16 s); the instructor divides the duct between the clips with the blade
//! (16–17.5 s). Timeline of `cholecystectomy` (one body, [`cast`]): the instructor's
//! forceps lifts the fundus (0.5–6.5 s); trainee B works around the neck with a probe
//! (7–12 s); trainee A repeats the lift (12.5–18.5 s).
//!
//! Every site records its embedded surface every 50 ms of simulated time; afterwards the
//! demo compares every site with the site that owned the region at that time, vertex by
//! vertex.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::cli::out_dir;
use crate::plot::{Chart, Series, write_chart};
use crate::site::SiteReport;
use debrief::{Recording, ScoreReport, ScoreSettings, score_site};
use sim_core::sync::SyncStrategy;

#[derive(Debug, Args, Clone)]
pub struct DemoArgs {
    /// Number of sites (instructor, trainee A, trainee B, then observers).
    #[arg(long, default_value_t = 3)]
    pub sites: usize,
    /// Simulated seconds.
    #[arg(long, default_value_t = 19.5)]
    pub seconds: f64,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
    /// Output folder (default out/demo-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Sync strategy: hybrid (every site simulates every tool from repeated input samples;
    /// owners' keyframes correct, blended), keyframe (owners' keyframes),
    /// full-state[:K] (every K steps), input-only.
    #[arg(long, default_value = "hybrid")]
    pub strategy: SyncStrategy,
    /// Network impairment preset applied to every site's link (netem presets: lan,
    /// metro, good, intercontinental, average, poor, burst (Gilbert–Elliott loss), outage
    /// (3 s without a link)).
    #[arg(long)]
    pub preset: Option<String>,
    /// Slow trainee B's simulation by this factor.
    #[arg(long, default_value_t = 1.0)]
    pub slowdown: f64,
    /// Simulated seconds between VTU frames per site.
    #[arg(long, default_value_t = 0.5)]
    pub vtu_interval: f64,
    /// Seed of the impairment.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Simulation time step of every site (s). 4 ms (250 Hz) lets three sites keep real
    /// time on a 2-core machine; the haptic loop renders at 1 kHz between steps.
    #[arg(long, default_value_t = 0.004)]
    pub dt: f64,
    /// The instructor resets the scene for every site at this simulated time (s).
    #[arg(long, value_name = "SECONDS")]
    pub reset_at: Option<f64>,
    /// One window per site (three synchronised views of the session); needs a display.
    /// Without it every site runs headless.
    #[arg(long)]
    pub view: bool,
    /// Built-in scene: `cholecystectomy-bodies` (the instructor's forceps lifts the
    /// gallbladder, trainee B's hook dissects the bed, the instructor and trainee A clip the
    /// cystic duct and the instructor divides it) or `cholecystectomy` (one body: forceps
    /// lift, probe, trainee A repeats the lift).
    #[arg(long, default_value = "cholecystectomy-bodies")]
    pub scene: String,
    /// Lattice cell size (m) of every body on every site, instead of the scene's (a finer
    /// organ).
    #[arg(long, value_name = "M", long_help = crate::scene_arg::CELL_HELP)]
    pub cell: Option<f64>,
    /// Run the coordinator and every site this many times slower than real time, the
    /// impairment stretched to match (time dilation): the session on a machine too slow
    /// to step every site in real time behaves, in its own time, as on one this much
    /// faster. Reported times and rates are in session time.
    #[arg(long, default_value = "1", value_name = "FACTOR")]
    pub time_scale: server::TimeScale,
    /// Extra arguments passed to every site's `cosurg join` (after `--`).
    #[arg(last = true)]
    pub site_args: Vec<String>,
}

/// One site of the demo.
#[derive(Clone, Debug)]
pub struct DemoSite {
    pub name: String,
    pub role: &'static str,
    /// The scene tools the site drives, the one in hand at the start first (empty: none).
    pub tools: Vec<&'static str>,
    /// A built-in scene file (path under `scenes/`) the site plays instead of the scene's
    /// own scripts for its tools.
    pub script_file: Option<&'static str>,
    pub script_start: f64,
    pub slowdown: f64,
    /// Further `cosurg join` arguments for this site only (e.g. its own solver budget).
    pub extra: Vec<String>,
}

/// The demo's cast for `n` sites.
pub fn cast(n: usize, slowdown: f64) -> Vec<DemoSite> {
    (0..n.max(1))
        .map(|i| match i {
            0 => DemoSite {
                name: "instructor".into(),
                role: "instructor",
                tools: vec!["forceps"],
                script_file: None,
                script_start: 0.5,
                slowdown: 1.0,
                extra: Vec::new(),
            },
            1 => DemoSite {
                name: "trainee-a".into(),
                role: "trainee",
                tools: vec!["forceps"],
                script_file: None,
                script_start: 12.5,
                slowdown: 1.0,
                extra: Vec::new(),
            },
            2 => DemoSite {
                name: "trainee-b".into(),
                role: "trainee",
                tools: vec!["probe"],
                script_file: None,
                script_start: 7.0,
                slowdown,
                extra: Vec::new(),
            },
            k => DemoSite {
                name: format!("observer-{}", k - 2),
                role: "observer",
                tools: Vec::new(),
                script_file: None,
                script_start: 0.0,
                slowdown: 1.0,
                extra: Vec::new(),
            },
        })
        .collect()
}

/// The demo's cast for `n` sites of the built-in scene `scene`: [`cast`] for the
/// cholecystectomy; for `cholecystectomy-bodies` (every script from 0.5 s: the scene's
/// scripts carry the timeline, see `sim_scene::builtin::bodies`) the instructor lifts the
/// gallbladder with the forceps and holds it, trainee B dissects the bed with the hook
/// (3–9.5 s), the instructor exchanges the forceps for the clip applier and clips the
/// cystic duct on the hilum's side (11–13.5 s), trainee A takes the applier and clips it
/// on the gallbladder's side (13.5–16 s), and the instructor divides the duct between the
/// clips with the blade (16–17.5 s).
pub fn cast_for(scene: &str, n: usize, slowdown: f64) -> Vec<DemoSite> {
    let mut c = cast(n, slowdown);
    if scene == "cholecystectomy-bodies" {
        for site in &mut c {
            site.script_start = 0.5;
            match site.name.as_str() {
                "instructor" => site.tools = vec!["forceps", "clip applier", "blade"],
                "trainee-a" => {
                    site.tools = vec!["clip applier"];
                    site.script_file = Some("scripts/bodies_second_clip.toml");
                }
                "trainee-b" => site.tools = vec!["hook"],
                _ => {}
            }
        }
    }
    c
}

/// Per-site row of the summary.
#[derive(Debug, Clone, Serialize)]
pub struct SiteRow {
    pub name: String,
    pub role: String,
    pub sim_rate_hz: f64,
    pub step_ms_p50: f64,
    pub step_ms_p99: f64,
    /// The longest step (ms).
    pub step_ms_max: f64,
    pub keyframes_sent: u64,
    pub keyframes_received: u64,
    pub up_bytes_per_s: f64,
    pub down_bytes_per_s: f64,
    pub divergence_max_mm: f64,
    pub divergence_rms_mm: f64,
    /// Haptic loop: rate (Hz) and p99 period jitter (µs).
    pub haptic_rate_hz: Option<f64>,
    pub haptic_jitter_p99_us: Option<f64>,
    /// Teaching: trajectories the instructor sent; on a guided trainee, the guide force
    /// (max/mean N) and the mean distance to the instructor's recorded tip (mm).
    pub teaching_sent: Option<u64>,
    pub guide_force_max_n: Option<f64>,
    pub guide_force_mean_n: Option<f64>,
    pub playback_distance_mm: Option<f64>,
    /// Scene epoch at the end (one per reset).
    pub epoch: u32,
    /// Topology at the end: epoch (topology ops applied) and digest (hex; equal on every
    /// site with the same cuts).
    pub topology_epoch: u32,
    pub topology_digest: String,
    /// Cuts, clips and attachment springs released in that topology.
    pub cuts: u32,
    pub clips: u32,
    pub springs_released: u32,
}

#[derive(Debug, Clone, Serialize)]
pub struct DemoSummary {
    pub scene_hash: String,
    /// The lattice cell (m) of every body when `--cell` replaced the scene's.
    pub cell_m: Option<f64>,
    pub seconds: f64,
    pub strategy: String,
    pub preset: Option<String>,
    pub out: PathBuf,
    pub sites: Vec<SiteRow>,
    /// Trainee A's acts scored against the instructor's recording (`cosurg score`'s
    /// measures); `None` when there is no trainee A or its recording could not be scored.
    pub scores: Option<ScoreReport>,
}

/// The site scored in the summary and its reference.
pub const SCORED_SITE: &str = "trainee-a";
pub const REFERENCE_SITE: &str = "instructor";

/// Scores `site`'s recording against `reference`'s (the recordings the sites wrote).
pub fn score_against(reports: &[SiteReport], site: &str, reference: &str) -> Result<ScoreReport> {
    let file = |name: &str| {
        reports
            .iter()
            .find(|r| r.name == name)
            .and_then(|r| r.recording_file.clone())
            .with_context(|| format!("no recording of site {name}"))
    };
    let (mine, theirs) = (file(site)?, file(reference)?);
    let rec = Recording::open(&mine).with_context(|| format!("opening {}", mine.display()))?;
    let reference_rec =
        Recording::open(&theirs).with_context(|| format!("opening {}", theirs.display()))?;
    Ok(score_site(
        &rec,
        site,
        Some((&reference_rec, reference)),
        &ScoreSettings::default(),
    )?)
}

/// Session options of a multi-site run (shared with `cosurg bench sync`).
#[derive(Clone, Debug)]
pub struct SessionRun {
    pub cast: Vec<DemoSite>,
    pub seconds: f64,
    pub strategy: SyncStrategy,
    pub preset: Option<String>,
    pub seed: u64,
    pub out: PathBuf,
    pub vtu_interval: f64,
    pub progress: bool,
    /// Time step override for every site (s).
    pub dt: Option<f64>,
    /// Extra arguments for every site's `cosurg join`.
    pub extra: Vec<String>,
    /// The instructor resets the scene at this simulated time (s).
    pub reset_at: Option<f64>,
    /// Every site opens its window (else every site runs headless).
    pub view: bool,
    /// Every body on a lattice of this cell (m) on every site (`cosurg join --cell`).
    pub cell: Option<f64>,
    /// Every party runs this many times slower than real time (`--time-scale`).
    pub time_scale: server::TimeScale,
}

/// Runs a coordinator in-process and every site as a child process on the built-in
/// cholecystectomy; returns the site reports (with divergence filled in) and the per-mark
/// divergence series.
pub fn run_session(run: &SessionRun) -> Result<(Vec<SiteReport>, Vec<Series>)> {
    run_session_on(run, "cholecystectomy")
}

/// [`run_session`] on the built-in scene `scene_name`.
pub fn run_session_on(
    run: &SessionRun,
    scene_name: &str,
) -> Result<(Vec<SiteReport>, Vec<Series>)> {
    let exe = std::env::current_exe().context("locating the cosurg executable")?;
    let scene = builtin_scene(scene_name, run.cell)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let token = format!("demo-{}", std::process::id());
    let mut session = proto::SessionConfig::new("demo", token.clone());
    session.scene_hash = Some(scene.hash.clone());
    // The coordinator lives as long as this demo: an in-memory invitation key, and one
    // invitation per trainee or observer, bound to its site name.
    let invite_key = proto::InviteKey::from_bytes(rand::random());
    session.invite_key = Some(invite_key.clone());
    let mut config = server::CoordinatorConfig::ephemeral(session)?;
    // The coordinator's recording of the session: `<out>/coordinator/demo.cosrec`.
    config.record_dir = Some(run.out.join("coordinator"));
    config.time_scale = run.time_scale;
    let (handle, addr) = runtime.block_on(async { server::Coordinator::bind(config) })?;
    let fingerprint = handle.fingerprint().to_string();
    std::fs::create_dir_all(&run.out)?;

    let multi = MultiProgress::new();
    if !run.progress {
        multi.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let style = ProgressStyle::with_template("{prefix:>12} {bar:30} {msg}").expect("template");
    let mut children = Vec::new();
    for site in &run.cast {
        let dir = run.out.join(&site.name);
        let mut cmd = Command::new(&exe);
        cmd.arg("join")
            .args(["--server", &addr.to_string()])
            .args(["--session", "demo"])
            .args(["--role", site.role])
            .args(["--site", &site.name])
            .args(["--pin", &fingerprint])
            .args(["--seconds", &run.seconds.to_string()])
            .args(["--strategy", &run.strategy.to_string()])
            .args(["--script-start", &site.script_start.to_string()])
            .args(["--slowdown", &site.slowdown.to_string()])
            .args(["--expect-sites", &run.cast.len().to_string()])
            .args(["--vtu-interval", &run.vtu_interval.to_string()])
            .args(["--seed", &run.seed.to_string()])
            .args(["--scene", &format!("builtin:{scene_name}")])
            .args(
                run.cell
                    .iter()
                    .flat_map(|c| ["--cell".to_string(), c.to_string()]),
            )
            .arg("--out")
            .arg(&dir)
            .args(["--json", "--progress-lines"])
            .stdout(Stdio::piped())
            .stderr(Stdio::from(std::fs::File::create(
                run.out.join(format!("{}.log", site.name)),
            )?))
            .env(
                "COSURG_LOG",
                std::env::var("COSURG_SITE_LOG").unwrap_or_else(|_| "warn,cosurg::=info".into()),
            );
        let role: proto::Role = site.role.parse().map_err(|e: String| anyhow::anyhow!(e))?;
        if role == proto::Role::Instructor {
            cmd.env("COSURG_TOKEN", &token).env_remove("COSURG_INVITE");
        } else {
            let issued = server::state::mint(
                &invite_key,
                "demo",
                role,
                Some(&site.name),
                (run.seconds * 4.0 + 3600.0) as u64,
                server::state::unix_now_s(),
            )?;
            cmd.env("COSURG_INVITE", issued.invitation);
        }
        // The demo's tools play the scene's canned scripts (or the built-in script file
        // the cast gives the site).
        if site.tools.is_empty() {
            cmd.arg("--no-tool");
        } else {
            cmd.args(["--tool", &site.tools.join(",")]).arg("--script");
            if let Some(rel) = site.script_file {
                let text = sim_core::sim_scene::builtin::embedded_file(rel)
                    .with_context(|| format!("built-in script {rel} is missing"))?;
                let path = run.out.join(format!("{}-script.toml", site.name));
                std::fs::write(&path, text)
                    .with_context(|| format!("writing {}", path.display()))?;
                cmd.arg(&path);
            }
        }
        if !run.view {
            cmd.arg("--headless");
        }
        if let Some(p) = &run.preset {
            cmd.args(["--preset", p]);
        }
        if let Some(dt) = run.dt {
            cmd.args(["--dt", &dt.to_string()]);
        }
        if let Some(at) = run.reset_at
            && site.role == "instructor"
        {
            cmd.args(["--reset-at", &at.to_string()]);
        }
        if !run.time_scale.is_real() {
            cmd.args(["--time-scale", &run.time_scale.to_string()]);
        }
        cmd.args(&run.extra);
        cmd.args(&site.extra);
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting site {}", site.name))?;
        let bar = multi.add(ProgressBar::new((run.seconds * 1000.0) as u64));
        bar.set_style(style.clone());
        bar.set_prefix(site.name.clone());
        let stdout = child.stdout.take().expect("piped");
        let reader = std::thread::spawn(move || -> Option<SiteReport> {
            let mut last = None;
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(rest) = line.strip_prefix("PROGRESS ") {
                    let mut it = rest.split_whitespace();
                    let t: f64 = it.next().and_then(|v| v.parse().ok()).unwrap_or(0.0);
                    bar.set_position((t * 1000.0) as u64);
                    bar.set_message(format!(
                        "t = {t:.2} s  {}",
                        it.collect::<Vec<_>>().join(" ")
                    ));
                } else if let Ok(r) = serde_json::from_str::<SiteReport>(&line) {
                    last = Some(r);
                }
            }
            bar.finish();
            last
        });
        children.push((site.clone(), child, reader));
    }

    // Sites that fall behind real time still finish; a finer lattice is slower.
    let deadline = Instant::now()
        + Duration::from_secs_f64(
            run.seconds * 4.0 * cell_slowdown(scene_name, run.cell) * run.time_scale.factor()
                + 60.0,
        );
    let mut reports = Vec::new();
    let mut failures = Vec::new();
    for (site, mut child, reader) in children {
        let status = loop {
            if let Some(s) = child.try_wait()? {
                break Some(s);
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                break None;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        let report = reader.join().ok().flatten();
        match (status, report) {
            (Some(s), Some(r)) if s.success() => reports.push(r),
            (s, _) => failures.push(format!(
                "site {} ended with {:?}; see {}",
                site.name,
                s,
                run.out.join(format!("{}.log", site.name)).display()
            )),
        }
    }
    runtime.block_on(handle.shutdown());
    if !failures.is_empty() {
        bail!("{}", failures.join("; "));
    }
    let series = crate::divergence::fill_divergence(&mut reports)?;
    Ok((reports, series))
}

/// The built-in scene `name`, on a lattice of `cell` (m) when given.
fn builtin_scene(name: &str, cell: Option<f64>) -> Result<sim_core::sim_scene::LoadedScene> {
    // `load_scene` names an unknown built-in scene and lists the known ones.
    crate::scene_arg::load_scene_with_cell(Some(&format!("builtin:{name}")), cell)
}

/// Builds `scene` once when `cell` replaced its lattice: some cells pass the scene's
/// checks but not the lattice's (bodies that touch), and a multi-site run should say so
/// once, before it starts its sites, rather than in every site's log.
pub fn check_cell(scene: &sim_core::sim_scene::LoadedScene, cell: Option<f64>) -> Result<()> {
    if let Some(cell) = cell {
        let options = sim_core::SimOptions::from_scene(&scene.scene);
        sim_core::Simulation::new(scene.clone(), options)
            .with_context(|| format!("--cell {cell}"))?;
    }
    Ok(())
}

/// How much longer than on its own lattice a step of built-in scene `name` may take with
/// every cell `cell` (m): the tets grow as the cube of the refinement.
fn cell_slowdown(name: &str, cell: Option<f64>) -> f64 {
    let own = sim_core::sim_scene::builtin::by_name(name)
        .and_then(|s| s.scene.bodies.iter().map(|b| b.cell).reduce(f64::min));
    match (own, cell) {
        (Some(own), Some(cell)) if cell > 0.0 => (own / cell).powi(3).max(1.0),
        _ => 1.0,
    }
}

pub fn demo(args: DemoArgs) -> Result<()> {
    let out = out_dir(&args.out, "demo");
    let scene = builtin_scene(&args.scene, args.cell)?;
    check_cell(&scene, args.cell)?;
    let run = SessionRun {
        cast: cast_for(&args.scene, args.sites, args.slowdown),
        seconds: args.seconds,
        strategy: args.strategy,
        preset: args.preset.clone(),
        seed: args.seed,
        out: out.clone(),
        vtu_interval: args.vtu_interval,
        progress: !args.json,
        dt: Some(args.dt),
        extra: args.site_args.clone(),
        reset_at: args.reset_at,
        view: args.view,
        cell: args.cell,
        time_scale: args.time_scale,
    };
    if args.view && !crate::run_window::display_available() {
        bail!("--view needs a display (DISPLAY is not set)");
    }
    if !args.json {
        eprintln!(
            "cosurg demo: coordinator + {} sites on 127.0.0.1 (QUIC/TLS), scene builtin:{}{} {}, strategy {}, {} s simulated",
            run.cast.len(),
            args.scene,
            args.cell
                .map_or(String::new(), |c| format!(" (cell {c} m)")),
            &scene.hash[..12],
            args.strategy.name(),
            args.seconds
        );
    }
    let (reports, series) = run_session_on(&run, &args.scene)?;
    let rows: Vec<SiteRow> = reports
        .iter()
        .map(|r| SiteRow {
            name: r.name.clone(),
            role: r.role.clone(),
            sim_rate_hz: r.sim_rate_hz,
            step_ms_p50: r.step_ms_p50,
            step_ms_p99: r.step_ms_p99,
            step_ms_max: r.step_ms_max,
            keyframes_sent: r.keyframes_sent,
            keyframes_received: r.keyframes_received,
            up_bytes_per_s: r.up_bytes_per_s,
            down_bytes_per_s: r.down_bytes_per_s,
            divergence_max_mm: r.divergence_max_mm.unwrap_or(0.0),
            divergence_rms_mm: r.divergence_rms_mm.unwrap_or(0.0),
            haptic_rate_hz: r.haptic_rate_hz,
            haptic_jitter_p99_us: r.haptic_jitter_p99_us,
            teaching_sent: r.teaching_sent,
            guide_force_max_n: r.guide_force_max_n,
            guide_force_mean_n: r.guide_force_mean_n,
            playback_distance_mm: r.playback_distance_mm,
            epoch: r.epoch,
            topology_epoch: r.topology_epoch,
            topology_digest: r.topology_digest.clone(),
            cuts: r.cuts,
            clips: r.clips,
            springs_released: r.springs_released,
        })
        .collect();
    write_plots(&out, &series, &reports)?;
    let scores = if reports.iter().any(|r| r.name == SCORED_SITE) {
        match score_against(&reports, SCORED_SITE, REFERENCE_SITE) {
            Ok(s) => Some(s),
            Err(e) => {
                eprintln!("cosurg demo: {SCORED_SITE} not scored: {e:#}");
                None
            }
        }
    } else {
        None
    };
    let summary = DemoSummary {
        scene_hash: scene.hash.clone(),
        cell_m: args.cell,
        seconds: args.seconds,
        strategy: args.strategy.name().into(),
        preset: args.preset.clone(),
        out: out.clone(),
        sites: rows,
        scores,
    };
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_table(&summary);
        println!(
            "\nwrote {}: per-site VTU/PVD series (<site>/vtu/series.pvd), surface recordings (<site>/surfaces.surf), session recordings (<site>/<site>.cosrec, coordinator/demo.cosrec), divergence.png/svg, bandwidth.png/svg, summary.json",
            out.display()
        );
    }
    Ok(())
}

fn print_table(s: &DemoSummary) {
    println!(
        "\n{:<12} {:<10} {:>9} {:>9} {:>9} {:>9} {:>7} {:>7} {:>10} {:>10} {:>9} {:>9}",
        "site",
        "role",
        "rate Hz",
        "p50 ms",
        "p99 ms",
        "max ms",
        "kf out",
        "kf in",
        "up B/s",
        "down B/s",
        "div max",
        "div rms"
    );
    for r in &s.sites {
        println!(
            "{:<12} {:<10} {:>9.0} {:>9.3} {:>9.3} {:>9.3} {:>7} {:>7} {:>10.0} {:>10.0} {:>6.2} mm {:>6.2} mm",
            r.name,
            r.role,
            r.sim_rate_hz,
            r.step_ms_p50,
            r.step_ms_p99,
            r.step_ms_max,
            r.keyframes_sent,
            r.keyframes_received,
            r.up_bytes_per_s,
            r.down_bytes_per_s,
            r.divergence_max_mm,
            r.divergence_rms_mm
        );
    }
    let opt = |v: Option<f64>, prec: usize| v.map_or("-".to_string(), |v| format!("{v:.prec$}"));
    println!(
        "\n{:<12} {:>10} {:>13} {:>8} {:>13} {:>14} {:>15}",
        "site",
        "haptic Hz",
        "jitter p99 µs",
        "taught",
        "guide max N",
        "guide mean N",
        "guide dist mm"
    );
    for r in &s.sites {
        println!(
            "{:<12} {:>10} {:>13} {:>8} {:>13} {:>14} {:>15}",
            r.name,
            opt(r.haptic_rate_hz, 1),
            opt(r.haptic_jitter_p99_us, 0),
            r.teaching_sent.map_or("-".to_string(), |n| n.to_string()),
            opt(r.guide_force_max_n, 3),
            opt(r.guide_force_mean_n, 3),
            opt(r.playback_distance_mm, 2)
        );
    }
    if s.sites.iter().any(|r| r.topology_epoch > 0) {
        println!(
            "\n{:<12} {:>6} {:>18} {:>5} {:>6} {:>16}",
            "site", "epoch", "topology digest", "cuts", "clips", "springs released"
        );
        for r in &s.sites {
            println!(
                "{:<12} {:>6} {:>18} {:>5} {:>6} {:>16}",
                r.name, r.topology_epoch, r.topology_digest, r.cuts, r.clips, r.springs_released
            );
        }
    }
    if let Some(sc) = &s.scores {
        println!(
            "\n{} against the {}'s recording ({} acts; `cosurg score` for details)",
            sc.site,
            REFERENCE_SITE,
            sc.acts.len()
        );
        print!("{}", debrief::report::text_table(sc));
    }
}

fn write_plots(out: &Path, series: &[Series], reports: &[SiteReport]) -> Result<()> {
    write_chart(
        out,
        "divergence",
        &Chart {
            title: "divergence from the owning site (max over surface vertices)",
            x_label: "simulated time (s)",
            y_label: "divergence (mm)",
            log_x: false,
            log_y: false,
            scatter: false,
        },
        series,
    )?;
    let bw: Vec<Series> = reports
        .iter()
        .map(|r| Series {
            label: format!("{} (up, down)", r.name),
            points: vec![
                (0.0, r.up_bytes_per_s / 1e3),
                (1.0, r.down_bytes_per_s / 1e3),
            ],
        })
        .collect();
    write_chart(
        out,
        "bandwidth",
        &Chart {
            title: "application bytes per second per site (x = 0 up, 1 down)",
            x_label: "direction (0 = up, 1 = down)",
            y_label: "kB/s",
            log_x: false,
            log_y: false,
            scatter: true,
        },
        &bw,
    )?;
    Ok(())
}
