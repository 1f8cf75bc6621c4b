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
/// repeating the last `inputs::RECENT_S` of samples and older ones on a coarse grid; with every
/// other datagram lost, the receiver still gets every sample (one loss costs nothing), and
/// after a long burst of losses a coarse path through the gap.
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
    // The session's own step (the test scene's), 0.4 s of it.
    let dt = sim_a.options().dt;
    let steps = (0.4 / dt).round() as usize;
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
    assert!(datagrams.iter().all(|h| {
        h.samples.len() <= proto::MAX_POSE_SAMPLES
            && h.samples.is_sorted_by(|a, b| a.sim_time_s < b.sim_time_s)
    }));
    let heard = |b: &mut SiteSession| {
        let mut heard: Vec<f64> = std::iter::from_fn(|| b.poll_event())
            .filter_map(|e| match e {
                SessionEvent::RemotePose(p) => Some(p.sim_time_s),
                _ => None,
            })
            .collect();
        heard.sort_by(f64::total_cmp);
        heard.dedup();
        heard
    };
    for (i, h) in datagrams.iter().enumerate() {
        if i % 2 == 1 {
            continue; // lost
        }
        b.handle_message(&mut sim_b, Message::ToolPoseHistory(h.clone()), clock.now())
            .unwrap();
    }
    // Every sample up to the last datagram delivered arrived.
    let last_delivered = (datagrams.len() - 1) / 2 * 2;
    let last = datagrams[last_delivered].samples.last().unwrap().sim_time_s;
    let want: Vec<f64> = (0..steps)
        .map(|k| k as f64 * dt)
        .filter(|t| *t <= last)
        .collect();
    assert_eq!(heard(&mut b), want);

    // A burst loses 12 datagrams in a row (96 ms of samples): the next one still brings
    // samples at most `COARSE_SPACING_S` apart across the gap, back to `COARSE_SPAN_S`.
    let mut c = session_with(Role::Trainee, &sim_b, &clock, SyncStrategy::Hybrid);
    c.handle_welcome(&welcome(2, &sites), clock.now());
    let (before, after) = (20, 33);
    for h in [&datagrams[before], &datagrams[after]] {
        c.handle_message(&mut sim_b, Message::ToolPoseHistory(h.clone()), clock.now())
            .unwrap();
    }
    let heard = heard(&mut c);
    // A datagram's samples are handed over newest first (only the newest measures how
    // late it came; `Tools::remote_pose`).
    c.handle_message(
        &mut sim_b,
        Message::ToolPoseHistory(datagrams[40].clone()),
        clock.now(),
    )
    .unwrap();
    let order: Vec<f64> = std::iter::from_fn(|| c.poll_event())
        .filter_map(|e| match e {
            SessionEvent::RemotePose(p) => Some(p.sim_time_s),
            _ => None,
        })
        .collect();
    assert!(order.len() as f64 > inputs::RECENT_S / dt, "{order:?}");
    assert!(order.is_sorted_by(|a, b| a > b), "{order:?}");
    let gap_start = datagrams[before].samples.last().unwrap().sim_time_s;
    let gap_end = datagrams[after].samples.last().unwrap().sim_time_s;
    assert!(gap_end - gap_start > inputs::COARSE_SPAN_S - 0.03);
    let widest = heard
        .windows(2)
        .filter(|w| w[0] >= gap_start - 1e-9)
        .map(|w| w[1] - w[0])
        .fold(0.0, f64::max);
    assert!(
        widest <= inputs::COARSE_SPACING_S + 1e-9,
        "a gap of {widest} s between samples heard: {heard:?}"
    );
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

/// A refinement op of site 1 around the first root of the pair's region (its rest
/// centroid), to the lattice's deepest level.
fn refine_first_root(p: &Pair) -> sim_core::adapt::RefineOp {
    let root = p.a.map.roots(p.region)[0];
    let lat = p.sim_a.lattice();
    let nodes = lat.tet_nodes(sim_core::TetId { root, heap: 1 });
    let c = nodes
        .iter()
        .map(|&n| lat.node_rest(n))
        .sum::<nalgebra::Vector3<f64>>()
        / 4.0;
    sim_core::adapt::RefineOp {
        id: sim_core::cut::OpId {
            site: 1,
            seq: sim_core::adapt::REFINE_SEQ_BASE,
        },
        focus: vec![[c.x, c.y, c.z]],
        distance: 0.25 * lat.params().cell,
        level: lat.params().max_depth,
        merge: Vec::new(),
    }
}

/// Under hybrid sync a refinement decision is scheduled ahead like a cut: both sites hold
/// it and apply it at its time, and their lattices end equal (the refinement is not in the
/// cut log); a keyframe made before it, whose tree would take it back, is dropped.
#[test]
fn a_refinement_is_applied_at_its_time_everywhere_and_not_undone_by_an_older_keyframe() {
    let mut p = pair_with(SyncStrategy::Hybrid);
    for _ in 0..3 {
        p.step(&[]);
    }
    // A keyframe of the owned region as it is now, before the refinement.
    let before = p.a_keyframe_after_grant(0);
    let op = refine_first_root(&p);
    drain(&mut p.a);
    let t = p.sim_a.time();
    let rtt = Duration::from_millis(40);
    p.a.share_topology(&[sim_core::cut::TopologyOp::Refine(op)], t, Some(rtt));
    let at = t + super::super::topology_lead(Some(rtt));
    let wire = drain(&mut p.a)
        .into_iter()
        .find_map(|x| match x {
            Transmit::Control(Message::Topology(m)) => Some(m),
            _ => None,
        })
        .expect("the refinement goes out");
    assert!(matches!(wire.kind, proto::TopologyKind::Refine { .. }));
    assert_eq!(wire.sim_time, at);
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Topology(wire), now)
        .unwrap();
    let leaves = p.sim_a.lattice().leaf_count();
    for (s, sim) in [(&mut p.a, &mut p.sim_a), (&mut p.b, &mut p.sim_b)] {
        s.apply_due(sim).unwrap();
        assert_eq!(
            sim.lattice().leaf_count(),
            leaves,
            "applied before its time"
        );
        sim.set_time(at);
        s.apply_due(sim).unwrap();
        assert!(
            sim.lattice().leaf_count() > leaves,
            "not applied at its time"
        );
        assert_eq!(s.stats().refinements_applied, 1);
        assert_eq!(sim.topology().epoch(), 0, "a refinement is not a cut");
    }
    let mut la = p.sim_a.lattice().leaves().to_vec();
    let mut lb = p.sim_b.lattice().leaves().to_vec();
    la.sort_unstable();
    lb.sort_unstable();
    assert_eq!(la, lb);
    // The keyframe made before it reaches B now: dropped, the tree stays refined.
    let refined = p.sim_b.lattice().leaf_count();
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Keyframe(before), now)
        .unwrap();
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!(p.b.stats().frames_refinement_dropped, 1);
    assert_eq!(p.sim_b.lattice().leaf_count(), refined);
}

/// A topology op of the epoch a scheduled reset leads to, made by a site that reset
/// before us, waits for our reset and is then applied at its time (it used to be dropped
/// as an op of another epoch).
#[test]
fn an_op_of_the_coming_epoch_waits_for_the_reset() {
    let mut p = pair_with(SyncStrategy::Hybrid);
    for _ in 0..3 {
        p.step(&[]);
    }
    let t = p.sim_b.time();
    let (reset_at, op_at) = (t + 0.06, t + 0.08);
    let now = p.clock.now();
    let reset = Message::Command(Command::ResetScene {
        epoch: 1,
        sim_time_s: reset_at,
    });
    p.b.handle_message(&mut p.sim_b, reset, now).unwrap();
    let op = sim_core::cut::TopologyOp::Refine(refine_first_root(&p));
    let wire = super::super::topology::topology_to_wire(&op, 1, op_at);
    // An op of an epoch nobody scheduled is still dropped.
    let stray = super::super::topology::topology_to_wire(&op, 2, op_at);
    for m in [wire, stray] {
        p.b.handle_message(&mut p.sim_b, Message::Topology(m), now)
            .unwrap();
    }
    let leaves = p.sim_b.lattice().leaf_count();
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!(p.b.epoch(), 0);
    assert_eq!(
        p.sim_b.lattice().leaf_count(),
        leaves,
        "applied before the reset"
    );
    p.sim_b.set_time(reset_at);
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!(p.b.epoch(), 1, "reset at its time");
    assert_eq!(
        p.sim_b.lattice().leaf_count(),
        leaves,
        "applied before its own time"
    );
    p.sim_b.set_time(op_at);
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert!(
        p.sim_b.lattice().leaf_count() > leaves,
        "the new epoch's op was not applied"
    );
    assert_eq!(p.b.stats().refinements_applied, 1);
}

/// A snapshot of a newer epoch (a site back after a lost link, the session reset
/// meanwhile) rebuilds the simulation like a reset, then takes the snapshot's ops; with a
/// reset to that epoch already scheduled, its ops wait for the reset instead.
#[test]
fn a_snapshot_of_a_newer_epoch_resets_or_waits_for_the_scheduled_reset() {
    let snapshot_with = |t: f64, epoch: Epoch, op: proto::TopologyOp| {
        Message::Snapshot(proto::Snapshot {
            sim_time_s: t,
            epoch,
            owners: Vec::new(),
            keyframes: Vec::new(),
            topology: vec![op],
        })
    };
    // No reset scheduled: rebuilt at once.
    let mut p = pair_with(SyncStrategy::Hybrid);
    for _ in 0..3 {
        p.step(&[]);
    }
    let op = sim_core::cut::TopologyOp::Refine(refine_first_root(&p));
    let t = p.sim_b.time();
    let leaves = p.sim_b.lattice().leaf_count();
    let wire = super::super::topology::topology_to_wire(&op, 1, t);
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, snapshot_with(t, 1, wire.clone()), now)
        .unwrap();
    assert_eq!(p.b.epoch(), 1);
    assert_eq!(p.b.stats().resets, 1, "the simulation was not rebuilt");
    let events: Vec<_> = std::iter::from_fn(|| p.b.poll_event()).collect();
    assert!(events.contains(&SessionEvent::SceneReset { epoch: 1 }));
    assert!(p.sim_b.lattice().leaf_count() > leaves, "the snapshot's op");
    assert!((p.sim_b.time() - t).abs() < 1e-12, "the clock is kept");

    // A reset to it scheduled: the snapshot's ops wait for it.
    let mut p = pair_with(SyncStrategy::Hybrid);
    for _ in 0..3 {
        p.step(&[]);
    }
    let t = p.sim_b.time();
    let at = t + 0.06;
    let now = p.clock.now();
    let reset = Message::Command(Command::ResetScene {
        epoch: 1,
        sim_time_s: at,
    });
    p.b.handle_message(&mut p.sim_b, reset, now).unwrap();
    let mut wire = wire;
    wire.sim_time = at;
    p.b.handle_message(&mut p.sim_b, snapshot_with(t, 1, wire), now)
        .unwrap();
    assert_eq!(p.b.epoch(), 0, "the reset waits for its time");
    assert_eq!(p.sim_b.lattice().leaf_count(), leaves);
    p.sim_b.set_time(at);
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!((p.b.epoch(), p.b.stats().resets), (1, 1));
    assert!(
        p.sim_b.lattice().leaf_count() > leaves,
        "the op after the reset"
    );
}
