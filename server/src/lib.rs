//! cosurg coordinator: the QUIC endpoint that relays simulation clocks and state deltas
//! between sites, arbitrates region ownership and keeps the latest keyframes for late joiners.
//!
//! * [`sessions`] — the sessions hosted (sessions file, persistence in the state directory);
//! * [`metrics`] — Prometheus metrics over HTTP (`--metrics`);
//! * [`session`] — the session logic, sans IO (joins, roles, relay decisions, ownership);
//! * [`coordinator`] — the async shell: [`Coordinator::bind`] → ([`CoordinatorHandle`], address);
//! * [`state`] — the state directory: invitation key, revocations ([`state::mint`]);
//! * [`ratelimit`] — failed joins per source address;
//! * [`recording`] — the coordinator's session recording (`--record DIR`);
//! * [`admin`] — `cosurg invite`: mint an invitation through a running coordinator;
//! * [`tls`] — certificates, fingerprints, QUIC/TLS configs for both sides
//!   ([`tls::client_config_pinned`], [`tls::client_config_ca`]);
//! * [`cli`] — the `cosurg-server` command line ([`cli::main`]); the binary is `src/main.rs`.

pub mod admin;
pub mod admission;
pub mod cli;
pub mod clock;
pub mod coordinator;
pub mod metrics;
pub mod ratelimit;
pub mod recording;
pub mod session;
pub mod sessions;
pub mod state;
mod stats;
pub mod tls;

pub use coordinator::{
    Coordinator, CoordinatorConfig, CoordinatorHandle, CoordinatorStats, ServerError, SessionClock,
    TimeScale, WallClock,
};
pub use proto;
