//! Under hybrid: the local tool's input samples and what each input datagram repeats of
//! them.
//!
//! Every datagram carries the newest [`POSE_HISTORY_SAMPLES`] per-step samples, so up to
//! two consecutive losses cost nothing, and before them a few older samples on a coarse
//! grid ([`COARSE_SPACING_S`], back to [`COARSE_SPAN_S`]), so that a long burst of losses
//! leaves the receiver a coarse path through the gap instead of one straight line across
//! it. Measured (`cosurg bench sync`, hybrid, `burst`, ×2, seed 14, 2026-11-28): a burst
//! lost the forceps' samples from 1.988 to about 2.13 s, across the approach's stop and the
//! jaws starting to close; the follower drew the tool straight across the gap and was
//! 0.31 mm off the owner (input-only, whose lag keeps a wider margin: 0.12 mm).

use std::collections::VecDeque;

/// Simulated time between tool-input datagrams (s).
pub const POSE_HISTORY_INTERVAL: f64 = 0.008;
/// How many of the newest per-step samples each datagram carries: every sample travels in
/// `POSE_HISTORY_SAMPLES × dt / POSE_HISTORY_INTERVAL` datagrams (3 at the bench's 4 ms
/// step).
pub const POSE_HISTORY_SAMPLES: usize = 6;
/// Spacing (s of simulated time) of the older samples a datagram repeats: samples on this
/// grid of step indices, so that consecutive datagrams repeat the same ones.
pub const COARSE_SPACING_S: f64 = 0.04;
/// How far back (s of simulated time) from its newest sample a datagram repeats samples.
/// Two or three 40-byte samples more per datagram at 4 ms steps (`cosurg bench sync`'s lan
/// row stays under 5 % of full-state).
pub const COARSE_SPAN_S: f64 = 0.12;

/// The local tool's recent samples (oldest first).
#[derive(Debug, Default)]
pub struct InputHistory {
    samples: VecDeque<proto::ToolPose>,
}

impl InputHistory {
    /// Adds the local tool's sample of the step; a sample of another tool starts afresh.
    pub fn push(&mut self, pose: proto::ToolPose) {
        if self.samples.back().is_some_and(|p| p.tool != pose.tool) {
            self.samples.clear();
        }
        self.samples.push_back(pose);
        while self
            .samples
            .front()
            .is_some_and(|p| pose.sim_time_s - p.sim_time_s > COARSE_SPAN_S + 1e-9)
        {
            self.samples.pop_front();
        }
    }

    pub fn clear(&mut self) {
        self.samples.clear();
    }

    /// The samples of the next datagram, oldest first: the older ones on the coarse grid of
    /// steps `dt` (s), then the newest [`POSE_HISTORY_SAMPLES`].
    pub fn datagram(&self, dt: f64) -> Vec<proto::PoseSample> {
        let newest = self.samples.len().saturating_sub(POSE_HISTORY_SAMPLES);
        let every = (COARSE_SPACING_S / dt).round().max(1.0) as i64;
        let on_grid = |p: &proto::ToolPose| (p.sim_time_s / dt).round() as i64 % every == 0;
        self.samples
            .iter()
            .enumerate()
            .filter(|(i, p)| *i >= newest || on_grid(p))
            .map(|(_, p)| proto::PoseSample {
                sim_time_s: p.sim_time_s,
                position: p.position,
                orientation: p.orientation,
                jaw_rad: p.jaw_rad,
            })
            .collect()
    }
}
