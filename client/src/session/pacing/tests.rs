//! The pacing on fake sites and a fake clock.

use super::*;

/// A fake site: its simulation time advances by `rate` per wall second as asked.
struct FakeSite {
    id: u16,
    t: f64,
    clocks: PeerClocks,
    leading: bool,
}

/// Advances every site by `dt` of wall time in small steps, exchanging time stamps
/// every 50 ms of wall time with a one-way `transit` (s) and returns the final times.
fn run(sites: &mut [FakeSite], seconds: f64, transit: f64) {
    let dt = 0.004;
    let mut now = 0.0;
    let mut next_stamp = 0.0;
    // Stamps in flight: (deliver at, from, sim time).
    let mut wire: Vec<(f64, u16, f64)> = Vec::new();
    while now < seconds {
        if now >= next_stamp {
            next_stamp += 0.05;
            for s in sites.iter() {
                wire.push((now + transit, s.id, s.t));
            }
        }
        let (due, later): (Vec<_>, Vec<_>) = wire.into_iter().partition(|w| w.0 <= now);
        wire = later;
        for (_, from, t) in due {
            for s in sites.iter_mut().filter(|s| s.id != from) {
                s.clocks.heard(from, t, now, Some(transit));
            }
        }
        for s in sites.iter_mut() {
            let pace = s.clocks.pace(s.t, now, s.leading, true);
            if pace.hold <= 0.0 {
                s.t += dt * pace.rate;
            }
        }
        now += dt;
    }
}

fn site(id: u16, lag: PlayoutLag, leading: bool) -> FakeSite {
    FakeSite {
        id,
        t: 0.0,
        clocks: PeerClocks::new(lag),
        leading,
    }
}

#[test]
fn follower_converges_to_the_target_lag_and_owner_keeps_real_time() {
    let mut sites = [
        site(1, PlayoutLag::Fixed(0.0), true),
        site(2, PlayoutLag::Fixed(0.25), false),
    ];
    sites[1].clocks.owners.insert(7, 1);
    run(&mut sites, 6.0, 0.08);
    let (owner, follower) = (sites[0].t, sites[1].t);
    // The owner follows nobody and runs at real time.
    assert!((owner - 6.0).abs() < 0.01, "owner at {owner}");
    let lag = owner - follower;
    assert!(
        (lag - 0.25).abs() < 0.02,
        "follower lags {lag} s, want 0.25"
    );
    // It got there gently: never slower than MIN_RATE over the run.
    assert!(follower >= 6.0 * MIN_RATE);
    let pace = sites[1].clocks.pace(follower, 6.0, false, true);
    assert!((pace.rate - 1.0).abs() < 0.05, "rate {}", pace.rate);
    assert!((pace.behind.unwrap() - 0.25).abs() < 0.02);
}

#[test]
fn auto_lag_covers_delay_jitter_and_one_keyframe_interval_within_the_cap() {
    let mut c = PeerClocks::new(PlayoutLag::Auto);
    for i in 0..200 {
        let d = if i % 2 == 0 { 0.09 } else { 0.11 };
        c.heard(1, i as f64 * 0.05, i as f64 * 0.05 + d, Some(d));
    }
    let l = c.target_lag();
    assert!(
        l > 0.1 + KEYFRAME_INTERVAL && l < 0.1 + KEYFRAME_INTERVAL + 0.1,
        "{l}"
    );
    let mut slow = PeerClocks::new(PlayoutLag::Auto);
    slow.heard(1, 0.0, 2.0, Some(2.0));
    assert_eq!(slow.target_lag(), MAX_AUTO_LAG);
}

#[test]
fn two_owners_following_each_other_do_not_deadlock() {
    let mut sites = [
        site(1, PlayoutLag::Fixed(0.3), true),
        site(2, PlayoutLag::Fixed(0.3), true),
    ];
    sites[0].clocks.owners.insert(1, 2);
    sites[1].clocks.owners.insert(2, 1);
    // Site 2 starts 0.2 s behind (it was a follower until it took a region).
    sites[1].t = -0.2;
    run(&mut sites, 8.0, 0.05);
    let (a, b) = (sites[0].t, sites[1].t);
    // Both keep (close to) real time and end level, neither waiting for the other.
    assert!(a > 8.0 * 0.95 && b > 8.0 * 0.95, "{a} {b}");
    assert!((a - b).abs() < 0.03, "{a} {b}");
}

#[test]
fn zero_lag_keeps_real_time_and_only_the_hard_cap() {
    let mut sites = [
        site(1, PlayoutLag::Fixed(0.0), true),
        site(2, PlayoutLag::Fixed(0.0), false),
    ];
    sites[1].clocks.owners.insert(7, 1);
    run(&mut sites, 3.0, 0.04);
    assert!((sites[0].t - sites[1].t).abs() < 0.05);
    assert_eq!(sites[1].clocks.pace(sites[1].t, 3.0, false, true).rate, 1.0);
}

#[test]
fn release_of_a_silent_site_is_not_pushed_into_the_future() {
    let mut c = PeerClocks::new(PlayoutLag::Auto);
    c.heard(4, 2.0, 10.0, Some(0.05));
    assert!((c.release_time(4, 10.2).unwrap() - 2.2).abs() < 1e-9);
    // Ten seconds of silence (the site dropped out): at most SILENT_AFTER later.
    assert!((c.release_time(4, 20.0).unwrap() - (2.0 + SILENT_AFTER)).abs() < 1e-9);
    assert_eq!(c.release_time(5, 20.0), None);
}

#[test]
fn parses_auto_and_milliseconds() {
    assert_eq!("auto".parse::<PlayoutLag>(), Ok(PlayoutLag::Auto));
    assert_eq!("250".parse::<PlayoutLag>(), Ok(PlayoutLag::Fixed(0.25)));
    assert!(!"0".parse::<PlayoutLag>().unwrap().enabled());
    assert!("-3".parse::<PlayoutLag>().is_err());
}

/// Hybrid: the auto lag follows the inputs' path alone (stamp transits: mean plus
/// 1.5 deviations plus one input interval), is not raised by keyframe ages or a
/// round-trip seed, and a follower short of it waits at once instead of slewing.
#[test]
fn hybrid_lag_follows_the_input_path_and_is_reached_by_waiting() {
    let mut c =
        PeerClocks::new(PlayoutLag::Auto).for_strategy(sim_core::sync::SyncStrategy::Hybrid);
    c.seed_delay(1.5);
    assert!(
        (c.target_lag() - (0.1 + HYBRID_INPUT_INTERVAL)).abs() < 1e-12,
        "no seed from a round trip: {}",
        c.target_lag()
    );
    for i in 0..400 {
        let wall = i as f64 * 0.05;
        // Transit 0.4 s ± 0.03 s, alternating.
        let transit = if i % 2 == 0 { 0.37 } else { 0.43 };
        c.heard(1, wall, wall + transit, Some(transit));
        // Keyframes 1.2 s old (retransmitted) are no delay sample under hybrid.
        c.keyframe_arrived(1, wall - 1.2, wall + transit);
    }
    let want = 0.4 + HYBRID_JITTER_DEVS * 0.03 + HYBRID_INPUT_INTERVAL;
    let lag = c.target_lag();
    assert!((lag - want).abs() < 0.01, "lag {lag} want {want}");
    let now = 399.0 * 0.05 + 0.43;
    // An owner is not followed under hybrid (nor capped against): its tool is.
    c.owners.insert(3, 1);
    assert!(!c.leads_by_claims() && PeerClocks::new(PlayoutLag::Auto).leads_by_claims());
    assert_eq!(c.pace(now + 1.0, now, false, true).hold, 0.0);
    c.tool_heard(1, now);
    // At the tool's site's time (about 20 s), a follower with no lag yet waits.
    let pace = c.pace(399.0 * 0.05 + 0.43, now, false, true);
    assert!(pace.hold > 0.0, "waits to build the lag: {pace:?}");
    // Behind its target it catches up faster than the keyframe strategy may, and far
    // behind (a late start) faster still.
    // (The owner's time now is about `now`: its stamps carry its wall time.)
    let pace = c.pace(now - lag - 0.2, now, false, true);
    assert_eq!(pace.rate, HYBRID_MAX_RATE);
    let pace = c.pace(now - lag - 1.5, now, false, true);
    assert_eq!(pace.rate, HYBRID_CATCH_UP_RATE);
    // A leader ahead of a site it follows (one whose tool began to move after a rest,
    // its lag still to make up) neither waits nor slows: the other catches up.
    let pace = c.pace(now + 0.1, now, true, true);
    assert_eq!((pace.rate, pace.hold), (1.0, 0.0), "{pace:?}");
    // Unless it is not paced by real time at all.
    assert!(c.pace(now + 0.1, now, true, false).hold > 0.0);
}

/// Over a jittery path that keeps packet order (a delayed stamp holds back the next
/// ones, which then arrive together), the owner's current time is still known to a
/// millisecond: from the stamps' send times, not their arrivals.
#[test]
fn bunched_stamps_do_not_move_the_owner_estimate() {
    let mut c = PeerClocks::new(PlayoutLag::Auto);
    // Owner at rate 1 (sim time = its wall time); stamps every 50 ms; transit 0.45 s
    // ± a deterministic jitter of up to 0.12 s, released in order.
    let mut released: f64 = 0.0;
    let mut worst: f64 = 0.0;
    for i in 0..400 {
        let sent = i as f64 * 0.05;
        let jitter = 0.12 * ((i * 7919) % 13) as f64 / 12.0;
        released = released.max(sent + 0.45 + jitter);
        c.heard(1, sent, released, Some(released - sent));
        if i > 20 {
            let err = c.estimate_now(1, released).unwrap() - released;
            worst = worst.max(err.abs());
        }
    }
    assert!(worst < 1e-3, "owner estimate off by {worst} s");
}

/// Hybrid clocks that heard `n` stamps of site 1, 50 ms apart at rate 1 with 0.2 s
/// of transit.
fn hybrid_heard(n: usize) -> PeerClocks {
    let mut c =
        PeerClocks::new(PlayoutLag::Auto).for_strategy(sim_core::sync::SyncStrategy::Hybrid);
    for i in 0..n {
        let wall = i as f64 * 0.05;
        c.heard(1, wall, wall + 0.2, Some(0.2));
    }
    c
}

/// A pose `x` m along x, jaws open by `jaw` rad.
fn at_x(x: f64, jaw: f32) -> [f32; 8] {
    pose_key([x as f32, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], jaw)
}

/// A driven, moving tool's stream of poses makes its site followed; a resting tool's
/// announcements, 0.25 s apart, do not, and neither does a stream of one still pose.
#[test]
fn only_a_moving_tools_stream_makes_its_site_followed() {
    let mut c = PeerClocks::new(PlayoutLag::Auto);
    for k in 0..8 {
        let t = 1.0 + 0.25 * f64::from(k);
        c.tool_pose(1, 0, t, at_x(t, 0.0), t);
    }
    assert!(c.followed(2.75).is_empty(), "announcements only");
    for k in 0..3 {
        let t = 3.0 + 0.008 * f64::from(k);
        c.tool_pose(1, 0, t, at_x(t, 0.0), t);
    }
    assert_eq!(c.followed(3.02).into_iter().collect::<Vec<_>>(), vec![1]);
    // Out of order or repeated: no stream either.
    let mut d = PeerClocks::new(PlayoutLag::Auto);
    d.tool_pose(2, 0, 1.0, at_x(1.0, 0.0), 1.0);
    d.tool_pose(2, 0, 1.0, at_x(1.01, 0.0), 1.01);
    d.tool_pose(2, 0, 0.99, at_x(1.02, 0.0), 1.02);
    assert!(d.followed(1.02).is_empty());
    // Every step, but held still: not followed; the jaws closing alone are motion.
    let mut e = PeerClocks::new(PlayoutLag::Auto);
    for k in 0..50 {
        let t = 1.0 + 0.004 * f64::from(k);
        e.tool_pose(3, 0, t, at_x(0.05, 0.6), t);
    }
    assert!(e.followed(1.2).is_empty(), "a still tool");
    e.tool_pose(3, 0, 1.2, at_x(0.05, 0.55), 1.2);
    assert_eq!(e.followed(1.2).into_iter().collect::<Vec<_>>(), vec![3]);
    assert!(
        e.followed(1.2 + TOOL_ACTIVE_FOR + 0.01).is_empty(),
        "still again"
    );
}

/// A site waiting to start announces a clock that stands still (at 0 here, for a
/// second). Once it runs, its rate is measured between running stamps only, so the
/// wait does not read as a slow clock: its time is estimated exactly. (Measured across
/// the last still stamp, the first running one gave a rate of 0.5 and a smoothed 0.9,
/// and the estimate 0.2 s later was 19 ms short.) Its first step starts a quiet second
/// of its own, although it was first heard long before.
#[test]
fn a_clock_that_stood_still_before_it_started_keeps_its_rate() {
    let mut c = hybrid_heard(200);
    let transit = 0.1;
    // Site 2 waits from wall 10.0 to 11.0, then runs at real time from 11.0.
    for k in 0..20 {
        let sent = 10.0 + 0.05 * f64::from(k);
        c.heard(2, 0.0, sent + transit, Some(transit));
    }
    let base = c.target_lag();
    for k in 1..=3 {
        let sent = 11.0 + 0.05 * f64::from(k);
        c.heard(2, sent - 11.0, sent + transit, Some(transit));
    }
    let now = 11.15 + transit + 0.2;
    let estimate = c.estimate_now(2, now).unwrap();
    assert!(
        (estimate - (now - 11.0)).abs() < 1e-9,
        "site 2 estimated at {estimate} s at wall {now}, running since 11.0"
    );
    // Its first running stamp (wall 11.15) started a quiet second: a long transit
    // then is not taken as the path's, though the site was first heard at 10.1.
    c.heard(2, 0.2, 11.5, Some(0.3));
    assert_eq!(c.target_lag(), base, "quiet after its start");
}

/// A site that appears once the session runs (a rejoin under a new id), or our own
/// link coming back, starts a quiet second: its late samples and long transits carry
/// the gap, not the path, and change neither the lag nor the delay estimate.
#[test]
fn samples_right_after_a_rejoin_do_not_move_the_lag() {
    let mut c = hybrid_heard(200);
    c.tool_heard(1, 10.0);
    let base = c.target_lag();
    // Site 1 rejoins as site 2 at wall 10.0: its first stamps say 0.6 s of transit.
    c.heard(2, 9.4, 10.0, Some(0.6));
    c.tool_heard(2, 10.0);
    c.input_shortfall(1, 0.45, 9.4, 10.1);
    assert_eq!(c.target_lag(), base, "quiet after the rejoin");
    // A second later the new site's samples count again.
    let later = 10.0 + QUIET_AFTER_JOIN_S + 0.05;
    c.heard(2, later - 0.3, later, Some(0.3));
    assert!(
        c.target_lag() > base + 0.005,
        "{} against {base}",
        c.target_lag()
    );
    // Our own link coming back: quiet as well.
    let mut d = hybrid_heard(200);
    d.tool_heard(1, 10.0);
    d.quiet(10.0);
    d.heard(1, 9.5, 10.05, Some(0.55));
    assert_eq!(d.target_lag(), base);
}

/// The inputs' real path is longer than the stamps' transit says: inputs arrive
/// after the follower passed their time. The lag grows at once to cover the shortfall,
/// stays there while the inputs stay late, and comes back down slowly once they arrive in time; early
/// inputs, other strategies and a tool that stopped sending change nothing.
#[test]
fn late_inputs_raise_the_hybrid_lag_which_decays_slowly_once_they_are_in_time() {
    // Stamps say 0.2 s of transit, steady.
    let mut c = hybrid_heard(200);
    c.tool_heard(1, 10.0);
    let base = c.target_lag();
    assert!(
        (base - (0.2 + HYBRID_INPUT_INTERVAL)).abs() < 1e-6,
        "{base}"
    );
    // At wall 10.2 the owner is at 10.0 + 0.2 = about 10.2 s; we are `base` behind.
    let now = 10.2;
    let at = 10.2 - base;
    // Early inputs, and inputs late by no more than the tools are carried on past
    // their newest sample: nothing changes.
    c.input_shortfall(1, -0.05, at, now);
    assert_eq!(c.target_lag(), base);
    c.input_shortfall(1, INPUT_EXTRAPOLATION_S - INPUT_HEADROOM - 1e-3, at, now);
    assert_eq!(c.target_lag(), base);
    // A sample 0.3 s late from a site we do not follow (its tool rests): nothing.
    c.input_shortfall(2, 0.3, at, now);
    assert_eq!(c.target_lag(), base);
    // A sample 0.3 s late: the lag must cover what the carrying on does not, plus
    // the headroom.
    c.input_shortfall(1, 0.3, at, now);
    let raised = c.target_lag();
    let behind = c.estimate_now(1, now).unwrap() - at;
    assert!(
        (raised - (behind + 0.3 - INPUT_EXTRAPOLATION_S + INPUT_HEADROOM)).abs() < 1e-9,
        "raised to {raised}, behind {behind}"
    );
    // In time for 10 s: down by the decay rate, not below the transit-based lag.
    c.input_shortfall(1, -0.1, at + 10.0, now + 10.0);
    let decayed = c.target_lag();
    assert!(
        (decayed - (raised - 10.0 * INPUT_FLOOR_DECAY)).abs() < 1e-9,
        "{decayed}"
    );
    c.input_shortfall(1, -0.1, at + 100.0, now + 100.0);
    assert_eq!(c.target_lag(), base);
    // A sample later than any path (after an outage) is no measure of the path.
    c.input_shortfall(1, MAX_INPUT_SHORTFALL + 0.1, at + 100.0, now + 100.0);
    assert_eq!(c.target_lag(), base);
    // A follower still short of its lag (the session just started: it runs level
    // with the owner) finds every sample late by the path's delay: no measure of
    // the path, nothing changes.
    let mut fresh = hybrid_heard(20);
    fresh.tool_heard(1, 1.15);
    let lag = fresh.target_lag();
    let level = fresh.estimate_now(1, 1.15).unwrap();
    fresh.input_shortfall(1, 0.2, level, 1.15);
    assert_eq!(fresh.target_lag(), lag);
    // Under the keyframe strategy the inputs do not pace the site.
    let mut k = PeerClocks::new(PlayoutLag::Auto);
    k.heard(1, 0.0, 0.2, Some(0.2));
    let before = k.target_lag();
    k.input_shortfall(1, 0.3, 0.0, 0.2);
    assert_eq!(k.target_lag(), before);
}
