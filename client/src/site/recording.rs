//! The site's recordings: surfaces (sim-core's `.surf` format) and the session
//! recording (`cosurg-debrief`'s `.cosrec`).

use std::path::Path;

use std::collections::{BTreeMap, BTreeSet};

use anyhow::{Context, Result};
use debrief::{EventKind, RecorderSettings, SessionHeader};
use proto::{Epoch, RegionId, SiteId};
use sim_core::Simulation;
use sim_core::sync;

use super::tools::Tools;
use crate::record::{DAMAGE_STRAIN, SimRecorder};
use crate::session::SiteSession;

/// Surface recordings at fixed simulated-time marks (sim-core's `.surf` format).
pub struct Recorder(sync::SurfaceRecorder);

impl Recorder {
    pub fn new(sim: &Simulation, interval: f64) -> Self {
        Recorder(sync::SurfaceRecorder::new(sim, interval))
    }
    pub fn record(&mut self, sim: &Simulation) {
        self.0.record(sim);
    }
    pub fn write(&self, path: &Path) -> Result<()> {
        let file =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        self.0
            .recording()
            .write_to(std::io::BufWriter::new(file))
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// File name of a site's session recording inside its output folder.
pub fn session_recording_path(out: &Path, site: &str) -> std::path::PathBuf {
    out.join(format!("{site}.{}", debrief::EXTENSION))
}

/// Simulated time between damage measures in a site's recording (s): coarser than
/// [`crate::record::SimRecorder`]'s 0.05 s, which costs a few ms per measure in debug
/// builds and would stretch steps of a real-time site.
pub const SITE_DAMAGE_INTERVAL: f64 = 0.25;

/// A site's session recording (`cosurg-debrief` format): the simulation after every
/// step, and the session's events — other sites joining and leaving, regions claimed
/// and released (ours and others'), resets, teaching — found by comparing what the
/// session reports from one step to the next.
pub struct SessionRecording {
    rec: SimRecorder,
    path: std::path::PathBuf,
    /// Other sites by id, with their names (kept after they leave).
    others: BTreeMap<SiteId, String>,
    owned: BTreeSet<RegionId>,
    remote_owners: BTreeMap<RegionId, SiteId>,
    epoch: Epoch,
    /// The instructor's act being recorded for teaching.
    teaching: bool,
}

impl SessionRecording {
    /// Starts `<out>/<site>.cosrec` for a site whose local tool is `local`.
    pub fn create(
        out: &Path,
        site: &str,
        role: &str,
        session: &SiteSession,
        sim: &Simulation,
        tools: &Tools,
    ) -> Result<Self> {
        std::fs::create_dir_all(out)?;
        let path = session_recording_path(out, site);
        let scene = sim.scene();
        let header = SessionHeader {
            session: "session".into(),
            site: site.into(),
            role: role.into(),
            scene: format!(
                "{} (sha256 {})",
                scene.scene.title.as_deref().unwrap_or(&scene.file),
                scene.hash
            ),
            sim_rate_hz: 0.0,
            sample_every: 0,
            started_unix_ms: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_millis() as u64),
            damage_strain_threshold: None,
            software: format!("cosurg {}", env!("CARGO_PKG_VERSION")),
        };
        let rec = SimRecorder::create_with_local(
            &path,
            header,
            RecorderSettings::default(),
            sim,
            tools.interaction(),
            Some(DAMAGE_STRAIN),
            Some(tools.local_index()),
        )?
        .with_damage_interval(SITE_DAMAGE_INTERVAL);
        let mut me = SessionRecording {
            rec,
            path,
            others: BTreeMap::new(),
            owned: BTreeSet::new(),
            remote_owners: BTreeMap::new(),
            epoch: session.epoch(),
            teaching: false,
        };
        me.rec.event(
            EventKind::Join,
            &format!("{role}, epoch {}", session.epoch()),
            sim,
        )?;
        me.session_events(session, sim)?;
        Ok(me)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Records the step just taken and what changed in the session since the last call.
    pub fn after_step(
        &mut self,
        session: &SiteSession,
        sim: &Simulation,
        tools: &Tools,
    ) -> Result<()> {
        self.session_events(session, sim)?;
        self.rec.after_step(sim, tools.interaction())
    }

    /// A reset took effect (epoch `epoch`).
    pub fn reset(&mut self, epoch: Epoch, sim: &Simulation) -> Result<()> {
        self.epoch = epoch;
        self.rec
            .event(EventKind::Reset, &format!("epoch {epoch}"), sim)
    }

    /// Teaching: the instructor's act starts or ends being recorded (`active`), or a
    /// trainee is told to start or stop a playback.
    pub fn teaching(&mut self, active: bool, detail: &str, sim: &Simulation) -> Result<()> {
        if active == self.teaching {
            return Ok(());
        }
        self.teaching = active;
        let kind = if active {
            EventKind::TeachingStart
        } else {
            EventKind::TeachingStop
        };
        self.rec.event(kind, detail, sim)
    }

    /// An event of another kind (e.g. a trajectory received).
    pub fn other(&mut self, name: &str, detail: &str, sim: &Simulation) -> Result<()> {
        self.rec.event(EventKind::Other(name.into()), detail, sim)
    }

    fn session_events(&mut self, session: &SiteSession, sim: &Simulation) -> Result<()> {
        let sites = session.sites();
        let now: BTreeMap<SiteId, String> = sites
            .receivers()
            .map(|s| (s, sites.name(s).unwrap_or("?").to_string()))
            .collect();
        if now != self.others {
            for (id, name) in &now {
                if !self.others.contains_key(id) {
                    self.rec
                        .event(EventKind::Join, &format!("{name} (site {id:?})"), sim)?;
                }
            }
            for (id, name) in &self.others {
                if !now.contains_key(id) {
                    self.rec
                        .event(EventKind::Leave, &format!("{name} (site {id:?})"), sim)?;
                }
            }
            // Names of sites that left stay known for their regions' releases.
            self.others.extend(now.clone());
            self.others.retain(|id, _| now.contains_key(id));
        }
        let snap = session.snapshot();
        if snap.epoch != self.epoch {
            self.epoch = snap.epoch;
            self.rec
                .event(EventKind::Reset, &format!("epoch {}", snap.epoch), sim)?;
        }
        let owned: BTreeSet<RegionId> = snap.owned.iter().copied().collect();
        if owned != self.owned {
            for r in owned.difference(&self.owned) {
                self.rec
                    .event(EventKind::Claim, &format!("region {r:?} by us"), sim)?;
            }
            for r in self.owned.difference(&owned) {
                self.rec
                    .event(EventKind::Release, &format!("region {r:?} by us"), sim)?;
            }
            self.owned = owned;
        }
        let remote: BTreeMap<RegionId, SiteId> = snap.remote_owners.iter().copied().collect();
        if remote != self.remote_owners {
            let who = |s: &SiteId| {
                sites
                    .name(*s)
                    .map_or_else(|| format!("site {s:?}"), str::to_string)
            };
            for (r, s) in &remote {
                if self.remote_owners.get(r) != Some(s) {
                    self.rec.event(
                        EventKind::Claim,
                        &format!("region {r:?} by {}", who(s)),
                        sim,
                    )?;
                }
            }
            for (r, s) in &self.remote_owners {
                if !remote.contains_key(r) {
                    self.rec.event(
                        EventKind::Release,
                        &format!("region {r:?} by {}", who(s)),
                        sim,
                    )?;
                }
            }
            self.remote_owners = remote;
        }
        Ok(())
    }

    /// Records that the site ends, flushes and closes the file; returns its size (bytes).
    pub fn finish(mut self, sim: &Simulation) -> Result<u64> {
        self.rec.event(EventKind::Leave, "end of session", sim)?;
        self.rec.finish()
    }
}
