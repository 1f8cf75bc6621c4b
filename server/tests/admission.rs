//! Admission over real QUIC: invitations minted through the admin path, refusals of bad
//! invitations with their close codes, revocation of a running member, rate limiting of
//! failed joins, and peers of the previous protocol version.

use std::time::Duration;

use cosurg_server::admin::{AdminError, InvitationRequest, mint_remote};
use cosurg_server::ratelimit::RateLimitConfig;
use cosurg_server::state::{self, StateDir};
use cosurg_server::{Coordinator, CoordinatorConfig, CoordinatorHandle, tls};
use proto::*;
use quinn::Endpoint;
use test_support::link::{self, LinkError};

const SCENE: &str = "abcd";
const T: Duration = Duration::from_secs(30);

struct Fixture {
    handle: CoordinatorHandle,
    addr: std::net::SocketAddr,
    endpoint: Endpoint,
    state: StateDir,
    key: InviteKey,
    _dir: tempfile::TempDir,
}

fn start_with(f: impl FnOnce(&mut CoordinatorConfig)) -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let state = StateDir::new(dir.path());
    let (key, _) = state.invite_key().unwrap();
    let session = SessionConfig {
        scene_hash: Some(SCENE.into()),
        invite_key: Some(key.clone()),
        ..SessionConfig::new("lap-chole", "s3cret")
    };
    let mut cfg = CoordinatorConfig::ephemeral(session).unwrap();
    cfg.state_dir = Some(dir.path().to_path_buf());
    f(&mut cfg);
    let (handle, addr) = Coordinator::bind(cfg).unwrap();
    let client_cfg = tls::client_config_pinned(handle.fingerprint()).unwrap();
    let endpoint = link::client_endpoint_on("127.0.0.1:0".parse().unwrap(), client_cfg).unwrap();
    Fixture {
        handle,
        addr,
        endpoint,
        state,
        key,
        _dir: dir,
    }
}

impl Fixture {
    fn request(&self, role: Role, site: Option<&str>) -> InvitationRequest {
        InvitationRequest {
            session: "lap-chole".into(),
            token: "s3cret".into(),
            role,
            site: site.map(String::from),
            valid_for: Duration::from_secs(600),
        }
    }

    async fn join(
        &self,
        name: &str,
        role: Role,
        credential: Credential,
    ) -> Result<link::SiteLink, LinkError> {
        let join = link::join_message(name, role, "lap-chole", credential, SCENE);
        link::connect_and_join(&self.endpoint, self.addr, "localhost", &join).await
    }

    fn mint(&self, role: Role, site: Option<&str>, valid_for_s: u64) -> String {
        state::mint(
            &self.key,
            "lap-chole",
            role,
            site,
            valid_for_s,
            state::unix_now_s(),
        )
        .unwrap()
        .invitation
    }
}

fn refused(r: Result<link::SiteLink, LinkError>) -> Refusal {
    match r {
        Err(LinkError::Refused(r)) => r,
        Err(e) => panic!("expected a refusal, got {e}"),
        Ok(s) => panic!("expected a refusal, joined as {}", s.welcome.site),
    }
}

#[tokio::test]
async fn instructor_mints_through_the_running_coordinator_without_disturbing_its_site() {
    tokio::time::timeout(T, async {
        let f = start_with(|_| {});
        let prof = f
            .join("prof", Role::Instructor, Credential::Token("s3cret".into()))
            .await
            .unwrap();
        let issued = mint_remote(
            &f.endpoint,
            f.addr,
            "localhost",
            &f.request(Role::Trainee, Some("kyoto")),
        )
        .await
        .unwrap();
        assert!(issued.invitation.starts_with("csi1."));
        assert_eq!(issued.site.as_deref(), Some("kyoto"));
        let inv = Credential::Invitation(issued.invitation.clone());
        // bound to kyoto
        let r = refused(f.join("osaka", Role::Trainee, inv.clone()).await);
        assert_eq!(r.reason, RefusalReason::WrongSite);
        let kyoto = f.join("kyoto", Role::Trainee, inv).await.unwrap();
        // the admin connection never became a site; the instructor is still there
        let names: Vec<String> = f
            .handle
            .status()
            .sites
            .into_iter()
            .map(|s| s.name)
            .collect();
        assert_eq!(names, vec!["prof".to_string(), "kyoto".to_string()]);
        assert_eq!(prof.welcome.site, 1);
        assert!(prof.conn.close_reason().is_none());
        // wrong token, instructor invitation, unknown session: refused with reasons
        let mut bad = f.request(Role::Trainee, None);
        bad.token = "guess".into();
        let e = mint_remote(&f.endpoint, f.addr, "localhost", &bad)
            .await
            .unwrap_err();
        assert!(
            matches!(&e, AdminError::Refused(r) if r.reason == RefusalReason::WrongToken),
            "{e}"
        );
        let e = mint_remote(
            &f.endpoint,
            f.addr,
            "localhost",
            &f.request(Role::Instructor, None),
        )
        .await
        .unwrap_err();
        assert!(e.to_string().contains("trainees and observers"), "{e}");
        let mut other = f.request(Role::Observer, None);
        other.session = "other".into();
        let e = mint_remote(&f.endpoint, f.addr, "localhost", &other)
            .await
            .unwrap_err();
        assert!(
            matches!(&e, AdminError::Refused(r) if r.reason == RefusalReason::WrongSession),
            "{e}"
        );
        drop(kyoto);
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn bad_invitations_are_refused_with_their_close_codes() {
    tokio::time::timeout(T, async {
        let f = start_with(|c| c.rate_limit.burst = 100);
        let foreign = InviteKey::from_bytes([9; 32]);
        let foreign_inv = state::mint(
            &foreign,
            "lap-chole",
            Role::Trainee,
            None,
            600,
            state::unix_now_s(),
        )
        .unwrap()
        .invitation;
        let other_session = state::mint(
            &f.key,
            "other",
            Role::Trainee,
            None,
            600,
            state::unix_now_s(),
        )
        .unwrap()
        .invitation;
        let cases = [
            (
                Role::Trainee,
                f.mint(Role::Trainee, None, 0),
                RefusalReason::InvitationExpired,
                close_code::INVITATION_EXPIRED,
                "expired",
            ),
            (
                Role::Trainee,
                foreign_inv,
                RefusalReason::InvalidInvitation,
                close_code::INVALID_INVITATION,
                "another coordinator",
            ),
            (
                Role::Trainee,
                "csi1.AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA".into(),
                RefusalReason::InvalidInvitation,
                close_code::INVALID_INVITATION,
                "corrupted",
            ),
            (
                Role::Trainee,
                other_session,
                RefusalReason::WrongSession,
                close_code::WRONG_SESSION,
                "other",
            ),
            (
                Role::Observer,
                f.mint(Role::Trainee, None, 600),
                RefusalReason::WrongRole,
                close_code::WRONG_ROLE,
                "trainee",
            ),
        ];
        for (role, inv, reason, code, needle) in cases {
            let join =
                link::join_message("x", role, "lap-chole", Credential::Invitation(inv), SCENE);
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
            let m = link::read_frame(&mut recv, &mut FrameDecoder::default())
                .await
                .unwrap();
            let Some(Message::Refusal(r)) = m else {
                panic!("{m:?}")
            };
            assert_eq!(r.reason, reason);
            assert!(r.text.contains(needle), "{needle}: {}", r.text);
            match conn.closed().await {
                quinn::ConnectionError::ApplicationClosed(c) => {
                    assert_eq!(c.error_code, quinn::VarInt::from_u32(code))
                }
                e => panic!("{e}"),
            }
        }
        // the instructor token admits the instructor only
        let r = refused(
            f.join("t", Role::Trainee, Credential::Token("s3cret".into()))
                .await,
        );
        assert_eq!(r.reason, RefusalReason::WrongRole);
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn revoking_on_disk_removes_the_member_and_refuses_rejoining() {
    tokio::time::timeout(T, async {
        let f = start_with(|_| {});
        let inv = f.mint(Role::Trainee, None, 600);
        let keep = f.mint(Role::Observer, None, 600);
        let mut a = f
            .join("a", Role::Trainee, Credential::Invitation(inv.clone()))
            .await
            .unwrap();
        let _o = f
            .join("o", Role::Observer, Credential::Invitation(keep))
            .await
            .unwrap();
        // what `cosurg-server revoke INVITATION` does, while the coordinator runs
        f.state.revoke(&inv).unwrap();
        let r = loop {
            match a.next_control().await {
                Ok(Some(Message::Refusal(r))) => break r,
                Ok(Some(_)) => continue,
                other => panic!("expected a refusal, got {other:?}"),
            }
        };
        assert_eq!(r.reason, RefusalReason::InvitationRevoked);
        let r = refused(
            f.join("a", Role::Trainee, Credential::Invitation(inv))
                .await,
        );
        assert_eq!(r.reason, RefusalReason::InvitationRevoked);
        let names: Vec<String> = f
            .handle
            .status()
            .sites
            .into_iter()
            .map(|s| s.name)
            .collect();
        assert_eq!(names, vec!["o".to_string()]);
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn failed_joins_are_rate_limited_per_address() {
    tokio::time::timeout(T, async {
        let f = start_with(|c| {
            c.rate_limit = RateLimitConfig {
                burst: 2,
                refill: Duration::from_secs(60),
                base_block: Duration::from_millis(800),
                ..RateLimitConfig::default()
            }
        });
        let wrong = || Credential::Token("guess".into());
        for _ in 0..3 {
            let r = refused(f.join("p", Role::Instructor, wrong()).await);
            assert_eq!(r.reason, RefusalReason::WrongToken);
        }
        // blocked now, even with the right token
        let r = refused(
            f.join("p", Role::Instructor, Credential::Token("s3cret".into()))
                .await,
        );
        // the attempt during the block doubled it
        let RefusalReason::RateLimited { retry_after_ms } = r.reason else {
            panic!("{r:?}")
        };
        assert!((800..=1600).contains(&retry_after_ms), "{r:?}");
        assert!(r.text.contains("rate limited"), "{}", r.text);
        tokio::time::sleep(Duration::from_millis(retry_after_ms + 100)).await;
        f.join("p", Role::Instructor, Credential::Token("s3cret".into()))
            .await
            .unwrap();
        // a refusal a legitimate site meets (name taken) costs nothing
        let inv = f.mint(Role::Trainee, None, 600);
        let _a = f
            .join("a", Role::Trainee, Credential::Invitation(inv.clone()))
            .await
            .unwrap();
        for _ in 0..3 {
            let r = refused(
                f.join("a", Role::Trainee, Credential::Invitation(inv.clone()))
                    .await,
            );
            assert_eq!(r.reason, RefusalReason::NameTaken);
        }
    })
    .await
    .unwrap();
}

#[tokio::test]
async fn a_peer_of_the_previous_protocol_version_is_told_so() {
    tokio::time::timeout(T, async {
        let f = start_with(|_| {});
        let conn = f
            .endpoint
            .connect(f.addr, "localhost")
            .unwrap()
            .await
            .unwrap();
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        // a version-1 Join frame: wire tag 1, then anything
        let body = [1u8, 0, 1, 2, 3];
        let mut frame = (body.len() as u32).to_be_bytes().to_vec();
        frame.extend_from_slice(&body);
        send.write_all(&frame).await.unwrap();
        let m = link::read_frame(&mut recv, &mut FrameDecoder::default())
            .await
            .unwrap();
        let Some(Message::Refusal(r)) = m else {
            panic!("{m:?}")
        };
        assert_eq!(
            r.reason,
            RefusalReason::WrongVersion {
                server: PROTOCOL_VERSION,
                client: 1
            }
        );
        match conn.closed().await {
            quinn::ConnectionError::ApplicationClosed(c) => {
                assert_eq!(
                    c.error_code,
                    quinn::VarInt::from_u32(close_code::WRONG_VERSION)
                );
                assert!(String::from_utf8_lossy(&c.reason).contains("protocol version 1"));
            }
            e => panic!("{e}"),
        }
    })
    .await
    .unwrap();
}
