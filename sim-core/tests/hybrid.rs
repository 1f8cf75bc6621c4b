//! The hybrid strategy's follower: blended corrections towards the owner's keyframes,
//! keyframes that agree to the wire's rounding, and sites that show keyframes instead of
//! simulating (with owners that then send on drift).

use cosurg_sim_core::sync::*;
use cosurg_sim_core::{NodeId, Simulation};

mod common;
use common::{TIP, V3, beam, beam_map, tip_nodes};

/// Pushes the tip up with `newtons` spread over `nodes`.
fn push_tip(sim: &mut Simulation, nodes: &[NodeId], newtons: f64) {
    for &n in nodes {
        sim.add_force(n, V3::new(0.0, newtons, 0.0) / nodes.len() as f64);
    }
}

/// Two equal beams, `a` pushed at the tip for `steps` steps and `b` not.
fn pushed_and_not(steps: usize) -> (Simulation, Simulation, RegionMap) {
    let mut a = beam();
    let mut b = beam();
    let map = beam_map(&a);
    let loaded = tip_nodes(&a, &map, 0.37);
    for _ in 0..steps {
        push_tip(&mut a, &loaded, 20.0);
        a.step().unwrap();
        b.step().unwrap();
    }
    (a, b, map)
}

/// Hybrid: a keyframe of another site's simulation is not taken over at once but spread
/// over steps, each moving no node by more than `max_step_m`, and ends on the keyframe's
/// state (here with no physics in between, so the end state is the keyframe's exactly).
#[test]
fn hybrid_correction_is_bounded_per_step_and_reaches_the_keyframe() {
    let (a, mut b, map) = pushed_and_not(30);
    let kf = encode_keyframe(&a, &map, TIP, 1).unwrap();
    let config = HybridConfig {
        max_step_m: 1e-4,
        min_steps: 4,
        ..HybridConfig::default()
    };
    let mut region = CorrectedRegion::new(TIP, config);
    let Correction::Started { steps, max_m } = region
        .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
        .unwrap()
    else {
        panic!("no correction started");
    };
    assert!(
        max_m > 1e-3,
        "the load moved a's tip away from b's ({max_m} m)"
    );
    assert_eq!(steps, (max_m / 1e-4).ceil() as u32);
    let nodes = map.canonical_nodes(b.lattice(), TIP);
    for _ in 0..steps {
        let before: Vec<V3> = nodes.iter().map(|n| b.positions()[n.0 as usize]).collect();
        let reported = region.drive(&mut b);
        assert!(reported <= 1e-4 * (1.0 + 1e-12), "{reported} m in one step");
        for (i, n) in nodes.iter().enumerate() {
            let moved = (b.positions()[n.0 as usize] - before[i]).norm();
            assert!(
                moved <= 1e-4 * (1.0 + 1e-9),
                "node {i} moved {moved} m in one step"
            );
        }
    }
    assert_eq!(region.steps_left(), 0);
    for (i, n) in nodes.iter().enumerate() {
        if b.is_fixed(*n) {
            continue;
        }
        let d = (b.positions()[n.0 as usize] - V3::from(kf.positions[i])).norm();
        assert!(d < 1e-9, "node {i} ends {d} m from the keyframe");
    }
    // Nothing more is added once the correction has run out; stale keyframes are ignored.
    assert_eq!(region.drive(&mut b), 0.0);
    assert_eq!(
        region
            .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
            .unwrap(),
        Correction::Stale
    );
}

/// Hybrid: a keyframe older than `max_age_s` at the local clock is skipped; a keyframe
/// slightly in the local clock's past is advanced by its velocity.
#[test]
fn hybrid_skips_stale_keyframes_and_advances_recent_ones() {
    let mut a = beam();
    let mut b = beam();
    let map = beam_map(&a);
    let mut kf = encode_keyframe(&a, &map, TIP, 1).unwrap();
    let u = V3::new(0.0, 0.0, 0.01);
    for v in &mut kf.velocities {
        *v = u.into();
    }
    let config = HybridConfig::default();
    let mut region = CorrectedRegion::new(TIP, config);
    b.set_time(kf.sim_time + config.max_age_s + 0.01);
    assert_eq!(
        region
            .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
            .unwrap(),
        Correction::TooOld
    );
    kf.keyframe_id = 2;
    b.set_time(kf.sim_time + 0.05);
    a.set_time(kf.sim_time);
    let Correction::Started { max_m, .. } = region
        .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
        .unwrap()
    else {
        panic!("no correction started");
    };
    // Equal states, 50 ms ahead at 1 cm/s: every free node is corrected by 0.5 mm.
    assert!((max_m - 5e-4).abs() < 1e-12, "{max_m}");
}

/// Rounds a keyframe's node states as proto's default quantisation does (10 µm, 0.1 mm/s
/// steps; the origin is itself a multiple of the step).
fn rounded(kf: &RegionKeyframe) -> RegionKeyframe {
    let round = |v: &[f64; 3], step: f64| v.map(|x| (x / step).round() * step);
    RegionKeyframe {
        positions: kf.positions.iter().map(|p| round(p, 1e-5)).collect(),
        velocities: kf.velocities.iter().map(|v| round(v, 1e-4)).collect(),
        ..kf.clone()
    }
}

/// Equal simulations: a keyframe that differs from the local state by the wire's rounding
/// only starts no correction (correcting it would nudge equal sites apart: measured on
/// `lan`, 0.13–0.21 mm of divergence against input-only's 0.00). A real difference does,
/// and a later agreeing keyframe drops the correction under way.
#[test]
fn a_keyframe_equal_but_for_rounding_starts_no_correction() {
    let (a, mut b, map) = pushed_and_not(30);
    let mut same = beam();
    for _ in 0..30 {
        same.step().unwrap();
    }
    let mut region = CorrectedRegion::new(TIP, HybridConfig::default());
    let mut kf = rounded(&encode_keyframe(&same, &map, TIP, 1).unwrap());
    let before: Vec<V3> = b.positions().to_vec();
    match region
        .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
        .unwrap()
    {
        Correction::Agrees { max_m } => assert!(max_m <= 1e-5, "{max_m} m"),
        other => panic!("rounding alone started {other:?}"),
    }
    assert_eq!(region.drive(&mut b), 0.0);
    assert_eq!(b.positions(), &before[..], "nothing moved");
    assert_eq!(region.corrections(), 0);

    let moved = rounded(&encode_keyframe(&a, &map, TIP, 2).unwrap());
    let Correction::Started { max_m, .. } = region
        .apply_keyframe(&mut b, &map, &moved, &StateHistory::default())
        .unwrap()
    else {
        panic!("a pushed tip started no correction");
    };
    assert!(max_m > 1e-3, "{max_m} m");
    assert!(region.drive(&mut b) > 0.0);
    assert!(region.steps_left() > 0);

    // The local state now agrees with a newer keyframe (the owner came back to it): the
    // rest of the correction is dropped.
    kf.keyframe_id = 3;
    let nodes = map.canonical_nodes(b.lattice(), TIP);
    kf.positions = nodes
        .iter()
        .map(|n| b.positions()[n.0 as usize].into())
        .collect();
    kf.velocities = nodes
        .iter()
        .map(|n| b.velocities()[n.0 as usize].into())
        .collect();
    kf.sim_time = b.time();
    let kf = rounded(&kf);
    assert!(matches!(
        region
            .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
            .unwrap(),
        Correction::Agrees { .. }
    ));
    assert_eq!(region.steps_left(), 0);
    assert_eq!(region.drive(&mut b), 0.0);
}

/// A hybrid site that shows keyframes takes another site's keyframe over as a keyframe
/// receiver does (here snapped: the region's nodes are the keyframe's at once), where a
/// simulating hybrid site only starts a blended correction.
#[test]
fn a_hybrid_site_that_shows_keyframes_takes_them_over() {
    let snap = SyncConfig {
        blend_window_s: 0.0,
        ..SyncConfig::default()
    };
    let (a, mut b1, map) = pushed_and_not(30);
    let (_, mut b2, _) = pushed_and_not(30);
    let kf = encode_keyframe(&a, &map, TIP, 1).unwrap();
    let frame = SyncFrame::Keyframe(kf.clone());
    let nodes = map.canonical_nodes(b1.lattice(), TIP);
    let largest_gap = |sim: &Simulation| {
        nodes
            .iter()
            .zip(&kf.positions)
            .map(|(n, p)| (sim.positions()[n.0 as usize] - V3::from(*p)).norm())
            .fold(0.0, f64::max)
    };

    let mut shows = SiteSync::new(SyncStrategy::Hybrid, map.clone(), snap);
    shows.show_keyframes(true);
    assert!(shows.shows_keyframes());
    assert_eq!(shows.on_frame(&mut b1, &frame).unwrap(), Some(1));
    shows.before_step(&mut b1);
    assert!(shows.remote(TIP).is_some() && shows.corrected(TIP).is_none());
    assert!(largest_gap(&b1) < 1e-12, "{} m", largest_gap(&b1));

    let mut simulates = SiteSync::new(SyncStrategy::Hybrid, map.clone(), snap);
    assert!(!simulates.shows_keyframes());
    assert_eq!(simulates.on_frame(&mut b2, &frame).unwrap(), Some(1));
    simulates.before_step(&mut b2);
    assert!(simulates.remote(TIP).is_none() && simulates.corrected(TIP).is_some());
    assert!(largest_gap(&b2) > 1e-4, "{} m", largest_gap(&b2));

    // Only hybrid has the choice: under keyframe sync every site shows keyframes.
    let mut input_only = SiteSync::new(SyncStrategy::InputOnly, map, snap);
    input_only.show_keyframes(true);
    assert!(!input_only.shows_keyframes());
}

/// A hybrid owner sends on its heartbeat only, until a follower says it shows keyframes:
/// then also whenever the region departs from the receivers' dead reckoning.
#[test]
fn a_hybrid_owner_sends_on_drift_once_a_follower_shows_keyframes() {
    let count = |told: bool| {
        let mut a = beam();
        let map = beam_map(&a);
        let loaded = tip_nodes(&a, &map, 0.37);
        let mut owner = SiteSync::new(SyncStrategy::Hybrid, map, SyncConfig::default());
        owner.on_grant(TIP);
        if told {
            assert!(owner.follower_shows_keyframes());
            assert!(
                !owner.follower_shows_keyframes(),
                "only the first tells anything"
            );
            let policy = owner.policy.config();
            assert_eq!(
                policy.drift_threshold_m,
                SyncConfig::default().drift_threshold_m
            );
            assert_eq!(
                policy.min_interval_s,
                HybridConfig::default().shown_min_interval_s
            );
        }
        for k in 0..100 {
            // A push that comes and goes: no constant-acceleration extrapolation holds.
            push_tip(
                &mut a,
                &loaded,
                if (k / 10) % 2 == 0 { 40.0 } else { -40.0 },
            );
            a.step().unwrap();
            owner.after_step(&a, |_| None);
        }
        *owner.policy.counters()
    };
    let heartbeat_only = count(false);
    let told = count(true);
    assert_eq!(heartbeat_only.by_drift, 0, "{heartbeat_only:?}");
    assert!(told.by_drift >= 5, "{told:?}");
    assert!(
        told.keyframes > heartbeat_only.keyframes,
        "{told:?} {heartbeat_only:?}"
    );
}

/// Equal simulations in accelerating motion: a keyframe that arrives three steps late is
/// compared with the local state at its time (the history) and agrees. Advanced by its
/// velocity instead (no history), it is off by about ½ a Δt² in position and a Δt in
/// velocity, and starts a correction that would nudge the equal simulations apart.
#[test]
fn a_late_keyframe_is_compared_with_the_local_state_at_its_time() {
    let mut a = beam();
    let mut b = beam();
    let map = beam_map(&a);
    let loaded = tip_nodes(&a, &map, 0.37);
    let mut history = StateHistory::default();
    for _ in 0..10 {
        push_tip(&mut a, &loaded, 20.0);
        a.step().unwrap();
        push_tip(&mut b, &loaded, 20.0);
        history.record(&b, 0.2, false);
        b.step().unwrap();
    }
    let kf = rounded(&encode_keyframe(&a, &map, TIP, 1).unwrap());
    for _ in 0..3 {
        push_tip(&mut b, &loaded, 20.0);
        history.record(&b, 0.2, false);
        b.step().unwrap();
    }
    assert!(b.time() > kf.sim_time + 2.5 * b.options().dt);
    let mut region = CorrectedRegion::new(TIP, HybridConfig::default());
    match region.apply_keyframe(&mut b, &map, &kf, &history).unwrap() {
        Correction::Agrees { max_m } => assert!(max_m <= 1e-5, "{max_m} m"),
        other => panic!("a late keyframe of an equal simulation started {other:?}"),
    }
    let mut without = CorrectedRegion::new(TIP, HybridConfig::default());
    assert!(
        matches!(
            without
                .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
                .unwrap(),
            Correction::Started { .. }
        ),
        "the tip does not accelerate enough for the test to tell"
    );
    // A correction under way since the keyframe's time moved nodes after the recorded
    // states (its shares are not in them): the history is not used, and the keyframe is
    // advanced by its velocity as without one.
    let mut marked = history.clone();
    marked.record(&b, 0.2, true);
    let mut after = CorrectedRegion::new(TIP, HybridConfig::default());
    assert!(matches!(
        after.apply_keyframe(&mut b, &map, &kf, &marked).unwrap(),
        Correction::Started { .. }
    ));
}

/// A keyframe older than `max_age_s` (a still owner that keeps the playout lag behind a
/// moving site sends keyframes a path's delay old) is still compared with the local state
/// at its time when the history holds it, and the difference it finds there is the one
/// the two simulations had then; without the history, or older than
/// `max_history_age_s`, it is skipped.
#[test]
fn an_old_keyframe_is_used_through_the_history_and_skipped_without_it() {
    let config = HybridConfig::default();
    let (mut a, mut b) = (beam(), beam());
    let map = beam_map(&a);
    let loaded = tip_nodes(&a, &map, 0.37);
    let keep = config.max_history_age_s + b.options().dt;
    let mut history = StateHistory::default();
    for _ in 0..20 {
        push_tip(&mut a, &loaded, 20.0);
        a.step().unwrap();
        history.record(&b, keep, false);
        b.step().unwrap();
    }
    // The keyframe of the pushed beam, and the difference the two had at its time.
    let kf = encode_keyframe(&a, &map, TIP, 1).unwrap();
    let nodes = map.canonical_nodes(b.lattice(), TIP);
    // Per free node, the difference the beams had at the keyframe's time.
    let gaps: Vec<(usize, V3)> = nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| !b.is_fixed(**n))
        .map(|(i, n)| {
            (
                n.0 as usize,
                V3::from(kf.positions[i]) - b.positions()[n.0 as usize],
            )
        })
        .collect();
    let then = gaps.iter().map(|(_, d)| d.norm()).fold(0.0, f64::max);
    assert!(then > 1e-3, "the push moved a's tip ({then} m)");
    // The local clock runs on past `max_age_s` (both beams settle meanwhile).
    while b.time() < kf.sim_time + config.max_age_s + 0.1 {
        history.record(&b, keep, false);
        b.step().unwrap();
    }
    let mut region = CorrectedRegion::new(TIP, config);
    assert_eq!(
        region
            .apply_keyframe(&mut b, &map, &kf, &StateHistory::default())
            .unwrap(),
        Correction::TooOld,
        "without the history"
    );
    // A correction under way since the keyframe's time: its shares are not in the
    // recorded states, so the old keyframe is skipped.
    let mut marked = history.clone();
    marked.record(&b, keep, true);
    let mut region = CorrectedRegion::new(TIP, config);
    assert_eq!(
        region.apply_keyframe(&mut b, &map, &kf, &marked).unwrap(),
        Correction::TooOld
    );
    let mut region = CorrectedRegion::new(TIP, config);
    let steps = match region.apply_keyframe(&mut b, &map, &kf, &history).unwrap() {
        Correction::Started { max_m, steps } => {
            assert!(
                (max_m - then).abs() < 1e-6 * then,
                "measured {max_m} m at the keyframe's time, the beams differed by {then} m"
            );
            steps
        }
        other => panic!("an old keyframe with the history at its time gave {other:?}"),
    };
    // The correction adds exactly that difference (its velocity difference, of 0.25 s
    // ago, is not carried), with no physics in between.
    let before: Vec<V3> = b.positions().to_vec();
    let velocities: Vec<V3> = b.velocities().to_vec();
    for _ in 0..steps {
        region.drive(&mut b);
    }
    for (j, gap) in &gaps {
        let moved = b.positions()[*j] - before[*j];
        assert!(
            (moved - gap).norm() < 1e-12,
            "node {j} moved {moved:?}, the gap was {gap:?}"
        );
        assert!((b.velocities()[*j] - velocities[*j]).norm() < 1e-12);
    }
    // Older than `max_history_age_s` (the age limit; the history's own eviction is not
    // what skips it here).
    b.set_time(kf.sim_time + config.max_history_age_s + 0.01);
    let mut region = CorrectedRegion::new(TIP, config);
    assert_eq!(
        region.apply_keyframe(&mut b, &map, &kf, &history).unwrap(),
        Correction::TooOld
    );
}
