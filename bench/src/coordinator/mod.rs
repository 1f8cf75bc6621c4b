//! `cosurg bench coordinator`: how many sites one coordinator process relays, and at what
//! latency, CPU and memory.
//!
//! For each configuration `SESSIONS×SITES` a fresh `cosurg-server` child process hosts that
//! many sessions (a sessions file in a temporary state directory), and this process runs
//! SESSIONS × SITES synthetic sites against it: real QUIC + TLS (pinned fingerprint), the
//! real join (the first site of a session with the instructor token, the others with
//! invitations), no simulation. Every site sends the demo's message mix:
//!
//! * tool poses as datagrams at `--pose-hz` (the demo: every 16 ms of simulated time);
//! * sim-time stamps as datagrams at `--stamp-hz` (the demo: every 50 ms);
//! * heartbeats at the session's heartbeat interval;
//! * keyframes of its own region on unidirectional streams, `--keyframe-hz` per session
//!   shared equally by the session's sites, of `--keyframe-bytes` each, each acknowledged
//!   by every receiver on its control stream. The defaults are what the demo sends: 19.8
//!   keyframes per second per session (mostly from the region owner), 1620 bytes on average
//!   (p50 735, p90 3491, max 3820; docs/results/coordinator/demo-keyframe-sizes.txt).
//!
//! The send time (this process's monotonic clock, since the start of the run) travels in
//! the payload (`ToolPose::sim_time_s`, `SimTimeStamp::wall_send_us`,
//! `RegionKeyframe::sim_time`), so the relay latency — sender → coordinator → receiver,
//! through both QUIC stacks and the loopback — is measured by the receiving synthetic site
//! on the same clock. Only messages sent in the measurement window (after a warm-up) count;
//! receivers keep listening for a drain period after it. "Expected" is what the coordinator
//! should deliver: every message sent, times the other sites of the session.
//!
//! Coordinator CPU is read from `/proc/<pid>/stat` (utime + stime over the window), memory
//! from `/proc/<pid>/status` (VmRSS at the end; per site: the growth over the idle
//! coordinator, divided by the sites). **The synthetic sites run in this process on the same
//! machine and share its cores with the coordinator**: on a small machine they take much of
//! the CPU, so the knee found here is a lower bound for a coordinator with a host of its own.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use clap::Args;
use proto::{
    Credential, FrameDecoder, Heartbeat, Join, KEYFRAME_PRIORITY, KeyframeAck, Message,
    QuantisedNodes, RegionKeyframe, Role, SimTimeStamp, SiteId, ToolPose,
};
use quinn::{Connection, Endpoint};
use serde::Serialize;
use tokio::sync::mpsc;

use cosurg::cli::out_dir;

/// A load: sessions × sites per session.
mod report;
mod synthetic;

use report::{table, write_plots};
use synthetic::{SendParams, connect, site};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Load {
    pub sessions: usize,
    pub sites_per_session: usize,
}

impl std::str::FromStr for Load {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let (a, b) = s
            .split_once(['x', 'X', '×'])
            .ok_or_else(|| format!("{s:?}: expected SESSIONSxSITES, e.g. 32x4"))?;
        let sessions: usize = a.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
        let sites: usize = b.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
        if sessions == 0 || !(2..=64).contains(&sites) {
            return Err(format!(
                "{s:?}: at least one session and 2..=64 sites per session"
            ));
        }
        Ok(Load {
            sessions,
            sites_per_session: sites,
        })
    }
}

#[derive(Debug, Args)]
pub struct CoordinatorArgs {
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Output folder (default out/bench-coordinator-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Quick run: loads 1x3 and 2x3, 1 s each (for tests; timings meaningless).
    #[arg(long)]
    pub quick: bool,
    /// Loads SESSIONSxSITES, in order (comma-separated). Without --keep-going the run
    /// stops after the first load that breaks (datagram loss over 1 % or p99 over 50 ms).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1x3,4x4,8x4,16x4,24x4,32x4,40x4,48x4,64x4,96x4"
    )]
    pub loads: Vec<Load>,
    /// Run every load even after one broke.
    #[arg(long)]
    pub keep_going: bool,
    /// Measurement window per load (s).
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Warm-up before the window (s).
    #[arg(long, default_value_t = 1.0)]
    pub warmup: f64,
    /// Tool poses per second per site.
    #[arg(long, default_value_t = 60.0)]
    pub pose_hz: f64,
    /// Sim-time stamps per second per site.
    #[arg(long, default_value_t = 20.0)]
    pub stamp_hz: f64,
    /// Keyframes per second per session (shared equally by its sites).
    #[arg(long, default_value_t = 20.0)]
    pub keyframe_hz: f64,
    /// Size of one keyframe frame (bytes, approximately; default: the demo's mean).
    #[arg(long, default_value_t = DEMO_KEYFRAME_BYTES)]
    pub keyframe_bytes: usize,
    /// The `cosurg-server` executable (default: beside this executable, else on PATH).
    #[arg(long)]
    pub server: Option<PathBuf>,
    /// Run the coordinator with `--record` (every session recorded into a temporary
    /// folder), to measure what recording costs the relay.
    #[arg(long)]
    pub record: bool,
}

/// Mean keyframe frame size the demo sends (bytes), measured from the coordinator's relay
/// log of `cosurg demo` (docs/results/coordinator/demo-keyframe-sizes.txt).
pub const DEMO_KEYFRAME_BYTES: usize = 1620;

/// Goal: relay p99 at most this (ms) with nothing dropped.
pub const GOAL_P99_MS: f64 = 2.0;

/// One load's results.
#[derive(Debug, Clone, Serialize)]
pub struct LoadRow {
    pub sessions: usize,
    pub sites_per_session: usize,
    pub sites: usize,
    /// Datagrams (poses + stamps) sent in the window, expected deliveries, deliveries.
    pub datagrams_sent: u64,
    pub datagrams_expected: u64,
    pub datagrams_received: u64,
    /// Fraction of expected datagram deliveries that did not arrive.
    pub datagram_loss: f64,
    pub keyframes_sent: u64,
    pub keyframes_expected: u64,
    pub keyframes_received: u64,
    /// Relay latency of datagrams, sender → coordinator → receiver (ms).
    pub relay_p50_ms: f64,
    pub relay_p99_ms: f64,
    pub relay_max_ms: f64,
    /// Keyframe relay latency, first byte sent → whole stream received (ms).
    pub keyframe_p50_ms: f64,
    pub keyframe_p99_ms: f64,
    /// Coordinator CPU over the window (% of one core).
    pub coordinator_cpu_percent: f64,
    /// Coordinator CPU per site (% of one core).
    pub cpu_percent_per_site: f64,
    /// CPU of this process, all synthetic sites together, over the window (% of one core):
    /// they share the machine with the coordinator.
    pub sites_cpu_percent: f64,
    /// The machine's 1-minute load average when the load started (other work included).
    pub load_average: f64,
    /// Coordinator resident memory at the end (MiB) and its growth per site over the idle
    /// coordinator (KiB).
    pub coordinator_rss_mib: f64,
    pub rss_kib_per_site: f64,
    /// Relay p99 within the goal and nothing dropped.
    pub meets_goal: bool,
    /// With `--record`: bytes the coordinator wrote into its recordings.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recording_bytes: Option<u64>,
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct CoordinatorBench {
    pub seconds: f64,
    pub warmup: f64,
    pub pose_hz: f64,
    pub stamp_hz: f64,
    pub keyframe_hz: f64,
    pub keyframe_bytes: usize,
    /// The coordinator recorded every session (`--record`).
    #[serde(default)]
    pub record: bool,
    pub cores: usize,
    pub rows: Vec<LoadRow>,
    /// The largest load meeting the goal (sites), if any.
    pub knee_sites: Option<usize>,
}

pub fn run(mut args: CoordinatorArgs) -> Result<()> {
    if args.quick {
        args.loads = vec!["1x3".parse().expect("load"), "2x3".parse().expect("load")];
        args.seconds = 1.0;
        args.warmup = 0.3;
        args.keep_going = true;
    }
    if !(args.seconds > 0.0 && args.warmup >= 0.0 && args.pose_hz > 0.0) {
        bail!("--seconds and --pose-hz must be positive, --warmup not negative");
    }
    let out = out_dir(&args.out, "bench-coordinator");
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let server = find_server(args.server.as_deref())?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    let mut rows = Vec::new();
    for load in &args.loads {
        if !args.json {
            eprintln!(
                "load {}x{} ({} sites)…",
                load.sessions,
                load.sites_per_session,
                load.sessions * load.sites_per_session
            );
        }
        let row = rt.block_on(run_load(&server, *load, &args))?;
        let broken = row.datagram_loss > 0.01 || row.relay_p99_ms > 50.0;
        rows.push(row);
        if broken && !args.keep_going {
            break;
        }
    }
    let knee_sites = rows.iter().filter(|r| r.meets_goal).map(|r| r.sites).max();
    let bench = CoordinatorBench {
        seconds: args.seconds,
        warmup: args.warmup,
        pose_hz: args.pose_hz,
        stamp_hz: args.stamp_hz,
        keyframe_hz: args.keyframe_hz,
        keyframe_bytes: args.keyframe_bytes,
        record: args.record,
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        rows,
        knee_sites,
    };
    std::fs::write(
        out.join("bench-coordinator.json"),
        serde_json::to_string_pretty(&bench)?,
    )?;
    let table = table(&bench);
    std::fs::write(out.join("bench-coordinator.txt"), &table)?;
    write_plots(&out, &bench.rows)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&bench)?);
    } else {
        print!("{table}");
        println!(
            "\nwrote {} (bench-coordinator.json/.txt, coordinator_latency.png/svg, coordinator_cost.png/svg)",
            out.display()
        );
    }
    Ok(())
}

/// `cosurg-server`: the given path, else beside this executable, else on PATH.
fn find_server(given: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = given {
        if p.is_file() {
            return Ok(p.to_path_buf());
        }
        bail!("--server {}: no such file", p.display());
    }
    let name = format!("cosurg-server{}", std::env::consts::EXE_SUFFIX);
    if let Ok(exe) = std::env::current_exe()
        && let Some(dir) = exe.parent()
        && dir.join(&name).is_file()
    {
        return Ok(dir.join(name));
    }
    if let Some(path) = std::env::var_os("PATH") {
        for dir in std::env::split_paths(&path) {
            if dir.join(&name).is_file() {
                return Ok(dir.join(name));
            }
        }
    }
    bail!(
        "cosurg-server not found beside this executable nor on PATH; build it \
         (cargo build --release --bin cosurg-server) or give --server PATH"
    )
}

/// The coordinator child process.
struct ServerProcess {
    child: Child,
    addr: std::net::SocketAddr,
    fingerprint: String,
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

const TOKEN: &str = "bench-instructor";
const SCENE: &str = "0000";

fn session_name(i: usize) -> String {
    format!("bench-{i:03}")
}

fn start_server(
    exe: &Path,
    state: &Path,
    load: Load,
    record: Option<&Path>,
) -> Result<ServerProcess> {
    use std::io::{BufRead, BufReader, Read};
    let mut file = String::new();
    for i in 0..load.sessions {
        file += &format!(
            "[[session]]\nname = \"{}\"\ntoken = \"{TOKEN}\"\nscene_hash = \"{SCENE}\"\nmax_sites = {}\n\n",
            session_name(i),
            load.sites_per_session
        );
    }
    let sessions = state.join("bench-sessions.toml");
    std::fs::write(&sessions, file)?;
    let mut command = Command::new(exe);
    if let Some(dir) = record {
        command.arg("--record").arg(dir);
    }
    let mut child = command
        .args(["--listen", "127.0.0.1:0", "--status-interval", "0"])
        .arg("--state-dir")
        .arg(state)
        .arg("--sessions")
        .arg(&sessions)
        .args(["--max-sessions", &load.sessions.to_string()])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {}", exe.display()))?;
    let mut out = BufReader::new(child.stdout.take().context("server stdout")?);
    let (mut addr, mut fingerprint) = (None, None);
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut line = String::new();
    while addr.is_none() || fingerprint.is_none() {
        if Instant::now() > deadline {
            bail!("cosurg-server did not print its address within 30 s");
        }
        line.clear();
        if out.read_line(&mut line)? == 0 {
            bail!("cosurg-server exited: {:?}", child.wait()?);
        }
        if let Some(a) = line.strip_prefix("listening: ") {
            addr = Some(a.trim().parse().context("server address")?);
        } else if let Some(f) = line.strip_prefix("fingerprint: ") {
            fingerprint = Some(f.trim().to_string());
        }
    }
    std::thread::spawn(move || {
        let mut sink = String::new();
        let _ = out.read_to_string(&mut sink);
    });
    Ok(ServerProcess {
        child,
        addr: addr.expect("checked"),
        fingerprint: fingerprint.expect("checked"),
    })
}

/// utime + stime of a process (clock ticks).
fn cpu_ticks(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // After "pid (comm) ": state is field 3; utime and stime are fields 14 and 15.
    Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
}

fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

fn clock_ticks_per_s() -> f64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(100.0)
}

/// What every synthetic site shares: the clock, the window, the counters.
struct Shared {
    epoch: Instant,
    /// Measurement window on `epoch`'s clock (s).
    window: (f64, f64),
    datagrams_sent: AtomicU64,
    keyframes_sent: AtomicU64,
    keyframe: RegionKeyframe,
}

impl Shared {
    fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }
    fn in_window(&self, t: f64) -> bool {
        t >= self.window.0 && t < self.window.1
    }
}

/// What one synthetic site received in the window.
struct Received {
    datagram_latency_us: Vec<u32>,
    keyframe_latency_us: Vec<u32>,
}

/// A keyframe of about `bytes` bytes (frame size) with `n` nodes.
fn keyframe_of_size(bytes: usize) -> Result<RegionKeyframe> {
    let make = |n: usize, bits: usize| -> Result<RegionKeyframe> {
        let ids: Vec<u32> = (0..n as u32).collect();
        let pos: Vec<[f64; 3]> = ids
            .iter()
            .map(|&i| [i as f64 * 1e-4, (i % 7) as f64 * 1e-3, 0.02])
            .collect();
        let vel: Vec<[f64; 3]> = ids
            .iter()
            .map(|&i| [0.0, 0.0, (i % 5) as f64 * 1e-3])
            .collect();
        Ok(RegionKeyframe {
            region: 0,
            keyframe_id: 1,
            owner: 0,
            sim_time: 0.0,
            epoch: 0,
            topology: 0,
            tree_bits: vec![0xA5; bits],
            nodes: QuantisedNodes::encode_default(&ids, &pos, &vel)
                .map_err(|e| anyhow::anyhow!("quantising nodes: {e:?}"))?,
        })
    };
    let len = |k: &RegionKeyframe| proto::encode_frame(&Message::Keyframe(k.clone())).len();
    // Nodes carry most of a real keyframe; tree bits are an eighth of it here.
    let bits = bytes / 8;
    let per_node = (len(&make(200, bits)?) - len(&make(100, bits)?)) as f64 / 100.0;
    let base = len(&make(0, bits)?) as f64;
    let n = ((bytes as f64 - base) / per_node).max(0.0).round() as usize;
    make(n, bits)
}

async fn run_load(server_exe: &Path, load: Load, args: &CoordinatorArgs) -> Result<LoadRow> {
    let state = tempfile::tempdir().context("temporary state directory")?;
    let (key, _) = server::state::StateDir::new(state.path())
        .invite_key()
        .context("invitation key")?;
    let load_average = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(f64::NAN);
    let recordings = args.record.then(|| state.path().join("recordings"));
    let server = start_server(server_exe, state.path(), load, recordings.as_deref())?;
    let pid = server.child.id();
    let idle_rss = rss_kib(pid).unwrap_or(0);
    let client_cfg = server::tls::client_config_pinned(&server.fingerprint)?;
    // A few client endpoints (UDP sockets), as several machines would have.
    let endpoints: Vec<Endpoint> = (0..load.sessions.clamp(1, 8))
        .map(|_| {
            // Each socket stands for several remote machines: give it the coordinator's
            // receive buffer, so the load generator does not drop what the coordinator sent.
            let addr = "127.0.0.1:0".parse().expect("addr");
            let mut e = server::coordinator::bind_endpoint(None, addr)?;
            e.set_default_client_config(client_cfg.clone());
            Ok(e)
        })
        .collect::<std::io::Result<_>>()?;
    let mut keyframe = keyframe_of_size(args.keyframe_bytes)?;
    keyframe.owner = 0;

    // Join every site (sessions in parallel, sites of a session in order).
    let mut joins = tokio::task::JoinSet::new();
    for s in 0..load.sessions {
        let ep = endpoints[s % endpoints.len()].clone();
        let key = key.clone();
        let addr = server.addr;
        joins.spawn(async move {
            let mut links = Vec::new();
            for k in 0..load.sites_per_session {
                let (role, credential) = if k == 0 {
                    (Role::Instructor, Credential::Token(TOKEN.into()))
                } else {
                    let i = server::state::mint(
                        &key,
                        &session_name(s),
                        Role::Trainee,
                        None,
                        3600,
                        server::state::unix_now_s(),
                    )?;
                    (Role::Trainee, Credential::Invitation(i.invitation))
                };
                let join = Join {
                    protocol_version: proto::PROTOCOL_VERSION,
                    scene_hash: SCENE.into(),
                    role,
                    site_name: format!("site-{k}"),
                    session: session_name(s),
                    credential,
                    time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
                };
                links.push(connect(&ep, addr, &join).await?);
            }
            anyhow::Ok(links)
        });
    }
    let mut sessions = Vec::new();
    while let Some(r) = joins.join_next().await {
        sessions.push(r.context("join task")??);
    }

    let start = args.warmup;
    let shared = Arc::new(Shared {
        epoch: Instant::now(),
        window: (start, start + args.seconds),
        datagrams_sent: AtomicU64::new(0),
        keyframes_sent: AtomicU64::new(0),
        keyframe,
    });
    let stop_at = shared.window.1;
    let drain = 0.5;
    let mut tasks = tokio::task::JoinSet::new();
    let mut site_index = 0usize;
    for links in sessions {
        for link in links {
            let shared = shared.clone();
            site_index += 1;
            let params = SendParams {
                pose_hz: args.pose_hz,
                stamp_hz: args.stamp_hz,
                keyframe_hz: args.keyframe_hz / load.sites_per_session as f64,
                // Real sites' clocks are independent: spread every site's phase over one
                // pose period (golden-ratio sequence). Phases shared by all sessions would
                // make every session's k-th site send at the same instant, a burst no
                // deployment produces.
                phase: (site_index as f64 * 0.618_033_988_75).fract(),
            };
            tasks.spawn(site(link, shared, params, stop_at, stop_at + drain));
        }
    }
    // CPU over the window.
    let tick = clock_ticks_per_s();
    tokio::time::sleep(Duration::from_secs_f64(start)).await;
    let me = std::process::id();
    let (c0, s0, t0) = (cpu_ticks(pid), cpu_ticks(me), Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    let (c1, s1, t1) = (cpu_ticks(pid), cpu_ticks(me), Instant::now());
    let rss = rss_kib(pid).unwrap_or(0);
    let mut datagram_latency = Vec::new();
    let mut keyframe_latency = Vec::new();
    while let Some(r) = tasks.join_next().await {
        let r = r.context("site task")?;
        datagram_latency.extend(r.datagram_latency_us);
        keyframe_latency.extend(r.keyframe_latency_us);
    }
    drop(server);
    let recording_bytes = recordings.map(|dir| {
        std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| e.metadata().ok())
            .map(|m| m.len())
            .sum()
    });
    for e in &endpoints {
        e.close(0u32.into(), b"bench done");
    }

    let sites = load.sessions * load.sites_per_session;
    let others = (load.sites_per_session - 1) as u64;
    let datagrams_sent = shared.datagrams_sent.load(Ordering::Relaxed);
    let keyframes_sent = shared.keyframes_sent.load(Ordering::Relaxed);
    let datagrams_expected = datagrams_sent * others;
    let keyframes_expected = keyframes_sent * others;
    let datagrams_received = datagram_latency.len() as u64;
    let percent = |a: Option<u64>, b: Option<u64>| match (a, b) {
        (Some(a), Some(b)) => 100.0 * b.saturating_sub(a) as f64 / tick / (t1 - t0).as_secs_f64(),
        _ => f64::NAN,
    };
    let cpu = percent(c0, c1);
    let sites_cpu = percent(s0, s1);
    let (p50, p99, max) = percentiles(&mut datagram_latency);
    let (kp50, kp99, _) = percentiles(&mut keyframe_latency);
    let loss = if datagrams_expected == 0 {
        0.0
    } else {
        datagrams_expected.saturating_sub(datagrams_received) as f64 / datagrams_expected as f64
    };
    let keyframes_received = keyframe_latency.len() as u64;
    Ok(LoadRow {
        sessions: load.sessions,
        sites_per_session: load.sites_per_session,
        sites,
        datagrams_sent,
        datagrams_expected,
        datagrams_received,
        datagram_loss: loss,
        keyframes_sent,
        keyframes_expected,
        keyframes_received,
        relay_p50_ms: p50,
        relay_p99_ms: p99,
        relay_max_ms: max,
        keyframe_p50_ms: kp50,
        keyframe_p99_ms: kp99,
        coordinator_cpu_percent: cpu,
        cpu_percent_per_site: cpu / sites as f64,
        sites_cpu_percent: sites_cpu,
        load_average,
        coordinator_rss_mib: rss as f64 / 1024.0,
        rss_kib_per_site: rss.saturating_sub(idle_rss) as f64 / sites as f64,
        meets_goal: p99 <= GOAL_P99_MS
            && datagrams_received >= datagrams_expected
            && keyframes_received >= keyframes_expected,
        recording_bytes,
    })
}

/// (p50, p99, max) in ms of latencies in µs (NaN for none).
fn percentiles(v: &mut [u32]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    v.sort_unstable();
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize] as f64 / 1000.0;
    (q(0.5), q(0.99), q(1.0))
}
