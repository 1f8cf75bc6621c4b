//! A virtual X display for the window tests: `Xvfb` with Mesa's software OpenGL behind it.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// An Xvfb server, killed on drop. `display` is its `DISPLAY` value (`:N`).
pub struct Xvfb {
    child: Child,
    pub display: String,
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Xvfb {
    /// Starts a 1280×720×24 server. Panics with what to install when `Xvfb` is missing or
    /// does not become ready within 20 s: a window test never passes without rendering.
    pub fn start() -> Xvfb {
        // `-displayfd 1`: Xvfb picks a free display number itself (several test binaries
        // may run at once) and writes it on stdout once it accepts connections, so there is
        // no socket or lock file to probe.
        let mut child = Command::new("Xvfb")
            .args(["-displayfd", "1", "-screen", "0", "1280x720x24"])
            .args(["-nolisten", "tcp"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start Xvfb ({e}): the window tests need a virtual X display; \
                     install it (Debian: apt-get install xvfb libgl1-mesa-dri) or run .ci/run"
                )
            });
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let mut x = Xvfb {
            child,
            display: String::new(),
        };
        match rx.recv_timeout(Duration::from_secs(20)) {
            Ok(line) if line.trim().parse::<u32>().is_ok() => {
                x.display = format!(":{}", line.trim());
                x
            }
            Ok(line) => panic!(
                "Xvfb did not report a display (it wrote {line:?}; exit status {:?})",
                x.child.try_wait()
            ),
            Err(_) => panic!("Xvfb did not become ready within 20 s"),
        }
    }
}
