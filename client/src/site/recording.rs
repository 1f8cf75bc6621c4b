//! The site's surface recordings (sim-core's `.surf` format).

use std::path::Path;

use anyhow::{Context, Result};
use sim_core::Simulation;
use sim_core::sync;

/// Surface recordings at fixed simulated-time marks (sim-core's `.surf` format).
pub struct Recorder(sync::SurfaceRecorder);

impl Recorder {
    pub fn new(sim: &Simulation, interval: f64) -> Self {
        Recorder(sync::SurfaceRecorder::new(sim, interval))
    }
    pub fn record(&mut self, sim: &Simulation) {
        self.0.record(sim);
    }
    pub fn write(&self, path: &Path) -> Result<()> {
        let file =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        self.0
            .recording()
            .write_to(std::io::BufWriter::new(file))
            .with_context(|| format!("writing {}", path.display()))
    }
}
