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
#[derive(Clone, Debug, Default)]
pub struct TaskDirections {
    /// Workers that ran dry with nothing left to hand out, and the donors asked for each
    /// since.
    idle: BTreeMap<u32, BTreeSet<u32>>,
    /// Requests out, by donor: the receiver each was asked to serve.
    asked: BTreeMap<u32, u32>,
    /// Each worker's queued rays as it last said (a busy worker not heard from yet is
    /// presumed to hold work).
    queued: BTreeMap<u32, u64>,
    /// Requests made.
    pub requests: u64,
    /// Rays the donors said they sent.
    pub rays_moved: u64,
}

impl TaskDirections {
    /// `key` ran dry and there are no tiles left to hand out: the next request, if any busy
    /// worker may have work. `members` are the frame's workers.
    pub fn ran_dry(&mut self, key: u32, members: &BTreeSet<u32>) -> Option<Direction> {
        self.queued.insert(key, 0);
        self.idle.entry(key).or_default().clear();
        // An idle worker is nobody's donor: a request out to it stays out, it will answer.
        if self.asked.values().any(|&r| r == key) {
            return None;
        }
        self.next_for(key, members)
    }

    /// `key` reported queued rays (it is not idle, or no longer).
    pub fn busy(&mut self, key: u32, queued: u64) {
        self.queued.insert(key, queued);
        if queued > 0 {
            self.idle.remove(&key);
        }
    }

    /// `donor` answered: it sent `rays` and still holds `queued`. Returns the next request:
    /// the same idle worker from another donor if this one sent nothing, and any idle
    /// worker's that waited for this donor to be free.
    pub fn answered(
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
            // Work is on its way: the receiver reports again when it has run dry once more.
            self.idle.remove(&receiver);
        }
        let waiting: Vec<u32> = self.idle.keys().copied().collect();
        waiting
            .into_iter()
            .filter_map(|r| self.next_for(r, members))
            .collect()
    }

    /// `key` left the frame: requests to it or for it are void.
    pub fn lose(&mut self, key: u32) {
        self.idle.remove(&key);
        self.queued.remove(&key);
        self.asked.remove(&key);
        self.asked.retain(|_, r| *r != key);
    }

    /// The idle worker `receiver`'s next donor, if it has no request out and some busy
    /// worker it has not asked yet may hold work: the one that last said it holds the most
    /// (one not heard from counts as holding the least that is still worth asking; ties: the
    /// lower key).
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

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(donor: u32, receiver: u32) -> Direction {
        Direction { donor, receiver }
    }

    fn members(n: u32) -> BTreeSet<u32> {
        (0..n).collect()
    }

    #[test]
    fn a_dry_worker_is_served_by_the_busiest_worker_it_has_not_asked() {
        let m = members(4);
        let mut t = TaskDirections::default();
        // Nobody heard from: the lowest busy key is asked.
        assert_eq!(t.ran_dry(2, &m), Some(dir(0, 2)));
        // 0 had nothing: the next busy worker is asked, never the receiver itself.
        assert_eq!(t.answered(0, 0, 10, &m), vec![dir(1, 2)]);
        // 1 sent rays: the receiver is served; nobody else waits.
        assert_eq!(t.answered(1, 500, 90_000, &m), vec![]);
        assert_eq!((t.requests, t.rays_moved), (2, 500));
        // Dry again: 1 said it holds the most, 0 too little to be worth asking.
        t.busy(3, 4_000);
        assert_eq!(t.ran_dry(2, &m), Some(dir(1, 2)));
    }

    #[test]
    fn one_request_per_donor_and_per_receiver_at_a_time() {
        let m = members(3);
        let mut t = TaskDirections::default();
        assert_eq!(t.ran_dry(1, &m), Some(dir(0, 1)));
        // 2 runs dry while 0 is asked: 0 is taken, 1 is idle, so nobody is left to ask.
        assert_eq!(t.ran_dry(2, &m), None);
        // 1 reporting dry again does not ask a second donor while its request is out.
        assert_eq!(t.ran_dry(1, &m), None);
        // 0 answers with nothing: 1 has nobody left to ask (2 is idle); 2 waited for 0, but
        // after 0's answer of 10 rays it is not worth asking.
        assert_eq!(t.answered(0, 0, 10, &m), vec![]);
        // 0 reports more work: the idle ones may ask it again (2 never did).
        t.busy(0, 50_000);
        assert_eq!(
            t.answered(0, 0, 50_000, &m),
            vec![],
            "an answer nobody asked for directs nobody"
        );
        assert_eq!(t.ran_dry(2, &m), Some(dir(0, 2)));
    }

    #[test]
    fn a_lost_worker_is_neither_asked_nor_served() {
        let m = members(3);
        let mut t = TaskDirections::default();
        assert_eq!(t.ran_dry(2, &m), Some(dir(0, 2)));
        t.lose(0);
        let m: BTreeSet<u32> = [1, 2].into();
        // The request to 0 is void: 2 may be served by 1 when it runs dry again.
        assert_eq!(t.ran_dry(2, &m), Some(dir(1, 2)));
        t.lose(2);
        assert_eq!(t.answered(1, 100, 100_000, &m), vec![]);
    }
}
