//! Property tests of the codec: roundtrip of every message kind, and `decode` never panics on
//! arbitrary bytes or on mutated valid encodings; framing under arbitrary chunking.

use cosurg_proto::quant::QuantisedNodes;
use cosurg_proto::*;
use proptest::collection::vec;
use proptest::prelude::*;

fn s() -> impl Strategy<Value = String> {
    "[a-zA-Z0-9 _é-]{0,24}"
}
fn f3() -> impl Strategy<Value = [f32; 3]> {
    prop::array::uniform3(-10.0f32..10.0)
}
fn f4() -> impl Strategy<Value = [f32; 4]> {
    prop::array::uniform4(-1.0f32..1.0)
}
fn simt() -> impl Strategy<Value = f64> {
    0.0f64..1.0e5
}
fn role() -> impl Strategy<Value = Role> {
    prop_oneof![
        Just(Role::Instructor),
        Just(Role::Trainee),
        Just(Role::Observer)
    ]
}
fn entry() -> impl Strategy<Value = SiteEntry> {
    (any::<u16>(), s(), role()).prop_map(|(site, name, role)| SiteEntry { site, name, role })
}
fn reason() -> impl Strategy<Value = RefusalReason> {
    prop_oneof![
        Just(RefusalReason::WrongToken),
        (any::<u16>(), any::<u16>())
            .prop_map(|(server, client)| RefusalReason::WrongVersion { server, client }),
        s().prop_map(|expected| RefusalReason::WrongScene { expected }),
        Just(RefusalReason::WrongSession),
        Just(RefusalReason::NameTaken),
        Just(RefusalReason::Full),
        Just(RefusalReason::Kicked),
        Just(RefusalReason::Malformed),
        Just(RefusalReason::InvalidInvitation),
        Just(RefusalReason::InvitationExpired),
        Just(RefusalReason::InvitationRevoked),
        Just(RefusalReason::WrongRole),
        Just(RefusalReason::WrongSite),
        any::<u64>().prop_map(|retry_after_ms| RefusalReason::RateLimited { retry_after_ms }),
        (any::<u32>(), any::<u32>()).prop_map(|(server_milli, client_milli)| {
            RefusalReason::WrongTimeScale {
                server_milli,
                client_milli,
            }
        }),
    ]
}
fn nodes() -> impl Strategy<Value = QuantisedNodes> {
    vec(
        (
            any::<u32>(),
            prop::array::uniform3(-0.2f64..0.2),
            prop::array::uniform3(-1.0f64..1.0),
        ),
        0..40,
    )
    .prop_map(|n| {
        let ids: Vec<u32> = n.iter().map(|x| x.0).collect();
        let p: Vec<[f64; 3]> = n.iter().map(|x| x.1).collect();
        let v: Vec<[f64; 3]> = n.iter().map(|x| x.2).collect();
        QuantisedNodes::encode_default(&ids, &p, &v).unwrap()
    })
}
fn keyframe() -> impl Strategy<Value = RegionKeyframe> {
    (
        any::<u32>(),
        any::<u64>(),
        any::<u16>(),
        simt(),
        any::<u32>(),
        vec(any::<u8>(), 0..64),
        nodes(),
        any::<u32>(),
    )
        .prop_map(
            |(region, keyframe, owner, sim_time_s, epoch, tree_bits, nodes, topology)| {
                RegionKeyframe {
                    region,
                    keyframe_id: keyframe,
                    owner,
                    sim_time: sim_time_s,
                    epoch,
                    tree_bits,
                    nodes,
                    topology,
                }
            },
        )
}

fn topology_op() -> impl Strategy<Value = TopologyOp> {
    (
        any::<u32>(),
        any::<u16>(),
        any::<u32>(),
        vec(vec(-1.0e3f64..1.0e3, 9), 0..4),
        proptest::option::of((any::<u32>(), vec(any::<u32>(), 0..8))),
        any::<f64>(),
        proptest::option::of(vec(any::<f64>(), 6)),
        proptest::option::of((
            vec(vec(any::<f64>(), 3), 0..4),
            any::<f64>(),
            any::<u8>(),
            vec(vec(any::<i64>(), 3), 0..4),
        )),
    )
        .prop_map(
            |(epoch, site, seq, tris, release, sim_time, clip, refine)| TopologyOp {
                epoch,
                site,
                seq,
                sim_time,
                kind: match (release, clip) {
                    _ if refine.is_some() => {
                        let (focus, distance, level, merge) = refine.expect("some");
                        TopologyKind::Refine {
                            focus: focus.iter().map(|p| [p[0], p[1], p[2]]).collect(),
                            distance,
                            level,
                            merge: merge.iter().map(|g| [g[0], g[1], g[2]]).collect(),
                        }
                    }
                    (_, Some(e)) => TopologyKind::Clip {
                        ends: std::array::from_fn(|i| std::array::from_fn(|k| e[3 * i + k])),
                    },
                    (Some((layer, springs)), None) => TopologyKind::Release { layer, springs },
                    (None, None) => TopologyKind::Cut {
                        triangles: tris
                            .into_iter()
                            .map(|t| std::array::from_fn(|i| std::array::from_fn(|k| t[3 * i + k])))
                            .collect(),
                    },
                },
            },
        )
}
fn sample() -> impl Strategy<Value = ToolSample> {
    (simt(), f3(), f4(), -1.0f32..1.0).prop_map(|(t_s, position, orientation, jaw_rad)| {
        ToolSample {
            t_s,
            position,
            orientation,
            jaw_rad,
        }
    })
}
fn command() -> impl Strategy<Value = Command> {
    prop_oneof![
        (any::<u32>(), -1e6f64..1e6)
            .prop_map(|(epoch, sim_time_s)| Command::ResetScene { epoch, sim_time_s }),
        (any::<u16>(), s()).prop_map(|(site, reason)| Command::KickSite { site, reason }),
        (any::<u32>(), simt()).prop_map(|(trajectory, start_sim_time_s)| Command::StartPlayback {
            trajectory,
            start_sim_time_s
        }),
        any::<u32>().prop_map(|trajectory| Command::StopPlayback { trajectory }),
    ]
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        (
            any::<u16>(),
            s(),
            role(),
            s(),
            s(),
            s(),
            any::<bool>(),
            any::<u32>()
        )
            .prop_map(|(v, h, role, n, sess, tok, invited, time_scale_milli)| {
                Message::Join(Join {
                    protocol_version: v,
                    scene_hash: h,
                    role,
                    site_name: n,
                    session: sess,
                    credential: if invited {
                        Credential::Invitation(tok)
                    } else {
                        Credential::Token(tok)
                    },
                    time_scale_milli,
                })
            }),
        (s(), role(), proptest::option::of(s()), any::<u64>(), s()).prop_map(
            |(sess, role, site, valid_for_s, tok)| {
                Message::Admin(AdminRequest {
                    protocol_version: PROTOCOL_VERSION,
                    session: sess,
                    credential: Credential::Token(tok),
                    action: AdminAction::MintInvitation {
                        role,
                        site,
                        valid_for_s,
                    },
                })
            }
        ),
        (s(), s(), proptest::option::of(s()), any::<u16>(), s()).prop_map(
            |(sess, instructor_token, scene_hash, max_sites, tok)| {
                Message::Admin(AdminRequest {
                    protocol_version: PROTOCOL_VERSION,
                    session: sess,
                    credential: Credential::Token(tok),
                    action: AdminAction::CreateSession {
                        instructor_token,
                        scene_hash,
                        max_sites,
                    },
                })
            }
        ),
        (s(), role(), proptest::option::of(s()), any::<u64>(), s()).prop_map(
            |(invitation, role, site, expires_unix_s, nonce_hex)| {
                Message::Invitation(InvitationIssued {
                    invitation,
                    role,
                    site,
                    expires_unix_s,
                    nonce_hex,
                })
            }
        ),
        (
            any::<u16>(),
            s(),
            s(),
            any::<u16>(),
            vec(entry(), 0..5),
            any::<u64>(),
            any::<u64>()
        )
            .prop_map(
                |(site, name, scene_hash, max_sites, sites, t, hb)| Message::Welcome(Welcome {
                    site,
                    session: SessionInfo {
                        name,
                        scene_hash,
                        max_sites,
                        protocol_version: PROTOCOL_VERSION,
                        heartbeat_interval_us: hb
                    },
                    sites,
                    coordinator_time_us: t
                })
            ),
        (reason(), s()).prop_map(|(reason, text)| Message::Refusal(Refusal { reason, text })),
        (any::<u32>(), any::<u64>())
            .prop_map(|(seq, t1_us)| Message::ClockPing(ClockPing { seq, t1_us })),
        (any::<u32>(), any::<u64>(), any::<u64>(), any::<u64>()).prop_map(
            |(seq, t1_us, t2_us, t3_us)| Message::ClockPong(ClockPong {
                seq,
                t1_us,
                t2_us,
                t3_us
            })
        ),
        (any::<u16>(), simt(), any::<u64>(), any::<u64>()).prop_map(
            |(site, sim_time_s, step, wall_send_us)| {
                Message::SimTime(SimTimeStamp {
                    site,
                    sim_time_s,
                    step,
                    wall_send_us,
                })
            }
        ),
        (
            any::<u16>(),
            any::<u8>(),
            simt(),
            f3(),
            f4(),
            -1.0f32..1.0,
            f3(),
            f3()
        )
            .prop_map(
                |(
                    site,
                    tool,
                    sim_time_s,
                    position,
                    orientation,
                    jaw_rad,
                    velocity,
                    angular_velocity,
                )| {
                    Message::ToolPose(ToolPose {
                        site,
                        tool,
                        sim_time_s,
                        position,
                        orientation,
                        jaw_rad,
                        velocity,
                        angular_velocity,
                    })
                }
            ),
        keyframe().prop_map(Message::Keyframe),
        (
            any::<u32>(),
            any::<u16>(),
            any::<u32>(),
            simt(),
            any::<u64>(),
            vec(any::<u8>(), 0..100)
        )
            .prop_map(
                |(region, site, epoch, sim_time_s, base_keyframe, xor_bits)| Message::TreeDelta(
                    TreeDelta {
                        region,
                        site,
                        epoch,
                        sim_time: sim_time_s,
                        base_keyframe,
                        xor_bits
                    }
                )
            ),
        (any::<u32>(), any::<u64>(), any::<u16>(), any::<bool>()).prop_map(
            |(region, keyframe, site, shows_keyframes)| {
                Message::KeyframeAck(KeyframeAck {
                    region,
                    keyframe_id: keyframe,
                    site,
                    shows_keyframes,
                })
            }
        ),
        (any::<u32>(), any::<u64>()).prop_map(|(region, claim_time_us)| Message::OwnershipRequest(
            OwnershipRequest {
                region,
                claim_time_us
            }
        )),
        (any::<u32>(), any::<u16>(), any::<Option<u16>>()).prop_map(|(region, site, previous)| {
            Message::OwnershipGrant(OwnershipGrant {
                region,
                site,
                previous,
            })
        }),
        (any::<u32>(), any::<u16>()).prop_map(|(region, site)| Message::OwnershipRelease(
            OwnershipRelease { region, site }
        )),
        (
            any::<u32>(),
            any::<Option<u16>>(),
            prop_oneof![
                Just(DenyReason::HeldByOther),
                Just(DenyReason::ObserverCannotOwn),
                Just(DenyReason::NotOwner)
            ]
        )
            .prop_map(
                |(region, holder, reason)| Message::OwnershipDeny(OwnershipDeny {
                    region,
                    holder,
                    reason
                })
            ),
        (
            simt(),
            any::<u32>(),
            vec((any::<u32>(), any::<u16>()), 0..4),
            vec(keyframe(), 0..3),
            vec(topology_op(), 0..3)
        )
            .prop_map(|(sim_time_s, epoch, owners, keyframes, topology)| {
                Message::Snapshot(Snapshot {
                    sim_time_s,
                    epoch,
                    owners: owners
                        .into_iter()
                        .map(|(region, site)| RegionOwner { region, site })
                        .collect(),
                    keyframes,
                    topology,
                })
            }),
        (any::<u32>(), any::<u8>(), vec(sample(), 0..20)).prop_map(|(id, tool, samples)| {
            Message::Teaching(TeachingTrajectory { id, tool, samples })
        }),
        command().prop_map(Message::Command),
        (any::<u16>(), s()).prop_map(|(site, reason)| Message::Leave(Leave { site, reason })),
        (any::<u16>(), any::<u64>())
            .prop_map(|(site, time_us)| Message::Heartbeat(Heartbeat { site, time_us })),
        (
            any::<u64>(),
            vec(
                (
                    any::<u16>(),
                    s(),
                    role(),
                    simt(),
                    any::<u64>(),
                    any::<u32>()
                ),
                0..5
            )
        )
            .prop_map(|(coordinator_time_us, rows)| Message::Status(Status {
                coordinator_time_us,
                sites: rows
                    .into_iter()
                    .map(|(site, name, role, sim_time_s, step, rtt_us)| SiteStatus {
                        site,
                        name,
                        role,
                        sim_time_s,
                        step,
                        rtt_us
                    })
                    .collect()
            })),
        entry().prop_map(Message::SiteJoined),
        topology_op().prop_map(Message::Topology),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, .. ProptestConfig::default() })]

    #[test]
    fn roundtrip(m in message()) {
        let b = encode(&m);
        prop_assert_eq!(b[0], codec::WIRE_TAG);
        let d = decode(&b).unwrap();
        prop_assert_eq!(&d, &m);
        prop_assert_eq!(encode(&d), b);
    }

    #[test]
    fn frame_roundtrip_any_chunking(ms in vec(message(), 1..6), chunk in 1usize..300) {
        let stream: Vec<u8> = ms.iter().flat_map(encode_frame).collect();
        let mut dec = FrameDecoder::default();
        let mut got = Vec::new();
        for c in stream.chunks(chunk) {
            dec.push(c);
            while let Some(m) = dec.next_message().unwrap() {
                got.push(m);
            }
        }
        dec.finish().unwrap();
        prop_assert_eq!(got, ms);
    }

    #[test]
    fn decode_arbitrary_bytes_never_panics(b in vec(any::<u8>(), 0..512)) {
        let _ = decode(&b);
        let mut tagged = vec![codec::WIRE_TAG];
        tagged.extend_from_slice(&b);
        let _ = decode(&tagged);
    }

    #[test]
    fn decode_mutated_never_panics(
        m in message(),
        flips in vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        cut in any::<prop::sample::Index>(),
    ) {
        let mut b = encode(&m);
        for (i, x) in &flips {
            let i = i.index(b.len());
            b[i] ^= x;
        }
        let _ = decode(&b);
        let n = cut.index(b.len() + 1);
        let _ = decode(&b[..n]);
        // a truncated valid encoding never decodes to a message
        let valid = encode(&m);
        let k = cut.index(valid.len());
        prop_assert!(decode(&valid[..k]).is_err());
    }

    #[test]
    fn frame_decoder_arbitrary_bytes_never_panics(b in vec(any::<u8>(), 0..2048), chunk in 1usize..64) {
        let mut dec = FrameDecoder::new(1024);
        for c in b.chunks(chunk) {
            dec.push(c);
            loop {
                match dec.next_message() {
                    Ok(Some(_)) => continue,
                    Ok(None) => break,
                    Err(FrameError::Decode(_)) => continue,
                    Err(_) => break,
                }
            }
        }
        let _ = dec.finish();
    }
}

#[test]
fn huge_length_prefixes_do_not_allocate() {
    // A Vec length of u32::MAX in a tiny input must fail cleanly, not allocate 4 GiB.
    let mut b = vec![codec::WIRE_TAG, 7 /* Keyframe */];
    b.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0x0f]);
    assert!(decode(&b).is_err());
    let mut b = vec![codec::WIRE_TAG, 15 /* Teaching */, 1, 1];
    b.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0x0f]);
    assert!(decode(&b).is_err());
}
