//! The device seam: what the haptic loop reads from and writes to.

use std::time::Duration;

use nalgebra::{UnitQuaternion, Vector3};

use super::latest::{Words, f, g};

/// The tool as the haptic device holds it, sampled by the haptic loop. The simulation
/// thread reads the newest one (see [`InputReader`](super::InputReader)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolInput {
    /// Loop time of the sample (since the loop started).
    pub time: Duration,
    /// Tool tip position, m (scene frame).
    pub position: Vector3<f64>,
    /// Tool orientation (tool frame: shaft along local +z, tip at the origin).
    pub orientation: UnitQuaternion<f64>,
    /// Jaw opening angle, rad (0 = closed).
    pub jaw: f64,
    /// Device buttons, bit `i` = button `i` pressed.
    pub buttons: u32,
}

impl Default for ToolInput {
    fn default() -> Self {
        ToolInput {
            time: Duration::ZERO,
            position: Vector3::zeros(),
            orientation: UnitQuaternion::identity(),
            jaw: 0.0,
            buttons: 0,
        }
    }
}

impl Words for ToolInput {
    const WORDS: usize = 10;
    fn to_words(&self, o: &mut [u64]) {
        o[0] = self.time.as_nanos() as u64;
        o[1] = f(self.position.x);
        o[2] = f(self.position.y);
        o[3] = f(self.position.z);
        let q = self.orientation.quaternion();
        o[4] = f(q.w);
        o[5] = f(q.i);
        o[6] = f(q.j);
        o[7] = f(q.k);
        o[8] = f(self.jaw);
        o[9] = u64::from(self.buttons);
    }
    fn from_words(w: &[u64]) -> Self {
        ToolInput {
            time: Duration::from_nanos(w[0]),
            position: Vector3::new(g(w[1]), g(w[2]), g(w[3])),
            orientation: UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(
                g(w[4]),
                g(w[5]),
                g(w[6]),
                g(w[7]),
            )),
            jaw: g(w[8]),
            buttons: w[9] as u32,
        }
    }
}

/// A haptic device as the 1 kHz loop sees it. Both calls are made once per tick from the
/// haptic thread and must not block (no waiting on sockets, locks or files).
pub trait HapticDevice: Send {
    /// Samples the device at loop time `t` (since the loop started).
    fn read(&mut self, t: Duration) -> ToolInput;
    /// Commands a force (N, at the tool tip, scene frame) and torque (N·m).
    fn apply(&mut self, force: Vector3<f64>, torque: Vector3<f64>);
    /// A short name for logs and reports.
    fn name(&self) -> &str;
    /// `true` when the last [`read`](Self::read) returned no fresh data from the device
    /// (e.g. no datagram for longer than the bridge's stale timeout): the loop then fades
    /// its force to zero. Local devices are never stale.
    fn input_stale(&self) -> bool {
        false
    }
}

impl<D: HapticDevice + ?Sized> HapticDevice for Box<D> {
    fn read(&mut self, t: Duration) -> ToolInput {
        (**self).read(t)
    }
    fn apply(&mut self, force: Vector3<f64>, torque: Vector3<f64>) {
        (**self).apply(force, torque)
    }
    fn name(&self) -> &str {
        (**self).name()
    }
    fn input_stale(&self) -> bool {
        (**self).input_stale()
    }
}
