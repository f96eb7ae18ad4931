//! The dynamic ray-weighted schedule of Navrátil et al. (Figs. 5-6).
//!
//! At every round boundary each worker reports its resident domains and queue
//! sizes; the coordinator (the paper's master) calls [`next_round`] and tells
//! every worker which domains to hold. Rays for domain `d` are then sent to
//! the worker(s) holding `d` (see [`RoundPlan::routes`]), and each worker works
//! through its assigned queues fullest first, as in Fig. 6.
//!
//! Fig. 5, in words, and where this module generalises it:
//! 1. A domain is *wanted* when some ray is queued for it. Empty queues get no
//!    one, so nothing is ever loaded for an empty queue.
//! 2. A worker whose loaded domain is wanted keeps it. The paper's `is_loaded`
//!    map remembers one process per domain, which would leave a second holder
//!    of the same domain neither scheduled nor evictable (idle, with the data
//!    in memory). We keep every holder instead: the paper's text expects such
//!    duplicates after the image-plane start ("potentially duplicated domains
//!    across processes"), and splitting a hot queue between holders costs no
//!    load.
//! 3. Processes whose loaded data is not wanted (or who hold nothing) form
//!    `to_evict`; wanted domains no one holds form `to_assign`. They are paired
//!    off, fullest unassigned queue first, until either list runs out.
//!    With caches of several domains, each slot not taken by wanted data counts
//!    as one `to_evict` entry, and slots are handed out to the worker with the
//!    fewest planned domains first, so new work spreads across workers before
//!    any one of them takes a second new domain (with one-domain caches this is
//!    exactly the paper's pairing). Among workers with as many planned, one
//!    with an empty slot goes before one whose slot holds data: a load there
//!    evicts nothing that rays may come back to ([`Opening`]).
//! 4. Data is evicted only when a load needs its slot (in the paper,
//!    `LoadDomain` replaces the single resident domain). Unwanted data on a
//!    worker with nothing to load stays resident: dropping it saves nothing and
//!    may cost a reload later.
//!
//! Fig. 5 never creates new duplicates: once every wanted domain has a holder,
//! remaining `to_evict` processes sit idle. [`Options::replicate_onto_idle`]
//! optionally hands such idle workers a copy of the domain with the most rays
//! per holder, in the spirit of the paper's goal of "high utilization"; it is
//! off by default so that [`next_round`] stays the paper's algorithm. Either
//! extension copies a domain only while every holder keeps
//! [`Options::copy_rays`] of its rays.
//!
//! Ties are broken deterministically: among equally full queues the lower
//! domain id goes first; among equally loaded workers the lower worker id is
//! served first. Among unwanted resident domains the least recently used is
//! evicted first, in the order the worker reports them
//! ([`WorkerState::by_use`](super::WorkerState)): the domain a worker traced
//! last is the one its new rays most likely come back to. Evicting the lower
//! id first made a worker holding a pair of neighbouring domains and one free
//! slot load them in turn, each load evicting the other just as the rays it
//! had made left for it (README "Validation against the real cluster").

use std::borrow::Cow;
use std::cmp::Ordering;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap};

use super::{ClusterState, DomainId, WorkerId};

/// Knobs that extend the paper's algorithm; the default is Fig. 5 as written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Options {
    /// Give workers left idle after Fig. 5 a copy of the domain with the most
    /// queued rays per holder, so hot queues are shared instead of leaving
    /// cores unused. Each copy costs a load.
    pub replicate_onto_idle: bool,
    /// Fill every cache slot left free after Fig. 5 with a copy of a wanted domain (most
    /// rays per holder first). When the caches hold the scene this converges to every
    /// worker tracing its own rays with no migration (the image-plane regime), at the cost
    /// of one load per copy.
    pub fill_free_slots: bool,
    /// The extensions copy a domain only if every holder is left at least this many of its
    /// rays (0 counts as 1: a holder keeps one ray, the rule before `DEFAULT_COPY_RAYS`). A
    /// copy costs a load from shared storage; one that takes a ray or two off a holder costs
    /// the cluster more than it saves when loading dominates (README "Simulator": copies for
    /// a ray or two were most of the plans of a 4,096-worker frame).
    pub copy_rays: u64,
}

/// The coordinator's default [`Options::copy_rays`]: a copy must leave every holder at least
/// a pass's worth of rays. Tracing 4,096 rays takes a core a few milliseconds, about what a
/// load of a small domain from fast storage takes; a copy for fewer rays cannot repay its
/// load. With 1 (a copy while a holder keeps one ray), copies were most of the dynamic
/// schedule's loads where loading dominates: at 8 workers on b32 288 loads and 2.10 s against
/// 46 and 0.80 s, at 1,024 simulated workers 48,067 loads against 8,147 (README "Simulator").
pub const DEFAULT_COPY_RAYS: u64 = 4096;

/// What one worker should hold and work on in the coming round.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WorkerPlan {
    /// The worker this plan is for.
    pub worker: WorkerId,
    /// Resident domains that are wanted: keep them and trace their rays.
    pub keep: BTreeSet<DomainId>,
    /// Domains to load this round and trace rays for.
    pub load: BTreeSet<DomainId>,
    /// Resident domains to drop to make room for `load`.
    pub evict: BTreeSet<DomainId>,
}

impl WorkerPlan {
    /// Domains this worker traces rays for this round (kept and loaded).
    pub fn work(&self) -> impl Iterator<Item = DomainId> + '_ {
        self.keep.union(&self.load).copied()
    }

    /// Whether this worker will trace rays for `domain` this round.
    pub fn works_on(&self, domain: DomainId) -> bool {
        self.keep.contains(&domain) || self.load.contains(&domain)
    }

    /// Whether this worker has nothing to trace this round.
    pub fn is_idle(&self) -> bool {
        self.keep.is_empty() && self.load.is_empty()
    }
}

/// The coordinator's decision for one round: a plan per worker, by worker id.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RoundPlan {
    workers: Vec<WorkerPlan>,
}

impl RoundPlan {
    /// Plans for every worker in the state, ordered by worker id.
    pub fn workers(&self) -> &[WorkerPlan] {
        &self.workers
    }

    /// The plan for one worker, if it was part of the state.
    pub fn for_worker(&self, worker: WorkerId) -> Option<&WorkerPlan> {
        self.workers
            .binary_search_by_key(&worker, |p| p.worker)
            .ok()
            .map(|i| &self.workers[i])
    }

    /// Workers that will trace rays for `domain`, by id; empty if none.
    pub fn holders(&self, domain: DomainId) -> Vec<WorkerId> {
        self.workers
            .iter()
            .filter(|p| p.works_on(domain))
            .map(|p| p.worker)
            .collect()
    }

    /// Where rays should be sent: for every domain someone works on, the
    /// workers working on it, by id.
    pub fn routes(&self) -> BTreeMap<DomainId, Vec<WorkerId>> {
        let mut routes: BTreeMap<DomainId, Vec<WorkerId>> = BTreeMap::new();
        for plan in &self.workers {
            for domain in plan.work() {
                routes.entry(domain).or_default().push(plan.worker);
            }
        }
        routes
    }

    /// Number of domain loads this plan costs (the paper's main metric).
    pub fn load_count(&self) -> usize {
        self.workers.iter().map(|p| p.load.len()).sum()
    }
}

/// `ScheduleNextRound` (Fig. 5): the paper's algorithm, without extensions.
pub fn next_round(state: &ClusterState) -> RoundPlan {
    next_round_with(state, Options::default())
}

/// `ScheduleNextRound` (Fig. 5) with optional extensions, see [`Options`].
///
/// Each of Fig. 5's questions is answered from an index rather than by scanning the cluster
/// (who holds a domain: a set; who has the fewest planned domains: an ordered set; which domain
/// has the most rays per holder: a heap), so a round for 4096 workers over 32768 domains takes
/// milliseconds (`benches/planning.rs`). The plans equal those of the paper's loops written out
/// (`dynamic_reference.rs`, compared by a property test).
pub fn next_round_with(state: &ClusterState, options: Options) -> RoundPlan {
    let drafts: Vec<Draft<'_>> = state
        .workers()
        .iter()
        .map(|w| {
            Draft::keeping_wanted(w.id, Cow::Borrowed(&w.by_use), w.capacity, |d| {
                state.queued(d) > 0
            })
        })
        .collect();
    let to_assign = unheld_fullest_first(state, &drafts);
    let mut drafts = DraftList::new(drafts);
    pair_with_free_slots(&mut drafts, to_assign, |_, _| {});
    if options.replicate_onto_idle || options.fill_free_slots {
        let mut hot = HotDomains::new(state, &drafts.drafts, options.copy_rays);
        extend_plans(&mut hot, &mut drafts, options);
    }
    RoundPlan {
        workers: drafts.drafts.into_iter().map(Draft::finish).collect(),
    }
}

/// A worker's plan while it is being built: the one drafting of Fig. 5, shared by
/// [`next_round_with`] (from a whole [`ClusterState`]) and `round_index` (from its figures).
pub(super) struct Draft<'a> {
    worker: WorkerId,
    /// Domains in the worker's cache, least recently used first, each once (borrowed from a
    /// state, or gathered by the caller).
    by_use: Cow<'a, [DomainId]>,
    /// Domains the cache holds at once.
    capacity: usize,
    keep: BTreeSet<DomainId>,
    load: BTreeSet<DomainId>,
}

impl<'a> Draft<'a> {
    /// Fig. 5, first loop over `to_schedule`: a loaded domain that some ray
    /// wants stays with the worker that has it.
    pub(super) fn keeping_wanted(
        worker: WorkerId,
        by_use: Cow<'a, [DomainId]>,
        capacity: usize,
        wanted: impl Fn(DomainId) -> bool,
    ) -> Self {
        let keep = by_use.iter().copied().filter(|&d| wanted(d)).collect();
        Draft {
            worker,
            by_use,
            capacity,
            keep,
            load: BTreeSet::new(),
        }
    }

    /// Domains planned so far (kept and loaded).
    pub(super) fn planned(&self) -> usize {
        self.keep.len() + self.load.len()
    }

    /// Slots not holding wanted data: each is one `to_evict` entry of Fig. 5.
    pub(super) fn free_slots(&self) -> usize {
        self.capacity - self.planned()
    }

    /// Where the plan so far stands in the pairing's order.
    pub(super) fn opening(&self) -> Opening {
        Opening::new(
            self.planned(),
            self.by_use.len() + self.load.len(),
            self.capacity,
        )
    }

    /// Whether the plan so far traces rays for `domain`.
    pub(super) fn works_on(&self, domain: DomainId) -> bool {
        self.keep.contains(&domain) || self.load.contains(&domain)
    }

    /// `domain` loaded and traced.
    pub(super) fn load(&mut self, domain: DomainId) {
        self.load.insert(domain);
    }

    /// Evicts just enough unwanted data to fit the loads (least recently used first).
    pub(super) fn finish(self) -> WorkerPlan {
        let overflow = (self.by_use.len() + self.load.len()).saturating_sub(self.capacity);
        let evict = self
            .by_use
            .iter()
            .copied()
            .filter(|d| !self.keep.contains(d))
            .take(overflow)
            .collect();
        WorkerPlan {
            worker: self.worker,
            keep: self.keep,
            load: self.load,
            evict,
        }
    }
}

/// Fig. 5's `to_assign`, ordered as its `top()` pops it: wanted domains no
/// worker holds with their rays, fullest queue first, lower domain id on ties.
fn unheld_fullest_first(state: &ClusterState, drafts: &[Draft<'_>]) -> Vec<(DomainId, u64)> {
    // Before any load is planned, a domain is worked on exactly where it is kept.
    let held: BTreeSet<DomainId> = drafts.iter().flat_map(|w| w.keep.iter().copied()).collect();
    let mut unheld: Vec<(DomainId, u64)> =
        state.wanted().filter(|(d, _)| !held.contains(d)).collect();
    unheld.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    unheld
}

/// A worker's place in the order Fig. 5's pairing hands out free slots in: fewest planned
/// domains first, then a worker with an empty slot before one whose load would evict
/// (unwanted data it holds may be wanted again: a worker with one empty slot left unused while
/// another evicted for every load loaded a pair of domains in turn, each evicting the other),
/// then the lower id (the caller's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) struct Opening {
    planned: usize,
    evicts: bool,
}

impl Opening {
    /// A worker with `planned` domains planned and `filled` slots taken (held or to load) of
    /// `capacity`.
    pub(super) fn new(planned: usize, filled: usize, capacity: usize) -> Self {
        Opening {
            planned,
            evicts: filled >= capacity,
        }
    }

    /// The places of a worker with nothing planned: with an empty slot, and without.
    pub(super) const IDLE: [Opening; 2] = [
        Opening {
            planned: 0,
            evicts: false,
        },
        Opening {
            planned: 0,
            evicts: true,
        },
    ];
}

/// The drafts of a round as its pairing and extensions walk them, by worker: every worker's
/// ([`DraftList`]), or only the dry members' of an index, each made when the round first gives
/// it something (`round_index`), so a round costs what it hands out, not the dry members.
pub(super) trait Drafts {
    /// The worker with a free slot and the fewest planned domains, the lower id on ties.
    fn least_busy_open(&self) -> Option<WorkerId>;
    /// The first worker after `after` (from the first if `None`), in worker order, whose
    /// draft has a free slot, or (`idle`) nothing planned.
    fn next_open(&self, after: Option<WorkerId>, idle: bool) -> Option<WorkerId>;
    /// Whether `worker`'s draft so far traces rays for `domain`.
    fn works_on(&self, worker: WorkerId, domain: DomainId) -> bool;
    /// `domain` loaded by `worker`, which [`Drafts::least_busy_open`] or
    /// [`Drafts::next_open`] named.
    fn load(&mut self, worker: WorkerId, domain: DomainId);
}

/// Every worker's draft by worker id, with those that have a free slot ordered by
/// (planned domains, position).
pub(super) struct DraftList<'a> {
    drafts: Vec<Draft<'a>>,
    open: BTreeSet<(Opening, usize)>,
}

impl<'a> DraftList<'a> {
    /// `drafts`, sorted by worker id.
    fn new(drafts: Vec<Draft<'a>>) -> Self {
        let open = drafts
            .iter()
            .enumerate()
            .filter(|(_, d)| d.free_slots() > 0)
            .map(|(i, d)| (d.opening(), i))
            .collect();
        DraftList { drafts, open }
    }

    fn position(&self, worker: WorkerId) -> usize {
        self.drafts
            .binary_search_by_key(&worker, |d| d.worker)
            .expect("a worker of the list")
    }
}

impl Drafts for DraftList<'_> {
    fn least_busy_open(&self) -> Option<WorkerId> {
        let &(_, i) = self.open.first()?;
        Some(self.drafts[i].worker)
    }

    fn next_open(&self, after: Option<WorkerId>, idle: bool) -> Option<WorkerId> {
        let from = after.map_or(0, |w| self.position(w) + 1);
        self.drafts[from..]
            .iter()
            .find(|d| {
                if idle {
                    d.planned() == 0
                } else {
                    d.free_slots() > 0
                }
            })
            .map(|d| d.worker)
    }

    fn works_on(&self, worker: WorkerId, domain: DomainId) -> bool {
        self.drafts[self.position(worker)].works_on(domain)
    }

    fn load(&mut self, worker: WorkerId, domain: DomainId) {
        let i = self.position(worker);
        let draft = &mut self.drafts[i];
        let before = (draft.opening(), i);
        draft.load(domain);
        self.open.remove(&before);
        if draft.free_slots() > 0 {
            self.open.insert((draft.opening(), i));
        }
    }
}

/// Fig. 5's `while` loop: pair `to_assign` (domains with their rays, in `top()` order) with
/// `to_evict` until either runs out. A domain goes to the worker with a free slot and the
/// fewest planned domains (lower id on ties), so idle workers are served before busy ones.
/// `placed` hears of each domain given to a worker, with its rays.
pub(super) fn pair_with_free_slots(
    drafts: &mut impl Drafts,
    to_assign: impl IntoIterator<Item = (DomainId, u64)>,
    mut placed: impl FnMut(DomainId, u64),
) {
    for (domain, rays) in to_assign {
        let Some(worker) = drafts.least_busy_open() else {
            return;
        };
        drafts.load(worker, domain);
        placed(domain, rays);
    }
}

/// Where the extensions find the domain with the most rays per holder: a heap built for one
/// round here, the index's ordered set with this round's copies laid over it in `round_index`.
pub(super) trait Hottest {
    /// The hottest domain among `eligible` ones, counted as having one more holder.
    fn take_hottest(&mut self, eligible: impl Fn(DomainId) -> bool) -> Option<DomainId>;
    /// Whether no domain is left to take, whatever is eligible: the extensions stop there
    /// rather than ask every remaining worker.
    fn exhausted(&self) -> bool;
}

/// The extensions [`Options`] turns on, after Fig. 5's pairing.
pub(super) fn extend_plans(hot: &mut impl Hottest, drafts: &mut impl Drafts, options: Options) {
    if options.replicate_onto_idle {
        replicate_onto_idle(hot, drafts);
    }
    if options.fill_free_slots {
        fill_free_slots(hot, drafts);
    }
}

/// Extension (off by default): each worker still idle after Fig. 5 loads a
/// copy of the domain with the most rays per holder, provided the split still
/// leaves every holder at least `Options::copy_rays` rays.
fn replicate_onto_idle(hot: &mut impl Hottest, drafts: &mut impl Drafts) {
    let mut at = None;
    while let Some(worker) = drafts.next_open(at, true) {
        if hot.exhausted() {
            return;
        }
        if let Some(domain) = hot.take_hottest(|_| true) {
            drafts.load(worker, domain);
        }
        at = Some(worker);
    }
}

/// Extension (off by default): free slots take copies of wanted domains, hottest per
/// holder first, a slot at a time across workers (lower id first) so copies spread.
fn fill_free_slots(hot: &mut impl Hottest, drafts: &mut impl Drafts) {
    loop {
        let mut placed = false;
        let mut at = None;
        while let Some(worker) = drafts.next_open(at, false) {
            if hot.exhausted() {
                return;
            }
            if let Some(domain) = hot.take_hottest(|d| !drafts.works_on(worker, d)) {
                drafts.load(worker, domain);
                placed = true;
            }
            at = Some(worker);
        }
        if !placed {
            return;
        }
    }
}

/// Wanted domains with more rays than holders, hottest (most rays per holder) first.
struct HotDomains {
    heap: BinaryHeap<Heat>,
    copy_rays: u64,
}

impl HotDomains {
    /// Every wanted domain that splits, with its holders as the drafts plan them.
    fn new(state: &ClusterState, drafts: &[Draft<'_>], copy_rays: u64) -> Self {
        let mut copies: BTreeMap<DomainId, u64> = BTreeMap::new();
        for draft in drafts {
            for domain in draft.keep.iter().chain(&draft.load) {
                *copies.entry(*domain).or_default() += 1;
            }
        }
        let heap = state
            .wanted()
            .map(|(domain, rays)| Heat {
                domain,
                rays,
                copies: copies.get(&domain).copied().unwrap_or(0),
            })
            .filter(|h| h.splits(copy_rays))
            .collect();
        HotDomains { heap, copy_rays }
    }
}

impl Hottest for HotDomains {
    fn take_hottest(&mut self, eligible: impl Fn(DomainId) -> bool) -> Option<DomainId> {
        let mut passed = Vec::new();
        let found = loop {
            match self.heap.pop() {
                Some(heat) if eligible(heat.domain) => break Some(heat),
                Some(heat) => passed.push(heat),
                None => break None,
            }
        };
        self.heap.extend(passed);
        let mut heat = found?;
        heat.copies += 1;
        let domain = heat.domain;
        if heat.splits(self.copy_rays) {
            self.heap.push(heat);
        }
        Some(domain)
    }

    fn exhausted(&self) -> bool {
        self.heap.is_empty()
    }
}

/// A wanted domain's rays and holders, ordered by rays per holder (compared as fractions,
/// without division), then the lower domain id first.
#[derive(Clone, Copy, Debug)]
pub(super) struct Heat {
    pub(super) domain: DomainId,
    pub(super) rays: u64,
    pub(super) copies: u64,
}

impl Heat {
    /// Whether another copy still leaves every holder at least `copy_rays` rays (at least
    /// one: [`Options::copy_rays`]).
    pub(super) fn splits(&self, copy_rays: u64) -> bool {
        u128::from(self.rays) >= u128::from(copy_rays.max(1)) * (u128::from(self.copies) + 1)
    }
}

impl Ord for Heat {
    fn cmp(&self, other: &Self) -> Ordering {
        let mine = u128::from(self.rays) * u128::from(other.copies);
        let theirs = u128::from(other.rays) * u128::from(self.copies);
        mine.cmp(&theirs).then(other.domain.cmp(&self.domain))
    }
}

impl PartialEq for Heat {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Heat {}

impl PartialOrd for Heat {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

#[cfg(test)]
#[path = "dynamic_reference.rs"]
mod reference;

#[cfg(test)]
#[path = "dynamic_tests.rs"]
mod tests;
