//! The `.surf` surface-recording file: every embedded-surface vertex of a simulation at
//! fixed marks of simulated time, written by each site of a session so that sites can be
//! compared afterwards (`cosurg divergence`). Recordings are collected in memory by
//! sim-core's `sync::SurfaceRecorder`; this module reads and writes the file.
//!
//! # Format (version 1, little-endian, no padding)
//! ```text
//! header
//!   8 bytes   magic "CSURF01\n" (the version is the "01")
//!   u32       scene hash length H (≤ 1024), then H bytes of UTF-8 scene hash
//!             (the hex SHA-256 of the scene, see [`crate::scene_hash`])
//!   f64       mark interval (s of simulated time), positive and finite
//!   u32       surface count S (≤ 4096), then S × u32 vertex counts, one per surface in
//!             the scene's surface order; N = their sum (≤ 2^24)
//! records, until the end of the file, each 8 + 12 N bytes:
//!   f64       simulated time of the mark (s), finite, strictly increasing
//!   N × 3 f32 vertex positions x, y, z (m, world frame), surfaces concatenated in order
//! ```
//! A file therefore ends on a record boundary; a trailing partial record is an error (a
//! writer that was killed mid-record leaves one). Vertex coordinates must be finite.
//! Readers reject every malformation with a [`SurfError`] and never panic.

use std::io::Write;

use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// Max and RMS distance (m) between corresponding vertices of two surfaces; compares the
/// first `min(a.len(), b.len())` vertices; `(0, 0)` when there are none.
pub fn surface_divergence(a: &[V3], b: &[V3]) -> (f64, f64) {
    let n = a.len().min(b.len());
    if n == 0 {
        return (0.0, 0.0);
    }
    let (mut max, mut sum): (f64, f64) = (0.0, 0.0);
    for (p, q) in a.iter().zip(b) {
        let d2 = (p - q).norm_squared();
        max = max.max(d2);
        sum += d2;
    }
    (max.sqrt(), (sum / n as f64).sqrt())
}

/// Magic of a `.surf` file.
pub const SURF_MAGIC: &[u8; 8] = b"CSURF01\n";
const SURF_MAX_HASH: u32 = 1024;
const SURF_MAX_SURFACES: u32 = 4096;
const SURF_MAX_VERTICES: u64 = 1 << 24;

/// A malformed `.surf` file (or two recordings that cannot be compared).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[allow(missing_docs)] // fields: named in each variant's message
pub enum SurfError {
    /// Not a `.surf` file, or another version.
    #[error(".surf: bad magic (not a cosurg surface recording, or another version)")]
    BadMagic,
    /// The header ends early.
    #[error(".surf: truncated in {what} at byte {offset}")]
    Truncated { what: &'static str, offset: usize },
    /// A header count exceeds its limit.
    #[error(".surf: {what} {value} exceeds the limit {max}")]
    TooLarge {
        what: &'static str,
        value: u64,
        max: u64,
    },
    /// The scene hash is not UTF-8.
    #[error(".surf: scene hash is not UTF-8")]
    HashNotUtf8,
    /// The mark interval is not positive and finite.
    #[error(".surf: mark interval {0} s is not positive and finite")]
    BadInterval(f64),
    /// The file does not end on a record boundary.
    #[error(".surf: {remaining} trailing bytes do not form a whole record of {record_size} bytes")]
    PartialRecord {
        remaining: usize,
        record_size: usize,
    },
    /// A record's time is not finite or not after the previous one.
    #[error(".surf: record {index}: time {time} s is not finite or not increasing")]
    BadTime { index: usize, time: f64 },
    /// A record holds a non-finite coordinate.
    #[error(".surf: record {index}: non-finite vertex coordinate")]
    NonFinite { index: usize },
    /// Two recordings cannot be compared (different scene or surfaces).
    #[error("surface recordings differ in {what}: {a} vs {b}")]
    Mismatch {
        what: &'static str,
        a: String,
        b: String,
    },
}

/// One sample of every surface vertex at a sim-time mark.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceRecord {
    /// Simulation time of the mark (s).
    pub time_s: f64,
    /// Vertex positions (m) of all surfaces, concatenated in surface order.
    pub vertices: Vec<[f32; 3]>,
}

/// Surface vertex positions at fixed sim-time marks, as stored in a `.surf` file (format
/// in the [module docs](self)).
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceRecording {
    /// Hash of the recorded scene (recordings of different scenes are not compared).
    pub scene_hash: String,
    /// Simulated time between marks (s).
    pub interval_s: f64,
    /// Vertex count of each surface.
    pub surface_sizes: Vec<u32>,
    /// The marks, time increasing.
    pub records: Vec<SurfaceRecord>,
}

/// Divergence between two recordings at one mark.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DivergenceSample {
    /// Simulated time of the mark (s).
    pub time_s: f64,
    /// Largest vertex distance (m).
    pub max_m: f64,
    /// Root mean square vertex distance (m).
    pub rms_m: f64,
}

impl SurfaceRecording {
    /// Total vertex count per record.
    pub fn vertex_count(&self) -> usize {
        self.surface_sizes.iter().map(|&n| n as usize).sum()
    }

    /// Bytes of the header.
    fn header_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(SURF_MAGIC);
        out.extend_from_slice(&(self.scene_hash.len() as u32).to_le_bytes());
        out.extend_from_slice(self.scene_hash.as_bytes());
        out.extend_from_slice(&self.interval_s.to_le_bytes());
        out.extend_from_slice(&(self.surface_sizes.len() as u32).to_le_bytes());
        for n in &self.surface_sizes {
            out.extend_from_slice(&n.to_le_bytes());
        }
        out
    }

    fn record_bytes(r: &SurfaceRecord, out: &mut Vec<u8>) {
        out.extend_from_slice(&r.time_s.to_le_bytes());
        for v in &r.vertices {
            for c in v {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = self.header_bytes();
        for r in &self.records {
            Self::record_bytes(r, &mut out);
        }
        out
    }

    /// Writes the file.
    pub fn write_to<W: Write>(&self, mut w: W) -> std::io::Result<()> {
        w.write_all(&self.to_bytes())
    }

    /// Parses a file; rejects malformed input with a [`SurfError`], never panics.
    pub fn from_bytes(bytes: &[u8]) -> Result<SurfaceRecording, SurfError> {
        let mut pos = 0usize;
        let mut take = |n: usize, what: &'static str| -> Result<&[u8], SurfError> {
            let s = bytes
                .get(pos..pos.saturating_add(n))
                .ok_or(SurfError::Truncated { what, offset: pos })?;
            pos += n;
            Ok(s)
        };
        if take(8, "magic").map_err(|_| SurfError::BadMagic)? != SURF_MAGIC {
            return Err(SurfError::BadMagic);
        }
        let u32_of = |s: &[u8]| u32::from_le_bytes(s.try_into().expect("4 bytes"));
        let hash_len = u32_of(take(4, "hash length")?);
        if hash_len > SURF_MAX_HASH {
            return Err(SurfError::TooLarge {
                what: "scene hash length",
                value: hash_len.into(),
                max: SURF_MAX_HASH.into(),
            });
        }
        let scene_hash = std::str::from_utf8(take(hash_len as usize, "scene hash")?)
            .map_err(|_| SurfError::HashNotUtf8)?
            .to_string();
        let interval_s = f64::from_le_bytes(take(8, "interval")?.try_into().expect("8 bytes"));
        if !(interval_s.is_finite() && interval_s > 0.0) {
            return Err(SurfError::BadInterval(interval_s));
        }
        let n_surfaces = u32_of(take(4, "surface count")?);
        if n_surfaces > SURF_MAX_SURFACES {
            return Err(SurfError::TooLarge {
                what: "surface count",
                value: n_surfaces.into(),
                max: SURF_MAX_SURFACES.into(),
            });
        }
        let mut surface_sizes = Vec::with_capacity(n_surfaces as usize);
        let mut total: u64 = 0;
        for _ in 0..n_surfaces {
            let n = u32_of(take(4, "vertex counts")?);
            total += u64::from(n);
            surface_sizes.push(n);
        }
        if total > SURF_MAX_VERTICES {
            return Err(SurfError::TooLarge {
                what: "vertex count",
                value: total,
                max: SURF_MAX_VERTICES,
            });
        }
        let n = total as usize;
        let record_size = 8 + 12 * n;
        let rest = &bytes[pos..];
        if !rest.len().is_multiple_of(record_size) {
            return Err(SurfError::PartialRecord {
                remaining: rest.len() % record_size,
                record_size,
            });
        }
        let mut records = Vec::with_capacity(rest.len() / record_size);
        let mut prev = f64::NEG_INFINITY;
        for (index, rec) in rest.chunks_exact(record_size).enumerate() {
            let time_s = f64::from_le_bytes(rec[..8].try_into().expect("8 bytes"));
            if !(time_s.is_finite() && time_s > prev) {
                return Err(SurfError::BadTime {
                    index,
                    time: time_s,
                });
            }
            prev = time_s;
            let mut vertices = Vec::with_capacity(n);
            for v in rec[8..].chunks_exact(12) {
                let c =
                    |k: usize| f32::from_le_bytes(v[4 * k..4 * k + 4].try_into().expect("4 bytes"));
                let p = [c(0), c(1), c(2)];
                if p.iter().any(|c| !c.is_finite()) {
                    return Err(SurfError::NonFinite { index });
                }
                vertices.push(p);
            }
            records.push(SurfaceRecord { time_s, vertices });
        }
        Ok(SurfaceRecording {
            scene_hash,
            interval_s,
            surface_sizes,
            records,
        })
    }

    /// For every mark, the largest distance (m) between it and any mark at most
    /// `window_s` before or after it, over all vertices: how far from this recording a
    /// view can be that shows it up to `window_s` early or late (a keyframe receiver
    /// shows its owner about one network path late, and early when it interpolates
    /// towards a keyframe its clock has not reached). Returns `(time_s, distance_m)` per
    /// mark. Every record holds the same vertices ([`SurfaceRecording::from_bytes`]
    /// checks it).
    pub fn motion_around(&self, window_s: f64) -> Vec<(f64, f64)> {
        let dist2 = |a: &SurfaceRecord, b: &SurfaceRecord| -> f64 {
            a.vertices
                .iter()
                .zip(&b.vertices)
                .map(|(p, q)| {
                    (0..3)
                        .map(|k| (f64::from(p[k]) - f64::from(q[k])).powi(2))
                        .sum::<f64>()
                })
                .fold(0.0, f64::max)
        };
        self.records
            .iter()
            .map(|r| {
                let max2 = self
                    .records
                    .iter()
                    .filter(|o| (o.time_s - r.time_s).abs() <= window_s + 1e-9)
                    .map(|o| dist2(r, o))
                    .fold(0.0, f64::max);
                (r.time_s, max2.sqrt())
            })
            .collect()
    }

    /// Divergence at every mark present in both recordings (times equal within 1 µs).
    /// Errors if the scene hashes or surface sizes differ.
    pub fn divergence(&self, other: &SurfaceRecording) -> Result<Vec<DivergenceSample>, SurfError> {
        if self.scene_hash != other.scene_hash {
            return Err(SurfError::Mismatch {
                what: "scene hash",
                a: self.scene_hash.clone(),
                b: other.scene_hash.clone(),
            });
        }
        if self.surface_sizes != other.surface_sizes {
            return Err(SurfError::Mismatch {
                what: "surface sizes",
                a: format!("{:?}", self.surface_sizes),
                b: format!("{:?}", other.surface_sizes),
            });
        }
        let mut out = Vec::new();
        let mut j = 0;
        for r in &self.records {
            while j < other.records.len() && other.records[j].time_s < r.time_s - 1e-6 {
                j += 1;
            }
            let Some(o) = other.records.get(j) else { break };
            if (o.time_s - r.time_s).abs() <= 1e-6 {
                let to64 = |v: &[[f32; 3]]| -> Vec<V3> {
                    v.iter()
                        .map(|p| V3::new(p[0].into(), p[1].into(), p[2].into()))
                        .collect()
                };
                let (max_m, rms_m) = surface_divergence(&to64(&r.vertices), &to64(&o.vertices));
                out.push(DivergenceSample {
                    time_s: r.time_s,
                    max_m,
                    rms_m,
                });
            }
        }
        Ok(out)
    }
}
