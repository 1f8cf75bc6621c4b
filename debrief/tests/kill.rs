//! A writer process killed (SIGKILL on Unix) mid-recording leaves a file that reads back
//! up to its last complete record, with no gap before it.

use std::process::Command;
use std::time::{Duration, Instant};

use cosurg_debrief::*;

const CHILD_ENV: &str = "COSURG_DEBRIEF_KILL_CHILD";

/// Runs only as the child of `killed_writer_leaves_a_readable_recording`: records
/// forever at about 2,500 steps per second of wall time until killed.
#[test]
#[ignore = "child process of killed_writer_leaves_a_readable_recording"]
fn kill_child_writer() {
    let Ok(path) = std::env::var(CHILD_ENV) else {
        return;
    };
    let header = SessionHeader {
        session: "kill".into(),
        site: "A".into(),
        role: "trainee".into(),
        scene: "synthetic".into(),
        sim_rate_hz: 500.0,
        sample_every: 0,
        started_unix_ms: 0,
        damage_strain_threshold: None,
        software: "test".into(),
    };
    let mut rec = Recorder::create(&path, header, RecorderSettings::default()).unwrap();
    let tool = rec.declare_tool("A", "forceps", "forceps").unwrap();
    let rest: Vec<[f64; 3]> = (0..500).map(|i| [i as f64 * 1e-4, 0.0, 0.0]).collect();
    let tris: Vec<[u32; 3]> = (0..498).map(|i| [i, i + 1, i + 2]).collect();
    let surf = rec.declare_surface("organ", &rest, &tris).unwrap();
    for step in 0u64.. {
        let t = step as f64 / 500.0;
        let state = ToolState {
            position: [0.01 * t.sin(), 0.01 * t.cos(), 0.0],
            orientation: [1.0, 0.0, 0.0, 0.0],
            ..ToolState::default()
        };
        rec.tool_sample(step, t, tool, &state).unwrap();
        if rec.wants_surface(surf, t) {
            let v: Vec<[f64; 3]> = rest.iter().map(|p| [p[0], 1e-3 * t.sin(), 0.0]).collect();
            rec.surface(step, t, surf, &v).unwrap();
        }
        if step % 5 == 0 {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

#[test]
fn killed_writer_leaves_a_readable_recording() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("A.cosrec");
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["kill_child_writer", "--exact", "--ignored", "--nocapture"])
        .env(CHILD_ENV, &path)
        .spawn()
        .unwrap();
    // Let it record at least a few flush intervals (0.5 s of simulated time each).
    let start = Instant::now();
    loop {
        std::thread::sleep(Duration::from_millis(100));
        let seen = Recording::open(&path)
            .ok()
            .and_then(|r| r.time_span())
            .map_or(0.0, |s| s.1);
        if seen > 2.0 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the child recorded {seen} s in 60 s"
        );
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let r = Recording::open(&path).unwrap();
    assert_eq!(r.header.site, "A");
    assert!(
        matches!(r.tail, Tail::Complete | Tail::Truncated { .. }),
        "{}",
        r.tail
    );
    // Every recorded step from 0 to the last, none missing (every 2nd step at 500 Hz).
    let steps: Vec<u64> = r.steps().map(|s| s.step).collect();
    assert!(steps.len() > 500, "{} step records", steps.len());
    for (k, s) in steps.iter().enumerate() {
        assert_eq!(*s, 2 * k as u64);
    }
    assert!(!r.surface_shapes(0).is_empty());
}
