//! Time on the workers' cores: a pass's work at once on a worker's own cores or sliced on
//! the cores they share (`--cores`, `cores::SharedCores`), a message's handling taking its
//! share, and a finished pass handed to its worker's machine.

use std::time::Duration;

use rayfarm_machine::Time;
use rayfarm_machine::worker as machine;

use crate::cores::SharedCores;
use crate::cost::FinishedWork;
use crate::net::NodeId;

use super::{Ev, MeasuredFinished, World};

impl World<'_> {
    /// Computes `work` that can start at `ready` (not before now), then sets off `done`: at
    /// once on the worker's own cores, or on the cores every worker shares (`--cores`),
    /// sliced with whatever else wants them then (`cores::SharedCores`).
    pub(super) fn compute(&mut self, node: NodeId, ready: Time, work: Duration, done: Ev) {
        if self.cores.is_none() {
            return self.heap.push(ready + work, done);
        }
        let done = Box::new(done);
        self.heap.push(ready, Ev::Compute { node, work, done });
    }

    /// A wait of mean `mean` (a pass's for its tracing thread, a bundle's for the engine):
    /// drawn around it when a timing seed asks (`SimConfig::timing_seed`), else the mean.
    pub(super) fn wait(&mut self, mean: Duration) -> Duration {
        match &mut self.waits {
            Some(draws) if !mean.is_zero() => draws.exponential(mean),
            _ => mean,
        }
    }

    /// When handling a message, `work` that its shell takes up at `ready`, ends: on the
    /// worker's own cores after `work`; on shared cores at its share of them when it starts
    /// (longer when they are saturated, `SharedCores::handle`), taking that share from the
    /// computations while it runs.
    pub(super) fn steal(&mut self, ready: Time, work: Duration) -> Time {
        self.outcome.time.handling += work;
        let Some(cores) = self.cores.as_mut() else {
            return ready + work;
        };
        let end = cores.handle(self.now, ready, work);
        self.check_cores_again();
        end
    }

    /// Hands a finished pass to its worker's machine (timed, with `measure`).
    pub(super) fn take_pass(
        &mut self,
        node: NodeId,
        job_id: String,
        result: Result<machine::PassOutput, machine::PassFailed>,
    ) {
        let Some(w) = self.worker(node) else {
            return;
        };
        let resident = w.resident();
        let measured = match (&result, self.config.measure) {
            (Ok(out), true) => Some(FinishedWork::of(out)),
            _ => None,
        };
        self.feed(
            node,
            machine::Event::PassFinished {
                job_id,
                result,
                resident,
            },
        );
        if let (Some(work), Some(cpu_ns)) = (measured, self.handled_ns.take()) {
            self.outcome
                .measured_finished
                .push(MeasuredFinished { work, cpu_ns });
        }
    }

    /// Schedules the shared cores' next check (after every change to what they run).
    pub(super) fn check_cores_again(&mut self) {
        if let Some((at, epoch)) = self.cores.as_ref().and_then(SharedCores::next_check) {
            self.heap.push(at, Ev::CoresCheck { epoch });
        }
    }
}
