//! The coordinator's session recording (`cosurg-debrief` format, site `coordinator`,
//! role `coordinator`): what the coordinator relays, so that a debrief works even when a
//! site dies or leaves early.
//!
//! It holds
//! * every site's **tool poses** as they arrive (a site sends its driven tool every
//!   16 ms of simulated time, about 62.5 Hz; nothing is decimated). A tool is declared
//!   when its first pose arrives, driven by the sending site, named `#N` after its index
//!   `N` in the scene with an empty kind: the coordinator does not load the scene, and a
//!   reader of a session directory names it after tool `N` of a site's recording
//!   (`debrief::Session::open`). Poses carry no forces or grasp state (zero in the
//!   samples), so only path measures (time, path length, economy, idle time, depth, LDLJ,
//!   DTW) are meaningful from this recording. A pose older than the newest recorded one of
//!   the same tool (datagrams may be reordered) is skipped, so every track is in time
//!   order;
//! * **events**: joins (name and role), leaves (reason), region grants (`claim`) and
//!   releases, resets (`reset`, new epoch), teaching (`teaching-start` when a trajectory is
//!   relayed or a playback starts, `teaching-stop` when it stops), other instructor
//!   commands (`other:kick-site`);
//! * **keyframe metadata** (`other:keyframe` events: region, id, owner, epoch, simulated
//!   time, node count and bytes), not the payloads: they are the sites' business (their
//!   own recordings hold the surfaces), and relayed keyframes of the built-in scene run to
//!   tens of kB each (see `docs/debrief.md` for the measured cost).
//!
//! Step records are numbered by arrival (the `step` field is a sequence number, not a
//! simulation step: the coordinator does not step) and timed by the pose's simulated
//! time; events are timed by the newest simulated time heard from any site.
//!
//! Errors never stop the relay: the first failure is logged and the recording stops.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use debrief::{
    Event, EventKind, RecordError, Recorder, RecorderSettings, SessionHeader, ToolId, ToolState,
};
use proto::{Command, Message, RegionKeyframe, SiteId};
use tracing::{info, warn};

/// Site name and role written in the coordinator's recording header.
pub const COORDINATOR_SITE: &str = "coordinator";

/// File name of a session's recording in the coordinator's record directory:
/// `<session>.cosrec`, the session name with anything but ASCII letters, digits, `-`
/// and `_` replaced by `_`.
pub fn recording_path(dir: &Path, session: &str) -> PathBuf {
    let mut name: String = session
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if name.is_empty() {
        name = "session".into();
    }
    dir.join(format!("{name}.{}", debrief::EXTENSION))
}

/// What a coordinator recording holds so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecordingCounts {
    pub poses: u64,
    pub events: u64,
    pub keyframes: u64,
    /// Bytes of the relayed keyframes' payloads (what recording them in full would cost).
    pub keyframe_bytes: u64,
}

/// The coordinator's recording of one session.
pub struct CoordinatorRecording {
    rec: Option<Recorder>,
    path: PathBuf,
    names: HashMap<SiteId, String>,
    /// The instructor's name, once it joined (commands and teaching come from it only).
    instructor: Option<String>,
    tools: HashMap<(SiteId, u8), (ToolId, f64)>,
    /// Newest simulated time heard from any site (s).
    sim_time: f64,
    seq: u64,
    trajectories: BTreeSet<u32>,
    counts: RecordingCounts,
}

impl CoordinatorRecording {
    /// Creates `dir/<session>.cosrec` (and `dir`). `scene_hash`: the required scene, if
    /// the coordinator was given one.
    pub fn create(
        dir: &Path,
        session: &str,
        scene_hash: Option<&str>,
    ) -> Result<Self, RecordError> {
        std::fs::create_dir_all(dir)?;
        let path = recording_path(dir, session);
        let header = SessionHeader {
            session: session.into(),
            site: COORDINATOR_SITE.into(),
            role: COORDINATOR_SITE.into(),
            scene: scene_hash.map_or("(scene fixed by the first site)".into(), |h| {
                format!("sha256 {h}")
            }),
            // The coordinator does not step: every arriving pose is one step record.
            sim_rate_hz: 0.0,
            sample_every: 1,
            started_unix_ms: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_millis() as u64),
            damage_strain_threshold: None,
            software: format!("cosurg-server {}", env!("CARGO_PKG_VERSION")),
        };
        let rec = Recorder::create(&path, header, RecorderSettings::default())?;
        info!(path = %path.display(), "recording the session");
        Ok(CoordinatorRecording {
            rec: Some(rec),
            path,
            names: HashMap::new(),
            instructor: None,
            tools: HashMap::new(),
            sim_time: 0.0,
            seq: 0,
            trajectories: BTreeSet::new(),
            counts: RecordingCounts::default(),
        })
    }

    /// Path of the recording file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What was recorded so far.
    pub fn counts(&self) -> RecordingCounts {
        self.counts
    }

    fn name(&self, site: SiteId) -> String {
        self.names
            .get(&site)
            .cloned()
            .unwrap_or_else(|| format!("site-{site}"))
    }

    /// Runs `f` on the recorder; the first error stops the recording.
    fn with(&mut self, f: impl FnOnce(&mut Recorder) -> Result<(), RecordError>) {
        if let Some(rec) = self.rec.as_mut()
            && let Err(e) = f(rec)
        {
            warn!(path = %self.path.display(), error = %e, "coordinator recording failed; stopped");
            self.rec = None;
        }
    }

    fn event(&mut self, site: String, kind: EventKind, detail: String) {
        let event = Event {
            step: self.seq,
            time: self.sim_time,
            site,
            tool: None,
            kind,
            detail,
        };
        self.counts.events += 1;
        self.with(|r| r.event(event));
    }

    /// A control message the coordinator sends (joins, leaves, grants, releases,
    /// commands, teaching), whoever it goes to.
    pub fn on_control(&mut self, msg: &Message) {
        match msg {
            Message::SiteJoined(e) => {
                self.names.insert(e.site, e.name.clone());
                if e.role == proto::Role::Instructor {
                    self.instructor = Some(e.name.clone());
                }
                self.event(e.name.clone(), EventKind::Join, format!("{}", e.role));
            }
            Message::Leave(l) => {
                let name = self.name(l.site);
                self.event(name, EventKind::Leave, l.reason.clone());
            }
            Message::OwnershipGrant(g) => {
                let detail = match g.previous {
                    Some(p) => format!("region {} (taken from {})", g.region, self.name(p)),
                    None => format!("region {}", g.region),
                };
                self.event(self.name(g.site), EventKind::Claim, detail);
            }
            Message::OwnershipRelease(r) => {
                let name = self.name(r.site);
                self.event(name, EventKind::Release, format!("region {}", r.region));
            }
            // Re-sent to every late joiner: record each trajectory once.
            Message::Teaching(t) if self.trajectories.insert(t.id) => {
                let detail = format!(
                    "trajectory {} of tool {}: {} samples",
                    t.id,
                    t.tool,
                    t.samples.len()
                );
                self.event(self.instructor(), EventKind::TeachingStart, detail);
            }
            Message::Command(c) => {
                let (kind, detail) = match c {
                    Command::ResetScene { epoch, sim_time_s } => (
                        EventKind::Reset,
                        format!("epoch {epoch} at {sim_time_s:.3} s"),
                    ),
                    Command::StartPlayback {
                        trajectory,
                        start_sim_time_s,
                    } => (
                        EventKind::TeachingStart,
                        format!("playback of trajectory {trajectory} from {start_sim_time_s:.3} s"),
                    ),
                    Command::StopPlayback { trajectory } => (
                        EventKind::TeachingStop,
                        format!("playback of trajectory {trajectory} stopped"),
                    ),
                    Command::KickSite { site, reason } => (
                        EventKind::Other("kick-site".into()),
                        format!("{}: {reason}", self.name(*site)),
                    ),
                };
                self.event(self.instructor(), kind, detail);
            }
            _ => {}
        }
    }

    /// The instructor's name (commands and teaching come from the instructor only).
    fn instructor(&self) -> String {
        self.instructor
            .clone()
            .unwrap_or_else(|| "instructor".into())
    }

    /// A datagram the coordinator relays (tool poses, simulation clocks).
    pub fn on_datagram(&mut self, msg: &Message) {
        match msg {
            Message::SimTime(s) if s.sim_time_s.is_finite() => {
                self.sim_time = self.sim_time.max(s.sim_time_s);
            }
            Message::ToolPose(p) if p.sim_time_s.is_finite() => {
                self.sim_time = self.sim_time.max(p.sim_time_s);
                let key = (p.site, p.tool);
                let id = match self.tools.get(&key) {
                    Some(&(_, last)) if p.sim_time_s <= last => return,
                    Some(&(id, _)) => id,
                    None => {
                        let site = self.name(p.site);
                        let name = format!("#{}", p.tool);
                        let mut declared = None;
                        self.with(|r| {
                            declared = Some(r.declare_tool(&site, &name, "")?);
                            Ok(())
                        });
                        match declared {
                            Some(id) => id,
                            None => return,
                        }
                    }
                };
                self.tools.insert(key, (id, p.sim_time_s));
                self.seq += 1;
                let state = ToolState {
                    position: p.position.map(f64::from),
                    orientation: p.orientation.map(f64::from),
                    jaw: f64::from(p.jaw_rad),
                    ..ToolState::default()
                };
                let (step, time) = (self.seq, p.sim_time_s);
                self.counts.poses += 1;
                self.with(|r| r.tool_sample(step, time, id, &state));
            }
            _ => {}
        }
    }

    /// A keyframe accepted for relaying (`bytes`: its encoded size): metadata only.
    pub fn on_keyframe(&mut self, kf: &RegionKeyframe, bytes: usize) {
        self.counts.keyframes += 1;
        self.counts.keyframe_bytes += bytes as u64;
        let detail = format!(
            "region {} id {} epoch {} at {:.3} s: {} nodes, {} bytes",
            kf.region,
            kf.keyframe_id,
            kf.epoch,
            kf.sim_time,
            kf.nodes.ids.len(),
            bytes
        );
        let owner = self.name(kf.owner);
        self.event(owner, EventKind::Other("keyframe".into()), detail);
    }

    /// Flushes and closes the file.
    pub fn finish(&mut self) {
        if let Some(rec) = self.rec.take() {
            match rec.finish() {
                Ok(_) => info!(
                    path = %self.path.display(),
                    poses = self.counts.poses,
                    events = self.counts.events,
                    keyframes = self.counts.keyframes,
                    keyframe_bytes = self.counts.keyframe_bytes,
                    "coordinator recording finished"
                ),
                Err(e) => {
                    warn!(path = %self.path.display(), error = %e, "coordinator recording not finished")
                }
            }
        }
    }
}

impl Drop for CoordinatorRecording {
    fn drop(&mut self) {
        self.finish();
    }
}

#[cfg(test)]
mod tests;
