//! Measuring the loop's rate and jitter on this machine.

use std::time::Duration;

use nalgebra::{Matrix3, Vector3};

use super::render::HapticModel;
use super::runner::{HapticConfig, spawn_with_model};
use super::scripted::ScriptedDevice;
use super::timing::HapticStats;
use super::{HapticDevice, HapticError};

/// A static contact model for measurements: a penalty wall `z ≤ 0` (k = 500 N/m) sampled
/// with the tip 2 mm inside.
pub(crate) fn wall_model() -> HapticModel {
    let mut m = HapticModel::default();
    m.tool_pose_at_sample.position = Vector3::new(0.0, 0.0, -0.002);
    m.force = Vector3::new(0.0, 0.0, 1.0);
    m.stiffness = Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, -500.0));
    m
}

/// Runs a haptic loop with the default configuration for `duration` against a local
/// stationary device in contact with a static wall model, and returns its statistics.
/// Whatever else runs meanwhile (e.g. the simulation thread) is the load being measured.
pub fn measure_loop(duration: Duration) -> HapticStats {
    let device = ScriptedDevice::at(Vector3::new(0.0, 0.0, -0.002)).with_record_limit(0);
    measure_loop_with(
        device,
        HapticConfig::default(),
        duration,
        Some(&wall_model()),
    )
    .map(|(_, s)| s)
    .expect("the default configuration is valid")
}

/// Runs a haptic loop with `device` and `config` for `duration` (with `model` published
/// before the first tick and republished every 10 ms) and returns the device and the
/// statistics.
pub fn measure_loop_with<D: HapticDevice + 'static>(
    device: D,
    config: HapticConfig,
    duration: Duration,
    model: Option<&HapticModel>,
) -> Result<(D, HapticStats), HapticError> {
    let handle = spawn_with_model(device, config, model)?;
    let start = std::time::Instant::now();
    // Republish the model every 10 ms like a simulation thread would (a model that is not
    // renewed goes stale after `model_timeout` and its force fades out).
    let mut model = model.cloned();
    while start.elapsed() < duration {
        std::thread::sleep((duration - start.elapsed()).min(Duration::from_millis(10)));
        if let Some(m) = model.as_mut() {
            m.sim_time += 0.01;
            handle.publish_model(m);
        }
    }
    Ok(handle.stop())
}
