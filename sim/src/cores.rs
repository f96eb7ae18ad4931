//! Cores shared by every simulated worker (`--cores N`), sliced between whatever wants them
//! as an operating system's scheduler slices them: processor sharing. While k computations
//! (passes) and m short handlings (bundles and finished passes on a worker's shell) want the
//! N cores, each advances at min(1, N / (k + m)) of a core, so a long pass cannot hold a core
//! that another worker's pass waits for, every pass slows while bundles are handled, and
//! handlings slow too when the cores are saturated (where a cluster's processes spend more
//! on their messages than on tracing, as nine processes on two cores do, that is most of a
//! frame's tail: `perf` shows the cores busy throughout it, tracing a fifth of that).
//!
//! A handling's rate is fixed at its start: its share then, counting itself, which sets its
//! end at once (its shell's next handling follows it, so the end must be known); a
//! computation's end moves whenever something starts or ends, so the world asks
//! [`SharedCores::next_check`] after every change and calls [`SharedCores::check`] then,
//! ignoring checks an epoch has passed by. Arithmetic is in `f64` core-nanoseconds in one
//! order, so a run repeats bit for bit.

use std::collections::BTreeMap;
use std::time::Duration;

use rayfarm_machine::Time;

use crate::net::NodeId;

/// Work left below this many core-nanoseconds is done (rounding of the end times).
const DONE_BELOW: f64 = 1.0;

/// A computation on the shared cores.
struct Computation<E> {
    node: NodeId,
    /// Core-nanoseconds still to compute.
    left: f64,
    /// What happens when it is done.
    done: E,
}

/// N cores shared by every simulated worker; `E` is what a computation's end sets off.
pub struct SharedCores<E> {
    cores: u32,
    /// The time up to which every computation's work left is brought.
    at: Time,
    /// Computations by the order they started in.
    computing: BTreeMap<u64, Computation<E>>,
    next_id: u64,
    /// Handlings as (start, end): each counts as one more contender while it runs.
    handling: Vec<(Time, Time)>,
    /// Bumped by every change: a check of an older epoch is stale.
    epoch: u64,
}

impl<E> SharedCores<E> {
    /// `cores` cores (at least one), nothing on them.
    pub fn new(cores: u32) -> Self {
        SharedCores {
            cores: cores.max(1),
            at: Time(0),
            computing: BTreeMap::new(),
            next_id: 0,
            handling: Vec::new(),
            epoch: 0,
        }
    }

    /// Starts computing `work` at `now` (not before the last change); `done` comes back from
    /// [`SharedCores::check`] when it is finished.
    pub fn compute(&mut self, now: Time, node: NodeId, work: Duration, done: E) {
        self.advance(now);
        self.computing.insert(
            self.next_id,
            Computation {
                node,
                left: work.as_nanos() as f64,
                done,
            },
        );
        self.next_id += 1;
        self.epoch += 1;
    }

    /// A handling of `work` that its shell takes up at `start` (now or later): it runs at
    /// the share of a core it would have then, itself one more contender, so on saturated
    /// cores it takes longer than `work`; its end is returned, and it shares the cores with
    /// the computations meanwhile.
    pub fn handle(&mut self, now: Time, start: Time, work: Duration) -> Time {
        self.advance(now);
        let start = start.max(now);
        let contenders = self.computing.len() + self.handlings_at(start) + 1;
        let slowdown = (contenders as f64 / f64::from(self.cores)).max(1.0);
        let end = start + Duration::from_nanos((work.as_nanos() as f64 * slowdown).ceil() as u64);
        if end > start {
            self.handling.push((start, end));
            self.epoch += 1;
        }
        end
    }

    /// Drops the computations of `node` (its process died): they give their share back.
    pub fn forget(&mut self, now: Time, node: NodeId) {
        self.advance(now);
        let before = self.computing.len();
        self.computing.retain(|_, c| c.node != node);
        if self.computing.len() != before {
            self.epoch += 1;
        }
    }

    /// When the next check is due and the epoch it is for: the earliest end of a computation
    /// at today's shares, or the next start or end of a handling, whichever is sooner.
    pub fn next_check(&self) -> Option<(Time, u64)> {
        let share = self.share(self.at);
        let first_end = self
            .computing
            .values()
            .map(|c| c.left)
            .min_by(f64::total_cmp)
            .map(|left| self.at + Duration::from_nanos((left / share).ceil().max(1.0) as u64));
        let boundary = self.next_boundary();
        match (first_end, boundary) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
        .map(|t| (t, self.epoch))
    }

    /// At a check due at `now` for `epoch`: the computations done by now, in the order they
    /// started, or nothing when the check is stale. Ask [`SharedCores::next_check`] again
    /// after it.
    pub fn check(&mut self, now: Time, epoch: u64) -> Option<Vec<E>> {
        if epoch != self.epoch {
            return None;
        }
        self.advance(now);
        let done: Vec<u64> = self
            .computing
            .iter()
            .filter(|(_, c)| c.left < DONE_BELOW)
            .map(|(&id, _)| id)
            .collect();
        self.epoch += 1;
        Some(
            done.into_iter()
                .filter_map(|id| self.computing.remove(&id))
                .map(|c| c.done)
                .collect(),
        )
    }

    /// Each computation's share of a core at `t`: all of one while there are no more
    /// contenders than cores.
    fn share(&self, t: Time) -> f64 {
        let contenders = self.computing.len() + self.handlings_at(t);
        if contenders <= self.cores as usize {
            1.0
        } else {
            f64::from(self.cores) / contenders as f64
        }
    }

    /// Handlings running at `t`.
    fn handlings_at(&self, t: Time) -> usize {
        self.handling
            .iter()
            .filter(|&&(start, end)| start <= t && t < end)
            .count()
    }

    /// The first start or end of a handling after `self.at`.
    fn next_boundary(&self) -> Option<Time> {
        self.handling
            .iter()
            .flat_map(|&(start, end)| [start, end])
            .filter(|&t| t > self.at)
            .min()
    }

    /// Brings every computation's work left to `now`, share by share between the handlings'
    /// starts and ends.
    fn advance(&mut self, now: Time) {
        while self.at < now {
            let until = self.next_boundary().map_or(now, |b| b.min(now));
            let share = self.share(self.at);
            let done = until.since(self.at).as_nanos() as f64 * share;
            for c in self.computing.values_mut() {
                c.left -= done;
            }
            self.at = until;
        }
        self.handling.retain(|&(_, end)| end > now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Asserts that `t` is `n` ms after time zero, to within the microsecond the
    /// core-nanosecond arithmetic rounds to.
    fn assert_at(t: Time, n: u64) {
        assert!(
            t.since(Time(0)).abs_diff(ms(n)) < Duration::from_micros(1),
            "{t:?}"
        );
    }

    /// Runs the cores' checks until nothing is left; the ends in order.
    fn run(cores: &mut SharedCores<&'static str>) -> Vec<(Time, &'static str)> {
        let mut ends = Vec::new();
        while let Some((t, epoch)) = cores.next_check() {
            if let Some(done) = cores.check(t, epoch) {
                ends.extend(done.into_iter().map(|e| (t, e)));
            }
        }
        ends
    }

    #[test]
    fn computations_share_the_cores_evenly_when_there_are_more_of_them() {
        // Two cores, three passes of 30 ms each started together: each gets 2/3 of a core,
        // so all end at 45 ms (first come, first served would end two at 30 and one at 60).
        let mut cores = SharedCores::new(2);
        for name in ["a", "b", "c"] {
            cores.compute(Time(0), 1, ms(30), name);
        }
        let ends = run(&mut cores);
        assert_eq!(ends.len(), 3);
        for (t, _) in &ends {
            assert_at(*t, 45);
        }
    }

    #[test]
    fn a_long_computation_does_not_hold_a_core_a_short_one_waits_for() {
        // One core: a 100 ms pass, then 10 ms later a 10 ms one. Sliced, the short one ends
        // at 30 ms (10 + 2 x 10) and the long one at 110 ms.
        let mut cores = SharedCores::new(1);
        cores.compute(Time(0), 1, ms(100), "long");
        let (t, epoch) = cores.next_check().unwrap();
        assert_eq!(t, Time(0) + ms(100));
        cores.compute(Time(0) + ms(10), 2, ms(10), "short");
        assert!(
            cores.check(t, epoch).is_none(),
            "a stale check does nothing"
        );
        let ends = run(&mut cores);
        let names: Vec<_> = ends.iter().map(|e| e.1).collect();
        assert_eq!(names, ["short", "long"]);
        assert_at(ends[0].0, 30);
        assert_at(ends[1].0, 110);
    }

    #[test]
    fn a_handling_on_a_free_core_ends_on_its_own_time_and_slows_the_computations_meanwhile() {
        // Two cores: a 20 ms pass; a 10 ms handling from 5 ms has a core of its own (two
        // contenders on two cores), ends at 15 ms, and leaves the pass its whole core.
        let mut cores = SharedCores::new(2);
        cores.compute(Time(0), 1, ms(20), "pass");
        let end = cores.handle(Time(0), Time(0) + ms(5), ms(10));
        assert_eq!(end, Time(0) + ms(15));
        let ends = run(&mut cores);
        assert_at(ends[0].0, 20);
        // Two passes on the two cores: the handling makes three contenders, so each of the
        // three runs at two thirds of a core while it lasts: it ends after 15 ms, not 10.
        let mut cores = SharedCores::new(2);
        cores.compute(Time(0), 1, ms(20), "a");
        cores.compute(Time(0), 2, ms(20), "b");
        let end = cores.handle(Time(0), Time(0) + ms(5), ms(10));
        assert_eq!(end, Time(0) + ms(20));
        // Each pass: 5 ms alone, 15 ms at 2/3 (10 ms of work), then 5 ms alone: 25 ms.
        let ends = run(&mut cores);
        assert_eq!(ends.len(), 2);
        for (t, _) in ends {
            assert_at(t, 25);
        }
    }

    #[test]
    fn a_handling_on_a_saturated_core_takes_its_share_too() {
        // One core: a 20 ms pass; a 10 ms handling from 5 ms gets half the core, so it ends
        // at 25 ms, and the pass, at half a core meanwhile, ends at 30 ms.
        let mut cores = SharedCores::new(1);
        cores.compute(Time(0), 1, ms(20), "pass");
        let end = cores.handle(Time(0), Time(0) + ms(5), ms(10));
        assert_eq!(end, Time(0) + ms(25));
        let ends = run(&mut cores);
        assert_eq!(ends.len(), 1);
        assert_at(ends[0].0, 30);
    }

    #[test]
    fn a_dead_workers_computation_gives_its_share_back() {
        let mut cores = SharedCores::new(1);
        cores.compute(Time(0), 1, ms(10), "kept");
        cores.compute(Time(0), 2, ms(10), "dead");
        cores.forget(Time(0) + ms(4), 2);
        // 4 ms at half a core (2 ms done), then 8 ms alone.
        let ends = run(&mut cores);
        assert_eq!(ends.len(), 1);
        assert_eq!(ends[0].1, "kept");
        assert_at(ends[0].0, 12);
    }
}
