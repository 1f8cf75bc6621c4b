//! Under hybrid: the local tool's input samples and what each input datagram repeats of
//! them.
//!
//! Every datagram carries the per-step samples of the last [`RECENT_S`] (three datagram
//! intervals, so up to two consecutive losses cost nothing), and before them a few older
//! samples on a coarse grid ([`COARSE_SPACING_S`], back to [`COARSE_SPAN_S`]), so that a
//! long burst of losses leaves the receiver a coarse path through the gap instead of one
//! straight line across it. Measured (`cosurg bench sync`, hybrid, `burst`, ×2, seed 14,
//! 2026-11-28): a burst lost the forceps' samples from 1.988 to about 2.13 s, across the
//! approach's stop and the jaws starting to close; the follower drew the tool straight
//! across the gap and was 0.31 mm off the owner (input-only, whose lag keeps a wider
//! margin: 0.12 mm). With the coarse samples the same row's worst seed was 0.09 mm.

use std::collections::VecDeque;

/// Simulated time between tool-input datagrams (s).
pub const POSE_HISTORY_INTERVAL: f64 = 0.008;
/// Every datagram repeats the per-step samples of this much simulated time (s; at least
/// three steps): each sample travels in three datagrams.
pub const RECENT_S: f64 = 3.0 * POSE_HISTORY_INTERVAL;
/// At most this many of them; at steps shorter than 2 ms every k-th step is repeated (the
/// newest always), so that a datagram stays within [`proto::MAX_POSE_SAMPLES`] with the
/// older ones.
const MAX_RECENT: usize = 12;
/// Spacing (s of simulated time) of the older samples a datagram repeats, at most: samples
/// on a grid of step indices, so that consecutive datagrams repeat the same ones.
pub const COARSE_SPACING_S: f64 = 0.04;
/// How far back (s of simulated time) from its newest sample a datagram repeats samples:
/// two or three 40-byte samples more per datagram (`cosurg bench sync`'s lan row stays
/// under 5 % of full-state).
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

    /// The samples of the next datagram, oldest first, for steps of `dt` (s): the older
    /// ones on the coarse grid, then the per-step ones of the last [`RECENT_S`].
    pub fn datagram(&self, dt: f64) -> Vec<proto::PoseSample> {
        let Some(newest) = self.samples.back().map(|p| p.sim_time_s) else {
            return Vec::new();
        };
        // At least three steps (a datagram goes out every step when steps are longer
        // than the interval); half a step of slack: sample times are multiples of dt in
        // floating point.
        let span = RECENT_S.max(3.0 * dt) - 0.5 * dt;
        let recent = |p: &proto::ToolPose| newest - p.sim_time_s < span;
        let n_recent = self.samples.iter().rev().take_while(|p| recent(p)).count();
        let thin = n_recent.div_ceil(MAX_RECENT).max(1);
        let first_recent = self.samples.len() - n_recent;
        let every = (COARSE_SPACING_S / dt + 1e-6).floor().max(1.0) as i64;
        let on_grid = |p: &proto::ToolPose| (p.sim_time_s / dt).round() as i64 % every == 0;
        let last = self.samples.len() - 1;
        let samples: Vec<proto::PoseSample> = self
            .samples
            .iter()
            .enumerate()
            .filter(|(i, p)| {
                if *i >= first_recent {
                    (last - i).is_multiple_of(thin)
                } else {
                    on_grid(p)
                }
            })
            .map(|(_, p)| proto::PoseSample {
                sim_time_s: p.sim_time_s,
                position: p.position,
                orientation: p.orientation,
                jaw_rad: p.jaw_rad,
            })
            .collect();
        debug_assert!(
            samples.len() <= proto::MAX_POSE_SAMPLES,
            "{}",
            samples.len()
        );
        samples
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: f64) -> proto::ToolPose {
        proto::ToolPose {
            site: 1,
            tool: 0,
            sim_time_s: t,
            position: [t as f32, 0.0, 0.0],
            orientation: [1.0, 0.0, 0.0, 0.0],
            jaw_rad: 0.1,
            velocity: [0.0; 3],
            angular_velocity: [0.0; 3],
        }
    }

    /// At every step size a datagram fits [`proto::MAX_POSE_SAMPLES`], is sorted, ends with
    /// the newest sample, covers the last [`RECENT_S`] with samples at most 2 ms apart (or
    /// one step, if longer), and reaches back about [`COARSE_SPAN_S`] in gaps of at most
    /// [`COARSE_SPACING_S`].
    #[test]
    fn a_datagram_covers_its_recent_steps_and_a_coarse_past_at_every_step_size() {
        for dt in [0.0005, 0.001, 0.002, 0.004, 0.006, 0.01, 0.016] {
            let mut h = InputHistory::default();
            for k in 0..400 {
                let t = f64::from(k) * dt;
                h.push(pose(t));
                let d = h.datagram(dt);
                let times: Vec<f64> = d.iter().map(|s| s.sim_time_s).collect();
                assert!(d.len() <= proto::MAX_POSE_SAMPLES, "dt {dt}: {times:?}");
                assert!(times.is_sorted_by(|a, b| a < b), "dt {dt}: {times:?}");
                assert_eq!(times.last(), Some(&t));
                if t < COARSE_SPAN_S + COARSE_SPACING_S {
                    continue;
                }
                let step = dt.max(0.002) + 1e-9;
                let recent_gaps = times
                    .windows(2)
                    .filter(|w| t - w[0] < RECENT_S - 0.5 * dt)
                    .map(|w| w[1] - w[0]);
                assert!(
                    recent_gaps.fold(0.0, f64::max) <= step,
                    "dt {dt}: {times:?}"
                );
                assert!(
                    t - times[0] >= RECENT_S.max(COARSE_SPAN_S - COARSE_SPACING_S) - 1e-9,
                    "dt {dt}: reaches back {} s: {times:?}",
                    t - times[0]
                );
                let widest = times.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
                // Plus one thinned recent step (≤ 2 ms): the oldest recent sample kept may
                // be that much younger than the window's edge.
                assert!(
                    widest <= COARSE_SPACING_S.max(dt) + 0.002 + 1e-9,
                    "dt {dt}: {times:?}"
                );
            }
        }
    }
}
