use super::*;
use crate::PROTOCOL_VERSION;
use crate::invite::InvitationClaims;

const SCENE: &str = "ab12";

fn cfg() -> SessionConfig {
    SessionConfig {
        scene_hash: Some(SCENE.into()),
        max_sites: 3,
        invite_key: Some(key()),
        ..SessionConfig::new("lap-chole", "s3cret")
    }
}

fn key() -> InviteKey {
    InviteKey::from_bytes([7; 32])
}

/// Coordinator clock of the tests (µs since the Unix epoch) and its Unix seconds.
const NOW_US: u64 = 1_700_000_000_000_000;
const NOW_S: u64 = NOW_US / 1_000_000;

fn claims(role: Role, site: Option<&str>) -> InvitationClaims {
    InvitationClaims {
        key_id: [0; 8],
        session: "lap-chole".into(),
        role,
        site: site.map(String::from),
        expires_unix_s: NOW_S + 3600,
        nonce: [1; 16],
    }
}

fn invited(name: &str, role: Role, claims: &InvitationClaims) -> Join {
    Join {
        role,
        credential: Credential::Invitation(key().sign(claims)),
        ..join(name)
    }
}

fn join(name: &str) -> Join {
    Join {
        protocol_version: PROTOCOL_VERSION,
        scene_hash: SCENE.into(),
        role: Role::Instructor,
        site_name: name.into(),
        session: "lap-chole".into(),
        credential: Credential::Token("s3cret".into()),
        time_scale_milli: TIME_SCALE_REAL_MILLI,
    }
}

fn reason(h: &mut JoinHandshake, j: Join) -> RefusalReason {
    h.handle_join(&j, 0).unwrap_err().reason
}

#[test]
fn welcome_assigns_ids_and_lists_sites() {
    let mut h = JoinHandshake::new(cfg());
    let w1 = h.handle_join(&join("kyoto"), 10).unwrap();
    let w2 = h.handle_join(&join("osaka"), 20).unwrap();
    assert_eq!(w1.site, 1);
    assert_eq!(w2.site, 2);
    assert_eq!(w2.sites.len(), 2);
    assert_eq!(w2.coordinator_time_us, 20);
    assert_eq!(w2.session.scene_hash, SCENE);
    assert_eq!(w2.session.protocol_version, PROTOCOL_VERSION);
}

#[test]
fn refusals_in_order() {
    let mut h = JoinHandshake::new(cfg());
    let mut j = join("a");
    j.protocol_version = 99;
    j.credential = Credential::Token("bad".into());
    assert_eq!(
        reason(&mut h, j),
        RefusalReason::WrongVersion {
            server: PROTOCOL_VERSION,
            client: 99
        }
    );
    let mut j = join("a");
    j.session = "other".into();
    assert_eq!(reason(&mut h, j), RefusalReason::WrongSession);
    let mut j = join("a");
    j.credential = Credential::Token("s3creT".into());
    j.scene_hash = "ffff".into();
    assert_eq!(reason(&mut h, j), RefusalReason::WrongToken);
    let mut j = join("a");
    j.scene_hash = "ffff".into();
    assert_eq!(
        reason(&mut h, j),
        RefusalReason::WrongScene {
            expected: SCENE.into()
        }
    );
    // The time scale is checked after the scene and before the name.
    let mut j = join("");
    j.scene_hash = "ffff".into();
    j.time_scale_milli = 2000;
    assert!(matches!(
        reason(&mut h, j),
        RefusalReason::WrongScene { .. }
    ));
    let mut j = join("");
    j.time_scale_milli = 2000;
    assert_eq!(
        reason(&mut h, j),
        RefusalReason::WrongTimeScale {
            server_milli: TIME_SCALE_REAL_MILLI,
            client_milli: 2000
        }
    );
    assert_eq!(reason(&mut h, join("")), RefusalReason::Malformed);
    assert_eq!(reason(&mut h, join("a\nb")), RefusalReason::Malformed);
    assert_eq!(
        reason(&mut h, join(&"x".repeat(65))),
        RefusalReason::Malformed
    );
    assert!(h.is_empty());
}

#[test]
fn a_dilated_session_admits_its_own_time_scale_only() {
    let mut h = JoinHandshake::new(SessionConfig {
        time_scale_milli: 2000,
        ..cfg()
    });
    let mut j = join("a");
    j.time_scale_milli = 2000;
    assert!(h.handle_join(&j, 0).is_ok());
    let r = h.handle_join(&join("b"), 0).unwrap_err();
    assert_eq!(
        r.reason,
        RefusalReason::WrongTimeScale {
            server_milli: 2000,
            client_milli: TIME_SCALE_REAL_MILLI
        }
    );
    assert!(r.text.contains("--time-scale"), "{}", r.text);
}

#[test]
fn scene_hash_case_insensitive() {
    let mut h = JoinHandshake::new(cfg());
    let mut j = join("a");
    j.scene_hash = "AB12".into();
    assert!(h.handle_join(&j, 0).is_ok());
}

#[test]
fn name_taken_then_free_after_leave() {
    let mut h = JoinHandshake::new(cfg());
    let w = h.handle_join(&join("a"), 0).unwrap();
    assert_eq!(reason(&mut h, join("a")), RefusalReason::NameTaken);
    assert!(h.leave(w.site).is_some());
    assert!(h.leave(w.site).is_none());
    let w2 = h.handle_join(&join("a"), 0).unwrap();
    assert_ne!(w2.site, w.site, "ids are not reused immediately");
}

#[test]
fn capacity() {
    let mut h = JoinHandshake::new(cfg());
    for n in ["a", "b", "c"] {
        h.handle_join(&join(n), 0).unwrap();
    }
    assert_eq!(reason(&mut h, join("d")), RefusalReason::Full);
}

#[test]
fn kicked_name_cannot_rejoin() {
    let mut h = JoinHandshake::new(cfg());
    let w = h.handle_join(&join("a"), 0).unwrap();
    let (entry, r) = h.kick(w.site, "bye").unwrap();
    assert_eq!(entry.name, "a");
    assert_eq!(r.reason, RefusalReason::Kicked);
    assert!(h.kick(w.site, "again").is_none());
    assert_eq!(reason(&mut h, join("a")), RefusalReason::Kicked);
}

#[test]
fn first_join_fixes_scene_when_unset() {
    let mut h = JoinHandshake::new(SessionConfig::new("lap-chole", "s3cret"));
    let mut j = join("a");
    j.scene_hash = "CAFE".into();
    let w = h.handle_join(&j, 0).unwrap();
    assert_eq!(w.session.scene_hash, "cafe");
    assert_eq!(
        reason(&mut h, join("b")),
        RefusalReason::WrongScene {
            expected: "cafe".into()
        }
    );
}

#[test]
fn id_allocation_wraps_and_skips_used() {
    let mut h = JoinHandshake::new(SessionConfig {
        max_sites: 10,
        ..cfg()
    });
    h.next_id = u16::MAX;
    let a = h.handle_join(&join("a"), 0).unwrap().site;
    let b = h.handle_join(&join("b"), 0).unwrap().site;
    assert_eq!((a, b), (u16::MAX, 1));
}

#[test]
fn instructor_token_admits_the_instructor_role_only() {
    let mut h = JoinHandshake::new(cfg());
    for role in [Role::Trainee, Role::Observer] {
        let j = Join { role, ..join("b") };
        let r = h.handle_join(&j, NOW_US).unwrap_err();
        assert_eq!(r.reason, RefusalReason::WrongRole);
        assert!(r.text.contains("invitation"), "{}", r.text);
    }
    // a wrong token is a wrong token whatever the role
    let j = Join {
        role: Role::Trainee,
        credential: Credential::Token("guess".into()),
        ..join("b")
    };
    assert_eq!(reason(&mut h, j), RefusalReason::WrongToken);
    assert!(h.handle_join(&join("prof"), NOW_US).is_ok());
}

#[test]
fn invitation_admits_its_session_role_and_site_until_expiry() {
    let mut h = JoinHandshake::new(cfg());
    let refuse = |h: &mut JoinHandshake, j: Join, now: u64| h.handle_join(&j, now).unwrap_err();
    // good: unbound trainee invitation, and a bound observer one
    let j = invited("kyoto", Role::Trainee, &claims(Role::Trainee, None));
    assert!(h.handle_join(&j, NOW_US).is_ok());
    let obs = claims(Role::Observer, Some("osaka"));
    assert!(
        h.handle_join(&invited("osaka", Role::Observer, &obs), NOW_US)
            .is_ok()
    );
    // wrong role
    let r = refuse(
        &mut h,
        invited("nara", Role::Instructor, &claims(Role::Trainee, None)),
        NOW_US,
    );
    assert_eq!(r.reason, RefusalReason::WrongRole);
    assert!(r.text.contains("trainee"), "{}", r.text);
    let r = refuse(&mut h, invited("nara", Role::Trainee, &obs), NOW_US);
    assert_eq!(r.reason, RefusalReason::WrongRole);
    // wrong bound site
    let r = refuse(&mut h, invited("nara", Role::Observer, &obs), NOW_US);
    assert_eq!(r.reason, RefusalReason::WrongSite);
    assert!(r.text.contains("osaka"), "{}", r.text);
    // another session (same key)
    let other = InvitationClaims {
        session: "other".into(),
        ..claims(Role::Trainee, None)
    };
    let r = refuse(&mut h, invited("nara", Role::Trainee, &other), NOW_US);
    assert_eq!(r.reason, RefusalReason::WrongSession);
    assert!(r.text.contains("other"), "{}", r.text);
    // expired: valid up to the second before expiry
    let c = claims(Role::Trainee, None);
    let at_expiry = c.expires_unix_s * 1_000_000;
    let r = refuse(&mut h, invited("nara", Role::Trainee, &c), at_expiry);
    assert_eq!(r.reason, RefusalReason::InvitationExpired);
    assert!(
        h.validate(&invited("nara", Role::Trainee, &c), at_expiry - 1)
            .is_ok()
    );
    assert_eq!(h.len(), 2);
}

#[test]
fn forged_foreign_and_garbage_invitations_are_invalid() {
    let mut h = JoinHandshake::new(cfg());
    let good = key().sign(&claims(Role::Trainee, None));
    let foreign = InviteKey::from_bytes([8; 32]).sign(&claims(Role::Trainee, None));
    // flip one character of the signature part
    let mut forged = good.clone().into_bytes();
    let last = forged.len() - 2;
    forged[last] = if forged[last] == b'A' { b'B' } else { b'A' };
    let forged = String::from_utf8(forged).unwrap();
    for (inv, needle) in [
        (foreign, "another coordinator"),
        (forged, "signature"),
        ("csi1.".to_string(), "corrupted"),
        ("s3cret".to_string(), "not an invitation"),
    ] {
        let j = Join {
            role: Role::Trainee,
            credential: Credential::Invitation(inv),
            ..join("x")
        };
        let r = h.handle_join(&j, NOW_US).unwrap_err();
        assert_eq!(r.reason, RefusalReason::InvalidInvitation);
        assert!(r.text.contains(needle), "{needle}: {}", r.text);
    }
    // a coordinator without a key accepts no invitation at all
    let mut h = JoinHandshake::new(SessionConfig {
        invite_key: None,
        ..cfg()
    });
    let j = invited("x", Role::Trainee, &claims(Role::Trainee, None));
    assert_eq!(reason(&mut h, j), RefusalReason::InvalidInvitation);
}

#[test]
fn revocation_refuses_new_joins_and_names_current_members() {
    let mut h = JoinHandshake::new(cfg());
    let c = claims(Role::Trainee, None);
    let w = h
        .handle_join(&invited("kyoto", Role::Trainee, &c), NOW_US)
        .unwrap();
    let prof = h.handle_join(&join("prof"), NOW_US).unwrap();
    assert!(h.set_revoked(BTreeSet::from([[9; 16]])).is_empty());
    assert_eq!(h.set_revoked(BTreeSet::from([c.nonce])), vec![w.site]);
    assert!(h.site(prof.site).is_some());
    h.leave(w.site);
    let r = h
        .handle_join(&invited("kyoto", Role::Trainee, &c), NOW_US)
        .unwrap_err();
    assert_eq!(r.reason, RefusalReason::InvitationRevoked);
    assert!(r.text.contains(&crate::invite::hex(&c.nonce)), "{}", r.text);
    // other invitations are unaffected
    let c2 = InvitationClaims {
        nonce: [2; 16],
        ..c
    };
    assert!(
        h.handle_join(&invited("kyoto", Role::Trainee, &c2), NOW_US)
            .is_ok()
    );
}

#[test]
fn admin_requests_need_the_instructor_token() {
    let h = JoinHandshake::new(cfg());
    let req = |credential: Credential, session: &str| AdminRequest {
        protocol_version: PROTOCOL_VERSION,
        session: session.into(),
        credential,
        action: crate::msg::AdminAction::MintInvitation {
            role: Role::Trainee,
            site: None,
            valid_for_s: 60,
        },
    };
    assert!(
        h.validate_admin(&req(Credential::Token("s3cret".into()), "lap-chole"))
            .is_ok()
    );
    let r = |c, s| h.validate_admin(&req(c, s)).unwrap_err().reason;
    assert_eq!(
        r(Credential::Token("nope".into()), "lap-chole"),
        RefusalReason::WrongToken
    );
    assert_eq!(
        r(Credential::Token("s3cret".into()), "other"),
        RefusalReason::WrongSession
    );
    let inv = key().sign(&claims(Role::Trainee, None));
    assert_eq!(
        r(Credential::Invitation(inv), "lap-chole"),
        RefusalReason::WrongRole
    );
}
