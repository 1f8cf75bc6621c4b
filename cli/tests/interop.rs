//! Interop with a foreign QUIC stack: the Python aioquic client of `deploy/interop/` against
//! `cosurg-server` through `cosurg netem`. Runs when `python3 -c "import aioquic"` works and
//! prints "skipped: aioquic not installed" otherwise (install: `pip install aioquic`).

use std::path::{Path, PathBuf};
use std::process::Command;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn python_ok(check: &str) -> bool {
    Command::new("python3")
        .args(["-c", check])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// The Python client hand-encodes `Join` (postcard); it must match `proto::encode_frame`.
/// Needs only python3.
#[test]
fn python_join_encoding_matches_proto() {
    if !python_ok("import sys") {
        println!("skipped: python3 not available");
        return;
    }
    let join = proto::Join {
        protocol_version: proto::PROTOCOL_VERSION,
        scene_hash: "ab".repeat(32),
        role: proto::Role::Trainee,
        site_name: "kyōto-1".into(),
        session: "lap-chole".into(),
        credential: proto::Credential::Invitation("csi1.abc".into()),
        time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
    };
    let out = Command::new("python3")
        .arg(repo().join("deploy/interop/aioquic_join.py"))
        .args(["--print-join-hex", "--site", "kyōto-1", "--role", "trainee"])
        .args([
            "--session",
            "lap-chole",
            "--token",
            "s3cret",
            "--invite",
            "csi1.abc",
            "--scene-hash",
        ])
        .arg("ab".repeat(32))
        .output()
        .expect("running python3");
    assert!(out.status.success(), "{out:?}");
    let got = String::from_utf8(out.stdout).unwrap();
    let want = hex::encode(proto::encode_frame(&proto::Message::Join(join)));
    assert_eq!(got.trim(), want);
}

#[test]
fn aioquic_client_through_netem() {
    if !python_ok("import aioquic") {
        println!("skipped: aioquic not installed");
        return;
    }
    let server = test_support::exe::sibling_exe(env!("CARGO_BIN_EXE_cosurg"), "cosurg-server");
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_cosurg")).parent().unwrap();
    assert_eq!(server.parent().unwrap(), bin_dir);
    let out = Command::new("bash")
        .arg(repo().join("deploy/interop/run.sh"))
        .env("COSURG_BIN_DIR", bin_dir)
        .env("PRESET", "average")
        .env("INTEROP_REQUIRE", "1")
        .output()
        .expect("running deploy/interop/run.sh");
    let text = String::from_utf8_lossy(&out.stdout);
    println!("{text}");
    eprintln!("{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "interop failed: {:?}", out.status);
    assert!(text.contains("interop: PASS"));
    assert!(text.contains("connection_close: application error code 1 (WRONG_TOKEN)"));
    assert!(text.contains("connection_close: application error code 8 (MALFORMED)"));
}
