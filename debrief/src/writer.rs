//! [`Recorder`]: the append-only writer a site (or the coordinator) calls from its loop.
//!
//! The site only passes plain data:
//!
//! ```no_run
//! # use cosurg_debrief::*;
//! # fn demo() -> Result<(), RecordError> {
//! let header = SessionHeader {
//!     session: "s1".into(), site: "A".into(), role: "trainee".into(),
//!     scene: "cholecystectomy".into(), sim_rate_hz: 500.0, sample_every: 0,
//!     started_unix_ms: 0, damage_strain_threshold: Some(0.2), software: "cosurg".into(),
//! };
//! let mut rec = Recorder::create("A.cosrec", header, RecorderSettings::default())?;
//! let forceps = rec.declare_tool("A", "forceps", "forceps")?;
//! let liver = rec.declare_surface("liver", &[[0.0; 3]; 3], &[[0, 1, 2]])?;
//! for step in 0..1000u64 {
//!     let t = step as f64 * 0.002;
//!     if rec.wants_step(step) {
//!         rec.tool_sample(step, t, forceps, &ToolState::default())?;
//!         rec.damage(step, t, 0.0)?;
//!     }
//!     if rec.wants_surface(liver, t) {
//!         rec.surface(step, t, liver, &[[0.0; 3]; 3])?;
//!     }
//! }
//! rec.finish()?;
//! # Ok(()) }
//! ```

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use crate::format::{
    Event, FRAME_LEN, HEADER_LEN, MAGIC, MAX_RECORD_LEN, Record, SessionHeader, StepRecord,
    SurfaceDecl, SurfaceFrame, ToolDecl, ToolSample, ToolState, VERSION,
};

/// Errors of writing a recording.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("writing the recording: {0}")]
    Io(#[from] std::io::Error),
    #[error("encoding a record: {0}")]
    Encode(#[from] postcard::Error),
    #[error("record of {0} bytes exceeds the format's limit of {MAX_RECORD_LEN} bytes")]
    TooLarge(usize),
    #[error("surface {surface}: {got} vertices given, {expected} declared")]
    SurfaceSize {
        surface: u16,
        expected: usize,
        got: usize,
    },
    #[error("unknown {0} id {1} (declare it first)")]
    Unknown(&'static str, u16),
    #[error("too many {0} (at most 65536)")]
    TooMany(&'static str),
}

/// What to record and how often.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecorderSettings {
    /// Highest rate of step records (Hz): every `ceil(sim_rate / max_sample_rate_hz)`-th
    /// step is recorded.
    pub max_sample_rate_hz: f64,
    /// Simulated time between surface frames of one surface (s).
    pub surface_interval_s: f64,
    /// Displacement quantum of surface frames (m).
    pub surface_quantum_m: f64,
    /// Every this many frames of a surface is a key frame (displacement from rest);
    /// the others are deltas from the previous frame.
    pub keyframe_every: u32,
    /// Simulated time between flushes to the file (s): what a kill can lose at most.
    pub flush_interval_s: f64,
}

impl Default for RecorderSettings {
    fn default() -> Self {
        RecorderSettings {
            max_sample_rate_hz: 250.0,
            surface_interval_s: 0.5,
            surface_quantum_m: 1e-5,
            keyframe_every: 10,
            flush_interval_s: 0.5,
        }
    }
}

impl RecorderSettings {
    /// Steps per step record at simulation rate `sim_rate_hz`.
    pub fn sample_every(&self, sim_rate_hz: f64) -> u32 {
        if sim_rate_hz.is_nan()
            || sim_rate_hz <= 0.0
            || self.max_sample_rate_hz.is_nan()
            || self.max_sample_rate_hz <= 0.0
        {
            return 1;
        }
        ((sim_rate_hz / self.max_sample_rate_hz) - 1e-9)
            .ceil()
            .clamp(1.0, u32::MAX as f64) as u32
    }
}

/// Index of a declared tool.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ToolId(pub u16);

/// Index of a declared surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SurfaceId(pub u16);

struct SurfaceState {
    rest: Vec<[f32; 3]>,
    quantum: f64,
    last: Vec<i32>,
    frames: u32,
    last_time: Option<f64>,
}

/// Appends records to a recording; buffered, flushed every `flush_interval_s` of
/// simulated time, on events and on [`Recorder::finish`] (and, best effort, on drop).
pub struct Recorder<W: Write = BufWriter<File>> {
    out: Option<W>,
    settings: RecorderSettings,
    sample_every: u32,
    tools: usize,
    surfaces: Vec<SurfaceState>,
    pending: Option<StepRecord>,
    last_flush_time: f64,
    bytes: u64,
    records: u64,
}

impl Recorder<BufWriter<File>> {
    /// Creates (truncates) `path` and writes the file header and the session record.
    pub fn create(
        path: impl AsRef<Path>,
        header: SessionHeader,
        settings: RecorderSettings,
    ) -> Result<Self, RecordError> {
        let file = File::create(path.as_ref())?;
        Recorder::new(BufWriter::with_capacity(1 << 16, file), header, settings)
    }
}

impl<W: Write> Recorder<W> {
    /// Writes the file header and the session record into `out`. The header's
    /// `sample_every` is set from the settings and the simulation rate.
    pub fn new(
        mut out: W,
        mut header: SessionHeader,
        settings: RecorderSettings,
    ) -> Result<Self, RecordError> {
        let sample_every = settings.sample_every(header.sim_rate_hz);
        header.sample_every = sample_every;
        out.write_all(&file_header())?;
        let mut rec = Recorder {
            out: Some(out),
            settings,
            sample_every,
            tools: 0,
            surfaces: Vec::new(),
            pending: None,
            last_flush_time: 0.0,
            bytes: HEADER_LEN as u64,
            records: 0,
        };
        rec.write(&Record::Session(header))?;
        rec.flush()?;
        Ok(rec)
    }

    /// Steps per step record.
    pub fn sample_every(&self) -> u32 {
        self.sample_every
    }

    /// Whether step `step` is one that gets recorded (the others' samples are ignored).
    pub fn wants_step(&self, step: u64) -> bool {
        step.is_multiple_of(u64::from(self.sample_every))
    }

    /// Bytes written so far (header and records, including what is still buffered).
    pub fn bytes_written(&self) -> u64 {
        self.bytes
    }

    /// Records written so far.
    pub fn records_written(&self) -> u64 {
        self.records
    }

    /// Declares a tool driven by `site`.
    pub fn declare_tool(
        &mut self,
        site: &str,
        name: &str,
        kind: &str,
    ) -> Result<ToolId, RecordError> {
        let id = u16::try_from(self.tools).map_err(|_| RecordError::TooMany("tools"))?;
        self.write_pending()?;
        self.write(&Record::Tool(ToolDecl {
            id,
            site: site.into(),
            name: name.into(),
            kind: kind.into(),
        }))?;
        self.tools += 1;
        Ok(ToolId(id))
    }

    /// Declares a surface by its rest shape (m).
    pub fn declare_surface(
        &mut self,
        name: &str,
        rest: &[[f64; 3]],
        triangles: &[[u32; 3]],
    ) -> Result<SurfaceId, RecordError> {
        let id =
            u16::try_from(self.surfaces.len()).map_err(|_| RecordError::TooMany("surfaces"))?;
        let rest32: Vec<[f32; 3]> = rest.iter().map(|p| p.map(|c| c as f32)).collect();
        self.write_pending()?;
        self.write(&Record::Surface(SurfaceDecl {
            id,
            name: name.into(),
            rest: rest32.clone(),
            triangles: triangles.to_vec(),
            quantum_m: self.settings.surface_quantum_m,
        }))?;
        self.surfaces.push(SurfaceState {
            last: vec![0; rest32.len() * 3],
            rest: rest32,
            quantum: self.settings.surface_quantum_m,
            frames: 0,
            last_time: None,
        });
        Ok(SurfaceId(id))
    }

    /// Adds one tool's state to step `step` (simulated time `time`, s). Samples of a
    /// step that [`Recorder::wants_step`] rejects are ignored; a sample of a new step
    /// writes the previous step's record.
    pub fn tool_sample(
        &mut self,
        step: u64,
        time: f64,
        tool: ToolId,
        state: &ToolState,
    ) -> Result<(), RecordError> {
        if usize::from(tool.0) >= self.tools {
            return Err(RecordError::Unknown("tool", tool.0));
        }
        if !self.wants_step(step) {
            return Ok(());
        }
        self.pending_for(step, time)?
            .samples
            .push(ToolSample::quantise(tool.0, state));
        Ok(())
    }

    /// Sets the damaged tissue volume (m³) of step `step`.
    pub fn damage(&mut self, step: u64, time: f64, volume_m3: f64) -> Result<(), RecordError> {
        if !self.wants_step(step) {
            return Ok(());
        }
        self.pending_for(step, time)?.damaged_volume_m3 = Some(volume_m3 as f32);
        Ok(())
    }

    /// Appends an event and flushes (events are rare and matter most after a kill).
    pub fn event(&mut self, event: Event) -> Result<(), RecordError> {
        self.write_pending()?;
        self.write(&Record::Event(event))?;
        self.flush()
    }

    /// Whether a frame of `surface` at simulated time `time` is due.
    pub fn wants_surface(&self, surface: SurfaceId, time: f64) -> bool {
        self.surfaces
            .get(usize::from(surface.0))
            .is_some_and(|s| match s.last_time {
                None => true,
                Some(t) => time - t >= self.settings.surface_interval_s - 1e-9 || time < t,
            })
    }

    /// Records the deformed vertices (m) of `surface`, whether due or not.
    pub fn surface(
        &mut self,
        step: u64,
        time: f64,
        surface: SurfaceId,
        deformed: &[[f64; 3]],
    ) -> Result<(), RecordError> {
        let keyframe_every = self.settings.keyframe_every.max(1);
        let s = self
            .surfaces
            .get_mut(usize::from(surface.0))
            .ok_or(RecordError::Unknown("surface", surface.0))?;
        if deformed.len() != s.rest.len() {
            return Err(RecordError::SurfaceSize {
                surface: surface.0,
                expected: s.rest.len(),
                got: deformed.len(),
            });
        }
        let key = s.frames % keyframe_every == 0;
        let mut values = Vec::with_capacity(deformed.len() * 3);
        for (i, (p, r)) in deformed.iter().zip(&s.rest).enumerate() {
            for k in 0..3 {
                let q = ((p[k] - f64::from(r[k])) / s.quantum).round();
                let q = if q.is_nan() {
                    0
                } else {
                    q.clamp(i32::MIN as f64, i32::MAX as f64) as i32
                };
                let j = 3 * i + k;
                values.push(if key { q } else { q.wrapping_sub(s.last[j]) });
                s.last[j] = q;
            }
        }
        s.frames += 1;
        s.last_time = Some(time);
        self.write_pending()?;
        self.write(&Record::SurfaceFrame(SurfaceFrame {
            surface: surface.0,
            step,
            time,
            key,
            values,
        }))
    }

    /// Writes the buffered step and flushes the writer.
    pub fn flush(&mut self) -> Result<(), RecordError> {
        self.write_pending()?;
        if let Some(out) = self.out.as_mut() {
            out.flush()?;
        }
        Ok(())
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> Result<W, RecordError> {
        self.flush()?;
        Ok(self.out.take().expect("writer present until finish"))
    }

    fn pending_for(&mut self, step: u64, time: f64) -> Result<&mut StepRecord, RecordError> {
        if self.pending.as_ref().is_some_and(|p| p.step != step) {
            self.write_pending()?;
            // A jump back by more than the interval is a new time base (a reset):
            // flush then too. Small steps back are a coordinator interleaving sites.
            if (time - self.last_flush_time).abs() >= self.settings.flush_interval_s {
                self.last_flush_time = time;
                if let Some(out) = self.out.as_mut() {
                    out.flush()?;
                }
            }
        }
        Ok(self.pending.get_or_insert_with(|| StepRecord {
            step,
            time,
            samples: Vec::new(),
            damaged_volume_m3: None,
        }))
    }

    fn write_pending(&mut self) -> Result<(), RecordError> {
        if let Some(p) = self.pending.take() {
            self.write(&Record::Step(p))?;
        }
        Ok(())
    }

    fn write(&mut self, record: &Record) -> Result<(), RecordError> {
        let framed = encode_framed(record)?;
        if let Some(out) = self.out.as_mut() {
            out.write_all(&framed)?;
        }
        self.bytes += framed.len() as u64;
        self.records += 1;
        Ok(())
    }
}

impl<W: Write> Drop for Recorder<W> {
    fn drop(&mut self) {
        if self.out.is_some()
            && let Err(e) = self.flush()
        {
            tracing::warn!("recording not flushed on drop: {e}");
        }
    }
}

/// One record with its frame: payload length (u32 LE), CRC-32 of the payload (u32 LE),
/// payload (postcard).
pub fn encode_framed(record: &Record) -> Result<Vec<u8>, RecordError> {
    let payload = postcard::to_allocvec(record)?;
    if payload.len() > MAX_RECORD_LEN as usize {
        return Err(RecordError::TooLarge(payload.len()));
    }
    let mut out = Vec::with_capacity(FRAME_LEN + payload.len());
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    out.extend_from_slice(&payload);
    Ok(out)
}

/// The file header of this version.
pub fn file_header() -> [u8; HEADER_LEN] {
    let mut head = [0u8; HEADER_LEN];
    head[..8].copy_from_slice(&MAGIC);
    head[8..10].copy_from_slice(&VERSION.to_le_bytes());
    head
}
