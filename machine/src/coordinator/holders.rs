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
//! The one map kept is the last one sent, with the members known to hold it; a member that
//! joined, or that missed a map (a barrier round plans only some members), gets the whole
//! map once. Control streams are ordered, so a member that got every message since holds
//! exactly the last map sent, less the peers it was told are lost (whose domains the next
//! delta lists, since the lost member is no holder any more).

use std::collections::{BTreeMap, BTreeSet};

/// Holders by domain, as member keys.
pub type HolderMap = BTreeMap<u32, Vec<u32>>;

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

    /// `map` becomes the last map sent; returns the domains whose holders changed since the
    /// one before, a domain no one holds any more listed with none.
    pub fn update(&mut self, map: HolderMap) -> Vec<(u32, Vec<u32>)> {
        self.in_step = false;
        let mut delta: Vec<(u32, Vec<u32>)> = map
            .iter()
            .filter(|(d, keys)| self.sent.get(d) != Some(keys))
            .map(|(&d, keys)| (d, keys.clone()))
            .collect();
        delta.extend(
            self.sent
                .keys()
                .filter(|d| !map.contains_key(d))
                .map(|&d| (d, Vec::new())),
        );
        delta.sort_unstable_by_key(|&(d, _)| d);
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
    ) -> Vec<(u32, Vec<u32>)> {
        if !self.in_step {
            let delta = self.update(whole());
            self.in_step = true;
            return delta;
        }
        let mut delta = Vec::with_capacity(changes.len());
        for (d, keys) in changes {
            let unchanged = match self.sent.get(&d) {
                Some(sent) => *sent == keys,
                None => keys.is_empty(),
            };
            if unchanged {
                continue;
            }
            if keys.is_empty() {
                self.sent.remove(&d);
            } else {
                self.sent.insert(d, keys.clone());
            }
            delta.push((d, keys));
        }
        delta.sort_unstable_by_key(|&(d, _)| d);
        delta
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

    fn map(list: &[(u32, &[u32])]) -> HolderMap {
        list.iter().map(|&(d, ks)| (d, ks.to_vec())).collect()
    }

    #[test]
    fn a_delta_lists_changed_and_dropped_domains_only() {
        let mut s = SentHolders::default();
        let first = s.update(map(&[(0, &[1]), (1, &[2]), (2, &[3])]));
        assert_eq!(first.len(), 3, "everything is new");
        let next = s.update(map(&[(0, &[1]), (1, &[2, 4]), (3, &[5])]));
        assert_eq!(
            next,
            vec![(1, vec![2, 4]), (2, vec![]), (3, vec![5])],
            "0 unchanged, 1 gained a holder, 2 has none now, 3 is new"
        );
        assert_eq!(s.sent(), &map(&[(0, &[1]), (1, &[2, 4]), (3, &[5])]));
        assert!(s.update(s.sent().clone()).is_empty());
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
            kept.update_from_index(Vec::new(), || next.clone()),
            vec![(0, vec![1]), (1, vec![2, 4]), (3, vec![5]), (7, vec![])]
        );
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
