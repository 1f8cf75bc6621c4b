//! `SiteSession` on a fake clock, with the coordinator played by hand: claim and
//! release, acknowledgement and baseline, reconnect, and a scene reset; the hybrid
//! strategy's inputs and keyframe followers in `hybrid.rs`; joining and starting in
//! `start.rs`.

use std::time::{Duration, Instant};

use proto::{Command, Message, Role, SessionInfo, SiteEntry, Welcome};
use sim_core::sim_scene::{LoadedScene, builtin};
use sim_core::sync::SyncStrategy;
use sim_core::{SimOptions, Simulation};

use super::*;

mod hybrid;
mod start;

fn scene() -> LoadedScene {
    builtin::cantilever()
}

fn new_sim() -> Simulation {
    let scene = scene();
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).unwrap()
}

fn session(role: Role, sim: &Simulation, clock: &FakeClock) -> SiteSession {
    session_with(role, sim, clock, SyncStrategy::Keyframe)
}

fn session_with(
    role: Role,
    sim: &Simulation,
    clock: &FakeClock,
    strategy: SyncStrategy,
) -> SiteSession {
    let scene = scene();
    SiteSession::new(
        SessionConfig {
            role,
            strategy,
            options: SimOptions::from_scene(&scene.scene),
            scene,
            linked: true,
            playout_lag: PlayoutLag::Fixed(0.0),
            realtime: false,
            shows_keyframes: false,
        },
        sim,
        clock.now().wall,
    )
}

/// Wall time and coordinator time advanced by hand.
struct FakeClock {
    origin: Instant,
    elapsed: Duration,
}

impl FakeClock {
    fn new() -> Self {
        FakeClock {
            origin: Instant::now(),
            elapsed: Duration::ZERO,
        }
    }
    fn advance(&mut self, ms: u64) {
        self.elapsed += Duration::from_millis(ms);
    }
    fn now(&self) -> Now {
        Now {
            wall: self.origin + self.elapsed,
            coordinator_us: 1_000_000 + self.elapsed.as_micros() as u64,
            synced: true,
        }
    }
}

fn welcome(site: SiteId, sites: &[(SiteId, Role)]) -> Welcome {
    Welcome {
        site,
        session: SessionInfo {
            name: "test".into(),
            scene_hash: String::new(),
            max_sites: 8,
            protocol_version: proto::PROTOCOL_VERSION,
            heartbeat_interval_us: 500_000,
        },
        sites: sites
            .iter()
            .map(|&(site, role)| SiteEntry {
                site,
                name: format!("site-{site}"),
                role,
            })
            .collect(),
        coordinator_time_us: 0,
    }
}

fn snapshot(sim_time_s: f64, epoch: Epoch, keyframes: Vec<proto::RegionKeyframe>) -> Message {
    Message::Snapshot(proto::Snapshot {
        sim_time_s,
        epoch,
        owners: Vec::new(),
        keyframes,
        topology: Vec::new(),
    })
}

/// A clock stamp of `site` at simulated time `sim_time_s`, sent 100 ms before now on the
/// coordinator's clock.
fn stamp(site: SiteId, sim_time_s: f64, clock: &FakeClock) -> Message {
    Message::SimTime(proto::SimTimeStamp {
        site,
        sim_time_s,
        step: (sim_time_s / 0.004) as u64,
        wall_send_us: clock.now().coordinator_us - 100_000,
    })
}

fn drain(s: &mut SiteSession) -> Vec<Transmit> {
    std::iter::from_fn(|| s.poll_transmit()).collect()
}

fn keyframes(t: &[Transmit]) -> Vec<proto::RegionKeyframe> {
    t.iter()
        .filter_map(|t| match t {
            Transmit::Keyframe(k) => Some(k.clone()),
            _ => None,
        })
        .collect()
}

fn acks(t: &[Transmit]) -> Vec<proto::KeyframeAck> {
    t.iter()
        .filter_map(|t| match t {
            Transmit::Control(Message::KeyframeAck(a)) => Some(*a),
            _ => None,
        })
        .collect()
}

fn grant(region: RegionId, site: SiteId) -> Message {
    Message::OwnershipGrant(proto::OwnershipGrant {
        region,
        site,
        previous: None,
    })
}

fn first_region(sim: &Simulation) -> RegionId {
    RegionMap::for_simulation(sim).regions().next().unwrap()
}

/// Owner session 1 (instructor) and receiver 2 (trainee), both welcomed and started;
/// the owner holds the first region and has stepped its sim a few times.
struct Pair {
    clock: FakeClock,
    a: SiteSession,
    sim_a: Simulation,
    b: SiteSession,
    sim_b: Simulation,
    region: RegionId,
}

/// A third site (a trainee, id 3) welcomed into a session of three, before its snapshot.
fn late_joiner() -> (FakeClock, Simulation, SiteSession) {
    let clock = FakeClock::new();
    let sim = new_sim();
    let mut c = session(Role::Trainee, &sim, &clock);
    let sites = [
        (1, Role::Instructor),
        (2, Role::Trainee),
        (3, Role::Trainee),
    ];
    c.handle_welcome(&welcome(3, &sites), clock.now());
    (clock, sim, c)
}

fn pair() -> Pair {
    pair_with(SyncStrategy::Keyframe)
}

fn pair_with(strategy: SyncStrategy) -> Pair {
    let clock = FakeClock::new();
    let sim_a = new_sim();
    let sim_b = new_sim();
    let mut a = session_with(Role::Instructor, &sim_a, &clock, strategy);
    let mut b = session_with(Role::Trainee, &sim_b, &clock, strategy);
    let sites = [(1, Role::Instructor), (2, Role::Trainee)];
    a.handle_welcome(&welcome(1, &sites), clock.now());
    b.handle_welcome(&welcome(2, &sites), clock.now());
    let region = first_region(&sim_a);
    let mut p = Pair {
        clock,
        a,
        sim_a,
        b,
        sim_b,
        region,
    };
    for (s, sim) in [(&mut p.a, &mut p.sim_a), (&mut p.b, &mut p.sim_b)] {
        s.handle_message(sim, snapshot(0.0, 0, Vec::new()), p.clock.now())
            .unwrap();
        s.start(p.clock.now().wall, Some(2_000));
        s.handle_message(sim, grant(region, 1), p.clock.now())
            .unwrap();
    }
    p
}

impl Pair {
    /// One step of both sites at the same simulated time; A's frames go to B and B's
    /// acknowledgements back to A. Returns A's transmits.
    fn step(&mut self, touched: &[RegionId]) -> Vec<Transmit> {
        self.clock.advance(10);
        let now = self.clock.now();
        self.a.apply_due(&mut self.sim_a).unwrap();
        self.a.handle_touched(&self.sim_a, touched, now);
        self.a.before_step(&mut self.sim_a);
        self.sim_a.step().unwrap();
        self.a.after_step(&self.sim_a, now);
        let out = drain(&mut self.a);
        self.b.apply_due(&mut self.sim_b).unwrap();
        self.b.before_step(&mut self.sim_b);
        self.sim_b.step().unwrap();
        self.deliver_to_b(&out);
        out
    }

    fn deliver_to_b(&mut self, out: &[Transmit]) {
        let now = self.clock.now();
        for t in out {
            let m = match t {
                Transmit::Keyframe(k) => Message::Keyframe(k.clone()),
                Transmit::Datagram(m @ Message::TreeDelta(_)) => m.clone(),
                _ => continue,
            };
            self.b.handle_message(&mut self.sim_b, m, now).unwrap();
        }
        for t in drain(&mut self.b) {
            if let Transmit::Control(m @ Message::KeyframeAck(_)) = t {
                self.a.handle_message(&mut self.sim_a, m, now).unwrap();
            }
        }
    }
}

/// Tissue that still moves after the tool let go stays owned (its owner keeps sending
/// keyframes of the motion) until it is at rest, or for [`claims::HOLD_MOVING_AT_MOST`].
#[test]
fn a_region_still_moving_is_released_once_at_rest() {
    let clock = FakeClock::new();
    let mut sim = new_sim();
    let mut s = session(Role::Trainee, &sim, &clock);
    s.handle_welcome(
        &welcome(2, &[(1, Role::Instructor), (2, Role::Trainee)]),
        clock.now(),
    );
    let r = first_region(&sim);
    s.handle_touched(&sim, &[r], clock.now());
    s.handle_message(&mut sim, grant(r, 2), clock.now())
        .unwrap();
    drain(&mut s);
    // One free node of the region moves at 4× the settled speed.
    let map = RegionMap::for_simulation(&sim);
    let node = map
        .canonical_nodes(sim.lattice(), r)
        .into_iter()
        .find(|&n| !sim.is_fixed(n))
        .expect("a free node");
    let x = sim.positions()[node.0 as usize];
    let moving = nalgebra::Vector3::new(0.0, 0.0, 4.0 * claims::SETTLED_SPEED);
    sim.set_node_state(node, x, moving);
    sim.set_time(claims::RELEASE_AFTER + 0.01);
    s.handle_touched(&sim, &[], clock.now());
    drain(&mut s);
    assert_eq!(s.snapshot().owned, vec![r], "released while moving");
    // At rest: released.
    sim.set_node_state(node, x, nalgebra::Vector3::zeros());
    s.handle_touched(&sim, &[], clock.now());
    assert!(s.snapshot().owned.is_empty(), "kept at rest");
    // Moving for ever: released after the bound all the same.
    let mut s = session(Role::Trainee, &sim, &clock);
    s.handle_welcome(
        &welcome(2, &[(1, Role::Instructor), (2, Role::Trainee)]),
        clock.now(),
    );
    sim.set_time(0.0);
    s.handle_touched(&sim, &[r], clock.now());
    s.handle_message(&mut sim, grant(r, 2), clock.now())
        .unwrap();
    sim.set_node_state(node, x, moving);
    sim.set_time(claims::HOLD_MOVING_AT_MOST - 0.01);
    s.handle_touched(&sim, &[], clock.now());
    assert_eq!(s.snapshot().owned, vec![r]);
    sim.set_time(claims::HOLD_MOVING_AT_MOST + 0.01);
    s.handle_touched(&sim, &[], clock.now());
    assert!(s.snapshot().owned.is_empty(), "held beyond the bound");
}

#[test]
fn claim_then_release_after_the_tool_leaves() {
    let clock = FakeClock::new();
    let mut sim = new_sim();
    let mut s = session(Role::Trainee, &sim, &clock);
    s.handle_welcome(
        &welcome(2, &[(1, Role::Instructor), (2, Role::Trainee)]),
        clock.now(),
    );
    let r = first_region(&sim);
    s.handle_touched(&sim, &[r], clock.now());
    let out = drain(&mut s);
    assert_eq!(
        out,
        vec![Transmit::Control(Message::OwnershipRequest(
            proto::OwnershipRequest {
                region: r,
                claim_time_us: clock.now().coordinator_us,
            }
        ))]
    );
    // Claimed once only.
    s.handle_touched(&sim, &[r], clock.now());
    assert!(drain(&mut s).is_empty());
    s.handle_message(&mut sim, grant(r, 2), clock.now())
        .unwrap();
    assert_eq!(s.snapshot().owned, vec![r]);
    // The first keyframe goes out with our id, the current epoch and our time.
    s.after_step(&sim, clock.now());
    let kfs = keyframes(&drain(&mut s));
    assert_eq!(kfs.len(), 1);
    assert_eq!((kfs[0].region, kfs[0].owner, kfs[0].epoch), (r, 2, 0));
    // Touched within RELEASE_AFTER: kept; after it: a final keyframe, then the release.
    sim.set_time(claims::RELEASE_AFTER * 0.5);
    s.handle_touched(&sim, &[], clock.now());
    assert!(drain(&mut s).is_empty());
    sim.set_time(claims::RELEASE_AFTER + 0.01);
    s.handle_touched(&sim, &[], clock.now());
    let out = drain(&mut s);
    assert!(
        matches!(&out[0], Transmit::Keyframe(k) if k.region == r),
        "{out:?}"
    );
    assert_eq!(
        out[1],
        Transmit::Control(Message::OwnershipRelease(proto::OwnershipRelease {
            region: r,
            site: 2
        }))
    );
    assert!(s.snapshot().owned.is_empty());
    assert_eq!(
        s.owned_intervals(1.0),
        vec![(r, 0.0, claims::RELEASE_AFTER + 0.01)]
    );
    // Observers never claim.
    let mut o = session(Role::Observer, &sim, &clock);
    o.handle_welcome(&welcome(3, &[(3, Role::Observer)]), clock.now());
    o.handle_touched(&sim, &[r], clock.now());
    assert!(drain(&mut o).is_empty());
}

#[test]
fn acknowledgements_set_the_delta_baseline() {
    let mut p = pair();
    let r = p.region;
    let first = p.step(&[r]);
    let kfs = keyframes(&first);
    assert_eq!(kfs.len(), 1, "first keyframe: {first:?}");
    // B applied it (same simulated time) and acknowledged it to A.
    assert_eq!(p.b.stats().keyframes_applied, 1);
    assert_eq!(
        p.a.baselines.common_baseline(r, [2]),
        Some(kfs[0].keyframe_id),
        "the acknowledged keyframe is the baseline"
    );
    // An acknowledgement from a site that is not a receiver of that keyframe, or of a
    // keyframe never sent, moves nothing.
    let now = p.clock.now();
    p.a.handle_message(
        &mut p.sim_a,
        Message::KeyframeAck(proto::KeyframeAck {
            region: r,
            keyframe_id: 99,
            site: 2,
            shows_keyframes: false,
        }),
        now,
    )
    .unwrap();
    assert_eq!(
        p.a.baselines.common_baseline(r, [2]),
        Some(kfs[0].keyframe_id)
    );
    // A third site that has acknowledged nothing: no common baseline (keyframes only).
    p.a.handle_message(
        &mut p.sim_a,
        Message::SiteJoined(SiteEntry {
            site: 3,
            name: "c".into(),
            role: Role::Trainee,
        }),
        now,
    )
    .unwrap();
    assert_eq!(
        p.a.baselines
            .common_baseline(r, p.a.sites.receivers().collect::<Vec<_>>()),
        None
    );
    // It leaves: the baseline is B's again.
    p.a.handle_message(
        &mut p.sim_a,
        Message::Leave(proto::Leave {
            site: 3,
            reason: "bye".into(),
        }),
        now,
    )
    .unwrap();
    assert_eq!(
        p.a.baselines
            .common_baseline(r, p.a.sites.receivers().collect::<Vec<_>>()),
        Some(kfs[0].keyframe_id)
    );
}

/// After a reconnect the coordinator has dropped our regions: we ask for them again at
/// once (our tool may have stopped during the outage, and the sites' copies must be
/// brought together by our keyframes), under the new id.
#[test]
fn reconnect_drops_ownership_and_takes_the_new_id() {
    let mut p = pair();
    let r = p.region;
    p.step(&[r]);
    assert_eq!(p.a.snapshot().owned, vec![r]);
    let now = p.clock.now();
    let t = p.sim_a.time();
    // It released the region (its tool left it) just before the link was found dead:
    // nobody heard of it.
    p.a.claims.lost(r, t);
    drain(&mut p.a);
    p.sim_a.set_time(t + 1.0);
    p.a.handle_disconnected(&p.sim_a);
    p.a.handle_reconnected(
        &welcome(7, &[(2, Role::Trainee), (7, Role::Instructor)]),
        &p.sim_a,
        now,
    );
    assert_eq!(p.a.site_id(), Some(7));
    assert_eq!(p.a.stats().reconnects, 1);
    // What it sent under its former id is still its own, not another site's.
    assert!(!p.a.sites.is_other(1) && !p.a.sites.is_other(7) && p.a.sites.is_other(2));
    assert!(p.a.snapshot().owned.is_empty());
    assert_eq!(p.a.owned_intervals(t), vec![(r, 0.0, t)]);
    assert_eq!(p.a.baselines.common_baseline(r, [2]), None);
    // The region it owned is asked for again, once, without a touch.
    let requests = |out: &[Transmit]| {
        out.iter()
            .filter(|t| {
                matches!(
                    t,
                    Transmit::Control(Message::OwnershipRequest(q)) if q.region == r
                )
            })
            .count()
    };
    assert_eq!(requests(&drain(&mut p.a)), 1);
    // Its next time stamp carries the new id; touching the region asks nothing more.
    p.sim_a.set_time(t + 1.0 + SIM_TIME_INTERVAL);
    p.a.handle_touched(&p.sim_a, &[r], now);
    p.a.after_step(&p.sim_a, now);
    let out = drain(&mut p.a);
    assert_eq!(requests(&out), 0);
    assert!(out.iter().any(|t| matches!(
        t,
        Transmit::Datagram(Message::SimTime(s)) if s.site == 7
    )));
}

/// A site whose tool acted while it was cut off asks, once back, for every region its
/// copy moved meanwhile (the others did not see it), besides the one it owned, and not
/// for the ones that stayed put; a site whose tool did nothing asks for none of them.
#[test]
fn reconnect_asks_for_the_regions_its_tool_moved_unseen() {
    for drove in [true, false] {
        let mut p = pair();
        let r = p.region;
        p.a.handle_disconnected(&p.sim_a);
        let now = p.clock.now();
        if drove {
            p.a.handle_touched(&p.sim_a, &[r], now);
        }
        drain(&mut p.a);
        // A free node of exactly one region, moved 2 mm.
        let regions =
            p.a.map
                .max_speeds(p.sim_a.lattice(), p.sim_a.velocities())
                .len();
        let members: Vec<Vec<_>> = (0..regions as RegionId)
            .map(|g| p.a.map.canonical_nodes(p.sim_a.lattice(), g))
            .collect();
        let (moved, node) = members
            .iter()
            .enumerate()
            .flat_map(|(g, nodes)| nodes.iter().map(move |&n| (g as RegionId, n)))
            .find(|&(g, n)| {
                g != r
                    && !p.sim_a.is_fixed(n)
                    && members.iter().filter(|m| m.contains(&n)).count() == 1
            })
            .expect("a node of one region only");
        let (x, v) = (
            p.sim_a.positions()[node.0 as usize],
            p.sim_a.velocities()[node.0 as usize],
        );
        p.sim_a
            .set_node_state(node, x + nalgebra::Vector3::new(0.0, 2e-3, 0.0), v);
        p.a.handle_reconnected(
            &welcome(7, &[(2, Role::Trainee), (7, Role::Instructor)]),
            &p.sim_a,
            now,
        );
        let asked: Vec<RegionId> = drain(&mut p.a)
            .into_iter()
            .filter_map(|t| match t {
                Transmit::Control(Message::OwnershipRequest(q)) => Some(q.region),
                _ => None,
            })
            .collect();
        // The region it owns (granted at the start) is asked for in any case.
        let mut want = vec![r];
        if drove {
            want.push(moved);
        }
        want.sort_unstable();
        assert_eq!(asked, want);
    }
}

#[test]
fn reset_drops_the_old_epoch_and_applies_the_new_one() {
    let mut p = pair();
    let r = p.region;
    for _ in 0..20 {
        p.step(&[r]);
    }
    let applied_before = p.b.stats().keyframes_applied;
    assert!(applied_before >= 1);
    let moved = |sim: &Simulation| {
        let rest = new_sim();
        sim.surfaces()[0]
            .deformed
            .iter()
            .zip(&rest.surfaces()[0].deformed)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max)
    };
    assert!(
        moved(&p.sim_b) > 1e-6,
        "the receiver follows the owner's sag"
    );

    // Only the instructor may ask; the request carries a time a little ahead.
    let t = p.sim_a.time();
    assert_eq!(
        p.b.request_reset(t, None),
        Err(ResetError::NotInstructor(Role::Trainee))
    );
    p.a.request_reset(t, Some(Duration::from_millis(30)))
        .unwrap();
    let at = t + 0.06;
    match &drain(&mut p.a)[..] {
        [
            Transmit::Control(Message::Command(Command::ResetScene {
                epoch: 0,
                sim_time_s,
            })),
        ] => {
            assert!((sim_time_s - at).abs() < 1e-12, "{sim_time_s} vs {at}")
        }
        other => panic!("expected one reset request: {other:?}"),
    }
    // The coordinator's answer to every site: epoch 1 at `at`.
    let reset = Message::Command(Command::ResetScene {
        epoch: 1,
        sim_time_s: at,
    });
    let now = p.clock.now();
    p.a.handle_message(&mut p.sim_a, reset.clone(), now)
        .unwrap();
    p.b.handle_message(&mut p.sim_b, reset, now).unwrap();
    assert_eq!(p.b.epoch(), 0, "the reset waits for its simulated time");
    // Until then old-epoch frames still count; at `at` both sites reset.
    let mut steps = 0;
    while p.b.epoch() == 0 {
        p.step(&[r]);
        steps += 1;
        assert!(steps < 100, "no reset");
    }
    assert_eq!(p.a.epoch(), 1);
    assert!(p.sim_b.time() >= at - 1e-9 && p.sim_b.time() < at + 0.02);
    let events: Vec<_> = std::iter::from_fn(|| p.b.poll_event()).collect();
    assert!(
        events.contains(&SessionEvent::SceneReset { epoch: 1 }),
        "{events:?}"
    );
    assert_eq!(p.b.stats().resets, 1);
    // Ownership is gone on both sides (the coordinator dropped it).
    assert!(p.a.snapshot().owned.is_empty());
    assert!(p.b.snapshot().remote_owners.is_empty());

    // A keyframe of the old epoch arriving late is dropped: not applied, not acknowledged.
    let mut stale = p.a_keyframe_after_grant(0);
    stale.sim_time = p.sim_b.time();
    let applied = p.b.stats().keyframes_applied;
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Keyframe(stale), now)
        .unwrap();
    assert_eq!(p.b.stats().keyframes_applied, applied);
    assert!(acks(&drain(&mut p.b)).is_empty());

    // New-epoch keyframes from the owner are applied and acknowledged.
    let now = p.clock.now();
    p.a.handle_message(&mut p.sim_a, grant(r, 1), now).unwrap();
    p.b.handle_message(&mut p.sim_b, grant(r, 1), now).unwrap();
    let out = p.step(&[r]);
    let kfs = keyframes(&out);
    assert_eq!(kfs.len(), 1);
    assert_eq!(kfs[0].epoch, 1);
    assert_eq!(p.b.stats().keyframes_applied, applied + 1);

    // A late joiner takes epoch 1 from its snapshot and applies its keyframes.
    let (clock, mut sim_c, mut c) = late_joiner();
    let mut kf = kfs[0].clone();
    kf.sim_time = p.sim_a.time();
    c.handle_message(
        &mut sim_c,
        snapshot(p.sim_a.time(), 1, vec![kf.clone()]),
        clock.now(),
    )
    .unwrap();
    assert_eq!(c.epoch(), 1);
    assert_eq!(c.stats().keyframes_applied, 1);
    assert_eq!(acks(&drain(&mut c)).len(), 1);
    // Snapshot keyframes of another epoch are not applied.
    let mut d = session(Role::Trainee, &new_sim(), &clock);
    let mut sim_d = new_sim();
    d.handle_welcome(
        &welcome(4, &[(1, Role::Instructor), (4, Role::Trainee)]),
        clock.now(),
    );
    kf.epoch = 0;
    d.handle_message(&mut sim_d, snapshot(kf.sim_time, 1, vec![kf]), clock.now())
        .unwrap();
    assert_eq!(d.stats().keyframes_applied, 0);
}

#[test]
fn a_site_on_its_own_resets_locally() {
    let clock = FakeClock::new();
    let mut sim = new_sim();
    let scene = scene();
    let mut s = SiteSession::new(
        SessionConfig {
            role: Role::Instructor,
            strategy: SyncStrategy::Keyframe,
            options: SimOptions::from_scene(&scene.scene),
            scene,
            linked: false,
            playout_lag: PlayoutLag::Auto,
            realtime: false,
            shows_keyframes: false,
        },
        &sim,
        clock.now().wall,
    );
    for _ in 0..5 {
        sim.step().unwrap();
    }
    let t = sim.time();
    s.request_reset(t, None).unwrap();
    s.apply_due(&mut sim).unwrap();
    assert_eq!(s.epoch(), 1);
    assert_eq!(sim.time(), t, "the clock keeps running");
    assert_eq!(sim.steps(), 0, "a fresh simulation");
    assert!(drain(&mut s).is_empty(), "nothing to send without a link");
}

impl Pair {
    /// A keyframe of A's first region in epoch `epoch` (a copy of one A would send).
    fn a_keyframe_after_grant(&mut self, epoch: Epoch) -> proto::RegionKeyframe {
        let frame = sim_core::sync::encode_keyframe(&self.sim_a, &self.a.map, self.region, 1_000)
            .expect("encodable");
        match wire::frame_to_wire(sim_core::sync::SyncFrame::Keyframe(frame), 1, epoch) {
            Some(WireFrame::Keyframe(k)) => k,
            other => panic!("{other:?}"),
        }
    }
}

/// A cut through the middle of the organ (x = mid-point of its rest box plus 1.3 mm, off
/// the lattice planes), as A would send it.
fn cut_message(sim: &Simulation, epoch: Epoch) -> proto::TopologyOp {
    let rest = sim.rest_positions();
    let (lo, hi) = rest
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.x), hi.max(p.x))
        });
    let x = 0.5 * (lo + hi) + 0.0013;
    proto::TopologyOp {
        epoch,
        site: 1,
        seq: 0,
        sim_time: sim.time(),
        kind: proto::TopologyKind::Cut {
            triangles: vec![
                [[x, -1.0, -1.0], [x, 1.0, -1.0], [x, 1.0, 1.0]],
                [[x, -1.0, -1.0], [x, 1.0, 1.0], [x, -1.0, 1.0]],
            ],
        },
    }
}

#[test]
fn topology_ops_apply_once_and_keyframes_of_an_unreached_topology_are_dropped() {
    let mut p = pair();
    // A keyframe from a sender that already applied one topology op: B has not.
    let mut ahead = p.a_keyframe_after_grant(0);
    ahead.topology = 1;
    ahead.sim_time = p.sim_b.time();
    let applied = p.b.stats().keyframes_applied;
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Keyframe(ahead.clone()), now)
        .unwrap();
    assert_eq!(p.b.stats().keyframes_applied, applied);
    assert_eq!(p.b.stats().keyframes_topology_dropped, 1);
    assert!(
        acks(&drain(&mut p.b)).is_empty(),
        "a dropped keyframe is not acknowledged"
    );

    // The op arrives twice (a duplicate) and one of another epoch: applied once.
    let op = cut_message(&p.sim_b, 0);
    for m in [
        op.clone(),
        op.clone(),
        proto::TopologyOp {
            epoch: 7,
            ..op.clone()
        },
    ] {
        let now = p.clock.now();
        p.b.handle_message(&mut p.sim_b, Message::Topology(m), now)
            .unwrap();
    }
    assert_eq!(p.sim_b.topology().epoch(), 1);
    assert_eq!(p.b.stats().topology_applied, 1);
    assert!(p.sim_b.separation().is_some_and(|s| !s.crossed.is_empty()));

    // A late joiner takes the op from its snapshot and reaches the same topology.
    let (clock, mut sim_c, mut c) = late_joiner();
    let Message::Snapshot(mut s) = snapshot(p.sim_b.time(), 0, Vec::new()) else {
        unreachable!()
    };
    s.topology = vec![op.clone()];
    c.handle_message(&mut sim_c, Message::Snapshot(s), clock.now())
        .unwrap();
    assert_eq!(sim_c.topology().digest(), p.sim_b.topology().digest());

    // The owner's ops go out on the control stream with our scene epoch.
    let own = sim_core::cut::TopologyOp::Cut(sim_core::cut::CutOp {
        id: sim_core::cut::OpId { site: 1, seq: 0 },
        triangles: match &op.kind {
            proto::TopologyKind::Cut { triangles } => triangles.clone(),
            _ => unreachable!("cut_message makes a cut"),
        },
    });
    // Under keyframe sync an op goes out stamped with the time it was applied at here.
    let t = p.sim_a.time();
    p.a.share_topology(&[own], t, Some(Duration::from_millis(40)));
    let sent: Vec<Transmit> = drain(&mut p.a);
    let stamped = proto::TopologyOp {
        sim_time: t,
        ..op.clone()
    };
    assert!(
        sent.iter()
            .any(|x| matches!(x, Transmit::Control(Message::Topology(m)) if *m == stamped)),
        "{sent:?}"
    );
    assert!(p.a.stats().topology_bytes_sent > 0);
}

/// Under hybrid sync a site schedules its own cut a little ahead (the round trip and a
/// margin), for the others and for itself, and applies it when its clock gets there.
#[test]
fn under_hybrid_an_own_cut_is_scheduled_ahead_and_applied_at_its_time() {
    let mut p = pair_with(SyncStrategy::Hybrid);
    let op = cut_message(&p.sim_a, 0);
    let own = sim_core::cut::TopologyOp::Cut(sim_core::cut::CutOp {
        id: sim_core::cut::OpId { site: 1, seq: 0 },
        triangles: match &op.kind {
            proto::TopologyKind::Cut { triangles } => triangles.clone(),
            _ => unreachable!("cut_message makes a cut"),
        },
    });
    drain(&mut p.a);
    let t = p.sim_a.time();
    let rtt = Duration::from_millis(40);
    p.a.share_topology(&[own], t, Some(rtt));
    let at = t + super::topology_lead(Some(rtt));
    assert!(at >= t + 0.05 - 1e-12 && at <= t + 0.5, "lead {}", at - t);
    let scheduled = proto::TopologyOp {
        sim_time: at,
        ..op.clone()
    };
    let sent: Vec<Transmit> = drain(&mut p.a);
    assert!(
        sent.iter()
            .any(|x| matches!(x, Transmit::Control(Message::Topology(m)) if *m == scheduled)),
        "{sent:?}"
    );
    let before = p.sim_a.topology().epoch();
    p.a.apply_due(&mut p.sim_a).unwrap();
    assert_eq!(
        p.sim_a.topology().epoch(),
        before,
        "own cut applied before its time"
    );
    assert!(!p.a.take_own_cut_applied());
    p.sim_a.set_time(at);
    p.a.apply_due(&mut p.sim_a).unwrap();
    assert_eq!(
        p.sim_a.topology().epoch(),
        before + 1,
        "own cut not applied at its time"
    );
    assert!(
        p.a.take_own_cut_applied(),
        "the driver is not told to claim the cut"
    );
}

/// Under hybrid sync, a cut made by a site whose clock is ahead of ours waits for our
/// clock to reach the simulated time it was made at (so that the tissue parts at the same simulated moment
/// everywhere); a keyframe made after it is kept meanwhile, not dropped as one of an
/// unreached topology.
#[test]
fn a_topology_op_from_ahead_waits_for_its_simulated_time() {
    let mut p = pair_with(SyncStrategy::Hybrid);
    let t0 = p.sim_b.time();
    let mut op = cut_message(&p.sim_b, 0);
    op.sim_time = t0 + 0.5;
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Topology(op), now)
        .unwrap();
    let mut after = p.a_keyframe_after_grant(0);
    after.topology = 1;
    after.sim_time = t0 + 0.6;
    let now = p.clock.now();
    p.b.handle_message(&mut p.sim_b, Message::Keyframe(after), now)
        .unwrap();
    assert_eq!(p.b.stats().keyframes_topology_dropped, 0);
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!(p.sim_b.topology().epoch(), 0, "applied before its time");
    p.sim_b.set_time(t0 + 0.5);
    p.b.apply_due(&mut p.sim_b).unwrap();
    assert_eq!(p.sim_b.topology().epoch(), 1, "not applied at its time");
    assert_eq!(p.b.stats().topology_applied, 1);
}
