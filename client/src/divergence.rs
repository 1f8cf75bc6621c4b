//! Divergence between sites, recomputed from their surface recordings.
//! PROVISIONAL until the sim-core surface recorder lands.

use anyhow::Result;

use crate::plot::Series;
use crate::site::SiteReport;

pub fn fill_divergence(_reports: &mut [SiteReport]) -> Result<Vec<Series>> {
    Ok(Vec::new())
}
