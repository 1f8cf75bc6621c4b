//! Coordinator metrics in the Prometheus/OpenMetrics text format, served over plain HTTP
//! on an opt-in address (`cosurg-server --metrics 127.0.0.1:9464`): `GET /metrics`.
//!
//! Encoding is `prometheus-client`'s; values are read from the coordinator's counters at
//! scrape time (a [`Collector`]), so the relay path pays nothing for them. The HTTP side is
//! a minimal responder on a tokio TCP listener (one request per connection, request head at
//! most 8 KiB, 5 s to send it): enough for a Prometheus scraper or `curl`, nothing else.
//! It has no authentication: bind it to a loopback or otherwise private address.
//!
//! | metric | type | labels |
//! |---|---|---|
//! | `cosurg_sessions` | gauge | |
//! | `cosurg_connections_total` | counter | |
//! | `cosurg_handshake_failures_total` | counter | |
//! | `cosurg_unrouted_refusals_total` (unknown session, malformed or rate-limited first message) | counter | |
//! | `cosurg_session_sites` | gauge | `session` |
//! | `cosurg_session_joins_total` | counter | `session` |
//! | `cosurg_session_messages_relayed_total` (datagrams, keyframes, control frames; per recipient) | counter | `session` |
//! | `cosurg_session_bytes_relayed_total` | counter | `session` |
//! | `cosurg_session_refusals_total` | counter | `session` |
//! | `cosurg_session_keyframes_total` (keyframes received) | counter | `session` |
//! | `cosurg_session_dropped_messages_total` | counter | `session` |
//! | `cosurg_session_over_budget_total` (datagrams over a site's relay budget; also dropped) | counter | `session` |

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tracing::{debug, info, warn};

use crate::CoordinatorStats;

/// The counters of one session at scrape time.
#[derive(Debug, Clone)]
pub struct SessionSample {
    pub name: String,
    pub sites: u64,
    pub stats: CoordinatorStats,
}

/// The coordinator's counters at scrape time.
#[derive(Debug, Clone, Default)]
pub struct Sample {
    /// Connection-level counters (not attributable to a session).
    pub coordinator: CoordinatorStats,
    pub sessions: Vec<SessionSample>,
}

/// Something that can be sampled at scrape time (the coordinator).
pub trait Source: Send + Sync + 'static {
    fn sample(&self) -> Sample;
}

struct SampleCollector<S>(Arc<S>);

impl<S> std::fmt::Debug for SampleCollector<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SampleCollector")
    }
}

fn gauge(
    enc: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    v: u64,
) -> Result<(), std::fmt::Error> {
    let g = ConstGauge::new(v as i64);
    let m = enc.encode_descriptor(name, help, None, g.metric_type())?;
    g.encode(m)
}

fn counter(
    enc: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    v: u64,
) -> Result<(), std::fmt::Error> {
    let c = ConstCounter::new(v);
    let m = enc.encode_descriptor(name, help, None, c.metric_type())?;
    c.encode(m)
}

/// A per-session family: one series per session, label `session`.
fn per_session(
    enc: &mut DescriptorEncoder,
    sessions: &[SessionSample],
    name: &str,
    help: &str,
    is_gauge: bool,
    value: impl Fn(&SessionSample) -> u64,
) -> Result<(), std::fmt::Error> {
    let metric_type = if is_gauge {
        ConstGauge::new(0i64).metric_type()
    } else {
        ConstCounter::new(0u64).metric_type()
    };
    let mut m = enc.encode_descriptor(name, help, None, metric_type)?;
    for s in sessions {
        let labels = [("session", s.name.as_str())];
        let series = m.encode_family(&labels)?;
        if is_gauge {
            ConstGauge::new(value(s) as i64).encode(series)?;
        } else {
            ConstCounter::new(value(s)).encode(series)?;
        }
    }
    Ok(())
}

impl<S: Source> Collector for SampleCollector<S> {
    fn encode(&self, mut enc: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let sample = self.0.sample();
        let c = &sample.coordinator;
        gauge(
            &mut enc,
            "cosurg_sessions",
            "Sessions hosted.",
            sample.sessions.len() as u64,
        )?;
        counter(
            &mut enc,
            "cosurg_connections",
            "Incoming QUIC connection attempts.",
            c.connections,
        )?;
        counter(
            &mut enc,
            "cosurg_handshake_failures",
            "Failed TLS/QUIC handshakes.",
            c.handshake_failures,
        )?;
        counter(
            &mut enc,
            "cosurg_unrouted_refusals",
            "Refusals before a session was found (unknown session, malformed or rate-limited first message).",
            c.refused,
        )?;
        let s = &sample.sessions;
        per_session(
            &mut enc,
            s,
            "cosurg_session_sites",
            "Sites in the session.",
            true,
            |s| s.sites,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_joins",
            "Sites admitted.",
            false,
            |s| s.stats.joined,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_messages_relayed",
            "Messages relayed to sites (datagrams, keyframes, control frames; one per recipient).",
            false,
            |s| s.stats.messages_relayed(),
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_bytes_relayed",
            "Bytes relayed to sites (payload, one count per recipient).",
            false,
            |s| s.stats.bytes_relayed,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_refusals",
            "Joins and admin requests of the session refused.",
            false,
            |s| s.stats.refused,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_keyframes",
            "Keyframes received from the session's sites.",
            false,
            |s| s.stats.keyframes_in,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_dropped_messages",
            "Well-formed messages dropped by policy (observer, not owner, stale, ...).",
            false,
            |s| s.stats.dropped_messages,
        )?;
        per_session(
            &mut enc,
            s,
            "cosurg_session_over_budget",
            "Datagrams dropped because their site exceeded its relay budget.",
            false,
            |s| s.stats.over_budget,
        )?;
        Ok(())
    }
}

/// The metrics page of `source` (OpenMetrics text, ends with `# EOF`).
pub fn render<S: Source>(source: Arc<S>) -> String {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(SampleCollector(source)));
    let mut out = String::new();
    // Writing into a String cannot fail; an encoder error would be a bug in the names.
    if let Err(e) = prometheus_client::encoding::text::encode(&mut out, &registry) {
        warn!(error = %e, "metrics encoding failed");
    }
    out
}

/// Content type of [`render`]'s output.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Bind `addr` and serve `GET /metrics` from `source` on a task added to `tasks`. Returns
/// the bound address.
pub(crate) fn serve<S: Source>(
    source: Arc<S>,
    addr: SocketAddr,
    tasks: &mut tokio::task::JoinSet<()>,
) -> Result<SocketAddr, crate::ServerError> {
    let err = |source| crate::ServerError::Metrics { addr, source };
    let std_listener = std::net::TcpListener::bind(addr).map_err(err)?;
    std_listener.set_nonblocking(true).map_err(err)?;
    let listener = TcpListener::from_std(std_listener).map_err(err)?;
    let bound = listener.local_addr().map_err(err)?;
    if !bound.ip().is_loopback() {
        warn!(%bound, "metrics served without authentication on a non-loopback address");
    }
    info!(%bound, "metrics on http://{bound}/metrics");
    tasks.spawn(async move {
        loop {
            match listener.accept().await {
                Ok((stream, peer)) => {
                    let source = source.clone();
                    tokio::spawn(async move {
                        if let Err(e) = answer(stream, source).await {
                            debug!(%peer, error = %e, "metrics request failed");
                        }
                    });
                }
                Err(e) => {
                    warn!(error = %e, "metrics accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
    });
    Ok(bound)
}

/// Longest request head read.
const MAX_HEAD: usize = 8 * 1024;

async fn answer<S: Source>(mut stream: TcpStream, source: Arc<S>) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(512);
    let read = async {
        let mut buf = [0u8; 1024];
        while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < MAX_HEAD {
            let n = stream.read(&mut buf).await?;
            if n == 0 {
                break;
            }
            head.extend_from_slice(&buf[..n]);
        }
        Ok::<_, std::io::Error>(())
    };
    tokio::time::timeout(Duration::from_secs(5), read)
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "request head"))??;
    let line = head
        .split(|&b| b == b'\r' || b == b'\n')
        .next()
        .unwrap_or(&[]);
    let mut words = line.split(|&b| b == b' ');
    let (method, path) = (words.next().unwrap_or(&[]), words.next().unwrap_or(&[]));
    let path = path.split(|&b| b == b'?').next().unwrap_or(&[]);
    let (status, ctype, body) = match (method, path) {
        (b"GET", b"/metrics") => ("200 OK", CONTENT_TYPE, render(source)),
        (b"GET", _) => (
            "404 Not Found",
            "text/plain; charset=utf-8",
            "not found; metrics are at /metrics\n".to_string(),
        ),
        _ => (
            "405 Method Not Allowed",
            "text/plain; charset=utf-8",
            "only GET\n".to_string(),
        ),
    };
    let response = format!(
        "HTTP/1.1 {status}\r\ncontent-type: {ctype}\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Fixed(Sample);
    impl Source for Fixed {
        fn sample(&self) -> Sample {
            self.0.clone()
        }
    }

    #[test]
    fn renders_per_session_series_in_the_text_format() {
        let a = CoordinatorStats {
            joined: 3,
            datagrams_relayed: 10,
            keyframes_relayed: 2,
            control_frames_out: 5,
            bytes_relayed: 1234,
            refused: 1,
            keyframes_in: 7,
            ..Default::default()
        };
        let sample = Sample {
            coordinator: CoordinatorStats {
                connections: 9,
                refused: 2,
                ..Default::default()
            },
            sessions: vec![
                SessionSample {
                    name: "a".into(),
                    sites: 3,
                    stats: a,
                },
                SessionSample {
                    name: "b \"x\"".into(),
                    sites: 0,
                    stats: CoordinatorStats::default(),
                },
            ],
        };
        let text = render(Arc::new(Fixed(sample)));
        for line in [
            "cosurg_sessions 2",
            "cosurg_connections_total 9",
            "cosurg_unrouted_refusals_total 2",
            "cosurg_session_sites{session=\"a\"} 3",
            "cosurg_session_messages_relayed_total{session=\"a\"} 17",
            "cosurg_session_bytes_relayed_total{session=\"a\"} 1234",
            "cosurg_session_refusals_total{session=\"a\"} 1",
            "cosurg_session_keyframes_total{session=\"a\"} 7",
            "# TYPE cosurg_session_sites gauge",
            "# TYPE cosurg_session_keyframes counter",
        ] {
            assert!(
                text.lines().any(|l| l == line),
                "{line:?} missing in\n{text}"
            );
        }
        assert!(text.trim_end().ends_with("# EOF"), "{text}");
        // label values are escaped
        assert!(text.contains("session=\"b \\\"x\\\"\""), "{text}");
    }
}
