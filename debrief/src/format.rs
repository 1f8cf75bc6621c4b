//! The records of a recording and their quantisation (see `FORMAT.md` for the byte
//! layout). Everything here is plain data: positions as `[f64; 3]` in metres,
//! orientations as unit quaternions `[w, x, y, z]`, forces in newtons.

use serde::{Deserialize, Serialize};

/// First eight bytes of every recording.
pub const MAGIC: [u8; 8] = *b"COSURGRC";
/// Format version written by this crate (bytes 8..10, little endian).
pub const VERSION: u16 = 1;
/// Magic, version (u16 LE) and two reserved bytes (zero).
pub const HEADER_LEN: usize = 12;
/// Bytes before each record's payload: length (u32 LE) and CRC-32 (u32 LE) of the payload.
pub const FRAME_LEN: usize = 8;
/// Largest payload a reader accepts (64 MiB): a longer length field is corruption.
pub const MAX_RECORD_LEN: u32 = 64 << 20;

/// Position quantum of tool samples (m): 1 µm.
pub const POSITION_QUANTUM_M: f64 = 1e-6;
/// Force quantum of tool samples (N): 1 mN.
pub const FORCE_QUANTUM_N: f64 = 1e-3;

/// One record of a recording, in file order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Record {
    /// Always the first record.
    Session(SessionHeader),
    /// Declares a tool before its first sample.
    Tool(ToolDecl),
    /// Declares a surface (rest shape) before its first frame.
    Surface(SurfaceDecl),
    /// The tool samples and the damage scalar of one simulation step.
    Step(StepRecord),
    /// Something that happened (join, claim, grasp, reset, ...).
    Event(Event),
    /// The deformed shape of one surface.
    SurfaceFrame(SurfaceFrame),
}

/// Who recorded what.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionHeader {
    /// Session identifier (shared by all sites of one session).
    pub session: String,
    /// The recording site's name ("coordinator" for the coordinator's recording).
    pub site: String,
    /// Its role (instructor, trainee, observer, coordinator).
    pub role: String,
    /// Scene name (and hash where known).
    pub scene: String,
    /// Simulation rate (Hz) = 1 / dt.
    pub sim_rate_hz: f64,
    /// One step record every this many simulation steps.
    pub sample_every: u32,
    /// Wall clock at the start (ms since the Unix epoch).
    pub started_unix_ms: u64,
    /// Strain above which a tetrahedron counts as damaged, if the site records damage.
    pub damage_strain_threshold: Option<f64>,
    /// Writer software and version.
    pub software: String,
}

/// A tool: `id` is what samples refer to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ToolDecl {
    pub id: u16,
    /// Site that drives the tool.
    pub site: String,
    /// Tool name (as in the scene).
    pub name: String,
    /// Tool kind (forceps, probe, hook, ...).
    pub kind: String,
}

/// A surface's rest shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceDecl {
    pub id: u16,
    pub name: String,
    /// Rest vertex positions (m).
    pub rest: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// Displacement quantum of its frames (m).
    pub quantum_m: f64,
}

/// The samples of one step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// Simulation step index.
    pub step: u64,
    /// Simulated time (s).
    pub time: f64,
    pub samples: Vec<ToolSample>,
    /// Tissue volume above the damage strain threshold at this step (m³), if measured.
    pub damaged_volume_m3: Option<f32>,
}

/// One tool at one step, quantised (see [`ToolState`] for the plain form).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ToolSample {
    pub tool: u16,
    /// Tip position in µm (zigzag varints).
    pub position_um: [i32; 3],
    /// Orientation `[w, x, y, z]`, each component × 32767 as i16 little endian.
    pub orientation: [u8; 8],
    /// Jaw opening (rad).
    pub jaw: f32,
    /// Grasped surface points (0: not grasping).
    pub grasped: u16,
    /// Contact force on the tool in mN.
    pub contact_mn: [i32; 3],
    /// Grasp force on the tool in mN.
    pub grasp_mn: [i32; 3],
}

/// A tool at one step in plain units: what a site passes to the recorder.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct ToolState {
    /// Tip position (m).
    pub position: [f64; 3],
    /// Unit quaternion `[w, x, y, z]`, tool frame → world; the shaft is the tool frame's +z.
    pub orientation: [f64; 4],
    /// Jaw opening (rad).
    pub jaw: f64,
    /// Grasped surface points (0: not grasping).
    pub grasped: u32,
    /// Contact force on the tool (N), grasping excluded.
    pub contact_force: [f64; 3],
    /// Grasp force on the tool (N).
    pub grasp_force: [f64; 3],
}

fn quantise(v: f64, quantum: f64) -> i32 {
    let q = (v / quantum).round();
    if q.is_nan() {
        0
    } else {
        q.clamp(i32::MIN as f64, i32::MAX as f64) as i32
    }
}

fn quantise3(v: [f64; 3], quantum: f64) -> [i32; 3] {
    v.map(|x| quantise(x, quantum))
}

impl ToolSample {
    /// Quantises a plain tool state (positions to 1 µm, forces to 1 mN, quaternion
    /// components to 1/32767).
    pub fn quantise(tool: u16, s: &ToolState) -> ToolSample {
        let mut q = s.orientation;
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if n > 0.0 && n.is_finite() {
            q = q.map(|c| c / n);
        } else {
            q = [1.0, 0.0, 0.0, 0.0];
        }
        let mut orientation = [0u8; 8];
        for (k, c) in q.iter().enumerate() {
            let v = (c * 32767.0).round().clamp(-32767.0, 32767.0) as i16;
            orientation[2 * k..2 * k + 2].copy_from_slice(&v.to_le_bytes());
        }
        ToolSample {
            tool,
            position_um: quantise3(s.position, POSITION_QUANTUM_M),
            orientation,
            jaw: s.jaw as f32,
            grasped: s.grasped.min(u16::MAX as u32) as u16,
            contact_mn: quantise3(s.contact_force, FORCE_QUANTUM_N),
            grasp_mn: quantise3(s.grasp_force, FORCE_QUANTUM_N),
        }
    }

    /// Back to plain units.
    pub fn state(&self) -> ToolState {
        let mut q = [0.0; 4];
        for (k, c) in q.iter_mut().enumerate() {
            let raw = i16::from_le_bytes([self.orientation[2 * k], self.orientation[2 * k + 1]]);
            *c = f64::from(raw) / 32767.0;
        }
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if n > 0.0 {
            q = q.map(|c| c / n);
        } else {
            q = [1.0, 0.0, 0.0, 0.0];
        }
        ToolState {
            position: self.position_um.map(|v| f64::from(v) * POSITION_QUANTUM_M),
            orientation: q,
            jaw: f64::from(self.jaw),
            grasped: u32::from(self.grasped),
            contact_force: self.contact_mn.map(|v| f64::from(v) * FORCE_QUANTUM_N),
            grasp_force: self.grasp_mn.map(|v| f64::from(v) * FORCE_QUANTUM_N),
        }
    }
}

/// Something that happened at a step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    pub step: u64,
    /// Simulated time (s).
    pub time: f64,
    /// Site the event is about.
    pub site: String,
    /// Tool the event is about, if any.
    pub tool: Option<String>,
    pub kind: EventKind,
    /// Free text (region claimed, reason for leaving, ...).
    pub detail: String,
}

/// What kind of event. New kinds are appended at the end (a reader that does not know
/// one skips the record and counts it, see `FORMAT.md`); `Other` carries anything else.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EventKind {
    Join,
    Leave,
    Claim,
    Release,
    Reset,
    TeachingStart,
    TeachingStop,
    /// A tool closed on tissue.
    Grasp,
    /// A tool let go of tissue.
    GraspRelease,
    CutStart,
    CutStop,
    Other(String),
}

impl EventKind {
    /// A short lower-case name (`teaching-start`, `other:<name>`).
    pub fn label(&self) -> String {
        match self {
            EventKind::Join => "join".into(),
            EventKind::Leave => "leave".into(),
            EventKind::Claim => "claim".into(),
            EventKind::Release => "release".into(),
            EventKind::Reset => "reset".into(),
            EventKind::TeachingStart => "teaching-start".into(),
            EventKind::TeachingStop => "teaching-stop".into(),
            EventKind::Grasp => "grasp".into(),
            EventKind::GraspRelease => "grasp-release".into(),
            EventKind::CutStart => "cut-start".into(),
            EventKind::CutStop => "cut-stop".into(),
            EventKind::Other(s) => format!("other:{s}"),
        }
    }
}

/// One surface's shape at one step: quantised displacements from the rest shape
/// (`key`), or their change since the previous frame of the same surface (not `key`),
/// three values per vertex, in units of the surface's `quantum_m`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceFrame {
    pub surface: u16,
    pub step: u64,
    pub time: f64,
    pub key: bool,
    pub values: Vec<i32>,
}
