//! Running a command of the product to its end within a time limit, and reading the JSON
//! summary a `--json` run prints last (e.g. `cosurg demo --json`).

use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Run `cmd` with its output captured; kill it if it is still running after `limit` (the
/// returned status then says it did not succeed).
pub fn run_bounded(mut cmd: Command, limit: Duration) -> Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let deadline = Instant::now() + limit;
    loop {
        if child.try_wait().unwrap().is_some() || Instant::now() > deadline {
            let _ = child.kill();
            return child.wait_with_output().unwrap();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Run `cmd` (a `--json` run) within `limit` and parse the JSON document that starts at the
/// first `{` of its standard output. Panics with the status and both outputs when it fails,
/// overruns or prints no JSON.
pub fn json_summary(cmd: Command, limit: Duration) -> serde_json::Value {
    let output = run_bounded(cmd, limit);
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "failed or did not finish within {limit:?}: {:?}\n{stdout}\n{}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    let start = stdout.find('{').expect("JSON summary on stdout");
    serde_json::from_str(&stdout[start..]).expect("summary JSON")
}
