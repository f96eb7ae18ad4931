//! Dealing a frame's tiles to workers: fixed shares (the image-plane and dynamic schedules,
//! and the tiles re-dealt after a worker is lost) and demand-driven hand-outs (hybrid: a first
//! batch each, the rest to whoever runs dry first).

use std::collections::VecDeque;

/// The `i`-th of `n` strided shares of `tiles`: every `n`-th, from the `i`-th.
pub fn strided_share(tiles: &[u32], i: usize, n: usize) -> Vec<u32> {
    tiles.iter().copied().skip(i).step_by(n.max(1)).collect()
}

/// Tiles not yet handed out, and how many go out at a time.
#[derive(Clone, Debug)]
pub struct HandOuts {
    pending: VecDeque<u32>,
    batch: usize,
}

impl Default for HandOuts {
    fn default() -> Self {
        HandOuts {
            pending: VecDeque::new(),
            batch: 1,
        }
    }
}

impl HandOuts {
    /// All `count` tiles of a frame for `workers` workers: batches of a quarter of a fair
    /// share, so that four hand-outs each even out what the workers' speeds make uneven.
    pub fn new(count: u32, workers: usize) -> Self {
        HandOuts {
            pending: (0..count).collect(),
            batch: (count as usize / (workers.max(1) * 4)).max(1),
        }
    }

    /// Replaces the tiles still to hand out (those re-dealt after a loss), same batch size.
    pub fn refill(&mut self, tiles: Vec<u32>) {
        self.pending = tiles.into();
    }

    /// Whether every tile has been handed out.
    pub fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }

    /// The next batch (empty once all are out).
    pub fn next_batch(&mut self) -> Vec<u32> {
        let n = self.batch.min(self.pending.len());
        self.pending.drain(..n).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strided_shares_cover_every_tile_once() {
        let tiles: Vec<u32> = (10..21).collect();
        let mut all: Vec<u32> = (0..3).flat_map(|i| strided_share(&tiles, i, 3)).collect();
        assert_eq!(strided_share(&tiles, 1, 3), [11, 14, 17, 20]);
        all.sort();
        assert_eq!(all, tiles);
    }

    #[test]
    fn hand_outs_come_in_quarter_shares_until_none_are_left() {
        let mut h = HandOuts::new(20, 2);
        assert_eq!(h.next_batch(), [0, 1]);
        let rest: Vec<u32> = std::iter::from_fn(|| Some(h.next_batch()).filter(|b| !b.is_empty()))
            .flatten()
            .collect();
        assert_eq!(rest, (2..20).collect::<Vec<_>>());
        assert!(h.is_empty());
        h.refill(vec![7, 3, 5]);
        assert_eq!(h.next_batch(), [7, 3]);
        assert_eq!(h.next_batch(), [5]);
    }

    #[test]
    fn a_tiny_frame_still_hands_out_one_tile_at_a_time() {
        let mut h = HandOuts::new(3, 8);
        assert_eq!(h.next_batch(), [0]);
    }
}
