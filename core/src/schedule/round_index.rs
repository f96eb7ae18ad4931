//! Asynchronous rounds planned incrementally: the figures Fig. 5 reads (rays wanted per domain,
//! who holds what, which wanted domains nobody holds, fullest first, and which have the most
//! rays per holder) kept up to date member by member as reports and plans change, so that
//! planning the members that ran dry costs what their own plans cost, not what turning every
//! report of the cluster into a [`ClusterState`](super::ClusterState) and drafting every
//! member's plan costs (`Cluster::dry_plans`, linear in members and domains).
//!
//! The plans equal `Cluster::dry_plans`'s, which equal Fig. 5's loops on the cluster's state
//! (property tests here and in `dynamic.rs`). When nobody is busy (a frame's first round, or
//! its tail) every member is planned anyway, and the index hands over to `Cluster::dry_plans`.
//!
//! The owner calls [`RoundIndex::update`] for a member whenever its report, plan or presence
//! changes; nothing else is read from the members between updates except their cache sizes,
//! reports and plans of the members that ran dry.

use std::borrow::Cow;
use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet};

use super::dynamic::{
    Draft, Drafts, Heat, Hottest, Opening, Options, WorkerPlan, extend_plans, pair_with_free_slots,
};
use super::rounds::{Cluster, Member, Queues, deposit_moved, sent_plan, set_plans};
use super::{DomainId, WorkerId};

/// What one member adds to the cluster's figures, kept so it can be taken out again. Every
/// list is ascending (a multiset for `generations`), so a member's old and new parts are
/// compared in one merge and only what differs is counted again (`RoundIndex::recount`).
#[derive(Clone, Debug, Default, PartialEq)]
struct Part {
    /// (domain, rays, oldest generation among them) of its report, domains in the scene only.
    queued: Vec<(u32, u64, Option<u32>)>,
    /// Every generation its report names (the oldest-generation rule reads the least).
    generations: Vec<u32>,
    /// Domains it holds as the schedule sees it: its memory if it ran dry, its memory and plan
    /// if it is busy; nothing if it has not reported.
    held: Vec<u32>,
    /// Domains in its memory or plan (the oldest-generation rule counts their queues).
    in_memory: Vec<u32>,
    /// Domains in its memory, least recently used first, each once: the order its draft
    /// evicts them in if it ran dry. The only list here not ascending.
    by_use: Vec<u32>,
    /// Domains of its plan if it is busy (rays queued elsewhere for them move to it).
    holding_plan: Vec<u32>,
    /// Domains its report has a queue for, empty or not.
    queues: Vec<u32>,
    /// Its plan, whatever it names: the holders map lists it under each of these.
    plan: Vec<u32>,
}

/// Whether `a` and `b` name the same domains, in any order (each names each once).
fn same_set(a: &[u32], b: &[u32]) -> bool {
    if a == b {
        return true;
    }
    if a.len() != b.len() {
        return false;
    }
    let (mut a, mut b) = (a.to_vec(), b.to_vec());
    a.sort_unstable();
    b.sort_unstable();
    a == b
}

/// One domain's queue in a report: (its rays, the oldest generation among them), `None` where
/// the report has no entry.
pub type Queue = (Option<u64>, Option<u32>);

/// A member's report that names only the queues that changed since its last
/// (`QueueReport.delta`), for [`RoundIndex::take_changes`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Changes {
    /// The round of the plan it had when it reported.
    pub round: u64,
    /// Domains in its memory, least recently used first, each once.
    pub resident: Vec<u32>,
    /// The oldest generation of its rays that wait on something other than a domain.
    pub oldest_waiting: Option<u32>,
    /// (domain, its queue now) of each queue that changed, each domain once.
    pub queues: Vec<(u32, Queue)>,
}

/// Member `key`'s queue for domain `d`, if it has a report.
fn queue_of<M: AsRef<Member>>(members: &BTreeMap<u32, M>, key: u32, d: u32) -> Option<Queue> {
    Some(members.get(&key)?.as_ref().report.as_ref()?.queue(d))
}

impl Queues {
    /// Domain `d`'s queue.
    fn queue(&self, d: u32) -> Queue {
        (
            self.queued.get(&d).copied(),
            self.oldest_generation.get(&d).copied(),
        )
    }

    /// Domain `d`'s queue made `(rays, generation)`.
    fn set_queue(&mut self, d: u32, (rays, generation): Queue) {
        match rays {
            Some(n) => self.queued.insert(d, n),
            None => self.queued.remove(&d),
        };
        match generation {
            Some(g) => self.oldest_generation.insert(d, g),
            None => self.oldest_generation.remove(&d),
        };
    }
}

/// `items` sorted ascending without repeats.
fn sort_dedup(items: &mut Vec<u32>) {
    items.sort_unstable();
    items.dedup();
}

impl Part {
    /// Member `m`'s part (`dry`: whether it ran dry) in a scene of `domains` domains, made in
    /// this part's lists, which keep their memory: a part is made for every report, plan and
    /// presence taken in (`RoundIndex::update` reuses the part it replaced).
    fn fill(&mut self, m: &Member, dry: bool, domains: u32) {
        self.clear();
        self.fill_holdings(m, dry, domains);
        if let Some(report) = m.report.as_ref() {
            self.fill_queues(report, domains);
        }
    }

    /// The lists of what member `m` holds and plans (all but the queues'), made again.
    fn fill_holdings(&mut self, m: &Member, dry: bool, domains: u32) {
        for list in [
            &mut self.held,
            &mut self.in_memory,
            &mut self.by_use,
            &mut self.holding_plan,
            &mut self.plan,
        ] {
            list.clear();
        }
        let in_scene = m.plan.iter().copied().filter(|&d| d < domains);
        self.plan.extend(m.plan.iter().copied());
        if !dry {
            self.holding_plan.extend(in_scene.clone());
        }
        self.in_memory.extend(in_scene.clone());
        let Some(report) = m.report.as_ref() else {
            return;
        };
        let resident = report.resident.iter().copied().filter(|&d| d < domains);
        self.in_memory.extend(resident.clone());
        self.set_by_use(&report.resident, domains);
        sort_dedup(&mut self.in_memory);
        self.held.extend(resident);
        if !dry {
            self.held.extend(in_scene);
        }
        sort_dedup(&mut self.held);
    }

    /// Its order of use: `resident` (least recently used first), domains in the scene only.
    fn set_by_use(&mut self, resident: &[u32], domains: u32) {
        self.by_use.clear();
        self.by_use
            .extend(resident.iter().copied().filter(|&d| d < domains));
    }

    /// The lists of `report`'s queues and generations, made (from empty).
    fn fill_queues(&mut self, report: &Queues, domains: u32) {
        self.generations.extend(
            report
                .oldest_generation
                .values()
                .copied()
                .chain(report.oldest_waiting),
        );
        self.generations.sort_unstable();
        // Both maps ascend by domain: one walk pairs each queue with its oldest generation, not
        // a lookup a queue (a predictive report names about 150 at 4,096 workers).
        let mut oldest = report.oldest_generation.iter().peekable();
        self.queued.extend(
            report
                .queued
                .iter()
                .filter(|&(&d, &n)| d < domains && n > 0)
                .map(|(&d, &n)| {
                    while oldest.next_if(|&(&g, _)| g < d).is_some() {}
                    (d, n, oldest.next_if(|&(&g, _)| g == d).map(|(_, &g)| g))
                }),
        );
        self.queues
            .extend(report.queued.keys().copied().filter(|&d| d < domains));
    }

    /// Empty, keeping its lists' memory.
    fn clear(&mut self) {
        self.queued.clear();
        self.generations.clear();
        self.held.clear();
        self.in_memory.clear();
        self.by_use.clear();
        self.holding_plan.clear();
        self.queues.clear();
        self.plan.clear();
    }
}

/// A member that ran dry as Fig. 5's first loop leaves it, kept from round to round: what its
/// draft would be, without making one (`RoundIndex::dry_plans` makes a draft only for a member
/// the round gives something or whose plan would change, `rounds::sent_plan`).
#[derive(Clone, Debug, PartialEq)]
struct Dry {
    /// Domains its cache holds at once, counted by the scene's largest domain (never fewer
    /// than it holds).
    capacity: usize,
    /// Its resident domains with rays that count: those its draft keeps.
    kept: usize,
    /// Its resident domains.
    held: usize,
    /// Whether its plan names exactly its resident domains (as `rounds::sent_plan` names them):
    /// then a round that gives it nothing leaves its plan as it is.
    stands: bool,
}

impl Dry {
    /// Whether its draft has a slot not holding wanted data.
    fn has_free_slot(&self) -> bool {
        self.capacity > self.kept
    }

    /// Where its draft would stand in the pairing's order.
    fn opening(&self) -> Opening {
        Opening::new(self.kept, self.held, self.capacity)
    }

    /// Whether it is planned even if the round gives it nothing (`rounds::sent_plan`): its plan
    /// does not name exactly the domains it holds. Whether their rays count does not matter:
    /// a plan names every resident domain, wanted or not.
    fn differs(&self) -> bool {
        !self.stands
    }
}

/// Whether domain `d` has rays that count (`RoundIndex::shown`): a draft keeps it if resident.
fn wanted(shown: &[(u64, u32)], d: u32) -> bool {
    shown[d as usize].0 > 0
}

/// A generation `before` in a member's ascending multiset `list` (and in the index's `counts`)
/// made `now` (`None`: no generation).
fn swap_generation(
    list: &mut Vec<u32>,
    counts: &mut BTreeMap<u32, usize>,
    before: Option<u32>,
    now: Option<u32>,
) {
    if before == now {
        return;
    }
    for (g, add) in [(before, false), (now, true)] {
        let Some(g) = g else { continue };
        let at = list.partition_point(|&x| x < g);
        if add {
            list.insert(at, g);
        } else {
            list.remove(at);
        }
        tally(counts, g, 1, add);
    }
}

/// `key` added to `list`, ascending without repeats.
fn list_in(list: &mut Vec<u32>, key: u32) {
    if let Err(at) = list.binary_search(&key) {
        list.insert(at, key);
    }
}

/// `key` taken out of `list`, ascending.
fn list_out(list: &mut Vec<u32>, key: u32) {
    if let Ok(at) = list.binary_search(&key) {
        list.remove(at);
    }
}

/// Member `key` listed under the domains of `new` instead of those of `old` (both
/// ascending) in `lists` (the members of each domain, ascending: a domain has a few, and a
/// list keeps its memory where a set allocated and freed a node whenever a domain's first
/// member came and its last went); returns the domains it was added to.
fn list_member(lists: &mut [Vec<u32>], key: u32, old: &[u32], new: &[u32]) -> Vec<u32> {
    let mut added = Vec::new();
    for step in merge(old, new, |&d| d) {
        match step {
            Merged::Both(..) => {}
            Merged::Old(&d) => list_out(&mut lists[d as usize], key),
            Merged::New(&d) => {
                list_in(&mut lists[d as usize], key);
                added.push(d);
            }
        }
    }
    added
}

/// `x` moved `by` up (`add`) or down.
fn step_by<T: std::ops::AddAssign + std::ops::SubAssign>(x: &mut T, by: T, add: bool) {
    if add { *x += by } else { *x -= by }
}

/// `n` rays queued for domain `d`, the oldest of generation `g`, counted in (`add`) or out of
/// the rays reported per domain (and per oldest generation, under the oldest-generation rule).
fn count_queue(
    queued: &mut [u64],
    by_generation: &mut [BTreeMap<u32, u64>],
    oldest_first: bool,
    (d, n, g): (u32, u64, Option<u32>),
    add: bool,
) {
    step_by(&mut queued[d as usize], n, add);
    if let (true, Some(g)) = (oldest_first, g) {
        tally(&mut by_generation[d as usize], g, n, add);
    }
}

/// `counts[key]` moved `by` up (`add`) or down, the entry gone once it is zero.
fn tally<T>(counts: &mut BTreeMap<u32, T>, key: u32, by: T, add: bool)
where
    T: std::ops::AddAssign + std::ops::SubAssign + Default + PartialEq,
{
    let count = counts.entry(key).or_default();
    step_by(count, by, add);
    if *count == T::default() {
        counts.remove(&key);
    }
}

/// One step of a merge of two ascending lists: an item of the old list only, of the new
/// only, or of both.
enum Merged<T> {
    Old(T),
    New(T),
    Both(T, T),
}

/// Merges ascending `old` and `new` by `key` (each key at most once a list, except where
/// equal items pair off one by one, as a multiset's do).
fn merge<'a, T, K: Ord>(
    old: &'a [T],
    new: &'a [T],
    key: impl Fn(&T) -> K,
) -> impl Iterator<Item = Merged<&'a T>> {
    let (mut i, mut j) = (0, 0);
    std::iter::from_fn(move || {
        let step = match (old.get(i), new.get(j)) {
            (None, None) => return None,
            (Some(o), None) => Merged::Old(o),
            (None, Some(n)) => Merged::New(n),
            (Some(o), Some(n)) => match key(o).cmp(&key(n)) {
                std::cmp::Ordering::Less => Merged::Old(o),
                std::cmp::Ordering::Greater => Merged::New(n),
                std::cmp::Ordering::Equal => Merged::Both(o, n),
            },
        };
        match step {
            Merged::Old(_) => i += 1,
            Merged::New(_) => j += 1,
            Merged::Both(..) => (i, j) = (i + 1, j + 1),
        }
        Some(step)
    })
}

/// The cluster's figures for asynchronous rounds, kept up to date member by member.
#[derive(Clone, Debug)]
pub struct RoundIndex {
    domains: u32,
    oldest_first: bool,
    parts: BTreeMap<u32, Part>,
    /// Members that ran dry since their last plan, each as its draft would start.
    dry: BTreeMap<u32, Dry>,
    /// (place, key) of the dry members with a free slot: the order Fig. 5's pairing serves
    /// them in (`Opening`: domains kept, then an empty slot first).
    open: BTreeSet<(Opening, u32)>,
    /// The same members by key: the order the extensions serve them in.
    free: BTreeSet<u32>,
    /// Dry members whose plan names other domains than their draft keeps.
    differs: BTreeSet<u32>,
    /// Dry members with each domain resident (a domain's rays coming or going changes what
    /// their drafts keep).
    dry_resident: Vec<Vec<u32>>,
    /// Rays reported per domain, over every member.
    queued: Vec<u64>,
    /// Rays reported per domain by oldest generation (the oldest-generation rule only).
    by_generation: Vec<BTreeMap<u32, u64>>,
    /// Every generation reported, with how many times.
    generations: BTreeMap<u32, usize>,
    /// The oldest generation the figures below were counted for.
    oldest: Option<u32>,
    /// Members holding each domain as the schedule sees them.
    held: Vec<u32>,
    /// Members with each domain in memory or plan.
    in_memory: Vec<u32>,
    /// (rays that count, holders) of each domain as the sets below show it.
    shown: Vec<(u64, u32)>,
    /// Domains with rays that count.
    wanted: usize,
    /// Wanted domains nobody holds, fullest first, then the lower id (Fig. 5's `to_assign`).
    unheld: BTreeSet<(Reverse<u64>, u32)>,
    /// The same domains as a bit a domain, for the hot order: a domain nobody holds has more
    /// rays per holder than any held one, and among them the lower id comes first, so the
    /// hottest domains are these in ascending order, then `hot`'s. Kept apart, a domain that
    /// stays unheld moves in `unheld` alone when its rays change (most domains at 4,096
    /// workers x 32,768 domains, where updating the sets, `refresh`, was a quarter of a round).
    unheld_bits: Vec<u64>,
    /// Wanted domains that someone holds with more rays than holders, by rays per holder.
    hot: BTreeSet<Heat>,
    /// Busy members with each domain in their plan (the last one receives rays moved).
    plan_holders: Vec<Vec<u32>>,
    /// Members whose report has a queue for each domain.
    queuers: Vec<Vec<u32>>,
    /// Members changed, and domains that gained a busy holder, since rays last moved: only
    /// their queues can have a holder elsewhere (`adopt`).
    unmoved: BTreeSet<u32>,
    newly_held: BTreeSet<u32>,
    /// (member, domain) queues that may have a holder elsewhere since rays last moved, of
    /// members whose reports named only what changed ([`RoundIndex::update_queues`]): the
    /// queues named, and those of domains the member stopped holding or planning.
    unmoved_queues: Vec<(u32, u32)>,
    /// By member: its queues as it last reported them where the rounds moved rays since (from
    /// it to a holder, or to it): a report that names only what changed leaves those queues
    /// as the worker has them, not as the rounds left them ([`RoundIndex::take_changes`]).
    unreported: BTreeMap<u32, BTreeMap<u32, Queue>>,
    /// Every domain in someone's plan, with the members whose plan it is in
    /// (`rounds::current_holders`, kept member by member).
    holders: BTreeMap<u32, BTreeSet<u32>>,
    /// Domains whose holders changed since [`RoundIndex::take_holder_changes`] last ran.
    holders_changed: BTreeSet<u32>,
    /// By member: the domains whose queued rays the last [`RoundIndex::adopt`] moved from it
    /// to a holder (it must learn those holders at once).
    moved: BTreeMap<u32, BTreeSet<u32>>,
    /// Bytes of each domain of the scene, and the largest of them (at least 1): a cache's
    /// slots are counted by it (found once: walking every domain's size each round was 3% of
    /// a dynamic run at 256 workers, README "Simulator").
    domain_bytes: Vec<u64>,
    largest: u64,
    /// Rays every holder must keep for the extensions to copy a domain
    /// ([`Options::copy_rays`]): only domains that split so are in `hot`.
    copy_rays: u64,
    /// A part whose lists the next [`RoundIndex::update`] makes its member's part in.
    spare: Part,
    /// Drafts [`RoundIndex::dry_plans`] made, since the index began.
    drafts_made: u64,
}

impl RoundIndex {
    /// An empty index for a scene of domains of `domain_bytes` bytes each; `oldest_first` as
    /// in [`Cluster`].
    pub fn new(domain_bytes: &[u64], oldest_first: bool) -> RoundIndex {
        let n = domain_bytes.len();
        RoundIndex {
            domains: u32::try_from(n).unwrap_or(u32::MAX),
            oldest_first,
            parts: BTreeMap::new(),
            dry: BTreeMap::new(),
            open: BTreeSet::new(),
            free: BTreeSet::new(),
            differs: BTreeSet::new(),
            dry_resident: vec![Vec::new(); n],
            queued: vec![0; n],
            by_generation: if oldest_first {
                vec![BTreeMap::new(); n]
            } else {
                Vec::new()
            },
            generations: BTreeMap::new(),
            oldest: None,
            held: vec![0; n],
            in_memory: vec![0; n],
            shown: vec![(0, 0); n],
            wanted: 0,
            unheld: BTreeSet::new(),
            unheld_bits: vec![0; n.div_ceil(64)],
            hot: BTreeSet::new(),
            plan_holders: vec![Vec::new(); n],
            queuers: vec![Vec::new(); n],
            unmoved: BTreeSet::new(),
            newly_held: BTreeSet::new(),
            unmoved_queues: Vec::new(),
            unreported: BTreeMap::new(),
            holders: BTreeMap::new(),
            holders_changed: BTreeSet::new(),
            moved: BTreeMap::new(),
            domain_bytes: domain_bytes.to_vec(),
            largest: domain_bytes.iter().copied().max().unwrap_or(1).max(1),
            spare: Part::default(),
            drafts_made: 0,
            copy_rays: 1,
        }
    }

    /// The same index with the extensions copying a domain only if every holder keeps at
    /// least `copy_rays` of its rays ([`Options::copy_rays`], which `dry_plans` must be given
    /// alike); set before the first update.
    pub fn copying_from(mut self, copy_rays: u64) -> RoundIndex {
        self.copy_rays = copy_rays;
        self
    }

    /// Takes member `key` as it is now (`None`: it left the frame) into the figures: its
    /// report, plan and whether it ran dry. Costs its report's size, not the cluster's, and
    /// counts again only what changed since its last update (a holder that rays moved to
    /// differs in those domains' queues alone).
    pub fn update(&mut self, key: u32, member: Option<&Member>) {
        if member.and_then(|m| m.report.as_ref()).is_none() {
            self.unreported.remove(&key);
        }
        self.renew(key, member, false);
    }

    /// Member `key` sent a whole report: its queues the rounds moved rays from or to since its
    /// last are as it says now. The owner calls this with [`RoundIndex::update`] for it.
    pub fn reported_whole(&mut self, key: u32) {
        self.unreported.remove(&key);
    }

    /// Takes in member `key`'s report that names only what changed since its last
    /// (`QueueReport.delta`): the member's report is brought up to date and the figures with
    /// it. First its queues the rounds moved rays from or to since are put back as it last
    /// reported them (it does not name what did not change on its side), then the queues
    /// `changes` names are set. Costs what the report names and the rounds moved, not every
    /// queue the member has, as [`RoundIndex::update`] does (a predictive report at 4,096
    /// workers names about 150 queues, of which one or two changed). False if the member has
    /// no report to put it in (nothing changes).
    pub fn take_changes<M: AsMut<Member> + AsRef<Member>>(
        &mut self,
        key: u32,
        members: &mut BTreeMap<u32, M>,
        changes: Changes,
    ) -> bool {
        let Some(q) = members
            .get_mut(&key)
            .and_then(|m| m.as_mut().report.as_mut())
        else {
            return false;
        };
        // Domain -> (its queue as the figures count it, as it is now).
        let mut edits: BTreeMap<u32, (Queue, Queue)> = BTreeMap::new();
        for (d, reported) in self.unreported.remove(&key).unwrap_or_default() {
            edits.insert(d, (q.queue(d), reported));
            q.set_queue(d, reported);
        }
        for (d, now) in changes.queues {
            let before = edits.get(&d).map_or_else(|| q.queue(d), |e| e.0);
            edits.insert(d, (before, now));
            q.set_queue(d, now);
        }
        let waiting_before = q.oldest_waiting;
        // Most reports of a dry member say only that rays came for domains it does not hold:
        // then what it holds and whether it ran dry are as they were. Most others of the same
        // round name the same domains resident in another order of use (a pass used one):
        // only the order its draft would evict in changed.
        let holds_the_same = q.round == changes.round && same_set(&q.resident, &changes.resident);
        q.round = changes.round;
        q.resident = changes.resident;
        q.oldest_waiting = changes.oldest_waiting;
        let edits: Vec<(u32, Queue, Queue)> = edits
            .into_iter()
            .filter(|(_, (before, now))| before != now)
            .map(|(d, (before, now))| (d, before, now))
            .collect();
        self.update_queues(key, members, &edits, waiting_before, holds_the_same);
        true
    }

    /// Takes member `key`'s new report into the figures when it differs from the member as
    /// last taken in only in the queues of `edits` ((domain, its queue before, after), each
    /// domain once), its oldest waiting generation (`waiting_before` before), and its round
    /// and resident domains unless `holds_the_same` (then they are as they were, but for the
    /// order of use).
    fn update_queues<M: AsRef<Member>>(
        &mut self,
        key: u32,
        members: &BTreeMap<u32, M>,
        edits: &[(u32, Queue, Queue)],
        waiting_before: Option<u32>,
        holds_the_same: bool,
    ) {
        let member = members.get(&key).map(AsRef::as_ref);
        let (Some(m), Some(part)) = (member, self.parts.get_mut(&key)) else {
            // Gone, or never counted: counted whole.
            return self.update(key, member);
        };
        let waiting = m.report.as_ref().and_then(|r| r.oldest_waiting);
        swap_generation(
            &mut part.generations,
            &mut self.generations,
            waiting_before,
            waiting,
        );
        let edits: Vec<(u32, u32, Queue, Queue)> =
            edits.iter().map(|&(d, b, a)| (key, d, b, a)).collect();
        self.requeue(members, &edits);
        self.unmoved_queues
            .extend(edits.iter().map(|&(k, d, ..)| (k, d)));
        if !holds_the_same {
            return self.renew(key, member, true);
        }
        // What it holds, its plan and its being dry are as they were: of its part only the
        // order of use may differ, which no figure counts (a member's part made again was a
        // fifth of predictive's coordinator at 4,096 workers, most of it for a new order).
        let resident = m.report.as_ref().map_or(&[][..], |r| &r.resident[..]);
        if let Some(part) = self.parts.get_mut(&key) {
            part.set_by_use(resident, self.domains);
        }
    }

    /// Member `key` as it is now (see [`RoundIndex::update`]); with `queues_kept`, its part's
    /// queue lists are taken as they stand (the owner brought them up to date queue by queue,
    /// [`RoundIndex::update_queues`]) and only the rest is made again.
    fn renew(&mut self, key: u32, member: Option<&Member>, queues_kept: bool) {
        if !queues_kept {
            self.unmoved.insert(key);
        }
        // The member's part is made in the lists of the one replaced last time (`spare`),
        // and the one it replaces kept for next time: no list allocated in a steady state.
        let mut old = self
            .parts
            .get_mut(&key)
            .map(std::mem::take)
            .unwrap_or_default();
        if let Some(dry) = self.dry.remove(&key) {
            self.file_dry(key, &dry, false);
            for &d in &old.held {
                list_out(&mut self.dry_resident[d as usize], key);
            }
        }
        let mut new = std::mem::take(&mut self.spare);
        let dry = member.filter(|m| m.is_dry());
        match member {
            Some(m) if queues_kept => {
                new.fill_holdings(m, dry.is_some(), self.domains);
                std::mem::swap(&mut new.queued, &mut old.queued);
                std::mem::swap(&mut new.generations, &mut old.generations);
                std::mem::swap(&mut new.queues, &mut old.queues);
                // A queue of a domain it no longer holds nor plans may now move to a holder.
                for step in merge(&old.in_memory, &new.in_memory, |&d| d) {
                    if let Merged::Old(&d) = step {
                        self.unmoved_queues.push((key, d));
                    }
                }
            }
            Some(m) => new.fill(m, dry.is_some(), self.domains),
            None => new.clear(),
        }
        let mut touched = Vec::new();
        self.recount(key, &old, &new, queues_kept, &mut touched);
        for step in merge(&old.plan, &new.plan, |&d| d) {
            match step {
                Merged::New(&d) => {
                    self.holders.entry(d).or_default().insert(key);
                    self.holders_changed.insert(d);
                }
                Merged::Old(&d) => {
                    if let Some(keys) = self.holders.get_mut(&d) {
                        keys.remove(&key);
                        if keys.is_empty() {
                            self.holders.remove(&d);
                        }
                    }
                    self.holders_changed.insert(d);
                }
                Merged::Both(..) => {}
            }
        }
        if member.is_some() {
            match self.parts.get_mut(&key) {
                Some(part) => *part = new,
                None => {
                    self.parts.insert(key, new);
                }
            }
        } else {
            self.parts.remove(&key);
        }
        self.spare = old;
        self.refresh_touched(touched);
        if let Some(m) = dry {
            self.note_dry(key, m.cache_bytes);
        }
    }

    /// Member `key`, which ran dry (its part just made), as its draft would start, with a
    /// cache of `cache_bytes`.
    fn note_dry(&mut self, key: u32, cache_bytes: u64) {
        let part = &self.parts[&key];
        let resident = &part.held;
        let kept = |d: &&u32| wanted(&self.shown, **d);
        let dry = Dry {
            capacity: ((cache_bytes / self.largest) as usize)
                .max(1)
                .max(resident.len()),
            kept: resident.iter().filter(kept).count(),
            held: resident.len(),
            stands: part.plan == *resident,
        };
        for &d in resident {
            list_in(&mut self.dry_resident[d as usize], key);
        }
        self.file_dry(key, &dry, true);
        self.dry.insert(key, dry);
    }

    /// Dry member `key`, as `dry` says it stands, entered in (`add`) or taken out of the
    /// orders the rounds serve dry members in.
    fn file_dry(&mut self, key: u32, dry: &Dry, add: bool) {
        for (set, is_in) in [
            (&mut self.free, dry.has_free_slot()),
            (&mut self.differs, dry.differs()),
        ] {
            if is_in && add {
                set.insert(key);
            } else if is_in {
                set.remove(&key);
            }
        }
        if dry.has_free_slot() {
            if add {
                self.open.insert((dry.opening(), key));
            } else {
                self.open.remove(&(dry.opening(), key));
            }
        }
    }

    /// Domain `d`'s rays began (`wanted`) or ceased to count: the drafts of the dry members
    /// holding it keep it, or no longer.
    fn rewant(&mut self, d: u32, wanted: bool) {
        let keys = std::mem::take(&mut self.dry_resident[d as usize]);
        for &key in &keys {
            let Some(mut dry) = self.dry.get(&key).cloned() else {
                continue;
            };
            self.file_dry(key, &dry, false);
            step_by(&mut dry.kept, 1, wanted);
            self.file_dry(key, &dry, true);
            self.dry.insert(key, dry);
        }
        self.dry_resident[d as usize] = keys;
    }

    /// Every domain someone's current plan includes, with the keys of its holders, in key
    /// order: `rounds::current_holders` of the members this index was last updated with.
    pub fn holders(&self) -> &BTreeMap<u32, BTreeSet<u32>> {
        &self.holders
    }

    /// The domains whose holders changed since the last call (or since the index began), each
    /// with its holders now (none if nobody holds it any more), by domain: what turns the
    /// holders map of that time into [`RoundIndex::holders`]. Costs what changed, not the map.
    pub fn take_holder_changes(&mut self) -> Vec<(u32, Vec<u32>)> {
        std::mem::take(&mut self.holders_changed)
            .into_iter()
            .map(|d| {
                let keys = self.holders.get(&d);
                (d, keys.into_iter().flatten().copied().collect())
            })
            .collect()
    }

    /// Drafts the incremental rounds made since the index began: the members a round gave
    /// something, or whose plans it changed, not every dry member (a round planned from the
    /// whole cluster counts none here).
    pub fn drafts_made(&self) -> u64 {
        self.drafts_made
    }

    /// Members that ran dry since their last plan: those the next `dry_plans` plans (it
    /// drafts only those it gives something or whose plans change).
    pub fn dry_count(&self) -> usize {
        self.dry.len()
    }

    /// Counts member `key`'s part `new` in place of `old`: only the entries that differ
    /// (a merge of the two ascending lists of each kind; the queues' not at all if
    /// `queues_kept`: they are counted already), noting the domains whose figures moved in
    /// `touched`.
    fn recount(
        &mut self,
        key: u32,
        old: &Part,
        new: &Part,
        queues_kept: bool,
        touched: &mut Vec<u32>,
    ) {
        if !queues_kept {
            self.recount_queues(key, old, new, touched);
        }
        for (counts, old, new) in [
            (&mut self.held, &old.held, &new.held),
            (&mut self.in_memory, &old.in_memory, &new.in_memory),
        ] {
            for step in merge(old, new, |&d| d) {
                let (d, add) = match step {
                    Merged::Both(..) => continue,
                    Merged::Old(&d) => (d, false),
                    Merged::New(&d) => (d, true),
                };
                step_by(&mut counts[d as usize], 1, add);
                touched.push(d);
            }
        }
        let gained = list_member(
            &mut self.plan_holders,
            key,
            &old.holding_plan,
            &new.holding_plan,
        );
        self.newly_held.extend(gained);
    }

    /// The queue lists' part of [`RoundIndex::recount`].
    fn recount_queues(&mut self, key: u32, old: &Part, new: &Part, touched: &mut Vec<u32>) {
        for step in merge(&old.queued, &new.queued, |q| q.0) {
            let (gone, come) = match step {
                Merged::Both(o, n) if o == n => continue,
                Merged::Both(o, n) => (Some(o), Some(n)),
                Merged::Old(o) => (Some(o), None),
                Merged::New(n) => (None, Some(n)),
            };
            for (&(d, n, g), add) in gone
                .map(|q| (q, false))
                .into_iter()
                .chain(come.map(|q| (q, true)))
            {
                let (queued, by_generation) = (&mut self.queued, &mut self.by_generation);
                count_queue(queued, by_generation, self.oldest_first, (d, n, g), add);
                touched.push(d);
            }
        }
        for step in merge(&old.generations, &new.generations, |&g| g) {
            let (g, add) = match step {
                Merged::Both(..) => continue,
                Merged::Old(&g) => (g, false),
                Merged::New(&g) => (g, true),
            };
            tally(&mut self.generations, g, 1, add);
        }
        list_member(&mut self.queuers, key, &old.queues, &new.queues);
    }

    /// Asynchronous rounds: `plans` become round `round`'s, as
    /// [`adopt_plans`](super::rounds::adopt_plans) makes them, with the same rays moved to
    /// their new holders; only the queues of members changed since the last move, and of
    /// domains that gained a holder, are looked at (any other queue was looked at then and
    /// nothing about it changed). Returns the loads the plans ask for and the members changed;
    /// the index is up to date with them.
    pub fn adopt<M: AsMut<Member> + AsRef<Member>>(
        &mut self,
        members: &mut BTreeMap<u32, M>,
        plans: &[WorkerPlan],
        round: u64,
    ) -> (u64, BTreeSet<u32>) {
        let (loads, mut changed) = set_plans(members, plans, round);
        for &k in &changed {
            self.update(k, members.get(&k).map(AsRef::as_ref));
        }
        let moved = self.move_queued_to_holders(members);
        // Rays just moved went to members that keep them: nothing is left to move.
        self.unmoved.clear();
        self.unmoved_queues.clear();
        self.newly_held.clear();
        changed.extend(moved);
        (loads, changed)
    }

    /// `rounds::move_queued_to_holders` over the queues that may have a holder elsewhere,
    /// the figures taken along queue by queue (`RoundIndex::requeue`): a member that gave or
    /// received rays differs from its last update in those domains' queues alone, so its
    /// part is not made again (rebuilding and merging the whole part of every member touched
    /// was a third of a round at 4,096 x 32,768).
    fn move_queued_to_holders<M: AsMut<Member> + AsRef<Member>>(
        &mut self,
        members: &mut BTreeMap<u32, M>,
    ) -> BTreeSet<u32> {
        // Only a queue of a domain in some busy member's plan can move: the others are left
        // out before they are sorted (a predictive report names about a hundred queues, and
        // putting each in an ordered set was a sixth of its round, README "Simulator").
        let plan_holders = &self.plan_holders;
        let held =
            |&(_, d): &(u32, u32)| plan_holders.get(d as usize).is_some_and(|h| !h.is_empty());
        let mut candidates: Vec<(u32, u32)> = Vec::new();
        for &k in &self.unmoved {
            if let Some(part) = self.parts.get(&k) {
                candidates.extend(part.queues.iter().map(|&d| (k, d)).filter(held));
            }
        }
        for &d in &self.newly_held {
            candidates.extend(
                self.queuers[d as usize]
                    .iter()
                    .map(|&k| (k, d))
                    .filter(held),
            );
        }
        let parts = &self.parts;
        let queued_at = |&(k, d): &(u32, u32)| {
            parts
                .get(&k)
                .is_some_and(|p| p.queues.binary_search(&d).is_ok())
        };
        candidates.extend(
            self.unmoved_queues
                .iter()
                .copied()
                .filter(held)
                .filter(queued_at),
        );
        candidates.sort_unstable();
        candidates.dedup();
        let mut changed = BTreeSet::new();
        self.moved.clear();
        // Every queue changed, as (member, domain, before, after).
        let mut edits: Vec<(u32, u32, Queue, Queue)> = Vec::new();
        // Per new holder: domain -> (rays, oldest generation among them).
        let mut moved: BTreeMap<u32, BTreeMap<u32, (u64, Option<u32>)>> = BTreeMap::new();
        for (k, d) in candidates {
            let Some(&holder) = self.plan_holders[d as usize].last() else {
                continue;
            };
            let Some(m) = members.get_mut(&k).map(AsMut::as_mut) else {
                continue;
            };
            let Some(report) = m.report.as_mut() else {
                continue;
            };
            if m.plan.contains(&d) || report.resident.contains(&d) {
                continue;
            }
            let generation = report.oldest_generation.remove(&d);
            let rays = report.queued.remove(&d);
            if generation.is_some() || rays.is_some() {
                edits.push((k, d, (rays, generation), (None, None)));
            }
            if let Some(n) = rays {
                changed.insert(k);
                self.moved.entry(k).or_default().insert(d);
                let entry = moved.entry(holder).or_default().entry(d).or_default();
                entry.0 += n;
                entry.1 = entry.1.into_iter().chain(generation).min();
            }
        }
        // Each holder's queues before and after `deposit_moved` adds the rays to them.
        let deposits: Vec<(u32, u32)> = moved
            .iter()
            .flat_map(|(&h, queues)| queues.keys().map(move |&d| (h, d)))
            .collect();
        let before: Vec<Option<Queue>> = deposits
            .iter()
            .map(|&(h, d)| queue_of(members, h, d))
            .collect();
        changed.extend(deposit_moved(members, moved));
        for (&(h, d), before) in deposits.iter().zip(before) {
            if let (Some(before), Some(after)) = (before, queue_of(members, h, d)) {
                edits.push((h, d, before, after));
            }
        }
        for &(k, d, before, _) in &edits {
            self.unreported
                .entry(k)
                .or_default()
                .entry(d)
                .or_insert(before);
        }
        self.requeue(members, &edits);
        changed
    }

    /// Takes queue `edits` into the figures, each (member, domain, its queue before, after),
    /// in place of an update of each member named: valid when nothing else about those
    /// members changed since their last update (their parts differ in those queues alone).
    fn requeue<M: AsRef<Member>>(
        &mut self,
        members: &BTreeMap<u32, M>,
        edits: &[(u32, u32, Queue, Queue)],
    ) {
        let mut touched = Vec::new();
        let mut unknown = BTreeSet::new();
        for &(key, d, (rays, generation), (rays_now, generation_now)) in edits {
            let Some(part) = self.parts.get_mut(&key) else {
                // Never counted (the owner did not update it): counted whole below.
                unknown.insert(key);
                continue;
            };
            swap_generation(
                &mut part.generations,
                &mut self.generations,
                generation,
                generation_now,
            );
            if d >= self.domains {
                continue;
            }
            let queued = |rays: Option<u64>, g| rays.filter(|&n| n > 0).map(|n| (d, n, g));
            let (old, new) = (queued(rays, generation), queued(rays_now, generation_now));
            if old != new {
                let at = part.queued.partition_point(|q| q.0 < d);
                match new {
                    Some(q) if old.is_some() => part.queued[at] = q,
                    Some(q) => part.queued.insert(at, q),
                    None => {
                        part.queued.remove(at);
                    }
                }
                for (&(_, n, g), add) in old
                    .iter()
                    .map(|q| (q, false))
                    .chain(new.iter().map(|q| (q, true)))
                {
                    let (queued, by_generation) = (&mut self.queued, &mut self.by_generation);
                    count_queue(queued, by_generation, self.oldest_first, (d, n, g), add);
                }
                touched.push(d);
            }
            if rays.is_some() != rays_now.is_some() {
                let at = part.queues.partition_point(|&x| x < d);
                if rays_now.is_some() {
                    part.queues.insert(at, d);
                    list_in(&mut self.queuers[d as usize], key);
                } else {
                    part.queues.remove(at);
                    list_out(&mut self.queuers[d as usize], key);
                }
            }
        }
        self.refresh_touched(touched);
        for key in unknown {
            self.update(key, members.get(&key).map(AsRef::as_ref));
        }
    }

    /// Brings the ordered sets in line with the figures of the domains `touched`, or of
    /// every domain if the oldest generation reported changed (it decides which rays count).
    fn refresh_touched(&mut self, mut touched: Vec<u32>) {
        let oldest = if self.oldest_first {
            self.generations.keys().next().copied()
        } else {
            None
        };
        if oldest != self.oldest {
            self.oldest = oldest;
            for d in 0..self.domains {
                self.refresh(d);
            }
        } else {
            touched.sort_unstable();
            touched.dedup();
            for d in touched {
                self.refresh(d);
            }
        }
    }

    /// The domains whose queued rays the last [`RoundIndex::adopt`] moved from member `key`
    /// to their holders.
    pub fn moved_from(&self, key: u32) -> Option<&BTreeSet<u32>> {
        self.moved.get(&key)
    }

    /// Wanted domains nobody holds, fullest first (Fig. 5's `to_assign` as it stands now):
    /// after a round's plans are adopted, the domains the next members to run dry will be
    /// given, in that order.
    pub fn unheld(&self) -> impl Iterator<Item = u32> + '_ {
        self.unheld.iter().map(|&(_, d)| d)
    }

    /// Rays queued for `d` that count: under the oldest-generation rule only queues whose
    /// oldest rays are of the oldest generation, unless `d` is in memory somewhere.
    fn counted(&self, d: u32) -> u64 {
        let i = d as usize;
        match self.oldest {
            Some(g) if self.in_memory[i] == 0 => {
                self.by_generation[i].get(&g).copied().unwrap_or(0)
            }
            _ => self.queued[i],
        }
    }

    /// Brings domain `d`'s entries in the ordered sets in line with its figures.
    fn refresh(&mut self, d: u32) {
        let now = (self.counted(d), self.held[d as usize]);
        let before = std::mem::replace(&mut self.shown[d as usize], now);
        if before == now {
            return;
        }
        if (before.0 > 0) != (now.0 > 0) {
            self.rewant(d, now.0 > 0);
        }
        for ((rays, holders), add) in [(before, false), (now, true)] {
            if rays == 0 {
                continue;
            }
            if add {
                self.wanted += 1;
            } else {
                self.wanted -= 1;
            }
            if holders == 0 {
                let bit = &mut self.unheld_bits[d as usize / 64];
                if add {
                    self.unheld.insert((Reverse(rays), d));
                    *bit |= 1 << (d % 64);
                } else {
                    self.unheld.remove(&(Reverse(rays), d));
                    *bit &= !(1 << (d % 64));
                }
                continue;
            }
            let heat = Heat {
                domain: DomainId(d),
                rays,
                copies: u64::from(holders),
            };
            if !heat.splits(self.copy_rays) {
                continue;
            }
            if add {
                self.hot.insert(heat);
            } else {
                self.hot.remove(&heat);
            }
        }
    }

    /// New plans for the members that ran dry, equal to
    /// [`Cluster::dry_plans`](super::rounds::Cluster::dry_plans) over the same members.
    /// `members` must be the members this index was last updated with. Unless nobody is busy,
    /// a round costs what it hands out and the dry members whose plans change, not the dry
    /// members: at 4,096 workers most are dry with nothing to gain most of the time, and
    /// drafting each of them every round was half the coordinator's time (README, "4,096
    /// workers").
    pub fn dry_plans<M: AsRef<Member>>(
        &mut self,
        members: &BTreeMap<u32, M>,
        options: Options,
    ) -> Vec<WorkerPlan> {
        if self.dry.is_empty() {
            return Vec::new();
        }
        if self.dry.len() == members.len() {
            // Nobody is busy and no ray is queued anywhere (rays between members, or the
            // frame's end): the whole cluster's planner would find nothing to plan, after
            // reading every member's report (4.6 ms at 4,096 workers, 62 times in dynamic's
            // 256x256 frame there: a tenth of its coordinator's CPU); the index's counts say
            // so in one walk of the domains.
            if self.queued.iter().all(|&n| n == 0) {
                return Vec::new();
            }
            // Under the oldest-generation rule the index's plans first, then, if they change
            // nothing, every queue counted, from the whole cluster.
            if self.oldest_first {
                let plans = self.index_plans(members, options);
                if !plans.is_empty() {
                    return plans;
                }
            }
            let cluster = Cluster {
                members,
                domain_bytes: &self.domain_bytes,
                oldest_first: false,
                options,
            };
            return cluster.dry_plans();
        }
        self.index_plans(members, options)
    }

    /// The dry members' plans from the index's figures.
    fn index_plans<M: AsRef<Member>>(
        &mut self,
        members: &BTreeMap<u32, M>,
        options: Options,
    ) -> Vec<WorkerPlan> {
        if self.wanted == 0 {
            return Vec::new();
        }
        let mut drafts = DryDrafts {
            dry: &self.dry,
            parts: &self.parts,
            shown: &self.shown,
            free: &self.free,
            open: &mut self.open,
            taken: Vec::new(),
            reopened: BTreeSet::new(),
            drawn: BTreeMap::new(),
        };
        let mut hot = HotOverlay {
            hot: &mut self.hot,
            unheld: &self.unheld_bits,
            unheld_left: self.unheld.len(),
            shown: &self.shown,
            changed: BTreeMap::new(),
            copy_rays: self.copy_rays,
        };
        let to_assign = self
            .unheld
            .iter()
            .map(|&(Reverse(rays), d)| (DomainId(d), rays));
        pair_with_free_slots(&mut drafts, to_assign, |domain, rays| {
            hot.add_copy(domain.0, rays, 0)
        });
        extend_plans(&mut hot, &mut drafts, options);
        hot.undo();
        let mut drawn = drafts.put_back();
        let keys: BTreeSet<u32> = drawn.keys().chain(&self.differs).copied().collect();
        self.drafts_made += keys.len() as u64;
        keys.into_iter()
            .map(|key| {
                drawn
                    .remove(&key)
                    .unwrap_or_else(|| self.draft(key))
                    .finish()
            })
            .filter_map(|p| {
                let m = members.get(&p.worker.0)?.as_ref();
                sent_plan(p, m, self.domains)
            })
            .collect()
    }

    /// Dry member `key`'s draft (Fig. 5's first loop).
    fn draft(&self, key: u32) -> Draft<'static> {
        draft_of(key, &self.parts[&key], &self.dry[&key], &self.shown)
    }
}

/// Dry member `key`'s draft (Fig. 5's first loop): its resident domains in the scene (its
/// `part`'s), `dry`'s slots, keeping the domains with rays that count (`shown`).
fn draft_of(key: u32, part: &Part, dry: &Dry, shown: &[(u64, u32)]) -> Draft<'static> {
    let by_use: Vec<DomainId> = part.by_use.iter().copied().map(DomainId).collect();
    Draft::keeping_wanted(WorkerId(key), Cow::Owned(by_use), dry.capacity, |d| {
        wanted(shown, d.0)
    })
}

/// A round's drafts of the dry members: a member's draft is made when the round first gives
/// it a domain (`drawn`); until then the index's figures stand for it. The pairing's order
/// (`RoundIndex::open`) loses the drawn members while the round lasts (`taken`, put back
/// after), their drafts ordered apart (`reopened`).
struct DryDrafts<'a> {
    dry: &'a BTreeMap<u32, Dry>,
    parts: &'a BTreeMap<u32, Part>,
    shown: &'a [(u64, u32)],
    free: &'a BTreeSet<u32>,
    open: &'a mut BTreeSet<(Opening, u32)>,
    taken: Vec<(Opening, u32)>,
    reopened: BTreeSet<(Opening, u32)>,
    drawn: BTreeMap<u32, Draft<'static>>,
}

impl DryDrafts<'_> {
    /// The pairing's order as it was, and the drafts made.
    fn put_back(self) -> BTreeMap<u32, Draft<'static>> {
        self.open.extend(self.taken);
        self.drawn
    }
}

impl Drafts for DryDrafts<'_> {
    fn least_busy_open(&self) -> Option<WorkerId> {
        let first = match (self.open.first(), self.reopened.first()) {
            (Some(a), Some(b)) => a.min(b),
            (a, b) => a.or(b)?,
        };
        Some(WorkerId(first.1))
    }

    fn next_open(&self, after: Option<WorkerId>, idle: bool) -> Option<WorkerId> {
        let from = match after {
            Some(w) => w.0.checked_add(1)?,
            None => 0,
        };
        let key = if idle {
            // Every drawn member has something planned; the others keep what they keep.
            Opening::IDLE
                .iter()
                .filter_map(|&o| self.open.range((o, from)..=(o, u32::MAX)).next())
                .map(|&(_, key)| key)
                .min()
        } else {
            self.free.range(from..).copied().find(|key| {
                self.drawn
                    .get(key)
                    .is_none_or(|draft| draft.free_slots() > 0)
            })
        };
        key.map(WorkerId)
    }

    fn works_on(&self, worker: WorkerId, domain: DomainId) -> bool {
        match self.drawn.get(&worker.0) {
            Some(draft) => draft.works_on(domain),
            None => {
                wanted(self.shown, domain.0)
                    && self.parts[&worker.0].held.binary_search(&domain.0).is_ok()
            }
        }
    }

    fn load(&mut self, worker: WorkerId, domain: DomainId) {
        let key = worker.0;
        let draft = match self.drawn.entry(key) {
            std::collections::btree_map::Entry::Occupied(e) => {
                let draft = e.into_mut();
                self.reopened.remove(&(draft.opening(), key));
                draft
            }
            std::collections::btree_map::Entry::Vacant(e) => {
                let dry = &self.dry[&key];
                if dry.has_free_slot() && self.open.remove(&(dry.opening(), key)) {
                    self.taken.push((dry.opening(), key));
                }
                e.insert(draft_of(key, &self.parts[&key], dry, self.shown))
            }
        };
        draft.load(domain);
        if draft.free_slots() > 0 {
            self.reopened.insert((draft.opening(), key));
        }
    }
}

/// The hot order (`RoundIndex::unheld_bits`, then `RoundIndex::hot`) with this round's
/// copies counted in, the hot set put back as it was afterwards.
struct HotOverlay<'a> {
    hot: &'a mut BTreeSet<Heat>,
    /// The unheld domains, a bit each: those not in `changed` have no copy yet.
    unheld: &'a [u64],
    /// How many of them have no copy yet.
    unheld_left: usize,
    /// (rays that count, holders) of each domain (`RoundIndex::shown`).
    shown: &'a [(u64, u32)],
    /// Domains whose entry changed, with their entry now.
    changed: BTreeMap<u32, Option<Heat>>,
    /// [`Options::copy_rays`].
    copy_rays: u64,
}

impl HotOverlay<'_> {
    /// Counts one more holder of `domain`, which has `rays` rays and `copies` holders.
    fn add_copy(&mut self, domain: u32, rays: u64, copies: u64) {
        let heat = Heat {
            domain: DomainId(domain),
            rays,
            copies,
        };
        self.take(heat);
    }

    /// `heat`, an entry of the hot order, out of it, and back with one more copy if it still
    /// splits.
    fn take(&mut self, mut heat: Heat) {
        if heat.copies == 0 && !self.changed.contains_key(&heat.domain.0) {
            self.unheld_left -= 1;
        } else {
            self.hot.remove(&heat);
        }
        heat.copies += 1;
        let now = heat.splits(self.copy_rays).then_some(heat);
        if let Some(h) = now {
            self.hot.insert(h);
        }
        self.changed.insert(heat.domain.0, now);
    }

    /// The lowest unheld domain without a copy yet that is `eligible`.
    fn first_unheld(&self, eligible: impl Fn(DomainId) -> bool) -> Option<u32> {
        if self.unheld_left == 0 {
            return None;
        }
        for (i, &word) in self.unheld.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let d = i as u32 * 64 + bits.trailing_zeros();
                bits &= bits - 1;
                let first = Heat {
                    domain: DomainId(d),
                    rays: self.shown[d as usize].0,
                    copies: 0,
                };
                if !self.changed.contains_key(&d)
                    && first.splits(self.copy_rays)
                    && eligible(DomainId(d))
                {
                    return Some(d);
                }
            }
        }
        None
    }

    /// Puts every changed entry of the hot set back as the figures show it.
    fn undo(self) {
        for (d, now) in self.changed {
            if let Some(h) = now {
                self.hot.remove(&h);
            }
            let (rays, holders) = self.shown[d as usize];
            let heat = Heat {
                domain: DomainId(d),
                rays,
                copies: u64::from(holders),
            };
            if rays > 0 && holders > 0 && heat.splits(self.copy_rays) {
                self.hot.insert(heat);
            }
        }
    }
}

impl Hottest for HotOverlay<'_> {
    fn take_hottest(&mut self, eligible: impl Fn(DomainId) -> bool) -> Option<DomainId> {
        let heat = match self.first_unheld(&eligible) {
            Some(d) => Heat {
                domain: DomainId(d),
                rays: self.shown[d as usize].0,
                copies: 0,
            },
            None => *self.hot.iter().rev().find(|h| eligible(h.domain))?,
        };
        self.take(heat);
        Some(heat.domain)
    }

    fn exhausted(&self) -> bool {
        self.unheld_left == 0 && self.hot.is_empty()
    }
}

#[cfg(test)]
#[path = "round_index_tests.rs"]
mod tests;
