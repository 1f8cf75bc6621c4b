//! Test support shared by the packages' integration tests; not part of any product crate.
//!
//! * [`link`] — a bare site client: connect, join, frames, datagrams, streams;
//! * [`exe`] — locating a sibling executable that another package builds (`cosurg-server`
//!   for the tests of the `cosurg` binary);
//! * [`run`] — a command run to its end within a time limit, its JSON summary;
//! * [`server`] — a `cosurg-server` child process and its announcements;
//! * [`xvfb`] — a virtual X display for the window tests.

pub mod exe;
pub mod link;
pub mod run;
pub mod server;
pub mod xvfb;
