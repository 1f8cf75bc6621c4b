//! `cosurg bench sync`: how far apart are the sites' organs, at what bandwidth and display
//! delay, when the network is bad and the machines are unequal?
//!
//! Each case runs the demo's first act (the instructor lifts the gallbladder, both trainees
//! follow) over real QUIC through the in-process impairment of every site's link, for one
//! strategy × preset (plus unequal-machine cases), once per impairment seed (`--seeds`, at
//! least 5 for a row worth reporting): a single run is not a measurement, the spread
//! between seeds is part of the result. Each row reports the median and the worst over its
//! seeds. Divergence is measured against the owning site at the same simulated time over
//! every embedded-surface vertex; "settled" is the last second, after every tool stopped.
//! Display delay is how far the receivers trail the owner in simulated time; the owner's
//! state reaches a follower through two impaired links (owner → coordinator → follower),
//! so it cannot be below twice the preset's one-way delay (the "path" delay).

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
    /// Presets to run (comma-separated; netem presets, `burst` and `outage` included;
    /// empty: only the unequal-machine rows).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "lan,metro,good,average,poor,intercontinental,burst,outage"
    )]
    pub presets: Vec<String>,
    /// Strategies to run (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "hybrid,keyframe,full-state,input-only"
    )]
    pub strategies: Vec<SyncStrategy>,
    /// Slowdown of trainee B in the extra "unequal machines" rows (metro, every strategy
    /// but full-state; 1: no such rows).
    #[arg(long, default_value_t = 3.0)]
    pub slowdown: f64,
    /// CG budget of trainee B in the extra "unequal fidelity" rows (every strategy but
    /// full-state, over lan and good): a slower machine that cuts its solver budget to keep
    /// up, so that its simulation is no longer the owner's (0: no such rows).
    #[arg(long, default_value_t = 5)]
    pub reduced_cg: usize,
    /// Further arguments of every site (`cosurg join`), whitespace-separated, for
    /// experiments: e.g. `--site-args "--adaptivity false"`. Recorded in the JSON.
    #[arg(long, value_delimiter = ' ', allow_hyphen_values = true)]
    pub site_args: Vec<String>,
    /// Presets of the unequal-fidelity rows (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "lan,good")]
    pub unequal_presets: Vec<String>,
    /// Impairment seeds per row (the row reports median and worst over them).
    #[arg(long, default_value_t = 5)]
    pub seeds: u64,
    /// First impairment seed.
    #[arg(long, default_value_t = 11)]
    pub seed: u64,
    /// Playout lag of every site (`cosurg join --playout-lag`): `auto` or milliseconds
    /// (0: followers run at the owner's simulated time and extrapolate).
    #[arg(long, default_value = "auto")]
    pub playout_lag: cosurg::site::PlayoutLag,
    /// Lattice cell size (m) of every body on every site, instead of the scene's (the
    /// sync of a finer organ; `cosurg join --cell`).
    #[arg(long, value_name = "M")]
    pub cell: Option<f64>,
    /// Run every session this many times slower than real time, the impairment stretched
    /// to match (time dilation; `cosurg demo --time-scale`): the sync of three sites
    /// measured, in session time, as on a machine this much faster. Use it where the sites
    /// do not keep real time (their `sim_rate_hz` below 1/dt).
    #[arg(long, default_value = "1", value_name = "FACTOR")]
    pub time_scale: server::TimeScale,
}

/// One case: strategy, preset and the receivers' machines.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SyncCase {
    pub strategy: String,
    pub preset: String,
    pub slowdown: f64,
    /// Trainee B's CG budget in the "unequal fidelity" rows (null: the scene's, as every
    /// other site).
    pub receiver_cg_iterations: Option<usize>,
}

/// What one run (one seed of a case) measured.
#[derive(Debug, Clone, Serialize)]
pub struct SyncRun {
    pub seed: u64,
    /// Max / RMS over the run and over receiving sites (mm).
    pub divergence_max_mm: f64,
    pub divergence_rms_mm: f64,
    /// Max over the last second, after every tool stopped (mm).
    pub settled_divergence_max_mm: f64,
    /// Mean over sites of application bytes per second, up and down.
    pub up_bytes_per_s: f64,
    pub down_bytes_per_s: f64,
    /// Keyframes sent per second, summed over sites.
    pub keyframes_per_s: f64,
    /// Receiving sites' CPU time per applied keyframe (µs).
    pub apply_us_per_keyframe: f64,
    /// Display delay: receiving sites' mean simulated-time lag behind the owner while
    /// following it (ms).
    pub display_delay_ms: f64,
    /// The one-way delay the impaired links added to the packets they delivered, as the
    /// packets experienced it: the sites' mean up-link delay plus their mean down-link
    /// delay (ms; site → coordinator → site). Above the preset's when it has jitter: the
    /// presets keep packet order, so a packet waits for the earlier ones.
    pub measured_path_ms: f64,
    /// The slowest site's simulated steps per second of session time, a follower's counted
    /// with its playout lag ([`cosurg::site::SiteReport::kept_real_time`]): below 1/dt (250 Hz) a site
    /// did not keep up, and its lag and delay say more of the machine than of the sync
    /// (then run with `--time-scale`).
    pub slowest_site_hz: f64,
}

/// Median and worst (largest) of one measure over a row's seeds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Spread {
    pub median: f64,
    pub worst: f64,
    pub best: f64,
}

impl Spread {
    fn of(values: impl Iterator<Item = f64>) -> Spread {
        let mut v: Vec<f64> = values.collect();
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            return Spread {
                median: f64::NAN,
                worst: f64::NAN,
                best: f64::NAN,
            };
        }
        let n = v.len();
        let median = if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        };
        Spread {
            median,
            worst: v[n - 1],
            best: v[0],
        }
    }
}

/// A case over all its seeds.
#[derive(Debug, Clone, Serialize)]
pub struct SyncRow {
    #[serde(flatten)]
    pub case: SyncCase,
    /// The preset's one-way delay per link, and the owner → coordinator → follower path's
    /// (twice that): the least display delay possible (ms).
    pub preset_one_way_ms: f64,
    pub path_one_way_ms: f64,
    pub divergence_max_mm: Spread,
    pub divergence_rms_mm: Spread,
    pub settled_divergence_max_mm: Spread,
    /// Up + down bytes per second per site.
    pub bytes_per_s: Spread,
    pub keyframes_per_s: Spread,
    pub display_delay_ms: Spread,
    /// Display delay above the path's one-way delay (ms).
    pub delay_above_path_ms: Spread,
    /// The path's one-way delay as its packets experienced it ([`SyncRun::measured_path_ms`]),
    /// and the display delay above that (ms).
    pub measured_path_ms: Spread,
    pub delay_above_measured_path_ms: Spread,
    /// The slowest site's step rate over the row's runs (Hz of session time).
    pub slowest_site_hz: f64,
    pub runs: Vec<SyncRun>,
}

#[derive(Debug, Serialize)]
pub struct SyncBench {
    pub scene_hash: String,
    /// The lattice cell (m) of every body when `--cell` replaced the scene's.
    pub cell_m: Option<f64>,
    pub seconds: f64,
    pub seeds: u64,
    /// The sessions' time dilation (`--time-scale`; 1: real time).
    pub time_scale: f64,
    /// `--site-args` (empty: none).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub site_args: Vec<String>,
    pub rows: Vec<SyncRow>,
}

/// The bench's cast: the instructor lifts the gallbladder; both trainees receive (trainee
/// B on the slowed machine in the unequal-machines row).
fn cast(slowdown: f64, receiver_cg: Option<usize>, site_args: &[String]) -> Vec<DemoSite> {
    let mut c = cosurg::demo::cast(3, slowdown);
    c[1].tools.clear();
    c[2].tools.clear();
    if let Some(n) = receiver_cg {
        c[2].extra = vec!["--cg-iterations".into(), n.to_string()];
    }
    for site in &mut c {
        site.extra.extend(site_args.iter().cloned());
    }
    c
}

/// Every case the arguments ask for, in table order.
fn cases(args: &SyncArgs) -> Vec<(SyncStrategy, SyncCase)> {
    let case = |s: &SyncStrategy, p: &str, slowdown: f64, cg: Option<usize>| {
        (
            *s,
            SyncCase {
                strategy: s.name().into(),
                preset: p.into(),
                slowdown,
                receiver_cg_iterations: cg,
            },
        )
    };
    let mut cases = Vec::new();
    for s in &args.strategies {
        for p in args.presets.iter().filter(|p| !p.is_empty()) {
            cases.push(case(s, p, 1.0, None));
        }
    }
    let unequal = args
        .strategies
        .iter()
        .filter(|s| !matches!(s, SyncStrategy::FullState { .. }));
    for s in unequal {
        if args.slowdown > 1.0 {
            cases.push(case(s, "metro", args.slowdown, None));
        }
        if args.reduced_cg > 0 {
            for p in &args.unequal_presets {
                cases.push(case(s, p, 1.0, Some(args.reduced_cg)));
            }
        }
    }
    cases
}

pub fn run(args: SyncArgs) -> Result<()> {
    anyhow::ensure!(args.seeds >= 1, "--seeds must be at least 1");
    for p in args.presets.iter().chain(&args.unequal_presets) {
        if !p.is_empty() {
            netem::ImpairmentConfig::preset(p)?;
        }
    }
    let out = out_dir(&args.out, "bench-sync");
    let scene =
        cosurg::scene_arg::load_scene_with_cell(Some("builtin:cholecystectomy"), args.cell)?;
    cosurg::demo::check_cell(&scene, args.cell)?;
    let cases = cases(&args);
    let bar = ProgressBar::new(cases.len() as u64 * args.seeds).with_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} runs  {msg}").expect("template"),
    );
    let mut rows = Vec::new();
    for (strategy, case) in &cases {
        let mut runs = Vec::new();
        for k in 0..args.seeds {
            let seed = args.seed + k;
            bar.set_message(format!(
                "{} over {}, slowdown {}, seed {seed}",
                case.strategy, case.preset, case.slowdown
            ));
            runs.push(run_case(&args, &out, *strategy, case, seed)?);
            bar.inc(1);
        }
        rows.push(summarise(case.clone(), runs));
    }
    bar.finish_and_clear();
    write_plots(&out, &rows)?;
    let bench = SyncBench {
        scene_hash: scene.hash.clone(),
        cell_m: args.cell,
        seconds: args.seconds,
        seeds: args.seeds,
        time_scale: args.time_scale.factor(),
        site_args: args.site_args.clone(),
        rows,
    };
    std::fs::write(
        out.join("bench-sync.json"),
        serde_json::to_string_pretty(&bench)?,
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&bench)?);
    } else {
        print!("{}", table(&bench));
        println!(
            "\nwrote {} (bench-sync.json, sync_divergence.png/svg, sync_bandwidth.png/svg, \
             sync_delay.png/svg)",
            out.display()
        );
    }
    Ok(())
}

/// One run of a case with one impairment seed.
fn run_case(
    args: &SyncArgs,
    out: &std::path::Path,
    strategy: SyncStrategy,
    case: &SyncCase,
    seed: u64,
) -> Result<SyncRun> {
    let tag = case
        .receiver_cg_iterations
        .map_or(String::new(), |n| format!("-cg{n}"));
    let run = SessionRun {
        cast: cast(case.slowdown, case.receiver_cg_iterations, &args.site_args),
        seconds: args.seconds,
        strategy,
        preset: Some(case.preset.clone()),
        seed,
        out: out.join(format!(
            "{}-{}-x{}{tag}-s{seed}",
            case.strategy, case.preset, case.slowdown
        )),
        vtu_interval: 0.0,
        progress: false,
        dt: Some(0.004),
        extra: vec!["--playout-lag".into(), args.playout_lag.to_string()],
        reset_at: None,
        view: false,
        cell: args.cell,
        time_scale: args.time_scale,
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
    Ok(SyncRun {
        seed,
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
        measured_path_ms: mean(reports.iter().filter_map(|r| r.link_up_delay_ms))
            + mean(reports.iter().filter_map(|r| r.link_down_delay_ms)),
        // Steps per simulated second times the simulated (plus lag) per session second.
        slowest_site_hz: reports
            .iter()
            .map(|r| r.sim_rate_hz * r.wall_seconds / r.sim_seconds.max(1e-9) * r.kept_real_time())
            .fold(f64::INFINITY, f64::min),
        apply_us_per_keyframe: if applied == 0 {
            0.0
        } else {
            reports
                .iter()
                .map(|r| r.apply_us_per_keyframe * r.keyframes_applied as f64)
                .sum::<f64>()
                / applied as f64
        },
    })
}

/// Median and worst of every measure over a case's runs.
fn summarise(case: SyncCase, runs: Vec<SyncRun>) -> SyncRow {
    let preset_one_way_ms = preset_delay_ms(&case.preset);
    let path_one_way_ms = 2.0 * preset_one_way_ms;
    let spread = |f: fn(&SyncRun) -> f64| Spread::of(runs.iter().map(f));
    SyncRow {
        preset_one_way_ms,
        path_one_way_ms,
        divergence_max_mm: spread(|r| r.divergence_max_mm),
        divergence_rms_mm: spread(|r| r.divergence_rms_mm),
        settled_divergence_max_mm: spread(|r| r.settled_divergence_max_mm),
        bytes_per_s: spread(|r| r.up_bytes_per_s + r.down_bytes_per_s),
        keyframes_per_s: spread(|r| r.keyframes_per_s),
        display_delay_ms: spread(|r| r.display_delay_ms),
        delay_above_path_ms: Spread::of(runs.iter().map(|r| r.display_delay_ms - path_one_way_ms)),
        measured_path_ms: spread(|r| r.measured_path_ms),
        delay_above_measured_path_ms: spread(|r| r.display_delay_ms - r.measured_path_ms),
        slowest_site_hz: runs
            .iter()
            .map(|r| r.slowest_site_hz)
            .fold(f64::INFINITY, f64::min),
        case,
        runs,
    }
}

/// The text table: `median / worst` of each measure per row.
fn table(bench: &SyncBench) -> String {
    use std::fmt::Write;
    let mut t = String::new();
    let _ = writeln!(
        t,
        "{} seed(s) per row; each cell median / worst over them\n\
         {:<11} {:<17} {:>4} {:>4} {:>17} {:>15} {:>15} {:>17} {:>13} {:>6} {:>13} {:>9} {:>13} {:>7}",
        bench.seeds,
        "strategy",
        "preset",
        "slow",
        "B cg",
        "div max mm",
        "div rms mm",
        "settled mm",
        "B/s up+down",
        "delay ms",
        "path",
        "above path",
        "measured",
        "above it",
        "site Hz"
    );
    for r in &bench.rows {
        let c = &r.case;
        let _ = writeln!(
            t,
            "{:<11} {:<17} {:>4} {:>4} {:>8.2} / {:<6.2} {:>6.2} / {:<6.2} {:>6.2} / {:<6.2} {:>8.0} / {:<8.0}{:>5.0} / {:<5.0} {:>6.0} {:>5.0} / {:<5.0} {:>9.0} {:>5.0} / {:<5.0} {:>7.0}",
            c.strategy,
            c.preset,
            c.slowdown,
            c.receiver_cg_iterations
                .map_or("-".to_string(), |n| n.to_string()),
            r.divergence_max_mm.median,
            r.divergence_max_mm.worst,
            r.divergence_rms_mm.median,
            r.divergence_rms_mm.worst,
            r.settled_divergence_max_mm.median,
            r.settled_divergence_max_mm.worst,
            r.bytes_per_s.median,
            r.bytes_per_s.worst,
            r.display_delay_ms.median,
            r.display_delay_ms.worst,
            r.path_one_way_ms,
            r.delay_above_path_ms.median,
            r.delay_above_path_ms.worst,
            r.measured_path_ms.median,
            r.delay_above_measured_path_ms.median,
            r.delay_above_measured_path_ms.worst,
            r.slowest_site_hz,
        );
    }
    if bench.time_scale != 1.0 {
        let _ = writeln!(
            t,
            "time-dilated ×{}: every time and rate above is in session time",
            bench.time_scale
        );
    }
    t
}

/// Mean of the values (0 for none).
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// One-way delay (ms) of each preset.
fn preset_delay_ms(p: &str) -> f64 {
    netem::ImpairmentConfig::preset(p).map_or(0.0, |c| c.delay_ms)
}

/// The x position of a preset in the plots: its rank in the table, shifted a little per
/// strategy so that the strategies' seeds do not hide each other.
fn preset_x(presets: &[String], preset: &str, strategy: usize) -> f64 {
    let rank = presets.iter().position(|p| p == preset).unwrap_or(0) as f64 + 1.0;
    rank + 0.12 * (strategy as f64 - 1.5)
}

/// Every seed of every equal-machines row as one point (the spread is the cloud), one
/// series per strategy.
fn write_plots(out: &std::path::Path, rows: &[SyncRow]) -> Result<()> {
    let equal: Vec<&SyncRow> = rows
        .iter()
        .filter(|r| r.case.slowdown == 1.0 && r.case.receiver_cg_iterations.is_none())
        .collect();
    let mut presets: Vec<String> = Vec::new();
    let mut strategies: Vec<String> = Vec::new();
    for r in &equal {
        if !presets.contains(&r.case.preset) {
            presets.push(r.case.preset.clone());
        }
        if !strategies.contains(&r.case.strategy) {
            strategies.push(r.case.strategy.clone());
        }
    }
    let x_label = format!(
        "preset: {}",
        presets
            .iter()
            .enumerate()
            .map(|(i, p)| format!("{} {p}", i + 1))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let series = |measure: &dyn Fn(&SyncRun, &SyncRow) -> f64| -> Vec<Series> {
        strategies
            .iter()
            .enumerate()
            .map(|(k, s)| Series {
                label: s.clone(),
                points: equal
                    .iter()
                    .filter(|r| &r.case.strategy == s)
                    .flat_map(|r| {
                        let x = preset_x(&presets, &r.case.preset, k);
                        r.runs.iter().map(move |run| (x, measure(run, r)))
                    })
                    .collect(),
            })
            .collect()
    };
    write_chart(
        out,
        "sync_divergence",
        &Chart {
            title: "max divergence from the owning site, every seed",
            x_label: &x_label,
            y_label: "max divergence (mm)",
            log_x: false,
            log_y: true,
            scatter: true,
        },
        &series(&|run, _| run.divergence_max_mm.max(1e-3)),
    )?;
    write_chart(
        out,
        "sync_bandwidth",
        &Chart {
            title: "bytes per second per site (up + down), every seed",
            x_label: &x_label,
            y_label: "bytes/s per site",
            log_x: false,
            log_y: true,
            scatter: true,
        },
        &series(&|run, _| (run.up_bytes_per_s + run.down_bytes_per_s).max(1.0)),
    )?;
    write_chart(
        out,
        "sync_delay",
        &Chart {
            title: "display delay above the owner-to-follower path delay, every seed",
            x_label: &x_label,
            y_label: "display delay - 2 x preset one-way delay (ms)",
            log_x: false,
            log_y: false,
            scatter: true,
        },
        &series(&|run, row| run.display_delay_ms - row.path_one_way_ms),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::Spread;

    #[test]
    fn spread_takes_median_and_worst() {
        let s = Spread::of([3.0, 1.0, 9.0, 2.0, 5.0].into_iter());
        assert_eq!((s.median, s.worst, s.best), (3.0, 9.0, 1.0));
        let s = Spread::of([4.0, 1.0].into_iter());
        assert_eq!((s.median, s.worst), (2.5, 4.0));
        assert!(Spread::of(std::iter::empty()).median.is_nan());
    }
}
