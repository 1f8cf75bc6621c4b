//! Keyframe streams between the coordinator and its sites: accepting a site's
//! unidirectional streams, reading one keyframe per stream, and relaying it to every other
//! site under the shared scheduler (`proto::KeyframeStreams`: newest wins, a bounded number
//! in flight per region, stalled streams reset).

use super::*;

pub(super) async fn uni_loop(shared: &Arc<Shared>, site: SiteId, conn: &Connection) -> String {
    let mut readers = JoinSet::new();
    loop {
        let mut recv = match conn.accept_uni().await {
            Ok(r) => r,
            Err(e) => return format!("connection: {e}"),
        };
        let observer = shared.lock().session.role(site) == Some(Role::Observer);
        if observer {
            inc(&shared.counters.dropped_messages);
            let _ = recv.stop(VarInt::from_u32(stream_code::REFUSED));
            continue;
        }
        readers.spawn(read_keyframe_stream(shared.clone(), site, recv));
        while readers.try_join_next().is_some() {}
    }
}

async fn read_keyframe_stream(shared: Arc<Shared>, site: SiteId, mut recv: RecvStream) {
    let limit = shared.max_frame + proto::codec::FRAME_HEADER_LEN;
    let bad = |recv: &mut RecvStream, what: String| {
        inc(&shared.counters.malformed_streams);
        warn!(site, "{what}; stream dropped");
        let _ = recv.stop(VarInt::from_u32(stream_code::MALFORMED));
    };
    let buf = match tokio::time::timeout(STREAM_READ_TIMEOUT, recv.read_to_end(limit)).await {
        Ok(Ok(b)) => b,
        Ok(Err(quinn::ReadToEndError::TooLong)) => {
            return bad(&mut recv, format!("stream longer than {limit} bytes"));
        }
        // The site replaced this keyframe by a newer one of the same region: normal.
        Ok(Err(quinn::ReadToEndError::Read(quinn::ReadError::Reset(code))))
            if code == VarInt::from_u32(stream_code::SUPERSEDED) =>
        {
            inc(&shared.counters.superseded_streams_in);
            debug!(site, "incoming keyframe stream superseded by the site");
            return;
        }
        // The connection ended (the site left or was lost): not the stream's fault.
        Ok(Err(quinn::ReadToEndError::Read(quinn::ReadError::ConnectionLost(e)))) => {
            debug!(site, error = %e, "keyframe stream ended with the connection");
            return;
        }
        Ok(Err(e)) => {
            inc(&shared.counters.malformed_streams);
            debug!(site, error = %e, "keyframe stream aborted");
            return;
        }
        Err(_) => return bad(&mut recv, "stream too slow".into()),
    };
    let mut dec = FrameDecoder::new(shared.max_frame);
    dec.push(&buf);
    let kf = match (dec.next_message(), dec.finish()) {
        (Ok(Some(Message::Keyframe(k))), Ok(())) => k,
        (Ok(Some(other)), Ok(())) => {
            return bad(
                &mut recv,
                format!("unexpected {} on a stream", other.kind()),
            );
        }
        (Ok(Some(_)), Err(e)) => return bad(&mut recv, format!("trailing data: {e}")),
        (Ok(None), Err(e)) | (Err(e), _) => {
            return bad(&mut recv, format!("bad stream ({} bytes): {e}", buf.len()));
        }
        (Ok(None), Ok(())) => return bad(&mut recv, "empty stream".into()),
    };
    let region = kf.region;
    let keyframe_id = kf.keyframe_id;
    let now = shared.clock.now_us();
    let mut st = shared.lock();
    let st = &mut *st;
    let stored = match st.session.on_keyframe(site, kf, Bytes::from(buf), now) {
        Ok(s) => s,
        Err(reason) => {
            inc(&shared.counters.dropped_messages);
            debug!(site, region, keyframe_id, ?reason, "keyframe dropped");
            return;
        }
    };
    inc(&shared.counters.keyframes_in);
    // recording: keyframe metadata.
    if let Some(r) = st.recording.as_mut() {
        r.on_keyframe(&stored.keyframe, stored.frame.len());
    }
    let now = Instant::now();
    let ids: Vec<SiteId> = st.peers.keys().copied().filter(|&id| id != site).collect();
    for id in ids {
        let Some(peer) = st.peers.get_mut(&id) else {
            continue;
        };
        let stall = proto::stall_time(peer.conn.rtt());
        let actions = peer
            .streams
            .submit(region, stored.frame.clone(), now, stall);
        debug!(
            to = id,
            region,
            keyframe_id,
            bytes = stored.frame.len(),
            "relaying keyframe"
        );
        relay_streams(&shared, peer, id, actions);
    }
}

/// Carries out the keyframe-stream scheduler's decisions for `peer` (site `id`).
pub(super) fn relay_streams(
    shared: &Arc<Shared>,
    peer: &mut Peer,
    id: SiteId,
    actions: Vec<StreamAction<Bytes>>,
) {
    for a in actions {
        match a {
            StreamAction::Open {
                token,
                region,
                payload,
            } => {
                let (ctx, crx) = oneshot::channel();
                peer.cancels.insert(token, ctx);
                let conn = peer.conn.clone();
                let shared = shared.clone();
                tokio::spawn(async move {
                    let len = payload.len();
                    let r = send_stream_once(&conn, payload, Some(crx)).await;
                    match &r {
                        Ok(true) => {
                            inc(&shared.counters.keyframes_relayed);
                            add(&shared.counters.bytes_relayed, len);
                        }
                        Ok(false) => inc(&shared.counters.keyframe_streams_reset),
                        Err(e) => debug!(to = id, region, error = %e, "keyframe relay failed"),
                    }
                    // The stream ended: a waiting keyframe may go out now.
                    let mut st = shared.lock();
                    if let Some(p) = st.peers.get_mut(&id) {
                        p.cancels.remove(&token);
                        p.streams.finished(region, token);
                        let stall = proto::stall_time(p.conn.rtt());
                        let more = p.streams.poll(Instant::now(), stall);
                        relay_streams(&shared, p, id, more);
                    }
                });
            }
            StreamAction::Reset { token, region } => {
                debug!(to = id, region, "superseding keyframe stream");
                if let Some(cancel) = peer.cancels.remove(&token) {
                    let _ = cancel.send(());
                }
            }
        }
    }
}

/// Send one frame on a new unidirectional stream at [`KEYFRAME_PRIORITY`] and wait until the
/// peer acknowledged it. `Ok(false)`: cancelled (stream reset with `SUPERSEDED`).
pub(super) async fn send_stream_once(
    conn: &Connection,
    frame: Bytes,
    cancel: Option<oneshot::Receiver<()>>,
) -> Result<bool, String> {
    // Cancelled by the keyframe-stream scheduler (a newer keyframe, this one stalled).
    // A dropped sender (peer gone) is not a cancellation.
    let cancelled = async move {
        match cancel {
            Some(rx) => {
                if rx.await.is_err() {
                    std::future::pending::<()>().await;
                }
            }
            None => std::future::pending::<()>().await,
        }
    };
    tokio::pin!(cancelled);
    let mut s = tokio::select! {
        s = conn.open_uni() => s.map_err(|e| e.to_string())?,
        _ = &mut cancelled => return Ok(false),
    };
    let _ = s.set_priority(KEYFRAME_PRIORITY);
    let done = {
        let write = async {
            s.write_chunk(frame).await.map_err(|e| e.to_string())?;
            s.finish().map_err(|e| e.to_string())?;
            match s.stopped().await {
                Ok(None) => Ok(()),
                Ok(Some(code)) => Err(format!("peer stopped the stream ({code})")),
                Err(e) => Err(e.to_string()),
            }
        };
        tokio::select! {
            r = write => Some(r),
            _ = &mut cancelled => None,
        }
    };
    match done {
        Some(r) => r.map(|()| true),
        None => {
            let _ = s.reset(VarInt::from_u32(stream_code::SUPERSEDED));
            Ok(false)
        }
    }
}
