use super::*;
use proto::*;

fn key() -> InviteKey {
    InviteKey::from_bytes([5; 32])
}

fn session() -> Session {
    Session::new(SessionConfig {
        scene_hash: Some("ab".into()),
        max_sites: 8,
        invite_key: Some(key()),
        ..SessionConfig::new("s", "t")
    })
}

fn invitation(role: Role, nonce: Nonce) -> String {
    key().sign(&InvitationClaims {
        key_id: [0; 8],
        session: "s".into(),
        role,
        site: None,
        expires_unix_s: u64::MAX,
        nonce,
    })
}

/// The instructor presents the token; the others an invitation for their role. A token
/// other than "t" is presented as a (wrong) instructor token.
fn credential(role: Role, token: &str) -> Credential {
    if role == Role::Instructor || token != "t" {
        Credential::Token(token.into())
    } else {
        Credential::Invitation(invitation(role, [1; 16]))
    }
}

/// `name` joins as `role` with the right credential, at time 0.
fn join_full(s: &mut Session, name: &str, role: Role) -> Joined {
    s.join(
        &Join {
            protocol_version: PROTOCOL_VERSION,
            scene_hash: "ab".into(),
            role,
            site_name: name.into(),
            session: "s".into(),
            credential: credential(role, "t"),
            time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
        },
        0,
    )
    .unwrap()
}

fn join(s: &mut Session, name: &str, role: Role) -> SiteId {
    join_full(s, name, role).welcome.site
}

fn kf(region: RegionId, id: KeyframeId, owner: SiteId, epoch: u32) -> RegionKeyframe {
    RegionKeyframe {
        region,
        keyframe_id: id,
        owner,
        sim_time: 0.0,
        epoch,
        tree_bits: vec![1],
        nodes: QuantisedNodes::default(),
        topology: 0,
    }
}

fn pose(site: SiteId) -> Message {
    Message::ToolPose(ToolPose {
        site,
        tool: 0,
        sim_time_s: 0.0,
        position: [0.0; 3],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.0,
        velocity: [0.0; 3],
        angular_velocity: [0.0; 3],
    })
}

#[test]
fn datagram_relay_restamps_sender_and_observer_dropped() {
    let mut s = session();
    let a = join(&mut s, "a", Role::Trainee);
    let o = join(&mut s, "o", Role::Observer);
    match s.on_datagram(a, pose(99), 5) {
        DatagramVerdict::Relay {
            msg: Message::ToolPose(p),
            restamped,
        } => {
            assert_eq!(p.site, a);
            assert!(restamped);
        }
        v => panic!("{v:?}"),
    }
    assert_eq!(
        s.on_datagram(o, pose(o), 5),
        DatagramVerdict::Drop(DropReason::Observer)
    );
    assert!(matches!(
        s.on_datagram(o, Message::ClockPing(ClockPing { seq: 1, t1_us: 2 }), 7),
        DatagramVerdict::Reply(Message::ClockPong(ClockPong {
            seq: 1,
            t1_us: 2,
            t2_us: 7,
            ..
        }))
    ));
    assert_eq!(
        s.on_datagram(42, pose(42), 5),
        DatagramVerdict::Drop(DropReason::UnknownSite)
    );
}

#[test]
fn keyframes_owner_epoch_and_staleness() {
    let mut s = session();
    let a = join(&mut s, "a", Role::Trainee);
    let b = join(&mut s, "b", Role::Trainee);
    let o = join(&mut s, "o", Role::Observer);
    assert!(s.on_keyframe(a, kf(1, 1, a, 0), Bytes::new(), 0).is_ok());
    assert_eq!(
        s.on_keyframe(a, kf(1, 1, a, 0), Bytes::new(), 0)
            .unwrap_err(),
        DropReason::StaleKeyframe
    );
    assert_eq!(
        s.on_keyframe(a, kf(1, 2, a, 3), Bytes::new(), 0)
            .unwrap_err(),
        DropReason::StaleEpoch
    );
    assert_eq!(
        s.on_keyframe(o, kf(1, 2, o, 0), Bytes::new(), 0)
            .unwrap_err(),
        DropReason::Observer
    );
    s.on_control(
        a,
        Message::OwnershipRequest(OwnershipRequest {
            region: 1,
            claim_time_us: 0,
        }),
        0,
    );
    assert_eq!(
        s.on_keyframe(b, kf(1, 5, b, 0), Bytes::new(), 0)
            .unwrap_err(),
        DropReason::NotOwner
    );
    // owner field corrected and re-encoded
    let st = s.on_keyframe(a, kf(1, 3, 77, 0), Bytes::new(), 0).unwrap();
    assert_eq!(st.keyframe.owner, a);
    let mut d = FrameDecoder::default();
    d.push(&st.frame);
    assert!(matches!(d.next_message().unwrap(), Some(Message::Keyframe(k)) if k.owner == a));
    let snap = s.snapshot();
    assert_eq!(snap.keyframes.len(), 1);
    assert_eq!(snap.owners, vec![RegionOwner { region: 1, site: a }]);
}

#[test]
fn ack_routed_to_keyframe_owner() {
    let mut s = session();
    let a = join(&mut s, "a", Role::Trainee);
    let b = join(&mut s, "b", Role::Trainee);
    s.on_keyframe(a, kf(4, 1, a, 0), Bytes::new(), 0).unwrap();
    let acts = s.on_control(
        b,
        Message::KeyframeAck(KeyframeAck {
            region: 4,
            keyframe_id: 1,
            site: 0,
            shows_keyframes: true,
        }),
        0,
    );
    assert_eq!(
        acts,
        vec![Action::Control {
            to: Target::One(a),
            msg: Message::KeyframeAck(KeyframeAck {
                region: 4,
                keyframe_id: 1,
                site: b,
                shows_keyframes: true,
            })
        }]
    );
}

#[test]
fn instructor_commands_and_kick() {
    let mut s = session();
    let i = join(&mut s, "prof", Role::Instructor);
    let a = join(&mut s, "a", Role::Trainee);
    // trainees cannot command
    let acts = s.on_control(
        a,
        Message::Command(Command::ResetScene {
            epoch: 0,
            sim_time_s: 2.0,
        }),
        0,
    );
    assert!(matches!(
        acts[0],
        Action::Drop {
            reason: DropReason::NotInstructor,
            ..
        }
    ));
    // … and told why.
    assert!(matches!(
        &acts[1],
        Action::Control {
            to: Target::One(to),
            msg: Message::CommandRefused(r),
        } if *to == a && r.command == "reset-scene" && r.reason.contains("instructor")
    ));
    assert_eq!(s.epoch(), 0);
    // reset bumps epoch and clears keyframes
    s.on_keyframe(a, kf(1, 1, a, 0), Bytes::new(), 0).unwrap();
    let acts = s.on_control(
        i,
        Message::Command(Command::ResetScene {
            epoch: 0,
            sim_time_s: 2.0,
        }),
        0,
    );
    assert_eq!(
        acts,
        vec![Action::Control {
            to: Target::All,
            msg: Message::Command(Command::ResetScene {
                epoch: 1,
                sim_time_s: 2.0
            })
        }]
    );
    assert!(s.keyframe(1).is_none());
    // kick: refusal to the target, leave to others, close
    s.on_control(
        a,
        Message::OwnershipRequest(OwnershipRequest {
            region: 9,
            claim_time_us: 0,
        }),
        0,
    );
    let acts = s.on_control(
        i,
        Message::Command(Command::KickSite {
            site: a,
            reason: "x".into(),
        }),
        0,
    );
    assert!(
        matches!(&acts[0], Action::Control { to: Target::One(t), msg: Message::Refusal(r) } if *t == a && r.reason == RefusalReason::Kicked)
    );
    assert!(acts.iter().any(
        |x| matches!(x, Action::Control { msg: Message::OwnershipRelease(r), .. } if r.region == 9)
    ));
    assert!(
        acts.iter()
            .any(|x| matches!(x, Action::Control { msg: Message::Leave(l), .. } if l.site == a))
    );
    assert!(
        matches!(acts.last().unwrap(), Action::Close { site, code, .. } if *site == a && *code == close_code::KICKED)
    );
    assert!(s.site(a).is_none());
    assert!(s.site_left(a, "again").is_empty());
}

#[test]
fn late_joiner_gets_teaching_state() {
    let mut s = session();
    let i = join(&mut s, "prof", Role::Instructor);
    s.on_control(
        i,
        Message::Teaching(TeachingTrajectory {
            id: 3,
            tool: 0,
            samples: vec![],
        }),
        0,
    );
    s.on_control(
        i,
        Message::Command(Command::StartPlayback {
            trajectory: 3,
            start_sim_time_s: 1.0,
        }),
        0,
    );
    let j = join_full(&mut s, "late", Role::Trainee);
    assert!(j.actions.iter().any(|a| matches!(
        a,
        Action::Control {
            msg: Message::Teaching(_),
            ..
        }
    )));
    assert!(j.actions.iter().any(|a| matches!(
        a,
        Action::Control {
            msg: Message::Command(Command::StartPlayback { .. }),
            ..
        }
    )));
}

#[test]
fn liveness_armed_by_first_heartbeat() {
    let mut s = session();
    let a = join(&mut s, "a", Role::Trainee);
    let b = join(&mut s, "b", Role::Trainee);
    assert!(
        s.poll_liveness(100_000_000).is_empty(),
        "not armed: no timeout"
    );
    s.on_datagram(
        a,
        Message::Heartbeat(Heartbeat {
            site: a,
            time_us: 0,
        }),
        100_000_000,
    );
    assert!(s.poll_liveness(100_000_000 + 1_100_000).is_empty());
    let acts = s.poll_liveness(100_000_000 + 1_200_000);
    assert!(
        matches!(acts.last().unwrap(), Action::Close { site, code, .. } if *site == a && *code == close_code::TIMED_OUT)
    );
    assert!(s.site(b).is_some());
}

#[test]
fn quick_reconnect_replaces_a_silent_member_only() {
    let mut s = session();
    let iv = s.config().heartbeat_interval_us;
    let again = |name: &str, role: Role, token: &str| Join {
        protocol_version: PROTOCOL_VERSION,
        scene_hash: "ab".into(),
        role,
        site_name: name.into(),
        session: "s".into(),
        credential: credential(role, token),
        time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
    };
    let t0 = 1_000_000;
    let a = s
        .join(&again("a", Role::Trainee, "t"), t0)
        .unwrap()
        .welcome
        .site;
    let b = join(&mut s, "b", Role::Trainee);
    s.on_control(
        a,
        Message::OwnershipRequest(OwnershipRequest {
            region: 2,
            claim_time_us: 0,
        }),
        t0,
    );
    // still talking: the name stays taken
    s.on_datagram(
        a,
        Message::Heartbeat(Heartbeat {
            site: a,
            time_us: 0,
        }),
        t0 + iv,
    );
    let t = t0 + iv + RESUME_SILENCE_INTERVALS * iv - 1;
    let r = s.join(&again("a", Role::Trainee, "t"), t).unwrap_err();
    assert_eq!(r.reason, RefusalReason::NameTaken);
    // silent long enough, but another role or a wrong token: no replacement
    let t = t + 1;
    let r = s.join(&again("a", Role::Instructor, "t"), t).unwrap_err();
    assert_eq!(r.reason, RefusalReason::NameTaken);
    let r = s.join(&again("a", Role::Trainee, "x"), t).unwrap_err();
    assert_eq!(r.reason, RefusalReason::WrongToken);
    assert!(s.site(a).is_some());
    // same name and role, silent: replaced
    let j = s.join(&again("a", Role::Trainee, "t"), t).unwrap();
    assert_eq!(j.replaced, Some(a));
    assert_ne!(j.welcome.site, a);
    assert!(s.site(a).is_none());
    assert_eq!(s.owner(2), None);
    assert!(
        j.actions
            .iter()
            .any(|x| matches!(x, Action::Control { msg: Message::Leave(l), .. } if l.site == a))
    );
    assert!(j.actions.iter().any(|x| matches!(x, Action::Close { site, code, .. } if *site == a && *code == close_code::TIMED_OUT)));
    assert!(j.welcome.sites.iter().all(|e| e.site != a));
    assert!(s.site(b).is_some());
}

#[test]
fn status_table() {
    let mut s = session();
    let a = join(&mut s, "a", Role::Trainee);
    s.on_datagram(
        a,
        Message::SimTime(SimTimeStamp {
            site: a,
            sim_time_s: 2.5,
            step: 2500,
            wall_send_us: 0,
        }),
        9,
    );
    s.set_rtt(a, 1234);
    let st = s.status(10);
    assert_eq!(st.sites[0].sim_time_s, 2.5);
    assert_eq!(st.sites[0].step, 2500);
    assert_eq!(st.sites[0].rtt_us, 1234);
    assert_eq!(s.max_sim_time(), 2.5);
}

#[test]
fn revoking_an_invitation_removes_its_members_only() {
    let mut s = session();
    let i = join(&mut s, "prof", Role::Instructor);
    let join_with = |s: &mut Session, name: &str, nonce: Nonce| {
        s.join(
            &Join {
                protocol_version: PROTOCOL_VERSION,
                scene_hash: "ab".into(),
                role: Role::Trainee,
                site_name: name.into(),
                session: "s".into(),
                credential: Credential::Invitation(invitation(Role::Trainee, nonce)),
                time_scale_milli: proto::TIME_SCALE_REAL_MILLI,
            },
            0,
        )
        .unwrap()
        .welcome
        .site
    };
    let a = join_with(&mut s, "a", [1; 16]);
    let b = join_with(&mut s, "b", [2; 16]);
    let acts = s.set_revoked(BTreeSet::from([[1; 16]]));
    assert!(
        matches!(&acts[0], Action::Control { to: Target::One(t), msg: Message::Refusal(r) } if *t == a && r.reason == RefusalReason::InvitationRevoked)
    );
    assert!(acts.iter().any(
        |x| matches!(x, Action::Close { site, code, .. } if *site == a && *code == close_code::INVITATION_REVOKED)
    ));
    assert!(s.site(a).is_none());
    assert!(s.site(b).is_some() && s.site(i).is_some());
    // the same list again changes nothing
    assert!(s.set_revoked(BTreeSet::from([[1; 16]])).is_empty());
}

fn cut(epoch: u32, site: SiteId, seq: u32) -> TopologyOp {
    TopologyOp {
        epoch,
        site,
        seq,
        sim_time: 1.0,
        kind: TopologyKind::Cut {
            triangles: vec![[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]],
        },
    }
}

#[test]
fn topology_ops_are_relayed_once_kept_for_late_joiners_and_cleared_by_a_reset() {
    let mut s = session();
    let i = join(&mut s, "prof", Role::Instructor);
    let a = join(&mut s, "a", Role::Trainee);
    let o = join(&mut s, "o", Role::Observer);
    // Relayed to the others, stamped with the sender's id.
    let acts = s.on_control(a, Message::Topology(cut(0, 99, 0)), 0);
    assert_eq!(
        acts,
        vec![Action::Control {
            to: Target::AllExcept(a),
            msg: Message::Topology(cut(0, a, 0)),
        }]
    );
    // A duplicate is not relayed again; an op of another epoch or from an observer is
    // dropped.
    assert!(
        s.on_control(a, Message::Topology(cut(0, a, 0)), 0)
            .is_empty()
    );
    assert!(matches!(
        s.on_control(a, Message::Topology(cut(3, a, 1)), 0)[0],
        Action::Drop {
            reason: DropReason::StaleEpoch,
            ..
        }
    ));
    assert!(matches!(
        s.on_control(o, Message::Topology(cut(0, o, 0)), 0)[0],
        Action::Drop {
            reason: DropReason::Observer,
            ..
        }
    ));
    // A late joiner's snapshot holds it.
    assert_eq!(s.snapshot().topology, vec![cut(0, a, 0)]);
    // A reset starts a new scene: no topology.
    s.on_control(
        i,
        Message::Command(Command::ResetScene {
            epoch: 0,
            sim_time_s: 1.0,
        }),
        0,
    );
    assert!(s.snapshot().topology.is_empty());
}

/// A refinement decision is relayed every time it comes and never kept:
/// late joiners take the tree states from keyframes, and the cut log stays for cuts.
#[test]
fn refinements_are_relayed_but_not_kept() {
    let mut s = session();
    let _i = join(&mut s, "prof", Role::Instructor);
    let a = join(&mut s, "a", Role::Trainee);
    let refine = |site, seq| TopologyOp {
        epoch: 0,
        site,
        seq,
        sim_time: 1.0,
        kind: TopologyKind::Refine {
            focus: vec![[0.01, 0.02, 0.03]],
            distance: 0.01,
            level: 3,
            merge: vec![[1, 2, 3]],
        },
    };
    // Not deduplicated: the same id twice is relayed twice (applying a refinement twice
    // changes nothing).
    for seq in [7, 8, 8] {
        assert_eq!(
            s.on_control(a, Message::Topology(refine(99, seq)), 0),
            vec![Action::Control {
                to: Target::AllExcept(a),
                msg: Message::Topology(refine(a, seq)),
            }]
        );
    }
    assert!(s.snapshot().topology.is_empty());
    // An observer's is dropped like any op of its.
    let o = join(&mut s, "o", Role::Observer);
    assert!(matches!(
        s.on_control(o, Message::Topology(refine(o, 1)), 0)[0],
        Action::Drop {
            reason: DropReason::Observer,
            ..
        }
    ));
}

/// Teaching replay start/stop, like a scene reset, is the instructor's: a trainee's or an
/// observer's request is refused with a reason, dropped, and relayed to nobody.
#[test]
fn teaching_start_and_stop_are_refused_from_anyone_but_the_instructor() {
    let mut s = session();
    let i = join(&mut s, "prof", Role::Instructor);
    let a = join(&mut s, "a", Role::Trainee);
    let o = join(&mut s, "gallery", Role::Observer);
    let start = Command::StartPlayback {
        trajectory: 1,
        start_sim_time_s: 2.0,
    };
    let stop = Command::StopPlayback { trajectory: 1 };
    for (who, name) in [(a, "a"), (o, "gallery")] {
        for (c, label) in [
            (start.clone(), "start-playback"),
            (stop.clone(), "stop-playback"),
        ] {
            let acts = s.on_control(who, Message::Command(c), 0);
            assert_eq!(acts.len(), 2, "{name} {label}: {acts:?}");
            assert!(
                matches!(
                    acts[0],
                    Action::Drop {
                        reason: DropReason::NotInstructor,
                        ..
                    }
                ),
                "{name} {label}: {acts:?}"
            );
            assert!(
                matches!(
                    &acts[1],
                    Action::Control {
                        to: Target::One(to),
                        msg: Message::CommandRefused(r),
                    } if *to == who && r.command == label && r.reason.contains("instructor")
                ),
                "{name} {label}: {acts:?}"
            );
        }
    }
    // nothing was armed for late joiners by the refused start
    let late = join_full(&mut s, "late", Role::Trainee);
    assert!(!late.actions.iter().any(|x| matches!(
        x,
        Action::Control {
            msg: Message::Command(Command::StartPlayback { .. }),
            ..
        }
    )));
    // the instructor's start and stop are relayed to everyone else
    for c in [start, stop] {
        let acts = s.on_control(i, Message::Command(c.clone()), 0);
        assert_eq!(
            acts,
            vec![Action::Control {
                to: Target::AllExcept(i),
                msg: Message::Command(c)
            }]
        );
    }
}

#[test]
fn a_site_over_its_relay_budget_is_dropped_alone_and_refilled_at_its_rate() {
    let mut s = session();
    s.set_relay_budget(RelayBudget {
        rate_per_s: 100.0,
        burst: 10.0,
    });
    let a = join(&mut s, "a", Role::Trainee);
    let b = join(&mut s, "b", Role::Trainee);
    let relayed = |v: DatagramVerdict| matches!(v, DatagramVerdict::Relay { .. });
    // A burst at one instant: the bucket's 10, then drops.
    let burst = (0..50)
        .filter(|_| relayed(s.on_datagram(a, pose(a), 0)))
        .count();
    assert_eq!(burst, 10);
    assert_eq!(
        s.on_datagram(a, pose(a), 0),
        DatagramVerdict::Drop(DropReason::OverBudget)
    );
    // The other site keeps its own budget, and what is not relayed (clock pings) still works.
    assert_eq!(
        (0..5)
            .filter(|_| relayed(s.on_datagram(b, pose(b), 0)))
            .count(),
        5
    );
    assert!(matches!(
        s.on_datagram(a, Message::ClockPing(ClockPing { seq: 1, t1_us: 2 }), 0),
        DatagramVerdict::Reply(_)
    ));
    // Flooding at 1000/s for 2 s: the refill rate (100/s) gets through, nothing more.
    let mut n = 0;
    for i in 1..=2000u64 {
        n += usize::from(relayed(s.on_datagram(a, pose(a), i * 1000)));
    }
    assert!((199..=201).contains(&n), "relayed {n} of 2000");
    // After a pause the bucket is full again, not larger.
    let later = 2_000_000 + 10_000_000;
    let refilled = (0..50)
        .filter(|_| relayed(s.on_datagram(a, pose(a), later)))
        .count();
    assert_eq!(refilled, 10);
}
