use proptest::prelude::*;

use super::*;

fn claims() -> InvitationClaims {
    InvitationClaims {
        key_id: [0; 8],
        session: "lap-chole".into(),
        role: Role::Trainee,
        site: Some("kyoto".into()),
        expires_unix_s: 1_800_000_000,
        nonce: [3; NONCE_LEN],
    }
}

#[test]
fn sign_verify_round_trip_and_format() {
    let key = InviteKey::from_bytes([1; KEY_LEN]);
    let inv = key.sign(&claims());
    assert!(inv.starts_with(PREFIX), "{inv}");
    assert!(
        inv[PREFIX.len()..]
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'),
        "one copy-pasteable word: {inv}"
    );
    assert!(inv.len() < 200, "short: {} characters", inv.len());
    let got = key.verify(&inv).unwrap();
    assert_eq!(got.key_id, key.id());
    assert_eq!(
        got,
        InvitationClaims {
            key_id: key.id(),
            ..claims()
        }
    );
    // surrounding whitespace from copy-paste is fine
    assert_eq!(key.verify(&format!("  {inv}\n")).unwrap(), got);
    assert_eq!(peek_claims(&inv).unwrap(), got);
}

#[test]
fn every_signed_field_matters() {
    let key = InviteKey::from_bytes([1; KEY_LEN]);
    let inv = key.sign(&claims());
    let (_, raw, tag) = split(&inv).unwrap();
    // Re-sign altered claims with the genuine tag: each alteration is caught.
    let alter: [fn(&mut InvitationClaims); 5] = [
        |c| c.session.push('x'),
        |c| c.role = Role::Instructor,
        |c| c.site = None,
        |c| c.expires_unix_s += 1,
        |c| c.nonce[0] ^= 1,
    ];
    for f in alter {
        let mut c = InvitationClaims {
            key_id: key.id(),
            ..claims()
        };
        f(&mut c);
        let mut body = postcard::to_allocvec(&c).unwrap();
        assert_ne!(body, raw);
        body.extend_from_slice(&tag);
        let forged = format!("{PREFIX}{}", URL_SAFE_NO_PAD.encode(body));
        assert_eq!(key.verify(&forged), Err(InviteError::BadSignature));
    }
}

#[test]
fn foreign_key_and_envelope_errors_are_named() {
    let ours = InviteKey::from_bytes([1; KEY_LEN]);
    let theirs = InviteKey::from_bytes([2; KEY_LEN]);
    assert_ne!(ours.id(), theirs.id());
    assert!(matches!(
        ours.verify(&theirs.sign(&claims())),
        Err(InviteError::ForeignKey { .. })
    ));
    assert_eq!(ours.verify("hello"), Err(InviteError::NotAnInvitation));
    assert!(matches!(
        ours.verify("csi1.!!!"),
        Err(InviteError::BadEncoding(_))
    ));
    assert_eq!(ours.verify("csi1.AAAA"), Err(InviteError::Corrupted));
    let long = format!("{PREFIX}{}", "A".repeat(MAX_INVITATION_LEN));
    assert!(matches!(ours.verify(&long), Err(InviteError::TooLong(_))));
    // trailing bytes inside the envelope
    let inv = ours.sign(&claims());
    let mut raw = URL_SAFE_NO_PAD.decode(&inv[PREFIX.len()..]).unwrap();
    raw.insert(raw.len() - 32, 0);
    let padded = format!("{PREFIX}{}", URL_SAFE_NO_PAD.encode(raw));
    assert_eq!(ours.verify(&padded), Err(InviteError::Corrupted));
}

#[test]
fn key_debug_hides_the_secret_and_nonce_parses() {
    let key = InviteKey::from_bytes([0xab; KEY_LEN]);
    let dbg = format!("{key:?}");
    assert!(!dbg.contains("abab"), "{dbg}");
    let n = [0x0f; NONCE_LEN];
    assert_eq!(parse_nonce(&hex(&n)), Some(n));
    assert_eq!(parse_nonce(&hex(&n).to_uppercase()), Some(n));
    assert_eq!(parse_nonce("0f"), None);
    assert_eq!(parse_nonce(&"zz".repeat(NONCE_LEN)), None);
    assert_eq!(parse_nonce(&"é".repeat(NONCE_LEN)), None);
}

proptest! {
    /// Garbage never panics and is never accepted.
    #[test]
    fn garbage_never_panics(s in ".{0,300}", bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let key = InviteKey::from_bytes([1; KEY_LEN]);
        prop_assert!(key.verify(&s).is_err());
        let enc = format!("{PREFIX}{}", URL_SAFE_NO_PAD.encode(&bytes));
        prop_assert!(key.verify(&enc).is_err());
        let _ = peek_claims(&enc);
        let _ = parse_nonce(&s);
    }

    /// Any single-byte change of a genuine invitation is refused.
    #[test]
    fn any_bit_flip_is_refused(pos in 0usize..1000, bit in 0u8..8) {
        let key = InviteKey::from_bytes([1; KEY_LEN]);
        let inv = key.sign(&claims());
        let mut raw = URL_SAFE_NO_PAD.decode(&inv[PREFIX.len()..]).unwrap();
        let pos = pos % raw.len();
        raw[pos] ^= 1 << bit;
        let altered = format!("{PREFIX}{}", URL_SAFE_NO_PAD.encode(raw));
        prop_assert!(key.verify(&altered).is_err());
    }
}
