use super::*;
use debrief::{Recording, Tail};
use proto::{Leave, OwnershipGrant, OwnershipRelease, Role, SiteEntry, ToolPose};

fn pose(site: SiteId, tool: u8, t: f64, x: f32) -> Message {
    Message::ToolPose(ToolPose {
        site,
        tool,
        sim_time_s: t,
        position: [x, 0.0, 0.1],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.3,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    })
}

fn joined(site: SiteId, name: &str, role: Role) -> Message {
    Message::SiteJoined(SiteEntry {
        site,
        name: name.into(),
        role,
    })
}

#[test]
fn records_joins_poses_claims_and_leaves_and_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let mut rec = CoordinatorRecording::create(dir.path(), "lap chole/1", None).unwrap();
    assert_eq!(
        rec.path(),
        dir.path().join("lap_chole_1.cosrec"),
        "session name sanitised into the file name"
    );
    rec.on_control(&joined(1, "instructor", Role::Instructor));
    rec.on_control(&joined(2, "A", Role::Trainee));
    for k in 0..100 {
        let t = k as f64 * 0.016;
        rec.on_datagram(&pose(1, 0, t, 0.001 * k as f32));
        rec.on_datagram(&pose(2, 1, t + 0.003, -0.001 * k as f32));
    }
    // A reordered datagram (older than the newest recorded pose) is skipped.
    rec.on_datagram(&pose(2, 1, 0.5, 9.0));
    rec.on_control(&Message::OwnershipGrant(OwnershipGrant {
        region: 7,
        site: 2,
        previous: None,
    }));
    rec.on_control(&Message::OwnershipRelease(OwnershipRelease {
        region: 7,
        site: 2,
    }));
    rec.on_control(&Message::Command(Command::ResetScene {
        epoch: 1,
        sim_time_s: 1.6,
    }));
    rec.on_control(&Message::Leave(Leave {
        site: 2,
        reason: "connection lost".into(),
    }));
    assert_eq!(rec.counts().poses, 200);
    rec.finish();

    let r = Recording::open(rec.path()).unwrap();
    assert_eq!(r.tail, Tail::Complete);
    assert_eq!(r.header.site, COORDINATOR_SITE);
    assert_eq!(r.header.role, COORDINATOR_SITE);
    assert_eq!(r.header.session, "lap chole/1");
    let tools = r.tools();
    assert_eq!(tools.len(), 2);
    assert_eq!(
        (tools[0].site.as_str(), tools[0].name.as_str()),
        ("instructor", "#0")
    );
    assert_eq!(
        (tools[1].site.as_str(), tools[1].name.as_str()),
        ("A", "#1")
    );
    let a = &r.site_tracks("A")[0];
    assert_eq!(a.len(), 100);
    assert!(
        a.times.windows(2).all(|w| w[1] > w[0]),
        "track in time order"
    );
    let last = a.states.last().unwrap().position;
    assert!((last[0] + 0.099).abs() < 2e-6, "{last:?}");
    assert!((a.states[0].jaw - 0.3).abs() < 1e-6);
    let kinds: Vec<(String, String)> = r
        .events()
        .map(|e| (e.site.clone(), e.kind.label()))
        .collect();
    let want = [
        ("instructor", "join"),
        ("A", "join"),
        ("A", "claim"),
        ("A", "release"),
        ("instructor", "reset"),
        ("A", "leave"),
    ];
    assert_eq!(
        kinds,
        want.map(|(s, k)| (s.to_string(), k.to_string())).to_vec()
    );
    let leave = r.events().last().unwrap();
    assert_eq!(leave.detail, "connection lost");
    assert!(
        (leave.time - 99.0 * 0.016 - 0.003).abs() < 1e-9,
        "event at the newest sim time"
    );
}

#[test]
fn a_teaching_trajectory_resent_to_late_joiners_is_recorded_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut rec = CoordinatorRecording::create(dir.path(), "s", Some("abcd")).unwrap();
    rec.on_control(&joined(1, "teacher", Role::Instructor));
    let t = Message::Teaching(proto::TeachingTrajectory {
        id: 3,
        tool: 0,
        samples: Vec::new(),
    });
    rec.on_control(&t);
    rec.on_control(&t);
    rec.finish();
    let r = Recording::open(rec.path()).unwrap();
    assert_eq!(r.header.scene, "sha256 abcd");
    let teaching: Vec<_> = r
        .events()
        .filter(|e| e.kind == EventKind::TeachingStart)
        .collect();
    assert_eq!(teaching.len(), 1);
    assert_eq!(teaching[0].site, "teacher");
}
