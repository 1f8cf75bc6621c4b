//! # cosurg-debrief
//!
//! Session recordings and their debrief.
//!
//! * [`format`] — the records (session header, tool and surface declarations, step
//!   records with tool samples and tissue damage, events, surface frames) and their
//!   quantisation. The byte layout is in `FORMAT.md`: a 12-byte file header (magic,
//!   version) then length-prefixed, CRC-32-checked postcard records, append-only, so a
//!   recording cut off by a kill reads back up to its last complete record.
//! * [`Recorder`] — the writer a site calls from its loop with plain data
//!   ([`ToolState`], `[f64; 3]` vertices, [`Event`]).
//! * [`Recording`] / [`Session`] — the reader (never panics; reports truncation, bad
//!   magic, unknown versions and CRC mismatches) and the recordings of one directory.
//! * [`score`] — skill measures per act (time, path length, economy, idle time, depth
//!   along the shaft, LDLJ, forces, tissue damage, DTW against a reference).
//! * [`report`] — scores as JSON and as a self-contained HTML page with SVG plots.
//!
//! Units: SI (m, s, N, m³).

pub mod format;
pub mod reader;
pub mod report;
pub mod score;
mod writer;

pub use format::{
    Event, EventKind, Record, SessionHeader, StepRecord, SurfaceDecl, SurfaceFrame, ToolDecl,
    ToolSample, ToolState,
};
pub use reader::{
    COORDINATOR_ROLE, EXTENSION, ReadError, Recording, Records, Session, SurfaceShape, Tail, Track,
    read_records,
};
pub use report::{ScoreError, ScoreReport, ScoredAct, SiteTracks, html_report, score_site};
pub use score::{Act, ActKind, EventActs, Measures, ScoreSettings};
pub use writer::{
    RecordError, Recorder, RecorderSettings, SurfaceId, ToolId, encode_framed, file_header,
};
