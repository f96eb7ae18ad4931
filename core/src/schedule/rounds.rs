//! The dynamic schedule's rounds as the coordinator runs them: which members are planned and
//! when, from what figures. Barrier rounds plan everyone once all have reported; asynchronous
//! rounds plan each member the moment it runs dry, from the latest reports of all. Under the
//! predictive schedule only the oldest generation's queues count (`speculative`), unless no
//! one is busy and that generation cannot move on: then everything queued is planned, or a
//! generation whose last copies are on the wire or lost would stall the frame. An asynchronous
//! plan names every domain its member holds and does not evict, wanted or not, so a domain
//! whose rays ran out keeps its holders (`naming_resident`). Pure: the coordinator turns the
//! plans into messages.

use super::dynamic::{Options, RoundPlan, WorkerPlan, next_round_with};
use super::speculative::oldest_generation;
use super::{ClusterState, DomainId, WorkerId, WorkerState};
use std::collections::{BTreeMap, BTreeSet};

/// A member's latest queue report, as the rounds see it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Queues {
    /// The round of the plan it had when it reported.
    pub round: u64,
    /// Domains in its memory, least recently used first, each once (the coordinator drops a
    /// repeat as it takes a report in): a load evicts those no ray wants in this order.
    pub resident: Vec<u32>,
    /// Rays it holds per domain.
    pub queued: BTreeMap<u32, u64>,
    /// The oldest generation among those rays, per domain.
    pub oldest_generation: BTreeMap<u32, u32>,
    /// The oldest generation of rays it holds that wait on something other than a domain.
    pub oldest_waiting: Option<u32>,
}

/// Dry member `m`'s new plan `p` naming, besides the domains it works on, every other domain
/// of the scene's `domains` it holds and does not evict. Fig. 5 plans a member to keep only
/// the resident domains with rays; one whose rays ran out then lost its holder in the map and
/// every ray that entered it later waited at its sender for a report and a round to plan a
/// member holding it to keep it: a report, two plans and two changes of the holders map for
/// every return of rays (README "Simulator"). Named, the domain keeps its holders, and such a
/// ray is sent to one of them directly. The pairing of Fig. 5 is unchanged: an unwanted
/// domain's slot is still free for a load, which evicts it.
fn naming_resident(mut p: WorkerPlan, m: &Member, domains: u32) -> WorkerPlan {
    let resident = m.report.iter().flat_map(|r| r.resident.iter().copied());
    for d in resident.filter(|&d| d < domains).map(DomainId) {
        if !p.evict.contains(&d) && !p.load.contains(&d) {
            p.keep.insert(d);
        }
    }
    p
}

/// Whether `p`, a new plan for dry member `m` (`naming_resident`), is sent to it: it loads or
/// evicts, works on a domain `m`'s plan does not name, or `m`'s plan names a domain `m` does
/// not hold.
fn is_news(p: &WorkerPlan, m: &Member) -> bool {
    let held = |d: &u32| m.report.as_ref().is_some_and(|r| r.resident.contains(d));
    !p.load.is_empty()
        || !p.evict.is_empty()
        || p.work().any(|d| !m.plan.contains(&d.0))
        || !m.plan.iter().all(held)
}

/// Fig. 5's plan `p` for dry member `m` in a scene of `domains` domains as it is sent
/// (`naming_resident`), or `None` if it would not change what `m` does (`is_news`): the one
/// rule of both planners, `Cluster::dry_plans` and `RoundIndex::dry_plans`.
pub fn sent_plan(p: WorkerPlan, m: &Member, domains: u32) -> Option<WorkerPlan> {
    let p = naming_resident(p, m, domains);
    is_news(&p, m).then_some(p)
}

/// What the rounds know of one member of the frame.
#[derive(Clone, Debug, Default)]
pub struct Member {
    /// Its cache size: how many domains it can hold.
    pub cache_bytes: u64,
    /// Its latest report for this frame.
    pub report: Option<Queues>,
    /// Domains of its current plan (asynchronous rounds).
    pub plan: BTreeSet<u32>,
    /// Round of its current plan: a report of that round or later means it has run dry.
    pub planned_round: u64,
}

impl Member {
    /// A member with a cache of `cache_bytes` that has not reported yet.
    pub fn new(cache_bytes: u64) -> Self {
        Member {
            cache_bytes,
            ..Member::default()
        }
    }

    /// Whether it has run out of work since its last plan.
    pub fn is_dry(&self) -> bool {
        self.report
            .as_ref()
            .is_some_and(|r| r.round >= self.planned_round)
    }
}

// A coordinator keeps more about a member than the rounds need (its address, its figures): it
// holds a `Member` inside its own type and lends it out through these.
impl AsRef<Member> for Member {
    fn as_ref(&self) -> &Member {
        self
    }
}

impl AsMut<Member> for Member {
    fn as_mut(&mut self) -> &mut Member {
        self
    }
}

/// The members of a frame by key (anything that holds a [`Member`]), and the scene's domain
/// sizes.
pub struct Cluster<'a, M = Member> {
    /// Members by the coordinator's key.
    pub members: &'a BTreeMap<u32, M>,
    /// Bytes of each domain.
    pub domain_bytes: &'a [u64],
    /// Whether the oldest-generation rule applies (the predictive schedule).
    pub oldest_first: bool,
    /// The schedule's options.
    pub options: Options,
}

impl<M: AsRef<Member>> Cluster<'_, M> {
    /// Barrier rounds: the plan of round `round + 1` once every member has reported round
    /// `round`, with the number of domains wanted; `None` while someone is still working or
    /// when no ray is queued anywhere (rays or results are on the wire: a member reports
    /// again when they land).
    pub fn barrier_round(&self, round: u64) -> Option<(RoundPlan, usize)> {
        let all_in = self
            .each_member()
            .all(|(_, m)| m.report.as_ref().is_some_and(|r| r.round >= round));
        if !all_in {
            return None;
        }
        let none_busy = BTreeSet::new();
        let mut state = self.state(&none_busy, self.oldest_first)?;
        if !state.has_rays() {
            // Everyone has reported, so plan the younger rays.
            state = self.state(&none_busy, false)?;
        }
        if !state.has_rays() {
            return None;
        }
        Some((
            next_round_with(&state, self.options),
            state.wanted().count(),
        ))
    }

    /// Asynchronous rounds: new plans for the members that have run dry. Busy members keep
    /// theirs: the schedule sees them holding exactly what they work on, with no free slot.
    /// Each plan names every resident domain not evicted; a dry member whose plan would not
    /// change is left out (`sent_plan`; its rays are elsewhere or on the wire; its next report
    /// plans it again).
    pub fn dry_plans(&self) -> Vec<WorkerPlan> {
        let dry: BTreeSet<u32> = self
            .each_member()
            .filter(|(_, m)| m.is_dry())
            .map(|(k, _)| k)
            .collect();
        if dry.is_empty() {
            return Vec::new();
        }
        let busy: BTreeSet<u32> = self
            .members
            .keys()
            .copied()
            .filter(|k| !dry.contains(k))
            .collect();
        // With no one busy, a generation that cannot move on must not stall the frame.
        let filters: &[bool] = match (self.oldest_first, busy.is_empty()) {
            (false, _) => &[false],
            (true, true) => &[true, false],
            (true, false) => &[true],
        };
        for &oldest_first in filters {
            let Some(state) = self.state(&busy, oldest_first) else {
                return Vec::new();
            };
            if !state.has_rays() {
                continue;
            }
            let changed: Vec<WorkerPlan> = next_round_with(&state, self.options)
                .workers()
                .iter()
                .filter(|p| dry.contains(&p.worker.0))
                .filter_map(|p| {
                    let m = self.members[&p.worker.0].as_ref();
                    sent_plan(p.clone(), m, self.domain_bytes.len() as u32)
                })
                .collect();
            if !changed.is_empty() {
                return changed;
            }
        }
        Vec::new()
    }

    /// The cluster as the schedule sees it, from the latest reports. Members in `busy` are
    /// planned already and not re-planned now: they hold their plan and what they reported
    /// resident, with no slot to spare. Members that have not reported take no part. With
    /// `oldest_first` only queues holding the oldest generation still being traced count, or
    /// whose domain is in memory somewhere (they cost no load, and counting them keeps the
    /// domain for them rather than evicting it and loading it again a generation later).
    pub fn state(&self, busy: &BTreeSet<u32>, oldest_first: bool) -> Option<ClusterState> {
        let domains = self.domain_bytes.len() as u32;
        let reports = || self.each_member().filter_map(|(_, m)| m.report.as_ref());
        let oldest = oldest_first
            .then(|| {
                oldest_generation(reports().flat_map(|r| {
                    r.oldest_generation
                        .values()
                        .copied()
                        .chain(r.oldest_waiting)
                }))
            })
            .flatten();
        let in_memory: BTreeSet<u32> = self
            .each_member()
            .flat_map(|(_, m)| {
                let resident = m.report.iter().flat_map(|r| r.resident.iter());
                resident.chain(m.plan.iter()).copied()
            })
            .collect();
        let counts = |r: &Queues, d: &u32| {
            oldest.is_none_or(|g| r.oldest_generation.get(d) == Some(&g) || in_memory.contains(d))
        };
        let largest = self.domain_bytes.iter().copied().max().unwrap_or(1).max(1);
        let mut queued: BTreeMap<DomainId, u64> = BTreeMap::new();
        for (_, m) in self.each_member() {
            let Some(report) = m.report.as_ref() else {
                continue;
            };
            for (&d, &n) in &report.queued {
                if d < domains && counts(report, &d) && n > 0 {
                    *queued.entry(DomainId(d)).or_default() += n;
                }
            }
        }
        let mut workers = Vec::new();
        for (key, m) in self.each_member() {
            let Some(report) = m.report.as_ref() else {
                continue;
            };
            // In the worker's order of use: a dry member's load evicts in it.
            let by_use = report
                .resident
                .iter()
                .filter(|&&d| d < domains)
                .map(|&d| DomainId(d));
            if !busy.contains(&key) {
                let mut worker = WorkerState::new(WorkerId(key), by_use, 0);
                // Domains differ in size: count the slots by the largest, but never fewer
                // than what the worker holds now.
                worker.capacity = ((m.cache_bytes / largest) as usize)
                    .max(1)
                    .max(worker.resident.len());
                workers.push(worker);
            } else {
                let mut resident: BTreeSet<DomainId> = by_use.collect();
                // A busy member holds exactly the wanted domains of its plan and memory, with
                // no slot to spare: what it holds and nobody wants is not a free slot (it is
                // not being re-planned, so a load handed to it would be handed to no one).
                resident.extend(m.plan.iter().map(|&d| DomainId(d)));
                resident.retain(|d| queued.contains_key(d));
                // A busy member holding nothing wanted has no place in the plan; its rays count.
                if !resident.is_empty() {
                    let capacity = resident.len();
                    workers.push(WorkerState::new(WorkerId(key), resident, capacity));
                }
            }
        }
        ClusterState::new(workers, queued).ok()
    }

    /// Each member by key, as the rounds see it.
    fn each_member(&self) -> impl Iterator<Item = (u32, &Member)> {
        self.members.iter().map(|(&k, m)| (k, m.as_ref()))
    }
}

/// Asynchronous rounds: `plans` become round `round`'s; returns the domain loads they ask for
/// and the keys of the members changed (planned, or whose queued counts moved: see
/// `move_queued_to_holders`), for a [`RoundIndex`](super::round_index::RoundIndex) to update.
pub fn adopt_plans<M: AsMut<Member>>(
    members: &mut BTreeMap<u32, M>,
    plans: &[WorkerPlan],
    round: u64,
) -> (u64, BTreeSet<u32>) {
    let (loads, mut changed) = set_plans(members, plans, round);
    changed.extend(move_queued_to_holders(members));
    (loads, changed)
}

/// `plans` become round `round`'s plans of their members; returns the domain loads they ask
/// for and the keys of the members planned.
pub(crate) fn set_plans<M: AsMut<Member>>(
    members: &mut BTreeMap<u32, M>,
    plans: &[WorkerPlan],
    round: u64,
) -> (u64, BTreeSet<u32>) {
    let mut loads = 0;
    let mut planned = BTreeSet::new();
    for p in plans {
        loads += p.load.len() as u64;
        if let Some(m) = members.get_mut(&p.worker.0).map(AsMut::as_mut) {
            m.plan = p.work().map(|d| d.0).collect();
            m.planned_round = round;
            planned.insert(p.worker.0);
        }
    }
    (loads, planned)
}

/// Once told the new holders, a busy member sends its waiting rays for their domains to them,
/// but its next report may be far off: the move is accounted for now, so that its older
/// figures do not keep a dry holder waiting on rays it has already traced. A dry holder
/// reports again when the rays reach it; counted there now, they would stay after it traced
/// them and mislead every later plan. Returns the keys of the members whose figures changed.
pub fn move_queued_to_holders<M: AsMut<Member>>(members: &mut BTreeMap<u32, M>) -> BTreeSet<u32> {
    let mut changed = BTreeSet::new();
    let holder_of: BTreeMap<u32, u32> = members
        .iter_mut()
        .map(|(&k, m)| (k, &*m.as_mut()))
        .filter(|(_, m)| !m.is_dry())
        .flat_map(|(k, m)| m.plan.iter().map(move |&d| (d, k)))
        .collect();
    // Per new holder: domain -> (rays, oldest generation among them).
    let mut moved: BTreeMap<u32, BTreeMap<u32, (u64, Option<u32>)>> = BTreeMap::new();
    for (&key, m) in members.iter_mut() {
        let m = m.as_mut();
        let Some(report) = m.report.as_mut() else {
            continue;
        };
        let keeps = |d: &u32| m.plan.contains(d) || report.resident.contains(d);
        let leaving: Vec<u32> = report
            .queued
            .keys()
            .copied()
            .filter(|d| holder_of.contains_key(d) && !keeps(d))
            .collect();
        if !leaving.is_empty() {
            changed.insert(key);
        }
        for d in leaving {
            let generation = report.oldest_generation.remove(&d);
            if let Some(n) = report.queued.remove(&d) {
                let entry = moved
                    .entry(holder_of[&d])
                    .or_default()
                    .entry(d)
                    .or_default();
                entry.0 += n;
                entry.1 = entry.1.into_iter().chain(generation).min();
            }
        }
    }
    changed.extend(deposit_moved(members, moved));
    changed
}

/// Queued counts taken from members for domains others hold now, by (holder, domain): the
/// rays and their oldest generation, added to each holder's report. Returns the holders
/// whose report changed.
pub(crate) fn deposit_moved<M: AsMut<Member>>(
    members: &mut BTreeMap<u32, M>,
    moved: BTreeMap<u32, BTreeMap<u32, (u64, Option<u32>)>>,
) -> BTreeSet<u32> {
    let mut changed = BTreeSet::new();
    for (key, queues) in moved {
        let member = members.get_mut(&key).map(AsMut::as_mut);
        if let Some(report) = member.and_then(|m| m.report.as_mut()) {
            changed.insert(key);
            for (d, (n, generation)) in queues {
                *report.queued.entry(d).or_default() += n;
                if let Some(g) = generation {
                    let oldest = report.oldest_generation.entry(d).or_insert(g);
                    *oldest = (*oldest).min(g);
                }
            }
        }
    }
    changed
}

/// Every domain someone's current plan includes, with the keys of its holders.
pub fn current_holders<M: AsRef<Member>>(members: &BTreeMap<u32, M>) -> BTreeMap<u32, Vec<u32>> {
    let mut by_domain: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for (&k, m) in members {
        for &d in &m.as_ref().plan {
            by_domain.entry(d).or_default().push(k);
        }
    }
    by_domain
}

#[cfg(test)]
#[path = "rounds_tests.rs"]
mod tests;
