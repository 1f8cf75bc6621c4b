//! The relay's counters account for every datagram (plain UDP echo server on loopback).

mod common;

use std::collections::HashSet;
use std::sync::atomic::Ordering;
use std::time::Duration;

use cosurg_netem::{
    GilbertElliott, ImpairmentConfig, JitterDist, Relay, RelayConfig, RelayCounters, RelayHandle,
};
use tokio::net::UdpSocket;
use tokio::time::{Instant, sleep, timeout};

use common::{echo_server, local};

/// Wait until nothing is pending and the counters stop changing.
async fn settle(relay: &RelayHandle) -> RelayCounters {
    let mut last = relay.counters();
    loop {
        sleep(Duration::from_millis(150)).await;
        let c = relay.counters();
        if c == last && c.up.pending == 0 && c.down.pending == 0 {
            return c;
        }
        last = c;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn counters_account_for_every_datagram() {
    common::init_tracing();
    timeout(Duration::from_secs(20), async {
        let (echo, echo_count) = echo_server().await;
        let up = ImpairmentConfig {
            delay_ms: 5.0,
            jitter_ms: 2.0,
            jitter_dist: JitterDist::Uniform,
            reorder: true,
            loss_pct: 5.0,
            burst: Some(GilbertElliott::new(0.02, 0.3)),
            dup_pct: 3.0,
            rate_kbps: Some(2000.0), // 250 kB/s per client
            bucket_bytes: 2000,
            queue_pkts: 20,
            outage: None,
        };
        let down = ImpairmentConfig {
            delay_ms: 3.0,
            loss_pct: 3.0,
            dup_pct: 2.0,
            ..Default::default()
        };
        let cfg = RelayConfig {
            up,
            down,
            ..RelayConfig::new(local(), echo).with_seed(42)
        };
        let relay = Relay::spawn(cfg).await.unwrap();
        let addr = relay.local_addr;

        const CLIENTS: usize = 2;
        const PER_CLIENT: u64 = 500;
        let mut clients = Vec::new();
        for c in 0..CLIENTS {
            clients.push(tokio::spawn(async move {
                let sock = UdpSocket::bind(local()).await.unwrap();
                let recv_sock = std::sync::Arc::new(sock);
                let r = recv_sock.clone();
                let receiver = tokio::spawn(async move {
                    let mut buf = [0u8; 2048];
                    let mut n = 0u64;
                    let mut ids = HashSet::new();
                    while let Ok(Ok(len)) =
                        timeout(Duration::from_millis(800), r.recv(&mut buf)).await
                    {
                        assert_eq!(len, 200);
                        assert_eq!(buf[0] as usize, c, "datagram for another client");
                        ids.insert(u64::from_le_bytes(buf[1..9].try_into().unwrap()));
                        n += 1;
                    }
                    (n, ids.len() as u64)
                });
                for i in 0..PER_CLIENT {
                    let mut pkt = vec![0u8; 200];
                    pkt[0] = c as u8;
                    pkt[1..9].copy_from_slice(&i.to_le_bytes());
                    recv_sock.send_to(&pkt, addr).await.unwrap();
                    if i % 10 == 9 {
                        sleep(Duration::from_millis(2)).await;
                    }
                }
                receiver.await.unwrap()
            }));
        }
        let mut received = 0;
        for c in clients {
            let (n, unique) = c.await.unwrap();
            assert!(unique <= n && unique > PER_CLIENT / 10, "{unique} of {n}");
            received += n;
        }
        let c = settle(&relay).await;
        eprintln!("{c}");
        let echoed = echo_count.load(Ordering::Relaxed);

        // Up: every datagram the clients sent is accounted for.
        let total = CLIENTS as u64 * PER_CLIENT;
        assert_eq!(c.clients_total, CLIENTS as u64);
        assert_eq!(c.up.model.sent, total);
        assert_eq!(c.up.model.bytes_sent, total * 200);
        assert_eq!(c.up.model.sent, c.up.model.delivered + c.up.model.dropped());
        assert!(c.up.model.dropped_loss > 0);
        assert!(c.up.model.dropped_burst > 0);
        assert!(c.up.model.dropped_rate > 0);
        assert_eq!(c.up.model.dropped_outage, 0);
        assert!(c.up.model.duplicated > 0);
        assert_eq!(c.up.send_errors, 0);
        assert_eq!(c.up.forwarded, c.up.model.released());
        assert_eq!(
            echoed, c.up.forwarded,
            "echo server saw what the relay sent"
        );

        // Down: every echo is accounted for and reached its client.
        assert_eq!(c.down.model.sent, echoed);
        assert_eq!(
            c.down.model.sent,
            c.down.model.delivered + c.down.model.dropped()
        );
        assert!(c.down.model.dropped_loss > 0);
        assert_eq!(c.down.model.dropped_burst + c.down.model.dropped_rate, 0);
        assert_eq!(c.down.send_errors, 0);
        assert_eq!(c.down.forwarded, c.down.model.released());
        assert_eq!(
            received, c.down.forwarded,
            "clients got what the relay sent"
        );

        let end = relay.shutdown().await;
        assert_eq!(end.up.model, c.up.model);
        assert_eq!(end.down.model, c.down.model);
    })
    .await
    .expect("test timed out");
}

/// A fixed-delay relay never releases early, keeps order, and (loosely) measures how late
/// the 1 ms tokio timer releases packets.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fixed_delay_in_order_and_never_early() {
    common::init_tracing();
    timeout(Duration::from_secs(20), async {
        let (echo, _) = echo_server().await;
        let cfg = RelayConfig::new(local(), echo).symmetric(ImpairmentConfig {
            delay_ms: 10.0,
            ..Default::default()
        });
        let relay = Relay::spawn(cfg).await.unwrap();
        let sock = UdpSocket::bind(local()).await.unwrap();
        sock.connect(relay.local_addr).await.unwrap();
        let mut rtts = Vec::new();
        let mut buf = [0u8; 64];
        for i in 0u32..40 {
            let t0 = Instant::now();
            sock.send(&i.to_le_bytes()).await.unwrap();
            let n = timeout(Duration::from_secs(2), sock.recv(&mut buf))
                .await
                .expect("echo lost")
                .unwrap();
            assert_eq!(&buf[..n], &i.to_le_bytes());
            rtts.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        // A burst keeps its order.
        for i in 0u32..200 {
            sock.send(&i.to_le_bytes()).await.unwrap();
        }
        for i in 0u32..200 {
            let n = timeout(Duration::from_secs(2), sock.recv(&mut buf))
                .await
                .expect("echo lost")
                .unwrap();
            assert_eq!(&buf[..n], &i.to_le_bytes(), "reordered or lost");
        }
        let c = relay.shutdown().await;
        let mean = rtts.iter().sum::<f64>() / rtts.len() as f64;
        let min = rtts.iter().cloned().fold(f64::MAX, f64::min);
        let max = rtts.iter().cloned().fold(0.0, f64::max);
        eprintln!(
            "RTT through 10 ms + 10 ms relay: mean {mean:.2} ms, min {min:.2}, max {max:.2}; \
             release lateness up mean {:.0} µs max {} µs, down mean {:.0} µs max {} µs",
            c.up.late_mean_us, c.up.late_max_us, c.down.late_mean_us, c.down.late_max_us
        );
        assert!(min >= 20.0, "released early: {min} ms");
        assert_eq!(c.up.model.dropped() + c.down.model.dropped(), 0);
        assert_eq!(c.up.forwarded, 240);
        assert_eq!(c.down.forwarded, 240);
    })
    .await
    .expect("test timed out");
}

/// Idle clients are forgotten, their counters kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_clients_expire() {
    timeout(Duration::from_secs(10), async {
        let (echo, _) = echo_server().await;
        let cfg = RelayConfig {
            client_timeout: Duration::from_millis(200),
            ..RelayConfig::new(local(), echo)
        };
        let relay = Relay::spawn(cfg).await.unwrap();
        let sock = UdpSocket::bind(local()).await.unwrap();
        sock.send_to(b"hello", relay.local_addr).await.unwrap();
        let mut buf = [0u8; 16];
        let n = timeout(Duration::from_secs(2), sock.recv(&mut buf))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(&buf[..n], b"hello");
        assert_eq!(relay.counters().clients, 1);
        sleep(Duration::from_millis(600)).await;
        let c = relay.counters();
        assert_eq!(c.clients, 0);
        assert_eq!(c.clients_total, 1);
        assert_eq!(c.up.model.sent, 1);
        assert_eq!(c.down.model.sent, 1);
    })
    .await
    .expect("test timed out");
}

/// `run_cli` (the `cosurg netem` entry point) parses, relays and stops after `--seconds`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn run_cli_stops_after_seconds() {
    use clap::Parser;
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        netem: cosurg_netem::NetemArgs,
    }
    let (echo, _) = echo_server().await;
    let cli = Cli::try_parse_from([
        "netem",
        "--listen",
        "127.0.0.1:0",
        "--upstream",
        &echo.to_string(),
        "--preset",
        "metro",
        "--seconds",
        "0.3",
    ])
    .unwrap();
    let t0 = Instant::now();
    timeout(Duration::from_secs(5), cosurg_netem::run_cli(cli.netem))
        .await
        .expect("run_cli did not stop")
        .unwrap();
    assert!(t0.elapsed() >= Duration::from_millis(300));

    // A bad preset is an error, not a panic.
    let cli = Cli::try_parse_from([
        "netem",
        "--listen",
        "127.0.0.1:0",
        "--upstream",
        "127.0.0.1:9",
        "--preset",
        "moon",
    ])
    .unwrap();
    let err = cosurg_netem::run_cli(cli.netem).await.unwrap_err();
    assert!(format!("{err:#}").contains("moon"), "{err:#}");
}
