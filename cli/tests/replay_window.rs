//! `cosurg replay` without a screen: recordings of the built-in scene stepped with its
//! scripted tools (an instructor, and trainee A doing the same 0.25 s later) are played
//! back into pictures under a virtual X display (Xvfb, Mesa's software OpenGL). A
//! picture shows the organ; pictures at two times differ (the lift moves the tissue and
//! the tools); the overlay of two sites renders; `--headless` makes every frame and
//! reports its speed (measured, not asserted: performance lives in benchmarks).
//!
//! Needs `Xvfb` (Debian: `xvfb`, plus `libgl1-mesa-dri`). If no X server can be started
//! the test FAILS: it never passes without rendering.

use std::path::Path;
use std::process::Command;

use cosurg::record::record_scripted;
use debrief::RecorderSettings;
use test_support::xvfb::Xvfb;

fn start_xvfb() -> Xvfb {
    Xvfb::start()
}

fn replay(x: &Xvfb, args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .arg("replay")
        .args(args)
        .env("DISPLAY", &x.display)
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .expect("run cosurg replay");
    assert!(
        out.status.success(),
        "cosurg replay {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn picture(path: &Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).expect("PNG written"),
    ));
    let mut reader = decoder.read_info().expect("a PNG");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("PNG decodes");
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// Liver pixels: red clearly dominant (as in `window.rs`).
fn is_liver(p: &[u8]) -> bool {
    let (r, g, b) = (p[0] as f64, p[1] as f64, p[2] as f64);
    r > 35.0 && r > 1.5 * g && r > 1.5 * b
}

#[test]
fn replay_screenshots_show_the_recording_and_change_with_time() {
    let tmp = tempfile::tempdir().unwrap();
    // REPLAY_TEST_DIR=DIR keeps the recordings and pictures for a look.
    let kept = std::env::var_os("REPLAY_TEST_DIR").map(std::path::PathBuf::from);
    let dir = kept.as_deref().unwrap_or(tmp.path());
    std::fs::create_dir_all(dir).unwrap();
    for (site, delay) in [("instructor", 0.0), ("A", 0.25)] {
        record_scripted(
            // the one-body scene this file's figures were measured on
            Some("builtin:cholecystectomy"),
            4.0,
            site,
            "trainee",
            delay,
            &dir.join(format!("{site}.cosrec")),
            RecorderSettings::default(),
        )
        .unwrap();
    }
    let x = start_xvfb();
    let d = dir.to_str().unwrap();
    let shot = |name: &str, at: &str, sites: &str| {
        let path = dir.join(name);
        let p = path.to_str().unwrap().to_string();
        let text = replay(
            &x,
            &[
                d,
                "--sites",
                sites,
                "--screenshot",
                &p,
                "--at",
                at,
                "--size",
                "960x540",
            ],
        );
        assert!(text.contains("wrote"), "{text}");
        let (w, h, rgba) = picture(&path);
        assert_eq!((w, h), (960, 540));
        rgba
    };
    let early = shot("early.png", "0.3", "instructor");
    let late = shot("late.png", "3.6", "instructor");
    let pixels = early.len() / 4;
    let liver = early.chunks(4).filter(|p| is_liver(p)).count();
    eprintln!("liver pixels: {liver} of {pixels}");
    assert!(
        liver > pixels / 100,
        "the organ is in the picture: {liver} liver pixels"
    );
    let distinct: std::collections::HashSet<&[u8]> = early.chunks(4).collect();
    assert!(
        distinct.len() > 100,
        "not a blank picture: {} colours",
        distinct.len()
    );
    let changed = early
        .chunks(4)
        .zip(late.chunks(4))
        .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > 24))
        .count();
    eprintln!("pixels changed between 0.3 s and 3.6 s: {changed} of {pixels}");
    assert!(
        changed > pixels / 200,
        "the tools and tissue moved: only {changed} pixels changed"
    );
    // Two sites overlaid: the trainee's tools (0.25 s behind) add to the picture.
    let both = shot("both.png", "3.6", "instructor,A");
    let added = late
        .chunks(4)
        .zip(both.chunks(4))
        .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > 24))
        .count();
    eprintln!("pixels the overlaid trainee changed: {added}");
    assert!(added > 0, "the second site's tools are drawn");

    let text = replay(&x, &[d, "--headless"]);
    assert!(text.contains("× real time"), "{text}");
    eprintln!("{text}");
    // Bad input gets a clear error.
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(["replay", d, "--sites", "nobody", "--headless"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("\"nobody\" not found"));
}
