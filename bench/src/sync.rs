//! `cosurg bench sync`: how far apart are the sites' organs, at what bandwidth, when the
//! network is bad and the machines are unequal?
//!
//! Each row runs the demo's first act (the instructor lifts the gallbladder, both trainees
//! follow) over real QUIC through the in-process impairment of
//! every site's link, for one strategy × preset, plus one case with trainee B slowed 3×.
//! Divergence is measured against the owning site at the same simulated time over every
//! embedded-surface vertex; "settled" is the part of the run after every tool stopped.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use cosurg::cli::out_dir;
use cosurg::demo::{DemoSite, SessionRun, run_session};
use cosurg::plot::{Chart, Series, write_chart};
use sim_core::sync::SyncStrategy;

#[derive(Debug, Args)]
pub struct SyncArgs {
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Output folder (default out/bench-sync-<timestamp>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Simulated seconds per run (tools stop moving at about 6.5 s).
    #[arg(long, default_value_t = 9.0)]
    pub seconds: f64,
    /// Presets to run (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "lan,metro,good,average,poor,intercontinental"
    )]
    pub presets: Vec<String>,
    /// Strategies to run (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "keyframe,full-state,input-only"
    )]
    pub strategies: Vec<SyncStrategy>,
    /// Slowdown of trainee B in the extra "unequal machines" row (1: no such row).
    #[arg(long, default_value_t = 3.0)]
    pub slowdown: f64,
    /// CG budget of trainee B in the extra "unequal fidelity" rows (keyframe and
    /// input-only over lan and good): a slower machine that cuts its solver budget to keep
    /// up, so that its simulation is no longer the owner's (0: no such rows).
    #[arg(long, default_value_t = 5)]
    pub reduced_cg: usize,
    /// Impairment seed.
    #[arg(long, default_value_t = 11)]
    pub seed: u64,
    /// Playout lag of every site (`cosurg join --playout-lag`): `auto` or milliseconds
    /// (0: followers run at the owner's simulated time and extrapolate).
    #[arg(long, default_value = "auto")]
    pub playout_lag: cosurg::site::PlayoutLag,
}

#[derive(Debug, Clone, Serialize)]
pub struct SyncRow {
    pub strategy: String,
    pub preset: String,
    pub slowdown: f64,
    /// Trainee B's CG budget in the "unequal fidelity" rows (null: the scene's, as every
    /// other site).
    pub receiver_cg_iterations: Option<usize>,
    /// Max / RMS over the run and over receiving sites (mm).
    pub divergence_max_mm: f64,
    pub divergence_rms_mm: f64,
    /// Max over the last second, after every tool stopped (mm).
    pub settled_divergence_max_mm: f64,
    /// Mean over sites of application bytes per second.
    pub up_bytes_per_s: f64,
    pub down_bytes_per_s: f64,
    /// Keyframes sent per second, summed over sites.
    pub keyframes_per_s: f64,
    /// Receiving sites' CPU time per applied keyframe (µs).
    pub apply_us_per_keyframe: f64,
    /// Display delay: receiving sites' mean simulated-time lag behind the owner while
    /// following it (ms): the cost of the playout lag.
    pub display_delay_ms: f64,
}

#[derive(Debug, Serialize)]
pub struct SyncBench {
    pub scene_hash: String,
    pub seconds: f64,
    pub rows: Vec<SyncRow>,
}

/// The bench's cast: the instructor lifts the gallbladder; both trainees receive (trainee
/// B on the slowed machine in the unequal-machines row).
fn cast(slowdown: f64, receiver_cg: Option<usize>) -> Vec<DemoSite> {
    let mut c = cosurg::demo::cast(3, slowdown);
    c[1].tool = None;
    c[2].tool = None;
    if let Some(n) = receiver_cg {
        c[2].extra = vec!["--cg-iterations".into(), n.to_string()];
    }
    c
}

pub fn run(args: SyncArgs) -> Result<()> {
    let out = out_dir(&args.out, "bench-sync");
    let scene = sim_core::sim_scene::builtin::cholecystectomy();
    let mut cases: Vec<(SyncStrategy, String, f64, Option<usize>)> = Vec::new();
    for s in &args.strategies {
        for p in &args.presets {
            cases.push((*s, p.clone(), 1.0, None));
        }
    }
    if args.slowdown > 1.0 {
        cases.push((SyncStrategy::Keyframe, "metro".into(), args.slowdown, None));
    }
    if args.reduced_cg > 0 {
        for s in [SyncStrategy::Keyframe, SyncStrategy::InputOnly] {
            for p in ["lan", "good"] {
                cases.push((s, p.into(), 1.0, Some(args.reduced_cg)));
            }
        }
    }
    let bar = ProgressBar::new(cases.len() as u64).with_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} runs  {msg}").expect("template"),
    );
    let mut rows = Vec::new();
    for (i, (strategy, preset, slowdown, receiver_cg)) in cases.iter().enumerate() {
        bar.set_message(format!(
            "{} over {preset}, slowdown {slowdown}",
            strategy.name()
        ));
        let tag = receiver_cg.map_or(String::new(), |n| format!("-cg{n}"));
        let run = SessionRun {
            cast: cast(*slowdown, *receiver_cg),
            seconds: args.seconds,
            strategy: *strategy,
            preset: Some(preset.clone()),
            seed: args.seed + i as u64,
            out: out.join(format!("{}-{preset}-x{slowdown}{tag}", strategy.name())),
            vtu_interval: 0.0,
            progress: false,
            dt: Some(0.004),
            extra: vec!["--playout-lag".into(), args.playout_lag.to_string()],
            reset_at: None,
            view: false,
        };
        let (reports, series) = run_session(&run)?;
        let receivers: Vec<_> = reports
            .iter()
            .filter(|r| r.divergence_max_mm.is_some())
            .collect();
        let n = reports.len().max(1) as f64;
        let wall = reports
            .iter()
            .map(|r| r.wall_seconds)
            .fold(0.0, f64::max)
            .max(1e-9);
        let applied: u64 = reports.iter().map(|r| r.keyframes_applied).sum();
        let settled_from = args.seconds - 1.0;
        let settled = series
            .iter()
            .flat_map(|s| s.points.iter().filter(|p| p.0 >= settled_from).map(|p| p.1))
            .fold(0.0, f64::max);
        rows.push(SyncRow {
            strategy: strategy.name().into(),
            preset: preset.clone(),
            slowdown: *slowdown,
            receiver_cg_iterations: *receiver_cg,
            divergence_max_mm: receivers
                .iter()
                .filter_map(|r| r.divergence_max_mm)
                .fold(0.0, f64::max),
            divergence_rms_mm: (receivers
                .iter()
                .filter_map(|r| r.divergence_rms_mm)
                .map(|v| v * v)
                .sum::<f64>()
                / receivers.len().max(1) as f64)
                .sqrt(),
            settled_divergence_max_mm: settled,
            up_bytes_per_s: reports.iter().map(|r| r.up_bytes_per_s).sum::<f64>() / n,
            down_bytes_per_s: reports.iter().map(|r| r.down_bytes_per_s).sum::<f64>() / n,
            keyframes_per_s: reports.iter().map(|r| r.keyframes_sent).sum::<u64>() as f64 / wall,
            display_delay_ms: mean(receivers.iter().map(|r| r.playout_lag_ms)),
            apply_us_per_keyframe: if applied == 0 {
                0.0
            } else {
                reports
                    .iter()
                    .map(|r| r.apply_us_per_keyframe * r.keyframes_applied as f64)
                    .sum::<f64>()
                    / applied as f64
            },
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    write_plots(&out, &rows)?;
    let bench = SyncBench {
        scene_hash: scene.hash.clone(),
        seconds: args.seconds,
        rows,
    };
    std::fs::write(
        out.join("bench-sync.json"),
        serde_json::to_string_pretty(&bench)?,
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&bench)?);
    } else {
        println!(
            "{:<11} {:<17} {:>4} {:>4} {:>10} {:>10} {:>12} {:>11} {:>11} {:>8} {:>9} {:>9}",
            "strategy",
            "preset",
            "slow",
            "B cg",
            "div max",
            "div rms",
            "settled max",
            "up B/s",
            "down B/s",
            "kf/s",
            "apply µs",
            "delay ms"
        );
        for r in &bench.rows {
            println!(
                "{:<11} {:<17} {:>4} {:>4} {:>7.2} mm {:>7.2} mm {:>9.2} mm {:>11.0} {:>11.0} {:>8.1} {:>9.1} {:>9.0}",
                r.strategy,
                r.preset,
                r.slowdown,
                r.receiver_cg_iterations
                    .map_or("-".to_string(), |n| n.to_string()),
                r.divergence_max_mm,
                r.divergence_rms_mm,
                r.settled_divergence_max_mm,
                r.up_bytes_per_s,
                r.down_bytes_per_s,
                r.keyframes_per_s,
                r.apply_us_per_keyframe,
                r.display_delay_ms
            );
        }
        println!(
            "\nwrote {} (bench-sync.json, divergence_vs_delay.png/svg, bandwidth.png/svg)",
            out.display()
        );
    }
    Ok(())
}

/// Mean of the values (0 for none).
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// One-way delay (ms) of each preset, for the x axis.
fn preset_delay_ms(p: &str) -> f64 {
    netem::ImpairmentConfig::preset(p).map_or(0.0, |c| c.delay_ms)
}

fn write_plots(out: &std::path::Path, rows: &[SyncRow]) -> Result<()> {
    let mut div = Vec::new();
    let mut bw = Vec::new();
    for s in ["keyframe", "full-state", "input-only"] {
        let mut pts: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.strategy == s && r.slowdown == 1.0 && r.receiver_cg_iterations.is_none())
            .map(|r| {
                (
                    preset_delay_ms(&r.preset).max(0.1),
                    r.divergence_max_mm.max(1e-3),
                )
            })
            .collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        if pts.is_empty() {
            continue;
        }
        div.push(Series {
            label: s.into(),
            points: pts,
        });
        let mut b: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.strategy == s && r.slowdown == 1.0 && r.receiver_cg_iterations.is_none())
            .map(|r| {
                (
                    preset_delay_ms(&r.preset).max(0.1),
                    (r.up_bytes_per_s + r.down_bytes_per_s).max(1.0),
                )
            })
            .collect();
        b.sort_by(|a, c| a.0.total_cmp(&c.0));
        bw.push(Series {
            label: s.into(),
            points: b,
        });
    }
    write_chart(
        out,
        "divergence_vs_delay",
        &Chart {
            title: "divergence from the owning site against one-way delay",
            x_label: "one-way delay of the preset (ms)",
            y_label: "max divergence (mm)",
            log_x: true,
            log_y: true,
            scatter: false,
        },
        &div,
    )?;
    write_chart(
        out,
        "bandwidth",
        &Chart {
            title: "bytes per second per site (up + down) by strategy",
            x_label: "one-way delay of the preset (ms)",
            y_label: "bytes/s per site",
            log_x: true,
            log_y: true,
            scatter: false,
        },
        &bw,
    )?;
    Ok(())
}
