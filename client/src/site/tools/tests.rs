//! Unit tests of the site's tools (`super`).

use super::*;
use crate::session::pacing::INPUT_EXTRAPOLATION_S;

fn input(x: f64, jaw: f64) -> ToolInput {
    ToolInput::new(
        V3::new(x, 0.0, 0.0),
        nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, x),
        jaw,
    )
}

/// A driven tool leads only while its input moves it: held still by its script (the
/// demo's trainees before their turn) it does not, from [`LEADS_AFTER_MOTION_S`] after
/// its last motion; the jaws closing alone are motion.
#[test]
fn a_driven_tool_held_still_does_not_make_its_site_lead() {
    let scene = sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = sim_core::SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene, options).unwrap();
    let dt = sim.options().dt;
    let mut tools = Tools::new(&sim, &["forceps".into()], SyncStrategy::Hybrid).unwrap();
    let i = tools.local_index().unwrap();
    let rest = ToolInput {
        pose: *tools.interaction.tools.tools[i].pose(),
        jaw: tools.interaction.tools.tools[i].jaw(),
    };
    let drive = |tools: &mut Tools, input: &ToolInput, t: f64| {
        tools.note_local_motion(Some(input), t);
        tools.note_local_input(true, t);
        tools.interaction.tools.tools[i].set_input(input, dt);
    };
    for k in 0..100 {
        let t = f64::from(k) * dt;
        drive(&mut tools, &rest, t);
        assert!(
            tools.local_active() && !tools.local_moving(t),
            "still at {t} s"
        );
    }
    let closing = ToolInput {
        jaw: rest.jaw + 0.05,
        ..rest
    };
    let t = 100.0 * dt;
    drive(&mut tools, &closing, t);
    assert!(tools.local_moving(t), "the jaws moved");
    assert!(tools.local_moving(t + LEADS_AFTER_MOTION_S - dt));
    drive(&mut tools, &closing, t + dt);
    assert!(
        !tools.local_moving(t + LEADS_AFTER_MOTION_S + dt),
        "still again"
    );
    tools.note_local_input(false, t + 2.0 * dt);
    assert!(!tools.local_moving(t + 2.0 * dt), "not driven");
}

/// A follower waits for one late sample at most [`MAX_INPUT_WAIT_S`] of session time,
/// then carries the tool on; a newer sample that is still late starts a new wait;
/// nothing awaited, no wait.
#[test]
fn a_late_input_is_waited_for_at_most_the_longest_wait_per_sample() {
    let t0 = Instant::now();
    let at = |s: f64| t0 + std::time::Duration::from_secs_f64(s);
    let mut wait = InputWait::default();
    assert_eq!(wait.waits(None, t0), None);
    // The newest sample at 2.0 s; the step needs 2.1 s: 100 ms short.
    assert_eq!(wait.waits(Some((0.1, (0, 2.0))), at(0.0)), Some(0.1));
    assert_eq!(
        wait.waits(Some((0.1, (0, 2.0))), at(MAX_INPUT_WAIT_S - 0.001)),
        Some(0.1),
        "still within the wait"
    );
    assert_eq!(
        wait.waits(Some((0.1, (0, 2.0))), at(MAX_INPUT_WAIT_S + 0.001)),
        None,
        "waited long enough: carried on"
    );
    assert_eq!(
        wait.waits(Some((0.1, (0, 2.0))), at(1.0)),
        None,
        "not again"
    );
    // Another tool whose newest sample has the same time has a wait of its own.
    assert_eq!(wait.waits(Some((0.1, (1, 2.0))), at(1.0)), Some(0.1));
    // A newer sample arrives, still short of the step: a new wait.
    assert_eq!(wait.waits(Some((0.05, (0, 2.06))), at(2.0)), Some(0.05));
    assert_eq!(
        wait.waits(Some((0.05, (0, 2.06))), at(2.0 + MAX_INPUT_WAIT_S + 0.001)),
        None
    );
}

/// Only a sample newer than every sample of its track measures lateness: the older
/// ones a datagram repeats (handed over after its newest) fill gaps, however late.
#[test]
fn only_a_tracks_newest_sample_measures_lateness() {
    let scene = sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = sim_core::SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene, options).unwrap();
    // No instrument of our own: every tool is simulated from the others' samples.
    let mut tools = Tools::new(&sim, &[], SyncStrategy::Hybrid).unwrap();
    let sample = |t: f64| proto::ToolPose {
        site: 8,
        tool: 0,
        sim_time_s: t,
        position: [0.0; 3],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.1,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    };
    // The stream starts (no lateness at its first step), then runs.
    assert_eq!(tools.remote_pose(&sample(1.0), 1.0), None);
    assert_eq!(tools.remote_pose(&sample(1.004), 1.004), Some(0.0));
    // A datagram after a burst, newest first: 1.2 is late by 10 ms; the older samples
    // it repeats (1.1, 1.16) fill the gap and say nothing of the path.
    let late = tools.remote_pose(&sample(1.2), 1.21).unwrap();
    assert!((late - 0.01).abs() < 1e-12, "{late}");
    assert_eq!(tools.remote_pose(&sample(1.16), 1.21), None);
    assert_eq!(tools.remote_pose(&sample(1.1), 1.21), None);
    // A repeat of the newest is no news either.
    assert_eq!(tools.remote_pose(&sample(1.2), 1.22), None);
}

/// A tool this site drove keeps announcing its resting pose every
/// `IDLE_POSE_INTERVAL_S` until another site drives it; a tool never driven here is
/// not announced.
#[test]
fn a_resting_tool_is_announced_until_another_site_drives_it() {
    let scene = sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = sim_core::SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene, options).unwrap();
    let mut tools = Tools::new(&sim, &["forceps".into()], SyncStrategy::Hybrid).unwrap();
    let me = 7;
    let sent = |tools: &mut Tools, t: f64| tools.local_pose_message(me, t).is_some();
    assert!(
        !sent(&mut tools, 0.5),
        "never driven here: nothing to announce"
    );
    tools.note_local_input(true, 1.0);
    assert!(sent(&mut tools, 1.0), "driven: every step");
    tools.note_local_input(false, 1.004);
    let announced: Vec<f64> = (0..=200)
        .map(|k| 1.004 + 0.004 * f64::from(k))
        .filter(|&t| sent(&mut tools, t))
        .collect();
    assert_eq!(announced.len(), 3, "{announced:?}");
    // The first one interval after the last driven step, then one per interval (each
    // at the first step past its time).
    let mut due = 1.0 + IDLE_POSE_INTERVAL_S;
    for t in &announced {
        assert!(*t >= due - 1e-9 && *t < due + 0.004 + 1e-9, "{announced:?}");
        due = t + IDLE_POSE_INTERVAL_S;
    }
    let pose = tools.local_pose_message(me, 9.0).unwrap();
    assert_eq!((pose.site, pose.sim_time_s), (me, 9.0));
    // Another site takes the forceps: we stop telling where it rests.
    let mut theirs = pose;
    theirs.site = 8;
    tools.remote_pose(&theirs, 9.1);
    assert!(!sent(&mut tools, 20.0));
}

/// The samples handled at the step a remote tool's stream starts or resumes after a
/// gap (one datagram carries several) are no measure of the path: no lateness; the
/// next step's are.
#[test]
fn a_streams_first_datagram_reports_no_lateness() {
    let scene = sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = sim_core::SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene, options).unwrap();
    // No instrument of our own: every tool is simulated from the others' samples.
    let mut tools = Tools::new(&sim, &[], SyncStrategy::Hybrid).unwrap();
    let mut theirs = proto::ToolPose {
        site: 8,
        tool: 0,
        sim_time_s: 9.0,
        position: [0.0; 3],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.1,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    };
    assert_eq!(tools.remote_pose(&theirs, 9.1), None, "first sample");
    theirs.sim_time_s = 9.004;
    assert_eq!(tools.remote_pose(&theirs, 9.1), None, "same datagram");
    theirs.sim_time_s = 9.008;
    assert!((tools.remote_pose(&theirs, 9.104).unwrap() - 0.096).abs() < 1e-12);
    theirs.sim_time_s = 9.9;
    assert_eq!(tools.remote_pose(&theirs, 9.95), None, "after a gap");
    theirs.sim_time_s = 9.904;
    assert_eq!(tools.remote_pose(&theirs, 9.95), None, "same datagram");
    theirs.sim_time_s = 9.908;
    assert!(
        tools.remote_pose(&theirs, 9.96).is_some(),
        "the next step counts"
    );
}

/// The bodies scene's instructor: forceps, clip applier and blade, one hand. The
/// instrument in hand follows the script's tracks (each taken as its track begins,
/// the last kept between tracks); the window's `T` cycles them in scene order; only the
/// instrument in hand is sent to the others.
#[test]
fn instruments_are_exchanged_as_their_tracks_begin() {
    let scene = sim_core::sim_scene::builtin::cholecystectomy_bodies();
    let options = sim_core::SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene.clone(), options).unwrap();
    let names = ["forceps", "clip applier", "blade"].map(String::from);
    let mut tools = Tools::new(&sim, &names, SyncStrategy::Hybrid).unwrap();
    let index = |n: &str| tools.interaction.tools.index(n).unwrap();
    let (forceps, applier, blade) = (index("forceps"), index("clip applier"), index("blade"));
    let mut script = ToolScript::default();
    for n in &names {
        script
            .tracks
            .insert(n.clone(), scene.scripts[n].tracks[n].clone());
    }
    assert_eq!(
        tools.local_index(),
        Some(forceps),
        "the first in hand at the start"
    );
    let held = |tools: &mut Tools, t: f64| {
        let input = tools.local_input(Some(&script), t);
        (tools.local_index(), input.is_some())
    };
    assert_eq!(held(&mut tools, 1.0), (Some(forceps), true));
    assert_eq!(held(&mut tools, 11.0), (Some(applier), true));
    // Between the applier's track (to 13 s) and the blade's (from 15.5 s): nothing
    // driven, the applier stays in hand.
    assert_eq!(held(&mut tools, 14.0), (Some(applier), false));
    assert_eq!(held(&mut tools, 16.0), (Some(blade), true));
    // The input is the track of the tool in hand, not another's.
    let at = tools.local_input(Some(&script), 16.0).unwrap();
    let expect = script.sample("blade", 16.0).unwrap();
    assert!((at.pose.translation.vector - expect.position).norm() < 1e-12);
    // `T` in scene order: forceps (0) → clip applier → blade → forceps.
    let mut order = [forceps, applier, blade];
    order.sort_unstable();
    tools.local = Some(order[0]);
    let cycled: Vec<usize> = (0..3)
        .map(|_| {
            tools.next_instrument().unwrap();
            tools.local_index().unwrap()
        })
        .collect();
    assert_eq!(cycled, vec![order[1], order[2], order[0]]);
    // One instrument: nothing to exchange.
    let mut one = Tools::new(&sim, &names[..1], SyncStrategy::Hybrid).unwrap();
    assert!(one.next_instrument().is_none());
    // An unknown tool is refused with its name.
    let err = Tools::new(&sim, &["scalpel".into()], SyncStrategy::Hybrid)
        .err()
        .unwrap();
    assert!(err.to_string().contains("scalpel"), "{err}");
}

#[test]
fn pose_track_samples_by_simulated_time() {
    let mut track = PoseTrack::default();
    assert!(track.sample(0.0).is_none());
    // Out of order, as datagrams may arrive.
    track.insert(0.2, input(0.2, 0.4));
    track.insert(0.1, input(0.1, 0.2));
    let mid = track.sample(0.15).unwrap();
    assert!((mid.pose.translation.vector.x - 0.15).abs() < 1e-12);
    assert!((mid.jaw - 0.3).abs() < 1e-12);
    assert!((mid.pose.rotation.angle() - 0.15).abs() < 1e-9);
    // Before the first pose: the first one (hold).
    assert_eq!(track.sample(0.0).unwrap().jaw, 0.2);
    // After the newest, when the last two are 0.1 s apart (too far to give a rate):
    // the newest, held.
    assert_eq!(track.sample(9.0).unwrap().jaw, 0.4);
    // Per-step samples: carried on at the last rate (x and jaw rise 1 and 2 per s)
    // for at most INPUT_EXTRAPOLATION_S, the orientation held.
    let mut steps = PoseTrack::default();
    steps.insert(0.000, input(0.000, 0.200));
    steps.insert(0.004, input(0.004, 0.208));
    let ahead = steps.sample(0.010).unwrap();
    assert!((ahead.pose.translation.vector.x - 0.010).abs() < 1e-12);
    assert!((ahead.jaw - 0.220).abs() < 1e-12);
    assert!((ahead.pose.rotation.angle() - 0.004).abs() < 1e-9);
    let far = steps.sample(9.0).unwrap();
    let x_max = 0.004 + INPUT_EXTRAPOLATION_S;
    assert!((far.pose.translation.vector.x - x_max).abs() < 1e-12);
    // A closing jaw stops at 0.
    let mut closing = PoseTrack::default();
    closing.insert(0.00, input(0.0, 0.02));
    closing.insert(0.01, input(0.0, 0.01));
    assert_eq!(closing.sample(0.04).unwrap().jaw, 0.0);
    // Old poses are dropped beyond the kept window.
    track.insert(5.0, input(5.0, 1.0));
    assert_eq!(track.poses.len(), 2);
}
