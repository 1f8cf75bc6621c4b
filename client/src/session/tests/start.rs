//! `SiteSession` joining and starting: the snapshot, the sites present, and the wait for
//! every known site's clock.

use super::*;

#[test]
fn join_waits_for_the_snapshot_and_takes_its_time_and_epoch() {
    let mut clock = FakeClock::new();
    let mut sim = new_sim();
    let mut s = session(Role::Trainee, &sim, &clock);
    assert_eq!(s.site_id(), None);
    assert!(!s.is_ready(1, clock.now().wall));
    s.handle_welcome(
        &welcome(3, &[(1, Role::Instructor), (3, Role::Trainee)]),
        clock.now(),
    );
    assert_eq!(s.site_id(), Some(3));
    assert!(!s.is_ready(2, clock.now().wall), "no snapshot yet");
    assert!(!s.is_ready(3, clock.now().wall), "a site is missing");
    s.handle_message(&mut sim, snapshot(2.5, 4, Vec::new()), clock.now())
        .unwrap();
    assert!(
        !s.is_ready(2, clock.now().wall),
        "site 1's clock not heard yet"
    );
    s.handle_message(&mut sim, stamp(1, 2.5, &clock), clock.now())
        .unwrap();
    assert!(s.is_ready(2, clock.now().wall));
    assert_eq!(sim.time(), 2.5, "a late joiner takes the session's time");
    assert_eq!(s.epoch(), 4, "… and its scene epoch");
    // Without a snapshot, the wait ends after SNAPSHOT_WAIT.
    let mut t = session(Role::Trainee, &new_sim(), &clock);
    t.handle_welcome(&welcome(5, &[(5, Role::Trainee)]), clock.now());
    assert!(!t.is_ready(1, clock.now().wall));
    clock.advance(SNAPSHOT_WAIT.as_millis() as u64 + 1);
    assert!(t.is_ready(1, clock.now().wall));
}

/// A site whose arrival the coordinator's table does not list yet (its announcement is
/// late on the control stream) counts as present once its clock stamps arrive, and the
/// stamps heard while waiting keep their wall times once the clock starts.
#[test]
fn a_site_heard_by_its_clock_stamps_completes_the_session() {
    let mut clock = FakeClock::new();
    let mut sim = new_sim();
    let mut s = session_with(Role::Trainee, &sim, &clock, SyncStrategy::Hybrid);
    s.handle_welcome(&welcome(3, &[(3, Role::Trainee)]), clock.now());
    s.handle_message(&mut sim, snapshot(0.0, 0, Vec::new()), clock.now())
        .unwrap();
    assert!(!s.is_ready(2, clock.now().wall), "alone in the table");
    // Our own stamps (echoed) do not count.
    s.handle_message(&mut sim, stamp(3, 0.05, &clock), clock.now())
        .unwrap();
    assert!(!s.is_ready(2, clock.now().wall), "our own stamp");
    clock.advance(1_000);
    s.handle_message(&mut sim, stamp(1, 0.30, &clock), clock.now())
        .unwrap();
    assert!(s.is_ready(2, clock.now().wall), "site 1's stamp");
    assert!(!s.is_ready(3, clock.now().wall), "a third site is missing");
    // Once listed, a site is not counted twice.
    s.handle_message(
        &mut sim,
        Message::SiteJoined(SiteEntry {
            site: 1,
            name: "site-1".into(),
            role: Role::Instructor,
        }),
        clock.now(),
    )
    .unwrap();
    assert!(s.is_ready(2, clock.now().wall));
    assert!(!s.is_ready(3, clock.now().wall), "site 1 counted once");
    // A site that left does not count, even if a datagram of its comes after its Leave.
    s.handle_message(&mut sim, stamp(4, 0.30, &clock), clock.now())
        .unwrap();
    assert!(s.is_ready(3, clock.now().wall), "site 4's stamp");
    s.handle_message(
        &mut sim,
        Message::Leave(proto::Leave {
            site: 4,
            reason: "gone".into(),
        }),
        clock.now(),
    )
    .unwrap();
    s.handle_message(&mut sim, stamp(4, 0.35, &clock), clock.now())
        .unwrap();
    assert!(!s.is_ready(3, clock.now().wall), "site 4 left");
    // Started a second after the stamp was heard, and following site 1's moving tool,
    // the follower is that second plus the stamp's transit behind site 1's stamped time
    // (site 1 runs on at real time): the stamp kept its wall time across the start.
    clock.advance(1_000);
    s.start(clock.now().wall, None);
    for (k, x) in [0.0f32, 0.01].into_iter().enumerate() {
        s.handle_message(
            &mut sim,
            Message::ToolPose(proto::ToolPose {
                site: 1,
                tool: 0,
                sim_time_s: 0.3 + 0.004 * k as f64,
                position: [x, 0.0, 0.0],
                orientation: [1.0, 0.0, 0.0, 0.0],
                jaw_rad: 0.0,
                velocity: [0.0; 3],
                angular_velocity: [0.0; 3],
            }),
            clock.now(),
        )
        .unwrap();
    }
    let behind = s.end_step(0.0, false, clock.now().wall).behind;
    let expected = 0.30 + 1.0 + 0.1;
    assert!(
        behind.is_some_and(|b| (b - expected).abs() < 1e-6),
        "behind {behind:?} s, expected {expected} s"
    );
    // Its (fixed, zero) target lag not reached yet, then reached once caught up: the
    // report's display delay without the catch-up counts from there.
    assert_eq!(s.stats().lag_reached_at, None);
    let behind = s.end_step(expected, false, clock.now().wall).behind;
    assert!(
        behind.is_some_and(|b| b.abs() < 1e-9),
        "caught up: {behind:?}"
    );
    assert_eq!(s.stats().lag_reached_at, Some(expected));
    assert_eq!(
        (s.stats().behind_steps, s.stats().reached_behind_steps),
        (2, 1)
    );
}

/// A site whose session is complete starts once it has heard the clock of every site it
/// knows of (observers send none), or after [`PRESENCE_WAIT`]; while it waits it sends
/// its own clock every [`SIM_TIME_INTERVAL`], and once started (or as an observer) it
/// sends none.
#[test]
fn a_complete_session_waits_for_the_clock_of_every_site_it_knows() {
    let presence = |s: &mut SiteSession| -> Vec<(SiteId, f64)> {
        drain(s)
            .into_iter()
            .filter_map(|t| match t {
                Transmit::Datagram(Message::SimTime(st)) => Some((st.site, st.sim_time_s)),
                _ => None,
            })
            .collect()
    };
    let sites = [
        (1, Role::Instructor),
        (2, Role::Observer),
        (3, Role::Trainee),
    ];
    let mut clock = FakeClock::new();
    let mut sim = new_sim();
    let mut s = session(Role::Trainee, &sim, &clock);
    s.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut s), [], "not welcomed yet: no id to send");
    s.handle_welcome(&welcome(3, &sites), clock.now());
    s.handle_message(&mut sim, snapshot(0.0, 0, Vec::new()), clock.now())
        .unwrap();
    s.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut s), [(3, 0.0)]);
    clock.advance(20);
    s.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut s), [], "one stamp per interval");
    clock.advance(40);
    s.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut s), [(3, 0.0)]);
    assert!(
        !s.is_ready(3, clock.now().wall),
        "the instructor's clock unheard"
    );
    s.handle_message(&mut sim, stamp(1, 0.0, &clock), clock.now())
        .unwrap();
    assert!(
        s.is_ready(3, clock.now().wall),
        "every site heard but the observer, which sends no clock"
    );
    s.start(clock.now().wall, None);
    clock.advance(100);
    s.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut s), [], "started: the steps send the stamps");

    // Nobody heard: the site starts PRESENCE_WAIT after its session was complete.
    let mut t = session(Role::Trainee, &sim, &clock);
    t.handle_welcome(&welcome(3, &sites), clock.now());
    clock.advance(1_000);
    assert!(!t.is_ready(3, clock.now().wall), "no snapshot yet");
    t.handle_message(&mut sim, snapshot(0.0, 0, Vec::new()), clock.now())
        .unwrap();
    assert!(!t.is_ready(3, clock.now().wall));
    clock.advance(PRESENCE_WAIT.as_millis() as u64);
    assert!(
        !t.is_ready(3, clock.now().wall),
        "the wait counts from completion"
    );
    // Incomplete again (the instructor left) and complete again (it joined again): the
    // wait starts over.
    let instructor = SiteEntry {
        site: 1,
        name: "site-1".into(),
        role: Role::Instructor,
    };
    let leave = Message::Leave(proto::Leave {
        site: 1,
        reason: "gone".into(),
    });
    t.handle_message(&mut sim, leave, clock.now()).unwrap();
    assert!(!t.is_ready(3, clock.now().wall), "two sites of three");
    t.handle_message(&mut sim, Message::SiteJoined(instructor), clock.now())
        .unwrap();
    clock.advance(1);
    assert!(!t.is_ready(3, clock.now().wall), "the wait starts over");
    clock.advance(PRESENCE_WAIT.as_millis() as u64 + 1);
    assert!(t.is_ready(3, clock.now().wall));

    // An observer sends no clock.
    let mut o = session(Role::Observer, &sim, &clock);
    o.handle_welcome(&welcome(2, &sites), clock.now());
    o.announce_presence(&sim, clock.now());
    assert_eq!(presence(&mut o), []);
}
