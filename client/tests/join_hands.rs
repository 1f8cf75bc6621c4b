//! Who drives a `cosurg join` site's tool: a canned script only when asked (`--script`);
//! headless without a script or a device the tool stays where it is (it does not play
//! the scene's grasp-and-lift by itself). The site runs in-process without a link.

use clap::Parser;
use cosurg::join::{JoinArgs, site_config};
use cosurg::site::{SiteConfig, run_site};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    join: JoinArgs,
}

/// `cosurg join` for the instructor's forceps, 3 simulated seconds (the scene's script
/// closes the jaws on the fundus at 2 s), headless, plus `extra`.
fn config(extra: &[&str]) -> SiteConfig {
    let mut argv = vec![
        "join",
        "--server",
        "127.0.0.1:9",
        "--session",
        "s",
        "--role",
        "instructor",
        "--site",
        "prof",
        "--pin",
        "00",
        "--token",
        "t",
        "--tool",
        "forceps",
        "--scene",
        "builtin:cholecystectomy",
        "--headless",
        "--no-haptics",
        "--no-realtime",
        "--seconds",
        "3",
        "--vtu-interval",
        "0",
    ];
    argv.extend_from_slice(extra);
    let args = Cli::try_parse_from(argv).expect("arguments parse").join;
    let mut cfg = site_config(&args).expect("site config");
    // a site on its own: no coordinator
    cfg.link = None;
    cfg
}

#[test]
fn without_script_or_device_the_headless_tool_stays_still() {
    let cfg = config(&[]);
    assert!(cfg.script.is_none(), "no script unless asked");
    assert!(
        cfg.view.is_none() && !cfg.hands,
        "headless: no window, no hands"
    );
    let report = run_site(cfg).unwrap();
    assert_eq!(
        report.max_tool_force_n, 0.0,
        "the forceps touched the organ by itself"
    );
    assert_eq!(report.teaching_sent, None, "an act was recorded");
}

#[test]
fn script_without_a_file_plays_the_scenes_script() {
    let cfg = config(&["--script"]);
    assert!(cfg.script.is_some());
    let report = run_site(cfg).unwrap();
    assert!(
        report.max_tool_force_n > 0.05,
        "the scripted forceps should grasp the fundus (largest force {:.3} N)",
        report.max_tool_force_n
    );
}

#[test]
fn script_needs_a_tool() {
    let args = Cli::try_parse_from([
        "join",
        "--server",
        "127.0.0.1:9",
        "--session",
        "s",
        "--role",
        "trainee",
        "--site",
        "a",
        "--pin",
        "00",
        "--invite",
        "x",
        "--no-tool",
        "--script",
        "--headless",
    ])
    .unwrap()
    .join;
    let err = match site_config(&args) {
        Ok(_) => panic!("--script without a tool was accepted"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("drives no tool"), "{err}");
}
