//! Which queue to trace next when rays are placed speculatively (see
//! `render::speculation`).
//!
//! A generation of rays is made only once the previous one has been traced, and placed
//! speculatively a generation needs each domain only once. So the oldest generation goes
//! first: each domain is then loaded about once per generation, not once per trip of a ray
//! through it. Among the queues holding that generation a domain already in memory goes
//! first (it costs no load); then, for camera rays (generation 0), the domain nearest the
//! eye, so a camera ray's nearer copies are traced before its farther ones, which are skipped
//! once a nearer domain has ended the ray (`Groups::skip`); then the fullest; ties go to the
//! lowest domain id.

use std::collections::BTreeMap;

/// The oldest of `generations`: the one the rule puts first, on a worker (which queue to
/// trace, `next_queue`) and on the coordinator (which queues a round plans for,
/// `rounds::Cluster::state`).
pub fn oldest_generation<G: Ord>(generations: impl IntoIterator<Item = G>) -> Option<G> {
    generations.into_iter().min()
}

/// One domain's queue as the policy sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QueueView {
    /// The domain.
    pub domain: u32,
    /// Rays queued for it.
    pub rays: u64,
    /// The oldest generation among them (`RayRecord::generation`).
    pub oldest: u16,
    /// Whether the domain is in memory.
    pub resident: bool,
    /// The domain's place in the order camera rays meet domains (`DomainTree::front_to_back`
    /// from the eye); 0 for every domain where it is not known.
    pub from_eye: u32,
}

/// A queue holding at most this many rays of its oldest generation counts as holding the
/// next generation when its domain is not in memory ([`scheduled_generation`]). The
/// threshold hardly matters: in the simulator (4 workers, b48, predicted:0.9, an experiment's
/// build) 20, 200 and 2,000 gave 270, 273 and 274 loads, against 299 without the rule.
pub const STRAGGLER_RAYS: u64 = 200;

/// The last generation of a frame of bounce depth `max_depth`: the shadow rays of its
/// deepest hits (`RayRecord::generation`: a radiance ray's depth, one more for a shadow ray).
pub fn last_generation(max_depth: u16) -> u16 {
    max_depth.saturating_add(1)
}

/// The generation a domain's queue counts as for the oldest-generation rule, when rays are
/// placed speculatively in windows: its oldest generation (`oldest`, of which it holds
/// `of_oldest` rays), unless those are a few stragglers (at most [`STRAGGLER_RAYS`]) and the
/// domain is not in memory; then the generation after, unless that is the frame's `last`
/// ([`last_generation`]).
///
/// Why: a later window's copies, and the children of a ray that needed one, are sent only
/// once the verdicts before them are in, by which time the sweep of their generation has
/// usually traced their domains and evicted them. Counted at their own generation, a
/// handful of them go before everything younger and load the domain again, once per domain
/// any of them needs (issue 20, README "Why predicted speculation loads more than full").
/// Counted a generation later they wait for that generation's visit to the domain, which
/// loads it anyway, unless it is in memory already, when they cost nothing now. The rays
/// themselves keep their generation (it is not on the wire): only the order changes, so
/// the image stays the chained trace's.
///
/// Why not into the last generation: no generation comes after it to absorb what is late for
/// it. Stragglers waiting for its visits make their own children (its rays) only then, after
/// most of its domains were visited, and those are loaded again for a few rays each, at the
/// frame's very end. Traced at once, their children join the last generation's queues
/// before its visits. In the simulator (4 workers, depth 3, two-domain caches) big48 took
/// 1,742.9 -> 1,662.7 virtual ms (219 -> 218 loads), the scanned bunny 392.3 -> 289.0 ms (236
/// loads both); with predicted speculation 2,114.4 -> 2,047.2 and 385.1 -> 336.4 ms. Not
/// shifting stragglers at all: big48 1,705.7 ms and 222 loads, the bunny 227.5 ms but 276
/// loads.
pub fn scheduled_generation(oldest: u16, of_oldest: u64, resident: bool, last: u16) -> u16 {
    if of_oldest <= STRAGGLER_RAYS && !resident && oldest.saturating_add(1) < last {
        oldest.saturating_add(1)
    } else {
        oldest
    }
}

/// The domain to trace next, or `None` when no rays are queued.
pub fn next_queue(queues: impl IntoIterator<Item = QueueView>) -> Option<u32> {
    let queues: Vec<QueueView> = queues.into_iter().filter(|q| q.rays > 0).collect();
    let oldest = oldest_generation(queues.iter().map(|q| q.oldest))?;
    queues
        .iter()
        .filter(|q| q.oldest == oldest)
        .max_by_key(|q| {
            let from_eye = if oldest == 0 { q.from_eye } else { 0 };
            (
                q.resident,
                std::cmp::Reverse(from_eye),
                q.rays,
                std::cmp::Reverse(q.domain),
            )
        })
        .map(|q| q.domain)
}

/// How many rays there are of each generation, and which is the oldest.
#[derive(Clone, Debug, Default)]
pub struct Generations {
    counts: Vec<u64>,
}

impl Generations {
    /// One more ray of `generation`.
    pub fn add(&mut self, generation: u16) {
        let g = generation as usize;
        if self.counts.len() <= g {
            self.counts.resize(g + 1, 0);
        }
        self.counts[g] += 1;
    }

    /// One ray of `generation` less.
    pub fn remove(&mut self, generation: u16) {
        if let Some(n) = self.counts.get_mut(generation as usize) {
            *n = n.saturating_sub(1);
        }
    }

    /// No rays at all.
    pub fn clear(&mut self) {
        self.counts.clear();
    }

    /// The oldest generation with a ray, if any.
    pub fn oldest(&self) -> Option<u16> {
        self.counts.iter().position(|&n| n > 0).map(|g| g as u16)
    }

    /// Rays counted of each generation, the oldest first (generation 0 at index 0).
    pub fn counts(&self) -> &[u64] {
        &self.counts
    }
}

impl FromIterator<u16> for Generations {
    /// The counts of these generations (`RayRecord::generation` of each ray).
    fn from_iter<I: IntoIterator<Item = u16>>(generations: I) -> Self {
        let mut counts = Generations::default();
        for g in generations {
            counts.add(g);
        }
        counts
    }
}

/// Rays queued per domain and generation, kept alongside the queues so the policy needs no
/// scan of the rays. Only domains with rays counted have an entry: a worker's counts grow
/// with its queues, not with the scene's domain count.
#[derive(Clone, Debug, Default)]
pub struct GenerationCounts {
    counts: BTreeMap<u32, Generations>,
}

impl GenerationCounts {
    /// One more ray of `generation` queued for `domain`.
    pub fn add(&mut self, domain: u32, generation: u16) {
        self.counts.entry(domain).or_default().add(generation);
    }

    /// One ray of `generation` taken from `domain`'s queue.
    pub fn remove(&mut self, domain: u32, generation: u16) {
        if let Some(g) = self.counts.get_mut(&domain) {
            g.remove(generation);
        }
    }

    /// `domain`'s queue was emptied.
    pub fn clear(&mut self, domain: u32) {
        self.counts.remove(&domain);
    }

    /// The oldest generation queued for `domain`, if any.
    pub fn oldest(&self, domain: u32) -> Option<u16> {
        self.counts.get(&domain)?.oldest()
    }

    /// The oldest generation queued for `domain` and how many of its rays are queued there.
    pub fn oldest_with_count(&self, domain: u32) -> Option<(u16, u64)> {
        let counts = self.counts.get(&domain)?;
        let oldest = counts.oldest()?;
        Some((oldest, counts.counts[oldest as usize]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(domain: u32, rays: u64, oldest: u16, resident: bool) -> QueueView {
        QueueView {
            domain,
            rays,
            oldest,
            resident,
            from_eye: 0,
        }
    }

    #[test]
    fn camera_rays_go_front_to_back_after_what_is_in_memory() {
        let near = |domain, from_eye, oldest, resident| QueueView {
            from_eye,
            ..q(domain, 10 * u64::from(domain), oldest, resident)
        };
        // Generation 0: the domain nearest the eye before the fullest.
        let pick = next_queue([near(1, 0, 0, false), near(2, 5, 0, false)]);
        assert_eq!(pick, Some(1));
        assert_eq!(
            next_queue([near(1, 0, 0, false), near(2, 5, 0, true)]),
            Some(2)
        );
        // Later generations leave from surfaces everywhere: the fullest.
        assert_eq!(
            next_queue([near(1, 0, 1, false), near(2, 5, 1, false)]),
            Some(2)
        );
    }

    #[test]
    fn the_oldest_generation_goes_first_even_when_its_queue_is_small() {
        let pick = next_queue([q(0, 1000, 2, true), q(1, 3, 1, false), q(2, 5, 1, false)]);
        assert_eq!(pick, Some(2));
    }

    #[test]
    fn a_resident_domain_beats_a_fuller_one_of_the_same_generation() {
        let pick = next_queue([q(0, 1000, 0, false), q(1, 3, 0, true)]);
        assert_eq!(pick, Some(1));
    }

    #[test]
    fn ties_go_to_the_lowest_domain_and_empty_queues_are_ignored() {
        assert_eq!(next_queue([q(5, 4, 0, false), q(3, 4, 0, false)]), Some(3));
        assert_eq!(next_queue([q(0, 0, 0, true)]), None);
        assert_eq!(next_queue([]), None);
    }

    #[test]
    fn counts_track_the_oldest_generation_per_domain() {
        let mut c = GenerationCounts::default();
        assert_eq!(c.oldest(0), None);
        c.add(0, 3);
        c.add(0, 1);
        assert_eq!(c.oldest(0), Some(1));
        c.remove(0, 1);
        assert_eq!(c.oldest(0), Some(3));
        c.add(0, 1);
        assert_eq!(c.oldest(1), None);
        assert_eq!(c.oldest_with_count(0), Some((1, 1)));
        c.add(0, 1);
        assert_eq!(c.oldest_with_count(0), Some((1, 2)));
        c.clear(0);
        assert_eq!(c.oldest(0), None);
        assert_eq!(c.oldest_with_count(0), None);
    }

    #[test]
    fn stragglers_of_the_generation_before_the_last_do_not_wait_for_it() {
        // Depth 3: generations 0 to 4, the last the shadow rays of the deepest hits.
        let last = last_generation(3);
        assert_eq!(last, 4);
        assert_eq!(scheduled_generation(2, 3, false, last), 3);
        assert_eq!(scheduled_generation(3, 3, false, last), 3);
        assert_eq!(scheduled_generation(4, 3, false, last), 4);
        // Depth 0: camera rays and their shadow rays; camera stragglers go at once.
        assert_eq!(scheduled_generation(0, 3, false, last_generation(0)), 0);
    }

    #[test]
    fn a_few_stragglers_wait_for_the_next_generation_unless_their_domain_is_in_memory() {
        let last = last_generation(3);
        assert_eq!(scheduled_generation(1, 3, false, last), 2);
        assert_eq!(scheduled_generation(1, STRAGGLER_RAYS, false, last), 2);
        assert_eq!(scheduled_generation(1, STRAGGLER_RAYS + 1, false, last), 1);
        assert_eq!(scheduled_generation(1, 3, true, last), 1);
        assert_eq!(scheduled_generation(u16::MAX, 3, false, u16::MAX), u16::MAX);
        // Counted so, a straggler queue no longer goes before a full queue of the next
        // generation that is in memory, and ties with a full one that is not.
        let stragglers = QueueView {
            domain: 0,
            rays: 3,
            oldest: scheduled_generation(1, 3, false, last),
            resident: false,
            from_eye: 0,
        };
        let next = QueueView {
            domain: 1,
            rays: 1000,
            oldest: 2,
            resident: true,
            from_eye: 0,
        };
        assert_eq!(next_queue([stragglers, next]), Some(1));
        assert_eq!(
            next_queue([
                stragglers,
                QueueView {
                    resident: false,
                    ..next
                }
            ]),
            Some(1)
        );
        // Once the rest is traced they go: nothing waits for ever.
        assert_eq!(next_queue([stragglers]), Some(0));
    }
}
