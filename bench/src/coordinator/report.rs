//! The table and plots of `cosurg bench coordinator`.

use super::*;
use cosurg::plot::{Chart, Series, write_chart};

pub(super) fn table(b: &CoordinatorBench) -> String {
    let mut s = format!(
        "{:>8} {:>5} {:>9} {:>9} {:>9} {:>8} {:>8} {:>9} {:>9} {:>11} {:>7} {:>8} {:>9} {:>7} {:>5} {:>5}\n",
        "sessions",
        "sites",
        "p50 ms",
        "p99 ms",
        "max ms",
        "kf p50",
        "kf p99",
        "dgram rx",
        "loss",
        "kf rx",
        "CPU %",
        "CPU/site",
        "RSS MiB",
        "sites %",
        "load",
        "goal"
    );
    for r in &b.rows {
        s += &format!(
            "{:>8} {:>5} {:>9.3} {:>9.3} {:>9.2} {:>8.2} {:>8.2} {:>9} {:>8.3}% {:>11} {:>7.1} {:>8.2} {:>9.1} {:>7.0} {:>5.1} {:>5}\n",
            r.sessions,
            r.sites,
            r.relay_p50_ms,
            r.relay_p99_ms,
            r.relay_max_ms,
            r.keyframe_p50_ms,
            r.keyframe_p99_ms,
            r.datagrams_received,
            100.0 * r.datagram_loss,
            format!("{}/{}", r.keyframes_received, r.keyframes_expected),
            r.coordinator_cpu_percent,
            r.cpu_percent_per_site,
            r.coordinator_rss_mib,
            r.sites_cpu_percent,
            r.load_average,
            if r.meets_goal { "yes" } else { "no" }
        );
    }
    s += &format!(
        "mix: poses {} Hz and stamps {} Hz per site, keyframes {} Hz per session × ~{} B; window {} s after {} s warm-up; {} cores shared by the coordinator and all synthetic sites\nknee (largest load meeting p99 ≤ {GOAL_P99_MS} ms, nothing dropped): {}\n",
        b.pose_hz,
        b.stamp_hz,
        b.keyframe_hz,
        b.keyframe_bytes,
        b.seconds,
        b.warmup,
        b.cores,
        b.knee_sites
            .map_or("none".to_string(), |n| format!("{n} sites"))
    );
    if b.record {
        s += "coordinator recording every session (--record):";
        for r in &b.rows {
            let bytes = r.recording_bytes.unwrap_or(0) as f64;
            // The recording spans warm-up, window and drain.
            let minutes = (b.warmup + b.seconds + 0.5) / 60.0;
            s += &format!(
                " {} sites {:.2} MB/session-minute;",
                r.sites,
                bytes / 1e6 / r.sessions.max(1) as f64 / minutes
            );
        }
        s += "\n";
    }
    s
}

pub(super) fn write_plots(out: &Path, rows: &[LoadRow]) -> Result<()> {
    let pts = |f: &dyn Fn(&LoadRow) -> f64| -> Vec<(f64, f64)> {
        rows.iter()
            .map(|r| (r.sites as f64, f(r).max(1e-3)))
            .collect()
    };
    write_chart(
        out,
        "coordinator_latency",
        &Chart {
            title: "relay latency against sites on one coordinator",
            x_label: "sites (sessions × sites per session)",
            y_label: "latency (ms)",
            log_x: true,
            log_y: true,
            scatter: false,
        },
        &[
            Series {
                label: "datagram p50".into(),
                points: pts(&|r| r.relay_p50_ms),
            },
            Series {
                label: "datagram p99".into(),
                points: pts(&|r| r.relay_p99_ms),
            },
            Series {
                label: "keyframe p99".into(),
                points: pts(&|r| r.keyframe_p99_ms),
            },
            Series {
                label: "goal p99".into(),
                points: pts(&|_| GOAL_P99_MS),
            },
        ],
    )?;
    write_chart(
        out,
        "coordinator_cost",
        &Chart {
            title: "coordinator CPU and datagram loss against sites",
            x_label: "sites (sessions × sites per session)",
            y_label: "CPU (% of one core) / loss (%)",
            log_x: true,
            log_y: false,
            scatter: false,
        },
        &[
            Series {
                label: "coordinator CPU %".into(),
                points: pts(&|r| r.coordinator_cpu_percent),
            },
            Series {
                label: "datagram loss %".into(),
                points: pts(&|r| 100.0 * r.datagram_loss),
            },
        ],
    )?;
    Ok(())
}
