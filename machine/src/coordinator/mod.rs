//! The coordinator machine: jobs, workers, rounds, the tile ledger, job store records.
//!
//! `cluster::Coordinator` is the whole of it (registered workers, the job queue of `queue`,
//! job records, starting and finishing frames); inside it, the running frame (`frame`: its
//! members, their reports, the rounds of the dynamic schedule, tile dealing, losses and the
//! tile ledger), its life around the rounds (`frame::lifecycle`: admission, restart epochs,
//! judging accusations, the end), the judgement of workers' reports of unreachable peers
//! (`accusations`), which worker may send results of which tile (`grants`), what the
//! members were last told of the domains' holders (`holders`), and the hybrid schedule's
//! demand-driven tasks: which busy worker is asked to feed which idle one (`tasks`). The process
//! shell (`rayfarm-coordinator`) and the simulator feed it events and carry out its actions.
//! `synthetic` is a coordinator at scale in its steady state, for timing its rounds (the
//! simulator's calibration and this crate's `rounds` benchmark).

pub mod accusations;
pub mod cluster;
pub mod frame;
pub mod grants;
pub mod holders;
pub mod queue;
pub mod synthetic;
pub mod tasks;

pub use accusations::{Accusations, Verdict};
pub use cluster::Coordinator;
pub use frame::lifecycle::{ACCUSATION_GRACE, accusation_grace};
pub use frame::subframes::{job_of_frame, subframe_id};
pub use frame::{CommittedTile, FlushWork, Member, Outgoing, PlanningWork, Rounds, RunningFrame};
