//! The worker machine: a frame's queues, routing, the bundler, speculation groups, reports,
//! as a plain value driven by events (see `machine`). The process shell (`rayfarm-worker`)
//! turns gRPC messages and finished passes into [`Event`]s and carries out the [`Action`]s;
//! tests and the simulator drive the same value directly.
//!
//! Queue spilling: the queues are generic over a small store ([`RaySpill`]); the worker
//! binary's store writes local files, [`MemorySpill`] keeps them in memory. A trait rather
//! than spill and reload actions because a pass needs its rays the moment it is planned: a
//! round trip through the shell would split one decision into three events for no gain.

pub mod counters;
pub mod early;
pub mod events;
pub mod frame;
pub mod holder_map;
mod inbound;
mod machine;
mod outbound;
pub mod plan;
pub mod queues;
pub mod speculation;

pub use events::{Action, Event, OpenedScene, PassFailed, PassOutput, PassWork, Payload};
pub use machine::{Worker, WorkerConfig};
pub use plan::{Destination, HolderLine, Mode, Plan, Sorted};
pub use queues::{DomainQueues, MemorySpill, QueueError, RaySpill};
pub use speculation::Speculation;

#[cfg(test)]
mod tests;
