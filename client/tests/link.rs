//! Tests of the site's QUIC link (`cosurg::link`) against an in-process coordinator on
//! loopback. Every test is wrapped in a timeout and stops by itself.

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use cosurg::link::{Link, LinkConfig, LinkEvent, LinkImpairment};
use proto::{
    Message, QuantisedNodes, RefusalReason, RegionKeyframe, Role, SessionConfig, SiteId, ToolPose,
};
use server::tls::Identity;
use server::{Coordinator, CoordinatorConfig, CoordinatorHandle};
use test_support::link as wire;
use tokio::time::{Instant, sleep};

const SCENE: &str = "5ca1ab1e";
const SESSION: &str = "lap-chole";
const TOKEN: &str = "s3cret";

fn init_tracing() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("COSURG_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_test_writer()
        .try_init();
}

/// Run a test body with a hard timeout.
async fn within<F: Future<Output = ()>>(secs: u64, f: F) {
    tokio::time::timeout(Duration::from_secs(secs), f)
        .await
        .unwrap_or_else(|_| panic!("test did not finish within {secs} s"));
}

fn session_config() -> SessionConfig {
    SessionConfig {
        scene_hash: Some(SCENE.into()),
        invite_key: Some(invite_key()),
        ..SessionConfig::new(SESSION, TOKEN)
    }
}

/// A coordinator on `listen` with `identity`; retries binding for a while (a port that was
/// just released may still be held by the previous endpoint's driver).
async fn coordinator_on(listen: SocketAddr, identity: Identity) -> (CoordinatorHandle, SocketAddr) {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let mut cfg = CoordinatorConfig::new(session_config(), identity.clone());
        cfg.listen = listen;
        cfg.status_interval = None;
        match Coordinator::bind(cfg) {
            Ok(x) => return x,
            Err(e) if Instant::now() < deadline => {
                eprintln!("bind {listen}: {e}; retrying");
                sleep(Duration::from_millis(50)).await;
            }
            Err(e) => panic!("cannot bind the coordinator on {listen}: {e}"),
        }
    }
}

async fn coordinator() -> (CoordinatorHandle, SocketAddr, Identity) {
    let (id, _, _) = Identity::generate_self_signed().unwrap();
    let (h, addr) = coordinator_on(SocketAddr::from(([127, 0, 0, 1], 0)), id.clone()).await;
    (h, addr, id)
}

fn invite_key() -> proto::InviteKey {
    proto::InviteKey::from_bytes([3; 32])
}

/// A trainee invitation valid for an hour.
fn invitation() -> proto::Credential {
    let issued = server::state::mint(
        &invite_key(),
        SESSION,
        Role::Trainee,
        None,
        3600,
        server::state::unix_now_s(),
    )
    .unwrap();
    proto::Credential::Invitation(issued.invitation)
}

fn config(addr: SocketAddr, h: &CoordinatorHandle, name: &str) -> LinkConfig {
    LinkConfig::new(
        addr,
        h.fingerprint(),
        SESSION,
        invitation(),
        Role::Trainee,
        name,
        SCENE,
    )
}

fn start(cfg: LinkConfig) -> Link {
    Link::start(cfg, &tokio::runtime::Handle::current()).expect("link start")
}

/// Wait for an event matching `pred`, skipping (and remembering) others.
async fn wait_for(
    link: &Link,
    within: Duration,
    mut pred: impl FnMut(&LinkEvent) -> bool,
) -> LinkEvent {
    let deadline = Instant::now() + within;
    let mut seen = Vec::new();
    loop {
        while let Some(e) = link.try_recv() {
            if pred(&e) {
                return e;
            }
            seen.push(e);
        }
        if Instant::now() > deadline {
            panic!("no matching event within {within:?}; saw: {seen:#?}");
        }
        sleep(Duration::from_millis(5)).await;
    }
}

async fn welcome(link: &Link, within: Duration) -> SiteId {
    match wait_for(link, within, |e| {
        matches!(
            e,
            LinkEvent::Welcome(_) | LinkEvent::Refused(_) | LinkEvent::Stopped { .. }
        )
    })
    .await
    {
        LinkEvent::Welcome(w) => {
            assert_eq!(link.site_id(), Some(w.site));
            w.site
        }
        other => panic!("expected Welcome, got {other:?}"),
    }
}

fn pose(x: f32) -> Message {
    Message::ToolPose(ToolPose {
        site: 0,
        tool: 1,
        sim_time_s: x as f64,
        position: [x, 0.02, 0.03],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.1,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    })
}

fn keyframe(region: u32, id: u64, nodes: u32) -> RegionKeyframe {
    let ids: Vec<u32> = (0..nodes).collect();
    RegionKeyframe {
        region,
        keyframe_id: id,
        owner: 0,
        sim_time: 1.5,
        epoch: 0,
        tree_bits: vec![0b1011_0001; 64],
        nodes: QuantisedNodes {
            positions: ids.iter().map(|&i| [i as i32, -(i as i32), 7]).collect(),
            velocities: ids.iter().map(|&i| [0, i as i32 % 5, 0]).collect(),
            ids,
            ..QuantisedNodes::default()
        },
        topology: 0,
    }
}

/// Send poses from `from` every 20 ms until `to` receives one; returns it.
async fn relay_pose(from: &Link, to: &Link, within: Duration) -> ToolPose {
    let deadline = Instant::now() + within;
    let mut x = 0.0f32;
    loop {
        x += 0.001;
        from.send_datagram(pose(x));
        sleep(Duration::from_millis(20)).await;
        while let Some(e) = to.try_recv() {
            if let LinkEvent::Message(Message::ToolPose(p)) = e {
                return p;
            }
        }
        assert!(
            Instant::now() < deadline,
            "no tool pose relayed within {within:?}"
        );
    }
}

async fn keyframe_arrives(link: &Link, region: u32, within: Duration) -> RegionKeyframe {
    match wait_for(
        link,
        within,
        |e| matches!(e, LinkEvent::Message(Message::Keyframe(k)) if k.region == region),
    )
    .await
    {
        LinkEvent::Message(Message::Keyframe(k)) => k,
        _ => unreachable!(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_sites_exchange_pose_keyframe_and_ack() {
    init_tracing();
    within(20, async {
        let (coord, addr, _) = coordinator().await;
        let a = start(config(addr, &coord, "kyoto"));
        let a_id = welcome(&a, Duration::from_secs(5)).await;
        let b = start(config(addr, &coord, "osaka"));
        let b_id = welcome(&b, Duration::from_secs(5)).await;
        assert_ne!(a_id, b_id);
        // Both get the late-join snapshot; A hears about B.
        wait_for(&b, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::Snapshot(_)))
        })
        .await;
        wait_for(&a, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::SiteJoined(s)) if s.site == b_id && s.name == "osaka")
        })
        .await;

        // Datagram: a tool pose from A reaches B with A's id stamped.
        let p = relay_pose(&a, &b, Duration::from_secs(5)).await;
        assert_eq!(p.site, a_id);
        assert_eq!(p.tool, 1);
        assert_eq!(p.position[1], 0.02);

        // Keyframe stream: a 3000-node keyframe from A reaches B intact, owner stamped.
        let kf = keyframe(7, 1, 3000);
        a.send_keyframe(kf.clone());
        let got = keyframe_arrives(&b, 7, Duration::from_secs(5)).await;
        assert_eq!(got.owner, a_id);
        assert_eq!(got.nodes, kf.nodes);
        assert_eq!(got.tree_bits, kf.tree_bits);

        // Control stream: B acknowledges; the coordinator relays the ack to the owner A.
        b.send_control(Message::KeyframeAck(proto::KeyframeAck {
            region: 7,
            keyframe_id: 1,
            site: 0,
            shows_keyframes: false,
        }));
        match wait_for(&a, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::KeyframeAck(_)))
        })
        .await
        {
            LinkEvent::Message(Message::KeyframeAck(ack)) => {
                assert_eq!((ack.region, ack.keyframe_id, ack.site), (7, 1, b_id));
            }
            _ => unreachable!(),
        }

        // Ownership on the control stream: the grant is broadcast to both sites.
        a.send_control(Message::OwnershipRequest(proto::OwnershipRequest {
            region: 7,
            claim_time_us: a.coordinator_time_us(),
        }));
        for l in [&a, &b] {
            match wait_for(l, Duration::from_secs(5), |e| {
                matches!(e, LinkEvent::Message(Message::OwnershipGrant(_)))
            })
            .await
            {
                LinkEvent::Message(Message::OwnershipGrant(g)) => {
                    assert_eq!((g.region, g.site), (7, a_id));
                }
                _ => unreachable!(),
            }
        }

        // A tree delta too large for a datagram falls back to the control stream.
        a.send_datagram(Message::TreeDelta(proto::TreeDelta {
            region: 7,
            site: 0,
            epoch: 0,
            sim_time: 2.0,
            base_keyframe: 1,
            xor_bits: vec![0x5A; 3000],
        }));
        match wait_for(&b, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::TreeDelta(_)))
        })
        .await
        {
            LinkEvent::Message(Message::TreeDelta(d)) => {
                assert_eq!((d.site, d.xor_bits.len()), (a_id, 3000));
            }
            _ => unreachable!(),
        }
        assert_eq!(a.stats().datagram_fallbacks, 1);

        // Counters on both sides.
        let (sa, sb) = (a.stats(), b.stats());
        assert!(sa.datagrams_sent >= 1, "{sa:?}");
        assert!(sb.datagrams_received >= 1, "{sb:?}");
        assert_eq!(sb.keyframes_received, 1, "{sb:?}");
        assert!(sb.snapshots_received >= 1, "{sb:?}");
        assert!(sa.bytes_up > 3000 && sb.bytes_down > 3000, "{sa:?} {sb:?}");
        assert!(sa.udp_bytes_up > 0 && sb.udp_bytes_down > 0, "{sa:?} {sb:?}");
        assert_eq!(sa.malformed + sb.malformed, 0);
        let cs = coord.stats();
        assert_eq!(cs.keyframes_in, 1);
        assert_eq!(cs.malformed_datagrams + cs.malformed_streams + cs.malformed_control, 0);

        // A leaves gracefully: B is told, the coordinator counts the departure.
        a.close_async().await;
        match wait_for(&b, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::Leave(_)))
        })
        .await
        {
            LinkEvent::Message(Message::Leave(l)) => assert_eq!(l.site, a_id),
            _ => unreachable!(),
        }
        assert_eq!(coord.status().sites.len(), 1);
        b.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_token_is_refused_without_reconnect() {
    init_tracing();
    within(15, async {
        let (coord, addr, _) = coordinator().await;
        let mut cfg = config(addr, &coord, "intruder");
        cfg.credential = proto::Credential::Token("guess".into());
        assert!(cfg.reconnect);
        let link = start(cfg);
        match wait_for(&link, Duration::from_secs(5), |e| {
            !matches!(e, LinkEvent::ConnectFailed { .. })
        })
        .await
        {
            LinkEvent::Refused(r) => {
                assert_eq!(r.reason, RefusalReason::WrongToken);
                assert!(r.text.contains("token"), "{}", r.text);
            }
            other => panic!("expected Refused, got {other:?}"),
        }
        match wait_for(&link, Duration::from_secs(3), |_| true).await {
            LinkEvent::Stopped { reason } => assert!(reason.contains("WrongToken"), "{reason}"),
            other => panic!("expected Stopped, got {other:?}"),
        }
        // No further attempt.
        sleep(Duration::from_millis(800)).await;
        assert_eq!(link.try_recv(), None);
        assert_eq!(link.site_id(), None);
        let cs = coord.stats();
        assert_eq!((cs.connections, cs.refused, cs.joined), (1, 1, 0), "{cs:?}");
        assert_eq!(link.stats().connects, 0);
        link.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clock_offset_small_on_loopback() {
    init_tracing();
    within(15, async {
        let (coord, addr, _) = coordinator().await;
        let link = start(config(addr, &coord, "clock"));
        welcome(&link, Duration::from_secs(5)).await;
        let deadline = Instant::now() + Duration::from_secs(5);
        while link.clock().samples < 8 {
            assert!(
                Instant::now() < deadline,
                "too few clock samples: {:?}",
                link.clock()
            );
            sleep(Duration::from_millis(20)).await;
        }
        let c = link.clock();
        let offset = c.offset_us.expect("synchronised");
        assert!(
            offset.abs() < 5_000.0,
            "offset {offset} µs on loopback: {c:?}"
        );
        let rtt = c.rtt_us.expect("rtt");
        assert!(rtt > 0 && rtt < 50_000, "rtt {rtt} µs: {c:?}");
        // The estimated coordinator time agrees with the coordinator's own clock.
        let est = link.coordinator_time_us() as i64;
        let real = coord.now_us() as i64;
        assert!(
            (est - real).abs() < 5_000,
            "estimate {est} vs coordinator {real}"
        );
        let s = link.stats();
        assert!(s.clock_pings >= 8 && s.clock_pongs >= 8, "{s:?}");
        assert!(s.heartbeats_sent >= 1, "{s:?}");
        link.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poor_network_still_joins_and_receives() {
    init_tracing();
    within(30, async {
        let (coord, addr, _) = coordinator().await;
        let mut cfg = config(addr, &coord, "remote");
        cfg.impairment = Some(LinkImpairment::preset("poor", 42).unwrap());
        let far = start(cfg);
        let near = start(config(addr, &coord, "near"));
        welcome(&near, Duration::from_secs(5)).await;
        let far_id = welcome(&far, Duration::from_secs(15)).await;

        // Datagrams from the near site reach the far one despite 10 % loss each way.
        let p = relay_pose(&near, &far, Duration::from_secs(8)).await;
        assert_ne!(p.site, far_id);
        // A keyframe stream survives loss (retransmitted) …
        near.send_keyframe(keyframe(3, 1, 500));
        let k = keyframe_arrives(&far, 3, Duration::from_secs(8)).await;
        assert_eq!(k.nodes.ids.len(), 500);
        // A newer keyframe of a region does not wait for an older one still in flight
        // (≈ 300 kB cannot cross a 400 ms RTT link in 150 ms): it arrives first (the
        // coordinator drops the older one as stale should it still arrive). The older
        // stream either completes or, stalled with a newer one behind it, is reset as
        // superseded; either way it ends.
        let before = far.stats();
        far.send_keyframe(keyframe(9, 1, 20_000));
        sleep(Duration::from_millis(150)).await;
        far.send_keyframe(keyframe(9, 2, 10));
        let k = keyframe_arrives(&near, 9, Duration::from_secs(8)).await;
        assert_eq!((k.keyframe_id, k.nodes.ids.len()), (2, 10));
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let s = far.stats();
            let ended = (s.keyframes_sent - before.keyframes_sent)
                + (s.keyframes_superseded - before.keyframes_superseded);
            if ended == 2 {
                break;
            }
            assert!(Instant::now() < deadline, "{s:?}");
            sleep(Duration::from_millis(50)).await;
        }
        // … and so does the far site's own traffic towards the near one.
        let p = relay_pose(&far, &near, Duration::from_secs(8)).await;
        assert_eq!(p.site, far_id);

        // The clock estimate sees the emulated round trip (2 × 200 ms one-way).
        let deadline = Instant::now() + Duration::from_secs(5);
        while link_rtt(&far) < 250_000 {
            assert!(Instant::now() < deadline, "rtt {:?}", far.clock());
            sleep(Duration::from_millis(50)).await;
        }
        let counters = far.impaired().expect("impaired socket").counters();
        assert!(
            counters.up.model.sent > 0 && counters.down.model.sent > 0,
            "{counters}"
        );
        assert!(
            counters.up.model.dropped() + counters.down.model.dropped() > 0,
            "{counters}"
        );
        assert_eq!(far.stats().disconnects, 0, "{:?}", far.stats());
        far.close_async().await;
        near.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

fn link_rtt(l: &Link) -> u64 {
    l.clock().rtt_us.unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn coordinator_restart_reconnects_with_snapshot() {
    init_tracing();
    within(30, async {
        let (coord, addr, identity) = coordinator().await;
        let link = start(config(addr, &coord, "kobe"));
        welcome(&link, Duration::from_secs(5)).await;
        wait_for(&link, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::Snapshot(_)))
        })
        .await;

        coord.shutdown().await;
        match wait_for(&link, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Disconnected { .. })
        })
        .await
        {
            LinkEvent::Disconnected {
                reason,
                will_reconnect,
            } => {
                assert!(will_reconnect);
                assert!(reason.contains("shutting down"), "{reason}");
            }
            _ => unreachable!(),
        }
        assert_eq!(link.site_id(), None);
        // Messages sent while disconnected are held for the next session.
        link.send_keyframe(keyframe(11, 1, 10));

        // Same identity (pinned fingerprint), same port.
        let (coord, _) = coordinator_on(addr, identity).await;
        match wait_for(&link, Duration::from_secs(10), |e| {
            matches!(e, LinkEvent::Reconnected(_) | LinkEvent::Stopped { .. })
        })
        .await
        {
            LinkEvent::Reconnected(w) => assert_eq!(link.site_id(), Some(w.site)),
            other => panic!("expected Reconnected, got {other:?}"),
        }
        match wait_for(&link, Duration::from_secs(5), |_| true).await {
            LinkEvent::Message(Message::Snapshot(s)) => assert_eq!(s.epoch, 0),
            other => panic!("expected the snapshot right after Reconnected, got {other:?}"),
        }
        let s = link.stats();
        assert_eq!(
            (s.connects, s.reconnects, s.disconnects),
            (2, 1, 1),
            "{s:?}"
        );
        // The held keyframe went to the new coordinator.
        let deadline = Instant::now() + Duration::from_secs(5);
        while coord.stats().keyframes_in < 1 {
            assert!(Instant::now() < deadline, "held keyframe not delivered");
            sleep(Duration::from_millis(20)).await;
        }
        link.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn outage_detected_by_silence_then_rejoin_with_snapshot() {
    init_tracing();
    within(30, async {
        let (coord, addr, _) = coordinator().await;
        let mut cfg = config(addr, &coord, "nara");
        cfg.impairment = Some(LinkImpairment::preset("lan", 1).unwrap());
        cfg.backoff.initial = Duration::from_millis(100);
        let link = start(cfg);
        welcome(&link, Duration::from_secs(5)).await;
        // Another site stores a keyframe at the coordinator.
        let other = start(config(addr, &coord, "other"));
        let other_id = welcome(&other, Duration::from_secs(5)).await;
        other.send_keyframe(keyframe(5, 9, 100));
        keyframe_arrives(&link, 5, Duration::from_secs(5)).await;

        // 100 % loss for 2.5 s: the link notices the silence long before QUIC's idle timeout.
        let t0 = Instant::now();
        link.impaired()
            .unwrap()
            .start_outage(Duration::from_millis(2500));
        match wait_for(&link, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Disconnected { .. })
        })
        .await
        {
            LinkEvent::Disconnected { reason, .. } => {
                assert!(reason.contains("nothing heard"), "{reason}")
            }
            _ => unreachable!(),
        }
        let detected = t0.elapsed();
        assert!(
            detected < Duration::from_millis(2400),
            "detected after {detected:?}"
        );

        match wait_for(&link, Duration::from_secs(12), |e| {
            matches!(e, LinkEvent::Reconnected(_) | LinkEvent::Stopped { .. })
        })
        .await
        {
            LinkEvent::Reconnected(_) => {}
            other => panic!("expected Reconnected, got {other:?}"),
        }
        // The late-join snapshot carries the keyframe stored before the outage.
        match wait_for(&link, Duration::from_secs(5), |_| true).await {
            LinkEvent::Message(Message::Snapshot(s)) => {
                assert_eq!(s.keyframes.len(), 1, "{s:?}");
                assert_eq!((s.keyframes[0].region, s.keyframes[0].keyframe_id), (5, 9));
                assert_eq!(s.keyframes[0].owner, other_id);
            }
            other => panic!("expected the snapshot, got {other:?}"),
        }
        let p = relay_pose(&other, &link, Duration::from_secs(5)).await;
        assert_eq!(p.site, other_id);
        link.close_async().await;
        other.close_async().await;
        coord.shutdown().await;
    })
    .await;
}

/// The link is handed to the simulation thread.
#[test]
fn link_is_send() {
    fn assert_send<T: Send>() {}
    assert_send::<Link>();
    assert_send::<LinkEvent>();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plain_simulation_thread_uses_the_sync_api() {
    init_tracing();
    within(15, async {
        let (coord, addr, _) = coordinator().await;
        let cfg = config(addr, &coord, "sim-thread");
        let rt = tokio::runtime::Handle::current();
        // A fixed-rate loop on a std thread: never blocks on the network, closes synchronously.
        let sim = std::thread::spawn(move || {
            let link = Link::start(cfg, &rt).expect("link start");
            let mut joined = None;
            let mut steps = 0u32;
            let t0 = std::time::Instant::now();
            while t0.elapsed() < Duration::from_secs(5) {
                let step_start = std::time::Instant::now();
                while let Some(e) = link.try_recv() {
                    if let LinkEvent::Welcome(w) = e {
                        joined = Some(w.site);
                    }
                }
                link.send_datagram(pose(steps as f32 * 1e-3));
                steps += 1;
                // The non-blocking calls cost far less than a 1 ms step.
                assert!(step_start.elapsed() < Duration::from_millis(50));
                if joined.is_some() && steps > 50 {
                    break;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            let stats = link.stats();
            link.close();
            (joined, stats)
        });
        let (joined, stats) = tokio::task::spawn_blocking(move || sim.join().unwrap())
            .await
            .unwrap();
        assert!(joined.is_some(), "never joined: {stats:?}");
        let cs = coord.stats();
        assert_eq!((cs.joined, cs.left), (1, 1), "{cs:?}");
        assert!(cs.datagrams_in > 0, "{cs:?}");
        coord.shutdown().await;
    })
    .await;
}

/// A fake coordinator that answers the Join, then sends garbage on every channel.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_input_is_counted_not_fatal() {
    use quinn::VarInt;
    init_tracing();
    within(15, async {
        let (id, _, _) = Identity::generate_self_signed().unwrap();
        let server_config = server::tls::server_config(&id).unwrap();
        let ep =
            quinn::Endpoint::server(server_config, SocketAddr::from(([127, 0, 0, 1], 0))).unwrap();
        let addr = ep.local_addr().unwrap();
        let mut cfg = LinkConfig::new(
            addr,
            &id.fingerprint(),
            SESSION,
            invitation(),
            Role::Trainee,
            "victim",
            SCENE,
        );
        cfg.reconnect = false;
        let link = start(cfg);

        let conn = ep.accept().await.unwrap().await.unwrap();
        let (mut send, mut recv) = conn.accept_bi().await.unwrap();
        let mut dec = proto::FrameDecoder::default();
        match wire::read_frame(&mut recv, &mut dec).await.unwrap() {
            Some(Message::Join(j)) => assert_eq!(j.site_name, "victim"),
            other => panic!("expected Join, got {other:?}"),
        }
        let welcome = proto::Welcome {
            site: 4,
            session: proto::SessionInfo {
                name: SESSION.into(),
                scene_hash: SCENE.into(),
                max_sites: 8,
                protocol_version: proto::PROTOCOL_VERSION,
                heartbeat_interval_us: 500_000,
            },
            sites: vec![],
            coordinator_time_us: 0,
        };
        wire::write_frame(&mut send, &Message::Welcome(welcome))
            .await
            .unwrap();
        assert_eq!(welcome_site(&link).await, 4);

        // 1: control frame with an undecodable body (framing intact); 2: undecodable
        // datagram; 3: a stream that is not a frame; 4: a well-framed stream holding a
        // message that does not belong on a stream; 5: a truncated stream.
        send.write_all(&[0, 0, 0, 3, 1, 0xEE, 0xEE]).await.unwrap();
        conn.send_datagram(bytes::Bytes::from_static(&[1, 0xFF, 0xFF, 0xFF]))
            .unwrap();
        for body in [
            b"garbage, not a frame".to_vec(),
            proto::encode_frame(&Message::Heartbeat(proto::Heartbeat {
                site: 0,
                time_us: 1,
            })),
            proto::encode_frame(&Message::Keyframe(keyframe(1, 1, 10)))[..20].to_vec(),
        ] {
            let mut s = conn.open_uni().await.unwrap();
            s.write_all(&body).await.unwrap();
            s.finish().unwrap();
        }
        // Valid traffic still gets through on every channel afterwards.
        wire::send_datagram(&conn, &pose(0.5)).unwrap();
        wire::send_uni(&conn, &Message::Keyframe(keyframe(2, 1, 10)), 0)
            .await
            .unwrap();
        wire::write_frame(
            &mut send,
            &Message::Leave(proto::Leave {
                site: 9,
                reason: "x".into(),
            }),
        )
        .await
        .unwrap();
        let mut got = (false, false, false);
        let deadline = Instant::now() + Duration::from_secs(5);
        while got != (true, true, true) {
            assert!(
                Instant::now() < deadline,
                "valid traffic lost: {got:?}, {:?}",
                link.stats()
            );
            match link.try_recv() {
                Some(LinkEvent::Message(Message::ToolPose(_))) => got.0 = true,
                Some(LinkEvent::Message(Message::Keyframe(k))) => {
                    assert_eq!(k.region, 2);
                    got.1 = true;
                }
                Some(LinkEvent::Message(Message::Leave(l))) => {
                    assert_eq!(l.site, 9);
                    got.2 = true;
                }
                Some(e @ (LinkEvent::Disconnected { .. } | LinkEvent::Stopped { .. })) => {
                    panic!("link gave up on malformed input: {e:?}")
                }
                Some(_) => {}
                None => sleep(Duration::from_millis(5)).await,
            }
        }
        let deadline = Instant::now() + Duration::from_secs(3);
        while link.stats().malformed < 5 {
            assert!(Instant::now() < deadline, "{:?}", link.stats());
            sleep(Duration::from_millis(10)).await;
        }
        assert!(link.is_joined());

        // Broken framing on the control stream (oversized header) ends the connection.
        send.write_all(&[0xFF, 0xFF, 0xFF, 0xFF]).await.unwrap();
        match wait_for(&link, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Disconnected { .. })
        })
        .await
        {
            LinkEvent::Disconnected {
                reason,
                will_reconnect,
            } => {
                assert!(!will_reconnect);
                assert!(reason.contains("exceeds"), "{reason}");
            }
            _ => unreachable!(),
        }
        wait_for(&link, Duration::from_secs(3), |e| {
            matches!(e, LinkEvent::Stopped { .. })
        })
        .await;
        match tokio::time::timeout(Duration::from_secs(3), conn.closed()).await {
            Ok(quinn::ConnectionError::ApplicationClosed(c)) => {
                assert_eq!(
                    c.error_code,
                    VarInt::from_u32(proto::close_code::PROTOCOL_ERROR)
                );
            }
            other => panic!("expected a protocol-error close, got {other:?}"),
        }
        link.close_async().await;
        ep.close(VarInt::from_u32(0), b"");
    })
    .await;
}

async fn welcome_site(link: &Link) -> SiteId {
    welcome(link, Duration::from_secs(5)).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kicked_site_is_refused_and_stops() {
    init_tracing();
    within(15, async {
        let (coord, addr, _) = coordinator().await;
        let mut icfg = config(addr, &coord, "instructor");
        icfg.role = Role::Instructor;
        icfg.credential = proto::Credential::Token(TOKEN.into());
        let instructor = start(icfg);
        welcome(&instructor, Duration::from_secs(5)).await;
        let trainee = start(config(addr, &coord, "trainee"));
        let t_id = welcome(&trainee, Duration::from_secs(5)).await;
        instructor.send_control(Message::Command(proto::Command::KickSite {
            site: t_id,
            reason: "wrong patient".into(),
        }));
        match wait_for(&trainee, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Refused(_) | LinkEvent::Disconnected { .. })
        })
        .await
        {
            LinkEvent::Refused(r) => {
                assert_eq!(r.reason, RefusalReason::Kicked);
                assert!(r.text.contains("wrong patient"), "{}", r.text);
            }
            other => panic!("expected Refused(Kicked), got {other:?}"),
        }
        wait_for(&trainee, Duration::from_secs(3), |e| {
            matches!(e, LinkEvent::Stopped { .. })
        })
        .await;
        match wait_for(&instructor, Duration::from_secs(5), |e| {
            matches!(e, LinkEvent::Message(Message::Leave(_)))
        })
        .await
        {
            LinkEvent::Message(Message::Leave(l)) => assert_eq!(l.site, t_id),
            _ => unreachable!(),
        }
        // No reconnection attempt after a kick.
        sleep(Duration::from_millis(600)).await;
        assert_eq!(coord.stats().connections, 2);
        assert_eq!(trainee.stats().reconnects, 0);
        trainee.close_async().await;
        instructor.close_async().await;
        coord.shutdown().await;
    })
    .await;
}
