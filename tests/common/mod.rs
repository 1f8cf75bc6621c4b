//! What the end-to-end tests share: the real `cosurg-server` and `cosurg` binaries as
//! separate processes, speaking QUIC with TLS on 127.0.0.1. Every child is killed when its
//! test ends; every wait is bounded.

// Each test binary uses its own part of these helpers.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use cosurg::site::SiteReport;

pub const TOKEN: &str = "e2e-secret";

/// The tests run one at a time: each starts several real-time simulations, and a 2-core
/// machine running them all at once would measure its own overload, not the protocol.
pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}
pub const SESSION: &str = "e2e";

/// A `cosurg` command logging warnings only, or what `COSURG_E2E_LOG` asks for (a
/// `COSURG_LOG` filter, to read a failed run's site logs with `COSURG_E2E_KEEP`).
pub fn cosurg() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cosurg"));
    let filter = std::env::var("COSURG_E2E_LOG").unwrap_or_else(|_| "warn".into());
    c.env("COSURG_LOG", filter);
    c
}

/// A coordinator process (killed on drop) and its state directory.
pub struct Server {
    _process: test_support::server::ServerProcess,
    pub addr: String,
    pub fingerprint: String,
    pub _state: tempfile::TempDir,
}

pub fn start_server() -> Server {
    start_server_in(tempfile::tempdir().unwrap())
}

/// A coordinator with `state` as its state directory (certificate, invitation key,
/// revocations).
pub fn start_server_in(state: tempfile::TempDir) -> Server {
    let scene = sim_core::sim_scene::builtin::cholecystectomy();
    start_server_for(state, &scene.hash)
}

/// A coordinator for the scene whose hash is `scene_hash`.
pub fn start_server_for(state: tempfile::TempDir, scene_hash: &str) -> Server {
    start_server_with(state, scene_hash, &[])
}

/// A coordinator on the built-in scene whose session runs `factor` times slower than real
/// time (`--time-scale`; its sites must join with the same).
pub fn start_server_dilated(factor: &str) -> Server {
    let scene = sim_core::sim_scene::builtin::cholecystectomy();
    start_server_with(
        tempfile::tempdir().unwrap(),
        &scene.hash,
        &["--time-scale", factor],
    )
}

fn start_server_with(state: tempfile::TempDir, scene_hash: &str, extra: &[&str]) -> Server {
    // `cosurg-server` belongs to another package: no CARGO_BIN_EXE_ for it here.
    let server_exe = test_support::exe::sibling_exe(env!("CARGO_BIN_EXE_cosurg"), "cosurg-server");
    let mut command = Command::new(server_exe);
    command
        .args([
            "--listen",
            "127.0.0.1:0",
            "--session",
            SESSION,
            "--token",
            TOKEN,
        ])
        .args(["--scene-hash", scene_hash, "--seconds", "300"])
        .args(extra)
        .arg("--state-dir")
        .arg(state.path())
        .env("COSURG_LOG", "warn")
        .stderr(Stdio::null());
    let process = test_support::server::spawn(command, &[]);
    Server {
        addr: process.addr.clone(),
        fingerprint: process.fingerprint.clone(),
        _process: process,
        _state: state,
    }
}

impl Server {
    /// `cosurg-server invite` on the coordinator's state directory: an invitation for
    /// `role`, bound to `site` if given.
    pub fn invite(&self, role: &str, site: Option<&str>, expires: &str) -> String {
        let mut c = Command::new(test_support::exe::sibling_exe(
            env!("CARGO_BIN_EXE_cosurg"),
            "cosurg-server",
        ));
        c.args(["invite", "--role", role, "--expires", expires])
            .arg("--state-dir")
            .arg(self._state.path());
        if let Some(s) = site {
            c.args(["--site", s]);
        }
        let out = c.output().expect("cosurg-server invite");
        assert!(out.status.success(), "{out:?}");
        let text = String::from_utf8(out.stdout).unwrap();
        assert_eq!(text.lines().count(), 1, "one line: {text}");
        text.trim().to_string()
    }
}

/// `cosurg join` for `server` with the common flags: the instructor with the token, the
/// other roles with an invitation bound to their site name.
pub fn join(server: &Server, site: &str, role: &str) -> Command {
    if role == "instructor" {
        join_with_token(server, site, role, TOKEN)
    } else {
        join_with_invite(server, site, role, &server.invite(role, Some(site), "1h"))
    }
}

pub fn join_base(server: &Server, site: &str, role: &str) -> Command {
    let mut c = cosurg();
    c.arg("join")
        .args(["--server", &server.addr, "--session", SESSION])
        .args(["--role", role, "--site", site, "--pin", &server.fingerprint])
        .args(["--dt", "0.004", "--no-haptics", "--vtu-interval", "0"])
        // never a window, whatever the environment's DISPLAY
        .arg("--headless")
        // the one-body scene (the server's scene hash) and keyframe sync, unless a test
        // asks for another (clap takes the last of a repeated option)
        .args([
            "--scene",
            "builtin:cholecystectomy",
            "--strategy",
            "keyframe",
        ])
        .env_remove("COSURG_TOKEN")
        .env_remove("COSURG_INVITE");
    c
}

pub fn join_with_token(server: &Server, site: &str, role: &str, token: &str) -> Command {
    let mut c = join_base(server, site, role);
    c.args(["--token", token]);
    c
}

pub fn join_with_invite(server: &Server, site: &str, role: &str, invite: &str) -> Command {
    let mut c = join_base(server, site, role);
    c.args(["--invite", invite]);
    c
}

pub fn report_of(out: &Output) -> SiteReport {
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout
        .lines()
        .rev()
        .find(|l| l.starts_with('{'))
        .unwrap_or_else(|| {
            panic!(
                "no JSON report; status {:?}\nstdout: {stdout}\nstderr: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr)
            )
        });
    serde_json::from_str(line).expect("site report JSON")
}

pub fn refused(mut cmd: Command, expect: &str) {
    cmd.args(["--seconds", "1", "--no-tool"]);
    let out = test_support::run::run_bounded(cmd, Duration::from_secs(60));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(3),
        "exit code 3 = refused; stderr: {stderr}"
    );
    assert!(
        stderr.contains("refused by the coordinator") && stderr.contains(expect),
        "stderr names the reason {expect}: {stderr}"
    );
}

/// A directory for one session's logs and recordings, removed afterwards unless
/// `COSURG_E2E_KEEP` is set (then its path is printed, to read a failed run's site logs).
pub fn session_dir() -> tempfile::TempDir {
    let mut dir = tempfile::Builder::new();
    let keep = std::env::var_os("COSURG_E2E_KEEP").is_some();
    dir.disable_cleanup(keep);
    let dir = dir.tempdir().unwrap();
    if keep {
        eprintln!("session directory kept: {}", dir.path().display());
    }
    dir
}

pub fn spawn_site(server: &Server, dir: &Path, name: &str, role: &str, extra: &[&str]) -> Child {
    let mut c = join(server, name, role);
    c.args(extra)
        .arg("--out")
        .arg(dir.join(name))
        .arg("--json")
        .stdout(Stdio::piped())
        .stderr(Stdio::from(
            std::fs::File::create(dir.join(format!("{name}.log"))).unwrap(),
        ));
    c.spawn().expect("spawn site")
}

pub fn wait_report(mut child: Child, limit: Duration, log: PathBuf) -> SiteReport {
    let deadline = Instant::now() + limit;
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "site failed: {:?}\n{}",
        out.status,
        std::fs::read_to_string(log).unwrap_or_default()
    );
    report_of(&out)
}

/// A site that joins, runs one simulated second and leaves: exit code 0.
pub fn joins(mut cmd: Command) {
    cmd.args(["--seconds", "1", "--no-tool", "--no-realtime"]);
    let out = test_support::run::run_bounded(cmd, Duration::from_secs(60));
    assert!(
        out.status.success(),
        "joined and left; stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// On loopback, receivers keep a playout lag behind the owner, so keyframes arrive before
/// they are due and the region is interpolated between them rather than extrapolated:
/// 2–12 mm measured with debug binaries (the grasp release is the largest transient).
pub const LOOPBACK_MOTION_BOUND_MM: f64 = 25.0;
