//! Debrief end to end on real simulation data: the built-in scene stepped with its
//! scripted tools is recorded as an instructor and as a trainee whose tools follow the
//! same scripts 0.25 s later; then `cosurg score` and `cosurg replay --export-vtu` run
//! as processes on the recordings.

use std::path::Path;
use std::process::Command;

use cosurg::record::record_scripted;
use debrief::{ActKind, RecorderSettings, Recording, ScoreReport, Tail};

const SECONDS: f64 = 5.6;

fn record_both(dir: &Path) {
    for (site, role, delay) in [("instructor", "instructor", 0.0), ("A", "trainee", 0.25)] {
        let run = record_scripted(
            None,
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
    let cut = dir.join("cut");
    std::fs::create_dir_all(&cut).unwrap();
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
