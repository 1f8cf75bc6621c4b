//! Force rendering of one haptic tick, without threads or clocks (sans-IO): local linear
//! model, guide force, clamp, safety fade, rate limit.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use sim_scene::ToolPose;

use super::latest::{Words, f, g};

/// What the simulation publishes for the haptic loop after each step.
#[derive(Debug, Clone, PartialEq)]
pub struct HapticModel {
    /// Simulation time of the step, s.
    pub sim_time: f64,
    /// The tool pose the step used (`x_s` is its position; the jaw is informative).
    pub tool_pose_at_sample: ToolPose,
    /// Force on the tool at the tip, N (scene frame): what the device should push.
    pub force: Vector3<f64>,
    /// Torque on the tool about the tip, N·m.
    pub torque: Vector3<f64>,
    /// `∂F/∂x` at the sample, N/m: the local linear model of the force around `x_s`.
    /// Negative semi-definite for contact (e.g. `−k·nnᵀ` for a penalty wall with normal n).
    pub stiffness: Matrix3<f64>,
    /// The tool grasps tissue: the model is bilateral (it may pull the tool).
    pub grasped: bool,
}

impl Default for HapticModel {
    fn default() -> Self {
        HapticModel {
            sim_time: 0.0,
            tool_pose_at_sample: ToolPose {
                position: Vector3::zeros(),
                orientation: UnitQuaternion::identity(),
                jaw: 0.0,
            },
            force: Vector3::zeros(),
            torque: Vector3::zeros(),
            stiffness: Matrix3::zeros(),
            grasped: false,
        }
    }
}

impl HapticModel {
    /// The local linear model at tip position `x`: `F_s + K (x − x_s)`, made unilateral
    /// when nothing is grasped (the component along `n = F_s/|F_s|` is kept ≥ 0: a contact
    /// pushes, it does not pull).
    pub fn force_at(&self, x: &Vector3<f64>) -> Vector3<f64> {
        let dx = x - self.tool_pose_at_sample.position;
        let mut f = self.force + self.stiffness * dx;
        if !self.grasped {
            let n2 = self.force.norm_squared();
            if n2 > 0.0 {
                let along = f.dot(&self.force) / n2; // in units of F_s
                if along < 0.0 {
                    f -= self.force * along;
                }
            }
        }
        f
    }
}

impl Words for HapticModel {
    const WORDS: usize = 25;
    fn to_words(&self, o: &mut [u64]) {
        let p = &self.tool_pose_at_sample;
        let q = p.orientation.quaternion();
        let vals = [
            self.sim_time,
            p.position.x,
            p.position.y,
            p.position.z,
            q.w,
            q.i,
            q.j,
            q.k,
            p.jaw,
            self.force.x,
            self.force.y,
            self.force.z,
            self.torque.x,
            self.torque.y,
            self.torque.z,
        ];
        for (o, v) in o.iter_mut().zip(vals) {
            *o = f(v);
        }
        for (o, v) in o[15..24].iter_mut().zip(self.stiffness.iter()) {
            *o = f(*v);
        }
        o[24] = u64::from(self.grasped);
    }
    fn from_words(w: &[u64]) -> Self {
        let v = |i: usize| g(w[i]);
        HapticModel {
            sim_time: v(0),
            tool_pose_at_sample: ToolPose {
                position: Vector3::new(v(1), v(2), v(3)),
                orientation: UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(
                    v(4),
                    v(5),
                    v(6),
                    v(7),
                )),
                jaw: v(8),
            },
            force: Vector3::new(v(9), v(10), v(11)),
            torque: Vector3::new(v(12), v(13), v(14)),
            stiffness: Matrix3::from_iterator((15..24).map(v)),
            grasped: w[24] != 0,
        }
    }
}

/// Limits and safety behaviour of the renderer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderConfig {
    /// Device force limit, N: `|F| ≤ max_force` always.
    pub max_force: f64,
    /// Device torque limit, N·m.
    pub max_torque: f64,
    /// Largest change of the force vector per second, N/s (`f64::INFINITY`: off).
    /// Applied per tick as `max_force_rate · period`.
    pub max_force_rate: f64,
    /// Time for the force to fade from full to zero when the device input is stale or the
    /// model is too old, s.
    pub fade_out: f64,
    /// Time for the force to fade back in once input is fresh again, s.
    pub fade_in: f64,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig {
            max_force: 3.0,
            max_torque: 0.2,
            max_force_rate: 1000.0,
            fade_out: 0.02,
            fade_in: 0.2,
        }
    }
}

/// The result of one tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rendered {
    /// Force sent to the device, N.
    pub force: Vector3<f64>,
    /// Torque sent to the device, N·m.
    pub torque: Vector3<f64>,
    /// The limit or the rate limit changed the force this tick.
    pub clamped: bool,
    /// The safety fade gain (1 = full force, 0 = none).
    pub gain: f64,
    /// The target was not finite and was replaced by zero.
    pub non_finite: bool,
}

/// Per-tick force rendering with state (previous force, fade gain).
#[derive(Debug, Clone)]
pub struct ForceRenderer {
    cfg: RenderConfig,
    period: f64,
    prev_force: Vector3<f64>,
    prev_torque: Vector3<f64>,
    gain: f64,
}

fn clamp_norm(v: Vector3<f64>, max: f64) -> (Vector3<f64>, bool) {
    let n = v.norm();
    if n > max {
        (v * (max / n), true)
    } else {
        (v, false)
    }
}

impl ForceRenderer {
    /// A renderer ticking every `period` seconds, starting at zero force and full gain.
    pub fn new(cfg: RenderConfig, period: f64) -> Self {
        ForceRenderer {
            cfg,
            period,
            prev_force: Vector3::zeros(),
            prev_torque: Vector3::zeros(),
            gain: 1.0,
        }
    }

    /// Sets the fade gain (e.g. 0 when a remote device has not sent anything yet).
    pub fn set_gain(&mut self, gain: f64) {
        self.gain = gain.clamp(0.0, 1.0);
    }

    /// One tick: `model` is the newest simulation model (if any), `x` the device tip
    /// position, `extra` an additional force (the teaching guide), `unsafe_input` true when
    /// the device input or the model is stale (fade out).
    pub fn tick(
        &mut self,
        model: Option<&HapticModel>,
        x: &Vector3<f64>,
        extra: Vector3<f64>,
        unsafe_input: bool,
    ) -> Rendered {
        let c = &self.cfg;
        let (mut target, mut torque) = match model {
            Some(m) => (m.force_at(x) + extra, m.torque),
            None => (extra, Vector3::zeros()),
        };
        let mut non_finite = false;
        if !target.iter().all(|v| v.is_finite()) {
            target = Vector3::zeros();
            non_finite = true;
        }
        if !torque.iter().all(|v| v.is_finite()) {
            torque = Vector3::zeros();
            non_finite = true;
        }
        let (target, c1) = clamp_norm(target, c.max_force);
        let (torque, c2) = clamp_norm(torque, c.max_torque);
        // Safety fade.
        if unsafe_input {
            let step = if c.fade_out > 0.0 {
                self.period / c.fade_out
            } else {
                1.0
            };
            self.gain = (self.gain - step).max(0.0);
        } else if self.gain < 1.0 {
            let step = if c.fade_in > 0.0 {
                self.period / c.fade_in
            } else {
                1.0
            };
            self.gain = (self.gain + step).min(1.0);
        }
        let target = target * self.gain;
        let torque = torque * self.gain;
        // Rate limit: the result lies on the segment prev → target, inside the ball.
        let max_step = c.max_force_rate * self.period;
        let (df, c3) = clamp_norm(target - self.prev_force, max_step);
        let force = if c3 { self.prev_force + df } else { target };
        // The torque may change as fast, relative to its limit, as the force.
        let torque_step = if c.max_force > 0.0 {
            max_step * c.max_torque / c.max_force
        } else {
            f64::INFINITY
        };
        let (dt, _) = clamp_norm(torque - self.prev_torque, torque_step);
        let torque = self.prev_torque + dt;
        self.prev_force = force;
        self.prev_torque = torque;
        Rendered {
            force,
            torque,
            clamped: c1 || c2 || c3,
            gain: self.gain,
            non_finite,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall(k: f64) -> HapticModel {
        // Penalty wall z ≤ 0 sampled with the tip 1 mm inside.
        let mut m = HapticModel::default();
        m.tool_pose_at_sample.position = Vector3::new(0.0, 0.0, -0.001);
        m.force = Vector3::new(0.0, 0.0, k * 0.001);
        m.stiffness = Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -k);
        m
    }

    #[test]
    fn words_roundtrip() {
        let mut m = wall(300.0);
        m.stiffness[(0, 1)] = 7.0;
        m.grasped = true;
        m.sim_time = 1.25;
        let mut w = vec![0; HapticModel::WORDS];
        m.to_words(&mut w);
        assert_eq!(HapticModel::from_words(&w), m);
    }

    #[test]
    fn linear_model_and_unilateral_contact() {
        let m = wall(300.0);
        // deeper: more force, exactly linear
        let f = m.force_at(&Vector3::new(0.01, 0.0, -0.002));
        assert!((f - Vector3::new(0.0, 0.0, 0.6)).norm() < 1e-12);
        // left the surface: the linear model would pull (−0.3 N); unilateral → 0
        let f = m.force_at(&Vector3::new(0.0, 0.0, 0.0005));
        assert!(f.norm() < 1e-12, "{f}");
        // grasped: bilateral
        let mut g = m.clone();
        g.grasped = true;
        let f = g.force_at(&Vector3::new(0.0, 0.0, 0.0005));
        assert!((f - Vector3::new(0.0, 0.0, -0.15)).norm() < 1e-12);
    }

    #[test]
    fn clamp_rate_limit_and_fade() {
        let cfg = RenderConfig {
            max_force: 2.0,
            max_torque: 0.1,
            max_force_rate: 500.0, // 0.5 N per 1 ms tick
            fade_out: 0.01,
            fade_in: 0.02,
        };
        let mut r = ForceRenderer::new(cfg, 0.001);
        let m = wall(10_000.0); // 10 N at the sample: over the limit
        let x = m.tool_pose_at_sample.position;
        let mut last = 0.0;
        for i in 0..10 {
            let out = r.tick(Some(&m), &x, Vector3::zeros(), false);
            assert!(out.force.norm() <= 2.0 + 1e-12);
            assert!(
                out.force.norm() - last <= 0.5 + 1e-12,
                "rate limit at tick {i}"
            );
            last = out.force.norm();
            assert!(out.clamped);
        }
        assert!((last - 2.0).abs() < 1e-12);
        // stale: fades to zero in fade_out / period = 10 ticks
        for _ in 0..10 {
            let out = r.tick(Some(&m), &x, Vector3::zeros(), true);
            last = out.force.norm();
        }
        assert!(last < 1e-12, "{last}");
        // fresh again: back in 20 ticks
        for _ in 0..19 {
            assert!(r.tick(Some(&m), &x, Vector3::zeros(), false).gain < 1.0);
        }
        assert_eq!(r.tick(Some(&m), &x, Vector3::zeros(), false).gain, 1.0);
        // NaN target → zero
        let mut bad = m.clone();
        bad.force.x = f64::NAN;
        let out = r.tick(Some(&bad), &x, Vector3::zeros(), false);
        assert!(out.non_finite && out.force.iter().all(|v| v.is_finite()));
    }
}
