//! One site: the simulation thread at a fixed rate, the local tool, the QUIC link and
//! the sync strategy. The network never blocks a step: the link is polled without
//! waiting, and a site with no link at all still simulates.

pub mod glue;
mod haptics;
pub mod pacing;
mod runtime;

pub use pacing::PlayoutLag;
pub use runtime::{SiteConfig, SiteReport, Strategy, run_site};
