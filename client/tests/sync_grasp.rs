//! A receiver driven by the owner's keyframes follows a grasp-and-lift of the default
//! scene: two `SiteSession`s in process, no network (the test hands the owner's frames to
//! the receiver and the acknowledgements back, and plays the coordinator's grants).

use std::time::{Duration, Instant};

use cosurg::session::{Now, PlayoutLag, SessionConfig, SiteSession, Transmit};
use cosurg::site::tools::Tools;
use proto::{Message, Role, SessionInfo, SiteEntry, Welcome};
use sim_core::sim_scene::builtin;
use sim_core::sync::SyncStrategy;
use sim_core::{SimOptions, Simulation};

#[test]
fn receiver_follows_grasp_and_lift() {
    follow(1);
}

#[test]
fn lagging_receiver_follows_grasp_and_lift() {
    follow(3);
}

fn welcome(site: u16) -> Welcome {
    Welcome {
        site,
        session: SessionInfo {
            name: "grasp".into(),
            scene_hash: String::new(),
            max_sites: 2,
            protocol_version: proto::PROTOCOL_VERSION,
            heartbeat_interval_us: 500_000,
        },
        sites: [(1, Role::Instructor), (2, Role::Trainee)]
            .into_iter()
            .map(|(site, role)| SiteEntry {
                site,
                name: format!("site-{site}"),
                role,
            })
            .collect(),
        coordinator_time_us: 0,
    }
}

/// The receiver steps once for every `lag`-th owner step until it falls 1.2 s behind,
/// then keeps pace: keyframes from its future wait for its clock.
fn follow(lag: usize) {
    let scene = builtin::cholecystectomy();
    let mut options = SimOptions::from_scene(&scene.scene);
    options.dt = 0.004;
    let mut owner = Simulation::new(scene.clone(), options.clone()).unwrap();
    let mut recv = Simulation::new(scene.clone(), options.clone()).unwrap();
    let mut tools = Tools::new(&owner, &["forceps".into()], SyncStrategy::Keyframe).unwrap();
    let config = |role| SessionConfig {
        role,
        strategy: SyncStrategy::Keyframe,
        scene: scene.clone(),
        options: options.clone(),
        linked: true,
        playout_lag: PlayoutLag::Fixed(0.0),
        realtime: false,
        shows_keyframes: false,
    };
    let origin = Instant::now();
    let now = |k: usize| Now {
        wall: origin + Duration::from_millis(4 * k as u64),
        coordinator_us: 4_000 * k as u64,
        synced: true,
    };
    let mut s_owner = SiteSession::new(config(Role::Instructor), &owner, origin);
    let mut s_recv = SiteSession::new(config(Role::Trainee), &recv, origin);
    s_owner.handle_welcome(&welcome(1), now(0));
    s_recv.handle_welcome(&welcome(2), now(0));
    s_owner.start(origin, None);
    s_recv.start(origin, None);
    let script = scene.scripts.get("forceps").unwrap().clone();
    let mut worst: f64 = 0.0;
    let mut owner_frames: Vec<(f64, Vec<nalgebra::Vector3<f64>>)> = Vec::new();
    for k in 0..(7.0 / 0.004) as usize {
        let t = owner.time();
        let input = tools.local_input(Some(&script), t);
        s_owner.apply_due(&mut owner).unwrap();
        let touched = tools.before_step(&mut owner, input, &s_owner).unwrap();
        s_owner.handle_touched(&owner, &touched, now(k));
        s_owner.before_step(&mut owner);
        owner.step().unwrap();
        s_owner.after_step(&owner, now(k));
        // The coordinator grants every request at once; frames go to the receiver.
        while let Some(out) = s_owner.poll_transmit() {
            let m = match out {
                Transmit::Control(Message::OwnershipRequest(q)) => {
                    let g = Message::OwnershipGrant(proto::OwnershipGrant {
                        region: q.region,
                        site: 1,
                        previous: None,
                    });
                    s_owner
                        .handle_message(&mut owner, g.clone(), now(k))
                        .unwrap();
                    g
                }
                Transmit::Keyframe(kf) => Message::Keyframe(kf),
                Transmit::Datagram(m @ Message::TreeDelta(_)) => m,
                Transmit::Control(m @ Message::OwnershipRelease(_)) => m,
                _ => continue,
            };
            s_recv.handle_message(&mut recv, m, now(k)).unwrap();
        }
        ack(&mut s_recv, &mut s_owner, &mut owner, now(k));
        owner_frames.push((owner.time(), owner.surfaces()[0].deformed.clone()));
        if lag > 1 && k % lag != 0 && owner.time() - recv.time() < 1.2 {
            continue;
        }
        s_recv.apply_due(&mut recv).unwrap();
        ack(&mut s_recv, &mut s_owner, &mut owner, now(k));
        s_recv.before_step(&mut recv);
        recv.step().unwrap();
        // Compare with the owner at the same simulated time.
        let Some((_, a)) = owner_frames
            .iter()
            .find(|(t, _)| (t - recv.time()).abs() < 1e-9)
        else {
            continue;
        };
        let b = &recv.surfaces()[0].deformed;
        let d = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
        worst = worst.max(d);
    }
    assert!(s_recv.stats().keyframes_applied > 10);
    // Bounds: the release of the grasp (tissue springing back while the owner still owns
    // the region for 0.4 s) is the largest transient at 4 ms steps: 12.5 mm for a receiver
    // level with the owner (it extrapolates), 9.3 mm for one behind it (it holds the next
    // keyframe and interpolates towards it, but the snap is faster than the owner's 30 ms
    // keyframe rate cap), measured 2026-11-27. While keyframe sync decided refinement in
    // rest space the receiver behind measured 12.1 mm. Since contact fades on collapsing
    // leaves and stops on inverted ones (2026-11-29; in the scene's scripted 2,500 steps
    // a sample is nearest an inverted leaf's triangle 14 times, `contact_cost`), 12.2 and
    // 10.2 mm (12.5 and 9.3 before, the same day). At the end the tissue has settled on
    // both.
    let bound = if lag > 1 { 0.011 } else { 0.015 };
    assert!(worst < bound, "receiver diverged by {worst} m");
    let a = &owner.surfaces()[0].deformed;
    let b = &recv.surfaces()[0].deformed;
    if (owner.time() - recv.time()).abs() < 1e-9 {
        let end = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
        assert!(end < 0.001, "settled divergence {end} m");
    }
}

/// The receiver's acknowledgements go back to the owner.
fn ack(recv: &mut SiteSession, owner: &mut SiteSession, owner_sim: &mut Simulation, now: Now) {
    while let Some(t) = recv.poll_transmit() {
        if let Transmit::Control(m @ Message::KeyframeAck(_)) = t {
            owner.handle_message(owner_sim, m, now).unwrap();
        }
    }
}
