//! The event heap: events ordered by virtual time, ties broken by the order they were
//! scheduled in (a sequence number), so two runs of one seed pop the same events in the same
//! order.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use rayfarm_machine::Time;

/// A heap of `E`s by (time, sequence number). The heap orders small keys that name a slot
/// where the event waits: sifting whole events (a finished pass carries its output) through
/// the heap's levels was a twentieth of a 1,024-worker run's time in `memmove`.
pub struct EventHeap<E> {
    heap: BinaryHeap<Reverse<(Time, u64, u32)>>,
    /// Events by slot; `None` for a free slot.
    slots: Vec<Option<E>>,
    /// Slots free for the next events.
    free: Vec<u32>,
    seq: u64,
}

impl<E> Default for EventHeap<E> {
    fn default() -> Self {
        EventHeap {
            heap: BinaryHeap::new(),
            slots: Vec::new(),
            free: Vec::new(),
            seq: 0,
        }
    }
}

impl<E> EventHeap<E> {
    /// Schedules `event` at `at`.
    pub fn push(&mut self, at: Time, event: E) {
        self.seq += 1;
        let slot = match self.free.pop() {
            Some(i) => {
                self.slots[i as usize] = Some(event);
                i
            }
            None => {
                self.slots.push(Some(event));
                // More than 4 billion events waiting at once would not fit in memory anyway.
                u32::try_from(self.slots.len() - 1).expect("fewer than 2^32 events waiting")
            }
        };
        self.heap.push(Reverse((at, self.seq, slot)));
    }

    /// The earliest event and its time.
    pub fn pop(&mut self) -> Option<(Time, E)> {
        // (time, sequence number) is unique, so the slot never decides the order.
        let Reverse((t, _, slot)) = self.heap.pop()?;
        let event = self.slots[slot as usize].take()?;
        self.free.push(slot);
        Some((t, event))
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
        // Slots are reused, and the order still follows time then push order.
        h.push(Time(9), "b");
        h.push(Time(8), "a");
        h.push(Time(9), "c");
        let order: Vec<_> = std::iter::from_fn(|| h.pop().map(|(_, e)| e)).collect();
        assert_eq!(order, ["a", "b", "c"]);
        assert_eq!(
            h.slots.len(),
            4,
            "the slots of the first four events serve again"
        );
    }
}
