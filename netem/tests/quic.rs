//! quinn through the relay and through the in-process impaired socket (loopback only).

mod common;

use std::time::Duration;

use cosurg_netem::{ImpairmentConfig, Relay, RelayConfig, impaired_endpoint};
use quinn::Endpoint;
use tokio::time::{Instant, timeout};

use common::{datagram_echoes, local, spawn_echo_quic, stream_roundtrip, tls};

fn poor() -> ImpairmentConfig {
    ImpairmentConfig::preset("poor").unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quic_through_relay_poor() {
    common::init_tracing();
    timeout(Duration::from_secs(25), async {
        let tls = tls();
        let server = Endpoint::server(tls.server, local()).unwrap();
        let server_addr = server.local_addr().unwrap();
        spawn_echo_quic(server);
        let relay = Relay::spawn(
            RelayConfig::new(local(), server_addr)
                .symmetric(poor())
                .with_seed(3),
        )
        .await
        .unwrap();

        let client = Endpoint::client(local()).unwrap();
        let t0 = Instant::now();
        let conn = client
            .connect_with(tls.client, relay.local_addr, "localhost")
            .unwrap()
            .await
            .expect("handshake through poor relay");
        let handshake = t0.elapsed();
        stream_roundtrip(&conn, 20_000, 1).await;
        let got = datagram_echoes(&conn, 20, Duration::from_secs(3)).await;
        let rtt = conn.rtt();
        conn.close(0u32.into(), b"done");
        let c = relay.shutdown().await;
        eprintln!(
            "poor relay: handshake {handshake:?}, rtt {rtt:?}, datagram echoes {got}/20\n{c}"
        );
        // 200 ms one-way each way: RTT ≈ 400 ms (+ jitter).
        assert!(rtt >= Duration::from_millis(300), "{rtt:?}");
        assert!(got >= 5, "only {got} datagram echoes");
        assert!(c.up.model.sent > 0 && c.down.model.sent > 0);
        assert_eq!(c.up.model.sent, c.up.model.delivered + c.up.model.dropped());
    })
    .await
    .expect("test timed out");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quic_through_impaired_socket_poor() {
    common::init_tracing();
    timeout(Duration::from_secs(25), async {
        let tls = tls();
        let server = Endpoint::server(tls.server, local()).unwrap();
        let server_addr = server.local_addr().unwrap();
        spawn_echo_quic(server);

        let (client, link) = impaired_endpoint(local(), None, poor(), poor(), 5).unwrap();
        let t0 = Instant::now();
        let conn = client
            .connect_with(tls.client, server_addr, "localhost")
            .unwrap()
            .await
            .expect("handshake through impaired socket");
        let handshake = t0.elapsed();
        stream_roundtrip(&conn, 20_000, 2).await;
        let got = datagram_echoes(&conn, 20, Duration::from_secs(3)).await;
        let rtt = conn.rtt();
        conn.close(0u32.into(), b"done");
        let c = link.counters();
        eprintln!(
            "poor socket: handshake {handshake:?}, rtt {rtt:?}, datagram echoes {got}/20\n{c}"
        );
        assert!(rtt >= Duration::from_millis(300), "{rtt:?}");
        assert!(got >= 5, "only {got} datagram echoes");
        for d in [c.up, c.down] {
            assert!(d.model.sent > 10);
            assert_eq!(d.model.sent, d.model.delivered + d.model.dropped());
            assert_eq!(d.model.released(), d.forwarded + d.send_errors + d.pending);
        }
        // Transmits are single packets (no GSO): every outgoing packet went through the model.
        assert!(c.up.model.bytes_sent / c.up.model.sent <= 1500);
    })
    .await
    .expect("test timed out");
}

/// Data sent while a 2 s, 100 % loss outage is running only arrives after it; the
/// connection (idle timeout 10 s, keep-alive 1 s) survives and carries data again.
async fn outage_and_recovery(conn: &quinn::Connection, start_outage: impl FnOnce(Duration)) {
    stream_roundtrip(conn, 5_000, 3).await;
    let outage = Duration::from_secs(2);
    start_outage(outage);
    let t0 = Instant::now();
    stream_roundtrip(conn, 5_000, 4).await;
    let recovered = t0.elapsed();
    eprintln!("stream round trip started with the outage completed after {recovered:?}");
    assert!(
        recovered >= outage - Duration::from_millis(50),
        "{recovered:?}"
    );
    assert!(
        conn.close_reason().is_none(),
        "connection died: {:?}",
        conn.close_reason()
    );
    let got = datagram_echoes(conn, 10, Duration::from_secs(1)).await;
    assert_eq!(got, 10);
    stream_roundtrip(conn, 5_000, 5).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quic_survives_outage_through_relay() {
    common::init_tracing();
    timeout(Duration::from_secs(20), async {
        let tls = tls();
        let server = Endpoint::server(tls.server, local()).unwrap();
        let server_addr = server.local_addr().unwrap();
        spawn_echo_quic(server);
        let lan = ImpairmentConfig::preset("lan").unwrap();
        let relay = Relay::spawn(RelayConfig::new(local(), server_addr).symmetric(lan))
            .await
            .unwrap();
        let client = Endpoint::client(local()).unwrap();
        let conn = client
            .connect_with(tls.client, relay.local_addr, "localhost")
            .unwrap()
            .await
            .unwrap();
        outage_and_recovery(&conn, |d| relay.start_outage(d)).await;
        let c = relay.shutdown().await;
        eprintln!("{c}");
        assert!(c.up.model.dropped_outage > 0);
        assert!(c.down.model.dropped_outage + c.up.model.dropped_outage >= 2);
    })
    .await
    .expect("test timed out");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quic_survives_outage_in_socket() {
    common::init_tracing();
    timeout(Duration::from_secs(20), async {
        let tls = tls();
        let server = Endpoint::server(tls.server, local()).unwrap();
        let server_addr = server.local_addr().unwrap();
        spawn_echo_quic(server);
        let metro = ImpairmentConfig::preset("metro").unwrap();
        let (client, link) = impaired_endpoint(local(), None, metro.clone(), metro, 9).unwrap();
        let conn = client
            .connect_with(tls.client, server_addr, "localhost")
            .unwrap()
            .await
            .unwrap();
        outage_and_recovery(&conn, |d| link.start_outage(d)).await;
        let c = link.counters();
        eprintln!("{c}");
        assert!(c.up.model.dropped_outage > 0);
    })
    .await
    .expect("test timed out");
}
