//! Where the groups of the rays waiting for verdicts live: slots in chunks of fixed size,
//! addressed by group id. A chunk never moves once made, so adding groups never copies those
//! held: one vector of groups, doubling under a wave of a million new rays, copied and
//! page-faulted hundreds of MiB on a predictive worker's event loop (perf, README
//! "Benchmarks").

/// Slots per chunk (as a power of two, so an id splits into chunk and place by shifts).
const CHUNK_BITS: u32 = 12;
const CHUNK: usize = 1 << CHUNK_BITS;

/// Slots of `T`, each empty or holding one, addressed by the id [`Slots::push`] gave.
pub(super) struct Slots<T> {
    chunks: Vec<Box<[Option<T>]>>,
    /// Slots made so far: ids below this exist.
    len: usize,
}

impl<T> Default for Slots<T> {
    fn default() -> Self {
        Slots {
            chunks: Vec::new(),
            len: 0,
        }
    }
}

impl<T> Slots<T> {
    /// Slots made so far (empty or not).
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Slot `id`, if made.
    pub(super) fn get_mut(&mut self, id: u32) -> Option<&mut Option<T>> {
        let id = id as usize;
        if id >= self.len {
            return None;
        }
        self.chunks
            .get_mut(id >> CHUNK_BITS)
            .and_then(|c| c.get_mut(id & (CHUNK - 1)))
    }

    /// Makes a new slot holding `value`; returns its id.
    pub(super) fn push(&mut self, value: T) -> u32 {
        let id = self.len;
        if id & (CHUNK - 1) == 0 && id >> CHUNK_BITS == self.chunks.len() {
            self.chunks.push((0..CHUNK).map(|_| None).collect());
        }
        self.len += 1;
        let chunk = &mut self.chunks[id >> CHUNK_BITS];
        chunk[id & (CHUNK - 1)] = Some(value);
        id as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_count_up_across_chunks_and_address_their_values() {
        let mut slots = Slots::default();
        let n = 3 * CHUNK + 5;
        for i in 0..n {
            assert_eq!(slots.push(i * 10), i as u32);
        }
        assert_eq!(slots.len(), n);
        for i in [0, CHUNK - 1, CHUNK, 2 * CHUNK + 7, n - 1] {
            assert_eq!(
                slots.get_mut(i as u32).copied(),
                Some(Some(i * 10)),
                "id {i}"
            );
        }
        *slots.get_mut(CHUNK as u32).unwrap() = None;
        assert_eq!(slots.get_mut(CHUNK as u32).copied(), Some(None));
        assert!(slots.get_mut(n as u32).is_none(), "not made yet");
        assert!(slots.get_mut(u32::MAX).is_none());
    }
}
