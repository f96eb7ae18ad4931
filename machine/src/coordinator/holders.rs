//! What the frame's members were last told of who holds which domain, so an asynchronous
//! round tells them only what changed.
//!
//! Every asynchronous round changes the plans of the members that ran dry, and every member
//! must learn the new holders to route its rays. Sending each the whole map made a round
//! O(members x held domains) in bytes: at 1,024 workers over 8,192 domains the coordinator's
//! messages of one round were hundreds of megabytes, more than its link sends before the next
//! round, and the simulator ran out of memory holding them (README "Simulator"). A round
//! changes the holders of the few domains the planned members gained or dropped, so members
//! that already hold the last map sent get only those domains (`holders_delta`).
//!
//! Asynchronous rounds send the holders map of every member's plan, which the frame's
//! `RoundIndex` keeps member by member with the domains whose holders changed since it was last
//! asked (`RoundIndex::take_holder_changes`): once the last map sent is that map, a round
//! applies those changes only (`SentHolders::update_from_index`), so it costs what the round
//! changed, not a rebuild and a comparison of the whole map (at 1,024 workers that was about a
//! tenth of a simulated frame, README "Simulator").
//!
//! A delta names each changed domain's gained and lost keys (`HolderChange`), not its whole
//! list: under the dynamic schedule every dry member's free cache slots get copies of the
//! hottest domains, so a hot domain's holders are hundreds of keys long and change by one or
//! two every round. Sending the whole list of every changed domain to every member cost the
//! coordinator 7.2 GB of queued messages at 4,096 workers x 32,768 domains (heaptrack, README
//! "Simulator"); what changed is a few keys a domain.
//!
//! The one map kept is the latest, with the members known to hold a map they can be brought
//! up to it from; a member that joined, or that missed a map (a barrier round plans only some
//! members), gets the whole map once. A round's changes are not sent to every busy member:
//! they wait, folded by view class (`Pending`), and go out with a member's next plan, or to
//! every member at the next flush, at most once per holders interval
//! (`RunningFrame::flush_holders`): one message a round to every busy member was 91% of a
//! 256-worker dynamic simulation's messages. Control streams are ordered, so after a flush
//! every member holds the latest map, less the peers it was told are lost (whose domains the
//! next delta lists, since the lost member is no holder any more).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::time::Duration;

use rayfarm_proto as proto;

use crate::Time;

/// Holders by domain, as member keys.
pub type HolderMap = BTreeMap<u32, Vec<u32>>;

/// Members per view class: how many members share one view of the holders (see
/// [`view`]). Up to twice this many members, there is one class and every member sees every
/// holder.
pub const MEMBERS_PER_CLASS: usize = 64;

/// View classes for a frame of `members` members.
pub fn view_classes(members: usize) -> u32 {
    (members / MEMBERS_PER_CLASS).max(1) as u32
}

/// The class of member `key` among `classes` view classes.
pub fn class_of(key: u32, classes: u32) -> u32 {
    key % classes.max(1)
}

/// What a member of view class `class` is told of a domain held by `holders` (ascending):
/// the holders of its own class if there are any, else every holder. A member routes a ray
/// to one holder of the domain anyway (by pixel), so it needs no more than a few of them;
/// members of different classes send to different holders, so the rays still spread over all
/// of them. Under the dynamic schedule a hot domain has hundreds of holders and gains or loses
/// some every round; with views only the members of the classes of those holders hear of it
/// (about `MEMBERS_PER_CLASS` members, not every member): at 4,096 workers the broadcast of
/// every change to everyone outgrew the coordinator's link (README "Simulator").
pub fn view(holders: &[u32], class: u32, classes: u32) -> Vec<u32> {
    let own: Vec<u32> = holders
        .iter()
        .copied()
        .filter(|&k| class_of(k, classes) == class)
        .collect();
    if own.is_empty() {
        holders.to_vec()
    } else {
        own
    }
}

/// One line of a delta: the keys a view gained and lost, each ascending.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ViewChange {
    pub gained: Vec<u32>,
    pub lost: Vec<u32>,
}

impl ViewChange {
    /// What turns `before` into `now` (both ascending), or `None` if they are the same: one
    /// merge of the two lists (a hot domain's are hundreds of keys long).
    fn between(before: &[u32], now: &[u32]) -> Option<ViewChange> {
        let (mut gained, mut lost) = (Vec::new(), Vec::new());
        let (mut i, mut j) = (0, 0);
        while i < before.len() || j < now.len() {
            match (before.get(i), now.get(j)) {
                (Some(b), Some(n)) if b == n => (i, j) = (i + 1, j + 1),
                (Some(&b), Some(&n)) if b < n => {
                    lost.push(b);
                    i += 1;
                }
                (Some(_), Some(&n)) | (None, Some(&n)) => {
                    gained.push(n);
                    j += 1;
                }
                (Some(&b), None) => {
                    lost.push(b);
                    i += 1;
                }
                (None, None) => break,
            }
        }
        (!gained.is_empty() || !lost.is_empty()).then_some(ViewChange { gained, lost })
    }

    /// Folds `next` in after this line.
    fn fold(&mut self, next: &ViewChange) {
        for &k in &next.lost {
            if let Ok(i) = self.gained.binary_search(&k) {
                self.gained.remove(i);
            }
            if let Err(i) = self.lost.binary_search(&k) {
                self.lost.insert(i, k);
            }
        }
        for &k in &next.gained {
            if let Err(i) = self.gained.binary_search(&k) {
                self.gained.insert(i, k);
            }
        }
    }

    /// Whether the line says nothing.
    fn is_empty(&self) -> bool {
        self.gained.is_empty() && self.lost.is_empty()
    }
}

/// How one domain's holders changed between two maps: its holders before and now, each
/// ascending.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HolderChange {
    pub domain: u32,
    pub before: Vec<u32>,
    pub now: Vec<u32>,
}

impl HolderChange {
    /// What turns `before` (none: nobody held it) into `now` for `domain`, or `None` if they
    /// hold the same keys.
    pub fn between(domain: u32, before: Option<&Vec<u32>>, now: &[u32]) -> Option<HolderChange> {
        let mut old: Vec<u32> = before.cloned().unwrap_or_default();
        let mut new: Vec<u32> = now.to_vec();
        old.sort_unstable();
        new.sort_unstable();
        (old != new).then_some(HolderChange {
            domain,
            before: old,
            now: new,
        })
    }

    /// The whole change: what a member that sees every holder is told.
    pub fn whole(&self) -> ViewChange {
        ViewChange::between(&self.before, &self.now).unwrap_or_default()
    }

    /// What each view class is told of this change among `classes` (see [`ClassLines`]).
    /// Costs the holders before and now, counted by class, and the keys that changed: a
    /// class with a holder both before and now is told the change's keys of its class, and
    /// only a class that gains its first holder or loses its last one is told a list of its
    /// own. Splitting every hot domain's hundreds of holders into a list a class, for each
    /// domain a round changed, was two thirds of the coordinator's CPU at 4,096 workers
    /// (perf of a 4,096-worker dynamic simulation, README "Simulator").
    pub fn lines(&self, classes: u32) -> ClassLines {
        let rest = ViewChange::between(&self.before, &self.now);
        let classes = classes.max(1);
        // By class: its holders (before, now).
        let mut count = vec![(0u32, 0u32); classes as usize];
        for &k in &self.before {
            count[class_of(k, classes) as usize].0 += 1;
        }
        for &k in &self.now {
            count[class_of(k, classes) as usize].1 += 1;
        }
        let of_class = |keys: &[u32], class: u32| -> Vec<u32> {
            keys.iter()
                .copied()
                .filter(|&k| class_of(k, classes) == class)
                .collect()
        };
        let own = (0..classes)
            .zip(count)
            .filter(|&(_, (before, now))| before > 0 || now > 0)
            .map(|(class, (before, now))| {
                let line = if before == 0 {
                    // Saw every holder before, its own now.
                    ViewChange::between(&self.before, &of_class(&self.now, class))
                } else if now == 0 {
                    // Saw its own before, every holder now.
                    ViewChange::between(&of_class(&self.before, class), &self.now)
                } else {
                    rest.as_ref().map(|whole| ViewChange {
                        gained: of_class(&whole.gained, class),
                        lost: of_class(&whole.lost, class),
                    })
                };
                (class, line.filter(|l| !l.is_empty()))
            })
            .collect();
        ClassLines {
            domain: self.domain,
            rest,
            own,
        }
    }
}

/// One changed domain's delta lines by view class: a class with a holder of the domain before
/// or now is in `own`, with its line there (`None`: its view did not change); every other
/// class sees every holder and is told `rest`. Under the dynamic schedule most domains have a
/// holder or two, so most classes are told `rest`: kept once, not once a class.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ClassLines {
    pub domain: u32,
    pub rest: Option<ViewChange>,
    pub own: BTreeMap<u32, Option<ViewChange>>,
}

impl ClassLines {
    /// The line view `class` is told, if its view changed.
    pub fn of(&self, class: u32) -> Option<&ViewChange> {
        match self.own.get(&class) {
            Some(line) => line.as_ref(),
            None => self.rest.as_ref(),
        }
    }

    /// The same lines with `keep` applied to each line's gained keys, and a line that says
    /// nothing then as no line (`None`).
    pub fn keeping(mut self, keep: impl Fn(u32) -> bool) -> ClassLines {
        let trim = |line: &mut Option<ViewChange>| {
            if let Some(l) = line {
                l.gained.retain(|&k| keep(k));
                if l.is_empty() {
                    *line = None;
                }
            }
        };
        trim(&mut self.rest);
        self.own.values_mut().for_each(trim);
        self
    }
}

/// One domain's pending lines: the fold of what the classes that have not held it since the
/// last flush were told (`rest`, one fold for all of them), and the fold of each class that
/// has (`own`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
struct DomainPending {
    rest: ViewChange,
    own: BTreeMap<u32, ViewChange>,
}

impl DomainPending {
    /// View `class`'s line, if it says something.
    fn line(&self, class: u32) -> Option<&ViewChange> {
        Some(self.own.get(&class).unwrap_or(&self.rest)).filter(|l| !l.is_empty())
    }
}

/// The holder changes since the members were last all told, folded into one line a domain and
/// view class: what a member of the class that holds any map sent since is told to bring it up
/// to date. A busy member needs the holders only to route its rays, and every asynchronous
/// round changed some: one `Holders` a round to every busy member was 91% of a 256-worker
/// dynamic simulation's 15.9 M messages (README "Simulator"). The changes now wait here and go
/// out with the member's next plan, or to every member at most once per holders interval
/// (`RunningFrame::flush_holders`).
///
/// A line keeps every key the domain lost and every key it gained and did not lose after
/// (`ViewChange::fold`: lost keys of either out, then those gained and not lost after, and
/// those gained after, in; a worker takes a line's lost keys out before it puts the gained
/// ones in). So the fold of the changes since version `v` brings a member at any version from
/// `v` on to the latest: what it applied already is taken out and put back as the latest has
/// it. A member told by its plan, then by the flush, is never out of step (a test applies the
/// fold to workers' maps at every version between).
///
/// The classes that have held a domain since the last flush are folded apart; the others
/// were told the same lines, so they share one fold. A class that first holds the domain
/// starts from the shared fold, which is what it was told until then (had it held the domain
/// earlier, it would have been apart since). Folding each change into every class's lines cost
/// 44% of a round at 4,096 workers (64 classes) over 32,768 domains; a change now costs the
/// classes of its holders, and such a round went from 130 to 76 us (README "Simulator"). A
/// property test holds every class's lines equal to its own fold.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Pending {
    /// By domain.
    lines: BTreeMap<u32, DomainPending>,
    /// Domains whose `rest` line says something.
    rest_lines: usize,
    /// By class: its lines that say something less `rest_lines` (its own lines counted in
    /// place of the shared ones they stand for).
    own_lines: Vec<isize>,
    /// By class: the round that last added to its lines (a member told at or after it holds
    /// them).
    changed_round: Vec<u64>,
}

impl Pending {
    /// Nothing pending for any of `classes` view classes.
    pub fn new(classes: u32) -> Pending {
        let n = classes.max(1) as usize;
        Pending {
            lines: BTreeMap::new(),
            rest_lines: 0,
            own_lines: vec![0; n],
            changed_round: vec![0; n],
        }
    }

    /// Folds round `round`'s delta (a [`ClassLines`] per changed domain, lines that say
    /// nothing left out) in after the others.
    pub fn absorb(&mut self, delta: &[ClassLines], round: u64) {
        let classes = self.changed_round.len();
        // A class is told something by the round if a domain told it its own line, or told
        // `rest` while it was not named (`named`: how many domains that told `rest` named it).
        let mut told = vec![false; classes];
        let (mut rest_domains, mut named) = (0, vec![0usize; classes]);
        for change in delta {
            if change.rest.is_none() && change.own.is_empty() {
                continue;
            }
            let entry = self.lines.entry(change.domain).or_default();
            for (&class, line) in &change.own {
                let c = class as usize;
                // First held since the flush: it was told the shared lines until now, so its
                // own fold starts from them (and stands for them in the count).
                let own = entry.own.entry(class).or_insert_with(|| entry.rest.clone());
                if let Some(line) = line {
                    if own.is_empty() {
                        self.own_lines[c] += 1;
                    }
                    own.fold(line);
                    told[c] = true;
                }
            }
            let Some(rest) = &change.rest else {
                continue;
            };
            rest_domains += 1;
            for &class in change.own.keys() {
                named[class as usize] += 1;
            }
            // The classes apart that this change does not name see every holder: `rest`.
            for (&class, own) in entry.own.iter_mut() {
                if change.own.contains_key(&class) {
                    continue;
                }
                if own.is_empty() {
                    self.own_lines[class as usize] += 1;
                }
                own.fold(rest);
            }
            if entry.rest.is_empty() {
                self.rest_lines += 1;
                for &class in entry.own.keys() {
                    self.own_lines[class as usize] -= 1;
                }
            }
            entry.rest.fold(rest);
        }
        for (class, changed) in self.changed_round.iter_mut().enumerate() {
            if told[class] || named[class] < rest_domains {
                *changed = round;
            }
        }
    }

    /// Whether nothing changed since the members were last all told.
    pub fn is_empty(&self) -> bool {
        self.lines.is_empty()
    }

    /// Lines that say something pending for view `class`.
    pub fn len(&self, class: u32) -> usize {
        let own = self.own_lines.get(class as usize).copied().unwrap_or(0);
        (self.rest_lines as isize + own).max(0) as usize
    }

    /// The round that last added to view `class`'s lines (0: none since the last flush).
    pub fn changed_round(&self, class: u32) -> u64 {
        self.changed_round.get(class as usize).copied().unwrap_or(0)
    }

    /// View `class`'s line of `domain`, if one is pending.
    fn line_of(&self, domain: u32, class: u32) -> Option<&ViewChange> {
        self.lines.get(&domain)?.line(class)
    }

    /// View `class`'s folded lines as a delta's, ascending by domain; gained keys that
    /// `is_member` refuses are left out (a member lost since: the workers forgot it, and a
    /// later round lists it lost).
    pub fn lines(&self, class: u32, is_member: impl Fn(u32) -> bool) -> Vec<proto::DomainHolders> {
        // Walked in order, each domain's entry at hand: looking each up again by its key was a
        // sixth of predictive's coordinator at 4,096 workers (40,000 lines a flush).
        self.lines
            .iter()
            .filter_map(|(&d, entry)| Self::line(d, entry.line(class)?, &is_member))
            .collect()
    }

    /// View `class`'s folded lines of `domains` only (ascending), as [`Pending::lines`] makes
    /// them, and whether they are every line pending for it. A line brings its domain to the
    /// latest holders whatever version since the last flush a member holds (see above), so a
    /// member may be told some domains' lines now and the rest later: a round tells the
    /// members it plans, or whose rays it moved, the lines of the domains it changed, which
    /// cost what the round changed, not every line folded since the last flush (at 1,024
    /// workers and a 100 ms interval, hundreds of lines in each of ten messages a round:
    /// README "Simulator").
    pub fn lines_of(
        &self,
        class: u32,
        domains: &BTreeSet<u32>,
        is_member: impl Fn(u32) -> bool,
    ) -> (Vec<proto::DomainHolders>, bool) {
        let mut found = 0;
        let lines = domains
            .iter()
            .filter_map(|&d| self.line_of(d, class).map(|l| (d, l)))
            .inspect(|_| found += 1)
            .filter_map(|(d, l)| Self::line(d, l, &is_member))
            .collect();
        (lines, found == self.len(class))
    }

    /// One folded line as a delta's, if it says anything once non-members are left out.
    fn line(
        domain: u32,
        l: &ViewChange,
        is_member: &impl Fn(u32) -> bool,
    ) -> Option<proto::DomainHolders> {
        let workers: Vec<u32> = l.gained.iter().copied().filter(|&k| is_member(k)).collect();
        (!workers.is_empty() || !l.lost.is_empty()).then(|| proto::DomainHolders {
            domain,
            workers,
            lost: l.lost.clone(),
        })
    }
}

/// See the module documentation.
#[derive(Clone, Debug, Default)]
pub struct SentHolders {
    /// The latest map: what a member is brought up to by what it is told next.
    sent: HolderMap,
    /// Members that hold a map from the last flush on (or the whole of the last barrier or
    /// owner map), so that their class's `pending` brings them up to date; the others are
    /// told the whole map.
    synced: BTreeSet<u32>,
    /// Whether `sent` is the map of every member's plan as of the index's last taken changes
    /// (else it is a barrier round's map, the owner map, or none yet).
    in_step: bool,
    /// The changes since the last flush, folded by view class.
    pending: Pending,
    /// By member: the round whose holders it was last told (its plan's or a flush's).
    told: HashMap<u32, u64>,
    /// Whether a round changed something since the last flush (or left a member unsynced).
    dirty: bool,
    /// When the members were last all told.
    last_flush: Option<Time>,
}

impl SentHolders {
    /// Starts over: no member holds any map (a new frame or subframe on the workers).
    pub fn reset(&mut self) {
        *self = SentHolders::default();
    }

    /// `key` left the frame, or joined it with no map yet.
    pub fn forget(&mut self, key: u32) {
        self.synced.remove(&key);
        self.told.remove(&key);
    }

    /// `map` becomes the last map sent; returns how the holders of each domain changed since
    /// the one before, by domain (a domain no one holds any more is listed with none now).
    pub fn update(&mut self, map: HolderMap) -> Vec<HolderChange> {
        self.in_step = false;
        let mut delta: Vec<HolderChange> = map
            .iter()
            .filter_map(|(&d, keys)| HolderChange::between(d, self.sent.get(&d), keys))
            .collect();
        delta.extend(
            self.sent
                .iter()
                .filter(|(d, _)| !map.contains_key(d))
                .filter_map(|(&d, keys)| HolderChange::between(d, Some(keys), &[])),
        );
        delta.sort_unstable_by_key(|c| c.domain);
        self.sent = map;
        delta
    }

    /// The holders map of every member's plan becomes the last map sent, as
    /// [`SentHolders::update`] would make it from the whole map, and the same delta is
    /// returned. `changes` are the domains whose holders changed since the index's changes were
    /// last taken, with their holders now (`RoundIndex::take_holder_changes`); if the last map
    /// sent is not the one those changes apply to, `whole` makes the whole map instead.
    pub fn update_from_index(
        &mut self,
        changes: Vec<(u32, Vec<u32>)>,
        whole: impl FnOnce() -> HolderMap,
    ) -> Vec<HolderChange> {
        if !self.in_step {
            let delta = self.update(whole());
            self.in_step = true;
            return delta;
        }
        let mut delta = Vec::with_capacity(changes.len());
        for (d, keys) in changes {
            let Some(change) = HolderChange::between(d, self.sent.get(&d), &keys) else {
                continue;
            };
            if keys.is_empty() {
                self.sent.remove(&d);
            } else {
                self.sent.insert(d, keys);
            }
            delta.push(change);
        }
        delta.sort_unstable_by_key(|c| c.domain);
        delta
    }

    /// Whether the last map sent is the map of every member's plan that the index's changes
    /// apply to (else the next [`SentHolders::update_from_index`] starts from the whole map).
    pub fn in_step(&self) -> bool {
        self.in_step
    }

    /// The last map sent.
    pub fn sent(&self) -> &HolderMap {
        &self.sent
    }

    /// Whether `key` holds the last map sent (then a delta brings it up to date).
    pub fn is_synced(&self, key: u32) -> bool {
        self.synced.contains(&key)
    }

    /// How many members hold the last map sent (`is_synced`): only members are ever synced
    /// (one that leaves is forgotten), so fewer than the members means some member is not.
    pub fn synced_count(&self) -> usize {
        self.synced.len()
    }

    /// `key` was sent the last map (whole or as a delta on the one before).
    pub fn mark_synced(&mut self, key: u32) {
        self.synced.insert(key);
    }

    /// Only `keys` were sent the last map: the others hold an older one. What was pending
    /// is spent (those that hold the map got it whole; the others will).
    pub fn synced_only(&mut self, keys: impl IntoIterator<Item = u32>) {
        self.synced = keys.into_iter().collect();
        self.pending = Pending::new(self.classes());
    }

    /// View classes the pending lines are kept for.
    fn classes(&self) -> u32 {
        self.pending.changed_round.len() as u32
    }

    /// Folds a round's delta (a [`ClassLines`] per changed domain among `classes` view
    /// classes) into what is pending; the next flush is due.
    pub fn absorb(&mut self, delta: &[ClassLines], classes: u32, round: u64) {
        if self.classes() != classes.max(1) {
            debug_assert!(self.pending.is_empty(), "the view classes are the frame's");
            self.pending = Pending::new(classes);
        }
        self.pending.absorb(delta, round);
        // Due if some class was told a line.
        self.dirty |= delta.iter().any(|c| {
            c.own.values().any(Option::is_some)
                || (c.rest.is_some() && c.own.len() < classes as usize)
        });
    }

    /// Makes the next flush due though nothing changed: some member holds no map it can be
    /// brought up to date from (it joined, or missed a barrier round's map) and is told the
    /// whole map then.
    pub fn mark_dirty(&mut self) {
        self.dirty = true;
    }

    /// What is pending, by view class.
    pub fn pending(&self) -> &Pending {
        &self.pending
    }

    /// `key` was told the holders as of `round` (its plan carried its class's pending lines,
    /// or the whole map).
    pub fn told(&mut self, key: u32, round: u64) {
        self.synced.insert(key);
        self.told.insert(key, round);
    }

    /// Whether `key`, synced, was told its class's pending lines already (its plan came after
    /// they last changed).
    pub fn is_told(&self, key: u32, class: u32) -> bool {
        self.told
            .get(&key)
            .is_some_and(|&r| r >= self.pending.changed_round(class))
    }

    /// When the next flush is due, if a round changed anything since the last: `interval`
    /// after the last flush (at once after the first round).
    pub fn due(&self, interval: Duration) -> Option<Time> {
        self.dirty
            .then(|| self.last_flush.map_or(Time(0), |t| t + interval))
    }

    /// Every member in `members` was told the latest map at `now`: nothing is pending.
    pub fn flushed(&mut self, now: Time, members: impl IntoIterator<Item = u32>, round: u64) {
        self.synced_only(members);
        for &k in &self.synced {
            self.told.insert(k, round);
        }
        self.dirty = false;
        self.last_flush = Some(now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Draws below `n` from a fixed sequence started by `seed` (a linear congruential
    /// generator: the tests' random maps and messages are the same in every run).
    fn draws(mut seed: u64) -> impl FnMut(u64) -> u64 {
        move |n| {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (seed >> 33) % n
        }
    }

    fn map(list: &[(u32, &[u32])]) -> HolderMap {
        list.iter().map(|&(d, ks)| (d, ks.to_vec())).collect()
    }

    /// A change as (domain, gained, lost).
    type Said = (u32, Vec<u32>, Vec<u32>);

    fn change(domain: u32, gained: &[u32], lost: &[u32]) -> Said {
        (domain, gained.to_vec(), lost.to_vec())
    }

    fn said(changes: Vec<HolderChange>) -> Vec<Said> {
        changes
            .into_iter()
            .map(|c| {
                let w = c.whole();
                (c.domain, w.gained, w.lost)
            })
            .collect()
    }

    #[test]
    fn a_delta_lists_what_changed_domains_gained_and_lost_only() {
        let mut s = SentHolders::default();
        let first = s.update(map(&[(0, &[1]), (1, &[2]), (2, &[3])]));
        assert_eq!(first.len(), 3, "everything is new");
        let next = said(s.update(map(&[(0, &[1]), (1, &[2, 4]), (3, &[5])])));
        assert_eq!(
            next,
            vec![
                change(1, &[4], &[]),
                change(2, &[], &[3]),
                change(3, &[5], &[])
            ],
            "0 unchanged, 1 gained a holder, 2 has none now, 3 is new"
        );
        assert_eq!(s.sent(), &map(&[(0, &[1]), (1, &[2, 4]), (3, &[5])]));
        assert!(s.update(s.sent().clone()).is_empty());
        // A long list that gains one key and loses another is two keys on the wire.
        let hot: Vec<u32> = (0..300).collect();
        s.update([(9, hot.clone())].into_iter().collect());
        let mut moved = hot.clone();
        moved.retain(|&k| k != 17);
        moved.push(300);
        assert_eq!(
            said(s.update([(9, moved)].into_iter().collect())),
            vec![change(9, &[300], &[17])]
        );
    }

    #[test]
    fn changes_from_the_index_give_the_whole_maps_delta() {
        let mut whole = SentHolders::default();
        let mut kept = SentHolders::default();
        let first = map(&[(0, &[1]), (1, &[2]), (2, &[3])]);
        assert_eq!(
            kept.update_from_index(vec![(9, vec![9])], || first.clone()),
            whole.update(first.clone()),
            "out of step: the whole map is taken, the changes ignored"
        );
        let next = map(&[(0, &[1]), (1, &[2, 4]), (3, &[5])]);
        // 0 changed and changed back; 1 gained a holder; 2 lost its last; 3 is new.
        let changes = vec![(0, vec![1]), (1, vec![2, 4]), (2, vec![]), (3, vec![5])];
        let want = whole.update(next.clone());
        assert_eq!(
            kept.update_from_index(changes, || unreachable!("in step")),
            want
        );
        assert_eq!(kept.sent(), &next);
        // A map sent from elsewhere (a barrier round's) puts it out of step again.
        kept.update(map(&[(7, &[7])]));
        assert_eq!(
            said(kept.update_from_index(Vec::new(), || next.clone())),
            vec![
                change(0, &[1], &[]),
                change(1, &[2, 4], &[]),
                change(3, &[5], &[]),
                change(7, &[], &[7])
            ]
        );
    }

    /// Applies one line to `held`'s list of `domain` as a worker does: lost keys out, gained
    /// keys in.
    fn apply(held: &mut HolderMap, domain: u32, line: &ViewChange) {
        let keys = held.entry(domain).or_default();
        keys.retain(|k| !line.lost.contains(k));
        keys.extend(&line.gained);
        keys.sort_unstable();
        if keys.is_empty() {
            held.remove(&domain);
        }
    }

    /// A member of `class`'s view of the whole map.
    fn view_of(map: &HolderMap, class: u32, classes: u32) -> HolderMap {
        map.iter()
            .map(|(&d, keys)| (d, view(keys, class, classes)))
            .filter(|(_, keys)| !keys.is_empty())
            .collect()
    }

    #[test]
    fn deltas_applied_in_turn_give_each_classs_view_of_each_map_sent() {
        let classes = 3;
        let mut s = SentHolders::default();
        // What a member of each class holds, and a member that sees every holder.
        let mut held = vec![HolderMap::new(); classes as usize];
        let mut all = HolderMap::new();
        let mut draw = draws(7);
        for _ in 0..50 {
            let mut next = HolderMap::new();
            for d in 0..20u32 {
                let keys: Vec<u32> = (0..12u32).filter(|_| draw(3) == 0).collect();
                if !keys.is_empty() {
                    next.insert(d, keys);
                }
            }
            for c in s.update(next.clone()) {
                apply(&mut all, c.domain, &c.whole());
                let lines = c.lines(classes);
                for class in 0..classes {
                    if let Some(line) = lines.of(class) {
                        apply(&mut held[class as usize], c.domain, line);
                    }
                }
            }
            assert_eq!(all, next);
            for class in 0..classes {
                assert_eq!(held[class as usize], view_of(&next, class, classes));
            }
        }
    }

    /// Each class's lines folded on their own, as every class's were before the classes
    /// without a holder shared one fold: the reference the shared fold must equal.
    #[derive(Default)]
    struct OwnFold {
        lines: BTreeMap<u32, ViewChange>,
        changed_round: u64,
    }

    impl OwnFold {
        fn absorb(&mut self, domain: u32, line: &ViewChange, round: u64) {
            if line.is_empty() {
                return;
            }
            self.changed_round = round;
            self.lines.entry(domain).or_default().fold(line);
        }

        fn lines(&self, domains: Option<&BTreeSet<u32>>) -> Vec<proto::DomainHolders> {
            self.lines
                .iter()
                .filter(|(d, _)| domains.is_none_or(|ds| ds.contains(d)))
                .map(|(&domain, l)| proto::DomainHolders {
                    domain,
                    workers: l.gained.clone(),
                    lost: l.lost.clone(),
                })
                .collect()
        }
    }

    #[test]
    fn the_shared_fold_gives_every_class_its_own_fold() {
        let (classes, domains, keys) = (4u32, 10u32, 24u32);
        let mut draw = draws(5);
        let mut checked = 0;
        for _ in 0..60 {
            let mut sent = SentHolders::default();
            let mut pending = Pending::new(classes);
            let mut own: Vec<OwnFold> = (0..classes).map(|_| OwnFold::default()).collect();
            let mut map = HolderMap::new();
            for round in 1..=40u64 {
                // Now and then the members are all told: nothing pending.
                if draw(8) == 0 {
                    pending = Pending::new(classes);
                    own.iter_mut().for_each(|o| *o = OwnFold::default());
                }
                for _ in 0..1 + draw(4) {
                    let d = draw(u64::from(domains)) as u32;
                    let holders = map.entry(d).or_default();
                    // Mostly a holder or two; now and then a hot domain held in every class.
                    let flips = if draw(6) == 0 { 12 } else { 1 + draw(2) };
                    for _ in 0..flips {
                        let k = draw(u64::from(keys)) as u32;
                        match holders.binary_search(&k) {
                            Ok(i) => {
                                holders.remove(i);
                            }
                            Err(i) => holders.insert(i, k),
                        }
                    }
                }
                map.retain(|_, h| !h.is_empty());
                let delta: Vec<ClassLines> = sent
                    .update(map.clone())
                    .iter()
                    .map(|c| c.lines(classes).keeping(|k| k != 13))
                    .collect();
                pending.absorb(&delta, round);
                for change in &delta {
                    for class in 0..classes {
                        if let Some(line) = change.of(class) {
                            own[class as usize].absorb(change.domain, line, round);
                        }
                    }
                }
                let some: BTreeSet<u32> = (0..domains).filter(|_| draw(2) == 0).collect();
                for class in 0..classes {
                    let o = &own[class as usize];
                    assert_eq!(
                        pending.lines(class, |_| true),
                        o.lines(None),
                        "class {class}"
                    );
                    assert_eq!(pending.len(class), o.lines.len(), "class {class}");
                    assert_eq!(pending.changed_round(class), o.changed_round);
                    let (lines, all) = pending.lines_of(class, &some, |_| true);
                    assert_eq!(lines, o.lines(Some(&some)));
                    assert_eq!(all, o.lines.keys().all(|d| some.contains(d)));
                    checked += 1;
                }
            }
        }
        assert!(checked > 9_000, "{checked} classes checked");
    }

    /// Random rounds of holder changes for one member's class, each a delta line a domain
    /// (what `RunningFrame::holder_changes` makes): the fold of the rounds from any one on
    /// (`Pending`), applied by a worker (`Plan::set_holders`) whose map is that of any round
    /// from there on, gives the map of the last round. So a member told the pending lines with
    /// its plan and again at the flush, or only at the flush, holds the coordinator's map.
    #[test]
    fn pending_changes_bring_a_worker_at_any_later_map_to_the_latest() {
        use crate::worker::{HolderLine, Mode, Plan};
        let domains = 6u32;
        let roster: std::sync::Arc<std::collections::HashMap<u32, String>> =
            std::sync::Arc::new((0..8).map(|k| (k, format!("w{k}"))).collect());
        let lines_of = |p: &Pending| -> Vec<HolderLine> {
            p.lines(0, |_| true)
                .into_iter()
                .map(|l| HolderLine {
                    domain: l.domain,
                    workers: l.workers.into(),
                    lost: l.lost.into(),
                })
                .collect()
        };
        // This member is key 0: the worker leaves itself out of every list.
        let held = |p: &Plan| -> Vec<Vec<u32>> {
            (0..domains).map(|d| p.holder_keys(d).to_vec()).collect()
        };
        let mut draw = draws(11);
        let mut checked = 0;
        for _ in 0..200 {
            // The coordinator's maps, one a round, and each round's delta (a whole map first).
            let mut maps: Vec<HolderMap> = Vec::new();
            let mut sent = SentHolders::default();
            let mut deltas: Vec<Vec<ClassLines>> = Vec::new();
            for _ in 0..2 + draw(6) {
                let mut next = maps.last().cloned().unwrap_or_default();
                // A few domains change: keys in and out, now and then every holder gone.
                for _ in 0..1 + draw(3) {
                    let d = draw(u64::from(domains)) as u32;
                    let keys = next.entry(d).or_default();
                    for _ in 0..draw(3) {
                        let k = draw(8) as u32;
                        match keys.binary_search(&k) {
                            Ok(i) => {
                                keys.remove(i);
                            }
                            Err(i) => keys.insert(i, k),
                        }
                    }
                    if draw(5) == 0 {
                        keys.clear();
                    }
                }
                next.retain(|_, keys| !keys.is_empty());
                let delta = sent
                    .update(next.clone())
                    .iter()
                    .map(|c| c.lines(1))
                    .collect();
                deltas.push(delta);
                maps.push(next);
            }
            let last = maps.len() - 1;
            let worker_at = |u: usize| {
                let mut p = Plan::new(Mode::Dynamic, 1, domains, 0, roster.clone());
                let whole = maps[u].iter().map(|(&domain, keys)| HolderLine {
                    domain,
                    workers: keys.clone().into(),
                    lost: Default::default(),
                });
                p.set_holders(whole, false);
                p
            };
            let want = held(&worker_at(last));
            // Pending from round v + 1 on; a worker at round u >= v applies it.
            for v in 0..last {
                let mut pending = Pending::new(1);
                for (r, delta) in deltas.iter().enumerate().skip(v + 1) {
                    pending.absorb(delta, r as u64);
                }
                assert!(pending.len(0) <= domains as usize, "one line a domain");
                for u in v..=last {
                    let mut p = worker_at(u);
                    p.set_holders(lines_of(&pending), true);
                    assert_eq!(held(&p), want, "from {v}, the worker at {u}: {pending:?}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 500, "{checked} workers checked");
    }

    #[test]
    fn a_view_is_a_members_class_of_holders_or_every_holder() {
        assert_eq!(view_classes(4), 1);
        assert_eq!(view_classes(4_096), 64);
        let holders = [1, 2, 5, 9, 130];
        assert_eq!(view(&holders, 1, 64), [1]);
        assert_eq!(view(&holders, 2, 64), [2, 130], "130 is of class 2 too");
        assert_eq!(view(&holders, 3, 64), holders, "no holder of class 3");
        assert_eq!(view(&holders, 0, 1), holders, "one class sees everything");
        // A hot domain gaining a holder of class 7 is news to class 7 only.
        let before: Vec<u32> = (0..300).collect();
        let mut now = before.clone();
        now.push(64 * 5 + 7);
        let c = HolderChange::between(1, Some(&before), &now).unwrap();
        let ClassLines { rest, own, .. } = c.lines(64);
        assert_eq!(
            own[&7],
            Some(ViewChange {
                gained: vec![327],
                lost: vec![]
            })
        );
        assert_eq!(own.values().filter(|l| l.is_some()).count(), 1);
        assert_eq!(
            own.len(),
            64,
            "every class holds it, so `rest` goes to none"
        );
        assert!(rest.is_some());
    }

    #[test]
    fn each_classs_line_turns_its_view_before_into_its_view_now() {
        // Every class's line is what turns its view of the holders before into its view now
        // (`view`), however many holders a class has on either side: none, some or all.
        let mut draw = draws(11);
        for case in 0..2_000 {
            let classes = 1 + draw(6) as u32;
            let keys = 1 + draw(40) as u32;
            let dense = 1 + draw(4);
            let pick = |draw: &mut dyn FnMut(u64) -> u64| -> Vec<u32> {
                (0..keys).filter(|_| draw(dense + 1) != 0).collect()
            };
            let before = pick(&mut draw);
            let now = pick(&mut draw);
            let Some(c) = HolderChange::between(case, Some(&before), &now) else {
                continue;
            };
            let lines = c.lines(classes);
            for class in 0..classes {
                let (was, is) = (view(&before, class, classes), view(&now, class, classes));
                assert_eq!(
                    lines.of(class).cloned(),
                    ViewChange::between(&was, &is),
                    "case {case}: class {class} of {classes}, {before:?} -> {now:?}"
                );
                let named = before
                    .iter()
                    .chain(&now)
                    .any(|&k| class_of(k, classes) == class);
                assert_eq!(lines.own.contains_key(&class), named, "case {case}");
            }
        }
    }

    #[test]
    fn members_that_missed_a_map_are_not_synced() {
        let mut s = SentHolders::default();
        s.update(map(&[(0, &[1])]));
        s.synced_only([1, 2]);
        assert!(s.is_synced(1) && s.is_synced(2) && !s.is_synced(3));
        s.forget(2);
        assert!(
            !s.is_synced(2),
            "a member that left or joined gets the whole map"
        );
        s.mark_synced(3);
        assert!(s.is_synced(3));
        s.reset();
        assert!(!s.is_synced(1) && s.sent().is_empty());
    }
}
