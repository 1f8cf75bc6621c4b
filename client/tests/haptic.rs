//! The haptic loop, its devices and teaching mode (issue 4 items 5–6).
//!
//! No wall-clock performance assertions: counts and invariants only. Timing-dependent
//! steps (UDP staleness) wait for a condition with a generous timeout.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use cosurg::haptic::udp::{FLAG_STALE, ForceDatagram, PoseDatagram};
use cosurg::haptic::{
    AppliedForce, GuideSpring, HapticConfig, HapticModel, RenderConfig, ScriptedDevice,
    TeachingPlayback, TeachingRecorder, UdpBridgeDevice, measure_loop, measure_loop_with, spawn,
    spawn_with_model,
};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use sim_scene::{ToolPose, ToolScript, ToolWaypoint};

fn pose(x: [f64; 3], jaw: f64) -> ToolPose {
    ToolPose {
        position: Vector3::from(x),
        orientation: UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.3),
        jaw,
    }
}

/// A script of one tool: `(t, position, jaw)` keyframes.
fn script(tool: &str, keys: &[(f64, [f64; 3], f64)]) -> ToolScript {
    let mut s = ToolScript::default();
    s.tracks.insert(
        tool.into(),
        keys.iter()
            .map(|&(t, x, jaw)| ToolWaypoint {
                t,
                pose: pose(x, jaw),
                label: None,
            })
            .collect(),
    );
    s
}

/// A model sampled at `xs` with force `fs` and a full (non-diagonal) stiffness.
fn model(xs: [f64; 3], fs: [f64; 3], grasped: bool) -> HapticModel {
    HapticModel {
        sim_time: 0.5,
        tool_pose_at_sample: pose(xs, 0.0),
        force: Vector3::from(fs),
        torque: Vector3::new(0.001, -0.002, 0.0),
        stiffness: -Matrix3::new(400.0, 50.0, 0.0, 50.0, 300.0, 20.0, 0.0, 20.0, 600.0),
        grasped,
    }
}

fn no_limits() -> HapticConfig {
    HapticConfig {
        render: RenderConfig {
            max_force: 1e6,
            max_torque: 1e6,
            max_force_rate: f64::INFINITY,
            ..RenderConfig::default()
        },
        ..HapticConfig::default()
    }
}

/// All records but the final zero the loop sends when it stops.
fn body(forces: &[AppliedForce]) -> &[AppliedForce] {
    let (last, body) = forces.split_last().expect("at least the final record");
    assert_eq!(
        last.force,
        Vector3::zeros(),
        "the loop leaves the device at zero force"
    );
    body
}

#[test]
fn renders_local_linear_model_exactly() {
    let xs = [0.03, -0.07, -0.03];
    // sweeps ±5 mm around x_s on all axes
    let dev = ScriptedDevice::new(
        script(
            "forceps",
            &[
                (0.0, [0.025, -0.075, -0.035], 0.6),
                (0.1, [0.035, -0.065, -0.025], 0.3),
                (0.2, [0.025, -0.07, -0.028], 0.0),
            ],
        ),
        "forceps",
    )
    .unwrap();
    let m = model(xs, [0.3, -0.2, 1.0], true);
    let h = spawn_with_model(dev, no_limits(), Some(&m)).unwrap();
    std::thread::sleep(Duration::from_millis(250));
    let (dev, stats) = h.stop();
    let rec = body(dev.forces());
    assert_eq!(rec.len() as u64, stats.ticks);
    assert!(stats.ticks >= 20, "{stats:?}");
    assert_eq!(stats.models_seen, 1);
    let k = m.stiffness;
    let mut spread = 0.0f64;
    for r in rec {
        let expect = m.force + k * (r.position - m.tool_pose_at_sample.position);
        assert!((r.force - expect).norm() < 1e-12, "{:?} vs {expect}", r);
        assert_eq!(r.torque, m.torque);
        assert_eq!(r.position, dev.pose_at(r.t).position);
        spread = spread.max((r.force - m.force).norm());
    }
    assert!(
        spread > 1.0,
        "the device moved through the model: {spread} N"
    );
    assert_eq!(stats.clamped_ticks, 0);
}

#[test]
fn force_limit_and_rate_limit_always_hold() {
    let limit = 2.0;
    let rate = 2000.0; // N/s → 2 N per 1 ms tick
    let cfg = HapticConfig {
        render: RenderConfig {
            max_force: limit,
            max_torque: 0.05,
            max_force_rate: rate,
            ..RenderConfig::default()
        },
        ..HapticConfig::default()
    };
    // a stiff wall crossed back and forth: forces from 0 to ~40 N
    let dev = ScriptedDevice::new(
        script(
            "probe",
            &[
                (0.0, [0.0, 0.0, 0.01], 0.0),
                (0.05, [0.0, 0.0, -0.01], 0.0),
                (0.1, [0.0, 0.0, 0.01], 0.0),
                (0.15, [0.0, 0.0, -0.01], 0.0),
            ],
        ),
        "probe",
    )
    .unwrap();
    let h = spawn(dev, cfg).unwrap();
    let writer = h.model_writer();
    // A stand-in simulation thread publishing changing models at ≈ 200 Hz, one of them
    // not finite.
    let sim = std::thread::spawn(move || {
        for i in 0..40 {
            let mut m = model([0.0, 0.0, 0.0], [0.0, 0.0, 0.5 + 0.1 * i as f64], false);
            m.stiffness =
                Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, -2000.0 - 100.0 * i as f64));
            if i == 20 {
                m.force.x = f64::NAN;
            }
            writer.publish(&m);
            std::thread::sleep(Duration::from_millis(5));
        }
    });
    sim.join().unwrap();
    let (dev, stats) = h.stop();
    let rec = body(dev.forces());
    assert!(stats.models_seen >= 2, "{stats:?}");
    assert!(stats.clamped_ticks > 0);
    assert!(stats.max_force <= limit + 1e-12);
    let mut prev = Vector3::zeros();
    for r in rec {
        assert!(r.force.iter().all(|v| v.is_finite()));
        assert!(r.force.norm() <= limit + 1e-12, "{r:?}");
        assert!(r.torque.norm() <= 0.05 + 1e-12, "{r:?}");
        assert!(
            (r.force - prev).norm() <= rate * 1e-3 + 1e-9,
            "rate limit: {r:?} after {prev}"
        );
        prev = r.force;
    }
    assert!(
        rec.iter().any(|r| (r.force.norm() - limit).abs() < 1e-9),
        "limit reached"
    );
}

#[test]
fn stops_cleanly_and_counts_ticks() {
    let dev = ScriptedDevice::at(Vector3::new(0.01, 0.02, 0.03));
    let h = spawn(dev, HapticConfig::default()).unwrap();
    let reader = h.input_reader();
    let t0 = Instant::now();
    while h.ticks() < 20 && t0.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(h.is_running());
    assert_eq!(h.device_name(), "scripted:probe");
    let seen = h.ticks();
    let (version, input) = reader.latest().expect("inputs published");
    assert!(version >= 1);
    assert_eq!(input.position, Vector3::new(0.01, 0.02, 0.03));
    let (dev, stats) = h.stop();
    assert!(stats.ticks >= seen && seen >= 20, "{seen} {stats:?}");
    assert_eq!(
        dev.forces().len() as u64,
        stats.ticks + 1,
        "one apply per tick + final zero"
    );
    // one input per tick, the reader outlives the loop
    assert_eq!(reader.latest().unwrap().0, stats.ticks);
    assert!(stats.rate_hz.is_finite() && stats.rate_hz > 0.0);
    assert!(stats.period_p50_us.is_finite() && stats.jitter_p99_us.is_finite());
    assert!(stats.period_p99_us >= stats.period_p50_us);
    assert_eq!(stats.max_force, 0.0, "no model, no guide: no force");
    // Dropping a running handle stops and joins the thread too.
    let h = spawn(
        ScriptedDevice::at(Vector3::zeros()),
        HapticConfig::default(),
    )
    .unwrap();
    drop(h);
    // Invalid configurations are refused.
    let bad = HapticConfig {
        spin: Duration::from_millis(2),
        ..HapticConfig::default()
    };
    let e = spawn(ScriptedDevice::at(Vector3::zeros()), bad)
        .err()
        .unwrap();
    assert!(e.to_string().contains("spin"), "{e}");
}

fn recv_force(sock: &UdpSocket) -> Option<ForceDatagram> {
    let mut buf = [0u8; 256];
    match sock.recv(&mut buf) {
        Ok(n) => ForceDatagram::decode(&buf[..n]),
        Err(_) => None,
    }
}

#[test]
fn udp_bridge_roundtrip_and_stale_fade_out() {
    let bridge = UdpBridgeDevice::bind("127.0.0.1:0").unwrap();
    let addr = bridge.local_addr();
    // grasped, constant 1 N along z (K = 0)
    let mut m = model([0.0; 3], [0.0, 0.0, 1.0], true);
    m.stiffness = Matrix3::zeros();
    m.torque = Vector3::zeros();
    let h = spawn_with_model(bridge, HapticConfig::default(), Some(&m)).unwrap();

    // The fake driver: pose datagrams at ≈ 1 kHz until it has felt the full 1 N.
    let driver = UdpSocket::bind("127.0.0.1:0").unwrap();
    driver.connect(addr).unwrap();
    driver.set_nonblocking(true).unwrap(); // drain what is there, then send the next pose
    let pose_at = |seq: u32| PoseDatagram {
        seq,
        device_time_us: 1_000_000 + 1000 * u64::from(seq),
        position: [0.01, 0.02 + 1e-6 * f64::from(seq), 0.03],
        orientation: [0.0, 0.0, 0.0, 2.0], // not normalised: 180° about z
        jaw: 0.25,
        buttons: 0b10,
    };
    let t0 = Instant::now();
    let mut seq = 0u32;
    let mut full: Option<ForceDatagram> = None;
    let mut received = 0;
    while t0.elapsed() < Duration::from_secs(5) && (full.is_none() || seq < 100) {
        seq += 1;
        driver.send(&pose_at(seq).encode()).unwrap();
        if seq == 50 {
            // a late, older datagram must be ignored
            let mut old = pose_at(10);
            old.position = [9.0, 9.0, 9.0];
            driver.send(&old.encode()).unwrap();
            // and garbage is counted, not fatal
            driver.send(b"hello").unwrap();
        }
        while let Some(f) = recv_force(&driver) {
            received += 1;
            assert!(f.echo_seq <= seq);
            let n = Vector3::from(f.force).norm();
            assert!(n <= 1.0 + 1e-12);
            if f.flags & FLAG_STALE == 0 && (n - 1.0).abs() < 1e-9 && f.echo_seq > 0 {
                assert_eq!(
                    f.echo_device_time_us,
                    pose_at(f.echo_seq).device_time_us,
                    "echo matches the pose"
                );
                full = Some(f);
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let full = full.expect("the driver felt the model force");
    assert_eq!(full.force, [0.0, 0.0, 1.0]);
    assert!(received > 10);
    // pose in → ToolInput out
    let input = h.latest_input().unwrap();
    assert!(
        (input.position - Vector3::from(pose_at(seq).position)).norm() < 1e-5,
        "{input:?}"
    );
    let expect_q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
    assert!(input.orientation.angle_to(&expect_q) < 1e-12);
    assert_eq!((input.jaw, input.buttons), (0.25, 0b10));

    // The driver goes silent: after 50 ms the force fades to zero, flagged stale.
    driver.set_nonblocking(false).unwrap();
    driver
        .set_read_timeout(Some(Duration::from_millis(10)))
        .unwrap();
    let silent = Instant::now();
    let mut faded = None;
    while silent.elapsed() < Duration::from_secs(5) && faded.is_none() {
        if let Some(f) = recv_force(&driver)
            && f.flags & FLAG_STALE != 0
            && f.force == [0.0; 3]
        {
            faded = Some(silent.elapsed());
        }
    }
    let faded = faded.expect("force faded to zero");
    eprintln!(
        "fresh phase {:?}, {seq} poses, {received} forces; faded after {faded:?}",
        t0.elapsed() - silent.elapsed()
    );
    assert!(
        faded >= Duration::from_millis(50),
        "not before the stale timeout: {faded:?}"
    );

    let (bridge, stats) = h.stop();
    let b = bridge.stats();
    assert!(b.received >= 50 && b.received <= u64::from(seq), "{b:?}");
    assert!(b.out_of_order >= 1, "{b:?}");
    assert!(b.malformed >= 1, "{b:?}");
    assert!(b.stale_events >= 1 && b.stale_reads > 0, "{b:?}");
    assert!(b.sent > 0 && b.send_errors == 0, "{b:?}");
    assert!(stats.stale_input_ticks > 0, "{stats:?}");
    assert!(stats.max_force <= 1.0 + 1e-12);
    assert!(bridge.last_device_time_us() >= pose_at(50).device_time_us);
}

#[test]
fn teaching_record_file_playback() {
    // Instructor: moves 4 cm along x in 0.2 s, closes the jaws, then holds.
    let source = script(
        "forceps",
        &[
            (0.0, [0.00, -0.1, 0.02], 0.6),
            (0.2, [0.04, -0.1, 0.02], 0.6),
            (0.25, [0.04, -0.1, 0.02], 0.0),
        ],
    );
    let dev = ScriptedDevice::new(source.clone(), "forceps")
        .unwrap()
        .with_record_limit(0);
    let h = spawn(dev, HapticConfig::default()).unwrap();
    h.start_recording(
        TeachingRecorder::new("forceps", Duration::from_millis(5))
            .unwrap()
            .with_title("test demonstration"),
    );
    std::thread::sleep(Duration::from_millis(350));
    let rec = h.stop_recording().expect("a recording");
    drop(h);
    assert!(rec.len() >= 10, "{}", rec.len());
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demo.toml");
    rec.save(&file).unwrap();

    // The file is a valid tool script on the source trajectory.
    let loaded = ToolScript::load(&file).unwrap();
    assert_eq!(loaded.title.as_deref(), Some("test demonstration"));
    let t0 = rec.start_time().unwrap().as_secs_f64();
    let keys = &loaded.tracks["forceps"];
    assert_eq!(keys.len(), rec.to_script().unwrap().tracks["forceps"].len());
    for k in keys {
        let src = source.sample("forceps", t0 + k.t).unwrap();
        assert!(
            (k.pose.position - src.position).norm() < 3e-5,
            "{k:?} vs {src:?}"
        );
        assert!((k.pose.jaw - src.jaw).abs() < 2e-3, "{k:?}");
        assert!(k.pose.orientation.angle_to(&src.orientation) < 1e-5);
    }
    let end = keys.last().unwrap().pose.position;

    // Trainee: holds the tool 4 mm off the end of the path. After playback ends the
    // guide holds the last recorded tip: F = k (x_r − x) exactly (both velocities 0).
    let spring = GuideSpring {
        stiffness: 250.0,
        damping: 2.0,
        max_force: 1.5,
        ramp: 0.05,
    };
    let playback = TeachingPlayback::load(&file, None, spring).unwrap();
    let duration = playback.duration();
    assert!((duration - keys.last().unwrap().t).abs() < 1e-12);
    let offset = Vector3::new(0.0, 0.003, -0.002);
    let trainee = ScriptedDevice::at(end + offset);
    let h = spawn(trainee, HapticConfig::default()).unwrap();
    h.set_guide(Some(playback.clone()));
    std::thread::sleep(Duration::from_secs_f64(duration + 0.3));
    h.set_guide(None);
    std::thread::sleep(Duration::from_millis(20));
    let (dev, stats) = h.stop();
    let rec = body(dev.forces());
    let expect = -offset * spring.stiffness; // (0, −0.75, 0.5) N, below the limits
    let settled = rec
        .iter()
        .filter(|r| (r.force - expect).norm() < 1e-9)
        .count();
    assert!(
        settled >= 100,
        "{settled} ticks at the spring force {expect}"
    );
    // Every guide force has a positive component toward the recorded tip at the end of
    // the path once playback holds, and never exceeds the guide's maximum.
    assert!(
        rec.iter()
            .all(|r| r.force.norm() <= spring.max_force + 1e-9)
    );
    assert!(stats.max_force <= spring.max_force + 1e-9);
    // After the guide was removed the force went back to zero (rate limited).
    assert_eq!(rec.last().unwrap().force, Vector3::zeros());

    // Direct check of the law while the recorded tip moves: pointing toward the target.
    let x = Vector3::new(0.02, -0.1, 0.02);
    let t = 0.1;
    let xr = playback.target(t).position;
    let vr = playback.target_velocity(t);
    let f = playback.guide_force(t, &x, &Vector3::zeros());
    let law = (xr - x) * spring.stiffness + vr * spring.damping;
    let law = if law.norm() > spring.max_force {
        law * (spring.max_force / law.norm())
    } else {
        law
    };
    assert!((f - law).norm() < 1e-9, "{f} vs {law}");
}

#[test]
fn measure_loop_reports_counts() {
    let stats = measure_loop(Duration::from_millis(100));
    assert!(stats.ticks > 0);
    assert!(stats.max_force > 0.0, "the wall model pushes: {stats:?}");
    assert!(stats.max_force <= RenderConfig::default().max_force);
    let dev = ScriptedDevice::at(Vector3::zeros()).with_record_limit(10);
    let (dev, stats) = measure_loop_with(
        dev,
        HapticConfig::default(),
        Duration::from_millis(50),
        None,
    )
    .unwrap();
    assert_eq!(dev.forces().len(), 10);
    assert_eq!(dev.dropped_records(), stats.ticks + 1 - 10);
}

/// The measurement reported in docs/haptics.md: `cargo test -p cosurg --release --test
/// haptic -- --ignored --nocapture`. A busy thread stands in for the simulation thread;
/// "fifo" gives the haptic thread SCHED_FIFO 80 through `chrt` (needs the permission).
#[test]
#[ignore]
fn measure_rate_and_jitter_under_load() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    fn fifo() {
        let tid = std::fs::read_link("/proc/thread-self")
            .ok()
            .and_then(|p| p.file_name().map(|s| s.to_string_lossy().into_owned()));
        if let Some(tid) = tid {
            let ok = std::process::Command::new("chrt")
                .args(["-f", "-p", "80", &tid])
                .status()
                .is_ok_and(|s| s.success());
            if !ok {
                println!("  (chrt failed: normal priority)");
            }
        }
    }
    let secs: f64 = std::env::var("HAPTIC_MEASURE_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2.0);
    for load in [0usize, 1] {
        let stop = Arc::new(AtomicBool::new(false));
        let busy: Vec<_> = (0..load)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut x = 1.0f64;
                    while !stop.load(Ordering::Relaxed) {
                        for _ in 0..10_000 {
                            x = (x * 1.000_001).sqrt() + 1e-9;
                        }
                    }
                    x
                })
            })
            .collect();
        for (prio, setup) in [("normal", None), ("fifo", Some(fifo as fn()))] {
            for spin_us in [0u64, 50, 100] {
                let cfg = HapticConfig {
                    spin: Duration::from_micros(spin_us),
                    thread_setup: setup,
                    ..HapticConfig::default()
                };
                let dev = ScriptedDevice::at(Vector3::new(0.0, 0.0, -0.002)).with_record_limit(0);
                let (_, s) =
                    measure_loop_with(dev, cfg, Duration::from_secs_f64(secs), None).unwrap();
                println!(
                    "busy threads {load}, {prio:>6}, spin {spin_us:>3} µs: {}",
                    s.summary()
                );
            }
        }
        let s = measure_loop(Duration::from_secs_f64(secs));
        println!(
            "busy threads {load}, measure_loop (defaults): {}",
            s.summary()
        );
        stop.store(true, Ordering::Relaxed);
        for b in busy {
            b.join().unwrap();
        }
    }
}
