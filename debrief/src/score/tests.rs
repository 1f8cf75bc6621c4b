use super::*;
use std::f64::consts::PI;

const RATE: f64 = 250.0;

fn sampled(t_end: f64, f: impl Fn(f64) -> P3) -> (Vec<f64>, Vec<P3>) {
    let n = (t_end * RATE).round() as usize;
    let times: Vec<f64> = (0..=n).map(|i| i as f64 / RATE).collect();
    let p = times.iter().map(|&t| f(t)).collect();
    (times, p)
}

/// Quantises to 1 µm as the recording does.
fn quantised(p: &[P3]) -> Vec<P3> {
    p.iter()
        .map(|x| x.map(|c| (c * 1e6).round() * 1e-6))
        .collect()
}

#[test]
fn straight_line_has_economy_one() {
    // 8 cm along a skew direction in 2 s, constant speed.
    let d = [0.03, -0.02, 0.07];
    let (t, p) = sampled(2.0, |t| d.map(|c| c * t / 2.0));
    let e = economy(&p).unwrap();
    assert!((e - 1.0).abs() < 1e-12, "economy {e}");
    assert!((path_length(&p) - norm(d)).abs() < 1e-12);
    // Through the measure pipeline (filtered, quantised positions) it stays 1 to 1e-4.
    let track = track_of(&t, &quantised(&p));
    let act = &find_acts(&track, &[], &ScoreSettings::default())[0];
    let m = measure(&track, act, &[], &ScoreSettings::default());
    assert!((m.economy.unwrap() - 1.0).abs() < 1e-4, "{:?}", m.economy);
}

#[test]
fn circle_path_length_is_two_pi_r() {
    let r = 0.03;
    // One turn in 4 s: the 10 Hz filter passes 0.25 Hz unchanged.
    let (t, p) = sampled(4.0, |t| {
        let a = 2.0 * PI * t / 4.0;
        [r * a.cos(), r * a.sin(), 0.01]
    });
    let exact = 2.0 * PI * r;
    let raw = path_length(&p);
    // Chords of 1000 segments: relative error (2π/1000)²/24 ≈ 1.6e-6.
    assert!((raw - exact).abs() / exact < 1e-5, "{raw} vs {exact}");
    let track = track_of(&t, &quantised(&p));
    let s = ScoreSettings::default();
    let act = &find_acts(&track, &[], &s)[0];
    let m = measure(&track, act, &[], &s);
    assert!(
        (m.path_length_m - exact).abs() / exact < 1e-3,
        "{} vs {exact}",
        m.path_length_m
    );
    // Closed path: economy undefined.
    assert!(m.economy.is_none());
}

/// x(t) = D (10τ³ − 15τ⁴ + 6τ⁵): peak speed 1.875 D/T, ∫ jerk² = 720 D²/T⁵, so
/// DLJ = T³/v_peak² · 720 D²/T⁵ = 720/1.875² = 204.8.
fn min_jerk(d: P3, big_t: f64) -> impl Fn(f64) -> P3 {
    move |t| {
        let u = (t / big_t).clamp(0.0, 1.0);
        let s = 10.0 * u.powi(3) - 15.0 * u.powi(4) + 6.0 * u.powi(5);
        d.map(|c| c * s)
    }
}

#[test]
fn minimum_jerk_ldlj_matches_closed_form() {
    let expected = -(720.0f64 / (1.875 * 1.875)).ln();
    assert!((expected + 5.3221).abs() < 1e-4);
    let (t, p) = sampled(1.0, min_jerk([0.05, 0.02, -0.01], 1.0));
    // Independent check of the closed form: fine numerical integration of the analytic
    // jerk 60 D/T³ (1 − 6τ + 6τ²).
    let n = 100_000;
    let integral: f64 = (0..n)
        .map(|i| {
            let u = (i as f64 + 0.5) / n as f64;
            (60.0 * (1.0 - 6.0 * u + 6.0 * u * u)).powi(2) / n as f64
        })
        .sum();
    assert!((integral - 720.0).abs() < 1e-6, "{integral}");
    let got = ldlj(&t, &quantised(&p), 10.0).unwrap();
    assert!((got - expected).abs() < 0.05, "LDLJ {got} vs {expected}");
    // A jerky movement (the same reach with a 6 Hz tremor of 0.3 mm) scores lower.
    let (t2, p2) = sampled(1.0, |t| {
        let base = min_jerk([0.05, 0.02, -0.01], 1.0)(t);
        [
            base[0],
            base[1] + 3e-4 * (2.0 * PI * 6.0 * t).sin(),
            base[2],
        ]
    });
    let jerky = ldlj(&t2, &quantised(&p2), 10.0).unwrap();
    assert!(jerky < got - 1.0, "jerky {jerky} vs smooth {got}");
}

#[test]
fn dtw_of_a_path_with_itself_is_zero_and_with_a_time_shifted_copy_near_zero() {
    let path = |t: f64| {
        let a = PI * t;
        [0.04 * a.cos(), 0.02 * (2.0 * a).sin(), 0.01 * t]
    };
    let (t, p) = sampled(2.0, path);
    let band = 100;
    let a = resample(&t, &p, 500);
    assert_eq!(dtw_mean_distance(&a, &a, band), Some(0.0));
    // The same movement starting 0.2 s later (held still before), over 2.2 s.
    let (ts, ps) = sampled(2.2, |t| path((t - 0.2).max(0.0)));
    let b = resample(&ts, &ps, 500);
    let d = dtw_mean_distance(&a, &b, band).unwrap();
    // Lock-step distance for comparison: what DTW removes.
    let lockstep: f64 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| norm(sub(*x, *y)))
        .sum::<f64>()
        / 500.0;
    assert!(d < 2e-4, "DTW {d} m");
    assert!(lockstep > 20.0 * d, "lock-step {lockstep} m vs DTW {d} m");
    // A different path is far.
    let c: Vec<P3> = a.iter().map(|x| [x[0], x[1] + 0.01, x[2]]).collect();
    let far = dtw_mean_distance(&a, &c, band).unwrap();
    // DTW may warp along the path towards the copy but never beyond the lock-step 10 mm.
    assert!(far > 0.005 && far <= 0.01 + 1e-12, "offset path {far}");
}

#[test]
fn idle_time_of_a_known_pause() {
    // Move 3 cm in 1 s (min-jerk), hold for 1.5 s, move back in 1 s.
    let go = min_jerk([0.03, 0.0, 0.0], 1.0);
    let (t, p) = sampled(3.5, |t| {
        if t <= 2.5 {
            go(t)
        } else {
            let b = go(t - 2.5);
            [0.03 - b[0], 0.0, 0.0]
        }
    });
    let idle = idle_time(&t, &quantised(&p), 0.005, 10.0);
    // A min-jerk reach has v/v_peak = 16 τ²(1−τ)², v_peak = 1.875 · 30 mm / 1 s =
    // 56.25 mm/s, so it is below 5 mm/s while τ(1−τ) < sqrt(5 / 56.25 / 16): the first
    // and last τ* of each reach. Four such ends plus the 1.5 s pause.
    let c = (5.0f64 / 56.25 / 16.0).sqrt();
    let tau = (1.0 - (1.0 - 4.0 * c).sqrt()) / 2.0;
    assert!((tau - 0.0811).abs() < 1e-4);
    let expected = 1.5 + 4.0 * tau;
    assert!((idle - expected).abs() < 0.02, "idle {idle} vs {expected}");
}

#[test]
fn depth_along_shaft_counts_only_axial_motion() {
    // Shaft along world +z for the identity; move 2 cm along z and 5 cm along x.
    let s = |p: P3| ToolState {
        position: p,
        orientation: [1.0, 0.0, 0.0, 0.0],
        ..ToolState::default()
    };
    let states = [s([0.0; 3]), s([0.05, 0.0, 0.0]), s([0.05, 0.0, 0.02])];
    assert!((depth_along_shaft(&states) - 0.02).abs() < 1e-12);
    // Rotated 90° about y: the shaft lies along +x.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let axis = shaft_axis([h, 0.0, h, 0.0]);
    assert!((axis[0] - 1.0).abs() < 1e-12 && axis[1].abs() < 1e-12 && axis[2].abs() < 1e-12);
}

#[test]
fn acts_from_grasp_and_contact() {
    let n = 1000;
    let times: Vec<f64> = (0..n).map(|i| i as f64 / RATE).collect();
    let states: Vec<ToolState> = (0..n)
        .map(|i| ToolState {
            position: [i as f64 * 1e-5, 0.0, 0.0],
            orientation: [1.0, 0.0, 0.0, 0.0],
            grasped: u32::from((300..600).contains(&i)),
            contact_force: if (20..120).contains(&i) || (280..300).contains(&i) {
                [0.0, 0.0, 0.5]
            } else {
                [0.0; 3]
            },
            grasp_force: if (300..600).contains(&i) {
                [0.0, 1.0, 0.0]
            } else {
                [0.0; 3]
            },
            ..ToolState::default()
        })
        .collect();
    let track = Track {
        decl: None,
        times,
        states,
    };
    let s = ScoreSettings::default();
    let acts = find_acts(&track, &[(3.0, 3.5)], &s);
    let kinds: Vec<ActKind> = acts.iter().map(|a| a.kind).collect();
    // The contact at 280..300 is the grasp's approach; 20..120 is a dissection.
    assert_eq!(
        kinds,
        [
            ActKind::Session,
            ActKind::Grasp,
            ActKind::Dissection,
            ActKind::Cut
        ]
    );
    assert_eq!((acts[1].first, acts[1].last), (300, 599));
    assert_eq!((acts[2].first, acts[2].last), (20, 119));
    let damage = [
        (1.0, 5e-9),
        (1.2, 1e-9),
        (1.8, 3e-9),
        (2.3, 3e-9),
        (2.5, 9e-9),
    ];
    let m = measure(&track, &acts[1], &damage, &s);
    assert!(
        (m.grasp_force_peak_n - 1.0).abs() < 1e-12 && (m.grasp_force_rms_n - 1.0).abs() < 1e-12
    );
    assert_eq!(m.contact_force_peak_n, 0.0);
    // Damage inside the act (1.2..2.396 s): trapezoids 0.6 s × 2 mm³ + 0.5 s × 3 mm³.
    assert!(
        (m.damage_m3_s.unwrap() - 2.7e-9).abs() < 1e-20,
        "{:?}",
        m.damage_m3_s
    );
    assert!((m.damage_peak_m3.unwrap() - 3e-9).abs() < 1e-20);
}

fn track_of(times: &[f64], p: &[P3]) -> Track {
    Track {
        decl: None,
        times: times.to_vec(),
        states: p
            .iter()
            .map(|&position| ToolState {
                position,
                orientation: [1.0, 0.0, 0.0, 0.0],
                ..ToolState::default()
            })
            .collect(),
    }
}

#[test]
fn grasp_and_cut_acts_from_events_when_the_samples_have_no_grasp_state() {
    use crate::format::{Event, SessionHeader};
    use crate::writer::{Recorder, RecorderSettings};
    let header = SessionHeader {
        session: "s".into(),
        site: "coordinator".into(),
        role: "coordinator".into(),
        scene: "x".into(),
        sim_rate_hz: 0.0,
        sample_every: 1,
        started_unix_ms: 0,
        damage_strain_threshold: None,
        software: "test".into(),
    };
    let mut rec = Recorder::new(Vec::new(), header, RecorderSettings::default()).unwrap();
    let id = rec.declare_tool("A", "forceps", "forceps").unwrap();
    let ev = |time: f64, kind: EventKind, tool: Option<&str>| Event {
        step: 0,
        time,
        site: "A".into(),
        tool: tool.map(str::to_owned),
        kind,
        detail: String::new(),
    };
    for i in 0..1000u64 {
        let t = i as f64 / RATE;
        // poses only: no grasp state, no forces
        let state = ToolState {
            position: [t * 1e-2, 0.0, 0.0],
            orientation: [1.0, 0.0, 0.0, 0.0],
            ..ToolState::default()
        };
        rec.tool_sample(i, t, id, &state).unwrap();
        match i {
            100 => rec.event(ev(t, EventKind::Grasp, Some("forceps"))).unwrap(),
            300 => rec
                .event(ev(t, EventKind::GraspRelease, Some("forceps")))
                .unwrap(),
            // another tool's grasp is not this tool's
            400 => rec.event(ev(t, EventKind::Grasp, Some("probe"))).unwrap(),
            // a cut naming no tool, never stopped (the site was killed)
            700 => rec.event(ev(t, EventKind::CutStart, None)).unwrap(),
            _ => {}
        }
    }
    let bytes = rec.finish().unwrap();
    let recording = Recording::from_bytes(&bytes).unwrap();
    let events = event_acts(&recording, "A", "forceps");
    assert_eq!(events.grasps, [(100.0 / RATE, 300.0 / RATE)]);
    assert_eq!(events.cuts, [(700.0 / RATE, f64::INFINITY)]);
    let track = recording.site_tracks("A").remove(0);
    let acts = find_acts_with(&track, &events, &ScoreSettings::default());
    let spans: Vec<(ActKind, usize, usize)> =
        acts.iter().map(|a| (a.kind, a.first, a.last)).collect();
    assert_eq!(
        spans,
        [
            (ActKind::Session, 0, 999),
            (ActKind::Grasp, 100, 300),
            (ActKind::Cut, 700, 999)
        ]
    );
    // With grasp state in the samples, the samples decide (events ignored for grasps).
    let mut stated = track.clone();
    for s in &mut stated.states[500..600] {
        s.grasped = 3;
    }
    let acts = find_acts_with(&stated, &events, &ScoreSettings::default());
    let grasp = acts.iter().find(|a| a.kind == ActKind::Grasp).unwrap();
    assert_eq!((grasp.first, grasp.last), (500, 599));
}
