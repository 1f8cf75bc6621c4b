//! The haptic loop inside a site (`run_site`): a real device over UDP drives the local
//! tool and feels the contact forces; teaching mode through a coordinator on loopback
//! (the instructor's act is recorded, sent, and guides a trainee's device).
//!
//! Loopback only, bounded (a few simulated seconds each); no timing assertions.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use cosurg::haptic::UdpBridgeDevice;
use cosurg::haptic::site::DeviceSpec;
use cosurg::haptic::udp::{ForceDatagram, PoseDatagram};
use cosurg::link::LinkConfig;
use cosurg::site::{PlayoutLag, SiteConfig, SiteReport, run_site};
use proto::Role;
use sim_core::SimOptions;
use sim_core::sim_scene::{LoadedScene, ToolPose, ToolScript, ToolWaypoint, builtin};
use sim_core::sync::SyncStrategy;

fn site(scene: &LoadedScene, name: &str, role: Role, tool: &str, seconds: f64) -> SiteConfig {
    let mut options = SimOptions::from_scene(&scene.scene);
    options.dt = 0.004;
    SiteConfig {
        name: name.into(),
        role,
        scene: scene.clone(),
        cell_m: None,
        time_scale: server::TimeScale::REAL,
        options,
        tools: vec![tool.into()],
        script: None,
        script_start: 0.0,
        seconds,
        strategy: SyncStrategy::Keyframe,
        slowdown: 1.0,
        out: None,
        vtu_interval: None,
        record: true,
        link: None,
        expect_sites: 1,
        realtime: true,
        playout_lag: PlayoutLag::Auto,
        shows_keyframes: false,
        haptics: true,
        device: DeviceSpec::Script,
        rt_priority: None,
        on_progress: None,
        reset_at: Vec::new(),
        status: None,
        view: None,
        hands: false,
    }
}

/// What the fake driver saw.
#[derive(Default, Debug)]
struct DriverLog {
    sent: u32,
    forces: Vec<ForceDatagram>,
}

/// A device driver: holds the probe pressed 5 mm into the gallbladder neck (the probe
/// script's pose at 1.5 s), sending a pose about every millisecond, and collects force
/// datagrams.
fn driver(to: SocketAddr, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<DriverLog> {
    let script = builtin::cholecystectomy().scripts["probe"].clone();
    std::thread::spawn(move || {
        let s = UdpSocket::bind("127.0.0.1:0").unwrap();
        s.set_read_timeout(Some(Duration::from_millis(1))).unwrap();
        let mut log = DriverLog::default();
        let start = Instant::now();
        let mut buf = [0u8; 256];
        while !stop.load(Ordering::Relaxed) && start.elapsed() < Duration::from_secs(30) {
            let p = script.sample("probe", 1.5).unwrap();
            log.sent += 1;
            let q = p.orientation.quaternion();
            let d = PoseDatagram {
                seq: log.sent,
                device_time_us: start.elapsed().as_micros() as u64,
                position: p.position.into(),
                orientation: [q.w, q.i, q.j, q.k],
                jaw: 0.0,
                buttons: 0,
            };
            s.send_to(&d.encode(), to).unwrap();
            // Drain forces (the read timeout paces the loop at about 1 kHz).
            while let Ok(n) = s.recv(&mut buf) {
                if let Some(f) = ForceDatagram::decode(&buf[..n]) {
                    log.forces.push(f);
                }
                s.set_nonblocking(true).unwrap();
            }
            s.set_nonblocking(false).unwrap();
        }
        log
    })
}

#[test]
fn udp_device_drives_the_local_tool_and_feels_the_contact() {
    let scene = builtin::cholecystectomy();
    let bridge = UdpBridgeDevice::bind("127.0.0.1:0").unwrap();
    let addr = bridge.local_addr();
    let mut cfg = site(&scene, "device", Role::Trainee, "probe", 1.0);
    // The probe's script would only reach the tissue after the run: any contact comes
    // from the device.
    cfg.script = scene.scripts.get("probe").cloned();
    cfg.script_start = 10.0;
    cfg.device = DeviceSpec::Udp(Box::new(bridge));
    let stop = Arc::new(AtomicBool::new(false));
    let drv = driver(addr, stop.clone());
    let report = run_site(cfg).unwrap();
    stop.store(true, Ordering::Relaxed);
    let log = drv.join().unwrap();
    eprintln!("{report:?}");

    assert_eq!(
        report.haptic_device.as_deref(),
        Some(&*format!("udp:{addr}"))
    );
    let received = report.device_poses_received.unwrap();
    assert!(
        received > 10 && received <= u64::from(log.sent),
        "{received}"
    );
    assert!(report.device_forces_sent.unwrap() > 10);
    assert!(log.forces.len() > 10, "{} forces", log.forces.len());
    // Forces answer our poses (echo) and are finite and within the device limit.
    let last = log.forces.last().unwrap();
    assert!(last.echo_seq > 0 && last.echo_seq <= log.sent);
    for f in &log.forces {
        let n = (f.force[0].powi(2) + f.force[1].powi(2) + f.force[2].powi(2)).sqrt();
        assert!(n.is_finite() && n <= 3.0 + 1e-9, "{f:?}");
    }
    // The tool followed the device into the tissue: the simulation felt contact and the
    // device felt it back.
    let max = log
        .forces
        .iter()
        .map(|f| (f.force[0].powi(2) + f.force[1].powi(2) + f.force[2].powi(2)).sqrt())
        .fold(0.0, f64::max);
    assert!(
        report.max_tool_force_n > 0.01,
        "{}",
        report.max_tool_force_n
    );
    assert!(max > 0.01, "device felt at most {max} N");
}

/// The forceps script's approach (free space, no contact), `len` s long, shifted by
/// `offset` m.
fn approach(len: f64, offset: [f64; 3]) -> ToolScript {
    let src = &builtin::cholecystectomy().scripts["forceps"];
    let mut s = ToolScript::default();
    let keys = (0..=4)
        .map(|i| {
            let t = len * i as f64 / 4.0;
            let p = src.sample("forceps", t).unwrap();
            ToolWaypoint {
                t,
                pose: ToolPose {
                    position: p.position + nalgebra::Vector3::from(offset),
                    ..p
                },
                label: None,
            }
        })
        .collect();
    s.tracks.insert("forceps".into(), keys);
    s
}

#[test]
fn instructor_act_guides_a_trainee_through_the_session() {
    let scene = builtin::cholecystectomy();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let mut session = proto::SessionConfig::new("teach", "tok".to_string());
    session.scene_hash = Some(scene.hash.clone());
    let key = proto::InviteKey::from_bytes([4; 32]);
    session.invite_key = Some(key.clone());
    let mut config = server::CoordinatorConfig::ephemeral(session).unwrap();
    config.status_interval = None;
    let (handle, addr) = runtime
        .block_on(async { server::Coordinator::bind(config) })
        .unwrap();
    let fingerprint = handle.fingerprint().to_string();
    let out = tempfile::tempdir().unwrap();

    let link = |role, name: &str| {
        let credential = match role {
            Role::Instructor => proto::Credential::Token("tok".into()),
            role => proto::Credential::Invitation(
                server::state::mint(
                    &key,
                    "teach",
                    role,
                    Some(name),
                    3600,
                    server::state::unix_now_s(),
                )
                .unwrap()
                .invitation,
            ),
        };
        Some(LinkConfig::new(
            addr,
            &fingerprint,
            "teach",
            credential,
            role,
            name,
            &scene.hash,
        ))
    };
    // Instructor: a 0.8 s act from 0.05 s. Trainee: the same motion 5 mm off along +x,
    // from 1.2 s (after the instructor's act has been sent).
    let mut instructor = site(&scene, "prof", Role::Instructor, "forceps", 1.0);
    instructor.script = Some(approach(0.8, [0.0; 3]));
    instructor.script_start = 0.05;
    instructor.link = link(Role::Instructor, "prof");
    instructor.expect_sites = 2;
    instructor.out = Some(out.path().join("prof"));
    let mut trainee = site(&scene, "student", Role::Trainee, "forceps", 2.3);
    trainee.script = Some(approach(0.8, [0.005, 0.0, 0.0]));
    trainee.script_start = 1.2;
    trainee.link = link(Role::Trainee, "student");
    trainee.expect_sites = 2;

    let t = std::thread::spawn(move || run_site(trainee));
    let prof: SiteReport = run_site(instructor).unwrap();
    let student: SiteReport = t.join().unwrap().unwrap();
    runtime.block_on(handle.shutdown());
    eprintln!("{prof:?}\n{student:?}");

    // The instructor sent its act and saved it as a tool script.
    assert_eq!(prof.teaching_sent, Some(1));
    let file = prof.teaching_file.clone().unwrap();
    let rec = ToolScript::load(&file).unwrap();
    let keys = &rec.tracks["forceps"];
    assert!(
        (keys.last().unwrap().t - 0.8).abs() < 0.02,
        "{}",
        keys.last().unwrap().t
    );
    let src = approach(0.8, [0.0; 3]);
    for k in keys {
        let d = (k.pose.position - src.sample("forceps", k.t).unwrap().position).norm();
        assert!(
            d < 1e-3,
            "recorded pose {d} m off the instructor's script at {}",
            k.t
        );
    }
    // The trainee was guided along it: 5 mm away all along, so the spring pulled with
    // about 150 N/m · 5 mm = 0.75 N once faded in.
    let dist = student.playback_distance_mm.unwrap();
    assert!((dist - 5.0).abs() < 1.0, "mean distance {dist} mm");
    let fmax = student.guide_force_max_n.unwrap();
    assert!(fmax > 0.5 && fmax < 1.0, "guide force max {fmax} N");
    assert!(student.guide_force_mean_n.unwrap() <= fmax);
    assert!(prof.guide_force_max_n.is_none() && prof.playback_distance_mm.is_none());
}
