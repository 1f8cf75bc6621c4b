//! [`Recording`]: reads a recording back, up to its last complete record; [`Session`]:
//! the recordings of several sites found in one directory.

use std::path::{Path, PathBuf};

use crate::format::{
    Event, FRAME_LEN, HEADER_LEN, MAGIC, MAX_RECORD_LEN, Record, SessionHeader, StepRecord,
    SurfaceDecl, ToolDecl, ToolState, VERSION,
};

/// File extension of recordings.
pub const EXTENSION: &str = "cosrec";

/// Why a recording could not be read at all.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("reading {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("not a cosurg recording: {0} bytes, shorter than the {HEADER_LEN}-byte file header")]
    ShortHeader(usize),
    #[error("not a cosurg recording: bad magic {0:02x?} (expected \"COSURGRC\")")]
    BadMagic([u8; 8]),
    #[error("recording format version {0} is not supported (this reader knows version {VERSION})")]
    UnknownVersion(u16),
    #[error("the recording holds no complete session record ({0})")]
    NoSession(Tail),
    #[error("the first record is not the session record")]
    SessionNotFirst,
    #[error("{0}: no {ext} recordings in this directory", ext = EXTENSION)]
    EmptyDir(PathBuf),
}

/// How the record sequence ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Tail {
    /// At a record boundary.
    Complete,
    /// Cut inside a frame header or payload (a killed writer): `bytes` left over at `offset`.
    Truncated { offset: u64, bytes: u64 },
    /// A record's CRC did not match at `offset`; nothing after it is trusted.
    BadCrc { offset: u64 },
    /// A length field above the format's limit at `offset`.
    BadLength { offset: u64, length: u32 },
}

impl std::fmt::Display for Tail {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Tail::Complete => write!(f, "complete"),
            Tail::Truncated { offset, bytes } => {
                write!(
                    f,
                    "truncated: {bytes} bytes of an incomplete record at byte {offset}"
                )
            }
            Tail::BadCrc { offset } => write!(f, "CRC mismatch in the record at byte {offset}"),
            Tail::BadLength { offset, length } => {
                write!(f, "impossible record length {length} at byte {offset}")
            }
        }
    }
}

/// Records of a byte string after its file header.
#[derive(Clone, Debug, PartialEq)]
pub struct Records {
    pub records: Vec<Record>,
    pub tail: Tail,
    /// Records with a good CRC that this reader could not decode (newer kinds), skipped.
    pub skipped_unknown: usize,
}

/// Checks the file header and decodes every complete record; never panics.
pub fn read_records(bytes: &[u8]) -> Result<Records, ReadError> {
    if bytes.len() < HEADER_LEN {
        // A prefix of a valid header is a truncated recording; anything else is not one.
        if !MAGIC.starts_with(&bytes[..bytes.len().min(8)]) {
            let mut m = [0u8; 8];
            m[..bytes.len().min(8)].copy_from_slice(&bytes[..bytes.len().min(8)]);
            return Err(ReadError::BadMagic(m));
        }
        return Err(ReadError::ShortHeader(bytes.len()));
    }
    let magic: [u8; 8] = bytes[..8].try_into().expect("8 bytes");
    if magic != MAGIC {
        return Err(ReadError::BadMagic(magic));
    }
    let version = u16::from_le_bytes([bytes[8], bytes[9]]);
    if version != VERSION {
        return Err(ReadError::UnknownVersion(version));
    }
    let mut records = Vec::new();
    let mut skipped_unknown = 0;
    let mut at = HEADER_LEN;
    let tail = loop {
        let rest = &bytes[at..];
        if rest.is_empty() {
            break Tail::Complete;
        }
        if rest.len() < FRAME_LEN {
            break Tail::Truncated {
                offset: at as u64,
                bytes: rest.len() as u64,
            };
        }
        let len = u32::from_le_bytes(rest[..4].try_into().expect("4 bytes"));
        let crc = u32::from_le_bytes(rest[4..8].try_into().expect("4 bytes"));
        if len > MAX_RECORD_LEN {
            break Tail::BadLength {
                offset: at as u64,
                length: len,
            };
        }
        let Some(payload) = rest.get(FRAME_LEN..FRAME_LEN + len as usize) else {
            break Tail::Truncated {
                offset: at as u64,
                bytes: rest.len() as u64,
            };
        };
        if crc32fast::hash(payload) != crc {
            break Tail::BadCrc { offset: at as u64 };
        }
        match postcard::from_bytes::<Record>(payload) {
            Ok(r) => records.push(r),
            Err(e) => {
                tracing::debug!("skipping an undecodable record at byte {at}: {e}");
                skipped_unknown += 1;
            }
        }
        at += FRAME_LEN + len as usize;
    };
    Ok(Records {
        records,
        tail,
        skipped_unknown,
    })
}

/// The time series of one tool.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Track {
    pub decl: Option<ToolDecl>,
    /// Simulated time of each sample (s).
    pub times: Vec<f64>,
    pub states: Vec<ToolState>,
}

impl Track {
    /// Tip positions (m).
    pub fn positions(&self) -> Vec<[f64; 3]> {
        self.states.iter().map(|s| s.position).collect()
    }
    pub fn len(&self) -> usize {
        self.times.len()
    }
    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }
}

/// One decoded surface frame.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceShape {
    pub step: u64,
    pub time: f64,
    /// Deformed vertices (m).
    pub vertices: Vec<[f64; 3]>,
}

/// Role (and site name) in the header of a coordinator's recording.
pub const COORDINATOR_ROLE: &str = "coordinator";

/// How much longer (s of simulated time) another recording must hold a site's tool
/// samples than the site's own recording for [`Session::recording_for`] to prefer it.
pub const STALE_OWN_S: f64 = 1.0;

/// One site's recording, read up to its last complete record.
#[derive(Clone, Debug)]
pub struct Recording {
    pub header: SessionHeader,
    /// Every record after the session record, in file order.
    pub records: Vec<Record>,
    pub tail: Tail,
    pub skipped_unknown: usize,
    /// File it came from, if any.
    pub path: Option<PathBuf>,
    /// Size in bytes.
    pub bytes: u64,
}

impl Recording {
    /// Parses a recording held in memory.
    pub fn from_bytes(bytes: &[u8]) -> Result<Recording, ReadError> {
        let r = read_records(bytes)?;
        let mut it = r.records.into_iter();
        let header = match it.next() {
            Some(Record::Session(h)) => h,
            Some(_) => return Err(ReadError::SessionNotFirst),
            None => return Err(ReadError::NoSession(r.tail)),
        };
        if r.tail != Tail::Complete {
            tracing::warn!("recording of site {}: {}", header.site, r.tail);
        }
        Ok(Recording {
            header,
            records: it.collect(),
            tail: r.tail,
            skipped_unknown: r.skipped_unknown,
            path: None,
            bytes: bytes.len() as u64,
        })
    }

    /// Reads a recording file.
    pub fn open(path: impl AsRef<Path>) -> Result<Recording, ReadError> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| ReadError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut r = Recording::from_bytes(&bytes)?;
        r.path = Some(path.to_path_buf());
        Ok(r)
    }

    /// The declared tools.
    pub fn tools(&self) -> Vec<&ToolDecl> {
        self.records
            .iter()
            .filter_map(|r| match r {
                Record::Tool(t) => Some(t),
                _ => None,
            })
            .collect()
    }

    /// The declared surfaces.
    pub fn surfaces(&self) -> Vec<&SurfaceDecl> {
        self.records
            .iter()
            .filter_map(|r| match r {
                Record::Surface(s) => Some(s),
                _ => None,
            })
            .collect()
    }

    /// The step records.
    pub fn steps(&self) -> impl Iterator<Item = &StepRecord> {
        self.records.iter().filter_map(|r| match r {
            Record::Step(s) => Some(s),
            _ => None,
        })
    }

    /// The events.
    pub fn events(&self) -> impl Iterator<Item = &Event> {
        self.records.iter().filter_map(|r| match r {
            Record::Event(e) => Some(e),
            _ => None,
        })
    }

    /// Simulated time of the earliest and latest step record (s) (a coordinator's
    /// recording interleaves sites whose clocks differ by a few ms).
    pub fn time_span(&self) -> Option<(f64, f64)> {
        self.steps()
            .map(|s| s.time)
            .fold(None, |span, t| match span {
                None => Some((t, t)),
                Some((a, b)) => Some((f64::min(a, t), f64::max(b, t))),
            })
    }

    /// The samples of tool `id`.
    pub fn track(&self, id: u16) -> Track {
        let mut track = Track {
            decl: self.tools().into_iter().find(|t| t.id == id).cloned(),
            ..Track::default()
        };
        for s in self.steps() {
            if let Some(sample) = s.samples.iter().find(|x| x.tool == id) {
                track.times.push(s.time);
                track.states.push(sample.state());
            }
        }
        track
    }

    /// The tools driven by `site`, with their tracks.
    pub fn site_tracks(&self, site: &str) -> Vec<Track> {
        self.tools()
            .into_iter()
            .filter(|t| t.site == site)
            .map(|t| self.track(t.id))
            .collect()
    }

    /// The damaged volume series: (time s, volume m³) of the steps that have one.
    pub fn damage(&self) -> Vec<(f64, f64)> {
        self.steps()
            .filter_map(|s| s.damaged_volume_m3.map(|v| (s.time, f64::from(v))))
            .collect()
    }

    /// The decoded frames of surface `id`, in order (deltas resolved).
    pub fn surface_shapes(&self, id: u16) -> Vec<SurfaceShape> {
        let Some(decl) = self.surfaces().into_iter().find(|s| s.id == id) else {
            return Vec::new();
        };
        let n = decl.rest.len() * 3;
        let mut q = vec![0i32; n];
        let mut out = Vec::new();
        for r in &self.records {
            let Record::SurfaceFrame(f) = r else { continue };
            if f.surface != id || f.values.len() != n {
                continue;
            }
            for (a, b) in q.iter_mut().zip(&f.values) {
                *a = if f.key { *b } else { a.wrapping_add(*b) };
            }
            let vertices = decl
                .rest
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    [0, 1, 2].map(|k| f64::from(r[k]) + f64::from(q[3 * i + k]) * decl.quantum_m)
                })
                .collect();
            out.push(SurfaceShape {
                step: f.step,
                time: f.time,
                vertices,
            });
        }
        out
    }
}

/// The recordings of one session: one file, or every `*.cosrec` in a directory and its
/// immediate subdirectories.
#[derive(Clone, Debug)]
pub struct Session {
    pub recordings: Vec<Recording>,
}

impl Session {
    /// Opens a recording file or a directory of recordings, with those of its immediate
    /// subdirectories (sorted by path; unreadable files in a directory are skipped with
    /// a warning).
    pub fn open(path: impl AsRef<Path>) -> Result<Session, ReadError> {
        let path = path.as_ref();
        if !path.is_dir() {
            return Ok(Session {
                recordings: vec![Recording::open(path)?],
            });
        }
        let io = |source| ReadError::Io {
            path: path.to_path_buf(),
            source,
        };
        let is_rec = |p: &Path| p.is_file() && p.extension().is_some_and(|e| e == EXTENSION);
        let entries: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(io)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        // The recordings in the directory and in its immediate subdirectories (a demo's
        // out folder holds one folder per site).
        let mut files: Vec<PathBuf> = entries.iter().filter(|p| is_rec(p)).cloned().collect();
        for sub in entries.iter().filter(|p| p.is_dir()) {
            if let Ok(rd) = std::fs::read_dir(sub) {
                files.extend(
                    rd.filter_map(|e| e.ok().map(|e| e.path()))
                        .filter(|p| is_rec(p)),
                );
            }
        }
        files.sort();
        let mut recordings = Vec::new();
        for f in files {
            match Recording::open(&f) {
                Ok(r) => recordings.push(r),
                Err(e) => tracing::warn!("skipping {}: {e}", f.display()),
            }
        }
        if recordings.is_empty() {
            return Err(ReadError::EmptyDir(path.to_path_buf()));
        }
        let mut session = Session { recordings };
        session.name_coordinator_tools();
        Ok(session)
    }

    /// Gives the tools of a coordinator's recording, which it knows only by scene index
    /// (`#N`, empty kind), the name and kind of tool `N` in a site's recording of the
    /// session (a site declares every scene tool, in scene order).
    pub fn name_coordinator_tools(&mut self) {
        let Some(names) = self
            .recordings
            .iter()
            .find(|r| r.header.role != COORDINATOR_ROLE && !r.tools().is_empty())
            .map(|r| {
                r.tools()
                    .iter()
                    .map(|t| (t.id, (t.name.clone(), t.kind.clone())))
                    .collect::<std::collections::BTreeMap<_, _>>()
            })
        else {
            return;
        };
        for rec in self
            .recordings
            .iter_mut()
            .filter(|r| r.header.role == COORDINATOR_ROLE)
        {
            for record in &mut rec.records {
                if let Record::Tool(t) = record
                    && t.kind.is_empty()
                    && let Some((name, kind)) = t
                        .name
                        .strip_prefix('#')
                        .and_then(|n| n.parse::<u16>().ok())
                        .and_then(|n| names.get(&n))
                {
                    t.name = name.clone();
                    t.kind = kind.clone();
                }
            }
        }
    }

    /// Names of the recording sites.
    pub fn sites(&self) -> Vec<&str> {
        self.recordings
            .iter()
            .map(|r| r.header.site.as_str())
            .collect()
    }

    /// The recording that holds `site`'s tools best: the site's own recording, unless it
    /// has no samples of them or ends more than [`STALE_OWN_S`] of simulated time before
    /// another recording's samples of them do (a killed site's cut-off file, when the
    /// coordinator's recording goes on to the kill); else the recording whose samples of
    /// the site's tools end last (e.g. the coordinator's, if the site's file is missing).
    pub fn recording_for(&self, site: &str) -> Option<&Recording> {
        let end = |r: &Recording| {
            r.site_tracks(site)
                .iter()
                .filter_map(|t| t.times.last().copied())
                .reduce(f64::max)
        };
        let own = self
            .recordings
            .iter()
            .find(|r| r.header.site == site)
            .and_then(|r| end(r).map(|e| (e, r)));
        let other = self
            .recordings
            .iter()
            .filter(|r| r.header.site != site)
            .filter_map(|r| end(r).map(|e| (e, r)))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        match (own, other) {
            (Some((own_end, _)), Some((other_end, r))) if other_end > own_end + STALE_OWN_S => {
                Some(r)
            }
            (Some((_, r)), _) => Some(r),
            (None, Some((_, r))) => Some(r),
            (None, None) => self.recordings.iter().find(|r| r.header.site == site),
        }
    }

    /// Every event of every recording, by time (duplicates seen by several sites kept).
    pub fn events(&self) -> Vec<(&str, &Event)> {
        let mut all: Vec<(&str, &Event)> = self
            .recordings
            .iter()
            .flat_map(|r| r.events().map(move |e| (r.header.site.as_str(), e)))
            .collect();
        all.sort_by(|a, b| a.1.time.total_cmp(&b.1.time));
        all
    }
}
