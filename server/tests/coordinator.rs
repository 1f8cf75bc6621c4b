//! Coordinator integration tests on loopback (127.0.0.1): real quinn clients against an
//! in-process coordinator. Every test is bounded by `tokio::time::timeout`.

use std::net::SocketAddr;
use std::time::Duration;

use bytes::Bytes;
use cosurg_server::{Coordinator, CoordinatorConfig, CoordinatorHandle, tls};
use proto::*;
use quinn::Endpoint;
use test_support::link::{self, LinkError, SiteLink};

const SCENE: &str = "5e3c0a1b";
const T: Duration = Duration::from_secs(20);

struct Fixture {
    handle: CoordinatorHandle,
    addr: SocketAddr,
    endpoint: Endpoint,
}

fn init_tracing() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_test_writer()
        .try_init();
}

fn start_with(f: impl FnOnce(&mut CoordinatorConfig)) -> Fixture {
    init_tracing();
    let session = SessionConfig {
        scene_hash: Some(SCENE.into()),
        max_sites: 8,
        heartbeat_interval_us: 200_000,
        invite_key: Some(invite_key()),
        ..SessionConfig::new("lap-chole", "s3cret")
    };
    let mut cfg = CoordinatorConfig::ephemeral(session).unwrap();
    cfg.status_interval = Some(Duration::from_millis(300));
    f(&mut cfg);
    let (handle, addr) = Coordinator::bind(cfg).unwrap();
    let client_cfg = tls::client_config_pinned(handle.fingerprint()).unwrap();
    let endpoint = link::client_endpoint_on("127.0.0.1:0".parse().unwrap(), client_cfg).unwrap();
    Fixture {
        handle,
        addr,
        endpoint,
    }
}

fn start() -> Fixture {
    start_with(|_| {})
}

fn invite_key() -> InviteKey {
    InviteKey::from_bytes([42; 32])
}

/// The instructor's token, or an invitation for the other roles.
fn credential(role: Role) -> Credential {
    match role {
        Role::Instructor => Credential::Token("s3cret".into()),
        role => Credential::Invitation(
            cosurg_server::state::mint(&invite_key(), "lap-chole", role, None, 3600, now_s())
                .unwrap()
                .invitation,
        ),
    }
}

fn now_s() -> u64 {
    cosurg_server::state::unix_now_s()
}

fn join_msg(name: &str, role: Role) -> Join {
    link::join_message(name, role, "lap-chole", credential(role), SCENE)
}

impl Fixture {
    async fn join(&self, name: &str, role: Role) -> SiteLink {
        let s = link::connect_and_join(
            &self.endpoint,
            self.addr,
            "localhost",
            &join_msg(name, role),
        )
        .await
        .unwrap();
        // every join is followed by a snapshot on a uni stream
        match s.next_uni().await.unwrap() {
            Message::Snapshot(_) => {}
            m => panic!("expected snapshot, got {m:?}"),
        }
        s
    }

    async fn join_with_snapshot(&self, name: &str, role: Role) -> (SiteLink, Snapshot) {
        let s = link::connect_and_join(
            &self.endpoint,
            self.addr,
            "localhost",
            &join_msg(name, role),
        )
        .await
        .unwrap();
        match s.next_uni().await.unwrap() {
            Message::Snapshot(snap) => (s, snap),
            m => panic!("expected snapshot, got {m:?}"),
        }
    }
}

fn pose(site: SiteId, x: f32) -> Message {
    Message::ToolPose(ToolPose {
        site,
        tool: 1,
        sim_time_s: 1.5,
        position: [x, 0.02, 0.03],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.3,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    })
}

fn keyframe(region: RegionId, id: KeyframeId, owner: SiteId, bits: usize) -> RegionKeyframe {
    let ids: Vec<u32> = (0..50).collect();
    let pos: Vec<[f64; 3]> = ids.iter().map(|&i| [i as f64 * 1e-3, 0.01, 0.02]).collect();
    let vel = vec![[0.0, 0.0, 0.001]; ids.len()];
    RegionKeyframe {
        region,
        keyframe_id: id,
        owner,
        sim_time: id as f64 * 0.1,
        epoch: 0,
        tree_bits: vec![0x5A; bits],
        nodes: QuantisedNodes::encode_default(&ids, &pos, &vel).unwrap(),
        topology: 0,
    }
}

/// Next control message that is not a periodic Status.
async fn next_ctrl(s: &mut SiteLink) -> Message {
    loop {
        match s.next_control().await.unwrap() {
            Some(Message::Status(_)) => continue,
            Some(m) => return m,
            None => panic!("control stream ended"),
        }
    }
}

/// Next datagram that is not a coordinator heartbeat.
async fn next_dgram(s: &SiteLink) -> Message {
    loop {
        match s.next_datagram().await.unwrap() {
            Message::Heartbeat(_) => continue,
            m => return m,
        }
    }
}

async fn refused_with(f: &Fixture, join: Join) -> (Refusal, quinn::ConnectionError) {
    let conn = f
        .endpoint
        .connect(f.addr, "localhost")
        .unwrap()
        .await
        .unwrap();
    let (mut send, mut recv) = conn.open_bi().await.unwrap();
    link::write_frame(&mut send, &Message::Join(join))
        .await
        .unwrap();
    let mut dec = FrameDecoder::default();
    let m = link::read_frame(&mut recv, &mut dec).await.unwrap();
    let Some(Message::Refusal(r)) = m else {
        panic!("expected refusal, got {m:?}")
    };
    let closed = conn.closed().await;
    (r, closed)
}

#[tokio::test]
async fn join_gets_welcome_and_empty_snapshot() {
    tokio::time::timeout(T, async {
        let f = start();
        let (s, snap) = f.join_with_snapshot("kyoto", Role::Trainee).await;
        assert_eq!(s.welcome.site, 1);
        assert_eq!(s.welcome.session.name, "lap-chole");
        assert_eq!(s.welcome.session.scene_hash, SCENE);
        assert_eq!(s.welcome.sites.len(), 1);
        assert!(snap.keyframes.is_empty());
        assert!(s.welcome.coordinator_time_us > 1_600_000_000_000_000);
        assert_eq!(f.handle.stats().joined, 1);
        s.leave("done").await;
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn wrong_token_version_scene_session_time_scale_are_refused() {
    tokio::time::timeout(T, async {
        let f = start();
        let cases: Vec<(Join, RefusalReason, u32)> = vec![
            (
                Join {
                    credential: Credential::Token("nope".into()),
                    ..join_msg("a", Role::Instructor)
                },
                RefusalReason::WrongToken,
                close_code::WRONG_TOKEN,
            ),
            (
                Join {
                    protocol_version: 77,
                    ..join_msg("a", Role::Trainee)
                },
                RefusalReason::WrongVersion {
                    server: PROTOCOL_VERSION,
                    client: 77,
                },
                close_code::WRONG_VERSION,
            ),
            (
                Join {
                    scene_hash: "ffff".into(),
                    ..join_msg("a", Role::Trainee)
                },
                RefusalReason::WrongScene {
                    expected: SCENE.into(),
                },
                close_code::WRONG_SCENE,
            ),
            (
                Join {
                    session: "other".into(),
                    ..join_msg("a", Role::Trainee)
                },
                RefusalReason::WrongSession,
                close_code::WRONG_SESSION,
            ),
            (
                // A site started with `--time-scale 2` at a coordinator in real time.
                Join {
                    time_scale_milli: 2000,
                    ..join_msg("a", Role::Trainee)
                },
                RefusalReason::WrongTimeScale {
                    server_milli: 1000,
                    client_milli: 2000,
                },
                close_code::WRONG_TIME_SCALE,
            ),
        ];
        for (join, reason, code) in cases {
            let (r, closed) = refused_with(&f, join).await;
            assert_eq!(r.reason, reason);
            assert!(!r.text.is_empty());
            match closed {
                quinn::ConnectionError::ApplicationClosed(c) => {
                    assert_eq!(c.error_code, quinn::VarInt::from_u32(code));
                    assert_eq!(c.reason, Bytes::from(r.text.clone()));
                }
                e => panic!("expected application close, got {e}"),
            }
        }
        // via the link helper
        let e = link::connect_and_join(
            &f.endpoint,
            f.addr,
            "localhost",
            &Join {
                credential: Credential::Token("x".into()),
                ..join_msg("a", Role::Instructor)
            },
        )
        .await
        .err()
        .unwrap();
        assert!(
            matches!(
                e,
                LinkError::Refused(Refusal {
                    reason: RefusalReason::WrongToken,
                    ..
                })
            ),
            "{e}"
        );
        // name taken
        let _a = f.join("dup", Role::Trainee).await;
        let (r, _) = refused_with(&f, join_msg("dup", Role::Trainee)).await;
        assert_eq!(r.reason, RefusalReason::NameTaken);
        assert_eq!(f.handle.stats().refused, 7);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn wrong_alpn_is_refused_by_tls_and_wrong_fingerprint_fails() {
    tokio::time::timeout(T, async {
        let f = start();
        // A client offering another ALPN.
        let verifier =
            tls::PinnedCertVerifier::new(tls::parse_fingerprint(f.handle.fingerprint()).unwrap());
        let mut tlscfg = rustls::ClientConfig::builder_with_provider(tls::provider())
            .with_protocol_versions(&[&rustls::version::TLS13])
            .unwrap()
            .dangerous()
            .with_custom_certificate_verifier(std::sync::Arc::new(verifier))
            .with_no_client_auth();
        tlscfg.alpn_protocols = vec![b"h3".to_vec()];
        let qc = quinn::crypto::rustls::QuicClientConfig::try_from(tlscfg).unwrap();
        let cfg = quinn::ClientConfig::new(std::sync::Arc::new(qc));
        let e = f
            .endpoint
            .connect_with(cfg, f.addr, "localhost")
            .unwrap()
            .await
            .unwrap_err();
        let text = e.to_string();
        println!("wrong ALPN: {text}");
        // TLS alert 120 (no_application_protocol) is QUIC CRYPTO_ERROR 0x178
        assert!(text.contains("error 120"), "{text}");
        // Pinning another certificate fails the handshake.
        let bad = tls::client_config_pinned(&"00".repeat(32)).unwrap();
        let e = f
            .endpoint
            .connect_with(bad, f.addr, "localhost")
            .unwrap()
            .await;
        assert!(e.is_err());
        // CA-based validation with the coordinator's own (self-signed) certificate works.
        assert!(f.handle.stats().handshake_failures >= 1);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn ca_validation_with_persisted_certificate() {
    tokio::time::timeout(T, async {
        init_tracing();
        let dir = tempfile::tempdir().unwrap();
        let (id, _) = tls::Identity::load_or_create(dir.path()).unwrap();
        let session = SessionConfig {
            scene_hash: Some(SCENE.into()),
            invite_key: Some(invite_key()),
            ..SessionConfig::new("lap-chole", "s3cret")
        };
        let (handle, addr) = Coordinator::bind(CoordinatorConfig::new(session, id)).unwrap();
        let pem = std::fs::read(dir.path().join(tls::CERT_FILE)).unwrap();
        let ep = link::client_endpoint_on(
            "127.0.0.1:0".parse().unwrap(),
            tls::client_config_ca(&pem).unwrap(),
        )
        .unwrap();
        for name in ["localhost", "127.0.0.1"] {
            let s = link::connect_and_join(
                &ep,
                addr,
                name,
                &join_msg(&format!("ca-{name}"), Role::Observer),
            )
            .await
            .unwrap();
            s.leave("ok").await;
        }
        // a name not in the certificate is rejected
        assert!(
            link::connect_and_join(&ep, addr, "example.org", &join_msg("x", Role::Observer))
                .await
                .is_err()
        );
        handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn datagrams_are_relayed_with_sender_id_and_clock_pings_answered() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut a = f.join("a", Role::Trainee).await;
        let b = f.join("b", Role::Trainee).await;
        let obs = f.join("obs", Role::Observer).await;
        // a learns about b and obs
        assert!(matches!(next_ctrl(&mut a).await, Message::SiteJoined(e) if e.name == "b"));
        // a sends a pose claiming to be site 99: relayed to b and obs as from a
        link::send_datagram(&a.conn, &pose(99, 0.25)).unwrap();
        for rx in [&b, &obs] {
            match next_dgram(rx).await {
                Message::ToolPose(p) => {
                    assert_eq!(p.site, a.welcome.site);
                    assert_eq!(p.position[0], 0.25);
                }
                m => panic!("{m:?}"),
            }
        }
        // sim-time stamps too
        link::send_datagram(&b.conn, &Message::SimTime(SimTimeStamp { site: b.welcome.site, sim_time_s: 3.25, step: 3250, wall_send_us: 0 })).unwrap();
        assert!(matches!(next_dgram(&a).await, Message::SimTime(s) if s.sim_time_s == 3.25 && s.site == b.welcome.site));
        // the observer's datagrams are dropped: b sees the next pose from a, not obs's
        link::send_datagram(&obs.conn, &pose(obs.welcome.site, 9.0)).unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        link::send_datagram(&a.conn, &pose(a.welcome.site, 0.5)).unwrap();
        assert!(matches!(next_dgram(&b).await, Message::ToolPose(p) if p.position[0] == 0.5));
        // clock ping answered by the coordinator
        let mut filter = ClockFilter::default();
        let t0 = std::time::Instant::now();
        for seq in 0..5u32 {
            let t1 = t0.elapsed().as_micros() as u64;
            link::send_datagram(&a.conn, &Message::ClockPing(ClockPing { seq, t1_us: t1 })).unwrap();
            loop {
                if let Message::ClockPong(p) = next_dgram(&a).await {
                    assert_eq!(p.seq, seq);
                    assert!(p.t3_us >= p.t2_us);
                    filter.add_sample(ClockSample::from_pong(&p, t0.elapsed().as_micros() as u64));
                    break;
                }
            }
        }
        let coord_now = filter.coordinator_time(t0.elapsed().as_micros() as u64).unwrap();
        let diff = coord_now as i64 - f.handle.now_us() as i64;
        assert!(diff.abs() < 20_000, "clock estimate off by {diff} µs");
        // the status table has b's sim time
        let st = f.handle.status();
        assert!(st.sites.iter().any(|s| s.name == "b" && s.sim_time_s == 3.25));
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn keyframe_relayed_acked_and_late_joiner_gets_snapshot() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut a = f.join("a", Role::Trainee).await;
        let mut b = f.join("b", Role::Trainee).await;
        let _ = next_ctrl(&mut a).await; // SiteJoined b
        let sa = a.welcome.site;
        a.send_control(&Message::OwnershipRequest(OwnershipRequest { region: 7, claim_time_us: 0 })).await.unwrap();
        assert!(matches!(next_ctrl(&mut a).await, Message::OwnershipGrant(g) if g.site == sa && g.region == 7));
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipGrant(g) if g.site == sa));
        let kf = keyframe(7, 1, sa, 2000);
        link::send_uni(&a.conn, &Message::Keyframe(kf.clone()), 0).await.unwrap();
        match b.next_uni().await.unwrap() {
            Message::Keyframe(k) => assert_eq!(k, kf),
            m => panic!("{m:?}"),
        }
        // b acknowledges; the ack is routed to a
        b.send_control(&Message::KeyframeAck(KeyframeAck { region: 7, keyframe_id: 1, site: 0, shows_keyframes: false })).await.unwrap();
        assert_eq!(
            next_ctrl(&mut a).await,
            Message::KeyframeAck(KeyframeAck { region: 7, keyframe_id: 1, site: b.welcome.site, shows_keyframes: false })
        );
        // a newer keyframe replaces it for late joiners
        let kf2 = keyframe(7, 2, sa, 100);
        link::send_uni(&a.conn, &Message::Keyframe(kf2.clone()), 0).await.unwrap();
        assert!(matches!(b.next_uni().await.unwrap(), Message::Keyframe(k) if k.keyframe_id == 2));
        let (_late, snap) = f.join_with_snapshot("late", Role::Observer).await;
        assert_eq!(snap.keyframes, vec![kf2]);
        assert_eq!(snap.owners, vec![RegionOwner { region: 7, site: sa }]);
        assert_eq!(f.handle.stats().keyframes_in, 2);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn tree_deltas_relayed_only_from_owner_and_observer_streams_refused() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut a = f.join("a", Role::Trainee).await;
        let mut b = f.join("b", Role::Trainee).await;
        let obs = f.join("obs", Role::Observer).await;
        let _ = next_ctrl(&mut a).await;
        let (sa, sb) = (a.welcome.site, b.welcome.site);
        a.send_control(&Message::OwnershipRequest(OwnershipRequest {
            region: 2,
            claim_time_us: 0,
        }))
        .await
        .unwrap();
        loop {
            if let Message::OwnershipGrant(g) = next_ctrl(&mut b).await {
                assert_eq!(g.site, sa);
                break;
            }
        }
        let delta = |site, x: u8| {
            Message::TreeDelta(TreeDelta {
                region: 2,
                site,
                epoch: 0,
                sim_time: 0.5,
                base_keyframe: 1,
                xor_bits: vec![x; 16],
            })
        };
        // b does not own region 2: dropped; a's delta is relayed
        link::send_datagram(&b.conn, &delta(sb, 1)).unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
        link::send_datagram(&a.conn, &delta(sa, 2)).unwrap();
        match next_dgram(&obs).await {
            Message::TreeDelta(d) => assert_eq!((d.site, d.xor_bits[0]), (sa, 2)),
            m => panic!("{m:?}"),
        }
        // a delta too large for a datagram goes on the control stream and is relayed there
        let mut big = delta(sa, 3);
        if let Message::TreeDelta(d) = &mut big {
            d.xor_bits = vec![3; 5000];
        }
        a.send_control(&big).await.unwrap();
        loop {
            if let Message::TreeDelta(d) = next_ctrl(&mut b).await {
                assert_eq!(d.xor_bits.len(), 5000);
                break;
            }
        }
        // an observer's keyframe stream is refused (STOP_SENDING, counted) and not relayed
        let dropped = f.handle.stats().dropped_messages;
        link::send_uni(
            &obs.conn,
            &Message::Keyframe(keyframe(9, 1, obs.welcome.site, 8)),
            0,
        )
        .await
        .unwrap();
        while f.handle.stats().dropped_messages == dropped {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert_eq!(f.handle.stats().keyframes_in, 0);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn superseded_keyframe_stream_is_reset() {
    tokio::time::timeout(T, async {
        let f = start();
        let a = f.join("a", Role::Trainee).await;
        let b = f.join("b", Role::Trainee).await;
        // A large keyframe that b does not read: it stalls on b's stream flow-control window.
        let big = keyframe(3, 1, a.welcome.site, 3 << 20);
        link::send_uni(&a.conn, &Message::Keyframe(big), 0)
            .await
            .unwrap();
        // b sees the relayed stream open (and stall on its flow-control window) ...
        let first = b.conn.accept_uni().await.unwrap();
        // ... when a newer keyframe of the same region arrives.
        let small = keyframe(3, 2, a.welcome.site, 10);
        link::send_uni(&a.conn, &Message::Keyframe(small), 0)
            .await
            .unwrap();
        while f.handle.stats().keyframe_streams_reset < 1 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // The old stream was reset, the new one arrives whole.
        match link::read_uni(first, DEFAULT_MAX_FRAME).await {
            Err(LinkError::ReadToEnd(quinn::ReadToEndError::Read(quinn::ReadError::Reset(
                code,
            )))) => assert_eq!(code, quinn::VarInt::from_u32(stream_code::SUPERSEDED)),
            other => panic!("expected a reset stream, got {other:?}"),
        }
        match b.next_uni().await.unwrap() {
            Message::Keyframe(k) => assert_eq!(k.keyframe_id, 2),
            m => panic!("{m:?}"),
        }
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn garbage_from_one_site_does_not_disturb_others() {
    tokio::time::timeout(T, async {
        let f = start();
        let bad = f.join("bad", Role::Trainee).await;
        let good = f.join("good", Role::Trainee).await;
        let peer = f.join("peer", Role::Trainee).await;
        // garbage datagrams
        for i in 0..50u8 {
            let junk: Vec<u8> = (0..(i as usize * 7 % 300 + 1))
                .map(|k| (k as u8).wrapping_mul(31).wrapping_add(i))
                .collect();
            bad.conn.send_datagram(Bytes::from(junk)).unwrap();
        }
        bad.conn.send_datagram(Bytes::from_static(&[])).ok();
        // a truncated keyframe stream (header says 1000 bytes, 10 sent)
        let mut s = bad.conn.open_uni().await.unwrap();
        s.write_all(&[0, 0, 3, 232, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10])
            .await
            .unwrap();
        s.finish().unwrap();
        // an oversized frame header
        let mut s = bad.conn.open_uni().await.unwrap();
        s.write_all(&u32::MAX.to_be_bytes()).await.unwrap();
        s.finish().unwrap();
        // a well-framed but undecodable stream
        let mut s = bad.conn.open_uni().await.unwrap();
        s.write_all(&[0, 0, 0, 3, 1, 250, 250]).await.unwrap();
        s.finish().unwrap();
        // a stream reset mid-way
        let mut s = bad.conn.open_uni().await.unwrap();
        s.write_all(&[0, 0, 1, 0, 1]).await.unwrap();
        s.reset(quinn::VarInt::from_u32(9)).unwrap();
        // an undecodable control frame (framing intact)
        let mut bad = bad;
        bad.control_send
            .write_all(&[0, 0, 0, 2, 1, 255])
            .await
            .unwrap();

        while {
            let st = f.handle.stats();
            st.malformed_datagrams < 50 || st.malformed_streams < 3 || st.malformed_control < 1
        } {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // good sites are unaffected
        link::send_datagram(&good.conn, &pose(good.welcome.site, 0.75)).unwrap();
        assert!(matches!(next_dgram(&peer).await, Message::ToolPose(p) if p.position[0] == 0.75));
        link::send_uni(
            &good.conn,
            &Message::Keyframe(keyframe(11, 1, good.welcome.site, 64)),
            0,
        )
        .await
        .unwrap();
        loop {
            match peer.next_uni().await.unwrap() {
                Message::Keyframe(k) if k.region == 11 => break,
                _ => continue,
            }
        }
        // the bad site is still connected (garbage is dropped, not fatal) and can still relay
        link::send_datagram(&bad.conn, &pose(bad.welcome.site, 1.0)).unwrap();
        assert!(
            matches!(next_dgram(&peer).await, Message::ToolPose(p) if p.site == bad.welcome.site)
        );
        // broken control framing closes only the bad site
        bad.control_send
            .write_all(&u32::MAX.to_be_bytes())
            .await
            .unwrap();
        match bad.conn.closed().await {
            quinn::ConnectionError::ApplicationClosed(c) => {
                assert_eq!(
                    c.error_code,
                    quinn::VarInt::from_u32(close_code::PROTOCOL_ERROR)
                )
            }
            e => panic!("{e}"),
        }
        link::send_datagram(&good.conn, &pose(good.welcome.site, 2.0)).unwrap();
        assert!(matches!(next_dgram(&peer).await, Message::ToolPose(p) if p.position[0] == 2.0));
        let st = f.handle.stats();
        assert!(st.malformed_datagrams >= 50, "{st:?}");
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn instructor_kicks_a_site() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut prof = f.join("prof", Role::Instructor).await;
        let mut tr = f.join("trainee", Role::Trainee).await;
        let _ = next_ctrl(&mut prof).await; // SiteJoined
        // a trainee cannot kick
        tr.send_control(&Message::Command(Command::KickSite {
            site: prof.welcome.site,
            reason: "ha".into(),
        }))
        .await
        .unwrap();
        // … and is told why.
        match next_ctrl(&mut tr).await {
            Message::CommandRefused(r) => {
                assert_eq!(r.command, "kick-site");
                assert!(r.reason.contains("instructor"), "{}", r.reason);
            }
            m => panic!("{m:?}"),
        }
        prof.send_control(&Message::Command(Command::KickSite {
            site: tr.welcome.site,
            reason: "disruptive".into(),
        }))
        .await
        .unwrap();
        match next_ctrl(&mut tr).await {
            Message::Refusal(r) => assert_eq!(r.reason, RefusalReason::Kicked),
            m => panic!("{m:?}"),
        }
        match tr.conn.closed().await {
            quinn::ConnectionError::ApplicationClosed(c) => {
                assert_eq!(c.error_code, quinn::VarInt::from_u32(close_code::KICKED))
            }
            e => panic!("{e}"),
        }
        assert!(
            matches!(next_ctrl(&mut prof).await, Message::Leave(l) if l.site == tr.welcome.site)
        );
        // the kicked name cannot come back
        let (r, _) = refused_with(&f, join_msg("trainee", Role::Trainee)).await;
        assert_eq!(r.reason, RefusalReason::Kicked);
        assert!(
            f.handle.stats().dropped_messages >= 1,
            "trainee's kick attempt dropped"
        );
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn ownership_conflicts_resolved_instructor_first() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut a = f.join("a", Role::Trainee).await;
        let mut b = f.join("b", Role::Trainee).await;
        let mut i = f.join("prof", Role::Instructor).await;
        let _ = next_ctrl(&mut a).await;
        let _ = next_ctrl(&mut a).await;
        let _ = next_ctrl(&mut b).await;
        let (sa, si) = (a.welcome.site, i.welcome.site);
        let req = |region| Message::OwnershipRequest(OwnershipRequest { region, claim_time_us: f.handle.now_us() });
        a.send_control(&req(5)).await.unwrap();
        assert!(matches!(next_ctrl(&mut a).await, Message::OwnershipGrant(g) if g.site == sa && g.previous.is_none()));
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipGrant(g) if g.site == sa));
        tokio::time::sleep(Duration::from_millis(150)).await; // beyond the contest window
        b.send_control(&req(5)).await.unwrap();
        match next_ctrl(&mut b).await {
            Message::OwnershipDeny(d) => {
                assert_eq!(d.holder, Some(sa));
                assert_eq!(d.reason, DenyReason::HeldByOther);
            }
            m => panic!("{m:?}"),
        }
        i.send_control(&req(5)).await.unwrap();
        assert!(matches!(next_ctrl(&mut a).await, Message::OwnershipGrant(g) if g.site == si && g.previous == Some(sa)));
        // release by a non-owner is denied, by the owner broadcast
        a.send_control(&Message::OwnershipRelease(OwnershipRelease { region: 5, site: sa })).await.unwrap();
        assert!(matches!(next_ctrl(&mut a).await, Message::OwnershipDeny(d) if d.reason == DenyReason::NotOwner));
        i.send_control(&Message::OwnershipRelease(OwnershipRelease { region: 5, site: si })).await.unwrap();
        assert!(matches!(next_ctrl(&mut a).await, Message::OwnershipRelease(r) if r.site == si));
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn abrupt_disconnects_release_regions() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut b = f.join("b", Role::Trainee).await;
        // Site "crash" runs in its own runtime, which we then tear down without any close:
        // its UDP socket disappears, as when a site loses power.
        let addr = f.addr;
        let fp = f.handle.fingerprint().to_string();
        let crash_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let (site_tx, site_rx) = tokio::sync::oneshot::channel();
        crash_rt.spawn(async move {
            let ep = link::client_endpoint_on("127.0.0.1:0".parse().unwrap(), tls::client_config_pinned(&fp).unwrap()).unwrap();
            let mut s = link::connect_and_join(&ep, addr, "localhost", &join_msg("crash", Role::Trainee)).await.unwrap();
            s.send_control(&Message::OwnershipRequest(OwnershipRequest { region: 42, claim_time_us: 0 })).await.unwrap();
            loop {
                if let Some(Message::OwnershipGrant(_)) = s.next_control().await.unwrap() {
                    break;
                }
            }
            // heartbeats arm the coordinator's liveness check
            for _ in 0..3 {
                link::send_datagram(&s.conn, &Message::Heartbeat(Heartbeat { site: s.welcome.site, time_us: 0 })).unwrap();
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            let _ = site_tx.send(s.welcome.site);
            std::future::pending::<()>().await;
            drop((ep, s));
        });
        let crashed = site_rx.await.unwrap();
        assert!(matches!(next_ctrl(&mut b).await, Message::SiteJoined(_)));
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipGrant(g) if g.region == 42 && g.site == crashed));
        let t0 = std::time::Instant::now();
        crash_rt.shutdown_background();
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipRelease(r) if r.region == 42 && r.site == crashed));
        assert!(matches!(next_ctrl(&mut b).await, Message::Leave(l) if l.site == crashed));
        let waited = t0.elapsed();
        assert!(waited < Duration::from_secs(5), "liveness timeout took {waited:?}");

        // A site that closes its connection without Leave.
        let mut c = f.join("closer", Role::Trainee).await;
        let _ = next_ctrl(&mut b).await; // SiteJoined
        c.send_control(&Message::OwnershipRequest(OwnershipRequest { region: 43, claim_time_us: 0 })).await.unwrap();
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipGrant(g) if g.region == 43));
        c.conn.close(quinn::VarInt::from_u32(0), b"gone");
        assert!(matches!(next_ctrl(&mut b).await, Message::OwnershipRelease(r) if r.region == 43));
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn reset_scene_and_teaching_playback_reach_everyone() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut prof = f.join("prof", Role::Instructor).await;
        let mut tr = f.join("tr", Role::Trainee).await;
        let _ = next_ctrl(&mut prof).await;
        let traj = TeachingTrajectory {
            id: 1,
            tool: 0,
            samples: (0..100)
                .map(|k| ToolSample {
                    t_s: k as f64 * 0.01,
                    position: [k as f32 * 1e-3, 0.0, 0.0],
                    orientation: [1.0, 0.0, 0.0, 0.0],
                    jaw_rad: 0.0,
                })
                .collect(),
        };
        prof.send_control(&Message::Teaching(traj.clone()))
            .await
            .unwrap();
        prof.send_control(&Message::Command(Command::StartPlayback {
            trajectory: 1,
            start_sim_time_s: 2.0,
        }))
        .await
        .unwrap();
        assert_eq!(next_ctrl(&mut tr).await, Message::Teaching(traj.clone()));
        assert!(matches!(
            next_ctrl(&mut tr).await,
            Message::Command(Command::StartPlayback { trajectory: 1, .. })
        ));
        // a late joiner gets the trajectory and the running playback
        let mut late = f.join("late", Role::Trainee).await;
        assert_eq!(next_ctrl(&mut late).await, Message::Teaching(traj));
        assert!(matches!(
            next_ctrl(&mut late).await,
            Message::Command(Command::StartPlayback { .. })
        ));
        prof.send_control(&Message::Command(Command::ResetScene {
            epoch: 0,
            sim_time_s: 1.0,
        }))
        .await
        .unwrap();
        for s in [&mut tr, &mut late] {
            loop {
                if let Message::Command(Command::ResetScene { epoch, sim_time_s }) =
                    next_ctrl(s).await
                {
                    assert_eq!(epoch, 1);
                    assert_eq!(sim_time_s, 1.0, "the reset's simulated time is relayed");
                    break;
                }
            }
        }
        // A site joining after the reset takes the new epoch from its join snapshot.
        let (_after, snap) = f.join_with_snapshot("after", Role::Trainee).await;
        assert_eq!(snap.epoch, 1);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn status_broadcast_and_leave() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut a = f.join("a", Role::Trainee).await;
        let b = f.join("b", Role::Trainee).await;
        loop {
            match a.next_control().await.unwrap().unwrap() {
                Message::Status(s) if s.sites.len() == 2 => break,
                _ => continue,
            }
        }
        let sb = b.welcome.site;
        b.leave("done").await;
        loop {
            if let Message::Leave(l) = next_ctrl(&mut a).await {
                assert_eq!(l.site, sb);
                assert_eq!(l.reason, "left: done");
                break;
            }
        }
        assert_eq!(f.handle.status().sites.len(), 1);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

/// Relay latency the coordinator adds on loopback: one-way A → coordinator → B against a
/// direct A → B quinn datagram, both measured in one process with one clock.
/// Run: `cargo test -p cosurg-server --release --test coordinator -- --ignored --nocapture relay_latency`
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore]
async fn relay_latency() {
    tokio::time::timeout(Duration::from_secs(120), async {
        let n = 3000;
        let f = start_with(|c| c.status_interval = None);
        let a = f.join("a", Role::Trainee).await;
        let b = f.join("b", Role::Trainee).await;
        let base = std::time::Instant::now();
        let relayed = measure(n, base, |m| link::send_datagram(&a.conn, m).unwrap(), &b.conn).await;

        // Direct path: a bare quinn server as B.
        let (id, _, _) = tls::Identity::generate_self_signed().unwrap();
        let server = quinn::Endpoint::server(tls::server_config(&id).unwrap(), "127.0.0.1:0".parse().unwrap()).unwrap();
        let saddr = server.local_addr().unwrap();
        let ep = link::client_endpoint_on("127.0.0.1:0".parse().unwrap(), tls::client_config_pinned(&id.fingerprint()).unwrap()).unwrap();
        let (client, srv) = tokio::join!(async { ep.connect(saddr, "localhost").unwrap().await.unwrap() }, async {
            server.accept().await.unwrap().await.unwrap()
        });
        let direct = measure(n, base, |m| link::send_datagram(&client, m).unwrap(), &srv).await;

        let pct = |v: &Vec<f64>, p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        println!(
            "loopback one-way latency over {} datagrams (µs): direct p50 {:.0} p99 {:.0}; via coordinator p50 {:.0} p99 {:.0}; added p50 {:.0} p99 {:.0}",
            relayed.len(),
            pct(&direct, 0.5),
            pct(&direct, 0.99),
            pct(&relayed, 0.5),
            pct(&relayed, 0.99),
            pct(&relayed, 0.5) - pct(&direct, 0.5),
            pct(&relayed, 0.99) - pct(&direct, 0.99),
        );
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

async fn measure(
    n: usize,
    base: std::time::Instant,
    send: impl Fn(&Message),
    rx: &quinn::Connection,
) -> Vec<f64> {
    let mut lat = Vec::with_capacity(n);
    let mut interval = tokio::time::interval(Duration::from_millis(1));
    for k in 0..n {
        interval.tick().await;
        let t = base.elapsed().as_secs_f64();
        send(&Message::ToolPose(ToolPose {
            sim_time_s: t,
            ..match pose(0, k as f32) {
                Message::ToolPose(p) => p,
                _ => unreachable!(),
            }
        }));
        loop {
            let d = match tokio::time::timeout(Duration::from_millis(200), rx.read_datagram()).await
            {
                Ok(d) => d.unwrap(),
                Err(_) => break, // lost: skip
            };
            if let Ok(Message::ToolPose(p)) = proto::decode(&d) {
                lat.push((base.elapsed().as_secs_f64() - p.sim_time_s) * 1e6);
                if p.position[0] == k as f32 {
                    break;
                }
            }
        }
    }
    lat.sort_by(|a, b| a.partial_cmp(b).unwrap());
    lat
}

#[tokio::test]
async fn keyframe_stream_superseded_by_its_sender_is_not_malformed() {
    tokio::time::timeout(T, async {
        let f = start();
        let a = f.join("a", Role::Trainee).await;
        // The site starts a keyframe stream, then replaces it by a newer keyframe: it resets
        // the old stream with SUPERSEDED (what the site link does).
        let mut s = a.conn.open_uni().await.unwrap();
        s.write_all(&[0, 0, 4, 0, 1, 2, 3]).await.unwrap();
        s.reset(quinn::VarInt::from_u32(stream_code::SUPERSEDED))
            .unwrap();
        link::send_uni(
            &a.conn,
            &Message::Keyframe(keyframe(5, 2, a.welcome.site, 16)),
            0,
        )
        .await
        .unwrap();
        while f.handle.stats().superseded_streams_in < 1 || f.handle.stats().keyframes_in < 1 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // a reset with any other code still counts
        let mut s = a.conn.open_uni().await.unwrap();
        s.write_all(&[0, 0, 4, 0, 1]).await.unwrap();
        s.reset(quinn::VarInt::from_u32(77)).unwrap();
        while f.handle.stats().malformed_streams < 1 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let st = f.handle.stats();
        assert_eq!(st.superseded_streams_in, 1, "{st:?}");
        assert_eq!(st.malformed_streams, 1, "{st:?}");
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn quick_reconnect_replaces_the_silent_previous_connection() {
    tokio::time::timeout(T, async {
        let f = start();
        let mut watcher = f.join("w", Role::Trainee).await;
        // The old connection of site "r" lives on its own endpoint and goes silent (as when
        // the site's process restarts behind a NAT that keeps the old path).
        let old_ep = link::client_endpoint_on(
            "127.0.0.1:0".parse().unwrap(),
            tls::client_config_pinned(f.handle.fingerprint()).unwrap(),
        )
        .unwrap();
        let old = link::connect_and_join(&old_ep, f.addr, "localhost", &join_msg("r", Role::Trainee))
            .await
            .unwrap();
        let old_id = old.welcome.site;
        assert!(matches!(next_ctrl(&mut watcher).await, Message::SiteJoined(e) if e.site == old_id));
        // Silent for more than 2 heartbeat intervals (2 × 200 ms here): the reconnection wins.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let new = f.join("r", Role::Trainee).await;
        assert_ne!(new.welcome.site, old_id);
        assert!(new.welcome.sites.iter().all(|e| e.site != old_id));
        match old.conn.closed().await {
            quinn::ConnectionError::ApplicationClosed(c) => {
                assert_eq!(c.error_code, quinn::VarInt::from_u32(close_code::TIMED_OUT))
            }
            e => panic!("{e}"),
        }
        assert!(matches!(next_ctrl(&mut watcher).await, Message::Leave(l) if l.site == old_id));
        assert!(
            matches!(next_ctrl(&mut watcher).await, Message::SiteJoined(e) if e.site == new.welcome.site)
        );
        let st = f.handle.stats();
        assert_eq!((st.resumed, st.refused), (1, 0), "{st:?}");
        assert_eq!(f.handle.status().sites.len(), 2);
        f.handle.shutdown().await;
    })
    .await
    .unwrap();
}
