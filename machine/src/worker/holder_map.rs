//! Who holds each domain now, and who held it before, as a worker keeps them: one slot per
//! domain of the scene, with a single holder's key in the slot itself and only lists of two or
//! more keys in a side table.
//!
//! Every worker keeps these for every domain, and the simulator runs thousands of workers in
//! one process. As hash maps of vectors they cost about 66 bytes a domain a worker: 554 MB of
//! a 256-worker run's 650 MB heap over 32,768 domains, and so about 9 GB of the 21 GiB a
//! 4,096-worker run held (heaptrack, README "Simulator"). Most domains have no holder or one
//! (the domain schedule's owner, a domain under dynamic that is not hot), which a 4-byte slot
//! holds; the slots are allocated with the first holder, so a frame without holders
//! (image-plane) has none. A lookup is an index, not a hash.

use std::collections::HashMap;

// Looked up for every line of every holders message on every worker: SipHash there was 7% of
// a 4,096-worker simulation (perf). The keys are domain ids the coordinator sends, already
// bounded by the scene's domains.
use foldhash::fast::FixedState;

/// A slot: nobody holds the domain.
const NOBODY: u32 = u32::MAX;
/// A slot: two or more hold it, the list is in the side table.
const MANY: u32 = u32::MAX - 1;

/// Whether `key` can name a worker here: the two slot markers cannot. The coordinator numbers
/// workers from zero up, so it never sends them; a line naming one is read without it.
fn is_key(key: u32) -> bool {
    key < MANY
}

/// Puts each of `gained` but `me` (and the markers) into `kept`, in key order, once.
fn insert_gained(kept: &mut Vec<u32>, gained: impl IntoIterator<Item = u32>, me: u32) {
    for g in gained {
        if g != me
            && is_key(g)
            && let Err(at) = kept.binary_search(&g)
        {
            kept.insert(at, g);
        }
    }
}

/// Takes the keys in `lost` (sorted) out of `kept` (sorted), pushing each onto `gone`.
fn remove_lost(kept: &mut Vec<u32>, lost: &[u32], gone: &mut Vec<u32>) {
    // A line loses a key or two of a list that may be hundreds long (a hot domain's): find
    // each. Many lost at once: one pass over the list.
    if lost.len() * 8 < kept.len() {
        for w in lost {
            if let Ok(at) = kept.binary_search(w) {
                kept.remove(at);
                gone.push(*w);
            }
        }
    } else {
        kept.retain(|w| {
            let lost = lost.binary_search(w).is_ok();
            if lost {
                gone.push(*w);
            }
            !lost
        });
    }
}

/// The workers holding each domain this round, by key, each list in key order (the order of
/// the coordinator's lists, which the choice of a ray's holder depends on).
#[derive(Clone, Debug)]
pub struct HolderMap {
    /// Domains of the scene: lines for others are not kept (no ray goes to them).
    domains: u32,
    /// One slot a domain ([`NOBODY`], a key, or [`MANY`]); empty until a domain is held.
    slots: Vec<u32>,
    /// The lists of two or more keys.
    many: HashMap<u32, Vec<u32>, FixedState>,
}

impl HolderMap {
    /// Nobody holds any of `domains` domains.
    pub fn new(domains: u32) -> Self {
        HolderMap {
            domains,
            slots: Vec::new(),
            many: HashMap::default(),
        }
    }

    /// The keys holding `domain`, in key order (none for a domain out of the scene).
    pub fn get(&self, domain: u32) -> &[u32] {
        match self.slots.get(domain as usize) {
            None | Some(&NOBODY) => &[],
            Some(&MANY) => self.many.get(&domain).map_or(&[], Vec::as_slice),
            Some(key) => std::slice::from_ref(key),
        }
    }

    /// Whether anyone holds `domain`.
    pub fn contains(&self, domain: u32) -> bool {
        !self.get(domain).is_empty()
    }

    /// The domains someone holds, ascending.
    pub fn held(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.slots.len() as u32).filter(|&d| self.slots[d as usize] != NOBODY)
    }

    /// Makes `keys` (in key order, without `me` or markers) the holders of `domain`.
    fn store(&mut self, domain: u32, keys: Vec<u32>) {
        if self.slots.is_empty() {
            if keys.is_empty() {
                return;
            }
            self.slots = vec![NOBODY; self.domains as usize];
        }
        let slot = &mut self.slots[domain as usize];
        if *slot == MANY && keys.len() < 2 {
            self.many.remove(&domain);
        }
        *slot = match keys.len() {
            0 => NOBODY,
            1 => keys[0],
            _ => {
                self.many.insert(domain, keys);
                MANY
            }
        };
    }

    /// Sets the holders of `domain` to `keys` (any order; `me`, markers and repeats left
    /// out). A domain out of the scene is ignored.
    pub fn set(&mut self, domain: u32, mut keys: Vec<u32>, me: u32) {
        if domain >= self.domains {
            return;
        }
        keys.retain(|&k| k != me && is_key(k));
        keys.sort_unstable();
        keys.dedup();
        self.store(domain, keys);
    }

    /// Applies one domain's line of a delta: the keys in `lost` (sorted) out, those in
    /// `gained` in at their places; who was lost is pushed onto `gone`. A domain out of the
    /// scene is ignored.
    pub fn change(
        &mut self,
        domain: u32,
        lost: &[u32],
        gained: &[u32],
        me: u32,
        gone: &mut Vec<u32>,
    ) {
        if domain >= self.domains {
            return;
        }
        let lose = |w: &u32| lost.binary_search(w).is_ok();
        let many = self.slots.get(domain as usize) == Some(&MANY);
        if let Some(kept) = self.many.get_mut(&domain).filter(|_| many) {
            // A long list is changed where it is (no new vector): this runs for every line of
            // every holders message on every worker, and hot domains' lists are long.
            remove_lost(kept, lost, gone);
            insert_gained(kept, gained.iter().copied(), me);
            if kept.len() < 2 {
                let kept = self.many.remove(&domain).unwrap_or_default();
                self.store(domain, kept);
            }
            return;
        }
        let mut kept = Vec::new();
        if let Some(&key) = self.get(domain).first() {
            if lose(&key) {
                gone.push(key);
            } else {
                kept.push(key);
            }
        }
        insert_gained(&mut kept, gained.iter().copied(), me);
        self.store(domain, kept);
    }

    /// Forgets every key `keep` refuses, in every list.
    pub fn retain_keys(&mut self, keep: impl Fn(u32) -> bool) {
        for d in 0..self.slots.len() as u32 {
            match self.slots[d as usize] {
                NOBODY => {}
                MANY => {
                    let mut kept = self.many.remove(&d).unwrap_or_default();
                    kept.retain(|&k| keep(k));
                    self.store(d, kept);
                }
                key if !keep(key) => self.slots[d as usize] = NOBODY,
                _ => {}
            }
        }
    }
}

/// Workers that held each domain in an earlier round and hold it no longer, latest first, at
/// most [`FormerHolders::KEPT`] a domain: they may still have it loaded, so a load may ask
/// them for it. Slots allocated with the first such worker.
#[derive(Clone, Debug)]
pub struct FormerHolders {
    /// Domains of the scene.
    domains: u32,
    /// [`FormerHolders::KEPT`] keys a domain, latest first, padded with [`NOBODY`].
    slots: Vec<[u32; FormerHolders::KEPT]>,
}

impl FormerHolders {
    /// Former holders remembered per domain.
    pub const KEPT: usize = 2;

    /// No former holder of any of `domains` domains.
    pub fn new(domains: u32) -> Self {
        FormerHolders {
            domains,
            slots: Vec::new(),
        }
    }

    /// The former holders of `domain`, latest first.
    pub fn get(&self, domain: u32) -> impl Iterator<Item = u32> + '_ {
        self.slots
            .get(domain as usize)
            .into_iter()
            .flatten()
            .copied()
            .filter(|&k| k != NOBODY)
    }

    /// Records that `gone` (in order, the last the latest) no longer hold `domain`.
    pub fn note(&mut self, domain: u32, gone: impl IntoIterator<Item = u32>) {
        if domain >= self.domains {
            return;
        }
        for w in gone.into_iter().filter(|&w| is_key(w)) {
            if self.slots.is_empty() {
                self.slots = vec![[NOBODY; Self::KEPT]; self.domains as usize];
            }
            let slot = &mut self.slots[domain as usize];
            // Move `w` to the front: shift down what was before it (or everything, when new).
            let at = slot.iter().position(|&k| k == w).unwrap_or(Self::KEPT - 1);
            slot.copy_within(0..at, 1);
            slot[0] = w;
        }
    }

    /// Forgets every key `keep` refuses.
    pub fn retain_keys(&mut self, keep: impl Fn(u32) -> bool) {
        for slot in &mut self.slots {
            let kept: Vec<u32> = slot
                .iter()
                .copied()
                .filter(|&k| k != NOBODY && keep(k))
                .collect();
            *slot = [NOBODY; Self::KEPT];
            slot[..kept.len()].copy_from_slice(&kept);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_domain_holds_none_one_or_many_keys_in_key_order() {
        let mut m = HolderMap::new(4);
        assert!(m.slots.is_empty(), "no slots before the first holder");
        m.set(1, vec![7], 0);
        assert_eq!(m.get(1), [7]);
        m.set(1, vec![9, 3, 0, 9], 0);
        assert_eq!(m.get(1), [3, 9], "sorted, without me and repeats");
        assert_eq!(m.held().collect::<Vec<_>>(), [1]);
        let mut gone = Vec::new();
        m.change(1, &[3], &[], 0, &mut gone);
        assert_eq!((m.get(1), gone.as_slice()), (&[9][..], &[3][..]));
        assert!(m.many.is_empty(), "a list of one lives in its slot");
        m.change(1, &[], &[5, 12], 0, &mut gone);
        assert_eq!(m.get(1), [5, 9, 12]);
        m.change(1, &[5, 9, 12], &[], 0, &mut gone);
        assert!(!m.contains(1));
        assert!(m.many.is_empty());
        // Out of the scene, and the slot markers as keys: ignored.
        m.set(4, vec![1], 0);
        assert!(!m.contains(4));
        m.set(2, vec![MANY, NOBODY], 0);
        assert!(!m.contains(2));
    }

    #[test]
    fn a_long_list_loses_a_few_keys_or_many_alike() {
        // A few lost of a long list are found one by one, many in one pass: the same list.
        for lost in [vec![4, 10, 99], (0..40).step_by(3).collect()] {
            let mut m = HolderMap::new(1);
            m.set(0, (0..40).collect(), 99);
            let mut gone = Vec::new();
            m.change(0, &lost, &[41, 7], 99, &mut gone);
            let kept: Vec<u32> = (0..40)
                .filter(|k| !lost.contains(k) || *k == 7)
                .chain([41])
                .collect();
            assert_eq!(m.get(0), kept);
            let lost_there: Vec<u32> = lost.iter().copied().filter(|&k| k < 40).collect();
            assert_eq!(gone, lost_there, "in key order");
        }
    }

    #[test]
    fn forgotten_keys_leave_every_list() {
        let mut m = HolderMap::new(3);
        m.set(0, vec![1], 9);
        m.set(1, vec![1, 2], 9);
        m.set(2, vec![1, 2, 3], 9);
        m.retain_keys(|k| k != 1);
        assert_eq!(
            (m.get(0), m.get(1), m.get(2)),
            (&[][..], &[2][..], &[2, 3][..])
        );
        assert_eq!(m.many.len(), 1);
    }

    #[test]
    fn former_holders_are_the_latest_two_once_each() {
        let mut f = FormerHolders::new(2);
        assert_eq!(f.get(0).count(), 0);
        f.note(0, [4]);
        f.note(0, [5, 6]);
        assert_eq!(f.get(0).collect::<Vec<_>>(), [6, 5]);
        f.note(0, [5]);
        assert_eq!(f.get(0).collect::<Vec<_>>(), [5, 6]);
        f.note(2, [1]);
        assert_eq!(f.get(1).count() + f.get(2).count(), 0);
        f.retain_keys(|k| k != 5);
        assert_eq!(f.get(0).collect::<Vec<_>>(), [6]);
    }
}
