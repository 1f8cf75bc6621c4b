//! Quantisation of node states for [`crate::msg::RegionKeyframe`].
//!
//! Positions are stored as `i32` multiples of `pos_step_m` relative to a per-keyframe `origin`
//! (the centre of the nodes' bounding box); velocities as `i32` multiples of `vel_step_m_s`.
//! postcard writes integers as zig-zag varints, so offsets below 2¹³ steps take 2 bytes.
//!
//! **Error bound.** For every finite input within range, each component satisfies
//! `|dequantise(quantise(x)) − x| ≤ step/2` (up to f64 rounding, ≤ 1e-12 relative to the
//! magnitude of the origin). Out-of-range or non-finite inputs are rejected with
//! [`QuantError`], never silently clamped. With the defaults ([`DEFAULT_POSITION_STEP_M`] =
//! 10 µm, [`DEFAULT_VELOCITY_STEP_M_S`] = 0.1 mm/s) the position error is ≤ 5 µm and the
//! velocity error ≤ 0.05 mm/s; the ranges are ±21 km and ±214 km/s, i.e. never hit in practice.

use serde::{Deserialize, Serialize};

/// Default position step: 10 µm.
pub const DEFAULT_POSITION_STEP_M: f64 = 1e-5;
/// Default velocity step: 0.1 mm/s.
pub const DEFAULT_VELOCITY_STEP_M_S: f64 = 1e-4;

/// Quantisation failure.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QuantError {
    #[error("node {index}: non-finite {what}")]
    NonFinite { index: usize, what: &'static str },
    #[error("node {index}: {what} {value} out of range for step {step}")]
    OutOfRange {
        index: usize,
        what: &'static str,
        value: f64,
        step: f64,
    },
    #[error("invalid step {0} (must be finite and > 0)")]
    BadStep(f64),
    #[error("length mismatch: {ids} ids, {positions} positions, {velocities} velocities")]
    LengthMismatch {
        ids: usize,
        positions: usize,
        velocities: usize,
    },
}

/// Quantise one scalar: `round((x - origin) / step)` as `i32`.
pub fn quantise_scalar(x: f64, origin: f64, step: f64) -> Option<i32> {
    if !x.is_finite() {
        return None;
    }
    let q = ((x - origin) / step).round();
    if q >= i32::MIN as f64 && q <= i32::MAX as f64 {
        Some(q as i32)
    } else {
        None
    }
}

/// Inverse of [`quantise_scalar`].
pub fn dequantise_scalar(q: i32, origin: f64, step: f64) -> f64 {
    origin + q as f64 * step
}

/// Quantised node ids, positions and velocities of one region.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QuantisedNodes {
    /// Position origin (m).
    pub origin: [f64; 3],
    /// Position step (m).
    pub pos_step_m: f64,
    /// Velocity step (m/s).
    pub vel_step_m_s: f64,
    pub ids: Vec<u32>,
    pub positions: Vec<[i32; 3]>,
    pub velocities: Vec<[i32; 3]>,
}

impl Default for QuantisedNodes {
    /// No nodes, origin 0, default steps.
    fn default() -> Self {
        Self {
            origin: [0.0; 3],
            pos_step_m: DEFAULT_POSITION_STEP_M,
            vel_step_m_s: DEFAULT_VELOCITY_STEP_M_S,
            ids: Vec::new(),
            positions: Vec::new(),
            velocities: Vec::new(),
        }
    }
}

fn check_step(step: f64) -> Result<(), QuantError> {
    if step.is_finite() && step > 0.0 {
        Ok(())
    } else {
        Err(QuantError::BadStep(step))
    }
}

impl QuantisedNodes {
    /// Quantise with the default steps.
    pub fn encode_default(
        ids: &[u32],
        positions: &[[f64; 3]],
        velocities: &[[f64; 3]],
    ) -> Result<Self, QuantError> {
        Self::encode(
            ids,
            positions,
            velocities,
            DEFAULT_POSITION_STEP_M,
            DEFAULT_VELOCITY_STEP_M_S,
        )
    }

    /// Quantise nodes. The origin is the centre of the positions' bounding box, snapped to
    /// the step grid.
    pub fn encode(
        ids: &[u32],
        positions: &[[f64; 3]],
        velocities: &[[f64; 3]],
        pos_step_m: f64,
        vel_step_m_s: f64,
    ) -> Result<Self, QuantError> {
        check_step(pos_step_m)?;
        check_step(vel_step_m_s)?;
        if ids.len() != positions.len() || ids.len() != velocities.len() {
            return Err(QuantError::LengthMismatch {
                ids: ids.len(),
                positions: positions.len(),
                velocities: velocities.len(),
            });
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for (index, p) in positions.iter().enumerate() {
            for k in 0..3 {
                if !p[k].is_finite() {
                    return Err(QuantError::NonFinite {
                        index,
                        what: "position",
                    });
                }
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let mut origin = [0.0; 3];
        if !positions.is_empty() {
            for k in 0..3 {
                origin[k] = (0.5 * (lo[k] + hi[k]) / pos_step_m).round() * pos_step_m;
            }
        }
        let mut qp = Vec::with_capacity(positions.len());
        for (index, p) in positions.iter().enumerate() {
            let mut q = [0i32; 3];
            for k in 0..3 {
                q[k] =
                    quantise_scalar(p[k], origin[k], pos_step_m).ok_or(QuantError::OutOfRange {
                        index,
                        what: "position",
                        value: p[k],
                        step: pos_step_m,
                    })?;
            }
            qp.push(q);
        }
        let mut qv = Vec::with_capacity(velocities.len());
        for (index, v) in velocities.iter().enumerate() {
            let mut q = [0i32; 3];
            for k in 0..3 {
                if !v[k].is_finite() {
                    return Err(QuantError::NonFinite {
                        index,
                        what: "velocity",
                    });
                }
                q[k] = quantise_scalar(v[k], 0.0, vel_step_m_s).ok_or(QuantError::OutOfRange {
                    index,
                    what: "velocity",
                    value: v[k],
                    step: vel_step_m_s,
                })?;
            }
            qv.push(q);
        }
        Ok(Self {
            origin,
            pos_step_m,
            vel_step_m_s,
            ids: ids.to_vec(),
            positions: qp,
            velocities: qv,
        })
    }

    /// Number of nodes (the shortest of the three arrays, for robustness against
    /// inconsistent input from the wire; see [`Self::is_consistent`]).
    pub fn len(&self) -> usize {
        self.ids
            .len()
            .min(self.positions.len())
            .min(self.velocities.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True if all arrays have the same length and the steps are positive and finite.
    pub fn is_consistent(&self) -> bool {
        self.ids.len() == self.positions.len()
            && self.ids.len() == self.velocities.len()
            && check_step(self.pos_step_m).is_ok()
            && check_step(self.vel_step_m_s).is_ok()
            && self.origin.iter().all(|o| o.is_finite())
    }

    /// Dequantised position of node `i` (m).
    pub fn position(&self, i: usize) -> [f64; 3] {
        let q = self.positions[i];
        [0, 1, 2].map(|k| dequantise_scalar(q[k], self.origin[k], self.pos_step_m))
    }

    /// Dequantised velocity of node `i` (m/s).
    pub fn velocity(&self, i: usize) -> [f64; 3] {
        let q = self.velocities[i];
        [0, 1, 2].map(|k| dequantise_scalar(q[k], 0.0, self.vel_step_m_s))
    }

    /// Iterate `(id, position, velocity)` dequantised.
    pub fn iter(&self) -> impl Iterator<Item = (u32, [f64; 3], [f64; 3])> + '_ {
        (0..self.len()).map(|i| (self.ids[i], self.position(i), self.velocity(i)))
    }

    /// Maximum position error of this encoding (m): `pos_step_m / 2`.
    pub fn position_error_bound(&self) -> f64 {
        0.5 * self.pos_step_m
    }

    /// Maximum velocity error of this encoding (m/s): `vel_step_m_s / 2`.
    pub fn velocity_error_bound(&self) -> f64 {
        0.5 * self.vel_step_m_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tol(bound: f64, x: f64) -> f64 {
        bound * (1.0 + 1e-9) + x.abs() * 4.0 * f64::EPSILON
    }

    proptest! {
        #[test]
        fn position_and_velocity_within_half_step(
            nodes in prop::collection::vec(
                (any::<u32>(), prop::array::uniform3(-0.5f64..0.5), prop::array::uniform3(-5.0f64..5.0)),
                0..64),
            base in prop::array::uniform3(-2.0f64..2.0),
            pos_step in prop::sample::select(vec![1e-6, 1e-5, 2.5e-5, 1e-4]),
            vel_step in prop::sample::select(vec![1e-5, 1e-4, 1e-3]),
        ) {
            let ids: Vec<u32> = nodes.iter().map(|n| n.0).collect();
            let pos: Vec<[f64; 3]> = nodes.iter().map(|n| [0,1,2].map(|k| base[k] + n.1[k])).collect();
            let vel: Vec<[f64; 3]> = nodes.iter().map(|n| n.2).collect();
            let q = QuantisedNodes::encode(&ids, &pos, &vel, pos_step, vel_step).unwrap();
            prop_assert!(q.is_consistent());
            prop_assert_eq!(q.len(), ids.len());
            for (i, (id, p, v)) in q.iter().enumerate() {
                prop_assert_eq!(id, ids[i]);
                for k in 0..3 {
                    prop_assert!((p[k] - pos[i][k]).abs() <= tol(q.position_error_bound(), pos[i][k]),
                        "pos err {} > {}", (p[k] - pos[i][k]).abs(), q.position_error_bound());
                    prop_assert!((v[k] - vel[i][k]).abs() <= tol(q.velocity_error_bound(), vel[i][k]));
                }
            }
        }

        #[test]
        fn scalar_roundtrip_within_half_step(x in -1.0e3f64..1.0e3, origin in -1.0e3f64..1.0e3) {
            let step = 1e-5;
            let q = quantise_scalar(x, origin, step).unwrap();
            let y = dequantise_scalar(q, origin, step);
            prop_assert!((x - y).abs() <= 0.5 * step * (1.0 + 1e-6) + 1e-12);
        }
    }

    #[test]
    fn default_is_consistent() {
        assert!(QuantisedNodes::default().is_consistent());
        assert!(QuantisedNodes::default().is_empty());
    }

    #[test]
    fn default_steps_bound_is_five_micrometres() {
        let q = QuantisedNodes::encode_default(&[1], &[[0.1, 0.2, 0.3]], &[[0.0; 3]]).unwrap();
        assert_eq!(q.position_error_bound(), 5e-6);
        assert_eq!(q.velocity_error_bound(), 5e-5);
    }

    #[test]
    fn rejects_non_finite_and_out_of_range() {
        assert!(matches!(
            QuantisedNodes::encode_default(&[1], &[[f64::NAN, 0.0, 0.0]], &[[0.0; 3]]),
            Err(QuantError::NonFinite { .. })
        ));
        assert!(matches!(
            QuantisedNodes::encode_default(&[1, 2], &[[0.0; 3], [1e6, 0.0, 0.0]], &[[0.0; 3]; 2]),
            Err(QuantError::OutOfRange { .. })
        ));
        assert!(matches!(
            QuantisedNodes::encode_default(&[1], &[[0.0; 3]], &[[1e9, 0.0, 0.0]]),
            Err(QuantError::OutOfRange { .. })
        ));
        assert!(matches!(
            QuantisedNodes::encode(&[1], &[[0.0; 3]], &[[0.0; 3]], 0.0, 1.0),
            Err(QuantError::BadStep(_))
        ));
        assert!(matches!(
            QuantisedNodes::encode_default(&[1, 2], &[[0.0; 3]], &[[0.0; 3]]),
            Err(QuantError::LengthMismatch { .. })
        ));
    }
}
