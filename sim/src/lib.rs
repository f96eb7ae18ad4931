//! `rayfarm sim`: a deterministic discrete-event simulation of a rayfarm cluster in one
//! process (issue 16). It runs N real worker machines (`rayfarm_machine::worker::Worker`) and
//! the real coordinator machine (`rayfarm_machine::coordinator::Coordinator`, which can crash
//! and restart from the records on its simulated disk) on virtual time; every pass is the real kernel (`rayfarm_machine::pass`) on the real scene, so
//! the image is the real image and its hash must equal `rayfarm render --local`'s.
//!
//! Why an event loop of our own rather than turmoil or NeXosim: the machines are sans-IO (they
//! take events with a time and return actions), so the simulator only needs a heap of timed
//! events and a model of links; turmoil simulates tokio sockets and would put the shells'
//! I/O back between the simulator and the machines, and NeXosim's models are asynchronous
//! actors that would wrap each machine for nothing. The loop here is a few hundred lines,
//! owns every source of order (one heap ordered by time then sequence number, per-link FIFO,
//! ordered maps) and so repeats bit for bit.
//!
//! Modules: [`events`] (the heap), [`net`] (links: latency, NIC bandwidth, FIFO, partitions),
//! [`cost`] (virtual time of passes and planning), [`cores`] (cores shared by every worker, sliced), [`storage`] (the shared storage loads read
//! from), [`calibrate`] (the cost model's prices measured here), [`faults`] (a seed's faults), [`node`] (a
//! simulated worker shell), [`coord`] (the simulated coordinator process and its disk), [`world`] (the
//! loop), [`check`] (the invariants after a run).

pub mod calibrate;
pub mod check;
pub mod coord;
pub mod cores;
pub mod cost;
pub mod events;
pub mod faults;
pub mod net;
pub mod node;
pub mod storage;
pub mod world;

pub use check::Violation;
pub use cost::{ComputeCost, CostModel};
pub use faults::{Fault, FaultPlan};
/// How long workers hold their reports for a plan's rays; the simulated coordinator takes the
/// coordinator's default (`ReportHold::DEFAULT`) unless told otherwise.
pub use rayfarm_machine::coordinator::cluster::ReportHold;
pub use storage::StorageModel;
pub use world::{FrameTime, Outcome, RECONNECT, SimConfig, default_max_events, simulate};
