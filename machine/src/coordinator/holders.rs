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
    /// What turns `before` into `now` (both ascending), or `None` if they are the same.
    fn between(before: &[u32], now: &[u32]) -> Option<ViewChange> {
        let gained: Vec<u32> = now
            .iter()
            .copied()
            .filter(|k| before.binary_search(k).is_err())
            .collect();
        let lost: Vec<u32> = before
            .iter()
            .copied()
            .filter(|k| now.binary_search(k).is_err())
            .collect();
        (!gained.is_empty() || !lost.is_empty()).then_some(ViewChange { gained, lost })
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

    /// What each view class is told of this change among `classes`: `(rest, own)`, where a
    /// class in `own` is told its line there (`None`: its view did not change) and every
    /// other class is told `rest` (no holder of it before or now, so it sees every holder).
    /// Costs the holders before and now, not the classes.
    pub fn lines(&self, classes: u32) -> (Option<ViewChange>, BTreeMap<u32, Option<ViewChange>>) {
        let rest = ViewChange::between(&self.before, &self.now);
        let mut split: BTreeMap<u32, (Vec<u32>, Vec<u32>)> = BTreeMap::new();
        for &k in &self.before {
            split.entry(class_of(k, classes)).or_default().0.push(k);
        }
        for &k in &self.now {
            split.entry(class_of(k, classes)).or_default().1.push(k);
        }
        let own = split
            .into_iter()
            .map(|(class, (before, now))| {
                let before = if before.is_empty() {
                    &self.before
                } else {
                    &before
                };
                let now = if now.is_empty() { &self.now } else { &now };
                (class, ViewChange::between(before, now))
            })
            .collect();
        (rest, own)
    }
}

/// One view class's holder changes since the members were last all told, folded into one line
/// a domain: what a member of the class that holds any map sent since is told to bring it up to
/// date. A busy member needs the holders only to route its rays, and every asynchronous round
/// changed some: one `Holders` a round to every busy member was 91% of a 256-worker dynamic
/// simulation's 15.9 M messages (README "Simulator"). The changes now wait here and go out with
/// the member's next plan, or to every member at most once per holders interval
/// (`RunningFrame::flush_holders`).
///
/// A line keeps every key the domain lost and every key it gained and did not lose after
/// (`absorb`: lost keys of either out, then those gained and not lost after, and those gained
/// after, in; a worker takes a line's lost keys out before it puts the gained ones in). So the
/// fold of the changes since version `v` brings a member at any version from `v` on to the
/// latest: what it applied already is taken out and put back as the latest has it. A member
/// told by its plan, then by the flush, is never out of step (a test applies the fold to
/// workers' maps at every version between).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Pending {
    /// By domain: the keys gained and lost (each ascending).
    lines: BTreeMap<u32, ViewChange>,
    /// The round that last added to the lines (a member told at or after it holds them).
    pub changed_round: u64,
}

impl Pending {
    /// Folds one delta line of `domain` (keys `gained` and `lost`) in after the others.
    pub fn absorb(&mut self, domain: u32, gained: &[u32], lost: &[u32], round: u64) {
        if gained.is_empty() && lost.is_empty() {
            return;
        }
        self.changed_round = round;
        let line = self.lines.entry(domain).or_default();
        for &k in lost {
            if let Ok(i) = line.gained.binary_search(&k) {
                line.gained.remove(i);
            }
            if let Err(i) = line.lost.binary_search(&k) {
                line.lost.insert(i, k);
            }
        }
        for &k in gained {
            if let Err(i) = line.gained.binary_search(&k) {
                line.gained.insert(i, k);
            }
        }
    }

    /// Whether nothing changed since the members were last all told.
    pub fn is_empty(&self) -> bool {
        self.lines.is_empty()
    }

    /// Domain lines changed.
    pub fn len(&self) -> usize {
        self.lines.len()
    }

    /// The folded lines as a delta's, ascending by domain; gained keys that `is_member` refuses
    /// are left out (a member lost since: the workers forgot it, and a later round lists it
    /// lost).
    pub fn lines(&self, is_member: impl Fn(u32) -> bool) -> Vec<proto::DomainHolders> {
        self.lines
            .iter()
            .filter_map(|(&domain, l)| Self::line(domain, l, &is_member))
            .collect()
    }

    /// The folded lines of `domains` only (ascending), as [`Pending::lines`] makes them, and
    /// whether they are every line pending. A line brings its domain to the latest holders
    /// whatever version since the last flush a member holds (see above), so a member may be
    /// told some domains' lines now and the rest later: a round tells the members it plans,
    /// or whose rays it moved, the lines of the domains it changed, which cost what the round
    /// changed, not every line folded since the last flush (at 1,024 workers and a 100 ms
    /// interval, hundreds of lines in each of ten messages a round: README "Simulator").
    pub fn lines_of(
        &self,
        domains: &BTreeSet<u32>,
        is_member: impl Fn(u32) -> bool,
    ) -> (Vec<proto::DomainHolders>, bool) {
        let mut found = 0;
        let lines = domains
            .iter()
            .filter_map(|&d| self.lines.get(&d).map(|l| (d, l)))
            .inspect(|_| found += 1)
            .filter_map(|(d, l)| Self::line(d, l, &is_member))
            .collect();
        (lines, found == self.lines.len())
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
    /// By view class: the changes since the last flush, folded.
    pending: Vec<Pending>,
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
        self.pending
            .iter_mut()
            .for_each(|p| *p = Pending::default());
    }

    /// Folds a round's delta lines, by view class (`lines[class]`), into what is pending for
    /// each class; the next flush is due.
    pub fn absorb(&mut self, lines: &[Vec<proto::DomainHolders>], round: u64) {
        if self.pending.len() < lines.len() {
            self.pending.resize_with(lines.len(), Pending::default);
        }
        for (pending, lines) in self.pending.iter_mut().zip(lines) {
            for l in lines {
                pending.absorb(l.domain, &l.workers, &l.lost, round);
            }
        }
        self.dirty |= lines.iter().any(|l| !l.is_empty());
    }

    /// Makes the next flush due though nothing changed: some member holds no map it can be
    /// brought up to date from (it joined, or missed a barrier round's map) and is told the
    /// whole map then.
    pub fn mark_dirty(&mut self) {
        self.dirty = true;
    }

    /// What is pending for view `class`.
    pub fn pending(&self, class: u32) -> Option<&Pending> {
        self.pending.get(class as usize)
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
            .is_some_and(|&r| self.pending(class).is_none_or(|p| r >= p.changed_round))
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
                let (rest, own) = c.lines(classes);
                for class in 0..classes {
                    let line = own.get(&class).unwrap_or(&rest);
                    if let Some(line) = line {
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
            p.lines(|_| true)
                .into_iter()
                .map(|l| HolderLine {
                    domain: l.domain,
                    workers: l.workers,
                    lost: l.lost,
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
            let mut deltas: Vec<Vec<proto::DomainHolders>> = Vec::new();
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
                    .map(|c| {
                        let w = c.whole();
                        proto::DomainHolders {
                            domain: c.domain,
                            workers: w.gained,
                            lost: w.lost,
                        }
                    })
                    .collect();
                deltas.push(delta);
                maps.push(next);
            }
            let last = maps.len() - 1;
            let worker_at = |u: usize| {
                let mut p = Plan::new(Mode::Dynamic, 1, domains, 0, roster.clone());
                let whole = maps[u].iter().map(|(&domain, keys)| HolderLine {
                    domain,
                    workers: keys.clone(),
                    lost: Vec::new(),
                });
                p.set_holders(whole, false);
                p
            };
            let want = held(&worker_at(last));
            // Pending from round v + 1 on; a worker at round u >= v applies it.
            for v in 0..last {
                let mut pending = Pending::default();
                for (r, delta) in deltas.iter().enumerate().skip(v + 1) {
                    for l in delta {
                        pending.absorb(l.domain, &l.workers, &l.lost, r as u64);
                    }
                }
                assert!(pending.len() <= domains as usize, "one line a domain");
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
        let (rest, own) = c.lines(64);
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
