//! `cosurg run --cell`: the default organ on a finer lattice (more tets, another scene
//! hash), and a cell size the scene's bodies cannot take refused with the reason.

use std::process::{Command, Output};

fn run(extra: &[&str]) -> Output {
    let dir = tempfile::tempdir().unwrap();
    Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(["run", "--headless", "--seconds", "0.01", "--out"])
        .arg(dir.path())
        .args(extra)
        .output()
        .expect("run cosurg")
}

/// `(scene hash, leaf tets)` from the first line of a run's summary: `scene NAME (sha256
/// HASH): N leaf tets, …`.
fn summary(out: &Output) -> (String, usize) {
    assert!(
        out.status.success(),
        "cosurg run failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The summary's first lines go to stderr with the log (stdout: the results).
    let text = String::from_utf8_lossy(&out.stderr);
    let line = text
        .lines()
        .find(|l| l.starts_with("scene "))
        .expect("summary line");
    let hash = line.split("sha256 ").nth(1).unwrap()[..64].to_string();
    let tets = line
        .split("): ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no tet count in {line:?}"));
    (hash, tets)
}

/// `(p50, p99, max)` step times (ms) from the run's result line on stdout: `simulated T s
/// in N steps: step p50 A ms, p99 B ms, max C ms`.
fn step_times(out: &Output) -> (f64, f64, f64) {
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("simulated "))
        .unwrap_or_else(|| panic!("no result line in {text:?}"));
    let after = |key: &str| -> f64 {
        line.split(key)
            .nth(1)
            .and_then(|r| r.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no {key:?} in {line:?}"))
    };
    (after("p50 "), after("p99 "), after("max "))
}

#[test]
fn a_finer_cell_gives_more_tets_and_another_scene_hash() {
    let out = run(&[]);
    // The result line names the longest step, which bounds the percentiles.
    let (p50, p99, max) = step_times(&out);
    assert!(0.0 < p50 && p50 <= p99 && p99 <= max, "{p50} {p99} {max}");
    let (hash_2cm, tets_2cm) = summary(&out);
    let (hash_fine, tets_fine) = summary(&run(&["--cell", "0.013333333"]));
    assert_ne!(hash_2cm, hash_fine, "the scene hash names the cell size");
    // (2 / 1.33)^3 ≈ 3.4 times the cells; the bodies' boundaries are refined alike.
    assert!(
        tets_fine as f64 > 2.5 * tets_2cm as f64,
        "{tets_fine} tets at 1.33 cm against {tets_2cm} at 2 cm"
    );
}

#[test]
fn a_cell_the_gallbladder_bed_cannot_take_is_refused_with_the_reason() {
    let out = run(&["--cell", "0.015"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("gallbladder bed"), "{err}");
    assert!(err.contains("empty cell (0.015 m)"), "{err}");
    let out = run(&["--cell=-1"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("must be positive"), "{err}");
}
