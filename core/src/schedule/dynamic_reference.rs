//! Fig. 5 transcribed loop for loop, the way the paper states it: every question ("does anyone
//! hold this domain?", "who has the fewest planned domains?", "which domain has the most rays
//! per holder?") answered by scanning every worker and every domain. Quadratic in the cluster's
//! size, so the planner does not use it; the tests check that the planner's plans equal these.

use std::collections::BTreeSet;

use super::{ClusterState, DomainId, Options, RoundPlan, WorkerPlan};
use crate::schedule::WorkerState;

struct Draft<'a> {
    worker: &'a WorkerState,
    keep: BTreeSet<DomainId>,
    load: BTreeSet<DomainId>,
}

impl Draft<'_> {
    fn planned(&self) -> usize {
        self.keep.len() + self.load.len()
    }

    fn free_slots(&self) -> usize {
        self.worker.capacity - self.planned()
    }

    /// Whether a load now would evict: no slot of the cache is empty.
    fn evicts(&self) -> bool {
        self.worker.resident.len() + self.load.len() >= self.worker.capacity
    }

    fn works_on(&self, domain: DomainId) -> bool {
        self.keep.contains(&domain) || self.load.contains(&domain)
    }
}

/// The plan of [`super::next_round_with`], computed by scanning.
pub fn next_round_with(state: &ClusterState, options: Options) -> RoundPlan {
    let mut drafts: Vec<Draft<'_>> = state
        .workers()
        .iter()
        .map(|w| Draft {
            worker: w,
            keep: w
                .resident
                .iter()
                .copied()
                .filter(|&d| state.queued(d) > 0)
                .collect(),
            load: BTreeSet::new(),
        })
        .collect();
    let mut unheld: Vec<(DomainId, u64)> = state
        .wanted()
        .filter(|&(d, _)| !drafts.iter().any(|w| w.works_on(d)))
        .collect();
    unheld.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    for (domain, _) in unheld {
        let Some(draft) = drafts
            .iter_mut()
            .filter(|d| d.free_slots() > 0)
            .min_by_key(|d| (d.planned(), d.evicts()))
        else {
            break;
        };
        draft.load.insert(domain);
    }
    if options.replicate_onto_idle {
        for i in 0..drafts.len() {
            if drafts[i].planned() == 0
                && let Some(domain) = hottest(state, &drafts, options.copy_rays, |_| true)
            {
                drafts[i].load.insert(domain);
            }
        }
    }
    if options.fill_free_slots {
        loop {
            let mut placed = false;
            for i in 0..drafts.len() {
                if drafts[i].free_slots() == 0 {
                    continue;
                }
                let mine = &drafts[i];
                if let Some(domain) =
                    hottest(state, &drafts, options.copy_rays, |d| !mine.works_on(d))
                {
                    drafts[i].load.insert(domain);
                    placed = true;
                }
            }
            if !placed {
                break;
            }
        }
    }
    let workers = drafts
        .into_iter()
        .map(|d| {
            let by_use = &d.worker.by_use;
            let overflow = (by_use.len() + d.load.len()).saturating_sub(d.worker.capacity);
            let evict = by_use
                .iter()
                .copied()
                .filter(|r| !d.keep.contains(r))
                .take(overflow)
                .collect();
            WorkerPlan {
                worker: d.worker.id,
                keep: d.keep,
                load: d.load,
                evict,
            }
        })
        .collect();
    RoundPlan { workers }
}

/// The wanted domain with the most rays per holder among `eligible` ones (first maximum, so
/// the lower id on ties), if any has more rays than holders.
fn hottest(
    state: &ClusterState,
    drafts: &[Draft<'_>],
    copy_rays: u64,
    eligible: impl Fn(DomainId) -> bool,
) -> Option<DomainId> {
    let mut best: Option<(DomainId, u64, u64)> = None;
    for (domain, rays) in state.wanted().filter(|&(d, _)| eligible(d)) {
        let copies = drafts.iter().filter(|w| w.works_on(domain)).count() as u64;
        // Another copy must leave every holder at least `copy_rays` rays (at least one).
        if u128::from(rays) < u128::from(copy_rays.max(1)) * u128::from(copies + 1) {
            continue;
        }
        let beats = |&(_, r, c): &(DomainId, u64, u64)| {
            u128::from(rays) * u128::from(c) > u128::from(r) * u128::from(copies)
        };
        if best.as_ref().is_none_or(beats) {
            best = Some((domain, rays, copies));
        }
    }
    best.map(|(d, _, _)| d)
}
