//! Shared helpers for the netem integration tests (loopback only).
#![allow(dead_code)]

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use quinn::rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
use quinn::{ClientConfig, Connection, Endpoint, ServerConfig, TransportConfig};
use tokio::net::UdpSocket;

pub const LOCAL: &str = "127.0.0.1:0";

pub fn local() -> SocketAddr {
    LOCAL.parse().unwrap()
}

pub fn init_tracing() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_test_writer()
        .try_init();
}

/// A UDP echo server; returns its address and the number of datagrams it received.
pub async fn echo_server() -> (SocketAddr, Arc<AtomicU64>) {
    let sock = UdpSocket::bind(LOCAL).await.unwrap();
    let addr = sock.local_addr().unwrap();
    let count = Arc::new(AtomicU64::new(0));
    let c = count.clone();
    tokio::spawn(async move {
        let mut buf = vec![0u8; 65_536];
        while let Ok((n, from)) = sock.recv_from(&mut buf).await {
            c.fetch_add(1, Ordering::Relaxed);
            let _ = sock.send_to(&buf[..n], from).await;
        }
    });
    (addr, count)
}

fn transport() -> Arc<TransportConfig> {
    let mut t = TransportConfig::default();
    t.keep_alive_interval(Some(Duration::from_secs(1)));
    t.max_idle_timeout(Some(Duration::from_secs(10).try_into().unwrap()));
    Arc::new(t)
}

pub struct Tls {
    pub server: ServerConfig,
    pub client: ClientConfig,
}

pub fn tls() -> Tls {
    let ck = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
    let cert: CertificateDer<'static> = ck.cert.der().clone();
    let key: PrivateKeyDer<'static> =
        PrivatePkcs8KeyDer::from(ck.signing_key.serialize_der()).into();
    let mut server = ServerConfig::with_single_cert(vec![cert.clone()], key).unwrap();
    server.transport_config(transport());
    let mut roots = quinn::rustls::RootCertStore::empty();
    roots.add(cert).unwrap();
    let mut client = ClientConfig::with_root_certificates(Arc::new(roots)).unwrap();
    client.transport_config(transport());
    Tls { server, client }
}

/// Serve every connection on `endpoint`: echo bidirectional streams (reversed) and datagrams.
pub fn spawn_echo_quic(endpoint: Endpoint) {
    tokio::spawn(async move {
        while let Some(incoming) = endpoint.accept().await {
            tokio::spawn(async move {
                let Ok(conn) = incoming.await else { return };
                let c2 = conn.clone();
                tokio::spawn(async move {
                    while let Ok(d) = c2.read_datagram().await {
                        let _ = c2.send_datagram(d);
                    }
                });
                while let Ok((mut send, mut recv)) = conn.accept_bi().await {
                    tokio::spawn(async move {
                        let Ok(mut data) = recv.read_to_end(1 << 20).await else {
                            return;
                        };
                        data.reverse();
                        let _ = send.write_all(&data).await;
                        let _ = send.finish();
                        let _ = send.stopped().await;
                    });
                }
            });
        }
    });
}

/// One stream round trip of `len` bytes.
pub async fn stream_roundtrip(conn: &Connection, len: usize, tag: u8) {
    let data: Vec<u8> = (0..len).map(|i| (i as u8).wrapping_mul(31) ^ tag).collect();
    let (mut send, mut recv) = conn.open_bi().await.unwrap();
    send.write_all(&data).await.unwrap();
    send.finish().unwrap();
    let mut back = recv.read_to_end(1 << 20).await.unwrap();
    back.reverse();
    assert_eq!(back, data);
}

/// Send `n` datagrams 10 ms apart; return how many echoes arrived within `wait`.
pub async fn datagram_echoes(conn: &Connection, n: usize, wait: Duration) -> usize {
    let recv = {
        let conn = conn.clone();
        tokio::spawn(async move {
            let mut got = 0;
            let deadline = tokio::time::Instant::now() + wait;
            while let Ok(Ok(d)) = tokio::time::timeout_at(deadline, conn.read_datagram()).await {
                assert_eq!(d.len(), 500);
                got += 1;
                if got == n {
                    break;
                }
            }
            got
        })
    };
    for i in 0..n {
        conn.send_datagram(bytes::Bytes::from(vec![i as u8; 500]))
            .unwrap();
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    recv.await.unwrap()
}
