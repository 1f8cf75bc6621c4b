//! The window's input path with real X events: `cosurg run` opens its window under a
//! virtual X display (Xvfb) with no script, and `xdotool` moves the mouse, turns the
//! wheel, drags and presses the jaw key in it. The window turns these into tool commands
//! (the same path a user's hands take); the run's `--stats-json` reports every command as
//! it reached the simulation and the site at the start and end. The forceps must go where
//! the drag put it, grasp the gallbladder's fundus on the jaw key, and an upward drag must
//! lift the gallbladder.
//!
//! Needs `Xvfb` and `xdotool` (Debian: `xvfb xdotool libgl1-mesa-dri`; `.ci/run` installs
//! them). Without them the test FAILS: it never passes without the real input path.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cosurg::run_window::{LocalSite, WindowRunStats};
use nalgebra::Vector3;
use sim_core::SimOptions;
use sim_core::sim_scene::builtin;
use test_support::xvfb::Xvfb;
use viewer::camera::WHEEL_DEPTH_STEP;
use viewer::{FrameBuilder, Hands};

/// The window's size; Xvfb's screen is the same, so the window fills it.
const WIDTH_PX: f64 = 1280.0;
const HEIGHT_PX: f64 = 720.0;
/// Wheel notches the window sees per XTest wheel click (see the test).
const NOTCHES_PER_CLICK: f64 = 2.0;
/// Simulated seconds the run lasts (the events take about 10 s of wall time).
const RUN_SECONDS: &str = "12";

fn xdotool(display: &str, args: &[&str]) -> String {
    let out = Command::new("xdotool")
        .args(args)
        .env("DISPLAY", display)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "cannot run xdotool ({e}): this test sends real X events to the window; \
                 install it (Debian: apt-get install xdotool) or run .ci/run"
            )
        });
    assert!(
        out.status.success(),
        "xdotool {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Drags with the left button from `(x, y)` by `(dx, dy)` pixels in window `win`.
fn drag(display: &str, win: &str, (x, y): (i64, i64), (dx, dy): (i64, i64)) {
    let (x0, y0, x1, y1) = (
        x.to_string(),
        y.to_string(),
        (x + dx).to_string(),
        (y + dy).to_string(),
    );
    xdotool(display, &["mousemove", "--window", win, &x0, &y0]);
    std::thread::sleep(Duration::from_millis(200));
    xdotool(display, &["mousedown", "1"]);
    std::thread::sleep(Duration::from_millis(200));
    xdotool(display, &["mousemove", "--window", win, &x1, &y1]);
    std::thread::sleep(Duration::from_millis(200));
    xdotool(display, &["mouseup", "1"]);
}

fn v(a: [f64; 3]) -> Vector3<f64> {
    Vector3::from(a)
}

#[test]
fn x_events_in_the_window_move_the_forceps_grasp_and_lift_the_gallbladder() {
    // fail loudly before anything starts when xdotool is missing
    let has_xdotool = Command::new("xdotool")
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok();
    assert!(
        has_xdotool,
        "xdotool is missing: this test sends real X events to the window; install it \
         (Debian: apt-get install xdotool) or run .ci/run"
    );

    // The camera and where the canned script grasps (the fundus at t = 2 s), computed from
    // the same scene the run loads, to know which pixels to drag.
    let scene = builtin::cholecystectomy();
    let grasp_at = scene.scripts["forceps"]
        .sample("forceps", 2.0)
        .unwrap()
        .position;
    let options = SimOptions::from_scene(&scene.scene);
    let site = LocalSite::new(scene, options, false).unwrap();
    let mut builder = FrameBuilder::new(&site.sim).unwrap();
    let frame = site.frame(&mut builder, false, None);
    let view = Hands::default().view(&frame);
    let tip0 = frame.tools[0].pose.translation.vector;
    // Wheel clicks: one XTest click of button 4/5 reaches the window as TWO wheel notches
    // (winit reports the button and the X server's emulated scroll valuator; measured under
    // Xvfb with xdotool 3.2016), so the clicks are half the notches; the depth left over is
    // under 4 mm, and the log below checks the notches one by one.
    let clicks = ((view.depth_of(&grasp_at) - view.depth_of(&tip0))
        / (NOTCHES_PER_CLICK * WHEEL_DEPTH_STEP))
        .round();
    let notches = clicks * NOTCHES_PER_CLICK;
    let pushed = tip0 + view.forward() * (notches * WHEEL_DEPTH_STEP);
    let d = grasp_at - pushed;
    let mpp = view.metres_per_pixel(view.depth_of(&pushed), HEIGHT_PX);
    let (dx, dy) = (
        (d.dot(&view.right()) / mpp).round() as i64,
        (-d.dot(&view.image_up()) / mpp).round() as i64,
    );
    let lift_px = (0.03 / mpp).round() as i64;

    let x = Xvfb::start();
    let dir = tempfile::tempdir().unwrap();
    let stats_path = dir.path().join("stats.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(["run", "builtin:cholecystectomy", "--size", "1280x720"])
        .args(["--seconds", RUN_SECONDS])
        .arg("--stats-json")
        .arg(&stats_path)
        .env("DISPLAY", &x.display)
        .env_remove("WAYLAND_DISPLAY")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run cosurg");
    let win = xdotool(
        &x.display,
        &["search", "--sync", "--onlyvisible", "--name", "cosurg run"],
    );
    let win = win
        .lines()
        .next()
        .expect("the window's id")
        .trim()
        .to_string();
    // the first frames: the window is drawing and takes input
    std::thread::sleep(Duration::from_secs(2));

    // 1. the wheel brings the tip to the fundus' depth, a drag across to the fundus
    let away = if clicks >= 0.0 { "4" } else { "5" };
    let centre = ((WIDTH_PX * 0.6) as i64, (HEIGHT_PX * 0.6) as i64);
    xdotool(
        &x.display,
        &[
            "mousemove",
            "--window",
            &win,
            &centre.0.to_string(),
            &centre.1.to_string(),
        ],
    );
    let n = (clicks.abs() as usize).to_string();
    xdotool(
        &x.display,
        &["click", "--repeat", &n, "--delay", "60", away],
    );
    std::thread::sleep(Duration::from_millis(300));
    let start = (
        (centre.0 - dx / 2).clamp(400, WIDTH_PX as i64 - 10),
        (centre.1 - dy / 2).clamp(10, HEIGHT_PX as i64 - 10),
    );
    drag(&x.display, &win, start, (dx, dy));
    std::thread::sleep(Duration::from_millis(2500));
    // 2. the jaw key closes the forceps on the fundus
    xdotool(&x.display, &["key", "space"]);
    std::thread::sleep(Duration::from_millis(1500));
    // 3. a drag 3 cm up the screen lifts it
    drag(
        &x.display,
        &win,
        (centre.0, centre.1 + lift_px / 2),
        (0, -lift_px),
    );

    let limit = Instant::now() + Duration::from_secs(240);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > limit {
            let _ = child.kill();
            panic!("cosurg run did not end within 240 s");
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let out = child.wait_with_output().unwrap();
    assert!(
        status.success(),
        "cosurg run failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let stats: WindowRunStats =
        serde_json::from_str(&std::fs::read_to_string(&stats_path).expect("stats written"))
            .expect("stats parse");
    let log = &stats.hands;
    let summary = serde_json::to_string_pretty(log).unwrap();

    // the wheel: one move straight along the view per notch
    let moves: Vec<Vector3<f64>> = log
        .iter()
        .filter(|c| c.command == "move_to")
        .map(|c| v(c.target.unwrap()))
        .collect();
    assert!(
        moves.len() as f64 >= notches.abs() + 2.0,
        "expected {} wheel moves and two drags, got: {summary}",
        notches.abs()
    );
    for (k, m) in moves[..notches.abs() as usize].iter().enumerate() {
        let want = tip0 + view.forward() * ((k + 1) as f64 * notches.signum() * WHEEL_DEPTH_STEP);
        assert!(
            (m - want).norm() < 1e-6,
            "wheel notch {k} put the target at {m}, expected {want}: {summary}"
        );
    }
    let wheeled = moves[notches.abs() as usize - 1];
    assert!(
        (wheeled - pushed).norm() < 1e-6,
        "the wheel put the target at {wheeled}, expected {pushed} ({notches} notches): {summary}"
    );
    // the drag (one or more motion events, as the X server delivers it): the target moved
    // right and up by the pixels dragged, at the tip's depth
    let jaw_at = log
        .iter()
        .position(|c| c.command == "jaw_closed")
        .unwrap_or_else(|| panic!("no jaw command from the space key: {summary}"));
    let dragged = log[..jaw_at]
        .iter()
        .rev()
        .find(|c| c.command == "move_to")
        .map(|c| v(c.target.unwrap()))
        .unwrap();
    let moved = dragged - wheeled;
    let expected = view.right() * (dx as f64 * mpp) - view.image_up() * (dy as f64 * mpp);
    assert!(
        (moved - expected).norm() < 0.05 * expected.norm() + 1e-4,
        "the drag of ({dx}, {dy}) px moved the target by {moved}, expected {expected}: {summary}"
    );
    // the forceps followed: at the jaw key its tip was at the fundus
    let jaw = &log[jaw_at];
    let tip = v(jaw.site.tip);
    let off = (tip - grasp_at).norm();
    // the wheel's resolution (8 mm per click) leaves up to 4 mm of depth
    assert!(
        off < 5e-3,
        "the forceps' tip was {:.1} mm from the fundus when the jaws closed: {summary}",
        off * 1e3
    );
    // the upward drag came after the jaw key, and the grasp held to the end
    let lift = log
        .iter()
        .rposition(|c| c.command == "move_to")
        .filter(|&i| log[i].site.t > jaw.site.t)
        .unwrap_or_else(|| panic!("no drag after the jaw key: {summary}"));
    let end = stats.end.as_ref().expect("end state");
    assert!(
        end.grasping,
        "the forceps does not grasp at the end: {end:?}"
    );
    let before = v(log[lift].site.gallbladder_centroid.expect("a gallbladder"));
    let after = v(end.gallbladder_centroid.expect("a gallbladder"));
    let rose_up_screen = (after - before).dot(&view.image_up());
    let rose = after.z - before.z;
    eprintln!(
        "gallbladder centroid: up the screen {:.2} mm, up (z) {:.2} mm; tip at grasp {:.2} mm off",
        rose_up_screen * 1e3,
        rose * 1e3,
        off * 1e3
    );
    assert!(
        rose_up_screen > 2e-3,
        "the gallbladder's centroid rose {:.2} mm up the screen after a 30 mm lift of its \
         fundus, expected more than 2 mm",
        rose_up_screen * 1e3
    );
}
