//! The hybrid schedule's demand-driven tasks (Reinhard et al.): once every tile has been
//! handed out, a worker that runs dry would sit idle while others still hold queued coherent
//! work. The coordinator hears who ran dry (their queue reports) and who is still busy, so it
//! directs: it asks one busy worker at a time to hand part of its queue to the idle one, and
//! hears back how much it sent and how much it still holds. This module is that decision, pure:
//! the frame turns its answers into `ShareTasks` messages.
//!
//! Bounded: one request out per idle worker and per busy worker at a time, each busy worker
//! asked at most once per idle worker's dry spell, each request for at most
//! [`TASK_RAYS`] rays; a busy worker that answered that it holds nothing is not asked again
//! until it has more.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet};

/// Most rays one request moves (about 6.5 MiB of ray records): enough to keep an idle worker
/// busy for a pass or two, not so many that the busy one is left idle in turn.
pub const TASK_RAYS: u32 = 1 << 16;

/// A busy worker whose last answer said it holds fewer queued rays than this is not asked:
/// handing over a few rays costs more in messages than tracing them where they are.
pub const MIN_QUEUED: u64 = 1024;

/// One direction: ask `donor` to send work to `receiver`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Direction {
    pub donor: u32,
    pub receiver: u32,
}

/// See the module documentation.
///
/// Each decision costs O(log n) plus the receiver's own tried set, not a scan of the members:
/// with thousands of workers a scan per idle worker per answer took a hybrid frame's whole
/// time (issue 17). The donors that may be asked are kept ranked (`ranked`), in step with
/// every change to membership, `queued`, `idle` and `asked` (`refresh`).
#[derive(Clone, Debug, Default)]
pub struct TaskDirections {
    /// The frame's workers (`joined`, `lose`): only they are asked.
    members: BTreeSet<u32>,
    /// Workers that ran dry with nothing left to hand out, and the donors asked for each
    /// since.
    idle: BTreeMap<u32, BTreeSet<u32>>,
    /// Requests out, by donor: the receiver each was asked to serve.
    asked: BTreeMap<u32, u32>,
    /// Requests out, by receiver: `asked` the other way round (one request per receiver at a
    /// time, so one donor each).
    serving: BTreeMap<u32, u32>,
    /// Each worker's queued rays as it last said (a busy worker not heard from yet is
    /// presumed to hold work).
    queued: BTreeMap<u32, u64>,
    /// The donors that may be asked — members neither idle nor asked already that hold at
    /// least [`MIN_QUEUED`] rays or were not heard from — in the order they are asked: most
    /// queued first, then the lower key.
    ranked: BTreeSet<(Reverse<u64>, u32)>,
    /// The queued rays each donor in `ranked` is ranked by, to find its entry there.
    rank: BTreeMap<u32, u64>,
    /// Requests made.
    pub requests: u64,
    /// Rays the donors said they sent.
    pub rays_moved: u64,
}

impl TaskDirections {
    /// `key` joined the frame: it may be asked for work (one not heard from yet is presumed
    /// to hold some).
    pub fn joined(&mut self, key: u32) {
        self.members.insert(key);
        self.refresh(key);
    }

    /// `key` ran dry and there are no tiles left to hand out: the next request, if any busy
    /// worker may have work.
    pub fn ran_dry(&mut self, key: u32) -> Option<Direction> {
        self.queued.insert(key, 0);
        self.idle.entry(key).or_default().clear();
        self.refresh(key);
        // An idle worker is nobody's donor: a request out to it stays out, it will answer.
        if self.serving.contains_key(&key) {
            return None;
        }
        self.next_for(key)
    }

    /// `key` reported queued rays (it is not idle, or no longer).
    pub fn busy(&mut self, key: u32, queued: u64) {
        self.queued.insert(key, queued);
        if queued > 0 {
            self.idle.remove(&key);
        }
        self.refresh(key);
    }

    /// `donor` answered: it sent `rays` and still holds `queued`. Returns the next request:
    /// the same idle worker from another donor if this one sent nothing, and any idle
    /// worker's that waited for this donor to be free.
    pub fn answered(&mut self, donor: u32, rays: u64, queued: u64) -> Vec<Direction> {
        self.queued.insert(donor, queued);
        self.rays_moved += rays;
        let Some(receiver) = self.asked.remove(&donor) else {
            self.refresh(donor);
            return Vec::new();
        };
        self.serving.remove(&receiver);
        self.refresh(donor);
        if rays > 0 {
            // Work is on its way: the receiver reports again when it has run dry once more.
            self.idle.remove(&receiver);
            self.refresh(receiver);
        }
        // Every idle worker in key order, as long as some donor is left: asking only takes
        // donors out of `ranked` and adds to tried sets, so once it is empty nobody else
        // would be served, and the idle workers are not walked for nothing.
        let mut directions = Vec::new();
        let mut after = None;
        while !self.ranked.is_empty() {
            let next = match after {
                None => self.idle.keys().next(),
                Some(k) => self
                    .idle
                    .range((std::ops::Bound::Excluded(k), std::ops::Bound::Unbounded))
                    .next()
                    .map(|(k, _)| k),
            };
            let Some(&r) = next else {
                break;
            };
            after = Some(r);
            directions.extend(self.next_for(r));
        }
        directions
    }

    /// `key` left the frame: requests to it or for it are void.
    pub fn lose(&mut self, key: u32) {
        self.members.remove(&key);
        self.idle.remove(&key);
        self.queued.remove(&key);
        if let Some(receiver) = self.asked.remove(&key) {
            self.serving.remove(&receiver);
        }
        if let Some(donor) = self.serving.remove(&key) {
            self.asked.remove(&donor);
            self.refresh(donor);
        }
        self.refresh(key);
    }

    /// The idle worker `receiver`'s next donor, if it has no request out and some busy
    /// worker it has not asked yet may hold work: the one that last said it holds the most
    /// (one not heard from counts as holding the least that is still worth asking; ties: the
    /// lower key).
    fn next_for(&mut self, receiver: u32) -> Option<Direction> {
        if self.serving.contains_key(&receiver) {
            return None;
        }
        let tried = self.idle.get_mut(&receiver)?;
        // The receiver is idle, so not ranked; the donors it tried are skipped, so this walks
        // at most its tried set before it finds one.
        let donor = self
            .ranked
            .iter()
            .map(|&(_, d)| d)
            .find(|d| !tried.contains(d))?;
        tried.insert(donor);
        self.asked.insert(donor, receiver);
        self.serving.insert(receiver, donor);
        self.refresh(donor);
        self.requests += 1;
        Some(Direction { donor, receiver })
    }

    /// Brings `key`'s place in `ranked` in line with its membership, `idle`, `asked` and
    /// `queued`: called after any of them changes for `key`.
    fn refresh(&mut self, key: u32) {
        let now = Some(self.queued.get(&key).copied().unwrap_or(MIN_QUEUED)).filter(|&q| {
            q >= MIN_QUEUED
                && self.members.contains(&key)
                && !self.idle.contains_key(&key)
                && !self.asked.contains_key(&key)
        });
        let before = match now {
            Some(q) => self.rank.insert(key, q),
            None => self.rank.remove(&key),
        };
        if before == now {
            return;
        }
        if let Some(q) = before {
            self.ranked.remove(&(Reverse(q), key));
        }
        if let Some(q) = now {
            self.ranked.insert((Reverse(q), key));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn dir(donor: u32, receiver: u32) -> Direction {
        Direction { donor, receiver }
    }

    /// Directions for a frame of members `0..n`.
    fn with_members(n: u32) -> TaskDirections {
        let mut t = TaskDirections::default();
        for k in 0..n {
            t.joined(k);
        }
        t
    }

    #[test]
    fn a_dry_worker_is_served_by_the_busiest_worker_it_has_not_asked() {
        let mut t = with_members(4);
        // Nobody heard from: the lowest busy key is asked.
        assert_eq!(t.ran_dry(2), Some(dir(0, 2)));
        // 0 had nothing: the next busy worker is asked, never the receiver itself.
        assert_eq!(t.answered(0, 0, 10), vec![dir(1, 2)]);
        // 1 sent rays: the receiver is served; nobody else waits.
        assert_eq!(t.answered(1, 500, 90_000), vec![]);
        assert_eq!((t.requests, t.rays_moved), (2, 500));
        // Dry again: 1 said it holds the most, 0 too little to be worth asking.
        t.busy(3, 4_000);
        assert_eq!(t.ran_dry(2), Some(dir(1, 2)));
    }

    #[test]
    fn one_request_per_donor_and_per_receiver_at_a_time() {
        let mut t = with_members(3);
        assert_eq!(t.ran_dry(1), Some(dir(0, 1)));
        // 2 runs dry while 0 is asked: 0 is taken, 1 is idle, so nobody is left to ask.
        assert_eq!(t.ran_dry(2), None);
        // 1 reporting dry again does not ask a second donor while its request is out.
        assert_eq!(t.ran_dry(1), None);
        // 0 answers with nothing: 1 has nobody left to ask (2 is idle); 2 waited for 0, but
        // after 0's answer of 10 rays it is not worth asking.
        assert_eq!(t.answered(0, 0, 10), vec![]);
        // 0 reports more work: the idle ones may ask it again (2 never did).
        t.busy(0, 50_000);
        assert_eq!(
            t.answered(0, 0, 50_000),
            vec![],
            "an answer nobody asked for directs nobody"
        );
        assert_eq!(t.ran_dry(2), Some(dir(0, 2)));
    }

    #[test]
    fn a_lost_worker_is_neither_asked_nor_served() {
        let mut t = with_members(3);
        assert_eq!(t.ran_dry(2), Some(dir(0, 2)));
        t.lose(0);
        // The request to 0 is void: 2 may be served by 1 when it runs dry again.
        assert_eq!(t.ran_dry(2), Some(dir(1, 2)));
        t.lose(2);
        assert_eq!(t.answered(1, 100, 100_000), vec![]);
    }

    #[test]
    fn a_worker_that_joins_mid_frame_is_asked_from_the_next_answer() {
        let mut t = with_members(3);
        assert_eq!(t.ran_dry(0), Some(dir(1, 0)));
        assert_eq!(t.ran_dry(2), None);
        t.joined(5);
        // 1 had too little: 0 asks the newcomer; 2 has nobody left (5 is taken).
        assert_eq!(t.answered(1, 0, 10), vec![dir(5, 0)]);
    }

    #[test]
    fn an_answer_with_no_donor_free_directs_nobody() {
        // Every worker but 0 holds too little to be asked, and all but one of them ran dry
        // while 0 was asked: 0's answer of nothing leaves no donor, so nobody is directed
        // (and the idle workers are not walked for it).
        let mut t = with_members(4_096);
        for k in 1..4_096 {
            t.busy(k, 10);
        }
        assert_eq!(t.ran_dry(1), Some(dir(0, 1)));
        for k in 2..4_095 {
            assert_eq!(t.ran_dry(k), None);
        }
        assert_eq!(t.answered(0, 0, 0), vec![]);
        assert!(t.ranked.is_empty());
        // 4,095 reports more: it is ranked again, and the next worker to run dry asks it.
        t.busy(4_095, 5_000);
        assert_eq!(t.ran_dry(0), Some(dir(4_095, 0)));
    }

    /// The decision as it was before the donor index (issue 17), kept as the reference the
    /// index must agree with: it scans every member for every idle worker.
    #[derive(Default)]
    struct Scanning {
        idle: BTreeMap<u32, BTreeSet<u32>>,
        asked: BTreeMap<u32, u32>,
        queued: BTreeMap<u32, u64>,
        requests: u64,
        rays_moved: u64,
    }

    impl Scanning {
        fn ran_dry(&mut self, key: u32, members: &BTreeSet<u32>) -> Option<Direction> {
            self.queued.insert(key, 0);
            self.idle.entry(key).or_default().clear();
            if self.asked.values().any(|&r| r == key) {
                return None;
            }
            self.next_for(key, members)
        }

        fn busy(&mut self, key: u32, queued: u64) {
            self.queued.insert(key, queued);
            if queued > 0 {
                self.idle.remove(&key);
            }
        }

        fn answered(
            &mut self,
            donor: u32,
            rays: u64,
            queued: u64,
            members: &BTreeSet<u32>,
        ) -> Vec<Direction> {
            self.queued.insert(donor, queued);
            self.rays_moved += rays;
            let Some(receiver) = self.asked.remove(&donor) else {
                return Vec::new();
            };
            if rays > 0 {
                self.idle.remove(&receiver);
            }
            let waiting: Vec<u32> = self.idle.keys().copied().collect();
            waiting
                .into_iter()
                .filter_map(|r| self.next_for(r, members))
                .collect()
        }

        fn lose(&mut self, key: u32) {
            self.idle.remove(&key);
            self.queued.remove(&key);
            self.asked.remove(&key);
            self.asked.retain(|_, r| *r != key);
        }

        fn next_for(&mut self, receiver: u32, members: &BTreeSet<u32>) -> Option<Direction> {
            if self.asked.values().any(|&r| r == receiver) {
                return None;
            }
            let tried = self.idle.get(&receiver)?;
            let donor = members
                .iter()
                .copied()
                .filter(|d| {
                    *d != receiver
                        && !self.idle.contains_key(d)
                        && !self.asked.contains_key(d)
                        && !tried.contains(d)
                })
                .map(|d| (d, self.queued.get(&d).copied().unwrap_or(MIN_QUEUED)))
                .filter(|&(_, q)| q >= MIN_QUEUED)
                .max_by_key(|&(d, q)| (q, std::cmp::Reverse(d)))?
                .0;
            self.idle.entry(receiver).or_default().insert(donor);
            self.asked.insert(donor, receiver);
            self.requests += 1;
            Some(Direction { donor, receiver })
        }
    }

    /// What happens to the frame's workers, as the frame tells `TaskDirections`.
    #[derive(Clone, Debug)]
    enum Event {
        Joined(u32),
        RanDry(u32),
        Busy(u32, u64),
        Answered(u32, u64, u64),
        Lose(u32),
    }

    /// Queued rays around [`MIN_QUEUED`] and a few repeated values, so ties and the
    /// threshold are hit often.
    fn queued() -> impl Strategy<Value = u64> {
        prop_oneof![
            Just(0),
            Just(10),
            Just(MIN_QUEUED - 1),
            Just(MIN_QUEUED),
            Just(MIN_QUEUED + 1),
            Just(50_000),
            Just(90_000),
            0..200_000u64,
        ]
    }

    /// One event about one of workers `0..keys`, members or not (the index must agree with
    /// the scan whatever it is told).
    fn event(keys: u32) -> impl Strategy<Value = Event> {
        let key = 0..keys;
        prop_oneof![
            1 => key.clone().prop_map(Event::Joined),
            4 => key.clone().prop_map(Event::RanDry),
            3 => (key.clone(), queued()).prop_map(|(k, q)| Event::Busy(k, q)),
            4 => (key.clone(), prop_oneof![Just(0), 1..70_000u64], queued())
                .prop_map(|(k, r, q)| Event::Answered(k, r, q)),
            1 => key.prop_map(Event::Lose),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2_000))]

        /// The index gives exactly the directions the scan gave, whatever happens in
        /// whatever order, and its ranking always matches its state.
        #[test]
        fn the_donor_index_directs_as_the_scan_did(
            start in 0..12u32,
            events in prop::collection::vec(event(12), 0..200),
        ) {
            let mut members: BTreeSet<u32> = (0..start).collect();
            let mut index = with_members(start);
            let mut scan = Scanning::default();
            for e in events {
                match e {
                    Event::Joined(k) => {
                        members.insert(k);
                        index.joined(k);
                    }
                    Event::RanDry(k) => {
                        prop_assert_eq!(index.ran_dry(k), scan.ran_dry(k, &members), "{:?}", e);
                    }
                    Event::Busy(k, q) => {
                        index.busy(k, q);
                        scan.busy(k, q);
                    }
                    Event::Answered(k, r, q) => {
                        prop_assert_eq!(
                            index.answered(k, r, q),
                            scan.answered(k, r, q, &members),
                            "{:?}",
                            e
                        );
                    }
                    Event::Lose(k) => {
                        members.remove(&k);
                        index.lose(k);
                        scan.lose(k);
                    }
                }
                prop_assert_eq!(
                    (index.requests, index.rays_moved),
                    (scan.requests, scan.rays_moved)
                );
                prop_assert_eq!(&index.asked, &scan.asked);
                let serving: BTreeMap<u32, u32> =
                    index.asked.iter().map(|(&d, &r)| (r, d)).collect();
                prop_assert_eq!(&index.serving, &serving);
                let ranked: BTreeSet<(Reverse<u64>, u32)> = members
                    .iter()
                    .copied()
                    .filter(|d| !index.idle.contains_key(d) && !index.asked.contains_key(d))
                    .map(|d| (Reverse(index.queued.get(&d).copied().unwrap_or(MIN_QUEUED)), d))
                    .filter(|&(Reverse(q), _)| q >= MIN_QUEUED)
                    .collect();
                prop_assert_eq!(&index.ranked, &ranked);
            }
        }
    }
}
