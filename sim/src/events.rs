//! The event heap: events ordered by virtual time, ties broken by the order they were
//! scheduled in (a sequence number), so two runs of one seed pop the same events in the same
//! order.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use rayfarm_machine::Time;

/// A heap of `E`s by (time, sequence number).
pub struct EventHeap<E> {
    heap: BinaryHeap<Reverse<(Time, u64, Slot<E>)>>,
    seq: u64,
}

/// An event in the heap; compared by nothing (time and sequence number decide).
struct Slot<E>(E);

impl<E> PartialEq for Slot<E> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}
impl<E> Eq for Slot<E> {}
impl<E> PartialOrd for Slot<E> {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl<E> Ord for Slot<E> {
    fn cmp(&self, _: &Self) -> std::cmp::Ordering {
        std::cmp::Ordering::Equal
    }
}

impl<E> Default for EventHeap<E> {
    fn default() -> Self {
        EventHeap {
            heap: BinaryHeap::new(),
            seq: 0,
        }
    }
}

impl<E> EventHeap<E> {
    /// Schedules `event` at `at`.
    pub fn push(&mut self, at: Time, event: E) {
        self.seq += 1;
        self.heap.push(Reverse((at, self.seq, Slot(event))));
    }

    /// The earliest event and its time.
    pub fn pop(&mut self) -> Option<(Time, E)> {
        self.heap.pop().map(|Reverse((t, _, Slot(e)))| (t, e))
    }

    /// Events scheduled so far.
    pub fn scheduled(&self) -> u64 {
        self.seq
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_pop_by_time_then_by_the_order_they_were_pushed() {
        let mut h = EventHeap::default();
        h.push(Time(5), "late");
        h.push(Time(1), "first");
        h.push(Time(1), "second");
        h.push(Time(3), "middle");
        let order: Vec<_> = std::iter::from_fn(|| h.pop().map(|(_, e)| e)).collect();
        assert_eq!(order, ["first", "second", "middle", "late"]);
    }
}
