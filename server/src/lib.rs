//! cosurg coordinator: the QUIC endpoint that relays simulation clocks and state deltas
//! between sites, arbitrates region ownership and keeps the latest keyframes for late joiners.
//!
//! * [`session`] — the session logic, sans IO (joins, roles, relay decisions, ownership);
//! * [`coordinator`] — the async shell: [`Coordinator::bind`] → ([`CoordinatorHandle`], address);
//! * [`tls`] — certificates, fingerprints, QUIC/TLS configs for both sides
//!   ([`tls::client_config_pinned`], [`tls::client_config_ca`]);
//! * [`link`] — site-side helpers: connect, join, frames, datagrams, streams;
//! * [`cli`] — the `cosurg-server` command line ([`cli::main`]).

pub mod cli;
pub mod clock;
pub mod coordinator;
pub mod link;
pub mod session;
mod stats;
pub mod tls;

pub use coordinator::{
    Coordinator, CoordinatorConfig, CoordinatorHandle, CoordinatorStats, ServerError, WallClock,
};
pub use proto;
