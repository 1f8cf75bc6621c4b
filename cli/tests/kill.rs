//! A site killed mid-session: with the real binaries (`cosurg-server --record`, two
//! `cosurg join` sites over QUIC on 127.0.0.1), trainee A is SIGKILLed about 2.5 s into
//! the session. Its own recording reads back up to its last complete record; the
//! coordinator — stopped gracefully with SIGTERM after the instructor finished — holds
//! the whole session, A's tool poses until the kill and A's leave included; and
//! `cosurg score` scores A from the coordinator's recording when A's own file is gone.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use debrief::{EventKind, Recording, ScoreReport, Session, Tail};

const TOKEN: &str = "kill-secret";
const SESSION: &str = "kill";
/// Simulated seconds the instructor runs.
const SECONDS: f64 = 7.0;

/// Kills (SIGKILL) and reaps a child when dropped: nothing outlives the test.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn server_exe() -> std::path::PathBuf {
    test_support::exe::sibling_exe(env!("CARGO_BIN_EXE_cosurg"), "cosurg-server")
}

fn wait_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        assert!(
            Instant::now() < deadline,
            "process did not exit within {limit:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn join(
    addr: &str,
    fingerprint: &str,
    dir: &Path,
    site: &str,
    role: &str,
    credential: (&str, &str),
    tool: &str,
) -> Reaped {
    let child = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .arg("join")
        .args(["--server", addr, "--session", SESSION])
        .args(["--role", role, "--site", site, "--pin", fingerprint])
        .args([credential.0, credential.1])
        .args(["--dt", "0.004", "--no-haptics", "--vtu-interval", "0"])
        // the one-body scene and keyframe sync this test's timings were set for
        .args([
            "--scene",
            "builtin:cholecystectomy",
            "--strategy",
            "keyframe",
        ])
        .args(["--expect-sites", "2", "--seconds", &SECONDS.to_string()])
        .args([
            "--tool",
            tool,
            "--script",
            "--headless",
            "--script-start",
            "0.2",
        ])
        .arg("--out")
        .arg(dir.join(site))
        .env_remove("COSURG_TOKEN")
        .env_remove("COSURG_INVITE")
        .env("COSURG_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::from(
            std::fs::File::create(dir.join(format!("{site}.log"))).unwrap(),
        ))
        .spawn()
        .expect("spawn cosurg join");
    Reaped(child)
}

/// Last sample time of `site`'s tools in `rec` (s).
fn last_sample(rec: &Recording, site: &str) -> Option<f64> {
    rec.site_tracks(site)
        .iter()
        .filter_map(|t| t.times.last().copied())
        .reduce(f64::max)
}

fn score_json(path: &Path, site: &str) -> ScoreReport {
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .arg("score")
        .arg(path)
        .args(["--site", site, "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "cosurg score {}: {}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn a_killed_site_leaves_a_readable_recording_and_the_coordinator_keeps_the_session() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let state = dir.join("state");
    let scene = sim_core::sim_scene::builtin::cholecystectomy();

    let mut command = Command::new(server_exe());
    command
        .args(["--listen", "127.0.0.1:0", "--session", SESSION])
        .args(["--token", TOKEN, "--scene-hash", &scene.hash])
        .args(["--seconds", "300", "--status-interval", "0"])
        .arg("--state-dir")
        .arg(&state)
        .arg("--record")
        .arg(dir.join("coordinator"))
        .env("COSURG_LOG", "warn")
        .stderr(Stdio::null());
    let mut server = test_support::server::spawn(command, &["recording"]);
    let (addr, fingerprint) = (server.addr.clone(), server.fingerprint.clone());
    let coordinator_file = std::path::PathBuf::from(&server.announced["recording"]);
    assert_eq!(
        coordinator_file,
        dir.join("coordinator").join("kill.cosrec")
    );

    let invite = Command::new(server_exe())
        .args(["invite", "--role", "trainee", "--site", "A"])
        .arg("--state-dir")
        .arg(&state)
        .output()
        .unwrap();
    assert!(invite.status.success(), "{invite:?}");
    let invite = String::from_utf8(invite.stdout).unwrap().trim().to_string();

    let mut instructor = join(
        &addr,
        &fingerprint,
        dir,
        "instructor",
        "instructor",
        ("--token", TOKEN),
        "forceps",
    );
    let mut a = join(
        &addr,
        &fingerprint,
        dir,
        "A",
        "trainee",
        ("--invite", &invite),
        "probe",
    );

    // Kill A once its own recording (read while being written) reaches 2.5 s.
    let a_file = dir.join("A").join("A.cosrec");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let t = Recording::open(&a_file)
            .ok()
            .and_then(|r| last_sample(&r, "A"));
        if t.is_some_and(|t| t >= 2.5) {
            break;
        }
        assert!(
            a.0.try_wait().unwrap().is_none(),
            "A ended early: {}",
            std::fs::read_to_string(dir.join("A.log")).unwrap_or_default()
        );
        assert!(Instant::now() < deadline, "A never reached 2.5 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    a.0.kill().unwrap(); // SIGKILL: no flush, no leave message
    a.0.wait().unwrap();

    // The instructor carries on to the end of its session.
    let status = wait_exit(&mut instructor.0, Duration::from_secs(180));
    assert!(
        status.success(),
        "instructor failed: {}",
        std::fs::read_to_string(dir.join("instructor.log")).unwrap_or_default()
    );

    // A's own file: every complete record before the kill, nothing worse than a cut.
    let own = Recording::open(&a_file).expect("a killed site's recording reads back");
    assert!(
        matches!(own.tail, Tail::Complete | Tail::Truncated { .. }),
        "{}",
        own.tail
    );
    let own_end = last_sample(&own, "A").unwrap();
    assert!(own_end >= 2.5, "A's own recording ends at {own_end} s");
    assert!(
        !own.events()
            .any(|e| e.site == "A" && e.kind == EventKind::Leave),
        "a killed site cannot record its own leave"
    );

    // Stop the coordinator gracefully (SIGTERM), once it noticed A is gone (A's leave is
    // written as soon as the liveness timeout fires; events are flushed at once).
    let deadline = Instant::now() + Duration::from_secs(60);
    while !Recording::open(&coordinator_file)
        .unwrap()
        .events()
        .any(|e| e.site == "A" && e.kind == EventKind::Leave)
    {
        assert!(
            Instant::now() < deadline,
            "the coordinator never recorded A's leave"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let term = Command::new("kill")
        .args(["-TERM", &server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    assert!(wait_exit(&mut server.child, Duration::from_secs(30)).success());

    let coord = Recording::open(&coordinator_file).unwrap();
    assert_eq!(coord.tail, Tail::Complete, "finished on SIGTERM");
    assert_eq!(coord.header.role, "coordinator");
    let joins: Vec<&str> = coord
        .events()
        .filter(|e| e.kind == EventKind::Join)
        .map(|e| e.site.as_str())
        .collect();
    assert!(
        joins.contains(&"instructor") && joins.contains(&"A"),
        "{joins:?}"
    );
    // A's poses until the kill: at least as far as its own file, and not past its leave.
    let coord_a_end = last_sample(&coord, "A").expect("A's poses");
    assert!(
        coord_a_end >= own_end - 0.05,
        "coordinator has A until {coord_a_end} s, A's file until {own_end} s"
    );
    let leave = coord
        .events()
        .find(|e| e.site == "A" && e.kind == EventKind::Leave)
        .unwrap();
    assert!(leave.time >= coord_a_end, "leave after the last pose");
    let a_track = &coord.site_tracks("A")[0];
    assert!(
        a_track.len() as f64 >= 30.0 * (coord_a_end - a_track.times[0]),
        "poses at the sites' 62.5 Hz: {} over {} s",
        a_track.len(),
        coord_a_end - a_track.times[0]
    );
    // The instructor's poses well past the kill (a site sends its tool while its script
    // drives it: the grasp-and-lift ends 6 s after its start at 0.2 s), and its leave at
    // the end of its session.
    let instructor_end = last_sample(&coord, "instructor").unwrap();
    assert!(
        instructor_end >= 6.0,
        "instructor poses until {instructor_end} s"
    );
    let instructor_leave = coord
        .events()
        .find(|e| e.site == "instructor" && e.kind == EventKind::Leave)
        .expect("the instructor's leave");
    assert!(
        instructor_leave.time >= SECONDS - 0.5,
        "instructor left at {} s",
        instructor_leave.time
    );
    assert!(
        coord.events().any(|e| e.kind == EventKind::Claim),
        "region claims recorded"
    );

    // Scores: A's path from the coordinator's recording alone...
    let from_coord = score_json(&coordinator_file, "A");
    let session = &from_coord.acts[0];
    assert!(session.measures.path_length_m > 0.005, "{session:?}");
    assert!((session.act.end_s - coord_a_end).abs() < 1e-6);
    // ...and from the session folder once A's own file is gone, the tool named after the
    // instructor's recording of the scene.
    std::fs::remove_file(&a_file).unwrap();
    let s = Session::open(dir).unwrap();
    assert_eq!(s.recording_for("A").unwrap().header.site, "coordinator");
    let from_dir = score_json(dir, "A");
    assert_eq!(from_dir.acts[0].act.tool, "probe");
    assert_eq!(
        from_dir.acts[0].measures.path_length_m,
        session.measures.path_length_m
    );
}
