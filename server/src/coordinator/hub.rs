//! Many sessions on one endpoint. The hub owns what is shared by all sessions of a
//! coordinator (the endpoint's accept loop, admission: rate limiting and revocations, the
//! operator's admin token) and routes every connection, at its first message, to the one
//! session it names.
//!
//! **Isolation.** Each session is a [`Shared`] of its own: its own lock, site table,
//! counters, housekeeping and status tasks. A connection belongs to exactly one session for
//! its whole life and every relay loop only ever looks at its own session's peers, so
//! nothing of one session can reach another.
//!
//! **Fairness.** No lock is shared between sessions on the relay path (only the session
//! table's read lock, taken once per connection at join). Every connection has its own tasks
//! (control reader/writer, datagram loop, keyframe streams), which tokio schedules with a
//! per-task budget, and every queue towards a site is bounded (control queue
//! [`CONTROL_QUEUE`], quinn's datagram send buffer, the keyframe-stream scheduler's
//! per-region limit), so a busy session costs CPU but cannot stall or grow memory for the
//! others.

use std::collections::BTreeMap;
use std::sync::RwLock;

use proto::{AdminAction, AdminRequest, Credential, Refusal, RefusalReason, SessionInfo};
use subtle::ConstantTimeEq;
use tokio::task::AbortHandle;

use super::*;
use crate::sessions::{SessionSpec, SessionsFile, check_spec};

/// What all sessions of a coordinator share.
pub(super) struct Hub {
    pub(super) clock: WallClock,
    sessions: RwLock<BTreeMap<String, Arc<Shared>>>,
    /// Connection-level counters (handshakes, refusals before a session was found).
    pub(super) counters: Counters,
    pub(super) admission: Admission,
    pub(super) join_timeout: Duration,
    pub(super) max_frame: usize,
    admin_token: Option<String>,
    max_sessions: usize,
    /// Invitation key and heartbeat interval of sessions created at run time.
    template: SessionConfig,
    status_interval: Option<Duration>,
    /// Where sessions created at run time are persisted.
    state_dir: Option<PathBuf>,
    /// Where every session's recording goes (`--record`); `None`: not recorded.
    record_dir: Option<PathBuf>,
    /// Every site's relay budget, in every session.
    relay_budget: RelayBudget,
    tasks: Mutex<Vec<AbortHandle>>,
}

impl Hub {
    pub(super) fn new(config: &CoordinatorConfig) -> Self {
        Self {
            clock: WallClock::dilated(config.time_scale),
            sessions: RwLock::new(BTreeMap::new()),
            counters: Counters::default(),
            admission: Admission::new(
                config.rate_limit,
                config.state_dir.clone().map(crate::state::StateDir::new),
            ),
            join_timeout: config.join_timeout,
            max_frame: config.max_frame,
            admin_token: config.admin_token.clone(),
            max_sessions: config.max_sessions,
            template: config.session.clone(),
            status_interval: config.status_interval,
            state_dir: config.state_dir.clone(),
            record_dir: config.record_dir.clone(),
            relay_budget: config.relay_budget,
            tasks: Mutex::new(Vec::new()),
        }
    }

    /// The session named `name`.
    pub(super) fn session(&self, name: &str) -> Option<Arc<Shared>> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(name)
            .cloned()
    }

    /// All sessions, by name.
    pub(super) fn all(&self) -> Vec<Arc<Shared>> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .values()
            .cloned()
            .collect()
    }

    /// Keep a task to abort at shutdown.
    pub(super) fn keep(&self, h: AbortHandle) {
        let mut t = self.tasks.lock().unwrap_or_else(|p| p.into_inner());
        t.retain(|h| !h.is_finished());
        t.push(h);
    }

    pub(super) fn abort_all(&self) {
        for h in self
            .tasks
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .drain(..)
        {
            h.abort();
        }
    }

    /// Host a session and start its housekeeping and status tasks. Must run within the
    /// tokio runtime. Refused when the name is taken or the coordinator is full.
    /// Every session of the hub runs at the hub clock's time scale, whatever `config`
    /// says: sites at another scale are refused.
    pub(super) fn add_session(&self, mut config: SessionConfig) -> Result<Arc<Shared>, Refusal> {
        config.time_scale_milli = self.clock.time_scale().milli();
        let name = config.name.clone();
        let heartbeat_us = config.heartbeat_interval_us.max(10_000);
        let recording = self.record_dir.as_ref().and_then(|dir| {
            CoordinatorRecording::create(dir, &name, config.scene_hash.as_deref())
                .inspect_err(|e| {
                    warn!(session = %name, dir = %dir.display(), "not recorded: {e}");
                })
                .ok()
        });
        let mut session = Session::new(config);
        session.set_relay_budget(self.relay_budget);
        let shared = Arc::new(Shared {
            name: name.clone(),
            clock: self.clock,
            state: Mutex::new(State {
                session,
                peers: HashMap::new(),
                recording,
            }),
            counters: Counters::default(),
            max_frame: self.max_frame,
        });
        {
            let mut map = self.sessions.write().unwrap_or_else(|p| p.into_inner());
            if map.contains_key(&name) {
                return Err(Refusal {
                    reason: RefusalReason::NameTaken,
                    text: format!("a session named {name:?} already exists"),
                });
            }
            if map.len() >= self.max_sessions {
                return Err(Refusal {
                    reason: RefusalReason::Full,
                    text: format!(
                        "this coordinator hosts its maximum of {} sessions",
                        self.max_sessions
                    ),
                });
            }
            map.insert(name.clone(), shared.clone());
        }
        // The revocation list already loaded applies to the new session too.
        if let Some(revoked) = self.admission.current_revocations() {
            let mut st = shared.lock();
            let st = &mut *st;
            let actions = st.session.set_revoked(revoked);
            shared.execute(st, actions);
        }
        self.keep(
            tokio::spawn(housekeeping(
                shared.clone(),
                Duration::from_micros(heartbeat_us),
            ))
            .abort_handle(),
        );
        if let Some(iv) = self.status_interval.filter(|d| !d.is_zero()) {
            self.keep(tokio::spawn(status_loop(shared.clone(), iv)).abort_handle());
        }
        info!(session = %name, "session hosted");
        Ok(shared)
    }

    /// Load the state directory's revocation list if it changed and apply it to every
    /// session: members admitted by a revoked invitation are removed.
    pub(super) fn apply_revocations(&self) {
        let Some(revoked) = self.admission.poll_revocations() else {
            return;
        };
        for shared in self.all() {
            let mut st = shared.lock();
            let st = &mut *st;
            let actions = st.session.set_revoked(revoked.clone());
            for a in &actions {
                if let Action::Close { site, .. } = a {
                    warn!(session = %shared.name, site, "site removed: its invitation was revoked");
                }
            }
            shared.execute(st, actions);
        }
    }

    /// `AdminAction::CreateSession`: check the operator's admin token, host the session,
    /// persist it in the state directory.
    fn create_session(&self, req: &AdminRequest) -> Result<SessionInfo, Refusal> {
        let refuse = |reason, text: String| Refusal { reason, text };
        if req.protocol_version != proto::PROTOCOL_VERSION {
            return Err(refuse(
                RefusalReason::WrongVersion {
                    server: proto::PROTOCOL_VERSION,
                    client: req.protocol_version,
                },
                format!(
                    "protocol version {} not supported; the coordinator speaks {}",
                    req.protocol_version,
                    proto::PROTOCOL_VERSION
                ),
            ));
        }
        let AdminAction::CreateSession {
            instructor_token,
            scene_hash,
            max_sites,
        } = &req.action
        else {
            return Err(refuse(
                RefusalReason::Malformed,
                "not a CreateSession".into(),
            ));
        };
        let Some(admin) = &self.admin_token else {
            return Err(refuse(
                RefusalReason::WrongToken,
                "this coordinator does not create sessions at run time (started without --admin-token)"
                    .into(),
            ));
        };
        let ok = match &req.credential {
            Credential::Token(t) => bool::from(t.as_bytes().ct_eq(admin.as_bytes())),
            Credential::Invitation(_) => false,
        };
        if !ok {
            return Err(refuse(
                RefusalReason::WrongToken,
                "creating a session needs the coordinator's admin token".into(),
            ));
        }
        let spec = SessionSpec {
            name: req.session.clone(),
            token: instructor_token.clone(),
            scene_hash: scene_hash.as_ref().map(|h| h.to_ascii_lowercase()),
            max_sites: if *max_sites == 0 {
                self.template.max_sites
            } else {
                *max_sites
            },
        };
        check_spec(&spec).map_err(|t| refuse(RefusalReason::Malformed, t))?;
        let config = session_config(&spec, &self.template);
        let info = SessionInfo {
            name: spec.name.clone(),
            scene_hash: spec.scene_hash.clone().unwrap_or_default(),
            max_sites: spec.max_sites,
            protocol_version: proto::PROTOCOL_VERSION,
            heartbeat_interval_us: config.heartbeat_interval_us,
        };
        self.add_session(config)?;
        if let Some(dir) = &self.state_dir
            && let Err(e) = SessionsFile::persist(dir, [spec])
        {
            // Served now, but would not survive a restart: say so loudly.
            warn!(session = %info.name, error = %e, "session created but not persisted");
        }
        Ok(info)
    }
}

/// The configuration of a hosted session from its spec; invitation key and heartbeat
/// interval from `template` (the coordinator's first session).
pub fn session_config(spec: &SessionSpec, template: &SessionConfig) -> SessionConfig {
    let mut c = SessionConfig::new(spec.name.clone(), spec.token.clone());
    c.invite_key = template.invite_key.clone();
    c.heartbeat_interval_us = template.heartbeat_interval_us;
    c.scene_hash = spec.scene_hash.as_ref().map(|h| h.to_ascii_lowercase());
    c.max_sites = spec.max_sites;
    c
}

pub(super) async fn accept_loop(hub: Arc<Hub>, endpoint: Endpoint) {
    let mut conns = JoinSet::new();
    while let Some(incoming) = endpoint.accept().await {
        inc(&hub.counters.connections);
        conns.spawn(handle_incoming(hub.clone(), incoming));
        while conns.try_join_next().is_some() {}
    }
}

/// Periodic: the revocation list, for all sessions.
pub(super) async fn revocation_loop(hub: Arc<Hub>, interval: Duration) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        hub.apply_revocations();
    }
}

/// Answer an administrative connection (see [`crate::admin`]): one request, one answer,
/// closed. It never becomes a site.
pub(super) async fn handle_admin(
    hub: &Hub,
    conn: &Connection,
    send: &mut SendStream,
    remote: SocketAddr,
    req: AdminRequest,
) {
    let now = hub.clock.now_us();
    let answer = match &req.action {
        AdminAction::MintInvitation { .. } => match hub.session(&req.session) {
            Some(shared) => {
                let a = crate::admission::answer_admin(&shared.lock().session, &req, now);
                if let Ok(issued) = &a {
                    info!(%remote, session = %req.session, role = %issued.role, site = ?issued.site, nonce = %issued.nonce_hex, expires_unix_s = issued.expires_unix_s, "invitation minted by the instructor");
                } else {
                    inc(&shared.counters.refused);
                }
                a.map(Message::Invitation)
            }
            None => {
                inc(&hub.counters.refused);
                Err(no_such_session(&req.session))
            }
        },
        AdminAction::CreateSession { .. } => {
            let a = hub.create_session(&req);
            match &a {
                Ok(info) => info!(%remote, session = %info.name, "session created by the operator"),
                Err(_) => inc(&hub.counters.refused),
            }
            a.map(Message::SessionCreated)
        }
    };
    match answer {
        Ok(msg) => {
            let frame = proto::encode_frame(&msg);
            if send.write_all(&frame).await.is_ok() && send.finish().is_ok() {
                let _ = tokio::time::timeout(Duration::from_secs(2), send.stopped()).await;
            }
            conn.close(VarInt::from_u32(close_code::NORMAL), b"done");
        }
        Err(refusal) => {
            info!(%remote, reason = ?refusal.reason, text = %refusal.text, "admin request refused");
            hub.admission.record(remote.ip(), &refusal, now);
            refuse(conn, Some(send), refusal).await;
        }
    }
}

/// The refusal for a session this coordinator does not host.
pub(super) fn no_such_session(name: &str) -> Refusal {
    Refusal {
        reason: RefusalReason::WrongSession,
        text: format!("no session named {name:?} here"),
    }
}

impl crate::metrics::Source for Hub {
    fn sample(&self) -> crate::metrics::Sample {
        crate::metrics::Sample {
            coordinator: self.counters.snapshot(),
            sessions: self
                .all()
                .iter()
                .map(|s| crate::metrics::SessionSample {
                    name: s.name.clone(),
                    sites: s.lock().session.sites().count() as u64,
                    stats: s.counters.snapshot(),
                })
                .collect(),
        }
    }
}
