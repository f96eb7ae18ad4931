//! The messages of `proto/rayfarm/v1` (the user API, the worker control stream, the peer bundle
//! stream) as plain prost types. They carry no gRPC runtime, so the coordinator and worker
//! machines, and the simulator that drives them, can exchange them without any I/O;
//! `rayfarm_node::proto` adds the tonic services over the same types.

#![allow(missing_docs, clippy::all, clippy::pedantic)]

include!(concat!(env!("OUT_DIR"), "/rayfarm.v1.rs"));

/// Version of the worker and peer protocols; a peer of another version is refused. 4: holders
/// named by worker key (`DomainHolders.workers`), demand-driven tasks (`ShareTasks`,
/// `TasksShared`, `StartFrame.hybrid_rounds`). 5: a holders delta names each changed domain's
/// gained and lost keys (`DomainHolders.workers`, `DomainHolders.lost`), not its whole list.
/// 6: the control tier, which no bundle used, retired (`Tier` 1 reserved); a bundle of tier 1
/// or of no tier is refused. 7: a whole map's domains with one holder each go packed
/// (`RoundPlan.sole_holders`), which an older worker would not read. 8: a frame's roster
/// comes in a `Roster` after the `StartFrame` (`StartFrame.roster` retired), which an older
/// worker would ignore. 9: a queue report after a frame's first names only the queues that
/// changed (`QueueReport.delta`), which an older coordinator would take as whole. 10: a
/// speculative copy's occluder or hit verdict names the copy's domain, where it named the
/// domain's place along the ray, which an older worker would misread.
pub const PROTOCOL_VERSION: u32 = 10;
