//! The coordinator and the worker as state machines without I/O (issue 16), in the manner of
//! quinn-proto: each is a plain value that takes events (a message received, a timer fired, a
//! pass finished, a domain loaded, a link lost; time comes in with the event) and returns
//! actions (send this message to that node, start a pass, load a domain, persist a record, set
//! a timer). They own no socket, clock, thread or file, so the process shells
//! (`rayfarm-coordinator`, `rayfarm-worker`) and the deterministic simulator drive the same
//! code.

pub mod coordinator;
pub mod pass;
pub mod queue_report;
pub mod time;
pub mod worker;

pub use time::Time;
