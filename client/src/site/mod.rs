//! One site: the simulation thread at a fixed rate, the local tool, the QUIC link and
//! the sync strategy. The network never blocks a step: the link is polled without
//! waiting, and a site with no link at all still simulates. The protocol state lives in
//! the sans-IO [`crate::session::SiteSession`]; [`run_site`] drives it, the simulation
//! and the link.

mod config;
pub mod recording;
mod runtime;
pub mod status;
pub mod tools;
pub mod view;

pub use crate::session::PlayoutLag;
pub use config::{ProgressCallback, SiteConfig, SiteReport};
pub use runtime::{RECORD_INTERVAL, run_site};
pub use status::{SiteStatus, StatusBoard};
pub use view::{SiteView, SiteViewer, ViewRequest};
