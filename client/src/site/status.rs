//! The site's state as a renderer or HUD reads it: published by the driver every step.

use std::sync::{Arc, Mutex};

use crate::session::SessionSnapshot;

/// One step's view of a site.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SiteStatus {
    /// Simulated time (s) and steps taken.
    pub sim_time: f64,
    pub steps: u64,
    /// Site id, role, scene epoch, sites present, regions owned here and elsewhere.
    pub session: SessionSnapshot,
    /// Contact force on the local tool (N).
    pub tool_force_n: f64,
    /// Lag behind the sites followed at the last step (s), if following.
    pub behind_s: Option<f64>,
}

/// A shared cell holding the newest [`SiteStatus`]; cheap to clone, one writer (the site
/// thread), any number of readers.
#[derive(Debug, Clone, Default)]
pub struct StatusBoard(Arc<Mutex<SiteStatus>>);

impl StatusBoard {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn publish(&self, status: SiteStatus) {
        *self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = status;
    }

    pub fn read(&self) -> SiteStatus {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }
}
