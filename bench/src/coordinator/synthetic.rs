//! The synthetic sites of `cosurg bench coordinator`: join, send the message mix, receive
//! and time what the coordinator relays.

use super::*;

/// A joined synthetic site.
pub(super) struct SiteLink {
    conn: Connection,
    send: quinn::SendStream,
    recv: quinn::RecvStream,
    decoder: FrameDecoder,
    site: SiteId,
    heartbeat: Duration,
}

pub(super) async fn connect(
    ep: &Endpoint,
    addr: std::net::SocketAddr,
    join: &Join,
) -> Result<SiteLink> {
    tokio::time::timeout(Duration::from_secs(20), async {
        let conn = ep.connect(addr, "localhost")?.await?;
        let (mut send, mut recv) = conn.open_bi().await?;
        send.write_all(&proto::encode_frame(&Message::Join(join.clone())))
            .await?;
        let mut decoder = FrameDecoder::default();
        loop {
            if let Some(m) = decoder.next_message()? {
                return match m {
                    Message::Welcome(w) => Ok(SiteLink {
                        conn,
                        send,
                        recv,
                        decoder,
                        site: w.site,
                        heartbeat: Duration::from_micros(w.session.heartbeat_interval_us),
                    }),
                    Message::Refusal(r) => bail!("join refused: {:?}: {}", r.reason, r.text),
                    other => bail!("expected Welcome, got {}", other.kind()),
                };
            }
            match recv.read_chunk(64 * 1024, true).await? {
                Some(c) => decoder.push(&c.bytes),
                None => bail!("control stream ended before Welcome"),
            }
        }
    })
    .await
    .context("join timed out")?
}

#[derive(Clone, Copy)]
pub(super) struct SendParams {
    pub(super) pose_hz: f64,
    pub(super) stamp_hz: f64,
    pub(super) keyframe_hz: f64,
    /// Where in each of its periods this site sends, as a fraction of the period (0..1).
    pub(super) phase: f64,
}

/// Run one synthetic site: send the mix until `stop_s`, receive until `end_s`.
pub(super) async fn site(
    link: SiteLink,
    shared: Arc<Shared>,
    p: SendParams,
    stop_s: f64,
    end_s: f64,
) -> Received {
    let SiteLink {
        conn,
        mut send,
        mut recv,
        mut decoder,
        site,
        heartbeat,
    } = link;
    let (ack_tx, mut ack_rx) = mpsc::channel::<Message>(1024);
    let end = tokio::time::Instant::from_std(shared.epoch + Duration::from_secs_f64(end_s));
    // Control: write acks, drain what the coordinator sends.
    // One deadline timer per loop, not one per message: the generator's timer operations
    // (a lock shared by the runtime's workers) were a visible share of its CPU.
    let control = async {
        let mut buf_ok = true;
        let deadline = tokio::time::sleep_until(end);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => return,
                m = ack_rx.recv() => match m {
                    Some(m) => {
                        if send.write_all(&proto::encode_frame(&m)).await.is_err() {
                            return;
                        }
                    }
                    None => return,
                },
                c = recv.read_chunk(64 * 1024, true), if buf_ok => match c {
                    Ok(Some(c)) => {
                        decoder.push(&c.bytes);
                        while let Ok(Some(_)) = decoder.next_message() {}
                    }
                    _ => buf_ok = false,
                },
            }
        }
    };
    // Datagrams in.
    let datagrams = async {
        let mut lat = Vec::new();
        let deadline = tokio::time::sleep_until(end);
        tokio::pin!(deadline);
        loop {
            let d = tokio::select! {
                _ = &mut deadline => break,
                d = conn.read_datagram() => match d {
                    Ok(d) => d,
                    Err(_) => break,
                },
            };
            let now = shared.now_s();
            let sent = match proto::decode(&d) {
                Ok(Message::ToolPose(p)) => p.sim_time_s,
                Ok(Message::SimTime(s)) => s.wall_send_us as f64 * 1e-6,
                _ => continue,
            };
            if shared.in_window(sent) {
                lat.push(((now - sent) * 1e6).max(0.0) as u32);
            }
        }
        lat
    };
    // Keyframe streams in: read, measure, acknowledge.
    let keyframes = async {
        let mut lat = Vec::new();
        let mut readers = tokio::task::JoinSet::new();
        let deadline = tokio::time::sleep_until(end);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => break,
                s = conn.accept_uni() => match s {
                    Ok(mut r) => {
                        let shared = shared.clone();
                        readers.spawn(async move {
                            let buf = r.read_to_end(proto::DEFAULT_MAX_FRAME + 4).await.ok()?;
                            let now = shared.now_s();
                            let mut dec = FrameDecoder::default();
                            dec.push(&buf);
                            match dec.next_message() {
                                Ok(Some(Message::Keyframe(k))) => Some((k, now)),
                                _ => None,
                            }
                        });
                    }
                    Err(_) => break,
                },
                Some(r) = readers.join_next(), if !readers.is_empty() => {
                    if let Ok(Some((k, now))) = r {
                        if shared.in_window(k.sim_time) {
                            lat.push(((now - k.sim_time) * 1e6).max(0.0) as u32);
                        }
                        let _ = ack_tx.try_send(Message::KeyframeAck(KeyframeAck {
                            region: k.region,
                            keyframe_id: k.keyframe_id,
                            site,
                            shows_keyframes: false,
                        }));
                    }
                }
            }
        }
        lat
    };
    let sender = send_mix(&conn, &shared, site, p, stop_s, heartbeat);
    let (datagram_latency_us, keyframe_latency_us, (), ()) =
        tokio::join!(datagrams, keyframes, control, sender);
    conn.close(0u32.into(), b"bench done");
    Received {
        datagram_latency_us,
        keyframe_latency_us,
    }
}

/// The synthetic site's sending loop (see the module documentation).
async fn send_mix(
    conn: &Connection,
    shared: &Shared,
    site: SiteId,
    p: SendParams,
    stop_s: f64,
    heartbeat: Duration,
) {
    let period = 1.0 / p.pose_hz;
    // Each stream of messages starts at the site's phase within its own period, so that
    // neither poses nor stamps nor keyframes of different sites line up.
    let mut next = p.phase * period;
    let (mut next_stamp, mut next_kf, mut next_hb) = (
        p.phase / p.stamp_hz.max(f64::MIN_POSITIVE),
        p.phase / p.keyframe_hz.max(f64::MIN_POSITIVE),
        0.0,
    );
    let region = u32::from(site);
    let mut keyframe_id = 0u64;
    let mut seq = 0u64;
    let mut streams = tokio::task::JoinSet::new();
    loop {
        let at = shared.epoch + Duration::from_secs_f64(next);
        tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await;
        let now = shared.now_s();
        if now >= stop_s {
            break;
        }
        let counted = shared.in_window(now);
        let datagram = |m: &Message| {
            if conn.send_datagram(Bytes::from(proto::encode(m))).is_ok() && counted {
                shared.datagrams_sent.fetch_add(1, Ordering::Relaxed);
            }
        };
        seq += 1;
        datagram(&Message::ToolPose(ToolPose {
            site,
            tool: 0,
            sim_time_s: now,
            position: [seq as f32 * 1e-4, 0.01, 0.02],
            orientation: [1.0, 0.0, 0.0, 0.0],
            jaw_rad: 0.1,
            velocity: [0.01, 0.0, 0.0],
            angular_velocity: [0.0; 3],
        }));
        if p.stamp_hz > 0.0 && now >= next_stamp {
            next_stamp += 1.0 / p.stamp_hz;
            datagram(&Message::SimTime(SimTimeStamp {
                site,
                sim_time_s: now,
                step: seq,
                wall_send_us: (now * 1e6) as u64,
            }));
        }
        if now >= next_hb {
            next_hb += heartbeat.as_secs_f64();
            // Heartbeats are not relayed: not counted.
            let hb = Message::Heartbeat(Heartbeat {
                site,
                time_us: (now * 1e6) as u64,
            });
            let _ = conn.send_datagram(Bytes::from(proto::encode(&hb)));
        }
        if p.keyframe_hz > 0.0 && now >= next_kf {
            next_kf += 1.0 / p.keyframe_hz;
            keyframe_id += 1;
            let mut kf = shared.keyframe.clone();
            kf.region = region;
            kf.owner = site;
            kf.keyframe_id = keyframe_id;
            kf.sim_time = now;
            let frame = Bytes::from(proto::encode_frame(&Message::Keyframe(kf)));
            let conn = conn.clone();
            if counted {
                shared.keyframes_sent.fetch_add(1, Ordering::Relaxed);
            }
            streams.spawn(async move {
                let mut s = conn.open_uni().await.ok()?;
                let _ = s.set_priority(KEYFRAME_PRIORITY);
                s.write_chunk(frame).await.ok()?;
                s.finish().ok()
            });
            while streams.try_join_next().is_some() {}
        }
        next += period;
    }
}
