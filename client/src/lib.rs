//! The cosurg site: simulation thread, haptic loop, tools, QUIC link to the coordinator,
//! and the product's commands of the `cosurg` command line (the binary and `cosurg bench`
//! live in the packages cosurg-cli and cosurg-bench).

pub mod cli;
pub mod demo;
pub mod divergence;
pub mod haptic;
pub mod invite;
pub mod join;
pub mod link;
pub mod output;
pub mod plot;
pub mod record;
pub mod replay;
pub mod run;
pub mod run_window;
pub mod scene_arg;
pub mod score;
pub mod session;
pub mod site;
pub mod solve;
pub mod stats;
