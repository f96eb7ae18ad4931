//! Pure scheduling policies: functions from cluster state to decisions.
//!
//! Nothing in here performs I/O, reads a clock or draws random numbers, so the
//! same code can run in the coordinator, in unit tests and in a simulator and
//! always give the same answer for the same input.
//!
//! The policies follow Navrátil et al., "Dynamic Ray Scheduling to Improve Ray
//! Coherence and Bandwidth Utilization" (EGPGV 2012):
//! - [`static_plans`]: the image-plane and domain decompositions (Figs. 3-4);
//! - [`dynamic`]: the ray-weighted schedule, `ScheduleNextRound` (Figs. 5-6);
//! - [`speculative`]: the queue order for speculatively placed rays (Park et al.);
//! - [`speculation_depth`]: how many domains ahead a speculative ray is copied (Park et al.);
//! - [`rounds`]: when members are planned (barrier or asynchronous rounds) and from what;
//! - [`round_index`]: the same asynchronous rounds planned incrementally, from figures kept
//!   up to date report by report;
//! - [`tiles`]: dealing tiles to workers, in fixed shares or on demand;
//! - [`synthetic`]: a synthetic cluster at the papers' scale, for measuring planning.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

pub mod dynamic;
pub mod round_index;
pub mod rounds;
pub mod speculation_depth;
pub mod speculative;
pub mod static_plans;
pub mod synthetic;
pub mod tiles;

/// Identifies one spatial domain (a brick of scene data loaded as a unit).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct DomainId(pub u32);

/// Identifies one worker (the paper's "process").
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WorkerId(pub u32);

impl fmt::Display for DomainId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "domain {}", self.0)
    }
}

impl fmt::Display for WorkerId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "worker {}", self.0)
    }
}

/// What one worker reported at a round boundary.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WorkerState {
    /// The reporting worker.
    pub id: WorkerId,
    /// Domains currently in the worker's cache.
    pub resident: BTreeSet<DomainId>,
    /// The same domains, least recently used first: the order in which a load evicts those
    /// no ray wants ([`dynamic`]).
    pub by_use: Vec<DomainId>,
    /// How many domains the cache can hold at once; at least 1 (the paper's
    /// processes hold exactly one).
    pub capacity: usize,
}

impl WorkerState {
    /// A worker with the given resident domains, least recently used first (a domain named
    /// twice counts where it is first named), and cache capacity.
    pub fn new(
        id: WorkerId,
        resident: impl IntoIterator<Item = DomainId>,
        capacity: usize,
    ) -> Self {
        let mut by_use: Vec<DomainId> = resident.into_iter().collect();
        // Built whole (sorted, then in bulk): a whole-cluster round makes one for every member.
        let resident: BTreeSet<DomainId> = by_use.iter().copied().collect();
        if resident.len() < by_use.len() {
            keep_first_of_each(&mut by_use);
        }
        Self {
            id,
            resident,
            by_use,
            capacity,
        }
    }
}

/// Drops every repeat from `list`, each value kept where it is first named: a worker lists its
/// resident domains least recently used first, and a repeat (a faulty list) must not move a
/// domain's place. Callers check for repeats their own cheap way first; this is the rule.
pub fn keep_first_of_each<T: Ord + Copy>(list: &mut Vec<T>) {
    let mut seen = BTreeSet::new();
    list.retain(|&x| seen.insert(x));
}

/// Why a reported cluster state cannot be scheduled.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StateError {
    /// A worker reported a cache that holds no domain at all.
    ZeroCapacity(WorkerId),
    /// A worker reported more resident domains than its cache holds.
    OverCapacity(WorkerId),
    /// Two reports carried the same worker id.
    DuplicateWorker(WorkerId),
}

impl fmt::Display for StateError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::ZeroCapacity(w) => write!(f, "{w} reports a cache capacity of zero"),
            Self::OverCapacity(w) => write!(f, "{w} reports more resident domains than it holds"),
            Self::DuplicateWorker(w) => write!(f, "{w} reported twice"),
        }
    }
}

impl std::error::Error for StateError {}

/// The cluster as the coordinator sees it at a round boundary.
///
/// Workers are kept sorted by id so that the order in which reports arrived
/// can never change a decision.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClusterState {
    workers: Vec<WorkerState>,
    queued: BTreeMap<DomainId, u64>,
}

impl ClusterState {
    /// Builds a state from worker reports and the global number of rays
    /// queued per domain (summed over all workers; absent means zero).
    ///
    /// Rejects reports the schedule could not honour, rather than letting a
    /// policy silently overfill a cache.
    pub fn new(
        workers: impl IntoIterator<Item = WorkerState>,
        queued: impl IntoIterator<Item = (DomainId, u64)>,
    ) -> Result<Self, StateError> {
        let mut workers: Vec<WorkerState> = workers.into_iter().collect();
        workers.sort_by_key(|w| w.id);
        validate_workers(&workers)?;
        let mut totals = BTreeMap::new();
        for (domain, rays) in queued {
            *totals.entry(domain).or_insert(0u64) += rays;
        }
        totals.retain(|_, rays| *rays > 0);
        Ok(Self {
            workers,
            queued: totals,
        })
    }

    /// Worker reports, ordered by worker id.
    pub fn workers(&self) -> &[WorkerState] {
        &self.workers
    }

    /// Rays queued for `domain` across the whole cluster.
    pub fn queued(&self, domain: DomainId) -> u64 {
        self.queued.get(&domain).copied().unwrap_or(0)
    }

    /// Domains with at least one queued ray, with their ray counts, by id.
    pub fn wanted(&self) -> impl Iterator<Item = (DomainId, u64)> + '_ {
        self.queued.iter().map(|(&d, &n)| (d, n))
    }

    /// Whether any ray is still queued anywhere (the paper's
    /// `NoProcessHasRays`, negated).
    pub fn has_rays(&self) -> bool {
        !self.queued.is_empty()
    }
}

fn validate_workers(workers: &[WorkerState]) -> Result<(), StateError> {
    for pair in workers.windows(2) {
        if pair[0].id == pair[1].id {
            return Err(StateError::DuplicateWorker(pair[0].id));
        }
    }
    for w in workers {
        if w.capacity == 0 {
            return Err(StateError::ZeroCapacity(w.id));
        }
        if w.resident.len() > w.capacity {
            return Err(StateError::OverCapacity(w.id));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn worker(id: u32, resident: &[u32], capacity: usize) -> WorkerState {
        WorkerState::new(
            WorkerId(id),
            resident.iter().map(|&d| DomainId(d)),
            capacity,
        )
    }

    #[test]
    fn a_repeated_resident_domain_keeps_its_first_place_in_the_order_of_use() {
        let mut by_use = vec![3, 1, 3, 2, 1];
        keep_first_of_each(&mut by_use);
        assert_eq!(by_use, [3, 1, 2]);
        let w = worker(0, &[3, 1, 3, 2], 4);
        assert_eq!(w.by_use, [DomainId(3), DomainId(1), DomainId(2)]);
        assert_eq!(w.resident.len(), 3);
    }

    #[test]
    fn state_sorts_workers_and_drops_empty_queues() {
        let state = ClusterState::new(
            [worker(2, &[], 1), worker(0, &[], 1)],
            [(DomainId(1), 0), (DomainId(3), 4), (DomainId(3), 1)],
        )
        .unwrap();
        let ids: Vec<_> = state.workers().iter().map(|w| w.id.0).collect();
        assert_eq!(ids, [0, 2]);
        assert_eq!(state.wanted().collect::<Vec<_>>(), [(DomainId(3), 5)]);
        assert_eq!(state.queued(DomainId(1)), 0);
    }

    #[test]
    fn state_rejects_impossible_reports() {
        let err = |ws: Vec<WorkerState>| ClusterState::new(ws, []).unwrap_err();
        assert_eq!(
            err(vec![worker(1, &[], 0)]),
            StateError::ZeroCapacity(WorkerId(1))
        );
        assert_eq!(
            err(vec![worker(1, &[0, 1], 1)]),
            StateError::OverCapacity(WorkerId(1))
        );
        assert_eq!(
            err(vec![worker(1, &[], 1), worker(1, &[], 1)]),
            StateError::DuplicateWorker(WorkerId(1))
        );
    }
}
