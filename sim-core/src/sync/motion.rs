//! The motion model shared by owner and receiver: second-order extrapolation of every
//! node from a region's last keyframe (DIS "FVW" dead reckoning, see the module docs of
//! [`super`]). The owner runs the same model as its receivers to decide when to send.

use std::collections::HashMap;

use sim_lattice::{Lattice, NodeId};

use super::{Grid, RegionKeyframe, V3};

/// Second-order motion of one node from a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Motion {
    pub(super) x: V3,
    pub(super) v: V3,
    pub(super) a: V3,
    pub(super) t0: f64,
}

impl Motion {
    pub(super) fn eval(&self, t: f64, horizon: f64) -> (V3, V3) {
        let d = (t - self.t0).clamp(-horizon, horizon);
        (
            self.x + self.v * d + 0.5 * self.a * (d * d),
            self.v + self.a * d,
        )
    }

    fn average(a: &Motion, b: &Motion) -> Motion {
        Motion {
            x: 0.5 * (a.x + b.x),
            v: 0.5 * (a.v + b.v),
            a: 0.5 * (a.a + b.a),
            t0: a.t0.max(b.t0),
        }
    }
}

/// Node motions of a region from its keyframes, by grid coordinate.
#[derive(Clone, Debug, Default)]
pub(super) struct MotionSet {
    pub(super) motions: HashMap<Grid, Motion>,
    /// Velocities and time of the latest keyframe (for the next acceleration estimate).
    last_velocities: HashMap<Grid, V3>,
    last_time: Option<f64>,
}

impl MotionSet {
    /// Takes a keyframe (canonical grids and states) as the new motion.
    pub(super) fn take_keyframe(&mut self, grids: &[Grid], kf: &RegionKeyframe, max_accel: f64) {
        let dt = self.last_time.map(|t| kf.sim_time - t);
        let mut motions = HashMap::with_capacity(grids.len());
        let mut velocities = HashMap::with_capacity(grids.len());
        for (i, g) in grids.iter().enumerate() {
            let x = V3::from(kf.positions[i]);
            let v = V3::from(kf.velocities[i]);
            let mut a = match (dt, self.last_velocities.get(g)) {
                (Some(dt), Some(v0)) if dt > 1e-9 => (v - v0) / dt,
                _ => V3::zeros(),
            };
            let n = a.norm();
            if n.is_nan() || n > max_accel {
                a = if n.is_finite() {
                    a * (max_accel / n)
                } else {
                    V3::zeros()
                };
            }
            motions.insert(
                *g,
                Motion {
                    x,
                    v,
                    a,
                    t0: kf.sim_time,
                },
            );
            velocities.insert(*g, v);
        }
        self.motions = motions;
        self.last_velocities = velocities;
        self.last_time = Some(kf.sim_time);
    }

    /// The motion of a node, derived for nodes created since the keyframe from the motions
    /// of the edge they split (recursively), the same way on owner and receiver.
    pub(super) fn motion(&mut self, lattice: &Lattice, n: NodeId) -> Option<Motion> {
        let g = lattice.node_grid(n);
        if let Some(m) = self.motions.get(&g) {
            return Some(*m);
        }
        let (a, b) = lattice.node_parent_edge(n)?;
        let ma = self.motion(lattice, a)?;
        let mb = self.motion(lattice, b)?;
        let m = Motion::average(&ma, &mb);
        self.motions.insert(g, m);
        Some(m)
    }
}
