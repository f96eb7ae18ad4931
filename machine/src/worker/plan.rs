//! A worker's view of the round: the schedule it runs under, which domains it traces, which
//! are mapped here, who holds the others, and every tile's current epoch. From these alone
//! follows where each ray goes (here, to a peer, or nowhere when its tile restarted), so the
//! routing rule lives here once, without queues or sockets.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

use rayfarm_core::ray::RayRecord;
use rayfarm_core::schedule::keep_first_of_each;

use super::holder_map::{FormerHolders, HolderMap};

/// Where a frame's rays are traced: the job's schedule as the worker sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Image-plane (Fig. 3): rays never leave this worker; any domain is loaded on demand.
    ImagePlane,
    /// Domain (Fig. 4): this worker traces the domains it owns; rays go to the owners.
    Domain,
    /// Dynamic (Figs. 5-6): the planned domains, plus any domain still mapped here; rays go
    /// to this round's holders.
    Dynamic,
    /// Predictive (Park et al.): dynamic rounds, with each new ray queued in every domain
    /// along it at once (speculation) and the oldest generation traced first.
    Predictive,
    /// Hybrid (Reinhard et al.): camera rays and their shadow rays, coherent, are traced by
    /// the worker whose tile they are, loading what they need (`demand_loads`; off when the
    /// cache is too small, then they migrate too); incoherent rays migrate to the domains'
    /// owners. Owned domains' queues go first (data-parallel first). `rounds`: the owned
    /// domains did not fit the caches, so the coordinator gives each worker what its cache
    /// holds in asynchronous rounds instead of one owner map, and this worker traces only
    /// what it is planned or has mapped, as under the dynamic schedule.
    Hybrid { demand_loads: bool, rounds: bool },
}

/// Where a routed ray goes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Destination {
    /// Queued here.
    Local,
    /// To the worker at this peer address.
    Peer(String),
}

/// Rays sorted by `Plan::sort`.
#[derive(Debug, Default, PartialEq)]
pub struct Sorted {
    /// Rays to queue here, by domain.
    pub local: BTreeMap<u32, Vec<RayRecord>>,
    /// Rays to send, by peer address.
    pub peers: BTreeMap<String, Vec<RayRecord>>,
    /// Rays dropped: of an older epoch than their tile's, or for a domain the scene lacks.
    pub dropped: u64,
}

/// One domain's line of a holders message (`proto::DomainHolders`): in a whole map, the keys
/// holding it (`workers`); in a delta, the keys that began to hold it (`workers`) and those
/// that stopped (`lost`), so a hot domain's long list travels once, not every round. The
/// lists may be borrowed from the message: the simulator hands one holders message to every
/// worker of a view class, and copying it for each was a fifth of a 4,096-worker run.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HolderLine<'a> {
    pub domain: u32,
    pub workers: Cow<'a, [u32]>,
    pub lost: Cow<'a, [u32]>,
}

/// Adds to `changed` (when it is kept) the domains in one of `before` and `after` but not
/// both: a set of domains (the plan's or the mapped ones) moved from `before` to `after`.
fn note_moved(changed: &mut Option<BTreeSet<u32>>, before: &BTreeSet<u32>, after: &BTreeSet<u32>) {
    if let Some(changed) = changed {
        changed.extend(before.symmetric_difference(after).copied());
    }
}

/// See the module documentation.
#[derive(Clone, Debug)]
pub struct Plan {
    pub mode: Mode,
    /// The round whose plan this is.
    pub round: u64,
    /// Current epoch of every tile: rays of older epochs are dropped.
    pub epochs: Vec<u32>,
    /// Domains of the scene.
    domains: u32,
    /// This worker's key: never a destination.
    me: u32,
    /// Every worker's peer address by key (the frame's roster, shared with the frame's
    /// speculation): holders are kept as keys and turned into an address only when rays are
    /// sent to one.
    roster: Arc<HashMap<u32, String>>,
    work_on: BTreeSet<u32>,
    /// Domains mapped here now. Rays for them are traced here even when the plan gave the
    /// domain to no one or to another worker: any worker may trace any ray of a domain it
    /// has, and doing so costs neither a load nor a transfer.
    resident: BTreeSet<u32>,
    /// The same domains, least recently used first, as the cache last listed them: the
    /// order the report gives them in, which the coordinator evicts in.
    by_use: Vec<u32>,
    /// Other workers holding each domain this round, by key. Keys, not addresses: at 256
    /// workers under the dynamic schedule the addresses, in every member's copy of the map and
    /// in every round's messages, held gigabytes (README "Simulator"); a slot a domain, not a
    /// map of lists (see [`HolderMap`]).
    holders: HolderMap,
    /// Other workers that held each domain in an earlier round, by key, latest first: they
    /// may still have it loaded, so a load may ask them for it.
    former: FormerHolders,
    /// Domains the coordinator expects to give this worker next, most likely first (what
    /// it may prefetch once its own plan is loaded).
    next: Vec<u32>,
    /// Domains whose holders, plan or residency changed since [`Plan::take_changed`] last
    /// ran: only their queued rays can have begun to leave. `None`: any may have (before
    /// the first call, after a roster change or a peer's loss).
    changed: Option<BTreeSet<u32>>,
}

impl Plan {
    /// The plan before the first round: nothing traced, nothing held, every epoch zero; `me`
    /// is this worker's key in `roster`.
    pub fn new(
        mode: Mode,
        tiles: usize,
        domains: u32,
        me: u32,
        roster: Arc<HashMap<u32, String>>,
    ) -> Self {
        Plan {
            mode,
            round: 0,
            epochs: vec![0; tiles],
            domains,
            me,
            roster,
            work_on: BTreeSet::new(),
            resident: BTreeSet::new(),
            by_use: Vec::new(),
            holders: HolderMap::new(domains),
            former: FormerHolders::new(domains),
            next: Vec::new(),
            changed: None,
        }
    }

    /// Notes that whether `domain`'s queued rays leave may have changed.
    fn note_changed(&mut self, domain: u32) {
        if let Some(changed) = self.changed.as_mut() {
            changed.insert(domain);
        }
    }

    /// The domains whose queued rays may have begun to leave since the last call (their
    /// holders, this worker's plan or what is mapped here changed), ascending; `None` when
    /// any may have. Under the domain, dynamic and predictive schedules a ray is kept here
    /// exactly when it is not forwarded ([`Plan::forwards`]), so after a walk of the queues
    /// no other domain's rays can leave: [`Frame::take_for_peers`](super::frame::Frame)
    /// looks at these instead of every queue, on every holders message.
    pub fn take_changed(&mut self) -> Option<BTreeSet<u32>> {
        self.changed.replace(BTreeSet::new())
    }

    /// Domains this worker traces this round.
    pub fn work_on(&self) -> &BTreeSet<u32> {
        &self.work_on
    }

    /// Domains mapped here.
    pub fn resident(&self) -> &BTreeSet<u32> {
        &self.resident
    }

    /// Domains mapped here, least recently used first.
    pub fn resident_by_use(&self) -> &[u32] {
        &self.by_use
    }

    /// Domains the coordinator expects to give this worker next, most likely first.
    pub fn next(&self) -> &[u32] {
        &self.next
    }

    /// Records the coordinator's guess of this worker's next domains (with each plan).
    pub fn set_next(&mut self, next: impl IntoIterator<Item = u32>) {
        self.next = next.into_iter().filter(|&d| d < self.domains).collect();
    }

    /// Domains some other worker holds this round, ascending.
    pub fn held_elsewhere(&self) -> impl Iterator<Item = u32> + '_ {
        self.holders.held()
    }

    /// Where a load of `domain` may take its bytes from: the other workers holding it this
    /// round, then those that held it before, latest first (they may still have it loaded).
    pub fn holders_of(&self, domain: u32) -> Vec<String> {
        let now = self.holders.get(domain).iter().copied();
        let before = self.former.get(domain);
        let mut keys: Vec<u32> = Vec::new();
        for w in now.chain(before) {
            if !keys.contains(&w) {
                keys.push(w);
            }
        }
        keys.iter()
            .filter_map(|k| self.roster.get(k).cloned())
            .collect()
    }

    /// Records that `gone` no longer hold `domain` (they may still have it loaded).
    fn note_former(&mut self, domain: u32, gone: impl IntoIterator<Item = u32>) {
        self.former.note(domain, gone);
    }

    /// The other workers holding `domain` now, in key order (as the coordinator's messages
    /// made them; former holders are not named).
    pub fn holder_keys(&self, domain: u32) -> &[u32] {
        self.holders.get(domain)
    }

    /// Whether some other worker holds `domain` this round.
    pub fn is_held_elsewhere(&self, domain: u32) -> bool {
        self.holders.contains(domain)
    }

    /// Adopts a round's plan (its holders as [`Plan::set_holders`] takes them).
    pub fn set_round<'a>(
        &mut self,
        round: u64,
        work_on: impl IntoIterator<Item = u32>,
        holders: impl IntoIterator<Item = HolderLine<'a>>,
        delta: bool,
    ) {
        self.round = round;
        let work_on: BTreeSet<u32> = work_on.into_iter().collect();
        note_moved(&mut self.changed, &self.work_on, &work_on);
        self.work_on = work_on;
        self.set_holders(holders, delta);
    }

    /// Adopts new holders of the domains (worker keys), keeping this worker's own plan; this
    /// worker is left out. `delta`: only the domains listed changed, each by the keys it gained
    /// and lost (a gained key goes in at its place in key order, the order the coordinator's
    /// lists have, so the list is the coordinator's and a ray's holder the same as from a whole
    /// map); the others keep theirs. Otherwise the list is the whole map. Deltas keep the
    /// coordinator's broadcast of a round to what changed, where whole lists to every member
    /// grew with workers x holders (README "Simulator").
    pub fn set_holders<'a>(
        &mut self,
        holders: impl IntoIterator<Item = HolderLine<'a>>,
        delta: bool,
    ) {
        if delta {
            for line in holders {
                self.note_changed(line.domain);
                self.change_holders(line);
            }
            return;
        }
        // A whole map may change any domain: the next walk looks at every queue.
        self.changed = None;
        let before = std::mem::replace(&mut self.holders, HolderMap::new(self.domains));
        for line in holders {
            self.holders
                .set(line.domain, line.workers.into_owned(), self.me);
        }
        // Who held a domain before and not now, listed or left out (nobody holds it now).
        for d in before.held() {
            let now = self.holders.get(d);
            let gone = before.get(d).iter().filter(|k| !now.contains(k)).copied();
            self.former.note(d, gone);
        }
    }

    /// Applies one domain's line of a delta: its lost keys out, its gained keys in.
    fn change_holders(&mut self, line: HolderLine) {
        let HolderLine {
            domain: d,
            workers: gained,
            mut lost,
        } = line;
        // The coordinator sends them sorted; a line that is not is sorted here, in a copy.
        if !lost.is_sorted() {
            lost.to_mut().sort_unstable();
        }
        let mut gone = Vec::new();
        self.holders.change(d, &lost, &gained, self.me, &mut gone);
        self.note_former(d, gone);
    }

    /// Records which domains are mapped here now, least recently used first (a domain named
    /// twice counts where it is first named).
    pub fn set_resident(&mut self, by_use: impl IntoIterator<Item = u32>) {
        self.by_use.clear();
        self.by_use.extend(by_use);
        let resident: BTreeSet<u32> = self.by_use.iter().copied().collect();
        if resident.len() < self.by_use.len() {
            keep_first_of_each(&mut self.by_use);
        }
        note_moved(&mut self.changed, &self.resident, &resident);
        self.resident = resident;
    }

    /// The frame's roster changed (a worker joined): keys now name these addresses.
    pub fn set_roster(&mut self, roster: Arc<HashMap<u32, String>>) {
        self.roster = roster;
        // A holder the roster did not name kept its rays here (`peer_of`): they may leave now.
        self.changed = None;
    }

    /// The frame's roster: every worker's peer address by key.
    pub fn roster(&self) -> &Arc<HashMap<u32, String>> {
        &self.roster
    }

    /// Sends nothing more to `peers` (their addresses: they are gone); their domains' rays
    /// wait here for the next plan.
    pub fn forget_peers(&mut self, peers: &[String]) {
        let gone: BTreeSet<u32> = self
            .roster
            .iter()
            .filter(|(_, address)| peers.contains(address))
            .map(|(&k, _)| k)
            .collect();
        self.holders.retain_keys(|k| !gone.contains(&k));
        self.former.retain_keys(|k| !gone.contains(&k));
        self.changed = None;
    }

    /// Raises tiles' epochs (never lowers them).
    pub fn bump_epochs<'a>(&mut self, bumps: impl IntoIterator<Item = (&'a u32, &'a u32)>) {
        for (&tile, &epoch) in bumps {
            if let Some(e) = self.epochs.get_mut(tile as usize) {
                *e = (*e).max(epoch);
            }
        }
    }

    /// Whether `domain` is planned here or mapped here.
    pub fn planned_or_resident(&self, domain: u32) -> bool {
        self.work_on.contains(&domain) || self.resident.contains(&domain)
    }

    /// Whether rays queued here for `domain` leave for its holders elsewhere. Under the
    /// domain schedule only the owner ever traces a domain, however many are mapped here: a
    /// ray queued before the plan came (a pass that ended first) must still go to it.
    /// Otherwise a domain planned or mapped here is traced here.
    pub fn forwards(&self, domain: u32) -> bool {
        match self.mode {
            Mode::Domain => !self.work_on.contains(&domain),
            _ => !self.planned_or_resident(domain),
        }
    }

    /// Whether this worker may trace the queue of `domain` now.
    pub fn traces(&self, domain: u32) -> bool {
        match self.mode {
            // Every ray queued under hybrid with owners was kept here on purpose (see `keeps`).
            Mode::ImagePlane | Mode::Hybrid { rounds: false, .. } => true,
            Mode::Hybrid { rounds: true, .. } => self.planned_or_resident(domain),
            Mode::Domain => self.work_on.contains(&domain),
            Mode::Dynamic | Mode::Predictive => self.planned_or_resident(domain),
        }
    }

    /// Whether `ray` stays on this worker.
    fn keeps(&self, ray: &RayRecord) -> bool {
        match self.mode {
            Mode::Hybrid { demand_loads, .. } => {
                self.planned_or_resident(ray.domain) || (demand_loads && ray.depth == 0)
            }
            _ => self.traces(ray.domain),
        }
    }

    /// Whether a ray belongs to the current epoch of its tile.
    pub fn is_current(&self, tile: u32, epoch: u32) -> bool {
        self.epochs.get(tile as usize) == Some(&epoch)
    }

    /// Where a ray goes this round: here if this worker traces the domain or no one does (it
    /// waits for a later round), else to one of its holders, chosen by pixel so that a hot
    /// domain's rays spread evenly over its holders.
    pub fn destination(&self, ray: &RayRecord) -> Destination {
        match self.peer_of(ray) {
            Some(peer) => Destination::Peer(peer.to_string()),
            None => Destination::Local,
        }
    }

    /// [`Plan::destination`] without the copy of the address: `None` is here (also for a
    /// holder the roster does not name, which the coordinator never sends: it sends the
    /// roster behind a frame's StartFrame, and with a new worker, before naming it a holder).
    fn peer_of(&self, ray: &RayRecord) -> Option<&str> {
        if self.keeps(ray) {
            return None;
        }
        let ws = self.holders.get(ray.domain);
        if ws.is_empty() {
            return None;
        }
        let key = ws[ray.pixel as usize % ws.len()];
        self.roster.get(&key).map(String::as_str)
    }

    /// Sorts rays by destination, dropping those of an older epoch than their tile's and
    /// those for a domain the scene lacks.
    ///
    /// This runs on every ray a worker makes or receives (2.3 M a frame per predictive
    /// worker on big48), so it decides per domain and allocates per destination, not per
    /// ray: whether a domain's rays stay here and who holds it is found once a batch (each
    /// ray asked the plan's sets, the holder map and the roster, and compared addresses as
    /// strings to find its list: 7.8% of a predictive worker's event loop, perf, README
    /// "Benchmarks"), a ray then only picks its holder by pixel, the destinations' rays are
    /// counted first so that each list is allocated once at its size, and rays that all go
    /// to one place keep their vector. The result is what [`Plan::destination`] says ray by
    /// ray, in the rays' order.
    pub fn sort(&self, rays: Vec<RayRecord>) -> Sorted {
        /// Where one ray goes: an index into the local or the peer lists.
        #[derive(Clone, Copy)]
        enum To {
            Dropped,
            Local(u32),
            Peer(u32),
        }
        /// What the rays of one domain do in this batch.
        #[derive(Clone, Copy)]
        enum Route<'a> {
            /// Queued here, in local list `i`.
            Here(u32),
            /// To the holder its pixel picks among these keys.
            Holders(&'a [u32]),
        }
        let mut sorted = Sorted::default();
        let mut local_index: BTreeMap<u32, u32> = BTreeMap::new();
        let mut local_counts: Vec<usize> = Vec::new();
        // Peer lists by address (two keys of one address share a list, as when the ray's
        // address chose it), found once a key: a ray looks its holder's key up.
        let mut peer_index: BTreeMap<&str, u32> = BTreeMap::new();
        let mut peer_counts: Vec<usize> = Vec::new();
        let mut by_key: BTreeMap<u32, Option<u32>> = BTreeMap::new();
        // By domain and, where the schedule keeps a domain's camera rays apart from the rest
        // (hybrid's demand loads), whether the ray is a camera ray.
        let mut routes: BTreeMap<(u32, bool), Route<'_>> = BTreeMap::new();
        fn slot<K: Ord>(index: &mut BTreeMap<K, u32>, counts: &mut Vec<usize>, key: K) -> u32 {
            let next = counts.len() as u32;
            let i = *index.entry(key).or_insert(next);
            if i == next {
                counts.push(0);
            }
            i
        }
        let camera_apart = matches!(
            self.mode,
            Mode::Hybrid {
                demand_loads: true,
                ..
            }
        );
        let mut to = Vec::with_capacity(rays.len());
        for ray in &rays {
            if !self.is_current(ray.tile, ray.epoch) || ray.domain >= self.domains {
                sorted.dropped += 1;
                to.push(To::Dropped);
                continue;
            }
            let camera = camera_apart && ray.depth == 0;
            let route = *routes.entry((ray.domain, camera)).or_insert_with(|| {
                let ws = self.holders.get(ray.domain);
                if self.keeps(ray) || ws.is_empty() {
                    Route::Here(slot(&mut local_index, &mut local_counts, ray.domain))
                } else {
                    Route::Holders(ws)
                }
            });
            let dest = match route {
                Route::Here(i) => To::Local(i),
                Route::Holders(ws) => {
                    let key = ws[ray.pixel as usize % ws.len()];
                    let peer = *by_key.entry(key).or_insert_with(|| {
                        // A holder the roster does not name: the ray stays here (`peer_of`).
                        let address = self.roster.get(&key)?;
                        Some(slot(&mut peer_index, &mut peer_counts, address.as_str()))
                    });
                    match peer {
                        Some(i) => To::Peer(i),
                        None => To::Local(slot(&mut local_index, &mut local_counts, ray.domain)),
                    }
                }
            };
            match dest {
                To::Local(i) => local_counts[i as usize] += 1,
                To::Peer(i) => peer_counts[i as usize] += 1,
                To::Dropped => {}
            }
            to.push(dest);
        }
        if sorted.dropped == 0 && local_counts.len() + peer_counts.len() == 1 {
            // One destination: the rays go as they came, in order.
            if let Some((&d, _)) = local_index.first_key_value() {
                sorted.local.insert(d, rays);
            } else if let Some((&p, _)) = peer_index.first_key_value() {
                sorted.peers.insert(p.to_string(), rays);
            }
            return sorted;
        }
        let mut local: Vec<Vec<RayRecord>> = local_counts
            .iter()
            .map(|&n| Vec::with_capacity(n))
            .collect();
        let mut peers: Vec<Vec<RayRecord>> =
            peer_counts.iter().map(|&n| Vec::with_capacity(n)).collect();
        for (ray, to) in rays.into_iter().zip(to) {
            match to {
                To::Dropped => {}
                To::Local(i) => local[i as usize].push(ray),
                To::Peer(i) => peers[i as usize].push(ray),
            }
        }
        sorted.local = local_index
            .into_iter()
            .map(|(d, i)| (d, std::mem::take(&mut local[i as usize])))
            .collect();
        sorted.peers = peer_index
            .into_iter()
            .map(|(p, i)| (p.to_string(), std::mem::take(&mut peers[i as usize])))
            .collect();
        sorted
    }
}

#[cfg(test)]
#[path = "plan_tests.rs"]
mod tests;
