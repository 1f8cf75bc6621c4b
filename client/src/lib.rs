//! The cosurg site: simulation thread, haptic loop, tools, QUIC link to the coordinator,
//! and the commands of the `cosurg` command line (see `main.rs`).

pub mod bench;
pub mod cli;
pub mod demo;
pub mod divergence;
pub mod haptic;
pub mod join;
pub mod link;
pub mod output;
pub mod plot;
pub mod run;
pub mod scene_arg;
pub mod session;
pub mod site;
pub mod solve;
pub mod stats;
