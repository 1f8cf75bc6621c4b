//! Surface recordings in memory: [`SurfaceRecorder`] samples every embedded surface at
//! fixed marks of simulated time into a [`SurfaceRecording`]. The `.surf` file format
//! (reader and writer) lives in [`sim_scene::surf`]; sim-core does no IO.

use sim_scene::surf::{SurfaceRecord, SurfaceRecording};

use super::V3;
use crate::engine::Simulation;

/// Records every surface's vertices at marks `k · interval` of sim time (linearly
/// interpolated between the two steps around a mark). Call [`SurfaceRecorder::record`]
/// after every step (and once before the first).
#[derive(Clone, Debug)]
pub struct SurfaceRecorder {
    recording: SurfaceRecording,
    next_mark: u64,
    prev: Option<(f64, Vec<V3>)>,
}

/// Default mark interval of [`SurfaceRecorder`]: 50 ms of sim time.
pub const DEFAULT_MARK_INTERVAL_S: f64 = 0.05;

impl SurfaceRecorder {
    /// A recorder for the simulation's surfaces; `interval_s` ≤ 0 or non-finite falls back
    /// to [`DEFAULT_MARK_INTERVAL_S`].
    pub fn new(sim: &Simulation, interval_s: f64) -> Self {
        let interval_s = if interval_s.is_finite() && interval_s > 0.0 {
            interval_s
        } else {
            DEFAULT_MARK_INTERVAL_S
        };
        SurfaceRecorder {
            recording: SurfaceRecording {
                scene_hash: sim.scene().hash.clone(),
                interval_s,
                surface_sizes: sim
                    .surfaces()
                    .iter()
                    .map(|s| s.deformed.len() as u32)
                    .collect(),
                records: Vec::new(),
            },
            next_mark: (sim.time() / interval_s - 1e-9).ceil().max(0.0) as u64,
            prev: None,
        }
    }

    /// Samples the marks passed since the last call.
    pub fn record(&mut self, sim: &Simulation) {
        let t = sim.time();
        // A cut appends vertices to a surface (its original ones keep their indices): the
        // recording keeps the vertices it declared.
        let cur: Vec<V3> = sim
            .surfaces()
            .iter()
            .zip(&self.recording.surface_sizes)
            .flat_map(|(s, &n)| s.deformed.iter().take(n as usize).copied())
            .collect();
        let dt = self.recording.interval_s;
        loop {
            let mark = self.next_mark as f64 * dt;
            if mark > t + 1e-9 {
                break;
            }
            let pts: Vec<[f32; 3]> = match &self.prev {
                Some((tp, prev)) if *tp < mark - 1e-9 && t - tp > 1e-12 => {
                    let w = (mark - tp) / (t - tp);
                    prev.iter()
                        .zip(&cur)
                        .map(|(a, b)| to_f32(&(a + (b - a) * w)))
                        .collect()
                }
                _ => cur.iter().map(to_f32).collect(),
            };
            self.recording.records.push(SurfaceRecord {
                time_s: mark,
                vertices: pts,
            });
            self.next_mark += 1;
        }
        self.prev = Some((t, cur));
    }

    pub fn recording(&self) -> &SurfaceRecording {
        &self.recording
    }

    pub fn into_recording(self) -> SurfaceRecording {
        self.recording
    }
}

fn to_f32(p: &V3) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}
