//! Records the built-in scene stepped with its scripted tools, twice: as site
//! `instructor` and as site `A` whose tools follow the same scripts `--delay` seconds
//! later. The two recordings give `cosurg score DIR --site A --reference instructor`
//! and `cosurg replay DIR --export-vtu OUT` real data before the sites record
//! themselves.
//!
//! `cargo run --release -p cosurg --example record_scripted -- OUT_DIR [SECONDS] [DELAY]`

use std::path::PathBuf;

use anyhow::{Context, Result};
use cosurg::record::record_scripted;
use debrief::RecorderSettings;

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(
        args.next()
            .context("usage: record_scripted OUT_DIR [SECONDS] [DELAY]")?,
    );
    let seconds: f64 = args.next().map_or(Ok(6.0), |s| s.parse())?;
    let delay: f64 = args.next().map_or(Ok(0.25), |s| s.parse())?;
    std::fs::create_dir_all(&dir)?;
    for (site, role, d) in [("instructor", "instructor", 0.0), ("A", "trainee", delay)] {
        let path = dir.join(format!("{site}.cosrec"));
        let run = record_scripted(
            // the one-body scene this file's figures were measured on
            Some("builtin:cholecystectomy"),
            seconds,
            site,
            role,
            d,
            &path,
            RecorderSettings::default(),
        )?;
        println!(
            "{}: {} steps, {} bytes ({:.2} MB per simulated minute), step p50 {:.3} ms, recorder p50 {:.4} ms mean {:.4} ms",
            path.display(),
            run.steps,
            run.bytes,
            run.bytes as f64 / 1e6 * 60.0 / seconds,
            run.step_ms_p50,
            run.record_ms_p50,
            run.record_ms_mean,
        );
    }
    Ok(())
}
