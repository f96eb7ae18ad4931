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
//! The one map kept is the last one sent, with the members known to hold it; a member that
//! joined, or that missed a map (a barrier round plans only some members), gets the whole
//! map once. Control streams are ordered, so a member that got every message since holds
//! exactly the last map sent, less the peers it was told are lost (whose domains the next
//! delta lists, since the lost member is no holder any more).

use std::collections::{BTreeMap, BTreeSet};

use rayfarm_proto as proto;

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

/// Folds `later` into `earlier`: two `Holders` messages for one member of one frame, with
/// nothing else sent to it between them, made one that leaves the member's map as the two
/// applied in turn do (`worker::Plan::set_holders`: a delta line takes its lost keys out, then
/// puts its gained keys in; a whole map replaces the map). A shell whose link to a member is
/// still busy sending merges that member's waiting `Holders` with the next instead of queueing
/// both: under the predictive schedule most domains have one holder, so every round's change
/// is news to every member (views do not help), and at 4,096 workers the rounds' messages
/// outran the coordinator's link and waited in memory by the gigabyte (README "Simulator").
/// Merged, a member has at most one waiting, of at most one line a changed domain.
pub fn fold_holders(earlier: &mut proto::Holders, later: proto::Holders) {
    if !later.delta {
        *earlier = later;
        return;
    }
    // A domain's line so far: the keys put in and, for a delta, taken out.
    let mut lines: BTreeMap<u32, (BTreeSet<u32>, BTreeSet<u32>)> = BTreeMap::new();
    for h in earlier.holders.drain(..) {
        let line = lines.entry(h.domain).or_default();
        if earlier.delta {
            fold_line(line, h.workers, h.lost);
        } else {
            // A whole map's line names every holder of its domain.
            *line = (h.workers.into_iter().collect(), BTreeSet::new());
        }
    }
    for h in later.holders {
        let line = lines.entry(h.domain).or_default();
        fold_line(line, h.workers, h.lost);
    }
    let whole = !earlier.delta;
    earlier.holders = lines
        .into_iter()
        .filter_map(|(domain, (gained, lost))| {
            // A whole map leaves out the domains nobody holds; its lines lose nothing.
            (!whole || !gained.is_empty()).then(|| proto::DomainHolders {
                domain,
                workers: gained.into_iter().collect(),
                lost: if whole {
                    Vec::new()
                } else {
                    lost.into_iter().collect()
                },
            })
        })
        .collect();
}

/// [`fold_holders`] of a delta `later` into an `earlier` that is itself the result of a fold
/// of a delta (its lines ascending by domain, one a domain, each line's keys ascending and
/// once; a whole map's lines each with a holder and none lost), at the cost of `later`, not
/// of `earlier`: a folded message waiting for a backlogged link
/// holds the net change since the member's last message, thousands of lines, and rebuilding
/// all of them on every round's fold (a map of sets of every line, collected back) was 89% of
/// a 256-worker predictive simulation (perf, README "Simulator"). The result is the one
/// `fold_holders` gives, line for line. `line_len` is a line's share of the message's encoded
/// bytes; returns by how much the lines' bytes changed.
pub fn fold_into_folded(
    held: &mut proto::Holders,
    later: proto::Holders,
    line_len: impl Fn(&proto::DomainHolders) -> usize,
) -> isize {
    debug_assert!(later.delta, "a whole map replaces what waits: fold_holders");
    let whole = !held.delta;
    // `later`'s lines by domain, in order (a delta may name a domain twice).
    let mut by_domain: BTreeMap<u32, Vec<GainedLost>> = BTreeMap::new();
    for h in later.holders {
        by_domain
            .entry(h.domain)
            .or_default()
            .push((h.workers, h.lost));
    }
    let mut change = 0isize;
    // Each named domain's line is changed where it is, or made where it goes; a whole map
    // drops a line left with no holder.
    let mut emptied = false;
    let mut fresh: Vec<proto::DomainHolders> = Vec::new();
    for (domain, steps) in by_domain {
        let found = held.holders.binary_search_by_key(&domain, |l| l.domain);
        let mut line = match found {
            Ok(i) => {
                change -= line_len(&held.holders[i]) as isize;
                std::mem::take(&mut held.holders[i])
            }
            Err(_) => proto::DomainHolders {
                domain,
                ..Default::default()
            },
        };
        for (gained, lost) in steps {
            for k in lost {
                if let Ok(i) = line.workers.binary_search(&k) {
                    line.workers.remove(i);
                }
                if !whole && let Err(i) = line.lost.binary_search(&k) {
                    line.lost.insert(i, k);
                }
            }
            for k in gained {
                if let Err(i) = line.workers.binary_search(&k) {
                    line.workers.insert(i, k);
                }
            }
        }
        line.domain = domain;
        let keep = !whole || !line.workers.is_empty();
        if keep {
            change += line_len(&line) as isize;
        }
        match found {
            Ok(i) => {
                emptied |= !keep;
                held.holders[i] = line;
            }
            Err(_) if keep => fresh.push(line),
            Err(_) => {}
        }
    }
    if emptied {
        held.holders.retain(|l| !l.workers.is_empty());
    }
    if !fresh.is_empty() {
        // Both ascending by domain, no domain in both: merged in one pass.
        let old = std::mem::take(&mut held.holders);
        let mut merged = Vec::with_capacity(old.len() + fresh.len());
        let mut fresh = fresh.into_iter().peekable();
        for line in old {
            while let Some(f) = fresh.next_if(|f| f.domain < line.domain) {
                merged.push(f);
            }
            merged.push(line);
        }
        merged.extend(fresh);
        held.holders = merged;
    }
    change
}

/// A delta line's keys gained and lost.
type GainedLost = (Vec<u32>, Vec<u32>);

/// One domain's line `(gained, lost)` followed by a delta line of `gained` and `lost`: the
/// keys lost by either are taken out first, then those gained and not lost after, and those
/// gained after, put in (a whole map's line has nothing taken out; the worker takes a line's
/// lost keys out before it puts the gained ones in, so a key lost then gained again stays).
fn fold_line(line: &mut (BTreeSet<u32>, BTreeSet<u32>), gained: Vec<u32>, lost: Vec<u32>) {
    for k in lost {
        line.0.remove(&k);
        line.1.insert(k);
    }
    line.0.extend(gained);
}

/// See the module documentation.
#[derive(Clone, Debug, Default)]
pub struct SentHolders {
    /// The last map sent.
    sent: HolderMap,
    /// Members that hold `sent`.
    synced: BTreeSet<u32>,
    /// Whether `sent` is the map of every member's plan as of the index's last taken changes
    /// (else it is a barrier round's map, the owner map, or none yet).
    in_step: bool,
}

impl SentHolders {
    /// Starts over: no member holds any map (a new frame or subframe on the workers).
    pub fn reset(&mut self) {
        *self = SentHolders::default();
    }

    /// `key` left the frame, or joined it with no map yet.
    pub fn forget(&mut self, key: u32) {
        self.synced.remove(&key);
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

    /// `key` was sent the last map (whole or as a delta on the one before).
    pub fn mark_synced(&mut self, key: u32) {
        self.synced.insert(key);
    }

    /// Only `keys` were sent the last map: the others hold an older one.
    pub fn synced_only(&mut self, keys: impl IntoIterator<Item = u32>) {
        self.synced = keys.into_iter().collect();
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

    /// Random messages folded one after another, each delta into a fold of a delta by
    /// `fold_into_folded` (as the simulator does) and all by `fold_holders`: the same message
    /// after every fold, and `fold_into_folded`'s change of the lines' bytes is theirs.
    #[test]
    fn folding_into_a_fold_gives_the_fold_of_every_line() {
        let mut draw = draws(5);
        // Any additive measure of a line will do to check the accounting.
        let line_len = |l: &proto::DomainHolders| {
            1 + l.domain as usize % 7 + 3 * l.workers.len() + 5 * l.lost.len()
        };
        let total = |h: &proto::Holders| h.holders.iter().map(line_len).sum::<usize>();
        let mut fast_folds = 0;
        for _ in 0..400 {
            let message = |draw: &mut dyn FnMut(u64) -> u64| {
                let delta = draw(8) != 0;
                // Keys unsorted and repeated now and then: a fold takes any.
                let keys = |draw: &mut dyn FnMut(u64) -> u64| -> Vec<u32> {
                    (0..draw(4)).map(|_| draw(10) as u32).collect()
                };
                let mut holders: Vec<proto::DomainHolders> = Vec::new();
                for _ in 0..draw(6) {
                    let domain = draw(12) as u32;
                    let workers = keys(draw);
                    let lost = if delta { keys(draw) } else { Vec::new() };
                    holders.push(proto::DomainHolders {
                        domain,
                        workers,
                        lost,
                    });
                }
                if !delta {
                    let mut seen = BTreeSet::new();
                    holders.retain(|l| seen.insert(l.domain));
                    for l in &mut holders {
                        l.workers.sort_unstable();
                        l.workers.dedup();
                    }
                }
                proto::Holders {
                    job_id: "f".into(),
                    holders,
                    delta,
                }
            };
            let first = message(&mut draw);
            let mut slow = first.clone();
            let mut fast = first;
            // Whether `fast` is a fold of a delta, and its lines' bytes then.
            let mut folded: Option<usize> = None;
            for _ in 0..1 + draw(6) {
                let later = message(&mut draw);
                fold_holders(&mut slow, later.clone());
                match folded {
                    Some(len) if later.delta => {
                        let change = fold_into_folded(&mut fast, later, line_len);
                        let len = len.checked_add_signed(change).unwrap();
                        assert_eq!(len, total(&fast), "the bytes of {fast:?}");
                        folded = Some(len);
                        fast_folds += 1;
                    }
                    _ => {
                        let delta = later.delta;
                        fold_holders(&mut fast, later);
                        folded = delta.then(|| total(&fast));
                    }
                }
                assert_eq!(fast, slow);
            }
        }
        assert!(fast_folds > 500, "{fast_folds} folds into a fold");
    }

    /// Random deltas (and now and then a whole map) for one worker: the worker's map after
    /// each message in turn is the map after their fold, whichever message the fold starts at.
    #[test]
    fn folded_holders_leave_the_workers_map_as_the_messages_in_turn() {
        use crate::worker::{HolderLine, Mode, Plan};
        let roster: std::sync::Arc<std::collections::HashMap<u32, String>> =
            std::sync::Arc::new((0..8).map(|k| (k, format!("w{k}"))).collect());
        let plan = || Plan::new(Mode::Predictive, 1, 6, 0, roster.clone());
        let apply = |p: &mut Plan, h: &proto::Holders| {
            let lines = h.holders.iter().map(|l| HolderLine {
                domain: l.domain,
                workers: l.workers.clone(),
                lost: l.lost.clone(),
            });
            p.set_holders(lines, h.delta);
        };
        let held =
            |p: &Plan| -> Vec<Vec<u32>> { (0..6).map(|d| p.holder_keys(d).to_vec()).collect() };
        let mut draw = draws(11);
        let mut folds = 0;
        for _ in 0..300 {
            let messages: Vec<proto::Holders> = (0..1 + draw(5))
                .map(|_| {
                    let keys = |draw: &mut dyn FnMut(u64) -> u64| -> Vec<u32> {
                        let mut ks: Vec<u32> = (0..draw(3)).map(|_| draw(8) as u32).collect();
                        ks.sort_unstable();
                        ks.dedup();
                        ks
                    };
                    let delta = draw(6) != 0;
                    let mut holders: Vec<proto::DomainHolders> = (0..draw(4))
                        .map(|_| proto::DomainHolders {
                            domain: draw(6) as u32,
                            workers: keys(&mut draw),
                            lost: if delta { keys(&mut draw) } else { Vec::new() },
                        })
                        .collect();
                    if !delta {
                        // A whole map names a domain once (a delta may name it again).
                        let mut seen = BTreeSet::new();
                        holders.retain(|l| seen.insert(l.domain));
                    }
                    proto::Holders {
                        job_id: "f".into(),
                        holders,
                        delta,
                    }
                })
                .collect();
            // Both workers start from the same map, then take the messages in turn or folded.
            let mut in_turn = plan();
            let start = proto::Holders {
                job_id: "f".into(),
                holders: (0..6)
                    .map(|d| proto::DomainHolders {
                        domain: d,
                        workers: vec![(d % 4) + 1, 7],
                        lost: Vec::new(),
                    })
                    .collect(),
                delta: false,
            };
            apply(&mut in_turn, &start);
            let mut folded = in_turn.clone();
            let mut one = messages[0].clone();
            for m in &messages {
                apply(&mut in_turn, m);
            }
            for m in &messages[1..] {
                fold_holders(&mut one, m.clone());
                folds += 1;
            }
            apply(&mut folded, &one);
            assert_eq!(
                held(&folded),
                held(&in_turn),
                "{messages:?} folded into {one:?}"
            );
            let lines = one
                .holders
                .iter()
                .map(|l| l.domain)
                .collect::<BTreeSet<_>>();
            if messages.len() > 1 {
                assert_eq!(
                    lines.len(),
                    one.holders.len(),
                    "a fold has one line a domain"
                );
            }
        }
        assert!(folds > 300);
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
