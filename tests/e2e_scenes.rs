//! End-to-end tests of scenes in sessions, with the real binaries (helpers in `common`):
//! the demo's scene reset, a late joiner after a cut, and a session on a finer lattice.

mod common;

use std::path::Path;
use std::time::Duration;

use common::*;
use cosurg::divergence::fill_divergence;
use cosurg::site::SiteReport;

/// `cosurg demo --seconds 12 --reset-at 4 --json`: the instructor resets the scene at 4 s;
/// every site ends in the same epoch (one reset: epoch 1), and the divergence from the
/// owner stays as bounded after the reset as before it.
#[test]
fn demo_scene_reset_keeps_the_sites_together() {
    let _serial = serial();
    let out = tempfile::tempdir().unwrap();
    let mut cmd = cosurg();
    cmd.args(["demo", "--seconds", "12", "--reset-at", "4", "--json"])
        .args(["--scene", "cholecystectomy", "--strategy", "keyframe"])
        .args(["--vtu-interval", "100"])
        .arg("--out")
        .arg(out.path())
        .args(["--", "--no-haptics"]);
    let summary = test_support::run::json_summary(cmd, Duration::from_secs(300));
    let sites = summary["sites"].as_array().expect("sites");
    assert_eq!(sites.len(), 3);
    for s in sites {
        assert_eq!(s["epoch"], 1, "site {} did not end in epoch 1", s["name"]);
    }
    // Divergence per recording mark, from the sites' own recordings.
    let mut reports: Vec<SiteReport> = sites
        .iter()
        .map(|s| {
            let dir = out.path().join(s["name"].as_str().unwrap());
            let text = std::fs::read_to_string(dir.join("report.json")).unwrap();
            serde_json::from_str(&text).unwrap()
        })
        .collect();
    for r in &reports {
        assert_eq!(r.resets, 1, "{} reset {} times", r.name, r.resets);
    }
    let series = fill_divergence(&mut reports).unwrap();
    let max_in = |from: f64, to: f64| {
        series
            .iter()
            .flat_map(|s| s.points.iter().filter(|p| p.0 >= from && p.0 < to))
            .map(|p| p.1)
            .fold(0.0, f64::max)
    };
    let before = max_in(0.0, 4.0);
    let after = max_in(4.0, 12.0);
    eprintln!("divergence before the reset {before:.2} mm, after {after:.2} mm");
    assert!(
        before < LOOPBACK_MOTION_BOUND_MM,
        "before the reset: {before} mm"
    );
    assert!(
        after < LOOPBACK_MOTION_BOUND_MM,
        "after the reset: {after} mm"
    );
}

/// `scenes/cut-block.toml`: the instructor's blade cuts the block at 0.65 s of simulated
/// time; a trainee joining after the cut receives it in its join snapshot and ends with the
/// same topology (epoch and digest of the ops and the separated element set).
#[test]
fn late_joiner_after_a_cut_has_the_cut() {
    let _serial = serial();
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cut-block.toml");
    let scene = sim_core::sim_scene::Scene::load(&scene_path).expect("cut-block scene");
    let server = start_server_for(tempfile::tempdir().unwrap(), &scene.hash);
    let dir = session_dir();
    let scene_arg = scene_path.to_str().unwrap();
    let instructor = spawn_site(
        &server,
        dir.path(),
        "instructor",
        "instructor",
        &[
            "--scene",
            scene_arg,
            "--tool",
            "blade",
            "--script",
            "--seconds",
            "3.0",
            "--expect-sites",
            "1",
        ],
    );
    // Join once the instructor's clock is past the cut (0.65 s simulated; real-time pacing
    // plus start-up).
    std::thread::sleep(Duration::from_millis(2500));
    let trainee = spawn_site(
        &server,
        dir.path(),
        "trainee",
        "trainee",
        &["--scene", scene_arg, "--no-tool", "--seconds", "3.0"],
    );
    let r_instructor = wait_report(
        instructor,
        Duration::from_secs(120),
        dir.path().join("instructor.log"),
    );
    let r_trainee = wait_report(
        trainee,
        Duration::from_secs(120),
        dir.path().join("trainee.log"),
    );
    assert_eq!(
        r_instructor.topology_epoch, 1,
        "the instructor's blade cut once"
    );
    assert!(r_instructor.topology_bytes_sent > 0);
    assert_eq!(r_trainee.topology_epoch, 1, "the late joiner has the cut");
    assert_eq!(r_trainee.topology_ops_received, 1);
    assert_eq!(r_trainee.topology_digest, r_instructor.topology_digest);
}

/// A session on the one-body scene with every lattice cell at 1.33 cm instead of 2 cm
/// (`--cell`, about 2.4× the tetrahedra): the cell is part of the scene's identity, so the
/// coordinator admits sites that give it and refuses one that does not (WrongScene); the
/// sites' reports carry the cell, from which their divergence is computed on the finer
/// scene.
#[test]
fn a_session_on_a_finer_lattice_admits_only_that_lattice() {
    let _serial = serial();
    const CELL: &str = "0.013333333";
    let mut scene = sim_core::sim_scene::builtin::cholecystectomy();
    let coarse_hash = scene.hash.clone();
    scene.set_cell(CELL.parse().unwrap()).unwrap();
    assert_ne!(scene.hash, coarse_hash, "the cell changes the scene's hash");
    let server = start_server_for(tempfile::tempdir().unwrap(), &scene.hash);
    refused(join(&server, "coarse", "trainee"), "WrongScene");

    let dir = session_dir();
    let seconds = "1.5";
    let instructor = spawn_site(
        &server,
        dir.path(),
        "instructor",
        "instructor",
        &[
            "--cell",
            CELL,
            "--tool",
            "forceps",
            "--script",
            "--seconds",
            seconds,
            "--expect-sites",
            "2",
        ],
    );
    let trainee = spawn_site(
        &server,
        dir.path(),
        "trainee",
        "trainee",
        &[
            "--cell",
            CELL,
            "--no-tool",
            "--seconds",
            seconds,
            "--expect-sites",
            "2",
        ],
    );
    let limit = Duration::from_secs(180);
    let owner = wait_report(instructor, limit, dir.path().join("instructor.log"));
    let receiver = wait_report(trainee, limit, dir.path().join("trainee.log"));
    for r in [&owner, &receiver] {
        assert_eq!(r.scene_hash, scene.hash, "{} ran the finer scene", r.name);
        assert_eq!(r.cell_m, Some(CELL.parse().unwrap()));
        // The report on disk too, which `divergence_of` reads after the run.
        let text = std::fs::read_to_string(dir.path().join(&r.name).join("report.json"))
            .expect("report.json");
        let on_disk: SiteReport = serde_json::from_str(&text).unwrap();
        assert_eq!(
            on_disk.cell_m, r.cell_m,
            "{}'s report.json names the cell",
            r.name
        );
    }
    let mut reports = vec![owner, receiver];
    let series = fill_divergence(&mut reports).unwrap();
    assert!(!series.is_empty() && series.iter().all(|s| !s.points.is_empty()));
    let max = reports[1].divergence_max_mm.unwrap();
    eprintln!("finer lattice: max divergence {max:.2} mm");
    assert!(
        max.is_finite() && max < LOOPBACK_MOTION_BOUND_MM,
        "divergence {max} mm on the finer lattice"
    );
}
