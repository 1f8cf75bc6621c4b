//! Recording a running simulation with [`debrief::Recorder`]: the glue a site loop calls
//! after each step ([`SimRecorder::after_step`]), and [`record_scripted`], which steps a
//! scene with its scripted tools the way `cosurg run` does and records it (used by the
//! debrief tests and the `record_scripted` example).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use debrief::{
    Event, EventKind, Recorder, RecorderSettings, SessionHeader, SurfaceId, ToolId, ToolState,
};
use nalgebra::Matrix3;
use sim_core::{Interaction, SimOptions, Simulation, Tool, ToolContact};

use crate::scene_arg::load_scene;

/// Default strain above which tissue counts as damaged (largest principal Green strain).
/// A comparison threshold between trainees, not a validated injury criterion.
pub const DAMAGE_STRAIN: f64 = 0.2;

/// The driving site declared for tools other sites drive ([`SimRecorder::create_with_local`]).
pub const REMOTE_SITE: &str = "remote";

/// A tool's recorded state: pose, jaw, grasp, and its reaction split into contact
/// (the penetrating samples' forces) and grasp (the rest of the total).
pub fn tool_state(tool: &Tool, contact: Option<&ToolContact>) -> ToolState {
    let pose = tool.pose();
    let q = pose.rotation;
    let mut state = ToolState {
        position: pose.translation.vector.into(),
        orientation: [q.w, q.i, q.j, q.k],
        jaw: tool.jaw(),
        ..ToolState::default()
    };
    if let Some(c) = contact {
        let on_tissue: nalgebra::Vector3<f64> = c.contacts.iter().map(|p| p.force).sum();
        let contact_on_tool = -on_tissue;
        state.grasped = c.grasped as u32;
        state.contact_force = contact_on_tool.into();
        state.grasp_force = (c.force - contact_on_tool).into();
    }
    state
}

/// Volume (m³) of the leaf tets inside the organ whose largest principal Green strain
/// exceeds `threshold`. Rotation-invariant, so rigid motion counts as no damage.
pub fn damaged_volume(sim: &Simulation, threshold: f64) -> f64 {
    let lattice = sim.lattice();
    let x = sim.positions();
    let mut volume = 0.0;
    for &t in lattice.leaves() {
        if sim.leaf_material(t).is_none() {
            continue;
        }
        let n = lattice.tet_nodes(t);
        let r = n.map(|k| lattice.node_rest(k));
        let p = n.map(|k| x[k.0 as usize]);
        let dm = Matrix3::from_columns(&[r[1] - r[0], r[2] - r[0], r[3] - r[0]]);
        let ds = Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]);
        let Some(dm_inv) = dm.try_inverse() else {
            continue;
        };
        let f = ds * dm_inv;
        let e = 0.5 * (f.transpose() * f - Matrix3::identity());
        let largest = e.symmetric_eigenvalues().max();
        if largest > threshold {
            volume += lattice.tet_rest_volume(t);
        }
    }
    volume
}

/// Records one site's simulation: tools at up to the recorder's sample rate, damage every
/// `damage_interval_s`, surfaces at the recorder's surface interval, and grasp/release
/// events from the tools' grasp state.
pub struct SimRecorder {
    pub recorder: Recorder,
    site: String,
    tools: Vec<ToolId>,
    surfaces: Vec<SurfaceId>,
    /// Vertices each surface was declared with: a cut appends vertices (the original ones
    /// keep their indices), and the recording keeps the declared ones.
    surface_vertices: Vec<usize>,
    grasping: Vec<bool>,
    damage_strain: Option<f64>,
    damage_interval_s: f64,
    last_damage: Option<f64>,
}

impl SimRecorder {
    /// Declares `sim`'s tools (driven by `site`) and surfaces in a new recording at `path`.
    pub fn create(
        path: &Path,
        header: SessionHeader,
        settings: RecorderSettings,
        sim: &Simulation,
        interaction: &Interaction,
        damage_strain: Option<f64>,
    ) -> Result<Self> {
        Self::create_with_local(
            path,
            header,
            settings,
            sim,
            interaction,
            damage_strain,
            None,
        )
    }

    /// As [`SimRecorder::create`], for a site of a session: with `local` = `Some(i)`,
    /// only tool `i` is declared as driven by the recording site, the others by
    /// [`REMOTE_SITE`] (other sites drive them; their samples are what this site saw).
    pub fn create_with_local(
        path: &Path,
        mut header: SessionHeader,
        settings: RecorderSettings,
        sim: &Simulation,
        interaction: &Interaction,
        damage_strain: Option<f64>,
        local: Option<Option<usize>>,
    ) -> Result<Self> {
        header.damage_strain_threshold = damage_strain;
        header.sim_rate_hz = 1.0 / sim.options().dt;
        let site = header.site.clone();
        let mut recorder = Recorder::create(path, header, settings)
            .with_context(|| format!("creating {}", path.display()))?;
        let tools = interaction
            .tools
            .tools
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let driver = match local {
                    Some(l) if l != Some(i) => REMOTE_SITE,
                    _ => site.as_str(),
                };
                recorder.declare_tool(driver, &t.name, &format!("{:?}", t.kind).to_lowercase())
            })
            .collect::<Result<Vec<_>, _>>()?;
        let surfaces = sim
            .surfaces()
            .iter()
            .map(|s| {
                let rest: Vec<[f64; 3]> = s.rest.vertices.iter().map(|v| (*v).into()).collect();
                recorder.declare_surface(&s.name, &rest, &s.rest.triangles)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let surface_vertices = sim
            .surfaces()
            .iter()
            .map(|s| s.rest.vertices.len())
            .collect();
        Ok(SimRecorder {
            surface_vertices,
            grasping: vec![false; tools.len()],
            recorder,
            site,
            tools,
            surfaces,
            damage_strain,
            damage_interval_s: 0.05,
            last_damage: None,
        })
    }

    /// Measures the damaged volume every `seconds` of simulated time (default 0.05 s).
    pub fn with_damage_interval(mut self, seconds: f64) -> Self {
        self.damage_interval_s = seconds;
        self
    }

    /// Records what the last step produced (call after `sim.step()`).
    pub fn after_step(&mut self, sim: &Simulation, interaction: &Interaction) -> Result<()> {
        let (step, time) = (sim.steps(), sim.time());
        let contacts = &interaction.state().tools;
        for (i, (tool, id)) in interaction.tools.tools.iter().zip(&self.tools).enumerate() {
            let state = tool_state(tool, contacts.get(i));
            let holding = state.grasped > 0;
            if holding != self.grasping[i] {
                self.grasping[i] = holding;
                self.recorder.event(Event {
                    step,
                    time,
                    site: self.site.clone(),
                    tool: Some(tool.name.clone()),
                    kind: if holding {
                        EventKind::Grasp
                    } else {
                        EventKind::GraspRelease
                    },
                    detail: format!("{} points", state.grasped),
                })?;
            }
            self.recorder.tool_sample(step, time, *id, &state)?;
        }
        if let Some(threshold) = self.damage_strain
            && self.recorder.wants_step(step)
            && self
                .last_damage
                .is_none_or(|t| time - t >= self.damage_interval_s - 1e-9)
        {
            self.last_damage = Some(time);
            self.recorder
                .damage(step, time, damaged_volume(sim, threshold))?;
        }
        for ((s, id), n) in sim
            .surfaces()
            .iter()
            .zip(&self.surfaces)
            .zip(&self.surface_vertices)
        {
            if self.recorder.wants_surface(*id, time) {
                let v: Vec<[f64; 3]> = s.deformed.iter().take(*n).map(|p| (*p).into()).collect();
                self.recorder.surface(step, time, *id, &v)?;
            }
        }
        Ok(())
    }

    /// Appends an event about this site.
    pub fn event(&mut self, kind: EventKind, detail: &str, sim: &Simulation) -> Result<()> {
        self.recorder.event(Event {
            step: sim.steps(),
            time: sim.time(),
            site: self.site.clone(),
            tool: None,
            kind,
            detail: detail.into(),
        })?;
        Ok(())
    }

    /// Flushes and closes the file; returns its size in bytes.
    pub fn finish(self) -> Result<u64> {
        let bytes = self.recorder.bytes_written();
        self.recorder.finish()?;
        Ok(bytes)
    }
}

/// What [`record_scripted`] measured.
#[derive(Clone, Copy, Debug)]
pub struct RecordedRun {
    pub steps: u64,
    pub bytes: u64,
    /// Step wall time without and with recording, p50 (ms): `step_ms` is the simulation
    /// alone, `record_ms` the recorder's share.
    pub step_ms_p50: f64,
    pub record_ms_p50: f64,
    /// Mean of the recorder's share (ms): damage is measured only every 0.05 s.
    pub record_ms_mean: f64,
}

/// Steps `scene` (None: the built-in cholecystectomy) for `seconds` with its scripted
/// tools and records it as site `site` at `path`. `tool_delay_s` delays the scripts
/// (the tools hold their first pose meanwhile), which makes a second, time-shifted
/// performance of the same acts.
pub fn record_scripted(
    scene: Option<&str>,
    seconds: f64,
    site: &str,
    role: &str,
    tool_delay_s: f64,
    path: &Path,
    settings: RecorderSettings,
) -> Result<RecordedRun> {
    let scene = load_scene(scene)?;
    let name = format!(
        "{} (sha256 {})",
        scene.scene.title.as_deref().unwrap_or(&scene.file),
        &scene.hash
    );
    let options = SimOptions::from_scene(&scene.scene);
    let mut sim = Simulation::new(scene, options)?;
    let mut interaction = Interaction::new(&sim);
    let header = SessionHeader {
        session: "scripted".into(),
        site: site.into(),
        role: role.into(),
        scene: name,
        sim_rate_hz: 0.0,
        sample_every: 0,
        started_unix_ms: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64),
        damage_strain_threshold: None,
        software: format!("cosurg {}", env!("CARGO_PKG_VERSION")),
    };
    let mut rec = SimRecorder::create(
        path,
        header,
        settings,
        &sim,
        &interaction,
        Some(DAMAGE_STRAIN),
    )?;
    rec.event(EventKind::Join, "scripted run", &sim)?;
    let steps = (seconds / sim.options().dt).round() as u64;
    let mut step_ms = Vec::with_capacity(steps as usize);
    let mut record_ms = Vec::with_capacity(steps as usize);
    for _ in 0..steps {
        let t0 = Instant::now();
        let t = (sim.time() - tool_delay_s).max(0.0);
        let inputs = interaction.scripted_inputs(&sim, t);
        interaction.before_step(&mut sim, &inputs)?;
        sim.step()?;
        let t1 = Instant::now();
        rec.after_step(&sim, &interaction)?;
        step_ms.push((t1 - t0).as_secs_f64() * 1e3);
        record_ms.push(t1.elapsed().as_secs_f64() * 1e3);
    }
    rec.event(EventKind::Leave, "end of script", &sim)?;
    let bytes = rec.finish()?;
    Ok(RecordedRun {
        steps,
        bytes,
        step_ms_p50: crate::stats::percentile(&step_ms, 50.0),
        record_ms_p50: crate::stats::percentile(&record_ms, 50.0),
        record_ms_mean: record_ms.iter().sum::<f64>() / record_ms.len().max(1) as f64,
    })
}
