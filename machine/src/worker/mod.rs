//! The worker machine: a frame's queues, routing, the bundler, speculation groups, reports.
//!
//! Landed so far: the round's plan and the routing it implies (`plan`), and the predictive
//! schedule's speculation groups with verdict addressing (`speculation`). The process shell
//! (`rayfarm-worker`) holds them in its frame and executes what they decide.

pub mod plan;
pub mod speculation;

pub use plan::{Destination, Mode, Plan, Sorted};
pub use speculation::Speculation;
