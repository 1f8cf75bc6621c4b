//! Debrief end to end on real simulation data: the built-in scene stepped with its
//! scripted tools is recorded as an instructor and as a trainee whose tools follow the
//! same scripts 0.25 s later; then `cosurg score` and `cosurg replay --export-vtu` run
//! as processes on the recordings.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use cosurg::record::record_scripted;
use debrief::{ActKind, EventKind, RecorderSettings, Recording, ScoreReport, Tail};

const SECONDS: f64 = 5.6;

fn record_both(dir: &Path) {
    for (site, role, delay) in [("instructor", "instructor", 0.0), ("A", "trainee", 0.25)] {
        let run = record_scripted(
            // the one-body scene this file's figures were measured on
            Some("builtin:cholecystectomy"),
            SECONDS,
            site,
            role,
            delay,
            &dir.join(format!("{site}.cosrec")),
            RecorderSettings::default(),
        )
        .unwrap();
        assert!(run.steps > 0 && run.bytes > 0);
    }
}

fn cosurg(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "cosurg {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn score_and_replay_a_recorded_simulation() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    record_both(dir);

    // The recording: both tools, grasp events, surfaces, damage, complete.
    let a = Recording::open(dir.join("A.cosrec")).unwrap();
    assert_eq!(a.tail, Tail::Complete);
    assert_eq!(a.tools().len(), 2);
    assert!(!a.surfaces().is_empty());
    assert!(a.damage().len() > 50);
    assert!(
        a.events().any(|e| e.kind == debrief::EventKind::Grasp),
        "the scripted forceps grasps the fundus"
    );

    // Scores as JSON against the instructor.
    let a_str = dir.to_str().unwrap();
    let json = cosurg(&[
        "score",
        a_str,
        "--site",
        "A",
        "--reference",
        "instructor",
        "--json",
    ]);
    let report: ScoreReport = serde_json::from_str(&json).unwrap();
    assert_eq!(report.site, "A");
    let grasp = report
        .acts
        .iter()
        .find(|s| s.act.kind == ActKind::Grasp && s.act.tool == "forceps")
        .expect("a grasp act of the forceps");
    let m = &grasp.measures;
    // Grasp (jaws closed ≈ 2.0 s) to release (≈ 5.0 s), 0.25 s later for A.
    assert!(
        m.duration_s > 2.0 && m.duration_s < 3.5,
        "grasp lasted {} s",
        m.duration_s
    );
    assert!(
        m.path_length_m > 0.02,
        "lift of 3 cm: {} m",
        m.path_length_m
    );
    assert!(m.economy.unwrap() >= 1.0);
    assert!(m.grasp_force_peak_n > 0.0);
    // Same script, 0.25 s later: the paths nearly coincide after warping.
    let dtw = m
        .dtw_to_reference_m
        .expect("matched with the instructor's grasp");
    assert!(
        dtw < 0.1 * m.path_length_m,
        "DTW {dtw} m vs path {} m",
        m.path_length_m
    );
    assert_eq!(m.reference_act.as_deref(), Some("grasp 1 of forceps"));

    // Text and HTML.
    let html = dir.join("A.html");
    let text = cosurg(&[
        "score",
        &dir.join("A.cosrec").display().to_string(),
        "--site",
        "A",
        "--reference",
        &dir.join("instructor.cosrec").display().to_string(),
        "--html",
        html.to_str().unwrap(),
    ]);
    assert!(text.contains("grasp 1 of forceps"), "{text}");
    let page = std::fs::read_to_string(&html).unwrap();
    assert!(page.contains("<table") && page.matches("<svg").count() >= 3);
    assert!(!page.contains("src=\"http"), "self-contained");

    // A recording cut mid-record (as by a kill) still scores.
    let bytes = std::fs::read(dir.join("A.cosrec")).unwrap();
    // (Outside `dir`: a directory's recordings include its subdirectories'.)
    let cut_tmp = tempfile::tempdir().unwrap();
    let cut = cut_tmp.path();
    std::fs::write(cut.join("A.cosrec"), &bytes[..bytes.len() * 2 / 3 + 3]).unwrap();
    let text = cosurg(&["score", cut.to_str().unwrap(), "--site", "A"]);
    assert!(text.contains("truncated"), "{text}");

    // Unknown site: a clear error.
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(["score", a_str, "--site", "nobody"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("A, instructor"));

    // Headless replay to ParaView.
    let vtu = dir.join("vtu");
    let text = cosurg(&["replay", a_str, "--export-vtu", vtu.to_str().unwrap()]);
    assert!(text.contains("real time"), "{text}");
    for site in ["A", "instructor"] {
        let pvd = std::fs::read_to_string(vtu.join(site).join("series.pvd")).unwrap();
        let frames = a.surface_shapes(0).len();
        assert!(pvd.matches("tools_").count() >= frames - 1, "{pvd}");
        assert!(vtu.join(site).join("tools_00001.vtu").exists());
    }
}

/// Every number in a JSON value (NaN and infinities serialise as null).
fn numbers(v: &serde_json::Value, out: &mut Vec<f64>) {
    match v {
        serde_json::Value::Number(n) => out.push(n.as_f64().unwrap()),
        serde_json::Value::Array(a) => a.iter().for_each(|x| numbers(x, out)),
        serde_json::Value::Object(o) => o.values().for_each(|x| numbers(x, out)),
        _ => {}
    }
}

/// `cosurg demo --seconds 8`: every site records `<out>/<site>/<site>.cosrec` (steps,
/// joins of the others, claims, the end), the instructor's grasp shows as an act in its
/// recording, the summary scores trainee A against the instructor, and `cosurg score`
/// reads the demo's out folder.
#[test]
fn demo_sites_record_and_the_summary_scores_trainee_a() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_cosurg"));
    cmd.env("COSURG_LOG", "warn")
        .args(["demo", "--seconds", "8", "--json", "--vtu-interval", "100"])
        // the one-body scene, where trainee A repeats the instructor's lift
        .args(["--scene", "cholecystectomy", "--strategy", "keyframe"])
        .arg("--out")
        .arg(out)
        .args(["--", "--no-haptics"]);
    let summary = test_support::run::json_summary(cmd, Duration::from_secs(240));

    for site in ["instructor", "trainee-a", "trainee-b"] {
        let path = out.join(site).join(format!("{site}.cosrec"));
        let rec = Recording::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(rec.tail, Tail::Complete, "{site}");
        assert_eq!(rec.header.site, site);
        let steps = rec.steps().count();
        assert!(steps > 500, "{site}: {steps} step records in 8 s");
        let (t0, t1) = rec.time_span().unwrap();
        assert!(t1 - t0 > 6.0, "{site}: {t0}..{t1} s");
        assert!(!rec.damage().is_empty(), "{site}: damage measured");
        let kinds: Vec<EventKind> = rec.events().map(|e| e.kind.clone()).collect();
        let joins = kinds.iter().filter(|k| **k == EventKind::Join).count();
        assert!(joins >= 3, "{site}: own join and two others: {kinds:?}");
        assert_eq!(kinds.last(), Some(&EventKind::Leave), "{site}: {kinds:?}");
        assert!(
            kinds.contains(&EventKind::Claim),
            "{site}: the instructor's grasp claims regions: {kinds:?}"
        );
    }
    // The instructor's grasp (0.5 s + ≈ 2 s) is an act in its own recording.
    let instructor = Recording::open(out.join("instructor/instructor.cosrec")).unwrap();
    let own = debrief::score_site(
        &instructor,
        "instructor",
        None,
        &debrief::ScoreSettings::default(),
    )
    .unwrap();
    assert!(
        own.acts
            .iter()
            .any(|a| a.act.kind == ActKind::Grasp && a.act.tool == "forceps"),
        "{:?}",
        own.acts
    );

    // The summary's scores of trainee A against the instructor.
    let scores = &summary["scores"];
    assert_eq!(scores["site"], "trainee-a", "{summary}");
    assert!(
        scores["reference"]
            .as_str()
            .unwrap()
            .starts_with("instructor@")
    );
    assert!(scores["acts"].is_array());
    let mut nums = Vec::new();
    numbers(scores, &mut nums);
    assert!(!nums.is_empty() && nums.iter().all(|x| x.is_finite()));
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(file["scores"], *scores);

    // `cosurg score` on the demo's out folder.
    let text = cosurg(&["score", out.to_str().unwrap(), "--site", "instructor"]);
    assert!(text.contains("grasp 1 of forceps"), "{text}");
    let json = cosurg(&[
        "score",
        out.to_str().unwrap(),
        "--site",
        "trainee-a",
        "--reference",
        "instructor",
        "--json",
    ]);
    let report: ScoreReport = serde_json::from_str(&json).unwrap();
    assert_eq!(report.site, "trainee-a");
}
