//! Unit tests of the impairment model.

use super::*;

fn deliver(v: &Verdict) -> &[u64] {
    match v {
        Verdict::Deliver { at_us } => at_us,
        Verdict::Drop(_) => &[],
    }
}

#[test]
fn presets_parse_and_are_one_way() {
    for name in PRESET_NAMES {
        let c = ImpairmentConfig::preset(name).unwrap();
        c.validate().unwrap();
        assert!(!c.reorder);
    }
    let p = ImpairmentConfig::preset("poor").unwrap();
    assert_eq!((p.delay_ms, p.jitter_ms, p.loss_pct), (200.0, 30.0, 10.0));
    assert!(ImpairmentConfig::preset("moon").is_err());
}

#[test]
fn passthrough_delivers_immediately() {
    let mut m = Impairment::new(ImpairmentConfig::none(), 1);
    for i in 0..100 {
        assert_eq!(
            m.on_packet(i * 10, 100),
            Verdict::Deliver {
                at_us: vec![i * 10]
            }
        );
    }
    assert_eq!(m.counters().delivered, 100);
}

#[test]
fn deterministic_for_seed() {
    let cfg = ImpairmentConfig::preset("poor").unwrap();
    let run = |seed| {
        let mut m = Impairment::new(cfg.clone(), seed);
        (0..1000)
            .map(|i| m.on_packet(i * 1000, 500))
            .collect::<Vec<_>>()
    };
    assert_eq!(run(7), run(7));
    assert_ne!(run(7), run(8));
}

/// Loss fraction within 4 binomial standard deviations.
#[test]
fn loss_fraction_binomial() {
    for (loss, seed) in [(0.2, 1u64), (2.0, 2), (10.0, 3), (50.0, 4)] {
        let cfg = ImpairmentConfig {
            loss_pct: loss,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, seed);
        let n = 200_000u64;
        for i in 0..n {
            m.on_packet(i * 100, 100);
        }
        let c = m.counters();
        assert_eq!(c.sent, c.delivered + c.dropped());
        let p = loss / 100.0;
        let sd = (n as f64 * p * (1.0 - p)).sqrt();
        let dev = (c.dropped_loss as f64 - n as f64 * p).abs();
        assert!(
            dev < 4.0 * sd,
            "loss {loss}: {} lost, sd {sd}",
            c.dropped_loss
        );
    }
}

/// The mean delay counted is what the packets experienced: exactly the configured
/// delay without jitter; with jitter and packet order kept, above it by the wait for
/// earlier packets (compared with the release times the model returned).
#[test]
fn mean_delay_is_what_packets_experienced() {
    let steady = ImpairmentConfig {
        delay_ms: 40.0,
        ..Default::default()
    };
    let mut m = Impairment::new(steady, 1);
    assert_eq!(m.counters().mean_delay_ms(), None);
    for i in 0..100 {
        m.on_packet(i * 8_000, 100);
    }
    assert_eq!(m.counters().mean_delay_ms(), Some(40.0));

    let cfg = ImpairmentConfig::preset("poor").unwrap();
    let mut m = Impairment::new(cfg, 3);
    let mut held_us = Vec::new();
    for i in 0..20_000u64 {
        if let Verdict::Deliver { at_us } = m.on_packet(i * 8_000, 100) {
            held_us.push((at_us[0] - i * 8_000) as f64);
        }
    }
    let expected = held_us.iter().sum::<f64>() / held_us.len() as f64 / 1e3;
    let mean = m.counters().mean_delay_ms().unwrap();
    assert!((mean - expected).abs() < 1e-9, "{mean} against {expected}");
    // Packets 8 ms apart with 30 ms of jitter wait for one another.
    assert!(mean > 210.0, "{mean} ms");
}

fn mean_sd(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

#[test]
fn delay_distribution_normal_and_uniform() {
    let n = 100_000;
    for (dist, want_sd) in [
        (JitterDist::Normal, 15.0),
        (JitterDist::Uniform, 15.0 / 3f64.sqrt()),
    ] {
        let cfg = ImpairmentConfig {
            delay_ms: 100.0,
            jitter_ms: 15.0,
            jitter_dist: dist,
            reorder: true,
            ..Default::default()
        };
        let mut m = Impairment::new(cfg, 11);
        let mut delays = Vec::with_capacity(n);
        for i in 0..n as u64 {
            let now = i * 1000;
            let v = m.on_packet(now, 100);
            delays.push((deliver(&v)[0] - now) as f64 / 1000.0);
        }
        let (mean, sd) = mean_sd(&delays);
        // Standard error of the mean is 15/sqrt(1e5) ≈ 0.05 ms.
        assert!((mean - 100.0).abs() < 0.3, "{dist:?} mean {mean}");
        assert!((sd - want_sd).abs() < 0.02 * want_sd, "{dist:?} sd {sd}");
        if dist == JitterDist::Uniform {
            assert!(delays.iter().all(|&d| (84.999..=115.001).contains(&d)));
        }
        // Packets 1 ms apart with 15 ms jitter overtake each other often.
        assert!(m.counters().reordered > n as u64 / 10);
    }
}

#[test]
fn no_reordering_when_disabled() {
    let cfg = ImpairmentConfig {
        delay_ms: 50.0,
        jitter_ms: 20.0,
        dup_pct: 5.0,
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, 5);
    let mut last = 0;
    for i in 0..50_000u64 {
        let now = i * 500;
        for &at in deliver(&m.on_packet(now, 100)) {
            assert!(at >= last, "release went backwards");
            assert!(at >= now);
            last = at;
        }
    }
    assert_eq!(m.counters().reordered, 0);
    assert!(m.counters().duplicated > 2000);
}

#[test]
fn duplication_fraction() {
    let cfg = ImpairmentConfig {
        dup_pct: 10.0,
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, 9);
    let n = 100_000u64;
    let mut copies = 0u64;
    for i in 0..n {
        copies += deliver(&m.on_packet(i, 10)).len() as u64;
    }
    let c = m.counters();
    assert_eq!(copies, c.released());
    let sd = (n as f64 * 0.1 * 0.9).sqrt();
    assert!((c.duplicated as f64 - 0.1 * n as f64).abs() < 4.0 * sd);
}

#[test]
fn rate_cap_throughput_and_queue_drops() {
    // 800 kbit/s = 100 kB/s; offer 1000-byte packets at 200 kB/s for 10 s.
    let cfg = ImpairmentConfig {
        rate_kbps: Some(800.0),
        bucket_bytes: 3000,
        queue_pkts: 50,
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, 3);
    let mut releases = Vec::new();
    for i in 0..2000u64 {
        let now = i * 5000; // 5 ms apart
        releases.extend_from_slice(deliver(&m.on_packet(now, 1000)));
    }
    let c = m.counters();
    assert_eq!(c.sent, c.delivered + c.dropped_rate);
    assert!(c.dropped_rate > 900, "{c}");
    // Throughput over the whole run: delivered bytes / span of departures.
    let span_s = (*releases.last().unwrap() - releases[0]) as f64 * 1e-6;
    let rate = (c.bytes_delivered - 1000) as f64 / span_s; // first packet starts the span
    assert!((rate - 100_000.0).abs() < 1000.0, "rate {rate} B/s");
    // Nothing departs before it arrives, and FIFO order holds.
    assert!(releases.windows(2).all(|w| w[0] <= w[1]));

    // Under the rate: no drops, no queueing beyond the packet's own transmission.
    let mut m = Impairment::new(
        ImpairmentConfig {
            rate_kbps: Some(800.0),
            queue_pkts: 5,
            ..Default::default()
        },
        3,
    );
    for i in 0..1000u64 {
        let now = i * 20_000; // 50 kB/s
        assert_eq!(deliver(&m.on_packet(now, 1000)), &[now]);
    }
    assert_eq!(m.counters().dropped_rate, 0);
}

#[test]
fn rate_cap_bounds_queueing_delay() {
    let cfg = ImpairmentConfig {
        rate_kbps: Some(80.0), // 10 kB/s: a 1000-byte packet every 100 ms
        bucket_bytes: 1000,
        queue_pkts: 10,
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, 3);
    let mut max_wait = 0;
    for i in 0..1000u64 {
        let now = i * 10_000;
        if let Verdict::Deliver { at_us } = m.on_packet(now, 1000) {
            max_wait = max_wait.max(at_us[0] - now);
        }
    }
    // At most 10 queued packets ahead + own transmission: ≤ 1.1 s.
    assert!((900_000..=1_100_000).contains(&max_wait), "{max_wait}");
}

#[test]
fn gilbert_elliott_burst_length() {
    let ge = GilbertElliott::new(0.01, 0.25);
    let cfg = ImpairmentConfig {
        burst: Some(ge),
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, 17);
    let n = 400_000u64;
    let mut bursts = Vec::new();
    let mut run = 0u64;
    for i in 0..n {
        match m.on_packet(i * 100, 100) {
            Verdict::Drop(DropReason::Burst) => run += 1,
            Verdict::Drop(r) => panic!("unexpected {r:?}"),
            Verdict::Deliver { .. } => {
                if run > 0 {
                    bursts.push(run as f64);
                }
                run = 0;
            }
        }
    }
    let (mean, sd) = mean_sd(&bursts);
    // Geometric with mean 1/p_bg = 4, sd sqrt(1-p)/p ≈ 3.46.
    let se = sd / (bursts.len() as f64).sqrt();
    assert!((mean - 4.0).abs() < 4.0 * se, "mean burst {mean} (se {se})");
    let loss = m.counters().dropped_burst as f64 / n as f64;
    let want = ge.stationary_loss();
    assert!((loss - want).abs() < 0.15 * want, "loss {loss} want {want}");
}

#[test]
fn outage_window() {
    let cfg = ImpairmentConfig::preset("lan")
        .unwrap()
        .with_outage(1.0, 2.0);
    let mut m = Impairment::new(cfg, 1);
    for ms in 0..5000u64 {
        let v = m.on_packet(ms * 1000, 100);
        let in_outage = (1000..3000).contains(&ms);
        assert_eq!(
            matches!(v, Verdict::Drop(DropReason::Outage)),
            in_outage,
            "{ms}"
        );
    }
    let c = m.counters();
    assert_eq!(c.dropped_outage, 2000);
    assert_eq!(c.delivered, 3000);
}

#[test]
fn validate_rejects_bad_values() {
    let bad = ImpairmentConfig {
        loss_pct: 150.0,
        ..Default::default()
    };
    assert!(bad.validate().is_err());
    let bad = ImpairmentConfig {
        burst: Some(GilbertElliott::new(2.0, 0.1)),
        ..Default::default()
    };
    assert!(bad.validate().is_err());
}

/// Loss rate and mean burst of a classic Gilbert chain, measured over `n` packets.
fn gilbert_measure(ge: GilbertElliott, seed: u64, n: u64) -> (f64, f64, usize) {
    let cfg = ImpairmentConfig {
        burst: Some(ge),
        ..Default::default()
    };
    let mut m = Impairment::new(cfg, seed);
    let (mut lost, mut run, mut bursts, mut burst_sum) = (0u64, 0u64, 0usize, 0u64);
    for i in 0..n {
        if matches!(m.on_packet(i * 100, 100), Verdict::Drop(_)) {
            lost += 1;
            run += 1;
        } else if run > 0 {
            bursts += 1;
            burst_sum += run;
            run = 0;
        }
    }
    let mean_burst = burst_sum as f64 / bursts.max(1) as f64;
    (lost as f64 / n as f64, mean_burst, bursts)
}

#[test]
fn burst_preset_matches_its_closed_form() {
    let c = ImpairmentConfig::preset("burst").unwrap();
    assert_eq!(c.loss_pct, 0.0);
    let ge = c.burst.unwrap();
    assert!((ge.stationary_loss() - 0.01 / 0.21).abs() < 1e-12);
    assert_eq!(ge.mean_bad_run(), 5.0);
    // 2 M packets: ~19,000 bursts; the burst mean (geometric, sd = √0.8 / 0.2 ≈ 4.47)
    // has a standard error of ≈ 0.03 packets (4 se allowed); the loss rate is held to
    // 10 %.
    let (loss, mean_burst, bursts) = gilbert_measure(ge, 5, 2_000_000);
    let se_burst = 0.8f64.sqrt() / 0.2 / (bursts as f64).sqrt();
    assert!(
        (mean_burst - 5.0).abs() < 4.0 * se_burst,
        "mean burst {mean_burst} packets over {bursts} bursts"
    );
    assert!(
        (loss - ge.stationary_loss()).abs() < 0.1 * ge.stationary_loss(),
        "loss {loss}"
    );
    let o = ImpairmentConfig::preset("outage").unwrap().outage.unwrap();
    assert_eq!((o.start_s, o.duration_s), (3.0, 3.0));
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(16))]
    /// For any classic Gilbert chain, the measured loss rate and mean burst length match
    /// the closed forms `p_gb / (p_gb + p_bg)` and `1 / p_bg` (tolerances: several
    /// standard errors of 400,000 packets; bursts counted only with enough of them).
    #[test]
    fn gilbert_loss_and_burst_follow_closed_form(
        p_gb in 0.002f64..0.05, p_bg in 0.05f64..0.8, seed: u64,
    ) {
        let ge = GilbertElliott::new(p_gb, p_bg);
        let (loss, mean_burst, bursts) = gilbert_measure(ge, seed, 400_000);
        let want = ge.stationary_loss();
        // Loss indicators are correlated over ~1/(p_gb+p_bg) packets: the standard error
        // of the rate is about sqrt(want (1-want) / n * (2/(p_gb+p_bg))).
        let corr = 2.0 / (p_gb + p_bg);
        let se = (want * (1.0 - want) / 400_000.0 * corr).sqrt();
        proptest::prop_assert!((loss - want).abs() < 5.0 * se, "loss {} want {} se {}", loss, want, se);
        let sd = (1.0 - p_bg).sqrt() / p_bg;
        let se_b = sd / (bursts as f64).sqrt();
        proptest::prop_assert!(
            (mean_burst - ge.mean_bad_run()).abs() < 5.0 * se_b + 1e-9,
            "burst {} want {} se {}", mean_burst, ge.mean_bad_run(), se_b
        );
    }
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
    /// For any configuration: every packet is accounted for, nothing is released before it
    /// arrives, and without `reorder` releases never go backwards.
    #[test]
    fn accounting_invariants(
        delay in 0.0f64..50.0, jitter in 0.0f64..20.0, reorder: bool, loss in 0.0f64..30.0,
        burst: bool, dup in 0.0f64..20.0, rate in proptest::option::of(10.0f64..5000.0),
        queue in 1usize..50, seed: u64,
        gaps in proptest::collection::vec((0u64..5000, 1usize..1500), 1..400),
    ) {
        let cfg = ImpairmentConfig {
            delay_ms: delay, jitter_ms: jitter, reorder, loss_pct: loss,
            burst: burst.then(|| GilbertElliott::new(0.05, 0.3)), dup_pct: dup,
            rate_kbps: rate, queue_pkts: queue, ..Default::default()
        };
        let mut m = Impairment::new(cfg, seed);
        let (mut now, mut last, mut released) = (0u64, 0u64, 0u64);
        for (gap, len) in gaps {
            now += gap;
            for &at in deliver(&m.on_packet(now, len)) {
                proptest::prop_assert!(at >= now);
                if !reorder {
                    proptest::prop_assert!(at >= last);
                }
                last = last.max(at);
                released += 1;
            }
        }
        let c = m.counters();
        proptest::prop_assert_eq!(c.sent, c.delivered + c.dropped());
        proptest::prop_assert_eq!(released, c.released());
        if rate.is_none() {
            proptest::prop_assert_eq!(c.dropped_rate, 0);
        }
    }
}

/// A path dilated by F, fed the same packets at F times their times, drops the same
/// packets and releases the rest at F times the original release times (to the µs
/// rounding of the sampled delays): in a session's own time it is the same path.
#[test]
fn a_dilated_path_is_the_original_in_dilated_time() {
    const F: u64 = 3;
    for name in ["poor", "burst", "outage", "intercontinental"] {
        let mut cfg = ImpairmentConfig::preset(name).unwrap();
        // A rate cap too, so that the token bucket is stretched as well.
        cfg.rate_kbps = Some(2_000.0);
        let dilated = cfg.dilated(F as f64);
        dilated.validate().unwrap();
        let mut original = Impairment::new(cfg, 7);
        let mut slow = Impairment::new(dilated, 7);
        let (mut delivered, mut dropped) = (0, 0);
        for i in 0..20_000u64 {
            // 1,200-byte packets every 2 ms for 40 s, spanning the outage preset's cut.
            let t = i * 2_000;
            let a = original.on_packet(t, 1_200);
            let b = slow.on_packet(t * F, 1_200);
            match (&a, &b) {
                (Verdict::Drop(x), Verdict::Drop(y)) => {
                    assert_eq!(x, y, "{name}: packet {i}");
                    dropped += 1;
                }
                (Verdict::Deliver { .. }, Verdict::Deliver { .. }) => {
                    let (a, b) = (deliver(&a), deliver(&b));
                    assert_eq!(a.len(), b.len(), "{name}: packet {i}");
                    for (x, y) in a.iter().zip(b) {
                        let err = (*y as i64 - (*x * F) as i64).abs();
                        assert!(err <= 2 * F as i64, "{name}: packet {i}: {x} µs vs {y} µs");
                    }
                    delivered += 1;
                }
                _ => panic!("{name}: packet {i}: {a:?} against {b:?}"),
            }
        }
        assert!(
            delivered > 5_000 && dropped > 100,
            "{name}: {delivered} / {dropped}"
        );
    }
}
