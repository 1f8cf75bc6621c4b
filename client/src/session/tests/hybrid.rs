//! `SiteSession` under hybrid sync: input datagrams, and followers that show keyframes.

use super::*;

fn pose(site: SiteId, t: f64) -> proto::ToolPose {
    proto::ToolPose {
        site,
        tool: 0,
        sim_time_s: t,
        position: [t as f32, 0.0, 0.0],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.1,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    }
}

/// Hybrid: the local tool's samples go out every `POSE_HISTORY_INTERVAL` as one datagram
/// repeating the last `POSE_HISTORY_SAMPLES`; with every other datagram lost, the receiver
/// still gets every sample (one loss costs nothing).
#[test]
fn hybrid_input_datagrams_repeat_samples_so_a_loss_costs_nothing() {
    let clock = FakeClock::new();
    let sim_a = new_sim();
    let mut sim_b = new_sim();
    let mut a = session_with(Role::Instructor, &sim_a, &clock, SyncStrategy::Hybrid);
    let mut b = session_with(Role::Trainee, &sim_b, &clock, SyncStrategy::Hybrid);
    let sites = [(1, Role::Instructor), (2, Role::Trainee)];
    a.handle_welcome(&welcome(1, &sites), clock.now());
    b.handle_welcome(&welcome(2, &sites), clock.now());
    let dt = 0.004;
    let steps = 100;
    let mut datagrams = Vec::new();
    for k in 0..steps {
        let t = k as f64 * dt;
        assert!(a.pose_due(t), "a pose every step under hybrid");
        a.send_pose(pose(1, t));
        for tr in drain(&mut a) {
            match tr {
                Transmit::Datagram(Message::ToolPoseHistory(h)) => datagrams.push(h),
                Transmit::Datagram(Message::ToolPose(_)) => panic!("single poses under hybrid"),
                _ => {}
            }
        }
    }
    let per_datagram = POSE_HISTORY_INTERVAL / dt;
    assert!(
        (datagrams.len() as f64 - steps as f64 / per_datagram).abs() <= 1.0,
        "{} datagrams for {steps} steps",
        datagrams.len()
    );
    assert!(
        datagrams
            .iter()
            .all(|h| h.samples.len() <= POSE_HISTORY_SAMPLES)
    );
    for (i, h) in datagrams.iter().enumerate() {
        if i % 2 == 1 {
            continue; // lost
        }
        b.handle_message(&mut sim_b, Message::ToolPoseHistory(h.clone()), clock.now())
            .unwrap();
    }
    let mut heard: Vec<f64> = std::iter::from_fn(|| b.poll_event())
        .filter_map(|e| match e {
            SessionEvent::RemotePose(p) => Some(p.sim_time_s),
            _ => None,
        })
        .collect();
    heard.sort_by(f64::total_cmp);
    heard.dedup();
    // Every sample up to the last datagram delivered arrived.
    let last_delivered = (datagrams.len() - 1) / 2 * 2;
    let last = datagrams[last_delivered].samples.last().unwrap().sim_time_s;
    let want: Vec<f64> = (0..steps)
        .map(|k| k as f64 * dt)
        .filter(|t| *t <= last)
        .collect();
    assert_eq!(heard, want);
}

/// A hybrid follower that shows keyframes (`--follow keyframes`) says so in its
/// acknowledgements; its owner then also sends on dead-reckoning drift. With a follower
/// that simulates, the owner keeps to its heartbeat.
#[test]
fn a_follower_that_shows_keyframes_makes_its_owner_send_on_drift() {
    for shows in [false, true] {
        let mut p = pair_with(SyncStrategy::Hybrid);
        let r = p.region;
        assert_eq!(p.a.sync.policy.config().drift_threshold_m, f64::INFINITY);
        p.b.cfg.shows_keyframes = shows;
        p.b.sync = p.b.cfg.new_sync(p.b.map.clone());
        for _ in 0..3 {
            p.step(&[r]);
        }
        assert_eq!(p.b.stats().keyframes_applied, 1, "shows keyframes: {shows}");
        assert_eq!(p.b.sync.remote(r).is_some(), shows);
        assert_eq!(p.b.sync.corrected(r).is_some(), !shows);
        let threshold = p.a.sync.policy.config().drift_threshold_m;
        if shows {
            assert_eq!(threshold, sync_config().drift_threshold_m);
        } else {
            assert_eq!(threshold, f64::INFINITY);
        }
    }
}
