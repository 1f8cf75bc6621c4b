//! `cosurg demo --scene cholecystectomy-bodies`: three sites as separate processes over real
//! QUIC; the instructor's forceps lifts the gallbladder, trainee B's hook dissects the bed
//! (each release a topology op relayed to the others), trainee A's blade cuts the duct. At
//! the end every site has applied the same topology ops (epoch) with the same result
//! (digest).

use std::process::Command;
use std::time::Duration;

#[test]
fn demo_dissection_ends_with_the_same_topology_on_every_site() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_cosurg"));
    cmd.env("COSURG_LOG", "warn")
        .args(["demo", "--scene", "cholecystectomy-bodies"])
        .args(["--seconds", "14", "--json", "--vtu-interval", "100"])
        .arg("--out")
        .arg(out)
        .args(["--", "--no-haptics"]);
    let summary = test_support::run::json_summary(cmd, Duration::from_secs(420));
    let sites = summary["sites"].as_array().expect("sites");
    assert_eq!(sites.len(), 3, "{summary}");
    let epochs: Vec<u64> = sites
        .iter()
        .map(|s| s["topology_epoch"].as_u64().unwrap())
        .collect();
    let digests: Vec<&str> = sites
        .iter()
        .map(|s| s["topology_digest"].as_str().unwrap())
        .collect();
    // The bed has 272 springs; the hook releases them one op at a time or a few per op
    // (60 springs/s at 250 Hz), and the blade adds its cut(s).
    assert!(epochs[0] >= 100, "topology epochs {epochs:?}");
    assert!(epochs.iter().all(|e| *e == epochs[0]), "{epochs:?}");
    assert!(digests.iter().all(|d| *d == digests[0]), "{digests:?}");
}
