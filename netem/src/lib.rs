//! Network impairment for cosurg: a seeded, sans-IO per-direction model ([`model`]), a
//! user-space UDP relay that applies it ([`relay`], the `cosurg netem` subcommand, whose clap
//! arguments are [`NetemArgs`]), and an in-process impaired socket for quinn ([`socket`]).
//!
//! This machine's kernel has no `tc netem`, so impairment happens in user space.
//!
//! **Delays are one-way, per direction.** A preset applied to both directions of a link has
//! an RTT of twice its delay (e.g. `poor`: 200 ms ± 30 one-way, ≈ 400 ms RTT, 10 % loss each
//! way). See [`ImpairmentConfig::preset`] for the table.
//!
//! *Up* means client → server (relay: client → upstream; impaired socket: outgoing), *down*
//! the reverse.

pub mod args;
pub mod model;
pub mod relay;
mod sched;
pub mod socket;

pub use args::{Direction, ImpairArgs, NetemArgs};
pub use model::{
    BURST_P_BG, BURST_P_GB, ConfigError, Counters, DropReason, GilbertElliott, Impairment,
    ImpairmentConfig, JitterDist, OUTAGE_DURATION_S, OUTAGE_START_S, Outage, PRESET_NAMES, Verdict,
};
pub use relay::{Relay, RelayConfig, RelayCounters, RelayHandle, run_cli};
pub use sched::DirectionStats;
pub use socket::{ImpairedLink, ImpairedSocket, LinkCounters, impaired_endpoint};
