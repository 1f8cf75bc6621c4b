//! A `cosurg-server` child process for end-to-end tests: started from a prepared command,
//! its announcements (`listening: ADDR`, `fingerprint: HEX`, and any other `key: value`
//! lines the test waits for) read from its standard output, the rest of which is drained so
//! the server never blocks on a full pipe. Killed on drop.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How long a server has to announce itself.
pub const ANNOUNCE_TIMEOUT: Duration = Duration::from_secs(30);

/// A running `cosurg-server`; killed (and reaped) on drop.
pub struct ServerProcess {
    pub child: Child,
    /// `listening:` address.
    pub addr: String,
    /// `fingerprint:` of its certificate (SHA-256, hex).
    pub fingerprint: String,
    /// The other announcements waited for, by key (e.g. `recording`).
    pub announced: HashMap<String, String>,
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Spawn `command` (standard output is taken over) and wait until it has announced its
/// address, its fingerprint and every key of `also`. Panics, naming what is missing, when
/// the server exits or stays silent for [`ANNOUNCE_TIMEOUT`].
pub fn spawn(mut command: Command, also: &[&str]) -> ServerProcess {
    let mut child = command
        .stdout(Stdio::piped())
        .spawn()
        .expect("start cosurg-server");
    let mut lines = BufReader::new(child.stdout.take().expect("piped stdout")).lines();
    let mut announced = HashMap::new();
    let wanted = |a: &HashMap<String, String>| {
        ["listening", "fingerprint"]
            .iter()
            .chain(also)
            .filter(|k| !a.contains_key(**k))
            .map(|k| k.to_string())
            .collect::<Vec<_>>()
    };
    let deadline = Instant::now() + ANNOUNCE_TIMEOUT;
    while !wanted(&announced).is_empty() {
        assert!(
            Instant::now() < deadline,
            "cosurg-server did not announce {:?}",
            wanted(&announced)
        );
        let Some(Ok(line)) = lines.next() else {
            panic!(
                "cosurg-server exited ({:?}) before announcing {:?}",
                child.wait(),
                wanted(&announced)
            );
        };
        if let Some((key, value)) = line.split_once(": ") {
            announced.insert(key.to_string(), value.trim().to_string());
        }
    }
    std::thread::spawn(move || for _ in lines {});
    let addr = announced.remove("listening").expect("checked");
    let fingerprint = announced.remove("fingerprint").expect("checked");
    ServerProcess {
        child,
        addr,
        fingerprint,
        announced,
    }
}
